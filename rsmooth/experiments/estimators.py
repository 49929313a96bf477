"""Experiment: the three gradient estimators on four non-smooth functions of one variable.

On the Heaviside step, |x|, a stiff sigmoid and a Coulomb friction law, smoothed with Gaussian
noise, it compares the zeroth-, first- and alpha-order estimates of the smoothed gradient with
the truth (closed forms, and quadrature for the sigmoid): their mean and spread along x, their
error against the number of samples, and the alpha the alpha-order estimator picks. It shows the
first-order estimate of the Heaviside gradient is exactly zero (biased), the one of the stiff
sigmoid unbiased but noisy, and that the alpha-order estimate avoids both failures
(Suh, Simchowitz, Zhang, Tedrake, ICML 2022, Sec. 3-4).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.stats import norm
from tqdm.auto import tqdm

import rsmooth
from rsmooth import _checks, viz
from rsmooth.experiments import _protocol

METRICS_DOC = """metrics.json keys: for each function F in heaviside, abs, stiff_sigmoid, coulomb and each
estimator E in zeroth, first, alpha: F.E.rmse / bias / std (lists over num_samples at x0),
F.alpha_mean (alpha chosen at x0, per num_samples); heaviside_first_order_grad_max_abs (0: the
first-order gradient of a step is null), heaviside_E_max_abs_error (largest |mean estimate -
true smoothed gradient| over the x grid, the peak of the truth being 1/(sigma sqrt(2 pi)));
num_samples, x0, sigma."""


@dataclasses.dataclass(frozen=True)
class Config:
    sigma: float = _protocol.option(0.3, "Standard deviation of the Gaussian smoothing noise.", above=0.0)
    x0: float = _protocol.option(0.1, "The point where the error against the number of samples is measured.")
    x_grid: tuple[float, float, int] = _protocol.option(
        (-1.2, 1.2, 49), "The x grid of the mean and spread curves: start, stop, number of points.")
    num_samples_grid: tuple[int, ...] = _protocol.option(
        (4, 16, 64, 256, 1024), "Numbers of samples of the error curves at x0.", flag="samples", min=1)
    num_samples_curve: int = _protocol.option(256, "Samples per estimate on the x grid.", min=1)
    num_trials: int = _protocol.option(100, "Independent estimates per point (their mean and spread).", min=2)
    stiffness: float = _protocol.option(100.0, "Slope factor k of the stiff sigmoid 1 / (1 + exp(-k x)).")

    @classmethod
    def quick(cls) -> "Config":
        return cls(x_grid=(-1.2, 1.2, 25), num_samples_grid=(4, 16, 64, 256), num_trials=40)

    def __post_init__(self):
        _protocol.check_options(self)
        if not self.x_grid[2] >= 2:
            raise ValueError(f"x_grid needs at least 2 points, got {self.x_grid[2]}")
        if not self.num_samples_grid:
            raise ValueError("num_samples_grid needs at least one number of samples")


def _gaussian_smoothing_by_quadrature(f: Callable, xs, sigma: float, num_nodes: int = 20001):
    """E f(x + sigma Z) for Gaussian Z by the trapezoid rule on [-8, 8] (fine enough for the
    steepest function here: the grid step times sigma is far below its transition width)."""
    z = jnp.linspace(-8.0, 8.0, num_nodes)
    weights = norm.pdf(z)
    return jax.vmap(lambda x: jnp.trapezoid(f(x + sigma * z) * weights, z))(xs)


def functions(config: Config) -> dict[str, tuple[Callable, Callable]]:
    """name -> (f, true smoothed derivative as a function of x)."""
    s = config.sigma
    k = config.stiffness

    def stiff_sigmoid(x):
        return jax.nn.sigmoid(k * x)

    def stiff_sigmoid_derivative(x):
        return k * jax.nn.sigmoid(k * x) * jax.nn.sigmoid(-k * x)

    return {
        "heaviside": (lambda x: jnp.where(x > 0, 1.0, 0.0), lambda x: norm.pdf(x / s) / s),
        "abs": (jnp.abs, lambda x: 2 * norm.cdf(x / s) - 1),
        "stiff_sigmoid": (
            stiff_sigmoid,
            lambda x: _gaussian_smoothing_by_quadrature(stiff_sigmoid_derivative, jnp.atleast_1d(x), s).reshape(jnp.shape(x)),
        ),
        # Coulomb friction with mu N = 1: F(v) = -sign(v), smoothed -(2 Phi(v / s) - 1).
        "coulomb": (lambda v: -jnp.sign(v), lambda v: -2 * norm.pdf(v / s) / s),
    }


def _estimate_table(estimator, fs, key, points, sigma, num_samples, num_trials):
    """Grads and alphas of num_trials independent estimates for every function of `fs` at each
    of `points`: arrays (len(fs), len(points), num_trials). One compiled program for all the
    functions (a `lax.switch` on the function's index, batched): the experiment compiles one
    program per estimator and sample count rather than one per function as well."""
    keys = jax.random.split(key, (len(fs), points.shape[0], num_trials))
    index = jnp.arange(len(fs))

    def run(keys, points):
        def one(k, x, i):
            f = lambda y: jax.lax.switch(i, fs, y)  # noqa: E731
            return estimator(f, k, x, sigma=sigma, num_samples=num_samples)

        per_trial = jax.vmap(one, in_axes=(0, None, None))
        est = jax.vmap(jax.vmap(per_trial, in_axes=(0, 0, None)), in_axes=(0, None, 0))(keys, points, index)
        return est.grad, est.stats.get("alpha")

    grads, alphas = _checks.jit_checked_on_host(run, "the estimators experiment")(keys, points)
    return grads, jnp.full(grads.shape, jnp.nan) if alphas is None else alphas


ESTIMATORS = {"zeroth": rsmooth.zeroth_order, "first": rsmooth.first_order, "alpha": rsmooth.alpha_order}


def run(config: Config, out: Path | str, key, progress: bool = True) -> dict:
    """Runs the experiment, writes metrics.json and estimators.png under `out`, returns metrics."""
    out = Path(out)
    fns = functions(config)
    xs = jnp.linspace(*config.x_grid)
    x0 = jnp.array([config.x0])
    metrics: dict = {"sigma": config.sigma, "x0": config.x0, "num_samples": list(config.num_samples_grid)}
    names = list(fns)
    fs = [fns[name][0] for name in names]
    # Every estimate first: one program per estimator and sample count; at num_samples_curve
    # the x grid and x0 together (x0 last), at the other counts x0 alone.
    counts = sorted(set(config.num_samples_grid) | {config.num_samples_curve})
    estimates = {}  # (estimator, M) -> grads, alphas as (function, point, trial) arrays
    bar = tqdm(total=len(ESTIMATORS) * len(counts), desc="estimators", disable=not progress)
    for est_name, estimator in ESTIMATORS.items():
        for m in counts:
            key, sub = jax.random.split(key)
            points = jnp.concatenate([xs, x0]) if m == config.num_samples_curve else x0
            grads, alphas = _estimate_table(estimator, fs, sub, points, config.sigma, m, config.num_trials)
            estimates[est_name, m] = np.asarray(grads), np.asarray(alphas)
            bar.update()
    bar.close()

    fig, axes = viz.plt.subplots(len(fns), 4, figsize=(17, 3.4 * len(fns)))
    colors = {"zeroth": "tab:blue", "first": "tab:orange", "alpha": "tab:green"}
    for row, (name, (f, true_grad)) in enumerate(fns.items()):
        truth_curve = np.asarray(true_grad(xs))
        truth_x0 = float(np.asarray(true_grad(x0))[0])
        ax_value, ax_grad, ax_error, ax_alpha = axes[row]
        fine = jnp.linspace(*config.x_grid[:2], 400)
        ax_value.plot(fine, f(fine), color="k", lw=1, label="f")
        ax_value.plot(fine, _gaussian_smoothing_by_quadrature(f, fine, config.sigma), color="tab:red", label=r"$f_\sigma$")
        ax_value.set_title(f"{name}: f and its smoothing (sigma={config.sigma})")
        ax_value.legend(fontsize=8)
        ax_grad.plot(xs, truth_curve, color="k", lw=2, label=r"true $f_\sigma'$")
        metrics[name] = {}
        for est_name in ESTIMATORS:
            all_grads, all_alphas = estimates[est_name, config.num_samples_curve]
            grads, alphas = all_grads[row, :-1], all_alphas[row, :-1]
            mean, std = grads.mean(1), grads.std(1)
            ax_grad.plot(xs, mean, color=colors[est_name], label=f"{est_name} (M={config.num_samples_curve})")
            ax_grad.fill_between(xs, mean - std, mean + std, color=colors[est_name], alpha=0.2)
            if name == "heaviside" and est_name == "first":
                metrics["heaviside_first_order_grad_max_abs"] = float(np.max(np.abs(grads)))
            if name == "heaviside":
                metrics[f"heaviside_{est_name}_max_abs_error"] = float(np.max(np.abs(mean - truth_curve)))
            if est_name == "alpha":
                ax_alpha.plot(xs, alphas.mean(1), color=colors["alpha"], label=f"M={config.num_samples_curve}")
            rmse, bias, spread, alpha_mean = [], [], [], []
            for m in config.num_samples_grid:
                g, a = (table[row, -1] for table in estimates[est_name, m])
                rmse.append(float(np.sqrt(np.mean((g - truth_x0) ** 2))))
                bias.append(float(np.mean(g) - truth_x0))
                spread.append(float(np.std(g)))
                alpha_mean.append(float(np.mean(a)))
            metrics[name][est_name] = {"rmse": rmse, "bias": bias, "std": spread}
            if est_name == "alpha":
                metrics[name]["alpha_mean"] = alpha_mean
            ax_error.loglog(config.num_samples_grid, rmse, "o-", color=colors[est_name], label=est_name)
        m_grid = np.asarray(config.num_samples_grid, float)
        first_rmse = metrics[name]["zeroth"]["rmse"][0]
        ax_error.loglog(m_grid, first_rmse * np.sqrt(m_grid[0] / m_grid), "k:", label=r"$1/\sqrt{M}$")
        ax_error.set_title(f"RMSE of the gradient at x0={config.x0}")
        ax_error.set_xlabel("samples M")
        ax_error.legend(fontsize=8)
        ax_grad.set_title("smoothed gradient: mean ± std of estimates")
        ax_grad.legend(fontsize=7)
        ax_alpha.set_ylim(-0.05, 1.05)
        ax_alpha.set_title("alpha chosen by the alpha-order estimator")
        ax_alpha.set_xlabel("x")
    fig.tight_layout()
    viz.save_figure(fig, out / "estimators.png")
    viz.write_metrics(out / "metrics.json", metrics)
    return metrics


def summary(metrics: dict) -> dict:
    """The lines printed after a run: the first-order Heaviside gradient and each estimator's error."""
    return {
        "first-order gradient of the Heaviside (max |.|)": metrics["heaviside_first_order_grad_max_abs"],
        "Heaviside: max |mean gradient - truth| (first, zeroth, alpha)": ", ".join(
            f"{metrics[f'heaviside_{e}_max_abs_error']:.3f}" for e in ("first", "zeroth", "alpha")
        ),
    }


EXPERIMENT = _protocol.Experiment(
    command=("experiment", "estimators"),
    name="estimators",
    config=Config,
    run=run,
    summary=summary,
    help="Zeroth-, first- and alpha-order gradient estimates on the Heaviside, |x|, a stiff sigmoid and Coulomb "
    "friction: means, spread and error against the number of samples.",
    metrics_doc=METRICS_DOC,
)
