"""Rigid-body dynamics in JAX (rsmooth.sim) against Pinocchio, the reference implementation.

Each jitted function is compiled once per model and evaluated on a batch of random
configurations with ``vmap``; the comparisons hold to 1e-8 relative to the quantity's scale.
"""

import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rsmooth import sim
from rsmooth.sim import _spatial as spatial

pin = pytest.importorskip("pinocchio")

FEET = ("FL_FOOT", "FR_FOOT", "HL_FOOT", "HR_FOOT")
REFERENCES = {
    "local_world_aligned": pin.LOCAL_WORLD_ALIGNED,
    "local": pin.LOCAL,
    "world": pin.WORLD,
}
NUM_CONFIGURATIONS = 4
TOLERANCE = 1e-8


def assert_close(actual, expected, tolerance=TOLERANCE):
    """Agreement to ``tolerance``, relative to the largest entry of ``expected`` (at least 1)."""
    expected = np.asarray(expected)
    scale = max(1.0, float(np.abs(expected).max(initial=0.0)))
    np.testing.assert_allclose(np.asarray(actual), expected, rtol=tolerance, atol=tolerance * scale)


def random_configuration(pin_model, rng):
    """Uniform joint positions in [-pi, pi] (prismatic: [-1, 1] m), random base pose."""
    q = np.zeros(pin_model.nq)
    for joint in pin_model.joints[1:]:
        name = joint.shortname()
        if name == "JointModelFreeFlyer":
            quaternion = rng.normal(size=4)
            q[joint.idx_q : joint.idx_q + 7] = np.concatenate([rng.uniform(-1, 1, 3), quaternion / np.linalg.norm(quaternion)])
        elif name == "JointModelSpherical":
            quaternion = rng.normal(size=4)
            q[joint.idx_q : joint.idx_q + 4] = quaternion / np.linalg.norm(quaternion)
        elif name.startswith("JointModelP"):
            q[joint.idx_q] = rng.uniform(-1, 1)
        else:
            q[joint.idx_q] = rng.uniform(-np.pi, np.pi)
    return q


def random_states(pin_model, seed, count=NUM_CONFIGURATIONS):
    rng = np.random.default_rng(seed)
    qs = np.stack([random_configuration(pin_model, rng) for _ in range(count)])
    vs, accelerations, torques = (rng.normal(size=(count, pin_model.nv)) for _ in range(3))
    return qs, vs, accelerations, torques


def all_terms(model, q, v, a, tau):
    """Every joint-space quantity under test, for one state."""
    rotations, translations = sim.forward_kinematics(model, q)
    return {
        "rotations": rotations,
        "translations": translations,
        "mass_matrix": sim.crba(model, q),
        "rnea": sim.rnea(model, q, v, a),
        "nonlinear_effects": sim.nonlinear_effects(model, q, v),
        "gravity": sim.gravity_torques(model, q),
        "forward_dynamics": sim.forward_dynamics(model, q, v, tau),
    }


def frame_terms(model, q, v, frames):
    """Placements and Jacobians of ``frames``, and velocities of the first one, for one state."""
    out = {}
    for frame in frames:
        out[frame, "placement"] = sim.frame_placement(model, q, frame)
        for reference in REFERENCES:
            out[frame, reference] = sim.frame_jacobian(model, q, frame, reference)
            if frame == frames[0]:
                out[frame, reference, "velocity"] = sim.frame_velocity(model, q, v, frame, reference)
    return out


batched_terms = jax.jit(jax.vmap(all_terms, in_axes=(None, 0, 0, 0, 0)))
batched_frame_terms = jax.jit(jax.vmap(frame_terms, in_axes=(None, 0, 0, None)), static_argnums=3)


def pinocchio_terms(pin_model, q, v, a, tau, frames):
    """The same quantities as :func:`all_terms` and :func:`frame_terms`, from Pinocchio."""
    data = pin_model.createData()
    pin.forwardKinematics(pin_model, data, q)
    out = {
        "rotations": np.stack([m.rotation for m in data.oMi]),
        "translations": np.stack([m.translation for m in data.oMi]),
        "mass_matrix": pin.crba(pin_model, data, q).copy(),
        "rnea": pin.rnea(pin_model, data, q, v, a).copy(),
        "nonlinear_effects": pin.nonLinearEffects(pin_model, data, q, v).copy(),
        "gravity": pin.computeGeneralizedGravity(pin_model, data, q).copy(),
        "forward_dynamics": pin.aba(pin_model, data, q, v, tau).copy(),
    }
    pin.forwardKinematics(pin_model, data, q, v)
    pin.computeJointJacobians(pin_model, data, q)
    pin.updateFramePlacements(pin_model, data)
    for frame in frames:
        frame_id = pin_model.getFrameId(frame)
        placement = data.oMf[frame_id]
        out[frame, "placement"] = (placement.rotation.copy(), placement.translation.copy())
        for reference, pin_reference in REFERENCES.items():
            out[frame, reference] = pin.getFrameJacobian(pin_model, data, frame_id, pin_reference).copy()
            out[frame, reference, "velocity"] = pin.getFrameVelocity(
                pin_model, data, frame_id, pin_reference
            ).vector.copy()
    return out


def compare_with_pinocchio(model, pin_model, states, frames):
    qs, vs, accelerations, torques = states
    ours = batched_terms(model, qs, vs, accelerations, torques)
    ours_frames = batched_frame_terms(model, qs, vs, frames)
    for k in range(len(qs)):
        reference = pinocchio_terms(pin_model, qs[k], vs[k], accelerations[k], torques[k], frames)
        for name, value in ours.items():
            assert_close(value[k], reference[name])
        for key, value in ours_frames.items():
            if key[-1] == "placement":
                assert_close(value[0][k], reference[key][0])
                assert_close(value[1][k], reference[key][1])
            else:
                assert_close(value[k], reference[key])


# --------------------------------------------------------------------------------------
# Solo-12
# --------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def solo():
    path = sim.solo12_urdf_path()
    pin_model = pin.buildModelFromUrdf(str(path), pin.JointModelFreeFlyer())
    return sim.load_urdf(path), pin_model


def test_solo12_model_structure(solo):
    model, pin_model = solo
    assert (model.nq, model.nv, model.njoints) == (19, 18, 14)
    assert model.joint_types[1] == "free_flyer"
    assert set(model.joint_types[2:]) == {"revolute"}
    assert float(jnp.sum(model.body_mass)) == pytest.approx(2.5, abs=0.01)
    assert model.frame_parents[model.frame_id("FL_FOOT")] == pin_model.frames[pin_model.getFrameId("FL_FOOT")].parentJoint
    # Unlimited coordinates are infinite (Pinocchio uses the largest double).
    assert bool(jnp.all(jnp.isinf(model.upper_position_limit[:7])))
    assert float(model.upper_position_limit[7]) == 10.0
    leaves = jax.tree_util.tree_leaves(model)
    assert all(isinstance(leaf, jax.Array) for leaf in leaves)


def test_solo12_matches_pinocchio(solo):
    model, pin_model = solo
    compare_with_pinocchio(model, pin_model, random_states(pin_model, seed=0), FEET)


def test_solo12_standing_configuration(solo):
    model, pin_model = solo
    q0 = sim.solo12_standing_configuration(model)
    srdf = sim.solo12_urdf_path().parents[1] / "srdf" / "solo.srdf"
    pin.loadReferenceConfigurations(pin_model, str(srdf), False)
    np.testing.assert_array_equal(np.asarray(q0), pin_model.referenceConfigurations["standing"])
    # Field notes: feet about 0.019 m above the ground when standing.
    q0_batch = jnp.broadcast_to(q0, (NUM_CONFIGURATIONS, model.nq))
    frames = batched_frame_terms(model, q0_batch, jnp.zeros((NUM_CONFIGURATIONS, model.nv)), FEET)
    for foot in FEET:
        _, translation = frames[foot, "placement"]
        assert float(translation[0, 2]) == pytest.approx(0.019, abs=2e-3)


def test_solo12_urdf_comes_from_the_installed_package():
    path = sim.solo12_urdf_path()
    assert path.is_file() and path.name == "solo12.urdf"
    assert "cmeel.prefix" in path.parts


def test_integrate_and_difference_match_pinocchio(solo):
    model, pin_model = solo
    rng = np.random.default_rng(1)
    qs = np.stack([random_configuration(pin_model, rng) for _ in range(6)])
    targets = np.stack([random_configuration(pin_model, rng) for _ in range(6)])
    vs = rng.normal(size=(6, 18))
    # Angular speeds beyond pi (hemisphere flip), tiny (Taylor branch) and zero.
    for k, speed in enumerate([0.5, 3.0, 5.0, 9.0, 1e-7, 0.0]):
        vs[k, 3:6] *= speed / np.linalg.norm(vs[k, 3:6])
    # A relative rotation close to pi exercises the logarithm's hardest case.
    targets[0] = pin.integrate(pin_model, qs[0], np.r_[0.1, -0.2, 0.3, 0.0, 0.0, np.pi - 1e-6, np.zeros(12)])
    integrate = jax.jit(jax.vmap(sim.integrate, in_axes=(None, 0, 0, None)))
    difference = jax.jit(jax.vmap(sim.difference, in_axes=(None, 0, 0)))
    ours_integrate = integrate(model, qs, vs, 0.5)
    ours_difference = difference(model, qs, targets)
    for k in range(6):
        assert_close(ours_integrate[k], pin.integrate(pin_model, qs[k], 0.5 * vs[k]))
        assert_close(ours_difference[k], pin.difference(pin_model, qs[k], targets[k]))
    # integrate(q, difference(q, q1)) is q1 (the quaternion up to sign).
    round_trip = integrate(model, qs, ours_difference, 1.0)
    for k in range(6):
        sign = np.sign(np.dot(round_trip[k, 3:7], targets[k, 3:7]))
        assert_close(round_trip[k, 3:7] * sign, targets[k, 3:7])
        assert_close(round_trip[k, 7:], targets[k, 7:])
        assert_close(round_trip[k, :3], targets[k, :3])


def test_derivatives_at_zero_motion_are_finite(solo):
    model, pin_model = solo
    q = np.asarray(sim.solo12_standing_configuration(model))

    def round_trip(step):
        return sim.difference(model, q, sim.integrate(model, q, step))

    jacobian = jax.jit(jax.jacfwd(round_trip))(jnp.zeros(model.nv))
    assert_close(jacobian, np.eye(model.nv))
    gradient = jax.jit(jax.grad(lambda step: jnp.sum(sim.integrate(model, q, step) ** 2)))(jnp.zeros(model.nv))
    assert bool(jnp.all(jnp.isfinite(gradient)))


def test_forward_dynamics_derivatives_match_pinocchio(solo):
    """jacfwd of forward_dynamics in Pinocchio's tangent convention q (+) dq, and jacrev."""
    model, pin_model = solo
    qs, vs, _, torques = random_states(pin_model, seed=2, count=3)

    def tangent_dynamics(q, step, v, tau):
        return sim.forward_dynamics(model, sim.integrate(model, q, step), v, tau)

    jacobians = jax.jit(jax.vmap(jax.jacfwd(tangent_dynamics, argnums=(1, 2, 3)), in_axes=(0, None, 0, 0)))
    # Reverse mode, as an optimizer uses it: one vector-Jacobian product per state.
    cotangents = np.random.default_rng(4).normal(size=(len(qs), model.nv))

    def weighted(q, step, v, tau, cotangent):
        return jnp.sum(cotangent * tangent_dynamics(q, step, v, tau))

    gradients = jax.jit(jax.vmap(jax.grad(weighted, argnums=(1, 2, 3)), in_axes=(0, None, 0, 0, 0)))
    zero = jnp.zeros(model.nv)
    ours_forward = jacobians(qs, zero, vs, torques)
    ours_reverse = gradients(qs, zero, vs, torques, cotangents)
    data = pin_model.createData()
    for k in range(len(qs)):
        expected = pin.computeABADerivatives(pin_model, data, qs[k], vs[k], torques[k])
        expected = [np.array(x) for x in expected]
        expected[2] = np.triu(expected[2]) + np.triu(expected[2], 1).T  # Pinocchio fills Minv's upper half
        for forward, reverse, reference in zip(ours_forward, ours_reverse, expected):
            assert_close(forward[k], reference)
            assert_close(reverse[k], cotangents[k] @ reference)


def test_jit_and_vmap_agree_with_a_loop(solo, getkey):
    model, _ = solo
    q0 = sim.solo12_standing_configuration(model)
    steps = 0.5 * jax.random.normal(getkey(), (NUM_CONFIGURATIONS, model.nv))
    qs = jnp.stack([sim.integrate(model, q0, step) for step in steps])
    vs = jax.random.normal(getkey(), (NUM_CONFIGURATIONS, model.nv))
    torques = jax.random.normal(getkey(), (NUM_CONFIGURATIONS, model.nv))
    batched = batched_terms(model, qs, vs, vs, torques)["forward_dynamics"]
    single = jax.jit(sim.forward_dynamics)
    for k in range(NUM_CONFIGURATIONS):
        # Different compilations may round differently: agreement to 1e-10, not bit for bit.
        assert_close(batched[k], single(model, qs[k], vs[k], torques[k]), tolerance=1e-10)


def test_gravity_argument_overrides_the_model(solo):
    model, pin_model = solo
    q = np.asarray(sim.solo12_standing_configuration(model))
    gravity = np.array([1.0, -2.0, -3.0])
    moon = pin_model.copy()
    moon.gravity = pin.Motion(np.r_[gravity, 0.0, 0.0, 0.0])
    assert_close(sim.gravity_torques(model, q, gravity=gravity), pin.computeGeneralizedGravity(moon, moon.createData(), q))
    v = np.linspace(-1, 1, 18)
    assert_close(sim.rnea(model, q, v, v, gravity=gravity), pin.rnea(moon, moon.createData(), q, v, v))


# --------------------------------------------------------------------------------------
# A synthetic tree: prismatic and revolute joints, unaligned axes, several roots, armature
# --------------------------------------------------------------------------------------


def _placement(rng):
    return pin.SE3(pin.exp3(rng.normal(size=3)), rng.normal(size=3))


def _joint_adder(pin_model, rng):
    """``add(parent, joint_model, name)``: a joint at a random placement carrying a body of
    random mass, centre of mass and inertia; returns its index."""

    def add(parent, joint_model, name):
        joint = pin_model.addJoint(parent, joint_model, _placement(rng), name)
        root = rng.normal(size=(3, 3))
        inertia = pin.Inertia(rng.uniform(0.5, 2.0), rng.normal(size=3) * 0.3, root @ root.T + 0.1 * np.eye(3))
        pin_model.appendBodyToJoint(joint, inertia, pin.SE3.Identity())
        return joint

    return add


def synthetic_pin_model():
    rng = np.random.default_rng(7)
    pin_model = pin.Model()
    pin_model.gravity = pin.Motion(np.array([0.5, -1.0, -9.0, 0.0, 0.0, 0.0]))

    add = _joint_adder(pin_model, rng)

    axis = rng.normal(size=3)
    first = add(0, pin.JointModelRevoluteUnaligned(axis / np.linalg.norm(axis)), "hinge")
    slider = add(first, pin.JointModelPX(), "slider_x")
    wrist = add(slider, pin.JointModelRZ(), "wrist")
    axis = rng.normal(size=3)
    branch = add(first, pin.JointModelPrismaticUnaligned(axis / np.linalg.norm(axis)), "slider_skew")
    tip = add(branch, pin.JointModelRY(), "elbow")
    add(0, pin.JointModelPZ(), "lift")
    pin_model.addFrame(pin.Frame("tip", tip, _placement(rng), pin.FrameType.OP_FRAME))
    pin_model.addFrame(pin.Frame("hand", wrist, _placement(rng), pin.FrameType.OP_FRAME))
    pin_model.armature = rng.uniform(0.01, 0.1, size=pin_model.nv)
    return pin_model


def test_synthetic_tree_matches_pinocchio():
    pin_model = synthetic_pin_model()
    model = sim.from_pinocchio(pin_model)
    assert model.joint_types[1:] == ("revolute", "prismatic", "revolute", "prismatic", "revolute", "prismatic")
    compare_with_pinocchio(model, pin_model, random_states(pin_model, seed=3), ("tip", "hand"))


def test_ball_joints_match_pinocchio():
    """Spherical (ball) joints, in a fixed chain and below a free flyer: kinematics, dynamics,
    frame Jacobians, integrate and difference as Pinocchio's JointModelSpherical."""
    rng = np.random.default_rng(11)
    pin_model = pin.Model()

    add = _joint_adder(pin_model, rng)

    shoulder = add(0, pin.JointModelSpherical(), "shoulder")
    elbow = add(shoulder, pin.JointModelRY(), "elbow")
    wrist = add(elbow, pin.JointModelSpherical(), "wrist")
    base = add(0, pin.JointModelFreeFlyer(), "base")
    neck = add(base, pin.JointModelSpherical(), "neck")
    pin_model.addFrame(pin.Frame("hand", wrist, _placement(rng), pin.FrameType.OP_FRAME))
    pin_model.addFrame(pin.Frame("head", neck, _placement(rng), pin.FrameType.OP_FRAME))
    model = sim.from_pinocchio(pin_model)
    assert model.joint_types[1:] == ("spherical", "revolute", "spherical", "free_flyer", "spherical")
    assert (model.nq, model.nv) == (4 + 1 + 4 + 7 + 4, 3 + 1 + 3 + 6 + 3)
    states = random_states(pin_model, seed=5)
    compare_with_pinocchio(model, pin_model, states, ("hand", "head"))
    qs, vs = states[0], states[1]
    for k in range(len(qs)):
        q1 = pin.integrate(pin_model, qs[k], 0.3 * vs[k])
        assert_close(sim.integrate(model, qs[k], vs[k], 0.3), q1)
        assert_close(sim.difference(model, qs[k], q1), pin.difference(pin_model, qs[k], q1))


# --------------------------------------------------------------------------------------
# Loading errors and boundary checks
# --------------------------------------------------------------------------------------


def test_saved_model_loads_without_pinocchio_and_matches_it(solo, tmp_path, monkeypatch):
    model, pin_model = solo
    path = sim.save_model(tmp_path / "solo12", model)
    assert path == tmp_path / "solo12.npz" and path.is_file()
    assert [p.name for p in tmp_path.iterdir()] == ["solo12.npz"]  # no temporary left
    # Loading must not need Pinocchio: make importing it fail.
    monkeypatch.setitem(sys.modules, "pinocchio", None)
    loaded = sim.load_model(path)
    for name in ("joint_names", "joint_types", "parents", "idx_q", "idx_v", "frame_names", "frame_parents", "nq", "nv"):
        assert getattr(loaded, name) == getattr(model, name), name
    for (where, original), restored in zip(jax.tree_util.tree_leaves_with_path(model), jax.tree_util.tree_leaves(loaded)):
        np.testing.assert_array_equal(np.asarray(restored), np.asarray(original), err_msg=str(where))
    compare_with_pinocchio(loaded, pin_model, random_states(pin_model, seed=3), FEET)


def test_load_model_rejects_other_files(tmp_path):
    with pytest.raises(FileNotFoundError, match="missing.npz"):
        sim.load_model(tmp_path / "missing.npz")
    (tmp_path / "text.npz").write_text("not a zip")
    with pytest.raises(ValueError, match="text.npz is not a model file"):
        sim.load_model(tmp_path / "text.npz")
    np.savez(tmp_path / "arrays.npz", a=np.zeros(3))
    with pytest.raises(ValueError, match="arrays.npz is not a model file"):
        sim.load_model(tmp_path / "arrays.npz")
    path = sim.save_model(tmp_path / "body.npz", sim.free_body(1.0, [1.0, 1.0, 1.0]))
    with np.load(path) as data:
        contents = {name: data[name] for name in data.files if name != "body_mass"}
    np.savez(tmp_path / "partial.npz", **contents)
    with pytest.raises(ValueError, match="lacks the model fields \\['body_mass'\\]"):
        sim.load_model(tmp_path / "partial.npz")
    with pytest.raises(TypeError, match="model must be an rsmooth.sim.Model"):
        sim.save_model(tmp_path / "x.npz", {"nq": 7})


def test_missing_urdf_raises_file_not_found(tmp_path):
    path = tmp_path / "nowhere.urdf"
    with pytest.raises(FileNotFoundError, match="nowhere.urdf"):
        sim.load_urdf(path)


@pytest.mark.parametrize(
    "text",
    [
        '<robot name="broken"><link name="base">',  # not well-formed XML
        "<mujoco/>",  # XML, but not URDF
        # Well-formed URDF that urdfdom rejects (the child link does not exist).
        '<robot name="r"><link name="a"/><joint name="j" type="revolute"><parent link="a"/>'
        '<child link="missing"/><limit effort="1" lower="-1" upper="1" velocity="1"/></joint></robot>',
    ],
)
def test_malformed_urdf_raises_value_error(tmp_path, text):
    path = tmp_path / "malformed.urdf"
    path.write_text(text)
    with pytest.raises(ValueError, match="malformed.urdf"):
        sim.load_urdf(path)


URDF_WITH_CONTINUOUS_JOINT = """<robot name="cart">
  <link name="body"><inertial><mass value="1"/><inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial></link>
  <link name="wheel"><inertial><mass value="1"/><inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial></link>
  <joint name="wheel_spin" type="continuous">
    <parent link="body"/><child link="wheel"/><axis xyz="0 1 0"/>
  </joint>
</robot>
"""


def test_unsupported_joint_is_named(tmp_path):
    path = tmp_path / "cart.urdf"
    path.write_text(URDF_WITH_CONTINUOUS_JOINT)
    with pytest.raises(ValueError, match="wheel_spin"):
        sim.load_urdf(path)
    # The same file with the joint made revolute loads, fixed or floating.
    path.write_text(URDF_WITH_CONTINUOUS_JOINT.replace('type="continuous"', 'type="revolute"').replace(
        "<axis", '<limit effort="1" lower="-1" upper="1" velocity="1"/><axis'))
    assert sim.load_urdf(path, floating_base=False).nq == 1
    assert sim.load_urdf(path).nq == 8


def test_boundary_checks(solo):
    model, _ = solo
    with pytest.raises(ValueError, match="q must have shape"):
        sim.crba(model, jnp.zeros(18))
    with pytest.raises(ValueError, match="no frame named"):
        sim.frame_placement(model, jnp.zeros(19), "NO_SUCH_FOOT")
    with pytest.raises(ValueError, match="reference"):
        sim.frame_jacobian(model, jnp.zeros(19), "FL_FOOT", reference="body")


# --------------------------------------------------------------------------------------
# Spatial helpers
# --------------------------------------------------------------------------------------


def test_spatial_exp_log_match_pinocchio():
    rng = np.random.default_rng(5)
    twists = rng.normal(size=(6, 6))
    twists[0, 3:] = 0.0
    twists[1, 3:] *= 1e-6
    twists[2, 3:] *= (np.pi - 1e-5) / np.linalg.norm(twists[2, 3:])

    @jax.jit
    @jax.vmap
    def exp_log(twist):
        rotation, translation = spatial.exp6(twist)
        quaternion = spatial.rotation_to_quaternion(rotation)
        return rotation, translation, spatial.log6(rotation, translation), spatial.quaternion_to_rotation(quaternion)

    rotations, translations, logs, rotations_from_quaternions = exp_log(twists)
    assert_close(rotations_from_quaternions, rotations)
    for k in range(len(twists)):
        expected = pin.exp6(pin.Motion(twists[k]))
        assert_close(rotations[k], expected.rotation)
        assert_close(translations[k], expected.translation)
        assert_close(logs[k], pin.log6(expected).vector)
        assert_close(logs[k], twists[k])


_FOREST = """<mujoco><worldbody>
  <body name="pendulum" pos="0 0 1"><joint type="hinge" axis="0 1 0"/><geom type="capsule" size="0.02 0.2" fromto="0 0 0 0 0 -0.4"/></body>
  <body name="box1" pos="1 0 0.5"><freejoint/><geom type="box" size="0.1 0.2 0.05" mass="2"/></body>
  <body name="upper" pos="-1 0 1"><joint type="hinge" axis="1 0 0"/><geom type="capsule" size="0.02 0.15" fromto="0 0 0 0 0 -0.3"/>
    <body name="lower" pos="0 0 -0.3"><joint type="hinge" axis="0 1 0"/><geom type="sphere" size="0.05"/></body></body>
  <body name="box2" pos="0 1 0.5"><freejoint/><geom type="box" size="0.05 0.05 0.3" mass="0.5"/></body>
</worldbody></mujoco>"""


def test_the_mass_matrix_of_several_trees_is_factored_and_solved_block_by_block(tmp_path):
    # A pendulum (1 dof), two free boxes (6 each) and a two-link arm (2): M couples no two
    # trees; the factor and the solves block by block equal the dense ones. One tree: no blocks.
    from rsmooth.sim import _dynamics

    path = tmp_path / "forest.xml"
    path.write_text(_FOREST)
    model = sim.scene(path).model
    blocks = _dynamics._dof_blocks(model)
    assert [(size, starts.tolist()) for size, starts in blocks] == [(1, [0]), (2, [7]), (6, [1, 9])]
    rng = np.random.default_rng(0)
    q = np.asarray(sim.scene(path).initial_state())[: model.nq] + 0.3 * np.r_[rng.normal(size=model.nq)]
    q = jnp.asarray(q)
    kinematics = _dynamics._kinematics(model, q)
    mass = _dynamics._crba(model, kinematics, _dynamics._world_inertias(model, kinematics)) + jnp.diag(jnp.linspace(0.01, 0.1, model.nv))
    dense = np.asarray(mass)
    assert np.all(dense[np.ix_([0], range(1, model.nv))] == 0) and np.all(dense[np.ix_(range(1, 7), range(7, 15))] == 0)
    factor = jax.jit(lambda m: _dynamics.mass_cholesky(model, m))(mass)
    np.testing.assert_allclose(np.asarray(factor), np.linalg.cholesky(dense), rtol=0, atol=1e-12)
    b, B = rng.normal(size=model.nv), rng.normal(size=(model.nv, 5))
    L = np.linalg.cholesky(dense)
    np.testing.assert_allclose(_dynamics.mass_solve_triangular(model, factor, jnp.asarray(B)), np.linalg.solve(L, B), atol=1e-10)
    np.testing.assert_allclose(_dynamics.mass_solve_triangular(model, factor, jnp.asarray(b), trans=True), np.linalg.solve(L.T, b), atol=1e-10)
    np.testing.assert_allclose(_dynamics.mass_cho_solve(model, factor, jnp.asarray(b)), np.linalg.solve(dense, b), atol=1e-10)
    # more columns than any block has rows (a contact Jacobian's, solved by the blocks' inverses),
    # and their derivative, as the dense factor's
    C = jnp.asarray(rng.normal(size=(model.nv, 8)))
    same_tree = np.zeros(mass.shape)
    for size, starts in blocks:
        for start in starts.tolist():
            same_tree[start : start + size, start : start + size] = 1.0
    for trans in (False, True):
        blocked = lambda m: _dynamics.mass_solve_triangular(model, _dynamics.mass_cholesky(model, m), C, trans=trans)  # noqa: B023, E731
        reference = lambda m: jax.scipy.linalg.solve_triangular(jnp.linalg.cholesky(m), C, lower=True, trans=int(trans))  # noqa: B023, E731
        np.testing.assert_allclose(blocked(mass), reference(mass), rtol=0, atol=1e-10)
        direction = rng.normal(size=mass.shape) * same_tree  # M's changes keep its trees apart
        direction = jnp.asarray(direction + direction.T)
        np.testing.assert_allclose(jax.jvp(blocked, (mass,), (direction,))[1], jax.jvp(reference, (mass,), (direction,))[1], rtol=0, atol=1e-9)
    # batched as the step is, and differentiated (the factor's JVP through the blocks)
    batched = jax.vmap(lambda m: _dynamics.mass_cho_solve(model, _dynamics.mass_cholesky(model, m), jnp.asarray(b)))
    np.testing.assert_allclose(batched(jnp.stack([mass, 2 * mass])), np.stack([np.linalg.solve(dense, b), np.linalg.solve(2 * dense, b)]), atol=1e-10)
    tangent = jax.jvp(lambda m: _dynamics.mass_cho_solve(model, _dynamics.mass_cholesky(model, m), jnp.asarray(b)), (mass,), (mass,))[1]
    np.testing.assert_allclose(tangent, -np.linalg.solve(dense, b), atol=1e-9)  # d(M^-1 b)/dM [M] = -M^-1 b
    one = tmp_path / "one_tree.xml"
    one.write_text(_FOREST.split('<body name="box1"')[0] + "</worldbody></mujoco>")
    assert _dynamics._dof_blocks(sim.scene(one).model) is None
