"""Joint position limits as frictionless unilateral constraints of the contact NCP: a joint
stops at its limit and is held there by the closed-form static torque, a joint beyond its limit
is pushed back at the Baumgarte rate, and the step's derivative through an active limit is the
constrained one."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rsmooth import sim

G = 9.81
H = 0.01
MASS, LENGTH, LOWER, UPPER = 1.0, 0.5, -30.0, 45.0

# A horizontal rod on a hinge about y: gravity turns it towards +q (its tip goes down).
ARM = f"""<mujoco><option timestep="{H}"/><worldbody><body name="arm" pos="0 0 1">
<joint name="hinge" type="hinge" axis="0 1 0" limited="true" range="{LOWER} {UPPER}"/>
<geom type="capsule" fromto="0 0 0 {LENGTH} 0 0" size="0.01" mass="{MASS}" contype="0" conaffinity="0"/>
</body></worldbody></mujoco>"""

# A block on a vertical slider whose lower limit is 0.3 m below its start.
SLIDER = f"""<mujoco><option timestep="{H}"/><worldbody><body name="block" pos="0 0 1">
<joint name="slide" type="slide" axis="0 0 1" limited="true" range="-0.3 0.2"/>
<geom type="box" size="0.05 0.05 0.05" mass="2" contype="0" conaffinity="0"/>
</body></worldbody></mujoco>"""


def _rollout(system, x0, steps, us=None):
    us = jnp.zeros((steps, system.nu)) if us is None else us
    return eqx.filter_jit(system.rollout)(x0, us)


def test_a_falling_arm_stops_at_its_limit_and_is_held_by_the_static_torque():
    free = sim.scene(ARM, joint_limits=False)
    system = free.with_joint_limits()
    assert system.joints.limits == ((0, 1), (0, -1)) and system.num_contacts == free.num_contacts + 2
    assert sim.scene(ARM).joints.limits == system.joints.limits  # scene enforces them by default, as MuJoCo
    xs, infos = _rollout(system, system.initial_state(), 80)
    sim.check_steps(infos, what="the limited arm")
    q = np.asarray(xs[:, 0])
    upper = np.radians(UPPER)
    # speculative constraint: the joint reaches the limit's skin (1e-6 rad) within the step it
    # would cross it, closes the rest at the Baumgarte rate, and never passes it by more than
    # rounding
    assert q.max() <= upper + 1e-9 and np.isclose(q[-1], upper, atol=1e-9)
    # without the limit the same arm swings through it
    xs_free, _ = _rollout(free, free.initial_state(), 80)
    assert np.max(np.asarray(xs_free[:, 0])) > upper + 0.3
    # at rest on the limit: the constraint carries gravity's torque about the hinge, m g (L/2)
    # cos(q) (the capsule's caps are symmetric about its centre, which sits at L / 2)
    assert np.max(np.abs(np.asarray(xs[-10:, 1]))) < 1e-7
    force = np.asarray(infos.force[-1])
    np.testing.assert_allclose(force[-1], [0.0, 0.0, MASS * G * LENGTH / 2 * np.cos(upper)], rtol=1e-6)
    np.testing.assert_array_equal(force[-2], 0.0)  # the lower limit is far
    assert int(infos.mode[-1][-1]) != sim.SEPARATED and int(infos.mode[-1][-2]) == sim.SEPARATED
    # a budget of one limit, the nearer to its bound: the lower one at the start (30 deg away
    # against 45), the upper one once the arm has turned past 7.5 deg; the same motion
    budget = system.with_contact_budget(None, max_limits=1)
    xs_budget, infos_budget = _rollout(budget, system.initial_state(), 80)
    assert sim.check_steps(infos_budget)["dropped_contact_steps"] == 0  # no warning: errors in the suite
    np.testing.assert_allclose(np.asarray(xs_budget), np.asarray(xs), rtol=0, atol=1e-12)


def test_a_slider_lands_on_its_lower_limit_inelastically_and_is_pushed_out_at_the_baumgarte_rate():
    system = sim.scene(SLIDER).with_joint_limits(["slide"])
    lower = -0.3
    xs, infos = _rollout(system, system.initial_state(), 40)
    sim.check_steps(infos, what="the limited slider")
    q, v = np.asarray(xs[:, 0]), np.asarray(xs[:, 1])
    assert q.min() >= lower - 1e-9 and np.isclose(q[-1], lower, atol=1e-9)
    # the step that lands moves it onto the limit's skin, (1 - beta) s = 0.8 um above it;
    # it then settles at the Baumgarte rate (the gap times 1 - beta per step): no bounce
    landed = int(np.argmax(np.isclose(q, lower + 0.8e-6, atol=1e-9)))
    assert landed > 0 and v[landed] < -0.1
    gaps = q[landed:] - lower
    np.testing.assert_allclose(gaps[1:11], gaps[:10] * (1.0 - system.baumgarte), rtol=1e-6)
    assert np.all(gaps >= 0) and np.max(np.abs(v[landed + 1 :])) < 2e-4
    # holds the weight (to the settling of the last fraction of a micrometre)
    np.testing.assert_allclose(np.asarray(infos.force[-1])[0, 2], 2.0 * G, rtol=1e-4)
    # from 1 cm beyond the limit, at rest: c_N + beta phi / h = 0 moves it by -beta phi
    phi = -0.01
    x0 = system.state(jnp.array([lower + phi]))
    x1 = system.step(x0, jnp.zeros(system.nu))
    np.testing.assert_allclose(float(x1[0]) - lower, (1.0 - system.baumgarte) * phi, rtol=1e-9)


def test_the_step_derivative_through_an_active_limit_is_the_constrained_one():
    system = sim.scene(SLIDER).with_joint_limits()
    rest = system.state(jnp.array([-0.3]))
    actuated = dataclasses.replace(system, actuation=sim.Actuation("joints", jnp.array([100.0]), dofs=(0,)))
    # resting on its lower limit, a small push down changes nothing; a push up above its
    # weight lifts it at (u - m g) / m: derivatives 0 and h / m of the next velocity
    step_and_jacobians = eqx.filter_jit(lambda s, x, u: s.step_and_jacobians(x, u))
    step = eqx.filter_jit(lambda s, x, u: s.step(x, u))
    reference = eqx.filter_jit(lambda s, x, u: jax.jacfwd(s.step)(x, u))
    for u, expected in ((5.0, 0.0), (30.0, H / 2.0)):
        _, fx, fu = step_and_jacobians(actuated, rest, jnp.array([u]))
        np.testing.assert_allclose(np.asarray(fu)[1, 0], expected, atol=1e-9)
        eps = 1e-6
        finite = (step(actuated, rest, jnp.array([u + eps])) - step(actuated, rest, jnp.array([u - eps]))) / (2 * eps)
        np.testing.assert_allclose(np.asarray(fu)[:, 0], np.asarray(finite), atol=1e-7)
        np.testing.assert_allclose(fx, reference(actuated, rest, jnp.array([u])), atol=1e-9)


# An upright rod on a ball joint whose cone limit is 30 degrees from the vertical. Not too
# thin: resting on its cone, a rod 0.01 m thick (twist inertia 1/440 of its swing inertia) is
# unstable at 10 ms steps here and in MuJoCo (the cone's normal turns with the twist).
CONE = 30.0
ROD = f"""<mujoco><option timestep="{H}"/><worldbody><body name="rod" pos="0 0 1">
<joint name="ball" type="ball" limited="true" range="0 {CONE}"/>
<geom type="capsule" fromto="0 0 0 0 0 {LENGTH}" size="0.05" mass="{MASS}" contype="0" conaffinity="0"/>
</body></worldbody></mujoco>"""


def test_a_toppling_rod_stops_at_its_ball_joints_cone_limit_and_rests_on_it():
    free = sim.scene(ROD, joint_limits=False)
    system = free.with_joint_limits()
    assert system.joints.limits == ((0, 0),) and sim.scene(ROD).joints.limits == ((0, 0),)
    # tilted by 10 degrees about a horizontal axis: gravity topples it about that axis
    axis, tilt = np.array([1.0, 2.0, 0.0]) / np.sqrt(5.0), np.radians(10.0)
    x0 = system.state(jnp.asarray(np.r_[np.sin(tilt / 2) * axis, np.cos(tilt / 2)]))

    def angles_and_axes(xs):
        quaternions = np.asarray(xs[:, :4])
        sine = np.linalg.norm(quaternions[:, :3], axis=1)
        return 2 * np.arctan2(sine, np.abs(quaternions[:, 3])), quaternions[:, :3] / sine[:, None]

    xs, infos = _rollout(system, x0, 80)
    sim.check_steps(infos, what="the rod on a limited ball joint")
    angle, axes = angles_and_axes(xs)
    cone = np.radians(CONE)
    assert angle.max() <= cone + 1e-9 and np.isclose(angle[-1], cone, atol=1e-9)
    np.testing.assert_allclose(axes, np.broadcast_to(axis, axes.shape), atol=1e-9)  # no twist, no drift of the axis
    assert np.max(np.abs(np.asarray(xs[-10:, 4:]))) < 1e-7
    # at rest on the cone: the constraint carries gravity's torque about the axis, m g (L/2) sin
    # (the capsule's centre of mass is at L / 2)
    np.testing.assert_allclose(np.asarray(infos.force[-1, -1]), [0.0, 0.0, MASS * G * LENGTH / 2 * np.sin(cone)], rtol=1e-6)
    # without the limit the rod falls through the cone
    free_angle, _ = angles_and_axes(_rollout(free, x0, 80)[0])
    assert free_angle.max() > cone + 0.5


def test_bad_joint_limits_are_refused_by_name():
    system = sim.scene(ARM)
    with pytest.raises(ValueError, match="unknown joint 'elbow'"):
        system.with_joint_limits(["elbow"])
    with pytest.raises(ValueError, match=r"joint_limits entries must be \(dof, side\)"):
        dataclasses.replace(system, joints=sim.Joints(limits=((0, 2),)))
    for bad in (0, -1, 1.5, True):
        with pytest.raises(ValueError, match="max_limits must be a positive integer or None"):
            system.with_contact_budget(None, max_limits=bad)
    unlimited = sim.scene(ARM.replace(f'limited="true" range="{LOWER} {UPPER}"', ""))
    assert unlimited.with_joint_limits().joints.limits == ()
    with pytest.raises(ValueError, match="'hinge' has no finite position limit"):
        unlimited.with_joint_limits(["hinge"])
    with pytest.raises(ValueError, match="no finite upper position limit"):
        dataclasses.replace(unlimited, joints=sim.Joints(limits=((0, -1),)))
    floating = sim.scene(ARM.replace('<joint name="hinge"', '<freejoint name="root"/><!--').replace(f'{UPPER}"/>', f'{UPPER}"/>-->'))
    with pytest.raises(ValueError, match="'root' is a free_flyer joint"):
        floating.with_joint_limits(["root"])
    rod = sim.scene(ROD)
    with pytest.raises(ValueError, match=r"joint_limits entries must be \(dof, side\)"):
        dataclasses.replace(rod, joints=sim.Joints(limits=((0, 1),)))  # a spherical joint's limit is its cone: side 0
    with pytest.raises(ValueError, match="'ball' has no finite cone position limit"):
        dataclasses.replace(sim.scene(ROD.replace(f'limited="true" range="0 {CONE}"', "")), joints=sim.Joints(limits=((0, 0),)))
