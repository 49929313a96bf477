"""The estimators experiment on a reduced grid: its metrics say what the issue promises."""

import dataclasses

import jax
import numpy as np
import pytest

from rsmooth.experiments import estimators


@pytest.mark.slow
def test_estimators_experiment_small(tmp_path):
    config = dataclasses.replace(estimators.Config.quick(), x_grid=(-1.0, 1.0, 9), num_samples_grid=(16, 256), num_trials=24)
    metrics = estimators.run(config, str(tmp_path), jax.random.key(0), progress=False)  # a str works as well as a Path
    assert metrics["heaviside_first_order_grad_max_abs"] == 0.0
    peak = 1 / (config.sigma * np.sqrt(2 * np.pi))
    assert metrics["heaviside_first_max_abs_error"] > 0.9 * peak
    assert metrics["heaviside_zeroth_max_abs_error"] < 0.15 * peak
    # Zeroth-order error falls with M (about 1/sqrt(M): 4x fewer for 16x samples).
    rmse = metrics["coulomb"]["zeroth"]["rmse"]
    assert rmse[1] < rmse[0] / 2
    assert (tmp_path / "estimators.png").exists() and (tmp_path / "metrics.json").exists()


def test_quadrature_matches_closed_forms():
    from jax.scipy.stats import norm

    xs = np.linspace(-1, 1, 7)
    fns = estimators.functions(estimators.Config())
    np.testing.assert_allclose(
        estimators._gaussian_smoothing_by_quadrature(fns["abs"][0], xs, 0.3),
        0.3 * np.sqrt(2 / np.pi) * np.exp(-(xs**2) / 0.18) + xs * (1 - 2 * norm.cdf(-xs / 0.3)),
        atol=1e-6,
    )
