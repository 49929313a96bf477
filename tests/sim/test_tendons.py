"""Tendons of MuJoCo models: motors on a fixed tendon drive several dofs with one input (the
system's moment arms), an equality of one tendon couples its joints, springs and dampers pull
along fixed and spatial tendons as in MuJoCo's Euler integrator, length limits hold (a string),
and what rsmooth does not model of tendons is refused by name."""

import dataclasses

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
    <body name="a"><joint name="j0" type="hinge" {joint_extra}/><geom name="g" type="sphere" size="0.1" contype="0" conaffinity="0"/>
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
        (
            _tendon_model('<spatial name="t"><site site="s1"/><geom geom="g" sidesite="s0"/><site site="s1"/></spatial>'),
            "tendon 't'.*side site 's0' of its wrap around geom 'g' is inside the geom",
        ),
        (
            _tendon_model('<spatial name="t"><site site="s0"/><site site="s1"/></spatial>', actuator='<motor name="m" tendon="t"/>'),
            "tendon 't'.*spatial tendon driven by a motor",
        ),
        (_tendon_model(FIXED.format('armature="0.1"')), "tendon 't'.*armature"),
        (
            _tendon_model(FIXED.format(""), '<tendon name="e" tendon1="t" tendon2="other"/>'),
            "equality 'e' on tendon 't' couples it to a second tendon",
        ),
    ],
)
def test_what_rsmooth_does_not_model_of_tendons_is_refused_by_name(text, message):
    with pytest.raises(ValueError, match=message):
        sim.load_mjcf(text)


THREE = '<fixed name="t"><joint joint="j0" coef="1"/><joint joint="j1" coef="0.5"/><joint joint="j2" coef="-2"/></fixed>'


def test_an_equality_of_a_tendon_on_three_joints_holds_its_length():
    """MuJoCo's ``L - L0 = c_0`` on a tendon over three hinges: a bilateral row along the
    tendon. From rest with the equality open by 0.1 rad, each step closes the Baumgarte
    fraction of the gap (the tendon is linear in the coordinates, the hinges integrate
    linearly), while a motor on j2 turns the joints."""
    text = _tendon_model(THREE, '<tendon name="e" tendon1="t" polycoef="0.1 0 0 0 0"/>', actuator='<motor name="m" joint="j2"/>')
    loaded = sim.load_mjcf(text)
    assert loaded.joint_couplings is None and loaded.tendons.equalities == (0,)
    np.testing.assert_allclose(loaded.tendons.equality_length[0], mujoco.MjModel.from_xml_string(text).tendon_length0[0] + 0.1)
    system = sim.scene(loaded)
    steps = 60
    xs, infos = eqx.filter_jit(system.rollout)(system.initial_state(), jnp.full((steps, 1), 0.3))
    assert bool(jnp.all(infos.ncp.converged))
    gaps = np.array([float(system.tendon_lengths(x[:3])[0] - loaded.tendons.equality_length[0]) for x in xs])
    np.testing.assert_allclose(gaps, -0.1 * 0.8 ** np.arange(steps + 1), rtol=1e-9, atol=1e-13)
    # the step's Jacobians through the row, against central differences
    x, u = xs[5], jnp.array([0.3])
    _, fx, fu = eqx.filter_jit(lambda s, x_, u_: s.step_and_jacobians(x_, u_))(system, x, u)
    step = eqx.filter_jit(lambda s, x_, u_: s.step(x_, u_))
    eps = 1e-6
    columns = [(step(system, x + eps * e, u) - step(system, x - eps * e, u)) / (2 * eps) for e in jnp.eye(6)]
    np.testing.assert_allclose(fx, jnp.stack(columns, axis=1), rtol=0, atol=1e-7)
    np.testing.assert_allclose(fu[:, 0], (step(system, x, u + eps) - step(system, x, u - eps)) / (2 * eps), rtol=0, atol=1e-7)


ROD = """
<mujoco>
  <option timestep="0.001"/>
  <worldbody>
    <site name="anchor" pos="0 0 1"/>
    <body name="ball" pos="{x} 0 0.5">
      <joint name="x" type="slide" axis="1 0 0"/><joint name="z" type="slide" axis="0 0 1"/>
      <geom type="sphere" size="0.02" mass="1" contype="0" conaffinity="0"/><site name="hook"/>
    </body>
  </worldbody>
  <tendon><spatial name="rod"><site site="anchor"/><site site="hook"/></spatial></tendon>
  <equality><tendon name="hold" tendon1="rod"/></equality>
</mujoco>
"""


def test_a_spatial_tendon_held_at_its_length_is_a_pendulums_rod():
    """A point mass on two slides hung from a fixed site by a spatial tendon held at its length
    (MuJoCo's tendon equality): released at rest 0.3 rad from the vertical it swings with the
    rigid pendulum's period, 4 sqrt(L / g) K(sin^2(theta_0 / 2)), the rod's length held."""
    from scipy.special import ellipk

    length, theta = 0.5 / np.cos(0.3), 0.3
    system = sim.scene(ROD.format(x=0.5 * np.tan(theta)))
    assert system.joints.tendons.equalities == (0,)
    steps, h = 3000, 0.001
    xs, infos = eqx.filter_jit(system.rollout)(system.initial_state(), jnp.zeros((steps, 0)))
    assert bool(jnp.all(infos.ncp.converged))
    # held at the velocity level, the length grows by the chord's (h v)^2 / 2 L a step, which the
    # correction (a fifth of the gap a step) balances at five times that, v at most the speed
    # at the bottom (10 % margin)
    speed = np.sqrt(2 * 9.81 * length * (1 - np.cos(theta)))
    lengths = jax.vmap(lambda x: system.tendon_lengths(x[:2])[0])(xs)
    np.testing.assert_allclose(lengths, length, rtol=0, atol=1.1 * 5 * (h * speed) ** 2 / (2 * length))
    # the period from the times the ball passes under the anchor moving the same way
    x = 0.5 * np.tan(theta) + np.asarray(xs[:, 0])  # the slide moves the ball from its place in the file
    crossings = np.flatnonzero((x[:-1] > 0) & (x[1:] <= 0))
    times = h * (crossings + x[crossings] / (x[crossings] - x[crossings + 1]))
    period = 4 * np.sqrt(length / 9.81) * ellipk(np.sin(theta / 2) ** 2)
    assert len(times) >= 2
    np.testing.assert_allclose(np.diff(times), period, rtol=1e-4)


def test_a_tendons_length_row_is_the_joint_coupling_of_a_tendon_on_two_joints():
    """On two joints the loader makes the equality a joint coupling; held as a tendon length
    instead, the step is the same (the same constraint, its row and correction scaled alike)."""
    text = _tendon_model(FIXED.format(""), '<tendon name="e" tendon1="t" polycoef="0.05 0 0 0 0"/>',
                         actuator='<motor name="m" joint="j1"/>')
    loaded = sim.load_mjcf(text)
    coupled = sim.scene(loaded)
    assert loaded.joint_couplings.joints == (1,) and loaded.tendons is None
    lengths = np.zeros((2, 3))
    lengths[0, :2] = [1.0, -1.0]
    lengths[1, 2] = 1.0
    tendons = sim.Tendons(lengths=jnp.asarray(lengths), moments=jnp.asarray(lengths), offsets=jnp.zeros(2),
                          stiffness=jnp.zeros(2), spring_length=jnp.zeros((2, 2)), damping=jnp.zeros(2),
                          equalities=(0,), equality_length=jnp.array([0.05, 0.0]))
    held = dataclasses.replace(coupled, joints=dataclasses.replace(coupled.joints, couplings=None)).with_tendons(tendons)
    x0 = coupled.state(jnp.array([0.2, -0.1, 0.3]), jnp.array([0.5, 0.1, -0.4]))
    us = jnp.full((40, 1), 0.2)
    xs_coupled, _ = eqx.filter_jit(coupled.rollout)(x0, us)
    xs_held, _ = eqx.filter_jit(held.rollout)(x0, us)
    np.testing.assert_allclose(xs_held, xs_coupled, rtol=0, atol=1e-10)
    with pytest.raises(ValueError, match="Tendons.equalities needs Tendons.equality_length"):
        dataclasses.replace(tendons, equality_length=None)


def test_a_tendon_motor_on_a_dof_with_a_bounded_total_force_is_driven_by_its_control():
    """The dof's bound is on the sum of the motors' forces along it, which bounds on each input
    cannot express: the motors are driven by their controls and the sum clipped, as MuJoCo does."""
    text = _tendon_model(
        FIXED.format(""), joint_extra='actuatorfrcrange="-1 1" actuatorfrclimited="true"',
        actuator='<motor name="m" tendon="t" gear="3"/><motor name="n" joint="j1"/>',
    )
    system = sim.scene(text)
    assert system.actuation.kind == "servos" and system.nu == 2
    m = mujoco.MjModel.from_xml_string(text)
    d = mujoco.MjData(m)
    forces = jax.jit(lambda q, v, u: system.generalized_forces(q, u, None, v)[0])
    loaded = sim.load_mjcf(text)
    for ctrl in ([0.2, 0.0], [1.0, -0.5], [-2.0, 4.0]):  # the first within dof 0's bound, then beyond it
        d.ctrl[:] = ctrl
        mujoco.mj_forward(m, d)
        q, v = loaded.qpos_to_q(jnp.asarray(d.qpos)), jnp.asarray(d.qvel)
        np.testing.assert_allclose(forces(q, v, jnp.asarray(ctrl)), d.qfrc_actuator, rtol=1e-12, atol=1e-12)
    assert abs(d.qfrc_actuator[0]) == 1.0  # clipped at dof 0's bound


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
    assert float(system._tendon_stretch(system.tendon_lengths(within))[0]) == 0.0


def test_the_step_derivative_through_tendon_springs_and_dampers_matches_finite_differences(
        state_jacobian_is_central_differences):
    state_jacobian_is_central_differences(sim.scene(SPRUNG_ARM), jnp.array([0.3, -0.4, 0.2, 0.05, 1.0, -0.5, 0.8, 0.2]))


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


# A floating body carrying a chain of a ball joint and two hinges, with a spatial tendon from a
# world site through sites on the floating body and the chain's last link (and a second one
# between two sites of one link, whose length never changes).
SPATIAL = """
<mujoco>
  <option timestep="0.01" gravity="0 0 0"/>
  <worldbody>
    <site name="anchor" pos="0.2 -0.1 0.5"/>
    <body name="base" pos="0 0 1"><freejoint/>
      <geom type="box" size="0.1 0.08 0.05" contype="0" conaffinity="0"/>
      <site name="on_base" pos="0.1 0.05 -0.02"/>
      <body name="upper" pos="0.1 0 0"><joint name="shoulder" type="ball"/>
        <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03" contype="0" conaffinity="0"/>
        <site name="mid" pos="0.15 0.03 0"/>
        <body name="lower" pos="0.3 0 0"><joint name="elbow" type="hinge" axis="0 1 0"/>
          <joint name="twist" type="hinge" axis="1 0 0"/>
          <geom type="capsule" fromto="0 0 0 0.25 0 0" size="0.03" contype="0" conaffinity="0"/>
          <site name="tip" pos="0.25 0 0.02"/><site name="tip2" pos="0.1 0.02 0"/>
        </body>
      </body>
    </body>
  </worldbody>
  <tendon>
    <spatial name="cable" stiffness="3" damping="0.2">
      <site site="anchor"/><site site="on_base"/><site site="mid"/><site site="tip"/>
    </spatial>
    <spatial name="rigid" frictionloss="0.1"><site site="tip"/><site site="tip2"/></spatial>
  </tendon>
</mujoco>
"""


def test_spatial_tendon_lengths_and_rates_are_mujocos(getkey):
    # On random configurations and velocities of a floating body with a ball joint: the
    # lengths are MuJoCo's ten_length, and the moments times rsmooth's velocity equal
    # ten_J times MuJoCo's qvel (the length's rate, whatever each side's velocity convention).
    loaded = sim.load_mjcf(SPATIAL)
    tendons = loaded.tendons
    assert tendons.spatial == (0, 1) and [len(path) for path in tendons.paths] == [4, 2]
    system = sim.scene(loaded, floor=False)
    m = mujoco.MjModel.from_xml_string(SPATIAL)
    d = mujoco.MjData(m)
    rng = np.random.default_rng(0)
    geometry = jax.jit(lambda q: (system.tendon_lengths(q), system.tendon_moments(q)))
    for _ in range(6):
        d.qpos[:3] = rng.normal(size=3)
        d.qpos[3:7] = rng.normal(size=4) / 2
        d.qpos[7:11] = rng.normal(size=4)
        d.qpos[11:] = rng.uniform(-2, 2, size=2)
        mujoco.mj_normalizeQuat(m, d.qpos)
        d.qvel[:] = rng.normal(size=m.nv)
        mujoco.mj_forward(m, d)
        q = loaded.qpos_to_q(jnp.asarray(d.qpos))
        v = loaded.qvel_to_v(jnp.asarray(d.qpos), jnp.asarray(d.qvel))
        length, moments = geometry(q)
        np.testing.assert_allclose(length, d.ten_length, rtol=0, atol=1e-12)
        np.testing.assert_allclose(moments @ v, d.ten_J.reshape(2, m.nv) @ d.qvel, rtol=0, atol=1e-12)
    assert abs(float(moments[1] @ v)) < 1e-12  # two sites on one link: no rate
    # on the hinges, the moments are the lengths' derivatives in the coordinates
    np.testing.assert_allclose(moments[:, -2:], jax.jacfwd(system.tendon_lengths)(q)[:, -2:], rtol=0, atol=1e-12)


def test_spatial_tendon_springs_and_dampers_step_as_mujocos_euler_integrator(
        mujoco_and_rsmooth_trajectories, state_jacobian_is_central_differences):
    # The chain of SPATIAL without its floating base (hinges only, so that MuJoCo's qpos is
    # rsmooth's q): the cable's spring and damper pull the arm as in MuJoCo's Euler steps.
    text = SPATIAL.replace('<freejoint/>', '').replace('<joint name="shoulder" type="ball"/>', '<joint name="shoulder" type="hinge" axis="0 0 1"/>')
    text = text.replace(' frictionloss="0.1"', '')
    qvel = np.array([1.5, -2.0, 3.0])
    system, loaded, xs, expected = mujoco_and_rsmooth_trajectories(text, None, qvel, 150)
    np.testing.assert_allclose(np.asarray(xs)[1:, :3] + np.asarray(loaded.qpos0), expected, rtol=0, atol=1e-10)
    # the springs' forces are minus the gradient of their energy
    q = jnp.asarray(np.asarray(xs)[40, :3])
    np.testing.assert_allclose(system.spring_forces(q), -jax.grad(system.spring_energy)(q), rtol=0, atol=1e-12)
    # the step's state Jacobian (moments that vary with q) against central differences
    state_jacobian_is_central_differences(system, jnp.asarray(np.asarray(xs)[40]))


# A 0.2 kg ball on two slides (x, z) hanging from a world site by a string of 0.5 m (a spatial
# tendon limited to [0, 0.5], as dm_control's ball in cup), no gravity on the ball's rotation.
STRING = """
<mujoco>
  <option timestep="0.002" gravity="0 0 -9.81"/>
  <worldbody>
    <site name="hook" pos="0 0 1"/>
    <body name="ball"><joint name="x" type="slide" axis="1 0 0"/><joint name="z" type="slide" axis="0 0 1"/>
      <geom type="sphere" size="0.02" mass="0.2" contype="0" conaffinity="0"/><site name="knot"/>
    </body>
  </worldbody>
  <tendon><spatial name="string" limited="true" range="0 0.5"><site site="hook"/><site site="knot"/></spatial></tendon>
</mujoco>
"""


def test_a_string_holds_a_hanging_ball_and_swings_it_as_a_pendulum():
    system = sim.scene(STRING, floor=False)
    tendons = system.joints.tendons
    assert tendons.limits == ((0, -1),)  # the lower limit (0) cannot be reached: left out
    assert system.num_limits == 1 and system.num_contacts == 1
    length, mass, h, g = 0.5, 0.2, 0.002, 9.81
    rollout = eqx.filter_jit(lambda s, x, us: s.rollout(x, us))
    # Hanging still, taut: the string's impulse is the ball's weight times the step.
    x0 = system.state(jnp.array([0.0, 1.0 - length]), jnp.zeros(2))
    xs, infos = rollout(system, x0, jnp.zeros((50, 0)))
    np.testing.assert_allclose(np.asarray(xs), np.asarray(x0)[None].repeat(51, axis=0), rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(infos.impulse)[:, -1], mass * g * h, rtol=1e-9)
    # Released taut at 0.2 rad: a pendulum whose period is 2 pi sqrt(L / g) (1 + theta0^2 / 16)
    # (to second order); the string stays taut (its impulse positive) and stretches only by the
    # time stepping's drift off the circle, h^2 v^2 / (2 L) a step, which the contact's
    # Baumgarte correction (a fraction of the gap a step) pulls back: their balance bounds it.
    theta0 = 0.2
    x0 = system.state(jnp.array([length * np.sin(theta0), 1.0 - length * np.cos(theta0)]), jnp.zeros(2))
    steps = 1200
    xs, infos = rollout(system, x0, jnp.zeros((steps, 0)))
    q = np.asarray(xs)[:, :2]
    lengths = np.hypot(q[:, 0], 1.0 - q[:, 1])
    speed = np.sqrt(2 * g * length * (1 - np.cos(theta0)))  # at the bottom
    assert lengths.max() - length < 1.1 * h**2 * speed**2 / (2 * length) / float(system.baumgarte)
    assert np.all(np.asarray(infos.impulse)[:, -1] > 0) and bool(jnp.all(infos.ncp.converged))
    downward = np.flatnonzero((q[:-1, 0] > 0) & (q[1:, 0] <= 0))  # crossings from the right
    crossings = downward - q[downward, 0] / (q[downward + 1, 0] - q[downward, 0])  # interpolated steps
    period = np.diff(crossings).mean() * h
    expected = 2 * np.pi * np.sqrt(length / g) * (1 + theta0**2 / 16)
    assert period == pytest.approx(expected, rel=2e-3)
    # slack (shorter than its length): the ball falls freely
    x0 = system.state(jnp.array([0.0, 0.6]), jnp.zeros(2))
    xs, infos = rollout(system, x0, jnp.zeros((10, 0)))
    np.testing.assert_allclose(np.asarray(xs)[-1, 3], -g * h * 10, rtol=1e-12)


# Two 1 kg carts on slides whose tendon, the sum of their coordinates, is limited above.
TWO_CARTS = """
<mujoco>
  <option timestep="0.01" gravity="0 0 0"/>
  <worldbody>
    <body name="a"><joint name="xa" type="slide" axis="1 0 0"/><geom type="box" size="0.1 0.1 0.1" mass="1" contype="0" conaffinity="0"/></body>
    <body name="b"><joint name="xb" type="slide" axis="1 0 0"/><geom type="box" size="0.1 0.1 0.1" mass="1" contype="0" conaffinity="0"/></body>
  </worldbody>
  <tendon><fixed name="sum" limited="true" range="-0.3 0.1"><joint joint="xa" coef="1"/><joint joint="xb" coef="1"/></fixed></tendon>
  <actuator><motor name="fa" joint="xa"/><motor name="fb" joint="xb"/></actuator>
</mujoco>
"""


def test_a_fixed_tendons_limit_stops_the_sum_and_lets_the_difference_move():
    # At its upper limit, pushed by 3 N and 1 N: the tendon's force (3 + 1) / 2 = 2 N holds the
    # sum, and the difference accelerates at (3 - 1) / 1 kg (each cart at +-1 m/s^2).
    system = sim.scene(TWO_CARTS, floor=False)
    assert system.joints.tendons.limits == ((0, 1), (0, -1))
    h, steps = 0.01, 40
    x0 = system.state(jnp.array([0.05, 0.05]), jnp.zeros(2))
    xs, infos = eqx.filter_jit(lambda s, x, us: s.rollout(x, us))(system, x0, jnp.tile(jnp.array([3.0, 1.0]), (steps, 1)))
    xs = np.asarray(xs)
    np.testing.assert_allclose(xs[:, 0] + xs[:, 1], 0.1, rtol=0, atol=1e-12)
    np.testing.assert_allclose(xs[1:, 2], h * np.arange(1, steps + 1), rtol=1e-9)
    impulse = np.asarray(infos.impulse).reshape(steps, 2, 3)  # [t1, t2, n] of the lower side, the upper side
    np.testing.assert_allclose(impulse[:, 1, 2], 2.0 * h, rtol=1e-9)
    np.testing.assert_allclose(impulse[:, 0], 0.0, atol=1e-12)
    np.testing.assert_allclose(impulse[:, 1, :2], 0.0, atol=1e-12)  # frictionless
    # the lower side holds the pull the other way (1 N on each cart: 1 N along the tendon)
    x0 = system.state(jnp.array([-0.2, -0.1]), jnp.zeros(2))
    xs, infos = eqx.filter_jit(lambda s, x, us: s.rollout(x, us))(system, x0, jnp.tile(jnp.array([-1.0, -1.0]), (steps, 1)))
    np.testing.assert_allclose(np.asarray(xs)[:, 0] + np.asarray(xs)[:, 1], -0.3, rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(infos.impulse).reshape(steps, 2, 3)[:, 0, 2], 1.0 * h, rtol=1e-9)
    with pytest.raises(ValueError, match="tendons' limits are solved by the hard-contact NCP"):
        system.with_options(contact=sim.SpringDamper(stiffness=1e4, damping=10.0, friction=0.5))
    # MuJoCo's limit flag disabled: none
    off = sim.load_mjcf(TWO_CARTS.replace('gravity="0 0 0"', 'gravity="0 0 0"><flag limit="disable"/></option><option'))
    assert off.tendons is None


def test_bad_tendon_limits_and_paths_are_refused_by_name():
    base = dict(
        lengths=jnp.zeros((1, 2)), moments=jnp.zeros((1, 2)), offsets=jnp.zeros(1), stiffness=jnp.zeros(1),
        spring_length=jnp.zeros((1, 2)), damping=jnp.zeros(1),
    )
    with pytest.raises(ValueError, match="Tendons.limits needs Tendons.range"):
        sim.Tendons(**base, limits=((0, 1),))
    with pytest.raises(ValueError, match=r"Tendons.limits entries must be \(tendon, side\)"):
        sim.Tendons(**base, range=jnp.array([[0.0, 1.0]]), limits=((0, 2),))
    with pytest.raises(ValueError, match="tendon 0 has no finite lower limit"):
        sim.Tendons(**base, range=jnp.array([[-jnp.inf, 1.0]]), limits=((0, 1),))
    with pytest.raises(ValueError, match="Tendons.range must hold lower <= upper"):
        sim.Tendons(**base, range=jnp.array([[1.0, 0.0]]), limits=((0, -1),))
    with pytest.raises(ValueError, match="Tendons.paths must hold one tuple of at least two frames"):
        sim.Tendons(**base, spatial=(0,), paths=(("a",),))
    system = sim.scene(TWO_CARTS, floor=False)
    with pytest.raises(ValueError, match=r"joints.tendons.paths \(tendon 0\): .*no_such_frame"):
        system.with_tendons(sim.Tendons(**base, spatial=(0,), paths=(("a", "no_such_frame"),)))
    path = dict(spatial=(0,), paths=(("a", "a", "a"),))
    shape = dict(wrap_rotations=jnp.eye(3)[None], wrap_offsets=jnp.zeros((1, 3)), wrap_radii=jnp.ones(1))
    with pytest.raises(ValueError, match=r"Tendons.wraps entries must be \(k, segment, frame, shape, side\)"):
        sim.Tendons(**base, **path, **shape, wraps=((0, 2, "a", "sphere", None),))
    with pytest.raises(ValueError, match="shape must be 'sphere' or 'cylinder', got 'box'"):
        sim.Tendons(**base, **path, **shape, wraps=((0, 0, "a", "box", None),))
    with pytest.raises(ValueError, match="Tendons.wrap_radii must be > 0"):
        sim.Tendons(**base, **path, **dict(shape, wrap_radii=jnp.zeros(1)), wraps=((0, 0, "a", "sphere", None),))
    with pytest.raises(ValueError, match="Tendons.pulleys: segment .* has a shape of Tendons.wraps"):
        sim.Tendons(**base, **path, **shape, wraps=((0, 0, "a", "sphere", None),), pulleys=((0, 0),), pulley_divisors=jnp.ones(1))
    with pytest.raises(ValueError, match="Tendons.pulley_divisors must be > 0"):
        sim.Tendons(**base, **path, pulleys=((0, 1),), pulley_divisors=jnp.zeros(1))
    with pytest.raises(ValueError, match=r"joints.tendons.wraps .*no_such_frame"):
        system.with_tendons(sim.Tendons(**base, **path, **shape, wraps=((0, 0, "no_such_frame", "sphere", None),)))


# Four spatial tendons from a world site to a site on a two-link arm, around a sphere and
# around a cylinder with a tilted axis that turn with the arm's first link, each without and
# with a side site (which picks the way round, and sends it the long way where the straight
# segment passes behind the shape).
WRAPPED = """
<mujoco>
  <option timestep="0.005" gravity="0 0 -9.81"/>
  <worldbody>
    <site name="anchor" pos="-0.35 0.04 0.12"/>
    <body name="upper"><joint name="h0" type="hinge" axis="0 1 0"/><joint name="h1" type="hinge" axis="1 0 0"/>
      <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.02" contype="0" conaffinity="0"/>
      <geom name="ball" type="sphere" size="0.08" pos="0.02 0.01 0.03" contype="0" conaffinity="0"/>
      <geom name="drum" type="cylinder" size="0.06 0.05" pos="0 -0.01 0" euler="1.3 0.3 0" contype="0" conaffinity="0"/>
      <site name="ball_side" pos="0.05 0.02 0.3"/><site name="drum_side" pos="0.02 -0.2 -0.25"/>
      <body name="lower" pos="0.3 0 0"><joint name="h2" type="hinge" axis="0 1 0"/><joint name="s" type="slide" axis="1 0 0"/>
        <geom type="capsule" fromto="0 0 0 0.2 0 0" size="0.02" contype="0" conaffinity="0"/>
        <site name="tip" pos="0.2 0.01 0.02"/>
      </body>
    </body>
  </worldbody>
  <tendon>
    <spatial name="ball" stiffness="1"><site site="anchor"/><geom geom="ball"/><site site="tip"/></spatial>
    <spatial name="ball_side" stiffness="1"><site site="anchor"/><geom geom="ball" sidesite="ball_side"/><site site="tip"/></spatial>
    <spatial name="drum" stiffness="1"><site site="anchor"/><geom geom="drum"/><site site="tip"/></spatial>
    <spatial name="drum_side" stiffness="1"><site site="anchor"/><geom geom="drum" sidesite="drum_side"/><site site="tip"/></spatial>
  </tendon>
</mujoco>
"""


def _ours_and_mujocos(system, text: str, count: int, seed: int):
    """At ``count`` random configurations of the wrapping arm (its q is MuJoCo's qpos): ``(qs,
    our lengths, our moments, MuJoCo's ten_length, its ten_J, its ten_wrapnum)``."""
    m = mujoco.MjModel.from_xml_string(text)
    d = mujoco.MjData(m)
    rng = np.random.default_rng(seed)
    qs = np.column_stack([rng.uniform(-np.pi, np.pi, (count, 3)), rng.uniform(-0.25, 0.1, count)])
    lengths, moments = jax.jit(jax.vmap(lambda q: (system.tendon_lengths(q), system.tendon_moments(q))))(jnp.asarray(qs))
    expected_lengths, expected_moments, wrap_points = [], [], []
    for q in qs:
        d.qpos[:] = q
        mujoco.mj_forward(m, d)
        expected_lengths.append(d.ten_length.copy())
        expected_moments.append(_dense_ten_J(m, d))
        wrap_points.append(d.ten_wrapnum.copy())
    return qs, lengths, moments, np.array(expected_lengths), np.array(expected_moments), np.array(wrap_points)


# A tendon around a world-fixed ball whose side site rides on a slider that falls through it:
# outside the ball at qpos0 (loadable), inside it after a few steps.
FALLING_SIDE = """
<mujoco>
  <option timestep="0.01"/>
  <worldbody>
    <site name="a" pos="-0.3 0 0"/><site name="b" pos="0.3 0 0.02"/>
    <geom name="ball" type="sphere" size="0.1" contype="0" conaffinity="0"/>
    <body name="slider" pos="0 0 0.15"><joint name="z" type="slide" axis="0 0 1"/>
      <geom type="box" size="0.01 0.01 0.01" contype="0" conaffinity="0"/><site name="side" pos="0.02 0 0"/>
    </body>
  </worldbody>
  <tendon><spatial name="t" stiffness="1"><site site="a"/><geom geom="ball" sidesite="side"/><site site="b"/></spatial></tendon>
</mujoco>
"""


def test_a_side_site_that_moves_into_its_shape_is_counted_and_warned_about():
    # MuJoCo then wraps through the shape, which rsmooth does not model: each step that starts
    # so is counted in its info (MuJoCo's own test on the same configurations: the site's
    # distance to the geom's centre below its radius) and check_steps warns.
    system = sim.scene(sim.load_mjcf(FALLING_SIDE), floor=False)
    xs, infos = eqx.filter_jit(system.rollout)(system.initial_state(), jnp.zeros((20, system.nu)))
    m = mujoco.MjModel.from_xml_string(FALLING_SIDE)
    d = mujoco.MjData(m)
    inside = []
    for x in np.asarray(xs)[:-1]:
        d.qpos[:] = x[: m.nq]
        mujoco.mj_kinematics(m, d)
        inside.append(np.linalg.norm(d.site_xpos[2] - d.geom_xpos[0]) < m.geom_size[0, 0])
    inside = np.array(inside)
    assert 0 < inside.sum() < len(inside)  # outside first, then inside
    np.testing.assert_array_equal(np.asarray(infos.inside_side_sites), inside.astype(int))
    with pytest.warns(sim.SimulationWarning, match=r"side site was inside its wrapping shape"):
        counts = sim.check_steps(infos, what="falling side site")
    assert counts["inside_side_site_steps"] == inside.sum()
    # a side site that stays outside: nothing counted
    assert int(system.inside_side_sites(system.initial_state()[: system.model.nq])) == 0


def test_tendons_wrapped_around_spheres_and_cylinders_have_mujocos_lengths_and_moments():
    # At random configurations (the arm's q is MuJoCo's qpos), where each tendon wraps and
    # where it does not: the lengths are MuJoCo's ten_length, the moments its ten_J.
    loaded = sim.load_mjcf(WRAPPED)
    tendons = loaded.tendons
    assert [(k, segment, shape, side is not None) for k, segment, _, shape, side in tendons.wraps] == [
        (0, 0, "sphere", False), (1, 0, "sphere", True), (2, 0, "cylinder", False), (3, 0, "cylinder", True)
    ]
    system = sim.scene(loaded, floor=False)
    qs, lengths, moments, expected_lengths, expected_moments, wrap_points = _ours_and_mujocos(system, WRAPPED, 400, seed=0)
    wrapped = wrap_points == 4
    assert np.all(wrapped.mean(axis=0) > 0.1) and np.all(wrapped.mean(axis=0) < 0.9)  # both occur, each tendon
    # the side sites send the path another way round than the short one in some configurations
    assert np.any(np.abs(np.array(expected_lengths)[:, 1] - np.array(expected_lengths)[:, 0]) > 1e-3)
    assert np.any(np.abs(np.array(expected_lengths)[:, 3] - np.array(expected_lengths)[:, 2]) > 1e-3)
    np.testing.assert_allclose(lengths, np.array(expected_lengths), rtol=0, atol=1e-12)
    np.testing.assert_allclose(moments, np.array(expected_moments), rtol=0, atol=1e-12)
    # the moments are the lengths' derivatives
    np.testing.assert_allclose(jax.jit(jax.vmap(jax.jacfwd(system.tendon_lengths)))(jnp.asarray(qs[:50])), moments[:50], rtol=0, atol=1e-12)


def _over_a_shape(shape: str, rise: float) -> str:
    """A string of two sites on slides along x (at x = -0.1 and 0.1 at q = 0, heights 0 and
    ``rise`` along y), over a fixed sphere or a cylinder (axis y) of radius 0.1 at the origin."""
    size = "0.1" if shape == "sphere" else "0.1 0.3"
    return f"""
<mujoco>
  <worldbody>
    <geom name="shape" type="{shape}" size="{size}" euler="90 0 0" contype="0" conaffinity="0"/>
    <body name="left" pos="-0.1 0 0"><joint name="x0" type="slide" axis="1 0 0"/><geom size="0.01" contype="0" conaffinity="0"/>
      <site name="left"/></body>
    <body name="right" pos="0.1 {rise} 0"><joint name="x1" type="slide" axis="1 0 0"/><geom size="0.01" contype="0" conaffinity="0"/>
      <site name="right"/></body>
  </worldbody>
  <tendon><spatial name="string" stiffness="1"><site site="left"/><geom geom="shape"/><site site="right"/></spatial></tendon>
</mujoco>"""


@pytest.mark.parametrize("shape, rise", [("sphere", 0.0), ("cylinder", 0.0), ("cylinder", 0.25)])
def test_a_string_over_a_sphere_or_a_cylinder_has_the_closed_form_length(shape, rise):
    # Sites at x = -d and d, the shape of radius r at the origin between them (on the line
    # through its centre: any plane through them holds the great circle): two tangent
    # segments of sqrt(d^2 - r^2) and an arc of pi - 2 acos(r / d); along a cylinder whose
    # axis the sites are apart by ``rise``, a helix: the unrolled path's hypotenuse. Moving a
    # site along x stretches the string by sqrt(d^2 - r^2) / d (times the planar share). With
    # a site inside the shape, the string is straight.
    r = 0.1
    system = sim.scene(sim.load_mjcf(_over_a_shape(shape, rise)), floor=False)
    d = np.array([0.1, 0.1 + 1e-9, 0.15, 0.4])  # 0.1: the sites on the surface (no straight part)
    qs = jnp.asarray(np.column_stack([r - d, d - r]))
    geometry = jax.jit(jax.vmap(lambda q: (
        system.tendon_lengths(q), system.tendon_moments(q), jax.jacfwd(system.tendon_moments)(q))))
    # the last: a site inside the shape (at its centre), where the segment stays straight
    lengths, moments, curvature = geometry(jnp.concatenate([qs, jnp.array([[r, 0.05]])]))
    reach = np.sqrt((d - r) * (d + r))  # the tangent segments
    planar = 2 * reach + r * (np.pi - 2 * np.arctan2(reach, r))  # arctan2(reach, r) = acos(r / d)
    length = np.hypot(planar, rise)
    np.testing.assert_allclose(lengths[:, 0], np.r_[length, np.hypot(0.15, rise)], rtol=0, atol=1e-14)
    slope = np.r_[reach / d * planar / length, 0.15 / np.hypot(0.15, rise)]
    # (1e-12: 1e-9 off the surface, the tangent segments' directions are ill-conditioned)
    np.testing.assert_allclose(moments[:, 0], np.column_stack([-slope, slope]), rtol=0, atol=1e-12)
    assert np.all(np.isfinite(curvature))  # finite second derivatives, also with the sites on the surface


def test_a_spring_wrapped_over_a_cylinder_pulls_a_hinge_and_a_slide_as_mujocos_euler_integrator(
        mujoco_and_rsmooth_trajectories, state_jacobian_is_central_differences):
    # A spring from a world site over a drum on a swinging arm to a slider on it (with side
    # sites), and over a sphere: 200 steps as MuJoCo's Euler steps, wrapping and unwrapping.
    text = """
<mujoco>
  <option timestep="0.002" gravity="0 0 -9.81"/>
  <worldbody>
    <site name="anchor" pos="-0.3 0 0.25"/>
    <body name="arm"><joint name="h" type="hinge" axis="0 1 0" damping="0.01"/>
      <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.02" contype="0" conaffinity="0"/>
      <geom name="drum" type="cylinder" size="0.06 0.03" euler="90 0 0" contype="0" conaffinity="0"/>
      <geom name="ball" type="sphere" size="0.05" pos="0.12 0 0.06" contype="0" conaffinity="0" mass="0"/>
      <site name="above" pos="0 0 0.3"/>
      <body name="slider" pos="0.25 0 0"><joint name="s" type="slide" axis="1 0 0"/>
        <geom type="box" size="0.03 0.03 0.03" contype="0" conaffinity="0"/><site name="hook" pos="0 0 0.03"/>
      </body>
    </body>
  </worldbody>
  <tendon>
    <spatial name="spring" stiffness="40" damping="0.3" springlength="0.3">
      <site site="anchor"/><geom geom="drum" sidesite="above"/><site site="hook"/>
    </spatial>
    <spatial name="ball" stiffness="10" springlength="0.2">
      <site site="anchor"/><geom geom="ball"/><site site="hook"/>
    </spatial>
  </tendon>
</mujoco>"""
    qpos, qvel = np.array([-0.6, 0.02]), np.array([4.0, -0.5])
    system, loaded, xs, expected = mujoco_and_rsmooth_trajectories(text, qpos, qvel, 200)
    np.testing.assert_allclose(np.asarray(xs)[1:, :2], expected, rtol=0, atol=1e-12)
    m = mujoco.MjModel.from_xml_string(text)
    d = mujoco.MjData(m)
    wrapped = []
    for qpos in expected:
        d.qpos[:] = qpos
        mujoco.mj_forward(m, d)
        wrapped.append(d.ten_wrapnum == 4)
    assert np.any(wrapped, axis=0).all() and not np.all(wrapped, axis=0).any()
    # the step's state Jacobian (through the wrapped moments) against central differences,
    # whose own error (eps^2 times the third derivative, large on the drum) is 1.5e-7 here
    for tendon in range(2):
        steps = np.flatnonzero(np.asarray(wrapped)[:, tendon])
        state_jacobian_is_central_differences(system, jnp.asarray(np.asarray(xs)[steps[len(steps) // 2] + 1]), atol=1e-6)


def test_pulleys_divide_their_branches_as_mujocos(mujoco_and_rsmooth_trajectories):
    # A tendon of three branches (the second, over the sphere, halved; the third, over the
    # drum with its side site, quartered) on the arm of WRAPPED: MuJoCo's lengths and moments
    # at random configurations, and its Euler steps under the tendon's spring and damper.
    tendon = (
        '<spatial name="pulleys" stiffness="30" damping="0.2" springlength="0.2"><site site="anchor"/><site site="tip"/>'
        '<pulley divisor="2"/><site site="anchor"/><geom geom="ball"/><site site="tip"/>'
        '<pulley divisor="4"/><site site="tip"/><geom geom="drum" sidesite="drum_side"/><site site="anchor"/></spatial>'
    )
    text = WRAPPED.replace("<tendon>", "<tendon>" + tendon)
    loaded = sim.load_mjcf(text)
    assert loaded.tendons.pulleys == ((0, 1), (0, 3)) and loaded.tendons.paths[0][2] == loaded.tendons.paths[0][0]
    system = sim.scene(loaded, floor=False)
    _, lengths, moments, expected_lengths, expected_moments, wrap_points = _ours_and_mujocos(system, text, 200, seed=1)
    wrapped = wrap_points[:, 0] > 8  # six sites and two pulleys, and two points per wrap
    assert 0 < np.mean(wrapped) < 1  # around a shape in some configurations only
    np.testing.assert_allclose(lengths, np.array(expected_lengths), rtol=0, atol=1e-12)
    np.testing.assert_allclose(moments, np.array(expected_moments), rtol=0, atol=1e-12)
    _, _, xs, expected = mujoco_and_rsmooth_trajectories(text, np.array([0.4, -0.3, 1.0, 0.0]), np.array([1.0, 0.5, -1.5, 0.2]), 150)
    np.testing.assert_allclose(np.asarray(xs)[1:, :4], expected, rtol=0, atol=1e-11)
