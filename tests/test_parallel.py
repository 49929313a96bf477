"""rsmooth.parallel: a batch spread over devices, or evaluated in chunks, gives the batch's results.

The test process has one CPU device; the multi-device cases run in subprocesses started with
``--xla_force_host_platform_device_count=N`` (N XLA CPU devices). Several processes:
tests/test_distributed.py."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
from jax import lax
import numpy as np
import pytest

import rsmooth
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


def _looping(x):
    """A per-sample loop whose trip count depends on the sample (as a contact solve's)."""
    trips = lax.while_loop(lambda c: c[1] < 3.0 + 2.0 * jnp.tanh(c[0]), lambda c: (c[0], c[1] + 1.0), (jnp.sum(x), 0.0))[1]
    return {"scaled": trips * jnp.sin(x), "max": jnp.max(x)}


@pytest.mark.parametrize("chunk", [1, 2, 3, 7, 100])
def test_map_samples_in_chunks_is_vmap(chunk):
    # 7 samples: chunks of 2 or 3 do not divide them (padded, the padding dropped)
    xs = jax.random.normal(jax.random.key(0), (7, 3))
    expected = jax.vmap(_looping)(xs)
    out = jax.jit(lambda xs: parallel.map_samples(_looping, xs, sample_chunk=chunk))(xs)
    for key in expected:
        np.testing.assert_allclose(out[key], expected[key], rtol=1e-15, atol=0)


def _pair(x):
    """A vector function of a pytree, with a jump and a kink."""
    v = jnp.concatenate([x["a"], x["b"][None]])
    return jnp.stack([jnp.sum(jnp.where(v > 0, 1.0, 0.0) * v**2), jnp.sum(jnp.abs(jnp.sin(v)))])


_POINT = {"a": np.array([0.3, -0.2, 0.1]), "b": np.array(0.5)}


def _assert_same(a, b, tol=1e-12):
    for u, v in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_allclose(u, v, rtol=tol, atol=tol)


@pytest.mark.parametrize(
    "estimator, options",
    [
        (rsmooth.zeroth_order, {"antithetic": True}),
        (rsmooth.first_order, {}),
        (rsmooth.alpha_order, {"baseline": "leave-one-out"}),
    ],
    ids=["zeroth-antithetic", "first", "alpha"],
)
def test_estimates_in_chunks_equal_the_whole_batch(estimator, options, getkey):
    key = getkey()

    def run(chunk):
        return jax.jit(
            lambda k, x: estimator(_pair, k, x, sigma=0.3, num_samples=12, sample_chunk=chunk, **options)
        )(key, _POINT)

    whole, chunked = run(None), run(5)  # alpha order: 6 samples a part, chunks of 3 (5 at most)
    _assert_same(chunked, whole)


def test_smooth_in_chunks_gives_the_same_value_and_derivatives(getkey):
    # (the first-order rule, chunked and on several devices: test_four_devices_...)
    key = getkey()
    whole = rsmooth.smooth(_pair, sigma=0.3, num_samples=9)
    chunked = rsmooth.smooth(_pair, sigma=0.3, num_samples=9, sample_chunk=4)
    _assert_same(jax.jit(chunked)(key, _POINT), jax.jit(whole)(key, _POINT))
    _assert_same(jax.jit(jax.jacrev(chunked, argnums=1))(key, _POINT), jax.jit(jax.jacrev(whole, argnums=1))(key, _POINT))


def test_all_devices_of_one_is_no_mesh():
    """devices="all" with one device evaluates as devices=None: no mesh, a plain vmap."""
    assert parallel.resolve_devices("all") is None and parallel.resolve_devices(jax.devices()) is None


@pytest.mark.parametrize(
    "options, message",
    [
        ({"devices": "gpu"}, "devices must be None, 'all'"),
        ({"devices": []}, "devices must not be empty"),
        ({"devices": [0, 1]}, "devices must hold jax devices"),
        ({"devices": 2}, "devices must be None, 'all'"),
        ({"sample_chunk": 0}, "sample_chunk must be None or an int >= 1"),
        ({"sample_chunk": True}, "sample_chunk must be None or an int >= 1"),
        ({"sample_chunk": 2.0}, "sample_chunk must be None or an int >= 1"),
    ],
)
def test_bad_devices_or_chunk_are_refused_by_name(options, message):
    x = jnp.zeros(2)
    for estimator in (rsmooth.zeroth_order, rsmooth.first_order, rsmooth.alpha_order):
        with pytest.raises(ValueError, match=message):
            estimator(jnp.sum, jax.random.key(0), x, sigma=0.1, num_samples=4, **options)
    with pytest.raises(ValueError, match=message):
        rsmooth.smooth(jnp.sum, sigma=0.1, num_samples=4, **options)
    with pytest.raises(ValueError, match=message):
        rsmooth.smooth_elementwise(jnp.sign, sigma=0.1, num_samples=4, **options)
    with pytest.raises(ValueError, match=message):
        parallel.map_samples(jnp.sum, jnp.zeros((4, 2)), **options)


_FOUR_DEVICES = textwrap.dedent(
    """
    import jax, jax.numpy as jnp, numpy as np
    jax.config.update("jax_enable_x64", True)
    jax.config.update("jax_numpy_rank_promotion", "raise")
    import rsmooth
    from rsmooth import parallel, sim
    assert len(jax.devices()) == 4, jax.devices()

    def same(a, b, tol=1e-12):
        for u, v in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
            np.testing.assert_allclose(u, v, rtol=tol, atol=tol)

    # each device evaluates its own samples, and the outputs stay where they were computed
    xs = jax.random.normal(jax.random.key(0), (8, 5))
    out = jax.jit(lambda xs: parallel.map_samples(jnp.sin, xs, devices="all"))(xs)
    assert sorted(s.data.shape for s in out.addressable_shards) == [(2, 5)] * 4, out.sharding
    np.testing.assert_array_equal(out, jnp.sin(xs))

    def f(p):
        v = jnp.concatenate([p["a"], p["b"][None]])
        return jnp.stack([jnp.sum(jnp.where(v > 0, 1.0, 0.0) * v**2), jnp.sum(jnp.abs(jnp.sin(v)))])

    point = {"a": jnp.array([0.3, -0.2, 0.1]), "b": jnp.array(0.5)}
    key = jax.random.key(7)
    # 10 samples on 4 devices or on 3 (padded to 12, the padding dropped); alpha order's two
    # parts of 6 samples on 4 devices in chunks of 2 (a vmap within a chunk)
    for estimator, options, spread in [
        (rsmooth.zeroth_order, {"num_samples": 10}, dict(devices="all")),
        (rsmooth.first_order, {"num_samples": 10, "antithetic": True}, dict(devices=jax.devices()[:3])),
        (rsmooth.alpha_order, {"num_samples": 12}, dict(devices="all", sample_chunk=2)),
    ]:
        run = lambda **spread: jax.jit(lambda k, x: estimator(f, k, x, sigma=0.3, **options, **spread))(key, point)
        same(run(**spread), run())
    # smooth(): the first-order rule's per-sample JVPs, transposed by reverse mode
    g = lambda **spread: jax.jit(jax.jacrev(rsmooth.smooth(f, sigma=0.3, num_samples=10, estimator="first", **spread), argnums=1))
    same(g(devices="all", sample_chunk=2)(key, point), g()(key, point))
    # smooth_elementwise(): both rules, the value and its gradient (10 samples: padded on 4)
    step = lambda d: jnp.where(d > 0, 1.0, 0.0) * (1.0 + d**2)
    xs5 = jnp.array([-1.0, 0.0, 0.3, 2.0, 0.5])
    for rule in ("zeroth", "first"):
        e = lambda **spread: rsmooth.smooth_elementwise(step, sigma=0.5, num_samples=10, estimator=rule, **spread)
        both = lambda h: jax.jit(lambda k, x: (h(k, x), jax.grad(lambda x: jnp.sum(h(k, x) ** 2))(x)))(key, xs5)
        same(both(e(devices="all")), both(e()))
        same(both(e(devices="all", sample_chunk=2)), both(e()))

    # first order through the contact solver (while loops, batched LAPACK calls): a cube pushed
    # on a floor; on 4 CPU devices each evaluates its samples one at a time (the default there:
    # rsmooth.parallel), which on 2 cores a whole share at once did not survive (a deadlock)
    system = sim.cube()
    x0 = system.initial_state()
    pushed = lambda u: system.step(x0, u)[:3]
    push = jnp.zeros(system.nu).at[0].set(3.0)
    run = lambda **spread: jax.jit(
        lambda k, u: rsmooth.first_order(pushed, k, u, sigma=1.0, num_samples=6, **spread)
    )(jax.random.key(0), push)
    spread, alone = run(devices="all"), run(sample_chunk=1)
    # the same samples, each solved alone: equal to within the contact solve's accuracy (1e-10 in
    # impulse residual; four corners make the cube's problem rank-deficient, so the two
    # compiled layouts' rounding moves the sticking solution within it)
    same(spread, alone, tol=1e-8)
    assert float(jnp.max(jnp.abs(alone.grad))) > 1e-5  # a non-trivial estimate
    # vmapped on one device, a batch's solver loops run until its slowest sample converges:
    # the estimate moves within the solver's tolerance, not more
    vmapped = run()
    assert float(jnp.max(jnp.abs(vmapped.grad - alone.grad))) < 1e-3 * float(jnp.max(jnp.abs(alone.grad)))
    print("ok")
    """
)


def test_four_devices_give_the_one_device_estimates():
    """Estimators, smooth() and smooth_elementwise() with their samples on 4 devices (a share
    each, or in chunks) equal their one-device values to rounding, a first-order estimate
    through the contact solver included (against one device evaluating the samples one at a
    time, as each of the 4 CPU devices does)."""
    env = dict(os.environ, XLA_FLAGS=_flags("--xla_force_host_platform_device_count=4"), JAX_PLATFORMS="cpu")
    result = subprocess.run(
        [sys.executable, "-c", _FOUR_DEVICES], env=env, capture_output=True, text=True, timeout=300
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert result.stdout.strip().endswith("ok")
