"""The shooting problem: dynamics, running and terminal costs, horizon, initial state.

Vocabulary of Crocoddyl (Mastalli et al., ICRA 2020): a *shooting problem* is a sequence of
``T`` running nodes ``(x_t, u_t) -> (l(x_t, u_t), f(x_t, u_t))`` and a terminal node
``x_T -> l_T(x_T)``; its cost is

.. math:: J(u_{0:T-1}) = \\sum_{t=0}^{T-1} l(x_t, u_t) + l_T(x_T),
    \\qquad x_{t+1} = f(x_t, u_t),\\ x_0 \\text{ given}.
"""

from __future__ import annotations

from typing import Any, Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.typing import ArrayLike

from rsmooth import _checks
from rsmooth._xla import device_array

__all__ = ["ShootingProblem"]


def _bound(value, nu: int, name: str):
    if value is None:
        return None
    array = np.broadcast_to(np.asarray(value, dtype=float), (nu,)) if np.ndim(value) == 0 else np.asarray(value, dtype=float)
    if array.shape != (nu,):
        raise ValueError(f"{name} must be a scalar or have shape (nu,) = ({nu},), got {array.shape}")
    if np.any(np.isnan(array)):
        raise ValueError(f"{name} must not contain NaN")
    return device_array(array)


def check_initial_state(x0: ArrayLike, nx: int) -> Array:
    """``x0`` as a floating array of shape ``(nx,)``, checked finite (now when concrete, at run
    time under `jit` or `vmap`). Raises ``ValueError`` naming ``x0``."""
    if np.shape(x0) != (nx,):
        raise ValueError(f"x0 must have shape (nx,) = ({nx},), got {np.shape(x0)}")
    x0 = jnp.asarray(x0)
    if not jnp.issubdtype(x0.dtype, jnp.floating):
        x0 = x0.astype(float)
    return _checks.check_finite(x0, "x0 must be finite (it contains NaN or inf)")


class ShootingProblem(eqx.Module):
    """An optimal control problem over a finite horizon (single shooting).

    Attributes:
        dynamics: any pytree with ``step(x, u) -> x_next`` (pure JAX) and int attributes
            ``nx`` and ``nu``; optionally ``step_and_jacobians(x, u) -> (x_next, f_x, f_u)``,
            which the solvers then use instead of autodiff of ``step`` (the simulator's
            :meth:`~rsmooth.sim.RigidBodySystem.step_and_jacobians`); optionally
            ``project_state(x) -> x``, which R-DDP applies to every perturbed state before
            stepping from it (:meth:`~rsmooth.sim.RigidBodySystem.project_state`: unit
            quaternions); optionally ``step_with_info(x, u) -> (x_next, info)`` with a boolean
            ``info.diverged``, with which DDP's line search rejects a trial at its first
            flagged step, finite or not (the simulator's ``max_motion_per_step``).
        running_cost: ``l(x, u) -> scalar``, differentiable twice by JAX (its gradient and
            Hessian come from autodiff); ``l(x, u, t)`` with ``time_varying=True``.
        terminal_cost: ``l_T(x) -> scalar``, differentiable twice by JAX.
        x0: the initial state, shape ``(nx,)``, finite (may be traced: the problem can be
            built inside `jit` or `vmap`).
        horizon: the number ``T`` of running nodes (controls).
        control_lower, control_upper: box limits on every ``u_t`` (scalars or shape
            ``(nu,)``; ``None`` or infinite entries for none). With finite limits the solvers
            run Box-DDP (Tassa, Mansard, Todorov, ICRA 2014).
        time_varying: the running cost takes the node index ``t`` (an int32 array, from 0 to
            ``T - 1``) as a third argument, e.g. to track a reference ``x_ref[t]``.
        params: ``None``, or a pytree of arrays (targets, weights, references) that both
            costs then take as their last argument: ``l(x, u[, t], params)`` and
            ``l_T(x, params)``. Its arrays are traced, so problems that differ only in them
            (another target, another foot) share one compiled solver step.
        residuals: the two cost functions return residual vectors ``r`` rather than scalars,
            and the cost of a node is ``0.5 * ||r||^2`` (Crocoddyl's residual
            models with a quadratic activation). The solvers then use the Gauss-Newton
            Hessians ``r_x^T r_x`` (positive semi-definite), not the exact ones, whose
            curvature terms make ``Q_uu`` indefinite far from the target (e.g. a squared
            foot-height error through the forward kinematics).
        bounded: whether some limit is finite (set by the constructor).

    The cost functions are static parts of the problem (compared by identity): define them
    once, not anew for every solve, so that later solves reuse the compiled solver step; the
    arrays (``x0``, the limits, ``params``, the arrays inside ``dynamics``) may change freely.

    Raises:
        ValueError: when ``x0`` has not the shape ``(nx,)`` or is not finite, when
            ``horizon < 1``, or when the limits have a wrong shape or ``lower > upper``.

    Example:
        >>> import jax.numpy as jnp
        >>> from rsmooth.control import ShootingProblem
        >>> class Integrator:
        ...     nx, nu = 1, 1
        ...     def step(self, x, u):
        ...         return x + 0.1 * u
        >>> problem = ShootingProblem(Integrator(), lambda x, u: jnp.sum(u**2),
        ...                           lambda x: jnp.sum((x - 1.0) ** 2), jnp.zeros(1), horizon=5)
        >>> xs = problem.rollout(jnp.ones((5, 1)))
        >>> xs.shape, round(float(xs[-1, 0]), 6), round(float(problem.cost(xs, jnp.ones((5, 1)))), 6)
        ((6, 1), 0.5, 5.25)
    """

    dynamics: Any
    running_cost: Callable = eqx.field(static=True)
    terminal_cost: Callable = eqx.field(static=True)
    x0: Array
    horizon: int = eqx.field(static=True)
    control_lower: Array | None = None
    control_upper: Array | None = None
    time_varying: bool = eqx.field(static=True, default=False)
    residuals: bool = eqx.field(static=True, default=False)
    bounded: bool = eqx.field(static=True, default=False)
    params: Any = None

    def __init__(
        self,
        dynamics,
        running_cost: Callable,
        terminal_cost: Callable,
        x0: ArrayLike,
        horizon: int,
        *,
        control_lower: ArrayLike | None = None,
        control_upper: ArrayLike | None = None,
        time_varying: bool = False,
        residuals: bool = False,
        params: Any = None,
    ):
        for attribute in ("nx", "nu"):
            if not isinstance(getattr(dynamics, attribute, None), (int, np.integer)):
                raise TypeError(f"dynamics must have an int attribute {attribute!r}")
        if not callable(getattr(dynamics, "step", None)):
            raise TypeError("dynamics must have a method step(x, u) -> x_next")
        if not callable(running_cost) or not callable(terminal_cost):
            raise TypeError("running_cost and terminal_cost must be callable")
        nx, nu = int(dynamics.nx), int(dynamics.nu)
        if isinstance(horizon, bool) or not isinstance(horizon, (int, np.integer)) or horizon < 1:
            raise ValueError(f"horizon must be an int >= 1, got {horizon!r}")
        x0 = check_initial_state(x0, nx)
        lower = _bound(control_lower, nu, "control_lower")
        upper = _bound(control_upper, nu, "control_upper")
        if lower is not None and upper is not None and np.any(np.asarray(lower) > np.asarray(upper)):
            raise ValueError("control_lower must be <= control_upper")
        self.dynamics = dynamics
        self.running_cost = running_cost
        self.terminal_cost = terminal_cost
        self.x0 = x0
        self.horizon = int(horizon)
        self.control_lower = lower
        self.control_upper = upper
        self.time_varying = bool(time_varying)
        self.residuals = bool(residuals)
        self.params = params
        # Whether some limit is finite (then the solvers solve box QPs); static, as it
        # changes the program.
        self.bounded = any(b is not None and bool(np.any(np.isfinite(np.asarray(b)))) for b in (lower, upper))

    @property
    def nx(self) -> int:
        return int(self.dynamics.nx)

    @property
    def nu(self) -> int:
        return int(self.dynamics.nu)

    def bounds(self, dtype=None) -> tuple[Array, Array]:
        """The limits as two arrays ``(nu,)``, infinite where there is none."""
        dtype = dtype or self.x0.dtype
        lower = jnp.full((self.nu,), -jnp.inf, dtype) if self.control_lower is None else self.control_lower.astype(dtype)
        upper = jnp.full((self.nu,), jnp.inf, dtype) if self.control_upper is None else self.control_upper.astype(dtype)
        return lower, upper

    def clip(self, us: Array) -> Array:
        """Controls (one ``(nu,)`` or many ``(..., nu)``) projected on the box."""
        if not self.bounded:
            return us
        lower, upper = self.bounds(us.dtype)
        return jnp.clip(us, jnp.broadcast_to(lower, us.shape), jnp.broadcast_to(upper, us.shape))

    def rollout(self, us: Array) -> Array:
        """States ``(T + 1, nx)`` from ``x0`` under controls ``us`` ``(T, nu)`` (no clipping)."""

        def body(x, u):
            x_next = self.dynamics.step(x, u)
            return x_next, x_next

        _, xs = jax.lax.scan(body, self.x0.astype(us.dtype), us)
        return jnp.concatenate([self.x0.astype(us.dtype)[None], xs])

    def running_residual(self, x: Array, u: Array, t: Array) -> Array:
        """What ``running_cost`` returns at node ``t`` (a residual vector with ``residuals``)."""
        args = (x, u, t) if self.time_varying else (x, u)
        return self.running_cost(*args) if self.params is None else self.running_cost(*args, self.params)

    def terminal_residual(self, x: Array) -> Array:
        """What ``terminal_cost`` returns (a residual vector with ``residuals``)."""
        return self.terminal_cost(x) if self.params is None else self.terminal_cost(x, self.params)

    def running(self, x: Array, u: Array, t: Array) -> Array:
        """The running cost of node ``t`` (a scalar)."""
        value = self.running_residual(x, u, t)
        return 0.5 * jnp.sum(value**2) if self.residuals else value

    def terminal(self, x: Array) -> Array:
        """The terminal cost (a scalar)."""
        value = self.terminal_residual(x)
        return 0.5 * jnp.sum(value**2) if self.residuals else value

    def cost(self, xs: Array, us: Array) -> Array:
        """The total cost ``sum_t l(x_t, u_t) + l_T(x_T)`` of a trajectory."""
        running = jax.vmap(self.running)(xs[:-1], us, jnp.arange(self.horizon, dtype=jnp.int32))
        return jnp.sum(running) + self.terminal(xs[-1])

    def check_controls(self, us, name: str = "us_init") -> Array:
        """Host check of an initial control sequence: shape ``(T, nu)``, finite."""
        array = np.asarray(us)
        shape = (self.horizon, self.nu)
        if array.shape != shape:
            raise ValueError(f"{name} must have shape (horizon, nu) = {shape}, got {array.shape}")
        if not np.issubdtype(array.dtype, np.floating):
            array = array.astype(float)
        if not np.all(np.isfinite(array)):
            raise ValueError(f"{name} must be finite (it contains NaN or inf)")
        return jnp.asarray(array, dtype=self.x0.dtype)
