"""The stages of one time step, as public functions of a system: kinematics, collision, free
motion, contact solve, integration.

:meth:`RigidBodySystem.step` runs them in this order (the four steps of
:mod:`rsmooth.sim._simulator`'s docstring) and differentiates the whole velocity update at once
by the implicit function theorem. Called one by one they give what the step computes in
between: the contact candidates and their Jacobian, the free-motion velocity, the contact
problem and its impulses, e.g. to inspect a contact, add a force between stages or test a
contact law. Composed as :func:`step_stages` does, they give the step's result to rounding.
Under ``jax.grad``/``jacfwd`` a composition differentiates each stage on its own (the contact
solve by :func:`~rsmooth.sim.solve_ncp`'s implicit rule), the same derivative computed less
directly than the step's.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.typing import ArrayLike

from rsmooth import _linalg as linalg
from rsmooth._results import RESULTS
from rsmooth.sim import _dynamics
from rsmooth.sim import _spatial as spatial
from rsmooth.sim._contact import corrected_free_velocity
from rsmooth.sim._dynamics import Kinematics
from rsmooth.sim._model import Model
from rsmooth.sim._ncp import NCPInfo, solve_ncp

if TYPE_CHECKING:  # the system's module imports this one
    from rsmooth.sim._simulator import RigidBodySystem

Array = jax.Array

__all__ = [
    "ContactGeometry", "ContactSolution", "FreeMotion", "Kinematics", "State", "advance", "collision", "free_motion",
    "kinematics", "make_state", "solve_contacts", "step_stages",
]


class State(eqx.Module):
    """A system's state as a step carries it (:func:`~rsmooth.sim.step`).

    Attributes:
        q: configuration ``(nq,)``.
        v: velocity ``(nv,)`` (Pinocchio's conventions; see :mod:`rsmooth.sim._simulator`).
        impulse: the contact impulses ``(3 n,)`` of the step that led here (zeros at the start),
            from which the next hard-contact solve starts: a warm start changes how many
            iterations the solve takes, and its answer only where the contact problem has
            several solutions (e.g. a rigid finger whose friction can carry part of a sliding
            box's weight).
        act: the actuator states ``(na,)`` (:class:`~rsmooth.sim.ActivationDynamics`), ``None``
            for a system without any.
    """

    q: Array
    v: Array
    impulse: Array
    act: Array | None = None

    @property
    def x(self) -> Array:
        """The flat state ``[q, v, act]`` that ``step(x, u)`` and the optimizers use."""
        return jnp.concatenate([self.q, self.v] + ([] if self.act is None else [self.act]))


def make_state(system: RigidBodySystem, x: ArrayLike | None = None) -> State:
    """The :class:`State` of `system` at ``x = [q, v, act]`` (default: the system's
    :meth:`~RigidBodySystem.initial_state`), with zero impulses.

    Raises:
        ValueError: if ``x`` is not of shape ``(nx,)``.
    """
    x = system.initial_state() if x is None else jnp.asarray(x)
    if x.shape != (system.nx,):
        raise ValueError(f"x must have shape (nx,) = ({system.nx},), got {x.shape}")
    q, v = system.split(x)
    act = system.activations(x) if system.na else None
    return State(q, v, jnp.zeros(3 * system.num_contacts, jnp.result_type(x, float)), act)


class WitnessPoints(eqx.Module):
    """Where the candidate contacts act, from which any rows of their Jacobian, and their
    velocities ``J v``, are computed without forming ``J`` for every candidate: a step under a
    contact budget (:attr:`Options.max_contacts`) builds the rows of the contacts it solves
    only, and counts the ones it leaves out from their velocities (:func:`solve_contacts`).

    Attributes:
        joint1, joint2: the joints (bodies) carrying shape 1's and shape 2's witness points, one
            per contact between shapes (``n_s``, static; 0: the world).
        point1, point2: the witness points ``(n_s, 3)`` in world axes.
        weight: ``(n_s,)`` 1 for a contact of its pair's manifold, 0 for an inactive entry
            (whose rows are zero).
        motion_subspace: the dofs' world motion subspace ``(nv, 6)`` at the configuration (as
            :class:`Kinematics`').
        limit_rows: the limits' rows ``(l, 3, nv)`` (frames: the identity), after the shapes'.
    """

    joint1: tuple[int, ...] = eqx.field(static=True)
    point1: Array
    joint2: tuple[int, ...] = eqx.field(static=True)
    point2: Array
    weight: Array
    motion_subspace: Array
    limit_rows: Array


class ContactGeometry(eqx.Module):
    """The candidate contacts of a configuration (:func:`collision`), in the order of
    :meth:`RigidBodySystem.contacts`.

    Attributes:
        distance: signed distances ``(n,)`` (negative: penetration).
        frames: contact frames ``(n, 3, 3)``, columns ``[t1, t2, n]`` in world axes.
        jacobian: ``(3 n, nv)``, maps ``v`` to every contact's relative velocity in its frame.
        friction: Coulomb coefficients ``(n,)`` (0 for joint limits).
        joint_rows: the joints' box rows at the configuration
            (:meth:`RigidBodySystem.joint_rows`: dry friction, couplings), ``(rows (m, nv),
            correction (m,), bounds (m,))``.
        points: where the contacts act (:class:`WitnessPoints`), from which a budgeted solve
            builds its rows; ``None``: ``jacobian`` gives the rows and velocities (set it to
            ``None`` where ``jacobian`` was changed between stages).
    """

    distance: Array
    frames: Array
    jacobian: Array
    friction: Array
    joint_rows: tuple[Array, Array, Array]
    points: WitnessPoints | None = None


class FreeMotion(eqx.Module):
    """The motion of a step without contact impulses (:func:`free_motion`).

    Attributes:
        velocity: ``v_f = s + h W^-1 (tau - b)``, the end-of-step velocity without contact
            ``(nv,)`` (in the body axes of the step's start; see the simulator's docstring).
        mass: ``W = M + diag(armature + h D)`` ``(nv, nv)``, the matrix the step solves with.
        mass_cholesky: its lower Cholesky factor ``L`` (``W = L Lᵀ``).
        inertias: the bodies' spatial inertias in world axes (``rsmooth.sim._spatial``).
        torque_clipped: whether the input was beyond ``input_limit`` and was clipped (``()``).
    """

    velocity: Array
    mass: Array
    mass_cholesky: Array
    inertias: spatial.SpatialInertia
    torque_clipped: Array


class ContactSolution(eqx.Module):
    """The contact impulses of a step and the velocity they give (:func:`solve_contacts`).

    Attributes:
        velocity: ``v+ = v_f + W^-1 Jᵀ lambda`` ``(nv,)`` (body axes of the step's start).
        impulse: ``lambda`` ``(3 n,)``, ``[t1, t2, n]`` per candidate (zero where a contact
            budget left it out).
        ncp: the contact solve's :class:`~rsmooth.sim.NCPInfo` (zero iterations and
            ``RESULTS.successful`` where nothing is solved: no candidate, or a compliant law).
        delassus: ``G = J_s W^-1 J_sᵀ`` of the solved rows ``s``: the solved contacts (every
            candidate, or a budget's selection), then the joints' ``m`` box rows (dry
            friction, couplings: :meth:`RigidBodySystem.joint_rows`), ``(3 n_s + m, 3 n_s + m)``.
        free_velocity: the solved rows' free velocity ``g`` (hard contact: ``J_s v_f`` with
            the Baumgarte and gap corrections on the contacts and the couplings, the NCP's; a
            compliant law: ``J v_f``).
        friction: the solved contacts' Coulomb coefficients.
        selection: the solved contacts' indices under a budget (:attr:`Options.max_contacts`);
            ``None``: every candidate.
        dropped: :attr:`StepInfo.dropped_contacts` (``()``, int).
        joint_impulse: ``(m,)`` the impulses of the joints' box rows: each dof's dry
            friction (:attr:`Joints.friction`, ``|.| <= effort h``), then each
            coupling's (:attr:`Joints.couplings`), then each tendon's dry friction
            (:attr:`Joints.tendons`).
    """

    velocity: Array
    impulse: Array
    ncp: NCPInfo
    delassus: Array
    free_velocity: Array
    friction: Array
    selection: Array | None
    dropped: Array
    joint_impulse: Array


def kinematics(system: RigidBodySystem, q: Array) -> Kinematics:
    """Stage 1: the world placements of the joints at ``q`` (:class:`Kinematics`)."""
    return _dynamics._kinematics(system.model, q)


def collision(system: RigidBodySystem, q: Array, kinematics: Kinematics | None = None) -> ContactGeometry:
    """Stage 2: the candidate contacts at ``q`` (:meth:`RigidBodySystem.contacts`) and their
    friction, and the joints' box rows (:meth:`RigidBodySystem.joint_rows`); ``kinematics``:
    stage 1's at ``q``, computed when not given."""
    distance, frames, jacobian, points = system._candidates(q, kinematics)
    return ContactGeometry(distance, frames, jacobian, system.contact_friction(), system.joint_rows(q), points)


def free_motion(system: RigidBodySystem, q: Array, v: Array, u: Array, kinematics: Kinematics | None = None) -> FreeMotion:
    """Stage 3: the step's velocity without contact, from the state ``(q, v)`` under input ``u``
    (clipped to ``input_limit``; not checked here: :meth:`RigidBodySystem.step` checks it),
    followed by the actuator states ``act`` where the system has some (``(nu + na,)``)."""
    model, h = system.model, system.time_step
    if kinematics is None:
        kinematics = _dynamics._kinematics(model, q)
    inertias = _dynamics._world_inertias(model, kinematics)
    damping = system.damping()
    # W = M + h D: the damping force D v+ is implicit (see the simulator's docstring)
    mass = _dynamics._crba(model, kinematics, inertias) + jnp.diag(model.armature + h * damping)
    # v+ in the body axes of the step's start: a free flyer's linear velocity moves with the
    # frame's rotation exactly, and a free object rotates torque-free, energy-conserving
    # (_dynamics._free_flyer_start), not by explicit velocity-product terms
    v_start, removed = _dynamics._free_flyer_start(model, v, h)
    bias = _dynamics._rnea(model, kinematics, inertias, v, None, model.gravity) - removed + damping * v_start - system.passive_forces(q, v)
    tau, clipped = system.generalized_forces(q, u, kinematics, v)
    cholesky = _dynamics.mass_cholesky(model, mass)
    velocity = v_start + h * _dynamics.mass_cho_solve(model, cholesky, tau - bias)
    return FreeMotion(velocity, mass, cholesky, inertias, clipped)


def solve_contacts(
    system: RigidBodySystem, motion: FreeMotion, contacts: ContactGeometry, warm_start: ArrayLike | None = None
) -> ContactSolution:
    """Stage 4: the contact impulses by the system's contact law and the velocity they give.

    Hard contact solves the frictional NCP (:func:`~rsmooth.sim.solve_ncp`, from ``warm_start``
    ``(3 n,)`` if given) on the candidates, or on a budget's closest ones, with the joints' box
    rows (dry friction, couplings); a compliant law evaluates its force, linearly implicit in
    the velocity."""
    h, cholesky = system.time_step, motion.mass_cholesky
    distance, jacobian, mu = contacts.distance, contacts.jacobian, contacts.friction
    v_free = motion.velocity
    hard = isinstance(system.contact, str)
    joint_rows, joint_correction, bounds = contacts.joint_rows  # (m, nv); a compliant system has none
    m = joint_rows.shape[0]
    # the contacts the NCP solves: every candidate, or the budget's closest ones
    selection = system._contact_selection(distance) if hard else None
    dropped = jnp.zeros((), jnp.int32)
    if selection is not None:
        rows = flat_rows(selection)
        # every candidate's velocity, from where it acts: the rows of the left-out ones are never formed
        candidates = contact_velocities(system, contacts, v_free)
        corrected = corrected_free_velocity(candidates, distance, h, **system.options.correction)
        closes = lax.stop_gradient(corrected[2::3]) < 0  # the solve would have had to act on it
        dropped = jnp.sum(closes.at[selection].set(False), dtype=jnp.int32)
        distance, jacobian, mu = distance[selection], jacobian_rows(system, contacts, selection), mu[selection]
        warm_start = None if warm_start is None else jnp.asarray(warm_start)[rows]
    contact_rows = jacobian.shape[0]
    if m:  # the joints' rows after the contacts' (box rows of the NCP)
        jacobian = jnp.concatenate([jacobian, joint_rows.astype(jacobian.dtype)])
        if warm_start is not None:
            warm_start = jnp.concatenate([jnp.asarray(warm_start), jnp.zeros(m, jacobian.dtype)])
    # X = L^-1 Jᵀ: G = Xᵀ X (symmetric by construction) and W^-1 Jᵀ lambda = L^-T (X lambda),
    # one triangular solve with 3 n columns where W^-1 Jᵀ takes two
    half = _dynamics.mass_solve_triangular(system.model, cholesky, jacobian.T)  # (nv, 3n)
    delassus = half.T @ half
    zero = jnp.zeros((), v_free.dtype)
    nothing_solved = NCPInfo(jnp.zeros((), jnp.int32), zero, zero, zero, RESULTS.successful, zero)
    if jacobian.shape[0] == 0:
        # no candidate contact nor joint row (a body in free flight, a scene without a
        # colliding pair): nothing to solve, and an empty problem is not one the NCP solver accepts
        free_velocity, impulse, ncp = jacobian @ v_free, jnp.zeros(0, v_free.dtype), nothing_solved
    elif hard:
        free_velocity = corrected_free_velocity(jacobian[:contact_rows] @ v_free, distance, h, **system.options.correction)
        if m:
            free_velocity = jnp.concatenate([free_velocity, jacobian[contact_rows:] @ v_free + joint_correction])
        # From a finite but absurd state (a simulation that has already diverged: positions
        # of 1e8 m, velocities of 1e11 rad/s) the mass matrix loses definiteness to rounding
        # and the contact problem is not finite. That is the step's divergence, which it
        # reports (a non-finite next state, info.diverged), not a bad input of the NCP
        # solver's (whose check would abort a whole batched rollout or solver iteration).
        # (checked on L^-1 Jᵀ, not on G: the solve reads G through it, and a program that
        # takes no derivative then forms G only where the start does not solve the problem)
        broken = ~(jnp.all(jnp.isfinite(half)) & jnp.all(jnp.isfinite(free_velocity)))
        impulse, ncp = solve_ncp(
            jnp.where(broken, jnp.eye(delassus.shape[0], dtype=delassus.dtype), delassus),
            jnp.where(broken, 0.0, free_velocity), mu, solver=system.solver, warm_start=warm_start,
            delassus_factor=jnp.where(broken, 0.0, half),  # G = halfᵀ half
            bounds=bounds.astype(delassus.dtype) if m else None,
        )
        impulse = jnp.where(broken, jnp.nan, impulse)
        ncp = eqx.tree_at(lambda info: info.result, ncp, RESULTS.where(broken, RESULTS.nonfinite, ncp.result))
    else:
        free_velocity = jacobian @ v_free
        impulse, ncp = compliant_impulse(system.contact, distance, free_velocity, delassus, h), nothing_solved
    velocity = v_free + _dynamics.mass_solve_triangular(system.model, cholesky, half @ impulse, trans=True)
    impulse, joint_impulse = impulse[:contact_rows], impulse[contact_rows:]
    if selection is not None:  # every candidate's impulse, zero where left out
        impulse = jnp.zeros(contacts.jacobian.shape[0], impulse.dtype).at[rows].set(impulse)
    return ContactSolution(velocity, impulse, ncp, delassus, free_velocity, mu, selection, dropped, joint_impulse)


def advance(system: RigidBodySystem, q: Array, v_next: Array) -> tuple[Array, Array]:
    """Stage 5: ``(q+, v+)``: the configuration moved by ``h v+`` (free flyers on ``R^3 x SO(3)``,
    spherical joints on ``SO(3)``) and ``v+`` written in the new body axes (the state's
    convention)."""
    model, h = system.model, system.time_step
    return integrate_decoupled(model, q, v_next, h), _dynamics._free_flyer_new_axes(model, v_next, h)


def step_stages(
    system: RigidBodySystem, state: State, u: ArrayLike
) -> tuple[State, Kinematics, ContactGeometry, FreeMotion, ContactSolution]:
    """One step as the composition of the five stages, unchecked and differentiated stage by
    stage: ``(next state, kinematics, contacts, free motion, contact solution)``.
    :func:`~rsmooth.sim.step` gives the same next state with input checks, diagnostics and the
    whole step's implicit derivative."""
    u = system._drive(jnp.asarray(u), state.x)  # the input, then the actuator states where there are some
    warm_start = state.impulse if isinstance(system.contact, str) else None
    posed = kinematics(system, state.q)
    contacts = collision(system, state.q, posed)
    motion = free_motion(system, state.q, state.v, u, posed)
    solution = solve_contacts(system, motion, contacts, warm_start)
    q_next, v_next = advance(system, state.q, solution.velocity)
    act_next = None if state.act is None else system._next_activations(state.act, u)
    return State(q_next, v_next, solution.impulse, act_next), posed, contacts, motion, solution


def compliant_impulse(law, distance: Array, free_velocity: Array, delassus: Array, h: Array) -> Array:
    """Impulses ``h f(phi, c+)`` of a compliant law, linearly implicit in the velocity.

    The law is evaluated at the end-of-step contact velocity ``c+ = c_f + G lambda``,
    linearized about the free velocity: ``lambda = h f(phi, c_f) + h D (c+ - c_f)`` with
    ``D = df/dc`` (3 x 3 per contact), so ``(I - h D G) lambda = h f(phi, c_f)``. An
    explicit force (``lambda = h f(phi, c)``) is unstable as soon as ``h`` times the
    damping or the regularized friction's viscosity (``mu f_N / v_s``) exceeds twice the
    effective mass, which for a 1 kg cube with ``v_s = 1 mm/s`` already happens at
    ``h = 2 ms``; the implicit velocity dependence removes that limit (the distance stays
    explicit, so ``h`` must still resolve the contact stiffness, ``h sqrt(k / m) < 2``).
    """
    n = distance.shape[0]
    velocity = free_velocity.reshape(n, 3)
    force = law(distance, velocity)  # (n, 3)
    damping = jax.vmap(jax.jacfwd(lambda c, d: law(d, c)))(velocity, distance)  # (n, 3, 3)
    system = jnp.eye(3 * n, dtype=delassus.dtype) - h * block_diagonal(damping) @ delassus
    return linalg.solve(system, h * force.reshape(-1))


def point_rows(model: Model, kinematics, frames: Array, joint1, point1: Array, joint2, point2: Array,
               weight: Array | None = None, which: Array | None = None) -> Array:
    """Contact Jacobian rows ``R^T (J_2 - J_1)`` ``(k, 3, nv)`` of contacts in frames ``R``
    ``(k, 3, 3)``: ``J_i`` the Jacobian of the world velocity of the material point of body
    ``joint_i`` (static, per contact; 0: the world, which no dof moves) at ``point_i`` ``(k, 3)``;
    zero rows where ``weight`` is 0 (inactive manifold entries). ``which``: the rows of those
    contacts only (traced indices, ``(k',)``). ``kinematics``: anything with the
    ``motion_subspace``."""
    take = (lambda values: values) if which is None else (lambda values: values[which])  # noqa: E731
    velocity = 0.0  # (k, nv, 3): world velocity of point 2 relative to point 1
    for sign, joints, points in ((1.0, joint2, point2), (-1.0, joint1, point1)):
        joints = np.asarray(joints, np.int32)
        if joints.any():  # a side that is the world's everywhere moves with no dof
            joints = joints if which is None else jnp.asarray(joints)[which]
            velocity = velocity + sign * _dynamics._point_velocity_columns(model, kinematics, joints, take(points))
    # R^T velocity, unrolled over the 3-axis (a batched 3x3 dot is slow on CPU: _spatial)
    frames = take(frames)
    rows = sum(frames[:, j, :, None] * velocity[:, None, :, j] for j in range(3))
    return rows if weight is None else jnp.where(take(weight)[:, None, None] > 0, rows, 0.0)


def contact_velocities(system: RigidBodySystem, contacts: ContactGeometry, v: Array) -> Array:
    """``J v`` ``(3 n,)``: every candidate's velocity in its frame, from the bodies' twists at
    ``v`` and the witness points (:class:`WitnessPoints`) rather than from ``J``."""
    points = contacts.points
    if points is None:
        return contacts.jacobian @ v
    support = _dynamics._tree(system.model).support
    twists = _dynamics._mask_sum(support, points.motion_subspace * v[:, None])  # (njoints, 6), world axes

    def point_velocity(joints, point):  # world velocity of the material points of `joints` at `point`
        twist = twists[np.asarray(joints, np.int64)]
        return twist[:, :3] - jnp.cross(point, twist[:, 3:])

    relative = point_velocity(points.joint2, points.point2)
    if any(points.joint1):  # shape 1 is not the world's everywhere
        relative = relative - point_velocity(points.joint1, points.point1)
    shapes = len(points.joint1)
    frames = contacts.frames[:shapes]
    # R^T relative, unrolled over the 3-axis (as the rows: RigidBodySystem.contacts)
    velocity = sum(frames[:, j, :] * relative[:, j, None] for j in range(3))  # (n_s, 3)
    velocity = jnp.where(points.weight[:, None] > 0, velocity, 0.0)
    limits = points.limit_rows @ v  # (l, 3)
    return jnp.concatenate([velocity, limits.astype(velocity.dtype)]).reshape(-1)


def jacobian_rows(system: RigidBodySystem, contacts: ContactGeometry, selection: Array) -> Array:
    """The rows ``(3 k, nv)`` of ``contacts.jacobian`` of the candidates ``selection``
    (``(k,)``: the shapes' first, then the limits', as :meth:`RigidBodySystem._contact_selection`
    returns them), built for those contacts alone from :class:`WitnessPoints`."""
    points = contacts.points
    if points is None:
        return contacts.jacobian[flat_rows(selection)]
    model, shapes = system.model, len(points.joint1)
    count = system._selected_shape_count()  # static: the selection's contacts between shapes
    parts = []
    if count:  # points carries the motion subspace
        parts.append(point_rows(model, points, contacts.frames[:shapes], points.joint1, points.point1, points.joint2,
                                points.point2, points.weight, which=selection[:count]))
    if selection.shape[0] > count:
        parts.append(points.limit_rows[selection[count:] - shapes])
    return jnp.concatenate(parts).reshape(-1, model.nv)


def flat_rows(contacts: Array) -> Array:
    """The rows ``[t1, t2, n]`` of ``contacts`` in a flat ``(3 n, ...)`` contact array."""
    return (3 * contacts[:, None] + jnp.arange(3, dtype=contacts.dtype)[None, :]).reshape(-1)


def integrate_decoupled(model: Model, q: Array, v: Array, h: Array) -> Array:
    """``q (+) h v`` with free flyers on ``R^3 x SO(3)`` and spherical joints on ``SO(3)`` (see
    the simulator's docstring)."""
    tree = _dynamics._tree(model)
    step = v * h
    result = q.at[tree.vector_q].add(step[tree.vector_v])
    result = _dynamics._per_joint(model, tree.free_flyer, (7, 6), _free_flyer_decoupled, result, q, step)
    return _dynamics._per_joint(model, tree.spherical, (4, 3), _turn_and_normalize, result, q, step)


def _turn_and_normalize(quaternion: Array, rotation_vector: Array) -> Array:
    """``quaternion * exp(rotation_vector)``, normalized."""
    quaternion = spatial.quaternion_multiply(quaternion, spatial.quaternion_exp(rotation_vector))
    return quaternion / jnp.sqrt(spatial.sum_last(quaternion * quaternion))


def _free_flyer_decoupled(q: Array, step: Array) -> Array:
    """One free flyer's ``(7,)`` configuration moved by ``step`` ``(6,)`` on ``R^3 x SO(3)``: the
    position by the linear step turned to world axes, the orientation by the angular step."""
    position = q[:3] + spatial.rotate(spatial.quaternion_to_rotation(q[3:]), step[:3])
    return jnp.concatenate([position, _turn_and_normalize(q[3:], step[3:])])


def block_diagonal(blocks: Array) -> Array:
    """Block-diagonal matrix ``(n b, n b)`` from blocks ``(n, b, b)``."""
    n, b, _ = blocks.shape
    eye = jnp.eye(n, dtype=blocks.dtype)
    return jnp.einsum("ij,iab->iajb", eye, blocks).reshape(n * b, n * b)
