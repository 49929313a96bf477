import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rsmooth import _unrolled


@pytest.mark.parametrize("dtype, atol", [(jnp.float64, 3e-16), (jnp.float32, 2e-7)])
def test_log_sigmoid_equals_jax_within_the_rounding_of_one_plus_exp(dtype, atol):
    x = jnp.concatenate([jnp.linspace(-60.0, 60.0, 2001), jnp.array([0.0, -1e4, 1e4, -1e-9, 1e-9])]).astype(dtype)
    ours, reference = _unrolled.log_sigmoid(x), jax.nn.log_sigmoid(x)
    assert ours.dtype == dtype
    np.testing.assert_allclose(ours, reference, rtol=4 * jnp.finfo(dtype).eps, atol=atol)
    grad = jax.vmap(jax.grad(_unrolled.log_sigmoid))(x)
    np.testing.assert_allclose(grad, jax.nn.sigmoid(-x), rtol=8 * jnp.finfo(dtype).eps, atol=atol)
    assert bool(jnp.all(jnp.isfinite(grad)))


def test_short_sum_equals_numpy():
    x = jax.random.normal(jax.random.key(0), (5, 7, 3))
    np.testing.assert_allclose(_unrolled.sum_last(x), np.sum(x, axis=-1), rtol=1e-14)
    np.testing.assert_allclose(_unrolled.sum_last(x, keepdims=True), np.sum(x, axis=-1, keepdims=True), rtol=1e-14)
    with pytest.raises(ValueError, match="empty last axis"):
        _unrolled.sum_last(jnp.zeros((2, 0)))
