"""MuJoCo's position and velocity servos (actuators with an affine bias, `sim.Servos`): the
generalized forces equal MuJoCo's `qfrc_actuator`, an arm driven by servos follows MuJoCo's
Euler trajectory, and a position servo holds its target against gravity at the closed-form
offset."""

import equinox as eqx
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from rsmooth import sim

# A planar arm of two hinges and a slide: a position servo on hinge 0 (gear 2, its force and
# control ranges limited), a velocity servo on the slide, a motor on hinge 1, and a position
# servo on a fixed tendon over both hinges; no contact.
ARM = """
<mujoco>
  <option timestep="0.005" gravity="0 0 -9.81"/>
  <worldbody>
    <body name="a"><joint name="h0" type="hinge" axis="0 1 0" ref="0.3"/>
      <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03" contype="0" conaffinity="0"/>
      <body name="b" pos="0.3 0 0"><joint name="h1" type="hinge" axis="0 1 0"/>
        <geom type="capsule" fromto="0 0 0 0.25 0 0" size="0.03" contype="0" conaffinity="0"/>
        <body name="c" pos="0.25 0 0"><joint name="s" type="slide" axis="1 0 0"/>
          <geom type="box" size="0.04 0.04 0.04" contype="0" conaffinity="0"/>
        </body>
      </body>
    </body>
  </worldbody>
  <tendon><fixed name="both"><joint joint="h0" coef="0.5"/><joint joint="h1" coef="1"/></fixed></tendon>
  <actuator>
    <position name="shoulder" joint="h0" kp="20" kv="1" gear="2" ctrlrange="-1 1" ctrllimited="true" forcerange="-15 15" forcelimited="true"/>
    <velocity name="slider" joint="s" kv="5"/>
    <motor name="elbow" joint="h1" gear="1.5"/>
    <position name="pair" tendon="both" kp="3"/>
  </actuator>
</mujoco>
"""


def test_servo_forces_are_mujocos_qfrc_actuator():
    loaded = sim.load_mjcf(ARM)
    system = sim.scene(loaded)
    assert system.actuation.kind == "servos" and system.nu == 4
    np.testing.assert_allclose(loaded.actuator_bias, [[0, -20, -1], [0, 0, -5], [0, 0, 0], [0, -3, 0]])
    m = mujoco.MjModel.from_xml_string(ARM)
    d = mujoco.MjData(m)
    rng = np.random.default_rng(0)
    forces = jax.jit(lambda q, v, u: system.generalized_forces(q, u, None, v))
    for _ in range(8):
        d.qpos[:] = rng.uniform(-1.5, 1.5, size=m.nq)
        d.qvel[:] = rng.normal(size=m.nv)
        d.ctrl[:] = rng.uniform(-2, 2, size=m.nu)  # beyond the shoulder's control range too
        mujoco.mj_forward(m, d)
        q, v = loaded.qpos_to_q(jnp.asarray(d.qpos)), jnp.asarray(d.qvel)
        tau, clipped = forces(q, v, jnp.asarray(d.ctrl))
        np.testing.assert_allclose(tau, d.qfrc_actuator, rtol=1e-12, atol=1e-12)
        assert bool(clipped) == (abs(d.ctrl[0]) > 1)
        np.testing.assert_allclose(loaded.ctrl_to_tau(d.ctrl, d.qpos, d.qvel), d.qfrc_actuator, rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError, match="needs qpos and qvel"):
        loaded.ctrl_to_tau(np.zeros(4))


def test_servos_drive_the_arm_as_mujocos_euler_integrator(mujoco_and_rsmooth_trajectories):
    ctrl = np.array([0.7, -0.4, 0.8, 0.3])
    system, loaded, xs, expected = mujoco_and_rsmooth_trajectories(ARM, None, np.zeros(3), 300, ctrl=ctrl, u=ctrl)
    np.testing.assert_allclose(np.asarray(xs)[1:, :3] + np.asarray(loaded.qpos0), expected, rtol=0, atol=1e-10)
    # the step's Jacobians (forces that depend on q, v and u) against central differences
    x, u = jnp.asarray(np.asarray(xs)[50]), jnp.asarray(ctrl)
    _, fx, fu = eqx.filter_jit(lambda s, x_, u_: s.step_and_jacobians(x_, u_))(system, x, u)
    step = eqx.filter_jit(lambda s, x_, u_: s.step(x_, u_))
    eps = 1e-6
    columns = [(step(system, x + eps * e, u) - step(system, x - eps * e, u)) / (2 * eps) for e in jnp.eye(6)]
    np.testing.assert_allclose(fx, jnp.stack(columns, axis=1), rtol=0, atol=1e-7)
    columns = [(step(system, x, u + eps * e) - step(system, x, u - eps * e)) / (2 * eps) for e in jnp.eye(4)]
    np.testing.assert_allclose(fu, jnp.stack(columns, axis=1), rtol=0, atol=1e-7)


def test_a_position_servo_holds_its_target_offset_by_gravity():
    # A 1 kg point mass on a vertical slide, a position servo of stiffness kp: at rest it sits
    # m g / kp below its target (and the damper kv settles it there).
    text = """<mujoco><option timestep="0.01"/><worldbody><body><joint name="z" type="slide" axis="0 0 1"/>
      <geom type="sphere" size="0.05" mass="1" contype="0" conaffinity="0"/></body></worldbody>
      <actuator><position joint="z" kp="400" kv="30"/></actuator></mujoco>"""
    system = sim.scene(text)
    xs, infos = eqx.filter_jit(lambda s, x: s.rollout(x, jnp.full((400, 1), 0.2)))(system, system.initial_state())
    np.testing.assert_allclose(float(xs[-1, 0]), 0.2 - 9.81 / 400, rtol=1e-9)
    assert not bool(jnp.any(infos.torque_clipped))


def test_a_one_sided_motor_lifts_a_slide_as_mujocos_euler_integrator(mujoco_and_rsmooth_trajectories):
    """A motor whose control range is [0, 1] (it can only push up): no symmetric bound on the
    slide's force expresses it, so u is its control. Beyond the range it is clipped: a control
    of 1.5 lifts with the force of 1 (14 N against 9.81 N of weight), as in MuJoCo."""
    text = """<mujoco><option timestep="0.005"/><worldbody><body><joint name="z" type="slide" axis="0 0 1"/>
      <geom type="sphere" size="0.05" mass="1" contype="0" conaffinity="0"/></body></worldbody>
      <actuator><motor joint="z" gear="14" ctrlrange="0 1" ctrllimited="true"/></actuator></mujoco>"""
    system, loaded, xs, expected = mujoco_and_rsmooth_trajectories(text, None, np.zeros(1), 100, ctrl=[1.5], u=[1.5])
    assert system.actuation.kind == "servos"
    np.testing.assert_allclose(np.asarray(xs)[1:, :1], expected, rtol=0, atol=1e-12)
    # semi-implicit Euler under the clipped force: z_n = a h^2 n (n + 1) / 2
    n, h = np.arange(1, 101), 0.005
    np.testing.assert_allclose(expected[:, 0], (14.0 - 9.81) * h**2 * n * (n + 1) / 2, rtol=1e-9)


def test_unsupported_actuators_are_refused_by_name():
    with pytest.raises(ValueError, match="actuator 'slow' is not supported: its gain type is affine"):
        sim.load_mjcf(ARM.replace('<velocity name="slider" joint="s" kv="5"/>',
                                  '<general name="slow" joint="s" gaintype="affine" gainprm="1 0 1"/>'))
    servos = sim.scene(ARM).actuation.servos
    with pytest.raises(ValueError, match=r"actuation servos \(a Servos\) are given with kind 'servos'"):
        sim.Actuation("joints", jnp.ones(1), dofs=(0,), servos=servos)
    with pytest.raises(ValueError, match="actuation servos must have one entry per input"):
        sim.Actuation("servos", jnp.ones(2), moments=jnp.ones((2, 3)), servos=servos)
    with pytest.raises(ValueError, match="Servos.ctrl_range must hold lower <= upper"):
        sim.Servos(servos.gain, servos.bias, servos.lengths, servos.offsets, servos.ctrl_range[:, ::-1],
                   servos.force_range, servos.dof_force_range)
