"""Experiment: simulate Solo-12 with hard frictional contact and write an animation.

``standing`` applies the gravity-compensating torques of the standing posture: the robot must
hold still. Under constant torques that posture is an unstable equilibrium (bending a knee
lengthens gravity's lever arm while the torque stays the same), so errors at the contact
solver's tolerance grow until the robot collapses after a few seconds; standing longer needs
feedback, as on the real robot. ``random`` adds uniform random torques (a fresh draw every
``hold`` steps) to them and to a joint PD controller that holds the standing posture: the robot
shakes, feet may slip or leave the floor, and the simulation must stay sane (contact solver
converged, no penetration, no diverged step). The base and the knees collide with the floor as
well (unless ``body_contacts`` is off). With ``open_loop`` (or ``stiffness = damping = 0``) the
torques are open loop and the robot falls, which the simulator integrates too (the model's
rotor inertia and joint damping keep the lifted legs from spinning up, see
:func:`rsmooth.sim.solo12`). The animation draws the robot's meshes with rsmooth's renderer
(:mod:`rsmooth.experiments._scene_render`); the plot shows the base's and feet's heights in
millimetres from their start."""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from rsmooth import _checks, sim, viz
from rsmooth.experiments import _protocol, _scene_render

METRICS_DOC = """metrics.json keys: torques ('standing' or 'random'), steps, time_step,
base_height_initial, base_height_final, base_height_min, base_drift (|final - initial base
position|, m), base_height_drift (|final - initial base height|, m), max_foot_slip (largest horizontal foot displacement, m), min_foot_distance
(signed distance of the lowest foot, m: penetration if negative), min_body_distance (the same for
the base and knee spheres; null without body contacts), ncp_converged_fraction,
ncp_max_iterations, torque_clipped_steps, diverged_steps (steps flagged by StepInfo.diverged;
the state is held from the first one on), wall_time_s (compile included)."""


@dataclasses.dataclass(frozen=True)
class Config:
    torques: str = _protocol.option(
        "standing", "The gravity-compensating torques alone, or with random torques and a posture PD on top.",
        choices=("standing", "random"))
    steps: int = _protocol.option(200, "Time steps of 10 ms.", min=1)
    random_scale: float = _protocol.option(
        0.1, "Amplitude of the random torques, N m (uniform in -scale, scale on each joint).", min=0.0)
    hold: int = _protocol.option(1, "Steps between two draws of the random torques.", min=1)
    stiffness: float = _protocol.option(1.0, "Stiffness of the posture PD under random torques, N m / rad.", min=0.0)
    damping: float = _protocol.option(0.02, "Damping of the posture PD under random torques, N m s / rad.", min=0.0)
    open_loop: bool = _protocol.option(
        False, "No posture PD under random torques (stiffness and damping 0): the robot falls.")
    frames: int = _protocol.option(50, "Frames of the animation.", min=2)
    body_contacts: bool = _protocol.option(
        True, "Whether the base and knees collide with the floor too (sim.solo12), or the feet only.",
        flag="body-contacts/feet-only")

    @classmethod
    def quick(cls, **changes) -> "Config":
        return dataclasses.replace(cls(steps=100, frames=25), **changes)

    def __post_init__(self):
        _protocol.check_options(self)

    def gains(self) -> tuple[float, float]:
        """The posture PD's ``(stiffness, damping)``: zero for standing torques or open loop."""
        if self.torques != "random" or self.open_loop:
            return 0.0, 0.0
        return self.stiffness, self.damping


def solo12_drawing_model():
    """Solo-12's URDF loaded by MuJoCo with its visual meshes (drawn by their convex hulls of at
    most 48 vertices: see :mod:`rsmooth.experiments._scene_render`); its kinematic tree is
    :func:`rsmooth.sim.solo12`'s, joint for joint."""
    root = Path(sim.example_robot_data_root())
    return sim.load_mjcf(sim.solo12_urdf_path(), package_dirs=(str(root.parent),), floating_base=True, visuals=True,
                         max_hull_vertices=48)


def run(config: Config, out: Path | str, key, progress: bool = True) -> dict:
    """Simulates, writes metrics.json, solo12.png and solo12.gif under `out`."""
    out = Path(out)
    start = time.perf_counter()
    system = sim.solo12(body_contacts=config.body_contacts)
    x0 = system.initial_state()
    standing = sim.solo12_standing_torques(system, x0)
    perturbations = jnp.zeros((config.steps, system.nu))
    gains = config.gains()
    if config.torques == "random":
        draws = -(-config.steps // config.hold)
        noise = jax.random.uniform(key, (draws, system.nu), minval=-1.0, maxval=1.0) * config.random_scale
        perturbations = jnp.repeat(noise, config.hold, axis=0)[: config.steps]
    posture = system.split(x0)[0][7:]
    bar = tqdm(total=2 + config.frames, desc=f"solo12 ({config.torques})", disable=not progress)

    def posture_pd(x):
        q, v = system.split(x)
        return gains[0] * (posture - q[7:]) - gains[1] * v[6:]

    # The rollout's diagnostics are checked below (sim.check_steps), so its program leaves out
    # the steps' traced checks: the persistent compilation cache can then keep it.
    @jax.jit
    @_checks.without_traced_checks()
    def simulate(x0, perturbations):
        return system.rollout(x0, standing[None] + perturbations, feedback=posture_pd)

    xs, infos = simulate(x0, perturbations)
    xs = jax.block_until_ready(xs)
    sim.check_steps(infos, what=f"solo12 ({config.torques} torques)")
    bar.update()
    feet = np.asarray(jax.vmap(lambda x: sim.solo12_foot_positions(system, x))(xs))
    slip = np.max(np.linalg.norm(feet[:, :, :2] - feet[:1, :, :2], axis=-1))
    distances = np.asarray(infos.distance)
    dt = float(system.time_step)
    metrics = {
        "torques": config.torques,
        "steps": config.steps,
        "time_step": dt,
        "base_height_initial": float(xs[0, 2]),
        "base_height_final": float(xs[-1, 2]),
        "base_height_min": float(jnp.min(xs[:, 2])),
        "base_drift": float(jnp.linalg.norm(xs[-1, :3] - xs[0, :3])),
        "base_height_drift": float(jnp.abs(xs[-1, 2] - xs[0, 2])),
        "max_foot_slip": float(slip),
        "min_foot_distance": float(distances[:, :4].min()),
        "min_body_distance": float(distances[:, 4:].min()) if config.body_contacts else None,
        "ncp_converged_fraction": float(np.mean(np.asarray(infos.ncp.converged))),
        "ncp_max_iterations": int(np.max(np.asarray(infos.ncp.iterations))),
        "torque_clipped_steps": int(np.sum(np.asarray(infos.torque_clipped))),
        "diverged_steps": int(np.sum(np.asarray(infos.diverged))),
    }
    times = np.arange(config.steps + 1) * dt
    fig, (ax_base, ax_feet) = viz.plt.subplots(1, 2, figsize=(11, 3.6))
    # Drift in mm from the start, on a plain axis: raw heights in metres hide a drift of 1e-7 m
    # behind matplotlib's offset notation (`1e-13 + 0.2349`).
    ax_base.plot(times, 1e3 * (np.asarray(xs[:, 2]) - float(xs[0, 2])), color="k")
    ax_base.set_xlabel("time (s)")
    ax_base.set_ylabel("base height - start (mm)")
    ax_base.set_title(f"Solo-12, {config.torques} torques (base starts at {1e3 * float(xs[0, 2]):.1f} mm)")
    for i, name in enumerate(sim.SOLO12_FEET):
        ax_feet.plot(times, 1e3 * (feet[:, i, 2] - sim.SOLO12_FOOT_RADIUS), label=name)
    ax_feet.set_xlabel("time (s)")
    ax_feet.set_ylabel("foot height above floor (mm)")
    ax_feet.legend(fontsize=8)
    for ax in (ax_base, ax_feet):
        ax.ticklabel_format(axis="y", useOffset=False)
    fig.tight_layout()
    viz.save_figure(fig, out / "solo12.png")
    bar.update()
    loaded = solo12_drawing_model()
    shown = np.linspace(0, config.steps, config.frames).round().astype(int)
    rotations, translations = (np.asarray(p) for p in jax.jit(jax.vmap(
        lambda x: sim.forward_kinematics(loaded.model, system.split(x)[0])))(xs[shown]))
    draw = _scene_render.SceneFrames(loaded, _scene_render.bounds(loaded, (rotations, translations)), image_size=(200, 260))
    frames = []
    for k in range(len(shown)):
        frames.append(draw(rotations[k], translations[k]))
        bar.update()
    bar.close()
    viz.save_animation(frames, out / "solo12.gif", fps=max(1, round(config.frames / (config.steps * dt))))
    metrics["wall_time_s"] = time.perf_counter() - start
    viz.write_metrics(out / "metrics.json", metrics)
    return metrics


def summary(metrics: dict) -> dict:
    """The lines printed after a run: drift, slip, the contact solver, diverged steps."""
    return {
        "base drift (m)": f"{metrics['base_drift']:.2e} (height {metrics['base_height_drift']:.2e})",
        "max foot slip (m)": f"{metrics['max_foot_slip']:.2e}",
        "contact solves converged": f"{100 * metrics['ncp_converged_fraction']:.1f} %",
        "diverged steps": metrics["diverged_steps"],
    }


EXPERIMENT = _protocol.Experiment(
    command=("sim", "solo12"),
    name="solo12",
    config=Config,
    run=run,
    summary=summary,
    help="Simulate Solo-12 on the floor under standing (gravity-compensating) or random torques and write an "
    "animation of its meshes drawn by rsmooth's renderer.",
    metrics_doc=METRICS_DOC,
)
