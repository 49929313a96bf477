"""The report page (`rsmooth.report`), opened in a real headless Chromium."""

import json
import shutil

import imageio.v3 as iio
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from rsmooth import report  # noqa: E402

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
# The flags a closed network needs: without them Chromium keeps trying Google's hosts.
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
                 "--disable-sync", "--no-first-run", "--disable-quic"]


def open_in_chromium(page_path):
    """Loads the page in headless Chromium: (console messages, failed requests, images as
    (src, complete, natural width), videos as (src, error code or None), the page's text)."""
    assert CHROMIUM is not None, "the report test needs Chromium (Debian: apt-get install chromium; .ci/run installs it)"
    from playwright.sync_api import sync_playwright

    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        try:
            page = browser.new_page()
            messages, failed = [], []
            page.on("console", lambda message: messages.append((message.type, message.text)))
            page.on("pageerror", lambda error: messages.append(("pageerror", str(error))))
            page.on("requestfailed", lambda request: failed.append(request.url))
            page.goto(page_path.as_uri())
            page.wait_for_load_state("load")
            page.evaluate("Promise.all([...document.images].map(i => i.decode().catch(() => null)))")
            images = page.evaluate("[...document.images].map(i => [i.getAttribute('src'), i.complete, i.naturalWidth])")
            videos = page.evaluate("[...document.querySelectorAll('video')].map(v => [v.getAttribute('src'), v.error && v.error.code])")
            text = page.inner_text("body")
        finally:
            browser.close()
    return messages, failed, images, videos, text


def _experiment_folder(root, name):
    folder = root / name
    folder.mkdir()
    fig, ax = plt.subplots(figsize=(2, 2), dpi=40)
    ax.plot([0, 1], [1, 0])
    fig.savefig(folder / "curve.png")
    plt.close(fig)
    frames = np.zeros((3, 16, 16, 3), np.uint8)
    frames[:, 4:12, 4:12] = np.array([0, 128, 255], np.uint8)[:, None, None, None]
    iio.imwrite(folder / "motion.gif", frames, duration=100, loop=0)
    metrics = {"methods": ["ddp", "rddp"], "ddp": {"success_rate": 0.0}, "rddp": {"success_rate": 0.75, "iterations": 12},
               "costs": list(np.linspace(1.0, 0.1, 20))}
    (folder / "metrics.json").write_text(json.dumps(metrics))
    return metrics


def test_page_loads_in_chromium_with_every_image_and_the_metrics(tmp_path):
    metrics = _experiment_folder(tmp_path, "cube lift")  # a space in the folder: the links must be escaped
    entries = [
        report.Entry(title="control cube-lift", folder="cube lift", command="rsmooth control cube-lift --quick",
                     help="Lift a cube <quickly> & well.", settings={"seeds": 2, "method": "all"}, metrics=metrics,
                     wall_time_s=3.2, files=("curve.png", "motion.gif", "metrics.json")),
        report.Entry(title="sim solo12", folder="solo12", command="rsmooth sim solo12 --quick", help="Falls over.",
                     settings={"steps": 3}, error="ValueError: steps must be positive\n  at run()", wall_time_s=0.1),
    ]
    page = report.write_page(tmp_path, entries, report.machine(), profile="quick")
    messages, failed, images, videos, text = open_in_chromium(page)
    assert messages == [] and failed == []
    assert [src for src, *_ in images] == ["cube%20lift/curve.png", "cube%20lift/motion.gif"]
    assert all(complete and width > 0 for _, complete, width in images)
    assert videos == []
    # Every metric shows its value; the failed run shows its error, and the other still renders.
    for key, value in report.flatten(metrics):
        assert f"{key}\t{report.format_value(value)}" in text
    assert "(20 values)" in text
    assert "ValueError: steps must be positive" in text and "sim solo12 (failed" in text
    assert "Lift a cube <quickly> & well." in text  # escaped, shown as written


def test_a_missing_figure_is_caught_by_the_browser_check(tmp_path):
    """The check above could fail: a file the entry lists but the folder lacks is a broken image."""
    (tmp_path / "run").mkdir()
    entry = report.Entry(title="broken", folder="run", command="rsmooth x", help="", settings={}, metrics={"a": 1},
                         files=("gone.png",))
    messages, failed, images, _, _ = open_in_chromium(report.write_page(tmp_path, [entry], {}, profile="quick"))
    assert failed and images == [["run/gone.png", True, 0]]
    assert any("ERR_FILE_NOT_FOUND" in text for _, text in messages)


@pytest.mark.parametrize("value, text", [
    (0.123456, "0.1235"), (float("nan"), "nan"), (True, "True"), (None, "None"), ([1, 2.5], "[1, 2.5]"),
    (list(range(10)), "[0, 1, 2, ..., 8, 9] (10 values)"), ("x", "x"), ({"a": 0.5, "b": [1]}, "{a: 0.5, b: [1]}"),
    ([{"seed": 0}, {"seed": 1}], "2 records (metrics.json)"),
])
def test_format_value(value, text):
    assert report.format_value(value) == text


def test_flatten_keeps_nested_keys_in_order():
    assert report.flatten({"a": {"b": 1, "c": {"d": 2}}, "e": [1], "f": {}}) == [("a.b", 1), ("a.c.d", 2), ("e", [1]), ("f", {})]


def test_report_command_runs_every_experiment_and_shows_a_failure_beside_the_others(tmp_path):
    """`rsmooth report`: each experiment into OUT/NAME, index.html with their figures, metrics
    and commands; an experiment that raises shows its error, and the one after it still runs."""
    import dataclasses

    from typer.testing import CliRunner

    from rsmooth import cli, viz
    from rsmooth.experiments import _protocol

    @dataclasses.dataclass(frozen=True)
    class Config:
        size: int = _protocol.option(3, "Points.", min=1)

        @classmethod
        def quick(cls):
            return cls(size=2)

    def plotting_run(config, out, key):
        fig, ax = viz.plt.subplots(figsize=(2, 2), dpi=40)
        ax.plot(range(config.size))
        viz.save_figure(fig, out / "curve.png")
        metrics = {"size": config.size, "score": 0.5}
        viz.write_metrics(out / "metrics.json", metrics)
        return metrics

    def failing_run(config, out, key):
        raise RuntimeError("the solver diverged")

    def experiment(name, run):
        return _protocol.Experiment(command=("experiment", name), name=name, config=Config, run=run,
                                    summary=lambda metrics: {"score": metrics["score"]}, help=f"The {name} experiment.",
                                    metrics_doc="")

    app = cli.build_app([experiment("first", plotting_run), experiment("broken", failing_run),
                         experiment("last", plotting_run)])
    result = CliRunner().invoke(app, ["report", "--quick", "--out", str(tmp_path / "site")])
    assert result.exit_code == 0, result.output
    site = tmp_path / "site"
    assert sorted(p.name for p in site.iterdir()) == ["broken", "first", "index.html", "last", "rsmooth-files.json"]
    messages, failed, images, _, text = open_in_chromium(site / "index.html")
    assert messages == [] and failed == []
    assert [src for src, *_ in images] == ["first/curve.png", "last/curve.png"]
    assert all(complete and width > 0 for _, complete, width in images)
    assert "RuntimeError: the solver diverged" in text and "experiment broken (failed" in text
    assert f"rsmooth experiment last --quick --seed 0 --out {site / 'last'}" in text
    assert "size\t2" in text and "score\t0.5" in text
    # A second report into the same folder replaces the first (its files are rsmooth's).
    again = CliRunner().invoke(app, ["report", "--quick", "--out", str(site)])
    assert again.exit_code == 0, again.output
    # --only and --skip choose experiments by their folder's name; an unknown name is refused.
    only = CliRunner().invoke(app, ["report", "--quick", "--out", str(tmp_path / "only"), "--only", "last"])
    assert only.exit_code == 0, only.output
    assert sorted(p.name for p in (tmp_path / "only").iterdir()) == ["index.html", "last", "rsmooth-files.json"]
    skip = CliRunner().invoke(app, ["report", "--quick", "--out", str(tmp_path / "skip"), "--skip", "broken"])
    assert skip.exit_code == 0, skip.output
    assert sorted(p.name for p in (tmp_path / "skip").iterdir()) == ["first", "index.html", "last", "rsmooth-files.json"]
    unknown = CliRunner().invoke(app, ["report", "--quick", "--out", str(tmp_path / "x"), "--only", "frist"])
    assert unknown.exit_code == 1 and "--only: unknown experiment 'frist'; one of: first, broken, last" in unknown.output
    none = CliRunner().invoke(app, ["report", "--quick", "--out", str(tmp_path / "y"), "--only", "first", "--skip", "first"])
    assert none.exit_code == 1 and "leave no experiment" in none.output
    assert not (tmp_path / "x").exists() and not (tmp_path / "y").exists()
