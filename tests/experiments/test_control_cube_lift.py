"""The cube-lift experiment: DDP stays at rest (zero gradient), R-DDP lifts the cube."""

import json

import jax
import pytest
from typer.testing import CliRunner

from rsmooth.cli import app
from rsmooth.experiments import control_cube_lift


@pytest.mark.slow
def test_ddp_stays_at_rest_and_rddp_reaches_the_target(tmp_path, getkey):
    config = control_cube_lift.Config(seeds=1, geometric_decays=(), max_iterations=30)
    metrics = control_cube_lift.run(config, tmp_path, getkey(), progress=False)
    assert metrics["methods"] == ["ddp", "rddp"]
    ddp, rddp = metrics["ddp"], metrics["rddp"]
    # DDP: the first backward pass sees f_u = 0 and stops; nothing moves.
    assert abs(ddp["final_height"]) < 1e-6 and ddp["max_force"] == 0.0 and not ddp["success"]
    assert ddp["iterations"] == 1 and ddp["converged"]
    # R-DDP: lifted within tolerance, finished with eps = 0 on the true dynamics.
    assert rddp["success"] and abs(rddp["final_height"] - config.height) < config.tolerance
    assert rddp["converged"] and rddp["final_cost"] < 0.01 * ddp["final_cost"]
    # both trajectories simulated again: every contact solve converged (a warning would fail here)
    assert ddp["unconverged_steps"] == rddp["unconverged_steps"] == rddp["diverged_steps"] == 0
    written = json.loads((tmp_path / "metrics.json").read_text())
    assert written["rddp"]["success_rate"] == 1.0 and written["ddp"]["success_rate"] == 0.0
    assert (tmp_path / "cube_lift.png").stat().st_size > 0 and (tmp_path / "cube_lift.gif").stat().st_size > 0
    assert not list(tmp_path.glob(".*"))


def test_cli_cube_lift_rejects_a_bad_method_and_documents_its_metrics(tmp_path):
    bad = CliRunner().invoke(app, ["control", "cube-lift", "--method", "sgd", "--out", str(tmp_path)])
    assert bad.exit_code != 0 and "--method" in bad.output
    help_text = CliRunner().invoke(app, ["control", "cube-lift", "--help"]).output
    assert "success_rate" in help_text and "final_height" in help_text
    with pytest.raises(ValueError, match="height"):
        control_cube_lift.Config(height=-0.1)


def test_a_float32_run_is_refused_before_it_solves(tmp_path):
    # built with jax_enable_x64 off, as in a fresh Python process: a clear error, not an R-DDP
    # that ends on a non-finite value
    with jax.enable_x64(False):
        with pytest.raises(ValueError, match="need float64: call jax.config.update"):
            control_cube_lift.run(control_cube_lift.Config.quick(), tmp_path, jax.random.key(0), progress=False)
    assert not (tmp_path / "metrics.json").exists()
