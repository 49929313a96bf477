"""Fixed tendons of MuJoCo models: motors on a tendon drive several dofs with one input (the
system's moment arms), an equality of one tendon couples its joints, springs and dampers pull
along tendons as in MuJoCo's Euler integrator, and what rsmooth does not model of tendons is
refused by name."""

import equinox as eqx
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from rsmooth import sim

# A planar arm of three hinges and a slide, no contact: a motor on hinge 2, one on a tendon over
# hinges 0 and 1 (gear 2, force range 3), one on a tendon over hinge 1, the slide and hinge 0.
ARM = """
<mujoco>
  <option timestep="0.01" gravity="0 0 -9.81"/>
  <worldbody>
    <body name="a"><joint name="h0" type="hinge" axis="0 1 0" ref="0.2"/>
      <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03" contype="0" conaffinity="0"/>
      <body name="b" pos="0.3 0 0"><joint name="h1" type="hinge" axis="0 1 0"/>
        <geom type="capsule" fromto="0 0 0 0.25 0 0" size="0.03" contype="0" conaffinity="0"/>
        <body name="c" pos="0.25 0 0"><joint name="h2" type="hinge" axis="0 1 0"/>
          <geom type="capsule" fromto="0 0 0 0.2 0 0" size="0.03" contype="0" conaffinity="0"/>
          <body name="d" pos="0.2 0 0"><joint name="s" type="slide" axis="1 0 0"/>
            <geom type="box" size="0.04 0.04 0.04" contype="0" conaffinity="0"/>
          </body>
        </body>
      </body>
    </body>
  </worldbody>
  <tendon>
    <fixed name="pair"><joint joint="h0" coef="0.5"/><joint joint="h1" coef="0.5"/></fixed>
    <fixed name="mixed"><joint joint="h1" coef="1"/><joint joint="s" coef="-2"/><joint joint="h0" coef="0.3"/></fixed>
  </tendon>
  <actuator>
    <motor name="elbow" joint="h2" gear="1.5" ctrlrange="-2 2" ctrllimited="true"/>
    <motor name="pair" tendon="pair" gear="2" forcerange="-3 3" forcelimited="true"/>
    <motor name="mixed" tendon="mixed" ctrlrange="-1 1" ctrllimited="true"/>
  </actuator>
</mujoco>
"""


def _dense_ten_J(m, d):
    """MuJoCo's tendon Jacobian ``(ntendon, nv)`` (stored sparse, row by row)."""
    dense = np.zeros((m.ntendon, m.nv))
    for t in range(m.ntendon):
        start, count = m.ten_J_rowadr[t], m.ten_J_rownnz[t]
        dense[t, m.ten_J_colind[start : start + count]] = d.ten_J[start : start + count]
    return dense


def test_tendon_motors_give_mujocos_actuator_forces_and_trajectory(mujoco_and_rsmooth_trajectories):
    loaded = sim.load_mjcf(ARM)
    assert loaded.tendon_names == ("pair", "mixed") and loaded.actuator_tendons == (-1, 0, 1)
    assert loaded.actuator_dofs == (2, -1, -1)
    np.testing.assert_array_equal(loaded.tendon_moments, [[0.5, 0.5, 0, 0], [0.3, 1.0, 0, -2.0]])
    m = mujoco.MjModel.from_xml_string(ARM)
    d = mujoco.MjData(m)
    rng = np.random.default_rng(0)
    for ctrl in rng.uniform(-5.0, 5.0, size=(5, 3)):  # in and beyond the control and force ranges
        d.qpos[:] = rng.normal(size=4)
        d.ctrl[:] = ctrl
        mujoco.mj_forward(m, d)
        np.testing.assert_allclose(loaded.ctrl_to_tau(jnp.asarray(ctrl)), d.qfrc_actuator, rtol=0, atol=1e-12)
        # MuJoCo's moment arms of the tendons (ten_J) are the converted ones, at any configuration
        np.testing.assert_allclose(_dense_ten_J(m, d), loaded.tendon_moments, rtol=0, atol=1e-15)
    # The system's inputs: the elbow's torque, then the force along each driven tendon, bounded
    # by what the motors reach (gear 1.5 x 2; the pair's force range 3 x gear 2; the mixed
    # tendon's control range 1).
    system = sim.scene(loaded)
    assert system.actuation.kind == "moments" and system.nu == 3
    np.testing.assert_allclose(system.actuation.input_limit, [3.0, 6.0, 1.0])
    np.testing.assert_allclose(system.actuation.moments, [[0, 0, 1, 0], [0.5, 0.5, 0, 0], [0.3, 1.0, 0, -2.0]])
    ctrl = np.array([0.7, -1.2, 0.4])  # within every range: the inputs are gear x ctrl
    u = np.array([1.5 * 0.7, 2.0 * -1.2, 0.4])
    tau, clipped = system.generalized_forces(jnp.zeros(4), jnp.asarray(u))
    np.testing.assert_allclose(tau, loaded.ctrl_to_tau(jnp.asarray(ctrl)), rtol=0, atol=1e-14)
    assert not bool(clipped)
    # 150 steps of MuJoCo's Euler integrator under that control, the arm swinging under gravity
    _, _, xs, expected = mujoco_and_rsmooth_trajectories(ARM, None, np.zeros(4), 150, ctrl=ctrl, u=u)
    q = np.asarray(xs)[1:, :4] + np.asarray(loaded.qpos0)  # rsmooth's hinge coordinates are qpos - qpos0
    assert np.ptp(expected[:, 3]) > 0.05  # the slide moved
    np.testing.assert_allclose(q, expected, rtol=0, atol=1e-10)


# Two fingers sliding along x (no gravity), held together by an equality of the tendon of
# their difference and driven by a motor on the tendon of their mean, MuJoCo's grippers.
GRIPPER = """
<mujoco>
  <option timestep="0.01" gravity="0 0 0"/>
  <worldbody>
    <body name="thumb"><joint name="thumb" type="slide" axis="1 0 0" ref="0.1"/>
      <geom type="box" size="0.02 0.02 0.02" mass="0.3" contype="0" conaffinity="0"/></body>
    <body name="finger" pos="0 0.1 0"><joint name="finger" type="slide" axis="1 0 0"/>
      <geom type="box" size="0.02 0.02 0.02" mass="0.5" contype="0" conaffinity="0"/></body>
  </worldbody>
  <tendon>
    <fixed name="grasp"><joint joint="thumb" coef=".5"/><joint joint="finger" coef=".5"/></fixed>
    <fixed name="coupling"><joint joint="thumb" coef="-.5"/><joint joint="finger" coef=".5"/></fixed>
  </tendon>
  <equality><tendon name="coupling" tendon1="coupling" polycoef="0.01 0 0 0 0"/></equality>
  <actuator><motor name="grasp" tendon="grasp" gear="2" ctrlrange="-1 1" ctrllimited="true"/></actuator>
</mujoco>
"""


def test_an_equality_of_one_tendon_holds_its_joints_together():
    loaded = sim.load_mjcf(GRIPPER)
    # -q_thumb / 2 + q_finger / 2 = 0.01 (MuJoCo's coordinates less qpos0): the thumb follows
    # the finger, 2 cm behind it
    coupling = loaded.joint_couplings
    assert (coupling.joints, coupling.others) == ((1,), (2,))
    np.testing.assert_allclose(coupling.coefficients, [[-0.02, 1.0, 0.0, 0.0, 0.0]])
    system = sim.scene(loaded)
    # Start with the coupling open by 1 cm, at rest; a force f = 0.8 N along the grasp tendon
    # pushes each finger with f / 2. The coupling's impulses are internal (equal and opposite):
    # the momentum is f t at every step. The Baumgarte correction closes the gap by 0.8 per
    # step; then the two move as one body of 0.8 kg, at f t / 0.8.
    force, steps, h = 0.8, 200, 0.01
    x0 = system.state(jnp.array([-0.01, 0.0]), jnp.zeros(2))
    xs, infos = system.rollout(x0, jnp.full((steps, 1), force))
    xs = np.asarray(xs)
    np.testing.assert_allclose(xs[:, 2:] @ [0.3, 0.5], force * h * np.arange(steps + 1), rtol=0, atol=1e-12)
    errors = np.array([float(system.coupling_errors(jnp.asarray(x[:2]))[0]) for x in xs[[0, 150, -1]]])
    assert errors[0] == pytest.approx(0.01) and np.all(np.abs(errors[1:]) < 1e-12)
    np.testing.assert_allclose(xs[-1, 2:], [force * steps * h / 0.8] * 2, rtol=1e-9)
    assert bool(jnp.all(infos.ncp.converged))
    # The step's input Jacobian (forward mode through the moment arms and the coupling's row)
    # against central differences, with the coupling open (its correction in the step)
    x, u = jnp.asarray(xs[3]), jnp.array([force])
    _, _, fu = eqx.filter_jit(lambda s, x_, u_: s.step_and_jacobians(x_, u_))(system, x, u)
    step = eqx.filter_jit(lambda s, x_, u_: s.step(x_, u_))
    eps = 1e-6
    difference = (step(system, x, u + eps) - step(system, x, u - eps)) / (2 * eps)
    np.testing.assert_allclose(fu[:, 0], difference, rtol=0, atol=1e-8)
    # momentum f t: dv/du = h (the same for both fingers once coupled) on the combined mass
    np.testing.assert_allclose(np.asarray(fu)[2:, 0] @ [0.3, 0.5], h, rtol=1e-12)


def _tendon_model(tendon: str, equality: str = "", joint_extra: str = "", actuator: str = "") -> str:
    return f"""
<mujoco>
  <worldbody>
    <body name="a"><joint name="j0" type="hinge" {joint_extra}/><geom type="sphere" size="0.1" contype="0" conaffinity="0"/>
      <site name="s0"/>
      <body name="b" pos="0.3 0 0"><joint name="j1" type="hinge"/><geom type="sphere" size="0.1" contype="0" conaffinity="0"/>
        <site name="s1"/>
        <body name="c" pos="0.3 0 0"><joint name="j2" type="hinge"/><geom type="sphere" size="0.1" contype="0" conaffinity="0"/>
        </body>
      </body>
    </body>
  </worldbody>
  <tendon>{tendon}
    <fixed name="other"><joint joint="j2" coef="1"/></fixed>
  </tendon>
  <equality>{equality}</equality>
  <actuator>{actuator}</actuator>
</mujoco>"""


FIXED = '<fixed name="t" {}><joint joint="j0" coef="1"/><joint joint="j1" coef="-1"/></fixed>'


@pytest.mark.parametrize(
    "text, message",
    [
        (_tendon_model('<spatial name="t"><site site="s0"/><site site="s1"/></spatial>'), "tendon 't'.*spatial"),
        (_tendon_model(FIXED.format('limited="true" range="-1 1"')), "tendon 't'.*length limits"),
        (_tendon_model(FIXED.format('armature="0.1"')), "tendon 't'.*armature"),
        (
            _tendon_model(FIXED.format(""), '<tendon name="e" tendon1="t" tendon2="other"/>'),
            "equality 'e' on tendon 't' couples it to a second tendon",
        ),
        (
            _tendon_model(
                '<fixed name="t"><joint joint="j0" coef="1"/><joint joint="j1" coef="1"/><joint joint="j2" coef="1"/></fixed>',
                '<tendon name="e" tendon1="t"/>',
            ),
            "equality 'e' on tendon 't'.*3 joints",
        ),
    ],
)
def test_what_rsmooth_does_not_model_of_tendons_is_refused_by_name(text, message):
    with pytest.raises(ValueError, match=message):
        sim.load_mjcf(text)


def test_a_tendon_motor_on_a_dof_with_a_bounded_total_force_is_refused_by_name():
    text = _tendon_model(
        FIXED.format(""), joint_extra='actuatorfrcrange="-1 1" actuatorfrclimited="true"',
        actuator='<motor name="m" tendon="t"/>',
    )
    loaded = sim.load_mjcf(text)  # converted: MuJoCo's forces are ctrl_to_tau's
    with pytest.raises(ValueError, match="actuator 'm' drives tendon 't', which moves dof 0"):
        sim.scene(loaded)


def test_moment_arms_of_the_wrong_shape_are_refused():
    with pytest.raises(ValueError, match="actuation moments are given with kind 'moments'"):
        sim.Actuation("joints", jnp.ones(1), dofs=(0,), moments=jnp.ones((1, 2)))
    with pytest.raises(ValueError, match=r"actuation moments must have shape \(nu, nv\)"):
        sim.Actuation("moments", jnp.ones(2), moments=jnp.ones(2))
    system = sim.scene(GRIPPER)
    with pytest.raises(ValueError, match=r"actuation moments must have shape \(nu, nv\) = \(1, 2\)"):
        system.__class__(**{**vars(system), "actuation": sim.Actuation("moments", jnp.ones(1), moments=jnp.ones((1, 3)))})


# The arm above with springs and dampers on its tendons: one about a rest band (no force while
# its length is within it), one about a single length.
SPRUNG_ARM = ARM.replace(
    '<fixed name="pair">', '<fixed name="pair" stiffness="4" springlength="0.05 0.15" damping="0.3">'
).replace('<fixed name="mixed">', '<fixed name="mixed" stiffness="2.5" springlength="0.1" damping="0.05">')


def test_tendon_springs_and_dampers_step_as_mujocos_euler_integrator(mujoco_and_rsmooth_trajectories):
    # From a swinging start, no input: the springs pull through their bands, the dampers
    # (explicit in MuJoCo's Euler integrator, unlike a joint's own damping) slow the arm.
    qvel = np.array([1.5, -2.0, 0.5, 0.3])
    system, loaded, xs, expected = mujoco_and_rsmooth_trajectories(SPRUNG_ARM, None, qvel, 200)
    tendons = system.joints.tendons
    np.testing.assert_allclose(tendons.spring_length, [[0.05, 0.15], [0.1, 0.1]])
    q = np.asarray(xs)[1:, :4] + np.asarray(loaded.qpos0)
    np.testing.assert_allclose(q, expected, rtol=0, atol=1e-10)
    # the lengths are MuJoCo's ten_length, and the first tendon crossed its band
    m = mujoco.MjModel.from_xml_string(SPRUNG_ARM)
    d = mujoco.MjData(m)
    lengths = []
    for x in np.asarray(xs)[::20]:
        d.qpos[:] = x[:4] + np.asarray(loaded.qpos0)
        mujoco.mj_kinematics(m, d)
        mujoco.mj_tendon(m, d)
        np.testing.assert_allclose(system.tendon_lengths(jnp.asarray(x[:4])), d.ten_length, rtol=0, atol=1e-14)
        lengths.append(d.ten_length[0])
    assert min(lengths) < 0.05 or max(lengths) > 0.15
    # the springs' forces are minus the gradient of their energy (zero within the band)
    for x in np.asarray(xs)[::40]:
        q_ = jnp.asarray(x[:4])
        np.testing.assert_allclose(system.spring_forces(q_), -jax.grad(system.spring_energy)(q_), rtol=0, atol=1e-12)
    within = jnp.zeros(4).at[0].set(0.2)  # pair tendon at 0.1 + 0.5 qpos0_h0: inside its band
    assert float(system._tendon_stretch(within)[0]) == 0.0


def test_the_step_derivative_through_tendon_springs_and_dampers_matches_finite_differences():
    system = sim.scene(SPRUNG_ARM)
    x = jnp.array([0.3, -0.4, 0.2, 0.05, 1.0, -0.5, 0.8, 0.2])
    u = jnp.zeros(system.nu)
    _, fx, _ = eqx.filter_jit(lambda s, x_, u_: s.step_and_jacobians(x_, u_))(system, x, u)
    step = eqx.filter_jit(lambda s, x_, u_: s.step(x_, u_))
    eps = 1e-6
    columns = [(step(system, x + eps * e, u) - step(system, x - eps * e, u)) / (2 * eps) for e in jnp.eye(8)]
    np.testing.assert_allclose(fx, jnp.stack(columns, axis=1), rtol=0, atol=1e-7)


# A 2 kg cart on a slide, pushed along it by a motor, with dry friction of 1 N along a tendon of
# twice its coordinate: the tendon holds generalized forces up to 2 x 1 N.
CART = """
<mujoco>
  <option timestep="0.01" gravity="0 0 -9.81"/>
  <worldbody>
    <body name="cart"><joint name="x" type="slide" axis="1 0 0"/>
      <geom type="box" size="0.1 0.1 0.1" mass="2" contype="0" conaffinity="0"/></body>
  </worldbody>
  <tendon><fixed name="t" frictionloss="1"><joint joint="x" coef="2"/></fixed></tendon>
  <actuator><motor name="push" joint="x"/></actuator>
</mujoco>
"""


def test_a_tendons_dry_friction_holds_the_cart_below_its_force_and_slows_it_beyond():
    system = sim.scene(CART)
    assert system.joints.tendons.frictional == (0,)
    np.testing.assert_allclose(system.joints.tendons.frictionloss, [1.0])
    rollout = eqx.filter_jit(lambda s, x, us: s.rollout(x, us))
    steps, h, mass = 50, 0.01, 2.0
    x0 = system.initial_state()
    # 1.5 N: held, the friction impulse along the tendon 1.5 h / 2 (within its bound h)
    xs, infos = rollout(system, x0, jnp.full((steps, 1), 1.5))
    np.testing.assert_allclose(np.asarray(xs), 0.0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(infos.joint_impulse), -1.5 * h / 2, rtol=1e-9)
    # 3 N: it slides, at (3 - 2 x 1) / 2 kg = 0.5 m/s^2, the impulse on its bound
    xs, infos = rollout(system, x0, jnp.full((steps, 1), 3.0))
    np.testing.assert_allclose(np.asarray(xs)[1:, 1], (3.0 - 2.0) / mass * h * np.arange(1, steps + 1), rtol=1e-9)
    np.testing.assert_allclose(np.asarray(infos.joint_impulse), -h, rtol=1e-9)
    assert bool(jnp.all(infos.ncp.converged))
    with pytest.raises(ValueError, match="tendons' friction are solved by the hard-contact NCP"):
        system.with_options(contact=sim.SpringDamper(stiffness=1e4, damping=10.0, friction=0.5))
