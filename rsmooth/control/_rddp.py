r"""Randomized DDP (R-DDP): DDP whose backward pass sees the randomly smoothed dynamics.

Le Lidec, Schramm, Montaut, Schmid, Laptev, Carpentier (2024) replace, in the backward pass
of DDP, the Jacobians of a non-smooth dynamics :math:`f` (contact, friction, floors: zero or
discontinuous derivatives) by those of its randomized smoothing

.. math:: f_\varepsilon(x, u) = \mathbb{E}_{z, w}\, f(x + \varepsilon s_x z,\ u + \varepsilon s_u w),

estimated by Monte-Carlo at every node of the current trajectory with one of the estimators
of :mod:`rsmooth.estimators` (first order: mean of sampled Jacobians; zeroth order: score
function; alpha order: their blend), the samples batched with `vmap`, a fresh key per
iteration (``fold_in(key, iteration)``, split over the nodes). With ``devices``, the
``T * num_samples`` (node, sample) evaluations of an iteration are one batch split over
several devices or hosts (:func:`rsmooth.parallel.map_samples`), for the same Jacobians.
``s_x`` and ``s_u`` (``state_noise_scale``, ``control_noise_scale``) set the relative size
of the noise on the state and the control. An iteration costs ``T * num_samples`` evaluations of the dynamics
(with their Jacobians for the first-order estimator). Everything else is the DDP of :func:`rsmooth.control.ddp`: the
forward pass and the line search use the TRUE dynamics and the true cost, so every accepted
step decreases the true cost.

The noise level :math:`\varepsilon` (``eps``) is owned by a schedule, recorded in
``solution.stats["noise"]``:

* ``schedule="adaptive"`` (default, our rule): ``eps`` is kept as long as the smoothed
  problem makes progress. The iteration *stalls* when its relative decrease of the true cost
  :math:`(J_k - J_{k+1}) / |J_k|` is below ``stall_threshold`` (a rejected step counts as
  no decrease) or when the expected improvement is below ``th_stop`` (the smoothed problem is
  solved); then ``eps <- decay * eps``.
* ``schedule="reheating"``: as ``"adaptive"``, except that a stall where more noise would
  lower the cost raises the noise instead, ``eps <- growth * eps`` up to ``eps_max``, at most
  ``max_raises`` times. The signal is the cost's first-order response to the smoothing,
  :math:`\sum_t \lambda_{t+1}^\top \partial f_\varepsilon(x_t, u_t) / \partial\varepsilon`
  with the adjoints :math:`\lambda_T = \nabla \ell_T`,
  :math:`\lambda_t = \nabla_x \ell_t + f_x^\top \lambda_{t+1}` of the smoothed
  linearization: the estimators give :math:`\partial f_\varepsilon / \partial\varepsilon`
  from the samples already drawn. The noise is raised when the decrease this signal promises
  for the raise, relative to the cost, exceeds ``stall_threshold``: the smoothed dynamics at
  a larger noise then reach lower cost (a contact that the samples at this noise barely
  make). A positive signal means the noise only blurs a solution, which a smaller noise
  refines (the reasoning of :class:`rsmooth.schedules.Reheating`); a zero one (linear
  dynamics, or no sample reaching the contact at all) keeps the usual reduction.
* ``schedule="geometric"``: ``eps <- decay * eps`` at every iteration (for comparison).

In all three, once ``eps`` would fall below the floor ``eps_min``, or after
``max_smoothed_iterations`` iterations, ``eps`` becomes exactly 0: the last iterations are
plain DDP, and convergence (expected improvement below ``th_stop``) is only declared with
``eps = 0``, so the solution is a (local) solution of the true, non-smoothed problem. With
``eps = 0`` from the start, R-DDP is DDP, iterate for iterate.

Example:
    >>> import jax, jax.numpy as jnp
    >>> from rsmooth import control
    >>> # A mass on a floor lifted by a force u (gravity 1): no motion while u < 1, so that
    >>> # d x_next / d u = 0 at u = 0 and DDP started from u = 0 stays on the floor.
    >>> class Lift:
    ...     nx, nu = 2, 1
    ...     def step(self, x, u):
    ...         v = jnp.where(x[0] <= 0.0, jnp.maximum(x[1] + 0.1 * (u[0] - 1.0), 0.0),
    ...                       x[1] + 0.1 * (u[0] - 1.0))
    ...         z = jnp.maximum(x[0] + 0.1 * v, 0.0)
    ...         return jnp.stack([z, jnp.where(z <= 0.0, 0.0, v)])
    >>> problem = control.ShootingProblem(
    ...     Lift(), running_cost=lambda x, u: 1e-3 * jnp.sum(u**2),
    ...     terminal_cost=lambda x: 10.0 * (x[0] - 0.2) ** 2, x0=jnp.zeros(2), horizon=10)
    >>> solver = control.RDDP(eps=1.0, num_samples=32, estimator="first")
    >>> solution = control.rddp(problem, jax.random.key(0), solver=solver)
    >>> bool(solution.converged), float(solution.stats["noise"][-1])
    (True, 0.0)
    >>> bool(solution.xs[-1, 0] > 0.15)
    True

References:
    Q. Le Lidec, F. Schramm, L. Montaut, C. Schmid, I. Laptev, J. Carpentier, "Leveraging
    randomized smoothing for optimal control of nonsmooth dynamical systems", Nonlinear
    Analysis: Hybrid Systems 52, 2024.
"""

from __future__ import annotations

import dataclasses
import functools
import inspect
from typing import Callable, ClassVar, Literal, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array, lax
from jax.sharding import Mesh

from rsmooth import _checks, _xla, parallel
from rsmooth import estimators as _estimators
from rsmooth.control._ddp import DDP, DDPState, Solution, dynamics_jacobians, map_nodes, solve
from rsmooth.control._problem import ShootingProblem
from rsmooth.noise import Gaussian, Noise

__all__ = ["RDDP", "rddp", "smoothed_dynamics_jacobians"]

ESTIMATORS = ("first", "zeroth", "alpha")
SCHEDULES = ("adaptive", "geometric", "reheating")


def _as_scale(value):
    """A noise scale as a hashable static value: a float, or a tuple of floats."""
    if np.ndim(value) == 0:
        return float(value)
    return tuple(float(v) for v in np.asarray(value, dtype=float).reshape(-1))


def _scale_vector(value, size: int, name: str, dtype) -> Array:
    array = np.asarray(value, dtype=float)
    if array.ndim == 0:
        array = np.full((size,), float(array))
    if array.shape != (size,):
        raise ValueError(f"{name} must be a scalar or have {size} entries, got shape {array.shape}")
    if not np.all(array > 0) or not np.all(np.isfinite(array)):
        raise ValueError(f"{name} must be positive and finite, got {value!r}")
    return jnp.asarray(array, dtype)


def smoothed_dynamics_jacobians(
    problem: ShootingProblem,
    key: Array,
    xs: Array,
    us: Array,
    *,
    eps,
    num_samples: int,
    estimator: str = "first",
    noise: Noise = Gaussian(),
    state_noise_scale: float | tuple[float, ...] = 1.0,
    control_noise_scale: float | tuple[float, ...] = 1.0,
    batch_size: int | None = 1,
    noise_effect: bool = False,
    alpha_rule: str = "suh",
    devices: str | Sequence[jax.Device] | Mesh | None = None,
    sample_chunk: int | None = None,
) -> tuple[Array, Array] | tuple[Array, Array, Array]:
    r"""Monte-Carlo Jacobians of the smoothed dynamics at every node of a trajectory.

    Estimates :math:`\partial f_\varepsilon / \partial x` and
    :math:`\partial f_\varepsilon / \partial u` at :math:`(x_t, u_t)`, ``t < T``, for
    :math:`f_\varepsilon(x, u) = \mathbb{E}\, f(P(x + \varepsilon s_x z), u + \varepsilon s_u w)`,
    with :math:`P` the dynamics' ``project_state`` if it has one (the identity otherwise):
    the estimator runs on :math:`h(y) = f(s \odot y)` at :math:`y = (x, u) / s` with noise
    ``eps`` and its Jacobian is divided by :math:`s` column by column.

    Args:
        problem: gives the dynamics.
        key: a `jax.random` key, split over the nodes.
        xs, us: the trajectory, ``(T + 1, nx)`` and ``(T, nu)``.
        eps: noise level, positive (may be traced).
        num_samples: samples per node.
        estimator: ``"first"``, ``"zeroth"`` or ``"alpha"``.
        noise: the noise law.
        state_noise_scale, control_noise_scale: ``s_x``, ``s_u``: positive scalars, or one
            positive value per coordinate (``nx`` and ``nu`` of them).
        batch_size: nodes estimated at a time (`lax.map` over batches; ``None``: `vmap` over
            all nodes); the samples of a node are always batched with `vmap`.
        noise_effect: also return the estimators' :math:`\partial f_\varepsilon /
            \partial\varepsilon` at every node, ``(T, nx)``.
        alpha_rule: for ``"alpha"``, how its two estimates are blended: ``"suh"`` (one alpha
            per node) or ``"inverse_variance"`` (one weight per entry of the node's
            Jacobian); the ``rule`` of :func:`rsmooth.alpha_order`.
        devices: where the dynamics are evaluated at the samples: ``None`` (default) on the
            default device, node by node as ``batch_size`` says; ``"all"``, a sequence of
            devices or a one-dimensional mesh: the ``T x num_samples`` (node, sample) pairs
            are one batch split over the devices by :func:`rsmooth.parallel.map_samples`,
            each device evaluating its share (its own contact-solver loops included), and
            the per-node means summed across devices. The samples are drawn from ``key`` as
            on one device, so the Jacobians are the one-device ones up to rounding (for
            dynamics whose value at a sample does not depend on the samples evaluated with
            it; see :mod:`rsmooth.parallel`). ``batch_size`` does not apply then. With one
            device (``"all"`` on a one-device machine), as ``None``.
        sample_chunk: the most (node, sample) pairs evaluated at once on a device, for the
            one batch of pairs above (given alone, on the default device): bounds the
            memory of the dynamics' intermediate values. ``None``: a device's whole share,
            except on several CPU devices, one pair at a time (see :mod:`rsmooth.parallel`).

    Returns:
        ``(fx, fu)``, shapes ``(T, nx, nx)`` and ``(T, nx, nu)`` (and the noise effect).

    Raises:
        ValueError: for bad ``devices`` or ``sample_chunk`` (naming the argument), noise
            scales of the wrong size, or an unknown ``alpha_rule``.
    """
    mesh = parallel.resolve_devices(devices, "devices")
    chunk = parallel.check_sample_chunk(sample_chunk, "sample_chunk")
    nx, nu = problem.nx, problem.nu
    dtype = xs.dtype
    scale = jnp.concatenate(
        [_scale_vector(state_noise_scale, nx, "state_noise_scale", dtype), _scale_vector(control_noise_scale, nu, "control_noise_scale", dtype)]
    )
    method = {
        "first": _estimators.first_order,
        "zeroth": _estimators.zeroth_order,
        "alpha": _estimators.alpha_order,
    }[estimator]

    # A perturbed state may leave the state's manifold (a free flyer's unit quaternion): the
    # dynamics' project_state, when it has one, brings it back before the step, so that the
    # smoothed function is f(project(x + noise), u + noise) for every estimator.
    project = getattr(problem.dynamics, "project_state", None)

    def h(y):
        y = scale * y
        x = y[:nx] if project is None else project(y[:nx])
        return problem.dynamics.step(x, y[nx:])

    _estimators.check_alpha_rule(alpha_rule, name="alpha_rule")
    options = {"rule": alpha_rule} if estimator == "alpha" else {}
    step_and_jacobians = getattr(problem.dynamics, "step_and_jacobians", None)
    if estimator in ("first", "alpha") and step_and_jacobians is not None:
        # (alpha order: for its first-order half)

        def value_and_jacobian(y):  # the dynamics' own Jacobians, in the scaled variable y
            y = scale * y
            x = y[:nx]
            if project is not None:
                x = project(x)
                projection = jax.jacfwd(project)(y[:nx])
            x_next, fx, fu = step_and_jacobians(x, y[nx:])
            if project is not None:
                fx = fx @ projection
            return x_next, jnp.concatenate([fx, fu], axis=1) * scale[None, :]

        options["value_and_jacobian"] = value_and_jacobian

    if mesh is not None or chunk is not None:  # (devices="all" on one device: as None)
        given = options.get("value_and_jacobian") or functools.partial(_estimators.value_and_jacobian, h)

        def jacobian_fn(y):
            value, jacobian = given(y)
            return value.astype(y.dtype), jacobian.astype(y.dtype)

        spread = dict(devices=mesh, sample_chunk=chunk)
        return _spread_jacobians(
            h, jacobian_fn, key, xs, us, scale, eps, num_samples, estimator, noise, noise_effect, alpha_rule, spread
        )

    def node(key, x, u):
        y = jnp.concatenate([x, u]) / scale
        estimate = method(h, key, y, sigma=eps, num_samples=num_samples, noise=noise, **options)
        jacobian = estimate.grad / scale[None, :]
        if noise_effect:
            return jacobian[:, :nx], jacobian[:, nx:], estimate.sigma_grad
        return jacobian[:, :nx], jacobian[:, nx:]

    keys = jax.random.split(key, us.shape[0])
    return map_nodes(node, (keys, xs[:-1], us), batch_size)


def _spread_jacobians(h, jacobian_fn, key, xs, us, scale, eps, num_samples, estimator, noise, noise_effect,
                      alpha_rule, spread):
    """:func:`smoothed_dynamics_jacobians` with its ``devices`` or ``sample_chunk``: the
    estimators' samples of every node drawn as they draw them (one key per node, split in two
    for alpha order), the dynamics evaluated at all the (node, sample) pairs in one
    :func:`rsmooth.parallel.map_samples` (one for each part of alpha order), and each node's
    estimate formed from its own pairs by the estimators' formulas. ``h`` is the dynamics in
    the scaled variable ``y = (x, u) / scale``, ``jacobian_fn(y) -> (h(y), dh/dy)``."""
    _checks.check_key(key)
    nx = xs.shape[1]
    nodes = us.shape[0]
    ys = jnp.concatenate([xs[:-1], us], axis=1) / scale[None, :]
    # The estimators' host and run-time checks, once for all the nodes: eps positive (named
    # sigma, as the estimators name it), a noise law with a score for the score-function
    # estimates; the trajectory finite and, for those estimates, eps above the resolution of
    # the nodes' dtype (tested at the node of largest min |y_k|, the first to fail).
    eps, num_samples = _estimators._check_options(
        eps, num_samples, noise, needs_score=estimator != "first", minimum=4 if estimator == "alpha" else 1
    )
    conditions = []
    if estimator != "first":
        conditions.append(_checks.resolution_failure(ys[jnp.argmax(jnp.min(jnp.abs(ys), axis=1))], eps))
    # (tied to a zero added to ys rather than to ys itself: a run-time check runs on one device,
    # and ys is then laid out across the devices)
    zero = _checks.check_all(jnp.zeros((), ys.dtype), [(ys, _estimators._NONFINITE_X)], conditions)
    ys = ys + zero
    keys = jax.random.split(key, nodes)

    def draw(keys, count):
        # (T, count, d) noise and points: perturbed_points of each node, as its estimator draws them
        return jax.vmap(lambda k, y: _estimators.perturbed_points(noise, k, y, eps, count, False))(keys, ys)

    def pairs(points):
        return points.reshape((-1, points.shape[-1]))

    def values_at(points):
        """h at every (node, sample) point and at every node (the zeroth-order baseline)."""
        count = points.shape[1]
        values = parallel.map_samples(lambda y: h(y).astype(y.dtype), jnp.concatenate([pairs(points), ys]), **spread)
        (samples,) = _estimators._checked_samples((values[: nodes * count], _estimators._NONFINITE_F))
        return samples.reshape((nodes, count, nx)), values[nodes * count :]

    def jacobians_at(points):
        count = points.shape[1]
        values, jacobians = parallel.map_samples(jacobian_fn, pairs(points), **spread)
        values, jacobians = _estimators._checked_samples(
            (values, _estimators._NONFINITE_F), (jacobians, _estimators._NONFINITE_GRAD)
        )
        return values.reshape((nodes, count, nx)), jacobians.reshape((nodes, count) + jacobians.shape[1:])

    def zeroth(z, values, reference):
        return _estimators._zeroth_order_terms(z, values, reference[None], eps, noise, False)

    def first(z, values, jacobians):
        return _estimators._first_order_terms(z, values, jacobians, False)

    if estimator == "first":
        z, points = draw(keys, num_samples)
        estimate = jax.vmap(first)(z, *jacobians_at(points))
    elif estimator == "zeroth":
        z, points = draw(keys, num_samples)
        estimate = jax.vmap(zeroth)(z, *values_at(points))
    else:
        halves = jax.vmap(jax.random.split)(keys)
        n_zeroth = num_samples // 2
        n_first = num_samples - n_zeroth
        z0, points0 = draw(halves[:, 0], n_zeroth)
        z1, points1 = draw(halves[:, 1], n_first)
        estimates0 = jax.vmap(zeroth)(z0, *values_at(points0))
        estimates1 = jax.vmap(first)(z1, *jacobians_at(points1))
        # alpha_order's own defaults (gamma, lipschitz, delta), as the per-node estimate uses
        defaults = inspect.signature(_estimators.alpha_order).parameters
        estimate, _ = jax.vmap(
            lambda e0, e1: _estimators._alpha_blend(
                e0, e1, n_zeroth, n_first, False, defaults["gamma"].default, defaults["lipschitz"].default,
                defaults["delta"].default, alpha_rule,
            )
        )(estimates0, estimates1)
    jacobian = estimate.jacobian / scale[None, None, :]
    if noise_effect:
        return jacobian[:, :, :nx], jacobian[:, :, nx:], estimate.sigma_grad
    return jacobian[:, :, :nx], jacobian[:, :, nx:]


class RDDP(DDP):
    """Randomized DDP: the DDP options (see :class:`~rsmooth.control.DDP`) plus the smoothing.

    Attributes:
        eps: the initial noise level (>= 0; 0 is plain DDP).
        num_samples: Monte-Carlo samples per node and iteration (>= 4 for ``"alpha"``).
        estimator: ``"first"`` (mean of sampled Jacobians, default), ``"zeroth"`` (score
            function: needs no derivative of the dynamics) or ``"alpha"`` (their blend).
        alpha_rule: for ``"alpha"``: ``"suh"`` (one alpha per node, default) or
            ``"inverse_variance"`` (one weight per entry of the node's Jacobian; see
            :func:`rsmooth.alpha_order`).
        noise: the noise law (:mod:`rsmooth.noise`).
        state_noise_scale, control_noise_scale: the noise on ``x`` and ``u`` is
            ``eps * state_noise_scale * z`` and ``eps * control_noise_scale * w``: positive
            scalars, or one positive value per coordinate (e.g. noise on one force only).
        schedule: ``"adaptive"`` (reduce on stall), ``"reheating"`` (reduce or raise on
            stall, by the sign of the cost's response to the noise) or ``"geometric"``
            (reduce every iteration); see the module docstring.
        decay: the factor in (0, 1) of each reduction.
        growth: the factor (> 1) of each raise (``"reheating"``).
        eps_max: the largest noise a raise reaches (``"reheating"``; ``None``: 4 ``eps``).
        max_raises: the most raises in a solve (``"reheating"``): near a solution the
            response's sign is noise, and unbounded raises would alternate with reductions.
        eps_min: the floor: a reduction below it sets ``eps`` to 0 (plain DDP).
        stall_threshold: the relative decrease of the true cost below which an iteration
            stalls (adaptive schedule).
        max_smoothed_iterations: after this many iterations ``eps`` is set to 0 (default
            ``max_iterations // 2``), so that the plain-DDP phase always has iterations left.
        sample_node_batch_size: the smoothed Jacobians are estimated this many nodes at a
            time (``None``: all at once); ``node_batch_size`` applies to the exact Jacobians
            of the eps = 0 iterations. ``"auto"`` (the default): 1 on the CPU, ``None`` on a
            GPU or TPU (decided when the solve is traced). On a CPU the ``num_samples``
            samples of a node are already one batch, and batching the nodes too makes every
            contact solve wait for the slowest of ``T x num_samples``; on a GPU one node at a
            time is ``T`` launches of a small batch (benchmarks/RESULTS.md).
        devices: where the dynamics are evaluated at the samples of the smoothed
            linearization: ``None`` (default) on the default device; ``"all"``, a sequence of
            devices or a one-dimensional mesh: the ``T x num_samples`` (node, sample) pairs of
            an iteration split over them, each device evaluating its share (see
            :func:`smoothed_dynamics_jacobians`; ``sample_node_batch_size`` does not apply
            then). The rest of the iteration (the eps = 0 iterations, the backward and forward
            passes) is unchanged: the Jacobians, and so the iterates for a given key, are
            those of one device up to rounding.
        sample_chunk: the most (node, sample) pairs evaluated at once on a device (given
            alone, on the default device, in one batch of pairs): bounds the memory of the
            dynamics' intermediate values. ``None``: a device's whole share, except on several
            CPU devices, one pair at a time (:mod:`rsmooth.parallel`).
    """

    eps: float = eqx.field(static=True, default=1.0)
    num_samples: int = eqx.field(static=True, default=16)
    estimator: str = eqx.field(static=True, default="first")
    noise: Noise = eqx.field(static=True, default=Gaussian())
    state_noise_scale: float | tuple[float, ...] = eqx.field(static=True, default=1.0, converter=_as_scale)
    control_noise_scale: float | tuple[float, ...] = eqx.field(static=True, default=1.0, converter=_as_scale)
    schedule: str = eqx.field(static=True, default="adaptive")
    decay: float = eqx.field(static=True, default=0.5)
    growth: float = eqx.field(static=True, default=2.0)
    eps_max: float | None = eqx.field(static=True, default=None)
    max_raises: int = eqx.field(static=True, default=2)
    eps_min: float = eqx.field(static=True, default=1e-3)
    stall_threshold: float = eqx.field(static=True, default=1e-3)
    max_smoothed_iterations: int | None = eqx.field(static=True, default=None)
    sample_node_batch_size: int | None | Literal["auto"] = eqx.field(static=True, default="auto")
    alpha_rule: str = eqx.field(static=True, default="suh")
    devices: str | tuple[jax.Device, ...] | Mesh | None = eqx.field(
        static=True, default=None, converter=parallel.static_devices
    )
    sample_chunk: int | None = eqx.field(static=True, default=None)

    _needs_key: ClassVar[bool] = True

    def __check_init__(self):
        if not (isinstance(self.eps, (int, float)) and self.eps >= 0 and self.eps < float("inf")):
            raise ValueError(f"eps must be a finite number >= 0, got {self.eps!r}")
        if self.estimator not in ESTIMATORS:
            raise ValueError(f"estimator must be one of {ESTIMATORS}, got {self.estimator!r}")
        _estimators.check_alpha_rule(self.alpha_rule, name="alpha_rule")
        _checks.check_num_samples(self.num_samples, minimum=4 if self.estimator == "alpha" else 1)
        if not isinstance(self.noise, Noise):
            raise TypeError(f"noise must be an rsmooth.noise.Noise, got {self.noise!r}")
        if self.estimator != "first" and not self.noise.has_score:
            raise ValueError(f"the {self.estimator}-order estimator needs a noise law with a score; {type(self.noise).__name__} has none")
        for name in ("state_noise_scale", "control_noise_scale"):
            value = np.asarray(getattr(self, name))
            if not (np.all(value > 0) and np.all(np.isfinite(value))):
                raise ValueError(f"{name} must be positive and finite, got {getattr(self, name)!r}")
        if self.schedule not in SCHEDULES:
            raise ValueError(f"schedule must be one of {SCHEDULES}, got {self.schedule!r}")
        if not 0 < self.decay < 1:
            raise ValueError(f"decay must be in (0, 1), got {self.decay}")
        if not self.growth > 1:
            raise ValueError(f"growth must be > 1, got {self.growth}")
        _checks.check_num_samples(self.max_raises, "max_raises", minimum=0)
        if self.eps_max is not None and not (self.eps_max > 0 and self.eps_max < float("inf")):
            raise ValueError(f"eps_max must be a positive finite number or None, got {self.eps_max!r}")
        if not self.eps_min >= 0:
            raise ValueError(f"eps_min must be >= 0, got {self.eps_min}")
        if not self.stall_threshold >= 0:
            raise ValueError(f"stall_threshold must be >= 0, got {self.stall_threshold}")
        if self.max_smoothed_iterations is not None:
            _checks.check_num_samples(self.max_smoothed_iterations, "max_smoothed_iterations", minimum=0)
        if isinstance(self.sample_node_batch_size, str) and self.sample_node_batch_size != "auto":
            raise ValueError(f"sample_node_batch_size must be an int >= 1, None or 'auto', got {self.sample_node_batch_size!r}")
        if self.sample_node_batch_size not in (None, "auto"):
            _checks.check_num_samples(self.sample_node_batch_size, "sample_node_batch_size", minimum=1)
        parallel.resolve_devices(self.devices, "devices")
        parallel.check_sample_chunk(self.sample_chunk, "sample_chunk")
        if self.approximation != "gauss_newton":
            raise ValueError(
                "RDDP supports approximation='gauss_newton' only: second derivatives of the "
                "smoothed dynamics are not estimated"
            )

    def _initial_noise(self, dtype) -> Array:
        return jnp.asarray(self.eps, dtype)

    def _dynamics_jacobians(self, problem, state: DDPState):
        positive = state.noise > 0
        return lax.cond(
            positive,
            lambda _: self._smoothed_jacobians(problem, state),
            lambda _: DDP._dynamics_jacobians(self, problem, state),
            None,
        )

    def _smoothed_jacobians(self, problem, state: DDPState):
        key = jax.random.fold_in(state.key, state.iteration)
        # The estimators check that sigma > 0 at run time: hand them 1 where eps = 0 (the
        # branch of lax.cond that does not run).
        sigma = jnp.where(state.noise > 0, state.noise, 1.0)
        jacobians = smoothed_dynamics_jacobians(
            problem,
            key,
            state.trajectory.xs,
            state.trajectory.us,
            eps=sigma,
            num_samples=self.num_samples,
            estimator=self.estimator,
            noise=self.noise,
            state_noise_scale=self.state_noise_scale,
            control_noise_scale=self.control_noise_scale,
            batch_size=self._sample_node_batch(),
            noise_effect=self.schedule == "reheating",
            alpha_rule=self.alpha_rule,
            devices=self.devices,
            sample_chunk=self.sample_chunk,
        )
        if self.schedule == "reheating":
            return jacobians
        fx, fu = jacobians  # the noise effect is read by the reheating rule only
        return fx, fu, jnp.zeros(fx.shape[:2], fx.dtype)

    def _sample_node_batch(self) -> int | None:
        """``sample_node_batch_size`` with ``"auto"`` decided (when the solve is traced)."""
        return _xla.resolve_auto(self.sample_node_batch_size, cpu=1, accelerator=None)

    def as_ddp(self) -> DDP:
        """The :class:`~rsmooth.control.DDP` with this solver's DDP options: what R-DDP runs
        once eps = 0 (and the plain-DDP baseline of a comparison)."""
        return DDP(**{field.name: getattr(self, field.name) for field in dataclasses.fields(DDP)})

    def _programs(self) -> tuple[DDP, DDP]:
        # The eps > 0 program holds the smoothed Jacobians only; the eps = 0 iterations run
        # the DDP with the same options (see `solve`): two smaller compilations instead of one
        # program holding both branches under lax.cond (~2x DDP's compile time).
        smoothed = _SmoothedPhase(**{field.name: getattr(self, field.name) for field in dataclasses.fields(self)})
        return smoothed, self.as_ddp()

    def _next_noise(self, state: DDPState, stop, accepted, cost_new, d) -> Array:
        eps = state.noise
        scale = jnp.maximum(jnp.abs(state.cost), jnp.finfo(eps.dtype).tiny)
        if self.schedule == "geometric":
            stalled = jnp.ones((), bool)
        else:
            relative_decrease = jnp.where(accepted, (state.cost - cost_new) / scale, 0.0)
            stalled = stop | (relative_decrease < self.stall_threshold)
        cap = self.max_iterations // 2 if self.max_smoothed_iterations is None else self.max_smoothed_iterations
        reduced = eps * self.decay
        if self.schedule == "reheating":
            eps_max = jnp.asarray(4.0 * self.eps if self.eps_max is None else self.eps_max, eps.dtype)
            # Raise where the response promises a relative decrease of the cost above the
            # stall threshold: a response of exactly zero (linear dynamics, or no sample
            # reaching a contact) gives no reason to move away from the usual reduction.
            promised = -noise_response(d) * (self.growth - 1.0) * eps / scale
            history = state.history["noise"]
            raises = jnp.sum(jnp.where(jnp.isfinite(history[1:]) & jnp.isfinite(history[:-1]), history[1:] > history[:-1], False))
            raise_ = (promised > self.stall_threshold) & (eps < eps_max) & (raises < self.max_raises)
            changed = jnp.where(raise_, jnp.minimum(eps * self.growth, eps_max), reduced)
        else:
            changed = reduced
        new = jnp.where(stalled, changed, eps)
        to_zero = (new < self.eps_min) | (state.iteration + 1 >= cap)
        return jnp.where(to_zero, 0.0, new).astype(eps.dtype)


def noise_response(d) -> Array:
    r"""The cost's first-order response to the noise level of the smoothed dynamics,
    :math:`\sum_t \lambda_{t+1}^\top \partial f_\varepsilon / \partial\varepsilon`, with
    the adjoints of the linearization in ``d`` (see the module docstring)."""

    def node(adjoint, inputs):
        fx, lx, effect = inputs
        return lx + fx.T @ adjoint, adjoint @ effect

    _, terms = lax.scan(node, d.lTx, (d.fx, d.lx, d.noise_effect), reverse=True)
    return jnp.sum(terms)


class _SmoothedPhase(RDDP):
    """R-DDP's step for the iterations with eps > 0 only: :func:`solve` runs those with
    eps = 0 by DDP's step (R-DDP's `step` itself chooses by lax.cond, and stays valid at any
    eps)."""

    def _dynamics_jacobians(self, problem, state: DDPState):
        return self._smoothed_jacobians(problem, state)


def rddp(
    problem: ShootingProblem,
    key: Array,
    us_init: Array | None = None,
    *,
    solver: RDDP = RDDP(),
    callback: Callable[[dict], None] | None = None,
    progress: bool = False,
) -> Solution:
    """Solves a shooting problem by randomized DDP (see the module docstring).

    Args:
        problem: the :class:`~rsmooth.control.ShootingProblem`.
        key: a `jax.random` key (the run is reproducible bit for bit for a given key).
        us_init: initial controls ``(T, nu)`` (default zeros), projected on the box.
        solver: the :class:`RDDP` configuration (noise, estimator, schedule, DDP options).
        callback: called after each iteration with a dict of floats (see
            :func:`~rsmooth.control.ddp`; ``noise`` is the ``eps`` of the next iteration).
        progress: show a `tqdm` progress bar (imported only then).

    Returns:
        A :class:`~rsmooth.control.Solution`; ``stats["noise"]`` is the noise history.

    Raises:
        ValueError: on a wrong shape or non-finite ``us_init``, noise scales of a wrong size,
            or a non-finite initial cost.
        RuntimeError: with ``solver.throw`` (default), when the solve does not succeed.
    """
    if not isinstance(solver, RDDP):
        raise TypeError(f"solver must be an RDDP, got {type(solver).__name__}")
    _checks.check_key(key)
    if isinstance(problem, ShootingProblem):
        _scale_vector(solver.state_noise_scale, problem.nx, "state_noise_scale", problem.x0.dtype)
        _scale_vector(solver.control_noise_scale, problem.nu, "control_noise_scale", problem.x0.dtype)
    return solve(solver, problem, us_init, key, callback, progress, "rddp")
