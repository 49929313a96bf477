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
def test_survival_function_is_one_minus_cdf_and_keeps_the_upper_tail(law):
    z = jnp.linspace(-5.0, 5.0, 101)
    np.testing.assert_allclose(law.sf(z) + law.cdf(z), 1.0, atol=1e-14)
    if isinstance(law, noise.Uniform):
        return
    # in float32, far in the upper tail, where 1 - cdf rounds to 0: the float64 value, to float32's
    # relative precision
    tail = {"gaussian": [5.0, 7.0, 9.0], "cauchy": [1e3, 1e5, 1e7]}.get(law.name, [6.0, 14.0, 30.0])
    tail = jnp.array(tail)
    reference = np.asarray(law.sf(tail))  # float64
    assert np.all(reference > 1e-30)
    assert float(1.0 - law.cdf(tail[-1].astype(jnp.float32))) < reference[-1] / 2  # what sf is for
    np.testing.assert_allclose(law.sf(tail.astype(jnp.float32)), reference, rtol=1e-5)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64], ids=["float32", "float64"])
@pytest.mark.parametrize("law", ALL, ids=lambda n: n.name)
def test_samples_follow_the_cdf(law, dtype, getkey):
    # float32 draws come from rsmooth's own use of threefry (both words), float64 from JAX's
    n = 40_000
    samples = np.sort(np.asarray(law.sample(getkey(), (n,), dtype), np.float64))
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


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64], ids=["float32", "float64"])
@pytest.mark.parametrize("law", ALL, ids=lambda n: n.name)
def test_samples_are_counted_in_row_major_order(law, dtype):
    # A draw of any shape is the flat draw of its size, reshaped: a key means the same numbers
    # whatever the layout the caller asks for.
    key = jax.random.key(11)
    grid = law.sample(key, (5, 3, 7), dtype)
    assert grid.shape == (5, 3, 7) and grid.dtype == dtype
    np.testing.assert_array_equal(np.asarray(grid).ravel(), np.asarray(law.sample(key, (105,), dtype)))
    assert law.sample(key, (), dtype).shape == ()
    assert bool(jnp.all(jnp.isfinite(grid)))


def test_float32_uniforms_pair_both_threefry_words_independently(getkey):
    # Numbers i and i + n/2 are the two words of one threefry block: they must look as
    # independent as any two, and the pairs must fill the unit square evenly.
    n = 200_000
    u = np.asarray(noise._uniform(getkey(), (n,), jnp.float32), np.float64)
    assert u.min() >= 0.0 and u.max() < 1.0
    first, second = u[: n // 2], u[n // 2 :]
    assert abs(np.corrcoef(first, second)[0, 1]) < 5.0 / np.sqrt(n // 2)
    counts, _, _ = np.histogram2d(first, second, bins=10, range=[[0, 1], [0, 1]])
    expected = n // 2 / 100
    chi2 = float(np.sum((counts - expected) ** 2 / expected))
    assert chi2 < 160.0  # 99 degrees of freedom: P(chi2 > 160) < 1e-4
    # as many repeated values as n independent draws among 2^23 mantissas give (birthday
    # problem: n - N (1 - exp(-n / N)) ~ 2,380 here), not more
    levels = 2.0**23
    repeats = n - np.unique(u).size
    expected = n - levels * (1.0 - np.exp(-n / levels))
    assert abs(repeats - expected) < 5.0 * np.sqrt(expected)


def test_draws_depend_on_the_key_alone(getkey):
    law = noise.Gaussian()
    # a raw uint32 key and the typed key with the same data draw the same numbers
    np.testing.assert_array_equal(
        np.asarray(law.sample(jax.random.PRNGKey(3), (9,), jnp.float32)),
        np.asarray(law.sample(jax.random.key(3), (9,), jnp.float32)),
    )
    # vmapped over keys, each row is that key's own draw
    keys = jax.random.split(getkey(), 4)
    batched = jax.vmap(lambda k: law.sample(k, (6,), jnp.float32))(keys)
    for row, k in zip(batched, keys):
        np.testing.assert_array_equal(np.asarray(row), np.asarray(law.sample(k, (6,), jnp.float32)))
    assert len({tuple(np.asarray(r)) for r in batched}) == 4


def test_a_key_array_is_refused():
    keys = jax.random.split(jax.random.key(0), 3)
    with pytest.raises(ValueError, match="single PRNG key"):
        noise.Gaussian().sample(keys, (4,), jnp.float32)


def test_other_key_implementations_draw_through_jax(getkey):
    # keys that are not threefry's (here rbg) fall back to jax.random's uniform
    key = jax.random.key(5, impl="rbg")
    samples = np.sort(np.asarray(noise.Gumbel().sample(key, (40_000,), jnp.float32), np.float64))
    ks = np.max(np.abs(np.asarray(noise.Gumbel().cdf(samples)) - np.arange(1, 40_001) / 40_000))
    assert ks < 1.95 / np.sqrt(40_000)
