"""Height fields (`sim.HeightField`, MuJoCo's hfield): the signed distances of spheres,
capsules, boxes, cylinders, convex meshes and ellipsoids to a random terrain equal MuJoCo's
contacts, closed forms of a box on a flat terrain and over a peak, derivatives in the pose, a ball
and a box rest on a flat terrace of a terrain at the analytic height, and what is not supported
is refused by name."""

import equinox as eqx
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from rsmooth import sim
from rsmooth.sim._collision import collide

ROWS, COLUMNS, HALF_X, HALF_Y, TOP, BASE = 6, 7, 0.6, 0.5, 0.2, 0.1


def _terrain(shape_geom: str, seed: int = 0, assets: str = "") -> str:
    """A random terrain (MuJoCo's hfield) and a free body of one geom above it."""
    elevation = " ".join(map(str, np.random.default_rng(seed).uniform(0, 1, size=ROWS * COLUMNS)))
    return f"""<mujoco><option ccd_tolerance="1e-12" ccd_iterations="500"/>
      <asset>{assets}<hfield name="terrain" nrow="{ROWS}" ncol="{COLUMNS}" size="{HALF_X} {HALF_Y} {TOP} {BASE}" elevation="{elevation}"/></asset>
      <worldbody><geom name="terrain" type="hfield" hfield="terrain"/><body name="body"><freejoint/><geom name="body" {shape_geom}/></body></worldbody>
    </mujoco>"""


@pytest.mark.parametrize("geom", ['type="sphere" size="0.08"', 'type="capsule" size="0.04 0.08"'], ids=["sphere", "capsule"])
def test_distances_to_a_terrain_are_mujocos(geom):
    # The deepest of our contacts against the deepest MuJoCo reports (it reports penetrating
    # contacts only, one per prism of the cells under the shape), on random poses over the
    # terrain; where MuJoCo reports none, ours is apart.
    text = _terrain(geom)
    m = mujoco.MjModel.from_xml_string(text)
    d = mujoco.MjData(m)
    system = sim.scene(text)
    pair = system.geometry.geom_pairs[0]
    assert isinstance(pair.shape1, sim.HeightField) and pair.frame1 is None
    np.testing.assert_allclose(pair.shape1.heights, np.asarray(m.hfield_data).reshape(ROWS, COLUMNS) * TOP, rtol=1e-6)
    distance = jax.jit(jax.vmap(lambda r, t: collide(pair.shape1, pair.placement1, pair.shape2, (r, t)).distance[0]))
    rng = np.random.default_rng(1)
    qpos = np.concatenate([rng.uniform([-0.45, -0.35, 0.0], [0.45, 0.35, 0.25], size=(48, 3)), rng.normal(size=(48, 4))], axis=1)
    qpos[:, 3:] /= np.linalg.norm(qpos[:, 3:], axis=1, keepdims=True)
    expected, rotations = [], []
    for q in qpos:
        d.qpos[:] = q
        mujoco.mj_forward(m, d)
        expected.append(min([c.dist for c in d.contact[: d.ncon]], default=np.inf))
        rotations.append(d.xmat[1].reshape(3, 3).copy())
    ours = np.asarray(distance(jnp.asarray(np.array(rotations)), jnp.asarray(qpos[:, :3])))
    expected = np.array(expected)
    touching = np.isfinite(expected)
    assert 10 < touching.sum() < 40
    # (MuJoCo's penetration of a height field's prisms iterates to about 1e-6)
    np.testing.assert_allclose(ours[touching], expected[touching], atol=1e-5)
    assert np.all(ours[~touching] > -1e-9)


@pytest.mark.parametrize("body, half_height", [('type="sphere" size="0.05"', 0.05), ('type="box" size="0.05 0.04 0.03"', 0.03)],
                         ids=["ball", "box"])
def test_a_shape_rests_on_a_terrace_of_a_terrain(body, half_height):
    # Heights: a flat terrace at 0.1 m over the middle columns, lower around: a ball of radius
    # 5 cm (against the cells' prisms) or a box 6 cm high (against the terrain's surface) set
    # down 2 mm above it, across a cell's side and diagonal, settles on it at rest.
    heights = np.full((ROWS, COLUMNS), 1.0)  # MuJoCo scales the elevation to [0, 1], times size[2]
    heights[:, 0] = heights[:, -1] = 0.0
    elevation = " ".join(map(str, heights.reshape(-1)))
    text = f"""<mujoco><option timestep="0.01"/>
      <asset><hfield name="terrain" nrow="{ROWS}" ncol="{COLUMNS}" size="{HALF_X} {HALF_Y} 0.1 {BASE}" elevation="{elevation}"/></asset>
      <worldbody><geom name="terrain" type="hfield" hfield="terrain"/>
        <body name="body" pos="0.05 0.02 {0.102 + half_height}"><freejoint/><geom {body} mass="1"/></body></worldbody>
    </mujoco>"""
    system = sim.scene(text)
    xs, infos = eqx.filter_jit(lambda s, x: s.rollout(x, jnp.zeros((100, 0))))(system, system.initial_state())
    sim.check_steps(infos, what="a shape on a terrace")
    np.testing.assert_allclose(float(xs[-1, 2]), 0.1 + half_height, atol=1e-3)
    assert float(jnp.max(jnp.abs(xs[-10:, 7:]))) < 1e-3


def test_bad_height_fields_are_refused_by_name():
    with pytest.raises(ValueError, match=r"heights must have shape \(R, C\) with R, C >= 2"):
        sim.HeightField(np.zeros((1, 3)), [1.0, 1.0], 0.1)
    floor = _terrain('type="box" size="0.1 0.1 0.1"').replace(
        "</worldbody>", '<geom name="floor" type="plane" size="1 1 1"/></worldbody><contact><pair geom1="terrain" geom2="floor"/></contact>'
    )
    with pytest.raises(ValueError, match=r"geom 'terrain' \(hfield\) collides with geom 'floor' \(plane\), a pair of shapes"):
        sim.scene(floor)
    with pytest.raises(NotImplementedError, match="no collision function for HeightField against HalfSpace"):
        collide(sim.HeightField(np.zeros((3, 3)), [1.0, 1.0], 0.1), (jnp.eye(3), jnp.zeros(3)), sim.HalfSpace(), (jnp.eye(3), jnp.zeros(3)))
    with pytest.raises(ValueError, match="window must be an int >= 1"):
        sim.HeightField(np.zeros((3, 3)), [1.0, 1.0], 0.1, window=0)
    moving = _terrain('type="sphere" size="0.08"').replace(
        '<geom name="terrain" type="hfield" hfield="terrain"/>',
        '<body name="raft"><freejoint/><geom name="terrain" type="hfield" hfield="terrain"/></body>',
    )
    with pytest.raises(ValueError, match="geom 'terrain' \\(hfield\\) is on a moving body"):
        sim.scene(moving)


# an irregular convex mesh (MuJoCo recentres it at its centre of mass and principal axes; the
# scene's shape is in the geom's frame, which the comparison below places by MuJoCo's geom pose)
_ROCK = "0.05 0 0  -0.04 0.03 0  -0.03 -0.04 0.01  0 0 0.04  0.01 0.01 -0.035  0.02 -0.03 -0.02  -0.01 0.035 0.02"
_POLYTOPES = {
    "box": 'type="box" size="0.05 0.04 0.03"',
    "cylinder": 'type="cylinder" size="0.04 0.03"',
    "mesh": 'type="mesh" mesh="rock"',
    "ellipsoid": 'type="ellipsoid" size="0.05 0.04 0.03"',
}


@pytest.mark.parametrize("name", list(_POLYTOPES))
def test_polytope_depths_in_a_terrain_are_mujocos(name):
    # The regime compared: the shape slightly tilted (up to about 0.3 rad) and lowered until its
    # deepest point sinks 0.5 to 3 mm into the terrain, where that point is over a triangle's
    # interior (1e-3 of a cell away from its edges and diagonal) and MuJoCo's deepest contact has
    # the triangle's normal: MuJoCo's depth of a shape in a cell's prism is then through the
    # prism's top face, the terrain's. (Where MuJoCo's deepest prism depth is through a prism's
    # side, it is not the terrain's penetration, and ours differs by design.) Our cylinder is
    # compared by its exact supports (its rim points); our ellipsoid by its exact supports.
    text = _terrain(_POLYTOPES[name], assets=f'<mesh name="rock" vertex="{_ROCK}"/>')
    m = mujoco.MjModel.from_xml_string(text)
    d = mujoco.MjData(m)
    pair = sim.scene(text).geometry.geom_pairs[0]
    assert isinstance(pair.shape1, sim.HeightField)
    manifolds = jax.jit(jax.vmap(lambda r, t: collide(pair.shape1, pair.placement1, pair.shape2, (r, t))))
    contacts = lambda r, t: jax.tree.map(lambda a: a[:, 0], manifolds(r, t))  # noqa: E731
    rng = np.random.default_rng(2)
    count = 96
    qpos = np.concatenate([rng.uniform([-0.45, -0.35, 0.5], [0.45, 0.35, 0.5], size=(count, 3)),
                           np.ones((count, 1)), rng.uniform(-0.15, 0.15, size=(count, 3))], axis=1)
    qpos[:, 3:] /= np.linalg.norm(qpos[:, 3:], axis=1, keepdims=True)

    def geom_poses():
        rotations, translations, deepest = [], [], []
        for q in qpos:
            d.qpos[:] = q
            mujoco.mj_forward(m, d)
            rotations.append(d.geom_xmat[1].reshape(3, 3).copy())
            translations.append(d.geom_xpos[1].copy())
            first = min(range(d.ncon), key=lambda i: d.contact[i].dist, default=None)
            deepest.append((np.inf, np.zeros(3)) if first is None else (d.contact[first].dist, d.contact[first].frame[:3].copy()))
        return jnp.asarray(np.array(rotations)), jnp.asarray(np.array(translations)), deepest

    # lower each shape so that its deepest point (ours, linear in the height along the triangle's normal) sinks by depth
    depth = rng.uniform(5e-4, 3e-3, size=count)
    for _ in range(2):
        above = contacts(*geom_poses()[:2])
        qpos[:, 2] -= (np.asarray(above.distance) + depth) / np.asarray(above.normal[:, 2])
    rotations, translations, deepest = geom_poses()
    manifold = manifolds(rotations, translations)
    ours = jax.tree.map(lambda a: a[:, 0], manifold)
    expected = np.array([dist for dist, _ in deepest])
    expected_normal = np.array([normal for _, normal in deepest])
    # where our deepest point (on the shape) is over a triangle's interior: away from the cells' edges and diagonal
    cell = np.asarray(pair.shape1.cell)
    scaled = (np.asarray(ours.point2[:, :2]) - np.asarray(pair.placement1[1])[None, :2] + np.array([HALF_X, HALF_Y])) / cell
    u, w = scaled[:, 0] - np.floor(scaled[:, 0]), scaled[:, 1] - np.floor(scaled[:, 1])
    interior = np.minimum(np.minimum(np.minimum(u, 1 - u), np.minimum(w, 1 - w)), np.abs(u - w)) > 1e-3
    through_top = np.isfinite(expected) & (np.sum(expected_normal * np.asarray(ours.normal), axis=1) > 1 - 1e-6)
    # and a single deepest point: no other contact on that triangle within 0.1 mm of it (an edge or
    # a face nearly parallel to the triangle: MuJoCo's iterative penetration then returns a point
    # between its ends, up to 3e-5 m short of the deepest end, which a sampled reference confirms)
    same_plane = np.sum(np.asarray(manifold.normal) * np.asarray(ours.normal)[:, None, :], axis=-1) > 1 - 1e-9
    close = np.asarray(manifold.distance[:, 1:]) < np.asarray(ours.distance)[:, None] + 1e-4
    single = ~np.any(same_plane[:, 1:] & np.asarray(manifold.active[:, 1:]) & close, axis=1)
    compared = interior & through_top & single & (expected < 0)
    assert compared.sum() >= count // 3, (compared.sum(), interior.sum(), through_top.sum(), single.sum())
    # (measured: within 5e-13 m)
    np.testing.assert_allclose(np.asarray(ours.distance)[compared], expected[compared], atol=1e-8)


def _rotation_x(angle):
    c, s = np.cos(angle), np.sin(angle)
    return jnp.asarray([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _flat_terrain(window=2, peak=0.0):
    heights = np.full((ROWS, COLUMNS), 0.1)
    heights[3, 3] += peak  # the grid point (x, y) = (0, 0.1)
    return sim.HeightField(heights, [HALF_X, HALF_Y], BASE, window=window)


def test_a_box_on_a_flat_terrain_has_the_closed_form_contacts():
    # A box over the interior of a cell of a flat terrain at 0.1 m (the cell's diagonal under it):
    # level, its bottom face's 4 corners at its height h above the terrain; tilted by an angle
    # about x, its low edge's 2 corners at z - 0.1 - (b sin + c cos), normals +z.
    field, half = _flat_terrain(), np.array([0.05, 0.04, 0.03])
    box = sim.Box(half)
    manifold = jax.jit(jax.vmap(lambda r, t: collide(field, (jnp.eye(3), jnp.zeros(3)), box, (r, t))))
    gaps = np.array([-2e-3, -1e-4, 0.0])
    level = manifold(jnp.broadcast_to(jnp.eye(3), (3, 3, 3)), jnp.asarray([[0.1, 0.0, 0.1 + half[2] + h] for h in gaps]))
    np.testing.assert_allclose(level.distance, np.repeat(gaps[:, None], 4, axis=1), atol=1e-12)
    np.testing.assert_allclose(level.normal, np.broadcast_to([0.0, 0.0, 1.0], (3, 4, 3)), atol=1e-12)
    assert bool(jnp.all(level.active))
    corners = np.array([[0.1 + sx * half[0], sy * half[1], 0.1 + gaps[0]] for sx in (-1, 1) for sy in (-1, 1)])
    np.testing.assert_allclose(np.sort(np.asarray(level.point2[0]), axis=0), np.sort(corners, axis=0), atol=1e-12)
    angles = np.array([0.1, 0.3, -0.5])
    sunk = 1e-3
    lowest = half[1] * np.abs(np.sin(angles)) + half[2] * np.cos(angles)
    tilted = manifold(jnp.stack([_rotation_x(a) for a in angles]), jnp.asarray([[0.1, 0.0, 0.1 + h - sunk] for h in lowest]))
    np.testing.assert_allclose(tilted.distance[:, 0], -sunk, atol=1e-12)
    assert np.all(np.asarray(tilted.active).sum(axis=1) == 2)
    np.testing.assert_allclose(np.where(tilted.active, tilted.distance, -sunk), -sunk, atol=1e-12)
    np.testing.assert_allclose(tilted.normal[tilted.active], np.broadcast_to([0.0, 0.0, 1.0], (6, 3)), atol=1e-12)


def test_a_peak_under_a_box_face_has_the_closed_form_contact():
    # One grid point raised 3 cm under the bottom face of a box tilted by 0.05 rad about x (its
    # slopes, 0.15, are steeper than the face's): the only contact is the peak's, at depth
    # cos(angle) (z - peak) - c below the face, normal minus the face's normal (0, -sin, cos).
    field = _flat_terrain(window=4, peak=0.03)
    half, angle, peak = np.array([0.15, 0.15, 0.05]), 0.05, np.array([0.0, 0.1, 0.13])
    depths = np.array([1e-3, 1e-2])
    z = peak[2] + (half[2] - depths) / np.cos(angle)
    contacts = jax.jit(jax.vmap(lambda t: collide(field, (jnp.eye(3), jnp.zeros(3)), sim.Box(half), (_rotation_x(angle), t))))(
        jnp.asarray([[0.0, 0.1, h] for h in z])
    )
    np.testing.assert_allclose(contacts.distance[:, 0], np.cos(angle) * (z - peak[2]) - half[2], atol=1e-12)
    np.testing.assert_allclose(contacts.distance[:, 0], -depths, atol=1e-12)
    np.testing.assert_allclose(contacts.normal[:, 0], np.broadcast_to([0.0, -np.sin(angle), np.cos(angle)], (2, 3)), atol=1e-12)
    np.testing.assert_allclose(contacts.point1[:, 0], np.broadcast_to(peak, (2, 3)), atol=1e-12)
    np.testing.assert_allclose(contacts.point2[:, 0] - contacts.point1[:, 0], contacts.distance[:, :1] * contacts.normal[:, 0], atol=1e-12)
    assert np.asarray(contacts.active).sum(axis=1).tolist() == [1, 1]


def _posed(rotation0):
    """The pose ``(rotation0 expm([w]x), t)`` of the parameters ``(t, w)`` ``(6,)``."""
    def pose(x):
        w = x[3:]
        skew = jnp.asarray([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
        return rotation0 @ jax.scipy.linalg.expm(skew), x[:3]
    return pose


def test_distances_to_a_terrain_have_finite_derivatives_equal_to_finite_differences():
    # At a flat terrain with the box's centre on a grid point and two of its bottom corners over
    # the cells' diagonals (an upright cylinder: its supports along -z have no radial part), the
    # Jacobian of the distances in the pose is finite; at a generic pose on a random terrain it
    # equals central finite differences. (The terrain, the shape and the pose are arguments: one
    # program per shape type.)
    def distances(field, shape, rotation0, x):
        return collide(field, (jnp.eye(3), jnp.zeros(3)), shape, _posed(rotation0)(x)).distance

    jacobian = jax.jit(jax.jacfwd(distances, argnums=3))
    flat, eye = _flat_terrain(), jnp.eye(3)
    for shape in [sim.Box([0.05, 0.05, 0.03]), sim.Cylinder(0.05, 0.03), sim.Ellipsoid([0.05, 0.04, 0.03])]:
        x = jnp.asarray([0.0, 0.1, 0.1 + 0.03 - 1e-3, 0.0, 0.0, 0.0])
        derivative = jacobian(flat, shape, eye, x)
        assert bool(jnp.all(jnp.isfinite(derivative))), type(shape).__name__
        np.testing.assert_allclose(derivative[0, :3], [0.0, 0.0, 1.0], atol=1e-12)
    rng = np.random.default_rng(3)
    field = sim.HeightField(rng.uniform(0, TOP, size=(ROWS, COLUMNS)), [HALF_X, HALF_Y], BASE, window=2)
    rotation0 = _rotation_x(0.2) @ jnp.asarray(np.linalg.qr(rng.normal(size=(3, 3)))[0])
    box = sim.Box([0.05, 0.04, 0.03])
    values = jax.jit(jax.vmap(distances, in_axes=(None, None, None, 0)))
    x = jnp.asarray([0.13, -0.07, 0.3, 0.0, 0.0, 0.0])
    x = x.at[2].add(-values(field, box, rotation0, x[None])[0, 0] - 2e-3)  # about 2 mm deep
    step = 1e-6
    shifted = values(field, box, rotation0, jnp.concatenate([x[None] + step * jnp.eye(6), x[None] - step * jnp.eye(6), x[None]]))
    assert -5e-3 < float(shifted[-1, 0]) < 0.0
    central = (shifted[:6] - shifted[6:12]).T / (2 * step)
    derivative = jacobian(field, box, rotation0, x)
    np.testing.assert_allclose(derivative, central, atol=1e-8)  # (measured: 7e-12)

