"""What the optimal-control experiments share: the methods compared, the loop over methods and
seeds with one progress bar, the summary of the runs, and the cost / noise figure.

A *method* is a name: ``ddp`` (Box-DDP on the true dynamics), ``rddp`` (randomized DDP with the
adaptive noise schedule), ``rddp-reheating`` (the adaptive schedule that also raises the noise
at a stall where more noise would lower the cost) or ``rddp-geometric-D`` (randomized DDP whose noise is multiplied by
``D`` at every iteration, to compare the schedules). Every method starts from the same initial
controls; seeds change the R-DDP samples.

The ``*_option`` functions declare the ``Config`` fields that every DDP experiment has, with
their help text and allowed values (:func:`rsmooth.experiments._protocol.option`).
"""

from __future__ import annotations

import dataclasses
import time
from typing import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from rsmooth import _checks, control, sim, viz
from rsmooth.experiments import _protocol

METHOD_CHOICES = ("ddp", "rddp", "rddp-reheating", "all")
ESTIMATOR_CHOICES = ("first", "zeroth", "alpha")


def method_option():
    return _protocol.option(
        "all", "ddp, rddp, rddp-reheating (noise raised at stalls where more would help), or all (ddp, rddp "
        "and R-DDP with geometric noise decays).", choices=METHOD_CHOICES)


def seeds_option(default: int):
    return _protocol.option(default, "R-DDP runs per method, keys fold_in(seed, i); DDP runs once.", min=1)


def horizon_option(default: int):
    return _protocol.option(default, "Time steps of 10 ms.", min=2)


def estimator_option():
    return _protocol.option(
        "first", "R-DDP's estimate of the smoothed dynamics' Jacobians: first, zeroth or alpha order (alpha: half the "
        "samples to each estimate).", choices=ESTIMATOR_CHOICES)


def samples_option(default: int):
    return _protocol.option(default, "R-DDP's samples per node.", flag="samples", min=1)


def eps_option():
    return _protocol.option(1.0, "R-DDP's initial noise level; each noise scale below is multiplied by it.", min=0.0)


def max_iterations_option(default: int):
    return _protocol.option(default, "Iterations of DDP and R-DDP at most.", min=1)


def geometric_decays_option(default: tuple[float, ...]):
    return _protocol.option(
        default, "With --method all, the decays D of the R-DDP runs whose noise is multiplied by D at every iteration.",
        flag="geometric-decay", min=0.0, max=1.0)


def method_names(method: str, geometric_decays: tuple[float, ...]) -> tuple[str, ...]:
    """The methods a ``--method`` choice runs: one, or (``all``) DDP, adaptive R-DDP and the
    geometric schedules."""
    if method not in METHOD_CHOICES:
        raise ValueError(f"method must be one of {METHOD_CHOICES}, got {method!r}")
    if method != "all":
        return (method,)
    return ("ddp", "rddp") + tuple(f"rddp-geometric-{d:g}" for d in geometric_decays)


def make_solver(name: str, rddp: control.RDDP) -> control.DDP:
    """The solver of a method: ``rddp`` configures the smoothing (and the DDP options, which
    every method shares)."""
    if name == "ddp":
        return rddp.as_ddp()
    if name == "rddp":
        return dataclasses.replace(rddp, schedule="adaptive")
    if name == "rddp-reheating":
        return dataclasses.replace(rddp, schedule="reheating")
    if name.startswith("rddp-geometric-"):
        return dataclasses.replace(rddp, schedule="geometric", decay=float(name.rsplit("-", 1)[1]))
    raise ValueError(f"unknown method {name!r}")


def make_solvers(config) -> dict[str, control.DDP]:
    """The solver of each method that a control experiment's ``Config`` runs, in the order of
    ``method_names``; ``config.solver()`` gives the R-DDP options."""
    rddp = config.solver()
    return {name: make_solver(name, rddp) for name in method_names(config.method, config.geometric_decays)}


def check_config(config) -> None:
    """The checks every control experiment's ``Config`` shares: its options' choices and ranges
    (:func:`rsmooth.experiments._protocol.check_options`), and ``num_samples >= 4`` with the
    alpha-order estimator. Raises ``ValueError``."""
    _protocol.check_options(config)
    if config.estimator == "alpha" and config.num_samples < 4:
        raise ValueError(
            f"num_samples must be >= 4 with estimator alpha (half to each estimate), got {config.num_samples}")


def free_body_state_noise(position: float, rest: tuple[float, ...]) -> tuple[float, ...]:
    """Noise scales of a state that starts with a free body's position (3) and unit quaternion
    (4), then ``rest``; the quaternion's four coordinates get the position's noise. R-DDP
    projects each perturbed quaternion back to unit norm (``RigidBodySystem.project_state``),
    so this is noise on the orientation, about ``2 position`` radians per axis. A far smaller
    noise on the quaternion would starve the zeroth- and alpha-order estimators: the
    score-function column of a coordinate has an error inversely proportional to its noise.

    Example:
        >>> free_body_state_noise(0.01, (0.1,) * 2)
        (0.01, 0.01, 0.01, 0.01, 0.01, 0.01, 0.01, 0.1, 0.1)
    """
    return (position,) * 7 + tuple(rest)


def rddp_solver(config, control_noise_scale: float, state_noise_scale: tuple[float, ...]) -> control.RDDP:
    """The R-DDP solver of a control experiment's ``Config`` (its ``eps``, ``num_samples``,
    ``estimator`` and ``max_iterations``) with the noise scales of its controls and state."""
    return control.RDDP(
        eps=config.eps,
        num_samples=config.num_samples,
        estimator=config.estimator,
        control_noise_scale=control_noise_scale,
        state_noise_scale=state_noise_scale,
        max_iterations=config.max_iterations,
    )


def solve(name: str, solver: control.DDP, problem: control.ShootingProblem, us_init, key, callback=None) -> control.Solution:
    """Runs one method; failures are reported in the solution, not raised.

    Where the dynamics is a simulator (:class:`rsmooth.sim.RigidBodySystem`), the solution's
    controls are simulated again from its first state with the contact solver's diagnostics,
    which the solvers' programs do not carry: ``solution.stats["contact"]`` holds
    :func:`rsmooth.sim.check_steps`'s counts, and an unconverged or diverged step of the
    returned trajectory is reported (a ``SimulationWarning``), not silent.
    """
    solver = dataclasses.replace(solver, throw=False)
    if name == "ddp":
        solution = control.ddp(problem, us_init, solver=solver, callback=callback)
    else:
        solution = control.rddp(problem, key, us_init, solver=solver, callback=callback)
    if not isinstance(problem.dynamics, sim.RigidBodySystem):
        return solution
    infos = _rollout_infos(problem.dynamics, solution.xs[0], solution.us)
    counts = sim.check_steps(infos, what=f"the {name} solution's trajectory")
    return dataclasses.replace(solution, stats={**solution.stats, "contact": counts})


@eqx.filter_jit
@_checks.without_traced_checks()
def _rollout_infos(system, x0, us):
    """The step diagnostics of ``system.rollout(x0, us)``; one program per system and shapes
    (its traced checks left out: :func:`rsmooth.sim.check_steps` reads the diagnostics)."""
    return system.rollout(x0, us)[1]


def solution_summary(solution: control.Solution) -> dict:
    """The solver's part of a run's metrics (with the trajectory's contact solves that did
    not converge, and its diverged steps, where :func:`solve` simulated it again)."""
    contact = solution.stats.get("contact")
    return {
        **({"unconverged_steps": contact["unconverged_steps"], "diverged_steps": contact["diverged_steps"]} if contact else {}),
        "final_cost": float(solution.cost),
        "iterations": solution.iterations,
        "converged": solution.converged,
        "result": str(control.RESULTS[solution.result]) or "successful",
        "wall_time_s": float(solution.stats["total_time"]),
        "time_per_iteration_s": float(np.median(solution.stats["time_per_iteration"][1:]))
        if solution.iterations > 1
        else float("nan"),
    }


def solve_methods(
    config, problem: control.ShootingProblem, us_init, key, metrics_of: Callable[[control.Solution], dict],
    description: str, progress: bool = True,
) -> tuple[tuple[str, ...], dict, dict]:
    """Every method of a control experiment's ``config`` (:func:`make_solvers`) from
    ``us_init``, over its seeds (:func:`run_methods`); ``metrics_of(solution)`` gives a run's
    task metrics (with ``success``). Returns the methods' names, their metrics and the first
    seed's solutions.

    Raises:
        ValueError: a problem whose state is not float64 (``jax_enable_x64`` off when it was
            built): the contact solves' tolerance and DDP's line search need float64, and in
            float32 R-DDP ends on a non-finite value instead of an answer.
    """
    dtype = jnp.asarray(problem.x0).dtype
    if dtype != jnp.float64:
        raise ValueError(
            f"{description}: the problem's state is {dtype}, and contact solves and DDP need float64: call "
            "jax.config.update('jax_enable_x64', True) before building it (the rsmooth command does)"
        )
    solvers = make_solvers(config)
    names = tuple(solvers)

    def run_one(name, key, callback):
        solution = solve(name, solvers[name], problem, us_init, key, callback)
        return solution, metrics_of(solution)

    return (names, *run_methods(names, config.seeds, key, run_one, description, progress))


def run_methods(
    names: tuple[str, ...],
    seeds: int,
    key,
    run_one: Callable[[str, jax.Array, Callable], tuple[control.Solution, dict]],
    description: str,
    progress: bool = True,
) -> tuple[dict, dict]:
    """Runs every method for ``seeds`` keys (``fold_in(key, i)``; DDP, deterministic, once).

    ``run_one(name, key, callback)`` solves and returns the solution and the task's metrics of
    the run, which must include ``success``. Returns ``(metrics, solutions)``: per method, the
    aggregate (``success_rate``, medians, the runs) with the first seed's run on top, and the
    solutions of the first seed (for figures).
    """
    total = sum(1 if name == "ddp" else seeds for name in names)
    bar = tqdm(total=total, desc=description, disable=not progress)
    metrics, solutions = {}, {}
    try:
        for name in names:
            runs = []
            for i in range(1 if name == "ddp" else seeds):
                bar.set_description(f"{description}: {name}, seed {i}")

                def callback(info):
                    bar.set_postfix(it=info["iteration"], cost=f"{info['cost']:.4g}", eps=f"{info['noise']:.3g}", step=f"{info['step_size']:.3g}")

                start = time.perf_counter()
                solution, task_metrics = run_one(name, jax.random.fold_in(key, i), callback)
                run = {**solution_summary(solution), **task_metrics, "run_time_s": time.perf_counter() - start}
                runs.append(run)
                if i == 0:
                    solutions[name] = solution
                bar.update()
            success = np.array([run["success"] for run in runs], dtype=float)
            metrics[name] = {
                **runs[0],
                "success_rate": float(success.mean()),
                "runs": len(runs),
                "median_final_cost": float(np.median([run["final_cost"] for run in runs])),
                "median_iterations": float(np.median([run["iterations"] for run in runs])),
                "per_seed": runs,
            }
    finally:
        bar.close()
    return metrics, solutions


def plot_histories(axes, solutions: dict[str, control.Solution]) -> None:
    """Cost (log scale) and noise level against the iteration, one line per method."""
    ax_cost, ax_eps = axes
    for index, (name, solution) in enumerate(solutions.items()):
        cost = np.asarray(solution.stats["cost"])
        ax_cost.semilogy(np.arange(cost.size), cost, marker=".", color=f"C{index}", label=name)
        if name != "ddp":
            noise = np.asarray(solution.stats["noise"])
            ax_eps.plot(np.arange(noise.size), noise, marker=".", color=f"C{index}", label=name)
    ax_cost.set_xlabel("iteration")
    ax_cost.set_ylabel("true cost")
    ax_cost.legend(fontsize=8)
    ax_eps.set_xlabel("iteration")
    ax_eps.set_ylabel("noise level eps")
    if ax_eps.lines:
        ax_eps.legend(fontsize=8)


def summary(columns: str, row: Callable[[dict], str]) -> Callable[[dict], dict]:
    """A control experiment's printed summary: per method, its success rate then ``row(its metrics)``.

    Example:
        >>> lines = summary("height (mm)", lambda m: f"{1000 * m['height']:.1f}")
        >>> lines({"methods": ["ddp"], "ddp": {"success_rate": 0.5, "height": 0.0123}})
        {'ddp: success rate, height (mm)': '50 %, 12.3'}
    """
    return lambda metrics: {
        f"{name}: success rate, {columns}": f"{100 * metrics[name]['success_rate']:.0f} %, {row(metrics[name])}"
        for name in metrics["methods"]
    }


def top_level(metrics: dict, names: tuple[str, ...]) -> dict:
    """With one method, its metrics also sit at the top level of metrics.json."""
    if len(names) == 1:
        return {**metrics[names[0]], **metrics}
    return metrics


def frames_side_by_side(draw: Callable[[object, str, int], None], names: tuple[str, ...], steps: int, size=(3.2, 3.2), dpi=80):
    """Frames of an animation: one panel per method, ``draw(ax, name, t)`` fills a panel."""
    frames = []
    for t in range(steps):
        fig, axes = viz.plt.subplots(1, len(names), figsize=(size[0] * len(names), size[1]), dpi=dpi, squeeze=False)
        for ax, name in zip(axes[0], names):
            draw(ax, name, t)
        fig.tight_layout()
        fig.canvas.draw()
        frames.append(np.asarray(fig.canvas.buffer_rgba())[..., :3].copy())
        viz.plt.close(fig)
    return frames
