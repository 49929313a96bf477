"""Experiment: Solo-12, standing on its four feet, lifts one foot (Le Lidec et al. 2022, Fig. 3-4).

The robot (hard frictional contact, joint torques within +-2.7 N m) starts standing still
under its gravity-compensating torques, which are also every method's initial guess. The
task: the chosen foot's centre ``height`` above where it started at the end of the horizon,
the three other feet where they were. The costs are residuals (``0.5 ||r||^2``, solved with
Gauss-Newton Hessians):

* running: posture (joints ``0.1``, base position and orientation ``10``), velocities
  ``1e-3``, torque change from the standing torques ``1e-2`` (weights of the squares);
* terminal: lifted-foot height ``1e3``, other feet positions ``1e3``, base position ``10``,
  velocities ``1e-3``.

With the four feet pressed on the floor, the foot's height does not change under a small
change of torque (the contact impulse absorbs it): its derivative is exactly zero, DDP's first
backward pass sees no descent direction and the robot keeps its four feet on the floor.
R-DDP's smoothed dynamics (noise on the torques and on the state) contain samples where the
foot leaves the floor; their averaged Jacobians give the direction that lifts it, and the
forward pass on the true dynamics accepts it when the true cost decreases.

A run succeeds when the lifted foot ends within ``tolerance`` of the target height, the other
feet never rise more than ``max_other_height`` above the floor and slip less than
``max_other_slip``.

With the defaults (5 seeds per foot, 5 cm, ``--foot all --seed 14``): DDP 0 % on every foot
(one iteration, the foot does not move); first-order R-DDP 100 % on every foot with the
adaptive schedule and with the geometric 0.5 decay (foot at 41-48 mm, the other feet up
< 0.4 mm, slipping < 0.7 mm, base tilt 2.2 deg; 23 iterations, median); alpha-order R-DDP
100 % on FL, FR and HL, 60 % on HR (40 % geometric: runs that stall at 32 mm or never leave
the floor).

Zeroth-order R-DDP (``--estimator zeroth``) fails here: on FL, seed 0, with 32, 256 and 2,048
samples per node, no forward pass is accepted (the cost stays at 2.5, the noise decays to 0 in
11 iterations). At the first node, against first order with 2,048 samples, the relative
(Frobenius) error of its state Jacobian is 2.0 / 0.70 / 0.25 / 0.10 with 32 / 256 / 2,048 /
16,384 samples, and 0.22 with 32 first-order ones, which succeed. A first-order error is a
mean of exact Jacobians: the integration's identity blocks are exact in every sample, only the
physical terms vary; the score-function error, of size ``sqrt(d / M)`` over all ``d = 49``
inputs, lands on every entry, so the linearization couples coordinates that the physics does
not. A control variate for the identity blocks (zeroth order on ``f(x, u) - A0 (x - x0)``)
leaves it unchanged: the state Jacobian's norm, 641, is almost all ``d v+ / d q`` (against 7.5
for ``d q+ / d q`` and 13 for ``d v+ / d v``), the contact's position correction answering the
1 cm position noise with velocities of order 1 / h, and a control variate for that needs the
contact's derivatives, i.e. first order.

``--foot all`` runs each foot in turn into ``OUT/FOOT`` (:func:`expand`): the foot and the
target height are traced cost parameters, so the four share one compilation.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from rsmooth import control, sim, viz
from rsmooth._xla import device_array
from rsmooth.experiments import _control, _protocol, _scene_render
from rsmooth.experiments.solo12_sim import solo12_drawing_model

FEET = ("FL", "FR", "HL", "HR")

METRICS_DOC = """metrics.json keys: task, foot, target_height (m above the foot's start), methods,
seeds, and per method (ddp, rddp, rddp-geometric-D): success (first seed), final_cost,
iterations, converged, result, wall_time_s (the solve, compilation included),
time_per_iteration_s (median, compiled), unconverged_steps and diverged_steps (the
returned trajectory simulated again: contact solves that did not converge, steps that diverged), foot_height (final height of the lifted foot above its
start, m), other_feet_max_height (highest the other feet rose over the horizon, m),
other_feet_max_slip (their largest horizontal displacement, m), base_tilt_deg (final angle of
the base's vertical axis), base_drift (final base displacement, m), success_rate (over seeds),
median_final_cost, median_iterations, per_seed (the runs). With --method ddp or rddp, the keys
of that method are also at the top level."""


@dataclasses.dataclass(frozen=True)
class Config:
    foot: str = _protocol.option(
        "FL", "The foot to lift; all: each foot in turn, into OUT/FOOT (compiled once).", choices=FEET + ("all",))
    height: float = _protocol.option(0.05, "Target height of the foot above its start, m.", above=0.0, max=0.15)
    method: str = _control.method_option()
    horizon: int = _control.horizon_option(20)
    seeds: int = _control.seeds_option(5)
    num_samples: int = _control.samples_option(8)
    eps: float = _control.eps_option()
    torque_noise: float = _protocol.option(1.0, "Noise scale of the joint torques, N m (times eps).", min=0.0)
    position_noise: float = _protocol.option(
        1e-2, "Noise scale of the base position and orientation and the joint angles, m and rad (times eps).", min=0.0)
    velocity_noise: float = _protocol.option(1e-1, "Noise scale of the velocities, m/s and rad/s (times eps).", min=0.0)
    estimator: str = _control.estimator_option()
    max_iterations: int = _control.max_iterations_option(40)
    geometric_decays: tuple[float, ...] = _control.geometric_decays_option((0.5,))
    tolerance: float = _protocol.option(0.01, "A run succeeds when the lifted foot ends within it of the target, m.", above=0.0)
    max_other_height: float = _protocol.option(
        0.005, "A run succeeds only if the other feet never rise more than this above the floor, m.", above=0.0)
    max_other_slip: float = _protocol.option(0.01, "A run succeeds only if the other feet slip less than this, m.", above=0.0)
    frames: int = _protocol.option(
        11, "Frames of the animation (evenly spaced over the horizon); 0: no animation.", min=0)

    @classmethod
    def quick(cls, **changes) -> "Config":
        return dataclasses.replace(cls(seeds=2, geometric_decays=()), **changes)

    def __post_init__(self):
        _control.check_config(self)

    def solver(self) -> control.RDDP:
        # State: base position (3), quaternion (4), joints (12); then velocities (18).
        state_noise = _control.free_body_state_noise(self.position_noise, (self.position_noise,) * 12 + (self.velocity_noise,) * 18)
        return _control.rddp_solver(self, self.torque_noise, state_noise)


def _weight(weight: float) -> float:
    return float(np.sqrt(2.0 * weight))  # 0.5 r^2 = weight * e^2


def _running(x, u, params):
    q, v = x[:19], x[19:]
    q0, u0 = params["q0"], params["u0"]
    return jnp.concatenate([
        _weight(0.1) * (q[7:] - q0[7:]), _weight(10.0) * (q[:6] - q0[:6]), _weight(1e-3) * v, _weight(1e-2) * (u - u0)
    ])


def _terminal(x, params):
    feet = sim.solo12_foot_positions(params["system"], x)
    lifted, others = params["lifted"], params["others"]  # (4,) one-hot and (3, 4) selection
    return jnp.concatenate([
        _weight(1e3) * (lifted @ feet[:, 2:3] - params["target"]),
        _weight(1e3) * (others @ (feet - params["feet0"])).reshape(-1),
        _weight(10.0) * (x[:3] - params["q0"][:3]),
        _weight(1e-3) * x[19:],
    ])


def build_problem(config: Config, system=None):
    """The system, the shooting problem (residual costs, torque box) and the standing torques.

    The costs are defined once, here at module level, and the foot, the target height and the
    standing posture are their traced ``params``: solving for another foot or height reuses
    the compiled solver steps."""
    system = sim.solo12() if system is None else system
    x0 = system.initial_state()
    u0 = sim.solo12_standing_torques(system, x0)
    feet0 = sim.solo12_foot_positions(system, x0)
    lifted = FEET.index(config.foot)
    # The parameters are computed in NumPy: set-up code run eagerly in JAX compiles a small
    # program per operation (see rsmooth._xla.device_array).
    selection = np.eye(4)
    feet0_host = np.asarray(feet0)
    params = {
        "system": system,
        "q0": device_array(np.asarray(x0)[:19], x0.dtype),
        "u0": u0,
        "feet0": feet0,
        "lifted": device_array(selection[lifted], x0.dtype),
        "others": device_array(selection[[i for i in range(4) if i != lifted]], x0.dtype),
        "target": device_array(feet0_host[lifted, 2:3] + config.height, x0.dtype),
    }
    limit = np.asarray(system.actuation.input_limit)
    problem = control.ShootingProblem(
        system, _running, _terminal, x0, config.horizon, control_lower=-limit, control_upper=limit, residuals=True,
        params=params,
    )
    return system, problem, u0


def base_tilt_deg(x) -> float:
    """The angle between the base's vertical axis and the world's (quaternion x, y, z, w)."""
    qx, qy = float(x[3]), float(x[4])
    return float(np.degrees(np.arccos(np.clip(1.0 - 2.0 * (qx**2 + qy**2), -1.0, 1.0))))


def trajectory_metrics(system, xs, foot: str, config: Config) -> dict:
    """Foot heights, slips and base motion along a trajectory, and whether the task succeeded."""
    feet = np.asarray(jax.vmap(lambda x: sim.solo12_foot_positions(system, x))(xs))
    lifted = FEET.index(foot)
    others = [i for i in range(4) if i != lifted]
    height = float(feet[-1, lifted, 2] - feet[0, lifted, 2])
    other_height = float(np.max(feet[:, others, 2] - feet[:1, others, 2]))
    other_slip = float(np.max(np.linalg.norm(feet[:, others, :2] - feet[:1, others, :2], axis=-1)))
    return {
        "foot_height": height,
        "other_feet_max_height": other_height,
        "other_feet_max_slip": other_slip,
        "base_tilt_deg": base_tilt_deg(xs[-1]),
        "base_drift": float(np.linalg.norm(np.asarray(xs[-1, :3] - xs[0, :3]))),
        "success": bool(
            abs(height - config.height) < config.tolerance
            and other_height < config.max_other_height
            and other_slip < config.max_other_slip
        ),
    }


def _animate(system, trajectories, path: Path, frames: int, duration_s: float) -> None:
    """The trajectories side by side (DDP left, R-DDP right) at ``frames`` evenly spaced
    steps, the robot drawn with its meshes (convex hulls) by rsmooth's renderer."""
    loaded = solo12_drawing_model()
    placements = jax.jit(jax.vmap(lambda x: sim.forward_kinematics(loaded.model, system.split(x)[0])))
    _scene_render.side_by_side(loaded, [[np.asarray(p) for p in placements(jnp.asarray(xs))] for xs in trajectories],
                               path, frames, duration_s)


def run(config: Config, out: Path | str, key, progress: bool = True) -> dict:
    """Solves with each method and seed; writes metrics.json, solo_lift.png and (with
    ``config.frames``) solo_lift.gif.

    Raises:
      ValueError: ``config.foot`` is ``"all"``: :func:`expand` gives one config per foot.
    """
    if config.foot not in FEET:
        raise ValueError(f"run lifts one foot of {FEET}, got {config.foot!r}: expand(config) gives one config per foot")
    out = Path(out)
    start = time.perf_counter()
    system, problem, u0 = build_problem(config)
    names, per_method, solutions = _control.solve_methods(
        config, problem, jnp.tile(u0, (config.horizon, 1)), key,
        lambda solution: trajectory_metrics(system, solution.xs, config.foot, config), f"solo-lift {config.foot}", progress)
    metrics = {
        "task": "solo-lift",
        "foot": config.foot,
        "target_height": config.height,
        "methods": list(names),
        "seeds": config.seeds,
        **per_method,
    }

    dt = float(system.time_step)
    times = np.arange(config.horizon + 1) * dt
    lifted = FEET.index(config.foot)
    fig, axes = viz.plt.subplots(1, 4, figsize=(18, 3.6))
    _control.plot_histories(axes[:2], solutions)
    axes[0].set_title(f"solo-lift {config.foot}: true cost (first seed)")
    for index, (name, solution) in enumerate(solutions.items()):
        feet = np.asarray(jax.vmap(lambda x: sim.solo12_foot_positions(system, x))(solution.xs))
        heights = feet[:, :, 2] - feet[:1, :, 2]
        axes[2].plot(times, heights[:, lifted], color=f"C{index}", label=f"{name}: {config.foot}")
        for i in range(4):
            if i != lifted:
                axes[2].plot(times, heights[:, i], color=f"C{index}", ls=":", lw=1)
        axes[3].plot(times[:-1], np.asarray(solution.us - u0[None]), color=f"C{index}", lw=0.8)
    axes[2].axhline(config.height, color="k", ls="--", lw=1, label="target")
    axes[2].set_xlabel("time (s)")
    axes[2].set_ylabel("foot height above start (m); dotted: other feet")
    axes[2].legend(fontsize=8)
    axes[3].set_xlabel("time (s)")
    axes[3].set_ylabel("torque - standing torque (N m)")
    axes[3].set_title("12 joint torques per method")
    fig.tight_layout()
    viz.save_figure(fig, out / "solo_lift.png")

    shown = tuple(n for n in ("ddp", "rddp") if n in solutions) or names[:1]
    if config.frames:  # played at half speed
        _animate(system, [solutions[name].xs for name in shown], out / "solo_lift.gif", config.frames,
                 2.0 * config.horizon * dt)
    metrics = _control.top_level(metrics, names)
    metrics["wall_time_s"] = time.perf_counter() - start
    viz.write_metrics(out / "metrics.json", metrics)
    return metrics


def expand(config: Config) -> list[tuple[str, Config]] | None:
    """``--foot all``: one config per foot, each run into ``OUT/FOOT``; None for one foot."""
    if config.foot != "all":
        return None
    return [(foot, dataclasses.replace(config, foot=foot)) for foot in FEET]


def combine(results: dict[str, dict]) -> dict:
    """The line printed after ``--foot all``: each foot's success rate per method."""
    rates = "; ".join(
        f"{foot}: " + ", ".join(f"{m} {100 * metrics[m]['success_rate']:.0f} %" for m in metrics["methods"])
        for foot, metrics in results.items()
    )
    return {"success rate per foot": rates}


_method_summary = _control.summary(
    "foot height (mm), other feet max height (mm), iterations",
    lambda metrics: f"{1000 * metrics['foot_height']:.1f}, {1000 * metrics['other_feet_max_height']:.1f}, "
    f"{metrics['iterations']}")


def summary(metrics: dict) -> dict:
    """The lines printed after a run: the foot and its target, then each method's results."""
    return {"foot, target height (mm)": f"{metrics['foot']}, {1000 * metrics['target_height']:.0f}", **_method_summary(metrics)}


EXPERIMENT = _protocol.Experiment(
    command=("control", "solo-lift"),
    name="solo-lift",
    config=Config,
    run=run,
    summary=summary,
    help="Solo-12 standing on its four feet lifts one foot to a target height while the others stay on the floor, "
    "from the gravity-compensating torques: DDP sees a zero gradient, R-DDP breaks the contact.",
    metrics_doc=METRICS_DOC,
    expand=expand,
    combine=combine,
)
