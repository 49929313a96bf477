"""Time to first result: `python -m benchmarks startup [--quick] [--repeats N] [--json DIR]`.

Each case runs in a fresh Python process, as a user starts it, first with an empty persistent
compilation cache (cold) and then with the cache that run filled (warm, the median of
``--repeats`` runs). Inside the process, JAX's monitoring events give the time spent tracing
(Python building the programs), lowering them to StableHLO, compiling them (XLA) and reading
them back from the cache; the rest of the wall time is Python's start, imports, running the
programs and writing outputs.

Cases:

* ``solo12-ddp-lift``: Solo-12 lifts its front-left foot 5 cm (``rsmooth control solo-lift``'s
  problem, T = 50, hard contact) by DDP from the standing torques, from a fresh process to the
  answer; its iterations' own time (the same solve repeated in the process, compiled) is
  reported apart, since the goal is on the rest.
* ``cube-lift``: ``rsmooth control cube-lift --quick --method rddp --seeds 1``.
* ``sim-solo12``: ``rsmooth sim solo12 --quick``.
* ``demo``: ``rsmooth demo`` (four experiments at their quick sizes; minutes cold): not with --quick.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

# A child prints its measurements on the last line of its standard output, after this tag.
TAG = "STARTUP-RESULT "
EVENTS = {
    "trace_s": "/jax/core/compile/jaxpr_trace_duration",
    "lower_s": "/jax/core/compile/jaxpr_to_mlir_module_duration",
    "compile_s": "/jax/core/compile/backend_compile_duration",
    "cache_read_s": "/jax/compilation_cache/cache_retrieval_time_sec",
}
CLI_CASES = {
    "cube-lift": ["control", "cube-lift", "--quick", "--method", "rddp", "--seeds", "1"],
    "sim-solo12": ["sim", "solo12", "--quick"],
    "demo": ["demo"],
}
CASES = ("solo12-ddp-lift", "cube-lift", "sim-solo12", "demo")
QUICK_CASES = ("solo12-ddp-lift", "cube-lift")
# The goals of the time-to-first-result work (seconds), checked on the page.
GOALS = {"solo12-ddp-lift cold": 5.0, "solo12-ddp-lift warm, beyond the iterations": 1.0, "demo warm": 60.0}


def command(case: str) -> str:
    """The case as a user types it."""
    if case == "solo12-ddp-lift":
        return "python: control.ddp on rsmooth control solo-lift's problem (FL, 5 cm, T = 50)"
    return "rsmooth " + " ".join(CLI_CASES[case])


def _solo12_ddp_lift() -> dict:
    import jax.numpy as jnp

    from rsmooth import control
    from rsmooth.experiments import control_solo_lift

    config = control_solo_lift.Config(foot="FL", horizon=50)
    _, problem, u0 = control_solo_lift.build_problem(config)
    us = jnp.tile(u0, (config.horizon, 1))
    solution = control.ddp(problem, us, solver=control.DDP(throw=False))
    # The same solve again in this process, compiled: the time of its iterations alone.
    start = time.perf_counter()
    control.ddp(problem, us, solver=control.DDP(throw=False))
    return {"iterations": solution.iterations, "iterations_s": time.perf_counter() - start}


def child(case: str, out: str) -> None:
    """Runs one case in this process and prints its measurements (see :data:`TAG`)."""
    start = time.perf_counter()
    import jax
    from jax import monitoring

    totals = {name: 0.0 for name in EVENTS}
    names = {event: name for name, event in EVENTS.items()}

    def listener(event, seconds, **_):
        if event in names:
            totals[names[event]] += seconds

    monitoring.register_event_duration_secs_listener(listener)
    extra = {}
    if case == "solo12-ddp-lift":
        from rsmooth import _xla

        _xla.enable_compilation_cache()
        jax.config.update("jax_enable_x64", True)
        extra = _solo12_ddp_lift()
    else:
        from rsmooth import cli

        words = list(CLI_CASES[case])
        sys.argv = ["rsmooth", *words, "--out", out]
        try:
            cli.main()
        except SystemExit as exit:
            if exit.code not in (0, None):
                raise
    result = {"inside_s": time.perf_counter() - start, **totals, **extra}
    if "iterations_s" in extra:  # the repeated solve is not part of the run a user waits for
        result["inside_s"] -= extra["iterations_s"]
    print(TAG + json.dumps(result), flush=True)


def run_case(case: str, cache: str, timeout: float) -> dict:
    """One fresh process: its wall time (start to exit) and the child's measurements."""
    with tempfile.TemporaryDirectory(prefix="rsmooth-startup-out-") as out:
        environ = dict(os.environ, RSMOOTH_COMPILATION_CACHE=cache)
        environ.pop("JAX_COMPILATION_CACHE_DIR", None)
        start = time.perf_counter()
        done = subprocess.run(
            [sys.executable, "-m", "benchmarks.startup", "--child", case, "--out", os.path.join(out, "run")],
            capture_output=True, text=True, env=environ, timeout=timeout,
        )
        wall = time.perf_counter() - start
    lines = [line for line in done.stdout.splitlines() if line.startswith(TAG)]
    if done.returncode != 0 or not lines:
        raise RuntimeError(f"startup case {case} failed (exit {done.returncode}):\n{done.stderr[-3000:]}")
    result = json.loads(lines[-1][len(TAG):])
    # The solo12 case repeats its solve to time the iterations: not part of the wait.
    return {"wall_s": wall - result.get("iterations_s", 0.0), **result}


def _median(runs: list[dict]) -> dict:
    keys = [k for k, v in runs[0].items() if isinstance(v, (int, float)) and not isinstance(v, bool)]
    merged = {k: statistics.median(run[k] for run in runs) for k in keys}
    merged.update({k: v for k, v in runs[0].items() if k not in merged})
    return merged


def fmt_row(case: str, kind: str, run: dict) -> str:
    compile_share = run["compile_s"] / run["wall_s"]
    jax_share = (run["trace_s"] + run["lower_s"] + run["compile_s"] + run["cache_read_s"]) / run["wall_s"]
    extra = f"  iterations {run['iterations_s']:.2f} s" if "iterations_s" in run else ""
    return (f"{case:16s} {kind:5s} {run['wall_s']:7.1f} s  trace {run['trace_s']:5.1f}  lower {run['lower_s']:4.1f}  "
            f"compile {run['compile_s']:5.1f} ({compile_share:4.0%})  cache read {run['cache_read_s']:4.1f}  "
            f"trace+lower+compile+read {jax_share:4.0%}{extra}")


def main(repeats: int = 3, quick: bool = False) -> dict:
    from benchmarks._record import machine_info

    cases = QUICK_CASES if quick else CASES
    info = machine_info()
    print(f"startup: {info['cpu']}, {info['cores']} cores; cold = empty compilation cache, warm = median of {repeats}")
    results = {"cases": {}, "repeats": repeats, "goals": GOALS}
    for case in cases:
        timeout = 3600.0 if case == "demo" else 900.0
        with tempfile.TemporaryDirectory(prefix="rsmooth-startup-cache-") as cache:
            cold = run_case(case, cache, timeout)
            print(fmt_row(case, "cold", cold), flush=True)
            warm_runs = [run_case(case, cache, timeout) for _ in range(1 if case == "demo" else repeats)]
        warm = _median(warm_runs)
        print(fmt_row(case, "warm", warm), flush=True)
        results["cases"][case] = {"command": command(case), "cold": cold, "warm": warm, "warm_runs": len(warm_runs)}
    lift = results["cases"].get("solo12-ddp-lift")
    if lift:
        beyond = lift["warm"]["wall_s"] - lift["warm"]["iterations_s"]
        print(f"solo12-ddp-lift: cold {lift['cold']['wall_s']:.1f} s (goal < {GOALS['solo12-ddp-lift cold']:g}); warm "
              f"{lift['warm']['wall_s']:.1f} s of which iterations {lift['warm']['iterations_s']:.2f} s: "
              f"{beyond:.1f} s beyond them (goal < {GOALS['solo12-ddp-lift warm, beyond the iterations']:g})")
    return results


if __name__ == "__main__":
    import argparse

    parser = argparse.ArgumentParser()
    parser.add_argument("--child", choices=CASES, required=True)
    parser.add_argument("--out", required=True)
    arguments = parser.parse_args()
    child(arguments.child, arguments.out)
