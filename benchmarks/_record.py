"""The machine-readable record of a benchmark run: `python -m benchmarks AREA --json DIR` writes
``DIR/AREA.json``, which `python -m benchmarks render-results` turns into ``benchmarks/RESULTS.md``.

A record is a JSON object::

    {"schema": 1, "area": "sim", "command": "python -m benchmarks sim --quick --json ...",
     "date": "2026-11-28", "duration_s": 412.0,
     "machine": {"cpu": ..., "cores": 2, "platform": "cpu", "gpu": null, "devices": [...], "xla_flags": ...},
     "versions": {"python": ..., "jax": ..., "jaxlib": ..., "mujoco": ..., "pin": ..., "crocoddyl": null,
                  "rsmooth": {"commit": "735ee59...", "modified": true}},
     "options": {"repeats": 30, "quick": false},
     "results": {...}}

``results`` is the area's own measurements, times in seconds (see `benchmarks.results_page` for
what each area holds); numbers that were not measured are null (NaN is not JSON). This module
reads the machine without importing JAX where it can (`jax.devices()` only when JAX is already
imported), so that it stays cheap for the tests.
"""

from __future__ import annotations

import datetime
import json
import math
import os
import pathlib
import platform
import shlex
import subprocess
import sys
import time
from importlib import metadata
from typing import Any, Callable, Optional

SCHEMA = 1
# The packages whose versions a record names (None where not installed).
PACKAGES = ("jax", "jaxlib", "numpy", "optax", "equinox", "mujoco", "mujoco-mjx", "pin", "crocoddyl", "trimesh", "example-robot-data")
REQUIRED_KEYS = ("schema", "area", "command", "date", "duration_s", "machine", "versions", "options", "results")
ROOT = pathlib.Path(__file__).resolve().parent.parent


def cpu_model() -> str:
    """The CPU's model name from /proc/cpuinfo (else what `platform` says)."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine_info() -> dict:
    """The machine: CPU model and cores, and the JAX devices (a GPU's name) when JAX is loaded."""
    info: dict[str, Any] = {
        "cpu": cpu_model(),
        "cores": os.cpu_count(),
        "system": f"{platform.system()} {platform.machine()}",
        "platform": None,
        "devices": [],
        "gpu": None,
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
    }
    if "jax" in sys.modules:
        import jax

        devices = jax.devices()
        info["platform"] = devices[0].platform
        info["devices"] = [f"{d.platform}: {d.device_kind}" for d in devices]
        accelerators = [d.device_kind for d in devices if d.platform != "cpu"]
        info["gpu"] = f"{len(accelerators)} x {accelerators[0]}" if accelerators else None
    return info


def git_commit() -> dict:
    """rsmooth's commit and whether the working tree differed from it (read-only git calls)."""

    def git(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True, timeout=30)

    try:
        head = git("rev-parse", "HEAD")
        if head.returncode != 0:
            return {"commit": None, "modified": None}
        modified = git("diff-index", "--quiet", "HEAD", "--").returncode != 0
        return {"commit": head.stdout.strip(), "modified": modified}
    except (OSError, subprocess.SubprocessError):
        return {"commit": None, "modified": None}


def versions() -> dict:
    """Python, the packages of :data:`PACKAGES` (None where absent) and rsmooth's commit."""
    found: dict[str, Any] = {"python": platform.python_version()}
    for name in PACKAGES:
        try:
            found[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            found[name] = None
    found["rsmooth"] = git_commit()
    return found


def command_line(argv: Optional[list[str]] = None) -> str:
    """The command as typed: `python -m benchmarks ...` for this package's entry point."""
    argv = list(sys.argv if argv is None else argv)
    program = pathlib.Path(argv[0]).resolve() if argv else None
    if program is not None and program.parent == pathlib.Path(__file__).resolve().parent:
        module = "benchmarks" if program.name == "__main__.py" else f"benchmarks.{program.stem}"
        head = ["python", "-m", module]
    else:
        head = ["python", pathlib.Path(argv[0]).name] if argv else ["python"]
    return " ".join(head + [shlex.quote(_relative(a)) for a in argv[1:]])


def _relative(argument: str) -> str:
    """A path inside the repository relative to its root, another absolute path by its last
    component (``.../NAME``): no machine path in a record."""
    path = pathlib.Path(argument)
    if path.is_absolute():
        try:
            return str(path.resolve().relative_to(ROOT))
        except ValueError:
            return f".../{path.name}"
    return argument


def jsonable(value: Any) -> Any:
    """`value` with NaN and infinities as None, tuples as lists, numpy scalars and arrays as
    Python numbers and lists, non-string keys as strings, and the repository's own path cut
    from strings (an error message's file names: no machine path in a record)."""
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, str):
        return value.replace(str(ROOT) + os.sep, "")
    if isinstance(value, bool) or value is None:
        return value
    if isinstance(value, int):
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if hasattr(value, "tolist"):  # numpy and JAX arrays and scalars
        return jsonable(value.tolist())
    return str(value)


def record(area: str, results: Any, *, command: str, options: Optional[dict] = None, duration_s: Optional[float] = None,
           date: Optional[str] = None) -> dict:
    """The record of one area's run (see the module's docstring)."""
    return {
        "schema": SCHEMA,
        "area": area,
        "command": command,
        "date": date or datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d"),
        "duration_s": None if duration_s is None else round(float(duration_s), 1),
        "machine": machine_info(),
        "versions": versions(),
        "options": jsonable(options or {}),
        "results": jsonable(results),
    }


def write(directory: str | os.PathLike, rec: dict) -> pathlib.Path:
    """Writes ``directory/AREA.json`` (sorted keys, indented: a stable diff) and returns its path."""
    path = pathlib.Path(directory) / f"{rec['area']}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(rec, indent=1, sort_keys=True, allow_nan=False) + "\n")
    return path


def run_and_record(area: str, fn: Callable[..., Any], *, command: str, options: Optional[dict] = None,
                   directory: str | os.PathLike | None = None, transform: Optional[Callable[[Any], Any]] = None) -> dict:
    """Runs ``fn(**options)`` (a benchmark's `main`), timing it; returns its record (its results
    through ``transform`` if given), written to ``directory`` when one is given."""
    start = time.perf_counter()
    results = fn(**(options or {}))
    if transform is not None:
        results = transform(results)
    rec = record(area, results, command=command, options=options, duration_s=time.perf_counter() - start)
    if directory is not None:
        path = write(directory, rec)
        print(f"\nwrote {path}")
    return rec
