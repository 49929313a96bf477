"""The landscape experiments (stiffness, chaos, continuity) at tiny sizes: their metrics show
what Suh et al. (ICML 2022) predict, against closed forms and invariants."""

import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.scipy.stats import norm

from rsmooth.experiments import _landscape, landscape_chaos, landscape_continuity, landscape_stiffness


@pytest.mark.slow
def test_stiffness_first_order_variance_grows_and_the_soft_step_zero_is_caught(tmp_path):
    config = landscape_stiffness.Config(stiffnesses=(10.0, 1e4), num_samples=16, repeats=4,
                                        soft_step_widths=(1.0, 1e-4), soft_step_repeats=20, policy_seeds=2,
                                        policy_iterations=5)
    metrics = landscape_stiffness.run(config, str(tmp_path), jax.random.key(0), progress=False)
    soft, stiff = metrics[f"k={10.0:g}"], metrics[f"k={1e4:g}"]
    # The first-order per-sample variance grows with the stiffness (the squared slope of the
    # ramp, as k, times the chance to land on it, as k^(-1/2) once the ramp is narrower than
    # sigma); the zeroth-order one stays below the squared range of the landscape over sigma^2.
    assert metrics["first_variance_growth"] > 100
    assert stiff["first"]["per_sample_variance"]["mean"] > 3 * stiff["zeroth"]["per_sample_variance"]["mean"]
    for entry in (soft, stiff):
        assert entry["zeroth"]["per_sample_variance"]["mean"] <= metrics["zeroth_variance_bound"]
    # The contact's ramp is as wide as the distance travelled during one contact.
    assert stiff["contact_width"] == pytest.approx(math.pi * math.sqrt(1 / 1e4))
    step = metrics["soft_step"]
    narrow, wide = -1, 0
    # On the narrowest ramp no sample of the first-order estimate lands on it (probability
    # 0.9994 per estimate): it is exactly 0, and reports a variance of 0 ...
    assert step["first"]["zero_fraction"][narrow] == 1.0 and step["first"]["reported_variance_median"][narrow] == 0.0
    assert step["first"]["bias"][narrow] == pytest.approx(-1 / math.sqrt(2 * math.pi), rel=1e-3)
    # ... while the zeroth-order mean is within 4 standard errors of the Gaussian density, and
    # the bias test flags the first-order zeros.
    zeroth_error = step["zeroth"]["std"][narrow] / math.sqrt(step["repeats"])
    assert abs(step["zeroth"]["bias"][narrow]) < 4 * zeroth_error
    assert step["detected_vs_zeroth"][narrow] >= 0.9 and step["detected_vs_closed_form"][narrow] == 1.0
    # On a ramp as wide as sigma the first-order estimate is fine and rarely flagged.
    assert step["true_gradient"][wide] == pytest.approx(float(norm.cdf(0.5) - norm.cdf(-0.5)))
    assert abs(step["first"]["bias"][wide]) < 4 * step["first"]["std"][wide] / math.sqrt(step["repeats"])
    assert step["detected_vs_zeroth"][wide] <= 0.2
    # Alpha order is measured beside them: Suh's rule trusts first order less on the stiff wall
    # (cross-fitted weights come from folds that mostly miss the ramp: no such trend).
    assert 0.0 <= stiff["alpha"]["mean_alpha"] < soft["alpha"]["mean_alpha"] <= 1.0
    assert stiff["alpha"]["rmse"] < stiff["first"]["rmse"]
    assert all(0.0 <= entry["alpha-cross-fit"]["mean_alpha"] <= 1.0 for entry in (soft, stiff))
    # The push task: from push_start the ball stops short of the wall (no contact force: its
    # final velocity is its speed, exactly); a strong push bounces it back elastically.
    policy, sigma, speed = metrics["policy"], config.push_sigma, config.speed
    effort = lambda theta: 0.5 * config.effort * (theta / sigma) ** 2  # noqa: E731
    problem = landscape_stiffness.push_problem(config, 1e4)
    short, bounced = landscape_stiffness._grid_costs(problem, np.array([config.push_start, 0.3]))
    assert short == pytest.approx((speed + config.push_start) / speed + effort(config.push_start), rel=1e-12)
    assert bounced - effort(0.3) == pytest.approx(-(speed + 0.3) / speed, rel=0.02)
    for k in config.stiffnesses:
        entry = policy[f"k={k:g}"]
        # The smoothed optimum improves on the start; on the stiff wall it is a push that bounces
        # the ball back (the cost drops by about 2).
        assert entry["optimum_cost"] < entry["start_cost"]
        for name in landscape_stiffness.ESTIMATORS:
            run = entry[name]
            assert len(run["gap"]) == 2 and min(run["gap"]) >= -1e-12  # the optimum is the minimum
            assert run["gap_mean"] < entry["start_cost"] - entry["optimum_cost"]  # better than the start
        assert entry["first"]["mean_alpha"] == 1.0 and entry["zeroth"]["mean_alpha"] == 0.0
        assert all(0.0 <= entry[name]["mean_alpha"] <= 1.0 for name in ("alpha", "alpha-cross-fit"))
        assert entry["best"] in landscape_stiffness.ESTIMATORS
    assert policy[f"k={1e4:g}"]["optimum_cost"] < policy[f"k={1e4:g}"]["start_cost"] - 1.5
    saved = json.loads((tmp_path / "metrics.json").read_text())
    assert saved["first_variance_growth"] == pytest.approx(metrics["first_variance_growth"])
    assert saved["policy"][f"k={1e4:g}"]["best"] == policy[f"k={1e4:g}"]["best"]
    for name in ("stiffness", "soft_step", "policy"):
        assert (tmp_path / f"{name}.png").stat().st_size > 10_000


@pytest.mark.slow
def test_chaos_first_order_variance_explodes_with_the_horizon(tmp_path):
    config = landscape_chaos.Config(horizons=(50, 200, 400), num_samples=8, repeats=4)
    metrics = landscape_chaos.run(config, str(tmp_path), jax.random.key(0), progress=False)
    first = np.asarray(metrics["first"]["per_sample_variance"]["mean"])
    zeroth = np.asarray(metrics["zeroth"]["per_sample_variance"]["mean"])
    # Before the first bounce (0.25 s) the final x is the start: every sampled derivative is
    # exactly 1 (first order: variance 0) and the score-function estimate of a linear
    # function has per-sample variance E[z^4] - 1 = 2 (estimated from 8 samples).
    assert first[0] == 0.0 and np.all(np.asarray(metrics["first"]["mean"])[0] == 1.0)
    assert 0.5 < zeroth[0] < 6
    # Then the exact derivative and the first-order variance grow exponentially, the
    # zeroth-order variance stays below range^2 / sigma^2.
    assert metrics["exact_derivative_median"][-1] > 1e3 and metrics["lyapunov_exponent"] > 1.0
    assert first[-1] > 1e4 * first[1] and first[-1] > 1e4 * zeroth[-1]
    assert np.all(zeroth <= 1.5 * np.asarray(metrics["zeroth_variance_bound"]))
    # Alpha order weighs each horizon alone: before the bounce its first-order half has variance
    # 0 and gets weight 1 wherever the bias test passes; at the longest horizon little weight.
    weight = np.asarray(metrics["alpha"]["weight"])
    assert weight[0] >= 0.5 and weight[-1] < 0.5 and np.all((0 <= weight) & (weight <= 1))
    assert (tmp_path / "chaos.png").stat().st_size > 10_000 and (tmp_path / "metrics.json").exists()


@pytest.mark.slow
def test_continuity_half_plane_is_lipschitz_the_edge_jumps_and_smoothing_bounds_it(tmp_path):
    config = landscape_continuity.Config(cases=("half-plane", "edge"), points=24, sigmas_deg=(6.0,), num_samples=16)
    metrics = landscape_continuity.run(config, str(tmp_path), jax.random.key(0), progress=False)
    plane, edge = metrics["half-plane"], metrics["edge"]
    # Halving the resolution doubles the largest change of a Lipschitz landscape, and leaves a
    # jump as it is: the cube lands on one face or the other, its centre half a side to either side.
    assert plane["raw_refinement_ratio"] > 1.8
    assert edge["raw_refinement_ratio"] < 1.1 and edge["raw_max_jump"] == pytest.approx(landscape_continuity.CUBE_SIDE, rel=0.1)
    final_x, tilts = np.asarray(edge["final_x"]), np.asarray(edge["sweep_deg"])
    assert np.all(final_x[tilts < 45] < -0.05) and np.all(final_x[tilts > 45] > 0.05)
    # Smoothing over 6 degrees turns the jump into a slope: Lipschitz at the scale of the sweep,
    # its steps within the bound of an exact Gaussian smoothing plus the jumps of single samples
    # crossing 45 degrees (range / M each, a few per step).
    smoothed = edge["sigma=6"]
    step = tilts[1] - tilts[0]
    assert smoothed["refinement_ratio"] > 1.3 and smoothed["max_jump"] < 0.5 * edge["raw_max_jump"]
    assert smoothed["max_jump"] <= smoothed["slope_bound"] * step + 3 * edge["range"] / config.num_samples
    # Far from the edge (beyond 2.5 sigma) the smoothing is the landscape, up to its slope.
    far = np.abs(tilts - 45) > 2.5 * 6
    assert np.max(np.abs(np.asarray(smoothed["smoothed"])[far] - final_x[far])) < 0.02
    assert (tmp_path / "continuity.png").stat().st_size > 10_000


def test_the_rollout_program_has_no_host_callback_and_its_values_are_checked_on_the_host():
    """A host callback (a traced check) keeps JAX's persistent compilation cache from storing a
    program: the shared rollout program leaves them out, and a NaN is caught on the host."""
    config = landscape_stiffness.Config(steps=5, lead=0.01)
    system = landscape_stiffness.wall_system(config)

    def objective(k, x):
        return landscape_stiffness.final_velocity(system, config, k, x)

    assert "callback" in jax.jit(objective).lower(1e3, 0.0).as_text()  # the rollout's own checks
    assert "callback" not in _landscape.value_and_derivative(objective).lower(1e3, 0.0).as_text()
    root = _landscape.value_and_derivative(lambda _, x: jnp.sqrt(x))
    values, derivatives = _landscape.evaluate_in_batches(root, 0.0, np.array([1.0, 4.0, 9.0]), (1, 2))
    assert values == pytest.approx([1.0, 2.0, 3.0]) and derivatives == pytest.approx([0.5, 0.25, 1 / 6])
    with pytest.raises(FloatingPointError, match="landscape"):
        _landscape.evaluate_in_batches(root, 0.0, np.array([1.0, -1.0]), (1, 2))


def test_configs_reject_inconsistent_options():
    with pytest.raises(ValueError, match="stiffness"):
        landscape_stiffness.Config(stiffnesses=(1e5,))
    with pytest.raises(ValueError, match="lead"):
        landscape_stiffness.Config(steps=2, lead=0.05)
    with pytest.raises(ValueError, match="horizons"):
        landscape_chaos.Config(horizons=(100, 50))
    with pytest.raises(ValueError, match="time_step"):
        landscape_chaos.Config(time_step=0.02)
    with pytest.raises(ValueError, match="start_x"):
        landscape_chaos.Config(start_x=2.0)
    with pytest.raises(ValueError, match="case"):
        landscape_continuity.Config(cases=("corner", "corner"))
    with pytest.raises(ValueError, match="tilt_range_deg"):
        landscape_continuity.Config(tilt_range_deg=(50.0, 40.0))
