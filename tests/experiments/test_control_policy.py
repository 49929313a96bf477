"""The ball-over-a-wall policy experiment: first order falls off the edge, alpha order clears it."""

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from rsmooth.cli import app
from rsmooth.experiments import control_policy

PER_METHOD = (
    "final_cost_mean", "final_cost_std", "success_rate", "final_angle_deg_mean", "mean_alpha",
    "gradient_variance", "gradient_variance_median", "per_seed",
)


@pytest.mark.slow
def test_first_order_hits_the_wall_and_alpha_order_clears_it(tmp_path, getkey):
    config = control_policy.Config.quick(seeds=2)
    metrics = control_policy.run(config, tmp_path, getkey(), progress=False)
    written = json.loads((tmp_path / "metrics.json").read_text())
    assert written["methods"] == ["first", "zeroth", "alpha"]
    for name in written["methods"]:
        assert all(key in written[name] for key in PER_METHOD) and len(written[name]["per_seed"]) == 2
    for key in ("edge_deg", "best_cost", "initial_cost", "success_criterion", "sigma_final"):
        assert key in written
    assert (tmp_path / "policy_cost.png").stat().st_size > 0 and (tmp_path / "policy_landscape.png").stat().st_size > 0
    assert not list(tmp_path.glob(".*"))
    # The landscape: the lowest throw that clears the wall, by the closed form of the drag-free
    # flight (tan theta - g d^2 (1 + tan^2 theta) / (2 v^2) = H: 54.4 deg), up to the 10 ms step.
    assert abs(metrics["edge_deg"] - 54.4) < 0.5
    first, zeroth, alpha = (metrics[name] for name in ("first", "zeroth", "alpha"))
    # The paper's point. First order follows the slope over the edge, where every sample's
    # gradient is 0, and ends at the wall (cost -1); alpha order, which switches to the
    # zeroth-order estimate near the edge, clears the wall in every run and lands > 2 m away.
    assert first["success_rate"] == 0.0 and first["final_cost_mean"] == pytest.approx(-config.wall_distance)
    assert alpha["success_rate"] == 1.0 and alpha["final_cost_mean"] < -2.0
    assert zeroth["success_rate"] == 1.0
    # Alpha uses both: mostly first order (far from the edge), zeroth order near it.
    assert 0.3 < alpha["mean_alpha"] < 0.98
    assert first["mean_alpha"] == 1.0 and zeroth["mean_alpha"] == 0.0
    # Half of alpha's iterations have a far lower gradient variance than zeroth order's.
    assert alpha["gradient_variance_median"] < 0.1 * zeroth["gradient_variance_median"]
    assert np.isfinite(first["gradient_variance"])


def test_cli_policy_rejects_a_bad_method_and_documents_its_metrics(tmp_path):
    bad = CliRunner().invoke(app, ["control", "policy", "--method", "second", "--out", str(tmp_path)])
    assert bad.exit_code != 0 and "--method" in bad.output
    help_text = CliRunner().invoke(app, ["control", "policy", "--help"]).output
    assert "success_rate" in help_text and "mean_alpha" in help_text
    with pytest.raises(ValueError, match="method"):
        control_policy.Config(method="second")
