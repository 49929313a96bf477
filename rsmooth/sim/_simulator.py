"""Time-stepping of rigid-body systems with frictional contact: the ``Dynamics`` of rsmooth.

A :class:`RigidBodySystem` is a pure, frozen pytree with ``step(x, u) -> x_next``, ``nx`` and
``nu`` (the interface every optimizer in rsmooth consumes). One step of length ``h``, from the
state ``x = [q, v]``:

1. Free motion (semi-implicit Euler on velocities):
   ``v_f = s + h W^-1 (tau(q, u) + k(q) - C(q, v) v - g(q) - D s)`` with ``W = M(q) + h D``: the
   joint damping ``D`` (:attr:`Joints.damping`, zero by default) is implicit,
   ``D v+``, so it dissipates at any ``h``; the joint springs' forces ``k(q)``
   (:attr:`Joints.springs`) are explicit, as in MuJoCo's Euler integrator. ``M`` includes the rotor inertia
   (``model.armature``); the rest of the system below uses ``W`` where it says ``M``. The
   step's velocities are written in the body axes of the step's start, a frame frozen for
   the step: ``s`` is ``v`` with every free flyer's linear velocity transported by the
   frame's rotation (``+ h omega x v_lin``, removed from ``C v``) and every free object (a
   free flyer with no joint below it) rotated torque-free by the implicit midpoint rule
   (its gyroscopic term removed from ``C v``). In free flight a body's world velocity is
   then constant and its kinetic energy exact; explicit velocity-product terms would gain
   energy at every step of a spinning or tumbling body.
2. Contacts between the system's spheres (a point is a sphere of radius 0) and the world's
   half-spaces, with signed distance ``phi``, contact frame ``R`` and contact Jacobian
   ``J = R^T J_p(q)`` (``3 n x nv``, rows ``[t1, t2, n]`` per contact); then the contact
   manifolds of its geometry pairs (:class:`GeomPair`, :func:`~rsmooth.sim.collide`), with
   ``J = R^T (J_p2 - J_p1)`` the Jacobian of the relative velocity of the witness points.
3. Contact impulses ``lambda``, by the selected contact law:

   - ``"hard"``: the frictional NCP of Signorini and Coulomb with maximum dissipation at the
     velocity level, on the Delassus matrix ``G = J M^-1 J^T`` and the free velocity
     ``g = J v_f`` corrected by ``max(phi, 0) / h`` (a gap that does not close within the
     step exerts no impulse) and ``baumgarte * min(phi, 0) / h`` (penetration is pushed out).
     The joints' dry friction (:attr:`Joints.friction`) adds one box row per
     dof, ``|lambda_k| <= effort_k h`` opposing the dof's velocity; each joint coupling
     (:attr:`Joints.couplings`) a bilateral row, each connection (:attr:`Joints.connections`)
     three and each weld (:attr:`Joints.welds`) six, with the Baumgarte correction of their
     position errors, solved with the contacts.
     Solved by :func:`~rsmooth.sim.solve_ncp` (ADMM), differentiated implicitly.
   - a :class:`~rsmooth.sim.SpringDamper` or :class:`~rsmooth.sim.LogBarrier`: the compliant
     force at ``(phi, J v)`` times ``h``.

4. ``v+ = v_f + M^-1 J^T lambda`` and ``q+ = q (+) h v+``. A free-flyer base is integrated
   on ``R^3 x SO(3)``: its origin moves by ``h`` times its world velocity and its orientation
   by ``exp(h omega)``; its linear velocity is then written in the new body axes,
   ``exp(h omega)^T v_lin`` (the state's convention, below). The SE(3) screw motion of :func:`~rsmooth.sim.integrate` is the
   exact flow of a constant body twist, but with a velocity-level contact it makes a ball
   rolling along a wall orbit its contact point and sink ``r (1 - cos(omega h))`` into the
   wall every step; with the decoupled update the velocity constraint on a sphere's centre
   holds exactly at the position level.

The state is ``x = [q, v]`` in Pinocchio's conventions: a free flyer's configuration is
``[x, y, z, qx, qy, qz, qw]`` (position in the world, unit quaternion) and its velocity
``[v_lin, omega]`` is its body twist, *both in body axes*: the velocity of the body frame's
origin and the angular velocity, expressed in the body frame (``R v_lin`` is the world
velocity). Joint velocities are the joints' rates. Actuators with activation dynamics (MuJoCo's filters
and integrators, :class:`ActivationDynamics`) add their states at the end,
``x = [q, v, act]``, advanced by the step (its forces take the current states, or with
``actearly`` the next ones).

Derivatives of ``step`` (hard contact) come from the implicit function theorem applied to the
whole velocity update, the momentum balance together with the NCP's natural map (see
``RigidBodySystem.derivative``): exactly zero where physics says so (a resting cube under a
small upward force does not move), equal to finite differences where the contact mode does not
change.

References:
    D. E. Stewart, J. C. Trinkle, "An implicit time-stepping scheme for rigid body dynamics
    with inelastic collisions and Coulomb friction", IJNME 39(15), 1996.
    J. Carpentier, Q. Le Lidec, L. Montaut, "From compliant to rigid contact simulation: a
    unified and efficient approach", RSS 2024.
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Sequence
from typing import Literal, NamedTuple, Union

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax
import numpy as np
from jax.typing import ArrayLike

from rsmooth import _checks
from rsmooth._xla import device_array
from rsmooth._results import RESULTS
from rsmooth.sim import _derivatives, _dynamics, _stages
from rsmooth.sim import _spatial as spatial
from rsmooth.sim import _wrapping
from rsmooth.sim._contact import _safe_norm, contact_frame, corrected_free_velocity
from rsmooth.sim._collision import Contacts, _lookup, _swapped, collide, manifold_size
from rsmooth.sim._geometry import Box, Capsule, ConvexMesh, Cylinder, Ellipsoid, HalfSpace, HeightField, Sphere, padded_meshes
from rsmooth.sim._laws import LogBarrier, SpringDamper
from rsmooth.sim._model import JOINT_NV, PRISMATIC, REVOLUTE, SPHERICAL, UNIVERSE, Model
from rsmooth.sim._ncp import (
    NCPInfo,
    NCPSolver,
    fixed_point_step_sizes,
    implicit_impulse_tangent,
    many_column_solver,
    natural_map_of_velocity,
)

Array = jax.Array
ContactLaw = Union[Literal["hard"], SpringDamper, LogBarrier]

__all__ = ["GeomPair", "RigidBodySystem", "SimulationWarning", "StepInfo", "check_steps", "energy", "step"]


SEPARATED, STICKING, SLIDING = 0, 1, 2  # StepInfo.mode


class StepInfo(eqx.Module):
    """Diagnostics of one step (no derivatives are meant to flow through them).

    Attributes:
        distance: signed distances of the candidate contacts at the start of the step, ``(n,)``.
        impulse: contact impulses ``[t1, t2, n]`` per contact, ``(3 n,)``.
        ncp: the :class:`~rsmooth.sim.NCPInfo` of the contact solve (hard contact; for a
            compliant law it reports zero iterations and ``RESULTS.successful``): its
            ``result`` is ``nonfinite`` where the contact problem itself was not finite
            (a step from an already diverged state).
        torque_clipped: whether an input was beyond its limit and was clipped.
        force: the contact forces in world axes, ``(n, 3)``: the impulses over the step, divided
            by ``h`` (the force on the sphere's body; for a :class:`GeomPair`, on shape 2's).
        mode: each contact's mode, ``(n,)``: :data:`SEPARATED` (0, no normal impulse),
            :data:`STICKING` (1) or :data:`SLIDING` (2, its end-of-step tangential velocity
            above the square root of the solver's tolerance).
        diverged: whether the step left the range where it means anything: a non-finite
            next state, or a velocity component with ``|v+| h`` above
            :attr:`RigidBodySystem.max_motion_per_step` (default 1: more than a radian or a
            metre per step, where the step's linearizations of the motion and the contacts
            fail and semi-implicit Euler injects energy). :meth:`RigidBodySystem.rollout`
            holds the state from such a step on; treat the rest of that trajectory as invalid.
        dropped_contacts: how many candidates :attr:`Options.max_contacts` and
            :attr:`Options.max_limits` left out of the solve although the step closes
            their gap (int, ``()``); 0 without a budget.
        skipped_pairs: how many geometry pairs :attr:`Options.max_pairs` left out of
            the collision although their bounding volumes were within their margin (int,
            ``()``; :meth:`RigidBodySystem.skipped_pairs`); 0 without the limit.
        joint_impulse: the impulses of the joints' box rows, ``(m,)`` in the order of
            :meth:`RigidBodySystem.joint_rows` (dry friction's dofs, then the couplings, the
            connections' and the welds' rows, then the tendons' dry friction; N m s or N s, the
            welds' orientation rows in their own units); empty without any.
        inside_side_sites: how many of the spatial tendons' side sites are inside their
            wrapping shape at the start of the step (int, ``()``;
            :meth:`RigidBodySystem.inside_side_sites`): there MuJoCo wraps through the shape,
            which is not modelled, and the tendon's length and moments are not MuJoCo's.
    """

    distance: Array
    impulse: Array
    ncp: NCPInfo
    torque_clipped: Array
    diverged: Array
    force: Array
    mode: Array
    dropped_contacts: Array
    skipped_pairs: Array
    joint_impulse: Array
    inside_side_sites: Array


class _VelocityUpdate(NamedTuple):
    """One step's velocity update and the quantities its implicit derivative reuses."""

    v_next: Array
    impulse: Array  # (3 n,): every candidate's (zero where the budget left it out)
    distance: Array  # (n,)
    ncp: NCPInfo
    clipped: Array
    mass_factor: tuple[Array, bool]  # Cholesky factor of M (rsmooth._linalg.cho_factor)
    jacobian: Array  # contact Jacobian J, (3 n, nv)
    delassus: Array  # G = J_s M^-1 J_sᵀ of the solved rows s (the contacts: all, or the selection; the joints' box rows)
    free_velocity: Array  # g: the NCP's free velocity (hard contact), solved rows
    mu: Array  # friction coefficient per solved contact
    kinematics: _dynamics.Kinematics  # at q
    inertias: spatial.SpatialInertia  # world-frame body inertias at q
    mass: Array  # W = M + diag(armature + h damping), the matrix of mass_factor

    frames: Array  # contact frames (n, 3, 3), columns [t1, t2, n] in world axes
    selection: Array | None  # the solved contacts' indices (K,) under a budget; None: all
    dropped: Array  # StepInfo.dropped_contacts
    joint_impulse: Array  # (m,): the joints' box rows (RigidBodySystem.joint_rows)
    joint_rows: Array  # (m, nv) at q
    joint_bounds: Array  # (m,)
    contact_velocity: Array  # J v+ (3 n,): every candidate's end-of-step velocity in its frame

    def solved(self, rows: Array) -> Array:
        """``rows`` (flat ``[t1, t2, n]`` per candidate, leading axis) of the solved contacts."""
        return rows if self.selection is None else rows[_stages.flat_rows(self.selection)]

    def solved_impulse(self) -> Array:
        """The NCP's unknowns: the solved contacts' impulses, then the joints' box rows'."""
        return jnp.concatenate([self.solved(self.impulse), self.joint_impulse])

    def public(self) -> tuple[Array, Array, Array, NCPInfo, Array, tuple[Array, Array, Array, Array]]:
        # the contact frames, end-of-step contact velocities J v+ and the joints' box rows'
        # impulses for the diagnostics
        diagnostics = (self.frames, self.contact_velocity, self.dropped, self.joint_impulse)
        return self.v_next, self.impulse, self.distance, self.ncp, self.clipped, diagnostics


_SHAPES = (Sphere, Capsule, Box, Cylinder, Ellipsoid, HalfSpace, HeightField, ConvexMesh)
# Signed distance given to the entries of a manifold that are not contacts (beyond the
# pair's margin, or repeats of another entry): ten metres, a gap that no step that has not
# diverged closes (StepInfo.diverged: at most max_motion_per_step, 1 m by default, per body
# and step), so these entries exert no impulse while keeping finite frames and Jacobians.
_INACTIVE_DISTANCE = 10.0


def _placement(name: str, placement) -> tuple[Array, Array]:
    """``(rotation (3, 3), translation (3,))`` from ``None`` (the identity) or a pair; checked."""
    if placement is None:
        return jnp.eye(3), jnp.zeros(3)
    if not isinstance(placement, (tuple, list)) or len(placement) != 2:
        raise ValueError(f"{name} must be a pair (rotation (3, 3), translation (3,)) or None, got {placement!r}")
    rotation, translation = jnp.asarray(placement[0], float), jnp.asarray(placement[1], float)
    if rotation.shape != (3, 3) or translation.shape != (3,):
        raise ValueError(
            f"{name} must be (rotation (3, 3), translation (3,)), got shapes {rotation.shape} and {translation.shape}"
        )
    if not (_checks.is_traced(rotation) or _checks.is_traced(translation)):
        r, t = np.asarray(rotation), np.asarray(translation)
        if not (np.all(np.isfinite(r)) and np.all(np.isfinite(t))):
            raise ValueError(f"{name} must be finite, got {placement!r}")
        if not (np.allclose(r.T @ r, np.eye(3), atol=1e-6) and np.linalg.det(r) > 0):
            raise ValueError(f"{name}: the rotation must be a rotation matrix (orthonormal, det +1), got {r.tolist()}")
    return rotation, translation


class GeomPair(eqx.Module):
    """Two collision shapes of a :class:`RigidBodySystem` that touch each other.

    Each shape is attached to a frame of the model (it moves with that frame's body) or, with
    frame ``None``, fixed in the world; its placement is its pose in that frame (in the world,
    for ``None``). The pair's contacts are :func:`~rsmooth.sim.collide`'s manifold
    (:func:`~rsmooth.sim.manifold_size` entries), normals from shape 1 to shape 2.

    Attributes:
        shape1: a :class:`~rsmooth.sim.Sphere`, :class:`~rsmooth.sim.Capsule`,
            :class:`~rsmooth.sim.Box`, :class:`~rsmooth.sim.Cylinder`,
            :class:`~rsmooth.sim.Ellipsoid`, :class:`~rsmooth.sim.HalfSpace`,
            :class:`~rsmooth.sim.HeightField` or :class:`~rsmooth.sim.ConvexMesh`.
        frame1: frame index or name carrying shape 1 (static), ``None``: fixed in the world.
        placement1: ``(rotation (3, 3), translation (3,))`` of shape 1 in its frame.
        shape2: the other shape; the pair of types must be one that
            :func:`~rsmooth.sim.collide` supports (either order).
        frame2: frame of shape 2 (static), ``None``: fixed in the world.
        placement2: pose of shape 2 in its frame.
        friction: Coulomb coefficient between the two shapes, ``>= 0``.
        margin: entries of the manifold at most this far apart (m, static) are candidate
            contacts: the contact law decides whether they act (hard contact: only a gap
            that closes within the step does), so a resting contact stays in the problem
            across steps. Farther entries are given a distance of 10 m (no impulse).
            ``inf``: every entry at its true distance, however far (a force at a distance,
            :class:`~rsmooth.sim.LogBarrier`, acts at any gap).

    Example:
        >>> import rsmooth.sim as sim
        >>> pair = sim.GeomPair(sim.HalfSpace(), None, sim.Box([0.1, 0.1, 0.1]), "box", friction=0.5)
        >>> sim.manifold_size(pair.shape1, pair.shape2)
        4
    """

    shape1: Sphere | Capsule | Box | Cylinder | Ellipsoid | HalfSpace | HeightField | ConvexMesh
    frame1: int | str | None = eqx.field(static=True)
    placement1: tuple[Array, Array]
    shape2: Sphere | Capsule | Box | Cylinder | Ellipsoid | HalfSpace | HeightField | ConvexMesh
    frame2: int | str | None = eqx.field(static=True)
    placement2: tuple[Array, Array]
    friction: Array
    margin: float = eqx.field(static=True)

    def __init__(self, shape1, frame1, shape2, frame2, *, friction, placement1=None, placement2=None, margin=0.01):
        """Args: as the attributes; ``placement1``/``placement2`` ``None`` is the identity."""
        for name, shape in (("shape1", shape1), ("shape2", shape2)):
            if not isinstance(shape, _SHAPES):
                names = ", ".join(t.__name__ for t in _SHAPES)
                raise ValueError(f"{name} must be a collision shape ({names}), got {type(shape).__name__}")
        try:
            manifold_size(shape1, shape2)
        except NotImplementedError as error:
            raise ValueError(f"shape1 and shape2: {error}") from None
        for name, frame in (("frame1", frame1), ("frame2", frame2)):
            valid_index = isinstance(frame, (int, np.integer)) and not isinstance(frame, bool) and frame >= 0
            if not (frame is None or isinstance(frame, str) or valid_index):
                raise ValueError(f"{name} must be a frame name, a frame index >= 0, or None (the world), got {frame!r}")
        if frame1 is None and frame2 is None:
            raise ValueError("frame1 and frame2 are both None: a pair of world-fixed shapes never moves")
        self.shape1, self.shape2 = shape1, shape2
        self.frame1 = frame1 if frame1 is None or isinstance(frame1, str) else int(frame1)
        self.frame2 = frame2 if frame2 is None or isinstance(frame2, str) else int(frame2)
        self.placement1 = _placement("placement1", placement1)
        self.placement2 = _placement("placement2", placement2)
        friction = jnp.asarray(friction, float)
        if friction.shape != ():
            raise ValueError(f"friction must be a scalar, got shape {friction.shape}")
        if not _checks.is_traced(friction) and not (np.isfinite(float(friction)) and float(friction) >= 0):
            raise ValueError(f"friction must be non-negative and finite, got {float(friction)}")
        self.friction = friction
        if isinstance(margin, bool) or not (np.ndim(margin) == 0 and margin >= 0):
            raise ValueError(f"margin must be a non-negative number (m) or inf, got {margin!r}")
        self.margin = float(margin)

    @property
    def size(self) -> int:
        """The number of candidate contacts of the pair (static)."""
        return manifold_size(self.shape1, self.shape2)


class Options(eqx.Module):
    """How a system is stepped (as MJX's ``Options`` beside its ``Model``): the time step, the
    contact law and its solver, the derivative. A :class:`RigidBodySystem` holds one
    (:attr:`RigidBodySystem.options`, its fields also readable on the system itself);
    :meth:`RigidBodySystem.with_options` changes some.

    Attributes:
        time_step: ``h`` in seconds, kept as a scalar array (traced: systems that differ only
            in it share compiled programs, and derivatives with respect to it flow).
        contact: ``"hard"`` (frictional contact as an NCP, solved by ``solver``), a
            :class:`~rsmooth.sim.SpringDamper` or a :class:`~rsmooth.sim.LogBarrier`.
        solver: the NCP solver configuration (hard contact).
        baumgarte: penetration correction rate in ``[0, 1]`` (hard contact; static).
        derivative: how ``step`` is differentiated with hard contact (static).
            ``"implicit"`` (default): the implicit function theorem on the step's own
            equations, momentum balance ``M (v+ - v) + h (b - tau) - Jᵀ lambda = 0`` and the
            NCP's natural map, so a derivative costs one forward-mode pass through inverse
            dynamics (RNEA) and contact kinematics plus linear solves with the already
            factored ``M`` and natural-map Jacobian; no derivative of the mass matrix, its
            Cholesky factor or the Delassus matrix is formed (the ABA-derivative identity
            ``d(M^-1 r) = -M^-1 dRNEA``, Carpentier and Mansard, RSS 2018). ``"autodiff"``:
            JAX autodiff through CRBA, Cholesky and the Delassus matrix, with only the NCP
            solve differentiated implicitly; the same derivative, several times slower,
            kept as a reference. Compliant contact laws always use ``"autodiff"``.
        max_motion_per_step: bound on ``|v+| h`` (rad or m) beyond which a step is reported
            as diverged (static; ``inf`` reports only non-finite states).
        max_correction_speed: the largest speed (m/s, or rad/s for a joint limit or coupling)
            at which the Baumgarte correction pushes a penetration, a joint beyond its limit
            or a coupling's error back (static; hard contact; ``inf``, the default: no
            bound, and no operation in the step). ``baumgarte d / h`` grows without bound as ``h`` shrinks: a quadruped's
            knee starting 0.9 rad beyond its limit is pushed back at 90 rad/s at ``h = 2``
            ms, which injects tens of joules; a bound turns that into a slower return.
        max_contacts: a budget on the contacts the NCP solves (static; hard contact only):
            at each step the ``max_contacts`` candidates between shapes with the smallest
            signed distance (ties to the lower index), plus the joint limits (every one, or
            :attr:`max_limits` of them). The others get
            zero impulse; a left-out candidate whose gap the step would close (its corrected
            free normal velocity negative, so the solve would have had to act on it) is
            counted in :attr:`StepInfo.dropped_contacts` and reported by :func:`check_steps`.
            A scene of many shapes has far more candidates (every manifold entry of every
            pair) than touching points; the solve's cost grows with the cube of the contacts
            it holds, and a step that takes no derivative builds the contact Jacobian's rows
            of the selected contacts only. The selection is piecewise constant in the state:
            derivatives are those of the selected problem. ``None`` (default): every candidate. See
            :meth:`RigidBodySystem.with_contact_budget`.
        max_limits: the same budget on the joint and tendon limits (:attr:`Joints.limits`,
            :attr:`Tendons.limits`; static): at
            each step the ``max_limits`` limits nearest their bounds (smallest distance, rad
            or m), left-out ones that the step would close counted as dropped contacts. A
            robot has two limits per joint (58 for a 29-joint humanoid), each a contact of
            three rows in every solve however far the joint is from its bounds. ``None``
            (default): every limit.
        max_pairs: a broad phase (static): in each group of geometry pairs that one
            vectorized collision evaluates (pairs of the same shape types and sizes), the
            narrow phase runs on the ``max_pairs`` pairs whose bounding spheres are closest
            (against a half-space: the sphere's height above its plane); the other pairs'
            manifold entries are inactive. A pair whose bounding gap exceeds its margin cannot
            touch, so this is exact while at most ``max_pairs`` pairs of a group are within
            their margin; beyond that the surplus is counted in
            :attr:`StepInfo.skipped_pairs` and reported by :func:`check_steps`. The narrow
            phase (a mesh pair's separating-axis test) is most of a scene's collision cost.
            ``None`` (default): every pair.

    Raises:
        ValueError: a time step that is not a positive, finite scalar, an unknown contact law
            or derivative mode, ``baumgarte`` outside ``[0, 1]``, a ``max_motion_per_step``
            that is not positive, a budget that is not a positive integer or ``None``, or a
            contact budget with a compliant contact law.
    """

    time_step: Array = eqx.field(converter=lambda h: jnp.asarray(h, dtype=float))
    contact: ContactLaw = "hard"
    solver: NCPSolver = NCPSolver()
    baumgarte: float = eqx.field(static=True, default=0.2)
    derivative: str = eqx.field(static=True, default="implicit")
    max_motion_per_step: float = eqx.field(static=True, default=1.0)
    max_correction_speed: float = eqx.field(static=True, default=float("inf"))
    max_contacts: int | None = eqx.field(static=True, default=None)
    max_pairs: int | None = eqx.field(static=True, default=None)
    max_limits: int | None = eqx.field(static=True, default=None)

    def __check_init__(self):
        if not _checks.is_traced(self.time_step) and np.shape(self.time_step) != ():
            raise ValueError(f"time_step must be a scalar (s), got shape {np.shape(self.time_step)}")
        _check_concrete("time_step", self.time_step, positive=True)
        if not (isinstance(self.contact, (SpringDamper, LogBarrier)) or self.contact == "hard"):
            raise ValueError(f"contact must be 'hard', a SpringDamper or a LogBarrier, got {self.contact!r}")
        if not isinstance(self.solver, NCPSolver):
            raise ValueError(f"solver must be an NCPSolver, got {self.solver!r}")
        if not 0.0 <= self.baumgarte <= 1.0:
            raise ValueError(f"baumgarte must be in [0, 1], got {self.baumgarte}")
        if self.derivative not in ("implicit", "autodiff"):
            raise ValueError(f"derivative must be 'implicit' or 'autodiff', got {self.derivative!r}")
        _check_concrete("max_motion_per_step", self.max_motion_per_step, positive=True, allow_inf=True)
        if isinstance(self.max_correction_speed, bool) or not isinstance(self.max_correction_speed, (int, float)):
            raise ValueError(f"max_correction_speed must be a Python number (m/s or rad/s), got {self.max_correction_speed!r}")
        _check_concrete("max_correction_speed", self.max_correction_speed, positive=True, allow_inf=True)
        for name in ("max_contacts", "max_pairs", "max_limits"):
            budget = getattr(self, name)
            if budget is None:
                continue
            if isinstance(budget, bool) or not isinstance(budget, (int, np.integer)) or budget < 1:
                raise ValueError(f"{name} must be a positive integer or None, got {budget!r}")
            if name != "max_pairs" and not isinstance(self.contact, str):
                raise ValueError(f"{name} budgets the hard-contact NCP: use contact='hard'")

    @property
    def correction(self) -> dict:
        """The keyword arguments of :func:`~rsmooth.sim.corrected_free_velocity` these options
        set (``baumgarte``, ``max_correction_speed``)."""
        return {"baumgarte": self.baumgarte, "max_correction_speed": self.max_correction_speed}


class JointFriction(eqx.Module):
    """Dry (Coulomb) friction on joints (MuJoCo's ``frictionloss``, a URDF's ``<dynamics
    friction>``): each dof of ``dofs`` resists its motion with an effort of at most ``effort``
    (N m or N), the most it can dissipate.

    A step solves it with the contacts, as box rows of the NCP: the impulse on dof ``k`` is
    bounded by ``|lambda_k| <= effort_k h``, opposes the dof's end-of-step velocity, and holds
    the dof still where that bound suffices (:func:`~rsmooth.sim.solve_ncp`'s ``bounds``).
    Being exact, a held joint does not creep, unlike a smoothed friction law; derivatives are
    those of the solved rows (a sticking dof's velocity is held at zero, a slipping one's
    impulse is its bound, whose derivative in ``effort`` flows).

    Attributes:
        dofs: the velocity indices with dry friction (static, distinct).
        effort: ``(len(dofs),)`` the friction effort of each, ``>= 0`` and finite.
    """

    dofs: tuple[int, ...] = eqx.field(static=True)
    effort: Array

    def __check_init__(self):
        if len(set(self.dofs)) != len(self.dofs) or not all(isinstance(d, (int, np.integer)) for d in self.dofs):
            raise ValueError(f"JointFriction.dofs must be distinct velocity indices, got {self.dofs!r}")
        if jnp.shape(self.effort) != (len(self.dofs),):
            raise ValueError(f"JointFriction.effort must have shape ({len(self.dofs)},) (one per dof), got {jnp.shape(self.effort)}")
        if not _checks.is_traced(self.effort):
            values = np.asarray(self.effort)
            if not np.all(np.isfinite(values)) or np.any(values < 0):
                raise ValueError(f"JointFriction.effort must be finite and >= 0 (N m or N), got {values}")


class JointCoupling(eqx.Module):
    """Joint equality constraints (MuJoCo's ``<equality><joint>``, what it makes of a URDF's
    ``<mimic>``): the coordinate of joint ``joints[k]`` follows a quartic of joint
    ``others[k]``'s, ``q_a = c_0 + c_1 q_b + c_2 q_b^2 + c_3 q_b^3 + c_4 q_b^4`` with ``c``
    the row ``coefficients[k]`` (``others[k] = 0``, the universe: ``q_a = c_0``). Both are
    revolute or prismatic joints, their coordinates rsmooth's (MuJoCo's less its ``qpos0``, the
    form of MuJoCo's own equation).

    A step enforces each as a bilateral row of the NCP (a box row without bounds), at the
    velocity level with the contacts' Baumgarte correction of the position error
    ``e = q_a - p(q_b)``: ``J v+ + baumgarte e / h = 0``, ``J`` the row ``e_a - p'(q_b) e_b``,
    so an error closes by the factor ``1 - baumgarte`` per step (a coupling MuJoCo makes soft,
    by its ``solref``, is hard here).

    Attributes:
        joints: the coupled joints (indices into the model's joints; static).
        others: the joints they follow, or 0 (static).
        coefficients: ``(len(joints), 5)``, ``c_0 ... c_4`` of each.
    """

    joints: tuple[int, ...] = eqx.field(static=True)
    others: tuple[int, ...] = eqx.field(static=True)
    coefficients: Array

    def __check_init__(self):
        if len(self.others) != len(self.joints):
            raise ValueError(f"JointCoupling.others must have one joint per coupled joint, got {self.others!r}")
        if jnp.shape(self.coefficients) != (len(self.joints), 5):
            raise ValueError(
                f"JointCoupling.coefficients must have shape ({len(self.joints)}, 5), got {jnp.shape(self.coefficients)}"
            )
        if not _checks.is_traced(self.coefficients) and not np.all(np.isfinite(np.asarray(self.coefficients))):
            raise ValueError("JointCoupling.coefficients must be finite")


class PointConnection(eqx.Module):
    """Ball-joint equality constraints between two bodies (MuJoCo's ``<equality><connect>``):
    the point ``anchors[k]`` of frame ``frames[k]`` stays at the point ``other_anchors[k]`` of
    frame ``others[k]`` (each in its frame's coordinates; the world's frame, 0, for a point
    fixed in the world). Closed kinematic loops (a four-bar linkage, a parallel gripper) are
    written so.

    A step enforces each as three bilateral rows of the NCP (box rows without bounds), at the
    velocity level with the contacts' Baumgarte correction of the position error ``e = p_a -
    p_b`` (world, m): ``(J_a - J_b) v+ + baumgarte e / h = 0``, ``J_a``, ``J_b`` the points'
    world velocity Jacobians, so an error closes by the factor ``1 - baumgarte`` per step (a
    connection MuJoCo makes soft, by its ``solref``, is hard here).

    Attributes:
        frames: the frames of the first points (indices into the model's frames; static).
        others: the frames of the points they are held to (static).
        anchors: ``(len(frames), 3)``, the first points in their frames (m).
        other_anchors: ``(len(frames), 3)``, the second points in theirs (m).
    """

    frames: tuple[int, ...] = eqx.field(static=True)
    others: tuple[int, ...] = eqx.field(static=True)
    anchors: Array
    other_anchors: Array

    def __check_init__(self):
        if len(self.others) != len(self.frames) or not self.frames:
            raise ValueError(
                f"PointConnection.others must have one frame per frame (at least one), got {self.frames!r} and "
                f"{self.others!r}"
            )
        for name, value in (("anchors", self.anchors), ("other_anchors", self.other_anchors)):
            if jnp.shape(value) != (len(self.frames), 3):
                raise ValueError(f"PointConnection.{name} must have shape ({len(self.frames)}, 3), got {jnp.shape(value)}")
            if not _checks.is_traced(value) and not np.all(np.isfinite(np.asarray(value))):
                raise ValueError(f"PointConnection.{name} must be finite")


class Weld(eqx.Module):
    """Weld equality constraints (MuJoCo's ``<equality><weld>``): frame ``frames[k]`` held at
    a fixed pose relative to frame ``others[k]`` (the world's frame, 0, to fix it in the world).
    Its point ``anchors[k]`` stays at the point ``other_anchors[k]`` of the other (each in its
    frame's coordinates), and its rotation turned by ``rotations[k]`` stays the other's:
    ``R_bᵀ R_a Q_k = I``.

    A step enforces each as six bilateral rows of the NCP (box rows without bounds) with the
    Baumgarte correction of the error: the points' gap ``p_a - p_b`` (world, m) as a
    :class:`PointConnection`'s, then MuJoCo's orientation error, ``torque_scale[k]`` times the
    vector part of the unit quaternion (``w >= 0``) of ``R_bᵀ R_a Q_k``, whose rate is
    ``torque_scale / 2 (w I - [v]x) R_bᵀ (omega_a - omega_b)`` (the bodies' world angular
    velocities). A weld MuJoCo makes soft, by its ``solref``, is hard here.

    Attributes:
        frames: the welded frames (indices into the model's frames; static).
        others: the frames they are welded to (static).
        anchors: ``(len(frames), 3)``, the weld points in the welded frames (m).
        other_anchors: ``(len(frames), 3)``, the same points in the other frames (m).
        rotations: ``(len(frames), 3, 3)``, the rotations ``Q``.
        torque_scale: ``(len(frames),)``, the orientation rows' scale (MuJoCo's
            ``torquescale``, > 0).
    """

    frames: tuple[int, ...] = eqx.field(static=True)
    others: tuple[int, ...] = eqx.field(static=True)
    anchors: Array
    other_anchors: Array
    rotations: Array
    torque_scale: Array

    def __check_init__(self):
        count = len(self.frames)
        if len(self.others) != count or not self.frames:
            raise ValueError(f"Weld.others must have one frame per frame (at least one), got {self.frames!r} and {self.others!r}")
        for name, value, shape in (("anchors", self.anchors, (count, 3)), ("other_anchors", self.other_anchors, (count, 3)),
                                   ("rotations", self.rotations, (count, 3, 3)), ("torque_scale", self.torque_scale, (count,))):
            if jnp.shape(value) != shape:
                raise ValueError(f"Weld.{name} must have shape {shape}, got {jnp.shape(value)}")
            if not _checks.is_traced(value) and not np.all(np.isfinite(np.asarray(value))):
                raise ValueError(f"Weld.{name} must be finite")
        if not _checks.is_traced(self.torque_scale) and np.any(np.asarray(self.torque_scale) <= 0):
            raise ValueError(f"Weld.torque_scale must be > 0, got {np.asarray(self.torque_scale)}")


class JointSprings(eqx.Module):
    """Linear springs on joints (MuJoCo's joint ``stiffness`` about its ``springref``): joint
    ``joints[k]`` is pulled towards its coordinates in ``reference`` with the stiffness
    ``stiffness[k]`` (N m/rad or N/m).

    A revolute or prismatic joint receives ``-k (q - q_ref)``; a spherical joint the torque
    ``-k w`` on its three dofs, ``w`` the rotation vector (body axes) that turns the reference
    orientation into the joint's (``q_ref^-1 q = exp(w)``, MuJoCo's ``mju_subQuat``), whose
    potential is ``k |w|^2 / 2``. The force is explicit in the step, as in MuJoCo's Euler
    integrator: a spring stiff enough that ``h sqrt(k / m) >= 2`` (with ``m`` the dof's
    inertia) makes the step unstable.

    Attributes:
        joints: the joints with a spring (indices into the model's joints; static, distinct;
            revolute, prismatic or spherical).
        stiffness: ``(len(joints),)``, ``>= 0`` and finite.
        reference: ``(nq,)``, a configuration holding every spring's rest position (its
            entries for other joints are not read).
    """

    joints: tuple[int, ...] = eqx.field(static=True)
    stiffness: Array
    reference: Array

    def __check_init__(self):
        if len(set(self.joints)) != len(self.joints) or not all(isinstance(j, (int, np.integer)) for j in self.joints):
            raise ValueError(f"JointSprings.joints must be distinct joint indices, got {self.joints!r}")
        if jnp.shape(self.stiffness) != (len(self.joints),):
            raise ValueError(
                f"JointSprings.stiffness must have shape ({len(self.joints)},) (one per joint), got {jnp.shape(self.stiffness)}"
            )
        if jnp.ndim(self.reference) != 1:
            raise ValueError(f"JointSprings.reference must be a configuration (nq,), got shape {jnp.shape(self.reference)}")
        for name, values in (("stiffness", self.stiffness), ("reference", self.reference)):
            if not _checks.is_traced(values) and not np.all(np.isfinite(np.asarray(values))):
                raise ValueError(f"JointSprings.{name} must be finite, got {np.asarray(values)}")
        if not _checks.is_traced(self.stiffness) and np.any(np.asarray(self.stiffness) < 0):
            raise ValueError(f"JointSprings.stiffness must be >= 0 (N m/rad or N/m), got {np.asarray(self.stiffness)}")


class Tendons(eqx.Module):
    """Tendons (MuJoCo's fixed and spatial tendons): their springs, dampers, dry friction and
    length limits. Tendon ``t`` has the length

    ``L_t(q) = lengths[t] . q + offsets[t]`` (fixed: linear in the coordinates of its hinges
    and slides), plus, for a spatial tendon (``spatial[k] = t``), the length of its path through
    the origins of the frames ``paths[k]`` (MuJoCo's sites): straight between consecutive
    frames, except where ``wraps`` puts a sphere or a cylinder between them, where it is the
    path that wraps around it as MuJoCo's does (``rsmooth.sim._wrapping``: the straight segment
    where that misses the shape, else two tangent segments and an arc on it, a great circle or
    a helix; a side frame picks the way round), where ``pulleys`` splits the path into branches
    (a pulley at segment ``s`` leaves out the segment between frames ``s`` and ``s + 1`` and
    divides the lengths of the segments after it, up to the next pulley, by its divisor, as
    MuJoCo's ``pulley``),

    and pulls its joints with the force ``f_t`` along its moments ``M_t(q) = dL_t/dq``
    (the generalized force ``M(q)^T f``; :meth:`RigidBodySystem.tendon_moments`):

    ``f_t = k_t (s_lo - L_t)`` below the spring's rest band ``[s_lo, s_hi]``
    (``spring_length[t]``), ``k_t (s_hi - L_t)`` above it, 0 within it (a spring about one length
    where ``s_lo = s_hi``), minus ``d_t dL_t/dt``.

    Both are explicit in the step, as in MuJoCo's Euler integrator (which is implicit in the
    joints' own damping only): a tendon stiff or damped enough for its joints' inertia makes
    the step unstable, as there. The dry friction of the tendons ``frictional`` is a box row
    of the contact problem, as a joint's (:class:`JointFriction`): the tendon does not slide
    (``dL/dt = 0`` at the step's end) while the force along it stays within ``frictionloss``
    (hard contact only; MuJoCo's friction loss is soft). A length limit is a frictionless
    contact along ``M_t`` (distance ``L_t - lower`` or ``upper - L_t``), solved with the
    contacts after the joint limits (hard contact only): a string that goes taut (dm_control's
    ball in cup). An equality holds the tendons ``equalities`` at the lengths
    ``equality_length``: a bilateral box row along ``M_t`` with MuJoCo's other equalities'
    correction (:meth:`RigidBodySystem.joint_rows`; hard contact only), e.g. a leg whose
    joints move together (dm_control's quadruped).

    Attributes:
        lengths: ``(T, nq)``, each length's coefficients on the coordinates (zero rows for
            spatial tendons).
        moments: ``(T, nv)``, the same on the velocities.
        offsets: ``(T,)``, the lengths at ``q = 0`` less the spatial paths (m or rad).
        stiffness: ``(T,)``, ``>= 0``.
        spring_length: ``(T, 2)``, the rest band, lower <= upper.
        damping: ``(T,)``, ``>= 0``.
        frictionloss: ``(T,)``, the dry friction force (N or N m along the tendon), ``>= 0``;
            read for the tendons ``frictional`` only.
        frictional: the tendons with dry friction (static, distinct indices).
        range: ``(T, 2)``, the length limits (lower, upper); read for the sides ``limits``
            name only.
        limits: the enforced length limits, ``((tendon, side), ...)`` (static): ``side`` ``+1``
            for ``range[tendon, 0]``, ``-1`` for ``range[tendon, 1]``, which must be finite.
        spatial: the spatial tendons (static, distinct indices).
        paths: for each of ``spatial``, the frames (names or indices of the model's frames,
            at least two) whose origins the tendon passes through, in order (static).
        wraps: the shapes the spatial tendons wrap around, ``((k, segment, frame, shape,
            side), ...)`` (static): between ``paths[k][segment]`` and ``paths[k][segment + 1]``
            (one shape per segment), a ``"sphere"`` or an infinite ``"cylinder"`` fixed in
            ``frame``, and the frame whose origin picks the way round (``None``: the short
            way). The side frame's origin must stay outside the shape (MuJoCo's other wrapping,
            through the shape, is not modelled).
        wrap_rotations: ``(W, 3, 3)``, each shape's orientation in its frame (a cylinder's axis
            is the third column).
        wrap_offsets: ``(W, 3)``, each shape's centre in its frame.
        wrap_radii: ``(W,)``, each shape's radius, ``> 0``.
        pulleys: the spatial tendons' pulleys, ``((k, segment), ...)`` (static): the segment of
            ``paths[k]`` that the pulley replaces (between two branches; no shape on it).
        pulley_divisors: ``(P,)``, each pulley's divisor, ``> 0``.
        equalities: the tendons held at a length (static, distinct indices).
        equality_length: ``(T,)``, their lengths, finite; read for ``equalities`` only.
    """

    lengths: Array
    moments: Array
    offsets: Array
    stiffness: Array
    spring_length: Array
    damping: Array
    frictionloss: Array | None = None
    frictional: tuple[int, ...] = eqx.field(static=True, default=())
    range: Array | None = None
    limits: tuple[tuple[int, int], ...] = eqx.field(static=True, default=())
    spatial: tuple[int, ...] = eqx.field(static=True, default=())
    paths: tuple[tuple[str | int, ...], ...] = eqx.field(static=True, default=())
    wraps: tuple[tuple[int, int, str | int, str, str | int | None], ...] = eqx.field(static=True, default=())
    wrap_rotations: Array | None = None
    wrap_offsets: Array | None = None
    wrap_radii: Array | None = None
    pulleys: tuple[tuple[int, int], ...] = eqx.field(static=True, default=())
    pulley_divisors: Array | None = None
    equalities: tuple[int, ...] = eqx.field(static=True, default=())
    equality_length: Array | None = None

    def __check_init__(self):
        count = jnp.shape(self.offsets)[0] if jnp.ndim(self.offsets) == 1 else -1
        if len(set(self.equalities)) != len(self.equalities) or not all(0 <= t < count for t in self.equalities):
            raise ValueError(f"Tendons.equalities must be distinct tendon indices in [0, {count}), got {self.equalities!r}")
        if self.equalities and (self.equality_length is None or jnp.shape(self.equality_length) != (count,)):
            shape = None if self.equality_length is None else jnp.shape(self.equality_length)
            raise ValueError(f"Tendons.equalities needs Tendons.equality_length of shape ({count},), got {shape}")
        if self.equalities and not _checks.is_traced(self.equality_length):
            if not np.all(np.isfinite(np.asarray(self.equality_length)[list(self.equalities)])):
                raise ValueError("Tendons.equality_length must be finite for the tendons held at a length")
        if len(set(self.spatial)) != len(self.spatial) or not all(0 <= t < count for t in self.spatial):
            raise ValueError(f"Tendons.spatial must be distinct tendon indices in [0, {count}), got {self.spatial!r}")
        if len(self.paths) != len(self.spatial) or any(not isinstance(p, tuple) or len(p) < 2 for p in self.paths):
            raise ValueError(
                f"Tendons.paths must hold one tuple of at least two frames per spatial tendon ({len(self.spatial)}), "
                f"got {self.paths!r}"
            )
        segments = set()
        for entry in self.wraps:
            valid = isinstance(entry, tuple) and len(entry) == 5 and isinstance(entry[0], int) and isinstance(entry[1], int)
            if not (valid and 0 <= entry[0] < len(self.paths) and 0 <= entry[1] < len(self.paths[entry[0]]) - 1):
                raise ValueError(
                    f"Tendons.wraps entries must be (k, segment, frame, shape, side) with k a spatial tendon's position "
                    f"in Tendons.spatial and segment one of its path's segments, got {entry!r}"
                )
            if entry[3] not in ("sphere", "cylinder"):
                raise ValueError(f"Tendons.wraps: shape must be 'sphere' or 'cylinder', got {entry[3]!r}")
            if entry[:2] in segments:
                raise ValueError(f"Tendons.wraps: one shape per segment, got two on {entry[:2]!r}")
            segments.add(entry[:2])
        if self.wraps:
            count_wraps = len(self.wraps)
            for name, shape in (("wrap_rotations", (count_wraps, 3, 3)), ("wrap_offsets", (count_wraps, 3)), ("wrap_radii", (count_wraps,))):
                value = getattr(self, name)
                if value is None or jnp.shape(value) != shape:
                    raise ValueError(f"Tendons.{name} must have shape {shape}, got {None if value is None else jnp.shape(value)}")
            if not _checks.is_traced(self.wrap_radii) and not np.all(np.asarray(self.wrap_radii) > 0):
                raise ValueError(f"Tendons.wrap_radii must be > 0, got {np.asarray(self.wrap_radii)}")
        for entry in self.pulleys:
            valid = isinstance(entry, tuple) and len(entry) == 2 and all(isinstance(i, int) for i in entry)
            if not (valid and 0 <= entry[0] < len(self.paths) and 0 <= entry[1] < len(self.paths[entry[0]]) - 1):
                raise ValueError(
                    f"Tendons.pulleys entries must be (k, segment) with k a spatial tendon's position in Tendons.spatial "
                    f"and segment one of its path's segments, got {entry!r}"
                )
            if entry in segments:
                raise ValueError(f"Tendons.pulleys: segment {entry!r} has a shape of Tendons.wraps, or two pulleys")
            segments.add(entry)
        if self.pulleys:
            shape = (len(self.pulleys),)
            if self.pulley_divisors is None or jnp.shape(self.pulley_divisors) != shape:
                got = None if self.pulley_divisors is None else jnp.shape(self.pulley_divisors)
                raise ValueError(f"Tendons.pulley_divisors must have shape {shape}, got {got}")
            if not _checks.is_traced(self.pulley_divisors) and not np.all(np.asarray(self.pulley_divisors) > 0):
                raise ValueError(f"Tendons.pulley_divisors must be > 0, got {np.asarray(self.pulley_divisors)}")
        if self.limits and self.range is None:
            raise ValueError("Tendons.limits needs Tendons.range")
        for entry in self.limits:
            if not (isinstance(entry, tuple) and len(entry) == 2 and 0 <= entry[0] < count and entry[1] in (1, -1)):
                raise ValueError(
                    f"Tendons.limits entries must be (tendon, side) with tendon in [0, {count}) and side +1 (lower) or "
                    f"-1 (upper), got {entry!r}"
                )
        if len(set(self.limits)) != len(self.limits):
            raise ValueError(f"Tendons.limits must be distinct, got {self.limits!r}")
        if self.range is not None:
            if jnp.shape(self.range) != (count, 2):
                raise ValueError(f"Tendons.range must have shape ({count}, 2), got {jnp.shape(self.range)}")
            if not _checks.is_traced(self.range):
                bounds = np.asarray(self.range)
                if np.any(np.isnan(bounds)) or np.any(bounds[:, 0] > bounds[:, 1]):
                    raise ValueError(f"Tendons.range must hold lower <= upper, got {bounds}")
                for tendon, side in self.limits:
                    if not np.isfinite(bounds[tendon, 0 if side > 0 else 1]):
                        which = "lower" if side > 0 else "upper"
                        raise ValueError(f"Tendons.limits: tendon {tendon} has no finite {which} limit in Tendons.range")
        if self.frictional and self.frictionloss is None:
            raise ValueError("Tendons.frictional needs Tendons.frictionloss")
        if len(set(self.frictional)) != len(self.frictional) or not all(0 <= t < count for t in self.frictional):
            raise ValueError(f"Tendons.frictional must be distinct tendon indices in [0, {count}), got {self.frictional!r}")
        checked = ("lengths", "moments", "offsets", "stiffness", "damping") + (() if self.frictionloss is None else ("frictionloss",))
        for name in checked:
            value, shape = getattr(self, name), 2 if name in ("lengths", "moments") else 1
            if jnp.ndim(value) != shape or jnp.shape(value)[0] != count:
                raise ValueError(f"Tendons.{name} must have {shape} dimension(s) and one row per tendon, got shape {jnp.shape(value)}")
        if jnp.shape(self.spring_length) != (count, 2):
            raise ValueError(f"Tendons.spring_length must have shape ({count}, 2), got {jnp.shape(self.spring_length)}")
        for name in checked + ("spring_length",):
            value = getattr(self, name)
            if not _checks.is_traced(value) and not np.all(np.isfinite(np.asarray(value))):
                raise ValueError(f"Tendons.{name} must be finite")
        for name in ("stiffness", "damping") + (() if self.frictionloss is None else ("frictionloss",)):
            value = getattr(self, name)
            if not _checks.is_traced(value) and np.any(np.asarray(value) < 0):
                raise ValueError(f"Tendons.{name} must be >= 0, got {np.asarray(value)}")
        band = self.spring_length
        if not _checks.is_traced(band) and np.any(np.asarray(band)[:, 0] > np.asarray(band)[:, 1]):
            raise ValueError(f"Tendons.spring_length must hold lower <= upper, got {np.asarray(band)}")


class GravityCompensation(eqx.Module):
    """Gravity compensation of bodies (MuJoCo's body ``gravcomp``): an upward force
    ``-masses[k] g`` at the centre of mass of body ``k``, ``masses[k]`` the part of its mass
    compensated (MuJoCo's ``gravcomp`` times ``mass``; 1: the body floats), an explicit passive
    force of the step.

    Attributes:
        frames: the frame of each body (static).
        offsets: ``(B, 3)``, the centre of mass in the frame (m).
        masses: ``(B,)``, the compensated masses (kg), finite.
    """

    frames: tuple[int, ...] = eqx.field(static=True)
    offsets: Array
    masses: Array

    def __check_init__(self):
        count = len(self.frames)
        for name, shape in (("offsets", (count, 3)), ("masses", (count,))):
            value = getattr(self, name)
            if jnp.shape(value) != shape:
                raise ValueError(f"GravityCompensation.{name} must have shape {shape}, got {jnp.shape(value)}")
            if not _checks.is_traced(value) and not np.all(np.isfinite(np.asarray(value))):
                raise ValueError(f"GravityCompensation.{name} must be finite")


class Fluid(eqx.Module):
    """Forces of a surrounding fluid on bodies (MuJoCo's inertia-box fluid model): each body is,
    for the fluid, the box of its mass with its rotational inertia (full side lengths ``box``,
    along its principal axes), and its velocity relative to the fluid, ``(omega, v)`` in those
    axes at its centre of mass (``v`` less the ``wind``), meets

    ``f = -3 pi d beta v - rho / 2 (b_y b_z |v_x| v_x, b_x b_z |v_y| v_y, b_x b_y |v_z| v_z)`` and
    ``tau = -pi d^3 beta omega - rho / 64 (b_x (b_y^4 + b_z^4) |omega_x| omega_x, ...)``,

    ``d`` the box's mean side, ``beta`` the ``viscosity`` (Stokes drag of a sphere of diameter
    ``d``), ``rho`` the ``density`` (quadratic drag on the box's faces). Explicit in the step, as
    in MuJoCo's Euler integrator: a drag strong for a body's mass (``h c / m > 2`` for a linear
    drag ``c``) makes the step unstable, as there. Reference: MuJoCo's documentation, "Fluid
    forces", inertia model.

    Attributes:
        frames: the frame of each body (static), whose principal axes and centre of mass are
            placed in it by ``rotations`` and ``offsets``.
        rotations: ``(B, 3, 3)``, the principal axes in the frame.
        offsets: ``(B, 3)``, the centre of mass in the frame (m).
        box: ``(B, 3)``, the equivalent inertia box's side lengths along the principal axes
            (m), ``>= 0``: ``sqrt(6 (I_y + I_z - I_x) / m)`` and its permutations.
        density: ``rho`` (kg/m^3), ``>= 0``.
        viscosity: ``beta`` (Pa s), ``>= 0``.
        wind: ``(3,)``, the fluid's velocity in the world (m/s).
    """

    frames: tuple[str | int, ...] = eqx.field(static=True)
    rotations: Array
    offsets: Array
    box: Array
    density: Array
    viscosity: Array
    wind: Array

    def __check_init__(self):
        count = len(self.frames)
        for name, shape in (("rotations", (count, 3, 3)), ("offsets", (count, 3)), ("box", (count, 3)), ("wind", (3,))):
            if jnp.shape(getattr(self, name)) != shape:
                raise ValueError(f"Fluid.{name} must have shape {shape}, got {jnp.shape(getattr(self, name))}")
        for name in ("rotations", "offsets", "box", "density", "viscosity", "wind"):
            value = getattr(self, name)
            if not _checks.is_traced(value) and not np.all(np.isfinite(np.asarray(value))):
                raise ValueError(f"Fluid.{name} must be finite")
        for name in ("box", "density", "viscosity"):
            value = getattr(self, name)
            if jnp.ndim(value) != (2 if name == "box" else 0):
                raise ValueError(f"Fluid.{name} must be {'(B, 3)' if name == 'box' else 'a scalar'}, got shape {jnp.shape(value)}")
            if not _checks.is_traced(value) and np.any(np.asarray(value) < 0):
                raise ValueError(f"Fluid.{name} must be >= 0, got {np.asarray(value)}")


class Geometry(eqx.Module):
    """What a system's bodies touch (:attr:`RigidBodySystem.geometry`): contact spheres of the
    kinematic tree against the world's half-spaces, and pairs of collision shapes.

    Attributes:
        sphere_frames: frame of every contact sphere (static).
        sphere_offsets: sphere centres in their frame, ``(S, 3)``.
        sphere_radii: ``(S,)``, ``>= 0``.
        plane_normals: unit normals of the half-spaces ``{p : n . p >= offset}``, ``(P, 3)``.
        plane_offsets: ``(P,)``.
        friction: Coulomb coefficient of every half-space, ``(P,)`` (hard contact).
        geom_pairs: pairs of collision shapes (:class:`GeomPair`) whose contact manifolds
            are contacts of the system, after the sphere contacts (e.g. boxes on a floor and
            on each other: :func:`~rsmooth.sim.bodies`; a pusher's finger against its box:
            :func:`~rsmooth.sim.pusher`).

    The defaults are no sphere, no half-space and no pair.
    """

    sphere_frames: tuple[int, ...] = eqx.field(static=True, default=())
    sphere_offsets: Array = eqx.field(default_factory=lambda: jnp.zeros((0, 3)))
    sphere_radii: Array = eqx.field(default_factory=lambda: jnp.zeros(0))
    plane_normals: Array = eqx.field(default_factory=lambda: jnp.zeros((0, 3)))
    plane_offsets: Array = eqx.field(default_factory=lambda: jnp.zeros(0))
    friction: Array = eqx.field(default_factory=lambda: jnp.zeros(0))
    geom_pairs: tuple[GeomPair, ...] = ()

    def __check_init__(self):
        num_spheres, num_planes = len(self.sphere_frames), jnp.shape(self.plane_normals)[0]
        if jnp.shape(self.sphere_offsets) != (num_spheres, 3) or jnp.shape(self.sphere_radii) != (num_spheres,):
            raise ValueError(
                f"sphere_offsets must have shape ({num_spheres}, 3) and sphere_radii ({num_spheres},), got "
                f"{jnp.shape(self.sphere_offsets)} and {jnp.shape(self.sphere_radii)}"
            )
        if jnp.shape(self.plane_normals) != (num_planes, 3) or jnp.shape(self.plane_offsets) != (num_planes,):
            raise ValueError("plane_normals must have shape (P, 3) and plane_offsets (P,)")
        if jnp.shape(self.friction) != (num_planes,):
            raise ValueError(f"friction must have shape ({num_planes},), got {jnp.shape(self.friction)}")
        _check_concrete("sphere_radii", self.sphere_radii)
        _check_concrete("friction", self.friction)
        if not isinstance(self.geom_pairs, tuple) or not all(isinstance(p, GeomPair) for p in self.geom_pairs):
            raise ValueError(f"geom_pairs must be a tuple of GeomPair, got {self.geom_pairs!r}")

    @property
    def num_contacts(self) -> int:
        """Candidate contacts between shapes: every sphere against every half-space, then the
        manifold entries of every pair (static)."""
        return len(self.sphere_frames) * self.plane_normals.shape[0] + sum(pair.size for pair in self.geom_pairs)


_ACTIVATION_KINDS = ("integrator", "filter", "filterexact")


class ActivationDynamics(eqx.Module):
    """MuJoCo's activation dynamics: a state ``act`` for each actuator that has one, which its
    force takes in place of its control (:class:`Servos`). With ``c`` the actuator's control
    (clipped to its range), ``h`` the time step and ``tau`` its time constant, one step is

    - ``"integrator"``: ``act+ = act + h c``;
    - ``"filter"``: ``act+ = act + h (c - act) / tau`` (MuJoCo's explicit Euler update);
    - ``"filterexact"``: ``act+ = act + (c - act) (1 - exp(-h / tau))`` (exact for a constant
      control);

    then clipped to ``act_range``. The force of the step takes ``act``, or ``act+`` where the
    actuator is ``early`` (MuJoCo's ``actearly``: no step of delay between control and force).
    The states follow the positions and velocities in the system's state, ``x = [q, v, act]``.

    Attributes:
        actuators: the actuators with a state, in increasing order (indices into the inputs;
            static).
        kinds: each one's dynamics, ``"integrator"``, ``"filter"`` or ``"filterexact"`` (static).
        early: each one's force takes the next state (static).
        time_constant: ``(na,)``, ``tau > 0`` (read by the filters).
        act_range: ``(na, 2)``, ``[-inf, inf]`` where unlimited.
    """

    actuators: tuple[int, ...] = eqx.field(static=True)
    kinds: tuple[str, ...] = eqx.field(static=True)
    early: tuple[bool, ...] = eqx.field(static=True)
    time_constant: Array
    act_range: Array

    def __check_init__(self):
        na = len(self.actuators)
        if list(self.actuators) != sorted(set(self.actuators)) or any(a < 0 for a in self.actuators):
            raise ValueError(
                f"ActivationDynamics.actuators must be distinct non-negative indices in increasing order, got {self.actuators}"
            )
        if len(self.kinds) != na or any(kind not in _ACTIVATION_KINDS for kind in self.kinds):
            raise ValueError(f"ActivationDynamics.kinds must hold one of {_ACTIVATION_KINDS} per actuator, got {self.kinds}")
        if len(self.early) != na or not all(isinstance(e, bool) for e in self.early):
            raise ValueError(f"ActivationDynamics.early must hold one bool per actuator, got {self.early}")
        if jnp.shape(self.time_constant) != (na,):
            raise ValueError(f"ActivationDynamics.time_constant must have shape ({na},), got {jnp.shape(self.time_constant)}")
        if jnp.shape(self.act_range) != (na, 2):
            raise ValueError(f"ActivationDynamics.act_range must have shape ({na}, 2), got {jnp.shape(self.act_range)}")
        _check_concrete("ActivationDynamics.time_constant", self.time_constant, positive=True)
        if not _checks.is_traced(self.act_range):
            bounds = np.asarray(self.act_range)
            if np.any(np.isnan(bounds)) or not np.all(bounds[:, 0] <= bounds[:, 1]):
                raise ValueError(f"ActivationDynamics.act_range must hold lower <= upper, got {bounds}")

    @property
    def na(self) -> int:
        """Number of states."""
        return len(self.actuators)

    def next(self, act: Array, ctrl: Array, time_step: Array) -> Array:
        """``act+`` ``(na,)`` from the states ``act`` and every actuator's clipped control ``ctrl`` ``(nu,)``."""
        dtype = act.dtype
        target = ctrl[np.asarray(self.actuators, dtype=np.int64)]
        tau = self.time_constant.astype(dtype)
        h = time_step.astype(dtype)
        kinds = np.asarray(self.kinds)
        gap = target - act
        change = jnp.where(jnp.asarray(kinds == "integrator"), h * target,
                           jnp.where(jnp.asarray(kinds == "filterexact"), -gap * jnp.expm1(-h / tau), h * gap / tau))
        return jnp.clip(act + change, self.act_range[:, 0].astype(dtype), self.act_range[:, 1].astype(dtype))

    def inputs(self, act: Array, ctrl: Array, time_step: Array) -> Array:
        """What every actuator's force takes ``(nu,)``: its clipped control ``ctrl``, or its
        state (``act``, or ``act+`` where ``early``)."""
        taken = jnp.where(jnp.asarray(self.early), self.next(act, ctrl, time_step), act)
        return ctrl.at[np.asarray(self.actuators, dtype=np.int64)].set(taken)


class Servos(eqx.Module):
    """MuJoCo's actuators of fixed gain and affine bias, as :class:`Actuation` kind
    ``"servos"`` drives them: input ``a`` (MuJoCo's control) along its moment arms ``m_a``
    applies the force

    ``f_a = clip(gain_a clip(u_a, ctrl_range_a) + b0 + b1 L_a + b2 dL_a/dt, force_range_a)``,

    ``L_a = lengths_a . q + offsets_a`` its length (``gear`` times its joint's coordinate or its
    fixed tendon's length), ``dL_a/dt = m_a . v``, ``bias_a = (b0, b1, b2)``: a motor has no
    bias, a position servo ``(0, -kp, -kv)`` with ``gain = kp`` (its control the target), a
    velocity servo ``(0, 0, -kv)`` with ``gain = kv``. The generalized force ``sum_a f_a m_a``
    is clipped per dof to ``dof_force_range`` (MuJoCo's ``actuatorfrcrange``). Explicit in the
    step, as in MuJoCo's Euler integrator (a stiff servo, ``h^2 kp / m`` or ``h kv / m`` of order
    1, makes the step unstable, as there). Where an actuator has activation dynamics
    (``dynamics``), its force takes its state in place of ``clip(u_a, ctrl_range_a)``.

    Attributes:
        gain: ``(nu,)``.
        bias: ``(nu, 3)``.
        lengths: ``(nu, nq)``, the lengths' coefficients on the coordinates.
        offsets: ``(nu,)``, the lengths at ``q = 0``.
        ctrl_range: ``(nu, 2)``, ``[-inf, inf]`` where unlimited.
        force_range: ``(nu, 2)``, likewise.
        dof_force_range: ``(nv, 2)``, likewise.
        dynamics: the actuators' states (:class:`ActivationDynamics`), or ``None``.
    """

    gain: Array
    bias: Array
    lengths: Array
    offsets: Array
    ctrl_range: Array
    force_range: Array
    dof_force_range: Array
    dynamics: ActivationDynamics | None = None

    def __check_init__(self):
        count = jnp.shape(self.gain)[0] if jnp.ndim(self.gain) == 1 else -1
        dynamics = self.dynamics
        if dynamics is not None and (not isinstance(dynamics, ActivationDynamics) or any(a >= count for a in dynamics.actuators)):
            raise ValueError(f"Servos.dynamics must be an ActivationDynamics of actuators below {count}, got {self.dynamics!r}")
        for name, shape in (("bias", (count, 3)), ("offsets", (count,)), ("ctrl_range", (count, 2)), ("force_range", (count, 2))):
            if jnp.shape(getattr(self, name)) != shape:
                raise ValueError(f"Servos.{name} must have shape {shape}, got {jnp.shape(getattr(self, name))}")
        if jnp.ndim(self.lengths) != 2 or jnp.shape(self.lengths)[0] != count:
            raise ValueError(f"Servos.lengths must have shape ({count}, nq), got {jnp.shape(self.lengths)}")
        if jnp.ndim(self.dof_force_range) != 2 or jnp.shape(self.dof_force_range)[1] != 2:
            raise ValueError(f"Servos.dof_force_range must have shape (nv, 2), got {jnp.shape(self.dof_force_range)}")
        for name in ("gain", "bias", "lengths", "offsets"):
            value = getattr(self, name)
            if not _checks.is_traced(value) and not np.all(np.isfinite(np.asarray(value))):
                raise ValueError(f"Servos.{name} must be finite")
        for name in ("ctrl_range", "force_range", "dof_force_range"):
            value = getattr(self, name)
            if not _checks.is_traced(value) and not np.all(np.asarray(value)[:, 0] <= np.asarray(value)[:, 1]):
                raise ValueError(f"Servos.{name} must hold lower <= upper, got {np.asarray(value)}")

    def clipped(self, u: Array) -> Array:
        """The controls ``(nu,)`` at the head of ``u``, clipped to their ranges."""
        dtype = u.dtype
        return jnp.clip(u[: self.gain.shape[0]], self.ctrl_range[:, 0].astype(dtype), self.ctrl_range[:, 1].astype(dtype))

    def forces(self, moments: Array, q: Array, v: Array, u: Array, time_step: Array | None = None) -> tuple[Array, Array]:
        """``(tau (nv,), clipped)``: the generalized force of controls ``u`` at ``(q, v)``, and
        whether a control was beyond its range. With :attr:`dynamics`, ``u`` holds the controls
        ``(nu,)`` followed by the states ``(na,)`` (and ``time_step`` is needed for ``early``
        actuators)."""
        dtype = q.dtype
        count = self.gain.shape[0]
        controls, ctrl = u[:count], self.clipped(u)
        taken = ctrl if self.dynamics is None else self.dynamics.inputs(u[count:], ctrl, time_step)
        moments = moments.astype(dtype)
        length = self.lengths.astype(dtype) @ q + self.offsets.astype(dtype)
        bias = self.bias.astype(dtype)
        force = self.gain.astype(dtype) * taken + bias[:, 0] + bias[:, 1] * length + bias[:, 2] * (moments @ v)
        force = jnp.clip(force, self.force_range[:, 0].astype(dtype), self.force_range[:, 1].astype(dtype))
        tau = jnp.clip(moments.T @ force, self.dof_force_range[:, 0].astype(dtype), self.dof_force_range[:, 1].astype(dtype))
        return tau, jnp.any(ctrl != controls)


class Actuation(eqx.Module):
    """How the input ``u`` drives a system (:attr:`RigidBodySystem.actuation`), in one of four
    ways (``kind``):

    - ``"joints"``: ``u`` are the efforts of the dofs ``dofs`` (joint torques).
    - ``"moments"``: ``u`` are forces along constant moment arms, the rows of ``moments``
      (``tau = moments^T u``): a fixed tendon's coefficients (a MuJoCo motor on a tendon drives
      several dofs with one input), or a unit row for a joint's own motor.
    - ``"wrench"``: ``u`` are components ``wrench_components`` of a wrench
      ``[force, torque]`` in world axes applied at the origin of frame ``wrench_frame``
      (``tau = J_frame^T w``).
    - ``"servos"``: ``u`` are the controls of MuJoCo actuators with a gain and an affine bias
      in their length and velocity (:class:`Servos`: position and velocity servos, motors),
      along the rows of ``moments`` (``gear`` times a joint's unit row or a fixed tendon's
      coefficients); the servos clip them to their control ranges (``input_limit`` is
      ``inf`` there).

    Inputs beyond ``input_limit`` are clipped to it (componentwise, symmetric) and the clip is
    reported in :class:`StepInfo`; ``+inf`` means unlimited.

    Attributes:
        kind: ``"joints"``, ``"moments"``, ``"wrench"`` or ``"servos"`` (static).
        dofs: velocity indices driven by ``u`` (``"joints"``; static).
        moments: ``(nu, nv)`` moment arms of the inputs (``"moments"``, ``"servos"``), finite.
        servos: the actuators' law (:class:`Servos`; ``"servos"`` only).
        wrench_frame: frame index of the applied wrench (``"wrench"``; static).
        wrench_components: which of ``[fx, fy, fz, tx, ty, tz]`` ``u`` holds (``"wrench"``; static).
        input_limit: ``(nu,)`` symmetric bounds on ``u``, ``> 0``.
        gravity_compensation: the actuated dofs also receive the efforts that hold the
            system against gravity at its configuration (their entries of
            :func:`~rsmooth.sim.gravity_torques`), as the controller of a torque-controlled
            arm adds them (Franka's does): ``u`` is then the effort beyond gravity's, and
            ``input_limit`` bounds ``u``, not the sum (static; ``kind="joints"`` only).
            Its derivative with respect to the configuration is part of the step's. See
            :meth:`RigidBodySystem.with_gravity_compensation`.
    """

    kind: str = eqx.field(static=True)
    input_limit: Array
    dofs: tuple[int, ...] = eqx.field(static=True, default=())
    wrench_frame: int = eqx.field(static=True, default=0)
    wrench_components: tuple[int, ...] = eqx.field(static=True, default=())
    gravity_compensation: bool = eqx.field(static=True, default=False)
    moments: Array | None = None
    servos: Servos | None = None

    def __check_init__(self):
        if self.kind not in ("joints", "moments", "wrench", "servos"):
            raise ValueError(f"actuation kind must be 'joints', 'moments', 'wrench' or 'servos', got {self.kind!r}")
        if (self.kind in ("moments", "servos")) != (self.moments is not None):
            raise ValueError("actuation moments are given with kind 'moments' or 'servos', and only then")
        if (self.kind == "servos") != isinstance(self.servos, Servos):
            raise ValueError("actuation servos (a Servos) are given with kind 'servos', and only then")
        if self.servos is not None and jnp.shape(self.servos.gain)[0] != jnp.shape(self.moments)[0]:
            raise ValueError(
                f"actuation servos must have one entry per input ({jnp.shape(self.moments)[0]}), got "
                f"{jnp.shape(self.servos.gain)[0]}"
            )
        if self.moments is not None:
            if jnp.ndim(self.moments) != 2:
                raise ValueError(f"actuation moments must have shape (nu, nv), got {jnp.shape(self.moments)}")
            if not _checks.is_traced(self.moments) and not np.all(np.isfinite(np.asarray(self.moments))):
                raise ValueError("actuation moments must be finite")
        if jnp.shape(self.input_limit) != (self.nu,):
            raise ValueError(f"input_limit must have shape ({self.nu},), got {jnp.shape(self.input_limit)}")
        _check_concrete("input_limit", self.input_limit, positive=True, allow_inf=True)
        if any(c not in range(6) for c in self.wrench_components):
            raise ValueError(f"wrench_components must be in 0..5, got {self.wrench_components}")
        if not isinstance(self.gravity_compensation, bool):
            raise TypeError(f"gravity_compensation must be a bool, got {self.gravity_compensation!r}")
        if self.gravity_compensation and self.kind != "joints":
            raise ValueError("gravity_compensation adds efforts to the actuated dofs: it needs actuation kind 'joints'")

    @property
    def nu(self) -> int:
        """Input dimension."""
        if self.kind in ("moments", "servos"):
            return jnp.shape(self.moments)[0]
        return len(self.dofs) if self.kind == "joints" else len(self.wrench_components)


class Joints(eqx.Module):
    """What acts on a system's joints besides its inertia and input
    (:attr:`RigidBodySystem.joints`); by default nothing.

    Attributes:
        damping: viscous damping ``(nv,)`` (N m s/rad or N s/m) of each dof, ``>= 0``,
            integrated implicitly; ``None`` for none. It bounds the speed a constant torque
            gives a free joint (``tau / d``), which explicit velocity-product (Coriolis)
            terms otherwise let grow until the step diverges.
        limits: position limits enforced as unilateral constraints, ``((dof, side),
            ...)`` (static): ``dof`` the velocity index of a revolute or prismatic joint,
            ``side`` ``+1`` for its :attr:`Model.lower_position_limit` and ``-1`` for its upper
            one, which must be finite; or ``dof`` the first velocity index of a spherical
            joint and ``side`` 0 for its cone limit (:attr:`Model.upper_position_limit`). Each
            is a frictionless contact after the geometry pairs (distance ``q - lower`` or
            ``upper - q``, in rad or m; for a cone, the largest angle minus the joint's
            rotation angle, its normal the rotation's axis, as MuJoCo's ball-joint range),
            solved with the contacts in one NCP (hard contact only). The cone's normal turns
            with the twist about the body's own axis: a body resting on its cone whose
            inertia about that axis is far below the others (a thin rod, 1:440) can be
            unstable at 10 ms steps, as in MuJoCo. :meth:`RigidBodySystem.with_joint_limits`
            lists a model's finite limits. Empty by default: a model's limits are not
            enforced unless asked.
        friction: dry friction on joints (:class:`JointFriction`), solved with the
            contacts (hard contact only); ``None``: none. See
            :meth:`RigidBodySystem.with_joint_friction`.
        couplings: joint equality constraints (:class:`JointCoupling`), solved with the
            contacts (hard contact only); ``None``: none.
        connections: ball-joint equality constraints between frames (:class:`PointConnection`),
            solved with the contacts (hard contact only); ``None``: none.
        welds: weld equality constraints between frames (:class:`Weld`), solved with the
            contacts (hard contact only); ``None``: none.
        springs: linear springs on joints (:class:`JointSprings`), explicit forces of
            the free motion; ``None``: none. See :meth:`RigidBodySystem.with_joint_springs`.
        tendons: springs and dampers along fixed and spatial tendons (:class:`Tendons`),
            explicit forces of the free motion, and their dry friction and length limits,
            solved with the contacts (hard contact only); ``None``: none.
        gravcomp: gravity compensation of bodies (:class:`GravityCompensation`, MuJoCo's
            ``gravcomp``), explicit forces of the free motion; ``None``: none.
        fluid: the forces of a surrounding fluid on the bodies (:class:`Fluid`), explicit
            forces of the free motion; ``None``: none.
    """

    damping: Array | None = None
    limits: tuple[tuple[int, int], ...] = eqx.field(static=True, default=())
    friction: JointFriction | None = None
    couplings: JointCoupling | None = None
    connections: PointConnection | None = None
    welds: Weld | None = None
    springs: JointSprings | None = None
    tendons: Tendons | None = None
    gravcomp: GravityCompensation | None = None
    fluid: Fluid | None = None

    def __check_init__(self):
        if self.damping is not None and not _checks.is_traced(self.damping) and np.any(np.asarray(self.damping) < 0):
            raise ValueError("joints.damping must be non-negative")
        for name, value, kind in (
            ("friction", self.friction, JointFriction), ("couplings", self.couplings, JointCoupling),
            ("connections", self.connections, PointConnection), ("welds", self.welds, Weld),
            ("springs", self.springs, JointSprings), ("tendons", self.tendons, Tendons), ("fluid", self.fluid, Fluid),
            ("gravcomp", self.gravcomp, GravityCompensation),
        ):
            if value is not None and not isinstance(value, kind):
                raise ValueError(f"joints.{name} must be a {kind.__name__} or None, got {value!r}")


class RigidBodySystem(eqx.Module):
    """A kinematic tree with contacts, stepped in time: data in five parts plus a start.

    Build one with the factories :func:`~rsmooth.sim.cube`, :func:`~rsmooth.sim.box`,
    :func:`~rsmooth.sim.ball`, :func:`~rsmooth.sim.ball_wall`, :func:`~rsmooth.sim.pusher`,
    :func:`~rsmooth.sim.solo12`, :func:`~rsmooth.sim.bodies`, :func:`~rsmooth.sim.scene` (or
    directly, for a new robot); the ``with_*`` methods change one part (:meth:`with_options`,
    :meth:`with_joint_limits`, :meth:`with_joint_friction`, :meth:`with_joint_springs`,
    :meth:`with_joint_couplings`, :meth:`with_tendons`, :meth:`with_contact_budget`,
    :meth:`with_gravity_compensation`); :meth:`initial_state` is
    the state each factory defines as the start.

    Attributes:
        model: the kinematic tree (:class:`~rsmooth.sim.Model`).
        geometry: what the bodies touch (:class:`Geometry`).
        actuation: how ``u`` drives the system (:class:`Actuation`).
        options: the time step, the contact law and its solver, the contact budgets, the
            derivative mode (:class:`Options`); ``time_step``, ``contact``, ``solver``,
            ``baumgarte``, ``derivative`` and ``max_motion_per_step`` read them on the system
            too.
        joints: damping, limits, dry friction, couplings and springs of the joints
            (:class:`Joints`; none by default).
        initial_configuration: the configuration ``q`` ``(nq,)`` that :meth:`initial_state`
            starts from, set by each factory (e.g. a cube resting on its floor); ``None``: the
            model's neutral configuration.
    """

    model: Model
    geometry: Geometry
    actuation: Actuation
    options: Options
    joints: Joints = Joints()
    initial_configuration: Array | None = None

    def __check_init__(self):
        model, joints = self.model, self.joints
        for name, value, kind in (
            ("geometry", self.geometry, Geometry), ("actuation", self.actuation, Actuation),
            ("options", self.options, Options), ("joints", joints, Joints),
        ):
            if not isinstance(value, kind):
                article = "an" if kind.__name__[0] in "AEIOU" else "a"
                raise ValueError(f"{name} must be {article} {kind.__name__}, got {value!r}")
        if self.initial_configuration is not None and jnp.shape(self.initial_configuration) != (model.nq,):
            raise ValueError(
                f"initial_configuration must have shape (nq,) = ({model.nq},), got {jnp.shape(self.initial_configuration)}"
            )
        for frame in self.geometry.sphere_frames:
            model.frame_id(frame)
        for index, pair in enumerate(self.geometry.geom_pairs):
            for name, frame in (("frame1", pair.frame1), ("frame2", pair.frame2)):
                if frame is not None:
                    try:
                        model.frame_id(frame)
                    except ValueError as error:
                        raise ValueError(f"geom_pairs[{index}].{name}: {error}") from None
        for dof in self.actuation.dofs:
            if not 0 <= dof < model.nv:
                raise ValueError(f"actuated dof {dof} out of range [0, {model.nv})")
        if self.actuation.kind == "wrench":
            model.frame_id(self.actuation.wrench_frame)
        if self.actuation.kind == "servos" and (
            jnp.shape(self.actuation.servos.lengths)[1] != model.nq or jnp.shape(self.actuation.servos.dof_force_range)[0] != model.nv
        ):
            raise ValueError(
                f"actuation servos must have lengths (nu, nq = {model.nq}) and dof_force_range (nv = {model.nv}, 2), got "
                f"{jnp.shape(self.actuation.servos.lengths)} and {jnp.shape(self.actuation.servos.dof_force_range)}"
            )
        if self.actuation.kind in ("moments", "servos") and jnp.shape(self.actuation.moments)[1] != model.nv:
            raise ValueError(
                f"actuation moments must have shape (nu, nv) = ({self.actuation.nu}, {model.nv}), got "
                f"{jnp.shape(self.actuation.moments)}"
            )
        hard = isinstance(self.contact, str)
        if joints.damping is not None and jnp.shape(joints.damping) != (model.nv,):
            raise ValueError(f"joints.damping must have shape ({model.nv},), got {jnp.shape(joints.damping)}")
        _limit_rows(model, joints.limits)  # raises on a bad entry
        tendon_friction = joints.tendons is not None and bool(joints.tendons.frictional)
        tendon_limits = joints.tendons is not None and bool(joints.tendons.limits)
        tendon_equalities = joints.tendons is not None and bool(joints.tendons.equalities)
        for name, present in (
            ("limits", joints.limits), ("friction", joints.friction), ("couplings", joints.couplings),
            ("connections", joints.connections), ("welds", joints.welds),
            ("tendons' friction", tendon_friction), ("tendons' limits", tendon_limits),
            ("tendons' equalities", tendon_equalities),
        ):
            if present and not hard:
                raise ValueError(f"joints.{name} are solved by the hard-contact NCP: use contact='hard'")
        if joints.friction is not None:
            bad = [d for d in joints.friction.dofs if not 0 <= d < model.nv]
            if bad:
                raise ValueError(f"joints.friction.dofs {bad} out of range [0, {model.nv})")
        if joints.couplings is not None:
            types = model.joint_types
            for joint, other in zip(joints.couplings.joints, joints.couplings.others):
                for index, allowed in ((joint, (REVOLUTE, PRISMATIC)), (other, (UNIVERSE, REVOLUTE, PRISMATIC))):
                    if not 0 <= index < len(types) or types[index] not in allowed:
                        raise ValueError(
                            f"joints.couplings: joint {index} must be a revolute or prismatic joint of the model"
                            f"{' (or 0)' if UNIVERSE in allowed else ''}"
                        )
        for name, held in (("connections", joints.connections), ("welds", joints.welds)):
            frames = len(model.frame_names)
            bad = [] if held is None else [f for f in held.frames + held.others if not 0 <= f < frames]
            if bad:
                raise ValueError(f"joints.{name}: frames {bad} out of range [0, {frames})")
        if joints.springs is not None:
            types = model.joint_types
            bad = [j for j in joints.springs.joints if not 0 <= j < len(types) or types[j] not in _SPRING_TYPES]
            if bad:
                raise ValueError(f"joints.springs: joints {bad} are not revolute, prismatic or spherical joints of the model")
            if jnp.shape(joints.springs.reference) != (model.nq,):
                raise ValueError(
                    f"joints.springs.reference must have shape (nq,) = ({model.nq},), got "
                    f"{jnp.shape(joints.springs.reference)}"
                )
        if joints.tendons is not None:
            for name, width in (("lengths", model.nq), ("moments", model.nv)):
                if jnp.shape(getattr(joints.tendons, name))[1] != width:
                    raise ValueError(
                        f"joints.tendons.{name} must have shape (T, {width}) for this model, got "
                        f"{jnp.shape(getattr(joints.tendons, name))}"
                    )
            for tendon, path in zip(joints.tendons.spatial, joints.tendons.paths):
                for frame in path:
                    try:
                        model.frame_id(frame)
                    except ValueError as error:
                        raise ValueError(f"joints.tendons.paths (tendon {tendon}): {error}") from None
            for entry in joints.tendons.wraps:
                for frame in entry[2:3] + (() if entry[4] is None else entry[4:5]):
                    try:
                        model.frame_id(frame)
                    except ValueError as error:
                        raise ValueError(f"joints.tendons.wraps {entry!r}: {error}") from None
        for name, part in (("fluid", joints.fluid), ("gravcomp", joints.gravcomp)):
            for frame in () if part is None else part.frames:
                try:
                    model.frame_id(frame)
                except ValueError as error:
                    raise ValueError(f"joints.{name}.frames: {error}") from None

    # -- options ------------------------------------------------------------------------

    @property
    def time_step(self) -> Array:
        """``options.time_step``: ``h`` (s)."""
        return self.options.time_step

    @property
    def contact(self) -> ContactLaw:
        """``options.contact``: the contact law."""
        return self.options.contact

    @property
    def solver(self) -> NCPSolver:
        """``options.solver``: the NCP solver configuration (hard contact)."""
        return self.options.solver

    @property
    def baumgarte(self) -> float:
        """``options.baumgarte``: the penetration correction rate (hard contact)."""
        return self.options.baumgarte

    @property
    def derivative(self) -> str:
        """``options.derivative``: ``"implicit"`` or ``"autodiff"``."""
        return self.options.derivative

    @property
    def max_motion_per_step(self) -> float:
        """``options.max_motion_per_step``: the divergence bound on ``|v+| h``."""
        return self.options.max_motion_per_step

    def with_options(self, **changes) -> "RigidBodySystem":
        """The same system with some of its :class:`Options` changed, e.g.
        ``system.with_options(solver=NCPSolver(max_iterations=2000), derivative="autodiff")``.

        Raises:
            TypeError: a name that is not a field of :class:`Options`.
            ValueError: a value :class:`Options` or the system refuses.
        """
        fields = {field.name for field in dataclasses.fields(Options)}
        unknown = sorted(set(changes) - fields)
        if unknown:
            raise TypeError(f"with_options takes the fields of Options ({', '.join(sorted(fields))}), got {unknown}")
        return dataclasses.replace(self, options=dataclasses.replace(self.options, **changes))

    # -- sizes and state layout -------------------------------------------------------

    @property
    def nx(self) -> int:
        """State dimension ``nq + nv + na`` (``x = [q, v, act]``; ``na = 0`` but for
        actuators with activation dynamics)."""
        return self.model.nq + self.model.nv + self.na

    @property
    def na(self) -> int:
        """Number of actuator states (:class:`ActivationDynamics`), which end the state."""
        dynamics = self._activation_dynamics
        return 0 if dynamics is None else dynamics.na

    @property
    def _activation_dynamics(self) -> ActivationDynamics | None:
        return self.actuation.servos.dynamics if self.actuation.servos is not None else None

    @property
    def nu(self) -> int:
        """Input dimension."""
        return self.actuation.nu

    @property
    def num_contacts(self) -> int:
        """Number of candidate contacts: every sphere against every half-space, then the
        manifold entries of every geometry pair, then the joint limits."""
        return self.geometry.num_contacts + self.num_limits

    @property
    def num_limits(self) -> int:
        """The candidate contacts that are limits, the last of :meth:`contacts`: the joint
        limits (:attr:`Joints.limits`), then the tendons' (:attr:`Tendons.limits`)."""
        tendons = self.joints.tendons
        return len(self.joints.limits) + (0 if tendons is None else len(tendons.limits))

    def _with_joints(self, **changes) -> "RigidBodySystem":
        return dataclasses.replace(self, joints=dataclasses.replace(self.joints, **changes))

    def with_joint_friction(self, effort: ArrayLike | None) -> "RigidBodySystem":
        """This system with dry friction on its joints (:attr:`Joints.friction`).

        Args:
            effort: ``(nv,)``, the friction effort of every dof (N m or N), ``>= 0``; the dofs
                where it is zero get none (and no row in the solve). ``None``: no friction.

        Raises:
            ValueError: on a wrong shape or a negative or non-finite value (naming the dofs),
                or a compliant contact law.
        """
        if effort is None:
            return self._with_joints(friction=None)
        values = np.asarray(effort, dtype=np.float64)
        if values.shape != (self.model.nv,):
            raise ValueError(f"effort must have shape (nv,) = ({self.model.nv},), got {values.shape}")
        bad = np.flatnonzero(~np.isfinite(values) | (values < 0))
        if bad.size:
            raise ValueError(f"effort must be finite and >= 0 (N m or N); dofs {bad.tolist()} have {values[bad].tolist()}")
        dofs = np.flatnonzero(values > 0)
        if dofs.size == 0:
            return self._with_joints(friction=None)
        friction = JointFriction(tuple(int(d) for d in dofs), device_array(values[dofs]))
        return self._with_joints(friction=friction)

    def with_joint_couplings(self, couplings: JointCoupling | None) -> "RigidBodySystem":
        """This system with the joint equality constraints ``couplings`` (:attr:`Joints.couplings`;
        ``None``: none), e.g. a loaded model's :attr:`~rsmooth.sim.MujocoModel.joint_couplings`.

        Raises:
            ValueError: a joint that is not a revolute or prismatic joint of the model, or a
                compliant contact law.
        """
        return self._with_joints(couplings=couplings)

    def with_connections(self, connections: PointConnection | None) -> "RigidBodySystem":
        """This system with the ball-joint equality constraints ``connections``
        (:attr:`Joints.connections`; ``None``: none), e.g. a loaded model's
        :attr:`~rsmooth.sim.MujocoModel.connections`.

        Raises:
            ValueError: a frame that is not the model's, or a compliant contact law.
        """
        return self._with_joints(connections=connections)

    def with_welds(self, welds: Weld | None) -> "RigidBodySystem":
        """This system with the weld equality constraints ``welds`` (:attr:`Joints.welds`;
        ``None``: none), e.g. a loaded model's :attr:`~rsmooth.sim.MujocoModel.welds`.

        Raises:
            ValueError: a frame that is not the model's, or a compliant contact law.
        """
        return self._with_joints(welds=welds)

    def with_gravcomp(self, gravcomp: GravityCompensation | None) -> "RigidBodySystem":
        """This system with the gravity compensation ``gravcomp`` of its bodies
        (:attr:`Joints.gravcomp`; ``None``: none), e.g. a loaded model's
        :attr:`~rsmooth.sim.MujocoModel.gravcomp`.

        Raises:
            ValueError: if a frame of ``gravcomp`` is not the model's.
        """
        return self._with_joints(gravcomp=gravcomp)

    def with_fluid(self, fluid: Fluid | None) -> "RigidBodySystem":
        """This system in the fluid ``fluid`` (:attr:`Joints.fluid`; ``None``: none), e.g. a
        loaded model's :attr:`~rsmooth.sim.MujocoModel.fluid`.

        Raises:
            ValueError: if a frame of ``fluid`` is not the model's.
        """
        return self._with_joints(fluid=fluid)

    def with_tendons(self, tendons: Tendons | None) -> "RigidBodySystem":
        """This system with the tendons ``tendons`` (:attr:`Joints.tendons`, their springs,
        dampers, dry friction and length limits; ``None``: none), e.g. a loaded model's
        :attr:`~rsmooth.sim.MujocoModel.tendons`.

        Raises:
            ValueError: if ``tendons`` does not fit the model (its ``(T, nq)`` lengths,
                ``(T, nv)`` moments and the frames of its spatial paths), or has limits, dry
                friction or equalities under a compliant contact law.
        """
        return self._with_joints(tendons=tendons)

    def with_joint_springs(self, stiffness: ArrayLike | None, reference: ArrayLike | None = None) -> "RigidBodySystem":
        """This system with linear springs on its joints (:attr:`Joints.springs`).

        Args:
            stiffness: ``(nv,)``, the stiffness of every dof (N m/rad or N/m), ``>= 0``; zero
                on a free flyer's dofs, and equal on a spherical joint's three (its spring is
                isotropic). The joints whose stiffness is zero get no spring. ``None``: none.
            reference: ``(nq,)``, the configuration at which every spring is at rest;
                ``None``: zero joint positions and identity orientations.

        Raises:
            ValueError: on a wrong shape, a negative or non-finite value, a stiffness on a
                free flyer or unequal on a spherical joint's dofs (naming the joint).

        Example:
            >>> import numpy as np, rsmooth.sim as sim
            >>> system = sim.scene("<mujoco><worldbody><body><joint name='hinge'/>"
            ...                    "<geom size='0.1' mass='1'/></body></worldbody></mujoco>")
            >>> system = system.with_joint_springs(np.array([2.0]))
            >>> float(system.spring_forces(jnp.array([0.5]))[0])
            -1.0
        """
        if stiffness is None:
            return self._with_joints(springs=None)
        model = self.model
        values = np.asarray(stiffness, dtype=np.float64)
        if values.shape != (model.nv,):
            raise ValueError(f"stiffness must have shape (nv,) = ({model.nv},), got {values.shape}")
        bad = np.flatnonzero(~np.isfinite(values) | (values < 0))
        if bad.size:
            raise ValueError(f"stiffness must be finite and >= 0 (N m/rad or N/m); dofs {bad.tolist()} have {values[bad].tolist()}")
        if reference is None:
            reference = np.zeros(model.nq)
            reference[_dynamics._tree(model).rotation_q + 3] = 1.0  # [x, y, z, w] = identity
            reference = device_array(reference)
        reference = jnp.asarray(reference)
        if reference.shape != (model.nq,):
            raise ValueError(f"reference must have shape (nq,) = ({model.nq},), got {reference.shape}")
        joints, per_joint = [], []
        for joint, (name, kind) in enumerate(zip(model.joint_names, model.joint_types)):
            dofs = values[model.idx_v[joint] : model.idx_v[joint] + JOINT_NV[kind]]
            if not np.any(dofs > 0):
                continue
            if kind not in _SPRING_TYPES:
                raise ValueError(f"stiffness: joint {name!r} is a {kind}; springs are on revolute, prismatic and spherical joints")
            if np.ptp(dofs) != 0:
                raise ValueError(f"stiffness: the spherical joint {name!r} has unequal stiffness {dofs.tolist()} on its dofs")
            joints.append(joint)
            per_joint.append(dofs[0])
        if not joints:
            return self._with_joints(springs=None)
        springs = JointSprings(tuple(joints), device_array(np.asarray(per_joint)), reference)
        return self._with_joints(springs=springs)

    def _spring_displacements(self, q: Array) -> tuple[np.ndarray, Array, Array]:
        """The springs per dof: ``(dofs (d,), stiffness (d,), displacement (d,))``, the
        displacement ``q - q_ref`` (revolute, prismatic; one batched expression for all) or the
        rotation vector of ``q_ref^-1 q`` (spherical, three dofs sharing one stiffness)."""
        model, springs = self.model, self.joints.springs
        reference, stiffness = springs.reference.astype(q.dtype), springs.stiffness.astype(q.dtype)
        scalar = [k for k, joint in enumerate(springs.joints) if model.joint_types[joint] != SPHERICAL]
        q_index = np.array([model.idx_q[springs.joints[k]] for k in scalar], dtype=np.int64)
        dofs = [np.array([model.idx_v[springs.joints[k]] for k in scalar], dtype=np.int64)]
        stiffnesses, displacements = [stiffness[np.array(scalar, dtype=np.int64)]], [q[q_index] - reference[q_index]]
        for k, joint in enumerate(springs.joints):
            if model.joint_types[joint] != SPHERICAL:
                continue
            start_q, start_v = model.idx_q[joint], model.idx_v[joint]
            quaternion = q[start_q : start_q + 4]
            quaternion = quaternion / jnp.sqrt(spatial.dot3(quaternion, quaternion) + quaternion[3] ** 2)
            relative = spatial.quaternion_multiply(spatial.quaternion_conjugate(reference[start_q : start_q + 4]), quaternion)
            dofs.append(np.arange(start_v, start_v + 3))
            stiffnesses.append(jnp.repeat(stiffness[k], 3))
            displacements.append(spatial.quaternion_log(relative))
        return np.concatenate(dofs), jnp.concatenate(stiffnesses), jnp.concatenate(displacements)

    def spring_forces(self, q: Array) -> Array:
        """The generalized forces ``(nv,)`` of :attr:`Joints.springs` and of the tendons'
        springs (:attr:`Joints.tendons`) at ``q`` (zeros without)."""
        return self._spring_forces(q, None)

    def passive_forces(self, q: Array, v: Array) -> Array:
        """The explicit passive forces ``(nv,)`` of a step from ``(q, v)``: :meth:`spring_forces`,
        the tendons' damping, ``-M^T d (M v)`` (:attr:`Joints.tendons`, ``M`` their
        :meth:`tendon_moments`), :meth:`fluid_forces` and :meth:`gravcomp_forces`."""
        forces = self._spring_forces(q, v)
        if self.joints.fluid is not None:
            forces = forces + self.fluid_forces(q, v)
        if self.joints.gravcomp is not None:
            forces = forces + self.gravcomp_forces(q)
        return forces

    def gravcomp_forces(self, q: Array) -> Array:
        """The generalized forces ``(nv,)`` of :attr:`Joints.gravcomp` at ``q`` (zeros
        without): ``-m_k g`` at each compensated body's centre of mass."""
        gravcomp, model = self.joints.gravcomp, self.model
        if gravcomp is None:
            return jnp.zeros(model.nv, q.dtype)
        kinematics = _dynamics._kinematics(model, q)
        ids = [model.frame_id(frame) for frame in gravcomp.frames]
        placements = [_dynamics._frame_placement(model, kinematics.rotation, kinematics.translation, i) for i in ids]
        centres = jnp.stack([rotation @ offset + translation for (rotation, translation), offset
                             in zip(placements, gravcomp.offsets.astype(q.dtype))])
        linear = _dynamics._point_velocity_columns(model, kinematics, np.asarray(model.frame_parents)[ids], centres)
        forces = -gravcomp.masses.astype(q.dtype)[:, None] * model.gravity.astype(q.dtype)[None, :]  # (B, 3)
        return jnp.einsum("bni,bi->n", linear, forces)

    def _spring_forces(self, q: Array, v: Array | None) -> Array:
        """:meth:`spring_forces`, plus the tendons' damping where ``v`` is given: one
        evaluation of the tendons' geometry for both."""
        forces = jnp.zeros(self.model.nv, q.dtype)
        if self.joints.springs is not None:
            dofs, stiffness, displacement = self._spring_displacements(q)
            forces = forces.at[dofs].set(-stiffness * displacement)
        tendons = self.joints.tendons
        if tendons is not None:
            length, moments = self._tendon_geometry(q)
            along = self._tendon_stretch(length) * tendons.stiffness.astype(q.dtype)
            if v is not None:
                along = along + tendons.damping.astype(q.dtype) * (moments @ v)
            forces = forces - along @ moments
        return forces

    def fluid_forces(self, q: Array, v: Array) -> Array:
        """The generalized forces ``(nv,)`` of :attr:`Joints.fluid` at ``(q, v)`` (zeros
        without): each body's force and torque (:class:`Fluid`) at its centre of mass."""
        fluid, model = self.joints.fluid, self.model
        if fluid is None:
            return jnp.zeros(model.nv, q.dtype)
        kinematics = _dynamics._kinematics(model, q)
        ids = [model.frame_id(frame) for frame in fluid.frames]
        joints = np.asarray(model.frame_parents)[ids]
        placements = [_dynamics._frame_placement(model, kinematics.rotation, kinematics.translation, i) for i in ids]
        rotation, translation = jnp.stack([p[0] for p in placements]), jnp.stack([p[1] for p in placements])
        axes = rotation @ fluid.rotations.astype(q.dtype)  # (B, 3, 3): principal axes in the world
        centres = translation + jnp.einsum("bij,bj->bi", rotation, fluid.offsets.astype(q.dtype))
        linear = _dynamics._point_velocity_columns(model, kinematics, joints, centres)  # (B, nv, 3)
        angular = _dynamics._support_columns(model, kinematics, joints)[..., 3:]  # (B, nv, 3)
        # velocities relative to the fluid in the principal axes
        omega = jnp.einsum("bij,bni,n->bj", axes, angular, v)
        velocity = jnp.einsum("bij,bni,n->bj", axes, linear, v) - jnp.einsum("bij,i->bj", axes, fluid.wind.astype(q.dtype))
        box, rho, beta = fluid.box.astype(q.dtype), fluid.density.astype(q.dtype), fluid.viscosity.astype(q.dtype)
        diameter = jnp.mean(box, axis=-1, keepdims=True)
        others = jnp.stack([box[:, 1] * box[:, 2], box[:, 0] * box[:, 2], box[:, 0] * box[:, 1]], axis=-1)
        fourth = box**4
        spans = jnp.stack([fourth[:, 1] + fourth[:, 2], fourth[:, 0] + fourth[:, 2], fourth[:, 0] + fourth[:, 1]], axis=-1)
        force = -3.0 * jnp.pi * diameter * beta * velocity - 0.5 * rho * others * jnp.abs(velocity) * velocity
        torque = -jnp.pi * diameter**3 * beta * omega - rho / 64.0 * box * spans * jnp.abs(omega) * omega
        world_force, world_torque = jnp.einsum("bij,bj->bi", axes, force), jnp.einsum("bij,bj->bi", axes, torque)
        return jnp.einsum("bni,bi->n", linear, world_force) + jnp.einsum("bni,bi->n", angular, world_torque)

    def tendon_lengths(self, q: Array) -> Array:
        """The lengths ``(T,)`` of :attr:`Joints.tendons` at ``q`` (empty without)."""
        if self.joints.tendons is None:
            return jnp.zeros(0, q.dtype)
        return self._tendon_geometry(q)[0]

    def tendon_moments(self, q: Array) -> Array:
        """The moments ``(T, nv)`` of :attr:`Joints.tendons` at ``q``, the derivative of their
        lengths in the velocities (MuJoCo's ``ten_J``; constant for fixed tendons)."""
        if self.joints.tendons is None:
            return jnp.zeros((0, self.model.nv), q.dtype)
        return self._tendon_geometry(q)[1]

    def _tendon_geometry(self, q: Array, kinematics=None) -> tuple[Array, Array]:
        """The tendons' lengths ``(T,)`` and moments ``(T, nv)`` at ``q``."""
        tendons, model = self.joints.tendons, self.model
        length = tendons.lengths.astype(q.dtype) @ q + tendons.offsets.astype(q.dtype)
        moments = tendons.moments.astype(q.dtype)
        if not tendons.spatial:
            return length, moments
        if kinematics is None:
            kinematics = _dynamics._kinematics(model, q)
        wraps = {entry[:2]: (w, entry) for w, entry in enumerate(tendons.wraps)}
        pulleys = {entry: p for p, entry in enumerate(tendons.pulleys)}
        parents = np.asarray(model.frame_parents)

        for k, (tendon, path) in enumerate(zip(tendons.spatial, tendons.paths)):
            ids = [model.frame_id(frame) for frame in path]
            sites = [self._frame_origin(kinematics, frame)[1] for frame in path]
            # the path as a polyline (a wrap adds its two tangent points, fixed on the shape's
            # body; their chord has no rate, and the arc replaces it in the length)
            points, joints, arcs = [sites[0]], [parents[ids[0]]], []
            # each polyline segment's share of the length: 0 across a pulley, 1 / the divisor of
            # the last pulley before it
            share, shares = jnp.ones((), q.dtype), []
            for segment in range(len(path) - 1):
                if (k, segment) in pulleys:
                    share = 1.0 / tendons.pulley_divisors[pulleys[(k, segment)]].astype(q.dtype)
                    shares.append(jnp.zeros((), q.dtype))
                else:
                    shares += [share] * (3 if (k, segment) in wraps else 1)
                if (k, segment) in wraps:
                    w, (_, _, frame, shape, _) = wraps[(k, segment)]
                    rotation, centre, radius, side_point = self._wrap_geometry(kinematics, w, q.dtype)
                    if shape == "sphere":
                        first, second, arc = _wrapping.wrap_sphere(sites[segment], sites[segment + 1], side_point, centre, radius)
                    else:
                        axes = rotation @ tendons.wrap_rotations[w].astype(q.dtype)
                        first, second, arc = _wrapping.wrap_cylinder(
                            sites[segment], sites[segment + 1], side_point, axes, centre, radius
                        )
                    points += [first, second]
                    joints += [parents[model.frame_id(frame)]] * 2
                    arcs.append((len(points) - 2, arc))
                points.append(sites[segment + 1])
                joints.append(parents[ids[segment + 1]])
            points = jnp.stack(points)
            columns = _dynamics._point_velocity_columns(model, kinematics, np.asarray(joints), points)
            segments = points[1:] - points[:-1]
            norms = _safe_norm(segments)
            lengths = norms
            for chord, arc in arcs:
                lengths = lengths.at[chord].set(arc)
            # the unit direction of each segment (none where its ends meet: no pull there)
            directions = segments / jnp.where(norms > 0, norms, 1.0)[:, None]
            rate = columns[1:] - columns[:-1]  # (segments, nv, 3): the segments' rates per dof
            shares = jnp.stack(shares)
            length = length.at[tendon].add(jnp.sum(shares * lengths).astype(q.dtype))
            moments = moments.at[tendon].add(jnp.einsum("snk,sk,s->n", rate, directions, shares).astype(q.dtype))
        return length, moments

    def inside_side_sites(self, q: ArrayLike) -> Array:
        """How many of the spatial tendons' side sites are inside their wrapping shape at
        configuration ``q`` (int, ``()``): closer to a sphere's centre, or to a cylinder's (the
        distance to its centre point, not to its axis: MuJoCo's test), than its radius.

        Loading refuses a side site inside its shape at ``qpos0``; one on another body than its
        shape can move inside it later, where MuJoCo wraps through the shape and this simulator
        keeps its outside path (:mod:`rsmooth.sim._wrapping`). The step reports the count
        (:attr:`StepInfo.inside_side_sites`) and :func:`check_steps` warns about it."""
        count = jnp.zeros((), jnp.int32)
        tendons = self.joints.tendons
        sides = [] if tendons is None or not tendons.spatial else [(w, entry) for w, entry in enumerate(tendons.wraps) if entry[4] is not None]
        if not sides:
            return count
        q = jnp.asarray(q)
        kinematics = _dynamics._kinematics(self.model, q)
        for w, _ in sides:
            _, centre, radius, side_point = self._wrap_geometry(kinematics, w, q.dtype)
            offset = lax.stop_gradient(side_point - centre)
            count = count + (offset @ offset < radius**2).astype(jnp.int32)
        return count

    def _wrap_geometry(self, kinematics, w: int, dtype) -> tuple[Array, Array, Array, Array | None]:
        """Wrap ``w``'s shape in the world: ``(rotation (3, 3), centre (3,), radius, side site's
        position (3,) or None)``."""
        tendons = self.joints.tendons
        _, _, frame, _, side = tendons.wraps[w]
        rotation, translation = self._frame_origin(kinematics, frame)
        centre = translation + rotation @ tendons.wrap_offsets[w].astype(dtype)
        side_point = None if side is None else self._frame_origin(kinematics, side)[1]
        return rotation, centre, tendons.wrap_radii[w].astype(dtype), side_point

    def _frame_origin(self, kinematics, name: str) -> tuple[Array, Array]:
        """The world placement ``(rotation (3, 3), translation (3,))`` of the frame ``name``."""
        return _dynamics._frame_placement(self.model, kinematics.rotation, kinematics.translation, self.model.frame_id(name))

    def _tendon_stretch(self, length: Array) -> Array:
        """How far each tendon's length ``(T,)`` is beyond its spring's rest band ``(T,)``
        (negative below it, 0 within it)."""
        band = self.joints.tendons.spring_length.astype(length.dtype)
        return length - jnp.clip(length, band[:, 0], band[:, 1])

    def spring_energy(self, q: Array) -> Array:
        """The potential energy ``sum k |displacement|^2 / 2`` of :attr:`Joints.springs` and of
        the tendons' springs (their stretch beyond the rest band) at ``q`` (zero without)."""
        energy = jnp.zeros((), q.dtype)
        if self.joints.springs is not None:
            _, stiffness, displacement = self._spring_displacements(q)
            energy = energy + 0.5 * jnp.sum(stiffness * displacement * displacement)
        if self.joints.tendons is not None:
            stretch = self._tendon_stretch(self.tendon_lengths(q))
            energy = energy + 0.5 * jnp.sum(self.joints.tendons.stiffness.astype(q.dtype) * stretch * stretch)
        return energy

    def joint_rows(self, q: Array) -> tuple[Array, Array, Array]:
        """The joints' box rows of the contact problem at ``q``: :attr:`Joints.friction`'s, then
        :attr:`Joints.couplings`', then :attr:`Joints.connections`' (three per connection, world
        x, y, z), then :attr:`Joints.welds`' (six per weld: the points' gap, then the
        orientation), then the dry friction of :attr:`Joints.tendons`, then their equalities, as
        ``(rows (m, nv), correction (m,), bounds (m,))``: the row ``k`` constrains ``rows[k] v+ +
        correction[k]`` with the impulse bound ``bounds[k]`` (``effort h`` for friction, along a
        tendon its moments; ``inf`` for a coupling, a connection, a weld or a tendon's
        equality, whose correction is ``baumgarte e / h`` for the error ``e``); ``m = 0``
        without any."""
        dtype = q.dtype
        dofs = () if self.joints.friction is None else self.joints.friction.dofs
        friction = np.zeros((len(dofs), self.model.nv))
        friction[np.arange(len(dofs)), list(dofs)] = 1.0
        rows, correction = [jnp.asarray(friction, dtype)], [jnp.zeros(len(dofs), dtype)]
        bounds = [jnp.zeros(0, dtype) if self.joints.friction is None else self.time_step * self.joints.friction.effort]
        def held(error, row):
            error = error.reshape(-1)
            rows.append(row.reshape(error.shape[0], self.model.nv))
            limit = self.options.max_correction_speed
            speed = self.baumgarte * error / self.time_step
            correction.append(speed if limit == float("inf") else jnp.clip(speed, -limit, limit))
            bounds.append(jnp.full(error.shape[0], jnp.inf, dtype))

        for present, terms in ((self.joints.couplings, self._coupling_terms), (self.joints.connections, self._connection_terms),
                               (self.joints.welds, self._weld_terms)):
            if present is not None:
                held(*terms(q))
        tendons = self.joints.tendons
        if tendons is not None and (tendons.frictional or tendons.equalities):
            lengths, moments = self._tendon_geometry(q)
            if tendons.frictional:
                frictional = np.asarray(tendons.frictional, dtype=np.int64)
                rows.append(moments[frictional])
                correction.append(jnp.zeros(frictional.size, dtype))
                bounds.append(self.time_step * tendons.frictionloss[frictional].astype(dtype))
            if tendons.equalities:
                equal = np.asarray(tendons.equalities, dtype=np.int64)
                held(lengths[equal] - tendons.equality_length[equal].astype(dtype), moments[equal])
        return jnp.concatenate(rows), jnp.concatenate(correction), jnp.concatenate(bounds).astype(dtype)

    def coupling_errors(self, q: Array) -> Array:
        """How far each of :attr:`Joints.couplings` is from holding at ``q``, ``q_a - p(q_b)``
        (rad or m), ``(k,)``; empty without couplings."""
        if self.joints.couplings is None:
            return jnp.zeros(0, q.dtype)
        return _first_term(self, "_coupling_terms", q)

    def connection_errors(self, q: Array) -> Array:
        """How far each of :attr:`Joints.connections` is from holding at ``q``: ``p_a - p_b``
        (world, m), ``(k, 3)``; empty without connections."""
        if self.joints.connections is None:
            return jnp.zeros((0, 3), q.dtype)
        return _first_term(self, "_connection_terms", q)

    def weld_errors(self, q: Array) -> Array:
        """How far each of :attr:`Joints.welds` is from holding at ``q``: the points' gap
        (world, m) then the orientation error (see :class:`Weld`), ``(k, 6)``; empty without
        welds."""
        if self.joints.welds is None:
            return jnp.zeros((0, 6), q.dtype)
        return _first_term(self, "_weld_terms", q)

    def _held_points(self, held, q: Array, kinematics) -> tuple[Array, Array, Array]:
        """The gaps ``p_a - p_b`` ``(k, 3)`` of a connection's or a weld's points, their
        velocity rows ``(k, 3, nv)`` and the frames' world rotations ``(2 k, 3, 3)``."""
        model, dtype = self.model, q.dtype
        frames = held.frames + held.others
        anchors = jnp.concatenate([held.anchors, held.other_anchors]).astype(dtype)
        rotations, points = [], []
        for frame, anchor in zip(frames, anchors):
            rotation, translation = _dynamics._frame_placement(model, kinematics.rotation, kinematics.translation, frame)
            rotations.append(rotation)
            points.append(rotation @ anchor + translation)
        points = jnp.stack(points)
        columns = _dynamics._point_velocity_columns(model, kinematics, np.asarray(model.frame_parents)[list(frames)], points)
        count = len(held.frames)
        return points[:count] - points[count:], jnp.swapaxes(columns[:count] - columns[count:], 1, 2), jnp.stack(rotations)

    def _connection_terms(self, q: Array) -> tuple[Array, Array]:
        """The connections' position errors ``(k, 3)`` and their velocity rows ``(k, 3, nv)``."""
        error, rows, _ = self._held_points(self.joints.connections, q, _dynamics._kinematics(self.model, q))
        return error, rows

    def _weld_terms(self, q: Array) -> tuple[Array, Array]:
        """The welds' errors ``(k, 6)`` (the points' gap, the orientation) and their velocity
        rows ``(k, 6, nv)``."""
        model, weld = self.model, self.joints.welds
        kinematics = _dynamics._kinematics(model, q)
        gap, point_rows, rotations = self._held_points(weld, q, kinematics)
        count = len(weld.frames)
        relative = jnp.einsum("kji,kjl,klm->kim", rotations[count:], rotations[:count], weld.rotations.astype(q.dtype))
        quaternion = jax.vmap(spatial.rotation_to_quaternion)(relative)  # [x, y, z, w], w >= 0
        scale = weld.torque_scale.astype(q.dtype)[:, None]
        orientation = scale * quaternion[:, :3]
        frames = weld.frames + weld.others
        angular = jnp.swapaxes(_dynamics._support_columns(model, kinematics, np.asarray(model.frame_parents)[list(frames)])[..., 3:], 1, 2)
        relative_rate = jnp.einsum("kji,kjn->kin", rotations[count:], angular[:count] - angular[count:])  # R_bᵀ (w_a - w_b)
        rate = quaternion[:, 3, None, None] * jnp.eye(3, dtype=q.dtype)[None] - jax.vmap(spatial.skew)(quaternion[:, :3])
        orientation_rows = 0.5 * scale[:, :, None] * jnp.einsum("kij,kjn->kin", rate, relative_rate)
        return jnp.concatenate([gap, orientation], axis=1), jnp.concatenate([point_rows, orientation_rows], axis=1)

    def _coupling_terms(self, q: Array) -> tuple[Array, Array]:
        """The couplings' position errors ``(k,)`` and their velocity rows ``(k, nv)`` at ``q``."""
        model, coupling, dtype = self.model, self.joints.couplings, q.dtype
        a_q, a_v = (np.array([getattr(model, field)[j] for j in coupling.joints]) for field in ("idx_q", "idx_v"))
        b_q, b_v = (np.array([getattr(model, field)[j] for j in coupling.others]) for field in ("idx_q", "idx_v"))
        leader = np.array([j != 0 for j in coupling.others])
        q_b = jnp.where(leader, q[b_q], 0.0)
        c = coupling.coefficients.astype(dtype)
        # Horner's rule (powers q^0 would have a NaN derivative at q = 0)
        value = c[:, 0] + q_b * (c[:, 1] + q_b * (c[:, 2] + q_b * (c[:, 3] + q_b * c[:, 4])))
        slope = c[:, 1] + q_b * (2 * c[:, 2] + q_b * (3 * c[:, 3] + q_b * 4 * c[:, 4]))
        count = len(coupling.joints)
        row = jnp.zeros((count, model.nv), dtype).at[np.arange(count), a_v].set(1.0)
        row = row.at[np.arange(count), b_v].add(jnp.where(leader, -slope, 0.0))
        return q[a_q] - value, row

    def with_joint_limits(self, joints: Sequence[str] | None = None) -> "RigidBodySystem":
        """This system with its model's finite position limits enforced (:attr:`Joints.limits`).

        Args:
            joints: names of the revolute, prismatic or spherical joints whose limits to
                enforce; ``None``: every such joint with a finite limit (a cone, for a
                spherical joint).

        Returns:
            A copy whose steps keep those joints within their limits: a joint reaching one
            stops there (an inelastic, frictionless unilateral constraint), a joint beyond one
            is pushed back at the Baumgarte rate, like a penetrating contact.

        Raises:
            ValueError: on an unknown joint name, a joint that is not revolute, prismatic or
                spherical, or a named joint without a finite limit.
        """
        model = self.model
        lower, upper = np.asarray(model.lower_position_limit), np.asarray(model.upper_position_limit)
        if joints is None:
            names = [name for name, kind in zip(model.joint_names, model.joint_types) if kind in _LIMITED_TYPES]
        else:
            names = list(joints)
        limits = []
        for name in names:
            if name not in model.joint_names:
                raise ValueError(f"joints: unknown joint {name!r}; the model's joints are {model.joint_names[1:]}")
            joint = model.joint_names.index(name)
            if model.joint_types[joint] not in _LIMITED_TYPES:
                raise ValueError(
                    f"joints: {name!r} is a {model.joint_types[joint]} joint; only revolute, prismatic and spherical "
                    "joints have position limits here")
            dof, index = model.idx_v[joint], model.idx_q[joint]
            if model.joint_types[joint] == "spherical":
                sides = [0] if np.isfinite(upper[index]) else []
            else:
                sides = [side for side, bound in ((1, lower[index]), (-1, upper[index])) if np.isfinite(bound)]
            if joints is not None and not sides:
                raise ValueError(f"joints: {name!r} has no finite position limit in the model")
            limits.extend((dof, side) for side in sides)
        return self._with_joints(limits=tuple(limits))

    def with_contact_budget(
        self, max_contacts: int | None, max_pairs: int | None = None, max_limits: int | None = None
    ) -> "RigidBodySystem":
        """This system with at most ``max_contacts`` contacts between shapes and ``max_limits``
        joint limits in each step's solve (:attr:`Options.max_contacts`, :attr:`Options.max_limits`) and at
        most ``max_pairs`` pairs of each pair group collided (:attr:`Options.max_pairs`); ``None``
        removes a budget.

        Raises:
            ValueError: unless each is a positive integer or ``None``, or a contact budget
                with a compliant contact law.
        """
        return self.with_options(max_contacts=max_contacts, max_pairs=max_pairs, max_limits=max_limits)

    def with_gravity_compensation(self, on: bool = True) -> "RigidBodySystem":
        """This system with (or without) :attr:`Actuation.gravity_compensation` on its actuated dofs.

        Raises:
            ValueError: with a wrench actuation (:attr:`Actuation.kind`).
        """
        return dataclasses.replace(self, actuation=dataclasses.replace(self.actuation, gravity_compensation=on))

    def _contact_selection(self, distance: Array) -> Array | None:
        """Indices ``(K,)`` (ascending) of the candidates the NCP solves under
        :attr:`Options.max_contacts` and :attr:`Options.max_limits`, or ``None`` where the budgets hold every
        candidate."""
        distance = lax.stop_gradient(distance)
        shapes, limits = distance.shape[0] - self.num_limits, self.num_limits

        def nearest(budget, first, count):  # the `budget` smallest distances of a block
            if budget is None or budget >= count:
                return None
            _, index = lax.top_k(-distance[first : first + count], budget)
            return first + jnp.sort(index).astype(jnp.int32)

        contacts, limit_rows = nearest(self.options.max_contacts, 0, shapes), nearest(self.options.max_limits, shapes, limits)
        if contacts is None and limit_rows is None:
            return None
        contacts = jnp.arange(shapes, dtype=jnp.int32) if contacts is None else contacts
        limit_rows = jnp.arange(shapes, shapes + limits, dtype=jnp.int32) if limit_rows is None else limit_rows
        return jnp.concatenate([contacts, limit_rows])

    def _selected_shape_count(self) -> int:
        """How many of :meth:`_contact_selection`'s indices are contacts between shapes (the
        rest are limits): static."""
        shapes, budget = self.num_contacts - self.num_limits, self.options.max_contacts
        return shapes if budget is None or budget >= shapes else budget

    def split(self, x: ArrayLike) -> tuple[Array, Array]:
        """``(q, v)`` from a state ``x`` of shape ``(..., nx)`` (:meth:`activations` gives the rest)."""
        x = jnp.asarray(x)
        nq, nv = self.model.nq, self.model.nv
        return x[..., :nq], x[..., nq : nq + nv]

    def activations(self, x: ArrayLike) -> Array:
        """The actuator states ``act`` ``(..., na)`` of a state ``x`` (:class:`ActivationDynamics`)."""
        return jnp.asarray(x)[..., self.model.nq + self.model.nv :]

    def state(self, q: ArrayLike, v: ArrayLike | None = None, act: ArrayLike | None = None) -> Array:
        """The state ``[q, v, act]`` (``v = 0`` and ``act = 0`` by default; ``act`` is empty
        but for actuators with activation dynamics).

        A free flyer's velocity in ``v`` is ``[v_lin, omega]`` in its body axes (Pinocchio's
        ``LOCAL`` twist): for a body at rotation ``R`` moving at world velocity ``u`` and
        spinning at world angular velocity ``w``, ``v_lin = R^T u`` and ``omega = R^T w``.
        """
        q = jnp.asarray(q)
        v = jnp.zeros(q.shape[:-1] + (self.model.nv,), q.dtype) if v is None else jnp.asarray(v)
        act = jnp.zeros(q.shape[:-1] + (self.na,), q.dtype) if act is None else jnp.asarray(act)
        if act.shape[-1:] != (self.na,):
            raise ValueError(f"act must have shape (..., na) = (..., {self.na}), got {act.shape}")
        return jnp.concatenate([q, v, act], axis=-1)

    def initial_state(self) -> Array:
        """The state the system starts from: :attr:`initial_configuration` at zero velocity.

        Each factory of :mod:`rsmooth.sim` stores the configuration its docstring describes
        (a body resting on its first half-space, the pusher's finger behind the box, Solo-12
        standing), so every system gives its default start the same way. Without one it is
        the model's neutral configuration: zero joint positions, free flyers at the origin
        with the identity orientation.

        Returns:
            The state ``[q, 0]``, shape ``(nx,)``.

        Example:
            >>> import rsmooth.sim as sim
            >>> [round(float(v), 3) for v in sim.cube().initial_state()[:7]]
            [0.0, 0.0, 0.1, 0.0, 0.0, 0.0, 1.0]
        """
        if self.initial_configuration is not None:
            return self.state(self.initial_configuration)
        q = np.zeros(self.model.nq)
        q[_dynamics._tree(self.model).rotation_q + 3] = 1.0  # quaternions [x, y, z, w] = identity
        return self.state(jnp.asarray(q, self.time_step.dtype))

    def project_state(self, x: ArrayLike) -> Array:
        """The state with every free flyer's quaternion scaled to unit norm (the rest as is).

        States live on ``R^3 x S^3 x R^(nq - 7) x R^nv``, while noise and DDP's steps are
        added in ``R^nx``: :func:`rsmooth.control.rddp` steps from ``project_state`` of each
        perturbed state, so that noise on a quaternion's four coordinates is noise on the
        orientation (its radial part does nothing). ``step`` itself does not normalize its
        input (it gives Pinocchio's placements for any input, unit or not).

        Example:
            >>> import rsmooth.sim as sim
            >>> system = sim.cube()
            >>> x = system.initial_state().at[3:7].multiply(2.0)  # a quaternion of norm 2
            >>> float(jnp.linalg.norm(system.project_state(x)[3:7]))
            1.0
        """
        x = jnp.asarray(x)
        tree = _dynamics._tree(self.model)
        for start in tree.rotation_q:
            start = int(start)
            quaternion = x[..., start : start + 4]
            norm = jnp.sqrt(spatial.sum_last(quaternion * quaternion))[..., None]
            x = x.at[..., start : start + 4].set(quaternion / norm)
        return x

    # -- stages -------------------------------------------------------------------------

    def _check(self, x: ArrayLike, u: ArrayLike) -> tuple[Array, Array]:
        x, u = jnp.asarray(x), jnp.asarray(u)
        if x.shape != (self.nx,):
            layout = f"[q (nq={self.model.nq}), v (nv={self.model.nv})" + (f", act (na={self.na})]" if self.na else "]")
            raise ValueError(f"x must have shape (nx,) = ({self.nx},) as {layout}, got {x.shape}")
        if u.shape != (self.nu,):
            raise ValueError(f"u must have shape (nu,) = ({self.nu},), got {u.shape}")
        dtype = jnp.result_type(x, u, float)
        x, u = x.astype(dtype), u.astype(dtype)
        x = _checks.check_finite(x, "x (the state) contains NaN or infinite values")
        u = _checks.check_finite(u, "u (the input) contains NaN or infinite values")
        return x, u

    def generalized_forces(self, q: Array, u: Array, kinematics=None, v: Array | None = None) -> tuple[Array, Array]:
        """``(tau, clipped)``: the generalized forces of input ``u`` (after clipping) at
        ``(q, v)`` (``v`` is read by servos only)."""
        if self.actuation.kind == "servos":
            if v is None:
                raise ValueError("servos' forces depend on the velocity: pass v")
            return self.actuation.servos.forces(self.actuation.moments, q, v, u, self.time_step)
        limited = jnp.clip(u, -self.actuation.input_limit, self.actuation.input_limit)
        clipped = jnp.any(limited != u)
        if self.actuation.kind == "joints":
            dofs = np.asarray(self.actuation.dofs, dtype=np.int64)
            if self.actuation.gravity_compensation:
                if kinematics is None:
                    kinematics = _dynamics._kinematics(self.model, q)
                inertias = _dynamics._world_inertias(self.model, kinematics)
                zero = jnp.zeros(self.model.nv, q.dtype)
                holding = _dynamics._rnea(self.model, kinematics, inertias, zero, None, self.model.gravity)
                limited = limited + holding[dofs]
            tau = jnp.zeros(self.model.nv, u.dtype).at[dofs].set(limited)
            return tau, clipped
        if self.actuation.kind == "moments":
            return self.actuation.moments.astype(limited.dtype).T @ limited, clipped
        if kinematics is None:
            kinematics = _dynamics._kinematics(self.model, q)
        rotation, translation = _dynamics._frame_placement(
            self.model, kinematics.rotation, kinematics.translation, self.actuation.wrench_frame
        )
        del rotation
        jacobian = _point_jacobian(self.model, kinematics, self.model.frame_parents[self.actuation.wrench_frame], translation)
        angular = _angular_jacobian(self.model, kinematics, self.model.frame_parents[self.actuation.wrench_frame])
        full = jnp.concatenate([jacobian, angular])  # (6, nv), world-aligned at the frame origin
        wrench_jacobian = full[np.asarray(self.actuation.wrench_components)]
        return wrench_jacobian.T @ limited, clipped

    def contacts(self, q: Array, kinematics=None) -> tuple[Array, Array, Array]:
        """Candidate contacts at ``q``: ``(distance (n,), frames (n, 3, 3), J (3n, nv))``.

        Ordered sphere-major: contact ``s * P + p`` is sphere ``s`` against half-space ``p``;
        then, pair by pair, the manifold entries of ``geom_pairs``
        (:meth:`_geom_pair_contacts`); then the joint limits, then the tendons' limits
        (:attr:`num_limits`). ``J`` maps ``v`` to the
        contact-frame velocity ``[t1, t2, n]`` of the sphere point deepest towards the plane
        (for geometry pairs, of shape 2's witness point relative to shape 1's).
        """
        return self._candidates(q, kinematics)[:3]

    def _candidates(self, q: Array, kinematics=None) -> tuple[Array, Array, Array, _stages.WitnessPoints]:
        """:meth:`contacts`, and the :class:`~rsmooth.sim._stages.WitnessPoints` from which
        any of its Jacobian's rows and ``J v`` are computed without ``J``."""
        if kinematics is None:
            kinematics = _dynamics._kinematics(self.model, q)
        distance, frames, jacobian, points = self._shape_contacts(q, kinematics)
        limit_rows = jnp.zeros((0, 3, self.model.nv), jacobian.dtype)
        if self.num_limits:
            parts = []  # (distances, rows) of the joint limits, then of the tendons' limits
            if self.joints.limits:
                parts.append(self._joint_limit_contacts(q, jacobian.dtype))
            tendons = self.joints.tendons
            if tendons is not None and tendons.limits:
                # frictionless contacts along the tendons' moments: the length's rate
                which, sides = (np.asarray([entry[k] for entry in tendons.limits], np.int64) for k in (0, 1))
                length, moments = self._tendon_geometry(q, kinematics)
                bounds = tendons.range.astype(q.dtype)
                limit_distance = jnp.where(sides > 0, length[which] - bounds[which, 0], bounds[which, 1] - length[which])
                rows = jnp.zeros((len(which), 3, self.model.nv), jacobian.dtype).at[:, 2].set(sides[:, None] * moments[which])
                parts.append((limit_distance, rows))
            count = self.num_limits
            limit_rows = jnp.concatenate([part[1] for part in parts])
            distance = jnp.concatenate([distance] + [part[0].astype(distance.dtype) for part in parts])
            frames = jnp.concatenate([frames, jnp.broadcast_to(jnp.eye(3, dtype=frames.dtype), (count, 3, 3))])
            jacobian = jnp.concatenate([jacobian, limit_rows.reshape(-1, self.model.nv)])
        joint1, point1, joint2, point2, weight = points
        return distance, frames, jacobian, _stages.WitnessPoints(
            joint1, point1, joint2, point2, weight, kinematics.motion_subspace, limit_rows
        )

    def _joint_limit_contacts(self, q: Array, dtype) -> tuple[Array, Array]:
        """The joint limits' distances ``(l,)`` and contact Jacobians ``(l, 3, nv)``
        (:meth:`contacts`)."""
        # Frictionless contacts whose normal is the joint's own coordinate, or for a spherical
        # joint's cone the axis of its rotation (the angle's rate is axisᵀ omega).
        indices, dofs, sides = _limit_rows(self.model, self.joints.limits)
        lower, upper = self.model.lower_position_limit[indices], self.model.upper_position_limit[indices]
        limit_distance = jnp.where(sides > 0, q[indices] - lower, upper - q[indices])
        rows = jnp.zeros((len(dofs), 3, self.model.nv), dtype).at[np.arange(len(dofs)), 2, dofs].set(sides)
        cones = np.flatnonzero(sides == 0)
        if cones.size:
            quaternion = q[indices[cones][:, None] + np.arange(4)]  # [qx, qy, qz, qw]
            sine = _safe_norm(quaternion[:, :3])  # |sin(angle / 2)|
            angle = 2.0 * jnp.arctan2(sine, jnp.abs(quaternion[:, 3]))
            axis = quaternion[:, :3] * (jnp.where(quaternion[:, 3] < 0, -1.0, 1.0) / jnp.maximum(sine, jnp.finfo(sine.dtype).tiny))[:, None]
            limit_distance = limit_distance.at[cones].set(upper[cones] - angle)
            rows = rows.at[cones[:, None], 2, dofs[cones][:, None] + np.arange(3)].set(-axis.astype(rows.dtype))
        return limit_distance, rows

    def _shape_contacts(self, q: Array, kinematics=None) -> tuple[Array, Array, Array, tuple]:
        """The contacts of :meth:`contacts` between shapes (all but the limits), and where they
        act: ``(joint1, point1, joint2, point2, weight)`` (:class:`~rsmooth.sim._stages.WitnessPoints`)."""
        model = self.model
        if kinematics is None:
            kinematics = _dynamics._kinematics(model, q)
        if not self.geometry.sphere_frames:
            if not self.geometry.geom_pairs:
                dtype = kinematics.translation.dtype
                nothing = jnp.zeros((0, 3), dtype)
                return (jnp.zeros(0, dtype), jnp.zeros((0, 3, 3), dtype), jnp.zeros((0, model.nv), dtype),
                        ((), nothing, (), nothing, jnp.zeros(0, dtype)))
            distance, frames, jacobians, points = self._geom_pairs_contacts(kinematics)
            return distance, frames, jacobians.reshape(-1, model.nv), points
        # All spheres at once (one batched expression per quantity, not one per sphere: the
        # traced graph, and the compile time of every solver built on the step, would grow
        # with the number of spheres). The contact -> joint map is static.
        centres, points, joints, rotations = self._sphere_geometry(kinematics)  # (n, 3) x2, (n,), (n, 3, 3)
        num_spheres, num_planes = len(self.geometry.sphere_frames), self.geometry.plane_normals.shape[0]
        normals = jnp.tile(self.geometry.plane_normals, (num_spheres, 1))
        offsets = jnp.tile(self.geometry.plane_offsets, num_spheres)
        distance = spatial.sum_last(centres * normals) - offsets - jnp.repeat(self.geometry.sphere_radii, num_planes)
        # the half-spaces are the world's (joint 0)
        acting = ((0,) * len(joints), points, tuple(int(j) for j in joints), points, jnp.ones(len(joints), points.dtype))
        jacobians = _stages.point_rows(model, kinematics, rotations, *acting[:4])  # (n, 3, nv)
        distances, frames, jacobians, where = [distance], [rotations], [jacobians], [acting]
        if self.geometry.geom_pairs:
            distance, rotation, jacobian, acting = self._geom_pairs_contacts(kinematics)
            distances.append(distance)
            frames.append(rotation)
            jacobians.append(jacobian)
            where.append(acting)
        distance = jnp.concatenate(distances)
        return distance, jnp.concatenate(frames), jnp.concatenate(jacobians).reshape(-1, model.nv), _joined_points(where)

    def _sphere_centres(self, kinematics) -> tuple[Array, np.ndarray]:
        """World centres of the spheres ``(S, 3)`` and the (static) joint carrying each."""
        model = self.model
        sphere_frames = np.asarray(self.geometry.sphere_frames, dtype=np.int64)  # int even when empty
        joints = np.asarray(model.frame_parents)[sphere_frames]
        rotation, translation = _dynamics._compose(
            kinematics.rotation[joints],
            kinematics.translation[joints],
            model.frame_placement_rotation[sphere_frames],
            model.frame_placement_translation[sphere_frames],
        )
        return translation + jax.vmap(spatial.rotate)(rotation, self.geometry.sphere_offsets), joints

    def _sphere_geometry(self, kinematics) -> tuple[Array, Array, np.ndarray, Array]:
        """Per sphere-half-space contact (the order of :meth:`contacts`): sphere centre ``(n, 3)``, contact point ``(n, 3)``, joint ``(n,)`` (static)
        and contact frame ``(n, 3, 3)``."""
        centres, joints = self._sphere_centres(kinematics)
        num_spheres, num_planes = centres.shape[0], self.geometry.plane_normals.shape[0]
        points = centres[:, None, :] - self.geometry.sphere_radii[:, None, None] * self.geometry.plane_normals[None]
        frames = jnp.broadcast_to(contact_frame(self.geometry.plane_normals), (num_spheres, num_planes, 3, 3))
        return (
            jnp.broadcast_to(centres[:, None, :], points.shape).reshape(-1, 3),
            points.reshape(-1, 3),
            np.repeat(joints, num_planes),
            frames.reshape(-1, 3, 3),
        )

    def _geom_pose(self, kinematics, frame, placement) -> tuple[Array, Array]:
        """World pose of a shape placed at ``placement`` in ``frame`` (``None``: the world)."""
        if frame is None:
            return placement
        model = self.model
        rotation, translation = _dynamics._frame_placement(
            model, kinematics.rotation, kinematics.translation, model.frame_id(frame)
        )
        return spatial.compose(rotation, translation, placement[0], placement[1])

    def _geom_pairs_contacts(self, kinematics) -> tuple[Array, Array, Array, tuple]:
        """:meth:`_geom_pair_contacts` of every geometry pair, concatenated in pair order.

        Pairs that differ only in their arrays (shape sizes, placements, frames; convex meshes
        of vertex counts within a power of 2, padded alike: see :func:`_pair_groups`) are
        evaluated by one ``vmap``-ed collision: the traced program
        holds one copy of each pair type's collision code rather than one per pair, which keeps
        the compile time of a scene of many bodies from growing with the number of pairs (a
        box-box pair is about 3,000 lines of HLO). Under :attr:`Options.max_pairs` the collision runs
        on a group's ``max_pairs`` pairs of smallest bounding gap (:func:`_bounding_gaps`); the
        other pairs' entries are inactive."""
        sizes = [pair.size for pair in self.geometry.geom_pairs]
        offsets = np.cumsum([0] + sizes)
        parts, positions = [], []
        for group in _pair_groups(self.geometry.geom_pairs):
            pairs = [self.geometry.geom_pairs[i] for i in group]
            positions.extend(np.arange(offsets[i], offsets[i + 1]) for i in group)
            if len(pairs) == 1:
                parts.append(self._geom_pair_contacts(kinematics, pairs[0]))
                continue
            first = pairs[0]
            shape1, pose1, shape2, pose2 = self._group_shapes(kinematics, pairs)
            if self.options.max_pairs is None or len(pairs) <= self.options.max_pairs:
                manifold = _collide_group(shape1, pose1, shape2, pose2, first.margin)
            else:
                gaps = lax.stop_gradient(_bounding_gaps(shape1, pose1, shape2, pose2))
                _, chosen = lax.top_k(-gaps, self.options.max_pairs)
                take = lambda tree: jax.tree.map(lambda leaf: leaf[chosen], tree)  # noqa: E731
                evaluated = _collide_group(take(shape1), take(pose1), take(shape2), take(pose2), first.margin)
                # the pairs not evaluated: inactive entries with finite values (normal +z)
                empty = Contacts(
                    distance=jnp.full(evaluated.distance.shape[1:], _INACTIVE_DISTANCE, evaluated.distance.dtype),
                    normal=jnp.zeros_like(evaluated.normal[0]).at[:, 2].set(1.0),
                    point1=jnp.zeros_like(evaluated.point1[0]), point2=jnp.zeros_like(evaluated.point2[0]),
                    active=jnp.zeros_like(evaluated.active[0]),
                )
                manifold = jax.tree.map(
                    lambda full, part: jnp.broadcast_to(full, (len(pairs),) + full.shape).at[chosen].set(part), empty, evaluated
                )
            manifold = _unreversed(manifold, np.array([_reversed(p) for p in pairs]))
            parts.append(self._manifold_contacts(kinematics, manifold, [p.frame1 for p in pairs], [p.frame2 for p in pairs], first.size))
        order = np.argsort(np.concatenate(positions))  # group-major -> pair order
        distance, rotations, jacobians = (jnp.concatenate(part)[order] for part in list(zip(*parts))[:3])
        return distance, rotations, jacobians, _joined_points([part[3] for part in parts], order)

    def _group_shapes(self, kinematics, pairs: list[GeomPair]) -> tuple:
        """``(shape1, pose1, shape2, pose2)`` of a group of pairs (:func:`_pair_groups`), each
        pair in its collision function's order (:func:`_reversed`), the shapes' arrays (convex
        meshes padded to common shapes, :func:`~rsmooth.sim._geometry.padded_meshes`) and world
        poses stacked along a leading pair axis."""
        model = self.model
        sides = [(p.shape2, p.shape1, p.placement2, p.placement1, p.frame2, p.frame1) if _reversed(p)
                 else (p.shape1, p.shape2, p.placement1, p.placement2, p.frame1, p.frame2) for p in pairs]
        shapes1, shapes2, placements1, placements2, frames1, frames2 = zip(*sides)
        shape1, shape2, placement1, placement2 = (
            jax.tree.map(lambda *leaves: jnp.stack(leaves), *(padded_meshes(items) if isinstance(items[0], ConvexMesh) else items))
            for items in (shapes1, shapes2, placements1, placements2)
        )

        def poses(frames, placements):
            if frames[0] is None:
                return placements
            ids = np.asarray([model.frame_id(frame) for frame in frames], dtype=np.int64)
            joints = np.asarray(model.frame_parents)[ids]
            frame_pose = _compose_batch(
                kinematics.rotation[joints], kinematics.translation[joints],
                model.frame_placement_rotation[ids], model.frame_placement_translation[ids],
            )
            return _compose_batch(*frame_pose, *placements)

        return shape1, poses(frames1, placement1), shape2, poses(frames2, placement2)

    def skipped_pairs(self, q: ArrayLike) -> Array:
        """How many geometry pairs :attr:`Options.max_pairs` leaves out although their bounding
        volumes are within the pair's margin (they may touch, and are not collided), summed
        over the pair groups, at configuration ``q`` (int, ``()``; 0 without the limit)."""
        count = jnp.zeros((), jnp.int32)
        if self.options.max_pairs is None:
            return count
        kinematics = _dynamics._kinematics(self.model, jnp.asarray(q))
        for group in _pair_groups(self.geometry.geom_pairs):
            if len(group) <= self.options.max_pairs:
                continue
            pairs = [self.geometry.geom_pairs[i] for i in group]
            gaps = lax.stop_gradient(_bounding_gaps(*self._group_shapes(kinematics, pairs)))
            near = jnp.sum(gaps <= pairs[0].margin, dtype=jnp.int32)
            count = count + jnp.maximum(near - self.options.max_pairs, 0)
        return count

    def _geom_pair_contacts(self, kinematics, pair: GeomPair) -> tuple[Array, Array, Array, tuple]:
        """Signed distances ``(k,)``, contact frames ``(k, 3, 3)``, relative contact
        Jacobians ``(k, 3, nv)`` and where they act (:meth:`_shape_contacts`) of a geometry
        pair's manifold: ``R^T (J_2 - J_1)`` (:func:`~rsmooth.sim._stages.point_rows`) with
        ``J_i`` the Jacobian of the world velocity of the material point of shape ``i``'s body at
        its witness point (none for a world-fixed shape), so the normal velocity (along the
        normal from shape 1 to shape 2) is positive where they separate. Entries that are not
        contacts of the manifold get a distance of 10 m (:data:`_INACTIVE_DISTANCE`)."""
        pose1 = self._geom_pose(kinematics, pair.frame1, pair.placement1)
        pose2 = self._geom_pose(kinematics, pair.frame2, pair.placement2)
        manifold = collide(pair.shape1, pose1, pair.shape2, pose2, margin=pair.margin)
        return self._manifold_contacts(kinematics, manifold, [pair.frame1], [pair.frame2], pair.size)

    def _manifold_contacts(self, kinematics, manifold, frames1, frames2, size: int) -> tuple[Array, Array, Array, tuple]:
        """Distances, contact frames, Jacobians and where they act (:meth:`_geom_pair_contacts`)
        of the manifolds of one or several pairs (``manifold``'s arrays with a leading pair axis or
        none), flattened: ``frames1``/``frames2`` the frame of each pair's shapes (all
        ``None`` or none), ``size`` entries per pair."""
        model = self.model
        distance = jnp.where(manifold.active, manifold.distance, _INACTIVE_DISTANCE).reshape(-1)
        rotations = contact_frame(manifold.normal.reshape(-1, 3))  # (n k, 3, 3)
        point1, point2 = manifold.point1.reshape(-1, 3), manifold.point2.reshape(-1, 3)
        # each side's body (a world-fixed shape: joint 0, which no dof moves)
        joints2, joints1 = (
            np.repeat([0 if frame is None else model.frame_parents[model.frame_id(frame)] for frame in frames], size)
            for frames in (frames2, frames1)
        )
        # An inactive entry gets no impulse (its 10 m gap does not close in a step): zero rows
        # keep it out of the Delassus matrix, so that where its witness points lie (a far
        # pair's, or none for a pair the broad phase skipped) does not change the problem.
        weight = manifold.active.reshape(-1).astype(distance.dtype)
        jacobians = _stages.point_rows(model, kinematics, rotations, joints1, point1, joints2, point2, weight)  # (n k, 3, nv)
        return distance, rotations, jacobians, (tuple(map(int, joints1)), point1, tuple(map(int, joints2)), point2, weight)

    def step_with_info(self, x: ArrayLike, u: ArrayLike, *, warm_start: ArrayLike | None = None) -> tuple[Array, StepInfo]:
        """One time step and its diagnostics.

        Args:
            x: state ``[q, v, act]``, shape ``(nx,)``.
            u: input, shape ``(nu,)``.
            warm_start: contact impulses to start the NCP solver from, ``(3 n,)`` (e.g. the
                previous step's ``info.impulse``); hard contact only.

        Returns:
            ``(x_next, info)``.

        Raises:
            ValueError: on wrong shapes, or NaN/inf in ``x`` or ``u`` (under ``jit``: an
                ``equinox`` runtime error with the same message).
        """
        x, u = self._check(x, u)
        return _step_with_info(self, x, u, warm_start)

    def _drive(self, u: Array, x: Array) -> Array:
        """The input of the velocity update: ``u``, followed by the actuator states where there
        are some (:meth:`Servos.forces`), so that its derivatives in the input hold theirs."""
        return jnp.concatenate([u, self.activations(x)]) if self.na else u

    def _next_activations(self, act: Array, drive: Array) -> Array:
        """The actuator states of the next step ``(na,)`` (:class:`ActivationDynamics`)."""
        dynamics = self._activation_dynamics
        if dynamics is None:
            return act
        return dynamics.next(act, self.actuation.servos.clipped(drive), self.time_step)

    def _contact_diagnostics(self, impulse: Array, frames: Array, velocity: Array) -> tuple[Array, Array]:
        """World-frame contact forces ``(n, 3)`` and contact modes ``(n,)`` (:class:`StepInfo`)."""
        n = frames.shape[0]
        local = lax.stop_gradient(impulse).reshape(n, 3)
        force = jnp.einsum("cab,cb->ca", frames, local) / self.time_step
        slip = jnp.sqrt(jnp.sum(velocity.reshape(n, 3)[:, :2] ** 2, axis=-1))
        # sliding: a contact slips faster than the contact solve's tolerance resolves (in
        # velocity units, sqrt(tolerance): 1e-5 m/s in float64)
        threshold = self.solver.tolerance_for(impulse.dtype) ** 0.5
        mode = jnp.where(~(local[:, 2] > 0), SEPARATED, jnp.where(slip > threshold, SLIDING, STICKING))
        return force, mode.astype(jnp.int32)

    def damping(self) -> Array:
        """The joint damping ``(nv,)`` (zeros when :attr:`Joints.damping` is ``None``)."""
        if self.joints.damping is None:
            return jnp.zeros(self.model.nv, self.time_step.dtype)
        return self.joints.damping

    def contact_friction(self) -> Array:
        """Coulomb coefficient of every candidate contact, ``(n,)`` (order of :meth:`contacts`)."""
        return jnp.concatenate([
            jnp.repeat(self.geometry.friction[None, :], len(self.geometry.sphere_frames), axis=0).reshape(-1),
        ] + [jnp.full(pair.size, pair.friction, self.geometry.friction.dtype) for pair in self.geometry.geom_pairs]
          + [jnp.zeros(self.num_limits, self.geometry.friction.dtype)])

    def _velocity_update(self, q: Array, v: Array, u: Array, warm_start, geometry=None) -> _VelocityUpdate:
        """The velocity update of one step (stages 1 to 4, :mod:`._stages`) and the quantities
        its derivative reuses; ``geometry``: stages 1 and 2 at ``q`` where already computed,
        ``(kinematics, contacts)``."""
        if geometry is None:
            posed = _stages.kinematics(self, q)
            contacts = _stages.collision(self, q, posed)
        else:
            posed, contacts = geometry
        motion = _stages.free_motion(self, q, v, u, posed)
        solution = _stages.solve_contacts(self, motion, contacts, warm_start)
        return _VelocityUpdate(
            solution.velocity, solution.impulse, contacts.distance, solution.ncp, motion.torque_clipped,
            (motion.mass_cholesky, True), contacts.jacobian, solution.delassus, solution.free_velocity,
            solution.friction, posed, motion.inertias, motion.mass, contacts.frames, solution.selection, solution.dropped,
            solution.joint_impulse, contacts.joint_rows[0], contacts.joint_rows[2],
            # under a budget, from the bodies' twists: a program that takes no derivative then
            # never forms the rows of the contacts it leaves out (_stages.contact_velocities);
            # otherwise from the rows the solve formed (fewer operations for a few contacts)
            contacts.jacobian @ solution.velocity if solution.selection is None
            else _stages.contact_velocities(self, contacts, solution.velocity),
        )

    def step(self, x: ArrayLike, u: ArrayLike) -> Array:
        """One time step: ``x_next = step(x, u)`` (see :meth:`step_with_info`).

        Raises:
            ValueError: as :meth:`step_with_info`; and (``equinox`` runtime error) where the
                next state is not finite: the step diverged (:meth:`step_with_info` reports
                it in ``info.diverged`` instead, and :meth:`rollout` holds the last finite state).
        """
        x_next = self.step_with_info(x, u)[0]
        return _checks.error_if(
            x_next, ~jnp.all(jnp.isfinite(x_next)),
            "the step diverged: the next state is not finite (step_with_info reports it as info.diverged)",
        )

    def step_and_jacobians(self, x: ArrayLike, u: ArrayLike) -> tuple[Array, Array, Array]:
        """``(x_next, f_x, f_u)``: one step and its Jacobians ``(nx, nx)``, ``(nx, nu)``.

        Equal to ``step`` and ``jax.jacfwd(step, argnums=(0, 1))``, computed faster with hard
        contact and ``derivative="implicit"``: one solve, then separate derivatives of the
        step's equations with respect to ``q``, ``v`` and ``u`` (a single ``jacfwd`` pushes all
        ``nx + nu`` directions through the kinematics, though only the ``nq`` of ``q`` move it).
        For joint-torque systems with sphere-half-space contacts (Solo-12) those with respect
        to ``q`` and ``v`` are in closed form (world-frame analytic RNEA and contact
        derivatives, :mod:`rsmooth.sim._derivatives`), plus one forward-mode tangent per free
        flyer along its quaternion's radial direction; other systems use forward mode (the
        ``v`` and ``u`` passes reuse the primal kinematics). The closed form assumes unit quaternions (every
        state the step returns, and :meth:`project_state`'s): for a quaternion of norm
        ``1 + e`` the bodies are not rigid and the configuration columns differ from
        ``jacfwd`` by ``O(e)``. The optimizers of :mod:`rsmooth.control` use this method when
        a dynamics has it.
        """
        x, u = self._check(x, u)
        if not (isinstance(self.contact, str) and self.derivative == "implicit"):
            fx, fu = jax.jacfwd(self.step, argnums=(0, 1))(x, u)
            return self.step(x, u), fx, fu
        q, v = self.split(x)
        x_next, fx, f_drive = _step_and_jacobians(self, q, v, self._drive(u, x))
        if not self.na:
            return x_next, fx, f_drive
        # The actuator states: their columns are the velocity update's through the forces (the
        # drive's tail), their rows their own update's.
        act = self.activations(x)
        next_of = lambda a, c: self._next_activations(a, jnp.concatenate([c, a]))  # noqa: E731
        by_act, by_u = jax.jacfwd(next_of, argnums=(0, 1))(act, u)
        nu, na = self.nu, self.na
        fx = jnp.block([[fx, f_drive[:, nu:]], [jnp.zeros((na, fx.shape[1]), fx.dtype), by_act]])
        fu = jnp.concatenate([f_drive[:, :nu], by_u])
        return jnp.concatenate([x_next, next_of(act, u)]), fx, fu

    def rollout(self, x0: ArrayLike, us: ArrayLike, feedback=None, *, throw: bool = False) -> tuple[Array, StepInfo]:
        """States ``(T + 1, nx)`` from ``x0`` under inputs ``us`` ``(T, nu)``, warm-starting
        each contact solve from the previous impulses, and the per-step diagnostics.

        ``feedback``, if given, is a state-feedback term ``x -> (nu,)`` (e.g. a PD around a
        posture) added to ``us[t]`` at every step: the input of step ``t`` is
        ``us[t] + feedback(x_t)``.

        From the first step whose ``info.diverged`` is set, the state is held at the last
        valid one (and ``diverged`` stays set), so a diverging sample of a batch stays
        finite instead of turning into NaN (or a runtime error) several steps later.

        Every step's contact solve and divergence are in the returned ``infos``
        (``infos.ncp.result``, ``infos.diverged``; traced inside
        ``rsmooth._checks.without_traced_checks``, an invalid contact problem is
        ``RESULTS.invalid_input`` rather than a runtime error): :func:`check_steps` counts them and warns;
        ``throw=True`` raises (an ``equinox`` runtime error) where any step diverged or left its
        contact solve unconverged."""
        x0, us = jnp.asarray(x0), jnp.asarray(us)
        if us.ndim != 2 or us.shape[1] != self.nu:
            raise ValueError(f"us must have shape (T, nu) = (T, {self.nu}), got {us.shape}")

        def body(carry, u):
            state, diverged = carry
            if feedback is not None:
                u = u + feedback(state.x)
            state_next, info = step(self, state, u)
            diverged = diverged | info.diverged
            state_next = jax.tree.map(lambda new, old: jnp.where(diverged, old, new), state_next, state)
            info = eqx.tree_at(lambda i: i.diverged, info, diverged)
            return (state_next, diverged), (state_next.x, info)

        _, (xs, infos) = jax.lax.scan(body, (_stages.make_state(self, x0), jnp.zeros((), bool)), us)
        xs = jnp.concatenate([x0[None], xs])
        if throw:
            xs = eqx.error_if(
                xs, jnp.any(infos.diverged) | ~jnp.all(infos.ncp.converged),
                "the rollout has a diverged step or an unconverged contact solve (infos.diverged, infos.ncp.result)",
            )
        return xs, infos


def step(system: RigidBodySystem, state: _stages.State, u: ArrayLike) -> tuple[_stages.State, StepInfo]:
    """One time step from a :class:`State` (made by :func:`make_state`): the next state, whose
    impulses warm-start the next hard-contact solve, and the step's diagnostics.

    The same step as :meth:`RigidBodySystem.step_with_info` (its checks, derivative and
    diagnostics), with the warm start carried in the state; :meth:`RigidBodySystem.rollout`
    is a ``lax.scan`` of it. The stages it runs are public (:mod:`rsmooth.sim._stages`).
    """
    if state.impulse.shape != (3 * system.num_contacts,):
        raise ValueError(
            f"state.impulse must have shape (3 n,) = ({3 * system.num_contacts},) for this system's "
            f"{system.num_contacts} candidate contacts, got {state.impulse.shape} (make_state(system, x) makes one)"
        )
    warm_start = state.impulse if isinstance(system.contact, str) else None
    x_next, info = system.step_with_info(state.x, u, warm_start=warm_start)
    q_next, v_next = system.split(x_next)
    return _stages.State(q_next, v_next, info.impulse, system.activations(x_next) if system.na else None), info


_compose_batch = jax.vmap(spatial.compose)


def _joined_points(parts: list[tuple], order: np.ndarray | None = None) -> tuple:
    """The ``(joint1, point1, joint2, point2, weight)`` of several blocks of contacts
    (:meth:`RigidBodySystem._shape_contacts`) concatenated, then taken in ``order``: the joints
    are static tuples, the rest arrays."""
    joint1, point1, joint2, point2, weight = zip(*parts)
    joint1, joint2 = (np.concatenate([np.asarray(j, np.int64) for j in joints]) for joints in (joint1, joint2))
    point1, point2, weight = (jnp.concatenate(values) for values in (point1, point2, weight))
    if order is not None:
        joint1, point1, joint2, point2, weight = (values[order] for values in (joint1, point1, joint2, point2, weight))
    return tuple(map(int, joint1)), point1, tuple(map(int, joint2)), point2, weight


def _bounding_gaps(shape1, pose1, shape2, pose2) -> Array:
    """Lower bounds ``(P,)`` on the signed distances of ``P`` pairs of shapes (arrays stacked
    along a leading axis, one class per side): the gap between their bounding spheres about
    the shapes' frame origins, or where shape 1 is a half-space, the height of shape 2's
    bounding sphere above its plane. A pair whose gap exceeds its margin has no contact."""
    centre = pose2[1] - pose1[1]
    if isinstance(shape2, HalfSpace):
        return _bounding_gaps(shape2, pose2, shape1, pose1)
    radius = jax.vmap(lambda shape: shape.bounding_radius)  # per pair (a stacked shape's own would pool them)
    radius2 = radius(shape2)
    if isinstance(shape1, HalfSpace):
        return jnp.sum(centre * pose1[0][:, :, 2], axis=-1) - radius2
    radius1 = radius(shape1)
    return jnp.sqrt(jnp.sum(centre**2, axis=-1)) - radius1 - radius2


# Bytes that one evaluation of a pair group's collision may take for its largest intermediate
# arrays (_collide_group): above it, the group's pairs go through in batches.
_GROUP_BYTES = 2**30


def _collide_group(shape1, pose1, shape2, pose2, margin, budget: int = _GROUP_BYTES) -> Contacts:
    """:func:`~rsmooth.sim._collision.collide` over a group's pairs (shapes and poses stacked
    along a leading axis): ``vmap``-ed, or in batches (``lax.map``, one copy of the code
    still) where the whole group would take more than ``budget`` bytes. The largest
    intermediates are those of the separating-axis test over edge pairs, about 16 arrays of
    ``edges1 x edges2`` entries per pair: a convex mesh's edges, a dozen for other shapes."""
    count = jax.tree.leaves(pose1)[0].shape[0]
    edges = [shape.edge_segments.shape[1] if isinstance(shape, ConvexMesh) else 12 for shape in (shape1, shape2)]
    per_pair = 16 * jax.tree.leaves(pose1)[0].dtype.itemsize * edges[0] * edges[1]
    batch = max(1, budget // per_pair)
    one = lambda a, pa, b, pb: collide(a, pa, b, pb, margin=margin)  # noqa: E731
    if batch >= count:
        return jax.vmap(one)(shape1, pose1, shape2, pose2)
    return lax.map(lambda args: one(*args), (shape1, pose1, shape2, pose2), batch_size=batch)


def _group_key(shape) -> tuple:
    """What pairs of one group share of a shape (:func:`_pair_groups`): its class, static
    fields and array shapes; for a convex mesh, the power of 2 at or above its vertex count
    (:meth:`RigidBodySystem._group_shapes` pads the meshes of a group to common array shapes, at
    most about twice their entries)."""
    if isinstance(shape, ConvexMesh):
        return (ConvexMesh, int(np.ceil(np.log2(shape.vertices.shape[0]))))
    return (jax.tree.structure(shape), tuple(np.shape(leaf) for leaf in jax.tree.leaves(shape)))


def _reversed(pair: GeomPair) -> bool:
    """Whether a pair group evaluates the pair in the reverse of its order: where its shape
    types are in the reverse of their collision function's order (a mesh against a sphere;
    :func:`~rsmooth.sim._collision.collide` then swaps them and its result) and both shapes
    move (or neither), so that pairs of both orders share a group: evaluated in the function's
    order (:meth:`RigidBodySystem._group_shapes`) and swapped back (:func:`_unreversed`), to the
    bit. (A fixed shape against a moving one keeps its order: a group's shapes on one side are
    all fixed or all moving.)"""
    return _lookup(pair.shape1, pair.shape2)[1] and (pair.frame1 is None) == (pair.frame2 is None)


def _unreversed(manifold: Contacts, reversed_: np.ndarray) -> Contacts:
    """The manifolds of a group (leading pair axis) with those of the pairs marked in
    ``reversed_`` (bool, per pair) swapped back to their pairs' own order."""
    if not np.any(reversed_):
        return manifold
    flip = lambda swapped, own: jnp.where(reversed_.reshape((-1,) + (1,) * (own.ndim - 1)), swapped, own)  # noqa: E731
    return jax.tree.map(flip, _swapped(manifold), manifold)


def _pair_groups(pairs: tuple[GeomPair, ...]) -> list[list[int]]:
    """The indices of the geometry pairs, grouped so that one ``vmap``-ed collision evaluates
    each group: the same shape classes with the same static fields and array shapes (convex
    meshes: vertex counts within the same power of 2, :func:`_group_key`), each shape in a
    moving frame or fixed alike, and the same margin, in either order (:func:`_reversed`).
    Groups in order of their first pair."""
    groups: dict = {}
    for index, pair in enumerate(pairs):
        sides = [(_group_key(pair.shape1), pair.frame1 is None), (_group_key(pair.shape2), pair.frame2 is None)]
        if _reversed(pair):
            sides.reverse()
        groups.setdefault((*sides, pair.margin), []).append(index)
    return list(groups.values())


# joints whose position limits Joints.limits enforces
_LIMITED_TYPES = ("revolute", "prismatic", "spherical")
_SPRING_TYPES = (REVOLUTE, PRISMATIC, SPHERICAL)


def _limit_rows(model: Model, joint_limits) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Configuration indices, velocity indices and sides (``+1`` lower, ``-1`` upper) of
    :attr:`Joints.limits`, checked against the model (side 0: a spherical
    joint's cone, its configuration index the joint's first)."""
    if not isinstance(joint_limits, tuple):
        raise ValueError(f"joint_limits must be a tuple of (dof, side) pairs, got {joint_limits!r}")
    owner = {model.idx_v[j]: j for j in range(1, len(model.joint_types)) if model.joint_types[j] in _LIMITED_TYPES}
    indices, dofs, sides = [], [], []
    for entry in joint_limits:
        valid = isinstance(entry, tuple) and len(entry) == 2 and entry[0] in owner
        if valid:
            spherical = model.joint_types[owner[entry[0]]] == "spherical"
            valid = entry[1] in ((0,) if spherical else (1, -1))
        if not valid:
            raise ValueError(
                f"joint_limits entries must be (dof, side) with dof the velocity index of a revolute or "
                f"prismatic joint and side +1 (lower) or -1 (upper), or the first velocity index of a spherical "
                f"joint and side 0 (its cone) ({sorted(owner)}), got {entry!r}"
            )
        joint = owner[entry[0]]
        bound = model.lower_position_limit if entry[1] > 0 else model.upper_position_limit
        if not _checks.is_traced(bound) and not np.isfinite(np.asarray(bound)[model.idx_q[joint]]):
            side = {1: "lower", -1: "upper", 0: "cone"}[entry[1]]
            raise ValueError(f"joint_limits: joint {model.joint_names[joint]!r} has no finite {side} position limit")
        indices.append(model.idx_q[joint])
        dofs.append(entry[0])
        sides.append(entry[1])
    return np.asarray(indices, np.int64), np.asarray(dofs, np.int64), np.asarray(sides, np.int64)


def _check_concrete(name, value, positive=False, allow_inf=False) -> None:
    """A host check of a physical value (skipped where traced): non-negative, or positive, and
    finite, or ``+inf`` where ``allow_inf``; else a ValueError naming it."""
    if value is None or _checks.is_traced(value):
        return
    array = np.asarray(value, dtype=float)
    bad = np.isnan(array) | (np.isinf(array) & (not allow_inf or array < 0))
    bad |= array <= 0 if positive else array < 0
    if np.any(bad):
        bound = "positive" if positive else "non-negative"
        raise ValueError(f"{name} must be {bound}{'' if allow_inf else ' and finite'}, got {array}")


@eqx.filter_jit
def _first_term(system: RigidBodySystem, terms: str, q: Array) -> Array:
    """``getattr(system, terms)(q)[0]``, jitted: the constraints' errors are called eagerly (a
    script checking a rollout, a test at random configurations), where their few hundred small
    operations would each be compiled and dispatched; inside a caller's jit it is inlined."""
    return getattr(system, terms)(q)[0]


# Jitted, a nested jit inside its callers' programs, so that a program that steps a system in
# several places (a rollout, DDP's forward pass beside its Jacobians) traces the step once:
# JAX keeps a jitted function's trace for arguments of the same structure and shapes.
@eqx.filter_jit
def _step_with_info(system: RigidBodySystem, x: Array, u: Array, warm_start) -> tuple[Array, StepInfo]:
    """:meth:`RigidBodySystem.step_with_info` after its checks."""
    q, v = system.split(x)
    act, u = system.activations(x), system._drive(u, x)
    if isinstance(system.contact, str) and system.derivative == "implicit":
        v_next, impulse, distance, ncp, clipped, contact = _implicit_velocity_update(system, q, v, u, warm_start)
    else:
        update = system._velocity_update(q, v, u, warm_start)
        v_next, impulse, distance, ncp, clipped, contact = update.public()
    q_next, v_next = _stages.advance(system, q, v_next)
    x_next = jnp.concatenate([q_next, v_next, system._next_activations(act, u)])
    diverged = ~jnp.all(jnp.isfinite(x_next)) | ~(jnp.max(jnp.abs(v_next), initial=0.0) * system.time_step <= system.max_motion_per_step)
    frames, velocity, dropped, joint_impulse = lax.stop_gradient(contact)
    force, mode = system._contact_diagnostics(impulse, frames, velocity)
    info = StepInfo(
        distance=distance, impulse=impulse, ncp=ncp, torque_clipped=clipped, diverged=diverged, force=force,
        mode=mode, dropped_contacts=dropped, skipped_pairs=system.skipped_pairs(q), joint_impulse=joint_impulse,
        inside_side_sites=system.inside_side_sites(q),
    )
    return x_next, info


@eqx.filter_custom_jvp
def _implicit_velocity_update(system: RigidBodySystem, q: Array, v: Array, u: Array, warm_start):
    """``(v_next, impulse, distance, ncp, clipped)`` of a hard-contact step, with the
    derivative of :attr:`RigidBodySystem.derivative` ``= "implicit"``."""
    return system._velocity_update(q, v, u, warm_start).public()


@_implicit_velocity_update.def_jvp
def _implicit_velocity_update_jvp(primals, tangents):
    # The step's velocity update solves, for the unknowns (v+, lambda) at parameters
    # theta = (system, q, v, u):
    #   E(theta, v+, lambda) = h ID(q, v, (v+ - v) / h) - h tau(q, u) - J(q)ᵀ lambda = 0,
    #   F(lambda, c(theta, v+), mu) = 0,  c = J(q) v+ + phi-correction(q)  (= G lambda + g),
    # with ID the inverse dynamics M a + b (plus armature) and F the NCP's natural map.
    # dE/dv+ = M, dE/dlambda = -Jᵀ, so at fixed lambda dv+ = -M^-1 dE|_theta and
    # dc|_lambda = dc|_theta - J M^-1 dE|_theta; the NCP's implicit solve gives dlambda from
    # dF|_lambda = dF/dc dc|_lambda + dF/dmu dmu, then dv+ = M^-1 (Jᵀ dlambda - dE|_theta).
    # The only tangent pass is through ID and contact kinematics (no CRBA, Cholesky or
    # Delassus derivative); the factors are primal and shared by all columns under jacfwd.
    system, q, v, u, warm_start = primals
    t_system, t_q, t_v, t_u, _ = tangents
    update = system._velocity_update(q, v, u, warm_start)
    residuals = _step_residuals(update)
    outputs, output_tangents = eqx.filter_jvp(residuals, (system, q, v, u), (t_system, t_q, t_v, t_u))
    momentum_dot, velocity_dot, distance_dot, mu_dot, bounds_dot = (
        jnp.zeros_like(primal) if tangent is None else tangent for primal, tangent in zip(outputs, output_tangents)
    )
    v_next_dot, impulse_dot = _velocity_update_tangent(system, update, momentum_dot, velocity_dot, mu_dot, bounds_dot)
    no_tangent = jax.tree.map(lambda _: None, update.ncp)  # diagnostics: symbolic zeros
    return update.public(), (v_next_dot, impulse_dot, distance_dot, no_tangent, None, (None, None, None, None))


def _step_residuals(update: _VelocityUpdate):
    """The step's equations at the solution ``(v+, lambda)`` of ``update``, as a function of
    the parameters ``(system, q, v, u)``: ``(E, c, distance, mu, bounds)`` (see the JVP rule
    above; ``c`` and ``lambda`` hold the solved contacts' rows, then the joints' box rows,
    :meth:`RigidBodySystem.joint_rows`, with their bounds).

    ``residuals(system, q, v, u, geometry=None)``: ``geometry`` is what depends on ``q`` only,
    ``(kinematics, inertias, distance, J)``; pass the primal one (``update``'s) to differentiate
    with respect to ``v`` or ``u`` without tracing the kinematics again."""
    v_next, impulse = lax.stop_gradient(update.v_next), lax.stop_gradient(update.solved_impulse())

    def residuals(system: RigidBodySystem, q: Array, v: Array, u: Array, geometry=None):
        model, h = system.model, system.time_step
        if geometry is None:
            kinematics = _dynamics._kinematics(model, q)
            inertias = _dynamics._world_inertias(model, kinematics)
            distance, _, jacobian = system.contacts(q, kinematics)
        else:
            kinematics, inertias, distance, jacobian = geometry
        v_start, removed = _dynamics._free_flyer_start(model, v, h)
        acceleration = (v_next - v_start) / h
        inverse_dynamics = (
            _dynamics._rnea(model, kinematics, inertias, v, acceleration, model.gravity)
            - removed
            + model.armature * acceleration
            + system.damping() * v_next  # implicit damping: dE/dv+ = M + h D, the factored W
            - system.passive_forces(q, v)  # explicit springs and tendon dampers: at the step's start
        )
        tau, _ = system.generalized_forces(q, u, kinematics, v)
        solved_distance, mu = distance, system.contact_friction()
        if update.selection is not None:  # the solved contacts' equations (a fixed selection)
            solved_distance, jacobian, mu = distance[update.selection], update.solved(jacobian), mu[update.selection]
        velocity = corrected_free_velocity(jacobian @ v_next, solved_distance, h, **system.options.correction)
        # the joints' box rows (dry friction within h effort, couplings with their correction)
        joint_rows, joint_correction, bounds = system.joint_rows(q)
        if joint_rows.shape[0]:
            jacobian = jnp.concatenate([jacobian, joint_rows.astype(jacobian.dtype)])
            velocity = jnp.concatenate([velocity, joint_rows @ v_next + joint_correction])
        # J^T lambda as an unrolled sum of rows: under jacfwd/vmap a dot transposes J's
        # batch and a reduction goes to YNNPACK, both several times slower on CPU (_spatial)
        momentum = h * (inverse_dynamics - tau) - sum(impulse[i] * jacobian[i] for i in range(impulse.shape[0]))
        return momentum, velocity, distance, mu, bounds

    return residuals


def _velocity_update_tangent(
    system: RigidBodySystem,
    update: _VelocityUpdate,
    momentum_dot: Array,
    velocity_dot: Array,
    mu_dot: Array,
    bounds_dot: Array | None = None,
) -> tuple[Array, Array]:
    """``(dv+, dlambda)`` from the change of the step's equations at fixed ``(v+, lambda)``
    (``velocity_dot``: that of the solved rows, the contacts' then the joints' box rows';
    ``mu_dot`` of the solved contacts; ``bounds_dot`` of the box rows' bounds, ``None``
    for zero; ``dlambda``: every candidate contact's, zero where a budget left it out)."""
    impulse = lax.stop_gradient(update.solved_impulse())
    jacobian = update.solved(update.jacobian)
    m = update.joint_rows.shape[0]
    if m:
        jacobian = jnp.concatenate([jacobian, update.joint_rows.astype(jacobian.dtype)])
    solve = many_column_solver(update.mass_factor, momentum_dot)
    free_motion_dot = -solve(momentum_dot)  # dv+ at fixed lambda
    if impulse.shape[0] == 0:  # no contact nor friction row: the free motion is the whole step
        return free_motion_dot, jnp.zeros((0,) + free_motion_dot.shape[1:], free_motion_dot.dtype)
    minv_jt = solve(jacobian.T)  # primal: once for all tangents (a product where M^-1 is formed)
    velocity_dot = velocity_dot + jacobian @ free_motion_dot
    G, g, mu = update.delassus, update.free_velocity, update.mu
    bounds = lax.stop_gradient(update.joint_bounds).astype(G.dtype) if m else None
    step_sizes = fixed_point_step_sizes(G, mu.shape[0])
    # dF at fixed lambda, as explicit (3 n x 3 n) and (3 n x n) matrices so that the
    # tangents may be vectors (a JVP) or matrices of columns (step_and_jacobians)
    by_velocity, by_mu = jax.jacfwd(
        lambda c, mu_: natural_map_of_velocity(impulse, c, mu_, step_sizes, bounds), argnums=(0, 1)
    )(G @ impulse + g, mu)
    rhs = by_velocity @ velocity_dot + by_mu @ mu_dot
    if bounds is not None and bounds_dot is not None:
        by_bounds = jax.jacfwd(lambda b: natural_map_of_velocity(impulse, G @ impulse + g, mu, step_sizes, b))(bounds)
        rhs = rhs + by_bounds @ bounds_dot
    impulse_dot = implicit_impulse_tangent(
        system.solver.implicit_regularization, impulse, G, g, mu, step_sizes, rhs, bounds
    )
    v_next_dot = free_motion_dot + minv_jt @ impulse_dot
    impulse_dot = impulse_dot[: impulse_dot.shape[0] - m]
    if update.selection is not None:
        full = jnp.zeros((update.impulse.shape[0],) + impulse_dot.shape[1:], impulse_dot.dtype)
        impulse_dot = full.at[_stages.flat_rows(update.selection)].set(impulse_dot)
    return v_next_dot, impulse_dot


@eqx.filter_jit  # (see _step_with_info)
def _step_and_jacobians(system: RigidBodySystem, q: Array, v: Array, u: Array) -> tuple[Array, Array, Array]:
    """``(x_next, f_x, f_u)`` of a hard-contact step by the implicit rule, with separate
    derivatives of the step's equations with respect to ``q``, ``v`` and ``u`` (closed forms
    for ``q`` and ``v`` where :mod:`._derivatives` supports the system)."""
    model, h = system.model, system.time_step
    closed_form = _derivatives.supported(system)
    if closed_form:
        update = system._velocity_update(q, v, u, None)
    else:
        # The kinematics and the contacts linearized once: the update takes their primal
        # values, the configuration pass their tangents, so that the traced graph holds the
        # collision (and its GJK loops) once rather than again inside a forward-mode pass.
        def geometry_of(q_):
            kinematics = _stages.kinematics(system, q_)
            return kinematics, _stages.collision(system, q_, kinematics)

        (kinematics, contacts), geometry_tangent = jax.linearize(geometry_of, q)
        update = system._velocity_update(q, v, u, None, (kinematics, contacts))
    residuals = _step_residuals(update)
    # v and u do not enter the kinematics: their passes reuse the update's primal geometry,
    # so the traced graph (and the compile time of every solver built on it) holds it once.
    geometry = (update.kinematics, update.inertias, update.distance, update.jacobian)
    if closed_form:
        # closed forms over the configuration tangent and the velocity, plus one forward-mode
        # tangent per free flyer along its quaternion's radial direction
        by_q, by_v = _derivatives.configuration_jacobian(system, update, residuals, q, v, u)
    else:

        def along(dq):
            d_kinematics, d_contacts = geometry_tangent(dq)

            def equations(q_, kinematics_, distance_, jacobian_):
                inertias = _dynamics._world_inertias(model, kinematics_)
                return residuals(system, q_, v, u, (kinematics_, inertias, distance_, jacobian_))[:2]

            primals = (q, kinematics, contacts.distance, contacts.jacobian)
            return jax.jvp(equations, primals, (dq, d_kinematics, d_contacts.distance, d_contacts.jacobian))[1]

        by_q = jax.vmap(along, out_axes=-1)(jnp.eye(model.nq, dtype=q.dtype))
        by_v = jax.jacfwd(lambda v_: residuals(system, q, v_, u, geometry)[:2])(v)
    by_u = jax.jacfwd(lambda u_: residuals(system, q, v, u_, geometry)[:2])(u)
    momentum_dot, velocity_dot = (jnp.concatenate(parts, axis=1) for parts in zip(by_q, by_v, by_u))
    columns = momentum_dot.shape[1]
    mu_dot = jnp.zeros((update.mu.shape[0], columns), momentum_dot.dtype)
    v_next_dot, _ = _velocity_update_tangent(system, update, momentum_dot, velocity_dot, mu_dot)
    v_next = lax.stop_gradient(update.v_next)
    q_next = _stages.integrate_decoupled(model, q, v_next, h)
    integrate_q, integrate_v = jax.jacfwd(lambda a, b: _stages.integrate_decoupled(model, a, b, h), argnums=(0, 1))(q, v_next)
    q_next_dot = integrate_v @ v_next_dot + jnp.pad(integrate_q, ((0, 0), (0, columns - model.nq)))
    new_axes = jax.jacfwd(lambda b: _dynamics._free_flyer_new_axes(model, b, h))(v_next)
    jacobian = jnp.concatenate([q_next_dot, new_axes @ v_next_dot])
    nx = model.nq + model.nv
    v_next = _dynamics._free_flyer_new_axes(model, v_next, h)
    return jnp.concatenate([q_next, v_next]), jacobian[:, :nx], jacobian[:, nx:]


def _point_jacobian(model: Model, kinematics, joint: int, point: Array) -> Array:
    """Jacobian ``(3, nv)`` of the world velocity of the body-``joint`` point at world ``point``."""
    return _dynamics._point_velocity_columns(model, kinematics, joint, point).T


def _angular_jacobian(model: Model, kinematics, joint: int) -> Array:
    """Jacobian ``(3, nv)`` of body ``joint``'s angular velocity in world axes."""
    return _dynamics._support_columns(model, kinematics, joint)[:, 3:].T


class SimulationWarning(UserWarning):
    """A simulation had unconverged contact solves or diverged steps (:func:`check_steps`)."""


def check_steps(infos: StepInfo, *, what: str = "the simulation") -> dict[str, int]:
    """Counts the steps whose contact solve did not succeed, those that diverged, those
    whose contact budget left out a closing contact and those whose broad phase left out a
    pair that may touch, and warns (:class:`SimulationWarning`)
    if there is any.

    Host-side, on concrete diagnostics (e.g. the ``infos`` of :meth:`RigidBodySystem.rollout`,
    any batch shape): the experiments call it on their rollouts, so that such steps are never
    silent. The warning gives, for each unsuccessful :class:`~rsmooth.RESULTS` item of
    ``infos.ncp.result``, its count and message. Use
    ``warnings.simplefilter("error", SimulationWarning)`` to make them errors.

    Args:
        infos: a :class:`StepInfo` with leading axes (steps, samples, ...).
        what: the name of the simulation, for the message.

    Returns:
        ``{"steps", "unconverged_steps", "diverged_steps", "dropped_contact_steps",
        "skipped_pair_steps", "inside_side_site_steps"}``: ``unconverged_steps`` counts the contact solves whose result
        is not ``RESULTS.successful``, ``dropped_contact_steps`` the steps with
        ``infos.dropped_contacts > 0`` (:attr:`Options.max_contacts` or
        :attr:`Options.max_limits` too small),
        ``skipped_pair_steps`` those with ``infos.skipped_pairs > 0``
        (:attr:`Options.max_pairs` too small), ``inside_side_site_steps`` those that started
        with a tendon's side site inside its wrapping shape (``infos.inside_side_sites > 0``,
        where the tendon's path is not MuJoCo's).
    """
    result = infos.ncp.result
    diverged = np.asarray(infos.diverged)
    failures = {
        name: int(np.sum(np.asarray(result == getattr(RESULTS, name))))
        for name in ("max_iterations_reached", "nonfinite", "invalid_input")
    }
    successful = np.asarray(result == RESULTS.successful)
    counts = {
        "steps": int(successful.size),
        "unconverged_steps": int(np.sum(~successful)),
        "diverged_steps": int(np.sum(diverged)),
        "dropped_contact_steps": int(np.sum(np.asarray(infos.dropped_contacts) > 0)),
        "skipped_pair_steps": int(np.sum(np.asarray(infos.skipped_pairs) > 0)),
        "inside_side_site_steps": int(np.sum(np.asarray(infos.inside_side_sites) > 0)),
    }
    if counts["inside_side_site_steps"]:
        warnings.warn(
            f"{what}: in {counts['inside_side_site_steps']} of {counts['steps']} steps a spatial tendon's side site "
            f"was inside its wrapping shape (StepInfo.inside_side_sites), where MuJoCo wraps through the shape: "
            f"that wrapping is not modelled, and those steps' tendon lengths and forces are not MuJoCo's",
            SimulationWarning,
            stacklevel=2,
        )
    if counts["skipped_pair_steps"]:
        warnings.warn(
            f"{what}: in {counts['skipped_pair_steps']} of {counts['steps']} steps the broad phase (max_pairs) "
            f"left out geometry pairs within their margin (StepInfo.skipped_pairs, at most "
            f"{int(np.max(np.asarray(infos.skipped_pairs)))} in a step): raise max_pairs",
            SimulationWarning,
            stacklevel=2,
        )
    if counts["dropped_contact_steps"]:
        warnings.warn(
            f"{what}: in {counts['dropped_contact_steps']} of {counts['steps']} steps the contact budget "
            f"(max_contacts, max_limits) left out contacts or joint limits whose gap the step closes "
            f"(StepInfo.dropped_contacts, at most {int(np.max(np.asarray(infos.dropped_contacts)))} in a step): "
            f"raise max_contacts or max_limits",
            SimulationWarning,
            stacklevel=2,
        )
    if counts["unconverged_steps"] or counts["diverged_steps"]:
        reasons = "".join(
            f"; {count} {name}: {RESULTS[getattr(RESULTS, name)]}" for name, count in failures.items() if count
        )
        warnings.warn(
            f"{what}: {counts['unconverged_steps']} of {counts['steps']} steps left the contact solve "
            f"unconverged and {counts['diverged_steps']} diverged (StepInfo.ncp.result, StepInfo.diverged)"
            f"{reasons}",
            SimulationWarning,
            stacklevel=2,
        )
    return counts


def energy(system: RigidBodySystem, x: ArrayLike) -> Array:
    """Total mechanical energy ``1/2 v^T M v + potential`` of a state (gravity potential
    ``-m g . c`` of every body's centre of mass, plus the joint springs'
    :meth:`~RigidBodySystem.spring_energy`); shape ``()``."""
    model = system.model
    q, v = system.split(jnp.asarray(x))
    kinematics = _dynamics._kinematics(model, q)
    mass = _dynamics._crba(model, kinematics, _dynamics._world_inertias(model, kinematics)) + jnp.diag(model.armature)
    coms = kinematics.translation + jnp.einsum("jab,jb->ja", kinematics.rotation, model.body_com)
    potential = -jnp.sum(model.body_mass * (coms @ model.gravity)) + system.spring_energy(q)
    return 0.5 * v @ mass @ v + potential
