"""A Franka Emika Panda arm (example-robot-data's URDF) beside a box on a table, for pushing.

The scene is assembled with MuJoCo's model editor (``mujoco.MjSpec``) from the robot's URDF and
converted by :func:`~rsmooth.sim.scene`:

- the Panda's seven arm joints; its two finger joints are removed (the fingers welded
  closed, their ``<mimic>`` coupling with them);
- a sphere ``tool_radius`` at the tool centre point between the fingertips
  (``panda_hand_tcp``) collides with the box and the table: by default the only robot
  geometry in contact, so that a push is one sphere-box contact. The links named in
  ``colliding_links`` (:data:`PANDA_HAND_LINKS`: the hand and the fingers, the links that
  reach the table and the box when the hand points down) collide with the box and the table
  too, with their collision geometry (the hand's mesh, as its convex hull; four boxes per
  finger), not with the robot. Each link geom adds a pair with the box and one with the table
  (a mesh-box or box-box test and a half-space test, 4 candidate contacts each), and
  ``max_contacts`` bounds the contacts a step solves. The hand reaches below the box's top
  face, and at the start its mesh is nearer the box (its top edge) than the tool: with the
  hand colliding, a push may meet the box with the hand as well as with the tool. The links'
  collision meshes, colliding or not, also draw the arm (its visual meshes hold about 60
  times as many triangles, which the renderer would pay for in every frame);
- the table top is the half-space ``z <= 0`` under the robot's base, in contact with the tool,
  the colliding links and the box; the box is a free body at rest on it;
- seven motors, one per arm joint, bounded by Franka's torque limits; with
  ``gravity_compensation`` (default) the inputs are the torques beyond those that hold the
  arm against gravity, as Franka's torque interface takes them
  (:attr:`Actuation.gravity_compensation`), so that zero input holds the arm still.

The start (``initial_state()``) puts the tool ``tool_gap`` behind the box's ``-x`` face at the
box's mid-height, ``tool_y`` off its centre line, the hand pointing down (inverse kinematics at
build time), everything at rest.
"""

from __future__ import annotations

import dataclasses
import inspect
import pathlib

import jax.numpy as jnp
import numpy as np

from rsmooth.sim._model import example_robot_data_root
from rsmooth.sim._mujoco import MujocoModel, _mujoco, _read_urdf, load_mjcf
from rsmooth.sim._ncp import NCPSolver
from rsmooth.sim._scene import scene
from rsmooth.sim._simulator import RigidBodySystem
from rsmooth.sim._systems import _number

__all__ = ["PANDA_HAND_LINKS", "PANDA_LINKS", "PANDA_TORQUE_LIMITS", "panda_push", "panda_push_model"]

# Franka Emika's joint torque limits (N m), joints 1 to 7.
PANDA_TORQUE_LIMITS = (87.0, 87.0, 87.0, 87.0, 12.0, 12.0, 12.0)
# The links that move and have collision geometry (``panda_link0`` stands on the table):
# the names ``colliding_links`` takes.
PANDA_LINKS = tuple(f"panda_link{i}" for i in range(1, 8)) + ("panda_hand", "panda_leftfinger", "panda_rightfinger")
# The hand and its fingers: the links that reach the table and the box when the hand points
# down (the wrist, panda_link7, stays above the box's top at the start).
PANDA_HAND_LINKS = ("panda_hand", "panda_leftfinger", "panda_rightfinger")
# Collision bits (MuJoCo's contype / conaffinity): the tool, the box and the table collide
# through bit 1; the colliding links' contype is bit 2 only, which the table's and the box's
# conaffinity hold and the tool's and the links' do not, so that the links meet the box and
# the table and nothing of the robot.
_LINK_BIT = 2
# A configuration near the start (hand over the table, pointing down): the inverse kinematics'
# initial guess.
_IK_GUESS = np.array([0.0, 0.3, 0.0, -2.4, 0.0, 2.7, np.pi / 4])


def _panda_spec(mj, box_side: float, box_mass: float, box_position, tool_radius: float, table_friction: float,
                tool_friction: float, time_step: float, colliding_links: tuple[str, ...]):
    root = pathlib.Path(example_robot_data_root())
    spec = _read_urdf(mj, root / "robots" / "panda_description" / "urdf" / "panda.urdf", (str(root.parent),))
    for equality in list(spec.equalities):  # the fingers' <mimic>
        spec.delete(equality)
    for joint in [j for j in spec.joints if "finger" in j.name]:
        spec.delete(joint)
    for geom in spec.geoms:  # the links are drawn, not collided, unless named
        geom.contype = geom.conaffinity = 0
    tool = spec.body("panda_hand_tcp").add_geom()
    tool.name, tool.type, tool.size, tool.friction = "tool", mj.mjtGeom.mjGEOM_SPHERE, [tool_radius, 0, 0], [tool_friction, 0, 0]
    table = spec.worldbody.add_geom()
    table.name, table.type, table.size, table.friction = "table", mj.mjtGeom.mjGEOM_PLANE, [1.0, 1.0, 0.1], [table_friction, 0, 0]
    table.conaffinity = 1 | _LINK_BIT
    box = spec.worldbody.add_body()
    box.name, box.pos = "box", [box_position[0], box_position[1], box_side / 2]
    box.add_freejoint()
    geom = box.add_geom()
    geom.name, geom.type, geom.size = "box", mj.mjtGeom.mjGEOM_BOX, [box_side / 2] * 3
    geom.mass, geom.friction, geom.conaffinity = box_mass, [table_friction, 0, 0], 1 | _LINK_BIT
    for index, limit in enumerate(PANDA_TORQUE_LIMITS, start=1):
        motor = spec.add_actuator()
        motor.name, motor.target, motor.trntype = f"motor{index}", f"panda_joint{index}", mj.mjtTrn.mjTRN_JOINT
        motor.ctrllimited, motor.ctrlrange = 1, [-limit, limit]
    spec.option.timestep = time_step
    # The visual meshes (Collada files, 135,000 triangles against the collision meshes' 2,300)
    # are dropped: the links' collision meshes stay, not colliding, for drawing (the URDF gives
    # the links' inertias).
    for mesh in [m for m in spec.meshes if m.file.lower().endswith(".dae")]:
        for geom in [g for g in spec.geoms if g.meshname == mesh.name]:
            spec.delete(geom)
        spec.delete(mesh)
    for link in colliding_links:  # their collision geoms, with the tool's friction
        for geom in spec.body(link).geoms:
            geom.contype, geom.friction = _LINK_BIT, [tool_friction, 0, 0]
    return spec


def panda_push(
    *,
    box_side: float = 0.1,
    box_mass: float = 0.5,
    box_position: tuple[float, float] = (0.55, 0.0),
    tool_radius: float = 0.015,
    tool_gap: float = 0.03,
    tool_y: float = 0.0,
    table_friction: float = 0.4,
    tool_friction: float = 0.5,
    time_step: float = 0.01,
    gravity_compensation: bool = True,
    colliding_links: tuple[str, ...] = (),
    max_contacts: int | None = 24,
    solver: NCPSolver = NCPSolver(sticking_guess=True, rank_deficient=True, polish=True, max_iterations=1000),
) -> RigidBodySystem:
    """The Panda, a spherical tool at its fingertips, a box on the table (see the module).

    ``nx = 14 + 13`` (the seven arm joints, the box's position and quaternion; then the
    velocities), ``nu = 7`` (joint torques, N m).

    Args:
        box_side: edge of the cubic box (m).
        box_mass: its mass (kg).
        box_position: its centre's ``(x, y)`` on the table (m), in front of the robot.
        tool_radius: radius of the tool sphere (m).
        tool_gap: at the start, the distance from the tool to the box's ``-x`` face (m).
        tool_y: at the start, the tool's offset from the box's centre line (m).
        table_friction: Coulomb coefficient of the box on the table (and of the tool on it).
        tool_friction: Coulomb coefficient of the tool (and of the colliding links) on the box.
        time_step: ``h`` (s).
        gravity_compensation: inputs beyond the torques that hold the arm against gravity.
        colliding_links: links whose collision geometry (a mesh's convex hull, a finger's
            boxes) collides with the box and the table, not with the robot, beside the tool:
            names from :data:`PANDA_LINKS`, such as :data:`PANDA_HAND_LINKS`. Their friction
            is ``tool_friction`` (against the table, the larger of it and ``table_friction``).
        max_contacts: the most contacts between shapes each step solves, the closest
            candidates (:attr:`~rsmooth.sim.Options.max_contacts`; a step that leaves out one
            it closes is reported by :func:`~rsmooth.sim.check_steps`); ``None``: every
            candidate. It binds only with ``colliding_links``: the tool, the box and the
            table give 6 candidates, the hand links 72 more, of which a push touches up to
            about twenty (the box's 4 on the table, 4 for each link geom lying on a face of
            the box or on the table); the NCP's cost grows with the cube of the contacts it
            holds.
        solver: the contact solver.

    Raises:
        ValueError: a size, mass or time step that is not positive and finite, a negative
            friction coefficient or tool gap, a start out of the arm's reach, a
            ``colliding_links`` that is not a tuple of names from :data:`PANDA_LINKS`, or a
            ``max_contacts`` that is not a positive integer or ``None``.
    """
    _number("tool_gap", tool_gap, zero=True)
    mj = _mujoco()
    compiled = _panda_compiled(mj, box_side, box_mass, box_position, tool_radius, table_friction, tool_friction,
                               time_step, colliding_links)
    # The limits are set after the start: the file's zero configuration is beyond joint 4's.
    system = scene(load_mjcf(compiled), solver=solver, joint_limits=False, max_contacts=max_contacts)
    q = np.array(system.initial_state()[: system.model.nq])  # the box where the scene puts it
    q[:7] = _arm_start(mj, compiled, box_side, box_position, tool_radius, tool_gap, tool_y)
    system = dataclasses.replace(system.with_gravity_compensation(gravity_compensation), initial_configuration=jnp.asarray(q))
    return system.with_joint_limits()


def panda_push_model(**arguments) -> MujocoModel:
    """The :class:`~rsmooth.sim.MujocoModel` that ``panda_push(**arguments)`` is built from:
    its geoms, the links' meshes among them, are what an animation draws. Takes
    :func:`panda_push`'s keyword arguments (those that do not shape the model, such as
    ``tool_gap`` or ``solver``, change nothing here).

    Raises:
        TypeError: an argument :func:`panda_push` does not take.
        ValueError: as :func:`panda_push`, for the arguments that shape the model.
    """
    return load_mjcf(_compiled_scene(**arguments))


def _compiled_scene(**arguments):
    """The compiled ``mujoco.MjModel`` that ``panda_push(**arguments)`` is built from (see
    :func:`panda_push_model`)."""
    given = inspect.signature(panda_push).bind(**arguments)
    given.apply_defaults()
    shaping = inspect.signature(_panda_compiled).parameters
    return _panda_compiled(_mujoco(), **{name: given.arguments[name] for name in list(shaping)[1:]})


def _panda_compiled(mj, box_side: float, box_mass: float, box_position, tool_radius: float, table_friction: float,
                    tool_friction: float, time_step: float, colliding_links: tuple[str, ...]):
    """The scene's compiled ``mujoco.MjModel``, its arguments checked."""
    for name, value in (("box_side", box_side), ("box_mass", box_mass), ("tool_radius", tool_radius),
                        ("time_step", time_step)):
        _number(name, value)
    for name, value in (("table_friction", table_friction), ("tool_friction", tool_friction)):
        _number(name, value, zero=True)
    if not isinstance(colliding_links, tuple) or not all(isinstance(link, str) for link in colliding_links):
        raise ValueError(f"colliding_links must be a tuple of link names, got {colliding_links!r}")
    unknown = [link for link in colliding_links if link not in PANDA_LINKS]
    if unknown:
        raise ValueError(f"colliding_links: unknown links {unknown}; the links that can collide are {list(PANDA_LINKS)} "
                         "(panda_link0 stands on the table)")
    return _panda_spec(mj, box_side, box_mass, box_position, tool_radius, table_friction, tool_friction,
                       time_step, colliding_links).compile()


def _arm_start(mj, compiled, box_side: float, box_position, tool_radius: float, tool_gap: float,
               tool_y: float) -> np.ndarray:
    """The arm's ``q`` ``(7,)`` with its tool ``tool_gap`` behind the box's ``-x`` face at the
    box's mid-height (the hand pointing down), by Gauss-Newton on MuJoCo's kinematics."""
    data = mj.MjData(compiled)
    tool = mj.mj_name2id(compiled, mj.mjtObj.mjOBJ_GEOM, "tool")
    target = np.array([box_position[0] - box_side / 2 - tool_gap - tool_radius, box_position[1] + tool_y, box_side / 2])
    q = _IK_GUESS.copy()
    error = np.full(6, np.inf)
    for _ in range(100):
        data.qpos[:7] = q
        mj.mj_kinematics(compiled, data)
        mj.mj_comPos(compiled, data)
        rotation = data.geom_xmat[tool].reshape(3, 3)
        error = np.r_[target - data.geom_xpos[tool], np.cross(rotation[:, 2], [0.0, 0.0, -1.0])]
        if np.linalg.norm(error) < 1e-12:
            break
        position_jacobian, rotation_jacobian = np.zeros((3, compiled.nv)), np.zeros((3, compiled.nv))
        mj.mj_jacGeom(compiled, data, position_jacobian, rotation_jacobian, tool)
        jacobian = np.r_[position_jacobian[:, :7], rotation_jacobian[:, :7]]
        q = q + np.linalg.lstsq(jacobian, error, rcond=None)[0]
    if not np.linalg.norm(error) < 1e-9:
        raise ValueError(f"no arm configuration puts the tool at {target.tolist()} (inverse kinematics error "
                         f"{np.linalg.norm(error):.2g}): move the box within the arm's reach")
    return q
