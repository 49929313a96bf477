"""What the stiffness and chaos experiments share: a rollout objective of one scalar whose
value and derivative come from one compiled program, and the summaries over repeats.

Compilation dominates these experiments' time on CPU (a rollout through the simulator compiles
in seconds and runs in milliseconds). :func:`value_and_derivative` is one jitted function of
``(parameter, x)`` giving the objective and its forward-mode derivative; the zeroth-order
estimator evaluates its value, the first-order one its value and derivative (the estimator's
``value_and_jacobian`` option) and the landscape both, all under the same two vmaps (repeats,
samples) with batches of the same shape: they share one compiled program, for every value of
the parameter (a stiffness). That program is traced without rsmooth's traced checks
(:func:`rsmooth._checks.without_traced_checks`): a check is a host callback, and JAX's
persistent compilation cache does not keep a program with one, so every run would compile the
rollout again. The estimators check their samples, and :func:`evaluate_in_batches` its
values, for NaN and inf.
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from rsmooth import _checks


def value_and_derivative(objective: Callable) -> Callable:
    """``jit((parameter, x) -> (objective(parameter, x), d objective / d x))`` for a scalar
    ``x``, by one forward-mode pass (the derivative has the shape of the value), traced
    without the traced checks (see the module docstring)."""

    def both(parameter, x):
        return jax.jvp(lambda y: objective(parameter, y), (x,), (jnp.ones_like(x),))

    return jax.jit(_checks.without_traced_checks()(both))


def evaluate_in_batches(compiled: Callable, parameter, points: np.ndarray, batch_shape: tuple[int, int]):
    """Values and derivatives of ``compiled(parameter, .)`` at `points` (1-D), evaluated in
    batches of ``batch_shape`` (a vmap of a vmap, as the estimators run it under a vmap over
    repeats: the same compiled program). The last batch is padded with its last point.

    Raises:
      FloatingPointError: a value or derivative is NaN or inf.
    """
    size = int(np.prod(batch_shape))
    points = np.asarray(points, dtype=np.float64)
    count = points.shape[0]
    padded = np.concatenate([points, np.full((-count) % size, points[-1])])
    batched = jax.vmap(jax.vmap(lambda x: compiled(parameter, x)))
    values, derivatives = [], []
    for start in range(0, padded.shape[0], size):
        chunk = jnp.asarray(padded[start : start + size]).reshape(batch_shape)
        value, derivative = batched(chunk)
        _checks.check_outputs_on_host((value, derivative), "the landscape's rollouts")
        values.append(np.asarray(value).reshape((size,) + value.shape[2:]))
        derivatives.append(np.asarray(derivative).reshape((size,) + derivative.shape[2:]))
    return np.concatenate(values)[:count], np.concatenate(derivatives)[:count]


def mean_and_spread(values, axis: int = 0) -> dict:
    """``{"mean", "std", "median", "q16", "q84"}`` of `values` over `axis` (the repeats):
    plain lists or floats for metrics.json."""
    values = np.asarray(values, dtype=np.float64)
    return {
        "mean": np.mean(values, axis=axis),
        "std": np.std(values, axis=axis, ddof=1) if values.shape[axis] > 1 else np.zeros_like(np.mean(values, axis=axis)),
        "median": np.median(values, axis=axis),
        "q16": np.quantile(values, 0.16, axis=axis),
        "q84": np.quantile(values, 0.84, axis=axis),
    }


def gaussian_smoothed_gradient(offsets: np.ndarray, values: np.ndarray, sigma: float) -> np.ndarray:
    """The gradient of the Gaussian smoothing of ``f`` at ``x``, ``E[f(x + sigma z) z] / sigma``
    (Stein's identity), by the trapezoid rule from the values ``f(x + offsets)`` on a fine grid
    of `offsets` spanning several sigma on each side: it needs the values only, where the
    derivative of a stiff ``f`` is a spike the grid may not resolve."""
    z = np.asarray(offsets) / sigma
    weights = z * np.exp(-0.5 * z**2) / np.sqrt(2.0 * np.pi)
    return np.trapezoid(np.asarray(values) * weights.reshape((-1,) + (1,) * (np.ndim(values) - 1)), z, axis=0) / sigma
