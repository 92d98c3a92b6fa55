r"""`simulate_lti_batch`: many LTI plant+observer samples given by ``model(params_k)``, exact
stepping, metrics only.

Each sample's plant and observers come from a user function ``model(params_k)`` (under
`jax.vmap`); the joint system is reduced and discretised by the batch-last kernel of
`fojax.simulation._batch` and the requested reductions are accumulated inside the time
loop, streamed, padded and sharded by the one driver, `fojax.simulation._driver.run_batched`.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array

from .._dtype import as_float_array
from .._errors import InputError, ShapeError
from ._batch import _output_basis, block_for, DEFAULT_BLOCK
from ._driver import _chunk_core, _mesh_for, _step_size, DEFAULT_CHUNK, run_batched
from ._exponential_setup import _parse_model_output, batch_params
from ._joint import joint_matrices
from ._reduction import (
    check_index1_host,
    is_concrete,
    lti_matrices,
    svd_split,
)


#: Reductions understood by `simulate_lti_batch` (``kind`` of a metric).
METRIC_KINDS = ("iae", "ise", "iae_l1", "ise_l2")


#: ``(kind, C, "sum")`` of the one metric vocabulary (`fojax.simulation._save`) → the kernel's
#: summed integrand (``"iae_l1"``, ``"ise_l2"``: their legacy names, still accepted as kinds).
_SUMMED = {"iae": "iae_l1", "ise": "ise_l2"}


def _joint_system(plant, observers, x0, split=None, r=None):
    """`joint_matrices` of a model's plant and observers (zero input), with the checks of
    `simulate_lti_batch`."""
    mats = lti_matrices(plant)
    if mats is None:
        raise InputError(
            "simulate_lti_batch needs a linear time-invariant plant (DescriptorSystem, or "
            f"UncertainDescriptorSystem with a Constant δ); model returned {type(plant).__name__}. "
            "Use jax.vmap(fojax.simulate) for other plants."
        )
    A, B, C = mats
    bad = [type(o).__name__ for o in observers if o.linear_matrices() is None]
    if bad:
        raise InputError(
            f"simulate_lti_batch needs LTI observers (linear_matrices() not None); {bad} are not."
        )
    return joint_matrices(plant.E, A, B, C, observers, x0, split, r)


def _integrand(o, kinds):
    """The metric integrands ``(R, b)`` of the stacked outputs ``o`` ``(K, b)`` (one row
    per output for ``iae``/``ise``, one per metric for ``iae_l1``/``ise_l2``)."""
    parts, off = [], 0
    for kind, k in kinds:
        ok = o[off : off + k]
        off += k
        if kind == "iae":
            parts.append(jnp.abs(ok))
        elif kind == "ise":
            parts.append(ok * ok)
        elif kind == "iae_l1":
            parts.append(jnp.sum(jnp.abs(ok), axis=0, keepdims=True))
        else:  # ise_l2
            parts.append(jnp.sum(ok * ok, axis=0, keepdims=True))
    return jnp.concatenate(parts, axis=0)


class _ModelProblem(eqx.Module):
    """The samples of `simulate_lti_batch`: ``model(params_k)``, zero input, the
    integrated metric kinds of ``Cstack``. A *problem* of the batch kernel gives, per
    sample ``p``, `joint` ``(Aj, w0, G, ok, jumps)`` (``G`` the metric outputs' map on
    the joint slow state, ``jumps`` ``None`` or ``(times (J,), Δw (J, N))``), and the
    reduction of the outputs along the grid (`init`, `update`, `final`)."""

    model: Callable
    Cstack: Array
    split: object
    r: int | None = eqx.field(static=True)
    kinds: tuple = eqx.field(static=True)
    keep: bool = eqx.field(static=True, default=False)
    #: the key of `fojax.simulation._batch.TRACE_COUNTS` counting this problem's compilations
    trace_name: ClassVar[str] = "simulate_lti_batch"

    def joint(self, p):
        params, x0k = p
        plant, observers = _parse_model_output(self.model(params), with_input=False)
        Aj, w0, out_map, ok = _joint_system(plant, observers, x0k, self.split, self.r)
        return Aj, w0, self.Cstack @ out_map, ok, None

    def init(self, o0):
        return jnp.zeros_like(_integrand(o0, self.kinds))

    def update(self, acc, o, k, ts):
        return acc + _integrand(o, self.kinds)

    def update_block(self, acc, O, ks, ts):
        """`update` over ``m`` steps at once: ``O`` ``(b, K, m)``."""
        parts, off = [], 0
        for kind, k in self.kinds:
            ok = O[:, off : off + k]
            off += k
            v = jnp.sum(jnp.abs(ok) if kind in ("iae", "iae_l1") else ok * ok, axis=2)  # (b, k)
            parts.append(jnp.sum(v, axis=1, keepdims=True) if kind in ("iae_l1", "ise_l2") else v)
        return acc + jnp.concatenate(parts, axis=1).T

    def final(self, acc, o0, o_end, ts, h, ok):
        # trapezoid: h (f_0/2 + f_1 + ... + f_{T-2} + f_{T-1}/2); acc holds f_1 .. f_{T-1}
        out = h * (acc + 0.5 * _integrand(o0, self.kinds) - 0.5 * _integrand(o_end, self.kinds))
        return jnp.where(ok[None, :], out, jnp.nan)


def _check_metrics(metrics, size):
    if not isinstance(metrics, Mapping) or not metrics:
        raise InputError("metrics must be a non-empty mapping name -> (kind, C).")
    names, kinds, mats = [], [], []
    for name, spec in metrics.items():
        ok = isinstance(spec, tuple) and (
            (len(spec) == 2 and spec[0] in METRIC_KINDS)
            or (len(spec) == 3 and spec[0] in ("iae", "ise") and spec[2] in ("none", "sum"))
        )
        if not ok:
            raise InputError(
                f"metrics[{name!r}] must be a tuple (kind, C) or (kind, C, reduce) with kind in ('iae', 'ise') "
                f"and reduce 'none' (per row of C) or 'sum' (over the rows: the metric table of "
                f"fojax.simulation._save; legacy kinds 'iae_l1' = ('iae', C, 'sum'), 'ise_l2' = "
                f"('ise', C, 'sum')); got {spec!r}."
            )
        kind, C = spec[0], spec[1]
        if len(spec) == 3 and spec[2] == "sum":
            kind = _SUMMED[kind]  # the kernel's name of the summed integrand
        C = as_float_array(f"metrics[{name!r}] C", C)
        if C.ndim == 1:
            C = C[None, :]
        if C.ndim != 2 or C.shape[1] != size:
            raise ShapeError(
                f"metrics[{name!r}] C",
                f"(k, {size}) acting on [x; observer states]",
                tuple(C.shape),
            )
        names.append(name)
        kinds.append((kind, int(C.shape[0])))
        mats.append(C)
    return names, tuple(kinds), jnp.concatenate(mats, axis=0)


@eqx.filter_jit
def _first_sample(model, p0, x00):
    """Sample 0, compiled once per structure (done eagerly, this host preparation would be
    traced again on every call): ``E``, ``A``, the SVD split of ``E`` and the full-size output map
    of the joint state."""
    plant, observers = _parse_model_output(model(p0), with_input=False)
    split = svd_split(plant.E)
    _, _, out_map, _ = _joint_system(plant, observers, x00, split, None)
    sizes = (plant.n,) + tuple(o.state_size for o in observers)  # static (Python ints)
    return plant.E, lti_matrices(plant)[0], split, out_map, sizes


@eqx.filter_jit
def _same_E(model, params, E0):
    """Whether every sample of ``params`` (leading batch axis) has ``E == E0``."""
    Es = jax.vmap(lambda p: _parse_model_output(model(p), with_input=False)[0].E)(params)
    return jnp.all(Es == E0[None])


def simulate_lti_batch(
    model: Callable,
    params,
    x0,
    ts,
    *,
    metrics: Mapping[str, tuple],
    chunk_size: int = DEFAULT_CHUNK,
    block: int = DEFAULT_BLOCK,
    devices=None,
) -> dict:
    r"""Integrated metrics of a batch of LTI descriptor plants (+ LTI observers), exactly.

    For every sample $k$, ``model(params_k)`` returns a linear time-invariant descriptor
    plant $E\dot x = A_k x$ (zero input: put feedback into the matrices) and optionally
    LTI observers $\dot\xi_i = A_{o,i}\xi_i + B_{y,i} y$ started at their
    `initial_state()`. The joint system is reduced to its slow ODE (the index-1
    reduction of `fojax.simulate`, kept in the ``rank E`` slow coordinates) and
    discretised exactly on the uniform grid ``ts`` (one matrix exponential per sample,
    `expm_last`); the samples are then stepped together and, for each requested metric
    ``name: (kind, C)`` with $o = C\,[x;\xi_1;\dots]$, the trapezoid rule on ``ts`` is
    accumulated during the time loop:

    - ``"iae"``: $\int |o_i|\,\mathrm dt$ per row of ``C`` → ``(B, k)``;
    - ``"ise"``: $\int o_i^2\,\mathrm dt$ per row → ``(B, k)``;
    - ``("iae", C, "sum")`` (legacy ``"iae_l1"``): $\int \|o\|_1\,\mathrm dt$ → ``(B,)``;
    - ``("ise", C, "sum")`` (legacy ``"ise_l2"``): $\int \|o\|_2^2\,\mathrm dt$ → ``(B,)``.

    This is the exact stepper's batch kernel (`fojax.Exact`): `fojax.run_study` with
    ``stepper=Exact()`` or ``Auto()`` runs the same kernel (`run_batched`) on a `Study`;
    this function is its entry for a user's own ``model(params)``.

    **How it runs.** No trajectory is stored. Batches are streamed in chunks of
    `chunk_size` samples (rounded up to a multiple of ``block × devices``; the last
    chunk padded), so the kernel is compiled once per *structure* (model, shapes, metric
    kinds, chunk) and reused for any ``B`` and any numbers; memory is
    ``O(chunk_size)``. Inside a chunk, samples are processed in blocks of `block`: a
    block is discretised and then stepped through the whole grid with the batch as the
    last axis (``Φ`` ``(N, N, block)``, each step ``N²`` fused multiply–adds per
    sample), so its data stays in the CPU cache; only blocks holding real samples are
    computed. With several devices (`devices`, default: all local devices, e.g.
    ``XLA_FLAGS=--xla_force_host_platform_device_count=2`` for two CPU cores) the blocks
    are distributed round-robin with `jax.shard_map` — one code path for one or many
    devices; the result does not depend on the number of devices or the block size
    (each sample's arithmetic is the same).

    When every sample has the same ``E`` (checked on the host), its SVD split is
    computed once; otherwise each sample computes its own and a sample whose ``rank E``
    differs from the first sample's gets ``nan`` metrics.

    **Arguments:**

    - `model`: ``params_k -> plant`` or ``(plant, observers)``; the plant must be a
      `fojax.DescriptorSystem` (or an `UncertainDescriptorSystem` with constant ``δ``),
      regular and impulse-free, the observers LTI. Use a stable function object (not a
      new lambda per call) so the compiled kernel is reused.
    - `params`: pytree of arrays with a leading batch axis ``B`` (one entry per sample).
    - `x0`: ``(B, n)`` initial plant states (made consistent by keeping their slow part,
      as `fojax.simulate` does).
    - `ts`: ``(T,)`` uniform increasing output grid.
    - `metrics`: mapping ``name -> (kind, C)`` or ``(kind, C, reduce)``, ``kind``
      ``"iae"`` or ``"ise"``, ``reduce`` ``"none"`` (default, per row) or ``"sum"`` (over
      the rows; the legacy kinds ``"iae_l1"``, ``"ise_l2"`` mean ``("iae", C, "sum")``,
      ``("ise", C, "sum")``): the names of `fojax.Metrics` (metric table of
      `fojax.simulation._save`). ``C`` of shape ``(k, n + Σ observer sizes)`` (or
      ``(n + Σ,)``).
    - `chunk_size`: samples per compiled call (default 4096).
    - `block`: samples stepped together in one time loop (default 256): ``Φ`` and the
      output maps of a block, ``8 (N² + k N) · block`` bytes, should fit in the CPU's
      L2 cache; it is capped by `block_for`: for ``N ≥ 10`` 64 at ``N = 64``, 16 at
      ``N = 128``; below, ``Φ`` within 64 KiB (128 at ``N = 6 … 8``, 64 at ``N = 9``).
      (The time loop is not unrolled: unrolling is slower.)
    - `devices`: the devices to spread the blocks over (default `jax.local_devices()`).

    **Returns:** a dict ``name -> (B,)`` or ``(B, k)`` array (float64).

    **Raises:** `fojax.errors.InputError` (non-LTI model, unknown metric kind, non-uniform
    grid, bad sizes), `fojax.errors.ShapeError`; index-1 checks run on the host for the first
    sample when the inputs are concrete. Samples whose plant is impulsive give non-finite
    metrics. Not differentiable in reverse mode (the block loop has a data-dependent
    trip count); use `fojax.simulate` under `jax.grad`.
    """
    x0, Bn = batch_params(params, x0)
    chunk_size, block = int(chunk_size), int(block)
    if chunk_size < 1:
        raise InputError(f"chunk_size must be a positive integer, got {chunk_size}.")
    if block < 1:
        raise InputError(f"block must be a positive integer, got {block}.")
    T, h, ts = _step_size(ts)
    params = jax.tree.map(jnp.asarray, params)
    first = jax.tree.map(lambda a: lax.index_in_dim(a, 0, keepdims=False), params)
    n = x0.shape[1]
    concrete = is_concrete(params, x0)
    if concrete:  # compiled once per structure; raises the InputError of a non-LTI model
        E0, A0, split0, out_map0, sizes = _first_sample(model, first, lax.index_in_dim(x0, 0, keepdims=False))
    else:
        plant0, observers0 = _parse_model_output(model(first), with_input=False)
        sizes = (plant0.n,) + tuple(o.state_size for o in observers0)
    if sizes[0] != n:
        raise ShapeError("x0", f"(B, {sizes[0]})", tuple(x0.shape))
    names, kinds, Cstack = _check_metrics(metrics, sum(sizes))
    if concrete:
        E0, out_map0 = np.asarray(E0), np.asarray(out_map0)
        check_index1_host(E0, np.asarray(A0), jacobian_name="A")
        r = int(np.sum(np.asarray(split0.slow)))
        G0 = np.asarray(Cstack) @ np.delete(out_map0, np.s_[r:n], axis=1)
        Nc = _output_basis(G0)
        Nc = None if Nc is None else (Nc[0], jnp.asarray(Nc[1]))
    else:
        if lti_matrices(plant0) is None:
            _joint_system(plant0, observers0, None)  # raises the InputError naming the plant
        split0, Nc = None, None
        r = int(np.sum(np.asarray(svd_split(plant0.E).slow))) if is_concrete(plant0.E) else None
    mesh = _mesh_for(devices)
    D = 1 if mesh is None else mesh.devices.size
    if r is not None:
        block = block_for(r + sum(sizes[1:]), block)
    block = min(block, -(-min(chunk_size, Bn) // D))  # tiny batches: no block of mostly padding
    unit = block * D
    bc = -(-chunk_size // unit) * unit

    n_chunks = -(-Bn // bc)
    pad = n_chunks * bc - Bn
    samples = (params, x0)  # unpadded: `run_batched` pads them itself
    if pad:
        padf = lambda a: jnp.concatenate(  # noqa: E731
            [a, jnp.repeat(lax.slice_in_dim(a, Bn - 1, Bn), pad, axis=0)], axis=0
        )
        params, x0 = jax.tree.map(padf, params), padf(x0)
    nreal = np.minimum(Bn - bc * np.arange(n_chunks), bc)
    chunks = None
    split = None
    if split0 is not None:
        # every sample shares E (checked per chunk, compiled once): one SVD split for all
        chunks = [
            jax.tree.map(lambda a, i=i: lax.slice_in_dim(a, i * bc, (i + 1) * bc), (params, x0))
            for i in range(n_chunks)
        ]
        if all(bool(_same_E(model, c[0], E0)) for c in chunks):
            split = split0
    problem = _ModelProblem(model, Cstack, split, r, kinds)
    if chunks is not None and is_concrete(h, Cstack, ts):
        # concrete inputs: the one chunk / pad / device front of the batch kernels, the one
        # `run_study` runs (`run_batched`: same chunks, blocks and per-sample arithmetic)
        out, _ = run_batched(problem, samples, ts, chunk_size=chunk_size, block=block, devices=devices, basis=Nc)
    elif n_chunks == 1:
        out = _chunk_core(problem, (params, x0), jnp.asarray(nreal[0]), h, ts, block, Nc, mesh)
    else:
        resh = lambda a: a.reshape((n_chunks, bc) + a.shape[1:])  # noqa: E731
        res = lax.map(
            lambda px: _chunk_core(problem, (px[0], px[1]), px[2], h, ts, block, Nc, mesh),
            (jax.tree.map(resh, params), resh(x0), jnp.asarray(nreal)),
        )  # (n_chunks, R, bc)
        out = jnp.moveaxis(res, 1, 0).reshape(res.shape[1], n_chunks * bc)
    out = out[:, :Bn].T  # (B, R)
    result, off = {}, 0
    for name, (kind, k) in zip(names, kinds):
        r_ = 1 if kind in ("iae_l1", "ise_l2") else k
        result[name] = out[:, off] if kind in ("iae_l1", "ise_l2") else out[:, off : off + r_]
        off += r_
    return result
