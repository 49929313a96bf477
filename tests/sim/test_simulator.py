"""Time-stepping with contact: invariants (rest, energy, cone), exact zero gradients,
implicit gradients against finite differences, Solo-12 standing, bad input."""

from __future__ import annotations

import dataclasses
import functools
import subprocess
import sys

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rsmooth import RESULTS, sim

GRAVITY = 9.81


@functools.lru_cache(maxsize=None)
def _cube():
    return sim.cube()


@functools.lru_cache(maxsize=None)
def _solo():
    return sim.solo12()


@eqx.filter_jit
def _rollout(system, x0, us):
    """The system is an argument (its arrays traced): systems that differ only in array fields
    share one compiled rollout."""
    return system.rollout(x0, us)


@eqx.filter_jit
def _energies(system, xs):
    return jax.vmap(lambda x: sim.energy(system, x))(xs)


def test_resting_cube_stays_at_rest():
    cube = _cube()
    x = cube.initial_state()
    step = jax.jit(lambda a, b, solver: cube.with_options(solver=solver).step_with_info(a, b))
    x_next, info = step(x, jnp.zeros(6), cube.solver)
    assert bool(info.ncp.converged)
    # The sticking guess (by G's pseudo-inverse: four coplanar corners make G singular) solves
    # it without ADMM, and the cube does not move, to rounding.
    assert int(info.ncp.iterations) == 0
    q, v = cube.split(x)
    q_next, v_next = cube.split(x_next)
    np.testing.assert_allclose(v_next, v, atol=1e-14)
    np.testing.assert_allclose(q_next, q, atol=1e-15)
    # ADMM alone (no guess) leaves it at rest up to its tolerance: the complementarity residual
    # lambda . c <= tol, on the corners' normal impulses m g h / 4, allows contact velocities up
    # to about 4 tol / (m g h) (4e-9 m/s here), and positions move by h times that.
    admm = sim.NCPSolver()
    x_admm, info_admm = step(x, jnp.zeros(6), admm)
    assert bool(info_admm.ncp.converged) and int(info_admm.ncp.iterations) > 0
    velocity_bound = 4.0 * admm.tolerance_for(jnp.float64) / (GRAVITY * 1.0 * 0.01)
    np.testing.assert_allclose(cube.split(x_admm)[1], v, atol=velocity_bound)
    np.testing.assert_allclose(x_admm[:7], q, atol=0.01 * velocity_bound)
    # The four bottom corners carry the weight, the top ones nothing.
    normal = info.impulse.reshape(8, 3)[:, 2]
    bottom = np.asarray(cube.geometry.sphere_offsets[:, 2] < 0)
    np.testing.assert_allclose(jnp.sum(normal[bottom]), GRAVITY * 1.0 * 0.01, rtol=1e-6)
    np.testing.assert_allclose(normal[~bottom], 0.0, atol=1e-12)


def test_dropped_cube_comes_to_rest_without_gaining_energy():
    cube = _cube()
    rest = cube.initial_state()
    axis = jnp.array([0.3, 0.1, 0.0, 1.0])
    x0 = rest.at[2].set(0.4).at[3:7].set(axis / jnp.linalg.norm(axis)).at[7:10].set(jnp.array([0.5, 0.0, 0.0]))
    xs, infos = _rollout(cube, x0, jnp.zeros((150, 6)))
    energies = _energies(cube, xs)
    # Inelastic contact and friction only dissipate (and semi-implicit Euler loses m g^2 h^2 / 2
    # per step of free fall). The only gain allowed is the Baumgarte push-out of the
    # penetration left by integrating rotating corners over a step: m g x (under 1 um).
    assert float(jnp.max(jnp.diff(energies))) < 1.0 * GRAVITY * 1e-6
    np.testing.assert_allclose(jnp.diff(energies)[:5], -0.5 * GRAVITY**2 * 0.01**2, rtol=1e-9)
    q_final, v_final = cube.split(xs[-1])
    np.testing.assert_allclose(v_final, 0.0, atol=1e-6)
    np.testing.assert_allclose(q_final[2], 0.1, atol=1e-4)  # flat on a face
    # The solver's diagnostics hold the residuals; they stay small even where capped.
    assert float(jnp.max(infos.ncp.dual_feasibility)) < 1e-4


def test_impulses_satisfy_cone_and_complementarity():
    cube = _cube()
    x = cube.initial_state()
    push = jnp.array([3.0, 1.0, 0.0, 0.0, 0.0, 0.2])  # below the friction bound: sticks
    _, info = jax.jit(lambda a, b: cube.step_with_info(a, b))(x, push)
    impulse = info.impulse.reshape(8, 3)
    assert bool(jnp.all(jnp.linalg.norm(impulse[:, :2], axis=1) <= 0.5 * impulse[:, 2] + 1e-10))
    assert bool(jnp.all(impulse[:, 2] >= -1e-12))


def test_small_upward_force_has_exactly_zero_gradient():
    """Fig. 2 of Le Lidec et al. 2022: below m g the cube does not move, whatever the force."""
    cube = _cube()
    x0 = cube.initial_state()

    def final_height(force, steps=5):
        us = jnp.zeros((steps, 6)).at[:, 2].set(force)
        xs, _ = cube.rollout(x0, us)
        return xs[-1, 2]

    # Forward mode: the height and its derivative from one program (reverse mode through a
    # rollout is the pusher's null-gradient test below).
    height_and_slope = jax.jit(lambda force: jax.jvp(final_height, (force,), (jnp.ones_like(force),)))
    for force in (0.0, 2.0, 5.0, 9.0):
        height, slope = height_and_slope(force)
        assert abs(float(slope)) < 1e-12
        np.testing.assert_allclose(height, 0.1, rtol=1e-8)
    # Above m g the cube flies: z(T) = z0 + h^2 (F/m - g) T (T + 1) / 2, semi-implicit Euler.
    force, steps, h = 15.0, 5, 0.01
    expected = h**2 * steps * (steps + 1) / 2
    height, slope = height_and_slope(force)
    np.testing.assert_allclose(slope, expected, rtol=1e-8)
    np.testing.assert_allclose(height, 0.1 + expected * (force - GRAVITY), rtol=1e-8)


def _central_differences(fun, x, eps=1e-6):
    x = np.asarray(x, dtype=np.float64)
    columns = []
    for i in range(x.size):
        dx = np.zeros_like(x)
        dx[i] = eps
        columns.append((np.asarray(fun(x + dx)) - np.asarray(fun(x - dx))) / (2 * eps))
    return np.stack(columns, axis=-1)


def test_sliding_ball_gradients_match_finite_differences():
    """One sliding contact: a well-posed NCP whose implicit derivative is exact."""
    system = sim.ball_wall(solver=sim.NCPSolver(tolerance=1e-13, max_iterations=2000))
    # 0.1 mm into the floor: the position correction max(phi, 0) / h + beta min(phi, 0) / h has
    # a kink at phi = 0, where finite differences would straddle two slopes.
    x = system.state(jnp.array([0.0, 0.0, 0.0499, 0.0, 0.0, 0.0, 1.0]), jnp.array([0.4, 0.1, 0.0, 0.0, 3.0, 1.0]))
    u = jnp.array([0.1, 0.05, -0.2])
    step = jax.jit(lambda a, b: system.step(a, b))
    _, info = jax.jit(lambda a, b: system.step_with_info(a, b))(x, u)
    impulse = info.impulse.reshape(2, 3)[0]
    np.testing.assert_allclose(jnp.linalg.norm(impulse[:2]), 0.3 * impulse[2], rtol=1e-9)  # on the cone: sliding
    jac_u = jax.jit(jax.jacfwd(lambda b: system.step(x, b)))(u)
    np.testing.assert_allclose(jac_u, _central_differences(lambda b: step(x, jnp.asarray(b)), u), atol=1e-7)
    jac_x = jax.jit(jax.jacrev(lambda a: system.step(a, u)))(x)
    fd_x = _central_differences(lambda a: step(jnp.asarray(a), u), x)
    # Columns of the quaternion are derivatives along R^4, off the unit sphere: compare all.
    np.testing.assert_allclose(jac_x, fd_x, atol=1e-6)


def test_sliding_cube_gradients_match_finite_differences():
    cube = sim.cube(solver=sim.NCPSolver(tolerance=1e-12, max_iterations=2000))
    x = cube.initial_state().at[7].set(0.3)  # sliding along x on the floor
    u = jnp.array([2.0, 0.5, 1.0, 0.0, 0.0, 0.1])
    step = jax.jit(lambda a, b: cube.step(a, b))
    jac_u = jax.jit(jax.jacfwd(lambda b: cube.step(x, b)))(u)
    fd_u = _central_differences(lambda b: step(x, jnp.asarray(b)), u)
    # Four coplanar contacts: 12 impulse components for 6 dofs, so the impulses are not
    # unique and the implicit derivative is the damped least-squares one. Velocities are
    # unique, and their derivatives agree to about 1e-5 (not to the solver's tolerance).
    np.testing.assert_allclose(jac_u, fd_u, atol=5e-5)
    velocity = x[7:]
    jac_v = jax.jit(jax.jacrev(lambda w: cube.step(x.at[7:].set(w), u)))(velocity)
    fd_v = _central_differences(lambda w: step(x.at[7:].set(jnp.asarray(w)), u), velocity)
    np.testing.assert_allclose(jac_v, fd_v, atol=5e-5)
    # Friction really acts: the sliding velocity drops by mu g h per step.
    x_next = step(x, jnp.zeros(6))
    np.testing.assert_allclose(x_next[7], 0.3 - 0.5 * GRAVITY * 0.01, rtol=1e-6)


def test_compliant_laws_reach_their_equilibria():
    spring = sim.cube(contact=sim.SpringDamper(stiffness=1e4, damping=50.0, friction=0.5), time_step=0.002)
    xs, _ = _rollout(spring, spring.initial_state(), jnp.zeros((300, 6)))
    # Four corners share the weight: k * penetration = m g / 4.
    np.testing.assert_allclose(xs[-1, 2], 0.1 - GRAVITY / 4e4, atol=1e-7)
    np.testing.assert_allclose(xs[-1, 7:], 0.0, atol=1e-6)
    # Log barrier: the 8 corners (4 at gap d, 4 at d + 0.2) hold the cube at a distance,
    # 4 kappa / d + 4 kappa / (d + 0.2) = m g; that state is a fixed point of the step.
    kappa = 1e-3
    barrier = sim.cube(contact=sim.LogBarrier(stiffness=kappa, friction=0.5), time_step=0.002)
    gap = 4 * kappa / GRAVITY
    for _ in range(50):  # fixed-point iteration on d = 4 kappa / (m g - 4 kappa / (d + 0.2))
        gap = 4 * kappa / (GRAVITY - 4 * kappa / (gap + 0.2))
    hovering = barrier.initial_state().at[2].add(gap)
    xs, _ = _rollout(barrier, hovering, jnp.zeros((100, 6)))
    np.testing.assert_allclose(xs[-1], hovering, atol=1e-9)
    # Its gradient is informative before touching: a lifting force moves the cube at once,
    # and so does a change of height (the hard model gives 0 for a cube in the air).
    grad = jax.jit(jax.grad(lambda f: barrier.step(hovering, jnp.array([0, 0, f, 0, 0, 0.0]))[2]))(0.0)
    assert float(grad) > 0


def test_ball_thrown_at_the_wall_stops_at_it():
    system = sim.ball_wall()
    x0 = system.state(jnp.array([0.0, 0.0, 0.3, 0.0, 0.0, 0.0, 1.0]))
    us = jnp.zeros((80, 3)).at[0].set(jnp.array([40.0, 0.0, 20.0]))  # 0.4 N s throw
    xs, infos = _rollout(system, x0, us)
    x_positions = xs[:, 0]
    assert float(jnp.max(x_positions)) <= 1.0 - 0.05 + 1e-4  # never through the wall
    assert float(jnp.max(x_positions)) > 1.0 - 0.05 - 1e-3  # but reaches it
    assert float(jnp.min(xs[:, 2])) >= 0.05 - 1e-3  # nor through the floor
    assert bool(jnp.all(infos.ncp.converged))


def test_solo12_stands_still_under_gravity_compensation():
    solo = _solo()
    x0 = solo.initial_state()
    assert solo.nx == 37 and solo.nu == 12
    distance, _, _ = eqx.filter_jit(lambda s, q: s.contacts(q))(solo, solo.split(x0)[0])
    np.testing.assert_allclose(distance, 0.0, atol=1e-12)
    torques = sim.solo12_standing_torques(solo, x0)
    assert float(jnp.max(jnp.abs(torques))) < sim.SOLO12_TORQUE_LIMIT
    xs, infos = _rollout(solo, x0, jnp.tile(torques, (100, 1)))  # one second
    np.testing.assert_allclose(xs[-1], x0, atol=1e-6)
    feet = sim.solo12_foot_positions(solo, xs[-1])
    np.testing.assert_allclose(feet, sim.solo12_foot_positions(solo, x0), atol=1e-6)
    assert bool(jnp.all(infos.ncp.converged))
    # Standing, the sticking guess (first step) and then the previous impulse solve every
    # contact problem without an ADMM iteration.
    assert bool(jnp.all(infos.ncp.iterations == 0))
    assert not bool(jnp.any(infos.torque_clipped))
    # Without torques it collapses.
    xs, _ = _rollout(solo, x0, jnp.zeros((30, 12)))
    assert float(xs[-1, 2]) < float(x0[2]) - 0.02


def test_a_thrown_tumbling_solo12_lands_on_its_body_with_accurate_contact_solves():
    """Thrown 0.3 m up with a tumble, limp (zero torque), Solo-12 lands on its base, knees and
    feet: up to 12 contacts (36 rows) on 18 dofs, impulses far from unique. Most solves reach
    the tolerance (1e-10), the others stop within 1e-6 (ADMM's slow tail on these problems;
    Pinocchio's ADMM does no better on them), and the robot ends lying still on the floor."""
    solo = sim.solo12(body_contacts=True)
    x0 = solo.initial_state()
    thrown = x0.at[2].add(0.3).at[19:25].set(jnp.array([0.5, 0.2, -1.0, 3.0, -2.0, 1.0]))
    xs, infos = _rollout(solo, thrown, jnp.zeros((300, 12)))
    assert not bool(jnp.any(infos.diverged))
    converged = np.asarray(infos.ncp.converged)
    assert converged.mean() > 0.7
    for residual in (infos.ncp.primal_feasibility, infos.ncp.dual_feasibility, infos.ncp.complementarity):
        assert float(jnp.max(residual)) < 1e-6
    assert float(jnp.min(infos.distance)) > -0.01  # nothing sinks into the floor
    assert float(jnp.max(jnp.abs(xs[-1, 19:]))) < 0.05  # at rest (m/s, rad/s)


def test_solo12_polish_solves_perturbed_steps_without_admm():
    """On states and torques perturbed as R-DDP samples them (feet sliding, lifting, pressing),
    Solo-12's default solver (sticking guess and Newton polish) needs no ADMM iteration and
    gives the next states of plain ADMM (the impulses are unique there: four feet, 18 dofs)."""
    solo = _solo()
    plain = solo.with_options(solver=dataclasses.replace(solo.solver, polish=False))
    x0 = solo.initial_state()
    key_x, key_u = jax.random.split(jax.random.key(5))
    scale = jnp.concatenate([jnp.full(19, 1e-2), jnp.full(18, 1e-1)])
    xs = jax.vmap(solo.project_state)(x0[None] + scale[None] * jax.random.normal(key_x, (16, solo.nx)))
    us = sim.solo12_standing_torques(solo, x0)[None] + jax.random.normal(key_u, (16, solo.nu))
    step = eqx.filter_jit(lambda system: jax.vmap(system.step_with_info)(xs, us))
    (polished, info), (reference, reference_info) = step(solo), step(plain)
    assert bool(jnp.all(info.ncp.converged)) and bool(jnp.all(reference_info.ncp.converged))
    assert bool(jnp.all(info.ncp.iterations == 0)) and int(jnp.max(reference_info.ncp.iterations)) > 20
    # ADMM stops at complementarity residuals of 1e-10 (N s x m/s): with the impulses of
    # a sliding foot (~1e-2 N s) its contact velocities are known to ~1e-8 m/s only, while
    # Newton ends at the rounding error.
    assert float(jnp.max(info.ncp.complementarity)) < 1e-14 and float(jnp.max(info.ncp.dual_feasibility)) < 1e-14
    np.testing.assert_allclose(polished, reference, rtol=0, atol=1e-7)


def test_solo12_under_random_open_loop_torques_stays_finite():
    """Open-loop torques (standing torques plus uniform noise of +-0.3 N m, fresh every step)
    make Solo fall: a physical outcome. With the rotor inertia and the implicit joint damping
    the fall stays finite and the contact solves converge; without them (the bare URDF) a
    lifted lower leg spins up until semi-implicit Euler creates energy: the step is then
    flagged as diverged, and the rollout held, before any value turns non-finite."""
    solo = _solo()
    bare = sim.solo12(armature=0.0, joint_damping=0.0, model=solo.model)
    x0 = solo.initial_state()
    standing = sim.solo12_standing_torques(solo, x0)
    noise = jax.random.uniform(jax.random.key(0), (3, 300, 12), minval=-0.3, maxval=0.3)
    rollout = eqx.filter_jit(lambda system, us: jax.vmap(lambda u: system.rollout(x0, u))(us))
    us = standing[None, None] + noise
    xs, infos = rollout(solo, us)
    assert bool(jnp.all(jnp.isfinite(xs)))
    assert not bool(jnp.any(infos.diverged))
    assert float(jnp.mean(infos.ncp.converged)) > 0.99
    assert float(jnp.min(xs[:, -1, 2])) < float(x0[2]) - 0.05  # it did fall
    xs, infos = rollout(bare, us)
    assert bool(jnp.all(jnp.isfinite(xs)))  # held at the last valid state, not NaN
    assert bool(jnp.all(infos.diverged[:, -1]))  # every run left the valid range...
    first = jnp.argmax(infos.diverged, axis=1)
    assert bool(jnp.all(first > 10))  # ...after the fall started, not at once
    held = xs[jnp.arange(3), first + 1]
    np.testing.assert_array_equal(xs[:, -1], held)


def test_joint_damping_is_implicit_and_dissipates():
    """A free-floating Solo (no gravity, far from the floor) with spinning joints: damping
    removes kinetic energy (below the undamped run at every step, which itself drifts only by
    the integrator's error), and at a huge damping the implicit step stops the joints within
    a step instead of reversing them (an explicit ``D v`` would overshoot once h d / I > 2)."""
    solo = _solo()
    x0 = solo.initial_state().at[2].add(1.0)  # one metre up: no contact
    nq = solo.model.nq
    x0 = x0.at[nq + 6 :].set(5.0)
    free = dataclasses.replace(solo, model=dataclasses.replace(solo.model, gravity=jnp.zeros(3)))
    undamped = dataclasses.replace(free, joints=sim.Joints())
    heavy = dataclasses.replace(free, joints=sim.Joints(damping=free.damping() * 1e4))
    us = jnp.zeros((20, 12))

    def energies(system):
        xs, infos = _rollout(system, x0, us)
        assert not bool(jnp.any(infos.diverged))
        return xs, _energies(system, xs)

    _, e_undamped = energies(undamped)
    _, e_damped = energies(free)
    xs, e_heavy = energies(heavy)
    np.testing.assert_allclose(e_undamped, e_undamped[0], rtol=0.03)  # semi-implicit Euler drift
    assert bool(jnp.all(e_damped[1:] < e_undamped[1:] - 1e-3))
    assert bool(jnp.all(jnp.diff(e_damped) < 0))
    assert float(e_heavy[1]) < 0.5 * float(e_damped[1])
    joint_speeds = xs[1:, nq + 6 :]
    assert float(jnp.min(joint_speeds[0])) >= 0.0  # the first step did not reverse them
    assert float(jnp.max(jnp.abs(joint_speeds))) < 0.05  # stopped at once, and stay stopped


def test_solo12_body_spheres_lie_within_the_urdf_collision_meshes():
    """The base and knee spheres of ``solo12(body_contacts=True)`` are taken from the bounding
    boxes of the URDF's collision meshes: every sphere stays inside the box of the mesh of its
    body, and the base spheres reach its bottom face."""
    import trimesh

    meshes = sim.example_robot_data_root() / "robots" / "solo_description" / "meshes" / "stl"
    base = trimesh.load(meshes / "solo12" / "solo_12_base.stl").bounds
    solo = sim.solo12(body_contacts=True, model=_solo().model)
    assert solo.num_contacts == 12
    centres, radii = np.asarray(solo.geometry.sphere_offsets[4:8]), np.asarray(solo.geometry.sphere_radii[4:8])
    mm = 1e-4  # the constants are rounded to 0.1 mm
    assert np.all(centres - radii[:, None] >= base[0] - mm) and np.all(centres + radii[:, None] <= base[1] + mm)
    np.testing.assert_allclose(centres[:, 2] - radii, np.full(4, base[0, 2]), atol=mm)
    np.testing.assert_allclose(np.abs(centres[:, :2]) + radii[:, None], np.tile(base[1, :2], (4, 1)), atol=mm)
    # The knee sphere covers the lower leg's width at the knee and the upper leg's end.
    lower = trimesh.load(meshes / "with_foot" / "solo_lower_leg_left_side.stl").bounds
    assert sim.SOLO12_KNEE_RADIUS >= max(np.abs(lower[:, 0]).max(), lower[1, 2])
    # Standing, only the feet touch; the standing torques still hold the robot.
    x0 = solo.initial_state()
    distance, _, _ = solo.contacts(solo.split(x0)[0])
    np.testing.assert_allclose(distance[:4], 0.0, atol=1e-12)
    assert float(jnp.min(distance[4:])) > 0.05
    np.testing.assert_allclose(sim.solo12_standing_torques(solo, x0), sim.solo12_standing_torques(_solo(), x0), atol=1e-12)


def test_torques_are_clipped_and_reported():
    solo = _solo()
    x0 = solo.initial_state()
    step = jax.jit(lambda a, b: solo.step_with_info(a, b))
    big, info = step(x0, jnp.full(12, 10.0))
    limited, info_limited = step(x0, jnp.full(12, sim.SOLO12_TORQUE_LIMIT))
    assert bool(info.torque_clipped) and not bool(info_limited.torque_clipped)
    np.testing.assert_allclose(big, limited, atol=1e-12)


def test_rollout_with_feedback_applies_it_at_every_step():
    """``rollout(x0, us, feedback)`` steps with ``us[t] + feedback(x_t)``: the same states as
    a loop of single steps, and a damping feedback slows a dropped cube's fall."""
    cube = _cube()
    x0 = cube.initial_state().at[2].add(0.2)
    us = jnp.zeros((15, 6))
    damping = lambda x: jnp.concatenate([-5.0 * x[7:10], jnp.zeros(3)])  # noqa: E731  (force on v)
    xs, _ = jax.jit(lambda a, b: cube.rollout(a, b, feedback=damping))(x0, us)
    step = jax.jit(lambda a, b: cube.step(a, b))
    x = x0
    for t in range(us.shape[0]):
        x = step(x, us[t] + damping(x))
        np.testing.assert_allclose(xs[t + 1], x, atol=1e-9)
    free, _ = _rollout(cube, x0, us)
    assert float(xs[5, 9]) > float(free[5, 9]) + 1e-3  # falls slower than without feedback


def test_step_vmaps_over_states_and_inputs(getkey):
    cube = _cube()
    rest = cube.initial_state()
    xs = jnp.stack([rest.at[2].set(z) for z in (0.1, 0.15, 0.3)])
    us = jax.random.normal(getkey(), (3, 6))
    batched = jax.jit(jax.vmap(lambda a, b: cube.step(a, b)))(xs, us)
    step = jax.jit(lambda a, b: cube.step(a, b))
    for i in range(3):
        np.testing.assert_allclose(batched[i], step(xs[i], us[i]), atol=1e-12)


def test_a_step_from_an_already_diverged_state_reports_it_instead_of_raising():
    """A finite but absurd state (what a diverged simulation reaches: 1e8 m, 1e11 rad/s; found
    in a DDP line-search trial under saturated feedback) makes the mass matrix indefinite by
    rounding and the contact problem non-finite: the step reports a diverged, non-finite next
    state (a rollout holds, a DDP trial is rejected) rather than aborting on the NCP solver's
    input check, which is for bad inputs."""
    solo = _solo()
    x = solo.initial_state().at[:3].set(jnp.array([-1.0e8, 1.4e8, 3.2e8])).at[7:].set(1e9).at[19:].set(1e11)
    x_next, info = eqx.filter_jit(lambda system, x, u: system.step_with_info(x, u))(solo, x, jnp.full(12, 2.7))
    assert bool(info.diverged) and not bool(jnp.all(jnp.isfinite(x_next)))
    with pytest.raises(ValueError, match="G contains NaN"):  # the solver's own check stands
        sim.solve_ncp(jnp.full((3, 3), jnp.nan), jnp.zeros(3), jnp.ones(1))


def test_bad_input_is_named():
    cube = _cube()
    rest = cube.initial_state()
    with pytest.raises(ValueError, match=r"x must have shape \(nx,\) = \(13,\)"):
        cube.step(rest[:12], jnp.zeros(6))
    with pytest.raises(ValueError, match=r"u must have shape \(nu,\) = \(6,\)"):
        cube.step(rest, jnp.zeros(3))
    with pytest.raises(ValueError, match="x .* NaN"):
        cube.step(rest.at[0].set(jnp.nan), jnp.zeros(6))
    with pytest.raises(ValueError, match="us must have shape"):
        cube.rollout(rest, jnp.zeros(6))
    with pytest.raises(ValueError, match="contact must be"):
        sim.cube(contact="springy")
    with pytest.raises(ValueError, match="side must be positive"):
        sim.cube(side=-1.0)
    with pytest.raises(ValueError, match="joint_damping must be non-negative"):
        sim.solo12(joint_damping=-0.1, model=_solo().model)
    with pytest.raises(ValueError, match=r"joints.damping must have shape \(6,\)"):
        dataclasses.replace(cube, joints=sim.Joints(damping=jnp.ones(3)))
    # Under jit a NaN state is caught at run time, with the same message.
    with pytest.raises(Exception, match="NaN"):
        jax.jit(lambda a: cube.step(a, jnp.zeros(6)))(rest.at[0].set(jnp.nan)).block_until_ready()


@pytest.mark.slow
def test_pusher_pushes_the_box_and_has_null_gradients_before_contact():
    pusher = sim.pusher()
    assert (pusher.nx, pusher.nu) == (17, 2)
    x0 = sim.pusher_start_state(pusher, finger_gap=0.05)
    xs, infos = _rollout(pusher, x0, jnp.tile(jnp.array([8.0, 0.0]), (40, 1)))
    box_x, finger_x = xs[:, 0], xs[:, 7]
    assert float(box_x[-1]) > 0.1  # pushed forward...
    np.testing.assert_allclose(xs[-1, 1:3], jnp.array([0.0, 0.1]), atol=1e-6)  # ...straight, on the floor
    np.testing.assert_allclose(xs[-1, 3:7], jnp.array([0.0, 0.0, 0.0, 1.0]), atol=1e-6)
    # The finger stays at the face: its signed distance to the box never goes below -1 mm.
    assert float(jnp.min(infos.distance[:, -1])) > -1e-3
    assert float(jnp.max(finger_x - box_x)) < -0.1 - 0.02 + 1e-3
    # Null gradient: over 5 steps a gentle push does not reach the box (5 cm away).
    grad = jax.jit(jax.grad(lambda f: pusher.rollout(x0, jnp.tile(jnp.array([f, 0.0]), (5, 1)))[0][-1, 0]))(1.0)
    assert float(grad) == 0.0


def test_pusher_gradients_match_finite_differences_while_pushing():
    pusher = sim.pusher(solver=sim.NCPSolver(tolerance=1e-12, max_iterations=3000))
    x0 = sim.pusher_start_state(pusher, finger_gap=0.0)
    x = x0.at[9].set(0.2).at[9 + 6].set(0.2)  # box and finger sliding together at 0.2 m/s
    u = jnp.array([9.0, 0.3])
    step = jax.jit(lambda a, b: pusher.step(a, b))
    jac = jax.jit(jax.jacfwd(lambda b: pusher.step(x, b)))(u)
    fd = _central_differences(lambda b: step(x, jnp.asarray(b)), u)
    # Box on 4 coplanar corners: impulses are not unique (see the sliding cube test), and with
    # the finger's contact beside them the split of the box's weight among its corners, which the
    # solver's path selects, moves the finger's velocity by up to 1e-4 of a unit of force in the
    # finite differences (measured 1.0e-4; 2.7e-5 with NCPSolver(scaling=False), which selects
    # another split): the implicit derivative is the least-squares one.
    np.testing.assert_allclose(jac, fd, atol=1.5e-4)
    assert float(jnp.abs(jac[9, 0])) > 1e-3  # the finger force moves the box


_PUSHER_SOLVER_CHECK = """
import dataclasses
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from rsmooth import sim
jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")
pusher = sim.pusher()
plain = pusher.with_options(solver=sim.NCPSolver())
batch, steps = 16, 30
forces = 5.0 * jax.random.normal(jax.random.key(0), (steps, batch, 2))
x0 = jnp.tile(pusher.initial_state(), (batch, 1))
xs, _ = jax.jit(jax.vmap(pusher.rollout, in_axes=(0, 1)))(x0, forces)  # (batch, steps + 1, nx)
states, inputs = xs[:, :-1].reshape(-1, pusher.nx), jnp.swapaxes(forces, 0, 1).reshape(-1, 2)
step = eqx.filter_jit(jax.vmap(lambda system, x, u: system.step_with_info(x, u), in_axes=(None, 0, 0)))
x_guess, info_guess = step(pusher, states, inputs)
x_plain, info_plain = step(plain, states, inputs)
guessed = np.asarray(info_guess.ncp.iterations == 0)
assert guessed.mean() > 0.5  # the box sticks in most steps: no ADMM there
both = np.asarray(info_guess.ncp.converged & info_plain.ncp.converged)
assert both.mean() > 0.9
np.testing.assert_allclose(x_guess[both], x_plain[both], atol=1e-7)
assert int(jnp.sum(~info_guess.ncp.converged)) <= int(jnp.sum(~info_plain.ncp.converged))
"""


def test_pusher_default_solver_steps_as_plain_admm_and_converges():
    """The pusher's solver (the sticking guess by the pseudo-inverse, then ADMM from zero) on the
    states of rollouts under random finger forces (the box rests, is pushed, slides, stops):
    where both converge its next states are plain ADMM's (sliding on four coplanar corners
    has non-unique solutions, so this checks that it finds the same one), and it leaves no
    more solves unconverged.

    In a fresh process: compiling this batched rollout crashed XLA:CPU (jaxlib 0.10, a
    segmentation fault in `backend_compile_and_load`) in a pytest-xdist worker that had
    compiled many other programs, and never in a fresh one."""
    done = subprocess.run([sys.executable, "-c", _PUSHER_SOLVER_CHECK], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-4000:]


def _sliding_ball():
    system = sim.ball_wall(solver=sim.NCPSolver(tolerance=1e-13, max_iterations=2000))
    x = system.state(jnp.array([0.0, 0.0, 0.0499, 0.0, 0.0, 0.0, 1.0]), jnp.array([0.4, 0.1, 0.0, 0.0, 3.0, 1.0]))
    return system, x, jnp.array([0.1, 0.05, -0.2])


def _solo_stepping():
    solo = _solo()
    x = solo.initial_state()
    noise = jax.random.normal(jax.random.key(3), x.shape) * jnp.concatenate([jnp.full(19, 1e-3), jnp.full(18, 1e-2)])
    x = (x + noise).at[3:7].set(x[3:7] / jnp.linalg.norm(x[3:7]))
    return solo, x, sim.solo12_standing_torques(solo, x) + 0.1


# (Reverse mode goes through the same rule: the finite-difference tests above use jacrev; the
# box contacts of the pusher are checked against finite differences above.) With four coplanar
# contacts (a box on the floor) the impulses are not unique: the damped least-squares solve then
# amplifies rounding differences by up to ~1 / sqrt(1e-12), and the two derivatives, computed in
# different orders, agree to ~1e-6 only; the cases here have unique impulses.
@pytest.mark.parametrize(
    "case, tolerance", [(_sliding_ball, 1e-9), (_solo_stepping, 1e-9)]
)
@pytest.mark.slow
def test_implicit_step_derivative_equals_the_autodiff_reference(case, tolerance):
    """The default derivative (implicit function theorem on momentum balance + NCP) equals
    autodiff through CRBA, Cholesky and the Delassus matrix, for the next state and the
    impulses (unique ones), with respect to state and input; so does step_and_jacobians."""
    system, x, u = case()
    reference = system.with_options(derivative="autodiff")
    assert system.derivative == "implicit"

    def jacobians(s):
        def outputs(a, b):
            x_next, info = s.step_with_info(a, b)
            return (x_next, info.impulse), x_next

        return jax.jit(jax.jacfwd(outputs, argnums=(0, 1), has_aux=True))(x, u)

    ((ours_x, ours_impulse), stepped), ((theirs_x, theirs_impulse), _) = jacobians(system), jacobians(reference)
    for ours, theirs in zip(ours_x, theirs_x):  # d x_next / d x, d x_next / d u
        scale = float(jnp.max(jnp.abs(theirs)))
        assert scale > 0
        np.testing.assert_allclose(ours, theirs, rtol=0, atol=tolerance * scale)
    # step_and_jacobians: the same Jacobians with separate tangent passes over q, v and u
    x_next, fx, fu = jax.jit(lambda a, b: system.step_and_jacobians(a, b))(x, u)
    np.testing.assert_allclose(x_next, stepped, rtol=1e-12, atol=1e-12)
    for ours, theirs in zip((fx, fu), theirs_x):
        np.testing.assert_allclose(ours, theirs, rtol=0, atol=tolerance * float(jnp.max(jnp.abs(theirs))))
    for ours, theirs in zip(ours_impulse, theirs_impulse):
        np.testing.assert_allclose(ours, theirs, rtol=0, atol=tolerance * float(jnp.max(jnp.abs(theirs))) + 1e-15)


def test_implicit_step_derivative_with_respect_to_system_parameters():
    """Derivatives with respect to the friction coefficient and the time step (fields of the
    system) also go through the implicit rule and equal the autodiff reference."""
    system, x, u = _sliding_ball()
    reference = system.with_options(derivative="autodiff")

    def by_parameters(s):
        def step(friction, time_step):
            varied = eqx.tree_at(lambda t: (t.geometry.friction, t.options.time_step), s, (friction, time_step))
            return varied.step(x, u)

        return jax.jit(jax.jacfwd(step, argnums=(0, 1)))(s.geometry.friction, s.time_step)

    for ours, theirs in zip(by_parameters(system), by_parameters(reference)):
        assert float(jnp.max(jnp.abs(theirs))) > 1e-3
        np.testing.assert_allclose(ours, theirs, rtol=0, atol=1e-9 * float(jnp.max(jnp.abs(theirs))))


def test_every_factory_gives_its_initial_state():
    """``system.initial_state()``: finite, of the system's shape, at zero velocity, with the
    system's contact spheres touching (a body resting on its first half-space, the feet on the
    floor) and none penetrating; the pusher's is pusher_start_state's default, a box on an
    incline rests flat on it, and one step from the ball's start stays put."""
    distance = eqx.filter_jit(lambda system, q: system.contacts(q)[0])
    systems = {"cube": _cube(), "box": sim.box(), "ball": sim.ball(), "ball_wall": sim.ball_wall(),
               "pusher": sim.pusher(), "solo12": _solo()}
    for name, system in systems.items():
        x = system.initial_state()
        assert x.shape == (system.nx,) and bool(jnp.all(jnp.isfinite(x))), name
        q, v = system.split(x)
        np.testing.assert_array_equal(v, 0.0, err_msg=name)
        d = distance(system, q)
        assert abs(float(jnp.min(d))) < 1e-12, name
    np.testing.assert_array_equal(systems["pusher"].initial_state(), sim.pusher_start_state(systems["pusher"]))
    np.testing.assert_allclose(systems["ball_wall"].initial_state()[:3], [0.0, 0.0, 0.05])
    incline = sim.box(planes=[((0.0, 0.3, 1.0), 0.1)])
    d = distance(incline, incline.split(incline.initial_state())[0])
    np.testing.assert_allclose(jnp.sort(d)[:4], 0.0, atol=1e-12)  # four corners on the plane
    assert float(jnp.sort(d)[4]) > 0.1
    # Without a configuration of its own: the model's neutral one (identity orientation).
    neutral = dataclasses.replace(systems["ball"], initial_configuration=None).initial_state()
    np.testing.assert_array_equal(neutral[:7], [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0])
    # One step from the ball's start (ADMM from zero, to its tolerance of 1e-10 on the
    # impulses: a tangential impulse of that size spins the ball, r / I = 500 / (kg m), at
    # about 1e-7 rad/s) leaves it where it is.
    ball = systems["ball_wall"]
    x = ball.initial_state()
    x_next, info = eqx.filter_jit(lambda s, a, b: s.step_with_info(a, b))(ball, x, jnp.zeros(3))
    assert bool(info.ncp.result == RESULTS.successful)
    np.testing.assert_allclose(x_next, x, atol=1e-6)
    np.testing.assert_allclose(x_next[:7], x[:7], atol=1e-8)


def test_rollout_without_traced_checks_reports_an_invalid_contact_problem():
    """Traced without the steps' traced checks (host callbacks, which JAX's persistent
    compilation cache does not store), a rollout reports what they raised on: a traced
    negative friction is RESULTS.invalid_input in every step where the ball touches."""
    from rsmooth import _checks

    system = sim.ball(friction=0.5)
    x0, us = system.initial_state(), jnp.zeros((3, system.nu))
    assert "callback" in str(jax.make_jaxpr(system.rollout)(x0, us))
    with _checks.without_traced_checks():
        assert "callback" not in str(jax.make_jaxpr(system.rollout)(x0, us))

    def rollout(mu):
        return eqx.tree_at(lambda s: s.geometry.friction, system, jnp.reshape(mu, (1,))).rollout(x0, us)

    with _checks.without_traced_checks():
        _, infos = jax.jit(rollout)(jnp.asarray(-0.5))
        _, fine = jax.jit(rollout)(jnp.asarray(0.5))
    assert np.all(np.asarray(infos.ncp.result == RESULTS.invalid_input))
    with pytest.warns(sim.SimulationWarning, match="3 invalid_input"):
        sim.check_steps(infos)
    assert np.all(np.asarray(fine.ncp.converged))


ARM = """
<mujoco><option timestep="0.01"/>
  <worldbody>
    <body name="upper" pos="0 0 1"><joint name="shoulder" type="hinge" axis="0 1 0" damping="0.1"/>
      <geom type="capsule" fromto="0 0 0 0.4 0 0" size="0.03" mass="2"/>
      <body name="lower" pos="0.4 0 0"><joint name="elbow" type="hinge" axis="0 1 0" damping="0.1"/>
        <geom type="capsule" fromto="0 0 0 0.3 0 0.1" size="0.025" mass="1"/>
      </body>
    </body>
  </worldbody>
  <actuator><motor joint="shoulder" ctrlrange="-50 50"/><motor joint="elbow" ctrlrange="-20 20"/></actuator>
</mujoco>
"""


def test_gravity_compensation_holds_an_arm_and_its_derivative_is_the_steps():
    # A two-link arm out of its hanging rest: under gravity compensation and no input it stays
    # where it is (its configuration exactly, to rounding); without, it falls. The step's
    # Jacobians include the compensation's dependence on the configuration (central
    # differences, step 1e-6: error O(1e-10)).
    arm = sim.scene(ARM)
    held = arm.with_gravity_compensation()
    x0 = arm.state(jnp.array([0.4, -0.7]))
    u = jnp.zeros(2)
    xs_held, _ = _rollout(held, x0, jnp.zeros((50, 2)))
    xs_free, _ = _rollout(arm, x0, jnp.zeros((50, 2)))
    np.testing.assert_allclose(xs_held[:, :2], np.broadcast_to(x0[:2], (51, 2)), atol=1e-12)
    assert float(jnp.max(jnp.abs(xs_free[-1, :2] - x0[:2]))) > 0.1
    x = x0.at[2:].set(jnp.array([0.3, -0.5]))
    u = jnp.array([1.0, -0.5])
    step_and_jacobians = eqx.filter_jit(lambda s, x_, u_: s.step_and_jacobians(x_, u_))
    step = eqx.filter_jit(lambda s, x_, u_: s.step(x_, u_))
    _, fx, fu = step_and_jacobians(held, x, u)
    eps = 1e-6
    central = lambda f, z, i: (f(z.at[i].add(eps)) - f(z.at[i].add(-eps))) / (2 * eps)  # noqa: E731
    fx_fd = jnp.stack([central(lambda z: step(held, z, u), x, i) for i in range(4)], axis=1)
    fu_fd = jnp.stack([central(lambda w: step(held, x, w), u, i) for i in range(2)], axis=1)
    np.testing.assert_allclose(fx, fx_fd, atol=1e-7)
    np.testing.assert_allclose(fu, fu_fd, atol=1e-7)
    # the compensation's own derivative matters: without it the Jacobians differ
    _, fx_plain, _ = step_and_jacobians(arm, x, u)
    assert float(jnp.max(jnp.abs(fx - fx_plain))) > 1e-3
    with pytest.raises(ValueError, match="gravity_compensation adds efforts to the actuated dofs"):
        sim.ball().with_gravity_compensation()
