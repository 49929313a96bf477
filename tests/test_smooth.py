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


def within(estimate, truth, std_error, k=4.5):
    """|estimate - truth| within k standard errors (Monte-Carlo tolerance)."""
    estimate, truth, std_error = map(np.asarray, (estimate, truth, std_error))
    assert np.all(np.abs(estimate - truth) <= k * std_error + 1e-12), (estimate, truth, std_error)


def mean_within(samples, truth, k=4.5):
    """The mean of independent estimates (first axis) within k of its standard errors of truth."""
    samples = np.asarray(samples)
    within(samples.mean(axis=0), truth, samples.std(axis=0, ddof=1) / np.sqrt(samples.shape[0]), k)


def test_derivatives_of_every_order_of_a_smoothed_step_are_the_closed_forms(getkey):
    # Phi(x / s), the Gaussian smoothing of a step: d2/dx2 = -x phi(x/s) / s^3,
    # d3/dx3 = (x^2/s^2 - 1) phi(x/s) / s^4, d2/dx ds = phi(x/s) (x^2/s^2 - 1) / s^2.
    # A pathwise derivative of the zeroth-order rule's tangent would give 0 for all three.
    x, s = 0.5, 1.0

    def derivatives(key):
        def g(x, s):
            return rsmooth.smooth(heaviside, sigma=s, num_samples=4000)(key, x)

        dx = jax.grad(g)
        return jax.grad(dx)(x, s), jax.grad(jax.grad(dx))(x, s), jax.grad(dx, argnums=1)(x, s)

    keys = jax.random.split(getkey(), 32)
    second, third, mixed = jax.jit(jax.vmap(derivatives))(keys)
    phi = norm.pdf(x / s)
    mean_within(second, -x * phi / s**3)
    mean_within(third, (x**2 / s**2 - 1) * phi / s**4)
    mean_within(mixed, phi * (x**2 / s**2 - 1) / s**2)


def test_hessian_is_the_naive_second_order_estimator_on_the_same_samples(getkey):
    # Gaussian noise: Hessian = mean((f(x + s z) - f(x)) (z z^T - I)) / s^2 (zeroth order), and
    # for the first-order rule mean((grad f(x + s z_i) - mean_{j != i} grad f(x + s z_j)) z_i^T) / s.
    key, s, m = getkey(), 0.3, 64
    f = lambda v: jnp.abs(v[0] - v[1]) + heaviside(v[0]) * v[1]  # noqa: E731
    x = jnp.array([0.2, -0.1])
    z = np.asarray(rsmooth.noise.Gaussian().sample(key, (m, 2)))
    points = np.asarray(x) + s * z
    values = np.asarray(jax.vmap(f)(jnp.asarray(points)))
    centred = values - float(f(x))
    naive = sum(c * (np.outer(zi, zi) - np.eye(2)) for c, zi in zip(centred, z)) / (m * s**2)
    hessian = jax.jit(jax.hessian(rsmooth.smooth(f, sigma=s, num_samples=m), argnums=1))(key, x)
    np.testing.assert_allclose(hessian, naive, rtol=1e-10, atol=1e-12)

    grads = np.asarray(jax.vmap(jax.grad(f))(jnp.asarray(points)))
    others = (grads.sum(axis=0) - grads) / (m - 1)
    naive_first = sum(np.outer(g - o, zi) for g, o, zi in zip(grads, others, z)) / (m * s)
    hessian_first = jax.jit(jax.hessian(rsmooth.smooth(f, sigma=s, num_samples=m, estimator="first"), argnums=1))(key, x)
    np.testing.assert_allclose(hessian_first, naive_first, rtol=1e-10, atol=1e-12)


def test_first_order_hessian_of_a_kink_is_the_score_function_estimate(getkey):
    # E|x + s Z| has second derivative 2 phi(x / s) / s; the mean of |x|'s own (zero) second
    # derivatives misses it. With antithetic pairs and without.
    x, s = 0.3, 0.5

    def hessians(key):
        return [
            jax.hessian(rsmooth.smooth(jnp.abs, sigma=s, num_samples=2000, estimator="first", antithetic=anti), argnums=1)(key, x)
            for anti in (False, True)
        ]

    for estimates in jax.jit(jax.vmap(hessians))(jax.random.split(getkey(), 16)):
        mean_within(estimates, 2 * norm.pdf(x / s) / s)


def test_elementwise_second_derivatives_are_diagonal_closed_forms(getkey):
    s, x = 0.5, jnp.array([-0.4, 0.3, 0.9])

    def hessian(key):
        g = rsmooth.smooth_elementwise(heaviside, sigma=s, num_samples=4000)
        return jax.hessian(lambda v: jnp.sum(g(key, v)))(x)

    hessians = jax.jit(jax.vmap(hessian))(jax.random.split(getkey(), 16))
    off_diagonal = np.asarray(hessians) * (1.0 - np.eye(3))
    assert float(np.max(np.abs(off_diagonal))) == 0.0
    mean_within(jnp.diagonal(hessians, axis1=1, axis2=2), -x * norm.pdf(x / s) / s**3)


def test_unsupported_second_derivatives_raise(getkey):
    key, x = getkey(), jnp.array([0.1, 0.2])
    f = lambda v: jnp.sum(jnp.abs(v))  # noqa: E731

    def g(estimator, law=rsmooth.noise.Gaussian()):
        return rsmooth.smooth(f, sigma=0.3, num_samples=8, estimator=estimator, noise=law)

    jax.jit(jax.grad(g("alpha"), argnums=1))(key, x)  # first derivatives are fine
    with pytest.raises(ValueError, match="second derivatives are not available with estimator='alpha'"):
        jax.jit(jax.hessian(g("alpha"), argnums=1))(key, x)
    # Laplace's score jumps at 0: the zeroth-order rule's second derivative would miss it ...
    with pytest.raises(ValueError, match="Laplace lacks"):
        jax.jit(jax.hessian(g("zeroth", rsmooth.noise.Laplace()), argnums=1))(key, x)
    # ... while the first-order rule's second derivative needs the score only (not its third).
    first = g("first", rsmooth.noise.Laplace())
    assert np.all(np.isfinite(jax.jit(jax.hessian(first, argnums=1))(key, x)))
    with pytest.raises(ValueError, match="Laplace lacks"):
        jax.jit(jax.jacfwd(jax.hessian(first, argnums=1), argnums=1))(key, x)
    with pytest.raises(ValueError, match="Uniform has none"):
        jax.jit(jax.hessian(g("first", rsmooth.noise.Uniform()), argnums=1))(key, x)


@pytest.mark.parametrize("estimator", ["zeroth", "first", "alpha"])
def test_non_finite_x_raises_under_jit_of_grad_and_of_value(estimator, getkey):
    key = getkey()
    g = rsmooth.smooth(lambda v: jnp.sum(heaviside(v) + v**2), sigma=0.3, num_samples=8, estimator=estimator)
    bad = jnp.array([jnp.nan, 1.0])
    for fn in (jax.jit(jax.grad(g, argnums=1)), jax.jit(g), jax.jit(jax.jacfwd(g, argnums=1))):
        with pytest.raises(Exception, match="x must be finite"):
            jax.block_until_ready(fn(key, bad))
    if estimator != "alpha":  # smooth_elementwise has no alpha-order rule
        h = rsmooth.smooth_elementwise(heaviside, sigma=0.3, num_samples=8, estimator=estimator)
        with pytest.raises(Exception, match="x must be finite"):
            jax.block_until_ready(jax.jit(jax.grad(lambda v: jnp.sum(h(key, v))))(bad))


def test_non_finite_values_and_baseline_raise_under_jit_of_grad(getkey):
    key = getkey()
    g = rsmooth.smooth(lambda v: jnp.sum(jnp.log(v)), sigma=1.0, num_samples=64)  # NaN below 0
    with pytest.raises(Exception, match="f returned a non-finite value"):
        jax.block_until_ready(jax.jit(jax.grad(g, argnums=1))(key, jnp.array([0.01])))
    # finite at every perturbed point, not at x itself (the baseline)
    pole = rsmooth.smooth(lambda v: jnp.sum(jnp.where(v == 0.0, jnp.inf, 0.0)), sigma=1.0, num_samples=8)
    with pytest.raises(ValueError, match="the baseline f"):
        jax.grad(pole, argnums=1)(key, jnp.array([0.0]))


def test_sigma_below_the_resolution_of_x_is_refused(getkey):
    # In float32, 1000 + 1e-5 z rounds to 1000: the zeroth-order estimate would be silently 0.
    key, x = getkey(), jnp.array([1000.0, -2000.0], jnp.float32)
    f = lambda v: jnp.sum(v**2)  # noqa: E731
    for estimator in ("zeroth", "alpha"):
        g = rsmooth.smooth(f, sigma=1e-5, num_samples=8, estimator=estimator)
        with pytest.raises(ValueError, match="sigma is below the resolution of x's dtype float32"):
            jax.grad(g, argnums=1)(key, x)
        traced = jax.jit(lambda k, v, s: jax.grad(rsmooth.smooth(f, sigma=s, num_samples=8, estimator=estimator), argnums=1)(k, v))
        with pytest.raises(Exception, match="sigma is below the resolution"):
            jax.block_until_ready(traced(key, x, jnp.float32(1e-5)))
        assert np.all(np.isfinite(traced(key, x, jnp.float32(1.0))))
    with pytest.raises(ValueError, match="sigma is below the resolution"):
        rsmooth.smooth_elementwise(heaviside, sigma=1e-5, num_samples=8)(key, x)
    # The first-order estimate tends to f's derivative: allowed. So are float64, and a
    # coordinate far beyond sigma / eps beside resolved ones (a sentinel).
    first = jax.grad(rsmooth.smooth(f, sigma=1e-5, num_samples=8, estimator="first"), argnums=1)(key, x)
    np.testing.assert_allclose(first, 2 * np.asarray(x), rtol=1e-6)
    jax.grad(rsmooth.smooth(f, sigma=1e-5, num_samples=8), argnums=1)(key, x.astype(jnp.float64))
    jax.grad(rsmooth.smooth(f, sigma=1e-5, num_samples=8), argnums=1)(key, jnp.array([1e12, 0.5], jnp.float32))
