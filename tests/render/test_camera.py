"""Rotations and cameras."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rsmooth import render


def test_axis_angle_and_quaternion_agree(getkey):
    for _ in range(5):
        axis = jax.random.normal(getkey(), (3,))
        axis = axis / jnp.linalg.norm(axis)
        angle = float(jax.random.uniform(getkey(), (), minval=0.0, maxval=3.0))
        r = render.axis_angle_to_matrix(angle * axis)
        q = jnp.concatenate([jnp.array([np.cos(angle / 2)]), np.sin(angle / 2) * axis])
        np.testing.assert_allclose(r, render.quaternion_to_matrix(q), atol=1e-12)
        np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
        assert float(render.rotation_angle(jnp.eye(3), r)) == pytest.approx(angle, abs=1e-6)


def test_axis_angle_is_differentiable_at_zero():
    jac = jax.jacobian(render.axis_angle_to_matrix)(jnp.zeros(3))
    assert bool(jnp.all(jnp.isfinite(jac)))
    # d R / d v_z at 0 is the generator [e_z]_x.
    np.testing.assert_allclose(jac[:, :, 2], np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 0]]), atol=1e-12)


def test_look_at_projects_target_to_centre_and_up_to_the_top():
    camera = render.look_at(jnp.array([1.0, 2.0, 5.0]), target=jnp.array([0.0, 0.5, 0.0]), image_size=(20, 30))
    xy, depth = camera.project(jnp.array([[0.0, 0.5, 0.0], [0.0, 1.0, 0.0]]))
    np.testing.assert_allclose(xy[0], [15.0, 10.0], atol=1e-9)
    assert float(depth[0]) == pytest.approx(float(np.linalg.norm([1.0, 1.5, 5.0])))
    assert float(xy[1, 1]) < 10.0  # world up is image up (smaller row)


def test_cameras_batch_under_vmap():
    eyes = jnp.array([[0.0, 0.0, 3.0], [3.0, 0.0, 0.0]])
    cameras = jax.vmap(lambda e: render.look_at(e, image_size=(8, 8)))(eyes)
    assert cameras.rotation.shape == (2, 3, 3)
    xy, _ = jax.vmap(lambda c: c.project(jnp.zeros((1, 3))))(cameras)
    np.testing.assert_allclose(xy, 4.0, atol=1e-9)


def test_bad_cameras():
    with pytest.raises(ValueError, match="coincide"):
        render.look_at(jnp.zeros(3), target=jnp.zeros(3))
    with pytest.raises(ValueError, match="parallel"):
        render.look_at(jnp.array([0.0, 3.0, 0.0]))
    with pytest.raises(ValueError, match="near"):
        render.look_at(jnp.array([0.0, 0.0, 3.0]), near=2.0, far=1.0)
    with pytest.raises(ValueError, match="fov"):
        render.look_at(jnp.array([0.0, 0.0, 3.0]), fov=200.0)
    with pytest.raises(ValueError, match="image_size"):
        render.look_at(jnp.array([0.0, 0.0, 3.0]), image_size=(0, 4))


def test_camera_from_pose_matches_look_at():
    camera = render.Camera.from_pose(jnp.array([0.0, np.pi, 0.0]), jnp.array([0.0, 0.0, 4.0]), image_size=(8, 8))
    # Rotating by pi about y and moving 4 along z: a camera at (0, 0, 4) looking at the origin, y down.
    reference = render.look_at(jnp.array([0.0, 0.0, 4.0]), up=jnp.array([0.0, -1.0, 0.0]), image_size=(8, 8))
    points = jnp.array([[0.3, -0.2, 0.1], [0.0, 0.5, -0.5]])
    np.testing.assert_allclose(camera.project(points)[0], reference.project(points)[0], atol=1e-9)


def test_camera_pose_must_be_finite():
    eye = jnp.array([0.0, 0.0, 4.0])
    with pytest.raises(ValueError, match="camera rotation must be finite"):
        render.Camera(jnp.full((3, 3), jnp.nan), jnp.zeros(3))
    with pytest.raises(ValueError, match="camera translation must be finite"):
        render.Camera(jnp.eye(3), jnp.array([0.0, jnp.inf, 0.0]))
    with pytest.raises(ValueError, match="look_at: eye must be finite"):
        render.look_at(eye.at[0].set(jnp.nan))
    with pytest.raises(ValueError, match="look_at: target must be finite"):
        render.look_at(eye, target=(0.0, jnp.nan, 0.0))
    with pytest.raises(ValueError, match="camera fov"):
        render.look_at(eye, fov=float("nan"))
    with pytest.raises(ValueError, match="near and far"):
        render.look_at(eye, near=float("nan"))
    # traced: checked when the program runs
    with pytest.raises(Exception, match="camera rotation and translation must be finite"):
        jax.jit(lambda t: render.Camera(jnp.eye(3), t).translation)(jnp.array([0.0, jnp.nan, 0.0])).block_until_ready()
    assert render.Camera.from_pose(jnp.zeros(3), jnp.array([0.0, 0.0, 4.0]), far=float("inf")).far == float("inf")
