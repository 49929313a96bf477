"""Spreading a batch (independent problems, Monte-Carlo samples) over devices with JAX's sharding.

:func:`vmap_samples` is `jax.vmap` with the batch axis laid out across every device of a
one-dimensional mesh (``jax.sharding``), so that under `jax.jit` XLA's SPMD partitioner gives
each device its share of the batch, and reductions over it become cross-device sums. Nothing
changes with one device, which is the default on CPU: the same code runs on a laptop, a GPU,
or several. `rsmooth render pose` and `rsmooth render reconstruct` spread their problems this way.

The estimators do not use it: sharding the samples of a first-order estimate through the
contact simulator over two forced CPU devices hangs XLA (no progress, no CPU use), although
the simulator's step and ``step_and_jacobians`` alone shard and run.

On CPU, XLA exposes one device unless told otherwise; to use several cores as devices (each
runs its share of the samples on its own thread), start the process with
``XLA_FLAGS=--xla_force_host_platform_device_count=N`` (before JAX is imported).

The axis is sharded only when its length is a multiple of the device count (otherwise the
samples stay where they are: an uneven split would pad every device to the longest share).
"""

from __future__ import annotations

from typing import Any, Callable, Sequence

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

__all__ = ["AXIS", "sample_mesh", "shard_leading", "vmap_samples"]

AXIS = "samples"


def sample_mesh(devices: Sequence[jax.Device] | None = None) -> Mesh | None:
    """A one-dimensional mesh named :data:`AXIS` over ``devices`` (default: all of
    ``jax.devices()``); ``None`` when there is a single device (nothing to spread)."""
    devices = list(jax.devices() if devices is None else devices)
    if not devices:
        raise ValueError("devices must not be empty")
    if len(devices) == 1:
        return None
    return Mesh(np.array(devices), (AXIS,))


def shard_leading(tree: Any, mesh: Mesh | None = None) -> Any:
    """``tree`` with the leading axis of every array leaf laid out across the mesh's devices
    (:func:`jax.lax.with_sharding_constraint` under `jit`; a transfer outside of it).

    Leaves without a leading axis, or whose leading axis is not a multiple of the device
    count, are left as they are; so is everything when ``mesh`` is ``None`` (one device)."""
    if mesh is None:
        mesh = sample_mesh()
    if mesh is None:
        return tree
    count = mesh.devices.size

    def constrain(leaf):
        shape = np.shape(leaf)
        if not shape or shape[0] % count != 0:
            return leaf
        spec = PartitionSpec(AXIS, *([None] * (len(shape) - 1)))
        return jax.lax.with_sharding_constraint(leaf, NamedSharding(mesh, spec))

    return jax.tree_util.tree_map(constrain, tree)


def vmap_samples(fn: Callable, mesh: Mesh | None = None) -> Callable:
    """``jax.vmap(fn)`` over the leading axis of every argument, that axis spread over the
    devices (inputs and outputs alike, see :func:`shard_leading`); exactly ``jax.vmap(fn)``
    on one device."""
    batched = jax.vmap(fn)

    def run(*args):
        target = sample_mesh() if mesh is None else mesh
        if target is None:
            return batched(*args)
        return shard_leading(batched(*shard_leading(args, target)), target)

    return run
