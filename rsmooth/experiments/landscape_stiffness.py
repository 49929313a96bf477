r"""Experiment: stiff contact makes first-order gradients noisy, and a step makes them wrong.

Suh, Simchowitz, Zhang and Tedrake ("Do differentiable simulators give better policy
gradients?", ICML 2022, Sec. 3) explain when the first-order (pathwise) estimate of a smoothed
gradient is worse than the zeroth-order (score-function) one. This experiment measures two of
their cases.

**A ball against a compliant wall.** A 1 kg ball (:func:`rsmooth.sim.ball`, no gravity, no
friction) starts at ``x`` and moves at ``speed`` toward a wall; the contact is the simulator's
spring-damper law (:class:`rsmooth.sim.SpringDamper`) of stiffness ``k`` and damping ratio
``damping_ratio`` (``d = 2 zeta sqrt(k m)``, so the coefficient of restitution is the same at
every ``k``). The damping ratio is 0 by default: the law's damper acts from the first step of
penetration with the force ``d |v|`` at zero depth, so with damping the velocity after the
bounce jumps wherever a change of the start moves the first contact step, and those jumps
bias the first-order estimate on their own (``--damping-ratio 0.1`` shows it); a pure spring
keeps the landscape continuous and isolates stiffness.

The objective is the ball's velocity after ``steps`` steps of 10 ms as a function of the start
``x``. From starts that reach the wall early the ball has bounced back; from the others it still
flies toward the wall: in between is a ramp as wide as the distance the ball travels during one
contact, ``speed pi sqrt(m / k)``, whose slope grows as ``sqrt(k)``. The smoothed gradient at
the nominal start is estimated ``repeats`` times with ``num_samples`` samples each: the
per-sample variance of the first-order estimate (the mean of exact gradients, autodiff through
the simulator) grows with ``k``, as the squared slope times the chance of landing on the ramp;
that of the zeroth-order estimate (with the leave-one-out baseline) stays below the squared
range of the velocity over ``sigma^2``. The alpha-order estimate (:func:`rsmooth.alpha_order`,
half of the samples to each of the two) is measured beside them, with the alpha it chose, by
Suh et al.'s rule (``alpha``) and with weights chosen on independent folds of its samples
(``alpha-cross-fit``: weights chosen from the samples they blend are correlated with them, and
at a stiff contact that biases the blend). All are compared with the true smoothed gradient,
by quadrature over the landscape (Stein's identity: values only).

**Policy optimization at each stiffness.** The same ball and wall; the policy is one push in
the first step that changes the ball's speed by ``theta`` (m/s). The cost is the final velocity
over ``speed`` (+1 while the ball has not reached the wall, -1 once it has bounced back) plus
the effort ``(effort / 2) (theta / push_sigma)^2``. From ``push_start`` (slower: the ball stops
short of the wall in time) each estimator (first, zeroth, alpha order by Suh et al.'s rule and
cross-fitted) runs :func:`rsmooth.control.optimize_policy` (Adam, ``policy_samples`` rollouts
per iteration, one compiled step shared by the estimators, the same key per seed for all) for
``policy_iterations`` iterations, over
``policy_seeds`` seeds. What is optimized is the smoothed cost ``J_sigma``; it is measured
exactly, by a Gaussian average over a fine grid of the true cost, at every final ``theta``,
and each run's *gap* is ``J_sigma(theta_N) - min J_sigma``. Suh et al. predict first order
ahead on soft contact (low variance), zeroth order ahead on stiff contact (the first-order
estimate's spikes), and alpha order never behind the better of the two beyond noise; the
metrics say whether it is so here. (Suh et al.'s alpha, chosen from the samples it blends, is
biased here at stiff contact: it stops short of the optimum, on the wall's side.)

**The soft step.** ``f(x) = clip(x / w + 1/2, 0, 1)``, a ramp of width ``w``, smoothed with
``sigma``: its smoothed gradient at 0 is ``(Phi(w / 2 sigma) - Phi(-w / 2 sigma)) / w``, the
Gaussian density ``1 / (sigma sqrt(2 pi))`` as ``w -> 0``. The first-order estimate is unbiased,
but once ``w`` is so small that none of its samples lands on the ramp it is exactly 0 and
reports a variance of 0: its spread over repeats cannot reveal the error; a bias test against
the zeroth-order estimate (:func:`rsmooth.diagnostics.bias_test`) does.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.stats import norm
from tqdm.auto import tqdm

import rsmooth
from rsmooth import _checks, control, diagnostics, sim, viz
from rsmooth.experiments import _landscape, _protocol

MASS = 1.0  # kg
# alpha-cross-fit: alpha order whose weights come from independent folds of its samples
# (rsmooth.alpha_order's cross_fit), beside Suh et al.'s rule.
ESTIMATORS = ("first", "zeroth", "alpha", "alpha-cross-fit")
ESTIMATOR_STYLES = (("first", "tab:orange", "o"), ("zeroth", "tab:blue", "x"), ("alpha", "tab:green", "s"),
                    ("alpha-cross-fit", "tab:red", "^"))
RADIUS = 0.05  # m
TIME_STEP = 0.01  # s

METRICS_DOC = """metrics.json keys: stiffnesses (N/m), damping_ratio, speed (m/s), wall_distance (m),
steps, sigma (m), num_samples, repeats; per stiffness 'k=K': contact_width (speed pi sqrt(m/k) /
sqrt(1 - zeta^2), the width of the ramp, m), landscape_offsets and landscape_velocity (the final
velocity against the start offset from x = 0), true_gradient (the smoothed gradient at x = 0 by
quadrature), and for E in first, zeroth, alpha, alpha-cross-fit: E.per_sample_variance (mean, std, median, q16, q84 over
the repeats of num_samples x the estimate's reported variance), E.empirical_variance (variance of
the estimates across repeats x num_samples), E.mean, E.median (the typical estimate: below the
mean in magnitude where few samples reach a stiff ramp, Suh et al.'s empirical bias), E.bias (mean - true_gradient),
E.bias_std_error, E.rmse (over repeats, against true_gradient), E.zero_fraction, E.mean_alpha (the
alpha chosen, mean over repeats: 1 for first, 0 for zeroth);
first_variance_growth (first-order per-sample variance at the largest stiffness over the smallest),
zeroth_variance_growth (the same for zeroth order), zeroth_variance_bound (the squared range of
the landscape over sigma^2). soft_step: widths (w / sigma), sigma, num_samples, repeats,
true_gradient (closed form per width), no_sample_on_ramp (closed-form probability (1 - p)^M),
and per estimator E in first, zeroth: E.mean, E.std (over repeats), E.zero_fraction,
E.reported_variance_median, E.bias; detected_vs_zeroth and detected_vs_closed_form (fraction of
repeats whose first-order estimate the bias test flags, at level delta), delta. policy (absent with
--policy-seeds 0): push_sigma (m/s), push_start (m/s), effort, num_samples, iterations,
learning_rate, seeds, and per stiffness 'k=K': grid_theta and grid_cost (the true cost against the
push), optimum_theta and optimum_cost (the minimum of the smoothed cost J_sigma), start_cost
(J_sigma at push_start), and for E in first, zeroth, alpha, alpha-cross-fit: E.final_theta and E.gap (per seed;
gap = J_sigma(final theta) - optimum_cost), E.gap_mean, E.gap_std, E.gap_median, E.came_back_rate
(fraction of seeds whose final push makes the ball bounce back: final velocity < 0),
E.mean_alpha; best (the estimator of lowest gap_mean) and, for A in alpha, alpha-cross-fit,
A.within_noise (A's gap_mean is at most the better of first and zeroth's plus twice their
combined standard error)."""


@dataclasses.dataclass(frozen=True)
class Config:
    stiffnesses: tuple[float, ...] = _protocol.option(
        (1e1, 1e2, 1e3, 1e4), "Contact stiffnesses k of the wall, N/m (below 4 m / h^2 = 4e4, where the explicit "
        "spring of the 10 ms step stays stable).", flag="stiffness", above=0.0, below=4e4)
    damping_ratio: float = _protocol.option(0.0, "Damping ratio zeta of the contact, d = 2 zeta sqrt(k m).", min=0.0, below=1.0)
    speed: float = _protocol.option(1.0, "Initial speed of the ball toward the wall, m/s.", above=0.0)
    steps: int = _protocol.option(100, "Time steps of 10 ms.", min=1)
    lead: float = _protocol.option(
        0.05, "From the nominal start x = 0, the ball reaches the wall this long before the end of the rollout, s.",
        above=0.0)
    sigma: float = _protocol.option(0.1, "Standard deviation of the Gaussian noise on the start, m.", above=0.0)
    num_samples: int = _protocol.option(
        64, "Samples per gradient estimate (a multiple of 4, >= 8: cross-fitted alpha order splits them in four).",
        flag="samples", min=8)
    repeats: int = _protocol.option(16, "Independent estimates per stiffness (their mean and spread).", min=2)
    soft_step_widths: tuple[float, ...] = _protocol.option(
        (1.0, 0.3, 0.1, 0.03, 0.01, 3e-3, 1e-3, 1e-4), "Widths w / sigma of the soft steps.", flag="soft-step-width",
        above=0.0)
    soft_step_repeats: int = _protocol.option(200, "Independent estimates per soft step.", min=2)
    delta: float = _protocol.option(0.05, "Level of the bias test.", above=0.0, below=1.0)
    policy_seeds: int = _protocol.option(
        8, "Seeds of the policy optimization per stiffness and estimator (0 skips the study).", min=0)
    policy_iterations: int = _protocol.option(60, "Adam iterations of each policy optimization.", min=1)
    policy_samples: int = _protocol.option(8, "Rollouts per policy-gradient estimate (a multiple of 4, >= 8).", min=8)
    policy_learning_rate: float = _protocol.option(0.02, "Adam's step size on the push, m/s.", above=0.0)
    push_sigma: float = _protocol.option(0.05, "Standard deviation of the noise on the push, m/s.", above=0.0)
    push_start: float = _protocol.option(-0.1, "The initial push, m/s (negative: the ball slows down).")
    effort: float = _protocol.option(
        0.05, "Weight c of the push's cost (c / 2) (push / push_sigma)^2: small, so that its own gradient noise "
        "(c / push_sigma per sample) does not hide the contact's.", above=0.0)

    @classmethod
    def quick(cls) -> "Config":
        return cls(num_samples=32, repeats=8, soft_step_repeats=100, policy_seeds=2, policy_iterations=40)

    def __post_init__(self):
        _protocol.check_options(self)
        if not self.stiffnesses:
            raise ValueError("stiffnesses (--stiffness) needs at least one stiffness")
        if not self.soft_step_widths:
            raise ValueError("soft_step_widths (--soft-step-width) needs at least one width")
        for name, flag in (("num_samples", "samples"), ("policy_samples", "policy-samples")):
            if getattr(self, name) % 4:
                raise ValueError(f"{name} (--{flag}) must be a multiple of 4, got {getattr(self, name)}")
        if not self.speed + self.push_start > 0:
            raise ValueError(f"push_start (--push-start) must leave the ball moving toward the wall: speed + push_start "
                             f"> 0, got {self.speed + self.push_start:g}")
        if not self.lead < self.steps * TIME_STEP:
            raise ValueError(f"lead (--lead) must be shorter than the rollout ({self.steps * TIME_STEP:g} s), got {self.lead}")

    @property
    def wall_distance(self) -> float:
        """The wall's ``x`` (m): the ball starting at 0 touches it ``lead`` before the end."""
        return RADIUS + self.speed * (self.steps * TIME_STEP - self.lead)


def wall_system(config: Config) -> sim.RigidBodySystem:
    """The ball and the wall ``x = wall_distance`` facing ``-x``, without gravity or friction;
    its contact law is replaced per stiffness (:func:`final_velocity`)."""
    return sim.ball(
        radius=RADIUS, mass=MASS, friction=0.0, planes=[((-1.0, 0.0, 0.0), -config.wall_distance)],
        gravity=(0.0, 0.0, 0.0), time_step=TIME_STEP, contact=sim.SpringDamper(stiffness=1.0, damping=0.0, friction=0.0),
    )


def final_velocity(system: sim.RigidBodySystem, config: Config, stiffness, start):
    """The ball's velocity along ``x`` after ``steps`` steps from ``x = start`` at ``speed``,
    against a wall of contact stiffness ``stiffness`` (both may be traced)."""
    law = sim.SpringDamper(stiffness=stiffness, damping=2.0 * config.damping_ratio * jnp.sqrt(stiffness * MASS), friction=0.0)
    system = system.with_options(contact=law)
    zero = jnp.zeros_like(start)
    q = jnp.concatenate([jnp.stack([start, zero, zero]), jnp.array([0.0, 0.0, 0.0, 1.0])])
    v = jnp.array([config.speed, 0.0, 0.0, 0.0, 0.0, 0.0])
    xs, _ = system.rollout(jnp.concatenate([q, v]), jnp.zeros((config.steps, 3)))
    return xs[-1, 7]  # body-frame linear velocity = world velocity: no friction, no rotation


def soft_step(x, width):
    """A ramp from 0 to 1 of width ``width`` centred at 0."""
    return jnp.clip(x / width + 0.5, 0.0, 1.0)


def soft_step_gradient(width, sigma):
    """The closed-form gradient at 0 of the soft step smoothed by ``N(0, sigma^2)``."""
    return (norm.cdf(0.5 * width / sigma) - norm.cdf(-0.5 * width / sigma)) / width


def _stiffness_study(config: Config, key, bar) -> tuple[dict, dict]:
    system = wall_system(config)
    compiled = _landscape.value_and_derivative(lambda k, x: final_velocity(system, config, k, x))
    batch = (config.repeats, config.num_samples)
    # The landscape's grid has as many points as one batch of estimates: one compiled program.
    offsets = np.linspace(-6 * config.sigma, 6 * config.sigma, config.repeats * config.num_samples)
    x0 = jnp.zeros(())
    results, curves = {}, {}
    for k in config.stiffnesses:
        values, _ = _landscape.evaluate_in_batches(compiled, k, offsets, batch)
        truth = float(_landscape.gaussian_smoothed_gradient(offsets, values, config.sigma))
        key, k_first, k_zeroth, k_alpha, k_crossed = jax.random.split(key, 5)
        entry = {
            "contact_width": config.speed * np.pi * np.sqrt(MASS / k) / np.sqrt(1 - config.damping_ratio**2),
            "true_gradient": truth,
        }
        both = lambda x, k=k: compiled(k, x)  # noqa: E731
        estimators = {
            "first": (rsmooth.first_order, k_first, {"value_and_jacobian": both}),
            # Leave-one-out needs no evaluation at x: every batch has the same shape.
            "zeroth": (rsmooth.zeroth_order, k_zeroth, {"baseline": "leave-one-out"}),
            "alpha": (rsmooth.alpha_order, k_alpha, {"value_and_jacobian": both, "baseline": "leave-one-out"}),
            "alpha-cross-fit": (rsmooth.alpha_order, k_crossed,
                                {"value_and_jacobian": both, "baseline": "leave-one-out", "cross_fit": True}),
        }
        for name, (estimator, subkey, options) in estimators.items():
            d = diagnostics.estimator_bias_variance(
                estimator, lambda x, k=k: compiled(k, x)[0], subkey, x0, repeats=config.repeats, reference=truth,
                sigma=config.sigma, num_samples=config.num_samples, **options)
            grads = np.asarray(d.grads)
            entry[name] = {
                "per_sample_variance": _landscape.mean_and_spread(np.asarray(d.reported_variance) * config.num_samples),
                "empirical_variance": float(d.variance) * config.num_samples,
                "mean": float(d.mean),
                "median": float(np.median(grads)),
                "bias": float(np.mean(grads) - truth),
                "bias_std_error": float(d.bias_std_error),
                "rmse": float(np.sqrt(np.mean((grads - truth) ** 2))),
                "zero_fraction": float(d.zero_fraction),
                "mean_alpha": float(np.mean(np.asarray(d.stats["alpha"]))) if "alpha" in d.stats else float(name == "first"),
            }
        results[f"k={k:g}"] = entry
        curves[k] = values
        bar.update()
    return results, {"offsets": offsets, "curves": curves}


def _soft_step_study(config: Config, key) -> dict:
    sigma = 1.0
    widths = np.asarray(config.soft_step_widths) * sigma
    m = config.num_samples

    def per_width(key, width):
        f = lambda x: soft_step(x, width)  # noqa: E731
        x0 = jnp.zeros(())
        truth = soft_step_gradient(width, sigma)
        k_first, k_zeroth = jax.random.split(key)
        keys_first = jax.random.split(k_first, config.soft_step_repeats)
        keys_zeroth = jax.random.split(k_zeroth, config.soft_step_repeats)

        def one(k1, k0):
            first = rsmooth.first_order(f, k1, x0, sigma=sigma, num_samples=m)
            zeroth = rsmooth.zeroth_order(f, k0, x0, sigma=sigma, num_samples=m)
            test_zeroth = diagnostics.bias_test(first, zeroth, delta=config.delta)
            test_closed = diagnostics.bias_test(first, truth, delta=config.delta)
            return first, zeroth, test_zeroth.biased, test_closed.biased

        first, zeroth, vs_zeroth, vs_closed = jax.vmap(one)(keys_first, keys_zeroth)
        return truth, first, zeroth, vs_zeroth, vs_closed

    run = _checks.jit_checked_on_host(per_width, "the soft-step study")
    out: dict = {"widths": list(config.soft_step_widths), "sigma": sigma, "num_samples": m,
                 "repeats": config.soft_step_repeats, "delta": config.delta}
    rows: dict = {"true_gradient": [], "no_sample_on_ramp": [], "detected_vs_zeroth": [], "detected_vs_closed_form": []}
    per = {name: {"mean": [], "std": [], "zero_fraction": [], "reported_variance_median": [], "bias": []} for name in ("first", "zeroth")}
    for width, subkey in zip(widths, jax.random.split(key, len(widths))):
        truth, first, zeroth, vs_zeroth, vs_closed = run(subkey, jnp.asarray(width))
        truth = float(truth)
        p = float(norm.cdf(0.5 * width / sigma) - norm.cdf(-0.5 * width / sigma))
        rows["true_gradient"].append(truth)
        rows["no_sample_on_ramp"].append((1.0 - p) ** m)
        rows["detected_vs_zeroth"].append(float(np.mean(np.asarray(vs_zeroth))))
        rows["detected_vs_closed_form"].append(float(np.mean(np.asarray(vs_closed))))
        for name, estimate in (("first", first), ("zeroth", zeroth)):
            grads = np.asarray(estimate.grad)
            per[name]["mean"].append(float(np.mean(grads)))
            per[name]["std"].append(float(np.std(grads, ddof=1)))
            per[name]["zero_fraction"].append(float(np.mean(grads == 0.0)))
            per[name]["reported_variance_median"].append(float(np.median(np.asarray(estimate.stats["variance"]))))
            per[name]["bias"].append(float(np.mean(grads) - truth))
    out.update(rows)
    out.update(per)
    return out


# The push task's pieces are module-level functions (static parts of the problem, compared by
# identity) and its numbers live in the problem's params: every stiffness, seed, estimator and
# configuration shares one compiled solver step.
def push_policy(theta, x, t):
    """One push in the first step: a force ``theta m / h`` along ``x`` changes the speed by
    ``theta`` (m/s); no force afterwards."""
    return jnp.where(t == 0, theta[0] * MASS / TIME_STEP, 0.0) * jnp.array([1.0, 0.0, 0.0])


def _push_effort(x, u, params):
    return 0.5 * params["effort"] * (u[0] * TIME_STEP / MASS / params["push_sigma"]) ** 2


def _final_velocity_cost(x, params):
    return x[7] / params["speed"]  # the body-frame linear velocity is the world one (no rotation)


def push_problem(config: Config, stiffness) -> control.ShootingProblem:
    """The push task at contact stiffness `stiffness` (may be traced): the ball at ``x = 0``
    moving at ``speed`` toward the wall, ``steps`` steps."""
    system = wall_system(config)
    law = sim.SpringDamper(stiffness=jnp.asarray(stiffness, float),
                           damping=2.0 * config.damping_ratio * jnp.sqrt(jnp.asarray(stiffness, float) * MASS),
                           friction=jnp.asarray(0.0))
    system = system.with_options(contact=law)
    x0 = jnp.concatenate([jnp.zeros(3), jnp.array([0.0, 0.0, 0.0, 1.0]), jnp.array([config.speed, 0.0, 0.0, 0.0, 0.0, 0.0])])
    params = {name: jnp.asarray(value, float) for name, value in
              (("effort", config.effort), ("push_sigma", config.push_sigma), ("speed", config.speed))}
    return control.ShootingProblem(dynamics=system, running_cost=_push_effort, terminal_cost=_final_velocity_cost,
                                   x0=x0, horizon=config.steps, params=params)


@eqx.filter_jit
@_checks.without_traced_checks()
def _push_costs(problem: control.ShootingProblem, thetas):
    return jax.vmap(lambda theta: control.policy_cost(problem, push_policy, theta[None]))(thetas)


def _grid_costs(problem, thetas: np.ndarray, chunk: int = 512) -> np.ndarray:
    """The true cost at every push of `thetas`, in chunks of one shape (one compiled program)."""
    padded = np.concatenate([thetas, np.full((-len(thetas)) % chunk, thetas[-1])])
    costs = np.concatenate([np.asarray(_push_costs(problem, jnp.asarray(padded[i : i + chunk])))
                            for i in range(0, len(padded), chunk)])[: len(thetas)]
    _checks.check_outputs_on_host(costs, "the push task's rollouts")
    return costs


def _smoothed(grid: np.ndarray, costs: np.ndarray, points, sigma: float) -> np.ndarray:
    """``J_sigma(theta) = E J(theta + sigma z)`` at `points`: the Gaussian-weighted average of the
    grid's costs (a spacing far below sigma and a grid reaching 6 sigma beyond every point)."""
    points = np.atleast_1d(np.asarray(points, dtype=np.float64))
    weights = np.exp(-0.5 * ((grid[None, :] - points[:, None]) / sigma) ** 2)
    return weights @ costs / weights.sum(axis=1)


def _policy_study(config: Config, key, bar) -> dict:
    solvers = {
        name: control.PolicyGradient(
            estimator=name.removesuffix("-cross-fit"), sigma=config.push_sigma, num_samples=config.policy_samples,
            learning_rate=config.policy_learning_rate, iterations=config.policy_iterations, shared_samples=True,
            baseline="leave-one-out", alpha_cross_fit=name.endswith("-cross-fit"))
        for name in ESTIMATORS
    }
    theta0 = jnp.array([config.push_start])
    sigma = config.push_sigma
    search = (config.push_start - 4 * sigma, config.push_start + 12 * sigma)  # where the optimum is sought
    out: dict = {"push_sigma": sigma, "push_start": config.push_start, "effort": config.effort,
                 "num_samples": config.policy_samples, "iterations": config.policy_iterations,
                 "learning_rate": config.policy_learning_rate, "seeds": config.policy_seeds}
    seed_keys = jax.random.split(key, config.policy_seeds)
    for k in config.stiffnesses:
        problem = push_problem(config, k)
        runs = {name: [] for name in solvers}
        for seed_key in seed_keys:
            for name, solver in solvers.items():  # the same key: common random numbers
                solution = control.optimize_policy(problem, push_policy, seed_key, theta0, solver=solver)
                if solution.result != rsmooth.RESULTS.successful:
                    raise FloatingPointError(f"the {name}-order policy optimization at k = {k:g} ended non-finite")
                runs[name].append((float(solution.theta[0]), float(solution.xs[-1, 7]),
                                   float(np.mean(solution.stats["alpha"]))))
        finals = [theta for results in runs.values() for theta, _, _ in results]
        low, high = min(search[0], *finals) - 6.5 * sigma, max(search[1], *finals) + 6.5 * sigma
        grid = np.arange(low, high + sigma / 50, sigma / 50)
        costs = _grid_costs(problem, grid)
        inside = grid[(grid >= search[0]) & (grid <= search[1])]
        smoothed = _smoothed(grid, costs, inside, sigma)
        optimum = float(np.min(smoothed))
        entry: dict = {"grid_theta": grid, "grid_cost": costs, "optimum_theta": float(inside[np.argmin(smoothed)]),
                       "optimum_cost": optimum, "start_cost": float(_smoothed(grid, costs, config.push_start, sigma)[0])}
        for name, results in runs.items():
            thetas = np.array([theta for theta, _, _ in results])
            gaps = _smoothed(grid, costs, thetas, sigma) - optimum
            entry[name] = {
                "final_theta": thetas, "gap": gaps, "gap_mean": float(np.mean(gaps)),
                "gap_std": float(np.std(gaps, ddof=1)) if len(gaps) > 1 else 0.0, "gap_median": float(np.median(gaps)),
                "came_back_rate": float(np.mean([velocity < 0 for _, velocity, _ in results])),
                "mean_alpha": float(np.mean([alpha for _, _, alpha in results])),
            }
        means = {name: entry[name]["gap_mean"] for name in solvers}
        entry["best"] = min(means, key=means.get)
        better = min(("first", "zeroth"), key=means.get)
        std_error = lambda name: entry[name]["gap_std"] / np.sqrt(len(seed_keys))  # noqa: E731
        for name in ("alpha", "alpha-cross-fit"):
            entry[name]["within_noise"] = bool(
                means[name] <= means[better] + 2 * np.hypot(std_error(name), std_error(better)))
        out[f"k={k:g}"] = entry
        bar.update()
    return out


def run(config: Config, out: Path | str, key, progress: bool = True) -> dict:
    """Runs both studies, writes metrics.json, stiffness.png and soft_step.png under `out`."""
    out = Path(out)
    key_stiff, key_step, key_policy = jax.random.split(key, 3)
    studies = 2 if config.policy_seeds else 1
    with tqdm(total=studies * len(config.stiffnesses) + 1, desc="stiffness", disable=not progress) as bar:
        results, landscape = _stiffness_study(config, key_stiff, bar)
        soft = _soft_step_study(config, key_step)
        bar.update()
        policy = _policy_study(config, key_policy, bar) if config.policy_seeds else None
    ks = list(config.stiffnesses)
    first_var = [results[f"k={k:g}"]["first"]["per_sample_variance"]["mean"] for k in ks]
    zeroth_var = [results[f"k={k:g}"]["zeroth"]["per_sample_variance"]["mean"] for k in ks]
    value_range = max(float(np.ptp(curve)) for curve in landscape["curves"].values())
    metrics: dict = {
        "stiffnesses": ks,
        "damping_ratio": config.damping_ratio,
        "speed": config.speed,
        "wall_distance": config.wall_distance,
        "steps": config.steps,
        "sigma": config.sigma,
        "num_samples": config.num_samples,
        "repeats": config.repeats,
        **results,
        "first_variance_growth": first_var[-1] / first_var[0],
        "zeroth_variance_growth": zeroth_var[-1] / zeroth_var[0],
        "zeroth_variance_bound": value_range**2 / config.sigma**2,
        "soft_step": soft,
    }
    for k in ks:
        metrics[f"k={k:g}"]["landscape_offsets"] = landscape["offsets"]
        metrics[f"k={k:g}"]["landscape_velocity"] = landscape["curves"][k]
    _plot_stiffness(metrics, landscape, out / "stiffness.png")
    _plot_soft_step(soft, out / "soft_step.png")
    if policy is not None:
        metrics["policy"] = policy
        _plot_policy(metrics, out / "policy.png")
    viz.write_metrics(out / "metrics.json", metrics)
    return metrics


def _plot_stiffness(metrics: dict, landscape: dict, path: Path) -> None:
    ks = np.asarray(metrics["stiffnesses"])
    sigma = metrics["sigma"]
    fig, (ax_land, ax_var, ax_err) = viz.plt.subplots(1, 3, figsize=(17, 4.6))
    colors = viz.plt.cm.viridis(np.linspace(0.1, 0.85, len(ks)))
    for k, color in zip(ks, colors):
        ax_land.plot(landscape["offsets"], landscape["curves"][k], color=color, label=f"k = {k:g} N/m")
    ax_land.axvline(0.0, color="gray", lw=0.8)
    ax_land.axvspan(-sigma, sigma, color="gray", alpha=0.1, label=r"nominal start $\pm\sigma$")
    ax_land.set_xlabel("start x (m)")
    ax_land.set_ylabel(f"velocity after {metrics['steps']} steps (m/s)")
    ax_land.set_title("a bounce off a compliant wall: a ramp of width ~ 1/sqrt(k)")
    ax_land.legend(fontsize=7)
    for name, color, marker in ESTIMATOR_STYLES:
        stats = [metrics[f"k={k:g}"][name]["per_sample_variance"] for k in ks]
        mean = np.array([s["mean"] for s in stats])
        low = np.array([s["q16"] for s in stats])
        high = np.array([s["q84"] for s in stats])
        ax_var.errorbar(ks, mean, yerr=[np.maximum(mean - low, 0), np.maximum(high - mean, 0)], fmt=marker + "-",
                        color=color, capsize=3, label=f"{name} order (mean, 16-84 %)")
        ax_err.loglog(ks, [metrics[f"k={k:g}"][name]["rmse"] for k in ks], marker + "-", color=color, label=f"{name} order")
    ax_var.axhline(metrics["zeroth_variance_bound"], color="tab:blue", ls=":", lw=1, label=r"range$^2/\sigma^2$")
    ax_var.set_xscale("log")
    ax_var.set_yscale("log")
    ax_var.set_xlabel("contact stiffness k (N/m)")
    ax_var.set_title(f"per-sample variance of the gradient estimate (sigma = {sigma:g} m)")
    ax_var.legend(fontsize=7)
    ax_err.set_xlabel("contact stiffness k (N/m)")
    ax_err.set_title(f"RMSE against the smoothed gradient (M = {metrics['num_samples']})")
    ax_err.legend(fontsize=7)
    fig.tight_layout()
    viz.save_figure(fig, path)


def _plot_policy(metrics: dict, path: Path) -> None:
    policy = metrics["policy"]
    ks = np.asarray(metrics["stiffnesses"])
    sigma = policy["push_sigma"]
    fig, (ax_land, ax_gap) = viz.plt.subplots(1, 2, figsize=(13, 4.6))
    colors = viz.plt.cm.viridis(np.linspace(0.1, 0.85, len(ks)))
    for k, color in zip(ks, colors):
        entry = policy[f"k={k:g}"]
        grid, costs = np.asarray(entry["grid_theta"]), np.asarray(entry["grid_cost"])
        shown = (grid >= policy["push_start"] - 4 * sigma) & (grid <= policy["push_start"] + 12 * sigma)
        ax_land.plot(grid[shown], costs[shown], color=color, lw=0.8, label=f"k = {k:g} N/m: cost")
        ax_land.plot(grid[shown], _smoothed(grid, costs, grid[shown], sigma), color=color, ls="--", lw=1.2)
        ax_land.plot(entry["optimum_theta"], entry["optimum_cost"], "*", color=color, ms=9)
    ax_land.axvline(policy["push_start"], color="gray", lw=0.8, label="start")
    ax_land.set_xlabel("push: change of speed (m/s)")
    ax_land.set_ylabel("final velocity / speed + effort")
    ax_land.set_title(rf"the push task: true cost (solid), smoothed $J_\sigma$ (dashed), its optimum (*)")
    ax_land.legend(fontsize=7)
    seeds = policy["seeds"]
    for offset, (name, color, marker) in zip((-0.09, -0.03, 0.03, 0.09), ESTIMATOR_STYLES):
        means = np.array([policy[f"k={k:g}"][name]["gap_mean"] for k in ks])
        errors = np.array([policy[f"k={k:g}"][name]["gap_std"] for k in ks]) / np.sqrt(seeds)
        ax_gap.errorbar(ks * 10**offset, means, yerr=errors, fmt=marker + "-", color=color, capsize=3,
                        label=f"{name} order: mean ± s.e. over {seeds} seeds")
    ax_gap.set_xscale("log")
    ax_gap.set_yscale("symlog", linthresh=1e-4)
    ax_gap.set_ylim(bottom=0.0)
    ax_gap.set_xlabel("contact stiffness k (N/m)")
    ax_gap.set_ylabel(r"$J_\sigma(\theta_N) - \min J_\sigma$")
    ax_gap.set_title(f"after {policy['iterations']} Adam iterations, M = {policy['num_samples']} rollouts each")
    ax_gap.legend(fontsize=7)
    fig.tight_layout()
    viz.save_figure(fig, path)


def _plot_soft_step(soft: dict, path: Path) -> None:
    widths = np.asarray(soft["widths"])
    fig, (ax_grad, ax_zero) = viz.plt.subplots(1, 2, figsize=(13, 4.6))
    ax_grad.semilogx(widths, soft["true_gradient"], "k-", lw=2, label="closed form")
    for name, color, marker in (("first", "tab:orange", "o"), ("zeroth", "tab:blue", "x")):
        mean, std = np.asarray(soft[name]["mean"]), np.asarray(soft[name]["std"])
        ax_grad.errorbar(widths, mean, yerr=std / np.sqrt(soft["repeats"]), fmt=marker + "-", color=color, capsize=3,
                         label=f"{name} order: mean ± s.e. over {soft['repeats']}")
    ax_grad.set_xlabel("ramp width w / sigma")
    ax_grad.set_ylabel("smoothed gradient at 0")
    ax_grad.set_title(f"soft step, M = {soft['num_samples']} samples per estimate")
    ax_grad.legend(fontsize=7)
    ax_zero.semilogx(widths, soft["first"]["zero_fraction"], "o-", color="tab:orange", label="first order: estimate exactly 0")
    ax_zero.semilogx(widths, soft["no_sample_on_ramp"], "k:", label=r"closed form $(1-p)^M$")
    ax_zero.semilogx(widths, soft["detected_vs_zeroth"], "s-", color="tab:green", label="bias test vs zeroth order flags it")
    ax_zero.semilogx(widths, soft["detected_vs_closed_form"], "^-", color="tab:red", label="bias test vs closed form flags it")
    ax_zero.set_ylim(-0.05, 1.05)
    ax_zero.set_xlabel("ramp width w / sigma")
    ax_zero.set_title("exact zeros with zero variance; the bias test catches them")
    ax_zero.legend(fontsize=7)
    fig.tight_layout()
    viz.save_figure(fig, path)


def summary(metrics: dict) -> dict:
    """The lines printed after a run: the variances at both ends of the stiffness range, the
    soft step's detection, and the push task's gaps at both ends."""
    ks = metrics["stiffnesses"]
    lo, hi = metrics[f"k={ks[0]:g}"], metrics[f"k={ks[-1]:g}"]
    soft = metrics["soft_step"]
    lines = {
        f"per-sample variance, first order, k = {ks[0]:g} -> {ks[-1]:g}":
            f"{lo['first']['per_sample_variance']['mean']:.3g} -> {hi['first']['per_sample_variance']['mean']:.3g}",
        f"per-sample variance, zeroth order, k = {ks[0]:g} -> {ks[-1]:g}":
            f"{lo['zeroth']['per_sample_variance']['mean']:.3g} -> {hi['zeroth']['per_sample_variance']['mean']:.3g}",
        f"soft step w/sigma = {soft['widths'][-1]:g}: first order exactly 0 / flagged by the bias test":
            f"{soft['first']['zero_fraction'][-1]:.2f} / {soft['detected_vs_zeroth'][-1]:.2f}",
    }
    policy = metrics.get("policy")
    if policy is not None:
        for k in (ks[0], ks[-1]):
            entry = policy[f"k={k:g}"]
            lines[f"push task, k = {k:g}: mean gap to the smoothed optimum, first / zeroth / alpha / cross-fitted"] = (
                " / ".join(f"{entry[name]['gap_mean']:.3g}" for name in ESTIMATORS) + f" (best: {entry['best']})")
    return lines


EXPERIMENT = _protocol.Experiment(
    command=("experiment", "stiffness"),
    name="stiffness",
    config=Config,
    run=run,
    summary=summary,
    help="A ball bouncing off a compliant wall of growing stiffness: the per-sample variance of the first-order "
    "gradient grows with k, the zeroth-order one stays bounded; a one-push policy optimized with each estimator at "
    "each k; on a soft step the first-order estimate becomes exactly 0 with 0 variance, and a bias test catches it "
    "(Suh et al. 2022).",
    metrics_doc=METRICS_DOC,
)
