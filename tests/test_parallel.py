"""rsmooth.parallel: a batch spread over devices gives the batch's results.

The test process has one CPU device; the multi-device case runs in a subprocess started with
``--xla_force_host_platform_device_count=2`` (two XLA CPU devices)."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rsmooth import parallel


def _f(x):
    return jnp.stack([jnp.sum(jnp.sin(x)), jnp.max(x)])


def test_one_device_is_plain_vmap():
    assert len(jax.devices()) == 1
    assert parallel.sample_mesh() is None
    xs = jax.random.normal(jax.random.key(0), (6, 3))
    np.testing.assert_array_equal(jax.jit(parallel.vmap_samples(_f))(xs), jax.vmap(_f)(xs))
    assert parallel.shard_leading(xs) is xs


def test_empty_device_list_is_an_error():
    with pytest.raises(ValueError, match="devices must not be empty"):
        parallel.sample_mesh([])


_TWO_DEVICES = textwrap.dedent(
    """
    import jax, jax.numpy as jnp, numpy as np
    jax.config.update("jax_enable_x64", True)
    from rsmooth import parallel
    assert len(jax.devices()) == 2, jax.devices()
    mesh = parallel.sample_mesh()
    assert mesh is not None and mesh.devices.size == 2
    f = lambda x: jnp.stack([jnp.sum(jnp.sin(x)), jnp.max(x)])
    xs = jax.random.normal(jax.random.key(0), (8, 5))
    out = jax.jit(parallel.vmap_samples(f))(xs)
    np.testing.assert_allclose(out, jax.vmap(f)(xs), rtol=1e-15)
    assert len(out.sharding.device_set) == 2, out.sharding  # spread over both devices
    shards = sorted(s.data.shape for s in out.addressable_shards)
    assert shards == [(4, 2), (4, 2)], shards
    # a reduction over the spread axis (a Monte-Carlo mean) equals the one-device value
    mean = jax.jit(lambda xs: jnp.mean(parallel.vmap_samples(f)(xs), axis=0))(xs)
    np.testing.assert_allclose(mean, jnp.mean(jax.vmap(f)(xs), axis=0), rtol=1e-14)
    # an odd batch is not split (an uneven split would pad), and still right
    odd = jax.jit(parallel.vmap_samples(f))(xs[:7])
    np.testing.assert_allclose(odd, jax.vmap(f)(xs[:7]), rtol=1e-15)
    # gradients flow through the sharding constraints
    g = jax.jit(jax.grad(lambda xs: jnp.sum(parallel.vmap_samples(f)(xs))))(xs)
    np.testing.assert_allclose(g, jax.grad(lambda xs: jnp.sum(jax.vmap(f)(xs)))(xs), rtol=1e-14)
    # shard_leading lays a state's problem axis over the devices (outside jit: a transfer),
    # leaves scalars and axes that do not split evenly alone, and changes no value
    state = {"x": xs, "t": jnp.zeros(()), "odd": xs[:7]}
    laid = parallel.shard_leading(state)
    assert len(laid["x"].sharding.device_set) == 2 and laid["x"].addressable_shards[0].data.shape == (4, 5)
    assert len(laid["odd"].sharding.device_set) == 1 and laid["t"].shape == ()
    np.testing.assert_array_equal(laid["x"], xs)
    print("ok")
    """
)


def _flags(flag: str) -> str:
    """XLA_FLAGS for a subprocess: the suite's own (tests/conftest.py) and ``flag``."""
    return f"{os.environ.get('XLA_FLAGS', '')} {flag}".strip()


def test_two_devices_share_the_batch_and_agree():
    env = dict(os.environ, XLA_FLAGS=_flags("--xla_force_host_platform_device_count=2"), JAX_PLATFORMS="cpu")
    result = subprocess.run(
        [sys.executable, "-c", _TWO_DEVICES], env=env, capture_output=True, text=True, timeout=300
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert result.stdout.strip().endswith("ok")


_POSE = textwrap.dedent(
    """
    import dataclasses, json, sys
    import jax
    jax.config.update("jax_enable_x64", True)
    from rsmooth.experiments import render_pose as rp
    config = dataclasses.replace(
        rp.Config.quick(), image_size=16, problems=2, steps=3, init_errors_deg=(30.0,), methods=("perturbed-gaussian",),
        keep_best=False, gif_every=10,
    )
    metrics = rp.run(config, sys.argv[1], jax.random.key(0), progress=False)
    print(json.dumps({"devices": len(jax.devices()), "errors": metrics["perturbed-gaussian"]["30"]["final_errors_deg"]}))
    """
)


@pytest.mark.slow
def test_pose_problems_spread_over_two_devices_give_the_same_results(tmp_path):
    """`rsmooth render pose` batches its problems with rsmooth.parallel.vmap_samples (as
    `rsmooth render reconstruct` does, which also lays its state out with shard_leading, tested
    above): on two devices each runs one problem, and the results are those of one device."""
    import json

    outputs = []
    for count in (1, 2):
        env = dict(os.environ, XLA_FLAGS=_flags(f"--xla_force_host_platform_device_count={count}"), JAX_PLATFORMS="cpu")
        result = subprocess.run(
            [sys.executable, "-c", _POSE, str(tmp_path / str(count))], env=env, capture_output=True, text=True,
            timeout=600,
        )
        assert result.returncode == 0, result.stderr[-3000:]
        outputs.append(json.loads(result.stdout.strip().splitlines()[-1]))
    one, two = outputs
    assert (one.pop("devices"), two.pop("devices")) == (1, 2)
    assert two["errors"] == pytest.approx(one["errors"], rel=1e-12)
