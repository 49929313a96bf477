"""Tests of `sim.scene`: a MuJoCo scene as a `RigidBodySystem`. References: the analytic resting
heights of the scene's bodies, and MuJoCo itself: the pairs and frictions of its contacts
(`mj_forward`) and its signed distances (`mj_geomDistance`) at seeded random configurations."""

import equinox as eqx
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

import rsmooth.sim as sim

# A stack of two boxes of different sizes (the upper one turned) and, side by
# side, a ball, a capsule lying on its side, a brick, a cylinder standing on its cap (its geom
# off its body's origin) and an ellipsoid lying on its shortest axis, each 2 mm above what it
# falls on. The objects beside the stack collide with the floor only (contype 2 meets the
# floor's conaffinity, nothing meets their conaffinity 0), so that the scene has 8 pairs rather
# than 28. The ball's priority makes its
# own friction apply against the floor; the capsule meets the floor through an explicit pair
# with its own friction.
SCENE = """<mujoco>
  <option timestep="0.02"/>
  <default><geom contype="2" conaffinity="0" friction="0.6"/></default>
  <worldbody>
    <geom name="floor" type="plane" size="2 2 0.1" contype="1" conaffinity="3" friction="0.8"/>
    <body name="base" pos="0 0 0.052"><freejoint/>
      <geom name="base" type="box" size="0.15 0.12 0.05" contype="1" conaffinity="1"/></body>
    <body name="middle" pos="0 0 0.144" euler="0 0 30"><freejoint/>
      <geom name="middle" type="box" size="0.1 0.08 0.04" contype="1" conaffinity="1" friction="0.9"/></body>
    <body name="ball" pos="0.5 0 0.072"><freejoint/>
      <geom name="ball" type="sphere" size="0.07" friction="0.3" priority="1"/></body>
    <body name="log" pos="0 0.5 0.042" euler="0 90 0"><freejoint/>
      <geom name="log" type="capsule" size="0.04 0.1"/></body>
    <body name="brick" pos="-0.5 0 0.042" euler="0 0 -20"><freejoint/>
      <geom name="brick" type="box" size="0.06 0.05 0.04"/></body>
    <body name="can" pos="0 -0.5 0.062"><freejoint/>
      <geom name="can" type="cylinder" size="0.05 0.06" pos="0.02 0 0"/></body>
    <body name="egg" pos="0.5 0.5 0.052" euler="0 0 40"><freejoint/>
      <geom name="egg" type="ellipsoid" size="0.08 0.06 0.05"/></body>
  </worldbody>
  <contact><pair geom1="floor" geom2="log" friction="0.5 0.5"/></contact>
</mujoco>"""
BODIES = ("base", "middle", "ball", "log", "brick", "can", "egg")
# Height of each body's frame above the floor at rest: the box stack's half heights, the
# ball's radius, the lying capsule's radius, the brick's half height, the cylinder's half length,
# the ellipsoid's shortest radius.
REST_HEIGHTS = np.array([0.05, 0.1 + 0.04, 0.07, 0.04, 0.04, 0.06, 0.05])


def test_scene_comes_to_rest_at_the_analytic_heights():
    system = sim.scene(SCENE)
    assert float(system.time_step) == 0.02  # MuJoCo's opt.timestep
    assert (system.nx, system.nu, len(system.geometry.geom_pairs), system.num_contacts) == (91, 0, 8, 24)
    assert isinstance(system.geometry.geom_pairs[0].shape2, sim.Capsule)  # the explicit pair comes first
    steps = 100  # 2 s
    xs, infos = eqx.filter_jit(lambda s, x: s.rollout(x, jnp.zeros((steps, 0))))(system, system.initial_state())
    counts = sim.check_steps(infos, what="a MuJoCo scene settling")  # a warning is an error here
    assert counts == {"steps": steps, "unconverged_steps": 0, "diverged_steps": 0, "dropped_contact_steps": 0, "skipped_pair_steps": 0,
                                       "inside_side_site_steps": 0}
    xs = np.asarray(xs)
    poses = xs[:, : system.model.nq].reshape(steps + 1, len(BODIES), 7)
    # qpos0: every body 2 mm above what it falls on, as the file places it
    np.testing.assert_allclose(poses[0, :, 2], REST_HEIGHTS + [0.002, 0.004, 0.002, 0.002, 0.002, 0.002, 0.002], atol=1e-12)
    np.testing.assert_allclose(poses[-1, :, 2], REST_HEIGHTS, atol=1e-3)
    # they settle straight down, without sliding or turning
    np.testing.assert_allclose(poses[-1, :, :2], poses[0, :, :2], atol=1e-3)
    np.testing.assert_allclose(np.abs(np.sum(poses[-1, :, 3:] * poses[0, :, 3:], axis=-1)), 1.0, atol=1e-6)
    assert np.max(np.abs(xs[-10:, system.model.nq :])) < 1e-3  # at rest over the last 0.2 s


def _random_qpos(rng, count: int) -> np.ndarray:
    """MuJoCo configurations of the scene: every body within 0.12 m of the origin sideways, its
    centre from 5 cm below the floor to 20 cm above, turned at random."""
    positions = np.concatenate(
        [rng.uniform(-0.12, 0.12, size=(count, len(BODIES), 2)), rng.uniform(-0.05, 0.2, size=(count, len(BODIES), 1))],
        axis=-1,
    )
    quaternions = rng.normal(size=(count, len(BODIES), 4))
    quaternions /= np.linalg.norm(quaternions, axis=-1, keepdims=True)
    return np.concatenate([positions, quaternions], axis=-1).reshape(count, -1)


def _distances(m, loaded, system, qpos) -> tuple[np.ndarray, np.ndarray]:
    """Signed distances ``(N, pairs)`` of every collision pair at MuJoCo configurations ``qpos``
    ``(N, nq)``: MuJoCo's (``mj_geomDistance``) and entry 0 of the system's manifolds (the
    system's margin must exceed them, else it reports 10 m)."""
    data = mujoco.MjData(m)
    expected = []
    for configuration in qpos:
        data.qpos[:] = configuration
        mujoco.mj_kinematics(m, data)
        expected.append([mujoco.mj_geomDistance(m, data, g1, g2, 1.0, None) for g1, g2 in loaded.collision_pairs])
    distances = jax.jit(jax.vmap(lambda q: system.contacts(q)[0]))(loaded.qpos_to_q(jnp.asarray(qpos)))
    starts = np.cumsum([0] + [pair.size for pair in system.geometry.geom_pairs])[:-1]
    return np.array(expected), np.asarray(distances)[:, starts]


def test_pairs_frictions_and_distances_match_mujoco():
    m = mujoco.MjModel.from_xml_string(SCENE)
    loaded = sim.load_mjcf(m)
    # a margin of 1 m makes entry 0 of every pair's manifold its signed distance in contacts()
    system = sim.scene(loaded, margin=1.0)
    names = [frozenset(loaded.geom_names[g] for g in pair) for pair in loaded.collision_pairs]
    kinds = [(type(p.shape1).__name__, type(p.shape2).__name__) for p in system.geometry.geom_pairs]
    expected_kinds = [(loaded.geom_types[a], loaded.geom_types[b]) for a, b in loaded.collision_pairs]
    shape_of = {"HalfSpace": "plane", "Box": "box", "Sphere": "sphere", "Capsule": "capsule", "Cylinder": "cylinder", "Ellipsoid": "ellipsoid"}
    assert [(shape_of[a], shape_of[b]) for a, b in kinds] == expected_kinds
    # geoms on the world are fixed there, the others ride on their body's frame
    for (g1, g2), pair in zip(loaded.collision_pairs, system.geometry.geom_pairs):
        for geom, frame in ((g1, pair.frame1), (g2, pair.frame2)):
            body = loaded.geom_bodies[geom]
            assert frame == (None if body == 0 else system.model.frame_id(loaded.body_names[body]))

    # signed distances of every pair at random configurations, about half of them penetrating
    expected, ours = _distances(m, loaded, system, _random_qpos(np.random.default_rng(0), 8))
    assert 0.3 < np.mean(expected < 0) < 0.7
    np.testing.assert_allclose(ours, expected, atol=1e-6)

    # frictions: with every margin at 1 m, MuJoCo reports one contact per pair at qpos0
    m.geom_margin[:] = 1.0
    m.pair_margin[:] = 1.0
    data = mujoco.MjData(m)
    mujoco.mj_forward(m, data)
    reported = {}
    for contact in data.contact[: data.ncon]:
        reported[frozenset(loaded.geom_names[g] for g in contact.geom)] = float(contact.friction[0])
    assert set(reported) == set(names)
    assert {name: float(pair.friction) for name, pair in zip(names, system.geometry.geom_pairs)} == pytest.approx(reported)
    assert reported[frozenset(("floor", "ball"))] == 0.3 and reported[frozenset(("floor", "log"))] == 0.5
    # a friction given overrides MuJoCo's
    assert {float(p.friction) for p in sim.scene(loaded, friction=0.25).geometry.geom_pairs} == {0.25}


# A hinged arm (its axis off the body's origin) whose capsule link swings through the floor,
# with a hand welded to it, turned, carrying a box off its origin.
ARM = """<mujoco><worldbody>
  <geom name="floor" type="plane" size="1 1 0.1"/>
  <body name="arm" pos="0 0 0.15" euler="10 0 0"><joint name="hinge" pos="0.05 0 0" axis="0 1 0" damping="0.3"/>
    <geom name="link" type="capsule" size="0.05" fromto="0 0 0 0.5 0 0"/>
    <body name="hand" pos="0.5 0 0" euler="0 30 45">
      <geom name="hand" type="box" size="0.08 0.05 0.03" pos="0.05 0 0" euler="20 0 0"/></body>
    {extra}
  </body></worldbody>
  <actuator><motor name="motor" joint="hinge" gear="2" ctrlrange="{low} 1"/></actuator>
</mujoco>"""


def test_hinged_and_welded_geoms_match_mujoco():
    """Geoms on a hinged body and on a body welded to it ride on their bodies' frames, placed
    as MuJoCo places them: MuJoCo's distances at random hinge angles."""
    m = mujoco.MjModel.from_xml_string(ARM.format(extra="", low=-1))
    loaded = sim.load_mjcf(m)
    system = sim.scene(loaded, margin=1.0)
    hand = system.model.frame_id("hand")
    assert [(p.frame1, p.frame2) for p in system.geometry.geom_pairs] == [(None, system.model.frame_id("arm")), (None, hand)]
    qpos = np.random.default_rng(1).uniform(-np.pi, np.pi, size=(16, 1))
    expected, ours = _distances(m, loaded, system, qpos)
    assert 0.2 < np.mean(expected < 0) < 0.8
    np.testing.assert_allclose(ours, expected, atol=1e-6)


def test_actuation_and_bad_input_are_named():
    with pytest.raises(ValueError, match=r"no joints \(nq = nv = 0\)"):
        sim.scene("<mujoco><worldbody><geom type='plane' size='1 1 0.1'/><geom size='0.1'/></worldbody></mujoco>")
    arm = sim.scene(ARM.format(extra="", low=-1))
    assert arm.actuation.dofs == (0,) and arm.nu == 1
    np.testing.assert_allclose(arm.actuation.input_limit, [2.0])  # ctrlrange times gear
    np.testing.assert_allclose(arm.joints.damping, [0.3])
    assert float(arm.time_step) == 0.002  # MuJoCo's default
    blob = sim.scene(ARM.format(extra='<geom name="blob" type="ellipsoid" size="0.1 0.2 0.1"/>', low=-1))
    assert any(isinstance(pair.shape2, sim.Ellipsoid) for pair in blob.geometry.geom_pairs)
    # a force range of [0, 2]: no symmetric bound on the hinge's force expresses it, so u is
    # the motor's control (a servo without a bias), clipped to [0, 1] as MuJoCo clips it
    one_sided = sim.scene(ARM.format(extra="", low=0))
    assert one_sided.actuation.kind == "servos" and one_sided.nu == 1
    q, v = one_sided.split(one_sided.initial_state())
    for ctrl, force in ((0.5, 1.0), (-0.5, 0.0), (3.0, 2.0)):
        tau, clipped = one_sided.generalized_forces(q, jnp.array([ctrl]), None, v)
        np.testing.assert_allclose(tau, [force], rtol=1e-15)
        assert bool(clipped) == (not 0.0 <= ctrl <= 1.0)
    for argument, value in (("time_step", 0.0), ("friction", -0.1), ("margin", -1.0)):
        with pytest.raises(ValueError, match=argument):
            sim.scene(ARM.format(extra="", low=-1), **{argument: value})
    with pytest.raises(ValueError, match="floating_base"):
        sim.scene(sim.load_mjcf(ARM.format(extra="", low=-1)), floating_base=True)


# One free object per scene, turned by a known angle; its lowest point in closed form.
# MuJoCo re-centres a mesh on its centroid and principal axes (geom_pos/geom_quat undo it):
# the tetrahedron's lowest vertex is the one of smallest y in the file's coordinates, which a
# quarter turn about x sends down.
ONE_OBJECT = """<mujoco>
  <asset><mesh name="tetrahedron" vertex="-0.1 -0.05 0  0.1 -0.05 0.02  0 0.2 0  0.03 0 0.3"/></asset>
  <worldbody><body name="object" pos="0.2 -0.1 {z}"><freejoint/><geom {geom}/></body></worldbody>
</mujoco>"""
TILT = np.deg2rad(np.array([30.0, 40.0, 50.0]))
LOWEST = {  # geom attributes -> lowest point below the body's origin
    'type="capsule" size="0.05 0.2" axisangle="0 1 0 30"': 0.2 * np.cos(TILT[0]) + 0.05,
    'type="box" size="0.1 0.2 0.3" axisangle="1 0 0 40"': 0.2 * np.sin(TILT[1]) + 0.3 * np.cos(TILT[1]),
    'type="cylinder" size="0.1 0.15" axisangle="1 1 0 50"': 0.15 * np.cos(TILT[2]) + 0.1 * np.sin(TILT[2]),
    'type="mesh" mesh="tetrahedron" axisangle="1 0 0 90"': 0.05,
}


def test_floor_touches_the_lowest_point_of_a_turned_shape():
    for geom, depth in LOWEST.items():
        system = sim.scene(ONE_OBJECT.format(z=1.0, geom=geom), floor=True, friction=0.3)
        (pair,) = system.geometry.geom_pairs
        assert isinstance(pair.shape1, sim.HalfSpace) and pair.frame1 is None and float(pair.friction) == 0.3
        np.testing.assert_allclose(pair.placement1[0], np.eye(3), atol=0)
        tolerance = 1e-8 if "mesh" in geom else 1e-12  # MuJoCo stores mesh vertices in float32
        np.testing.assert_allclose(pair.placement1[1], [0.0, 0.0, 1.0 - depth], rtol=0, atol=tolerance, err_msg=geom)
        # the collision code agrees: the shape touches the floor, nothing penetrates it
        distances = np.asarray(jax.jit(lambda q: system.contacts(q)[0])(system.initial_configuration))
        assert abs(distances.min()) < 1e-9, geom


# A floor under a scene of several objects: a free ball whose own friction applies to the
# floor, a visual geom far below (contype = conaffinity = 0: neither paired nor under the
# floor), a static shelf on the world (the lowest colliding geom, not paired: it does not move)
# and a hinged arm whose capsule (paired through an explicit pair only) hangs down.
FLOOR_SCENE = """<mujoco><worldbody>
  <geom name="shelf" type="box" size="0.2 0.2 0.05" pos="1 0 0.3"/>
  <body name="ball" pos="0 0 0.5"><freejoint/>
    <geom name="ball" type="sphere" size="0.1" friction="0.7"/>
    <geom name="ghost" type="sphere" size="0.1" pos="0 0 -5" contype="0" conaffinity="0"/></body>
  <body name="arm" pos="-1 0 0.8"><joint type="hinge" axis="0 1 0"/>
    <geom name="link" type="capsule" size="0.04" fromto="0 0 0 0 0 -0.3" contype="0" conaffinity="0"
          friction="0.2"/></body>
</worldbody><contact><pair geom1="shelf" geom2="link"/></contact></mujoco>"""


def test_floor_holds_the_moving_colliding_geoms_only():
    loaded = sim.load_mjcf(FLOOR_SCENE)
    plain = sim.scene(loaded)
    system = sim.scene(loaded, floor=True)
    floor_pairs = system.geometry.geom_pairs[len(plain.geometry.geom_pairs) :]
    assert len(plain.geometry.geom_pairs) == 2  # shelf-ball, and the explicit shelf-link
    # the ball and the link, by geom id; each with its geom's own friction
    ball, arm = system.model.frame_id("ball"), system.model.frame_id("arm")
    assert [(type(p.shape2).__name__, p.frame2, float(p.friction)) for p in floor_pairs] == [
        ("Sphere", ball, 0.7),
        ("Capsule", arm, 0.2),
    ]
    for pair in floor_pairs:  # under the shelf's bottom face, 0.3 - 0.05
        np.testing.assert_allclose(pair.placement1[1], [0.0, 0.0, 0.25], rtol=0, atol=1e-12)


def test_floor_and_self_collision_refuse_bad_input_by_name():
    for argument, value in (("floor", 1), ("self_collision", "no"), ("floating_base", None)):
        with pytest.raises(ValueError, match=rf"{argument} must be True or False"):
            sim.scene(ARM.format(extra="", low=-1), **{argument: value})
    with pytest.raises(ValueError, match=r"floor: the scene has no colliding geom on a moving body"):
        sim.scene(
            '<mujoco><worldbody><geom type="box" size="1 1 1"/><body pos="0 0 2"><joint/>'
            '<geom size="0.1" contype="0" conaffinity="0"/></body></worldbody></mujoco>', floor=True
        )
    blob = ONE_OBJECT.format(z=1.0, geom='name="blob" type="ellipsoid" size="0.1 0.2 0.1"')
    assert not sim.scene(blob).geometry.geom_pairs  # alone, it collides with nothing
    pairs = sim.scene(blob, floor=True).geometry.geom_pairs
    assert len(pairs) == 1 and isinstance(pairs[0].shape1, sim.HalfSpace) and isinstance(pairs[0].shape2, sim.Ellipsoid)


# Two kinematic trees and the world. The world body carries a floor and a post; a fixed-base
# arm (a base welded to the world, three hinged links in a chain) and a free chain of three
# boxes (hinged to one another) are the trees. MuJoCo pairs every two geoms but those welded
# together (floor, post, base) and, between two moving bodies, a parent and its child.
TREES = """<mujoco><worldbody>
  <geom name="floor" type="plane" size="2 2 0.1"/>
  <geom name="post" type="sphere" size="0.05" pos="0 1 0.5"/>
  <body name="base" pos="0 0 0.1"><geom name="base" type="cylinder" size="0.1 0.1"/>
    <body name="l1" pos="0 0 0.2"><joint type="hinge" axis="0 1 0"/><geom name="l1" type="capsule" size="0.03 0.1"/>
      <body name="l2" pos="0 0 0.2"><joint type="hinge" axis="0 1 0"/><geom name="l2" type="capsule" size="0.03 0.1"/>
        <body name="l3" pos="0 0 0.2"><joint type="hinge" axis="0 1 0"/>
          <geom name="l3" type="capsule" size="0.03 0.1"/></body></body></body></body>
  <body name="c1" pos="1 0 0.5"><freejoint/><geom name="c1" type="box" size="0.05 0.05 0.05"/>
    <body name="c2" pos="0.15 0 0"><joint type="hinge" axis="0 1 0"/><geom name="c2" type="box" size="0.05 0.05 0.05"/>
      <body name="c3" pos="0.15 0 0"><joint type="hinge" axis="0 1 0"/>
        <geom name="c3" type="box" size="0.05 0.05 0.05"/></body></body></body>
</worldbody></mujoco>"""


def test_without_self_collision_only_the_pairs_within_a_tree_are_dropped():
    loaded = sim.load_mjcf(TREES)
    names = [frozenset(loaded.geom_names[g] for g in pair) for pair in loaded.collision_pairs]
    # 9 geoms, 36 pairs, less 3 welded to the world together (floor, post, base) and 4
    # parent-child pairs of moving bodies (l1-l2, l2-l3, c1-c2, c2-c3)
    assert len(names) == 36 - 3 - 4
    within = {frozenset(p) for p in (("base", "l1"), ("base", "l2"), ("base", "l3"), ("l1", "l3"), ("c1", "c3"))}
    assert within <= set(names)

    def keys(system):  # the frames and shape types of a system's pairs: one key per geom pair here
        return [(type(p.shape1).__name__, p.frame1, type(p.shape2).__name__, p.frame2) for p in system.geometry.geom_pairs]

    every = keys(sim.scene(loaded))
    assert len(every) == 29
    kept = [key for key, name in zip(every, names) if name not in within]
    assert keys(sim.scene(loaded, self_collision=False)) == kept and len(kept) == 24
    # with a floor as well: its pairs (with the 6 moving geoms) come after those kept
    assert len(sim.scene(loaded, self_collision=False, floor=True).geometry.geom_pairs) == 24 + 6


def test_a_scene_without_contacts_falls_freely():
    # No colliding pair (no floor): the step has no contact problem to solve. The ball falls by
    # the time stepping's closed form, v_k = -g h k and z_k = z_0 - g h^2 k (k + 1) / 2, and the
    # step's Jacobians (the implicit-derivative path) equal forward-mode autodiff.
    system = sim.scene("""<mujoco><option timestep="0.01"/><worldbody>
      <body name="ball" pos="0 0 1"><freejoint/><geom type="sphere" size="0.1"/></body></worldbody></mujoco>""")
    assert system.num_contacts == 0 and system.nu == 0
    steps, h, g = 10, 0.01, 9.81
    xs, infos = eqx.filter_jit(lambda s, x, u: s.rollout(x, u))(system, system.initial_state(), jnp.zeros((steps, 0)))
    assert sim.check_steps(infos) == {"steps": steps, "unconverged_steps": 0, "diverged_steps": 0, "dropped_contact_steps": 0, "skipped_pair_steps": 0,
                                       "inside_side_site_steps": 0}
    k = np.arange(steps + 1)
    np.testing.assert_allclose(xs[:, 2], 1.0 - g * h**2 * k * (k + 1) / 2, rtol=0, atol=1e-12)
    np.testing.assert_allclose(xs[:, 9], -g * h * k, rtol=0, atol=1e-12)  # v_z (body axes = world here)
    x_next, fx, fu = eqx.filter_jit(lambda s, x, u: s.step_and_jacobians(x, u))(system, xs[3], jnp.zeros(0))
    np.testing.assert_allclose(x_next, xs[4], atol=1e-14)
    np.testing.assert_allclose(fx, eqx.filter_jit(lambda s, x, u: jax.jacfwd(s.step)(x, u))(system, xs[3], jnp.zeros(0)), atol=1e-12)
    assert fu.shape == (system.nx, 0)


def test_a_robot_with_undecodable_visual_meshes_stands_on_a_floor():
    # Go2 of example-robot-data: Collada visual meshes, which MuJoCo cannot decode; scene drops
    # every visual geom by default (visuals=False), without a warning (warnings are errors
    # here), and keeps its 19 collision meshes: each paired with the floor put under it. Its
    # zero configuration is beyond the calves' limits (-2.72 to -0.84 rad): that is warned of.
    root = sim.example_robot_data_root()
    path = root / "robots" / "go2_description" / "urdf" / "go2.urdf"
    with pytest.warns(UserWarning, match=r"limits of 4 joint\(s\) \('\w\w_calf_joint' by 0.838"):
        system = sim.scene(path, package_dirs=[root.parent], floating_base=True, floor=True, self_collision=False)
    assert (system.model.nq, system.model.nv) == (19, 18)
    assert len(system.geometry.geom_pairs) == 19
    assert all(isinstance(pair.shape1, sim.HalfSpace) and isinstance(pair.shape2, sim.ConvexMesh) for pair in system.geometry.geom_pairs)


def test_loading_options_are_refused_with_a_converted_model():
    loaded = sim.load_mjcf(ARM.format(extra="", low=-1))
    for options in (dict(visuals="auto"), dict(boundinertia=1e-9, drop_mimic=True), dict(drop_frictionloss=True)):
        with pytest.raises(ValueError, match=f"{', '.join(options)}: these options apply to a file or XML text"):
            sim.scene(loaded, **options)
    with pytest.raises(ValueError, match="visuals must be True, False or 'auto'"):
        sim.scene(ARM.format(extra="", low=-1), visuals=None)


# A spherical double pendulum (ball joints, damping on the first), colliding with nothing.
BALL_CHAIN = """<mujoco><option timestep="0.005" integrator="Euler"/><worldbody>
<body name="upper" pos="0 0 1"><joint name="shoulder" type="ball" damping="0.05"/>
<geom type="capsule" fromto="0 0 0 0.3 0.1 0" size="0.03" mass="0.8" contype="0" conaffinity="0"/>
<body name="lower" pos="0.3 0.1 0"><joint name="elbow" type="ball"/>
<geom type="box" size="0.1 0.03 0.02" pos="0.1 0 0" mass="0.4" contype="0" conaffinity="0"/></body></body>
</worldbody></mujoco>"""


def test_ball_joints_step_as_mujoco_euler(mujoco_and_rsmooth_trajectories):
    """Without contact, a step is MuJoCo's semi-implicit Euler step (implicit damping, the
    quaternion turned by exp(h omega / 2)), so the trajectories agree to rounding."""
    system, loaded, xs, expected = mujoco_and_rsmooth_trajectories(BALL_CHAIN, None, [0.5, -1.0, 2.0, 1.0, 0.3, -0.5], 200)
    assert system.model.joint_types[1:] == ("spherical", "spherical")
    ours = jax.vmap(loaded.q_to_qpos)(xs[1:, : system.model.nq])
    np.testing.assert_allclose(ours, expected, rtol=0, atol=1e-11)
    x_next, fx, _ = eqx.filter_jit(lambda s, x, u: s.step_and_jacobians(x, u))(system, xs[50], jnp.zeros(0))
    np.testing.assert_allclose(x_next, xs[51], atol=1e-14)
    reference = eqx.filter_jit(lambda s, x, u: jax.jacfwd(s.step)(x, u))(system, xs[50], jnp.zeros(0))
    np.testing.assert_allclose(fx, reference, atol=1e-10)


def test_bounded_mesh_hulls_are_what_mujoco_collides():
    """max_hull_vertices bounds MuJoCo's hull of each mesh (its maxhullvert): the hull's
    vertices are a subset of the mesh's, and the scene's signed distances between two such
    meshes, separated or penetrating, equal MuJoCo's on the same bounded hulls."""
    import trimesh

    vertices = trimesh.creation.icosphere(subdivisions=2, radius=0.1).vertices * [1.0, 0.7, 0.5]  # 162 on the hull
    text = (
        '<mujoco><asset><mesh name="pebble" vertex="{}"{}/></asset><worldbody>'
        '<body name="a"><freejoint/><geom type="mesh" mesh="pebble"/></body>'
        '<body name="b" pos="0.3 0 0"><freejoint/><geom type="mesh" mesh="pebble"/></body></worldbody></mujoco>'
    )
    xml = text.format(" ".join(f"{c:.6f}" for c in vertices.ravel()), "")
    loaded = sim.load_mjcf(xml, max_hull_vertices=12)
    hull, mesh = np.asarray(loaded.geom_hull[0]), np.asarray(loaded.geom_vertices[0])
    assert hull.shape == (12, 3) and mesh.shape == (162, 3)
    assert np.all(np.min(np.linalg.norm(hull[:, None] - mesh[None], axis=-1), axis=1) == 0)  # a subset
    assert sim.load_mjcf(xml).geom_hull[0].shape == (162, 3)  # unbounded: the whole hull
    system = sim.scene(loaded, margin=1.0)
    m = mujoco.MjModel.from_xml_string(text.format(" ".join(f"{c:.6f}" for c in vertices.ravel()), ' maxhullvert="12"'))
    rng = np.random.default_rng(3)
    qpos = np.zeros((8, 14))
    qpos[:, 7:10] = rng.uniform(-0.13, 0.13, size=(8, 3))  # b about a, at the origin: both cases
    for body in (0, 7):
        quaternion = rng.normal(size=(8, 4))
        qpos[:, body + 3 : body + 7] = quaternion / np.linalg.norm(quaternion, axis=1, keepdims=True)
    expected, ours = _distances(m, loaded, system, qpos)
    assert 0.2 < np.mean(expected < 0) < 0.8
    np.testing.assert_allclose(ours, expected, atol=1e-6)
    with pytest.raises(ValueError, match="max_hull_vertices must be None or an integer >= 4"):
        sim.load_mjcf(xml, max_hull_vertices=3)


def test_meshes_colliding_through_large_hulls_are_warned_of():
    """Two meshes whose hulls have hundreds of vertices each collide at a cost in proportion to
    the product of their edge counts: scene() warns, naming max_hull_vertices; bounded, it
    does not (warnings are errors here)."""
    import trimesh

    vertices = trimesh.creation.icosphere(subdivisions=3, radius=0.1).vertices  # 642, all on the hull
    xml = (
        '<mujoco><asset><mesh name="ball" vertex="{}"/></asset><worldbody>'
        '<body name="a"><freejoint/><geom name="left" type="mesh" mesh="ball"/></body>'
        '<body name="b" pos="0.3 0 0"><freejoint/><geom name="right" type="mesh" mesh="ball"/></body></worldbody></mujoco>'
    ).format(" ".join(f"{c:.6f}" for c in vertices.ravel()))
    with pytest.warns(UserWarning, match=r"2 mesh geom\(s\) collide with each other .*'left' \(642\).*max_hull_vertices"):
        sim.scene(xml)
    assert len(sim.scene(xml, max_hull_vertices=64).geometry.geom_pairs) == 1


def test_padded_meshes_collide_as_the_originals_and_share_groups():
    """Meshes padded to common array sizes (the simulator pads those of a pair group) give the
    same manifolds as the originals, separated or penetrating; meshes whose vertex counts lie
    within one power of 2 share a group."""
    import trimesh
    from scipy.spatial.transform import Rotation

    from rsmooth.sim._geometry import padded_meshes
    from rsmooth.sim._simulator import _pair_groups

    rng = np.random.default_rng(5)
    pebble = sim.convex_mesh(trimesh.creation.icosphere(subdivisions=1, radius=0.1).vertices * [1.0, 0.6, 0.4])
    rock = sim.convex_mesh(rng.normal(size=(30, 3)) * 0.08)
    padded = padded_meshes([pebble, rock], minimum=48)
    assert [leaf.shape for leaf in jax.tree.leaves(padded[0])] == [leaf.shape for leaf in jax.tree.leaves(padded[1])]
    for before, after in zip((pebble, rock), padded):  # each has entries repeated (42 and 15 vertices)
        assert any(a.shape != b.shape for a, b in zip(jax.tree.leaves(after), jax.tree.leaves(before)))
    rotations = jnp.asarray(Rotation.from_quat(rng.normal(size=(16, 4))).as_matrix())
    translations = jnp.asarray(rng.uniform(-0.2, 0.2, size=(16, 3)))
    identity = (jnp.eye(3), jnp.zeros(3))

    @jax.jit
    def manifolds(a, b):
        return jax.vmap(lambda r, t: sim.collide(a, identity, b, (r, t), margin=0.05))(rotations, translations)

    original, ours = manifolds(pebble, rock), manifolds(*padded)
    assert 0.2 < np.mean(np.asarray(original.distance[:, 0]) < 0) < 0.8
    active = np.asarray(original.active)
    np.testing.assert_array_equal(np.asarray(ours.active), active)
    for field in ("distance", "normal", "point1", "point2"):  # of the manifolds' contacts
        expected, actual = np.asarray(getattr(original, field))[active], np.asarray(getattr(ours, field))[active]
        np.testing.assert_allclose(actual, expected, rtol=0, atol=1e-12, err_msg=field)
    # hulls of 20, 40 and 60 vertices (points spread on a sphere): 40 and 60 share a group

    def on_sphere(n):
        height = 1.0 - (2.0 * np.arange(n) + 1.0) / n
        angle = np.pi * (3.0 - np.sqrt(5.0)) * np.arange(n)
        ring = np.sqrt(1.0 - height**2)
        return sim.convex_mesh(0.1 * np.stack([ring * np.cos(angle), ring * np.sin(angle), height], axis=1))

    hulls = [on_sphere(n) for n in (20, 40, 60)]
    assert [hull.vertices.shape[0] for hull in hulls] == [20, 40, 60]
    pair = lambda mesh: sim.GeomPair(pebble, None, mesh, 1, friction=0.5)  # noqa: E731
    assert _pair_groups(tuple(pair(hull) for hull in hulls)) == [[0], [1, 2]]


def test_a_start_beyond_the_joint_limits_is_warned_of_by_joint():
    # qpos0 = 0 lies 0.5 rad below the knee's range and within the hip's.
    text = """<mujoco><compiler angle="radian"/><worldbody><body name="thigh"><joint name="hip" range="-1 1"/>
      <geom type="capsule" size="0.02" fromto="0 0 0 0 0 -0.3"/>
      <body name="shin" pos="0 0 -0.3"><joint name="knee" range="0.5 2"/>
        <geom type="capsule" size="0.02" fromto="0 0 0 0 0 -0.3"/></body></body></worldbody></mujoco>"""
    with pytest.warns(UserWarning, match=r"the XML text: .*limits of 1 joint\(s\) \('knee' by 0\.5;.*joint_limits=False"):
        system = sim.scene(text)
    assert np.asarray(system.initial_state()).tolist() == [0.0] * 4  # the start is the file's
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        sim.scene(text, joint_limits=False)
