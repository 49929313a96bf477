"""Connect equalities (`sim.PointConnection`, MuJoCo's `<equality><connect>`): their errors and
rows equal MuJoCo's, a closed loop moves as its one degree of freedom allows, a body hung by a
point rests on its weight and swings at a physical pendulum's period, and what is not modelled is
refused by name."""

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


def test_connection_errors_and_rows_are_mujocos():
    m = mujoco.MjModel.from_xml_string(MIXED)
    d = mujoco.MjData(m)
    loaded = sim.load_mjcf(MIXED)
    assert len(loaded.connections.frames) == 3  # the inactive one left out
    system = sim.scene(loaded, floor=False)
    rng = np.random.default_rng(0)
    for _ in range(4):
        qpos = m.qpos0 + np.r_[rng.normal(size=3) * 0.1, np.zeros(4), rng.normal(size=3)]
        qpos[3:7] = rng.normal(size=4)
        qpos[3:7] /= np.linalg.norm(qpos[3:7])
        qvel = rng.normal(size=m.nv)
        d.qpos[:], d.qvel[:] = qpos, qvel
        mujoco.mj_forward(m, d)
        equality = d.efc_type == mujoco.mjtConstraint.mjCNSTR_EQUALITY
        q = loaded.qpos_to_q(jnp.asarray(qpos))
        v = loaded.qvel_to_v(jnp.asarray(qpos), jnp.asarray(qvel))
        # MuJoCo's constraint positions (p_a - p_b, world) and velocities (J qvel), row for row
        np.testing.assert_allclose(np.asarray(system.connection_errors(q)).reshape(-1), d.efc_pos[equality], rtol=0, atol=1e-12)
        rows, correction, bounds = system.joint_rows(q)
        assert rows.shape == (9, m.nv) and np.all(np.isinf(np.asarray(bounds)))
        np.testing.assert_allclose(np.asarray(rows @ v), d.efc_J.reshape(-1, m.nv)[equality] @ qvel, rtol=0, atol=1e-12)
        np.testing.assert_allclose(
            np.asarray(correction), float(system.baumgarte) * d.efc_pos[equality] / float(system.time_step), rtol=1e-12, atol=0
        )


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


def test_a_hung_box_rests_on_its_weight_and_its_step_jacobian_is_central_differences():
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
    x = system.project_state(x)
    u = jnp.zeros(system.nu)
    _, fx, _ = eqx.filter_jit(lambda s, x_, u_: s.step_and_jacobians(x_, u_))(system, x, u)
    step = eqx.filter_jit(lambda s, x_, u_: s.step(x_, u_))
    eps = 1e-6
    columns = [(step(system, x + eps * e, u) - step(system, x - eps * e, u)) / (2 * eps) for e in jnp.eye(x.shape[0])]
    np.testing.assert_allclose(fx, jnp.stack(columns, axis=1), rtol=0, atol=1e-7)


def test_what_is_not_modelled_and_bad_connections_are_refused_by_name():
    weld = HUNG.replace("<connect", "<weld").replace(' anchor="0 0 0.1"', "")
    with pytest.raises(ValueError, match="equality constraints other than joint couplings and connections"):
        sim.load_mjcf(weld)
    with pytest.raises(ValueError, match=r"PointConnection.anchors must have shape \(1, 3\)"):
        sim.PointConnection((1,), (0,), jnp.zeros((2, 3)), jnp.zeros((1, 3)))
    with pytest.raises(ValueError, match="PointConnection.other_anchors must be finite"):
        sim.PointConnection((1,), (0,), jnp.zeros((1, 3)), jnp.full((1, 3), jnp.nan))
    system = sim.scene(HUNG, floor=False)
    with pytest.raises(ValueError, match=r"joints.connections: frames \[99\] out of range"):
        system.with_connections(sim.PointConnection((99,), (0,), jnp.zeros((1, 3)), jnp.zeros((1, 3))))
