"""The pusher experiment: DDP leaves the box where it was (zero gradient), R-DDP pushes it to
the target pose."""

import json
import warnings

import numpy as np
import pytest
from typer.testing import CliRunner

from rsmooth import sim
from rsmooth.cli import app
from rsmooth.experiments import control_pusher


@pytest.mark.slow
def test_ddp_leaves_the_box_and_rddp_pushes_it_to_the_target(tmp_path, getkey):
    config = control_pusher.Config(seeds=1, geometric_decays=(), num_samples=8, max_iterations=8)
    # The trajectories are simulated again with the contact diagnostics: a solve left short of the
    # solver's tolerance (ADMM's iteration cap on sliding contact) is counted and warned about.
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", sim.SimulationWarning)
        metrics = control_pusher.run(config, tmp_path, getkey(), progress=False)
    assert metrics["methods"] == ["ddp", "rddp"]
    ddp, rddp = metrics["ddp"], metrics["rddp"]
    # DDP: with the finger 3 cm away, the box's pose does not depend on the forces; the first
    # backward pass sees no descent direction and nothing moves.
    assert ddp["iterations"] == 1 and ddp["converged"] and ddp["max_force"] == 0.0
    assert ddp["box_displacement"] < 1e-6 and not ddp["success"]
    assert ddp["unconverged_steps"] == ddp["diverged_steps"] == rddp["diverged_steps"] == 0
    # at most a few of the R-DDP trajectory's solves, a count that moves with the rounding of the
    # step's Jacobians (R-DDP's iterates through sliding contact amplify it): a minority, and
    # warned about where there are any
    assert 0 <= rddp["unconverged_steps"] <= config.horizon // 4
    warned = [w for w in caught if issubclass(w.category, sim.SimulationWarning)]
    assert bool(warned) == (rddp["unconverged_steps"] > 0)
    assert all("the rddp solution's trajectory" in str(w.message) for w in warned)
    np.testing.assert_allclose(ddp["position_error"], np.hypot(config.target_x, config.target_y), atol=1e-6)
    # R-DDP: the box pushed and turned onto the target, at rest.
    assert rddp["position_error"] < config.position_tolerance < ddp["position_error"]
    assert rddp["yaw_error_deg"] < config.yaw_tolerance < ddp["yaw_error_deg"]
    assert rddp["success"] and rddp["final_cost"] < 0.1 * ddp["final_cost"]
    written = json.loads((tmp_path / "metrics.json").read_text())
    assert written["rddp"]["success_rate"] == 1.0 and written["ddp"]["success_rate"] == 0.0
    assert written["target"] == [config.target_x, config.target_y, config.target_yaw]
    assert (tmp_path / "pusher.png").stat().st_size > 0 and (tmp_path / "pusher.gif").stat().st_size > 0
    assert not list(tmp_path.glob(".*"))  # no temporary file left behind


def test_box_pose_reads_the_yaw_from_the_quaternion():
    yaw = np.radians([-170.0, -15.0, 0.0, 30.0, 179.0])
    xs = np.zeros((5, 17))
    xs[:, 0], xs[:, 1] = 0.1, -0.2
    xs[:, 5], xs[:, 6] = np.sin(yaw / 2), np.cos(yaw / 2)
    np.testing.assert_allclose(control_pusher.box_pose(xs), np.stack([np.full(5, 0.1), np.full(5, -0.2), yaw], axis=1))
    flipped = xs.copy()
    flipped[:, 3:7] *= -1  # q and -q are the same rotation
    np.testing.assert_allclose(control_pusher.box_pose(flipped)[:, 2], yaw, atol=1e-12)


def test_cli_pusher_rejects_a_bad_method_and_documents_its_metrics(tmp_path):
    bad = CliRunner().invoke(app, ["control", "pusher", "--method", "sgd", "--out", str(tmp_path)])
    assert bad.exit_code != 0 and "--method" in bad.output
    help_text = CliRunner().invoke(app, ["control", "pusher", "--help"]).output
    for key in ("success_rate", "position_error", "yaw_error_deg", "--target-yaw"):
        assert key in help_text
    with pytest.raises(ValueError, match="finger_y"):
        control_pusher.Config(finger_y=0.2)
    with pytest.raises(ValueError, match="method"):
        control_pusher.Config(method="sgd")
