"""The render-pose experiment, small: the perturbed renderer recovers a cube's rotation. The
pose fit itself (pose noise, sample growth, keep-best, restarts) is tested in
tests/render/test_pose.py."""

import dataclasses
import json

import jax
import numpy as np
import pytest

from rsmooth.experiments import _protocol, render_pose


@pytest.mark.slow
def test_perturbed_renderer_solves_a_cube_from_20_degrees(tmp_path):
    # The quick profile's defaults (48 px, 60 Adam steps, back faces culled on the closed cube),
    # two problems.
    config = render_pose.Config.quick(problems=2, methods=("perturbed-gaussian",), init_errors_deg=(20.0,), gif_every=5)
    metrics = render_pose.run(config, tmp_path, jax.random.key(0), progress=False)
    result = metrics["perturbed-gaussian"]["20"]
    assert result["solved_pct"] == 100.0, result
    assert result["mean_error_deg"] < 10.0
    assert result["runs_per_problem"] == 1.0 and result["seconds_per_step"] > 0
    saved = json.loads((tmp_path / "metrics.json").read_text())
    assert saved["perturbed-gaussian"]["20"]["solved_pct"] == 100.0
    assert saved["cull_backfaces"] is True and saved["faces_per_pixel"] == render_pose.Config().faces_per_pixel
    assert saved["num_samples"] == config.num_samples == 8  # the quick profile's (the default: 16)
    assert saved["baseline"] == "hard" and saved["batch_size"] == 2
    for name in ("errors.png", "renders_20deg.png", "optimization.gif"):
        assert (tmp_path / name).stat().st_size > 0
    assert not list(tmp_path.glob(".*"))
    lines = render_pose.summary(metrics)
    assert lines == {"perturbed-gaussian: solved % from 20 deg": "100"}


@pytest.mark.parametrize(
    "change",
    [
        {"methods": ("blurry",)}, {"methods": ()}, {"batch_size": 0}, {"problems": 0}, {"pose_noise_deg": -1.0},
        {"pose_noise_deg": float("nan")}, {"pose_noise_until": 0.0}, {"pose_noise_until": 1.5},
        {"restarts": -1}, {"restart_loss": 0.0}, {"restart_loss": float("nan")},
        {"sample_growth": 0}, {"max_samples": 0}, {"average_decay": 1.0},
        {"average_decay": -0.1}, {"average_decay": float("nan")}, {"baseline": "mean"}, {"pixel_chunk": 0.0},
        {"pixel_chunk": 1.5}, {"init_errors_deg": (20.0, 190.0)}, {"init_errors_deg": (-1.0,)}, {"init_errors_deg": ()},
    ],
)
def test_bad_config_is_rejected(change):
    name = next(iter(change))
    with pytest.raises(ValueError, match=name if name != "methods" or change[name] == () else "blurry"):
        render_pose.Config.quick(**change)


def test_the_experiment_is_registered_with_its_options():
    experiment = render_pose.EXPERIMENT
    assert experiment.command == ("render", "pose") and experiment.name == "render-pose" and not experiment.x64
    flags = {_protocol.flag(f) for f in dataclasses.fields(render_pose.Config)}
    for flag in ("--samples", "--init-error", "--method", "--average-iterates", "--pose-noise", "--pixel-chunk",
                 "--baseline", "--restarts", "--keep-best", "--antithetic-pose", "--sample-growth", "--max-samples"):
        assert flag in flags, flag


def test_hard_renderer_fit_stays_unsmoothed():
    # The hard renderer is the unsmoothed baseline: no pose noise, a constant schedule; the
    # smoothed renderers get the configured pose noise, and only the perturbed ones sample growth.
    config = render_pose.Config.quick(pose_noise_deg=30.0, sample_growth=2)
    mesh = render_pose.load(config.mesh)
    hard, soft, perturbed = (render_pose.make_fit(config, m, mesh) for m in ("hard", "soft", "perturbed-gaussian"))
    assert hard.pose_noise == 0.0 and not hard.grows
    assert soft.pose_noise == perturbed.pose_noise == pytest.approx(np.deg2rad(30.0)) and not soft.grows
    assert perturbed.grows and perturbed.renderer.baseline is True


def test_problems_start_at_the_initial_error():
    config = render_pose.Config.quick(problems=3)
    r_true, r_init, offset = render_pose.problems(config, jax.random.key(1), 50.0)
    np.testing.assert_allclose(render_pose._degrees(r_init, r_true), 50.0, rtol=1e-5)
    np.testing.assert_array_equal(offset, 0.0)  # the translation is not optimized
