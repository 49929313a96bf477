"""A MuJoCo scene (MJCF, or URDF through MuJoCo's compiler) as a :class:`RigidBodySystem`.

:func:`~rsmooth.sim.load_mjcf` converts a file into a :class:`~rsmooth.sim.MujocoModel`: the
kinematic tree and the collision geometry as plain data. :func:`scene` turns that data into a
system that steps with hard frictional contact, as MuJoCo would pair its geoms:

- every geom of a colliding pair becomes a collision shape with MuJoCo's sizes (``geom_size``:
  a plane is a :class:`~rsmooth.sim.HalfSpace`, infinite, ``z <= 0`` of its frame; a sphere
  its radius; a capsule and a cylinder their radius and half length along their ``z`` axis; a
  box its half extents; an ellipsoid its three radii; a height field (fixed in the world,
  against any shape but a plane or another height field) its :class:`~rsmooth.sim.HeightField`; a mesh the :class:`~rsmooth.sim.ConvexMesh` of its vertices' convex
  hull, the shape MuJoCo collides);
- every pair of :attr:`MujocoModel.collision_pairs` (MuJoCo's filters: welded bodies, parent
  and child, ``<exclude>``, ``contype``/``conaffinity``, explicit ``<pair>``) becomes one
  :class:`~rsmooth.sim.GeomPair`: a geom on the world or on a body welded to it is fixed in the
  world, any other is carried by the frame of its MuJoCo body (frame index = body id);
- the pair's friction is MuJoCo's: an explicit pair's own, else the one of the geom of higher
  ``priority``, else the larger of the two geoms' sliding coefficients.

Two options change MuJoCo's set of pairs, for files that were not written as a scene (a robot's
URDF has no floor, and MuJoCo pairs every two links but a parent and its child):

- ``floor=True`` adds a half-space floor, normal ``+z``, at the height of the lowest point of the
  colliding geometry at the initial configuration (so that nothing starts in penetration), in
  contact with every colliding geom on a moving body;
- ``self_collision=False`` drops the pairs of two geoms of one kinematic tree (bodies under the
  same child of the world), keeping the pairs between different objects and with the world.

By default the collision detection computes the manifold of every pair at every step, so the
cost of a step grows with the number of pairs: prune pairs that cannot touch with
``contype``/``conaffinity`` or ``<exclude>`` (as in MuJoCo), and bound the narrow phase with
``max_pairs`` (a broad phase on bounding spheres, per group of pairs of the same shapes).
"""

from __future__ import annotations

import dataclasses
import pathlib
import warnings
from typing import Any

import jax.numpy as jnp
import numpy as np

from rsmooth._xla import device_array
from rsmooth.sim._collision import manifold_size
from rsmooth.sim._dynamics import forward_kinematics
from rsmooth.sim._geometry import Box, Capsule, ConvexMesh, Cylinder, Ellipsoid, HalfSpace, HeightField, Sphere, convex_mesh
from rsmooth.sim._mujoco import MujocoModel, load_mjcf, source_label
from rsmooth.sim._ncp import NCPSolver
from rsmooth.sim._simulator import Actuation, GeomPair, RigidBodySystem, Servos
from rsmooth.sim._systems import _number, geom_pair_system

__all__ = ["automatic_contact_budget", "scene"]


def _shape(loaded: MujocoModel, geom: int, meshes: dict[int, Any]):
    """The collision shape of a geom, in the geom's frame; ``None`` where rsmooth has none."""
    kind = loaded.geom_types[geom]
    size = np.asarray(loaded.geom_size[geom], dtype=np.float64)
    if kind == "plane":
        return HalfSpace()
    if kind == "sphere":
        return Sphere(size[0])
    if kind == "capsule":
        return Capsule(size[0], size[1])
    if kind == "cylinder":
        return Cylinder(size[0], size[1])
    if kind == "ellipsoid":
        return Ellipsoid(size)
    if kind == "hfield":
        return loaded.geom_height_fields[geom]
    if kind == "box":
        return Box(size)
    if kind == "mesh":
        if geom not in meshes:
            meshes[geom] = convex_mesh(np.asarray(loaded.geom_hull[geom], dtype=np.float64))
        return meshes[geom]
    return None


def _describe(loaded: MujocoModel, geom: int) -> str:
    return f"geom {loaded.geom_names[geom]!r} ({loaded.geom_types[geom]})"


def _placement(loaded: MujocoModel, geom: int) -> tuple[int | None, tuple[jnp.ndarray, jnp.ndarray]]:
    """``(frame, placement)`` of a geom: ``None`` and its world pose for a geom that does not
    move; otherwise its MuJoCo body's frame and its pose in that frame."""
    rotation = np.asarray(loaded.geom_rotation[geom], dtype=np.float64)
    translation = np.asarray(loaded.geom_translation[geom], dtype=np.float64)
    if loaded.geom_joints[geom] == 0:
        # joint 0 is the universe: the geom's placement in its joint's frame is its world pose
        return None, (jnp.asarray(rotation), jnp.asarray(translation))
    body = loaded.geom_bodies[geom]  # frames start with the bodies, in MuJoCo's order
    body_rotation = np.asarray(loaded.model.frame_placement_rotation[body], dtype=np.float64)
    body_translation = np.asarray(loaded.model.frame_placement_translation[body], dtype=np.float64)
    return body, (jnp.asarray(body_rotation.T @ rotation), jnp.asarray(body_rotation.T @ (translation - body_translation)))


def _pair_friction(loaded: MujocoModel, index: int, geom1: int, geom2: int) -> float:
    """MuJoCo's sliding friction of collision pair ``index`` (``mj_contactParam``)."""
    if index < len(loaded.contact_pairs):  # the explicit pairs come first
        return float(loaded.pair_friction[index])
    priority1, priority2 = loaded.geom_priority[geom1], loaded.geom_priority[geom2]
    friction1, friction2 = float(loaded.geom_friction[geom1]), float(loaded.geom_friction[geom2])
    if priority1 != priority2:
        return friction1 if priority1 > priority2 else friction2
    return max(friction1, friction2)


def _check_pair(names: tuple[str, str], kinds: tuple[str, str], shapes: tuple) -> None:
    """Refuses a pair with a geom that has no rsmooth shape (``None``), or a pair of shapes
    that :func:`~rsmooth.sim.collide` does not support; ``names`` describe the two geoms."""
    for side in (0, 1):
        if shapes[side] is None:
            raise ValueError(
                f"MuJoCo model: {names[side]} collides with {names[1 - side]}, but rsmooth.sim has no {kinds[side]} "
                "collision shape (supported: plane, height field, sphere, capsule, box, cylinder, ellipsoid, mesh); give it contype = "
                "conaffinity = 0 or replace it"
            )
    try:
        manifold_size(*shapes)
    except NotImplementedError:
        raise ValueError(
            f"MuJoCo model: {names[0]} collides with {names[1]}, a pair of shapes rsmooth.sim's collide does not "
            "support"
        ) from None


def _height_field_window(loaded: MujocoModel, geom: int, shape, other):
    """``shape``, a height field, with the window of cells that covers ``other`` (its bounding
    diameter in the smaller cell side, plus one); any other shape as it is. A height field on a
    moving body is refused by name."""
    if not isinstance(shape, HeightField):
        return shape
    if loaded.geom_joints[geom] != 0:
        raise ValueError(
            f"MuJoCo model: {_describe(loaded, geom)} is on a moving body; rsmooth.sim collides height fields fixed in "
            "the world only"
        )
    cells = 2.0 * float(other.bounding_radius) / float(np.min(np.asarray(shape.cell)))
    return dataclasses.replace(shape, window=int(np.ceil(cells)) + 1)


def _tree(loaded: MujocoModel, body: int) -> int:
    """The child of the world whose subtree holds ``body`` (MuJoCo's ``body_rootid``); 0 for the
    world itself."""
    while body != 0 and loaded.body_parents[body] != 0:
        body = loaded.body_parents[body]
    return body


def _lowest_point(loaded: MujocoModel, geom: int, rotation: np.ndarray, translation: np.ndarray) -> float:
    """The smallest world ``z`` of a bounded geom at the pose ``(rotation, translation)``: the
    support of its shape in the direction ``-z``."""
    kind = loaded.geom_types[geom]
    size = np.asarray(loaded.geom_size[geom], dtype=np.float64)
    up = rotation[2]  # the world z axis in the geom's frame
    if kind == "sphere":
        depth = size[0]
    elif kind == "capsule":
        depth = size[1] * abs(up[2]) + size[0]
    elif kind == "cylinder":
        depth = size[1] * abs(up[2]) + size[0] * np.sqrt(max(0.0, 1.0 - up[2] ** 2))
    elif kind == "box":
        depth = float(np.abs(up) @ size)
    elif kind == "ellipsoid":
        depth = float(np.linalg.norm(up * size))
    else:  # a mesh: its lowest vertex (also the lowest of its convex hull)
        depth = -float(np.min(np.asarray(loaded.geom_hull[geom], dtype=np.float64) @ up))
    return float(translation[2] - depth)


def _floor_height(loaded: MujocoModel, geoms: list[int], q: jnp.ndarray) -> float:
    """The lowest point of ``geoms`` (no plane among them) at the configuration ``q``."""
    rotations, translations = (np.asarray(a, dtype=np.float64) for a in forward_kinematics(loaded.model, q))
    heights = []
    for geom in geoms:
        joint = loaded.geom_joints[geom]
        rotation = rotations[joint] @ np.asarray(loaded.geom_rotation[geom], dtype=np.float64)
        offset = np.asarray(loaded.geom_translation[geom], dtype=np.float64)
        translation = rotations[joint] @ offset + translations[joint]
        heights.append(_lowest_point(loaded, geom, rotation, translation))
    return min(heights)


def _actuation(loaded: MujocoModel) -> tuple[tuple[int, ...], np.ndarray, np.ndarray | None] | None:
    """The dofs the joint motors drive, the symmetric bound of each input, and ``None``, or,
    where motors drive fixed tendons, the moment arms ``(nu, nv)`` of the inputs: the driven
    dofs' unit rows, then the driven tendons' :attr:`~MujocoModel.tendon_moments` (in increasing
    order). ``None`` where generalized forces bounded symmetrically cannot express the motors
    (:func:`scene` then drives them by their controls, as servos without a bias).

    The range of each motor's force is its control range times its gain, clipped to its force
    range, times its gear (MuJoCo's ``qfrc_actuator``); the ranges of the motors of one dof or
    tendon add up, and a dof's are clipped to its ``actfrcrange``. Not expressible: a range not
    symmetric about 0 (a gripper's ``ctrlrange="0 255"``), and a tendon motor that moves a dof
    whose total actuator force is bounded (the bound is on a sum of inputs, not on each).
    """
    ctrl = np.asarray(loaded.actuator_ctrl_range, dtype=np.float64).reshape(-1, 2)
    force = np.asarray(loaded.actuator_force_range, dtype=np.float64).reshape(-1, 2)
    gain = np.asarray(loaded.actuator_gain, dtype=np.float64)
    gear = np.asarray(loaded.actuator_gear, dtype=np.float64)
    dof_range = np.asarray(loaded.dof_actuator_force_range, dtype=np.float64).reshape(-1, 2)

    def bound(motors, clip=(-np.inf, np.inf)):
        """The motors' symmetric bound, ``None`` where their range is not symmetric about 0."""
        low = high = 0.0
        for a in motors:
            # interval products; a zero gain or gear reaches nothing, even from an infinite range
            reach = np.sort(gain[a] * ctrl[a]) if gain[a] != 0 else np.zeros(2)
            reach = np.clip(reach, force[a, 0], force[a, 1])
            reach = np.sort(gear[a] * reach) if gear[a] != 0 else np.zeros(2)
            low, high = low + reach[0], high + reach[1]
        low, high = max(low, clip[0]), min(high, clip[1])
        return high if np.isclose(low, -high, rtol=1e-9, atol=1e-12) and high > 0 else None

    dofs = tuple(sorted(set(loaded.actuator_dofs) - {-1}))
    limits = [bound([a for a, d in enumerate(loaded.actuator_dofs) if d == dof], dof_range[dof]) for dof in dofs]
    tendons = tuple(sorted(set(loaded.actuator_tendons) - {-1}))
    tendon_moments = np.asarray(loaded.tendon_moments, dtype=np.float64)
    for tendon in tendons:
        moved = np.flatnonzero(tendon_moments[tendon])
        bounded = np.any(np.isfinite(dof_range[moved]))
        limits.append(None if bounded else bound([a for a, t in enumerate(loaded.actuator_tendons) if t == tendon]))
    if any(limit is None for limit in limits):
        return None
    moments = np.concatenate([np.eye(loaded.model.nv)[list(dofs)], tendon_moments[list(tendons)]]) if tendons else None
    return dofs, np.asarray(limits, dtype=np.float64), moments


def _servo_actuation(loaded: MujocoModel) -> Actuation:
    """Every actuator of a model with servos (or with motors that :func:`_actuation` cannot
    express), driven by its control (:class:`~rsmooth.sim.Servos`; a motor is one without bias):
    lengths on rsmooth's coordinates (MuJoCo's ``qpos`` less ``qpos0`` on hinges and slides, the
    only joints actuators drive)."""
    lengths = np.asarray(loaded.actuator_lengths, dtype=np.float64)
    return Actuation(
        "servos",
        device_array(np.full(loaded.nu, np.inf)),
        moments=loaded.actuator_moments,
        servos=Servos(
            gain=loaded.actuator_gain,
            bias=loaded.actuator_bias,
            lengths=loaded.actuator_lengths,
            offsets=device_array(lengths @ np.asarray(loaded.qpos0, dtype=np.float64)),
            ctrl_range=loaded.actuator_ctrl_range,
            force_range=loaded.actuator_force_range,
            dof_force_range=loaded.dof_actuator_force_range,
            dynamics=loaded.activation_dynamics,
        ),
    )


def scene(
    source: str | pathlib.Path | Any,
    *,
    package_dirs=None,
    floating_base: bool = False,
    visuals: bool | str = False,
    boundinertia: float | None = None,
    drop_mimic: bool = False,
    drop_frictionloss: bool = False,
    max_hull_vertices: int | None = None,
    time_step: float | None = None,
    friction: float | None = None,
    margin: float = 0.01,
    solver: NCPSolver = NCPSolver(sticking_guess=True, rank_deficient=True, polish=True, max_iterations=1000),
    baumgarte: float = 0.2,
    floor: bool = False,
    self_collision: bool = True,
    joint_limits: bool = True,
    max_contacts: int | None | str = "auto",
    max_pairs: int | None = None,
    max_limits: int | None = None,
    max_correction_speed: float = float("inf"),
) -> RigidBodySystem:
    """A MuJoCo model (MJCF or URDF) as a system with hard frictional contact.

    The kinematic tree, gravity, armature, joint damping, joint springs (``stiffness``,
    :meth:`~rsmooth.sim.RigidBodySystem.with_joint_springs`), dry joint friction (``frictionloss``,
    :meth:`~rsmooth.sim.RigidBodySystem.with_joint_friction`), joint couplings (a URDF's
    ``<mimic>``, :attr:`~rsmooth.sim.Joints.couplings`), connect and weld equalities (closed
    kinematic loops, bodies held together: :attr:`~rsmooth.sim.Joints.connections`,
    :attr:`~rsmooth.sim.Joints.welds`) and the springs, dampers, dry friction
    and length limits of fixed and spatial tendons (:attr:`~rsmooth.sim.Joints.tendons`), the bodies'
    gravity compensation (:attr:`~rsmooth.sim.Joints.gravcomp`) and the fluid
    (:attr:`~rsmooth.sim.Joints.fluid`) are those of
    :func:`~rsmooth.sim.load_mjcf`; every colliding geom pair of MuJoCo is a
    :class:`~rsmooth.sim.GeomPair` with MuJoCo's friction (see the module's description for
    the mapping of geoms, frames and frictions). The input ``u`` ``(nu,)`` holds the
    generalized forces on the dofs the model's motors drive (``actuation.dofs``, in increasing
    order; ``nu = 0`` without motors), not MuJoCo's controls:
    :meth:`MujocoModel.ctrl_to_tau` gives the forces of given controls. Where motors drive
    fixed tendons, the actuation is ``"moments"``: ``u`` holds those dofs' forces, then the
    force along each driven tendon (in increasing tendon order), ``tau = moments^T u``
    (:attr:`~rsmooth.sim.Actuation.moments`). Each is bounded by what the motors of its dof or
    tendon can apply, ``+inf`` where unlimited. A model with servos (position or velocity
    actuators: an actuator bias) has the actuation ``"servos"`` instead: ``u`` holds MuJoCo's
    controls of all its actuators, in MuJoCo's order (:class:`~rsmooth.sim.Servos`); so does a
    model whose motors symmetric bounds on generalized forces cannot express (a control or force
    range not symmetric about 0, such as a gripper's ``ctrlrange="0 255"``, or a tendon motor
    moving a dof whose total actuator force is bounded), each motor a servo without a bias
    (MuJoCo's ``qfrc_actuator`` exactly, clipped as MuJoCo clips it), and a model whose
    actuators have activation dynamics (``dyntype`` integrator, filter, filterexact: their
    states end the state, ``x = [q, v, act]``, :class:`~rsmooth.sim.ActivationDynamics`).
    ``initial_state()`` is MuJoCo's ``qpos0`` (the configuration the file describes) at rest
    (and zero actuator states, as MuJoCo's reset).

    The limits of limited hinges and slides are enforced as MuJoCo does, as hard constraints
    here (:meth:`~rsmooth.sim.RigidBodySystem.with_joint_limits`). MuJoCo's disable flags are
    honoured: ``contact`` (no pair collides), ``limit``, ``equality``, ``frictionloss``,
    ``spring``, ``damper``, ``gravity`` and ``constraint`` (all of contacts, limits, equalities
    and dry friction). Not simulated, as
    :func:`~rsmooth.sim.load_mjcf` reads them: ``solref``/``solimp``, ``condim`` (every contact has sliding friction, none torsional or rolling), geom margins
    and gaps, MuJoCo's integrator and solver settings.

    Args:
        source: a path to an MJCF (``.xml``) or URDF (``.urdf``) file, MJCF text, a
            ``mujoco.MjModel``, or a :class:`~rsmooth.sim.MujocoModel`.
        package_dirs: folders holding the packages that ``package://`` URIs name (URDF);
            ``None``: the folders above the file (see :func:`~rsmooth.sim.load_mjcf`).
        floating_base: give the first body under the world a free joint (a file or text
            only; see :func:`~rsmooth.sim.load_mjcf`).
        visuals: which visual geoms to keep (:func:`~rsmooth.sim.load_mjcf`'s option; a file
            or text only). ``False`` by default: the system is built from the colliding geoms
            alone, so visual ones would only cost loading time (MuJoCo keeps the inertia they
            give their body).
        boundinertia: lower bound on the principal moments of inertia of every body, for a
            file with an inertia that is not positive definite (see
            :func:`~rsmooth.sim.load_mjcf`; a file or text only).
        drop_mimic: drop joint equality constraints (a URDF ``<mimic>``) with a warning (see
            :func:`~rsmooth.sim.load_mjcf`; a file or text only).
        drop_frictionloss: drop dry joint friction with a warning (see
            :func:`~rsmooth.sim.load_mjcf`; a file or text only).
        max_hull_vertices: bound on the vertices of each mesh's convex hull, the shape
            collided (see :func:`~rsmooth.sim.load_mjcf`; a file or text only).
        time_step: ``h`` (s); ``None``: MuJoCo's ``opt.timestep``.
        friction: Coulomb coefficient of every pair, ``>= 0``; ``None``: MuJoCo's per pair.
        margin: distance within which manifold entries are candidate contacts
            (:attr:`GeomPair.margin`, m).
        solver: NCP solver configuration, that of :func:`~rsmooth.sim.bodies` by default.
        baumgarte: penetration correction rate in ``[0, 1]``.
        floor: add a floor, a :class:`~rsmooth.sim.HalfSpace` of normal ``+z`` (in addition
            to the file's planes) whose plane touches the lowest point of the colliding geoms
            (geoms with a nonzero ``contype`` or ``conaffinity``, or in a pair; planes left
            out) at ``initial_configuration``, paired with every colliding geom on a moving
            body; the friction of a floor pair is ``friction``, else the geom's own.
        self_collision: ``False`` drops the pairs (explicit pairs included) of two geoms whose
            bodies hang from the same child of the world (one robot, one object), keeping the
            pairs between different trees and with geoms on the world body.
        joint_limits: enforce the position limits of the limited hinges and slides and the
            cone limits of the limited ball joints (the
            system's :attr:`~rsmooth.sim.Joints.limits`, frictionless contacts
            after the geometry pairs), unless the model disables them (its ``limit`` or
            ``constraint`` flag); ``False``: the joints move freely. A start beyond a
            hinge's or slide's limits (a URDF's zero configuration often is: a quadruped's
            knees) is warned of: the limits push the joints back in during the first steps.
        max_contacts: solve at most this many contacts between shapes per step, the closest
            candidates (:attr:`~rsmooth.sim.Options.max_contacts`): a robot's meshes
            give hundreds of candidates of which a few touch; ``None``: all; ``"auto"``:
            :func:`automatic_contact_budget` of the scene (4 per moving body that collides, at
            least 64; all where there are no more candidates). The NCP is dense: a hard
            step costs about the cube of the contacts it solves, whether they touch or not.
        max_pairs: collide at most this many pairs of each pair group per step, those whose
            bounding spheres are closest (:attr:`~rsmooth.sim.Options.max_pairs`,
            exact while no more are within the margin); ``None``: all.
        max_limits: solve at most this many joint limits per step, those nearest their
            bounds (:attr:`~rsmooth.sim.Options.max_limits`): a humanoid has dozens;
            ``None``: all.
        max_correction_speed: the largest speed (m/s, or rad/s) at which a penetration or a
            joint beyond its limit is pushed back (:attr:`~rsmooth.sim.Options.max_correction_speed`):
            a URDF whose start puts joints beyond their limits is otherwise set moving at
            ``baumgarte d / h``; ``inf``: no bound.

    Returns:
        The system; its frames are the model's (bodies first, by MuJoCo body id), its geometry
        pairs in the order of :attr:`MujocoModel.collision_pairs` (those kept), then the
        floor's, by geom id.

    Raises:
        ValueError: if the model cannot be loaded or converted (see
            :func:`~rsmooth.sim.load_mjcf`), if a colliding pair has no collision function (the
            message names the geoms and their types), if the motors of a dof can apply a
            generalized force over a range that is not symmetric about zero (the message names
            them), if ``floating_base``, ``package_dirs``, ``visuals``, ``boundinertia``,
            ``drop_mimic``, ``drop_frictionloss`` or ``max_hull_vertices`` is given with a converted model,
            if ``floor`` is asked of a scene with no colliding geom on a moving body, if
            ``time_step``, ``friction`` or ``margin`` is out of range, or if ``floating_base``,
            ``floor`` or ``self_collision`` is not a bool.

    Warns:
        UserWarning: where the start is beyond joint limits (the joints by name), and where
            mesh geoms collide with each other through hulls of many vertices (more than
            :data:`LARGE_HULL` as a geometric mean: bound them with ``max_hull_vertices``).

    Example:
        >>> import rsmooth.sim as sim
        >>> system = sim.scene('''<mujoco><option timestep="0.005"/><worldbody>
        ...   <geom name="floor" type="plane" size="1 1 0.1"/>
        ...   <body name="ball" pos="0 0 0.1"><freejoint/><geom type="sphere" size="0.1"/></body>
        ... </worldbody></mujoco>''')
        >>> system.nx, system.nu, system.num_contacts, round(float(system.time_step), 6)
        (13, 0, 1, 0.005)
    """
    for name, value in (
        ("floating_base", floating_base), ("floor", floor), ("self_collision", self_collision), ("joint_limits", joint_limits)
    ):
        if not isinstance(value, (bool, np.bool_)):
            raise ValueError(f"{name} must be True or False, got {value!r}")
    if isinstance(source, MujocoModel):
        given = {
            "floating_base": floating_base,
            "package_dirs": package_dirs is not None,
            "visuals": visuals is not False,
            "boundinertia": boundinertia is not None,
            "drop_mimic": drop_mimic,
            "drop_frictionloss": drop_frictionloss,
            "max_hull_vertices": max_hull_vertices is not None,
        }
        if any(given.values()):
            names = ", ".join(name for name, value in given.items() if value)
            raise ValueError(f"{names}: these options apply to a file or XML text, not to a converted MujocoModel")
        loaded = source
    else:
        loaded = load_mjcf(
            source,
            package_dirs=package_dirs,
            floating_base=floating_base,
            visuals=visuals,
            boundinertia=boundinertia,
            drop_mimic=drop_mimic,
            drop_frictionloss=drop_frictionloss,
            max_hull_vertices=max_hull_vertices,
        )
    if loaded.model.nv == 0:
        raise ValueError(
            f"{source_label(source)}: the model has no joints (nq = nv = 0), so nothing in it moves: give a body a "
            "joint (a <freejoint/> for a free body) or pass floating_base=True"
        )
    h = loaded.timestep if time_step is None else _number("time_step", time_step)
    if friction is not None:
        friction = _number("friction", friction, zero=True)
    if isinstance(margin, bool) or not (np.ndim(margin) == 0 and np.isfinite(margin) and margin >= 0):
        raise ValueError(f"margin must be a non-negative, finite number (m), got {margin!r}")
    meshes: dict[int, Any] = {}
    pairs, kept = [], []  # the geometry pairs and their geoms
    for index, (geom1, geom2) in enumerate(loaded.collision_pairs):
        tree1, tree2 = _tree(loaded, loaded.geom_bodies[geom1]), _tree(loaded, loaded.geom_bodies[geom2])
        if not self_collision and tree1 == tree2 != 0:
            continue
        shape1, shape2 = _shape(loaded, geom1, meshes), _shape(loaded, geom2, meshes)
        kinds = (loaded.geom_types[geom1], loaded.geom_types[geom2])
        _check_pair((_describe(loaded, geom1), _describe(loaded, geom2)), kinds, (shape1, shape2))
        shape1, shape2 = _height_field_window(loaded, geom1, shape1, shape2), _height_field_window(loaded, geom2, shape2, shape1)
        frame1, placement1 = _placement(loaded, geom1)
        frame2, placement2 = _placement(loaded, geom2)
        mu = _pair_friction(loaded, index, geom1, geom2) if friction is None else friction
        pairs.append(
            GeomPair(
                shape1, frame1, shape2, frame2, friction=mu, placement1=placement1, placement2=placement2, margin=margin
            )
        )
        kept.append((geom1, geom2))
    initial_configuration = loaded.qpos_to_q(loaded.default_qpos)
    if floor:
        paired = {geom for pair in loaded.collision_pairs for geom in pair}
        colliding = [
            g
            for g in range(loaded.ngeom)
            if (loaded.geom_contype[g] or loaded.geom_conaffinity[g] or g in paired) and loaded.geom_types[g] != "plane"
        ]
        moving = [g for g in colliding if loaded.geom_joints[g] != 0]
        if not moving:
            raise ValueError("floor: the scene has no colliding geom on a moving body for a floor to hold")
        height = _floor_height(loaded, colliding, initial_configuration)
        placement = (jnp.eye(3), jnp.asarray([0.0, 0.0, height]))
        for geom in moving:
            shape = _shape(loaded, geom, meshes)
            names = ("the floor (plane, floor=True)", _describe(loaded, geom))
            _check_pair(names, ("plane", loaded.geom_types[geom]), (HalfSpace(), shape))
            frame, geom_placement = _placement(loaded, geom)
            mu = float(loaded.geom_friction[geom]) if friction is None else friction
            pairs.append(
                GeomPair(
                    HalfSpace(), None, shape, frame, friction=mu, placement1=placement, placement2=geom_placement,
                    margin=margin,
                )
            )
            kept.append((geom,))
    _warn_if_large_hulls(loaded, pairs, kept, source_label(source))
    if isinstance(max_contacts, str):
        if max_contacts != "auto":
            raise ValueError(f"max_contacts must be a positive integer, None or 'auto', got {max_contacts!r}")
        moving = {loaded.geom_joints[g] for pair in kept for g in pair if loaded.geom_joints[g] != 0}
        max_contacts = automatic_contact_budget(sum(pair.size for pair in pairs), len(moving))
    motors = None if loaded.servo_actuators or loaded.na else _actuation(loaded)
    servos = motors is None
    dofs, limits, moments = ((), np.zeros(0), None) if servos else motors
    model = loaded.model
    system = geom_pair_system(
        model,
        pairs,
        time_step=h,
        solver=solver,
        baumgarte=baumgarte,
        actuated_dofs=dofs,
        input_limit=limits[: len(dofs)],
        initial_configuration=initial_configuration,
        joint_damping=loaded.damping,
    )
    if moments is not None:  # motors on tendons: each input along its moment arms
        system = dataclasses.replace(system, actuation=Actuation("moments", device_array(limits), moments=device_array(moments)))
    if servos:  # u: MuJoCo's controls of every actuator (servos, or motors that force bounds cannot express)
        system = dataclasses.replace(system, actuation=_servo_actuation(loaded))
    system = system.with_contact_budget(max_contacts, max_pairs, max_limits).with_options(max_correction_speed=max_correction_speed)
    system = system.with_joint_friction(np.asarray(loaded.frictionloss))
    system = system.with_joint_springs(np.asarray(loaded.stiffness), loaded.spring_reference)
    system = system.with_tendons(loaded.tendons).with_fluid(loaded.fluid).with_gravcomp(loaded.gravcomp)
    system = system.with_joint_couplings(loaded.joint_couplings).with_connections(loaded.connections).with_welds(loaded.welds)
    if not joint_limits or not loaded.limits_enforced:
        return system
    _warn_if_beyond_limits(model, np.asarray(initial_configuration), source_label(source))
    return system.with_joint_limits()


def automatic_contact_budget(candidates: int, moving_bodies: int) -> int | None:
    """The contact budget (:attr:`~rsmooth.sim.Options.max_contacts`) :func:`scene` takes by
    default: 4 contacts per moving body that collides (a body at rest on a face needs no more),
    at least 64; ``None`` (all) where the scene has no more ``candidates`` than that.

    The budget keeps the closest candidates each step, and a step that leaves out one whose gap
    it closes is reported (:func:`~rsmooth.sim.check_steps`), so a budget that binds is not
    silent; while it holds every touching contact, the step is the one without it (states,
    impulses and Jacobians).

    Example:
        >>> automatic_contact_budget(40, 3), automatic_contact_budget(319, 16), automatic_contact_budget(400, 30)
        (None, 64, 120)
    """
    budget = max(64, 4 * moving_bodies)
    return None if candidates <= budget else budget


# scene() warns of pairs of convex meshes whose hulls' vertex counts multiply to more than
# this squared: their separating-axis test takes about nine times that many edge pairs a step.
LARGE_HULL = 256


def _warn_if_large_hulls(loaded: MujocoModel, pairs: list, kept: list, where: str) -> None:
    """Warns where two collided mesh geoms have hulls of more than :data:`LARGE_HULL` vertices
    (as a geometric mean; a URDF's meshes give hulls of thousands): their collision costs time
    and memory in proportion to the product of their edge counts, so that a step with them
    takes minutes to compile and can exhaust memory. A mesh against a plane costs only its
    vertices. Names the option that bounds the hulls."""
    large = {}
    for pair, geoms in zip(pairs, kept):
        if isinstance(pair.shape1, ConvexMesh) and isinstance(pair.shape2, ConvexMesh):
            counts = (int(pair.shape1.vertices.shape[0]), int(pair.shape2.vertices.shape[0]))
            if counts[0] * counts[1] > LARGE_HULL**2:
                large.update(zip(geoms, counts))
    if large:
        listed = ", ".join(f"{loaded.geom_names[geom]!r} ({count})" for geom, count in sorted(large.items(), key=lambda item: -item[1])[:3])
        warnings.warn(
            f"{where}: {len(large)} mesh geom(s) collide with each other through convex hulls of many vertices "
            f"({listed}{', ...' if len(large) > 3 else ''}): collision costs time and memory in proportion to the "
            "product of two hulls' edge counts, so a step with them is slow to compile and to run. Bound the hulls "
            "with max_hull_vertices (MuJoCo's maxhullvert: 16 to 32 make a robot's meshes tractable), or pass "
            "self_collision=False.",
            UserWarning, stacklevel=3,
        )


def _warn_if_beyond_limits(model, q: np.ndarray, where: str) -> None:
    """Warns where the start ``q`` puts hinges or slides beyond their limits (a URDF's zero
    configuration often does: a quadruped's knee): the enforced limits push them back in during
    the first steps, at the Baumgarte rate, which sets the robot moving."""
    lower, upper = np.asarray(model.lower_position_limit), np.asarray(model.upper_position_limit)
    beyond = []
    for name, kind, index in zip(model.joint_names, model.joint_types, model.idx_q):
        if kind in ("revolute", "prismatic"):
            excess = max(lower[index] - q[index], q[index] - upper[index])
            if excess > 0:
                beyond.append((excess, name))
    if beyond:
        beyond.sort(reverse=True)
        listed = ", ".join(f"{name!r} by {excess:.3g}" for excess, name in beyond[:3])
        warnings.warn(
            f"{where}: the initial configuration is beyond the position limits of {len(beyond)} joint(s) "
            f"({listed}{', ...' if len(beyond) > 3 else ''}; rad or m): the limits push them back in during the "
            "first steps, which sets the model moving. Start from a configuration within the limits "
            "(system.state(q)), or pass joint_limits=False.",
            UserWarning, stacklevel=3,
        )
