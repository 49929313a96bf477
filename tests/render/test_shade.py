"""Shading: Lambertian and Blinn-Phong under a directional light."""

import jax.numpy as jnp
import numpy as np
import pytest

from rsmooth import render


def test_lambertian_and_phong_terms():
    camera = render.look_at(jnp.array([0.0, 0.0, 4.0]), image_size=(8, 8))
    # One triangle facing the camera (normal +z), lit head-on, then at 60 degrees.
    mesh = render.Mesh(np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]), np.array([[0, 1, 2]]))
    head_on = render.DirectionalLight(direction=(0.0, 0.0, -1.0), ambient=0.2, diffuse=0.8, specular=0.5, shininess=8.0)
    diffuse, specular = render.shade_faces(mesh, camera, head_on)
    assert float(diffuse[0]) == pytest.approx(1.0)
    assert float(specular[0, 0]) > 0.45
    oblique = render.DirectionalLight(direction=(0.0, -np.sqrt(3) / 2, -0.5), ambient=0.2, diffuse=0.8)
    diffuse, specular = render.shade_faces(mesh, camera, oblique)
    assert float(diffuse[0]) == pytest.approx(0.2 + 0.8 * 0.5)
    assert float(jnp.max(specular)) == 0.0
    # Two-sided: the same face with the other winding is lit the same.
    flipped = render.Mesh(mesh.vertices, np.array([[0, 2, 1]]))
    np.testing.assert_allclose(render.shade_faces(flipped, camera, oblique)[0], diffuse)
    # Light from behind the face: ambient only.
    behind = render.DirectionalLight(direction=(0.0, 0.0, 1.0), ambient=0.2, diffuse=0.8)
    assert float(render.shade_faces(mesh, camera, behind)[0][0]) == pytest.approx(0.2)
