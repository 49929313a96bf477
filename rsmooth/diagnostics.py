r"""When an estimator can be trusted: its bias and variance over repeated keys, a bias test,
and the Monte-Carlo smoothing of a function along a sweep.

Suh, Simchowitz, Zhang and Tedrake ("Do differentiable simulators give better policy
gradients?", ICML 2022) show how the first-order (pathwise) estimate fails: on a stiff
function its variance explodes, and at a discontinuity it is biased, and silently so: once no
sample lands on the ramp of a step, every sampled gradient is zero and so is the estimate's
own variance. Repeating an estimator over independent keys shows the first failure
(:func:`estimator_bias_variance`: the spread across repeats, and what the estimator itself
reported); only a comparison with an unbiased estimate or a closed form shows the second
(:func:`bias_test`, the test that :func:`rsmooth.alpha_order` applies to choose its blend).
:func:`smoothed_landscape` evaluates the smoothed function itself, :math:`f_\sigma(x) =
\mathbb{E} f(x + \sigma z)`, along a sweep of points, which shows where smoothing turns a jump
into a slope.

:mod:`rsmooth.stats` has the plain version of the first: :func:`rsmooth.stats.diagnose`
compares the gradients of repeated estimates with a reference it requires.
"""

from __future__ import annotations

import math
from typing import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import Array
from jax.flatten_util import ravel_pytree
from jax.typing import ArrayLike

from rsmooth import _checks
from rsmooth.estimators import Estimate, perturbed_points
from rsmooth.noise import Gaussian, Noise

__all__ = [
    "BiasTest",
    "BiasVariance",
    "Landscape",
    "bias_test",
    "estimator_bias_variance",
    "smoothed_landscape",
]


class BiasVariance(eqx.Module):
    """An estimator's gradients over independent keys, and what they say about it.

    Attributes:
        mean: the mean gradient over the repeats (structure of the gradient).
        variance: the total variance of one estimate across the repeats (the trace of the
            covariance, unbiased), what the estimator's error actually is.
        reported_variance: the variance each repeat's estimate reported of itself
            (``stats["variance"]``), shape ``(repeats,)``: for an estimator that is
            right about itself, its mean is near `variance`; a first-order estimate of a step
            that no sample reached reports 0.
        reported_std_error: the standard error each repeat reported, entry by entry
            (``stats["std_error"]``, structure of the gradient with a leading repeat axis);
            None if the estimator does not report it.
        bias: the norm of ``mean - reference``; None without a reference.
        bias_std_error: ``sqrt(variance / repeats)``, the sampling error of `mean`: a bias
            well above it is not sampling noise.
        zero_fraction: the fraction of repeats whose gradient is exactly zero (every entry).
        grads: the gradient of every repeat (leading axis: repeat).
        stats: the estimator's ``stats`` of every repeat (leading axis: repeat), e.g. the
            ``alpha`` that :func:`rsmooth.alpha_order` chose each time.
    """

    mean: object
    variance: Array
    reported_variance: Array
    reported_std_error: object
    bias: Array | None
    bias_std_error: Array
    zero_fraction: Array
    grads: object
    stats: dict


def _rows(tree, leading: int) -> Array:
    """The leaves of a pytree with a leading axis, flattened into rows ``(leading, size)``."""
    return jnp.concatenate([jnp.reshape(leaf, (leading, -1)) for leaf in jax.tree.leaves(tree)], axis=1)


def estimator_bias_variance(
    estimator: Callable,
    f: Callable,
    key: Array,
    x,
    *,
    repeats: int,
    reference=None,
    **kwargs,
) -> BiasVariance:
    """Runs an estimator over `repeats` independent keys (batched by `vmap`) and summarizes
    its gradients: their mean, their spread, the variance the estimator reported of itself,
    how often it returned an exact zero, and its bias against a reference when one is given.

    Args:
        estimator: :func:`rsmooth.zeroth_order`, :func:`rsmooth.first_order`,
            :func:`rsmooth.alpha_order`, or any function with their signature whose
            :class:`~rsmooth.Estimate` has ``stats["variance"]``.
        f: the function whose smoothed gradient is estimated.
        key: a `jax.random` key; repeat ``i`` uses the ``i``-th of ``jax.random.split(key,
            repeats)``.
        x: the point, any pytree of floating arrays.
        repeats: the number of independent estimates, >= 2 (a Python int: it fixes shapes).
        reference: the true smoothed gradient (structure of the gradient, or broadcastable to
            it, e.g. a closed form); None: no bias is computed.
        **kwargs: passed to the estimator (``sigma``, ``num_samples``, ``noise``, ...).

    Returns:
        A :class:`BiasVariance`.

    Raises:
        ValueError: `repeats` is below 2, or `reference` does not broadcast to the gradient.
        TypeError: `key` is not a PRNG key, `repeats` is not an int, or the estimator's
            stats have no ``"variance"``.

    Example:
        >>> import jax, jax.numpy as jnp, rsmooth
        >>> step = lambda x: jnp.where(x > 0, 1.0, 0.0)
        >>> d = rsmooth.diagnostics.estimator_bias_variance(
        ...     rsmooth.first_order, step, jax.random.key(0), jnp.array(0.0),
        ...     repeats=8, reference=0.3989, sigma=1.0, num_samples=16)
        >>> float(d.zero_fraction), float(d.variance), round(float(d.bias), 4)
        (1.0, 0.0, 0.3989)

    References:
        Suh, Simchowitz, Zhang, Tedrake, "Do differentiable simulators give better policy
        gradients?", ICML 2022, Sec. 3 (empirical bias and variance of the two estimators).
    """
    _checks.check_key(key)
    repeats = _checks.check_num_samples(repeats, "repeats", minimum=2)
    keys = jax.random.split(key, repeats)
    estimates = jax.vmap(lambda k: estimator(f, k, x, **kwargs))(keys)
    if not isinstance(estimates, Estimate) or "variance" not in estimates.stats:
        raise TypeError("estimator must return an rsmooth.Estimate whose stats hold 'variance'")
    grads = estimates.grad
    rows = _rows(grads, repeats)
    variance = jnp.sum(jnp.var(rows, axis=0, ddof=1))
    mean_tree = jax.tree.map(lambda leaf: jnp.mean(leaf, axis=0), grads)
    bias = None
    if reference is not None:
        try:
            reference_tree = jax.tree.map(
                lambda m, r: jnp.broadcast_to(jnp.asarray(r, m.dtype), m.shape), mean_tree, reference
            )
        except (ValueError, TypeError) as error:
            raise ValueError(f"reference must have the structure of the gradient or broadcast to it: {error}") from None
        bias = jnp.linalg.norm(jnp.mean(rows, axis=0) - ravel_pytree(reference_tree)[0])
    return BiasVariance(
        mean=mean_tree,
        variance=variance,
        reported_variance=estimates.stats["variance"],
        reported_std_error=estimates.stats.get("std_error"),
        bias=bias,
        bias_std_error=jnp.sqrt(variance / repeats),
        zero_fraction=jnp.mean(jnp.all(rows == 0, axis=1).astype(rows.dtype)),
        grads=grads,
        stats=dict(estimates.stats),
    )


class BiasTest(eqx.Module):
    """The outcome of :func:`bias_test`.

    Attributes:
        biased: whether the gap exceeds the radius (a boolean array).
        gap: the norm of the difference of the two gradients.
        radius: the gap that sampling noise alone explains at level ``1 - delta``.
    """

    biased: Array
    gap: Array
    radius: Array


def bias_test(estimate: Estimate, reference, *, delta: float = 0.05) -> BiasTest:
    r"""Is an estimate's gradient farther from a reference than sampling noise explains?

    With :math:`V` and :math:`V_r` the estimated variances (``stats["variance"]``) of the
    estimate and of the reference (0 for a closed form), the test flags

    .. math:: \|\hat g - g_r\| > \sqrt{2 (V + V_r) \log(2 / \delta)},

    the trust-region test :func:`rsmooth.alpha_order` applies to its two halves (where it
    flags, alpha order with its default ``gamma`` falls back to the zeroth-order estimate).
    An unbiased reference, a zeroth-order estimate or a closed form, catches what the estimate's
    own variance cannot: a first-order estimate of a step whose samples all missed the step is
    zero with zero variance, and only its distance to the reference shows the bias.

    One estimate against one reference; ``jax.vmap`` it over batched estimates.

    Args:
        estimate: the :class:`~rsmooth.Estimate` under test.
        reference: another :class:`~rsmooth.Estimate` of the same gradient (independent
            samples), or the gradient itself (structure of ``estimate.grad``, or broadcastable
            to it).
        delta: the test's level: an unbiased estimate is flagged with probability about
            `delta` or less (when its variance estimate is right), in ``(0, 1)``.

    Returns:
        A :class:`BiasTest`.

    Raises:
        ValueError: `delta` is not in ``(0, 1)``, or `reference` does not broadcast to the
            gradient.

    Example:
        >>> import jax, jax.numpy as jnp, rsmooth
        >>> step = lambda x: jnp.where(x > 0, 1.0, 0.0)
        >>> k0, k1 = jax.random.split(jax.random.key(0))
        >>> first = rsmooth.first_order(step, k0, jnp.array(0.0), sigma=1.0, num_samples=64)
        >>> zeroth = rsmooth.zeroth_order(step, k1, jnp.array(0.0), sigma=1.0, num_samples=64)
        >>> bool(rsmooth.diagnostics.bias_test(first, zeroth).biased)
        True

    References:
        Suh, Simchowitz, Zhang, Tedrake, "Do differentiable simulators give better policy
        gradients?", ICML 2022, Sec. 4.
    """
    if not isinstance(delta, (int, float)) or isinstance(delta, bool) or not 0.0 < delta < 1.0:
        raise ValueError(f"delta must be a number in (0, 1), got {delta!r}")
    if not isinstance(estimate, Estimate):
        raise TypeError(f"estimate must be an rsmooth.Estimate, got {type(estimate).__name__}")
    grad, _ = ravel_pytree(estimate.grad)
    if isinstance(reference, Estimate):
        other, _ = ravel_pytree(reference.grad)
        if other.shape != grad.shape:
            raise ValueError(f"reference's gradient has {other.size} entries, the estimate's {grad.size}")
        reference_variance = reference.stats["variance"]
    else:
        try:
            tree = jax.tree.map(lambda g, r: jnp.broadcast_to(jnp.asarray(r, g.dtype), g.shape), estimate.grad, reference)
        except (ValueError, TypeError) as error:
            raise ValueError(f"reference must have the structure of the gradient or broadcast to it: {error}") from None
        other, _ = ravel_pytree(tree)
        reference_variance = jnp.zeros((), grad.dtype)
    gap = jnp.linalg.norm(grad - other)
    radius = jnp.sqrt(2.0 * (estimate.stats["variance"] + reference_variance) * math.log(2.0 / delta))
    return BiasTest(biased=gap > radius, gap=gap, radius=radius)


class Landscape(eqx.Module):
    """A function and its smoothing along a sweep of points (:func:`smoothed_landscape`).

    Attributes:
        value: the Monte-Carlo estimate of :math:`f_\\sigma` at each point, shape
            ``(N,) + f_shape``.
        std_error: its standard error at each point (same shape).
        unsmoothed: `f` itself at each point (same shape), evaluated in the same batch.
    """

    value: Array
    std_error: Array
    unsmoothed: Array


def smoothed_landscape(
    f: Callable,
    key: Array,
    xs: ArrayLike,
    *,
    sigma: ArrayLike,
    num_samples: int,
    noise: Noise = Gaussian(),
) -> Landscape:
    r"""The randomized smoothing :math:`f_\sigma(x) = \mathbb{E}_z f(x + \sigma z)` of `f` at
    every point of a sweep, by Monte Carlo with common random numbers.

    Every point uses the same draws :math:`z_1, \dots, z_M` (those the estimators draw from
    `key`, :func:`rsmooth.estimators.perturbed_points`): the Monte-Carlo error is then the
    same smooth-ish function along the sweep rather than independent noise at each point, so
    the curve's shape, a jump turned into a slope, shows at a few dozen samples. Its
    remaining jumps are those of single samples, each at most the range of `f` over `M`.
    `f` at the points themselves is evaluated in the same batch (one program, one vmap), to
    compare the landscape with its smoothing.

    Args:
        f: the function of one point (shape ``xs.shape[1:]``) returning one floating array;
            need not be differentiable or continuous.
        key: a `jax.random` key.
        xs: the sweep: points stacked along the first axis, ``(N,) + point_shape``.
        sigma: the noise scale, positive (may be traced, e.g. vmapped over).
        num_samples: Monte-Carlo samples M per point, >= 2.
        noise: the noise law (any law of :mod:`rsmooth.noise`).

    Returns:
        A :class:`Landscape`: the smoothed value, its standard error and `f` itself at each
        point.

    Raises:
        ValueError: `xs` has no leading axis or is empty, `num_samples` is below 2, or
            `sigma` is not positive and finite.
        TypeError: `key` is not a PRNG key, `xs` is not floating or `noise` is not a law.

    Example:
        >>> import jax, jax.numpy as jnp, rsmooth
        >>> step = lambda x: jnp.where(x > 0, 1.0, 0.0)
        >>> s = rsmooth.diagnostics.smoothed_landscape(step, jax.random.key(0), jnp.array([0.0]),
        ...                                           sigma=1.0, num_samples=4000)
        >>> abs(float(s.value[0]) - 0.5) < 3 * float(s.std_error[0])
        True

    References:
        Suh, Simchowitz, Zhang, Tedrake, "Do differentiable simulators give better policy
        gradients?", ICML 2022, Sec. 2 (the randomized smoothing of a discontinuous
        objective).
    """
    _checks.check_key(key)
    if not isinstance(noise, Noise):
        raise TypeError(f"noise must be an rsmooth.noise.Noise (e.g. Gaussian()), got {noise!r}")
    num_samples = _checks.check_num_samples(num_samples, minimum=2)
    sigma = _checks.check_positive_scalar(sigma, "sigma")
    xs = jnp.asarray(xs)
    if not jnp.issubdtype(xs.dtype, jnp.floating):
        raise TypeError(f"xs must hold floating-point points, got dtype {xs.dtype}")
    if xs.ndim == 0 or xs.shape[0] == 0:
        raise ValueError(f"xs must stack at least one point along its first axis, got shape {xs.shape}")
    point_shape = xs.shape[1:]

    flat_xs = jnp.reshape(xs, (xs.shape[0], -1))

    def points_at(x):
        _, points = perturbed_points(noise, key, x, sigma.astype(xs.dtype), num_samples, False)
        return jnp.concatenate([x[None], points])  # the point itself first

    points = jax.vmap(points_at)(flat_xs)  # (N, 1 + M, d)
    # One vmap over all N (1 + M) points rather than one per axis: a rollout through a
    # contact solver (while loops) compiled and ran several times slower under nested vmaps.
    values = jax.vmap(lambda p: f(jnp.reshape(p, point_shape)))(jnp.reshape(points, (-1, flat_xs.shape[1])))
    values = jnp.reshape(values, points.shape[:2] + values.shape[1:])  # (N, 1 + M) + f_shape
    samples = values[:, 1:]
    return Landscape(
        value=jnp.mean(samples, axis=1),
        std_error=jnp.std(samples, axis=1, ddof=1) / math.sqrt(num_samples),
        unsmoothed=values[:, 0],
    )
