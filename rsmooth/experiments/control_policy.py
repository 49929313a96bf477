r"""Experiment: a ball thrown over a wall of finite height, by first-, zeroth- and alpha-order
policy gradients (the example of Suh, Simchowitz, Zhang, Tedrake, ICML 2022).

The system (:class:`FiniteWall`): a point mass thrown in the vertical plane from the origin
at ``speed`` (an impulse in the first 10 ms step) at the angle ``theta``, the only policy
parameter; a wall of height ``wall_height`` stands at ``x = wall_distance``. A ball that meets
the wall below its top stops there and drops at its foot; a ball that lands on the floor stays
where it lands. The cost is ``-x_T``, the distance the ball ends at: throw as far as possible.
The landscape (``policy_landscape.png``): throws lower than the angle that just clears the wall
(about 54 deg by default) end at the wall (cost ``-wall_distance``, gradient 0); above it the
ball flies over and lands at ``v^2 sin(2 theta) / g``, farther the lower the throw. The cost
jumps by about 1.4 m at that edge: the best throw is just above the edge, and lower throws
are much worse.

From ``theta_0 = 70 deg`` (over the wall), the first-order estimate (the mean of exact
gradients of sampled throws) follows the slope down to the edge, does not see the jump (its
samples beyond the edge have gradient 0), crosses it and stops in the flat region: the ball
hits the wall. The zeroth-order (score-function) estimate sees the jump and stays above the
edge, at the price of a high variance. The alpha-order estimate uses the first-order one
(alpha near 1, low variance) far from the edge and, near it, where the two disagree by more
than their sampling noise explains, the zeroth-order one (alpha = 0).

Every method runs Adam for ``iterations`` steps from the same angle, with the same noise
schedule (``sigma`` multiplied by ``sigma_decay`` at every step, down to ``sigma_floor``; or
``--noise-schedule reheating``: :class:`rsmooth.schedules.Reheating`, which also raises
``sigma`` when the cost stalls), over ``seeds`` keys. A run *succeeds* when its final throw clears the wall (final true cost below
``-wall_distance``, i.e. the ball lands beyond the wall).

The system lives here rather than in :mod:`rsmooth.sim`: the simulator's ``ball_wall`` has a
wall of infinite height and its speculative contacts make every rollout continuous in the
throw (steep, but without the jump of the paper's example).
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from rsmooth import control, schedules, viz
from rsmooth.experiments import _control, _protocol

METHOD_CHOICES = ("first", "zeroth", "alpha", "all")

METRICS_DOC = """metrics.json keys: task, methods, seeds, success_criterion, speed (m/s),
wall_distance (m), wall_height (m), theta0_deg, edge_deg (the lowest throw that clears the wall,
on a 0.05 deg grid), best_cost (the lowest true cost on that grid), initial_cost, sigma,
noise_schedule, sigma_final, num_samples, alpha_rule, iterations, learning_rate, wall_time_s, and per method (first, zeroth,
alpha): final_cost_mean, final_cost_std (true cost -x_T of the final throw, over seeds),
success_rate, final_angle_deg_mean, final_angle_deg_std, mean_alpha (weight of the first-order
estimate, averaged over iterations and seeds: 1 for first, 0 for zeroth), gradient_variance (the
estimated variance of the gradient estimate, mean over iterations and seeds),
gradient_variance_median, run_time_s (all seeds, compilation included), per_seed (final_cost,
final_angle_deg, success, mean_alpha, gradient_variance). With one --method, its keys are also at
the top level."""


class FiniteWall(eqx.Module):
    """A point mass in the vertical plane, a floor ``z = 0`` and a wall of finite height.

    State ``x = [x, z, v_x, v_z]`` (``nx = 4``), input a force per unit mass ``u = [a_x, a_z]``
    (``nu = 2``); semi-implicit Euler under gravity. A step whose chord crosses the plane
    ``x = wall_distance`` below ``wall_height`` ends at the wall with ``v_x = 0`` (the ball
    then drops along it); a step that ends below the floor ends where the chord meets the
    floor, at rest (the ball stays where it lands). Both events are located on the chord, so
    the final position is continuous in the throw except where the ball grazes the top of the
    wall: there it jumps.
    """

    wall_distance: float = 1.0
    wall_height: float = 0.8
    time_step: float = 0.01
    gravity: float = 9.81
    nx: int = eqx.field(static=True, default=4)
    nu: int = eqx.field(static=True, default=2)

    def step(self, x, u):
        h, d = self.time_step, self.wall_distance
        v = x[2:] + h * (u + jnp.array([0.0, -self.gravity]))
        p = x[:2] + h * v
        crossed = (x[0] < d) & (p[0] >= d)
        s = jnp.where(crossed, (d - x[0]) / jnp.where(crossed, p[0] - x[0], 1.0), 0.0)
        hit = crossed & (x[1] + s * (p[1] - x[1]) <= self.wall_height)
        p = jnp.where(hit, jnp.stack([jnp.full_like(p[0], d), p[1]]), p)
        v = jnp.where(hit, jnp.stack([jnp.zeros_like(v[0]), v[1]]), v)
        below = p[1] < 0.0
        r = jnp.where(below, x[1] / jnp.where(below, x[1] - p[1], 1.0), 0.0)
        landing = jnp.stack([x[0] + r * (p[0] - x[0]), jnp.zeros_like(p[1])])
        p = jnp.where(below, landing, p)
        v = jnp.where(below, jnp.zeros_like(v), v)
        return jnp.concatenate([p, v])


class Throw(eqx.Module):
    """The policy: an impulse of ``speed`` (m/s) at the angle ``theta`` (rad, a scalar) in the
    first step, nothing after."""

    speed: float
    time_step: float

    def __call__(self, theta, x, t):
        magnitude = jnp.where(t == 0, self.speed / self.time_step, 0.0)
        return magnitude * jnp.stack([jnp.cos(theta), jnp.sin(theta)])


def method_option():
    return _protocol.option("all", "first, zeroth, alpha, or all (the three estimators).", choices=METHOD_CHOICES)


@dataclasses.dataclass(frozen=True)
class Config:
    method: str = method_option()
    seeds: int = _protocol.option(10, "Runs per method, keys fold_in(seed, i).", min=1)
    speed: float = _protocol.option(5.0, "Speed of the throw, m/s.", above=0.0)
    wall_distance: float = _protocol.option(1.0, "Distance of the wall from the thrower, m.", above=0.0)
    wall_height: float = _protocol.option(0.8, "Height of the wall, m.", above=0.0)
    theta0_deg: float = _protocol.option(70.0, "The initial throw's angle, degrees (over the wall).", min=0.0, max=90.0)
    horizon: int = _protocol.option(120, "Time steps of 10 ms: every throw has landed by then.", min=2)
    sigma: float = _protocol.option(0.1, "Initial noise on the throw's angle, rad.", above=0.0)
    noise_schedule: str = _protocol.option(
        "geometric", "The noise schedule: geometric decay, or reheating (rsmooth.schedules.Reheating: the sign "
        "rule on d cost / d sigma, raising the noise when the cost stalls).", choices=("geometric", "reheating"))
    sigma_decay: float = _protocol.option(0.98, "Geometric: factor of the noise at every iteration.", min=0.0, max=1.0)
    sigma_floor: float = _protocol.option(0.01, "The noise's floor, rad.", min=0.0)
    sigma_ceiling: float = _protocol.option(1.0, "Reheating: the noise's ceiling, rad.", above=0.0)
    stall_iterations: int = _protocol.option(10, "Reheating: iterations without a lower cost that make a stall.", min=1)
    num_samples: int = _protocol.option(64, "Rollouts per gradient estimate (alpha: half to each estimate).", flag="samples", min=4)
    alpha_rule: str = _protocol.option(
        "suh", "Alpha order's blend: suh (one alpha, Suh et al.) or inverse_variance (one weight per parameter; "
        "rsmooth.alpha_order's rule).", choices=("suh", "inverse_variance"))
    learning_rate: float = _protocol.option(0.02, "Adam's learning rate, rad.", above=0.0)
    iterations: int = _protocol.option(100, "Adam steps per run.", min=1)

    @classmethod
    def quick(cls, **changes) -> "Config":
        return dataclasses.replace(cls(seeds=4), **changes)

    def __post_init__(self):
        _protocol.check_options(self)

    def methods(self) -> tuple[str, ...]:
        return ("first", "zeroth", "alpha") if self.method == "all" else (self.method,)

    def solver(self, estimator: str) -> control.PolicyGradient:
        return control.PolicyGradient(
            estimator=estimator,
            sigma=self.sigma,
            num_samples=self.num_samples,
            learning_rate=self.learning_rate,
            iterations=self.iterations,
            schedule=self.schedule(),
            alpha_rule=self.alpha_rule,
        )

    def schedule(self) -> schedules.Schedule:
        if self.noise_schedule == "reheating":
            return schedules.Reheating(floor=self.sigma_floor, ceiling=self.sigma_ceiling, stall_patience=self.stall_iterations)
        return schedules.Geometric(decay=self.sigma_decay, floor=self.sigma_floor)


def _zero_running_cost(x, u):
    return jnp.zeros((), x.dtype)


def _distance_cost(x):
    return -x[0]


def build_problem(config: Config) -> tuple[control.ShootingProblem, Throw]:
    """The shooting problem (cost ``-x_T``) and the throwing policy."""
    system = FiniteWall(wall_distance=config.wall_distance, wall_height=config.wall_height)
    problem = control.ShootingProblem(system, _zero_running_cost, _distance_cost, jnp.zeros(4), config.horizon)
    return problem, Throw(speed=config.speed, time_step=system.time_step)


def landscape(problem, policy, thetas) -> np.ndarray:
    """The true cost ``V(theta)`` on a grid of angles (rad), one batched evaluation."""
    return np.asarray(jax.jit(jax.vmap(lambda th: control.policy_cost(problem, policy, th)))(jnp.asarray(thetas)))


def gaussian_smoothing(thetas: np.ndarray, values: np.ndarray, sigma: float) -> np.ndarray:
    """``E_w V(theta + sigma w)`` on the grid by quadrature (Gaussian weights on the grid,
    renormalized near its ends): the exact smoothed objective the estimators estimate, for
    the figure."""
    weights = np.exp(-0.5 * ((thetas[None, :] - thetas[:, None]) / sigma) ** 2)
    return (weights @ values) / weights.sum(axis=1)


def _run_summary(solution: control.PolicySolution, config: Config) -> dict:
    cost = float(solution.cost)
    return {
        "final_cost": cost,
        "final_angle_deg": float(np.degrees(float(solution.theta))),
        "success": bool(cost < -config.wall_distance),
        "mean_alpha": float(np.mean(solution.stats["alpha"])) if config.iterations else float("nan"),
        "gradient_variance": float(np.mean(solution.stats["variance"])) if config.iterations else float("nan"),
    }


def aggregate(runs: list[dict], solutions: list[control.PolicySolution], run_time: float, means: tuple[str, ...]) -> dict:
    """A method's metrics over its seeds: final cost, success rate, the mean and std of the
    per-seed quantities ``means`` (keys ``NAME_mean``, ``NAME_std``), alpha, the gradient
    variance, the run time and the runs (``per_seed``)."""
    costs = np.array([run["final_cost"] for run in runs])
    variances = np.concatenate([s.stats["variance"] for s in solutions])
    alphas = np.concatenate([s.stats["alpha"] for s in solutions])
    spread = {}
    for name in means:
        values = np.array([run[name] for run in runs])
        spread[f"{name}_mean"], spread[f"{name}_std"] = float(values.mean()), float(values.std())
    return {
        "final_cost_mean": float(costs.mean()),
        "final_cost_std": float(costs.std()),
        "success_rate": float(np.mean([run["success"] for run in runs])),
        **spread,
        "mean_alpha": float(alphas.mean()) if alphas.size else float("nan"),
        "gradient_variance": float(variances.mean()) if variances.size else float("nan"),
        "gradient_variance_median": float(np.median(variances)) if variances.size else float("nan"),
        "run_time_s": run_time,
        "per_seed": runs,
    }


def plot_histories(
    histories: dict[str, list[control.PolicySolution]], path: Path, cost_label: str, reference: tuple[float, str] | None = None
) -> None:
    """Per method, the true cost (mean +- std over seeds), alpha and the gradient variance
    against the iteration; ``reference``: a ``(cost, label)`` line on the cost axes."""
    fig, axes = viz.plt.subplots(1, 3, figsize=(15, 3.8))
    for index, (name, solutions) in enumerate(histories.items()):
        color = f"C{index}"
        costs = np.stack([s.stats["cost"] for s in solutions])
        mean, std = costs.mean(axis=0), costs.std(axis=0)
        steps = np.arange(costs.shape[1])
        axes[0].plot(steps, mean, color=color, label=f"{name} (mean of {len(solutions)} seeds)")
        axes[0].fill_between(steps, mean - std, mean + std, color=color, alpha=0.2)
        if costs.shape[1] > 1:  # some iterations
            alphas = np.stack([s.stats["alpha"] for s in solutions]).mean(axis=0)
            axes[1].plot(np.arange(alphas.size), alphas, color=color, label=name)
            variances = np.stack([s.stats["variance"] for s in solutions])
            axes[2].semilogy(np.arange(variances.shape[1]), np.median(variances, axis=0), color=color, label=name)
    if reference is not None:
        axes[0].axhline(reference[0], color="k", ls=":", lw=1, label=reference[1])
    axes[0].set_xlabel("iteration")
    axes[0].set_ylabel(cost_label)
    axes[0].set_title("cost (mean +- std over seeds)")
    axes[1].set_xlabel("iteration")
    axes[1].set_ylabel("alpha (weight of first order)")
    axes[1].set_ylim(-0.05, 1.05)
    axes[1].set_title("alpha (mean over seeds)")
    axes[2].set_xlabel("iteration")
    axes[2].set_ylabel("variance of the gradient estimate")
    axes[2].set_title("gradient variance (median over seeds)")
    for ax in axes:
        ax.legend(fontsize=8)
    fig.tight_layout()
    viz.save_figure(fig, path)


def run_methods(
    problem: control.ShootingProblem,
    policy,
    theta0,
    solvers: dict[str, control.PolicyGradient],
    seeds: int,
    key,
    summarize,
    means: tuple[str, ...],
    description: str,
    progress: bool = True,
) -> tuple[dict, dict]:
    """Runs every method (a name and its solver) from ``theta0`` for ``seeds`` keys
    (``fold_in(key, i)``), with one progress bar.

    ``summarize(solution, run_time)`` gives a run's metrics (with ``final_cost`` and
    ``success``). Returns ``(metrics, histories)``: per method, :func:`aggregate` of its runs
    (``means`` averaged), and its solutions."""
    metrics, histories = {}, {}
    bar = tqdm(total=len(solvers) * seeds, desc=description, disable=not progress)
    try:
        for name, solver in solvers.items():
            runs, solutions = [], []
            method_start = time.perf_counter()
            for i in range(seeds):
                bar.set_description(f"{description}: {name}, seed {i}")

                def callback(info):
                    bar.set_postfix(it=info["iteration"], cost=f"{info['cost']:.3f}", sigma=f"{info['sigma']:.3g}",
                                    alpha=f"{info['alpha']:.2f}")

                start = time.perf_counter()
                solution = control.optimize_policy(problem, policy, jax.random.fold_in(key, i), theta0, solver=solver,
                                                   callback=callback)
                solutions.append(solution)
                runs.append(summarize(solution, time.perf_counter() - start))
                bar.update()
            metrics[name] = aggregate(runs, solutions, time.perf_counter() - method_start, means)
            histories[name] = solutions
    finally:
        bar.close()
    return metrics, histories


def _plot_landscape(grid, values, config: Config, sigma_final: float, finals: dict[str, list[float]], path: Path) -> None:
    degrees = np.degrees(grid)
    fig, ax = viz.plt.subplots(figsize=(8, 4.2))
    ax.plot(degrees, values, color="k", lw=1.5, label="true V(theta) = -x_T")
    for sigma, style in ((config.sigma, "--"), (sigma_final, ":")):
        ax.plot(degrees, gaussian_smoothing(grid, values, sigma), ls=style, color="0.4",
                label=f"smoothed, sigma = {np.degrees(sigma):.1f} deg")
    ax.axvline(config.theta0_deg, color="0.6", lw=1, label="start")
    for index, (name, angles) in enumerate(finals.items()):
        ax.plot(angles, np.full(len(angles), -0.15 * (index + 1)), "|", ms=14, mew=2, color=f"C{index}",
                label=f"{name}: final angles")
    ax.set_xlabel("throw angle theta (deg)")
    ax.set_ylabel("cost (m)")
    ax.set_title("ball over a wall: the cost jumps where the throw just clears the wall")
    ax.legend(fontsize=8, loc="upper right")
    fig.tight_layout()
    viz.save_figure(fig, path)


def run(config: Config, out: Path, key, progress: bool = True) -> dict:
    """Runs each method over the seeds; writes metrics.json, policy_cost.png,
    policy_landscape.png."""
    start = time.perf_counter()
    out = Path(out)
    problem, policy = build_problem(config)
    names = config.methods()
    theta0 = jnp.asarray(np.radians(config.theta0_deg))
    grid = np.radians(np.arange(0.0, 90.0 + 1e-9, 0.05))
    values = landscape(problem, policy, grid)
    clears = values < -config.wall_distance
    edge = float(np.degrees(grid[np.argmax(clears)])) if clears.any() else float("nan")

    metrics = {
        "task": "ball over a wall (policy gradient)",
        "methods": list(names),
        "seeds": config.seeds,
        "success_criterion": "the final throw clears the wall: final true cost < -wall_distance",
        "speed": config.speed,
        "wall_distance": config.wall_distance,
        "wall_height": config.wall_height,
        "theta0_deg": config.theta0_deg,
        "edge_deg": edge,
        "best_cost": float(values.min()),
        "sigma": config.sigma,
        "noise_schedule": config.noise_schedule,
        "num_samples": config.num_samples,
        "alpha_rule": config.alpha_rule,
        "iterations": config.iterations,
        "learning_rate": config.learning_rate,
    }
    per_method, histories = run_methods(
        problem, policy, theta0, {name: config.solver(name) for name in names}, config.seeds, key,
        lambda solution, run_time: _run_summary(solution, config), ("final_angle_deg",), "control policy", progress,
    )
    metrics.update(per_method)
    first = histories[names[0]][0]
    metrics["initial_cost"] = float(first.stats["cost"][0])
    sigma_final = float(first.stats["sigma"][-1]) if config.iterations else config.sigma
    metrics["sigma_final"] = sigma_final

    plot_histories(histories, out / "policy_cost.png", "true cost -x_T (m)", (-config.wall_distance, "at the wall"))
    finals = {name: [run["final_angle_deg"] for run in metrics[name]["per_seed"]] for name in names}
    _plot_landscape(grid, values, config, sigma_final, finals, out / "policy_landscape.png")
    if len(names) == 1:
        metrics = {**metrics[names[0]], **metrics}
    metrics["wall_time_s"] = time.perf_counter() - start
    viz.write_metrics(out / "metrics.json", metrics)
    return metrics


summary = _control.summary(
    "final cost mean +- std (m), final angle (deg), mean alpha, median gradient variance",
    lambda metrics: f"{metrics['final_cost_mean']:.3f} +- {metrics['final_cost_std']:.3f}, "
    f"{metrics['final_angle_deg_mean']:.1f}, {metrics['mean_alpha']:.2f}, {metrics['gradient_variance_median']:.2g}")

EXPERIMENT = _protocol.Experiment(
    command=("control", "policy"),
    name="policy",
    config=Config,
    run=run,
    summary=summary,
    help="Policy optimization by Adam on first-, zeroth- and alpha-order estimates of the smoothed policy gradient "
    "(Suh et al., ICML 2022): throw a ball over a wall of finite height as far as possible; the first-order "
    "estimate misses the jump at the wall's top and the ball ends at the wall, zeroth and alpha order clear it.",
    metrics_doc=METRICS_DOC,
)
