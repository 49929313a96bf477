"""The command line: commands and options made from the experiments' Configs, the runner."""

import dataclasses
import json
import sys
from typing import Optional

import pytest
from typer.testing import CliRunner

from rsmooth import cli
from rsmooth.experiments import _protocol, registry
from rsmooth.experiments._protocol import option


@dataclasses.dataclass(frozen=True)
class FakeConfig:
    """One field of each kind the command line handles."""

    size: int = option(10, "Size of the thing.", min=1)
    label: str = option("full", "Which label.", choices=("full", "quick", "other"))
    scales: tuple[float, ...] = option((1.0, 2.0), "Noise scales.", flag="scale", min=0.0)
    kinds: tuple[str, ...] = option(("a", "b"), "Kinds run.", flag="kind", choices=("a", "b", "c"))
    verbose: bool = option(True, "Print more.", flag="verbose/quiet")
    limit: Optional[int] = option(None, "A limit, if any.")
    grid: tuple[float, int] = option((0.0, 5), "Start and number of points.")
    internal: int = option(3, "Set in code only.", cli=False)

    @classmethod
    def quick(cls):
        return cls(size=2, label="quick")

    def __post_init__(self):
        _protocol.check_options(self)
        if self.label == "other" and self.size > 5:
            raise ValueError(f"size must be <= 5 with label other, got {self.size}")


def _summary(metrics):
    return {f"{name} score": metrics[name]["score"] for name in metrics["methods"]}


def _experiment(config=FakeConfig, run=None, name="fake-name", command=("experiment", "fake"), **changes):
    def fake_run(config, out, key):
        return {"methods": ["ddp", "rddp"], "ddp": {"score": 0.25}, "rddp": {"score": 0.75}}

    return _protocol.Experiment(command=command, name=name, config=config, run=run or fake_run, summary=_summary,
                                help="A fake experiment.", metrics_doc="metrics.json keys: score.", **changes)


def _help(app, *command) -> str:
    """The command's ``--help`` on a wide terminal (at 80 columns Rich cuts long flags short),
    its table's borders and line breaks taken out."""
    from unittest import mock

    from typer import rich_utils

    with mock.patch.object(rich_utils, "MAX_WIDTH", 240):
        result = CliRunner().invoke(app, [*command, "--help"])
    assert result.exit_code == 0, result.output
    return " ".join(result.output.replace("\u2502", " ").split())


def _recorded(monkeypatch):
    """Replaces the runner: the calls' configs (and output folders) are recorded."""
    calls = []

    def run(experiment, config, out, seed, root=None, title=None):
        calls.append((experiment.name, config, out, title))
        return {"methods": ["rddp"], "rddp": {"success_rate": 0.5 if getattr(config, "foot", None) == "HR" else 1.0}}

    monkeypatch.setattr(cli, "_run", run)
    return calls


# -- options from Config fields ---------------------------------------------------------------


def test_options_come_from_the_config_fields_with_their_help_and_defaults():
    text = _help(cli.build_app([_experiment()]), "experiment", "fake")
    for expected in ("--out", "--seed", "--quick", "Size of the thing. (default 10, quick 2)",
                     "Which label. One of: full, quick, other. (default full, quick quick)",
                     "--scale", "Noise scales. Repeatable. (default 1, 2)", "--kind", "One of: a, b, c.",
                     "--verbose", "--quiet", "Print more. (default --verbose)", "--limit", "(default none)",
                     "--grid", "(default 0, 5)", "metrics.json keys: score."):
        assert expected in text, expected
    assert "--internal" not in text


def test_options_reach_the_config_and_none_keeps_its_value(monkeypatch):
    calls = _recorded(monkeypatch)
    app = cli.build_app([_experiment()])
    assert CliRunner().invoke(app, ["experiment", "fake"]).exit_code == 0
    assert calls[-1][1] == FakeConfig()
    assert CliRunner().invoke(app, ["experiment", "fake", "--quick", "--label", "other"]).exit_code == 0
    assert calls[-1][1] == FakeConfig(size=2, label="other")  # the quick Config, changed
    result = CliRunner().invoke(app, ["experiment", "fake", "--scale", "0.5", "--scale", "0.5", "--kind", "c", "--kind", "a",
                                      "--kind", "c", "--quiet", "--limit", "7", "--grid", "-1", "9"])
    assert result.exit_code == 0, result.output
    # a repeated option is a tuple; a selection among choices keeps each once, in order
    assert calls[-1][1] == FakeConfig(scales=(0.5, 0.5), kinds=("c", "a"), verbose=False, limit=7, grid=(-1.0, 9))


@pytest.mark.parametrize("args, flags", [
    (["--label", "none"], ["--label"]),
    (["--size", "0"], ["--size"]),
    (["--scale", "1", "--scale", "-1"], ["--scale"]),
    (["--kind", "d"], ["--kind"]),
    (["--label", "other"], ["--size", "--label"]),  # a check of two fields names both flags
])
def test_values_the_config_rejects_are_usage_errors_naming_the_flag(monkeypatch, args, flags):
    calls = _recorded(monkeypatch)
    result = CliRunner().invoke(cli.build_app([_experiment()]), ["experiment", "fake", *args])
    assert result.exit_code == 2 and not calls
    assert "Invalid value for " + " / ".join(f"'{flag}'" for flag in flags) in " ".join(result.stderr.split())
    assert "Traceback" not in result.output


def test_a_new_config_field_is_a_new_option(monkeypatch):
    """Adding an option is adding a field: the command line needs no change."""

    @dataclasses.dataclass(frozen=True)
    class WiderConfig(FakeConfig):
        width: float = option(1.5, "Width of the thing, m.", min=0.0)

    calls = _recorded(monkeypatch)
    app = cli.build_app([_experiment(WiderConfig)])
    help_text = _help(app, "experiment", "fake")
    assert "--width" in help_text and "Width of the thing, m. (default 1.5)" in help_text
    assert CliRunner().invoke(app, ["experiment", "fake", "--width", "2"]).exit_code == 0
    assert calls[-1][1].width == 2.0
    bad = CliRunner().invoke(app, ["experiment", "fake", "--width", "-1"])
    assert bad.exit_code == 2 and "'--width'" in bad.stderr


def test_every_registered_command_lists_its_config_fields():
    experiments = registry()
    assert [" ".join(command) for command in experiments][:4] == [
        "experiment estimators", "experiment perturbed-argmax", "experiment null-gradients", "sim solo12"]
    assert len({experiment.name for experiment in experiments.values()}) == len(experiments)
    for command, experiment in experiments.items():
        text = _help(cli.app, *command)
        for field in cli.cli_fields(experiment.config):
            assert _protocol.flag(field) in text, (command, field.name)
        assert " ".join(experiment.metrics_doc.split())[:40] in text, command


def test_command_help_keeps_paragraphs_and_reflows_their_lines():
    doc = cli._doc("A summary\nover two lines.", "metrics.json keys: a (one\nthing), b\n  (another).\n\nSecond paragraph.")
    # Typer keeps single newlines, which the terminal would wrap again into ragged lines.
    assert doc == "A summary over two lines.\n\nmetrics.json keys: a (one thing), b (another).\n\nSecond paragraph."


# -- the commands' special cases ----------------------------------------------------------------


def test_solo_lift_all_feet_runs_each_foot_into_its_folder(monkeypatch, tmp_path):
    calls = _recorded(monkeypatch)
    result = CliRunner().invoke(cli.app, ["control", "solo-lift", "--foot", "all", "--method", "rddp", "--out", str(tmp_path)])
    assert result.exit_code == 0, result.output
    assert [(out, config.foot, config.method) for _, config, out, _ in calls] == [
        (tmp_path / foot, foot, "rddp") for foot in ("FL", "FR", "HL", "HR")]
    assert [title for *_, title in calls] == [f"control solo-lift {foot}" for foot in ("FL", "FR", "HL", "HR")]
    assert "HR: rddp 50 %" in result.output and "FL: rddp 100 %" in result.output
    CliRunner().invoke(cli.app, ["control", "solo-lift", "--foot", "HL", "--out", str(tmp_path)])
    assert calls[-1][1].foot == "HL" and calls[-1][2] == tmp_path and len(calls) == 5
    bad = CliRunner().invoke(cli.app, ["control", "solo-lift", "--foot", "every", "--out", str(tmp_path)])
    assert bad.exit_code == 2 and "--foot" in bad.output and len(calls) == 5


def test_control_options_reach_the_configs_and_their_checks_name_the_flags(monkeypatch, tmp_path):
    calls = _recorded(monkeypatch)
    for task in ("cube-lift", "pusher", "panda-push", "solo-lift"):
        result = CliRunner().invoke(cli.app, ["control", task, "--estimator", "alpha", "--samples", "16", "--out", str(tmp_path)])
        assert result.exit_code == 0, result.output
        assert (calls[-1][1].estimator, calls[-1][1].num_samples) == ("alpha", 16), task
        CliRunner().invoke(cli.app, ["control", task, "--quick", "--out", str(tmp_path)])
        assert calls[-1][1] == registry()[("control", task)].config.quick()
    count = len(calls)
    for bad in (["--estimator", "second"], ["--estimator", "alpha", "--samples", "2"], ["--height", "0.2"]):
        result = CliRunner().invoke(cli.app, ["control", "solo-lift", *bad, "--out", str(tmp_path)])
        assert result.exit_code == 2 and bad[-2] in result.output
    assert len(calls) == count


def test_policy_commands_are_two_experiments_with_their_own_options(monkeypatch, tmp_path):
    calls = _recorded(monkeypatch)
    for command in ("policy", "policy-pusher"):
        result = CliRunner().invoke(cli.app, ["control", command, "--method", "zeroth", "--sigma", "0.2"])
        assert result.exit_code == 0, result.output
        assert calls[-1][0] == command and (calls[-1][1].method, calls[-1][1].sigma) == ("zeroth", 0.2)
    assert "--at-rest" in CliRunner().invoke(cli.app, ["control", "policy-pusher", "--help"]).output
    odd = CliRunner().invoke(cli.app, ["control", "policy-pusher", "--samples", "7"])
    assert odd.exit_code == 2 and "--samples" in odd.output
    zero = CliRunner().invoke(cli.app, ["control", "policy", "--sigma", "0"])
    assert zero.exit_code == 2 and "--sigma" in zero.output and len(calls) == 2


def test_sim_solo12_open_loop_drops_the_posture_gains(monkeypatch):
    calls = _recorded(monkeypatch)
    assert CliRunner().invoke(cli.app, ["sim", "solo12", "--torques", "random", "--open-loop", "--feet-only"]).exit_code == 0
    config = calls[-1][1]
    assert config.open_loop and not config.body_contacts and config.gains() == (0.0, 0.0)
    assert dataclasses.replace(config, open_loop=False).gains() == (config.stiffness, config.damping)


# -- the runner: output folders, operating-system errors, interrupts ------------------------------


def test_run_runs_the_config_and_reports(tmp_path, capsys):
    calls = []
    experiment = _experiment(run=lambda config, out, key: calls.append((config, out)) or {
        "methods": ["ddp", "rddp"], "ddp": {"score": 0.25}, "rddp": {"score": 0.75}})
    metrics = cli._run(experiment, FakeConfig(size=5), tmp_path / "out", 0)
    assert calls == [(FakeConfig(size=5), tmp_path / "out")] and metrics["rddp"]["score"] == 0.75
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("experiment fake: done in ") and lines[0].endswith(f"artifacts in {tmp_path / 'out'}/")
    assert lines[1:] == ["  ddp score: 0.25", "  rddp score: 0.75"]
    cli._run(experiment, FakeConfig(), None, 0, root=tmp_path, title="other title")
    assert calls[-1] == (FakeConfig(), tmp_path / "fake-name") and (tmp_path / "fake-name").is_dir()
    assert capsys.readouterr().out.startswith("other title: done in ")


def _writing_app(names):
    """A one-command app whose experiment writes `names[config.label]` (atomically, as the
    experiments do)."""
    from rsmooth._files import atomic_path

    def run(config, out, key):
        for name in names[config.label]:
            with atomic_path(out / name) as temporary:
                temporary.write_text(config.label)
        return {"methods": []}

    return cli.build_app([_experiment(run=run, name="writer")])


def test_rerun_removes_the_previous_runs_files_and_keeps_the_others(tmp_path):
    app, out = _writing_app({"full": ["metrics.json", "a.png", "b.png"], "quick": ["metrics.json", "a.png"]}), tmp_path / "out"
    assert CliRunner().invoke(app, ["experiment", "fake", "--out", str(out)]).exit_code == 0
    (out / "notes.txt").write_text("mine")
    (out / "folder").mkdir()
    result = CliRunner().invoke(app, ["experiment", "fake", "--out", str(out), "--quick"])
    assert result.exit_code == 0, result.output
    # b.png of the first run is gone; what rsmooth did not write stays
    assert sorted(p.name for p in out.iterdir()) == ["a.png", "folder", "metrics.json", "notes.txt", "rsmooth-files.json"]
    assert (out / "a.png").read_text() == "quick" and (out / "notes.txt").read_text() == "mine"
    assert json.loads((out / "rsmooth-files.json").read_text())["files"] == ["a.png", "metrics.json"]


def test_output_folder_errors_are_one_line(tmp_path):
    app = _writing_app({"full": ["metrics.json"], "quick": []})
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
        result = CliRunner().invoke(app, ["experiment", "fake", "--out", str(out)])
        assert result.exit_code == 1 and result.output.strip() == line
    assert sorted(p.name for p in foreign.iterdir()) == ["thesis.tex"]


def test_operating_system_errors_during_a_run_are_one_line(tmp_path):
    def run(config, out, key):
        raise PermissionError(13, "Permission denied", str(out / "metrics.json"))

    result = CliRunner().invoke(cli.build_app([_experiment(run=run)]), ["experiment", "fake", "--out", str(tmp_path)])
    assert result.exit_code == 1
    assert result.output.strip() == f"rsmooth: error: Permission denied: {tmp_path / 'metrics.json'}"


# -- the render commands (their Configs: rsmooth.experiments.render_pose, render_reconstruct) ---


def _value(config, flag: str):
    """The value of the Config field whose command-line flag is `flag`."""
    (field,) = [field for field in cli.cli_fields(type(config)) if _protocol.flag(field) == flag]
    return getattr(config, field.name)


def test_render_pose_options_reach_the_config(monkeypatch, tmp_path):
    from rsmooth.experiments import render_pose

    calls = _recorded(monkeypatch)
    (keep_best,) = [field for field in cli.cli_fields(render_pose.Config) if _protocol.flag(field) == "--keep-best"]
    last = _protocol.switches(keep_best)[1]
    result = CliRunner().invoke(cli.app, ["render", "pose", "--method", "soft", "--method", "perturbed-gaussian",
                                          "--method", "soft", "--steps", "250", "--samples", "16", last,
                                          "--pose-noise", "0", "--pose-noise-until", "0.75", "--baseline", "leave-one-out",
                                          "--out", str(tmp_path)])
    assert result.exit_code == 0, result.output
    config = calls[-1][1]
    assert _value(config, "--method") == ("soft", "perturbed-gaussian") and _value(config, "--steps") == 250
    assert _value(config, "--samples") == 16 and _value(config, "--keep-best") is False
    assert _value(config, "--pose-noise") == 0.0 and _value(config, "--pose-noise-until") == 0.75
    assert _value(config, "--baseline") == "leave-one-out"
    for bad in (["--method", "blurry"], ["--pose-noise", "-1"], ["--pose-noise-until", "1.5"], ["--sample-growth", "0"],
                ["--init-error", "20", "--init-error", "nan"], ["--init-error", "200"], ["--baseline", "mean"]):
        result = CliRunner().invoke(cli.app, ["render", "pose", *bad, "--out", str(tmp_path)])
        assert result.exit_code == 2 and bad[-2] in result.output, (bad, result.output)
    assert len(calls) == 1


def test_render_reconstruct_options_reach_the_config(monkeypatch, tmp_path):
    calls = _recorded(monkeypatch)
    result = CliRunner().invoke(cli.app, ["render", "reconstruct", "--method", "soft", "--method", "hard", "--steps", "50",
                                          "--samples", "32", "--laplacian-weight", "120", "--out", str(tmp_path)])
    assert result.exit_code == 0, result.output
    config = calls[-1][1]
    assert _value(config, "--method") == ("soft", "hard") and _value(config, "--steps") == 50
    assert _value(config, "--samples") == 32 and _value(config, "--laplacian-weight") == 120.0
    for bad in (["--method", "blurry"], ["--laplacian-weight", "-1"], ["--baseline", "mean"]):
        result = CliRunner().invoke(cli.app, ["render", "reconstruct", *bad, "--out", str(tmp_path)])
        assert result.exit_code == 2 and bad[-2] in result.output, (bad, result.output)
    assert len(calls) == 1


def test_render_pose_rejects_initial_errors_that_are_not_angles(tmp_path):
    import jax

    from rsmooth.experiments import render_pose

    field = next(f.name for f in cli.cli_fields(render_pose.Config) if _protocol.flag(f) == "--init-error")
    for errors in ((float("nan"),), (20.0, 181.0), ()):
        with pytest.raises(ValueError, match=field):
            config = dataclasses.replace(render_pose.Config.quick(), **{field: errors})
            render_pose.run(config, tmp_path, jax.random.key(0), progress=False)
    assert not any(tmp_path.iterdir())


INTERRUPTED_SCRIPT = """
import dataclasses, gc, signal, sys, time
from rsmooth import cli
from rsmooth.experiments import _protocol

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

@dataclasses.dataclass(frozen=True)
class Config:
    @classmethod
    def quick(cls):
        return cls()

run = compiling if sys.argv[1] == "compiling" else collecting
cli.app = cli.build_app([_protocol.Experiment(command=("experiment", "slow"), name="slow", config=Config, run=run,
                                               summary=None, help="Slow.", metrics_doc="")])
sys.argv = ["rsmooth", "experiment", "slow", "--out", "out"]
cli.main()
"""


@pytest.mark.parametrize("during", ["compiling", "collecting"])
def test_ctrl_c_stops_the_command_with_a_message_and_code_130(tmp_path, during):
    # An interrupt during an XLA compilation must not end in a segmentation fault (the
    # interpreter's shutdown destroying the backend under the compiling thread), and one that
    # lands in a garbage-collection callback must not be dropped.
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


def test_a_report_runs_its_float32_experiments_first_and_lists_them_in_order(monkeypatch, tmp_path):
    """rsmooth report / demo in one process: the float32 experiments (rendering) run first, in
    float32, then the float64 ones; precision only ever goes from float32 to float64; the page
    lists the experiments in the order given."""
    import jax

    from rsmooth import report

    ran = []

    def recording(name):
        def run(config, out, key):
            ran.append((name, bool(jax.config.jax_enable_x64)))
            return {"methods": ["ddp", "rddp"], "ddp": {"score": 0.25}, "rddp": {"score": 0.75}}
        return run

    experiments = [_experiment(run=recording(name), name=name, command=("experiment", name), x64=x64)
                   for name, x64 in (("first", True), ("render", False), ("last", True))]
    pages = []
    monkeypatch.setattr(report, "write_page", lambda out, entries, *args, **kwargs: pages.append(entries) or out / "index.html")
    before = bool(jax.config.jax_enable_x64)
    try:
        jax.config.update("jax_enable_x64", False)  # as a fresh process starts
        cli.run_report(experiments, tmp_path, seed=0, quick=True)
    finally:
        jax.config.update("jax_enable_x64", before)
    assert ran == [("render", False), ("first", True), ("last", True)]
    assert [entry.folder for entry in pages[0]] == ["first", "render", "last"]


def test_demo_runs_its_four_experiments_at_their_quick_sizes(monkeypatch, tmp_path):
    seen = []

    def fake_report(experiments, out, seed, quick):
        seen.append(([e.command for e in experiments], out, seed, quick))
        return out / "index.html"

    monkeypatch.setattr(cli, "run_report", fake_report)
    result = CliRunner().invoke(cli.app, ["demo", "--out", str(tmp_path), "--seed", "3"])
    assert result.exit_code == 0, result.output
    assert seen == [(list(cli.DEMO), tmp_path, 3, True)]
    assert set(cli.DEMO) <= set(registry())  # every demo command is an experiment
