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
experiment_app = typer.Typer(help="Experiments on the smoothing core.", no_args_is_help=True)
app.add_typer(experiment_app, name="experiment")

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


@app.command(help="Runs the quick profile of every experiment into ./rsmooth-out/ (or --out).")
def demo(
    out: Path = typer.Option(DEFAULT_ROOT, "--out", help="Root folder; one sub-folder per experiment."),
    seed: int = SeedOption,
):
    for runner in (_run_estimators, _run_perturbed_argmax):
        runner(None, seed, True, root=out)
    typer.echo(f"demo: all artifacts under {out}/")


def main():  # the console-script entry point
    app()


if __name__ == "__main__":
    main()
