"""The command line's generic experiment runner."""

import dataclasses
import json
import sys
import types
from pathlib import Path
from typing import Optional

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


# -- output folders, operating-system errors, interrupts -------------------------------------


def _command(experiment):
    """A one-command app that runs `experiment` through the command line's runner."""
    import typer

    app = typer.Typer()

    @app.command()
    def run(out: Optional[Path] = typer.Option(None, "--out"), quick: bool = typer.Option(False, "--quick")):
        cli._run(experiment, out, 0, quick)

    return app


def _writing_experiment(monkeypatch, names):
    """A fake experiment that writes `names[config.label]` (atomically, as the experiments do)."""
    from rsmooth._files import atomic_path

    def run(config, out, key):
        for name in names[config.label]:
            with atomic_path(out / name) as temporary:
                temporary.write_text(config.label)
        return {}

    monkeypatch.setitem(sys.modules, "rsmooth.experiments.writer", types.SimpleNamespace(Config=FakeConfig, run=run))
    return cli._Experiment("writer", "writer", "writer", lambda metrics: {})


def test_rerun_removes_the_previous_runs_files_and_keeps_the_others(monkeypatch, tmp_path):
    experiment = _writing_experiment(monkeypatch, {"full": ["metrics.json", "a.png", "b.png"], "quick": ["metrics.json", "a.png"]})
    app, out = _command(experiment), tmp_path / "out"
    assert CliRunner().invoke(app, ["--out", str(out)]).exit_code == 0
    (out / "notes.txt").write_text("mine")
    (out / "folder").mkdir()
    result = CliRunner().invoke(app, ["--out", str(out), "--quick"])
    assert result.exit_code == 0, result.output
    # b.png of the first run is gone; what rsmooth did not write stays
    assert sorted(p.name for p in out.iterdir()) == ["a.png", "folder", "metrics.json", "notes.txt", "rsmooth-files.json"]
    assert (out / "a.png").read_text() == "quick" and (out / "notes.txt").read_text() == "mine"
    assert json.loads((out / "rsmooth-files.json").read_text())["files"] == ["a.png", "metrics.json"]


def test_output_folder_errors_are_one_line(monkeypatch, tmp_path):
    experiment = _writing_experiment(monkeypatch, {"full": ["metrics.json"], "quick": []})
    app = _command(experiment)
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "thesis.tex").write_text("keep me")
    a_file = tmp_path / "file.txt"
    a_file.write_text("")
    expected = {
        foreign: f"rsmooth: error: --out {foreign} is not empty (thesis.tex) and holds no previous run of rsmooth "
        "(no rsmooth-files.json): choose a new or empty folder",
        a_file: f"rsmooth: error: --out {a_file} is a file, not a folder",
        a_file / "out": f"rsmooth: error: --out {a_file / 'out'}: a parent of it is a file, not a folder",
    }
    for out, line in expected.items():
        result = CliRunner().invoke(app, ["--out", str(out)])
        assert result.exit_code == 1 and result.output.strip() == line
    assert sorted(p.name for p in foreign.iterdir()) == ["thesis.tex"]


def test_operating_system_errors_during_a_run_are_one_line(monkeypatch, tmp_path):
    def run(config, out, key):
        raise PermissionError(13, "Permission denied", str(out / "metrics.json"))

    monkeypatch.setitem(sys.modules, "rsmooth.experiments.denied", types.SimpleNamespace(Config=FakeConfig, run=run))
    result = CliRunner().invoke(_command(cli._Experiment("denied", "denied", "denied", None)), ["--out", str(tmp_path)])
    assert result.exit_code == 1
    assert result.output.strip() == f"rsmooth: error: Permission denied: {tmp_path / 'metrics.json'}"


@pytest.mark.parametrize("value", ["nan", "inf", "-5", "200"])
def test_render_pose_rejects_an_initial_error_that_is_not_an_angle(monkeypatch, tmp_path, value):
    calls = []
    monkeypatch.setattr(cli, "_run", lambda *args, **overrides: calls.append(overrides))
    result = CliRunner().invoke(cli.app, ["render", "pose", "--init-error", "20", "--init-error", value, "--out", str(tmp_path)])
    assert result.exit_code != 0 and "--init-error" in result.output and not calls


def test_render_pose_run_rejects_initial_errors_that_are_not_angles(tmp_path):
    import jax

    from rsmooth.experiments import render_pose

    for errors in ((float("nan"),), (20.0, 181.0), ()):
        config = dataclasses.replace(render_pose.Config.quick(), init_errors_deg=errors)
        with pytest.raises(ValueError, match="init_errors_deg must hold"):
            render_pose.run(config, tmp_path, jax.random.key(0), progress=False)
    assert not any(tmp_path.iterdir())


INTERRUPTED_SCRIPT = """
import gc, signal, sys, time, types
from rsmooth import cli

# As in a terminal, whatever started the tests (a background job ignores SIGINT).
signal.signal(signal.SIGINT, signal.default_int_handler)

def compiling(config, out, key):
    import jax, jax.numpy as jnp

    print("started", flush=True)
    for i in range(10**6):  # compile after compile: the interrupt lands in one
        def f(x, i=i):
            for j in range(1500):
                x = jnp.sin(x * (i + j)) + jnp.cos(x)
            return x
        jax.jit(f).lower(jnp.ones(3)).compile()

def collecting(config, out, key):
    # Most of the time in garbage-collection callbacks, which drop the exceptions raised in them.
    gc.callbacks.append(lambda phase, info: time.sleep(0.2))
    print("started", flush=True)
    while True:
        gc.collect()
        time.sleep(0.05)

run = compiling if sys.argv[1] == "compiling" else collecting
sys.modules["rsmooth.experiments.slow"] = types.SimpleNamespace(Config=types.SimpleNamespace, run=run)

@cli.experiment_app.command("slow")
def slow(out: str):
    cli._run(cli._Experiment("slow", "slow", "slow", None), out, 0, False)

sys.argv = ["rsmooth", "experiment", "slow", "out"]
cli.main()
"""


@pytest.mark.parametrize("during", ["compiling", "collecting"])
def test_ctrl_c_stops_the_command_with_a_message_and_code_130(tmp_path, during):
    # An interrupt during an XLA compilation used to end in a segmentation fault (the
    # interpreter's shutdown destroyed the backend under the compiling thread); one that landed
    # in a garbage-collection callback was dropped, and the run went on.
    import signal
    import subprocess
    import time

    (tmp_path / "script.py").write_text(INTERRUPTED_SCRIPT)
    process = subprocess.Popen([sys.executable, "script.py", during], cwd=tmp_path, text=True,
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        assert process.stdout.readline() == "started\n"
        time.sleep(1.0)
        process.send_signal(signal.SIGINT)
        _, stderr = process.communicate(timeout=30)
    finally:
        process.kill()
    assert process.returncode == 130, stderr
    assert stderr.strip() == "rsmooth: interrupted"
