"""Experiment: null gradients of hard contact, and what randomized smoothing gives instead.

A cube rests on the floor; a constant upward force ``F`` acts on it for ``T`` steps. With
hard (rigid, inelastic) contact the cube does not move while ``F < m g``, so the final height
``z_T(F)`` is flat there and its exact gradient is zero: a gradient-based optimizer asked to
lift the cube from ``F = 0`` receives no signal (Fig. 2 of Le Lidec, Montaut, Schmid, Laptev,
Carpentier, "Augmenting differentiable physics with randomized smoothing", 2022). Above
``m g`` the cube flies and, with semi-implicit Euler, ``z_T = z_0 + h^2 T (T + 1) / 2 (F/m - g)``
exactly, so ``z_T(F) = z_0 + c max(F - m g, 0)`` and its Gaussian smoothing has the closed-form
gradient ``c Phi((F - m g) / sigma)``: the smoothed gradients (first order: mean of sampled
exact gradients; zeroth order: score function) are compared to it for several ``sigma``.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.stats import norm
from tqdm.auto import tqdm

import rsmooth
from rsmooth import _checks, sim, viz
from rsmooth.experiments import _protocol

METRICS_DOC = """metrics.json keys: forces (the grid of upward forces, N), weight (m g, N),
final_height (z_T on the grid), exact_gradient (d z_T / d F by implicit differentiation),
exact_gradient_max_abs_below_weight (max |d z_T / d F| for F < m g: 0 for hard contact),
exact_gradient_above_weight_rel_error (against h^2 T (T + 1) / (2 m)), sigmas, and per sigma
'sigma=S': first_order_mean, first_order_std, zeroth_order_mean, zeroth_order_std (gradient
estimates over trials on the grid), closed_form (c Phi((F - m g) / sigma)),
first_order_max_abs_error, zeroth_order_max_abs_error (of the mean, against the closed form),
first_order_at_rest and zeroth_order_at_rest (mean estimate at F = 0: non-zero, lifting)."""


@dataclasses.dataclass(frozen=True)
class Config:
    steps: int = _protocol.option(10, "Time steps of 10 ms under the constant upward force.", min=1)
    force_grid: tuple[float, float, int] = _protocol.option(
        (0.0, 20.0, 41), "The grid of upward forces: start (N), stop (N), number of points.")
    sigmas: tuple[float, ...] = _protocol.option((1.0, 2.0, 4.0), "Noise scales of the smoothing, N.", flag="sigma")
    num_samples: int = _protocol.option(64, "Samples per gradient estimate.", flag="samples", min=1)
    num_trials: int = _protocol.option(8, "Independent estimates per force (their mean and spread).", min=1)

    @classmethod
    def quick(cls) -> "Config":
        return cls(force_grid=(0.0, 20.0, 11), num_samples=32, num_trials=4)

    def __post_init__(self):
        _protocol.check_options(self)
        if not (self.sigmas and all(sigma > 0 for sigma in self.sigmas)):
            raise ValueError(f"sigmas must be positive (at least one), got {self.sigmas}")
        if not self.force_grid[2] >= 2:
            raise ValueError(f"force_grid needs at least 2 points, got {self.force_grid[2]}")


def run(config: Config, out: Path | str, key, progress: bool = True) -> dict:
    """Runs the experiment, writes metrics.json and null_gradients.png under `out`."""
    out = Path(out)
    cube = sim.cube()
    x0 = cube.initial_state()
    mass = float(cube.model.body_mass[1])
    weight = mass * float(-cube.model.gravity[2])
    h = float(cube.time_step)
    slope = h**2 * config.steps * (config.steps + 1) / (2 * mass)

    def final_height(force):
        us = jnp.zeros((config.steps, 6)).at[:, 2].set(force)
        xs, _ = cube.rollout(x0, us)
        return xs[-1, 2]

    forces = jnp.linspace(*config.force_grid)
    bar = tqdm(total=1 + 2 * len(config.sigmas), desc="null-gradients", disable=not progress)
    # Forward mode (one input, one output): no transposed rollout to compile. Traced without
    # the traced checks and checked on the host, so the persistent compilation cache keeps it.
    exact = jax.vmap(lambda f: jax.jvp(final_height, (f,), (jnp.ones_like(f),)))
    heights, gradients = _checks.jit_checked_on_host(exact, "the null-gradients experiment (exact gradient)")(forces)
    bar.update()
    below = np.asarray(forces) < weight - 1e-9
    above = np.asarray(forces) > weight + 1e-9
    metrics: dict = {
        "forces": forces,
        "weight": weight,
        "steps": config.steps,
        "final_height": heights,
        "exact_gradient": gradients,
        "exact_gradient_max_abs_below_weight": float(np.max(np.abs(np.asarray(gradients)[below]))),
        "exact_gradient_above_weight_rel_error": float(np.max(np.abs(np.asarray(gradients)[above] / slope - 1))),
        "sigmas": list(config.sigmas),
        "num_samples": config.num_samples,
    }

    def compile_estimates(estimator):
        def one(args):
            key, force, sigma = args
            return estimator(final_height, key, force, sigma=sigma, num_samples=config.num_samples).grad

        # Samples are batched by vmap inside the estimator; the (force, trial) pairs go one
        # after the other: a vmap over both levels (~1400 rollouts with contact solves in
        # while loops) made XLA on CPU hang, as reported for MJX in the field notes.
        def estimates(key, sigma):
            keys = jax.random.split(key, forces.shape[0] * config.num_trials)
            points = jnp.repeat(forces, config.num_trials)
            sigmas = jnp.full(points.shape, sigma)
            grads = jax.lax.map(one, (keys, points, sigmas)).reshape(forces.shape[0], -1)
            return grads.mean(1), grads.std(1)

        return _checks.jit_checked_on_host(estimates, "the null-gradients experiment")

    estimators = {
        "first_order": compile_estimates(rsmooth.first_order),
        "zeroth_order": compile_estimates(rsmooth.zeroth_order),
    }

    fig, (ax_height, ax_grad) = viz.plt.subplots(1, 2, figsize=(13, 4.6))
    fine = np.linspace(*config.force_grid[:2], 400)
    ax_height.plot(forces, heights, "k.-", label="hard contact $z_T(F)$")
    ax_grad.plot(forces, gradients, "k.-", lw=2, label="exact gradient (implicit)")
    colors = viz.plt.cm.viridis(np.linspace(0.1, 0.85, len(config.sigmas)))
    for sigma, color in zip(config.sigmas, colors):
        key, k_first, k_zeroth = jax.random.split(key, 3)
        closed_form = slope * norm.cdf((forces - weight) / sigma)
        entry = {"closed_form": closed_form}
        for (name, estimates), k in zip(estimators.items(), (k_first, k_zeroth)):
            mean, std = (np.asarray(a) for a in estimates(k, sigma))
            bar.update()
            entry[f"{name}_mean"], entry[f"{name}_std"] = mean, std
            entry[f"{name}_max_abs_error"] = float(np.max(np.abs(mean - np.asarray(closed_form))))
            entry[f"{name}_at_rest"] = float(mean[0])
            marker = "o" if name == "first_order" else "x"
            ax_grad.errorbar(forces, mean, yerr=std, fmt=marker, ms=4, color=color, alpha=0.8,
                             label=f"{name.replace('_', '-')}, sigma={sigma:g} N")
        metrics[f"sigma={sigma:g}"] = entry
        ax_grad.plot(fine, slope * norm.cdf((fine - weight) / sigma), "--", color=color, lw=1)
        smoothed_height = heights[0] + slope * _smoothed_ramp(fine - weight, sigma)
        ax_height.plot(fine, smoothed_height, "--", color=color, label=f"smoothed, sigma={sigma:g} N")
    bar.close()
    for ax in (ax_height, ax_grad):
        ax.axvline(weight, color="gray", lw=0.8, ls=":")
        ax.set_xlabel("upward force F (N)")
        ax.legend(fontsize=7)
    ax_height.set_ylabel(f"height after {config.steps} steps (m)")
    ax_height.set_title("a resting cube does not move until F > m g")
    ax_grad.set_ylabel("d height / d F")
    ax_grad.set_title("exact gradient is 0 below m g; smoothed ones (dashed: closed form) are not")
    fig.tight_layout()
    viz.save_figure(fig, out / "null_gradients.png")
    viz.write_metrics(out / "metrics.json", metrics)
    return metrics


def _smoothed_ramp(x, sigma):
    """``E[max(x + sigma Z, 0)] = x Phi(x / sigma) + sigma phi(x / sigma)`` for Gaussian Z."""
    return x * norm.cdf(x / sigma) + sigma * norm.pdf(x / sigma)


def summary(metrics: dict) -> dict:
    """The lines printed after a run: the exact gradient below m g, the smoothed ones' errors."""
    return {
        "exact gradient below m g (max |.|)": metrics["exact_gradient_max_abs_below_weight"],
        "smoothed gradients, max |mean - closed form| (first, zeroth) per sigma": "; ".join(
            f"sigma={s:g}: {metrics[f'sigma={s:g}']['first_order_max_abs_error']:.1e}, "
            f"{metrics[f'sigma={s:g}']['zeroth_order_max_abs_error']:.1e}"
            for s in metrics["sigmas"]
        ),
    }


EXPERIMENT = _protocol.Experiment(
    command=("experiment", "null-gradients"),
    name="null-gradients",
    config=Config,
    run=run,
    summary=summary,
    help="A cube resting on the floor under an upward force: the exact gradient of its final height is zero below "
    "m g; first- and zeroth-order smoothed gradients against their closed form.",
    metrics_doc=METRICS_DOC,
)
