"""XLA settings that the `rsmooth` command (and `python -m benchmarks`) applies for itself.

jaxlib 0.10's CPU backend hands reductions over short axes to YNNPACK kernels that are slow
for rsmooth's per-pixel and per-contact sums (see :mod:`rsmooth._unrolled`). The forward
code unrolls its own sums, but the sums that autodiff inserts (transposes of broadcasts) still
go there; ``--xla_cpu_experimental_ynn_fusion_type=`` (an empty list of fusion types) turns
the kernels off, which speeds up the renderer's batched forward and backward passes.

XLA aborts the process on a flag it does not know, so the flag is added only for the jaxlib
versions known to have it (:data:`KNOWN_JAXLIB`), only when the user has not set it, and never
by merely importing rsmooth (a library must not change its host's XLA configuration): the
console entry point calls :func:`apply_cpu_defaults` for the ``rsmooth render`` commands only,
before JAX creates its backend. Not for the simulator, whose batched step Jacobian is slower
with the flag. ``RSMOOTH_XLA_DEFAULTS=0`` leaves ``XLA_FLAGS`` alone.

:func:`on_accelerator` is what the solvers' ``"auto"`` batch sizes ask (``NCPSolver.chunk_size``,
``DDP.line_search_batch``, ``RDDP.sample_node_batch_size``): on a CPU a batch costs its
members' work, on a GPU it costs about one member's (kernel launches), so the best batch sizes
differ by an order of magnitude.
"""

from __future__ import annotations

import importlib.metadata
import os

import jax
import jax.numpy as jnp

YNN_FLAG = "--xla_cpu_experimental_ynn_fusion_type"
# jaxlib versions on which the flag exists and helps (see the module docstring)
KNOWN_JAXLIB = ("0.10.",)


def apply_cpu_defaults(environ: dict | None = None) -> bool:
    """Add the YNNPACK opt-out to ``XLA_FLAGS`` when it is known to be safe; True if added.

    Call it before the first JAX computation (XLA reads its flags when the backend starts).
    """
    environ = os.environ if environ is None else environ
    if environ.get("RSMOOTH_XLA_DEFAULTS", "1") == "0":
        return False
    try:
        version = importlib.metadata.version("jaxlib")
    except importlib.metadata.PackageNotFoundError:
        return False
    flags = environ.get("XLA_FLAGS", "")
    if not version.startswith(KNOWN_JAXLIB) or YNN_FLAG in flags:
        return False
    environ["XLA_FLAGS"] = f"{flags} {YNN_FLAG}=".strip()
    return True


def on_accelerator() -> bool:
    """True when JAX's default backend is not the CPU (a GPU or TPU).

    Asked when a solver is traced, not when it is built: building one must not start JAX's
    backend (it reads ``XLA_FLAGS`` once, when it starts; see :func:`apply_cpu_defaults`).
    """
    return jax.default_backend() != "cpu"


def resolve_auto(value, *, cpu, accelerator):
    """``value`` itself, or where it is ``"auto"``: ``accelerator`` on a GPU or TPU, ``cpu`` on
    the CPU (:func:`on_accelerator`)."""
    if value != "auto":
        return value
    return accelerator if on_accelerator() else cpu


def matmul(a, b):
    """``a @ b`` in full float32 precision on every backend.

    A float32 product's default precision on NVIDIA GPUs is TF32 (a 10-bit mantissa, relative
    error up to ~5e-4): rescaling a robot mesh can collapse its smallest faces to zero area, a
    rotated or projected vertex moves by up to ~5e-4 of its coordinates (a tenth of a pixel at
    128 x 128), and the cosine in a rotation-error metric can be off by ~1e-3, which reads as
    degrees near zero error.
    The geometry's products are 3 x 3 and the estimators' are small: full precision costs
    nothing there. On CPU, and in float64, this is ``a @ b``.
    """
    return jnp.matmul(a, b, precision=jax.lax.Precision.HIGHEST)
