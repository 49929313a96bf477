"""The contact budget (`Options.max_contacts`) and the broad phase
(`Options.max_pairs`): a limit that holds every touching contact or every pair within
its margin changes nothing (states, impulses, step Jacobians), one that leaves some out counts
and reports them, and bad limits are refused by name."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import rsmooth.sim as sim


def _bodies(max_contacts=None):
    """Two balls and a capsule lying on a floor, apart: four floor candidates, all touching
    (a ball's one point, the capsule's two ends), and three between the bodies, not touching.
    The balls' contact forces are determinate, the capsule's up to equal and opposite axial
    friction at its ends (a box's four corners leave more undetermined)."""
    shapes = [sim.Sphere(0.1), sim.Sphere(0.05), sim.Capsule(0.05, 0.2)]
    positions = [[0.0, 0.0, 0.1], [0.5, 0.0, 0.05], [1.0, 0.1, 0.05]]
    lying = [np.sin(np.pi / 4), 0.0, 0.0, np.cos(np.pi / 4)]  # the capsule's axis along y
    return sim.bodies(
        shapes, [1.0, 0.5, 0.3], positions, orientations=[[0, 0, 0, 1], [0, 0, 0, 1], lying], max_contacts=max_contacts
    )


def _sliding_state(system):
    """The bodies sliding at different speeds and spinning about the vertical."""
    x = np.array(system.initial_state())
    v = x[system.model.nq :].reshape(3, 6)
    v[:, :3] = [[0.6, 0.0, 0.0], [-0.3, 0.4, 0.0], [0.0, -0.5, 0.0]]
    v[:, 5] = [1.0, -2.0, 0.5]
    return jnp.asarray(np.concatenate([x[: system.model.nq], v.reshape(-1)]))


def _rollout(system, x0, steps):
    us = jnp.zeros((steps, system.nu))
    return eqx.filter_jit(lambda s, x: s.rollout(x, us))(system, x0)


def test_a_budget_holding_every_touching_contact_changes_nothing():
    full, budget = _bodies(), _bodies(max_contacts=4)
    assert full.num_contacts == budget.num_contacts == 7
    x0 = _sliding_state(full)
    xs_full, infos_full = _rollout(full, x0, 30)
    xs, infos = _rollout(budget, x0, 30)
    assert sim.check_steps(infos)["dropped_contact_steps"] == 0  # no warning: errors in the suite
    # the same contact problems, solved to the solver's tolerance (1e-10 in impulse residual)
    np.testing.assert_allclose(np.asarray(xs), np.asarray(xs_full), atol=1e-8)
    # the impulses up to the capsule's one non-unique direction: equal and opposite axial
    # friction at its two ends (contacts 2 and 3) moves nothing, and solves of different sizes
    # may return different amounts of it
    impulse, impulse_full = (np.asarray(i).reshape(30, -1, 3) for i in (infos.impulse, infos_full.impulse))
    np.testing.assert_allclose(impulse[..., 2], impulse_full[..., 2], atol=1e-8)  # normal
    np.testing.assert_allclose(impulse[:, :2], impulse_full[:, :2], atol=1e-8)  # the balls'
    np.testing.assert_allclose(impulse[:, 2:4, :2].sum(1), impulse_full[:, 2:4, :2].sum(1), atol=1e-8)
    np.testing.assert_allclose(impulse[:, 4:], impulse_full[:, 4:], atol=1e-8)  # none between bodies
    # the left-out candidates (between the bodies, 0.3 m apart) have no impulse
    assert np.all(np.asarray(infos.mode)[:, 4:] == sim.SEPARATED)
    # the step Jacobians are those of the selected problem, equal to the full one's here
    x, u = xs[10], jnp.zeros(budget.nu)
    step_jacobians = eqx.filter_jit(lambda s, x_, u_: s.step_and_jacobians(x_, u_))
    _, fx, fu = step_jacobians(budget, x, u)
    _, fx_full, fu_full = step_jacobians(full, x, u)
    np.testing.assert_allclose(np.asarray(fx), np.asarray(fx_full), atol=1e-6)
    np.testing.assert_allclose(np.asarray(fu), np.asarray(fu_full), atol=1e-6)


def test_a_budget_too_small_reports_the_contacts_it_leaves_out():
    """Two of the four resting contacts: the two left out close under gravity within the
    step, so they are counted, and check_steps warns."""
    system = _bodies(max_contacts=2)
    _, infos = _rollout(system, system.initial_state(), 3)
    assert np.all(np.asarray(infos.dropped_contacts) == 2)
    assert np.all(np.sum(np.asarray(infos.impulse).reshape(3, -1, 3)[..., 2] > 0, axis=1) <= 2)
    with pytest.warns(sim.SimulationWarning, match="max_contacts"):
        counts = sim.check_steps(infos)
    assert counts["dropped_contact_steps"] == 3


@pytest.mark.parametrize("bad", [0, -3, 2.5, True, "8"])
def test_bad_budgets_are_refused_by_name(bad):
    with pytest.raises(ValueError, match="max_contacts must be a positive integer or None"):
        _bodies().with_contact_budget(bad)


def test_a_budget_needs_hard_contact():
    compliant = sim.ball(contact=sim.SpringDamper(stiffness=1e4, damping=10.0, friction=0.3))
    with pytest.raises(ValueError, match="max_contacts budgets the hard-contact NCP"):
        compliant.with_contact_budget(1)


def _balls(max_pairs=None):
    """Four balls on a floor: ball 0 rolls into ball 1 (touching), balls 2 and 3 lie apart.
    Two pair groups: ball-floor (4 pairs, all touching) and ball-ball (6 pairs, one near)."""
    positions = [[0.0, 0.0, 0.1], [0.2, 0.0, 0.1], [1.0, 0.3, 0.1], [2.0, -0.4, 0.1]]
    system = sim.bodies([sim.Sphere(0.1)] * 4, [1.0, 0.5, 0.7, 0.3], positions, max_pairs=max_pairs)
    x = np.array(system.initial_state())
    v = x[system.model.nq :].reshape(4, 6)
    v[0, 0], v[2, 1], v[3, 5] = 0.8, -0.2, 3.0
    return system, jnp.asarray(np.concatenate([x[: system.model.nq], v.reshape(-1)]))


def test_a_pair_limit_holding_every_near_pair_changes_nothing():
    # max_pairs = 4 collides every ball-floor pair and the 4 closest of the 6 ball-ball pairs:
    # the two left out are more than 0.5 m apart, so they have no contact anyway
    (full, x0), (limited, _) = _balls(), _balls(max_pairs=4)
    xs_full, infos_full = _rollout(full, x0, 40)
    xs, infos = _rollout(limited, x0, 40)
    assert sim.check_steps(infos)["skipped_pair_steps"] == 0  # no warning: errors in the suite
    assert float(jnp.max(jnp.abs(xs[-1, 0:3] - xs[0, 0:3]))) > 0.05  # ball 0 moved and pushed ball 1
    # the same contact problems (a left-out pair's entries, like a far pair's, are inactive
    # rows of zeros): equal up to the rounding of the two compiled programs
    np.testing.assert_allclose(np.asarray(xs), np.asarray(xs_full), rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(infos.impulse), np.asarray(infos_full.impulse), rtol=0, atol=1e-12)
    step_jacobians = eqx.filter_jit(lambda s, x_, u_: s.step_and_jacobians(x_, u_))
    for a, b in zip(step_jacobians(limited, xs[5], jnp.zeros(limited.nu)), step_jacobians(full, xs[5], jnp.zeros(full.nu))):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=0, atol=1e-10)


def test_a_pair_limit_too_small_reports_the_pairs_it_leaves_out():
    # max_pairs = 1: of the 4 touching ball-floor pairs 3 are not collided (the balls fall
    # through the floor there); the ball-ball group has one near pair, which it collides
    system, x0 = _balls(max_pairs=1)
    assert int(system.skipped_pairs(x0[: system.model.nq])) == 3
    _, infos = _rollout(system, x0, 3)
    assert np.all(np.asarray(infos.skipped_pairs) == 3)
    with pytest.warns(sim.SimulationWarning, match="max_pairs"):
        counts = sim.check_steps(infos)
    assert counts["skipped_pair_steps"] == 3


@pytest.mark.parametrize("bad", [0, -3, 2.5, True, "8"])
def test_bad_pair_limits_are_refused_by_name(bad):
    with pytest.raises(ValueError, match="max_pairs must be a positive integer or None"):
        _bodies().with_contact_budget(None, bad)


def test_bounding_gaps_bound_each_pairs_distance():
    # a group of box pairs of different sizes at random poses: each pair's gap is its own
    # bounding spheres' (not a radius pooled over the group) and never above its distance
    from rsmooth.sim import _spatial, _simulator

    rng = np.random.default_rng(3)
    count = 12
    boxes = [sim.Box(rng.uniform(0.02, 0.3, 3)) for _ in range(2 * count)]
    rotations = np.stack([np.asarray(_spatial.exp3(jnp.asarray(rng.normal(size=3)))) for _ in range(2 * count)])
    translations = rng.uniform(-0.6, 0.6, (2 * count, 3))
    stack = lambda items: jax.tree.map(lambda *leaves: jnp.stack(leaves), *items)  # noqa: E731
    shape1, shape2 = stack(boxes[:count]), stack(boxes[count:])
    pose1 = (jnp.asarray(rotations[:count]), jnp.asarray(translations[:count]))
    pose2 = (jnp.asarray(rotations[count:]), jnp.asarray(translations[count:]))
    gaps = np.asarray(_simulator._bounding_gaps(shape1, pose1, shape2, pose2))
    distances = np.asarray(jax.jit(jax.vmap(sim.collide))(shape1, pose1, shape2, pose2).distance[:, 0])
    for k in range(count):
        expected = (np.linalg.norm(translations[count + k] - translations[k])
                    - np.linalg.norm(boxes[k].half_extents) - np.linalg.norm(boxes[count + k].half_extents))
        np.testing.assert_allclose(gaps[k], expected, rtol=1e-12)
        assert gaps[k] <= distances[k] + 1e-12


def _spheres_scene(count, **kwargs):
    """``count`` free balls in a row above a floor: every ball pair and every ball-floor pair
    collides (one candidate each)."""
    balls = "".join(
        f'<body pos="{0.3 * i} 0 0.2"><freejoint/><geom type="sphere" size="0.1"/></body>' for i in range(count)
    )
    xml = f'<mujoco><worldbody><geom type="plane" size="5 5 0.1"/>{balls}</worldbody></mujoco>'
    return sim.scene(xml, **kwargs)


def test_the_scenes_default_budget_is_four_contacts_per_moving_body_and_at_least_64():
    # 11 balls: 55 + 11 = 66 candidates, above 64: the closest 64 (4 x 11 = 44 is less)
    assert _spheres_scene(11).num_contacts == 66 and _spheres_scene(11).options.max_contacts == 64
    # 10 balls: 45 + 10 = 55 candidates, all solved: no budget
    assert _spheres_scene(10).options.max_contacts is None
    # 20 balls: 210 candidates, 4 x 20 = 80 of them
    assert _spheres_scene(20).options.max_contacts == sim.automatic_contact_budget(210, 20) == 80
    assert _spheres_scene(11, max_contacts=None).options.max_contacts is None
    assert _spheres_scene(11, max_contacts=7).options.max_contacts == 7
    with pytest.raises(ValueError, match="max_contacts must be a positive integer, None or 'auto'"):
        _spheres_scene(2, max_contacts="all")
