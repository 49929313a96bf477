r"""Rotations and the pinhole camera: world -> camera frame -> pixel coordinates.

Conventions (OpenCV's): the camera frame has x to the right, y down and z forward (the viewing
direction); pixel coordinates are continuous, in pixels, with the centre of pixel (row i,
column j) at ``(x, y) = (j + 0.5, i + 0.5)``. A camera holds the world-to-camera rigid motion
:math:`p_c = R\,p_w + t`, a vertical field of view, near and far planes and a static image
size; it is a pytree, so a batch of views is a `Camera` with a leading axis on its arrays,
rendered with `jax.vmap`.

Example:
    >>> import jax.numpy as jnp
    >>> from rsmooth.render import look_at
    >>> camera = look_at(jnp.array([0.0, 0.0, -3.0]), image_size=(32, 32), fov=60.0)
    >>> xy, depth = camera.project(jnp.zeros((1, 3)))
    >>> [round(float(v), 3) for v in xy[0]], round(float(depth[0]), 3)
    ([16.0, 16.0], 3.0)
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.typing import ArrayLike

from rsmooth import _checks
from rsmooth._xla import matmul as _matmul

__all__ = [
    "Camera",
    "look_at",
    "axis_angle_to_matrix",
    "quaternion_to_matrix",
    "rotation_angle",
    "random_rotation",
]


def axis_angle_to_matrix(axis_angle: ArrayLike) -> Array:
    r"""Rotation matrix of a rotation vector (axis times angle in radians), by Rodrigues' formula.

    .. math:: R = I + \frac{\sin\theta}{\theta}[v]_\times + \frac{1-\cos\theta}{\theta^2}[v]_\times^2,
        \qquad \theta = \|v\|,

    with the Taylor expansions near :math:`\theta = 0`, so that it is differentiable there.

    Example:
        >>> import jax.numpy as jnp
        >>> R = axis_angle_to_matrix(jnp.array([0.0, 0.0, jnp.pi / 2]))
        >>> [round(float(v), 6) + 0.0 for v in R @ jnp.array([1.0, 0.0, 0.0])]
        [0.0, 1.0, 0.0]
    """
    v = jnp.asarray(axis_angle)
    if v.shape[-1:] != (3,):
        raise ValueError(f"axis_angle must have a last axis of size 3, got shape {v.shape}")
    theta2 = jnp.sum(v**2, axis=-1)[..., None, None]
    small = theta2 < 1e-8
    safe2 = jnp.where(small, 1.0, theta2)
    safe = jnp.sqrt(safe2)
    a = jnp.where(small, 1.0 - theta2 / 6.0, jnp.sin(safe) / safe)
    b = jnp.where(small, 0.5 - theta2 / 24.0, (1.0 - jnp.cos(safe)) / safe2)
    zero = jnp.zeros_like(v[..., 0])
    k = jnp.stack(
        [
            jnp.stack([zero, -v[..., 2], v[..., 1]], -1),
            jnp.stack([v[..., 2], zero, -v[..., 0]], -1),
            jnp.stack([-v[..., 1], v[..., 0], zero], -1),
        ],
        -2,
    )
    eye = jnp.broadcast_to(jnp.eye(3, dtype=v.dtype), k.shape)
    return eye + a * k + b * _matmul(k, k)


def quaternion_to_matrix(quaternion: ArrayLike) -> Array:
    """Rotation matrix of a quaternion ``(w, x, y, z)`` (normalized here; need not be unit).

    Example:
        >>> import jax.numpy as jnp
        >>> bool(jnp.allclose(quaternion_to_matrix(jnp.array([2.0, 0.0, 0.0, 0.0])), jnp.eye(3)))
        True
    """
    q = jnp.asarray(quaternion)
    if q.shape[-1:] != (4,):
        raise ValueError(f"quaternion must have a last axis of size 4, got shape {q.shape}")
    q = q / jnp.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    return jnp.stack([jnp.stack(r, -1) for r in rows], -2)


def rotation_angle(r1: ArrayLike, r2: ArrayLike) -> Array:
    """Geodesic distance (radians, in [0, pi]) between two rotation matrices."""
    r1, r2 = jnp.asarray(r1), jnp.asarray(r2)
    cos = (jnp.trace(_matmul(jnp.swapaxes(r1, -1, -2), r2), axis1=-2, axis2=-1) - 1.0) / 2.0
    return jnp.arccos(jnp.clip(cos, -1.0, 1.0))


def random_rotation(key: Array, dtype=float) -> Array:
    """A rotation matrix drawn uniformly (Haar measure), from a normalized Gaussian quaternion."""
    return quaternion_to_matrix(jax.random.normal(key, (4,), dtype))


_POSE_MESSAGE = "camera rotation and translation must be finite (the camera pose contains NaN or inf)"
_INTRINSICS_MESSAGE = "camera fov must be in (0, 180) degrees and 0 < near < far"


def _is_traced(value) -> bool:
    return isinstance(value, jax.core.Tracer)


def _pose_is_finite(rotation, translation):
    return jnp.all(jnp.isfinite(rotation)) & jnp.all(jnp.isfinite(translation))


def _intrinsics_are_valid(fov, near, far):
    return jnp.all((fov > 0) & (fov < 180) & (near > 0) & (far > near))


def _check_concrete(camera: "Camera") -> None:
    """The checks of :func:`check_camera` on the arrays that are not traced, now (`ValueError`)."""
    if not any(_is_traced(a) for a in (camera.rotation, camera.translation)):
        rotation, translation = np.asarray(camera.rotation), np.asarray(camera.translation)
        if not np.all(np.isfinite(rotation)):
            raise ValueError(f"camera rotation must be finite, got {rotation.tolist()}")
        if not np.all(np.isfinite(translation)):
            raise ValueError(f"camera translation must be finite, got {translation.tolist()}")
    if not any(_is_traced(a) for a in (camera.fov, camera.near, camera.far)):
        fov, near, far = (np.asarray(a) for a in (camera.fov, camera.near, camera.far))
        if not np.all((fov > 0) & (fov < 180)):
            raise ValueError(f"camera fov must be in (0, 180) degrees, got {fov}")
        if not np.all((near > 0) & (far > near)):
            raise ValueError(f"camera near and far must satisfy 0 < near < far, got near={near}, far={far}")


def check_camera(camera: "Camera") -> "Camera":
    """Returns `camera` after checking that its pose is finite, ``0 < fov < 180`` and
    ``0 < near < far``: now (`ValueError`) for concrete arrays, when the program runs
    (`equinox.error_if`) for traced ones (the check is then tied to the returned camera)."""
    _check_concrete(camera)
    pose = lambda c: (c.rotation, c.translation)  # noqa: E731
    intrinsics = lambda c: (c.fov, c.near, c.far)  # noqa: E731
    if any(_is_traced(a) for a in pose(camera)):
        checked = _checks.error_if(pose(camera), ~_pose_is_finite(*pose(camera)), _POSE_MESSAGE)
        camera = eqx.tree_at(pose, camera, checked)
    if any(_is_traced(a) for a in intrinsics(camera)):
        checked = _checks.error_if(intrinsics(camera), ~_intrinsics_are_valid(*intrinsics(camera)), _INTRINSICS_MESSAGE)
        camera = eqx.tree_at(intrinsics, camera, checked)
    return camera


class Camera(eqx.Module):
    """A pinhole camera.

    Attributes:
        rotation: (3, 3) world-to-camera rotation R.
        translation: (3,) world-to-camera translation t: a world point p is at R p + t in the
            camera frame.
        fov: vertical field of view in degrees.
        near: near plane distance (> 0). A face with a vertex nearer than it is not drawn at
            all (`Fragments.near_culled` counts those in view) unless the renderer clips it
            (``Renderer(clip_near=True)``, ``rasterize(clip_near=True)``): then its part in
            front of the plane is drawn.
        far: far plane distance (> near); faces with every vertex beyond it are not drawn.
        image_size: (height, width) in pixels (static: it fixes array shapes).
    """

    rotation: Array
    translation: Array
    fov: Array
    near: Array
    far: Array
    image_size: tuple[int, int] = eqx.field(static=True)

    def __init__(self, rotation, translation, *, fov=45.0, near=0.1, far=100.0, image_size=(64, 64)):
        rotation = jnp.asarray(rotation, float)
        translation = jnp.asarray(translation, rotation.dtype)
        fov, near, far = (jnp.asarray(a, rotation.dtype) for a in (fov, near, far))
        # Traced values are checked when the program runs; concrete ones in __check_init__.
        if _is_traced(rotation) or _is_traced(translation):
            rotation, translation = _checks.error_if((rotation, translation), ~_pose_is_finite(rotation, translation), _POSE_MESSAGE)
        if any(_is_traced(a) for a in (fov, near, far)):
            fov, near, far = _checks.error_if((fov, near, far), ~_intrinsics_are_valid(fov, near, far), _INTRINSICS_MESSAGE)
        self.rotation, self.translation, self.fov, self.near, self.far = rotation, translation, fov, near, far
        if len(image_size) != 2 or any(int(s) != s or s < 1 for s in image_size):
            raise ValueError(f"image_size must be (height, width), two positive ints, got {image_size}")
        self.image_size = (int(image_size[0]), int(image_size[1]))

    def __check_init__(self):
        if self.rotation.shape[-2:] != (3, 3) or self.translation.shape[-1:] != (3,):
            raise ValueError(
                f"rotation must be (3, 3) and translation (3,), got {self.rotation.shape} and {self.translation.shape}"
            )
        _check_concrete(self)

    @classmethod
    def from_pose(
        cls, axis_angle: ArrayLike, translation: ArrayLike, *, fov=45.0, near=0.1, far=100.0, image_size=(64, 64)
    ) -> "Camera":
        """A camera whose world-to-camera rotation is given as a rotation vector (radians);
        use :func:`quaternion_to_matrix` and the constructor for a quaternion."""
        return cls(axis_angle_to_matrix(axis_angle), translation, fov=fov, near=near, far=far, image_size=image_size)

    @property
    def focal_length(self) -> Array:
        """Focal length in pixels: (height / 2) / tan(fov / 2)."""
        return 0.5 * self.image_size[0] / jnp.tan(jnp.deg2rad(self.fov) / 2.0)

    def to_camera(self, points: ArrayLike) -> Array:
        """World points (N, 3) -> camera-frame points (N, 3)."""
        points = jnp.asarray(points)
        return _matmul(points, self.rotation.T) + self.translation[None, :]

    def project(self, points: ArrayLike) -> tuple[Array, Array]:
        """World points (N, 3) -> pixel coordinates (N, 2) and depths z (N,).

        Points at or behind the camera (z <= 0) get finite but meaningless pixel coordinates;
        the rasterizer culls faces with a vertex nearer than `near`, or with `clip_near`
        clips them at the near plane, so that it never uses them.
        """
        p = self.to_camera(points)
        z = p[:, 2]
        safe = jnp.where(z > 1e-9, z, 1.0)
        height, width = self.image_size
        xy = self.focal_length * p[:, :2] / safe[:, None] + jnp.array([[width / 2.0, height / 2.0]], p.dtype)
        return xy, z


def look_at(
    eye: ArrayLike,
    target: ArrayLike = (0.0, 0.0, 0.0),
    up: ArrayLike = (0.0, 1.0, 0.0),
    *,
    fov: float = 45.0,
    near: float = 0.1,
    far: float = 100.0,
    image_size: tuple[int, int] = (64, 64),
) -> Camera:
    """A camera at `eye` looking at `target`, with world `up` pointing up in the image.

    Raises:
        ValueError: `eye`, `target` or `up` is not finite, `eye` equals `target`, or `up` is
            parallel to the viewing direction.
    """
    eye = jnp.asarray(eye, float)
    target = jnp.asarray(target, eye.dtype)
    up = jnp.asarray(up, eye.dtype)
    for name, value in (("eye", eye), ("target", target), ("up", up)):
        if not _is_traced(value) and not np.all(np.isfinite(np.asarray(value))):
            raise ValueError(f"look_at: {name} must be finite, got {np.asarray(value).tolist()}")
    forward = target - eye
    if not isinstance(forward, jax.core.Tracer):
        norm = float(np.linalg.norm(np.asarray(forward)))
        if norm < 1e-12:
            raise ValueError("look_at: eye and target coincide")
        if float(np.linalg.norm(np.cross(np.asarray(forward), np.asarray(up)))) < 1e-9 * norm:
            raise ValueError("look_at: up is parallel to the viewing direction")
    forward = forward / jnp.linalg.norm(forward)
    right = jnp.cross(forward, up)
    right = right / jnp.linalg.norm(right)
    down = jnp.cross(forward, right)
    rotation = jnp.stack([right, down, forward])
    return Camera(rotation, -_matmul(rotation, eye), fov=fov, near=near, far=far, image_size=image_size)

