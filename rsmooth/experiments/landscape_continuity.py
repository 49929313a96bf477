r"""Experiment: where contact makes the final state jump, and what smoothing makes of it.

A point in frictional contact with one half-plane ends in a state that is continuous in its
initial condition, kinks and all; the jumps come from geometry, when a change of the initial
condition changes which face is hit first or which face a body comes to rest on (Suh,
Simchowitz, Zhang, Tedrake, "Do differentiable simulators give better policy gradients?", ICML
2022, Sec. 3: discontinuities bias the first-order estimate; Pang, Suh, Yang, Tedrake, "Global
planning for contact-rich manipulation via local smoothing", T-RO 2023). Three cases, each the
final ``x`` of a body under the simulator's hard contact (:mod:`rsmooth.sim`) against a 1-D sweep
of its initial condition:

* ``half-plane``: a ball thrown at ``speed`` from ``throw_height`` at an angle (the sweep) onto
  the floor, where friction stops it: continuous.
* ``corner``: the same throw toward a wall at ``wall_distance`` (:func:`rsmooth.sim.ball_wall`).
  A ball that lands first slides into the wall and stops there; one that meets the wall first
  is spun by the wall's friction and, once it lands, rolls back. Between the two the final
  ``x`` drops by about half the distance to the wall within a degree or two of the throw: a
  jump at the resolution of the sweep (time stepping spreads it over those throws whose
  impacts fall in the same steps: resolved to hundredths of a degree, it is continuous).
* ``edge``: a cube (:func:`rsmooth.sim.cube`) dropped onto one of its edges at a tilt (the
  sweep): it comes to rest on one face or on the other, and its final ``x`` jumps by about its
  side at 45 degrees (only tilts within a vanishing distance of 45 degrees, exponentially small
  in the horizon, have not fallen yet).

Whether a landscape jumps at the scale of the sweep is measured by halving its resolution:
the largest change between every other point is twice the largest change between neighbours
where the landscape is Lipschitz at that scale, and the same where it jumps. Each landscape is
shown with its randomized smoothing, the mean of the final ``x`` under Gaussian noise of each
``sigma`` on the initial condition (:func:`rsmooth.diagnostics.smoothed_landscape`, the same
noise at every point of the sweep): the jumps become slopes no steeper than
``range / (sigma sqrt(2 pi))``, the bound of the derivative of a Gaussian smoothing of a
function whose values span ``range``.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from rsmooth import _checks, diagnostics, sim, viz
from rsmooth.experiments import _protocol

CASES = ("half-plane", "corner", "edge")
CUBE_SIDE = 0.2  # m, sim.cube's default
DROP = 0.05  # m: the cube's lowest edge starts this high above the floor
FAR = 1e3  # m: the wall of the half-plane case, out of reach

METRICS_DOC = """metrics.json keys: cases, sigmas_deg, num_samples, steps, speed (m/s), throw_height (m),
wall_distance (m); per case C: C.sweep_deg (the initial angle: the throw's elevation, or the
cube's tilt), C.final_x (the final x of the ball or of the cube's centre, m), C.raw_max_jump
(largest |change| of final_x between neighbouring sweep points, m), C.raw_max_slope (the same over
the sweep step, m/deg), C.raw_refinement_ratio (the largest change between every other point over
raw_max_jump: about 2 where the landscape is Lipschitz at the scale of the step, about 1 where it
jumps), C.range (max - min of final_x, m), and per sigma 'sigma=S': smoothed (Monte-Carlo mean of
the final x), std_error, max_jump, max_slope (m/deg), refinement_ratio (of the smoothed curve, as
for the raw one), slope_bound (range / (S sqrt(2 pi)), the largest slope of the exact smoothing,
m/deg)."""


@dataclasses.dataclass(frozen=True)
class Config:
    cases: tuple[str, ...] = _protocol.option(CASES, "Cases to run.", flag="case", choices=CASES)
    sigmas_deg: tuple[float, ...] = _protocol.option(
        (1.0, 3.0, 10.0), "Standard deviations of the Gaussian noise on the initial angle, degrees.", flag="sigma",
        above=0.0)
    num_samples: int = _protocol.option(32, "Monte-Carlo samples per point of the smoothed landscapes.",
                                        flag="samples", min=2)
    points: int = _protocol.option(120, "Points of each sweep (an even number keeps 45 degrees, where the cube "
                                   "balances on its edge, between two of the default tilts).", min=3)
    steps: int = _protocol.option(100, "Time steps of 10 ms.", min=1)
    speed: float = _protocol.option(2.0, "Speed of the ball's throw, m/s.", above=0.0)
    throw_height: float = _protocol.option(0.35, "Height of the ball's centre at the throw, m.", above=0.05)
    wall_distance: float = _protocol.option(0.6, "Distance of the wall in the corner case, m.", above=0.05)
    throw_range_deg: tuple[float, float] = _protocol.option(
        (-60.0, 60.0), "Sweep of the throw's elevation: first and last angle, degrees.", min=-89.0, max=89.0)
    tilt_range_deg: tuple[float, float] = _protocol.option(
        (25.0, 65.0), "Sweep of the cube's tilt about y: first and last angle, degrees.", min=0.0, max=90.0)

    @classmethod
    def quick(cls) -> "Config":
        return cls(sigmas_deg=(2.0, 8.0), num_samples=16, points=32)

    def __post_init__(self):
        _protocol.check_options(self)
        if not self.cases or len(set(self.cases)) != len(self.cases):
            raise ValueError(f"cases (--case) must name distinct cases, at least one, got {self.cases}")
        if not self.sigmas_deg:
            raise ValueError("sigmas_deg (--sigma) needs at least one noise level")
        for name in ("throw_range_deg", "tilt_range_deg"):
            low, high = getattr(self, name)
            if not low < high:
                raise ValueError(f"{name} must be increasing, got {(low, high)}")


def ball_final_x(system: sim.RigidBodySystem, config: Config, wall, angle):
    """The ball's final ``x`` after a throw at elevation ``angle`` (rad), with the wall at
    ``x = wall`` (both may be traced)."""
    system = eqx.tree_at(lambda s: s.geometry.plane_offsets, system, jnp.stack([jnp.zeros_like(wall), -wall]))
    q = jnp.array([0.0, 0.0, config.throw_height, 0.0, 0.0, 0.0, 1.0])
    velocity = config.speed * jnp.stack([jnp.cos(angle), jnp.zeros_like(angle), jnp.sin(angle)])
    xs, _ = system.rollout(jnp.concatenate([q, velocity, jnp.zeros(3)]), jnp.zeros((config.steps, 3)))
    return xs[-1, 0]


def cube_final_x(system: sim.RigidBodySystem, config: Config, tilt):
    """The cube's final centre ``x`` when dropped at rest, rotated by ``tilt`` (rad) about
    ``y``, its lowest edge ``DROP`` above the floor."""
    half = 0.5 * CUBE_SIDE
    lowest = half * (jnp.abs(jnp.cos(tilt)) + jnp.abs(jnp.sin(tilt)))  # centre height of the lowest edge's contact
    zero = jnp.zeros_like(tilt)
    q = jnp.concatenate([jnp.stack([zero, zero, lowest + DROP]),
                         jnp.stack([zero, jnp.sin(0.5 * tilt), zero, jnp.cos(0.5 * tilt)])])
    xs, _ = system.rollout(jnp.concatenate([q, jnp.zeros(6)]), jnp.zeros((config.steps, 6)))
    return xs[-1, 0]


def _landscapes(config: Config, key):
    """Yields ``(case, sweep_deg, unsmoothed (N,), smoothed (S, N), std_error (S, N))``: one
    compiled program per system (the two ball cases differ only in where the wall is; the
    noise level is an argument), called once per noise level."""
    ball = sim.ball_wall(wall_distance=config.wall_distance)
    cube = sim.cube()

    def ball_sweep(key, wall, angles, sigma):
        f = lambda a: ball_final_x(ball, config, wall, a)  # noqa: E731
        return diagnostics.smoothed_landscape(f, key, angles, sigma=sigma, num_samples=config.num_samples)

    def cube_sweep(key, angles, sigma):
        f = lambda a: cube_final_x(cube, config, a)  # noqa: E731
        return diagnostics.smoothed_landscape(f, key, angles, sigma=sigma, num_samples=config.num_samples)

    ball_program = _checks.jit_checked_on_host(ball_sweep, "the continuity experiment (ball)")
    cube_program = _checks.jit_checked_on_host(cube_sweep, "the continuity experiment (cube)")
    throws = np.linspace(*config.throw_range_deg, config.points)
    tilts = np.linspace(*config.tilt_range_deg, config.points)
    runs = {
        "half-plane": (throws, lambda k, a, s: ball_program(k, jnp.asarray(FAR), a, s)),
        "corner": (throws, lambda k, a, s: ball_program(k, jnp.asarray(config.wall_distance), a, s)),
        "edge": (tilts, cube_program),
    }
    for case in config.cases:
        key, subkey = jax.random.split(key)
        sweep_deg, program = runs[case]
        angles = jnp.deg2rad(jnp.asarray(sweep_deg))
        # The same noise at every level (common random numbers): the curves differ by sigma only.
        landscapes = [program(subkey, angles, jnp.deg2rad(jnp.asarray(sigma))) for sigma in config.sigmas_deg]
        yield (case, sweep_deg, np.asarray(landscapes[0].unsmoothed),
               np.stack([np.asarray(s.value) for s in landscapes]), np.stack([np.asarray(s.std_error) for s in landscapes]))


def _jumps(sweep_deg: np.ndarray, values: np.ndarray) -> tuple[float, float, float]:
    """The largest change between neighbouring sweep points, that over the sweep step, and the
    largest change between every other point over the first: halving the step halves the
    changes of a Lipschitz landscape (ratio 2) and leaves a jump as it is (ratio 1)."""
    jumps = np.abs(np.diff(values))
    coarse = np.abs(values[2:] - values[:-2])
    return float(jumps.max()), float((jumps / np.diff(sweep_deg)).max()), float(coarse.max() / jumps.max())


def run(config: Config, out: Path | str, key, progress: bool = True) -> dict:
    """Runs the cases, writes metrics.json and continuity.png under `out`, returns the metrics."""
    out = Path(out)
    metrics: dict = {
        "cases": list(config.cases), "sigmas_deg": list(config.sigmas_deg), "num_samples": config.num_samples,
        "steps": config.steps, "speed": config.speed, "throw_height": config.throw_height,
        "wall_distance": config.wall_distance,
    }
    fig, axes = viz.plt.subplots(1, len(config.cases), figsize=(6 * len(config.cases), 4.6), squeeze=False)
    colors = viz.plt.cm.plasma(np.linspace(0.15, 0.8, len(config.sigmas_deg)))
    with tqdm(total=len(config.cases), desc="continuity", disable=not progress) as bar:
        for ax, (case, sweep_deg, raw, smoothed, std_error) in zip(axes[0], _landscapes(config, key)):
            raw_jump, raw_slope, raw_ratio = _jumps(sweep_deg, raw)
            value_range = float(np.ptp(raw))
            entry: dict = {"sweep_deg": sweep_deg, "final_x": raw, "raw_max_jump": raw_jump, "raw_max_slope": raw_slope,
                           "raw_refinement_ratio": raw_ratio, "range": value_range}
            ax.plot(sweep_deg, raw, "k.-", lw=1, ms=3, label="final x")
            for sigma, values, errors, color in zip(config.sigmas_deg, smoothed, std_error, colors):
                jump, slope, ratio = _jumps(sweep_deg, values)
                entry[f"sigma={sigma:g}"] = {
                    "smoothed": values, "std_error": errors, "max_jump": jump, "max_slope": slope, "refinement_ratio": ratio,
                    "slope_bound": value_range / (sigma * np.sqrt(2 * np.pi)),
                }
                ax.plot(sweep_deg, values, color=color, label=f"smoothed, sigma = {sigma:g} deg")
                ax.fill_between(sweep_deg, values - errors, values + errors, color=color, alpha=0.2)
            metrics[case] = entry
            ax.set_title(f"{case}: largest step {raw_jump:.3g} m (x{raw_ratio:.2f} at half the resolution)")
            ax.set_xlabel("tilt of the cube (deg)" if case == "edge" else "elevation of the throw (deg)")
            ax.set_ylabel(f"final x after {config.steps} steps (m)")
            ax.legend(fontsize=7)
            bar.update()
    fig.tight_layout()
    viz.save_figure(fig, out / "continuity.png")
    viz.write_metrics(out / "metrics.json", metrics)
    return metrics


def summary(metrics: dict) -> dict:
    """The lines printed after a run: whether each landscape jumps, raw and smoothed."""
    lines = {}
    for case in metrics["cases"]:
        entry = metrics[case]
        smoothed = ", ".join(f"{entry[f'sigma={s:g}']['refinement_ratio']:.2f}" for s in metrics["sigmas_deg"])
        lines[f"{case}: refinement ratio (2: continuous, 1: a jump), raw; smoothed per sigma"] = (
            f"{entry['raw_refinement_ratio']:.2f}; {smoothed}")
    return lines


EXPERIMENT = _protocol.Experiment(
    command=("experiment", "continuity"),
    name="continuity",
    config=Config,
    run=run,
    summary=summary,
    help="The final state against the initial condition under hard contact: continuous for a ball thrown onto a "
    "half-plane, jumping where the ball reaches a corner first or a cube dropped on its edge lands on one face or the "
    "other; and its randomized smoothing at several noise levels.",
    metrics_doc=METRICS_DOC,
)
