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

`theta` is one problem (a vector, or any array the oracle takes); use `jax.vmap` over a batch
with one key per problem.
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
from jax import Array
from jax.typing import ArrayLike

from rsmooth.noise import Gumbel, Noise
from rsmooth.smooth import smooth

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


def argmax(
    theta: ArrayLike,
    key: Array,
    *,
    sigma: ArrayLike,
    num_samples: int,
    noise: Noise = Gumbel(),
    oracle: Callable = simplex_argmax,
    baseline: bool = True,
) -> Array:
    r"""Perturbed argmax :math:`\mathbb{E}\, y^*(\theta + \sigma Z)`, differentiable in `theta`.

    Args:
        theta: the LP's cost vector (one problem).
        key: a `jax.random` key.
        sigma: noise scale, positive.
        num_samples: Monte-Carlo samples.
        noise: noise law (Gumbel or Gaussian are the usual ones).
        oracle: argmax oracle of the LP; default the simplex (one-hot argmax).
        baseline: subtract `oracle(theta)` in the Jacobian estimator (Berthet et al. use none;
            it keeps the estimator unbiased and lowers its variance).

    Returns:
        The perturbed argmax, the shape of `oracle(theta)`; its Jacobian under `jax.jacobian`
        is the score-function estimator.

    Example:
        >>> import jax, jax.numpy as jnp
        >>> from rsmooth import perturbed
        >>> theta = jnp.array([1.0, 0.0, -1.0])
        >>> y = perturbed.argmax(theta, jax.random.key(0), sigma=1.0, num_samples=20000)
        >>> bool(jnp.allclose(y, jax.nn.softmax(theta), atol=0.02))
        True

    References:
        Berthet et al., "Learning with differentiable perturbed optimizers", NeurIPS 2020.
    """
    g = smooth(oracle, sigma=sigma, num_samples=num_samples, estimator="zeroth", noise=noise, baseline=baseline)
    return g(key, jnp.asarray(theta))


def max(  # noqa: A001 - the field's name for it
    theta: ArrayLike,
    key: Array,
    *,
    sigma: ArrayLike,
    num_samples: int,
    noise: Noise = Gumbel(),
    oracle: Callable = simplex_argmax,
) -> Array:
    r"""Perturbed max :math:`F_\sigma(\theta) = \mathbb{E}\max_y\langle y, \theta+\sigma Z\rangle`;
    its gradient is the perturbed argmax (estimated on the same samples)."""
    g = smooth(_oracle_max(oracle), sigma=sigma, num_samples=num_samples, estimator="first", noise=noise)
    return g(key, jnp.asarray(theta))


def argmin(
    theta: ArrayLike,
    key: Array,
    *,
    sigma: ArrayLike,
    num_samples: int,
    noise: Noise = Gumbel(),
    oracle: Callable = simplex_argmax,
    baseline: bool = True,
) -> Array:
    r"""Perturbed argmin :math:`\mathbb{E}\arg\min_y\langle y, \theta + \sigma Z\rangle`.

    `oracle` is the LP's *argmax* oracle, as in :func:`argmax`; argmin is taken as argmax of
    the negated cost, with the noise added to `theta` itself.
    """
    g = smooth(lambda t: oracle(-t), sigma=sigma, num_samples=num_samples, estimator="zeroth", noise=noise, baseline=baseline)
    return g(key, jnp.asarray(theta))


def min(  # noqa: A001
    theta: ArrayLike,
    key: Array,
    *,
    sigma: ArrayLike,
    num_samples: int,
    noise: Noise = Gumbel(),
    oracle: Callable = simplex_argmax,
) -> Array:
    r"""Perturbed min :math:`\mathbb{E}\min_y\langle y, \theta + \sigma Z\rangle`."""
    minimizer = lambda t: oracle(-t)  # noqa: E731
    g = smooth(_oracle_max(minimizer), sigma=sigma, num_samples=num_samples, estimator="first", noise=noise)
    return g(key, jnp.asarray(theta))


def fenchel_young_loss(
    theta: ArrayLike,
    y: ArrayLike,
    key: Array,
    *,
    sigma: ArrayLike,
    num_samples: int,
    noise: Noise = Gumbel(),
    oracle: Callable = simplex_argmax,
) -> Array:
    r"""Fenchel-Young loss :math:`F_\sigma(\theta) - \langle \theta, y\rangle` of the perturbed
    max, up to the term :math:`\Omega(y)` that does not depend on `theta`.

    Its gradient in `theta` is :math:`y_\sigma(\theta) - y`: zero exactly when the perturbed
    argmax reproduces the target `y`. Convex in `theta`.

    Args:
        theta: predicted cost vector (one problem).
        y: target solution, a point of the polytope (same shape as `oracle(theta)`).
        key, sigma, num_samples, noise, oracle: as in :func:`max`.

    Returns:
        A scalar.

    References:
        Berthet et al. 2020, Sec. 4; Blondel, Martins, Niculae, "Learning with Fenchel-Young
        losses", JMLR 2020.
    """
    theta = jnp.asarray(theta)
    y = jnp.asarray(y, theta.dtype)
    if y.shape != theta.shape:
        raise ValueError(f"y must have the shape of theta {theta.shape}, got {y.shape}")
    return max(theta, key, sigma=sigma, num_samples=num_samples, noise=noise, oracle=oracle) - jnp.sum(theta * y)
