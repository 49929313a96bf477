"""Tests of contact detection, the frictional contact NCP, its implicit derivative, and the
compliant models. References: closed forms on a point mass, Pinocchio's ADMM solver on the
same Delassus problems, and central finite differences."""

import functools
import pathlib

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rsmooth import RESULTS
from rsmooth.sim import _ncp
from rsmooth.sim._contact import contact_frame, corrected_free_velocity, sphere_halfspace_contacts
from rsmooth.sim._laws import LogBarrier, SpringDamper, log_barrier_force, spring_damper_force
from rsmooth.sim._ncp import (
    NCPSolver,
    cholesky_inverse,
    fixed_point_step_sizes,
    implicit_impulse_tangent,
    ncp_residuals,
    project_to_friction_cone,
    solve_ncp,
)

TIGHT = NCPSolver(tolerance=1e-13, max_iterations=20000)


def _solve_tight(G, g, mu):
    return solve_ncp(G, g, mu, solver=TIGHT)


def _solution(G, g, mu):
    return _solve_tight(G, g, mu)[0]


# Compiled once per number of contacts and shared by the tests: compilation, not solving,
# dominates their run time, so every batched solve goes through batches of BATCH problems.
BATCH = 8
_solve_tight_batch = jax.jit(jax.vmap(_solve_tight))
jacobians = jax.jit(
    lambda G, g, mu: (jax.jacfwd(_solution, argnums=(0, 1, 2))(G, g, mu),
                      jax.jacrev(_solution, argnums=(0, 1, 2))(G, g, mu))
)


def solve_tight_batch(G, g, mu):
    """Solves a stack of problems, in padded batches of BATCH."""
    size = G.shape[0]
    padding = -size % BATCH
    pad = lambda a: jnp.concatenate([a, jnp.repeat(a[:1], padding, axis=0)])
    G, g, mu = pad(G), pad(g), pad(mu)
    chunks = [_solve_tight_batch(G[i:i + BATCH], g[i:i + BATCH], mu[i:i + BATCH])
              for i in range(0, size + padding, BATCH)]
    return jax.tree.map(lambda *parts: jnp.concatenate(parts)[:size], *chunks)


def numpy_generator(key):
    """A NumPy generator seeded from a JAX key: problems are built on the host, in NumPy,
    to keep compilation out of the tests' run time."""
    return np.random.default_rng(np.asarray(jax.random.key_data(key)))


def random_problem(generator, n, extra_dofs=3):
    """G = J M^-1 Jᵀ with a random full-rank J (3n x nv) and SPD M, random g, mu in [0.1, 1]."""
    nv = 3 * n + extra_dofs
    J = generator.normal(size=(3 * n, nv))
    A = generator.normal(size=(nv, nv))
    M = A @ A.T / nv + 0.5 * np.eye(nv)
    G = J @ np.linalg.solve(M, J.T)
    G = 0.5 * (G + G.T)
    g = generator.normal(size=3 * n)
    mu = generator.uniform(0.1, 1.0, size=n)
    return G, g, mu


def problem_batch(getkey, n, batch):
    generator = numpy_generator(getkey())
    problems = [random_problem(generator, n) for _ in range(batch)]
    return tuple(jnp.asarray(np.stack(arrays)) for arrays in zip(*problems))


def check_ncp_numpy(G, g, mu, impulse, atol):
    """Independent check of cone feasibility, dual feasibility and complementarity."""
    G, g, mu, impulse = (np.asarray(a) for a in (G, g, mu, impulse))
    n = mu.shape[0]
    lam = impulse.reshape(n, 3)
    c = (G @ impulse + g).reshape(n, 3)
    c_tilde = c.copy()
    c_tilde[:, 2] += mu * np.linalg.norm(c[:, :2], axis=1)
    # Cone: ||lambda_T|| <= mu lambda_N; dual cone: mu ||c~_T|| <= c~_N.
    assert np.all(np.linalg.norm(lam[:, :2], axis=1) <= mu * lam[:, 2] + atol)
    assert np.all(mu * np.linalg.norm(c_tilde[:, :2], axis=1) <= c_tilde[:, 2] + atol)
    assert np.all(np.abs(np.sum(lam * c_tilde, axis=1)) <= atol)


# ----------------------------------------------------------------------------- detection


def test_contact_frame_is_a_rotation_with_the_normal_third(getkey):
    normals = jax.random.normal(getkey(), (64, 3))
    normals = jnp.concatenate([normals, jnp.array([[0.0, 0, 1], [0, 0, -1], [1, 0, 0]])])
    normals = normals / jnp.linalg.norm(normals, axis=-1, keepdims=True)
    frames = contact_frame(normals)
    identity = jnp.broadcast_to(jnp.eye(3), frames.shape)
    np.testing.assert_allclose(jnp.swapaxes(frames, -1, -2) @ frames, identity, atol=1e-12)
    np.testing.assert_allclose(jnp.linalg.det(frames), 1.0, atol=1e-12)
    np.testing.assert_allclose(frames[..., 2], normals, atol=0)
    np.testing.assert_allclose(contact_frame(jnp.array([0.0, 0.0, 1.0])), jnp.eye(3), atol=0)


def test_sphere_halfspace_contacts_distances_points_frames():
    centers = jnp.array([[0.0, 0.0, 0.1], [1.0, 2.0, -0.05], [0.3, 0.0, 0.5]])
    radii = jnp.array([0.02, 0.1, 0.0])  # the last is a point
    normals = jnp.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0]])  # floor z >= 0, wall x <= 0.5
    offsets = jnp.array([0.0, -0.5])
    contacts = jax.jit(sphere_halfspace_contacts)(centers, radii, normals, offsets)
    assert contacts.distance.shape == (3, 2)
    assert contacts.point.shape == (3, 2, 3)
    assert contacts.frame.shape == (3, 2, 3, 3)
    expected = np.array([[0.08, 0.48], [-0.15, -0.6], [0.5, 0.2]])
    np.testing.assert_allclose(contacts.distance, expected, atol=1e-12)
    np.testing.assert_allclose(contacts.point[1, 0], [1.0, 2.0, -0.15], atol=1e-12)
    np.testing.assert_allclose(contacts.point[2, 1], centers[2], atol=0)  # radius 0
    np.testing.assert_allclose(contacts.frame[:, 1, :, 2], jnp.tile(normals[1], (3, 1)))
    # The point on the plane lies on the plane.
    on_plane = contacts.point - contacts.distance[..., None] * normals[None]
    np.testing.assert_allclose(jnp.einsum("spk,pk->sp", on_plane, normals), 
                               jnp.broadcast_to(offsets, (3, 2)), atol=1e-12)


def test_sphere_halfspace_contacts_rejects_bad_input():
    with pytest.raises(ValueError, match="radii"):
        sphere_halfspace_contacts(jnp.zeros((2, 3)), jnp.array([0.1, -0.1]),
                                  jnp.array([[0.0, 0, 1]]), jnp.zeros(1))
    with pytest.raises(ValueError, match="normals"):
        sphere_halfspace_contacts(jnp.zeros((2, 3)), jnp.ones(2),
                                  jnp.array([[0.0, 0, 2]]), jnp.zeros(1))
    with pytest.raises(ValueError, match="centers"):
        sphere_halfspace_contacts(jnp.zeros((2, 2)), jnp.ones(2),
                                  jnp.array([[0.0, 0, 1]]), jnp.zeros(1))


def test_corrected_free_velocity():
    g = jnp.array([1.0, 2.0, -0.5, 0.0, 0.0, 0.0])
    # a gap beyond the skin closes to (1 - beta) s within the step; a penetration is pushed
    # out at beta / h
    corrected = corrected_free_velocity(g, jnp.array([0.01, -0.02]), 0.01, baumgarte=0.5, skin=1e-3)
    np.testing.assert_allclose(corrected, [1.0, 2.0, -0.5 + (0.01 - 0.5e-3) / 0.01, 0.0, 0.0, -1.0], atol=1e-12)
    # continuous, and linear through zero within the skin: the derivative at 0 is beta / h
    # from both sides, and distances of either sign within the skin (resting contacts, tilted
    # by rounding) get the targets of one rigid motion
    distance = jnp.array([-1e-9, 0.0, 1e-9, 1e-3 - 1e-15, 1e-3 + 1e-15])
    r = corrected_free_velocity(jnp.zeros(15), distance, 0.01, baumgarte=0.5, skin=1e-3)[2::3]
    np.testing.assert_allclose(r[:4], 0.5 * distance[:4] / 0.01, rtol=1e-12)
    np.testing.assert_allclose(r[4], r[3], atol=1e-9)
    slope = jax.vmap(jax.grad(lambda d: corrected_free_velocity(jnp.zeros(3), d[None], 0.01, baumgarte=0.5)[2]))(
        jnp.array([-1e-9, 0.0, 1e-9])
    )
    np.testing.assert_allclose(slope, 50.0, rtol=1e-12)


# ----------------------------------------------------------------------------- the NCP


def test_cone_projection_is_a_projection(getkey):
    v = 3.0 * jax.random.normal(getkey(), (200, 3))
    mu = jax.random.uniform(getkey(), (200,), minval=0.0, maxval=2.0)
    p = project_to_friction_cone(v, mu)
    np.testing.assert_allclose(project_to_friction_cone(p, mu), p, atol=1e-12)
    assert np.all(jnp.linalg.norm(p[:, :2], axis=1) <= mu * p[:, 2] + 1e-12)
    # Moreau: v - P_K(v) lies in the polar cone and is orthogonal to P_K(v).
    r = v - p
    np.testing.assert_allclose(jnp.sum(r * p, axis=1), 0.0, atol=1e-10)
    assert np.all(mu * r[:, 2] <= -jnp.linalg.norm(r[:, :2], axis=1) * mu**2 + 1e-10)


def test_frictionless_cone_is_the_nonnegative_normal_ray():
    # mu = 0: K = {(0, 0, a), a >= 0}; a vector with no tangential part and a negative normal
    # one projects to 0 (a random test never draws a zero tangential part)
    v = jnp.array([[0.0, 0.0, -1.5], [0.3, -0.2, -1.0], [0.3, 0.0, 2.0], [0.0, 0.0, 2.0]])
    np.testing.assert_array_equal(project_to_friction_cone(v, jnp.zeros(4)), [[0, 0, 0], [0, 0, 0], [0, 0, 2], [0, 0, 2]])
    # so a frictionless contact never pulls: two contacts, one closing and one opening
    # (contact rows without tangential coupling, as a joint limit's)
    G = jnp.diag(jnp.array([0.0, 0.0, 2.0, 0.0, 0.0, 2.0]))
    impulse, info = solve_ncp(G, jnp.array([0.0, 0.0, -1.0, 0.0, 0.0, 3.0]), jnp.zeros(2))
    assert bool(info.converged)
    np.testing.assert_allclose(impulse, [0, 0, 0.5, 0, 0, 0], atol=1e-12)


@pytest.mark.parametrize("n", [1, 2, 3, 4])
def test_random_problems_satisfy_the_ncp(getkey, n):
    G, g, mu = problem_batch(getkey, n, 8)
    impulse, info = solve_tight_batch(G, g, mu)
    assert bool(jnp.all(info.converged))
    assert jnp.max(info.primal_feasibility) <= TIGHT.tolerance
    assert jnp.max(info.dual_feasibility) <= TIGHT.tolerance
    assert jnp.max(info.complementarity) <= TIGHT.tolerance
    for i in range(G.shape[0]):
        check_ncp_numpy(G[i], g[i], mu[i], impulse[i], atol=1e-12)
    residuals = jax.jit(jax.vmap(ncp_residuals))(G, g, mu, impulse)
    np.testing.assert_allclose(
        jnp.stack(residuals),
        jnp.stack([info.primal_feasibility, info.dual_feasibility, info.complementarity]),
        atol=1e-14)
    # Some contacts of the batch are active, some are not.
    normal = impulse.reshape(-1, 3)[:, 2]
    assert jnp.any(normal > 0) and jnp.any(normal == 0)


def _pinocchio_solve(G, g, mu):
    """Pinocchio's own ADMM on the bare Delassus problem (dense operator, Coulomb cones).

    The solver takes constraint models only for their cones; a free-flyer model gives
    PointContactConstraintModel objects whose Coulomb cone is set by setFriction."""
    pin = pytest.importorskip("pinocchio")
    model = pin.Model()
    joint = model.addJoint(0, pin.JointModelFreeFlyer(), pin.SE3.Identity(), "free_flyer")
    constraint_models = pin.StdVec_ConstraintModel()
    constraint_datas = pin.StdVec_ConstraintData()
    for friction in np.asarray(mu):
        point_contact = pin.PointContactConstraintModel(model, joint)
        point_contact.setFriction(float(friction))
        constraint_model = pin.ConstraintModel(point_contact)
        constraint_models.append(constraint_model)
        constraint_datas.append(constraint_model.createData())
    settings = pin.ADMMSolverSettings()
    settings.max_iterations = 20000
    for name in ("absolute_feasibility_tol", "absolute_complementarity_tol",
                 "relative_feasibility_tol", "relative_complementarity_tol"):
        setattr(settings, name, 1e-13)
    assert settings.solve_ncp  # the NCP with the De Saxce correction, not the CCP
    result = pin.ADMMSolverResult()
    solver = pin.ADMMConstraintSolver(3 * len(mu))
    solver.solve(pin.DelassusOperatorDense(np.asarray(G)), np.asarray(g, dtype=float),
                 constraint_models, constraint_datas, settings, result)
    assert result.converged
    return result.retrieveConstraintImpulses()


@pytest.mark.parametrize("n", [1, 2, 3, 4])
def test_agrees_with_pinocchio_admm(getkey, n):
    G, g, mu = problem_batch(getkey, n, 8)
    impulse, info = solve_tight_batch(G, g, mu)
    assert bool(jnp.all(info.converged))
    for i in range(G.shape[0]):
        reference = _pinocchio_solve(G[i], g[i], mu[i])
        np.testing.assert_allclose(impulse[i], reference, atol=1e-7 * (1 + np.abs(reference).max()))


SPECTRAL = NCPSolver(tolerance=1e-13, max_iterations=20000, rho_update_power=0.05)
_solve_spectral_batch = jax.jit(jax.vmap(lambda G, g, mu: solve_ncp(G, g, mu, solver=SPECTRAL)))


@pytest.mark.parametrize("n", [2, 4])
def test_spectral_penalty_update_solves_the_same_problems(getkey, n):
    """The spectral rho update (Solo-12's default) reaches the tight tolerance on random
    problems (unique solutions: full-rank J) and agrees with Pinocchio's ADMM there."""
    G, g, mu = problem_batch(getkey, n, BATCH)
    impulse, info = _solve_spectral_batch(G, g, mu)
    assert bool(jnp.all(info.converged))
    for i in range(G.shape[0]):
        check_ncp_numpy(G[i], g[i], mu[i], impulse[i], atol=1e-12)
        reference = _pinocchio_solve(G[i], g[i], mu[i])
        np.testing.assert_allclose(impulse[i], reference, atol=1e-7 * (1 + np.abs(reference).max()))
    with pytest.raises(ValueError, match="rho_update_power"):
        NCPSolver(rho_update_power=0.0)


# ----------------------------------------------------------------------------- a point mass

MASS, STEP, GRAVITY, FRICTION = 2.0, 0.01, 9.81, 0.5


def point_mass_problem(force):
    """One velocity-level step of a point mass at rest on the floor: M = m I, J = I (floor
    frame = world frame), G = I / m, g = h (force / m - g0 e_z); dg/dforce = h / m I."""
    G = np.eye(3) / MASS
    g = STEP * (np.asarray(force) / MASS - GRAVITY * np.array([0.0, 0.0, 1.0]))
    return G, g, np.array([FRICTION])


def test_point_mass_rests_sticks_and_slides():
    limit = FRICTION * MASS * GRAVITY
    direction = np.array([0.6, -0.8, 0.0])
    forces = [np.zeros(3), 0.6 * limit * direction, 2.5 * limit * direction]
    G, g, mu = (jnp.asarray(np.stack(a)) for a in zip(*map(point_mass_problem, forces)))
    impulse, _ = solve_tight_batch(G, g, mu)
    velocity = jnp.einsum("bij,bj->bi", G, impulse) + g
    normal_impulse = MASS * STEP * GRAVITY
    # Resting: lambda_N = m h g0, no friction, no motion.
    np.testing.assert_allclose(impulse[0], [0.0, 0.0, normal_impulse], atol=1e-12)
    np.testing.assert_allclose(velocity[0], 0.0, atol=1e-12)
    # A push below mu m g0 sticks: friction cancels the push impulse, no tangential velocity.
    np.testing.assert_allclose(velocity[1], 0.0, atol=1e-12)
    np.testing.assert_allclose(impulse[1, :2], -STEP * forces[1][:2], atol=1e-12)
    np.testing.assert_allclose(impulse[1, 2], normal_impulse, atol=1e-12)
    # A push above it slides: friction impulse exactly mu lambda_N opposing the push, and
    # tangential velocity along the push, h (2.5 - 1) mu g0.
    np.testing.assert_allclose(impulse[2, 2], normal_impulse, rtol=1e-12)
    np.testing.assert_allclose(impulse[2, :2], -FRICTION * normal_impulse * direction[:2],
                               rtol=1e-10)
    np.testing.assert_allclose(velocity[2, 2], 0.0, atol=1e-12)
    np.testing.assert_allclose(velocity[2, :2], STEP * 1.5 * FRICTION * GRAVITY * direction[:2],
                               rtol=1e-10)


def test_point_mass_derivatives_are_zero_where_physics_says_so():
    limit = FRICTION * MASS * GRAVITY
    forces = [
        [0.0, 0.0, 0.3 * MASS * GRAVITY],  # small upward force: still resting
        [0.2 * limit, 0.0, 0.0],  # small push: sticks
        [3.0 * limit, 0.0, 0.0],  # large push: slides
    ]
    d_impulse, d_velocity = [], []
    for force in forces:
        G, g, mu = point_mass_problem(force)
        (_, forward, _), (_, reverse, _) = jacobians(G, g, mu)
        np.testing.assert_allclose(reverse, forward, atol=1e-14)
        # Chain rule through g = h (f / m - g0 e_z) and v+ = G lambda + g.
        d_impulse.append(forward * STEP / MASS)
        d_velocity.append((G @ forward + np.eye(3)) * STEP / MASS)
    # The upward force does not lift the mass: v_N after the step is 0 whatever the force,
    # so its derivative is exactly 0, and lambda_N decreases one for one with h f_up.
    assert abs(float(d_velocity[0][2, 2])) < 1e-14
    np.testing.assert_allclose(d_impulse[0][2, 2], -STEP, rtol=1e-10)
    # Sticking: the velocity responds to no small force at all.
    np.testing.assert_allclose(d_velocity[1], 0.0, atol=1e-14)
    # Sliding: friction is saturated, so d v_T / d f_T = h / m along the push, and v_N = 0.
    np.testing.assert_allclose(d_velocity[2][0, 0], STEP / MASS, rtol=1e-10)
    np.testing.assert_allclose(d_velocity[2][2], 0.0, atol=1e-14)


def test_box_on_four_corners_rank_deficient_delassus():
    # A box (6 DoF) on four corner contacts: G is 12 x 12 of rank 6 and the impulses are
    # not unique, but the motion is; its derivative is finite and physical.
    mass, inertia, step, friction = 1.0, 0.1, 0.01, 0.5
    corners = np.array([[x, y, -0.1] for x in (-0.1, 0.1) for y in (-0.1, 0.1)])
    cross = lambda p: np.array([[0, -p[2], p[1]], [p[2], 0, -p[0]], [-p[1], p[0], 0]])
    J = np.concatenate([np.hstack([np.eye(3), -cross(p)]) for p in corners])  # v + w x p
    M_inv = np.diag([1 / mass] * 3 + [1 / inertia] * 3)
    G = J @ M_inv @ J.T
    assert np.linalg.matrix_rank(G) == 6

    mu = jnp.full(4, friction)
    # Pushes that stick and slide; the step's free velocity is v_free = h (M^-1 f - g0 e_z).
    pushes = np.array([[0.5, 0.0, 0.0], [10.0, 0.0, 0.0]])
    free = step * np.concatenate([pushes / mass - [0.0, 0.0, GRAVITY], np.zeros((2, 3))], 1)
    impulse, info = solve_tight_batch(jnp.stack([G, G]), free @ J.T, jnp.stack([mu, mu]))
    assert bool(jnp.all(info.converged))
    velocity = free + impulse @ J @ M_inv
    # dv/df = (I + M^-1 Jᵀ dlambda/dg J) h M^-1 (force rows only).
    d_velocity = []
    for k in range(2):
        (_, d_impulse, _), _ = jacobians(G, J @ free[k], mu)
        d_velocity.append(((np.eye(6) + M_inv @ J.T @ d_impulse @ J) * step / mass)[:, :3])
    np.testing.assert_allclose(velocity[0], 0.0, atol=1e-10)
    np.testing.assert_allclose(d_velocity[0], 0.0, atol=1e-12)
    # Sliding: v_x = h (f / m - mu g0), so dv_x/df_x = h / m and dv_x/df_z = mu h / m.
    np.testing.assert_allclose(velocity[1, 0], step * (10.0 / mass - friction * GRAVITY),
                               rtol=1e-9)
    np.testing.assert_allclose(velocity[1, 1:], 0.0, atol=1e-9)
    np.testing.assert_allclose(d_velocity[1][0], [step / mass, 0.0, friction * step / mass],
                               atol=1e-10)
    # The sticking guess picks one of the non-unique sticking impulses; the motion is the same.
    guessed, guessed_info = solve_ncp(G, J @ free[0], mu, solver=NCPSolver(sticking_guess=True))
    assert bool(guessed_info.converged)
    np.testing.assert_allclose(free[0] + guessed @ J @ M_inv, 0.0, atol=1e-10)
    # With rank_deficient the guess is the minimum-norm sticking impulse (the pseudo-inverse),
    # which solves the problem without ADMM.
    pseudo, pseudo_info = solve_ncp(G, J @ free[0], mu, solver=NCPSolver(sticking_guess=True, rank_deficient=True))
    assert bool(pseudo_info.converged) and int(pseudo_info.iterations) == 0
    np.testing.assert_allclose(pseudo, -np.linalg.pinv(G) @ (J @ free[0]), atol=1e-12)
    np.testing.assert_allclose(free[0] + pseudo @ J @ M_inv, 0.0, atol=1e-12)
    # Where it fails (sliding), ADMM starts from zero, as without the guess: the same solve.
    slid, slid_info = solve_ncp(G, J @ free[1], mu, solver=NCPSolver(sticking_guess=True, rank_deficient=True))
    plain, plain_info = solve_ncp(G, J @ free[1], mu, solver=NCPSolver())
    assert int(slid_info.iterations) == int(plain_info.iterations) > 0
    np.testing.assert_array_equal(slid, plain)


# ----------------------------------------------------------------------------- derivatives


def mixed_mode_problem(key, modes):
    """A random G with a solution built by design: per contact 'stick' (lambda inside the
    cone, c = 0), 'slide' (lambda on the boundary opposing c_T, c_N = 0) or 'separate'
    (lambda = 0, c_N > 0); then g = c - G lambda. Every contact is strictly complementary,
    so small perturbations keep the modes. Draws with g_N >= 0 at an active contact are
    redrawn: there lambda_i = 0 would be a second solution (Coulomb friction on a coupled G
    need not have a unique solution)."""
    generator = numpy_generator(key)
    n = len(modes)
    while True:
        G, _, mu = random_problem(generator, n)
        angles = generator.uniform(0.0, 2 * np.pi, size=n)
        lam, c = np.zeros((n, 3)), np.zeros((n, 3))
        for i, mode in enumerate(modes):
            u = np.array([np.cos(angles[i]), np.sin(angles[i])])
            if mode == "stick":
                lam[i] = [*(0.4 * mu[i] * u), 1.0]
            elif mode == "slide":
                lam[i] = [*(-0.8 * mu[i] * u), 0.8]
                c[i] = [*(0.5 * u), 0.0]
            else:
                c[i] = [*(0.3 * u), 0.7]
        g = (c - (G @ lam.reshape(-1)).reshape(n, 3)).reshape(-1)
        active = np.array([mode != "separate" for mode in modes])
        if np.all(g.reshape(n, 3)[active, 2] < -0.1):
            return tuple(jnp.asarray(a) for a in (G, g, mu, lam.reshape(-1)))


MODES = [("stick",), ("slide",), ("separate",), ("stick", "slide", "separate")]


def test_implicit_tangent_of_many_columns_equals_the_refined_solves(getkey):
    """dlambda for a matrix of right-hand sides (more columns than unknowns: the step
    Jacobian's case) is formed as one operator (I + E + E^2) B; it equals the three refined
    solves applied column by column, at a solution where contacts stick, slide and separate
    (the separated contact's rows exactly zero)."""
    modes = ("stick", "slide", "separate")
    G, g, mu, solution = mixed_mode_problem(getkey(), modes)
    step_sizes = fixed_point_step_sizes(G, len(modes))
    rhs = jax.random.normal(getkey(), (3 * len(modes), 20), dtype=G.dtype)
    tangent = functools.partial(implicit_impulse_tangent, 1e-12, solution, G, g, mu, step_sizes)
    many = tangent(rhs)
    columns = jnp.stack([tangent(rhs[:, k]) for k in range(rhs.shape[1])], axis=1)
    assert float(jnp.max(jnp.abs(columns))) > 0.1
    np.testing.assert_allclose(many, columns, rtol=0, atol=1e-10 * float(jnp.max(jnp.abs(columns))))
    assert not np.any(np.asarray(many[6:]))


@pytest.mark.parametrize("lower", [True, False])
def test_cholesky_inverse_is_the_inverse(getkey, lower):
    a = jax.random.normal(getkey(), (7, 7), dtype=jnp.float64)
    spd = a @ a.T + 0.1 * jnp.eye(7)
    inverse = cholesky_inverse(jax.scipy.linalg.cho_factor(spd, lower=lower))
    np.testing.assert_allclose(inverse @ spd, np.eye(7), atol=1e-10)
    np.testing.assert_allclose(inverse, inverse.T, atol=1e-12 * float(jnp.max(jnp.abs(inverse))))


@pytest.mark.parametrize("modes", MODES, ids=["-".join(m) for m in MODES])
def test_implicit_derivatives_match_finite_differences(getkey, modes):
    G, g, mu, expected = mixed_mode_problem(getkey(), modes)
    n = len(modes)
    A = numpy_generator(getkey()).normal(size=(3 * n, 3 * n))
    direction_G = 0.1 * (A + A.T)
    step = 1e-6
    # The problem itself, then central differences, all in one batched solve: every
    # coordinate of g, every mu, and one symmetric direction in G (a Delassus matrix).
    perturbations = (
        [(np.zeros((3 * n, 3 * n)), np.zeros(3 * n), np.zeros(n))]
        + [(step * direction_G, np.zeros(3 * n), np.zeros(n))]
        + [(np.zeros((3 * n, 3 * n)), step * e, np.zeros(n)) for e in np.eye(3 * n)]
        + [(np.zeros((3 * n, 3 * n)), np.zeros(3 * n), step * e) for e in np.eye(n)]
    )
    dG, dg, dmu = (jnp.asarray(np.stack(p)) for p in zip(*perturbations))
    plus, info = solve_tight_batch(G[None] + dG, g[None] + dg, mu[None] + dmu)
    minus, _ = solve_tight_batch(G[None] - dG, g[None] - dg, mu[None] - dmu)
    assert bool(jnp.all(info.converged))
    impulse = plus[0]
    np.testing.assert_allclose(impulse, expected, atol=1e-10)
    finite_differences = (plus[1:] - minus[1:]) / (2 * step)

    forward, reverse = jacobians(G, g, mu)
    for jac_forward, jac_reverse in zip(forward, reverse):
        np.testing.assert_allclose(jac_forward, jac_reverse, atol=1e-12)
    jac_G, jac_g, jac_mu = forward

    implicit = jnp.concatenate([
        jnp.einsum("kij,ij->k", jac_G, direction_G)[None], jac_g.T, jac_mu.T
    ])
    np.testing.assert_allclose(implicit, finite_differences, atol=2e-6)

    for i, mode in enumerate(modes):
        rows = slice(3 * i, 3 * i + 3)
        if mode == "separate":  # no impulse whatever the perturbation: exactly zero
            for jac in forward + reverse:
                assert np.all(jac[rows] == 0)
        if mode == "stick":  # a bilateral constraint: c_i = (G lambda + g)_i stays 0
            dc_dg = G @ jac_g + jnp.eye(3 * n)
            np.testing.assert_allclose(dc_dg[rows], 0.0, atol=1e-12)
        if mode == "slide":  # c_N stays 0 and lambda stays on the cone boundary
            dc_dg = G @ jac_g + jnp.eye(3 * n)
            np.testing.assert_allclose(dc_dg[3 * i + 2], 0.0, atol=1e-12)
            lam = impulse[rows]
            boundary_normal = jnp.concatenate([lam[:2] / jnp.linalg.norm(lam[:2]), -mu[i:i + 1]])
            np.testing.assert_allclose(boundary_normal @ jac_g[rows], 0.0, atol=1e-12)


def test_sticking_guess_solves_sticking_problems_without_admm(getkey):
    """Where the contacts with closing free velocity stick and the others separate, the
    guess is the solution (0 iterations); elsewhere ADMM runs from the guess to the same
    solution as from zero, also inside a batch that mixes both."""
    while True:  # a separated contact whose free normal velocity opens (g_N > 0)
        G, g, mu, expected = mixed_mode_problem(getkey(), ("stick", "separate", "stick"))
        if g[5] > 0:
            break
    G_slide, g_slide, mu_slide, expected_slide = mixed_mode_problem(getkey(), ("stick", "slide", "separate"))
    batch = tuple(jnp.stack(pair) for pair in ((G, G_slide), (g, g_slide), (mu, mu_slide)))

    def solve(solver):
        return jax.jit(jax.vmap(lambda G, g, mu: solve_ncp(G, g, mu, solver=solver)))(*batch)

    guessed, guessed_info = solve(NCPSolver(tolerance=1e-12, max_iterations=20000, sticking_guess=True))
    plain, plain_info = solve(NCPSolver(tolerance=1e-12, max_iterations=20000))
    assert bool(jnp.all(guessed_info.converged))
    assert int(guessed_info.iterations[0]) == 0 and int(plain_info.iterations[0]) > 0
    assert float(guessed_info.rho[0]) == 0.0
    np.testing.assert_allclose(guessed[0], expected, atol=1e-12)
    assert int(guessed_info.iterations[1]) > 0
    np.testing.assert_allclose(guessed[1], expected_slide, atol=1e-10)
    np.testing.assert_allclose(plain[1], expected_slide, atol=1e-10)
    # The implicit derivative is that of the solution, however it was found.
    solution = lambda solver: jax.jacfwd(lambda g_: solve_ncp(G, g_, mu, solver=solver)[0])(g)
    np.testing.assert_allclose(solution(NCPSolver(sticking_guess=True)), solution(TIGHT), atol=1e-9)


POLISHED = NCPSolver(tolerance=1e-12, max_iterations=20000, sticking_guess=True, polish=True)
_solve_polished_batch = jax.jit(jax.vmap(lambda G, g, mu: solve_ncp(G, g, mu, solver=POLISHED)))


def test_polish_equations_have_the_closed_form_jacobian(getkey):
    """The polish's Newton Jacobian (closed form) equals forward-mode autodiff of its
    equations, for every mode and without friction, with the direction as an angle."""
    G, g, mu = problem_batch(getkey, 4, 1)
    G, g, mu = G[0], g[0], mu[0].at[1].set(0.0)  # contact 1 frictionless
    generator = numpy_generator(getkey())

    def equations(x, mode):
        direction = jnp.stack([jnp.cos(x[:, 1]), jnp.sin(x[:, 1])], axis=-1)
        return _ncp._mode_equations(x, direction, mode, G, g, mu)

    for _ in range(4):
        mode = jnp.asarray(generator.integers(0, 3, size=4))
        x = jnp.asarray(generator.normal(size=(4, 3)))
        autodiff = jax.jacfwd(lambda x_: equations(x_, mode)[1])(x).reshape(12, 12)
        np.testing.assert_allclose(equations(x, mode)[2], autodiff, atol=1e-12)


def test_polish_solves_without_admm(getkey):
    """The active-set Newton polish: constructed stick/slide/separate problems are solved to
    their known solution without an ADMM iteration; random problems of 2 and 4 contacts get
    valid solutions (independent check), most without ADMM, equal to ADMM's where the
    solution is unique for sure (the constructed ones; Coulomb friction need not have a
    unique solution even for one contact with an anisotropic G)."""
    patterns = [("stick", "slide", "separate"), ("slide", "slide"), ("slide", "stick", "slide", "separate")]
    for modes in patterns:
        G, g, mu, expected = mixed_mode_problem(getkey(), modes)
        impulse, info = solve_ncp(G, g, mu, solver=POLISHED)
        assert bool(info.converged) and int(info.iterations) == 0
        np.testing.assert_allclose(impulse, expected, atol=1e-10)
    # In float32 (tolerance 1e-5, as on a GPU) too, and Newton ends at float32's rounding.
    single = NCPSolver(tolerance=1e-5, sticking_guess=True, polish=True)
    impulse, info = solve_ncp(*(a.astype(jnp.float32) for a in (G, g, mu)), solver=single)
    assert impulse.dtype == jnp.float32 and bool(info.converged) and int(info.iterations) == 0
    np.testing.assert_allclose(impulse, expected, atol=1e-5)
    for n in (2, 4):
        G, g, mu = problem_batch(getkey, n, BATCH)
        impulse, info = _solve_polished_batch(G, g, mu)
        assert bool(jnp.all(info.converged))
        assert int(jnp.sum(info.iterations == 0)) >= BATCH - 1
        for i in range(BATCH):
            check_ncp_numpy(G[i], g[i], mu[i], impulse[i], atol=1e-10)
    with pytest.raises(ValueError, match="polish_rounds"):
        NCPSolver(polish_rounds=0)
    with pytest.raises(ValueError, match="polish_steps"):
        NCPSolver(polish_steps=1.5)


def test_the_least_squares_polish_solves_a_landing_foot_whose_equations_are_ill_conditioned():
    """dm_control's humanoid at rest, step 42 at zero torque: its two tilted feet land on the
    ends of their capsules, 8 contacts at gaps of 3 to 5 mm (the problem restricted to them;
    tests/sim/data). No all-sticking solution exists, ADMM stops at its cap in modes that are
    wrong, and the modes' equations there have a singular value about 1e-7 of the largest:
    the least-squares polish must take it (minimum-norm steps), where damped normal equations
    stalled at a dual residual of 6e-6."""
    data = np.load(pathlib.Path(__file__).parent / "data" / "humanoid_landing_feet.npz")
    G, g, mu = (jnp.asarray(data[name]) for name in ("G", "g", "mu"))
    solver = NCPSolver(sticking_guess=True, rank_deficient=True, polish=True, max_iterations=1000)
    impulse, info = solve_ncp(G, g, mu, solver=solver)
    assert bool(info.converged) and int(info.iterations) == solver.max_iterations  # after ADMM's cap
    check_ncp_numpy(G, g, mu, impulse, atol=1e-10)
    normal = np.asarray(impulse).reshape(8, 3)[:, 2]
    assert np.all(normal >= 0) and np.sum(normal) > 0.1  # the feet carry the landing


def test_the_contacts_acting_after_the_least_squares_polish_are_solved_alone():
    """dm_control's dog at rest, step 2 at zero torque, its 44 candidates closest to touching
    (tests/sim/data): four paws' contacts in pairs on a singular G. ADMM reaches its cap near
    impulses that no solution has (the pairs' normal impulses about equal, where in the solution
    one contact of each pair slides and carries less), and the least-squares polish returns
    there (dual residual 9e-7). The contacts acting there, solved alone (ADMM and the polish
    again, the others separated), give a solution of the whole problem."""
    data = np.load(pathlib.Path(__file__).parent / "data" / "dog_paws.npz")
    G, g, mu = (jnp.asarray(data[name]) for name in ("G", "g", "mu"))
    solver = NCPSolver(sticking_guess=True, rank_deficient=True, polish=True, max_iterations=1000)
    impulse, info = solve_ncp(G, g, mu, solver=solver)
    assert bool(info.converged) and int(info.iterations) > solver.max_iterations  # both ADMM runs
    check_ncp_numpy(G, g, mu, impulse, atol=1e-10)
    normal = np.asarray(impulse).reshape(-1, 3)[:, 2]
    acting = np.nonzero(normal > 0)[0]
    assert len(acting) >= 4 and np.sum(normal) > 0.05  # the paws carry the dog
    # not the equal split that ADMM reached: the pairs' normal impulses differ
    assert np.ptp(normal[acting]) > 1e-3


def test_batched_solves_do_not_depend_on_the_chunks(getkey):
    """Under vmap the problems that the start did not solve are solved in chunks
    (NCPSolver.chunk_size): each member's impulse, ADMM iteration count and convergence flag
    are those of solving it alone, whatever the chunk size, in a batch where some members need
    only the polish, some ADMM after it (one Newton step per round is too few where a contact
    slides) and some nothing (their start, a warm start at the solution, already solves)."""
    G, g, mu = problem_batch(getkey, 3, BATCH)
    exact = solve_tight_batch(G, g, mu)[0]
    warm = jnp.where((jnp.arange(BATCH) % 3 == 0)[:, None], exact, 0.0)
    weak = dict(tolerance=1e-11, max_iterations=20000, sticking_guess=True, polish=True, polish_steps=1)
    single = jax.jit(lambda G, g, mu, w: solve_ncp(G, g, mu, solver=NCPSolver(**weak), warm_start=w))
    singles = [single(G[i], g[i], mu[i], warm[i]) for i in range(BATCH)]
    alone = jax.tree.map(lambda *parts: jnp.stack(parts), *singles)
    assert 0 < int(jnp.sum(alone[1].iterations > 0)) < BATCH
    for chunk in (1, 3, BATCH):
        solver = NCPSolver(**weak, chunk_size=chunk)
        impulse, info = jax.jit(jax.vmap(lambda G, g, mu, w: solve_ncp(G, g, mu, solver=solver, warm_start=w)))(G, g, mu, warm)
        np.testing.assert_array_equal(info.converged, alone[1].converged)
        np.testing.assert_array_equal(info.iterations, alone[1].iterations)
        np.testing.assert_allclose(impulse, alone[0], atol=1e-12)
    with pytest.raises(ValueError, match="chunk_size"):
        NCPSolver(chunk_size=0)
    with pytest.raises(ValueError, match="'auto'"):
        NCPSolver(chunk_size="all")


def test_chunk_size_auto_follows_the_backend(monkeypatch):
    """chunk_size="auto" (the default): 4 problems per chunk on the CPU, the whole batch (no
    chunks) on a GPU or TPU; decided when the solve is traced, an int kept as it is."""
    from rsmooth import _xla

    assert NCPSolver().chunk_size == "auto"
    monkeypatch.setattr(_xla, "on_accelerator", lambda: False)
    assert NCPSolver()._chunk() == 4
    monkeypatch.setattr(_xla, "on_accelerator", lambda: True)
    assert NCPSolver()._chunk() is None
    assert NCPSolver(chunk_size=8)._chunk() == 8


def test_polish_falls_back_to_admm(getkey):
    """Where the polish fails (here one Newton step, one round: not enough to reach the
    tolerance where a contact slides), ADMM runs from the start as without the polish."""
    G, g, mu, expected = mixed_mode_problem(getkey(), ("stick", "slide", "separate"))
    weak = NCPSolver(tolerance=1e-12, max_iterations=20000, sticking_guess=True, polish=True, polish_rounds=1, polish_steps=1)
    impulse, info = solve_ncp(G, g, mu, solver=weak)
    assert bool(info.converged) and int(info.iterations) > 0
    np.testing.assert_allclose(impulse, expected, atol=1e-10)


def test_polish_after_capped_admm_solves_rank_deficient_box_problems():
    """A box on four corner contacts (G 12 x 12 of rank 6) pressed, tilted and spun: where
    the modes mix sliding and opening corners their equations are singular (Newton's own step
    is not finite) and ADMM's tail is slow. With ADMM capped at 20 iterations, the
    least-squares polish from ADMM's best iterate solves every problem (those the first polish
    did not solve report the 20 iterations), checked independently (with friction and several
    contacts the solution need not be unique, so it is not compared to another solver's);
    without the polish the same cap leaves every one unsolved."""
    corners = np.array([[x, y, -0.1] for x in (-0.1, 0.1) for y in (-0.1, 0.1)])
    cross = lambda p: np.array([[0, -p[2], p[1]], [p[2], 0, -p[0]], [-p[1], p[0], 0]])  # noqa: E731
    J = np.concatenate([np.hstack([np.eye(3), -cross(p)]) for p in corners])
    M_inv = np.diag([1.0, 1.0, 1.0, 10.0, 10.0, 10.0])
    G = jnp.asarray(J @ M_inv @ J.T)
    mu = jnp.full(4, 0.5)
    capped = NCPSolver(max_iterations=20, sticking_guess=True, rank_deficient=True, polish=True)
    unpolished = NCPSolver(max_iterations=20, sticking_guess=True, rank_deficient=True)
    rng = np.random.default_rng(1)
    after_admm = 0
    for _ in range(8):
        v = np.r_[rng.uniform(-0.3, 0.3, 2), -0.1, rng.uniform(-0.3, 0.3, 2), rng.uniform(-3.0, 3.0)]
        g = jnp.asarray(J @ v)
        impulse, info = solve_ncp(G, g, mu, solver=capped)
        assert bool(info.converged)
        after_admm += int(info.iterations) == 20
        check_ncp_numpy(G, g, mu, impulse, atol=1e-9)
        assert not bool(solve_ncp(G, g, mu, solver=unpolished)[1].converged)
    assert after_admm >= 4


# ----------------------------------------------------------------------------- jit, vmap, warm start


def test_eager_solves_of_one_shape_compile_once(getkey):
    """Outside any trace, solve_ncp is one compiled program per solver and shapes: a script's
    loop over problems compiles it at its first call only, and gets the solve it would get
    inside jit."""
    generator = numpy_generator(getkey())
    problems = [random_problem(generator, 5, extra_dofs=2) for _ in range(3)]  # shapes no other test solves
    solver = NCPSolver(max_iterations=3000)
    compiled = []

    def listener(event, seconds, **_):
        if event == "/jax/core/compile/backend_compile_duration":
            compiled.append(seconds)

    solve_ncp(*problems[0], solver=solver)
    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        solves = [solve_ncp(*problem, solver=solver) for problem in problems[1:]]
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)
    assert compiled == []
    jitted = jax.jit(lambda G, g, mu: solve_ncp(G, g, mu, solver=solver))
    for problem, (impulse, info) in zip(problems[1:], solves):
        assert bool(info.converged)
        check_ncp_numpy(*problem, impulse, atol=1e-9)
        np.testing.assert_allclose(impulse, jitted(*problem)[0], rtol=0, atol=1e-12)



def test_jit_vmap_and_warm_start(getkey):
    G, g, mu = problem_batch(getkey, 3, 8)
    solver = NCPSolver(tolerance=1e-10, max_iterations=5000)
    batched = jax.jit(jax.vmap(lambda G, g, mu, w: solve_ncp(G, g, mu, solver=solver, warm_start=w)))
    cold, cold_info = batched(G, g, mu, jnp.zeros_like(g))
    # With a zero warm start, the batched solves agree with the shared tight solves.
    np.testing.assert_allclose(cold, solve_tight_batch(G, g, mu)[0], atol=1e-8)
    # A nearby problem: warm starting from the previous solution needs fewer iterations.
    g_nearby = g + 1e-3 * jax.random.normal(getkey(), g.shape)
    _, nearby_cold = batched(G, g_nearby, mu, jnp.zeros_like(g))
    nearby_warm, nearby_warm_info = batched(G, g_nearby, mu, cold)
    assert bool(jnp.all(nearby_warm_info.converged))
    # ADMM converges linearly, so starting 1e-3 away instead of O(1) saves about a third.
    assert jnp.sum(nearby_warm_info.iterations) < 0.8 * jnp.sum(nearby_cold.iterations)
    # A warm start that already meets the tolerance needs no iteration at all.
    _, exact_info = batched(G, g, mu, cold)
    assert jnp.all(exact_info.iterations == 0)


def test_gradient_through_a_batch(getkey):
    G, g, mu = problem_batch(getkey, 2, BATCH)

    def loss(g):
        impulses, _ = jax.vmap(lambda G, g, mu: solve_ncp(G, g, mu, solver=TIGHT))(G, g, mu)
        return jnp.sum(impulses**2)

    gradient = jax.jit(jax.grad(loss))(g)
    direction = jax.random.normal(getkey(), g.shape)
    step = 1e-6
    plus, _ = solve_tight_batch(G, g + step * direction, mu)
    minus, _ = solve_tight_batch(G, g - step * direction, mu)
    fd = (jnp.sum(plus**2) - jnp.sum(minus**2)) / (2 * step)
    np.testing.assert_allclose(jnp.sum(gradient * direction), fd, rtol=1e-5, atol=1e-8)


# ----------------------------------------------------------------------------- bad input


def test_rejects_bad_input():
    G, g, mu = jnp.eye(6), -jnp.ones(6), jnp.array([0.5, 0.5])
    with pytest.raises(ValueError, match="G must have shape"):
        solve_ncp(jnp.eye(5), g, mu)
    with pytest.raises(ValueError, match="g must have shape"):
        solve_ncp(G, g[:5], mu)
    with pytest.raises(ValueError, match="mu must be non-negative"):
        solve_ncp(G, g, jnp.array([0.5, -0.1]))
    with pytest.raises(ValueError, match="g contains NaN"):
        solve_ncp(G, g.at[2].set(jnp.nan), mu)
    with pytest.raises(ValueError, match="G must be symmetric"):
        solve_ncp(G.at[0, 1].set(1.0), g, mu)
    with pytest.raises(ValueError, match="warm_start must have shape"):
        solve_ncp(G, g, mu, warm_start=jnp.zeros(3))
    with pytest.raises(ValueError, match="tolerance"):
        NCPSolver(tolerance=0.0)
    # Traced values are checked at run time (one compiled function for both).
    traced_solve = jax.jit(solve_ncp)
    with pytest.raises(Exception, match="g contains NaN"):
        jax.block_until_ready(traced_solve(G, g.at[2].set(jnp.nan), mu))
    with pytest.raises(Exception, match="mu must be non-negative"):
        jax.block_until_ready(traced_solve(G, g, jnp.array([0.5, -0.1])))


def test_throw_on_non_convergence():
    G, g, mu = jnp.eye(3), jnp.array([1.0, 0.0, -1.0]), jnp.array([0.5])
    _, info = solve_ncp(G, g, mu, solver=NCPSolver(max_iterations=1))
    assert not bool(info.converged) and int(info.iterations) == 1
    with pytest.raises(Exception, match="did not converge"):
        jax.block_until_ready(
            eqx.filter_jit(solve_ncp)(G, g, mu, solver=NCPSolver(max_iterations=1, throw=True))
        )


def test_result_of_batched_solves():
    """Under jit and vmap, NCPInfo.result is batched: a problem its start solves (a separating
    contact: zero impulse) is successful, one that ADMM capped at one iteration cannot solve
    reports max_iterations_reached, with its message; converged follows the result."""
    G = jnp.stack([jnp.eye(3)] * 2)
    g, mu = jnp.array([[0.0, 0.0, 1.0], [1.0, 0.0, -1.0]]), jnp.array([[0.5], [0.5]])
    capped = NCPSolver(max_iterations=1)
    _, info = jax.jit(jax.vmap(lambda G, g, mu: solve_ncp(G, g, mu, solver=capped)))(G, g, mu)
    np.testing.assert_array_equal(info.result == RESULTS.successful, [True, False])
    np.testing.assert_array_equal(info.result == RESULTS.max_iterations_reached, [False, True])
    np.testing.assert_array_equal(info.converged, [True, False])
    second = jax.tree.map(lambda leaf: leaf[1], info)
    assert "max_iterations" in RESULTS[second.result]


# ----------------------------------------------------------------------------- compliant models


def test_spring_damper_force():
    params = SpringDamper(stiffness=1e4, damping=50.0, friction=0.5, smoothing_velocity=1e-3)
    velocity = jnp.array([[0.3, -0.4, -0.1], [0.3, -0.4, 0.1], [0.0, 0.0, 0.0], [1.0, 0.0, 5.0]])
    distance = jnp.array([-1e-3, -1e-3, 0.01, -1e-3])
    force = jax.jit(spring_damper_force)(distance, velocity, params)
    # Penetrating and approaching: spring plus damper; separating: the damper subtracts.
    np.testing.assert_allclose(force[0, 2], 1e4 * 1e-3 + 50.0 * 0.1)
    np.testing.assert_allclose(force[1, 2], 1e4 * 1e-3 - 50.0 * 0.1)
    np.testing.assert_allclose(force[2], 0.0)  # separated
    np.testing.assert_allclose(force[3, 2], 0.0)  # the damper never pulls
    # Friction opposes the sliding velocity with magnitude just below mu f_N.
    direction = velocity[0, :2] / jnp.linalg.norm(velocity[0, :2])
    np.testing.assert_allclose(force[0, :2] / jnp.linalg.norm(force[0, :2]), -direction)
    assert 0.999 * 0.5 * force[0, 2] < jnp.linalg.norm(force[0, :2]) <= 0.5 * force[0, 2]
    np.testing.assert_allclose(params(distance, velocity), force)
    # Smooth in the tangential velocity: finite gradient at zero slip.
    slip_gradient = jax.jacfwd(lambda v: spring_damper_force(-1e-3, v, params))(jnp.zeros(3))
    assert np.all(np.isfinite(slip_gradient))


def test_log_barrier_force():
    params = LogBarrier(stiffness=1e-3, min_distance=1e-3, friction=0.4, smoothing_velocity=1e-2)
    velocity = jnp.array([0.2, 0.0, 0.0])
    # Force at a distance: kappa / phi.
    np.testing.assert_allclose(log_barrier_force(0.05, velocity, params)[2], 1e-3 / 0.05)
    # Finite and C^1 through the switch at min_distance and into penetration.
    normal_force = lambda d: log_barrier_force(d, velocity, params)[2]
    below, above = 1e-3 * (1 - 1e-9), 1e-3 * (1 + 1e-9)
    np.testing.assert_allclose(normal_force(below), normal_force(above), rtol=1e-8)
    np.testing.assert_allclose(jax.grad(normal_force)(below), jax.grad(normal_force)(above),
                               rtol=1e-6)
    assert np.isfinite(normal_force(-0.01)) and normal_force(-0.01) > normal_force(0.0) > 0
    distances = jnp.linspace(-0.01, 0.1, 50)
    forces = jax.vmap(normal_force)(distances)
    assert np.all(np.diff(forces) < 0)  # repulsion decreases with distance
    # Friction opposes the slip.
    assert log_barrier_force(0.05, velocity, params)[0] < 0
    # The lookahead acts on the predicted gap phi + h v_N.
    ahead = LogBarrier(stiffness=1e-3, lookahead=0.1)
    np.testing.assert_allclose(log_barrier_force(0.05, jnp.array([0.0, 0.0, -0.2]), ahead)[2],
                               1e-3 / 0.03)


def test_contact_law_parameters_out_of_range_are_refused_by_name():
    with pytest.raises(ValueError, match="SpringDamper.stiffness must be finite and positive"):
        SpringDamper(stiffness=0.0, damping=1.0, friction=0.5)
    with pytest.raises(ValueError, match="SpringDamper.damping"):
        SpringDamper(stiffness=1e3, damping=-1.0, friction=0.5)
    with pytest.raises(ValueError, match="LogBarrier.min_distance"):
        LogBarrier(stiffness=1e-3, min_distance=0.0)
    with pytest.raises(ValueError, match="LogBarrier.friction"):
        LogBarrier(stiffness=1e-3, friction=float("nan"))
    # traced parameters (a stiffness swept under vmap) are left to the caller
    stiffness = jax.vmap(lambda k: SpringDamper(stiffness=k, damping=0.0, friction=0.0).stiffness)(jnp.array([1e2, 1e3]))
    np.testing.assert_array_equal(stiffness, [1e2, 1e3])


def test_the_factored_sticking_guess_equals_the_pseudo_inverse_of_g():
    # A box on four corner contacts (G 12 x 12 of rank 6) held, pushed and tilted by random
    # free velocities: the rank-deficient sticking guess from the 6 x 6 X Xᵀ (G = Xᵀ X) gives
    # the impulse of the 12 x 12 eigendecomposition, where it solves the problem and where not.
    corners = np.array([[x, y, -0.1] for x in (-0.1, 0.1) for y in (-0.1, 0.1)])
    cross = lambda p: np.array([[0, -p[2], p[1]], [p[2], 0, -p[0]], [-p[1], p[0], 0]])  # noqa: E731
    J = np.concatenate([np.hstack([np.eye(3), -cross(p)]) for p in corners])
    X = np.diag(np.sqrt([1.0, 1.0, 1.0, 10.0, 10.0, 10.0])) @ J.T  # L^-1 Jᵀ for M = diag(1, 1, 1, .1, .1, .1)
    G = X.T @ X
    solver = NCPSolver(sticking_guess=True, rank_deficient=True)
    mu = jnp.full(4, 0.8)
    rng = np.random.default_rng(0)
    solved = 0
    for k in range(8):
        spin = 0.3 * rng.normal(size=3) if k % 2 else np.zeros(3)  # tilting opens corners; else all press
        v = np.r_[0.02 * rng.normal(size=2), -0.1 + 0.02 * rng.normal(), spin]
        g = jnp.asarray(J @ v)
        plain, plain_info = solver.start(jnp.asarray(G), g, mu, None)
        factored, factored_info = solver.start(jnp.asarray(G), g, mu, None, factor=jnp.asarray(X))
        np.testing.assert_allclose(np.asarray(factored), np.asarray(plain), rtol=0, atol=1e-12)
        assert bool(factored_info.converged) == bool(plain_info.converged)
        solved += bool(plain_info.converged)
        impulse, info = solve_ncp(jnp.asarray(G), g, mu, solver=solver, delassus_factor=jnp.asarray(X))
        reference, reference_info = solve_ncp(jnp.asarray(G), g, mu, solver=solver)
        np.testing.assert_allclose(np.asarray(impulse), np.asarray(reference), rtol=0, atol=1e-9)
    assert 0 < solved < 8  # both cases met
    with pytest.raises(ValueError, match=r"delassus_factor must have shape \(d, 12\)"):
        solve_ncp(jnp.asarray(G), g, mu, solver=solver, delassus_factor=jnp.asarray(X[:, :6]))


@pytest.mark.parametrize(
    "solver",
    [NCPSolver(sticking_guess=True, rank_deficient=True), NCPSolver(sticking_guess=True, polish=True), NCPSolver()],
    ids=["rank_deficient", "polish", "plain"],
)
def test_with_a_factor_the_solve_reads_g_only_through_it(solver):
    # A box on four corners pressed, pushed and tilted (as above): given X, the jitted solve
    # reads G = Xᵀ X only through X (the start's products, and G formed from X where ADMM or
    # the polish runs), so a G that is not Xᵀ X changes nothing; a NaN in X is caught.
    corners = np.array([[x, y, -0.1] for x in (-0.1, 0.1) for y in (-0.1, 0.1)])
    cross = lambda p: np.array([[0, -p[2], p[1]], [p[2], 0, -p[0]], [-p[1], p[0], 0]])  # noqa: E731
    J = np.concatenate([np.hstack([np.eye(3), -cross(p)]) for p in corners])
    X = jnp.asarray(np.diag(np.sqrt([1.0, 1.0, 1.0, 10.0, 10.0, 10.0])) @ J.T)
    G = X.T @ X
    mu = jnp.full(4, 0.8)
    factored = jax.jit(lambda G_, g_, X_: solve_ncp(G_, g_, mu, solver=solver, delassus_factor=X_))
    reference = jax.jit(lambda g_: solve_ncp(G, g_, mu, solver=solver))
    rng = np.random.default_rng(1)
    started = []
    for k in range(6):
        spin = 0.3 * rng.normal(size=3) if k % 2 else np.zeros(3)
        g = jnp.asarray(J @ np.r_[0.02 * rng.normal(size=2), -0.1 + 0.02 * rng.normal(), spin])
        impulse, info = factored(3.0 * G + jnp.eye(12), g, X)  # not Xᵀ X
        expected, expected_info = reference(g)
        np.testing.assert_allclose(np.asarray(impulse), np.asarray(expected), rtol=0, atol=1e-9)
        assert int(info.result._value) == int(expected_info.result._value) == int(RESULTS.successful._value)
        started.append(bool(solver.start(G, g, mu, None, factor=X)[1].converged))
    assert not all(started)  # the polish or ADMM ran on some (G formed from X there)
    with pytest.raises(Exception, match="delassus_factor contains NaN"):
        jax.block_until_ready(factored(G, g, X.at[0, 0].set(jnp.nan)))


def test_the_sticking_guess_solves_a_well_conditioned_gram_by_cholesky_and_a_singular_one_by_eigh(monkeypatch):
    # (A^+)² b against the eigendecomposition's pseudo-inverse (eigenvalues below 1e-9 of the
    # largest dropped): a well-conditioned A (its eigendecomposition never runs), a singular
    # one (b in its range), one with zero rows and columns (dofs no active contact touches),
    # and a batch mixing them (the eigendecomposition runs for the batch, each member keeps
    # its own answer); from the size where the factorization is tried first.
    calls = []
    eigh = jnp.linalg.eigh

    def counted(a, *args, **kwargs):
        jax.debug.callback(lambda: calls.append(1))
        return eigh(a, *args, **kwargs)

    monkeypatch.setattr(jnp.linalg, "eigh", counted)
    rng = np.random.default_rng(0)

    def reference(A, b):
        w, V = np.linalg.eigh(A)
        inverse = np.where(w > 1e-9 * w[-1], 1.0 / np.where(w > 1e-9 * w[-1], w, 1.0), 0.0)
        return V @ (inverse**2 * (V.T @ b))

    d = _ncp._CHOLESKY_MIN_SIZE
    X = rng.normal(size=(d, 4 * d))
    well = X @ X.T  # rank d
    Y = rng.normal(size=(d, d // 2))
    singular = Y @ Y.T  # rank d / 2
    Z = np.vstack([rng.normal(size=(d // 2, 4 * d)), np.zeros((d - d // 2, 4 * d))])
    zero_rows = Z @ Z.T  # a body without active contacts: rows d / 2 to d exactly zero
    cases = [(well, X @ rng.normal(size=4 * d)), (singular, Y @ rng.normal(size=d // 2)), (zero_rows, Z @ rng.normal(size=4 * d))]
    solve = jax.jit(_ncp._squared_pseudo_inverse_times)
    for k, (A, b) in enumerate(cases):
        calls.clear()
        got = np.asarray(solve(jnp.asarray(A), jnp.asarray(b)))
        expected = reference(A, b)
        np.testing.assert_allclose(got, expected, rtol=0, atol=1e-10 * np.max(np.abs(expected)))
        assert len(calls) == (k == 1)  # only the singular one needs the eigendecomposition
    calls.clear()
    batch = jax.jit(jax.vmap(_ncp._squared_pseudo_inverse_times))(
        jnp.asarray(np.stack([A for A, _ in cases])), jnp.asarray(np.stack([b for _, b in cases])))
    for (A, b), got in zip(cases, np.asarray(batch)):
        np.testing.assert_allclose(got, reference(A, b), rtol=0, atol=1e-10 * np.max(np.abs(reference(A, b))))
    calls.clear()
    jax.block_until_ready(jax.jit(jax.vmap(_ncp._squared_pseudo_inverse_times))(
        jnp.asarray(np.stack([well, zero_rows])), jnp.asarray(np.stack([cases[0][1], cases[2][1]]))))
    assert not calls  # a batch of well-conditioned members never runs it


def test_admm_on_the_scaled_problem_solves_contacts_of_very_different_masses_in_few_iterations():
    # Three point masses (1 kg, 1 g, 30 kg) each on one contact: G = diag(1 / m), and each
    # contact's impulse has a closed form: the normal one stops the approach, lambda_N = -m g_N;
    # the tangential one stops the slip, -m g_T, where that is inside the cone, else mu lambda_N
    # against the slip. One penalty for rows whose diagonals span 1 / 30 to 1000 makes ADMM
    # crawl; on the problem scaled to an equal diagonal (NCPSolver.scaling) it does not.
    masses = np.array([1.0, 1e-3, 30.0])
    G = jnp.asarray(np.diag(np.repeat(1.0 / masses, 3)))
    g = np.array([0.5, 0.0, -1.0, 0.2, 0.1, -0.3, -0.05, 0.02, -0.4])
    mu = np.array([0.3, 0.8, 1.0])
    expected = []
    for i, m in enumerate(masses):
        normal = -m * g[3 * i + 2]
        stick = -m * g[3 * i : 3 * i + 2]
        slide = mu[i] * normal * stick / np.linalg.norm(stick)
        expected += list(stick if np.linalg.norm(stick) <= mu[i] * normal else slide) + [normal]
    assert np.linalg.norm(expected[:2]) == pytest.approx(mu[0] * expected[2])  # the first slides, the others stick
    solves = {
        scaling: solve_ncp(G, jnp.asarray(g), jnp.asarray(mu), solver=NCPSolver(max_iterations=5000, scaling=scaling))
        for scaling in (True, False)
    }
    for impulse, info in solves.values():
        assert bool(info.converged)
        np.testing.assert_allclose(impulse, expected, rtol=0, atol=1e-9)
    scaled, plain = (int(solves[scaling][1].iterations) for scaling in (True, False))
    assert scaled <= 50 and plain > 10 * scaled  # (measured: 19 against 1034)
