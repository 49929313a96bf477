r"""Monte-Carlo estimators of the value and gradient of a randomly smoothed function.

For a function :math:`f` and a noise law :math:`\mu` (see :mod:`rsmooth.noise`), the smoothed
function is

.. math:: f_\sigma(x) = \mathbb{E}_{z \sim \mu}\, f(x + \sigma z),

and its gradient can be estimated from :math:`M` samples in two ways:

* zeroth order (score function, Berthet et al. 2020, Prop. 3.1):
  :math:`\hat g_0 = \frac{1}{M} \sum_i (f(x + \sigma z_i) - b)\, (-\nabla \log\mu(z_i)) / \sigma`,
  with the baseline :math:`b = f(x)` (it does not change the mean, since
  :math:`\mathbb{E}\nabla\log\mu(z) = 0`, and removes most of the variance);
* first order (pathwise): :math:`\hat g_1 = \frac{1}{M}\sum_i \nabla f(x + \sigma z_i)`,
  unbiased only where :math:`f` is differentiable almost surely *and* continuous: it is
  exactly zero for a step function.

The alpha-order estimator (Suh, Simchowitz, Zhang, Tedrake, "Do differentiable simulators
give better policy gradients?", ICML 2022, Sec. 4) blends the two, computed on independent
sample batches, choosing alpha from their empirical variances inside an empirical-bias trust
region; or, with ``rule="inverse_variance"``, one weight per entry of the gradient.

All estimators also return :math:`\partial f_\sigma / \partial \sigma`, which the adaptive
noise schedules use.

`x` may be any pytree of floating arrays; `f` returns one array (of any shape). For a scalar
`f`, `grad` has the structure of `x`; otherwise each leaf of `grad` has shape
`f_shape + leaf_shape`, as `jax.jacrev` would give.
"""

from __future__ import annotations

import math
from typing import Callable, NamedTuple, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.flatten_util import ravel_pytree
from jax.typing import ArrayLike

from rsmooth import _checks, parallel
from rsmooth.noise import Gaussian, Noise

__all__ = ["Estimate", "zeroth_order", "first_order", "alpha_order"]


class Estimate(eqx.Module):
    """The result of an estimator.

    Attributes:
        value: Monte-Carlo estimate of :math:`f_\\sigma(x)` (shape of `f`'s output).
        grad: estimate of :math:`\\nabla f_\\sigma(x)` (structure of `x`; a Jacobian for
            array-valued `f`).
        sigma_grad: estimate of :math:`\\partial f_\\sigma(x) / \\partial\\sigma` (shape of
            `f`'s output).
        stats: diagnostics, a dict of arrays. Always: ``variance`` (the estimated variance of
            `grad`, summed over its entries: the trace of its covariance) and ``std_error``
            (elementwise standard error, structure of `grad`). Alpha-order adds ``alpha``,
            ``alpha_star`` (the variance-optimal blend), ``bias`` (empirical bias, the norm of
            the difference of the two estimates), ``radius`` (confidence radius of the
            zeroth-order estimate), ``bias_radius`` (the bias sampling noise alone explains),
            ``gamma`` (the trust region used), ``variance_first``,
            ``variance_zeroth``; with its ``rule="inverse_variance"``, ``alpha`` is the mean
            of the per-entry weights ``alpha_entries`` (structure of `grad`), beside
            ``trusted_fraction`` and without ``alpha_star`` and ``gamma``.
    """

    value: Array
    grad: object
    sigma_grad: Array
    stats: dict


class _Flat(NamedTuple):
    """`f` seen as a map from a flat vector (d,) to a flat vector (m,)."""

    x: Array
    f: Callable[[Array], Array]
    unravel: Callable
    out_shape: tuple


class _FlatEstimate(NamedTuple):
    value: Array  # (m,)
    jacobian: Array  # (m, d)
    sigma_grad: Array  # (m,)
    variance: Array  # (m, d): variance of each Jacobian entry's estimate
    max_score_norm: Array  # largest ||z|| * ||score(z)||, for Lipschitz-based radii


_NONFINITE_X = "x must be finite (it contains NaN or inf)"


def _flatten(f, x, check: bool = True) -> _Flat:
    """Flattens x (checked finite unless `check` is False: then the caller checks it)."""
    _checks.check_floating_tree(x, "x")
    flat_x, unravel = ravel_pytree(x)
    if check:
        flat_x = _checks.check_finite(flat_x, _NONFINITE_X)
    out = jax.eval_shape(f, x)
    if not isinstance(out, jax.ShapeDtypeStruct):
        raise TypeError(
            f"f must return a single array, got a {type(out).__name__}; "
            "stack the outputs into one array"
        )
    if not jnp.issubdtype(out.dtype, jnp.floating):
        raise TypeError(f"f must return floating-point values, got dtype {out.dtype}")

    def f_flat(v):
        return jnp.reshape(f(unravel(v)), (-1,)).astype(v.dtype)

    return _Flat(flat_x, f_flat, unravel, out.shape)


def _flatten_resolved(f, x, sigma) -> _Flat:
    """:func:`_flatten`, with `x` checked finite and `sigma` checked against the resolution of
    `x`'s dtype (one runtime check when traced): below it, `x + sigma * z` rounds to `x` and
    the score-function estimate is zero (:func:`rsmooth._checks.resolution_failure`)."""
    flat = _flatten(f, x, check=False)
    checked = _checks.check_all(
        flat.x, [(flat.x, _NONFINITE_X)], [_checks.resolution_failure(flat.x, sigma)]
    )
    return flat._replace(x=checked)


def _unflatten_jacobian(flat: _Flat, jacobian: Array):
    """(m, d) -> the structure of x, each leaf of shape out_shape + leaf_shape."""
    tree = jax.vmap(flat.unravel)(jacobian)
    return jax.tree.map(lambda leaf: jnp.reshape(leaf, flat.out_shape + leaf.shape[1:]), tree)


def _check_options(sigma, num_samples, noise, *, antithetic=False, needs_score=False, minimum=1):
    if not isinstance(noise, Noise):
        raise TypeError(f"noise must be an rsmooth.noise.Noise (e.g. Gaussian()), got {noise!r}")
    num_samples = _checks.check_num_samples(num_samples, minimum=minimum)
    if antithetic:
        if num_samples % 2:
            raise ValueError(f"num_samples must be even with antithetic=True, got {num_samples}")
        if not noise.symmetric:
            raise ValueError(
                f"antithetic=True needs a symmetric noise law; {type(noise).__name__} is not"
            )
    if needs_score and not noise.has_score:
        raise ValueError(
            f"the zeroth-order estimator needs a noise law with a differentiable density; "
            f"{type(noise).__name__} has none (use first_order with it)"
        )
    return _checks.check_positive_scalar(sigma, "sigma"), num_samples


def _check_spread(devices, sample_chunk) -> dict:
    """``devices`` and ``sample_chunk``, checked on the host, as keyword arguments for the
    sample evaluation (:func:`rsmooth.parallel.map_samples`)."""
    return dict(devices=parallel.resolve_devices(devices), sample_chunk=parallel.check_sample_chunk(sample_chunk))


def _checked_samples(*arrays_and_messages) -> tuple:
    """The per-sample arrays, checked finite (`ValueError(message)` for the first that is not,
    at run time where traced). The traced check is tied to a zero added to each array rather
    than to the arrays themselves: a runtime check runs on one device, and the arrays, which
    may be laid out across devices (``devices``), would be gathered there."""
    arrays = [array for array, _ in arrays_and_messages]
    if not any(_checks.is_traced(array) for array in arrays):
        return tuple(_checks.check_finite(array, message) for array, message in arrays_and_messages)
    zero = _checks.check_all(jnp.zeros((), arrays[0].dtype), arrays_and_messages)
    return tuple(array + zero.astype(array.dtype) for array in arrays)


def perturbed_points(noise: Noise, key: Array, x: Array, sigma, num_samples: int, antithetic: bool):
    """Noise z (num_samples, d) and the points x + sigma z; with `antithetic`, the second half
    of z is minus the first. The one place samples are drawn, so that every estimator and
    `smooth` see the same points for the same key."""
    shape = (num_samples // 2 if antithetic else num_samples, x.shape[0])
    z = noise.sample(key, shape, x.dtype)
    if antithetic:
        z = jnp.concatenate([z, -z])
    return z, x[None, :] + sigma * z


_NONFINITE_F = "f returned a non-finite value (NaN or inf) at a perturbed point x + sigma * z"
_NONFINITE_GRAD = "the gradient of f is not finite (NaN or inf) at a perturbed point x + sigma * z"


def _mean_and_variance(a: Array, w: Array):
    """Mean over units i of the outer products a_i w_i^T, and the variance of that mean,
    entry by entry, without forming the (N, m, d) array of terms."""
    n = a.shape[0]
    mean = jnp.einsum("im,id->md", a, w, precision="highest") / n
    second = jnp.einsum("im,id->md", a**2, w**2, precision="highest") / n
    if n == 1:
        return mean, jnp.full_like(mean, jnp.inf)
    variance = jnp.maximum(second - mean**2, 0.0) / (n - 1)
    return mean, variance


LEAVE_ONE_OUT = "leave-one-out"
INVERSE_VARIANCE = "inverse_variance"
ALPHA_RULES = ("suh", INVERSE_VARIANCE)


def check_alpha_rule(rule, gamma=None, name: str = "rule") -> str:
    """``rule`` is one of :data:`ALPHA_RULES` (``ValueError`` naming the argument ``name``
    otherwise), and ``gamma``, the trust region of the ``"suh"`` rule, is None with the
    ``"inverse_variance"`` rule (which tests each entry's bias instead); returns ``rule``."""
    if not isinstance(rule, str) or rule not in ALPHA_RULES:
        raise ValueError(f"{name} must be one of {ALPHA_RULES}, got {rule!r}")
    if rule == INVERSE_VARIANCE and gamma is not None:
        raise ValueError(
            f"gamma is the trust region of {name}='suh'; {name}={INVERSE_VARIANCE!r} tests each entry's bias "
            "instead: leave gamma None"
        )
    return rule


def check_baseline(baseline, num_samples: int):
    """``baseline`` is True (``f(x)``), False (none) or ``"leave-one-out"`` (which needs two
    samples or more: always true of alpha order's zeroth-order half, whose estimator takes at
    least four); returns it."""
    if baseline is True or baseline is False:
        return baseline
    if baseline != LEAVE_ONE_OUT:
        raise ValueError(f"baseline must be True, False or {LEAVE_ONE_OUT!r}, got {baseline!r}")
    if num_samples < 2:
        raise ValueError(f"baseline={LEAVE_ONE_OUT!r} needs num_samples >= 2, got {num_samples}")
    return baseline


def baseline_values(values: Array, baseline, f_at_x: Callable[[], Array]) -> Array:
    """The baseline subtracted from each of the ``values`` ``f(x + sigma z_i)`` (M, ...):
    ``f(x)`` (``f_at_x()``, broadcast), zeros, or for ``"leave-one-out"`` the mean of the other
    samples' values, ``b_i = (sum_j f_j - f_i) / (M - 1)``. Each is independent of ``z_i``, so
    the estimator stays unbiased (``E score(z) = 0``). Leave-one-out needs no evaluation at
    ``x`` and is near the smoothed value itself, where ``f(x)`` of a discontinuous ``f`` may
    be far from it: for a step at ``x`` (an edge pixel of a renderer) ``f(x)`` is 0 or 1 while
    the smoothed value is 1/2, which makes each term's variance 0.341 against 0.091 for the
    Gaussian (tests/test_estimators.py; Kool, van Hoof,
    Welling, "Buy 4 REINFORCE samples, get a baseline for free!", ICLR 2019 workshop)."""
    if baseline == LEAVE_ONE_OUT:
        num_samples = values.shape[0]
        return (jnp.sum(values, axis=0, keepdims=True) - values) / (num_samples - 1)
    if baseline:
        return f_at_x()[None]
    return jnp.zeros_like(values[:1])


def _zeroth_order_flat(
    flat: _Flat, key, sigma, num_samples, noise, baseline, antithetic, *, devices=None, sample_chunk=None
) -> _FlatEstimate:
    z, points = perturbed_points(noise, key, flat.x, sigma, num_samples, antithetic)
    values = parallel.map_samples(flat.f, points, devices=devices, sample_chunk=sample_chunk)
    (values,) = _checked_samples((values, _NONFINITE_F))
    reference = baseline_values(values, baseline, lambda: flat.f(flat.x))
    return _zeroth_order_terms(z, values, reference, sigma, noise, antithetic)


def _zeroth_order_terms(z, values, reference, sigma, noise, antithetic) -> _FlatEstimate:
    """The zeroth-order estimate from the noise ``z`` (M, d), the values ``f(x + sigma z)``
    (M, m) and the baseline ``reference`` (1, m), or per sample (M, m) (:func:`baseline_values`).
    (With a per-sample baseline the terms are not quite independent; the variance is estimated
    as if they were.)"""
    num_samples, dim = z.shape
    score = noise.score(z)
    weights = -score / sigma
    # d/dsigma of log[mu((y - x)/sigma) / sigma^d] = -(z . score(z) + d) / sigma.
    sigma_weights = -(jnp.sum(z * score, axis=-1) + dim) / sigma
    centred = values - reference
    if antithetic:
        # A pair (z, -z) is one independent unit; for a symmetric law the score is odd, so
        # the pair's term is (f(x + sigma z) - f(x - sigma z)) / 2 * weight(z): no baseline.
        half = num_samples // 2
        units, unit_weights = 0.5 * (values[:half] - values[half:]), weights[:half]
    else:
        units, unit_weights = centred, weights
    jacobian, variance = _mean_and_variance(units, unit_weights)
    score_norms = jnp.linalg.norm(z, axis=-1) * jnp.linalg.norm(score, axis=-1)
    return _FlatEstimate(
        value=jnp.mean(values, axis=0),
        jacobian=jacobian,
        sigma_grad=jnp.mean(centred * sigma_weights[:, None], axis=0),
        variance=variance,
        max_score_norm=jnp.max(score_norms),
    )


def value_and_jacobian(f_flat: Callable[[Array], Array], v: Array) -> tuple[Array, Array]:
    """f(v) (m,) and its Jacobian (m, d), by reverse mode when m < d, forward mode otherwise.

    Forward mode is a vmap of JVPs over the basis of the input (the primal computed once);
    where ``m = d`` (a scalar function of a scalar, say) it is the cheaper of the two to
    compile and run: no transposed program and no stored residuals."""
    out = jax.eval_shape(f_flat, v)
    m, d = out.shape[0], v.shape[0]
    if m < d:
        y, pullback = jax.vjp(f_flat, v)
        (jacobian,) = jax.vmap(pullback)(jnp.eye(m, dtype=y.dtype))
    else:
        y, jacobian = jax.vmap(lambda e: jax.jvp(f_flat, (v,), (e,)), out_axes=(None, 1))(jnp.eye(d, dtype=v.dtype))
    return y, jacobian


def _first_order_flat(
    flat: _Flat, key, sigma, num_samples, noise, antithetic, jacobian_fn=None, *, devices=None, sample_chunk=None
) -> _FlatEstimate:
    z, points = perturbed_points(noise, key, flat.x, sigma, num_samples, antithetic)
    if jacobian_fn is None:
        def given(v):
            return value_and_jacobian(flat.f, v)
    else:
        def given(v):
            value, jac = jacobian_fn(flat.unravel(v))
            return jnp.reshape(value, (-1,)).astype(v.dtype), jnp.reshape(jac, (-1, v.shape[0])).astype(v.dtype)

    values, jacobians = parallel.map_samples(given, points, devices=devices, sample_chunk=sample_chunk)
    values, jacobians = _checked_samples((values, _NONFINITE_F), (jacobians, _NONFINITE_GRAD))
    return _first_order_terms(z, values, jacobians, antithetic)


def _first_order_terms(z, values, jacobians, antithetic) -> _FlatEstimate:
    """The first-order estimate from the noise ``z`` (M, d), the values ``f(x + sigma z)``
    (M, m) and their Jacobians (M, m, d)."""
    num_samples = z.shape[0]
    units = jacobians
    if antithetic:
        half = num_samples // 2
        units = 0.5 * (jacobians[:half] + jacobians[half:])
    n = units.shape[0]
    jacobian = jnp.mean(units, axis=0)
    if n == 1:
        variance = jnp.full_like(jacobian, jnp.inf)
    else:
        variance = jnp.var(units, axis=0, ddof=1) / n
    return _FlatEstimate(
        value=jnp.mean(values, axis=0),
        jacobian=jacobian,
        # d/dsigma f(x + sigma z) = grad f(x + sigma z) . z
        sigma_grad=jnp.mean(jnp.einsum("imd,id->im", jacobians, z, precision="highest"), axis=0),
        variance=variance,
        max_score_norm=jnp.zeros((), z.dtype),
    )


def _alpha_order_flat(
    flat: _Flat, key, sigma, num_samples, noise, baseline, antithetic, gamma, lipschitz, delta, *, devices=None,
    sample_chunk=None, rule="suh", jacobian_fn=None, cross_fit=False,
):
    key_zeroth, key_first = jax.random.split(key)
    n_zeroth = num_samples // 2
    n_first = num_samples - n_zeroth
    if antithetic and (n_zeroth % 2 or n_first % 2):
        raise ValueError(
            f"with antithetic=True, alpha_order needs num_samples divisible by 4, got {num_samples}"
        )
    spread = dict(devices=devices, sample_chunk=sample_chunk)
    options = (antithetic, gamma, lipschitz, delta, rule)
    if cross_fit:
        zeroth_folds = tuple(_zeroth_order_flat(flat, k, sigma, n_zeroth // 2, noise, baseline, antithetic, **spread)
                             for k in jax.random.split(key_zeroth))
        first_folds = tuple(_first_order_flat(flat, k, sigma, n_first // 2, noise, antithetic, jacobian_fn, **spread)
                            for k in jax.random.split(key_first))
        return _cross_fitted_blend(zeroth_folds, first_folds, n_zeroth, n_first, *options)
    zeroth = _zeroth_order_flat(flat, key_zeroth, sigma, n_zeroth, noise, baseline, antithetic, **spread)
    first = _first_order_flat(flat, key_first, sigma, n_first, noise, antithetic, jacobian_fn, **spread)
    return _alpha_blend(zeroth, first, n_zeroth, n_first, *options)


def _alpha_blend(
    zeroth: _FlatEstimate, first: _FlatEstimate, n_zeroth, n_first, antithetic, gamma, lipschitz, delta, rule="suh",
    targets: tuple[_FlatEstimate, _FlatEstimate] | None = None,
):
    """The alpha-order blend of independent zeroth- and first-order estimates (of ``n_zeroth``
    and ``n_first`` samples) by ``rule`` (see :func:`alpha_order`): the estimate and the extra
    stats (for ``"inverse_variance"``, ``alpha_entries`` is the flat (m, d) array). With
    ``targets = (zeroth', first')`` the weights chosen from ``zeroth`` and ``first`` blend
    those other two estimates instead (cross-fitting, :func:`_cross_fitted_blend`)."""
    target_zeroth, target_first = (zeroth, first) if targets is None else targets
    num_samples = n_zeroth + n_first
    var_zeroth = jnp.sum(zeroth.variance)
    var_first = jnp.sum(first.variance)
    total = var_zeroth + var_first
    # Minimizer of alpha^2 var_first + (1 - alpha)^2 var_zeroth (Suh et al. 2022, Sec. 4).
    alpha_star = jnp.where(total > 0, var_zeroth / jnp.where(total > 0, total, 1.0), 1.0)
    bias = jnp.linalg.norm(first.jacobian - zeroth.jacobian)
    # Confidence radius of the zeroth-order estimate at level 1 - delta: the Gaussian
    # (central-limit) radius sqrt(2 V log(2/delta)); with a Lipschitz constant L, plus the range
    # term of the empirical Bernstein bound (Maurer & Pontil 2009, Thm. 4), since one sample's
    # term is then bounded: |f(x + sigma z) - f(x)| / sigma <= L |z|, so |term| <= L |z| |score(z)|.
    n_units = n_zeroth // 2 if antithetic else n_zeroth
    log_term = math.log(2.0 / delta)
    radius = jnp.sqrt(2.0 * var_zeroth * log_term)
    if lipschitz is not None:
        radius = radius + 7.0 * 2.0 * lipschitz * zeroth.max_score_norm * log_term / (3.0 * max(n_units - 1, 1))
    # How large the empirical bias may be from sampling noise alone, were both unbiased.
    bias_radius = jnp.sqrt(2.0 * (var_zeroth + var_first) * log_term)
    if rule == INVERSE_VARIANCE:
        return _inverse_variance_blend(zeroth, first, n_zeroth, n_first, log_term, bias, radius, bias_radius, targets)
    if gamma is None:
        # Default (our documented choice, scale-free): trust the first-order estimate, with
        # the variance-optimal alpha*, unless its gap to the unbiased zeroth-order estimate is
        # larger than sampling noise explains at level 1 - delta; then alpha = 0. This is the
        # trust region of Suh et al. with gamma = radius + bias_radius, made all-or-nothing
        # (an MSE-optimal alpha with a plug-in estimate of the squared bias is itself too noisy
        # on smooth functions).
        gamma_used = radius + bias_radius
        alpha = jnp.where(bias <= bias_radius, alpha_star, 0.0)
    else:
        gamma_used = jnp.asarray(gamma, radius.dtype)
        safe_bias = jnp.where(bias > 0, bias, 1.0)
        alpha = jnp.where(
            radius + alpha_star * bias <= gamma_used,
            alpha_star,
            jnp.where(gamma_used > radius, (gamma_used - radius) / safe_bias, 0.0),
        )
    alpha = jnp.clip(alpha, 0.0, 1.0)
    value = (n_zeroth * target_zeroth.value + n_first * target_first.value) / num_samples
    blend = lambda a1, a0: alpha * a1 + (1.0 - alpha) * a0  # noqa: E731
    estimate = _FlatEstimate(
        value=value,
        jacobian=blend(target_first.jacobian, target_zeroth.jacobian),
        sigma_grad=blend(target_first.sigma_grad, target_zeroth.sigma_grad),
        variance=alpha**2 * target_first.variance + (1.0 - alpha) ** 2 * target_zeroth.variance,
        max_score_norm=target_zeroth.max_score_norm,
    )
    extra = {
        "alpha": alpha,
        "alpha_star": alpha_star,
        "bias": bias,
        "radius": radius,
        "bias_radius": bias_radius,
        "gamma": gamma_used,
        "variance_first": var_first,
        "variance_zeroth": var_zeroth,
    }
    return estimate, extra


def _inverse_variance_blend(zeroth: _FlatEstimate, first: _FlatEstimate, n_zeroth, n_first, log_term, bias, radius,
                            bias_radius, targets=None):
    """The per-entry (inverse-variance) blend of :func:`alpha_order` with
    ``rule="inverse_variance"``; ``log_term`` is ``log(2 / delta)``, the other scalars are the
    "suh" rule's stats, reported alike; ``targets`` as in :func:`_alpha_blend`."""
    target_zeroth, target_first = (zeroth, first) if targets is None else targets
    var_zeroth, var_first = zeroth.variance, first.variance  # (m, d), entry by entry
    total = var_zeroth + var_first
    # Minimum-variance weights of two independent unbiased estimates of the same entry; where
    # both variances are 0, 1, as the "suh" rule's alpha* (the bias test below then decides:
    # its radius is 0, so alpha = 0 unless the two estimates agree exactly, and then any
    # weight gives the same estimate).
    alpha_star = jnp.where(total > 0, var_zeroth / jnp.where(total > 0, total, 1.0), 1.0)
    # The "suh" rule's bias test, entry by entry: trust an entry's first-order estimate unless
    # its gap to the zeroth-order one exceeds what sampling noise explains at level 1 - delta.
    trusted = jnp.abs(first.jacobian - zeroth.jacobian) <= jnp.sqrt(2.0 * total * log_term)
    alpha = jnp.clip(jnp.where(trusted, alpha_star, 0.0), 0.0, 1.0)
    # d f_sigma / d sigma by first order, E[grad f(x + sigma z) . z], is biased wherever any
    # entry of its row of the Jacobian is: each output takes the smallest weight of its row.
    alpha_row = jnp.min(alpha, axis=1)
    estimate = _FlatEstimate(
        value=(n_zeroth * target_zeroth.value + n_first * target_first.value) / (n_zeroth + n_first),
        jacobian=alpha * target_first.jacobian + (1.0 - alpha) * target_zeroth.jacobian,
        sigma_grad=alpha_row * target_first.sigma_grad + (1.0 - alpha_row) * target_zeroth.sigma_grad,
        variance=alpha**2 * target_first.variance + (1.0 - alpha) ** 2 * target_zeroth.variance,
        max_score_norm=target_zeroth.max_score_norm,
    )
    extra = {
        "alpha": jnp.mean(alpha),
        "alpha_entries": alpha,
        "trusted_fraction": jnp.mean(trusted.astype(alpha.dtype)),
        "bias": bias,
        "radius": radius,
        "bias_radius": bias_radius,
        "variance_first": jnp.sum(var_first),
        "variance_zeroth": jnp.sum(var_zeroth),
    }
    return estimate, extra


def _cross_fitted_blend(zeroth_folds, first_folds, n_zeroth, n_first, antithetic, gamma, lipschitz, delta, rule):
    """Alpha order with cross-fitted weights: each half's samples form two folds ``a`` and
    ``b``; the weights chosen from fold ``b``'s two estimates blend fold ``a``'s, and the
    other way round; the two blends are averaged (so are the stats).

    Why: weights chosen from the very samples they blend are correlated with them. Where a
    stiff contact gives the first-order samples rare large gradients, the first-order half's
    variance (and its gap to the zeroth-order half) is large exactly when a sample hit the
    contact, so the rule keeps first order when no sample did: the blend is then biased
    against the contact's pull, even where both halves are unbiased. Weights from independent
    samples cannot correlate with what they blend: the blend of two unbiased estimates stays
    unbiased, at the price of weights from half as many samples."""
    (zeroth_a, zeroth_b), (first_a, first_b) = zeroth_folds, first_folds
    options = (antithetic, gamma, lipschitz, delta, rule)
    blend_a, extra_a = _alpha_blend(zeroth_b, first_b, n_zeroth // 2, n_first // 2, *options, targets=(zeroth_a, first_a))
    blend_b, extra_b = _alpha_blend(zeroth_a, first_a, n_zeroth // 2, n_first // 2, *options, targets=(zeroth_b, first_b))
    estimate = _FlatEstimate(
        value=0.5 * (blend_a.value + blend_b.value),
        jacobian=0.5 * (blend_a.jacobian + blend_b.jacobian),
        sigma_grad=0.5 * (blend_a.sigma_grad + blend_b.sigma_grad),
        variance=0.25 * (blend_a.variance + blend_b.variance),  # two independent blends
        max_score_norm=jnp.maximum(blend_a.max_score_norm, blend_b.max_score_norm),
    )
    return estimate, jax.tree.map(lambda a, b: 0.5 * (a + b), extra_a, extra_b)


def check_cross_fit(cross_fit, num_samples: int, antithetic: bool = False, name: str = "cross_fit") -> None:
    """Cross-fitted alpha order splits each half of the samples into two folds of at least two
    samples (antithetic pairs kept whole)."""
    if not isinstance(cross_fit, bool):
        raise TypeError(f"{name} must be a bool, got {cross_fit!r}")
    unit = 8 if antithetic else 4
    if cross_fit and (num_samples < 2 * unit or num_samples % unit):
        raise ValueError(f"{name}=True needs num_samples a multiple of {unit} and >= {2 * unit}"
                         f"{' (antithetic pairs in four folds)' if antithetic else ' (four folds of two samples or more)'}, "
                         f"got {num_samples}")


def _shared_sample_estimate(
    index, z, values, jacobians, reference, sigma, noise, gamma, lipschitz, delta, baseline=True, rule="suh",
):
    """The first- (``index`` 0), zeroth- (1), alpha-order (2) or cross-fitted alpha-order (3,
    where the samples split into four folds: :func:`check_cross_fit`) estimate from one set of
    samples: the noise ``z`` (M, d) (independent draws, no antithetic pairs), the values
    ``f(x + sigma z)`` (M, m), their Jacobians (M, m, d) and ``f(x)`` ``reference`` (m,), the
    baseline unless ``baseline`` is False or ``"leave-one-out"`` (:func:`baseline_values`).

    ``index`` may be traced: the estimators then share one evaluation of ``f`` and its
    Jacobian at the points, and one compiled program serves them all (a comparison of the
    estimators compiles the costly part once). First and zeroth order use all M samples;
    alpha order the first half for its zeroth-order estimate and the second half for its
    first-order one (independent halves, as :func:`alpha_order`), blended by ``rule``. Returns
    the estimate and alpha (1 for first order, 0 for zeroth order; the mean weight over the
    entries for ``rule="inverse_variance"``)."""
    num_samples = z.shape[0]
    half = num_samples // 2
    one = jnp.ones((), z.dtype)

    def first():
        return _first_order_terms(z, values, jacobians, False), one

    def zeroth():
        centre = baseline_values(values, baseline, lambda: reference)
        return _zeroth_order_terms(z, values, centre, sigma, noise, False), 0.0 * one

    def zeroth_terms(start, stop):
        part = values[start:stop]
        return _zeroth_order_terms(z[start:stop], part, baseline_values(part, baseline, lambda: reference), sigma, noise,
                                   False)

    def first_terms(start, stop):
        return _first_order_terms(z[start:stop], values[start:stop], jacobians[start:stop], False)

    options = (False, gamma, lipschitz, delta, rule)

    def alpha():
        estimate, extra = _alpha_blend(zeroth_terms(0, half), first_terms(half, num_samples), half,
                                       num_samples - half, *options)
        return estimate, extra["alpha"].astype(z.dtype)

    def cross_fitted_alpha():
        quarter, rest = half // 2, half + (num_samples - half) // 2
        estimate, extra = _cross_fitted_blend(
            (zeroth_terms(0, quarter), zeroth_terms(quarter, half)),
            (first_terms(half, rest), first_terms(rest, num_samples)), half, num_samples - half, *options)
        return estimate, extra["alpha"].astype(z.dtype)

    # The cross-fitted branch exists where the samples make four folds (index 3 is refused
    # before any solve otherwise).
    folds = num_samples >= 8 and num_samples % 4 == 0
    return jax.lax.switch(index, (first, zeroth, alpha, cross_fitted_alpha) if folds else (first, zeroth, alpha))


def _package(flat: _Flat, estimate: _FlatEstimate, extra_stats=None) -> Estimate:
    stats = {
        "variance": jnp.sum(estimate.variance),
        "std_error": _unflatten_jacobian(flat, jnp.sqrt(estimate.variance)),
    }
    stats.update(extra_stats or {})
    return Estimate(
        value=jnp.reshape(estimate.value, flat.out_shape),
        grad=_unflatten_jacobian(flat, estimate.jacobian),
        sigma_grad=jnp.reshape(estimate.sigma_grad, flat.out_shape),
        stats=stats,
    )


def zeroth_order(
    f: Callable,
    key: Array,
    x,
    *,
    sigma: ArrayLike,
    num_samples: int,
    noise: Noise = Gaussian(),
    baseline: bool | str = True,
    antithetic: bool = False,
    devices: str | Sequence[jax.Device] | None = None,
    sample_chunk: int | None = None,
) -> Estimate:
    r"""Zeroth-order (score-function) estimate of the smoothed value and gradient.

    .. math:: \hat g = \frac{1}{M}\sum_{i=1}^M \big(f(x + \sigma z_i) - b\big)\,
        \frac{-\nabla\log\mu(z_i)}{\sigma}, \qquad b = f(x) \text{ if baseline else } 0
        \text{ (or } b_i = \tfrac{1}{M-1}\textstyle\sum_{j \ne i} f(x + \sigma z_j)\text{, leave-one-out)}.

    Args:
        f: function of `x` returning one floating array; need not be differentiable.
        key: a `jax.random` key.
        x: the point, any pytree of floating arrays.
        sigma: noise scale, positive (may be traced).
        num_samples: number of samples M (even with `antithetic`).
        noise: the noise law; it must have a differentiable density (not `Uniform`).
        baseline: True: subtract `f(x)` (costs one more evaluation of `f`, lowers the variance);
            ``"leave-one-out"``: subtract from each sample the mean of the others (no extra
            evaluation; lower variance where `f` jumps at `x`; M >= 2); False: none.
        antithetic: use pairs `(z, -z)` (symmetric laws only); the baseline then cancels.
        devices: where `f` is evaluated at the samples: ``None`` (default) on the default
            device; ``"all"`` (every device of every process) or a sequence of devices: the
            samples split over them, each device evaluating its share, the means summed
            across devices (:mod:`rsmooth.parallel`). The samples are drawn whole from `key`
            first: the estimate is the one-device estimate up to rounding (for an `f` whose
            value at a sample does not depend on the samples evaluated with it).
        sample_chunk: the most samples at which `f` is evaluated at once (on each device);
            ``None``: all of them, except on several CPU devices: one at a time (see
            :mod:`rsmooth.parallel`). Bounds the memory of `f`'s intermediate values; the
            estimate is unchanged up to rounding.

    Returns:
        An :class:`Estimate`.

    Raises:
        ValueError: for a non-finite `x` or value of `f`, or a `sigma` below the resolution of
            `x`'s dtype at every coordinate, :math:`\sigma < \epsilon \min_k |x_k|` (then
            `x + sigma * z` rounds to `x` and the estimate would be zero); at run time (an
            `equinox` error) where these values are traced.

    Example:
        >>> import jax, jax.numpy as jnp, rsmooth
        >>> step = lambda x: jnp.where(x > 0, 1.0, 0.0)
        >>> est = rsmooth.zeroth_order(step, jax.random.key(0), jnp.array(0.0),
        ...                            sigma=1.0, num_samples=20000)
        >>> abs(float(est.grad) - 0.3989) < 0.02   # the normal density at 0
        True

    References:
        Berthet, Blondel, Teboul, Cuturi, Vert, Bach, "Learning with differentiable perturbed
        optimizers", NeurIPS 2020.
    """
    _checks.check_key(key)
    sigma, num_samples = _check_options(sigma, num_samples, noise, antithetic=antithetic, needs_score=True)
    check_baseline(baseline, num_samples)
    spread = _check_spread(devices, sample_chunk)
    flat = _flatten_resolved(f, x, sigma)
    return _package(flat, _zeroth_order_flat(flat, key, sigma, num_samples, noise, baseline, antithetic, **spread))


def first_order(
    f: Callable,
    key: Array,
    x,
    *,
    sigma: ArrayLike,
    num_samples: int,
    noise: Noise = Gaussian(),
    antithetic: bool = False,
    value_and_jacobian: Callable | None = None,
    devices: str | Sequence[jax.Device] | None = None,
    sample_chunk: int | None = None,
) -> Estimate:
    r"""First-order (pathwise) estimate: the mean of sampled gradients.

    .. math:: \hat g = \frac{1}{M}\sum_{i=1}^M \nabla f(x + \sigma z_i).

    Unbiased for continuous, almost-everywhere differentiable `f`; biased (zero) across jumps.
    A `sigma` below the resolution of `x`'s dtype is allowed (unlike :func:`zeroth_order`): the
    estimate is then `f`'s derivative at `x`, its limit as `sigma` vanishes.

    Args:
        f: function of `x` returning one floating array, differentiable by JAX.
        key: a `jax.random` key.
        x: the point, any pytree of floating arrays.
        sigma: noise scale, positive (may be traced).
        num_samples: number of samples M (even with `antithetic`).
        noise: the noise law (any, `Uniform` included).
        antithetic: use pairs `(z, -z)` (symmetric laws only).
        value_and_jacobian: optional `x -> (f(x), J(x))` for an `f` that has a faster
            Jacobian than JAX's autodiff of it (e.g. a simulator's `step_and_jacobians`);
            `x` must then be one array and `J(x)` of shape `f(x).shape + x.shape`. By
            default the Jacobian is autodiff of `f`.
        devices: where `f` and its Jacobian are evaluated at the samples, as in
            :func:`zeroth_order`; each device runs its own loops (a contact solve iterates as
            long as that device's samples need).
        sample_chunk: the most samples at which `f` and its Jacobian are evaluated at once
            (on each device), as in :func:`zeroth_order`.

    Returns:
        An :class:`Estimate`.

    Example:
        >>> import jax, jax.numpy as jnp, rsmooth
        >>> est = rsmooth.first_order(jnp.sin, jax.random.key(0), jnp.array(0.3),
        ...                           sigma=1e-3, num_samples=4)
        >>> abs(float(est.grad) - float(jnp.cos(0.3))) < 1e-3
        True
    """
    _checks.check_key(key)
    sigma, num_samples = _check_options(sigma, num_samples, noise, antithetic=antithetic)
    spread = _check_spread(devices, sample_chunk)
    flat = _flatten(f, x)
    if value_and_jacobian is not None and not isinstance(x, (jax.Array, np.ndarray)):
        raise TypeError(f"value_and_jacobian needs x to be one array, got {type(x).__name__}")
    return _package(
        flat, _first_order_flat(flat, key, sigma, num_samples, noise, antithetic, value_and_jacobian, **spread)
    )


def alpha_order(
    f: Callable,
    key: Array,
    x,
    *,
    sigma: ArrayLike,
    num_samples: int,
    noise: Noise = Gaussian(),
    gamma: ArrayLike | None = None,
    lipschitz: float | None = None,
    delta: float = 0.05,
    baseline: bool | str = True,
    antithetic: bool = False,
    devices: str | Sequence[jax.Device] | None = None,
    sample_chunk: int | None = None,
    rule: str = "suh",
    value_and_jacobian: Callable | None = None,
    cross_fit: bool = False,
) -> Estimate:
    r"""Alpha-order estimate: :math:`\alpha \hat g_1 + (1 - \alpha)\hat g_0` on independent batches.

    Half of the samples feed the zeroth-order estimate :math:`\hat g_0`, half the first-order
    :math:`\hat g_1`. With :math:`\hat\sigma_0^2, \hat\sigma_1^2` their empirical variances,
    :math:`\hat B = \|\hat g_1 - \hat g_0\|` the empirical bias and :math:`\varepsilon` the
    confidence radius of :math:`\hat g_0` at level :math:`1 - \delta`, alpha solves

    .. math:: \min_\alpha\ \alpha^2\hat\sigma_1^2 + (1-\alpha)^2\hat\sigma_0^2
        \quad\text{s.t.}\quad \varepsilon + \alpha \hat B \le \gamma,

    i.e. :math:`\alpha^* = \hat\sigma_0^2 / (\hat\sigma_0^2 + \hat\sigma_1^2)` when it satisfies
    the constraint, :math:`(\gamma - \varepsilon)/\hat B` when only a smaller alpha does, and 0
    when even :math:`\alpha = 0` violates it (the first-order estimate cannot be trusted).

    With ``rule="inverse_variance"`` each entry :math:`k` of the flattened gradient (of the
    Jacobian, for an array-valued `f`) gets its own weight, from the empirical variances
    :math:`\hat v_{0,k}, \hat v_{1,k}` of that entry's two estimates:

    .. math:: \alpha_k = \frac{\hat v_{0,k}}{\hat v_{0,k} + \hat v_{1,k}} \ \text{if}\
        |\hat g_{1,k} - \hat g_{0,k}| \le \sqrt{2 (\hat v_{0,k} + \hat v_{1,k}) \log(2/\delta)},
        \qquad \alpha_k = 0 \ \text{otherwise}.

    The weight is the classical inverse-variance one: the minimum-variance unbiased
    combination of two independent unbiased estimates of the same quantity. The safeguard is
    the default ``"suh"`` rule's bias test applied to each entry: an entry whose first-order
    estimate differs from the unbiased zeroth-order one by more than sampling noise explains
    falls back to zeroth order, whatever the others do; where one scalar alpha must serve
    every entry, a smooth coordinate and a jump in another share one compromise. The test
    runs at level :math:`1 - \delta` per entry, without a correction for the number of
    entries: a false alarm only costs one entry the variance of its zeroth-order estimate,
    while a radius that grew with the dimension would let more first-order bias through.
    Where both variances of an entry are 0, :math:`\alpha_k = 1` (as the ``"suh"`` rule's
    :math:`\alpha^*`) and the test's radius is 0: the entry falls back to zeroth order
    unless the two estimates agree exactly, when any weight gives the same estimate. The
    estimate of :math:`\partial f_\sigma / \partial\sigma` of each output takes the
    smallest weight of its row (its first-order estimate is biased wherever one of the row's
    entries is). Onoda, Parmas et al. (2026) revisit the paper's discontinuous tasks with
    this per-entry weighting.

    Args:
        f: function of `x` returning one floating array, differentiable by JAX.
        key: a `jax.random` key.
        x: the point, any pytree of floating arrays.
        sigma: noise scale, positive (may be traced).
        num_samples: total number of samples M >= 4, split evenly between the two estimates
            (a multiple of 4 with `antithetic`).
        noise: the noise law, with a differentiable density.
        gamma: the trust-region radius on the total error bound, as in Suh et al. When None
            (default, our scale-free choice): alpha = 0 (the first-order estimate is not
            trusted) when the empirical bias exceeds `bias_radius`, the size sampling noise
            alone explains at level 1 - delta; otherwise alpha = alpha*. With few samples a
            bias near a discontinuity may go undetected: use more samples or set gamma.
        lipschitz: a Lipschitz constant of `f`; it adds the range term of an empirical
            Bernstein bound to the confidence radius (without it, the Gaussian radius).
        delta: the confidence level of the radius is `1 - delta`.
        baseline: baseline for the zeroth-order part (as in :func:`zeroth_order`).
        antithetic: antithetic pairs in both parts.
        devices, sample_chunk: where and how many samples at a time `f` is evaluated, for
            each part (as in :func:`zeroth_order`).
        rule: ``"suh"`` (default): one alpha for the whole gradient, as above;
            ``"inverse_variance"``: one weight per entry (above; `gamma` must then be None).
        value_and_jacobian: optional `x -> (f(x), J(x))` for the first-order half, as in
            :func:`first_order` (`x` one array); the zeroth-order half evaluates `f`.
        cross_fit: choose the weights on independent samples: each half splits into two
            folds, the weights from one fold's two estimates blend the other fold's, and the
            two blends are averaged (`num_samples` a multiple of 4, >= 8; of 8, >= 16, with
            `antithetic`). Weights chosen from the samples they blend are correlated with
            them and bias the blend: at a stiff contact, whose rare large first-order
            gradients raise the first-order variance exactly when a sample hits it, the
            default keeps first order mostly when no sample hit, and the blend misses the
            contact's pull. Cross-fitted weights leave the blend of two unbiased estimates
            unbiased, from half as many samples each. The stats are the two folds' means.

    Returns:
        An :class:`Estimate` whose `stats` hold `alpha`, `alpha_star`, `bias`, `radius`,
        `bias_radius`, `gamma`, `variance_first`, `variance_zeroth`; with
        ``rule="inverse_variance"``: `alpha` (the mean of the per-entry weights),
        `alpha_entries` (the weights, structure of `grad`), `trusted_fraction` (the fraction
        of entries whose bias test passed), `bias`, `radius`, `bias_radius`,
        `variance_first`, `variance_zeroth`.

    Raises:
        ValueError: as :func:`zeroth_order` (its zeroth-order half needs `sigma` above the
            resolution of `x`'s dtype too); for an unknown `rule`, or a `gamma` with
            ``rule="inverse_variance"``.

    Example:
        >>> import jax, jax.numpy as jnp, rsmooth
        >>> step = lambda x: jnp.where(x > 0, 1.0, 0.0)
        >>> est = rsmooth.alpha_order(step, jax.random.key(0), jnp.array(0.0),
        ...                           sigma=1.0, num_samples=2000)
        >>> float(est.stats["alpha"])   # the zero first-order gradient is not trusted
        0.0

    References:
        Suh, Simchowitz, Zhang, Tedrake, "Do differentiable simulators give better policy
        gradients?", ICML 2022.
    """
    _checks.check_key(key)
    sigma, num_samples = _check_options(
        sigma, num_samples, noise, antithetic=antithetic, needs_score=True, minimum=4
    )
    check_baseline(baseline, num_samples)
    if not 0.0 < delta < 1.0:
        raise ValueError(f"delta must be in (0, 1), got {delta}")
    if lipschitz is not None and not lipschitz > 0:
        raise ValueError(f"lipschitz must be positive, got {lipschitz}")
    if gamma is not None and not _checks.is_traced(gamma) and not float(gamma) >= 0:
        raise ValueError(f"gamma must be non-negative, got {gamma}")
    check_alpha_rule(rule, gamma)
    check_cross_fit(cross_fit, num_samples, antithetic)
    spread = _check_spread(devices, sample_chunk)
    if value_and_jacobian is not None and not isinstance(x, (jax.Array, np.ndarray)):
        raise TypeError(f"value_and_jacobian needs x to be one array, got {type(x).__name__}")
    flat = _flatten_resolved(f, x, sigma)
    estimate, extra = _alpha_order_flat(
        flat, key, sigma, num_samples, noise, baseline, antithetic, gamma, lipschitz, delta, rule=rule,
        jacobian_fn=value_and_jacobian, cross_fit=cross_fit, **spread
    )
    if rule == INVERSE_VARIANCE:
        extra["alpha_entries"] = _unflatten_jacobian(flat, extra["alpha_entries"])
    return _package(flat, estimate, extra)
