"""Policy gradients on the simulator's pusher: with the finger away from the box, first and
alpha order see only the control cost and leave the box where it is; zeroth order's variance
makes it explore until its samples touch the box, and it pushes the box toward the target.

Every optimization here runs the experiment's one compiled step (shared samples; the estimator
and the number of iterations are not part of the program) and its one compiled rollout: the
reverse-mode gradient through the contact solver is what takes the time to compile.
"""

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from typer.testing import CliRunner

from rsmooth import cli, control, estimators
from rsmooth.experiments import control_policy_pusher, control_pusher
from rsmooth.noise import Gaussian

# A tiny budget: one seed, 20 iterations of 8 samples. Adam's step of 1 N (twice the default)
# makes zeroth order's walk reach the box within it for KEY (for 3 of the keys 1 to 8; for 2 of
# them first order too is carried to the box by Adam's first, sign-like step: the experiment's
# success rates over seeds report such runs).
CONFIG = control_policy_pusher.Config(
    seeds=1, horizon=20, sigma=0.1, num_samples=8, iterations=20, learning_rate=1.0, target_x=0.1, at_rest=False
)
KEY = jax.random.key(8)
PER_METHOD = (
    "final_cost_mean", "final_cost_std", "success_rate", "push_rate", "position_error_mean", "box_displacement_mean",
    "mean_alpha", "gradient_variance", "gradient_variance_median", "run_time_s", "per_seed",
)


@pytest.mark.slow
def test_first_and_alpha_order_leave_the_box_zeroth_order_pushes_it_first_order_sees_the_control_cost(tmp_path, getkey):
    metrics = control_policy_pusher.run(CONFIG, tmp_path, KEY, progress=False)
    written = json.loads((tmp_path / "metrics.json").read_text())
    assert written["methods"] == ["first", "zeroth", "alpha"]
    for name in written["methods"]:
        assert all(key in written[name] for key in PER_METHOD) and len(written[name]["per_seed"]) == CONFIG.seeds
    assert (tmp_path / "policy_pusher_cost.png").stat().st_size > 0
    assert (tmp_path / "policy_pusher_box_x.png").stat().st_size > 0
    assert not list(tmp_path.glob(".*"))  # no temporary file left behind
    first, zeroth, alpha = (metrics[name]["per_seed"][0] for name in ("first", "zeroth", "alpha"))
    # First order: no sample ever touches the box, the estimate is the control cost's
    # gradient (plus noise), and the forces stay near zero: the box does not move (resting
    # on the floor it stays put to rounding, whatever the forces).
    assert first["box_displacement"] < 1e-12 and first["max_force"] < 1.0 and first["first_push_iteration"] == -1
    assert first["final_cost"] == pytest.approx(metrics["initial_cost"], abs=1e-3) and not first["success"]
    # Alpha order: its estimates agree within noise (nothing touches the box), it trusts first
    # order and leaves the box too.
    assert alpha["box_displacement"] < 1e-12 and alpha["mean_alpha"] > 0.9 and alpha["first_push_iteration"] == -1
    # Zeroth order: the same mean, a far larger variance; Adam's steps on it walk the forces
    # until samples touch the box (not at the start: the zero-force policy pushes nothing),
    # then push the box toward the target.
    assert zeroth["first_push_iteration"] > 0 and zeroth["box_displacement"] > 0.03
    assert zeroth["position_error"] < CONFIG.target_x - 0.03 and zeroth["final_cost"] < 0.7 * first["final_cost"]
    assert metrics["zeroth"]["gradient_variance_median"] > 100 * metrics["first"]["gradient_variance_median"]
    assert [metrics[name]["push_rate"] for name in ("first", "zeroth", "alpha")] == [0.0, 1.0, 0.0]
    # In the same test, so that it runs the step compiled above (30-40 s to compile) rather
    # than compile it again on the other pytest-xdist worker.
    _first_order_estimate_away_from_the_box_is_the_control_cost_gradient_exactly(getkey)


def _first_order_estimate_away_from_the_box_is_the_control_cost_gradient_exactly(getkey):
    # At zero force no perturbed finger reaches the box: the exact derivative of the box's pose
    # with respect to every force is exactly zero, so each sample's gradient is the control
    # cost's, 1e-4 u (residual 1e-2 u), and the estimate is 1e-4 sigma mean(z) exactly.
    _, problem, policy, _ = control_policy_pusher.build_problem(CONFIG)
    key = getkey()
    solver = dataclasses.replace(CONFIG.solver("first"), iterations=1)
    solution = control.optimize_policy(problem, policy, key, policy.init(), solver=solver)
    dim = 2 * CONFIG.horizon
    z, _ = estimators.perturbed_points(Gaussian(), jax.random.fold_in(key, 0), jnp.zeros(dim), CONFIG.sigma,
                                       CONFIG.num_samples, False)
    z = np.asarray(z)
    weight = control_pusher.CONTROL_WEIGHT**2
    np.testing.assert_allclose(solution.stats["grad_norm"][0], weight * CONFIG.sigma * np.linalg.norm(z.mean(axis=0)),
                               rtol=1e-10)
    variance = np.sum(np.var(weight * CONFIG.sigma * z, axis=0, ddof=1)) / CONFIG.num_samples
    np.testing.assert_allclose(solution.stats["variance"][0], variance, rtol=1e-10)
    # The smoothed cost: the zero-force cost plus the samples' control cost, up to the resting
    # box's sub-nanometre drift, which the contact solver's tolerance lets vary from sample to
    # sample (its derivative, by the implicit function theorem at the solution, is still zero).
    control_cost = 0.5 * weight * CONFIG.sigma**2 * np.mean(np.sum(z**2, axis=1))
    np.testing.assert_allclose(solution.stats["smoothed_cost"][0], solution.stats["cost"][0] + control_cost, atol=1e-8)
    assert abs(solution.stats["smoothed_cost"][0] - solution.stats["cost"][0]) > 1e3 * 1e-8  # the check has teeth
    # In contact the estimates see the box: from a steady 4 N push, which moves the box short
    # of the target, both estimators' first Adam step pushes harder on average.
    push = policy.init().at[:, 0].set(4.0)
    for name in ("first", "zeroth"):
        step = control.optimize_policy(problem, policy, key, push, solver=dataclasses.replace(CONFIG.solver(name), iterations=1))
        assert 0.01 < float(step.xs[-1, 0]) < CONFIG.target_x - 0.03, name  # still short after the step
        assert float(jnp.mean(step.theta[:, 0] - push[:, 0])) > 0.0, name


def test_cli_policy_pusher_checks_its_options_and_documents_its_metrics(tmp_path):
    odd = CliRunner().invoke(cli.app, ["control", "policy-pusher", "--samples", "7", "--out", str(tmp_path)])
    assert odd.exit_code == 2 and "--samples" in odd.output
    help_text = CliRunner().invoke(cli.app, ["control", "policy-pusher", "--help"]).output
    for key in ("--sigma", "position_error", "first_push_iteration"):
        assert key in help_text
    with pytest.raises(ValueError, match="num_samples"):
        control_policy_pusher.Config(num_samples=7)
    with pytest.raises(ValueError, match="method"):
        control_policy_pusher.Config(method="second")
