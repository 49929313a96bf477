"""Joint springs (Joints.springs, MuJoCo's joint stiffness and springref)
against MuJoCo's Euler integrator, closed forms (the equilibrium of a sprung slide under
gravity, a one-step derivative in the stiffness, the springs' potential energy) and
forward-mode autodiff of the step, and their input checks."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rsmooth import sim
from rsmooth.sim import _spatial as spatial

H, G = 0.005, 9.81
# A hinge with its reference (ref) and its spring's rest angle (springref) apart, damped; a
# slide; a ball joint with an isotropic spring; nothing collides.
CHAIN = f"""<mujoco><compiler angle="radian"/><option timestep="{H}" integrator="Euler" gravity="0 0 -{G}"/><worldbody>
<body name="upper" pos="0 0 1"><joint name="hinge" axis="0 1 0" ref="0.3" springref="-0.4" stiffness="6" damping="0.2"/>
  <geom type="capsule" fromto="0 0 0 0.3 0.1 0" size="0.03" mass="0.8" contype="0" conaffinity="0"/>
  <body name="middle" pos="0.3 0.1 0"><joint name="slide" type="slide" axis="1 0 0" springref="0.05" stiffness="40"/>
    <geom type="box" size="0.05 0.03 0.02" mass="0.5" contype="0" conaffinity="0"/>
    <body name="lower" pos="0.1 0 0"><joint name="ball" type="ball" stiffness="3" damping="0.05"/>
      <geom type="box" size="0.1 0.03 0.02" pos="0.1 0 0" mass="0.4" contype="0" conaffinity="0"/></body></body></body>
</worldbody></mujoco>"""

rollout = eqx.filter_jit(lambda system, x0, us: system.rollout(x0, us))
step_jacobians = eqx.filter_jit(lambda system, x, u: system.step_and_jacobians(x, u))
forward_jacobian = eqx.filter_jit(lambda system, x, u: jax.jacfwd(system.step)(x, u))


def test_springs_step_as_mujoco_euler(mujoco_and_rsmooth_trajectories):
    """Without contact a step is MuJoCo's Euler step (the springs explicit, the damping
    implicit), so the trajectories agree to rounding; and the step's Jacobians are forward
    mode's."""
    qpos = [0.7, -0.1, np.cos(0.6), 0.0, np.sin(0.6) * 0.6, np.sin(0.6) * 0.8]
    system, loaded, xs, expected = mujoco_and_rsmooth_trajectories(CHAIN, qpos, [0.5, -0.3, 2.0, 1.0, -0.5], 200)
    assert system.joints.springs.joints == (1, 2, 3)
    np.testing.assert_allclose(system.joints.springs.stiffness, [6.0, 40.0, 3.0])
    # the rest configuration in rsmooth's coordinates: springref less ref, the identity
    np.testing.assert_allclose(system.joints.springs.reference, [-0.7, 0.05, 0.0, 0.0, 0.0, 1.0], atol=1e-15)
    ours = jax.vmap(loaded.q_to_qpos)(xs[1:, : system.model.nq])
    # the spring's pull is visible: the hinge swings far from where gravity alone takes it
    assert np.ptp(expected[:, 0]) > 0.3
    np.testing.assert_allclose(ours, expected, rtol=0, atol=1e-11)
    x_next, fx, fu = step_jacobians(system, xs[50], jnp.zeros(0))
    np.testing.assert_allclose(x_next, xs[51], atol=1e-14)
    np.testing.assert_allclose(fx, forward_jacobian(system, xs[50], jnp.zeros(0)), atol=1e-10)
    # and both are the step's derivative: central differences along the hinge and the slide
    # (the springs' pull is most of their columns)
    for column in (0, 1):
        e = jnp.zeros(system.nx).at[column].set(1e-6)
        difference = (system.step(xs[50] + e, jnp.zeros(0)) - system.step(xs[50] - e, jnp.zeros(0))) / 2e-6
        np.testing.assert_allclose(fx[:, column], difference, atol=1e-7)


def test_springs_potential_energy_and_forces_are_the_closed_forms():
    system = sim.scene(CHAIN)
    nq = system.model.nq
    reference = system.joints.springs.reference
    angle, axis = 0.9, np.array([0.0, 0.6, 0.8])
    q = reference.at[0].add(0.25).at[1].add(-0.1).at[2:6].set(spatial.quaternion_exp(angle * axis))
    expected = 0.5 * (6.0 * 0.25**2 + 40.0 * 0.1**2 + 3.0 * angle**2)
    np.testing.assert_allclose(system.spring_energy(q), expected, rtol=1e-13)
    np.testing.assert_allclose(system.spring_forces(q), [-6.0 * 0.25, 40.0 * 0.1, *(-3.0 * angle * axis)], rtol=1e-13)
    # the forces are minus the energy's gradient (the ball's in its body-axes tangent)
    np.testing.assert_allclose(jax.grad(system.spring_energy)(q)[:2], -system.spring_forces(q)[:2], rtol=1e-13)
    tangent = jax.jacfwd(lambda w: system.spring_energy(q.at[2:6].set(spatial.quaternion_multiply(q[2:6], spatial.quaternion_exp(w)))))
    np.testing.assert_allclose(tangent(jnp.zeros(3)), -system.spring_forces(q)[2:], rtol=1e-12)
    # the total energy holds the springs' potential: gravity's alone at zero stretch
    no_springs = system.with_joint_springs(None)
    x = system.state(q, jnp.zeros(system.model.nv))
    np.testing.assert_allclose(sim.energy(system, x) - sim.energy(no_springs, x), expected, rtol=1e-12)
    assert q.shape == (nq,)


SLIDER = f"""<mujoco><option timestep="{H}" gravity="0 0 -{G}"/><worldbody>
<body name="weight" pos="0 0 1"><joint name="lift" type="slide" axis="0 0 1" springref="0.2" stiffness="{{k}}" damping="{{c}}"/>
  <geom type="box" size="0.05 0.05 0.05" mass="2" contype="0" conaffinity="0"/></body>
</worldbody></mujoco>"""


def test_a_sprung_weight_rests_where_the_spring_holds_gravity_and_the_stiffness_derivative_is_exact():
    k, mass = 500.0, 2.0
    system = sim.scene(SLIDER.format(k=k, c=60.0))  # damping ratio 0.95
    rest = 0.2 - mass * G / k  # k (q_ref - q) = m g
    x = system.state(jnp.array([rest]))
    np.testing.assert_allclose(system.step(x, jnp.zeros(0)), x, atol=1e-15)
    xs, _ = rollout(system, system.state(jnp.array([0.3])), jnp.zeros((600, 0)))
    np.testing.assert_allclose(xs[-1], [rest, 0.0], atol=1e-9)

    # One undamped step from q (at rest): v+ = h (-k (q - q_ref) / m - g), q+ = q + h v+, so
    # dq+/dk = -h^2 (q - q_ref) / m.
    undamped = sim.scene(SLIDER.format(k=k, c=0.0))
    q = 0.35

    def next_position(stiffness):
        springy = eqx.tree_at(lambda s: s.joints.springs.stiffness, undamped, stiffness)
        return springy.step(springy.state(jnp.array([q])), jnp.zeros(0))[0]

    np.testing.assert_allclose(next_position(jnp.array([k])), q + H**2 * (-k * (q - 0.2) / mass - G), rtol=1e-14)
    np.testing.assert_allclose(jax.grad(next_position)(jnp.array([k])), [-(H**2) * (q - 0.2) / mass], rtol=1e-12)


def test_bad_springs_are_refused_by_name():
    system = sim.scene(CHAIN)
    with pytest.raises(ValueError, match=r"stiffness must have shape \(nv,\) = \(5,\)"):
        system.with_joint_springs(np.ones(4))
    with pytest.raises(ValueError, match=r"dofs \[1\] have \[-1.0\]"):
        system.with_joint_springs(np.array([1.0, -1.0, 0.0, 0.0, 0.0]))
    with pytest.raises(ValueError, match="spherical joint 'ball' has unequal stiffness"):
        system.with_joint_springs(np.array([1.0, 1.0, 1.0, 2.0, 1.0]))
    with pytest.raises(ValueError, match=r"reference must have shape \(nq,\) = \(6,\)"):
        system.with_joint_springs(np.ones(5), np.zeros(5))
    assert system.with_joint_springs(np.zeros(5)).joints.springs is None
    cube = sim.cube()
    with pytest.raises(ValueError, match="joint 'root_joint' is a free_flyer"):
        cube.with_joint_springs(np.ones(6))
    with pytest.raises(ValueError, match="free joint 'j' has a spring"):
        sim.load_mjcf("<mujoco><worldbody><body><joint name='j' type='free' stiffness='2'/><geom size='0.1'/></body></worldbody></mujoco>")
