"""Shared test configuration: double precision, strict rank promotion, seeded keys."""

import itertools
import os
import shutil
import tempfile

# Compile fast rather than run fast: most of the suite's time is XLA compiling small programs,
# and LLVM's optimizations are a third of that. At level 0 (instead of XLA's default 2) the suite
# ran in 14.8 min instead of 16.0 on 2 cores, back to back (the run-bound control tests 10-25 %
# slower, the compile-bound ones up to 1.6x faster); the programs' HLO and so their results are
# the same, up to rounding. Set here, before JAX starts its backend, and inherited by the
# tests' subprocesses; a level already in XLA_FLAGS is kept.
if "--xla_backend_optimization_level" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} --xla_backend_optimization_level=0".strip()

# On a GPU, JAX takes 75 % of its memory when its backend starts: with `pytest -n 2` the second
# worker then fails at start-up (CUDA_ERROR_OUT_OF_MEMORY; seen on an H200 with 8 workers).
# Allocate on demand instead; a setting already in the environment is kept. (No effect on CPU.)
os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")

import jax  # noqa: E402
import pytest  # noqa: E402

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")


# One persistent compilation cache for the run, shared by the pytest-xdist workers and the CLI
# subprocesses of the tests: a program that two tests (or two workers) build is compiled once.
# The controller makes the folder before the workers start (they inherit the environment) and
# removes it at the end, so every run starts cold, as CI does.
_CACHE_VARIABLE = "RSMOOTH_COMPILATION_CACHE"


def pytest_configure(config):
    if not hasattr(config, "workerinput") and _CACHE_VARIABLE not in os.environ:
        os.environ[_CACHE_VARIABLE] = tempfile.mkdtemp(prefix="rsmooth-test-jax-cache-")
        config._rsmooth_cache = os.environ[_CACHE_VARIABLE]
    from rsmooth import _xla

    _xla.enable_compilation_cache()


def pytest_unconfigure(config):
    folder = getattr(config, "_rsmooth_cache", None)
    if folder is not None:
        shutil.rmtree(folder, ignore_errors=True)


def pytest_collection_modifyitems(config, items):
    """Tests marked ``slow`` (30 s to 2 min each, mostly compilation) run first: pytest-xdist
    hands tests out in this order, so a slow one started last cannot keep one worker busy
    while the other has nothing left to do. The order of the others is unchanged."""
    items.sort(key=lambda item: item.get_closest_marker("slow") is None)


@pytest.fixture
def getkey():
    """Returns a function that gives a fresh, deterministic PRNG key at each call."""
    counter = itertools.count()
    base = jax.random.key(0)

    def _getkey():
        return jax.random.fold_in(base, next(counter))

    return _getkey


@pytest.fixture(autouse=True)
def _double_precision_after_each_test():
    """A test that runs a float32 CLI command in-process (`rsmooth render ...` turns x64
    off) must not change the precision of the tests after it in the same worker."""
    yield
    jax.config.update("jax_enable_x64", True)
