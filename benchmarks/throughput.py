"""Batched throughput: Solo-12 steps per second over thousands of environments, rsmooth against MJX.

`python -m benchmarks throughput [--batches N ...] [--float32] [--repeats R] [--quick] [--json DIR]`

The robot and scene of `benchmarks.sim` (Solo-12, four sphere feet on a floor, dt = 0.01 s,
friction 0.7, the same MJCF for MuJoCo built from the same URDF). For each batch size N, the N
environments start standing and take 5 steps under the standing torques plus Gaussian noise of
0.5 N m per joint (feet slide, lift or press harder); one more step from those states is timed:

- rsmooth `jit(vmap(step))` (hard contact, the NCP solved per environment) and
  `jit(vmap(step_and_jacobians))` (the next state and both Jacobians, what DDP and R-DDP call);
- MJX `jit(vmap(mjx.step))` (MuJoCo's soft contact) on its own states after the same protocol.

Printed and recorded per N: the time per batched call (median of ``repeats`` after compilation,
reported apart), steps per second, and the two ratios the goals are stated in (issue "scale
out"): rsmooth's steps per second over MJX's (goal >= 1 on a GPU) and the Jacobian call's time
over the step's (goal <= 3). Float64 by default (the precision rsmooth's tests run in; MJX then
runs in float64 too); ``--float32`` runs both in float32. Batch sizes default to 1,024, 4,096
and 16,384 on a GPU, 16 and 64 on a CPU (``--quick``: the first two on a GPU, 16 on a CPU). MJX is the
`mujoco-mjx` package, whose version must match the installed MuJoCo; without it its rows are null.
"""

from __future__ import annotations

import argparse
import time
from typing import Optional, Sequence

import jax
import numpy as np

GPU_BATCHES = (1024, 4096, 16384)
CPU_BATCHES = (16, 64)  # MJX's batched step of 256 hangs in XLA's CPU runtime (MuJoCo 3.17)
NOISE = 0.5  # N m, per joint
WARM_STEPS = 5
STEP_GOAL = 1.0  # rsmooth steps per second / MJX's, at least
JACOBIAN_GOAL = 3.0  # step-and-Jacobians time / step time, at most


def _compile_and_time(fn, *args, repeats: int) -> tuple[float, float]:
    """(seconds to the first result, compilation included; median seconds per call after)."""
    from benchmarks._timing import median_time

    start = time.perf_counter()
    jax.block_until_ready(fn(*args))
    first = time.perf_counter() - start
    return first, (median_time(fn, *args, repeats=repeats, warmup=1) if repeats else float("nan"))


def _solo12():
    """``(system, x0, u0)``: `benchmarks.sim`'s Solo-12, standing, and its standing torques."""
    from benchmarks._timing import solo12
    from benchmarks.sim import DT, FRICTION
    from rsmooth import sim

    system = solo12(friction=FRICTION, time_step=DT)
    x0 = system.initial_state()
    return system, x0, sim.solo12_standing_torques(system, x0)


def _ours(solo, batch: int, noise: np.ndarray, repeats: int) -> dict:
    import jax.numpy as jnp

    system, x0, u0 = solo
    dtype = x0.dtype
    us = jnp.tile(u0, (batch, 1)) + jnp.asarray(noise, dtype)
    step = jax.jit(jax.vmap(system.step))
    xs = jnp.tile(x0, (batch, 1))
    step_first, _ = _compile_and_time(step, xs, us, repeats=0)
    for _ in range(WARM_STEPS):
        xs = step(xs, us)
    step_jac = jax.jit(jax.vmap(system.step_and_jacobians))
    info = jax.jit(jax.vmap(lambda x, u: system.step_with_info(x, u)[1]))(xs, us)
    step_s = _compile_and_time(step, xs, us, repeats=repeats)[1]
    jac_first, jac_s = _compile_and_time(step_jac, xs, us, repeats=repeats)
    return {
        "step_s": step_s, "step_first_s": step_first, "step_jac_s": jac_s, "step_jac_first_s": jac_first,
        "finite": bool(jnp.all(jnp.isfinite(step(xs, us)))),
        "unconverged": int(jnp.sum(~info.ncp.converged)),
        "admm_iterations_mean": float(jnp.mean(info.ncp.iterations)),
        "base_height_mean": float(jnp.mean(xs[:, 2])),
    }


def _mjx(solo, batch: int, noise: np.ndarray, repeats: int) -> dict:
    import jax.numpy as jnp
    import mujoco
    from mujoco import mjx

    from benchmarks.sim import mujoco_solo12, to_mujoco_qpos

    system, x0, u0 = solo
    u0 = np.asarray(u0)
    model, _ = mujoco_solo12()
    data = mujoco.MjData(model)
    data.qpos[:] = to_mujoco_qpos(np.asarray(x0[: system.model.nq]))
    mujoco.mj_forward(model, data)
    mx = mjx.put_model(model)
    dx = mjx.put_data(model, data)
    dtype = jnp.asarray(x0).dtype
    ctrl = jnp.asarray(np.tile(u0, (batch, 1)) + noise, dtype)
    dxs = jax.vmap(lambda c: dx.replace(ctrl=c))(ctrl)
    step = jax.jit(jax.vmap(mjx.step, in_axes=(None, 0)))
    first, _ = _compile_and_time(step, mx, dxs, repeats=0)
    for _ in range(WARM_STEPS):
        dxs = step(mx, dxs)
    step_s = _compile_and_time(step, mx, dxs, repeats=repeats)[1]
    return {"step_s": step_s, "step_first_s": first, "finite": bool(jnp.all(jnp.isfinite(step(mx, dxs).qpos))),
            "base_height_mean": float(jnp.mean(dxs.qpos[:, 2]))}


def main(repeats: int = 10, quick: bool = False, batches: Optional[Sequence[int]] = None, float32: bool = False) -> dict:
    jax.config.update("jax_enable_x64", not float32)
    from benchmarks._record import machine_info
    from benchmarks._timing import machine

    gpu = jax.devices()[0].platform != "cpu"
    if batches is None:
        batches = GPU_BATCHES if gpu else CPU_BATCHES
        batches = batches[: len(batches) - 1] if quick else batches
    batches = tuple(int(b) for b in batches)
    if any(b < 1 for b in batches):
        raise ValueError(f"batches must be positive integers, got {batches}")
    print(f"machine: {machine()}")
    print(f"Solo-12 on a floor, one step from perturbed standing states, {'float32' if float32 else 'float64'}; "
          f"median of {repeats} calls after compilation\n", flush=True)
    dtype_name = "float32" if float32 else "float64"
    rows = []
    mjx_error = None
    solo = _solo12()
    for batch in batches:
        noise = NOISE * np.asarray(jax.random.normal(jax.random.key(0), (batch, 12)))
        ours = _ours(solo, batch, noise, repeats)
        try:
            reference = None if mjx_error else _mjx(solo, batch, noise, repeats)
        except Exception as error:  # the rows say why MJX is missing; rsmooth's stay measured
            mjx_error = f"MJX unavailable: {error!r}"[:300]
            reference = None
        row = {"batch": batch, "ours": ours, "mjx": reference,
               "ours_steps_per_s": batch / ours["step_s"],
               "ours_step_jac_per_s": batch / ours["step_jac_s"],
               "mjx_steps_per_s": batch / reference["step_s"] if reference else None,
               "jacobian_over_step": ours["step_jac_s"] / ours["step_s"]}
        row["ours_over_mjx"] = row["ours_steps_per_s"] / row["mjx_steps_per_s"] if reference else None
        rows.append(row)
        mjx_text = (f"MJX {reference['step_s'] * 1e3:8.2f} ms ({row['mjx_steps_per_s']:,.0f}/s; compile "
                    f"{reference['step_first_s']:.0f} s); rsmooth / MJX {row['ours_over_mjx']:.2f} (goal >= {STEP_GOAL:g})"
                    if reference else "MJX n/a")
        print(f"N = {batch:6d}: rsmooth step {ours['step_s'] * 1e3:8.2f} ms ({row['ours_steps_per_s']:,.0f}/s; compile "
              f"{ours['step_first_s']:.0f} s), step and Jacobians {ours['step_jac_s'] * 1e3:8.2f} ms "
              f"({row['jacobian_over_step']:.2f}x the step, goal <= {JACOBIAN_GOAL:g}; compile {ours['step_jac_first_s']:.0f} s); "
              f"{mjx_text}; unconverged solves {ours['unconverged']}", flush=True)
    if mjx_error:
        print(f"\nnote: {mjx_error}")
    return {"dtype": dtype_name, "platform": machine_info().get("platform"), "batches": list(batches), "rows": rows,
            "notes": [mjx_error] if mjx_error else []}


if __name__ == "__main__":
    from rsmooth import _xla

    _xla.apply_cpu_defaults()  # the settings `rsmooth` and `python -m benchmarks` run with, before JAX starts
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--quick", action="store_true", help="the default batch sizes but the largest")
    parser.add_argument("--batches", type=int, nargs="+", help="batch sizes (default: 1024 4096 16384 on a GPU, 16 64 on a CPU)")
    parser.add_argument("--float32", action="store_true", help="both simulators in float32 (default float64)")
    parser.add_argument("--solo12-model", metavar="FILE", help="a Solo-12 model file written by rsmooth.sim.save_model")
    parser.add_argument("--json", metavar="DIR", help="also write DIR/throughput.json (DIR/throughput_float32.json with --float32)")
    args = parser.parse_args()
    import os

    from benchmarks import _record
    from benchmarks._timing import SOLO12_MODEL_VARIABLE

    if args.solo12_model:
        os.environ[SOLO12_MODEL_VARIABLE] = os.path.abspath(args.solo12_model)
    options = dict(repeats=args.repeats, quick=args.quick, batches=args.batches, float32=args.float32)
    _record.run_and_record("throughput_float32" if args.float32 else "throughput", main, command=_record.command_line(),
                           options=options, directory=args.json)
