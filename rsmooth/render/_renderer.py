r"""The renderer: rasterize, shade, aggregate, in one jittable, vmappable function.

`Renderer(mode=...)` is a frozen configuration; calling it, ``renderer(key, mesh, camera)``,
returns an :class:`Image` (RGB and alpha). Modes:

* ``"hard"``: the z-buffer rasterizer; its image is piecewise constant in the geometry, so its
  derivative with respect to a pose is zero (up to shading);
* ``"perturbed"``: Le Lidec, Laptev, Schmid, Carpentier, "Differentiable rendering with
  perturbed optimizers", NeurIPS 2021: each pixel is the expectation of the hard pixel under
  noise on the signed distances (scale `sigma`, pixels) and on the depths (temperature
  `gamma`), estimated with `num_samples` samples, differentiated with the zeroth-order
  estimator with the hard pixel as baseline (:func:`rsmooth.render.perturbed_aggregate`);
* ``"soft"``: SoftRas (Liu et al., ICCV 2019) with sigmoid coverage, for comparison.

The cost is O(H W K) after a culling pass (:func:`rsmooth.render.rasterize`), not
O(H W F). A camera looking away from the mesh, or a mesh behind the camera, renders the
background (alpha 0) with zero derivatives. Faces that cross the camera's near plane are
culled whole unless ``Renderer(clip_near=True)``; :meth:`Renderer.fragments` counts them
(`near_culled`), with the tiles that overflowed (`tile_overflow`).

Example:
    >>> import jax, jax.numpy as jnp
    >>> from rsmooth.render import Renderer, cube, look_at
    >>> camera = look_at(jnp.array([0.0, 0.0, 4.0]), image_size=(16, 16))
    >>> renderer = Renderer(mode="hard", faces_per_pixel=2, faces_per_tile=12)
    >>> image = jax.jit(lambda mesh: renderer(None, mesh, camera))(cube())
    >>> image.rgb.shape, float(image.alpha[8, 8]), float(image.alpha[0, 0])
    ((16, 16, 3), 1.0, 0.0)
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.typing import ArrayLike

from rsmooth import _checks
from rsmooth._unrolled import sum_last
from rsmooth.estimators import check_baseline as _check_baseline
from rsmooth.noise import Gaussian, Gumbel, Noise
from rsmooth.render._aggregate import change_probability, hard_aggregate, perturbed_aggregate, soft_aggregate
from rsmooth.render._camera import Camera, check_camera
from rsmooth.render._mesh import Mesh
from rsmooth.render._raster import (
    Fragments, check_pixels, pixel_centres, rasterize, triangle_fragments_at, triangle_geometry,
)
from rsmooth.render._shade import DirectionalLight, _triple, shade_faces

__all__ = ["Image", "Renderer", "MODES", "NEGLIGIBLE", "random_pixel_chunks", "chunk_rows"]

MODES = ("hard", "soft", "perturbed")

# A pixel whose perturbed samples differ from its hard value with probability at most this (per
# sample, :meth:`Renderer.uncertainty`) is treated as certain: rendered hard, with no samples
# (`Renderer.pixel_chunk`, :meth:`rsmooth.render.PoseFit.estimate`).
NEGLIGIBLE = 1e-12

# Signed distance given to empty candidate slots: never covered, whatever the noise.
_NEVER = 1e20


def _noise_level(value: ArrayLike, name: str, dtype) -> Array:
    """A per-call sigma or gamma as an array of `dtype`, checked to be a positive, finite scalar:
    now (`ValueError`) when it is concrete, when the program runs (`equinox.error_if`) when it
    is traced (a NaN would otherwise surface as a non-finite point of the estimator)."""
    if np.ndim(value) != 0:
        raise ValueError(f"{name} must be a scalar, got shape {np.shape(value)}")
    if _checks.is_traced(value):
        array = jnp.asarray(value, dtype)
        return _checks.error_if(array, ~(jnp.isfinite(array) & (array > 0)), f"{name} must be positive and finite")
    number = float(np.asarray(value))
    if not (math.isfinite(number) and number > 0):
        raise ValueError(f"{name} must be positive and finite, got {number}")
    return jnp.asarray(value, dtype)


def _slots(fragments: Fragments) -> tuple[Array, Array]:
    """The candidates' signed distances and depths as the aggregations take them: an empty slot
    at distance -_NEVER (never covered) and depth 0."""
    return _slot_values(fragments.present, fragments.distance, fragments.depth)


def _slot_values(present: Array, distance: Array, depth: Array) -> tuple[Array, Array]:
    return jnp.where(present, distance, -_NEVER), jnp.where(present, depth, 0.0)


def random_pixel_chunks(uncertainty: Array, chunk: int) -> tuple[Array, Array]:
    """(order, num_chunks): the (N,) pixels whose `uncertainty` (:meth:`Renderer.uncertainty`,
    flattened) exceeds :data:`NEGLIGIBLE` first, then the others, each in image order; and how
    many chunks of `chunk` of them hold every such pixel (see :func:`chunk_rows`). A stable
    partition, by counts and one scatter (cheaper than a sort of the pixels by uncertainty)."""
    random = uncertainty > NEGLIGIBLE
    count = jnp.sum(random)
    rank = jnp.where(random, jnp.cumsum(random) - 1, count + jnp.cumsum(~random) - 1)
    order = jnp.zeros_like(rank).at[rank].set(jnp.arange(rank.shape[0], dtype=rank.dtype), unique_indices=True)
    return order, (count + chunk - 1) // chunk


def chunk_rows(order: Array, index: ArrayLike, chunk: int) -> tuple[Array, Array]:
    """(rows, fresh): chunk `index` of `order`, `chunk` entries from ``index * chunk``, or the last
    `chunk` entries where fewer remain; `fresh` marks those not in an earlier chunk (the last
    chunk overlaps the one before when `chunk` does not divide the length)."""
    start = jnp.minimum(index * chunk, order.shape[0] - chunk)
    return jax.lax.dynamic_slice(order, (start,), (chunk,)), start + jnp.arange(chunk) >= index * chunk


def _random_pixel_outputs(outputs_at, params, aux, sigma, gamma, keys, order, chunks, chunk, base):
    """(N, C) per-pixel outputs: ``outputs_at(params, aux, keys[rows], rows, sigma, gamma)`` at the
    rows order[:chunks * chunk] (the random pixels, in chunks of `chunk`, the last one
    overlapping the one before when `chunk` does not divide N), `base` at the others.

    A loop of a traced number of chunks, which reverse mode cannot differentiate: a custom VJP
    loops again over the chunks, each with its own VJP (the derivatives with respect to
    `params`, sigma and gamma are summed over the chunks, `base`'s are the cotangent where no
    chunk drew; aux, keys, order, chunks: none). `outputs_at` computes everything it needs at
    the rows, from `params`: the fragments' derivatives are then taken at the sampled pixels
    alone (recomputed there in the backward pass)."""
    @jax.custom_vjp
    def outputs(params, s, g, base, aux, keys, order, chunks):
        def body(c, out):
            rows, _ = chunk_rows(order, c, chunk)  # rows drawn before are drawn again, with the same keys
            return out.at[rows].set(outputs_at(params, aux, keys[rows], rows, s, g))

        return jax.lax.fori_loop(0, chunks, body, base)

    def forward(params, s, g, base, aux, keys, order, chunks):
        return outputs(params, s, g, base, aux, keys, order, chunks), (params, s, g, aux, keys, order, chunks)

    def backward(residuals, cotangent):
        params, s, g, aux, keys, order, chunks = residuals

        def body(c, carry):
            total, rest = carry
            rows, fresh = chunk_rows(order, c, chunk)
            _, vjp = jax.vjp(lambda p, ss, gg: outputs_at(p, aux, keys[rows], rows, ss, gg), params, s, g)
            total = jax.tree.map(jnp.add, total, vjp(jnp.where(fresh[:, None], cotangent[rows], 0.0)))
            return total, rest.at[rows].set(0.0)

        zero = jax.tree.map(jnp.zeros_like, (params, s, g))
        total, rest = jax.lax.fori_loop(0, chunks, body, (zero, cotangent))
        return (*total, rest, None, None, None, None)

    outputs.defvjp(forward, backward)
    return outputs(params, sigma, gamma, base, aux, keys, order, chunks)


def _face_colors(face_albedo, diffuse, specular, light_color, face, barycentric) -> list[Array]:
    """3 x (..., K): the colours of the faces `face` (..., K) at the fragments' perspective-correct
    `barycentric` weights (..., K, 3), from the faces' vertex albedos (F, 3, 3), diffuse
    factors (F,) and specular RGB (F, 3). Per channel, with the sums over the 3 vertices
    written out: no short reduction forward, and no broadcast of a per-pixel factor over the
    channels, whose transpose in reverse mode is one (jaxlib 0.10's CPU reductions over short
    axes are slow: rsmooth._unrolled; these took a third of a pose step)."""
    albedo = face_albedo[face]  # (..., K, 3 vertices, 3 channels)
    shade, highlight = diffuse[face], specular[face]  # (..., K), (..., K, 3)
    bary = [barycentric[..., v] for v in range(3)]
    return [
        (bary[0] * albedo[..., 0, c] + bary[1] * albedo[..., 1, c] + bary[2] * albedo[..., 2, c]) * shade * light_color[c]
        + highlight[..., c]
        for c in range(3)
    ]


def _rgba(weights: Array, color: list[Array], background: Array) -> Array:
    """(..., 4): the RGB composited by the aggregation `weights` (..., K + 1) of the K colours
    (3 x (..., K)) and the background (last weight), and alpha, 1 - the background's weight."""
    k = weights.shape[-1] - 1
    rgb = [sum_last(weights[..., :k] * color[c]) + weights[..., k] * background[c] for c in range(3)]
    return jnp.stack([*rgb, 1.0 - weights[..., k]], axis=-1)


class Image(eqx.Module):
    """A rendered image.

    Attributes:
        rgb: (H, W, 3) colours (background where nothing is drawn).
        alpha: (H, W) silhouette: 1 - the background's weight.
    """

    rgb: Array
    alpha: Array

    def rgba(self) -> Array:
        """(H, W, 4)."""
        return jnp.concatenate([self.rgb, self.alpha[..., None]], axis=-1)


class Renderer(eqx.Module):
    """A mesh renderer (a frozen configuration; call it to render).

    Attributes:
        mode: ``"hard"``, ``"soft"`` or ``"perturbed"``.
        sigma: coverage smoothing scale, in pixels (soft, perturbed); overridable per call.
        gamma: depth temperature, in normalized inverse depth units (soft, perturbed).
        num_samples: Monte-Carlo samples per pixel (perturbed).
        coverage_noise: law of the noise on signed distances (perturbed): Gaussian, Logistic,
            Cauchy, ... (any law with a differentiable density).
        depth_noise: law of the noise on depths (perturbed): Gumbel (softmax-like) or Gaussian.
        baseline: the perturbed estimator's baseline (static): True, the hard pixel (the
            paper's); ``"leave-one-out"``, the mean of the other samples (lower variance at
            edges, see :func:`rsmooth.render.perturbed_aggregate`); False, none.
        faces_per_pixel: candidate faces kept per pixel (K) by the smoothed modes and
            :meth:`fragments`; a hard render keeps one, the nearest covering face, all its
            image shows (the same image as with K, at half the time of K = 8 on a 1,280-face
            sphere at 128 x 128).
        faces_per_tile: candidate faces kept per tile in the first culling pass.
        tile_size: tile side in pixels.
        cull_backfaces: drop the faces seen from behind before choosing each pixel's
            candidates (for closed, outward-oriented meshes: the hard image is unchanged and a
            smaller `faces_per_pixel` suffices).
        clip_near: clip the faces that cross the camera's near plane and draw their part in
            front (static). False (the default) culls those faces whole, a hole where the mesh
            comes nearer than `Camera.near`, at no cost: the program does not contain the
            clipping, which about doubles the hard forward time on any mesh. Check
            ``renderer.fragments(mesh, camera).near_culled`` (0 when nothing was culled).
        interior_edges: smooth the coverage across every triangle edge, as SoftRas and the
            perturbed renderer of Le Lidec et al. do, which draws seams (coverage about 3/4)
            along the edges shared by two faces of a continuous surface; False (the default)
            smooths only the silhouette and boundary edges, where the image is discontinuous
            (see :func:`rsmooth.render.rasterize`). Hard rendering is the same either way.
        pixel_chunk: the perturbed renderer draws its samples only at the pixels whose change
            probability (:meth:`uncertainty`) exceeds :data:`NEGLIGIBLE`, in chunks of this
            fraction of the pixels (of the image, or of `pixels`), as many chunks as they fill
            (static; 1, the default: every pixel draws samples, no selection). The other
            pixels take their hard value, which every sample would give them, with a zero
            derivative from the aggregation (their shading's remains): the same image and
            derivatives, at a cost about proportional to the random pixels. The random pixels'
            fragments and colours are computed (and differentiated) in the chunks alone; the
            others' from their hard winner's fragment alone (with `clip_near`, the fragments of
            every pixel are differentiated). 1/8 suits gradients of closed meshes whose back
            faces are culled (timings: benchmarks/RESULTS.md). A loop of a traced number of
            chunks under a custom VJP: reverse mode, `jit` and `vmap` (which runs the most
            chunks of the batch) work, forward mode (`jax.jvp`, `jacfwd`) does not.
        dilation: candidate faces lie within `dilation * sigma` pixels of the pixel centre
            (smoothed modes); the noise's tail beyond is dropped (heavy-tailed laws such as
            Cauchy need a larger dilation).
        light: the directional light.
        background: background RGB.
        background_depth: the background's normalized inverse depth (0: at the far plane).
    """

    mode: str = eqx.field(static=True, default="perturbed")
    sigma: float = eqx.field(static=True, default=1.0, converter=float)
    gamma: float = eqx.field(static=True, default=0.01, converter=float)
    num_samples: int = eqx.field(static=True, default=8)
    coverage_noise: Noise = Gaussian()
    depth_noise: Noise = Gumbel()
    baseline: bool | str = eqx.field(static=True, default=True)
    faces_per_pixel: int = eqx.field(static=True, default=8)
    faces_per_tile: int = eqx.field(static=True, default=64)
    tile_size: int = eqx.field(static=True, default=8)
    cull_backfaces: bool = eqx.field(static=True, default=False)
    clip_near: bool = eqx.field(static=True, default=False)
    interior_edges: bool = eqx.field(static=True, default=False)
    dilation: float = eqx.field(static=True, default=3.0, converter=float)
    pixel_chunk: float = eqx.field(static=True, default=1.0, converter=float)
    light: DirectionalLight = DirectionalLight()
    background: tuple[float, float, float] = eqx.field(static=True, default=(0.0, 0.0, 0.0), converter=_triple)
    background_depth: float = eqx.field(static=True, default=0.0, converter=float)

    def __check_init__(self):
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {self.mode!r}")
        for name in ("sigma", "gamma"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive, finite number, got {value!r}")
        for name in ("num_samples", "faces_per_pixel", "faces_per_tile", "tile_size"):
            _checks.check_num_samples(getattr(self, name), name)
        if not 0.0 < self.pixel_chunk <= 1.0:
            raise ValueError(f"pixel_chunk must be in (0, 1] (a fraction of the pixels), got {self.pixel_chunk}")
        if not (math.isfinite(self.dilation) and self.dilation >= 0):
            raise ValueError(f"dilation must be a finite number >= 0, got {self.dilation}")
        if not math.isfinite(self.background_depth):
            raise ValueError(f"background_depth must be finite, got {self.background_depth}")
        if not all(math.isfinite(c) for c in self.background):
            raise ValueError(f"background must be a finite RGB colour, got {self.background}")
        if self.faces_per_tile < self.faces_per_pixel:
            raise ValueError(
                f"faces_per_tile ({self.faces_per_tile}) must be >= faces_per_pixel ({self.faces_per_pixel})"
            )
        if self.mode == "perturbed":
            _check_baseline(self.baseline, self.num_samples)
        for name in ("coverage_noise", "depth_noise"):
            law = getattr(self, name)
            if not isinstance(law, Noise):
                raise TypeError(f"{name} must be an rsmooth.noise.Noise, got {law!r}")
            if self.mode == "perturbed" and not law.has_score:
                raise ValueError(f"{name}: {type(law).__name__} has no differentiable density")

    def __call__(
        self,
        key: Array | None,
        mesh: Mesh,
        camera: Camera,
        *,
        sigma: ArrayLike | None = None,
        gamma: ArrayLike | None = None,
        pixels: ArrayLike | None = None,
    ) -> Image:
        """Renders `mesh` seen by `camera`.

        Args:
            key: PRNG key (used by ``"perturbed"``; may be None otherwise).
            mesh: the mesh (its vertices may be traced: the image is differentiable in them).
            camera: the camera (static image size).
            sigma, gamma: override the configured noise levels (may be traced, e.g. by a noise
                schedule; the perturbed estimator then also estimates their derivatives).
            pixels: (P,) integer indices into the flattened image (``row * W + col``): render
                these pixels only, at a cost about proportional to P (the candidate selection
                still scans the image, see :func:`rsmooth.render.rasterize`). A perturbed
                pixel draws the same noise as in the whole image rendered with the same key,
                so its value and derivatives are the same. Use it to spend more samples where
                the image is random (:meth:`uncertainty`).

        Returns:
            An :class:`Image`; with `pixels`, its `rgb` is (P, 3) and its `alpha` (P,).
        """
        if not isinstance(mesh, Mesh):
            raise TypeError(f"mesh must be an rsmooth.render.Mesh, got {type(mesh).__name__}")
        if not isinstance(camera, Camera):
            raise TypeError(f"camera must be an rsmooth.render.Camera, got {type(camera).__name__}")
        if self.mode == "perturbed":
            if key is None:
                raise ValueError("the perturbed renderer needs a PRNG key")
            _checks.check_key(key)
        camera = check_camera(camera)
        sigma, gamma = self._levels(mesh, sigma, gamma)
        if self.mode == "perturbed" and self.pixel_chunk < 1.0:
            return self._sampled_at_random_pixels(key, mesh, camera, sigma, gamma, pixels)
        fragments = self._rasterize(mesh, camera, sigma, gamma, pixels, 1 if self.mode == "hard" else self.faces_per_pixel)
        k = fragments.face_index.shape[-1]
        color = _face_colors(*self._shading(mesh, camera), self._light_color(mesh), fragments.face_index, fragments.barycentric)
        distance, depth = _slots(fragments)
        if self.mode == "hard":
            weights = hard_aggregate(distance, depth, self.background_depth)
        elif self.mode == "soft":
            weights = soft_aggregate(distance, depth, sigma=sigma, gamma=gamma, background_depth=self.background_depth)
        else:
            pixel = self._pixel_weights(sigma, gamma)
            flat = [a.reshape(-1, k) for a in (distance, depth)]
            weights = jax.vmap(pixel)(self._pixel_keys(key, camera, pixels), *flat).reshape(distance.shape[:-1] + (k + 1,))
        rgba = _rgba(weights, color, jnp.asarray(self.background, mesh.vertices.dtype))
        return Image(rgb=rgba[..., :3], alpha=rgba[..., 3])

    def _shading(self, mesh: Mesh, camera: Camera) -> tuple[Array, Array, Array]:
        """The faces' vertex albedos (F, 3, 3), diffuse factors (F,) and specular RGB (F, 3)."""
        return (mesh.albedo()[mesh.faces], *shade_faces(mesh, camera, self.light))

    def _light_color(self, mesh: Mesh) -> Array:
        return jnp.asarray(self.light.color, mesh.vertices.dtype)

    def _pixel_keys(self, key: Array, camera: Camera, pixels: Array | None) -> Array:
        """One key per pixel, the same for a pixel whether the image or `pixels` is rendered."""
        height, width = camera.image_size
        keys = jax.random.split(key, height * width)
        return keys if pixels is None else keys[pixels]

    def _pixel_weights(self, sigma: Array, gamma: Array):
        """``pixel(key, d, z, sigma=sigma, gamma=gamma)``: one pixel's (K + 1) perturbed weights."""
        def pixel(key, d, z, sigma=sigma, gamma=gamma):
            return perturbed_aggregate(
                key, d, z, sigma=sigma, gamma=gamma, num_samples=self.num_samples,
                coverage_noise=self.coverage_noise, depth_noise=self.depth_noise,
                background_depth=self.background_depth, baseline=self.baseline,
            )

        return pixel

    def _sampled_at_random_pixels(self, key, mesh, camera, sigma, gamma, pixels) -> Image:
        """The perturbed image with samples at the random pixels alone (`pixel_chunk`): the
        candidates' distances and depths of every pixel, values only, rank the pixels; the
        random ones are drawn in chunks (`_random_pixel_outputs`), each chunk's fragments
        recomputed there, with their derivatives; the others take their hard winner's colour,
        whose fragment alone is recomputed, differentiably (K = 1: the other candidates'
        barycentric weights and colours are not computed there)."""
        height, width = camera.image_size
        dtype = mesh.vertices.dtype
        fragments = self._rasterize(mesh, camera, sigma, gamma, pixels, self.faces_per_pixel)
        k = fragments.face_index.shape[-1]
        shape = fragments.face_index.shape[:-1]  # (H, W), or (P,)
        slots = [a.reshape(-1, k) for a in _slots(fragments)]
        num_pixels = slots[0].shape[0]
        fixed = jax.lax.stop_gradient(slots)
        uncertainty = change_probability(
            *fixed, sigma=sigma, gamma=gamma, coverage_noise=self.coverage_noise, depth_noise=self.depth_noise,
            background_depth=self.background_depth,
        )
        chunk = min(num_pixels, max(1, round(self.pixel_chunk * num_pixels)))
        order, chunks = random_pixel_chunks(uncertainty, chunk)
        hard_weights = hard_aggregate(*fixed, self.background_depth)  # (N, K + 1), one-hot
        keys = self._pixel_keys(key, camera, pixels)
        pixel = self._pixel_weights(sigma, gamma)
        shading, light_color = self._shading(mesh, camera), self._light_color(mesh)
        background = jnp.asarray(self.background, dtype)

        def drawn(keys, d, z, s, g):
            return jax.vmap(lambda key, d, z: pixel(key, d, z, s, g))(keys, d, z)

        if self.clip_near:
            # the clipped fragments of every pixel, differentiated there, gathered at the rows
            color = [c.reshape(-1, k) for c in _face_colors(*shading, light_color, fragments.face_index, fragments.barycentric)]
            params, aux = (slots, color), None
            base = _rgba(hard_weights, color, background)

            def outputs_at(params, aux, keys, rows, s, g):
                (d, z), color = params
                return _rgba(drawn(keys, d[rows], z[rows], s, g), [c[rows] for c in color], background)
        else:
            geometry, edges = triangle_geometry(mesh, camera, self.cull_backfaces, self.interior_edges)
            ids = jnp.arange(height * width) if pixels is None else check_pixels(pixels, height * width)
            qx, qy = pixel_centres(ids, width, dtype)
            face_index = jax.lax.stop_gradient(fragments.face_index).reshape(-1, k)
            params, aux = (geometry, shading), (edges, face_index, fragments.present.reshape(-1, k), qx, qy)

            def outputs_at(params, aux, keys, rows, s, g):
                geometry, shading = params
                edges, face_index, present, qx, qy = aux
                face = face_index[rows]
                d, z, bary = triangle_fragments_at(geometry, edges, face, qx[rows], qy[rows])
                weights = drawn(keys, *_slot_values(present[rows], d, z), s, g)
                return _rgba(weights, _face_colors(*shading, light_color, face, bary), background)

            winner = jnp.argmax(hard_weights, axis=-1)  # K: the background
            face = jnp.take_along_axis(face_index, jnp.minimum(winner, k - 1)[:, None], axis=-1)  # (N, 1)
            _, _, bary = triangle_fragments_at(geometry, edges, face, qx, qy)
            covered = (winner < k).astype(dtype)[:, None]
            base = _rgba(jnp.concatenate([covered, 1.0 - covered], axis=-1), _face_colors(*shading, light_color, face, bary), background)
        rgba = _random_pixel_outputs(outputs_at, params, aux, sigma, gamma, keys, order, chunks, chunk, base)
        rgba = rgba.reshape(shape + (4,))
        return Image(rgb=rgba[..., :3], alpha=rgba[..., 3])

    def _levels(self, mesh: Mesh, sigma: ArrayLike | None, gamma: ArrayLike | None) -> tuple[Array, Array]:
        """sigma and gamma of a call (the configured ones where None), in the mesh's dtype; those
        given are checked to be positive, finite scalars."""
        dtype = mesh.vertices.dtype
        return (
            jnp.asarray(self.sigma, dtype) if sigma is None else _noise_level(sigma, "sigma", dtype),
            jnp.asarray(self.gamma, dtype) if gamma is None else _noise_level(gamma, "gamma", dtype),
        )

    def fragments(
        self,
        mesh: Mesh,
        camera: Camera,
        *,
        sigma: ArrayLike | None = None,
        gamma: ArrayLike | None = None,
        pixels: ArrayLike | None = None,
    ) -> Fragments:
        """The rasterizer's output that this renderer draws (:func:`rsmooth.render.rasterize`
        with its options), and with it the diagnostics that the image does not carry:
        `near_culled`, the faces crossing the near plane that were dropped (see `clip_near`),
        and `tile_overflow`.

        Example:
            >>> import jax, jax.numpy as jnp
            >>> from rsmooth.render import Renderer, icosphere, look_at
            >>> camera = look_at(jnp.array([0.0, 0.0, 1.5]), image_size=(16, 16), fov=90.0, near=0.8)
            >>> for clip_near in (False, True):
            ...     renderer = Renderer(mode="hard", clip_near=clip_near)
            ...     # jitted, only the count is computed (the fragments are dead code)
            ...     print(int(jax.jit(lambda m: renderer.fragments(m, camera).near_culled)(icosphere(1))))
            16
            0
        """
        sigma, gamma = self._levels(mesh, sigma, gamma)
        return self._rasterize(mesh, check_camera(camera), sigma, gamma, pixels, self.faces_per_pixel)

    def _rasterize(self, mesh, camera, sigma, gamma, pixels, faces_per_pixel) -> Fragments:
        """`rasterize` with this renderer's options, at the levels of :meth:`_levels`."""
        hard = self.mode == "hard"
        return rasterize(
            mesh,
            camera,
            faces_per_pixel=faces_per_pixel,
            margin=0.0 if hard else self.dilation * sigma,
            sigma=None if hard else sigma,
            gamma=None if hard else gamma,
            tile_size=self.tile_size,
            faces_per_tile=self.faces_per_tile,
            cull_backfaces=self.cull_backfaces,
            interior_edges=hard or self.interior_edges,
            clip_near=self.clip_near,
            pixels=pixels,
        )

    def uncertainty(
        self, mesh: Mesh, camera: Camera, *, sigma: ArrayLike | None = None, gamma: ArrayLike | None = None
    ) -> Array:
        """(H, W): per pixel, an upper bound on the probability that a sample of the perturbed
        pixel differs from the hard pixel (:func:`rsmooth.render.change_probability` of its
        candidates), outside the derivative.

        Where it is ~0 (e.g. below 1e-9), every sample the renderer draws for the pixel gives the
        hard pixel, and the estimator's terms vanish (with a baseline): more samples there change
        nothing. With Gaussian coverage noise, only the pixels within ~6 sigma of a silhouette
        edge (or where faces lie within ~20 gamma in depth) are random. Rank pixels by it to
        render more samples at the random ones alone (`pixels` of :meth:`__call__`).

        Example:
            >>> import jax.numpy as jnp
            >>> from rsmooth.render import Renderer, cube, look_at
            >>> camera = look_at(jnp.array([0.0, 0.0, 4.0]), image_size=(32, 32), near=3.0, far=5.0)
            >>> p = Renderer(sigma=0.5, cull_backfaces=True).uncertainty(cube(), camera)
            >>> float(p[16, 16]) < 1e-9, float(p[0, 0]) < 1e-9, float(p.max()) > 0.4  # centre, corner, edge
            (True, True, True)
        """
        if self.mode != "perturbed":
            raise ValueError(f"uncertainty is the perturbed renderer's (mode 'perturbed'), got mode {self.mode!r}")
        sigma, gamma = self._levels(mesh, sigma, gamma)
        fragments = jax.lax.stop_gradient(self._rasterize(mesh, check_camera(camera), sigma, gamma, None, self.faces_per_pixel))
        return change_probability(
            *_slots(fragments), sigma=sigma, gamma=gamma, coverage_noise=self.coverage_noise, depth_noise=self.depth_noise,
            background_depth=self.background_depth,
        )
