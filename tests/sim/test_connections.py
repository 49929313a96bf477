"""Connect and weld equalities (`sim.PointConnection`, `sim.Weld`: MuJoCo's `<equality><connect>`
and `<weld>`): their errors and rows equal MuJoCo's, a closed loop moves as its one degree of
freedom allows and swings at a physical pendulum's period, a hung or welded box rests on its
weight, welded bodies fall as one, mocap bodies are held fixed, skins (visual only) are left
out, and what is not modelled is refused by name."""

import equinox as eqx
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from rsmooth import sim

# A free box held to the world by a corner, a hinged chain closed by a connection to a hinged
# rocker (bodies), and a site of the box held to a site of the world.
MIXED = """
<mujoco>
  <worldbody>
    <body name="a" pos="0 0 1"><freejoint/><geom type="box" size="0.1 0.05 0.02" mass="1" contype="0" conaffinity="0"/>
      <site name="sa" pos="0.1 0 0"/></body>
    <body name="l1" pos="0 0 0.5"><joint name="h1" axis="0 1 0"/>
      <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.02" contype="0" conaffinity="0"/>
      <body name="l2" pos="0.3 0 0"><joint name="h2" axis="0 1 0"/>
        <geom type="capsule" fromto="0 0 0 0 0 -0.3" size="0.02" contype="0" conaffinity="0"/></body></body>
    <body name="l3" pos="0.5 0 0.5"><joint name="h3" axis="1 0 0"/>
      <geom type="capsule" fromto="0 0 0 0 0 -0.3" size="0.02" contype="0" conaffinity="0"/></body>
    <site name="w" pos="0.5 0.2 1.2"/>
  </worldbody>
  <equality>
    <connect body1="a" body2="world" anchor="-0.1 0.05 0.02"/>
    <connect body1="l2" body2="l3" anchor="0 0 -0.3"/>
    <connect site1="sa" site2="w"/>
    <connect body1="l1" body2="world" anchor="0.1 0 0" active="false"/>
  </equality>
</mujoco>
"""

# A parallelogram: crank and rocker (0.3 m) hinged 0.4 m apart, the coupler (0.4 m) hinged to
# the crank's end and connected to the rocker's. The coupler translates without turning, the
# crank and the rocker keep equal angles: one degree of freedom, a physical pendulum.
PARALLELOGRAM = """
<mujoco>
  <option timestep="0.002"/>
  <worldbody>
    <body name="crank" pos="0 0 1"><joint name="h1" axis="0 1 0"/>
      <geom type="capsule" fromto="0 0 0 0 0 -0.3" size="0.02" mass="1" contype="0" conaffinity="0"/>
      <body name="coupler" pos="0 0 -0.3"><joint name="h2" axis="0 1 0"/>
        <geom type="capsule" fromto="0 0 0 0.4 0 0" size="0.02" mass="2" contype="0" conaffinity="0"/></body></body>
    <body name="rocker" pos="0.4 0 1"><joint name="h3" axis="0 1 0"/>
      <geom type="capsule" fromto="0 0 0 0 0 -0.3" size="0.02" mass="0.5" contype="0" conaffinity="0"/></body>
  </worldbody>
  <equality><connect body1="coupler" body2="rocker" anchor="0.4 0 0"/></equality>
</mujoco>
"""


def _assert_equality_rows_are_mujocos(text, errors, rows_count, quaternions, seed):
    """On random states of ``text`` (the free joint's and ball joints' quaternions at
    ``quaternions``, turned up to about 80 degrees), ``errors(system, q)`` (flattened) equals
    MuJoCo's equality constraint positions ``efc_pos``, and the system's equality rows times
    ``v`` MuJoCo's ``efc_J qvel``, row for row; the rows' corrections are ``baumgarte e / h``."""
    m = mujoco.MjModel.from_xml_string(text)
    d = mujoco.MjData(m)
    loaded = sim.load_mjcf(text)
    system = sim.scene(loaded, floor=False)
    rng = np.random.default_rng(seed)
    for _ in range(4):
        qpos = m.qpos0 + np.r_[rng.normal(size=3) * 0.1, np.zeros(m.nq - 3)]
        hinges = [a for a in range(7, m.nq) if not any(start <= a < start + 4 for start in quaternions)]
        qpos[hinges] += rng.normal(size=len(hinges)) * 0.5
        for start in quaternions:
            quaternion = rng.normal(size=4)
            quaternion[0] = abs(quaternion[0]) + 1.5
            qpos[start : start + 4] = quaternion / np.linalg.norm(quaternion)
        qvel = rng.normal(size=m.nv)
        d.qpos[:], d.qvel[:] = qpos, qvel
        mujoco.mj_forward(m, d)
        equality = d.efc_type == mujoco.mjtConstraint.mjCNSTR_EQUALITY
        q = loaded.qpos_to_q(jnp.asarray(qpos))
        v = loaded.qvel_to_v(jnp.asarray(qpos), jnp.asarray(qvel))
        np.testing.assert_allclose(np.asarray(errors(system, q)).reshape(-1), d.efc_pos[equality], rtol=0, atol=1e-12)
        rows, correction, bounds = system.joint_rows(q)
        assert rows.shape == (rows_count, m.nv) and np.all(np.isinf(np.asarray(bounds)))
        np.testing.assert_allclose(np.asarray(rows @ v), d.efc_J.reshape(-1, m.nv)[equality] @ qvel, rtol=0, atol=1e-12)
        np.testing.assert_allclose(
            np.asarray(correction), float(system.baumgarte) * d.efc_pos[equality] / float(system.time_step), rtol=1e-12, atol=0
        )
    return loaded


def test_connection_errors_and_rows_are_mujocos():
    # MuJoCo's constraint positions (p_a - p_b, world) and velocities (J qvel), three rows a connection
    loaded = _assert_equality_rows_are_mujocos(MIXED, lambda s, q: s.connection_errors(q), 9, (3,), seed=0)
    assert len(loaded.connections.frames) == 3  # the inactive one left out


def _pivot_inertia(m, body, pivot):
    """Body ``body``'s moment of inertia about the world y axis through ``pivot`` at ``qpos0``."""
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    rotation = d.ximat[body].reshape(3, 3)
    inertia = rotation @ np.diag(m.body_inertia[body]) @ rotation.T
    offset = d.xipos[body] - pivot
    return inertia[1, 1] + m.body_mass[body] * (offset[0] ** 2 + offset[2] ** 2)


def test_a_parallelogram_keeps_its_shape_and_swings_as_one_pendulum():
    m = mujoco.MjModel.from_xml_string(PARALLELOGRAM)
    system = sim.scene(PARALLELOGRAM, floor=False)
    h, g, theta0, steps = 0.002, 9.81, 0.1, 1000
    x0 = system.state(jnp.array([theta0, -theta0, theta0]), jnp.zeros(3))
    np.testing.assert_allclose(np.asarray(system.connection_errors(x0[:3])), 0.0, atol=1e-15)
    xs, infos = eqx.filter_jit(lambda s, x: s.rollout(x, jnp.zeros((steps, s.nu))))(system, x0)
    q = np.asarray(xs)[:, :3]
    assert bool(jnp.all(infos.ncp.converged))
    # the loop's shape: the rocker follows the crank, the coupler does not turn
    np.testing.assert_allclose(q[:, 2], q[:, 0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(q[:, 1], -q[:, 0], rtol=0, atol=1e-12)
    errors = np.asarray(jax.vmap(system.connection_errors)(xs[:, :3]))
    assert np.max(np.abs(errors)) < 1e-12
    # a physical pendulum: the crank and the rocker turn about their hinges, the coupler
    # translates on a circle of the crank's length
    crank, coupler, rocker = (m.body(name).id for name in ("crank", "coupler", "rocker"))
    inertia = (_pivot_inertia(m, crank, np.array([0.0, 0.0, 1.0])) + _pivot_inertia(m, rocker, np.array([0.4, 0.0, 1.0]))
               + m.body_mass[coupler] * 0.3**2)
    moment = (m.body_mass[crank] + m.body_mass[rocker]) * 0.15 + m.body_mass[coupler] * 0.3
    expected = 2 * np.pi * np.sqrt(inertia / (moment * g)) * (1 + theta0**2 / 16)
    angle = q[:, 0]
    downward = np.flatnonzero((angle[:-1] > 0) & (angle[1:] <= 0))
    crossings = downward - angle[downward] / (angle[downward + 1] - angle[downward])
    assert len(crossings) >= 2
    assert np.diff(crossings).mean() * h == pytest.approx(expected, rel=1e-4)


# A 2 kg box hung from the world by the centre of its top face.
HUNG = """
<mujoco>
  <option timestep="0.01"/>
  <worldbody>
    <body name="box" pos="0 0 1"><freejoint/><geom type="box" size="0.1 0.1 0.1" mass="2" contype="0" conaffinity="0"/></body>
  </worldbody>
  <equality><connect body1="box" body2="world" anchor="0 0 0.1"/></equality>
</mujoco>
"""


def test_a_hung_box_rests_on_its_weight_and_its_step_jacobian_is_central_differences(state_jacobian_is_central_differences):
    system = sim.scene(HUNG, floor=False)
    h, mass, g = 0.01, 2.0, 9.81
    x0 = system.initial_state()
    xs, infos = eqx.filter_jit(lambda s, x: s.rollout(x, jnp.zeros((20, s.nu))))(system, x0)
    np.testing.assert_allclose(np.asarray(xs), np.asarray(x0)[None].repeat(21, axis=0), rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(infos.joint_impulse)[:, 2], mass * g * h, rtol=1e-9)
    np.testing.assert_allclose(np.asarray(infos.joint_impulse)[:, :2], 0.0, atol=1e-12)
    # swinging and spinning: the step's state Jacobian (through the rows' dependence on the
    # pose and the correction of the error) against central differences
    x = system.state(x0[:7].at[:3].add(jnp.array([0.01, -0.02, 0.005])), jnp.array([0.3, -0.2, 0.1, 1.0, -0.5, 2.0]))
    state_jacobian_is_central_differences(system, system.project_state(x), atol=1e-7)


# A free box welded to the world, a hinged chain welded to a hinged rocker (with a torque
# scale), a bar welded to the box with a given relative pose, and two turned sites welded.
WELDED = """
<mujoco>
  <worldbody>
    <body name="a" pos="0 0 1" euler="10 20 30"><freejoint/>
      <geom type="box" size="0.1 0.05 0.02" mass="1" contype="0" conaffinity="0"/></body>
    <body name="l1" pos="0 0 0.5"><joint name="h1" axis="0 1 0"/><site name="s1" pos="0.1 0.02 0" euler="10 20 30"/>
      <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.02" contype="0" conaffinity="0"/>
      <body name="l2" pos="0.3 0 0"><joint name="h2" type="ball"/>
        <geom type="capsule" fromto="0 0 0 0 0 -0.3" size="0.02" contype="0" conaffinity="0"/></body></body>
    <body name="l3" pos="0.5 0 0.5" euler="0 0 40"><joint name="h3" axis="1 0 0"/>
      <site name="s2" pos="0 0.05 -0.1" euler="-20 5 40"/>
      <geom type="capsule" fromto="0 0 0 0 0 -0.3" size="0.02" contype="0" conaffinity="0"/></body>
  </worldbody>
  <equality>
    <weld body1="a" body2="world" anchor="-0.1 0.05 0.02"/>
    <weld body1="l2" body2="l3" anchor="0 0 -0.3" torquescale="2.5"/>
    <weld body1="l1" body2="a" relpose="0.1 0.2 0.3 0.9 0.1 0.3 0.2"/>
    <weld site1="s1" site2="s2" torquescale="0.7"/>
  </equality>
</mujoco>
"""


def test_weld_errors_and_rows_are_mujocos():
    # the points' gaps and MuJoCo's orientation errors, and their rates, six rows a weld
    loaded = _assert_equality_rows_are_mujocos(WELDED, lambda s, q: s.weld_errors(q), 24, (3, 8), seed=1)
    np.testing.assert_allclose(np.asarray(loaded.welds.torque_scale), [1.0, 2.5, 1.0, 0.7])


def test_a_box_welded_to_the_world_by_a_corner_holds_its_weight_and_its_moment():
    system = sim.scene(HUNG.replace("<connect", "<weld").replace('anchor="0 0 0.1"', 'anchor="0.1 0.1 0.1"'), floor=False)
    h, mass, g = 0.01, 2.0, 9.81
    x0 = system.initial_state()
    xs, infos = eqx.filter_jit(lambda s, x: s.rollout(x, jnp.zeros((20, s.nu))))(system, x0)
    np.testing.assert_allclose(np.asarray(xs), np.asarray(x0)[None].repeat(21, axis=0), rtol=0, atol=1e-12)
    # the point's impulse carries the weight; the orientation rows the moment of the weight
    # about the corner, (c - p) x F = (-0.1, -0.1, -0.1) x (0, 0, m g h), as 2 tau (their rate
    # is omega / 2 at the weld's pose)
    force = np.array([0.0, 0.0, mass * g * h])
    np.testing.assert_allclose(np.asarray(infos.joint_impulse)[:, :3], force[None].repeat(20, 0), rtol=0, atol=1e-12)
    moment = np.cross([-0.1, -0.1, -0.1], force)
    np.testing.assert_allclose(np.asarray(infos.joint_impulse)[:, 3:], 2 * moment[None].repeat(20, 0), rtol=0, atol=1e-12)


# Two free boxes welded side by side, thrown up spinning.
PAIR = """
<mujoco>
  <option timestep="0.005"/>
  <worldbody>
    <body name="a" pos="0 0 1"><freejoint/><geom type="box" size="0.1 0.05 0.05" mass="1" contype="0" conaffinity="0"/></body>
    <body name="b" pos="0.2 0 1" euler="0 0 30"><freejoint/><geom type="box" size="0.1 0.05 0.05" mass="3" contype="0" conaffinity="0"/></body>
  </worldbody>
  <equality><weld body1="b" body2="a" anchor="0.1 0 0"/></equality>
</mujoco>
"""


def test_welded_boxes_fall_as_one_body_and_the_step_jacobian_is_central_differences(state_jacobian_is_central_differences):
    system = sim.scene(PAIR, floor=False)
    h, g, steps = 0.005, 9.81, 100
    # a rigid motion of the pair: spinning at w about the vertical through a's centre
    w = 3.0
    x0 = np.array(system.initial_state())
    v = x0[system.model.nq :].reshape(2, 6)
    v[0] = [0.5, 0.0, 2.0, 0.0, 0.0, w]
    b_rotation = np.array([[np.cos(np.pi / 6), -np.sin(np.pi / 6), 0], [np.sin(np.pi / 6), np.cos(np.pi / 6), 0], [0, 0, 1]])
    v[1, :3] = b_rotation.T @ (np.array([0.5, 0.0, 2.0]) + np.cross([0, 0, w], [0.2, 0, 0]))  # body axes
    v[1, 3:] = b_rotation.T @ np.array([0.0, 0.0, w])
    x0 = jnp.asarray(np.concatenate([x0[: system.model.nq], v.reshape(-1)]))
    np.testing.assert_allclose(np.asarray(system.weld_errors(x0[: system.model.nq])), 0.0, atol=1e-15)
    xs, infos = eqx.filter_jit(lambda s, x: s.rollout(x, jnp.zeros((steps, s.nu))))(system, x0)
    assert bool(jnp.all(infos.ncp.converged))
    # The pair keeps its shape up to the time stepping's drift: each step moves b's centre
    # (0.2 m off the axis) along a chord, off its circle by w^2 r h^2 / 2, which the Baumgarte
    # correction (a fraction of the error a step) pulls back: their balance bounds the gap.
    errors = np.asarray(jax.vmap(system.weld_errors)(xs[:, : system.model.nq]))
    assert np.max(np.abs(errors)) < 1.1 * w**2 * 0.2 * h**2 / 2 / float(system.baumgarte)
    # the weld's impulses are internal: the centre of mass falls freely
    q = np.asarray(xs)[:, : system.model.nq]
    centre = (1.0 * q[:, 0:3] + 3.0 * q[:, 7:10]) / 4.0
    t = np.arange(steps + 1) * h
    start = centre[0]
    velocity = (1.0 * np.array([0.5, 0.0, 2.0]) + 3.0 * (np.array([0.5, 0.0, 2.0]) + np.cross([0, 0, w], [0.2, 0, 0]))) / 4.0
    # semi-implicit Euler: z_n = z_0 + v_0 t_n - g h^2 n (n + 1) / 2
    n = np.arange(steps + 1)
    expected = start + velocity * t[:, None] - np.outer(g * h**2 * n * (n + 1) / 2, [0, 0, 1])
    np.testing.assert_allclose(centre, expected, rtol=0, atol=1e-9)
    # the step's state Jacobian against central differences, mid-flight
    state_jacobian_is_central_differences(system, xs[40], atol=1e-6)


def test_bad_connections_and_welds_are_refused_by_name():
    with pytest.raises(ValueError, match="Weld.torque_scale must be > 0"):
        sim.Weld((1,), (0,), jnp.zeros((1, 3)), jnp.zeros((1, 3)), jnp.eye(3)[None], jnp.zeros(1))
    with pytest.raises(ValueError, match=r"PointConnection.anchors must have shape \(1, 3\)"):
        sim.PointConnection((1,), (0,), jnp.zeros((2, 3)), jnp.zeros((1, 3)))
    with pytest.raises(ValueError, match="PointConnection.other_anchors must be finite"):
        sim.PointConnection((1,), (0,), jnp.zeros((1, 3)), jnp.full((1, 3), jnp.nan))
    system = sim.scene(HUNG, floor=False)
    with pytest.raises(ValueError, match=r"joints.connections: frames \[99\] out of range"):
        system.with_connections(sim.PointConnection((99,), (0,), jnp.zeros((1, 3)), jnp.zeros((1, 3))))


# A table that is a mocap body (an IK target's kind: moved by data in MuJoCo, fixed here), a ball
# resting on it, and a box welded to a mocap handle above it.
MOCAP = """
<mujoco>
  <option timestep="0.01"/>
  <worldbody>
    <body name="table" mocap="true" pos="0 0 0.5"><geom type="box" size="0.3 0.3 0.05"/></body>
    <body name="ball" pos="0 0 0.65"><freejoint/><geom type="sphere" size="0.1" mass="1"/></body>
    <body name="handle" mocap="true" pos="1 0 1"/>
    <body name="box" pos="1 0 0.9"><freejoint/><geom type="box" size="0.05 0.05 0.05" mass="2" contype="0" conaffinity="0"/></body>
  </worldbody>
  <equality><weld body1="box" body2="handle"/></equality>
</mujoco>
"""


def test_mocap_bodies_are_held_fixed_with_a_warning():
    with pytest.warns(sim.MujocoLoadWarning, match=r"mocap bodies \['table', 'handle'\] are held fixed"):
        loaded = sim.load_mjcf(MOCAP)
    system = sim.scene(loaded, floor=False)
    x0 = system.initial_state()
    xs, infos = eqx.filter_jit(lambda s, x: s.rollout(x, jnp.zeros((50, s.nu))))(system, x0)
    assert bool(jnp.all(infos.ncp.converged))
    # the ball rests on the table's top (0.55 m) at its radius; the box hangs from the handle
    np.testing.assert_allclose(float(xs[-1, 2]), 0.55 + 0.1, atol=1e-6)
    np.testing.assert_allclose(np.asarray(xs[-1, 7:10]), [1.0, 0.0, 0.9], atol=1e-9)


SKINNED = """<mujoco><worldbody><geom type="plane" size="1 1 0.1"/>
  <body name="ball" pos="0 0 0.1"><freejoint/><geom size="0.1"/></body></worldbody>
  <deformable><skin name="cover" vertex="0 0 0  0.1 0 0  0 0.1 0" face="0 1 2">
    <bone body="ball" bindpos="0 0 0" bindquat="1 0 0 0" vertid="0 1 2" vertweight="1 1 1"/></skin></deformable>
</mujoco>"""


def test_skins_are_left_out_with_a_warning_and_change_nothing():
    with pytest.warns(sim.MujocoLoadWarning, match=r"skins \['cover'\] are left out"):
        skinned = sim.load_mjcf(SKINNED)
    plain = sim.load_mjcf(SKINNED[: SKINNED.index("<deformable>")] + "</mujoco>")
    for ours, theirs in zip(jax.tree.leaves(skinned.model), jax.tree.leaves(plain.model), strict=True):
        np.testing.assert_array_equal(np.asarray(ours), np.asarray(theirs))
    assert skinned.ngeom == plain.ngeom
