"""Estimator diagnostics against closed forms: a step (the Gaussian density is its smoothed
gradient, the first-order estimate is exactly zero) and a sine (smooth: both unbiased)."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.scipy.stats import norm

import rsmooth
from rsmooth import diagnostics

DENSITY_AT_0 = 1 / math.sqrt(2 * math.pi)  # the smoothed step's gradient at 0, sigma = 1


def step(x):
    return jnp.where(x > 0, 1.0, 0.0)


def bias_variance(estimator, f, key, x, **kwargs):
    """:func:`diagnostics.estimator_bias_variance` under `jax.jit` (as a user would run it)."""
    return jax.jit(lambda key: diagnostics.estimator_bias_variance(estimator, f, key, x, **kwargs))(key)


def test_first_order_on_a_step_is_exactly_zero_and_sure_of_it(getkey):
    d = bias_variance(rsmooth.first_order, step, getkey(), jnp.array(0.0), repeats=16, reference=DENSITY_AT_0,
                      sigma=1.0, num_samples=32)
    assert float(d.zero_fraction) == 1.0 and float(d.variance) == 0.0
    assert np.all(np.asarray(d.reported_variance) == 0.0) and np.all(np.asarray(d.reported_std_error) == 0.0)
    assert float(d.bias) == pytest.approx(DENSITY_AT_0, rel=1e-12)
    assert d.grads.shape == (16,)


def test_the_estimators_stats_come_per_repeat(getkey):
    """Alpha order on a step: the first-order half is 0, the zeroth-order half sees the step,
    so the bias test drops the first-order half (alpha = 0) in most repeats, and each
    repeat's alpha is there to see."""
    d = bias_variance(rsmooth.alpha_order, step, getkey(), jnp.array(0.0), repeats=16, sigma=1.0, num_samples=64)
    alpha = np.asarray(d.stats["alpha"])
    assert alpha.shape == (16,) and np.mean(alpha == 0.0) >= 0.75
    assert np.asarray(d.stats["variance"]).shape == (16,)


def test_zeroth_order_on_a_step_is_unbiased_and_reports_its_variance(getkey):
    repeats = 64
    d = bias_variance(rsmooth.zeroth_order, step, getkey(), jnp.array(0.0), repeats=repeats, reference=DENSITY_AT_0,
                      sigma=1.0, num_samples=32)
    assert float(d.bias) < 4 * float(d.bias_std_error)
    assert float(d.bias_std_error) == pytest.approx(math.sqrt(float(d.variance) / repeats))
    # What each estimate reports of itself agrees with its spread across repeats (the variance of
    # a variance estimate from 64 repeats: within a factor 1.5).
    assert 1 / 1.5 < float(np.mean(d.reported_variance)) / float(d.variance) < 1.5
    assert float(d.zero_fraction) == 0.0


def test_on_a_smooth_function_both_are_unbiased_and_first_order_is_less_noisy(getkey):
    # E cos(x + sigma z) = cos(x) exp(-sigma^2 / 2): the smoothed gradient of sin.
    x, sigma = 0.3, 0.5
    truth = math.cos(x) * math.exp(-(sigma**2) / 2)
    results = {
        estimator.__name__: bias_variance(estimator, jnp.sin, getkey(), jnp.array(x), repeats=32, reference=truth,
                                          sigma=sigma, num_samples=16)
        for estimator in (rsmooth.first_order, rsmooth.zeroth_order)
    }
    for d in results.values():
        assert float(d.bias) < 4 * float(d.bias_std_error)
    assert float(results["first_order"].variance) < 0.1 * float(results["zeroth_order"].variance)


def test_bias_variance_without_reference_under_jit_and_for_pytrees(getkey):
    x = {"a": jnp.zeros(2), "b": jnp.array(0.5)}
    f = lambda p: jnp.sum(jnp.array([1.0, -2.0]) * p["a"]) + 3 * p["b"]  # noqa: E731  linear
    d = bias_variance(rsmooth.first_order, f, getkey(), x, repeats=4, sigma=0.1, num_samples=4)
    assert d.bias is None and float(d.variance) < 1e-24
    np.testing.assert_allclose(d.mean["a"], [1.0, -2.0]) and float(d.mean["b"]) == pytest.approx(3.0)
    off = bias_variance(rsmooth.first_order, f, getkey(), x, repeats=4, reference={"a": 0.0, "b": 0.0}, sigma=0.1,
                        num_samples=4)
    assert float(off.bias) == pytest.approx(math.sqrt(1 + 4 + 9))  # a scalar broadcast to each leaf


@pytest.mark.parametrize("kwargs, error, match", [
    ({"repeats": 1}, ValueError, "repeats must be >= 2"),
    ({"repeats": 2.0}, TypeError, "repeats must be a Python int"),
    ({"repeats": 4, "reference": jnp.ones(3)}, ValueError, "reference must have the structure"),
])
def test_bias_variance_rejects_bad_input(getkey, kwargs, error, match):
    with pytest.raises(error, match=match):
        diagnostics.estimator_bias_variance(rsmooth.first_order, jnp.sin, getkey(), jnp.zeros(2), sigma=0.1,
                                            num_samples=4, **kwargs)


def test_bias_test_catches_the_zero_that_the_variance_hides(getkey):
    @jax.jit
    def run(key):
        key_first, key_zeroth = jax.random.split(key)
        first = rsmooth.first_order(step, key_first, jnp.array(0.0), sigma=1.0, num_samples=64)
        zeroth = rsmooth.zeroth_order(step, key_zeroth, jnp.array(0.0), sigma=1.0, num_samples=64)
        return first, zeroth, diagnostics.bias_test(first, zeroth, delta=0.05), diagnostics.bias_test(first, DENSITY_AT_0)

    first, zeroth, against_zeroth, closed = run(getkey())
    assert bool(against_zeroth.biased)
    # The radius: sqrt(2 (V_first + V_zeroth) log(2 / delta)), with V_first = 0.
    assert float(against_zeroth.radius) == pytest.approx(math.sqrt(2 * float(zeroth.stats["variance"]) * math.log(40)))
    assert float(against_zeroth.gap) == pytest.approx(abs(float(zeroth.grad)))
    assert bool(closed.biased) and float(closed.radius) == 0.0 and float(closed.gap) == pytest.approx(DENSITY_AT_0)


def test_bias_test_rarely_flags_an_unbiased_estimate(getkey):
    # A zeroth-order estimate of the step against its closed form, over 200 keys: flagged at
    # most at about the level (0.05; binomial error 0.015 at 200 trials).
    keys = jax.random.split(getkey(), 200)

    def flagged(key):
        estimate = rsmooth.zeroth_order(step, key, jnp.array(0.3), sigma=1.0, num_samples=64)
        return diagnostics.bias_test(estimate, norm.pdf(0.3)).biased

    assert float(jnp.mean(jax.jit(jax.vmap(flagged))(keys))) <= 0.08


def test_bias_test_rejects_bad_input(getkey):
    estimate = rsmooth.first_order(jnp.sin, getkey(), jnp.zeros(2), sigma=0.1, num_samples=4)
    with pytest.raises(ValueError, match="delta must be a number in"):
        diagnostics.bias_test(estimate, 0.0, delta=1.5)
    with pytest.raises(ValueError, match="reference must have the structure"):
        diagnostics.bias_test(estimate, jnp.ones(3))
    with pytest.raises(TypeError, match="estimate must be an rsmooth.Estimate"):
        diagnostics.bias_test(jnp.ones(2), 0.0)


def test_smoothed_landscape_of_a_step_is_the_gaussian_cdf_with_bounded_slope(getkey):
    xs = jnp.linspace(-2.0, 2.0, 81)
    sigma, m = 0.5, 400
    land = jax.jit(lambda key: diagnostics.smoothed_landscape(step, key, xs, sigma=sigma, num_samples=m))(getkey())
    truth = np.asarray(norm.cdf(xs / sigma))
    # Within 4.5 binomial standard errors (the estimated one is 0 where no sample crossed).
    assert np.all(np.abs(np.asarray(land.value) - truth) <= 4.5 * np.sqrt(truth * (1 - truth) / m) + 1e-12)
    assert float(jnp.max(land.std_error)) == pytest.approx(0.5 / math.sqrt(m), rel=0.05)
    np.testing.assert_array_equal(land.unsmoothed, step(xs))  # the landscape itself, unsmoothed
    # The raw step jumps by 1 between two neighbours; its smoothing has slope at most
    # 1 / (sigma sqrt(2 pi)) = 0.8: about 0.04 per grid step of 0.05, plus single samples (1 / M each).
    assert float(jnp.max(jnp.abs(jnp.diff(land.unsmoothed)))) == 1.0
    assert float(jnp.max(jnp.abs(jnp.diff(land.value)))) < 0.1


def test_smoothed_landscape_uses_common_noise_and_vmaps_over_sigma(getkey):
    key = getkey()
    xs = jnp.linspace(-1.0, 1.0, 5)
    f = lambda x: jnp.stack([x, x**2])  # noqa: E731  (f_sigma = x, x^2 + sigma^2)
    sigmas = jnp.array([0.1, 0.3])
    lands = jax.vmap(lambda s: diagnostics.smoothed_landscape(f, key, xs, sigma=s, num_samples=8))(sigmas)
    assert lands.value.shape == (2, 5, 2) and lands.unsmoothed.shape == (2, 5, 2)
    # The same draws z at every point: the linear part's error is the same constant sigma * mean(z).
    error = np.asarray(lands.value[:, :, 0] - xs[None])
    np.testing.assert_allclose(error, error[:, :1] * np.ones((1, 5)), atol=1e-12)
    np.testing.assert_allclose(error[1], 3 * error[0], rtol=1e-9)


@pytest.mark.parametrize("xs, kwargs, error, match", [
    (jnp.zeros(3), {"num_samples": 1}, ValueError, "num_samples must be >= 2"),
    (jnp.array(0.0), {}, ValueError, "xs must stack at least one point"),
    (jnp.zeros(3, int), {}, TypeError, "xs must hold floating-point"),
    (jnp.zeros(3), {"sigma": 0.0}, ValueError, "sigma must be positive"),
])
def test_smoothed_landscape_rejects_bad_input(getkey, xs, kwargs, error, match):
    options = {"sigma": 0.1, "num_samples": 4} | kwargs
    with pytest.raises(error, match=match):
        diagnostics.smoothed_landscape(jnp.sin, getkey(), xs, **options)


def test_reexported_from_the_package():
    assert rsmooth.bias_test is diagnostics.bias_test
    assert rsmooth.estimator_bias_variance is diagnostics.estimator_bias_variance
    assert rsmooth.smoothed_landscape is diagnostics.smoothed_landscape
