"""Alpha-order blending rules side by side: `python -m benchmarks alpha-rules [--quick] [--json DIR]`.

Four gradient estimators on the paper's cases (Suh, Simchowitz, Zhang, Tedrake, "Do
differentiable simulators give better policy gradients?", ICML 2022): zeroth order, first order,
alpha order with Suh et al.'s single alpha (:func:`rsmooth.alpha_order`'s default ``rule="suh"``)
and alpha order with one inverse-variance weight per entry (``rule="inverse_variance"``; Onoda,
Parmas et al. 2026 revisit the paper's discontinuous tasks with it).

* ``stiffness``: the ball against a compliant wall of :mod:`rsmooth.experiments.landscape_stiffness`
  (its default configuration), the velocity after the rollout against the start, at the softest
  and the stiffest of its stiffnesses;
* ``chaos``: the ball in a wedge of :mod:`rsmooth.experiments.landscape_chaos`, the final
  position against the start, at a short and a long horizon;
* ``policy``: the ball thrown over a wall, ``rsmooth control policy`` (success over seeds), run
  from the command line in a fresh process as `benchmarks.schedules` runs its experiments.

In the first two, one function returns both settings (the two stiffnesses, or the two horizons
of one rollout), so that each estimate covers both: Suh's alpha is one number for the two
entries, the per-entry rule weighs each by itself. Each estimator is repeated over independent
keys (:func:`rsmooth.diagnostics.estimator_bias_variance`) and its RMSE taken against the
smoothed gradient by quadrature of the values on a fine grid (Stein's identity, as the stiffness
experiment's reference). The zeroth-order estimates (alone and in alpha order) use the
leave-one-out baseline, as the experiments do. The throw has one parameter, where the two alpha
rules are the same rule. ``--quick`` runs fewer repeats and seeds (a smoke test of the harness,
not a result).

``results``: ``{"quick", "gradients": {TASK: {"task", "settings", "reference", "sigma",
"num_samples", "repeats", "rules": {RULE: {"rmse", "bias", "std", "alpha"}}}}, "policy": {"task",
"metric", "runs": {RULE: {"command", "success_pct", "final_cost_mean", "mean_alpha", "wall_s"}}}}``
with RULE in :data:`RULES`, each gradient quantity a list over the settings (``alpha``: the mean
weight of the first-order estimate over the repeats); a policy run that failed has
``success_pct`` null and its ``error``.
"""

from __future__ import annotations

import json
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

RULES = ("zeroth", "first", "alpha-suh", "alpha-inverse-variance")
GROUP = 8  # repeats per batch
SAMPLE_CHUNK = 16  # samples per batch (rsmooth.parallel's sample_chunk)
RSMOOTH = [sys.executable, "-m", "rsmooth.cli"]


def _estimators() -> dict:
    """Each rule's estimator and its options."""
    import rsmooth

    return {
        "zeroth": (rsmooth.zeroth_order, {"baseline": "leave-one-out"}),
        "first": (rsmooth.first_order, {}),
        "alpha-suh": (rsmooth.alpha_order, {"baseline": "leave-one-out"}),
        "alpha-inverse-variance": (rsmooth.alpha_order, {"baseline": "leave-one-out", "rule": "inverse_variance"}),
    }


def _with_derivative(compiled, parameters):
    """``x -> (compiled(p, x)[0] for p in parameters)``, concatenated into one vector, whose JAX
    derivative is ``compiled``'s own forward-mode derivative: every estimator then evaluates
    the one compiled rollout program (for every parameter: a traced argument)."""
    import jax
    import jax.numpy as jnp

    def both(x):
        pairs = [compiled(p, x) for p in parameters]
        return jnp.concatenate([jnp.atleast_1d(v) for v, _ in pairs]), jnp.concatenate([jnp.atleast_1d(d) for _, d in pairs])

    @jax.custom_jvp
    def f(x):
        return both(x)[0]

    @f.defjvp
    def f_jvp(primals, tangents):
        (x,), (x_dot,) = primals, tangents
        value, derivative = both(x)
        return value, derivative * x_dot

    return f


def gradient_errors(compiled, parameters, x0: float, sigma: float, num_samples: int, repeats: int, key) -> dict:
    """The reference gradient and, per rule, the RMSE, bias, spread and mean alpha over
    ``repeats`` estimates of the smoothed gradient at ``x0`` of ``compiled(p, .)`` for each of
    ``parameters``, one vector of settings (see the module docstring)."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from rsmooth import diagnostics
    from rsmooth.experiments import _landscape

    # Repeats in groups, samples in chunks: the batches of the rollout program stay small (on
    # jaxlib 0.10's CPU backend a batch of 16 x 64 of these rollouts stalled). The landscape
    # uses batches of the same shape: one compiled program for all.
    batch = (GROUP, SAMPLE_CHUNK)
    groups = max(repeats // GROUP, 1)
    repeats = groups * GROUP
    offsets = np.linspace(-6 * sigma, 6 * sigma, 4 * repeats * num_samples)
    reference = np.concatenate([
        np.atleast_1d(_landscape.gaussian_smoothed_gradient(
            offsets, _landscape.evaluate_in_batches(compiled, p, x0 + offsets, batch)[0], sigma))
        for p in parameters
    ])
    f = _with_derivative(compiled, parameters)
    x = jnp.asarray(x0)
    rules = {}
    for rule, (estimator, options) in _estimators().items():
        options = dict(options, sigma=sigma, num_samples=num_samples, sample_chunk=SAMPLE_CHUNK)

        @jax.jit
        def group(subkey, estimator=estimator, options=options, rule=rule):
            d = diagnostics.estimator_bias_variance(estimator, f, subkey, x, repeats=GROUP, **options)
            if not rule.startswith("alpha"):
                return d.grads, None
            # The weights the same estimates used (same keys).
            stats = jax.vmap(lambda k: estimator(f, k, x, **options).stats)(jax.random.split(subkey, GROUP))
            return d.grads, stats.get("alpha_entries", stats["alpha"])

        grads, weights = [], []
        for subkey in jax.random.split(jax.random.fold_in(key, RULES.index(rule)), groups):
            g, w = group(subkey)
            grads.append(np.asarray(g).reshape(GROUP, -1))
            if w is not None:
                weights.append(np.asarray(w).reshape(GROUP, -1))
        grads = np.concatenate(grads)
        if rule.startswith("alpha"):
            alpha = np.mean(np.broadcast_to(np.concatenate(weights), grads.shape), axis=0)
        else:
            alpha = np.full(grads.shape[1], 1.0 if rule == "first" else 0.0)
        rules[rule] = {
            "rmse": np.sqrt(np.mean((grads - reference) ** 2, axis=0)),
            "bias": grads.mean(0) - reference,
            "std": grads.std(0, ddof=1),
            "alpha": alpha,
        }
    return {"reference": reference, "sigma": sigma, "num_samples": num_samples, "repeats": repeats, "rules": rules}


def stiffness_task(repeats: int, key) -> dict:
    import jax.numpy as jnp

    from rsmooth.experiments import _landscape, landscape_stiffness as stiffness

    config = stiffness.Config()
    ks = (config.stiffnesses[0], config.stiffnesses[-1])
    system = stiffness.wall_system(config)
    compiled = _landscape.value_and_derivative(lambda k, x: stiffness.final_velocity(system, config, k, x))
    result = gradient_errors(compiled, [jnp.asarray(k) for k in ks], 0.0, config.sigma, config.num_samples, repeats, key)
    return {"task": "Ball against a compliant wall (rsmooth experiment stiffness): d velocity / d start",
            "settings": [f"k = {k:g} N/m" for k in ks], **result}


def chaos_task(repeats: int, key) -> dict:
    from rsmooth.experiments import _landscape, landscape_chaos as chaos

    horizons = (100, 800)
    config = chaos.Config(horizons=horizons)
    system = chaos.wedge_system(config)
    compiled = _landscape.value_and_derivative(lambda _, x: chaos.final_positions(system, config, x))
    result = gradient_errors(compiled, [0.0], config.start_x, config.sigma, config.num_samples, repeats, key)
    return {"task": "Ball in a wedge (rsmooth experiment chaos): d final x / d start",
            "settings": [f"T = {h * config.time_step:g} s" for h in horizons], **result}


# The policy runs: each rule's arguments, and the method whose metrics hold it.
POLICY = ["control", "policy", "--seed", "0", "--seeds", "10"]
POLICY_QUICK = ["--seeds", "2", "--iterations", "10"]
POLICY_RUNS = {
    "zeroth": (["--method", "zeroth"], "zeroth"),
    "first": (["--method", "first"], "first"),
    "alpha-suh": (["--method", "alpha", "--alpha-rule", "suh"], "alpha"),
    "alpha-inverse-variance": (["--method", "alpha", "--alpha-rule", "inverse_variance"], "alpha"),
}


def policy_run(arguments: list[str], method: str, timeout: float) -> dict:
    """One run of ``rsmooth control policy`` in a fresh process; its metrics for ``method``."""
    with tempfile.TemporaryDirectory(prefix="rsmooth-alpha-rules-") as out:
        start = time.perf_counter()
        try:
            done = subprocess.run(RSMOOTH + arguments + ["--out", out], capture_output=True, text=True, timeout=timeout)
        except subprocess.TimeoutExpired:
            return {"success_pct": None, "wall_s": time.perf_counter() - start, "error": f"timed out after {timeout:g} s"}
        wall = time.perf_counter() - start
        if done.returncode != 0:
            return {"success_pct": None, "wall_s": wall, "error": done.stderr.strip().splitlines()[-1:] or ["failed"]}
        metrics = json.loads((Path(out) / "metrics.json").read_text())[method]
        return {"success_pct": 100.0 * metrics["success_rate"], "final_cost_mean": metrics["final_cost_mean"],
                "mean_alpha": metrics["mean_alpha"], "wall_s": wall}


def policy_task(quick: bool) -> dict:
    entry = {"task": "Ball over a wall, policy gradient (rsmooth control policy)",
             "metric": "throws that clear the wall (%)", "runs": {}}
    for rule, (extra, method) in POLICY_RUNS.items():
        arguments = POLICY + extra + (POLICY_QUICK if quick else [])
        run = policy_run(arguments, method, timeout=3600.0)
        run["command"] = "rsmooth " + shlex.join(arguments)
        entry["runs"][rule] = run
        shown = "failed" if run["success_pct"] is None else f"{run['success_pct']:.0f} %"
        print(f"{'policy':>10} {rule:>24}: {shown:>7} ({run['wall_s']:.0f} s)", flush=True)
    return entry


def main(repeats: int = 1, quick: bool = False) -> dict:
    import jax

    jax.config.update("jax_enable_x64", True)  # the precision of the experiments' commands
    from benchmarks._record import machine_info

    info = machine_info()
    print(f"alpha-rules: {info['cpu']}, {info['cores']} cores; gradient RMSE per rule, then policy success")
    estimate_repeats = 16 if quick else 96
    key = jax.random.key(0)
    results: dict = {"quick": quick, "gradients": {}}
    for name, task in (("stiffness", stiffness_task), ("chaos", chaos_task)):
        key, subkey = jax.random.split(key)
        start = time.perf_counter()
        entry = task(estimate_repeats, subkey)
        results["gradients"][name] = entry
        print(f"{name}: {time.perf_counter() - start:.0f} s; reference {', '.join(f'{r:.4g}' for r in entry['reference'])}")
        for rule, row in entry["rules"].items():
            cells = ", ".join(f"{s}: RMSE {e:.3g} alpha {a:.2f}" for s, e, a in zip(entry["settings"], row["rmse"], row["alpha"]))
            print(f"{name:>10} {rule:>24}: {cells}", flush=True)
    results["policy"] = policy_task(quick)
    return results

