r"""`smooth(f)`: the randomly smoothed function as a JAX function with estimated derivatives.

`g = smooth(f, sigma=..., num_samples=...)` returns `g(key, x)`, the Monte-Carlo estimate of
:math:`f_\sigma(x) = \mathbb{E}\, f(x + \sigma z)`, whose derivatives under `jax.grad`,
`jax.jacrev`, `jax.jacfwd` and `jax.jvp` are the chosen estimator's (computed on the same
samples as the value). `g` works under `jit` and `vmap` and can sit inside a larger model.

The zeroth- and first-order rules are matrix-free: a tangent costs one weighted mean
(zeroth order) or one `jvp` of `f` per sample (first order), and the Jacobian is never formed,
so `f` may map many inputs to many outputs (an image). The alpha-order rule needs both
estimates' variances, so it forms the Jacobian.

Derivatives of every order. Each rule's tangent is itself a Monte-Carlo estimate, written as
a function of `x` and `sigma` on the same samples: the points :math:`y_i = x + \sigma z_i` are
held fixed and their dependence on `(x, sigma)` moved into the likelihood ratio
:math:`p_{x,\sigma}(y_i) / p(y_i)` (of value 1), so that differentiating a tangent again gives
the score-function estimator of the next order:

* zeroth order: the :math:`k`-th derivative weighs :math:`f(y_i) - b` by
  :math:`\nabla^k p_{x,\sigma}(y_i) / p_{x,\sigma}(y_i)`; for Gaussian noise the Hessian is
  :math:`\mathbb{E}[(f(x + \sigma z) - b)(z z^\top - I)] / \sigma^2`;
* first order: the first derivative is the mean of `f`'s derivatives at the samples
  (pathwise), the next ones the score-function estimators on those sampled derivatives
  (unbiased where `f`'s derivative has jumps: the Hessian of a perturbed max is the Jacobian
  of the perturbed argmax), each sample's baseline the mean of the other samples' terms;
* alpha order: first derivatives only (its blend is chosen for the first derivative, from the
  samples); a second derivative raises `ValueError`.

Derivatives of order two and more of the score-function estimators need the derivative of
the noise's score: they raise `ValueError` for Laplace noise (whose score jumps at 0), as
the first-order rule's second derivative does for Uniform noise (which has no score).

Derivatives with respect to `sigma` (when it is traced, e.g. by an outer `jax.grad`) are
estimated too, with the estimator's own formula; derivatives with respect to values that `f`
closes over (model parameters) are pathwise: the mean over samples of `f`'s own derivative.

Checks: `x` must be finite, and so must `f`'s values (and `f(x)` where it is the baseline);
for the zeroth- and alpha-order rules `sigma` must not be below the resolution of `x`'s dtype
at every coordinate, :math:`\sigma < \epsilon \min_k |x_k|` (there `x + sigma * z` rounds to
`x` and the estimate would be silently zero; a coordinate far beyond `sigma / eps`, as a
renderer's sentinel for an empty slot, is allowed, its derivative is not estimated). The
first-order rule tends to `f`'s derivative as `sigma` vanishes and is not checked. Concrete
values are checked when `g` is called (`ValueError`); traced ones at run time by one
`equinox` check tied to the value and to the tangent, so that it runs under
`jax.jit(jax.grad(g))` too.
"""

from __future__ import annotations

from typing import Callable, Sequence

import jax
import jax.numpy as jnp
from jax import lax
from jax.typing import ArrayLike

from rsmooth import _checks, parallel
from rsmooth import estimators as _est
from rsmooth._xla import matmul as _matmul
from rsmooth.noise import Gaussian, Laplace, Noise, Uniform

__all__ = ["smooth", "smooth_elementwise", "ESTIMATORS"]

ESTIMATORS = ("zeroth", "first", "alpha")


def smooth(
    f: Callable,
    *,
    sigma: ArrayLike,
    num_samples: int,
    estimator: str = "zeroth",
    noise: Noise = Gaussian(),
    baseline: bool | str = True,
    antithetic: bool = False,
    gamma: float | None = None,
    lipschitz: float | None = None,
    delta: float = 0.05,
    devices: str | Sequence[jax.Device] | None = None,
    sample_chunk: int | None = None,
    alpha_rule: str = "suh",
    alpha_cross_fit: bool = False,
) -> Callable:
    r"""Randomized smoothing of `f` as a differentiable function `g(key, x)`.

    Args:
        f: function of a pytree `x` returning one floating array.
        sigma: noise scale, positive; may be traced (its derivative is estimated).
        num_samples: Monte-Carlo samples per call.
        estimator: ``"zeroth"`` (score function; any `f`), ``"first"`` (mean of sampled
            gradients; `f` differentiable by JAX) or ``"alpha"`` (their blend, Suh et al. 2022).
        noise: the noise law (see :mod:`rsmooth.noise`).
        baseline, antithetic: variance reduction for the zeroth-order rule (see
            :func:`rsmooth.zeroth_order`: True, False or ``"leave-one-out"``).
        gamma, lipschitz, delta: trust region of the alpha-order rule (see
            :func:`rsmooth.alpha_order`).
        alpha_rule: how the alpha-order rule blends its two estimates: ``"suh"`` (one alpha)
            or ``"inverse_variance"`` (one weight per entry of the Jacobian); the ``rule`` of
            :func:`rsmooth.alpha_order`.
        alpha_cross_fit: the alpha-order rule chooses its weights on independent folds of
            its samples (the ``cross_fit`` of :func:`rsmooth.alpha_order`).
        devices: where `f` (and, for derivatives, its per-sample derivatives) is evaluated
            at the samples: ``None`` (default) on the default device; ``"all"`` or a sequence
            of devices: split over them, the value and its derivatives the one-device ones up
            to rounding (as in :func:`rsmooth.zeroth_order`).
        sample_chunk: the most samples at which `f` is evaluated at once on each device
            (as in :func:`rsmooth.zeroth_order`).

    Returns:
        `g(key, x)` with the shape of `f(x)`; its derivatives of every order are estimates on
        its samples (see the module docstring; alpha order: first derivatives only).

    Raises:
        ValueError: when called, for a non-finite `x` or value of `f`, or (zeroth and alpha
            order) a `sigma` below the resolution of `x`'s dtype; at run time (an `equinox`
            error) for the same conditions on traced values; when differentiated, for a
            derivative the estimator or the noise law does not support.

    Example:
        >>> import jax, jax.numpy as jnp, rsmooth
        >>> step = lambda x: jnp.where(x > 0, 1.0, 0.0)
        >>> g = rsmooth.smooth(step, sigma=1.0, num_samples=20000)
        >>> abs(float(jax.grad(g, argnums=1)(jax.random.key(0), 0.0)) - 0.3989) < 0.02
        True
        >>> # the second derivative of Phi(x): -x phi(x), -0.176 at 0.5
        >>> abs(float(jax.hessian(g, argnums=1)(jax.random.key(0), 0.5)) + 0.176) < 0.03
        True

    References:
        Berthet et al., "Learning with differentiable perturbed optimizers", NeurIPS 2020;
        Suh, Simchowitz, Zhang, Tedrake, "Do differentiable simulators give better policy
        gradients?", ICML 2022; Foerster et al., "DiCE: the infinitely differentiable Monte
        Carlo estimator", ICML 2018 (the likelihood ratio whose derivatives are the weights).
    """
    return _smooth(
        f,
        "x",
        sigma=sigma,
        num_samples=num_samples,
        estimator=estimator,
        noise=noise,
        baseline=baseline,
        antithetic=antithetic,
        gamma=gamma,
        lipschitz=lipschitz,
        delta=delta,
        devices=devices,
        sample_chunk=sample_chunk,
        alpha_rule=alpha_rule,
        alpha_cross_fit=alpha_cross_fit,
    )


def _smooth(
    f, name, *, sigma, num_samples, estimator="zeroth", noise=Gaussian(), baseline=True, antithetic=False,
    gamma=None, lipschitz=None, delta=0.05, devices=None, sample_chunk=None, alpha_rule="suh", alpha_cross_fit=False,
):
    """:func:`smooth`, whose errors call the smoothed argument `name`."""
    if estimator not in ESTIMATORS:
        raise ValueError(f"estimator must be one of {ESTIMATORS}, got {estimator!r}")
    if not callable(f):
        raise TypeError(f"f must be callable, got {type(f).__name__}")
    _, num_samples = _est._check_options(
        sigma,
        num_samples,
        noise,
        antithetic=antithetic,
        needs_score=estimator != "first",
        minimum=4 if estimator == "alpha" else 1,
    )
    _est.check_baseline(baseline, num_samples)
    if gamma is not None and _checks.is_traced(gamma):
        raise TypeError("gamma must be a Python float in smooth() (pass a traced one to alpha_order)")
    _est.check_alpha_rule(alpha_rule, gamma, "alpha_rule")
    if estimator == "alpha":
        _est.check_cross_fit(alpha_cross_fit, num_samples, antithetic, "alpha_cross_fit")
    options = dict(
        num_samples=num_samples,
        estimator=estimator,
        noise=noise,
        baseline=baseline,
        antithetic=antithetic,
        gamma=gamma,
        lipschitz=lipschitz,
        delta=delta,
        alpha_rule=alpha_rule,
        alpha_cross_fit=alpha_cross_fit,
        **_est._check_spread(devices, sample_chunk),
    )

    def smoothed(key, x):
        _checks.check_key(key)
        sigma_array = _checks.check_positive_scalar(sigma, "sigma")
        x = jax.tree.map(jnp.asarray, x)
        # x is checked inside the rule, together with f's values: one runtime check per call.
        flat = _est._flatten(f, x, check=False)
        sigma_array = sigma_array.astype(flat.x.dtype)
        # Hoist traced values that f closes over into explicit arguments, so that an outer
        # transformation may differentiate through them (custom_jvp forbids closures).
        converted, consts = jax.closure_convert(flat.f, flat.x)
        rule = _smoothed_flat(converted, len(consts), name, **options)
        return jnp.reshape(rule(key, flat.x, sigma_array, *consts), flat.out_shape)

    return smoothed


def _smoothed_flat(
    f_converted, num_consts, name, *, num_samples, estimator, noise, baseline, antithetic, gamma, lipschitz, delta,
    devices, sample_chunk, alpha_rule="suh", alpha_cross_fit=False,
):
    score = _derivative_score(noise)
    ratio = _likelihood_ratio(noise, score, elementwise=False)
    nonfinite_x = f"{name} must be finite (it contains NaN or inf)"

    def over_samples(fn, *args):
        """``fn`` at every sample (the leading axis of ``args``), spread as asked."""
        return parallel.map_samples(fn, *args, devices=devices, sample_chunk=sample_chunk)

    without_derivatives = _without_derivatives(
        "second derivatives are not available with estimator='alpha' (its blend is chosen for "
        "the first derivative from the samples); use estimator='zeroth' or 'first'"
    )

    def points(key, x, sigma):
        """The perturbed points, the same the estimators use for this key."""
        if estimator == "alpha":
            key_zeroth, key_first = jax.random.split(key)
            n_zeroth = num_samples // 2
            z0, p0 = _est.perturbed_points(noise, key_zeroth, x, sigma, n_zeroth, antithetic)
            z1, p1 = _est.perturbed_points(noise, key_first, x, sigma, num_samples - n_zeroth, antithetic)
            return jnp.concatenate([z0, z1]), jnp.concatenate([p0, p1])
        return _est.perturbed_points(noise, key, x, sigma, num_samples, antithetic)

    def checked(output, x, sigma, values, reference=None):
        """`output`, tied to the checks of `x`, `sigma` against `x`'s resolution and `f`'s values."""
        finite = [(x, nonfinite_x), (values, _est._NONFINITE_F)]
        if reference is not None:
            finite.append((reference, _NONFINITE_BASELINE))
        conditions = [] if estimator == "first" else [_checks.resolution_failure(x, sigma, name)]
        return _checks.check_all(output, finite, conditions)

    def first_order_baseline(terms):
        """The baseline of the derivatives of the first-order tangent (zero where it is used:
        the tangent's value is not changed): for each sample the mean of the others' terms,
        independent of its own noise (none with antithetic pairs, which cancel the constant
        part of an odd score by themselves, or with one sample)."""
        if antithetic or num_samples < 2:
            return jnp.zeros_like(terms)
        return (jnp.sum(terms, axis=0, keepdims=True) - terms) / (num_samples - 1)

    def alpha_jvp(key, x, sigma, consts, x_dot, sigma_dot, consts_dot):
        x, sigma, *consts = without_derivatives(x, sigma, *consts)
        x = _checks.check_all(x, [(x, nonfinite_x)], [_checks.resolution_failure(x, sigma, name)])
        flat = _est._Flat(x, lambda v: f_converted(v, *consts), None, ())
        estimate, _ = _est._alpha_order_flat(
            flat, key, sigma, num_samples, noise, baseline, antithetic, gamma, lipschitz, delta, devices=devices,
            sample_chunk=sample_chunk, rule=alpha_rule, cross_fit=alpha_cross_fit,
        )
        tangent = _matmul(estimate.jacobian, x_dot) + estimate.sigma_grad * sigma_dot
        if num_consts:
            # Pathwise derivative with respect to the values f closes over.
            _, perturbed = points(key, x, sigma)

            def consts_tangent(v):
                return jax.jvp(lambda *c: f_converted(v, *c), tuple(consts), tuple(consts_dot))[1]

            tangent = tangent + jnp.mean(over_samples(consts_tangent, perturbed), axis=0)
        return estimate.value, tangent

    @jax.custom_jvp
    def rule(key, x, sigma, *consts):
        _, perturbed = points(key, x, sigma)
        values = over_samples(lambda v: f_converted(v, *consts), perturbed)
        return checked(jnp.mean(values, axis=0), x, sigma, values)

    @rule.defjvp
    def rule_jvp(primals, tangents):
        key, x, sigma, *consts = primals
        _, x_dot, sigma_dot, *consts_dot = tangents
        if estimator == "alpha":
            return alpha_jvp(key, x, sigma, consts, x_dot, sigma_dot, consts_dot)
        # The points are held fixed; their dependence on (x, sigma) is carried by the
        # likelihood ratio `weight` (value 1) and the noise `z_at` (value z), whose derivatives
        # are those of p_{x,sigma}(y) / p(y) and (y - x) / sigma. The tangent is then itself a
        # Monte-Carlo estimate differentiable in (x, sigma), and its derivative the estimator of
        # the next order on the same samples (score-function, as the likelihood ratio's).
        z, perturbed = points(key, lax.stop_gradient(x), lax.stop_gradient(sigma))
        z_at = _noise_at(z, x, sigma)
        if estimator == "zeroth":
            if num_consts:
                values, consts_terms = over_samples(
                    lambda v: jax.jvp(lambda *c: f_converted(v, *c), tuple(consts), tuple(consts_dot)), perturbed
                )
            else:
                values, consts_terms = over_samples(lambda v: f_converted(v, *consts), perturbed), None
            reference = lax.stop_gradient(
                _est.baseline_values(values, baseline, lambda: f_converted(lax.stop_gradient(x), *consts))
            )
            # the checks tied to a zero, not to the (M,) weights: a runtime check runs on one
            # device, where the weights, laid out across devices (`devices`), would be gathered
            weight = (ratio(z, x, sigma) + checked(jnp.zeros((), x.dtype), x, sigma, values, reference))[:, None]
            centred = values - reference
            # The zeroth-order weights: -(score(z) . x_dot + sigma_dot (z . score(z) + d)) / sigma.
            weights = _log_density_tangent(score, z_at, sigma, x_dot, sigma_dot, elementwise=False)[:, None]
            tangent = jnp.mean(weight * centred * weights, axis=0)
            if consts_terms is not None:
                # Pathwise derivative with respect to the values f closes over.
                tangent = tangent + jnp.mean(weight * consts_terms, axis=0)
            # The value, written so that its derivatives are the rule's (it equals mean(values)).
            value = jnp.mean(values + centred * (weight - 1.0), axis=0)
            return value, tangent
        # first order: the mean of f's derivatives along x_dot + sigma_dot z, and of its
        # (pathwise) derivative with respect to the values f closes over.
        direction = x_dot[None, :] + sigma_dot * z_at

        def sample_jvp(v, dv):
            return jax.jvp(lambda u, *c: f_converted(u, *c), (v, *consts), (dv, *consts_dot))

        values, terms = over_samples(sample_jvp, perturbed, direction)
        anchor = checked(jnp.zeros((), x.dtype), x, sigma, values)
        weight = (ratio(z, x, sigma) + anchor)[:, None]
        tangent = jnp.mean(terms, axis=0) + jnp.mean((weight - 1.0) * (terms - first_order_baseline(terms)), axis=0)
        # A zero term, linear in the tangents, that needs the checks' result: the checks then
        # run wherever the derivative is used, also where f's own derivative is zero.
        tangent = tangent + anchor * (jnp.sum(x_dot) + sigma_dot)
        return rule(key, x, sigma, *consts), tangent

    return rule


_NONFINITE_BASELINE = "f returned a non-finite value (NaN or inf) at x, the baseline f(x)"


def _score_is_differentiable(noise: Noise) -> bool:
    """Whether `noise`'s score is differentiable (its density twice differentiable), as the
    derivatives of order two and more of the score-function estimator need. Laplace's score
    jumps at 0 and Uniform has none; a law built from other laws (a product) is as smooth as
    its parts; any other law is taken to be smooth."""
    if isinstance(noise, (Laplace, Uniform)) or not noise.has_score:
        return False
    parts = jax.tree.leaves(noise, is_leaf=lambda leaf: isinstance(leaf, Noise) and leaf is not noise)
    return all(_score_is_differentiable(part) for part in parts if isinstance(part, Noise))


def _without_derivatives(message: str) -> Callable:
    """The identity on its arguments, with a derivative rule that raises `ValueError(message)`
    (taken only where a tangent flows in: for a value that must not be differentiated)."""

    @jax.custom_jvp
    def identity(*args):
        return args

    @identity.defjvp
    def identity_jvp(primals, tangents):
        raise ValueError(message)

    return identity


@jax.custom_jvp
def _noise_at(z, x, sigma):
    """The noise `z` of a point `y = x + sigma z` held fixed, as a function of `x` and `sigma`:
    its value is `z`, its derivatives those of `(y - x) / sigma` (of every order)."""
    return z


@_noise_at.defjvp
def _noise_at_jvp(primals, tangents):
    z, x, sigma = primals
    _, x_dot, sigma_dot = tangents
    z_at = _noise_at(z, x, sigma)
    return z_at, -(x_dot[None] + sigma_dot * z_at) / sigma


def _log_density_tangent(score: Callable, z_at, sigma, x_dot, sigma_dot, *, elementwise: bool):
    r"""The derivative along `(x_dot, sigma_dot)` of the log-density of the points
    :math:`y = x + \sigma z` under :math:`p_{x,\sigma}(y) = \mu((y - x)/\sigma)/\sigma^d`:
    :math:`-(\nabla\log\mu(z)\cdot\dot x + \dot\sigma\,(z\cdot\nabla\log\mu(z) + d))/\sigma`,
    per sample (M,), or per element (M, ...) with `elementwise` (d = 1 for each)."""
    s = score(z_at)
    if elementwise:
        return -(s * x_dot[None] + sigma_dot * (z_at * s + 1.0)) / sigma
    return -(_matmul(s, x_dot) + sigma_dot * (jnp.sum(z_at * s, axis=-1) + z_at.shape[-1])) / sigma


def _derivative_score(noise: Noise) -> Callable:
    """`noise.score`, or where the score is not differentiable (:func:`_score_is_differentiable`)
    the score with a derivative rule that raises `ValueError`: the derivatives of the
    score-function estimators beyond the first would silently miss its jumps."""
    if _score_is_differentiable(noise):
        return noise.score
    return _without_derivative_of(noise.score, (
        f"derivatives of this order need the derivative of the noise's score, which "
        f"{type(noise).__name__} lacks (its density is not twice differentiable); use "
        "Gaussian, Logistic, Gumbel or Cauchy noise"
    ))


def _likelihood_ratio(noise: Noise, score: Callable, *, elementwise: bool) -> Callable:
    r"""`ratio(z, x, sigma)`: the likelihood ratio :math:`p_{x,\sigma}(y) / p_{x_0,\sigma_0}(y)`
    of the fixed points :math:`y = x_0 + \sigma_0 z`, at :math:`(x_0, \sigma_0)`: ones (M,)
    (per element, (M, ...), with `elementwise`), whose derivatives of every order are those of
    the ratio (Berthet et al. 2020, Prop. 3.1, applied again to each derivative; the
    construction of "DiCE", Foerster et al., ICML 2018). The weights of the score-function
    estimators of every order are its derivatives. Its first derivative needs the law's score
    (`score`: :func:`_derivative_score`), the next ones the score's derivative."""

    @jax.custom_jvp
    def ratio(z, x, sigma):
        return jnp.ones(z.shape if elementwise else z.shape[:1], z.dtype)

    @ratio.defjvp
    def ratio_jvp(primals, tangents):
        z, x, sigma = primals
        _, x_dot, sigma_dot = tangents
        if not noise.has_score:
            raise ValueError(
                f"derivatives of this order need a noise law with a differentiable density; "
                f"{type(noise).__name__} has none"
            )
        out = ratio(z, x, sigma)
        return out, out * _log_density_tangent(score, _noise_at(z, x, sigma), sigma, x_dot, sigma_dot, elementwise=elementwise)

    return ratio


def _without_derivative_of(fn: Callable, message: str) -> Callable:
    """`fn` of one array, with a derivative rule that raises `ValueError(message)`."""

    @jax.custom_jvp
    def wrapped(z):
        return fn(z)

    @wrapped.defjvp
    def wrapped_jvp(primals, tangents):
        raise ValueError(message)

    return wrapped


def smooth_elementwise(
    f: Callable,
    *,
    sigma: ArrayLike,
    num_samples: int,
    estimator: str = "zeroth",
    noise: Noise = Gaussian(),
    baseline: bool | str = True,
    antithetic: bool = False,
    devices: str | Sequence[jax.Device] | None = None,
    sample_chunk: int | None = None,
) -> Callable:
    r"""Randomized smoothing of an elementwise function, with independent noise per element.

    For `f` acting elementwise (`f(x)[i]` depends on `x[i]` only, as `jnp.where(x > 0, 1., 0.)`
    or `jnp.sign`), `g(key, x)[i]` estimates :math:`\mathbb{E}\, f(x_i + \sigma z_i)` and the
    derivative is diagonal, estimated element by element. Use it rather than :func:`smooth`
    when many elements are smoothed at once (the coverage of every pixel by every triangle in a
    renderer, the friction law at every contact): with :func:`smooth` the noise of every element
    would leak into every other element's derivative.

    Args:
        f: an elementwise function of a floating array.
        sigma: noise scale, positive; may be traced (its derivative is estimated).
        num_samples: Monte-Carlo samples per element.
        estimator: ``"zeroth"`` (any `f`) or ``"first"`` (`f` differentiable by JAX).
        noise: the noise law.
        baseline, antithetic: variance reduction (as in :func:`rsmooth.zeroth_order`).
        devices: where `f` (and its derivatives, first order) is evaluated at the samples:
            ``None`` (default) on the default device, at all samples at once; ``"all"`` or a
            sequence of devices: split over them (:func:`rsmooth.parallel.map_samples`), the
            value and its derivatives the one-device ones up to rounding.
        sample_chunk: the most samples at which `f` is evaluated at once on each device.

    Returns:
        `g(key, x)`, an array of the shape of `x`; its derivatives of every order are estimated
        as :func:`smooth`'s (element by element: diagonal), with the same checks.

    Example:
        >>> import jax, jax.numpy as jnp, rsmooth
        >>> from jax.scipy.stats import norm
        >>> g = rsmooth.smooth_elementwise(lambda d: jnp.where(d > 0, 1.0, 0.0), sigma=1.0, num_samples=20000)
        >>> x = jnp.array([-1.0, 0.0, 2.0])
        >>> bool(jnp.allclose(g(jax.random.key(0), x), norm.cdf(x), atol=0.02))
        True
    """
    if estimator not in ("zeroth", "first"):
        raise ValueError(f"estimator must be 'zeroth' or 'first' for smooth_elementwise, got {estimator!r}")
    _est._check_options(sigma, num_samples, noise, antithetic=antithetic, needs_score=estimator == "zeroth")
    _est.check_baseline(baseline, num_samples)
    spread = _est._check_spread(devices, sample_chunk)

    def evaluate(fn, *args):
        """``fn`` (elementwise) at every sample: at once, or spread as asked."""
        if spread["devices"] is None and spread["sample_chunk"] is None:
            return fn(*args)
        return parallel.map_samples(fn, *args, **spread)

    def samples(key, x):
        shape = (num_samples // 2 if antithetic else num_samples,) + x.shape
        z = noise.sample(key, shape, x.dtype)
        return jnp.concatenate([z, -z]) if antithetic else z

    score = _derivative_score(noise)
    ratio = _likelihood_ratio(noise, score, elementwise=True)

    def checked(output, x, sigma, values, reference=None):
        finite = [(x, _est._NONFINITE_X), (values, _est._NONFINITE_F)]
        if reference is not None:
            finite.append((reference, _NONFINITE_BASELINE))
        conditions = [_checks.resolution_failure(x, sigma)] if estimator == "zeroth" else []
        return _checks.check_all(output, finite, conditions)

    @jax.custom_jvp
    def rule(key, x, sigma):
        values = evaluate(f, x[None] + sigma * samples(key, x))
        return checked(jnp.mean(values, axis=0), x, sigma, values)

    @rule.defjvp
    def rule_jvp(primals, tangents):
        key, x, sigma = primals
        _, x_dot, sigma_dot = tangents
        # As in smooth(): fixed points, their dependence on (x, sigma) in the likelihood ratio
        # (per element) and the noise, so that the tangent is differentiable again.
        z = samples(key, x)
        perturbed = lax.stop_gradient(x[None] + sigma * z)
        z_at = _noise_at(z, x, sigma)
        if estimator == "zeroth":
            values = evaluate(f, perturbed)
            reference = lax.stop_gradient(_est.baseline_values(values, baseline, lambda: f(lax.stop_gradient(x))))
            # the checks tied to a zero, not to the weights (laid out across `devices`), as in smooth()
            weight = ratio(z, x, sigma) + checked(jnp.zeros((), x.dtype), x, sigma, values, reference)
            centred = values - reference
            # Per element: weight -score(z) / sigma for x, -(z score(z) + 1) / sigma for sigma.
            weights = _log_density_tangent(score, z_at, sigma, x_dot, sigma_dot, elementwise=True)
            return jnp.mean(values + centred * (weight - 1.0), axis=0), jnp.mean(weight * centred * weights, axis=0)
        values, terms = evaluate(lambda v, dv: jax.jvp(f, (v,), (dv,)), perturbed, x_dot[None] + sigma_dot * z_at)
        anchor = checked(jnp.zeros((), x.dtype), x, sigma, values)
        weight = ratio(z, x, sigma) + anchor
        if antithetic or num_samples < 2:
            others = jnp.zeros_like(terms)
        else:
            others = (jnp.sum(terms, axis=0, keepdims=True) - terms) / (num_samples - 1)
        tangent = jnp.mean(terms, axis=0) + jnp.mean((weight - 1.0) * (terms - others), axis=0)
        # tied to the checks, as in smooth()
        return rule(key, x, sigma), tangent + anchor * (x_dot + sigma_dot)

    def smoothed(key, x):
        _checks.check_key(key)
        sigma_array = _checks.check_positive_scalar(sigma, "sigma")
        x = jnp.asarray(x)
        _checks.check_floating_tree(x, "x")
        out = jax.eval_shape(f, x)
        if not isinstance(out, jax.ShapeDtypeStruct) or out.shape != x.shape:
            raise ValueError(f"f must act elementwise: it maps shape {x.shape} to {getattr(out, 'shape', out)}")
        return rule(key, x, sigma_array.astype(x.dtype))

    return smoothed
