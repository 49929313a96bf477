"""The Solo-12 simulation experiment: standing holds still, random torques stay sane."""

import json

from rsmooth.experiments import solo12_sim


def test_solo12_random_torques_stay_sane(tmp_path, getkey):
    """Standing still is checked through the command line (tests/test_project.py)."""
    config = solo12_sim.Config(torques="random", steps=30, frames=3)
    shaken = solo12_sim.run(config, str(tmp_path), getkey(), progress=False)  # a str works as well as a Path
    assert shaken["base_drift"] > 1e-4  # it does move
    assert shaken["min_foot_distance"] > -1e-3  # no foot sinks into the floor
    assert shaken["ncp_converged_fraction"] > 0.9
    assert json.loads((tmp_path / "metrics.json").read_text())["steps"] == 30
    assert (tmp_path / "solo12.gif").stat().st_size > 1000


def test_solo12_falls_under_open_loop_random_torques_without_diverging(tmp_path, getkey):
    """No posture controller, torques of +-0.5 N m around the standing ones for 1.5 s: the
    robot falls (a physical outcome), every step stays valid, and its base and knees land on
    the floor instead of passing through it (without body contacts the base sinks 0.25 m)."""
    config = solo12_sim.Config(torques="random", steps=150, frames=2, random_scale=0.5, stiffness=0.0, damping=0.0)
    fallen = solo12_sim.run(config, tmp_path, getkey(), progress=False)
    assert fallen["base_height_min"] < fallen["base_height_initial"] - 0.05
    assert fallen["diverged_steps"] == 0
    assert fallen["ncp_converged_fraction"] > 0.95
    assert fallen["min_body_distance"] > -0.02
