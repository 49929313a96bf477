"""Noise distributions for randomized smoothing.

Every distribution is a product of independent, identical one-dimensional laws: `sample`
draws an array of any shape, and `log_prob`, `score` and `cdf` act elementwise (sum
`log_prob` over the coordinates for the joint log-density). The score is
:math:`\\nabla \\log \\mu(z)`; the zeroth-order estimator weighs function values by
:math:`-\\nabla \\log \\mu(z) / \\sigma` (Berthet et al. 2020, Prop. 3.1).

Example:
    >>> import jax
    >>> from rsmooth.noise import Gaussian
    >>> z = Gaussian().sample(jax.random.key(0), (3,))
    >>> bool(jax.numpy.allclose(Gaussian().score(z), -z))
    True
"""

from __future__ import annotations

import math
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.extend.random import threefry_2x32
from jax.scipy.special import ndtr, erfinv
from jax import Array
from jax.typing import ArrayLike

__all__ = [
    "Noise",
    "Gaussian",
    "Gumbel",
    "Laplace",
    "Logistic",
    "Cauchy",
    "Uniform",
    "EULER_GAMMA",
]

#: The mean of the standard Gumbel law (the Euler-Mascheroni constant).
EULER_GAMMA = 0.5772156649015329


def _fast_bits(key: Array, dtype) -> bool:
    """Whether :func:`_uniform` draws `dtype` from `key` with both of threefry's output words."""
    if dtype != jnp.float32:
        return False
    key_dtype = getattr(key, "dtype", None)
    if key_dtype is not None and jax.dtypes.issubdtype(key_dtype, jax.dtypes.prng_key):
        return str(jax.random.key_impl(key)) == "threefry2x32"
    # a raw uint32 key (jax.random.PRNGKey) of the default implementation
    return jax.config.jax_default_prng_impl == "threefry2x32" and np.shape(key)[-1:] == (2,)


def _uniform(key: Array, shape, dtype, minval: float = 0.0, maxval: float = 1.0) -> Array:
    """Uniform numbers on [minval, maxval) of `shape`, the source of every law's sampler
    (each applies its quantile function).

    For float32 and a threefry key, from 32 random bits per number, counted in row-major order:
    the threefry-2x32 block of counters (i, i + n/2) gives numbers i and i + n/2 (n the size,
    rounded up to even), both output words used, where `jax.random` with
    `jax_threefry_partitionable` keeps one of the two. Half the blocks, and XLA on CPU
    compiles this flat counter better than the partitionable one: several times faster.
    The price: a draw sharded across devices is not generated in place
    on each shard; rsmooth shards batches of keys (one per problem, :mod:`rsmooth.parallel`),
    each drawn whole where it lies. Other key implementations and dtypes: `jax.random.uniform`.
    """
    shape = tuple(shape)
    dtype = jax.dtypes.canonicalize_dtype(dtype)
    size = math.prod(shape)
    if not _fast_bits(key, dtype):
        # drawn flat: XLA on CPU generates some multi-dimensional shapes several times slower
        u = jax.random.uniform(key, (size,), dtype, minval=minval, maxval=maxval)
        return u.reshape(shape)
    data = jax.random.key_data(key)
    if data.shape != (2,):
        raise ValueError(f"key must be a single PRNG key, got a key array of shape {np.shape(key)}")
    count = jax.lax.iota(jnp.uint32, size + size % 2)
    bits = threefry_2x32((data[0], data[1]), count)[:size]
    # the 23 high bits as the mantissa of a float in [1, 2)
    floats = jax.lax.bitcast_convert_type((bits >> 9) | np.uint32(0x3F800000), jnp.float32) - 1.0
    lo, hi = jnp.asarray(minval, dtype), jnp.asarray(maxval, dtype)
    return jnp.maximum(lo, floats * (hi - lo) + lo).reshape(shape)


def _finfo(dtype):
    return jnp.finfo(jax.dtypes.canonicalize_dtype(dtype))


def _above(value: float, dtype) -> float:
    """The next number of `dtype` above `value` (an open end of a uniform's range)."""
    dtype = jax.dtypes.canonicalize_dtype(dtype)
    return float(np.nextafter(np.asarray(value, dtype), np.asarray(np.inf, dtype)))


def _laplace(u: Array) -> Array:
    """The Laplace law's quantile function on u uniform on (-1, 1) (symmetric in the sign)."""
    return -jnp.sign(u) * jnp.log1p(-jnp.abs(u))


def _logit(u: Array) -> Array:
    return jnp.log(u) - jnp.log1p(-u)


class Noise(eqx.Module):
    """Base class: a standard (location 0, scale 1) one-dimensional law, used coordinatewise.

    Class attributes:
        symmetric: the law of `-z` equals the law of `z` (needed for antithetic sampling).
        has_score: the density is differentiable on the whole line, so the score-function
            (zeroth-order) estimator is unbiased with this noise.
    """

    symmetric: ClassVar[bool] = True
    has_score: ClassVar[bool] = True

    def sample(self, key: Array, shape: tuple[int, ...], dtype=float) -> Array:
        """Draws independent samples of the given shape."""
        raise NotImplementedError

    def log_prob(self, z: ArrayLike) -> Array:
        """Elementwise log-density."""
        raise NotImplementedError

    def score(self, z: ArrayLike) -> Array:
        """Elementwise derivative of the log-density, d log mu(z) / dz."""
        raise NotImplementedError

    def cdf(self, z: ArrayLike) -> Array:
        """Elementwise cumulative distribution function P(Z <= z)."""
        raise NotImplementedError

    def sf(self, z: ArrayLike) -> Array:
        """Elementwise survival function P(Z > z), accurate in the upper tail (where
        ``1 - cdf(z)`` rounds to 0): ``cdf(-z)`` for a symmetric law."""
        z = jnp.asarray(z)
        return self.cdf(-z) if self.symmetric else 1.0 - self.cdf(z)

    @property
    def name(self) -> str:
        return type(self).__name__.lower()


class Gaussian(Noise):
    """Standard normal noise; score(z) = -z."""

    def sample(self, key, shape, dtype=float):
        return math.sqrt(2.0) * erfinv(_uniform(key, shape, dtype, minval=_above(-1.0, dtype), maxval=1.0))

    def log_prob(self, z):
        z = jnp.asarray(z)
        return -0.5 * z**2 - 0.5 * math.log(2 * math.pi)

    def score(self, z):
        return -jnp.asarray(z)

    def cdf(self, z):
        return ndtr(jnp.asarray(z))


class Gumbel(Noise):
    """Standard Gumbel (max) noise, mean EULER_GAMMA; with it the perturbed argmax over the
    simplex is the softmax (Gumbel-max trick)."""

    symmetric: ClassVar[bool] = False

    def sample(self, key, shape, dtype=float):
        return -jnp.log(-jnp.log(_uniform(key, shape, dtype, minval=_finfo(dtype).tiny)))

    def log_prob(self, z):
        z = jnp.asarray(z)
        return -z - jnp.exp(-z)

    def score(self, z):
        return jnp.expm1(-jnp.asarray(z))

    def cdf(self, z):
        return jnp.exp(-jnp.exp(-jnp.asarray(z)))

    def sf(self, z):
        return -jnp.expm1(-jnp.exp(-jnp.asarray(z)))


class Laplace(Noise):
    """Standard Laplace noise (density exp(-|z|)/2); score(z) = -sign(z)."""

    def sample(self, key, shape, dtype=float):
        return _laplace(_uniform(key, shape, dtype, minval=_above(-1.0, dtype), maxval=1.0))

    def log_prob(self, z):
        return -jnp.abs(jnp.asarray(z)) - math.log(2.0)

    def score(self, z):
        return -jnp.sign(jnp.asarray(z))

    def cdf(self, z):
        z = jnp.asarray(z)
        return jnp.where(z < 0, 0.5 * jnp.exp(z), 1.0 - 0.5 * jnp.exp(-z))


class Logistic(Noise):
    """Standard logistic noise; its CDF is the sigmoid, score(z) = -tanh(z / 2)."""

    def sample(self, key, shape, dtype=float):
        return _logit(_uniform(key, shape, dtype, minval=_finfo(dtype).tiny))

    def log_prob(self, z):
        z = jnp.asarray(z)
        return -jnp.abs(z) - 2.0 * jnp.log1p(jnp.exp(-jnp.abs(z)))

    def score(self, z):
        return -jnp.tanh(0.5 * jnp.asarray(z))

    def cdf(self, z):
        return jax.nn.sigmoid(jnp.asarray(z))


class Cauchy(Noise):
    """Standard Cauchy noise (heavy tails, no mean); score(z) = -2z / (1 + z^2)."""

    def sample(self, key, shape, dtype=float):
        return jnp.tan(math.pi * (_uniform(key, shape, dtype, minval=_finfo(dtype).eps) - 0.5))

    def log_prob(self, z):
        z = jnp.asarray(z)
        return -jnp.log1p(z**2) - math.log(math.pi)

    def score(self, z):
        z = jnp.asarray(z)
        return -2.0 * z / (1.0 + z**2)

    def cdf(self, z):
        z = jnp.asarray(z)
        # below 0 as arctan(-1/z) / pi: 0.5 + arctan(z) / pi cancels in the lower tail (and sf,
        # cdf(-z), in the upper one: float32 gave 2.98e-8 for 3.18e-8 at 1e7)
        negative = jnp.where(z < 0, z, -1.0)
        return jnp.where(z < 0, jnp.arctan(-1.0 / negative) / math.pi, 0.5 + jnp.arctan(z) / math.pi)


class Uniform(Noise):
    """Uniform noise on [-1, 1].

    Its density jumps at the ends of the support, so its score is zero almost everywhere and
    the score-function estimator does not apply (`has_score` is False): use it with the
    first-order estimator only.
    """

    has_score: ClassVar[bool] = False

    def sample(self, key, shape, dtype=float):
        return _uniform(key, shape, dtype, minval=-1.0, maxval=1.0)

    def log_prob(self, z):
        z = jnp.asarray(z)
        return jnp.where(jnp.abs(z) <= 1.0, -math.log(2.0), -jnp.inf)

    def score(self, z):
        return jnp.zeros_like(jnp.asarray(z))

    def cdf(self, z):
        return jnp.clip(0.5 * (jnp.asarray(z) + 1.0), 0.0, 1.0)
