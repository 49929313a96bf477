"""Dry joint friction (Joints.friction, MuJoCo's frictionloss) against closed
forms: Coulomb's threshold on a slide and a hinge, the constant deceleration it gives a
slipping dof and its derivative in the friction effort, the joint's friction added to a
floor's, and the step's implicit Jacobians against forward-mode autodiff."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rsmooth import sim
from rsmooth.sim import _stages

H, MASS, FRICTION = 0.01, 1.0, 2.0
G = 9.81
# A cart on a horizontal slide pushed by a motor, and an arm (a rod of 0.5 m) on a hinge that
# gravity turns from horizontal; neither collides.
SCENE = f"""<mujoco><option timestep="{H}" gravity="0 0 -{G}"/><worldbody>
<body name="cart" pos="0 0 1"><joint name="slide" type="slide" axis="1 0 0" frictionloss="{FRICTION}"/>
  <geom type="box" size="0.1 0.1 0.1" mass="{MASS}" contype="0" conaffinity="0"/></body>
<body name="arm" pos="0 1 1"><joint name="hinge" type="hinge" axis="1 0 0" frictionloss="{{hinge}}"/>
  <geom type="capsule" fromto="0 0 0 0 0.5 0" size="0.001" mass="1.0" contype="0" conaffinity="0"/></body>
</worldbody><actuator><motor joint="slide"/></actuator></mujoco>"""


def cart_and_arm(hinge_friction: float) -> sim.RigidBodySystem:
    return sim.scene(SCENE.format(hinge=hinge_friction), floor=False)


# one compiled rollout per system structure and horizon, whatever the values
rollout = eqx.filter_jit(lambda system, x0, us: system.rollout(x0, us))


def test_the_cart_moves_only_beyond_its_friction_and_then_at_the_closed_form_rate():
    system = cart_and_arm(1.0)
    assert system.joints.friction.dofs == (0, 1)
    np.testing.assert_allclose(system.joints.friction.effort, [FRICTION, 1.0])
    x0, steps = system.initial_state(), 40
    for force in (0.5 * FRICTION, 0.99 * FRICTION, -0.99 * FRICTION):  # held exactly
        xs, infos = rollout(system, x0, jnp.full((steps, 1), force))
        assert bool(jnp.all(infos.ncp.converged))
        np.testing.assert_array_equal(np.asarray(xs[:, 0]), 0.0)
        # the friction impulse is the push's, opposed (the cart's row first, then the arm's)
        np.testing.assert_allclose(infos.joint_impulse[:, 0], -force * H, rtol=1e-9)
    for force in (1.5 * FRICTION, -3.0 * FRICTION):  # slips: v_k = k h (f - F sign f) / m
        xs, infos = rollout(system, x0, jnp.full((steps, 1), force))
        assert bool(jnp.all(infos.ncp.converged))
        rate = (force - np.sign(force) * FRICTION) / MASS
        np.testing.assert_allclose(np.asarray(xs[1:, 2]), rate * H * np.arange(1, steps + 1), rtol=1e-10)
        # the position of semi-implicit Euler under a constant acceleration
        expected = rate * H**2 * np.cumsum(np.arange(1, steps + 1))
        np.testing.assert_allclose(np.asarray(xs[1:, 0]), expected, rtol=1e-10)

    # The derivative of the slip speed in the friction effort: -T h / m, through the NCP's box
    # rows' implicit derivative (the bound's tangent), and in the push: T h / m.
    def final_speed(effort, force):
        with_effort = eqx.tree_at(lambda system: system.joints.friction.effort, system, effort)
        return with_effort.rollout(x0, jnp.full((steps, 1), force))[0][-1, 2]

    effort = jnp.array([FRICTION, 1.0])
    by_effort, by_force = jax.grad(final_speed, argnums=(0, 1))(effort, 1.5 * FRICTION)
    np.testing.assert_allclose(by_effort, [-steps * H / MASS, 0.0], atol=1e-9)
    np.testing.assert_allclose(by_force, steps * H / MASS, rtol=1e-9)


@pytest.mark.parametrize("hinge_friction", [2.0, 3.0])
def test_the_arm_is_held_where_its_friction_exceeds_gravitys_torque(hinge_friction):
    # Gravity's torque on the horizontal rod: m g l / 2 = 2.45 N m.
    system = cart_and_arm(hinge_friction)
    x0 = system.initial_state()
    xs, infos = rollout(system, x0, jnp.zeros((30, 1)))
    assert bool(jnp.all(infos.ncp.converged))
    held = hinge_friction > MASS * G * 0.25
    angle = np.asarray(xs[:, 1])
    if held:
        np.testing.assert_array_equal(angle, 0.0)
        # The friction impulse is gravity's over the step, opposite it.
        state = sim.make_state(system, x0)
        *_, solution = _stages.step_stages(system, state, jnp.zeros(1))
        np.testing.assert_allclose(abs(float(solution.joint_impulse[1])), MASS * G * 0.25 * H, rtol=1e-9)
        assert float(solution.joint_impulse[0]) == 0.0
    else:
        assert abs(angle[-1]) > 0.05
        # the first step's speed: (gravity's torque - friction) / inertia about the hinge, h
        # (MuJoCo's inertia of the capsule, caps included)
        mujoco = pytest.importorskip("mujoco")
        m = mujoco.MjModel.from_xml_string(SCENE.format(hinge=hinge_friction))
        data = mujoco.MjData(m)
        mujoco.mj_forward(m, data)
        full = np.zeros((m.nv, m.nv))
        mujoco.mj_fullM(m, data, full)
        expected = (MASS * G * 0.25 - hinge_friction) / full[1, 1] * H
        np.testing.assert_allclose(abs(float(xs[1, 3])), expected, rtol=1e-9)


def test_the_joints_friction_adds_to_the_floors():
    # A block on the floor on two slides (z free, x with dry friction F): pushed along x it
    # moves beyond F + mu m g, then at (f - F - mu m g) / m.
    mu = 0.3
    xml = f"""<mujoco><option timestep="{H}" gravity="0 0 -{G}"/><worldbody>
    <geom name="floor" type="plane" size="2 2 0.1" friction="{mu}"/>
    <body name="block" pos="0 0 0.1"><joint name="z" type="slide" axis="0 0 1"/>
      <joint name="x" type="slide" axis="1 0 0" frictionloss="{FRICTION}"/>
      <geom type="box" size="0.1 0.1 0.1" mass="{MASS}" friction="{mu}"/></body>
    </worldbody><actuator><motor joint="x"/></actuator></mujoco>"""
    system = sim.scene(xml, floor=False)
    assert system.joints.friction.dofs == (1,)
    resistance = FRICTION + mu * MASS * G
    x0, steps = system.initial_state(), 20
    xs, infos = rollout(system, x0, jnp.full((steps, 1), 0.95 * resistance))
    assert bool(jnp.all(infos.ncp.converged))
    # held to the NCP's tolerance (1e-10 on c (b + lambda), b = F h: c below 1e-8 m/s)
    assert np.max(np.abs(np.asarray(xs[:, 3]))) < 1e-7 and np.max(np.abs(np.asarray(xs[:, 1]))) < 1e-8
    force = 1.5 * resistance
    xs, infos = rollout(system, x0, jnp.full((steps, 1), force))
    assert bool(jnp.all(infos.ncp.converged))
    np.testing.assert_allclose(np.asarray(xs[1:, 3]), (force - resistance) / MASS * H * np.arange(1, steps + 1), rtol=1e-8)


@pytest.mark.parametrize("force", [0.5 * FRICTION, 1.5 * FRICTION])
def test_implicit_jacobians_match_forward_mode(force):
    system = cart_and_arm(1.0)
    x = system.initial_state().at[3].set(0.3)  # the arm turning: its friction slips
    u = jnp.array([force])
    x_next, fx, fu = eqx.filter_jit(lambda s, x_, u_: s.step_and_jacobians(x_, u_))(system, x, u)
    reference = system.with_options(derivative="autodiff")
    step = eqx.filter_jit(lambda s, x_, u_: (s.step(x_, u_), *jax.jacfwd(s.step, argnums=(0, 1))(x_, u_)))
    x_ref, fx_ref, fu_ref = step(reference, x, u)
    np.testing.assert_allclose(x_next, x_ref, atol=1e-12)
    np.testing.assert_allclose(fx, fx_ref, atol=1e-9)
    np.testing.assert_allclose(fu, fu_ref, atol=1e-9)
    assert (float(fu[2, 0]) == 0.0) == (force < FRICTION)  # a held cart does not feel the push


def test_bad_friction_is_refused_by_name():
    system = cart_and_arm(1.0)
    with pytest.raises(ValueError, match=r"effort must have shape \(nv,\) = \(2,\)"):
        system.with_joint_friction(np.ones(3))
    with pytest.raises(ValueError, match=r"effort must be finite and >= 0.*dofs \[1\] have \[-1.0\]"):
        system.with_joint_friction(np.array([1.0, -1.0]))
    assert system.with_joint_friction(np.zeros(2)).joints.friction is None
    with pytest.raises(ValueError, match="JointFriction.effort must have shape"):
        sim.JointFriction((0, 1), jnp.ones(3))
    with pytest.raises(ValueError, match="joints.friction are solved by the hard-contact NCP"):
        system.with_options(contact=sim.SpringDamper(stiffness=1e4, damping=10.0, friction=0.5))
