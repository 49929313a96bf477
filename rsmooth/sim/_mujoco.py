"""Models loaded through MuJoCo's own compiler (MJCF, or URDF as MuJoCo reads it).

MuJoCo compiles the file (defaults, ``fromto``, mesh inertia, angle units...) into an
``mujoco.MjModel``; :func:`from_mujoco` converts that into rsmooth's :class:`~rsmooth.sim.Model`
(the kinematic tree, inertias, limits, armature, gravity) plus what the tree does not hold: the
joint damping, springs and dry friction, the time step, the actuators (motors, and position and
velocity servos: a fixed gain and an affine bias; their activation dynamics, integrators and
filters, :attr:`MujocoModel.activation_dynamics`), the fluid (MuJoCo's inertia-box model), and
the collision geometry as plain data. The conversion is checked once on the host and refuses, by name, what
rsmooth's dynamics do not model (as MJX's ``put_model`` does), instead of simulating something
else silently. Joint equalities (a URDF ``<mimic>``) are converted
(:attr:`MujocoModel.joint_couplings`); :func:`load_mjcf` drops them on request, with a warning.
Connect and weld equalities (closed kinematic loops, bodies held together) are converted too
(:attr:`MujocoModel.connections`, :attr:`MujocoModel.welds`).
Fixed tendons (lengths ``sum_i c_i qpos_i`` over hinges and slides) are converted for what
drives or constrains them: motors on a tendon (:attr:`MujocoModel.tendon_moments`, the input's
moment arms), equalities of one tendon (joint couplings on one or two joints, on more a row
that holds its length, :attr:`Tendons.equalities`) and the
tendon's linear spring, damper, dry friction and length limits (:attr:`MujocoModel.tendons`).
Spatial tendons through sites, wrapping around spheres and cylinders between two sites (with or
without a side site, which must lie outside its geom at ``qpos0``; one that moves inside it later
is counted by the step, :attr:`StepInfo.inside_side_sites`) and split into branches by
pulleys, are converted for their springs, dampers, dry friction, limits (a string) and equalities (a rod: the row
that holds the length); motors on them, a tendon's armature and equalities between two tendons
are refused by name.

Joint mapping. Every MuJoCo joint becomes one rsmooth joint, in MuJoCo's order, so rsmooth
joint ``j + 1`` is MuJoCo joint ``j`` and ``q``/``v`` have the layout of ``qpos``/``qvel``:
``hinge`` is ``"revolute"``, ``slide`` is ``"prismatic"``, ``ball`` is ``"spherical"``, ``free`` is
``"free_flyer"``. A hinge
turns about ``jnt_axis`` through ``jnt_pos`` (in its body's frame), so its rsmooth joint frame
is the body frame moved to ``jnt_pos``; the body, its inertia, geoms and sites are placed
relative to that frame. A body with several joints becomes a chain of rsmooth joints whose
intermediate bodies are massless (the last one carries the body), composed in MuJoCo's order.
A body without joints is welded to its parent: its inertia is merged into the parent's body
(parallel-axis theorem, as Pinocchio merges fixed joints). Every body, joint and site is a
frame named like it (bodies first, so ``model.frame_id(body_name)`` finds the body; an unnamed
element is called ``"<kind> <id>"``, e.g. ``"body 3"``).

Conventions that differ (see :meth:`MujocoModel.qpos_to_q` and friends): MuJoCo's free joint
has ``qpos = [x, y, z, qw, qx, qy, qz]`` and ``qvel = [linear velocity in world axes,
angular velocity in body axes]``; rsmooth's has ``q = [x, y, z, qx, qy, qz, qw]`` and
``v = [linear, angular]`` both in body axes. A ball joint's ``qpos = [qw, qx, qy, qz]`` is
rsmooth's ``[qx, qy, qz, qw]``; its ``qvel``, the angular velocity in the joint frame, is
rsmooth's ``v``. A hinge or slide with a reference position
(``ref``, MuJoCo's ``qpos0``) has ``q = qpos - qpos0``. Because rsmooth's free-joint basis turns
with the body, accelerations carry a transport term (:meth:`MujocoModel.qacc_to_a`) and
``nonlinear_effects`` equals ``T^T (qfrc_bias + M dT/dt v)`` rather than ``T^T qfrc_bias``.

Of ``opt``, the gravity, the time step and the ``gravity``, ``damper`` and ``filterparent``
disable flags are read. Ignored without error: ``opt.integrator``, the constraint solver and
its settings (``solver``, ``iterations``, ``tolerance``, ``cone``, ``impratio``...),
``solref``/``solimp``, ``condim``, margins and gaps, cameras, lights, visuals, sensors and
keyframes.
"""

from __future__ import annotations

import contextlib
import os
import pathlib
import re
import warnings
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

from rsmooth._xla import device_array
from rsmooth.sim import _spatial as spatial
from rsmooth.sim._model import FREE_FLYER, PRISMATIC, REVOLUTE, SPHERICAL, UNIVERSE, Model
from rsmooth.sim._geometry import HeightField
from rsmooth.sim._simulator import (
    ActivationDynamics, Fluid, GravityCompensation, JointCoupling, PointConnection, Tendons, Weld,
)

# The geom types a collision routine may meet; SDFs are accepted only when they cannot collide
# (purely visual), so that geom indices stay MuJoCo's.
GEOM_TYPES = ("plane", "hfield", "sphere", "capsule", "ellipsoid", "cylinder", "box", "mesh")


def _mujoco() -> Any:
    try:
        import mujoco
    except ImportError as error:  # pragma: no cover - depends on the environment
        raise ImportError("loading MJCF files needs MuJoCo: pip install mujoco") from error
    return mujoco


class MujocoModel(eqx.Module):
    """A MuJoCo model converted for rsmooth: the kinematic tree plus damping, time step,
    motors and collision geometry, and the maps between MuJoCo's and rsmooth's state vectors.

    Indices: geoms, bodies and actuators keep MuJoCo's ids; ``geom_joints`` and
    ``body_joints`` give the rsmooth joint (index into ``model``) that moves each of them.

    Attributes:
        model: the rsmooth kinematic tree (``model.gravity`` is ``opt.gravity``, or zero where
            gravity is disabled; ``model.armature`` is ``dof_armature``; position limits are
            ``jnt_range - qpos0`` where ``jnt_limited``, and a limited ball joint's largest
            rotation angle (its range's second value) is its cone limit; ``model.effort_limit`` is the largest
            generalized force the motors of a joint can apply, ``inf`` where no limit applies).
        damping: ``(nv,)``, viscous joint damping ``dof_damping`` (the force is
            ``-damping * v``); zero where dampers are disabled.
        frictionloss: ``(nv,)``, dry joint friction ``dof_frictionloss``, the largest effort
            (N m or N) that resists a dof's motion (:class:`~rsmooth.sim.JointFriction`); zero
            where it is disabled (the ``frictionloss`` or ``constraint`` flag).
        stiffness: ``(nv,)``, the joint springs' ``jnt_stiffness`` on each dof (a ball joint's
            on its three), ``-stiffness (q - q_ref)``; zero where springs are disabled
            (:meth:`~rsmooth.sim.RigidBodySystem.with_joint_springs`).
        spring_reference: ``(nq,)``, the springs' rest configuration ``qpos_spring`` (their
            ``springref``) in rsmooth's coordinates (:meth:`qpos_to_q`).
        joint_couplings: the active joint equality constraints (``<equality><joint>``, a
            URDF's ``<mimic>``) as a :class:`~rsmooth.sim.JointCoupling` (rsmooth joints, MuJoCo's
            ``polycoef``), or ``None``; inactive ones (``active="false"``) are left out, and all
            where the ``equality`` or ``constraint`` flag is disabled. An equality of one
            fixed tendon on two joints is a coupling of one joint to the other.
        connections: the active connect equalities (``<equality><connect>``, between bodies or
            sites) as a :class:`~rsmooth.sim.PointConnection` (frames: MuJoCo's bodies by id,
            its sites after the bodies and joints), or ``None``; inactive ones and all where the
            ``equality`` or ``constraint`` flag is disabled are left out.
        welds: the active weld equalities (``<equality><weld>``, between bodies or sites) as a
            :class:`~rsmooth.sim.Weld` (frames as for connections), or ``None``; left out as
            connections are.
        tendons: the springs, dampers, dry friction and length limits of the tendons
            (:class:`~rsmooth.sim.Tendons`, spatial ones through their sites' frames; the
            ``spring``, ``damper``, ``frictionloss`` and ``limit`` flags honoured), or ``None``
            where none has any.
        gravcomp: the bodies' gravity compensation (``gravcomp``, a passive force) as a
            :class:`~rsmooth.sim.GravityCompensation`, or ``None`` without any or where the
            ``gravity`` flag is disabled.
        fluid: MuJoCo's inertia-box fluid model (``density``, ``viscosity``, ``wind``) on every
            body of positive mass (:class:`~rsmooth.sim.Fluid`), or ``None`` without density
            and viscosity.
        timestep: ``opt.timestep``, in seconds.
        limits_enforced: whether MuJoCo enforces the joints' position limits (``False`` where
            its ``limit`` or ``constraint`` flag is disabled; the limits stay in ``model``).
        body_names: name of every MuJoCo body (``"world"`` first).
        body_parents: MuJoCo parent body of every body (``body_parentid``; 0 for the world).
        body_joints: the rsmooth joint every MuJoCo body moves with (0 for the world and
            bodies welded to it).
        geom_names: name of every geom (``"geom <id>"`` when unnamed).
        geom_types: MuJoCo type name of every geom (:data:`GEOM_TYPES`, or ``"sdf"`` for geoms
            that cannot collide).
        geom_bodies: MuJoCo body of every geom.
        geom_joints: rsmooth joint every geom moves with.
        geom_size: ``(ngeom, 3)``, ``geom_size`` as MuJoCo defines it per type (radius, half
            lengths...).
        geom_rotation: ``(ngeom, 3, 3)``, placement of the geom in its joint's frame.
        geom_translation: ``(ngeom, 3)``.
        geom_friction: ``(ngeom,)``, sliding friction coefficient.
        geom_contype: ``contype`` bit mask of every geom.
        geom_conaffinity: ``conaffinity`` bit mask of every geom.
        geom_priority: ``priority`` of every geom (of two touching geoms, the friction of
            the one of higher priority applies; the larger of the two at equal priority).
        geom_vertices: for a mesh geom, its vertices ``(nvert, 3)`` in the geom's frame
            (``mesh_vert``); ``None`` for other geoms.
        geom_faces: for a mesh geom, its triangles ``(nface, 3)``, indices into its vertices;
            ``None`` for other geoms.
        geom_height_fields: for a height field geom, its :class:`~rsmooth.sim.HeightField`
            (MuJoCo's ``hfield_data`` times its elevation, its size and base); ``None`` for
            other geoms.
        geom_hull: for a mesh geom that MuJoCo collides, the vertices of the convex hull it
            collides (``mesh_graph``: at most the mesh's ``maxhullvert``, see
            :func:`load_mjcf`'s ``max_hull_vertices``), ``(nhull, 3)``; else its vertices.
        contact_pairs: explicit contact pairs ``(geom1, geom2)`` (``<contact><pair>``).
        pair_friction: ``(npair,)``, sliding friction of every explicit pair (its own
            ``friction``, which replaces the geoms').
        excluded_body_pairs: body pairs whose contacts are excluded (``<contact><exclude>``),
            as MuJoCo body ids.
        collision_pairs: every geom pair MuJoCo's collision detection may test, before any
            distance test: the explicit pairs first, then the pairs ``(g1, g2)``, ``g1 < g2``,
            that MuJoCo's filters keep (bodies not welded together, nor parent and child
            unless ``filterparent`` is disabled, not excluded, ``contype``/``conaffinity``
            compatible, not both planes, not already an explicit pair); none where the
            ``contact`` or ``constraint`` flag is disabled.
        actuator_names: name of every actuator (all are motors on one hinge or slide, or on
            one fixed tendon).
        actuator_dofs: the velocity index each actuator drives, ``-1`` for a motor on a
            tendon.
        actuator_tendons: the tendon each actuator drives, ``-1`` for a motor on a joint.
        servo_actuators: the actuators with a bias (position and velocity servos).
        tendon_names: name of every tendon.
        tendon_moments: ``(ntendon, nv)``, each fixed tendon's coefficients on the dofs of its
            joints (the derivative of its length in the velocities): a force ``f`` along tendon
            ``t`` is the generalized force ``f tendon_moments[t]``; zero rows for spatial tendons
            (their moments vary with the configuration:
            :meth:`~rsmooth.sim.RigidBodySystem.tendon_moments`).
        actuator_gear: ``(nu,)``, transmission ratio (generalized force per unit actuator force).
        actuator_gain: ``(nu,)``, actuator force per unit control (``gainprm[0]``).
        actuator_bias: ``(nu, 3)``, the affine bias ``(b0, b1, b2)`` of the force in the
            actuator's length and velocity (``biasprm[:3]``; zero for a motor): a position
            servo has ``(0, -kp, -kv)``, a velocity servo ``(0, 0, -kv)``.
        actuator_lengths: ``(nu, nq)``, the actuators' lengths' coefficients on MuJoCo's
            ``qpos`` (``actuator_length``: the gear times the joint's coordinate or the fixed
            tendon's length).
        actuator_moments: ``(nu, nv)``, their moment arms (``actuator_moment``: the gear times
            the joint's unit row or the tendon's moments).
        actuator_ctrl_range: ``(nu, 2)``, control range, ``[-inf, inf]`` where unlimited.
        actuator_force_range: ``(nu, 2)``, actuator force range, ``[-inf, inf]`` where
            unlimited.
        dof_actuator_force_range: ``(nv, 2)``, range of the total actuator force on each dof
            (``jnt_actfrcrange``), ``[-inf, inf]`` where unlimited.
        activation_dynamics: the actuators with a state (``dyntype`` integrator, filter or
            filterexact; :class:`~rsmooth.sim.ActivationDynamics`), ``None`` where none has one.
        qpos0: ``(nq,)``, MuJoCo's reference configuration on hinges and slides (zero
            elsewhere), subtracted from ``qpos`` to give ``q``.
        default_qpos: ``(nq,)``, MuJoCo's ``qpos0`` in full: the configuration the file
            describes, every free joint at its body's pose in the world.
        free_joint_qpos: ``qpos`` offset of every free joint.
        free_joint_qvel: ``qvel`` offset of every free joint.
        ball_joint_qpos: ``qpos`` offset of every ball joint.
    """

    model: Model
    damping: jax.Array
    frictionloss: jax.Array
    stiffness: jax.Array
    spring_reference: jax.Array
    joint_couplings: JointCoupling | None
    connections: PointConnection | None
    welds: Weld | None
    tendons: Tendons | None
    gravcomp: GravityCompensation | None
    fluid: Fluid | None
    timestep: float = eqx.field(static=True)
    limits_enforced: bool = eqx.field(static=True)
    body_names: tuple[str, ...] = eqx.field(static=True)
    body_parents: tuple[int, ...] = eqx.field(static=True)
    body_joints: tuple[int, ...] = eqx.field(static=True)
    geom_names: tuple[str, ...] = eqx.field(static=True)
    geom_types: tuple[str, ...] = eqx.field(static=True)
    geom_bodies: tuple[int, ...] = eqx.field(static=True)
    geom_joints: tuple[int, ...] = eqx.field(static=True)
    geom_size: jax.Array
    geom_rotation: jax.Array
    geom_translation: jax.Array
    geom_friction: jax.Array
    geom_contype: tuple[int, ...] = eqx.field(static=True)
    geom_conaffinity: tuple[int, ...] = eqx.field(static=True)
    geom_priority: tuple[int, ...] = eqx.field(static=True)
    geom_vertices: tuple[jax.Array | None, ...]
    geom_faces: tuple[jax.Array | None, ...]
    geom_hull: tuple[jax.Array | None, ...]
    geom_height_fields: tuple[Any, ...]
    contact_pairs: tuple[tuple[int, int], ...] = eqx.field(static=True)
    pair_friction: jax.Array
    excluded_body_pairs: tuple[tuple[int, int], ...] = eqx.field(static=True)
    collision_pairs: tuple[tuple[int, int], ...] = eqx.field(static=True)
    actuator_names: tuple[str, ...] = eqx.field(static=True)
    actuator_dofs: tuple[int, ...] = eqx.field(static=True)
    actuator_tendons: tuple[int, ...] = eqx.field(static=True)
    servo_actuators: tuple[int, ...] = eqx.field(static=True)
    tendon_names: tuple[str, ...] = eqx.field(static=True)
    tendon_moments: jax.Array
    actuator_gear: jax.Array
    actuator_gain: jax.Array
    actuator_bias: jax.Array
    actuator_lengths: jax.Array
    actuator_moments: jax.Array
    actuator_ctrl_range: jax.Array
    actuator_force_range: jax.Array
    dof_actuator_force_range: jax.Array
    qpos0: jax.Array
    default_qpos: jax.Array
    free_joint_qpos: tuple[int, ...] = eqx.field(static=True)
    free_joint_qvel: tuple[int, ...] = eqx.field(static=True)
    ball_joint_qpos: tuple[int, ...] = eqx.field(static=True, default=())
    activation_dynamics: ActivationDynamics | None = None

    @property
    def ngeom(self) -> int:
        """Number of geoms."""
        return len(self.geom_names)

    @property
    def nu(self) -> int:
        """Number of actuators (controls)."""
        return len(self.actuator_names)

    @property
    def na(self) -> int:
        """Number of actuator states (MuJoCo's ``na``)."""
        return 0 if self.activation_dynamics is None else self.activation_dynamics.na

    def _check(self, name: str, value: ArrayLike, size: int) -> jax.Array:
        value = jnp.asarray(value)
        if value.shape[-1:] != (size,):
            raise ValueError(f"{name} must have shape (..., {size}), got {value.shape}")
        return value

    def qpos_to_q(self, qpos: ArrayLike) -> jax.Array:
        """rsmooth's configuration from MuJoCo's ``qpos``.

        Free joints: ``[x, y, z, qw, qx, qy, qz]`` becomes ``[x, y, z, qx, qy, qz, qw]`` with the
        quaternion normalized (MuJoCo normalizes it before use; a zero quaternion is the
        identity, as in MuJoCo); ball joints: ``[qw, qx, qy, qz]`` becomes ``[qx, qy, qz, qw]``,
        normalized the same way. Hinges and slides: ``qpos - qpos0``.

        Args:
            qpos: shape ``(..., nq)``.

        Returns:
            ``q``, same shape.
        """
        qpos = self._check("qpos", qpos, self.model.nq)
        q = qpos - jnp.broadcast_to(self.qpos0, qpos.shape).astype(qpos.dtype)
        for adr in self.free_joint_qpos:
            quaternion = jnp.concatenate([qpos[..., adr + 4 : adr + 7], qpos[..., adr + 3 : adr + 4]], axis=-1)
            q = q.at[..., adr + 3 : adr + 7].set(_normalized_quaternion(quaternion))
        for adr in self.ball_joint_qpos:
            quaternion = jnp.concatenate([qpos[..., adr + 1 : adr + 4], qpos[..., adr : adr + 1]], axis=-1)
            q = q.at[..., adr : adr + 4].set(_normalized_quaternion(quaternion))
        return q

    def q_to_qpos(self, q: ArrayLike) -> jax.Array:
        """MuJoCo's ``qpos`` from rsmooth's configuration (the inverse of :meth:`qpos_to_q`
        for unit quaternions).

        Args:
            q: shape ``(..., nq)``.

        Returns:
            ``qpos``, same shape.
        """
        q = self._check("q", q, self.model.nq)
        qpos = q + jnp.broadcast_to(self.qpos0, q.shape).astype(q.dtype)
        for adr in self.free_joint_qpos:
            quaternion = jnp.concatenate([q[..., adr + 6 : adr + 7], q[..., adr + 3 : adr + 6]], axis=-1)
            qpos = qpos.at[..., adr + 3 : adr + 7].set(quaternion)
        for adr in self.ball_joint_qpos:
            qpos = qpos.at[..., adr : adr + 4].set(jnp.concatenate([q[..., adr + 3 : adr + 4], q[..., adr : adr + 3]], axis=-1))
        return qpos

    def qvel_to_v(self, qpos: ArrayLike, qvel: ArrayLike) -> jax.Array:
        """rsmooth's velocity from MuJoCo's ``(qpos, qvel)``: the linear velocity of every free
        joint is rotated from world axes into body axes (``v = T^T qvel`` where
        ``qvel = T v``, ``T = diag(R, I)`` on a free joint's block and the identity elsewhere).

        Generalized forces map the same way (:meth:`qfrc_to_tau`): ``T`` is orthogonal.

        Args:
            qpos: MuJoCo configuration, shape ``(..., nq)``.
            qvel: MuJoCo velocity, shape ``(..., nv)``.

        Returns:
            ``v``, shape ``(..., nv)``.
        """
        qpos = self._check("qpos", qpos, self.model.nq)
        qvel = self._check("qvel", qvel, self.model.nv)
        return self._rotate_free_linear(self.qpos_to_q(qpos), qvel, inverse=True)

    def v_to_qvel(self, q: ArrayLike, v: ArrayLike) -> jax.Array:
        """MuJoCo's ``qvel`` from rsmooth's ``(q, v)`` (``qvel = T v``, see :meth:`qvel_to_v`).

        Args:
            q: rsmooth configuration, shape ``(..., nq)``.
            v: rsmooth velocity, shape ``(..., nv)``.

        Returns:
            ``qvel``, shape ``(..., nv)``.
        """
        q = self._check("q", q, self.model.nq)
        v = self._check("v", v, self.model.nv)
        return self._rotate_free_linear(q, v, inverse=False)

    def qfrc_to_tau(self, qpos: ArrayLike, qfrc: ArrayLike) -> jax.Array:
        """rsmooth's generalized force from a MuJoCo one (``qfrc_bias``, ``qfrc_actuator``...):
        ``tau = T^T qfrc``, which keeps the power ``tau . v = qfrc . qvel``.

        Args:
            qpos: MuJoCo configuration, shape ``(..., nq)``.
            qfrc: MuJoCo generalized force, shape ``(..., nv)``.

        Returns:
            ``tau``, shape ``(..., nv)``.
        """
        return self.qvel_to_v(qpos, qfrc)

    def tau_to_qfrc(self, q: ArrayLike, tau: ArrayLike) -> jax.Array:
        """MuJoCo's generalized force from rsmooth's ``tau`` (``qfrc = T tau``).

        Args:
            q: rsmooth configuration, shape ``(..., nq)``.
            tau: rsmooth generalized force, shape ``(..., nv)``.

        Returns:
            ``qfrc``, shape ``(..., nv)``.
        """
        return self.v_to_qvel(q, tau)

    def qacc_to_a(self, qpos: ArrayLike, qvel: ArrayLike, qacc: ArrayLike) -> jax.Array:
        """rsmooth's acceleration from MuJoCo's ``qacc``.

        ``qvel = T(q) v`` with a ``T`` that turns with the body, so ``qacc = T a + (dT/dt) v``:
        on a free joint, ``a_linear = R^T qacc_linear - omega x v_linear`` (body axes). The
        same term makes rsmooth's bias ``C(q, v) v + g(q)`` equal to ``T^T (qfrc_bias + M
        (dT/dt) v)``, not ``T^T qfrc_bias``.

        Args:
            qpos: MuJoCo configuration, shape ``(..., nq)``.
            qvel: MuJoCo velocity, shape ``(..., nv)``.
            qacc: MuJoCo acceleration, shape ``(..., nv)``.

        Returns:
            ``a``, shape ``(..., nv)``.
        """
        qacc = self._check("qacc", qacc, self.model.nv)
        v = self.qvel_to_v(qpos, qvel)
        return self._add_transport(v, self.qvel_to_v(qpos, qacc), sign=-1.0)

    def a_to_qacc(self, q: ArrayLike, v: ArrayLike, a: ArrayLike) -> jax.Array:
        """MuJoCo's ``qacc`` from rsmooth's ``(q, v, a)`` (the inverse of :meth:`qacc_to_a`).

        Args:
            q: rsmooth configuration, shape ``(..., nq)``.
            v: rsmooth velocity, shape ``(..., nv)``.
            a: rsmooth acceleration, shape ``(..., nv)``.

        Returns:
            ``qacc``, shape ``(..., nv)``.
        """
        v = self._check("v", v, self.model.nv)
        a = self._check("a", a, self.model.nv)
        return self.v_to_qvel(q, self._add_transport(v, a, sign=1.0))

    def _add_transport(self, v: jax.Array, a: jax.Array, *, sign: float) -> jax.Array:
        for adr in self.free_joint_qvel:
            linear, angular = v[..., adr : adr + 3], v[..., adr + 3 : adr + 6]
            a = a.at[..., adr : adr + 3].add(sign * jnp.cross(angular, linear))
        return a

    def _rotate_free_linear(self, q: jax.Array, velocity: jax.Array, *, inverse: bool) -> jax.Array:
        for adr_q, adr_v in zip(self.free_joint_qpos, self.free_joint_qvel):
            rotation = jnp.vectorize(spatial.quaternion_to_rotation, signature="(4)->(3,3)")(q[..., adr_q + 3 : adr_q + 7])
            if inverse:
                rotation = jnp.swapaxes(rotation, -1, -2)
            linear = jnp.einsum("...ij,...j->...i", rotation, velocity[..., adr_v : adr_v + 3])
            velocity = velocity.at[..., adr_v : adr_v + 3].set(linear)
        return velocity

    def ctrl_to_tau(self, ctrl: ArrayLike, qpos: ArrayLike | None = None, qvel: ArrayLike | None = None,
                    act: ArrayLike | None = None) -> jax.Array:
        """Generalized force of the actuators, as MuJoCo computes ``qfrc_actuator``: the control
        clipped to its range (or the actuator's state ``act``, or its next state where
        ``actearly``, for actuators with activation dynamics), times the gain, plus the bias in the actuator's length and
        velocity at ``(qpos, qvel)`` (servos), clipped to the force range, along the
        actuator's moment arms (its gear times its joint's dof or its tendon's moments), summed
        per dof and clipped to the dof's actuator force range.

        The force is the same in rsmooth's and MuJoCo's bases: actuators drive hinges and slides
        only (directly or through fixed tendons), whose velocities coincide.

        Args:
            ctrl: shape ``(..., nu)``.
            qpos: MuJoCo's configuration ``(..., nq)``; needed where an actuator has a bias.
            qvel: MuJoCo's velocity ``(..., nv)``; likewise.
            act: MuJoCo's actuator states ``(..., na)``; needed where an actuator has activation
                dynamics.

        Returns:
            ``tau``, shape ``(..., nv)``.

        Raises:
            ValueError: if an actuator has a bias and ``qpos`` or ``qvel`` is missing, or
                activation dynamics and ``act`` is missing.
        """
        ctrl = self._check("ctrl", ctrl, self.nu)
        def like(values, target):  # explicit broadcasting over the batch dimensions
            return jnp.broadcast_to(values, target.shape)

        ctrl = jnp.clip(ctrl, like(self.actuator_ctrl_range[:, 0], ctrl), like(self.actuator_ctrl_range[:, 1], ctrl))
        if self.activation_dynamics is not None:
            if act is None:
                raise ValueError("ctrl_to_tau: the model's actuators have activation dynamics, whose force needs act")
            act = self._check("act", act, self.na)
            inputs = jax.vmap(lambda a, c: self.activation_dynamics.inputs(a, c, jnp.asarray(self.timestep, c.dtype)))
            shape = ctrl.shape
            act = jnp.broadcast_to(act, shape[:-1] + act.shape[-1:]).reshape(-1, self.na)
            ctrl = inputs(act, ctrl.reshape(-1, self.nu)).reshape(shape)
        force = like(self.actuator_gain, ctrl) * ctrl
        if self.servo_actuators:
            if qpos is None or qvel is None:
                raise ValueError("ctrl_to_tau: the model has servos (an actuator bias), whose force needs qpos and qvel")
            qpos, qvel = self._check("qpos", qpos, self.model.nq), self._check("qvel", qvel, self.model.nv)
            length = jnp.tensordot(qpos, self.actuator_lengths.T.astype(qpos.dtype), axes=1)
            velocity = jnp.tensordot(qvel, self.actuator_moments.T.astype(qvel.dtype), axes=1)
            bias = self.actuator_bias
            force = force + like(bias[:, 0], force) + like(bias[:, 1], force) * length + like(bias[:, 2], force) * velocity
        force = jnp.clip(force, like(self.actuator_force_range[:, 0], force), like(self.actuator_force_range[:, 1], force))
        tau = jnp.tensordot(force, self.actuator_moments.astype(force.dtype), axes=1)
        return jnp.clip(tau, like(self.dof_actuator_force_range[:, 0], tau), like(self.dof_actuator_force_range[:, 1], tau))


def _normalized_quaternion(quaternion: jax.Array) -> jax.Array:
    squared = jnp.sum(quaternion * quaternion, axis=-1, keepdims=True)
    tiny = squared < 1e-28
    identity = jnp.zeros_like(quaternion).at[..., 3].set(1.0)
    return jnp.where(tiny, identity, quaternion / jnp.sqrt(jnp.where(tiny, 1.0, squared)))


# --------------------------------------------------------------------------------------
# Host-side conversion
# --------------------------------------------------------------------------------------


def _names(mj_model: Any, kind: str, count: int) -> tuple[str, ...]:
    accessor = getattr(mj_model, kind)
    return tuple(accessor(i).name or f"{kind} {i}" for i in range(count))


def _quaternion_to_matrix(quaternion_wxyz: np.ndarray) -> np.ndarray:
    w, x, y, z = np.asarray(quaternion_wxyz, dtype=np.float64) / np.linalg.norm(quaternion_wxyz)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _compose(first: tuple[np.ndarray, np.ndarray], second: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    return first[0] @ second[0], first[0] @ second[1] + first[1]


def _pose(position: np.ndarray, quaternion_wxyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return _quaternion_to_matrix(quaternion_wxyz), np.asarray(position, dtype=np.float64)


_IDENTITY = (np.eye(3), np.zeros(3))


def _disabled(mj: Any, m: Any, *flags: str) -> bool:
    """Whether ``opt.disableflags`` disables any of ``flags`` (``"CONTACT"``: ``mjDSBL_CONTACT``...)."""
    return any(m.opt.disableflags & int(getattr(mj.mjtDisableBit, f"mjDSBL_{flag}")) for flag in flags)


def _reject_unsupported(mj: Any, m: Any) -> None:
    """Raises a ValueError naming the first element rsmooth cannot model faithfully."""
    joint_names = _names(m, "joint", m.njnt)
    body_names = _names(m, "body", m.nbody)
    for j in range(m.njnt):
        if int(m.jnt_type[j]) == int(mj.mjtJoint.mjJNT_BALL) and m.jnt_limited[j] and not 0 < m.jnt_range[j][1] <= np.pi:
            raise ValueError(
                f"MuJoCo model: ball joint {joint_names[j]!r} has the range {m.jnt_range[j].tolist()} (rad); its "
                "second value, the largest rotation angle, must be in (0, pi]"
            )
        if np.any(m.jnt_stiffnesspoly[j] != 0):
            raise ValueError(
                f"MuJoCo model: joint {joint_names[j]!r} has a nonlinear spring (stiffnesspoly); rsmooth.sim supports "
                "linear springs (stiffness) only"
            )
        if m.jnt_stiffness[j] != 0 and int(m.jnt_type[j]) == int(mj.mjtJoint.mjJNT_FREE):
            raise ValueError(
                f"MuJoCo model: free joint {joint_names[j]!r} has a spring (stiffness {m.jnt_stiffness[j]:g}), which "
                "rsmooth.sim does not model (supported: springs on hinge, slide and ball joints)"
            )
    for d in range(m.nv):
        joint = joint_names[m.dof_jntid[d]]
        if np.any(m.dof_dampingpoly[d] != 0):
            raise ValueError(
                f"MuJoCo model: joint {joint!r} has nonlinear damping (dampingpoly); rsmooth.sim supports linear "
                "damping only"
            )
    counts = [
        ("neq", "equality constraints other than joint couplings, connections and welds (distance, flex)",
         mj.mjtObj.mjOBJ_EQUALITY),
        ("nflex", "flexible bodies (flex)", mj.mjtObj.mjOBJ_FLEX),
        ("nplugin", "plugins", mj.mjtObj.mjOBJ_PLUGIN),
    ]
    # equality constraints MuJoCo does not enforce (the equality or constraint flag disabled) are left alone
    equalities_off = _disabled(mj, m, "EQUALITY", "CONSTRAINT")
    converted = (int(mj.mjtEq.mjEQ_JOINT), int(mj.mjtEq.mjEQ_TENDON), int(mj.mjtEq.mjEQ_CONNECT), int(mj.mjtEq.mjEQ_WELD))
    others = [] if equalities_off else [e for e in range(m.neq) if int(m.eq_type[e]) not in converted]
    for attribute, what, kind in counts:
        count = len(others) if attribute == "neq" else getattr(m, attribute)
        if count > 0:
            first = mj.mj_id2name(m, kind, others[0] if attribute == "neq" else 0)
            named = f" (the first is {first!r})" if first else ""
            raise ValueError(f"MuJoCo model has {count} {what}{named}, which rsmooth.sim does not support")
    if m.nskin:
        # A skin is a mesh MuJoCo's renderer deforms with the bodies it is bound to: no mass, no
        # collision, nothing in the dynamics. rsmooth's animations draw the geoms instead.
        skins = [mj.mj_id2name(m, mj.mjtObj.mjOBJ_SKIN, k) or f"#{k}" for k in range(m.nskin)]
        warnings.warn(
            f"MuJoCo model: skins {skins} are left out (visual only: they do not act in the physics, and rsmooth's "
            "renderer draws the geoms instead)", MujocoLoadWarning, stacklevel=3,
        )
    mocap = [body_names[b] for b in range(m.nbody) if m.body_mocapid[b] >= 0]
    if mocap:
        # A mocap body moves only where a program writes its pose into MuJoCo's data; rsmooth's
        # state has no such input, so the body stays where the model places it.
        warnings.warn(
            f"MuJoCo model: mocap bodies {mocap} are held fixed at their poses in the model (rsmooth.sim has no "
            "mocap data to move them)", MujocoLoadWarning, stacklevel=3,
        )
    for j in range(m.njnt):
        if m.jnt_actgravcomp[j] and np.any(m.body_gravcomp != 0):
            raise ValueError(
                f"MuJoCo model: joint {joint_names[j]!r} takes its gravity compensation through its actuators "
                "(actuatorgravcomp), which rsmooth.sim does not model (supported: gravity compensation as a passive force)"
            )
    if m.opt.density != 0 or m.opt.viscosity != 0:
        for g in range(m.ngeom):
            if m.geom_fluid[g, 0] != 0:
                raise ValueError(
                    f"MuJoCo model: geom {_names(m, 'geom', m.ngeom)[g]!r} takes the ellipsoid fluid model (fluidshape), which "
                    "rsmooth.sim does not model (supported: the inertia-box fluid model, fluidshape none)"
                )
    if _disabled(mj, m, "ACTUATION") and m.nu:
        raise ValueError(
            "MuJoCo model: its actuators are disabled (the actuation flag), which rsmooth.sim does not model "
            "(supported: enabled actuators, or none)"
        )
    geom_names = _names(m, "geom", m.ngeom)
    paired = set(int(g) for g in m.pair_geom1) | set(int(g) for g in m.pair_geom2)
    contacts_off = _disabled(mj, m, "CONTACT", "CONSTRAINT")
    for g in range(m.ngeom if not contacts_off else 0):  # nothing collides where contacts are disabled
        kind = mj.mjtGeom(m.geom_type[g]).name.removeprefix("mjGEOM_").lower()
        collides = m.geom_contype[g] != 0 or m.geom_conaffinity[g] != 0 or g in paired
        if kind not in GEOM_TYPES and collides:
            raise ValueError(
                f"MuJoCo model: geom {geom_names[g]!r} is a colliding {kind}, which rsmooth.sim does not support "
                f"(converted: {', '.join(GEOM_TYPES)}; a {kind} with contype = conaffinity = 0 is kept as visual)"
            )
    _check_tendons(mj, m)
    _check_actuators(mj, m, joint_names)


def _check_tendons(mj: Any, m: Any) -> None:
    """Refuses what rsmooth does not model of tendons (see the module's description); tendon
    equalities are checked where they are converted (:func:`_tendon_couplings`), motors on
    spatial tendons here."""
    names = _names(m, "tendon", m.ntendon)
    supported = (
        "supported: fixed tendons and spatial tendons through sites (wrapping around spheres and cylinders, with "
        "pulleys), with linear springs, dampers, dry friction and length limits, equalities of one tendon; motors on fixed ones"
    )
    driven = {int(m.actuator_trnid[a, 0]) for a in range(m.nu) if int(m.actuator_trntype[a]) == int(mj.mjtTrn.mjTRN_TENDON)}
    for t in range(m.ntendon):
        problem = None
        inside = [w for w in _wraps(mj, m, t) if _side_inside(mj, m, w)]
        if inside:
            w = inside[0]
            problem = (
                f"the side site {_names(m, 'site', m.nsite)[int(m.wrap_prm[w])]!r} of its wrap around geom "
                f"{_names(m, 'geom', m.ngeom)[int(m.wrap_objid[w])]!r} is inside the geom (MuJoCo's wrapping through it)"
            )
        elif _is_spatial(mj, m, t) and t in driven:
            problem = "it is a spatial tendon driven by a motor (its moment arms vary with the configuration)"
        elif np.any(m.tendon_stiffnesspoly[t] != 0):
            problem = "it has a nonlinear spring (stiffnesspoly)"
        elif np.any(m.tendon_dampingpoly[t] != 0):
            problem = "it has nonlinear damping (dampingpoly)"
        elif m.tendon_armature[t] != 0:
            problem = f"it has armature ({m.tendon_armature[t]:g})"
        elif m.tendon_actfrclimited[t]:
            problem = f"it bounds its actuators' total force (actuatorfrcrange {m.tendon_actfrcrange[t].tolist()})"
        if problem is not None:
            raise ValueError(f"MuJoCo model: tendon {names[t]!r} is not supported: {problem} ({supported})")


def _wraps_of(m: Any, t: int, types) -> list[int]:
    """The wraps (indices into MuJoCo's ``wrap_*``) of tendon ``t`` whose type is one of ``types``."""
    types = {int(kind) for kind in types}
    return [w for w in range(m.tendon_adr[t], m.tendon_adr[t] + m.tendon_num[t]) if int(m.wrap_type[w]) in types]


def _wraps(mj: Any, m: Any, t: int) -> list[int]:
    """The wraps of tendon ``t`` around a sphere or a cylinder."""
    return _wraps_of(m, t, (mj.mjtWrap.mjWRAP_SPHERE, mj.mjtWrap.mjWRAP_CYLINDER))


def _side_inside(mj: Any, m: Any, w: int) -> bool:
    """Whether wrap ``w``'s side site is inside its geom at ``qpos0`` (MuJoCo's test: its
    distance to the geom's centre below the radius, for a cylinder too)."""
    if m.wrap_prm[w] < 0:
        return False
    d = mj.MjData(m)
    mj.mj_kinematics(m, d)
    g, site = int(m.wrap_objid[w]), int(m.wrap_prm[w])
    return bool(np.linalg.norm(d.site_xpos[site] - d.geom_xpos[g]) < m.geom_size[g, 0])


def _is_spatial(mj: Any, m: Any, t: int) -> bool:
    """Whether tendon ``t`` is spatial (its path goes through sites), not fixed."""
    return any(int(m.wrap_type[w]) != int(mj.mjtWrap.mjWRAP_JOINT) for w in range(m.tendon_adr[t], m.tendon_adr[t] + m.tendon_num[t]))


def _tendon_moments(m: Any, positions: bool = False) -> np.ndarray:
    """``(ntendon, nv)``: the fixed tendons' coefficients on the dofs of their joints, the
    derivative of each length ``sum_i c_i qpos_i`` (MuJoCo's ``ten_J``, constant); with
    ``positions``, ``(ntendon, nq)``, the coefficients on ``qpos``. Zero rows for spatial
    tendons."""
    mj = _mujoco()
    address = m.jnt_qposadr if positions else m.jnt_dofadr
    moments = np.zeros((m.ntendon, m.nq if positions else m.nv))
    for t in range(m.ntendon):
        if _is_spatial(mj, m, t):
            continue
        for w in range(m.tendon_adr[t], m.tendon_adr[t] + m.tendon_num[t]):
            moments[t, address[m.wrap_objid[w]]] += m.wrap_prm[w]
    return moments


def _sites(mj: Any, m: Any, t: int) -> list[int]:
    """The wraps of spatial tendon ``t`` that are sites."""
    return _wraps_of(m, t, (mj.mjtWrap.mjWRAP_SITE,))


def _pulleys(mj: Any, m: Any, t: int) -> list[int]:
    """The wraps of spatial tendon ``t`` that are pulleys."""
    return _wraps_of(m, t, (mj.mjtWrap.mjWRAP_PULLEY,))


def _wrap_shapes() -> dict[int, str]:
    mj = _mujoco()
    return {int(mj.mjtWrap.mjWRAP_SPHERE): "sphere", int(mj.mjtWrap.mjWRAP_CYLINDER): "cylinder"}


def _tendons(mj: Any, m: Any) -> Tendons | None:
    """The springs, dampers, dry friction and length limits of the tendons (``None`` where none
    has any, or they are disabled): lengths in rsmooth's coordinates (MuJoCo's ``qpos`` less
    ``qpos0`` on hinges and slides), so ``L = lengths q + offsets`` is MuJoCo's ``ten_length``
    for a fixed tendon; a spatial tendon's path goes through its sites' frames and wraps around
    its spheres and cylinders (fixed in their bodies' frames, :attr:`Tendons.wraps`); its pulleys
    divide the branches after them (:attr:`Tendons.pulleys`). A spatial
    tendon's lower limit at or below 0 is left out (its length cannot go below it). An active
    equality of one spatial tendon, or of one fixed tendon on three or more joints, holds it at
    ``L0 + c_0`` (MuJoCo's ``L - L0 = c_0``, ``L0`` its length at ``qpos0``); of a fixed tendon
    on one or two joints it is a joint coupling instead (:func:`_tendon_couplings`)."""
    stiffness = np.zeros(m.ntendon) if _disabled(mj, m, "SPRING") else np.asarray(m.tendon_stiffness, dtype=np.float64)
    damping = np.zeros(m.ntendon) if _disabled(mj, m, "DAMPER") else np.asarray(m.tendon_damping, dtype=np.float64)
    friction_off = _disabled(mj, m, "FRICTIONLOSS", "CONSTRAINT")
    frictionloss = np.zeros(m.ntendon) if friction_off else np.asarray(m.tendon_frictionloss, dtype=np.float64)
    limits = []
    if not _disabled(mj, m, "LIMIT", "CONSTRAINT"):
        for t in np.flatnonzero(m.tendon_limited):
            lower, upper = m.tendon_range[t]
            if not (_is_spatial(mj, m, t) and lower <= 0):
                limits.append((int(t), 1))
            limits.append((int(t), -1))
    held = {} if _disabled(mj, m, "EQUALITY", "CONSTRAINT") else {
        int(m.eq_obj1id[e]): float(m.tendon_length0[m.eq_obj1id[e]] + m.eq_data[e, 0])
        for e, as_row in _tendon_equalities(mj, m) if as_row and m.eq_obj2id[e] < 0
    }
    if not (np.any(stiffness != 0) or np.any(damping != 0) or np.any(frictionloss != 0) or limits or held):
        return None
    lengths = _tendon_moments(m, positions=True)
    spatial = [t for t in range(m.ntendon) if _is_spatial(mj, m, t)]
    first_site = m.nbody + m.njnt  # frames: bodies, joints, then sites (from_mujoco); body b is frame b
    geoms = [int(m.wrap_objid[w]) for t in spatial for w in _wraps(mj, m, t)]
    pulleys = [w for t in spatial for w in _pulleys(mj, m, t)]
    return Tendons(
        lengths=_array(lengths),
        moments=_array(_tendon_moments(m)).reshape(m.ntendon, m.nv),
        offsets=_array(lengths @ np.asarray(m.qpos0, dtype=np.float64)),
        stiffness=_array(stiffness),
        spring_length=_array(m.tendon_lengthspring).reshape(m.ntendon, 2),
        damping=_array(damping),
        frictionloss=_array(frictionloss),
        frictional=tuple(int(t) for t in np.flatnonzero(frictionloss)),
        range=_array(m.tendon_range).reshape(m.ntendon, 2) if limits else None,
        limits=tuple(limits),
        spatial=tuple(spatial),
        paths=tuple(tuple(first_site + int(m.wrap_objid[w]) for w in _sites(mj, m, t)) for t in spatial),
        wraps=tuple(
            (k, _sites(mj, m, t).index(w - 1), int(m.geom_bodyid[m.wrap_objid[w]]), _wrap_shapes()[int(m.wrap_type[w])],
             None if m.wrap_prm[w] < 0 else first_site + int(m.wrap_prm[w]))
            for k, t in enumerate(spatial) for w in _wraps(mj, m, t)
        ),
        wrap_rotations=_array([_quaternion_to_matrix(m.geom_quat[g]) for g in geoms]).reshape(-1, 3, 3) if geoms else None,
        wrap_offsets=_array(np.asarray(m.geom_pos, dtype=np.float64)[geoms]).reshape(-1, 3) if geoms else None,
        wrap_radii=_array(np.asarray(m.geom_size, dtype=np.float64)[geoms, 0]) if geoms else None,
        pulleys=tuple((k, _sites(mj, m, t).index(w - 1)) for k, t in enumerate(spatial) for w in _pulleys(mj, m, t)),
        pulley_divisors=_array([m.wrap_prm[w] for t in spatial for w in _pulleys(mj, m, t)]) if pulleys else None,
        equalities=tuple(sorted(held)),
        equality_length=_array([held.get(t, 0.0) for t in range(m.ntendon)]) if held else None,
    )


def _height_field(mj: Any, m: Any, g: int) -> HeightField | None:
    """Geom ``g``'s height field (MuJoCo's normalized ``hfield_data``, rows from ``-y`` to ``+y``,
    times its elevation), ``None`` for another type."""
    if int(m.geom_type[g]) != int(mj.mjtGeom.mjGEOM_HFIELD):
        return None
    h = int(m.geom_dataid[g])
    rows, columns = int(m.hfield_nrow[h]), int(m.hfield_ncol[h])
    start = int(m.hfield_adr[h])
    data = np.asarray(m.hfield_data[start : start + rows * columns], dtype=np.float64).reshape(rows, columns)
    size = np.asarray(m.hfield_size[h], dtype=np.float64)
    return HeightField(_array(data * size[2]), _array(size[:2]), _array(size[3]))


def _gravcomp(mj: Any, m: Any) -> GravityCompensation | None:
    """The bodies' gravity compensation (``None`` without any, or with gravity disabled): each
    compensated body's centre of mass in its frame (frames: bodies first, by id) and ``gravcomp``
    times its mass."""
    bodies = [b for b in range(1, m.nbody) if m.body_gravcomp[b] != 0]
    if not bodies or _disabled(mj, m, "GRAVITY"):
        return None
    return GravityCompensation(
        frames=tuple(bodies),
        offsets=_array(np.asarray(m.body_ipos, dtype=np.float64)[bodies]).reshape(len(bodies), 3),
        masses=_array(np.asarray(m.body_gravcomp, dtype=np.float64)[bodies] * np.asarray(m.body_mass, dtype=np.float64)[bodies]),
    )


def _fluid(m: Any) -> Fluid | None:
    """MuJoCo's inertia-box fluid model (``None`` without density and viscosity): every body of
    positive mass, its inertial frame placed in its frame (frames: bodies first, by id)."""
    if m.opt.density == 0 and m.opt.viscosity == 0:
        return None
    bodies = [b for b in range(1, m.nbody) if m.body_mass[b] >= 1e-15]  # MuJoCo's mjMINVAL
    inertia = np.asarray(m.body_inertia, dtype=np.float64)[bodies]
    mass = np.asarray(m.body_mass, dtype=np.float64)[bodies, None]
    # the equivalent inertia box's sides, as MuJoCo computes them
    spans = np.stack([inertia[:, 1] + inertia[:, 2] - inertia[:, 0], inertia[:, 0] + inertia[:, 2] - inertia[:, 1],
                      inertia[:, 0] + inertia[:, 1] - inertia[:, 2]], axis=1)
    box = np.sqrt(np.maximum(1e-15, spans) / mass * 6.0)
    return Fluid(
        frames=tuple(bodies),
        rotations=_array(np.stack([_pose(np.zeros(3), m.body_iquat[b])[0] for b in bodies]).reshape(len(bodies), 3, 3)),
        offsets=_array(np.asarray(m.body_ipos, dtype=np.float64)[bodies]).reshape(len(bodies), 3),
        box=_array(box).reshape(len(bodies), 3),
        density=_array(float(m.opt.density)),
        viscosity=_array(float(m.opt.viscosity)),
        wind=_array(np.asarray(m.opt.wind, dtype=np.float64)),
    )


def _dynamics_kinds(mj: Any) -> dict[int, str | None]:
    """MuJoCo's ``dyntype`` values that rsmooth models: none, and :class:`ActivationDynamics`' kinds."""
    return {int(getattr(mj.mjtDyn, f"mjDYN_{kind.upper()}")): kind for kind in ("integrator", "filter", "filterexact")} | {
        int(mj.mjtDyn.mjDYN_NONE): None
    }


def _activation_dynamics(mj: Any, m: Any) -> ActivationDynamics | None:
    """The actuators with a state (checked by :func:`_check_actuators`), in MuJoCo's order of ``act``."""
    kinds = _dynamics_kinds(mj)
    actuators = [a for a in range(m.nu) if kinds[int(m.actuator_dyntype[a])] is not None]
    if not actuators:
        return None
    if [int(m.actuator_actadr[a]) for a in actuators] != list(range(len(actuators))):  # pragma: no cover - MuJoCo's layout
        raise ValueError(f"MuJoCo model: unexpected actuator state addresses {np.asarray(m.actuator_actadr)}")
    act_range = np.asarray(m.actuator_actrange, dtype=np.float64)[actuators].reshape(-1, 2).copy()
    act_range[~np.asarray(m.actuator_actlimited, dtype=bool)[actuators]] = (-np.inf, np.inf)
    return ActivationDynamics(
        actuators=tuple(actuators),
        kinds=tuple(kinds[int(m.actuator_dyntype[a])] for a in actuators),
        early=tuple(bool(m.actuator_actearly[a]) for a in actuators),
        # MuJoCo's time constant is at least mjMINVAL (an integrator's is not read)
        time_constant=_array(np.maximum(np.asarray(m.actuator_dynprm[actuators, 0], dtype=np.float64), 1e-15)),
        act_range=_array(act_range).reshape(-1, 2),
    )


def _check_actuators(mj: Any, m: Any, joint_names: tuple[str, ...]) -> None:
    names = _names(m, "actuator", m.nu)
    supported = (
        "supported: motors, position and velocity servos (<motor>, <position>, <velocity>, or <general> with gaintype "
        "fixed, biastype none or affine, dyntype none, integrator, filter or filterexact) driving one hinge or slide "
        "joint or a fixed tendon"
    )
    dynamics = _dynamics_kinds(mj)
    for a in range(m.nu):
        problem = None
        trntype = int(m.actuator_trntype[a])
        if trntype not in (int(mj.mjtTrn.mjTRN_JOINT), int(mj.mjtTrn.mjTRN_JOINTINPARENT), int(mj.mjtTrn.mjTRN_TENDON)):
            problem = f"its transmission is {mj.mjtTrn(trntype).name.removeprefix('mjTRN_').lower()}"
        elif trntype != int(mj.mjtTrn.mjTRN_TENDON) and int(m.jnt_type[m.actuator_trnid[a, 0]]) not in (
            int(mj.mjtJoint.mjJNT_HINGE), int(mj.mjtJoint.mjJNT_SLIDE)
        ):  # (a tendon is fixed: _check_tendons)
            problem = f"it drives joint {joint_names[m.actuator_trnid[a, 0]]!r}, which is not a hinge or slide"
        elif int(m.actuator_biastype[a]) not in (int(mj.mjtBias.mjBIAS_NONE), int(mj.mjtBias.mjBIAS_AFFINE)):
            problem = f"its bias type is {mj.mjtBias(m.actuator_biastype[a]).name.removeprefix('mjBIAS_').lower()}"
        elif int(m.actuator_gaintype[a]) != int(mj.mjtGain.mjGAIN_FIXED):
            problem = f"its gain type is {mj.mjtGain(m.actuator_gaintype[a]).name.removeprefix('mjGAIN_').lower()}"
        elif int(m.actuator_dyntype[a]) not in dynamics:
            problem = f"it has activation dynamics {mj.mjtDyn(m.actuator_dyntype[a]).name.removeprefix('mjDYN_').lower()}"
        elif int(m.actuator_dyntype[a]) != int(mj.mjtDyn.mjDYN_NONE) and int(m.actuator_actnum[a]) != 1:
            problem = f"it has {int(m.actuator_actnum[a])} activation states"
        elif m.actuator_damping[a] != 0 or m.actuator_armature[a] != 0 or np.any(m.actuator_dampingpoly[a] != 0):
            problem = "it has actuator damping or armature"
        elif m.actuator_delay[a] != 0 or m.actuator_plugin[a] >= 0:
            problem = "it has a delay or a plugin"
        if problem is not None:
            raise ValueError(f"MuJoCo model: actuator {names[a]!r} is not supported: {problem} ({supported})")


def _merge_inertias(parts: list[tuple[float, np.ndarray, np.ndarray]]) -> tuple[float, np.ndarray, np.ndarray]:
    """Mass, centre of mass and rotational inertia about it of rigid parts given as
    ``(mass, com, inertia about com)`` in one frame (parallel-axis theorem)."""
    mass = sum(p[0] for p in parts)
    if mass <= 0:
        return 0.0, np.zeros(3), sum((p[2] for p in parts), np.zeros((3, 3)))
    com = sum(p[0] * p[1] for p in parts) / mass

    def shifted(m, c, inertia):
        offset = c - com
        return inertia + m * (offset @ offset * np.eye(3) - np.outer(offset, offset))

    return mass, com, sum(shifted(*p) for p in parts)


def from_mujoco(mj_model: Any) -> MujocoModel:
    """Converts a compiled MuJoCo model into a :class:`MujocoModel`.

    Args:
        mj_model: a ``mujoco.MjModel``.

    Returns:
        The converted model (see the module's description for the mapping).

    Raises:
        ValueError: if the model uses a feature that rsmooth.sim does not model (the message
            names the element and what is supported): a ball joint's range beyond pi, a free joint's
            spring, nonlinear springs (``stiffnesspoly``),
            frictionloss on a free joint's linear axes, nonlinear damping, a spatial tendon
            whose wrap's side site is inside its geom (at ``qpos0``; MuJoCo then wraps through
            the geom), a tendon's nonlinear spring or damping or
            armature, equality constraints
            other than joint couplings, equalities of one tendon,
            connections and welds,
            flex, plugins, gravity compensation through actuators, the ellipsoid fluid model, a height
            field colliding with a plane or another height field, SDFs, actuators other than motors and servos (a fixed gain, an
            affine bias, activation dynamics none, integrator, filter or filterexact) on a
            hinge, a slide or a fixed tendon, and on a free
            joint's linear axes an armature (MuJoCo applies it to the world-axes acceleration)
            or a damping that differs between the three axes (it would not be diagonal in body
            axes).

    Warns:
        MujocoLoadWarning: for mocap bodies, which are held fixed at their poses in the model,
            and for skins, which are left out (visual only).
    """
    mj = _mujoco()
    if not isinstance(mj_model, mj.MjModel):
        raise ValueError(f"mj_model must be a mujoco.MjModel, got {type(mj_model).__name__}")
    m = mj_model
    _reject_unsupported(mj, m)
    free, hinge, slide = (int(mj.mjtJoint.mjJNT_FREE), int(mj.mjtJoint.mjJNT_HINGE), int(mj.mjtJoint.mjJNT_SLIDE))
    ball = int(mj.mjtJoint.mjJNT_BALL)
    body_names = _names(m, "body", m.nbody)
    joint_names = _names(m, "joint", m.njnt)
    site_names = _names(m, "site", m.nsite)
    geom_names = _names(m, "geom", m.ngeom)

    # rsmooth joint j + 1 is MuJoCo joint j; MuJoCo numbers bodies parent first and joints
    # body by body, so parents precede children as rsmooth requires.
    njoints = m.njnt + 1
    parents = [0] * njoints
    placements = [_IDENTITY] * njoints
    types = [UNIVERSE] + [""] * m.njnt
    axes = np.zeros((njoints, 3))
    body_joint = [0] * m.nbody
    body_in_joint = [_IDENTITY] * m.nbody  # placement of each body frame in its joint's frame
    for b in range(1, m.nbody):
        parent = m.body_parentid[b]
        frame = _compose(body_in_joint[parent], _pose(m.body_pos[b], m.body_quat[b]))
        joint = body_joint[parent]
        anchor = np.zeros(3)
        for j in range(m.body_jntadr[b], m.body_jntadr[b] + m.body_jntnum[b]):
            kind = int(m.jnt_type[j])
            if kind == free:
                # The free joint's qpos is the body's world pose (MuJoCo allows it on bodies
                # whose parent is the world only), whatever body_pos and jnt_pos say.
                placement, anchor = _IDENTITY, np.zeros(3)
            else:
                # The joint frame is the body frame (as moved by the joints before it) shifted
                # to jnt_pos, where MuJoCo anchors the hinge's rotation.
                new_anchor = np.asarray(m.jnt_pos[j], dtype=np.float64)
                placement = _compose(frame, (np.eye(3), new_anchor - anchor))
                anchor = new_anchor
                axes[j + 1] = m.jnt_axis[j]
            types[j + 1] = {free: FREE_FLYER, ball: SPHERICAL, hinge: REVOLUTE, slide: PRISMATIC}[kind]
            parents[j + 1] = joint
            placements[j + 1] = placement
            joint, frame = j + 1, _IDENTITY
        if m.body_jntnum[b] > 0:
            frame = (np.eye(3), -anchor)
        body_joint[b], body_in_joint[b] = joint, frame

    # Inertias: every body's, in its joint's frame, merged per joint.
    parts: list[list[tuple[float, np.ndarray, np.ndarray]]] = [[] for _ in range(njoints)]
    for b in range(m.nbody):
        rotation, translation = _compose(body_in_joint[b], _pose(m.body_ipos[b], m.body_iquat[b]))
        inertia = rotation @ np.diag(m.body_inertia[b]) @ rotation.T
        parts[body_joint[b]].append((float(m.body_mass[b]), translation, inertia))
    merged = [_merge_inertias(p) if p else (0.0, np.zeros(3), np.zeros((3, 3))) for p in parts]

    qpos0 = np.zeros(m.nq)
    lower, upper = np.full(m.nq, -np.inf), np.full(m.nq, np.inf)
    free_qpos, free_qvel, ball_qpos = [], [], []
    for j in range(m.njnt):
        adr = m.jnt_qposadr[j]
        if int(m.jnt_type[j]) == ball:
            ball_qpos.append(int(adr))  # [qw, qx, qy, qz]; qvel: angular velocity in the joint frame, as rsmooth's
            if m.jnt_limited[j]:  # the cone limit, at the joint's first coordinate (see Model)
                upper[adr] = m.jnt_range[j][1]
            continue
        if int(m.jnt_type[j]) == free:
            free_qpos.append(int(adr))
            free_qvel.append(int(m.jnt_dofadr[j]))
            dofs = slice(m.jnt_dofadr[j], m.jnt_dofadr[j] + 3)
            # MuJoCo's armature on a free joint multiplies the world-axes linear acceleration,
            # rsmooth's the body-axes one: they differ by armature * (omega x v).
            if np.any(m.dof_armature[dofs] != 0):
                raise ValueError(
                    f"MuJoCo model: free joint {joint_names[j]!r} has armature {m.dof_armature[dofs].tolist()} on its "
                    "linear axes; rsmooth.sim supports armature on a free joint's angular axes only"
                )
            if np.ptp(m.dof_damping[dofs]) != 0:
                raise ValueError(
                    f"MuJoCo model: free joint {joint_names[j]!r} has damping {m.dof_damping[dofs].tolist()} on its "
                    "linear axes; rsmooth.sim needs the same value on the three (its linear velocity is in body axes)"
                )
            if np.any(m.dof_frictionloss[dofs] != 0):  # MuJoCo bounds each world axis' force
                raise ValueError(
                    f"MuJoCo model: free joint {joint_names[j]!r} has frictionloss {m.dof_frictionloss[dofs].tolist()} "
                    "on its linear axes; rsmooth.sim supports it on a free joint's angular axes only (its linear "
                    "velocity is in body axes, MuJoCo's friction bounds the world axes' forces)"
                )
            continue
        qpos0[adr] = m.qpos0[adr]
        if m.jnt_limited[j]:
            lower[adr], upper[adr] = m.jnt_range[j] - m.qpos0[adr]

    effort, actuator_info = _actuator_limits(mj, m)
    frame_names = body_names + joint_names + site_names
    frame_parents = tuple(body_joint) + tuple(range(1, njoints)) + tuple(body_joint[m.site_bodyid[s]] for s in range(m.nsite))
    frame_poses = list(body_in_joint) + [_IDENTITY] * m.njnt + [
        _compose(body_in_joint[m.site_bodyid[s]], _pose(m.site_pos[s], m.site_quat[s])) for s in range(m.nsite)
    ]
    gravity = np.zeros(3) if _disabled(mj, m, "GRAVITY") else np.asarray(m.opt.gravity, dtype=np.float64)
    model = Model(
        joint_names=("universe",) + joint_names,
        joint_types=tuple(types),
        parents=tuple(parents),
        idx_q=(0,) + tuple(int(a) for a in m.jnt_qposadr),
        idx_v=(0,) + tuple(int(a) for a in m.jnt_dofadr),
        frame_names=frame_names,
        frame_parents=tuple(int(p) for p in frame_parents),
        nq=int(m.nq),
        nv=int(m.nv),
        joint_axes=_array(axes),
        joint_placement_rotation=_array([p[0] for p in placements]),
        joint_placement_translation=_array([p[1] for p in placements]),
        body_mass=_array([p[0] for p in merged]),
        body_com=_array([p[1] for p in merged]),
        body_inertia=_array([p[2] for p in merged]),
        frame_placement_rotation=_array([p[0] for p in frame_poses]).reshape(-1, 3, 3),
        frame_placement_translation=_array([p[1] for p in frame_poses]).reshape(-1, 3),
        lower_position_limit=_array(lower),
        upper_position_limit=_array(upper),
        velocity_limit=_array(np.full(m.nv, np.inf)),
        effort_limit=_array(effort),
        armature=_array(m.dof_armature),
        gravity=_array(gravity),
    )

    geom_poses = [_compose(body_in_joint[m.geom_bodyid[g]], _pose(m.geom_pos[g], m.geom_quat[g])) for g in range(m.ngeom)]
    vertices, faces, hulls = [], [], []
    for g in range(m.ngeom):
        mesh = m.geom_dataid[g]
        if int(m.geom_type[g]) != int(mj.mjtGeom.mjGEOM_MESH) or mesh < 0:
            vertices.append(None)
            faces.append(None)
            hulls.append(None)
            continue
        start, count = m.mesh_vertadr[mesh], m.mesh_vertnum[mesh]
        mesh_vertices = np.asarray(m.mesh_vert[start : start + count])
        vertices.append(_array(mesh_vertices))
        # MuJoCo's hull (mesh_graph: numvert, numface, vert_edgeadr[numvert],
        # vert_globalid[numvert], ...), which maxhullvert bounds
        graph = int(m.mesh_graphadr[mesh])
        if graph >= 0:
            hull_count = int(m.mesh_graph[graph])
            ids = np.asarray(m.mesh_graph[graph + 2 + hull_count : graph + 2 + 2 * hull_count], dtype=np.int64)
            hulls.append(_array(mesh_vertices[ids]))
        else:
            hulls.append(vertices[-1])
        start, count = m.mesh_faceadr[mesh], m.mesh_facenum[mesh]
        faces.append(device_array(m.mesh_face[start : start + count], np.int32))
    damping = np.zeros(m.nv) if _disabled(mj, m, "DAMPER") else np.asarray(m.dof_damping, dtype=np.float64)
    friction_off = _disabled(mj, m, "FRICTIONLOSS", "CONSTRAINT")
    frictionloss = np.zeros(m.nv) if friction_off else np.asarray(m.dof_frictionloss, dtype=np.float64)
    stiffness = np.zeros(m.nv)
    if not _disabled(mj, m, "SPRING"):
        for j in range(m.njnt):  # a ball joint's one stiffness on its three dofs
            stiffness[m.jnt_dofadr[j] : m.jnt_dofadr[j] + (3 if int(m.jnt_type[j]) == ball else 1)] = m.jnt_stiffness[j]
    spring_reference = np.asarray(m.qpos_spring, dtype=np.float64) - qpos0  # rsmooth's coordinates
    for adr in ball_qpos:
        spring_reference[adr : adr + 4] = np.asarray(_normalized_quaternion(np.r_[m.qpos_spring[adr + 1 : adr + 4], m.qpos_spring[adr]]))
    return MujocoModel(
        model=model,
        damping=_array(damping),
        frictionloss=_array(frictionloss),
        stiffness=_array(stiffness),
        spring_reference=_array(spring_reference),
        joint_couplings=None if _disabled(mj, m, "EQUALITY", "CONSTRAINT") else _joint_couplings(mj, m),
        connections=None if _disabled(mj, m, "EQUALITY", "CONSTRAINT") else _connections(mj, m),
        welds=None if _disabled(mj, m, "EQUALITY", "CONSTRAINT") else _welds(mj, m),
        tendons=_tendons(mj, m),
        gravcomp=_gravcomp(mj, m),
        fluid=_fluid(m),
        limits_enforced=not _disabled(mj, m, "LIMIT", "CONSTRAINT"),
        timestep=float(m.opt.timestep),
        body_names=body_names,
        body_parents=tuple(int(p) for p in m.body_parentid),
        body_joints=tuple(body_joint),
        geom_names=geom_names,
        geom_types=tuple(mj.mjtGeom(t).name.removeprefix("mjGEOM_").lower() for t in m.geom_type),
        geom_bodies=tuple(int(b) for b in m.geom_bodyid),
        geom_joints=tuple(body_joint[b] for b in m.geom_bodyid),
        geom_size=_array(m.geom_size).reshape(-1, 3),
        geom_rotation=_array([p[0] for p in geom_poses]).reshape(-1, 3, 3),
        geom_translation=_array([p[1] for p in geom_poses]).reshape(-1, 3),
        geom_friction=_array(m.geom_friction[:, 0]),
        geom_contype=tuple(int(c) for c in m.geom_contype),
        geom_conaffinity=tuple(int(c) for c in m.geom_conaffinity),
        geom_priority=tuple(int(p) for p in m.geom_priority),
        geom_vertices=tuple(vertices),
        geom_faces=tuple(faces),
        geom_hull=tuple(hulls),
        geom_height_fields=tuple(_height_field(mj, m, g) for g in range(m.ngeom)),
        contact_pairs=tuple((int(a), int(b)) for a, b in zip(m.pair_geom1, m.pair_geom2)),
        pair_friction=_array(m.pair_friction[:, 0]).reshape(-1),
        # MuJoCo packs an excluded pair as body1 << 16 | body2.
        excluded_body_pairs=tuple((int(s) >> 16, int(s) & 0xFFFF) for s in m.exclude_signature),
        collision_pairs=_collision_pairs(mj, m),
        **actuator_info,
        qpos0=_array(qpos0),
        default_qpos=_array(m.qpos0),
        free_joint_qpos=tuple(free_qpos),
        free_joint_qvel=tuple(free_qvel),
        ball_joint_qpos=tuple(ball_qpos),
        activation_dynamics=_activation_dynamics(mj, m),
    )


def _collision_pairs(mj: Any, m: Any) -> tuple[tuple[int, int], ...]:
    """The geom pairs MuJoCo's ``mj_collision`` may test, by its filters (see
    :attr:`MujocoModel.collision_pairs`); distances are left to the collision routines."""
    if _disabled(mj, m, "CONTACT", "CONSTRAINT"):
        return ()
    explicit = [(int(a), int(b)) for a, b in zip(m.pair_geom1, m.pair_geom2)]
    explicit_sets = {frozenset(pair) for pair in explicit}
    excluded = {frozenset((int(s) >> 16, int(s) & 0xFFFF)) for s in m.exclude_signature}
    weld = np.asarray(m.body_weldid)
    weld_parent = weld[np.asarray(m.body_parentid)[weld]]
    filter_parent = not _disabled(mj, m, "FILTERPARENT")
    plane = int(mj.mjtGeom.mjGEOM_PLANE)
    pairs = list(explicit)
    for g1 in range(m.ngeom):
        for g2 in range(g1 + 1, m.ngeom):
            b1, b2 = int(m.geom_bodyid[g1]), int(m.geom_bodyid[g2])
            w1, w2 = weld[b1], weld[b2]
            if w1 == w2:
                continue
            if filter_parent and w1 != 0 and w2 != 0 and (w1 == weld_parent[w2] or w2 == weld_parent[w1]):
                continue
            if frozenset((b1, b2)) in excluded or frozenset((g1, g2)) in explicit_sets:
                continue
            if not (m.geom_contype[g1] & m.geom_conaffinity[g2] or m.geom_contype[g2] & m.geom_conaffinity[g1]):
                continue
            if m.geom_type[g1] == plane and m.geom_type[g2] == plane:
                continue
            pairs.append((g1, g2))
    return tuple(pairs)


def _actuator_limits(mj: Any, m: Any) -> tuple[np.ndarray, dict[str, Any]]:
    """Effort limit per dof and the motors' fields. A dof driven by exactly one motor is
    limited by what its control range and force range allow (through the gear); the dof's
    own actuator force range (``actfrcrange``) limits it whatever drives it."""

    def bounds(limited, ranges):
        ranges = np.asarray(ranges, dtype=np.float64).reshape(-1, 2).copy()
        ranges[~np.asarray(limited, dtype=bool)] = (-np.inf, np.inf)
        return ranges

    ctrl_range = bounds(m.actuator_ctrllimited, m.actuator_ctrlrange)
    force_range = bounds(m.actuator_forcelimited, m.actuator_forcerange)
    gear = np.asarray(m.actuator_gear[:, 0], dtype=np.float64)
    gain = np.asarray(m.actuator_gainprm[:, 0], dtype=np.float64)
    on_tendon = [int(m.actuator_trntype[a]) == int(mj.mjtTrn.mjTRN_TENDON) for a in range(m.nu)]
    dofs = [-1 if on_tendon[a] else int(m.jnt_dofadr[m.actuator_trnid[a, 0]]) for a in range(m.nu)]
    tendons = [int(m.actuator_trnid[a, 0]) if on_tendon[a] else -1 for a in range(m.nu)]
    # each actuator's length on MuJoCo's qpos and its moment arms, gear included
    lengths, moments = np.zeros((m.nu, m.nq)), np.zeros((m.nu, m.nv))
    tendon_lengths, tendon_moments = _tendon_moments(m, positions=True), _tendon_moments(m)
    for a in range(m.nu):
        if on_tendon[a]:
            lengths[a], moments[a] = gear[a] * tendon_lengths[tendons[a]], gear[a] * tendon_moments[tendons[a]]
        else:
            lengths[a, m.jnt_qposadr[m.actuator_trnid[a, 0]]] = moments[a, dofs[a]] = gear[a]
    dof_range = np.tile([-np.inf, np.inf], (m.nv, 1))
    for j in range(m.njnt):
        if m.jnt_actfrclimited[j]:
            dof_range[m.jnt_dofadr[j]] = m.jnt_actfrcrange[j]
    effort = np.max(np.abs(dof_range), axis=1)
    for dof in set(dofs) - {-1}:
        motors = [a for a in range(m.nu) if dofs[a] == dof]
        if len(motors) != 1:
            continue
        a = motors[0]
        # A zero gain or gear reaches nothing, even with an unbounded range (not 0 * inf).
        scale_ctrl, scale_force = abs(gear[a] * gain[a]), abs(gear[a])
        reach = min(
            scale_ctrl * np.max(np.abs(ctrl_range[a])) if scale_ctrl > 0 else 0.0,
            scale_force * np.max(np.abs(force_range[a])) if scale_force > 0 else 0.0,
        )
        effort[dof] = min(effort[dof], reach)
    return effort, dict(
        actuator_names=_names(m, "actuator", m.nu),
        actuator_dofs=tuple(dofs),
        actuator_tendons=tuple(tendons),
        servo_actuators=tuple(
            a for a in range(m.nu)
            if int(m.actuator_biastype[a]) == int(mj.mjtBias.mjBIAS_AFFINE) and np.any(m.actuator_biasprm[a, :3] != 0)
        ),
        tendon_names=_names(m, "tendon", m.ntendon),
        tendon_moments=_array(tendon_moments).reshape(m.ntendon, m.nv),
        actuator_gear=_array(gear),
        actuator_gain=_array(gain),
        actuator_bias=_array(np.where(
            np.asarray(m.actuator_biastype)[:, None] == int(mj.mjtBias.mjBIAS_AFFINE), np.asarray(m.actuator_biasprm[:, :3], dtype=np.float64), 0.0
        )).reshape(m.nu, 3),
        actuator_lengths=_array(lengths).reshape(m.nu, m.nq),
        actuator_moments=_array(moments).reshape(m.nu, m.nv),
        actuator_ctrl_range=_array(ctrl_range).reshape(-1, 2),
        actuator_force_range=_array(force_range).reshape(-1, 2),
        dof_actuator_force_range=_array(dof_range).reshape(-1, 2),
    )


def _joint_couplings(mj: Any, m: Any) -> JointCoupling | None:
    """The active joint equalities of ``m`` as a ``JointCoupling`` (rsmooth joint ``j + 1`` is
    MuJoCo joint ``j``; MuJoCo's equation ``y - y0 = p(x - x0)`` is rsmooth's ``q_a = p(q_b)``,
    rsmooth's coordinates of hinges and slides being MuJoCo's less ``qpos0``), or ``None``."""
    equalities = [
        e for e in range(m.neq) if int(m.eq_type[e]) == int(mj.mjtEq.mjEQ_JOINT) and m.eq_active0[e]
    ]
    joints = [int(m.eq_obj1id[e]) + 1 for e in equalities]
    others = [int(m.eq_obj2id[e]) + 1 if m.eq_obj2id[e] >= 0 else 0 for e in equalities]
    coefficients = [np.asarray(m.eq_data[e, :5], dtype=np.float64) for e in equalities]
    for joint, other, row in _tendon_couplings(mj, m):
        joints.append(joint)
        others.append(other)
        coefficients.append(row)
    if not joints:
        return None
    return JointCoupling(tuple(joints), tuple(others), _array(np.array(coefficients)))


def _held_ends(mj: Any, m: Any, kind: Any, first: slice, second: slice):
    """The active equalities of type ``kind`` that hold two frames together: ``(equalities,
    sites, frames, others, anchors, other_anchors)``. Between sites, the sites' frames (bodies
    by id, joints, then sites) with their origins as anchors; between bodies, the bodies'
    frames (the world's, 0, for ``-1``) with the anchors ``eq_data[first]`` and
    ``eq_data[second]``."""
    equalities = [e for e in range(m.neq) if int(m.eq_type[e]) == int(kind) and m.eq_active0[e]]
    sites = [int(m.eq_objtype[e]) == int(mj.mjtObj.mjOBJ_SITE) for e in equalities]
    first_site = m.nbody + m.njnt
    frames, others, anchors, other_anchors = [], [], [], []
    for e, site in zip(equalities, sites):
        data = np.asarray(m.eq_data[e], dtype=np.float64)
        offset = first_site if site else 0
        frames.append(offset + int(m.eq_obj1id[e]))
        others.append(offset + max(int(m.eq_obj2id[e]), 0))  # a body's -1 or 0: the world
        anchors.append(np.zeros(3) if site else data[first])
        other_anchors.append(np.zeros(3) if site else data[second])
    return equalities, sites, tuple(frames), tuple(others), np.array(anchors), np.array(other_anchors)


def _connections(mj: Any, m: Any) -> PointConnection | None:
    """The active connect equalities of ``m`` as a ``PointConnection``, or ``None``. Between
    bodies, MuJoCo's ``eq_data[0:3]`` is the anchor in the first body's frame and
    ``eq_data[3:6]`` the same point in the second's (where the compiler found it at ``qpos0``);
    between sites, the sites' origins."""
    equalities, _, frames, others, anchors, other_anchors = _held_ends(mj, m, mj.mjtEq.mjEQ_CONNECT, slice(0, 3), slice(3, 6))
    if not equalities:
        return None
    return PointConnection(frames, others, _array(anchors), _array(other_anchors))


def _welds(mj: Any, m: Any) -> Weld | None:
    """The active weld equalities of ``m`` as a ``Weld``, or ``None``. MuJoCo's ``eq_data`` holds
    the weld point in the second body's frame (``[0:3]``), the first body's pose relative to it
    (``relpose``: the point in the first body's frame ``[3:6]`` and the quaternion ``[6:10]``,
    ``w`` first) and the ``torquescale`` (``[10]``). Between sites, the sites' frames are held
    together (origins and axes; ``relpose`` does not apply)."""
    equalities, sites, frames, others, anchors, other_anchors = _held_ends(mj, m, mj.mjtEq.mjEQ_WELD, slice(3, 6), slice(0, 3))
    if not equalities:
        return None
    rotations = [np.eye(3) if site else _pose(np.zeros(3), m.eq_data[e, 6:10])[0] for e, site in zip(equalities, sites)]
    scales = np.array([m.eq_data[e, 10] for e in equalities], dtype=np.float64)
    return Weld(frames, others, _array(anchors), _array(other_anchors), _array(np.array(rotations).reshape(len(frames), 3, 3)),
                _array(scales))


def _tendon_equalities(mj: Any, m: Any) -> list[tuple[int, bool]]:
    """The active equalities of tendons, each with whether it is a row that holds the tendon's
    length (a spatial tendon, or a fixed one on three or more joints: :func:`_tendons`) rather
    than a joint coupling (:func:`_tendon_couplings`)."""
    moments = _tendon_moments(m)
    return [
        (e, _is_spatial(mj, m, m.eq_obj1id[e]) or np.count_nonzero(moments[m.eq_obj1id[e]]) > 2)
        for e in range(m.neq) if int(m.eq_type[e]) == int(mj.mjtEq.mjEQ_TENDON) and m.eq_active0[e]
    ]


def _tendon_couplings(mj: Any, m: Any) -> list[tuple[int, int, np.ndarray]]:
    """The active equalities of one fixed tendon on one or two joints as joint couplings
    ``(joint, other, coefficients)`` (rsmooth joints). MuJoCo's equation ``L - L0 = c_0``, ``L0``
    the length at ``qpos0``, is ``a q_a + b q_b = c_0`` in rsmooth's coordinates (MuJoCo's less
    ``qpos0``): ``q_a = c_0 / a - (b / a) q_b`` (``b = 0``, other 0, for a tendon on one joint);
    grippers hold their two fingers together so (dm_control's manipulator). A fixed tendon on
    more joints, or a spatial tendon, is held at its length by :attr:`Tendons.equalities`
    (:func:`_tendons`); equalities between two tendons are refused by name."""
    couplings = []
    names, tendon_names = _names(m, "equality", m.neq), _names(m, "tendon", m.ntendon)
    moments = _tendon_moments(m)
    joint_of_dof = {int(m.jnt_dofadr[j]): j for j in range(m.njnt)}
    for e, as_row in _tendon_equalities(mj, m):
        tendon = int(m.eq_obj1id[e])
        where = f"MuJoCo model: equality {names[e]!r} on tendon {tendon_names[tendon]!r}"
        if m.eq_obj2id[e] >= 0:
            raise ValueError(
                f"{where} couples it to a second tendon, which rsmooth.sim does not support (supported: an equality of "
                "one tendon)"
            )
        if as_row:
            continue
        dofs = np.flatnonzero(moments[tendon])
        if not len(dofs):
            raise ValueError(f"{where}: the tendon has no nonzero coefficient")
        a = moments[tendon, dofs[0]]
        row = np.zeros(5)
        row[0] = m.eq_data[e, 0] / a
        other = 0
        if len(dofs) == 2:
            row[1] = -moments[tendon, dofs[1]] / a
            other = joint_of_dof[int(dofs[1])] + 1
        couplings.append((joint_of_dof[int(dofs[0])] + 1, other, row))
    return couplings


def _array(values: Any) -> jax.Array:
    return device_array(values)


# MuJoCo's URDF reader merges bodies without joints into their parents (a robot's floating base
# into the world), drops visual meshes and strips mesh paths to file names by default: a URDF
# read here keeps its bodies and its mesh paths, and balances inertias as Pinocchio's
# parser accepts them.
_URDF_COMPILER = (
    '<mujoco><compiler balanceinertia="true" discardvisual="false" fusestatic="false" strippath="false"/></mujoco>'
)


def _resolve_packages(text: str, package_dirs, path: pathlib.Path) -> str:
    """``text`` with every ``package://NAME/REST`` URI replaced by an absolute path: the first
    ``DIR/NAME/REST`` that exists for ``DIR`` in ``package_dirs`` (ROS's convention: folders
    that hold packages), or ``DIR/REST`` where ``DIR`` is itself named ``NAME``. Extra slashes
    before ``NAME`` are read as one, as Pinocchio reads them (Talos's URDFs in example-robot-data
    write ``package:///example-robot-data/...``)."""
    dirs = [pathlib.Path(d) for d in package_dirs]

    def resolve(match):
        name, rest = match.group(1), match.group(2)
        for folder in dirs:
            for candidate in (folder / name / rest, folder / rest if folder.name == name else None):
                if candidate is not None and candidate.exists():
                    return str(candidate.resolve())
        searched = ", ".join(str(d) for d in dirs) or "none given"
        raise FileNotFoundError(
            f"{path}: cannot resolve package://{name}/{rest}: no such file under package_dirs ({searched}); "
            f"pass the folder that holds the package {name!r}"
        )

    return re.sub(r"package:/{2,}([^/\"'\s]+)/([^\"'\s<>]+)", resolve, text)


def _read_urdf(mj, path: pathlib.Path, package_dirs) -> Any:
    """An ``MjSpec`` of a URDF file, its ``package://`` URIs resolved and relative mesh paths
    taken from the file's folder."""
    text = _resolve_packages(path.read_text(), package_dirs, path)
    if "<mujoco" not in text:
        robot = text.find("<robot")
        if robot < 0:
            raise ValueError(f"{path}: not a URDF file (no <robot> element)")
        start = text.index(">", robot) + 1
        text = text[:start] + _URDF_COMPILER + text[start:]
    try:
        spec = mj.MjSpec.from_string(text)
    except ValueError as error:
        raise ValueError(f"MuJoCo could not load {path}: {error}") from None
    if not spec.meshdir:
        spec.meshdir = str(path.parent.resolve())
    return spec


class MujocoLoadWarning(UserWarning):
    """What :func:`load_mjcf` changed in a model to load it: the visual geoms it dropped, the
    inertias ``boundinertia`` raised, the joint couplings and dry friction ``drop_mimic`` and
    ``drop_frictionloss`` dropped; and what MuJoCo warned of while loading it."""


# MuJoCo's compile errors that load_mjcf explains: a mesh file in a format it has no decoder
# for (the element is the mesh asset), and a rotational inertia that is not positive definite.
_NO_DECODER = re.compile(r"no decoder found for mesh file '(?P<file>[^']*)'\s*\nElement name '(?P<name>[^']*)', id (?P<id>\d+)")
_BAD_INERTIA = re.compile(r"inertia must have positive eigenvalues.*?\nElement name '(?P<name>[^']*)'", re.S)


def _geom_label(geom: Any) -> str:
    return f"geom {geom.name!r}" if geom.name else f"an unnamed geom of body {geom.parent.name!r}"


def _why_kept(mj: Any, spec: Any, geom: Any) -> str | None:
    """Why a geom is needed by the physics (``None`` if it is visual only): it collides, or its
    body's inertia is computed from it (MuJoCo's ``inertiafromgeom``, ``inertiagrouprange``)."""
    if geom.contype or geom.conaffinity:
        return f"it collides (contype {geom.contype}, conaffinity {geom.conaffinity})"
    if geom.name and any(geom.name in (pair.geomname1, pair.geomname2) for pair in spec.pairs):
        return "it is in an explicit contact pair"
    mode, body = spec.compiler.inertiafromgeom, geom.parent
    low, high = spec.compiler.inertiagrouprange
    inferred = mode == mj.mjtInertiaFromGeom.mjINERTIAFROMGEOM_TRUE or (
        mode == mj.mjtInertiaFromGeom.mjINERTIAFROMGEOM_AUTO and not body.explicitinertial
    )
    massive = geom.mass > 0 if np.isfinite(geom.mass) else geom.density > 0
    if inferred and massive and low <= geom.group <= high:
        return f"the inertia of body {body.name!r} is computed from it (no explicit inertial)"
    return None


def _undecodable_mesh(spec: Any, match: re.Match) -> Any:
    """The mesh asset MuJoCo's 'no decoder' error names (by name, else by id)."""
    if match["name"]:
        return spec.mesh(match["name"])
    meshes = list(spec.meshes)
    index = int(match["id"])
    return meshes[index] if index < len(meshes) else None


def _unread_reason(file: str, unread: dict[str, str] | None) -> str | None:
    """Why :func:`_read_collada` could not read ``file`` (MuJoCo's name for it), if it tried."""
    for path, why in (unread or {}).items():
        if path == file or pathlib.Path(path).resolve() == pathlib.Path(file).resolve():
            return why
    return None


def _load_error(mj: Any, spec: Any, where: str, error: ValueError, unread: dict[str, str] | None = None) -> ValueError:
    """MuJoCo's compile error, with what the user can do about the two that load_mjcf knows;
    ``unread``: the Collada files :func:`_read_collada` could not read, with why."""
    message = f"MuJoCo could not load {where}: {error}"
    decoder = _NO_DECODER.search(str(error))
    inertia = _BAD_INERTIA.search(str(error))
    if decoder is not None:
        mesh = _undecodable_mesh(spec, decoder)
        users = [g for g in spec.geoms if mesh is not None and g.meshname == mesh.name]
        needed = [(g, _why_kept(mj, spec, g)) for g in users]
        needed = [(g, why) for g, why in needed if why is not None]
        suffix = pathlib.Path(decoder["file"]).suffix or "extension-less"
        reason = _unread_reason(decoder["file"], unread)
        unread_why = f" (and {reason})" if reason and reason != "no such file" else ""
        if needed:
            geom, why = needed[0]
            message += (
                f"\nMuJoCo has no decoder for {suffix} mesh files{unread_why}, and {_geom_label(geom)}, which uses "
                f"{decoder['file']!r}, cannot be dropped: {why}; convert the file to a format MuJoCo reads (STL, OBJ)"
            )
        else:
            message += (
                f"\nMuJoCo has no decoder for {suffix} mesh files{unread_why}; the geoms that use {decoder['file']!r} are visual "
                "only: pass visuals='auto' to drop the visual geoms whose meshes MuJoCo cannot decode, or "
                "visuals=False to drop every visual geom"
            )
    elif inertia is not None:
        body = spec.body(inertia["name"]) if inertia["name"] else None
        given = ""
        if body is not None:
            full = np.asarray(body.fullinertia, dtype=np.float64)
            values = full if np.all(np.isfinite(full)) else np.asarray(body.inertia, dtype=np.float64)
            given = f" (mass {body.mass:g}, inertia {values.tolist()})"
        message += (
            f"\nbody {inertia['name']!r} has a rotational inertia that is not positive definite{given}: correct its "
            "inertial in the file, or pass boundinertia, a small lower bound in kg m^2 (e.g. 1e-9) on every body's "
            "principal moments of inertia (MuJoCo's compiler boundinertia; a warning names the bodies it raises)"
        )
    return ValueError(message)


def _drop_joint_equalities(mj: Any, spec: Any, where: str) -> None:
    """Deletes the joint equality constraints of ``spec`` (a URDF ``<mimic>`` becomes one),
    with a warning naming the joints they coupled."""
    dropped = []
    for equality in list(spec.equalities):
        if equality.type != mj.mjtEq.mjEQ_JOINT:
            continue
        couple = f"{equality.name1!r} to {equality.name2!r}" if equality.name2 else f"{equality.name1!r} to a constant"
        dropped.append(couple)
        spec.delete(equality)
    if dropped:
        warnings.warn(
            f"{where}: drop_mimic=True dropped the joint equality constraints coupling joint {'; '.join(dropped)}: "
            "these joints move independently",
            MujocoLoadWarning,
            stacklevel=4,
        )


def _drop_frictionloss(spec: Any, where: str) -> None:
    """Zeroes the dry friction (``frictionloss``) of every joint of ``spec``, with a warning
    naming the joints and the values dropped."""
    dropped = []
    for joint in spec.joints:
        if joint.frictionloss != 0:
            dropped.append(f"{joint.name!r} ({joint.frictionloss:g})")
            joint.frictionloss = 0.0
    if dropped:
        warnings.warn(
            f"{where}: drop_frictionloss=True dropped the dry friction (frictionloss) of {len(dropped)} joints: "
            f"{', '.join(dropped)}",
            MujocoLoadWarning,
            stacklevel=4,
        )


def _mesh_path(spec: Any, mesh: Any) -> pathlib.Path:
    """The file a mesh asset names, found as MuJoCo finds it: absolute, or under ``meshdir``
    (itself absolute or under the model file's folder)."""
    path = pathlib.Path(mesh.file)
    if path.is_absolute():
        return path
    return pathlib.Path(spec.modelfiledir or ".") / (spec.meshdir or "") / path


def _read_collada(spec: Any) -> dict[str, str]:
    """Reads the Collada (``.dae``) meshes of ``spec`` into their vertices and faces.

    MuJoCo has no decoder for Collada, which robot descriptions use for visual and collision
    meshes alike (13 of example-robot-data's URDFs collide Collada meshes); trimesh (with
    pycollada) reads them, and the mesh asset then holds the triangles instead of the file.
    The scene graph's transforms are applied and the file's ``<unit meter>`` is honoured, as the
    COLLADA standard asks; ``<up_axis>`` is not (Pinocchio and ROS's viewers ignore it, and
    robot descriptions that declare ``Y_UP``, such as Tiago's and iCub's, are drawn in their
    links' Z-up frames). Returns the files it could not read, each with why: MuJoCo then
    reports them as files it has no decoder for, and ``visuals="auto"`` drops those that are
    visual only.
    """
    meshes = [mesh for mesh in spec.meshes if mesh.file.lower().endswith(".dae")]
    if not meshes:
        return {}
    try:
        import trimesh
    except ImportError:
        why = "reading Collada needs trimesh and pycollada: pip install 'rsmooth[render]'"
        return {str(_mesh_path(spec, mesh)): why for mesh in meshes}
    failed, decoded = {}, {}
    for mesh in meshes:
        path = _mesh_path(spec, mesh)
        key = str(path)
        if key not in decoded and key not in failed:
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")  # pycollada's notes on the file's schema
                    triangles = trimesh.load(str(path), force="mesh", process=False)
                if not isinstance(triangles, trimesh.Trimesh) or len(triangles.faces) == 0:
                    raise ValueError("it holds no triangles")
                if triangles.units is not None:  # "0.001 * meters" for <unit meter="0.001">
                    triangles.convert_units("meters")
                triangles.merge_vertices(merge_tex=True, merge_norm=True)
                decoded[key] = (np.asarray(triangles.vertices, np.float64), np.asarray(triangles.faces, np.int64))
            except Exception as error:  # trimesh raises many types for a file it cannot read
                failed[key] = f"trimesh could not read it: {type(error).__name__}: {error}" if path.is_file() else "no such file"
        if key in decoded:
            vertices, faces = decoded[key]
            mesh.file = ""
            mesh.uservert = vertices.ravel().tolist()
            mesh.userface = faces.ravel().tolist()
    return failed


def _raised_inertias(spec: Any, compiled: Any, bound: float) -> list[str]:
    """The bodies whose principal moments of inertia ``boundinertia`` raised: an explicit
    inertia with a principal moment under the bound (MuJoCo may then rebalance it, see
    ``balanceinertia``), or a compiled one with a moment at the bound."""
    names = []
    for body in list(spec.bodies)[1:]:
        raised = np.min(compiled.body_inertia[body.id]) <= bound
        if body.explicitinertial:
            full = np.asarray(body.fullinertia, dtype=np.float64)
            if np.all(np.isfinite(full)):
                matrix = np.array([[full[0], full[3], full[4]], [full[3], full[1], full[5]], [full[4], full[5], full[2]]])
                moments = np.linalg.eigvalsh(matrix)
            else:
                moments = np.asarray(body.inertia, dtype=np.float64)
            raised = raised or np.min(moments) < bound
        if raised:
            names.append(body.name or f"body {body.id}")
    return names


def _compile(mj: Any, spec: Any, where: str, *, visuals, boundinertia, drop_mimic: bool, drop_frictionloss: bool) -> Any:
    """Compiles ``spec`` with load_mjcf's options (see there), warning of what they changed."""
    if drop_mimic:
        _drop_joint_equalities(mj, spec, where)
    if drop_frictionloss:
        _drop_frictionloss(spec, where)
    if boundinertia is not None:
        spec.compiler.boundinertia = boundinertia
    if visuals is False:
        try:
            spec.discard_visual()
        except ValueError as error:
            raise _load_error(mj, spec, where, error) from None
    unread = _read_collada(spec)
    dropped: dict[str, list[str]] = {}
    while True:
        try:
            compiled = spec.compile()
            break
        except ValueError as error:
            match = _NO_DECODER.search(str(error))
            mesh = _undecodable_mesh(spec, match) if match is not None and visuals == "auto" else None
            users = [g for g in spec.geoms if mesh is not None and g.meshname == mesh.name]
            if mesh is None or any(_why_kept(mj, spec, g) is not None for g in users):
                raise _load_error(mj, spec, where, error, unread) from None
            # Visual only: drop the geoms and the mesh; each pass removes one mesh, so this ends.
            labels = [f"{g.name!r} on {g.parent.name!r}" if g.name else repr(g.parent.name) for g in users]
            dropped.setdefault(match["file"], []).extend(labels)
            for geom in users:
                spec.delete(geom)
            spec.delete(mesh)
    if dropped:
        count = sum(len(geoms) for geoms in dropped.values())
        folder = os.path.commonpath([os.path.dirname(file) for file in dropped])
        def entry(file: str, geoms: list[str]) -> str:
            reason = _unread_reason(file, unread)
            on = f"on {', '.join(geoms)}" if geoms else "unused"
            return f"{os.path.relpath(file, folder) if folder else file} ({on}{'; ' + reason if reason else ''})"

        listing = "; ".join(entry(file, geoms) for file, geoms in dropped.items())
        warnings.warn(
            f"{where}: dropped {count} visual geoms whose mesh files MuJoCo has no decoder for (visuals='auto'; "
            f"visuals=False drops every visual geom, converting the files to STL or OBJ keeps them), in {folder or '.'}: "
            f"{listing}",
            MujocoLoadWarning,
            stacklevel=3,
        )
    if boundinertia is not None:
        raised = _raised_inertias(spec, compiled, boundinertia)
        if raised:
            warnings.warn(
                f"{where}: boundinertia={boundinertia:g} raised the principal moments of inertia of "
                f"{len(raised)} bodies to at least {boundinertia:g} kg m^2: {', '.join(map(repr, raised))}",
                MujocoLoadWarning,
                stacklevel=3,
            )
    return compiled


def source_label(source: Any) -> str:
    """How messages name a model's source: its path, "the XML text" or "the model"."""
    if isinstance(source, str) and source.lstrip().startswith("<"):
        return "the XML text"
    return str(pathlib.Path(source)) if isinstance(source, (str, pathlib.Path)) else "the model"


@contextlib.contextmanager
def _mujoco_warnings(mj: Any, where: str):
    """MuJoCo's warnings while loading a model (e.g. a joint whose limits are equal) as
    :class:`MujocoLoadWarning` naming its source ``where`` (:func:`source_label`), instead of
    MuJoCo's own output: a line on the terminal and a ``MUJOCO_LOG.TXT`` file in the working
    folder."""
    previous = mj.get_mju_user_warning()
    mj.set_mju_user_warning(lambda text: warnings.warn(f"{where}: MuJoCo: {text.strip()}", MujocoLoadWarning, stacklevel=2))
    try:
        yield
    finally:
        mj.set_mju_user_warning(previous)


def _check_options(visuals, boundinertia, drop_mimic, drop_frictionloss) -> None:
    if visuals is not True and visuals is not False and visuals != "auto":
        raise ValueError(f"visuals must be True, False or 'auto', got {visuals!r}")
    if boundinertia is not None and (
        isinstance(boundinertia, bool) or not (np.ndim(boundinertia) == 0 and np.isfinite(boundinertia) and boundinertia > 0)
    ):
        raise ValueError(f"boundinertia must be None or a positive, finite number (kg m^2), got {boundinertia!r}")
    for name, value in (("drop_mimic", drop_mimic), ("drop_frictionloss", drop_frictionloss)):
        if not isinstance(value, (bool, np.bool_)):
            raise ValueError(f"{name} must be True or False, got {value!r}")


def load_mjcf(
    source: str | pathlib.Path | Any,
    *,
    package_dirs=None,
    floating_base: bool = False,
    visuals: bool | str = "auto",
    boundinertia: float | None = None,
    drop_mimic: bool = False,
    drop_frictionloss: bool = False,
    max_hull_vertices: int | None = None,
) -> MujocoModel:
    """Loads a model with MuJoCo's compiler and converts it (:func:`from_mujoco`).

    A URDF file (``.urdf``) is read as MuJoCo reads URDF, with three differences that a robot
    model needs: ``package://`` mesh URIs are resolved through ``package_dirs``, bodies
    without joints are kept (MuJoCo's ``fusestatic`` would merge a floating base into the
    world) and visual meshes and mesh paths are kept; unless the file has its own
    ``<mujoco>`` element, which then decides.

    Collada meshes (``.dae``), which robot descriptions use for visual and collision geometry
    alike and MuJoCo has no decoder for, are read with trimesh (with pycollada; the
    ``render`` extra), their ``<unit>`` applied. Visual geoms (a URDF's ``<visual>``; in MJCF,
    geoms that do not collide and do not give their body its inertia) matter to drawing only.
    By default (``visuals="auto"``) they are kept where their meshes can be read and dropped,
    with a :class:`MujocoLoadWarning` that names the files and why, where they cannot; a geom
    the physics needs (it collides, or its body's inertia is computed from it) is never
    dropped: its unreadable mesh is an error naming the file and the geom.

    Args:
        source: path to an MJCF or URDF file, the MJCF text itself (a string whose first
            non-blank character is ``<``), or a ``mujoco.MjModel``.
        package_dirs: folders that hold the packages ``package://`` URIs name (each either
            contains a folder per package, or is the package's own folder). ``None``: the
            folders above the file, nearest first, which finds a package that holds the
            file (a robot of example-robot-data: ``package://example-robot-data/robots/...``).
        floating_base: give the first body under the world a free joint named
            ``"root_joint"`` (a legged robot's base; a URDF has no free joint of its own).
        visuals: ``"auto"``: drop the visual geoms whose meshes cannot be read (see above);
            ``True``: keep every visual geom (an unreadable mesh is an error);
            ``False``: drop every visual geom (MuJoCo's ``MjSpec.discard_visual``: the geoms
            that do not collide and are not referenced, after it has taken any inertia they
            give their body). A compiled ``mujoco.MjModel`` is converted with the geoms it has.
        boundinertia: ``None``, or a lower bound (kg m^2, > 0) that MuJoCo's compiler puts on
            the principal moments of inertia of every body (its ``boundinertia``), for a file
            whose inertial is not positive definite (Go1's ``base`` link: every entry
            ``1e-6``). It changes the physics of the bodies it raises (massless bodies too):
            a :class:`MujocoLoadWarning` names them. Prefer a small value (``1e-9``).
        drop_mimic: drop the joint equality constraints (what MuJoCo makes of a URDF
            ``<mimic>``: a gripper's second finger), which :func:`~rsmooth.sim.scene` enforces
            otherwise, with a :class:`MujocoLoadWarning` naming the joints: they then move
            independently. Other equality constraints are refused either way.
        drop_frictionloss: drop the dry joint friction (``frictionloss``; what MuJoCo makes of
            a URDF's ``<dynamics friction>``), to simulate the joints without it, with a
            :class:`MujocoLoadWarning` naming the joints and values.
        max_hull_vertices: ``None``, or the most vertices (``>= 4``) of the convex hull
            MuJoCo takes of each mesh (its ``maxhullvert``, for meshes that do not set their
            own), which is what both MuJoCo and :func:`~rsmooth.sim.scene` collide
            (:attr:`MujocoModel.geom_hull`). A robot's collision meshes have hulls of a
            hundred or more vertices; the separating-axis test between two meshes costs
            the product of their edge counts, so 16 to 32 vertices make a scene of meshes
            tractable, at the cost of a coarser shape.

    Returns:
        The converted model.

    Raises:
        FileNotFoundError: if the path does not exist, or a ``package://`` URI cannot be
            resolved (the message names the URI and the folders searched).
        ValueError: if MuJoCo cannot compile the source (MuJoCo's message is included, with
            the path: a malformed file, a missing mesh file, a mesh file that cannot be read and
            is needed or kept, an inertia that is not positive definite, each with what can be
            done), if ``source`` is of another type or an option is out of range, if
            ``floating_base``, ``boundinertia``, ``drop_mimic``, ``drop_frictionloss`` or ``max_hull_vertices`` is asked of a compiled
            ``mujoco.MjModel`` or ``floating_base`` of a model whose first body already has a
            joint, or if the model uses a feature rsmooth.sim does not support (see
            :func:`from_mujoco`).

    Example:
        >>> loaded = load_mjcf('''<mujoco><worldbody><body name="arm" pos="0 0 1">
        ...   <joint name="hinge" axis="0 1 0"/><geom type="capsule" size=".05" fromto="0 0 0 0 0 -.5"/>
        ... </body></worldbody></mujoco>''')
        >>> loaded.model.joint_names, loaded.model.joint_types[1], loaded.geom_types
        (('universe', 'hinge'), 'revolute', ('capsule',))
    """
    mj = _mujoco()
    where = source_label(source)
    with _mujoco_warnings(mj, where):
        _check_options(visuals, boundinertia, drop_mimic, drop_frictionloss)
        if max_hull_vertices is not None and (
            isinstance(max_hull_vertices, bool) or not isinstance(max_hull_vertices, (int, np.integer)) or max_hull_vertices < 4
        ):
            raise ValueError(f"max_hull_vertices must be None or an integer >= 4, got {max_hull_vertices!r}")
        if isinstance(source, mj.MjModel):
            given = (floating_base, boundinertia is not None, drop_mimic, drop_frictionloss, max_hull_vertices is not None)
            names = ("floating_base", "boundinertia", "drop_mimic", "drop_frictionloss", "max_hull_vertices")
            for name, given in zip(names, given):
                if given:
                    raise ValueError(f"{name} applies to a file or XML text, not to a compiled mujoco.MjModel")
            return from_mujoco(source)
        if isinstance(source, str) and source.lstrip().startswith("<"):
            try:
                spec = mj.MjSpec.from_string(source)
            except ValueError as error:
                raise ValueError(f"MuJoCo could not load the XML text: {error}") from None
        elif isinstance(source, (str, pathlib.Path)):
            path = pathlib.Path(source)
            if not path.is_file():
                raise FileNotFoundError(f"model file not found: {path}")
            if path.suffix.lower() == ".urdf":
                folders = path.resolve().parents if package_dirs is None else package_dirs
                spec = _read_urdf(mj, path, folders)
            else:
                try:
                    spec = mj.MjSpec.from_file(str(path))
                except ValueError as error:
                    raise ValueError(f"MuJoCo could not load {path}: {error}") from None
        else:
            raise ValueError(f"source must be a file path, XML text or a mujoco.MjModel, got {type(source).__name__}")
        if floating_base:
            body = spec.worldbody.first_body()
            if body is None:
                raise ValueError(f"floating_base: {where} has no body under the world")
            if body.first_joint() is not None:
                raise ValueError(f"floating_base: the first body of {where}, {body.name!r}, already has a joint")
            body.add_freejoint(name="root_joint")
        if max_hull_vertices is not None:
            for mesh in spec.meshes:
                if mesh.maxhullvert < 0:  # a mesh's own bound stays
                    mesh.maxhullvert = int(max_hull_vertices)
        compiled = _compile(
            mj, spec, where, visuals=visuals, boundinertia=boundinertia, drop_mimic=drop_mimic, drop_frictionloss=drop_frictionloss
        )
        return from_mujoco(compiled)
