"""Experiment: a finger pushes a box to a target pose (position and yaw) on the floor.

The pusher (``rsmooth.sim.pusher``: a 20 cm, 1 kg box on the floor with friction 0.4, a
finger of 0.1 kg moving in the horizontal plane at the box's mid-height, finger-box friction
0.5, hard contact, 10 ms steps) starts at rest with the finger ``finger_gap`` behind the
box's ``-x`` face, ``finger_y`` off its centre line (default on it); the inputs are the two
finger forces (``+-20 N``), starting from zero. The target is the box centre at
``(target_x, target_y)`` turned by ``target_yaw`` about the vertical, at rest. A push along the
centre line only translates the box: to turn it the finger must push off-centre or obliquely,
the contact sticking or sliding along the face, then brake so that the box (slowed by the
floor friction) stops on the target.

The costs are residuals (``0.5 ||r||^2``, Gauss-Newton Hessians): running ``1e-2 u``;
terminal ``10 (p - p_target)`` on the box centre, ``4 * 2 sin((yaw - yaw_target) / 2)`` on
its yaw (``4 (yaw - yaw_target)`` near the target, from the quaternion without a branch) and
the box's linear and angular velocities (weight 1).

With the finger away from the box, the box's state does not depend on the finger force:
every derivative of the box's pose with respect to the controls is exactly zero, DDP's first
backward pass sees no descent direction (the control cost alone is minimal at zero force)
and the box stays where it was. R-DDP differentiates the smoothed dynamics: with noise on the
finger's position and velocity, some samples touch the box, and their averaged Jacobians tell
how a push moves and turns it; the forward pass on the true dynamics keeps a step only when
the true cost decreases, and the noise goes to zero at the end.

Methods: ``ddp``, ``rddp`` (adaptive noise: reduced only when the smoothed problem stalls) and
``rddp-geometric-D`` (noise multiplied by ``D`` at every iteration). R-DDP runs over several
seeds (its samples change, the task does not); a run succeeds when the final box centre is
within ``position_tolerance`` of the target, its yaw within ``yaw_tolerance`` and its speed
below ``speed_tolerance``.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from rsmooth import control, sim, viz
from rsmooth.experiments import _control, _protocol

METRICS_DOC = """metrics.json keys: task, methods, seeds, target (x m, y m, yaw deg; the box starts
at the origin with yaw 0), finger_gap (m), finger_y (m), position_tolerance (m),
yaw_tolerance_deg, speed_tolerance (m/s), and per method (ddp, rddp, rddp-geometric-D): success
(first seed), final_cost, iterations, converged, result, wall_time_s (the solve, compilation
included), time_per_iteration_s (median, compiled), unconverged_steps and diverged_steps (the
returned trajectory simulated again: contact solves that did not converge, steps that diverged), position_error (final box centre to target,
m), yaw_error_deg, final_box (x m, y m, yaw deg), final_speed (box, m/s), box_displacement
(final box centre to its start, m), max_force (N), success_rate (over seeds), median_final_cost,
median_iterations, per_seed (the runs). With --method ddp or rddp, the keys of that method are
also at the top level."""

# Residual weights of the costs (see the module docstring).
CONTROL_WEIGHT = 1e-2
POSITION_WEIGHT = 10.0
YAW_WEIGHT = 4.0
VELOCITY_WEIGHT = 1.0


@dataclasses.dataclass(frozen=True)
class Config:
    method: str = _control.method_option()
    target_x: float = _protocol.option(0.10, "Target box centre x, m (the box starts at 0).")
    target_y: float = _protocol.option(0.0, "Target box centre y, m.")
    target_yaw: float = _protocol.option(15.0, "Target yaw, degrees counter-clockwise seen from above.", min=-89.0, max=89.0)
    finger_gap: float = _protocol.option(0.03, "Gap between the finger and the box's -x face at the start, m.", min=0.0)
    finger_y: float = _protocol.option(
        0.0, "The finger's start off the box's centre line, m, within the box's half side (0.1 m).")
    horizon: int = _control.horizon_option(40)
    seeds: int = _control.seeds_option(10)
    num_samples: int = _control.samples_option(16)
    eps: float = _control.eps_option()
    force_noise: float = _protocol.option(10.0, "Noise scale of the finger forces, N (times eps).", min=0.0)
    box_position_noise: float = _protocol.option(
        1e-2, "Noise scale of the box's position and orientation, m (times eps).", min=0.0)
    finger_position_noise: float = _protocol.option(
        3e-2, "Noise scale of the finger's position, m (times eps): of the order of the gap.", min=0.0)
    box_velocity_noise: float = _protocol.option(
        1e-1, "Noise scale of the box's velocities, m/s and rad/s (times eps).", min=0.0)
    finger_velocity_noise: float = _protocol.option(5e-1, "Noise scale of the finger's velocity, m/s (times eps).", min=0.0)
    estimator: str = _control.estimator_option()
    max_iterations: int = _control.max_iterations_option(20)
    geometric_decays: tuple[float, ...] = _control.geometric_decays_option((0.5, 0.8))
    position_tolerance: float = _protocol.option(0.02, "A run succeeds when the box centre ends within it of the target, m.", above=0.0)
    yaw_tolerance: float = _protocol.option(5.0, "A run succeeds only if the box's yaw ends within it of the target's, degrees.", above=0.0)
    speed_tolerance: float = _protocol.option(0.05, "A run succeeds only if the box's final speed is below it, m/s.", above=0.0)

    @classmethod
    def quick(cls, **changes) -> "Config":
        return dataclasses.replace(cls(seeds=2, geometric_decays=(), max_iterations=12), **changes)

    def __post_init__(self):
        _control.check_config(self)
        if not abs(self.finger_y) < 0.1:
            raise ValueError(f"finger_y must be within the box's half side, |finger_y| < 0.1 m, got {self.finger_y}")

    def target(self) -> tuple[float, float, float]:
        """The target pose ``(x, y, yaw)``, m and radians."""
        return self.target_x, self.target_y, float(np.radians(self.target_yaw))

    def solver(self) -> control.RDDP:
        # State: box position (3), quaternion (4), finger x, y; box linear and angular
        # velocities (6), finger velocities (2).
        state_noise = _control.free_body_state_noise(
            self.box_position_noise,
            (self.finger_position_noise,) * 2 + (self.box_velocity_noise,) * 6 + (self.finger_velocity_noise,) * 2,
        )
        return _control.rddp_solver(self, self.force_noise, state_noise)


def box_pose(xs) -> np.ndarray:
    """Box centre ``(x, y)`` and yaw (radians, in ``(-pi, pi]``) of states ``(..., 17)``.

    Example:
        >>> import numpy as np
        >>> x = np.zeros(17)
        >>> x[0], x[5], x[6] = 0.1, np.sin(np.radians(15) / 2), np.cos(np.radians(15) / 2)
        >>> [round(float(v), 6) for v in box_pose(x) * [1, 1, 180 / np.pi]]
        [0.1, 0.0, 15.0]
    """
    xs = np.asarray(xs)
    yaw = 2.0 * np.arctan2(xs[..., 5], xs[..., 6])
    return np.stack([xs[..., 0], xs[..., 1], np.angle(np.exp(1j * yaw))], axis=-1)


def build_problem(config: Config):
    """The system, the shooting problem and the target pose ``(x, y, yaw)`` (m, radians).

    Example:
        >>> system, problem, target = build_problem(Config.quick())
        >>> problem.nx, problem.nu, problem.horizon, problem.residuals
        (17, 2, 40, True)
        >>> [round(v, 4) for v in target]
        [0.1, 0.0, 0.2618]
    """
    target = config.target()
    system, problem = make_problem(target, config.horizon, finger_gap=config.finger_gap, finger_y=config.finger_y)
    return system, problem, target


def make_problem(target, horizon: int, *, finger_gap: float, finger_y: float = 0.0, at_rest: bool = True):
    """The system and the shooting problem (the costs of the module docstring) of pushing the
    box from the origin to the pose ``target = (x, y, yaw)`` (m, radians) in ``horizon`` steps,
    the finger starting ``finger_gap`` behind the box, ``finger_y`` off its centre line;
    without ``at_rest``, the terminal cost leaves out the box's velocities."""
    system = sim.pusher()
    x0 = sim.pusher_start_state(system, finger_gap=finger_gap, finger_y=finger_y)
    # The target is a traced cost parameter: other targets share the compiled solver steps.
    params = {
        "position": jnp.asarray(target[:2], x0.dtype),
        "half_yaw": jnp.asarray([np.cos(target[2] / 2), np.sin(target[2] / 2)], x0.dtype),
    }
    terminal = _terminal if at_rest else _terminal_pose
    problem = control.ShootingProblem(system, _running, terminal, x0, horizon, residuals=True, params=params)
    return system, problem


def _running(x, u, params):
    return CONTROL_WEIGHT * u


def _terminal_pose(x, params):
    # For a rotation about z, q = (0, 0, sin(yaw/2), cos(yaw/2)) and
    # q_z cos(yaw_t/2) - q_w sin(yaw_t/2) = sin((yaw - yaw_t)/2): smooth, no angle wrap.
    half_cos, half_sin = params["half_yaw"][0], params["half_yaw"][1]
    yaw = 2.0 * (x[5] * half_cos - x[6] * half_sin)
    return jnp.concatenate([POSITION_WEIGHT * (x[:2] - params["position"]), YAW_WEIGHT * yaw[None]])


def _terminal(x, params):
    return jnp.concatenate([_terminal_pose(x, params), VELOCITY_WEIGHT * x[9:15]])


def pose_metrics(xs, us, target) -> dict:
    """The box's final pose against the target, its displacement and the largest force of a
    trajectory (see ``METRICS_DOC``)."""
    pose = box_pose(xs)
    final = pose[-1]
    return {
        "position_error": float(np.hypot(*(final[:2] - np.asarray(target[:2])))),
        "yaw_error_deg": float(np.degrees(abs(np.angle(np.exp(1j * (final[2] - target[2])))))),
        "final_box": [float(final[0]), float(final[1]), float(np.degrees(final[2]))],
        "final_speed": float(np.linalg.norm(np.asarray(xs[-1, 9:12]))),
        "box_displacement": float(np.hypot(*(pose[-1, :2] - pose[0, :2]))),
        "max_force": float(np.max(np.abs(np.asarray(us)))),
    }


def trajectory_metrics(xs, us, target, config: Config) -> dict:
    """The task's metrics of a trajectory (see ``METRICS_DOC``)."""
    metrics = pose_metrics(xs, us, target)
    metrics["success"] = bool(
        metrics["position_error"] < config.position_tolerance
        and metrics["yaw_error_deg"] < config.yaw_tolerance
        and metrics["final_speed"] < config.speed_tolerance
    )
    return metrics


def _box_outline(pose, side: float) -> np.ndarray:
    """The four corners ``(4, 2)`` of the box's top-down square at ``pose = (x, y, yaw)``."""
    corners = 0.5 * side * np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=float)
    c, s = np.cos(pose[2]), np.sin(pose[2])
    return corners @ np.array([[c, s], [-s, c]]) + np.asarray(pose[:2])


def _draw_scene(ax, side: float, start, target) -> None:
    ax.add_patch(viz.plt.Polygon(_box_outline(start, side), fill=False, ec="0.6", ls=":", lw=1, label="start"))
    ax.add_patch(viz.plt.Polygon(_box_outline(target, side), fill=False, ec="k", ls="--", lw=1.2, label="target"))


def _draw_frame(ax, xs, us, name: str, t: int, side: float, radius: float, start, target, limits):
    _draw_scene(ax, side, start, target)
    pose = box_pose(xs[t])
    ax.add_patch(viz.plt.Polygon(_box_outline(pose, side), color="tab:blue", alpha=0.7, label="box"))
    finger = np.asarray(xs[t, 7:9])
    ax.add_patch(viz.plt.Circle(finger, radius, color="tab:red", label="finger"))
    if t < us.shape[0]:
        force = np.asarray(us[t])
        ax.annotate("", xy=finger + 0.005 * force, xytext=finger, arrowprops={"arrowstyle": "->", "color": "tab:red", "lw": 1.5})
        ax.set_title(f"{name}: t = {10 * t} ms, force ({force[0]:.1f}, {force[1]:.1f}) N", fontsize=8)
    else:
        ax.set_title(f"{name}: final yaw {np.degrees(pose[2]):.1f} deg", fontsize=8)
    ax.set_xlim(*limits[0])
    ax.set_ylim(*limits[1])
    ax.set_aspect("equal")
    ax.legend(loc="upper left", fontsize=6)


def _view_limits(config: Config, side: float):
    """Top-view limits holding the start (finger included) and the target."""
    x = (min(-0.35, config.target_x - side), max(0.3, config.target_x + side))
    y = (min(-0.25, config.target_y - side), max(0.25, config.target_y + side))
    return x, y


def run(config: Config, out: Path, key, progress: bool = True) -> dict:
    """Solves with each method and seed; writes metrics.json, pusher.png and pusher.gif."""
    start_time = time.perf_counter()
    system, problem, target = build_problem(config)
    names, per_method, solutions = _control.solve_methods(
        config, problem, jnp.zeros((config.horizon, system.nu)), key,
        lambda solution: trajectory_metrics(solution.xs, solution.us, target, config), "pusher", progress)
    metrics = {
        "task": "pusher",
        "methods": list(names),
        "seeds": config.seeds,
        "target": [config.target_x, config.target_y, config.target_yaw],
        "finger_gap": config.finger_gap,
        "finger_y": config.finger_y,
        "position_tolerance": config.position_tolerance,
        "yaw_tolerance_deg": config.yaw_tolerance,
        "speed_tolerance": config.speed_tolerance,
        **per_method,
    }

    finger = system.geometry.geom_pairs[0]  # the box (shape 1) and the finger (shape 2)
    side, radius = 2 * float(finger.shape1.half_extents[0]), float(finger.shape2.radius)
    start = box_pose(problem.x0)
    fig, axes = viz.plt.subplots(1, 3, figsize=(15, 4.2))
    _control.plot_histories(axes[:2], solutions)
    axes[0].set_title("pusher: true cost (first seed)")
    ax = axes[2]
    _draw_scene(ax, side, start, target)
    for index, (name, solution) in enumerate(solutions.items()):
        xs = np.asarray(solution.xs)
        color = f"C{index}"
        ax.plot(xs[:, 0], xs[:, 1], color=color, lw=1.5, label=f"{name}: box centre")
        ax.plot(xs[:, 7], xs[:, 8], color=color, lw=1, ls=":", label=f"{name}: finger")
        ax.plot(xs[-1, [0, 7]], xs[-1, [1, 8]], "o", color=color, ms=3)  # final box centre and finger
        ax.add_patch(viz.plt.Polygon(_box_outline(box_pose(xs[-1]), side), fill=False, ec=color, lw=1.5))
    limits = _view_limits(config, side)
    ax.set_xlim(*limits[0])
    ax.set_ylim(*limits[1])
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title("top view: paths and final boxes (first seed)", fontsize=9)
    ax.legend(fontsize=6, loc="center left", bbox_to_anchor=(1.02, 0.5))
    fig.tight_layout()
    viz.save_figure(fig, out / "pusher.png")

    shown = tuple(n for n in ("ddp", "rddp") if n in solutions) or names[:1]
    # Every other step (20 ms a frame, played 5 times slower than real time) and the last.
    steps = sorted(set(range(0, config.horizon + 1, 2)) | {config.horizon})
    frames = _control.frames_side_by_side(
        lambda ax, name, i: _draw_frame(
            ax, np.asarray(solutions[name].xs), np.asarray(solutions[name].us), name, steps[i], side, radius, start, target, limits
        ),
        shown,
        len(steps),
    )
    viz.save_animation(frames, out / "pusher.gif", fps=10)
    metrics = _control.top_level(metrics, names)
    metrics["wall_time_s"] = time.perf_counter() - start_time
    viz.write_metrics(out / "metrics.json", metrics)
    return metrics


summary = _control.summary(
    "position error (mm), yaw error (deg), iterations",
    lambda metrics: f"{1000 * metrics['position_error']:.1f}, {metrics['yaw_error_deg']:.1f}, {metrics['iterations']}")

EXPERIMENT = _protocol.Experiment(
    command=("control", "pusher"),
    name="pusher",
    config=Config,
    run=run,
    summary=summary,
    help="Push a box to a target pose (position and yaw) with a finger that starts 3 cm behind it, through sticking "
    "and sliding friction, from zero force: DDP sees a zero gradient and leaves the box, R-DDP pushes it.",
    metrics_doc=METRICS_DOC,
)
