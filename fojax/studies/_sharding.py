r"""The samples of a differentiable study loss spread over devices, and over processes.

`run_study` streams chunks through `fojax.simulation._driver.run_batched` (forward only);
`study_loss` (what `tune` differentiates) computes every sample in one traced block. With
`devices` (``SimConfig.devices``) that block is cut along the sample axis over a 1-d
`jax.sharding.Mesh` (`jax.shard_map`: each device computes its own samples, no
collective inside the time loop); the mesh may be global, spanning the devices of every
process of a `jax.distributed.initialize` run (CPU: gloo; GPU: NCCL).

**The same bits on any split.** Each sample's arithmetic does not depend on which
samples share its device (the exact kernel's per-sample scaling and squaring; `jax.vmap`
elsewhere). What would depend on the split are the two reductions *over* samples:

- the loss (mean or quantile over samples): the per-sample values are all-gathered
  (replicated on every device) before it is taken, so every device reduces the same
  ``(B,)`` vector in the same order;
- the gradient of the observer's arrays, a sum over samples of their per-sample
  cotangents. Reverse mode through `shard_map` would sum each device's samples and then
  ``psum`` the partial sums, in an order that depends on the number of devices. Instead
  the observer is broadcast to one copy per sample (`_broadcast_rows`, a `jax.custom_vjp`)
  whose backward pass gathers the ``(B, ...)`` per-sample cotangents and sums them in one
  reduction over the sample axis: the order of a single device.

So the loss and its gradient are bit-identical for one device, several local devices or
several processes (tested in ``tests/test_distributed.py``), and the cost is one copy of
the observer's arrays per sample (a few hundred numbers each). Leaves of the study that
are differentiated (not the case in `tune`; on the exact kernel `study_loss` refuses it)
get the ``psum`` of reverse mode: correct, but their last bits may depend on the split.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from .._errors import DistributedError, InputError
from ..simulation._driver import spans_processes as mesh_spans_processes


AXIS = "batch"


def sample_mesh(devices) -> Mesh | None:
    """The 1-d mesh over `devices` (a sequence of `jax.Device`, e.g. ``jax.devices()`` of
    a multi-process run), or ``None`` (`devices` ``None``: one block on the default
    device, as before)."""
    if devices is None:
        return None
    devices = list(devices)
    if not devices or not all(isinstance(d, jax.Device) for d in devices):
        raise InputError(
            f"devices must be a non-empty sequence of jax.Device (e.g. jax.devices()); got {devices!r}."
        )
    return Mesh(np.asarray(devices), (AXIS,))


def replicate(tree, devices):
    """Host: the arrays of `tree` placed replicated on the mesh of `devices` (no-op for
    ``None``), so that a jitted step fed its own outputs (replicated on that mesh) sees
    the same input placement from the first call on and compiles once."""
    mesh = sample_mesh(devices)
    if mesh is None:
        return tree
    arrays, rest = eqx.partition(tree, eqx.is_array)
    return eqx.combine(jax.device_put(arrays, NamedSharding(mesh, PartitionSpec())), rest)


def _replicated(a, mesh):
    return a if mesh is None else lax.with_sharding_constraint(a, NamedSharding(mesh, PartitionSpec()))


@functools.partial(jax.custom_vjp, nondiff_argnums=(1, 2, 3))
def _broadcast_rows(leaves, rows: int, real: int, mesh):
    """``rows`` copies of every leaf (a new leading axis); the backward pass sums the
    cotangents of the first ``real`` copies, gathered on every device, in one reduction."""
    return [jnp.broadcast_to(a, (rows,) + a.shape) for a in leaves]


def _broadcast_fwd(leaves, rows, real, mesh):
    return _broadcast_rows(leaves, rows, real, mesh), None


def sum_rows(a):
    """``a[0] + a[1] + ...`` in this order (a `jax.lax.scan`): a reduction XLA neither
    reassociates nor fuses into its producer differently in one- and many-device
    programs (``jnp.sum`` may: its sum on 4 devices over 2 processes can differ from one
    device in the last bits). `a` may be a pytree of arrays
    with the same leading length: one loop sums every leaf (the observers' cotangents: one
    loop instead of one per matrix, fewer kernels to compile)."""
    zeros = jax.tree.map(lambda x: jnp.zeros(x.shape[1:], x.dtype), a)
    acc, _ = lax.scan(lambda acc, row: (jax.tree.map(jnp.add, acc, row), None), zeros, a)
    return acc


def _broadcast_bwd(rows, real, mesh, _, cts):
    return (sum_rows([_replicated(c, mesh)[:real] for c in cts]) if cts else [],)


_broadcast_rows.defvjp(_broadcast_fwd, _broadcast_bwd)


def per_sample(local, shared, observers, iu, jf, mesh):
    """``local(shared, (iu_s, jf_s, observers_s))`` over all samples, spread over `mesh`.

    `local` maps a slice of samples (index arrays ``(b,)`` and one copy of the
    observers per sample, leading axis ``b``) to a pytree of arrays with the sample axis
    first; `shared` (the study, the problem) is replicated. Returns that pytree for all
    ``B = len(iu)`` samples, replicated on every device of `mesh` (every process reads
    it). The sample axis is padded with copies of sample 0 to a multiple of the number of
    devices; the copies are dropped. Traceable.
    """
    B = int(iu.shape[0])
    D = 1 if mesh is None else int(mesh.devices.size)
    rows = -(-B // D) * D
    if rows > B:
        iu = jnp.concatenate([iu, jnp.zeros((rows - B,), iu.dtype)])
        jf = jnp.concatenate([jf, jnp.zeros((rows - B,), jf.dtype)])
    diff, rest = eqx.partition(observers, eqx.is_inexact_array)
    leaves, treedef = jax.tree.flatten(diff)
    diff = jax.tree.unflatten(treedef, _broadcast_rows(leaves, rows, B, mesh))
    rest = jax.tree.map(lambda a: jnp.broadcast_to(a, (rows,) + a.shape) if eqx.is_array(a) else a, rest)
    obs_rows = eqx.combine(diff, rest)
    p = (iu, jf, obs_rows)
    if mesh is None:
        out = local(shared, p)
    else:
        s_dyn, s_static = eqx.partition(shared, eqx.is_array)
        p_dyn, p_static = eqx.partition(p, eqx.is_array)

        def body(s_dyn, p_dyn):
            return local(eqx.combine(s_dyn, s_static), eqx.combine(p_dyn, p_static))

        out = jax.shard_map(body, mesh=mesh, in_specs=(PartitionSpec(), PartitionSpec(AXIS)),
                            out_specs=PartitionSpec(AXIS), check_vma=False)(s_dyn, p_dyn)
        out = jax.tree.map(lambda a: _replicated(a, mesh), out)
    return jax.tree.map(lambda a: a[:B], out)


def spans_processes(devices) -> bool:
    """Whether `devices` (a sequence of `jax.Device`, or ``None``: ``jax.devices()``)
    include devices of other processes."""
    devices = jax.devices() if devices is None else devices
    return mesh_spans_processes(Mesh(np.asarray(list(devices)), (AXIS,)))


def check_same_on_every_process(tree, what: str) -> None:
    """Host, multi-process runs only: raise `DistributedError` unless every process passes
    the same numbers in `tree` (a SHA-256 of its arrays' bytes, shapes and dtypes,
    all-gathered). The arrays a global mesh replicates are taken from each process's own
    copy, so processes fed different models, seeds or designs would silently mix them."""
    if jax.process_count() == 1:
        return
    from jax.experimental import multihost_utils

    h = hashlib.sha256()
    for leaf in jax.tree.leaves(eqx.filter(tree, eqx.is_array)):
        a = np.asarray(leaf)
        h.update(f"{a.shape}{a.dtype}".encode())
        h.update(np.ascontiguousarray(a).tobytes())
    mine = np.frombuffer(h.digest(), dtype=np.uint8)
    with distributed_errors(what):
        every = np.asarray(multihost_utils.process_allgather(mine))  # (processes, 32)
    differ = [p for p in range(every.shape[0]) if not np.array_equal(every[p], every[0])]
    if differ:
        raise DistributedError(
            f"{what}: processes {differ} of {every.shape[0]} hold other numbers than process 0 (SHA-256 of "
            "the arrays differs). Every process must build the same study and observers: run the same "
            "model file, seed and fojax version on every host."
        )


def broadcast_bytes(data: bytes | None, what: str) -> bytes:
    """Host, every process of a multi-process run calls it: process 0's `data` (``None``:
    no bytes) on every process, bit for bit (sent as ``uint8``; a float broadcast by
    `multihost_utils.broadcast_one_to_all`, a sum with zeros, would turn ``-0.0`` into
    ``0.0``). The other processes' `data` is ignored. One process: `data` itself.

    The one way process 0's *files* reach the others (a tuning checkpoint to resume from,
    the folder of ``fojax study --resume``), so that every process continues from the same
    state without a file system shared by the hosts, and none reads a file while process 0
    replaces it."""
    if jax.process_count() == 1:
        return b"" if data is None else bytes(data)
    from jax.experimental import multihost_utils

    source = jax.process_index() == 0
    data = b"" if data is None or not source else bytes(data)
    with distributed_errors(what):
        n = int(multihost_utils.broadcast_one_to_all(np.asarray(len(data), np.int64)))
        buf = np.frombuffer(data, np.uint8) if source else np.zeros(n, np.uint8)
        if n == 0:
            return b""
        out = multihost_utils.broadcast_one_to_all(buf)
    return np.asarray(out, np.uint8).tobytes()


def writes_files(devices) -> bool:
    """Whether this process writes the files of a computation over `devices` (a sequence
    of `jax.Device` or ``None``): always, unless `devices` span several processes; then
    only process 0 does (the others hold the same numbers)."""
    return devices is None or not spans_processes(devices) or jax.process_index() == 0


#: Words of the runtime's messages when another process of a distributed run is gone.
_PEER_FAILURE = ("gloo", "nccl", "coordination", "heartbeat", "connection reset", "peer", "barrier")


@contextlib.contextmanager
def distributed_errors(what: str):
    """Turn the runtime error of a collective whose peer process died (multi-process runs
    only) into a `DistributedError` naming this process and what to do."""
    try:
        yield
    except (jax.errors.JaxRuntimeError, ValueError, RuntimeError) as err:
        # the same lost peer reaches Python as a JaxRuntimeError or, e.g. from
        # multihost_utils.process_allgather, as a ValueError ("UNKNOWN: Gloo AllGather
        # failed: ... Connection closed by peer"; seen on a 3-process loopback run)
        msg = str(err)
        if (isinstance(err, DistributedError) or jax.process_count() == 1
                or not any(w in msg.lower() for w in _PEER_FAILURE)):
            raise
        raise DistributedError(
            f"{what} stopped on process {jax.process_index()} of {jax.process_count()}: another process "
            f"of the distributed run failed or was killed (the runtime reported: {msg.splitlines()[0][:300]}). "
            "Check the other processes' logs, then restart every process (fojax study: with "
            "--resume FOLDER to continue from the last tuning checkpoint)."
        ) from err
