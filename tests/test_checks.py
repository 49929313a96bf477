"""rsmooth._checks: traced checks left out of a program, and checked on the host instead."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rsmooth import _checks


def _checked_sqrt(x):
    return jnp.sqrt(_checks.check_finite(x, "x must be finite"))


def _checked_cube(x):
    return _checks.check_finite(x, "x must be finite") ** 3


def test_traced_checks_are_left_out_inside_and_kept_outside():
    assert "callback" in str(jax.make_jaxpr(_checked_sqrt)(1.0))
    with _checks.without_traced_checks():
        assert "callback" not in str(jax.make_jaxpr(_checked_sqrt)(1.0))
    # traced inside first: JAX's trace caches must not hand that program to a caller outside
    with _checks.without_traced_checks():
        inside = jax.jit(_checked_cube).lower(1.0).as_text()
    assert "callback" not in inside and "callback" in jax.jit(_checked_cube).lower(1.0).as_text()
    with pytest.raises(Exception, match="x must be finite"):
        jax.jit(_checked_cube)(jnp.nan).block_until_ready()
    assert _checks.traced_checks()  # restored, also after an error inside
    with pytest.raises(RuntimeError), _checks.without_traced_checks():
        raise RuntimeError
    assert _checks.traced_checks()


def test_jit_checked_on_host_raises_on_a_nonfinite_output_and_names_it():
    fn = _checks.jit_checked_on_host(lambda x: {"root": jnp.sqrt(x), "count": jnp.int32(1)}, "the test program")
    np.testing.assert_allclose(fn(jnp.asarray(4.0))["root"], 2.0)
    with pytest.raises(FloatingPointError, match=r"the test program: \['root'\] is not finite"):
        fn(jnp.asarray(-1.0))
