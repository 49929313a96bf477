"""Randomized DDP: reduces to DDP without noise, lifts the cube DDP cannot, ends on the true problem."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from control_systems import cube_lift, linear_quadratic, pendulum_swing_up, riccati

from rsmooth import control

CUBE_SOLVER = control.RDDP(eps=1.0, num_samples=16, estimator="first", state_noise_scale=0.01, control_noise_scale=10.0)


def test_smoothed_jacobians_of_linear_dynamics(getkey):
    problem, (A, B, *_) = linear_quadratic(nx=3, nu=2, horizon=4)
    xs = jax.random.normal(getkey(), (5, 3))
    us = jax.random.normal(getkey(), (4, 2))
    jacobians = jax.jit(
        control.smoothed_dynamics_jacobians,
        static_argnames=("num_samples", "estimator", "state_noise_scale", "control_noise_scale", "batch_size"),
    )
    options = dict(eps=0.3, state_noise_scale=(2.0, 1.0, 1.5), control_noise_scale=0.5)
    # The mean of sampled Jacobians of a linear map is exact, whatever the noise scales (here
    # with all nodes at once; R-DDP defaults to one node at a time).
    fx, fu = jacobians(problem, getkey(), xs, us, num_samples=3, estimator="first", batch_size=None, **options)
    np.testing.assert_allclose(fx, np.broadcast_to(A, fx.shape), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(fu, np.broadcast_to(B, fu.shape), rtol=1e-12, atol=1e-12)
    # The score-function estimate is unbiased: close with many samples.
    fx, fu = jacobians(problem, getkey(), xs, us, num_samples=20000, estimator="zeroth", **options)
    np.testing.assert_allclose(fx, np.broadcast_to(A, fx.shape), atol=0.05)
    np.testing.assert_allclose(fu, np.broadcast_to(B, fu.shape), atol=0.05)


def test_without_noise_rddp_is_ddp_iterate_for_iterate(getkey):
    problem = pendulum_swing_up()
    reference = control.ddp(problem)
    solution = control.rddp(problem, getkey(), solver=control.RDDP(eps=0.0))
    assert solution.iterations == reference.iterations and solution.converged
    # The same program runs (`solve` runs R-DDP's eps = 0 iterations by DDP's step): equal to
    # the last bit.
    for name in ("cost", "step_size", "regularization", "expected_improvement"):
        np.testing.assert_array_equal(solution.stats[name], reference.stats[name])
    np.testing.assert_array_equal(solution.us, reference.us)
    np.testing.assert_array_equal(solution.gains, reference.gains)
    assert np.all(np.asarray(solution.stats["noise"]) == 0.0)
    # The DDP R-DDP runs at eps = 0 has its DDP options, and only those.
    assert control.RDDP(eps=0.3, num_samples=4, max_iterations=7, reg_init=1e-4).as_ddp() == control.DDP(max_iterations=7, reg_init=1e-4)
    assert type(control.RDDP().as_ddp()) is control.DDP


def test_cube_lift_ddp_stays_put_and_rddp_lifts_it():
    problem = cube_lift()
    stuck = control.ddp(problem)
    # Below the weight the floor takes the force: d x_next / d u = 0, DDP sees no way up.
    assert stuck.converged and stuck.iterations == 1
    assert float(jnp.max(jnp.abs(stuck.xs))) == 0.0 and float(jnp.max(jnp.abs(stuck.us))) == 0.0

    seen = []
    key = jax.random.key(0)
    solution = control.rddp(problem, key, solver=CUBE_SOLVER, callback=seen.append)
    assert solution.converged
    assert abs(float(solution.xs[-1, 0]) - 0.5) < 0.1
    assert float(solution.cost) < 0.1 * float(stuck.cost)
    noise = np.asarray(solution.stats["noise"])
    assert noise[0] == 1.0 and noise[-1] == 0.0 and np.all(np.diff(noise) <= 0.0)
    # The true cost never increases: the line search runs on the true dynamics.
    assert np.all(np.diff(np.asarray(solution.stats["cost"])) <= 0.0)
    # The final solution is a stationary point of the TRUE problem: converged with eps = 0.
    assert float(solution.stats["expected_improvement"][-1]) < CUBE_SOLVER.th_stop
    assert [info["noise"] for info in seen] == list(noise[1:])
    # Reproducible bit for bit from the key.
    again = control.rddp(problem, key, solver=CUBE_SOLVER)
    np.testing.assert_array_equal(again.us, solution.us)
    # `rddp` runs the eps > 0 iterations by a program without the exact Jacobians and the
    # eps = 0 ones by DDP's: the same iterates as R-DDP's own step (which picks by lax.cond),
    # up to rounding (the programs differ, so do XLA's fusions).
    solver = CUBE_SOLVER
    state = solver.init(problem, jnp.zeros((problem.horizon, problem.nu)), key)
    step = jax.jit(solver.step)
    while not bool(solver.terminate(state)):
        state = step(problem, state)
    assert int(state.iteration) == solution.iterations
    np.testing.assert_allclose(state.trajectory.us, solution.us, rtol=1e-12, atol=1e-20)
    np.testing.assert_array_equal(state.history["noise"][: solution.iterations + 1], noise)


def test_alpha_order_geometric_schedule_ends_at_the_lqr_solution(getkey):
    problem, (A, B, Q, R, Qf) = linear_quadratic()
    _, _, us, cost = riccati(A, B, Q, R, Qf, np.asarray(problem.x0), problem.horizon)
    solver = control.RDDP(eps=0.5, num_samples=8, estimator="alpha", schedule="geometric", decay=0.25, eps_min=1e-2)
    solution = control.rddp(problem, getkey(), solver=solver)
    noise = np.asarray(solution.stats["noise"])
    np.testing.assert_allclose(noise[:4], [0.5, 0.125, 0.03125, 0.0])
    assert solution.converged
    np.testing.assert_allclose(solution.cost, cost, rtol=1e-8)
    np.testing.assert_allclose(solution.us, us, rtol=1e-4, atol=1e-6)


def test_bad_input_raises_named_errors():
    with pytest.raises(ValueError, match="eps"):
        control.RDDP(eps=-0.1)
    with pytest.raises(ValueError, match="num_samples"):
        control.RDDP(num_samples=0)
    with pytest.raises(ValueError, match="num_samples"):
        control.RDDP(num_samples=2, estimator="alpha")
    with pytest.raises(ValueError, match="estimator"):
        control.RDDP(estimator="second")
    with pytest.raises(ValueError, match="schedule"):
        control.RDDP(schedule="cosine")
    with pytest.raises(ValueError, match="control_noise_scale"):
        control.RDDP(control_noise_scale=-1.0)
    with pytest.raises(ValueError, match="approximation"):
        control.RDDP(approximation="full")
    with pytest.raises(ValueError, match="sample_node_batch_size"):
        control.RDDP(sample_node_batch_size=0)
    with pytest.raises(ValueError, match="sample_node_batch_size"):
        control.RDDP(sample_node_batch_size="all")
    problem = cube_lift()
    with pytest.raises(TypeError, match="key"):
        control.rddp(problem, 0)
    with pytest.raises(ValueError, match="us_init"):
        control.rddp(problem, jax.random.key(0), jnp.zeros((3, 1)))
    with pytest.raises(ValueError, match="state_noise_scale"):
        control.rddp(problem, jax.random.key(0), solver=control.RDDP(state_noise_scale=(1.0, 1.0, 1.0)))
    with pytest.raises(TypeError, match="rddp"):
        control.ddp(problem, solver=control.RDDP())


def test_solvers_use_the_dynamics_own_jacobians(getkey):
    """A dynamics with ``step_and_jacobians`` (the simulator's fast implicit Jacobians) is
    differentiated by it, not by autodiff, in DDP and in R-DDP's first-order estimate."""
    import equinox as eqx
    from control_systems import Pendulum

    from rsmooth.control._ddp import dynamics_jacobians

    class ScaledJacobians(Pendulum):
        """The pendulum whose own Jacobians are autodiff's times ``factor``."""

        factor: float = 1.0

        def step_and_jacobians(self, x, u):
            fx, fu = jax.jacfwd(self.step, argnums=(0, 1))(x, u)
            return self.step(x, u), self.factor * fx, self.factor * fu

    base = pendulum_swing_up(horizon=6)
    xs = jax.random.normal(getkey(), (7, 2))
    us = jax.random.normal(getkey(), (6, 1))
    key = getkey()
    results = {}
    for factor in (1.0, 2.0):
        problem = eqx.tree_at(lambda p: p.dynamics, base, ScaledJacobians(factor=factor))
        results[factor] = (
            dynamics_jacobians(problem, xs, us),
            control.smoothed_dynamics_jacobians(problem, key, xs, us, eps=0.1, num_samples=4),
        )
    reference = (
        dynamics_jacobians(base, xs, us),
        control.smoothed_dynamics_jacobians(base, key, xs, us, eps=0.1, num_samples=4),
    )
    for which in range(2):  # exact, smoothed
        for ours, theirs in zip(results[1.0][which], reference[which]):
            np.testing.assert_allclose(ours, theirs, rtol=1e-12, atol=1e-14)
        for ours, theirs in zip(results[2.0][which], reference[which]):
            np.testing.assert_allclose(ours, 2.0 * theirs, rtol=1e-12, atol=1e-14)


def test_perturbed_states_are_projected_back_by_the_dynamics_project_state(getkey):
    """Noise added in R^nx may leave the state's manifold (a unit quaternion): R-DDP steps from
    ``dynamics.project_state`` of every perturbed state, for every estimator."""
    import equinox as eqx

    class Doubling(eqx.Module):
        """x_next = 2 x + u on R^2 (u broadcast): as a step that does not normalize its input."""

        nx: int = eqx.field(static=True, default=2)
        nu: int = eqx.field(static=True, default=1)

        def step(self, x, u):
            return 2.0 * x + u

    class OnTheCircle(Doubling):
        def project_state(self, x):
            return x / jnp.linalg.norm(x)

    x = jnp.array([0.6, 0.8])
    xs, us = jnp.stack([x, x]), jnp.zeros((1, 1))
    key = getkey()

    def problem(dynamics):
        return control.ShootingProblem(dynamics, lambda x, u: jnp.sum(u**2), lambda x: jnp.sum(x**2), x, 1)

    def jacobian(dynamics, estimator, eps, num_samples):
        fx, _ = control.smoothed_dynamics_jacobians(problem(dynamics), key, xs, us, eps=eps, num_samples=num_samples,
                                                     estimator=estimator)
        return np.asarray(fx[0])

    # Tiny noise: the first-order estimate is the step's Jacobian through the projection,
    # 2 (I - x x^T) at a unit x (the radial direction does nothing), not 2 I.
    tangent = 2.0 * (np.eye(2) - np.outer(x, x))
    np.testing.assert_allclose(jacobian(OnTheCircle(), "first", 1e-7, 4), tangent, atol=1e-5)
    np.testing.assert_allclose(jacobian(Doubling(), "first", 1e-7, 4), 2.0 * np.eye(2), atol=1e-12)
    # Large noise: zeroth and first order estimate the Jacobian of the same smoothed function
    # (the noise's radial part averages out of both); 5 standard errors of the zeroth-order
    # estimate (about 0.02 per entry at M = 20000).
    first = jacobian(OnTheCircle(), "first", 0.3, 20000)
    zeroth = jacobian(OnTheCircle(), "zeroth", 0.3, 20000)
    np.testing.assert_allclose(zeroth, first, atol=0.1)
    # Along x, the projected step barely changes (the smoothed direction changes with |x| only
    # through the relative noise); without the projection it doubles.
    assert abs(x @ first @ x) < 0.3 and x @ jacobian(Doubling(), "zeroth", 0.3, 20000) @ x > 1.8


def test_sample_node_batch_size_auto_follows_the_backend(monkeypatch):
    """sample_node_batch_size="auto" (the default): one node's samples at a time on the CPU, all
    nodes at once on a GPU or TPU; None and ints kept as they are."""
    from rsmooth import _xla

    assert control.RDDP().sample_node_batch_size == "auto"
    monkeypatch.setattr(_xla, "on_accelerator", lambda: False)
    assert control.RDDP()._sample_node_batch() == 1
    assert control.RDDP(sample_node_batch_size=None)._sample_node_batch() is None
    monkeypatch.setattr(_xla, "on_accelerator", lambda: True)
    assert control.RDDP()._sample_node_batch() is None
    assert control.RDDP(sample_node_batch_size=5)._sample_node_batch() == 5


def test_reheating_raises_the_noise_where_the_adaptive_rule_gives_up():
    """The cube lift with less noise on the force: the samples barely lift the cube, the
    adaptive rule reads the first stall as convergence and decays the noise to 0 (DDP's
    answer: the cube stays down); the reheating rule sees that more noise lowers the cost
    (a negative response) and doubles it, and the lift succeeds."""
    problem = cube_lift()
    options = dict(eps=1.0, num_samples=16, estimator="first", state_noise_scale=0.01, control_noise_scale=4.0)
    key = jax.random.key(0)
    adaptive = control.rddp(problem, key, solver=control.RDDP(**options, schedule="adaptive"))
    assert float(jnp.max(jnp.abs(adaptive.xs[:, 0]))) == 0.0
    assert np.all(np.diff(np.asarray(adaptive.stats["noise"])) <= 0.0)
    reheated = control.rddp(problem, key, solver=control.RDDP(**options, schedule="reheating"))
    noise = np.asarray(reheated.stats["noise"])
    assert noise[1] == 2.0 and noise[-1] == 0.0 and reheated.converged
    assert np.sum(np.diff(noise) > 0) <= control.RDDP().max_raises
    assert abs(float(reheated.xs[-1, 0]) - 0.5) < 0.1


def test_noise_response_is_the_derivative_of_the_cost_along_the_noise_effect(getkey):
    """`noise_response` is the adjoint form of d J / d delta for the rollout
    x_{t+1} = f(x_t, u_t) + delta e_t: compared with automatic differentiation of that
    rollout, on a nonlinear system."""
    from rsmooth.control._ddp import _cost_derivatives, _Derivatives
    from rsmooth.control._rddp import noise_response

    problem = pendulum_swing_up()
    us = 0.3 * jax.random.normal(getkey(), (problem.horizon, problem.nu))
    effect = jax.random.normal(getkey(), (problem.horizon, problem.nx))

    def cost(delta):
        def node(x, inputs):
            u, e = inputs
            return problem.dynamics.step(x, u) + delta * e, x
        x_last, xs = jax.lax.scan(node, problem.x0, (us, effect))
        return problem.cost(jnp.concatenate([xs, x_last[None]]), us)

    @jax.jit
    def adjoint_form(us, effect):
        xs = problem.rollout(us)
        fx, fu = jax.vmap(jax.jacfwd(problem.dynamics.step, argnums=(0, 1)))(xs[:-1], us)
        return noise_response(_Derivatives(fx, fu, *_cost_derivatives(problem, xs, us), effect))

    np.testing.assert_allclose(float(adjoint_form(us, effect)), float(jax.jit(jax.grad(cost))(0.0)), rtol=1e-10)
