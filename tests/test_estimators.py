"""Estimators against closed forms of smoothed functions, Monte-Carlo rates, variance reduction."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.scipy.stats import norm

import rsmooth
from rsmooth import noise


def heaviside(x):
    return jnp.where(x > 0, 1.0, 0.0)


def smoothed_abs(x, sigma):
    """E|x + sigma Z| for Gaussian Z (the folded-normal mean)."""
    return sigma * jnp.sqrt(2 / jnp.pi) * jnp.exp(-(x**2) / (2 * sigma**2)) + x * (1 - 2 * norm.cdf(-x / sigma))


def within(estimate, truth, std_error, k=4.5):
    """|estimate - truth| within k standard errors (Monte-Carlo tolerance, not a guess)."""
    estimate, truth, std_error = map(np.asarray, (estimate, truth, std_error))
    assert np.all(np.abs(estimate - truth) <= k * std_error + 1e-12), (estimate, truth, std_error)


@pytest.mark.parametrize("x0", [-0.8, 0.0, 0.3, 1.5])
def test_gaussian_smoothed_heaviside_is_normal_cdf(x0, getkey):
    sigma = 0.7
    est = rsmooth.zeroth_order(heaviside, getkey(), jnp.array(x0), sigma=sigma, num_samples=20_000)
    within(est.grad, norm.pdf(x0 / sigma) / sigma, est.stats["std_error"])
    value_std = np.sqrt(norm.cdf(x0 / sigma) * (1 - norm.cdf(x0 / sigma)) / 20_000)
    within(est.value, norm.cdf(x0 / sigma), value_std)
    # d/dsigma Phi(x / sigma) = -x / sigma^2 phi(x / sigma)
    assert abs(float(est.sigma_grad) - (-x0 / sigma**2 * norm.pdf(x0 / sigma))) < 0.03
    # The first-order estimate of a step is exactly zero: the gradient is null a.e.
    first = rsmooth.first_order(heaviside, getkey(), jnp.array(x0), sigma=sigma, num_samples=64)
    assert float(first.grad) == 0.0 and float(first.stats["variance"]) == 0.0
    alpha = rsmooth.alpha_order(heaviside, getkey(), jnp.array(x0), sigma=sigma, num_samples=20_000)
    assert float(alpha.stats["alpha"]) == 0.0
    within(alpha.grad, norm.pdf(x0 / sigma) / sigma, alpha.stats["std_error"])


@pytest.mark.parametrize("law", [noise.Logistic(), noise.Laplace(), noise.Cauchy(), noise.Gumbel()], ids=lambda n: n.name)
def test_smoothed_heaviside_with_other_noises(law, getkey):
    # H_sigma(x) = P(x + sigma Z > 0) = 1 - F(-x / sigma): gradient mu(-x / sigma) / sigma.
    sigma, x0 = 0.5, 0.2
    est = rsmooth.zeroth_order(heaviside, getkey(), jnp.array(x0), sigma=sigma, num_samples=40_000, noise=law)
    truth = jnp.exp(law.log_prob(-x0 / sigma)) / sigma
    within(est.grad, truth, est.stats["std_error"])


@pytest.mark.parametrize("x0", [-1.0, 0.0, 0.4])
def test_gaussian_smoothed_abs_closed_form(x0, getkey):
    sigma = 0.6
    truth_grad = 2 * norm.cdf(x0 / sigma) - 1
    for estimate in (
        rsmooth.zeroth_order(jnp.abs, getkey(), jnp.array(x0), sigma=sigma, num_samples=20_000),
        rsmooth.zeroth_order(jnp.abs, getkey(), jnp.array(x0), sigma=sigma, num_samples=20_000, antithetic=True),
        rsmooth.first_order(jnp.abs, getkey(), jnp.array(x0), sigma=sigma, num_samples=20_000),
        rsmooth.alpha_order(jnp.abs, getkey(), jnp.array(x0), sigma=sigma, num_samples=20_000),
    ):
        within(estimate.grad, truth_grad, estimate.stats["std_error"])
    first = rsmooth.first_order(jnp.abs, getkey(), jnp.array(x0), sigma=sigma, num_samples=20_000)
    value_std = float(jnp.sqrt(x0**2 + sigma**2) / jnp.sqrt(20_000.0))
    within(first.value, smoothed_abs(x0, sigma), value_std)


def test_uniform_noise_first_order(getkey):
    # E|x + sigma U|, U uniform on [-1, 1]: gradient clip(x / sigma, -1, 1).
    est = rsmooth.first_order(jnp.abs, getkey(), jnp.array(0.2), sigma=0.5, num_samples=20_000, noise=noise.Uniform())
    within(est.grad, 0.4, est.stats["std_error"])


def test_monte_carlo_rate(getkey):
    # The standard deviation of the estimate falls as 1 / sqrt(M).
    f = lambda x: jnp.sum(jnp.abs(x) + heaviside(x))  # noqa: E731
    x = jnp.array([0.1, -0.3, 0.5])
    variances = [
        rsmooth.stats.empirical_variance(rsmooth.zeroth_order, f, getkey(), x, num_trials=400, sigma=0.5, num_samples=m)
        for m in (16, 256)
    ]
    ratio = float(variances[0] / variances[1])
    assert 16 / 1.4 < ratio < 16 * 1.4


def test_reported_variance_matches_trials(getkey):
    f = lambda x: jnp.sum(jnp.sin(3 * x)) + heaviside(x[0])  # noqa: E731
    x = jnp.array([0.1, -0.3])
    for estimator in (rsmooth.zeroth_order, rsmooth.first_order):
        d = rsmooth.stats.diagnose(estimator, f, getkey(), x, reference=0.0, num_trials=300, sigma=0.4, num_samples=64)
        reported = estimator(f, getkey(), x, sigma=0.4, num_samples=64).stats["variance"]
        assert 0.75 < float(reported / d.variance) < 1.33


def test_first_order_matches_grad_as_sigma_vanishes(getkey):
    def f(params):
        return jnp.sum(jnp.sin(params["w"]) * params["b"] ** 2) + jnp.prod(params["w"])

    x = {"w": jnp.array([0.3, -1.2, 0.7]), "b": jnp.array(1.5)}
    exact = jax.grad(f)(x)
    errors = []
    for sigma in (1e-1, 1e-2, 1e-3):
        est = rsmooth.first_order(f, getkey(), x, sigma=sigma, num_samples=32)
        errors.append(max(jax.tree.leaves(jax.tree.map(lambda a, b: float(jnp.max(jnp.abs(a - b))), est.grad, exact))))
    assert errors[-1] < 5e-3 and errors[0] > errors[1] > errors[2]


def test_a_given_jacobian_equals_autodiff(getkey):
    """A caller-supplied (value, Jacobian) function (a simulator's faster Jacobian) gives the
    same first- and alpha-order estimates as autodiff on the same samples; a wrong one shows
    (it is really used)."""

    def f(x):
        return jnp.stack([jnp.sin(x[0]) * x[1], x[0] ** 2 + jnp.abs(x[1])])

    def analytic(x):
        jac = jnp.array([[jnp.cos(x[0]) * x[1], jnp.sin(x[0])], [2 * x[0], jnp.sign(x[1])]])
        return f(x), jac

    key, x = getkey(), jnp.array([0.4, -0.2])
    ours = rsmooth.first_order(f, key, x, sigma=0.3, num_samples=64, value_and_jacobian=analytic)
    reference = rsmooth.first_order(f, key, x, sigma=0.3, num_samples=64)
    np.testing.assert_allclose(ours.grad, reference.grad, rtol=1e-12)
    np.testing.assert_allclose(ours.value, reference.value, rtol=1e-12)
    doubled = rsmooth.first_order(f, key, x, sigma=0.3, num_samples=64, value_and_jacobian=lambda x: (f(x), 2 * analytic(x)[1]))
    np.testing.assert_allclose(doubled.grad, 2 * reference.grad, rtol=1e-12)
    with pytest.raises(TypeError, match="value_and_jacobian needs x to be one array"):
        rsmooth.first_order(lambda d: d["a"], key, {"a": x}, sigma=0.3, num_samples=4, value_and_jacobian=analytic)
    # Alpha order takes it for its first-order half: the same blend, the same stats.
    ours = rsmooth.alpha_order(f, key, x, sigma=0.3, num_samples=64, value_and_jacobian=analytic)
    reference = rsmooth.alpha_order(f, key, x, sigma=0.3, num_samples=64)
    np.testing.assert_allclose(ours.grad, reference.grad, rtol=1e-12)
    for name in ("alpha", "variance_first", "variance_zeroth", "bias"):
        np.testing.assert_allclose(ours.stats[name], reference.stats[name], rtol=1e-12)
    doubled = rsmooth.alpha_order(f, key, x, sigma=0.3, num_samples=64, value_and_jacobian=lambda x: (f(x), 2 * analytic(x)[1]))
    np.testing.assert_allclose(doubled.stats["variance_first"], 4 * reference.stats["variance_first"], rtol=1e-12)
    with pytest.raises(TypeError, match="value_and_jacobian needs x to be one array"):
        rsmooth.alpha_order(lambda d: d["a"], key, {"a": x}, sigma=0.3, num_samples=4, value_and_jacobian=analytic)


def test_vector_valued_f_gives_jacobian(getkey):
    def f(x):
        return jnp.stack([x["a"] @ x["a"], jnp.sum(jnp.tanh(x["b"])), x["a"][0] * x["b"][1, 0]])

    x = {"a": jnp.array([0.5, -1.0]), "b": jnp.array([[0.2], [0.7]])}
    exact = jax.jacrev(f)(x)
    est = rsmooth.first_order(f, getkey(), x, sigma=1e-4, num_samples=8)
    for key in x:
        assert est.grad[key].shape == exact[key].shape == (3,) + x[key].shape
        np.testing.assert_allclose(est.grad[key], exact[key], atol=1e-3)
    est0 = rsmooth.zeroth_order(f, getkey(), x, sigma=0.05, num_samples=40_000, antithetic=True)
    for key in x:
        within(est0.grad[key], exact[key], est0.stats["std_error"][key], k=5)


def test_antithetic_and_baseline_reduce_variance(getkey):
    # An offset (all variance without a baseline) and curvature near a minimum (the term
    # sigma/2 z'Hz that antithetic pairs cancel and a baseline does not).
    f = lambda x: 10.0 + jnp.sum(3.0 * x**2 + 0.1 * x)  # noqa: E731
    x = jnp.array([0.03, -0.02, 0.01, 0.0])
    kwargs = dict(sigma=0.3, num_samples=32, num_trials=200)
    plain = rsmooth.stats.empirical_variance(rsmooth.zeroth_order, f, getkey(), x, baseline=False, **kwargs)
    with_baseline = rsmooth.stats.empirical_variance(rsmooth.zeroth_order, f, getkey(), x, **kwargs)
    antithetic = rsmooth.stats.empirical_variance(rsmooth.zeroth_order, f, getkey(), x, antithetic=True, **kwargs)
    assert with_baseline < plain / 10   # the constant 10 is all variance without a baseline
    assert antithetic < with_baseline / 3


def test_leave_one_out_baseline_is_unbiased_and_lowers_the_variance_at_a_jump(getkey):
    # The Heaviside at its jump: f(x) = 0 is the worst constant baseline there (the smoothed
    # value is 1/2). Per term, E[(H(z) - b)^2 z^2] - phi(0)^2 is 0.341 for b = f(x) and
    # 0.091 for b = 1/2, which the leave-one-out mean approaches as M grows.
    x, num_samples, trials = jnp.array(0.0), 16, 4000
    keys = jax.random.split(getkey(), trials)
    spreads = {}
    for baseline in (True, "leave-one-out"):
        via_estimator = jax.vmap(
            lambda k: rsmooth.zeroth_order(heaviside, k, x, sigma=1.0, num_samples=num_samples, baseline=baseline).grad
        )(keys)
        g = rsmooth.smooth(heaviside, sigma=1.0, num_samples=num_samples, baseline=baseline)
        via_smooth = jax.vmap(jax.grad(g, argnums=1), in_axes=(0, None))(keys, x)
        np.testing.assert_allclose(via_smooth, via_estimator, rtol=1e-10, atol=1e-12)  # one rule
        h = rsmooth.smooth_elementwise(heaviside, sigma=1.0, num_samples=num_samples, baseline=baseline)
        elementwise = jax.vmap(lambda k: jax.grad(lambda v: jnp.sum(h(k, v)))(x[None])[0])(keys)
        for grads in (via_estimator, elementwise):
            within(np.mean(grads), norm.pdf(0.0), np.std(grads) / np.sqrt(trials))
        spreads[baseline] = float(np.var(via_estimator))
    assert abs(spreads[True] - 0.341 / num_samples) < 0.15 * 0.341 / num_samples
    assert spreads["leave-one-out"] < 0.45 * spreads[True]
    # d/dsigma too, where the hard baseline is no better: unbiased (Phi(0 / sigma) is flat in sigma)
    est = jax.vmap(lambda k: rsmooth.zeroth_order(
        heaviside, k, jnp.array(0.5), sigma=1.0, num_samples=num_samples, baseline="leave-one-out").sigma_grad)(keys)
    within(np.mean(est), -0.5 * norm.pdf(0.5), np.std(est) / np.sqrt(trials))


def test_same_key_same_result_and_jit(getkey):
    key = getkey()
    f = lambda x: jnp.sum(heaviside(x) * x**2)  # noqa: E731
    x = jnp.array([0.2, -0.1, 0.4])
    for estimator in (rsmooth.zeroth_order, rsmooth.first_order, rsmooth.alpha_order):
        a = estimator(f, key, x, sigma=0.3, num_samples=16)
        b = estimator(f, key, x, sigma=0.3, num_samples=16)
        c = jax.jit(lambda k, x, s: estimator(f, k, x, sigma=s, num_samples=16))(key, x, 0.3)
        d = estimator(f, getkey(), x, sigma=0.3, num_samples=16)
        np.testing.assert_array_equal(a.grad, b.grad)
        np.testing.assert_allclose(a.grad, c.grad, rtol=1e-12, atol=1e-12)
        assert not np.array_equal(a.grad, d.grad)


def test_alpha_order_trusts_first_order_on_smooth_functions(getkey):
    f = lambda x: jnp.sum(jnp.sin(x) * x)  # noqa: E731
    x = jnp.array([0.3, -0.5, 0.9])
    est = rsmooth.alpha_order(f, getkey(), x, sigma=0.2, num_samples=200)
    assert float(est.stats["alpha"]) > 0.9
    first = rsmooth.first_order(f, getkey(), x, sigma=0.2, num_samples=20_000)
    within(est.grad, first.grad, jnp.sqrt(est.stats["std_error"] ** 2 + first.stats["std_error"] ** 2))


def test_alpha_order_with_gamma_follows_the_trust_region(getkey):
    key = getkey()
    kwargs = dict(sigma=0.5, num_samples=4000)
    loose = rsmooth.alpha_order(heaviside, key, jnp.array(0.1), gamma=1e6, **kwargs).stats
    assert float(loose["alpha"]) == pytest.approx(float(loose["alpha_star"]))
    tight = rsmooth.alpha_order(heaviside, key, jnp.array(0.1), gamma=0.0, **kwargs).stats
    assert float(tight["alpha"]) == 0.0
    # In between: radius + alpha * bias = gamma exactly.
    gamma = float(loose["radius"]) + 0.1 * float(loose["bias"])
    middle = rsmooth.alpha_order(heaviside, key, jnp.array(0.1), gamma=gamma, **kwargs).stats
    assert float(middle["alpha"]) == pytest.approx(0.1)


class TestBadInput:
    x = jnp.array([0.1, 0.2])
    f = staticmethod(lambda x: jnp.sum(x**2))

    @pytest.mark.parametrize("sigma", [0.0, -1.0, float("nan"), float("inf")])
    def test_sigma(self, sigma, getkey):
        with pytest.raises(ValueError, match="sigma"):
            rsmooth.zeroth_order(self.f, getkey(), self.x, sigma=sigma, num_samples=4)

    def test_sigma_traced(self, getkey):
        fn = jax.jit(lambda s: rsmooth.first_order(self.f, jax.random.key(0), self.x, sigma=s, num_samples=4).grad)
        with pytest.raises(Exception, match="sigma must be positive"):
            jax.block_until_ready(fn(-1.0))

    def test_num_samples(self, getkey):
        with pytest.raises(ValueError, match="num_samples"):
            rsmooth.zeroth_order(self.f, getkey(), self.x, sigma=0.1, num_samples=0)
        with pytest.raises(TypeError, match="num_samples"):
            rsmooth.zeroth_order(self.f, getkey(), self.x, sigma=0.1, num_samples=4.0)
        with pytest.raises(ValueError, match="even"):
            rsmooth.zeroth_order(self.f, getkey(), self.x, sigma=0.1, num_samples=5, antithetic=True)
        with pytest.raises(ValueError, match="num_samples"):
            rsmooth.alpha_order(self.f, getkey(), self.x, sigma=0.1, num_samples=2)

    def test_baseline(self, getkey):
        with pytest.raises(ValueError, match="baseline must be True, False or 'leave-one-out'"):
            rsmooth.zeroth_order(self.f, getkey(), self.x, sigma=0.1, num_samples=4, baseline="mean")
        with pytest.raises(ValueError, match="needs num_samples >= 2"):
            rsmooth.zeroth_order(self.f, getkey(), self.x, sigma=0.1, num_samples=1, baseline="leave-one-out")
        with pytest.raises(ValueError, match="baseline must be"):
            rsmooth.smooth(self.f, sigma=0.1, num_samples=8, estimator="alpha", baseline="leave_one_out")
        with pytest.raises(ValueError, match="baseline must be"):
            rsmooth.alpha_order(self.f, getkey(), self.x, sigma=0.1, num_samples=8, baseline=None)
        with pytest.raises(ValueError, match="baseline"):
            rsmooth.smooth_elementwise(jnp.sign, sigma=0.1, num_samples=4, baseline=1)

    def test_noise(self, getkey):
        with pytest.raises(ValueError, match="symmetric"):
            rsmooth.zeroth_order(self.f, getkey(), self.x, sigma=0.1, num_samples=4, antithetic=True, noise=noise.Gumbel())
        with pytest.raises(ValueError, match="Uniform"):
            rsmooth.zeroth_order(self.f, getkey(), self.x, sigma=0.1, num_samples=4, noise=noise.Uniform())
        with pytest.raises(TypeError, match="noise"):
            rsmooth.zeroth_order(self.f, getkey(), self.x, sigma=0.1, num_samples=4, noise="gaussian")

    def test_x(self, getkey):
        with pytest.raises(ValueError, match="x must be finite"):
            rsmooth.first_order(self.f, getkey(), jnp.array([0.1, jnp.nan]), sigma=0.1, num_samples=4)
        with pytest.raises(TypeError, match="x must hold floating"):
            rsmooth.first_order(self.f, getkey(), jnp.array([1, 2]), sigma=0.1, num_samples=4)
        fn = jax.jit(lambda x: rsmooth.zeroth_order(self.f, jax.random.key(0), x, sigma=0.1, num_samples=4).grad)
        with pytest.raises(Exception, match="x must be finite"):
            jax.block_until_ready(fn(jnp.array([jnp.inf, 0.0])))

    def test_f_returning_nan(self, getkey):
        f = lambda x: jnp.sum(jnp.log(x))  # noqa: E731  NaN for negative perturbed points
        with pytest.raises(ValueError, match="f returned a non-finite value"):
            rsmooth.zeroth_order(f, getkey(), jnp.array([0.01]), sigma=1.0, num_samples=64)
        fn = jax.jit(lambda x: rsmooth.zeroth_order(f, jax.random.key(0), x, sigma=1.0, num_samples=64).grad)
        with pytest.raises(Exception, match="f returned a non-finite value"):
            jax.block_until_ready(fn(jnp.array([0.01])))
        with pytest.raises(ValueError, match="gradient of f is not finite"):
            # The classic NaN gradient: reverse mode (one output, two inputs) differentiates the
            # untaken branch of a where. (Forward mode, used where there are no more inputs than
            # outputs, selects the taken branch's tangent: no NaN.)
            rsmooth.first_order(lambda x: jnp.sum(jnp.where(x > 0, jnp.sqrt(x), 0.0)), getkey(), -jnp.ones(2), sigma=0.1, num_samples=2)

    def test_f_output_and_key(self, getkey):
        with pytest.raises(TypeError, match="single array"):
            rsmooth.zeroth_order(lambda x: (x, x), getkey(), self.x, sigma=0.1, num_samples=4)
        with pytest.raises(TypeError, match="key"):
            rsmooth.zeroth_order(self.f, 0, self.x, sigma=0.1, num_samples=4)


def test_sigma_below_the_resolution_of_x_is_refused_by_the_score_function_estimators(getkey):
    # float32: 1000 + 1e-5 z rounds to 1000, so every f(x + sigma z) is f(x) and the zeroth-order
    # estimate would be silently 0 (that of 2 x = 2000 by first order).
    key, x = getkey(), jnp.array([1000.0], jnp.float32)
    f = lambda v: jnp.sum(v**2)  # noqa: E731
    for estimator in (rsmooth.zeroth_order, rsmooth.alpha_order):
        with pytest.raises(ValueError, match=r"sigma is below the resolution of x's dtype float32.*sigma = 1e-05"):
            estimator(f, key, x, sigma=1e-5, num_samples=8)
    traced = jax.jit(lambda s: rsmooth.zeroth_order(f, key, x, sigma=s, num_samples=8).grad)
    with pytest.raises(Exception, match="sigma is below the resolution of x's dtype float32"):
        jax.block_until_ready(traced(jnp.float32(1e-5)))
    assert np.all(np.isfinite(traced(jnp.float32(10.0))))
    # first order tends to f's derivative as sigma vanishes: allowed
    est = rsmooth.first_order(f, key, x, sigma=1e-5, num_samples=8)
    np.testing.assert_allclose(est.grad, 2000.0, rtol=1e-6)
