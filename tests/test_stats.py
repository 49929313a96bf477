"""Diagnostics: the bias of the first-order estimate on a step, the variance on a stiff sigmoid."""

import jax
import jax.numpy as jnp
from jax.scipy.stats import norm

import rsmooth


def test_first_order_bias_on_heaviside(getkey):
    step = lambda x: jnp.where(x > 0, 1.0, 0.0)  # noqa: E731
    truth = norm.pdf(0.2 / 0.5) / 0.5
    first = rsmooth.stats.diagnose(rsmooth.first_order, step, getkey(), jnp.array(0.2), reference=truth, num_trials=20, sigma=0.5, num_samples=32)
    assert float(first.variance) == 0.0 and abs(float(first.bias) - truth) < 1e-12
    zeroth = rsmooth.stats.diagnose(rsmooth.zeroth_order, step, getkey(), jnp.array(0.2), reference=truth, num_trials=200, sigma=0.5, num_samples=32)
    assert float(zeroth.bias) < 4 * float(zeroth.bias_std_error)
    assert float(rsmooth.stats.empirical_bias(rsmooth.first_order, step, getkey(), jnp.array(0.2), truth, sigma=0.5, num_samples=8)) > 0.5


def test_first_order_variance_on_stiff_sigmoid(getkey):
    # A stiff sigmoid: the first-order estimate is unbiased but its variance dwarfs the
    # zeroth-order one's (Suh et al. 2022, Sec. 3).
    stiff = lambda x: jax.nn.sigmoid(500.0 * x)  # noqa: E731
    kwargs = dict(num_trials=200, sigma=0.5, num_samples=16)
    first = rsmooth.stats.empirical_variance(rsmooth.first_order, stiff, getkey(), jnp.array(0.0), **kwargs)
    zeroth = rsmooth.stats.empirical_variance(rsmooth.zeroth_order, stiff, getkey(), jnp.array(0.0), **kwargs)
    assert float(first) > 5 * float(zeroth)
