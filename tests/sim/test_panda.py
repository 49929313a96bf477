"""The Panda scene's colliding links (`sim.panda_push(colliding_links=...)`). References:
MuJoCo's signed distances (`mj_geomDistance`) between the links' collision geometry and the
table and the box, along trajectories simulated with and without the links colliding, and the
pairs MuJoCo's filters give."""

import equinox as eqx
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from rsmooth import sim
from rsmooth.sim._panda import _compiled_scene

# The tool's sphere shrunk to 2 mm and set 8 cm beside the box's centre line: the fingers reach
# below it (by about 7 mm) and the tool passes beside the box (5 cm half side), so that only the
# links can stop the hand at the table or move the box.
SCENE = {"tool_radius": 0.002, "tool_y": 0.08}
STEPS = 25  # 0.25 s
FORCE = 30.0  # N, at the tool centre point, by joint torques J^T f beyond gravity compensation
MARGIN = 0.01  # the scene's (sim.scene's default): candidates within it have their distance


def test_links_collide_with_the_box_and_the_table_only():
    loaded = sim.panda_push_model(colliding_links=sim.PANDA_HAND_LINKS)
    pairs = {tuple(sorted(_owner(loaded, g) for g in pair)) for pair in loaded.collision_pairs}
    links = [_owner(loaded, g) for g in range(loaded.ngeom) if loaded.body_names[loaded.geom_bodies[g]] in sim.PANDA_HAND_LINKS]
    assert len(links) == 9  # the hand's mesh, four boxes on each finger
    # each link geom against the table and the box; the tool as without links; nothing else
    tool_only = {("box", "table"), ("box", "tool"), ("table", "tool")}
    expected = tool_only | {tuple(sorted((link, other))) for link in links for other in ("box", "table")}
    assert pairs == expected and len(loaded.collision_pairs) == len(expected)
    default = sim.panda_push_model()
    assert {tuple(sorted(_owner(default, g) for g in pair)) for pair in default.collision_pairs} == tool_only
    with pytest.raises(ValueError, match=r"colliding_links: unknown links \['panda_link0'\].*panda_leftfinger"):
        sim.panda_push(colliding_links=("panda_link0",))
    with pytest.raises(ValueError, match="colliding_links must be a tuple of link names"):
        sim.panda_push_model(colliding_links="panda_hand")
    with pytest.raises(ValueError, match="max_contacts must be a positive integer"):
        sim.panda_push(max_contacts=0)


def _owner(loaded, geom: int) -> str:
    """A geom's name, or its body's name with the geom's id for an unnamed one."""
    name = loaded.geom_names[geom]
    return name if name in ("table", "box", "tool") else f"{loaded.body_names[loaded.geom_bodies[geom]]}/{geom}"


def _mujoco_scene():
    """MuJoCo's compiled scene with the hand links colliding, its conversion, and the geom ids
    of the pairs ``(link geom, table)``, ``(link geom, box)`` and ``(tool, box)``."""
    m = _compiled_scene(colliding_links=sim.PANDA_HAND_LINKS, **SCENE)
    geom = lambda name: mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, name)  # noqa: E731
    links = {mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, name) for name in sim.PANDA_HAND_LINKS}
    link_geoms = [g for g in range(m.ngeom) if m.geom_bodyid[g] in links]
    return m, sim.load_mjcf(m), [(g, geom("table")) for g in link_geoms], [(g, geom("box")) for g in link_geoms], (geom("tool"), geom("box"))


def _distances(m, loaded, pairs, qs) -> np.ndarray:
    """MuJoCo's signed distances ``(T, pairs)`` at the system's configurations ``qs`` ``(T, 14)``."""
    data = mujoco.MjData(m)
    out = []
    for qpos in np.asarray(loaded.q_to_qpos(qs)):
        data.qpos[:] = qpos
        mujoco.mj_kinematics(m, data)
        out.append([mujoco.mj_geomDistance(m, data, g1, g2, 1.0, None) for g1, g2 in pairs])
    return np.array(out)


def _pushes(system) -> jax.Array:
    """Constant inputs ``(2, T, 7)``: the torques ``J^T f`` of a force ``FORCE`` at the tool
    centre point along ``-z`` (the hand driven down onto the table) and along ``+x`` (towards
    the box), at the start."""
    q0 = system.initial_state()[: system.model.nq]
    frame = system.model.frame_id("panda_hand_tcp")
    jacobian = jax.jacfwd(lambda arm: sim.frame_placement(system.model, q0.at[:7].set(arm), frame)[1])(q0[:7])
    forces = jnp.asarray([[0.0, 0.0, -FORCE], [FORCE, 0.0, 0.0]])
    return jnp.broadcast_to((forces @ jacobian)[:, None, :], (2, STEPS, 7))


@eqx.filter_jit
def _rollout(system, us):
    return system.rollout(system.initial_state(), us)


def test_hand_links_stop_at_the_table_and_push_the_box():
    m, loaded, table_pairs, box_pairs, tool_box = _mujoco_scene()
    runs = {}
    for links in ((), sim.PANDA_HAND_LINKS):
        system = sim.panda_push(colliding_links=links, **SCENE)
        for name, us in zip(("down", "push"), _pushes(system)):
            xs, infos = _rollout(system, us)
            counts = sim.check_steps(infos, what=f"the Panda driven {name}")  # a warning is an error here
            assert counts["unconverged_steps"] == counts["diverged_steps"] == counts["dropped_contact_steps"] == 0
            runs[links, name] = np.asarray(xs)[:, :14], infos
    # Driven down (by 30 N), the hand goes through the table without its links; with them it
    # reaches the table and goes no more than a millimetre into it.
    assert np.min(_distances(m, loaded, table_pairs, runs[(), "down"][0])) < -3e-3
    assert -1e-3 < np.min(_distances(m, loaded, table_pairs, runs[sim.PANDA_HAND_LINKS, "down"][0])) < 1e-3
    # Pushed along +x, the hand moves the box with its links, not without; the tool never
    # touches the box, a link does.
    xs = runs[(), "push"][0]
    assert np.max(np.abs(xs[:, 7:10] - xs[0, 7:10])) < 1e-9
    xs = runs[sim.PANDA_HAND_LINKS, "push"][0]
    assert xs[-1, 7] - xs[0, 7] > 0.03
    assert np.min(_distances(m, loaded, [tool_box], xs)) > 0.02
    assert -1e-3 < np.min(_distances(m, loaded, box_pairs, xs)) < 1e-3
    # Along both, the steps saw the links' signed distances MuJoCo gives wherever they were
    # candidates (within the margin): the smallest entry of each pair's manifold. (`system`:
    # the one with the hand links, whose pairs are in the order of `loaded.collision_pairs`.)
    starts = np.cumsum([0] + [pair.size for pair in system.geometry.geom_pairs])
    index = {frozenset(pair): k for k, pair in enumerate(loaded.collision_pairs)}
    compared = 0
    for name in ("down", "push"):
        xs, infos = runs[sim.PANDA_HAND_LINKS, name]
        expected = _distances(m, loaded, table_pairs + box_pairs, xs[:-1])
        for column, pair in enumerate(table_pairs + box_pairs):
            k = index[frozenset(pair)]
            ours = np.min(np.asarray(infos.distance)[:, starts[k] : starts[k + 1]], axis=1)
            near = expected[:, column] < MARGIN - 1e-4
            np.testing.assert_allclose(ours[near], expected[near, column], atol=1e-6)
            compared += int(np.sum(near))
    assert compared > 20
