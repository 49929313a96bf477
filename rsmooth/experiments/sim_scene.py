"""Experiment: simulate a MuJoCo scene (MJCF or URDF) under gravity and write an animation.

The file is converted by :func:`rsmooth.sim.scene` (its geoms paired as MuJoCo pairs them) and
simulated from MuJoCo's ``qpos0`` at rest, with zero input, with hard frictional contact. The
metrics say whether the simulation stayed sane: the deepest penetration, the change of
mechanical energy (with zero input it can only be dissipated by contacts and damping: a gain
is energy injected by the time stepping), the contacts active per step and the contact solves
that did not converge. The animation draws every geom as its triangulated shape (rsmooth's own
renderer, a directional light; :mod:`rsmooth.experiments._scene_render`); the plot shows the
energy and the active contacts over time. Without ``--file`` a built-in scene is simulated: a stack of two
boxes, a ball, a capsule lying on its side, a brick and a cylinder on a floor.

A robot's URDF (e.g. one of example-robot-data) is not a scene: ``--floating-base`` frees its
base, ``--floor`` puts a floor under it and ``--no-self-collision`` drops the contacts between
its own links (see :func:`rsmooth.sim.scene`); with zero torque on its joints it is left to
gravity and the floor."""

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

METRICS_DOC = """metrics.json keys: file (the scene simulated; 'built-in' for the default), steps,
time_step (s), bodies (MuJoCo bodies, the world included), geom_pairs, candidate_contacts,
max_penetration (deepest penetration over the run, m), initial_penetration (the deepest at
the start, the file's configuration: shapes that overlap there are pushed apart by the contact
correction, which injects energy; m), energy_initial, energy_final (J),
energy_change (final - initial, J), energy_max_gain (largest rise above the initial energy
over the run, J: energy injected), contacts_active_mean, contacts_active_max (contacts with a
normal impulse, per step), joint_limits (limit constraints enforced: the joints', then the
tendons' length limits), initial_limit_violation
(deepest excursion beyond a limit at the start: the file's configuration; rad or m),
max_limit_violation (the deepest over the run, the start included), limits_active_max
(limits holding a joint or a tendon, per step), unconverged_steps, diverged_steps, max_contacts and
max_limits (the contact budgets in effect; null: none), dropped_contact_steps (steps where a budget
left out a closing contact or limit), max_pairs (the
broad phase's pairs per group; null: all), skipped_pair_steps (steps where it left out a pair
within its margin), inside_side_site_steps (steps that started with a spatial tendon's side site
inside its wrapping shape, where MuJoCo wraps through the shape, which is not modelled),
max_correction_speed (the bound on the Baumgarte correction's speed;
null: none), joint_friction_dofs (dofs with dry joint friction), joint_friction_held_mean
(those held still by it, per step: end-of-step speed below the contact solver's slip
threshold), joint_friction_impulse_max (largest ratio of a friction impulse to its bound,
at most 1), joint_couplings (joint equality constraints enforced), max_coupling_error (the
largest |q_a - p(q_b)| over the run, rad or m), connections (connect equalities enforced),
max_connection_error (the largest distance between a connection's two points over the run,
m), welds (weld equalities enforced), max_weld_error (the largest entry of a weld's error over
the run: the points' gap in m, the orientation error's quaternion part), joint_springs (joints
with a spring),
wall_time_s (compile included)."""

DEMO_SCENE = """<mujoco>
  <option timestep="0.01"/>
  <default><geom contype="2" conaffinity="0" friction="0.6"/></default>
  <worldbody>
    <geom name="floor" type="plane" size="1 1 0.1" contype="1" conaffinity="3" friction="0.8"/>
    <body name="base" pos="0 0 0.06"><freejoint/>
      <geom type="box" size="0.15 0.12 0.05" contype="1" conaffinity="1"/></body>
    <body name="middle" pos="0 0 0.16" euler="0 0 30"><freejoint/>
      <geom type="box" size="0.1 0.08 0.04" contype="1" conaffinity="1"/></body>
    <body name="ball" pos="0.45 0 0.12"><freejoint/><geom type="sphere" size="0.07"/></body>
    <body name="log" pos="0 0.45 0.1" euler="0 90 0"><freejoint/>
      <geom type="capsule" size="0.04 0.1"/></body>
    <body name="brick" pos="-0.45 0 0.1" euler="0 0 -20"><freejoint/>
      <geom type="box" size="0.06 0.05 0.04"/></body>
    <body name="can" pos="0 -0.45 0.12"><freejoint/><geom type="cylinder" size="0.05 0.06"/></body>
  </worldbody>
</mujoco>"""


@dataclasses.dataclass(frozen=True)
class Config:
    file: str = _protocol.option(
        "", "MJCF (.xml) or URDF (.urdf) file of the scene; empty: the built-in scene (a box stack, a ball, a "
        "capsule, a brick and a cylinder dropped on a floor).")
    steps: int = _protocol.option(200, "Time steps.", min=1)
    time_step: float | None = _protocol.option(None, "Time step, s; default: the file's opt.timestep.", above=0.0)
    frames: int = _protocol.option(40, "Frames of the animation.", min=2)
    floating_base: bool = _protocol.option(
        False, "Give the file's first body a free joint (a robot's base; a URDF has none of its own).")
    floor: bool = _protocol.option(
        False, "Add a floor (normal +z) touching the lowest point of the colliding geometry at the start, in "
        "contact with every colliding geom that moves.")
    self_collision: bool = _protocol.option(
        True, "Keep the contacts between geoms of one robot or object (bodies under the same child of the world); "
        "off: only contacts between different ones and with the world.")
    joint_limits: bool = _protocol.option(
        True, "Enforce the file's joint position limits (MuJoCo's limited hinge and slide joints), as MuJoCo "
        "does; off: the joints move freely.")
    max_contacts: int | None = _protocol.option(
        None, "Solve at most this many contacts between shapes per step, the closest candidates (a robot's meshes "
        "give hundreds of candidates, of which a few touch, and a step costs about the cube of the contacts solved); "
        "a step that leaves out a closing contact is reported. Default: 4 per moving body that collides, at least "
        "64 (all where there are no more candidates).", min=1)
    max_limits: int | None = _protocol.option(
        None, "Solve at most this many joint limits per step, those nearest their bounds (a humanoid has dozens, "
        "each in every solve however far from its bound); a step that leaves out a closing one is reported. "
        "Default: all.", min=1)
    max_pairs: int | None = _protocol.option(
        None, "Broad phase: collide at most this many pairs of each group of alike geom pairs per step, those whose "
        "bounding spheres are closest (exact while no more are within their margin; a step that leaves out one is "
        "reported). Default: all.", min=1)
    max_correction_speed: float | None = _protocol.option(
        None, "Largest speed (m/s, or rad/s for a joint) at which a penetration or a joint beyond its limit is "
        "pushed back (a URDF's start often puts knees beyond their limits, which the full Baumgarte rate turns "
        "into tens of joules). Default: no bound.", above=0.0)
    max_hull_vertices: int | None = _protocol.option(
        None, "Bound on the vertices of each mesh's convex hull, the shape collided (MuJoCo's maxhullvert; 16 to 32 "
        "make a robot's meshes tractable). Default: the whole hull.", min=4)
    drop_mimic: bool = _protocol.option(
        False, "Drop the file's joint couplings (a URDF <mimic>, e.g. Panda's fingers), with a warning: the coupled "
        "joints then move independently.")
    drop_frictionloss: bool = _protocol.option(
        False, "Drop the file's dry joint friction (frictionloss, a URDF <dynamics friction>), simulated otherwise, "
        "with a warning.")
    boundinertia: float | None = _protocol.option(
        None, "Lower bound (kg m^2) on every body's principal moments of inertia, for a file whose inertia is not "
        "positive definite (e.g. 1e-9; a warning names the bodies raised).", above=0.0)
    package_dir: str = _protocol.option(
        "", "Folder holding the packages that a URDF's package:// URIs name; empty: the folders above the file "
        "(a package's own folder, as in example-robot-data).")

    @classmethod
    def quick(cls, **changes) -> "Config":
        return dataclasses.replace(cls(steps=100, frames=20), **changes)

    def __post_init__(self):
        _protocol.check_options(self)
        if self.file and not Path(self.file).is_file():
            raise ValueError(f"file (--file) must be an existing MJCF or URDF file, got {self.file!r}")
        if self.package_dir and not Path(self.package_dir).is_dir():
            raise ValueError(f"package_dir (--package-dir) must be an existing folder, got {self.package_dir!r}")
        needs_file = (
            ("floating_base (--floating-base)", self.floating_base),
            ("package_dir (--package-dir)", self.package_dir),
            ("drop_mimic (--drop-mimic)", self.drop_mimic),
            ("drop_frictionloss (--drop-frictionloss)", self.drop_frictionloss),
            ("boundinertia (--boundinertia)", self.boundinertia is not None),
        )
        for name, given in needs_file:
            if given and not self.file:
                raise ValueError(f"{name} applies to a --file, not to the built-in scene")


def run(config: Config, out: Path | str, key, progress: bool = True) -> dict:
    """Simulates, writes metrics.json, scene.png and scene.gif under `out`."""
    del key  # the simulation is deterministic
    out = Path(out)
    start = time.perf_counter()
    loaded = sim.load_mjcf(
        config.file or DEMO_SCENE, package_dirs=[config.package_dir] if config.package_dir else None,
        floating_base=config.floating_base,
        boundinertia=config.boundinertia, drop_mimic=config.drop_mimic, drop_frictionloss=config.drop_frictionloss,
        max_hull_vertices=config.max_hull_vertices,
    )
    system = sim.scene(
        loaded, time_step=config.time_step, floor=config.floor, self_collision=config.self_collision,
        joint_limits=config.joint_limits, max_contacts="auto" if config.max_contacts is None else config.max_contacts,
        max_limits=config.max_limits,
        max_pairs=config.max_pairs,
        max_correction_speed=float("inf") if config.max_correction_speed is None else config.max_correction_speed,
    )
    limits = system.num_limits  # the last candidate contacts (RigidBodySystem.contacts)
    # the floor scene() adds is the last pair's half-space (drawn where it is)
    floor_height = float(system.geometry.geom_pairs[-1].placement1[1][2]) if config.floor else 0.0
    bar = tqdm(total=2 + config.frames, desc="sim scene", disable=not progress)

    # The rollout's diagnostics are checked below (sim.check_steps): its program leaves out
    # the steps' traced checks.
    @jax.jit
    @_checks.without_traced_checks()
    def simulate(x0):
        xs, infos = system.rollout(x0, jnp.zeros((config.steps, system.nu)))
        energies = jax.vmap(lambda x: sim.energy(system, x))(xs)
        placements = jax.vmap(lambda x: sim.forward_kinematics(system.model, system.split(x)[0]))(xs)
        coupling_errors = jax.vmap(lambda x: system.coupling_errors(system.split(x)[0]))(xs)
        connection_gaps = jax.vmap(lambda x: jnp.linalg.norm(system.connection_errors(system.split(x)[0]), axis=-1))(xs)
        weld_errors = jax.vmap(lambda x: system.weld_errors(system.split(x)[0]))(xs)
        return xs, infos, energies, placements, coupling_errors, connection_gaps, weld_errors

    xs, infos, energies, placements, coupling_errors, connection_gaps, weld_errors = simulate(system.initial_state())
    xs = jax.block_until_ready(xs)
    counts = sim.check_steps(infos, what=f"the scene {config.file or 'built-in'}")
    bar.update()
    distances = np.asarray(infos.distance).reshape(config.steps, -1)
    touching = np.asarray(infos.mode).reshape(config.steps, -1) != sim.SEPARATED
    distances, limit_distances = distances[:, : distances.shape[1] - limits], distances[:, distances.shape[1] - limits :]
    active, limits_active = touching[:, : touching.shape[1] - limits].sum(axis=-1), touching[:, touching.shape[1] - limits :].sum(axis=-1)
    energies = np.asarray(energies)
    dt = float(system.time_step)
    friction_dofs = () if system.joints.friction is None else system.joints.friction.dofs
    if friction_dofs:  # the friction rows come first among the joints' rows (RigidBodySystem.joint_rows)
        speeds = np.abs(np.asarray(xs)[1:, system.model.nq + np.array(friction_dofs)])
        held = (speeds <= system.solver.tolerance_for(xs.dtype) ** 0.5).sum(axis=-1)
        bounds = dt * np.asarray(system.joints.friction.effort)
        friction_share = np.abs(np.asarray(infos.joint_impulse)[:, : len(friction_dofs)]) / bounds
    metrics = {
        "file": config.file or "built-in",
        "steps": config.steps,
        "time_step": dt,
        "bodies": len(loaded.body_names),
        "geom_pairs": len(system.geometry.geom_pairs),
        "candidate_contacts": system.num_contacts - limits,
        "max_penetration": float(max(0.0, -distances.min())) if distances.size else 0.0,
        "initial_penetration": float(max(0.0, -distances[0].min())) if distances.size else 0.0,
        "joint_limits": limits,
        "initial_limit_violation": float(max(0.0, -limit_distances[0].min())) if limits else 0.0,
        "max_limit_violation": float(max(0.0, -limit_distances.min())) if limits else 0.0,
        "limits_active_max": int(limits_active.max()) if limits else 0,
        "energy_initial": float(energies[0]),
        "energy_final": float(energies[-1]),
        "energy_change": float(energies[-1] - energies[0]),
        "energy_max_gain": float(np.max(energies - energies[0])),
        "contacts_active_mean": float(np.mean(active)),
        "contacts_active_max": int(np.max(active)),
        "unconverged_steps": counts["unconverged_steps"],
        "diverged_steps": counts["diverged_steps"],
        "max_contacts": system.options.max_contacts,
        "max_limits": config.max_limits,
        "dropped_contact_steps": counts["dropped_contact_steps"],
        "max_pairs": config.max_pairs,
        "max_correction_speed": config.max_correction_speed,
        "skipped_pair_steps": counts["skipped_pair_steps"],
        "inside_side_site_steps": counts["inside_side_site_steps"],
        "joint_friction_dofs": len(friction_dofs),
        "joint_friction_held_mean": float(np.mean(held)) if friction_dofs else 0.0,
        "joint_friction_impulse_max": float(friction_share.max()) if friction_dofs else 0.0,
        "joint_couplings": int(coupling_errors.shape[-1]),
        "max_coupling_error": float(np.abs(np.asarray(coupling_errors)).max()) if coupling_errors.shape[-1] else 0.0,
        "connections": int(connection_gaps.shape[-1]),
        "max_connection_error": float(np.asarray(connection_gaps).max()) if connection_gaps.shape[-1] else 0.0,
        "welds": int(weld_errors.shape[1]),
        "max_weld_error": float(np.abs(np.asarray(weld_errors)).max()) if weld_errors.shape[1] else 0.0,
        "joint_springs": 0 if system.joints.springs is None else len(system.joints.springs.joints),
    }
    times = np.arange(config.steps + 1) * dt
    fig, (ax_energy, ax_contacts) = viz.plt.subplots(1, 2, figsize=(11, 3.6))
    ax_energy.plot(times, energies - energies[0], color="k")
    ax_energy.set_xlabel("time (s)")
    ax_energy.set_ylabel("energy - initial (J)")
    ax_energy.set_title(f"{Path(metrics['file']).name}: mechanical energy")
    ax_contacts.step(times[1:], active, where="post", color="tab:blue")
    ax_contacts.set_xlabel("time (s)")
    ax_contacts.set_ylabel("active contacts")
    fig.tight_layout()
    viz.save_figure(fig, out / "scene.png")
    bar.update()
    rotations, translations = (np.asarray(p) for p in placements)
    draw = _scene_render.SceneFrames(loaded, _scene_render.bounds(loaded, (rotations, translations), floor_height),
                                     floor_height)
    frames = []
    for k in np.linspace(0, config.steps, config.frames).round().astype(int):
        frames.append(draw(rotations[k], translations[k]))
        bar.update()
    bar.close()
    viz.save_animation(frames, out / "scene.gif", fps=max(1, round(config.frames / (config.steps * dt))))
    metrics["wall_time_s"] = time.perf_counter() - start
    viz.write_metrics(out / "metrics.json", metrics)
    return metrics


def summary(metrics: dict) -> dict:
    """The lines printed after a run: penetration, energy, contacts, the contact solver."""
    return {
        "max penetration (m)": f"{metrics['max_penetration']:.2e}",
        "energy change (J)": f"{metrics['energy_change']:.3e} (largest gain {metrics['energy_max_gain']:.2e})",
        "active contacts per step": f"{metrics['contacts_active_mean']:.1f} (max {metrics['contacts_active_max']})",
        "unconverged / diverged steps": f"{metrics['unconverged_steps']} / {metrics['diverged_steps']}",
        **({"penetration at the start (m)": f"{metrics['initial_penetration']:.2e} (pushed apart: see "
            "--max-correction-speed)"} if metrics.get("initial_penetration", 0.0) > 0 else {}),
        **({"beyond a joint limit at the start (rad or m)": f"{metrics['initial_limit_violation']:.3g}"}
           if metrics.get("initial_limit_violation", 0.0) > 0 else {}),
        **({"dofs held by joint friction per step": f"{metrics['joint_friction_held_mean']:.1f} of "
            f"{metrics['joint_friction_dofs']}"} if metrics.get("joint_friction_dofs") else {}),
        **({"largest coupling error (rad or m)": f"{metrics['max_coupling_error']:.2e}"}
           if metrics.get("joint_couplings") else {}),
        **({"largest connection error (m)": f"{metrics['max_connection_error']:.2e}"}
           if metrics.get("connections") else {}),
        **({"largest weld error (m, or quaternion part)": f"{metrics['max_weld_error']:.2e}"}
           if metrics.get("welds") else {}),
    }


EXPERIMENT = _protocol.Experiment(
    command=("sim", "scene"),
    name="scene",
    config=Config,
    run=run,
    summary=summary,
    help="Simulate a MuJoCo scene (MJCF or URDF file, or a built-in one) under gravity with hard frictional "
    "contact and write an animation of its shapes.",
    metrics_doc=METRICS_DOC,
)
