"""The render-reconstruct experiment, small: the perturbed renderer carves a cube out of an
icosphere; the hard renderer gives the silhouette loss no gradient."""

import dataclasses
import json

import jax
import numpy as np
import pytest

from rsmooth.experiments import _protocol, render_reconstruct

TINY = dict(
    targets=("cube",), methods=("perturbed-gaussian", "hard"), views=3, image_size=24, steps=20,
    learning_rate=0.03, patience=5, voxel_resolution=24, chamfer_points=256, gif_every=10,
)


@pytest.mark.slow
def test_perturbed_reconstruction_of_a_cube_improves_and_hard_does_not_move(tmp_path):
    config = render_reconstruct.Config.quick(**TINY)
    metrics = render_reconstruct.run(config, tmp_path, jax.random.key(0), progress=False)
    initial, perturbed, hard = (metrics[k]["cube"] for k in ("initial", "perturbed-gaussian", "hard"))
    # (Seeds 0 to 3: 3D IoU 0.51 -> 0.65 to 0.71, silhouette IoU 0.47 -> 0.84 to 0.88, Chamfer
    # divided by 1.6 to 1.9.)
    assert perturbed["iou_3d"] > initial["iou_3d"] + 0.08, (initial, perturbed)
    assert perturbed["silhouette_iou"] > initial["silhouette_iou"] + 0.25
    assert perturbed["chamfer"] < 0.75 * initial["chamfer"]
    # The hard renderer's silhouettes give no gradient; only the regularizers act on its mesh,
    # and they vanish at the icosphere.
    assert hard["first_gradient_norm"] == 0.0 and perturbed["first_gradient_norm"] > 0.0
    assert hard["silhouette_iou"] == pytest.approx(initial["silhouette_iou"], abs=0.02)
    assert hard["iou_3d"] == pytest.approx(initial["iou_3d"], abs=0.02)
    saved = json.loads((tmp_path / "metrics.json").read_text())
    keys = ("iou_3d", "chamfer", "silhouette_iou", "final_loss", "final_sigma", "first_gradient_norm", "seconds_per_step")
    assert set(keys) <= set(saved["perturbed-gaussian"]["cube"]) and set(keys) <= set(saved["hard"]["cube"])
    assert saved["targets"] == ["cube"] and saved["num_faces"] == 320
    assert (saved["num_samples"], saved["laplacian_weight"]) == (config.num_samples, config.laplacian_weight)
    assert saved["baseline"] == "hard" and saved["pixel_chunk"] == config.pixel_chunk
    for name in ("losses.png", "silhouettes_cube.png", "reconstructions.png", "optimization.gif"):
        assert (tmp_path / name).stat().st_size > 0
    assert not list(tmp_path.glob(".*"))


def test_targets_are_normalized_into_the_unit_box():
    for name in ("torus", "solo-upper-leg"):
        vertices = np.asarray(render_reconstruct.load_target(name).vertices)
        low, high = vertices.min(axis=0), vertices.max(axis=0)
        np.testing.assert_allclose(low + high, 0.0, atol=1e-12)
        assert np.max(high - low) == pytest.approx(1.0)


def test_unknown_targets_and_methods_are_rejected(tmp_path):
    with pytest.raises(ValueError, match="blob"):
        render_reconstruct.load_target("blob")
    with pytest.raises(ValueError, match="not found"):
        render_reconstruct.load_target(str(tmp_path / "missing.stl"))
    with pytest.raises(ValueError, match="blurry"):
        render_reconstruct.Config.quick(methods=("blurry",))
    for name, value in (
        ("laplacian_weight", -1.0), ("flatten_weight", float("nan")), ("baseline", "mean"), ("pixel_chunk", 0.0),
        ("targets", ()), ("targets", ("cube", "cube")),
    ):
        with pytest.raises(ValueError, match=name):
            render_reconstruct.Config.quick(**{name: value})


def test_the_experiment_is_registered_with_its_options():
    experiment = render_reconstruct.EXPERIMENT
    assert experiment.command == ("render", "reconstruct") and experiment.name == "render-reconstruct"
    flags = {_protocol.flag(f) for f in dataclasses.fields(render_reconstruct.Config)}
    for flag in ("--mesh", "--views", "--method", "--steps", "--samples", "--pixel-chunk", "--laplacian-weight", "--baseline"):
        assert flag in flags, flag
    metrics = {"methods": ["soft"], "targets": ["cube"], "soft": {"cube": {"iou_3d": 0.5, "chamfer": 0.01}}}
    assert render_reconstruct.summary(metrics) == {"soft: 3D IoU / Chamfer (cube)": "0.50 / 0.0100"}
