"""The rigid frictional contact problem at the velocity level and its solver.

Signorini's condition and Coulomb's law with maximum dissipation on the Delassus matrix ``G``
and the free velocity ``g`` form a nonlinear complementarity problem (NCP) with the De Saxcé
correction (:func:`ncp_residuals` measures a candidate impulse, :func:`project_to_friction_cone`
projects onto the friction cone). :class:`NCPSolver` (:func:`solve_ncp`) solves it from a
start (warm start, sticking guess), an active-set Newton polish and ADMM, and attaches the
derivative of the solution map by the implicit function theorem on the natural map (not by
unrolling); :func:`implicit_impulse_tangent` and the natural map are also what the
simulator's step differentiates with.

Impulses and velocities are flat ``(3 n + m,)``: per contact ``[t1, t2, n]`` in the contact
frames of :mod:`rsmooth.sim._contact` (its docstring states the conventions), then ``m``
box rows. A box row ``k`` bounds its impulse by ``|lambda_k| <= b_k`` with maximum
dissipation (``lambda_k`` opposes its velocity ``c_k`` and is interior only where ``c_k = 0``):
dry joint friction, ``b_k`` the friction torque times the time step; ``b_k = inf`` makes it a
bilateral constraint (``c_k = 0``). Without box rows (``bounds=None``) the problem is the
contact NCP alone.
"""

from __future__ import annotations

import functools
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.typing import ArrayLike

from rsmooth import _linalg as linalg
from rsmooth import _xla
from rsmooth._batching import once_if, run_where_needed
from rsmooth._results import RESULTS
from rsmooth._unrolled import sum_last
from rsmooth.sim._contact import _check_finite, _check_nonnegative, _is_concrete, _safe_norm

Array = jax.Array

__all__ = [
    "NCPInfo",
    "NCPSolver",
    "NCPState",
    "ncp_residuals",
    "project_to_friction_cone",
    "solve_ncp",
]


def project_to_friction_cone(v: ArrayLike, mu: ArrayLike) -> Array:
    """Euclidean projection onto the Coulomb cone ``K_mu = {||x_T|| <= mu x_N}``.

    Three cases: inside, in the polar cone ``{mu ||v_T|| <= -v_N}`` (projects to 0), and
    otherwise onto the boundary ray through ``v_T``:
    ``alpha (mu v_T / ||v_T||, 1)`` with ``alpha = (mu ||v_T|| + v_N) / (1 + mu^2)``.

    Args:
        v: vectors ``[t1, t2, n]``, shape ``(..., 3)``.
        mu: friction coefficients ``>= 0``, shape ``(...)``.

    Returns:
        The projections, shape ``(..., 3)``. By Moreau's decomposition the projection onto
        the dual cone is ``P_{K*}(v) = v + P_K(-v)``.
    """
    v, mu = jnp.asarray(v), jnp.asarray(mu)
    tangential, normal = v[..., :2], v[..., 2]
    tangential_norm = _safe_norm(tangential)
    # normal >= 0 too: without friction (mu = 0) the first test alone admits v = (0, 0, -a)
    inside = (tangential_norm <= mu * normal) & (normal >= 0)
    polar = mu * tangential_norm <= -normal
    alpha = (mu * tangential_norm + normal) / (1.0 + mu * mu)
    positive = tangential_norm > 0
    tangential_scale = jnp.where(
        positive, mu * alpha / jnp.where(positive, tangential_norm, 1.0), 0.0
    )
    on_boundary = jnp.concatenate(
        [tangential_scale[..., None] * tangential, alpha[..., None]], axis=-1
    )
    return jnp.where(
        inside[..., None], v, jnp.where(polar[..., None], jnp.zeros_like(v), on_boundary)
    )


def _de_saxce_velocity(contact_velocity: Array, mu: Array) -> Array:
    """``c~ = c + mu ||c_T|| e_N`` per contact; ``contact_velocity`` has shape ``(n, 3)``."""
    return contact_velocity.at[:, 2].add(mu * _safe_norm(contact_velocity[:, :2]))


def _project(impulse: Array, mu: Array, bounds: Array | None) -> Array:
    """The projection of flat impulses ``(3 n + m,)`` onto the cones and the boxes."""
    n = mu.shape[0]
    cones = project_to_friction_cone(impulse[: 3 * n].reshape(n, 3), mu).reshape(-1)
    if bounds is None:
        return cones
    return jnp.concatenate([cones, jnp.clip(impulse[3 * n :], -bounds, bounds)])


def _corrected_velocity(velocity: Array, mu: Array) -> Array:
    """Flat ``c~``: the De Saxcé correction on the contacts; box rows are not corrected
    (their bounds do not depend on another row's impulse)."""
    n = mu.shape[0]
    cones = _de_saxce_velocity(velocity[: 3 * n].reshape(n, 3), mu).reshape(-1)
    return jnp.concatenate([cones, velocity[3 * n :]]) if velocity.shape[0] > 3 * n else cones


def _delassus_times(G: Array | None, factor: Array | None, z: Array) -> Array:
    """``G z``, or ``Xᵀ (X z)`` where ``G`` is not formed (``G = Xᵀ X``, ``X = factor``)."""
    return G @ z if G is not None else factor.T @ (factor @ z)


def _largest(values: Array) -> Array:
    return jnp.max(values, initial=jnp.zeros((), values.dtype))


def ncp_residuals(G: Array, g: Array, mu: Array, impulse: Array, bounds: Array | None = None) -> tuple[Array, Array, Array]:
    """Residuals of the frictional contact NCP at ``impulse``.

    With ``c = G lambda + g`` and ``c~_i = c_i + mu_i ||c_{T,i}|| e_N`` the problem is
    ``K_mu ∋ lambda ⟂ c~ ∈ K_mu*``. Each residual is the maximum over contacts of:

    - primal feasibility: ``dist(lambda_i, K_mu_i)`` (impulse units);
    - dual feasibility: ``dist(c~_i, K*_mu_i) = ||P_K(-c~_i)||`` (velocity units);
    - complementarity: ``|lambda_i . c~_i|`` (impulse x velocity units).

    and over box rows of: primal feasibility ``max(|lambda_k| - b_k, 0)``; dual feasibility
    ``|c_k|`` where the row is bilateral (``b_k = inf``), else 0 (any velocity is admissible);
    complementarity ``max(c_k, 0) (b_k + lambda_k) + max(-c_k, 0) (b_k - lambda_k)`` (a
    velocity is met by the bound that opposes it).

    Args:
        G: Delassus matrix, ``(3 n + m, 3 n + m)``.
        g: free contact velocity, ``(3 n + m,)``.
        mu: friction coefficients, ``(n,)``.
        impulse: candidate impulses, ``(3 n + m,)``.
        bounds: ``None``, or the bounds ``b`` of the ``m`` box rows, ``(m,)``.

    Returns:
        ``(primal_feasibility, dual_feasibility, complementarity)``, scalars.
    """
    return _residuals_at(G @ impulse + g, mu, impulse, bounds)


def _residuals_at(full_velocity: Array, mu: Array, impulse: Array, bounds: Array | None) -> tuple[Array, Array, Array]:
    """:func:`ncp_residuals` given the velocity ``G lambda + g`` at ``impulse``."""
    n = mu.shape[0]
    impulse_by_contact = impulse[: 3 * n].reshape(n, 3)
    velocity = _de_saxce_velocity(full_velocity[: 3 * n].reshape(n, 3), mu)
    primal = _safe_norm(impulse_by_contact - project_to_friction_cone(impulse_by_contact, mu))
    dual = _safe_norm(project_to_friction_cone(-velocity, mu))
    complementarity = jnp.abs(sum_last(impulse_by_contact * velocity))
    if bounds is None:
        return jnp.max(primal), jnp.max(dual), jnp.max(complementarity)
    box, c = impulse[3 * n :], full_velocity[3 * n :]
    bilateral = jnp.isinf(bounds)
    finite = jnp.where(bilateral, 0.0, bounds)
    box_primal = jnp.maximum(jnp.abs(box) - bounds, 0.0)
    box_dual = jnp.where(bilateral, jnp.abs(c), 0.0)
    box_complementarity = jnp.where(
        bilateral, 0.0, jnp.maximum(c, 0.0) * (finite + box) + jnp.maximum(-c, 0.0) * (finite - box)
    )
    return (
        jnp.maximum(_largest(primal), _largest(box_primal)),
        jnp.maximum(_largest(dual), _largest(box_dual)),
        jnp.maximum(_largest(complementarity), _largest(jnp.abs(box_complementarity))),
    )


class NCPInfo(eqx.Module):
    """Diagnostics of an NCP solve (no derivatives flow through them).

    Its arrays, ``result``'s value included, are batched like the solve under `vmap` (and
    stacked by a rollout's `scan`): ``info.result == RESULTS.successful`` and ``converged``
    are then bool arrays of the batch's shape.

    Attributes:
        iterations: ADMM iterations used (0 if the warm start, the sticking guess or the
            polish already satisfied the tolerance; both runs' where ADMM ran again on the
            acting contacts alone, see :attr:`NCPSolver.polish`).
        primal_feasibility, dual_feasibility, complementarity: the residuals of
            :func:`ncp_residuals` at the returned impulse.
        result: a :class:`~rsmooth.RESULTS` item: ``successful`` (all three residuals
            ``<= tolerance``), ``max_iterations_reached`` (ADMM stopped at
            ``max_iterations``; the impulse is the best iterate met) or ``nonfinite`` (the
            impulse or a residual is NaN or infinite). A compliant contact law, which solves
            no NCP, reports ``successful``.
        rho: the final ADMM penalty (0 where the starting impulse already solved the problem
            and ADMM did not run).
    """

    iterations: Array
    primal_feasibility: Array
    dual_feasibility: Array
    complementarity: Array
    result: RESULTS
    rho: Array

    @property
    def converged(self) -> Array:
        """Whether the solve succeeded (``result == RESULTS.successful``), a bool array."""
        return self.result == RESULTS.successful


def _ncp_result(converged: Array, impulse: Array, primal: Array, dual: Array, complementarity: Array) -> RESULTS:
    """The :class:`~rsmooth.RESULTS` item of a solve that returns ``impulse`` with these
    residuals: ``successful`` where they met the tolerance (``converged``), ``nonfinite``
    where a value is not finite, else ``max_iterations_reached``."""
    finite = jnp.all(jnp.isfinite(impulse)) & jnp.isfinite(primal) & jnp.isfinite(dual) & jnp.isfinite(complementarity)
    return RESULTS.where(
        converged, RESULTS.successful, RESULTS.where(finite, RESULTS.max_iterations_reached, RESULTS.nonfinite)
    )


class NCPState(eqx.Module):
    """ADMM iterate, in the coordinates of the scaled problem (:attr:`NCPSolver.scaling`):
    ``x`` (unconstrained impulse), ``z`` (impulse in the cone), ``y`` (scaled multiplier,
    ``-c~`` at convergence), penalty ``rho``, the eigendecomposition of the scaled ``G`` used
    for every ``(G + rho I)^{-1}``, the rows' scales ``d`` (``lambda = d z``); then, in the
    problem's own units, the residuals of ``d z`` and the best impulse so far (the start
    included: the smallest largest residual) with its residuals, which the solve returns."""

    x: Array
    z: Array
    y: Array
    rho: Array
    eigenvalues: Array
    eigenvectors: Array
    scale: Array
    iteration: Array
    primal_feasibility: Array
    dual_feasibility: Array
    complementarity: Array
    best: Array
    best_residuals: Array  # (3,): primal, dual, complementarity of best


def _diagonal_means(G: Array, n: int) -> Array:
    """``(n + m,)``: the mean of ``G``'s diagonal over each contact's three rows, then each box
    row's diagonal entry (the scale of a row's effective inverse mass)."""
    diagonal = jnp.diagonal(G)
    return jnp.concatenate([sum_last(diagonal[: 3 * n].reshape(n, 3)) / 3.0, diagonal[3 * n :]])


def fixed_point_step_sizes(G: Array, n: int) -> Array:
    """Per-contact step ``r_i = 3 / trace(G_ii)`` of the natural map (a scalar per contact
    keeps the cone geometry: ``-r c~`` is in the polar cone iff ``c~`` is in the dual), then
    ``r_k = 1 / G_kk`` per box row: ``(n + m,)``."""
    scale = _diagonal_means(G, n)
    floor = jnp.maximum(jnp.max(scale), 1.0) * 1e-12
    return lax.stop_gradient(1.0 / jnp.maximum(scale, floor))


def _row_scales(G: Array, n: int) -> Array:
    """The rows' scales ``d`` ``(3 n + m,)`` of :attr:`NCPSolver.scaling`: ``sqrt(r / G_kk)``,
    with ``G_kk`` the mean diagonal of each contact's three rows (one number per contact, so that
    ``lambda_i = d_i z_i`` keeps the friction cone) or a box row's diagonal, and ``r`` their
    geometric mean: the rows are equilibrated among themselves and the problem keeps its overall
    scale (rows of equal diagonals are left as they are, and ADMM's residual balancing, which
    compares impulses with velocities, sees the units it would see unscaled). A row whose
    diagonal is below ``1e-6`` of the largest (a candidate with no Jacobian) keeps scale 1."""
    means = _diagonal_means(G, n)
    diagonal = jnp.concatenate([jnp.repeat(means[:n], 3), means[n:]])
    largest = jnp.maximum(jnp.max(diagonal), jnp.finfo(G.dtype).tiny ** 0.5)
    meaningful = diagonal > 1e-6 * largest
    logs = jnp.log(jnp.where(meaningful, diagonal, largest))
    reference = jnp.sum(jnp.where(meaningful, logs, 0.0)) / jnp.maximum(jnp.sum(meaningful), 1)
    return lax.stop_gradient(jnp.where(meaningful, jnp.exp(0.5 * (reference - logs)), 1.0))


def _restricted_rows(G: Array, g: Array, mu: Array, impulse: Array) -> Array:
    """``(3 n + m,)`` bool: the rows of the contacts that act at ``impulse`` (a positive normal
    impulse, or a normal velocity that closes, ``c_N < 0``) and every box row."""
    n = mu.shape[0]
    contacts = impulse[: 3 * n].reshape(n, 3)
    closing = (G @ impulse + g)[: 3 * n].reshape(n, 3)[:, 2] < 0
    acting = (contacts[:, 2] > 0) | closing
    return jnp.concatenate([jnp.repeat(acting, 3), jnp.ones(g.shape[0] - 3 * n, bool)])


def _restricted_problem(G: Array, g: Array, rows: Array) -> tuple[Array, Array]:
    """``(G', g')``: the problem on ``rows`` alone, at its full size: the other contacts are
    decoupled from them and separated (``G'`` the identity times the kept rows' geometric-mean
    diagonal there, ``g' = (0, 0, 1)``), so that their impulses are zero and ADMM's scaling
    and penalty (:func:`_row_scales`, the spectral ``rho``) are those of the kept rows' problem.
    With every row kept it is ``(G, g)`` exactly."""
    diagonal = jnp.diagonal(G)
    largest = jnp.maximum(jnp.max(diagonal), jnp.finfo(G.dtype).tiny ** 0.5)
    counted = rows & (diagonal > 1e-6 * largest)
    logs = jnp.log(jnp.where(counted, diagonal, largest))
    fill = jnp.exp(jnp.sum(jnp.where(counted, logs, 0.0)) / jnp.maximum(jnp.sum(counted), 1))
    kept = rows[:, None] & rows[None, :]
    G_kept = jnp.where(kept, G, 0.0) + jnp.diag(jnp.where(rows, 0.0, fill))
    separated = (jnp.arange(g.shape[0]) % 3 == 2).astype(g.dtype)
    return G_kept, jnp.where(rows, g, separated)


def _natural_map(impulse: Array, G: Array, g: Array, mu: Array, step_sizes: Array, bounds: Array | None = None) -> Array:
    """``F(lambda) = lambda - P_K(lambda - r c~(lambda))``, zero exactly at NCP solutions.

    By Moreau's decomposition ``lambda = P_K(lambda - r c~)`` iff ``lambda ∈ K``,
    ``c~ ∈ K*`` and ``lambda . c~ = 0``. Per contact mode, the Jacobian of ``P_K`` at the
    solution is 0 (separated: ``lambda - r c~`` is inside the polar cone), the identity
    (sticking: ``c~ = 0``, ``lambda`` inside ``K``) or the tangent projector of the cone
    boundary (sliding), so implicit differentiation of ``F = 0`` treats separated contacts
    as absent, sticking ones as bilateral constraints and sliding ones on the boundary. A box
    row's ``lambda_k - clip(lambda_k - r_k c_k, -b_k, b_k)`` has the Jacobian of ``c_k = 0``
    inside its bounds and of ``lambda_k = ±b_k`` on them.
    """
    return natural_map_of_velocity(impulse, G @ impulse + g, mu, step_sizes, bounds)


def natural_map_of_velocity(
    impulse: Array, velocity: Array, mu: Array, step_sizes: Array, bounds: Array | None = None
) -> Array:
    """The natural map of :func:`_natural_map` given the contact velocity ``c = G lambda + g``
    (flat ``(3 n + m,)``) instead of ``(G, g)``: the form in which a simulator's step states it."""
    n = mu.shape[0]
    impulse_by_contact = impulse[: 3 * n].reshape(n, 3)
    velocity_by_contact = _de_saxce_velocity(velocity[: 3 * n].reshape(n, 3), mu)
    projected = project_to_friction_cone(
        impulse_by_contact - step_sizes[:n, None] * velocity_by_contact, mu
    )
    cones = (impulse_by_contact - projected).reshape(-1)
    if bounds is None:
        return cones
    box = impulse[3 * n :]
    return jnp.concatenate([cones, box - jnp.clip(box - step_sizes[n:] * velocity[3 * n :], -bounds, bounds)])


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _with_implicit_derivative(
    regularization: float, impulse: Array, G: Array, g: Array, mu: Array, bounds: Array | None
) -> Array:
    """Returns ``impulse`` (an NCP solution) with the derivative of the solution map."""
    del G, g, mu, bounds
    return impulse


@_with_implicit_derivative.defjvp
def _with_implicit_derivative_jvp(regularization, primals, tangents):
    # Implicit function theorem on F(lambda*(theta), theta) = 0 (Blondel et al. 2022):
    #   dF/dlambda . dlambda = -dF/dtheta . dtheta.
    # The impulse tangent is ignored: lambda* is a function of theta only.
    impulse, G, g, mu, bounds = primals
    _, G_dot, g_dot, mu_dot, bounds_dot = tangents
    impulse = lax.stop_gradient(impulse)
    step_sizes = fixed_point_step_sizes(G, mu.shape[0])
    _, rhs = jax.jvp(
        lambda G_, g_, mu_, bounds_: _natural_map(impulse, G_, g_, mu_, step_sizes, bounds_),
        (G, g, mu, bounds),
        (G_dot, g_dot, mu_dot, bounds_dot),
    )
    return impulse, implicit_impulse_tangent(regularization, impulse, G, g, mu, step_sizes, rhs, bounds)


def implicit_impulse_tangent(
    regularization: float,
    impulse: Array,
    G: Array,
    g: Array,
    mu: Array,
    step_sizes: Array,
    rhs: Array,
    bounds: Array | None = None,
) -> Array:
    """``dlambda`` solving ``dF/dlambda dlambda = -rhs`` at an NCP solution ``impulse``.

    ``rhs`` is the change of the natural map ``F`` (:func:`_natural_map`) caused by the
    parameters at fixed ``lambda``, ``(3 n,)`` or a matrix of such columns ``(3 n, k)``;
    ``dF/dlambda`` is taken at the primal ``(G, g, mu)`` and does not depend on the tangents
    (under ``jacfwd`` it is computed once for all columns).
    """
    n = mu.shape[0]
    jacobian = jax.jacfwd(_natural_map)(impulse, G, g, mu, step_sizes, bounds)
    # Separated contacts (lambda_i = 0 exactly: the solver's projection returns exact zeros)
    # have dlambda_i = 0; decoupling their rows and columns makes that zero exact instead of
    # ~1e-13 from the regularized solve. A degenerate lambda_i = 0, c_i = 0 contact is thereby
    # treated as separated (a one-sided derivative). Box rows stay: a zero impulse inside the
    # bounds is a sticking row (c_k = 0).
    active = jnp.repeat(jnp.any(impulse[: 3 * n].reshape(n, 3) != 0, axis=-1), 3)
    if bounds is not None:
        active = jnp.concatenate([active, jnp.ones(bounds.shape, bool)])
    identity = jnp.eye(impulse.shape[0], dtype=jacobian.dtype)
    jacobian = jnp.where(active[:, None] & active[None, :], jacobian, identity)
    rhs = jnp.where(active.reshape(active.shape + (1,) * (rhs.ndim - 1)), rhs, 0.0)
    # Damped least squares (Tikhonov) with two steps of iterative refinement:
    #   dlambda = -(JᵀJ + eps I)^{-1} Jᵀ rhs, refined on the residual rhs - J dlambda.
    # J is O(1) thanks to the step sizes r_i. Where J is nonsingular the refinement removes
    # the O(eps / sigma_min(J)^2) bias; where it is singular (mode switches, sticking
    # contacts on a rank-deficient G whose impulses are not unique) eps = 1e-12 bounds the
    # gain by about 3 / (2 sqrt(eps)) instead of returning inf or NaN.
    factor = linalg.cho_factor(jacobian.T @ jacobian + regularization * identity)
    if rhs.ndim == 2 and rhs.shape[1] > impulse.shape[0]:
        # Many columns (the Jacobian columns of a step): the three refined solves are linear in
        # rhs, dlambda = -T rhs with T = (I + E + E^2) B, B = (JᵀJ + eps I)^{-1} Jᵀ and E = I - B J
        # (3 n x 3 n): form T once and apply it, one product per column instead of nine
        B = cholesky_inverse(factor) @ jacobian.T
        E = identity - B @ jacobian
        return -((B + E @ (B + E @ B)) @ rhs)
    impulse_dot = jnp.zeros_like(rhs)
    for _ in range(3):
        residual = -rhs - jacobian @ impulse_dot
        impulse_dot = impulse_dot + linalg.cho_solve(factor, jacobian.T @ residual)
    return impulse_dot


def many_column_solver(factor, rhs: Array):
    """``b -> A^-1 b`` for a Cholesky ``factor`` of ``A`` (n x n) and right-hand sides shaped
    like ``rhs``. With more than ``n`` columns (the Jacobian columns of a step), ``A^-1`` is
    formed once (:func:`cholesky_inverse`) and applied by matrix products, since XLA's batched
    triangular solve on CPU costs per column. Otherwise (a JVP's vector) it solves directly."""
    n = factor[0].shape[0]
    if rhs.ndim == 2 and rhs.shape[1] > n:
        inverse = cholesky_inverse(factor)
        return lambda b: inverse @ b
    return lambda b: linalg.cho_solve(factor, b)


def cholesky_inverse(factor) -> Array:
    """``A^-1`` from a Cholesky ``factor`` of ``A`` (:func:`rsmooth._linalg.cho_factor`): one
    triangular solve for ``L^-1`` and the product ``L^-T L^-1``, where ``cho_solve`` with the
    identity takes two solves (on the CPU a batched triangular solve costs several times the
    product)."""
    c, lower = factor
    inverse = linalg.solve_triangular(c, jnp.eye(c.shape[0], dtype=c.dtype), lower=lower)
    return inverse.T @ inverse if lower else inverse @ inverse.T


# Contact modes of the active-set Newton polish (NCPSolver.polish).
_SEPARATED, _STICKING, _SLIDING = 0, 1, 2


# Up to this many rows (16 contacts: a robot's feet, a cube's corners) the polish computes G lambda
# as an unrolled sum (rsmooth._unrolled) and solves its Newton systems by the unpivoted elimination
# (_solve_unpivoted), both written for small problems under vmap; beyond, a matrix product and
# LAPACK's LU, whose cost grows far more slowly with the rows than the unrolled chain's and the
# elimination's row-by-row loop (a body lying on many contacts).
_UNROLLED_COLUMNS = 48


def _mode_equations(x: Array, direction: Array, mode: Array, G: Array, g: Array, mu: Array) -> tuple[Array, Array, Array]:
    """The impulse, the equations and their Jacobian of the polish at its unknowns ``x``
    ``(n, 3)`` and sliding directions ``direction`` ``(n, 2)`` (unit vectors): ``(impulse
    (3 n,), residual (3 n,), jacobian (3 n, 3 n))``.

    Per contact mode, unknowns and equations (``c = G lambda + g`` per contact ``[c_T, c_N]``):

    - separated: ``lambda = 0``; unknowns ``x``, equations ``x = 0``;
    - sticking: ``lambda = x``; equations ``c = 0``;
    - sliding: ``lambda = (mu x_0 d, x_0)`` on the cone's boundary with ``d`` the direction,
      whose angle is the unknown ``x_1`` (the Jacobian's column is the derivative along
      ``d_perp``; ``x_1`` itself is not read: :func:`_polish` turns ``d`` by each step), slip
      speed ``x_2``; equations ``c_N = 0``, ``d_perp . c_T = 0``,
      ``d . c_T + x_2 = 0`` (the slip ``c_T = -x_2 d`` opposes the friction impulse), in this
      order so that the diagonal is ``G_NN``, ``mu x_0 d_perpᵀ G_TT d_perp + x_2`` and 1;
      without friction (``mu = 0``) ``c_N = 0``, ``x_1 = x_2 = 0``.

    The Jacobian is in closed form: ``c`` depends on ``x`` through ``G D``, ``D`` the
    block-diagonal derivative of the impulse, and each contact's equations are a rotation
    ``R`` of its ``c`` plus terms of its own unknowns."""
    n = mu.shape[0]
    dtype = G.dtype
    impulse = _cone_impulse(x, direction, mode, mu)
    flat = impulse.reshape(-1)
    product = sum_last(G * flat[None, :]) if 3 * n <= _UNROLLED_COLUMNS else G @ flat
    c = (product + g).reshape(n, 3)
    D, R, own, own_values = _cone_blocks(x, direction, mode, mu, c)
    # Products over the short axes written out (rsmooth._unrolled: einsum's small batched
    # dot products are several times slower under vmap on CPU).
    residual = sum(R[:, :, b] * c[:, None, b] for b in range(3)) + own_values
    G4 = G.reshape(n, 3, n, 3)  # (contact i, row a, contact j, column b)
    GD = sum(G4[:, :, :, b, None] * D[None, None, :, b, :] for b in range(3))  # (n, 3, n, 3)
    RGD = sum(R[:, :, b, None, None] * GD[:, None, b] for b in range(3))
    jacobian = RGD + jnp.eye(n, dtype=dtype)[:, None, :, None] * own[:, :, None, :]
    return impulse.reshape(-1), residual.reshape(-1), jacobian.reshape(3 * n, 3 * n)


def _cone_impulse(x: Array, direction: Array, mode: Array, mu: Array) -> Array:
    """The contacts' impulses ``(n, 3)`` of the polish's unknowns (see :func:`_mode_equations`)."""
    cos, sin = direction[:, 0], direction[:, 1]
    sliding_impulse = jnp.stack([mu * x[:, 0] * cos, mu * x[:, 0] * sin, x[:, 0]], axis=-1)
    return jnp.where((mode == _SEPARATED)[:, None], 0.0, jnp.where((mode == _STICKING)[:, None], x, sliding_impulse))


def _cone_blocks(x: Array, direction: Array, mode: Array, mu: Array, c: Array) -> tuple[Array, Array, Array, Array]:
    """Per contact, the blocks of :func:`_mode_equations` at the contact velocities ``c``
    ``(n, 3)``: ``D`` (d impulse / d x), ``R`` and ``own`` (the equations are ``R c + own
    values``, their derivative in the contact's own unknowns ``own``), each ``(n, 3, 3)``, and
    the own values ``(n, 3)``."""
    n = mu.shape[0]
    dtype = c.dtype
    # The direction as a unit vector rather than an angle: XLA recomputes cos and sin per
    # element inside the fused loops of the Jacobian.
    cos, sin = direction[:, 0], direction[:, 1]
    zero, one = jnp.zeros_like(cos), jnp.ones_like(cos)
    separated, sticking = (mode == _SEPARATED)[:, None, None], (mode == _STICKING)[:, None, None]
    friction = (mu > 0)[:, None, None]
    eye = jnp.broadcast_to(jnp.eye(3, dtype=dtype), (n, 3, 3))

    def blocks(*rows):  # (n, 3, 3) from three rows of three (n,) entries
        return jnp.stack([jnp.stack(row, axis=-1) for row in rows], axis=1)

    # d impulse / d x, and R (equations = R c + own terms).
    D = jnp.where(separated, 0.0, jnp.where(sticking, eye, blocks(
        (mu * cos, -mu * x[:, 0] * sin, zero), (mu * sin, mu * x[:, 0] * cos, zero), (one, zero, zero)
    )))
    sliding_R = jnp.where(
        friction,
        blocks((zero, zero, one), (-sin, cos, zero), (cos, sin, zero)),
        blocks((zero, zero, one), (zero,) * 3, (zero,) * 3),
    )
    R = jnp.where(separated, 0.0, jnp.where(sticking, eye, sliding_R))
    tangential_along, tangential_across = cos * c[:, 0] + sin * c[:, 1], -sin * c[:, 0] + cos * c[:, 1]
    sliding_own = jnp.where(
        friction,
        blocks((zero,) * 3, (zero, -tangential_along, zero), (zero, tangential_across, one)),  # dR/dx_1 c, and x_2
        blocks((zero,) * 3, (zero, one, zero), (zero, zero, one)),
    )
    own = jnp.where(separated, eye, jnp.where(sticking, 0.0, sliding_own))
    sliding_values = jnp.where(
        friction[:, :, 0], jnp.stack([zero, zero, x[:, 2]], axis=-1), jnp.stack([zero, x[:, 1], x[:, 2]], axis=-1)
    )
    own_values = jnp.where(separated[:, :, 0], x, jnp.where(sticking[:, :, 0], 0.0, sliding_values))
    return D, R, own, own_values


def _box_mode_equations(
    x: Array, box_x: Array, direction: Array, mode: Array, box_mode: Array, G: Array, g: Array, mu: Array, bounds: Array
) -> tuple[Array, Array, Array]:
    """:func:`_mode_equations` with box rows, dense: ``(impulse (3 n + m,), residual
    (3 n + m,), jacobian (3 n + m, 3 n + m))``. A box row inside its bounds (``box_mode``
    0) has the impulse ``box_x`` and the equation ``c_k = 0``; one on a bound (``box_mode``
    ``±1``) the impulse ``±b_k`` and the equation ``box_x = 0``."""
    n = mu.shape[0]
    interior = box_mode == 0
    box_impulse = jnp.where(box_mode > 0, bounds, jnp.where(box_mode < 0, -bounds, box_x))
    impulse = jnp.concatenate([_cone_impulse(x, direction, mode, mu).reshape(-1), box_impulse])
    c = G @ impulse + g
    D, R, own, own_values = _cone_blocks(x, direction, mode, mu, c[: 3 * n].reshape(n, 3))
    inside = interior.astype(G.dtype)

    def dense(cone_blocks, box_diagonal):
        cones = (jnp.eye(n, dtype=G.dtype)[:, None, :, None] * cone_blocks[:, :, None, :]).reshape(3 * n, 3 * n)
        return jax.scipy.linalg.block_diag(cones, jnp.diag(box_diagonal))

    R_full, D_full, own_full = dense(R, inside), dense(D, inside), dense(own, 1.0 - inside)
    values = jnp.concatenate([own_values.reshape(-1), jnp.where(interior, 0.0, box_x)])
    residual = R_full @ c + values
    return impulse, residual, R_full @ G @ D_full + own_full


def _solve_unpivoted(A: Array, b: Array) -> Array:
    """``A^{-1} b`` by Gauss-Jordan elimination without pivoting, one row per iteration of a
    ``fori_loop``. For the polish's small systems (12 x 12 for four contacts) under ``vmap``
    on CPU, ``jnp.linalg.solve`` (LAPACK's LU per matrix, then a loop turning its pivots
    into a permutation) costs more than the rest of a Newton step, and an unrolled
    elimination makes XLA fuse the steps into loops that recompute the earlier ones. A zero
    pivot gives a non-finite result, which the polish rejects like any other failure."""
    n = A.shape[-1]
    eye = jnp.eye(n, dtype=A.dtype)

    def eliminate(k, augmented):
        row = lax.dynamic_index_in_dim(augmented, k, axis=0, keepdims=False)
        row = row / row[k]
        column = lax.dynamic_index_in_dim(augmented, k, axis=1, keepdims=False)
        column = column - lax.dynamic_index_in_dim(eye, k, axis=1, keepdims=False)
        return augmented - column[:, None] * row[None, :]

    return lax.fori_loop(0, n, eliminate, jnp.concatenate([A, b[:, None]], axis=1))[:, n]


# The least-squares polish's cut on singular values, relative to the largest: well above the
# rounding of the Jacobian's (a few 1e-16), below the ill-conditioned ones of a landing foot.
_MIN_NORM_RCOND = 1e-13


def _newton_step(jacobian: Array, residual: Array) -> Array:
    if residual.shape[0] <= _UNROLLED_COLUMNS:
        return _solve_unpivoted(jacobian, residual)
    return linalg.solve(jacobian, residual)


def _polish(
    G: Array, g: Array, mu: Array, impulse: Array, steps: int, least_squares: ArrayLike = False, bounds: Array | None = None
) -> Array:
    """Active-set Newton polish: the contact modes read from ``impulse`` (in the cone: zero
    normal impulse separated, on the cone's boundary sliding, inside sticking; a box row on
    or inside its bounds), then
    ``steps`` Newton iterations on the modes' equations (:func:`_mode_equations`). The result
    (possibly not finite, or the solution of wrong modes) must be checked by
    :func:`ncp_residuals`.

    ``least_squares`` (a bool, possibly traced): minimum-norm least-squares steps (singular
    values below ``1e-13`` of the largest dropped), for modes whose equations are singular (more
    sticking rows than the degrees of freedom they hold: a stack of boxes, where Newton's own
    step is not finite; a tilted foot landing on the ends of two capsules). They reach a
    solution of consistent equations; damped normal equations do not where the equations are
    also ill-conditioned (a singular value 1e-7 of the largest, squared below the rounding of
    ``JᵀJ``), and their damping all but stops the steps along it."""
    n = mu.shape[0]
    z = impulse[: 3 * n].reshape(n, 3)
    c = (G @ impulse + g)[: 3 * n].reshape(n, 3)
    tangential = _safe_norm(z[:, :2])
    separated = z[:, 2] <= 0
    sliding = ~separated & (tangential >= mu * z[:, 2] * (1.0 - 1e-6))
    mode = jnp.where(separated, _SEPARATED, jnp.where(sliding, _SLIDING, _STICKING))
    slide_start = jnp.stack([z[:, 2], jnp.zeros_like(z[:, 2]), _safe_norm(c[:, :2])], axis=-1)
    x = jnp.where(sliding[:, None], slide_start, z)
    unit = z[:, :2] / jnp.where(tangential > 0, tangential, 1.0)[:, None]
    direction = jnp.where((tangential > 0)[:, None], unit, jnp.array([[1.0, 0.0]], G.dtype))
    if bounds is None:
        box_x = jnp.zeros((0,), G.dtype)

        def equations(x, box_x, direction):
            return _mode_equations(x, direction, mode, G, g, mu)
    else:
        box = impulse[3 * n :]
        near = 1.0 - 1e-6  # as the cone's boundary above
        box_mode = jnp.where(box >= bounds * near, 1, jnp.where(box <= -bounds * near, -1, 0))
        box_x = jnp.where(box_mode == 0, box, 0.0)

        def equations(x, box_x, direction):
            return _box_mode_equations(x, box_x, direction, mode, box_mode, G, g, mu, bounds)

    def newton(_, carry):
        x, box_x, direction = carry
        _, residual, jacobian = equations(x, box_x, direction)
        if least_squares is False:
            step = _newton_step(jacobian, residual)
        else:
            # the decomposition only where a member asks for least squares (under vmap)
            step = once_if(lambda operand, _: linalg.min_norm_solve(*operand, rcond=_MIN_NORM_RCOND),
                           jnp.asarray(least_squares), (jacobian, residual), _newton_step(jacobian, residual))
        cone_step = step[: 3 * n].reshape(n, 3)
        # Turn the direction by the angle step (a retraction onto the unit circle).
        turned = direction - cone_step[:, 1:2] * jnp.stack([-direction[:, 1], direction[:, 0]], axis=-1)
        return x - cone_step, box_x - step[3 * n :], turned / _safe_norm(turned)[:, None]

    # A loop, not unrolled: one copy of the Newton step in the program (compile time).
    x, box_x, direction = lax.fori_loop(0, steps, newton, (x, box_x, direction))
    return equations(x, box_x, direction)[0]


# NCPSolver.chunk_size = "auto" on the CPU (see the attribute's documentation)
CPU_CHUNK_SIZE = 4


class NCPSolver(eqx.Module):
    """ADMM for the frictional contact NCP with the De Saxcé correction.

    Finds impulses ``lambda`` (``3 n``, per contact ``[t1, t2, n]``) with

    .. math::
        K_\\mu \\ni \\lambda \\perp \\tilde c \\in K_\\mu^*, \\quad
        c = G\\lambda + g, \\quad \\tilde c = c + \\mu \\|c_T\\| e_N,

    i.e. Signorini's condition and Coulomb's law with maximum dissipation. For a fixed
    correction ``s = mu ||c_T|| e_N`` this is the KKT system of the convex problem
    ``min_{lambda in K} 1/2 lambdaᵀ G lambda + (g + s)ᵀ lambda``; ADMM on the splitting
    ``x = z, z in K`` iterates

    .. math::
        x^+ &= (G + \\rho I)^{-1}(\\rho z - y - g - s), \\\\
        z^+ &= P_K(\\alpha x^+ + (1 - \\alpha) z + y / \\rho), \\\\
        y^+ &= y + \\rho(\\alpha x^+ + (1 - \\alpha) z - z^+),

    and updates ``s`` from ``-y``, whose tangential part converges to ``c_T``, on the problem
    scaled to an equal diagonal (``scaling``). ``rho`` starts at ``sqrt(lambda_min lambda_max)``
    of the scaled ``G`` and is adapted by residual balancing; the linear solves reuse one
    eigendecomposition of it. Before ADMM a solve tries a starting impulse
    (the warm start or zero, or ``sticking_guess``) and ``polish``; ADMM runs only where they
    do not solve the problem (and ``polish`` once more where ADMM reaches its cap).

    Termination: all three residuals of :func:`ncp_residuals` are at most ``tolerance``
    (absolute: impulse, velocity and impulse x velocity units), or ADMM reaches
    ``max_iterations``. ADMM returns the best iterate ``z`` it met (the smallest largest
    residual, the starting impulse included; every ``z`` is exactly in the cone): a capped
    solve is never worse than its start, and ``NCPInfo.result`` says whether it is a solution
    (``NCPInfo.converged`` is ``result == RESULTS.successful``).

    Where ``G`` is singular (more contact rows than the degrees of freedom they constrain: a
    box on four coplanar corners) the impulses are not unique and the start decides which
    solution is found: ``sticking_guess``, ``polish`` and ``rho_update_power`` are therefore off
    by default, and the factories of :mod:`rsmooth.sim` turn them on per system (timings in
    benchmarks/RESULTS.md).

    Attributes:
        max_iterations: ADMM iteration cap.
        tolerance: absolute tolerance on the residuals; ``None``: one the problem's dtype can
            reach, ``1e-10`` in float64 and ``1e-5`` in float32 (rounding alone leaves
            residuals of about ``1e-7`` there).
        rho: initial ADMM penalty; ``None`` uses the spectral value.
        adaptive_rho: multiply or divide ``rho`` by a factor when the primal and dual ADMM
            residuals are more than 10 times apart.
        rho_update_power: ``None``: the factor is 2; a number ``p``: ``cond(G)^p``, large
            for the ill-conditioned ``G`` where ``rho`` matters (fewer iterations). Where the
            impulses are not unique the factor 2 reaches the solution whose next states match
            the finite differences of the implicit derivative; ``cond(G)^p`` another one.
        relaxation: over-relaxation ``alpha`` in ``(0, 2)`` for the first half of the
            iterations; the second half runs plain ADMM (``alpha = 1``), which converges where
            over-relaxation cycles (non-unique impulses at high friction).
        implicit_regularization: ``eps`` of the damped least-squares solve of the implicit
            derivative (see :func:`solve_ncp`).
        throw: raise (``equinox.error_if``) when the solve does not converge. Off by default:
            inside smoothed or batched rollouts one unconverged sample would abort the whole
            batch; check ``info.result`` (or ``info.converged``) instead.
        sticking_guess: where the warm start (or zero) is not already a solution, try the
            impulse that makes every contact whose free normal velocity does not open
            (``g_N`` at most the square root of the tolerance) stick and leaves the others
            without impulse, ``P_K(-G_AA^{-1} g_A)`` on that active
            set (one Cholesky factorization); where it solves the problem (a robot standing on
            sticking feet) the solve ends there. Otherwise ADMM starts from the warm start or,
            without one, from the guess (from zero with ``rank_deficient``).
        polish: an active-set Newton polish (in the spirit of OSQP's solution polishing, here
            with the nonlinear sliding modes), tried after the start and before ADMM: read
            each contact's mode (separated, sticking, sliding) from the start impulse, solve
            that mode's equations (``lambda = 0``; ``c = 0``; ``c_N = 0`` with the impulse on
            the cone's boundary opposite the slip) by ``polish_steps`` Newton iterations, and
            keep the result where it passes the tolerance test. A failed round is followed by
            one projected fixed-point step (correcting the modes it assumed) and another.
            Where ADMM then reaches ``max_iterations``, the polish runs again from its best
            iterate with least-squares (Gauss-Newton) steps: ADMM's slow tail is usually near
            enough for the modes to be right, and where many contacts stick on few degrees
            of freedom (a stack of boxes) the modes' equations are singular. Where that fails
            too, the contacts acting at its result (a positive normal impulse, or a closing
            normal velocity) are solved alone, ADMM and both polishes again with the other
            contacts separated, and that result is kept where it is better on the whole
            problem: on a singular ``G`` ADMM's iterate can lie elsewhere in the null space than
            any solution (a dog's paws, contacts in pairs whose solution has one of each pair
            sliding), and the polish returns there.
        polish_rounds: rounds of each polish (``polish`` only).
        polish_steps: Newton iterations per round.
        chunk_size: under ``vmap``, the problems that the start did not solve go through the
            polish and ADMM in chunks of this many (:func:`rsmooth._batching.run_where_needed`):
            a batch pays only for the members that need the work, and each loop runs as long
            as the slowest problem of its chunk, not of the batch. ``"auto"`` (the default):
            4 on the CPU, the whole batch on a GPU or TPU, where a chunk costs about what the
            whole batch does; an int fixes it. Results do not depend on it.
        rank_deficient: the sticking guess solves its active set by the pseudo-inverse of
            ``G_AA`` (eigenvalues below 1e-9 of the largest dropped: an eigendecomposition,
            or a Cholesky factorization of the smaller ``X_A X_Aᵀ`` where it is well
            conditioned and a Delassus factor is given), the minimum-norm sticking impulse,
            instead of a shifted Cholesky factorization of ``G_AA``, whose diagonal shift
            amplifies rounding in the null space of a singular ``G``. A resting
            box then stays at rest to rounding. Where the guess fails (a sliding box), ADMM
            starts from the warm start or zero: from the guess it is slower and reaches other
            solutions.
        scaling: ADMM iterates on the diagonally scaled problem ``G' = D G D``, ``g' = D g``,
            ``lambda = D z``, with one scale per contact (``D_ii`` proportional to ``1 /
            sqrt(trace(G_ii) / 3)``, so that each friction cone, the De Saxcé correction and
            ``lambdaᵀ c`` are unchanged) and per box row (``1 / sqrt(G_kk)``): an equivalent NCP
            whose diagonal entries are equal (their geometric mean, :func:`_row_scales`). One
            penalty ``rho`` cannot suit rows whose effective masses differ by orders of magnitude
            (the joint limits of a humanoid's light wrists beside its feet on the floor: ADMM
            then stalls far from the solution); on the scaled problem it can. The residuals, the
            tolerance and the best iterate stay in the problem's own units.

    References:
        J. Carpentier, Q. Le Lidec, L. Montaut, "From compliant to rigid contact simulation:
        a unified and efficient approach", RSS 2024.
        Q. Le Lidec, W. Jallet, L. Montaut, I. Laptev, C. Schmid, J. Carpentier, "Contact
        models in robotics: a comparative analysis", IEEE T-RO 2024.
        G. De Saxcé, Z.-Q. Feng, "The bipotential method: a constructive approach to design
        the complete contact law with friction and improved numerical algorithms",
        Mathematical and Computer Modelling 28(4-8), 1998.
        S. Boyd, N. Parikh, E. Chu, B. Peleato, J. Eckstein, "Distributed optimization and
        statistical learning via the alternating direction method of multipliers", 2011
        (Sec. 3.4.1 residual balancing, Sec. 3.4.3 over-relaxation).
    """

    max_iterations: int = eqx.field(static=True, default=500)
    tolerance: float | None = eqx.field(static=True, default=None)
    rho: float | None = eqx.field(static=True, default=None)
    adaptive_rho: bool = eqx.field(static=True, default=True)
    rho_update_power: float | None = eqx.field(static=True, default=None)
    relaxation: float = eqx.field(static=True, default=1.5)
    implicit_regularization: float = eqx.field(static=True, default=1e-12)
    throw: bool = eqx.field(static=True, default=False)
    sticking_guess: bool = eqx.field(static=True, default=False)
    polish: bool = eqx.field(static=True, default=False)
    polish_rounds: int = eqx.field(static=True, default=3)
    polish_steps: int = eqx.field(static=True, default=4)
    chunk_size: int | Literal["auto"] = eqx.field(static=True, default="auto")
    rank_deficient: bool = eqx.field(static=True, default=False)
    scaling: bool = eqx.field(static=True, default=True)

    def __check_init__(self):
        for name in ("polish_rounds", "polish_steps"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be an int >= 1, got {value!r}.")
        chunk = self.chunk_size
        if chunk != "auto" and (isinstance(chunk, bool) or not isinstance(chunk, int) or chunk < 1):
            raise ValueError(f"chunk_size must be an int >= 1 or 'auto', got {chunk!r}.")
        if not (isinstance(self.max_iterations, int) and self.max_iterations >= 1):
            raise ValueError(f"max_iterations must be an int >= 1, got {self.max_iterations}.")
        if self.tolerance is not None and not self.tolerance > 0:
            raise ValueError(f"tolerance must be positive, got {self.tolerance}.")
        if self.rho is not None and not self.rho > 0:
            raise ValueError(f"rho must be positive or None, got {self.rho}.")
        if self.rho_update_power is not None and not self.rho_update_power > 0:
            raise ValueError(f"rho_update_power must be positive, got {self.rho_update_power}.")
        if not 0 < self.relaxation < 2:
            raise ValueError(f"relaxation must be in (0, 2), got {self.relaxation}.")
        if not self.implicit_regularization > 0:
            raise ValueError(
                f"implicit_regularization must be positive, got {self.implicit_regularization}."
            )

    def _chunk(self) -> int | None:
        """``chunk_size`` for :func:`rsmooth._batching.run_where_needed` (``None``: the whole
        batch); ``"auto"`` is decided here, when the solve is traced."""
        return _xla.resolve_auto(self.chunk_size, cpu=CPU_CHUNK_SIZE, accelerator=None)

    def start(
        self, G: Array, g: Array, mu: Array, warm_start: Array | None, factor: Array | None = None, bounds: Array | None = None
    ) -> tuple[Array, NCPInfo]:
        """The impulse ADMM starts from and its diagnostics (``converged``: it already solves
        the problem and ADMM need not run; ``iterations`` and ``rho`` are 0). Without
        ``sticking_guess``: ``P_K(warm_start)``, or zero. With it: the sticking guess without a
        warm start (with ``rank_deficient``, only where it solves the problem, else zero);
        with one, the guess where it solves the problem and the warm start does not, else the
        warm start. ``factor``: an ``X`` ``(d, 3 n + m)`` with ``G = Xᵀ X`` (see :func:`solve_ncp`);
        ``bounds``: the box rows' (see :func:`solve_ncp`). ``G`` may be ``None`` with a
        ``factor``: its products are then taken as ``Xᵀ (X z)``, and ``G`` formed only where
        the sticking guess needs it."""

        def candidate(z):
            z = jnp.where(jnp.all(jnp.isfinite(z)), z, 0.0)
            primal, dual, complementarity = _residuals_at(_delassus_times(G, factor, z) + g, mu, z, bounds)
            converged = self._within_tolerance(primal, dual, complementarity)
            result = _ncp_result(converged, z, primal, dual, complementarity)
            return z, NCPInfo(jnp.zeros((), jnp.int32), primal, dual, complementarity, result, jnp.zeros((), g.dtype))

        if warm_start is None:
            given = jnp.zeros_like(g)
        else:
            given = _project(warm_start, mu, bounds)
        if not self.sticking_guess:
            return candidate(given)
        if warm_start is None and not self.rank_deficient:
            return candidate(self._sticking_guess(G, g, mu, factor, bounds))  # ADMM starts from it where it fails
        # The guess where it solves the problem and the start given does not; computed only
        # where that start fails (its eigendecomposition is most of a start's cost, and a warm
        # start from the previous step solves a resting scene's problem on its own): under
        # vmap, a loop run while some member of the batch needs it.
        warm = candidate(given)

        def use_guess_if_it_solves(problem, warm):
            guess = candidate(self._sticking_guess(*problem))
            use_guess = guess[1].converged & ~warm[1].converged
            return jax.tree.map(lambda a, b: jnp.where(use_guess, a, b), guess, warm)

        return once_if(use_guess_if_it_solves, ~warm[1].converged, (G, g, mu, factor, bounds), warm)

    def _sticking_guess(self, G: Array, g: Array, mu: Array, factor: Array | None, bounds: Array | None = None) -> Array:
        """The sticking impulse of :meth:`start`, projected on the friction cones (and the
        boxes: every box row with a positive bound is in the active set)."""
        n = mu.shape[0]
        # Contacts whose free normal velocity does not open stick (c_i = 0), the others carry
        # no impulse: solve G_AA lambda_A = -g_A on that active set A. "Does not open" is
        # g_N at most the square root of the solver's tolerance (1e-5 m/s in float64, the
        # slip below which StepInfo reports sticking), not g_N < 0: in a stack the bodies
        # fall together, so every contact but the floor's has g_N = 0 up to rounding and a
        # rocking of nanometres per step, and must stick to carry the weight above it. A
        # guess that is not finite or not a solution is not used.
        active = jnp.repeat(g[: 3 * n].reshape(n, 3)[:, 2] <= self.tolerance_for(g.dtype) ** 0.5, 3)
        if bounds is not None:
            active = jnp.concatenate([active, bounds > 0])
        rhs = jnp.where(active, g, 0.0)
        if self.rank_deficient and factor is not None and factor.shape[0] < g.shape[0]:
            # The same pseudo-inverse from the (m x m) X_A X_Aᵀ, X_A = X with A's columns only:
            # G_AA = X_Aᵀ X_A = V S² Vᵀ and X_A X_Aᵀ = U S² Uᵀ share their nonzero eigenvalues
            # S², and G_AA^+ = V S^-2 Vᵀ = X_Aᵀ U S^-4 Uᵀ X_A (V = X_Aᵀ U S^-1). For a scene of
            # many contacts on few degrees of freedom (a tower of boxes: 3 n = 4 m) the
            # factorization, the start's whole cost, shrinks by (3 n / m)³; where X_A X_Aᵀ is
            # well conditioned (every body held) it is a Cholesky factorization, not an
            # eigendecomposition (_squared_pseudo_inverse_times).
            reduced = jnp.where(active[None, :], factor, 0.0)
            inner = _squared_pseudo_inverse_times(reduced @ reduced.T, reduced @ rhs)
            sticking = jnp.where(active, -(reduced.T @ inner), 0.0)
            return _project(sticking, mu, bounds)
        if G is None:
            G = factor.T @ factor
        if self.rank_deficient:
            # The minimum-norm sticking impulse, by the pseudo-inverse of G_AA (eigenvalues
            # below 1e-9 of the largest dropped); see the attribute's documentation.
            eigenvalues, eigenvectors = linalg.eigh(jnp.where(active[:, None] & active[None, :], G, 0.0))
            keep = eigenvalues > 1e-9 * jnp.maximum(eigenvalues[-1], jnp.finfo(G.dtype).tiny ** 0.5)
            inverse = jnp.where(keep, 1.0 / jnp.where(keep, eigenvalues, 1.0), 0.0)
            # exactly zero off A: the eigenvectors mix A's null space with the inactive
            # coordinates, and a rounding-sized impulse there times a speculative contact's
            # large g_N (a gap of metres over h) fails the complementarity test
            sticking = jnp.where(active, -eigenvectors @ (inverse * (eigenvectors.T @ rhs)), 0.0)
        else:
            # Rows and columns of the inactive contacts replaced by the identity; a diagonal
            # shift of 1e-12 of G's scale keeps the factorization finite for a singular G, and
            # one step of iterative refinement removes its bias where G is not.
            identity = jnp.eye(G.shape[0], dtype=G.dtype)
            reduced = jnp.where(active[:, None] & active[None, :], G, identity)
            scale = jnp.maximum(jnp.max(jnp.diagonal(reduced)), jnp.finfo(G.dtype).tiny ** 0.5)
            factor = linalg.cho_factor(reduced + 1e-12 * scale * identity)
            sticking = -linalg.cho_solve(factor, rhs)
            sticking = sticking - linalg.cho_solve(factor, reduced @ sticking + rhs)
        return _project(sticking, mu, bounds)

    def init(self, G: Array, g: Array, mu: Array, warm_start: Array | None, bounds: Array | None = None) -> NCPState:
        """Initial iterate: ``z = P_K(warm_start)`` (or 0) and the matching ``y = -c~(z)``,
        so an exact warm start is a fixed point of :meth:`step` (:func:`solve_ncp` passes
        :meth:`start`'s impulse); with ``scaling``, of the scaled problem."""
        scale = _row_scales(G, mu.shape[0]) if self.scaling else jnp.ones_like(g)
        G_scaled, g_scaled = scale[:, None] * G * scale[None, :], scale * g
        eigenvalues, eigenvectors = linalg.eigh(G_scaled)
        largest = jnp.maximum(eigenvalues[-1], jnp.finfo(G.dtype).tiny ** 0.5)
        if self.rho is None:
            # Spectral choice sqrt(m L) (Carpentier et al. 2024), m floored so a singular G
            # (more contact rows than degrees of freedom) still gets a positive penalty.
            rho = jnp.sqrt(largest * jnp.maximum(eigenvalues[0], 1e-8 * largest))
        else:
            rho = jnp.asarray(self.rho, G.dtype)
        if warm_start is None:
            z = jnp.zeros_like(g)
        else:
            z = _project(warm_start, mu, bounds)
        y = -_corrected_velocity(G_scaled @ (z / scale) + g_scaled, mu)
        primal, dual, complementarity = ncp_residuals(G, g, mu, z, bounds)
        return NCPState(
            x=z / scale,
            z=z / scale,
            y=y,
            rho=rho,
            eigenvalues=eigenvalues,
            eigenvectors=eigenvectors,
            scale=scale,
            iteration=jnp.array(0, dtype=jnp.int32),
            primal_feasibility=primal,
            dual_feasibility=dual,
            complementarity=complementarity,
            best=z,
            best_residuals=jnp.stack([primal, dual, complementarity]),
        )

    def step(self, G: Array, g: Array, mu: Array, state: NCPState, bounds: Array | None = None) -> NCPState:
        """One ADMM iteration (see the class docstring)."""
        n = mu.shape[0]
        x, z, y, rho, scale = state.x, state.z, state.y, state.rho, state.scale
        del x
        dual_by_contact = (-y[: 3 * n]).reshape(n, 3)
        correction = jnp.zeros_like(dual_by_contact).at[:, 2].set(
            mu * _safe_norm(dual_by_contact[:, :2])
        ).reshape(-1)
        if bounds is not None:  # box rows are not corrected
            correction = jnp.concatenate([correction, jnp.zeros_like(bounds)])
        rhs = rho * z - y - scale * g - correction
        Q, eigenvalues = state.eigenvectors, state.eigenvalues
        x_next = Q @ ((Q.T @ rhs) / (eigenvalues + rho))
        # Over-relaxation speeds up most problems, but with the De Saxce correction (not a
        # convex problem) it can cycle where the impulses are not unique and friction is high
        # (a box sliding on four corners at mu = 0.8): the second half of the iterations runs
        # plain ADMM, which converges there.
        relaxation = jnp.where(state.iteration < self.max_iterations // 2, self.relaxation, 1.0).astype(z.dtype)
        x_relaxed = relaxation * x_next + (1.0 - relaxation) * z
        z_next = _project(x_relaxed + y / rho, mu, None if bounds is None else bounds / scale[3 * n :])
        y_next = y + rho * (x_relaxed - z_next)

        if self.adaptive_rho:
            admm_primal = jnp.max(jnp.abs(x_next - z_next))
            admm_dual = rho * jnp.max(jnp.abs(z_next - z))
            # Spectral step: the factor is cond(G)^p (the same floor on lambda_min as the
            # initial rho), large for the ill-conditioned G where rho matters and 1 for a
            # well-conditioned one, where the initial sqrt(m L) is already right; or 2.
            largest = jnp.maximum(eigenvalues[-1], jnp.finfo(G.dtype).tiny ** 0.5)
            if self.rho_update_power is None:
                factor = 2.0
            else:
                factor = (largest / jnp.maximum(eigenvalues[0], 1e-8 * largest)) ** self.rho_update_power
            rho_next = jnp.where(
                admm_primal > 10.0 * admm_dual,
                factor * rho,
                jnp.where(admm_dual > 10.0 * admm_primal, rho / factor, rho),
            )
            # Keep the penalty within 12 orders of magnitude of G's spectrum.
            rho_next = jnp.clip(rho_next, 1e-6 * largest, 1e6 * largest)
        else:
            rho_next = rho

        impulse = scale * z_next
        primal, dual, complementarity = ncp_residuals(G, g, mu, impulse, bounds)
        residuals = jnp.stack([primal, dual, complementarity])
        better = jnp.max(residuals) < jnp.max(state.best_residuals)  # False for NaN
        return NCPState(
            x=x_next,
            z=z_next,
            y=y_next,
            rho=rho_next,
            eigenvalues=eigenvalues,
            eigenvectors=Q,
            scale=scale,
            iteration=state.iteration + 1,
            primal_feasibility=primal,
            dual_feasibility=dual,
            complementarity=complementarity,
            best=jnp.where(better, impulse, state.best),
            best_residuals=jnp.where(better, residuals, state.best_residuals),
        )

    def _within_tolerance(self, primal: Array, dual: Array, complementarity: Array) -> Array:
        # A NaN residual compares False, so it never counts as converged.
        tolerance = self.tolerance_for(primal.dtype)
        return (primal <= tolerance) & (dual <= tolerance) & (complementarity <= tolerance)

    def tolerance_for(self, dtype) -> float:
        """The tolerance on the residuals of a problem in ``dtype`` (see ``tolerance``)."""
        if self.tolerance is not None:
            return self.tolerance
        return 1e-10 if jnp.finfo(dtype).bits >= 64 else 1e-5

    def polished(
        self, G: Array, g: Array, mu: Array, impulse: Array, least_squares: ArrayLike = False, bounds: Array | None = None
    ) -> tuple[Array, Array, Array, Array, Array]:
        """The polish (:func:`_polish`) of ``impulse``, or ``impulse`` where it is not finite,
        its residuals and whether they satisfy the tolerance: ``(candidate, primal, dual,
        complementarity, solved)``."""
        candidate = _polish(G, g, mu, impulse, self.polish_steps, least_squares, bounds)
        candidate = jnp.where(jnp.all(jnp.isfinite(candidate)), candidate, impulse)
        primal, dual, complementarity = ncp_residuals(G, g, mu, candidate, bounds)
        return candidate, primal, dual, complementarity, self._within_tolerance(primal, dual, complementarity)

    def _residuals_within_tolerance(self, state: NCPState) -> Array:
        return self._within_tolerance(*state.best_residuals)

    def terminate(self, state: NCPState) -> Array:
        """True once converged or at the iteration cap."""
        return self._residuals_within_tolerance(state) | (state.iteration >= self.max_iterations)

    def postprocess(self, state: NCPState) -> tuple[Array, NCPInfo]:
        """The best impulse (never worse than the one the iterations started from) and the
        diagnostics at it."""
        primal, dual, complementarity = state.best_residuals
        converged = self._residuals_within_tolerance(state)
        info = NCPInfo(
            iterations=state.iteration,
            primal_feasibility=primal,
            dual_feasibility=dual,
            complementarity=complementarity,
            result=_ncp_result(converged, state.best, primal, dual, complementarity),
            rho=state.rho,
        )
        return state.best, info

    def solve(
        self, G: ArrayLike, g: ArrayLike, mu: ArrayLike, *, warm_start: ArrayLike | None = None, bounds: ArrayLike | None = None
    ) -> tuple[Array, NCPInfo]:
        """Same as :func:`solve_ncp` with this solver."""
        return solve_ncp(G, g, mu, solver=self, warm_start=warm_start, bounds=bounds)


# The size of X_A X_Aᵀ from which the sticking guess tries a Cholesky factorization first. Below
# it the eigendecomposition costs little, and the factorization's fallback loop (a while loop,
# run or not) cost a cube's and a pusher's batched step more than it saved.
_CHOLESKY_MIN_SIZE = 24


def _squared_pseudo_inverse_times(gram: Array, b: Array) -> Array:
    """``(A^+)² b`` for the symmetric positive semidefinite ``A = gram`` ``(d, d)``, with ``b``
    in its range: eigenvalues below 1e-9 of the largest count as zero (the sticking guess's
    pseudo-inverse, :meth:`NCPSolver._sticking_guess`).

    From ``d`` = :data:`_CHOLESKY_MIN_SIZE` on, by a Cholesky factorization where ``A`` is well
    conditioned, the common case (every body of a resting stack held by its contacts), else by
    an eigendecomposition, seven to nine times the factorization's cost at ``d`` = 96 (under
    ``vmap``, computed only while some member needs it); below, by the eigendecomposition. The factorization is used where three steps of inverse iteration
    (from a fixed start with no special direction) find no eigenvalue below 1e-7 of the trace,
    a hundred times above the eigendecomposition's cut: the two give the same result to
    rounding there. Rows and columns that are exactly zero (degrees of freedom no active
    contact touches, e.g. a free body in flight) get a unit diagonal: ``b`` is zero there, and
    so is the result, as the pseudo-inverse gives."""
    d = gram.shape[0]
    if d < _CHOLESKY_MIN_SIZE:
        return _squared_pseudo_inverse_by_eigh(gram, b)
    diagonal = jnp.diagonal(gram)
    trace = jnp.maximum(jnp.sum(diagonal), jnp.finfo(gram.dtype).tiny ** 0.5)
    filled = gram + jnp.diag(jnp.where(diagonal == 0, trace, 0.0))
    cholesky = linalg.cholesky(filled)

    def solve(x):
        return linalg.cho_solve((cholesky, True), x)

    x = jnp.sin(1.0 + 2.3 * jnp.arange(d, dtype=gram.dtype))
    for _ in range(3):
        x = solve(x)
        x = x / jnp.maximum(_safe_norm(x), jnp.finfo(gram.dtype).tiny)
    smallest = x @ (filled @ x)
    result = solve(solve(b))
    conditioned = jnp.all(jnp.isfinite(result)) & jnp.isfinite(smallest) & (smallest > 1e-7 * trace)

    return once_if(lambda operand, _: _squared_pseudo_inverse_by_eigh(*operand), ~conditioned, (gram, b),
                   jnp.where(conditioned, result, 0.0))


def _squared_pseudo_inverse_by_eigh(gram: Array, b: Array) -> Array:
    """:func:`_squared_pseudo_inverse_times` by an eigendecomposition."""
    eigenvalues, eigenvectors = linalg.eigh(gram)
    keep = eigenvalues > 1e-9 * jnp.maximum(eigenvalues[-1], jnp.finfo(gram.dtype).tiny ** 0.5)
    inverse = jnp.where(keep, 1.0 / jnp.where(keep, eigenvalues, 1.0), 0.0)
    return eigenvectors @ (inverse**2 * (eigenvectors.T @ b))


def _checked_problem(G, g, mu, warm_start, bounds=None, factored=False):
    """Host-side shape checks, value checks (host or traced), common floating dtype;
    ``factored``: a traced ``G`` is not checked (its factor is: see :func:`_solve`)."""
    G, g, mu = jnp.asarray(G), jnp.asarray(g), jnp.asarray(mu)
    m = 0
    if bounds is not None:
        bounds = jnp.asarray(bounds)
        if bounds.ndim != 1 or bounds.shape[0] == 0:
            raise ValueError(f"bounds must be None or have shape (m,) for m >= 1 box rows, got {bounds.shape}.")
        m = bounds.shape[0]
    if mu.ndim != 1 or (mu.shape[0] == 0 and m == 0):
        raise ValueError(f"mu must have shape (n,) for n >= 1 contacts (n >= 0 with box rows), got {mu.shape}.")
    n = mu.shape[0]
    size = 3 * n + m
    rows = f"3n + m = {size} for n = {n} contacts and m = {m} box rows"
    if G.shape != (size, size):
        raise ValueError(f"G must have shape (3n + m, 3n + m) with {rows} (mu has shape {mu.shape}), got {G.shape}.")
    if g.shape != (size,):
        raise ValueError(f"g must have shape (3n + m,) with {rows}, got {g.shape}.")
    if warm_start is not None:
        warm_start = jnp.asarray(warm_start)
        if warm_start.shape != (size,):
            raise ValueError(f"warm_start must have shape {(size,)}, got {warm_start.shape}.")
    dtype = jnp.result_type(G, g, mu, float)
    G, g, mu = G.astype(dtype), g.astype(dtype), mu.astype(dtype)
    if not (factored and not _is_concrete(G)):
        G = _check_finite("G", G)
    g = _check_finite("g", g)
    mu = _check_finite("mu", mu)
    mu = _check_nonnegative("mu", mu)
    if bounds is not None:  # infinite bounds allowed (bilateral rows); NaN is not >= 0
        bounds = bounds.astype(dtype)
        if _is_concrete(bounds) and np.any(np.isnan(np.asarray(bounds))):
            raise ValueError("bounds contains NaN values.")
        bounds = _check_nonnegative("bounds", jnp.where(jnp.isnan(bounds), -1.0, bounds))
    if _is_concrete(G):
        G_host = np.asarray(G)
        scale = max(float(np.max(np.abs(G_host))), 1e-300)
        if np.max(np.abs(G_host - G_host.T)) > 1e-8 * scale:
            raise ValueError("G must be symmetric (G = J M^-1 J^T).")
        if np.linalg.eigvalsh(G_host)[0] < -1e-8 * scale:
            raise ValueError("G must be positive semi-definite (G = J M^-1 J^T).")
    if warm_start is not None:
        warm_start = _check_finite("warm_start", warm_start.astype(dtype))
    return G, g, mu, warm_start, bounds


def solve_ncp(
    G: ArrayLike,
    g: ArrayLike,
    mu: ArrayLike,
    *,
    solver: NCPSolver = NCPSolver(),
    warm_start: ArrayLike | None = None,
    delassus_factor: ArrayLike | None = None,
    bounds: ArrayLike | None = None,
) -> tuple[Array, NCPInfo]:
    """Solves the frictional contact NCP and attaches its implicit derivative.

    See :class:`NCPSolver` for the problem and the algorithm. The solve runs on
    ``stop_gradient``-ed inputs; derivatives with respect to ``G``, ``g`` and ``mu``
    (forward and reverse mode) come from the implicit function theorem applied to the
    natural map ``F(lambda) = lambda - P_K(lambda - r c~(lambda)) = 0`` at the returned
    solution, with one dense ``(3 n + m) x (3 n + m)`` damped least-squares solve. Per contact
    mode this gives: separated contacts (``lambda_i = 0``) a zero derivative, sticking contacts
    the derivative of a bilateral constraint (``dc_i = 0``), sliding contacts the derivative
    along the cone boundary with ``dc_N = 0``; box rows inside their bounds ``dc_k = 0``, on a
    bound ``dlambda_k = ±db_k``. At a mode switch the derivative is one of the one-sided ones.
    No derivative flows through ``warm_start`` or the diagnostics.

    Box rows (``bounds``) follow the ``3 n`` contact rows: ``|lambda_k| <= b_k`` with maximum
    dissipation, the impulse of dry friction on a joint (see the module docstring). With them
    the problem may have no contact at all (``mu`` of shape ``(0,)``).

    Args:
        G: Delassus matrix ``J M^{-1} Jᵀ``, symmetric positive semi-definite,
            ``(3 n + m, 3 n + m)``.
        g: free contact velocity (the contact-frame velocity without impulses, possibly
            with :func:`corrected_free_velocity`), ``(3 n + m,)``.
        mu: friction coefficients ``>= 0``, ``(n,)``.
        solver: the :class:`NCPSolver` configuration.
        warm_start: an impulse guess ``(3 n + m,)``, e.g. the previous time step's solution.
        delassus_factor: optionally ``X`` ``(d, 3 n + m)`` with ``G = Xᵀ X`` (a simulator's
            ``L^-1 Jᵀ``, ``L`` the Cholesky factor of the mass matrix, ``d`` its degrees of
            freedom). The solve then reads ``G`` only through ``X``: the start's products as
            ``Xᵀ (X z)``, and ``Xᵀ X`` formed again where the start does not solve the
            problem; with ``rank_deficient`` and ``d < 3 n + m`` the sticking guess takes its
            pseudo-inverse from the ``(d x d)`` ``X Xᵀ`` (the same impulse, to rounding). In a
            program where nothing else reads ``G`` (no derivative is taken) XLA then leaves
            out forming it (``O((3 n + m)² d)``, the largest cost of a resting stack of boxes'
            solve) wherever the start solves the problem. No derivative flows through ``X``;
            a traced ``G`` is not checked for NaN (``X`` is).
        bounds: ``None``, or the bounds ``b_k >= 0`` of ``m`` box rows, ``(m,)`` (``inf``: a
            bilateral row).

    Returns:
        ``(impulse, info)``: impulses ``(3 n + m,)``, per contact ``[t1, t2, n]`` then per
        box row, and an :class:`NCPInfo`.

    Raises:
        ValueError: on wrong shapes; on NaN/inf in ``G``, ``g``, ``mu``, negative ``mu``,
            NaN or negative ``bounds``, and a non-symmetric or indefinite ``G``, when these
            values are concrete. Traced values are checked with ``equinox.error_if``
            (NaN/inf, negative ``mu`` and ``bounds``).

    Example:
        >>> import jax.numpy as jnp
        >>> impulse, info = solve_ncp(jnp.eye(3), jnp.array([0.0, 0.0, -0.1]),
        ...                           jnp.array([0.5]))
        >>> [round(float(v), 6) for v in impulse], bool(info.converged)
        ([0.0, 0.0, 0.1], True)

    References:
        M. Blondel, Q. Berthet, M. Cuturi, R. Frostig, S. Hoyer, F. Llinares-López,
        F. Pedregosa, J.-P. Vert, "Efficient and modular implicit differentiation",
        NeurIPS 2022.
        Q. Le Lidec, L. Montaut, Y. de Mont-Marin, F. Schramm, J. Carpentier, "End-to-end
        and highly-efficient differentiable simulation for robotics", 2024.
    """
    G, g, mu, warm_start, bounds = _checked_problem(G, g, mu, warm_start, bounds, factored=delassus_factor is not None)
    if delassus_factor is not None:
        delassus_factor = jnp.asarray(delassus_factor)
        if delassus_factor.ndim != 2 or delassus_factor.shape[1] != G.shape[0]:
            raise ValueError(
                f"delassus_factor must have shape (d, {G.shape[0]}) (G = Xᵀ X), got {delassus_factor.shape}"
            )
        delassus_factor = _check_finite("delassus_factor", delassus_factor.astype(G.dtype))
    arguments = (G, g, mu, warm_start, delassus_factor, bounds)
    # Called outside any trace (a script's loop over problems) the solve is one compiled
    # program per solver and shapes, reused by later calls: run eagerly, each of its loops
    # would be compiled anew at every call (their bodies are new closures). Inside a trace
    # (a step, jit, grad, vmap) it is part of the caller's program.
    eager = all(_is_concrete(a) for a in arguments if a is not None)
    return (_solve_compiled if eager else _solve)(*arguments, solver)


def _solve(G, g, mu, warm_start, delassus_factor, bounds, solver: NCPSolver) -> tuple[Array, NCPInfo]:
    """:func:`solve_ncp` on a checked problem."""
    G_solve, g_solve, mu_solve = (lax.stop_gradient(a) for a in (G, g, mu))
    bounds_solve = None if bounds is None else lax.stop_gradient(bounds)
    if warm_start is not None:
        warm_start = lax.stop_gradient(warm_start)

    # ADMM (and the eigendecomposition of G its init computes) runs only if the starting
    # impulse does not already solve the problem. A while_loop rather than a cond: under vmap
    # a cond with a batched predicate computes both branches, while this loop's body runs
    # only if some member of the batch needs it.
    # With a factor X, G = Xᵀ X is read through X only: the start's products, and the work
    # after it forms G inside its branch (see solve_ncp's delassus_factor).
    factored = delassus_factor is not None
    if factored:
        delassus_factor = lax.stop_gradient(delassus_factor)
    start, start_info = solver.start(
        None if factored else G_solve, g_solve, mu_solve, warm_start, factor=delassus_factor, bounds=bounds_solve
    )

    # Each loop's body first passes the problem through an optimization barrier with the
    # loop's carry: without it XLA hoists loop-invariant work (ADMM's eigendecomposition of G,
    # parts of the polish) out of the loop, where it runs whether the loop does or not.
    problem = (delassus_factor if factored else G_solve, g_solve, mu_solve, bounds_solve)

    def polish(problem, carry, least_squares=False):
        # Rounds of the polish, in a loop that (under vmap) runs while some member of the
        # chunk is not solved: the first polishes the start, each later one first takes a
        # projected fixed-point step lambda - F(lambda) = P_K(lambda - r c~) (F the natural
        # map) from the last polished impulse, which corrects the modes the failed polish
        # assumed.
        def polish_round(carry):
            (G, g, mu, bounds), carry = lax.optimization_barrier((problem, carry))
            round_, _, (impulse, info), last = carry
            moved = last - _natural_map(last, G, g, mu, fixed_point_step_sizes(G, mu.shape[0]), bounds)
            candidate, primal, dual, complementarity, solved = solver.polished(
                G, g, mu, jnp.where(round_ == 0, impulse, moved), least_squares, bounds
            )
            solved = solved & ~info.converged
            # kept only where solved: a successful solve
            polished = NCPInfo(info.iterations, primal, dual, complementarity, RESULTS.successful, info.rho)
            info = jax.tree.map(lambda a, b: jnp.where(solved, a, b), polished, info)
            return round_ + 1, info.converged, (jnp.where(solved, candidate, impulse), info), candidate

        return lax.while_loop(lambda c: ~c[1] & (c[0] < solver.polish_rounds), polish_round, carry)

    def admm(problem, start, start_info, needed):
        def run(problem, state):
            G, g, mu, bounds = problem
            state = solver.init(G, g, mu, state[0], bounds)
            state = lax.while_loop(lambda s: ~solver.terminate(s), lambda s: solver.step(G, g, mu, s, bounds), state)
            return solver.postprocess(state)

        return once_if(run, needed & ~start_info.converged, problem, (start, start_info))

    def finish(problem, carry):
        if factored:  # G formed here, where the start did not solve the problem
            X, g_, mu_, bounds_ = problem
            problem = (X.T @ X, g_, mu_, bounds_)
        # the polish's rounds, then ADMM, for a problem the start did not solve; then the
        # polish again from ADMM's best iterate where ADMM stopped at its cap: its slow tail
        # (an impact that switches many contacts' modes at once) is usually close enough for
        # the modes to be right, and Newton's method on them then converges in a few steps
        # (by least squares: where ADMM needs its cap, the modes' equations are often singular)
        if not solver.polish:
            round_, _, (impulse, info), last = carry
            impulse, info = admm(problem, impulse, info, jnp.ones((), bool))
            return round_, info.converged, (impulse, info), last

        G, g, mu, bounds = problem

        def phase(state):
            # phase 0: polish, then ADMM; phase 1: the least-squares polish of ADMM's iterate;
            # phases 2 and 3: the same on the problem restricted to the contacts that act at
            # phase 1's result (its other contacts separated). One loop, so that the program
            # holds one copy of each (compile time).
            index, rows, fallback, carry = state
            local = (*_restricted_problem(G, g, rows), mu, bounds)
            carry = polish(local, carry, least_squares=index % 2 == 1)
            round_, _, (impulse, info), last = carry
            impulse, info = admm(local, impulse, info, index % 2 == 0)
            # after phase 1 (unsolved): its result kept, its acting contacts' problem next
            # (see NCPSolver.polish: ADMM's iterate in the wrong part of a singular G's null space)
            restrict = index == 1
            rows = jnp.where(restrict, _restricted_rows(G, g, mu, impulse), rows)
            fallback = jax.tree.map(lambda a, b: jnp.where(restrict, a, b), (impulse, info), fallback)
            impulse = jnp.where(restrict, jnp.where(rows, impulse, 0.0), impulse)
            return index + 1, rows, fallback, (jnp.zeros_like(round_), info.converged, (impulse, info), impulse)

        index, _, (fallback, fallback_info), carry = lax.while_loop(
            lambda state: (state[0] < 4) & ~state[3][1], phase, (jnp.zeros((), jnp.int32), jnp.ones(g.shape, bool), carry[2], carry)
        )
        # The restricted problem's result, where it ran, judged on the whole problem: kept where
        # it is better than phase 1's (a solution, or a smaller largest residual).
        round_, _, (impulse, info), last = carry
        primal, dual, complementarity = ncp_residuals(G, g, mu, impulse, bounds)
        converged = solver._within_tolerance(primal, dual, complementarity)
        whole = NCPInfo(fallback_info.iterations + info.iterations, primal, dual, complementarity,
                        _ncp_result(converged, impulse, primal, dual, complementarity), info.rho)
        restricted = index > 2
        phase_one = jax.tree.map(lambda a, b: jnp.where(restricted, a, b), (fallback, fallback_info), carry[2])
        largest = lambda i: jnp.maximum(jnp.maximum(i.primal_feasibility, i.dual_feasibility), i.complementarity)  # noqa: E731
        better = restricted & (converged | (largest(whole) < largest(fallback_info)))
        impulse, info = jax.tree.map(lambda a, b: jnp.where(better, a, b), (impulse, whole), phase_one)
        return round_, info.converged, (impulse, info), last

    # Everything after the start only where it did not solve the problem: under vmap, those
    # members are gathered in chunks (rsmooth._batching), so that the one member in a batch
    # that needs another round of the polish, or ADMM, does not make the whole batch run them,
    # and a batch whose start solved everything (a standing robot) skips it all.
    carry = (jnp.zeros((), jnp.int32), start_info.converged, (start, start_info), start)
    carry = run_where_needed(finish, ~start_info.converged, problem, carry, chunk=solver._chunk())
    impulse, info = carry[2]
    # Reported in the result too: a caller that leaves out the traced checks above
    # (rsmooth._checks.without_traced_checks, e.g. a rollout) still sees an invalid problem.
    invalid = ~jnp.all(jnp.isfinite(delassus_factor if factored else G)) | ~jnp.all(jnp.isfinite(g)) | ~jnp.all(jnp.isfinite(mu)) | jnp.any(mu < 0)
    if bounds is not None:
        invalid = invalid | ~jnp.all(bounds >= 0)
    info = eqx.tree_at(lambda i: i.result, info, RESULTS.where(invalid, RESULTS.invalid_input, info.result))
    if solver.throw:
        impulse = eqx.error_if(
            impulse, ~info.converged, "NCP solver did not converge within max_iterations, or its impulse is not finite (NCPInfo.result).",
        )
    impulse = _with_implicit_derivative(solver.implicit_regularization, impulse, G, g, mu, bounds)
    return impulse, info


_solve_compiled = eqx.filter_jit(_solve)
