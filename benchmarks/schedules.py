"""Noise schedules side by side: `python -m benchmarks schedules [--quick] [--json DIR]`.

Each comparison runs one experiment twice from the command line, in a fresh process, with the
same seeds and options except the noise schedule: the decrease-only rule the experiment uses
by default, and the reheating rule that also raises the noise when progress stalls
(:class:`rsmooth.schedules.Reheating`; R-DDP's ``schedule="reheating"``). It records each
run's success rate (the experiment's own criterion) from its ``metrics.json``.

The comparisons are the tasks where the decrease-only rule leaves runs stuck: alpha-order
R-DDP lifting Solo-12's hind-right foot, render pose from 80 degrees, and policy gradients
(the ball thrown over a wall, the finger that must first reach the box it pushes). For the
policy pusher the default schedule is a constant noise, the column's "decrease-only" entry. ``--quick`` runs fewer seeds and problems (a smoke test of the
harness, not a result).

``results``: ``{"comparisons": {NAME: {"task", "metric", "runs": {RULE: {"command",
"success_pct", "wall_s"}}}}}``; a run that failed has ``success_pct`` null and its ``error``.
"""

from __future__ import annotations

import json
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable

RSMOOTH = [sys.executable, "-m", "rsmooth.cli"]


# Readers of a run's success rate, given its metrics and the arguments of its rule.
def _solo(metrics: dict, extra: list[str]) -> float:
    return 100.0 * metrics[extra[extra.index("--method") + 1]]["success_rate"]


def _render(metrics: dict, extra: list[str]) -> float:
    return metrics["perturbed-gaussian"]["80"]["solved_pct"]


def _policy(metrics: dict, extra: list[str]) -> float:
    return 100.0 * metrics["alpha"]["success_rate"]


# name -> (task, metric, command (without --out), {rule: extra arguments}, success reader, quick changes)
COMPARISONS: dict[str, tuple[str, str, list[str], dict[str, list[str]], Callable, list[str]]] = {
    "solo-lift-hr-alpha": (
        "Solo-12 lifts its hind-right foot 5 cm, alpha-order R-DDP",
        "runs that lift the foot (%)",
        ["control", "solo-lift", "--foot", "HR", "--estimator", "alpha", "--seed", "0", "--seeds", "20"],
        {"decrease-only": ["--method", "rddp"], "reheating": ["--method", "rddp-reheating"]},
        _solo,
        ["--seeds", "2"],
    ),
    "render-pose-80": (
        "Pose from 80 deg, perturbed Gaussian renderer, 64-pixel images",
        "problems solved (%)",
        ["render", "pose", "--init-error", "80", "--problems", "24", "--image-size", "64", "--method",
         "perturbed-gaussian", "--seed", "0"],
        {"decrease-only": ["--noise-schedule", "adaptive"], "reheating": ["--noise-schedule", "reheating"]},
        _render,
        ["--problems", "2", "--steps", "20"],
    ),
    "policy-wall-alpha": (
        "Ball over a wall, alpha-order policy gradient",
        "throws that clear the wall (%)",
        ["control", "policy", "--method", "alpha", "--seeds", "10", "--seed", "0"],
        {"decrease-only": ["--noise-schedule", "geometric"], "reheating": ["--noise-schedule", "reheating"]},
        _policy,
        ["--seeds", "2", "--iterations", "10"],
    ),
    "policy-pusher-alpha": (
        "Finger pushes a box, open-loop alpha-order policy gradient from zero force",
        "boxes within 2 cm of the target (%)",
        ["control", "policy-pusher", "--method", "alpha", "--seed", "0"],
        {"decrease-only": ["--noise-schedule", "constant"], "reheating": ["--noise-schedule", "reheating"]},
        _policy,
        ["--seeds", "1", "--iterations", "5"],
    ),
}


def run_rule(arguments: list[str], read: Callable, extra: list[str], timeout: float) -> dict:
    """One run in a fresh process; its success rate from its metrics.json."""
    with tempfile.TemporaryDirectory(prefix="rsmooth-schedules-") as out:
        command = RSMOOTH + arguments + ["--out", out]
        start = time.perf_counter()
        try:
            done = subprocess.run(command, capture_output=True, text=True, timeout=timeout)
        except subprocess.TimeoutExpired:
            return {"success_pct": None, "wall_s": time.perf_counter() - start, "error": f"timed out after {timeout:g} s"}
        wall = time.perf_counter() - start
        if done.returncode != 0:
            return {"success_pct": None, "wall_s": wall, "error": done.stderr.strip().splitlines()[-1:] or ["failed"]}
        metrics = json.loads((Path(out) / "metrics.json").read_text())
        return {"success_pct": read(metrics, extra), "wall_s": wall}


def main(repeats: int = 1, quick: bool = False) -> dict:
    from benchmarks._record import machine_info

    info = machine_info()
    print(f"schedules: {info['cpu']}, {info['cores']} cores; success rates, decrease-only against reheating")
    results: dict = {"comparisons": {}, "quick": quick}
    for name, (task, metric, base, rules, read, quick_changes) in COMPARISONS.items():
        entry = {"task": task, "metric": metric, "runs": {}}
        for rule, extra in rules.items():
            arguments = base + extra + (quick_changes if quick else [])
            run = run_rule(arguments, read, extra, timeout=3600.0)
            run["command"] = "rsmooth " + shlex.join(arguments)
            entry["runs"][rule] = run
            shown = "failed" if run["success_pct"] is None else f"{run['success_pct']:.0f} %"
            print(f"{name:>20} {rule:>14}: {shown:>7} ({run['wall_s']:.0f} s)", flush=True)
        results["comparisons"][name] = entry
    return results
