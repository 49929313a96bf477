r"""Rasterization: signed distances in screen space, coverage, and per-pixel face culling.

A pixel centre :math:`q` is covered by a projected triangle when its signed distance
:math:`d(q)` to the triangle's boundary (positive inside, minus the Euclidean distance to the
triangle outside) is positive. The hard rasterizer takes :math:`H(d)`; the perturbed one (Le
Lidec, Laptev, Schmid, Carpentier, "Differentiable rendering with perturbed optimizers",
NeurIPS 2021, Sec. 3: the perturbed rasterization step) its randomized smoothing

.. math:: H_\sigma(d) = \mathbb{E}_{X\sim\mu}\, H(d + \sigma X) = F_\mu(d / \sigma),

estimated by Monte-Carlo, with the zeroth-order estimator (with baseline) as its derivative,
so that any noise law works (:func:`rsmooth.smooth_elementwise`); SoftRas (Liu et al., ICCV
2019) takes a sigmoid, which is :math:`H_\sigma` for logistic noise in closed form.

Per-pixel culling (:func:`rasterize`): a dense rasterizer compares every pixel with every face,
which does not scale (64 x 64 pixels, 1,000 faces and 64 samples ran out of memory in the
backward pass on a CPU). Here a non-differentiable
pass picks, per pixel, at most `faces_per_pixel` candidate faces, as PyTorch3D's
`faces_per_pixel`: first per tile of `tile_size` x `tile_size` pixels at most `faces_per_tile`
faces whose bounding box, dilated by `margin` pixels, reaches the tile (cost: tiles x faces,
1/64 of pixels x faces with 8-pixel tiles): those whose own box reaches it first, nearest
first, then the others by their gap to the tile; then, per pixel, the candidates of its tile
most likely to show under noise (the visible face first, then those that noise may make cover
the pixel, the ones behind the visible surface last), from cheap affine forms (signed
distances to the edge lines, depth plane). Only the selected (H, W, K) fragments are computed
differentiably, with exact distances. Faces beyond the caps are dropped: the farthest first
among those that reach a tile, which on a closed mesh are back faces
(`Fragments.tile_overflow` counts the tiles where it happened).

Faces crossing the near plane z = near are culled whole by default (`Fragments.near_culled`
counts those in view). Near-plane clipping is opt-in (`clip_near=True`, a static option: the
default program does not contain it): a face that crosses the plane is then drawn where it is
in front of it, as the 3- or 4-vertex polygon that the plane cuts from it (``_clip_faces``:
static shapes, 4 vertex slots per face), with depth and attributes from the face's plane by
homogeneous barycentric coordinates (Olano and Greer, 1997), finite for vertices behind the
camera. Faces entirely in front go through the triangle's formulas unchanged. It is not the
default for its cost, on every mesh, crossing or not: on a 1,280-face sphere at 128 x 128 it
about doubled the hard forward pass's time and its compilation time.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array, lax
from jax.typing import ArrayLike

from rsmooth._unrolled import log_sigmoid
from rsmooth.noise import Gaussian, Noise
from rsmooth.smooth import smooth_elementwise

from rsmooth.render._camera import Camera
from rsmooth.render._mesh import Mesh, _is_concrete

__all__ = [
    "signed_distance",
    "barycentric",
    "heaviside",
    "coverage",
    "Fragments",
    "project_faces",
    "edge_neighbors",
    "rasterize",
    "COVERAGE_MODES",
]

COVERAGE_MODES = ("hard", "perturbed", "soft")

_TINY = 1e-30
# Distance (pixels) to a triangle none of whose edges counts (see rasterize's interior_edges):
# far beyond any noise, finite so that nothing downstream meets inf - inf.
_NO_EDGE = 1e15


def heaviside(d: ArrayLike) -> Array:
    """H(d) = 1 where d > 0, else 0 (floating)."""
    d = jnp.asarray(d)
    return jnp.where(d > 0, 1.0, 0.0).astype(d.dtype)


def _broadcast(points: Array, triangles: Array) -> tuple[Array, Array]:
    """points (..., 2), triangles (..., 3, 2) -> both broadcast to the common leading shape."""
    lead = jnp.broadcast_shapes(points.shape[:-1], triangles.shape[:-2])
    return jnp.broadcast_to(points, lead + (2,)), jnp.broadcast_to(triangles, lead + (3, 2))


class _EdgeTerms(NamedTuple):
    """Per point and triangle (lists: per edge i, from vertex i to i + 1)."""

    t: list[Array]  # parameter of the point of the edge nearest to q
    rx: list[Array]  # q minus that point
    ry: list[Array]
    d2: list[Array]  # squared distance (_NO_EDGE**2 where the edge does not count)
    smallest: Array  # the smallest of d2
    dist: Array  # distance to the nearest counted edge
    area2: Array  # twice the signed area
    safe_area: Array
    bary: list[Array]  # screen-space barycentric coordinates
    inside: Array


def _edge_terms(
    qx: Array,
    qy: Array,
    xs: Sequence[Array],
    ys: Sequence[Array],
    edges: Sequence[Array] | None = None,
) -> _EdgeTerms:
    """The quantities of `_edge_geometry_xy` (and of the fragments' derivatives)."""
    t, rx, ry, d2, edge = [], [], [], [], []
    for i in range(3):
        j = (i + 1) % 3
        ex, ey = xs[j] - xs[i], ys[j] - ys[i]
        wx, wy = qx - xs[i], qy - ys[i]
        t.append(jnp.clip((wx * ex + wy * ey) / jnp.maximum(ex * ex + ey * ey, _TINY), 0.0, 1.0))
        rx.append(wx - t[i] * ex)
        ry.append(wy - t[i] * ey)
        squared = rx[i] * rx[i] + ry[i] * ry[i]
        d2.append(squared if edges is None else jnp.where(edges[i], squared, _NO_EDGE**2))
        # Edge function: cross(p_{i+1} - p_i, q - p_i).
        edge.append(ex * wy - ey * wx)
    smallest = jnp.minimum(jnp.minimum(d2[0], d2[1]), d2[2])
    dist = jnp.sqrt(jnp.maximum(smallest, _TINY))
    area2 = (xs[1] - xs[0]) * (ys[2] - ys[0]) - (ys[1] - ys[0]) * (xs[2] - xs[0])  # twice the signed area
    safe_area = jnp.where(area2 == 0, 1.0, area2)
    # The vertex k is opposite the edge k + 1.
    bary = [edge[1] / safe_area, edge[2] / safe_area, edge[0] / safe_area]
    # Triangles are closed: a pixel centre on an edge shared by two faces is not lost.
    inside = (bary[0] >= 0) & (bary[1] >= 0) & (bary[2] >= 0) & (area2 != 0)
    return _EdgeTerms(t, rx, ry, d2, smallest, dist, area2, safe_area, bary, inside)


def _edge_geometry_xy(
    qx: Array,
    qy: Array,
    xs: Sequence[Array],
    ys: Sequence[Array],
    edges: Sequence[Array] | None = None,
) -> tuple[Array, list[Array]]:
    """Signed distance (...) and the three screen-space barycentric coordinates (each (...)) of
    the points (qx, qy) in the triangles of vertices (xs[i], ys[i]), all broadcast together.
    With `edges` (booleans, edge i from vertex i to i + 1), the distance's magnitude is to the
    flagged edges only (``_NO_EDGE`` when none is); the sign still says inside or outside.

    Written per coordinate and per edge, with no axis of length 2 or 3: the renderer calls it
    on (H, W, K) fragments, where XLA on CPU handles short axes badly (reductions handed to
    YNNPACK, see rsmooth._unrolled; `roll`s whose transposes become pads in the gradient)."""
    terms = _edge_terms(qx, qy, xs, ys, edges)
    return jnp.where(terms.inside, terms.dist, -terms.dist), terms.bary


def _edge_geometry(points: Array, triangles: Array) -> tuple[Array, Array]:
    """Signed distance (...) and screen-space barycentric coordinates (..., 3)."""
    points, triangles = _broadcast(points, triangles)
    xs = tuple(triangles[..., i, 0] for i in range(3))
    ys = tuple(triangles[..., i, 1] for i in range(3))
    dist, bary = _edge_geometry_xy(points[..., 0], points[..., 1], xs, ys)
    return dist, jnp.stack(bary, axis=-1)


def signed_distance(points: ArrayLike, triangles: ArrayLike) -> Array:
    """Signed distance from 2D points to triangles: positive inside, minus the Euclidean
    distance to the triangle outside (either winding; zero-area triangles cover nothing).
    Triangles are closed: a point on an edge gets a tiny positive distance (about 1e-15), so
    that pixel centres on an edge shared by two faces are covered by one of them.

    Args:
        points: (..., 2).
        triangles: (..., 3, 2), broadcast against `points`' leading axes.

    Returns:
        (...) distances.

    Example:
        >>> import jax.numpy as jnp
        >>> tri = jnp.array([[0.0, 0.0], [4.0, 0.0], [0.0, 4.0]])
        >>> [float(v) for v in signed_distance(jnp.array([[1.0, 1.0], [-2.0, 1.0]]), tri)]
        [1.0, -2.0]
    """
    return _edge_geometry(jnp.asarray(points), jnp.asarray(triangles))[0]


def barycentric(points: ArrayLike, triangles: ArrayLike) -> Array:
    """Screen-space barycentric coordinates (..., 3) of points (..., 2) in triangles (..., 3, 2)."""
    return _edge_geometry(jnp.asarray(points), jnp.asarray(triangles))[1]


def coverage(
    distance: ArrayLike,
    key: Array | None = None,
    *,
    mode: str = "hard",
    sigma: ArrayLike = 1.0,
    num_samples: int = 16,
    noise: Noise = Gaussian(),
) -> Array:
    r"""Coverage of pixels by faces from their signed distances, elementwise.

    * ``"hard"``: :math:`H(d)` (zero derivative);
    * ``"perturbed"``: the Monte-Carlo estimate of :math:`\mathbb{E} H(d + \sigma X)` with
      independent noise per element; its derivative is the zeroth-order estimator with the
      baseline :math:`H(d)` (Le Lidec et al. 2021, Sec. 3; :func:`rsmooth.smooth_elementwise`);
    * ``"soft"``: :math:`\mathrm{sigmoid}(d/\sigma)`, SoftRas' closed form (exact gradient).

    Args:
        distance: signed distances (any shape), in pixels.
        key: PRNG key (``"perturbed"`` only).
        mode: one of ``"hard"``, ``"perturbed"``, ``"soft"``.
        sigma: smoothing scale in pixels (may be traced).
        num_samples: Monte-Carlo samples per element (``"perturbed"``).
        noise: the law of X (``"perturbed"``): Gaussian, Logistic, Cauchy, ...

    Returns:
        Coverage in [0, 1], the shape of `distance`.

    Example:
        >>> import jax, jax.numpy as jnp
        >>> d = jnp.array([-1.0, 0.0, 1.0])
        >>> c = coverage(d, jax.random.key(0), mode="perturbed", sigma=1.0, num_samples=20000)
        >>> bool(jnp.allclose(c, jax.scipy.stats.norm.cdf(d), atol=0.02))
        True
    """
    distance = jnp.asarray(distance)
    if mode == "hard":
        return heaviside(distance)
    if mode == "soft":
        return jax.nn.sigmoid(distance / sigma)
    if mode == "perturbed":
        if key is None:
            raise ValueError("coverage(mode='perturbed') needs a key")
        g = smooth_elementwise(heaviside, sigma=sigma, num_samples=num_samples, noise=noise)
        return g(key, distance)
    raise ValueError(f"mode must be one of {COVERAGE_MODES}, got {mode!r}")


class Fragments(eqx.Module):
    """The K candidate faces of every pixel, from :func:`rasterize` (K = faces_per_pixel).

    Attributes:
        face_index: (H, W, K) int, index of the candidate face (0 where not `present`).
        present: (H, W, K) bool, whether the slot holds a candidate.
        distance: (H, W, K) signed distance from the pixel centre to the projected face (with
            `clip_near`, to its part in front of the near plane), pixels.
        depth: (H, W, K) normalized inverse depth of the face's plane at the pixel:
            (1/z - 1/far) / (1/near - 1/far), 1 at the near plane, 0 at the far one (larger is
            nearer; it is affine in screen space, so interpolated exactly).
        barycentric: (H, W, K, 3) perspective-correct barycentric coordinates of the pixel
            centre with respect to the face's vertices (also when the face is clipped at the
            near plane), clipped to the triangle (for attribute interpolation).
        tile_overflow: () int, the number of tiles that more faces reached than
            `faces_per_tile` (the farthest were dropped): when it is not 0 on a dense mesh, raise
            `faces_per_tile` or lower `tile_size`.
        near_culled: () int, the number of faces crossing the near plane, and not out of view,
            that were dropped whole (always 0 with `clip_near`): when it is not 0, parts of the
            mesh nearer than the near plane's distance are missing together with the rest of
            their faces; lower `Camera.near` or pass `clip_near=True`.
    """

    face_index: Array
    present: Array
    distance: Array
    depth: Array
    barycentric: Array
    tile_overflow: Array
    near_culled: Array


def _normalized(raw: list[Array]) -> tuple[Array, list[Array]]:
    """``(total, raw / total)`` with ``total = max(sum(raw), _TINY)``, for three raw >= 0
    (its forward mode: `_normalize_jvp`)."""
    total = jnp.maximum(raw[0] + raw[1] + raw[2], _TINY)
    return total, [r / total for r in raw]


def _face_forms(screen: Array, depth: Array) -> tuple[Array, Array]:
    """Affine forms of the projected faces: for each edge, (a, b, c) with a x + b y + c the
    signed distance to the edge's line, positive inside (F, 3, 3: edge, coefficient), and the
    depth plane (F, 3): depth = p0 x + p1 y + p2. Zero-area faces get lines that nothing is
    near."""
    p0 = screen
    e = jnp.roll(screen, -1, axis=-2) - p0  # (F, 3, 2)
    area2 = e[:, 0, 0] * (p0[:, 2, 1] - p0[:, 0, 1]) - e[:, 0, 1] * (p0[:, 2, 0] - p0[:, 0, 0])
    degenerate = area2 == 0
    # Edge function cross(e, q - p) = -e_y x + e_x y + (e_y p_x - e_x p_y).
    a, b = -e[..., 1], e[..., 0]
    c = e[..., 1] * p0[..., 0] - e[..., 0] * p0[..., 1]
    safe_area = jnp.where(degenerate, 1.0, area2)
    # Barycentric coordinate k is edge function k + 1 over the doubled area: the depth plane.
    bary_forms = jnp.stack([jnp.roll(f, -1, axis=-1) for f in (a, b, c)], axis=-1) / safe_area[:, None, None]
    plane = jnp.sum(bary_forms * depth[:, :, None], axis=1)  # (F, 3)
    scale = jnp.sign(safe_area)[:, None] / jnp.maximum(jnp.sqrt(a**2 + b**2), _TINY)
    lines = jnp.stack([a * scale, b * scale, c * scale], axis=-1)
    never = jnp.array([0.0, 0.0, -1e30], screen.dtype)
    lines = jnp.where(degenerate[:, None, None], never[None, None, :], lines)
    return lines, plane


def edge_neighbors(faces: ArrayLike) -> Array:
    """(F, 3) index of the face across each edge (edge i joins vertex i to vertex i + 1), -1 on
    a boundary edge. Edges are matched by vertex index: faces that repeat a vertex position
    under another index (duplicated per face for flat colours, say) are not neighbours. Works on
    traced faces (a sort of the 3F edges); an edge shared by more than two faces pairs two of
    them.

    Example:
        >>> import jax.numpy as jnp
        >>> edge_neighbors(jnp.array([[0, 1, 2], [2, 1, 3]])).tolist()
        [[-1, 1, -1], [0, -1, -1]]
    """
    # Concrete faces (the usual case: a fixed topology) are paired with numpy, since XLA would
    # constant-fold the sort at compile time (seconds for 20k faces); traced ones with jnp.
    xp = np if _is_concrete(faces) else jnp
    faces = xp.asarray(faces)
    num = faces.shape[0] * 3
    a, b = faces, xp.roll(faces, -1, axis=1)
    lo, hi = xp.minimum(a, b).reshape(num), xp.maximum(a, b).reshape(num)
    order = xp.lexsort((hi, lo))
    lo_s, hi_s = lo[order], hi[order]
    same = (lo_s[1:] == lo_s[:-1]) & (hi_s[1:] == hi_s[:-1])  # sorted entry j equals entry j + 1
    with_next = xp.concatenate([same, xp.zeros((1,), bool)])
    with_prev = xp.concatenate([xp.zeros((1,), bool), same])
    # pair each entry with its next equal one, else its previous one (chains of 3+ pair up loosely)
    nxt = xp.concatenate([order[1:], order[:1]])
    prv = xp.concatenate([order[-1:], order[:-1]])
    partner = xp.where(with_next, nxt, xp.where(with_prev, prv, -1))
    halfedge = partner[xp.argsort(order)]  # back to the unsorted order
    return jnp.asarray(xp.where(halfedge >= 0, halfedge // 3, -1).reshape(faces.shape))


def _front_facing(mesh: Mesh, camera: Camera) -> Array:
    """(F,) faces whose right-handed normal (v1 - v0) x (v2 - v0) points towards the camera.

    In the camera frame (a rotation of the world's: cross products keep their sense) the
    camera is at the origin: a face is seen from the front when its normal points from the
    face towards the origin."""
    p = lax.stop_gradient(camera.to_camera(mesh.vertices))[mesh.faces]  # (F, 3, 3)
    normal = jnp.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    return jnp.sum(normal * p[:, 0], axis=-1) < 0


def _silhouette_edges(mesh: Mesh, camera: Camera, valid: Array) -> Array:
    """(F, 3) edges across which the image may be discontinuous: on the mesh's boundary, next
    to a face that is not drawn, or between a face seen from the front and one seen from
    behind. The others (interior edges between two faces that both face the camera, or both
    face away) are crossed by a continuous surface."""
    neighbor = edge_neighbors(mesh.faces)
    front = _front_facing(mesh, camera)
    other = jnp.maximum(neighbor, 0)
    return (neighbor < 0) | ~valid[other] | (front[other] != front[:, None])


def project_faces(mesh: Mesh, camera: Camera, cull_backfaces: bool = False):
    """Projected faces: pixel coordinates (F, 3, 2), depths z (F, 3), normalized inverse depths
    (F, 3) and the visibility mask (F,) of faces entirely in front of the near plane and not
    entirely beyond the far one (and, with `cull_backfaces`, facing the camera: their
    right-handed normal (v1 - v0) x (v2 - v0) points towards it). Faces that cross the near
    plane are not in the mask: their projected triangles mean nothing (a vertex behind the
    camera has no image); :func:`rasterize` culls them whole, or with `clip_near` clips them
    (``_clip_faces``) and draws their part in front."""
    xy, z = camera.project(mesh.vertices)
    faces = mesh.faces
    screen = xy[faces]
    z_faces = z[faces]
    valid = jnp.all(z_faces > camera.near, axis=-1) & jnp.any(z_faces < camera.far, axis=-1)
    valid = valid & jnp.all(jnp.isfinite(screen), axis=(-1, -2))
    if cull_backfaces:
        valid = valid & _front_facing(mesh, camera)
    return screen, z_faces, _normalized_depth(z_faces, camera.near, camera.far), valid


def _normalized_depth(z: Array, near: Array, far: Array) -> Array:
    """(1/z - 1/far) / (1/near - 1/far) with z clamped to [near, inf): 1 at the near plane."""
    safe_z = jnp.where(z > near, z, near)
    inv_near, inv_far = 1.0 / near, 1.0 / far
    return (1.0 / safe_z - inv_far) / (inv_near - inv_far)


def _normalized_depth_jvp(
    value: Array, z: Array, near: Array, far: Array, dz: Array, d_near: Array, d_far: Array
) -> Array:
    """Forward mode of `_normalized_depth` (`value`: its output)."""
    in_front = z > near
    safe_z = jnp.where(in_front, z, near)
    d_safe = jnp.where(in_front, dz, d_near)
    d_inv_far = -d_far / (far * far)
    d_scale = -d_near / (near * near) - d_inv_far
    return (-d_safe / (safe_z * safe_z) - d_inv_far - value * d_scale) / (1.0 / near - 1.0 / far)


# Near-plane clipping. A face crossing the plane z = near is cut into the convex polygon of its
# points in front, of 3 or 4 vertices (Sutherland-Hodgman against one plane), held in 4 slots
# per face: a triangle repeats its last vertex, and a face entirely in front is (v0, v1, v2, v2),
# bit for bit its projected triangle. Why one 4-slot polygon per face rather than two triangles
# per face (2F faces, half of them masked): the per-tile pass costs tiles x faces and the
# per-pixel pass tiles x faces_per_tile, which doubling the faces would double, or halve the
# distinct faces per tile, on every mesh, crossing or not; a fourth vertex costs one more edge
# in the (H, W, K) fragments only, and no seam along a split diagonal under smoothed coverage.
# Depth and attributes do not use the polygon: they come from the face's own plane, by
# homogeneous (camera-frame) barycentric coordinates, which stay finite and exact for vertices
# behind the camera, where projected ones mean nothing (Olano and Greer, "Triangle scan
# conversion using 2D homogeneous coordinates", 1997).
_CUT = 3  # the polygon edge on the near plane, in _ClippedFaces.edge_source


class _ClippedFaces(eqx.Module):
    polygon: Array  # (F, 4, 2) pixel coordinates of the visible part's vertices
    polygon_depth: Array  # (F, 4) their normalized inverse depths (1 on the near plane)
    vertices: Array  # (F, 3, 3) the face's vertices in the camera frame
    z: Array  # (F, 3) their depths
    clipped: Array  # (F,) faces with a vertex at or behind the near plane
    valid: Array  # (F,) faces drawn (partly in front of the near plane, not beyond the far one)
    edge_source: Array  # (F, 4) the face edge (0-2, from vertex i to i + 1) of each polygon edge, or _CUT


def _clip_faces(mesh: Mesh, camera: Camera, cull_backfaces: bool = False) -> _ClippedFaces:
    """Faces clipped against the near plane (see above), with static shapes.

    The slots, with the face's vertices relabelled u0, u1, u2 from the one that is alone on its
    side of the plane (u0 = v0 when all three are in front), and y0, y2 the cuts of the edges
    u0u1 and u2u0: all in front (u0, u1, u2, u2); u0 behind (y0, u1, u2, y2); only u0 in front
    (u0, y0, y2, y2). Winding is kept. A vertex exactly on the plane counts as behind (its
    cut is itself)."""
    xy, z = camera.project(mesh.vertices)
    faces = mesh.faces
    screen, z_faces = xy[faces], z[faces]
    vertices = camera.to_camera(mesh.vertices)[faces]
    near = camera.near
    front = z_faces > near
    count = jnp.sum(front, axis=-1)
    # the vertex alone on its side: the first behind when two are in front, else the first in front
    alone = jnp.where(count == 2, jnp.argmin(front, axis=-1), jnp.where(count == 1, jnp.argmax(front, axis=-1), 0))

    def rotated(a: Array, j: int) -> Array:
        """Vertex u_j = v_{alone + j} of each face, from a (F, 3, ...) array (copies: bit for bit)."""
        k = alone.reshape((-1,) + (1,) * (a.ndim - 2))
        return jnp.where(k == 0, a[:, j % 3], jnp.where(k == 1, a[:, (j + 1) % 3], a[:, (j + 2) % 3]))

    height, width = camera.image_size
    center = jnp.array([width / 2.0, height / 2.0], screen.dtype)

    def cut(i: int, j: int) -> Array:
        """Pixel coordinates of the point of edge u_i u_j on the near plane (u_i where the edge
        does not cross it). The safe denominator keeps the derivatives finite everywhere."""
        z_i, z_j = rotated(z_faces, i), rotated(z_faces, j)
        crosses = (z_i > near) != (z_j > near)
        t = jnp.where(crosses, (near - z_i) / jnp.where(crosses, z_j - z_i, 1.0), 0.0)
        p_i, p_j = rotated(vertices, i), rotated(vertices, j)
        point = p_i + t[:, None] * (p_j - p_i)
        return camera.focal_length * point[:, :2] / near + center[None, :]

    in_front = [rotated(front, j)[:, None] for j in range(3)]
    corner = [rotated(screen, j) for j in range(3)]
    y0, y2 = cut(0, 1), cut(2, 0)
    whole = (count == 3)[:, None]
    polygon = jnp.stack(
        [
            jnp.where(in_front[0], corner[0], y0),
            jnp.where(in_front[1], corner[1], y0),
            jnp.where(in_front[2], corner[2], y2),
            jnp.where(whole, corner[2], y2),
        ],
        axis=1,
    )
    depth = _normalized_depth(z_faces, near, camera.far)
    corner_depth = [rotated(depth, j) for j in range(3)]
    one = jnp.ones_like(corner_depth[0])
    polygon_depth = jnp.stack(
        [
            jnp.where(in_front[0][:, 0], corner_depth[0], one),
            jnp.where(in_front[1][:, 0], corner_depth[1], one),
            jnp.where(in_front[2][:, 0], corner_depth[2], one),
            jnp.where(whole[:, 0], corner_depth[2], one),
        ],
        axis=1,
    )
    # Polygon edge j joins slots j and j + 1; in u-labels it lies on edge u_r u_{r+1}, r below
    # (or on the near plane); edge 2 of a triangle joins a slot to its copy (zero length).
    two = count == 2
    rotated_edge = jnp.stack(
        [jnp.zeros_like(alone), jnp.where(in_front[1][:, 0], 1, _CUT), jnp.where(two, 2, _CUT), jnp.where(two, _CUT, 2)],
        axis=1,
    )
    edge_source = jnp.where(rotated_edge == _CUT, _CUT, (alone[:, None] + rotated_edge) % 3)
    valid = (count > 0) & jnp.any(z_faces < camera.far, axis=-1) & jnp.all(jnp.isfinite(polygon), axis=(-1, -2))
    if cull_backfaces:
        valid = valid & _front_facing(mesh, camera)
    return _ClippedFaces(
        polygon=polygon, polygon_depth=polygon_depth, vertices=vertices, z=z_faces, clipped=count < 3, valid=valid,
        edge_source=edge_source,
    )


def _clipped_face_forms(vertices: Array, camera: Camera) -> tuple[Array, Array, Array]:
    """The affine forms of `_face_forms` for faces that cross the near plane, from their
    camera-frame vertices (F, 3, 3): the edge lines (F, 3, 3), the normalized inverse depth
    plane (F, 3), and the signed distance to the near plane's line, ``c0 + c1 * depth`` (F, 2),
    positive on the visible side. The line of edge i is the image of the plane through the
    camera and that edge, ``h(q) = (v_i x v_{i+1}) . r(q)`` with r(q) the ray of pixel q, of
    the sign that is positive on the face's side whether or not its vertices are in front."""
    height, width = camera.image_size
    f = camera.focal_length
    v = [vertices[:, i] for i in range(3)]
    normals = [jnp.cross(v[i], v[(i + 1) % 3]) for i in range(3)]  # (F, 3) each
    det = jnp.sum(v[2] * normals[0], axis=-1)  # det(v0, v1, v2)
    degenerate = det == 0
    safe_det = jnp.where(degenerate, 1.0, det)
    # r(q) = ((x - width/2) / f, (y - height/2) / f, 1): h = a x + b y + c
    forms = []
    for n in normals:
        a, b = n[:, 0] / f, n[:, 1] / f
        forms.append(jnp.stack([a, b, n[:, 2] - a * (width / 2.0) - b * (height / 2.0)], axis=-1))
    forms = jnp.stack(forms, axis=1)  # (F, 3, 3)
    scale = jnp.sign(safe_det)[:, None] / jnp.maximum(jnp.sqrt(forms[..., 0] ** 2 + forms[..., 1] ** 2), _TINY)
    lines = forms * scale[..., None]
    never = jnp.array([0.0, 0.0, -1e30], lines.dtype)
    lines = jnp.where(degenerate[:, None, None], never[None, None, :], lines)
    # 1/z along the ray of q is (h_0 + h_1 + h_2)(q) / det(v0, v1, v2).
    inv_near, inv_far = 1.0 / camera.near, 1.0 / camera.far
    inverse_depth = jnp.sum(forms, axis=1) / safe_det[:, None]
    plane = (inverse_depth - jnp.array([0.0, 0.0, 1.0], lines.dtype)[None, :] * inv_far) / (inv_near - inv_far)
    gradient = jnp.maximum(jnp.sqrt(plane[:, 0] ** 2 + plane[:, 1] ** 2), _TINY)
    near_line = jnp.stack([1.0 / gradient, -1.0 / gradient], axis=-1)
    return lines, plane, near_line


class _PolygonTerms(NamedTuple):
    """`_EdgeTerms` for the 4-slot polygons of `_clip_faces` (lists: per polygon edge i, from
    slot i to slot i + 1), all (...)."""

    t: list[Array]
    rx: list[Array]
    ry: list[Array]
    counts: list[Array]  # the edge counts for the distance: flagged (when flags are given), of nonzero length
    d2: list[Array]  # squared distance (_NO_EDGE**2 where the edge does not count)
    smallest: Array
    dist: Array  # distance to the polygon's boundary (its counted edges)
    edge: list[Array]  # edge functions
    area2: Array  # twice the signed area of the triangle of slots 0, 1, 2
    safe_area: Array
    bary: list[Array]  # screen-space barycentric coordinates in that triangle
    in_triangle: Array
    in_polygon: Array


def _polygon_terms(
    qx: Array, qy: Array, xs: Sequence[Array], ys: Sequence[Array], edges: Sequence[Array] | None
) -> _PolygonTerms:
    """`_edge_terms` for the 4-slot polygons of `_clip_faces`: the distance to the polygon's
    boundary (to its flagged edges only with `edges`), the screen-space barycentric
    coordinates in the triangle of its first three slots and whether q is inside that triangle
    (what `_edge_terms` gives for a face entirely in front, bit for bit), and whether q is
    inside the polygon. Edges of zero length (a triangle's repeated slot) do not count."""
    t, rx, ry, counts, d2, edge = [], [], [], [], [], []
    for i in range(4):
        j = (i + 1) % 4
        ex, ey = xs[j] - xs[i], ys[j] - ys[i]
        wx, wy = qx - xs[i], qy - ys[i]
        length2 = ex * ex + ey * ey
        t.append(jnp.clip((wx * ex + wy * ey) / jnp.maximum(length2, _TINY), 0.0, 1.0))
        rx.append(wx - t[i] * ex)
        ry.append(wy - t[i] * ey)
        counts.append(length2 > 0 if edges is None else edges[i] & (length2 > 0))
        d2.append(jnp.where(counts[i], rx[i] * rx[i] + ry[i] * ry[i], _NO_EDGE**2))
        edge.append(ex * wy - ey * wx)
    smallest = jnp.minimum(jnp.minimum(jnp.minimum(d2[0], d2[1]), d2[2]), d2[3])
    dist = jnp.sqrt(jnp.maximum(smallest, _TINY))
    area2 = (xs[1] - xs[0]) * (ys[2] - ys[0]) - (ys[1] - ys[0]) * (xs[2] - xs[0])
    safe_area = jnp.where(area2 == 0, 1.0, area2)
    # In the triangle (slots 0, 1, 2) the edge from slot 2 back to slot 0 is polygon edge 3
    # when slot 3 repeats slot 2.
    bary = [edge[1] / safe_area, edge[3] / safe_area, edge[0] / safe_area]
    in_triangle = (bary[0] >= 0) & (bary[1] >= 0) & (bary[2] >= 0) & (area2 != 0)
    polygon_area2 = area2 + (xs[2] - xs[0]) * (ys[3] - ys[0]) - (ys[2] - ys[0]) * (xs[3] - xs[0])
    positive = polygon_area2 > 0
    in_polygon = polygon_area2 != 0
    for e in edge:
        in_polygon = in_polygon & jnp.where(positive, e >= 0, e <= 0)
    return _PolygonTerms(t, rx, ry, counts, d2, smallest, dist, edge, area2, safe_area, bary, in_triangle, in_polygon)


def _near_culled(mesh: Mesh, camera: Camera, margin: Array, cull_backfaces: bool) -> Array:
    """() int: the faces that cross the near plane (a vertex in front of it, one at or behind
    it), may be in view, and (with `cull_backfaces`) face the camera: those that culling whole
    drops, where clipping would draw their part in front. A face is out of view when its three
    vertices are beyond one side plane of the image's frustum dilated by `margin` pixels
    (planes through the camera: the face, convex, misses the viewing pyramid); a face
    crossing a corner's two planes may be counted though out of view. The side test keeps a
    floor under a camera from counting: its faces that cross the camera's plane are out of
    view."""
    p = lax.stop_gradient(camera.to_camera(mesh.vertices))[mesh.faces]  # (F, 3, 3)
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    front = z > camera.near
    crossing = jnp.any(front, axis=-1) & ~jnp.all(front, axis=-1)
    # Pixel u = f x / z + width / 2 is in [-margin, width + margin] (z > 0) when
    # f x + (width / 2 + margin) z >= 0 and f x - (width / 2 + margin) z <= 0; likewise v.
    height, width = camera.image_size
    f = lax.stop_gradient(camera.focal_length)
    half_w, half_h = width / 2.0 + margin, height / 2.0 + margin
    outside = (
        jnp.all(f * x + half_w * z < 0, axis=-1)
        | jnp.all(f * x - half_w * z > 0, axis=-1)
        | jnp.all(f * y + half_h * z < 0, axis=-1)
        | jnp.all(f * y - half_h * z > 0, axis=-1)
    )
    culled = crossing & ~outside
    if cull_backfaces:
        culled = culled & _front_facing(mesh, camera)
    return jnp.sum(culled)


def _clipped_forms(faces: _ClippedFaces, camera: Camera, s: Array, dv: Array) -> tuple[Array, Array, Array]:
    """The cheap affine forms of pass 2 for clipped faces (`s`, `dv`: their polygons and depths
    under stop_gradient): the edge lines (F, 3, 3) and depth planes (F, 3) of `_face_forms`,
    and the near plane's line (F, 2) on the depth, ``c0 + c1 * depth``.

    A face crossing the near plane has the lines of its edges as seen from the camera and the
    near plane's line (on which its normalized inverse depth is 1): the visible polygon is
    inside all four. A face in front keeps its triangle's forms, and no near line."""
    clipped = faces.clipped
    lines, plane = _face_forms(s[:, :3], dv[:, :3])
    cut_lines, cut_plane, cut_near = _clipped_face_forms(lax.stop_gradient(faces.vertices), lax.stop_gradient(camera))
    lines = jnp.where(clipped[:, None, None], cut_lines, lines)
    plane = jnp.where(clipped[:, None], cut_plane, plane)
    near_line = jnp.where(clipped[:, None], cut_near, jnp.array([1e30, 0.0], s.dtype)[None, :])
    return lines, plane, near_line


def _triangle_fragments(
    mesh: Mesh,
    camera: Camera,
    projected: tuple[Array, Array, Array, Array],
    face_index: Array,
    qx: Array,
    qy: Array,
    interior_edges: bool,
) -> tuple[Array, Array, Array]:
    """Signed distance, depth (H, W, K) and perspective-correct weights (H, W, K, 3) of the
    selected faces, all in front of the near plane (`projected`: from :func:`project_faces`),
    gathered per vertex and coordinate as (H, W, K) arrays (see _edge_geometry_xy)."""
    screen, z_faces, depth_vertices, valid = projected
    edges = None if interior_edges else _silhouette_edges(mesh, camera, valid)
    return triangle_fragments_at((screen, depth_vertices, z_faces), edges, face_index, qx, qy)


def triangle_geometry(
    mesh: Mesh, camera: Camera, cull_backfaces: bool, interior_edges: bool
) -> tuple[tuple[Array, Array, Array], Array | None]:
    """(geometry, edges): what :func:`triangle_fragments_at` takes, the projected faces
    (pixel coordinates (F, 3, 2), normalized inverse depths (F, 3), camera depths (F, 3)),
    differentiable, and the (F, 3) flags of the edges that count for the distances (None with
    `interior_edges`), as :func:`rasterize` (without `clip_near`) computes its fragments."""
    screen, z_faces, depth_vertices, valid = project_faces(mesh, camera, cull_backfaces)
    edges = None if interior_edges else _silhouette_edges(mesh, camera, valid)
    return (screen, depth_vertices, z_faces), edges


def triangle_fragments_at(geometry, edges, face_index, qx, qy) -> tuple[Array, Array, Array]:
    """Signed distance, depth and perspective-correct weights of the faces `face_index` at the
    pixel centres (qx, qy) (broadcast against it), from :func:`triangle_geometry`'s output: the
    fragments of :func:`rasterize` (without `clip_near`), recomputed where wanted (the renderer's
    `pixel_chunk` differentiates them at the sampled pixels alone)."""
    screen, depth_vertices, z_faces = geometry
    return _fragment_geometry(screen, depth_vertices, z_faces, edges, face_index, qx, qy)


def pixel_centres(pixels: Array, width: int, dtype) -> tuple[Array, Array]:
    """(x, y), each (P, 1): the centres of the flat pixel indices `pixels` of an image `width`
    pixels wide."""
    return (pixels % width).astype(dtype)[:, None] + 0.5, (pixels // width).astype(dtype)[:, None] + 0.5


class _FragmentTerms(NamedTuple):
    """The per-fragment quantities of `_fragment_terms`, all (H, W, K) (lists: per vertex)."""

    xs: list[Array]
    ys: list[Array]
    depths: list[Array]  # normalized inverse depth of each vertex
    z_raw: list[Array]  # camera-frame depth of each vertex
    zs: list[Array]  # the same, floored at _TINY
    flags: list[Array] | None  # edges that count for the distance
    edge: _EdgeTerms
    positive: list[Array]  # barycentric coordinates clipped at 0
    bary_total: Array  # normalizer of the clipped barycentric coordinates
    clipped: list[Array]  # clipped and normalized
    perspective: list[Array]  # clipped / zs
    weights_total: Array
    weights: list[Array]


def _fragment_terms(screen, depth_vertices, z_faces, edges, face_index, qx, qy) -> _FragmentTerms:
    """Gathers the selected faces' vertices and computes every quantity of `_fragment_geometry`."""
    xs = [screen[:, i, 0][face_index] for i in range(3)]
    ys = [screen[:, i, 1][face_index] for i in range(3)]
    depths = [depth_vertices[:, i][face_index] for i in range(3)]
    z_raw = [z_faces[:, i][face_index] for i in range(3)]
    zs = [jnp.maximum(z, _TINY) for z in z_raw]
    flags = None if edges is None else [edges[:, i][face_index] for i in range(3)]
    edge = _edge_terms(qx, qy, xs, ys, flags)
    positive = [jnp.maximum(b, 0.0) for b in edge.bary]
    bary_total, clipped = _normalized(positive)
    # Perspective-correct weights for attributes: screen weights divided by depth, renormalized.
    perspective = [b / z for b, z in zip(clipped, zs)]
    weights_total, weights = _normalized(perspective)
    return _FragmentTerms(
        xs, ys, depths, z_raw, zs, flags, edge, positive, bary_total, clipped, perspective, weights_total, weights
    )


def _fragment_outputs(terms: _FragmentTerms) -> tuple[Array, Array, Array]:
    distance = jnp.where(terms.edge.inside, terms.edge.dist, -terms.edge.dist)
    depth = sum(b * d for b, d in zip(terms.clipped, terms.depths))
    return distance, depth, jnp.stack(terms.weights, axis=-1)


def _fragment_values(screen, depth_vertices, z_faces, edges, face_index, qx, qy) -> tuple[Array, Array, Array]:
    """`_fragment_geometry` without its custom derivative (JAX's own)."""
    return _fragment_outputs(_fragment_terms(screen, depth_vertices, z_faces, edges, face_index, qx, qy))


@jax.custom_jvp
def _fragment_geometry(screen, depth_vertices, z_faces, edges, face_index, qx, qy) -> tuple[Array, Array, Array]:
    """The fragments of the faces `face_index` (H, W, K) at the pixel centres (qx, qy): signed
    distance (H, W, K; to the flagged `edges` only, when given), normalized inverse depth
    (H, W, K) and perspective-correct barycentric weights (H, W, K, 3), from the projected
    faces (`screen` (F, 3, 2), `depth_vertices` and camera depths `z_faces`, (F, 3)).

    Differentiable in `screen`, `depth_vertices` and `z_faces` by a hand-written forward mode
    (`_fragment_geometry_jvp`), which JAX transposes for reverse mode: JAX's own derivative of
    these formulas left XLA on CPU, in reverse mode, six fusions (the cotangents of the six
    vertex coordinates) that each recomputed the shared part of the others. Its results are
    autodiff's of `_fragment_values` up to rounding (tests/render/test_raster.py)."""
    return _fragment_values(screen, depth_vertices, z_faces, edges, face_index, qx, qy)


@_fragment_geometry.defjvp
def _fragment_geometry_jvp(primals, tangents):
    screen, depth_vertices, z_faces, edges, face_index, qx, qy = primals
    d_screen, d_depth_vertices, d_z_faces = tangents[:3]
    terms = _fragment_terms(screen, depth_vertices, z_faces, edges, face_index, qx, qy)
    xs, ys, edge = terms.xs, terms.ys, terms.edge
    dx = [d_screen[:, i, 0][face_index] for i in range(3)]
    dy = [d_screen[:, i, 1][face_index] for i in range(3)]

    d_dist = _nearest_edge_jvp(edge.t, edge.rx, edge.ry, edge.d2, edge.smallest, edge.dist, terms.flags, dx, dy)

    # bary = [edge_1, edge_2, edge_0] / area2; clipped = normalize(max(bary, 0));
    # depth = sum(clipped * depths)
    d_clipped = _barycentric_jvp(xs, ys, dx, dy, qx, qy, (1, 2, 0), edge.area2, edge.safe_area, edge.bary, terms)
    d_depths = [d_depth_vertices[:, i][face_index] for i in range(3)]
    d_depth = sum(dc * d + c * dd for dc, d, c, dd in zip(d_clipped, terms.depths, terms.clipped, d_depths))
    # weights = normalize(clipped / max(z, _TINY))
    d_zs = [jnp.where(z > _TINY, d_z_faces[:, i][face_index], 0.0) for i, z in enumerate(terms.z_raw)]
    d_perspective = [(dc - p * dz) / z for dc, p, dz, z in zip(d_clipped, terms.perspective, d_zs, terms.zs)]
    d_weights = _normalize_jvp(terms.weights, terms.perspective, terms.weights_total, d_perspective)

    tangent = (jnp.where(edge.inside, d_dist, -d_dist), d_depth, jnp.stack(d_weights, axis=-1))
    return _fragment_outputs(terms), tangent


def _nearest_edge_jvp(t, rx, ry, d2, smallest, dist, counts, dx, dy) -> Array:
    """Forward mode of the distance ``sqrt(max(min_i d2_i, _TINY))`` to the nearest counted edge
    of a polygon (edge i from vertex i to i + 1, of all ``len(t)``; `counts`: None for all).

    With r = q - the nearest point p_i + t (p_j - p_i) of the edge, d d2 = -2 r . ((1 - t) dp_i
    + t dp_j): the term in dt vanishes (t is optimal, r . (p_j - p_i) = 0, or clamped, dt = 0).
    Of tied edges the first counts (autodiff would average them)."""
    n = len(t)
    found, d_smallest = jnp.zeros(jnp.shape(smallest), bool), 0.0
    for i in range(n):
        j = (i + 1) % n
        first = (d2[i] == smallest) & ~found
        found = found | first
        nearest = first if counts is None else first & counts[i]
        s, u = 1.0 - t[i], t[i]
        d_d2 = -2.0 * (rx[i] * (s * dx[i] + u * dx[j]) + ry[i] * (s * dy[i] + u * dy[j]))
        d_smallest = d_smallest + jnp.where(nearest, d_d2, 0.0)
    return jnp.where(smallest > _TINY, d_smallest / (2.0 * dist), 0.0)


def _barycentric_jvp(xs, ys, dx, dy, qx, qy, opposite, area2, safe_area, bary, terms) -> list[Array]:
    """Forward mode of the screen-space barycentric coordinates clipped to the triangle of
    vertices 0, 1, 2 and normalized (`terms.clipped`, from `terms.positive` and
    `terms.bary_total`): bary_k = edge_{opposite[k]} / area2, with the edge functions
    edge_i = cross(p_j - p_i, q - p_i) of a polygon's edges (j = i + 1 around all ``len(xs)``
    vertices) and area2 = cross(p_1 - p_0, p_2 - p_0)."""
    n = len(xs)
    d_edge = []
    for i in range(n):
        j = (i + 1) % n
        d_edge.append((ys[j] - qy) * dx[i] + (qx - xs[j]) * dy[i] + (qy - ys[i]) * dx[j] + (xs[i] - qx) * dy[j])
    d_area = 0.0
    for i in range(3):
        j, k = (i + 1) % 3, (i + 2) % 3
        d_area = d_area + (ys[j] - ys[k]) * dx[i] + (xs[k] - xs[j]) * dy[i]
    d_area = jnp.where(area2 != 0, d_area, 0.0)
    d_bary = [(d_edge[e] - b * d_area) / safe_area for e, b in zip(opposite, bary)]
    return _normalize_jvp(
        terms.clipped, terms.positive, terms.bary_total, [jnp.where(b > 0, d, 0.0) for b, d in zip(bary, d_bary)]
    )


def _normalize_jvp(values: list[Array], raw: list[Array], total: Array, d_raw: list[Array]) -> list[Array]:
    """Forward mode of ``values = raw / max(sum(raw), _TINY)`` (raw >= 0)."""
    d_total = jnp.where(raw[0] + raw[1] + raw[2] > _TINY, d_raw[0] + d_raw[1] + d_raw[2], 0.0)
    return [(d - v * d_total) / total for d, v in zip(d_raw, values)]


def _clipped_fragments(
    mesh: Mesh,
    camera: Camera,
    faces: _ClippedFaces,
    face_index: Array,
    qx: Array,
    qy: Array,
    interior_edges: bool,
) -> tuple[Array, Array, Array]:
    """`_triangle_fragments` for the polygons of `_clip_faces` (``clip_near=True``)."""
    height, width = camera.image_size
    flags = None
    if not interior_edges:
        silhouette = _silhouette_edges(mesh, camera, faces.valid)
        # the near plane's cut is a silhouette edge: what lies behind it shows there
        silhouette = jnp.concatenate([silhouette, jnp.ones_like(silhouette[:, :1])], axis=1)
        flags = jnp.take_along_axis(silhouette, faces.edge_source, axis=1)  # (F, 4)
    dtype = faces.polygon.dtype
    lens = tuple(jnp.asarray(a, dtype) for a in (camera.near, camera.far, camera.focal_length))
    cx, cy = qx - width / 2.0, qy - height / 2.0
    return _clipped_geometry(faces.polygon, faces.vertices, lens, flags, face_index, qx, qy, cx, cy)


class _ClippedTerms(NamedTuple):
    """The per-fragment quantities of `_clipped_terms`, all (H, W, K) (lists: per slot or vertex)."""

    xs: list[Array]  # polygon slots
    ys: list[Array]
    polygon: _PolygonTerms
    vertices: list[list[Array]]  # [vertex][coordinate], camera frame
    cut: Array  # the face crosses the near plane
    # a face in front: screen-space barycentric coordinates, as `_FragmentTerms`
    z_front: list[Array]
    positive: list[Array]
    bary_total: Array
    clipped: list[Array]
    front_depths: list[Array]  # normalized inverse depths of the vertices
    zs: list[Array]
    perspective: list[Array]
    weights_total: Array
    weights: list[Array]
    # a face crossing the near plane: homogeneous barycentric coordinates
    ray: tuple[Array, Array]
    normals: list[tuple[Array, Array, Array]]  # v_{i+1} x v_{i+2}
    flip: Array  # det(v0, v1, v2) < 0
    homogeneous: list[Array]
    cut_positive: list[Array]
    cut_total: Array
    cut_weights: list[Array]
    z_point: Array
    cut_depth: Array


def _clipped_terms(polygon, vertices, lens, flags, face_index, qx, qy, cx, cy) -> _ClippedTerms:
    """Gathers the selected faces' polygons and vertices and computes every quantity of
    `_clipped_geometry`."""
    near, far, focal = lens
    xs = [polygon[:, i, 0][face_index] for i in range(4)]
    ys = [polygon[:, i, 1][face_index] for i in range(4)]
    edges = None if flags is None else [flags[:, i][face_index] for i in range(4)]
    terms = _polygon_terms(qx, qy, xs, ys, edges)
    v = [[vertices[:, i, j][face_index] for j in range(3)] for i in range(3)]
    z = [vertex[2] for vertex in v]
    cut = ~((z[0] > near) & (z[1] > near) & (z[2] > near))

    # A face in front: screen-space barycentric coordinates clipped to the triangle give the
    # depth (affine in screen space) and, divided by depth, the perspective-correct weights.
    z_front = [jnp.where(cut, 1.0, zi) for zi in z]  # (finite derivatives in the branch not taken)
    positive = [jnp.maximum(b, 0.0) for b in terms.bary]
    bary_total, clipped = _normalized(positive)
    front_depths = [_normalized_depth(zi, near, far) for zi in z_front]
    zs = [jnp.maximum(zi, _TINY) for zi in z_front]
    perspective = [b / zi for b, zi in zip(clipped, zs)]
    weights_total, weights = _normalized(perspective)

    # A face crossing the near plane: homogeneous barycentric coordinates, proportional to
    # (v_{i+1} x v_{i+2}) . r(q) for the ray r(q) of the pixel, are the perspective-correct
    # weights themselves (no division by a vertex depth, which may be 0 or negative), clipped
    # to the face the same way; the depth is that of the weighted point, clamped to the near
    # plane where it lies in the cut part. For a face in front this is the branch above in
    # exact arithmetic (clipping screen-space or perspective-correct coordinates drops the same
    # vertices), so nothing jumps when a vertex reaches the near plane.
    ray = (cx / focal, cy / focal)
    normals = []
    for i in range(3):
        (x1, y1, z1), (x2, y2, z2) = v[(i + 1) % 3], v[(i + 2) % 3]
        normals.append((y1 * z2 - z1 * y2, z1 * x2 - x1 * z2, x1 * y2 - y1 * x2))
    det = v[0][0] * normals[0][0] + v[0][1] * normals[0][1] + v[0][2] * normals[0][2]
    flip = det < 0
    homogeneous = [jnp.where(flip, -h, h) for h in (n[0] * ray[0] + n[1] * ray[1] + n[2] for n in normals)]
    cut_positive = [jnp.maximum(h, 0.0) for h in homogeneous]
    cut_total, cut_weights = _normalized(cut_positive)
    z_point = cut_weights[0] * z[0] + cut_weights[1] * z[1] + cut_weights[2] * z[2]
    cut_depth = _normalized_depth(z_point, near, far)
    return _ClippedTerms(
        xs, ys, terms, v, cut, z_front, positive, bary_total, clipped, front_depths, zs, perspective, weights_total,
        weights, ray, normals, flip, homogeneous, cut_positive, cut_total, cut_weights, z_point, cut_depth,
    )


def _clipped_outputs(terms: _ClippedTerms) -> tuple[Array, Array, Array]:
    polygon, cut = terms.polygon, terms.cut
    distance = jnp.where(jnp.where(cut, polygon.in_polygon, polygon.in_triangle), polygon.dist, -polygon.dist)
    front_depth = sum(b * d for b, d in zip(terms.clipped, terms.front_depths))
    depth = jnp.where(cut, terms.cut_depth, front_depth)
    weights = jnp.stack([jnp.where(cut, c, w) for c, w in zip(terms.cut_weights, terms.weights)], axis=-1)
    return distance, depth, weights


def _clipped_values(polygon, vertices, lens, flags, face_index, qx, qy, cx, cy) -> tuple[Array, Array, Array]:
    """`_clipped_geometry` without its custom derivative (JAX's own)."""
    return _clipped_outputs(_clipped_terms(polygon, vertices, lens, flags, face_index, qx, qy, cx, cy))


@jax.custom_jvp
def _clipped_geometry(polygon, vertices, lens, flags, face_index, qx, qy, cx, cy) -> tuple[Array, Array, Array]:
    """`_fragment_geometry` for the faces of `_clip_faces`: the signed distance (to the
    polygon's flagged edges only, when `flags` (F, 4) are given), the normalized inverse depth
    and the perspective-correct weights (H, W, K, 3) of the faces `face_index` (H, W, K) at
    the pixel centres (qx, qy), from the polygons (F, 4, 2), the camera-frame vertices
    (F, 3, 3) and the camera's ``lens = (near, far, focal length)``; (cx, cy) are the pixel
    centres relative to the image centre.

    Differentiable in `polygon`, `vertices` and `lens` by a hand-written forward mode
    (`_clipped_geometry_jvp`), which JAX transposes for reverse mode, for the reason given at
    `_fragment_geometry` (here JAX's own derivative is nine fusions, the
    cotangents of the nine vertex coordinates, each recomputing the others' shared part). Its
    results are autodiff's of `_clipped_values` up to rounding (tests/render/test_near_clip.py)."""
    return _clipped_values(polygon, vertices, lens, flags, face_index, qx, qy, cx, cy)


@_clipped_geometry.defjvp
def _clipped_geometry_jvp(primals, tangents):
    polygon, vertices, lens, flags, face_index, qx, qy, cx, cy = primals
    d_polygon, d_vertices, d_lens = tangents[:3]
    near, far, focal = lens
    d_near, d_far, d_focal = d_lens
    terms = _clipped_terms(polygon, vertices, lens, flags, face_index, qx, qy, cx, cy)
    xs, ys, poly, v, cut = terms.xs, terms.ys, terms.polygon, terms.vertices, terms.cut
    dx = [d_polygon[:, i, 0][face_index] for i in range(4)]
    dy = [d_polygon[:, i, 1][face_index] for i in range(4)]
    dv = [[d_vertices[:, i, j][face_index] for j in range(3)] for i in range(3)]

    d_dist = _nearest_edge_jvp(poly.t, poly.rx, poly.ry, poly.d2, poly.smallest, poly.dist, poly.counts, dx, dy)
    inside = jnp.where(cut, poly.in_polygon, poly.in_triangle)

    # A face in front: bary = [edge_1, edge_3, edge_0] / area2 (polygon edges), area2 of slots 0-2.
    d_clipped = _barycentric_jvp(xs, ys, dx, dy, qx, qy, (1, 3, 0), poly.area2, poly.safe_area, poly.bary, terms)
    d_z_front = [jnp.where(cut, 0.0, dv[i][2]) for i in range(3)]
    d_front_depths = [
        _normalized_depth_jvp(nd, zf, near, far, dzf, d_near, d_far)
        for nd, zf, dzf in zip(terms.front_depths, terms.z_front, d_z_front)
    ]
    d_front_depth = sum(
        dc * nd + c * dnd for dc, nd, c, dnd in zip(d_clipped, terms.front_depths, terms.clipped, d_front_depths)
    )
    d_zs = [jnp.where(zf > _TINY, dzf, 0.0) for zf, dzf in zip(terms.z_front, d_z_front)]
    d_perspective = [(dc - p * dz) / z for dc, p, dz, z in zip(d_clipped, terms.perspective, d_zs, terms.zs)]
    d_weights = _normalize_jvp(terms.weights, terms.perspective, terms.weights_total, d_perspective)

    # A face crossing the near plane: h_i = +-(v_{i+1} x v_{i+2}) . (cx / f, cy / f, 1).
    d_ray = (-terms.ray[0] * d_focal / focal, -terms.ray[1] * d_focal / focal)
    d_homogeneous = []
    for i in range(3):
        (x1, y1, z1), (x2, y2, z2) = v[(i + 1) % 3], v[(i + 2) % 3]
        (dx1, dy1, dz1), (dx2, dy2, dz2) = dv[(i + 1) % 3], dv[(i + 2) % 3]
        n = terms.normals[i]
        d_n = (
            dy1 * z2 + y1 * dz2 - dz1 * y2 - z1 * dy2,
            dz1 * x2 + z1 * dx2 - dx1 * z2 - x1 * dz2,
            dx1 * y2 + x1 * dy2 - dy1 * x2 - y1 * dx2,
        )
        d_h = d_n[0] * terms.ray[0] + n[0] * d_ray[0] + d_n[1] * terms.ray[1] + n[1] * d_ray[1] + d_n[2]
        d_homogeneous.append(jnp.where(terms.flip, -d_h, d_h))
    d_cut_weights = _normalize_jvp(
        terms.cut_weights, terms.cut_positive, terms.cut_total,
        [jnp.where(h > 0, d, 0.0) for h, d in zip(terms.homogeneous, d_homogeneous)],
    )
    d_z_point = sum(dw * p[2] + w * dp[2] for dw, w, p, dp in zip(d_cut_weights, terms.cut_weights, v, dv))
    d_cut_depth = _normalized_depth_jvp(terms.cut_depth, terms.z_point, near, far, d_z_point, d_near, d_far)

    tangent = (
        jnp.where(inside, d_dist, -d_dist),
        jnp.where(cut, d_cut_depth, d_front_depth),
        jnp.stack([jnp.where(cut, c, w) for c, w in zip(d_cut_weights, d_weights)], axis=-1),
    )
    return _clipped_outputs(terms), tangent


def check_pixels(pixels: ArrayLike, num_pixels: int) -> Array:
    """`pixels` as a (P,) integer array of indices into a flattened image of `num_pixels` pixels
    (checked when concrete), or a clear error."""
    pixels = jnp.asarray(pixels)
    if pixels.ndim != 1 or not jnp.issubdtype(pixels.dtype, jnp.integer):
        raise ValueError(f"pixels must be a 1-D integer array of flat pixel indices, got shape {pixels.shape} and dtype {pixels.dtype}")
    if _is_concrete(pixels) and pixels.size:
        host = np.asarray(pixels)
        if not (0 <= host.min() and host.max() < num_pixels):
            raise ValueError(f"pixels must lie in [0, {num_pixels}) (the image's H * W), got {host.min()} to {host.max()}")
    return pixels


def rasterize(
    mesh: Mesh,
    camera: Camera,
    *,
    faces_per_pixel: int = 8,
    margin: ArrayLike = 0.0,
    sigma: ArrayLike | None = None,
    gamma: ArrayLike | None = None,
    tile_size: int = 8,
    faces_per_tile: int = 64,
    cull_backfaces: bool = False,
    interior_edges: bool = True,
    clip_near: bool = False,
    pixels: ArrayLike | None = None,
) -> Fragments:
    r"""Per-pixel candidate faces and their differentiable fragments.

    Candidate selection is not differentiable (it is under `stop_gradient`); the returned
    distances, depths and barycentric coordinates are, with respect to the mesh vertices and
    the camera. Faces crossing the near plane are culled whole unless `clip_near`
    (`Fragments.near_culled` counts those in view); a mesh behind the camera, or out of view,
    gives no candidate at all (an empty image).

    Args:
        mesh: the mesh.
        camera: the camera (its `image_size` fixes the output shape).
        faces_per_pixel: K, candidates kept per pixel.
        margin: dilation of the faces' bounding boxes in pixels; faces farther than this from
            a pixel are not its candidates (use a few sigma for smoothed coverage).
        sigma, gamma: when given, pixels rank their candidates by
            :math:`\log\mathrm{sigmoid}(d/\sigma) + \min(0, z - z_{front})/\gamma` (d: the
            distance to the nearest edge line, z: the face's depth clipped to its range,
            :math:`z_{front}`: the depth of the nearest covering face): the visible face
            first, then the faces that noise may make cover the pixel, the ones behind the
            visible surface last; when None (hard rendering), only covering faces are kept,
            nearest first.
        tile_size: side of the square tiles of the first culling pass.
        faces_per_tile: candidates kept per tile (faces whose own box reaches the tile first,
            nearest first; then faces reached through the margin, smallest gap first).
        cull_backfaces: drop the faces seen from behind (see :func:`project_faces`). On a
            closed, outward-oriented mesh they are hidden anyway, so the hard image does not
            change, while every pixel's K candidates go to faces that can be seen; smoothed
            images lose the (small) weight of the hidden faces.
        interior_edges: when False, `distance` measures only to the edges across which the
            image may be discontinuous (silhouette and boundary edges, see
            ``_silhouette_edges``): smoothed coverage then stays 1 across the edge shared by
            two faces of a continuous surface, instead of about 1/2 on each side (the seams of
            SoftRas and of per-triangle perturbed coverage). The sign, hence hard coverage, is
            unchanged.
        clip_near: clip the faces that cross the near plane and draw their part in front, with
            the depth and perspective-correct barycentric coordinates of the face's own plane;
            the cut is a silhouette edge (see ``_clip_faces``). Static: False (the default)
            traces the program without clipping, which culls those faces whole; True costs
            about twice the hard forward time on any mesh (a polygon of 4 slots per face).
        pixels: (P,) integer indices into the flattened image (row-major, ``row * W + col``):
            the fragments of these pixels only, of shape (P, K). The candidates are chosen as
            for the whole image (a cheap pass, outside the derivative); the differentiable
            fragments, the costly part, are computed at the P pixels alone. Indices must lie
            in [0, H W) (traced indices cannot be checked; out-of-range ones are clamped).

    Returns:
        :class:`Fragments` of shape (H, W, K), K = min(faces_per_pixel, faces_per_tile, F), or
        (P, K) with `pixels`.
    """
    height, width = camera.image_size
    if pixels is not None:
        pixels = check_pixels(pixels, height * width)
    if clip_near:
        clipped = _clip_faces(mesh, camera, cull_backfaces)
        valid = clipped.valid
        s = lax.stop_gradient(clipped.polygon)  # (F, 4, 2)
        dv = lax.stop_gradient(clipped.polygon_depth)  # (F, 4)
    else:
        projected = project_faces(mesh, camera, cull_backfaces)
        screen, _, depth_vertices, valid = projected
        s = lax.stop_gradient(screen)  # (F, 3, 2)
        dv = lax.stop_gradient(depth_vertices)  # (F, 3)
    num_faces = s.shape[0]
    k_tile = min(faces_per_tile, num_faces)
    k_pixel = min(faces_per_pixel, k_tile)
    ts = tile_size
    ty, tx = math.ceil(height / ts), math.ceil(width / ts)
    dtype = s.dtype

    margin = lax.stop_gradient(jnp.asarray(margin, dtype))

    # Pass 1: per tile, the faces whose dilated bounding box reaches the tile's pixel centres:
    # first those whose own box does (they may cover a pixel), nearest first, then the others
    # by the gap between their box and the tile, smallest first (the nearest first had a
    # torus's near faces, reached only through the margin, crowd out the covering ones).
    low = jnp.min(s, axis=1)
    high = jnp.max(s, axis=1)
    start_x = jnp.arange(tx, dtype=dtype) * ts + 0.5
    end_x = jnp.minimum(start_x + ts - 1, width - 0.5)
    start_y = jnp.arange(ty, dtype=dtype) * ts + 0.5
    end_y = jnp.minimum(start_y + ts - 1, height - 0.5)
    # gap (pixels) between each face's box and each tile's pixel centres, per axis
    gap_x = jnp.maximum(jnp.maximum(low[None, :, 0] - end_x[:, None], start_x[:, None] - high[None, :, 0]), 0.0)  # (tx, F)
    gap_y = jnp.maximum(jnp.maximum(low[None, :, 1] - end_y[:, None], start_y[:, None] - high[None, :, 1]), 0.0)  # (ty, F)
    gap = jnp.maximum(gap_y[:, None, :], gap_x[None, :, :])  # (ty, tx, F)
    overlap = (gap <= margin) & valid[None, None, :]
    nearest = jnp.max(dv, axis=1)
    # nearest in (0, 1) for a face in view: 2 + nearest ranks above 1 - gap / (margin + 1)
    tile_key = jnp.where(gap == 0, 2.0 + nearest[None, None, :], 1.0 - gap / (margin + 1.0))
    tile_key = jnp.where(overlap, tile_key, -jnp.inf)
    tile_values, tile_faces = lax.top_k(tile_key, k_tile)  # (ty, tx, Kt)
    tile_ok = tile_values > -jnp.inf
    tile_overflow = jnp.sum(jnp.sum(overlap, axis=-1) > k_tile)

    # Pass 2: per pixel, rank its tile's candidates. Cheap affine forms only: the signed
    # distances to the three edge lines (their minimum is the signed distance inside the
    # triangle, and at least minus the distance outside, so the margin test is conservative)
    # and the depth plane, evaluated at the pixel centres.
    if clip_near:
        lines, plane, near_line = _clipped_forms(clipped, camera, s, dv)
    else:
        lines, plane = _face_forms(s, dv)
    offsets = jnp.arange(ts, dtype=dtype) + 0.5
    x = (jnp.arange(tx, dtype=dtype)[:, None] * ts + offsets[None, :])[None, :, None, :, None]  # (1, tx, 1, ts, 1)
    y = (jnp.arange(ty, dtype=dtype)[:, None] * ts + offsets[None, :])[:, None, :, None, None]  # (ty, 1, ts, 1, 1)
    # one (ty, tx, ts, ts, Kt) array per edge line, each coefficient gathered on its own: a
    # trailing axis of 3 (edges or coefficients) in these per-pixel arrays read strided in
    # XLA's CPU loops, several times slower than these
    def gathered(form):  # (F,) -> (ty, tx, 1, 1, Kt)
        return form[tile_faces][:, :, None, None, :]

    dist = functools.reduce(
        jnp.minimum,
        (gathered(lines[:, e, 0]) * x + gathered(lines[:, e, 1]) * y + gathered(lines[:, e, 2]) for e in range(3)),
    )  # (ty, tx, ts, ts, Kt)
    depth = gathered(plane[:, 0]) * x + gathered(plane[:, 1]) * y + gathered(plane[:, 2])
    edge_distance = dist
    if clip_near:
        # Covered: inside the edge lines and in front of the near line. Only the face's own
        # edge lines bound the margin test below: the near line appears when a vertex reaches
        # the plane, and would drop at once the candidates near that vertex that it admitted.
        n = near_line[tile_faces][:, :, None, None]  # (ty, tx, 1, 1, Kt, 2)
        dist = jnp.minimum(dist, n[..., 0] + n[..., 1] * depth)
    # Outside its triangle the plane is extrapolated: on a small face seen nearly edge-on it
    # reaches any value a few pixels away (a torus face 4 px off: 1.8 for vertex depths ~0.29,
    # which outranked the covering face at every pixel). Clipped to the face's depth range, as
    # the fragments' depth is (barycentric coordinates clipped to the triangle).
    depth = jnp.clip(depth, jnp.min(dv, axis=1)[tile_faces][:, :, None, None], nearest[tile_faces][:, :, None, None])
    ok = tile_ok[:, :, None, None, :]
    if sigma is None:
        pixel_key = jnp.where(ok & (dist >= 0), depth, -jnp.inf)
    else:
        sigma = lax.stop_gradient(jnp.asarray(sigma, dtype))
        gamma = lax.stop_gradient(jnp.asarray(1.0 if gamma is None else gamma, dtype))
        # The log-probability that the face covers the pixel, minus, for a face behind the
        # nearest covering one (the hard z-buffer's surface), its depth gap in units of gamma:
        # faces in front rank by how likely the noise makes them cover (they may occlude),
        # faces behind by how likely the depth noise lets them through. The visible face
        # (log-probability above log 1/2, no gap) always ranks first. (A SoftRas-like
        # log sigmoid(d / sigma) + z / gamma lets nearer faces that do not cover the pixel fill
        # the slots, and the visible face drops out of them.) Where no face covers the pixel,
        # front is -inf and the gap term is 0.
        front = jnp.max(jnp.where(ok & (dist >= 0), depth, -jnp.inf), axis=-1, keepdims=True)
        weight = log_sigmoid(dist / sigma) + jnp.minimum(depth - front, 0.0) / gamma
        pixel_key = jnp.where(ok & (edge_distance > -margin), weight, -jnp.inf)
    pixel_values, slot = lax.top_k(pixel_key, k_pixel)  # (ty, tx, ts, ts, K)
    faces_tile = jnp.broadcast_to(tile_faces[:, :, None, None, :], slot.shape[:4] + (k_tile,))
    face_index = jnp.take_along_axis(faces_tile, slot, axis=-1)
    present = pixel_values > -jnp.inf

    def to_image(a):
        a = jnp.swapaxes(a, 1, 2)  # (ty, ts, tx, ts, ...)
        a = a.reshape((ty * ts, tx * ts) + a.shape[4:])
        return a[:height, :width]

    face_index = jnp.where(present, face_index, 0)
    face_index, present = to_image(face_index), to_image(present)

    # The differentiable fragments of the selected faces only.
    if pixels is None:
        qx = (jnp.arange(width, dtype=dtype) + 0.5)[None, :, None]
        qy = (jnp.arange(height, dtype=dtype) + 0.5)[:, None, None]
    else:
        face_index = face_index.reshape(height * width, -1)[pixels]
        present = present.reshape(height * width, -1)[pixels]
        qx, qy = pixel_centres(pixels, width, dtype)
    if clip_near:
        distance, depth, weights = _clipped_fragments(mesh, camera, clipped, face_index, qx, qy, interior_edges)
        near_culled = jnp.zeros_like(tile_overflow)
    else:
        distance, depth, weights = _triangle_fragments(mesh, camera, projected, face_index, qx, qy, interior_edges)
        near_culled = _near_culled(mesh, camera, margin, cull_backfaces)
    return Fragments(
        face_index=face_index, present=present, distance=distance, depth=depth, barycentric=weights,
        tile_overflow=tile_overflow, near_culled=near_culled,
    )
