"""The `rsmooth` command: one sub-command per experiment.

Every experiment takes `--out DIR` (default `./rsmooth-out/NAME`), `--seed N` and `--quick`
(a reduced size that finishes in a couple of minutes on 2 CPU cores), shows a progress bar,
and writes `DIR/metrics.json` beside its figures. `DIR/rsmooth-files.json` lists the files a
run wrote: a run into the folder of an earlier one first removes those (and no other file), and
a non-empty folder that no run wrote into is refused. Errors of the operating system (a folder
that cannot be written) end the command with a one-line message and exit code 1; Ctrl-C ends
it with exit code 130.
"""

from __future__ import annotations

import dataclasses
import gc
import importlib
import math
import os
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Callable, Optional

import typer

from rsmooth import _files

app = typer.Typer(
    help="rsmooth: randomized smoothing for optimizing non-smooth physical processes (JAX).",
    no_args_is_help=True,
    add_completion=False,
)
experiment_app = typer.Typer(help="Experiments on the smoothing core and on contact.", no_args_is_help=True)
app.add_typer(experiment_app, name="experiment")
sim_app = typer.Typer(help="Simulation with hard frictional contact.", no_args_is_help=True)
app.add_typer(sim_app, name="sim")
render_app = typer.Typer(help="Differentiable perturbed rendering tasks.", no_args_is_help=True)
app.add_typer(render_app, name="render")
control_app = typer.Typer(help="Optimal control through contact: DDP, randomized DDP, and policy gradients (first, zeroth, alpha order).", no_args_is_help=True)
app.add_typer(control_app, name="control")

DEFAULT_ROOT = Path("rsmooth-out")

OutOption = typer.Option(None, "--out", help="Output folder (default ./rsmooth-out/NAME).")
SeedOption = typer.Option(0, "--seed", help="Seed of the jax.random key.")
QuickOption = typer.Option(False, "--quick", help="Reduced size: about two minutes on 2 CPU cores.")


def _fail(message: str) -> None:
    """Ends the command with a one-line error on stderr and exit code 1."""
    typer.echo(f"rsmooth: error: {message}", err=True)
    raise typer.Exit(1)


def _os_error_message(error: OSError) -> str:
    """``strerror: filename`` (e.g. ``Permission denied: out/metrics.json``), else the error's text."""
    if error.strerror and error.filename is not None:
        return f"{error.strerror}: {os.fsdecode(error.filename)}"
    return str(error) or type(error).__name__


def _prepare(name: str, out: Optional[Path], seed: int, x64: bool = True):
    """The output folder, made ready (:func:`rsmooth._files.prepare_output_folder`: the files of
    the previous run into it removed), and the key of `seed`."""
    import jax

    # One experiment per process: its precision is set once, before any array exists.
    jax.config.update("jax_enable_x64", x64)
    out = Path(out) if out is not None else DEFAULT_ROOT / name
    return _files.prepare_output_folder(out), jax.random.key(seed)


def _report(name: str, out: Path, start: float, summary: dict) -> None:
    typer.echo(f"{name}: done in {time.perf_counter() - start:.1f} s, artifacts in {out}/")
    for key, value in summary.items():
        typer.echo(f"  {key}: {value}")


@dataclasses.dataclass(frozen=True)
class _Experiment:
    """How the command line runs one experiment module and prints its summary."""

    name: str  # the output sub-folder: ./rsmooth-out/NAME
    module: str  # rsmooth.experiments.MODULE: Config, Config.quick() and run(config, out, key)
    title: str  # names the run in the printed summary
    summary: Callable[[dict], dict]  # metrics -> the lines printed after the run
    # float64 (contact solves and DDP need it); rendering runs in float32, which halves its
    # time on CPU and is what GPUs are fast at (measured: `python -m benchmarks render`)
    x64: bool = True


def _run(
    experiment: _Experiment, out: Optional[Path], seed: int, quick: bool, root: Optional[Path] = None,
    title: Optional[str] = None, **overrides,
) -> dict:
    """Runs an experiment at its default or quick size, the ``overrides`` that are not None
    replacing fields of its Config, and prints its summary; returns its metrics."""
    module = importlib.import_module(f"rsmooth.experiments.{experiment.module}")
    start = time.perf_counter()
    # `rsmooth demo` runs several experiments in one process: it keeps float64 throughout
    # rather than switching the precision under arrays that already exist.
    x64 = experiment.x64 or root is not None
    try:
        out, key = _prepare(experiment.name, out if root is None else root / experiment.name, seed, x64)
        config = module.Config.quick() if quick else module.Config()
        changes = {name: value for name, value in overrides.items() if value is not None}
        if changes:
            config = dataclasses.replace(config, **changes)
        with _files.recording_outputs(out):
            metrics = module.run(config, out, key)
    except _files.OutputFolderError as error:
        _fail(str(error))
    except OSError as error:  # a folder or file that cannot be written: permission denied, disk full...
        _fail(_os_error_message(error))
    _report(title or experiment.title, out, start, experiment.summary(metrics))
    return metrics


_ESTIMATORS = _Experiment("estimators", "estimators", "estimators", lambda metrics: {
    "first-order gradient of the Heaviside (max |.|)": metrics["heaviside_first_order_grad_max_abs"],
    "Heaviside: max |mean gradient - truth| (first, zeroth, alpha)": ", ".join(
        f"{metrics[f'heaviside_{e}_max_abs_error']:.3f}" for e in ("first", "zeroth", "alpha")
    ),
})

_PERTURBED_ARGMAX = _Experiment("perturbed-argmax", "perturbed_argmax", "perturbed-argmax", lambda metrics: {
    "max |perturbed argmax - softmax|": round(metrics["softmax_max_abs_error"], 4),
    "held-out Spearman correlation, before -> after": (
        f"{metrics['ranking_test_spearman_initial']:.3f} -> {metrics['ranking_test_spearman_final']:.3f}"
    ),
})

_NULL_GRADIENTS = _Experiment("null-gradients", "null_gradients", "null-gradients", lambda metrics: {
    "exact gradient below m g (max |.|)": metrics["exact_gradient_max_abs_below_weight"],
    "smoothed gradients, max |mean - closed form| (first, zeroth) per sigma": "; ".join(
        f"sigma={s:g}: {metrics[f'sigma={s:g}']['first_order_max_abs_error']:.1e}, "
        f"{metrics[f'sigma={s:g}']['zeroth_order_max_abs_error']:.1e}"
        for s in metrics["sigmas"]
    ),
})

_SOLO12 = _Experiment("solo12", "solo12_sim", "sim solo12", lambda metrics: {
    "base drift (m)": f"{metrics['base_drift']:.2e} (height {metrics['base_height_drift']:.2e})",
    "max foot slip (m)": f"{metrics['max_foot_slip']:.2e}",
    "contact solves converged": f"{100 * metrics['ncp_converged_fraction']:.1f} %",
    "diverged steps": metrics["diverged_steps"],
})


def _render_pose_summary(metrics: dict) -> dict:
    errors = ", ".join(f"{e:g}" for e in metrics["init_errors_deg"])
    if not metrics["restarts"]:
        return {
            f"{method}: solved % from {errors} deg": ", ".join(
                f"{metrics[method][f'{e:g}']['solved_pct']:.0f}" for e in metrics["init_errors_deg"]
            )
            for method in metrics["methods"]
        }
    return {
        f"{method}: solved % from {errors} deg (first run; runs per problem)": ", ".join(
            "{solved_pct:.0f} ({first_run_solved_pct:.0f}; {runs_per_problem:.2f})".format(**metrics[method][f"{e:g}"])
            for e in metrics["init_errors_deg"]
        )
        for method in metrics["methods"]
    }


_RENDER_POSE = _Experiment("render-pose", "render_pose", "render pose", _render_pose_summary, x64=False)

_RENDER_RECONSTRUCT = _Experiment("render-reconstruct", "render_reconstruct", "render reconstruct", lambda metrics: {
    f"{method}: 3D IoU / Chamfer ({', '.join(metrics['targets'])})": ", ".join(
        f"{metrics[method][t]['iou_3d']:.2f} / {metrics[method][t]['chamfer']:.4f}" for t in metrics["targets"]
    )
    for method in metrics["methods"]
}, x64=False)


def _control_summary(columns: str, row: Callable[[dict], str]) -> Callable[[dict], dict]:
    """A control experiment's summary: per method, its success rate then ``row(its metrics)``."""
    return lambda metrics: {
        f"{name}: success rate, {columns}": f"{100 * metrics[name]['success_rate']:.0f} %, {row(metrics[name])}"
        for name in metrics["methods"]
    }


_CUBE_LIFT = _Experiment("cube-lift", "control_cube_lift", "control cube-lift", _control_summary(
    "final height (mm), iterations", lambda metrics: f"{1000 * metrics['final_height']:.1f}, {metrics['iterations']}"))

_SOLO_LIFT = _Experiment("solo-lift", "control_solo_lift", "control solo-lift", _control_summary(
    "foot height (mm), other feet max height (mm), iterations",
    lambda metrics: f"{1000 * metrics['foot_height']:.1f}, {1000 * metrics['other_feet_max_height']:.1f}, {metrics['iterations']}"))

_PUSHER = _Experiment("pusher", "control_pusher", "control pusher", _control_summary(
    "position error (mm), yaw error (deg), iterations",
    lambda metrics: f"{1000 * metrics['position_error']:.1f}, {metrics['yaw_error_deg']:.1f}, {metrics['iterations']}"))

_POLICY = _Experiment("policy", "control_policy", "control policy", _control_summary(
    "final cost mean +- std (m), final angle (deg), mean alpha, median gradient variance",
    lambda metrics: f"{metrics['final_cost_mean']:.3f} +- {metrics['final_cost_std']:.3f}, "
    f"{metrics['final_angle_deg_mean']:.1f}, {metrics['mean_alpha']:.2f}, {metrics['gradient_variance_median']:.2g}"))

_POLICY_PUSHER = _Experiment("policy-pusher", "control_policy_pusher", "control policy --task pusher", _control_summary(
    "runs that pushed the box, final cost mean +- std, position error (mm), mean alpha, median gradient variance",
    lambda metrics: f"{100 * metrics['push_rate']:.0f} %, {metrics['final_cost_mean']:.3f} +- {metrics['final_cost_std']:.3f}, "
    f"{1000 * metrics['position_error_mean']:.1f}, {metrics['mean_alpha']:.2f}, {metrics['gradient_variance_median']:.2g}"))

POLICY_TASKS = {"throw": _POLICY, "pusher": _POLICY_PUSHER}


def _doc(summary: str, *experiments: _Experiment) -> str:
    # The METRICS_DOC strings are wrapped for the source; Typer keeps single newlines, which
    # then wrap again at the terminal's width into ragged lines: one line per paragraph.
    docs = [importlib.import_module(f"rsmooth.experiments.{experiment.module}").METRICS_DOC for experiment in experiments]
    return "\n\n".join(" ".join(paragraph.split()) for doc in [summary, *docs] for paragraph in doc.split("\n\n"))


@experiment_app.command("estimators", help=_doc(
    "Zeroth-, first- and alpha-order gradient estimates on the Heaviside, |x|, a stiff sigmoid "
    "and Coulomb friction: means, spread and error against the number of samples.", _ESTIMATORS))
def experiment_estimators(out: Optional[Path] = OutOption, seed: int = SeedOption, quick: bool = QuickOption):
    _run(_ESTIMATORS, out, seed, quick)


@experiment_app.command("perturbed-argmax", help=_doc(
    "Gumbel-perturbed argmax against the softmax, and learning to rank with the perturbed "
    "Fenchel-Young loss.", _PERTURBED_ARGMAX))
def experiment_perturbed_argmax(out: Optional[Path] = OutOption, seed: int = SeedOption, quick: bool = QuickOption):
    _run(_PERTURBED_ARGMAX, out, seed, quick)


@experiment_app.command("null-gradients", help=_doc(
    "A cube resting on the floor under an upward force: the exact gradient of its final height "
    "is zero below m g; first- and zeroth-order smoothed gradients against their closed form.",
    _NULL_GRADIENTS))
def experiment_null_gradients(out: Optional[Path] = OutOption, seed: int = SeedOption, quick: bool = QuickOption):
    _run(_NULL_GRADIENTS, out, seed, quick)


@sim_app.command("solo12", help=_doc(
    "Simulate Solo-12 on the floor under standing (gravity-compensating) or random torques and "
    "write a stick-figure animation.", _SOLO12))
def sim_solo12(
    out: Optional[Path] = OutOption,
    seed: int = SeedOption,
    quick: bool = QuickOption,
    torques: str = typer.Option("standing", "--torques", help="standing or random."),
    steps: Optional[int] = typer.Option(None, "--steps", min=1, help="Time steps of 10 ms (default 200, quick 100)."),
    random_scale: Optional[float] = typer.Option(
        None, "--random-scale", min=0.0, help="Amplitude of the random torques, N m (default 0.1)."),
    open_loop: bool = typer.Option(
        False, "--open-loop", help="No posture PD under random torques: the robot falls (default: PD on)."),
    body_contacts: bool = typer.Option(
        True, "--body-contacts/--feet-only", help="Whether the base and knees collide with the floor too."),
):
    if torques not in ("standing", "random"):
        raise typer.BadParameter(f"--torques must be 'standing' or 'random', got {torques!r}")
    gains = dict(stiffness=0.0, damping=0.0) if open_loop else {}
    _run(_SOLO12, out, seed, quick, torques=torques, steps=steps, random_scale=random_scale,
         body_contacts=body_contacts, **gains)


def _methods(method: Optional[list[str]], known: tuple[str, ...]) -> Optional[tuple[str, ...]]:
    """The --method values, in the given order, once each (None: the experiment's default)."""
    unknown = [m for m in method or () if m not in known]
    if unknown:
        raise typer.BadParameter(f"--method must be one of {', '.join(known)}, got {', '.join(unknown)}")
    return tuple(dict.fromkeys(method)) if method else None


BaselineOption = typer.Option(
    None, "--baseline", help="The perturbed estimator's baseline: 'hard' (the hard pixel, the paper's; default) or "
    "'leave-one-out' (the mean of the pixel's other samples: lower variance at edges).")


def _baseline(baseline: Optional[str]) -> bool | str | None:
    """The --baseline value as the renderers take it (None: the experiment's default)."""
    if baseline not in (None, "hard", "leave-one-out"):
        raise typer.BadParameter(f"--baseline must be 'hard' or 'leave-one-out', got {baseline!r}")
    return None if baseline is None else (True if baseline == "hard" else baseline)


@render_app.command("pose", help=_doc(
    "Recover a mesh's rotation from one RGB image with the perturbed renderer (Gaussian or Cauchy "
    "noise, adaptive noise decrease), a SoftRas-like one and the hard z-buffer.", _RENDER_POSE))
def render_pose_command(
    out: Optional[Path] = OutOption,
    seed: int = SeedOption,
    quick: bool = QuickOption,
    mesh: str = typer.Option("cube", "--mesh", help="cube, icosphere, torus, or a mesh file (OBJ, STL, PLY, DAE)."),
    init_error: Optional[list[float]] = typer.Option(
        None, "--init-error", help="Initial rotation error in degrees (repeatable; default 20, 50, 80)."),
    problems: Optional[int] = typer.Option(None, "--problems", min=1, help="Problems per initial error (default 100, quick 4)."),
    method: Optional[list[str]] = typer.Option(
        None, "--method", help="perturbed-gaussian, perturbed-cauchy, soft or hard (repeatable; default all four)."),
    steps: Optional[int] = typer.Option(None, "--steps", min=1, help="Adam steps per problem (default 200, quick 60)."),
    samples: Optional[int] = typer.Option(
        None, "--samples", min=1, help="Monte-Carlo samples per pixel of the perturbed renderers (default 16, quick 8; 8 / "
        "16 / 32 solved 59 / 73 / 83 % of the cubes from 80 deg: see benchmarks/RESULTS.md)."),
    sample_growth: Optional[int] = typer.Option(
        None, "--sample-growth", min=1, help="Multiply the perturbed renderers' samples per pixel by this at each noise "
        "decrease (the step averages that many renders), up to --max-samples (default 2; 1: off, ~2x faster "
        "per run, less precise: see benchmarks/RESULTS.md; quick 1)."),
    max_samples: Optional[int] = typer.Option(
        None, "--max-samples", min=1, help="Cap on the samples per pixel with --sample-growth (default 64)."),
    pixel_chunk: Optional[float] = typer.Option(
        None, "--pixel-chunk", min=0.0, max=1.0, help="The perturbed renders draw only the pixels their noise may "
        "change, in chunks of this fraction of the image (default 0.125), the others coming from one hard render "
        "(the same estimate, faster); 1: whole perturbed renders."),
    antithetic_pose: Optional[bool] = typer.Option(
        None, "--antithetic-pose/--independent-pose", help="With --sample-growth, draw a step's pose noise in "
        "antithetic pairs (+eps z, -eps z; default: the first-order terms cancel) or independently."),
    keep_best: Optional[bool] = typer.Option(
        None, "--keep-best/--last", help="Report each problem's iterate whose hard render is closest to the target "
        "(default) or the last iterate."),
    pose_noise: Optional[float] = typer.Option(
        None, "--pose-noise", min=0.0, help="Randomized smoothing of the loss over rotations: std of the rotation "
        "perturbation in degrees at the start, shrunk with the renderer's noise (0: off; default: the experiment's)."),
    pose_noise_until: Optional[float] = typer.Option(
        None, "--pose-noise-until", min=0.0, max=1.0, help="Fraction of the steps at which the pose noise has faded "
        "linearly to 0 (default 1: the last step); the steps after it descend the image-smoothed loss alone."),
    restarts: Optional[int] = typer.Option(
        None, "--restarts", min=0, help="Run a problem again from its initial pose with fresh noise, up to this many "
        "times, while its best hard render stays far from the target (loss above 5 % of the initial pose's; no ground "
        "truth used); each reports its closest run (default 0: one run, the paper's protocol)."),
    average_iterates: Optional[float] = typer.Option(
        None, "--average-iterates", min=0.0, max=0.999, help="With --keep-best, also consider the exponential average "
        "of the iterates with this decay per step (e.g. 0.97; one more hard render per step; default 0: off): the "
        "perturbed gradient's noise makes the last steps wander around the solution."),
    baseline: Optional[str] = BaselineOption,
):
    from rsmooth.experiments.render_pose import METHODS

    methods = _methods(method, METHODS)
    init_errors_deg = tuple(float(e) for e in init_error) if init_error else None
    for error in init_errors_deg or ():
        if not (math.isfinite(error) and 0.0 <= error <= 180.0):
            raise typer.BadParameter(f"--init-error must be an angle in [0, 180] degrees, got {error}")
    _run(_RENDER_POSE, out, seed, quick, mesh=mesh, init_errors_deg=init_errors_deg, problems=problems, methods=methods,
         steps=steps, num_samples=samples, keep_best=keep_best, pose_noise_deg=pose_noise, pose_noise_until=pose_noise_until,
         restarts=restarts, sample_growth=sample_growth, max_samples=max_samples, pixel_chunk=pixel_chunk,
         antithetic_pose=antithetic_pose, average_decay=average_iterates,
         baseline=_baseline(baseline))


@render_app.command("reconstruct", help=_doc(
    "Reconstruct meshes from multi-view silhouettes by deforming an icosphere (Laplacian and "
    "flattening regularizers) with the perturbed renderer, a SoftRas-like one and the hard "
    "z-buffer; 3D IoU and Chamfer distance to the targets.", _RENDER_RECONSTRUCT))
def render_reconstruct_command(
    out: Optional[Path] = OutOption,
    seed: int = SeedOption,
    quick: bool = QuickOption,
    mesh: Optional[list[str]] = typer.Option(
        None, "--mesh", help="Target (repeatable): cube, box, cylinder, torus, solo-upper-leg, solo-lower-leg, "
        "solo-hip, solo-foot, solo-base (example-robot-data), or a mesh file. Default: cube, torus, solo-upper-leg."),
    views: Optional[int] = typer.Option(None, "--views", min=1, help="Cameras around the target (default 8, quick 4)."),
    method: Optional[list[str]] = typer.Option(
        None, "--method", help="perturbed-gaussian, soft or hard (repeatable; default all three)."),
    steps: Optional[int] = typer.Option(None, "--steps", min=1, help="Adam steps (default 200, quick 60)."),
    samples: Optional[int] = typer.Option(
        None, "--samples", min=1, help="Monte-Carlo samples per pixel of the perturbed renderer (default 32, quick 8; "
        "8 is 1.6x faster and fits thin parts worse: see benchmarks/RESULTS.md)."),
    sample_chunk: Optional[float] = typer.Option(
        None, "--sample-chunk", min=0.0, max=1.0, help="The perturbed renderer draws its samples at the pixels its "
        "noise may change alone, in chunks of this fraction of a view (the same images and gradients, faster; "
        "default 0.125; 1: every pixel)."),
    laplacian_weight: Optional[float] = typer.Option(
        None, "--laplacian-weight", min=0.0, help="Weight of the Laplacian of the vertex offsets (default 30; thin "
        "parts gain from more, sharp corners lose: see benchmarks/RESULTS.md)."),
    baseline: Optional[str] = BaselineOption,
):
    from rsmooth.experiments.render_reconstruct import METHODS

    methods = _methods(method, METHODS)
    _run(_RENDER_RECONSTRUCT, out, seed, quick, targets=tuple(mesh) if mesh else None, views=views, methods=methods,
         steps=steps, num_samples=samples, sample_chunk=sample_chunk, laplacian_weight=laplacian_weight,
         baseline=_baseline(baseline))


MethodOption = typer.Option(
    "all", "--method", help="ddp, rddp, or all (ddp, rddp and R-DDP with geometric noise decays).")
SeedsOption = typer.Option(
    None, "--seeds", min=1, help="R-DDP runs per method, keys fold_in(seed, i) (default: the experiment's, 10 or 5 for solo-lift; quick 2)."
)


EstimatorOption = typer.Option(
    None, "--estimator", help="R-DDP's estimate of the smoothed dynamics' Jacobians: first (default), zeroth or alpha order.")
RddpSamplesOption = typer.Option(None, "--samples", min=1, help="R-DDP's samples per node (default: the experiment's).")


def _check_method(method: str, estimator: Optional[str] = None, samples: Optional[int] = None) -> None:
    if method not in ("ddp", "rddp", "all"):
        raise typer.BadParameter(f"--method must be ddp, rddp or all, got {method!r}")
    if estimator is not None and estimator not in ("first", "zeroth", "alpha"):
        raise typer.BadParameter(f"--estimator must be first, zeroth or alpha, got {estimator!r}")
    if estimator == "alpha" and samples is not None and samples < 4:
        raise typer.BadParameter(f"--samples must be >= 4 with --estimator alpha (half to each estimate), got {samples}")


@control_app.command("cube-lift", help=_doc(
    "Lift a cube resting on the floor to a target height with a vertical force, from zero force: "
    "DDP sees a zero gradient and stays put, R-DDP lifts it.", _CUBE_LIFT))
def control_cube_lift_command(
    out: Optional[Path] = OutOption,
    seed: int = SeedOption,
    quick: bool = QuickOption,
    method: str = MethodOption,
    seeds: Optional[int] = SeedsOption,
    height: Optional[float] = typer.Option(None, "--height", min=0.0, help="Target height above rest, m (default 0.1)."),
    estimator: Optional[str] = EstimatorOption,
    samples: Optional[int] = RddpSamplesOption,
):
    _check_method(method, estimator, samples)
    _run(_CUBE_LIFT, out, seed, quick, method=method, seeds=seeds, height=height, estimator=estimator, num_samples=samples)


@control_app.command("solo-lift", help=_doc(
    "Solo-12 standing on its four feet lifts one foot to a target height while the others stay "
    "on the floor, from the gravity-compensating torques: DDP sees a zero gradient, R-DDP breaks "
    "the contact.", _SOLO_LIFT))
def control_solo_lift_command(
    out: Optional[Path] = OutOption,
    seed: int = SeedOption,
    quick: bool = QuickOption,
    foot: str = typer.Option(
        "FL", "--foot", help="FL, FR, HL, HR, or all (each foot in turn, into OUT/FOOT; compiled once)."),
    height: Optional[float] = typer.Option(None, "--height", help="Target height of the foot above its start, m (default 0.05)."),
    method: str = MethodOption,
    seeds: Optional[int] = SeedsOption,
    estimator: Optional[str] = EstimatorOption,
    samples: Optional[int] = RddpSamplesOption,
):
    _check_method(method, estimator, samples)
    feet = ("FL", "FR", "HL", "HR")
    options = dict(height=height, method=method, seeds=seeds, estimator=estimator, num_samples=samples)
    if foot not in feet + ("all",):
        raise typer.BadParameter(f"--foot must be FL, FR, HL, HR or all, got {foot!r}")
    if height is not None and not 0 < height <= 0.15:
        raise typer.BadParameter(f"--height must be in (0, 0.15] m, got {height}")
    if foot != "all":
        _run(_SOLO_LIFT, out, seed, quick, title=f"control solo-lift {foot}", foot=foot, **options)
        return
    root = Path(out) if out is not None else DEFAULT_ROOT / _SOLO_LIFT.name
    rates = {}
    for name in feet:  # the foot is a traced cost parameter: one compilation for all four
        metrics = _run(_SOLO_LIFT, root / name, seed, quick, title=f"control solo-lift {name}", foot=name, **options)
        rates[name] = {m: metrics[m]["success_rate"] for m in metrics["methods"]}
    typer.echo("success rate per foot: " + "; ".join(
        f"{name}: " + ", ".join(f"{m} {100 * r:.0f} %" for m, r in rate.items()) for name, rate in rates.items()))


@control_app.command("pusher", help=_doc(
    "Push a box to a target pose (position and yaw) with a finger that starts 3 cm behind it, "
    "through sticking and sliding friction, from zero force: DDP sees a zero gradient and leaves "
    "the box, R-DDP pushes it.", _PUSHER))
def control_pusher_command(
    out: Optional[Path] = OutOption,
    seed: int = SeedOption,
    quick: bool = QuickOption,
    method: str = MethodOption,
    seeds: Optional[int] = SeedsOption,
    target_x: Optional[float] = typer.Option(None, "--target-x", help="Target box centre x, m (the box starts at 0; default 0.1)."),
    target_y: Optional[float] = typer.Option(None, "--target-y", help="Target box centre y, m (default 0)."),
    target_yaw: Optional[float] = typer.Option(
        None, "--target-yaw", min=-89.0, max=89.0, help="Target yaw, degrees counter-clockwise (default 15)."),
    estimator: Optional[str] = EstimatorOption,
    samples: Optional[int] = RddpSamplesOption,
):
    _check_method(method, estimator, samples)
    _run(_PUSHER, out, seed, quick, method=method, seeds=seeds, target_x=target_x, target_y=target_y, target_yaw=target_yaw,
         estimator=estimator, num_samples=samples)


@control_app.command("policy", help=_doc(
    "Policy optimization by Adam on first-, zeroth- and alpha-order estimates of the smoothed policy "
    "gradient (Suh et al., ICML 2022). --task throw (default): throw a ball over a wall of finite "
    "height as far as possible; the first-order estimate misses the jump at the wall's top and the "
    "ball ends at the wall, zeroth and alpha order clear it. --task pusher: open-loop finger forces "
    "push the simulator's box (hard frictional contact) to a target from zero force, the finger 5 cm "
    "behind it; the exact gradient of the box's pose is zero and no sample touches the box: first and "
    "alpha order mostly leave the box where it is, zeroth order's variance makes Adam's steps explore "
    "until it pushes (output in ./rsmooth-out/policy-pusher).",
    _POLICY, _POLICY_PUSHER))
def control_policy_command(
    out: Optional[Path] = OutOption,
    seed: int = SeedOption,
    quick: bool = QuickOption,
    task: str = typer.Option("throw", "--task", help="throw (a ball over a wall) or pusher (rsmooth.sim.pusher)."),
    method: str = typer.Option("all", "--method", help="first, zeroth, alpha, or all."),
    seeds: Optional[int] = typer.Option(
        None, "--seeds", min=1, help="Runs per method, keys fold_in(seed, i) (throw: default 10, quick 4; pusher: 8, quick 3)."),
    samples: Optional[int] = typer.Option(
        None, "--samples", min=4, help="Rollouts per gradient estimate (throw: default 64; pusher: 16, even)."),
    sigma: Optional[float] = typer.Option(
        None, "--sigma", help="Initial noise on the policy parameters (throw: rad, default 0.1; pusher: N, default 0.2)."),
):
    if task not in POLICY_TASKS:
        raise typer.BadParameter(f"--task must be throw or pusher, got {task!r}")
    if method not in ("first", "zeroth", "alpha", "all"):
        raise typer.BadParameter(f"--method must be first, zeroth, alpha or all, got {method!r}")
    if sigma is not None and not sigma > 0:
        raise typer.BadParameter(f"--sigma must be positive, got {sigma}")
    if task == "pusher" and samples is not None and samples % 2:
        raise typer.BadParameter(f"--samples must be even with --task pusher, got {samples}")
    _run(POLICY_TASKS[task], out, seed, quick, method=method, seeds=seeds, num_samples=samples, sigma=sigma)


@app.command(help=(
    "Runs the quick profile of the experiments into ./rsmooth-out/ (or --out): estimators, "
    "perturbed-argmax, null-gradients, sim solo12, render pose, control cube-lift."))
def demo(
    out: Path = typer.Option(DEFAULT_ROOT, "--out", help="Root folder; one sub-folder per experiment."),
    seed: int = SeedOption,
):
    for experiment in (_ESTIMATORS, _PERTURBED_ARGMAX, _NULL_GRADIENTS, _SOLO12, _RENDER_POSE, _CUBE_LIFT):
        _run(experiment, None, seed, True, root=out)
    typer.echo(f"demo: all artifacts under {out}/")


class _Interrupted(BaseException):
    """Raised in the main thread by the command's SIGINT handler. Not a `KeyboardInterrupt`,
    which Click turns into an ordinary exit, through the interpreter's shutdown."""


def _frame_after_dropping_callbacks(frame):
    """The frame that a garbage-collection callback or a ``__del__`` method interrupted, where
    `frame` runs inside one (Python prints an exception raised there and drops it: JAX's gc
    callback runs during compilation, and a Ctrl-C raised in it was lost); None otherwise."""
    codes = {getattr(callback, "__code__", None) for callback in gc.callbacks}
    outside = None
    while frame is not None:
        if frame.f_code in codes or frame.f_code.co_name == "__del__":
            outside = frame.f_back
        frame = frame.f_back
    return outside


def _trace_no_frame(frame, event, arg):
    return None


class _InterruptHandler:
    """The command's SIGINT handler: raises :class:`_Interrupted` in the main thread.

    Inside a callback that would drop it, it is raised instead when the interrupted frame runs
    its next line (a trace function set on that frame). It is also raised again every half
    second (by sending SIGINT to the process) until :func:`main` has caught it, in case it was
    lost all the same (e.g. turned into an error of a host callback, and that one handled)."""

    def __init__(self):
        self.received = threading.Event()
        self.caught = threading.Event()

    def __call__(self, signum, frame):
        if not self.received.is_set():
            self.received.set()
            threading.Thread(target=self._repeat, name="rsmooth-interrupt", daemon=True).start()
        outside = _frame_after_dropping_callbacks(frame)
        if outside is None:
            raise _Interrupted()
        outside.f_trace = self._raise_on_next_line
        if sys.gettrace() is None:  # frames' own trace functions run only while one is set
            sys.settrace(_trace_no_frame)

    @staticmethod
    def _raise_on_next_line(frame, event, arg):
        frame.f_trace = None
        if sys.gettrace() is _trace_no_frame:
            sys.settrace(None)
        raise _Interrupted()

    def _repeat(self):
        while not self.caught.wait(0.5):
            os.kill(os.getpid(), signal.SIGINT)

    def exit(self) -> None:
        """Prints that the run was interrupted and ends the process with code 130 (128 + SIGINT).

        By `os._exit`, without the interpreter's shutdown: an interrupted XLA compilation goes
        on in a worker thread, and the shutdown destroyed the JAX backend under it (a
        segmentation fault). Nothing is lost by skipping it: files are written atomically
        (rsmooth._files), and the `finally` blocks of the interrupted code have already run.
        """
        self.caught.set()
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):
                pass
        try:
            sys.stderr.write("\nrsmooth: interrupted\n")
            sys.stderr.flush()
        except (OSError, ValueError):
            pass
        os._exit(130)


def main():  # the console-script entry point
    handler = _InterruptHandler()
    # A shell starts background jobs with SIGINT ignored: keep it so.
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        signal.signal(signal.SIGINT, handler)

    try:
        from rsmooth import _xla

        if sys.argv[1:2] == ["render"]:
            _xla.apply_cpu_defaults()  # before JAX starts its backend (see rsmooth._xla)
        app()
    except BaseException:
        # Whatever ended the run after a Ctrl-C (the interrupt itself, or an error it caused,
        # e.g. in a host callback) ends it as an interrupt.
        if handler.received.is_set():
            handler.exit()
        raise


if __name__ == "__main__":
    main()
