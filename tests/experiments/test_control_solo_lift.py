"""The Solo-12 lift-foot experiment: DDP keeps the four feet down, R-DDP lifts the chosen foot."""

import dataclasses
import json

import pytest
from typer.testing import CliRunner

from rsmooth.cli import app
from rsmooth.experiments import control_solo_lift


@pytest.mark.slow
def test_ddp_keeps_four_feet_down_and_rddp_lifts_the_foot(tmp_path, getkey):
    config = control_solo_lift.Config(foot="HR", seeds=1, geometric_decays=(), max_iterations=30, frames=2)
    metrics = control_solo_lift.run(config, tmp_path, getkey(), progress=False)
    ddp, rddp = metrics["ddp"], metrics["rddp"]
    # DDP from the standing torques: the foot's height has a zero derivative, nothing moves.
    assert abs(ddp["foot_height"]) < 1e-6 and not ddp["success"]
    assert ddp["other_feet_max_slip"] < 1e-6 and ddp["iterations"] == 1
    # R-DDP breaks the contact: the foot reaches the target, the others stay on the floor.
    assert rddp["success"], rddp
    assert abs(rddp["foot_height"] - config.height) < config.tolerance
    assert rddp["other_feet_max_height"] < 1e-3 and rddp["other_feet_max_slip"] < 5e-3
    assert rddp["base_tilt_deg"] < 10.0 and rddp["final_cost"] < 0.5 * ddp["final_cost"]
    assert ddp["unconverged_steps"] == rddp["unconverged_steps"] == rddp["diverged_steps"] == 0
    written = json.loads((tmp_path / "metrics.json").read_text())
    assert written["foot"] == "HR" and written["rddp"]["success_rate"] == 1.0
    assert (tmp_path / "solo_lift.png").stat().st_size > 0 and (tmp_path / "solo_lift.gif").stat().st_size > 0
    assert not list(tmp_path.glob(".*"))
    # Another foot and height: the foot and target are traced cost parameters, so this solve
    # reuses the compiled R-DDP step; it lifts the diagonally opposite foot as well.
    other = dataclasses.replace(config, foot="FL", height=0.04, method="rddp", frames=0)
    rddp = control_solo_lift.run(other, tmp_path / "FL", getkey(), progress=False)["rddp"]
    assert rddp["success"] and abs(rddp["foot_height"] - 0.04) < config.tolerance, rddp
    assert not (tmp_path / "FL" / "solo_lift.gif").exists()  # frames=0: no animation


def test_solo_lift_rejects_bad_feet_and_heights(tmp_path):
    with pytest.raises(ValueError, match="foot"):
        control_solo_lift.Config(foot="LF")
    with pytest.raises(ValueError, match="height"):
        control_solo_lift.Config(height=0.0)
    bad = CliRunner().invoke(app, ["control", "solo-lift", "--foot", "XX", "--out", str(tmp_path)])
    assert bad.exit_code != 0 and "--foot" in bad.output
    help_text = CliRunner().invoke(app, ["control", "solo-lift", "--help"]).output
    assert "other_feet_max_height" in help_text and "base_tilt_deg" in help_text
