"""Shape metrics: surface sampling, Chamfer distance, voxelization, 3D and silhouette IoU."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh

from rsmooth import render

UNIT = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])


def shifted(mesh, shift):
    return render.transform_mesh(mesh, jnp.eye(3), jnp.asarray(shift, float))


def test_iou_of_a_mesh_with_itself_is_one():
    sphere = render.icosphere(2, 0.7)
    assert float(render.iou_3d(sphere, sphere, 32)) == 1.0
    torus = render.torus(0.6, 0.25, 16, 8)
    assert float(render.iou_3d(torus, torus, 32)) == 1.0


def test_iou_of_unit_cubes_offset_by_half_a_side_is_one_third():
    a = render.cube(1.0)
    b = shifted(a, [0.5, 0.0, 0.0])
    # A grid whose voxel centres avoid the faces: the count is exact.
    exact = render.iou_3d(a, b, 30, bounds=[[-0.5, -0.5, -0.5], [1.0, 0.5, 0.5]])
    assert float(exact) == pytest.approx(1.0 / 3.0, abs=1e-12)
    # The default grid (both bounding boxes, padded): within discretization error.
    assert float(render.iou_3d(a, b, 64)) == pytest.approx(1.0 / 3.0, abs=0.02)
    # A diagonal offset of half a side on each axis: (1/2)^3 / (2 - (1/2)^3) = 1/15.
    c = shifted(a, [0.5, 0.5, 0.5])
    assert float(render.iou_3d(a, c, 30, bounds=[[-0.5] * 3, [1.0] * 3])) == pytest.approx(1.0 / 15.0, abs=1e-12)


def test_voxel_volume_of_an_icosphere_is_that_of_the_ball():
    radius = 0.8
    for resolution, tolerance in ((32, 0.04), (64, 0.015)):
        occupancy = render.voxelize(render.icosphere(3, radius), resolution, UNIT)
        assert occupancy.shape == (resolution,) * 3 and occupancy.dtype == jnp.bool_
        volume = float(jnp.sum(occupancy)) * (2.0 / resolution) ** 3
        # The icosphere's own volume is 0.9 % below the ball's.
        assert volume == pytest.approx(4.0 / 3.0 * np.pi * radius**3, rel=tolerance)


def test_rays_through_edges_and_vertices_count_once():
    # A cube of side 1 on a grid of step 1/4: columns of voxel centres run exactly along the
    # diagonals that split its square faces, where two triangles meet.
    occupancy = np.asarray(render.voxelize(render.cube(1.0), 8, UNIT))
    expected = np.zeros((8, 8, 8), bool)
    expected[2:6, 2:6, 2:6] = True
    np.testing.assert_array_equal(occupancy, expected)
    # An octahedron whose vertices lie on rays of the grid (and rays along z graze its
    # equatorial edges), centred at a voxel corner.
    centre, radius = np.full(3, 0.125), 0.75
    hull = trimesh.convex.convex_hull(centre + radius * np.concatenate([np.eye(3), -np.eye(3)]))
    octahedron = render.Mesh(hull.vertices, hull.faces)
    x, y, z = np.meshgrid(*[-1.0 + (np.arange(8) + 0.5) / 4.0] * 3, indexing="ij")
    l1 = np.abs(x - centre[0]) + np.abs(y - centre[1]) + np.abs(z - centre[2])
    off_surface = np.abs(l1 - radius) > 1e-9
    occupancy = np.asarray(render.voxelize(octahedron, 8, UNIT))
    np.testing.assert_array_equal(occupancy[off_surface], (l1 < radius)[off_surface])
    assert occupancy[off_surface].sum() == np.sum(l1 < radius - 1e-9) > 0


def test_voxelize_an_annulus_against_its_closed_form():
    tm = trimesh.creation.annulus(r_min=0.3, r_max=0.7, height=0.5)  # a shape with a hole
    occupancy = np.asarray(render.voxelize(render.Mesh(tm.vertices, tm.faces), 16, UNIT))
    x, y, z = np.meshgrid(*[-1.0 + (np.arange(16) + 0.5) / 8.0] * 3, indexing="ij")
    radius = np.hypot(x, y)
    inside = (radius > 0.3) & (radius < 0.7) & (np.abs(z) < 0.25)
    # Away from the surface (farther than the polygons' deviation from the circles).
    clear = (np.abs(radius - 0.3) > 0.02) & (np.abs(radius - 0.7) > 0.02) & (np.abs(np.abs(z) - 0.25) > 0.01)
    np.testing.assert_array_equal(occupancy[clear], inside[clear])
    assert inside[clear].sum() > 100


def test_chamfer_distance_closed_forms():
    grid = np.stack(np.meshgrid(*[np.arange(4.0)] * 3, indexing="ij"), -1).reshape(-1, 3)
    assert float(render.chamfer_distance(grid, grid)) == 0.0
    # Shifted by s < 1/2 of the grid step: every nearest neighbour is the shifted copy.
    shift = np.array([0.1, -0.2, 0.15])
    assert float(render.chamfer_distance(grid, grid + shift)) == pytest.approx(np.sum(shift**2), rel=1e-12)
    # One point against two at distances 1 and 3: (1 + (1 + 9) / 2) / 2 = 3.
    a = np.array([[0.0, 0.0, 0.0]])
    b = np.array([[1.0, 0.0, 0.0], [0.0, 3.0, 0.0]])
    assert float(render.chamfer_distance(a, b)) == pytest.approx(3.0)
    assert float(render.chamfer_distance(b, a)) == pytest.approx(3.0)


def test_chamfer_distance_blocks_match_a_dense_reference(getkey):
    a = jax.random.normal(getkey(), (2500, 3))  # more than one block of 1024
    b = jax.random.normal(getkey(), (700, 3))
    d2 = np.sum((np.asarray(a)[:, None] - np.asarray(b)[None]) ** 2, axis=-1)
    reference = 0.5 * (d2.min(axis=1).mean() + d2.min(axis=0).mean())
    assert float(render.chamfer_distance(a, b)) == pytest.approx(reference, rel=1e-12)
    assert float(jax.jit(render.chamfer_distance)(a, b)) == pytest.approx(reference, rel=1e-12)
    grad = jax.grad(render.chamfer_distance)(a, b)
    assert grad.shape == a.shape and bool(jnp.all(jnp.isfinite(grad)))


def test_surface_samples_lie_on_the_surface_uniformly(getkey):
    box = render.box((2.0, 1.0, 0.5))
    points = np.asarray(render.sample_surface(getkey(), box, 20000))
    half = np.array([1.0, 0.5, 0.25])
    on_face = np.isclose(np.abs(points), half, atol=1e-12)
    assert np.all(on_face.sum(axis=1) >= 1) and np.all(np.abs(points) <= half + 1e-12)
    # Each pair of faces gets its share of the area: x faces 2 * 0.5, y faces 2 * 1, z faces 2 * 2.
    share = np.array([0.5, 1.0, 2.0]) / 3.5
    counts = on_face[on_face.sum(axis=1) == 1].sum(axis=0) / 20000
    np.testing.assert_allclose(counts, share, atol=0.015)
    sphere = render.icosphere(3, 0.5)
    radii = np.linalg.norm(np.asarray(render.sample_surface(getkey(), sphere, 500)), axis=1)
    assert np.all((radii <= 0.5 + 1e-12) & (radii > 0.49))


def test_surface_samples_follow_the_vertices(getkey):
    key = getkey()
    sphere = render.icosphere(1)

    def mean_point(offset):
        moved = eqx.tree_at(lambda m: m.vertices, sphere, sphere.vertices + offset[None, :])
        return jnp.mean(render.sample_surface(key, moved, 100), axis=0)

    jacobian = jax.jit(jax.jacobian(mean_point))(jnp.zeros(3))
    np.testing.assert_allclose(jacobian, np.eye(3), atol=1e-12)


def test_silhouette_iou_closed_forms():
    a = jnp.zeros((2, 6, 6)).at[0, :, :3].set(1.0).at[1, :2, :2].set(1.0)
    b = jnp.zeros((2, 6, 6)).at[0, :, 2:4].set(1.0).at[1, 4:, 4:].set(1.0)
    np.testing.assert_allclose(render.silhouette_iou(a, b), [6.0 / 24.0, 0.0])
    np.testing.assert_allclose(render.silhouette_iou(a, a), [1.0, 1.0])
    assert float(render.silhouette_iou(jnp.zeros((3, 3)), jnp.zeros((3, 3)))) == 0.0
    half = jnp.full((2, 2), 0.5)
    assert float(render.silhouette_iou(half, jnp.ones((2, 2)))) == pytest.approx(0.5)


def test_bad_inputs_raise_errors_that_name_the_argument(getkey):
    mesh = render.cube()
    empty = eqx.tree_at(lambda m: m.faces, mesh, jnp.zeros((0, 3), jnp.int32))
    with pytest.raises(ValueError, match="mesh is empty"):
        render.sample_surface(getkey(), empty, 10)
    with pytest.raises(ValueError, match="mesh is empty"):
        render.voxelize(empty, 8, UNIT)
    with pytest.raises(ValueError, match="mesh_b is empty"):
        render.iou_3d(mesh, empty, 8)
    with pytest.raises(ValueError, match="num_points"):
        render.sample_surface(getkey(), mesh, 0)
    with pytest.raises(TypeError, match="mesh must be an rsmooth.render.Mesh"):
        render.voxelize(np.zeros((3, 3)), 8, UNIT)
    with pytest.raises(ValueError, match="resolution"):
        render.voxelize(mesh, 0, UNIT)
    with pytest.raises(ValueError, match="bounds"):
        render.voxelize(mesh, 8, [[1.0, 1.0, 1.0], [-1.0, -1.0, -1.0]])
    with pytest.raises(ValueError, match="bounds"):
        render.voxelize(mesh, 8, [0.0, 1.0])
    with pytest.raises(ValueError, match=r"points_a must have shape \(N, 3\)"):
        render.chamfer_distance(np.zeros((4, 2)), np.zeros((4, 3)))
    with pytest.raises(ValueError, match="points_b is empty"):
        render.chamfer_distance(np.zeros((4, 3)), np.zeros((0, 3)))
    with pytest.raises(ValueError, match="alpha and target"):
        render.silhouette_iou(jnp.zeros((4, 4)), jnp.zeros((4, 5)))
