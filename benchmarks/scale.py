"""Monte-Carlo samples over devices: `python -m benchmarks scale [--quick] [--repeats N] [--json DIR]`.

The time of one first-order estimate through the contact simulator (a ball thrown at a wall,
a rollout of ``STEPS`` steps with hard contact, its final position differentiated with respect
to the throw) against the number of samples and the number of devices they are spread over
(``devices="all"``, :func:`rsmooth.parallel.map_samples`). On CPU the devices are XLA's forced
host devices (``--xla_force_host_platform_device_count=N``), which must be set before JAX
starts: each device count runs in a fresh Python process. With several devices, each device
evaluates its samples one at a time (the default on CPU devices, see :mod:`rsmooth.parallel`)
or its whole share vmapped (``sample_chunk`` = the sample count; safe for this system, whose
contact solve makes no batched LAPACK call large enough to be split over threads). Times are
the median of ``repeats`` calls of the jitted estimate after its compilation (reported apart),
and each is also given as a ratio to the one-device time at the same sample count (below 1:
faster).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

# A child prints its measurements on the last line of its standard output, after this tag.
TAG = "SCALE-RESULT "
DEVICES = (1, 2, 4)
SAMPLES = (16, 64, 256)
QUICK_SAMPLES = (8, 32)
STEPS = 10


def child(devices: int, samples: tuple[int, ...], repeats: int) -> dict:
    """Times the estimate in this process (started with ``devices`` forced host devices)."""
    import time

    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    import rsmooth
    from benchmarks._timing import machine, median_time
    from rsmooth import sim

    assert len(jax.devices()) == devices, (jax.devices(), devices)
    system = sim.ball_wall(wall_distance=0.3)
    x0 = system.initial_state()

    def final_position(throw):
        xs, _ = system.rollout(x0, jnp.zeros((STEPS, 3)).at[0].set(throw))
        return xs[-1, :3]

    throw = jnp.array([30.0, 0.0, 20.0])
    key = jax.random.key(0)
    rows = []
    for count in samples:
        for per_device in ("one at a time", "vmapped") if devices > 1 else ("vmapped",):
            chunk = count if per_device == "vmapped" else None
            estimate = jax.jit(lambda k, u, count=count, chunk=chunk: rsmooth.first_order(
                final_position, k, u, sigma=5.0, num_samples=count, devices="all", sample_chunk=chunk
            ).grad)
            start = time.perf_counter()
            jax.block_until_ready(estimate(key, throw))
            compile_s = time.perf_counter() - start
            rows.append({"samples": count, "per_device": per_device, "compile_s": compile_s,
                         "estimate_s": median_time(estimate, key, throw, repeats=repeats, warmup=1)})
    return {"devices": devices, "machine": machine(), "rows": rows}


def run_child(devices: int, samples: tuple[int, ...], repeats: int, timeout: float = 1800.0) -> dict:
    """One fresh process with ``devices`` forced host devices; its measurements."""
    flags = f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count={devices}".strip()
    environ = dict(os.environ, XLA_FLAGS=flags, JAX_PLATFORMS=os.environ.get("JAX_PLATFORMS", "cpu"))
    done = subprocess.run(
        [sys.executable, "-m", "benchmarks.scale", "--child", str(devices), "--samples", *map(str, samples),
         "--repeats", str(repeats)],
        capture_output=True, text=True, env=environ, timeout=timeout,
    )
    lines = [line for line in done.stdout.splitlines() if line.startswith(TAG)]
    if done.returncode != 0 or not lines:
        raise RuntimeError(f"scale: {devices} device(s) failed (exit {done.returncode}):\n{done.stderr[-3000:]}")
    return json.loads(lines[-1][len(TAG):])


def main(repeats: int = 5, quick: bool = False) -> dict:
    from benchmarks._record import machine_info

    samples = QUICK_SAMPLES if quick else SAMPLES
    info = machine_info()
    print(f"scale: {info['cpu']}, {info['cores']} cores; first-order estimate through a {STEPS}-step rollout "
          f"(ball_wall, hard contact); median of {repeats}; one fresh process per device count", flush=True)
    runs = []
    for devices in DEVICES:
        run = run_child(devices, samples, repeats)
        print(f"  {devices} device(s): {run['machine']}", flush=True)
        runs.append(run)
    one = {row["samples"]: row["estimate_s"] for row in runs[0]["rows"]}
    print(f"{'samples':>8s} {'devices':>8s} {'per device':>14s} {'estimate':>11s} {'vs 1 device':>12s} {'compile':>9s}")
    table = []
    for count in samples:
        for run in runs:
            for row in (r for r in run["rows"] if r["samples"] == count):
                ratio = row["estimate_s"] / one[count]
                print(f"{count:8d} {run['devices']:8d} {row['per_device']:>14s} {row['estimate_s'] * 1e3:8.2f} ms "
                      f"{ratio:11.2f}x {row['compile_s']:7.1f} s", flush=True)
                table.append({"samples": count, "devices": run["devices"], "per_device": row["per_device"],
                              "estimate_s": row["estimate_s"], "ratio_to_one_device": ratio, "compile_s": row["compile_s"]})
    return {"steps": STEPS, "repeats": repeats, "samples": list(samples), "devices": list(DEVICES), "rows": table}


if __name__ == "__main__":
    import argparse

    parser = argparse.ArgumentParser()
    parser.add_argument("--child", type=int, required=True, help="the number of devices this process has")
    parser.add_argument("--samples", type=int, nargs="+", required=True)
    parser.add_argument("--repeats", type=int, required=True)
    arguments = parser.parse_args()
    result = child(arguments.child, tuple(arguments.samples), arguments.repeats)
    print(TAG + json.dumps(result), flush=True)
