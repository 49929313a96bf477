r"""Triangle meshes: the `Mesh` pytree, file loading (trimesh), primitives and regularizers.

A `Mesh` is checked once on the host when it is built from concrete arrays (finite vertices,
integer faces in range, no degenerate face, not empty); inside `jit`/`vmap`/`grad` its arrays
are traced and not checked again. Geometry that changes during optimization is best kept
outside the mesh (a pose, a vertex offset) and applied with :func:`transform_mesh` or
``eqx.tree_at``.

The regularizers used for mesh reconstruction (Kato et al. / SoftRas, PyTorch3D) act on the
vertices given concrete faces, whose topology (edges, neighbouring faces) is computed on the
host: close over the faces, differentiate with respect to the vertices.

Example:
    >>> from rsmooth.render import icosphere
    >>> mesh = icosphere(subdivisions=1)
    >>> mesh.vertices.shape, mesh.faces.shape
    ((42, 3), (80, 3))
"""

from __future__ import annotations

import codecs
import io
import os
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.typing import ArrayLike

from rsmooth._xla import matmul as _matmul

__all__ = [
    "Mesh",
    "load_mesh",
    "icosphere",
    "box",
    "cube",
    "torus",
    "cylinder",
    "transform_mesh",
    "face_normals",
    "position_colors",
    "laplacian_loss",
    "edge_length_loss",
    "normal_consistency_loss",
]


def _is_concrete(*arrays) -> bool:
    return not any(isinstance(a, jax.core.Tracer) for a in arrays)


def _validate(vertices, faces, colors) -> None:
    """Host checks of a concrete mesh; raises ValueError with what is wrong and where."""
    v = np.asarray(vertices)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"vertices must have shape (V, 3), got {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3:
        raise ValueError(f"faces must have shape (F, 3), got {f.shape}")
    if v.shape[0] == 0 or f.shape[0] == 0:
        raise ValueError(f"empty mesh: {v.shape[0]} vertices and {f.shape[0]} faces")
    if not np.issubdtype(f.dtype, np.integer):
        raise ValueError(f"faces must hold integer vertex indices, got dtype {f.dtype}")
    if not np.all(np.isfinite(v)):
        bad = np.flatnonzero(~np.all(np.isfinite(v), axis=1))
        raise ValueError(f"vertices must be finite: {bad.size} contain NaN or inf (first: vertex {bad[0]})")
    out = (f < 0) | (f >= v.shape[0])
    if np.any(out):
        row = int(np.flatnonzero(np.any(out, axis=1))[0])
        raise ValueError(f"face index out of range [0, {v.shape[0]}): face {row} is {f[row].tolist()}")
    repeated = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2])
    tri = v[f]
    area2 = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    scale = float(np.max(np.ptp(v, axis=0))) if v.shape[0] > 1 else 0.0
    flat = area2 <= 1e-12 * max(scale, 1e-300) ** 2
    degenerate = repeated | flat
    if np.any(degenerate):
        row = int(np.flatnonzero(degenerate)[0])
        raise ValueError(
            f"{int(degenerate.sum())} degenerate face(s) (repeated vertex or zero area); "
            f"first: face {row} = {f[row].tolist()}"
        )
    if colors is not None:
        c = np.asarray(colors)
        if c.shape != v.shape:
            raise ValueError(f"colors must have the shape of vertices {v.shape}, got {c.shape}")
        if not np.all(np.isfinite(c)):
            raise ValueError("colors must be finite")


class Mesh(eqx.Module):
    """A triangle mesh.

    Attributes:
        vertices: (V, 3) floating positions.
        faces: (F, 3) integer vertex indices, counter-clockwise seen from outside for primitives
            (shading is two-sided, so orientation only matters to the normal-consistency term).
        colors: (V, 3) per-vertex RGB albedo in [0, 1], or None (uniform light grey).

    Raises:
        ValueError: built from concrete arrays that are empty, not finite, out of range or
            degenerate (see the message).
    """

    vertices: Array
    faces: Array
    colors: Array | None = None

    def __init__(self, vertices: ArrayLike, faces: ArrayLike, colors: ArrayLike | None = None):
        if _is_concrete(vertices, faces, colors):
            _validate(vertices, faces, colors)
        vertices = jnp.asarray(vertices)
        if not jnp.issubdtype(vertices.dtype, jnp.floating):
            vertices = vertices.astype(float)
        self.vertices = vertices
        self.faces = jnp.asarray(faces, jnp.int32)
        self.colors = None if colors is None else jnp.asarray(colors, vertices.dtype)

    @property
    def num_faces(self) -> int:
        return self.faces.shape[0]

    def albedo(self) -> Array:
        """Per-vertex colours, light grey when the mesh has none."""
        if self.colors is None:
            return jnp.full(self.vertices.shape, 0.8, self.vertices.dtype)
        return self.colors


def transform_mesh(mesh: Mesh, rotation: ArrayLike, translation: ArrayLike | None = None) -> Mesh:
    """The mesh moved rigidly: v -> R v + t (works under jit/grad; no re-validation)."""
    vertices = _matmul(mesh.vertices, jnp.asarray(rotation).T)
    if translation is not None:
        vertices = vertices + jnp.asarray(translation)[None, :]
    return eqx.tree_at(lambda m: m.vertices, mesh, vertices)


def position_colors(mesh: Mesh) -> Mesh:
    """The mesh with each vertex coloured by its position in the bounding box (x, y, z -> R, G, B).

    Gives every part of a symmetric shape (a cube, a sphere) a distinct colour, so that its
    pose can be read from an image.
    """
    v = np.asarray(mesh.vertices)
    low, high = v.min(axis=0), v.max(axis=0)
    colors = 0.15 + 0.8 * (v - low) / np.maximum(high - low, 1e-12)
    return Mesh(mesh.vertices, mesh.faces, colors)


def is_closed_outward(mesh: Mesh) -> bool:
    """True when the mesh is watertight, consistently wound and encloses a positive volume
    (trimesh's tests): its faces seen from behind are then always hidden, and renderers may
    cull them (``Renderer(cull_backfaces=True)``). Needs concrete (not traced) arrays.

    Example:
        >>> is_closed_outward(cube(1.0)), is_closed_outward(Mesh(cube(1.0).vertices, cube(1.0).faces[:, ::-1]))
        (True, False)
    """
    import trimesh

    tm = trimesh.Trimesh(np.asarray(mesh.vertices), np.asarray(mesh.faces), process=False)
    return bool(tm.is_watertight and tm.is_winding_consistent and tm.volume > 0)


def _from_trimesh(tm, name: str) -> Mesh:
    vertices = np.asarray(tm.vertices, float)
    faces = np.asarray(tm.faces, np.int64)
    colors = None
    visual = getattr(tm, "visual", None)
    if visual is not None and getattr(visual, "kind", None) == "vertex":
        rgba = np.asarray(visual.vertex_colors)
        if rgba.shape[0] == vertices.shape[0]:
            colors = rgba[:, :3].astype(float) / 255.0
    try:
        return Mesh(vertices, faces, colors)
    except ValueError as error:
        raise ValueError(f"{name}: {error}") from None


# Mesh formats that are text throughout: read and decoded here (see _load_trimesh).
_TEXT_FORMATS = ("obj", "off")


class _Unparseable(Exception):
    """A mesh file that is not what its suffix says (the message says why)."""


def _looks_binary(data: bytes) -> bool:
    """Whether `data` is binary rather than text: a NUL byte, or more than 10 % of control
    bytes other than whitespace, in its first 8 KiB."""
    head = data[:8192]
    if b"\0" in head:
        return True
    control = sum(byte < 32 and byte not in b"\t\n\r\f\v" for byte in head)
    return control > 0.1 * max(len(head), 1)


def _load_trimesh(trimesh, path: Path):
    """``trimesh.load`` of the file, with the text formats (OBJ, OFF) decoded here: trimesh
    guesses the encoding of text that is not UTF-8 with the optional `charset_normalizer`,
    and without it fails on a valid file with, say, a Latin-1 comment. Such a file is read as
    UTF-16 if it starts with its byte-order mark, else as Latin-1 (every byte is a character;
    the numbers and keywords are ASCII in any 8-bit encoding)."""
    file_type = path.suffix.lower().lstrip(".")
    if file_type not in _TEXT_FORMATS:
        return trimesh.load(path, force="mesh", process=True)
    data = path.read_bytes()
    try:
        data.decode("utf-8")
    except UnicodeDecodeError:
        pass
    else:
        return trimesh.load(path, force="mesh", process=True)
    if data.startswith((codecs.BOM_UTF16_LE, codecs.BOM_UTF16_BE)):
        try:
            text = data.decode("utf-16")
        except UnicodeDecodeError:
            raise _Unparseable(f"it is not {file_type.upper()} text (it starts as UTF-16 but does not decode)") from None
    elif _looks_binary(data):
        raise _Unparseable(f"it holds binary data, not {file_type.upper()} text")
    else:
        text = data.decode("latin-1")
    # The resolver finds the files the mesh refers to (an OBJ's materials) beside it.
    resolver = trimesh.resolvers.FilePathResolver(path)
    return trimesh.load(io.BytesIO(text.encode("utf-8")), file_type=file_type, resolver=resolver, force="mesh", process=True)


def load_mesh(path: str | os.PathLike, *, normalize: bool = False) -> Mesh:
    """Reads a triangle mesh (OBJ, STL, PLY, OFF, GLB; DAE when `pycollada` is installed).

    Scenes with several meshes are concatenated; polygons are triangulated; degenerate and
    duplicate faces are removed (trimesh's processing).

    Args:
        path: the file.
        normalize: centre the mesh at the origin and scale it into the unit ball.

    Returns:
        A :class:`Mesh` (with per-vertex colours when the file has them).

    Raises:
        ValueError: the file does not exist, cannot be parsed, or holds no triangles; the
            message names the path.
    """
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"mesh file not found: {path}")
    try:
        tm = _load_trimesh(trimesh, path)
    except _Unparseable as error:
        raise ValueError(f"cannot parse mesh file {path}: {error}") from None
    except ImportError as error:
        if error.name != "charset_normalizer":  # a reader's own package (pycollada for DAE): say which
            raise ValueError(f"cannot parse mesh file {path}: {type(error).__name__}: {error}") from None
        # trimesh's last resort on bytes that are neither its binary format nor UTF-8 text
        raise ValueError(f"cannot parse mesh file {path}: not a valid {path.suffix.upper()[1:]} file (nor UTF-8 text)") from None
    except Exception as error:  # trimesh raises many types for bad files
        raise ValueError(f"cannot parse mesh file {path}: {type(error).__name__}: {error}") from None
    if not isinstance(tm, trimesh.Trimesh) or len(tm.faces) == 0:
        raise ValueError(f"mesh file {path} holds no triangles")
    tm.update_faces(tm.nondegenerate_faces())
    tm.remove_unreferenced_vertices()
    if len(tm.faces) == 0:
        raise ValueError(f"mesh file {path} holds only degenerate triangles")
    if normalize:
        tm.apply_translation(-tm.bounds.mean(axis=0))
        tm.apply_scale(1.0 / max(float(np.linalg.norm(tm.vertices, axis=1).max()), 1e-12))
    return _from_trimesh(tm, str(path))


def icosphere(subdivisions: int = 2, radius: float = 1.0) -> Mesh:
    """A geodesic sphere with 20 * 4**subdivisions faces (1280 for 3, 20480 for 5)."""
    import trimesh

    return _from_trimesh(trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius), "icosphere")


def box(extents=(1.0, 1.0, 1.0)) -> Mesh:
    """An axis-aligned box centred at the origin (12 faces)."""
    import trimesh

    return _from_trimesh(trimesh.creation.box(extents=extents), "box")


def cube(size: float = 1.0) -> Mesh:
    """A cube of side `size` centred at the origin (12 faces)."""
    return box((size, size, size))


def torus(major_radius: float = 1.0, minor_radius: float = 0.35, major_sections: int = 32, minor_sections: int = 16) -> Mesh:
    """A torus around the z axis (2 * major_sections * minor_sections faces)."""
    import trimesh

    tm = trimesh.creation.torus(
        major_radius=major_radius, minor_radius=minor_radius,
        major_sections=major_sections, minor_sections=minor_sections,
    )
    return _from_trimesh(tm, "torus")


def cylinder(radius: float = 0.5, height: float = 1.0, sections: int = 32) -> Mesh:
    """A closed cylinder along the z axis, centred at the origin."""
    import trimesh

    return _from_trimesh(trimesh.creation.cylinder(radius=radius, height=height, sections=sections), "cylinder")


def face_normals(vertices: ArrayLike, faces: ArrayLike) -> Array:
    """Unit normals (F, 3) of the faces, by the right-hand rule on (v0, v1, v2)."""
    tri = jnp.asarray(vertices)[jnp.asarray(faces)]
    n = jnp.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norm = jnp.sqrt(jnp.maximum(jnp.sum(n**2, axis=-1, keepdims=True), 1e-30))
    return n / norm


def _concrete_faces(faces) -> np.ndarray:
    if isinstance(faces, jax.core.Tracer):
        raise TypeError("faces must be concrete (close over the mesh's faces; differentiate the vertices)")
    return np.asarray(faces)


def _edges(faces: np.ndarray) -> np.ndarray:
    """Unique undirected edges (E, 2)."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    return np.unique(np.sort(e, axis=1), axis=0)


def _face_pairs(faces: np.ndarray) -> np.ndarray:
    """Pairs of faces (P, 2) sharing an edge (edges with exactly two faces)."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    owner = np.tile(np.arange(faces.shape[0]), 3)
    _, inverse, counts = np.unique(np.sort(e, axis=1), axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    # Keep only edges shared by exactly two faces (manifold edges).
    keep = np.flatnonzero(counts[inverse] == 2)
    keep = keep[np.argsort(inverse[keep], kind="stable")]
    return owner[keep].reshape(-1, 2)


def laplacian_loss(vertices: ArrayLike, faces: ArrayLike) -> Array:
    r"""Uniform Laplacian smoothing term: the mean of :math:`\|v_i - \frac{1}{|N_i|}\sum_{j\in N_i} v_j\|^2`.

    Args:
        vertices: (V, 3), may be traced.
        faces: (F, 3) concrete indices.

    References:
        Nealen et al., "Laplacian mesh optimization", GRAPHITE 2006; as used by Kato et al. /
        Liu et al. (SoftRas, ICCV 2019) for reconstruction.
    """
    edges = _edges(_concrete_faces(faces))
    v = jnp.asarray(vertices)
    n = v.shape[0]
    i = np.concatenate([edges[:, 0], edges[:, 1]])
    j = np.concatenate([edges[:, 1], edges[:, 0]])
    degree = np.maximum(np.bincount(i, minlength=n), 1).astype(float)
    neighbour_sum = jnp.zeros_like(v).at[i].add(v[j])
    delta = v - neighbour_sum / jnp.asarray(degree, v.dtype)[:, None]
    return jnp.mean(jnp.sum(delta**2, axis=-1))


def edge_length_loss(vertices: ArrayLike, faces: ArrayLike, target_length: float = 0.0) -> Array:
    """Mean of (|edge| - target_length)^2 over the unique edges (PyTorch3D's `mesh_edge_loss`)."""
    edges = _edges(_concrete_faces(faces))
    v = jnp.asarray(vertices)
    d = v[edges[:, 0]] - v[edges[:, 1]]
    length = jnp.sqrt(jnp.maximum(jnp.sum(d**2, axis=-1), 1e-30))
    return jnp.mean((length - target_length) ** 2)


def normal_consistency_loss(vertices: ArrayLike, faces: ArrayLike) -> Array:
    r"""Flattening term: the mean of :math:`1 - \cos` of the angle between the normals of faces
    sharing an edge (0 for a plane; a consistently oriented mesh is assumed).

    References:
        Liu, Li, Chen, Li, "Soft Rasterizer", ICCV 2019 (flatten loss); PyTorch3D's
        `mesh_normal_consistency`.
    """
    f = _concrete_faces(faces)
    pairs = _face_pairs(f)
    if pairs.shape[0] == 0:
        return jnp.zeros((), jnp.asarray(vertices).dtype)
    n = face_normals(vertices, f)
    return jnp.mean(1.0 - jnp.sum(n[pairs[:, 0]] * n[pairs[:, 1]], axis=-1))
