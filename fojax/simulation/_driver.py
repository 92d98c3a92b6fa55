r"""The one chunk / pad / shard driver of the batch kernels.

`run_batched` runs any batch problem (`fojax.simulation._problem.AbstractBatchProblem`: the
exact study problems of `fojax.studies._exact`, the exponential integrator's
`fojax.simulation._exponential.ExponentialProblem`, `run_study`'s per-sample
`fojax.studies._runner.SimulateProblem`) over a batch of samples:

1. the batch is streamed in fixed-size chunks, the last one padded with copies of the
   last sample, so one compilation serves every chunk and every batch size;
2. each chunk is grouped in blocks of samples stepped together (`_device_kernel`: the
   problem's ``block_kernel``, by default the batch-last kernel `_block_kernel`);
3. the blocks are spread round-robin over the devices with `jax.shard_map`, each device
   computing only the blocks that hold real samples; on a mesh spanning several
   processes the result is gathered on every process.

`_step_size` is the batch kernels' one uniform-grid check.
"""

from __future__ import annotations

import os

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax, shard_map
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from tqdm import tqdm

from .._dtype import as_float_array
from .._errors import InputError, ShapeError
from ._batch import block_for, TRACE_COUNTS
from ._problem import AbstractBatchProblem
from ._reduction import is_concrete
from ._steppers import grid_deviation, grid_deviation_traced, UNIFORM_GRID_RTOL


#: Default number of samples per compiled call (discretised together).
DEFAULT_CHUNK = 4096


#: The XLA option of the chunk programs: vectors of 512 bits where the CPU has them
#: (AVX-512). XLA:CPU prefers 256-bit vectors by default; the batch-last time loops are
#: elementwise over the block and gain from the wider vectors on a CPU with full-width
#: AVX-512 units (``benchmarks/loop_block.py`` measures both). Without AVX-512 the option
#: changes nothing. Left out when ``XLA_FLAGS`` sets the width (the user's choice wins).
VECTOR_WIDTH_OPTION = "xla_cpu_prefer_vector_width"


def kernel_compiler_options(environ=None) -> dict:
    """The XLA compiler options of the batch kernels' programs (`VECTOR_WIDTH_OPTION`)."""
    environ = os.environ if environ is None else environ
    if VECTOR_WIDTH_OPTION in environ.get("XLA_FLAGS", ""):
        return {}
    return {VECTOR_WIDTH_OPTION: 512}


def _device_kernel(problem, p, nvalid, h, ts, basis, dev):
    """The blocks of one device: leaves of ``p`` ``(nb, block, ...)``; the first
    ``nvalid`` blocks are computed (a while loop), the others stay zero."""
    nb = jax.tree.leaves(p)[0].shape[0]
    take = lambda a, i: lax.dynamic_index_in_dim(a, i, keepdims=False)  # noqa: E731
    # the problem's block kernel: the exact batch-last one, or its own (ETDRK4, simulate)
    kernel = problem.block_kernel
    shape = jax.eval_shape(lambda q: kernel(q, h, ts, basis), jax.tree.map(lambda a: a[0], p))
    # block i's output (..., b) goes to out[..., i, :]: blocks next to each other along the
    # batch, so that `_chunk_core`'s reordering to (..., bc) is a reshape on one device
    # (with the blocks first, it was a copy of every output: 33 MB per chunk of 2,048
    # samples for the quantile bands' errors of the default §3.3.7 study)
    out = jax.tree.map(lambda s: jnp.zeros(s.shape[:-1] + (nb, s.shape[-1]), s.dtype), shape)

    def put(o, r_, i):
        return lax.dynamic_update_slice(o, r_[..., None, :], (0,) * (r_.ndim - 1) + (i, 0))

    def body(i, out):
        res = kernel(jax.tree.map(lambda a: take(a, i), p), h, ts, basis)
        return jax.tree.map(lambda o, r_: put(o, r_, i), out, res)

    return lax.fori_loop(0, nvalid[dev], body, out)


@eqx.filter_jit(compiler_options=kernel_compiler_options())
def _chunk_core(problem, p, nreal, h, ts, block, basis, mesh):
    """One chunk of ``bc`` samples (leading axis of every leaf of ``p``), of which the
    first ``nreal`` are real.

    Samples are grouped in blocks of ``block``; block ``k`` goes to device ``k mod D``
    (balanced within one block); each device computes only its blocks that hold real
    samples. Returns the problem's reduction with the batch as the last axis ``bc``.
    """
    TRACE_COUNTS[problem.trace_name] += 1
    bc = jax.tree.leaves(p)[0].shape[0]
    D = 1 if mesh is None else mesh.devices.size
    nb = bc // (block * D)
    # (bc, ...) -> (D, nb, block, ...): block k = j*D + d on device d
    arrange = lambda a: jnp.swapaxes(a.reshape((nb, D, block) + a.shape[1:]), 0, 1)  # noqa: E731
    P = jax.tree.map(arrange, p)
    nblocks = (nreal + block - 1) // block
    nvalid = jnp.clip((nblocks - jnp.arange(D) + D - 1) // D, 0, nb)  # (D,)
    if mesh is None:
        out = _device_kernel(problem, jax.tree.map(lambda a: a[0], P), nvalid, h, ts, basis, 0)
        out = jax.tree.map(lambda o: o[None], out)
    else:
        spec = PartitionSpec("devices")

        def local(p_, nv):
            d = lax.axis_index("devices")
            o = _device_kernel(problem, jax.tree.map(lambda a: a[0], p_), nv, h, ts, basis, d)
            return jax.tree.map(lambda a: a[None], o)

        out = shard_map(local, mesh=mesh, in_specs=(spec, PartitionSpec()), out_specs=spec, check_vma=False)(
            P, nvalid
        )

    # (D, *rest, nb, block) -> (*rest, nb, D, block) -> (*rest, bc): a reshape for D = 1
    def unarrange(o):
        k = o.ndim - 3
        rest = o.shape[1 : k + 1]
        if D > 1:
            o = jnp.transpose(o, tuple(range(1, 1 + k)) + (k + 1, 0, k + 2))
        return o.reshape(rest + (bc,))

    return gather_across_processes(jax.tree.map(unarrange, out), mesh)


def spans_processes(mesh) -> bool:
    """Whether `mesh` holds devices of other processes (a global mesh of
    `jax.distributed.initialize`: ``jax.devices()`` of a multi-process run)."""
    return mesh is not None and any(d.process_index != jax.process_index() for d in mesh.devices.flat)


def gather_across_processes(tree, mesh):
    """Inside a jitted function: the arrays of `tree` replicated on every device of
    `mesh` (an all-gather, XLA's collective: gloo on CPU, NCCL on GPU) when the mesh spans
    several processes, so that every process can read the whole result; unchanged
    otherwise (a single process reads the shards of its own devices)."""
    if not spans_processes(mesh):
        return tree
    rep = NamedSharding(mesh, PartitionSpec())
    return jax.tree.map(lambda a: lax.with_sharding_constraint(a, rep), tree)


def run_batched(problem: AbstractBatchProblem, p, ts, *, chunk_size: int, block: int | None, devices=None, basis=None, host: bool = False,
                compile_only: bool = False, progress: bool = False):
    """Run a batch-kernel `problem` over every sample of ``p`` (leaves with a leading
    batch axis ``B``), streamed in fixed-size chunks (the last one padded with copies of
    the last sample; one compilation serves every chunk and every ``B``) and spread over
    `devices`. ``ts`` must be a concrete uniform grid when the problem steps one
    (``problem.uniform_grid``). Returns the problem's reduction with the batch as the
    last axis ``B`` (JAX arrays; NumPy arrays with `host`), and the layout used (chunk
    size after rounding to ``block × devices``, number of chunks, devices, block). With
    `compile_only` it only compiles the program every chunk runs (JAX's caches then give
    it to the later run) and returns ``(None, layout)``; `progress`: a progress bar over
    the chunks.

    `block`: samples per block, at most (capped by the joint size, `block_for`, and by the
    batch); ``None``: one block per device and chunk (``ceil(chunk_size / devices)``
    samples, not capped by the batch, e.g. `fojax.studies._runner.SimulateProblem`,
    whose `jax.vmap`-ed adaptive loops gain nothing from blocking).

    **Memory.** Besides the result itself, only one chunk's work is alive at a time: with
    `host` (`run_study`) each chunk's result is copied into one preallocated NumPy array
    of the whole batch while the next chunk computes, then dropped, so the peak is the
    result plus about two chunks' outputs (before: every chunk's output, their
    concatenation and its slice to ``B``, three copies of the result: the quantile bands'
    error trajectories, ``8 · T_c · K · B`` bytes, are the one output of size ``B``).
    Without `host` the chunks' valid parts are concatenated once (two copies at the
    peak)."""
    if problem.uniform_grid:
        T, h, ts = _step_size(ts)
    else:  # the problem's kernel takes the grid as it is (no step)
        ts = as_float_array("ts", ts, ndim=1)
        h = jnp.zeros((), ts.dtype)
    Bn = jax.tree.leaves(p)[0].shape[0]
    mesh = _mesh_for(devices)
    D = 1 if mesh is None else mesh.devices.size
    # a global mesh (several processes): the block width of one device, so that every
    # block has the shapes of a one-process run and its samples the same bits (batched
    # products of other widths differed by ~1e-15 on a study with fault onsets)
    Dw = 1 if spans_processes(mesh) else D
    if block is None:  # one block per device and chunk
        block = max(1, -(-int(chunk_size) // D))
    else:
        block = block_for(problem.joint_size(p), int(block))  # the exact kernel: by N; own stepping: N is None
        block = max(1, min(int(block), -(-min(int(chunk_size), Bn) // Dw)))
    unit = block * D
    bc = -(-int(chunk_size) // unit) * unit
    n_chunks = -(-Bn // bc)
    pad = n_chunks * bc - Bn
    # host (NumPy) leaves are padded and sliced on the host, the chunks transferred by the call
    xp = np if all(isinstance(a, np.ndarray) for a in jax.tree.leaves(p)) else jnp
    if pad:
        p = jax.tree.map(lambda a: xp.concatenate([a, xp.repeat(a[Bn - 1 : Bn], pad, axis=0)], axis=0), p)
    layout = dict(chunk_size=bc, num_chunks=n_chunks, num_devices=D, block=block)
    outs, result, pending = [], None, None

    def store(i, o):  # host: chunk i's valid samples into the preallocated result, then drop it
        nonlocal result
        o = jax.tree.map(np.asarray, o)  # waits for chunk i (chunk i + 1 is already dispatched)
        if result is None:
            result = jax.tree.map(lambda a: np.empty(a.shape[:-1] + (Bn,), a.dtype), o)
        nv = min(Bn - i * bc, bc)
        for dst, src in zip(jax.tree.leaves(result), jax.tree.leaves(o)):
            dst[..., i * bc : i * bc + nv] = src[..., :nv]

    for i in tqdm(range(n_chunks), disable=not progress or compile_only, desc="study", unit="chunk"):
        pc = jax.tree.map(lambda a, i=i: a[i * bc : (i + 1) * bc], p)
        nv = min(Bn - i * bc, bc)
        if compile_only:  # one program for every chunk (the last one is padded)
            _chunk_core.lower(problem, pc, np.asarray(nv), h, ts, block, basis, mesh).compile()
            return None, layout
        o = _chunk_core(problem, pc, np.asarray(nv), h, ts, block, basis, mesh)
        if host:
            if pending is not None:
                store(*pending)
            pending = (i, o)
        else:
            outs.append(jax.tree.map(lambda a, nv=nv: a[..., :nv], o))
    if host:
        store(*pending)
        return result, layout
    out = outs[0] if n_chunks == 1 else jax.tree.map(lambda *a: jnp.concatenate(a, axis=-1), *outs)
    return out, layout


def _step_size(ts, who: str = "run_study"):
    """``(T, h, ts)`` of a uniform increasing grid (the batch kernels' entries; `who` names
    the caller in the error): the host test is `fojax.simulation._steppers.grid_deviation`,
    a traced grid is checked at run time."""
    ts = as_float_array("ts", ts, ndim=1)
    T = ts.shape[0]
    if T < 2:
        raise ShapeError("ts", "(T,) with T >= 2", tuple(ts.shape), "ts[0] is the initial time.")
    if is_concrete(ts):
        dev, h = grid_deviation(ts)
        if not dev <= UNIFORM_GRID_RTOL:  # also refuses decreasing grids (h <= 0)
            raise InputError(
                f"{who} steps on a uniform increasing grid; ts is not one "
                f"(max |ts_k − (t0 + k h)| / h = {dev:.2e} > {UNIFORM_GRID_RTOL:.0e}, h = {h:g}). "
                "Use ts = jnp.linspace(t0, t1, T)."
            )
        return T, np.asarray(h, dtype=ts.dtype), ts
    dev, h = grid_deviation_traced(ts)
    h = eqx.error_if(
        h,
        ~((dev <= UNIFORM_GRID_RTOL) & (h > 0)),
        f"{who} needs a uniform increasing grid ts (runtime check).",
    )
    return T, h, ts


def _mesh_for(devices):
    """A 1-d mesh over `devices` (``None``: all local devices of the default backend), or
    ``None`` for a single device."""
    if devices is None:
        devices = jax.local_devices()
    devices = list(devices)
    if not devices:
        raise InputError("devices must contain at least one jax.Device.")
    if len(devices) == 1:
        return None
    return Mesh(np.array(devices), ("devices",))
