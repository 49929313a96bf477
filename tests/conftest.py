"""Shared test configuration: double precision, strict rank promotion, seeded keys."""

import itertools

import jax
import pytest

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")


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
