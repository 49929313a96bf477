"""Timing helpers shared by the benchmarks."""

from __future__ import annotations

import os
import platform
import statistics
import time

import jax


# A Solo-12 model file (rsmooth.sim.save_model) for machines without Pinocchio (a GPU node):
# set by `python -m benchmarks --solo12-model FILE`, an environment variable so that the
# benchmarks' child processes see it too.
SOLO12_MODEL_VARIABLE = "RSMOOTH_BENCHMARK_SOLO12_MODEL"


def solo12(**options):
    """``rsmooth.sim.solo12(**options)``, its model read from the file that
    ``--solo12-model`` names if any (else loaded from the URDF through Pinocchio)."""
    from rsmooth import sim

    path = os.environ.get(SOLO12_MODEL_VARIABLE)
    return sim.solo12(model=sim.load_model(path) if path else None, **options)


def machine() -> str:
    devices = jax.devices()
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            names = [line.split(":", 1)[1].strip() for line in f if line.startswith("model name")]
        cpu = names[0] if names else cpu
    except OSError:
        pass
    return (
        f"{platform.node()}: {cpu}, {os.cpu_count()} cores; python {platform.python_version()}, "
        f"jax {jax.__version__} on {devices[0].platform} ({len(devices)} device(s): {devices[0].device_kind}); "
        f"XLA_FLAGS={os.environ.get('XLA_FLAGS', '')!r}"
    )


def median_time(fn, *args, repeats: int = 30, warmup: int = 2) -> float:
    """Median wall time in seconds of fn(*args) (outputs blocked on), after warm-up calls that
    include compilation."""
    for _ in range(warmup):
        jax.block_until_ready(fn(*args))
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def fmt(seconds: float) -> str:
    if seconds < 1e-3:
        return f"{seconds * 1e6:8.1f} us"
    if seconds < 1:
        return f"{seconds * 1e3:8.2f} ms"
    return f"{seconds:8.2f} s "
