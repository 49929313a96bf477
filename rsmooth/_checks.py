"""Argument checks shared by the public functions.

Host checks raise `TypeError`/`ValueError` before anything is traced. Values that are traced
(under `jax.jit`, `jax.vmap`, `jax.grad`) cannot be inspected on the host: they are checked at
run time with `equinox.error_if`, which raises an error carrying the same message when the
compiled program runs (the documented mechanism for checks under `jit`).
"""

from __future__ import annotations

import contextlib
import numbers
import threading

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np


def _trace_flag():
    """The flag of :func:`without_traced_checks`, as a JAX configuration state included in the
    trace context: JAX's caches of traced functions (``jax.jit``, ``make_jaxpr``) are then
    keyed on it, so a function traced inside the context is traced again outside it instead
    of reusing a program without its checks. That state is defined through ``jax._src.config``
    (JAX has no public way to add one); where that is missing, a thread-local flag, which
    those caches do not see."""
    try:
        from jax._src import config as jax_config

        return jax_config.bool_state(
            "rsmooth_traced_checks", True, "rsmooth's traced checks (rsmooth._checks)", include_in_trace_context=True
        )
    except (ImportError, AttributeError, TypeError):  # pragma: no cover - another JAX
        return None


_FLAG = _trace_flag()
_LOCAL = threading.local()


@contextlib.contextmanager
def without_traced_checks():
    """Programs traced inside leave out rsmooth's traced checks (:func:`error_if`).

    For solvers that test finiteness themselves and report it in their result (DDP, R-DDP,
    policy optimization, a rollout whose diagnostics the caller checks): a traced check is a
    host callback in the compiled program, and JAX's persistent compilation cache does not
    store programs with host callbacks, so every run would compile them again. Checks that a user asks for (``throw=True``) are kept.
    """
    if _FLAG is not None:
        with _FLAG(False):
            yield
        return
    previous = getattr(_LOCAL, "checks", True)
    _LOCAL.checks = False
    try:
        yield
    finally:
        _LOCAL.checks = previous


def traced_checks() -> bool:
    """False inside :func:`without_traced_checks`."""
    return bool(_FLAG.value) if _FLAG is not None else getattr(_LOCAL, "checks", True)


def error_if(x, pred, message: str):
    """`equinox.error_if`, left out inside :func:`without_traced_checks`."""
    return eqx.error_if(x, pred, message) if traced_checks() else x


def branched_error_if(x, pred, index, messages):
    """`equinox.branched_error_if`, left out inside :func:`without_traced_checks`."""
    return eqx.branched_error_if(x, pred, index, messages) if traced_checks() else x


def jit_checked_on_host(fn, what: str):
    """``jax.jit(fn)``, its program traced :func:`without_traced_checks`, and its floating
    outputs checked on the host instead: a non-finite one raises ``FloatingPointError``
    naming ``what`` and the output. For the programs an experiment or a fitting loop calls,
    which JAX's persistent compilation cache can then keep between runs."""
    compiled = jax.jit(without_traced_checks()(fn))

    def call(*args, **kwargs):
        out = compiled(*args, **kwargs)
        check_outputs_on_host(out, what)
        return out

    return call


def check_outputs_on_host(out, what: str) -> None:
    """Raises ``FloatingPointError`` if a floating leaf of ``out`` holds NaN or inf."""
    for path, leaf in jax.tree_util.tree_leaves_with_path(out):
        if jnp.issubdtype(jnp.result_type(leaf), jnp.inexact) and not np.all(np.isfinite(np.asarray(leaf))):
            name = jax.tree_util.keystr(path) or "the output"
            raise FloatingPointError(f"{what}: {name} is not finite (NaN or inf)")


def is_traced(value) -> bool:
    return isinstance(value, jax.core.Tracer)


def check_key(key, name: str = "key") -> None:
    """A PRNG key: a typed key array (`jax.random.key`) or a raw uint32 key of shape (2,)."""
    dtype = getattr(key, "dtype", None)
    if dtype is not None and jax.dtypes.issubdtype(dtype, jax.dtypes.prng_key):
        if np.shape(key) != ():
            raise ValueError(f"{name} must be a single PRNG key, got a key array of shape {np.shape(key)}")
        return
    if dtype is not None and dtype == jnp.uint32 and np.shape(key) == (2,):
        return
    raise TypeError(
        f"{name} must be a PRNG key from jax.random.key(seed) (or jax.random.PRNGKey), "
        f"got {type(key).__name__} with dtype {dtype}"
    )


def check_num_samples(num_samples, name: str = "num_samples", minimum: int = 1) -> int:
    if isinstance(num_samples, bool) or not isinstance(num_samples, numbers.Integral):
        raise TypeError(f"{name} must be a Python int (it fixes array shapes), got {num_samples!r}")
    if num_samples < minimum:
        raise ValueError(f"{name} must be >= {minimum}, got {num_samples}")
    return int(num_samples)


def check_positive_number(value, name: str) -> float:
    """A positive, finite Python or NumPy scalar (a static setting, checked on the host: no JAX
    array is made, so that building a configuration at import time does not start a backend)."""
    if isinstance(value, bool) or np.ndim(value) != 0 or is_traced(value):
        raise ValueError(f"{name} must be a positive number, got {value!r}")
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a positive number, got {value!r}") from None
    if not (np.isfinite(number) and number > 0):
        raise ValueError(f"{name} must be positive and finite, got {number}")
    return number


def check_positive_scalar(value, name: str):
    """A positive, finite scalar; returns it as a JAX array (checked at run time if traced)."""
    if np.ndim(value) != 0:
        raise ValueError(f"{name} must be a scalar, got shape {np.shape(value)}")
    array = jnp.asarray(value)
    if not jnp.issubdtype(array.dtype, jnp.floating):
        array = array.astype(float)
    if is_traced(value):
        bad = ~(jnp.isfinite(array) & (array > 0))
        return error_if(array, bad, f"{name} must be positive and finite")
    if not (np.isfinite(float(value)) and float(value) > 0):
        raise ValueError(f"{name} must be positive and finite, got {float(value)}")
    return array


def check_floating_tree(tree, name: str) -> None:
    leaves = jax.tree.leaves(tree)
    if not leaves:
        raise ValueError(f"{name} must contain at least one array, got an empty pytree")
    for leaf in leaves:
        dtype = jnp.result_type(leaf)
        if not jnp.issubdtype(dtype, jnp.floating):
            raise TypeError(
                f"{name} must hold floating-point arrays (smoothing perturbs them), got dtype {dtype}"
            )


def check_finite(array, message: str):
    """Returns `array`, raising `ValueError(message)` now if it is concrete and not finite,
    or an `equinox` runtime error with the same message when a traced value is not finite."""
    if is_traced(array):
        return error_if(array, ~jnp.all(jnp.isfinite(array)), message)
    # NumPy, not jnp: inside a jit trace even operations on concrete arrays are staged.
    if not np.all(np.isfinite(np.asarray(array))):
        raise ValueError(message)
    return array


def check_all(output, finite=(), conditions=()):
    """Returns `output`, after checking that every array of `finite` is finite and that no
    condition of `conditions` holds.

    `finite` is a sequence of `(array, message)`, `conditions` of `(failed, message)` with
    `failed` a boolean scalar. Concrete ones are checked now (`ValueError(message)` for the
    first failure); traced ones together by a single `equinox` runtime check tied to `output`:
    it runs wherever `output` is used, so tie it to a value that every result needs (in a
    derivative rule, a value that the tangent is computed from).
    """
    traced = []
    for array, message in finite:
        if is_traced(array):
            traced.append((~jnp.all(jnp.isfinite(array)), message))
        else:
            check_finite(array, message)
    for failed, message in conditions:
        if is_traced(failed):
            traced.append((jnp.asarray(failed), message))
        elif bool(np.asarray(failed)):
            raise ValueError(message)
    if not traced:
        return output
    failures = jnp.stack([failed for failed, _ in traced])
    return branched_error_if(output, jnp.any(failures), jnp.argmax(failures), [m for _, m in traced])


def resolution_failure(x, sigma, name: str = "x"):
    """`(failed, message)`: whether `sigma` is below the resolution of `x`'s dtype at every
    coordinate of `x`, :math:`\\sigma < \\epsilon \\min_k |x_k|` (`eps` the dtype's machine
    epsilon): then `x + sigma * z` rounds to `x` for a typical `|z| <= 1`, and a score-function
    estimate is zero. (At some coordinates only is allowed: a far coordinate may be a
    deliberate sentinel, as a renderer's empty slot.) `failed` is a Python bool when `x` and
    `sigma` are concrete (the message then gives their values), a traced boolean otherwise
    (for :func:`check_all`)."""
    dtype = jnp.result_type(x)
    eps = float(jnp.finfo(dtype).eps)
    message = (
        f"sigma is below the resolution of {name}'s dtype {dtype} at every coordinate of {name}: "
        f"sigma < eps * min|{name}_k| (eps = {eps:.3g}), so {name} + sigma * z rounds to {name} "
        f"and the zeroth-order estimate is zero; use a larger sigma, a rescaled {name}, "
        "float64 or the first-order estimator"
    )
    if np.size(x) == 0:
        return False, message
    if not is_traced(x) and not is_traced(sigma):
        scale = float(np.min(np.abs(np.asarray(x))))
        value = float(np.asarray(sigma))
        return bool(value < eps * scale), f"{message} (sigma = {value:.3g}, min|{name}_k| = {scale:.3g})"
    return jnp.asarray(sigma, dtype) < eps * jnp.min(jnp.abs(x)), message
