"""Small dynamics for the control tests: a linear system, a pendulum, a cube lifted off a floor."""

import functools
from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from rsmooth.control import ShootingProblem


class Linear(eqx.Module):
    """x_next = A x + B u; `Linear.traces[0]` counts how many times JAX traced `step`."""

    A: jnp.ndarray
    B: jnp.ndarray
    nx: int = eqx.field(static=True)
    nu: int = eqx.field(static=True)
    traces: ClassVar[list] = [0]

    def step(self, x, u):
        self.traces[0] += 1
        return self.A @ x + self.B @ u


# Cached: the solvers compile once per problem structure (its cost functions are static),
# so the tests share one compilation per problem.
@functools.lru_cache
def linear_quadratic(seed=0, nx=4, nu=2, horizon=15):
    """A random LQ problem and its (A, B, Q, R, Qf) in NumPy."""
    rng = np.random.default_rng(seed)
    A = np.eye(nx) + 0.1 * rng.standard_normal((nx, nx))
    B = 0.1 * rng.standard_normal((nx, nu))
    M = rng.standard_normal((nx, nx))
    Q = 0.1 * (M @ M.T) + 0.1 * np.eye(nx)
    R = 0.01 * np.eye(nu) + 0.005 * np.ones((nu, nu))
    Qf = 10.0 * np.eye(nx)
    x0 = rng.standard_normal(nx)
    problem = ShootingProblem(
        Linear(jnp.asarray(A), jnp.asarray(B), nx, nu),
        running_cost=lambda x, u: 0.5 * x @ (Q @ x) + 0.5 * u @ (R @ u),
        terminal_cost=lambda x: 0.5 * x @ (Qf @ x),
        x0=x0,
        horizon=horizon,
    )
    return problem, (A, B, Q, R, Qf)


def riccati(A, B, Q, R, Qf, x0, horizon):
    """Finite-horizon discrete LQR by the backward Riccati recursion, in NumPy: the gains,
    the states, the controls and the cost. `Q` may be one matrix or one per node."""
    Qs = np.broadcast_to(Q, (horizon,) + np.shape(Q)[-2:])
    P = Qf
    gains = []
    for t in reversed(range(horizon)):
        K = -np.linalg.solve(R + B.T @ P @ B, B.T @ P @ A)
        P = Qs[t] + A.T @ P @ (A + B @ K)
        gains.append(K)
    gains = gains[::-1]
    xs, us = [x0], []
    for K in gains:
        us.append(K @ xs[-1])
        xs.append(A @ xs[-1] + B @ us[-1])
    cost = sum(0.5 * x @ Qt @ x + 0.5 * u @ R @ u for x, u, Qt in zip(xs[:-1], us, Qs)) + 0.5 * xs[-1] @ Qf @ xs[-1]
    return np.array(gains), np.array(xs), np.array(us), cost


class Pendulum(eqx.Module):
    """theta'' = -(g / l) sin(theta) - b theta' + u / (m l^2), semi-implicit Euler;
    theta = 0 hangs down."""

    dt: float = 0.05
    nx: int = eqx.field(static=True, default=2)
    nu: int = eqx.field(static=True, default=1)

    def step(self, x, u):
        theta, omega = x[0], x[1]
        omega = omega + self.dt * (-9.81 * jnp.sin(theta) - 0.1 * omega + u[0])
        return jnp.stack([theta + self.dt * omega, omega])


@functools.lru_cache
def pendulum_swing_up(horizon=50, control_limit=None):
    """Swing the pendulum up (theta = pi, at rest) from hanging down."""
    target = jnp.array([jnp.pi, 0.0])
    limit = {} if control_limit is None else dict(control_lower=-control_limit, control_upper=control_limit)
    return ShootingProblem(
        Pendulum(),
        running_cost=lambda x, u: 1e-2 * jnp.sum(u**2) + 1e-2 * jnp.sum((x - target) ** 2),
        terminal_cost=lambda x: 100.0 * jnp.sum((x - target) ** 2),
        x0=jnp.zeros(2),
        horizon=horizon,
        **limit,
    )


class CubeLift(eqx.Module):
    """A cube of mass m on a floor, pushed up by a vertical force u.

    The floor's normal force is max(0, m g - u) while the cube rests on it, so below u = m g
    nothing moves and the derivative of the next state with respect to u is exactly zero.
    """

    mass: float = 1.0
    gravity: float = 9.81
    dt: float = 0.05
    nx: int = eqx.field(static=True, default=2)
    nu: int = eqx.field(static=True, default=1)

    def step(self, x, u):
        z, v = x[0], x[1]
        weight = self.mass * self.gravity
        normal = jnp.where(z <= 0.0, jnp.maximum(0.0, weight - u[0]), 0.0)
        v_next = v + self.dt * (u[0] + normal - weight) / self.mass
        z_free = z + self.dt * v_next
        # A hard floor: the cube stops on it (plastic impact).
        return jnp.stack([jnp.maximum(z_free, 0.0), jnp.where(z_free < 0.0, 0.0, v_next)])


@functools.lru_cache
def cube_lift(horizon=20, target=0.5):
    """Lift the cube to `target` at rest at the end of the horizon, with small forces."""
    return ShootingProblem(
        CubeLift(),
        running_cost=lambda x, u: 1e-3 * jnp.sum(u**2),
        terminal_cost=lambda x: 100.0 * (x[0] - target) ** 2 + 1.0 * x[1] ** 2,
        x0=jnp.zeros(2),
        horizon=horizon,
    )
