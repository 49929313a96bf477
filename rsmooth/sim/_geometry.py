"""Collision shapes: spheres, capsules, boxes, cylinders, ellipsoids, half-spaces and convex meshes.

Each shape is a frozen :class:`equinox.Module` in its own local frame; its array fields are
traced (so shapes can be batched, differentiated and built inside ``jit``) and checked on the
host when they are concrete. A shape is placed in the world by a pose
``(rotation (3, 3), translation (3,))`` mapping local to world coordinates,
``x_world = rotation @ x_local + translation`` (as :mod:`rsmooth.sim._spatial`).

Conventions follow MuJoCo's geoms so that sizes carry over: the axis of a capsule and of a
cylinder is the local ``z`` axis, ``half_length`` is half the length of that axis (of the
cylindrical part, for a capsule), and a :class:`HalfSpace` is the solid ``z <= 0`` of its
frame, whose boundary plane has the outward normal ``+z`` (MuJoCo's plane).

For the narrow phase (:mod:`rsmooth.sim._collision`) every bounded shape is described by a
*core* and a *radius*: the shape is the core dilated by a ball of that radius (a sphere is a
point dilated, a capsule a segment dilated; boxes, cylinders, ellipsoids and meshes have radius 0). The
core's support function, ``argmax_{x in core} x . d``, is all that the generic distance
algorithm needs.
"""

from __future__ import annotations

import os
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

Array = jax.Array

__all__ = [
    "Box",
    "Capsule",
    "ConvexMesh",
    "Cylinder",
    "Ellipsoid",
    "HalfSpace",
    "HeightField",
    "NonConvexMeshWarning",
    "Sphere",
    "convex_mesh",
]


def _as_float(value: ArrayLike) -> Array:
    value = jnp.asarray(value)
    if not jnp.issubdtype(value.dtype, jnp.floating):
        value = value.astype(jnp.result_type(float))
    return value


def _is_concrete(value) -> bool:
    return not isinstance(value, jax.core.Tracer)


def _check(name: str, value: Array, shape: tuple[int, ...], *, positive: bool = True) -> None:
    """Host check of a size field: its shape, and when concrete, finite (and positive)."""
    if value.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {value.shape}.")
    if _is_concrete(value):
        array = np.asarray(value)
        if not np.all(np.isfinite(array)):
            raise ValueError(f"{name} must be finite, got {array}.")
        if positive and not np.all(array > 0):
            raise ValueError(f"{name} must be positive (in (0, inf)), got {array}.")


def _safe_normalize(vector: Array, fallback: Array) -> tuple[Array, Array]:
    """``vector / |vector|`` over the last axis, ``fallback`` where it is 0 (NaN-free in
    value and derivative); also returns the norm."""
    from rsmooth.sim._contact import _safe_norm

    norm = _safe_norm(vector)
    nonzero = norm > 0
    unit = vector / jnp.where(nonzero, norm, 1.0)[..., None]
    return jnp.where(nonzero[..., None], unit, fallback), norm


class Sphere(eqx.Module):
    """A ball of radius ``radius`` centred at the origin of its frame (radius 0: a point).

    Attributes:
        radius: non-negative scalar.

    Example:
        >>> float(Sphere(0.5).bounding_radius)
        0.5
    """

    radius: Array = eqx.field(converter=_as_float)

    def __check_init__(self):
        _check("radius", self.radius, (), positive=False)
        if _is_concrete(self.radius) and not float(self.radius) >= 0:
            raise ValueError(f"radius must be non-negative (0: a point), got {float(self.radius)}.")

    @property
    def core_radius(self) -> Array:
        return self.radius

    def support_core(self, direction: Array) -> Array:
        """The core (the centre) has itself as support point in every direction."""
        return jnp.zeros_like(direction)

    @property
    def bounding_radius(self) -> Array:
        """Radius of the smallest ball about the frame's origin that contains the shape."""
        return self.radius


class Capsule(eqx.Module):
    """A segment along local ``z`` from ``-half_length`` to ``half_length``, dilated by
    ``radius`` (MuJoCo's capsule).

    Attributes:
        radius: positive scalar.
        half_length: positive scalar, half the length of the cylindrical part.
    """

    radius: Array = eqx.field(converter=_as_float)
    half_length: Array = eqx.field(converter=_as_float)

    def __check_init__(self):
        _check("radius", self.radius, ())
        _check("half_length", self.half_length, ())

    @property
    def core_radius(self) -> Array:
        return self.radius

    def support_core(self, direction: Array) -> Array:
        z = jnp.where(direction[..., 2] >= 0, self.half_length, -self.half_length)
        zeros = jnp.zeros_like(z)
        return jnp.stack([zeros, zeros, z], axis=-1)

    @property
    def bounding_radius(self) -> Array:
        return self.radius + self.half_length


class Box(eqx.Module):
    """The box ``|x_i| <= half_extents[i]`` (MuJoCo's box ``size``).

    Attributes:
        half_extents: positive, shape ``(3,)``.
    """

    half_extents: Array = eqx.field(converter=_as_float)

    def __check_init__(self):
        _check("half_extents", self.half_extents, (3,))

    @property
    def core_radius(self) -> Array:
        return jnp.zeros((), self.half_extents.dtype)

    def support_core(self, direction: Array) -> Array:
        return jnp.where(direction >= 0, self.half_extents, -self.half_extents)

    @property
    def bounding_radius(self) -> Array:
        return jnp.sqrt(jnp.sum(self.half_extents**2))

    def corners(self) -> Array:
        """The 8 corners in the local frame, shape ``(8, 3)``; corner ``i`` has the sign
        ``-`` on axis ``j`` where bit ``j`` of ``i`` is set."""
        signs = 1.0 - 2.0 * ((np.arange(8)[:, None] >> np.arange(3)[None, :]) & 1)
        return jnp.asarray(signs, self.half_extents.dtype) * self.half_extents[None, :]


class Cylinder(eqx.Module):
    """A solid cylinder of axis local ``z``: ``x^2 + y^2 <= radius^2``,
    ``|z| <= half_length`` (MuJoCo's cylinder).

    Attributes:
        radius: positive scalar.
        half_length: positive scalar.
    """

    radius: Array = eqx.field(converter=_as_float)
    half_length: Array = eqx.field(converter=_as_float)

    def __check_init__(self):
        _check("radius", self.radius, ())
        _check("half_length", self.half_length, ())

    @property
    def core_radius(self) -> Array:
        return jnp.zeros((), self.radius.dtype)

    def support_core(self, direction: Array) -> Array:
        # Along the axis the support is flat: any point of a cap's disc. For a direction with
        # no radial part the centre of the cap is returned (the fallback of the normalize).
        radial, _ = _safe_normalize(
            direction.at[..., 2].set(0.0), jnp.zeros_like(direction)
        )
        z = jnp.where(direction[..., 2] >= 0, self.half_length, -self.half_length)
        return (self.radius * radial).at[..., 2].set(z)

    @property
    def bounding_radius(self) -> Array:
        return jnp.sqrt(self.radius**2 + self.half_length**2)


class Ellipsoid(eqx.Module):
    """A solid ellipsoid ``(x / a)^2 + (y / b)^2 + (z / c)^2 <= 1`` of semi-axes
    ``radii = (a, b, c)`` along its frame's axes (MuJoCo's ellipsoid).

    Attributes:
        radii: ``(3,)``, positive.
    """

    radii: Array = eqx.field(converter=_as_float)

    def __check_init__(self):
        _check("radii", self.radii, (3,))

    @property
    def core_radius(self) -> Array:
        return jnp.zeros((), self.radii.dtype)

    def support_core(self, direction: Array) -> Array:
        """``diag(r)^2 d / |diag(r) d|``: the boundary point whose outward normal is ``d``."""
        from rsmooth.sim._contact import _safe_norm

        scaled = self.radii * direction
        return self.radii * scaled / jnp.maximum(_safe_norm(scaled), jnp.finfo(scaled.dtype).tiny)[..., None]

    @property
    def bounding_radius(self) -> Array:
        return jnp.max(self.radii)


class HalfSpace(eqx.Module):
    """The half-space ``z <= 0`` of its frame; its boundary plane has outward normal ``+z``
    (MuJoCo's plane, infinite for collision). It has no fields: place it with its pose."""

    @property
    def bounding_radius(self) -> Array:
        return jnp.asarray(jnp.inf)


class HeightField(eqx.Module):
    """A height field (MuJoCo's hfield): the solid under the surface of heights ``heights``
    ``(R, C)`` (m) on a grid of ``x`` from ``-half_size[0]`` to ``half_size[0]`` (columns) and
    ``y`` from ``-half_size[1]`` to ``half_size[1]`` (rows), down to ``z = -base``. Each grid
    cell is two triangles (MuJoCo's: split along the diagonal from ``(row, column)`` to ``(row +
    1, column + 1)``), each the top of a vertical prism, which a sphere or a capsule collides with
    as a convex polytope; a box, a cylinder, a convex mesh or an ellipsoid collides with the
    triangles' surface.

    Attributes:
        heights: ``(R, C)``, ``R, C >= 2``.
        half_size: ``(2,)``, positive.
        base: positive scalar, the depth of the solid below ``z = 0``.
        window: the cells per side of the square of cells a shape is collided with (static):
            at least its bounding diameter in cells plus one, so that the square from the cell
            under its bounding sphere's corner holds it (:func:`~rsmooth.sim.scene` sets it per
            pair); the square is clipped to the grid.
    """

    heights: Array = eqx.field(converter=_as_float)
    half_size: Array = eqx.field(converter=_as_float)
    base: Array = eqx.field(converter=_as_float)
    window: int = eqx.field(static=True, default=2)

    def __check_init__(self):
        if self.heights.ndim != 2 or min(self.heights.shape) < 2:
            raise ValueError(f"heights must have shape (R, C) with R, C >= 2, got {self.heights.shape}.")
        _check("heights", self.heights, self.heights.shape, positive=False)
        _check("half_size", self.half_size, (2,))
        _check("base", self.base, ())
        if isinstance(self.window, bool) or not isinstance(self.window, int) or self.window < 1:
            raise ValueError(f"window must be an int >= 1, got {self.window!r}.")

    @property
    def cell(self) -> Array:
        """The cells' sides ``(dx, dy)`` (m)."""
        rows, columns = self.heights.shape
        return 2.0 * self.half_size / jnp.asarray([columns - 1, rows - 1], self.half_size.dtype)

    @property
    def bounding_radius(self) -> Array:
        depth = jnp.maximum(jnp.max(jnp.abs(self.heights)), self.base)
        return jnp.sqrt(jnp.sum(self.half_size**2) + depth**2)


class ConvexMesh(eqx.Module):
    """A convex polytope, as the collision code needs it.

    Build one with :func:`convex_mesh`, which takes the convex hull and fills every field.

    Attributes:
        vertices: the hull's vertices, shape ``(V, 3)``, ``V >= 4``.
        face_normals: outward unit normals of the hull's faces, ``(F, 3)``; coplanar
            triangles are merged, so each plane appears once.
        face_offsets: ``face_normals[f] . x <= face_offsets[f]`` inside, shape ``(F,)``.
        face_polygons: each face's vertices in counter-clockwise order about its normal,
            padded to the largest face by repeating the last vertex, ``(F, P, 3)``.
        edge_segments: the hull's edges (not the diagonals of its triangulated faces) as
            end points, ``(M, 2, 3)``.
        edge_directions: unit directions of the hull's edges, one per direction up to
            sign, shape ``(E, 3)``.
        edge_normals: outward unit normals of the two faces that meet at each of
            ``edge_segments``, ``(M, 2, 3)``: the arcs of the hull's Gauss map, which let the
            separating-axis test of two meshes keep only the edge pairs that can separate
            them (``O(M1 M2)`` instead of ``O(M1 M2 (V1 + V2))``).
    """

    vertices: Array = eqx.field(converter=_as_float)
    face_normals: Array = eqx.field(converter=_as_float)
    face_offsets: Array = eqx.field(converter=_as_float)
    face_polygons: Array = eqx.field(converter=_as_float)
    edge_segments: Array = eqx.field(converter=_as_float)
    edge_directions: Array = eqx.field(converter=_as_float)
    edge_normals: Array = eqx.field(converter=_as_float)

    def __check_init__(self):
        if self.vertices.ndim != 2 or self.vertices.shape[1] != 3 or self.vertices.shape[0] < 4:
            raise ValueError(f"vertices must have shape (V, 3) with V >= 4, got {self.vertices.shape}.")
        faces = self.face_normals.shape[:1]
        _check("face_normals", self.face_normals, faces + (3,), positive=False)
        _check("face_offsets", self.face_offsets, faces, positive=False)
        _check("vertices", self.vertices, self.vertices.shape, positive=False)
        if self.face_polygons.ndim != 3 or self.face_polygons.shape[::2] != (faces[0], 3):
            raise ValueError(f"face_polygons must have shape ({faces[0]}, P, 3), got {self.face_polygons.shape}.")
        if self.edge_segments.ndim != 3 or self.edge_segments.shape[1:] != (2, 3):
            raise ValueError(f"edge_segments must have shape (M, 2, 3), got {self.edge_segments.shape}.")
        if self.edge_normals.shape != self.edge_segments.shape:
            raise ValueError(
                f"edge_normals must have the shape of edge_segments {self.edge_segments.shape}, got {self.edge_normals.shape}."
            )
        if self.edge_directions.ndim != 2 or self.edge_directions.shape[1] != 3:
            raise ValueError(
                f"edge_directions must have shape (E, 3), got {self.edge_directions.shape}."
            )

    @property
    def core_radius(self) -> Array:
        return jnp.zeros((), self.vertices.dtype)

    def support_core(self, direction: Array) -> Array:
        scores = self.vertices @ direction
        return self.vertices[jnp.argmax(scores)]

    @property
    def bounding_radius(self) -> Array:
        return jnp.sqrt(jnp.max(jnp.sum(self.vertices**2, axis=-1)))


# The axes of a ConvexMesh's arrays that count entries (the others are coordinates, or an
# edge's two ends): the axes padded_meshes pads.
_MESH_COUNT_AXES = {"vertices": (0,), "face_normals": (0,), "face_offsets": (0,), "face_polygons": (0, 1),
                    "edge_segments": (0,), "edge_directions": (0,), "edge_normals": (0,)}


def padded_meshes(meshes, minimum: int = 0) -> list[ConvexMesh]:
    """The meshes with their arrays padded to common shapes: along each axis that counts
    entries (vertices, faces, a face's polygon, edges with their faces' normals, edge
    directions), entries repeated from the last one up to the largest count among ``meshes``,
    and at least ``minimum``. To the collision code each is the same polytope as before, since
    its supports, separating axes, clipping and manifold reduction take maxima and minima over
    these entries, where a first occurrence wins a tie (a repeated polygon vertex is a
    zero-length side, already how polygons of fewer vertices are stored); stacked, they go
    through one ``vmap``-ed collision."""
    meshes = list(meshes)
    if not meshes or not all(isinstance(mesh, ConvexMesh) for mesh in meshes):
        raise TypeError("padded_meshes takes a non-empty sequence of ConvexMesh.")

    def pad(array, axis, count):
        have = array.shape[axis]
        if count <= have:
            return array
        return jnp.concatenate([array, jnp.take(array, jnp.full(count - have, have - 1), axis=axis)], axis=axis)

    padded = []
    for mesh in meshes:
        fields = {}
        for name, axes in _MESH_COUNT_AXES.items():
            array = getattr(mesh, name)
            for axis in axes:
                array = pad(array, axis, max([minimum] + [getattr(other, name).shape[axis] for other in meshes]))
            fields[name] = array
        padded.append(ConvexMesh(**fields))
    return padded


class NonConvexMeshWarning(UserWarning):
    """The mesh given to :func:`convex_mesh` was not convex; its convex hull is used."""


def _first_of_each_group(vectors: np.ndarray, same) -> np.ndarray:
    """The vectors, in order, that are not ``same`` as one kept before them (greedy); ``same``
    maps ``(vector, vectors)`` to a boolean mask. One vectorized test per kept vector, so that
    hulls of thousands of faces are reduced in milliseconds."""
    dropped = np.zeros(len(vectors), dtype=bool)
    kept = []
    for index, vector in enumerate(vectors):
        if not dropped[index]:
            kept.append(index)
            dropped[index + 1 :] |= same(vector, vectors[index + 1 :])
    return vectors[kept]


def _unique_directions(directions: np.ndarray, tolerance: float) -> np.ndarray:
    """Unit directions, one per line through the origin (``d`` and ``-d`` are the same)."""
    directions = np.asarray(directions, dtype=float).reshape(-1, 3)
    return _first_of_each_group(directions, lambda d, others: np.abs(np.abs(others @ d) - 1.0) <= tolerance)


def convex_mesh(source) -> ConvexMesh:
    """Builds a :class:`ConvexMesh` from a file, a ``trimesh.Trimesh`` or a vertex array.

    The convex hull of the points is taken (host-side, with ``trimesh``); coplanar hull
    triangles are merged into one face normal, and edge directions are deduplicated, so a
    box gives 6 faces and 3 edge directions.

    Args:
        source: a path to an STL, OBJ or PLY file (anything ``trimesh.load`` reads as one
            mesh), a ``trimesh.Trimesh``, or an array of vertices of shape ``(V, 3)``.

    Returns:
        The :class:`ConvexMesh` of the hull, in the coordinates of ``source``.

    Raises:
        ValueError: for a missing or unreadable file, an array of the wrong shape or with
            non-finite values, or fewer than 4 points not all in one plane.

    Warns:
        NonConvexMeshWarning: when a mesh (file or ``Trimesh``) is not convex.

    Example:
        >>> import numpy as np
        >>> corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)])
        >>> mesh = convex_mesh(corners)
        >>> mesh.vertices.shape, mesh.face_normals.shape, mesh.edge_directions.shape
        ((8, 3), (6, 3), (3, 3))
    """
    import trimesh

    name = "source"
    mesh = None
    if isinstance(source, (str, os.PathLike)):
        name = f"mesh file {os.fspath(source)!r}"
        if not os.path.isfile(source):
            raise ValueError(f"{name} does not exist.")
        try:
            loaded = trimesh.load(source, force="mesh")
        except Exception as error:  # trimesh raises many types for a bad file
            raise ValueError(f"{name} could not be read as a mesh: {error}") from error
        if not isinstance(loaded, trimesh.Trimesh) or len(loaded.vertices) == 0:
            raise ValueError(f"{name} could not be read as a mesh (no vertices found).")
        mesh = loaded
    elif isinstance(source, trimesh.Trimesh):
        mesh = source
    if mesh is not None:
        points = np.asarray(mesh.vertices, dtype=float)
        if len(mesh.faces) and not mesh.is_convex:
            warnings.warn(
                f"{name} is not convex; its convex hull is used.", NonConvexMeshWarning, stacklevel=2
            )
    else:
        points = np.asarray(source, dtype=float)
        if points.ndim != 2 or points.shape[1] != 3:
            raise ValueError(f"source vertices must have shape (V, 3), got {points.shape}.")
    if not np.all(np.isfinite(points)):
        raise ValueError(f"{name} has non-finite vertices.")
    centred = points - points.mean(axis=0)
    scale = max(float(np.abs(centred).max(initial=0.0)), 1e-300)
    if len(points) < 4 or np.linalg.matrix_rank(centred / scale, tol=1e-9) < 3:
        raise ValueError(
            f"{name} needs at least 4 points not all in one plane, got {len(points)} points "
            "spanning fewer than 3 dimensions."
        )
    hull = trimesh.convex.convex_hull(points)
    vertices = np.asarray(hull.vertices, dtype=float)
    normals = _unique_normals(np.asarray(hull.face_normals, dtype=float))
    offsets = np.max(vertices @ normals.T, axis=0)
    size = float(np.abs(vertices - vertices.mean(axis=0)).max())
    polygons = [_face_polygon(vertices, normal, offset, 1e-6 * size) for normal, offset in zip(normals, offsets)]
    largest = max(len(polygon) for polygon in polygons)
    polygons = np.stack([np.concatenate([p, np.repeat(p[-1:], largest - len(p), axis=0)]) for p in polygons])
    # Edges between two faces that are not coplanar: the diagonals of a triangulated face
    # are no edges of the polytope and would only add useless separating axes.
    real = hull.face_adjacency_angles > 1e-9
    segments = vertices[hull.face_adjacency_edges[real]]
    edge_normals = np.asarray(hull.face_normals, dtype=float)[hull.face_adjacency[real]]  # (M, 2, 3)
    directions = segments[:, 1] - segments[:, 0]
    directions = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    return ConvexMesh(vertices, normals, offsets, polygons, segments, _unique_directions(directions, 1e-9), edge_normals)


def _face_polygon(vertices: np.ndarray, normal: np.ndarray, offset: float, tolerance: float) -> np.ndarray:
    """The hull vertices on the plane ``normal . x = offset``, counter-clockwise about it."""
    on_plane = vertices[np.abs(vertices @ normal - offset) <= tolerance]
    centre = on_plane.mean(axis=0)
    tangent = on_plane[0] - centre
    tangent /= np.linalg.norm(tangent)
    bitangent = np.cross(normal, tangent)
    angles = np.arctan2((on_plane - centre) @ bitangent, (on_plane - centre) @ tangent)
    return on_plane[np.argsort(angles)]


def _unique_normals(normals: np.ndarray) -> np.ndarray:
    return _first_of_each_group(np.asarray(normals, dtype=float), lambda n, others: others @ n >= 1.0 - 1e-9)
