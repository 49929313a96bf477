"""Closed-form mechanics: free flight (momentum, energy, spin), sliding and sticking boxes at
high friction, rolling without slipping, the derivative at zero distance, and the contact
solver's guarantees (best iterate, reachable tolerance, reported failures)."""

from __future__ import annotations

import functools
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rsmooth import RESULTS, sim
from rsmooth.sim import _spatial

GRAVITY = 9.81


@eqx.filter_jit
def _rollout(system, x0, us):
    return system.rollout(x0, us)


@eqx.filter_jit
def _energies(system, xs):
    return jax.vmap(lambda x: sim.energy(system, x))(xs)


def _world_velocity(xs):
    """World-frame linear velocity of a free body from states ``(T, 13)`` (body-frame twist)."""
    rotations = jax.vmap(_spatial.quaternion_to_rotation)(xs[:, 3:7])
    return jnp.einsum("tab,tb->ta", rotations, xs[:, 7:10])


@eqx.filter_jit
def _contact_problem(system, x, with_jacobian=False):
    """The contact problem ``(G, g, mu)`` (and ``J``) of a step from ``x`` at zero input."""
    q, v = system.split(x)
    update = system._velocity_update(q, v, jnp.zeros(system.nu), None)
    problem = (update.delassus, update.free_velocity, update.mu)
    return (*problem, update.jacobian) if with_jacobian else problem


@functools.lru_cache(maxsize=None)
def _free_body(inertia: tuple[float, float, float], time_step: float = 0.01):
    """A free body far from its only obstacle (a floor 100 m below), without gravity."""
    system = sim.ball_wall(time_step=time_step, wall_distance=1e3)
    model = sim.free_body(1.0, np.asarray(inertia), name="ball", gravity=(0.0, 0.0, 0.0))
    system = eqx.tree_at(lambda s: s.model, system, model)
    return eqx.tree_at(lambda s: s.geometry.plane_offsets, system, jnp.array([-100.0, -1e3]))


def test_spinning_body_in_free_flight_keeps_its_world_velocity():
    # 1 m/s across a 15 rad/s spin, 100 steps of 10 ms: the world velocity is constant to
    # rounding (an explicit -w x v term, then the frame's rotation, would scale it by
    # sqrt(1 + (h w)^2) per step: 3.04 m/s after 1 s).
    system = _free_body((0.1, 0.1, 0.1))
    x0 = jnp.array([0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.0, 15.0])
    xs, infos = _rollout(system, x0, jnp.zeros((100, 3)))
    velocity = _world_velocity(xs)
    np.testing.assert_allclose(velocity, jnp.broadcast_to(velocity[0], velocity.shape), atol=1e-12)
    np.testing.assert_allclose(xs[-1, :3], x0[:3] + 100 * 0.01 * velocity[0], atol=1e-10)
    energies = _energies(system, xs)
    np.testing.assert_allclose(energies, energies[0], rtol=1e-12)
    assert not bool(jnp.any(infos.diverged))


def test_tumble_about_the_intermediate_axis_keeps_momentum_and_energy():
    # Near the intermediate axis the rotation flips (Dzhanibekov). Linear momentum, kinetic
    # energy and the angular momentum's magnitude |I w| stay exact (an explicit gyroscopic term
    # gained 4.6 % of the energy here, a body-frame linear update a third in a second); the
    # angular momentum's direction in the world moves by the step's O(h) splitting error only.
    inertia = jnp.array([1.0, 2.0, 3.0])
    system = _free_body(tuple(float(i) for i in inertia))
    x0 = jnp.array([0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 1.0, 0.5, -0.2, 0.01, 5.0, 0.01])
    xs, _ = _rollout(system, x0, jnp.zeros((300, 3)))
    velocity = _world_velocity(xs)
    np.testing.assert_allclose(velocity, jnp.broadcast_to(velocity[0], velocity.shape), atol=1e-12)
    energies = _energies(system, xs)
    np.testing.assert_allclose(energies, energies[0], rtol=1e-12)
    rotations = jax.vmap(_spatial.quaternion_to_rotation)(xs[:, 3:7])
    momentum = jnp.einsum("tab,tb->ta", rotations, inertia[None] * xs[:, 10:13])
    np.testing.assert_allclose(jnp.linalg.norm(momentum, axis=1), jnp.linalg.norm(momentum[0]), rtol=1e-12)
    np.testing.assert_allclose(momentum, jnp.broadcast_to(momentum[0], momentum.shape), atol=0.02 * 10.0)
    # the angular velocity about the intermediate axis did turn over within the 3 s
    assert float(jnp.min(xs[:, 11])) < -3.0


def test_spinning_ball_sliding_on_the_floor_settles_into_rolling_at_five_sevenths():
    # A solid ball sliding at v0 without rolling: friction conserves the angular momentum about
    # the contact point, m v r + I w, so it rolls at 5/7 v0 (I = 2/5 m r^2). A spin about the
    # vertical meets no torque (point contact) and stays.
    radius, v0, spin = 0.05, 1.0, 15.0
    system = sim.ball_wall(radius=radius, wall_distance=1e3, friction=0.3)
    x0 = jnp.array([0.0, 0.0, radius, 0.0, 0.0, 0.0, 1.0, v0, 0.0, 0.0, 0.0, 0.0, spin])
    xs, infos = _rollout(system, x0, jnp.zeros((100, 3)))
    assert bool(jnp.all(infos.ncp.converged))
    rotation = _spatial.quaternion_to_rotation(xs[-1, 3:7])
    velocity, omega = rotation @ xs[-1, 7:10], rotation @ xs[-1, 10:13]
    np.testing.assert_allclose(velocity, [5.0 / 7.0 * v0, 0.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(omega, [0.0, 5.0 / 7.0 * v0 / radius, spin], atol=1e-4)
    # the contact point is at rest (rolling without slipping)
    np.testing.assert_allclose(velocity + jnp.cross(omega, jnp.array([0.0, 0.0, -radius])), 0.0, atol=1e-6)
    # sliding lasts t = 2 v0 / (7 mu g) (0.097 s): rolling from step 11 on
    speeds = jnp.linalg.norm(_world_velocity(xs), axis=1)
    np.testing.assert_allclose(speeds[12:], 5.0 / 7.0 * v0, atol=1e-6)


@pytest.mark.parametrize("friction", [0.1, 0.5, 0.8, 0.9, 1.0])
def test_box_slides_without_rocking_and_stops_where_coulomb_says(friction):
    # A box sliding at v0 on four corners decelerates at mu g (it tips only for mu > 1, where
    # the back corners' normal impulse m g (1 - mu) / 2 vanishes). Semi-implicit Euler: the
    # velocity drops by mu g h per step and the box moves h v+ each step, so it travels
    # v0^2 / (2 mu g) - h v0 / 2 to within one step's h v0.
    v0, h = 2.0, 0.01
    system = sim.box(friction=friction)
    x0 = system.initial_state().at[7].set(v0)
    steps = 120 if friction > 0.2 else 10
    xs, infos = _rollout(system, x0, jnp.zeros((steps, 6)))
    assert bool(jnp.all(infos.ncp.converged))
    # the diagnostics: the corners that carry the box slide, the others are separated (the
    # split between the left and right corners is not unique), and the world-frame forces are
    # the weight, Coulomb's friction against the motion, and the front edge carrying mu m g
    # more than the back one (the friction's moment about the centre: the back edge carries
    # m g (1 - mu) / 2, nothing at mu = 1)
    bottom, front = (np.asarray(system.geometry.sphere_offsets[:, k] > 0) for k in (2, 0))
    bottom = ~bottom
    carrying = np.asarray(infos.impulse[1].reshape(8, 3)[:, 2] > 0)
    assert not carrying[~bottom].any()
    np.testing.assert_array_equal(infos.mode[1], np.where(carrying, sim.SLIDING, sim.SEPARATED))
    normal = infos.force[1][:, 2]
    np.testing.assert_allclose(normal[front].sum() - normal[~front].sum(), friction * GRAVITY, atol=1e-6)
    np.testing.assert_allclose(infos.force[1].sum(axis=0), [-friction * GRAVITY, 0.0, GRAVITY], atol=1e-6)
    np.testing.assert_allclose(infos.force[1][~bottom], 0.0, atol=1e-12)
    velocity = _world_velocity(xs)
    np.testing.assert_allclose(jnp.abs(xs[:, 10:13]).max(), 0.0, atol=1e-6)  # no rocking
    np.testing.assert_allclose(xs[:, 2], 0.1, atol=1e-9)
    if friction > 0.2:
        distance = v0**2 / (2 * friction * GRAVITY) - h * v0 / 2
        np.testing.assert_allclose(xs[-1, 0], distance, atol=h * v0 * friction * GRAVITY * h)
        np.testing.assert_allclose(velocity[-1], 0.0, atol=1e-7)  # at rest
    stop = v0 / (friction * GRAVITY * h)
    moving = velocity[1 : min(steps, int(stop))]
    np.testing.assert_allclose(
        moving[:, 0], v0 - friction * GRAVITY * h * jnp.arange(1, moving.shape[0] + 1), atol=1e-7
    )


@pytest.mark.parametrize("friction", [0.5, 0.8, 1.0])
def test_box_sticks_below_the_coulomb_threshold_and_slides_above(friction):
    system = sim.box(friction=friction)
    x0 = system.initial_state()
    threshold = friction * GRAVITY  # 1 kg
    step = jax.jit(lambda x, u: system.step_with_info(x, u))
    for scale, sticks in ((0.95, True), (1.05, False)):
        x, push = x0, jnp.array([scale * threshold, 0.0, 0.0, 0.0, 0.0, 0.0])
        for _ in range(5):
            x, info = step(x, push)
            assert bool(info.ncp.converged)
            carrying = np.asarray(info.impulse.reshape(8, 3)[:, 2] > 0)
            assert not carrying[np.asarray(system.geometry.sphere_offsets[:, 2] > 0)].any()
            np.testing.assert_array_equal(info.mode, np.where(carrying, sim.STICKING if sticks else sim.SLIDING, sim.SEPARATED))
            # friction balances the push while sticking, and is mu m g against it while sliding
            np.testing.assert_allclose(info.force.sum(axis=0)[0], -min(scale, 1.0) * threshold, rtol=1e-6)
        speed = float(x[7])
        if sticks:
            assert abs(speed) < 1e-8
        else:  # accelerates at (F - mu m g) / m
            np.testing.assert_allclose(speed, 5 * 0.01 * (scale - 1.0) * threshold, rtol=1e-6)


def test_derivative_at_zero_distance_is_the_touching_side():
    # A resting cube sits exactly at distance 0. Within the contact skin (1 um) the position
    # correction is linear, so the step's derivative there is the Baumgarte one from both
    # sides (dz+/dz = 1 - beta), as for an infinitesimal penetration; a gap beyond the skin
    # closes within the step (dz+/dz = 0).
    cube = sim.cube()
    x0 = cube.initial_state()

    def height(z):
        return cube.step(x0.at[2].set(z), jnp.zeros(6))[2]

    @jax.jit
    def derivatives(z):  # forward mode (reverse mode transposes the same rule), step_and_jacobians
        return jax.jacfwd(height)(z), cube.step_and_jacobians(x0.at[2].set(z), jnp.zeros(6))[1][2, 2]

    z0 = float(x0[2])
    touching = 1.0 - cube.baumgarte
    for z, expected in ((z0, touching), (z0 - 1e-7, touching), (z0 + 1e-7, touching), (z0 + 1e-5, 0.0)):
        np.testing.assert_allclose(derivatives(z), expected, atol=1e-12)
    # and it is the central finite difference at 0
    heights = jax.jit(jax.vmap(height))(jnp.array([z0 + 1e-7, z0 - 1e-7]))
    np.testing.assert_allclose((heights[0] - heights[1]) / 2e-7, touching, atol=1e-7)


def test_contact_solve_never_returns_worse_than_its_start():
    # A sliding box's contact problem on four corners, its impulses not unique: from a warm
    # start, a capped solve returns the best impulse it saw, never a worse one.
    system = sim.box(friction=0.8)
    x = system.initial_state().at[7].set(2.0)
    G, g, mu = _contact_problem(system, x)
    exact, info = sim.solve_ncp(G, g, mu, solver=system.solver)
    assert bool(info.converged)
    for iterations in (1, 40):
        solver = sim.NCPSolver(max_iterations=iterations)
        for start in (exact, exact * 1.1, jnp.zeros_like(exact)):
            start_residual = max(float(r) for r in sim.ncp_residuals(G, g, mu, sim.project_to_friction_cone(start.reshape(-1, 3), mu).reshape(-1)))
            _, info = sim.solve_ncp(G, g, mu, solver=solver, warm_start=start)
            residual = max(float(r) for r in (info.primal_feasibility, info.dual_feasibility, info.complementarity))
            assert residual <= start_residual


def test_default_tolerance_is_reachable_in_float32():
    system = sim.cube()
    x = system.initial_state().at[7].set(1.0)
    G, g, mu, jacobian = _contact_problem(system, x, with_jacobian=True)
    problem = [a.astype(jnp.float32) for a in (G, g, mu)]
    solver = sim.NCPSolver()
    assert solver.tolerance_for(jnp.float32) == 1e-5 and solver.tolerance_for(jnp.float64) == 1e-10
    impulse, info = sim.solve_ncp(*problem, solver=solver)
    assert impulse.dtype == jnp.float32 and bool(info.converged)
    # the float64 solution's generalized impulse J^T lambda (the impulses of a box on four
    # corners are not unique, their resultant is), to float32's resolution
    reference, _ = sim.solve_ncp(G, g, mu, solver=solver)
    # complementarity <= 1e-5 on corner impulses of m g h / 4 allows contact velocities of 4e-4
    np.testing.assert_allclose(jacobian.T @ impulse, jacobian.T @ reference, atol=4e-4)


def test_unconverged_solves_and_divergence_are_reported():
    # A solver capped at 2 iterations cannot solve a sliding box's problems: every such step is
    # reported, by check_steps (a warning) and by rollout(throw=True) (an error).
    capped = sim.cube(friction=0.8, solver=sim.NCPSolver(max_iterations=2))
    x0 = capped.initial_state().at[7].set(2.0)
    xs, infos = _rollout(capped, x0, jnp.zeros((3, 6)))
    with pytest.warns(sim.SimulationWarning, match="of 3 steps left the contact solve unconverged.*max_iterations_reached: "):
        counts = sim.check_steps(infos, what="the capped box")
    assert counts["unconverged_steps"] > 0 and counts["diverged_steps"] == 0
    with pytest.raises(Exception, match="unconverged contact solve"):
        eqx.filter_jit(lambda s, a, b: s.rollout(a, b, throw=True))(capped, x0, jnp.zeros((3, 6)))
    # a well-solved rollout is silent
    good = sim.box(friction=0.8)
    _, infos = _rollout(good, x0, jnp.zeros((3, 6)))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert sim.check_steps(infos)["unconverged_steps"] == 0
    # A state far beyond float64's resolution of the world-frame inertias (1e7 m) gives no
    # finite step: reported as diverged and unconverged, and step() raises instead of
    # returning NaN.
    far = good.initial_state().at[0].set(1e7)
    _, infos = _rollout(good, far, jnp.zeros((3, 6)))
    assert bool(infos.diverged[0]) and not bool(infos.ncp.converged[0])
    assert bool((infos.ncp.result == RESULTS.nonfinite)[0])
    with pytest.raises(Exception, match="the step diverged"):
        eqx.filter_jit(lambda s, a, b: s.step(a, b))(good, far, jnp.zeros(6))


def test_thrown_spinning_solo12_keeps_its_centroidal_momentum_to_first_order_in_h():
    # Solo-12 thrown and spinning, without gravity or contact, joints moving freely: its
    # centroidal momentum (Pinocchio's computeCentroidalMomentum) is conserved by the physics;
    # the step conserves it up to the explicit velocity-product terms of the joints, an error
    # of first order in h (halving h halves the drift over the same time; without rotor
    # inertia, which the model adds on the joint axes alone and which is not momentum-consistent).
    pin = pytest.importorskip("pinocchio")
    system = sim.solo12(armature=0.0)
    rng = np.random.default_rng(0)
    v0 = np.r_[1.0, 0.5, 0.2, 2.0, -1.0, 3.0, rng.uniform(-5.0, 5.0, 12)]
    x0 = system.initial_state().at[2].add(1.0).at[19:].set(v0)
    system = eqx.tree_at(lambda s: s.model.gravity, system, jnp.zeros(3))
    system = eqx.tree_at(lambda s: s.geometry.plane_offsets, system, system.geometry.plane_offsets - 100.0)
    pin_model = pin.buildModelFromUrdf(str(sim.solo12_urdf_path()), pin.JointModelFreeFlyer())
    data = pin_model.createData()

    def drift(time_step, steps):
        xs, infos = _rollout(system.with_options(time_step=time_step), x0, jnp.zeros((100, 12)))
        assert not bool(jnp.any(infos.diverged))
        momenta = np.array([
            pin.computeCentroidalMomentum(pin_model, data, np.asarray(x[:19]), np.asarray(x[19:])).vector
            for x in xs[: steps + 1]
        ])
        change = np.abs(momenta - momenta[0]).max(axis=0)
        # linear and angular momentum, relative to their magnitudes at the start
        return np.array([change[:3].max() / np.linalg.norm(momenta[0, :3]), change[3:].max() / np.linalg.norm(momenta[0, 3:])])

    coarse, fine = drift(0.01, 50), drift(0.005, 100)  # both 0.5 s
    assert coarse[0] < 0.01 and coarse[1] < 0.1
    np.testing.assert_allclose(fine / coarse, 0.5, atol=0.1)


@pytest.mark.parametrize("friction", [0.1, 0.5, 1.0])
def test_box_on_an_incline_sticks_below_tan_theta_equal_mu_and_slides_at_its_acceleration(friction):
    # A box on a plane of slope theta: it sticks for tan(theta) < mu and slides down with
    # acceleration g (sin(theta) - mu cos(theta)) above (exact per step: semi-implicit Euler
    # on a constant acceleration).
    half = np.array([0.2, 0.1, 0.05])
    for theta, sticks in ((np.arctan(friction) - 0.05, True), (np.arctan(friction) + 0.05, False)):
        normal = np.array([-np.sin(theta), 0.0, np.cos(theta)])
        system = sim.box(half_extents=tuple(half), friction=friction, planes=[(tuple(normal), 0.0)])
        quaternion = np.array([0.0, np.sin(-theta / 2), 0.0, np.cos(-theta / 2)])  # body z along the normal
        x0 = jnp.asarray(np.r_[half[2] * normal, quaternion, np.zeros(6)])
        xs, infos = _rollout(system, x0, jnp.zeros((20, 6)))
        assert bool(jnp.all(infos.ncp.converged))
        downhill = -np.array([np.cos(theta), 0.0, np.sin(theta)])
        speed = _world_velocity(xs) @ downhill
        expected = 0.0 if sticks else GRAVITY * (np.sin(theta) - friction * np.cos(theta))
        np.testing.assert_allclose(speed, expected * 0.01 * np.arange(21), atol=1e-7)
        np.testing.assert_allclose(xs[:, 10:13], 0.0, atol=1e-7)  # no tipping


def test_scenes_agree_with_mujoco():
    # The same scenes in MuJoCo (elliptic friction cones, its soft contact at default
    # stiffness): a box sliding to rest, a ball rolling. Agreement to MuJoCo's contact
    # softness (its box rests 0.1 mm into the floor) and to the closed forms.
    mujoco = pytest.importorskip("mujoco")

    def mujoco_run(body, friction, v0, time_step, duration):
        model = mujoco.MjModel.from_xml_string(f"""<mujoco><option timestep="{time_step}" cone="elliptic" impratio="10"/>
            <worldbody><geom type="plane" size="5 5 .1" friction="{friction} 0 0"/>
            <body pos="0 0 0.1"><freejoint/>{body}</body></worldbody></mujoco>""")
        data = mujoco.MjData(model)
        mujoco.mj_forward(model, data)
        data.qpos[2] = model.geom_size[1][2] if "box" in body else model.geom_size[1][0]
        data.qvel[0] = v0
        for _ in range(int(round(duration / time_step))):
            mujoco.mj_step(model, data)
        return data.qpos.copy(), data.qvel.copy()

    for friction in (0.5, 1.0):
        box = f'<geom type="box" size=".1 .1 .1" mass="1" friction="{friction} 0 0"/>'
        qpos, qvel = mujoco_run(box, friction, 2.0, 0.01, 1.0)
        system = sim.cube(friction=friction)
        xs, _ = _rollout(system, system.initial_state().at[7].set(2.0), jnp.zeros((100, 6)))
        np.testing.assert_allclose(xs[-1, 0], qpos[0], rtol=5e-3)  # slide distance
        np.testing.assert_allclose(xs[-1, 2], qpos[2], atol=2e-4)  # rest height
        np.testing.assert_allclose(qvel[:3], 0.0, atol=1e-6)
    ball = '<geom type="sphere" size=".05" mass="0.1" friction="0.3 0 0"/>'  # MuJoCo takes the larger of two frictions
    qpos, qvel = mujoco_run(ball, 0.3, 1.0, 0.002, 0.5)
    system = sim.ball_wall(friction=0.3, wall_distance=1e3)
    x0 = jnp.array([0.0, 0.0, 0.05, 0.0, 0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    xs, _ = _rollout(system, x0, jnp.zeros((50, 3)))
    ours = _world_velocity(xs)[-1]
    np.testing.assert_allclose(ours, qvel[:3], atol=2e-3)  # rolling speed
    np.testing.assert_allclose(ours[0], 5.0 / 7.0, atol=1e-6)
