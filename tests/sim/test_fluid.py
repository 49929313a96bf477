"""MuJoCo's inertia-box fluid model (`sim.Fluid`): the generalized forces equal MuJoCo's
`qfrc_fluid` on random states, a body in a fluid steps as MuJoCo's Euler integrator, and a
body falling in a viscous fluid reaches the Stokes terminal velocity."""

import equinox as eqx
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from rsmooth import sim

# A floating box carrying a chain of a ball joint and a hinge, its inertial frames turned and
# off its bodies' origins, in a dense, viscous fluid with wind; no contact.
SWIMMER = """
<mujoco>
  <option timestep="0.005" density="1000" viscosity="0.5" wind="0.3 -0.2 0.1"/>
  <worldbody>
    <body name="head" pos="0 0 1"><freejoint/>
      <geom type="box" size="0.1 0.05 0.03" contype="0" conaffinity="0"/>
      <body name="neck" pos="0.1 0 0"><joint name="ball" type="ball"/>
        <inertial pos="0.1 0.01 0" quat="0.9 0.1 0.3 0.2" mass="0.4" diaginertia="0.002 0.003 0.004"/>
        <geom type="capsule" fromto="0 0 0 0.2 0 0" size="0.02" contype="0" conaffinity="0"/>
        <body name="tail" pos="0.2 0 0"><joint name="fin" type="hinge" axis="0 0 1"/>
          <geom type="box" size="0.08 0.04 0.005" pos="0.08 0 0" contype="0" conaffinity="0"/>
        </body>
      </body>
    </body>
  </worldbody>
</mujoco>
"""


def test_fluid_forces_are_mujocos_on_random_states():
    loaded = sim.load_mjcf(SWIMMER)
    assert loaded.fluid is not None and len(loaded.fluid.frames) == 3
    system = sim.scene(loaded, floor=False)
    m = mujoco.MjModel.from_xml_string(SWIMMER)
    d = mujoco.MjData(m)
    rng = np.random.default_rng(0)
    forces = jax.jit(lambda q, v: system.fluid_forces(q, v))
    for _ in range(8):
        d.qpos[:3] = rng.normal(size=3)
        d.qpos[3:7] = rng.normal(size=4)
        d.qpos[7:11] = rng.normal(size=4)
        d.qpos[11] = rng.uniform(-2, 2)
        mujoco.mj_normalizeQuat(m, d.qpos)
        d.qvel[:] = 2.0 * rng.normal(size=m.nv)
        mujoco.mj_forward(m, d)
        q = loaded.qpos_to_q(jnp.asarray(d.qpos))
        v = loaded.qvel_to_v(jnp.asarray(d.qpos), jnp.asarray(d.qvel))
        ours = forces(q, v)
        # the same power: MuJoCo's qfrc . qvel = ours . v (velocity conventions differ)
        np.testing.assert_allclose(float(ours @ v), float(d.qfrc_fluid @ d.qvel), rtol=1e-10)
        # the hinge's generalized force is the same number in both
        np.testing.assert_allclose(float(ours[-1]), d.qfrc_fluid[-1], rtol=1e-10, atol=1e-12)


def test_a_swimmer_steps_as_mujocos_euler_integrator(mujoco_and_rsmooth_trajectories):
    # hinges only (MuJoCo's qpos is rsmooth's q), no gravity: the fluid alone slows the chain
    text = SWIMMER.replace("<freejoint/>", "").replace('<joint name="ball" type="ball"/>', '<joint name="yaw" type="hinge" axis="0 1 0"/>')
    text = text.replace('<option timestep="0.005"', '<option timestep="0.005" gravity="0 0 0"')
    system, loaded, xs, expected = mujoco_and_rsmooth_trajectories(text, None, np.array([4.0, -6.0]), 200)
    np.testing.assert_allclose(np.asarray(xs)[1:, :2] + np.asarray(loaded.qpos0), expected, rtol=0, atol=1e-10)
    assert np.all(np.abs(np.asarray(xs)[-1, 2:]) < [4.0, 6.0])  # slowed
    # the step's Jacobians hold the fluid's dependence on the state (by forward mode: the
    # closed-form derivatives of contact-free systems do not)
    x, u = xs[50], jnp.zeros(system.nu)
    _, fx, _ = eqx.filter_jit(lambda s, x_, u_: s.step_and_jacobians(x_, u_))(system, x, u)
    expected_fx = eqx.filter_jit(lambda s, x_, u_: jax.jacfwd(s.step)(x_, u_))(system, x, u)
    np.testing.assert_allclose(np.asarray(fx), np.asarray(expected_fx), rtol=0, atol=1e-12)


def test_a_ball_sinks_at_the_stokes_terminal_velocity():
    # A 50 g ball of radius 1 cm on a vertical slide in a viscous fluid: its inertia box has the
    # side r sqrt(12 / 5) (I = 2/5 m r^2 about each axis), its drag 3 pi d beta v, so it sinks at
    # m g / (3 pi d beta), where explicit Euler steps settle exactly.
    radius, mass, beta, g = 0.01, 0.05, 2.0, 9.81
    text = f"""<mujoco><option timestep="0.01" viscosity="{beta}"/><worldbody>
      <body><joint type="slide" axis="0 0 1"/><geom type="sphere" size="{radius}" mass="{mass}" contype="0" conaffinity="0"/></body>
    </worldbody></mujoco>"""
    system = sim.scene(text, floor=False)
    side = radius * np.sqrt(12 / 5)
    np.testing.assert_allclose(system.joints.fluid.box, [[side] * 3], rtol=1e-12)
    xs, _ = eqx.filter_jit(lambda s, x: s.rollout(x, jnp.zeros((600, 0))))(system, system.initial_state())
    np.testing.assert_allclose(float(xs[-1, 1]), -mass * g / (3 * np.pi * side * beta), rtol=1e-9)


def test_the_ellipsoid_fluid_model_and_bad_fluids_are_refused_by_name():
    with pytest.raises(ValueError, match="takes the ellipsoid fluid model"):
        sim.load_mjcf(SWIMMER.replace('<geom type="capsule"', '<geom type="capsule" fluidshape="ellipsoid"'))
    with pytest.raises(ValueError, match="Fluid.density must be >= 0"):
        sim.Fluid(frames=(1,), rotations=jnp.eye(3)[None], offsets=jnp.zeros((1, 3)), box=jnp.ones((1, 3)),
                  density=jnp.asarray(-1.0), viscosity=jnp.asarray(0.0), wind=jnp.zeros(3))
    system = sim.scene(SWIMMER, floor=False)
    with pytest.raises(ValueError, match="joints.fluid.frames"):
        fluid = system.joints.fluid
        system.with_fluid(sim.Fluid(("nowhere",) * 3, fluid.rotations, fluid.offsets, fluid.box, fluid.density, fluid.viscosity, fluid.wind))
