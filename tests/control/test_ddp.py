"""DDP / Box-DDP against a Riccati recursion in NumPy, on a pendulum, and with box limits."""

import dataclasses
import types

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from control_systems import Linear, linear_quadratic, pendulum_swing_up, riccati

import rsmooth
from rsmooth import control


@pytest.fixture(scope="module")
def pendulum():
    return pendulum_swing_up()


@pytest.fixture(scope="module")
def pendulum_solution(pendulum):
    return control.ddp(pendulum, solver=control.DDP(max_iterations=100))


def test_linear_quadratic_is_solved_by_riccati_in_one_iteration():
    problem, (A, B, Q, R, Qf) = linear_quadratic()
    gains, xs, us, cost = riccati(A, B, Q, R, Qf, np.asarray(problem.x0), problem.horizon)
    # Without regularization (reg_init = 0), the first backward pass is the Riccati recursion.
    solution = control.ddp(problem, solver=control.DDP(reg_init=0.0))
    # Iteration 1 takes the full step to the LQR solution; iteration 2 finds nothing to improve.
    assert solution.converged and solution.iterations == 2
    assert float(solution.stats["step_size"][1]) == 1.0
    np.testing.assert_allclose(solution.stats["cost"][1], cost, rtol=1e-9)
    np.testing.assert_allclose(solution.us, us, rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(solution.xs, xs, rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(solution.gains, gains, rtol=1e-7, atol=1e-9)
    # The node Jacobians in batches of 2 nodes (`lax.map`) instead of all at once: the same.
    batched = control.ddp(problem, solver=control.DDP(reg_init=0.0, node_batch_size=2))
    np.testing.assert_allclose(batched.us, solution.us, rtol=1e-12, atol=1e-14)
    # A time-varying running cost: weights w_t on the state cost.
    weights = np.linspace(0.0, 3.0, problem.horizon)
    varying = control.ShootingProblem(
        problem.dynamics,
        lambda x, u, t: 0.5 * jnp.asarray(weights)[t] * (x @ (Q @ x)) + 0.5 * u @ (R @ u),
        problem.terminal_cost,
        problem.x0,
        problem.horizon,
        time_varying=True,
    )
    _, _, us, cost = riccati(A, B, weights[:, None, None] * Q, R, Qf, np.asarray(problem.x0), problem.horizon)
    solution = control.ddp(varying, solver=control.DDP(reg_init=0.0))
    assert solution.converged and solution.iterations == 2
    np.testing.assert_allclose(solution.us, us, rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(solution.cost, cost, rtol=1e-9)


def test_step_is_compiled_once_and_runs_in_a_while_loop():
    reference, _ = linear_quadratic()

    def problem(x0):
        return control.ShootingProblem(reference.dynamics, reference.running_cost, reference.terminal_cost, x0, reference.horizon)

    solver = control.DDP(reg_init=0.0)
    control.ddp(problem(reference.x0), solver=solver)
    traces = Linear.traces[0]
    solution = control.ddp(problem(reference.x0 + 1.0), solver=solver)
    assert solution.converged and Linear.traces[0] == traces  # no new trace

    # init / step / terminate compose in a lax.while_loop, as in Optimistix.
    @jax.jit
    def solve(x0):
        state = solver.init(problem(x0), jnp.zeros((reference.horizon, 2)))
        return jax.lax.while_loop(lambda s: ~solver.terminate(s), lambda s: solver.step(problem(x0), s), state)

    state = solve(reference.x0 + 1.0)
    np.testing.assert_allclose(state.trajectory.us, solution.us, rtol=1e-9, atol=1e-12)


def test_cost_parameters_are_traced_and_share_one_compiled_step():
    """Costs that take ``params`` (here a target state and a terminal weight): two problems
    differing only in them reuse the compiled step, and each solve equals the one with the
    values written into the cost (closures), in residual and in scalar form."""
    reference, (A, B, Q, R, Qf) = linear_quadratic()
    traces = []

    def running(x, u, params):
        traces.append("running")
        return 0.5 * (x - params["target"]) @ (Q @ (x - params["target"])) + 0.5 * u @ (R @ u)

    def terminal(x, params):
        traces.append("terminal")
        return 0.5 * params["weight"] * (x - params["target"]) @ (x - params["target"])

    def with_params(target, weight):
        params = {"target": jnp.asarray(target), "weight": jnp.asarray(weight)}
        return control.ShootingProblem(reference.dynamics, running, terminal, reference.x0, reference.horizon, params=params)

    def closed(target, weight):
        return control.ShootingProblem(
            reference.dynamics,
            lambda x, u: 0.5 * (x - target) @ (Q @ (x - target)) + 0.5 * u @ (R @ u),
            lambda x: 0.5 * weight * (x - target) @ (x - target),
            reference.x0,
            reference.horizon,
        )

    solver = control.DDP(reg_init=0.0)
    first = control.ddp(with_params(np.zeros(4), 10.0), solver=solver)
    count = len(traces)
    target = np.array([1.0, -0.5, 0.2, 0.0])
    second = control.ddp(with_params(target, 3.0), solver=solver)
    assert len(traces) == count  # no new trace: the target and weight were traced
    for solution, (t, w) in ((first, (np.zeros(4), 10.0)), (second, (target, 3.0))):
        expected = control.ddp(closed(t, w), solver=solver)
        assert solution.converged
        np.testing.assert_allclose(solution.us, expected.us, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(solution.cost, expected.cost, rtol=1e-12)
    # residual costs take params the same way
    residual = control.ShootingProblem(
        reference.dynamics,
        lambda x, u, p: jnp.concatenate([jnp.linalg.cholesky(Q).T @ (x - p["target"]), jnp.linalg.cholesky(R).T @ u]),
        lambda x, p: jnp.sqrt(p["weight"]) * (x - p["target"]),
        reference.x0,
        reference.horizon,
        residuals=True,
        params={"target": jnp.asarray(target), "weight": jnp.asarray(3.0)},
    )
    np.testing.assert_allclose(control.ddp(residual, solver=solver).us, second.us, rtol=1e-7, atol=1e-10)


def test_pendulum_swing_up_converges_with_monotone_cost(pendulum, pendulum_solution):
    solution = pendulum_solution
    assert solution.converged and solution.result == control.RESULTS.successful
    costs = np.asarray(solution.stats["cost"])
    assert np.all(np.diff(costs) <= 0.0)
    assert costs[-1] < 0.1 * costs[0]
    np.testing.assert_allclose(solution.xs[-1], [np.pi, 0.0], atol=0.05)
    # The solution is a stationary point of the cost as a function of the controls.
    gradient = jax.grad(lambda us: pendulum.cost(pendulum.rollout(us), us))(solution.us)
    assert float(jnp.max(jnp.abs(gradient))) < 1e-4
    # Timings and histories have one entry per iteration.
    assert len(solution.stats["time_per_iteration"]) == solution.iterations
    assert solution.stats["cost"].shape == (solution.iterations + 1,)
    assert np.all(np.asarray(solution.stats["noise"]) == 0.0)


def test_full_second_order_reaches_the_same_solution(pendulum, pendulum_solution):
    solution = control.ddp(pendulum, solver=control.DDP(approximation="full"))
    assert solution.converged
    # The same local minimum (the cost is flat along it to within th_stop).
    np.testing.assert_allclose(solution.cost, pendulum_solution.cost, rtol=1e-8)
    np.testing.assert_allclose(solution.us, pendulum_solution.us, atol=1e-3)
    assert solution.iterations <= pendulum_solution.iterations


def test_box_qp_satisfies_the_kkt_conditions(getkey):
    solve = jax.jit(control.box_qp, static_argnums=5)
    for _ in range(5):
        M = jax.random.normal(getkey(), (4, 4))
        H = M @ M.T + 0.1 * jnp.eye(4)
        q = 3.0 * jax.random.normal(getkey(), (4,))
        lower, upper = -jnp.ones(4), jnp.array([1.0, 1.0, jnp.inf, 0.5])
        x, free, failed = solve(H, q, lower, upper, jnp.zeros(4), 30)
        g = q + H @ x
        assert not bool(failed)
        assert bool(jnp.all((x >= lower) & (x <= upper)))
        np.testing.assert_allclose(jnp.where(free, g, 0.0), 0.0, atol=1e-8)
        assert bool(jnp.all(jnp.where(x == lower, g >= -1e-8, True)))
        assert bool(jnp.all(jnp.where(x == upper, g <= 1e-8, True)))


def test_callback_progress_and_throw(pendulum):
    seen = []
    solver = control.DDP(max_iterations=3)
    with pytest.raises(RuntimeError, match="max_iterations"):
        control.ddp(pendulum, solver=solver, callback=seen.append, progress=True)
    assert [info["iteration"] for info in seen] == [1, 2, 3]
    assert {"cost", "noise", "step_size", "regularization", "expected_improvement", "time"} <= set(seen[0])
    solution = control.ddp(pendulum, solver=control.DDP(max_iterations=3, throw=False))
    assert solution.result == control.RESULTS.max_iterations_reached and not solution.converged
    # one enumeration for every solver of rsmooth, its message generic and DDP's error specific
    assert control.RESULTS is rsmooth.RESULTS and "max_iterations" in control.RESULTS[solution.result]


def test_bad_input_raises_named_errors(pendulum):
    with pytest.raises(ValueError, match="x0"):
        control.ShootingProblem(pendulum.dynamics, pendulum.running_cost, pendulum.terminal_cost, jnp.zeros(3), 10)
    with pytest.raises(ValueError, match="x0"):
        control.ShootingProblem(pendulum.dynamics, pendulum.running_cost, pendulum.terminal_cost, jnp.array([jnp.nan, 0.0]), 10)
    with pytest.raises(ValueError, match="horizon"):
        control.ShootingProblem(pendulum.dynamics, pendulum.running_cost, pendulum.terminal_cost, jnp.zeros(2), 0)
    with pytest.raises(ValueError, match="control_lower"):
        control.ShootingProblem(pendulum.dynamics, pendulum.running_cost, pendulum.terminal_cost, jnp.zeros(2), 10, control_lower=jnp.zeros(3))
    with pytest.raises(ValueError, match="us_init"):
        control.ddp(pendulum, jnp.zeros((pendulum.horizon + 1, 1)))
    with pytest.raises(ValueError, match="us_init"):
        control.ddp(pendulum, jnp.full((pendulum.horizon, 1), jnp.nan))
    with pytest.raises(ValueError, match="approximation"):
        control.DDP(approximation="newton")
    with pytest.raises(ValueError, match="max_iterations"):
        control.DDP(max_iterations=0)


def test_box_ddp_reaches_the_optimum_of_the_convex_box_constrained_lq_problem():
    reference, _ = linear_quadratic()
    problem = control.ShootingProblem(
        reference.dynamics, reference.running_cost, reference.terminal_cost, reference.x0, reference.horizon,
        control_lower=-2.0, control_upper=jnp.array([2.0, 1.0]),
    )
    solution = control.ddp(problem)
    assert solution.converged
    assert np.all(np.diff(np.asarray(solution.stats["cost"])) <= 0.0)
    us = np.asarray(solution.us)
    assert np.all((us >= -2.0) & (us <= np.array([2.0, 1.0])))
    # Clamped controls get no feedback.
    clamped = (us == -2.0) | (us == np.array([2.0, 1.0]))
    assert np.any(clamped) and np.all(np.asarray(solution.gains)[clamped] == 0.0)
    # The cost is a convex quadratic of the controls: minimize it over the box by projected
    # gradient descent (FISTA) in NumPy, a plain reference.
    flat_cost = lambda v: problem.cost(problem.rollout(v.reshape(-1, 2)), v.reshape(-1, 2))  # noqa: E731
    H = np.asarray(jax.jit(jax.hessian(flat_cost))(jnp.zeros(30)))
    g = np.asarray(jax.jit(jax.grad(flat_cost))(jnp.zeros(30)))
    lower, upper = np.tile([-2.0, -2.0], 15), np.tile([2.0, 1.0], 15)
    step = 1.0 / np.linalg.eigvalsh(H)[-1]
    v = y = np.zeros(30)
    t = 1.0
    for _ in range(5000):
        v_next = np.clip(y - step * (H @ y + g), lower, upper)
        t_next = (1 + np.sqrt(1 + 4 * t**2)) / 2
        y = v_next + (t - 1) / t_next * (v_next - v)
        v, t = v_next, t_next
    np.testing.assert_allclose(solution.us.reshape(-1), v, atol=1e-6)
    assert np.any(v == lower) and np.any(v == upper)  # both limits are active


class Wall:
    """x_next = x + u, undefined (NaN) beyond x = 5, and raising on a non-finite state as a
    simulator with runtime checks does."""

    nx, nu = 1, 1

    def step(self, x, u):
        x = eqx.error_if(x, ~jnp.all(jnp.isfinite(x)), "non-finite state")
        return jnp.where(x + u > 5.0, jnp.nan, x + u)


def test_diverging_trial_steps_are_rejected_without_feeding_nan_to_the_dynamics():
    problem = control.ShootingProblem(Wall(), lambda x, u: 0.0 * jnp.sum(u), lambda x: jnp.sum((x - 8.0) ** 2), jnp.zeros(1), 2)
    solution = control.ddp(problem, solver=control.DDP(max_iterations=5, throw=False))
    costs = np.asarray(solution.stats["cost"])
    assert np.all(np.isfinite(costs)) and np.all(np.diff(costs) <= 0.0) and costs[-1] < costs[0]
    assert float(jnp.max(solution.xs)) <= 5.0


class FlaggedWall(Wall):
    """The same steps, finite everywhere below 5, with ``step_with_info`` flagging those that end
    beyond ``x = 3`` as diverged (as the simulator flags a step beyond ``max_motion_per_step``)."""

    def step(self, x, u):
        return x + u

    def step_with_info(self, x, u):
        x_next = self.step(x, u)
        return x_next, types.SimpleNamespace(diverged=jnp.any(x_next > 3.0))


def test_trials_through_a_flagged_step_are_rejected_though_finite():
    problem = control.ShootingProblem(FlaggedWall(), lambda x, u: 0.0 * jnp.sum(u), lambda x: jnp.sum((x - 8.0) ** 2), jnp.zeros(1), 2)
    solution = control.ddp(problem, solver=control.DDP(max_iterations=5, throw=False))
    costs = np.asarray(solution.stats["cost"])
    assert np.all(np.isfinite(costs)) and np.all(np.diff(costs) <= 0.0) and costs[-1] < costs[0]
    # The full step (x -> 8) is finite but flagged: rejected, the iterates stay at or below 3.
    assert float(jnp.max(solution.xs)) <= 3.0 and float(solution.stats["step_size"][1]) < 1.0
    # Without step_with_info the same dynamics take the full step.
    plain = control.ddp(eqx.tree_at(lambda p: p.dynamics, problem, Linear(jnp.ones((1, 1)), jnp.ones((1, 1)), 1, 1)),
                        solver=control.DDP(max_iterations=5, throw=False))
    assert float(jnp.max(plain.xs)) > 7.9


def test_residual_costs_use_gauss_newton_hessians_and_reach_the_same_optima(pendulum, pendulum_solution):
    # Linear residuals: 0.5 ||r||^2 with r = [Q^1/2 x; R^1/2 u] is the LQ cost exactly, and its
    # Gauss-Newton Hessian is exact: the Riccati solution in one iteration.
    problem, (A, B, Q, R, Qf) = linear_quadratic()
    Qh, Rh, Qfh = (np.linalg.cholesky(M).T for M in (Q, R, Qf))
    residual = control.ShootingProblem(
        problem.dynamics,
        lambda x, u: jnp.concatenate([Qh @ x, Rh @ u]),
        lambda x: Qfh @ x,
        problem.x0,
        problem.horizon,
        residuals=True,
    )
    _, _, us, cost = riccati(A, B, Q, R, Qf, np.asarray(problem.x0), problem.horizon)
    np.testing.assert_allclose(residual.cost(residual.rollout(jnp.asarray(us)), jnp.asarray(us)), cost, rtol=1e-12)
    solution = control.ddp(residual, solver=control.DDP(reg_init=0.0))
    assert solution.converged and solution.iterations == 2
    np.testing.assert_allclose(solution.us, us, rtol=1e-7, atol=1e-9)
    # The pendulum's costs as residuals (0.5 ||r||^2 = the scalar costs): the same optimum.
    target = jnp.array([jnp.pi, 0.0])
    pendulum_residual = control.ShootingProblem(
        pendulum.dynamics,
        lambda x, u: jnp.sqrt(2e-2) * jnp.concatenate([u, x - target]),
        lambda x: jnp.sqrt(200.0) * (x - target),
        pendulum.x0,
        pendulum.horizon,
        residuals=True,
    )
    solution = control.ddp(pendulum_residual)
    assert solution.converged
    np.testing.assert_allclose(solution.cost, pendulum_solution.cost, rtol=1e-6)
    np.testing.assert_allclose(solution.us, pendulum_solution.us, atol=1e-3)


def test_relative_stopping_test_ends_a_solve_that_the_absolute_one_does_not():
    """Terminal cost |x_T - 1| (a kink at the optimum): the quadratic model keeps promising
    ~3e-9 there, above the absolute th_stop = 1e-9 whatever the iterations; relative to the
    cost (1/300), that is 1e-6."""

    class Integrator:
        nx, nu = 1, 1

        def step(self, x, u):
            return x + u

    problem = control.ShootingProblem(
        Integrator(), lambda x, u: 1e-2 * jnp.sum(u**2), lambda x: jnp.abs(x[0] - 1.0), jnp.zeros(1), 3
    )
    optimum = 1e-2 * 3 * (1 / 3) ** 2  # x_T = 1 in three equal steps
    absolute = control.ddp(problem, solver=control.DDP(max_iterations=60, throw=False))
    assert absolute.result == control.RESULTS.max_iterations_reached
    assert abs(float(absolute.cost) - optimum) < 1e-9
    relative = control.ddp(problem, solver=control.DDP(max_iterations=60, th_stop_relative=1e-5))
    assert relative.converged and relative.iterations < 40
    assert abs(float(relative.cost) - optimum) < 1e-6 * optimum
    # The test compares with the cost before the step: the last expected improvement is below it.
    last = float(relative.stats["expected_improvement"][-1])
    assert last < 1e-5 * float(relative.stats["cost"][-2]) and last > 1e-9
    with pytest.raises(ValueError, match="th_stop_relative"):
        control.DDP(th_stop_relative=-1.0)


def _backtracking_problem():
    """x' = x + u, a pseudo-Huber terminal cost: far from the target its Hessian is tiny and the
    full Newton step overshoots by ~60x, so the line search backtracks (to 2^-5, then 2^-3)."""
    return control.ShootingProblem(
        Linear(jnp.ones((1, 1)), jnp.ones((1, 1)), 1, 1),
        lambda x, u: 1e-3 * jnp.sum(u**2),
        lambda x: jnp.sum(jnp.sqrt(1.0 + (x - 8.0) ** 2)),
        jnp.zeros(1),
        2,
    )


@pytest.mark.parametrize("batch", [2, 3, 4, 10, 16])
def test_batched_line_search_takes_the_steps_of_the_sequential_one(batch):
    problem = _backtracking_problem()
    sequential = control.ddp(problem, solver=control.DDP(max_iterations=30))
    steps = np.asarray(sequential.stats["step_size"])[1:]
    assert steps[0] == 2.0**-5 and steps[1] == 2.0**-3  # backtracked across and within groups
    batched = control.ddp(problem, solver=control.DDP(max_iterations=30, line_search_batch=batch))
    assert batched.iterations == sequential.iterations
    for name in ("step_size", "cost", "regularization"):
        np.testing.assert_allclose(batched.stats[name], sequential.stats[name], rtol=1e-12, err_msg=name)
    np.testing.assert_allclose(batched.us, sequential.us, rtol=1e-12)
    # With 5 step sizes none is accepted (2^-5 would be, and pads the last group for batches
    # of 2, 3 and 4: it must not be taken), and the regularization grows after each failed search.
    few = [control.ddp(problem, solver=control.DDP(max_iterations=3, num_step_sizes=5, line_search_batch=b, throw=False))
           for b in (1, batch)]
    for solution in few:
        np.testing.assert_array_equal(np.asarray(solution.stats["step_size"])[1:], 0.0)
        np.testing.assert_allclose(solution.stats["regularization"], [1e-9, 1e-8, 1e-7, 1e-6])
        np.testing.assert_array_equal(solution.us, 0.0)


def test_line_search_batch_is_checked():
    with pytest.raises(ValueError, match="line_search_batch must be an int >= 1"):
        control.DDP(line_search_batch=0)
    with pytest.raises(ValueError, match="line_search_batch must be an int >= 1"):
        control.DDP(line_search_batch="all")


def test_line_search_batch_auto_follows_the_backend(monkeypatch):
    """line_search_batch="auto" (the default): one step size at a time on the CPU, all of them
    at once on a GPU or TPU (the steps are the same: the test above)."""
    from rsmooth import _xla

    assert control.DDP().line_search_batch == "auto"
    monkeypatch.setattr(_xla, "on_accelerator", lambda: False)
    assert control.DDP()._line_search_batch() == 1
    monkeypatch.setattr(_xla, "on_accelerator", lambda: True)
    assert control.DDP()._line_search_batch() == 10
    assert control.DDP(num_step_sizes=6)._line_search_batch() == 6
    assert control.DDP(line_search_batch=3)._line_search_batch() == 3
    assert control.DDP(line_search_batch=30)._line_search_batch() == 10


def test_line_search_auto_on_an_accelerator_takes_the_sequential_steps(monkeypatch):
    """The "auto" line search traced as on a GPU (all ten step sizes at once) solves the
    backtracking problem with the steps of the one-at-a-time search. (max_iterations = 29: a
    solver no other test compiles, so this one is traced under the patched backend.)"""
    from rsmooth import _xla

    problem = _backtracking_problem()
    sequential = control.ddp(problem, solver=control.DDP(max_iterations=29, line_search_batch=1))
    monkeypatch.setattr(_xla, "on_accelerator", lambda: True)
    batched = control.ddp(problem, solver=control.DDP(max_iterations=29))
    assert batched.iterations == sequential.iterations
    np.testing.assert_allclose(batched.stats["step_size"], sequential.stats["step_size"], rtol=1e-12)
    np.testing.assert_allclose(batched.us, sequential.us, rtol=1e-12)


def test_solver_programs_have_no_host_callbacks_so_the_compilation_cache_can_keep_them():
    """The simulator's step carries traced checks (host callbacks, which JAX's persistent
    compilation cache refuses to store); DDP's and R-DDP's programs leave them out, since the
    solver tests its rollouts for finiteness itself."""
    from rsmooth import sim
    from rsmooth.control import _ddp

    system = sim.ball(time_step=0.01)
    x0 = system.initial_state()
    assert "callback" in str(jax.make_jaxpr(system.step)(x0, jnp.zeros(system.nu)))
    problem = control.ShootingProblem(system, lambda x, u: jnp.sum(u**2), lambda x: jnp.sum(x**2), x0, 2)
    us = jnp.zeros((2, system.nu))
    for solver in (control.DDP(), control.RDDP(num_samples=2)):
        smoothed, exact = solver._programs()
        state = _ddp._jitted_init(exact, problem, us, None)
        if smoothed is not exact:
            state = dataclasses.replace(state, noise=jnp.asarray(0.1), key=jax.random.key(0))
        for program in {smoothed, exact}:
            jaxpr = jax.make_jaxpr(lambda s, program=program: _ddp._jitted_step(program, problem, s))(state)
            assert "callback" not in str(jaxpr)
