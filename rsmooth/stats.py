r"""Empirical variance and bias of gradient estimators.

Runs an estimator over many independent keys (batched with `vmap`) and compares the spread
and the mean of its gradients with a reference (a closed form, or a long run of an unbiased
estimator), so a user can see whether an estimator is biased (the first-order estimate of a
step function is exactly zero) or noisy (the first-order estimate on a stiff function).

Example:
    >>> import jax, jax.numpy as jnp, rsmooth
    >>> step = lambda x: jnp.where(x > 0, 1.0, 0.0)
    >>> d = rsmooth.stats.diagnose(rsmooth.first_order, step, jax.random.key(0), jnp.array(0.0),
    ...                            reference=0.3989, num_trials=16, sigma=1.0, num_samples=8)
    >>> float(d.variance), round(float(d.bias), 4)
    (0.0, 0.3989)
"""

from __future__ import annotations

from typing import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import Array

from rsmooth import _checks

__all__ = ["Diagnostics", "diagnose", "empirical_variance", "empirical_bias"]


class Diagnostics(eqx.Module):
    """Statistics of an estimator's gradient over independent trials.

    Attributes:
        mean: mean gradient over trials (structure of the gradient).
        variance: total variance of one estimate (trace of the covariance across trials).
        bias: norm of (mean - reference); NaN-free: zero-size reference is an error.
        bias_std_error: standard error of `bias` due to the finite number of trials.
        mse: mean squared error of one estimate, ||estimate - reference||^2 averaged.
        grads: the gradients of all trials (leading axis: trial).
    """

    mean: object
    variance: Array
    bias: Array
    bias_std_error: Array
    mse: Array
    grads: object


def _trial_grads(estimator: Callable, f: Callable, key: Array, x, num_trials: int, kwargs):
    _checks.check_key(key)
    num_trials = _checks.check_num_samples(num_trials, "num_trials", minimum=2)
    keys = jax.random.split(key, num_trials)
    return jax.vmap(lambda k: estimator(f, k, x, **kwargs).grad)(keys)


def _flat(tree) -> Array:
    leaves = jax.tree.leaves(tree)
    return jnp.concatenate([jnp.reshape(leaf, (leaf.shape[0], -1)) for leaf in leaves], axis=1)


def empirical_variance(estimator: Callable, f: Callable, key: Array, x, *, num_trials: int = 32, **kwargs) -> Array:
    """Total variance (trace of the covariance) of `estimator(f, key, x, **kwargs).grad` over
    `num_trials` independent keys."""
    grads = _flat(_trial_grads(estimator, f, key, x, num_trials, kwargs))
    return jnp.sum(jnp.var(grads, axis=0, ddof=1))


def empirical_bias(estimator: Callable, f: Callable, key: Array, x, reference, *, num_trials: int = 32, **kwargs) -> Array:
    """Norm of the difference between the mean gradient over `num_trials` keys and `reference`."""
    return diagnose(estimator, f, key, x, reference=reference, num_trials=num_trials, **kwargs).bias


def diagnose(estimator: Callable, f: Callable, key: Array, x, *, reference, num_trials: int = 32, **kwargs) -> Diagnostics:
    """Mean, variance, bias and mean squared error of an estimator's gradient.

    Args:
        estimator: :func:`rsmooth.zeroth_order`, :func:`rsmooth.first_order`,
            :func:`rsmooth.alpha_order` or any function with their signature.
        f: the function whose smoothed gradient is estimated.
        key: a `jax.random` key; trial `i` uses the `i`-th split.
        x: the point.
        reference: the true smoothed gradient (structure of the gradient, or broadcastable).
        num_trials: number of independent estimates, >= 2.
        **kwargs: passed to the estimator (sigma, num_samples, noise, ...).

    Returns:
        :class:`Diagnostics`.
    """
    tree = _trial_grads(estimator, f, key, x, num_trials, kwargs)
    grads = _flat(tree)
    mean_tree = jax.tree.map(lambda leaf: jnp.mean(leaf, axis=0), tree)
    reference_tree = jax.tree.map(lambda m, r: jnp.broadcast_to(jnp.asarray(r, m.dtype), m.shape), mean_tree, reference)
    reference_flat = _flat(jax.tree.map(lambda r: r[None], reference_tree))[0]
    mean = jnp.mean(grads, axis=0)
    variance = jnp.sum(jnp.var(grads, axis=0, ddof=1))
    bias = jnp.linalg.norm(mean - reference_flat)
    return Diagnostics(
        mean=mean_tree,
        variance=variance,
        bias=bias,
        bias_std_error=jnp.sqrt(variance / grads.shape[0]),
        mse=jnp.mean(jnp.sum((grads - reference_flat[None, :]) ** 2, axis=1)),
        grads=tree,
    )
