r"""Shading under a directional light: Lambertian diffuse and an optional Blinn-Phong specular.

Flat shading: each face has one normal; shading is two-sided (a face seen from its back is lit
as if its normal were flipped towards the camera), so open meshes and either winding work.

.. math:: c = \rho\,\big(k_a + k_d \max(0, n\cdot l)\big) + k_s \max(0, n\cdot h)^{s},
    \qquad h = \frac{l + v}{\|l + v\|},

with :math:`\rho` the albedo, :math:`l` the direction towards the light and :math:`v` towards
the camera.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jax import Array

from rsmooth._xla import matmul as _matmul
from rsmooth.render._camera import Camera
from rsmooth.render._mesh import Mesh, face_normals

__all__ = ["DirectionalLight", "shade_faces"]


def _triple(value) -> tuple[float, float, float]:
    value = tuple(float(v) for v in value)
    if len(value) != 3:
        raise ValueError(f"expected three numbers, got {value}")
    return value


class DirectionalLight(eqx.Module):
    """A directional light (all fields static: plain numbers).

    Attributes:
        direction: direction the light travels, in world coordinates (need not be unit).
        color: RGB intensity.
        ambient: ambient coefficient k_a.
        diffuse: Lambertian coefficient k_d.
        specular: Blinn-Phong coefficient k_s (0: Lambertian only).
        shininess: Blinn-Phong exponent s.
    """

    direction: tuple[float, float, float] = eqx.field(static=True, default=(0.3, -0.6, -1.0), converter=_triple)
    color: tuple[float, float, float] = eqx.field(static=True, default=(1.0, 1.0, 1.0), converter=_triple)
    ambient: float = eqx.field(static=True, default=0.35, converter=float)
    diffuse: float = eqx.field(static=True, default=0.65, converter=float)
    specular: float = eqx.field(static=True, default=0.0, converter=float)
    shininess: float = eqx.field(static=True, default=32.0, converter=float)


def shade_faces(mesh: Mesh, camera: Camera, light: DirectionalLight) -> tuple[Array, Array]:
    """Per-face diffuse factor (F,) and specular RGB (F, 3), in the camera frame.

    The colour of a fragment is ``albedo * diffuse_factor * light.color + specular``.
    """
    vertices = camera.to_camera(mesh.vertices)
    normals = face_normals(vertices, mesh.faces)
    centroid = jnp.mean(vertices[mesh.faces], axis=1)
    to_camera = -centroid / jnp.sqrt(jnp.maximum(jnp.sum(centroid**2, axis=-1, keepdims=True), 1e-30))
    facing = jnp.sum(normals * to_camera, axis=-1, keepdims=True)
    normals = jnp.where(facing < 0, -normals, normals)
    direction = jnp.asarray(light.direction, vertices.dtype)
    to_light = -_matmul(camera.rotation, direction)
    to_light = to_light / jnp.linalg.norm(to_light)
    lambert = jnp.maximum(_matmul(normals, to_light), 0.0)
    diffuse = light.ambient + light.diffuse * lambert
    color = jnp.asarray(light.color, vertices.dtype)
    if light.specular > 0:
        half = to_light[None, :] + to_camera
        half = half / jnp.sqrt(jnp.maximum(jnp.sum(half**2, axis=-1, keepdims=True), 1e-30))
        spec = light.specular * jnp.maximum(jnp.sum(normals * half, axis=-1), 0.0) ** light.shininess
        specular = spec[:, None] * color[None, :]
    else:
        specular = jnp.zeros(normals.shape, vertices.dtype)
    return diffuse, specular

