"""Models loaded through MuJoCo (rsmooth.sim._mujoco) against MuJoCo's own answers.

On seeded random states, MuJoCo's mass matrix, bias forces, accelerations and body, site and
geom placements are compared with rsmooth's (``crba``, ``nonlinear_effects``,
``forward_dynamics``, ``forward_kinematics``) after the change of velocity basis of free
joints; Solo-12's URDF loaded by MuJoCo is also compared with ``load_urdf``'s model (loaded by
Pinocchio), and Panda, Go1, Go2 and the Allegro hand of example-robot-data, loaded by
``load_mjcf`` with the options they need, with the same URDFs compiled by MuJoCo itself.
Collada meshes, which MuJoCo cannot decode and load_mjcf reads with trimesh, are compared with
Pinocchio's reading of them. Each model's functions are jitted once and vmapped over the
states.
"""

import pathlib
import re
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rsmooth import sim
from rsmooth.sim._mujoco import GEOM_TYPES, MujocoLoadWarning, MujocoModel, from_mujoco, load_mjcf

mujoco = pytest.importorskip("mujoco")

NUM_STATES = 4
TOLERANCE = 1e-9

DOUBLE_PENDULUM = """
<mujoco model="double_pendulum">
  <compiler angle="radian"/>
  <option timestep="0.005"/>
  <worldbody>
    <body name="upper" pos="0 0 2">
      <joint name="shoulder" axis="0 1 0" damping="0.1"/>
      <geom name="upper_link" type="capsule" fromto="0 0 0 0 0 -1" size="0.05" mass="1"/>
      <body name="lower" pos="0 0 -1">
        <joint name="elbow" axis="0 1 0" limited="true" range="-2 2"/>
        <geom name="lower_link" type="capsule" fromto="0 0 0 0 0 -1" size="0.05" mass="1"/>
        <site name="tip" pos="0 0 -1"/>
      </body>
    </body>
  </worldbody>
  <actuator>
    <motor name="elbow_motor" joint="elbow" gear="2" ctrllimited="true" ctrlrange="-1 1"/>
  </actuator>
</mujoco>
"""

CART_POLE = """
<mujoco model="cart_pole">
  <compiler angle="radian"/>
  <worldbody>
    <geom name="floor" type="plane" size="0 0 1" friction="0.7"/>
    <body name="cart" pos="0 0 0.5">
      <joint name="slider" type="slide" axis="1 0 0" limited="true" range="-2 2" armature="0.1" damping="0.5"/>
      <geom name="cart" type="box" size="0.2 0.1 0.05" mass="1"/>
      <body name="pole">
        <joint name="hinge" axis="0 1 0" ref="0.3"/>
        <geom name="pole" type="capsule" fromto="0 0 0 0 0 1" size="0.03" mass="0.2" contype="2" conaffinity="4"/>
      </body>
    </body>
  </worldbody>
  <actuator>
    <motor name="push" joint="slider" gear="10" forcelimited="true" forcerange="-3 3"/>
  </actuator>
  <contact>
    <exclude body1="cart" body2="pole"/>
    <pair geom1="floor" geom2="pole"/>
  </contact>
</mujoco>
"""

FLOATING_BOX = """
<mujoco model="floating_box">
  <compiler angle="radian"/>
  <option gravity="0.5 -0.3 -9.81" timestep="0.001"/>
  <worldbody>
    <body name="box" pos="0 0 1">
      <freejoint name="root"/>
      <geom name="box" type="box" size="0.3 0.2 0.1" mass="3" pos="0.05 0.02 -0.01" euler="0.1 0.2 0.3"/>
      <site name="corner" pos="0.3 0.2 0.1"/>
    </body>
  </worldbody>
</mujoco>
"""

# A free base; a body with three joints (two hinges about oblique axes and a slide, each
# anchored off the body's origin, one with a reference position); a welded child with a
# rotated inertia; a hinge below the welded child; armature, damping and a motor.
TREE = """
<mujoco model="tree">
  <compiler angle="radian"/>
  <option gravity="0.3 -0.2 -9.81"/>
  <worldbody>
    <geom name="ground" type="plane" size="5 5 0.1"/>
    <body name="base" pos="0.1 0.2 1" quat="0.9 0.1 0.2 0.3">
      <joint name="root" type="free" damping="0.1"/>
      <geom name="base" type="box" size="0.2 0.1 0.05" mass="2"/>
      <site name="front" pos="0.2 0 0" euler="0.3 0 0.1"/>
      <body name="arm" pos="0.2 0.1 0" euler="0.1 0.2 0.3">
        <joint name="h1" axis="0 1 0" pos="0.05 0 0.02" armature="0.01" damping="0.3" ref="0.2"/>
        <joint name="h2" axis="1 0 1" pos="0 0.03 0" limited="true" range="-1 1.5"/>
        <joint name="s1" type="slide" axis="0 0 1" pos="0.1 0.1 0.1"/>
        <geom name="arm" type="capsule" fromto="0 0 0 0.3 0 0" size="0.03" mass="0.5"/>
        <body name="welded" pos="0.3 0 0" euler="0 0.5 0">
          <inertial pos="0.01 0.02 0.03" quat="0.8 0.2 0.3 0.1" mass="0.7" diaginertia="0.01 0.02 0.025"/>
          <geom name="knob" type="sphere" size="0.05" contype="0" conaffinity="0"/>
          <site name="knob"/>
          <body name="child" pos="0.1 0 0">
            <joint name="h3" axis="0 0 1" pos="0.02 0.01 0"/>
            <geom name="child" type="cylinder" size="0.02 0.1" mass="0.2"/>
            <geom name="child_tip" type="ellipsoid" size="0.02 0.03 0.04" pos="0 0 0.1" mass="0.05"/>
          </body>
        </body>
      </body>
    </body>
  </worldbody>
  <actuator>
    <motor name="h2_motor" joint="h2" gear="3" ctrllimited="true" ctrlrange="-0.5 2"/>
    <motor name="h3_motor" joint="h3" gear="0.5"/>
  </actuator>
</mujoco>
"""

# Ball joints: a fixed two-link chain (anchors off the bodies' origins, armature and damping),
# and a ball-jointed head on a free base.
BALLS = """
<mujoco model="balls">
  <compiler angle="radian"/>
  <option gravity="0.2 0.1 -9.81"/>
  <worldbody>
    <body name="upper" pos="0 0 1" quat="0.9 0.3 0.1 0.2">
      <joint name="shoulder" type="ball" pos="0 0 0.05" armature="0.02" damping="0.1"/>
      <geom name="upper" type="capsule" fromto="0 0 0 0.3 0.1 0" size="0.03" mass="0.8"/>
      <body name="lower" pos="0.3 0.1 0" euler="0.2 0.1 0">
        <joint name="elbow" type="ball" pos="0.02 0 0"/>
        <geom name="lower" type="box" size="0.1 0.03 0.02" pos="0.1 0 0" mass="0.4"/>
      </body>
    </body>
    <body name="torso" pos="1 0 1">
      <freejoint name="root"/>
      <geom name="torso" type="box" size="0.2 0.1 0.3" mass="5"/>
      <body name="head" pos="0 0 0.35">
        <joint name="neck" type="ball" pos="0 0 -0.05"/>
        <geom name="head" type="sphere" size="0.08" pos="0.02 0 0.05" mass="1"/>
      </body>
    </body>
  </worldbody>
</mujoco>
"""

MODELS = {"double_pendulum": DOUBLE_PENDULUM, "cart_pole": CART_POLE, "floating_box": FLOATING_BOX, "tree": TREE, "balls": BALLS}


def assert_close(actual, expected, tolerance=TOLERANCE):
    """Agreement to ``tolerance``, relative to the largest entry of ``expected`` (at least 1)."""
    expected = np.asarray(expected)
    scale = max(1.0, float(np.abs(expected).max(initial=0.0)))
    np.testing.assert_allclose(np.asarray(actual), expected, rtol=tolerance, atol=tolerance * scale)


def solo12_mujoco():
    """Solo-12's URDF compiled by MuJoCo (mesh paths rewritten, static bodies kept), with a
    free joint named as Pinocchio's."""
    root = sim.example_robot_data_root()
    text = sim.solo12_urdf_path().read_text().replace("package://example-robot-data/", f"{root}/")
    start = text.index(">", text.index("<robot")) + 1
    options = '<mujoco><compiler balanceinertia="true" discardvisual="false" fusestatic="false"/></mujoco>'
    spec = mujoco.MjSpec.from_string(text[:start] + options + text[start:])
    spec.worldbody.first_body().add_freejoint(name="root_joint")
    return spec.compile()


def random_states(m, seed):
    """MuJoCo states: hinges in [-pi, pi], slides in [-1, 1] m, random base poses and ball
    joint rotations, normal
    velocities and controls (large enough that some controls are clipped)."""
    rng = np.random.default_rng(seed)
    qpos = np.zeros((NUM_STATES, m.nq))
    for j in range(m.njnt):
        adr = m.jnt_qposadr[j]
        if m.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE:
            quaternion = rng.normal(size=(NUM_STATES, 4))
            qpos[:, adr : adr + 3] = rng.uniform(-1, 1, (NUM_STATES, 3))
            qpos[:, adr + 3 : adr + 7] = quaternion / np.linalg.norm(quaternion, axis=1, keepdims=True)
        elif m.jnt_type[j] == mujoco.mjtJoint.mjJNT_BALL:
            quaternion = rng.normal(size=(NUM_STATES, 4))
            qpos[:, adr : adr + 4] = quaternion / np.linalg.norm(quaternion, axis=1, keepdims=True)
        elif m.jnt_type[j] == mujoco.mjtJoint.mjJNT_SLIDE:
            qpos[:, adr] = rng.uniform(-1, 1, NUM_STATES)
        else:
            qpos[:, adr] = rng.uniform(-np.pi, np.pi, NUM_STATES)
    return qpos, rng.normal(size=(NUM_STATES, m.nv)), 2.0 * rng.normal(size=(NUM_STATES, m.nu))


def mujoco_answers(m, qpos, qvel, ctrl):
    """MuJoCo's quantities at each state, constraints (contacts, limits) disabled."""
    m.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONSTRAINT
    d = mujoco.MjData(m)
    names = ("M", "bias", "qacc", "actuator", "T", "Tdot_v", "xpos", "xmat", "site_xpos", "site_xmat", "geom_xpos", "geom_xmat")
    answers = {name: [] for name in names}
    for state in zip(qpos, qvel, ctrl):
        d.qpos[:], d.qvel[:], d.ctrl[:] = state
        mujoco.mj_forward(m, d)
        mass = np.zeros((m.nv, m.nv))
        mujoco.mj_fullM(m, d, mass)
        # qvel = T v: on a free joint's block T = diag(R, I), R the body's rotation in MuJoCo's
        # own kinematics; dT/dt v = [omega_world x qvel_linear, 0].
        change, transport = np.eye(m.nv), np.zeros(m.nv)
        for j in np.flatnonzero(m.jnt_type == mujoco.mjtJoint.mjJNT_FREE):
            adr = m.jnt_dofadr[j]
            rotation = d.xmat[m.jnt_bodyid[j]].reshape(3, 3)
            change[adr : adr + 3, adr : adr + 3] = rotation
            transport[adr : adr + 3] = np.cross(rotation @ d.qvel[adr + 3 : adr + 6], d.qvel[adr : adr + 3])
        for name, value in (("M", mass), ("bias", d.qfrc_bias), ("qacc", d.qacc), ("actuator", d.qfrc_actuator), ("T", change),
                            ("Tdot_v", transport), ("xpos", d.xpos), ("xmat", d.xmat), ("site_xpos", d.site_xpos),
                            ("site_xmat", d.site_xmat), ("geom_xpos", d.geom_xpos), ("geom_xmat", d.geom_xmat)):
            answers[name].append(np.array(value))
    return {name: np.stack(values) for name, values in answers.items()}


@jax.jit
def rsmooth_answers(loaded: MujocoModel, qpos, qvel, ctrl):
    def one(qpos, qvel, ctrl):
        q, v = loaded.qpos_to_q(qpos), loaded.qvel_to_v(qpos, qvel)
        tau = loaded.ctrl_to_tau(ctrl) - loaded.damping * v
        rotations, translations = sim.forward_kinematics(loaded.model, q)
        return dict(
            q=q,
            v=v,
            M=sim.crba(loaded.model, q),
            bias=sim.nonlinear_effects(loaded.model, q, v),
            a=sim.forward_dynamics(loaded.model, q, v, tau),
            actuator=loaded.ctrl_to_tau(ctrl),
            rotations=rotations,
            translations=translations,
        )

    return jax.vmap(one)(qpos, qvel, ctrl)


def place(rotations, translations, joints, local_rotations, local_translations):
    """World placements ``oMi[joint] * iMx`` of frames or geoms, batched over states."""
    joints = np.asarray(joints, dtype=np.int64)
    rotation = np.einsum("sxij,xjk->sxik", rotations[:, joints], local_rotations)
    translation = np.einsum("sxij,xj->sxi", rotations[:, joints], local_translations) + translations[:, joints]
    return rotation, translation


def check_against_mujoco(m, loaded, seed):
    qpos, qvel, ctrl = random_states(m, seed)
    expected = mujoco_answers(m, qpos, qvel, ctrl)
    actual = jax.tree_util.tree_map(np.asarray, rsmooth_answers(loaded, qpos, qvel, ctrl))
    change = expected["T"]
    transpose = np.swapaxes(change, 1, 2)
    assert_close(np.einsum("sij,sj->si", change, actual["v"]), qvel)
    assert_close(actual["M"], transpose @ expected["M"] @ change)
    # rsmooth's velocity basis turns with the body: its bias has the extra M (dT/dt) v.
    bias = expected["bias"] + np.einsum("sij,sj->si", expected["M"], expected["Tdot_v"])
    assert_close(actual["bias"], np.einsum("sij,sj->si", transpose, bias))
    assert_close(actual["actuator"], np.einsum("sij,sj->si", transpose, expected["actuator"]))
    assert_close(actual["a"], jax.vmap(loaded.qacc_to_a)(qpos, qvel, expected["qacc"]), tolerance=1e-8)
    model = loaded.model
    rotations, translations = actual["rotations"], actual["translations"]
    frames = [model.frame_id(name) for name in loaded.body_names]
    local_rotations = np.asarray(model.frame_placement_rotation)
    local_translations = np.asarray(model.frame_placement_translation)
    parents = np.asarray(model.frame_parents)
    rotation, translation = place(rotations, translations, parents[frames], local_rotations[frames], local_translations[frames])
    assert_close(translation, expected["xpos"])
    assert_close(rotation.reshape(NUM_STATES, -1, 9), expected["xmat"])
    sites = np.arange(len(frames) + m.njnt, model.nframes)
    assert [model.frame_names[f] for f in sites] == [m.site(s).name for s in range(m.nsite)]
    rotation, translation = place(rotations, translations, parents[sites], local_rotations[sites], local_translations[sites])
    assert_close(translation, expected["site_xpos"])
    assert_close(rotation.reshape(NUM_STATES, -1, 9), expected["site_xmat"])
    geom_rotations, geom_translations = np.asarray(loaded.geom_rotation), np.asarray(loaded.geom_translation)
    rotation, translation = place(rotations, translations, loaded.geom_joints, geom_rotations, geom_translations)
    assert_close(translation, expected["geom_xpos"])
    assert_close(rotation.reshape(NUM_STATES, -1, 9), expected["geom_xmat"])
    return actual


@pytest.mark.parametrize("name", sorted(MODELS))
def test_matches_mujoco(name):
    m = mujoco.MjModel.from_xml_string(MODELS[name])
    if name == "tree":
        # Armature on a free joint's angular axes (MJCF sets a joint's armature on all its dofs).
        m.dof_armature[3:6] = [0.01, 0.02, 0.03]
    loaded = from_mujoco(m)
    check_against_mujoco(m, loaded, seed=sorted(MODELS).index(name))
    # Round trips of the state maps.
    qpos, qvel, _ = random_states(m, seed=10)
    q = loaded.qpos_to_q(qpos)
    assert_close(loaded.q_to_qpos(q), qpos, tolerance=1e-14)
    v = loaded.qvel_to_v(qpos, qvel)
    assert_close(loaded.v_to_qvel(q, v), qvel, tolerance=1e-14)
    assert_close(loaded.qacc_to_a(qpos, qvel, loaded.a_to_qacc(q, v, qvel)), qvel, tolerance=1e-14)


def test_fields_of_the_cart_pole():
    loaded = load_mjcf(CART_POLE)
    model = loaded.model
    assert model.joint_names == ("universe", "slider", "hinge")
    assert model.joint_types == ("universe", "prismatic", "revolute")
    assert loaded.body_names == ("world", "cart", "pole") and loaded.body_joints == (0, 1, 2)
    assert model.frame_id("cart") == 1 and model.frame_id("hinge") == 4
    assert loaded.timestep == 0.002
    np.testing.assert_array_equal(loaded.damping, [0.5, 0.0])
    np.testing.assert_array_equal(model.armature, [0.1, 0.0])
    # The hinge's reference position is subtracted from qpos (and from nothing else).
    np.testing.assert_array_equal(loaded.qpos0, [0.0, 0.3])
    np.testing.assert_array_equal(model.lower_position_limit, [-2.0, -np.inf])
    np.testing.assert_array_equal(model.upper_position_limit, [2.0, np.inf])
    # The motor's force range (3 N) through its gear (10) bounds the slider's force.
    np.testing.assert_array_equal(model.effort_limit, [30.0, np.inf])
    assert loaded.actuator_names == ("push",) and loaded.actuator_dofs == (0,)
    assert loaded.geom_types == ("plane", "box", "capsule")
    assert loaded.geom_names == ("floor", "cart", "pole") and loaded.geom_joints == (0, 1, 2)
    np.testing.assert_array_equal(loaded.geom_friction, [0.7, 1.0, 1.0])
    assert loaded.geom_contype == (1, 1, 2) and loaded.geom_conaffinity == (1, 1, 4)
    assert loaded.contact_pairs == ((0, 2),)
    assert loaded.excluded_body_pairs == ((1, 2),)
    assert all(vertices is None for vertices in loaded.geom_vertices)


def test_welded_bodies_are_merged():
    """The welded child's inertia joins its parent's body (the last of the three joints of
    'arm'); the intermediate bodies of the chain are massless; total mass is kept."""
    m = mujoco.MjModel.from_xml_string(TREE)
    loaded = from_mujoco(m)
    model = loaded.model
    assert model.joint_names == ("universe", "root", "h1", "h2", "s1", "h3")
    assert model.parents == (0, 0, 1, 2, 3, 4)
    mass = np.asarray(model.body_mass)
    np.testing.assert_allclose(mass[[2, 3]], 0.0)
    np.testing.assert_allclose(mass[4], m.body_mass[2] + m.body_mass[3])
    np.testing.assert_allclose(mass.sum(), m.body_mass.sum())
    assert loaded.body_joints == (0, 1, 4, 4, 5)
    np.testing.assert_array_equal(model.effort_limit, [np.inf] * 7 + [2.0 * 3.0, np.inf, np.inf])


def test_solo12_matches_mujoco_and_pinocchio():
    pytest.importorskip("pinocchio")
    m = solo12_mujoco()
    # The URDF read by load_mjcf itself (package:// URIs resolved, the base kept and given a
    # free joint) against MuJoCo's answers on the model compiled by hand above.
    loaded = load_mjcf(sim.solo12_urdf_path(), package_dirs=[sim.example_robot_data_root().parent], floating_base=True)
    assert loaded.body_names == tuple(m.body(i).name for i in range(m.nbody))
    actual = check_against_mujoco(m, loaded, seed=7)
    assert loaded.geom_types.count("mesh") == m.ngeom
    vertices = loaded.geom_vertices[0]
    assert vertices.shape == (m.mesh_vertnum[m.geom_dataid[0]], 3)
    assert int(np.max(np.asarray(loaded.geom_faces[0]))) < vertices.shape[0]
    # The same robot loaded by Pinocchio: the same dynamics at the same (rsmooth) states.
    reference = sim.load_urdf(sim.solo12_urdf_path())
    joints = [loaded.model.joint_id(name) for name in reference.joint_names[1:]]
    assert (loaded.model.nq, loaded.model.nv) == (reference.nq, reference.nv)

    def indices(offsets, size):
        return np.concatenate([np.arange(offsets[j], offsets[j] + size(j)) for j in joints])

    # Pinocchio's joint order may differ from MuJoCo's: reorder MuJoCo's vectors by name.
    q_order = indices(loaded.model.idx_q, loaded.model.joint_nq)
    v_order = indices(loaded.model.idx_v, loaded.model.joint_nv)
    configurations, velocities = np.asarray(actual["q"])[:, q_order], np.asarray(actual["v"])[:, v_order]

    @jax.jit
    @jax.vmap
    def pinocchio_side(q, v):
        placements = [sim.frame_placement(reference, q, name) for name in loaded.body_names[1:]]
        return sim.crba(reference, q), sim.nonlinear_effects(reference, q, v), placements

    mass, bias, placements = pinocchio_side(configurations, velocities)
    assert_close(mass, actual["M"][:, v_order][:, :, v_order])
    assert_close(bias, actual["bias"][:, v_order])
    for b, (rotation, translation) in enumerate(placements, start=1):
        joint = loaded.body_joints[b]
        frame = loaded.model.frame_id(loaded.body_names[b])
        rotations, local_translation = actual["rotations"][:, joint], np.asarray(loaded.model.frame_placement_translation[frame])
        expected_rotation = rotations @ np.asarray(loaded.model.frame_placement_rotation[frame])
        expected_translation = np.einsum("sij,j->si", rotations, local_translation) + actual["translations"][:, joint]
        assert_close(rotation, expected_rotation)
        assert_close(translation, expected_translation)


def test_mujoco_testdata_model_is_rejected_by_name():
    path = pathlib.Path(mujoco.__file__).parent / "testdata" / "model.xml"
    if not path.is_file():
        pytest.skip("the mujoco package has no testdata/model.xml")
    with pytest.raises(ValueError, match="does not (support|model)"):
        load_mjcf(path)


def wrap(body, extra=""):
    return f"<mujoco><compiler angle='radian'/><worldbody>{body}</worldbody>{extra}</mujoco>"


HINGE_BODY = "<body name='b'><joint name='j'/><geom name='g' size='0.1'/><site name='s'/></body>"
UNSUPPORTED = {
    "ball_limit": (wrap("<body><joint name='shoulder' type='ball' range='0 4'/><geom size='0.1'/></body>"), "ball joint 'shoulder' has the range"),
    "equality": (
        wrap("<flexcomp name='f' type='grid' count='2 2 1' spacing='0.1 0.1 0.1' dim='2'><edge equality='true'/></flexcomp>"),
        "1 equality constraints other than joint couplings, connections and welds",
    ),
    "spring": (wrap("<body><joint name='j' type='free' stiffness='3'/><geom size='0.1'/></body>"), "free joint 'j' has a spring"),
    "free_frictionloss": (
        wrap("<body><joint name='j' type='free' frictionloss='1'/><geom size='0.1'/></body>"),
        "free joint 'j' has frictionloss .* on its linear axes",
    ),
    "user_bias": (
        wrap(HINGE_BODY, "<actuator><general name='p' joint='j' biastype='user'/></actuator>"),
        "actuator 'p' is not supported: its bias type is user",
    ),
    "site_actuator": (
        wrap(HINGE_BODY, "<actuator><general name='a' site='s' gear='0 0 0 0 0 1'/></actuator>"),
        "actuator 'a' .*transmission is site",
    ),
    "user_dynamics_actuator": (
        wrap(HINGE_BODY, "<actuator><general name='a' joint='j' dyntype='user'/></actuator>"),
        "actuator 'a' .*activation dynamics user",
    ),
    "free_motor": (
        wrap("<body><freejoint name='f'/><geom size='0.1'/></body>", "<actuator><motor name='a' joint='f' gear='1 0 0 0 0 0'/></actuator>"),
        "actuator 'a' .*not a hinge or slide",
    ),
    "gravcomp": (wrap("<body name='b' gravcomp='1'><joint name='j' actuatorgravcomp='true'/><geom size='0.1'/></body>"),
                 "joint 'j' takes its gravity compensation through its actuators"),
    "ellipsoid_fluid": (
        "<mujoco><option density='1.2'/><worldbody><body><joint/><geom name='g' size='0.1' fluidshape='ellipsoid'/></body></worldbody></mujoco>",
        "geom 'g' takes the ellipsoid fluid model",
    ),
}


@pytest.mark.parametrize("name", sorted(UNSUPPORTED))
def test_unsupported_features_are_rejected_by_name(name):
    xml, message = UNSUPPORTED[name]
    with pytest.raises(ValueError, match=message):
        load_mjcf(xml)


def test_free_joint_armature_and_damping():
    """Armature on a free joint's angular axes and isotropic damping are kept; linear armature
    (MuJoCo's multiplies the world-axes acceleration) and anisotropic damping are refused."""
    m = mujoco.MjModel.from_xml_string(wrap("<body name='b'><freejoint name='f'/><geom size='0.1'/></body>"))
    m.dof_armature[3:] = [0.1, 0.2, 0.3]
    m.dof_damping[:] = [0.5, 0.5, 0.5, 0.1, 0.2, 0.3]
    loaded = from_mujoco(m)
    np.testing.assert_array_equal(loaded.model.armature, [0, 0, 0, 0.1, 0.2, 0.3])
    np.testing.assert_array_equal(loaded.damping, [0.5, 0.5, 0.5, 0.1, 0.2, 0.3])
    m.dof_damping[0] = 0.4
    with pytest.raises(ValueError, match="free joint 'f' has damping"):
        from_mujoco(m)
    with pytest.raises(ValueError, match="free joint 'f' has armature"):
        load_mjcf(wrap("<body><joint name='f' type='free' armature='0.1'/><geom size='0.1'/></body>"))


def test_an_hfield_is_kept_with_its_heights():
    loaded = load_mjcf(wrap(
        "<geom name='terrain' type='hfield' hfield='h'/><geom name='ball' size='0.1'/>",
        "<asset><hfield name='h' nrow='2' ncol='3' size='1 2 0.5 0.1' elevation='0 1 2 4 3 2'/></asset>",
    ))
    assert loaded.geom_types == ("hfield", "sphere") and "hfield" in GEOM_TYPES
    field = loaded.geom_height_fields[0]
    # MuJoCo scales the elevation to [0, 1] (times size[2] = 0.5) and lists the file's rows from +y down
    np.testing.assert_allclose(field.heights, [[0.5, 0.375, 0.25], [0.0, 0.125, 0.25]])
    np.testing.assert_allclose(field.half_size, [1.0, 2.0])
    assert float(field.base) == 0.1 and loaded.geom_height_fields[1] is None


def test_bad_sources(tmp_path):
    with pytest.raises(FileNotFoundError, match="missing.xml"):
        load_mjcf(tmp_path / "missing.xml")
    broken = tmp_path / "broken.xml"
    broken.write_text("<mujoco><worldbody><body></worldbody></mujoco>")
    with pytest.raises(ValueError, match="MuJoCo could not load .*broken.xml.*XML"):
        load_mjcf(broken)
    with_mesh = tmp_path / "with_mesh.xml"
    with_mesh.write_text(
        "<mujoco><asset><mesh name='m' file='absent.stl'/></asset><worldbody><geom type='mesh' mesh='m'/></worldbody></mujoco>"
    )
    with pytest.raises(ValueError, match="with_mesh.xml.*absent.stl"):
        load_mjcf(with_mesh)
    with pytest.raises(ValueError, match="MuJoCo could not load the XML text"):
        load_mjcf("<mujoco><worldbody><geom type='sphere'/></worldbody><bogus/></mujoco>")
    with pytest.raises(ValueError, match="source must be"):
        load_mjcf(3)
    with pytest.raises(ValueError, match="mj_model must be"):
        from_mujoco("<mujoco/>")
    urdf = tmp_path / "robot.urdf"
    urdf.write_text("""<robot name="r"><link name="base"><visual><geometry>
      <mesh filename="package://missing_description/meshes/base.stl"/></geometry></visual></link></robot>""")
    with pytest.raises(FileNotFoundError, match="package://missing_description/meshes/base.stl.*package_dirs"):
        load_mjcf(urdf, package_dirs=[tmp_path])
    # package:/// (an empty authority, as Talos's URDFs write it) names the package after it;
    # the package is found in the folders above the file by default
    (tmp_path / "pkg" / "meshes").mkdir(parents=True)
    (tmp_path / "pkg" / "meshes" / "tetra.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n")
    (tmp_path / "pkg" / "robot.urdf").write_text("""<robot name="r"><link name="base"><visual><geometry>
      <mesh filename="package:///pkg/meshes/tetra.obj"/></geometry></visual></link></robot>""")
    assert load_mjcf(tmp_path / "pkg" / "robot.urdf").geom_types == ("mesh",)
    with pytest.raises(ValueError, match="floating_base.*'arm'.*already has a joint"):
        load_mjcf("<mujoco><worldbody><body name='arm'><joint/><geom size='.1'/></body></worldbody></mujoco>",
                  floating_base=True)


def test_state_maps_check_shapes():
    loaded = load_mjcf(FLOATING_BOX)
    with pytest.raises(ValueError, match="qpos must have shape"):
        loaded.qpos_to_q(jnp.zeros(6))
    with pytest.raises(ValueError, match="ctrl must have shape"):
        loaded.ctrl_to_tau(jnp.zeros(1))


# Spheres around the origin, all overlapping one another and the floor: MuJoCo then reports a
# contact for every geom pair its filters keep.
FILTERS = """
<mujoco>
  <worldbody>
    <geom name="floor" type="plane" size="5 5 0.1"/>
    <geom name="floor2" type="plane" size="5 5 0.1" pos="0 0 0.01"/>
    <geom name="post" size="0.5" pos="0.01 0 0"/>
    <body name="a">
      <joint axis="0 1 0"/>
      <geom name="a" size="0.5" pos="0 0.01 0"/>
      <body name="b">
        <joint axis="0 1 0"/>
        <geom name="b" size="0.5" pos="0 0 0.01"/>
      </body>
      <body name="c" pos="0.01 0.01 0">
        <geom name="c" size="0.5"/>
        <body name="d">
          <joint axis="1 0 0"/>
          <geom name="d" size="0.5" pos="0 0 -0.01"/>
        </body>
      </body>
    </body>
    <body name="e" pos="-0.01 0 0">
      <freejoint/>
      <geom name="e" size="0.5" contype="2" conaffinity="2"/>
      <geom name="e2" size="0.5" pos="0 -0.01 0"/>
    </body>
    <body name="f" pos="0 -0.02 0">
      <freejoint/>
      <geom name="f" size="0.5" contype="4" conaffinity="1"/>
    </body>
  </worldbody>
  <contact>
    <pair geom1="e" geom2="a"/>
    <pair geom1="e2" geom2="b"/>
    <exclude body1="b" body2="f"/>
  </contact>
</mujoco>
"""


@pytest.mark.parametrize("filter_parent", [True, False])
def test_collision_pairs_match_mujoco(filter_parent):
    m = mujoco.MjModel.from_xml_string(FILTERS)
    if not filter_parent:
        m.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_FILTERPARENT
    loaded = from_mujoco(m)
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    reported = {frozenset(int(g) for g in d.contact.geom[i]) for i in range(d.ncon)}
    candidates = [frozenset(pair) for pair in loaded.collision_pairs]
    assert len(set(candidates)) == len(candidates)
    assert set(candidates) == reported
    assert loaded.collision_pairs[:2] == loaded.contact_pairs
    names = {frozenset(loaded.geom_names[g] for g in pair) for pair in loaded.collision_pairs}
    # Welded together (a, c), parent and child (a, b; c, d), excluded (b, f), incompatible
    # masks (e, post), two planes: never tested.
    for kept_apart in (("a", "c"), ("b", "f"), ("e", "post"), ("floor", "floor2"), ("floor", "post")):
        assert frozenset(kept_apart) not in names
    assert (frozenset(("a", "b")) in names) == (not filter_parent)


def test_urdf_file_through_mujoco_matches_load_urdf(tmp_path):
    pytest.importorskip("pinocchio")
    urdf = tmp_path / "arm.urdf"
    urdf.write_text("""<robot name="arm">
      <link name="base"/>
      <link name="upper"><inertial><origin xyz="0.1 0 -0.3" rpy="0.1 0.2 0.3"/><mass value="1.5"/>
        <inertia ixx="0.02" ixy="0.001" ixz="0" iyy="0.025" iyz="0.002" izz="0.015"/></inertial></link>
      <link name="lower"><inertial><origin xyz="0 0.05 -0.2"/><mass value="0.5"/>
        <inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.002"/></inertial></link>
      <joint name="shoulder" type="revolute"><parent link="base"/><child link="upper"/>
        <origin xyz="0 0 1" rpy="0.2 0 0"/><axis xyz="0 1 0"/><limit effort="5" lower="-2" upper="2" velocity="3"/></joint>
      <joint name="elbow" type="revolute"><parent link="upper"/><child link="lower"/>
        <origin xyz="0.1 0 -0.6"/><axis xyz="1 0 0"/><limit effort="5" lower="-2" upper="2" velocity="3"/></joint>
    </robot>""")
    loaded = load_mjcf(urdf)
    reference = sim.load_urdf(urdf, floating_base=False)
    assert loaded.model.joint_names == reference.joint_names
    np.testing.assert_allclose(loaded.model.lower_position_limit, reference.lower_position_limit)
    for q, v in (([0.3, -1.2], [0.5, 2.0]), ([-2.0, 0.7], [-1.0, 0.1])):
        q, v = jnp.array(q), jnp.array(v)
        assert_close(sim.crba(loaded.model, q), sim.crba(reference, q))
        assert_close(sim.nonlinear_effects(loaded.model, q, v), sim.nonlinear_effects(reference, q, v))


# Robots of example-robot-data: the URDF (under robots/), whether it has a floating base, the
# load_mjcf options it needs, the warnings they give, and the compiler attributes of MuJoCo's
# own reading that match those options. Panda's finger joint mimics the other; Go1's base link
# has an inertia that is not positive definite (every entry 1e-6) and its joints, as the
# Allegro hand's, have dry friction. visuals=False compares the colliding geoms alone with
# MuJoCo's own reading, which discards the visual ones.
ROBOTS = {
    "panda": (
        "panda_description/urdf/panda.urdf",
        False,
        dict(drop_mimic=True, visuals=False),
        ("'panda_finger_joint2' to 'panda_finger_joint1'",),
        "",
    ),
    "go1": (
        "go1_description/urdf/go1.urdf",
        True,
        dict(visuals=False, boundinertia=1e-9, drop_frictionloss=True),
        ("frictionloss.*'FR_hip_joint' \\(0.2\\)", "boundinertia=1e-09 raised .*'base'"),
        'boundinertia="1e-9"',
    ),
    "go2": ("go2_description/urdf/go2.urdf", True, dict(visuals=False), (), ""),
    "allegro": ("allegro_hand_description/urdf/allegro_right_hand.urdf", False, dict(visuals=False), (), ""),
}


def robot_mujoco(path: pathlib.Path, floating_base: bool, attributes: str):
    """A URDF of example-robot-data compiled by MuJoCo itself: mesh paths rewritten, static
    bodies kept, visual geoms discarded by its URDF reader, free joint named as Pinocchio's."""
    root = sim.example_robot_data_root()
    text = path.read_text().replace("package://example-robot-data/", f"{root}/")
    start = text.index(">", text.index("<robot")) + 1
    options = (f'<mujoco><compiler balanceinertia="true" discardvisual="true" fusestatic="false" meshdir="{path.parent}" '
               f'{attributes}/></mujoco>')
    spec = mujoco.MjSpec.from_string(text[:start] + options + text[start:])
    if floating_base:
        spec.worldbody.first_body().add_freejoint(name="root_joint")
    return spec.compile()


@pytest.mark.parametrize("name", sorted(ROBOTS))
def test_example_robots_match_mujoco(name):
    relative, floating_base, options, messages, attributes = ROBOTS[name]
    root = sim.example_robot_data_root()
    path = root / "robots" / relative
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        loaded = load_mjcf(path, floating_base=floating_base, **options)  # package_dirs: the folders above
    said = [str(w.message) for w in caught if issubclass(w.category, MujocoLoadWarning)]
    assert len(said) == len(messages) == len(caught)
    for message in messages:
        assert any(re.search(message, text) for text in said), (message, said)
    m = robot_mujoco(path, floating_base, attributes)
    # The same bodies and colliding geoms as MuJoCo's own reading without visuals.
    assert loaded.body_names == tuple(m.body(b).name for b in range(m.nbody))
    assert loaded.ngeom == m.ngeom and all(loaded.geom_contype)
    check_against_mujoco(m, loaded, seed=sorted(ROBOTS).index(name))
    # Dry joint friction as MuJoCo reads it (Allegro's), or dropped on request (Go1's).
    dropped = options.get("drop_frictionloss", False)
    np.testing.assert_array_equal(loaded.frictionloss, 0.0 if dropped else m.dof_frictionloss)
    assert dropped or name != "allegro" or np.all(m.dof_frictionloss[:16] > 0)


def test_example_robots_without_their_options_say_which_to_pass():
    root = sim.example_robot_data_root()
    robots = root / "robots"
    panda = load_mjcf(robots / ROBOTS["panda"][0], package_dirs=[root.parent], visuals=False)  # its <mimic> kept
    assert [panda.model.joint_names[j] for j in panda.joint_couplings.joints] == ["panda_finger_joint2"]
    inertia = "(?s)inertia must have positive eigenvalues.*body 'base'.*not positive definite.*boundinertia"
    with pytest.raises(ValueError, match=inertia):
        load_mjcf(robots / ROBOTS["go1"][0], package_dirs=[root.parent], visuals=False, floating_base=True)
    with pytest.warns(MujocoLoadWarning, match="boundinertia"):  # its dry friction kept
        go1 = load_mjcf(robots / ROBOTS["go1"][0], package_dirs=[root.parent], visuals=False, boundinertia=1e-9)
    hip = go1.model.idx_v[go1.model.joint_id("FR_hip_joint")]
    assert float(go1.frictionloss[hip]) == 0.2


def mesh_bounds_by_body(loaded: MujocoModel, geoms) -> dict[str, np.ndarray]:
    """The world bounding box ``[low, high]`` of the vertices of the given mesh geoms, per body,
    at ``q = 0``."""
    rotations, translations = map(np.asarray, sim.forward_kinematics(loaded.model, jnp.zeros(loaded.model.nq)))
    bounds = {}
    for g in geoms:
        joint, body = loaded.geom_joints[g], loaded.body_names[loaded.geom_bodies[g]]
        rotation = rotations[joint] @ np.asarray(loaded.geom_rotation[g])
        translation = rotations[joint] @ np.asarray(loaded.geom_translation[g]) + translations[joint]
        world = np.asarray(loaded.geom_vertices[g]) @ rotation.T + translation
        low, high = bounds.get(body, (np.full(3, np.inf), np.full(3, -np.inf)))
        bounds[body] = np.stack([np.minimum(low, world.min(0)), np.maximum(high, world.max(0))])
    return bounds


def test_collada_meshes_are_read_as_pinocchio_reads_them():
    pin = pytest.importorskip("pinocchio")
    pytest.importorskip("collada")
    root = sim.example_robot_data_root()
    # Kinova's collision meshes are all Collada files (MuJoCo has no decoder for them).
    path = root / "robots" / "kinova_description" / "robots" / "kinova.urdf"
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        loaded = load_mjcf(path)
    colliding = [g for g in range(loaded.ngeom) if loaded.geom_contype[g] and loaded.geom_types[g] == "mesh"]
    actual = mesh_bounds_by_body(loaded, colliding)
    model = pin.buildModelFromUrdf(str(path))
    geometry = pin.buildGeomFromUrdf(model, str(path), pin.GeometryType.COLLISION, package_dirs=[str(root.parent)])
    data, placements = model.createData(), pin.GeometryData(geometry)
    pin.updateGeometryPlacements(model, data, geometry, placements, pin.neutral(model))
    expected = {}
    for index, shape in enumerate(geometry.geometryObjects):
        assert shape.meshPath.endswith(".dae")
        placement = placements.oMg[index]
        world = np.asarray(shape.geometry.vertices()) @ placement.rotation.T + placement.translation
        body = model.frames[shape.parentFrame].name
        low, high = expected.get(body, (np.full(3, np.inf), np.full(3, -np.inf)))
        expected[body] = np.stack([np.minimum(low, world.min(0)), np.maximum(high, world.max(0))])
    assert sorted(actual) == sorted(expected) and len(expected) == 11
    for body in expected:  # MuJoCo keeps vertices in float32: 1e-8 m on a robot arm
        np.testing.assert_allclose(actual[body], expected[body], atol=1e-6, err_msg=body)
    # Panda's visual meshes are Collada files too: every one is kept.
    path = root / "robots" / ROBOTS["panda"][0]
    with pytest.warns(MujocoLoadWarning, match="drop_mimic"):
        panda = load_mjcf(path, visuals=True, drop_mimic=True)
    visuals = [g for g in range(panda.ngeom) if not panda.geom_contype[g]]
    assert len(visuals) == path.read_text().count("<visual") and len(visuals) > 0
    assert all(panda.geom_types[g] == "mesh" and panda.geom_vertices[g].shape[0] > 100 for g in visuals)


def test_collada_unit_and_scale_are_applied(tmp_path):
    trimesh = pytest.importorskip("trimesh")
    pytest.importorskip("collada")
    box = trimesh.creation.box(extents=[1.0, 2.0, 3.0])
    text = trimesh.exchange.dae.export_collada(box)
    text = text.decode() if isinstance(text, bytes) else text
    # A file in centimetres, scaled twice by the URDF: a box of 0.02 x 0.04 x 0.06 m.
    text = re.sub(r"<unit[^>]*/>", "", text).replace("<asset>", '<asset><unit meter="0.01" name="centimeter"/>', 1)
    (tmp_path / "box.dae").write_text(text)
    path = tmp_path / "robot.urdf"
    path.write_text("""<robot name="r"><link name="base">
      <inertial><mass value="1"/><inertia ixx="0.1" ixy="0" ixz="0" iyy="0.1" iyz="0" izz="0.1"/></inertial>
      <collision><origin xyz="0 0 1"/><geometry><mesh filename="box.dae" scale="2 2 2"/></geometry></collision>
    </link></robot>""")
    loaded = load_mjcf(path)
    (bounds,) = mesh_bounds_by_body(loaded, [0]).values()
    half = np.array([0.01, 0.02, 0.03])
    np.testing.assert_allclose(bounds, [np.array([0, 0, 1]) - half, np.array([0, 0, 1]) + half], atol=1e-7)


def robot_urdf(tmp_path, visual: str, collision: str) -> pathlib.Path:
    """A one-link URDF with the given visual and collision geometry, and a mesh file shape.dae
    beside it that is not a Collada file that can be read (MuJoCo has no decoder for Collada,
    and trimesh cannot read this one)."""
    (tmp_path / "shape.dae").write_text("<COLLADA/>")
    path = tmp_path / "robot.urdf"
    path.write_text(f"""<robot name="r"><link name="base">
      <inertial><mass value="1"/><inertia ixx="0.1" ixy="0" ixz="0" iyy="0.1" iyz="0" izz="0.1"/></inertial>
      <visual><geometry>{visual}</geometry></visual><collision><geometry>{collision}</geometry></collision>
    </link></robot>""")
    return path


def test_undecodable_visual_mesh_is_dropped_with_a_warning(tmp_path):
    path = robot_urdf(tmp_path, '<mesh filename="shape.dae"/>', '<box size="0.2 0.2 0.2"/>')
    dropped = "dropped 1 visual geoms whose mesh files MuJoCo has no decoder for.*shape.dae \\(on 'base'; trimesh could not read it"
    with pytest.warns(MujocoLoadWarning, match=dropped):
        loaded = load_mjcf(path, floating_base=True)
    assert loaded.geom_types == ("box",) and loaded.geom_contype == (1,)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert load_mjcf(path, floating_base=True, visuals=False).geom_types == ("box",)
    with pytest.raises(ValueError, match="(?s)robot.urdf.*no decoder found.*shape.dae.*visual only: pass visuals='auto'"):
        load_mjcf(path, floating_base=True, visuals=True)
    # A decodable visual is kept by "auto".
    path = robot_urdf(tmp_path, '<sphere radius="0.1"/>', '<box size="0.2 0.2 0.2"/>')
    assert load_mjcf(path, floating_base=True).geom_types == ("sphere", "box")


def test_undecodable_mesh_the_physics_needs_is_an_error(tmp_path):
    path = robot_urdf(tmp_path, '<box size="0.2 0.2 0.2"/>', '<mesh filename="shape.dae"/>')
    for visuals in ("auto", True, False):
        with pytest.raises(ValueError, match=r"no decoder for \.dae mesh files \(and trimesh could not read it: .*\), and an unnamed geom of body 'base', which "
                           r"uses '.*shape.dae', cannot be dropped: it collides .*convert the file"):
            load_mjcf(path, floating_base=True, visuals=visuals)
    # A geom that does not collide but gives its body its inertia (no explicit inertial).
    (tmp_path / "shape.dae").write_text("<COLLADA/>")
    xml = f"""<mujoco><compiler meshdir="{tmp_path}"/><asset><mesh file="shape.dae"/></asset><worldbody>
      <body name="link"><joint/><geom name="look" type="mesh" mesh="shape" contype="0" conaffinity="0"/>
      <geom type="box" size="0.1 0.1 0.1"/></body></worldbody></mujoco>"""
    with pytest.raises(ValueError, match="geom 'look'.*cannot be dropped: the inertia of body 'link' is computed from it"):
        load_mjcf(xml)


def test_loading_options_are_checked():
    xml = wrap("<body><joint/><geom size='0.1'/></body>")
    for options, message in (
        (dict(visuals="none"), "visuals must be True, False or 'auto', got 'none'"),
        (dict(boundinertia=0.0), "boundinertia must be None or a positive"),
        (dict(drop_mimic=1), "drop_mimic must be True or False"),
        (dict(drop_frictionloss=None), "drop_frictionloss must be True or False"),
    ):
        with pytest.raises(ValueError, match=message):
            load_mjcf(xml, **options)
    compiled = mujoco.MjModel.from_xml_string(xml)
    for name, value in (("boundinertia", 1e-9), ("drop_mimic", True), ("drop_frictionloss", True)):
        with pytest.raises(ValueError, match=f"{name} applies to a file or XML text"):
            load_mjcf(compiled, **{name: value})
    # drop_mimic drops joint equalities only; the others are still converted.
    equalities = "<equality><joint name='mimic' joint1='j2' joint2='j1'/><weld name='weld' site1='s' site2='w'/></equality>"
    bodies = ("<body name='b'><joint name='j1'/><geom size='0.1'/><site name='s'/><body><joint name='j2'/><geom size='0.1'/>"
              "</body></body><site name='w'/>")
    two = wrap(bodies, equalities)
    both = load_mjcf(two)
    assert both.joint_couplings is not None and both.welds is not None
    with pytest.warns(MujocoLoadWarning, match="'j2' to 'j1'"):
        weld_only = load_mjcf(two, drop_mimic=True)
    assert weld_only.joint_couplings is None and weld_only.welds.frames == both.welds.frames
    coupled = load_mjcf(wrap(bodies, "<equality><joint name='mimic' joint1='j2' joint2='j1' polycoef='0 2 0 0 0'/></equality>"))
    assert coupled.joint_couplings.joints == (2,) and coupled.joint_couplings.others == (1,)
    np.testing.assert_array_equal(coupled.joint_couplings.coefficients, [[0, 2, 0, 0, 0]])


def test_mujocos_own_warnings_become_load_warnings_and_write_no_log_file(tmp_path, monkeypatch):
    import mujoco

    path = tmp_path / "arm.urdf"
    path.write_text("""<robot name="arm"><link name="base"/>
      <link name="arm"><inertial><mass value="1"/><inertia ixx="0.1" ixy="0" ixz="0" iyy="0.1" iyz="0" izz="0.1"/></inertial></link>
      <joint name="stuck" type="revolute"><parent link="base"/><child link="arm"/><axis xyz="0 1 0"/>
        <limit lower="0.5" upper="0.5" effort="1" velocity="1"/></joint></robot>""")
    monkeypatch.chdir(tmp_path)
    before = mujoco.get_mju_user_warning()
    with pytest.warns(MujocoLoadWarning, match=r"arm.urdf: MuJoCo: joint 'stuck' has equal lower and upper limits"):
        loaded = load_mjcf(path)
    assert loaded.model.joint_names == ("universe", "stuck")
    assert not (tmp_path / "MUJOCO_LOG.TXT").exists() and mujoco.get_mju_user_warning() is before


FLAGGED = """<mujoco><option><flag {flag}="disable"/></option><worldbody>
<geom name="floor" type="plane" size="1 1 0.1"/>
<geom name="terrain" type="hfield" hfield="h"/>
<body name="a" pos="0 0 0.5"><joint name="ja" limited="true" range="-1 1" frictionloss="0.3"/><geom size="0.1"/>
  <body name="b" pos="0.3 0 0"><joint name="jb"/><geom size="0.1"/></body></body>
<body name="c" pos="1 0 1"><freejoint/><geom size="0.1"/><site name="sc"/></body><site name="sw"/>
</worldbody><asset><hfield name="h" nrow="2" ncol="2" size="1 1 0.1 0.1"/></asset>
<equality><joint joint1="jb" joint2="ja"/><weld site1="sc" site2="sw"/></equality></mujoco>"""


@pytest.mark.parametrize("flag", ["contact", "limit", "equality", "frictionloss", "constraint"])
def test_disabled_constraints_are_left_out_as_mujoco_leaves_them_out(flag):
    """A model whose option flags disable a kind of constraint converts without it (and without
    converting an element of that kind: the colliding hfield, the weld, which is in the model only
    where equalities are disabled, so that a ball without contact falls freely)."""
    off = {
        "contact": {"contact"},
        "limit": {"limit"},
        "equality": {"equality"},
        "frictionloss": {"frictionloss"},
        "constraint": {"contact", "limit", "equality", "frictionloss"},
    }[flag]
    text = FLAGGED.format(flag=flag)
    if off.isdisjoint({"contact"}):
        text = text.replace('type="hfield" hfield="h"', 'type="hfield" hfield="h" contype="0" conaffinity="0"')
    if off.isdisjoint({"equality"}):
        text = text.replace('<weld site1="sc" site2="sw"/>', "")
    m = mujoco.MjModel.from_xml_string(text)
    loaded = sim.from_mujoco(m)
    assert (loaded.collision_pairs == ()) == ("contact" in off)
    assert loaded.limits_enforced == ("limit" not in off)
    assert (loaded.joint_couplings is None) == ("equality" in off) and loaded.welds is None
    assert float(loaded.frictionloss[0]) == (0.0 if "frictionloss" in off else 0.3)
    system = sim.scene(loaded)
    assert (system.joints.limits == ()) == ("limit" in off)
    assert (system.joints.couplings is None) == ("equality" in off)
    assert (len(system.geometry.geom_pairs) == 0) == ("contact" in off)
    if "contact" in off:  # as in MuJoCo, the free ball falls through the floor
        d = mujoco.MjData(m)
        steps = 400  # 0.8 s of 2 ms: the ball, 1 m up, falls 3.1 m
        for _ in range(steps):
            mujoco.mj_step(m, d)
        xs, _ = eqx.filter_jit(system.rollout)(system.initial_state(), jnp.zeros((steps, system.nu)))
        ball = loaded.q_to_qpos(xs[-1, : system.model.nq])[2:5]  # the free ball's position
        assert d.ncon == 0 and float(ball[2]) < -2.0
        np.testing.assert_allclose(ball, d.qpos[2:5], atol=1e-9)


def test_disabled_actuation_is_refused_by_name():
    text = "<mujoco><option><flag actuation='disable'/></option><worldbody><body><joint name='j'/><geom size='0.1'/></body>"
    with pytest.raises(ValueError, match="actuators are disabled"):
        sim.load_mjcf(text + "</worldbody><actuator><motor joint='j'/></actuator></mujoco>")
