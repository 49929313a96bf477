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
    y = perturbed.argmax(getkey(), THETA, sigma=sigma, num_samples=m)
    p = jax.nn.softmax(THETA / sigma)
    np.testing.assert_array_less(jnp.abs(y - p), 4.5 * jnp.sqrt(p * (1 - p) / m) + 1e-12)
    np.testing.assert_allclose(jnp.sum(y), 1.0)


def test_gaussian_argmax_matches_naive_reference(getkey):
    key = getkey()
    y = perturbed.argmax(key, THETA, sigma=0.5, num_samples=3000, noise=noise.Gaussian())
    np.testing.assert_allclose(y, naive_perturbed_argmax(THETA, key, 0.5, 3000, noise.Gaussian()), atol=1e-12)


def test_gumbel_max_is_logsumexp_and_its_gradient_the_argmax(getkey):
    sigma, m = 0.7, 20_000
    key = getkey()
    value, grad = jax.value_and_grad(perturbed.max, argnums=1)(key, THETA, sigma=sigma, num_samples=m)
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
    jac = jax.jacobian(perturbed.argmax, argnums=1)(getkey(), THETA, sigma=sigma, num_samples=40_000, baseline=baseline)
    np.testing.assert_allclose(jac, exact, atol=0.03 if baseline else 0.06)


def test_baseline_lowers_jacobian_variance(getkey):
    def spread(baseline):
        keys = jax.random.split(getkey(), 200)
        jacs = jax.vmap(lambda k: jax.jacobian(perturbed.argmax, argnums=1)(k, THETA, sigma=0.2, num_samples=32, baseline=baseline))(keys)
        return float(jnp.sum(jnp.var(jacs, axis=0)))

    assert spread(True) < 0.7 * spread(False)


def test_argmin_and_min(getkey):
    key = getkey()
    sigma, m = 0.5, 20_000
    y = perturbed.argmin(key, THETA, sigma=sigma, num_samples=m, noise=noise.Gaussian())
    # With symmetric noise, argmin(theta) has the law of argmax(-theta).
    y_ref = perturbed.argmax(getkey(), -THETA, sigma=sigma, num_samples=m, noise=noise.Gaussian())
    np.testing.assert_allclose(y, y_ref, atol=0.03)
    # Gumbel noise on a min: E min(theta + sigma G) = -sigma logsumexp(-theta / sigma) + sigma * gamma.
    value = perturbed.min(key, THETA, sigma=sigma, num_samples=m)
    # P(argmin = i) for Gumbel-perturbed costs is not a softmax; the minimum is checked by MC.
    z = noise.Gumbel().sample(key, (m, THETA.shape[0]))
    np.testing.assert_allclose(value, jnp.mean(jnp.min(THETA[None, :] + sigma * z, axis=1)), rtol=1e-10)


def test_fenchel_young_gradient(getkey):
    sigma = 0.5
    y = jax.nn.one_hot(3, 5)
    key = getkey()
    loss, grad = jax.value_and_grad(perturbed.fenchel_young_loss, argnums=1)(key, THETA, y, sigma=sigma, num_samples=20_000)
    expected = jax.nn.softmax(THETA / sigma) - y
    np.testing.assert_allclose(grad, expected, atol=0.02)
    closed = sigma * jax.nn.logsumexp(THETA / sigma) + sigma * EULER_GAMMA - THETA @ y
    assert abs(float(loss - closed)) < 0.02
    with pytest.raises(ValueError, match="y must have the shape"):
        perturbed.fenchel_young_loss(key, THETA, jnp.ones(3), sigma=sigma, num_samples=4)


def test_ranking_oracle_solves_the_lp():
    theta = jnp.array([0.3, -1.0, 2.0, 0.5])
    best = max(itertools.permutations(range(1, 5)), key=lambda perm: float(jnp.dot(jnp.array(perm, float), theta)))
    np.testing.assert_array_equal(perturbed.ranking_argmax(theta), jnp.array(best, float))


def test_perturbed_ranking_tends_to_hard_ranking(getkey):
    theta = jnp.array([0.3, -1.0, 2.0, 0.5])
    y = perturbed.argmax(getkey(), theta, sigma=1e-3, num_samples=16, noise=noise.Gaussian(), oracle=perturbed.ranking_argmax)
    np.testing.assert_allclose(y, perturbed.ranking_argmax(theta))
    # With large noise every rank is equally likely: the mean rank is (n + 1) / 2.
    y = perturbed.argmax(getkey(), theta, sigma=1e4, num_samples=20_000, noise=noise.Gaussian(), oracle=perturbed.ranking_argmax)
    np.testing.assert_allclose(y, 2.5 * jnp.ones(4), atol=0.06)


def test_jit_and_vmap(getkey):
    thetas = jax.random.normal(getkey(), (3, 5))
    keys = jax.random.split(getkey(), 3)
    fn = jax.jit(jax.vmap(lambda t, k: perturbed.argmax(k, t, sigma=0.5, num_samples=8)))
    batched = fn(thetas, keys)
    for i in range(3):
        np.testing.assert_allclose(batched[i], perturbed.argmax(keys[i], thetas[i], sigma=0.5, num_samples=8))


def mean_within(samples, truth, k=4.5):
    """The mean of independent estimates (first axis) within k of its standard errors of truth."""
    samples = np.asarray(samples)
    error = samples.std(axis=0, ddof=1) / np.sqrt(samples.shape[0])
    assert np.all(np.abs(samples.mean(axis=0) - np.asarray(truth)) <= k * error + 1e-12)


def softmax_jacobian(theta, sigma):
    p = jax.nn.softmax(theta / sigma)
    return (jnp.diag(p) - jnp.outer(p, p)) / sigma


def test_max_hessian_is_the_argmax_jacobian_is_the_softmax_jacobian(getkey):
    # Berthet et al. 2020, Prop. 3.1: the Hessian of F_sigma is the Jacobian of y_sigma, for
    # Gumbel noise the softmax Jacobian. Both are estimated on the same samples (the max's
    # second derivative with each sample's baseline the mean of the others').
    sigma, m = 0.7, 2000

    def estimates(key):
        hessian = jax.hessian(perturbed.max, argnums=1)(key, THETA, sigma=sigma, num_samples=m)
        loss_hessian = jax.hessian(perturbed.fenchel_young_loss, argnums=1)(key, THETA, jax.nn.one_hot(1, 5), sigma=sigma, num_samples=m)
        jacobian = jax.jacobian(perturbed.argmax, argnums=1)(key, THETA, sigma=sigma, num_samples=m, baseline="leave-one-out")
        return hessian, loss_hessian, jacobian

    hessians, loss_hessians, jacobians = jax.jit(jax.vmap(estimates))(jax.random.split(getkey(), 16))
    np.testing.assert_allclose(hessians, jacobians, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(loss_hessians, hessians, rtol=1e-9, atol=1e-12)
    mean_within(hessians, softmax_jacobian(THETA, sigma))


def test_a_batch_gets_independent_noise_per_problem(getkey):
    key, b, m, sigma = getkey(), 64, 32, 0.5
    rows = jnp.tile(THETA, (b, 1))
    keys = jax.random.split(key, b)
    y = perturbed.argmax(key, rows, sigma=sigma, num_samples=m)
    assert y.shape == (b, 5) and not np.allclose(y[0], y[1])  # identical rows, different noise
    # the documented rule: vmap over the rows with the keys split from key
    single = jax.vmap(lambda t, k: perturbed.argmax(k, t, sigma=sigma, num_samples=m))(rows, keys)
    np.testing.assert_allclose(y, single, rtol=1e-12)

    # The gradient of the mean over the batch of <c, y_b>: row b's gradient comes from row b's
    # samples only, so the rows' gradients spread as one problem's and their mean's error
    # falls as 1 / sqrt(B) (one noise for all rows would add every row's noise to each).
    c = jnp.arange(5.0)
    grads = b * jax.jit(jax.grad(lambda t: jnp.mean(perturbed.argmax(key, t, sigma=sigma, num_samples=m) @ c)))(rows)
    single_grads = jax.jit(jax.vmap(jax.grad(lambda t, k: perturbed.argmax(k, t, sigma=sigma, num_samples=m) @ c)))(
        rows, jax.random.split(getkey(), b)
    )
    spread, single_spread = np.std(np.asarray(grads), axis=0), np.std(np.asarray(single_grads), axis=0)
    assert np.all(spread < 1.5 * single_spread) and np.all(spread > single_spread / 1.5)
    mean_within(grads, softmax_jacobian(THETA, sigma).T @ c)

    # max, argmin, min and the Fenchel-Young loss follow the same rule, over any leading axes
    targets = jax.nn.one_hot(jnp.arange(6) % 5, 5).reshape(2, 3, 5)
    thetas = jax.random.normal(getkey(), (2, 3, 5))
    split = jax.random.split(key, 6)
    for fn, args in (
        (perturbed.max, ()), (perturbed.argmin, ()), (perturbed.min, ()), (perturbed.fenchel_young_loss, (targets,))
    ):
        batched = fn(key, thetas, *args, sigma=sigma, num_samples=m)
        one_by_one = jax.vmap(lambda t, *a: fn(a[-1], t, *a[:-1], sigma=sigma, num_samples=m))(
            thetas.reshape(6, 5), *[a.reshape(6, 5) for a in args], split
        )
        np.testing.assert_allclose(batched, one_by_one.reshape(batched.shape), rtol=1e-12)
    loss_grad = jax.jit(jax.grad(lambda t: jnp.sum(perturbed.fenchel_young_loss(key, t, targets, sigma=sigma, num_samples=m))))(thetas)
    argmaxes = perturbed.argmax(key, thetas, sigma=sigma, num_samples=m)
    np.testing.assert_allclose(loss_grad, argmaxes - targets, rtol=1e-10, atol=1e-12)
    with pytest.raises(ValueError, match="theta must have at least one axis"):
        perturbed.argmax(key, jnp.array(1.0), sigma=sigma, num_samples=m)


def test_non_finite_theta_raises_under_jit_of_grad(getkey):
    key, theta = getkey(), THETA.at[2].set(jnp.nan)
    y = jax.nn.one_hot(3, 5)
    for fn in (
        jax.jit(jax.grad(lambda t: perturbed.fenchel_young_loss(key, t, y, sigma=0.5, num_samples=8))),
        jax.jit(jax.jacobian(lambda t: perturbed.argmax(key, t, sigma=0.5, num_samples=8))),
        jax.jit(lambda t: perturbed.max(key, t, sigma=0.5, num_samples=8)),
    ):
        with pytest.raises(Exception, match="theta must be finite"):
            jax.block_until_ready(fn(theta))
    with pytest.raises(ValueError, match="theta must be finite"):
        perturbed.fenchel_young_loss(key, theta, y, sigma=0.5, num_samples=8)


def unit_interval_argmax(theta):
    """The LP oracle over the unit cube [0, 1]^n: 1 where theta > 0."""
    return jnp.where(theta > 0, 1.0, 0.0)


def test_gaussian_perturbed_argmax_and_max_of_a_one_dimensional_problem_are_closed_forms(getkey):
    # max_{y in [0, 1]} y theta = max(theta, 0); with Gaussian noise: argmax Phi(theta / s),
    # its derivative phi(theta / s) / s, max theta Phi(theta / s) + s phi(theta / s), whose
    # gradient is the argmax and Hessian the argmax's derivative.
    from jax.scipy.stats import norm

    s, m = 0.5, 20_000
    theta = jnp.array([[-0.6], [0.0], [0.3], [1.2]])  # a batch of four one-dimensional problems
    gauss = noise.Gaussian()
    kwargs = dict(sigma=s, num_samples=m, noise=gauss, oracle=unit_interval_argmax)
    key = getkey()
    y = perturbed.argmax(key, theta, **kwargs)
    p = norm.cdf(theta / s)
    np.testing.assert_array_less(jnp.abs(y - p), 4.5 * jnp.sqrt(p * (1 - p) / m) + 1e-12)
    # one problem per row: the Jacobian of the batch is diagonal
    jac = jax.jit(jax.jacobian(lambda t: perturbed.argmax(key, t, **kwargs)))(theta)[:, 0, :, 0]
    np.testing.assert_array_equal(jac * (1 - np.eye(4)), 0.0)
    np.testing.assert_allclose(jnp.diag(jac), norm.pdf(theta[:, 0] / s) / s, atol=0.04)

    value, grad = jax.jit(jax.value_and_grad(lambda t: jnp.sum(perturbed.max(key, t, **kwargs))))(theta)
    closed = theta * p + s * norm.pdf(theta / s)
    np.testing.assert_allclose(value, jnp.sum(closed), atol=4.5 * 4 * s / np.sqrt(m))
    np.testing.assert_allclose(grad, y, rtol=1e-12)  # the gradient of the max is the argmax
    hessian = jax.jit(jax.hessian(lambda t: perturbed.max(key, t, **kwargs)))(theta[0])
    np.testing.assert_allclose(hessian[0, 0], norm.pdf(theta[0, 0] / s) / s, atol=0.04)


def test_fenchel_young_loss_gradient_is_argmax_minus_target_and_loss_is_nonnegative(getkey):
    key, sigma, m = getkey(), 0.5, 4000
    gauss = noise.Gaussian()
    targets = jnp.eye(5)
    thetas = jnp.tile(THETA, (5, 1))
    kwargs = dict(sigma=sigma, num_samples=m, noise=gauss)
    # on the same samples, exactly: grad L(theta; y) = y_sigma(theta) - y
    grads = jax.jit(jax.grad(lambda t: jnp.sum(perturbed.fenchel_young_loss(key, t, targets, **kwargs))))(thetas)
    np.testing.assert_allclose(grads, perturbed.argmax(key, thetas, **kwargs) - targets, rtol=1e-12, atol=1e-12)
    # Jensen: E max_y <y, theta + sigma Z> >= max_y <y, theta> >= <y, theta> for zero-mean noise,
    # so the loss is >= 0 (up to the Monte-Carlo error of the noise's sample mean) ...
    losses = perturbed.fenchel_young_loss(key, thetas, targets, **kwargs)
    assert np.all(np.asarray(losses) > -4.5 * sigma / np.sqrt(m))
    # ... and as sigma vanishes it tends to max theta - <theta, y>: zero at y = argmax only.
    small = perturbed.fenchel_young_loss(key, thetas, targets, sigma=1e-4, num_samples=16, noise=gauss)
    np.testing.assert_allclose(small, jnp.max(THETA) - THETA, atol=1e-3)
    assert int(jnp.argmin(small)) == int(jnp.argmax(THETA)) and float(jnp.min(small)) < 1e-3


@pytest.mark.parametrize("fn", [perturbed.argmax, perturbed.max, perturbed.argmin, perturbed.min])
def test_the_key_comes_first_and_the_old_order_is_refused_by_name(fn, getkey):
    with pytest.raises(TypeError, match="the key comes first"):
        fn(THETA, getkey(), sigma=0.5, num_samples=4)
    with pytest.raises(TypeError, match="the key comes first"):
        perturbed.fenchel_young_loss(THETA, getkey(), jnp.ones(3), sigma=0.5, num_samples=4)
