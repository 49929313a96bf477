"""Near-plane clipping (``clip_near=True``): a face crossing the plane z = near is drawn where it
is in front; without it (the default) such faces are culled whole, and counted."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rsmooth import render

SIZE = 32
NEAR = 0.5
# The camera frame is the world frame: x right, y down, z forward.
CAMERA = render.Camera(np.eye(3), np.zeros(3), fov=90.0, near=NEAR, far=10.0, image_size=(SIZE, SIZE))
FACES = np.array([[0, 1, 2], [0, 2, 3]])  # a square: the two faces share the diagonal 0-2
COLORS = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 1.0, 1.0]])
LIGHT = render.DirectionalLight(ambient=1.0, diffuse=0.0)  # rgb is the interpolated colour
KW = dict(sigma=0.7, gamma=0.02, faces_per_pixel=4, faces_per_tile=8, light=LIGHT)
MODES = ("hard", "soft", "perturbed")


def square(depth_near_edge, center=(0.03, -0.02, 1.2)):
    """A square tilted away from the camera, its lower edge (vertices 0, 1) at depths about
    `depth_near_edge` and its upper one at about 2.4 - depth_near_edge."""
    c = np.asarray(center)
    a = np.array([0.35, 0.02, 0.08])
    b = np.array([0.03, 0.3, c[2] - depth_near_edge])
    vertices = np.stack([c - a - b, c + a - b, c + a + b, c - a + b])
    return render.Mesh(vertices, FACES, COLORS)


@pytest.fixture(scope="module")
def draw():
    """f(key, mesh) -> (images by mode, fragments of the hard and soft renderers, gradient of the
    soft image's weighted sum with respect to the vertices), with clipping; jitted once for
    every test here (the meshes share their shapes): compiling the clipping code, forward and
    backward, is what this file's time goes to. One function rather than one per mode lets
    XLA share the soft and perturbed renderers' rasterization (the same options), and the
    fragments with the renderers' own."""
    renderers = {mode: render.Renderer(mode=mode, num_samples=64, clip_near=True, **KW) for mode in MODES}
    weights = render.Image(rgb=np.random.default_rng(1).uniform(size=(SIZE, SIZE, 3)), alpha=np.ones((SIZE, SIZE)))

    def f(key, mesh):
        def soft(vertices):
            return renderers["soft"](key, eqx.tree_at(lambda m: m.vertices, mesh, vertices), CAMERA)

        images = {mode: renderers[mode](key, mesh, CAMERA) for mode in ("hard", "perturbed")}
        images["soft"], pullback = jax.vjp(soft, mesh.vertices)
        (gradient,) = pullback(weights)
        fragments = {mode: renderers[mode].fragments(mesh, CAMERA) for mode in ("hard", "soft")}
        return images, fragments, gradient

    return jax.jit(f)


@pytest.fixture(scope="module")
def culled():
    """mesh -> without clipping (the default): the faces that the rasterizer draws (the mask of
    `project_faces`), and the hard and soft renderers' `near_culled`. A small program: jit
    drops the rest of their fragments, dead code here."""
    hard, soft = (render.Renderer(mode=mode, **KW) for mode in ("hard", "soft"))

    def f(mesh):
        drawn = render.project_faces(mesh, CAMERA)[3]
        return drawn, hard.fragments(mesh, CAMERA).near_culled, soft.fragments(mesh, CAMERA).near_culled

    return jax.jit(f)


def fragment_reference(mesh, face_index, flagged):
    """Naive reference for the fragments of faces entirely in front, in numpy: signed distance
    from the pixel centres to the projected faces (inside: positive; its magnitude to the
    flagged edges only, edge i from vertex i to i + 1), screen-space barycentric coordinates
    clipped to the triangle, the normalized inverse depth they interpolate, and the
    perspective-correct weights (screen weights divided by depth, renormalized)."""
    v = np.asarray(mesh.vertices)
    f = float(CAMERA.focal_length)
    screen = (f * v[:, :2] / v[:, 2:] + SIZE / 2)[FACES][face_index]  # (H, W, K, 3, 2)
    z = v[:, 2][FACES][face_index]  # (H, W, K, 3)
    flagged = flagged[face_index]
    ys, xs = np.meshgrid(np.arange(SIZE) + 0.5, np.arange(SIZE) + 0.5, indexing="ij")
    q = np.broadcast_to(np.stack([xs, ys], -1)[:, :, None, :], face_index.shape + (2,))
    distances, edges = [], []
    for i in range(3):
        a, b = screen[..., i, :], screen[..., (i + 1) % 3, :]
        t = np.clip(np.sum((q - a) * (b - a), -1) / np.sum((b - a) ** 2, -1), 0.0, 1.0)
        distances.append(np.where(flagged[..., i], np.linalg.norm(q - a - t[..., None] * (b - a), axis=-1), np.inf))
        edges.append((b - a)[..., 0] * (q - a)[..., 1] - (b - a)[..., 1] * (q - a)[..., 0])
    area = edges[0] + edges[1] + edges[2]  # twice the signed area: the edge functions sum to it
    bary = np.stack([edges[1], edges[2], edges[0]], -1) / area[..., None]  # vertex k faces edge k + 1
    inside = np.all(bary >= 0, axis=-1)
    distance = np.where(inside, 1.0, -1.0) * np.min(distances, axis=0)
    bary = np.maximum(bary, 0.0)
    bary = bary / np.sum(bary, -1, keepdims=True)
    depth = np.sum(bary * (1 / z - 1 / 10.0) / (1 / NEAR - 1 / 10.0), -1)
    weights = bary / z
    return distance, depth, weights / np.sum(weights, -1, keepdims=True)


def ray_cast(mesh):
    """Reference, pixel by pixel: the nearest hit of the pixel's ray with a face at depth >= near,
    its perspective-correct colour (3D barycentric coordinates of the hit) and its normalized
    inverse depth; alpha 0 where nothing is hit."""
    v = np.asarray(mesh.vertices)
    f = float(CAMERA.focal_length)
    alpha, rgb, depth = np.zeros((SIZE, SIZE)), np.zeros((SIZE, SIZE, 3)), np.zeros((SIZE, SIZE))
    for i in range(SIZE):
        for j in range(SIZE):
            ray = np.array([(j + 0.5 - SIZE / 2) / f, (i + 0.5 - SIZE / 2) / f, 1.0])
            best = np.inf
            for face in FACES:
                p = v[face]
                # p0 + s (p1 - p0) + t (p2 - p0) = z ray: z is the depth of the hit
                s, t, z = np.linalg.solve(np.stack([p[1] - p[0], p[2] - p[0], -ray], axis=1), -p[0])
                if min(s, t, 1 - s - t) >= 0 and NEAR <= z < best:
                    best = z
                    alpha[i, j] = 1.0
                    rgb[i, j] = (1 - s - t) * COLORS[face[0]] + s * COLORS[face[1]] + t * COLORS[face[2]]
                    depth[i, j] = (1 / z - 1 / 10.0) / (1 / NEAR - 1 / 10.0)
    return alpha, rgb, depth


def visible_area(mesh):
    """Closed form: the square cut by the plane z = near (Sutherland-Hodgman), projected, its
    area in pixels by the shoelace formula."""
    v = np.asarray(mesh.vertices)[[0, 1, 2, 3]]
    kept = []
    for k in range(4):
        a, b = v[k], v[(k + 1) % 4]
        if a[2] >= NEAR:
            kept.append(a)
        if (a[2] >= NEAR) != (b[2] >= NEAR):
            kept.append(a + (NEAR - a[2]) / (b[2] - a[2]) * (b - a))
    xy = np.array([float(CAMERA.focal_length) * p[:2] / p[2] for p in kept])
    x, y = xy[:, 0], xy[:, 1]
    return 0.5 * abs(np.sum(x * np.roll(y, -1) - y * np.roll(x, -1)))


def test_square_crossing_the_near_plane_draws_its_part_in_front(draw, culled, getkey):
    # Vertices 0 and 1 behind the near plane: face (0, 1, 2) keeps a triangle, face (0, 2, 3) a
    # quadrilateral. Without clipping both faces are dropped: an empty image.
    mesh = square(0.2)
    z = np.asarray(mesh.vertices)[:, 2]
    assert z[0] < NEAR and z[1] < NEAR and z[2] > NEAR and z[3] > NEAR
    alpha, rgb, depth = ray_cast(mesh)
    images, fragments, _ = draw(getkey(), mesh)
    hard = images["hard"]
    np.testing.assert_array_equal(np.asarray(hard.alpha), alpha)
    covered = alpha > 0
    np.testing.assert_allclose(np.asarray(hard.rgb)[covered], rgb[covered], atol=1e-9)  # perspective-correct
    np.testing.assert_allclose(np.asarray(fragments["hard"].depth[..., 0])[covered], depth[covered], atol=1e-9)
    area = visible_area(mesh)
    assert area > 100.0
    assert float(jnp.sum(hard.alpha)) == pytest.approx(area, rel=0.1)  # pixel counting
    # Smoothed coverage integrates to about the area (the polygon stays 3 sigma inside the
    # image; its acute corners and the two faces' cuts meeting add a few sigma^2, as in
    # test_render's square). The perturbed estimate's own error is far below that: a pixel's
    # standard deviation is at most 1/2 / sqrt(64) = 0.0625, with independent noise across
    # pixels, nonzero in the band of about 2 sigma along the ~60-px boundary: about
    # 0.0625 * sqrt(100) ~ 0.6 px^2 on the sum, under 1 % of the area.
    assert float(jnp.sum(images["soft"].alpha)) == pytest.approx(area, rel=0.08)
    assert float(jnp.sum(images["perturbed"].alpha)) == pytest.approx(area, rel=0.1)
    assert not np.any(np.asarray(culled(mesh)[0]))  # culled whole without clipping


def test_faces_behind_the_near_plane_draw_nothing(draw, culled, getkey):
    # depths 0.4 to 0.1, then with vertices on the camera plane (z = 0) and behind it
    for shift in (0.0, 0.3, 0.6):
        mesh = square(0.3, center=(0.03, -0.02, 0.35 - shift))
        assert np.all(np.asarray(mesh.vertices)[:, 2] < NEAR)
        images, fragments, _ = draw(getkey(), mesh)
        for mode in MODES:
            image = images[mode]
            assert float(jnp.max(image.alpha)) == 0.0 and float(jnp.max(image.rgb)) == 0.0, (mode, shift)
        # nothing in front to draw: no face crosses the plane, none is counted as culled
        drawn, hard_culled, soft_culled = culled(mesh)
        assert not np.any(np.asarray(drawn))
        assert int(hard_culled) == 0 and int(soft_culled) == 0


def test_faces_in_front_keep_the_unclipped_fragments(draw, culled, getkey):
    # A face entirely in front goes through the triangle's own screen-space formulas: signed
    # distance (to the silhouette edges only, for the soft renderer's interior_edges=False),
    # barycentric coordinates clipped to the triangle, depth interpolated in screen space,
    # weights divided by depth, as without clipping. Checked against a naive reference, at the
    # covered pixels (hard) and at the candidates of smoothed rendering too (pixels outside
    # the triangles, within the margin).
    mesh = square(0.9)
    assert np.all(np.asarray(mesh.vertices)[:, 2] > NEAR)
    _, fragments, _ = draw(getkey(), mesh)
    # Only the diagonal, shared by the two faces (both seen from the front), is interior.
    interior = np.array([[{int(f[i]), int(f[(i + 1) % 3])} == {0, 2} for i in range(3)] for f in FACES])
    for mode, flagged, count in (("hard", np.ones_like(interior), 60), ("soft", ~interior, 200)):
        fragment = fragments[mode]
        present = np.asarray(fragment.present)
        assert present.sum() > count, mode
        distance, depth, weights = fragment_reference(mesh, np.asarray(fragment.face_index), flagged)
        np.testing.assert_allclose(np.asarray(fragment.distance)[present], distance[present], atol=1e-12, err_msg=mode)
        np.testing.assert_allclose(np.asarray(fragment.depth)[present], depth[present], atol=1e-12, err_msg=mode)
        np.testing.assert_allclose(np.asarray(fragment.barycentric)[present], weights[present], atol=1e-12, err_msg=mode)

    assert bool(np.all(np.asarray(culled(mesh)[0])))  # drawn without clipping too


def test_faces_crossing_the_near_plane_are_counted_when_culled(draw, culled, getkey):
    key = getkey()
    # Both faces cross the plane: culled whole without clipping, and counted; never with it.
    mesh = square(0.2)
    _, hard_culled, soft_culled = culled(mesh)
    assert int(hard_culled) == 2 and int(soft_culled) == 2
    fragments = draw(key, mesh)[1]
    assert int(fragments["hard"].near_culled) == 0 and int(fragments["soft"].near_culled) == 0
    # Entirely in front: nothing culled.
    _, hard_culled, soft_culled = culled(square(0.9))
    assert int(hard_culled) == 0 and int(soft_culled) == 0
    # A floor below the camera that crosses its near plane out of view (all its vertices below
    # the lower plane y = z of this 90-degree camera's frustum) is not counted, and clipping
    # draws nothing of it either; raised into view, its two faces are counted. The soft
    # renderer's count reaches `margin` = 3 sigma = 2.1 px beyond the image, where smoothed
    # coverage still shows: the floor at y = 0.6, 1.45 px below it at z = 0.55, is counted.
    floor = np.array([[-0.3, 0.0, 0.2], [0.3, 0.0, 0.2], [0.3, 0.0, 0.55], [-0.3, 0.0, 0.55]])
    for height, culled_hard, culled_soft in ((0.7, 0, 0), (0.6, 0, 2), (0.4, 2, 2)):
        mesh = render.Mesh(floor + np.array([0.0, height, 0.0]), FACES, COLORS)
        _, hard_culled, soft_culled = culled(mesh)
        assert (int(hard_culled), int(soft_culled)) == (culled_hard, culled_soft), height
        images = draw(key, mesh)[0]
        assert (float(jnp.sum(images["hard"].alpha)) > 0) == (culled_hard > 0), height
        assert (float(jnp.sum(images["soft"].alpha)) > 1e-3) == (culled_soft > 0), height


def test_image_is_continuous_as_a_vertex_crosses_the_near_plane(draw, getkey):
    # Vertex 1 moves through the near plane. Without clipping, both its faces vanish at once
    # (about 60 pixels of alpha); with it, the image changes by the sliver the plane cuts off.
    key = getkey()

    def images(dz):
        vertices = np.asarray(square(0.7).vertices).copy()
        vertices[1, 2] = NEAR + dz
        return draw(key, render.Mesh(vertices, FACES, COLORS))[0]

    below, on, above = images(-1e-7), images(0.0), images(1e-7)
    assert float(jnp.sum(on["hard"].alpha)) > 60
    for mode in MODES:
        for image in (below[mode], above[mode]):
            np.testing.assert_allclose(np.asarray(image.alpha), np.asarray(on[mode].alpha), atol=1e-5, err_msg=mode)
            np.testing.assert_allclose(np.asarray(image.rgb), np.asarray(on[mode].rgb), atol=1e-5, err_msg=mode)
    # Over a coarse sweep through the plane the smoothed silhouette grows (the vertex comes
    # nearer) by steps of a few pixels, none of them the faces' 60.
    sums = [float(jnp.sum(images(dz)["soft"].alpha)) for dz in np.linspace(0.06, -0.06, 7)]
    steps = np.diff(sums)
    assert np.all(steps > 0) and np.all(steps < 6.0)


def test_gradients_are_finite_with_vertices_on_the_near_and_camera_planes(draw, getkey):
    vertices = np.asarray(square(0.7).vertices).copy()
    vertices[1, 2] = NEAR  # on the near plane
    vertices[0, 2] = 0.0  # on the camera plane: its projection is undefined
    mesh = render.Mesh(vertices, FACES, COLORS)
    # The soft image's gradient only. The hard renderer's derivatives go through the same
    # clipped fragments (but for the coverage, which has none), and so does the perturbed
    # renderer's, whose fragments are the soft one's (the same options): a fragment
    # derivative that is not finite would make the soft gradient NaN too, whatever weight
    # the aggregation gives it (0 * inf is NaN). A second backward pass, for the perturbed
    # image, would double this file's compilation time.
    images, _, gradient = draw(getkey(), mesh)
    assert float(jnp.sum(images["soft"].alpha)) > 0
    assert np.all(np.isfinite(np.asarray(gradient)))
    assert float(jnp.max(jnp.abs(gradient))) > 0


@pytest.mark.parametrize("with_edges", [False, True])
@pytest.mark.parametrize("output", ["distance", "depth", "weights", "all"])
def test_clipped_fragment_derivatives_equal_autodiff_of_the_formulas(getkey, with_edges, output):
    # The clipped fragments' hand-written forward mode (rsmooth.render._raster._clipped_geometry)
    # and JAX's transpose of it (reverse mode), against JAX's derivatives of the same formulas,
    # with respect to the polygons, the camera-frame vertices and the camera's near, far and
    # focal length: random faces in front of, across and behind the near plane (their polygons
    # from _clip_faces, 3 or 4 slots), with no counted edge or all four, around a 12 x 10 grid
    # of pixels, inside and outside. The tangents are drawn independently for polygons and
    # vertices (the formulas' derivatives, not the renderer's chain through _clip_faces).
    from rsmooth.render import _raster

    faces = 12
    vertices = jax.random.uniform(getkey(), (faces, 3, 3), minval=-1.0, maxval=1.0)
    vertices = vertices.at[..., 2].set(jax.random.uniform(getkey(), (faces, 3), minval=-0.3, maxval=2.5))
    vertices = vertices.at[2, :, 2].set(jnp.array([0.2, -0.1, 0.3]))  # behind the near plane
    camera = render.Camera(np.eye(3), np.zeros(3), fov=90.0, near=NEAR, far=4.0, image_size=(12, 10))
    mesh = render.Mesh(vertices.reshape(-1, 3), np.arange(3 * faces).reshape(faces, 3))
    clipped = _raster._clip_faces(mesh, camera)
    in_front = np.sum(np.asarray(vertices[..., 2]) > NEAR, axis=1)
    assert {0, 1, 2, 3} <= set(in_front.tolist())  # every kind of face
    flags = jax.random.bernoulli(getkey(), 0.5, (faces, 4)).at[0].set(False).at[1].set(True) if with_edges else None
    index = jax.random.randint(getkey(), (12, 10, 4), 0, faces)
    qx = (jnp.arange(10.0) + 0.5)[None, :, None]
    qy = (jnp.arange(12.0) + 0.5)[:, None, None]
    lens = (camera.near, camera.far, camera.focal_length)
    args = (clipped.polygon, clipped.vertices, lens)
    keep = {"distance": 0, "depth": 1, "weights": 2}.get(output)

    def function(fn):
        def outputs(*a):
            values = fn(*a, flags, index, qx, qy, qx - 5.0, qy - 6.0)
            return values if keep is None else values[keep]

        return outputs

    reference, new = function(_raster._clipped_values), function(_raster._clipped_geometry)
    tangents = jax.tree.map(lambda a: jax.random.normal(getkey(), jnp.shape(a)), args)
    # A repeated slot moves with its original, as through _clip_faces: where two edges of a
    # polygon meet at one point (or overlap: a face behind the plane), their distances tie,
    # and of the tied edges autodiff takes the average derivative, the hand-written one the first.
    repeated = [jnp.all(clipped.polygon[:, k] == clipped.polygon[:, k - 1], axis=-1)[:, None] for k in range(4)]
    d_polygon = tangents[0]
    for k in range(1, 4):
        d_polygon = d_polygon.at[:, k].set(jnp.where(repeated[k], d_polygon[:, k - 1], d_polygon[:, k]))
    tangents = (d_polygon,) + tangents[1:]

    def gathered(polygon_cotangent):  # the transpose: a repeated slot's cotangent goes to its original
        for k in range(3, 0, -1):
            moved = jnp.where(repeated[k], polygon_cotangent[:, k], 0.0)
            polygon_cotangent = polygon_cotangent.at[:, k].add(-moved).at[:, k - 1].add(moved)
        return polygon_cotangent

    values, got = jax.jvp(new, args, tangents)
    _, expected = jax.jvp(reference, args, tangents)
    # the values are the formulas' bit for bit (JAX's own forward mode rounds the depth otherwise, by an ulp)
    for a, b in zip(jax.tree.leaves(reference(*args)), jax.tree.leaves(values)):
        np.testing.assert_array_equal(a, b)
    for e, g in zip(jax.tree.leaves(expected), jax.tree.leaves(got)):
        assert np.all(np.isfinite(g))
        np.testing.assert_allclose(g, e, rtol=1e-9, atol=1e-9 * float(jnp.max(jnp.abs(e))) + 1e-12)
    cotangents = jax.tree.map(lambda v: jax.random.normal(getkey(), v.shape), values)
    _, vjp = jax.vjp(new, *args)
    _, reference_vjp = jax.vjp(reference, *args)
    expected, got = reference_vjp(cotangents), vjp(cotangents)
    expected, got = ((gathered(c[0]),) + c[1:] for c in (expected, got))
    for name, e, g in zip(("polygon", "vertices", "lens"), expected, got):
        for e_leaf, g_leaf in zip(jax.tree.leaves(e), jax.tree.leaves(g)):
            assert np.all(np.isfinite(g_leaf)), name
            scale = float(jnp.max(jnp.abs(e_leaf)))
            np.testing.assert_allclose(g_leaf, e_leaf, rtol=1e-9, atol=1e-9 * scale + 1e-12, err_msg=name)
    if output in ("distance", "all"):
        assert float(jnp.max(jnp.abs(got[0]))) > 0  # the distance reaches the polygons
    if output in ("depth", "all"):
        assert all(abs(float(g)) > 0 for g in got[2][:2])  # near and far move the depth


@pytest.mark.parametrize("depth_near_edge", [0.2, 0.5, 0.9])
def test_soft_gradient_through_clipped_faces_equals_finite_differences(draw, getkey, depth_near_edge):
    # End to end, through _clip_faces and the clipped fragments' hand-written derivative: the
    # gradient of the soft image's weighted sum with respect to the vertices, along a random
    # direction, against central differences. Vertex depths (see square()): 0.12, 0.28, 2.28,
    # 2.12 (the face 0-1-2 has one vertex in front: 3 slots; 0-2-3 two: 4 slots); 0.42, 0.58,
    # 1.98, 1.82 (each face has one vertex behind); all in front.
    key = getkey()
    mesh = square(depth_near_edge)
    vertices = np.asarray(mesh.vertices)
    assert np.sum(vertices[:, 2] < NEAR) == {0.2: 2, 0.5: 1, 0.9: 0}[depth_near_edge]
    weights = render.Image(rgb=np.random.default_rng(1).uniform(size=(SIZE, SIZE, 3)), alpha=np.ones((SIZE, SIZE)))
    direction = np.asarray(jax.random.normal(getkey(), vertices.shape))

    def loss(v):
        image = draw(key, render.Mesh(v, FACES, COLORS))[0]["soft"]
        return float(jnp.sum(image.rgb * weights.rgb) + jnp.sum(image.alpha * weights.alpha))

    h = 1e-6
    finite_difference = (loss(vertices + h * direction) - loss(vertices - h * direction)) / (2 * h)
    gradient = np.asarray(draw(key, mesh)[2])
    assert abs(finite_difference) > 1e-2
    np.testing.assert_allclose(np.sum(gradient * direction), finite_difference, rtol=1e-5)
