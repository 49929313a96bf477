r"""Experiment: over long horizons a chaotic system's first-order gradients explode.

Suh, Simchowitz, Zhang and Tedrake ("Do differentiable simulators give better policy
gradients?", ICML 2022, Sec. 3) note that the exact gradient of a chaotic rollout grows
exponentially with the horizon, and with it the variance of the first-order (pathwise)
estimate of the smoothed gradient, while the zeroth-order (score-function) estimate only sees
values, which stay bounded.

The system: a 1 kg ball (:func:`rsmooth.sim.ball`, no friction) dropped from rest at height
``height`` and horizontal position ``x`` into a wedge of two planes through the origin, each at
``half_angle`` from the vertical, with elastic compliant contact (:class:`rsmooth.sim.SpringDamper`
without damping). This is the gravitational wedge billiard, chaotic for half-angles above 45
degrees (Lehtihet and Miller, "Numerical study of a billiard in a gravitational field", Physica
D 21, 1986); the experiment measures the growth of the exact derivative itself.
The objective is the ball's horizontal position after each horizon of ``horizons`` (steps of
``time_step``), all from one rollout, as a function of the start ``x``. The smoothed gradient at
``start_x`` is estimated ``repeats`` times with ``num_samples`` samples each, by both estimators:
per horizon, the per-sample variance of each (mean and spread over the repeats), the exact
derivative along a sweep of starts (its median size grows as ``exp(lambda t)``, ``lambda`` a
Lyapunov exponent, fitted), and the range of the final position, which bounds the zeroth-order
variance by ``range^2 / sigma^2``. The alpha-order estimate is measured beside them with the
per-entry rule (``rule="inverse_variance"``): each horizon is its own objective and gets its own
weight, where the default rule's single alpha would let the longest horizon decide for all.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

import rsmooth
from rsmooth import diagnostics, sim, viz
from rsmooth.experiments import _landscape, _protocol

MASS = 1.0  # kg
RADIUS = 0.05  # m

METRICS_DOC = """metrics.json keys: half_angle_deg, height (m), start_x (m), stiffness (N/m), time_step (s),
horizons (steps), horizon_times (s), sigma (m), num_samples, repeats; landscape_offsets (starts
relative to start_x, m) and landscape_final_x (final x per start, one list per horizon);
exact_derivative_median (median |d x_T / d x_0| over the landscape, per horizon), lyapunov_exponent
(1/s, the slope of log exact_derivative_median against time over the horizons after the first
bounce), value_range (max - min of the final x over the landscape, per horizon),
zeroth_variance_bound (value_range^2 / sigma^2); for E in first, zeroth, alpha: E.per_sample_variance
(per horizon: mean, std, median, q16, q84 over the repeats of num_samples x the estimate's squared
standard error), E.mean and E.std (of the gradient estimates over the repeats, per horizon); alpha.weight
(the first-order weight per horizon, mean over the repeats);
first_over_zeroth_variance (ratio of the mean per-sample variances, per horizon)."""


@dataclasses.dataclass(frozen=True)
class Config:
    half_angle_deg: float = _protocol.option(60.0, "Angle of each wall of the wedge from the vertical, degrees.",
                                             above=0.0, below=90.0)
    height: float = _protocol.option(0.6, "Drop height of the ball's centre above the wedge's apex, m.", above=0.0)
    start_x: float = _protocol.option(0.1, "Horizontal start of the ball where the gradient is estimated, m.")
    stiffness: float = _protocol.option(1e4, "Contact stiffness, N/m (elastic: no damping).", above=0.0)
    time_step: float = _protocol.option(0.005, "Time step, s.", above=0.0)
    horizons: tuple[int, ...] = _protocol.option(
        (50, 100, 200, 400, 800), "Horizons, in steps, increasing (one rollout gives them all).", flag="horizon", min=1)
    sigma: float = _protocol.option(0.01, "Standard deviation of the Gaussian noise on the start, m.", above=0.0)
    num_samples: int = _protocol.option(64, "Samples per gradient estimate.", flag="samples", min=2)
    repeats: int = _protocol.option(16, "Independent estimates (their mean and spread).", min=2)

    @classmethod
    def quick(cls) -> "Config":
        return cls(horizons=(50, 100, 200, 400), num_samples=32, repeats=8)

    def __post_init__(self):
        _protocol.check_options(self)
        if not self.horizons or list(self.horizons) != sorted(set(self.horizons)):
            raise ValueError(f"horizons (--horizon) must be distinct and increasing, got {self.horizons}")
        # The spring is explicit in the penetration: stable while h sqrt(k / m) < 2.
        if not self.time_step * np.sqrt(self.stiffness / MASS) < 1.0:
            raise ValueError(f"time_step (--time-step) x sqrt(stiffness / m) must be below 1 for a stable contact, got "
                             f"{self.time_step * np.sqrt(self.stiffness / MASS):.3g}")
        angle = np.deg2rad(self.half_angle_deg)
        clearance = self.height * np.sin(angle) - abs(self.start_x) * np.cos(angle) - 6 * self.sigma * np.cos(angle)
        if not clearance > RADIUS:
            raise ValueError(f"start_x (--start-x) +- 6 sigma must start inside the wedge at height {self.height} m")


def wedge_system(config: Config) -> sim.RigidBodySystem:
    """The ball and the two walls ``{p : n . p >= 0}`` of the wedge (inward normals)."""
    angle = np.deg2rad(config.half_angle_deg)
    planes = [((-np.cos(angle), 0.0, np.sin(angle)), 0.0), ((np.cos(angle), 0.0, np.sin(angle)), 0.0)]
    return sim.ball(
        radius=RADIUS, mass=MASS, friction=0.0, planes=planes, time_step=config.time_step,
        contact=sim.SpringDamper(stiffness=config.stiffness, damping=0.0, friction=0.0),
    )


def final_positions(system: sim.RigidBodySystem, config: Config, start):
    """The ball's ``x`` at every horizon, dropped from rest at ``(start, 0, height)``."""
    zero = jnp.zeros_like(start)
    q = jnp.concatenate([jnp.stack([start, zero, zero + config.height]), jnp.array([0.0, 0.0, 0.0, 1.0])])
    xs, _ = system.rollout(jnp.concatenate([q, jnp.zeros(6)]), jnp.zeros((max(config.horizons), 3)))
    return xs[np.asarray(config.horizons), 0]


def run(config: Config, out: Path | str, key, progress: bool = True) -> dict:
    """Runs the experiment, writes metrics.json and chaos.png under `out`, returns the metrics."""
    out = Path(out)
    system = wedge_system(config)
    compiled = _landscape.value_and_derivative(lambda _, x: final_positions(system, config, x))
    batch = (config.repeats, config.num_samples)
    offsets = np.linspace(-6 * config.sigma, 6 * config.sigma, config.repeats * config.num_samples)
    times = np.asarray(config.horizons) * config.time_step
    metrics: dict = {
        "half_angle_deg": config.half_angle_deg, "height": config.height, "start_x": config.start_x,
        "stiffness": config.stiffness, "time_step": config.time_step, "horizons": list(config.horizons),
        "horizon_times": times, "sigma": config.sigma, "num_samples": config.num_samples, "repeats": config.repeats,
    }
    with tqdm(total=4, desc="chaos", disable=not progress) as bar:
        values, derivatives = _landscape.evaluate_in_batches(compiled, 0.0, config.start_x + offsets, batch)
        bar.update()
        x0 = jnp.asarray(config.start_x)
        for name, estimator, options in (
            ("first", rsmooth.first_order, {"value_and_jacobian": lambda x: compiled(0.0, x)}),
            # Leave-one-out needs no evaluation at x: every batch has the same shape.
            ("zeroth", rsmooth.zeroth_order, {"baseline": "leave-one-out"}),
            ("alpha", rsmooth.alpha_order, {"value_and_jacobian": lambda x: compiled(0.0, x), "baseline": "leave-one-out",
                                            "rule": "inverse_variance"}),
        ):
            key, subkey = jax.random.split(key)
            d = diagnostics.estimator_bias_variance(
                estimator, lambda x: compiled(0.0, x)[0], subkey, x0, repeats=config.repeats, sigma=config.sigma, num_samples=config.num_samples,
                **options)
            per_sample = np.asarray(d.reported_std_error) ** 2 * config.num_samples  # (repeats, horizons)
            grads = np.asarray(d.grads)
            metrics[name] = {
                "per_sample_variance": _landscape.mean_and_spread(per_sample),
                "mean": grads.mean(0),
                "std": grads.std(0, ddof=1),
            }
            if name == "alpha":
                metrics[name]["weight"] = np.asarray(d.stats["alpha_entries"]).reshape(config.repeats, -1).mean(0)
            bar.update()
    median_derivative = np.median(np.abs(derivatives), axis=0)
    # After the first bounce the derivative grows as exp(lambda t); before it, it is 1.
    grown = median_derivative > 2.0
    lyapunov = float(np.polyfit(times[grown], np.log(median_derivative[grown]), 1)[0]) if grown.sum() >= 2 else float("nan")
    value_range = np.ptp(values, axis=0)
    metrics.update({
        "landscape_offsets": offsets,
        "landscape_final_x": values.T,
        "exact_derivative_median": median_derivative,
        "lyapunov_exponent": lyapunov,
        "value_range": value_range,
        "zeroth_variance_bound": value_range**2 / config.sigma**2,
        "first_over_zeroth_variance": np.asarray(metrics["first"]["per_sample_variance"]["mean"])
        / np.asarray(metrics["zeroth"]["per_sample_variance"]["mean"]),
    })
    _plot(metrics, values, out / "chaos.png")
    viz.write_metrics(out / "metrics.json", metrics)
    return metrics


def _plot(metrics: dict, values: np.ndarray, path: Path) -> None:
    times = np.asarray(metrics["horizon_times"])
    fig, (ax_land, ax_var, ax_der) = viz.plt.subplots(1, 3, figsize=(17, 4.6))
    colors = viz.plt.cm.viridis(np.linspace(0.1, 0.85, len(times)))
    starts = metrics["start_x"] + np.asarray(metrics["landscape_offsets"])
    for column, (t, color) in enumerate(zip(times, colors)):
        ax_land.plot(starts, values[:, column], color=color, lw=0.8, label=f"t = {t:g} s")
    ax_land.axvspan(metrics["start_x"] - metrics["sigma"], metrics["start_x"] + metrics["sigma"], color="gray", alpha=0.15,
                    label=r"start $\pm\sigma$")
    ax_land.set_xlabel("start x (m)")
    ax_land.set_ylabel("final x (m)")
    ax_land.set_title(f"ball in a wedge ({metrics['half_angle_deg']:g} deg walls): final x against the start")
    ax_land.legend(fontsize=7)
    for name, color, marker in (("first", "tab:orange", "o"), ("zeroth", "tab:blue", "x"), ("alpha", "tab:green", "s")):
        stats = metrics[name]["per_sample_variance"]
        mean, low, high = (np.asarray(stats[k]) for k in ("mean", "q16", "q84"))
        ax_var.errorbar(times, mean, yerr=[np.maximum(mean - low, 0), np.maximum(high - mean, 0)], fmt=marker + "-",
                        color=color, capsize=3, label=f"{name} order (mean, 16-84 %)")
    ax_var.plot(times, metrics["zeroth_variance_bound"], ":", color="tab:blue", label=r"range$^2/\sigma^2$")
    ax_var.set_yscale("log")
    ax_var.set_xlabel("horizon (s)")
    ax_var.set_title(f"per-sample variance of the gradient (sigma = {metrics['sigma']:g} m)")
    ax_var.legend(fontsize=7)
    ax_der.semilogy(times, metrics["exact_derivative_median"], "k.-", label="median |d x_T / d x_0| over the sweep")
    if np.isfinite(metrics["lyapunov_exponent"]):
        ax_der.set_title(f"exact derivative: fitted exponent {metrics['lyapunov_exponent']:.2f} / s")
    ax_der.set_xlabel("horizon (s)")
    ax_der.legend(fontsize=7)
    fig.tight_layout()
    viz.save_figure(fig, path)


def summary(metrics: dict) -> dict:
    """The lines printed after a run: per-sample variances at the first and last horizon."""
    first, zeroth = metrics["first"]["per_sample_variance"]["mean"], metrics["zeroth"]["per_sample_variance"]["mean"]
    t0, t1 = metrics["horizon_times"][0], metrics["horizon_times"][-1]
    return {
        f"per-sample variance, first order, t = {t0:g} -> {t1:g} s": f"{first[0]:.3g} -> {first[-1]:.3g}",
        f"per-sample variance, zeroth order, t = {t0:g} -> {t1:g} s": f"{zeroth[0]:.3g} -> {zeroth[-1]:.3g}",
        "fitted exponent of the exact derivative (1/s)": f"{metrics['lyapunov_exponent']:.3g}",
        f"alpha order's first-order weight, t = {t0:g} -> {t1:g} s":
            f"{metrics['alpha']['weight'][0]:.2f} -> {metrics['alpha']['weight'][-1]:.2f}",
    }


EXPERIMENT = _protocol.Experiment(
    command=("experiment", "chaos"),
    name="chaos",
    config=Config,
    run=run,
    summary=summary,
    help="A ball bouncing in a wedge under gravity (a chaotic billiard): over growing horizons the variance of the "
    "first-order gradient explodes with the exact derivative, the zeroth-order one stays bounded (Suh et al. 2022).",
    metrics_doc=METRICS_DOC,
)
