"""smooth(f): derivatives under grad/jacrev/jvp equal the estimators', under jit and vmap."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.scipy.stats import norm

import rsmooth


def heaviside(x):
    return jnp.where(x > 0, 1.0, 0.0)


def scalar_f(x):
    return jnp.sum(heaviside(x["a"]) * x["a"] ** 2) + jnp.abs(x["b"]) * 3.0


def vector_f(x):
    return jnp.stack([jnp.sum(jnp.abs(x["a"])), x["a"][0] * x["b"], jnp.sum(jnp.sin(x["a"]))])


X = {"a": jnp.array([0.2, -0.4, 0.1]), "b": jnp.array(0.3)}
ESTIMATOR_FUNCTIONS = {"zeroth": rsmooth.zeroth_order, "first": rsmooth.first_order, "alpha": rsmooth.alpha_order}


def assert_trees_close(a, b, tol=1e-10):
    jax.tree.map(lambda u, v: np.testing.assert_allclose(u, v, rtol=tol, atol=tol), a, b)


@pytest.mark.parametrize("estimator", ["zeroth", "first", "alpha"])
@pytest.mark.parametrize("antithetic", [False, True])
def test_grad_equals_direct_estimator(estimator, antithetic, getkey):
    key = getkey()
    kwargs = dict(sigma=0.25, num_samples=16, antithetic=antithetic)
    g = rsmooth.smooth(scalar_f, estimator=estimator, **kwargs)
    direct = ESTIMATOR_FUNCTIONS[estimator](scalar_f, key, X, **kwargs)
    value, grad = jax.value_and_grad(g, argnums=1)(key, X)
    assert_trees_close(grad, direct.grad)
    np.testing.assert_allclose(value, direct.value, rtol=1e-12)
    jitted = jax.jit(jax.grad(g, argnums=1))(key, X)
    assert_trees_close(jitted, direct.grad)


@pytest.mark.parametrize("estimator", ["zeroth", "first", "alpha"])
def test_jacobians_and_jvp(estimator, getkey):
    key = getkey()
    g = rsmooth.smooth(vector_f, sigma=0.2, num_samples=12, estimator=estimator)
    direct = ESTIMATOR_FUNCTIONS[estimator](vector_f, key, X, sigma=0.2, num_samples=12).grad
    assert_trees_close(jax.jacrev(g, argnums=1)(key, X), direct)
    assert_trees_close(jax.jacfwd(g, argnums=1)(key, X), direct)
    tangent = {"a": jnp.array([1.0, -2.0, 0.5]), "b": jnp.array(0.7)}
    _, out_tangent = jax.jvp(lambda x: g(key, x), (X,), (tangent,))
    expected = direct["a"] @ tangent["a"] + direct["b"] * tangent["b"]
    np.testing.assert_allclose(out_tangent, expected, rtol=1e-10, atol=1e-12)


def test_vmap_over_points_and_keys(getkey):
    g = rsmooth.smooth(heaviside, sigma=0.5, num_samples=4000)
    xs = jnp.array([-0.5, 0.0, 0.6])
    keys = jax.random.split(getkey(), 3)
    grads = jax.vmap(jax.grad(g, argnums=1))(keys, xs)
    for k, x, gr in zip(keys, xs, grads):
        np.testing.assert_allclose(gr, jax.grad(g, argnums=1)(k, x), rtol=1e-10)
    np.testing.assert_allclose(grads, norm.pdf(xs / 0.5) / 0.5, atol=0.1)


def test_nested_in_a_larger_model(getkey):
    # A loss around the smoothed step: chain rule through smooth, and parameters closed over.
    key = getkey()
    weights = jnp.array([1.5, -0.5])

    def loss(w, x):
        g = rsmooth.smooth(lambda v: heaviside(jnp.dot(w, v)), sigma=0.3, num_samples=64, estimator="zeroth")
        return (g(key, x) - 0.8) ** 2

    x = jnp.array([0.1, 0.2])
    grad_x = jax.grad(loss, argnums=1)(weights, x)
    g = rsmooth.smooth(lambda v: heaviside(jnp.dot(weights, v)), sigma=0.3, num_samples=64)
    value, inner = jax.value_and_grad(g, argnums=1)(key, x)
    np.testing.assert_allclose(grad_x, 2 * (value - 0.8) * inner, rtol=1e-10)
    # With respect to closed-over parameters the derivative is pathwise: zero for a step.
    np.testing.assert_array_equal(jax.grad(loss, argnums=0)(weights, x), jnp.zeros(2))
    # ... and the mean of f's own derivative for a differentiable f.
    smooth_loss = lambda w: rsmooth.smooth(lambda v: jnp.sin(w @ v), sigma=0.1, num_samples=8)(key, x)  # noqa: E731
    h = 1e-6
    fd = (smooth_loss(weights + jnp.array([h, 0.0])) - smooth_loss(weights - jnp.array([h, 0.0]))) / (2 * h)
    np.testing.assert_allclose(jax.grad(smooth_loss)(weights)[0], fd, rtol=1e-6)


@pytest.mark.parametrize("estimator", ["zeroth", "first", "alpha"])
def test_sigma_derivative(estimator, getkey):
    key = getkey()
    f = lambda x: jnp.abs(x) + 0.5 * x**2  # noqa: E731
    # E|x + sigma Z| + (x^2 + sigma^2) / 2: d/dsigma = 2 phi(x / sigma) + sigma.
    x, sigma = 0.3, 0.5
    dsigma = jax.grad(lambda s: rsmooth.smooth(f, sigma=s, num_samples=20_000, estimator=estimator, antithetic=True)(key, x))(sigma)
    assert abs(float(dsigma) - (2 * norm.pdf(x / sigma) + sigma)) < 0.03
    direct = ESTIMATOR_FUNCTIONS[estimator](f, key, jnp.array(x), sigma=sigma, num_samples=20_000, antithetic=True)
    np.testing.assert_allclose(dsigma, direct.sigma_grad, rtol=1e-8)


def test_bad_options():
    with pytest.raises(ValueError, match="estimator"):
        rsmooth.smooth(heaviside, sigma=1.0, num_samples=4, estimator="second")
    with pytest.raises(ValueError, match="sigma"):
        rsmooth.smooth(heaviside, sigma=-1.0, num_samples=4)
    with pytest.raises(ValueError, match="num_samples"):
        rsmooth.smooth(heaviside, sigma=1.0, num_samples=0)
    g = rsmooth.smooth(heaviside, sigma=1.0, num_samples=4)
    with pytest.raises(ValueError, match="x must be finite"):
        g(jax.random.key(0), jnp.array(jnp.nan))


@pytest.mark.parametrize("estimator", ["zeroth", "first"])
def test_smooth_elementwise_closed_forms(estimator, getkey):
    # Heaviside for zeroth order (first order is exactly 0 there), |x| for both.
    sigma = 0.4
    x = jnp.array([[-0.6, 0.0], [0.1, 0.9]])
    m = 20_000
    g_abs = rsmooth.smooth_elementwise(jnp.abs, sigma=sigma, num_samples=m, estimator=estimator, antithetic=True)
    key = getkey()
    jac = jax.jacrev(g_abs, argnums=1)(key, x)
    diag = jnp.einsum("ijij->ij", jac)
    np.testing.assert_allclose(diag, 2 * norm.cdf(x / sigma) - 1, atol=0.03)
    off_diagonal = jac - jnp.einsum("ij,ijkl->ijkl", diag, jnp.eye(4).reshape(2, 2, 2, 2))
    assert float(jnp.max(jnp.abs(off_diagonal))) == 0.0  # no leakage between elements
    if estimator == "zeroth":
        g_step = rsmooth.smooth_elementwise(lambda d: jnp.where(d > 0, 1.0, 0.0), sigma=sigma, num_samples=m)
        value, vjp = jax.vjp(lambda v: g_step(key, v), x)
        np.testing.assert_allclose(value, norm.cdf(x / sigma), atol=0.015)
        np.testing.assert_allclose(vjp(jnp.ones_like(x))[0], norm.pdf(x / sigma) / sigma, atol=0.05)
        # d/dsigma Phi(x / sigma) = -x / sigma^2 phi(x / sigma)
        dsigma = jax.grad(lambda s: jnp.sum(rsmooth.smooth_elementwise(lambda d: jnp.where(d > 0, 1.0, 0.0), sigma=s, num_samples=m)(key, x)))(sigma)
        np.testing.assert_allclose(dsigma, jnp.sum(-x / sigma**2 * norm.pdf(x / sigma)), atol=0.05)


def test_smooth_elementwise_matches_smooth_on_one_element(getkey):
    key = getkey()
    step = lambda d: jnp.where(d > 0, 1.0, 0.0)  # noqa: E731
    g = rsmooth.smooth_elementwise(step, sigma=0.5, num_samples=64)
    h = rsmooth.smooth(lambda v: step(v), sigma=0.5, num_samples=64)
    x = jnp.array([0.2])
    np.testing.assert_allclose(jax.jacrev(g, argnums=1)(key, x), jax.jacrev(h, argnums=1)(key, x), rtol=1e-12)
    with pytest.raises(ValueError, match="elementwise"):
        rsmooth.smooth_elementwise(jnp.sum, sigma=1.0, num_samples=4)(key, x)
