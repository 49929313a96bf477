r"""Aggregation: which face (or the background) a pixel shows, hard, soft or perturbed.

For one pixel with K candidate faces of signed distances :math:`d_k` and normalized inverse
depths :math:`z_k` (larger is nearer), and the background at depth :math:`z_{bg}`, the z-buffer
shows the nearest covering face:

.. math:: w^*(d, z) = \mathrm{onehot}\Big(\arg\max\big(\{z_k : H(d_k) = 1\} \cup \{z_{bg}\}\big)\Big)
    \in \{0, 1\}^{K+1}.

The perturbed renderer (Le Lidec, Laptev, Schmid, Carpentier, NeurIPS 2021, Sec. 3) replaces
both the coverage and the argmax by their randomized smoothing, with independent noise on each
distance (scale :math:`\sigma`, law :math:`\mu`) and on each depth (temperature
:math:`\gamma`, law :math:`\nu`, e.g. Gumbel):

.. math:: w_{\sigma,\gamma}(d, z) = \mathbb{E}_{X\sim\mu, G\sim\nu}\; w^*(d + \sigma X, z + \gamma G),

estimated by Monte-Carlo, with the zeroth-order (score-function) Jacobian estimator with the
baseline :math:`w^*(d, z)` (their variance-reduced estimator): it is :func:`rsmooth.smooth`
applied to :math:`w^*` on the scaled point :math:`(d/\sigma, z/\gamma)` with the product law
:math:`\mu^K\otimes\nu^{K+1}` (:math:`w^*` is invariant to that scaling). With Gumbel depth
noise and all faces covering, :math:`w` is :math:`\mathrm{softmax}(z/\gamma)` (Gumbel-max).
SoftRas' aggregation (:func:`soft_aggregate`, Liu et al., ICCV 2019) is a closed-form analogue:
it weighs each face by its coverage probability, :math:`\hat w_k \propto
\mathrm{sigmoid}(d_k/\sigma)\, e^{z_k/\gamma}`, rather than sampling coverage.
"""

from __future__ import annotations

import math
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import Array, lax
from jax.typing import ArrayLike

from rsmooth._unrolled import log_sigmoid
from rsmooth.noise import Gaussian, Gumbel, Noise
from rsmooth.smooth import smooth

__all__ = ["hard_aggregate", "soft_aggregate", "perturbed_aggregate", "change_probability", "ProductNoise"]

# Scaled distances are clamped to [-_FAR, _FAR]: a slot that far out (in) is never (always)
# covered, whatever the noise, and the clamp makes its derivative with respect to sigma zero.
# (Without the upper clamp, the 1e15-pixel distance of a face with no silhouette edge, see
# rasterize's interior_edges, gave the estimator d(d / sigma)/d sigma ~ 1e14 per sample.)
_FAR = 1e12


def _scaled(distance: Array, sigma) -> Array:
    return jnp.clip(distance / sigma, -_FAR, _FAR)


def _with_background(scores: Array, background: Array) -> Array:
    background = jnp.broadcast_to(background, scores.shape[:-1] + (1,)).astype(scores.dtype)
    return jnp.concatenate([scores, background], axis=-1)


def hard_aggregate(distance: ArrayLike, depth: ArrayLike, background_depth: ArrayLike = 0.0) -> Array:
    """The z-buffer: one-hot weights (..., K + 1) of the nearest covering face, or of the
    background (last slot) when no face covers the pixel or the background is nearer.

    Args:
        distance: (..., K) signed distances (positive: covered).
        depth: (..., K) normalized inverse depths (larger is nearer).
        background_depth: the background's normalized inverse depth.

    Example:
        >>> import jax.numpy as jnp
        >>> hard_aggregate(jnp.array([1.0, 1.0, -1.0]), jnp.array([0.2, 0.5, 0.9])).tolist()
        [0.0, 1.0, 0.0, 0.0]
    """
    distance, depth = jnp.asarray(distance), jnp.asarray(depth)
    scores = jnp.where(distance > 0, depth, -jnp.inf)
    scores = _with_background(scores, jnp.asarray(background_depth))
    return jax.nn.one_hot(jnp.argmax(scores, axis=-1), scores.shape[-1], dtype=depth.dtype)


def soft_aggregate(
    distance: ArrayLike, depth: ArrayLike, *, sigma: ArrayLike, gamma: ArrayLike, background_depth: ArrayLike = 0.0
) -> Array:
    r"""SoftRas-like aggregation, alpha-composited over the background.

    With the coverage probabilities :math:`D_k = \mathrm{sigmoid}(d_k/\sigma)`, the silhouette
    is :math:`\alpha = 1 - \prod_k (1 - D_k)` and the faces share it by SoftRas' weights
    :math:`\hat w_k \propto D_k\,e^{z_k/\gamma}` (Liu, Li, Chen, Li, "Soft Rasterizer", ICCV
    2019: its silhouette and its aggregation function): :math:`w_k = \alpha \hat w_k`, :math:`w_{bg} = 1 - \alpha`. (SoftRas
    proper also gives the background a share :math:`e^{z_{bg}/\gamma}` inside the softmax; with
    small :math:`\gamma` that makes face colours bleed far outside the silhouette, so here the
    background enters by compositing, as in the perturbed renderer.) `background_depth` is
    accepted for a uniform signature and unused.
    """
    del background_depth
    distance, depth = jnp.asarray(distance), jnp.asarray(depth)
    scaled = _scaled(distance, sigma)
    uncovered = jnp.exp(jnp.sum(log_sigmoid(-scaled), axis=-1, keepdims=True))
    faces = jax.nn.softmax(log_sigmoid(scaled) + depth / gamma, axis=-1)
    return jnp.concatenate([(1.0 - uncovered) * faces, uncovered], axis=-1)


class ProductNoise(Noise):
    """Independent noise with two laws: `first` on the first `split` coordinates of the last
    axis, `second` on the others (a product law; the score is still coordinatewise)."""

    symmetric: ClassVar[bool] = False
    first: Noise = Gaussian()
    second: Noise = Gumbel()
    split: int = eqx.field(static=True, default=1)

    def __check_init__(self):
        for law in (self.first, self.second):
            if not law.has_score:
                raise ValueError(
                    f"perturbed rendering needs noise laws with a differentiable density; {type(law).__name__} has none"
                )

    def sample(self, key, shape, dtype=float):
        key_first, key_second = jax.random.split(key)
        a = self.first.sample(key_first, shape[:-1] + (self.split,), dtype)
        b = self.second.sample(key_second, shape[:-1] + (shape[-1] - self.split,), dtype)
        return jnp.concatenate([a, b], axis=-1)

    def _apply(self, method, z):
        z = jnp.asarray(z)
        a = getattr(self.first, method)(z[..., : self.split])
        b = getattr(self.second, method)(z[..., self.split :])
        return jnp.concatenate([a, b], axis=-1)

    def log_prob(self, z):
        return self._apply("log_prob", z)

    def score(self, z):
        return self._apply("score", z)

    def cdf(self, z):
        return self._apply("cdf", z)


def perturbed_aggregate(
    key: Array,
    distance: ArrayLike,
    depth: ArrayLike,
    *,
    sigma: ArrayLike,
    gamma: ArrayLike,
    num_samples: int,
    coverage_noise: Noise = Gaussian(),
    depth_noise: Noise = Gumbel(),
    background_depth: ArrayLike = 0.0,
    baseline: bool | str = True,
) -> Array:
    r"""Perturbed z-buffer weights of one pixel, :math:`\mathbb{E}\,w^*(d+\sigma X, z+\gamma G)`.

    The value is the Monte-Carlo mean over `num_samples` joint samples; the derivatives with
    respect to `distance`, `depth`, `sigma` and `gamma` are the zeroth-order estimator with the
    hard weights as baseline (Le Lidec et al. 2021, Sec. 3), computed by
    :func:`rsmooth.smooth`. Use `jax.vmap` over pixels, with one key per pixel.

    Args:
        key: PRNG key.
        distance: (K,) signed distances in pixels; a slot with a distance below -1e12 sigma
            (e.g. -1e20, for an empty slot) is never covered.
        depth: (K,) normalized inverse depths.
        sigma: coverage noise scale in pixels (may be traced).
        gamma: depth noise temperature (may be traced).
        num_samples: Monte-Carlo samples.
        coverage_noise: law of the distance noise X.
        depth_noise: law of the depth noise G (Gumbel: softmax aggregation; Gaussian).
        background_depth: the background's normalized inverse depth; it is the (K+1)-th option
            and gets its own depth-noise sample.
        baseline: the estimator's baseline: True, the hard weights :math:`w^*(d, z)` (the
            paper's); ``"leave-one-out"``, each sample's the mean of the others' weights
            (lower variance at the pixels where the hard weights jump, the edges and
            occlusion boundaries, whose gradients the image has; no hard evaluation; needs
            ``num_samples >= 2``); False, none (see :func:`rsmooth.zeroth_order`).

    Returns:
        (K + 1,) weights summing to 1, the background's last.

    Example:
        >>> import jax, jax.numpy as jnp
        >>> w = perturbed_aggregate(jax.random.key(0), jnp.array([50.0, 50.0]), jnp.array([0.5, 0.4]),
        ...                         sigma=1.0, gamma=0.1, num_samples=20000)
        >>> bool(jnp.allclose(w, jax.nn.softmax(jnp.array([0.5, 0.4, 0.0]) / 0.1), atol=0.02))
        True
    """
    distance, depth = jnp.asarray(distance), jnp.asarray(depth)
    if distance.ndim != 1 or depth.shape != distance.shape:
        raise ValueError(f"distance and depth must both have shape (K,), got {distance.shape} and {depth.shape}")
    k = distance.shape[0]
    depths = _with_background(depth, jnp.asarray(background_depth))
    point = jnp.concatenate([_scaled(distance, sigma), depths / gamma])
    noise = ProductNoise(coverage_noise, depth_noise, split=k)

    def oracle(x):
        return hard_aggregate(x[:k], x[k : 2 * k], x[2 * k])

    g = smooth(oracle, sigma=1.0, num_samples=num_samples, estimator="zeroth", noise=noise, baseline=baseline)
    return g(key, point)


def change_probability(
    distance: ArrayLike,
    depth: ArrayLike,
    *,
    sigma: ArrayLike,
    gamma: ArrayLike,
    coverage_noise: Noise = Gaussian(),
    depth_noise: Noise = Gumbel(),
    background_depth: ArrayLike = 0.0,
) -> Array:
    r"""An upper bound on the probability that one sample of the perturbed z-buffer differs from
    the hard one, :math:`Pig(w^*(d+\sigma X, z+\gamma G) \neq w^*(d, z)\big)`, per pixel.

    By the union bound over the events that can change the hard weights: a slot's coverage
    flips (:math:`P(\sigma X_k < -d_k)` for a covered slot, :math:`P(\sigma X_k > -d_k)`
    otherwise), or an option covered in the hard image (a face, or the background) overtakes
    the hard winner :math:`w` in depth, :math:`P(\gamma(G_j - G_w) > z_w - z_j) \le
    P(G_j > \Delta_j/2) + P(G_w < -\Delta_j/2)` with :math:`\Delta_j = (z_w - z_j)/\gamma`
    (exactly :math:`\mathrm{sigmoid}(-\Delta_j)` for Gumbel depth noise, the difference of two
    Gumbel variables being logistic, and :math:`P(N(0, 2) > \Delta_j)` for Gaussian).
    Where the bound is ~0 every sample of the pixel is its hard value, and the estimator's
    terms (with a baseline) are zero: a perturbed render may spend its samples on the pixels
    where it is not (see :meth:`rsmooth.render.Renderer.uncertainty`). Computed in the noise
    laws' tails (:meth:`rsmooth.noise.Noise.sf`), outside the derivative.

    Args:
        distance, depth: (..., K) signed distances and normalized inverse depths, as in
            :func:`perturbed_aggregate` (a slot with a distance below -1e12 sigma is empty).
        sigma, gamma, coverage_noise, depth_noise, background_depth: as in
            :func:`perturbed_aggregate`.

    Returns:
        (...,) the bound, in [0, 1].

    Example:
        >>> import jax.numpy as jnp
        >>> # a face 6 sigma inside its edge, and nothing behind it within 30 gamma
        >>> p = change_probability(jnp.array([6.0]), jnp.array([0.3]), sigma=1.0, gamma=0.01)
        >>> bool(p < 1e-8), float(change_probability(jnp.array([0.0]), jnp.array([0.3]), sigma=1.0, gamma=0.01))
        (True, 0.5)
    """
    distance = lax.stop_gradient(jnp.asarray(distance))
    depth = lax.stop_gradient(jnp.asarray(depth))
    sigma, gamma = lax.stop_gradient(sigma), lax.stop_gradient(gamma)
    scaled = _scaled(distance, sigma)
    covered = distance > 0
    flips = jnp.where(covered, coverage_noise.cdf(-scaled), coverage_noise.sf(-scaled))
    depths = _with_background(depth, jnp.asarray(background_depth))
    options = _with_background(covered, jnp.asarray(True))
    winner = jnp.argmax(jnp.where(options, depths, -jnp.inf), axis=-1, keepdims=True)
    gap = (jnp.take_along_axis(depths, winner, axis=-1) - depths) / gamma  # >= 0 for the options
    if isinstance(depth_noise, Gumbel):  # G_j - G_w is logistic: exact
        overtakes = jax.nn.sigmoid(-gap)
    elif isinstance(depth_noise, Gaussian):  # G_j - G_w ~ N(0, 2): exact
        overtakes = depth_noise.sf(gap / math.sqrt(2.0))
    else:
        overtakes = depth_noise.sf(0.5 * gap) + depth_noise.cdf(-0.5 * gap)
    others = options & (lax.broadcasted_iota(winner.dtype, depths.shape, depths.ndim - 1) != winner)
    overtakes = jnp.where(others, overtakes, 0.0)
    return jnp.minimum(jnp.sum(flips, axis=-1) + jnp.sum(overtakes, axis=-1), 1.0)
