"""The command line's generic experiment runner."""

import dataclasses
import sys
import types

import pytest
from typer.testing import CliRunner

from rsmooth import cli


@dataclasses.dataclass(frozen=True)
class FakeConfig:
    size: int = 10
    label: str = "full"

    @classmethod
    def quick(cls):
        return cls(size=2, label="quick")


@pytest.fixture
def fake_experiment(monkeypatch):
    calls = []

    def run(config, out, key):
        calls.append((config, out))
        return {"methods": ["ddp", "rddp"], "ddp": {"score": 0.25}, "rddp": {"score": 0.75}}

    module = types.SimpleNamespace(Config=FakeConfig, run=run)
    monkeypatch.setitem(sys.modules, "rsmooth.experiments.fake", module)
    summary = lambda metrics: {f"{name} score": metrics[name]["score"] for name in metrics["methods"]}  # noqa: E731
    return cli._Experiment("fake-name", "fake", "fake title", summary), calls


def test_run_builds_the_config_runs_and_reports(fake_experiment, tmp_path, capsys):
    experiment, calls = fake_experiment
    metrics = cli._run(experiment, tmp_path / "out", 0, True, size=5, label=None)
    # Overrides that are None keep the Config's value; the others replace it.
    assert calls == [(FakeConfig(size=5, label="quick"), tmp_path / "out")]
    assert metrics["rddp"]["score"] == 0.75
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("fake title: done in ") and lines[0].endswith(f"artifacts in {tmp_path / 'out'}/")
    assert lines[1:] == ["  ddp score: 0.25", "  rddp score: 0.75"]


def test_run_under_a_root_uses_the_experiment_name_and_a_given_title(fake_experiment, tmp_path, capsys):
    experiment, calls = fake_experiment
    cli._run(experiment, None, 0, False, root=tmp_path, title="other title")
    assert calls == [(FakeConfig(), tmp_path / "fake-name")]
    assert (tmp_path / "fake-name").is_dir()
    assert capsys.readouterr().out.startswith("other title: done in ")


def test_control_summary_prints_the_success_rate_then_the_row():
    summary = cli._control_summary("height (mm)", lambda metrics: f"{1000 * metrics['height']:.1f}")
    metrics = {"methods": ["ddp"], "ddp": {"success_rate": 0.5, "height": 0.0123}}
    assert summary(metrics) == {"ddp: success rate, height (mm)": "50 %, 12.3"}


def test_solo_lift_all_feet_runs_each_foot_into_its_folder(monkeypatch, tmp_path):
    from typer.testing import CliRunner

    calls = []

    def fake_run(experiment, out, seed, quick, title=None, **overrides):
        calls.append((experiment.name, out, overrides["foot"], overrides["method"]))
        return {"methods": ["rddp"], "rddp": {"success_rate": 1.0 if overrides["foot"] != "HR" else 0.5}}

    monkeypatch.setattr(cli, "_run", fake_run)
    result = CliRunner().invoke(cli.app, ["control", "solo-lift", "--foot", "all", "--method", "rddp", "--out", str(tmp_path)])
    assert result.exit_code == 0, result.output
    assert [(c[1], c[2]) for c in calls] == [(tmp_path / f, f) for f in ("FL", "FR", "HL", "HR")]
    assert "HR: rddp 50 %" in result.output and "FL: rddp 100 %" in result.output
    bad = CliRunner().invoke(cli.app, ["control", "solo-lift", "--foot", "every", "--out", str(tmp_path)])
    assert bad.exit_code != 0 and "--foot" in bad.output


def test_render_pose_method_and_steps_reach_the_config(monkeypatch, tmp_path):
    calls = []
    monkeypatch.setattr(cli, "_run", lambda experiment, out, seed, quick, **overrides: calls.append((experiment.module, overrides)))
    result = CliRunner().invoke(cli.app, ["render", "pose", "--method", "soft", "--method", "perturbed-gaussian",
                                          "--method", "soft", "--steps", "250", "--samples", "16", "--out", str(tmp_path)])
    assert result.exit_code == 0, result.output
    module, overrides = calls[-1]
    assert module == "render_pose"
    assert overrides["methods"] == ("soft", "perturbed-gaussian") and overrides["steps"] == 250
    assert overrides["num_samples"] == 16
    CliRunner().invoke(cli.app, ["render", "pose", "--out", str(tmp_path)])
    # the Config's defaults
    assert calls[-1][1]["methods"] is None and calls[-1][1]["steps"] is None and calls[-1][1]["keep_best"] is None
    assert calls[-1][1]["num_samples"] is None
    CliRunner().invoke(cli.app, ["render", "pose", "--last", "--out", str(tmp_path)])
    assert calls[-1][1]["keep_best"] is False and calls[-1][1]["pose_noise_deg"] is None
    CliRunner().invoke(cli.app, ["render", "pose", "--pose-noise", "0", "--pose-noise-until", "0.75", "--out", str(tmp_path)])
    assert calls[-1][1]["pose_noise_deg"] == 0.0 and calls[-1][1]["pose_noise_until"] == 0.75
    bad = CliRunner().invoke(cli.app, ["render", "pose", "--method", "blurry", "--out", str(tmp_path)])
    assert bad.exit_code != 0 and "--method" in bad.output and len(calls) == 4
    negative = CliRunner().invoke(cli.app, ["render", "pose", "--pose-noise", "-1", "--out", str(tmp_path)])
    assert negative.exit_code != 0 and "--pose-noise" in negative.output and len(calls) == 4
    beyond = CliRunner().invoke(cli.app, ["render", "pose", "--pose-noise-until", "1.5", "--out", str(tmp_path)])
    assert beyond.exit_code != 0 and "--pose-noise-until" in beyond.output and len(calls) == 4
    CliRunner().invoke(cli.app, ["render", "pose", "--sample-growth", "2", "--max-samples", "64", "--out", str(tmp_path)])
    assert calls[-1][1]["sample_growth"] == 2 and calls[-1][1]["max_samples"] == 64 and len(calls) == 5
    assert calls[-2][1]["sample_growth"] is None and calls[-2][1]["max_samples"] is None  # the Config's defaults
    zero = CliRunner().invoke(cli.app, ["render", "pose", "--sample-growth", "0", "--out", str(tmp_path)])
    assert zero.exit_code != 0 and "--sample-growth" in zero.output and len(calls) == 5


def test_control_estimator_and_samples_reach_the_configs(monkeypatch, tmp_path):
    calls = []
    monkeypatch.setattr(cli, "_run", lambda experiment, out, seed, quick, title=None, **overrides: calls.append(
        (experiment.module, overrides)) or {})
    for task in ("cube-lift", "pusher", "solo-lift"):
        result = CliRunner().invoke(cli.app, ["control", task, "--estimator", "alpha", "--samples", "16", "--out", str(tmp_path)])
        assert result.exit_code == 0, result.output
        assert calls[-1][1]["estimator"] == "alpha" and calls[-1][1]["num_samples"] == 16, (task, calls[-1])
        CliRunner().invoke(cli.app, ["control", task, "--out", str(tmp_path)])
        assert calls[-1][1]["estimator"] is None and calls[-1][1]["num_samples"] is None  # the Config's defaults
    count = len(calls)
    for bad in (["--estimator", "second"], ["--estimator", "alpha", "--samples", "2"]):
        result = CliRunner().invoke(cli.app, ["control", "solo-lift", *bad, "--out", str(tmp_path)])
        assert result.exit_code != 0 and bad[-2] in result.output
    assert len(calls) == count


def test_command_help_keeps_paragraphs_and_reflows_their_lines(monkeypatch):
    module = types.SimpleNamespace(METRICS_DOC="metrics.json keys: a (one\nthing), b\n  (another).\n\nSecond paragraph.")
    monkeypatch.setitem(sys.modules, "rsmooth.experiments.fake", module)
    doc = cli._doc("A summary\nover two lines.", cli._Experiment("fake-name", "fake", "fake title", None))
    # Typer keeps single newlines, which the terminal would wrap again into ragged lines.
    assert doc == "A summary over two lines.\n\nmetrics.json keys: a (one thing), b (another).\n\nSecond paragraph."


def test_render_reconstruct_options_reach_the_config(monkeypatch, tmp_path):
    calls = []
    monkeypatch.setattr(cli, "_run", lambda experiment, out, seed, quick, **overrides: calls.append((experiment.module, overrides)))
    result = CliRunner().invoke(cli.app, ["render", "reconstruct", "--method", "soft", "--method", "hard", "--steps", "50",
                                          "--samples", "32", "--laplacian-weight", "120", "--out", str(tmp_path)])
    assert result.exit_code == 0, result.output
    module, overrides = calls[-1]
    assert module == "render_reconstruct"
    assert overrides["methods"] == ("soft", "hard") and overrides["steps"] == 50
    assert overrides["num_samples"] == 32 and overrides["laplacian_weight"] == 120.0
    CliRunner().invoke(cli.app, ["render", "reconstruct", "--out", str(tmp_path)])
    assert all(calls[-1][1][name] is None for name in ("methods", "steps", "num_samples", "laplacian_weight"))
    bad = CliRunner().invoke(cli.app, ["render", "reconstruct", "--method", "blurry", "--out", str(tmp_path)])
    assert bad.exit_code != 0 and "--method" in bad.output and len(calls) == 2
    negative = CliRunner().invoke(cli.app, ["render", "reconstruct", "--laplacian-weight", "-1", "--out", str(tmp_path)])
    assert negative.exit_code != 0 and "--laplacian-weight" in negative.output and len(calls) == 2


@pytest.mark.parametrize("command", ["pose", "reconstruct"])
def test_render_baseline_option_reaches_the_config(monkeypatch, tmp_path, command):
    calls = []
    monkeypatch.setattr(cli, "_run", lambda experiment, out, seed, quick, **overrides: calls.append(overrides))
    for value, expected in (("hard", True), ("leave-one-out", "leave-one-out")):
        result = CliRunner().invoke(cli.app, ["render", command, "--baseline", value, "--out", str(tmp_path)])
        assert result.exit_code == 0, result.output
        assert calls[-1]["baseline"] == expected
    CliRunner().invoke(cli.app, ["render", command, "--out", str(tmp_path)])
    assert calls[-1]["baseline"] is None  # the Config's default
    bad = CliRunner().invoke(cli.app, ["render", command, "--baseline", "mean", "--out", str(tmp_path)])
    assert bad.exit_code != 0 and "--baseline" in bad.output and len(calls) == 3
