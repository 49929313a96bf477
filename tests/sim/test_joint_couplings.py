"""Joint couplings (Joints.couplings: MuJoCo's joint equalities, a URDF's
<mimic>) against closed forms: two carts coupled by a ratio move as one mass, an initial
error closes by the Baumgarte factor per step, and the step's implicit Jacobians against
forward-mode autodiff; Panda's finger, loaded from its URDF, follows the other."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rsmooth import sim

H, RATIO, M1, M2 = 0.01, 0.5, 1.0, 2.0


def coupled_carts(offset: float) -> sim.RigidBodySystem:
    """Two carts on parallel slides, the second's coordinate ``offset + RATIO x1``; a motor
    pushes the first; no gravity along the slides."""
    xml = f"""<mujoco><option timestep="{H}"/><worldbody>
    <body name="a" pos="0 0 1"><joint name="x1" type="slide" axis="1 0 0"/>
      <geom type="box" size="0.1 0.1 0.1" mass="{M1}" contype="0" conaffinity="0"/></body>
    <body name="b" pos="0 1 1"><joint name="x2" type="slide" axis="1 0 0"/>
      <geom type="box" size="0.1 0.1 0.1" mass="{M2}" contype="0" conaffinity="0"/></body>
    </worldbody><equality><joint joint1="x2" joint2="x1" polycoef="{offset} {RATIO} 0 0 0"/></equality>
    <actuator><motor joint="x1"/></actuator></mujoco>"""
    return sim.scene(xml, floor=False)


rollout = eqx.filter_jit(lambda system, x0, us: system.rollout(x0, us))
step_and_jacobians = eqx.filter_jit(lambda system, x, u: system.step_and_jacobians(x, u))
step_and_forward_mode = eqx.filter_jit(lambda system, x, u: (system.step(x, u), *jax.jacfwd(system.step, argnums=(0, 1))(x, u)))


def test_coupled_carts_move_as_one_mass():
    system = coupled_carts(0.0)
    assert system.joints.couplings.joints == (2,) and system.joints.couplings.others == (1,)
    steps, force = 20, 1.5
    xs, infos = rollout(system, system.initial_state(), jnp.full((steps, 1), force))
    assert bool(jnp.all(infos.ncp.converged))
    # x2 = RATIO x1, and the push accelerates the mass M1 + RATIO^2 M2 seen by x1
    rate = force / (M1 + RATIO**2 * M2)
    np.testing.assert_allclose(np.asarray(xs[1:, 2]), rate * H * np.arange(1, steps + 1), rtol=1e-9)
    np.testing.assert_allclose(np.asarray(xs[:, 1]), RATIO * np.asarray(xs[:, 0]), atol=1e-12)


def test_an_initial_error_closes_by_the_baumgarte_factor():
    offset = 0.05
    system = coupled_carts(offset)
    xs, infos = rollout(system, system.initial_state(), jnp.zeros((10, 1)))
    assert bool(jnp.all(infos.ncp.converged))
    error = np.asarray(xs[:, 1]) - (offset + RATIO * np.asarray(xs[:, 0]))
    np.testing.assert_allclose(error, -offset * (1 - system.baumgarte) ** np.arange(11), rtol=1e-9)
    # coupling_errors is that error, q_a - p(q_b), at each state
    np.testing.assert_allclose([float(system.coupling_errors(x[:2])[0]) for x in xs], error, rtol=1e-12, atol=1e-15)
    # The coupling's impulse acts as J^T lambda = (-RATIO, 1) lambda: it leaves the momentum
    # M1 v1 + RATIO M2 v2 unchanged (zero, from rest and without a push).
    v1, v2 = np.asarray(xs[:, 2]), np.asarray(xs[:, 3])
    assert np.max(np.abs(v2)) > 0.1
    np.testing.assert_allclose(M1 * v1 + RATIO * M2 * v2, 0.0, atol=1e-12)


def test_implicit_jacobians_match_forward_mode():
    system = coupled_carts(0.05)  # the position error's correction depends on the configuration
    x, u = system.initial_state().at[2].set(0.2), jnp.array([0.7])
    x_next, fx, fu = step_and_jacobians(system, x, u)
    x_ref, fx_ref, fu_ref = step_and_forward_mode(system.with_options(derivative="autodiff"), x, u)
    np.testing.assert_allclose(x_next, x_ref, atol=1e-12)
    np.testing.assert_allclose(fx, fx_ref, atol=1e-9)
    np.testing.assert_allclose(fu, fu_ref, atol=1e-9)


def test_pandas_second_finger_follows_the_first():
    path = sim.example_robot_data_root() / "robots" / "panda_description" / "urdf" / "panda.urdf"
    system = sim.scene(path, floor=False, self_collision=False, joint_limits=False)  # its zero is beyond a limit
    model, coupling = system.model, system.joints.couplings
    assert [model.joint_names[j] for j in coupling.joints] == ["panda_finger_joint2"]
    assert [model.joint_names[j] for j in coupling.others] == ["panda_finger_joint1"]
    np.testing.assert_allclose(coupling.coefficients, [[0.0, 1.0, 0.0, 0.0, 0.0]])
    first, second = (model.idx_q[model.joint_id(f"panda_finger_joint{k}")] for k in (1, 2))
    x0 = system.initial_state()
    # open the first finger by 1 cm: the coupling opens the second with it
    x0 = x0.at[model.nq + model.idx_v[model.joint_id("panda_finger_joint1")]].set(0.5)
    xs, infos = rollout(system, x0, jnp.zeros((20, system.nu)))
    assert bool(jnp.all(infos.ncp.converged))
    np.testing.assert_allclose(np.asarray(xs[:, second]), np.asarray(xs[:, first]), atol=1e-9)


def test_bad_couplings_are_refused_by_name():
    system = coupled_carts(0.0)
    with pytest.raises(ValueError, match=r"JointCoupling.coefficients must have shape \(1, 5\)"):
        sim.JointCoupling((2,), (1,), jnp.ones((1, 4)))
    with pytest.raises(ValueError, match="joint 7 must be a revolute or prismatic joint"):
        system.with_joint_couplings(sim.JointCoupling((7,), (1,), jnp.zeros((1, 5))))
    with pytest.raises(ValueError, match="joints.couplings are solved by the hard-contact NCP"):
        system.with_options(contact=sim.SpringDamper(stiffness=1e4, damping=10.0, friction=0.5))
