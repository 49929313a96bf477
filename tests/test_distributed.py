"""Estimates with their samples spread over two processes (`jax.distributed`), as on two hosts.

Two Python processes on this machine, each with two XLA CPU devices, join a local coordinator
on a free port; every process computes the same estimate with ``devices="all"`` (four devices,
two of them in the other process: the cross-process sums go through gloo, jaxlib's CPU
collectives) and with ``devices=None`` (its own default device alone), and both results come
back to the test, which checks that they agree across processes and with each other."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import textwrap

import numpy as np

_WORKER = textwrap.dedent(
    """
    import json, sys
    import jax, jax.numpy as jnp, numpy as np
    jax.config.update("jax_enable_x64", True)
    jax.config.update("jax_numpy_rank_promotion", "raise")
    jax.config.update("jax_num_cpu_devices", 2)
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    process, port = int(sys.argv[1]), sys.argv[2]
    jax.distributed.initialize(f"127.0.0.1:{port}", num_processes=2, process_id=process, initialization_timeout=60)
    import rsmooth
    from rsmooth import parallel
    assert jax.process_count() == 2 and len(jax.devices()) == 4 and len(jax.local_devices()) == 2, jax.devices()

    def f(x):
        # a loop whose trip count depends on the sample, as a contact solve's
        trips = jax.lax.while_loop(
            lambda c: c[1] < 3.0 + 2.0 * jnp.tanh(c[0]), lambda c: (c[0], c[1] + 1.0), (jnp.sum(x), 0.0)
        )[1]
        return jnp.stack([trips * jnp.sum(jnp.sin(x)), jnp.sum(jnp.abs(x))])

    # each process evaluates the samples on its own devices, and only those
    xs = jnp.arange(8.0)[:, None] * jnp.array([0.1, -0.2])[None]
    mapped = jax.jit(lambda xs: parallel.map_samples(f, xs, devices="all"))(xs)
    assert not mapped.is_fully_addressable
    rows = sorted((s.index[0].start, s.data.shape) for s in mapped.addressable_shards)
    assert rows == [(4 * process, (2, 2)), (4 * process + 2, (2, 2))], rows
    for shard in mapped.addressable_shards:
        np.testing.assert_allclose(shard.data, jax.vmap(f)(xs[shard.index[0]]), rtol=1e-15)

    x, key = jnp.array([0.3, -0.2, 0.1]), jax.random.key(3)
    out = {}
    # 7 samples: padded to 8 over the 4 devices; first order also in chunks of one
    for name, spread in [("zeroth_order", {}), ("first_order", {"sample_chunk": 1})]:
        estimate = lambda **kw: jax.jit(
            lambda k, x: getattr(rsmooth, name)(f, k, x, sigma=0.5, num_samples=7, **kw)
        )(key, x)
        spread_out, alone = estimate(devices="all", **spread), estimate()
        assert len(spread_out.grad.sharding.device_set) == 4, spread_out.grad.sharding
        out[name] = {
            key_: {"value": np.asarray(e.value).tolist(), "grad": np.asarray(e.grad).tolist()}
            for key_, e in (("spread", spread_out), ("alone", alone))
        }
    print(json.dumps(out))
    """
)


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def test_estimates_spread_over_two_processes_equal_the_single_process_ones():
    port = _free_port()
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    workers = [
        subprocess.Popen(
            [sys.executable, "-c", _WORKER, str(process), str(port)],
            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        )
        for process in range(2)
    ]
    outputs = []
    try:
        for worker in workers:
            stdout, stderr = worker.communicate(timeout=240)
            assert worker.returncode == 0, stderr[-3000:]
            outputs.append(json.loads(stdout.strip().splitlines()[-1]))
    finally:
        for worker in workers:
            if worker.poll() is None:
                worker.kill()
                worker.communicate()
    first, second = outputs
    for name in ("zeroth_order", "first_order"):
        for field in ("value", "grad"):
            spread = np.asarray(first[name]["spread"][field])
            # both processes hold the same (replicated) estimate ...
            np.testing.assert_array_equal(np.asarray(second[name]["spread"][field]), spread)
            # ... the one a single process computes alone, to rounding
            np.testing.assert_allclose(spread, np.asarray(first[name]["alone"][field]), rtol=1e-12, atol=1e-12)
            np.testing.assert_array_equal(np.asarray(second[name]["alone"][field]), np.asarray(first[name]["alone"][field]))
        assert np.max(np.abs(np.asarray(first[name]["spread"]["grad"]))) > 0.1  # a non-trivial estimate
