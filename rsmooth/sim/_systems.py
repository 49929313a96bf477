"""The canonical systems: a box or a cube among half-spaces, a ball (and a wall), a finger
pushing a box, the Solo-12 quadruped, and free bodies of any shape colliding with each other
(:func:`bodies`).

Each factory returns a :class:`~rsmooth.sim.RigidBodySystem` (a ``Dynamics``: ``step(x, u)``,
``nx``, ``nu``) that stores the configuration its docstring describes as the start, so that
``system.initial_state()`` gives every system's default initial state (at zero velocity).
"""

from __future__ import annotations

import itertools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from rsmooth._xla import device_array
from rsmooth.sim import _dynamics
from rsmooth.sim._laws import LogBarrier, SpringDamper
from rsmooth.sim._model import FREE_FLYER, PRISMATIC, UNIVERSE, Model, free_body, load_urdf, solo12_standing_configuration, solo12_urdf_path
from rsmooth.sim._collision import manifold_size
from rsmooth.sim._contact import contact_frame
from rsmooth.sim._geometry import Box, Capsule, Cylinder, Ellipsoid, HalfSpace, Sphere
from rsmooth.sim._ncp import NCPSolver
from rsmooth.sim._simulator import (
    Actuation, ContactLaw, GeomPair, Geometry, Joints, Options, RigidBodySystem, _point_jacobian,
)

__all__ = [
    "SOLO12_ARMATURE",
    "SOLO12_BASE_HALF_EXTENTS",
    "SOLO12_KNEE_RADIUS",
    "SOLO12_FEET",
    "SOLO12_FOOT_RADIUS",
    "SOLO12_JOINT_DAMPING",
    "SOLO12_TORQUE_LIMIT",
    "ball",
    "ball_wall",
    "bodies",
    "box",
    "cube",
    "pusher",
    "pusher_start_state",
    "solo12",
    "solo12_foot_positions",
    "solo12_standing_torques",
]

FLOOR = ((0.0, 0.0, 1.0), 0.0)

SOLO12_FEET = ("FL_FOOT", "FR_FOOT", "HL_FOOT", "HR_FOOT")
# The foot frames sit at the centre of Solo-12's spherical feet; 19 mm is the height of the
# foot centres above the floor in the SRDF's standing posture, i.e. the foot radius for which
# that posture just touches the floor.
SOLO12_FOOT_RADIUS = 0.019
# Body collision spheres (``solo12(body_contacts=True)``), from the bounding boxes of the URDF's
# collision meshes (example-robot-data, meshes/stl): the base (solo_12_base.stl) spans
# [-0.2241, 0.2241] x [-0.1095, 0.1095] x [-0.025, 0.028] m in base_link; four spheres of its
# half thickness at its corners, inset by that radius, touch the floor where its bottom edges
# would. Each knee gets a sphere at the KFE axis whose radius reaches the end of the upper leg
# below the axis (solo_upper_leg_*.stl ends 0.022 m past it) and covers the lower leg's width.
SOLO12_BASE_HALF_EXTENTS = (0.2241, 0.1095, 0.0265)
SOLO12_BASE_CENTRE_Z = 0.0015
SOLO12_KNEE_RADIUS = 0.022
SOLO12_KNEES = ("FL_KFE", "FR_KFE", "HL_KFE", "HR_KFE")
# Peak joint torque of Solo-12's actuators (0.025 N m/A x 9:1 gear x 12 A): Grimminger et al.,
# "An open torque-controlled modular robot architecture for legged locomotion research",
# IEEE RA-L 2020. The URDF's 1000 N m are placeholders.
SOLO12_TORQUE_LIMIT = 2.7
# Rotor inertia reflected through the 9:1 transmission, I_rotor N^2 = 4.5e-6 kg m^2 x 81: the
# values ODRI's robot_properties_solo sets on its Pinocchio model (config.py, Solo12Config:
# motor_inertia = 0.0000045, motor_gear_ration = 9.0); the 9:1 dual-stage belt reduction is
# that of the ODRI actuator module (open_robot_actuator_hardware, actuator_module_v1). The URDF
# has none. It is 0.67 of the knee's own inertia about its axis (5.4e-4 kg m^2 standing).
SOLO12_ARMATURE = 4.5e-6 * 9.0**2
# Viscous joint damping (N m s/rad), not identified on the hardware: a small round value that
# keeps the 10 ms step from diverging under open-loop random torques up to the torque limit.
# It is small next to the damping of a voltage-driven motor, (Kt N)^2 / R =
# (0.025 x 9)^2 / 0.23 = 0.22 N m s/rad, and gives 0.27 N m (10% of the torque limit) at 27 rad/s.
SOLO12_JOINT_DAMPING = 0.01


def _number(name: str, value, *, zero: bool = False, infinite: bool = False) -> float:
    """A factory's physical parameter as a float, checked: positive (or zero, where `zero`)
    and finite (or ``+inf``, "unlimited", where `infinite`); else a `ValueError` naming it."""
    sign = "non-negative" if zero else "positive"
    allowed = f"{sign} (inf: unlimited)" if infinite else f"{sign} and finite"
    if isinstance(value, bool) or np.ndim(value) != 0:
        raise ValueError(f"{name} must be a {sign} number, got {value!r}")
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a {sign} number, got {value!r}") from None
    in_range = number >= 0 if zero else number > 0
    if not (in_range and (np.isfinite(number) or (infinite and number == np.inf))):
        raise ValueError(f"{name} must be {allowed}, got {number}")
    return number


def _as_contact(contact: ContactLaw | str, friction: float) -> ContactLaw:
    """``"hard"``, a compliant law, or the names ``"spring_damper"``/``"log_barrier"`` with
    default parameters."""
    if isinstance(contact, str):
        if contact == "hard":
            return "hard"
        if contact == "spring_damper":
            return SpringDamper(stiffness=1e4, damping=1e2, friction=friction)
        if contact == "log_barrier":
            return LogBarrier(stiffness=1e-2, friction=friction)
        raise ValueError(f"contact must be 'hard', 'spring_damper', 'log_barrier' or a contact law, got {contact!r}")
    return contact


def _planes(planes, friction) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Normals (unit), offsets and friction per plane from ``((normal, offset), ...)`` and a
    friction coefficient or one per plane; checked."""
    try:
        normals = np.array([p[0] for p in planes], dtype=np.float64).reshape(len(planes), 3)
        offsets = np.array([p[1] for p in planes], dtype=np.float64).reshape(len(planes))
    except (TypeError, ValueError, IndexError):
        raise ValueError(f"planes must be a sequence of (normal (3,), offset) pairs, got {planes!r}") from None
    if len(planes) == 0:
        raise ValueError("planes must hold at least one (normal, offset) pair")
    lengths = np.linalg.norm(normals, axis=1)
    if not (np.all(np.isfinite(normals)) and np.all(np.isfinite(offsets)) and np.all(lengths > 0)):
        raise ValueError(f"planes must have finite, non-zero normals and finite offsets, got {planes!r}")
    if np.ndim(friction) == 0:
        mu = np.full(len(planes), _number("friction", friction, zero=True))
    else:
        mu = np.array([_number("friction", f, zero=True) for f in friction])
        if mu.shape != (len(planes),):
            raise ValueError(f"friction must be a number or one per plane ({len(planes)}), got {friction!r}")
    return device_array(normals / lengths[:, None]), device_array(offsets), device_array(mu)


def _gravity(gravity) -> np.ndarray:
    vector = np.asarray(gravity, dtype=np.float64)
    if vector.shape != (3,) or not np.all(np.isfinite(vector)):
        raise ValueError(f"gravity must be a finite vector (3,) in m/s^2, got {gravity!r}")
    return vector


def _resting_configuration(normal: np.ndarray, offset: float, height: float) -> np.ndarray:
    """The free-flyer configuration ``[p, quaternion]`` ``(7,)`` of a body resting on the
    half-space ``{p : n . p >= offset}`` (``n`` unit): its centre ``height`` above the plane's
    point nearest the origin, its ``z`` axis along ``n`` (the shortest rotation from ``e_z``), so
    that the body's ``-z`` side faces the plane."""
    normal = np.asarray(normal, dtype=np.float64)
    if normal[2] > -1.0 + 1e-12:
        quaternion = np.array([-normal[1], normal[0], 0.0, 1.0 + normal[2]])  # [e_z x n, 1 + e_z . n]
    else:
        quaternion = np.array([1.0, 0.0, 0.0, 0.0])  # upside down: half a turn about x
    return np.concatenate([(float(offset) + height) * normal, quaternion / np.linalg.norm(quaternion)]) + 0.0  # no -0


def _free_body_system(model, name, offsets, radii, planes, friction, time_step, contact, solver, baumgarte, wrench_components, height):
    """A free body whose spheres (``offsets`` in its frame, ``radii``) touch half-spaces, driven by
    a wrench at its centre of mass, starting at rest on the first half-space with its centre
    ``height`` above it."""
    normals, plane_offsets, mu = _planes(planes, friction)
    if not isinstance(contact, str) or contact == "hard":
        law = _as_contact(contact, 0.0)
    elif np.ndim(friction) == 0:
        law = _as_contact(contact, float(friction))
    else:
        raise ValueError("one friction coefficient per plane needs contact='hard' or a contact law instance")
    return RigidBodySystem(
        model=model,
        geometry=Geometry(
            sphere_frames=(model.frame_id(name),) * len(radii),
            sphere_offsets=device_array(offsets),
            sphere_radii=device_array(radii),
            plane_normals=normals,
            plane_offsets=plane_offsets,
            friction=mu,
        ),
        options=Options(_number("time_step", time_step), law, solver, baumgarte),
        actuation=Actuation(
            "wrench",
            device_array(np.full(len(wrench_components), np.inf)),
            wrench_frame=model.frame_id(name),
            wrench_components=tuple(int(c) for c in wrench_components),
        ),
        initial_configuration=device_array(_resting_configuration(np.asarray(normals)[0], np.asarray(plane_offsets)[0], height)),
    )


def box(
    *,
    half_extents=(0.1, 0.1, 0.1),
    mass: float = 1.0,
    friction=0.5,
    planes=(FLOOR,),
    gravity=(0.0, 0.0, -9.81),
    time_step: float = 0.01,
    contact: ContactLaw | str = "hard",
    solver: NCPSolver = NCPSolver(sticking_guess=True, rank_deficient=True, polish=True),
    baumgarte: float = 0.2,
    wrench_components: tuple[int, ...] = (0, 1, 2, 3, 4, 5),
    name: str = "box",
) -> RigidBodySystem:
    """A box among half-spaces (a floor, an incline, walls), pushed by a wrench.

    Its eight corners are point contacts with every half-space ``{p : n . p >= offset}``. The
    input is a wrench ``u = [fx, fy, fz, tx, ty, tz]`` in world axes at the centre of mass, or
    the components listed in ``wrench_components``; ``nx = 13``. ``initial_state()``: the box
    at rest on the first half-space, its ``-z`` face flat on it (its ``z`` axis along the
    plane's normal), centred above the plane's point nearest the origin.

    Args:
        half_extents: half side lengths ``(3,)`` (m), positive.
        mass: mass (kg); a uniform box, ``I_x = m (b^2 + c^2) / 3`` from half extents.
        friction: Coulomb coefficient, one for all half-spaces or one per half-space.
        planes: the half-spaces, ``((normal, offset), ...)``; the normal need not be unit.
        gravity: gravity in world axes (m/s^2), e.g. tilted for an incline.
        time_step: ``h`` (s).
        contact: ``"hard"`` (NCP), ``"spring_damper"``, ``"log_barrier"`` or a law instance.
        solver: NCP solver configuration (hard contact): the sticking guess by the
            pseudo-inverse (``NCPSolver.rank_deficient``: four coplanar corners make the
            Delassus matrix singular), then the active-set polish (from the previous step's
            impulses in a rollout: it keeps a sliding box's non-unique impulses where they
            were), then ADMM.
        baumgarte: penetration correction rate (hard contact).
        wrench_components: indices into ``[fx, fy, fz, tx, ty, tz]`` of the inputs.
        name: the body's frame name.

    Returns:
        The system.

    Example:
        >>> import rsmooth.sim as sim
        >>> slab = sim.box(half_extents=(0.2, 0.1, 0.05), mass=2.0, friction=0.8)
        >>> slab.nx, slab.nu, slab.num_contacts
        (13, 6, 8)
    """
    extents = np.array([_number("half_extents", e) for e in np.ravel(half_extents)])
    if extents.shape != (3,):
        raise ValueError(f"half_extents must have shape (3,), got {np.shape(half_extents)}")
    mass = _number("mass", mass)
    squares = extents**2
    inertia = mass / 3.0 * np.array([squares[1] + squares[2], squares[0] + squares[2], squares[0] + squares[1]])
    model = free_body(mass, inertia, name=name, gravity=_gravity(gravity))
    corners = np.array(list(itertools.product((-1.0, 1.0), repeat=3))) * extents
    return _free_body_system(
        model, name, corners, np.zeros(8), planes, friction, time_step, contact, solver, baumgarte, wrench_components,
        height=extents[2],
    )


def ball(
    *,
    radius: float = 0.05,
    mass: float = 0.1,
    friction=0.3,
    planes=(FLOOR,),
    gravity=(0.0, 0.0, -9.81),
    time_step: float = 0.01,
    contact: ContactLaw | str = "hard",
    solver: NCPSolver = NCPSolver(),
    baumgarte: float = 0.2,
    name: str = "ball",
) -> RigidBodySystem:
    """A solid ball among half-spaces, pushed by a force ``u = [fx, fy, fz]`` (world axes) at its
    centre; ``nx = 13``, ``nu = 3``. ``initial_state()``: the ball at rest on the first
    half-space, above the plane's point nearest the origin (on the default floor: at
    ``(0, 0, radius)``).

    Args:
        radius: radius (m).
        mass: mass (kg); a solid ball, inertia ``2 m r^2 / 5``.
        friction, planes, gravity, time_step, contact, solver, baumgarte, name: as in
            :func:`box`.

    Returns:
        The system.
    """
    radius, mass = _number("radius", radius), _number("mass", mass)
    model = free_body(mass, np.full(3, 0.4 * mass * radius**2), name=name, gravity=_gravity(gravity))
    return _free_body_system(
        model, name, np.zeros((1, 3)), np.array([radius]), planes, friction, time_step, contact, solver, baumgarte, (0, 1, 2),
        height=radius,
    )


def cube(
    *,
    side: float = 0.2,
    mass: float = 1.0,
    friction: float = 0.5,
    time_step: float = 0.01,
    contact: ContactLaw | str = "hard",
    solver: NCPSolver = NCPSolver(sticking_guess=True, rank_deficient=True),
    baumgarte: float = 0.2,
    wrench_components: tuple[int, ...] = (0, 1, 2, 3, 4, 5),
) -> RigidBodySystem:
    """A cube on a floor, pushed by a wrench: the system of Fig. 2 of Le Lidec et al. 2022.

    Its eight corners are point contacts with the floor ``z = 0``. The input is a wrench
    ``u = [fx, fy, fz, tx, ty, tz]`` in world axes applied at the centre of mass, or the
    components of it listed in ``wrench_components`` (e.g. ``(2,)``: a vertical force only):
    ``nx = 13`` (position, quaternion, linear and angular velocity),
    ``nu = len(wrench_components)``.

    Args:
        side: edge length (m).
        mass: mass (kg); the inertia is that of a uniform cube, ``m s^2 / 6``.
        friction: Coulomb coefficient of the floor.
        time_step: ``h`` (s).
        contact: ``"hard"`` (NCP), ``"spring_damper"``, ``"log_barrier"`` or a law instance.
        solver: NCP solver configuration (hard contact); by default the sticking guess by
            the pseudo-inverse (``NCPSolver.rank_deficient``: four coplanar corners make the
            Delassus matrix singular), then ADMM. For a cube sliding at a friction of about
            0.8 or more, add ``polish=True`` (:func:`box`'s default), without which a few
            steps end unconverged (reported in the step's diagnostics); it costs compilation
            and, from a cold start, time.
        baumgarte: penetration correction rate (hard contact).
        wrench_components: indices into ``[fx, fy, fz, tx, ty, tz]`` of the inputs.

    Returns:
        The system; ``initial_state()`` is the cube resting flat on the floor at the origin.

    Raises:
        ValueError: ``side``, ``mass`` or ``time_step`` is not positive and finite, or
            ``friction`` is negative or not finite.

    References:
        Q. Le Lidec, L. Montaut, C. Schmid, I. Laptev, J. Carpentier, "Augmenting
        differentiable physics with randomized smoothing", 2022.
    """
    side = _number("side", side)
    return box(
        half_extents=(side / 2,) * 3, mass=mass, friction=friction, time_step=time_step, contact=contact,
        solver=solver, baumgarte=baumgarte, wrench_components=wrench_components, name="cube",
    )


def ball_wall(
    *,
    radius: float = 0.05,
    mass: float = 0.1,
    wall_distance: float = 1.0,
    friction: float = 0.3,
    time_step: float = 0.01,
    contact: ContactLaw | str = "hard",
    solver: NCPSolver = NCPSolver(),
    baumgarte: float = 0.2,
) -> RigidBodySystem:
    """A ball thrown at a wall: a sphere against the floor ``z = 0`` and the wall
    ``x = wall_distance`` (facing ``-x``).

    Whether the ball reaches the wall before landing decides where it ends: the final
    position is discontinuous in the throw, the geometric discontinuity smoothing has to
    deal with. The input is a force ``u = [fx, fy, fz]`` in world axes at the centre
    (``nu = 3``; a throw is a large force during the first step), ``nx = 13``.
    ``initial_state()``: the ball at rest on the floor at ``(0, 0, radius)``, its centre
    ``wall_distance`` from the wall.

    Args:
        radius: ball radius (m).
        mass: mass (kg); a solid ball, inertia ``2 m r^2 / 5``.
        wall_distance: ``x`` of the wall (m).
        friction: Coulomb coefficient of floor and wall.
        time_step: ``h`` (s).
        contact: ``"hard"`` (NCP), ``"spring_damper"``, ``"log_barrier"`` or a law instance.
        solver: NCP solver configuration (hard contact).
        baumgarte: penetration correction rate (hard contact).

    Returns:
        The system.

    Raises:
        ValueError: ``radius``, ``mass`` or ``time_step`` is not positive and finite,
            ``wall_distance`` is not finite, or ``friction`` is negative or not finite.
    """
    if not (isinstance(wall_distance, (int, float, np.integer, np.floating)) and np.isfinite(wall_distance)) or isinstance(wall_distance, bool):
        raise ValueError(f"wall_distance must be a finite number, got {wall_distance!r}")
    return ball(
        radius=radius, mass=mass, friction=friction, planes=[FLOOR, ((-1.0, 0.0, 0.0), -float(wall_distance))],
        time_step=time_step, contact=contact, solver=solver, baumgarte=baumgarte,
    )


def _inertia(shape, mass: float) -> np.ndarray:
    """Principal moments ``(3,)`` of a uniform solid ``shape`` of ``mass`` about its centre, in
    its frame."""
    if isinstance(shape, Sphere):
        return np.full(3, 0.4 * mass * float(shape.radius) ** 2)
    if isinstance(shape, Box):
        squares = np.asarray(shape.half_extents, dtype=np.float64) ** 2
        return mass / 3.0 * np.array([squares[1] + squares[2], squares[0] + squares[2], squares[0] + squares[1]])
    if isinstance(shape, Ellipsoid):
        squares = np.asarray(shape.radii, dtype=np.float64) ** 2
        return mass / 5.0 * np.array([squares[1] + squares[2], squares[0] + squares[2], squares[0] + squares[1]])
    r, a = float(shape.radius), float(shape.half_length)  # Cylinder or Capsule, axis z
    if isinstance(shape, Cylinder):
        return np.array([mass * (3 * r**2 + 4 * a**2) / 12, mass * (3 * r**2 + 4 * a**2) / 12, mass * r**2 / 2])
    # capsule: a cylinder of length 2a and two hemispheres, masses in proportion to volume
    cylinder_volume, ball_volume = 2 * np.pi * r**2 * a, 4 / 3 * np.pi * r**3
    m_c = mass * cylinder_volume / (cylinder_volume + ball_volume)
    m_b = mass - m_c
    axial = m_c * r**2 / 2 + 0.4 * m_b * r**2
    # hemispheres: 2/5 m r^2 about their centre of curvature, moved to the capsule's centre
    # (their centres of mass are 3 r / 8 beyond the cylinder's ends)
    transverse = m_c * (3 * r**2 + 4 * a**2) / 12 + m_b * (0.4 * r**2 + a**2 + 0.75 * a * r)
    return np.array([transverse, transverse, axial])


def _bodies_model(names, masses, inertias, gravity) -> Model:
    """Free bodies, each on its own free-flyer joint under the world; frames ``"universe"``,
    then ``f"{name}_joint"`` and ``name`` per body."""
    n = len(names)
    eye = np.eye(3)
    to_jax = device_array
    frame_names = ("universe",) + tuple(f for name in names for f in (f"{name}_joint", name))
    return Model(
        joint_names=("universe",) + tuple(f"{name}_joint" for name in names),
        joint_types=(UNIVERSE,) + (FREE_FLYER,) * n,
        parents=(0,) * (n + 1),
        idx_q=(0,) + tuple(7 * i for i in range(n)),
        idx_v=(0,) + tuple(6 * i for i in range(n)),
        frame_names=frame_names,
        frame_parents=(0,) + tuple(j for j in range(1, n + 1) for _ in range(2)),
        nq=7 * n,
        nv=6 * n,
        joint_axes=to_jax(np.zeros((n + 1, 3))),
        joint_placement_rotation=to_jax([eye] * (n + 1)),
        joint_placement_translation=to_jax(np.zeros((n + 1, 3))),
        body_mass=to_jax([0.0, *masses]),
        body_com=to_jax(np.zeros((n + 1, 3))),
        body_inertia=to_jax([np.zeros((3, 3))] + [np.diag(i) for i in inertias]),
        frame_placement_rotation=to_jax([eye] * (2 * n + 1)),
        frame_placement_translation=to_jax(np.zeros((2 * n + 1, 3))),
        lower_position_limit=to_jax(np.full(7 * n, -np.inf)),
        upper_position_limit=to_jax(np.full(7 * n, np.inf)),
        velocity_limit=to_jax(np.full(6 * n, np.inf)),
        effort_limit=to_jax(np.full(6 * n, np.inf)),
        armature=to_jax(np.zeros(6 * n)),
        gravity=to_jax(gravity),
    )


def bodies(
    shapes,
    masses,
    positions,
    *,
    orientations=None,
    planes=(FLOOR,),
    obstacles=(),
    friction: float = 0.5,
    margin: float = 0.01,
    gravity=(0.0, 0.0, -9.81),
    time_step: float = 0.01,
    solver: NCPSolver = NCPSolver(sticking_guess=True, rank_deficient=True, polish=True, max_iterations=1000),
    baumgarte: float = 0.2,
    max_contacts: int | None = None,
    max_pairs: int | None = None,
) -> RigidBodySystem:
    """Free rigid bodies among half-spaces and fixed obstacles, colliding with all of them and
    with each other (hard contact).

    Every body is a uniform solid (its inertia from its shape and mass) on its own free-flyer
    joint, its frame at its centre. Contacts are :class:`~rsmooth.sim.GeomPair` manifolds:
    every body against every half-space and every obstacle, and every pair of bodies. The
    input ``u`` ``(6 n,)`` holds each body's generalized force ``[force, torque]`` in its body
    axes; ``nx = 13 n``. ``initial_state()``: the bodies at ``positions`` and
    ``orientations``, at rest.

    Args:
        shapes: one :class:`~rsmooth.sim.Sphere`, :class:`~rsmooth.sim.Box`,
            :class:`~rsmooth.sim.Capsule`, :class:`~rsmooth.sim.Cylinder` or
            :class:`~rsmooth.sim.Ellipsoid` per body.
        masses: a mass (kg) per body, positive.
        positions: the bodies' initial centres in the world, ``(n, 3)`` (m).
        orientations: their initial unit quaternions ``[qx, qy, qz, qw]``, ``(n, 4)``;
            ``None``: the identity.
        planes: the half-spaces ``((normal, offset), ...)``, ``{p : n . p >= offset}``; the
            normal need not be unit.
        obstacles: world-fixed shapes, ``((shape, (rotation (3, 3), translation (3,))), ...)``.
        friction: Coulomb coefficient of every contact.
        margin: distance within which manifold entries are candidate contacts
            (:attr:`GeomPair.margin`, m).
        gravity: gravity in world axes (m/s^2).
        time_step: ``h`` (s).
        solver: NCP solver configuration: the sticking guess by the pseudo-inverse (the
            coplanar corners of a face resting on a face make the Delassus matrix singular),
            the active-set polish, then ADMM, up to 1000 iterations (a stack of bodies of
            different masses couples their contacts into a worse-conditioned problem than
            one body's).
        baumgarte: penetration correction rate.
        max_contacts: solve at most this many contacts per step, the closest candidates
            (:attr:`~rsmooth.sim.Options.max_contacts`): ``n`` boxes have
            ``2 n (n - 1) + 4 n`` candidates on a floor, of which about ``4 n`` touch when
            they rest; ``None``: all.
        max_pairs: collide at most this many pairs of each pair group per step, those whose
            bounding spheres are closest (:attr:`~rsmooth.sim.Options.max_pairs`,
            exact while no more are within the margin): ``n`` boxes have ``n (n - 1) / 2``
            box pairs, of which about ``n`` touch in a stack; ``None``: all.

    Returns:
        The system; its frames are ``"body0"``, ``"body1"``, ...

    Raises:
        ValueError: a shape is not one of the four, a mass is not positive, the sizes of
            ``shapes``, ``masses``, ``positions`` and ``orientations`` differ, a pair of shapes
            has no collision function, or a parameter is out of range.

    Example:
        >>> import rsmooth.sim as sim
        >>> stack = sim.bodies([sim.Box([0.1, 0.1, 0.1])] * 2, [1.0, 1.0], [[0, 0, 0.1], [0, 0, 0.3]])
        >>> stack.nx, stack.nu, stack.num_contacts
        (26, 12, 12)
    """
    shapes = tuple(shapes)
    n = len(shapes)
    if n == 0:
        raise ValueError("shapes must hold at least one shape")
    for i, shape in enumerate(shapes):
        if not isinstance(shape, (Sphere, Box, Capsule, Cylinder, Ellipsoid)):
            raise ValueError(f"shapes[{i}] must be a Sphere, Box, Capsule, Cylinder or Ellipsoid, got {type(shape).__name__}")
    masses = [_number(f"masses[{i}]", m) for i, m in enumerate(np.ravel(np.asarray(masses, dtype=object)))]
    if len(masses) != n:
        raise ValueError(f"masses must hold one mass per shape ({n}), got {len(masses)}")
    positions = np.asarray(positions, dtype=np.float64)
    if positions.shape != (n, 3) or not np.all(np.isfinite(positions)):
        raise ValueError(f"positions must be finite with shape ({n}, 3), got {positions.shape}")
    if orientations is None:
        orientations = np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))
    orientations = np.asarray(orientations, dtype=np.float64)
    if orientations.shape != (n, 4) or not np.allclose(np.linalg.norm(orientations, axis=1), 1.0, atol=1e-9):
        raise ValueError(f"orientations must be unit quaternions [qx, qy, qz, qw] with shape ({n}, 4)")
    friction = _number("friction", friction, zero=True)
    names = tuple(f"body{i}" for i in range(n))
    model = _bodies_model(names, masses, [_inertia(s, m) for s, m in zip(shapes, masses)], _gravity(gravity))
    world = []
    if planes:
        normals, offsets, _ = _planes(planes, 0.0)
        for normal, offset in zip(np.asarray(normals), np.asarray(offsets)):
            # the HalfSpace is z <= 0 of its frame: the frame's z along the plane's normal
            world.append((HalfSpace(), (contact_frame(jnp.asarray(normal)), jnp.asarray(offset * normal))))
    for index, obstacle in enumerate(obstacles):
        if not (isinstance(obstacle, (tuple, list)) and len(obstacle) == 2):
            raise ValueError(f"obstacles[{index}] must be (shape, (rotation, translation)), got {obstacle!r}")
        world.append(tuple(obstacle))
    pairs = []
    for i in range(n):
        for shape, pose in world:
            pairs.append(GeomPair(shape, None, shapes[i], names[i], placement1=pose, friction=friction, margin=margin))
    for i, j in itertools.combinations(range(n), 2):
        try:
            manifold_size(shapes[i], shapes[j])
        except NotImplementedError:
            raise ValueError(
                f"shapes[{i}] and shapes[{j}]: no collision function for {type(shapes[i]).__name__} against "
                f"{type(shapes[j]).__name__}"
            ) from None
        pairs.append(GeomPair(shapes[i], names[i], shapes[j], names[j], friction=friction, margin=margin))
    return geom_pair_system(
        model,
        pairs,
        time_step=_number("time_step", time_step),
        solver=solver,
        baumgarte=baumgarte,
        actuated_dofs=tuple(range(6 * n)),
        input_limit=np.full(6 * n, np.inf),
        initial_configuration=np.concatenate([positions, orientations], axis=1).reshape(-1),
    ).with_contact_budget(max_contacts, max_pairs)


def geom_pair_system(
    model: Model, pairs, *, time_step, solver, baumgarte, actuated_dofs, input_limit, initial_configuration,
    joint_damping=None,
) -> RigidBodySystem:
    """A hard-contact system whose contacts are all :class:`GeomPair` manifolds (no contact
    spheres or half-spaces of their own) and whose input ``u`` is the generalized force on
    ``actuated_dofs``: what :func:`bodies` and :func:`~rsmooth.sim.scene` build."""
    return RigidBodySystem(
        model=model,
        geometry=Geometry(geom_pairs=tuple(pairs)),
        options=Options(float(time_step), "hard", solver, baumgarte),
        actuation=Actuation("joints", jnp.asarray(input_limit), dofs=tuple(actuated_dofs)),
        joints=Joints(damping=None if joint_damping is None else jnp.asarray(joint_damping)),
        initial_configuration=jnp.asarray(initial_configuration),
    )


def _pusher_model(box_side: float, box_mass: float, finger_mass: float, finger_height: float) -> Model:
    """A free box and a finger on two prismatic joints (x, then y) at a fixed height."""
    eye = np.eye(3)
    inf = np.inf
    box_inertia = np.eye(3) * box_mass * box_side**2 / 6.0
    finger_inertia = np.eye(3) * 1e-6  # a point-like finger (only its translation moves)
    to_jax = device_array
    return Model(
        joint_names=("universe", "root_joint", "finger_x", "finger_y"),
        joint_types=(UNIVERSE, FREE_FLYER, PRISMATIC, PRISMATIC),
        parents=(0, 0, 0, 2),
        idx_q=(0, 0, 7, 8),
        idx_v=(0, 0, 6, 7),
        frame_names=("universe", "root_joint", "box", "finger_x", "finger_y", "finger"),
        frame_parents=(0, 1, 1, 2, 3, 3),
        nq=9,
        nv=8,
        joint_axes=to_jax([[0, 0, 0], [0, 0, 0], [1, 0, 0], [0, 1, 0]]),
        joint_placement_rotation=to_jax([eye] * 4),
        joint_placement_translation=to_jax([[0, 0, 0], [0, 0, 0], [0, 0, finger_height], [0, 0, 0]]),
        body_mass=to_jax([0.0, box_mass, 0.0, finger_mass]),
        body_com=to_jax(np.zeros((4, 3))),
        body_inertia=to_jax([np.zeros((3, 3)), box_inertia, np.zeros((3, 3)), finger_inertia]),
        frame_placement_rotation=to_jax([eye] * 6),
        frame_placement_translation=to_jax(np.zeros((6, 3))),
        lower_position_limit=to_jax(np.full(9, -inf)),
        upper_position_limit=to_jax(np.full(9, inf)),
        velocity_limit=to_jax(np.full(8, inf)),
        effort_limit=to_jax(np.full(8, inf)),
        armature=to_jax(np.zeros(8)),
        gravity=to_jax([0.0, 0.0, -9.81]),
    )


def pusher(
    *,
    box_side: float = 0.2,
    box_mass: float = 1.0,
    finger_radius: float = 0.02,
    finger_mass: float = 0.1,
    floor_friction: float = 0.4,
    finger_friction: float = 0.5,
    force_limit: float = 20.0,
    time_step: float = 0.01,
    contact: ContactLaw | str = "hard",
    solver: NCPSolver = NCPSolver(sticking_guess=True, rank_deficient=True),
    baumgarte: float = 0.2,
) -> RigidBodySystem:
    """A planar finger pushing a box on a floor, through sticking and sliding friction.

    The box (a free body, its 8 corners against the floor) and a spherical finger moving in
    the horizontal plane at the box's mid-height (two prismatic joints, x then y, driven by the
    input forces ``u = [fx, fy]``, clipped to ``+-force_limit``). The finger touches the box
    through a :class:`~rsmooth.sim.GeomPair` (box, finger) without a margin: its contact is a
    candidate at any distance, at the box's signed distance (for a force at a distance, which
    acts at any gap); the finger does not touch the floor.
    ``nx = 9 + 8 = 17`` (box position and quaternion, finger x, y; then the velocities),
    ``nu = 2``.

    Args:
        box_side: edge of the cubic box (m).
        box_mass: box mass (kg).
        finger_radius: finger sphere radius (m); 0 for a point finger.
        finger_mass: finger mass (kg).
        floor_friction: box-floor Coulomb coefficient.
        finger_friction: finger-box Coulomb coefficient.
        force_limit: bound on each input force (N); ``inf`` for none.
        time_step: ``h`` (s).
        contact: ``"hard"`` (NCP), ``"spring_damper"``, ``"log_barrier"`` or a law instance.
        solver: NCP solver configuration (hard contact); by default the sticking guess by
            the pseudo-inverse (``NCPSolver.rank_deficient``, for the box's four coplanar
            corners), then ADMM.
        baumgarte: penetration correction rate (hard contact).

    Returns:
        The system; ``initial_state()`` is :func:`pusher_start_state`'s default: the box at
        rest at the origin, the finger 5 cm behind its ``-x`` face.

    Raises:
        ValueError: a size or mass is not positive and finite, a friction coefficient is
            negative, ``force_limit`` is not positive, or ``time_step`` is not positive and
            finite.
    """
    box_side, box_mass = _number("box_side", box_side), _number("box_mass", box_mass)
    finger_radius = _number("finger_radius", finger_radius, zero=True)
    finger_mass = _number("finger_mass", finger_mass)
    floor_friction = _number("floor_friction", floor_friction, zero=True)
    finger_friction = _number("finger_friction", finger_friction, zero=True)
    force_limit, time_step = _number("force_limit", force_limit, infinite=True), _number("time_step", time_step)
    model = _pusher_model(box_side, box_mass, finger_mass, box_side / 2)
    corners = np.array(list(itertools.product((-0.5, 0.5), repeat=3))) * box_side
    normals, offsets, mu = _planes([FLOOR], floor_friction)
    box = model.frame_id("box")
    finger = GeomPair(
        Box(jnp.full(3, box_side / 2)), "box", Sphere(float(finger_radius)), "finger", friction=finger_friction,
        margin=float("inf"),
    )
    return RigidBodySystem(
        model=model,
        geometry=Geometry(
            # The finger is a sphere above the floor too, but it stays at the box's mid-height:
            # its floor contact is a candidate that never acts.
            sphere_frames=(box,) * 8 + (model.frame_id("finger"),),
            sphere_offsets=jnp.zeros((9, 3)).at[:8].set(jnp.asarray(corners)),
            sphere_radii=jnp.zeros(9).at[8].set(float(finger_radius)),
            plane_normals=normals,
            plane_offsets=offsets,
            friction=mu,
            geom_pairs=(finger,),
        ),
        options=Options(float(time_step), _as_contact(contact, floor_friction), solver, baumgarte),
        actuation=Actuation("joints", jnp.full(2, float(force_limit)), dofs=(6, 7)),
        initial_configuration=jnp.asarray(_pusher_configuration(box_side / 2, finger_radius, 0.05, 0.0)),
    )


def _pusher_configuration(half: float, radius: float, finger_gap: float, finger_y: float) -> np.ndarray:
    """The pusher's box at rest on the floor at the origin and its finger ``finger_gap``
    behind the box's ``-x`` face, ``finger_y`` along it: ``q`` ``(9,)``."""
    return np.array([0.0, 0.0, half, 0.0, 0.0, 0.0, 1.0, -(half + radius + finger_gap), finger_y])


def _pusher_sizes(system: RigidBodySystem) -> tuple[float, float]:
    """The box's half side and the finger's radius of a :func:`pusher` system (m)."""
    pair = system.geometry.geom_pairs[0]
    return float(pair.shape1.half_extents[0]), float(pair.shape2.radius)


def pusher_start_state(system: RigidBodySystem, *, finger_gap: float = 0.05, finger_y: float = 0.0) -> jax.Array:
    """A :func:`pusher` start with the finger placed elsewhere than ``system.initial_state()``.

    Args:
        system: a :func:`pusher` system.
        finger_gap: the distance (m) from the finger's surface to the box's ``-x`` face.
        finger_y: the finger's offset (m) along that face.

    Returns:
        The box at rest on the floor at the origin and the finger at rest behind it, shape
        ``(17,)``; with the default arguments, ``system.initial_state()``.
    """
    half, radius = _pusher_sizes(system)
    return system.state(jnp.asarray(_pusher_configuration(half, radius, finger_gap, finger_y)))


def solo12(
    *,
    friction: float = 0.7,
    time_step: float = 0.01,
    contact: ContactLaw | str = "hard",
    solver: NCPSolver | None = None,
    baumgarte: float = 0.2,
    torque_limit: float = SOLO12_TORQUE_LIMIT,
    model: Model | None = None,
    armature: float = SOLO12_ARMATURE,
    joint_damping: float = SOLO12_JOINT_DAMPING,
    body_contacts: bool = False,
) -> RigidBodySystem:
    """The Solo-12 quadruped (18 dofs) with spherical feet on the floor and joint torques.

    The model comes from the URDF of the installed ``example-robot-data`` package (free-flyer
    base): ``nx = 19 + 18 = 37``, ``nu = 12`` joint torques ordered as the URDF's joints
    (``FL_HAA, FL_HFE, FL_KFE, FR_..., HL_..., HR_...``), clipped to ``+-torque_limit``
    (reported in the step's diagnostics). Feet are spheres of radius
    :data:`SOLO12_FOOT_RADIUS` at the ``*_FOOT`` frames (contacts 0-3); with
    ``body_contacts`` the base (four spheres at its corners) and the knees (a sphere each) also
    collide with the floor (contacts 4-11: base, then knees), so that a fallen robot lies on
    the floor instead of passing through it; without, the rest of the robot does not collide.

    Args:
        friction: Coulomb coefficient of the floor.
        time_step: ``h`` (s).
        contact: ``"hard"`` (NCP), ``"spring_damper"``, ``"log_barrier"`` or a law instance.
        solver: NCP solver configuration (hard contact); by default with the spectral
            penalty update (``rho_update_power=0.05``, see :class:`NCPSolver`: fewer ADMM
            iterations on the perturbed states of R-DDP), the sticking guess
            (``sticking_guess=True``: the steps where the feet on the floor stick are solved
            without ADMM) and the active-set Newton polish (``polish=True``: so are most of
            those where feet slide or lift); see benchmarks/RESULTS.md. With
            ``body_contacts``, ADMM's cap is 2,000 iterations instead of 500: a robot lying
            on its base, knees and feet presses up to 12 contacts (36 rows) on 18 degrees of
            freedom, where the impulses are far from unique and ADMM's tail is slow.
        baumgarte: penetration correction rate (hard contact).
        torque_limit: joint torque bound (N m).
        model: an already loaded Solo-12 model (default: loaded from the URDF).
        armature: reflected rotor inertia of each of the 12 joints (kg m^2), set on the
            model (:data:`SOLO12_ARMATURE`; the URDF has none).
        joint_damping: viscous damping of each of the 12 joints (N m s/rad), implicit
            (:data:`SOLO12_JOINT_DAMPING`). With neither, open-loop torques spin a lifted
            lower leg up without bound and the 10 ms step diverges within a second.
        body_contacts: whether the base and the knees collide too (8 more contacts, each
            solved in every step: costlier, and not needed while the robot stands).

    Returns:
        The system; ``initial_state()`` is the SRDF's standing posture with the base lowered
        until the feet touch the floor, which :func:`solo12_standing_torques` holds still.

    Raises:
        ValueError: ``time_step`` is not positive and finite, ``torque_limit`` is not
            positive, or ``friction``, ``armature`` or ``joint_damping`` is negative or not
            finite.
    """
    friction, time_step = _number("friction", friction, zero=True), _number("time_step", time_step)
    torque_limit = _number("torque_limit", torque_limit, infinite=True)
    armature = _number("armature", armature, zero=True)
    joint_damping = _number("joint_damping", joint_damping, zero=True)
    if solver is None:
        solver = NCPSolver(rho_update_power=0.05, sticking_guess=True, polish=True,
                           max_iterations=2000 if body_contacts else 500)
    if model is None:
        model = load_urdf(solo12_urdf_path())
    armatures = np.array(model.armature)
    armatures[6:] = float(armature)
    model = eqx.tree_at(lambda m: m.armature, model, device_array(armatures))
    frames = [model.frame_id(name) for name in SOLO12_FEET]
    centres = [np.zeros(3)] * 4
    radii = [SOLO12_FOOT_RADIUS] * 4
    if body_contacts:
        hx, hy, radius = SOLO12_BASE_HALF_EXTENTS
        for sx, sy in itertools.product((1.0, -1.0), repeat=2):
            frames.append(model.frame_id("base_link"))
            centres.append(np.array([sx * (hx - radius), sy * (hy - radius), SOLO12_BASE_CENTRE_Z]))
            radii.append(radius)
        for name in SOLO12_KNEES:
            frames.append(model.frame_id(name))
            centres.append(np.zeros(3))
            radii.append(SOLO12_KNEE_RADIUS)
    normals, offsets, mu = _planes([FLOOR], friction)
    fields = dict(
        model=model,
        geometry=Geometry(
            sphere_frames=tuple(frames),
            sphere_offsets=device_array(np.stack(centres)),
            sphere_radii=device_array(radii),
            plane_normals=normals,
            plane_offsets=offsets,
            friction=mu,
        ),
        options=Options(float(time_step), _as_contact(contact, friction), solver, baumgarte),
        actuation=Actuation(
            "joints", device_array(np.full(model.nv - 6, float(torque_limit))), dofs=tuple(range(6, model.nv))
        ),
        joints=Joints(damping=device_array(np.r_[np.zeros(6), np.full(model.nv - 6, float(joint_damping))])),
    )
    # The start: the SRDF's standing posture, lowered until the lowest contact sphere (a foot)
    # touches the floor.
    q = np.array(solo12_standing_configuration(model))
    distance, _, _ = _contacts(RigidBodySystem(**fields), device_array(q))
    q[2] -= float(np.asarray(distance).min())
    return RigidBodySystem(**fields, initial_configuration=device_array(q))


# Jitted so that set-up code calling it eagerly compiles one program instead of dispatching
# (and compiling) the kinematics' few hundred small operations one by one.
_contacts = eqx.filter_jit(lambda system, q: system.contacts(q))


@eqx.filter_jit
def solo12_foot_positions(system: RigidBodySystem, x: jax.Array) -> jax.Array:
    """World positions of the four foot centres (FL, FR, HL, HR), shape ``(4, 3)``."""
    q, _ = system.split(x)
    kinematics = _dynamics._kinematics(system.model, q)
    return jnp.stack([
        _dynamics._frame_placement(system.model, kinematics.rotation, kinematics.translation, f)[1]
        for f in system.geometry.sphere_frames
    ])


@eqx.filter_jit
def solo12_standing_torques(system: RigidBodySystem, x: jax.Array) -> jax.Array:
    """Joint torques that hold the robot still at ``x`` with its four feet on the floor.

    At rest, ``B tau + J_f^T f = g(q)`` (joint torques ``tau`` and world-frame foot forces
    ``f``): of its solutions, the one of least ``||tau||^2 + ||f||^2 / m^2`` with ``m`` the
    robot's mass (so both terms are comparable), by least squares.

    Args:
        system: a :func:`solo12` system.
        x: a state with the feet on the floor (e.g. ``system.initial_state()``).

    Returns:
        Torques, shape ``(12,)``.
    """
    model = system.model
    q, _ = system.split(x)
    gravity = _dynamics.gravity_torques(model, q)
    kinematics = _dynamics._kinematics(model, q)
    foot_jacobians = []
    for frame in system.geometry.sphere_frames[: len(SOLO12_FEET)]:  # the feet come first
        _, translation = _dynamics._frame_placement(model, kinematics.rotation, kinematics.translation, frame)
        contact_point = translation - jnp.array([0.0, 0.0, SOLO12_FOOT_RADIUS])
        foot_jacobians.append(_point_jacobian(model, kinematics, model.frame_parents[frame], contact_point))
    foot_jacobian = jnp.concatenate(foot_jacobians)  # (12, nv)
    selection = jnp.zeros((model.nv, system.nu)).at[np.asarray(system.actuation.dofs), jnp.arange(system.nu)].set(1.0)
    total_mass = jnp.sum(model.body_mass)
    scaled = jnp.concatenate([selection, foot_jacobian.T / total_mass], axis=1)
    solution = jnp.linalg.lstsq(scaled, gravity)[0]
    return solution[: system.nu]
