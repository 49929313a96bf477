"""Contacts between arbitrary collision shapes (`GeomPair`) in `RigidBodySystem`, and the
`sim.bodies` factory: resting, stacking, sliding against closed forms, a cross-check with the
hand-written sphere-box contact, and derivatives against finite differences."""

import dataclasses
import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import rsmooth.sim as sim
from rsmooth.sim import _derivatives

G = 9.81
H = 0.01


def _rollout(system, x0, steps):
    """States and diagnostics of `steps` steps at zero input (one compilation per system)."""
    us = jnp.zeros((steps, system.nu))
    xs, infos = eqx.filter_jit(lambda s, x: s.rollout(x, us))(system, x0)
    return np.asarray(xs), infos


def test_box_rests_on_floor_through_a_geom_pair():
    mass, half = 2.0, np.array([0.2, 0.1, 0.05])
    system = sim.bodies([sim.Box(half)], [mass], [[0.3, -0.2, half[2]]], time_step=H)
    assert system.num_contacts == 4
    assert isinstance(system.geometry.geom_pairs[0].shape1, sim.HalfSpace) and system.geometry.geom_pairs[0].frame1 is None
    x0 = np.asarray(system.initial_state())
    xs, infos = _rollout(system, x0, 100)
    sim.check_steps(infos, what="a box resting on the floor")  # warnings are errors
    assert np.max(np.abs(np.asarray(xs[:, :3] - x0[:3]))) < 1e-6
    assert np.max(np.abs(np.asarray(xs[:, 7:]))) < 1e-6  # at rest
    # the contact forces carry the weight, at every step
    total = np.asarray(infos.force).sum(axis=1)
    np.testing.assert_allclose(total, np.tile([0.0, 0.0, mass * G], (100, 1)), atol=1e-6)


def test_box_stack_rests():
    """A box on a box on the floor: the floor carries both weights, the lower box the upper."""
    half, masses = 0.1, [1.0, 0.5]
    system = sim.bodies(
        [sim.Box([half] * 3), sim.Box([0.08, 0.06, half])], masses, [[0, 0, half], [0, 0, 3 * half]], time_step=H
    )
    # pairs: floor-body0, floor-body1, body0-body1
    assert [type(p.shape1).__name__ for p in system.geometry.geom_pairs] == ["HalfSpace", "HalfSpace", "Box"]
    x0 = np.asarray(system.initial_state())
    xs, infos = _rollout(system, x0, 100)
    sim.check_steps(infos, what="a box stack")
    np.testing.assert_allclose(xs[:, :3], np.broadcast_to(x0[:3], (101, 3)), atol=1e-6)
    np.testing.assert_allclose(xs[:, 7:10], np.broadcast_to(x0[7:10], (101, 3)), atol=1e-6)
    assert np.max(np.abs(np.asarray(xs[:, 14:]))) < 1e-6
    force = np.asarray(infos.force[-1]).reshape(3, 4, 3).sum(axis=1)  # per pair
    np.testing.assert_allclose(force[0], [0, 0, sum(masses) * G], atol=1e-6)  # floor on the lower box
    np.testing.assert_allclose(force[1], 0.0, atol=1e-12)  # the upper box does not touch the floor
    np.testing.assert_allclose(force[2], [0, 0, masses[1] * G], atol=1e-6)  # on the upper box (shape 2)


def test_an_ellipsoid_rests_on_a_box_with_mujocos_inertia():
    """An ellipsoid lying on its shortest axis on a box on the floor: both stay put, the box
    carries the ellipsoid's weight through one contact; its inertia is MuJoCo's for the geom."""
    import mujoco

    radii, masses = np.array([0.12, 0.08, 0.05]), [1.0, 0.4]
    system = sim.bodies(
        [sim.Box([0.2, 0.2, 0.1]), sim.Ellipsoid(radii)], masses, [[0, 0, 0.1], [0.03, -0.02, 0.2 + radii[2]]], time_step=H
    )
    m = mujoco.MjModel.from_xml_string(
        f'<mujoco><worldbody><body><freejoint/><geom type="ellipsoid" size="{" ".join(map(str, radii))}" mass="0.4"/>'
        "</body></worldbody></mujoco>"
    )
    np.testing.assert_allclose(np.diag(np.asarray(system.model.body_inertia[2])), m.body_inertia[1], rtol=1e-12)
    x0 = np.asarray(system.initial_state())
    xs, infos = _rollout(system, x0, 100)
    sim.check_steps(infos, what="an ellipsoid on a box")
    np.testing.assert_allclose(xs[:, :14], np.broadcast_to(x0[:14], (101, 14)), atol=1e-6)
    assert np.max(np.abs(xs[:, 14:])) < 1e-6
    force = np.asarray(infos.force[-1])
    np.testing.assert_allclose(force[-4:].sum(axis=0), [0.0, 0.0, masses[1] * G], atol=1e-6)  # the box-ellipsoid pair


def test_equal_boxes_stacked_off_centre_rest():
    """Two equal boxes, the upper one shifted sideways by a quarter of its width (its centre
    of mass still over the lower box): it rests on the overlap of the faces, untilted, and
    the floor carries both weights. Equal faces make the face and edge axes of the
    separating axis test tie; an edge contact would be a single point and the box would
    tip."""
    half = 0.1
    system = sim.bodies([sim.Box([half] * 3)] * 2, [1.0, 1.0], [[0, 0, half], [0.05, 0.03, 3 * half]], time_step=H)
    x0 = np.asarray(system.initial_state())
    xs, infos = _rollout(system, x0, 100)
    sim.check_steps(infos, what="an off-centre box stack")
    assert np.all((np.asarray(infos.distance)[:, 8:] < 1.0).sum(axis=1) >= 3)  # inactive entries sit 10 m apart
    # the force split over the four corners is indeterminate: the solver's choice of it
    # moves the box by a fraction of a millimetre over the second, and tilts it by 1e-3 rad
    assert np.max(np.abs(xs[:, 7:10] - x0[7:10])) < 3e-4
    assert np.max(np.abs(xs[:, 10:13])) < 1e-3  # quaternion's vector part: half the tilt
    # over the last half second, the floor carries both weights and the lower box the upper
    force = np.asarray(infos.force[50:]).reshape(50, 3, 4, 3).sum(axis=2).mean(axis=0)
    np.testing.assert_allclose(force[0], [0, 0, 2 * G], atol=0.01)
    np.testing.assert_allclose(force[2], [0, 0, G], atol=0.01)


def test_a_tower_written_in_mjcf_rests_without_solver_iterations():
    """Five cubes stacked on a floor (MJCF, every pair of boxes collided, a contact budget of
    40): for 2 s each box stays at its analytic height, and every step's contact problem is
    solved by the sticking guess alone. Only the floor's contacts close under free motion
    (the boxes fall together); those between boxes carry the weight above them with a free
    normal velocity of zero, so the guess must hold them as sticking too."""
    n, half = 5, 0.05
    bodies = "".join(
        f'<body pos="0 0 {half * (2 * i + 1)}"><freejoint/><geom type="box" size="{half} {half} {half}" mass="1"/></body>'
        for i in range(n)
    )
    system = sim.scene(f'<mujoco><option timestep="{H}"/><worldbody><geom type="plane" size="1 1 0.1"/>{bodies}'
                       "</worldbody></mujoco>", max_contacts=8 * n)
    assert len(system.geometry.geom_pairs) == n + n * (n - 1) // 2
    xs, infos = _rollout(system, system.initial_state(), 200)
    assert sim.check_steps(infos) == {"steps": 200, "unconverged_steps": 0, "diverged_steps": 0, "dropped_contact_steps": 0, "skipped_pair_steps": 0,
                                       "inside_side_site_steps": 0}
    assert np.max(np.asarray(infos.ncp.iterations)) == 0
    heights = xs[:, : 7 * n].reshape(-1, n, 7)[:, :, 2]
    np.testing.assert_allclose(heights, np.broadcast_to(half * (2 * np.arange(n) + 1), heights.shape), rtol=0, atol=1e-9)
    # the floor carries the whole tower (to 1e-8 of its weight: rounding in the rank-deficient
    # split of the force over four corners)
    np.testing.assert_allclose(np.asarray(infos.force[-1])[:4].sum(axis=0), [0, 0, n * G], atol=1e-8 * n * G)


def test_pairs_of_one_type_are_evaluated_together_with_the_same_contacts(getkey):
    """Geometry pairs that differ only in their arrays go through one vmapped collision
    (`_pair_groups`), in either order of their shapes (a box against the sphere, the sphere
    against the other box); the contacts equal each pair's own, in pair order, at random poses
    of a scene of mixed shapes (boxes of two sizes, a sphere, a fixed slab)."""
    shapes = [sim.Box([0.1, 0.1, 0.1]), sim.Sphere(0.07), sim.Box([0.05, 0.08, 0.1])]
    slab = (sim.Box([1.0, 1.0, 0.1]), (jnp.eye(3), jnp.array([0.0, 0.0, -0.1])))
    system = sim.bodies(shapes, [1.0] * 3, [[0.2 * i, 0.05 * i, 0.15] for i in range(3)], obstacles=(slab,))
    pairs = system.geometry.geom_pairs
    groups = sim._simulator._pair_groups(pairs)
    assert len(groups) < len(pairs) and sorted(sum(groups, [])) == list(range(len(pairs)))
    assert any({sim._simulator._reversed(pairs[i]) for i in group} == {False, True} for group in groups)
    quaternions = jax.random.normal(getkey(), (3, 3, 4))
    positions = jax.random.uniform(getkey(), (3, 3, 3), minval=-0.1, maxval=0.1) + jnp.array([[[0.08 * b, 0.0, 0.1] for b in range(3)]])
    qs = jnp.concatenate([positions, quaternions / jnp.linalg.norm(quaternions, axis=-1, keepdims=True)], axis=-1).reshape(3, -1)

    def both(q, joints=None):
        kinematics = sim._dynamics._kinematics(system.model, q)
        separate = [system._geom_pair_contacts(kinematics, pair) for pair in system.geometry.geom_pairs]
        grouped = system._geom_pairs_contacts(kinematics)
        alone = [jnp.concatenate(parts) for parts in list(zip(*separate))[:3]] + [sim._simulator._joined_points([part[3] for part in separate])]
        if joints is not None:  # where they act: the joints (static) of the witness points
            joints.extend([(grouped[3][0], grouped[3][2]), (alone[3][0], alone[3][2])])
        # the contacts and the witness points and weights (the joints are static)
        return [*grouped[:3], *(grouped[3][i] for i in (1, 3, 4))], [*alone[:3], *(alone[3][i] for i in (1, 3, 4))]

    joints = []
    jax.eval_shape(lambda q: both(q, joints), qs[0])
    assert joints[0] == joints[1] and any(joints[0][0]) and any(joints[0][1])
    grouped, separate = jax.jit(jax.vmap(both))(qs)
    for together, alone in zip(grouped, separate):
        np.testing.assert_allclose(together, alone, rtol=1e-12, atol=1e-12)
    assert np.sum(np.asarray(grouped[0]) < 0.01) > 0  # some pairs touch at these poses


def test_a_group_over_its_memory_budget_is_collided_in_batches_with_the_same_contacts():
    """A pair group whose vmapped collision would take more than its byte budget is collided in
    batches (lax.map): the same contacts, in pair order, with a last batch of fewer pairs."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(2)
    count = 5
    boxes = [sim.Box(rng.uniform(0.05, 0.15, size=3)) for _ in range(2 * count)]
    stack = lambda shapes: jax.tree.map(lambda *leaves: jnp.stack(leaves), *shapes)  # noqa: E731
    shape1, shape2 = stack(boxes[:count]), stack(boxes[count:])
    pose1 = (jnp.asarray(Rotation.random(count, random_state=1).as_matrix()), jnp.zeros((count, 3)))
    pose2 = (jnp.asarray(Rotation.random(count, random_state=2).as_matrix()), jnp.asarray(rng.uniform(-0.35, 0.35, size=(count, 3))))
    per_pair = 16 * 8 * 12 * 12  # bytes: a box's 12 edges against the other's, float64
    whole, batched = (
        jax.jit(functools.partial(sim._simulator._collide_group, margin=0.05, budget=budget))(shape1, pose1, shape2, pose2)
        for budget in (count * per_pair, 2 * per_pair)
    )
    assert 0 < np.sum(np.asarray(whole.distance[:, 0]) < 0) < count  # some pairs overlap, some do not
    for field in ("distance", "normal", "point1", "point2", "active"):
        np.testing.assert_array_equal(np.asarray(getattr(batched, field)), np.asarray(getattr(whole, field)), err_msg=field)


def _slider(mu, height=0.1, **options):
    """A box (half side 0.1 m) with its centre at `height` over a world-fixed slab whose top
    face is z = 0; no floor."""
    slab = (sim.Box([1.0, 1.0, 0.1]), (jnp.eye(3), jnp.array([0.0, 0.0, -0.1])))
    return sim.bodies(
        [sim.Box([0.1, 0.1, 0.1])], [1.0], [[0.0, 0.0, height]], planes=(), obstacles=(slab,), friction=mu, time_step=H,
        **options,
    )


def test_box_slides_on_fixed_box_to_the_closed_form_distance():
    """With semi-implicit Euler, kinetic friction removes exactly mu g h of speed per step, so a
    box launched at v0 = N mu g h stops after N steps, having moved
    h sum_{k=1..N} (v0 - k mu g h) = v0^2 / (2 mu g) - v0 h / 2: the continuous closed form
    less half a step of travel (the first-order error of the time stepping). The discrete sum
    is met to the contact solver's accuracy; the continuous one within v0 h / 2."""
    mu, steps = 0.5, 20
    v0 = steps * mu * G * H
    system = _slider(mu)
    x0 = system.state(system.initial_configuration, jnp.zeros(6).at[0].set(v0))
    xs, infos = _rollout(system, x0, 60)
    sim.check_steps(infos, what="a box sliding on a box")
    travelled = float(xs[-1, 0] - xs[0, 0])
    discrete = v0**2 / (2 * mu * G) - v0 * H / 2
    continuous = v0**2 / (2 * mu * G)
    assert abs(travelled - discrete) < 1e-6
    assert abs(travelled - continuous) <= v0 * H / 2 + 1e-6
    assert np.max(np.abs(np.asarray(xs[steps + 1 :, 7:]))) < 1e-6  # at rest from step N on
    np.testing.assert_allclose(xs[:, 2], 0.1, atol=1e-6)  # no sinking or lifting
    np.testing.assert_allclose(np.asarray(infos.force[: steps - 1]).sum(axis=1), np.tile([-mu * G, 0, G], (steps - 1, 1)), atol=1e-6)


def _box_signed_distance(half, point):
    """The box's signed distance at ``point`` (box frame) and its gradient (the outward normal)."""
    excess = np.abs(point) - half
    outside = np.maximum(excess, 0.0)
    if np.any(excess > 0):
        return np.linalg.norm(outside), np.sign(point) * outside / np.linalg.norm(outside)
    face = int(np.argmax(excess))
    return excess[face], np.sign(point) * (np.arange(3) == face)


@pytest.mark.parametrize("radius", [0.02, 0.0])
def test_the_pushers_finger_contact_is_the_boxs_signed_distance_at_any_gap(radius):
    """The pusher's finger against its box (a GeomPair without a margin; radius 0: a point
    finger): distance and normal from the box's signed distance function at the finger's
    centre, minus the radius, at contact, apart (the box turned) and half a metre away; the
    Jacobian is the relative velocity of the finger's point against the box's."""
    pusher = sim.pusher(finger_radius=radius)
    half = 0.1
    assert pusher.num_contacts == 10 and float(pusher.contact_friction()[-1]) == 0.5
    contacts = eqx.filter_jit(lambda s, q: s.contacts(q))
    for gap, finger_y, angle in ((0.0, 0.0, 0.0), (0.0, 0.05, 0.0), (0.005, 0.03, -0.05), (0.5, 0.2, 0.3)):
        q = pusher.split(sim.pusher_start_state(pusher, finger_gap=gap, finger_y=finger_y))[0]
        q = q.at[3:7].set(jnp.array([0.0, 0.0, np.sin(angle / 2), np.cos(angle / 2)]))
        distance, frames, jacobian = contacts(pusher, q)
        rotation = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
        finger = np.array([float(q[7]), float(q[8]), half])  # at the box's mid-height
        expected, normal = _box_signed_distance(half, rotation.T @ (finger - np.asarray(q[:3])))
        np.testing.assert_allclose(distance[-1], expected - radius, atol=1e-12)
        np.testing.assert_allclose(frames[-1][:, 2], rotation @ normal, atol=1e-12)
        if gap == 0.0:  # the witness points coincide: the finger's x, y rates against the box's motion
            point = finger - radius * (rotation @ normal)
            lever = point - np.asarray(q[:3])
            box_velocity = np.concatenate([np.eye(3), -np.array([[0, -lever[2], lever[1]], [lever[2], 0, -lever[0]],
                                                                [-lever[1], lever[0], 0]])], axis=1)
            # the box's velocity is its body twist: in world axes, blockdiag(R, R) of it
            box_columns = box_velocity @ np.kron(np.eye(2), rotation)
            relative = np.concatenate([-box_columns, np.eye(3)[:, :2]], axis=1)
            np.testing.assert_allclose(jacobian[-3:], np.asarray(frames[-1]).T @ relative, atol=1e-12)


def test_step_jacobian_of_sliding_box_matches_finite_differences():
    """Mid-slide, away from mode switches, the implicit derivative equals central differences
    of the step. The box slides at 0.5 m/s without spinning, 0.1 mm into the slab, so that its
    four face contacts are all sliding, in one direction, and pushed out (Baumgarte) on both
    sides of every difference: at zero distance the position correction has a kink, and a
    spinning face contact has no unique friction torque (four coplanar contacts leave one
    pattern of normal forces free, which then changes the torque). Plain ADMM (no active-set
    polish) keeps the normal forces spread over the four contacts rather than at a vertex
    of that free set, where one contact would be weakly active."""
    system = _slider(0.3, height=0.1 - 1e-4, solver=sim.NCPSolver())
    # joint-actuated, but its geometry pairs are outside the closed-form derivatives: forward mode
    assert system.actuation.kind == "joints" and not _derivatives.supported(system)
    v = jnp.array([0.5, 0.1, 0.0, 0.0, 0.0, 0.0])
    x = system.state(system.initial_configuration, v)
    u = jnp.array([0.2, -0.1, 0.3, 0.0, 0.0, 0.0])
    # step_and_jacobians: forward mode through the step here (the closed form is gated off)
    _, fx, fu = eqx.filter_jit(lambda s, x_, u_: s.step_and_jacobians(x_, u_))(system, x, u)
    assert np.all(np.isfinite(fx)) and np.all(np.isfinite(fu))
    step_with_info = eqx.filter_jit(lambda s, x_, u_: s.step_with_info(x_, u_))
    np.testing.assert_array_equal(step_with_info(system, x, u)[1].mode, [sim.SLIDING] * 4)
    step = lambda x_, u_: step_with_info(system, x_, u_)[0]  # noqa: E731
    eps = 1e-5  # the solver's tolerance limits smaller steps
    numeric_x = np.stack([(step(x + eps * e, u) - step(x - eps * e, u)) / (2 * eps) for e in np.eye(system.nx)], axis=1)
    numeric_u = np.stack([(step(x, u + eps * e) - step(x, u - eps * e)) / (2 * eps) for e in np.eye(system.nu)], axis=1)
    np.testing.assert_allclose(fx, numeric_x, rtol=1e-4, atol=2e-5)
    np.testing.assert_allclose(fu, numeric_u, rtol=1e-4, atol=2e-5)


def test_bad_input_names_the_argument():
    box = sim.Box([0.1, 0.1, 0.1])
    with pytest.raises(ValueError, match="shape1"):
        sim.GeomPair("box", "body0", box, None, friction=0.5)
    with pytest.raises(ValueError, match="shape1 and shape2"):
        sim.GeomPair(sim.HalfSpace(), None, sim.HalfSpace(), "body0", friction=0.5)
    with pytest.raises(ValueError, match="frame1 and frame2"):
        sim.GeomPair(sim.HalfSpace(), None, box, None, friction=0.5)
    with pytest.raises(ValueError, match="frame2"):
        sim.GeomPair(sim.HalfSpace(), None, box, 1.5, friction=0.5)
    with pytest.raises(ValueError, match="friction"):
        sim.GeomPair(sim.HalfSpace(), None, box, "body0", friction=-0.1)
    with pytest.raises(ValueError, match="margin"):
        sim.GeomPair(sim.HalfSpace(), None, box, "body0", friction=0.1, margin=-1.0)
    with pytest.raises(ValueError, match="placement2"):
        sim.GeomPair(sim.HalfSpace(), None, box, "body0", friction=0.1, placement2=(2 * jnp.eye(3), jnp.zeros(3)))
    system = sim.bodies([box], [1.0], [[0, 0, 0.1]])
    with pytest.raises(ValueError, match=r"geom_pairs\[0\].frame2"):
        dataclasses.replace(system, geometry=sim.Geometry(geom_pairs=(sim.GeomPair(sim.HalfSpace(), None, box, "nope", friction=0.1),)))
    with pytest.raises(ValueError, match="masses"):
        sim.bodies([box], [1.0, 2.0], [[0, 0, 0.1]])
    with pytest.raises(ValueError, match=r"shapes\[0\]"):
        sim.bodies([sim.HalfSpace()], [1.0], [[0, 0, 0.1]])
    with pytest.raises(ValueError, match="positions"):
        sim.bodies([box], [1.0], [0, 0, 0.1])
