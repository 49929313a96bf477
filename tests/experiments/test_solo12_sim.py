"""The Solo-12 simulation experiment: standing holds still, random torques stay sane."""

import json

from rsmooth.experiments import solo12_sim


def test_solo12_standing_and_random(tmp_path, getkey):
    standing = solo12_sim.run(solo12_sim.Config(steps=30, frames=3), tmp_path / "standing", getkey(), progress=False)
    assert standing["base_drift"] < 1e-6 and standing["max_foot_slip"] < 1e-6
    assert standing["ncp_converged_fraction"] == 1.0
    config = solo12_sim.Config(torques="random", steps=30, frames=3)
    shaken = solo12_sim.run(config, tmp_path / "random", getkey(), progress=False)
    assert shaken["base_drift"] > 1e-4  # it does move
    assert shaken["min_foot_distance"] > -1e-3  # no foot sinks into the floor
    assert shaken["ncp_converged_fraction"] > 0.9
    for folder in ("standing", "random"):
        assert json.loads((tmp_path / folder / "metrics.json").read_text())["steps"] == 30
        assert (tmp_path / folder / "solo12.gif").stat().st_size > 1000
