"""Policies, closed-loop rollouts and smoothed policy gradients (rsmooth.control._policy).

Problems, policies and solvers are built once at module level: the jitted step of
`optimize_policy` and the estimators compile once per structure, and the tests share them.
"""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from control_systems import Pendulum

from rsmooth import control, schedules

HORIZON = 4


class Jump:
    """x_next = x + u + 1[x + u > 0]: a unit jump of the next state across x + u = 0."""

    nx, nu = 1, 1

    def step(self, x, u):
        y = x + u
        return y + jnp.where(y > 0, 1.0, 0.0)


class Linear:
    nx, nu = 2, 1

    def step(self, x, u):
        return jnp.stack([x[0] + 0.1 * x[1], x[1] + 0.1 * u[0]])


def _quadratic_running(x, u):
    return 0.5 * jnp.sum(x**2) + 0.05 * jnp.sum(u**2)


def _quadratic_terminal(x):
    return 5.0 * jnp.sum((x - jnp.array([1.0, 0.0])) ** 2)


def _pendulum_terminal(x):
    return (x[0] - 1.0) ** 2 + 0.1 * x[1] ** 2


def _jump_terminal(x):
    return jnp.sum(x**2)


# V(theta) of the linear problem under an open-loop policy is a quadratic in theta: its Gaussian
# smoothing differs by a constant, so the smoothed gradient is the exact one.
LINEAR = control.ShootingProblem(Linear(), _quadratic_running, _quadratic_terminal, jnp.array([0.0, 0.5]), HORIZON)
OPEN_LOOP = control.OpenLoop(horizon=HORIZON, nu=1)
THETA_LINEAR = jnp.array([[1.0], [-0.5], [2.0], [0.3]])
PENDULUM = control.ShootingProblem(Pendulum(), _quadratic_running, _pendulum_terminal, jnp.array([0.3, -0.2]), HORIZON)
FEEDBACK = control.LinearFeedback(nx=2, nu=1)
THETA_FEEDBACK = {"gain": jnp.array([[-1.0, -0.5]]), "offset": jnp.array([2.0])}
# One step from x0 = 0: V(theta) = (theta + 1[theta > 0])^2 jumps from 0 to 1 at theta = 0.
JUMP = control.ShootingProblem(Jump(), lambda x, u: jnp.zeros(()), _jump_terminal, jnp.zeros(1), 1)
JUMP_POLICY = control.OpenLoop(horizon=1, nu=1)


@eqx.filter_jit
def _gradient(problem, policy, key, theta, sigma, num_samples, estimator):
    """policy_gradient, jitted (one program per problem, estimator and sample count)."""
    return control.policy_gradient(problem, policy, key, theta, sigma=sigma, num_samples=num_samples, estimator=estimator)


@eqx.filter_jit
def _exact_gradient(problem, policy, theta):
    return jax.grad(lambda th: control.policy_cost(problem, policy, th))(theta)


def test_rollout_equals_a_python_loop_of_step_and_vmaps():
    policy = control.LinearFeedback(nx=2, nu=1, horizon=HORIZON)
    theta = {"gain": jnp.linspace(-1.0, 1.0, 2 * HORIZON).reshape(HORIZON, 1, 2), "offset": jnp.arange(HORIZON, dtype=float)[:, None]}
    xs, us = control.rollout(Pendulum(), policy, theta, PENDULUM.x0, HORIZON)
    x, expected_xs, expected_us = np.asarray(PENDULUM.x0), [np.asarray(PENDULUM.x0)], []
    for t in range(HORIZON):
        u = np.asarray(theta["gain"][t]) @ x + np.asarray(theta["offset"][t])
        x = np.asarray(Pendulum().step(jnp.asarray(x), jnp.asarray(u)))
        expected_us.append(u)
        expected_xs.append(x)
    np.testing.assert_allclose(xs, np.array(expected_xs), rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(us, np.array(expected_us), rtol=1e-12, atol=1e-14)
    # Batched over parameters under jit: each row is the rollout of its own parameters.
    batch = jax.tree.map(lambda leaf: jnp.stack([leaf, 2.0 * leaf]), theta)
    batched_xs, _ = jax.jit(jax.vmap(lambda th: control.rollout(Pendulum(), policy, th, PENDULUM.x0, HORIZON)))(batch)
    np.testing.assert_allclose(batched_xs[0], xs, rtol=1e-12)
    doubled = jax.tree.map(lambda leaf: 2.0 * leaf, theta)
    np.testing.assert_allclose(batched_xs[1], control.rollout(Pendulum(), policy, doubled, PENDULUM.x0, HORIZON)[0], rtol=1e-12)
    # The objective is the problem's cost of that rollout.
    cost = control.policy_cost(PENDULUM, policy, theta)
    np.testing.assert_allclose(cost, PENDULUM.cost(xs, us), rtol=1e-12)


def test_first_order_with_tiny_sigma_is_the_exact_gradient(getkey):
    estimate = _gradient(PENDULUM, FEEDBACK, getkey(), THETA_FEEDBACK, jnp.asarray(1e-7), 2, "first")
    exact = _exact_gradient(PENDULUM, FEEDBACK, THETA_FEEDBACK)
    # sigma |w| ~ 1e-7 moves the gradient by about 1e-7 times the curvature (O(10) here).
    for name in ("gain", "offset"):
        np.testing.assert_allclose(estimate.grad[name], exact[name], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(estimate.value, control.policy_cost(PENDULUM, FEEDBACK, THETA_FEEDBACK), rtol=1e-6)


def test_zeroth_order_agrees_with_first_order_on_a_smooth_quadratic(getkey):
    exact = _exact_gradient(LINEAR, OPEN_LOOP, THETA_LINEAR)
    zeroth = _gradient(LINEAR, OPEN_LOOP, getkey(), THETA_LINEAR, jnp.asarray(0.1), 4096, "zeroth")
    first = _gradient(LINEAR, OPEN_LOOP, getkey(), THETA_LINEAR, jnp.asarray(0.1), 4096, "first")
    # Both estimate the exact gradient (V quadratic); 5 standard errors, estimated from the
    # samples themselves: a false failure has probability ~6e-7 per entry.
    for estimate in (zeroth, first):
        error = np.abs(np.asarray(estimate.grad) - np.asarray(exact))
        assert np.all(error <= 5.0 * np.asarray(estimate.stats["std_error"])), (error, estimate.stats["std_error"])
    # ... and the check has teeth: the zeroth-order standard error is below 10% of the gradient.
    assert float(jnp.max(zeroth.stats["std_error"])) < 0.1 * float(jnp.min(jnp.abs(exact)))


def test_alpha_rejects_first_order_across_a_jump(getkey):
    # Across the jump at theta = 0 the first-order samples see only the slope 2 x of each side
    # (mean 2 E[sigma w + 1[w > 0]] = 1), while the smoothed gradient adds the jump,
    # phi(0) / sigma = 4: the empirical bias (about 4) is many times the sampling noise of
    # 128 zeroth-order samples (standard error about 0.5).
    jump = _gradient(JUMP, JUMP_POLICY, getkey(), jnp.zeros((1, 1)), jnp.asarray(0.1), 256, "alpha")
    assert float(jump.stats["alpha"]) == 0.0
    assert float(jump.stats["bias"]) > 2.0 * float(jump.stats["bias_radius"]) and float(jump.stats["bias"]) > 2.0
    smoothed = 1.0 + 1.0 / (0.1 * np.sqrt(2.0 * np.pi))  # d/dtheta E[(theta + sigma w + 1[.])^2] at 0
    assert abs(float(jump.grad[0, 0]) - smoothed) < 5.0 * float(jump.stats["std_error"][0, 0])


def test_optimize_policy_decreases_a_smooth_cost_and_records_its_histories(getkey):
    solver = control.PolicyGradient(
        estimator="alpha", sigma=0.1, num_samples=16, learning_rate=0.3, iterations=30,
        schedule=schedules.Geometric(decay=0.9),
    )
    seen = []
    solution = control.optimize_policy(LINEAR, OPEN_LOOP, getkey(), OPEN_LOOP.init(), solver=solver, callback=seen.append)
    stats = solution.stats
    assert stats["cost"].shape == (31,) and stats["theta"].shape == (31, HORIZON, 1)
    for name in ("smoothed_cost", "sigma", "alpha", "variance", "grad_norm"):
        assert stats[name].shape == (30,)
    # V is quadratic, its gradient affine: columns of the Hessian are differences of gradients,
    # and the minimum V* = V(0) - g^T H^-1 g / 2 is one Newton step from 0.
    gradient = lambda th: np.asarray(_exact_gradient(LINEAR, OPEN_LOOP, jnp.asarray(th))).reshape(HORIZON)  # noqa: E731
    g = gradient(np.zeros((HORIZON, 1)))
    hessian = np.stack([gradient(np.eye(HORIZON)[i][:, None]) - g for i in range(HORIZON)], axis=1)
    best = stats["cost"][0] - 0.5 * g @ np.linalg.solve(hessian, g)
    assert stats["cost"][-1] - best < 0.05 * (stats["cost"][0] - best)
    assert stats["cost"][-1] == float(solution.cost)
    assert bool(solution.result == control.RESULTS.successful)
    np.testing.assert_allclose(stats["sigma"], 0.1 * 0.9 ** np.arange(30), rtol=1e-12)
    # On a quadratic the first-order samples vary by H sigma w only, far less than the score
    # function's: alpha* = var_0 / (var_0 + var_1) is close to 1. The trust region rejects
    # first order (alpha = 0) when its gap to zeroth order exceeds the sampling noise at level
    # 1 - delta = 0.95: with 8 samples per estimate, in 4 of these 30 iterations.
    assert np.all((stats["alpha"] >= 0) & (stats["alpha"] <= 1))
    assert np.median(stats["alpha"]) > 0.95 and np.mean(stats["alpha"] == 0.0) < 0.25
    assert [info["iteration"] for info in seen] == list(range(30))
    # Reproducible bit for bit for a given key.
    again = control.optimize_policy(LINEAR, OPEN_LOOP, jax.random.key(0), OPEN_LOOP.init(), solver=solver)
    twice = control.optimize_policy(LINEAR, OPEN_LOOP, jax.random.key(0), OPEN_LOOP.init(), solver=solver)
    np.testing.assert_array_equal(again.stats["theta"], twice.stats["theta"])


class Integrator:
    nx, nu = 1, 1

    def step(self, x, u):
        return x + u


def _undefined_beyond_half(x):
    return jnp.sum(jnp.where(x > 0.5, jnp.nan, (x - 1.0) ** 2))


def test_optimize_policy_reports_a_nonfinite_result():
    """The cost is NaN beyond x = 0.5 and Adam's first step (about the learning rate, 1) goes
    there from theta = 0: the final cost is not finite, which the result reports (and the next
    iteration's estimate, at NaN samples, raises)."""
    problem = control.ShootingProblem(Integrator(), lambda x, u: jnp.zeros(()), _undefined_beyond_half, jnp.zeros(1), 1)
    policy = control.OpenLoop(horizon=1, nu=1)
    solver = control.PolicyGradient(estimator="first", sigma=0.01, num_samples=4, learning_rate=1.0, iterations=1)
    solution = control.optimize_policy(problem, policy, jax.random.key(0), policy.init(), solver=solver)
    assert bool(solution.result == control.RESULTS.nonfinite) and not np.isfinite(float(solution.cost))
    assert np.isfinite(solution.stats["cost"][0])
    with pytest.raises(FloatingPointError, match="iteration 1: .*non-finite"):
        control.optimize_policy(problem, policy, jax.random.key(0), policy.init(), solver=dataclasses.replace(solver, iterations=2))


def test_policy_step_has_no_host_callbacks_so_the_compilation_cache_can_keep_it():
    """The estimators' traced checks are host callbacks (JAX's persistent compilation cache
    does not store programs with them); the policy step leaves them out and tests its
    estimate's finiteness itself (the test above)."""
    from rsmooth import estimators
    from rsmooth.control import _policy

    problem = control.ShootingProblem(Integrator(), _quadratic_running, _quadratic_terminal, jnp.zeros(1), 2)
    policy = control.OpenLoop(horizon=2, nu=1)
    theta = policy.init()
    f = lambda th: _policy._policy_cost(problem, policy, th)  # noqa: E731
    smoothed = jax.make_jaxpr(lambda key, th: estimators.zeroth_order(f, key, th, sigma=0.1, num_samples=4).grad)
    assert "callback" in str(smoothed(jax.random.key(0), theta))
    for estimator in ("zeroth", "first", "alpha"):
        solver = control.PolicyGradient(estimator=estimator, num_samples=4, iterations=1)
        schedule_state = solver.schedule.init(jnp.asarray(solver.sigma, jnp.float64), solver.num_samples)
        opt_state = optax.adam(solver.learning_rate).init(theta)
        jaxpr = jax.make_jaxpr(lambda th, o, s, k: _policy._jitted_step(solver, problem, policy, th, o, s, k))(
            theta, opt_state, schedule_state, jax.random.key(0))
        assert "callback" not in str(jaxpr)


TRACES = []


class CountingOpenLoop(control.OpenLoop):
    """OpenLoop that counts its traces: a call of a compiled program does not trace it again."""

    def __call__(self, theta, x, t):
        TRACES.append(t)
        return theta[t]


def test_shared_samples_serve_the_estimators_with_one_compiled_step(getkey):
    key = getkey()
    policy = CountingOpenLoop(horizon=HORIZON, nu=1)
    solvers = {
        name: control.PolicyGradient(estimator=name, sigma=0.1, num_samples=8, learning_rate=0.1, iterations=4,
                                     shared_samples=True)
        for name in ("first", "zeroth", "alpha")
    }
    shared = {"first": control.optimize_policy(LINEAR, policy, key, THETA_LINEAR, solver=solvers["first"])}
    traced = len(TRACES)
    for name in ("zeroth", "alpha"):
        shared[name] = control.optimize_policy(LINEAR, policy, key, THETA_LINEAR, solver=solvers[name])
    control.optimize_policy(LINEAR, policy, key, THETA_LINEAR, solver=dataclasses.replace(solvers["alpha"], iterations=2))
    crossed = control.optimize_policy(LINEAR, policy, key, THETA_LINEAR,
                                      solver=dataclasses.replace(solvers["alpha"], alpha_cross_fit=True))
    # the other estimators, cross-fitted alpha order and another length ran the same program
    assert len(TRACES) == traced
    # First and zeroth order on shared samples are the separate estimators on the same samples
    # (iteration k draws them from fold_in(key, k) in both).
    for name in ("first", "zeroth"):
        separate = control.optimize_policy(
            LINEAR, OPEN_LOOP, key, THETA_LINEAR, solver=dataclasses.replace(solvers[name], shared_samples=False)
        )
        np.testing.assert_allclose(shared[name].stats["theta"], separate.stats["theta"], rtol=1e-12, atol=1e-14)
        for stat in ("cost", "smoothed_cost", "variance", "grad_norm", "alpha"):
            np.testing.assert_allclose(shared[name].stats[stat], separate.stats[stat], rtol=1e-10, atol=1e-14)
    assert np.all(shared["first"].stats["alpha"] == 1.0) and np.all(shared["zeroth"].stats["alpha"] == 0.0)
    # Alpha order blends the halves: on this quadratic, mostly first order.
    alpha = shared["alpha"].stats["alpha"]
    assert np.all((alpha >= 0.0) & (alpha <= 1.0)) and np.median(alpha) > 0.9
    assert shared["alpha"].stats["cost"][-1] < shared["alpha"].stats["cost"][0]
    # Cross-fitted, on the same samples: weights from the other folds, another blend.
    crossed_alpha = crossed.stats["alpha"]
    assert np.all((crossed_alpha >= 0.0) & (crossed_alpha <= 1.0)) and not np.allclose(crossed_alpha, alpha)
    assert crossed.stats["cost"][-1] < crossed.stats["cost"][0]
    # The leave-one-out baseline: the same on shared samples as in the separate estimator.
    loo = dataclasses.replace(solvers["zeroth"], baseline="leave-one-out")
    shared_loo = control.optimize_policy(LINEAR, policy, key, THETA_LINEAR, solver=loo)
    separate_loo = control.optimize_policy(
        LINEAR, OPEN_LOOP, key, THETA_LINEAR, solver=dataclasses.replace(loo, shared_samples=False)
    )
    np.testing.assert_allclose(shared_loo.stats["theta"], separate_loo.stats["theta"], rtol=1e-12, atol=1e-14)
    assert not np.allclose(shared_loo.stats["theta"][1:], shared["zeroth"].stats["theta"][1:])
    with pytest.raises(ValueError, match="baseline must be"):
        control.PolicyGradient(estimator="zeroth", num_samples=8, baseline="mean")
    with pytest.raises(ValueError, match="antithetic"):
        control.PolicyGradient(estimator="first", num_samples=8, antithetic=True, shared_samples=True)
    with pytest.raises(ValueError, match="num_samples"):
        control.PolicyGradient(estimator="first", num_samples=5, shared_samples=True)


def test_bad_inputs_raise_errors_naming_the_argument(getkey):
    key = getkey()
    with pytest.raises(ValueError, match="sigma"):
        control.policy_gradient(LINEAR, OPEN_LOOP, key, THETA_LINEAR, sigma=0.0, num_samples=4)
    with pytest.raises(ValueError, match="sigma"):
        control.PolicyGradient(sigma=-1.0)
    with pytest.raises(ValueError, match="num_samples"):
        control.policy_gradient(LINEAR, OPEN_LOOP, key, THETA_LINEAR, sigma=0.1, num_samples=0)
    with pytest.raises(ValueError, match="num_samples"):
        control.PolicyGradient(estimator="alpha", num_samples=2)
    with pytest.raises(ValueError, match="estimator"):
        control.PolicyGradient(estimator="second")
    with pytest.raises(ValueError, match="theta"):
        control.policy_gradient(LINEAR, OPEN_LOOP, key, jnp.zeros((HORIZON + 1, 1)), sigma=0.1, num_samples=4)
    with pytest.raises(ValueError, match="theta"):
        control.policy_cost(PENDULUM, FEEDBACK, {"gain": jnp.zeros((2, 1)), "offset": jnp.zeros(1)})
    with pytest.raises(ValueError, match="theta"):
        control.optimize_policy(LINEAR, OPEN_LOOP, key, THETA_LINEAR.at[0, 0].set(jnp.nan))
    with pytest.raises(ValueError, match="x0"):
        control.rollout(Linear(), OPEN_LOOP, THETA_LINEAR, jnp.array([jnp.nan, 0.0]), HORIZON)
    with pytest.raises(ValueError, match="x0"):
        control.rollout(Linear(), OPEN_LOOP, THETA_LINEAR, jnp.zeros(3), HORIZON)
    with pytest.raises(ValueError, match="x0"):
        control.ShootingProblem(Linear(), _quadratic_running, _quadratic_terminal, jnp.array([0.0, jnp.nan]), HORIZON)
    with pytest.raises(ValueError, match="policy"):
        control.policy_cost(LINEAR, lambda th, x, t: th, jnp.zeros(3))
