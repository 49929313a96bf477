r"""Policy optimization with first-, zeroth- and alpha-order estimates of the smoothed gradient.

A *policy* is a parametrized feedback law :math:`u_t = \pi(\theta, x_t, t)`: any callable
``policy(theta, x, t) -> u`` with ``theta`` a pytree of floating arrays, ``x`` the state
``(nx,)``, ``t`` the node index (an int32 array) and ``u`` the control ``(nu,)``. Two are
provided, both frozen Equinox modules with an ``init()`` that gives zero parameters (and so
their shapes, which are checked):

* :class:`OpenLoop`: :math:`u_t = \theta_t`, ``theta`` of shape ``(T, nu)``;
* :class:`LinearFeedback`: :math:`u_t = K x_t + k`, or :math:`K_t x_t + k_t` per node,
  ``theta = {"gain": K, "offset": k}``.

On a :class:`~rsmooth.control.ShootingProblem` (dynamics, costs, ``x0``, horizon ``T``) the
objective of a policy is the total cost of its closed-loop rollout,

.. math:: V(\theta) = \sum_{t=0}^{T-1} l(x_t, u_t) + l_T(x_T), \qquad
    u_t = \mathrm{clip}(\pi(\theta, x_t, t)),\ x_{t+1} = f(x_t, u_t),

(:func:`rollout`, :func:`policy_cost`). Through contact :math:`V` is non-smooth, even
discontinuous; :func:`policy_gradient` estimates the gradient of its randomized smoothing
:math:`V_\sigma(\theta) = \mathbb{E}_w V(\theta + \sigma w)` with one of the estimators of
:mod:`rsmooth.estimators`, the samples batched with `vmap`:

* ``"first"``: the mean of exact gradients of sampled rollouts (autodiff through the
  simulator): low variance, but biased where :math:`V` jumps (it does not see the jump);
* ``"zeroth"``: the score-function estimate with a baseline: unbiased, higher variance;
* ``"alpha"``: their blend, alpha chosen from the two empirical variances inside the
  empirical-bias trust region of Suh et al. (alpha = 0 when the first-order estimate
  disagrees with the zeroth-order one by more than sampling noise explains).

:func:`optimize_policy` (configured by :class:`PolicyGradient`) runs Adam (`optax`) on these
estimates, a :mod:`rsmooth.schedules` schedule owning :math:`\sigma`, and returns a
:class:`PolicySolution` with the histories of the parameters, the true cost, :math:`\sigma`,
alpha and the estimated variance of the gradient.

Example:
    >>> import jax, jax.numpy as jnp
    >>> from rsmooth import control
    >>> class Integrator:
    ...     nx, nu = 1, 1
    ...     def step(self, x, u):
    ...         return x + 0.1 * u
    >>> problem = control.ShootingProblem(Integrator(), lambda x, u: 1e-3 * jnp.sum(u**2),
    ...                                   lambda x: jnp.sum((x - 1.0) ** 2), jnp.zeros(1), horizon=5)
    >>> policy = control.OpenLoop(horizon=5, nu=1)
    >>> solver = control.PolicyGradient(estimator="alpha", sigma=0.1, num_samples=8,
    ...                                 learning_rate=0.5, iterations=40)
    >>> solution = control.optimize_policy(problem, policy, jax.random.key(0), policy.init(), solver=solver)
    >>> bool(solution.stats["cost"][-1] < 0.05 * solution.stats["cost"][0])
    True

References:
    H. J. T. Suh, M. Simchowitz, K. Zhang, R. Tedrake, "Do differentiable simulators give
    better policy gradients?", ICML 2022.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from typing import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax import Array, lax
from jax.flatten_util import ravel_pytree
from jax.sharding import Mesh
from jax.typing import ArrayLike

from rsmooth import _checks, parallel
from rsmooth import estimators as _estimators
from rsmooth._results import RESULTS
from rsmooth import schedules as _schedules
from rsmooth.control._problem import ShootingProblem, check_initial_state
from rsmooth.noise import Gaussian, Noise

__all__ = [
    "LinearFeedback",
    "OpenLoop",
    "PolicyGradient",
    "PolicySolution",
    "optimize_policy",
    "policy_cost",
    "policy_gradient",
    "rollout",
]

ESTIMATORS = ("first", "zeroth", "alpha")
_METHODS = {
    "first": _estimators.first_order,
    "zeroth": _estimators.zeroth_order,
    "alpha": _estimators.alpha_order,
}


def _check_size(value, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ValueError(f"{name} must be an int >= 1, got {value!r}")
    return int(value)


class OpenLoop(eqx.Module):
    """The open-loop, time-varying policy :math:`u_t = \\theta_t`: ``theta`` is ``(T, nu)``.

    Attributes:
        horizon: ``T``, the number of controls.
        nu: the control dimension.

    Example:
        >>> import jax.numpy as jnp
        >>> policy = OpenLoop(horizon=3, nu=2)
        >>> theta = jnp.arange(6.0).reshape(3, 2)
        >>> policy(theta, jnp.zeros(4), 1).tolist()
        [2.0, 3.0]
    """

    horizon: int = eqx.field(static=True)
    nu: int = eqx.field(static=True)

    def __check_init__(self):
        _check_size(self.horizon, "horizon")
        _check_size(self.nu, "nu")

    def init(self, dtype=float) -> Array:
        """Zero parameters, shape ``(horizon, nu)``."""
        return jnp.zeros((self.horizon, self.nu), dtype)

    def __call__(self, theta: Array, x: Array, t: ArrayLike) -> Array:
        return theta[t]


class LinearFeedback(eqx.Module):
    """The affine state feedback :math:`u = K x + k`, time-invariant or one per node.

    ``theta = {"gain": K, "offset": k}`` with ``K`` of shape ``(nu, nx)`` and ``k`` ``(nu,)``,
    or, with ``horizon=T``, ``(T, nu, nx)`` and ``(T, nu)`` (node ``t`` uses ``K_t, k_t``).

    Attributes:
        nx: the state dimension.
        nu: the control dimension.
        horizon: ``None`` (time-invariant) or the number of nodes ``T``.

    Example:
        >>> import jax.numpy as jnp
        >>> policy = LinearFeedback(nx=2, nu=1)
        >>> theta = {"gain": jnp.array([[-1.0, -2.0]]), "offset": jnp.array([0.5])}
        >>> policy(theta, jnp.array([1.0, 1.0]), 0).tolist()
        [-2.5]
    """

    nx: int = eqx.field(static=True)
    nu: int = eqx.field(static=True)
    horizon: int | None = eqx.field(static=True, default=None)

    def __check_init__(self):
        _check_size(self.nx, "nx")
        _check_size(self.nu, "nu")
        if self.horizon is not None:
            _check_size(self.horizon, "horizon")

    def init(self, dtype=float) -> dict:
        """Zero gain and offset, shapes ``(nu, nx)`` and ``(nu,)`` (``T`` first per node)."""
        lead = () if self.horizon is None else (self.horizon,)
        return {"gain": jnp.zeros(lead + (self.nu, self.nx), dtype), "offset": jnp.zeros(lead + (self.nu,), dtype)}

    def __call__(self, theta: dict, x: Array, t: ArrayLike) -> Array:
        gain, offset = theta["gain"], theta["offset"]
        if self.horizon is not None:
            gain, offset = gain[t], offset[t]
        return gain @ x + offset


def _shapes(tree) -> str:
    return str(jax.tree.map(lambda leaf: tuple(np.shape(leaf)), tree))


def check_parameters(policy: Callable, theta, name: str = "theta"):
    """Host check of policy parameters: floating arrays, finite, and, for a policy with an
    ``init()``, of its structure and shapes. Returns ``theta`` as JAX arrays."""
    _checks.check_floating_tree(theta, name)
    init = getattr(policy, "init", None)
    if callable(init):
        expected = jax.eval_shape(init)
        same_structure = jax.tree.structure(expected) == jax.tree.structure(theta)
        if not same_structure or any(
            np.shape(a) != b.shape for a, b in zip(jax.tree.leaves(theta), jax.tree.leaves(expected))
        ):
            raise ValueError(
                f"{name} must have the structure and shapes of policy.init(), {_shapes(expected)}, got {_shapes(theta)}"
            )
    message = f"{name} must be finite (it contains NaN or inf)"
    return jax.tree.map(lambda leaf: _checks.check_finite(jnp.asarray(leaf), message), theta)


def _check_policy_output(policy, theta, x0, nu: int) -> None:
    out = jax.eval_shape(policy, theta, x0, jnp.zeros((), jnp.int32))
    if getattr(out, "shape", None) != (nu,):
        raise ValueError(f"policy(theta, x, t) must return a control of shape (nu,) = ({nu},), got {_shapes(out)}")


def _rollout(dynamics, policy, theta, x0: Array, horizon: int, clip=None) -> tuple[Array, Array]:
    def body(x, t):
        u = policy(theta, x, t)
        u = u if clip is None else clip(u)
        x_next = dynamics.step(x, u)
        return x_next, (x_next, u)

    _, (xs, us) = lax.scan(body, x0, jnp.arange(horizon, dtype=jnp.int32))
    return jnp.concatenate([x0[None], xs]), us


def rollout(dynamics, policy: Callable, theta, x0: ArrayLike, horizon: int) -> tuple[Array, Array]:
    """The closed-loop trajectory of a policy: :math:`u_t = \\pi(\\theta, x_t, t)`,
    :math:`x_{t+1} = f(x_t, u_t)`, one `lax.scan` (jit and vmap it freely).

    Args:
        dynamics: any pytree with ``step(x, u) -> x_next`` and int attributes ``nx``, ``nu``.
        policy: ``policy(theta, x, t) -> u``, ``u`` of shape ``(nu,)``.
        theta: the policy parameters (checked against ``policy.init()`` when it has one).
        x0: the initial state ``(nx,)``, finite.
        horizon: the number ``T`` of steps.

    Returns:
        ``(xs, us)``: the states ``(T + 1, nx)`` (``xs[0] = x0``) and controls ``(T, nu)``.

    Raises:
        ValueError: on a wrong ``x0`` shape, a non-finite ``x0`` or ``theta``, a ``theta`` of
            the wrong shapes, or a policy whose output is not ``(nu,)``.

    Example:
        >>> import jax.numpy as jnp
        >>> class Integrator:
        ...     nx, nu = 1, 1
        ...     def step(self, x, u):
        ...         return x + u
        >>> xs, us = rollout(Integrator(), OpenLoop(horizon=3, nu=1), jnp.ones((3, 1)), jnp.zeros(1), 3)
        >>> xs[:, 0].tolist(), us.shape
        ([0.0, 1.0, 2.0, 3.0], (3, 1))
    """
    horizon = _check_size(horizon, "horizon")
    nx, nu = int(dynamics.nx), int(dynamics.nu)
    x0 = check_initial_state(x0, nx)
    theta = check_parameters(policy, theta)
    _check_policy_output(policy, theta, x0, nu)
    return _rollout(dynamics, policy, theta, x0, horizon)


def _policy_cost(problem: ShootingProblem, policy, theta) -> Array:
    xs, us = _rollout(problem.dynamics, policy, theta, problem.x0, problem.horizon, problem.clip)
    return problem.cost(xs, us)


def _check_problem(problem, policy, theta):
    if not isinstance(problem, ShootingProblem):
        raise TypeError(f"problem must be a ShootingProblem, got {type(problem).__name__}")
    if not callable(policy):
        raise TypeError(f"policy must be callable as policy(theta, x, t), got {type(policy).__name__}")
    theta = check_parameters(policy, theta)
    _check_policy_output(policy, theta, problem.x0, problem.nu)
    return theta


def policy_cost(problem: ShootingProblem, policy: Callable, theta) -> Array:
    """The objective :math:`V(\\theta)`: the total cost of the policy's closed-loop rollout
    from ``problem.x0``, its controls projected on the problem's box (if any).

    Args:
        problem: the :class:`~rsmooth.control.ShootingProblem` (dynamics, costs, ``x0``, ``T``).
        policy: ``policy(theta, x, t) -> u``.
        theta: the policy parameters.

    Returns:
        A scalar.
    """
    theta = _check_problem(problem, policy, theta)
    return _policy_cost(problem, policy, theta)


def _check_estimator(estimator: str, num_samples) -> None:
    if estimator not in ESTIMATORS:
        raise ValueError(f"estimator must be one of {ESTIMATORS}, got {estimator!r}")
    _checks.check_num_samples(num_samples, minimum=4 if estimator == "alpha" else 1)


def _estimate(problem, policy, key, theta, sigma, num_samples, estimator, noise, options) -> _estimators.Estimate:
    options = dict(options)
    if estimator == "first":
        for name in ("baseline", "gamma", "lipschitz", "delta", "rule", "cross_fit"):  # zeroth/alpha-order options
            options.pop(name, None)
    elif estimator == "zeroth":
        for name in ("gamma", "lipschitz", "delta", "rule", "cross_fit"):
            options.pop(name, None)
    return _METHODS[estimator](
        lambda th: _policy_cost(problem, policy, th), key, theta, sigma=sigma, num_samples=num_samples, noise=noise, **options
    )


def policy_gradient(
    problem: ShootingProblem,
    policy: Callable,
    key: Array,
    theta,
    *,
    sigma: ArrayLike,
    num_samples: int,
    estimator: str = "first",
    noise: Noise = Gaussian(),
    **options,
) -> _estimators.Estimate:
    r"""Monte-Carlo estimate of :math:`\nabla_\theta\, \mathbb{E}_w V(\theta + \sigma w)`.

    Args:
        problem: the :class:`~rsmooth.control.ShootingProblem`.
        policy: ``policy(theta, x, t) -> u``.
        key: a `jax.random` key.
        theta: the policy parameters (any pytree of floating arrays).
        sigma: the noise level on the parameters, positive (may be traced).
        num_samples: rollouts per estimate (>= 4 for ``"alpha"``, which gives half of them
            to each of its two estimates).
        estimator: ``"first"`` (mean of sampled exact gradients), ``"zeroth"`` (score
            function with a baseline) or ``"alpha"`` (their blend).
        noise: the noise law of ``w``.
        **options: passed to the estimator (``antithetic``; ``devices`` and
            ``sample_chunk``, where and how many rollouts at a time are evaluated: the
            samples split over devices, each device rolling out its share, as in
            :func:`rsmooth.zeroth_order`; ``baseline`` for ``"zeroth"`` and ``"alpha"``;
            ``gamma``, ``lipschitz``, ``delta``, ``rule`` (``"suh"`` or
            ``"inverse_variance"``) and ``cross_fit`` for ``"alpha"``); those an estimator
            does not take are ignored, so one set of options serves all three.

    Returns:
        An :class:`~rsmooth.estimators.Estimate`: ``value`` the smoothed cost, ``grad`` with
        the structure of ``theta``, ``stats`` with ``variance`` (and ``alpha`` etc. for
        ``"alpha"``).

    Raises:
        ValueError: on ``sigma <= 0``, too few ``num_samples``, an unknown ``estimator``, a
            ``theta`` of the wrong shapes or not finite, or bad ``devices`` or
            ``sample_chunk``.

    References:
        H. J. T. Suh, M. Simchowitz, K. Zhang, R. Tedrake, "Do differentiable simulators give
        better policy gradients?", ICML 2022, Sec. 2 (first- and zeroth-order batched
        gradients) and Sec. 4 (alpha-order).
    """
    _checks.check_key(key)
    _check_estimator(estimator, num_samples)
    sigma = _checks.check_positive_scalar(sigma, "sigma")
    theta = _check_problem(problem, policy, theta)
    return _estimate(problem, policy, key, theta, sigma, num_samples, estimator, noise, options)


class PolicyGradient(eqx.Module):
    """Configuration of :func:`optimize_policy`: Adam on smoothed-gradient estimates.

    Attributes:
        estimator: ``"first"``, ``"zeroth"`` or ``"alpha"`` (see :func:`policy_gradient`).
        sigma: the initial noise level on the parameters (> 0).
        num_samples: rollouts per iteration (>= 4 for ``"alpha"``).
        learning_rate: Adam's step size.
        iterations: the number of Adam steps.
        schedule: owns sigma (:mod:`rsmooth.schedules`; ``Constant()`` by default). It is
            updated after every step with the estimate's ``d V_sigma / d sigma`` (the signal
            of ``Adaptive``) and the true cost ``V(theta)`` (the loss ``Reheating`` judges
            progress by); sample growth (``Adaptive.sample_growth``) recompiles the step.
        noise: the noise law.
        antithetic: antithetic pairs in the estimators.
        baseline: the zeroth-order baseline (``"zeroth"`` and ``"alpha"``): True, ``V(theta)``;
            ``"leave-one-out"``, the mean of the other samples' costs; False, none.
        delta: the confidence level ``1 - delta`` of the alpha-order trust region.
        gamma: the alpha-order trust-region radius (``None``: the estimator's scale-free rule).
        alpha_rule: how alpha order blends its two estimates: ``"suh"`` (one alpha) or
            ``"inverse_variance"`` (one weight per parameter; ``gamma`` must be None); the
            ``rule`` of :func:`rsmooth.alpha_order`. ``stats["alpha"]`` is then the mean
            weight over the parameters.
        alpha_cross_fit: alpha order chooses its weights on independent folds of its samples
            (the ``cross_fit`` of :func:`rsmooth.alpha_order`: unbiased where both halves are;
            ``num_samples`` a multiple of 4, >= 8).
        shared_samples: evaluate :math:`V` and its gradient at the same ``num_samples``
            points whatever the estimator, which is then chosen at run time: solvers that
            differ only in ``estimator`` and ``alpha_cross_fit`` share one compiled step (a
            comparison of the estimators compiles the costly rollout gradient once, at the
            price of a gradient per sample for ``"zeroth"`` too). First and zeroth order use all the
            samples; alpha order gives the first half to its zeroth-order estimate and the
            second half to its first-order one. Needs an even ``num_samples >= 4``, a noise
            law with a score, and no ``antithetic``.
        devices: where the rollouts of every estimate (and, with ``shared_samples``, the
            rollout at ``theta``) are evaluated: ``None`` (default) on the default device;
            ``"all"``, a sequence of devices or a one-dimensional mesh: the samples split
            over them, each device rolling out its share (:mod:`rsmooth.parallel`). The
            samples are drawn from the key as on one device: the estimates, and so the
            iterates, are the one-device ones up to rounding (for rollouts whose value at a
            sample does not depend on the samples evaluated with it; see
            :mod:`rsmooth.parallel`).
        sample_chunk: the most rollouts evaluated at once on a device: bounds the memory of
            the rollouts' intermediate values. ``None``: a device's whole share, except on
            several CPU devices, one at a time (:mod:`rsmooth.parallel`).
    """

    estimator: str = eqx.field(static=True, default="alpha")
    sigma: float = eqx.field(static=True, default=0.1)
    num_samples: int = eqx.field(static=True, default=32)
    learning_rate: float = eqx.field(static=True, default=1e-2)
    iterations: int = eqx.field(static=True, default=100)
    schedule: _schedules.Schedule = eqx.field(static=True, default=_schedules.Constant())
    noise: Noise = eqx.field(static=True, default=Gaussian())
    antithetic: bool = eqx.field(static=True, default=False)
    baseline: bool | str = eqx.field(static=True, default=True)
    delta: float = eqx.field(static=True, default=0.05)
    gamma: float | None = eqx.field(static=True, default=None)
    shared_samples: bool = eqx.field(static=True, default=False)
    alpha_rule: str = eqx.field(static=True, default="suh")
    alpha_cross_fit: bool = eqx.field(static=True, default=False)
    devices: str | tuple[jax.Device, ...] | Mesh | None = eqx.field(
        static=True, default=None, converter=parallel.static_devices
    )
    sample_chunk: int | None = eqx.field(static=True, default=None)

    def __check_init__(self):
        _check_estimator(self.estimator, self.num_samples)
        parallel.resolve_devices(self.devices, "devices")
        parallel.check_sample_chunk(self.sample_chunk, "sample_chunk")
        _estimators.check_baseline(self.baseline, self.num_samples)
        _estimators.check_alpha_rule(self.alpha_rule, self.gamma, "alpha_rule")
        if self.estimator == "alpha" or self.shared_samples:
            _estimators.check_cross_fit(self.alpha_cross_fit, self.num_samples, self.antithetic, "alpha_cross_fit")
        if self.shared_samples:
            if self.antithetic:
                raise ValueError("shared_samples draws independent samples: it does not take antithetic=True")
            if self.num_samples < 4 or self.num_samples % 2:
                raise ValueError(f"shared_samples needs an even num_samples >= 4, got {self.num_samples}")
            if not self.noise.has_score:
                raise ValueError(f"shared_samples needs a noise law with a score; {type(self.noise).__name__} has none")
        # Host checks (static fields): a default PolicyGradient() is built at import time.
        _checks.check_positive_number(self.sigma, "sigma")
        _checks.check_positive_number(self.learning_rate, "learning_rate")
        _checks.check_num_samples(self.iterations, "iterations", minimum=0)
        if not isinstance(self.schedule, _schedules.Schedule):
            raise TypeError(f"schedule must be an rsmooth.schedules.Schedule, got {self.schedule!r}")
        if not isinstance(self.noise, Noise):
            raise TypeError(f"noise must be an rsmooth.noise.Noise, got {self.noise!r}")
        if self.estimator != "first" and not self.noise.has_score:
            raise ValueError(f"the {self.estimator}-order estimator needs a noise law with a score; {type(self.noise).__name__} has none")

    def options(self) -> dict:
        return {"antithetic": self.antithetic, "baseline": self.baseline, "delta": self.delta, "gamma": self.gamma,
                "rule": self.alpha_rule, "cross_fit": self.alpha_cross_fit, "devices": self.devices,
                "sample_chunk": self.sample_chunk}


class PolicySolution(eqx.Module):
    """The result of :func:`optimize_policy`.

    Attributes:
        theta: the final parameters.
        cost: the true cost :math:`V` of the final parameters.
        xs, us: their rollout, ``(T + 1, nx)`` and ``(T, nu)``.
        result: a :class:`~rsmooth.RESULTS` item: ``successful``, or ``nonfinite`` where the
            final cost or a final parameter is NaN or infinite (the last step left the region
            where the cost is defined; the earlier iterates are in ``stats["theta"]``). The
            optimization runs a fixed number of iterations, so it has no other failure.
        stats: NumPy histories, one entry per iteration ``k = 0 .. N - 1`` (the iterate
            ``theta_k`` the step started from) unless said: ``theta`` (the parameters, a
            pytree with a leading axis ``N + 1``, the final ones last), ``cost`` (true cost,
            ``N + 1`` entries, the final one last), ``smoothed_cost`` (the estimate of
            :math:`V_\\sigma`), ``sigma``, ``alpha`` (the weight of the first-order estimate:
            1 for ``"first"``, 0 for ``"zeroth"``), ``variance`` (the estimated variance of
            the gradient estimate, trace of its covariance), ``grad_norm``; and
            ``time_per_iteration`` (s), ``total_time`` (s).
    """

    theta: object
    cost: Array
    xs: Array
    us: Array
    result: RESULTS
    stats: dict


_NONFINITE_ESTIMATE = (
    "the estimate of the smoothed cost or of its gradient is not finite: the cost or its gradient is "
    "non-finite (NaN or inf) at a sampled point theta + sigma * z"
)
_HISTORY = ("cost", "smoothed_cost", "sigma", "alpha", "variance", "grad_norm")


# The programs below test the estimate for finiteness themselves (the record's "finite",
# raised on by the host loop), so the traced checks of the estimators and the dynamics are
# left out of them: without host callbacks, JAX's persistent compilation cache can keep them.
@eqx.filter_jit
@_checks.without_traced_checks()
def _jitted_step(solver: PolicyGradient, problem, policy, theta, opt_state, schedule_state, key):
    sigma = schedule_state.sigma
    estimate = _estimate(
        problem, policy, key, theta, sigma, solver.num_samples, solver.estimator, solver.noise, solver.options()
    )
    cost = _policy_cost(problem, policy, theta)
    alpha = {"first": 1.0, "zeroth": 0.0}.get(solver.estimator)
    alpha = estimate.stats["alpha"] if alpha is None else jnp.asarray(alpha, sigma.dtype)
    return _update(solver, theta, opt_state, schedule_state, estimate, cost, alpha)


def _shared_sample_estimate(problem, policy, key, theta, sigma, solver: PolicyGradient, index):
    """The estimate of the estimator ``index`` (traced; 3: alpha order cross-fitted) from shared samples, and the
    true cost."""
    flat_theta, unravel = ravel_pytree(theta)
    sigma = sigma.astype(flat_theta.dtype)
    z, points = _estimators.perturbed_points(solver.noise, key, flat_theta, sigma, solver.num_samples, False)
    # V and its gradient at theta (the baseline and the true cost) and at the perturbed points,
    # in one batch: the gradient at theta is not needed, but one batch is one rollout program
    # (split over the solver's devices as the separate estimators split theirs).
    values, grads = parallel.map_samples(
        jax.value_and_grad(lambda v: _policy_cost(problem, policy, unravel(v))),
        jnp.concatenate([flat_theta[None], points]),
        devices=solver.devices,
        sample_chunk=solver.sample_chunk,
    )
    values = _checks.check_finite(values, _estimators._NONFINITE_F)
    grads = _checks.check_finite(grads, _estimators._NONFINITE_GRAD)
    flat_estimate, alpha = _estimators._shared_sample_estimate(
        index, z, values[1:, None], grads[1:, None, :], values[:1], sigma, solver.noise, solver.gamma, None, solver.delta,
        solver.baseline, solver.alpha_rule,
    )
    flat = _estimators._Flat(flat_theta, None, unravel, ())
    return _estimators._package(flat, flat_estimate, {"alpha": alpha}), values[0]


@eqx.filter_jit
@_checks.without_traced_checks()
def _jitted_shared_step(solver: PolicyGradient, problem, policy, theta, opt_state, schedule_state, key, index):
    estimate, cost = _shared_sample_estimate(problem, policy, key, theta, schedule_state.sigma, solver, index)
    return _update(solver, theta, opt_state, schedule_state, estimate, cost, estimate.stats["alpha"])


def _update(solver: PolicyGradient, theta, opt_state, schedule_state, estimate, cost, alpha):
    """Adam's step on the estimate, the schedule's update and the iteration's record."""
    sigma = schedule_state.sigma
    updates, opt_state = optax.adam(solver.learning_rate).update(estimate.grad, opt_state, theta)
    theta_next = optax.apply_updates(theta, updates)
    schedule_state = solver.schedule.update(schedule_state, estimate.sigma_grad, loss=cost)
    grad_norm = jnp.sqrt(sum(jnp.sum(g**2) for g in jax.tree.leaves(estimate.grad)))
    record = {
        "cost": cost,
        "smoothed_cost": estimate.value,
        "sigma": sigma,
        "alpha": alpha,
        "variance": estimate.stats["variance"],
        "grad_norm": grad_norm,
        "finite": jnp.isfinite(estimate.value) & jnp.isfinite(grad_norm),
    }
    return theta_next, opt_state, schedule_state, record


@eqx.filter_jit
@_checks.without_traced_checks()
def _jitted_rollout(problem, policy, theta):
    xs, us = _rollout(problem.dynamics, policy, theta, problem.x0, problem.horizon, problem.clip)
    return xs, us, problem.cost(xs, us)


def optimize_policy(
    problem: ShootingProblem,
    policy: Callable,
    key: Array,
    theta,
    *,
    solver: PolicyGradient = PolicyGradient(),
    callback: Callable[[dict], None] | None = None,
    progress: bool = False,
) -> PolicySolution:
    r"""Minimizes the smoothed policy cost :math:`V_\sigma(\theta)` by Adam.

    Iteration ``k`` draws its samples with ``fold_in(key, k)``, estimates the gradient by
    :func:`policy_gradient` at the current ``sigma`` (owned by ``solver.schedule``), takes an
    Adam step, and updates the schedule. The step is jitted once per (solver, problem,
    policy) structure: define the cost functions and a plain-function policy once, not anew
    for every call, so that later calls reuse it. With ``solver.shared_samples``, solvers that
    differ only in their ``estimator`` or ``iterations`` share it.

    Args:
        problem: the :class:`~rsmooth.control.ShootingProblem`.
        policy: ``policy(theta, x, t) -> u`` (e.g. :class:`OpenLoop`, :class:`LinearFeedback`).
        key: a `jax.random` key (the run is reproducible bit for bit for a given key).
        theta: the initial parameters.
        solver: the :class:`PolicyGradient` configuration.
        callback: called after each iteration with a dict of floats: ``iteration``, ``cost``
            (true cost before the step), ``sigma``, ``alpha``, ``variance``, ``grad_norm``,
            ``time``.
        progress: show a `tqdm` progress bar.

    Returns:
        A :class:`PolicySolution`; its ``result`` is ``RESULTS.nonfinite`` where the final
        cost or parameters are not finite (check it: the solve does not raise for it).

    Raises:
        ValueError: on a ``theta`` of the wrong shapes or not finite, or a non-finite initial
            cost.
        FloatingPointError: where an iteration's estimate is not finite (the cost or its
            gradient is not finite at a sampled point).
    """
    if not isinstance(solver, PolicyGradient):
        raise TypeError(f"solver must be a PolicyGradient, got {type(solver).__name__}")
    _checks.check_key(key)
    theta = _check_problem(problem, policy, theta)
    schedule_state = solver.schedule.init(jnp.asarray(solver.sigma, problem.x0.dtype), solver.num_samples)
    opt_state = optax.adam(solver.learning_rate).init(theta)
    _, _, cost0 = _jitted_rollout(problem, policy, theta)
    if not np.isfinite(float(cost0)):
        raise ValueError("the cost of the initial policy (x0, theta) is not finite")
    bar = None
    if progress:
        from tqdm.auto import tqdm  # optional: only needed for progress=True

        bar = tqdm(total=solver.iterations, desc="policy gradient", leave=False)
    thetas, records, times = [theta], [], []
    # The estimator is a traced index of _estimators._shared_sample_estimate: 3 is alpha order
    # cross-fitted.
    cross_fitted = solver.estimator == "alpha" and solver.alpha_cross_fit
    estimator_index = jnp.asarray(3 if cross_fitted else ESTIMATORS.index(solver.estimator), jnp.int32)
    # What the shared step's program does not depend on (the estimator and its cross-fitting, a
    # traced index; the number of iterations) is set to one value, so that such solvers share
    # the compiled step.
    shared_solver = functools.partial(dataclasses.replace, estimator=ESTIMATORS[0], alpha_cross_fit=False, iterations=0)
    try:
        for k in range(solver.iterations):
            start = time.perf_counter()
            step_solver = solver
            num_samples = int(schedule_state.num_samples)
            if num_samples != solver.num_samples:  # Adaptive's sample growth
                step_solver = dataclasses.replace(solver, num_samples=num_samples)
            step_key = jax.random.fold_in(key, k)
            if solver.shared_samples:
                # The estimator is a traced index: every estimator runs the same program.
                step = _jitted_shared_step(shared_solver(step_solver), problem, policy, theta, opt_state,
                                           schedule_state, step_key, estimator_index)
            else:
                step = _jitted_step(step_solver, problem, policy, theta, opt_state, schedule_state, step_key)
            theta, opt_state, schedule_state, record = jax.block_until_ready(step)
            times.append(time.perf_counter() - start)
            if not bool(record["finite"]):
                raise FloatingPointError(f"iteration {k}: {_NONFINITE_ESTIMATE}")
            thetas.append(theta)
            records.append(record)
            info = {name: float(record[name]) for name in _HISTORY if name != "smoothed_cost"}
            info.update(iteration=k, time=times[-1])
            if callback is not None:
                callback(info)
            if bar is not None:
                bar.update(1)
                bar.set_postfix(cost=f"{info['cost']:.4g}", sigma=f"{info['sigma']:.3g}", alpha=f"{info['alpha']:.2f}")
    finally:
        if bar is not None:
            bar.close()
    xs, us, cost = _jitted_rollout(problem, policy, theta)
    stats = {name: np.asarray([float(r[name]) for r in records]) for name in _HISTORY}
    stats["cost"] = np.append(stats["cost"], float(cost))
    stats["theta"] = jax.tree.map(lambda *leaves: np.stack([np.asarray(leaf) for leaf in leaves]), *thetas)
    stats["time_per_iteration"] = np.asarray(times)
    stats["total_time"] = float(np.sum(times))
    finite = np.isfinite(float(cost)) and all(bool(np.all(np.isfinite(np.asarray(leaf)))) for leaf in jax.tree.leaves(theta))
    result = RESULTS.successful if finite else RESULTS.nonfinite
    return PolicySolution(theta=theta, cost=cost, xs=xs, us=us, result=result, stats=stats)
