"""Perturbed optimizers against closed forms: Gumbel argmax = softmax, max = log-sum-exp."""

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rsmooth import noise, perturbed
from rsmooth.noise import EULER_GAMMA

THETA = jnp.array([0.5, -0.3, 0.1, 0.9, -1.2])


def naive_perturbed_argmax(theta, key, sigma, num_samples, law):
    """A deliberately plain reference: a Python loop over samples with NumPy."""
    z = np.asarray(law.sample(key, (num_samples, theta.shape[0])))
    total = np.zeros(theta.shape[0])
    for zi in z:
        total[np.argmax(np.asarray(theta) + sigma * zi)] += 1.0
    return total / num_samples


@pytest.mark.parametrize("sigma", [0.3, 1.0])
def test_gumbel_argmax_is_softmax(sigma, getkey):
    m = 20_000
    y = perturbed.argmax(THETA, getkey(), sigma=sigma, num_samples=m)
    p = jax.nn.softmax(THETA / sigma)
    np.testing.assert_array_less(jnp.abs(y - p), 4.5 * jnp.sqrt(p * (1 - p) / m) + 1e-12)
    np.testing.assert_allclose(jnp.sum(y), 1.0)


def test_gaussian_argmax_matches_naive_reference(getkey):
    key = getkey()
    y = perturbed.argmax(THETA, key, sigma=0.5, num_samples=3000, noise=noise.Gaussian())
    np.testing.assert_allclose(y, naive_perturbed_argmax(THETA, key, 0.5, 3000, noise.Gaussian()), atol=1e-12)


def test_gumbel_max_is_logsumexp_and_its_gradient_the_argmax(getkey):
    sigma, m = 0.7, 20_000
    key = getkey()
    value, grad = jax.value_and_grad(perturbed.max)(THETA, key, sigma=sigma, num_samples=m)
    expected = sigma * jax.nn.logsumexp(THETA / sigma) + sigma * EULER_GAMMA
    # The max of Gumbels is Gumbel with scale sigma: standard deviation sigma * pi / sqrt(6).
    assert abs(float(value - expected)) < 4.5 * sigma * np.pi / np.sqrt(6 * m)
    p = jax.nn.softmax(THETA / sigma)
    np.testing.assert_array_less(jnp.abs(grad - p), 4.5 * jnp.sqrt(p * (1 - p) / m))


@pytest.mark.parametrize("baseline", [True, False])
def test_argmax_jacobian_is_softmax_jacobian(baseline, getkey):
    sigma = 1.0
    p = jax.nn.softmax(THETA / sigma)
    exact = (jnp.diag(p) - jnp.outer(p, p)) / sigma
    jac = jax.jacobian(perturbed.argmax)(THETA, getkey(), sigma=sigma, num_samples=40_000, baseline=baseline)
    np.testing.assert_allclose(jac, exact, atol=0.03 if baseline else 0.06)


def test_baseline_lowers_jacobian_variance(getkey):
    def spread(baseline):
        keys = jax.random.split(getkey(), 200)
        jacs = jax.vmap(lambda k: jax.jacobian(perturbed.argmax)(THETA, k, sigma=0.2, num_samples=32, baseline=baseline))(keys)
        return float(jnp.sum(jnp.var(jacs, axis=0)))

    assert spread(True) < 0.7 * spread(False)


def test_argmin_and_min(getkey):
    key = getkey()
    sigma, m = 0.5, 20_000
    y = perturbed.argmin(THETA, key, sigma=sigma, num_samples=m, noise=noise.Gaussian())
    # With symmetric noise, argmin(theta) has the law of argmax(-theta).
    y_ref = perturbed.argmax(-THETA, getkey(), sigma=sigma, num_samples=m, noise=noise.Gaussian())
    np.testing.assert_allclose(y, y_ref, atol=0.03)
    # Gumbel noise on a min: E min(theta + sigma G) = -sigma logsumexp(-theta / sigma) + sigma * gamma.
    value = perturbed.min(THETA, key, sigma=sigma, num_samples=m)
    # P(argmin = i) for Gumbel-perturbed costs is not a softmax; the minimum is checked by MC.
    z = noise.Gumbel().sample(key, (m, THETA.shape[0]))
    np.testing.assert_allclose(value, jnp.mean(jnp.min(THETA[None, :] + sigma * z, axis=1)), rtol=1e-10)


def test_fenchel_young_gradient(getkey):
    sigma = 0.5
    y = jax.nn.one_hot(3, 5)
    key = getkey()
    loss, grad = jax.value_and_grad(perturbed.fenchel_young_loss)(THETA, y, key, sigma=sigma, num_samples=20_000)
    expected = jax.nn.softmax(THETA / sigma) - y
    np.testing.assert_allclose(grad, expected, atol=0.02)
    closed = sigma * jax.nn.logsumexp(THETA / sigma) + sigma * EULER_GAMMA - THETA @ y
    assert abs(float(loss - closed)) < 0.02
    with pytest.raises(ValueError, match="y must have the shape"):
        perturbed.fenchel_young_loss(THETA, jnp.ones(3), key, sigma=sigma, num_samples=4)


def test_ranking_oracle_solves_the_lp():
    theta = jnp.array([0.3, -1.0, 2.0, 0.5])
    best = max(itertools.permutations(range(1, 5)), key=lambda perm: float(jnp.dot(jnp.array(perm, float), theta)))
    np.testing.assert_array_equal(perturbed.ranking_argmax(theta), jnp.array(best, float))


def test_perturbed_ranking_tends_to_hard_ranking(getkey):
    theta = jnp.array([0.3, -1.0, 2.0, 0.5])
    y = perturbed.argmax(theta, getkey(), sigma=1e-3, num_samples=16, noise=noise.Gaussian(), oracle=perturbed.ranking_argmax)
    np.testing.assert_allclose(y, perturbed.ranking_argmax(theta))
    # With large noise every rank is equally likely: the mean rank is (n + 1) / 2.
    y = perturbed.argmax(theta, getkey(), sigma=1e4, num_samples=20_000, noise=noise.Gaussian(), oracle=perturbed.ranking_argmax)
    np.testing.assert_allclose(y, 2.5 * jnp.ones(4), atol=0.06)


def test_jit_and_vmap(getkey):
    thetas = jax.random.normal(getkey(), (3, 5))
    keys = jax.random.split(getkey(), 3)
    fn = jax.jit(jax.vmap(lambda t, k: perturbed.argmax(t, k, sigma=0.5, num_samples=8)))
    batched = fn(thetas, keys)
    for i in range(3):
        np.testing.assert_allclose(batched[i], perturbed.argmax(thetas[i], keys[i], sigma=0.5, num_samples=8))
