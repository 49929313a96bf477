"""Running an expensive step only for the members of a ``vmap`` batch that need it.

Under ``jax.vmap`` a ``lax.cond`` with a batched predicate computes both branches for every
member, and a ``lax.while_loop`` runs as long as its slowest member: one member of 64 whose
contact problem the cheap path did not solve (see :class:`rsmooth.sim.NCPSolver`) makes the
whole batch pay for the expensive path. :func:`run_where_needed` gathers the members that need
it into chunks of a fixed size and runs the expensive path on those chunks only (static
shapes: the chunk size is fixed, the number of chunks a loop's trip count). JAX has no
primitive for this stream compaction; it is written here with
``jax.custom_batching.custom_vmap``, whose batching rule sees the whole batch.
"""

from __future__ import annotations

from typing import Any, Callable

import jax
import jax.numpy as jnp
from jax import lax
from jax.custom_batching import custom_vmap

__all__ = ["once_if", "run_where_needed"]


def once_if(fn: Callable, needed, operand, state):
    """``fn(operand, state)`` if ``needed`` else ``state``, for one problem: a loop run 0 or 1
    times (under ``vmap``, as long as some member needs it: :func:`run_where_needed` runs it
    only for those). Its body passes the operand through an optimization barrier with the carry, or XLA
    may hoist work that depends on the operand only out of the loop, where it runs whether the
    loop does or not."""

    def body(carry):
        operand_, (_, state_) = lax.optimization_barrier((operand, carry))
        return jnp.ones((), bool), fn(operand_, state_)

    return lax.while_loop(lambda carry: ~carry[0], body, (~needed, state))[1]


def run_where_needed(fn: Callable[[Any, Any], Any], needed, operand, state, *, chunk: int | None = 8):
    """``fn(operand, state)`` where ``needed``, ``state`` elsewhere, computing ``fn`` only where
    needed, also under ``jax.vmap``.

    Without ``vmap`` this is a branch. Under ``vmap`` (batch ``B``), when ``B > chunk``, the
    members with ``needed`` set are gathered, ``chunk`` at a time, and ``fn`` runs vmapped on
    each chunk in a loop: the cost is that of ``ceil(count / chunk)`` chunks rather than of the
    whole batch, and a loop inside ``fn`` runs as long as the slowest member of its chunk, not
    of the batch. ``fn`` may also be evaluated on members that do not need it (to fill the last
    chunk), whose results are discarded; it must be safe to call on any member.

    Args:
        fn: ``(operand, state) -> new state``, with the structure, shapes and dtypes of
            ``state``.
        needed: boolean scalar (per member).
        operand: pytree of arrays ``fn`` reads.
        state: pytree of arrays ``fn`` updates.
        chunk: members per chunk under ``vmap``; ``None``: the whole batch at once (``fn`` runs
            for every member, as long as one needs it).

    Returns:
        The new state.

    Derivatives: none; call it on values without tangents (under ``lax.stop_gradient``).

    Example:
        >>> import jax, jax.numpy as jnp
        >>> f = lambda x: run_where_needed(lambda a, s: s + a, x > 2, 10.0, x, chunk=2)
        >>> jax.vmap(f)(jnp.arange(6.0)).tolist()
        [0.0, 1.0, 2.0, 13.0, 14.0, 15.0]
    """
    if chunk is not None and not (isinstance(chunk, int) and not isinstance(chunk, bool) and chunk >= 1):
        raise ValueError(f"chunk must be an int >= 1 or None, got {chunk!r}")

    @custom_vmap
    def run(needed, operand, state):
        return once_if(fn, needed, operand, state)

    @run.def_vmap
    def _rule(axis_size, in_batched, needed, operand, state):
        def batched(x, is_batched):
            return x if is_batched else jnp.broadcast_to(x, (axis_size,) + jnp.shape(x))

        needed_batched, operand_batched, state_batched = in_batched
        needed = batched(needed, needed_batched)
        operand = jax.tree.map(batched, operand, operand_batched)
        state = jax.tree.map(batched, state, state_batched)
        if chunk is None or axis_size <= chunk:
            out = jax.vmap(lambda n, o, s: once_if(fn, n, o, s))(needed, operand, state)
            return out, jax.tree.map(lambda _: True, out)
        count = jnp.sum(needed, dtype=jnp.int32)
        num_chunks = -(-axis_size // chunk)
        # members that need fn first (a stable sort of the flags), padded to whole chunks
        order = jnp.argsort(~needed, stable=True).astype(jnp.int32)
        order = jnp.concatenate([order, jnp.zeros((num_chunks * chunk - axis_size,), jnp.int32)])

        def body(carry):
            operand_, (k, state_) = lax.optimization_barrier((operand, carry))
            index = lax.dynamic_slice(order, (k * chunk,), (chunk,))
            new = jax.vmap(fn)(jax.tree.map(lambda a: a[index], operand_), jax.tree.map(lambda a: a[index], state_))
            # positions past the count (members that did not need fn, or padding) are dropped
            target = jnp.where(k * chunk + jnp.arange(chunk, dtype=jnp.int32) < count, index, axis_size)
            state_ = jax.tree.map(lambda a, b: a.at[target].set(b, mode="drop"), state_, new)
            return k + 1, state_

        out = lax.while_loop(lambda carry: carry[0] * chunk < count, body, (jnp.zeros((), jnp.int32), state))[1]
        return out, jax.tree.map(lambda _: True, out)

    return run(needed, operand, state)
