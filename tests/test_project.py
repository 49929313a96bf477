"""The project's promises to a newcomer: README commands, CI script, command line."""

import json
import re
import subprocess
import sys
from pathlib import Path

from typer.testing import CliRunner

from rsmooth.cli import app

ROOT = Path(__file__).resolve().parents[1]


def readme_commands():
    return re.findall(r"```bash\n(.+?)\n```", (ROOT / "README.md").read_text())


def test_readme_opens_with_demo_and_test_commands_and_ci_runs_the_latter():
    demo, tests = readme_commands()[:2]
    assert demo.endswith("rsmooth demo")
    assert "pytest" in tests
    ci_lines = [line.strip() for line in (ROOT / ".ci/run").read_text().splitlines()]
    assert tests in ci_lines


def test_cli_help_lists_the_experiments():
    result = CliRunner().invoke(app, ["experiment", "--help"])
    assert result.exit_code == 0
    for name in ("estimators", "perturbed-argmax", "null-gradients"):
        assert name in result.output
    assert CliRunner().invoke(app, ["render", "pose", "--help"]).exit_code == 0
    reconstruct = CliRunner().invoke(app, ["render", "reconstruct", "--help"])
    assert reconstruct.exit_code == 0 and "iou_3d" in reconstruct.output
    control = CliRunner().invoke(app, ["control", "--help"])
    assert control.exit_code == 0
    for name in ("cube-lift", "solo-lift", "pusher", "policy"):
        assert name in control.output


def test_cli_sim_solo12_writes_metrics_and_animation(tmp_path):
    # As a user runs it, in a fresh process: in a pytest-xdist worker loaded with the suite's
    # earlier programs, XLA:CPU (jaxlib 0.10.2) once crashed compiling this command's programs.
    command = [sys.executable, "-m", "rsmooth.cli", "sim", "solo12", "--quick", "--steps", "5", "--frames", "2", "--out", str(tmp_path)]
    done = subprocess.run(command, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout + done.stderr
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["steps"] == 5 and metrics["base_drift"] < 1e-6 and metrics["max_foot_slip"] < 1e-6
    assert metrics["base_height_drift"] <= metrics["base_drift"] and metrics["ncp_converged_fraction"] == 1.0
    assert (tmp_path / "solo12.gif").stat().st_size > 0 and (tmp_path / "solo12.png").stat().st_size > 0
    bad = CliRunner().invoke(app, ["sim", "solo12", "--torques", "wild", "--out", str(tmp_path)])
    assert bad.exit_code != 0 and "--torques" in bad.output


def test_cli_perturbed_argmax_quick_writes_metrics_and_figures(tmp_path):
    result = CliRunner().invoke(app, ["experiment", "perturbed-argmax", "--quick", "--out", str(tmp_path), "--seed", "3"])
    assert result.exit_code == 0, result.output
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["softmax_max_abs_error"] < 0.05
    assert metrics["ranking_test_spearman_final"] > 0.9 > metrics["ranking_test_spearman_initial"]
    assert (tmp_path / "softmax.png").stat().st_size > 0 and (tmp_path / "ranking.png").stat().st_size > 0
    assert not list(tmp_path.glob(".*"))  # no temporary file left behind


def test_importing_rsmooth_starts_no_jax_backend():
    # A library must leave JAX's start-up to its user: XLA_FLAGS (host device count, CPU
    # flags), jax_platforms and the CPU affinity are read when the backend starts, so a module
    # that makes a JAX array at import (a default argument that checks its value with jnp,
    # as PolicyGradient() did) fixes them too early. Checked in a fresh interpreter.
    import subprocess
    import sys

    script = (
        "import importlib, pkgutil\n"
        "from jax._src import xla_bridge\n"
        "import rsmooth\n"
        "names = [m.name for m in pkgutil.walk_packages(rsmooth.__path__, prefix='rsmooth.')]\n"
        "started = []\n"
        "for name in names:\n"
        "    importlib.import_module(name)\n"
        "    if xla_bridge._backends:\n"
        "        started.append(name)\n"
        "        break\n"
        "print(len(names), started)\n"
    )
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert result.returncode == 0, result.stderr
    count, started = result.stdout.strip().split(" ", 1)
    assert int(count) >= 40 and started == "[]", result.stdout  # every module, experiments included


def test_readme_lists_every_command_once():
    """One line per command in the README's table: a command added to the registry must be added there."""
    from rsmooth.experiments import registry

    text = (ROOT / "README.md").read_text()
    for experiment in registry().values():
        assert text.count(f"| `rsmooth {experiment.title}` |") == 1, experiment.title
