"""The results page (`python -m benchmarks render-results`) and the benchmarks' JSON records:
no benchmark runs here and nothing is compiled."""

import json
import math
import pathlib
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:  # `benchmarks` is a folder of the repository, not an installed package
    sys.path.insert(0, str(ROOT))

from benchmarks import _record, experiments, results_page  # noqa: E402

MACHINE = {"cpu": "Test CPU 9000", "cores": 4, "system": "Linux x86_64", "platform": "cpu", "devices": ["cpu: cpu"], "gpu": None,
           "xla_flags": ""}
VERSIONS = {"python": "3.11.0", "jax": "0.1.0", "jaxlib": "0.1.0", "mujoco": "4.0.0", "pin": None, "crocoddyl": None,
            "rsmooth": {"commit": "0123456789abcdef", "modified": False}}


def _record_of(area, results, command, date="2026-01-02"):
    return {"schema": 1, "area": area, "command": command, "date": date, "duration_s": 12.0, "machine": MACHINE,
            "versions": VERSIONS, "options": {}, "results": results}


@pytest.fixture
def records():
    core = _record_of("core", {"dim": 8, "sigma": 0.1, "plain_grad": 1e-6, "rows": [
        {"M": 1, "optax": 2e-5, "smooth_zeroth": 1e-5, "ratio": 999.0, "zeroth_order": 1e-5, "first_order": 1e-5, "alpha_order": None},
        {"M": 16, "optax": 1e-4, "smooth_zeroth": 3e-4, "zeroth_order": 1e-4, "first_order": 1e-4, "alpha_order": 2e-4},
    ]}, "python -m benchmarks core --json DIR")
    sim = _record_of("sim", {"ours_step_batch": 15e-6, "mj_step": 10e-6, "ours_step_jac": 1e-4, "mjd_transitionFD": 6e-4,
                             "notes": ["a note"]}, "python -m benchmarks sim --quick --json DIR")
    control = _record_of("control", {
        "ours": [{"solver": "ddp", "T": 50, "per_iteration": 0.02, "timed": 7, "foot_height": 0.05},
                 {"solver": "rddp32", "T": 50, "per_iteration": 0.1, "timed": 7}],
        "crocoddyl": [], "crocoddyl_status": "Crocoddyl skipped: cannot import it",
        "settings": {"horizons": [50], "samples": [32], "iterations": 8},
    }, "python -m benchmarks control --json DIR")
    pose = {"methods": ["perturbed-gaussian"], "problems": 4, "mesh": "cube", "success_deg": 5,
            "perturbed-gaussian": {"20": {"solved_pct": 75.0, "median_error_deg": 1.25}, "80": {"solved_pct": 25.0, "median_error_deg": 30.0}}}
    exps = _record_of("experiments", {"profile": "quick", "experiments": {
        "render-pose": {"metrics": pose, "date": "2026-01-01"},
        "solo-lift": {"metrics": {"methods": ["rddp"], "seeds": [0, 1],
                                  "rddp": {"success_rate": 0.5, "per_seed": [{"foot_height": 0.05}, {"foot_height": 0.01}]}},
                      "date": "2026-01-01"},
        "estimators": None,
        "stiffness": {"metrics": {
            "stiffnesses": [10.0], "sigma": 0.1, "num_samples": 8, "repeats": 4,
            "k=10": {"contact_width": 0.99, "first": {"per_sample_variance": {"mean": 0.5}, "rmse": 0.1},
                     "zeroth": {"per_sample_variance": {"mean": 2.0}, "rmse": 0.3},
                     "alpha": {"per_sample_variance": {"mean": 1.0}, "rmse": 0.2, "mean_alpha": 0.6},
                     "alpha-cross-fit": {"per_sample_variance": {"mean": 1.5}, "rmse": 0.25, "mean_alpha": 0.5}},
            "policy": {"seeds": 4, "iterations": 60, "num_samples": 8,
                       "k=10": {"first": {"gap_mean": 0.002, "gap_std": 0.002}, "zeroth": {"gap_mean": 0.01, "gap_std": 0.004},
                                "alpha": {"gap_mean": 0.004, "gap_std": 0.002}, "best": "first"}}}, "date": "2026-01-01"},
    }}, "python -m benchmarks experiments --metrics rsmooth-out --profile quick --json DIR")
    return {"cpu": {"core": core, "sim": sim, "control": control, "experiments": exps}, "gpu": {}}


def _lines_with(page, *words):
    return [line for line in page.splitlines() if all(w in line for w in words)]


def test_page_states_how_it_is_generated(records):
    page = results_page.render(records)
    first = page.splitlines()[0]
    assert "Generated" in first and "python -m benchmarks render-results" in first
    assert "session" not in page.lower()


def test_core_ratios_are_computed_from_the_times(records):
    page = results_page.render(records)
    (m1,) = _lines_with(page, "| 1 |", "us")
    assert "| 0.50 |" in m1 and "met" in m1 and "not met" not in m1  # 1e-5 / 2e-5, not the recorded 999
    (m16,) = _lines_with(page, "| 16 |", "us")
    assert "| 3.00 |" in m16 and "not met" in m16
    assert "(M < 4)" in m1
    assert "3.00 (not met)" in page  # the summary


def test_sim_ratios_and_missing_references(records):
    page = results_page.render(records)
    (step,) = _lines_with(page, "| step, vmap 64, per env |", "`mj_step`")
    assert "rsmooth / MuJoCo = 1.50" in step and "≤ 2: met" in step
    (jac,) = _lines_with(page, "| `step_and_jacobians`, batch 1 |")
    assert "MuJoCo / rsmooth = 6.00" in jac and "≥ 5: met" in jac
    mjx = _lines_with(page, "MJX `jit(step)`")
    assert mjx and "not measured" in mjx[0]
    assert "- a note" in page


def test_machine_command_and_date_are_shown(records):
    page = results_page.render(records)
    assert "Command: `python -m benchmarks core --json DIR`" in page
    assert "Test CPU 9000, 4 cores; date 2026-01-02" in page
    assert "jax 0.1.0, jaxlib 0.1.0, mujoco 4.0.0" in page
    assert "0123456789" not in page  # the commit stays in the record


def test_missing_areas_are_not_measured(records):
    page = results_page.render(records)
    render_section = page.split("### render:")[1].split("###")[0]
    assert "Not measured: no record" in render_section
    assert "python -m benchmarks render --json benchmarks/results/cpu" in render_section
    gpu = page.split("## GPU")[1].split("## Experiments")[0]
    assert "No GPU results are recorded yet" in gpu and "bash benchmarks/gpu.sh" in gpu


def test_control_without_crocoddyl(records):
    page = results_page.render(records)
    assert "Crocoddyl: not measured (Crocoddyl skipped: cannot import it)." in page
    (fddp,) = _lines_with(page, "| our DDP / Crocoddyl FDDP, T = 50 |")
    assert "not measured" in fddp
    (rddp,) = _lines_with(page, "| R-DDP M = 32 / our DDP, T = 50 |")
    assert "5.00" in rddp and "≤ 4: not met" in rddp
    assert "foot +5.0 cm" in page


def test_startup_goals_and_compile_share(records):
    lift = {"cold": {"wall_s": 20.0, "trace_s": 3.0, "lower_s": 1.0, "compile_s": 15.0, "cache_read_s": 0.0, "iterations_s": 0.5},
            "warm": {"wall_s": 6.5, "trace_s": 3.0, "lower_s": 1.0, "compile_s": 0.2, "cache_read_s": 0.5, "iterations_s": 0.5}}
    records["cpu"]["startup"] = _record_of("startup", {"repeats": 3, "cases": {
        "solo12-ddp-lift": {"command": "python: the lift", **lift}}}, "python -m benchmarks startup --json DIR")
    page = results_page.render(records)
    (cold,) = _lines_with(page, "| startup: Solo-12 DDP lift, fresh process to answer, cold cache |")
    assert "| < 5.00 s | 20.0 s (not met) |" in cold
    (warm,) = _lines_with(page, "| startup: the same, warm cache, beyond the iterations |")
    assert "| 6.00 s (not met) |" in warm  # 6.5 s wall - 0.5 s of iterations
    (demo,) = _lines_with(page, "| startup: `rsmooth demo`, warm cache |")
    assert "not measured" in demo
    (row,) = _lines_with(page, "| `python: the lift` | cold |")
    assert "| 75% |" in row  # 15 s of 20 s compiling


def test_throughput_ratios_come_from_the_times(records):
    rows = [{"batch": 1000, "ours": {"step_s": 2e-3, "step_jac_s": 5e-3, "unconverged": 0}, "mjx": {"step_s": 8e-3},
             "ours_over_mjx": 999.0, "jacobian_over_step": 999.0},
            {"batch": 4000, "ours": {"step_s": 4e-3, "step_jac_s": 16e-3, "unconverged": 2}, "mjx": None}]
    records["gpu"]["throughput"] = _record_of("throughput", {"dtype": "float64", "rows": rows, "notes": ["MJX unavailable: x"]},
                                              "python -m benchmarks.throughput --json DIR")
    page = results_page.render(records)
    (small,) = _lines_with(page, "| 1,000 |")
    assert "| 500,000 |" in small and "| 125,000 |" in small  # steps per second from the times
    assert "| 2.50 | ≤ 3: met |" in small and "| 4.00 | ≥ 1: met |" in small  # not the recorded 999
    (large,) = _lines_with(page, "| 4,000 |")
    assert "| 4.00 | ≤ 3: not met |" in large and "| 2 |" in large and "not measured" in large
    (summary,) = _lines_with(page, "| throughput: Solo-12 steps per second, rsmooth / MJX")
    assert summary.endswith("| not measured | not measured |")  # the largest batch has no MJX time
    (jacobians,) = _lines_with(page, "| throughput: `step_and_jacobians` / step")
    assert jacobians.endswith("| not measured | 4.00 (not met) |")
    assert "- MJX unavailable: x" in page


def test_boxes_ratios_come_from_the_times(records):
    case = {"pairs": 3, "candidates": 16, "max_pairs": 2, "ours_step_batch": 30e-6, "mj_step": 10e-6, "ratio": 999.0,
            "ours_compile_s": 5.0, "ours_height_error": 0.0, "mujoco_height_error": 2e-3, "mjx_step_batch": None,
            "mjx_ratio": None, "ours_stages": {"collision": 5e-6, "free_motion": 1e-6, "solve_contacts": 20e-6,
                                               "jacobian_rows": 48, "solved_rows": 48}}
    records["cpu"]["boxes"] = _record_of("boxes", {"batch": 64, "cold_start": True, "sizes": [2], "cases": {"2": case},
                                                   "growth": {}, "notes": ["MJX unavailable: x"]}, "python -m benchmarks boxes")
    page = results_page.render(records)
    assert "Every timed step starts its contact solve cold" in page
    assert "MJX per env" not in page  # no MJX time: no MJX columns
    step, stages = _lines_with(page, "| 2 |")
    assert "| 30.0 us | 10.0 us | 3.00 |" in step and "0.000 / 2.000 mm" in step  # not the recorded 999
    assert "| 20.0 us |" in stages and "48 / 48" in stages
    (summary,) = _lines_with(page, "| sim: box tower step per env")
    assert "3.00" in summary and "999" not in summary
    assert "- MJX unavailable: x" in page


def test_schedules_table(records):
    runs = {"decrease-only": {"command": "rsmooth control solo-lift --method rddp", "success_pct": 60.0, "wall_s": 1.0},
            "reheating": {"command": "rsmooth control solo-lift --method rddp-reheating", "success_pct": None, "wall_s": 1.0,
                          "error": "boom"}}
    records["cpu"]["schedules"] = _record_of("schedules", {"quick": False, "comparisons": {
        "solo": {"task": "Solo-12 lifts HR", "metric": "runs (%)", "runs": runs}}}, "python -m benchmarks schedules")
    page = results_page.render(records)
    (row,) = _lines_with(page, "| Solo-12 lifts HR |")
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[1:4] == ["runs (%)", "60 %", "not measured"]
    assert "`rsmooth control solo-lift --method rddp-reheating`" in row


def test_experiments_tables(records):
    page = results_page.render(records)
    exp = page.split("## Experiments")[1]
    assert "Profile: **quick**" in exp
    (ours,) = _lines_with(exp, "| perturbed-gaussian |")
    cells = [c.strip() for c in ours.strip("|").split("|")]
    assert cells[1:4] == ["75 % (median error 1.2 deg)", "not measured", "25 % (median error 30.0 deg)"]  # 50 deg was not run
    (paper,) = _lines_with(exp, "Le Lidec et al. 2021, perturbed renderer")
    assert "93 %" in paper and "84 %" in paper and "67 %" in paper
    assert "+5.0, +1.0" in exp  # the foot heights over seeds, cm
    estimators = exp.split("#### estimators")[1].split("####")[0]
    assert "Not measured." in estimators
    policy = exp.split("#### policy:")[1].split("####")[0]
    assert "Not measured." in policy
    (stiffness,) = _lines_with(exp, "| 10 |")
    cells = [c.strip() for c in stiffness.strip("|").split("|")]
    # per-sample variances, RMSEs, alpha, the push task's gaps (mean ± s.e. over 4 seeds), the best
    assert cells[2:] == ["0.5 / 2 / 1 / 1.5", "0.1 / 0.3 / 0.2 / 0.25", "0.60 / 0.50",
                         "0.002 ± 0.001 / 0.01 ± 0.002 / 0.004 ± 0.001 / not measured", "first"]
    chaos = exp.split("#### chaos:")[1].split("####")[0]
    assert "Not measured." in chaos


def test_committed_page_matches_the_committed_records():
    page = results_page.render(results_page.load(results_page.RESULTS))
    assert results_page.PAGE.read_text() == page, "run `python -m benchmarks render-results`"


def test_committed_records_have_the_required_keys():
    paths = sorted(results_page.RESULTS.glob("*/*.json"))
    for path in paths:
        record = json.loads(path.read_text())
        assert set(_record.REQUIRED_KEYS) <= set(record), path
        assert path.parent.name in results_page.KINDS and record["area"] == path.stem


def test_writer_record_has_the_required_keys(tmp_path):
    def measure(repeats):
        return {"rows": [{"M": 1, "seconds": 0.5 * repeats, "missing": math.nan}], "pair": (1, 2), "note": f"failed in {ROOT}/x.py"}

    record = _record.run_and_record("demo", measure, command="python -m benchmarks demo", options={"repeats": 2}, directory=tmp_path)
    written = json.loads((tmp_path / "demo.json").read_text())
    assert written == record
    assert set(_record.REQUIRED_KEYS) <= set(written)
    assert written["area"] == "demo" and written["command"] == "python -m benchmarks demo"
    assert written["results"] == {"rows": [{"M": 1, "seconds": 1.0, "missing": None}], "pair": [1, 2], "note": "failed in x.py"}
    assert written["options"] == {"repeats": 2}
    assert written["machine"]["cpu"] and written["machine"]["cores"] >= 1
    assert {"jax", "jaxlib", "mujoco", "pin", "crocoddyl", "python"} <= set(written["versions"])
    assert set(written["versions"]["rsmooth"]) == {"commit", "modified"}
    assert len(written["date"]) == 10 and written["duration_s"] >= 0


def test_command_line_names_the_module_and_relative_paths():
    main = str(ROOT / "benchmarks" / "__main__.py")
    assert _record.command_line([main, "sim", "--json", str(ROOT / "benchmarks/results/cpu")]) == (
        "python -m benchmarks sim --json benchmarks/results/cpu"
    )
    assert _record.command_line([str(ROOT / "benchmarks" / "control.py"), "--quick"]) == "python -m benchmarks.control --quick"
    assert _record.command_line([main, "core", "--json", "/somewhere/else/results"]) == "python -m benchmarks core --json .../results"


def test_experiments_collects_metrics_and_marks_the_missing(tmp_path):
    (tmp_path / "render-pose").mkdir()
    curve = list(range(experiments.LONGEST_LIST + 1))  # a landscape: left out of the record
    (tmp_path / "render-pose" / "metrics.json").write_text(json.dumps({"soft": {"20": {"solved_pct": 50.0}, "curve": curve}}))
    record = experiments.main(str(tmp_path), str(tmp_path / "out"), "quick")
    written = json.loads((tmp_path / "out" / "experiments.json").read_text())
    assert written == record and written["area"] == "experiments"
    found = written["results"]["experiments"]
    assert written["results"]["profile"] == "quick"
    assert set(found) == set(experiments.EXPERIMENTS)
    assert found["render-pose"]["metrics"] == {"soft": {"20": {"solved_pct": 50.0}}}
    assert all(found[name] is None for name in experiments.EXPERIMENTS if name != "render-pose")


def test_experiments_keeps_missing_entries_with_their_own_profile_and_machine(tmp_path):
    """An experiment measured at its default size beside one kept from a quick record of
    another machine: the page names the kept one's profile and machine under its heading."""
    for name, profile in (("render-pose", "quick"), ("policy", "default")):
        (tmp_path / profile / name).mkdir(parents=True)
        (tmp_path / profile / name / "metrics.json").write_text(json.dumps({"seeds": 1}))
    out = tmp_path / "out"
    experiments.main(str(tmp_path / "quick"), str(out), "quick")
    old = json.loads((out / "experiments.json").read_text())
    old["machine"] = {**old["machine"], "cpu": "Another CPU"}
    (out / "experiments.json").write_text(json.dumps(old))
    without = experiments.main(str(tmp_path / "default"), str(tmp_path / "elsewhere"), "default", keep_missing=True)
    assert without["results"]["experiments"]["render-pose"] is None  # nothing to keep there
    record = experiments.main(str(tmp_path / "default"), str(out), "default", keep_missing=True)
    found = record["results"]["experiments"]
    assert found["policy"]["profile"] == "default" and "machine" not in found["policy"]
    assert found["render-pose"]["profile"] == "quick" and found["render-pose"]["machine"]["cpu"] == "Another CPU"
    assert found["render-pose"]["metrics"] == {"seeds": 1}
    lines = results_page.experiments_section(record, "cpu")
    pose = lines[lines.index("#### render-pose: " + results_page.EXPERIMENT_SECTIONS["render-pose"][0]) + 2]
    policy = lines[lines.index("#### policy: " + results_page.EXPERIMENT_SECTIONS["policy"][0]) + 2]
    assert "profile **quick**" in pose and "on Another CPU" in pose
    assert policy.startswith("Run ") and "profile" not in policy and " on " not in policy


def test_docstring_examples():
    import doctest

    assert doctest.testmod(results_page).failed == 0
