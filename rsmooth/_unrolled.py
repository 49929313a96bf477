"""Reductions over a short last axis, unrolled into elementwise operations.

jaxlib 0.10's CPU backend hands reductions (``jnp.sum``, ``jnp.min``, ...) to YNNPACK
kernels that are slow when the reduced axis is short (2 to a few dozen) and the batch large:
the simulator's step Jacobian and the renderer's per-pixel sums over edges and vertices were
measured several times slower that way than as a chain of additions, which XLA fuses with
their producers into one loop. ``XLA_FLAGS=--xla_cpu_experimental_ynn_fusion_type=`` turns
the kernels off globally (see README); these helpers avoid them where it matters without a
flag. Use them only for short static axes (the chain is unrolled at trace time).
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


def min_last(values: jax.Array, keepdims: bool = False) -> jax.Array:
    """``jnp.min(values, axis=-1)`` for a short last axis."""
    return _reduce_last(values, jnp.minimum, keepdims)


def all_last(values: jax.Array, keepdims: bool = False) -> jax.Array:
    """``jnp.all(values, axis=-1)`` for a short last axis of booleans."""
    return _reduce_last(values, operator.and_, keepdims)
