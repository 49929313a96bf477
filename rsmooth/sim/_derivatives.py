"""Analytic configuration derivatives of a hard-contact step's equations (world frame).

:func:`rsmooth.sim.RigidBodySystem.step_and_jacobians` needs the derivative, with respect to
the configuration ``q``, of the step's two equations at the solution ``(v+, lambda)`` (see
``_simulator._step_residuals``):

* momentum ``E = h (ID(q, v, a) - r(v) + armature a + D v+ - tau) - J(q)^T lambda`` with
  ``a = (v+ - s(v)) / h``, ``(s, r)`` the free flyers' start velocity and the bias it accounts
  for (:func:`rsmooth.sim._dynamics._free_flyer_start`: ``s = v``, ``r = 0`` without free
  flyers; both independent of ``q``);
* contact velocity ``c = J(q) v+ + correction(phi(q))``.

Forward-mode autodiff pushes ``nq`` tangents through the kinematics, the body inertias, the
recursive Newton-Euler algorithm and the contact Jacobian; this module computes the same
derivative in closed form from the primal quantities, in the spirit of Carpentier and
Mansard's analytic RNEA derivatives (RSS 2018), written here in the world frame.

The derivation. Let ``delta`` be the configuration tangent (``nv``: the free flyer's is
``q (+) delta``, see :func:`rsmooth.sim.integrate`, to first order). Moving dof ``k`` by
``delta_k`` moves every body of the subtree of its joint ``K`` rigidly by the world twist
``X = S_k delta_k`` (``S`` the world-frame motion subspace). Attached world quantities then
change by the spatial cross products: motion subspaces of dofs below ``k`` (and of ``K``'s own
dofs) ``dS_j = X x S_j``, body inertias ``dI = X x* I - I X x``. With ``P`` and ``Q`` the
velocity and acceleration of ``K``'s parent (unchanged), the velocities, accelerations and
forces of the bodies ``i`` below ``K`` change by

    dV_i = X x (V_i - P),   dA_i = X x (A_i - Q) - (X x P) x (V_i - P),
    dF_i = X x* F_i + g_i,  g_i = -I_i (X x Q) + I_i (V_i x Y) + I_i (Y x P) - Y x* (I_i V_i)
                                  - V_i x* (I_i Y),   Y = X x P

(Jacobi's identity for ``x`` and ``x*`` collapses the rest). With ``tau_j = S_j . F^c`` (``F^c``
the sum of ``F_i`` over the subtree of ``j``'s joint), and ``S_j . (X x* F) + (X x S_j) . F = 0``:

* ``j`` on ``K`` or below: ``d tau_j = S_j . sum_{i below j} g_i``;
* ``j`` strictly above ``K``: ``d tau_j = S_j . (X x* F^c_K + sum_{i below K} g_i)``;
* otherwise 0.

The sums of ``g_i`` over a subtree need only subtree sums of ``I_i``, ``I_i [V_i x]``,
``[V_i x*] I_i`` and ``I_i V_i`` (composite quantities, one masked sum each), so the whole
``(nv, nv)`` derivative is a few small dense products instead of ``nq`` tangent passes.

The velocity derivative (at fixed ``v+``: ``a = (v+ - v) / h`` moves with ``v``) follows the
same pattern: ``dV_i / dv_k = S_k`` and ``dA_i / dv_k = S_k x (V_i - P) + V_K x S_k`` for the
bodies below ``K``; the momentum equation's is ``h dRNEA/dv - M - armature``.

The contact terms: a sphere's centre is a material point of its body, its contact point
``p = centre - r n`` moves with the centre (``u_k = S_k`` evaluated at the centre), and the
velocity column of dof ``j`` at ``p`` changes by ``(X x S_j)`` at ``p`` (``j`` on or below
``K``) plus ``omega_j x u_k`` (always). The signed distance changes by ``n . u_k``.

The raw configuration coordinates ``q`` (``nq``: a free flyer's quaternion has 4) relate to
``delta`` by ``d delta = D dq``; ``D`` annihilates the quaternion's radial direction, along which
the step is not a rigid motion (the rotation matrix of a non-unit quaternion, as in Pinocchio,
is not a rotation): that one direction per free flyer is pushed through the equations by a
single forward-mode tangent, so that the result equals ``jax.jacfwd`` of the equations exactly.

Supported systems: joint-torque actuation, sphere-against-half-space contacts (no box
contacts); others use forward-mode autodiff (``supported`` says which).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from rsmooth.sim import _dynamics
from rsmooth.sim import _spatial as spatial
from rsmooth.sim._contact import corrected_free_velocity

Array = jax.Array


# the spatial algebra broadcasts over leading axes (pairs of bodies and dofs here)
_cross_mm = spatial.motion_cross_motion
_cross_mf = spatial.motion_cross_force
_apply = spatial.inertia_apply


def supported(system) -> bool:
    """Whether :func:`configuration_jacobian` handles ``system`` (else use forward mode)."""
    # (Gravity compensation, by the inputs or of bodies, the fluid, springs, tendons and the
    # joints' constraint rows depend on the state through terms the closed form does not hold:
    # forward mode through the step's equations has them.)
    return (
        system.actuation.kind == "joints" and not system.actuation.gravity_compensation
        and not system.geometry.geom_pairs and not system.joints.limits and system.joints.friction is None
        and system.joints.couplings is None and system.joints.connections is None and system.joints.welds is None
        and system.joints.springs is None and system.joints.tendons is None and system.joints.fluid is None
        and system.joints.gravcomp is None
        and not len(_dynamics._tree(system.model).spherical)
        and (system.options.max_contacts is None or system.options.max_contacts >= system.num_contacts)
    )


def _take(inertia: spatial.SpatialInertia, index) -> spatial.SpatialInertia:
    return spatial.SpatialInertia(*(field[index] for field in inertia))


def _subtree_sum(subtree: np.ndarray, inertia: spatial.SpatialInertia) -> spatial.SpatialInertia:
    """Composite inertias: ``subtree[R, i] = 1`` for the bodies ``i`` summed into ``R``."""
    flat = jnp.concatenate(
        [inertia.mass[:, None], inertia.first_moment, inertia.rotational_inertia.reshape(-1, 9)], axis=1
    )
    total = _dynamics._mask_sum(subtree, flat)
    return spatial.SpatialInertia(total[:, 0], total[:, 1:4], total[:, 4:].reshape(-1, 3, 3))


def configuration_jacobian(system, update, residuals, q: Array, v: Array, u: Array) -> tuple[list[Array], list[Array]]:
    """``([dE/dq (nv, nq), dc/dq (3 n, nq)], [dE/dv, dc/dv])``, ``q`` in raw coordinates: the
    closed form over the tangent, composed with ``d delta / dq``, plus the forward-mode response
    along each free flyer's quaternion radial direction (``residuals``:
    ``_simulator._step_residuals``); and the closed-form velocity derivative."""
    *by_delta, by_v = tangent_jacobian(system, update, v)
    to_tangent, radial, coefficients = tangent_map(system.model, q)
    by_q = [part @ to_tangent for part in by_delta]
    if radial.shape[0]:  # all radial directions in one vectorized pass (one copy of the residuals)
        along = jax.vmap(lambda d: jax.jvp(lambda q_: residuals(system, q_, v, u)[:2], (q,), (d,))[1])(radial)
        by_q = [part + a.T @ coefficients for part, a in zip(by_q, along)]
    return by_q, [by_v, jnp.zeros((by_delta[1].shape[0], v.shape[0]), v.dtype)]


def tangent_map(model, q: Array) -> tuple[Array, Array, Array]:
    """``(D, radial, coefficients)``: ``d delta = D dq`` (``(nv, nq)``), and per free flyer the
    quaternion's radial direction in ``q`` (``(F, nq)``) with the row ``(F, nq)`` giving a
    ``dq``'s component along it."""
    tree = _dynamics._tree(model)
    nq, nv = model.nq, model.nv
    D = jnp.zeros((nv, nq), q.dtype).at[tree.vector_v, tree.vector_q].set(1.0)
    radial, coefficients = [], []
    for joint in tree.free_flyer:
        start_q, start_v = model.idx_q[joint], model.idx_v[joint]
        quaternion = q[start_q + 3 : start_q + 7]
        rotation = spatial.quaternion_to_rotation(quaternion)
        # delta_lin = R^T dp; delta_ang = 2 vec(conj(quat) (x) dquat), linear in dquat
        D = D.at[start_v : start_v + 3, start_q : start_q + 3].set(rotation.T)
        conjugate = spatial.quaternion_conjugate(quaternion)
        by_quaternion = jax.jacfwd(lambda d: 2.0 * spatial.quaternion_multiply(conjugate, d)[:3])(quaternion)
        D = D.at[start_v + 3 : start_v + 6, start_q + 3 : start_q + 7].set(by_quaternion)
        direction = jnp.zeros(nq, q.dtype).at[start_q + 3 : start_q + 7].set(quaternion)
        radial.append(direction)
        coefficients.append(direction / jnp.sum(quaternion * quaternion))
    if not radial:
        empty = jnp.zeros((0, nq), q.dtype)
        return D, empty, empty
    return D, jnp.stack(radial), jnp.stack(coefficients)


def tangent_jacobian(system, update, v: Array) -> tuple[Array, Array, Array]:
    """``(dE/d delta (nv, nv), dc/d delta (3 n, nv), dE/dv (nv, nv))`` at the step's solution
    (module docstring; ``c`` does not depend on ``v``)."""
    model, h = system.model, system.time_step
    tree = _dynamics._tree(model)
    kinematics, inertias = update.kinematics, update.inertias
    S = kinematics.motion_subspace  # (nv, 6)
    dtype = S.dtype
    owner = tree.dof_owner
    parent_of_owner = np.asarray(model.parents)[owner]
    # below[j, k]: dof j's joint is k's joint or below it; above[j, k]: strictly above
    below = tree.dof_ancestor.T
    above = tree.dof_ancestor & ~tree.dof_ancestor.T
    v_next = jax.lax.stop_gradient(update.v_next)
    impulse = jax.lax.stop_gradient(update.impulse)
    # the velocity the step's forces act from, and the bias it accounts for: both depend on v
    # alone (_dynamics._free_flyer_start)
    v_start, _ = _dynamics._free_flyer_start(model, v, h)
    acceleration = (v_next - v_start) / h

    # ----- inverse dynamics: the world-frame RNEA quantities (as in _dynamics._rnea)
    twists = S * v[:, None]
    V = _dynamics._mask_sum(tree.support, twists)  # (nj, 6)
    bias = _cross_mm(V[owner], twists) + S * acceleration[:, None]
    gravity = jnp.concatenate([-model.gravity, jnp.zeros_like(model.gravity)]).astype(dtype)
    A = _dynamics._mask_sum(tree.support, bias) + gravity[None, :]
    momenta = _apply(inertias, V)
    F = _apply(inertias, A) + _cross_mf(V, momenta)
    # subtree sums (composite quantities) over the bodies below each joint
    composite = _subtree_sum(tree.subtree, inertias)
    momenta_c, forces_c = _dynamics._mask_sum(tree.subtree, momenta), _dynamics._mask_sum(tree.subtree, F)
    P, Q = V[parent_of_owner], A[parent_of_owner]  # (nv, 6): the parent of each dof's joint
    Y = _cross_mm(S, P)
    Z = _cross_mm(Y, P) - _cross_mm(S, Q)

    # K_i = I_i [V_i x] + [V_i x]^T I_i (symmetric), column by column: K_i e_b =
    # I_i (V_i x e_b) - V_i x* (I_i e_b); stored [i, b, a] = (K_i)_ab
    basis = jnp.eye(6, dtype=dtype)[None]
    body_inertias = _take(inertias, (slice(None), None))  # (nj, 1): broadcasts over columns
    K = _apply(body_inertias, _cross_mm(V[:, None], basis)) - _cross_mf(V[:, None], _apply(body_inertias, basis))
    K_owner = _dynamics._mask_sum(tree.subtree, K.reshape(-1, 36)).reshape(-1, 6, 6)[owner]  # (nv, 6, 6)

    def mixed(motions):
        # the subtree sum of K_i below each dof's joint applied to motions (nv, 6), unrolled
        # (a batched 6 x 6 dot is slow on CPU: see _spatial)
        return sum(K_owner[:, b, :] * motions[:, b : b + 1] for b in range(6))

    owner_composite = _take(composite, owner)
    # j on or below k's joint: S_j . G[joint(j), k] = a_j . Z_k + b_j . Y_k
    a = _apply(owner_composite, S)
    b = mixed(S) + _cross_mf(S, momenta_c[owner])
    # j strictly above k's joint: S_j . w_k
    w = _apply(owner_composite, Z) + mixed(Y) - _cross_mf(Y, momenta_c[owner]) + _cross_mf(S, forces_c[owner])
    d_inverse_dynamics = jnp.where(below, a @ Z.T + b @ Y.T, 0.0) + jnp.where(above, S @ w.T, 0.0)
    # velocity derivative at fixed acceleration (Carpentier and Mansard's d tau / d v, world
    # frame): dV_i / dv_k = S_k, dA_i / dv_k = S_k x (V_i - P_k) + V_k x S_k (V_k: the velocity of
    # k's joint) for the bodies i below k's joint, so that the subtree sum of dF_i / dv_k is
    # -K S_k + I^c W_k + S_k x* h^c with W_k = (V_k + P_k) x S_k; then as above with the deeper
    # joint: a_j . W_k - b_j . S_k (j on or below k), S_j . w'_k (j above k)
    W = _cross_mm(V[owner] + P, S)
    w_v = -mixed(S) + _apply(owner_composite, W) + _cross_mf(S, momenta_c[owner])
    d_inverse_dynamics_v = jnp.where(below, a @ W.T - b @ S.T, 0.0) + jnp.where(above, S @ w_v.T, 0.0)

    # ----- contacts
    centres, points, joints, rotations = system._sphere_geometry(kinematics)  # (n, 3) x2, (n,), (n, 3, 3)
    n = centres.shape[0]
    supports = tree.support[joints][..., None]  # (n, nv, 1): the dof moves the contact's body
    # u[c, k]: velocity of the sphere centre per unit delta_k
    u = _dynamics._point_velocity_columns(model, kinematics, joints, centres)  # (n, nv, 3)
    forces = jnp.einsum("cia,ca->ci", rotations, impulse.reshape(n, 3))  # world forces R lambda
    wrenches = jnp.concatenate([forces, jnp.cross(points, forces)], axis=-1)  # about the origin
    # d(J^T lambda)[j, k] = sum_c w_c . (S_k x S_j) (j on or below k) + (f_c x omega_j) . u[c, k]
    moved_columns = _dynamics._support_columns(model, kinematics, joints)  # (n, nv, 6)
    first = jnp.einsum("cja,cka->jk", jnp.where(supports, _cross_mf(S[None], wrenches[:, None]), 0.0), moved_columns)
    second = jnp.einsum("cja,cka->jk", jnp.where(supports, jnp.cross(forces[:, None], S[None, :, 3:]), 0.0), u)
    d_contact_forces = jnp.where(below, first, 0.0) + second

    V_next = _dynamics._mask_sum(tree.support, S * v_next[:, None])  # (nj, 6)
    relative = V_next[joints][:, None, :] - V_next[parent_of_owner][None, :, :]  # (n, nv, 6)
    motion = _cross_mm(S[None, :, :], relative)
    at_point = motion[..., :3] + jnp.cross(motion[..., 3:], points[:, None, :])
    world = jnp.where(supports, at_point + jnp.cross(V_next[joints][:, None, 3:], u), 0.0)  # (n, nv, 3)
    d_contact_velocity = jnp.einsum("cia,cki->cak", rotations, world)  # (n, 3, nv): R^T, rows [t1, t2, n]
    d_distance = jnp.einsum("ci,cki->ck", rotations[:, :, 2], u)  # (n, nv): normal . u
    correction = jax.jacfwd(lambda d: _corrected(system, jnp.zeros(3 * n, d.dtype), d))(update.distance)  # (3 n, n)
    d_velocity = d_contact_velocity.reshape(3 * n, model.nv) + correction @ d_distance
    # dE/dv at fixed (v+, lambda): h dRNEA/dv - (M + armature) ds/dv - h dr/dv, with
    # M + armature = W - h D (W the update's matrix) and a = (v+ - s(v)) / h
    start_v, removed_v = jax.jacfwd(lambda v_: _dynamics._free_flyer_start(model, v_, h))(v)
    inertia = update.mass - jnp.diag(h * system.damping())
    by_v = h * d_inverse_dynamics_v - inertia @ start_v - h * removed_v
    return h * d_inverse_dynamics - d_contact_forces, d_velocity, by_v


def _corrected(system, free_velocity, distance):
    return corrected_free_velocity(free_velocity, distance, system.time_step, **system.options.correction)
