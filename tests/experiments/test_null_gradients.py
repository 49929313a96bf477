"""The null-gradient experiment on a small grid: exact zeros, closed forms, files."""

import json

import numpy as np
import pytest
from jax.scipy.stats import norm

from rsmooth.experiments import null_gradients


@pytest.mark.slow
def test_null_gradients_small(tmp_path, getkey):
    config = null_gradients.Config(steps=5, force_grid=(0.0, 16.0, 5), sigmas=(3.0,), num_samples=16, num_trials=4)
    metrics = null_gradients.run(config, str(tmp_path), getkey(), progress=False)  # a str works as well as a Path
    # Hard contact: exactly no signal below the weight, the free-flight slope above it.
    assert metrics["exact_gradient_max_abs_below_weight"] < 1e-15
    assert metrics["exact_gradient_above_weight_rel_error"] < 1e-9
    entry = metrics["sigma=3"]
    closed_form = np.asarray(entry["closed_form"])
    slope = closed_form.max() / norm.cdf((16.0 - metrics["weight"]) / 3.0)
    # Far below m g few samples reach the lifting region (probability p): all 64 may miss it,
    # so the empirical spread is 0 there; the binomial error slope * sqrt(p (1 - p) / 64)
    # bounds that case.
    p = closed_form / slope
    rare = slope * np.sqrt(p * (1 - p) / 64)
    for name in ("first_order", "zeroth_order"):
        mean, std = np.asarray(entry[f"{name}_mean"]), np.asarray(entry[f"{name}_std"])
        # Mean of 4 trials: within 5 standard errors of the closed form.
        assert np.all(np.abs(mean - closed_form) <= 5 * (std / np.sqrt(4) + rare) + 1e-12), name
    # Smoothing gives a lifting signal where the exact gradient is zero (F = 8 N < m g).
    assert entry["first_order_mean"][2] > 0 and closed_form[2] > 1e-4
    saved = json.loads((tmp_path / "metrics.json").read_text())
    assert saved["weight"] == metrics["weight"]
    assert (tmp_path / "null_gradients.png").stat().st_size > 10_000
