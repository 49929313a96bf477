"""Rasterization: signed distances, coverage (hard, perturbed, soft), per-pixel culling."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.scipy.stats import norm

from rsmooth import noise, render


def point_in_triangle(p, tri):
    """Reference: solve for the barycentric coordinates with numpy."""
    a = np.array([[tri[0, 0], tri[1, 0], tri[2, 0]], [tri[0, 1], tri[1, 1], tri[2, 1]], [1.0, 1.0, 1.0]])
    lam = np.linalg.solve(a, np.array([p[0], p[1], 1.0]))
    return bool(np.all(lam > 0)), lam


def segment_distance(p, a, b):
    t = np.clip(np.dot(p - a, b - a) / np.dot(b - a, b - a), 0.0, 1.0)
    return np.linalg.norm(p - (a + t * (b - a)))


def test_hard_coverage_is_the_point_in_triangle_test(getkey):
    tris = np.asarray(jax.random.uniform(getkey(), (20, 3, 2), minval=-1.0, maxval=1.0))
    points = np.asarray(jax.random.uniform(getkey(), (20, 50, 2), minval=-1.0, maxval=1.0))
    d = np.asarray(render.signed_distance(points, tris[:, None]))
    bary = np.asarray(render.barycentric(points, tris[:, None]))
    cover = np.asarray(render.coverage(d, mode="hard"))
    for i in range(20):
        for j in range(50):
            inside, lam = point_in_triangle(points[i, j], tris[i])
            assert bool(cover[i, j]) == inside
            np.testing.assert_allclose(bary[i, j], lam, atol=1e-9)
            dist = min(segment_distance(points[i, j], tris[i, k], tris[i, (k + 1) % 3]) for k in range(3))
            assert float(d[i, j]) == pytest.approx(dist if inside else -dist, abs=1e-9)


def test_degenerate_triangle_covers_nothing():
    tri = jnp.array([[0.0, 0.0], [1.0, 1.0], [2.0, 2.0]])
    d = render.signed_distance(jnp.array([[1.0, 1.0], [1.0, 0.0]]), tri)
    assert float(d[0]) <= 0 and float(d[1]) == pytest.approx(-np.sqrt(0.5))


@pytest.mark.parametrize(
    "law, cdf, pdf",
    [
        (noise.Gaussian(), norm.cdf, norm.pdf),
        (noise.Logistic(), jax.nn.sigmoid, lambda x: jax.nn.sigmoid(x) * (1 - jax.nn.sigmoid(x))),
        (noise.Cauchy(), lambda x: 0.5 + jnp.arctan(x) / jnp.pi, lambda x: 1 / (jnp.pi * (1 + x**2))),
    ],
)
def test_perturbed_coverage_and_its_gradient_match_the_closed_form(getkey, law, cdf, pdf):
    """Half-plane: a pixel at signed distance d is covered by the perturbed edge with
    probability F(d / sigma); the estimator's derivative is F'(d / sigma) / sigma."""
    sigma, m = 0.5, 4000
    d = jnp.linspace(-1.0, 1.0, 9)
    key = getkey()
    cov = jax.jit(lambda d: render.coverage(d, key, mode="perturbed", sigma=sigma, num_samples=m, noise=law))
    value = cov(d)
    grad = jax.jit(jax.vmap(jax.grad(lambda x: render.coverage(x, key, mode="perturbed", sigma=sigma, num_samples=m, noise=law))))(d)
    np.testing.assert_allclose(value, cdf(d / sigma), atol=4 * 0.5 / np.sqrt(m))
    # Standard error of the zeroth-order estimate (with baseline) <= sqrt(E score^2 / M) / sigma.
    tol = 4 * np.sqrt(1.0 / m) / sigma
    np.testing.assert_allclose(grad, pdf(d / sigma) / sigma, atol=tol)


def test_perturbed_coverage_tends_to_hard_as_sigma_vanishes(getkey):
    d = jnp.array([-0.3, -0.05, 0.05, 0.3])
    key = getkey()
    errors = [
        float(jnp.max(jnp.abs(render.coverage(d, key, mode="perturbed", sigma=s, num_samples=2000) - render.coverage(d, mode="hard"))))
        for s in (0.5, 0.05, 0.005)
    ]
    assert errors[0] > errors[1] > errors[2] and errors[2] < 1e-2


def test_soft_coverage_is_the_sigmoid_and_bad_modes_fail():
    np.testing.assert_allclose(render.coverage(jnp.array([0.0, 1.0]), mode="soft", sigma=0.5), jax.nn.sigmoid(jnp.array([0.0, 2.0])))
    with pytest.raises(ValueError, match="mode"):
        render.coverage(jnp.zeros(2), mode="fuzzy")
    with pytest.raises(ValueError, match="key"):
        render.coverage(jnp.zeros(2), mode="perturbed")


def brute_force_zbuffer(mesh, camera):
    """Reference: every pixel against every face, nearest covering face or -1."""
    screen, _, depth, valid = render.project_faces(mesh, camera)
    height, width = camera.image_size
    ys, xs = np.meshgrid(np.arange(height) + 0.5, np.arange(width) + 0.5, indexing="ij")
    points = jnp.asarray(np.stack([xs, ys], -1))[:, :, None, :]
    d, bary = jax.jit(jax.vmap(jax.vmap(lambda p: (render.signed_distance(p, screen), render.barycentric(p, screen)))))(points[:, :, 0])
    z = jnp.sum(bary * depth[None, None], axis=-1)
    key = jnp.where((d > 0) & valid[None, None], z, -jnp.inf)
    return np.where(np.isfinite(np.max(key, axis=-1)), np.argmax(key, axis=-1), -1)


def test_culled_rasterizer_finds_the_nearest_covering_face(getkey):
    mesh = render.icosphere(2)
    camera = render.look_at(jnp.array([0.6, 0.8, 2.6]), image_size=(24, 20), fov=50.0)
    fragments = jax.jit(lambda m: render.rasterize(m, camera, faces_per_pixel=4, tile_size=8, faces_per_tile=48))(mesh)
    assert fragments.face_index.shape == (24, 20, 4)
    hard = np.where(np.asarray(fragments.present[..., 0]) & (np.asarray(fragments.distance[..., 0]) > 0), np.asarray(fragments.face_index[..., 0]), -1)
    reference = brute_force_zbuffer(mesh, camera)
    assert np.mean(reference >= 0) > 0.3
    np.testing.assert_array_equal(hard, reference)


@pytest.mark.parametrize("margin", [9.0, 18.0])
def test_smoothed_candidates_always_hold_the_visible_face(margin):
    # A torus of small faces seen obliquely: the pixels' candidate lists for smoothed rendering
    # (ranked by coverage probability and depth, within `margin` pixels) must contain the face
    # the z-buffer shows, even when more faces reach a tile than it keeps. Ranking by a
    # SoftRas-like log sigmoid(d / sigma) + z / gamma with extrapolated depth planes, and
    # keeping the nearest faces per tile, lost it at 30-100 % of the covered pixels.
    mesh = render.torus(0.7, 0.3, 24, 12)
    rotation = render.axis_angle_to_matrix(jnp.array([1.1, 0.4, -0.3]))
    mesh = render.transform_mesh(mesh, rotation, jnp.zeros(3))
    camera = render.look_at(jnp.array([0.0, 0.0, 4.0]), image_size=(96, 96), fov=40.0, near=2.0, far=6.0)
    kw = dict(faces_per_pixel=8, faces_per_tile=64, cull_backfaces=True)
    hard = render.rasterize(mesh, camera, **kw)
    visible = np.where(np.asarray(hard.present[..., 0]), np.asarray(hard.face_index[..., 0]), -1)
    smoothed = render.rasterize(mesh, camera, margin=margin, sigma=3.0, gamma=0.02, **kw)
    assert int(smoothed.tile_overflow) > 0 or margin == 9.0  # the wide margin overflows tiles
    found = np.any((np.asarray(smoothed.face_index) == visible[..., None]) & np.asarray(smoothed.present), axis=-1)
    assert np.mean(visible >= 0) > 0.15
    assert np.all(found[visible >= 0])


@pytest.mark.parametrize("with_edges", [False, True])
@pytest.mark.parametrize("output", ["distance", "depth", "weights", "all"])
def test_fragment_derivatives_equal_autodiff_of_the_formulas(getkey, with_edges, output):
    # The fragments' hand-written forward mode (rsmooth.render._raster._fragment_geometry),
    # and JAX's transpose of it (reverse mode), against JAX's derivatives of the same formulas,
    # on random triangles around a 12 x 10 grid of pixels: faces with no counted edge (an
    # interior face: its distance is constant) or all three, pixels inside and outside; and
    # two zero-area faces (three collinear vertices, two equal vertices), where both
    # derivatives are finite but may differ: there edges overlap, or a barycentric coordinate
    # is exactly 0, and of the subgradients at these kinks (min of tied distances, max(b, 0)
    # at b = 0) autodiff takes the average, the hand-written one a one-sided one.
    from rsmooth.render import _raster

    faces = 7
    screen = jax.random.uniform(getkey(), (faces, 3, 2), minval=-2.0, maxval=14.0)
    screen = screen.at[3].set(jnp.array([[1.0, 1.0], [4.0, 3.0], [7.0, 5.0]]))  # zero area
    screen = screen.at[4, 1].set(screen[4, 0])  # two equal vertices
    depths = jax.random.uniform(getkey(), (faces, 3))
    z = jax.random.uniform(getkey(), (faces, 3), minval=1.0, maxval=3.0)
    edges = jax.random.bernoulli(getkey(), 0.5, (faces, 3)).at[5].set(False).at[6].set(True) if with_edges else None
    index = jax.random.randint(getkey(), (12, 10, 4), 0, faces)
    qx = (jnp.arange(10.0) + 0.5)[None, :, None]
    qy = (jnp.arange(12.0) + 0.5)[:, None, None]
    args = (screen, depths, z)
    keep = {"distance": 0, "depth": 1, "weights": 2}.get(output)

    def function(fn):
        def outputs(*a):
            values = fn(*a, edges, index, qx, qy)
            return values if keep is None else values[keep]

        return outputs

    reference, new = function(_raster._fragment_values), function(_raster._fragment_geometry)
    generic = (index != 3) & (index != 4)
    # forward mode, with the degenerate faces held still (zero tangents)
    tangents = tuple(jax.random.normal(getkey(), a.shape) for a in args)
    generic_face = jnp.ones(faces, bool).at[3].set(False).at[4].set(False)
    held = tuple(t * generic_face.reshape((faces,) + (1,) * (t.ndim - 1)) for t in tangents)
    values, got = jax.jvp(new, args, held)
    expected_values, expected = jax.jvp(reference, args, held)
    for a, b in zip(jax.tree.leaves(expected_values), jax.tree.leaves(values)):
        np.testing.assert_array_equal(a, b)
    for e, g in zip(jax.tree.leaves(expected), jax.tree.leaves(got)):
        np.testing.assert_allclose(g, e, rtol=1e-9, atol=1e-9 * float(jnp.max(jnp.abs(e))) + 1e-12)
    _, got_all = jax.jvp(new, args, tangents)
    assert all(np.all(np.isfinite(g)) for g in jax.tree.leaves(got_all))
    # reverse mode, with no cotangent on the degenerate faces' fragments
    cotangents = jax.tree.map(lambda v: jax.random.normal(getkey(), v.shape), values)
    _, vjp = jax.vjp(new, *args)
    assert all(np.all(np.isfinite(g)) for g in vjp(cotangents))
    cotangents = jax.tree.map(lambda c: jnp.where(generic if c.ndim == 3 else generic[..., None], c, 0.0), cotangents)
    _, reference_vjp = jax.vjp(reference, *args)
    expected, got = reference_vjp(cotangents), vjp(cotangents)
    for name, e, g in zip(("screen", "depths", "z"), expected, got):
        np.testing.assert_allclose(g, e, rtol=1e-9, atol=1e-9 * float(jnp.max(jnp.abs(e))) + 1e-12, err_msg=name)
    if output in ("distance", "all"):
        assert float(jnp.max(jnp.abs(got[0]))) > 0  # the distance reaches the vertices
