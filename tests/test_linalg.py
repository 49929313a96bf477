"""rsmooth._linalg: JAX's dense linear algebra, with batches handed to jaxlib's CPU LAPACK
kernels only in chunks those kernels run inline (larger ones wait on XLA's thread pool and can
deadlock the program). Values and derivatives against JAX's own functions; the invariant
that prevents the deadlock, read from the lowered programs of a batched contact step."""

from __future__ import annotations

import functools
import math
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rsmooth import _linalg as linalg
from rsmooth import sim


def _spd(key, n, batch=()):
    a = jax.random.normal(key, batch + (n, n))
    return a @ jnp.swapaxes(a, -1, -2) + n * jnp.broadcast_to(jnp.eye(n), batch + (n, n))


def _close(a, b, tol=1e-11):
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=tol, atol=tol)


def test_values_are_jax_s():
    a = _spd(jax.random.key(0), 6)
    b = jax.random.normal(jax.random.key(1), (6, 3))
    factor = jnp.linalg.cholesky(a)
    _close(linalg.cholesky(a), factor)
    for trans in (False, True):
        reference = jax.scipy.linalg.solve_triangular(factor, b, lower=True, trans=int(trans))
        _close(linalg.solve_triangular(factor, b, trans=trans), reference)
        _close(linalg.solve_triangular(factor, b[:, 0], trans=trans), reference[:, 0])  # a vector
        upper = jax.scipy.linalg.solve_triangular(factor.T, b, lower=False, trans=int(trans))
        _close(linalg.solve_triangular(factor.T, b, lower=False, trans=trans), upper)
    _close(linalg.cho_solve(linalg.cho_factor(a), b), jnp.linalg.solve(a, b))
    _close(linalg.cho_solve(jax.scipy.linalg.cho_factor(a), b), jnp.linalg.solve(a, b))  # an upper factor
    general = a + jnp.triu(a)
    _close(linalg.solve(general, b), jnp.linalg.solve(general, b))
    eigenvalues, eigenvectors = linalg.eigh(a)
    _close(eigenvalues, jnp.linalg.eigh(a)[0])
    _close(eigenvectors @ jnp.diag(eigenvalues) @ eigenvectors.T, a)
    assert bool(jnp.all(jnp.isnan(linalg.cholesky(-a)[jnp.tril_indices(6)])))  # not positive definite: NaN, as JAX
    # leading axes, values and forward derivative (no rank promotion in the JVP)
    stack, direction = jnp.stack([a, 2.0 * a]), jnp.stack([b @ b.T, a])
    values, tangents = jax.jvp(linalg.cholesky, (stack,), (direction,))
    reference = jax.jvp(jnp.linalg.cholesky, (stack,), (direction,))
    _close(values, reference[0])
    _close(tangents, reference[1])
    u, s, vt = linalg.svd(b)
    _close(u @ jnp.diag(s) @ vt, b)
    _close(s, jnp.linalg.svd(b, compute_uv=False))
    # rank 3 of 6, one singular value 3e-7 of the largest (kept by the cut of 1e-13)
    left, right = np.linalg.qr(np.random.default_rng(0).normal(size=(6, 6)))[0], np.linalg.qr(np.random.default_rng(1).normal(size=(6, 6)))[0]
    matrix = left @ np.diag([3.0, 1.0, 1e-6, 0, 0, 0]) @ right.T
    rhs = np.random.default_rng(2).normal(size=6)
    solution = np.asarray(linalg.min_norm_solve(matrix, rhs, rcond=1e-13))
    np.testing.assert_allclose(solution, np.linalg.lstsq(matrix, rhs, rcond=1e-13)[0], rtol=1e-8, atol=1e-8 * np.abs(solution).max())
    assert np.linalg.norm(solution @ right[:, 3:]) < 1e-8 * np.linalg.norm(solution)  # minimum norm: no null-space part


def _ours(a, b):
    a = 0.5 * (a + a.T)
    factor = linalg.cholesky(a)
    x = linalg.cho_solve((factor, True), b)
    y = linalg.solve(a + jnp.triu(a), x)
    z = linalg.solve_triangular(factor, y, trans=True)
    return jnp.sum(jnp.sin(z)) + jnp.sum(factor**2 * jnp.arange(a.shape[0])[None, :])


def _jax_s(a, b):
    a = 0.5 * (a + a.T)
    factor = jnp.linalg.cholesky(a)
    x = jax.scipy.linalg.cho_solve((factor, True), b)
    y = jnp.linalg.solve(a + jnp.triu(a), x)
    z = jax.scipy.linalg.solve_triangular(factor, y, lower=True, trans=1)
    return jnp.sum(jnp.sin(z)) + jnp.sum(factor**2 * jnp.arange(a.shape[0])[None, :])


def _derivatives(f, a, b, direction, batch_a, batch_b):
    """Reverse and forward derivatives of ``f`` in both arguments, reverse over forward, and
    batched: one program (compile time)."""

    def curvature(a, b):  # gradient of the derivative of f along `direction`
        return jax.grad(lambda a, b: jax.jvp(lambda a: f(a, b), (a,), (direction,))[1], argnums=(0, 1))(a, b)

    return (jax.grad(f, (0, 1))(a, b), jax.jacfwd(f, (0, 1))(a, b), curvature(a, b),
            jax.vmap(jax.grad(f))(batch_a, batch_b),
            jax.grad(lambda a, bs: jax.vmap(f, (None, 0))(a, bs).sum())(a, batch_b))


def test_derivatives_are_jax_s_forward_reverse_second_order_and_batched():
    args = (_spd(jax.random.key(2), 5), jax.random.normal(jax.random.key(3), (5, 2)), jax.random.normal(jax.random.key(4), (5, 5)),
            _spd(jax.random.key(5), 5, (4,)), jax.random.normal(jax.random.key(6), (4, 5, 2)))
    ours = jax.jit(functools.partial(_derivatives, _ours))(*args)
    theirs = jax.jit(functools.partial(_derivatives, _jax_s))(*args)
    for mine, reference in zip(jax.tree.leaves(ours), jax.tree.leaves(theirs)):
        _close(mine, reference, 1e-9)


def test_eigh_is_not_differentiable():
    with pytest.raises(NotImplementedError, match="rsmooth_eigh"):
        jax.grad(lambda a: linalg.eigh(a)[0].sum())(_spd(jax.random.key(0), 3))


def test_which_jaxlib_releases_pool_their_batches(monkeypatch):
    import importlib.metadata

    for version, pooled in [("0.9.2", False), ("0.10.0", True), ("0.10.2", True), ("0.11.0", True), ("0.11.1", False)]:
        monkeypatch.setattr(importlib.metadata, "version", lambda name, v=version: v)
        assert linalg._jaxlib_pools_batches() is pooled, version
    assert linalg.chunk_size(10**9) == 1 and linalg.chunk_size(1000) == 199


# jaxlib's flop estimate per matrix (jaxlib/cpu/lapack_kernels.cc), from the custom call's
# operand shapes: a batch runs inline while batch x estimate < 200,000
_ESTIMATES = {
    "trsm": lambda shapes: shapes[1][-2] ** 2 * shapes[1][-1],
    "potrf": lambda shapes: shapes[0][-1] ** 3 // 3,
    "getrf": lambda shapes: shapes[0][-2] * shapes[0][-1] * min(shapes[0][-2:]),
    "syevd": lambda shapes: 5 * shapes[0][-1] ** 3,
    "gesdd": lambda shapes: 10 * shapes[0][-2] * shapes[0][-1] * min(shapes[0][-2:]),
}


def _lapack_calls(text: str):
    """(kernel, batch, estimate) of every LAPACK custom call in a StableHLO module's text."""
    calls = []
    for line in text.splitlines():
        match = re.search(r"custom_call @lapack_[sdcz](\w+?)_ffi\(", line)
        if match is None:
            continue
        kernel, operands = match.group(1), line.rsplit(" : (", 1)[1].split(" -> ")[0]
        shapes = [tuple(int(d) for d in t.split("x")[:-1]) for t in re.findall(r"tensor<([^>]*)>", operands)]
        calls.append((kernel, math.prod(shapes[0][:-2]), _ESTIMATES[kernel](shapes)))
    return calls


@pytest.mark.skipif(jax.default_backend() != "cpu" or not linalg.POOLED_BATCHES,
                    reason="the chunking applies to the CPU under a jaxlib that pools LAPACK batches")
def test_a_batched_contact_step_hands_lapack_only_batches_it_runs_inline():
    # 64 cubes: the Delassus matrix (24 x 24), the step Jacobians' solves (many columns),
    # batched whole, would be over the threshold, so they must arrive in chunks (inside a
    # loop); a call site that used jnp.linalg or jax.scipy.linalg directly would show up here
    # with the whole batch. (A batched Solo-12 step with Jacobians, called repeatedly on two
    # cores, stopped for good when its solves were batched whole.)
    cube = sim.cube()
    xs, us = jnp.tile(cube.initial_state(), (64, 1)), jnp.zeros((64, cube.nu))
    for program in (jax.vmap(cube.step), jax.vmap(cube.step_and_jacobians)):
        text = jax.jit(program).lower(xs, us).as_text()
        calls = _lapack_calls(text)
        assert calls, "no LAPACK call found: the parser no longer reads the lowered text"
        assert any(batch > 1 for _, batch, _ in calls)  # still batched where that is inline
        over = [call for call in calls if call[1] > 1 and call[1] * call[2] >= linalg.INLINE_WORK]
        assert not over, f"LAPACK batches that jaxlib would split over its thread pool: {over}"
    # and the batched loop computes what one call does
    big, rhs = _spd(jax.random.key(7), 40, (16,)), jax.random.normal(jax.random.key(8), (16, 40, 40))
    _close(jax.jit(jax.vmap(linalg.solve_triangular))(jax.vmap(linalg.cholesky)(big), rhs),
           jax.scipy.linalg.solve_triangular(jnp.linalg.cholesky(big), rhs, lower=True), 1e-10)
