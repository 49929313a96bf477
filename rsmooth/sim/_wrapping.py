"""The path of a spatial tendon segment around a sphere or a cylinder (MuJoCo's wrapping).

Between two points ``a`` and ``b`` with a wrapping geom between them, the path is the shortest
one that stays out of the geom, as MuJoCo defines it (MuJoCo's XML reference, ``tendon/spatial/
geom`` and its ``sidesite``; the computation chapter, "Tendons"): the straight segment where it
misses the geom, else a straight segment from ``a`` to a tangent point, an arc on the geom and
a straight segment from a second tangent point to ``b``. Around a sphere the arc is a great
circle in the plane through the centre, ``a`` and ``b``; around a cylinder the construction is
planar, in the plane normal to the axis, and the height varies linearly with the planar path
length (a helix). A side point, where given, keeps the path off the side of the geom opposite
it: seen from the centre, the path turns from ``a`` to ``b`` the short way unless that way
passes the direction opposite the side point, in which case it goes the long way round, even
where the straight segment misses the geom (MuJoCo 4.0.1's rule, checked against its
``ten_length`` in the tests). Only the side point's direction counts; MuJoCo's other wrapping,
for a side point inside the geom, is not modelled here (loading refuses it at ``qpos0``, and a
step that starts so reports it: ``StepInfo.inside_side_sites``).

Branch-free: the wrapped path is computed everywhere (from stand-in points where it does not
apply) and selected with ``where``; derivatives stay finite where a point lies on the surface or
the straight segment grazes it.
"""

from __future__ import annotations

import jax.numpy as jnp
from jax import Array

from rsmooth.sim._contact import _safe_norm


def _safe_sqrt(x: Array) -> Array:
    """``sqrt(max(x, 0))`` whose derivative is 0 at and below 0 (not infinite or NaN)."""
    positive = x > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, x, 1.0)), 0.0)


def _cross2(u: Array, v: Array) -> Array:
    return u[0] * v[1] - u[1] * v[0]


def _perp(u: Array) -> Array:
    """``u`` turned by +90 degrees."""
    return jnp.stack([-u[1], u[0]])


def wrap_circle(a: Array, b: Array, side: Array | None, radius: Array) -> tuple[Array, Array, Array, Array]:
    """The planar path from ``a`` to ``b`` ``(2,)`` around the circle of ``radius`` at the
    origin: ``(wraps, t_a, t_b, angle)``, whether it wraps, the tangent points (both the
    midpoint of ``a`` and ``b`` where it does not wrap) and the arc's angle (0 where it does not
    wrap).

    Seen from the centre, the path turns from ``a`` to ``b`` one way or the other: the short
    way (by less than pi, as the segment ``ab`` does) unless that way passes the direction
    opposite ``side``, in which case it goes the long way (round ``side``). It wraps where
    neither point is inside the circle and the segment ``ab`` meets the circle or goes the
    long way.
    """
    dtype = a.dtype
    squared = radius * radius
    difference = b - a
    span = difference @ difference
    along = jnp.clip(-(difference @ a) / jnp.where(span > 0, span, 1.0), 0.0, 1.0)
    nearest = a + along * difference
    cross = _cross2(a, b)
    short = jnp.where(cross >= 0, 1.0, -1.0).astype(dtype)  # +1: a to b turns counterclockwise
    if side is None:
        long = jnp.zeros((), bool)
    else:
        # the short way's turn passes the direction opposite the side
        long = (short * _cross2(a, -side) >= 0) & (short * _cross2(-side, b) >= 0)
    wraps = (nearest @ nearest <= squared) | long
    wraps = wraps & (a @ a >= squared) & (b @ b >= squared) & (span > 0) & (radius > 0)
    # stand-ins where it does not wrap, so that nothing below divides by 0
    a_ = jnp.where(wraps, a, jnp.stack([2 * radius, jnp.zeros((), dtype)]))
    b_ = jnp.where(wraps, b, jnp.stack([jnp.zeros((), dtype), 2 * radius]))
    sense = jnp.where(long, -short, short)
    da, db = a_ @ a_, b_ @ b_
    reach_a, reach_b = _safe_sqrt(da - squared), _safe_sqrt(db - squared)  # tangent lengths
    t_a = radius / da * (radius * a_ + sense * reach_a * _perp(a_))
    t_b = radius / db * (radius * b_ - sense * reach_b * _perp(b_))
    # the arc's angle: the turn from a to b less each tangent point's angle off its point
    between = jnp.arctan2(jnp.abs(_cross2(a_, b_)), a_ @ b_)
    off = jnp.arctan2(reach_a, radius) + jnp.arctan2(reach_b, radius)
    angle = jnp.where(long, 2 * jnp.pi - between - off, jnp.maximum(between - off, 0.0))
    halfway = 0.5 * (a + b)
    return (
        wraps,
        jnp.where(wraps, t_a, halfway),
        jnp.where(wraps, t_b, halfway),
        jnp.where(wraps, angle, 0.0),
    )


def wrap_sphere(a: Array, b: Array, side: Array | None, centre: Array, radius: Array) -> tuple[Array, Array, Array]:
    """The path from ``a`` to ``b`` ``(3,)`` around the sphere ``(centre, radius)``: the tangent
    points ``(3,)`` (the midpoint of ``a`` and ``b`` twice where it does not wrap) and the arc's
    length. The arc is a great circle in the plane through the centre, ``a`` and ``b`` (where
    they are aligned with the centre, where all planes through them give the same length, the
    plane that holds ``side``, else one that holds the x or y axis); ``side`` is projected on
    that plane."""
    dtype = a.dtype
    p, q = a - centre, b - centre
    normal = jnp.cross(p, q)
    fallback = jnp.cross(p, side - centre) if side is not None else jnp.zeros(3, dtype)
    axis = jnp.where(jnp.abs(p[0]) < jnp.abs(p[1]), jnp.array([1.0, 0.0, 0.0], dtype), jnp.array([0.0, 1.0, 0.0], dtype))
    fallback = jnp.where(_safe_norm(fallback) > 1e-12 * (p @ p), fallback, jnp.cross(p, axis))
    normal = jnp.where(_safe_norm(normal) > 1e-12 * (p @ p + q @ q), normal, fallback)
    length_p, length_n = _safe_norm(p), _safe_norm(normal)
    first = p / jnp.where(length_p > 0, length_p, 1.0)
    second = jnp.cross(normal / jnp.where(length_n > 0, length_n, 1.0), first)
    plane = jnp.stack([first, second])  # (2, 3)
    wraps, t_a, t_b, angle = wrap_circle(plane @ p, plane @ q, None if side is None else plane @ (side - centre), radius)
    halfway = 0.5 * (a + b)  # (in 3D: with a at the centre, the plane is not defined)
    return jnp.where(wraps, centre + t_a @ plane, halfway), jnp.where(wraps, centre + t_b @ plane, halfway), radius * angle


def wrap_cylinder(
    a: Array, b: Array, side: Array | None, rotation: Array, centre: Array, radius: Array
) -> tuple[Array, Array, Array]:
    """The path from ``a`` to ``b`` ``(3,)`` around the infinite cylinder of ``radius`` whose
    axis is the third column of ``rotation`` through ``centre``: the tangent points ``(3,)`` (the
    midpoint of ``a`` and ``b`` twice where it does not wrap) and the helix's length. The
    planar construction is in the plane normal to the axis; the height goes linearly with the
    planar path length."""
    p, q = (a - centre) @ rotation, (b - centre) @ rotation
    s = None if side is None else ((side - centre) @ rotation)[:2]
    wraps, t_a, t_b, angle = wrap_circle(p[:2], q[:2], s, radius)
    first, last = _safe_norm(p[:2] - t_a), _safe_norm(q[:2] - t_b)
    arc = radius * angle
    planar = first + arc + last
    rise = q[2] - p[2]
    height_a = p[2] + rise * first / jnp.where(planar > 0, planar, 1.0)
    height_b = p[2] + rise * (first + arc) / jnp.where(planar > 0, planar, 1.0)
    halfway = 0.5 * (a + b)
    point_a = jnp.where(wraps, centre + rotation @ jnp.concatenate([t_a, height_a[None]]), halfway)
    point_b = jnp.where(wraps, centre + rotation @ jnp.concatenate([t_b, height_b[None]]), halfway)
    return point_a, point_b, _safe_norm(jnp.stack([arc, height_b - height_a]))
