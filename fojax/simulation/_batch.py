r"""`simulate_lti_batch`: many LTI plant+observer samples, exact stepping, metrics only.

A Monte Carlo study of a linear time-invariant loop needs per-sample *numbers*
(integrated errors), not trajectories. This path

1. builds every sample's plant and observers with a user function ``model(params_k)``
   (under `jax.vmap`), reduces the joint system to its slow ODE
   $\dot w = \mathcal A_k w$ in the ``rank E`` slow SVD coordinates of `fojax.simulation`
   (the reduction of `fojax.simulate`'s exact method; the SVD of ``E`` is computed once
   when all samples share it) and discretises it exactly, $\Phi_k = e^{\mathcal A_k h}$
   (`expm_last`: Taylor/Paterson–Stockmeyer scaling-and-squaring over the samples,
   LAPACK-free);
2. when the metric outputs $o = G_k w$ have at most as many independent rows as states,
   changes coordinates to $w' = S_k w$ whose leading entries *are* the outputs, so a time
   step is a single ``N × N`` product per sample (`_output_basis`);
3. steps a block of samples together with the batch as the **last** axis (state
   ``(N, b)``, ``Φ`` ``(N, N, b)``: each step is ``N²`` fused multiply–adds over the
   block, whose data stays in cache) in one `jax.lax.scan` over the grid, and
   accumulates the requested reductions *inside* the scan (trapezoid rule), so no
   ``(B, T, N)`` trajectory is ever stored and memory grows linearly with ``B``;
4. spreads the blocks over all devices with `jax.shard_map` (round-robin, each device
   computing only blocks that hold real samples).

Batches larger than `chunk_size` are streamed in fixed-size chunks, so one compilation
serves every ``B``.
"""

from __future__ import annotations

import collections
from collections.abc import Callable, Mapping

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax, shard_map
from jax.sharding import Mesh, PartitionSpec

from .._dtype import as_float_array
from .._errors import InputError, ShapeError
from .._small_linalg import solve_small
from ..observer import AbstractObserver
from ..plant import AbstractPlant
from ._reduction import (
    check_index1_host,
    is_concrete,
    lti_matrices,
    reduce_linear_masked,
    svd_split,
)
from ._simulate import UNIFORM_GRID_RTOL


#: Number of traces of the compiled chunk kernel (tests prove no retrace with it).
TRACE_COUNTS: collections.Counter = collections.Counter()

#: Reductions understood by `simulate_lti_batch` (``kind`` of a metric).
METRIC_KINDS = ("iae", "ise", "iae_l1", "ise_l2")

#: Default number of samples per compiled call (discretised together).
DEFAULT_CHUNK = 4096
#: Default number of samples stepped together in one time loop (Φ stays in cache).
DEFAULT_BLOCK = 256


def _as_model_output(out):
    if isinstance(out, AbstractPlant):
        return out, ()
    if isinstance(out, tuple) and len(out) == 2 and isinstance(out[0], AbstractPlant):
        obs = out[1]
        if isinstance(obs, AbstractObserver):
            obs = (obs,)
        obs = tuple(obs)
        for i, o in enumerate(obs):
            if not isinstance(o, AbstractObserver):
                raise InputError(
                    f"model(...)[1][{i}] is a {type(o).__name__}, not a fojax.AbstractObserver."
                )
        return out[0], obs
    raise InputError(
        "model(params) must return a fojax.AbstractPlant or a tuple (plant, observers); "
        f"got {type(out).__name__}."
    )


def _joint_system(plant, observers, x0, split=None, r=None):
    """Joint slow matrix ``(N, N)``, initial slow state ``(N,)``, output map ``(n+Σ, N)`` and
    a validity flag.

    With ``r`` (static) the plant part is kept in its ``r`` slow SVD coordinates only
    (``N = r + Σ``, the compact form); the flag is ``False`` when the sample's slow mask is
    not ``[1]*r + [0]*(n-r)`` (a different rank of ``E``). Without ``r`` the masked
    full-size form is used (``N = n + Σ``, fast coordinates identically zero).
    """
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
    red = reduce_linear_masked(plant.E, A, B, split)
    n = A.shape[0]
    As, Tx = red.As, red.Tx
    z0 = red.split.slow * (red.split.V.T @ x0)
    if r is None:
        r, ok = n, jnp.asarray(True)
    else:
        ok = jnp.all(red.split.slow == (jnp.arange(n) < r))
        As, Tx, z0 = As[:r, :r], Tx[:, :r], z0[:r]
    Cs = C @ Tx
    blocks = [[As] + [jnp.zeros((r, o.state_size)) for o in observers]]
    for i, o in enumerate(observers):
        L = o.linear_matrices()
        row = [L.By @ Cs]
        for j, o2 in enumerate(observers):
            row.append(L.A if i == j else jnp.zeros((o.state_size, o2.state_size)))
        blocks.append(row)
    Aj = jnp.block(blocks)
    w0 = jnp.concatenate([z0] + [o.initial_state() for o in observers])
    # joint vector [x; ξ_1; ...] = blkdiag(Tx, I) w
    no = Aj.shape[0] - r
    out_map = jnp.block([[Tx, jnp.zeros((n, no))], [jnp.zeros((no, r)), jnp.eye(no)]])
    return Aj, w0, out_map, ok


def _matvec_last(M, v):
    """``Σ_j M[:, j, :] * v[j, :]`` written as elementwise FMAs over the batch axis."""
    acc = M[:, 0, :] * v[0][None, :]
    for j in range(1, v.shape[0]):
        acc = acc + M[:, j, :] * v[j][None, :]
    return acc


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


#: Taylor degree and scaling threshold of `expm_last`: for ‖X‖₁ ≤ θ the remainder of the
#: degree-m Taylor polynomial is ≤ θ^(m+1)/(m+1)! · e^θ ≈ 2e-17 (θ = 1, m = 18).
_TAYLOR_DEGREE, _TAYLOR_THETA, _PS_BLOCK = 18, 1.0, 4


#: Largest matrix size for which `_mm_last` unrolls the product into column FMAs; above it
#: the graph (``N²`` fused multiply–adds per product) compiles too slowly (measured with
#: the unrolled form at every size: compile 18.5 s at N = 12, 43.6 s at N = 24, against
#: 12.8 s and 25 s with einsum) and the batched einsum is used instead.
_MM_UNROLL_MAX = 10


def _mm_last(A, B):
    """Batch-last matrix product ``(N, K, b) × (K, M, b) → (N, M, b)``.

    For small matrices (``K, M ≤ _MM_UNROLL_MAX``): column by column as fused
    multiply–adds over the batch axis, fenced with `jax.lax.optimization_barrier`.
    Without the fence XLA fuses each product into its consumers and recomputes it per
    use, and the batched ``einsum`` becomes a dot with ``b`` tiny ``N × N`` matrices.
    Measured on the ``7 × 7`` reference loop, one product per sample: einsum 450 ns, this
    55 ns; the whole `expm_last` of 10,000 samples in blocks of 256: einsum 39 ms, this
    11–20 ms, without the fence 100 ms. Larger matrices use the einsum (see
    `_MM_UNROLL_MAX`).
    """
    if max(A.shape[1], B.shape[1]) > _MM_UNROLL_MAX:
        return jnp.einsum("ijb,jkb->ikb", A, B)
    cols = []
    for k in range(B.shape[1]):
        acc = A[:, 0, :] * B[0, k][None, :]
        for j in range(1, A.shape[1]):
            acc = acc + A[:, j, :] * B[j, k][None, :]
        cols.append(acc)
    return lax.optimization_barrier(jnp.stack(cols, axis=1))


def expm_last(M):
    r"""Matrix exponentials of a batch stored batch-last: ``M`` ``(N, N, b)`` → ``(N, N, b)``.

    Scaling and squaring with the degree-18 Taylor polynomial, evaluated by the
    Paterson–Stockmeyer scheme (powers up to $X^4$, then Horner in $X^4$: 7 products
    instead of 17), per sample: $s_k = \max(0, \lceil\log_2\|M_k\|_1\rceil)$ squarings
    (truncation error $\le e/19! \approx 2\cdot 10^{-17}$ relative before squaring). All
    products run over the batch axis (no LAPACK); each sample's result depends only on its
    own matrix, so it does not change with how samples are grouped into blocks. Agrees
    with `scipy.linalg.expm` to rounding (tested).
    """
    import math

    N = M.shape[0]
    norm = jnp.max(jnp.sum(jnp.abs(M), axis=0), axis=0)  # (b,) induced 1-norm
    s = jnp.where(norm > _TAYLOR_THETA, jnp.ceil(jnp.log2(norm / _TAYLOR_THETA)), 0.0)
    s = jnp.clip(jnp.where(jnp.isfinite(s), s, 0.0), 0, 1000).astype(jnp.int32)
    X = M * jnp.exp2(-s.astype(M.dtype))[None, None, :]
    powers = [jnp.broadcast_to(jnp.eye(N, dtype=M.dtype)[:, :, None], M.shape), X]
    for _ in range(2, _PS_BLOCK + 1):
        powers.append(_mm_last(powers[-1], X))
    coef = [1.0 / math.factorial(k) for k in range(_TAYLOR_DEGREE + 1)]
    nblk = _TAYLOR_DEGREE // _PS_BLOCK + 1

    def chunk(j):  # Σ_i c[j·blk + i] X^i
        terms = [coef[j * _PS_BLOCK + i] * powers[i] for i in range(_PS_BLOCK)
                 if j * _PS_BLOCK + i <= _TAYLOR_DEGREE]
        return sum(terms[1:], terms[0])

    E = chunk(nblk - 1)
    for j in range(nblk - 2, -1, -1):
        E = _mm_last(E, powers[_PS_BLOCK]) + chunk(j)

    def square(i, E):
        return jnp.where((i < s)[None, None, :], _mm_last(E, E), E)

    return lax.fori_loop(0, jnp.max(s), square, E)


#: Largest accepted ``‖S‖₁‖S⁻¹‖₁`` of the output-coordinate transform (per sample).
OUTPUT_BASIS_MAX_COND = 1e8


def _output_basis(G0: np.ndarray):
    """Host: ``(ind, Nc)`` for the output-coordinate transform, or ``None``.

    ``ind`` (a tuple) selects ``ρ`` linearly independent rows of the metric map ``G0``
    (pivoted QR of the row-normalised ``G0``); ``Nc`` ``(N − ρ, N)`` is an orthonormal
    basis of the complement of their span, so ``S = [D G_ind; Nc]`` is invertible and
    well conditioned. ``None`` when ``S`` would be ill-conditioned (``cond₁ > 1e4``)."""
    import scipy.linalg

    K, N = G0.shape
    nrm = np.linalg.norm(G0, axis=1, keepdims=True)
    if not np.all(np.isfinite(G0)) or np.any(nrm == 0):
        return None
    Gs = G0 / nrm
    _, R, piv = scipy.linalg.qr(Gs.T, pivoting=True, mode="economic")
    diag = np.abs(np.diag(R))
    rho = int(np.sum(diag > 1e-10 * diag[0]))
    ind = tuple(int(i) for i in np.sort(piv[:rho]))
    _, _, Vt = np.linalg.svd(Gs[list(ind)])
    Nc = Vt[rho:]
    S0 = np.concatenate([Gs[list(ind)], Nc], axis=0)
    if np.linalg.cond(S0, 1) > 1e4:
        return None
    return ind, Nc


def _block_kernel(model, params, x0, h, Cstack, T, kinds, split, r, basis):
    """One block of samples (leading axis ``b``): metrics ``(R, b)``.

    With ``basis = (ind, Nc)`` (from `_output_basis` on the host), each sample's slow
    state is expressed in the coordinates ``w' = S w``, ``S = [D G_ind; Nc]``, whose first
    ``ρ`` entries are the (row-scaled) independent metric outputs; the other outputs are
    ``(G_dep S⁻¹) w'``. A step is then one ``N × N`` product plus ``(K − ρ) × N`` for the
    dependent outputs, instead of ``N × N + K × N``. A sample whose ``S`` has
    ``cond₁ > OUTPUT_BASIS_MAX_COND`` gets ``nan`` metrics.
    """
    K = Cstack.shape[0]
    if basis is not None:
        ind, Nc = basis
        dep = tuple(i for i in range(K) if i not in ind)
        order = np.argsort(np.array(ind + dep))  # o = concat([o_ind, o_dep])[order]

    def per_sample(p, x0k):
        plant, observers = _as_model_output(model(p))
        Aj, w0, out_map, ok = _joint_system(plant, observers, x0k, split, r)
        G = Cstack @ out_map
        if basis is None:
            return Aj, w0, G, jnp.ones((K,), Aj.dtype), ok
        Gi = G[jnp.array(ind)]
        d = jnp.linalg.norm(Gi, axis=1)
        S = jnp.concatenate([Gi / d[:, None], Nc], axis=0)
        Sinv = solve_small(S, jnp.eye(S.shape[0], dtype=S.dtype))
        cond = jnp.max(jnp.sum(jnp.abs(S), axis=0)) * jnp.max(jnp.sum(jnp.abs(Sinv), axis=0))
        ok = ok & (cond <= OUTPUT_BASIS_MAX_COND)
        Gd = G[jnp.array(dep, dtype=int)] @ Sinv if dep else jnp.zeros((0, S.shape[0]), S.dtype)
        return S @ Aj @ Sinv, S @ w0, Gd, d, ok

    Aj, w0, G, scale, ok = jax.vmap(per_sample)(params, x0)  # (b,N,N), (b,N), (b,·,N), (b,·), (b,)
    Phi = expm_last(jnp.moveaxis(h * Aj, 0, -1))  # (N, N, b)
    G = jnp.moveaxis(G, 0, -1)  # (K or K-ρ, N, b)
    scale = scale.T
    w0 = w0.T  # (N, b)

    def outputs(w):
        if basis is None:
            return _matvec_last(G, w)
        o = w[: len(ind)] * scale
        if dep:
            o = jnp.concatenate([o, _matvec_last(G, w)], axis=0)
        if np.array_equal(order, np.arange(K)):
            return o
        return jnp.concatenate([o[i : i + 1] for i in order], axis=0)  # static permutation, no gather

    def integrand(w):  # (N, b) -> (R, b)
        return _integrand(outputs(w), kinds)

    def step(carry, _):
        w, acc = carry
        w = _matvec_last(Phi, w)
        return (w, acc + integrand(w)), None

    f0 = integrand(w0)
    (w_end, acc), _ = lax.scan(step, (w0, jnp.zeros_like(f0)), None, length=T - 1)
    # trapezoid: h (f_0/2 + f_1 + ... + f_{T-2} + f_{T-1}/2); acc holds f_1 .. f_{T-1}
    out = h * (acc + 0.5 * f0 - 0.5 * integrand(w_end))
    return jnp.where(ok[None, :], out, jnp.nan)


def _device_kernel(model, params, x0, nvalid, h, Cstack, layout, split, Nc, dev):
    """The blocks of one device: ``params``/``x0`` ``(nb, block, ...)``; the first
    ``nvalid`` blocks are computed (a while loop), the others stay zero."""
    T, kinds, _, r, R = layout
    nb, block = x0.shape[0], x0.shape[1]

    def body(i, out):
        take = lambda a: lax.dynamic_index_in_dim(a, i, keepdims=False)  # noqa: E731
        res = _block_kernel(model, jax.tree.map(take, params), take(x0), h, Cstack, T, kinds, split, r, Nc)
        return lax.dynamic_update_index_in_dim(out, res, i, 0)

    out = jnp.zeros((nb, R, block), dtype=x0.dtype)
    return lax.fori_loop(0, nvalid[dev], body, out)


@eqx.filter_jit
def _chunk_core(model, params, x0, nreal, h, Cstack, layout, split, Nc, mesh):
    """One chunk of ``bc`` samples (leading axis), of which the first ``nreal`` are real.

    Samples are grouped in blocks of ``block``; block ``k`` goes to device ``k mod D``
    (balanced within one block); each device computes only its blocks that hold real
    samples. Returns ``(R, bc)``.
    """
    TRACE_COUNTS["simulate_lti_batch"] += 1
    T, kinds, block, r, R = layout
    bc = x0.shape[0]
    D = 1 if mesh is None else mesh.devices.size
    nb = bc // (block * D)
    # (bc, ...) -> (D, nb, block, ...): block k = j*D + d on device d
    arrange = lambda a: jnp.swapaxes(a.reshape((nb, D, block) + a.shape[1:]), 0, 1)  # noqa: E731
    P, X = jax.tree.map(arrange, params), arrange(x0)
    nblocks = (nreal + block - 1) // block
    nvalid = jnp.clip((nblocks - jnp.arange(D) + D - 1) // D, 0, nb)  # (D,)
    if mesh is None:
        out = _device_kernel(model, jax.tree.map(lambda a: a[0], P), X[0], nvalid, h, Cstack, layout, split, Nc, 0)
        out = out[None]
    else:
        spec = PartitionSpec("devices")

        def local(p, x, nv):
            d = lax.axis_index("devices")
            o = _device_kernel(model, jax.tree.map(lambda a: a[0], p), x[0], nv, h, Cstack, layout, split, Nc, d)
            return o[None]

        out = shard_map(
            local, mesh=mesh, in_specs=(spec, spec, PartitionSpec()), out_specs=spec, check_vma=False
        )(P, X, nvalid)
    # (D, nb, R, block) -> (R, nb, D, block) -> (R, bc)
    return jnp.transpose(out, (2, 1, 0, 3)).reshape(R, bc)


def _check_metrics(metrics, size):
    if not isinstance(metrics, Mapping) or not metrics:
        raise InputError("metrics must be a non-empty mapping name -> (kind, C).")
    names, kinds, mats = [], [], []
    for name, spec in metrics.items():
        if not (isinstance(spec, tuple) and len(spec) == 2 and spec[0] in METRIC_KINDS):
            raise InputError(
                f"metrics[{name!r}] must be a tuple (kind, C) with kind in {METRIC_KINDS}; got {spec!r}."
            )
        kind, C = spec
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


def _step_size(ts):
    ts = as_float_array("ts", ts, ndim=1)
    T = ts.shape[0]
    if T < 2:
        raise ShapeError("ts", "(T,) with T >= 2", tuple(ts.shape), "ts[0] is the initial time.")
    if is_concrete(ts):
        t = np.asarray(ts)
        h = (t[-1] - t[0]) / (T - 1)
        dev = np.max(np.abs(t - (t[0] + np.arange(T) * h))) / h if h > 0 else np.inf
        if not dev <= UNIFORM_GRID_RTOL:
            raise InputError(
                "simulate_lti_batch steps on a uniform increasing grid; ts is not one "
                f"(max |ts_k − (t0 + k h)| / h = {dev:.2e} > {UNIFORM_GRID_RTOL:.0e}, h = {h:g}). "
                "Use ts = jnp.linspace(t0, t1, T)."
            )
        return T, jnp.asarray(h, dtype=ts.dtype), ts
    h = (ts[-1] - ts[0]) / (T - 1)
    k = jnp.arange(T, dtype=ts.dtype)
    dev = jnp.max(jnp.abs(ts - (ts[0] + k * h))) / h
    h = eqx.error_if(
        h,
        ~(dev <= UNIFORM_GRID_RTOL),
        "simulate_lti_batch needs a uniform grid ts (runtime check).",
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


@eqx.filter_jit
def _first_sample(model, p0, x00):
    """Sample 0, compiled once per structure (done eagerly, this host preparation cost
    ~0.1 s per call): ``E``, ``A``, the SVD split of ``E`` and the full-size output map
    of the joint state."""
    plant, observers = _as_model_output(model(p0))
    split = svd_split(plant.E)
    _, _, out_map, _ = _joint_system(plant, observers, x00, split, None)
    sizes = (plant.n,) + tuple(o.state_size for o in observers)  # static (Python ints)
    return plant.E, lti_matrices(plant)[0], split, out_map, sizes


@eqx.filter_jit
def _same_E(model, params, E0):
    """Whether every sample of ``params`` (leading batch axis) has ``E == E0``."""
    Es = jax.vmap(lambda p: _as_model_output(model(p))[0].E)(params)
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
    - ``"iae_l1"``: $\int \|o\|_1\,\mathrm dt$ → ``(B,)``;
    - ``"ise_l2"``: $\int \|o\|_2^2\,\mathrm dt$ → ``(B,)``.

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
    - `metrics`: mapping ``name -> (kind, C)``, ``kind`` in ``METRIC_KINDS``, ``C`` of
      shape ``(k, n + Σ observer sizes)`` (or ``(n + Σ,)``).
    - `chunk_size`: samples per compiled call (default 4096).
    - `block`: samples stepped together in one time loop (default 256): ``Φ`` and the
      output maps of a block, ``8 (N² + k N) · block`` bytes, should fit in the CPU's
      L2 cache. (Unrolling the time loop was measured slower.)
    - `devices`: the devices to spread the blocks over (default `jax.local_devices()`).

    **Returns:** a dict ``name -> (B,)`` or ``(B, k)`` array (float64).

    **Raises:** `fojax.InputError` (non-LTI model, unknown metric kind, non-uniform
    grid, bad sizes), `fojax.ShapeError`; index-1 checks run on the host for the first
    sample when the inputs are concrete. Samples whose plant is impulsive give non-finite
    metrics. Not differentiable in reverse mode (the block loop has a data-dependent
    trip count); use `fojax.simulate` under `jax.grad`.
    """
    leaves = jax.tree.leaves(params)
    if not leaves:
        raise InputError("params must contain at least one array with a leading batch axis.")
    x0 = as_float_array("x0", x0, ndim=2)
    Bn = x0.shape[0]
    for leaf in leaves:
        if jnp.ndim(leaf) < 1 or jnp.shape(leaf)[0] != Bn:
            raise ShapeError(
                "params leaves", f"leading batch axis {Bn} (= x0.shape[0])", tuple(jnp.shape(leaf))
            )
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
        plant0, observers0 = _as_model_output(model(first))
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
    block = min(block, -(-min(chunk_size, Bn) // D))  # tiny batches: no block of mostly padding
    unit = block * D
    bc = -(-chunk_size // unit) * unit
    R = sum(1 if kd in ("iae_l1", "ise_l2") else k for kd, k in kinds)
    layout = (T, kinds, block, r, R)

    n_chunks = -(-Bn // bc)
    pad = n_chunks * bc - Bn
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
    if n_chunks == 1:
        out = _chunk_core(model, params, x0, jnp.asarray(nreal[0]), h, Cstack, layout, split, Nc, mesh)
    elif chunks is not None and is_concrete(h, Cstack):
        outs = [
            _chunk_core(model, pc, xc, jnp.asarray(nreal[i]), h, Cstack, layout, split, Nc, mesh)
            for i, (pc, xc) in enumerate(chunks)
        ]
        out = jnp.concatenate(outs, axis=1)
    else:
        resh = lambda a: a.reshape((n_chunks, bc) + a.shape[1:])  # noqa: E731
        res = lax.map(
            lambda px: _chunk_core(model, px[0], px[1], px[2], h, Cstack, layout, split, Nc, mesh),
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
