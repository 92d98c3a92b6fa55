r"""The batch kernel: many LTI plant+observer samples stepped exactly, metrics accumulated
in the time loop.

A Monte Carlo study of a linear time-invariant loop needs per-sample *numbers*
(integrated errors), not trajectories. A batch *problem* (`fojax.studies._exact`) gives
each sample's joint plant+observer system
(`joint_matrices`, the one joint builder); this kernel

1. reduces the joint system to its slow ODE $\dot w = \mathcal A_k w$ in the ``rank E``
   slow SVD coordinates of `fojax.simulation` (the reduction of `fojax.simulate`'s exact
   method) and discretises it exactly, $\Phi_k = e^{\mathcal A_k h}$ (`expm_last` of
   `fojax.simulation._expm`: LAPACK-free, over the samples);
2. when the metric outputs $o = G_k w$ have at most as many independent rows as states,
   changes coordinates to $w' = S_k w$ whose leading entries *are* the outputs, so a time
   step is a single ``N × N`` product per sample (`_output_basis`);
3. steps a block of samples together in one `jax.lax.scan` over the grid, with a layout
   chosen by the joint size ``N``: below ``MULTISTEP_MIN_N`` with the batch as the
   **last** axis (state ``(N, b)``, ``Φ`` ``(N, N, b)``: each step is ``N²`` fused
   multiply–adds over the block, whose data stays in cache); from it on (and without
   jumps) several grid steps per pass from precomputed powers: the outputs
   ``[GΦ; …; GΦ^m] w`` and ``Φ^m w``, batch last up to ``TRIANGULAR_MIN_N``
   (`_multistep_last`: column FMAs over small blocks), batch first from it on
   (`_multistep_block`; ``Φ`` by `expm_first`, block lower-triangular when the problem
   says which states are the plant's; a graph independent of ``N``); the requested
   reductions are accumulated *inside* the loop
   (trapezoid rule), so no ``(B, T, N)`` trajectory is ever stored and memory grows
   linearly with ``B``.

Chunks, padding and devices are the driver's (`fojax.simulation._driver.run_batched`).
"""

from __future__ import annotations

import collections
import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array

from .._small_linalg import solve_small
from ._expm import (
    block_mm,
    block_mv,
    block_row_mm,
    DIFF_MAX_SQUARINGS,
    expm_first,
    expm_last,
    matvec_last,
    mm_last,
)


#: Number of traces of the compiled chunk kernel (tests prove no retrace with it).
TRACE_COUNTS: collections.Counter = collections.Counter()


#: Default number of samples stepped together in one time loop (Φ stays in cache).
DEFAULT_BLOCK = 256


#: Largest accepted ``‖S‖₁‖S⁻¹‖₁`` of the output-coordinate transform (per sample).
OUTPUT_BASIS_MAX_COND = 1e8


class OutputBasis(eqx.Module):
    """The output coordinates of the batch kernel (`_output_basis`, host): ``w' = S w``
    with ``S = [G_ind; Nc]``, whose first ``ρ = len(ind)`` entries are the independent
    metric outputs ``G_ind w`` themselves (`_block_kernel`)."""

    #: rows of the metric map ``G`` that are linearly independent (``ρ`` of them)
    ind: tuple[int, ...] = eqx.field(static=True)
    #: ``(N − ρ, N)`` orthonormal basis of the complement of their span
    Nc: Array
    #: ``(K, N)`` the metric map of the first sample, and its ``S``, ``S⁻¹`` (float64, host)
    G0: Array
    S0: Array
    S0inv: Array


#: `_output_basis`'s results by the bytes of ``G0`` (cleared when it holds 64).
_BASIS_CACHE: dict = {}


def _output_basis(G0: np.ndarray) -> OutputBasis | None:
    """Host: the `OutputBasis` of the metric map ``G0`` (the first sample's), or ``None``.

    ``ind`` selects ``ρ`` linearly independent rows of ``G0`` (pivoted QR of the
    row-normalised ``G0``); ``Nc`` ``(N − ρ, N)`` is an orthonormal basis of the complement
    of their span, so ``S = [D⁻¹ G_ind; Nc]`` (``D`` the rows' norms) is invertible and
    well conditioned. ``None`` when it would be ill-conditioned (``cond₁ > 1e4``). A
    function of the numbers of ``G0``: repeated studies of one loop reuse it."""
    G0 = np.asarray(G0, dtype=float)
    key = (G0.shape, G0.tobytes())
    if key not in _BASIS_CACHE:
        if len(_BASIS_CACHE) >= 64:
            _BASIS_CACHE.clear()
        _BASIS_CACHE[key] = _compute_output_basis(G0)
    return _BASIS_CACHE[key]


def _compute_output_basis(G0: np.ndarray) -> OutputBasis | None:
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
    inv = np.linalg.inv(S0)
    if np.linalg.norm(S0, 1) * np.linalg.norm(inv, 1) > 1e4:  # cond₁
        return None
    scale = np.concatenate([nrm[list(ind), 0], np.ones(N - rho)])
    return OutputBasis(ind, Nc, G0, S0 * scale[:, None], inv / scale[None, :])


def _const_left(C, A):
    """``C A_k`` for a constant ``C`` ``(n, m)`` and a batch ``A`` ``(b, m, k)``: ``m``
    multiply-adds of whole arrays (elementwise over the batch, so a sample's bits do not
    depend on the batch)."""
    C = jnp.asarray(C, A.dtype)
    acc = C[None, :, 0, None] * A[:, 0:1, :]
    for j in range(1, C.shape[1]):
        acc = acc + C[None, :, j, None] * A[:, j : j + 1, :]
    return acc


def _const_right(A, C):
    """``A_k C`` for a batch ``A`` ``(b, n, m)`` and a constant ``C`` ``(m, k)`` (as `_const_left`)."""
    C = jnp.asarray(C, A.dtype)
    acc = A[:, :, 0:1] * C[None, None, 0, :]
    for j in range(1, C.shape[0]):
        acc = acc + A[:, :, j : j + 1] * C[None, None, j, :]
    return acc


def _dependent_rows(ind: tuple[int, ...], K: int) -> tuple[int, ...]:
    """The rows of a ``K``-row metric map outside the independent ones ``ind``."""
    return tuple(i for i in range(K) if i not in ind)


def _output_transform(basis: OutputBasis, G):
    """``(S, S⁻¹, ok)`` of one sample's metric map ``G`` ``(K, N)``: ``S = [G_ind; Nc]``,
    inverted from its row-normalised form (well scaled), ``ok`` false when that form has
    ``cond₁ > OUTPUT_BASIS_MAX_COND``."""
    Gi = G[jnp.array(basis.ind)]
    d = jnp.linalg.norm(Gi, axis=1)
    S = jnp.concatenate([Gi / d[:, None], basis.Nc], axis=0)
    Sinv = solve_small(S, jnp.eye(S.shape[0], dtype=S.dtype))
    cond = jnp.max(jnp.sum(jnp.abs(S), axis=0)) * jnp.max(jnp.sum(jnp.abs(Sinv), axis=0))
    scale = jnp.concatenate([d, jnp.ones((basis.Nc.shape[0],), d.dtype)])
    return S * scale[:, None], Sinv / scale[None, :], cond <= OUTPUT_BASIS_MAX_COND


def repeat_groups(a, reps: int, axis: int):
    """``jnp.repeat(a, reps, axis)`` (each entry along `axis` becomes ``reps`` consecutive
    copies: one group's value for each of its samples) whose reverse pass sums each
    group's ``reps`` cotangents as a chain of additions in sample order, so that the sum
    has the same bits in every program (a ``reduce`` XLA may split or fuse differently in
    one- and many-device programs; see `fojax.studies._sharding.sum_rows`). ``reps = 1``:
    `a` itself."""
    return a if reps == 1 else _repeat_groups(a, reps, axis)


@functools.partial(jax.custom_vjp, nondiff_argnums=(1, 2))
def _repeat_groups(a, reps: int, axis: int):
    return jnp.repeat(a, reps, axis=axis)


def _repeat_fwd(a, reps, axis):
    return _repeat_groups(a, reps, axis), None


def _repeat_bwd(reps, axis, _, ct):
    ct = jnp.moveaxis(ct, axis, 0)
    ct = ct.reshape((ct.shape[0] // reps, reps) + ct.shape[1:])
    acc = ct[:, 0]
    for r in range(1, reps):
        acc = acc + ct[:, r]
    return (jnp.moveaxis(acc, 0, axis),)


_repeat_groups.defvjp(_repeat_fwd, _repeat_bwd)


def _block_kernel(problem, p, h, ts, basis, differentiable: bool = False, time_loop=None, groups=None):
    r"""One block of samples (leading axis ``b`` of every leaf of ``p``): the problem's
    reduction, batch last.

    With a `basis` (`OutputBasis`, from `_output_basis` on the host), each sample's slow
    state is expressed in the coordinates ``w' = S w``, ``S = [G_ind; Nc]``, whose first
    ``ρ`` entries are the independent metric outputs themselves; the other outputs are
    ``(G_dep S⁻¹) w'``. A step is then one ``N × N`` product plus ``(K − ρ) × N`` for the
    dependent outputs, instead of ``N × N + K × N``. ``S⁻¹`` is computed from the
    row-normalised ``[D⁻¹ G_ind; Nc]`` and scaled back; a sample whose normalised matrix
    has ``cond₁ > OUTPUT_BASIS_MAX_COND`` is flagged (``ok`` false). When every sample of
    the block has the first sample's metric map ``G0`` (bit for bit: e.g. an uncertainty
    that leaves the algebraic equations and the outputs alone), the host's ``S`` and
    ``S⁻¹`` of ``G0`` serve the whole block (no per-sample inversion). The outputs reach the
    problem's reduction in the order ``[independent; dependent]`` (a reduction treats
    each output row on its own) and its metrics are put back in the problem's order.

    Jumps of the exogenous state at ``t_j`` (between grid points ``t_{k-1} < t_j ≤ t_k``)
    enter exactly: ``w_k = Φ w_{k-1} + e^{\mathcal A (t_k - t_j)} Δw_j``.

    With `differentiable` `expm_last` gets a squaring budget (``DIFF_MAX_SQUARINGS``) and
    its hand-written reverse mode (`fojax.simulation._expm`), so the whole block is
    reverse-differentiable (``jax.grad``); the time loop is the same `jax.lax.scan`.

    `time_loop` (with ``basis=None``): a replacement of the time loop,
    ``time_loop(problem, Phi, w0, G, jv, kon, ts, reps) -> (acc, w_end)`` (``jv``/``kon``
    ``None`` without jumps), e.g. `fojax.studies._exact._split_loop` (through
    `fojax.studies._adjoint.split_recurrence_reduce`), whose
    custom VJP is the adjoint recurrence; the reduction's `final` is applied here.

    `groups`: ``(p_rep, reps)``, one representative per run of ``reps``
    consecutive samples of ``p`` whose joint matrix, output map and validity are the same
    (a study's scenarios of one uncertainty sample: `fojax.studies._exact.scenario_free`).
    The joint matrix, its exponential and the output map are then formed once per group
    (``b / reps`` columns) and passed so to the time loop, which is called as
    ``time_loop(problem, Phi, w0, G, jv, kon, ts, reps)`` (``reps = 1``: per-sample
    matrices); the initial states and jumps stay per sample. Without a `time_loop` (or
    with kept outputs) ``Phi`` and ``G`` are repeated to the samples before the generic
    loop.
    """
    if not differentiable and time_loop is None:
        # layout by N: several steps per pass as matrix products from MULTISTEP_MIN_N on, the
        # batch-last FMA matvec below (fastest for tiny loops), and for loops with jumps
        shapes = eqx.filter_eval_shape(problem.joint, jax.tree.map(lambda a: a[0], p))
        N = shapes[0].shape[0]
        if shapes[4] is None and MULTISTEP_MIN_N <= N < TRIANGULAR_MIN_N:
            return _multistep_last(problem, p, h, ts)
        if shapes[4] is None and N >= MULTISTEP_MIN_N:
            return _multistep_block(problem, p, h, ts)
    expm = (lambda M: expm_last(M, max_squarings=DIFF_MAX_SQUARINGS)) if differentiable else expm_last  # noqa: E731
    # the unrolled FMA matvec (N column FMAs) is the fastest forward step, but its reverse
    # mode scatters N column cotangents into Φ̄ at every step, about twice as slow as the
    # einsum's, so the differentiable path uses the einsum
    matvec = (lambda M, v: jnp.einsum("ijb,jb->ib", M, v)) if differentiable else matvec_last  # noqa: E731
    T = ts.shape[0]

    reps = 1
    if groups is not None:
        if basis is not None:
            raise ValueError("_block_kernel: groups need basis=None")
        p_rep, reps = groups
        # the representatives' matrices and validity; the samples' initial states and
        # jumps (their joint matrices are unused: removed as dead code)
        Aj, _, G, ok, _ = jax.vmap(problem.joint)(p_rep)
        _, w0, _, _, jumps = jax.vmap(problem.joint)(p)
        ok = jnp.repeat(ok, reps)  # not differentiated
    else:
        Aj, w0, G, ok, jumps = jax.vmap(problem.joint)(p)  # (b,N,N), (b,N), (b,K,N), (b,)
    if basis is not None:
        # the joint system in the output coordinates: with the first sample's transform
        # (the host's S0, S0⁻¹: products with constant matrices) when every sample of the
        # block has its metric map bit for bit, else with each sample's own
        dep = np.array(_dependent_rows(basis.ind, G.shape[1]), dtype=int)
        jd = None if jumps is None else jumps[1]

        def shared(args):
            # products with the constant S0, S0⁻¹ as multiply-adds over the batch axis: each
            # sample's arithmetic does not depend on the block's width
            Aj, w0, G, jd = args
            Aj = _const_right(_const_left(basis.S0, Aj), basis.S0inv)
            return (Aj, _const_right(w0[:, None, :], basis.S0.T)[:, 0], _const_right(G[:, dep], basis.S0inv),
                    None if jd is None else _const_right(jd, basis.S0.T), jnp.ones((Aj.shape[0],), bool))

        def own(args):
            Aj, w0, G, jd = args
            S, Sinv, good = jax.vmap(lambda g: _output_transform(basis, g))(G)
            Aj = jnp.moveaxis(mm_last(mm_last(jnp.moveaxis(S, 0, -1), jnp.moveaxis(Aj, 0, -1)),
                                      jnp.moveaxis(Sinv, 0, -1)), -1, 0)  # S A S⁻¹, batch-last products
            return (Aj, jnp.einsum("bnm,bm->bn", S, w0), jnp.einsum("bkn,bnm->bkm", G[:, dep], Sinv),
                    None if jd is None else jnp.einsum("bjm,bnm->bjn", jd, S), good)

        Aj, w0, G, jd, good = lax.cond(jnp.all(G == basis.G0[None]), shared, own, (Aj, w0, G, jd))
        ok = ok & good  # G: the dependent outputs' rows from here on
        if jumps is not None:
            jumps = (jumps[0], jd)
    Aj = jnp.moveaxis(Aj, 0, -1)  # (N, N, b), or (N, N, b / reps)
    K = G.shape[1] if basis is None else len(basis.ind) + G.shape[1]
    Phi = expm(h * Aj)  # (N, N, b), or (N, N, b / reps)
    grouped_loop = reps > 1 and time_loop is not None and not problem.keep
    if reps > 1 and not grouped_loop:  # the generic loop: every sample's own copy
        Phi, G = repeat_groups(Phi, reps, -1), repeat_groups(G, reps, 0)  # G: (b / reps, K, N) here
    G = jnp.moveaxis(G, 0, -1)  # (K or K-ρ, N, b)
    w0 = w0.T  # (N, b)
    if jumps is not None:
        jt, dW = jumps  # (b, J), (b, J, N)
        b_, J = jt.shape
        kon = jnp.searchsorted(ts, jt, side="left")  # first grid index with t_k ≥ t_j
        valid = (kon >= 1) & (kon <= T - 1) & jnp.isfinite(jt)
        tau = jnp.where(valid, ts[jnp.clip(kon, 0, T - 1)] - jnp.where(valid, jt, 0.0), 0.0)
        Ajb = repeat_groups(jnp.moveaxis(Aj, -1, 0), reps, 0)  # each sample's copy
        Mj = tau[:, :, None, None] * Ajb[:, None]  # (b, J, N, N)
        Psi = expm(jnp.moveaxis(Mj.reshape((b_ * J,) + Aj.shape[:2]), 0, -1))
        jv = matvec(Psi, jnp.moveaxis(dW.reshape(b_ * J, -1), 0, -1))  # (N, b J)
        jv = jnp.moveaxis(jv.reshape(jv.shape[0], b_, J), 2, 0)  # (J, N, b)
        jv = jnp.where(valid.T[:, None, :], jv, 0.0)
        kon = jnp.where(valid, kon, -1).T  # (J, b)
    # with a basis the outputs are computed in the order [independent rows; dependent rows]
    # and reach the reduction so (its rows are independent of each other); the metrics and
    # the kept outputs are put back in the problem's order at the end
    order = None
    if basis is not None:
        ind = basis.ind
        dep = _dependent_rows(ind, K)
        order = np.argsort(np.array(ind + dep))  # o = concat([o_ind, o_dep])[order]
        if np.array_equal(order, np.arange(K)):
            order = None

    def outputs(w):
        if basis is None:
            return matvec(G, w)
        o = w[: len(ind)]
        return jnp.concatenate([o, matvec(G, w)], axis=0) if dep else o

    def reorder(out):  # (metrics (·, K, b), ok) [, kept (T_c, K, b)] in the problem's order
        if order is None:
            return out
        if problem.keep:
            (mets, ok), traj = out
            return (mets[:, order], ok), traj[:, order]
        mets, ok = out
        return mets[:, order], ok

    def step(carry, k):
        w, acc = carry
        w = matvec(Phi, w)
        if jumps is not None:
            for j in range(jv.shape[0]):
                w = w + jnp.where(kon[j] == k, 1.0, 0.0)[None, :] * jv[j]
        o = outputs(w)
        return (w, problem.update(acc, o, k, ts)), (o if problem.keep else None)  # keep: 0 or the stride

    if time_loop is not None and basis is None and not problem.keep:
        r = reps if grouped_loop else 1  # the matrices' columns per sample group as passed
        acc, w_end = time_loop(problem, Phi, w0, G, jv if jumps is not None else None,
                               kon if jumps is not None else None, ts, r)
        G = repeat_groups(G, r, -1)
        return problem.final(acc, matvec(G, w0), matvec(G, w_end), ts, h, ok)
    o0 = outputs(w0)
    stride = int(problem.keep)
    if stride > 1:
        # keep the outputs on every stride-th grid point only (ts[::stride]): an outer scan
        # over the kept points, each an inner scan of `stride` steps, then the remaining
        # (T - 1) mod stride steps unsaved
        n_kept, rest = divmod(T - 1, stride)

        def coarse(carry, c):
            carry, os = lax.scan(step, carry, 1 + c * stride + jnp.arange(stride))
            return carry, os[-1]

        carry, traj = lax.scan(coarse, (w0, problem.init(o0)), jnp.arange(n_kept))
        if rest:
            carry, _ = lax.scan(step, carry, 1 + n_kept * stride + jnp.arange(rest))
        w_end, acc = carry
    else:
        (w_end, acc), traj = lax.scan(step, (w0, problem.init(o0)), jnp.arange(1, T))
    out = problem.final(acc, o0, outputs(w_end), ts, h, ok)
    if stride:
        out = (out, jnp.concatenate([o0[None], traj], axis=0))  # (T_c, K, b), T_c = ceil(T / stride)
    return reorder(out)


#: Grid steps per pass of `_multistep_block` (rounded up to a multiple of the bands' stride).
MULTISTEP = 16
#: Smallest joint size ``N`` stepped by `_multistep_block`: below it the batch-last matvec
#: of one step per pass is faster, above it the matrix products of 16 steps per pass.
MULTISTEP_MIN_N = 10


#: Smallest joint size ``N`` stepped by `_multistep_block` (batch first), which steps it in
#: block lower-triangular form (plant first, `StudyProblem.plant_first`); below it three
#: small GEMMs per product cost more than one full one, and the batch-last passes of
#: `_multistep_last` are faster than both (the default §3.3.7 study, ``N = 22``: about half
#: the time of the batch-first passes).
TRIANGULAR_MIN_N = 32


#: Bytes of one block's ``Φ^m`` (``8 N² b``) that `block_for` aims at: small enough to
#: stay in the CPU's cache while the block is stepped.
BLOCK_BYTES = 2**21


#: Bytes of one block's ``Φ`` (``8 N² b``) that `block_for` aims at from ``MULTISTEP_MIN_N``
#: up to ``TRIANGULAR_MIN_N`` (`_multistep_last`, whose stacked output rows are a few times
#: ``Φ``): about twice the L1 data cache of one core.
STEP_BLOCK_BYTES = 2**16


#: Bytes of one block's ``Φ`` and state (``8 b (N² + 2N)``) that `block_for` keeps within
#: below ``MULTISTEP_MIN_N``, where the batch-last time loop reads all of ``Φ`` at every step:
#: most of a 48 KiB L1 data cache (the block sweep: ``benchmarks/loop_block.py``).
LOOP_BLOCK_BYTES = 40 * 2**10


def block_for(N: int | None, block: int) -> int:
    """The block size for joint size ``N``: `block`, capped so that a block's ``Φ^m``
    takes at most ``BLOCK_BYTES`` (at least 4 samples) when ``N ≥ TRIANGULAR_MIN_N``
    (`_multistep_block`), so that ``Φ`` takes at most ``STEP_BLOCK_BYTES`` (at least 4
    samples) from ``MULTISTEP_MIN_N`` up to it (`_multistep_last`), and below
    ``MULTISTEP_MIN_N`` so that ``Φ`` and the state take at most ``LOOP_BLOCK_BYTES`` (a
    power of two, at least 64 samples). ``N ≤ 3``: 256; 4, 5: 128; 6 … 9: 64; 10: 81;
    22: 16; 31: 8; 64: 64; 128: 16; 256: 4."""
    if N is None or N < 1:
        return block
    if N < MULTISTEP_MIN_N:
        fit = LOOP_BLOCK_BYTES // (8 * (N * N + 2 * N))
        return max(1, min(block, max(64, 1 << max(0, fit.bit_length() - 1))))
    if N < TRIANGULAR_MIN_N:
        return max(1, min(block, max(4, STEP_BLOCK_BYTES // (8 * N * N))))
    return max(1, min(block, max(4, BLOCK_BYTES // (8 * N * N))))


def _output_rows(Phi, G, m: int, row_mm=block_row_mm, mm=block_mm, axis: int = 1):
    r"""``(R, Φ^m)`` of a batch-first stack ``Φ`` (``(Φ,)`` or its lower-triangular blocks,
    see `expm_first`) and output map ``G`` (``(G,)`` or its column blocks): ``R``
    ``(b, m K, ·)`` holds the rows $G\Phi^j$, ``j = 1 … m`` (block ``j − 1`` of ``K``
    rows is $G\Phi^j$). By doubling: with the rows up to ``j`` and $\Phi^{2^i}$, the
    next ones are ``R Φ^{2^i}`` (a ``(jK × N)(N × N)`` product), then $\Phi^{2^{i+1}}$
    by one squaring; $\Phi^m$ is the product of the squares of ``m``'s binary digits
    (``m`` static: ``⌊log₂ m⌋`` squarings, plus one product per further digit).

    `row_mm`, `mm` and the rows' `axis` give the products and layout: `_multistep_last`
    passes batch-last 1-tuples (`mm_last`, rows on axis 0)."""
    K = G[0].shape[axis]
    R, sq, i = row_mm(G, Phi), [Phi], 0  # sq[i] = Φ^(2^i)
    while R[0].shape[axis] < m * K or (1 << (i + 1)) <= m:
        if R[0].shape[axis] < m * K:
            have = R[0].shape[axis]
            more = row_mm(tuple(lax.slice_in_dim(x, 0, min(m * K - have, have), axis=axis) for x in R), sq[i])
            R = tuple(jnp.concatenate([a, b], axis=axis) for a, b in zip(R, more))
        if (1 << (i + 1)) <= m:
            sq.append(mm(sq[i], sq[i]))
        i += 1
    Pm = None
    for i, P in enumerate(sq):
        if m >> i & 1:
            Pm = P if Pm is None else mm(Pm, P)
    return R, Pm


def _multistep_block(problem, p, h, ts):
    r"""The forward time loop of `_block_kernel` for problems without jumps: ``m`` grid
    steps per pass from precomputed powers, batch first.

    With the state $w_{pm}$ of a sample at the start of pass ``p``, the outputs of the
    next ``m`` steps are $o_{pm+j} = G\Phi^j w_{pm}$ (``j = 1 … m``), i.e. one product
    ``R w`` with the stacked rows ``R = [GΦ; GΦ²; …; GΦ^m]`` ``(m K, N)``, and the state
    moves on by $w_{(p+1)m} = \Phi^m w_{pm}$: per pass ``N² + m K N`` multiply–adds per
    sample instead of ``m (N² + K N)`` (``K``, the metric outputs, is small: a study's
    error signals). ``R`` and ``Φ^m`` come from `_output_rows` (doubling: ``⌊log₂ m⌋``
    squarings and as many ``(jK × N)(N × N)`` products), ``Φ`` from `expm_first`
    (batched GEMMs). All products are batch-first (XLA's batched GEMM); the graph does
    not grow with ``N`` (no loop unrolled over ``N``).

    Each output is $G\Phi^j(\Phi^m)^p w_0$ instead of ``G Φ(…Φ w_0)``: the rounding
    differs by a few ulps of $\|\Phi\|^k$ (tests compare with SciPy at ``1e-8``). The
    outputs are reduced with the problem's `update_block` (vectorised over the ``m``
    steps); with ``problem.keep = k`` the outputs on ``ts[::k]`` are kept (``m`` is a
    multiple of ``k``, so their positions within a pass are static).
    """
    T = ts.shape[0]
    stride = int(problem.keep)
    m = MULTISTEP if stride <= 1 else stride * -(-MULTISTEP // stride)
    Aj, w0, G, ok, _ = jax.vmap(problem.joint)(p)  # (b,N,N), (b,N), (b,K,N), (b,)
    b, K = G.shape[0], G.shape[1]
    o0 = jnp.einsum("bkn,bn->kb", G, w0)
    order = problem.plant_first(Aj.shape[1]) if Aj.shape[1] >= TRIANGULAR_MIN_N else None
    if order is None:
        hA, G, w = (h * Aj,), (G,), (w0,)
    else:  # [plant; observers]: block lower-triangular, the zero block never multiplied
        perm, k = order
        Aj, G, w0 = Aj[:, perm][:, :, perm], G[:, :, perm], w0[:, perm]
        hA = (h * Aj[:, :k, :k], h * Aj[:, k:, :k], h * Aj[:, k:, k:])
        G, w = (G[:, :, :k], G[:, :, k:]), (w0[:, :k], w0[:, k:])
    Phi = expm_first(hA)
    R, Pm = _output_rows(Phi, G, m)  # rows (b, m K, ·), Φ^m

    def outputs(w):  # the outputs of the m steps after w: (b, K, m)
        o = sum(jnp.einsum("brn,bn->br", Ri, wi) for Ri, wi in zip(R, w))
        return jnp.swapaxes(o.reshape(b, m, K), 1, 2)

    w0 = w
    n_pass, rest = divmod(T - 1, m)
    kept = np.flatnonzero((1 + np.arange(m)) % stride == 0) if stride else None

    def body(carry, q):
        w, acc, _ = carry
        O = outputs(w)
        acc = problem.update_block(acc, O, 1 + q * m + jnp.arange(m), ts)
        w = block_mv(Pm, w)
        # the kept outputs turned batch-last here, on the pass's few columns in cache:
        # the stacked (n_pass, len(kept), K, b) is then the bands' layout as it is
        return (w, acc, O[:, :, -1].T), (jnp.transpose(O[:, :, kept], (2, 1, 0)) if stride else None)

    (w, acc, o_end), traj = lax.scan(body, (w0, problem.init(o0), o0), jnp.arange(n_pass))
    parts = [o0[None]]
    if stride:
        parts.append(traj.reshape((-1,) + o0.shape))  # (n_pass · len(kept), K, b)
    if rest:
        O = outputs(w)[:, :, :rest]
        acc = problem.update_block(acc, O, 1 + n_pass * m + jnp.arange(rest), ts)
        o_end = O[:, :, -1].T
        if stride and np.any(kept < rest):
            parts.append(jnp.transpose(O[:, :, kept[kept < rest]], (2, 1, 0)))
    out = problem.final(acc, o0, o_end, ts, h, ok)
    if stride:
        out = (out, jnp.concatenate(parts, axis=0))  # (T_c, K, b), T_c = ceil(T / stride)
    return out




#: Grid steps per pass of `_multistep_last` (rounded up to a multiple of the bands' stride).
MULTISTEP_LAST = 8


def _multistep_last(problem, p, h, ts):
    r"""The forward time loop of `_block_kernel` for problems without jumps and
    ``MULTISTEP_MIN_N ≤ N < TRIANGULAR_MIN_N``: the passes of `_multistep_block`
    (``m = MULTISTEP_LAST`` grid steps per pass, outputs $G\Phi^j w$ from the stacked rows
    ``R = [GΦ; …; GΦ^m]``, then $w \leftarrow \Phi^m w$) with the batch as the **last**
    axis: every product is the column FMAs of `matvec_last` over the block (no batched
    matrix–vector call per sample), ``Φ`` comes from `expm_last`, and each pass's outputs
    ``R w`` are part of the loop's carry, so that they are computed once and read by every
    accumulator (not recomputed inside each consumer). The accumulators take the ``m``
    outputs one step at a time (the problem's `update`, in grid order). The time loop's
    arithmetic is elementwise over the block. The graph grows linearly with ``N`` (``N`` column FMAs per product), hence
    the bound ``TRIANGULAR_MIN_N``. With ``problem.keep = k``, ``m`` is a multiple of
    ``k`` and the outputs on ``ts[::k]`` are kept."""
    T = ts.shape[0]
    stride = int(problem.keep)
    m = MULTISTEP_LAST if stride <= 1 else stride * -(-MULTISTEP_LAST // stride)
    Aj, w0, G, ok, _ = jax.vmap(problem.joint)(p)  # (b,N,N), (b,N), (b,K,N), (b,)
    K = G.shape[1]
    Aj, G, w0 = jnp.moveaxis(Aj, 0, -1), jnp.moveaxis(G, 0, -1), w0.T  # batch last
    last = lambda P, Q: (mm_last(P[0], Q[0]),)  # noqa: E731
    (R,), (Pm,) = _output_rows((expm_last(h * Aj),), (G,), m, row_mm=last, mm=last, axis=0)  # (m K, N, b), (N, N, b)
    o0 = matvec_last(G, w0)
    n_pass, rest = divmod(T - 1, m)
    kept = np.flatnonzero((1 + np.arange(m)) % stride == 0) if stride else None

    def step_rows(O, j):  # the outputs of the pass's j-th step, (K, b)
        return O[j * K : (j + 1) * K]

    def body(carry, q):
        w, O, acc = carry  # O = R w: the outputs of the m steps after w
        for j in range(m):
            acc = problem.update(acc, step_rows(O, j), 1 + q * m + j, ts)
        w = matvec_last(Pm, w)
        kept_o = jnp.stack([step_rows(O, j) for j in kept]) if stride else None
        return (w, matvec_last(R, w), acc), kept_o

    (w, O, acc), traj = lax.scan(body, (w0, matvec_last(R, w0), problem.init(o0)), jnp.arange(n_pass))
    parts = [o0[None]]
    if stride:
        parts.append(traj.reshape((-1,) + o0.shape))  # (n_pass · len(kept), K, b)
    if rest:  # the last rest steps: the first rows of the carried outputs
        for j in range(rest):
            acc = problem.update(acc, step_rows(O, j), 1 + n_pass * m + j, ts)
        o_end = step_rows(O, rest - 1)
        if stride and np.any(kept < rest):
            parts.append(jnp.stack([step_rows(O, j) for j in kept[kept < rest]]))
    else:
        o_end = matvec_last(G, w)
    out = problem.final(acc, o0, o_end, ts, h, ok)
    if stride:
        out = (out, jnp.concatenate(parts, axis=0))  # (T_c, K, b), T_c = ceil(T / stride)
    return out
