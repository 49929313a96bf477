"""The renderer: areas, occlusion, aggregation, derivatives, empty views, errors."""

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.scipy.stats import norm

from rsmooth import noise, render

SIZE = 32
CAMERA = render.look_at(jnp.array([0.0, 0.0, 4.0]), image_size=(SIZE, SIZE), fov=40.0, near=1.0, far=10.0)


# Every test mesh has 6 vertices, 2 faces and colours: one compilation per renderer.
FACES = np.array([[0, 1, 2], [3, 4, 5]])


def square(side, z=0.0, color=(0.8, 0.8, 0.8)):
    h = side / 2
    vertices = np.array([[-h, -h, z], [h, -h, z], [h, h, z], [-h, -h, z], [h, h, z], [-h, h, z]])
    return render.Mesh(vertices, FACES, np.tile(np.asarray(color, float), (6, 1)))


def side_for_pixels(pixels, depth=4.0):
    return pixels * depth / float(CAMERA.focal_length)


@pytest.fixture(scope="module")
def renderers():
    """Jitted renderers f(key, mesh, camera=CAMERA), compiled once per mode for all tests."""
    kw = dict(sigma=0.7, gamma=0.01, faces_per_pixel=4, faces_per_tile=16)
    configs = {
        "hard": render.Renderer(mode="hard", **kw),
        "soft": render.Renderer(mode="soft", **kw),
        "perturbed": render.Renderer(mode="perturbed", num_samples=64, **kw),
    }

    def wrap(renderer):
        jitted = jax.jit(lambda k, m, c: renderer(k, m, c))
        # The camera is always passed explicitly: jit caches a defaulted argument separately.
        return lambda k, m, c=CAMERA: jitted(k, m, c)

    return {mode: wrap(r) for mode, r in configs.items()}


def test_fronto_parallel_square_covers_its_area(renderers, getkey):
    mesh = square(side_for_pixels(12.0))  # 12 x 12 pixels, edges between pixel centres
    hard = renderers["hard"](None, mesh)
    assert float(jnp.sum(hard.alpha)) == pytest.approx(144.0)
    assert set(np.unique(np.asarray(hard.alpha)).tolist()) == {0.0, 1.0}
    for mode in ("soft", "perturbed"):
        image = renderers[mode](getkey(), mesh)
        assert float(jnp.sum(image.alpha)) == pytest.approx(144.0, rel=0.06), mode


def test_perturbed_render_of_an_edge_is_the_smoothed_step(renderers, getkey):
    """Across the middle of the square's left edge, alpha is Phi(d / sigma) (Gaussian noise)."""
    mesh = square(side_for_pixels(12.5))  # edges at 9.75 and 22.25: centres at +-0.25, 0.75, ...
    # Columns 5-12: in these rows column 13 comes within 1 px of the square's diagonal, an edge inside the
    # silhouette; this square's triangles share no vertex, so the diagonal is a boundary edge of both
    # and leaves a seam (see test_interior_edges_leave_no_seam for a connected square).
    row = np.mean(np.stack([np.asarray(renderers["perturbed"](getkey(), mesh).alpha[14:18, 5:13]) for _ in range(4)]), axis=(0, 1))
    d = np.arange(5, 13) + 0.5 - 9.75
    np.testing.assert_allclose(row, norm.cdf(d / 0.7), atol=0.04)


def test_nearer_triangle_occludes_the_farther_one(renderers, getkey):
    red, green = (1.0, 0.0, 0.0), (0.0, 1.0, 0.0)
    for z_red, z_green, winner in ((0.0, 0.5, 1), (0.5, 0.0, 0)):
        v = np.array([[-1.0, -1, z_red], [1, -1, z_red], [0, 1, z_red], [-0.5, -0.3, z_green], [1.2, -0.3, z_green], [0.5, 1.2, z_green]])
        colors = np.array([red] * 3 + [green] * 3)
        mesh = render.Mesh(v, FACES, colors)
        for mode in ("hard", "soft", "perturbed"):
            rgb = np.asarray(renderers[mode](getkey(), mesh).rgb)
            # A pixel in the overlap (world (0.2, 0.0) -> image column ~18.2, row ~16-ish).
            pixel = rgb[15:17, 17:19].mean(axis=(0, 1))
            assert np.argmax(pixel) == winner, (mode, pixel)
            assert pixel[winner] > 5 * pixel[1 - winner], (mode, pixel)


def test_gumbel_aggregation_is_the_softmax_of_depths(getkey):
    depth = jnp.array([0.30, 0.32, 0.25])
    gamma = 0.02
    key = getkey()

    def weights(z):
        return render.perturbed_aggregate(key, jnp.full(3, 100.0), z, sigma=1.0, gamma=gamma, num_samples=20000, background_depth=0.28)

    # Value and Jacobian estimate (the same samples) in one compilation.
    w, jac = jax.jit(lambda z: (weights(z), jax.jacfwd(weights)(z)))(depth)
    p = jax.nn.softmax(jnp.append(depth, 0.28) / gamma)
    np.testing.assert_allclose(w, p, atol=0.02)
    exact = (jnp.diag(p) - jnp.outer(p, p))[:, :3] / gamma
    np.testing.assert_allclose(jac, exact, atol=0.1 * float(jnp.max(jnp.abs(exact))))
    # The soft (SoftRas) aggregation is the softmax over faces when every face covers the pixel.
    soft = render.soft_aggregate(jnp.full(3, 100.0), depth, sigma=1.0, gamma=gamma)
    np.testing.assert_allclose(soft, jnp.append(jax.nn.softmax(depth / gamma), 0.0), atol=1e-12)
    # Gaussian depth noise, one face: it beats the background with probability Phi(dz / (gamma sqrt 2)).
    w = jax.jit(lambda k: render.perturbed_aggregate(k, jnp.array([100.0]), jnp.array([0.3]), sigma=1.0, gamma=gamma, num_samples=10000, depth_noise=noise.Gaussian(), background_depth=0.28))(getkey())
    assert float(w[0]) == pytest.approx(float(norm.cdf(0.02 / (gamma * np.sqrt(2)))), abs=0.02)


def test_hard_gradient_is_zero_and_perturbed_gradient_follows_finite_differences(renderers, getkey):
    mesh = square(side_for_pixels(10.0))
    ramp = jnp.asarray(np.arange(SIZE) - SIZE / 2.0)
    weights = ramp[None, :] + 0.5 * ramp[:, None]

    def loss(renderer, key, t):
        return jnp.sum(renderer(key, render.transform_mesh(mesh, jnp.eye(3), t)).alpha * weights)

    kw = dict(sigma=0.7, gamma=0.01, faces_per_pixel=4, faces_per_tile=16)
    hard = render.Renderer(mode="hard", **kw)
    perturbed = render.Renderer(mode="perturbed", num_samples=64, **kw)
    t0 = jnp.zeros(3)
    key = getkey()
    assert np.all(np.asarray(jax.jit(jax.grad(lambda t: loss(lambda k, m: hard(k, m, CAMERA), key, t)))(t0)) == 0.0)
    grad = np.asarray(jax.jit(jax.grad(lambda t: loss(lambda k, m: perturbed(k, m, CAMERA), key, t)))(t0))
    # Finite differences of the smoothed image, on the same samples (common random numbers).
    h = 0.05
    fd = np.array([(float(loss(renderers["perturbed"], key, t0.at[i].add(h))) - float(loss(renderers["perturbed"], key, t0.at[i].add(-h)))) / (2 * h) for i in range(2)])
    # +x in the world is +x (right) in the image, +y is up (smaller rows).
    assert grad[0] > 0 and grad[1] < 0
    np.testing.assert_array_equal(np.sign(grad[:2]), np.sign(fd))
    np.testing.assert_allclose(grad[:2], fd, rtol=0.3)


def test_leave_one_out_baseline_keeps_the_image_and_the_mean_gradient_and_lowers_its_variance(getkey):
    """The baseline changes only the derivative estimate: the image is the same Monte-Carlo
    mean; the gradient's mean is the same (both unbiased) and, at the square's edges, where the
    hard pixel is 0 or 1 and the smoothed one in between, its variance is lower."""
    mesh = square(side_for_pixels(10.0))
    ramp = jnp.asarray(np.arange(SIZE) - SIZE / 2.0)
    weights = ramp[None, :] + 0.5 * ramp[:, None]
    kw = dict(sigma=0.7, gamma=0.01, faces_per_pixel=4, faces_per_tile=16, num_samples=16)
    keys = jax.random.split(getkey(), 192)
    images, grads = {}, {}
    for baseline in (True, "leave-one-out"):
        renderer = render.Renderer(mode="perturbed", baseline=baseline, **kw)

        def loss(key, t):
            return jnp.sum(renderer(key, render.transform_mesh(mesh, jnp.eye(3), t), CAMERA).alpha * weights)

        images[baseline] = jax.jit(lambda k: renderer(k, mesh, CAMERA).rgba())(keys[0])
        grads[baseline] = np.asarray(jax.jit(jax.vmap(jax.grad(loss, argnums=1), in_axes=(0, None)))(keys, jnp.zeros(3)))[:, :2]
    np.testing.assert_allclose(images[True], images["leave-one-out"], rtol=1e-6, atol=1e-6)
    a, b = grads[True], grads["leave-one-out"]
    std_error = np.sqrt((a.var(axis=0) + b.var(axis=0)) / len(keys))
    assert np.all(np.abs(a.mean(axis=0) - b.mean(axis=0)) <= 4.5 * std_error), (a.mean(axis=0), b.mean(axis=0), std_error)
    # The total variance's ratio is 0.68-0.79 over seeds with 192 keys: pixels away from the
    # edge gain less than the 0.27 of a pixel centred on it (tests/test_estimators.py)
    assert np.sum(b.var(axis=0)) < 0.85 * np.sum(a.var(axis=0)), (a.var(axis=0), b.var(axis=0))
    with pytest.raises(ValueError, match="needs num_samples >= 2"):
        render.Renderer(mode="perturbed", num_samples=1, baseline="leave-one-out")


def test_mesh_behind_or_beside_the_camera_renders_the_background(renderers, getkey):
    mesh = square(1.0)
    looking_away = render.look_at(jnp.array([0.0, 0.0, 4.0]), target=jnp.array([0.0, 0.0, 8.0]), image_size=(SIZE, SIZE), near=1.0, far=10.0)
    beside = render.look_at(jnp.array([0.0, 0.0, 4.0]), target=jnp.array([8.0, 0.0, 4.0]), image_size=(SIZE, SIZE), near=1.0, far=10.0)
    for camera in (looking_away, beside):
        for mode in ("hard", "soft", "perturbed"):
            image = renderers[mode](getkey(), mesh, camera)
            assert float(jnp.max(image.alpha)) == 0.0 and float(jnp.max(image.rgb)) == 0.0, mode
    renderer = render.Renderer(mode="soft", sigma=0.7, gamma=0.01, faces_per_pixel=4, faces_per_tile=16)
    grad = jax.jit(jax.grad(lambda v: jnp.sum(renderer(None, eqx.tree_at(lambda m: m.vertices, mesh, v), looking_away).rgb)))(mesh.vertices)
    assert np.all(np.asarray(grad) == 0.0)


def test_views_batch_under_vmap(renderers):
    mesh = square(side_for_pixels(10.0), color=(0.2, 0.5, 0.9))
    eyes = jnp.array([[0.0, 0.0, 4.0], [1.0, 0.5, 3.0]])
    cameras = jax.vmap(lambda e: render.look_at(e, image_size=(SIZE, SIZE), fov=40.0, near=1.0, far=10.0))(eyes)
    batch = jax.vmap(lambda c: renderers["hard"](None, mesh, c))(cameras)
    for i in range(2):
        single = renderers["hard"](None, mesh, jax.tree.map(lambda a: a[i], cameras))
        np.testing.assert_allclose(batch.rgb[i], single.rgb, atol=1e-12)
        assert float(jnp.sum(single.alpha)) > 20
    assert not np.allclose(batch.alpha[0], batch.alpha[1])


def test_bad_renderer_inputs():
    with pytest.raises(ValueError, match="mode"):
        render.Renderer(mode="blurry")
    with pytest.raises(ValueError, match="sigma"):
        render.Renderer(sigma=0.0)
    with pytest.raises(ValueError, match="faces_per_tile"):
        render.Renderer(faces_per_pixel=8, faces_per_tile=4)
    with pytest.raises(ValueError, match="density"):
        render.Renderer(coverage_noise=noise.Uniform())
    with pytest.raises(ValueError, match="key"):
        render.Renderer(mode="perturbed")(None, render.cube(), CAMERA)
    with pytest.raises(TypeError, match="Mesh"):
        render.Renderer(mode="hard")(None, np.zeros((3, 3)), CAMERA)


@pytest.mark.parametrize("name, value", [("sigma", np.inf), ("gamma", np.inf), ("sigma", np.nan), ("dilation", np.inf)])
def test_renderer_settings_must_be_finite(name, value):
    with pytest.raises(ValueError, match=f"^{name} must be"):
        render.Renderer(**{name: value})


@pytest.mark.parametrize("mode", ["soft", "perturbed"])
@pytest.mark.parametrize("name, value", [("sigma", -1.0), ("sigma", 0.0), ("sigma", np.nan), ("gamma", np.inf), ("gamma", -0.01)])
def test_per_call_noise_levels_must_be_positive_and_finite(mode, name, value):
    # Checked on the host before anything is traced; a NaN sigma was reported as a non-finite x.
    renderer = render.Renderer(mode=mode)
    with pytest.raises(ValueError, match=rf"^{name} must be positive and finite, got {value}"):
        renderer(jax.random.key(0), render.cube(), CAMERA, **{name: value})
    with pytest.raises(ValueError, match=f"^{name} must be positive and finite"):
        renderer.fragments(render.cube(), CAMERA, **{name: value})
    with pytest.raises(ValueError, match=f"^{name} must be a scalar"):
        renderer(jax.random.key(0), render.cube(), CAMERA, **{name: np.ones(2)})


def test_traced_noise_level_and_camera_pose_are_checked_when_the_program_runs():
    renderer = render.Renderer(mode="soft", faces_per_pixel=2, faces_per_tile=12)
    camera = render.look_at(jnp.array([0.0, 0.0, 4.0]), image_size=(8, 8))
    draw = eqx.filter_jit(lambda sigma, translation: renderer(
        None, render.cube(), eqx.tree_at(lambda c: c.translation, camera, translation), sigma=sigma).alpha)
    assert float(jnp.sum(draw(jnp.asarray(1.0), camera.translation))) > 0
    with pytest.raises(Exception, match="sigma must be positive and finite"):
        draw(jnp.asarray(-1.0), camera.translation).block_until_ready()
    with pytest.raises(Exception, match="camera rotation and translation must be finite"):
        draw(jnp.asarray(1.0), camera.translation.at[1].set(jnp.nan)).block_until_ready()


def test_renderer_rejects_a_camera_with_a_nan_pose():
    # A camera changed after it was made (its constructor checks it): the renderer checks again.
    camera = eqx.tree_at(lambda c: c.rotation, CAMERA, CAMERA.rotation.at[0, 0].set(jnp.nan))
    for mode in ("hard", "perturbed"):
        with pytest.raises(ValueError, match="camera rotation must be finite"):
            render.Renderer(mode=mode)(jax.random.key(0), render.cube(), camera)


@pytest.mark.parametrize(
    "name, mesh",
    [("cube", render.cube(1.2)), ("icosphere", render.icosphere(1)), ("torus", render.torus(0.7, 0.3, 12, 6))],
)
def test_backface_culling_keeps_the_hard_image_of_closed_meshes(name, mesh, getkey):
    # Closed, outward-oriented primitives: the faces seen from behind are hidden anyway, so
    # culling them changes no pixel (and would blank the visible side if the sense were wrong).
    mesh = render.position_colors(mesh)
    kw = dict(mode="hard", faces_per_pixel=8, faces_per_tile=64)
    plain = jax.jit(lambda m: render.Renderer(**kw)(None, m, CAMERA))
    culled = jax.jit(lambda m: render.Renderer(cull_backfaces=True, **kw)(None, m, CAMERA))
    for _ in range(2):
        posed = render.transform_mesh(mesh, render.random_rotation(getkey()))
        a, b = plain(posed), culled(posed)
        assert float(jnp.sum(a.alpha)) > 50
        np.testing.assert_array_equal(np.asarray(a.alpha), np.asarray(b.alpha))
        np.testing.assert_allclose(np.asarray(a.rgb), np.asarray(b.rgb), atol=1e-12)


@pytest.mark.slow
def test_backface_culling_drops_a_square_seen_from_behind(getkey):
    front = square(side_for_pixels(10.0))
    back = render.Mesh(front.vertices, front.faces[:, ::-1], front.colors)
    for mode, extra in [("hard", {}), ("perturbed", dict(num_samples=8))]:
        r = render.Renderer(mode=mode, cull_backfaces=True, sigma=0.7, faces_per_pixel=4, faces_per_tile=16, **extra)
        alpha = jax.jit(lambda key, mesh: r(key, mesh, CAMERA).alpha)
        assert float(jnp.sum(alpha(getkey(), front))) > 80
        assert float(jnp.max(alpha(getkey(), back))) == 0.0


def test_slots_beyond_any_noise_have_zero_sigma_derivative(getkey):
    # A face with no silhouette edge is at 1e15 px (always covered), an empty slot at -1e20
    # (never): the weights then depend on the depth noise only, so the estimated derivative
    # with respect to sigma is 0, not the 1e14-sized d(d / sigma)/d sigma of the raw distance.
    def weights(sigma):
        return render.perturbed_aggregate(
            getkey(), jnp.array([1e15, 1e15, -1e20]), jnp.array([0.3, 0.31, 0.5]), sigma=sigma, gamma=0.02, num_samples=16
        )

    d_sigma = jax.jacfwd(weights)(2.0)
    np.testing.assert_array_equal(np.asarray(d_sigma), 0.0)


@pytest.mark.parametrize("mode", ["soft", "perturbed"])
def test_interior_edges_leave_no_seam(renderers, mode, getkey):
    # The square's two triangles share a diagonal. Smoothing every triangle edge (SoftRas, the
    # paper's perturbed coverage) gives each side coverage ~1/2 there: alpha ~3/4 along it.
    # Smoothing only the silhouette keeps the inside covered; the outline is the same.
    # (Edges are matched by vertex index: the two triangles share the diagonal's two vertices.)
    loose = square(side_for_pixels(12.5))  # outer edges at 9.75 and 22.25 px
    mesh = render.Mesh(loose.vertices[np.array([0, 1, 2, 5])], np.array([[0, 1, 2], [0, 2, 3]]), loose.colors[:4])
    kw = dict(mode=mode, sigma=0.7, gamma=0.01, faces_per_pixel=4, faces_per_tile=16, num_samples=64)
    seamed, seamless = render.Renderer(interior_edges=True, **kw), render.Renderer(**kw)
    with_seam = np.asarray(seamed(getkey(), mesh, CAMERA).alpha)
    without = np.asarray(seamless(getkey(), mesh, CAMERA).alpha)
    inside = (slice(13, 19), slice(13, 19))  # >= 3.25 px = 4.6 sigma from the outer edges
    assert with_seam[inside].min() < 0.85
    assert without[inside].min() > 0.98
    tolerance = 1e-6 if mode == "soft" else 0.25  # one Monte-Carlo draw per pixel, M = 64
    y, x = np.mgrid[:SIZE, :SIZE] + 0.5
    outline = (np.abs(x - y) > 4) & (np.abs(x + y - SIZE) > 4)  # away from both diagonals: the same edges
    np.testing.assert_allclose(without[outline], with_seam[outline], atol=tolerance)


def test_edge_neighbors_pair_the_faces_of_closed_and_open_meshes():
    for mesh in (render.icosphere(1), render.torus(0.7, 0.3, 12, 6), render.cube(1.0)):
        faces = np.asarray(mesh.faces)
        neighbor = np.asarray(render.edge_neighbors(faces))  # concrete faces: paired with numpy
        np.testing.assert_array_equal(np.asarray(jax.jit(render.edge_neighbors)(faces)), neighbor)  # traced: jnp
        assert (neighbor >= 0).all()  # closed: every edge has a face across
        for f in range(len(faces)):
            for i in range(3):
                g = neighbor[f, i]
                edge = {faces[f, i], faces[f, (i + 1) % 3]}
                assert g != f and edge <= set(faces[g].tolist())
    np.testing.assert_array_equal(np.asarray(render.edge_neighbors(FACES)), -np.ones((2, 3)))  # two separate triangles
    open_square = np.array([[0, 1, 2], [0, 2, 3]])
    np.testing.assert_array_equal(np.asarray(render.edge_neighbors(open_square)), [[-1, -1, 1], [0, -1, -1]])


def test_forward_and_reverse_mode_give_the_same_image_jacobian(getkey):
    # The image's Jacobian with respect to a pose (axis-angle, translation) by jacfwd (the
    # fragments' hand-written forward mode, the estimator's linear tangent) and reverse mode
    # (their transposes): for the same key, vector-Jacobian products with random cotangents
    # equal the forward Jacobian's transpose times them, up to rounding (jacrev would run one
    # reverse pass per pixel and channel).
    renderer = render.Renderer(mode="perturbed", sigma=0.7, gamma=0.01, num_samples=8, faces_per_pixel=4, faces_per_tile=16)
    mesh = render.position_colors(square(side_for_pixels(12.0)))
    key = getkey()

    def image(pose):
        moved = render.transform_mesh(mesh, render.axis_angle_to_matrix(pose[:3]), pose[3:])
        return renderer(key, moved, CAMERA).rgb

    pose = jnp.array([0.3, -0.2, 0.1, 0.05, -0.03, 0.2])
    forward = jax.jit(jax.jacfwd(image))(pose)
    assert forward.shape == (SIZE, SIZE, 3, 6) and float(jnp.max(jnp.abs(forward))) > 0.1
    cotangents = jax.random.normal(getkey(), (6, SIZE, SIZE, 3), pose.dtype)
    reverse = jax.jit(lambda c: jax.vmap(jax.vjp(image, pose)[1])(c)[0])(cotangents)
    expected = jnp.einsum("kijc,ijcp->kp", cotangents, forward)
    np.testing.assert_allclose(reverse, expected, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("mode", ["hard", "soft", "perturbed"])
def test_rendering_some_pixels_gives_their_values_and_derivatives_in_the_whole_image(mode, getkey):
    # the same noise (one key per pixel, split from the render's key): the same numbers
    mesh = square(side_for_pixels(10.0), color=(0.3, 0.6, 0.9))
    renderer = render.Renderer(mode=mode, sigma=0.7, gamma=0.01, num_samples=8, faces_per_pixel=4, faces_per_tile=16)
    pixels = jnp.asarray(np.random.default_rng(0).choice(SIZE * SIZE, 200, replace=False))
    r0 = render.axis_angle_to_matrix(jnp.array([0.2, 0.3, 0.1]))

    def whole(t, key):
        image = renderer(key, render.transform_mesh(mesh, r0, t), CAMERA)
        return jnp.concatenate([image.rgb.reshape(-1, 3), image.alpha.reshape(-1, 1)], axis=1)[pixels]

    def some(t, key):
        image = renderer(key, render.transform_mesh(mesh, r0, t), CAMERA, pixels=pixels)
        assert image.rgb.shape == (200, 3) and image.alpha.shape == (200,)
        return jnp.concatenate([image.rgb, image.alpha[:, None]], axis=1)

    key, t = getkey(), jnp.array([0.05, -0.02, 0.0])
    a, b = jax.jit(whole)(t, key), jax.jit(some)(t, key)
    assert float(jnp.max(a[:, 3])) > 0.5 and float(jnp.min(a[:, 3])) < 1e-6  # inside, outside (and edges)
    np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=1e-12, atol=1e-12)
    if mode != "hard":
        # reverse mode: vector-Jacobian products with the same random cotangents (jacrev would
        # run one reverse pass per entry)
        cotangents = jax.random.normal(getkey(), (4,) + a.shape, a.dtype)
        vjps = lambda f: jax.jit(lambda c: jax.vmap(jax.vjp(lambda t_: f(t_, key), t)[1])(c)[0])(cotangents)  # noqa: E731
        ja, jb = vjps(whole), vjps(some)
        assert float(jnp.max(jnp.abs(ja))) > 0.1
        np.testing.assert_allclose(np.asarray(jb), np.asarray(ja), rtol=1e-9, atol=1e-9)


def test_random_pixel_chunks_cover_each_random_pixel_once():
    uncertainty = jnp.array([0.0, 0.3, 1e-13, 0.5, 2e-12, 0.0, 0.9, 1e-3, 0.0, 0.2])  # 6 above 1e-12
    order, chunks = render.random_pixel_chunks(uncertainty, 4)
    assert int(chunks) == 2
    np.testing.assert_array_equal(np.asarray(order), [1, 3, 4, 6, 7, 9, 0, 2, 5, 8])  # random first
    fresh_rows = []
    for chunk in (4, 3):  # 3 chunks of 4 overlap at the end (10 rows), 4 of 3 too (12)
        fresh_rows = []
        for c in range(-(-10 // chunk)):
            rows, fresh = render.chunk_rows(order, c, chunk)
            assert rows.shape == (chunk,)
            fresh_rows += np.asarray(rows)[np.asarray(fresh)].tolist()
        assert sorted(fresh_rows) == list(range(10))  # each row once, in order
        assert fresh_rows == np.asarray(order).tolist()


def test_pixel_chunk_gives_the_image_and_derivatives_of_samples_everywhere(getkey):
    # The pixels the noise cannot change take their hard value with no samples: the image and its
    # derivatives are those of every pixel drawing samples (the same key per pixel), in chunks of
    # 0.6 of the pixels (2 chunks, the second overlapping the first: the image has 1024 pixels),
    # in a vmapped batch of two poses, and in chunks of 0.1 (3 chunks) with sigma = 0.5, where a
    # tenth of the pixels are covered and certain: their colour is their hard winner's, with its
    # shading's derivatives (its fragment recomputed alone, or gathered from the whole image's
    # with near-plane clipping). The random pixels' fragments are recomputed in each chunk, with
    # distances to every edge (interior_edges) or to the silhouette edges alone.
    mesh = render.position_colors(render.cube(1.2))
    camera = render.look_at(jnp.array([0.0, 0.0, 4.0]), image_size=(SIZE, SIZE), fov=40.0, near=2.0, far=6.0)
    options = dict(mode="perturbed", sigma=1.5, gamma=0.01, num_samples=8, faces_per_pixel=4, faces_per_tile=32, cull_backfaces=True)
    r0 = render.axis_angle_to_matrix(jnp.array([0.4, 0.5, 0.2]))
    key, t = getkey(), jnp.array([0.03, -0.02, 0.0])
    ts = jnp.stack([t, jnp.array([0.3, 0.1, -0.2])])
    edges = {"interior_edges": True}

    @functools.partial(jax.jit, static_argnums=0)
    def random(renderer, t):
        return renderer.uncertainty(render.transform_mesh(mesh, r0, t), camera) > render.NEGLIGIBLE

    for pose in ts:  # the premise: between 0.6 and 0.8 of the pixels are random
        assert 0.6 < float(jnp.mean(random(render.Renderer(**options, **edges), pose))) < 0.8
    hard_alpha = jax.jit(lambda t: render.Renderer(mode="hard")(None, render.transform_mesh(mesh, r0, t), camera).alpha)(t)
    assert float(jnp.mean(~random(render.Renderer(**{**options, "sigma": 0.5}), t) & (hard_alpha > 0))) > 0.08
    weights = jax.random.normal(jax.random.key(1), (SIZE, SIZE, 4))  # a random direction of the image

    def image_and_gradient(chunk, **changes):
        renderer = render.Renderer(**{**options, **changes}, pixel_chunk=chunk)

        def projected(t):
            out = renderer(key, render.transform_mesh(mesh, r0, t), camera)
            out = jnp.concatenate([out.rgb, out.alpha[..., None]], axis=-1)
            return jnp.sum(weights * out), out

        return jax.jit(jax.value_and_grad(projected, has_aux=True))

    def run(fn, t):
        (_, out), grad = fn(t)
        return np.asarray(out), np.asarray(grad)

    def check(b, gb, a, ga):
        np.testing.assert_allclose(b, a, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(gb, ga, rtol=1e-9, atol=1e-12)

    everywhere = image_and_gradient(1.0, **edges)
    a, ga = run(everywhere, t)
    assert float(np.max(np.abs(ga))) > 0.1
    b, gb = run(image_and_gradient(0.6, **edges), t)
    check(b, gb, a, ga)
    # batched: the poses' random pixels differ
    outs, grads = run(jax.vmap(image_and_gradient(0.6, **edges)), ts)
    check(outs[0], grads[0], b, gb)
    check(outs[1], grads[1], *run(everywhere, ts[1]))
    a, ga = run(image_and_gradient(1.0, sigma=0.5), t)
    for clip_near in (True, False):  # no face crosses the near plane: the same image either way
        b, gb = run(image_and_gradient(0.1, sigma=0.5, clip_near=clip_near), t)
        check(b, gb, a, ga)
    # some pixels alone: the same values
    pixels = jnp.arange(0, SIZE * SIZE, 3)
    renderer = render.Renderer(**{**options, "sigma": 0.5}, pixel_chunk=0.1)
    some = jax.jit(lambda t: renderer(key, render.transform_mesh(mesh, r0, t), camera, pixels=pixels))(t)
    np.testing.assert_allclose(np.asarray(some.rgba()), b.reshape(-1, 4)[pixels], rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError, match=r"pixel_chunk must be in \(0, 1\]"):
        render.Renderer(pixel_chunk=0.0)


def test_bad_pixel_indices_are_named():
    renderer = render.Renderer(mode="hard", faces_per_pixel=2, faces_per_tile=8)
    with pytest.raises(ValueError, match=r"pixels must lie in \[0, 1024\)"):
        renderer(None, render.cube(), CAMERA, pixels=jnp.array([0, SIZE * SIZE]))
    with pytest.raises(ValueError, match="pixels must be a 1-D integer array"):
        renderer(None, render.cube(), CAMERA, pixels=jnp.array([[1, 2]]))
    with pytest.raises(ValueError, match="pixels must be a 1-D integer array"):
        renderer(None, render.cube(), CAMERA, pixels=jnp.array([1.0, 2.0]))
    with pytest.raises(ValueError, match="perturbed renderer's"):
        renderer.uncertainty(render.cube(), CAMERA)


@pytest.mark.parametrize("depth_noise", [noise.Gumbel(), noise.Gaussian(), noise.Logistic()], ids=lambda n: n.name)
def test_change_probability_bounds_how_often_a_sample_is_not_the_hard_pixel(depth_noise, getkey):
    # random pixels of 3 slots (one empty), some covered, depths near one another and the
    # background: the frequency of samples whose z-buffer weights differ from the hard ones
    n, samples, sigma, gamma = 400, 4000, 0.8, 0.02
    distance = jax.random.uniform(getkey(), (n, 3), minval=-4.0, maxval=4.0).at[:, 2].set(-1e20)
    depth = jax.random.uniform(getkey(), (n, 3), minval=0.0, maxval=0.15)
    bound = render.change_probability(distance, depth, sigma=sigma, gamma=gamma, depth_noise=depth_noise, background_depth=0.02)

    def frequency(key, d, z):
        x = jax.random.normal(key, (samples, 3))
        g = depth_noise.sample(jax.random.fold_in(key, 1), (samples, 4))
        hard = render.hard_aggregate(d, z, 0.02)
        noisy = jax.vmap(lambda x, g: render.hard_aggregate(d + sigma * x, z + gamma * g[:3], 0.02 + gamma * g[3]))(x, g)
        return jnp.mean(jnp.any(noisy != hard[None, :], axis=-1))

    freq = jax.jit(jax.vmap(frequency))(jax.random.split(getkey(), n), distance, depth)
    slack = 4.0 * np.sqrt(np.asarray(bound) * (1 - np.asarray(bound)) / samples) + 2.0 / samples
    assert np.all(np.asarray(freq) <= np.asarray(bound) + slack)
    assert 0.1 < float(jnp.mean(freq)) < 0.9  # the pixels are random enough for the check to bite
    # one slot always covered, so only the depth order can change: exact for Gumbel and Gaussian
    gap = jnp.linspace(0.0, 0.2, 11)
    alone = render.change_probability(jnp.full((11, 1), 1e15), (0.02 + gap)[:, None], sigma=sigma, gamma=gamma, depth_noise=depth_noise, background_depth=0.02)
    exact = {"gumbel": jax.nn.sigmoid(-gap / gamma), "gaussian": norm.sf(gap / (gamma * np.sqrt(2)))}
    if depth_noise.name in exact:
        np.testing.assert_allclose(np.asarray(alone), np.asarray(exact[depth_noise.name]), rtol=1e-9)
    # and the coverage of a lone face, far in front of the background: Phi(-|d| / sigma)
    d = jnp.linspace(-7.0, 7.0, 15)
    lone = render.change_probability(d[:, None], jnp.full((15, 1), 0.9), sigma=sigma, gamma=gamma, background_depth=0.02)
    # (+ the background overtaking it, sigmoid(-44) < 1e-19)
    np.testing.assert_allclose(np.asarray(lone), norm.cdf(-np.abs(np.asarray(d)) / sigma), rtol=1e-6, atol=1e-19)


def test_pixels_the_noise_cannot_change_render_their_hard_value_with_zero_derivative(getkey):
    mesh = render.position_colors(render.cube(1.2))
    renderer = render.Renderer(mode="perturbed", sigma=0.5, gamma=0.01, num_samples=16, faces_per_pixel=4, faces_per_tile=32, cull_backfaces=True)
    hard = render.Renderer(mode="hard", faces_per_pixel=4, faces_per_tile=32, cull_backfaces=True)
    camera = render.look_at(jnp.array([0.0, 0.0, 4.0]), image_size=(SIZE, SIZE), fov=40.0, near=2.0, far=6.0)
    r0 = render.axis_angle_to_matrix(jnp.array([0.4, 0.5, 0.2]))
    p = np.asarray(jax.jit(lambda m: renderer.uncertainty(m, camera))(render.transform_mesh(mesh, r0))).ravel()
    certain = jnp.asarray(np.flatnonzero(p < 1e-12))
    assert 0.3 * SIZE * SIZE < certain.size < SIZE * SIZE  # some of the cube, the background; not the edges

    def alpha(t, key):
        m = render.transform_mesh(mesh, r0, t)
        return renderer(key, m, camera, pixels=certain).alpha, renderer(key, m, camera, pixels=certain).rgb

    key, t = getkey(), jnp.zeros(3)
    expected = jax.jit(lambda m: hard(None, m, camera))(render.transform_mesh(mesh, r0))
    got_alpha, got_rgb = jax.jit(alpha)(t, key)
    np.testing.assert_array_equal(np.asarray(got_alpha), np.asarray(expected.alpha).ravel()[np.asarray(certain)])
    np.testing.assert_allclose(np.asarray(got_rgb), np.asarray(expected.rgb).reshape(-1, 3)[np.asarray(certain)], atol=1e-12)
    jac = jax.jit(jax.jacfwd(lambda t, k: alpha(t, k)[0]))(t, key)
    np.testing.assert_array_equal(np.asarray(jac), 0.0)


def _dot_precisions(jaxpr, found):
    """The precision of every matrix product in a jaxpr and in the jaxprs inside it."""
    from jax.extend import core

    for eqn in jaxpr.eqns:
        if eqn.primitive.name == "dot_general":
            found.append(eqn.params["precision"])
        for param in eqn.params.values():
            for sub in param if isinstance(param, (list, tuple)) else [param]:
                if isinstance(sub, core.ClosedJaxpr):
                    _dot_precisions(sub.jaxpr, found)
                elif isinstance(sub, core.Jaxpr):
                    _dot_precisions(sub, found)
    return found


@pytest.mark.parametrize(
    "options", [dict(mode="hard"), dict(mode="soft"), dict(mode="perturbed", num_samples=2), dict(mode="perturbed", pixel_chunk=0.5)]
)
def test_float32_products_ask_for_full_precision(options):
    # On NVIDIA GPUs a float32 product defaults to TF32 (a 10-bit mantissa): on an H100 it
    # collapsed a rescaled robot mesh's small faces to zero area. CPUs compute every precision
    # alike, so the test reads the request: every product of the render and its gradient, with
    # respect to the pose, asks for full precision (rsmooth._xla.matmul).
    mesh = render.position_colors(render.icosphere(1))
    camera = render.look_at(jnp.array([0.3, 0.2, 3.0]), image_size=(8, 8))
    renderer = render.Renderer(**options)

    def loss(pose):
        rotation = render.axis_angle_to_matrix(pose[:3])
        image = renderer(jax.random.key(0), render.transform_mesh(mesh, rotation, pose[3:]), camera)
        return jnp.sum(image.rgb) + render.rotation_angle(rotation, jnp.eye(3, dtype=jnp.float32))

    jaxpr = jax.make_jaxpr(jax.grad(loss))(jnp.full(6, 0.1, jnp.float32)).jaxpr
    precisions = _dot_precisions(jaxpr, [])
    assert precisions, "no product found: the test no longer looks at the renderer's geometry"
    assert all(p == (jax.lax.Precision.HIGHEST, jax.lax.Precision.HIGHEST) for p in precisions), precisions
