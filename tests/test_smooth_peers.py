"""smooth(f) against an independent implementation: optax's perturbed functions."""

import jax
import jax.numpy as jnp
import numpy as np
from optax import perturbations

import rsmooth


def f(v):
    # a jump across a line, times a smooth factor: no closed form needed
    return jnp.where(v[0] + 0.5 * v[1] > 0, 1.0, 0.0) * (1.0 + v[1])


def test_hessian_agrees_with_optax_make_perturbed_fun(getkey):
    # Both are unbiased Monte-Carlo estimates of the Hessian of E f(x + sigma Z), Z Gaussian,
    # on independent samples: their means over independent keys agree within their errors.
    x, sigma, m, trials = jnp.array([0.1, -0.2]), 0.5, 4000, 16
    ours = rsmooth.smooth(f, sigma=sigma, num_samples=m)
    theirs = perturbations.make_perturbed_fun(f, num_samples=m, sigma=sigma, noise=perturbations.Normal())

    def hessians(key):
        key_ours, key_theirs = jax.random.split(key)
        return jax.hessian(ours, argnums=1)(key_ours, x), jax.hessian(theirs, argnums=1)(key_theirs, x)

    a, b = map(np.asarray, jax.jit(jax.vmap(hessians))(jax.random.split(getkey(), trials)))
    error = np.sqrt(a.var(axis=0, ddof=1) / trials + b.var(axis=0, ddof=1) / trials)
    assert np.all(np.abs(a.mean(axis=0) - b.mean(axis=0)) <= 4.5 * error), (a.mean(axis=0), b.mean(axis=0), error)
    # and the Hessian is not the pathwise zero
    assert np.all(np.abs(a.mean(axis=0)) > 4.5 * np.sqrt(a.var(axis=0, ddof=1) / trials))
