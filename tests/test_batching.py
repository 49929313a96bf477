"""rsmooth._batching.run_where_needed: the same results as a masked evaluation, with the
expensive function evaluated on the needed members' chunks only."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rsmooth._batching import run_where_needed


def _iterate(a, state):
    """A loop whose trip count depends on the member (as the contact solver's do)."""
    count, value = state

    def body(carry):
        return carry[0] + 1, 0.5 * carry[1] + a

    _, value = jax.lax.while_loop(lambda c: c[0] < count.astype(jnp.int32), body, (jnp.zeros((), jnp.int32), value))
    return count + 100.0, value


def _masked(needed, a, state):
    return jax.tree.map(lambda new, old: jnp.where(needed, new, old), _iterate(a, state), state)


@pytest.mark.parametrize("batch", [1, 3, 4, 9, 21])
def test_equals_masked_evaluation(batch, getkey):
    needed = jax.random.bernoulli(getkey(), 0.3, (batch,))
    a = jax.random.normal(getkey(), (batch,))
    state = (jnp.arange(batch, dtype=float) % 5, jax.random.normal(getkey(), (batch,)))
    got = jax.jit(jax.vmap(lambda n, a, s: run_where_needed(_iterate, n, a, s, chunk=4)))(needed, a, state)
    want = jax.vmap(_masked)(needed, a, state)
    for x, y in zip(got, want):
        np.testing.assert_array_equal(x, y)
    # an operand shared by the batch (not batched)
    got = jax.jit(jax.vmap(lambda n, s: run_where_needed(_iterate, n, 0.25, s, chunk=4)))(needed, state)
    want = jax.vmap(lambda n, s: _masked(n, 0.25, s))(needed, state)
    for x, y in zip(got, want):
        np.testing.assert_array_equal(x, y)


def test_nested_vmap_and_unbatched(getkey):
    needed = jax.random.bernoulli(getkey(), 0.3, (3, 10))
    a = jax.random.normal(getkey(), (3, 10))
    state = (jnp.full((3, 10), 3.0), jnp.zeros((3, 10)))
    got = jax.jit(jax.vmap(jax.vmap(lambda n, a, s: run_where_needed(_iterate, n, a, s, chunk=4))))(needed, a, state)
    want = jax.vmap(jax.vmap(_masked))(needed, a, state)
    for x, y in zip(got, want):
        np.testing.assert_array_equal(x, y)
    for flag in (True, False):
        one = run_where_needed(_iterate, jnp.array(flag), 1.0, (jnp.array(2.0), jnp.array(1.0)))
        expected = (102.0, 1.75) if flag else (2.0, 1.0)
        assert [float(v) for v in one] == list(expected)


def test_evaluates_only_the_needed_chunks():
    """One member of 16 needs the function: with chunks of 4 it runs on 4 members, not 16; none
    needs it: it does not run."""
    seen = []

    def recorded(a, state):
        jax.debug.callback(lambda x: seen.append(np.asarray(x).size), a)
        return _iterate(a, state)

    run = jax.jit(jax.vmap(lambda n, a, s: run_where_needed(recorded, n, a, s, chunk=4)))
    a = jnp.linspace(0.0, 1.0, 16)
    state = (jnp.full(16, 2.0), jnp.zeros(16))
    for count, evaluations in ((1, 4), (5, 8), (0, 0), (16, 16)):
        seen.clear()
        out = run(jnp.arange(16) < count, a, state)
        jax.block_until_ready(out)
        jax.effects_barrier()
        assert sum(seen) == evaluations
        np.testing.assert_array_equal(out[0], jnp.where(jnp.arange(16) < count, 102.0, 2.0))


def test_rejects_a_bad_chunk():
    with pytest.raises(ValueError, match="chunk"):
        run_where_needed(_iterate, jnp.array(True), 1.0, (jnp.array(1.0), jnp.array(1.0)), chunk=0)


def test_whole_batch_chunk(getkey):
    """chunk=None (NCPSolver's choice on a GPU): the masked evaluation's results, the function
    evaluated on the whole batch as soon as one member needs it, not at all when none does."""
    seen = []

    def recorded(a, state):
        jax.debug.callback(lambda x: seen.append(np.asarray(x).size), a)
        return _iterate(a, state)

    run = jax.jit(jax.vmap(lambda n, a, s: run_where_needed(recorded, n, a, s, chunk=None)))
    needed = jax.random.bernoulli(getkey(), 0.3, (9,)).at[0].set(True)
    a = jax.random.normal(getkey(), (9,))
    state = (jnp.arange(9, dtype=float) % 5, jax.random.normal(getkey(), (9,)))
    for flags, evaluations in ((needed, 9), (jnp.zeros(9, bool), 0)):
        seen.clear()
        got = jax.block_until_ready(run(flags, a, state))
        jax.effects_barrier()
        assert sum(seen) == evaluations
        for x, y in zip(got, jax.vmap(_masked)(flags, a, state)):
            np.testing.assert_array_equal(x, y)
    with pytest.raises(ValueError, match="chunk"):
        run_where_needed(_iterate, jnp.array(True), 1.0, (jnp.array(1.0), jnp.array(1.0)), chunk=True)
