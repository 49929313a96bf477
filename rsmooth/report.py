"""The experiments' results as one static HTML page that works offline (`rsmooth report`).

The page lists, per experiment, its figures and animations (as files beside the page, in the
experiment's output folder), its metrics as a table, the command that reproduces it, its
settings, how long it ran, and, for a run that failed, its error; at the top, the machine and
the versions of the packages. It has no script and loads nothing from the network.

Example:
  >>> import tempfile
  >>> from pathlib import Path
  >>> from rsmooth import report
  >>> entry = report.Entry(title="experiment demo", folder="demo", command="rsmooth experiment demo",
  ...                      help="A demo.", settings={"size": 3}, metrics={"error": 0.5})
  >>> page = report.write_page(Path(tempfile.mkdtemp()), [entry], {"python": "3"}, profile="quick")
  >>> page.name
  'index.html'
"""

from __future__ import annotations

import dataclasses
import datetime
import html
import math
import os
import platform
import urllib.parse
from importlib import metadata
from pathlib import Path
from typing import Any, Iterable, Optional

from rsmooth import _files

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".gif", ".svg", ".webp")
VIDEO_SUFFIXES = (".mp4", ".webm")
# Lists longer than this are shown by their length, first and last values (the full list is in
# the experiment's metrics.json, linked beside the table).
LIST_SHOWN = 8
PACKAGES = ("rsmooth", "jax", "jaxlib", "optax", "equinox", "mujoco", "pin", "trimesh", "numpy")


@dataclasses.dataclass(frozen=True)
class Entry:
    """One experiment's section of the page.

    Attributes:
      title: the experiment's command, e.g. ``"control cube-lift"``.
      folder: its output folder, relative to the page.
      command: the command line that reproduces the run.
      help: what the experiment shows, a sentence or two.
      settings: its configuration, field -> value.
      metrics: its ``metrics.json``; None when the run failed.
      error: the error that ended the run (type, message and where), None when it succeeded.
      wall_time_s: how long the run took, compilation included.
      files: the files the run wrote, relative to `folder`.
    """

    title: str
    folder: str
    command: str
    help: str
    settings: dict
    metrics: Optional[dict] = None
    error: Optional[str] = None
    wall_time_s: Optional[float] = None
    files: tuple[str, ...] = ()


def machine() -> dict[str, str]:
    """The machine and the versions of the packages a result depends on."""
    info = {
        "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "cpu": _cpu_name(),
        "cores": str(os.cpu_count()),
    }
    try:
        import jax

        info["devices"] = ", ".join(sorted({f"{d.platform}: {d.device_kind}" for d in jax.devices()}))
    except Exception as error:  # a broken backend is worth a line on the page, not a failed report
        info["devices"] = f"unavailable ({type(error).__name__}: {error})"
    for package in PACKAGES:
        try:
            info[package] = metadata.version(package)
        except metadata.PackageNotFoundError:
            pass
    return info


def _cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def format_value(value: Any) -> str:
    """A metric as text: 4 significant digits for floats, lists shortened past LIST_SHOWN, lists of
    records (per-seed runs) by their count."""
    if isinstance(value, bool) or value is None:
        return str(value)
    if isinstance(value, float):
        return f"{value:.4g}" if math.isfinite(value) else str(value)
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k}: {format_value(v)}" for k, v in value.items()) + "}"
    if isinstance(value, (list, tuple)):
        if value and all(isinstance(v, dict) for v in value):  # per-run records: in metrics.json
            return f"{len(value)} records (metrics.json)"
        if len(value) > LIST_SHOWN:
            head = ", ".join(format_value(v) for v in value[:3])
            tail = ", ".join(format_value(v) for v in value[-2:])
            return f"[{head}, ..., {tail}] ({len(value)} values)"
        return "[" + ", ".join(format_value(v) for v in value) + "]"
    return str(value)


def flatten(metrics: dict, prefix: str = "") -> list[tuple[str, Any]]:
    """``(dotted key, value)`` for every leaf of nested dicts, in the dict's order."""
    rows = []
    for key, value in metrics.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict) and value:
            rows.extend(flatten(value, name + "."))
        else:
            rows.append((name, value))
    return rows


def _table(rows: Iterable[tuple[str, Any]], header: tuple[str, str], css: str) -> str:
    cells = "".join(
        f"<tr><td>{html.escape(str(k))}</td><td>{html.escape(format_value(v))}</td></tr>" for k, v in rows
    )
    return (f'<table class="{css}"><thead><tr><th>{html.escape(header[0])}</th><th>{html.escape(header[1])}</th>'
            f"</tr></thead><tbody>{cells}</tbody></table>")


def _href(folder: str, name: str) -> str:
    """A relative URL: each path part percent-encoded (spaces, '#', '?' in folder names)."""
    return "/".join(urllib.parse.quote(part) for part in Path(folder, name).as_posix().split("/"))


def _media(entry: Entry) -> str:
    parts = []
    for name in entry.files:
        src = html.escape(_href(entry.folder, name), quote=True)
        label = html.escape(name)
        suffix = Path(name).suffix.lower()
        if suffix in IMAGE_SUFFIXES:
            parts.append(f'<figure><a href="{src}"><img src="{src}" alt="{label}"></a><figcaption>{label}</figcaption></figure>')
        elif suffix in VIDEO_SUFFIXES:
            parts.append(f'<figure><video src="{src}" controls muted loop></video><figcaption>{label}</figcaption></figure>')
    return f'<div class="media">{"".join(parts)}</div>' if parts else ""


def _files_list(entry: Entry) -> str:
    links = [
        f'<a href="{html.escape(_href(entry.folder, name), quote=True)}">{html.escape(name)}</a>'
        for name in entry.files
        if Path(name).suffix.lower() not in IMAGE_SUFFIXES + VIDEO_SUFFIXES
    ]
    return f'<p class="files">Files: {", ".join(links)}</p>' if links else ""


def _anchor(title: str) -> str:
    return "".join(c if c.isalnum() else "-" for c in title.lower())


def _section(entry: Entry) -> str:
    status = "failed" if entry.error is not None else "ok"
    took = f", {entry.wall_time_s:.1f} s" if entry.wall_time_s is not None else ""
    body = [
        f'<section id="{_anchor(entry.title)}" class="{status}">',
        f"<h2>{html.escape(entry.title)} <small>({status}{took})</small></h2>",
        f"<p>{html.escape(entry.help)}</p>",
        f"<pre class=\"command\">{html.escape(entry.command)}</pre>",
    ]
    if entry.error is not None:
        body.append(f'<pre class="error">{html.escape(entry.error)}</pre>')
    body.append(_media(entry))
    if entry.metrics is not None:
        body.append("<h3>Metrics</h3>" + _table(flatten(entry.metrics), ("metric", "value"), "metrics"))
    body.append(_files_list(entry))
    body.append("<details><summary>Settings</summary>"
                + _table(entry.settings.items(), ("field", "value"), "settings") + "</details>")
    body.append("</section>")
    return "\n".join(part for part in body if part)


_STYLE = """
body { font-family: sans-serif; max-width: 72rem; margin: 2rem auto; padding: 0 1rem; color: #222; }
table { border-collapse: collapse; margin: 0.5rem 0; font-size: 0.9rem; }
td, th { border: 1px solid #ccc; padding: 0.2rem 0.5rem; text-align: left; vertical-align: top; }
td:last-child { font-family: monospace; }
.media { display: flex; flex-wrap: wrap; gap: 1rem; }
figure { margin: 0; } figure img, figure video { max-width: 34rem; max-height: 28rem; border: 1px solid #ddd; }
figcaption { font-size: 0.8rem; color: #555; }
pre { background: #f5f5f5; padding: 0.5rem; overflow-x: auto; }
pre.error { background: #fde8e8; color: #800; }
section { border-top: 2px solid #ddd; margin-top: 2rem; }
section.failed h2 { color: #a00; }
"""


def render_page(entries: list[Entry], machine_info: dict, profile: str) -> str:
    """The page's HTML: a header with the machine, a table of contents, one section per entry."""
    failed = sum(entry.error is not None for entry in entries)
    contents = "".join(
        f'<li><a href="#{_anchor(e.title)}">{html.escape(e.title)}</a>{" (failed)" if e.error is not None else ""}</li>'
        for e in entries
    )
    head = (
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
        f"<title>rsmooth report ({html.escape(profile)})</title><style>{_STYLE}</style></head><body>"
    )
    summary = (
        f"<h1>rsmooth report</h1><p>Profile: {html.escape(profile)}. {len(entries)} experiments, "
        f"{len(entries) - failed} ran, {failed} failed.</p>"
    )
    return "\n".join([
        head, summary, _table(machine_info.items(), ("machine", ""), "machine"),
        f"<ul class=\"contents\">{contents}</ul>", *(_section(e) for e in entries), "</body></html>\n",
    ])


def write_page(out: Path, entries: list[Entry], machine_info: dict, profile: str) -> Path:
    """Writes ``out/index.html`` (atomically) and returns its path."""
    path = Path(out) / "index.html"
    with _files.atomic_path(path) as temporary:
        temporary.write_text(render_page(entries, machine_info, profile), encoding="utf-8")
    return path
