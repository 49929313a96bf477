"""MuJoCo's activation dynamics (`sim.ActivationDynamics`): actuator states that filter or
integrate the controls end the state, step as MuJoCo's Euler integrator steps them, set the
forces as MuJoCo's `qfrc_actuator`, and have the step's Jacobians."""

import equinox as eqx
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from rsmooth import sim

# A cart on a slide carrying a pole on a hinge, no contact. Four actuators: a filtered
# position servo on the cart (control range [-1, 1]), an integrator on the pole with its state
# limited to [-0.5, 0.5], an exact filter on the cart whose force takes its next state
# (actearly), and a plain motor on the pole (no state).
CART_POLE = """
<mujoco>
  <option timestep="0.01" gravity="0 0 -9.81"><flag contact="disable"/></option>
  <worldbody>
    <body name="cart"><joint name="slide" type="slide" axis="1 0 0"/><geom type="box" size=".1 .1 .1" mass="2"/>
      <body name="pole" pos="0 0 .1"><joint name="hinge" type="hinge" axis="0 1 0"/>
        <geom type="capsule" fromto="0 0 0 0 0 .5" size=".03" mass=".5"/></body>
    </body>
  </worldbody>
  <actuator>
    <general name="servo" joint="slide" dyntype="filter" dynprm="0.05" gainprm="30" biastype="affine" biasprm="0 -30 -2"
             ctrllimited="true" ctrlrange="-1 1"/>
    <general name="integrator" joint="hinge" dyntype="integrator" gainprm="2" actlimited="true" actrange="-0.5 0.5"/>
    <general name="early" joint="slide" dyntype="filterexact" dynprm="0.2" gainprm="5" actearly="true"/>
    <motor name="motor" joint="hinge" gear="0.5"/>
  </actuator>
</mujoco>
"""


def _mujoco_states(controls):
    """MuJoCo's ``(qpos, qvel, act)`` after each ``mj_step`` under ``controls`` ``(T, nu)``."""
    m = mujoco.MjModel.from_xml_string(CART_POLE)
    d = mujoco.MjData(m)
    states = []
    for ctrl in controls:
        d.ctrl[:] = ctrl
        mujoco.mj_step(m, d)
        states.append(np.concatenate([d.qpos, d.qvel, d.act]))
    return np.array(states)


def test_activation_states_step_and_drive_as_mujocos_euler_integrator():
    loaded = sim.load_mjcf(CART_POLE)
    system = sim.scene(loaded)
    dynamics = system.actuation.servos.dynamics
    assert (system.na, system.nx, system.nu) == (3, 7, 4) and dynamics.actuators == (0, 1, 2)
    assert dynamics.kinds == ("filter", "integrator", "filterexact") and dynamics.early == (False, False, True)
    x0 = system.initial_state()
    np.testing.assert_array_equal(system.activations(x0), np.zeros(3))
    # controls beyond the servo's range and long enough on the integrator to reach its limit
    controls = np.random.default_rng(0).uniform(-2, 2, size=(120, 4))
    controls[:60, 1] = 1.5
    xs, infos = eqx.filter_jit(system.rollout)(x0, jnp.asarray(controls))
    expected = _mujoco_states(controls)
    np.testing.assert_allclose(np.asarray(xs)[1:], expected, rtol=0, atol=1e-10)
    assert np.max(expected[:, 5]) == 0.5  # the integrator's state held at its limit
    assert bool(jnp.all(infos.torque_clipped == (np.abs(controls[:, 0]) > 1)))


def test_forces_from_states_are_mujocos_qfrc_actuator():
    loaded = sim.load_mjcf(CART_POLE)
    system = sim.scene(loaded)
    m = mujoco.MjModel.from_xml_string(CART_POLE)
    d = mujoco.MjData(m)
    rng = np.random.default_rng(1)
    forces = jax.jit(lambda q, v, u, act: system.generalized_forces(q, jnp.concatenate([u, act]), None, v))
    for _ in range(6):
        d.qpos[:], d.qvel[:] = rng.uniform(-1, 1, size=2), rng.normal(size=2)
        d.act[:], d.ctrl[:] = rng.uniform(-0.5, 0.5, size=3), rng.uniform(-2, 2, size=4)
        mujoco.mj_forward(m, d)
        tau, _ = forces(jnp.asarray(d.qpos), jnp.asarray(d.qvel), jnp.asarray(d.ctrl), jnp.asarray(d.act))
        np.testing.assert_allclose(tau, d.qfrc_actuator, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(loaded.ctrl_to_tau(d.ctrl, d.qpos, d.qvel, d.act), d.qfrc_actuator, rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError, match="needs act"):
        loaded.ctrl_to_tau(d.ctrl, d.qpos, d.qvel)


def test_step_jacobians_hold_the_states_columns_and_rows():
    system = sim.scene(CART_POLE)
    x = system.state(jnp.array([0.1, 0.3]), jnp.array([0.2, -0.4]), jnp.array([0.3, 0.1, -0.2]))
    u = jnp.array([0.5, -0.7, 0.4, 0.2])
    x_next, fx, fu = eqx.filter_jit(lambda s, x_, u_: s.step_and_jacobians(x_, u_))(system, x, u)
    step = eqx.filter_jit(lambda s, x_, u_: s.step(x_, u_))
    np.testing.assert_allclose(x_next, step(system, x, u), rtol=0, atol=1e-14)
    eps = 1e-6
    columns = [(step(system, x + eps * e, u) - step(system, x - eps * e, u)) / (2 * eps) for e in jnp.eye(7)]
    np.testing.assert_allclose(fx, jnp.stack(columns, axis=1), rtol=0, atol=1e-7)
    columns = [(step(system, x, u + eps * e) - step(system, x, u - eps * e)) / (2 * eps) for e in jnp.eye(4)]
    np.testing.assert_allclose(fu, jnp.stack(columns, axis=1), rtol=0, atol=1e-7)
    # the stages composed by hand carry the states too
    state, *_ = sim.step_stages(system, sim.make_state(system, x), u)
    np.testing.assert_allclose(state.x, x_next, rtol=0, atol=1e-12)
    # the filter's own row: act+ = act + h (c - act) / tau
    h, tau = 0.01, 0.05
    np.testing.assert_allclose(fx[4, 4], 1 - h / tau, rtol=1e-12)
    np.testing.assert_allclose(fu[4], [h / tau, 0, 0, 0], rtol=1e-12, atol=1e-15)
    # beyond the servo's control range its state no longer moves with the control
    _, _, fu_clipped = eqx.filter_jit(lambda s, x_, u_: s.step_and_jacobians(x_, u_))(system, x, u.at[0].set(1.5))
    assert fu_clipped[4, 0] == 0.0


def test_bad_dynamics_and_unsupported_ones_are_refused_by_name():
    with pytest.raises(ValueError, match="ActivationDynamics.kinds must hold one of"):
        sim.ActivationDynamics((0,), ("muscle",), (False,), jnp.ones(1), jnp.array([[-1.0, 1.0]]))
    with pytest.raises(ValueError, match="ActivationDynamics.time_constant must be positive"):
        sim.ActivationDynamics((0,), ("filter",), (False,), jnp.zeros(1), jnp.array([[-1.0, 1.0]]))
    with pytest.raises(ValueError, match="act_range must hold lower <= upper"):
        sim.ActivationDynamics((0,), ("filter",), (False,), jnp.ones(1), jnp.array([[1.0, -1.0]]))
    with pytest.raises(ValueError, match="actuator 'user' is not supported: it has activation dynamics user"):
        sim.load_mjcf(CART_POLE.replace('<motor name="motor"', '<general name="user" dyntype="user"'))
    system = sim.scene(CART_POLE)
    with pytest.raises(ValueError, match=r"act must have shape \(..., na\) = \(..., 3\)"):
        system.state(jnp.zeros(2), None, jnp.zeros(2))
    with pytest.raises(ValueError, match=r"x must have shape \(nx,\) = \(7,\) as \[q \(nq=2\), v \(nv=2\), act \(na=3\)\]"):
        system.step(jnp.zeros(4), jnp.zeros(4))
