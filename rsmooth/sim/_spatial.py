"""Spatial algebra in pure JAX: rotations, quaternions, SE(3) exp/log, 6D vectors, inertias.

Conventions follow Pinocchio so that results can be compared number for number:

- A placement ``(rotation, translation)`` of frame B in frame A maps B-coordinates to
  A-coordinates: ``x_A = rotation @ x_B + translation``.
- A spatial motion (twist) is a 6-vector ``[linear, angular]``; a spatial force (wrench) is
  ``[force, torque]``.
- Quaternions are stored ``[x, y, z, w]`` (Eigen's coefficient order, as in Pinocchio's
  configuration vectors).

Functions act on single vectors and matrices; batch them with ``jax.vmap`` (``rotate``, the
spatial cross products and ``inertia_apply`` also broadcast over leading axes). Products of
3x3 matrices and 3-vectors are written as sums of elementwise products (:func:`rotate`,
:func:`matmul3`): XLA fuses these into one loop, whereas it lowers a batched 3x3 ``dot``
under ``vmap``/``jacfwd`` to thousands of tiny matrix products (about 10x slower on CPU).
For the same reason short sums are unrolled (:func:`dot3`, ``rsmooth._unrolled.sum_last``):
jaxlib 0.10's CPU backend hands a reduction over a length-3 axis of a large batch to YNNPACK,
several times slower than the unrolled sum inside the batched step Jacobian of Solo-12.

Every function is branch-free (``jnp.where`` instead of Python ``if`` on values), so it jits
once, vmaps, and is differentiable everywhere, including at zero rotation, where the usual
closed forms divide by zero: there the Taylor expansion is selected, with the "double
``where``" trick so that the discarded branch cannot inject NaNs into gradients.

References:
    R. Featherstone, "Rigid Body Dynamics Algorithms", Springer, 2008 (chapter 2).
    J. Sola, J. Deray, D. Atchuthan, "A micro Lie theory for state estimation in robotics",
    arXiv:1812.01537, 2018 (SO(3)/SE(3) exp, log and Jacobians).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax.typing import ArrayLike

from rsmooth._unrolled import sum_last  # noqa: F401  (re-exported for the simulator)

# Below this angle (rad) the closed forms are replaced by their Taylor series. The series
# below are truncated after the theta^4 term, whose successor is < 1e-17 at this angle; the
# closed forms lose at most ~1e-12 relative precision to cancellation just above it.
_SMALL_ANGLE = 1e-2


def _norm_and_safe(squared_norm: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Returns (is_small, theta_safe, theta_squared) for the double-``where`` trick."""
    is_small = squared_norm < _SMALL_ANGLE**2
    theta_safe = jnp.sqrt(jnp.where(is_small, 1.0, squared_norm))
    return is_small, theta_safe, squared_norm


# --------------------------------------------------------------------------------------
# 3D rotations
# --------------------------------------------------------------------------------------


def rotate(rotation: jax.Array, vector: jax.Array) -> jax.Array:
    """``rotation @ vector`` for a 3x3 matrix and a 3-vector, as fusible elementwise products.

    Args:
        rotation: shape ``(3, 3)``.
        vector: shape ``(3,)``.

    Returns:
        Shape ``(3,)``.
    """
    return (
        rotation[..., :, 0] * vector[..., 0, None]
        + rotation[..., :, 1] * vector[..., 1, None]
        + rotation[..., :, 2] * vector[..., 2, None]
    )


def rotate_inverse(rotation: jax.Array, vector: jax.Array) -> jax.Array:
    """``rotation.T @ vector`` for a 3x3 matrix and a 3-vector.

    Args:
        rotation: shape ``(3, 3)``.
        vector: shape ``(3,)``.

    Returns:
        Shape ``(3,)``.
    """
    return rotation[0] * vector[0] + rotation[1] * vector[1] + rotation[2] * vector[2]


def dot3(left: jax.Array, right: jax.Array) -> jax.Array:
    """Dot product of 3-vectors over the last axis, unrolled (see the module docstring)."""
    return left[..., 0] * right[..., 0] + left[..., 1] * right[..., 1] + left[..., 2] * right[..., 2]


def matmul3(left: jax.Array, right: jax.Array) -> jax.Array:
    """``left @ right`` for 3x3 matrices, as fusible elementwise products.

    Args:
        left: shape ``(3, 3)``.
        right: shape ``(3, 3)``.

    Returns:
        Shape ``(3, 3)``.
    """
    return left[:, 0:1] * right[0:1, :] + left[:, 1:2] * right[1:2, :] + left[:, 2:3] * right[2:3, :]


def outer3(left: jax.Array, right: jax.Array) -> jax.Array:
    """Outer product ``left right^T`` of 3-vectors, shape ``(3, 3)``."""
    return left[:, None] * right[None, :]


def skew_square(vector: jax.Array) -> jax.Array:
    """``[v]x @ [v]x = v v^T - |v|^2 I`` without a matrix product."""
    return outer3(vector, vector) - dot3(vector, vector) * jnp.eye(3, dtype=vector.dtype)


def skew(vector: ArrayLike) -> jax.Array:
    """Skew-symmetric matrix ``[v]x`` such that ``[v]x @ u == cross(v, u)``.

    Args:
        vector: array of shape ``(..., 3)``.

    Returns:
        Array of shape ``(..., 3, 3)``.
    """
    vector = jnp.asarray(vector)
    x, y, z = vector[..., 0], vector[..., 1], vector[..., 2]
    zero = jnp.zeros_like(x)
    return jnp.stack(
        [
            jnp.stack([zero, -z, y], axis=-1),
            jnp.stack([z, zero, -x], axis=-1),
            jnp.stack([-y, x, zero], axis=-1),
        ],
        axis=-2,
    )


def rotation_about_axis(axis: ArrayLike, angle: ArrayLike) -> jax.Array:
    """Rotation by ``angle`` about the unit vector ``axis`` (Rodrigues' formula).

    Written as ``cos(t) I + sin(t) [a]x + (1 - cos(t)) a a^T``, which for a coordinate axis
    reproduces the elementary rotation matrices exactly (as Pinocchio's ``JointModelRX``).

    Args:
        axis: unit vector, shape ``(3,)``.
        angle: scalar angle in radians.

    Returns:
        Rotation matrix of shape ``(3, 3)``.
    """
    axis = jnp.asarray(axis)
    cos, sin = jnp.cos(angle), jnp.sin(angle)
    return (
        cos * jnp.eye(3, dtype=axis.dtype)
        + sin * skew(axis)
        + (1.0 - cos) * outer3(axis, axis)
    )


def exp3(rotation_vector: ArrayLike) -> jax.Array:
    """Exponential map of SO(3): rotation matrix of a rotation vector ``theta * axis``.

    Args:
        rotation_vector: array of shape ``(3,)``.

    Returns:
        Rotation matrix of shape ``(3, 3)``.
    """
    w = jnp.asarray(rotation_vector)
    is_small, theta, theta2 = _norm_and_safe(dot3(w, w))
    # sin(t)/t and (1 - cos t)/t^2 = 2 sin^2(t/2)/t^2 (half-angle form: no cancellation).
    sin_over_theta = jnp.where(is_small, 1.0 - theta2 / 6.0 + theta2**2 / 120.0, jnp.sin(theta) / theta)
    half_sin = jnp.sin(0.5 * theta)
    one_minus_cos_over_theta2 = jnp.where(
        is_small,
        0.5 - theta2 / 24.0 + theta2**2 / 720.0,
        2.0 * half_sin * half_sin / (theta * theta),
    )
    return jnp.eye(3, dtype=w.dtype) + sin_over_theta * skew(w) + one_minus_cos_over_theta2 * skew_square(w)


def left_jacobian_so3(rotation_vector: ArrayLike) -> jax.Array:
    """Left Jacobian of SO(3), the matrix ``V`` in ``exp6([v, w]) = (exp3(w), V(w) v)``.

    ``V(w) = I + (1 - cos t)/t^2 [w]x + (t - sin t)/t^3 [w]x^2`` with ``t = |w|``
    (Sola et al. 2018, eq. 145).

    Args:
        rotation_vector: array of shape ``(3,)``.

    Returns:
        Array of shape ``(3, 3)``.
    """
    w = jnp.asarray(rotation_vector)
    is_small, theta, theta2 = _norm_and_safe(dot3(w, w))
    half_sin = jnp.sin(0.5 * theta)
    a = jnp.where(is_small, 0.5 - theta2 / 24.0 + theta2**2 / 720.0, 2.0 * half_sin * half_sin / (theta * theta))
    b = jnp.where(
        is_small,
        1.0 / 6.0 - theta2 / 120.0 + theta2**2 / 5040.0,
        (theta - jnp.sin(theta)) / (theta * theta * theta),
    )
    return jnp.eye(3, dtype=w.dtype) + a * skew(w) + b * skew_square(w)


def left_jacobian_so3_inverse_apply(rotation_vector: ArrayLike, vector: ArrayLike) -> jax.Array:
    """Applies the inverse of :func:`left_jacobian_so3` to a vector, as Pinocchio's ``log6``.

    ``V(w)^-1 p = alpha p - 1/2 w x p + beta (w . p) w`` with
    ``alpha = t sin t / (2 (1 - cos t))`` and ``beta = 1/t^2 - sin t / (2 t (1 - cos t))``.
    Valid for ``|w| < 2 pi`` (the logarithm returns ``|w| <= pi``).

    Args:
        rotation_vector: ``w``, shape ``(3,)``.
        vector: ``p``, shape ``(3,)``.

    Returns:
        ``V(w)^-1 p``, shape ``(3,)``.
    """
    w = jnp.asarray(rotation_vector)
    p = jnp.asarray(vector)
    is_small, theta, theta2 = _norm_and_safe(dot3(w, w))
    sin = jnp.sin(theta)
    half_sin = jnp.sin(0.5 * theta)
    one_minus_cos = 2.0 * half_sin * half_sin
    alpha = jnp.where(is_small, 1.0 - theta2 / 12.0 - theta2**2 / 720.0, theta * sin / (2.0 * one_minus_cos))
    beta = jnp.where(
        is_small,
        1.0 / 12.0 + theta2 / 720.0,
        1.0 / (theta * theta) - sin / (2.0 * theta * one_minus_cos),
    )
    return alpha * p - 0.5 * jnp.cross(w, p) + (beta * dot3(w, p)) * w


# --------------------------------------------------------------------------------------
# Quaternions, stored [x, y, z, w]
# --------------------------------------------------------------------------------------


def quaternion_to_rotation(quaternion: ArrayLike) -> jax.Array:
    """Rotation matrix of a unit quaternion ``[x, y, z, w]``.

    Uses the same expression as Eigen's ``Quaternion::toRotationMatrix`` (no normalization),
    so configurations give the very same placements as in Pinocchio.

    Args:
        quaternion: array of shape ``(4,)``, assumed unit norm.

    Returns:
        Rotation matrix of shape ``(3, 3)``.
    """
    quaternion = jnp.asarray(quaternion)
    x, y, z, w = quaternion[0], quaternion[1], quaternion[2], quaternion[3]
    tx, ty, tz = 2.0 * x, 2.0 * y, 2.0 * z
    twx, twy, twz = tx * w, ty * w, tz * w
    txx, txy, txz = tx * x, ty * x, tz * x
    tyy, tyz, tzz = ty * y, tz * y, tz * z
    return jnp.stack(
        [
            jnp.stack([1.0 - (tyy + tzz), txy - twz, txz + twy]),
            jnp.stack([txy + twz, 1.0 - (txx + tzz), tyz - twx]),
            jnp.stack([txz - twy, tyz + twx, 1.0 - (txx + tyy)]),
        ]
    )


def rotation_to_quaternion(rotation: ArrayLike) -> jax.Array:
    """Unit quaternion ``[x, y, z, w]`` with ``w >= 0`` of a rotation matrix.

    Shepperd's method: the four candidate formulas are all evaluated and the numerically best
    one (largest pivot) is selected, which keeps the function branch-free.

    Args:
        rotation: rotation matrix of shape ``(3, 3)``.

    Returns:
        Array of shape ``(4,)``.
    """
    r = jnp.asarray(rotation)
    trace = r[0, 0] + r[1, 1] + r[2, 2]
    pivots = jnp.stack([trace, r[0, 0], r[1, 1], r[2, 2]])
    best = jnp.argmax(pivots)
    # Candidate (unnormalized) quaternions, each scaled by 4 * its pivot component.
    candidates = jnp.stack(
        [
            jnp.stack([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1], 1.0 + trace]),
            jnp.stack([1.0 + r[0, 0] - r[1, 1] - r[2, 2], r[0, 1] + r[1, 0], r[0, 2] + r[2, 0], r[2, 1] - r[1, 2]]),
            jnp.stack([r[0, 1] + r[1, 0], 1.0 - r[0, 0] + r[1, 1] - r[2, 2], r[1, 2] + r[2, 1], r[0, 2] - r[2, 0]]),
            jnp.stack([r[0, 2] + r[2, 0], r[1, 2] + r[2, 1], 1.0 - r[0, 0] - r[1, 1] + r[2, 2], r[1, 0] - r[0, 1]]),
        ]
    )
    quaternion = candidates[best]
    quaternion = quaternion / jnp.linalg.norm(quaternion)
    return jnp.where(quaternion[3] < 0.0, -quaternion, quaternion)


def quaternion_multiply(left: ArrayLike, right: ArrayLike) -> jax.Array:
    """Hamilton product ``left * right`` of quaternions stored ``[x, y, z, w]``.

    Args:
        left: array of shape ``(4,)``.
        right: array of shape ``(4,)``.

    Returns:
        Array of shape ``(4,)``; its rotation is ``R(left) @ R(right)``.
    """
    left, right = jnp.asarray(left), jnp.asarray(right)
    lv, lw = left[:3], left[3]
    rv, rw = right[:3], right[3]
    vector = lw * rv + rw * lv + jnp.cross(lv, rv)
    scalar = lw * rw - dot3(lv, rv)
    return jnp.concatenate([vector, scalar[None]])


def quaternion_conjugate(quaternion: ArrayLike) -> jax.Array:
    """Conjugate ``[-x, -y, -z, w]`` (the inverse of a unit quaternion)."""
    quaternion = jnp.asarray(quaternion)
    return jnp.concatenate([-quaternion[:3], quaternion[3:]])


def quaternion_exp(rotation_vector: ArrayLike) -> jax.Array:
    """Unit quaternion of the rotation vector ``w``: ``[sin(t/2) w/t, cos(t/2)]``, ``t = |w|``.

    Args:
        rotation_vector: array of shape ``(3,)``.

    Returns:
        Array of shape ``(4,)``.
    """
    w = jnp.asarray(rotation_vector)
    is_small, theta, theta2 = _norm_and_safe(dot3(w, w))
    half_sin_over_theta = jnp.where(
        is_small,
        0.5 - theta2 / 48.0 + theta2**2 / 3840.0,
        jnp.sin(0.5 * theta) / theta,
    )
    half_cos = jnp.where(is_small, 1.0 - theta2 / 8.0 + theta2**2 / 384.0, jnp.cos(0.5 * theta))
    return jnp.concatenate([half_sin_over_theta * w, half_cos[None]])


def quaternion_log(quaternion: ArrayLike) -> jax.Array:
    """Rotation vector ``w`` with ``|w| <= pi`` of a unit quaternion (either sign).

    Args:
        quaternion: array of shape ``(4,)``, assumed unit norm.

    Returns:
        Array of shape ``(3,)``.
    """
    quaternion = jnp.asarray(quaternion)
    # q and -q are the same rotation; the representative with w >= 0 gives angle <= pi.
    quaternion = jnp.where(quaternion[3] < 0.0, -quaternion, quaternion)
    vector, scalar = quaternion[:3], quaternion[3]
    sin_half_squared = dot3(vector, vector)
    is_small = sin_half_squared < (0.5 * _SMALL_ANGLE) ** 2
    sin_half = jnp.sqrt(jnp.where(is_small, 1.0, sin_half_squared))
    # angle / sin(angle / 2) = 2 atan2(s, c) / s, expanded for small s as 2/c - 2 s^2/(3 c^3).
    factor = jnp.where(
        is_small,
        2.0 / scalar - 2.0 * sin_half_squared / (3.0 * scalar**3),
        2.0 * jnp.arctan2(sin_half, scalar) / sin_half,
    )
    return factor * vector


def log3(rotation: ArrayLike) -> jax.Array:
    """Logarithm of SO(3): rotation vector ``w`` with ``|w| <= pi`` and ``exp3(w) == R``.

    Args:
        rotation: rotation matrix of shape ``(3, 3)``.

    Returns:
        Array of shape ``(3,)``.
    """
    return quaternion_log(rotation_to_quaternion(rotation))


# --------------------------------------------------------------------------------------
# SE(3)
# --------------------------------------------------------------------------------------


def exp6(motion: ArrayLike) -> tuple[jax.Array, jax.Array]:
    """Exponential map of SE(3): placement reached by following the twist ``[v, w]`` for 1 s.

    Args:
        motion: twist ``[linear, angular]`` of shape ``(6,)``, in the moving frame.

    Returns:
        ``(rotation, translation)`` of shapes ``(3, 3)`` and ``(3,)``.
    """
    motion = jnp.asarray(motion)
    linear, angular = motion[:3], motion[3:]
    return exp3(angular), rotate(left_jacobian_so3(angular), linear)


def log6(rotation: ArrayLike, translation: ArrayLike) -> jax.Array:
    """Logarithm of SE(3), the inverse of :func:`exp6` (angular part with norm ``<= pi``).

    Args:
        rotation: rotation matrix of shape ``(3, 3)``.
        translation: array of shape ``(3,)``.

    Returns:
        Twist ``[linear, angular]`` of shape ``(6,)``.
    """
    angular = log3(rotation)
    linear = left_jacobian_so3_inverse_apply(angular, translation)
    return jnp.concatenate([linear, angular])


def compose(
    rotation_ab: jax.Array, translation_ab: jax.Array, rotation_bc: jax.Array, translation_bc: jax.Array
) -> tuple[jax.Array, jax.Array]:
    """Placement ``aMc = aMb * bMc``.

    Args:
        rotation_ab: rotation of ``aMb``, shape ``(3, 3)``.
        translation_ab: translation of ``aMb``, shape ``(3,)``.
        rotation_bc: rotation of ``bMc``, shape ``(3, 3)``.
        translation_bc: translation of ``bMc``, shape ``(3,)``.

    Returns:
        ``(rotation, translation)`` of ``aMc``.
    """
    return matmul3(rotation_ab, rotation_bc), rotate(rotation_ab, translation_bc) + translation_ab


# --------------------------------------------------------------------------------------
# Spatial (6D) vectors
# --------------------------------------------------------------------------------------


def transform_motion(rotation: jax.Array, translation: jax.Array, motion: jax.Array) -> jax.Array:
    """Expresses in frame A a twist given in frame B, with ``aMb = (rotation, translation)``.

    The motion transform of Featherstone (2008, Sec. 2.8) in Pinocchio's ``[linear,
    angular]`` order: ``w_A = R w_B``, ``v_A = R v_B + p x w_A``.

    Args:
        rotation: shape ``(3, 3)``.
        translation: shape ``(3,)``.
        motion: twist, shape ``(6,)``.

    Returns:
        Twist, shape ``(6,)``.
    """
    angular = rotate(rotation, motion[3:])
    linear = rotate(rotation, motion[:3]) + jnp.cross(translation, angular)
    return jnp.concatenate([linear, angular])


def motion_cross_motion(motion: jax.Array, other: jax.Array) -> jax.Array:
    """Spatial cross product ``m x m'`` of two twists (Featherstone 2008, Sec. 2.9).

    Args:
        motion: twist, shape ``(6,)``.
        other: twist, shape ``(6,)``.

    Returns:
        Twist ``[w x v' + v x w', w x w']``, shape ``(6,)``.
    """
    linear, angular = motion[..., :3], motion[..., 3:]
    other_linear, other_angular = other[..., :3], other[..., 3:]
    return jnp.concatenate(
        [
            jnp.cross(angular, other_linear) + jnp.cross(linear, other_angular),
            jnp.cross(angular, other_angular),
        ],
        axis=-1,
    )


def motion_cross_force(motion: jax.Array, force: jax.Array) -> jax.Array:
    """Dual spatial cross product ``m x* f`` (Featherstone 2008, Sec. 2.9).

    Args:
        motion: twist, shape ``(6,)``.
        force: wrench, shape ``(6,)``.

    Returns:
        Wrench ``[w x f, w x n + v x f]``, shape ``(6,)``.
    """
    linear, angular = motion[..., :3], motion[..., 3:]
    force_linear, torque = force[..., :3], force[..., 3:]
    return jnp.concatenate(
        [
            jnp.cross(angular, force_linear),
            jnp.cross(angular, torque) + jnp.cross(linear, force_linear),
        ],
        axis=-1,
    )


# --------------------------------------------------------------------------------------
# Spatial inertia
# --------------------------------------------------------------------------------------


class SpatialInertia(NamedTuple):
    """Rigid-body spatial inertia about the origin of the frame it is expressed in.

    Stored in the "first moment" form, which is closed under addition and frame changes and
    needs no division by the mass (so massless links are fine):

    .. math::
        I = \\begin{bmatrix} m 1 & -[h]_\\times \\\\ [h]_\\times & I_O \\end{bmatrix},
        \\quad h = m c, \\quad I_O = I_C - m [c]_\\times^2

    Attributes:
        mass: ``m``, shape ``()``.
        first_moment: ``h = m c`` with ``c`` the centre of mass, shape ``(3,)``.
        rotational_inertia: ``I_O``, rotational inertia about the frame origin, ``(3, 3)``.
    """

    mass: jax.Array
    first_moment: jax.Array
    rotational_inertia: jax.Array


def spatial_inertia(mass: ArrayLike, com: ArrayLike, inertia_about_com: ArrayLike) -> SpatialInertia:
    """Builds a :class:`SpatialInertia` from mass, centre of mass and inertia about the COM.

    Args:
        mass: scalar mass.
        com: centre of mass, shape ``(3,)``.
        inertia_about_com: rotational inertia about the COM in the frame's axes, ``(3, 3)``.

    Returns:
        The spatial inertia about the frame origin (parallel-axis theorem).
    """
    mass, com, inertia_about_com = jnp.asarray(mass), jnp.asarray(com), jnp.asarray(inertia_about_com)
    return SpatialInertia(mass, mass * com, inertia_about_com - mass * skew_square(com))


def inertia_apply(inertia: SpatialInertia, motion: jax.Array) -> jax.Array:
    """Momentum ``I m`` of a body with inertia ``I`` moving with twist ``m``.

    Args:
        inertia: spatial inertia.
        motion: twist, shape ``(6,)``.

    Returns:
        Wrench ``[m v - h x w, I_O w + h x v]``, shape ``(6,)``.
    """
    linear, angular = motion[..., :3], motion[..., 3:]
    h = inertia.first_moment
    return jnp.concatenate(
        [
            jnp.asarray(inertia.mass)[..., None] * linear - jnp.cross(h, angular),
            rotate(inertia.rotational_inertia, angular) + jnp.cross(h, linear),
        ],
        axis=-1,
    )


def transform_inertia(rotation: jax.Array, translation: jax.Array, inertia: SpatialInertia) -> SpatialInertia:
    """Expresses in frame A an inertia given in frame B, with ``aMb = (rotation, translation)``.

    With ``h_r = R h``: ``h_A = h_r + m p`` and
    ``I_A = R I_O R^T - ([h_r]x [p]x + [p]x [h_r]x + m [p]x^2)`` (parallel-axis theorem in
    first-moment form; 3x3 work only, instead of the 6x6 product ``X^* I X^-1``), where
    ``[a]x [b]x + [b]x [a]x = a b^T + b a^T - 2 (a . b) I``.

    Args:
        rotation: shape ``(3, 3)``.
        translation: shape ``(3,)``.
        inertia: spatial inertia in frame B.

    Returns:
        The same inertia in frame A.
    """
    h_rotated = rotate(rotation, inertia.first_moment)
    p = translation
    symmetric_hp = outer3(h_rotated, p) + outer3(p, h_rotated) - 2.0 * dot3(h_rotated, p) * jnp.eye(3, dtype=p.dtype)
    rotational = (
        matmul3(matmul3(rotation, inertia.rotational_inertia), rotation.T)
        - symmetric_hp
        - inertia.mass * skew_square(p)
    )
    return SpatialInertia(inertia.mass, h_rotated + inertia.mass * translation, rotational)
