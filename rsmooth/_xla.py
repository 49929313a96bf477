"""XLA settings that the `rsmooth` command (and `python -m benchmarks`) applies for itself.

jaxlib 0.10's CPU backend hands reductions over short axes to YNNPACK kernels that are slow
for rsmooth's per-pixel and per-contact sums (see :mod:`rsmooth._unrolled`). The forward
code unrolls its own sums, but the sums that autodiff inserts (transposes of broadcasts) still
go there; ``--xla_cpu_experimental_ynn_fusion_type=`` (an empty list of fusion types) turns
the kernels off, which speeds up the renderer's batched forward and backward passes.

Its MLIR fusion emitters compile the large programs (a DDP or R-DDP step through the contact
solver, a renderer's backward pass) about twice as slowly as the older loop emitters, for
programs that run as fast either way (``python -m benchmarks startup``):
``--xla_cpu_use_fusion_emitters=false`` (:data:`EMITTERS_FLAG`) halves what a first run of a
command waits for.

Its concurrency-optimized scheduler (on by default) runs more of a program's operations at
once on the intra-op thread pool (one thread per core). jaxlib 0.10's batched LAPACK kernels
split a large batch into tasks on that pool and wait for them: when every thread is such a
waiting kernel, nothing runs the tasks and the program stops, its threads idle.
``jit(vmap(step_and_jacobians))`` of 64 Solo-12 states, called repeatedly on two cores,
stopped so in every run tried and in none with
``--xla_cpu_enable_concurrency_optimized_scheduler=false`` (:data:`SCHEDULER_FLAG`). The plain
scheduler lowers the risk without removing it (a batched rollout of 64 towers of 16 boxes
stopped with it); what removes it is :mod:`rsmooth._linalg`, through which rsmooth's solvers do
their linear algebra: it hands LAPACK only batches small enough to run inline.

XLA aborts the process on a flag it does not know, so a flag is added only for the jaxlib
versions known to have it (:data:`KNOWN_JAXLIB`), only when the user has not set it, and never
by merely importing rsmooth (a library must not change its host's XLA configuration): the
console entry point calls :func:`apply_cpu_defaults` before JAX creates its backend: the loop
emitters and the plain scheduler always, the YNNPACK opt-out for the ``rsmooth render`` commands only (the simulator's batched step
Jacobian is slower with it). ``RSMOOTH_XLA_DEFAULTS=0`` leaves ``XLA_FLAGS`` alone. A script
or notebook that imports rsmooth sets the same flags itself, in ``XLA_FLAGS`` before JAX
starts.

The persistent compilation cache (:func:`enable_compilation_cache`) saves a second run XLA's
compilation, not JAX's tracing and lowering, which every process pays again and which are
most of a warm start. Ahead-of-time export (``jax.export``: a program serialized after
lowering) would skip those too, and rsmooth's solver programs export (they hold no host
callback under :func:`rsmooth._checks.without_traced_checks`). It is not used: an exported
program bakes in the arrays it closes over (a system's model and contacts), so it would need a
store keyed by every value and by rsmooth's own code, invalidated by hand, for each solver
program and horizon; and serialization needs the ``flatbuffers`` package.

:func:`on_accelerator` is what the solvers' ``"auto"`` batch sizes ask (``NCPSolver.chunk_size``,
``DDP.line_search_batch``, ``RDDP.sample_node_batch_size``): on a CPU a batch costs its
members' work, on a GPU it costs about one member's (kernel launches), so the best batch sizes
differ by an order of magnitude.
"""

from __future__ import annotations

import gc
import importlib.metadata
import os
import pathlib

import jax
import jax.numpy as jnp
import numpy as np

YNN_FLAG = "--xla_cpu_experimental_ynn_fusion_type"
EMITTERS_FLAG = "--xla_cpu_use_fusion_emitters"
SCHEDULER_FLAG = "--xla_cpu_enable_concurrency_optimized_scheduler"
# jaxlib versions on which the flags exist and help (see the module docstring)
KNOWN_JAXLIB = ("0.10.",)


def apply_cpu_defaults(environ: dict | None = None, *, render: bool = False) -> bool:
    """Add rsmooth's CPU flags to ``XLA_FLAGS`` where known to be safe; True if any was added.

    The loop emitters (:data:`EMITTERS_FLAG`) and the plain scheduler (:data:`SCHEDULER_FLAG`)
    always; the YNNPACK opt-out (:data:`YNN_FLAG`) with ``render``. A flag the user has set, in any value, is kept. Call it before the first
    JAX computation (XLA reads its flags when the backend starts).
    """
    environ = os.environ if environ is None else environ
    if environ.get("RSMOOTH_XLA_DEFAULTS", "1") == "0":
        return False
    try:
        version = importlib.metadata.version("jaxlib")
    except importlib.metadata.PackageNotFoundError:
        return False
    if not version.startswith(KNOWN_JAXLIB):
        return False
    flags = environ.get("XLA_FLAGS", "")
    wanted = [(EMITTERS_FLAG, "false"), (SCHEDULER_FLAG, "false")] + ([(YNN_FLAG, "")] if render else [])
    added = [f"{flag}={value}" for flag, value in wanted if flag not in flags]
    if added:
        environ["XLA_FLAGS"] = " ".join([flags, *added]).strip()
    return bool(added)


CACHE_VARIABLE = "RSMOOTH_COMPILATION_CACHE"
# Every program is written to the cache: reading back even the small programs of a run (key
# splits, reshapes, a problem's set-up) is faster than compiling them again, and a warm run then
# compiles nothing (python -m benchmarks startup).
CACHE_MIN_COMPILE_SECONDS = 0.0


def default_cache_dir(environ: dict | None = None) -> pathlib.Path:
    """``$XDG_CACHE_HOME/rsmooth/jax``, or ``~/.cache/rsmooth/jax``."""
    environ = os.environ if environ is None else environ
    base = environ.get("XDG_CACHE_HOME") or str(pathlib.Path.home() / ".cache")
    return pathlib.Path(base) / "rsmooth" / "jax"


def enable_compilation_cache(environ: dict | None = None) -> pathlib.Path | None:
    """Turns on JAX's persistent compilation cache for the ``rsmooth`` command; its folder.

    Most of a command's time on a first run is XLA compiling; a second run of the same
    command (or of another that builds the same programs) reads them back. The folder is
    ``RSMOOTH_COMPILATION_CACHE`` when set (``0`` or ``off`` turns the cache off), else
    :func:`default_cache_dir`. A cache the user configured for JAX
    (``JAX_COMPILATION_CACHE_DIR``) is left as it is. Never called by importing rsmooth: a
    library does not choose its host's cache. The folder is not size-capped (JAX's cap needs
    the ``filelock`` package): a command's programs take a few MB, and deleting the folder at
    any time only costs the next run its compilation.
    """
    environ = os.environ if environ is None else environ
    setting = environ.get(CACHE_VARIABLE)
    if setting is not None and setting.strip().lower() in ("", "0", "off", "false", "no"):
        return None
    if environ.get("JAX_COMPILATION_CACHE_DIR"):
        return pathlib.Path(environ["JAX_COMPILATION_CACHE_DIR"])
    folder = pathlib.Path(setting).expanduser() if setting else default_cache_dir(environ)
    jax.config.update("jax_compilation_cache_dir", str(folder))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", CACHE_MIN_COMPILE_SECONDS)
    return folder


def device_array(values, dtype=np.float64) -> jax.Array:
    """``values`` as a JAX array on the default device, without compiling anything.

    ``jnp.asarray`` of a NumPy array compiles (jaxlib 0.10) a small program per new shape and
    dtype, tens of milliseconds each; building a system or a problem converts dozens of arrays,
    which a fresh process (a command's first run, a test worker) would pay in compilations.
    ``jax.device_put`` copies without one. The dtype is canonicalized as ``jnp.asarray`` does
    (float64 becomes float32 unless ``jax_enable_x64`` is set).
    """
    return jax.device_put(np.asarray(values, dtype=dtype))


def memory_maps() -> tuple[int, int] | None:
    """``(maps, limit)``: the memory maps this process holds and the most the kernel allows it
    (``vm.max_map_count``); ``None`` where ``/proc`` does not say (not Linux)."""
    try:
        with open("/proc/self/maps") as maps, open("/proc/sys/vm/max_map_count") as limit:
            return sum(1 for _ in maps), int(limit.read())
    except (OSError, ValueError):
        return None


def release_compiled_programs(fraction: float = 0.5) -> bool:
    """Drops JAX's in-memory caches of compiled programs (``jax.clear_caches``) when this
    process holds more than ``fraction`` of the memory maps Linux allows it; True if it did.

    XLA:CPU keeps each compiled program's machine code in memory maps of its own (about six for
    a small program, more for a large one) for as long as JAX's caches hold the program. Linux
    bounds a process's maps (``vm.max_map_count``, 65,530 by default); past the bound LLVM
    cannot map the next program's code and the process dies in a segmentation fault while
    compiling (a worker of the full test suite comes near it). A process that
    compiles thousands of programs (the test suite's workers, ``rsmooth report``) calls this
    between its units of work: a program dropped is compiled again when used again (read back
    from the persistent compilation cache where that is on).
    """
    counts = memory_maps()
    if counts is None or counts[0] <= fraction * counts[1]:
        return False
    jax.clear_caches()
    gc.collect()
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
