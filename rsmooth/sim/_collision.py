"""Narrow- and broad-phase collision detection between the shapes of :mod:`._geometry`.

:func:`collide` returns a fixed-size contact manifold (:class:`Contacts`) for a pair of posed
shapes, dispatching on the shapes' types at trace time; :func:`candidate_pairs` prunes the
pairs of many bodies by bounding spheres. Everything is branch-free JAX: it jits once,
vmaps over poses, and has finite derivatives in the poses (equal to finite differences away
from the configurations where the closest features switch).

Algorithms, by pair:

- Half-space against a shape: the shape's lowest points (the ends of a capsule, the corners
  of a box, rim points of a cylinder, the vertices of a mesh), reduced to at most 4 that
  span the largest area, so that a resting face gives a stable manifold; an ellipsoid's
  lowest point, exact (its support function).
- Spheres and capsules among themselves, and sphere-box: closest points of points and
  segments (Ericson, *Real-Time Collision Detection*, 2005, sections 5.1.2, 5.1.9).
- Polytope cores (a sphere is a point dilated, a capsule a segment dilated, boxes and convex
  meshes are polytopes, a cylinder its inscribed prism of ``_CYLINDER_SIDES`` sides, an
  ellipsoid its inscribed icosphere, :data:`_ELLIPSOID_SUBDIVISIONS`, a height field's cell,
  against a sphere or a capsule, a pair of triangular prisms): the separating axis test over
  face normals and edge cross products (Gottschalk, Lin, Manocha, "OBBTree", SIGGRAPH 1996)
  gives the penetration depth of the cores; when the cores are apart, GJK (Gilbert, Johnson,
  Keerthi, IEEE J. Robotics and Automation 4(2), 1988, with the closest point of each simplex
  found by enumerating its faces) gives their distance. A face axis gives a manifold by clipping the most
  anti-parallel face (or the capsule's segment) of the other shape against the reference
  face's side planes, reduced to 4 points (2 for a capsule); an edge axis gives one contact
  at the edges' closest points.
- A height field against a box, a cylinder, a convex mesh or an ellipsoid: point against plane,
  normals from the terrain (:func:`_heightfield_polytope`): the shape's vertices and curved
  supports against the triangle under them, the terrain's peaks and ridges against the shape's
  faces, and the crossings of the shape's edges with the terrain's creases; reduced to 4 as a
  half-space's contacts are. (One prism against a polytope would often give its way out
  through the prism's side, inside the terrain.)

GJK runs in a ``lax.while_loop`` without derivatives; its final simplex is then evaluated
again from the poses, which gives derivatives of the closest points that are exact for the
closest features found (no unrolling through iterations).

A pair with an ellipsoid whose cores overlap takes its deepest entry on the exact shapes' best
axis (:func:`_refined_axis`: the ellipsoid's inscribed polytope only approximates it), found
without derivatives: the distance's derivative in the poses is exact (the axis is optimal, so
its turning does not change the distance to first order), and the witness points' derivatives
hold the axis fixed (they leave out how the contact point slides over the curved surface).

MJX (``mujoco.mjx``) has collision functions for most of these pairs, but they are private
(``mjx._src``, no stable API), they take MJX's ``Model``/``Data`` and geom-type tables rather
than standalone shapes and poses, and some of them are written for speed of the forward value
(``jnp.argmax`` over sampled features, fixed polygon sizes per geom pair) rather than for
derivatives; depending on them would tie our contact code to MuJoCo's release cadence. We
write our own, standalone and tested against MuJoCo's own distance (``mj_geomDistance``).
"""

from __future__ import annotations

import functools
import itertools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.typing import ArrayLike
from typing import NamedTuple

from rsmooth.sim._contact import _safe_norm
from rsmooth.sim._geometry import (
    Box,
    Capsule,
    ConvexMesh,
    Cylinder,
    Ellipsoid,
    HalfSpace,
    HeightField,
    Sphere,
    _safe_normalize,
)

Array = jax.Array

__all__ = [
    "CandidatePairs",
    "Contacts",
    "candidate_pairs",
    "collide",
    "manifold_size",
]


class Contacts(eqx.Module):
    """A fixed-size contact manifold between shape 1 and shape 2.

    Entries are sorted so that entry 0 is the deepest (smallest distance); it always holds
    the pair's signed distance, active or not. Inactive entries hold finite values.

    Attributes:
        distance: signed distances, shape ``(k,)``; negative means penetration.
        normal: unit normals in world coordinates pointing from shape 1 to shape 2,
            ``(k, 3)``.
        point1: witness points on the surface of shape 1, world coordinates, ``(k, 3)``.
        point2: witness points on the surface of shape 2, ``(k, 3)``; for entry 0,
            ``point2 - point1 = distance * normal``.
        active: whether the entry is a contact of the manifold (``distance <= margin``
            and not a repeat of another entry), bool ``(k,)``.
    """

    distance: Array
    normal: Array
    point1: Array
    point2: Array
    active: Array


def _swapped(contacts: Contacts) -> Contacts:
    return Contacts(contacts.distance, -contacts.normal, contacts.point2, contacts.point1, contacts.active)


def _transform(pose, points: Array) -> Array:
    rotation, translation = pose
    return points @ rotation.T + translation[None, :]


def _eps(dtype) -> float:
    return float(jnp.finfo(dtype).eps)


# --------------------------------------------------------------------------------------
# Manifold reduction.
# --------------------------------------------------------------------------------------


def _reduce(point1, point2, distance, normal, candidate, margin, count: int) -> Contacts:
    """At most ``count`` (1, 2 or 4) of ``C`` candidate contacts: the deepest, then the one
    farthest from it, then the two that make the largest triangles on either side of that
    segment (the largest-area heuristic of game physics engines)."""
    dtype = distance.dtype
    huge = jnp.asarray(jnp.finfo(dtype).max, dtype)
    first = jnp.argmin(jnp.where(candidate, distance, huge))
    valid = candidate & (distance <= margin)
    points = point2
    p0 = points[first]
    scale = jnp.max(jnp.abs(p0)) + jnp.max(jnp.where(valid[:, None], jnp.abs(points - p0[None, :]), 0.0))
    tolerance = 1e3 * _eps(dtype) * (1.0 + scale)
    chosen = [first]
    keep = [valid[first]]
    if count >= 2:
        spread = jnp.sum((points - p0[None, :]) ** 2, axis=-1)
        second = jnp.argmax(jnp.where(valid, spread, -1.0))
        chosen.append(second)
        keep.append(valid[second] & (spread[second] > tolerance**2))
    if count >= 4:
        edge = points[second] - p0
        normals = jnp.broadcast_to(normal, points.shape)
        area = jnp.sum(jnp.cross(edge[None, :], points - p0[None, :]) * normals, axis=-1)
        area_tolerance = tolerance * (_safe_norm(edge) + tolerance)
        third = jnp.argmax(jnp.where(valid, area, -huge))
        fourth = jnp.argmin(jnp.where(valid, area, huge))
        chosen += [third, fourth]
        keep += [valid[third] & (area[third] > area_tolerance), valid[fourth] & (area[fourth] < -area_tolerance)]
    index = jnp.stack(chosen)
    normals = jnp.broadcast_to(normal, points.shape)[index]
    return Contacts(distance[index], normals, point1[index], point2[index], jnp.stack(keep))


def _single(distance, normal, point1, point2, margin) -> Contacts:
    return Contacts(distance[None], normal[None], point1[None], point2[None], (distance <= margin)[None])


# --------------------------------------------------------------------------------------
# Half-space against shapes.
# --------------------------------------------------------------------------------------


def _halfspace_points(plane_pose, core_points: Array, radius, margin, count: int) -> Contacts:
    """Contacts of points dilated by ``radius`` with the half-space; the plane's witness is
    the projection of the shape's lowest point."""
    rotation, translation = plane_pose
    normal = rotation[:, 2]
    height = (core_points - translation[None, :]) @ normal
    point2 = core_points - radius * normal[None, :]
    point1 = core_points - height[:, None] * normal[None, :]
    distance = height - radius
    if count == 1:
        return _single(distance[0], normal, point1[0], point2[0], margin)
    return _reduce(point1, point2, distance, normal, jnp.ones(distance.shape, bool), margin, count)


def _halfspace_sphere(plane: HalfSpace, plane_pose, sphere: Sphere, pose, margin) -> Contacts:
    return _halfspace_points(plane_pose, pose[1][None, :], sphere.radius, margin, 1)


def _capsule_ends(capsule: Capsule, pose) -> Array:
    rotation, translation = pose
    axis = capsule.half_length * rotation[:, 2]
    return jnp.stack([translation - axis, translation + axis])


def _halfspace_capsule(plane, plane_pose, capsule: Capsule, pose, margin) -> Contacts:
    return _halfspace_points(plane_pose, _capsule_ends(capsule, pose), capsule.radius, margin, 2)


def _halfspace_box(plane, plane_pose, box: Box, pose, margin) -> Contacts:
    return _halfspace_points(plane_pose, _transform(pose, box.corners()), 0.0, margin, 4)


def _halfspace_mesh(plane, plane_pose, mesh: ConvexMesh, pose, margin) -> Contacts:
    return _halfspace_points(plane_pose, _transform(pose, mesh.vertices), 0.0, margin, 4)


def _halfspace_ellipsoid(plane, plane_pose, ellipsoid: Ellipsoid, pose, margin) -> Contacts:
    """The ellipsoid's lowest point, its support against the plane's normal: exact, one point
    (a resting ellipsoid touches a plane at one point)."""
    rotation, translation = pose
    lowest = translation + rotation @ ellipsoid.support_core(rotation.T @ -plane_pose[0][:, 2])
    return _halfspace_points(plane_pose, lowest[None, :], 0.0, margin, 1)


def _halfspace_cylinder(plane, plane_pose, cylinder: Cylinder, pose, margin) -> Contacts:
    """Rim points of both caps: the lowest one and two more at 120 degrees on each side,
    so that a cylinder standing on a cap gets a triangle and one lying down a segment."""
    rotation, translation = pose
    down = -(rotation.T @ plane_pose[0][:, 2])
    fallback = jnp.array([1.0, 0.0, 0.0], down.dtype)
    radial, _ = _safe_normalize(down.at[2].set(0.0), fallback)
    angles = np.array([0.0, 2.0 * np.pi / 3.0, -2.0 * np.pi / 3.0])
    cos, sin = jnp.asarray(np.cos(angles), down.dtype), jnp.asarray(np.sin(angles), down.dtype)
    rim_x = cylinder.radius * (cos * radial[0] - sin * radial[1])
    rim_y = cylinder.radius * (sin * radial[0] + cos * radial[1])
    caps = jnp.stack([-cylinder.half_length, cylinder.half_length])
    local = jnp.stack(
        [jnp.tile(rim_x, 2), jnp.tile(rim_y, 2), jnp.repeat(caps, 3)], axis=-1
    )
    return _halfspace_points(plane_pose, _transform(pose, local), 0.0, margin, 4)


# --------------------------------------------------------------------------------------
# Points and segments: spheres and capsules.
# --------------------------------------------------------------------------------------


def _closest_on_segment(start: Array, end: Array, point: Array) -> Array:
    direction = end - start
    length2 = jnp.sum(direction**2)
    t = jnp.sum((point - start) * direction) / jnp.where(length2 > 0, length2, 1.0)
    return start + jnp.clip(t, 0.0, 1.0) * direction


def _closest_segment_segment(p1, q1, p2, q2) -> tuple[Array, Array]:
    """Closest points of segments ``[p1, q1]`` and ``[p2, q2]`` (Ericson 2005, 5.1.9), with
    the parameter of the first segment set to 0 when they are parallel."""
    d1, d2, r = q1 - p1, q2 - p2, p1 - p2
    a, e = jnp.sum(d1 * d1), jnp.sum(d2 * d2)
    b, c, f = jnp.sum(d1 * d2), jnp.sum(d1 * r), jnp.sum(d2 * r)
    denominator = a * e - b * b
    general = denominator > 1e3 * _eps(a.dtype) * a * e
    safe_a, safe_e = jnp.where(a > 0, a, 1.0), jnp.where(e > 0, e, 1.0)
    s = jnp.where(general, jnp.clip((b * f - c * e) / jnp.where(general, denominator, 1.0), 0.0, 1.0), 0.0)
    t = (b * s + f) / safe_e
    s = jnp.where(t < 0, jnp.clip(-c / safe_a, 0.0, 1.0), jnp.where(t > 1, jnp.clip((b - c) / safe_a, 0.0, 1.0), s))
    t = jnp.clip(t, 0.0, 1.0)
    return p1 + s * d1, p2 + t * d2


def _dilated_points(core1, core2, radius1, radius2, margin) -> Contacts:
    """The contact of two balls of the given radii centred at the closest core points."""
    fallback = jnp.array([0.0, 0.0, 1.0], core1.dtype)
    normal, length = _safe_normalize(core2 - core1, fallback)
    return _single(length - radius1 - radius2, normal, core1 + radius1 * normal, core2 - radius2 * normal, margin)


def _sphere_sphere(sphere1: Sphere, pose1, sphere2: Sphere, pose2, margin) -> Contacts:
    return _dilated_points(pose1[1], pose2[1], sphere1.radius, sphere2.radius, margin)


def _sphere_capsule(sphere: Sphere, pose1, capsule: Capsule, pose2, margin) -> Contacts:
    start, end = _capsule_ends(capsule, pose2)
    closest = _closest_on_segment(start, end, pose1[1])
    return _dilated_points(pose1[1], closest, sphere.radius, capsule.radius, margin)


def _capsule_capsule(capsule1: Capsule, pose1, capsule2: Capsule, pose2, margin) -> Contacts:
    """Entry 0: the segments' closest points. Entry 1: of the four endpoint-to-segment
    closest pairs, the one farthest along segment 1 from entry 0, so that two capsules lying
    side by side touch along their overlap's two ends (one point would let them spin about
    it); it is active when within the margin and apart from entry 0."""
    start1, end1 = _capsule_ends(capsule1, pose1)
    start2, end2 = _capsule_ends(capsule2, pose2)
    closest1, closest2 = _closest_segment_segment(start1, end1, start2, end2)
    first = _dilated_points(closest1, closest2, capsule1.radius, capsule2.radius, margin)
    cores1 = jnp.stack([start1, end1, _closest_on_segment(start1, end1, start2), _closest_on_segment(start1, end1, end2)])
    cores2 = jnp.stack([_closest_on_segment(start2, end2, start1), _closest_on_segment(start2, end2, end1), start2, end2])
    candidates = jax.vmap(lambda a, b: _dilated_points(a, b, capsule1.radius, capsule2.radius, margin))(cores1, cores2)
    candidates = jax.tree.map(lambda a: a[:, 0], candidates)
    along = jnp.abs((cores1 - closest1[None, :]) @ (end1 - start1))
    within = candidates.distance <= margin
    pick = jnp.argmax(jnp.where(within, along, -1.0))
    second = jax.tree.map(lambda a: a[pick][None], candidates)
    scale = 2.0 * capsule1.half_length + 2.0 * capsule2.half_length
    apart = jnp.linalg.norm(cores1[pick] - closest1) > 1e3 * _eps(closest1.dtype) * scale
    second = eqx.tree_at(lambda c: c.active, second, second.active & apart)
    return jax.tree.map(lambda a, b: jnp.concatenate([a, b]), first, second)


def _box_sphere(box: Box, pose1, sphere: Sphere, pose2, margin) -> Contacts:
    """Outside the box: the clamped centre is the closest point. Inside: the nearest face,
    whose normal pushes the centre out (on a face, both agree and the depth is 0)."""
    rotation, translation = pose1
    centre = rotation.T @ (pose2[1] - translation)
    half = box.half_extents
    clamped = jnp.clip(centre, -half, half)
    fallback = jnp.array([0.0, 0.0, 1.0], centre.dtype)
    outward, outside_distance = _safe_normalize(centre - clamped, fallback)
    inside = jnp.all(jnp.abs(centre) <= half)
    face_depth = half - jnp.abs(centre)
    axis = jnp.argmin(face_depth)
    sign = jnp.where(centre[axis] >= 0, 1.0, -1.0)
    face_normal = sign * jnp.eye(3, dtype=centre.dtype)[axis]
    face_point = centre.at[axis].set(sign * half[axis])
    normal_local = jnp.where(inside, face_normal, outward)
    core_distance = jnp.where(inside, -face_depth[axis], outside_distance)
    surface_local = jnp.where(inside, face_point, clamped)
    normal = rotation @ normal_local
    point1 = rotation @ surface_local + translation
    point2 = pose2[1] - sphere.radius * normal
    return _single(core_distance - sphere.radius, normal, point1, point2, margin)


# --------------------------------------------------------------------------------------
# GJK on the cores of two convex shapes.
# --------------------------------------------------------------------------------------

_PAIRS = tuple(itertools.combinations(range(4), 2))
_TRIANGLES = tuple(itertools.combinations(range(4), 3))


def _closest_in_simplex(points: Array, used: Array) -> tuple[Array, Array]:
    """Barycentric weights ``(4,)`` of the point of the simplex ``points[used]`` closest to
    the origin, and that point. Every face of the simplex is tried (its affine projection
    of the origin is kept when its weights are non-negative); the closest point is the
    nearest of those, and a vertex is always a candidate."""
    dtype = points.dtype
    tiny = 1e3 * _eps(dtype)
    # Weights within rounding of 0 count as non-negative: a face whose projection lies on
    # its boundary must not be rejected, or the iteration stalls on a worse face.
    slack = tiny
    zero = jnp.zeros(4, dtype)
    weights, feasible = [], []
    for i in range(4):
        weights.append(zero.at[i].set(1.0))
        feasible.append(used[i])
    for i, j in _PAIRS:
        edge = points[j] - points[i]
        length2 = jnp.sum(edge * edge)
        ok = length2 > tiny * (jnp.sum(points[i] ** 2) + jnp.sum(points[j] ** 2))
        t = -jnp.sum(points[i] * edge) / jnp.where(ok, length2, 1.0)
        weights.append(zero.at[i].set(1.0 - t).at[j].set(t))
        feasible.append(used[i] & used[j] & ok & (t >= -slack) & (t <= 1 + slack))
    for i, j, k in _TRIANGLES:
        e1, e2 = points[j] - points[i], points[k] - points[i]
        a, b, c = jnp.sum(e1 * e1), jnp.sum(e1 * e2), jnp.sum(e2 * e2)
        r1, r2 = -jnp.sum(points[i] * e1), -jnp.sum(points[i] * e2)
        determinant = a * c - b * b
        ok = determinant > tiny * a * c
        safe = jnp.where(ok, determinant, 1.0)
        mu1, mu2 = (c * r1 - b * r2) / safe, (a * r2 - b * r1) / safe
        weights.append(zero.at[i].set(1.0 - mu1 - mu2).at[j].set(mu1).at[k].set(mu2))
        feasible.append(used[i] & used[j] & used[k] & ok & (mu1 >= -slack) & (mu2 >= -slack) & (mu1 + mu2 <= 1 + slack))
    e1, e2, e3 = points[1] - points[0], points[2] - points[0], points[3] - points[0]
    determinant = jnp.sum(e1 * jnp.cross(e2, e3))
    scale = _safe_norm(e1) * _safe_norm(e2) * _safe_norm(e3)
    ok = jnp.abs(determinant) > tiny * scale
    safe = jnp.where(ok, determinant, 1.0)
    origin = -points[0]
    mu = jnp.stack(
        [jnp.sum(origin * jnp.cross(e2, e3)), jnp.sum(e1 * jnp.cross(origin, e3)), jnp.sum(e1 * jnp.cross(e2, origin))]
    ) / safe
    weights.append(jnp.concatenate([1.0 - jnp.sum(mu)[None], mu]))
    feasible.append(jnp.all(used) & ok & jnp.all(mu >= -slack) & (jnp.sum(mu) <= 1 + slack))
    weights = jnp.stack(weights)
    closest = weights @ points
    squared = jnp.where(jnp.stack(feasible), jnp.sum(closest**2, axis=-1), jnp.inf)
    best = jnp.argmin(squared)
    return weights[best], closest[best]


def _gjk(shape1, pose1, shape2, pose2, iterations: int = 64):
    """Closest points of the cores of two convex shapes (``support_core`` in local frames);
    returns ``(point1, point2)`` in world coordinates (equal where the cores meet)."""

    def difference(p1, p2, direction):
        local1 = shape1.support_core(p1[0].T @ -direction)
        local2 = shape2.support_core(p2[0].T @ direction)
        return p2[0] @ local2 + p2[1] - (p1[0] @ local1 + p1[1]), local1, local2

    def run(p1, p2):
        start = p1[1] - p2[1]
        start = jnp.where(jnp.sum(start**2) > 0, start, jnp.array([1.0, 0.0, 0.0], start.dtype))
        w, local1, local2 = difference(p1, p2, start)
        dtype = w.dtype
        simplex = jnp.zeros((4, 3), dtype).at[0].set(w)
        locals1 = jnp.zeros((4, 3), dtype).at[0].set(local1)
        locals2 = jnp.zeros((4, 3), dtype).at[0].set(local2)
        used = jnp.zeros(4, bool).at[0].set(True)
        scale2 = jnp.sum((p1[1] - p2[1]) ** 2) + jnp.sum(w**2)
        tolerance = 1e3 * _eps(dtype)

        def body(state):
            simplex, locals1, locals2, used, closest, step, _ = state
            w, local1, local2 = difference(p1, p2, -closest)
            norm2 = jnp.sum(closest**2)
            converged = norm2 - jnp.sum(closest * w) <= tolerance * norm2
            slot = jnp.argmin(used)
            new_simplex = simplex.at[slot].set(w)
            new_used = used.at[slot].set(True)
            weights, new_closest = _closest_in_simplex(new_simplex, new_used)
            new_norm2 = jnp.sum(new_closest**2)
            accept = ~converged & (new_norm2 < norm2)
            pick = lambda new, old: jnp.where(accept, new, old)  # noqa: E731
            return (
                pick(new_simplex, simplex),
                pick(locals1.at[slot].set(local1), locals1),
                pick(locals2.at[slot].set(local2), locals2),
                pick(new_used & (weights > 0), used),
                pick(new_closest, closest),
                step + 1,
                ~accept | (new_norm2 <= tolerance**2 * scale2),
            )

        def cond(state):
            return (state[5] < iterations) & ~state[6]

        state = (simplex, locals1, locals2, used, w, jnp.zeros((), jnp.int32), jnp.zeros((), bool))
        return lax.while_loop(cond, body, state)

    frozen = jax.tree.map(lax.stop_gradient, (pose1, pose2))
    _, locals1, locals2, used, _, _, _ = run(*frozen)
    # The final simplex again, from the differentiable poses: its vertices are points fixed
    # in the shapes (exact for polytopes), which gives the derivative of the closest points
    # for the features found without differentiating through the iterations.
    points1, points2 = _transform(pose1, locals1), _transform(pose2, locals2)
    weights, _ = _closest_in_simplex(points2 - points1, used)
    return weights @ points1, weights @ points2


# --------------------------------------------------------------------------------------
# Polytope cores: separating axes, face clipping.
# --------------------------------------------------------------------------------------


class _Polytope(NamedTuple):
    """A posed core in world coordinates; ``None`` fields are absent (a point has no faces
    nor edges, a segment no faces)."""

    vertices: Array
    face_normals: Array | None
    face_polygons: Array | None
    edges: Array | None
    edge_directions: Array | None
    radius: Array
    edge_normals: Array | None = None  # the two face normals at each edge (Gauss-map arcs)


def _box_faces() -> tuple[np.ndarray, np.ndarray]:
    """Outward normals ``(6, 3)`` and corner signs ``(6, 4, 3)`` of the faces of a box,
    counter-clockwise about each normal."""
    normals, polygons = [], []
    for axis in range(3):
        i, j = (axis + 1) % 3, (axis + 2) % 3
        for sign in (1.0, -1.0):
            square = [(1, 1), (-1, 1), (-1, -1), (1, -1)]
            if sign < 0:
                square = square[::-1]
            polygon = np.zeros((4, 3))
            for corner, (u, v) in enumerate(square):
                polygon[corner, axis], polygon[corner, i], polygon[corner, j] = sign, u, v
            normal = np.zeros(3)
            normal[axis] = sign
            normals.append(normal)
            polygons.append(polygon)
    return np.array(normals), np.array(polygons)


_BOX_NORMALS, _BOX_POLYGONS = _box_faces()
_BOX_EDGES = np.array(
    [
        [[s if k == axis else (u if k == (axis + 1) % 3 else v) for k in range(3)] for s in (-1.0, 1.0)]
        for axis in range(3)
        for u in (-1.0, 1.0)
        for v in (-1.0, 1.0)
    ]
)
# the outward normals of the two faces at each edge of _BOX_EDGES (u e_{axis+1} and v e_{axis+2})
_BOX_EDGE_NORMALS = np.array(
    [
        [np.eye(3)[(axis + 1) % 3] * u, np.eye(3)[(axis + 2) % 3] * v]
        for axis in range(3)
        for u in (-1.0, 1.0)
        for v in (-1.0, 1.0)
    ]
)


# A cylinder against anything but a half-space is the prism of this many sides inscribed in
# it (vertices on its rims): the separating-axis and clipping code of polytopes then gives
# its manifolds, a cap flat on a face included. Penetration depths err by at most the
# sagitta r (1 - cos(pi / n)), 0.5 % of the radius; distances between separated shapes are
# GJK's on the exact cylinder. An exact penetration depth would need EPA or MPR, which give
# one point per pair, not a manifold.
_CYLINDER_SIDES = 32


def _prism_template(sides: int):
    """A prism of unit radius and half-length inscribed in the cylinder ``x^2 + y^2 <= 1``,
    ``|z| <= 1``: vertices ``(2 n, 3)``, outward face normals ``(n + 2, 3)``, face polygons
    counter-clockwise about their normals, padded to ``n`` vertices ``(n + 2, n, 3)``, edges
    ``(3 n, 2, 3)``, the distinct edge directions ``(n / 2 + 1, 3)`` and the normals of the two
    faces at each edge ``(3 n, 2, 3)``."""
    angles = 2.0 * np.pi * np.arange(sides) / sides
    rim = np.stack([np.cos(angles), np.sin(angles)], axis=1)
    top = np.concatenate([rim, np.ones((sides, 1))], axis=1)
    bottom = np.concatenate([rim, -np.ones((sides, 1))], axis=1)
    following = np.roll(np.arange(sides), -1)
    middle = angles + np.pi / sides
    side_normals = np.stack([np.cos(middle), np.sin(middle), np.zeros(sides)], axis=1)
    normals = np.concatenate([[[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]], side_normals])
    quads = np.stack([bottom, bottom[following], top[following], top], axis=1)  # counter-clockwise seen from outside
    pad = lambda polygon: np.concatenate([polygon, np.repeat(polygon[-1:], sides - len(polygon), axis=0)])  # noqa: E731
    polygons = np.stack([top, bottom[::-1]] + [pad(quad) for quad in quads])
    edges = np.concatenate(
        [np.stack([top, top[following]], axis=1), np.stack([bottom, bottom[following]], axis=1), np.stack([bottom, top], axis=1)]
    )
    chords = (top[following] - top)[: (sides + 1) // 2]  # the rest are parallel to these (even n)
    directions = np.concatenate([chords, [[0.0, 0.0, 1.0]]])
    directions[:-1] /= np.linalg.norm(directions[:-1], axis=1, keepdims=True)
    # rim edge k borders a cap and side k (which spans rim vertices k and k + 1); vertical edge k
    # borders sides k - 1 and k
    caps = np.repeat(normals[:2], sides, axis=0)  # top rims, then bottom rims
    edge_normals = np.concatenate(
        [np.stack([caps, np.tile(side_normals, (2, 1))], axis=1),
         np.stack([side_normals[np.roll(np.arange(sides), 1)], side_normals], axis=1)]
    )
    return np.concatenate([top, bottom]), normals, polygons, edges, directions, edge_normals


_PRISM = _prism_template(_CYLINDER_SIDES)


# An ellipsoid against anything but a half-space is the polytope inscribed in it whose vertices
# are an icosphere's (this many subdivisions of the icosahedron: 642 vertices, 1280 triangles)
# scaled by its radii, without edges: its faces' normals sample its Gauss map densely (4.6
# degrees apart), so the axes of its edges would add nothing the faces' do not give to within
# the same error, at O(M1 M2) cost (two ellipsoids: 1920^2 edge pairs). Penetration depths err
# by about 0.45 % of its largest radius (the icosphere's sagitta); distances between separated
# shapes are GJK's on the exact ellipsoid (its support function).
_ELLIPSOID_SUBDIVISIONS = 3


@functools.cache
def _ellipsoid_template() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The unit icosphere (trimesh's): vertices ``(V, 3)``, triangles ``(F, 3)`` counter-clockwise
    about their outward normals, and those normals ``(F, 3)``."""
    import trimesh

    mesh = trimesh.creation.icosphere(subdivisions=_ELLIPSOID_SUBDIVISIONS, radius=1.0)
    return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces), np.asarray(mesh.face_normals, dtype=np.float64)


def _polytope(shape, pose) -> _Polytope:
    rotation, translation = pose
    if isinstance(shape, Sphere):
        return _Polytope(translation[None, :], None, None, None, None, shape.radius)
    if isinstance(shape, Capsule):
        ends = _capsule_ends(shape, pose)
        return _Polytope(ends, None, None, ends[None], rotation[:, 2][None, :], shape.radius)
    if isinstance(shape, Box):
        half = shape.half_extents
        dtype = half.dtype
        polygons = _transform(pose, (jnp.asarray(_BOX_POLYGONS, dtype) * half[None, None, :]).reshape(-1, 3)).reshape(6, 4, 3)
        edges = _transform(pose, (jnp.asarray(_BOX_EDGES, dtype) * half[None, None, :]).reshape(-1, 3)).reshape(12, 2, 3)
        return _Polytope(
            _transform(pose, shape.corners()),
            jnp.asarray(_BOX_NORMALS, dtype) @ rotation.T,
            polygons,
            edges,
            rotation.T,
            shape.core_radius,
            jnp.asarray(_BOX_EDGE_NORMALS, dtype) @ rotation.T,
        )
    if isinstance(shape, Cylinder):
        dtype = shape.radius.dtype
        scale = jnp.stack([shape.radius, shape.radius, shape.half_length])[None, :]
        vertices, normals, polygons, edges, directions, edge_normals = (jnp.asarray(a, dtype) for a in _PRISM)
        faces, size = polygons.shape[:2]
        return _Polytope(
            _transform(pose, vertices * scale),
            normals @ rotation.T,
            _transform(pose, polygons.reshape(-1, 3) * scale).reshape(faces, size, 3),
            _transform(pose, edges.reshape(-1, 3) * scale).reshape(edges.shape[0], 2, 3),
            directions @ rotation.T,
            shape.core_radius,
            edge_normals @ rotation.T,
        )
    if isinstance(shape, Ellipsoid):
        vertices, triangles, normals = _ellipsoid_template()
        radii = shape.radii
        local = jnp.asarray(vertices, radii.dtype) * radii[None, :]
        # a plane's normal maps by the inverse transpose of the scaling
        face_normals, _ = _safe_normalize(jnp.asarray(normals, radii.dtype) / radii[None, :], jnp.zeros_like(local[:1]))
        return _Polytope(
            _transform(pose, local),
            face_normals @ rotation.T,
            _transform(pose, local[triangles.reshape(-1)]).reshape(triangles.shape[0], 3, 3),
            None,
            None,
            shape.core_radius,
        )
    if isinstance(shape, ConvexMesh):
        faces, size = shape.face_polygons.shape[:2]
        edges = shape.edge_segments.shape[0]
        return _Polytope(
            _transform(pose, shape.vertices),
            shape.face_normals @ rotation.T,
            _transform(pose, shape.face_polygons.reshape(-1, 3)).reshape(faces, size, 3),
            _transform(pose, shape.edge_segments.reshape(-1, 3)).reshape(edges, 2, 3),
            shape.edge_directions @ rotation.T,
            shape.core_radius,
            shape.edge_normals @ rotation.T,
        )
    raise TypeError(f"{type(shape).__name__} is not a polytope core.")


def _clip(reference: Array, normal: Array, incident: _Polytope, tolerance):
    """Candidate contact points of ``incident`` against the reference face (polygon
    ``(P, 3)``, counter-clockwise about its outward ``normal``): the incident feature's
    vertices inside the reference face's prism, its edges' crossings of the prism's side
    planes, and the reference vertices inside the incident face. Returns the points on
    the incident core ``(C, 3)`` and a validity mask ``(C,)``."""
    following = jnp.roll(reference, -1, axis=0)
    sides = jnp.cross(following - reference, normal[None, :])  # outward side-plane normals

    def inside(points):
        offsets = jnp.einsum("pk,cpk->cp", sides, points[:, None, :] - reference[None, :, :])
        return jnp.all(offsets <= tolerance * (_safe_norm(sides)[None, :] + 1.0), axis=-1)

    if incident.face_normals is not None:
        face = jnp.argmin(incident.face_normals @ normal)
        polygon = incident.face_polygons[face]
        incident_edges = jnp.stack([polygon, jnp.roll(polygon, -1, axis=0)], axis=1)
    elif incident.edges is not None:
        polygon = incident.edges[0]
        incident_edges = incident.edges
    else:
        polygon = incident.vertices
        incident_edges = None
    points, valid = [polygon], [inside(polygon)]
    if incident_edges is not None:
        start, end = incident_edges[:, 0], incident_edges[:, 1]
        across = jnp.einsum("pk,ek->ep", sides, end - start)
        reach = jnp.einsum("pk,epk->ep", sides, reference[None, :, :] - start[:, None, :])
        ok = jnp.abs(across) > tolerance * (_safe_norm(sides)[None, :] + 1.0)
        t = reach / jnp.where(ok, across, 1.0)
        crossing = start[:, None, :] + t[..., None] * (end - start)[:, None, :]
        crossing = crossing.reshape(-1, 3)
        points.append(crossing)
        valid.append((ok & (t >= 0) & (t <= 1)).reshape(-1) & inside(crossing))
    if incident.face_normals is not None:
        face_normal = incident.face_normals[face]
        slope = jnp.sum(face_normal * normal)
        ok = jnp.abs(slope) > 1e-6
        lift = (polygon[0][None, :] - reference) @ face_normal / jnp.where(ok, slope, 1.0)
        lifted = reference + lift[:, None] * normal[None, :]
        incident_sides = jnp.cross(jnp.roll(polygon, -1, axis=0) - polygon, face_normal[None, :])
        offsets = jnp.einsum("qk,cqk->cq", incident_sides, lifted[:, None, :] - polygon[None, :, :])
        points.append(lifted)
        valid.append(ok & jnp.all(offsets <= tolerance * (_safe_norm(incident_sides)[None, :] + 1.0), axis=-1))
    return jnp.concatenate(points), jnp.concatenate(valid)


def _face_manifold(reference: _Polytope, face, normal, incident: _Polytope, tolerance):
    """Points on the incident core and their depths along the reference face's normal; the
    incident core's deepest vertex (whose depth is the separation along the axis) stands in
    when clipping leaves no point."""
    polygon = reference.face_polygons[face]
    points, valid = _clip(polygon, normal, incident, tolerance)
    deepest = incident.vertices[jnp.argmin(incident.vertices @ normal)]
    points = jnp.concatenate([deepest[None, :], points])
    valid = jnp.concatenate([~jnp.any(valid)[None], valid])
    depth = (points - polygon[0][None, :]) @ normal
    return points, depth, valid


def _support_edge(polytope: _Polytope, axis: Array) -> Array:
    """The edge of ``polytope`` perpendicular to ``axis`` that is farthest along it (both
    ends), the edge's side of an edge-edge contact. Chosen by geometry rather than by the
    pair of directions whose cross product gave the axis: identical directions in both
    shapes (two boxes) give the same axis for several pairs."""
    edges = polytope.edges
    along, _ = _safe_normalize(edges[:, 1] - edges[:, 0], jnp.zeros_like(edges[:, 0]))
    perpendicular = jnp.abs(along @ axis) <= 1e-6
    height = jnp.minimum(edges[:, 0] @ axis, edges[:, 1] @ axis)
    return edges[jnp.argmax(jnp.where(perpendicular, height, -jnp.inf))]


# How much better than the best face axis an edge axis must separate the cores to be
# chosen when the two axes are within _FACE_PREFERENCE_ANGLE (rad) of each other: a share
# of the face's penetration plus a length relative to the pair's size.
_FACE_PREFERENCE_ANGLE = 0.01
_FACE_PREFERENCE_RELATIVE = 0.05
_FACE_PREFERENCE_ABSOLUTE = 1e-3


def _gap(core1: _Polytope, core2: _Polytope, axes: Array) -> Array:
    """Separation of the cores' vertices along unit axes ``(N, 3)`` pointing from 1 to 2."""
    return jnp.min(core2.vertices @ axes.T, axis=0) - jnp.max(core1.vertices @ axes.T, axis=0)


def _face_gaps(owner: _Polytope, other: _Polytope) -> Array:
    """Separation of ``other``'s vertices from each face plane of ``owner`` along the face's
    outward normal ``(F,)``: ``owner``'s own support along its face normal is the face's plane,
    so only ``other``'s vertices are projected, ``O(F V_other)`` instead of the
    ``O(F (V_owner + V_other))`` of :func:`_gap` (a robot's hull of thousands of faces and
    vertices makes the difference)."""
    offsets = jnp.sum(owner.face_normals * owner.face_polygons[:, 0], axis=-1)
    return jnp.min(other.vertices @ owner.face_normals.T, axis=0) - offsets


def _edge_axis(core1: _Polytope, core2: _Polytope) -> tuple[Array, Array]:
    """The largest separation over the axes normal to an edge direction of each core (both
    orientations), and its axis (pointing from 1 to 2): every vertex projected on every
    pair of directions."""
    crosses = jnp.cross(core1.edge_directions[:, None, :], core2.edge_directions[None, :, :]).reshape(-1, 3)
    axes, length = _safe_normalize(crosses, jnp.zeros_like(crosses))
    plus, minus = _gap(core1, core2, axes), _gap(core1, core2, -axes)
    oriented = jnp.where((plus >= minus)[:, None], axes, -axes)
    edge_gaps = jnp.where(length > 1e-6, jnp.maximum(plus, minus), -jnp.inf)
    edge = jnp.argmax(edge_gaps)
    return edge_gaps[edge], oriented[edge]


def _minkowski_edge_axis(core1: _Polytope, core2: _Polytope) -> tuple[Array, Array]:
    """:func:`_edge_axis` for two meshes by their Gauss maps: only an edge pair whose arcs
    cross (the pair spans a face of the Minkowski difference) can give the largest
    separation, and for such a pair the edges themselves are the supporting features, so the
    separation is the distance between their lines along the axis (D. Gregorius, "The
    separating axis test between convex polyhedra", GDC 2013). Every edge pair is tested in
    ``O(1)``, with no vertex projected.

    Arcs: edge ``i`` of core 1 joins the face normals ``a, b``; edge ``j`` of core 2, in the
    difference ``1 - 2``, joins ``-c, -d``. They cross where ``-c`` and ``-d`` lie on either
    side of the plane of ``a, b``, ``a`` and ``b`` on either side of that of ``-c, -d``, and
    the arcs lie in one hemisphere."""
    a, b = core1.edge_normals[:, 0], core1.edge_normals[:, 1]  # (M1, 3)
    c, d = -core2.edge_normals[:, 0], -core2.edge_normals[:, 1]  # (M2, 3)
    b_a, d_c = jnp.cross(b, a), jnp.cross(d, c)
    cba, dba = b_a @ c.T, b_a @ d.T  # (M1, M2)
    adc, bdc = a @ d_c.T, b @ d_c.T
    crossing = (cba * dba < 0) & (adc * bdc < 0) & (cba * bdc > 0)
    start1, start2 = core1.edges[:, 0], core2.edges[:, 0]
    direction1 = core1.edges[:, 1] - start1
    direction2 = core2.edges[:, 1] - start2
    axes = jnp.cross(direction1[:, None, :], direction2[None, :, :])  # (M1, M2, 3)
    axes, length = _safe_normalize(axes, jnp.zeros_like(axes))
    scale = _safe_norm(direction1)[:, None] * _safe_norm(direction2)[None, :]
    # pointing out of core 1 (its centroid is inside it)
    centroid = jnp.mean(core1.vertices, axis=0)
    outward = jnp.sum(axes * (start1 - centroid[None, :])[:, None, :], axis=-1)
    axes = jnp.where((outward < 0)[..., None], -axes, axes)
    gaps = jnp.sum(axes * (start2[None, :, :] - start1[:, None, :]), axis=-1)
    gaps = jnp.where(crossing & (length > 1e-6 * scale), gaps, -jnp.inf).reshape(-1)
    edge = jnp.argmax(gaps)
    return gaps[edge], axes.reshape(-1, 3)[edge]


# The exact best axis of a pair with an ellipsoid (_refined_axis): rounds of the pattern search
# and its first step (rad), wider than the icosphere's faces' spacing (4.6 degrees), halved
# each round that finds no better axis; iterations of the golden-section search along each
# edge's circle of axes, within this angle (rad) of the polytopes' best axis, on at most this
# many edges of a shape (those that reach farthest towards the other).
_REFINE_ROUNDS = 48
_REFINE_STEP = 0.1
_EDGE_SEARCH_ITERATIONS = 48
_EDGE_SEARCH_WINDOW = 1.5
_EDGE_SEARCH_COUNT = 16


def _support(shape, pose, direction: Array) -> Array:
    """The world point of ``shape``'s core farthest along the world ``direction``."""
    rotation, translation = pose
    return translation + rotation @ shape.support_core(rotation.T @ direction)


def _axis_gap(shape1, pose1, shape2, pose2, axis: Array) -> Array:
    """The separation of the two shapes along the unit ``axis`` (from 1 to 2): at most their
    signed distance, equal to it at the best axis (convex shapes)."""
    gap = axis @ (_support(shape2, pose2, -axis) - _support(shape1, pose1, axis))
    return gap - shape1.core_radius - shape2.core_radius


def _refined_axis(shape1, pose1, shape2, pose2, start: Array, core1: _Polytope, core2: _Polytope) -> Array:
    """The best separating axis of a pair with an ellipsoid, from the polytopes' best one
    ``start``: the separating axes of an ellipsoid's inscribed polytope are only within its
    faces' spacing of the exact shapes' best axis, and a box's edge against it errs by that
    angle times the box's size. The gap (:func:`_axis_gap`, on the shapes' exact support
    functions) is largest, for convex shapes, on a face normal of the other shape (tried
    exactly), across an edge of it (a golden-section search along the circle of axes normal to
    each edge, near ``start``: the gap has a kink across the edge, which a search over the
    sphere stalls at), or where it is smooth (a vertex, or two curved shapes): a pattern search
    over the sphere (eight neighbours at a step that halves when none is better) from the best
    of these finishes. Derivatives are not taken through the searches."""
    start = lax.stop_gradient(start)
    poses = jax.tree.map(lax.stop_gradient, (pose1, pose2))
    cores = jax.tree.map(lambda a: None if a is None else lax.stop_gradient(a), (core1, core2), is_leaf=lambda a: a is None)
    gap = lambda axis: _axis_gap(shape1, poses[0], shape2, poses[1], axis)  # noqa: E731
    dtype = start.dtype
    candidates = [start[None, :]]
    # faces of a shape that is not the ellipsoid (outward from 1 towards 2); the edges of its
    # polytope that reach farthest towards the other shape (a mesh's edges are many)
    for core, sign, shape in ((cores[0], 1.0, shape1), (cores[1], -1.0, shape2)):
        if isinstance(shape, Ellipsoid):
            continue
        if core.face_normals is not None:
            candidates.append(sign * core.face_normals)
        if core.edges is not None:
            edges = core.edges
            if edges.shape[0] > _EDGE_SEARCH_COUNT:
                reach = jnp.max(edges @ (sign * start), axis=-1)
                edges = edges[lax.top_k(reach, _EDGE_SEARCH_COUNT)[1]]
            candidates.append(_edge_axes(gap, edges, start))
    candidates = jnp.concatenate(candidates)
    values = jax.vmap(gap)(candidates)
    best = jnp.argmax(values)

    helper_x, helper_y = jnp.array([1.0, 0.0, 0.0], dtype), jnp.array([0.0, 1.0, 0.0], dtype)
    root_half = np.sqrt(0.5)
    offsets = np.array([[1, 0], [-1, 0], [0, 1], [0, -1], [root_half, root_half], [-root_half, root_half],
                        [root_half, -root_half], [-root_half, -root_half]])

    def round_(_, carry):
        axis, value, step = carry
        helper = jnp.where(jnp.abs(axis[0]) < 0.9, helper_x, helper_y)
        tangent1, _ = _safe_normalize(jnp.cross(axis, helper), jnp.array([0.0, 0.0, 1.0], dtype))
        tangent2 = jnp.cross(axis, tangent1)
        moves = jnp.asarray(offsets, dtype) @ jnp.stack([tangent1, tangent2])  # (8, 3)
        trial = jnp.cos(step) * axis[None, :] + jnp.sin(step) * moves
        trial = trial / _safe_norm(trial)[:, None]
        trial_values = jax.vmap(gap)(trial)
        pick = jnp.argmax(trial_values)
        better = trial_values[pick] > value
        return (
            jnp.where(better, trial[pick], axis), jnp.where(better, trial_values[pick], value),
            jnp.where(better, step, 0.5 * step),
        )

    carry = (candidates[best], values[best], jnp.asarray(_REFINE_STEP, dtype))
    axis, _, _ = lax.fori_loop(0, _REFINE_ROUNDS, round_, carry)
    return axis


def _edge_axes(gap, edges: Array, start: Array) -> Array:
    """For each edge ``(M, 2, 3)``, the axis normal to it of largest ``gap`` within
    :data:`_EDGE_SEARCH_WINDOW` of ``start`` along the circle of such axes (golden-section
    search from ``start``'s projection on it), ``(M, 3)``."""
    dtype = start.dtype
    direction, _ = _safe_normalize(edges[:, 1] - edges[:, 0], jnp.zeros_like(edges[:, 0]))
    # the circle's basis: start's part normal to the edge, and the edge's direction times it
    # (an edge along start, to rounding: any axis normal to it)
    helper = jnp.where(jnp.abs(direction[:, :1]) < 0.9, jnp.array([1.0, 0.0, 0.0], dtype), jnp.array([0.0, 1.0, 0.0], dtype))
    normal_to_edge, _ = _safe_normalize(jnp.cross(direction, helper), jnp.broadcast_to(start, direction.shape))
    residual = start[None, :] - (direction @ start)[:, None] * direction
    square = jnp.sum(residual * residual, axis=-1)
    usable = square > 1e-12
    first = jnp.where(usable[:, None], residual / jnp.sqrt(jnp.where(usable, square, 1.0))[:, None], normal_to_edge)
    second = jnp.cross(direction, first)
    on_circle = lambda angle: jnp.cos(angle)[:, None] * first + jnp.sin(angle)[:, None] * second  # noqa: E731
    values = lambda angle: jax.vmap(gap)(on_circle(angle))  # noqa: E731
    ratio = (np.sqrt(5.0) - 1.0) / 2.0
    count = edges.shape[0]
    low, high = jnp.full(count, -_EDGE_SEARCH_WINDOW, dtype), jnp.full(count, _EDGE_SEARCH_WINDOW, dtype)

    def narrow(_, bracket):
        low, high = bracket
        left, right = high - ratio * (high - low), low + ratio * (high - low)
        keep_left = values(left) >= values(right)
        return jnp.where(keep_left, low, left), jnp.where(keep_left, right, high)

    low, high = lax.fori_loop(0, _EDGE_SEARCH_ITERATIONS, narrow, (low, high))
    return on_circle(0.5 * (low + high))


def _polytope_pair(shape1, pose1, shape2, pose2, margin, count: int) -> Contacts:
    """Separating axes for overlapping cores, GJK for separated ones, face clipping for
    the manifold (see the module's docstring)."""
    core1, core2 = _polytope(shape1, pose1), _polytope(shape2, pose2)
    dtype = core1.vertices.dtype
    scale = shape1.bounding_radius + shape2.bounding_radius + _safe_norm(pose1[1] - pose2[1])
    tolerance = 1e3 * _eps(dtype) * scale
    radius1, radius2 = core1.radius, core2.radius

    minus_infinity = jnp.asarray(-jnp.inf, dtype)
    # Faces: of shape 1 (outward normals) and of shape 2 (reversed outward normals).
    best_face_gap, face_of_1 = minus_infinity, jnp.asarray(True)
    if core1.face_normals is not None:
        gaps1 = _face_gaps(core1, core2)
        face1 = jnp.argmax(gaps1)
        best_face_gap = gaps1[face1]
    if core2.face_normals is not None:
        gaps2 = _face_gaps(core2, core1)
        face2 = jnp.argmax(gaps2)
        face_of_1 = best_face_gap >= gaps2[face2]
        best_face_gap = jnp.maximum(best_face_gap, gaps2[face2])
    # Edges: cross products of edge directions, both orientations; by the Gauss maps where a
    # mesh is in the pair (its edge directions are many: every pair projected with every
    # vertex would be a (V, M1 M2) array, gigabytes for a robot's hulls).
    has_edges = core1.edges is not None and core2.edges is not None
    if has_edges:
        if core1.edge_normals is not None and core2.edge_normals is not None and (
            isinstance(shape1, ConvexMesh) or isinstance(shape2, ConvexMesh)
        ):
            edge_gap, edge_axis = _minkowski_edge_axis(core1, core2)
        else:
            edge_gap, edge_axis = _edge_axis(core1, core2)
        if core1.face_normals is not None and core2.face_normals is not None:
            best_face_normal = jnp.where(face_of_1, core1.face_normals[face1], -core2.face_normals[face2])
        elif core1.face_normals is not None:
            best_face_normal = core1.face_normals[face1]
        else:
            best_face_normal = -core2.face_normals[face2]
        # Faces win near-ties: a resting face tilted by rounding or by a small rotation has
        # edge axes within that angle of its normal and a hair better than it, and an edge
        # contact is one point where the face gives the manifold that keeps a stack at
        # rest. Such an edge must beat the face by a share of the penetration plus a slop
        # (ODE's box-box test prefers faces the same way): the depth error this allows is
        # at most that margin, and only for near-parallel axes; elsewhere the best axis wins.
        face_normal = best_face_normal
        near_parallel = jnp.abs(edge_axis @ face_normal) > jnp.cos(jnp.asarray(_FACE_PREFERENCE_ANGLE, dtype))
        preference = _FACE_PREFERENCE_RELATIVE * jnp.abs(best_face_gap) + _FACE_PREFERENCE_ABSOLUTE * scale
        use_edge = edge_gap > best_face_gap + tolerance + jnp.where(near_parallel, preference, 0.0)
        separation = jnp.where(use_edge, edge_gap, best_face_gap)
    else:
        use_edge = jnp.asarray(False)
        separation = best_face_gap

    # Face manifold, from whichever shape owns the best face.
    candidates = []
    if core1.face_normals is not None:
        normal = core1.face_normals[face1]
        points, depth, valid = _face_manifold(core1, face1, normal, core2, tolerance)
        point2 = points - radius2 * normal[None, :]
        point1 = points - depth[:, None] * normal[None, :] + radius1 * normal[None, :]
        candidates.append((face_of_1, normal, point1, point2, depth - radius1 - radius2, valid))
    if core2.face_normals is not None:
        normal = -core2.face_normals[face2]
        points, depth, valid = _face_manifold(core2, face2, -normal, core1, tolerance)
        point1 = points + radius1 * normal[None, :]
        point2 = points + depth[:, None] * normal[None, :] - radius2 * normal[None, :]
        candidates.append((~face_of_1, normal, point1, point2, depth - radius1 - radius2, valid))
    if len(candidates) == 2 and candidates[0][2].shape != candidates[1][2].shape:
        size = max(c[2].shape[0] for c in candidates)
        candidates = [_pad(c, size) for c in candidates]
    if len(candidates) == 2:
        pick = candidates[0][0]
        _, normal, point1, point2, distance, valid = jax.tree.map(
            lambda a, b: jnp.where(pick, a, b),
            candidates[0],
            candidates[1],
        )
    else:
        _, normal, point1, point2, distance, valid = candidates[0]
    manifold = _reduce(point1, point2, distance, normal, valid, margin, count)
    if isinstance(shape1, Ellipsoid) or isinstance(shape2, Ellipsoid):
        # the deepest entry on the exact shapes' best axis (see _refined_axis), from the
        # polytopes' best one; its point on shape 2 is that shape's deepest along the axis
        axis = _refined_axis(shape1, pose1, shape2, pose2, manifold.normal[0], core1, core2)
        deepest = _axis_gap(shape1, pose1, shape2, pose2, axis)
        point2 = _support(shape2, pose2, -axis) - radius2 * axis
        manifold = Contacts(
            manifold.distance.at[0].set(deepest), manifold.normal.at[0].set(axis),
            manifold.point1.at[0].set(point2 - deepest * axis), manifold.point2.at[0].set(point2),
            manifold.active.at[0].set(deepest <= margin),
        )

    def replace_first(contacts, distance, normal, point1, point2, condition):
        update = lambda field, value: field.at[0].set(jnp.where(condition, value, field[0]))  # noqa: E731
        return Contacts(
            update(contacts.distance, distance),
            update(contacts.normal, normal),
            update(contacts.point1, point1),
            update(contacts.point2, point2),
            update(contacts.active, distance <= margin),
        )

    if has_edges:
        edge1 = _support_edge(core1, edge_axis)
        edge2 = _support_edge(core2, -edge_axis)
        closest1, closest2 = _closest_segment_segment(edge1[0], edge1[1], edge2[0], edge2[1])
        edge_distance = jnp.sum((closest2 - closest1) * edge_axis) - radius1 - radius2
        # An edge-edge contact is a single point: every entry holds it, only the first is active.
        edge_contact = _single(edge_distance, edge_axis, closest1 + radius1 * edge_axis, closest2 - radius2 * edge_axis, margin)
        manifold = jax.tree.map(
            lambda ours, edge: jnp.where(use_edge, jnp.broadcast_to(edge, ours.shape), ours), manifold, edge_contact
        )
        manifold = eqx.tree_at(lambda c: c.active, manifold, manifold.active & ((jnp.arange(count) == 0) | ~use_edge))

    # Separated cores: GJK's exact distance for the deepest entry.
    closest1, closest2 = _gjk(shape1, pose1, shape2, pose2)
    fallback = manifold.normal[0]
    gjk_normal, length = _safe_normalize(closest2 - closest1, fallback)
    # The separation along the best axis is a lower bound of the distance of separated
    # cores, exact when their closest features are parallel faces (a resting contact):
    # keep the clipped manifold then, whose points span the face. GJK's distance is only
    # accurate to a few thousand roundings of the shapes' size (its simplex spans them), so
    # it replaces the manifold's first entry only where it is longer by more than
    # sqrt(eps) of that size (8 nm for boxes of 10 cm in float64): a box resting on a box,
    # its faces apart by 1e-13 m, otherwise gets a GJK point mid-face whose normal (the
    # direction of a 1e-13 m vector) is rounding noise, and the stack's sticking solve fails.
    gjk_tolerance = jnp.sqrt(jnp.asarray(_eps(dtype), dtype)) * scale
    separated = (separation > 0) & (jnp.abs(length - radius1 - radius2 - manifold.distance[0]) > gjk_tolerance)
    if isinstance(shape1, Ellipsoid) or isinstance(shape2, Ellipsoid):
        # the exact shapes' cores apart (GJK), not their inscribed polytopes: within the
        # ellipsoid's sagitta the polytopes separate where the shapes overlap
        separated = length > gjk_tolerance
    return replace_first(
        manifold,
        length - radius1 - radius2,
        gjk_normal,
        closest1 + radius1 * gjk_normal,
        closest2 - radius2 * gjk_normal,
        separated,
    )


# --------------------------------------------------------------------------------------
# Height fields: the prisms under a sphere or a capsule, each a convex polytope; the terrain's
# surface under a polytope core.
# --------------------------------------------------------------------------------------


def _prism(top: Array, base: Array) -> ConvexMesh:
    """The vertical prism under the triangle ``top`` ``(3, 3)`` (counter-clockwise seen from
    above) down to ``z = -base``, as a :class:`ConvexMesh` (its faces, edges and Gauss-map arcs)."""
    dtype = top.dtype
    bottom = top.at[:, 2].set(-base)
    up = jnp.cross(top[1] - top[0], top[2] - top[0])
    top_normal = up / _safe_norm(up)
    following = np.array([1, 2, 0])
    along = top[following, :2] - top[:, :2]  # the triangle's edges in the plane
    length = _safe_norm(along)
    outward = jnp.stack([along[:, 1], -along[:, 0], jnp.zeros(3, dtype)], axis=-1) / length[:, None]  # (3, 3)
    down = jnp.array([0.0, 0.0, -1.0], dtype)
    normals = jnp.concatenate([top_normal[None], down[None], outward])  # top, bottom, the sides
    sides = jnp.stack([bottom, bottom[following], top[following], top], axis=1)  # (3, 4, 3), counter-clockwise from outside
    polygons = jnp.concatenate([
        jnp.concatenate([top, top[2:]])[None], jnp.concatenate([bottom[::-1], bottom[:1]])[None], sides,
    ])
    edges = jnp.concatenate([
        jnp.stack([top, top[following]], axis=1), jnp.stack([bottom, bottom[following]], axis=1), jnp.stack([bottom, top], axis=1),
    ])
    previous = np.array([2, 0, 1])
    edge_normals = jnp.concatenate([
        jnp.stack([jnp.broadcast_to(top_normal, (3, 3)), outward], axis=1),
        jnp.stack([jnp.broadcast_to(down, (3, 3)), outward], axis=1),
        jnp.stack([outward[previous], outward], axis=1),  # vertical edge k: sides k - 1 and k
    ])
    directions = (edges[:, 1] - edges[:, 0]) / _safe_norm(edges[:, 1] - edges[:, 0])[:, None]
    vertices = jnp.concatenate([top, bottom])
    return ConvexMesh(
        vertices=vertices, face_normals=normals, face_offsets=jnp.sum(normals * polygons[:, 0], axis=-1),
        face_polygons=polygons, edge_segments=edges, edge_directions=directions, edge_normals=edge_normals,
    )


def _heightfield_grid(field: HeightField, center: Array, reach: Array, peaks: bool = False):
    """The grid points ``(w_r + 1, w_c + 1, 3)`` (local ``x``, ``y``, height) of the ``window`` x
    ``window`` cells (fewer on a smaller grid) from the cell under the height field's local point
    ``center`` less ``reach`` (a shape's bounding radius about it), clipped to the grid; rows
    along ``y``, columns along ``x``. With ``peaks``, also which of them are above the mean
    height of their four neighbours ``(w_r + 1, w_c + 1)``."""
    rows, columns = field.heights.shape
    window_r, window_c = min(field.window, rows - 1), min(field.window, columns - 1)
    cell = field.cell
    start = jnp.floor((center[:2] - reach + field.half_size) / cell).astype(jnp.int32)
    c0 = jnp.clip(start[0], 0, columns - 1 - window_c)
    r0 = jnp.clip(start[1], 0, rows - 1 - window_r)
    heights = lax.dynamic_slice(field.heights, (r0, c0), (window_r + 1, window_c + 1))
    xs = -field.half_size[0] + cell[0] * (c0 + jnp.arange(window_c + 1)).astype(cell.dtype)
    ys = -field.half_size[1] + cell[1] * (r0 + jnp.arange(window_r + 1)).astype(cell.dtype)
    grid = jnp.stack(jnp.broadcast_arrays(xs[None, :], ys[:, None], heights), axis=-1)
    if not peaks:
        return grid
    # a grid point above the mean of its four neighbours (the grid's border repeated)
    block = lax.dynamic_slice(jnp.pad(field.heights, 1, mode="edge"), (r0, c0), (window_r + 3, window_c + 3))
    around = (block[:-2, 1:-1] + block[2:, 1:-1] + block[1:-1, :-2] + block[1:-1, 2:]) / 4.0
    return grid, heights > around + 1e3 * _eps(heights.dtype) * (1.0 + jnp.abs(heights))


def _heightfield_prisms(field: HeightField, center: Array, reach: Array) -> ConvexMesh:
    """The prisms ``(2 w_r w_c,)`` of the cells of :func:`_heightfield_grid`: MuJoCo's
    triangles, ``(c, r + 1), (c, r), (c + 1, r + 1)`` and ``(c, r), (c + 1, r), (c + 1, r + 1)``."""
    grid = _heightfield_grid(field, center, reach)
    low, high = grid[:-1], grid[1:]  # row r, row r + 1
    a, b, c, d = high[:, :-1], low[:, :-1], high[:, 1:], low[:, 1:]  # (c, r+1), (c, r), (c+1, r+1), (c+1, r)
    # counter-clockwise seen from above: (b, d, c) and (b, c, a)
    triangles = jnp.concatenate([jnp.stack([b, c, a], axis=-2), jnp.stack([b, d, c], axis=-2)]).reshape(-1, 3, 3)
    return jax.vmap(lambda top: _prism(top, field.base))(triangles)


def _terrain_under(field: HeightField, points: Array) -> tuple[Array, Array, Array]:
    """The triangle of the terrain under each of the local ``points`` ``(N, 3)`` (MuJoCo's split
    of the cell under its ``(x, y)``): whether the point is over the grid ``(N,)``, the
    triangle's unit up-normal ``(N, 3)`` and its corner ``(c, r)`` ``(N, 3)``. A point over a
    cell's diagonal takes one of its two triangles; one off the grid the nearest cell's."""
    rows, columns = field.heights.shape
    cell = field.cell
    scaled = (points[:, :2] + field.half_size[None, :]) / cell[None, :]  # in cells from the corner
    limit = jnp.asarray([columns - 1, rows - 1], scaled.dtype)
    over = jnp.all((scaled >= 0) & (scaled <= limit[None, :]), axis=-1)
    c = jnp.clip(jnp.floor(scaled[:, 0]).astype(jnp.int32), 0, columns - 2)
    r = jnp.clip(jnp.floor(scaled[:, 1]).astype(jnp.int32), 0, rows - 2)
    u, w = scaled[:, 0] - c.astype(scaled.dtype), scaled[:, 1] - r.astype(scaled.dtype)
    heights = field.heights
    h00, h10, h01, h11 = heights[r, c], heights[r, c + 1], heights[r + 1, c], heights[r + 1, c + 1]
    upper = w >= u  # the triangle (c, r), (c + 1, r + 1), (c, r + 1); else (c, r), (c + 1, r), (c + 1, r + 1)
    slope_x = jnp.where(upper, h11 - h01, h10 - h00) / cell[0]
    slope_y = jnp.where(upper, h01 - h00, h11 - h10) / cell[1]
    up = jnp.stack([-slope_x, -slope_y, jnp.ones_like(slope_x)], axis=-1)
    normal = up / jnp.sqrt(1.0 + slope_x**2 + slope_y**2)[:, None]
    corner = jnp.stack([
        -field.half_size[0] + cell[0] * c.astype(cell.dtype), -field.half_size[1] + cell[1] * r.astype(cell.dtype), h00,
    ], axis=-1)
    return over, normal, corner


def _heightfield_pair(field: HeightField, field_pose, shape, pose, margin, count: int) -> Contacts:
    """The ``count`` deepest contacts of ``shape`` with the prisms of the height field's cells
    under it (:func:`_heightfield_prisms`), each a polytope pair; normals from the field."""
    rotation, translation = field_pose
    prisms = _heightfield_prisms(field, rotation.T @ (pose[1] - translation), shape.bounding_radius)
    contacts = jax.vmap(lambda prism: _polytope_pair(prism, field_pose, shape, pose, margin, count))(prisms)
    flat = jax.tree.map(lambda a: a.reshape((-1,) + a.shape[2:]), contacts)
    # the deepest entries, each away from those chosen before it: a shape on a flat stretch
    # touches the prisms that meet under it at one point, which one contact holds (copies of
    # it would make the contact problem's impulses indeterminate)
    gaps = jnp.where(flat.active, flat.distance, _INACTIVE_GAP)
    tolerance = 1e3 * _eps(gaps.dtype) * (1.0 + shape.bounding_radius)
    chosen, distinct, free = [], [], jnp.ones(gaps.shape, bool)
    for _ in range(count):
        index = jnp.argmin(jnp.where(free, gaps, 2 * _INACTIVE_GAP))
        chosen.append(index)
        distinct.append(free[index])
        free = free & (_safe_norm(flat.point2 - flat.point2[index][None, :]) > tolerance)
    result = jax.tree.map(lambda a: a[jnp.stack(chosen)], flat)
    return eqx.tree_at(lambda c: c.active, result, result.active & jnp.stack(distinct))


def _support_points(shape, pose, directions: Array) -> Array:
    """The exact shape's core points farthest along each of ``directions`` ``(D, 3)``, for the
    curved shapes (a cylinder: the rim points of both caps, so that one lying on its side gets
    both ends); none for a polytope, whose vertices hold its supports."""
    rotation, translation = pose
    if isinstance(shape, Ellipsoid):
        local = jax.vmap(shape.support_core)(directions @ rotation)
    elif isinstance(shape, Cylinder):
        local = jax.vmap(shape.support_core)(directions @ rotation)
        local = jnp.concatenate([local, local.at[:, 2].multiply(-1.0)])
    else:
        return jnp.zeros((0, 3), directions.dtype)
    return _transform(pose, local)


def _heightfield_polytope(field: HeightField, field_pose, shape, pose, margin, count: int) -> Contacts:
    """The ``count`` contacts of a polytope core (box, cylinder, convex mesh, ellipsoid) with
    the terrain's surface, normals from the terrain where the shape rests on it.

    A polytope that overlaps one of the cell prisms of :func:`_heightfield_pair` often has its
    smallest way out of that prism through the prism's side, which is inside the terrain: a
    depth and normal that are not the terrain's. The candidates here are instead the feature
    pairs of a polyhedral terrain and a convex shape, each a point against a plane, with the
    terrain's normal where the shape's point is against it (as a half-space's contacts):

    - the shape's points against the triangle under them (:func:`_terrain_under`): the core's
      vertices, and for a curved shape (cylinder, ellipsoid) its exact supports along minus the
      normals of the triangles under it (:func:`_support_points`), the deepest point against each
      triangle's plane: distance ``n . (v - a) - radius`` along the triangle's unit up-normal
      ``n``, the terrain's witness ``v - (n . (v - a)) n`` on the triangle's plane;
    - the terrain's grid points under the shape that are above the mean of their four neighbours
      (a peak, a ridge, a terrace's edge; elsewhere the terrain reaches no deeper into the shape
      than at the shape's points against it) against the core: distance
      ``max_f (n_f . g - o_f) - radius`` over the core's faces, normal minus that face's, where
      the grid point is inside the core or over that face (its projection inside the face's
      polygon) (:func:`_points_in_core`);
    - where an edge of the core crosses an edge of the terrain seen from above (a crease, a cell's
      side or diagonal), both points of the crossing, as above (:func:`_edge_crossings`).

    The distance of a point below the terrain is its depth along the triangle's normal, the
    terrain's penetration where the deepest point is over the triangle's interior (a resting
    shape); above it, the distance along that normal, the Euclidean distance where the point's
    nearest feature of the terrain is the triangle under it. A grid point inside the core has its
    exact depth, one over a face its exact distance. Points off the grid give no contact. The
    candidates are reduced by :func:`_reduce` (the deepest first, then the largest area), which
    gives a box resting on a flat terrain its four corners. The distances are smooth in the poses
    but where a point crosses a cell's edge or diagonal, a face's choice changes, or the
    reduction's; their derivatives are finite everywhere."""
    field_rotation, field_translation = field_pose
    rotation, translation = pose
    local_pose = (field_rotation.T @ rotation, field_rotation.T @ (translation - field_translation))
    core = _polytope(shape, local_pose)
    radius = core.radius
    window, peak = _heightfield_grid(field, local_pose[1], shape.bounding_radius, peaks=True)
    grid = window.reshape(-1, 3)
    if isinstance(shape, (Cylinder, Ellipsoid)):
        # minus the normals of the window's triangles (_terrain_under at their centroids)
        _, window_normals, _ = _terrain_under(field, _window_centroids(window))
        supports = _support_points(shape, local_pose, -window_normals)
    else:
        supports = jnp.zeros((0, 3), grid.dtype)
    points = core.vertices if not isinstance(shape, Ellipsoid) else jnp.zeros((0, 3), grid.dtype)
    points = jnp.concatenate([points, supports])
    over, normal, corner = _terrain_under(field, points)
    height = jnp.sum(normal * (points - corner), axis=-1)
    parts = [(height - radius, normal, points - height[:, None] * normal, points - radius * normal, over)]
    gap, peak_normal, point1, point2, valid = _points_in_core(core, grid, shape.bounding_radius)
    parts.append((gap, peak_normal, point1, point2, valid & peak.reshape(-1)))
    if core.edges is not None:
        parts += _edge_crossings(field, window, core, shape.bounding_radius)
    distance, normal, point1, point2, candidate = (jnp.concatenate(part) for part in zip(*parts))
    contacts = _reduce(point1, point2, distance, normal, candidate, margin, count)
    return Contacts(
        contacts.distance,
        contacts.normal @ field_rotation.T,
        _transform(field_pose, contacts.point1),
        _transform(field_pose, contacts.point2),
        contacts.active,
    )


def _window_centroids(window: Array) -> Array:
    """The centroids ``(2 w_r w_c, 3)`` of the triangles of a window of :func:`_heightfield_grid`
    (their ``x``, ``y`` pick the triangle in :func:`_terrain_under`)."""
    low, high = window[:-1], window[1:]
    a, b, c, d = high[:, :-1], low[:, :-1], high[:, 1:], low[:, 1:]
    return jnp.concatenate([(a + b + c) / 3.0, (b + c + d) / 3.0]).reshape(-1, 3)


def _points_in_core(core: _Polytope, points: Array, size) -> tuple:
    """Terrain ``points`` ``(G, 3)`` against the core: the largest face gap ``max_f (n_f . g -
    o_f)`` less the core's radius, normal minus that face's, and whether it is the distance: the
    point is inside the core (its exact depth) or over that face (its projection inside the face's
    polygon; elsewhere the gap is less than the distance, whose nearest feature is an edge or a
    vertex)."""
    offsets = jnp.sum(core.face_normals * core.face_polygons[:, 0], axis=-1)
    gaps = points @ core.face_normals.T - offsets[None, :]
    face = jnp.argmax(gaps, axis=-1)
    face_gap = jnp.take_along_axis(gaps, face[:, None], axis=-1)[:, 0]
    polygon, face_normal = core.face_polygons[face], core.face_normals[face]
    projected = points - face_gap[:, None] * face_normal
    sides = jnp.cross(jnp.roll(polygon, -1, axis=1) - polygon, face_normal[:, None, :])
    inward = jnp.einsum("gpk,gpk->gp", sides, projected[:, None, :] - polygon)
    tolerance = 1e3 * _eps(points.dtype) * (1.0 + size)
    on_face = jnp.all(inward <= tolerance * (_safe_norm(sides) + 1.0), axis=-1)
    gap = face_gap - core.radius
    normal = -face_normal
    return gap, normal, points, points + gap[:, None] * normal, (face_gap <= 0) | on_face


def _edge_crossings(field: HeightField, window: Array, core: _Polytope, size) -> list:
    """The crossings, seen from above, of the core's edges with the terrain's edges in the window
    (the cells' sides and diagonals): an edge of the shape over a crease of the terrain, whose
    deepest point need not be a vertex of either. At a crossing, ``p`` on the shape's edge over
    ``q`` on the terrain's: ``p`` against the terrain (the two triangles at the crease: in a
    valley, where the solid is their half-spaces' union, the deeper; on a ridge, their
    intersection, the shallower) and, on a ridge, ``q`` against the core
    (:func:`_points_in_core`); elsewhere the terrain reaches no deeper into the shape at ``q``
    than at the shape's points against it."""
    low, high = window[:-1], window[1:]
    terrain = jnp.concatenate([
        jnp.stack([window[:, :-1], window[:, 1:]], axis=-2).reshape(-1, 2, 3),  # along x
        jnp.stack([low, high], axis=-2).reshape(-1, 2, 3),  # along y
        jnp.stack([low[:, :-1], high[:, 1:]], axis=-2).reshape(-1, 2, 3),  # the diagonals
    ])
    start, end = core.edges[:, None, 0], core.edges[:, None, 1]  # (E, 1, 3)
    t0, t1 = terrain[None, :, 0], terrain[None, :, 1]  # (1, T, 3)
    cross2 = lambda u, v: u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]  # noqa: E731
    along, across = end - start, t1 - t0
    denominator = cross2(along, across)
    scale = _safe_norm(along[..., :2]) * _safe_norm(across[..., :2])
    ok = jnp.abs(denominator) > 1e-9 * (scale + _eps(scale.dtype))
    safe = jnp.where(ok, denominator, 1.0)
    s = cross2(t0 - start, across) / safe
    t = cross2(t0 - start, along) / safe
    crossing = ok & (s >= 0) & (s <= 1) & (t >= 0) & (t <= 1)
    p = (start + s[..., None] * along).reshape(-1, 3)
    q = (t0 + t[..., None] * across).reshape(-1, 3)
    crossing = crossing.reshape(-1)
    # the two triangles at the crease: looked up a little to either side of it
    side = jnp.stack([-across[..., 1], across[..., 0], jnp.zeros_like(across[..., 0])], axis=-1)
    side = jnp.broadcast_to(side / (_safe_norm(side)[..., None] + _eps(side.dtype)), s.shape + (3,)).reshape(-1, 3)
    nudge = 1e-6 * jnp.min(field.cell)
    over1, normal1, corner1 = _terrain_under(field, q - nudge * side)
    over2, normal2, corner2 = _terrain_under(field, q + nudge * side)
    height1 = jnp.sum(normal1 * (p - corner1), axis=-1)
    height2 = jnp.sum(normal2 * (p - corner2), axis=-1)
    # a valley where the terrain's slope toward side 2 grows across the crease
    slope1 = -jnp.sum(normal1 * side, axis=-1) / normal1[:, 2]
    slope2 = -jnp.sum(normal2 * side, axis=-1) / normal2[:, 2]
    valley = slope2 > slope1
    first = jnp.where(over1 & over2, jnp.where(valley, height1 <= height2, height1 >= height2), over1)
    height = jnp.where(first, height1, height2)
    normal = jnp.where(first[:, None], normal1, normal2)
    shape_points = (height - core.radius, normal, p - height[:, None] * normal, p - core.radius * normal, crossing & (over1 | over2))
    ridge = slope2 < slope1 - 1e3 * _eps(slope1.dtype) * (1.0 + jnp.abs(slope1))
    gap, peak_normal, point1, point2, valid = _points_in_core(core, q, size)
    return [shape_points, (gap, peak_normal, point1, point2, valid & crossing & ridge & over1 & over2)]


def _heightfield_pair_of(count):
    return lambda s1, p1, s2, p2, margin: _heightfield_pair(s1, p1, s2, p2, margin, count)


def _heightfield_polytope_of(count):
    return lambda s1, p1, s2, p2, margin: _heightfield_polytope(s1, p1, s2, p2, margin, count)


# an inactive entry's distance in the choice of a height field's deepest contacts
_INACTIVE_GAP = 1e10


def _pad(candidate, size):
    condition, normal, point1, point2, distance, valid = candidate
    extra = size - point1.shape[0]
    repeat = lambda a: jnp.concatenate([a, jnp.repeat(a[:1], extra, axis=0)])  # noqa: E731
    return condition, normal, repeat(point1), repeat(point2), repeat(distance), jnp.concatenate([valid, jnp.zeros(extra, bool)])


# --------------------------------------------------------------------------------------
# Dispatch.
# --------------------------------------------------------------------------------------


def _polytope_pair_of(count):
    return lambda s1, p1, s2, p2, margin: _polytope_pair(s1, p1, s2, p2, margin, count)


# (type1, type2) -> (function, manifold size). A pair given in the other order is computed
# in this order and swapped.
_PAIR_FUNCTIONS = {
    (HalfSpace, Sphere): (_halfspace_sphere, 1),
    (HalfSpace, Capsule): (_halfspace_capsule, 2),
    (HalfSpace, Box): (_halfspace_box, 4),
    (HalfSpace, Cylinder): (_halfspace_cylinder, 4),
    (HalfSpace, ConvexMesh): (_halfspace_mesh, 4),
    (Sphere, Sphere): (_sphere_sphere, 1),
    (Sphere, Capsule): (_sphere_capsule, 1),
    (Capsule, Capsule): (_capsule_capsule, 2),
    (Box, Sphere): (_box_sphere, 1),
    (Capsule, Box): (_polytope_pair_of(2), 2),
    (Box, Box): (_polytope_pair_of(4), 4),
    (Sphere, ConvexMesh): (_polytope_pair_of(1), 1),
    (Capsule, ConvexMesh): (_polytope_pair_of(2), 2),
    (Box, ConvexMesh): (_polytope_pair_of(4), 4),
    (ConvexMesh, ConvexMesh): (_polytope_pair_of(4), 4),
    (Sphere, Cylinder): (_polytope_pair_of(1), 1),
    (Capsule, Cylinder): (_polytope_pair_of(2), 2),
    (Box, Cylinder): (_polytope_pair_of(4), 4),
    (Cylinder, Cylinder): (_polytope_pair_of(4), 4),
    (Cylinder, ConvexMesh): (_polytope_pair_of(4), 4),
    (HalfSpace, Ellipsoid): (_halfspace_ellipsoid, 1),
    (Sphere, Ellipsoid): (_polytope_pair_of(1), 1),
    (Capsule, Ellipsoid): (_polytope_pair_of(2), 2),
    (Box, Ellipsoid): (_polytope_pair_of(4), 4),
    (Cylinder, Ellipsoid): (_polytope_pair_of(4), 4),
    (Ellipsoid, Ellipsoid): (_polytope_pair_of(4), 4),
    (Ellipsoid, ConvexMesh): (_polytope_pair_of(4), 4),
    # Height fields: spheres and capsules against the prisms of the cells under them (while
    # their cores are above the terrain the nearest prism's distance is the terrain's); polytope
    # cores against the terrain's surface (_heightfield_polytope: a polytope's overlap with one
    # prism has its smallest way out through the prism's side, inside the terrain).
    (HeightField, Sphere): (_heightfield_pair_of(2), 2),
    (HeightField, Capsule): (_heightfield_pair_of(2), 2),
    (HeightField, Box): (_heightfield_polytope_of(4), 4),
    (HeightField, Cylinder): (_heightfield_polytope_of(4), 4),
    (HeightField, ConvexMesh): (_heightfield_polytope_of(4), 4),
    (HeightField, Ellipsoid): (_heightfield_polytope_of(4), 4),
}


def _lookup(shape1, shape2):
    key = (type(shape1), type(shape2))
    if key in _PAIR_FUNCTIONS:
        return _PAIR_FUNCTIONS[key], False
    if key[::-1] in _PAIR_FUNCTIONS:
        return _PAIR_FUNCTIONS[key[::-1]], True
    supported = ", ".join(f"{a.__name__}-{b.__name__}" for a, b in _PAIR_FUNCTIONS)
    raise NotImplementedError(
        f"no collision function for {key[0].__name__} against {key[1].__name__}; "
        f"supported pairs (either order): {supported}."
    )


def manifold_size(shape1, shape2) -> int:
    """The number of entries ``k`` of the :class:`Contacts` that :func:`collide` returns for
    these shape types (static).

    Example:
        >>> manifold_size(HalfSpace(), Box([1.0, 1.0, 1.0]))
        4
    """
    (_, size), _ = _lookup(shape1, shape2)
    return size


def _check_pose(name: str, pose):
    if not isinstance(pose, (tuple, list)) or len(pose) != 2:
        raise ValueError(f"{name} must be a pair (rotation (3, 3), translation (3,)), got {type(pose).__name__}.")
    rotation, translation = jnp.asarray(pose[0]), jnp.asarray(pose[1])
    if rotation.shape != (3, 3) or translation.shape != (3,):
        raise ValueError(
            f"{name} must be (rotation (3, 3), translation (3,)), got shapes {rotation.shape} and "
            f"{translation.shape}; vmap over poses to batch them."
        )
    dtype = jnp.result_type(rotation, translation, float)
    return rotation.astype(dtype), translation.astype(dtype)


def collide(shape1, pose1, shape2, pose2, *, margin: ArrayLike = 0.0) -> Contacts:
    """Contact manifold between two posed shapes.

    Args:
        shape1, shape2: shapes of :mod:`rsmooth.sim._geometry`; the pair of types must be
            supported (see :func:`manifold_size`; either order).
        pose1, pose2: ``(rotation (3, 3), translation (3,))`` placing each shape in the
            world (``x_world = rotation @ x_local + translation``).
        margin: entries with ``distance <= margin`` are active; a positive margin reports
            contacts before touching.

    Returns:
        :class:`Contacts` of size :func:`manifold_size`, normals from shape 1 to shape 2.

    Raises:
        NotImplementedError: for an unsupported pair of types.
        ValueError: for poses of the wrong shape.

    Example:
        >>> import jax.numpy as jnp
        >>> eye = jnp.eye(3)
        >>> contacts = collide(HalfSpace(), (eye, jnp.zeros(3)),
        ...                    Box([0.5, 0.5, 0.5]), (eye, jnp.array([0.0, 0.0, 0.4])))
        >>> [round(float(d), 6) for d in contacts.distance], contacts.active.tolist()
        ([-0.1, -0.1, -0.1, -0.1], [True, True, True, True])
    """
    (function, _), swap = _lookup(shape1, shape2)
    pose1, pose2 = _check_pose("pose1", pose1), _check_pose("pose2", pose2)
    dtype = jnp.result_type(pose1[0], pose2[0])
    margin = jnp.asarray(margin, dtype)
    if swap:
        return _swapped(function(shape2, pose2, shape1, pose1, margin))
    return function(shape1, pose1, shape2, pose2, margin)


# --------------------------------------------------------------------------------------
# Broad phase.
# --------------------------------------------------------------------------------------


class CandidatePairs(eqx.Module):
    """Pairs of shapes whose bounding volumes overlap, in a fixed-capacity array.

    Attributes:
        pairs: indices ``(i, j)``, ``i < j``, shape ``(capacity, 2)``; unused rows hold
            ``(0, 0)``.
        active: which rows are candidate pairs, bool ``(capacity,)``.
        count: the number of overlapping pairs found (may exceed ``capacity``).
        overflow: ``count > capacity``: some overlapping pairs were left out; raise the
            capacity.
    """

    pairs: Array
    active: Array
    count: Array
    overflow: Array


def candidate_pairs(shapes, poses, *, capacity: int, margin: ArrayLike = 0.0, excluded=()) -> CandidatePairs:
    """Broad phase: the pairs whose bounding spheres (half-spaces: the half-space itself)
    are within ``margin`` of each other.

    The test is over all pairs, ``O(N^2)`` but a few flops each and branch-free, so that the
    costly narrow phase (:func:`collide`) runs only on ``capacity`` pairs.

    Args:
        shapes: a sequence of ``N`` shapes (static: their types and order).
        poses: ``(rotations (N, 3, 3), translations (N, 3))``.
        capacity: the number of rows of the result (static).
        margin: extra distance below which a pair is a candidate.
        excluded: pairs ``(i, j)`` never to report (bodies joined together, two
            half-spaces are always excluded).

    Returns:
        A :class:`CandidatePairs`; rows are in increasing ``(i, j)`` order.

    Example:
        >>> import jax.numpy as jnp
        >>> shapes = [HalfSpace(), Sphere(0.1), Sphere(0.1)]
        >>> poses = (jnp.broadcast_to(jnp.eye(3), (3, 3, 3)),
        ...          jnp.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.05], [5.0, 0.0, 1.0]]))
        >>> found = candidate_pairs(shapes, poses, capacity=2)
        >>> found.pairs[found.active].tolist(), bool(found.overflow)
        ([[0, 1]], False)
    """
    count = len(shapes)
    rotations, translations = jnp.asarray(poses[0]), jnp.asarray(poses[1])
    if rotations.shape != (count, 3, 3) or translations.shape != (count, 3):
        raise ValueError(
            f"poses must be (rotations ({count}, 3, 3), translations ({count}, 3)) for {count} shapes, "
            f"got {rotations.shape} and {translations.shape}."
        )
    if not isinstance(capacity, (int, np.integer)) or capacity < 1:
        raise ValueError(f"capacity must be a positive int, got {capacity!r}.")
    excluded = {tuple(sorted(map(int, pair))) for pair in excluded}
    planes = [isinstance(shape, HalfSpace) for shape in shapes]
    index = [
        (i, j)
        for i, j in itertools.combinations(range(count), 2)
        if (i, j) not in excluded and not (planes[i] and planes[j])
    ]
    if not index:
        empty = jnp.zeros((capacity, 2), jnp.int32)
        return CandidatePairs(empty, jnp.zeros(capacity, bool), jnp.zeros((), jnp.int32), jnp.zeros((), bool))
    index = np.array(index)
    dtype = translations.dtype
    radii = jnp.stack([jnp.zeros((), dtype) if plane else jnp.asarray(s.bounding_radius, dtype) for s, plane in zip(shapes, planes)])
    first, second = index[:, 0], index[:, 1]
    plane_first = jnp.asarray(np.array(planes)[first])
    plane_second = jnp.asarray(np.array(planes)[second])
    gap_spheres = _safe_norm(translations[second] - translations[first]) - radii[first] - radii[second]
    # A bounding sphere against a half-space: the height of its centre above the plane.
    height_first_plane = jnp.sum((translations[second] - translations[first]) * rotations[first][:, :, 2], axis=-1) - radii[second]
    height_second_plane = jnp.sum((translations[first] - translations[second]) * rotations[second][:, :, 2], axis=-1) - radii[first]
    gaps = jnp.where(plane_first, height_first_plane, jnp.where(plane_second, height_second_plane, gap_spheres))
    overlapping = gaps <= margin
    found = jnp.sum(overlapping.astype(jnp.int32))
    (rows,) = jnp.nonzero(overlapping, size=capacity, fill_value=index.shape[0])
    padded = jnp.concatenate([jnp.asarray(index, jnp.int32), jnp.zeros((1, 2), jnp.int32)])
    return CandidatePairs(padded[rows], rows < index.shape[0], found, found > capacity)
