r"""Experiment: policy gradients on the simulator's pusher, a box pushed by a finger through
hard frictional contact, from zero force (``rsmooth control policy-pusher``).

The system and the costs are those of ``rsmooth control pusher`` (:mod:`.control_pusher`):
``rsmooth.sim.pusher`` (a 20 cm, 1 kg box on the floor, friction 0.4; a 0.1 kg finger moving in
the horizontal plane, finger-box friction 0.5; hard contact; 10 ms steps; forces clipped to
``+-20 N``), the box at rest at the origin and the finger ``finger_gap`` behind its ``-x`` face.
The target is the box centre at ``(target_x, 0)`` with yaw 0 at the end of the horizon; the
cost is the sum of squared residuals: running ``1e-2 u``, terminal ``10 (p - p_target)`` on the
box centre and ``4 * 2 sin(yaw / 2)`` on its yaw. With ``at_rest`` the terminal cost also has
the box's velocities (weight 1), as ``rsmooth control pusher``'s; in the default 0.2 s our best
runs with it stopped about 2 cm short of the target, so by default the box may still slide at
the end. The policy is open loop, :class:`~rsmooth.control.OpenLoop`: one force ``(f_x, f_y)``
per step, ``2 T`` parameters, zero at the start. A run *succeeds* when its final box centre is
within ``position_tolerance`` of the target.

With the finger away from the box, the box's state does not depend on the forces: every exact
derivative of the box's pose with respect to them is exactly zero, and the first-order
estimate at zero force is the gradient of the control cost alone (the tests check both).
Every method runs Adam for ``iterations`` steps with the noise ``sigma`` on every force, from
zero force, over ``seeds`` keys. At the default ``sigma = 0.2 N`` the samples' fingers spread by
about 1 cm by the end of the horizon: none reaches the box 5 cm ahead, and the smoothed cost is,
to many digits, the control cost plus a constant. What happened (8 seeds, 150 iterations,
``rsmooth control policy-pusher``, key 0):

* first order, 1 of 8 runs succeeded: the estimate is the control cost's gradient plus a little
  noise, and Adam holds the forces near zero; the box never moved in 7 runs. In the other one,
  Adam's first step, which moves every force by about ``learning_rate`` whatever the size of
  the gradient (its normalization), carried the finger to the box at iteration 3; from then on
  the contact gradients pushed the box to the target.
* zeroth order, 8 of 8 succeeded (final error 12 +- 5 mm): its estimate has the same mean (no
  sample touches the box either), but a far larger variance (about ``d / M`` times the squared
  gradient, ``d = 2 T`` parameters, ``M`` samples), which Adam's normalized steps turn into a
  random walk of the forces of about ``learning_rate`` per step. The walk brought the finger
  to the box after 3 to 115 iterations; from then on the samples that touch it tell the
  estimate how a push moves the box, and it pushes the box to the target. Its success is
  exploration by its own variance, not a better estimate of the smoothed gradient.
* alpha order, 0 of 8: its two estimates agree within sampling noise (nothing touches the box;
  the smoothed cost is smooth), so it trusts the low-variance first-order one (mean alpha
  0.998) and, like first order, leaves the box where it is. The expected story, that alpha
  order sees the samples that touch the box, does not hold here: at the start none does.

``--quick`` (3 seeds, 40 iterations, about 2 minutes on 2 CPU cores) is too short for zeroth
order to reach the target; its ``push_rate`` (first 1/3, zeroth 3/3, alpha 0/3) tells the story.

With a larger noise (about 1 N per force) the samples' fingers reach the box from the first
iterations: then all three estimators see the contact and push the box, as they did in our
runs (the pusher's contact is continuous in the forces, so the first-order estimate is not
biased, unlike on the ball-over-a-wall task). ``--sigma`` sets it. A smaller ``learning_rate`` (0.3 N) keeps first
order from the box in every run but also slows zeroth order's walk (3 of 4 runs reached the box,
none the target, in 80 iterations).

All three methods share one compiled step (``PolicyGradient(shared_samples=True)``): the
reverse-mode rollout gradient through the contact solver takes 30 to 40 s to compile on 2 CPU
cores, once rather than three times. With one key, the three methods draw the same noise at
the same iteration.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np

from rsmooth import control, schedules, viz
from rsmooth.experiments import _control, _protocol, control_policy, control_pusher

METHOD_CHOICES = control_policy.METHOD_CHOICES

METRICS_DOC = """metrics.json keys: task, methods, seeds, success_criterion, target_x
(m; the box starts at x = 0), finger_gap (m), horizon (steps of 10 ms), at_rest (whether the box's final velocities are
costed), position_tolerance (m), sigma
(N, the initial noise on every force), noise_schedule (constant or reheating: floor 0.01 N), num_samples, iterations, learning_rate, initial_cost (the zero-force
policy's true cost), wall_time_s, and per method (first, zeroth, alpha): final_cost_mean,
final_cost_std (true cost of the final policy, over seeds), success_rate, push_rate (the fraction of
runs that pushed the box at all: first_push_iteration >= 0), position_error_mean,
position_error_std (final box centre to target, m), box_displacement_mean, box_displacement_std (m),
mean_alpha (weight of the first-order estimate, averaged over iterations and seeds: 1 for first, 0
for zeroth), gradient_variance (the estimated variance of the gradient estimate, mean over iterations
and seeds), gradient_variance_median, run_time_s (all seeds), per_seed (final_cost, success,
position_error, yaw_error_deg, final_box (x m, y m, yaw deg), final_speed (m/s), box_displacement (m),
max_force (N, before the simulator's +-20 N clip), first_push_iteration (the first iterate whose
true cost is 1 % below the zero-force policy's, i.e. that pushes the box toward the target; -1 if
none), mean_alpha, gradient_variance, run_time_s). With one --method, its keys are also at the top
level."""

# The relative fall of the true cost from the zero-force policy's that marks a push.
PUSH_DROP = 0.01


@dataclasses.dataclass(frozen=True)
class Config:
    method: str = control_policy.method_option()
    seeds: int = _protocol.option(8, "Runs per method, keys fold_in(seed, i).", min=1)
    target_x: float = _protocol.option(0.1, "Target box centre x, m (the box starts at 0).")
    finger_gap: float = _protocol.option(0.05, "Gap between the finger and the box's -x face at the start, m.", min=0.0)
    horizon: int = _protocol.option(20, "Time steps of 10 ms.", min=2)
    sigma: float = _protocol.option(0.2, "Noise on every force of the open-loop policy, N.", above=0.0)
    noise_schedule: str = _protocol.option(
        "constant", "The noise schedule: constant sigma, or reheating (rsmooth.schedules.Reheating: the sign rule on "
        "d cost / d sigma, raising the noise when the cost stalls).", choices=("constant", "reheating"))
    sigma_ceiling: float = _protocol.option(2.0, "Reheating: the noise's ceiling, N.", above=0.0)
    stall_iterations: int = _protocol.option(10, "Reheating: iterations without a lower cost that make a stall.", min=1)
    num_samples: int = _protocol.option(
        16, "Rollouts per gradient estimate, even (alpha: half to each estimate).", flag="samples", min=4)
    learning_rate: float = _protocol.option(0.5, "Adam's learning rate, N.", above=0.0)
    iterations: int = _protocol.option(150, "Adam steps per run.", min=1)
    position_tolerance: float = _protocol.option(0.02, "A run succeeds when the box centre ends within it of the target, m.", above=0.0)
    at_rest: bool = _protocol.option(False, "Whether the terminal cost also has the box's velocities (the box at rest).")

    @classmethod
    def quick(cls, **changes) -> "Config":
        return dataclasses.replace(cls(seeds=3, iterations=40), **changes)

    def __post_init__(self):
        _protocol.check_options(self)
        if self.num_samples % 2:
            raise ValueError(f"num_samples must be even (alpha order halves them), got {self.num_samples}")

    def methods(self) -> tuple[str, ...]:
        return ("first", "zeroth", "alpha") if self.method == "all" else (self.method,)

    def solver(self, estimator: str) -> control.PolicyGradient:
        # One compiled step for the three estimators (see the module docstring).
        return control.PolicyGradient(
            estimator=estimator,
            sigma=self.sigma,
            num_samples=self.num_samples,
            learning_rate=self.learning_rate,
            iterations=self.iterations,
            shared_samples=True,
            schedule=(schedules.Reheating(floor=0.01, ceiling=self.sigma_ceiling, stall_patience=self.stall_iterations)
                      if self.noise_schedule == "reheating" else schedules.Constant()),
        )


def build_problem(config: Config):
    """The system, the shooting problem, the open-loop policy and the target pose.

    Example:
        >>> system, problem, policy, target = build_problem(Config.quick())
        >>> problem.nx, problem.nu, problem.horizon, policy.init().shape, target
        (17, 2, 20, (20, 2), (0.1, 0.0, 0.0))
    """
    target = (config.target_x, 0.0, 0.0)
    system, problem = control_pusher.make_problem(
        target, config.horizon, finger_gap=config.finger_gap, at_rest=config.at_rest
    )
    return system, problem, control.OpenLoop(horizon=config.horizon, nu=system.nu), target


def first_push_iteration(costs) -> int:
    """The first iterate whose true cost is ``PUSH_DROP`` below the first one's, -1 if none:
    forces alone only add control cost, so the cost falls only when the box is pushed toward
    the target (by about half a millimetre at the default target)."""
    costs = np.asarray(costs)
    pushed = costs < (1.0 - PUSH_DROP) * costs[0]
    return int(np.argmax(pushed)) if pushed.any() else -1


def _run_summary(solution: control.PolicySolution, run_time: float, target, config: Config) -> dict:
    run = control_pusher.pose_metrics(solution.xs, solution.us, target)
    stats = solution.stats
    return {
        "final_cost": float(solution.cost),
        "success": bool(run["position_error"] < config.position_tolerance),
        **run,
        "mean_alpha": float(np.mean(stats["alpha"])) if config.iterations else float("nan"),
        "gradient_variance": float(np.mean(stats["variance"])) if config.iterations else float("nan"),
        "first_push_iteration": first_push_iteration(stats["cost"]),
        "run_time_s": run_time,
    }


def _plot_box_paths(histories, config: Config, path: Path) -> None:
    """The box's x (and the finger's) against time under every final policy."""
    names = list(histories)
    fig, axes = viz.plt.subplots(1, len(names), figsize=(5 * len(names), 3.8), sharey=True, squeeze=False)
    for index, (ax, name) in enumerate(zip(axes[0], names)):
        color = f"C{index}"
        for i, solution in enumerate(histories[name]):
            xs = np.asarray(solution.xs)
            time_ms = 10.0 * np.arange(xs.shape[0])
            ax.plot(time_ms, xs[:, 0], color=color, lw=1.5, alpha=0.8, label="box centre x" if i == 0 else None)
            ax.plot(time_ms, xs[:, 7], color=color, lw=0.8, ls=":", alpha=0.8, label="finger x" if i == 0 else None)
        ax.axhline(config.target_x, color="k", ls="--", lw=1, label="target")
        ax.axhspan(config.target_x - config.position_tolerance, config.target_x + config.position_tolerance,
                   color="k", alpha=0.08, label="tolerance")
        ax.set_xlabel("time (ms)")
        ax.set_title(f"{name}: final policies ({len(histories[name])} seeds)", fontsize=9)
        ax.legend(fontsize=7, loc="upper left")
    axes[0, 0].set_ylabel("x (m)")
    fig.tight_layout()
    viz.save_figure(fig, path)


def run(config: Config, out: Path, key, progress: bool = True) -> dict:
    """Runs each method over the seeds; writes metrics.json, policy_pusher_cost.png and
    policy_pusher_box_x.png."""
    start = time.perf_counter()
    out = Path(out)
    _, problem, policy, target = build_problem(config)
    names = config.methods()
    metrics = {
        "task": "pusher (policy gradient)",
        "methods": list(names),
        "seeds": config.seeds,
        "success_criterion": "the final box centre within position_tolerance of the target",
        "target_x": config.target_x,
        "finger_gap": config.finger_gap,
        "horizon": config.horizon,
        "at_rest": config.at_rest,
        "position_tolerance": config.position_tolerance,
        "sigma": config.sigma,
        "noise_schedule": config.noise_schedule,
        "num_samples": config.num_samples,
        "iterations": config.iterations,
        "learning_rate": config.learning_rate,
    }

    per_method, histories = control_policy.run_methods(
        problem, policy, policy.init(), {name: config.solver(name) for name in names}, config.seeds, key,
        lambda solution, run_time: _run_summary(solution, run_time, target, config),
        ("position_error", "box_displacement"), "control policy pusher", progress,
    )
    for name in names:  # whether a run moved the box at all: the question the estimators differ on
        runs = per_method[name]["per_seed"]
        per_method[name]["push_rate"] = float(np.mean([run["first_push_iteration"] >= 0 for run in runs]))
    metrics.update(per_method)
    metrics["initial_cost"] = float(histories[names[0]][0].stats["cost"][0])
    control_policy.plot_histories(
        histories, out / "policy_pusher_cost.png", "true cost", (metrics["initial_cost"], "zero force")
    )
    _plot_box_paths(histories, config, out / "policy_pusher_box_x.png")
    if len(names) == 1:
        metrics = {**metrics[names[0]], **metrics}
    metrics["wall_time_s"] = time.perf_counter() - start
    viz.write_metrics(out / "metrics.json", metrics)
    return metrics


summary = _control.summary(
    "runs that pushed the box, final cost mean +- std, position error (mm), mean alpha, median gradient variance",
    lambda metrics: f"{100 * metrics['push_rate']:.0f} %, {metrics['final_cost_mean']:.3f} +- {metrics['final_cost_std']:.3f}, "
    f"{1000 * metrics['position_error_mean']:.1f}, {metrics['mean_alpha']:.2f}, {metrics['gradient_variance_median']:.2g}")

EXPERIMENT = _protocol.Experiment(
    command=("control", "policy-pusher"),
    name="policy-pusher",
    config=Config,
    run=run,
    summary=summary,
    help="Policy gradients (first, zeroth, alpha order) on the pusher: open-loop finger forces push the simulator's "
    "box (hard frictional contact) to a target from zero force, the finger 5 cm behind it; the exact gradient of the "
    "box's pose is zero and no sample touches the box: first and alpha order mostly leave the box where it is, zeroth "
    "order's variance makes Adam's steps explore until it pushes.",
    metrics_doc=METRICS_DOC,
)
