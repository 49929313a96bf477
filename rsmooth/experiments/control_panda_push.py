"""Experiment: a Panda arm pushes a box across a table, from zero torque.

The scene (:func:`rsmooth.sim.panda_push`): example-robot-data's Panda with a spherical tool
between its fingertips, a 10 cm, 0.5 kg box on the table in front of it (box-table friction
0.4, tool-box 0.5), hard contact, 10 ms steps. The inputs are the seven joint torques beyond
gravity compensation (Franka's torque interface), bounded by Franka's limits; zero torque
holds the arm still, the tool ``tool_gap`` behind the box. The target: the box's centre
``push`` farther along ``+x``, at rest. The arm's links pass through the box and the table
unless ``colliding_links`` names them (``--colliding-links``, repeatable; ``panda_hand``,
``panda_leftfinger`` and ``panda_rightfinger`` are the links that reach them).

The costs are residuals (``0.5 ||r||^2``, Gauss-Newton Hessians): running ``1e-2 u / s`` (``s``
10 N m for the four large joints, 2 N m for the wrist's three); terminal ``10 (p - p_target)``
on the box centre's ``(x, y)``, the box's linear and angular velocities (weight 1) and the arm's
joint velocities (weight 0.1).

With the tool away from the box, the box's state does not depend on the torques: DDP's first
backward pass sees no descent direction and keeps the arm still (the box stays). R-DDP
differentiates the smoothed dynamics: with noise on the arm's joints (a few centimetres at the
tool) some samples touch the box, and their averaged Jacobians tell how a push moves it.

Methods: ``ddp``, ``rddp`` (adaptive noise), ``rddp-reheating`` and, with ``--method all``, R-DDP
with geometric noise decays. A run succeeds when the box's centre ends within
``position_tolerance`` of the target and its speed below ``speed_tolerance``.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from rsmooth import control, sim, viz
from rsmooth.experiments import _control, _protocol, _scene_render

METRICS_DOC = """metrics.json keys: task, methods, seeds, push (m), target (x, y of the box centre, m;
it starts at box_start), box_start, tool_gap (m), colliding_links, position_tolerance (m), speed_tolerance (m/s),
and per method (ddp, rddp, ...): success (first seed), final_cost, iterations, converged, result,
wall_time_s (the solve, compilation included), time_per_iteration_s (median, compiled),
unconverged_steps and diverged_steps (the returned trajectory simulated again),
position_error (final box centre to target, m), final_box (x, y, m), final_speed (box, m/s),
box_displacement (m), max_torque (N m), success_rate (over seeds), median_final_cost,
median_iterations, per_seed (the runs). With one --method, its keys are also at the top level."""

# Residual weights of the costs (see the module docstring).
CONTROL_WEIGHT = 1e-2
TORQUE_SCALES = (10.0, 10.0, 10.0, 10.0, 2.0, 2.0, 2.0)
POSITION_WEIGHT = 10.0
BOX_VELOCITY_WEIGHT = 1.0
ARM_VELOCITY_WEIGHT = 0.1
ARM, BOX = 7, 7  # configuration sizes: the arm's joints, the box's position and quaternion
NQ = ARM + BOX


@dataclasses.dataclass(frozen=True)
class Config:
    method: str = _control.method_option()
    push: float = _protocol.option(0.1, "How far the box's centre must move along +x, m.", above=0.0, below=0.3)
    tool_gap: float = _protocol.option(0.03, "Gap between the tool and the box's -x face at the start, m.", min=0.0)
    colliding_links: tuple[str, ...] = _protocol.option(
        (), "Links of the arm that collide with the box and the table beside the tool (panda_hand, panda_leftfinger "
        "and panda_rightfinger: the hand).", choices=sim.PANDA_LINKS)
    horizon: int = _control.horizon_option(40)
    seeds: int = _control.seeds_option(5)
    num_samples: int = _control.samples_option(16)
    eps: float = _control.eps_option()
    torque_noise: float = _protocol.option(5.0, "Noise scale of the joint torques, N m (times eps).", min=0.0)
    joint_noise: float = _protocol.option(
        0.05, "Noise scale of the arm's joint angles, rad (times eps): a few centimetres at the tool.", min=0.0)
    joint_velocity_noise: float = _protocol.option(0.5, "Noise scale of the arm's joint velocities, rad/s (times eps).",
                                                   min=0.0)
    box_position_noise: float = _protocol.option(
        1e-2, "Noise scale of the box's position and orientation, m (times eps).", min=0.0)
    box_velocity_noise: float = _protocol.option(0.1, "Noise scale of the box's velocities, m/s and rad/s (times eps).",
                                                 min=0.0)
    estimator: str = _control.estimator_option()
    max_iterations: int = _control.max_iterations_option(25)
    geometric_decays: tuple[float, ...] = _control.geometric_decays_option((0.5,))
    position_tolerance: float = _protocol.option(0.02, "A run succeeds when the box centre ends within it of the target, m.",
                                                 above=0.0)
    speed_tolerance: float = _protocol.option(0.05, "A run succeeds only if the box's final speed is below it, m/s.",
                                              above=0.0)
    frames: int = _protocol.option(
        21, "Frames of the animation (evenly spaced over the horizon); 0: no animation.", min=0)

    @classmethod
    def quick(cls, **changes) -> "Config":
        return dataclasses.replace(cls(seeds=1, geometric_decays=(), max_iterations=20), **changes)

    def __post_init__(self):
        _control.check_config(self)

    def solver(self) -> control.RDDP:
        state_noise = ((self.joint_noise,) * ARM + _control.free_body_state_noise(self.box_position_noise, ())
                       + (self.joint_velocity_noise,) * ARM + (self.box_velocity_noise,) * 6)
        return _control.rddp_solver(self, self.torque_noise, state_noise)


def build_problem(config: Config):
    """The system, the shooting problem and the target ``(x, y)`` of the box's centre (m).

    Example:
        >>> system, problem, target = build_problem(Config.quick())
        >>> problem.nx, problem.nu, problem.horizon, problem.residuals
        (27, 7, 40, True)
        >>> [round(v, 4) for v in target]
        [0.65, 0.0]
    """
    system = sim.panda_push(tool_gap=config.tool_gap, colliding_links=config.colliding_links)
    x0 = system.initial_state()
    target = (float(x0[ARM]) + config.push, float(x0[ARM + 1]))
    # The target is a traced cost parameter: other pushes share the compiled solver steps.
    params = {"target": jnp.asarray(target, x0.dtype)}
    problem = control.ShootingProblem(system, _running, _terminal, x0, config.horizon, residuals=True, params=params)
    return system, problem, target


def _running(x, u, params):
    return CONTROL_WEIGHT * u / jnp.asarray(TORQUE_SCALES, u.dtype)


def _terminal(x, params):
    return jnp.concatenate([
        POSITION_WEIGHT * (x[ARM : ARM + 2] - params["target"]),
        BOX_VELOCITY_WEIGHT * x[NQ + ARM : NQ + ARM + 6],
        ARM_VELOCITY_WEIGHT * x[NQ : NQ + ARM],
    ])


def trajectory_metrics(xs, us, target, config: Config) -> dict:
    """The task's metrics of a trajectory (see ``METRICS_DOC``)."""
    xs, us = np.asarray(xs), np.asarray(us)
    final = xs[-1, ARM : ARM + 2]
    metrics = {
        "position_error": float(np.hypot(*(final - np.asarray(target)))),
        "final_box": [float(final[0]), float(final[1])],
        "final_speed": float(np.linalg.norm(xs[-1, NQ + ARM : NQ + ARM + 3])),
        "box_displacement": float(np.hypot(*(final - xs[0, ARM : ARM + 2]))),
        "max_torque": float(np.max(np.abs(us))),
    }
    metrics["success"] = bool(metrics["position_error"] < config.position_tolerance
                              and metrics["final_speed"] < config.speed_tolerance)
    return metrics


def _tool_positions(system, xs) -> np.ndarray:
    """The tool's centre ``(T + 1, 3)`` along a trajectory (world, m)."""
    frame = system.model.frame_id("panda_hand_tcp")
    return np.asarray(jax.jit(jax.vmap(lambda q: sim.frame_placement(system.model, q, frame)[1]))(jnp.asarray(xs)[:, :NQ]))


def _animate(system, trajectories, path: Path, frames: int) -> None:
    """The trajectories side by side (DDP left, R-DDP right) at ``frames`` evenly spaced
    steps, played in real time, the arm drawn with its collision meshes by rsmooth's renderer."""
    loaded = sim.panda_push_model()
    placements = jax.jit(jax.vmap(lambda q: sim.forward_kinematics(system.model, q)))
    _scene_render.side_by_side(loaded, [[np.asarray(p) for p in placements(jnp.asarray(xs)[:, :NQ])] for xs in trajectories],
                               path, frames, (trajectories[0].shape[0] - 1) * float(system.time_step))


def run(config: Config, out: Path, key, progress: bool = True) -> dict:
    """Solves with each method and seed; writes metrics.json, panda_push.png and (with
    ``config.frames``) panda_push.gif (DDP and R-DDP side by side, first seed)."""
    start_time = time.perf_counter()
    system, problem, target = build_problem(config)
    names, per_method, solutions = _control.solve_methods(
        config, problem, jnp.zeros((config.horizon, system.nu)), key,
        lambda solution: trajectory_metrics(solution.xs, solution.us, target, config), "panda push", progress)
    x0 = np.asarray(problem.x0)
    metrics = {
        "task": "panda-push",
        "methods": list(names),
        "seeds": config.seeds,
        "push": config.push,
        "target": list(target),
        "box_start": [float(x0[ARM]), float(x0[ARM + 1])],
        "tool_gap": config.tool_gap,
        "colliding_links": list(config.colliding_links),
        "position_tolerance": config.position_tolerance,
        "speed_tolerance": config.speed_tolerance,
        **per_method,
    }
    fig, axes = viz.plt.subplots(1, 3, figsize=(15, 4.2))
    _control.plot_histories(axes[:2], solutions)
    axes[0].set_title("panda push: true cost (first seed)")
    ax = axes[2]
    times = np.arange(config.horizon + 1) * float(system.time_step)
    for index, (name, solution) in enumerate(solutions.items()):
        xs = np.asarray(solution.xs)
        tool = _tool_positions(system, xs)
        ax.plot(times, xs[:, ARM], color=f"C{index}", lw=1.5, label=f"{name}: box centre x")
        ax.plot(times, tool[:, 0], color=f"C{index}", lw=1, ls=":", label=f"{name}: tool x")
    ax.axhline(target[0], color="k", ls="--", lw=1, label="target")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("x (m)")
    ax.set_title("the box and the tool along the push (first seed)", fontsize=9)
    ax.legend(fontsize=6, loc="center left", bbox_to_anchor=(1.02, 0.5))
    fig.tight_layout()
    viz.save_figure(fig, out / "panda_push.png")
    if config.frames:
        shown = [name for name in ("ddp", "rddp") if name in solutions] or list(solutions)
        _animate(system, [np.asarray(solutions[name].xs) for name in shown], out / "panda_push.gif", config.frames)
    metrics = _control.top_level(metrics, names)
    metrics["wall_time_s"] = time.perf_counter() - start_time
    viz.write_metrics(out / "metrics.json", metrics)
    return metrics


summary = _control.summary(
    "position error (mm), box displacement (mm), iterations",
    lambda metrics: f"{1000 * metrics['position_error']:.1f}, {1000 * metrics['box_displacement']:.1f}, "
                    f"{metrics['iterations']}")

EXPERIMENT = _protocol.Experiment(
    command=("control", "panda-push"),
    name="panda-push",
    config=Config,
    run=run,
    summary=summary,
    help="A Panda arm (example-robot-data) pushes a box 10 cm across a table with a tool that starts 3 cm behind it, "
    "from zero torque (gravity compensated): DDP sees a zero gradient and leaves the box, R-DDP pushes it.",
    metrics_doc=METRICS_DOC,
)
