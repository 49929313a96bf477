"""Reductions over a short last axis, unrolled into elementwise operations.

jaxlib 0.10's CPU backend hands reductions (``jnp.sum``, ``jnp.min``, ...) to YNNPACK
kernels that are slow when the reduced axis is short (2 to a few dozen) and the batch large:
the simulator's step Jacobian and the renderer's per-pixel sums over edges and vertices run
several times slower that way than as a chain of additions, which XLA fuses with their
producers into one loop. ``XLA_FLAGS=--xla_cpu_experimental_ynn_fusion_type=`` turns
the kernels off globally (see README); these helpers avoid them where it matters without a
flag. Use them only for short static axes (the chain is unrolled at trace time).

The same kernels come back in reverse mode: the transpose of a broadcast (``x[..., None] * y``)
is a reduction over the broadcast axis; the renderer writes its per-channel products out
instead.

A last slow path of the same backend, not a reduction: ``log1p`` inside a loop fused with
broadcasts is not vectorized (about 8x ``log``), and ``jax.nn.log_sigmoid`` is written with
it; :func:`log_sigmoid` is written with ``log``.
"""

from __future__ import annotations

import functools
import operator

import jax
import jax.numpy as jnp


def _reduce_last(values: jax.Array, op, keepdims: bool) -> jax.Array:
    if values.shape[-1] == 0:
        raise ValueError("cannot reduce an empty last axis")
    result = functools.reduce(op, (values[..., i] for i in range(values.shape[-1])))
    return result[..., None] if keepdims else result


def sum_last(values: jax.Array, keepdims: bool = False) -> jax.Array:
    """``jnp.sum(values, axis=-1)`` for a short last axis."""
    return _reduce_last(values, operator.add, keepdims)


@jax.custom_jvp
def log_sigmoid(values: jax.Array) -> jax.Array:
    """``jax.nn.log_sigmoid`` as ``min(x, 0) - log(1 + exp(-|x|))``: ``log`` instead of
    ``log1p`` (see the module's docstring; the renderer fuses it with per-pixel edge
    distances). The absolute error is the rounding of ``1 + exp(-|x|)``: below 1.2e-7 in
    float32, 2.3e-16 in float64. The derivative, ``sigmoid(-x)``, is given by hand (autodiff
    through ``min`` and ``abs`` gives 1 at 0 instead of 1/2)."""
    return jnp.minimum(values, 0.0) - jnp.log(1.0 + jnp.exp(-jnp.abs(values)))


@log_sigmoid.defjvp
def _log_sigmoid_jvp(primals, tangents):
    (values,), (tangent,) = primals, tangents
    e = jnp.exp(-jnp.abs(values))
    slope = jnp.where(values >= 0, e, 1.0) / (1.0 + e)  # sigmoid(-x), without overflow
    return jnp.minimum(values, 0.0) - jnp.log(1.0 + e), slope * tangent
