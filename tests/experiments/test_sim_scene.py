"""The MuJoCo-scene simulation experiment: a ball and a box dropped on a floor from a file."""

import json

from rsmooth.experiments import sim_scene

# A ball and a box 5 cm above a floor, 10 ms steps: both land within 0.1 s.
SCENE = """<mujoco><option timestep="0.01"/><worldbody>
  <geom name="floor" type="plane" size="1 1 0.1"/>
  <body name="ball" pos="0.3 0 0.1"><freejoint/><geom type="sphere" size="0.05"/></body>
  <body name="box" pos="-0.3 0 0.1"><freejoint/><geom type="box" size="0.05 0.04 0.05" euler="0 0 20"/></body>
</worldbody></mujoco>"""


def test_dropped_ball_and_box_land_without_sinking(tmp_path, getkey):
    scene = tmp_path / "drop.xml"
    scene.write_text(SCENE)
    config = sim_scene.Config(file=str(scene), steps=20, frames=2)
    metrics = sim_scene.run(config, tmp_path / "out", getkey(), progress=False)
    # floor-ball (1 contact), floor-box (4), ball-box (1)
    assert metrics["geom_pairs"] == 3 and metrics["candidate_contacts"] == 1 + 4 + 1
    assert metrics["contacts_active_max"] == 5  # the ball's point and the box's four corners
    assert metrics["max_penetration"] < 1e-3
    # falling 5 cm and landing inelastically loses potential energy, and gains none on the way
    assert metrics["energy_change"] < 0 and metrics["energy_max_gain"] < 1e-6
    assert metrics["unconverged_steps"] == 0 and metrics["diverged_steps"] == 0
    assert json.loads((tmp_path / "out" / "metrics.json").read_text())["steps"] == 20
    assert (tmp_path / "out" / "scene.gif").stat().st_size > 1000
