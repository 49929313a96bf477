"""The stages of a step (kinematics, collision, free motion, contact solve, integration) and the
State that `sim.step` carries: the stages compose to the step, each obeys its law (Pinocchio's
mass matrix and gravity, Newton's balance of a standing robot), and a composition differentiates
to the step's Jacobians."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rsmooth import sim
from rsmooth.sim import _stages


def _solo_perturbed():
    solo = sim.solo12()
    x = solo.initial_state()
    noise = jax.random.normal(jax.random.key(3), x.shape) * jnp.concatenate([jnp.full(19, 1e-3), jnp.full(18, 1e-2)])
    x = (x + noise).at[3:7].set(x[3:7] / jnp.linalg.norm(x[3:7]))
    return solo, x, sim.solo12_standing_torques(solo, x) + 0.1


def _box_with_a_budget():
    """A box on the floor (a geometry pair), its solve budgeted to 3 of its 4 corners."""
    box = sim.bodies([sim.Box(jnp.array([0.1, 0.1, 0.1]))], [1.0], [[0.0, 0.0, 0.1]], max_contacts=3)
    return box, box.initial_state(), jnp.array([0.5, 0.0, 0.0, 0.0, 0.0, 0.2])


def _compliant_cube():
    cube = sim.cube(contact=sim.SpringDamper(stiffness=1e4, damping=50.0, friction=0.5))
    x = cube.initial_state().at[2].add(-1e-3).at[7].set(0.2)  # pressed 1 mm into the floor, sliding along x
    return cube, x, jnp.array([0.0, 1.0, 0.0, 0.0, 0.0, 0.1])


@pytest.mark.parametrize("case", [_solo_perturbed, _box_with_a_budget, _compliant_cube])
def test_the_stages_compose_to_the_step(case):
    """Spheres on planes (Solo-12), a geometry pair under a contact budget, a compliant law."""
    system, x, u = case()

    @eqx.filter_jit
    def both(system, x, u):
        state = sim.make_state(system, x)
        composed = sim.step_stages(system, state, u)[0]
        return composed, *sim.step(system, state, u)

    composed, stepped, info = both(system, x, u)
    assert bool(info.ncp.converged) and not bool(info.diverged)
    assert float(jnp.max(jnp.abs(stepped.impulse))) > 0  # something touches
    np.testing.assert_allclose(composed.x, stepped.x, rtol=0, atol=1e-12)
    np.testing.assert_allclose(composed.impulse, stepped.impulse, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(stepped.impulse, info.impulse)


def test_standing_solo12_stages_match_pinocchio_and_balance_its_weight():
    """Free motion against Pinocchio's CRBA and RNEA; the contact solve holds the robot still,
    its four feet carrying m g between them."""
    pin = pytest.importorskip("pinocchio")
    solo = sim.solo12()
    x = solo.initial_state()
    q, v = solo.split(x)
    u = sim.solo12_standing_torques(solo, x)

    @eqx.filter_jit
    def stages(system, q, v, u):
        posed = sim.kinematics(system, q)
        contacts = sim.collision(system, q, posed)
        motion = sim.free_motion(system, q, v, u, posed)
        return contacts, motion, sim.solve_contacts(system, motion, contacts)

    contacts, motion, solution = stages(solo, q, v, u)

    model = pin.buildModelFromUrdf(str(sim.solo12_urdf_path()), pin.JointModelFreeFlyer())
    data = model.createData()
    q_np = np.asarray(q)
    mass = pin.crba(model, data, q_np)
    mass = np.triu(mass) + np.triu(mass, 1).T
    mass += np.diag(np.asarray(solo.model.armature + solo.time_step * solo.damping()))
    gravity = pin.rnea(model, data, q_np, np.zeros(model.nv), np.zeros(model.nv))
    tau = np.zeros(model.nv)
    tau[6:] = np.asarray(u)
    h = float(solo.time_step)
    np.testing.assert_allclose(motion.mass, mass, rtol=0, atol=1e-10)
    np.testing.assert_allclose(motion.mass_cholesky @ motion.mass_cholesky.T, mass, rtol=0, atol=1e-10)
    np.testing.assert_allclose(motion.velocity, h * np.linalg.solve(mass, tau - gravity), rtol=0, atol=1e-10)
    assert not bool(motion.torque_clipped)

    touching = np.flatnonzero(np.abs(np.asarray(contacts.distance)) < 1e-9)
    assert touching.size == 4  # the feet
    np.testing.assert_allclose(np.asarray(contacts.frames)[touching, :, 2], np.tile([0.0, 0.0, 1.0], (4, 1)), atol=1e-12)
    np.testing.assert_allclose(contacts.friction, solo.contact_friction())
    # Newton: at rest, the impulses over the step carry the weight, and the robot stays still.
    total_mass = float(np.sum(np.asarray(solo.model.body_mass)))
    impulse = np.asarray(solution.impulse).reshape(-1, 3)
    np.testing.assert_allclose(np.sum(impulse[:, 2]), total_mass * 9.81 * h, rtol=1e-9)
    np.testing.assert_allclose(impulse[np.setdiff1d(np.arange(len(impulse)), touching)], 0.0, atol=1e-15)
    np.testing.assert_allclose(solution.velocity, 0.0, atol=1e-9)
    assert bool(solution.ncp.converged)


def test_the_state_carries_the_warm_start_through_steps_as_the_rollout_does():
    solo, x, u = _solo_perturbed()
    us = jnp.tile(u, (3, 1))
    xs, infos = eqx.filter_jit(lambda s, x, us: s.rollout(x, us))(solo, x, us)
    step = eqx.filter_jit(sim.step)
    state = sim.make_state(solo, x)
    np.testing.assert_array_equal(state.impulse, 0.0)
    for t in range(3):
        state, info = step(solo, state, us[t])
        np.testing.assert_allclose(state.x, xs[t + 1], rtol=0, atol=1e-14)
        np.testing.assert_array_equal(info.ncp.iterations, infos.ncp.iterations[t])
    np.testing.assert_array_equal(sim.make_state(solo).x, solo.initial_state())


def test_bad_states_are_named():
    solo = sim.solo12()
    with pytest.raises(ValueError, match=r"x must have shape \(nx,\) = \(37,\)"):
        sim.make_state(solo, jnp.zeros(36))
    state = sim.make_state(solo)
    with pytest.raises(ValueError, match=r"state.impulse must have shape"):
        sim.step(solo, sim.State(state.q, state.v, jnp.zeros(3)), jnp.zeros(12))


def test_composed_stages_differentiate_to_the_steps_jacobians():
    """Stage by stage (the contact solve by solve_ncp's own implicit rule) against the step's
    implicit rule on the whole velocity update: a ball sliding and spinning against a floor and
    a wall (unique impulses)."""
    system = sim.ball_wall(solver=sim.NCPSolver(tolerance=1e-13, max_iterations=2000))
    x = system.state(jnp.array([0.0, 0.0, 0.0499, 0.0, 0.0, 0.0, 1.0]), jnp.array([0.4, 0.1, 0.0, 0.0, 3.0, 1.0]))
    u = jnp.array([0.1, 0.05, -0.2])

    @eqx.filter_jit
    def jacobians(system, x, u):
        composed = jax.jacfwd(lambda a, b: sim.step_stages(system, sim.make_state(system, a), b)[0].x, argnums=(0, 1))
        return composed(x, u), system.step_and_jacobians(x, u)[1:]

    composed, stepped = jacobians(system, x, u)
    for ours, theirs in zip(composed, stepped):
        scale = float(jnp.max(jnp.abs(theirs)))
        assert scale > 0
        np.testing.assert_allclose(ours, theirs, rtol=0, atol=1e-8 * scale)


# Free shapes beside each other on a floor (pairs where both shapes move), an arm with a limited
# hinge and a ball joint's cone, and a spatial tendon limited on both sides.
_LIMITED_SCENE = """<mujoco><option timestep="0.01"/><worldbody>
  <geom name="floor" type="plane" size="2 2 0.1"/>
  <body name="ball" pos="0 0 0.1"><freejoint/><geom type="sphere" size="0.1" mass="1"/></body>
  <body name="box" pos="0.25 0 0.1"><freejoint/><geom type="box" size="0.1 0.1 0.1" mass="1"/></body>
  <body name="arm" pos="0 0.3 0.3">
    <joint name="hinge" type="hinge" axis="0 1 0" limited="true" range="-30 45"/>
    <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03" mass="1"/><site name="tip" pos="0.3 0 0"/>
    <body name="forearm" pos="0.3 0 0"><joint name="ball" type="ball" limited="true" range="0 40"/>
      <geom type="capsule" fromto="0 0 0 0.2 0 0" size="0.03" mass="0.5"/></body>
  </body>
  <site name="anchor" pos="0 0.3 1"/>
</worldbody>
<tendon><spatial name="string" limited="true" range="0.5 0.9"><site site="anchor"/><site site="tip"/></spatial></tendon>
</mujoco>"""


@pytest.mark.parametrize("make", [lambda: sim.scene(_LIMITED_SCENE), sim.pusher], ids=["scene", "pusher"])
def test_rows_and_velocities_built_from_where_the_contacts_act_are_the_jacobians(make, getkey):
    """A budgeted step builds the rows of the contacts it solves, and counts those it leaves out
    from their velocities, from the witness points (`WitnessPoints`) without the Jacobian of every
    candidate: both equal the Jacobian's, for spheres on planes and the pusher's finger (the
    pusher), pairs of moving shapes, inactive manifold entries, joint, cone and tendon limits."""
    system = make()
    shapes, limits = system.num_contacts - system.num_limits, system.num_limits
    x = system.initial_state()
    x = system.project_state(x + 0.05 * jax.random.normal(getkey(), x.shape))
    q, v = system.split(x)
    v = jax.random.normal(getkey(), v.shape)
    contacts = eqx.filter_jit(sim.collision)(system, q)
    weight = np.asarray(contacts.points.weight)
    assert weight.shape == (shapes,) and (limits == 0 or contacts.points.limit_rows.shape[0] == limits)
    np.testing.assert_allclose(_stages.contact_velocities(system, contacts, v), contacts.jacobian @ v, rtol=0, atol=1e-12)
    # a budget's selection: some contacts between shapes, then some limits (ascending each)
    budget, limit_budget = shapes - 3, max(limits - 2, 0) or None
    budgeted = system.with_contact_budget(budget, max_limits=limit_budget)
    chosen = np.sort(np.asarray(jax.random.choice(getkey(), shapes, (budget,), replace=False)))
    if limits:
        chosen = np.concatenate([chosen, shapes + np.sort(np.asarray(jax.random.choice(getkey(), limits, (limit_budget,), replace=False)))])
    selection = jnp.asarray(chosen, jnp.int32)
    rows = eqx.filter_jit(_stages.jacobian_rows)(budgeted, contacts, selection)
    np.testing.assert_allclose(rows, contacts.jacobian[_stages.flat_rows(selection)], rtol=0, atol=1e-12)
    # the rows are not trivial: moving bodies on both sides of a pair, entries of both kinds
    assert np.any(weight == 1.0) and np.any(np.abs(np.asarray(rows)) > 0.1)
