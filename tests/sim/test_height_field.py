"""Height fields (`sim.HeightField`, MuJoCo's hfield): the signed distances of spheres and
capsules to a random terrain equal MuJoCo's contacts, a ball rests on a flat terrace of a
terrain at the analytic height, and what is not supported is refused by name."""

import equinox as eqx
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from rsmooth import sim
from rsmooth.sim._collision import collide

ROWS, COLUMNS, HALF_X, HALF_Y, TOP, BASE = 6, 7, 0.6, 0.5, 0.2, 0.1


def _terrain(shape_geom: str, seed: int = 0) -> str:
    """A random terrain (MuJoCo's hfield) and a free body of one geom above it."""
    elevation = " ".join(map(str, np.random.default_rng(seed).uniform(0, 1, size=ROWS * COLUMNS)))
    return f"""<mujoco><option ccd_tolerance="1e-12" ccd_iterations="500"/>
      <asset><hfield name="terrain" nrow="{ROWS}" ncol="{COLUMNS}" size="{HALF_X} {HALF_Y} {TOP} {BASE}" elevation="{elevation}"/></asset>
      <worldbody><geom name="terrain" type="hfield" hfield="terrain"/><body name="body"><freejoint/><geom name="body" {shape_geom}/></body></worldbody>
    </mujoco>"""


@pytest.mark.parametrize("geom", ['type="sphere" size="0.08"', 'type="capsule" size="0.04 0.08"'], ids=["sphere", "capsule"])
def test_distances_to_a_terrain_are_mujocos(geom):
    # The deepest of our contacts against the deepest MuJoCo reports (it reports penetrating
    # contacts only, one per prism of the cells under the shape), on random poses over the
    # terrain; where MuJoCo reports none, ours is apart.
    text = _terrain(geom)
    m = mujoco.MjModel.from_xml_string(text)
    d = mujoco.MjData(m)
    system = sim.scene(text)
    pair = system.geometry.geom_pairs[0]
    assert isinstance(pair.shape1, sim.HeightField) and pair.frame1 is None
    np.testing.assert_allclose(pair.shape1.heights, np.asarray(m.hfield_data).reshape(ROWS, COLUMNS) * TOP, rtol=1e-6)
    distance = jax.jit(jax.vmap(lambda r, t: collide(pair.shape1, pair.placement1, pair.shape2, (r, t)).distance[0]))
    rng = np.random.default_rng(1)
    qpos = np.concatenate([rng.uniform([-0.45, -0.35, 0.0], [0.45, 0.35, 0.25], size=(48, 3)), rng.normal(size=(48, 4))], axis=1)
    qpos[:, 3:] /= np.linalg.norm(qpos[:, 3:], axis=1, keepdims=True)
    expected, rotations = [], []
    for q in qpos:
        d.qpos[:] = q
        mujoco.mj_forward(m, d)
        expected.append(min([c.dist for c in d.contact[: d.ncon]], default=np.inf))
        rotations.append(d.xmat[1].reshape(3, 3).copy())
    ours = np.asarray(distance(jnp.asarray(np.array(rotations)), jnp.asarray(qpos[:, :3])))
    expected = np.array(expected)
    touching = np.isfinite(expected)
    assert 10 < touching.sum() < 40
    # (MuJoCo's penetration of a height field's prisms iterates to about 1e-6)
    np.testing.assert_allclose(ours[touching], expected[touching], atol=1e-5)
    assert np.all(ours[~touching] > -1e-9)


def test_a_ball_rests_on_a_terrace_of_a_terrain():
    # Heights: a flat terrace at 0.1 m over the middle columns, lower around: a ball of radius
    # 5 cm set down 2 mm above it settles on it, where two prisms meet.
    heights = np.full((ROWS, COLUMNS), 1.0)  # MuJoCo scales the elevation to [0, 1], times size[2]
    heights[:, 0] = heights[:, -1] = 0.0
    elevation = " ".join(map(str, heights.reshape(-1)))
    text = f"""<mujoco><option timestep="0.01"/>
      <asset><hfield name="terrain" nrow="{ROWS}" ncol="{COLUMNS}" size="{HALF_X} {HALF_Y} 0.1 {BASE}" elevation="{elevation}"/></asset>
      <worldbody><geom name="terrain" type="hfield" hfield="terrain"/>
        <body name="ball" pos="0.05 0.02 0.152"><freejoint/><geom type="sphere" size="0.05" mass="1"/></body></worldbody>
    </mujoco>"""
    system = sim.scene(text)
    xs, infos = eqx.filter_jit(lambda s, x: s.rollout(x, jnp.zeros((100, 0))))(system, system.initial_state())
    sim.check_steps(infos, what="a ball on a terrace")
    np.testing.assert_allclose(float(xs[-1, 2]), 0.1 + 0.05, atol=1e-3)
    assert float(jnp.max(jnp.abs(xs[-10:, 7:]))) < 1e-3


def test_bad_height_fields_are_refused_by_name():
    with pytest.raises(ValueError, match=r"heights must have shape \(R, C\) with R, C >= 2"):
        sim.HeightField(np.zeros((1, 3)), [1.0, 1.0], 0.1)
    with pytest.raises(ValueError, match=r"geom 'terrain' \(hfield\) collides with geom 'body' \(box\)"):
        sim.scene(_terrain('type="box" size="0.1 0.1 0.1"'))
    with pytest.raises(ValueError, match="window must be an int >= 1"):
        sim.HeightField(np.zeros((3, 3)), [1.0, 1.0], 0.1, window=0)
    moving = _terrain('type="sphere" size="0.08"').replace(
        '<geom name="terrain" type="hfield" hfield="terrain"/>',
        '<body name="raft"><freejoint/><geom name="terrain" type="hfield" hfield="terrain"/></body>',
    )
    with pytest.raises(ValueError, match="geom 'terrain' \\(hfield\\) is on a moving body"):
        sim.scene(moving)
