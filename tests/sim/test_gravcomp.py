"""Gravity compensation of bodies (`sim.GravityCompensation`, MuJoCo's body `gravcomp`): the
generalized forces equal MuJoCo's `qfrc_gravcomp` on random states, an arm steps as MuJoCo's
Euler integrator, a fully compensated body floats, and compensation through actuators is refused
by name."""

import equinox as eqx
import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from rsmooth import sim

# A floating box, half compensated, carrying a chain of a ball joint and a hinge, the first
# fully compensated, its inertial frame off its origin; no contact.
CHAIN = """
<mujoco>
  <option timestep="0.005"/>
  <worldbody>
    <body name="base" pos="0 0 1" gravcomp="0.5"><freejoint/>
      <geom type="box" size="0.1 0.05 0.03" contype="0" conaffinity="0"/>
      <body name="upper" pos="0.1 0 0" gravcomp="1"><joint name="shoulder" type="ball"/>
        <inertial pos="0.1 0.01 0" quat="0.9 0.1 0.3 0.2" mass="0.4" diaginertia="0.002 0.003 0.004"/>
        <body name="lower" pos="0.2 0 0" gravcomp="0.3"><joint name="elbow" type="hinge" axis="0 1 0"/>
          <geom type="capsule" fromto="0 0 0 0.2 0 0" size="0.02" contype="0" conaffinity="0"/>
        </body>
      </body>
    </body>
  </worldbody>
</mujoco>
"""


def test_gravity_compensation_forces_are_mujocos_on_random_states():
    loaded = sim.load_mjcf(CHAIN)
    system = sim.scene(loaded, floor=False)
    m = mujoco.MjModel.from_xml_string(CHAIN)
    np.testing.assert_allclose(np.asarray(loaded.gravcomp.masses), [0.5, 1.0, 0.3] * m.body_mass[1:], rtol=1e-15)
    d = mujoco.MjData(m)
    rng = np.random.default_rng(0)
    forces = eqx.filter_jit(lambda s, q: s.gravcomp_forces(q))
    for _ in range(6):
        d.qpos[:3] = rng.normal(size=3)
        d.qpos[3:11] = rng.normal(size=8)
        d.qpos[11] = rng.uniform(-2, 2)
        mujoco.mj_normalizeQuat(m, d.qpos)
        d.qvel[:] = rng.normal(size=m.nv)
        mujoco.mj_forward(m, d)
        q = loaded.qpos_to_q(jnp.asarray(d.qpos))
        v = loaded.qvel_to_v(jnp.asarray(d.qpos), jnp.asarray(d.qvel))
        ours = forces(system, q)
        # the same power (velocity conventions differ), and the hinge's force is the same number
        np.testing.assert_allclose(float(ours @ v), float(d.qfrc_gravcomp @ d.qvel), rtol=1e-10)
        np.testing.assert_allclose(float(ours[-1]), d.qfrc_gravcomp[-1], rtol=1e-10, atol=1e-12)


def test_a_compensated_arm_steps_as_mujocos_euler_integrator(mujoco_and_rsmooth_trajectories):
    # hinges only (MuJoCo's qpos is rsmooth's q): the arm falls slower than it would uncompensated
    text = CHAIN.replace("<freejoint/>", "").replace('type="ball"/>', 'type="hinge" axis="1 0 0"/>')
    system, loaded, xs, expected = mujoco_and_rsmooth_trajectories(text, None, np.array([0.5, -1.0]), 100)
    np.testing.assert_allclose(np.asarray(xs)[1:, :2] + np.asarray(loaded.qpos0), expected, rtol=0, atol=1e-10)
    # the step's Jacobians hold the compensation's dependence on the configuration
    x, u = xs[50], jnp.zeros(system.nu)
    _, fx, _ = eqx.filter_jit(lambda s, x_, u_: s.step_and_jacobians(x_, u_))(system, x, u)
    expected_fx = eqx.filter_jit(lambda s, x_, u_: jax.jacfwd(s.step)(x_, u_))(system, x, u)
    np.testing.assert_allclose(np.asarray(fx), np.asarray(expected_fx), rtol=0, atol=1e-12)


def test_a_fully_compensated_body_floats_and_a_half_compensated_one_falls_at_half_g():
    text = """<mujoco><option timestep="0.01"/><worldbody>
      <body name="a" pos="0 0 1" gravcomp="1"><freejoint/><geom type="box" size="0.1 0.2 0.05" pos="0.1 0 0" contype="0" conaffinity="0"/></body>
      <body name="b" pos="1 0 1" gravcomp="0.5"><freejoint/><geom type="sphere" size="0.1" contype="0" conaffinity="0"/></body>
    </worldbody></mujoco>"""
    system = sim.scene(text, floor=False)
    x0 = system.initial_state()
    steps, h, g = 30, 0.01, 9.81
    xs, _ = eqx.filter_jit(lambda s, x: s.rollout(x, jnp.zeros((steps, s.nu))))(system, x0)
    np.testing.assert_allclose(np.asarray(xs)[:, :7], np.asarray(x0)[None, :7].repeat(steps + 1, 0), rtol=0, atol=1e-12)
    # semi-implicit Euler at g / 2: z_n = z_0 - (g / 2) h^2 n (n + 1) / 2
    n = np.arange(steps + 1)
    np.testing.assert_allclose(np.asarray(xs)[:, 9], 1.0 - 0.5 * g * h**2 * n * (n + 1) / 2, rtol=0, atol=1e-12)
