"""Spreading a batch (Monte-Carlo samples, independent problems) over devices and hosts.

Two ways, for two kinds of batch:

* :func:`map_samples` evaluates a function at every sample of a batch with the sample axis
  split over the devices of a one-dimensional mesh by :func:`jax.shard_map`: each device runs
  its own share, its own loops included (the contact solver's ``lax.while_loop`` runs as many
  iterations as that device's samples need), and returns its share of the outputs, laid out
  across the devices. Reductions over the samples that follow (the estimators' means and
  variances) are partitioned by XLA into per-device partial sums and one cross-device sum;
  nothing else crosses devices. Each device may also evaluate its share a bounded number of
  samples at a time (``sample_chunk``, with :func:`jax.lax.map`), for sample counts whose
  intermediate values do not fit in memory at once. The estimators (:func:`rsmooth.zeroth_order`,
  :func:`rsmooth.first_order`, :func:`rsmooth.alpha_order`) and :func:`rsmooth.smooth` take
  ``devices`` and ``sample_chunk`` and pass them here; so do R-DDP's sampled linearization
  (:class:`rsmooth.control.RDDP`, :func:`rsmooth.control.smoothed_dynamics_jacobians`: one map
  over all the (node, sample) pairs) and the policy gradients
  (:class:`rsmooth.control.PolicyGradient`, :func:`rsmooth.control.policy_gradient`).
* :func:`vmap_samples` is `jax.vmap` with the batch axis laid out across the devices by a
  sharding constraint, for XLA's SPMD partitioner to split the vmapped program: for batches
  of independent problems without data-dependent loops (`rsmooth render pose` and `rsmooth
  render reconstruct` spread their problems this way).

The samples are drawn whole from the key before they are split, so an estimate is the same,
up to the rounding of the cross-device sums, on any number of devices and with any chunk
size, for a function whose value at a sample does not depend on the other samples evaluated
with it. A vmapped iterative solver is not such a function: its loops run until the slowest
sample of the batch converges, so its results move with the batch, within its tolerance
(tests/test_parallel.py measures it for the contact solver).

On several CPU devices, each device evaluates its share one sample at a time unless a
``sample_chunk`` is given: XLA runs every CPU device's program on one intra-op thread pool of
one thread per core, and jaxlib 0.10's LAPACK kernels (``eigh``, ``cholesky``, ``lu``,
triangular solves: the contact solver's linear algebra) split a batch of large enough matrices
into tasks on that pool and wait for them; when every pool thread is a device waiting that
way, no thread is left to run the tasks and the program stops, with no CPU use (a first-order
estimate through :func:`rsmooth.sim.cube` on two devices of a two-core machine, split by
:func:`map_samples` or by :func:`vmap_samples`, with JAX's own ``jnp.linalg`` in the contact
solver). A batch of one matrix runs inline, and :mod:`rsmooth._linalg` hands LAPACK nothing
larger than what runs inline. A chunk larger than one is safe on several CPU devices for
functions whose linear algebra is rsmooth's (the simulator, the control solvers) or that have
none; on accelerators the whole share is vmapped by default.

Devices (the ``devices`` argument of :func:`map_samples` and of the estimators): ``None``, the
default, splits nothing (the batch is vmapped on the default device); ``"all"`` takes
``jax.devices()``, every device of every process; or a sequence of devices, or a
one-dimensional :class:`jax.sharding.Mesh`. A sample count that is not a multiple of the
device count is padded with copies of the first sample, whose outputs are dropped.

CPU cores as devices: XLA exposes one CPU device per process unless the process starts with
``XLA_FLAGS=--xla_force_host_platform_device_count=N`` (or sets
``jax.config.update("jax_num_cpu_devices", N)``) before JAX creates its backend.

Several hosts: start one process per host running the same program, call
:func:`jax.distributed.initialize` before any other JAX call, and call the estimator with the
same key and point in every process; ``devices="all"`` then spans every process's devices,
each process evaluates the samples of its own devices, and every process receives the whole
estimate. Across CPU processes the cross-device sums go through jaxlib's CPU collectives
(``jax_cpu_collectives_implementation``; gloo, its default, works).
"""

from __future__ import annotations

import functools
from typing import Any, Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.sharding import Mesh, NamedSharding, PartitionSpec

__all__ = [
    "AXIS", "check_sample_chunk", "map_samples", "resolve_devices", "sample_mesh", "shard_leading", "static_devices",
    "vmap_samples",
]

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


def resolve_devices(devices: Any, name: str = "devices") -> Mesh | None:
    """The mesh that ``devices`` names, ``None`` where there is nothing to split.

    Args:
        devices: ``None`` (no splitting), ``"all"`` (``jax.devices()``), a sequence of
            distinct ``jax.Device``, or a one-dimensional :class:`jax.sharding.Mesh`.
        name: the argument's name in error messages.

    Returns:
        A one-dimensional mesh over the devices, or ``None`` for ``None`` or a single device.

    Raises:
        ValueError: for anything else, an empty sequence, a repeated device or a mesh of more
            than one axis.
    """
    if devices is None:
        return None
    if isinstance(devices, Mesh):
        if devices.devices.ndim != 1:
            raise ValueError(f"{name} must be a one-dimensional mesh, got axes {devices.axis_names}")
        return devices if devices.devices.size > 1 else None
    if isinstance(devices, str):
        if devices != "all":
            raise ValueError(f"{name} must be None, 'all', a sequence of jax devices or a Mesh, got {devices!r}")
        return sample_mesh()
    try:
        listed = list(devices)
    except TypeError:
        raise ValueError(
            f"{name} must be None, 'all', a sequence of jax devices or a Mesh, got {type(devices).__name__}"
        ) from None
    if not listed:
        raise ValueError(f"{name} must not be empty")
    if not all(isinstance(device, jax.Device) for device in listed):
        raise ValueError(f"{name} must hold jax devices (e.g. jax.devices()), got {listed!r}")
    if len(set(listed)) != len(listed):
        raise ValueError(f"{name} must not repeat a device, got {listed!r}")
    return sample_mesh(listed)


def static_devices(devices: Any) -> Any:
    """``devices`` as a hashable value, for a static field of a solver (a jitted program is
    keyed by its static fields): a sequence of devices becomes a tuple; ``None``, a string, a
    mesh, and anything not iterable (left for :func:`resolve_devices` to refuse) are returned
    as they are."""
    if devices is None or isinstance(devices, (str, Mesh)):
        return devices
    try:
        return tuple(devices)
    except TypeError:
        return devices


def check_sample_chunk(sample_chunk: Any, name: str = "sample_chunk") -> int | None:
    """``sample_chunk`` (``None`` or an int >= 1), checked on the host; returns it."""
    if sample_chunk is None:
        return None
    if isinstance(sample_chunk, bool) or not isinstance(sample_chunk, (int, np.integer)) or sample_chunk < 1:
        raise ValueError(f"{name} must be None or an int >= 1, got {sample_chunk!r}")
    return int(sample_chunk)


def _layout(count: int, num_devices: int, chunk: int | None) -> tuple[int, int]:
    """(chunk size, chunks per device) for ``count`` samples on ``num_devices``: each device's
    share cut into as few chunks of at most ``chunk`` as possible, of equal size (the padding
    is then less than one chunk per device)."""
    share = -(-count // num_devices)
    chunks = 1 if chunk is None else -(-share // chunk)
    return -(-share // chunks), chunks


def map_samples(fn: Callable, *args, devices: Any = None, sample_chunk: int | None = None):
    """``jax.vmap(fn)(*args)``, the leading (sample) axis of the arguments split over
    ``devices`` and each device's share evaluated at most ``sample_chunk`` samples at a time.

    With several devices the evaluation is a :func:`jax.shard_map`: every device runs ``fn`` on
    its own samples, loops included, with no communication, and the outputs stay laid out
    across the devices (their leading axis split as the inputs'), so that a mean over them is
    a sum of per-device partial sums. With a chunk, each device loops over its share with
    :func:`jax.lax.map`, vmapping ``fn`` over one chunk at a time: memory for one chunk's
    intermediate values instead of the share's. When the sample count does not split into
    whole chunks on every device, the arguments are padded with copies of the first sample
    (a point as safe to evaluate as any) and the padded outputs dropped: at most one chunk per
    device of extra work, and one compiled copy of ``fn``.

    ``fn`` may close over traced values (parameters of an outer `jax.jit` or `jax.grad`); they
    are passed whole to every device. The map is differentiable and batches under `jax.vmap`
    (as `jax.shard_map` and `jax.lax.map` are).

    Args:
        fn: a function of one sample of each argument, returning a pytree of arrays.
        *args: pytrees of arrays with the same leading length ``M`` (the samples).
        devices: ``None`` (vmapped on the default device), ``"all"``, a sequence of devices or
            a mesh (see :func:`resolve_devices`).
        sample_chunk: the most samples evaluated at once on a device; ``None``: the device's
            whole share at once, except on several CPU devices: one at a time (see the
            module docstring).

    Returns:
        The outputs of ``fn`` stacked along a leading axis of length ``M``.

    Raises:
        ValueError: for bad ``devices`` or ``sample_chunk``, or arguments with no common
            leading axis.

    Example:
        >>> import jax.numpy as jnp
        >>> from rsmooth import parallel
        >>> parallel.map_samples(jnp.sin, jnp.zeros(5), sample_chunk=2).shape
        (5,)
    """
    mesh = resolve_devices(devices)
    chunk = check_sample_chunk(sample_chunk)
    leaves = jax.tree.leaves(args)
    lengths = {np.shape(leaf)[0] if np.ndim(leaf) else None for leaf in leaves}
    if not leaves or len(lengths) != 1 or None in lengths:
        raise ValueError(f"map_samples needs arguments with one common leading axis, got shapes {[np.shape(a) for a in leaves]}")
    (count,) = lengths
    num_devices = 1 if mesh is None else mesh.devices.size
    if chunk is None and mesh is not None and all(device.platform == "cpu" for device in mesh.devices.flat):
        chunk = 1  # jaxlib's batched LAPACK kernels can deadlock here (see the module docstring)
    if mesh is None and (chunk is None or chunk >= count):
        return jax.vmap(fn)(*args)
    size, chunks = _layout(count, num_devices, chunk)
    padded = num_devices * chunks * size

    def pad(leaf):
        leaf = jnp.asarray(leaf)
        if padded == count:
            return leaf
        return jnp.concatenate([leaf, jnp.broadcast_to(leaf[:1], (padded - count,) + leaf.shape[1:])])

    def local(*shares):
        if chunks == 1:
            return jax.vmap(fn)(*shares)
        return lax.map(lambda one: fn(*one), shares, batch_size=size)

    inputs = jax.tree.map(pad, args)
    if mesh is None:
        outputs = local(*inputs)
    else:
        # check_vma=False: fn may be any JAX function (custom batching rules, while loops) and
        # nothing inside it communicates; every output is per-sample, split as the inputs.
        outputs = jax.shard_map(
            local, mesh=mesh, in_specs=(PartitionSpec(AXIS),) * len(inputs), out_specs=PartitionSpec(AXIS),
            check_vma=False,
        )(*inputs)
    if padded != count:
        outputs = jax.tree.map(lambda leaf: leaf[:count], outputs)
    return jax.tree.map(lambda leaf: _readable(leaf, mesh), outputs)


def _readable(leaf, mesh: Mesh | None):
    """``leaf``, copied to every device when it is a concrete array that spans several
    processes (outside `jax.jit`, on several hosts): a process can read only its own devices'
    data, and the estimators' host checks read the per-sample outputs."""
    if mesh is None or isinstance(leaf, jax.core.Tracer) or getattr(leaf, "is_fully_addressable", True):
        return leaf
    return _replicate(mesh)(leaf)


@functools.lru_cache(maxsize=None)
def _replicate(mesh: Mesh) -> Callable:
    """The identity, its output copied to every device of ``mesh`` (compiled once per shape)."""
    return jax.jit(lambda leaf: leaf, out_shardings=NamedSharding(mesh, PartitionSpec()))


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
    devices of ``mesh`` (default: all of them) by sharding constraints on inputs and outputs
    (see :func:`shard_leading`); exactly ``jax.vmap(fn)`` on one device.

    An axis whose length is not a multiple of the device count is not split (an uneven split
    would pad every device to the longest share). For batches whose members run
    data-dependent loops, :func:`map_samples` gives each device its own loop instead."""
    batched = jax.vmap(fn)

    def run(*args):
        target = sample_mesh() if mesh is None else mesh
        if target is None:
            return batched(*args)
        return shard_leading(batched(*shard_leading(args, target)), target)

    return run
