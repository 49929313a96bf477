"""The alpha-order blending rules (rsmooth.alpha_order's ``rule``): Suh et al.'s single alpha and
the per-entry inverse-variance weights, against a naive NumPy reference and closed forms, and
the option threaded through smooth, the policy gradient and R-DDP."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import rsmooth
from rsmooth import control
from rsmooth.noise import Gaussian

LOG_TERM = np.log(2.0 / 0.05)  # the radius's log(2 / delta) at the default delta


def heaviside(x):
    return jnp.where(x > 0, 1.0, 0.0)


def two_outputs(x):
    """A smooth map R^3 -> R^2 whose Jacobian is known in closed form."""
    return jnp.stack([jnp.sum(jnp.array([1.0, 2.0, 0.5]) * x**2), x[0] * x[1] + x[2]])


def two_outputs_jacobian(y):
    """The Jacobian of :func:`two_outputs` at each row of ``y`` (N, 3): (N, 2, 3)."""
    first = np.stack([2.0 * y[:, 0], 4.0 * y[:, 1], 1.0 * y[:, 2]], axis=1)
    second = np.stack([y[:, 1], y[:, 0], np.ones(len(y))], axis=1)
    return np.stack([first, second], axis=1)


def test_inverse_variance_weights_match_a_naive_reference(getkey):
    """On a smooth map both halves are unbiased: every entry is trusted and weighted by
    var0 / (var0 + var1), the per-entry variances computed here from the same samples."""
    key, x, sigma, m = getkey(), jnp.array([0.3, -0.2, 0.5]), 0.2, 64
    est = rsmooth.alpha_order(two_outputs, key, x, sigma=sigma, num_samples=m, rule="inverse_variance")
    # The samples alpha_order draws: the first half of the budget for zeroth order, the second
    # for first order, from the two halves of the key.
    key_zeroth, key_first = jax.random.split(key)
    z0 = np.asarray(Gaussian().sample(key_zeroth, (m // 2, 3), x.dtype))
    z1 = np.asarray(Gaussian().sample(key_first, (m // 2, 3), x.dtype))
    x_np = np.asarray(x)
    f = lambda y: np.stack([np.sum([1.0, 2.0, 0.5] * y**2, axis=1), y[:, 0] * y[:, 1] + y[:, 2]], axis=1)  # noqa: E731
    # Zeroth order with the baseline f(x): terms (f(x + sigma z) - f(x)) z / sigma (Gaussian score -z).
    terms0 = (f(x_np + sigma * z0) - f(x_np[None]))[:, :, None] * z0[:, None, :] / sigma
    terms1 = two_outputs_jacobian(x_np + sigma * z1)
    g0, v0 = terms0.mean(0), terms0.var(0, ddof=1) / len(terms0)
    g1, v1 = terms1.mean(0), terms1.var(0, ddof=1) / len(terms1)
    assert np.all(np.abs(g1 - g0) <= np.sqrt(2 * (v0 + v1) * LOG_TERM))  # no entry flagged at this key
    alpha = v0 / (v0 + v1)
    np.testing.assert_allclose(est.stats["alpha_entries"], alpha, rtol=1e-9)
    np.testing.assert_allclose(est.grad, alpha * g1 + (1 - alpha) * g0, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(est.stats["std_error"] ** 2, alpha**2 * v1 + (1 - alpha) ** 2 * v0, rtol=1e-9)
    assert float(est.stats["alpha"]) == pytest.approx(alpha.mean(), rel=1e-9)
    assert float(est.stats["trusted_fraction"]) == 1.0
    assert est.grad.shape == est.stats["alpha_entries"].shape == (2, 3)


def smooth_and_step(x):
    return x[0] ** 2 + heaviside(x[1])


def test_per_entry_rule_trusts_the_smooth_coordinate_and_not_the_step(getkey):
    """f = x0^2 + step(x1): the first-order estimate is right on x0 and exactly zero on x1.
    Suh's single alpha must reject it for both; the per-entry rule keeps it on x0."""
    key, x, sigma = getkey(), jnp.array([0.3, 0.0]), 0.1
    kwargs = dict(sigma=sigma, num_samples=256)
    suh = rsmooth.alpha_order(smooth_and_step, key, x, **kwargs)
    per_entry = rsmooth.alpha_order(smooth_and_step, key, x, rule="inverse_variance", **kwargs)
    assert float(suh.stats["alpha"]) == 0.0
    alpha = np.asarray(per_entry.stats["alpha_entries"])
    assert alpha[0] > 0.99 and alpha[1] == 0.0
    assert float(per_entry.stats["trusted_fraction"]) == 0.5
    # Same samples: the step coordinate is the zeroth-order estimate under both rules, the
    # smooth one mostly first order, with a much smaller standard error than Suh's fallback.
    assert float(per_entry.grad[1]) == float(suh.grad[1])
    assert float(per_entry.grad[1]) == pytest.approx(1.0 / (sigma * np.sqrt(2 * np.pi)), rel=0.1)
    assert float(per_entry.stats["std_error"][0]) < 0.1 * float(suh.stats["std_error"][0])
    assert abs(float(per_entry.grad[0]) - 0.6) < 4 * float(per_entry.stats["std_error"][0])


def test_combined_variance_is_at_most_the_better_half(getkey):
    """f = x^2 at 0, sigma = 1, n samples per half: the first-order terms 2 z have variance 4,
    the zeroth-order ones z^3 variance 15, so the halves have variances 4 / n and 15 / n and
    their inverse-variance combination 60 / (19 n), below both (measured across keys)."""
    n, repeats = 32, 400
    keys = jax.random.split(getkey(), repeats)
    estimate = jax.jit(jax.vmap(
        lambda k: rsmooth.alpha_order(lambda x: x**2, k, jnp.array(0.0), sigma=1.0, num_samples=2 * n,
                                      rule="inverse_variance").grad
    ))(keys)
    variance = float(np.var(np.asarray(estimate), ddof=1))
    better, combined = 4.0 / n, 60.0 / (19.0 * n)
    assert abs(float(np.mean(estimate))) < 4 * np.sqrt(variance / repeats)  # unbiased
    assert variance < better
    assert variance == pytest.approx(combined, rel=0.25)


def test_default_rule_is_suh(getkey):
    """The default is the "suh" rule, bit for bit, with and without gamma."""
    key, x = getkey(), jnp.array([0.05, -0.3])
    for options in ({}, {"gamma": 0.5}):
        default = rsmooth.alpha_order(smooth_and_step, key, x, sigma=0.1, num_samples=256, **options)
        suh = rsmooth.alpha_order(smooth_and_step, key, x, sigma=0.1, num_samples=256, rule="suh", **options)
        assert default.stats.keys() == suh.stats.keys()
        for a, b in zip(jax.tree.leaves(default), jax.tree.leaves(suh)):
            np.testing.assert_array_equal(a, b)


def test_bad_rule_is_refused(getkey):
    f, x = (lambda x: jnp.sum(x**2)), jnp.array([0.1, 0.2])
    with pytest.raises(ValueError, match=r"rule must be one of \('suh', 'inverse_variance'\), got 'ivw'"):
        rsmooth.alpha_order(f, getkey(), x, sigma=0.1, num_samples=8, rule="ivw")
    with pytest.raises(ValueError, match="gamma is the trust region of rule='suh'"):
        rsmooth.alpha_order(f, getkey(), x, sigma=0.1, num_samples=8, rule="inverse_variance", gamma=1.0)
    with pytest.raises(ValueError, match=r"alpha_rule must be one of \('suh', 'inverse_variance'\)"):
        rsmooth.smooth(f, sigma=0.1, num_samples=8, estimator="alpha", alpha_rule="Suh")
    with pytest.raises(ValueError, match="alpha_rule must be one of"):
        control.PolicyGradient(alpha_rule=None)
    with pytest.raises(ValueError, match="gamma is the trust region of alpha_rule='suh'"):
        control.PolicyGradient(alpha_rule="inverse_variance", gamma=0.1)
    with pytest.raises(ValueError, match="alpha_rule must be one of"):
        control.RDDP(estimator="alpha", alpha_rule="per-entry")


def test_inverse_variance_under_jit_and_vmap_and_through_smooth(getkey):
    key, x = getkey(), jnp.array([0.3, 0.0])
    options = dict(sigma=0.1, num_samples=256, rule="inverse_variance")
    eager = rsmooth.alpha_order(smooth_and_step, key, x, **options)
    keys = jnp.stack([key, getkey()])
    batched = jax.jit(jax.vmap(lambda k: rsmooth.alpha_order(smooth_and_step, k, x, **options)))(keys)
    assert batched.grad.shape == (2, 2) and batched.stats["alpha_entries"].shape == (2, 2)
    for a, b in zip(jax.tree.leaves(eager), jax.tree.leaves(batched)):
        np.testing.assert_allclose(a, b[0], rtol=1e-12, atol=1e-14)
    # smooth(estimator="alpha") differentiates to the same estimate on the same samples.
    g = rsmooth.smooth(smooth_and_step, sigma=0.1, num_samples=256, estimator="alpha", alpha_rule="inverse_variance")
    np.testing.assert_allclose(jax.jit(jax.grad(g, argnums=1))(key, x), eager.grad, rtol=1e-12)


class SmoothAndJump:
    """x_next = (x0 + u, x1 + u + 1[x1 + u > 0]): the first row is linear, the second jumps."""

    nx, nu = 2, 1

    def step(self, x, u):
        return jnp.stack([x[0] + u[0], x[1] + u[0] + heaviside(x[1] + u[0])])


def test_rddp_jacobians_by_rule(getkey):
    """Smoothed dynamics Jacobians: the per-entry rule keeps the exact first-order Jacobian on
    the linear row and the zeroth-order estimate on the jump's entries."""
    problem = control.ShootingProblem(SmoothAndJump(), lambda x, u: jnp.sum(u**2), lambda x: jnp.sum(x**2),
                                      jnp.zeros(2), horizon=1)
    key, xs, us = getkey(), jnp.zeros((2, 2)), jnp.zeros((1, 1))
    options = dict(eps=0.1, num_samples=256, estimator="alpha")
    fx, fu = control.smoothed_dynamics_jacobians(problem, key, xs, us, alpha_rule="inverse_variance", **options)
    np.testing.assert_allclose(fx[0, 0], [1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(fu[0, 0], [1.0], atol=1e-12)
    assert float(fx[0, 1, 0]) == 0.0  # the second row's zero derivative in x0: first order's exact 0
    # The jump's entries: the zeroth-order estimate of 1 + the density of x1 + u at 0 (the
    # noise on x1 + u has standard deviation eps sqrt(2)), as the "suh" rule's alpha = 0 gives
    # for every entry of the node.
    density = 1.0 / (0.1 * np.sqrt(2.0) * np.sqrt(2.0 * np.pi))
    assert abs(float(fx[0, 1, 1]) - (1.0 + density)) < 0.5 * density


class Shift:
    """x_next = x + u, two coordinates."""

    nx, nu = 2, 2

    def step(self, x, u):
        return x + u


@pytest.mark.parametrize("shared_samples", [False, True])
def test_policy_optimization_with_the_per_entry_rule(getkey, shared_samples):
    """The rule reaches the policy gradient (by the estimator, and from shared samples): one
    parameter moves a smooth cost, the other a step at the start, so the first iteration's
    mean weight is about 1/2 (first order trusted on one parameter of two), where Suh's
    single alpha would be 0."""
    problem = control.ShootingProblem(Shift(), lambda x, u: jnp.zeros((), x.dtype),
                                      lambda x: (x[0] - 1.0) ** 2 - heaviside(x[1]), jnp.zeros(2), horizon=1)
    policy = control.OpenLoop(horizon=1, nu=2)
    solver = control.PolicyGradient(estimator="alpha", sigma=0.1, num_samples=128, learning_rate=0.1, iterations=1,
                                    shared_samples=shared_samples, alpha_rule="inverse_variance")
    solution = control.optimize_policy(problem, policy, getkey(), policy.init(), solver=solver)
    assert 0.45 < float(solution.stats["alpha"][0]) <= 0.5


def test_cross_fitted_weights_remove_the_bias_of_same_sample_weights(getkey):
    """A slope of 1 and a rare steep ramp (height 1, width 0.05, 1.5 sigma away): a first-order
    sample lands on the ramp with probability 0.0065 and then has gradient 21. Suh's alpha,
    chosen from the samples it blends, keeps first order when none landed (variance 0, no
    detectable bias) and drops it when one did: its mean falls short of the smoothed gradient
    by more than the ramp's whole share (0.13). With cross-fitted weights the blend is
    unbiased: both halves are (the function is continuous)."""
    sigma, centre, width = 1.0, 1.5, 0.05

    def f(x):
        return x + jnp.clip((x - centre) / width + 0.5, 0.0, 1.0)

    truth = 1.0 + float(jax.scipy.stats.norm.cdf(centre + width / 2) - jax.scipy.stats.norm.cdf(centre - width / 2)) / width
    keys = jax.random.split(getkey(), 4000)

    def means(cross_fit):
        grads = np.asarray(jax.jit(jax.vmap(lambda k: rsmooth.alpha_order(
            f, k, jnp.array(0.0), sigma=sigma, num_samples=8, baseline="leave-one-out", cross_fit=cross_fit).grad))(keys))
        return grads.mean(), grads.std(ddof=1) / np.sqrt(len(grads))

    same, same_error = means(False)
    crossed, crossed_error = means(True)
    assert truth - same > truth - 1.0 and truth - same > 8 * same_error
    assert abs(crossed - truth) < 4 * crossed_error
    # smooth() gives the same cross-fitted estimate as its derivative.
    smoothed = rsmooth.smooth(f, sigma=sigma, num_samples=8, estimator="alpha", baseline="leave-one-out",
                              alpha_cross_fit=True)
    direct = rsmooth.alpha_order(f, keys[0], jnp.array(0.0), sigma=sigma, num_samples=8, baseline="leave-one-out",
                                 cross_fit=True)
    assert float(jax.grad(smoothed, argnums=1)(keys[0], 0.0)) == pytest.approx(float(direct.grad), rel=1e-12)


@pytest.mark.parametrize("kwargs, error, match", [
    ({"num_samples": 6, "cross_fit": True}, ValueError, "cross_fit=True needs num_samples a multiple of 4 and >= 8"),
    ({"num_samples": 8, "cross_fit": True, "antithetic": True}, ValueError, "a multiple of 8 and >= 16"),
    ({"num_samples": 8, "cross_fit": 1}, TypeError, "cross_fit must be a bool"),
])
def test_bad_cross_fit_is_refused(getkey, kwargs, error, match):
    with pytest.raises(error, match=match):
        rsmooth.alpha_order(jnp.sin, getkey(), jnp.array(0.3), sigma=0.1, **kwargs)
    if kwargs.get("cross_fit") is True and not kwargs.get("antithetic"):
        with pytest.raises(error, match="alpha_cross_fit=True needs"):
            control.PolicyGradient(estimator="alpha", num_samples=kwargs["num_samples"], alpha_cross_fit=True)
