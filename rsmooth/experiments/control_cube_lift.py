"""Experiment: lift a cube resting on the floor to a target height with a vertical force.

The cube (hard frictional contact, ``rsmooth.sim.cube(wrench_components=(2,))``) rests on the
floor; the input is the vertical force at its centre, starting from zero force. The cost is
``1e-6 sum_t u_t^2 + 100 (z_T - z_target)^2 + v_z,T^2``. While the force stays below the
weight ``m g`` the cube does not move: the derivative of every state with respect to the force
is exactly zero, so DDP's first backward pass sees no descent direction and stops at once
(converged to the rest trajectory). R-DDP differentiates the smoothed dynamics: a noisy force
larger than ``m g`` lifts the cube in some samples, and noise on the state takes some samples
off the floor, where gravity and the force act; the averaged Jacobians point upwards and R-DDP
lifts the cube, then drives the noise to zero to finish on the true dynamics.

Methods: ``ddp``, ``rddp`` (adaptive noise: reduced only when the smoothed problem stalls) and
``rddp-geometric-D`` (noise multiplied by ``D`` at every iteration). R-DDP runs over several
seeds; a run succeeds when the final height is within ``tolerance`` of the target.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from rsmooth import control, sim, viz
from rsmooth.experiments import _control, _protocol

METRICS_DOC = """metrics.json keys: task, methods, seeds, target_height (m above the rest height),
tolerance (m), and per method (ddp, rddp, rddp-geometric-D): success (first seed), final_cost,
iterations, converged, result, wall_time_s (the solve, compilation included), time_per_iteration_s
(median, compiled), unconverged_steps and diverged_steps (the
returned trajectory simulated again: contact solves that did not converge, steps that diverged), final_height (m above rest), max_force (N), success_rate (over seeds),
median_final_cost, median_iterations, per_seed (the runs). With --method ddp or rddp, the keys of
that method are also at the top level."""


@dataclasses.dataclass(frozen=True)
class Config:
    method: str = _control.method_option()
    height: float = _protocol.option(0.1, "Target height above rest, m.", above=0.0)
    tolerance: float = _protocol.option(0.01, "A run succeeds when |final height - target| is below it, m.", above=0.0)
    horizon: int = _control.horizon_option(20)
    seeds: int = _control.seeds_option(10)
    num_samples: int = _control.samples_option(16)
    eps: float = _control.eps_option()
    force_noise: float = _protocol.option(10.0, "Noise scale of the force, N (times eps).", min=0.0)
    position_noise: float = _protocol.option(1e-2, "Noise scale of the position and orientation, m (times eps).", min=0.0)
    velocity_noise: float = _protocol.option(1e-1, "Noise scale of the velocities, m/s and rad/s (times eps).", min=0.0)
    estimator: str = _control.estimator_option()
    max_iterations: int = _control.max_iterations_option(40)
    geometric_decays: tuple[float, ...] = _control.geometric_decays_option((0.5, 0.8))

    @classmethod
    def quick(cls, **changes) -> "Config":
        return dataclasses.replace(cls(seeds=2, geometric_decays=(0.5,)), **changes)

    def __post_init__(self):
        _control.check_config(self)

    def solver(self) -> control.RDDP:
        # State: position (3), quaternion (4), linear and angular velocities (6).
        state_noise = _control.free_body_state_noise(self.position_noise, (self.velocity_noise,) * 6)
        return _control.rddp_solver(self, self.force_noise, state_noise)


def _running(x, u, params):
    return 1e-6 * jnp.sum(u**2)


def _terminal(x, params):
    return 100.0 * (x[2] - params["target"]) ** 2 + x[9] ** 2


def build_problem(config: Config):
    """The system, the shooting problem and the target height (absolute, m). The target is a
    traced cost parameter: problems for other heights share the compiled solver steps."""
    system = sim.cube(wrench_components=(2,))
    x0 = system.initial_state()
    target = float(x0[2]) + config.height
    params = {"target": jnp.asarray(target, x0.dtype)}
    problem = control.ShootingProblem(system, _running, _terminal, x0, config.horizon, params=params)
    return system, problem, target


def _draw(ax, xs, us, name: str, t: int, rest: float, target: float, side: float, weight: float):
    z = float(xs[t, 2]) - rest
    ax.axhspan(-0.05, 0.0, color="0.8")
    ax.axhline(target - rest, color="tab:green", ls="--", lw=1, label="target (bottom face)")
    ax.legend(loc="upper left", fontsize=7)
    ax.add_patch(viz.plt.Rectangle((-side / 2, z), side, side, color="tab:blue", alpha=0.8))
    if t < us.shape[0]:
        force = float(us[t, 0])
        ax.annotate("", xy=(0.0, z + side / 2 + 0.1 * force / weight), xytext=(0.0, z + side / 2),
                    arrowprops={"arrowstyle": "->", "color": "tab:red", "lw": 2})
        ax.set_title(f"{name}: force {force:.1f} N", fontsize=9)
    else:
        ax.set_title(f"{name}: height {1000 * z:.0f} mm", fontsize=9)
    ax.set_xlim(-0.3, 0.3)
    ax.set_ylim(-0.05, max(0.45, target - rest + side + 0.1))
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_ylabel("height above rest (m)")


def run(config: Config, out: Path | str, key, progress: bool = True) -> dict:
    """Solves with each method and seed; writes metrics.json, cube_lift.png, cube_lift.gif."""
    out = Path(out)
    start = time.perf_counter()
    system, problem, target = build_problem(config)
    rest = float(problem.x0[2])

    def metrics_of(solution):
        height = float(solution.xs[-1, 2]) - rest
        return {
            "final_height": height,
            "max_force": float(jnp.max(jnp.abs(solution.us))),
            "success": bool(abs(height - config.height) < config.tolerance),
        }

    names, per_method, solutions = _control.solve_methods(
        config, problem, jnp.zeros((config.horizon, system.nu)), key, metrics_of, "cube-lift", progress)
    metrics = {
        "task": "cube-lift",
        "methods": list(names),
        "seeds": config.seeds,
        "target_height": config.height,
        "tolerance": config.tolerance,
        **per_method,
    }

    dt = float(system.time_step)
    times = np.arange(config.horizon + 1) * dt
    fig, axes = viz.plt.subplots(1, 4, figsize=(17, 3.6))
    _control.plot_histories(axes[:2], solutions)
    axes[0].set_title("cube-lift: true cost (first seed)")
    for name, solution in solutions.items():
        axes[2].plot(times, np.asarray(solution.xs[:, 2]) - rest, label=name)
        axes[3].step(times[:-1], np.asarray(solution.us[:, 0]), where="post", label=name)
    axes[2].axhline(config.height, color="k", ls="--", lw=1, label="target")
    axes[2].set_xlabel("time (s)")
    axes[2].set_ylabel("height above rest (m)")
    axes[2].legend(fontsize=8)
    weight = float(system.model.body_mass.sum()) * 9.81
    axes[3].axhline(weight, color="k", ls=":", lw=1, label="m g")
    axes[3].set_xlabel("time (s)")
    axes[3].set_ylabel("vertical force (N)")
    axes[3].legend(fontsize=8)
    fig.tight_layout()
    viz.save_figure(fig, out / "cube_lift.png")

    shown = tuple(n for n in ("ddp", "rddp") if n in solutions) or names[:1]
    side = 2 * float(jnp.max(system.geometry.sphere_offsets[:, 2]))
    frames = _control.frames_side_by_side(
        lambda ax, name, t: _draw(ax, solutions[name].xs, solutions[name].us, name, t, rest, target, side, weight),
        shown,
        config.horizon + 1,
    )
    viz.save_animation(frames, out / "cube_lift.gif", fps=10)
    metrics = _control.top_level(metrics, names)
    metrics["wall_time_s"] = time.perf_counter() - start
    viz.write_metrics(out / "metrics.json", metrics)
    return metrics


summary = _control.summary(
    "final height (mm), iterations", lambda metrics: f"{1000 * metrics['final_height']:.1f}, {metrics['iterations']}")

EXPERIMENT = _protocol.Experiment(
    command=("control", "cube-lift"),
    name="cube-lift",
    config=Config,
    run=run,
    summary=summary,
    help="Lift a cube resting on the floor to a target height with a vertical force, from zero force: DDP sees a "
    "zero gradient and stays put, R-DDP lifts it.",
    metrics_doc=METRICS_DOC,
)
