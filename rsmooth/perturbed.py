r"""Perturbed optimizers (Berthet, Blondel, Teboul, Cuturi, Vert, Bach, NeurIPS 2020).

For a linear program over a polytope :math:`C`, with the argmax oracle
:math:`y^*(\theta) = \arg\max_{y \in C} \langle y, \theta\rangle`, the perturbed optimizers are

.. math::
    y_\sigma(\theta) = \mathbb{E}\, y^*(\theta + \sigma Z), \qquad
    F_\sigma(\theta) = \mathbb{E} \max_{y\in C} \langle y, \theta + \sigma Z\rangle,
    \qquad \nabla F_\sigma = y_\sigma,

with Jacobian :math:`J y_\sigma(\theta) = \mathbb{E}[y^*(\theta+\sigma Z)\,
(-\nabla\log\mu(Z))^\top] / \sigma` (their Prop. 3.1). They are :func:`rsmooth.smooth` applied
to the oracle: `argmax` with the zeroth-order rule (optionally with the baseline
:math:`y^*(\theta)`, which lowers the variance), `max` with the first-order rule (the gradient
of a max is its argmax, Danskin). The Fenchel-Young loss
:math:`L_\sigma(\theta; y) = F_\sigma(\theta) - \langle\theta, y\rangle` (up to a term constant
in :math:`\theta`) has gradient :math:`y_\sigma(\theta) - y`.

With Gumbel noise over the simplex, :math:`y_\sigma = \mathrm{softmax}(\theta/\sigma)` and
:math:`F_\sigma = \sigma\,\mathrm{logsumexp}(\theta/\sigma) + \sigma\gamma_E`.

Batches: `theta` of shape `(..., n)` holds one problem per vector along its last axis, and
the oracle takes one such vector. The leading axes are a batch of independent problems, each
perturbed with its own noise, from its own key: the batch's keys are
``jax.random.split(key, B)`` for the `B` problems in row-major order, so the result is that of
`jax.vmap` over the problems with those keys, and each problem's derivatives come from its own
samples only (one shared noise would let every problem's Monte-Carlo error leak into every
other's gradient). An oracle of a problem that is not a vector (an assignment problem's cost
matrix) takes it flattened, and reshapes it itself.
"""

from __future__ import annotations

import math
from typing import Callable

import jax
import jax.numpy as jnp
from jax import Array
from jax.typing import ArrayLike

from rsmooth import _checks
from rsmooth.noise import Gumbel, Noise
from rsmooth.smooth import _smooth

__all__ = [
    "simplex_argmax",
    "ranking_argmax",
    "argmax",
    "max",
    "argmin",
    "min",
    "fenchel_young_loss",
]


def simplex_argmax(theta: Array) -> Array:
    """The LP oracle over the probability simplex: the one-hot vector of argmax(theta)."""
    return jax.nn.one_hot(jnp.argmax(theta, axis=-1), theta.shape[-1], dtype=theta.dtype)


def ranking_argmax(theta: Array) -> Array:
    """The LP oracle over the permutahedron of (1, ..., n): the ranks of theta (1 = smallest).

    argmax over permutations y of <y, theta> puts the largest value n where theta is largest
    (rearrangement inequality), so y is the rank vector.
    """
    ranks = jnp.argsort(jnp.argsort(theta, axis=-1), axis=-1)
    return (ranks + 1).astype(theta.dtype)


def _oracle_max(oracle: Callable) -> Callable:
    def value(theta):
        # <y*(theta), theta> with y* held constant: its gradient is y* (Danskin).
        return jnp.sum(jax.lax.stop_gradient(oracle(theta)) * theta)

    return value


def _check_not_key(theta) -> None:
    dtype = getattr(theta, "dtype", None)
    if dtype is not None and jax.dtypes.issubdtype(dtype, jax.dtypes.prng_key):
        raise TypeError("theta is a PRNG key: the key comes first, as in perturbed.argmax(key, theta, ...)")


def _over_problems(fn: Callable, key: Array, theta: ArrayLike, *others: ArrayLike) -> Array:
    """`fn(key, theta, *others)` for one problem (a vector `theta`), applied to each problem of a
    batch `theta` of shape (..., n), with the keys ``jax.random.split(key, B)`` (see the module
    docstring); `others` have the shape of `theta` and are split with it."""
    _check_not_key(theta)
    theta = jnp.asarray(theta)
    _checks.check_floating_tree(theta, "theta")
    if theta.ndim == 0:
        raise ValueError("theta must have at least one axis (one problem is a vector), got a scalar")
    if theta.ndim == 1:
        return fn(key, theta, *others)
    batch = theta.shape[:-1]
    _checks.check_key(key)
    keys = jax.random.split(key, math.prod(batch))
    rows = [jnp.reshape(a, (-1, theta.shape[-1])) for a in (theta, *others)]
    out = jax.vmap(fn)(keys, *rows)
    return jnp.reshape(out, batch + out.shape[1:])


def argmax(
    key: Array,
    theta: ArrayLike,
    *,
    sigma: ArrayLike,
    num_samples: int,
    noise: Noise = Gumbel(),
    oracle: Callable = simplex_argmax,
    baseline: bool | str = True,
) -> Array:
    r"""Perturbed argmax :math:`\mathbb{E}\, y^*(\theta + \sigma Z)`, differentiable in `theta`.

    Args:
        theta: the LP's cost vector (n,), or a batch of them (..., n): each problem is
            perturbed with its own key, split from `key` (see the module docstring).
        key: a `jax.random` key.
        sigma: noise scale, positive.
        num_samples: Monte-Carlo samples per problem.
        noise: noise law (Gumbel or Gaussian are the usual ones).
        oracle: argmax oracle of the LP for one problem; default the simplex (one-hot argmax).
        baseline: subtract `oracle(theta)` in the Jacobian estimator (Berthet et al. use none;
            it keeps the estimator unbiased and lowers its variance); True, False or
            ``"leave-one-out"`` (see :func:`rsmooth.zeroth_order`).

    Returns:
        The perturbed argmax, of shape ``theta.shape[:-1] + oracle(row).shape``; its Jacobian
        under `jax.jacobian` is the score-function estimator, and its derivatives of higher
        order the score-function estimators of the next orders (:func:`rsmooth.smooth`).

    Example:
        >>> import jax, jax.numpy as jnp
        >>> from rsmooth import perturbed
        >>> theta = jnp.array([1.0, 0.0, -1.0])
        >>> y = perturbed.argmax(jax.random.key(0), theta, sigma=1.0, num_samples=20000)
        >>> bool(jnp.allclose(y, jax.nn.softmax(theta), atol=0.02))
        True

    References:
        Berthet et al., "Learning with differentiable perturbed optimizers", NeurIPS 2020.
    """
    g = _smooth(oracle, "theta", sigma=sigma, num_samples=num_samples, estimator="zeroth", noise=noise, baseline=baseline)
    return _over_problems(g, key, theta)


def max(  # noqa: A001 - the field's name for it
    key: Array,
    theta: ArrayLike,
    *,
    sigma: ArrayLike,
    num_samples: int,
    noise: Noise = Gumbel(),
    oracle: Callable = simplex_argmax,
) -> Array:
    r"""Perturbed max :math:`F_\sigma(\theta) = \mathbb{E}\max_y\langle y, \theta+\sigma Z\rangle`.

    Its gradient is the perturbed argmax (the mean of the sampled maximizers, Danskin) and its
    Hessian the Jacobian of the perturbed argmax (the score-function estimator on the sampled
    maximizers, each sample's baseline the mean of the others'): on the same samples, those of
    :func:`argmax` for the same key and `num_samples`, they equal the value and the Jacobian
    of ``argmax(..., baseline="leave-one-out")``.

    Args:
        theta, key, sigma, num_samples, noise, oracle: as in :func:`argmax`.

    Returns:
        The perturbed max, of shape ``theta.shape[:-1]``.
    """
    g = _smooth(_oracle_max(oracle), "theta", sigma=sigma, num_samples=num_samples, estimator="first", noise=noise)
    return _over_problems(g, key, theta)


def argmin(
    key: Array,
    theta: ArrayLike,
    *,
    sigma: ArrayLike,
    num_samples: int,
    noise: Noise = Gumbel(),
    oracle: Callable = simplex_argmax,
    baseline: bool | str = True,
) -> Array:
    r"""Perturbed argmin :math:`\mathbb{E}\arg\min_y\langle y, \theta + \sigma Z\rangle`.

    `oracle` is the LP's *argmax* oracle, as in :func:`argmax`; argmin is taken as argmax of
    the negated cost, with the noise added to `theta` itself. Batches as in :func:`argmax`.
    """
    g = _smooth(lambda t: oracle(-t), "theta", sigma=sigma, num_samples=num_samples, estimator="zeroth", noise=noise, baseline=baseline)
    return _over_problems(g, key, theta)


def min(  # noqa: A001
    key: Array,
    theta: ArrayLike,
    *,
    sigma: ArrayLike,
    num_samples: int,
    noise: Noise = Gumbel(),
    oracle: Callable = simplex_argmax,
) -> Array:
    r"""Perturbed min :math:`\mathbb{E}\min_y\langle y, \theta + \sigma Z\rangle`, of shape
    ``theta.shape[:-1]`` (batches as in :func:`argmax`)."""
    minimizer = lambda t: oracle(-t)  # noqa: E731
    g = _smooth(_oracle_max(minimizer), "theta", sigma=sigma, num_samples=num_samples, estimator="first", noise=noise)
    return _over_problems(g, key, theta)


def fenchel_young_loss(
    key: Array,
    theta: ArrayLike,
    y: ArrayLike,
    *,
    sigma: ArrayLike,
    num_samples: int,
    noise: Noise = Gumbel(),
    oracle: Callable = simplex_argmax,
) -> Array:
    r"""Fenchel-Young loss :math:`F_\sigma(\theta) - \langle \theta, y\rangle` of the perturbed
    max, up to the term :math:`\Omega(y)` that does not depend on `theta`.

    Its gradient in `theta` is :math:`y_\sigma(\theta) - y`: zero exactly when the perturbed
    argmax reproduces the target `y`; its Hessian is the Jacobian of the perturbed argmax
    (see :func:`max`). Convex in `theta`.

    Args:
        theta: predicted cost vector (n,), or a batch of them (..., n), each problem with its
            own key (as in :func:`argmax`).
        y: target solutions, points of the polytope, of the shape of `theta`.
        key, sigma, num_samples, noise, oracle: as in :func:`max`.

    Returns:
        The loss of each problem, of shape ``theta.shape[:-1]`` (a scalar for one problem).

    References:
        Berthet et al. 2020, Sec. 4; Blondel, Martins, Niculae, "Learning with Fenchel-Young
        losses", JMLR 2020.
    """
    _check_not_key(theta)
    theta = jnp.asarray(theta)
    y = jnp.asarray(y, theta.dtype)
    if y.shape != theta.shape:
        raise ValueError(f"y must have the shape of theta {theta.shape}, got {y.shape}")
    g = _smooth(_oracle_max(oracle), "theta", sigma=sigma, num_samples=num_samples, estimator="first", noise=noise)
    return _over_problems(lambda k, t, target: g(k, t) - jnp.sum(t * target), key, theta, y)
