r"""`smooth(f)`: the randomly smoothed function as a JAX function with estimated derivatives.

`g = smooth(f, sigma=..., num_samples=...)` returns `g(key, x)`, the Monte-Carlo estimate of
:math:`f_\sigma(x) = \mathbb{E}\, f(x + \sigma z)`, whose derivatives under `jax.grad`,
`jax.jacrev`, `jax.jacfwd` and `jax.jvp` are the chosen estimator's (computed on the same
samples as the value). `g` works under `jit` and `vmap` and can sit inside a larger model.

The zeroth- and first-order rules are matrix-free: a tangent costs one weighted mean
(zeroth order) or one `jvp` of `f` per sample (first order), and the Jacobian is never formed,
so `f` may map many inputs to many outputs (an image). The alpha-order rule needs both
estimates' variances, so it forms the Jacobian.

Derivatives with respect to `sigma` (when it is traced, e.g. by an outer `jax.grad`) are
estimated too, with the estimator's own formula; derivatives with respect to values that `f`
closes over (model parameters) are pathwise: the mean over samples of `f`'s own derivative.
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
from jax.typing import ArrayLike

from rsmooth import _checks
from rsmooth import estimators as _est
from rsmooth._xla import matmul as _matmul
from rsmooth.noise import Gaussian, Noise

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

    Returns:
        `g(key, x)` with the shape of `f(x)`.

    Example:
        >>> import jax, jax.numpy as jnp, rsmooth
        >>> step = lambda x: jnp.where(x > 0, 1.0, 0.0)
        >>> g = rsmooth.smooth(step, sigma=1.0, num_samples=20000)
        >>> abs(float(jax.grad(g, argnums=1)(jax.random.key(0), 0.0)) - 0.3989) < 0.02
        True

    References:
        Berthet et al., "Learning with differentiable perturbed optimizers", NeurIPS 2020;
        Suh, Simchowitz, Zhang, Tedrake, "Do differentiable simulators give better policy
        gradients?", ICML 2022.
    """
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
    options = dict(
        num_samples=num_samples,
        estimator=estimator,
        noise=noise,
        baseline=baseline,
        antithetic=antithetic,
        gamma=gamma,
        lipschitz=lipschitz,
        delta=delta,
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
        rule = _smoothed_flat(converted, len(consts), **options)
        return jnp.reshape(rule(key, flat.x, sigma_array, *consts), flat.out_shape)

    return smoothed


def _smoothed_flat(f_converted, num_consts, *, num_samples, estimator, noise, baseline, antithetic, gamma, lipschitz, delta):
    def points(key, x, sigma):
        """The perturbed points, the same the estimators use for this key."""
        if estimator == "alpha":
            key_zeroth, key_first = jax.random.split(key)
            n_zeroth = num_samples // 2
            z0, p0 = _est.perturbed_points(noise, key_zeroth, x, sigma, n_zeroth, antithetic)
            z1, p1 = _est.perturbed_points(noise, key_first, x, sigma, num_samples - n_zeroth, antithetic)
            return jnp.concatenate([z0, z1]), jnp.concatenate([p0, p1])
        return _est.perturbed_points(noise, key, x, sigma, num_samples, antithetic)

    def checked(value, x, values):
        return _checks.check_all_finite(value, [(x, _est._NONFINITE_X), (values, _est._NONFINITE_F)])

    @jax.custom_jvp
    def rule(key, x, sigma, *consts):
        _, perturbed = points(key, x, sigma)
        values = jax.vmap(lambda v: f_converted(v, *consts))(perturbed)
        return checked(jnp.mean(values, axis=0), x, values)

    @rule.defjvp
    def rule_jvp(primals, tangents):
        key, x, sigma, *consts = primals
        _, x_dot, sigma_dot, *consts_dot = tangents
        f = lambda v: f_converted(v, *consts)  # noqa: E731
        z, perturbed = points(key, x, sigma)
        if estimator == "zeroth":
            values = jax.vmap(f)(perturbed)
            score = noise.score(z)
            centred = values - _est.baseline_values(values, baseline, lambda: f(x))
            # Linear in (x_dot, sigma_dot); the same weights as zeroth_order's (see there).
            weights = (-_matmul(score, x_dot) - sigma_dot * (jnp.sum(z * score, axis=-1) + x.shape[0])) / sigma
            value = checked(jnp.mean(values, axis=0), x, values)
            tangent = jnp.mean(centred * weights[:, None], axis=0)
        elif estimator == "first":
            values, tangents_out = jax.vmap(
                lambda zi, vi: jax.jvp(f, (vi,), (x_dot + sigma_dot * zi,))
            )(z, perturbed)
            value = checked(jnp.mean(values, axis=0), x, values)
            tangent = jnp.mean(tangents_out, axis=0)
        else:
            x = _checks.check_finite(x, _est._NONFINITE_X)
            flat = _est._Flat(x, f, None, ())
            estimate, _ = _est._alpha_order_flat(
                flat, key, sigma, num_samples, noise, baseline, antithetic, gamma, lipschitz, delta
            )
            value = estimate.value
            tangent = _matmul(estimate.jacobian, x_dot) + estimate.sigma_grad * sigma_dot
        if num_consts:
            # Pathwise derivative with respect to the values f closes over.
            def consts_tangent(v):
                return jax.jvp(lambda *c: f_converted(v, *c), tuple(consts), tuple(consts_dot))[1]

            tangent = tangent + jnp.mean(jax.vmap(consts_tangent)(perturbed), axis=0)
        return value, tangent

    return rule


def smooth_elementwise(
    f: Callable,
    *,
    sigma: ArrayLike,
    num_samples: int,
    estimator: str = "zeroth",
    noise: Noise = Gaussian(),
    baseline: bool | str = True,
    antithetic: bool = False,
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

    Returns:
        `g(key, x)`, an array of the shape of `x`.

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

    def samples(key, x):
        shape = (num_samples // 2 if antithetic else num_samples,) + x.shape
        z = noise.sample(key, shape, x.dtype)
        return jnp.concatenate([z, -z]) if antithetic else z

    def checked(value, x, values):
        return _checks.check_all_finite(value, [(x, _est._NONFINITE_X), (values, _est._NONFINITE_F)])

    @jax.custom_jvp
    def rule(key, x, sigma):
        values = f(x[None] + sigma * samples(key, x))
        return checked(jnp.mean(values, axis=0), x, values)

    @rule.defjvp
    def rule_jvp(primals, tangents):
        key, x, sigma = primals
        _, x_dot, sigma_dot = tangents
        z = samples(key, x)
        if estimator == "zeroth":
            values = f(x[None] + sigma * z)
            score = noise.score(z)
            centred = values - _est.baseline_values(values, baseline, lambda: f(x))
            # Per element: weight -score(z) / sigma for x, -(z score(z) + 1) / sigma for sigma.
            weights = (-score * x_dot[None] - sigma_dot * (z * score + 1.0)) / sigma
            tangent = jnp.mean(centred * weights, axis=0)
        else:
            values, tangent_values = jax.jvp(f, (x[None] + sigma * z,), (x_dot[None] + sigma_dot * z,))
            tangent = jnp.mean(tangent_values, axis=0)
        return checked(jnp.mean(values, axis=0), x, values), tangent

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
