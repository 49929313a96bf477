"""Dense linear algebra for rsmooth's batched programs: JAX's own, without jaxlib's CPU deadlock.

jaxlib 0.10.0 to 0.11.0 split a batch of matrices that a CPU LAPACK kernel receives (a
vmapped Cholesky factorization, triangular solve, LU, symmetric eigendecomposition or singular
value decomposition) into tasks on XLA's intra-op thread pool and block the calling pool thread until they finish.
XLA runs independent operations of a program side by side on that same pool, so when every
pool thread is such a waiting kernel, nothing is left to run the tasks: the program stops,
with no CPU use and no error (a batched rollout of 64 towers of 16 boxes, on two cores, every
time). A kernel runs its batch inline, without the pool, where the batch times the kernel's
flop estimate is under 200,000 (``jaxlib/cpu/lapack_kernels.cc``, ``GetLapackBatchChunkSize``);
open-source builds after 0.11.0 never use the pool.

The functions here are JAX's (``jnp.linalg``, ``jax.scipy.linalg``) with the same results,
each its own primitive so that it keeps its batch dimensions through ``vmap``: compiled for a
CPU under an affected jaxlib, a batch is handed to LAPACK in chunks small enough to run
inline, one after another in a loop (a batch that is already small enough, the common case
for small robots, in one call); elsewhere (a GPU, an unaffected jaxlib) in one call. Writing
this here is the only fix available from a library: the kernels' thread pool is XLA's, and
jaxlib has no setting to keep them off it.

Derivatives: :func:`solve_triangular` and :func:`solve` are differentiable in both arguments,
forward and reverse (their tangents are again solves); :func:`cholesky` by its JVP
``dL = L Phi(L^-1 dA L^-T)`` (lower triangle, halved diagonal). :func:`eigh` and :func:`svd`
are not differentiable (rsmooth uses them inside solvers that are differentiated implicitly)
and raise if differentiated.
"""

from __future__ import annotations

import functools
import importlib.metadata

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.extend.core import Primitive
from jax.interpreters import ad, batching, mlir

# jaxlib's threshold for a batched kernel to run inline, in its own flop estimate
INLINE_WORK = 200_000


def _version(text: str) -> tuple[int, ...]:
    parts = []
    for part in text.split(".")[:3]:
        digits = "".join(c for c in part if c.isdigit()) if part else ""
        parts.append(int(digits) if digits else 0)
    return tuple(parts)


def _jaxlib_pools_batches() -> bool:
    """Whether the installed jaxlib splits CPU LAPACK batches over the intra-op pool."""
    try:
        version = _version(importlib.metadata.version("jaxlib"))
    except importlib.metadata.PackageNotFoundError:
        return True
    return (0, 10, 0) <= version <= (0, 11, 0)


POOLED_BATCHES = _jaxlib_pools_batches()


def chunk_size(cost: int) -> int:
    """The largest batch of matrices of LAPACK ``cost`` (jaxlib's flop estimate per matrix)
    that jaxlib runs inline: at least one."""
    return max(1, (INLINE_WORK - 1) // max(int(cost), 1))


def _over_batch(function, ndim: int):
    """``function`` vmapped over ``ndim`` leading dimensions."""
    for _ in range(ndim):
        function = jax.vmap(function)
    return function


def _batched(function, cost_of, *operands, **params):
    """Eager and default-platform evaluation: one call over the whole batch."""
    del cost_of
    return _over_batch(functools.partial(function, **params), operands[0].ndim - 2)(*operands)


def _cpu(function, cost_of, *operands, **params):
    """CPU evaluation: ``function`` (of unbatched matrices) over the leading batch dimensions
    that all ``operands`` share, in chunks of :func:`chunk_size` matrices, which jaxlib runs
    inline."""
    function = functools.partial(function, **params)
    batch_shape = operands[0].shape[:-2]
    size = int(np.prod(batch_shape, dtype=np.int64))
    chunk = chunk_size(cost_of(*operands))
    if not POOLED_BATCHES or size <= chunk:
        return _over_batch(function, len(batch_shape))(*operands)
    flat = tuple(x.reshape((size,) + x.shape[len(batch_shape):]) for x in operands)
    if chunk == 1:
        out = lax.map(lambda xs: function(*xs), flat)
    else:
        out = lax.map(lambda xs: function(*xs), flat, batch_size=chunk)
    return jax.tree.map(lambda y: y.reshape(batch_shape + y.shape[1:]), out)


def _define(name: str, function, cost_of, *, multiple_results: bool = False) -> Primitive:
    """A primitive evaluating ``function`` (of unbatched matrices) over leading batch
    dimensions shared by its operands; ``vmap`` adds one in front."""
    primitive = Primitive(f"rsmooth_{name}")
    primitive.multiple_results = multiple_results

    def impl(*operands, **params):
        if jax.default_backend() == "cpu":
            return _cpu(function, cost_of, *operands, **params)
        return _batched(function, cost_of, *operands, **params)

    primitive.def_impl(impl)

    def abstract(*avals, **params):
        batch_shape = avals[0].shape[:-2]
        unbatched = [jax.ShapeDtypeStruct(a.shape[len(batch_shape):], a.dtype) for a in avals]
        out = jax.eval_shape(functools.partial(function, **params), *unbatched)
        outs = out if multiple_results else (out,)
        shaped = [jax.core.ShapedArray(batch_shape + o.shape, o.dtype) for o in outs]
        return shaped if multiple_results else shaped[0]

    primitive.def_abstract_eval(abstract)

    def batch(operands, dims, **params):
        size = next(x.shape[d] for x, d in zip(operands, dims) if d is not None)
        moved = [batching.bdim_at_front(x, d, size) for x, d in zip(operands, dims)]
        out = primitive.bind(*moved, **params)
        return out, ([0] * len(out) if multiple_results else 0)

    batching.primitive_batchers[primitive] = batch
    mlir.register_lowering(primitive, mlir.lower_fun(functools.partial(_batched, function, cost_of),
                                                     multiple_results=multiple_results))
    mlir.register_lowering(primitive, mlir.lower_fun(functools.partial(_cpu, function, cost_of),
                                                     multiple_results=multiple_results), platform="cpu")
    return primitive


def _matrix_shape(x):
    return x.shape[-2], x.shape[-1]


# --- triangular solve: a (n, n) lower or upper, b (n, k); x = a^-1 b or a^-T b ----------------

def _triangular_solve(a, b, *, lower, transpose):
    return lax.linalg.triangular_solve(a, b, left_side=True, lower=lower, transpose_a=transpose)


def _triangular_solve_cost(a, b):
    n, k = _matrix_shape(b)
    return n * n * k


_triangular_solve_p = _define("triangular_solve", _triangular_solve, _triangular_solve_cost)


def _triangle(x, lower):
    return jnp.tril(x) if lower else jnp.triu(x)


def _triangular_solve_jvp_a(g, ans, a, b, *, lower, transpose):
    g = _triangle(g, lower)
    product = (jnp.swapaxes(g, -1, -2) if transpose else g) @ ans
    return -_triangular_solve_p.bind(a, product, lower=lower, transpose=transpose)


def _triangular_solve_jvp_b(g, ans, a, b, *, lower, transpose):
    return _triangular_solve_p.bind(a, g, lower=lower, transpose=transpose)


ad.defjvp2(_triangular_solve_p, _triangular_solve_jvp_a, _triangular_solve_jvp_b)


def _triangular_solve_transpose(cotangent, a, b, *, lower, transpose):
    if ad.is_undefined_primal(a):
        raise NotImplementedError("rsmooth._linalg.solve_triangular is linear in b only")
    if type(cotangent) is ad.Zero:
        return [None, ad.Zero(b.aval)]
    return [None, _triangular_solve_p.bind(a, cotangent, lower=lower, transpose=not transpose)]


ad.primitive_transposes[_triangular_solve_p] = _triangular_solve_transpose


def _matrix_operands(a, b):
    """``a`` (..., n, n) and ``b`` as (..., n, k), in one dtype and with one batch shape, and
    how to give a result ``b``'s own shape (``b`` may be (..., n))."""
    a, b = jnp.asarray(a), jnp.asarray(b)
    dtype = jnp.promote_types(a.dtype, b.dtype)
    a, b = a.astype(dtype), b.astype(dtype)
    if b.ndim == a.ndim - 1:
        matrix, restore = b[..., None], lambda x: x[..., 0]
    elif b.ndim == a.ndim:
        matrix, restore = b, lambda x: x
    else:
        raise ValueError(f"b must have shape {a.shape[:-1]} or {a.shape[:-1]} + (k,) beside a of shape "
                         f"{a.shape}, got {b.shape}")
    batch_shape = jnp.broadcast_shapes(a.shape[:-2], matrix.shape[:-2])
    return jnp.broadcast_to(a, batch_shape + a.shape[-2:]), jnp.broadcast_to(matrix, batch_shape + matrix.shape[-2:]), restore


def solve_triangular(a, b, *, lower: bool = True, trans: bool = False):
    """``a^-1 b`` (or ``a^-T b`` with ``trans``) for a triangular ``a`` (..., n, n) and ``b``
    (..., n) or (..., n, k): ``jax.scipy.linalg.solve_triangular(a, b, lower=lower,
    trans="T" if trans else 0)``."""
    a, matrix, restore = _matrix_operands(a, b)
    return restore(_triangular_solve_p.bind(a, matrix, lower=bool(lower), transpose=bool(trans)))


# --- Cholesky factorization ---------------------------------------------------------------

def _potrf(a):
    return lax.linalg.cholesky(a, symmetrize_input=False)


_cholesky_p = _define("cholesky", _potrf, lambda a: a.shape[-1] ** 3 // 3)


@jax.custom_jvp
def _cholesky(a):
    return _cholesky_p.bind(a)


@_cholesky.defjvp
def _cholesky_jvp(primals, tangents):
    (a,), (da,) = primals, tangents
    factor = _cholesky(a)  # differentiable again, for second derivatives
    da = 0.5 * (da + jnp.swapaxes(da, -1, -2))
    half = _triangular_solve_p.bind(factor, da, lower=True, transpose=False)  # L^-1 dA
    inner = _triangular_solve_p.bind(factor, jnp.swapaxes(half, -1, -2), lower=True, transpose=False)
    diagonal = jnp.eye(a.shape[-1], dtype=a.dtype).reshape((1,) * (a.ndim - 2) + (a.shape[-1],) * 2)  # (..., n, n): no rank promotion
    phi = jnp.tril(inner) - 0.5 * diagonal * inner
    return factor, factor @ phi


def cholesky(a):
    """The lower Cholesky factor ``L`` of a symmetric positive-definite ``a`` (..., n, n),
    ``a = L Lᵀ`` (from ``(a + aᵀ) / 2``, as ``jnp.linalg.cholesky``); NaN where ``a`` is not
    positive definite."""
    a = jnp.asarray(a)
    return _cholesky(0.5 * (a + jnp.swapaxes(a, -1, -2)))


def cho_factor(a):
    """``(L, True)``: :func:`cholesky`'s factor in ``jax.scipy.linalg.cho_factor``'s form."""
    return cholesky(a), True


def cho_solve(factor, b):
    """``A^-1 b`` from ``factor = (c, lower)``, a Cholesky factor of ``A`` as
    :func:`cho_factor` (or ``jax.scipy.linalg.cho_factor``) gives it."""
    c, lower = factor
    if lower:  # A = L Lᵀ
        return solve_triangular(c, solve_triangular(c, b, lower=True), lower=True, trans=True)
    return solve_triangular(c, solve_triangular(c, b, lower=False, trans=True), lower=False)  # A = Uᵀ U


# --- general solve ------------------------------------------------------------------------

def _solve(a, b):
    return jnp.linalg.solve(a, b)


def _solve_cost(a, b):
    n, k = _matrix_shape(b)
    return max(n * n * n, n * n * k)


_solve_p = _define("solve", _solve, _solve_cost)


def _solve_jvp_a(g, ans, a, b):
    return -_solve_p.bind(a, g @ ans)


def _solve_jvp_b(g, ans, a, b):
    return _solve_p.bind(a, g)


ad.defjvp2(_solve_p, _solve_jvp_a, _solve_jvp_b)


def _solve_transpose(cotangent, a, b):
    if ad.is_undefined_primal(a):
        raise NotImplementedError("rsmooth._linalg.solve is linear in b only")
    if type(cotangent) is ad.Zero:
        return [None, ad.Zero(b.aval)]
    return [None, _solve_p.bind(jnp.swapaxes(a, -1, -2), cotangent)]


ad.primitive_transposes[_solve_p] = _solve_transpose


def solve(a, b):
    """``a^-1 b`` for a square ``a`` (..., n, n) and ``b`` (..., n) or (..., n, k):
    ``jnp.linalg.solve`` (LU with partial pivoting)."""
    a, matrix, restore = _matrix_operands(a, b)
    return restore(_solve_p.bind(a, matrix))


# --- symmetric eigendecomposition ---------------------------------------------------------

def _syevd(a):
    eigenvalues, eigenvectors = jnp.linalg.eigh(a)
    return [eigenvalues, eigenvectors]


_eigh_p = _define("eigh", _syevd, lambda a: 5 * a.shape[-1] ** 3, multiple_results=True)


def eigh(a):
    """``(eigenvalues, eigenvectors)`` of a symmetric ``a`` (..., n, n), eigenvalues
    ascending: ``jnp.linalg.eigh``. Not differentiable."""
    eigenvalues, eigenvectors = _eigh_p.bind(jnp.asarray(a))
    return eigenvalues, eigenvectors


# --- singular value decomposition ---------------------------------------------------------

def _gesdd(a):
    u, s, vt = jnp.linalg.svd(a, full_matrices=False)
    return [u, s, vt]


def _svd_cost(a):
    rows, columns = _matrix_shape(a)
    return 10 * rows * columns * min(rows, columns)


_svd_p = _define("svd", _gesdd, _svd_cost, multiple_results=True)


def svd(a):
    """``(u, s, vt)`` with ``a = u diag(s) vt`` for ``a`` (..., m, n), singular values
    descending, ``u`` and ``vt`` reduced (``jnp.linalg.svd(a, full_matrices=False)``). Not
    differentiable."""
    u, s, vt = _svd_p.bind(jnp.asarray(a))
    return u, s, vt


def min_norm_solve(a, b, rcond: float):
    """The minimum-norm least-squares solution of ``a x = b`` for ``a`` (m, n) and ``b`` (m,),
    singular values below ``rcond`` times the largest taken as zero: ``np.linalg.lstsq(a, b,
    rcond)``. Not differentiable."""
    u, s, vt = svd(a)
    keep = s > rcond * s[0]
    return vt.T @ jnp.where(keep, (u.T @ b) / jnp.where(keep, s, 1.0), 0.0)
