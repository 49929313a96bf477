"""Noise laws: score = d log-density, CDF and sampler agree, densities integrate to one."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rsmooth import noise

ALL = [noise.Gaussian(), noise.Gumbel(), noise.Laplace(), noise.Logistic(), noise.Cauchy(), noise.Uniform()]
WITH_SCORE = [n for n in ALL if n.has_score]


@pytest.mark.parametrize("law", WITH_SCORE, ids=lambda n: n.name)
def test_score_is_derivative_of_log_prob(law):
    # Away from 0, where the Laplace density has its kink.
    z = jnp.array([-2.3, -0.7, 0.4, 1.9, 3.1])
    autodiff = jax.vmap(jax.grad(law.log_prob))(z)
    np.testing.assert_allclose(law.score(z), autodiff, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("law", ALL, ids=lambda n: n.name)
def test_density_integrates_to_one_and_is_cdf_derivative(law):
    grid = jnp.linspace(-60.0, 60.0, 1_200_001)
    density = jnp.exp(law.log_prob(grid))
    total = jnp.trapezoid(density, grid)
    # The Cauchy tails beyond |z| = 60 carry 2 * (1/2 - arctan(60)/pi) of the mass.
    expected = float(law.cdf(60.0) - law.cdf(-60.0))
    assert abs(float(total) - expected) < 1e-4
    inner = jnp.array([-1.7, -0.3, 0.45, 0.8, 2.2])
    inner = inner[jnp.abs(inner) < 0.99] if isinstance(law, noise.Uniform) else inner
    cdf_derivative = jax.vmap(jax.grad(law.cdf))(inner)
    np.testing.assert_allclose(cdf_derivative, jnp.exp(law.log_prob(inner)), rtol=1e-9)


@pytest.mark.parametrize("law", ALL, ids=lambda n: n.name)
def test_samples_follow_the_cdf(law, getkey):
    n = 40_000
    samples = np.sort(np.asarray(law.sample(getkey(), (n,))))
    empirical = np.arange(1, n + 1) / n
    # Kolmogorov-Smirnov statistic; its 99.9% quantile is about 1.95 / sqrt(n).
    ks = np.max(np.abs(np.asarray(law.cdf(samples)) - empirical))
    assert ks < 1.95 / np.sqrt(n)


@pytest.mark.parametrize("law", WITH_SCORE, ids=lambda n: n.name)
def test_score_identities(law, getkey):
    # E[score(Z)] = 0 and E[Z score(Z)] = -1 (integration by parts): what makes the baseline
    # and the sigma-derivative estimators unbiased.
    z = law.sample(getkey(), (400_000,))
    score = law.score(z)
    stderr = float(jnp.std(score)) / np.sqrt(z.size)
    assert abs(float(jnp.mean(score))) < 5 * stderr
    zs = z * score
    assert abs(float(jnp.mean(zs)) + 1.0) < 5 * float(jnp.std(zs)) / np.sqrt(z.size)


def test_symmetry_flags(getkey):
    for law in ALL:
        z = law.sample(getkey(), (100_000,))
        median = float(jnp.median(z))
        if law.symmetric:
            assert abs(median) < 0.02, law.name
        else:
            assert abs(median - (-np.log(np.log(2.0)))) < 0.02  # the Gumbel median


SHAPED_DRAWS = {
    "gaussian": jax.random.normal,
    "gumbel": jax.random.gumbel,
    "laplace": jax.random.laplace,
    "logistic": jax.random.logistic,
    "cauchy": jax.random.cauchy,
    "uniform": lambda key, shape, dtype: jax.random.uniform(key, shape, dtype, minval=-1.0, maxval=1.0),
}


@pytest.mark.parametrize("law", ALL, ids=lambda n: n.name)
def test_samples_are_jax_random_draws_of_the_shape(law):
    # Laws draw flat and reshape (faster on CPU); the numbers must be those of JAX's own draw
    # of the multi-dimensional shape, entry for entry, so that seeds keep their meaning.
    key = jax.random.key(11)
    grid = law.sample(key, (5, 3, 7), jnp.float32)
    assert grid.shape == (5, 3, 7) and grid.dtype == jnp.float32
    np.testing.assert_array_equal(np.asarray(grid), np.asarray(SHAPED_DRAWS[law.name](key, (5, 3, 7), jnp.float32)))
    assert law.sample(key, ()).shape == ()
