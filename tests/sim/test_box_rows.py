"""Box rows of the NCP (dry joint friction, bilateral rows): ``|lambda_k| <= b_k`` with maximum
dissipation, alone and beside frictional contacts. References: the closed form of one row,
an exact enumeration of the active sets of the box-constrained quadratic program that a
problem of box rows alone is, the optimality conditions checked in NumPy, and central finite
differences of the implicit derivative."""

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rsmooth.sim._ncp import NCPSolver, ncp_residuals, solve_ncp

TIGHT = NCPSolver(tolerance=1e-13, max_iterations=20000)
POLISHED = NCPSolver(sticking_guess=True, polish=True, rank_deficient=True, max_iterations=2000)
NO_CONTACTS = jnp.zeros((0,))


def random_delassus(rng, size, rank=None):
    """A symmetric positive (semi-)definite ``J M^-1 Jᵀ`` of the given size."""
    J = rng.normal(size=(size if rank is None else rank, size))
    return J.T @ J + (1e-1 * np.eye(size) if rank is None else 0.0)


def box_qp_by_enumeration(G, g, bounds):
    """``argmin 1/2 λᵀGλ + gᵀλ`` over ``|λ| <= b`` (G positive definite) by trying every
    assignment of the rows to the lower bound, the upper bound or the interior: the one whose
    KKT conditions hold is the unique minimizer."""
    m = len(bounds)
    for assignment in itertools.product((-1, 0, 1), repeat=m):
        assignment = np.array(assignment)
        free = assignment == 0
        impulse = np.where(free, 0.0, assignment * bounds)
        if free.any():
            rhs = -(g[free] + G[np.ix_(free, ~free)] @ impulse[~free])
            impulse[free] = np.linalg.solve(G[np.ix_(free, free)], rhs)
        velocity = G @ impulse + g
        feasible = np.all(np.abs(impulse) <= bounds + 1e-12)
        opposed = np.all(np.where(assignment > 0, velocity <= 1e-12, True) & np.where(assignment < 0, velocity >= -1e-12, True))
        if feasible and opposed:
            return impulse
    raise AssertionError("no active set satisfies the KKT conditions")


@pytest.mark.parametrize("free_velocity", [0.3, -0.3, 2.0, -2.0])
def test_one_row_matches_its_closed_form(free_velocity):
    # λ = clip(-g / G, -b, b): sticking where the bound can stop the row, else at the bound
    # that opposes its velocity.
    G, bounds = jnp.array([[2.0]]), jnp.array([0.5])
    for solver in (NCPSolver(), POLISHED):
        impulse, info = solve_ncp(G, jnp.array([free_velocity]), NO_CONTACTS, bounds=bounds, solver=solver)
        assert bool(info.converged)
        np.testing.assert_allclose(impulse, [np.clip(-free_velocity / 2.0, -0.5, 0.5)], atol=1e-10)


@pytest.mark.parametrize("seed", range(4))
def test_box_rows_alone_solve_the_box_qp(seed):
    rng = np.random.default_rng(seed)
    G = random_delassus(rng, 3)
    g = rng.normal(size=3)
    bounds = np.abs(rng.normal(size=3)) * 0.5
    expected = box_qp_by_enumeration(G, g, bounds)
    for solver in (TIGHT, POLISHED):
        impulse, info = solve_ncp(G, g, NO_CONTACTS, bounds=bounds, solver=solver)
        assert bool(info.converged), info
        np.testing.assert_allclose(impulse, expected, atol=1e-8)


def test_infinite_bounds_are_bilateral_rows():
    rng = np.random.default_rng(5)
    G, g = random_delassus(rng, 3), rng.normal(size=3)
    impulse, info = solve_ncp(G, g, NO_CONTACTS, bounds=jnp.full(3, jnp.inf), solver=POLISHED)
    assert bool(info.converged)
    np.testing.assert_allclose(G @ np.asarray(impulse) + g, 0.0, atol=1e-9)


def check_optimality(G, g, mu, bounds, impulse, tolerance=1e-7):
    """The contact and box conditions, checked in NumPy on one contact and box rows."""
    impulse, velocity = np.asarray(impulse), G @ np.asarray(impulse) + g
    lam_t, lam_n, c_t, c_n = impulse[:2], impulse[2], velocity[:2], velocity[2]
    assert lam_n >= -tolerance and np.linalg.norm(lam_t) <= mu * lam_n + tolerance
    if lam_n <= tolerance:  # separated: the contact opens
        assert c_n >= -tolerance
    elif np.linalg.norm(lam_t) < mu * lam_n - tolerance:  # sticking
        np.testing.assert_allclose(velocity[:3], 0.0, atol=tolerance)
    else:  # sliding: no normal velocity, friction opposite the slip
        assert abs(c_n) <= tolerance
        np.testing.assert_allclose(lam_t * np.linalg.norm(c_t), -mu * lam_n * c_t, atol=tolerance)
    box, c = impulse[3:], velocity[3:]
    assert np.all(np.abs(box) <= bounds + tolerance)
    interior = np.abs(box) < bounds - tolerance
    assert np.all(np.abs(c[interior]) <= tolerance)
    assert np.all(c[box >= bounds - tolerance] <= tolerance) and np.all(c[box <= -bounds + tolerance] >= -tolerance)


@pytest.mark.parametrize("seed", range(6))
def test_box_rows_beside_a_contact(seed):
    # One frictional contact coupled with two box rows (a foot on the ground and two joints
    # with dry friction): the contact's modes and the rows' bounds hold together.
    rng = np.random.default_rng(10 + seed)
    G = random_delassus(rng, 5)
    g = rng.normal(size=5)
    g[2] = -abs(g[2])  # the contact closes
    mu, bounds = np.array([0.3 + 0.4 * rng.random()]), np.abs(rng.normal(size=2)) * 0.3
    for solver in (TIGHT, POLISHED):
        impulse, info = solve_ncp(G, g, mu, bounds=bounds, solver=solver)
        assert bool(info.converged), info
        check_optimality(G, g, mu[0], bounds, impulse)
    # Residuals see a violated bound and a row sticking inside its bound while it moves.
    primal, _, _ = ncp_residuals(G, g, mu, impulse.at[3].set(bounds[0] + 0.1), bounds)
    assert float(primal) >= 0.1 - 1e-12


def test_decoupled_rows_do_not_change_the_contact():
    rng = np.random.default_rng(3)
    G_contact, g_contact, mu = random_delassus(rng, 3), np.array([0.2, -0.1, -0.5]), np.array([0.5])
    G_box, g_box, bounds = random_delassus(rng, 2), rng.normal(size=2), np.array([0.1, 0.2])
    G = np.block([[G_contact, np.zeros((3, 2))], [np.zeros((2, 3)), G_box]])
    impulse, info = solve_ncp(G, np.concatenate([g_contact, g_box]), mu, bounds=bounds, solver=TIGHT)
    contact_alone, _ = solve_ncp(G_contact, g_contact, mu, solver=TIGHT)
    assert bool(info.converged)
    np.testing.assert_allclose(impulse[:3], contact_alone, atol=1e-9)
    np.testing.assert_allclose(impulse[3:], box_qp_by_enumeration(G_box, g_box, bounds), atol=1e-9)


def test_float32_box_rows():
    G = jnp.array([[2.0, 0.5], [0.5, 1.0]], jnp.float32)
    g, no_contacts, bounds = jnp.array([1.0, -0.05], jnp.float32), jnp.zeros((0,), jnp.float32), jnp.full(2, 0.2, jnp.float32)
    impulse, info = solve_ncp(G, g, no_contacts, bounds=bounds)
    assert impulse.dtype == jnp.float32 and bool(info.converged)
    expected = box_qp_by_enumeration(np.asarray(G, np.float64), np.array([1.0, -0.05]), np.array([0.2, 0.2]))
    # float32's tolerance is 1e-5 on c_k (b_k + lambda_k) = c_k 0.35: c_k up to 3e-5, which G
    # (smallest eigenvalue 0.79) turns into an impulse error up to 4e-5.
    np.testing.assert_allclose(impulse, expected, atol=5e-5)
    impulse, info = solve_ncp(G, g, no_contacts, bounds=bounds, solver=POLISHED)
    assert bool(info.converged)
    np.testing.assert_allclose(impulse, expected, atol=1e-6)  # the polish solves the modes' equations


@pytest.mark.parametrize("sticking", [True, False])
def test_implicit_derivative_matches_finite_differences(sticking):
    # Away from mode switches: the last row sticking inside its bound, or at its bound, beside
    # a sliding contact and a sticking row; the derivative in g and in the bounds.
    rng = np.random.default_rng(21)
    G = random_delassus(rng, 5)
    g = np.array([0.05, -0.02, -1.0, 0.1, -0.3 if sticking else -3.0])
    mu, bounds = np.array([1.0]), np.array([2.0, 5.0 if sticking else 0.5])

    @jax.jit
    def solve(g, bounds):
        return solve_ncp(G, g, mu, bounds=bounds, solver=TIGHT)[0]

    impulse = np.asarray(solve(g, bounds))
    assert (abs(impulse[4]) < bounds[1] - 1e-3) == sticking
    derivative_g, derivative_bounds = jax.jacfwd(solve, argnums=(0, 1))(jnp.asarray(g), jnp.asarray(bounds))
    step = 1e-6
    for k in range(5):
        e = np.eye(5)[k] * step
        central = (np.asarray(solve(g + e, bounds)) - np.asarray(solve(g - e, bounds))) / (2 * step)
        np.testing.assert_allclose(derivative_g[:, k], central, atol=1e-5)
    for k in range(2):
        e = np.eye(2)[k] * step
        central = (np.asarray(solve(g, bounds + e)) - np.asarray(solve(g, bounds - e))) / (2 * step)
        np.testing.assert_allclose(derivative_bounds[:, k], central, atol=1e-5)
    if not sticking:  # at its bound, the row's impulse follows the bound
        assert abs(float(derivative_bounds[4, 1])) == pytest.approx(1.0)


def test_bad_bounds_are_refused_by_name():
    G, g = jnp.eye(4), jnp.zeros(4)
    mu = jnp.array([0.5])
    with pytest.raises(ValueError, match="bounds must be non-negative"):
        solve_ncp(G, g, mu, bounds=jnp.array([-1.0]))
    with pytest.raises(ValueError, match="bounds contains NaN"):
        solve_ncp(G, g, mu, bounds=jnp.array([jnp.nan]))
    with pytest.raises(ValueError, match=r"G must have shape \(3n \+ m, 3n \+ m\) with 3n \+ m = 5 for n = 1 contacts and m = 2"):
        solve_ncp(G, g, mu, bounds=jnp.array([1.0, 1.0]))
    with pytest.raises(ValueError, match=r"bounds must be None or have shape \(m,\)"):
        solve_ncp(G, g, mu, bounds=jnp.ones((1, 1)))
    with pytest.raises(ValueError, match=r"mu must have shape \(n,\) for n >= 1 contacts"):
        solve_ncp(jnp.zeros((0, 0)), jnp.zeros(0), jnp.zeros(0))
