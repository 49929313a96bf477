"""Smoothing core: estimator cost against M, and against optax's perturbed functions.

The function is a 256-dimensional piecewise-linear one (a sum of absolute values plus the max of
32 affine pieces), vectorizable over samples. All gradients are jitted and timed in this one
process; ratios are rsmooth / optax on the same function, M, sigma and Gaussian noise, both with
the baseline.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import optax

import rsmooth
from benchmarks._timing import fmt, machine, median_time

DIM = 256
PIECES = 32
SIGMA = 0.1
SAMPLES = (1, 16, 256)


def make_function(key):
    k_a, k_b, k_c = jax.random.split(key, 3)
    a = jax.random.normal(k_a, (PIECES, DIM)) / jnp.sqrt(DIM)
    b = jax.random.normal(k_b, (PIECES,))
    c = jax.random.normal(k_c, (DIM,))

    def f(x):
        return jnp.sum(jnp.abs(x - c)) + jnp.max(a @ x + b)

    return f


def main(repeats: int = 30) -> dict:
    """Prints the table; returns ``{"dim", "sigma", "plain_grad", "rows"}``, times in seconds, a row
    per M: optax (its perturbed gradient), smooth_zeroth (``rsmooth.smooth``'s), ratio, and each
    estimator's gradient (alpha_order: NaN below M = 4)."""
    key = jax.random.key(0)
    f = make_function(key)
    x = jax.random.normal(jax.random.key(1), (DIM,))
    print(f"machine: {machine()}")
    print(f"function: R^{DIM} -> R, piecewise linear; sigma = {SIGMA}; median of {repeats} jitted calls\n")
    plain = jax.jit(jax.grad(f))
    t_plain = median_time(plain, x, repeats=repeats)
    print(f"plain jax.grad(f) (no smoothing): {fmt(t_plain)}\n")
    header = f"{'M':>5} | {'optax grad':>11} | {'smooth zeroth':>13} | {'ratio':>5} | {'zeroth_order':>12} | {'first_order':>11} | {'alpha_order':>11} | {'smooth zeroth / M=1':>19}"
    print(header)
    print("-" * len(header))
    rows = []
    base = None
    for m in SAMPLES:
        optax_fn = optax.perturbations.make_perturbed_fun(f, num_samples=m, sigma=SIGMA, noise=optax.perturbations.Normal())
        t_optax = median_time(jax.jit(jax.grad(optax_fn, argnums=1)), key, x, repeats=repeats)
        g = rsmooth.smooth(f, sigma=SIGMA, num_samples=m)
        t_smooth = median_time(jax.jit(jax.grad(g, argnums=1)), key, x, repeats=repeats)
        timings = {}
        for name, estimator in (("zeroth_order", rsmooth.zeroth_order), ("first_order", rsmooth.first_order), ("alpha_order", rsmooth.alpha_order)):
            if name == "alpha_order" and m < 4:
                timings[name] = float("nan")
                continue
            fn = jax.jit(lambda k, x, est=estimator: est(f, k, x, sigma=SIGMA, num_samples=m).grad)
            timings[name] = median_time(fn, key, x, repeats=repeats)
        base = base or t_smooth
        ratio = t_smooth / t_optax
        alpha = fmt(timings["alpha_order"]) if timings["alpha_order"] == timings["alpha_order"] else "   (M < 4)"
        print(
            f"{m:>5} | {fmt(t_optax):>11} | {fmt(t_smooth):>13} | {ratio:5.2f} | {fmt(timings['zeroth_order']):>12} | "
            f"{fmt(timings['first_order']):>11} | {alpha:>11} | {t_smooth / base:>19.2f}"
        )
        rows.append({"M": m, "optax": t_optax, "smooth_zeroth": t_smooth, "ratio": ratio, **timings})
    print("\nratio = rsmooth.smooth zeroth-order gradient / optax make_perturbed_fun gradient (goal <= 1.0)")
    print("last column: cost of M samples relative to M = 1 (sub-linear until the machine saturates)")
    return {"dim": DIM, "sigma": SIGMA, "plain_grad": t_plain, "rows": rows}


if __name__ == "__main__":
    main()
