r"""Differential dynamic programming (DDP / iLQR) with box control limits.

One iteration, around the current trajectory :math:`(\bar x, \bar u)`:

1. *Derivatives* of the dynamics and of the costs at every node, by JAX autodiff, all nodes
   at once (`vmap`).
2. *Backward pass* (a reverse `lax.scan`, Tassa, Erez, Todorov, IROS 2012, Eq. 5 and 11):

   .. math::
       Q_x = l_x + f_x^\top V'_x, \quad Q_u = l_u + f_u^\top V'_x, \quad
       Q_{xx} = l_{xx} + f_x^\top V'_{xx} f_x, \quad Q_{ux} = l_{ux} + f_u^\top V'_{xx} f_x,
       \quad Q_{uu} = l_{uu} + f_u^\top V'_{xx} f_u,

   plus :math:`V'_x \cdot f_{xx}`-type terms with ``approximation="full"`` (DDP; without
   them, ``"gauss_newton"``, it is iLQR). The control step solves
   :math:`\min_{\delta u} \tfrac12 \delta u^\top (Q_{uu} + \mu I)\delta u + Q_u^\top\delta u`,
   unconstrained (:math:`k = -\tilde Q_{uu}^{-1} Q_u`, :math:`K = -\tilde Q_{uu}^{-1} Q_{ux}`)
   or within the box :math:`\underline u - \bar u \le \delta u \le \overline u - \bar u` by
   the projected-Newton QP of Box-DDP (Tassa, Mansard, Todorov, ICRA 2014, Alg. 3), whose
   gains are zero on the clamped controls. :math:`\mu` is a Levenberg-Marquardt
   regularization; when :math:`\tilde Q_{uu}` is not positive definite the pass is redone
   with :math:`\mu` multiplied by ``reg_factor`` (up to ``reg_max``).
3. *Convergence test*: the expected improvement of the full step,
   :math:`\Delta = -\sum_t (k_t^\top Q_u + \tfrac12 k_t^\top Q_{uu} k_t)`, below
   ``max(th_stop, th_stop_relative * |J|)`` with :math:`J` the current true cost (the
   relative part, off by default, makes the test independent of the cost's scale).
4. *Forward pass* (a `lax.scan`) with backtracking line search on the true cost:
   :math:`u_t = \mathrm{clip}(\bar u_t + \alpha k_t + K_t (x_t - \bar x_t))`, step sizes
   :math:`\alpha = 1, 1/2, \ldots`, accepted when the cost decreases by at least
   ``th_acceptstep`` times the expected :math:`-(\alpha d_1 + \tfrac12\alpha^2 d_2)`;
   a trial whose rollout diverges (non-finite state or cost) is rejected, and the dynamics
   are never called on a non-finite state.
   :math:`\mu` is divided by ``reg_factor`` after a step :math:`\alpha \ge` ``th_stepdec``
   and multiplied after a small (:math:`\le` ``th_stepinc``) or failed one (Crocoddyl's rule).

The solver has the shape of Equinox/Optimistix solvers: ``init``, ``step`` (jitted once,
pure, usable in a `lax.while_loop`), ``terminate``, ``postprocess``; :func:`ddp` runs the
loop in Python so that a progress callback can follow it.

Example:
    >>> import jax.numpy as jnp
    >>> from rsmooth import control
    >>> class DoubleIntegrator:
    ...     nx, nu = 2, 1
    ...     def step(self, x, u):
    ...         return jnp.array([x[0] + 0.1 * x[1], x[1] + 0.1 * u[0]])
    >>> problem = control.ShootingProblem(
    ...     DoubleIntegrator(),
    ...     running_cost=lambda x, u: 1e-2 * jnp.sum(u**2),
    ...     terminal_cost=lambda x: 10.0 * jnp.sum((x - jnp.array([1.0, 0.0])) ** 2),
    ...     x0=jnp.zeros(2), horizon=20, control_lower=-1.0, control_upper=1.0)
    >>> solution = control.ddp(problem)
    >>> bool(solution.converged), bool(jnp.all(jnp.abs(solution.us) <= 1.0))
    (True, True)
    >>> round(float(solution.xs[-1, 0]), 2)
    0.97

References:
    Y. Tassa, T. Erez, E. Todorov, "Synthesis and stabilization of complex behaviors through
    online trajectory optimization", IROS 2012.
    Y. Tassa, N. Mansard, E. Todorov, "Control-limited differential dynamic programming",
    ICRA 2014.
    C. Mastalli et al., "Crocoddyl: an efficient and versatile framework for multi-contact
    optimal control", ICRA 2020.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Callable, ClassVar, Literal, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array, lax

from rsmooth import _checks, _xla
from rsmooth import _linalg as linalg
from rsmooth._results import RESULTS
from rsmooth.control._problem import ShootingProblem

__all__ = ["RESULTS", "DDP", "DDPState", "Trajectory", "Solution", "ddp"]

APPROXIMATIONS = ("gauss_newton", "full")
_HISTORY = ("cost", "noise", "step_size", "regularization", "expected_improvement")


# DDP's context for the shared messages of RESULTS, added when `throw` raises.
_CONTEXT = {
    "max_iterations_reached": "the expected improvement stayed above max(th_stop, th_stop_relative * |cost|), "
    "the tolerance; pass throw=False to get the last iterate",
    "regularization_exceeded": "the backward pass: Quu + reg I is not positive definite at reg = reg_max",
    "nonfinite": "the derivatives of the dynamics or of the costs along the trajectory are not finite",
}


def _failure_message(description: str, result: RESULTS) -> str:
    """The error of a failed solve: the result's message and DDP's context for it."""
    context = next((text for name, text in _CONTEXT.items() if bool(result == getattr(RESULTS, name))), None)
    message = f"{description}: {RESULTS[result]}"
    return message if context is None else f"{message} ({context})"


class Trajectory(eqx.Module):
    """A trajectory and its affine feedback policy ``u_t = us[t] + gains[t] (x - xs[t])``.

    Attributes:
        xs: states ``(T + 1, nx)``.
        us: controls ``(T, nu)``.
        gains: feedback gains ``K`` ``(T, nu, nx)`` of the last backward pass.
        feedforward: feedforward steps ``k`` ``(T, nu)`` of the last backward pass.
    """

    xs: Array
    us: Array
    gains: Array
    feedforward: Array


class DDPState(eqx.Module):
    """The solver state; ``history`` holds one entry per iteration (NaN-padded)."""

    trajectory: Trajectory
    cost: Array
    regularization: Array
    noise: Array
    iteration: Array
    expected_improvement: Array
    step_size: Array
    converged: Array
    result: RESULTS
    key: Array | None
    history: dict


class Solution(eqx.Module):
    """What :func:`ddp` and :func:`~rsmooth.control.rddp` return.

    Attributes:
        value: the :class:`Trajectory` (states, controls, feedback gains).
        result: a :class:`~rsmooth.RESULTS` item: ``successful``, ``max_iterations_reached``,
            ``regularization_exceeded`` (the backward pass) or ``nonfinite`` (the derivatives);
            ``RESULTS[solution.result]`` is its message.
        stats: ``iterations`` (int), ``converged`` (bool), ``cost`` (the true cost before the
            first and after each iteration, ``iterations + 1``), ``noise`` (the smoothing
            ``eps``: ``noise[i]`` is the one iteration ``i + 1`` uses; zeros for DDP),
            ``step_size`` (accepted line-search step, 0 when rejected), ``regularization``,
            ``expected_improvement`` (NaN before the first backward pass),
            ``time_per_iteration`` (seconds, wall clock; the first includes compilation)
            and ``total_time``.
        state: the final :class:`DDPState`.
    """

    value: Trajectory
    result: RESULTS
    stats: dict
    state: DDPState

    @property
    def xs(self) -> Array:
        return self.value.xs

    @property
    def us(self) -> Array:
        return self.value.us

    @property
    def gains(self) -> Array:
        return self.value.gains

    @property
    def cost(self) -> Array:
        return self.state.cost

    @property
    def converged(self) -> bool:
        return bool(self.stats["converged"])

    @property
    def iterations(self) -> int:
        return int(self.stats["iterations"])


class _Derivatives(NamedTuple):
    fx: Array  # (T, nx, nx)
    fu: Array  # (T, nx, nu)
    lx: Array  # (T, nx)
    lu: Array  # (T, nu)
    lxx: Array  # (T, nx, nx)
    lxu: Array  # (T, nx, nu)
    luu: Array  # (T, nu, nu)
    lTx: Array  # (nx,)
    lTxx: Array  # (nx, nx)
    noise_effect: Array  # (T, nx): d f_eps / d eps at each node (zero without smoothing)


class _Backward(NamedTuple):
    feedforward: Array  # (T, nu)
    gains: Array  # (T, nu, nx)
    failed: Array  # bool
    d1: Array  # sum_t k_t . Q_u
    d2: Array  # sum_t k_t . Q_uu k_t


def map_nodes(function: Callable, inputs, batch_size: int | None):
    """``function`` over the leading (node) axis of ``inputs``: ``batch_size`` nodes at a time
    (`lax.map`, vmapped within a batch; a plain scan for one node at a time), or all at once
    with `vmap` when ``batch_size`` is None."""
    if batch_size is None:
        return jax.vmap(function)(*inputs)
    if batch_size == 1:
        # unbatched: under vmap, conditionals and loops (the contact solve's) take batched
        # predicates, both branches of a cond run, and the program is larger and slower to build
        return lax.map(lambda args: function(*args), inputs)
    return lax.map(lambda args: function(*args), inputs, batch_size=batch_size)


def dynamics_jacobians(problem: ShootingProblem, xs: Array, us: Array, batch_size: int | None = 1) -> tuple[Array, Array]:
    """``f_x`` ``(T, nx, nx)`` and ``f_u`` ``(T, nx, nu)`` along a trajectory, ``batch_size``
    nodes at a time (see :class:`DDP`): by the dynamics' own ``step_and_jacobians(x, u) ->
    (x_next, f_x, f_u)`` when it has one (the simulator's faster implicit Jacobians), else by
    autodiff of ``step``."""
    step_and_jacobians = getattr(problem.dynamics, "step_and_jacobians", None)
    if step_and_jacobians is not None:
        jacobian = lambda x, u: step_and_jacobians(x, u)[1:]  # noqa: E731
    else:
        jacobian = jax.jacfwd(problem.dynamics.step, argnums=(0, 1))
    return map_nodes(jacobian, (xs[:-1], us), batch_size)


def _cost_derivatives(problem: ShootingProblem, xs: Array, us: Array):
    if problem.residuals:
        return _residual_derivatives(problem, xs, us)
    gradient = jax.grad(problem.running, argnums=(0, 1))
    hessian = jax.hessian(problem.running, argnums=(0, 1))
    ts = jnp.arange(problem.horizon, dtype=jnp.int32)
    lx, lu = jax.vmap(gradient)(xs[:-1], us, ts)
    ((lxx, lxu), (_, luu)) = jax.vmap(hessian)(xs[:-1], us, ts)
    lTx = jax.grad(problem.terminal_residual)(xs[-1])
    lTxx = jax.hessian(problem.terminal_residual)(xs[-1])
    return lx, lu, lxx, lxu, luu, lTx, lTxx


def _residual_derivatives(problem: ShootingProblem, xs: Array, us: Array):
    """Gradients and Gauss-Newton Hessians of costs ``0.5 ||r||^2`` (``problem.residuals``)."""

    def node(x, u, t):
        r = jnp.atleast_1d(problem.running_residual(x, u, t))
        rx, ru = jax.jacfwd(lambda x, u: jnp.atleast_1d(problem.running_residual(x, u, t)), argnums=(0, 1))(x, u)
        return rx.T @ r, ru.T @ r, rx.T @ rx, rx.T @ ru, ru.T @ ru

    ts = jnp.arange(problem.horizon, dtype=jnp.int32)
    lx, lu, lxx, lxu, luu = jax.vmap(node)(xs[:-1], us, ts)
    terminal = lambda x: jnp.atleast_1d(problem.terminal_residual(x))  # noqa: E731
    r, rx = terminal(xs[-1]), jax.jacfwd(terminal)(xs[-1])
    return lx, lu, lxx, lxu, luu, rx.T @ r, rx.T @ rx


def _cholesky_solve(matrix: Array, rhs: Array) -> tuple[Array, Array]:
    """``matrix^{-1} rhs`` and whether ``matrix`` failed to be positive definite."""
    factor = linalg.cholesky(matrix)
    failed = ~jnp.all(jnp.isfinite(factor))
    return linalg.cho_solve((factor, True), rhs), failed


def box_qp(H: Array, q: Array, lower: Array, upper: Array, x_init: Array, max_iterations: int):
    """Projected-Newton solution of ``min 1/2 x'Hx + q'x`` s.t. ``lower <= x <= upper``.

    Tassa, Mansard, Todorov, ICRA 2014, Alg. 3: at each iteration the clamped set holds the
    coordinates at a bound whose gradient pushes outwards; a Newton step on the free ones is
    followed by a projected Armijo backtracking line search (factor 0.6). Branch-free: the
    step sizes are tried all at once and the largest acceptable one kept.

    Returns:
        ``(x, free, failed)``: the solution, the mask of the free coordinates at it, and
        whether the free block of ``H`` was not positive definite.
    """
    nu = q.shape[0]
    eye = jnp.eye(nu, dtype=H.dtype)
    steps = 0.6 ** jnp.arange(30, dtype=H.dtype)

    def free_set(x):
        g = q + H @ x
        clamped = ((x <= lower) & (g > 0)) | ((x >= upper) & (g < 0))
        return g, ~clamped

    def value(x):
        return q @ x + 0.5 * x @ (H @ x)

    def body(carry):
        i, x, _, failed = carry
        g, free = free_set(x)
        masked = jnp.where(free[:, None] & free[None, :], H, eye)
        direction, not_pd = _cholesky_solve(masked, -jnp.where(free, g, 0.0))
        slope = direction @ g
        candidates = jnp.clip(x[None, :] + steps[:, None] * direction[None, :], lower[None, :], upper[None, :])
        values = jax.vmap(value)(candidates)
        ok = (values - value(x) <= 0.1 * steps * slope) & jnp.isfinite(values)
        index = jnp.argmax(ok)
        x_next = jnp.where(jnp.any(ok) & ~not_pd, candidates[index], x)
        # Done when the free gradient vanishes or nothing moved (no acceptable step).
        small = jnp.linalg.norm(jnp.where(free, g, 0.0)) <= 1e-10 * (1.0 + jnp.linalg.norm(q))
        done = small | jnp.all(x_next == x) | not_pd
        return i + 1, x_next, done, failed | not_pd

    x0 = jnp.clip(jnp.where(jnp.isfinite(x_init), x_init, 0.0), lower, upper)
    init = (jnp.zeros((), jnp.int32), x0, jnp.zeros((), bool), jnp.zeros((), bool))
    _, x, _, failed = lax.while_loop(lambda c: (c[0] < max_iterations) & ~c[2], body, init)
    _, free = free_set(x)
    return x, free, failed


class DDP(eqx.Module):
    """DDP / iLQR with box control limits (Box-DDP), Levenberg-Marquardt regularization and
    a backtracking line search; see the module docstring for the algorithm.

    Attributes:
        max_iterations: iteration cap.
        th_stop: convergence threshold on the expected improvement of the full step.
        th_stop_relative: convergence threshold relative to the current cost: the solve
            also stops when the expected improvement is below ``th_stop_relative * |cost|``
            (default 0: absolute test only).
        approximation: ``"gauss_newton"`` (iLQR: first-order dynamics, exact cost
            Hessians) or ``"full"`` (DDP: adds the second derivatives of the dynamics
            contracted with the value gradient).
        reg_init, reg_min, reg_max, reg_factor: the regularization ``mu`` added to ``Quu``:
            initial value, floor, cap, and the factor of each increase or decrease.
        th_acceptstep: Armijo fraction of the expected decrease a step must achieve.
        th_stepdec, th_stepinc: steps at least / at most this decrease / increase ``mu``.
        num_step_sizes: the line search tries ``alpha = 2^0, ..., 2^-(num_step_sizes-1)``.
        line_search_batch: the line search rolls out this many step sizes at once (``vmap``),
            largest first, and takes the largest one accepted, as one at a time would (the
            same step, up to the rounding of the batched rollouts); 1: one at a time, as
            Crocoddyl. ``"auto"`` (the default): 1 on the CPU, all ``num_step_sizes`` at once
            on a GPU or TPU (decided when the solve is traced). A batch pays where the search
            often backtracks (non-smooth dynamics) and where a rollout is latency-bound (on a
            GPU ``num_step_sizes`` rollouts at once cost about one); an iteration that takes
            the full step pays for the whole batch (benchmarks/RESULTS.md).
        box_qp_iterations: iteration cap of the box QP (Box-DDP).
        node_batch_size: the Jacobians of the dynamics are computed this many nodes at a
            time (`lax.map` over batches, `vmap` within one); ``None`` (the default): all
            nodes at once (on a CPU too: though the batch waits for its slowest node, it is
            not slower than one node at a time on Solo-12). R-DDP's sampled Jacobians have their own
            ``sample_node_batch_size``.
        throw: raise a ``RuntimeError`` with the result's message when the solve does not
            succeed (otherwise inspect ``solution.result``).
    """

    max_iterations: int = eqx.field(static=True, default=100)
    th_stop: float = eqx.field(static=True, default=1e-9)
    th_stop_relative: float = eqx.field(static=True, default=0.0)
    approximation: str = eqx.field(static=True, default="gauss_newton")
    reg_init: float = eqx.field(static=True, default=1e-9)
    reg_min: float = eqx.field(static=True, default=1e-9)
    reg_max: float = eqx.field(static=True, default=1e9)
    reg_factor: float = eqx.field(static=True, default=10.0)
    th_acceptstep: float = eqx.field(static=True, default=0.1)
    th_stepdec: float = eqx.field(static=True, default=0.5)
    th_stepinc: float = eqx.field(static=True, default=0.01)
    num_step_sizes: int = eqx.field(static=True, default=10)
    line_search_batch: int | Literal["auto"] = eqx.field(static=True, default="auto")
    box_qp_iterations: int = eqx.field(static=True, default=30)
    node_batch_size: int | None = eqx.field(static=True, default=None)
    throw: bool = eqx.field(static=True, default=True)

    # R-DDP draws samples: its state carries a key.
    _needs_key: ClassVar[bool] = False

    def __check_init__(self):
        names = ("max_iterations", "num_step_sizes", "box_qp_iterations")
        if self.line_search_batch != "auto":
            names += ("line_search_batch",)
        if self.node_batch_size is not None:
            names += ("node_batch_size",)
        for name in names:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be an int >= 1, got {value!r}")
        if self.approximation not in APPROXIMATIONS:
            raise ValueError(f"approximation must be one of {APPROXIMATIONS}, got {self.approximation!r}")
        if not self.th_stop >= 0:
            raise ValueError(f"th_stop must be >= 0, got {self.th_stop}")
        if not 0 <= self.th_stop_relative < 1:
            raise ValueError(f"th_stop_relative must be in [0, 1), got {self.th_stop_relative}")
        if not 0 < self.reg_min <= self.reg_max:
            raise ValueError(f"need 0 < reg_min <= reg_max, got reg_min={self.reg_min}, reg_max={self.reg_max}")
        if not 0 <= self.reg_init <= self.reg_max:
            raise ValueError(f"reg_init must be in [0, reg_max], got {self.reg_init}")
        if not self.reg_factor > 1:
            raise ValueError(f"reg_factor must be > 1, got {self.reg_factor}")
        if not 0 <= self.th_acceptstep < 1:
            raise ValueError(f"th_acceptstep must be in [0, 1), got {self.th_acceptstep}")

    # -- hooks overridden by R-DDP ---------------------------------------------------------

    def _line_search_batch(self) -> int:
        """Step sizes per batch of the line search, ``"auto"`` decided (when the solve is traced)."""
        return min(_xla.resolve_auto(self.line_search_batch, cpu=1, accelerator=self.num_step_sizes), self.num_step_sizes)

    def _initial_noise(self, dtype) -> Array:
        return jnp.zeros((), dtype)

    def _dynamics_jacobians(self, problem, state: DDPState):
        """``(fx, fu, noise_effect)`` at the nodes of the current trajectory; the noise effect
        (d f_eps / d eps) is zero without smoothing."""
        trajectory = state.trajectory
        fx, fu = dynamics_jacobians(problem, trajectory.xs, trajectory.us, self.node_batch_size)
        return fx, fu, jnp.zeros(fx.shape[:2], fx.dtype)

    def _next_noise(self, state: DDPState, stop, accepted, cost_new, d: _Derivatives) -> Array:
        return state.noise

    def _programs(self) -> tuple[DDP, DDP]:
        """The solvers whose jitted steps :func:`solve` runs: ``(smoothed, exact)``, for the
        iterations with noise > 0 and = 0. DDP has no noise: itself, twice."""
        return self, self

    # -- the solver ------------------------------------------------------------------------

    def init(self, problem: ShootingProblem, us: Array, key: Array | None = None) -> DDPState:
        """The state at the initial controls ``us`` (projected on the box)."""
        us = problem.clip(jnp.asarray(us, problem.x0.dtype))
        xs = problem.rollout(us)
        cost = problem.cost(xs, us)
        dtype = xs.dtype
        nan = jnp.full((self.max_iterations + 1,), jnp.nan, dtype)
        noise = self._initial_noise(dtype)
        reg = jnp.asarray(self.reg_init, dtype)
        history = {name: nan for name in _HISTORY}
        history["cost"] = history["cost"].at[0].set(cost)
        history["noise"] = history["noise"].at[0].set(noise)
        history["regularization"] = history["regularization"].at[0].set(reg)
        T, nx, nu = problem.horizon, problem.nx, problem.nu
        return DDPState(
            trajectory=Trajectory(xs, us, jnp.zeros((T, nu, nx), dtype), jnp.zeros((T, nu), dtype)),
            cost=cost,
            regularization=reg,
            noise=noise,
            iteration=jnp.zeros((), jnp.int32),
            expected_improvement=jnp.asarray(jnp.inf, dtype),
            step_size=jnp.zeros((), dtype),
            converged=jnp.zeros((), bool),
            result=RESULTS.successful,
            key=key,
            history=history,
        )

    def _derivatives(self, problem, state) -> _Derivatives:
        trajectory = state.trajectory
        fx, fu, noise_effect = self._dynamics_jacobians(problem, state)
        return _Derivatives(fx, fu, *_cost_derivatives(problem, trajectory.xs, trajectory.us), noise_effect)

    def _backward_pass(self, problem: ShootingProblem, state: DDPState, d: _Derivatives, reg) -> _Backward:
        nx, nu = problem.nx, problem.nu
        xs, us = state.trajectory.xs, state.trajectory.us
        eye = jnp.eye(nu, dtype=xs.dtype)
        lower, upper = problem.bounds(xs.dtype)
        full = self.approximation == "full"

        def node(carry, inputs):
            Vx, Vxx = carry
            fx, fu, lx, lu, lxx, lxu, luu, x, u, k_previous = inputs
            Qx = lx + fx.T @ Vx
            Qu = lu + fu.T @ Vx
            Qxx = lxx + fx.T @ Vxx @ fx
            Qux = lxu.T + fu.T @ Vxx @ fx
            Quu = luu + fu.T @ Vxx @ fu
            if full:
                # Second-order dynamics terms: the Hessian of V'_x . f(x, u).
                H = jax.hessian(lambda xu: Vx @ problem.dynamics.step(xu[:nx], xu[nx:]))(jnp.concatenate([x, u]))
                Qxx, Qux, Quu = Qxx + H[:nx, :nx], Qux + H[nx:, :nx], Quu + H[nx:, nx:]
            Quu_reg = Quu + reg * eye
            if problem.bounded:
                k, free, failed = box_qp(Quu_reg, Qu, lower - u, upper - u, k_previous, self.box_qp_iterations)
                masked = jnp.where(free[:, None] & free[None, :], Quu_reg, eye)
                K, failed_gains = _cholesky_solve(masked, -jnp.where(free[:, None], Qux, 0.0))
                failed = failed | failed_gains
            else:
                kK, failed = _cholesky_solve(Quu_reg, -jnp.concatenate([Qu[:, None], Qux], axis=1))
                k, K = kK[:, 0], kK[:, 1:]
            # Value update valid for any (k, K) (Tassa, Erez, Todorov 2012, Eq. 11).
            Vx_new = Qx + K.T @ (Quu @ k) + K.T @ Qu + Qux.T @ k
            Vxx_new = Qxx + K.T @ Quu @ K + K.T @ Qux + Qux.T @ K
            Vxx_new = 0.5 * (Vxx_new + Vxx_new.T)
            return (Vx_new, Vxx_new), (k, K, failed, k @ Qu, k @ (Quu @ k))

        inputs = (d.fx, d.fu, d.lx, d.lu, d.lxx, d.lxu, d.luu, xs[:-1], us, state.trajectory.feedforward)
        _, (k, K, failed, d1, d2) = lax.scan(node, (d.lTx, d.lTxx), inputs, reverse=True)
        failed = jnp.any(failed) | ~jnp.all(jnp.isfinite(k)) | ~jnp.all(jnp.isfinite(K))
        return _Backward(k, K, failed, jnp.sum(d1), jnp.sum(d2))

    def _forward_pass(self, problem: ShootingProblem, trajectory: Trajectory, k, K, alpha):
        """Rollout of the TRUE dynamics under the updated affine policy."""

        # A dynamics with step_with_info (the simulator) also flags a step that left its valid
        # range while still finite (info.diverged: e.g. more than max_motion_per_step): such
        # a trial is rejected too, not only one that reaches a non-finite state.
        step_with_info = getattr(problem.dynamics, "step_with_info", None)

        def node(carry, inputs):
            x, cost = carry
            x_bar, u_bar, k_t, K_t, t = inputs
            u = problem.clip(u_bar + alpha * k_t + K_t @ (x - x_bar))
            # A diverging trial is rejected (infinite cost), and the dynamics never see a
            # non-finite state or control: a simulator may raise on one (equinox.error_if).
            bad_control = ~jnp.all(jnp.isfinite(u))
            u = jnp.where(bad_control, u_bar, u)
            cost = cost + problem.running(x, u, t)
            if step_with_info is None:
                x_next, flagged = problem.dynamics.step(x, u), jnp.zeros((), bool)
            else:
                x_next, info = step_with_info(x, u)
                flagged = info.diverged
            diverged = bad_control | flagged | ~jnp.all(jnp.isfinite(x_next)) | ~jnp.isfinite(cost)
            x_next = jnp.where(diverged, x, x_next)
            cost = jnp.where(diverged, jnp.inf, cost)
            return (x_next, cost), (x_next, u)

        x0 = problem.x0.astype(trajectory.xs.dtype)
        init = (x0, jnp.zeros((), trajectory.xs.dtype))
        ts = jnp.arange(problem.horizon, dtype=jnp.int32)
        (x_last, cost), (xs, us) = lax.scan(node, init, (trajectory.xs[:-1], trajectory.us, k, K, ts))
        cost = cost + problem.terminal(x_last)
        return jnp.concatenate([x0[None], xs]), us, cost

    def step(self, problem: ShootingProblem, state: DDPState) -> DDPState:
        """One iteration: derivatives, backward pass (redone with more regularization while it
        fails), convergence test, line search. Pure; jit it once."""
        dtype = state.cost.dtype
        d = self._derivatives(problem, state)
        nonfinite = ~jnp.all(jnp.array([jnp.all(jnp.isfinite(a)) for a in d]))

        # The backward pass, redone with a larger regularization while it fails. One call site
        # in a while_loop (the first pass included) keeps the compiled program small.
        def attempt(carry):
            reg, _, first = carry
            reg = jnp.where(first, reg, jnp.minimum(jnp.maximum(reg * self.reg_factor, self.reg_min), self.reg_max))
            return reg, self._backward_pass(problem, state, d, reg), jnp.zeros((), bool)

        T, nx, nu = problem.horizon, problem.nx, problem.nu
        placeholder = _Backward(
            jnp.zeros((T, nu), dtype), jnp.zeros((T, nu, nx), dtype), jnp.ones((), bool), jnp.zeros((), dtype), jnp.zeros((), dtype)
        )
        reg, backward, _ = lax.while_loop(
            lambda c: c[2] | (c[1].failed & (c[0] < self.reg_max) & ~nonfinite),
            attempt,
            (state.regularization, placeholder, jnp.ones((), bool)),
        )
        failed = backward.failed | nonfinite
        improvement = jnp.where(failed, jnp.nan, -(backward.d1 + 0.5 * backward.d2))
        stop = ~failed & (improvement < jnp.maximum(self.th_stop, self.th_stop_relative * jnp.abs(state.cost)))

        # The step sizes in groups of `line_search_batch`, the last group padded with smaller
        # ones that are never accepted.
        batch = self._line_search_batch()
        groups = -(-self.num_step_sizes // batch)
        alphas = 2.0 ** -jnp.arange(groups * batch, dtype=dtype)
        trajectory = state.trajectory

        def trial(alpha):
            xs_new, us_new, cost_new = self._forward_pass(problem, trajectory, backward.feedforward, backward.gains, alpha)
            expected = -(alpha * backward.d1 + 0.5 * alpha**2 * backward.d2)
            accepted = jnp.isfinite(cost_new) & (state.cost - cost_new >= self.th_acceptstep * jnp.maximum(expected, 0.0))
            return accepted, xs_new, us_new, cost_new

        def try_group(carry):
            group, _, _, xs, us, cost = carry
            index = group * batch + jnp.arange(batch, dtype=jnp.int32)
            if batch == 1:  # no vmap: the rollouts of the sequential search, bit for bit
                outputs = jax.tree.map(lambda a: a[None], trial(alphas[index[0]]))
            else:
                outputs = jax.vmap(trial)(alphas[index])
            accepted = outputs[0] & (index < self.num_step_sizes)
            first = jnp.argmax(accepted)  # the largest accepted step size of the group
            _, xs_new, us_new, cost_new = jax.tree.map(lambda a: a[first], outputs)
            return group + 1, jnp.any(accepted), index[first], xs_new, us_new, cost_new

        init = (jnp.zeros((), jnp.int32), jnp.zeros((), bool), jnp.zeros((), jnp.int32), trajectory.xs, trajectory.us, state.cost)
        _, accepted, chosen, xs_new, us_new, cost_new = lax.while_loop(
            lambda c: ~c[1] & (c[0] < groups) & ~stop & ~failed, try_group, init
        )
        alpha = jnp.where(accepted, alphas[chosen], 0.0)

        # Levenberg-Marquardt schedule (Crocoddyl): decrease after a large step, increase
        # after a small or failed one; keep it after a convergence test.
        increased = jnp.minimum(jnp.maximum(reg * self.reg_factor, self.reg_min), self.reg_max)
        decreased = jnp.minimum(reg, jnp.maximum(reg / self.reg_factor, self.reg_min))
        reg_next = jnp.where(
            stop | failed,
            reg,
            jnp.where(accepted & (alpha >= self.th_stepdec), decreased, jnp.where(~accepted | (alpha <= self.th_stepinc), increased, reg)),
        )

        keep = lambda new, old: jnp.where(accepted, new, old)  # noqa: E731
        cost_next = keep(cost_new, state.cost)
        noise_next = self._next_noise(state, stop, accepted, cost_next, d)
        converged = stop & (state.noise == 0)
        result = RESULTS.where(
            nonfinite,
            RESULTS.nonfinite,
            RESULTS.where(backward.failed, RESULTS.regularization_exceeded, RESULTS.successful),
        )
        new_trajectory = Trajectory(
            xs=keep(xs_new, trajectory.xs),
            us=keep(us_new, trajectory.us),
            gains=jnp.where(failed, trajectory.gains, backward.gains),
            feedforward=jnp.where(failed, trajectory.feedforward, backward.feedforward),
        )
        index = state.iteration + 1
        record = {
            "cost": cost_next,
            "noise": noise_next,
            "step_size": alpha,
            "regularization": reg_next,
            "expected_improvement": improvement,
        }
        history = {name: state.history[name].at[index].set(record[name].astype(dtype)) for name in _HISTORY}
        return DDPState(
            trajectory=new_trajectory,
            cost=cost_next,
            regularization=reg_next,
            noise=noise_next,
            iteration=index,
            expected_improvement=improvement,
            step_size=alpha,
            converged=converged,
            result=result,
            key=state.key,
            history=history,
        )

    def terminate(self, state: DDPState) -> Array:
        """True once converged, failed, or at ``max_iterations``."""
        return state.converged | (state.result != RESULTS.successful) | (state.iteration >= self.max_iterations)

    def postprocess(self, state: DDPState, times=None) -> Solution:
        """The :class:`Solution` (histories cut to the iterations done; call it outside `jit`)."""
        iterations = int(state.iteration)
        result = RESULTS.where(
            (state.result == RESULTS.successful) & ~state.converged,
            RESULTS.max_iterations_reached,
            state.result,
        )
        stats = {name: state.history[name][: iterations + 1] for name in _HISTORY}
        times = np.asarray([] if times is None else times, dtype=float)
        stats.update(
            iterations=iterations,
            converged=bool(state.converged),
            time_per_iteration=times,
            total_time=float(np.sum(times)),
        )
        return Solution(value=state.trajectory, result=result, stats=stats, state=state)


# The solver tests every rollout for finiteness and reports it (RESULTS.nonfinite, rejected
# trials), so the dynamics' own traced checks are left out of its programs: without host
# callbacks, JAX's persistent compilation cache can keep them between runs.
@eqx.filter_jit
def _jitted_step(solver, problem, state):
    with _checks.without_traced_checks():
        return solver.step(problem, state)


@eqx.filter_jit
def _jitted_init(solver, problem, us, key):
    with _checks.without_traced_checks():
        return solver.init(problem, us, key)


def _tqdm_callback(total: int, description: str):
    from tqdm.auto import tqdm  # optional: only needed for progress=True

    bar = tqdm(total=total, desc=description, leave=False)

    def callback(info):
        bar.update(1)
        bar.set_postfix(cost=f"{info['cost']:.4g}", eps=f"{info['noise']:.3g}", step=f"{info['step_size']:.3g}")

    return bar, callback


def solve(
    solver: DDP,
    problem: ShootingProblem,
    us_init,
    key,
    callback: Callable[[dict], None] | None,
    progress: bool,
    description: str,
) -> Solution:
    """The host loop shared by :func:`ddp` and :func:`~rsmooth.control.rddp`."""
    if not isinstance(problem, ShootingProblem):
        raise TypeError(f"problem must be a ShootingProblem, got {type(problem).__name__}")
    if us_init is None:
        us = jnp.zeros((problem.horizon, problem.nu), problem.x0.dtype)
    else:
        us = problem.check_controls(us_init)
    # `throw` does not change the program: one compilation serves both values.
    compiled_solver = dataclasses.replace(solver, throw=True)
    smoothed_program, exact_program = compiled_solver._programs()
    # The initial rollout is the same for every solver with the same DDP options: DDP's
    # program computes it (compiled once per problem), then the noise and key are set.
    state = _jitted_init(exact_program, problem, us, None)
    if smoothed_program is not exact_program:
        noise = compiled_solver._initial_noise(state.cost.dtype)
        history = {**state.history, "noise": state.history["noise"].at[0].set(noise)}
        state = dataclasses.replace(state, noise=noise, key=key, history=history)
    if not np.isfinite(float(state.cost)):
        raise ValueError("the cost of the initial rollout (x0, us_init) is not finite")
    bar = None
    callbacks = [callback] if callback is not None else []
    if progress:
        bar, bar_callback = _tqdm_callback(solver.max_iterations, description)
        callbacks.append(bar_callback)
    times = []
    try:
        while not bool(solver.terminate(state)):
            start = time.perf_counter()
            if exact_program is smoothed_program or float(state.noise) > 0:
                state = _jitted_step(smoothed_program, problem, state)
            else:
                # R-DDP's eps = 0 iterations are DDP's: they run DDP's program (compiled
                # once, and shared with a DDP solve of the same problem), without the key.
                key = state.key
                state = _jitted_step(exact_program, problem, dataclasses.replace(state, key=None))
                state = dataclasses.replace(state, key=key)
            state = jax.block_until_ready(state)
            times.append(time.perf_counter() - start)
            if callbacks:
                info = {
                    "iteration": int(state.iteration),
                    "cost": float(state.cost),
                    "noise": float(state.noise),
                    "step_size": float(state.step_size),
                    "regularization": float(state.regularization),
                    "expected_improvement": float(state.expected_improvement),
                    "time": times[-1],
                }
                for function in callbacks:
                    function(info)
    finally:
        if bar is not None:
            bar.close()
    solution = solver.postprocess(state, times)
    if solver.throw and not bool(solution.result == RESULTS.successful):
        raise RuntimeError(_failure_message(description, solution.result))
    return solution


def ddp(
    problem: ShootingProblem,
    us_init: Array | None = None,
    *,
    solver: DDP = DDP(),
    callback: Callable[[dict], None] | None = None,
    progress: bool = False,
) -> Solution:
    """Solves a shooting problem by DDP / iLQR (Box-DDP with control limits).

    Args:
        problem: the :class:`~rsmooth.control.ShootingProblem`.
        us_init: initial controls ``(T, nu)`` (default zeros), projected on the box.
        solver: the :class:`DDP` configuration (``throw``, thresholds, caps).
        callback: called after each iteration with a dict of floats: ``iteration``,
            ``cost``, ``noise``, ``step_size``, ``regularization``,
            ``expected_improvement``, ``time``.
        progress: show a `tqdm` progress bar (imported only then).

    Returns:
        A :class:`Solution`.

    Raises:
        ValueError: on a wrong shape or non-finite ``us_init``, or a non-finite initial cost.
        RuntimeError: with ``solver.throw`` (default), when the solve does not succeed.
    """
    if not isinstance(solver, DDP) or solver._needs_key:
        raise TypeError(f"solver must be a DDP (use rddp for an RDDP), got {type(solver).__name__}")
    return solve(solver, problem, us_init, None, callback, progress, "ddp")
