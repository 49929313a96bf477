"""The `rsmooth` command: one sub-command per experiment.

Every experiment takes `--out DIR` (default `./rsmooth-out/NAME`), `--seed N` and `--quick`
(a reduced size that finishes in a couple of minutes on 2 CPU cores), shows a progress bar,
and writes `DIR/metrics.json` beside its figures.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Optional

import typer

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
control_app = typer.Typer(help="Optimal control through contact: DDP and randomized DDP.", no_args_is_help=True)
app.add_typer(control_app, name="control")

DEFAULT_ROOT = Path("rsmooth-out")

OutOption = typer.Option(None, "--out", help="Output folder (default ./rsmooth-out/NAME).")
SeedOption = typer.Option(0, "--seed", help="Seed of the jax.random key.")
QuickOption = typer.Option(False, "--quick", help="Reduced size: about two minutes on 2 CPU cores.")


def _prepare(name: str, out: Optional[Path], seed: int):
    import jax

    jax.config.update("jax_enable_x64", True)
    out = Path(out) if out is not None else DEFAULT_ROOT / name
    out.mkdir(parents=True, exist_ok=True)
    return out, jax.random.key(seed)


def _report(name: str, out: Path, start: float, summary: dict) -> None:
    typer.echo(f"{name}: done in {time.perf_counter() - start:.1f} s, artifacts in {out}/")
    for key, value in summary.items():
        typer.echo(f"  {key}: {value}")


def _run_estimators(out: Optional[Path], seed: int, quick: bool, root: Optional[Path] = None) -> dict:
    from rsmooth.experiments import estimators

    start = time.perf_counter()
    out, key = _prepare("estimators", out if root is None else root / "estimators", seed)
    config = estimators.Config.quick() if quick else estimators.Config()
    metrics = estimators.run(config, out, key)
    _report("estimators", out, start, {
        "first-order gradient of the Heaviside (max |.|)": metrics["heaviside_first_order_grad_max_abs"],
        "Heaviside: max |mean gradient - truth| (first, zeroth, alpha)": ", ".join(
            f"{metrics[f'heaviside_{e}_max_abs_error']:.3f}" for e in ("first", "zeroth", "alpha")
        ),
    })
    return metrics


def _run_perturbed_argmax(out: Optional[Path], seed: int, quick: bool, root: Optional[Path] = None) -> dict:
    from rsmooth.experiments import perturbed_argmax

    start = time.perf_counter()
    out, key = _prepare("perturbed-argmax", out if root is None else root / "perturbed-argmax", seed)
    config = perturbed_argmax.Config.quick() if quick else perturbed_argmax.Config()
    metrics = perturbed_argmax.run(config, out, key)
    _report("perturbed-argmax", out, start, {
        "max |perturbed argmax - softmax|": round(metrics["softmax_max_abs_error"], 4),
        "held-out Spearman correlation, before -> after": (
            f"{metrics['ranking_test_spearman_initial']:.3f} -> {metrics['ranking_test_spearman_final']:.3f}"
        ),
    })
    return metrics


def _run_null_gradients(out: Optional[Path], seed: int, quick: bool, root: Optional[Path] = None) -> dict:
    from rsmooth.experiments import null_gradients

    start = time.perf_counter()
    out, key = _prepare("null-gradients", out if root is None else root / "null-gradients", seed)
    config = null_gradients.Config.quick() if quick else null_gradients.Config()
    metrics = null_gradients.run(config, out, key)
    _report("null-gradients", out, start, {
        "exact gradient below m g (max |.|)": metrics["exact_gradient_max_abs_below_weight"],
        "smoothed gradients, max |mean - closed form| (first, zeroth) per sigma": "; ".join(
            f"sigma={s:g}: {metrics[f'sigma={s:g}']['first_order_max_abs_error']:.1e}, "
            f"{metrics[f'sigma={s:g}']['zeroth_order_max_abs_error']:.1e}"
            for s in metrics["sigmas"]
        ),
    })
    return metrics


def _run_solo12(
    out: Optional[Path], seed: int, quick: bool, root: Optional[Path] = None,
    torques: str = "standing", steps: Optional[int] = None,
) -> dict:
    import dataclasses

    from rsmooth.experiments import solo12_sim

    start = time.perf_counter()
    out, key = _prepare("solo12", out if root is None else root / "solo12", seed)
    config = solo12_sim.Config.quick() if quick else solo12_sim.Config()
    config = dataclasses.replace(config, torques=torques, **({} if steps is None else {"steps": steps}))
    metrics = solo12_sim.run(config, out, key)
    _report("sim solo12", out, start, {
        "base drift (m)": f"{metrics['base_drift']:.2e}",
        "max foot slip (m)": f"{metrics['max_foot_slip']:.2e}",
        "contact solves converged": f"{100 * metrics['ncp_converged_fraction']:.1f} %",
    })
    return metrics


def _run_render_pose(
    out: Optional[Path], seed: int, quick: bool, root: Optional[Path] = None,
    mesh: str = "cube", init_errors: Optional[list[float]] = None, problems: Optional[int] = None,
) -> dict:
    import dataclasses

    from rsmooth.experiments import render_pose

    start = time.perf_counter()
    out, key = _prepare("render-pose", out if root is None else root / "render-pose", seed)
    config = render_pose.Config.quick() if quick else render_pose.Config()
    changes: dict = {"mesh": mesh}
    if init_errors:
        changes["init_errors_deg"] = tuple(float(e) for e in init_errors)
    if problems is not None:
        changes["problems"] = problems
    config = dataclasses.replace(config, **changes)
    metrics = render_pose.run(config, out, key)
    errors = ", ".join(f"{e:g}" for e in metrics["init_errors_deg"])
    _report("render pose", out, start, {
        f"{method}: solved % from {errors} deg": ", ".join(
            f"{metrics[method][f'{e:g}']['solved_pct']:.0f}" for e in metrics["init_errors_deg"]
        )
        for method in metrics["methods"]
    })
    return metrics


def _run_render_reconstruct(
    out: Optional[Path], seed: int, quick: bool, root: Optional[Path] = None,
    meshes: Optional[list[str]] = None, views: Optional[int] = None,
) -> dict:
    import dataclasses

    from rsmooth.experiments import render_reconstruct

    start = time.perf_counter()
    out, key = _prepare("render-reconstruct", out if root is None else root / "render-reconstruct", seed)
    config = render_reconstruct.Config.quick() if quick else render_reconstruct.Config()
    changes: dict = {}
    if meshes:
        changes["targets"] = tuple(meshes)
    if views is not None:
        changes["views"] = views
    config = dataclasses.replace(config, **changes)
    metrics = render_reconstruct.run(config, out, key)
    _report("render reconstruct", out, start, {
        f"{method}: 3D IoU / Chamfer ({', '.join(metrics['targets'])})": ", ".join(
            f"{metrics[method][t]['iou_3d']:.2f} / {metrics[method][t]['chamfer']:.4f}" for t in metrics["targets"]
        )
        for method in metrics["methods"]
    })
    return metrics


def _run_control_cube_lift(
    out: Optional[Path], seed: int, quick: bool, root: Optional[Path] = None,
    method: str = "all", seeds: Optional[int] = None, height: Optional[float] = None,
) -> dict:
    import dataclasses

    from rsmooth.experiments import control_cube_lift

    start = time.perf_counter()
    out, key = _prepare("cube-lift", out if root is None else root / "cube-lift", seed)
    config = control_cube_lift.Config.quick() if quick else control_cube_lift.Config()
    changes: dict = {"method": method}
    if seeds is not None:
        changes["seeds"] = seeds
    if height is not None:
        changes["height"] = height
    config = dataclasses.replace(config, **changes)
    metrics = control_cube_lift.run(config, out, key)
    _report("control cube-lift", out, start, {
        f"{name}: success rate, final height (mm), iterations": (
            f"{100 * metrics[name]['success_rate']:.0f} %, {1000 * metrics[name]['final_height']:.1f}, {metrics[name]['iterations']}"
        )
        for name in metrics["methods"]
    })
    return metrics


def _run_control_solo_lift(
    out: Optional[Path], seed: int, quick: bool, root: Optional[Path] = None,
    foot: str = "FL", height: Optional[float] = None, method: str = "all", seeds: Optional[int] = None,
) -> dict:
    import dataclasses

    from rsmooth.experiments import control_solo_lift

    start = time.perf_counter()
    out, key = _prepare("solo-lift", out if root is None else root / "solo-lift", seed)
    config = control_solo_lift.Config.quick() if quick else control_solo_lift.Config()
    changes: dict = {"foot": foot, "method": method}
    if seeds is not None:
        changes["seeds"] = seeds
    if height is not None:
        changes["height"] = height
    config = dataclasses.replace(config, **changes)
    metrics = control_solo_lift.run(config, out, key)
    _report(f"control solo-lift {foot}", out, start, {
        f"{name}: success rate, foot height (mm), other feet max height (mm), iterations": (
            f"{100 * metrics[name]['success_rate']:.0f} %, {1000 * metrics[name]['foot_height']:.1f}, "
            f"{1000 * metrics[name]['other_feet_max_height']:.1f}, {metrics[name]['iterations']}"
        )
        for name in metrics["methods"]
    })
    return metrics


def _run_control_pusher(
    out: Optional[Path], seed: int, quick: bool, root: Optional[Path] = None, method: str = "all",
    seeds: Optional[int] = None, target_x: Optional[float] = None, target_y: Optional[float] = None,
    target_yaw: Optional[float] = None,
) -> dict:
    import dataclasses

    from rsmooth.experiments import control_pusher

    start = time.perf_counter()
    out, key = _prepare("pusher", out if root is None else root / "pusher", seed)
    config = control_pusher.Config.quick() if quick else control_pusher.Config()
    changes: dict = {"method": method}
    for name, value in (("seeds", seeds), ("target_x", target_x), ("target_y", target_y), ("target_yaw", target_yaw)):
        if value is not None:
            changes[name] = value
    config = dataclasses.replace(config, **changes)
    metrics = control_pusher.run(config, out, key)
    _report("control pusher", out, start, {
        f"{name}: success rate, position error (mm), yaw error (deg), iterations": (
            f"{100 * metrics[name]['success_rate']:.0f} %, {1000 * metrics[name]['position_error']:.1f}, "
            f"{metrics[name]['yaw_error_deg']:.1f}, {metrics[name]['iterations']}"
        )
        for name in metrics["methods"]
    })
    return metrics


def _doc(summary: str, module: str) -> str:
    import importlib

    return summary + "\n\n" + importlib.import_module(f"rsmooth.experiments.{module}").METRICS_DOC


@experiment_app.command("estimators", help=_doc(
    "Zeroth-, first- and alpha-order gradient estimates on the Heaviside, |x|, a stiff sigmoid "
    "and Coulomb friction: means, spread and error against the number of samples.", "estimators"))
def experiment_estimators(out: Optional[Path] = OutOption, seed: int = SeedOption, quick: bool = QuickOption):
    _run_estimators(out, seed, quick)


@experiment_app.command("perturbed-argmax", help=_doc(
    "Gumbel-perturbed argmax against the softmax, and learning to rank with the perturbed "
    "Fenchel-Young loss.", "perturbed_argmax"))
def experiment_perturbed_argmax(out: Optional[Path] = OutOption, seed: int = SeedOption, quick: bool = QuickOption):
    _run_perturbed_argmax(out, seed, quick)


@experiment_app.command("null-gradients", help=_doc(
    "A cube resting on the floor under an upward force: the exact gradient of its final height "
    "is zero below m g; first- and zeroth-order smoothed gradients against their closed form.",
    "null_gradients"))
def experiment_null_gradients(out: Optional[Path] = OutOption, seed: int = SeedOption, quick: bool = QuickOption):
    _run_null_gradients(out, seed, quick)


@sim_app.command("solo12", help=_doc(
    "Simulate Solo-12 on the floor under standing (gravity-compensating) or random torques and "
    "write a stick-figure animation.", "solo12_sim"))
def sim_solo12(
    out: Optional[Path] = OutOption,
    seed: int = SeedOption,
    quick: bool = QuickOption,
    torques: str = typer.Option("standing", "--torques", help="standing or random."),
    steps: Optional[int] = typer.Option(None, "--steps", min=1, help="Time steps of 10 ms (default 200, quick 100)."),
):
    if torques not in ("standing", "random"):
        raise typer.BadParameter(f"--torques must be 'standing' or 'random', got {torques!r}")
    _run_solo12(out, seed, quick, torques=torques, steps=steps)


@render_app.command("pose", help=_doc(
    "Recover a mesh's rotation from one RGB image with the perturbed renderer (Gaussian or Cauchy "
    "noise, adaptive noise decrease), a SoftRas-like one and the hard z-buffer.", "render_pose"))
def render_pose_command(
    out: Optional[Path] = OutOption,
    seed: int = SeedOption,
    quick: bool = QuickOption,
    mesh: str = typer.Option("cube", "--mesh", help="cube, icosphere, torus, or a mesh file (OBJ, STL, PLY, DAE)."),
    init_error: Optional[list[float]] = typer.Option(
        None, "--init-error", help="Initial rotation error in degrees (repeatable; default 20, 50, 80)."),
    problems: Optional[int] = typer.Option(None, "--problems", min=1, help="Problems per initial error."),
):
    _run_render_pose(out, seed, quick, mesh=mesh, init_errors=init_error, problems=problems)


@render_app.command("reconstruct", help=_doc(
    "Reconstruct meshes from multi-view silhouettes by deforming an icosphere (Laplacian and "
    "flattening regularizers) with the perturbed renderer, a SoftRas-like one and the hard "
    "z-buffer; 3D IoU and Chamfer distance to the targets.", "render_reconstruct"))
def render_reconstruct_command(
    out: Optional[Path] = OutOption,
    seed: int = SeedOption,
    quick: bool = QuickOption,
    mesh: Optional[list[str]] = typer.Option(
        None, "--mesh", help="Target (repeatable): cube, box, cylinder, torus, solo-upper-leg, solo-lower-leg, "
        "solo-hip, solo-foot, solo-base (example-robot-data), or a mesh file. Default: cube, torus, solo-upper-leg."),
    views: Optional[int] = typer.Option(None, "--views", min=1, help="Cameras around the target (default 8, quick 4)."),
):
    _run_render_reconstruct(out, seed, quick, meshes=mesh, views=views)


MethodOption = typer.Option(
    "all", "--method", help="ddp, rddp, or all (ddp, rddp and R-DDP with geometric noise decays).")
SeedsOption = typer.Option(None, "--seeds", min=1, help="R-DDP runs per method, keys fold_in(seed, i) (default 10, quick 2).")


@control_app.command("cube-lift", help=_doc(
    "Lift a cube resting on the floor to a target height with a vertical force, from zero force: "
    "DDP sees a zero gradient and stays put, R-DDP lifts it.", "control_cube_lift"))
def control_cube_lift_command(
    out: Optional[Path] = OutOption,
    seed: int = SeedOption,
    quick: bool = QuickOption,
    method: str = MethodOption,
    seeds: Optional[int] = SeedsOption,
    height: Optional[float] = typer.Option(None, "--height", min=0.0, help="Target height above rest, m (default 0.1)."),
):
    if method not in ("ddp", "rddp", "all"):
        raise typer.BadParameter(f"--method must be ddp, rddp or all, got {method!r}")
    _run_control_cube_lift(out, seed, quick, method=method, seeds=seeds, height=height)


@control_app.command("solo-lift", help=_doc(
    "Solo-12 standing on its four feet lifts one foot to a target height while the others stay "
    "on the floor, from the gravity-compensating torques: DDP sees a zero gradient, R-DDP breaks "
    "the contact.", "control_solo_lift"))
def control_solo_lift_command(
    out: Optional[Path] = OutOption,
    seed: int = SeedOption,
    quick: bool = QuickOption,
    foot: str = typer.Option("FL", "--foot", help="FL, FR, HL or HR."),
    height: Optional[float] = typer.Option(None, "--height", help="Target height of the foot above its start, m (default 0.05)."),
    method: str = MethodOption,
    seeds: Optional[int] = SeedsOption,
):
    if method not in ("ddp", "rddp", "all"):
        raise typer.BadParameter(f"--method must be ddp, rddp or all, got {method!r}")
    if foot not in ("FL", "FR", "HL", "HR"):
        raise typer.BadParameter(f"--foot must be FL, FR, HL or HR, got {foot!r}")
    if height is not None and not 0 < height <= 0.15:
        raise typer.BadParameter(f"--height must be in (0, 0.15] m, got {height}")
    _run_control_solo_lift(out, seed, quick, foot=foot, height=height, method=method, seeds=seeds)


@control_app.command("pusher", help=_doc(
    "Push a box to a target pose (position and yaw) with a finger that starts 3 cm behind it, "
    "through sticking and sliding friction, from zero force: DDP sees a zero gradient and leaves "
    "the box, R-DDP pushes it.", "control_pusher"))
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
):
    if method not in ("ddp", "rddp", "all"):
        raise typer.BadParameter(f"--method must be ddp, rddp or all, got {method!r}")
    _run_control_pusher(out, seed, quick, method=method, seeds=seeds, target_x=target_x, target_y=target_y, target_yaw=target_yaw)


@app.command(help=(
    "Runs the quick profile of the experiments into ./rsmooth-out/ (or --out): estimators, "
    "perturbed-argmax, null-gradients, sim solo12, render pose, control cube-lift."))
def demo(
    out: Path = typer.Option(DEFAULT_ROOT, "--out", help="Root folder; one sub-folder per experiment."),
    seed: int = SeedOption,
):
    runners = (_run_estimators, _run_perturbed_argmax, _run_null_gradients, _run_solo12, _run_render_pose, _run_control_cube_lift)
    for runner in runners:
        runner(None, seed, True, root=out)
    typer.echo(f"demo: all artifacts under {out}/")


def main():  # the console-script entry point
    app()


if __name__ == "__main__":
    main()
