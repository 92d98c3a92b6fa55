r"""The matrix exponentials of fojax, in one place.

Every kernel here is plain XLA (matrix products and loops, no LAPACK custom call), so it
jits, vmaps and differentiates like any other array code and cannot deadlock the CPU
thread pool under `jax.vmap` (see `fojax._small_linalg`).

- `expm_last(M)`: a batch stored batch-last, ``(N, N, b)``: degree-18 Taylor polynomial
  (Paterson–Stockmeyer), per-sample scaling and squaring; with ``max_squarings`` a
  hand-written reverse mode (`_expm_last_diff`). The products are `mm_last`; the
  batch-last time step of the kernels is `matvec_last`. Also the stacks ``(..., n, n)``
  of one-off exponentials (`expm_stack`, e.g. the φ-functions of the exponential
  integrator).
- `expm_first(M)`: a batch stored batch-first, ``(b, N, N)`` (batched GEMMs, for large
  ``N``), full or block lower-triangular; degree-15 Taylor polynomial.
- `expm_small(A)`: one small matrix, degree-13 Padé approximant (forward and reverse
  differentiable without a custom rule; the single-simulation `fojax.simulate`).

All agree with `scipy.linalg.expm` to rounding (``tests/test_expm.py``).
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
from jax import lax

from .._small_linalg import solve_small


#: Squarings of the reverse-differentiable `expm_last` (``‖h A‖₁ ≤ 2^24`` per sample;
#: larger gives NaN, never a silently wrong result).
DIFF_MAX_SQUARINGS = 24


def matvec_last(M, v):
    """``Σ_j M[:, j, :] * v[j, :]`` written as elementwise FMAs over the batch axis.

    Unrolled over ``j`` on purpose: ``N`` (not ``N²``) operations on ``(N, b)`` arrays, so
    the graph grows only linearly with ``N``; as a time step it is faster than a
    `jax.lax.fori_loop`, ``jnp.sum(M * v, axis=1)`` or an einsum over the batch axis."""
    acc = M[:, 0, :] * v[0][None, :]
    for j in range(1, v.shape[0]):
        acc = acc + M[:, j, :] * v[j][None, :]
    return acc


#: Taylor degree and scaling threshold of `expm_last`: for ‖X‖₁ ≤ θ the remainder of the
#: degree-m Taylor polynomial is ≤ θ^(m+1)/(m+1)! · e^θ ≈ 2e-17 (θ = 1, m = 18).
_TAYLOR_DEGREE, _TAYLOR_THETA, _PS_BLOCK = 18, 1.0, 4


#: `mm_last` by inner size ``K``: unrolled column FMAs for ``K ≤ _MM_UNROLL_MAX``, a
#: `jax.lax.fori_loop` of rank-1 updates for ``K ≤ _MM_LOOP_MAX``, the batched einsum
#: above. The unrolled graph has ``N²`` FMAs per product (its compile time grows with
#: ``N²``, so it is kept to tiny sizes, where it runs fastest); the loop's and the
#: einsum's graphs do not grow, the loop being the faster of the two for small ``K``.
_MM_UNROLL_MAX = 4
_MM_LOOP_MAX = 11


def mm_last(A, B):
    """Batch-last matrix product ``(N, K, b) × (K, M, b) → (N, M, b)``.

    For tiny matrices (``K, M ≤ _MM_UNROLL_MAX``): column by column as fused
    multiply–adds over the batch axis, fenced with `jax.lax.optimization_barrier`
    (without the fence XLA fuses each product into its consumers and recomputes it per
    use). Up to ``_MM_LOOP_MAX``: the same FMAs as ``K`` rank-1 updates
    ``A[:, j] ⊗ B[j]`` in a `jax.lax.fori_loop` (a graph of constant size). Larger:
    the batched ``einsum`` (a dot with ``b`` small matrices, slower per product for
    small ``K`` but fastest above). See `_MM_LOOP_MAX`.
    """
    K = max(A.shape[1], B.shape[1])
    if K > _MM_LOOP_MAX:
        return jnp.einsum("ijb,jkb->ikb", A, B)
    if K > _MM_UNROLL_MAX:
        def rank1(j, acc):
            a = lax.dynamic_index_in_dim(A, j, 1, keepdims=False)  # (N, b)
            bj = lax.dynamic_index_in_dim(B, j, 0, keepdims=False)  # (M, b)
            return acc + a[:, None, :] * bj[None, :, :]

        return lax.fori_loop(0, A.shape[1], rank1, jnp.zeros((A.shape[0], B.shape[1], A.shape[2]), A.dtype))
    cols = []
    for k in range(B.shape[1]):
        acc = A[:, 0, :] * B[0, k][None, :]
        for j in range(1, A.shape[1]):
            acc = acc + A[:, j, :] * B[j, k][None, :]
        cols.append(acc)
    return lax.optimization_barrier(jnp.stack(cols, axis=1))


def _expm_parts(M):
    """The scaled Taylor part of `expm_last`: ``(s, X, powers, horner, E)`` with ``powers``
    ``[I, X, X², X³, X⁴]``, ``horner`` the Horner intermediates (the factor multiplied by
    ``X⁴`` at each Horner step) and ``E`` the polynomial before squaring."""
    N = M.shape[0]
    s = _squarings(jnp.max(jnp.sum(jnp.abs(M), axis=0), axis=0), _TAYLOR_THETA)  # (b,)
    X = M * jnp.exp2(-s.astype(M.dtype))[None, None, :]
    powers = [jnp.broadcast_to(jnp.eye(N, dtype=M.dtype)[:, :, None], M.shape), X]
    for _ in range(2, _PS_BLOCK + 1):
        powers.append(mm_last(powers[-1], X))
    nblk = _TAYLOR_DEGREE // _PS_BLOCK + 1
    E = _taylor_chunk(powers, nblk - 1)
    horner = []
    for j in range(nblk - 2, -1, -1):
        horner.append(E)
        E = mm_last(E, powers[_PS_BLOCK]) + _taylor_chunk(powers, j)
    return s, X, powers, horner, E


def _squarings(norm, theta: float):
    """Per-sample squaring counts ``s = max(0, ⌈log₂(‖M‖₁ / θ)⌉)`` (int32) from the induced
    1-norms: after scaling by ``2^-s`` every matrix has ``‖X‖₁ ≤ θ`` (0 for a non-finite norm,
    whose result is then non-finite too)."""
    s = jnp.where(norm > theta, jnp.ceil(jnp.log2(norm / theta)), 0.0)
    return jnp.clip(jnp.where(jnp.isfinite(s), s, 0.0), 0, 1000).astype(jnp.int32)


def _taylor_coefficient(k: int) -> float:
    return 1.0 / math.factorial(k)


def _taylor_chunk(powers, j):
    """``Σ_i c[j·blk + i] X^i`` (the Paterson–Stockmeyer block ``j``)."""
    terms = [_taylor_coefficient(j * _PS_BLOCK + i) * powers[i] for i in range(_PS_BLOCK)
             if j * _PS_BLOCK + i <= _TAYLOR_DEGREE]
    return sum(terms[1:], terms[0])


def expm_last(M, max_squarings: int | None = None):
    r"""Matrix exponentials of a batch stored batch-last: ``M`` ``(N, N, b)`` → ``(N, N, b)``.

    With `max_squarings` (an int) the function is reverse-differentiable (a custom VJP,
    `_expm_last_diff`); samples needing more than `max_squarings` squarings give NaN.

    Scaling and squaring with the degree-18 Taylor polynomial, evaluated by the
    Paterson–Stockmeyer scheme (powers up to $X^4$, then Horner in $X^4$: 7 products
    instead of 17), per sample: $s_k = \max(0, \lceil\log_2\|M_k\|_1\rceil)$ squarings
    (truncation error $\le e/19! \approx 2\cdot 10^{-17}$ relative before squaring). All
    products run over the batch axis (no LAPACK); each sample's result depends only on its
    own matrix, so it does not change with how samples are grouped into blocks. Agrees
    with `scipy.linalg.expm` to rounding (tested).
    """
    if max_squarings is not None:
        return _expm_last_diff(M, int(max_squarings))
    s, _, _, _, E = _expm_parts(M)
    return lax.fori_loop(0, jnp.max(s), _squaring(s), E)


def _squaring(s):
    """The ``i``-th squaring of `expm_last`, applied to the samples with ``i < s``."""

    def square(i, E):
        return jnp.where((i < s)[None, None, :], mm_last(E, E), E)

    return square


def _mm_t(A, B):
    """``A Bᵀ`` batch-last."""
    return mm_last(A, jnp.swapaxes(B, 0, 1))


def _mm_tl(A, B):
    """``Aᵀ B`` batch-last."""
    return mm_last(jnp.swapaxes(A, 0, 1), B)


def _expm_diff_forward(M, max_squarings: int, keep: bool = False):
    """`expm_last` with at most `max_squarings` squarings (NaN beyond); with `keep` also
    ``(s, X, powers, horner, stack, smax)``: the parts of `_expm_parts` and the squarings'
    inputs ``stack`` ``(max_squarings, N, N, b)`` (from index ``smax`` on unused)."""
    s, X, powers, horner, E = _expm_parts(M)
    smax = jnp.minimum(jnp.max(s), max_squarings)
    square = _squaring(s)
    if keep:
        def square_keep(i, c):
            E, stack = c
            return square(i, E), lax.dynamic_update_index_in_dim(stack, E, i, 0)

        stack = jnp.zeros((max(max_squarings, 1),) + E.shape, E.dtype)
        E, stack = lax.fori_loop(0, smax, square_keep, (E, stack))
    else:
        E = lax.fori_loop(0, smax, square, E)
    E = jnp.where((s > max_squarings)[None, None, :], jnp.nan, E)
    return (E, (s, X, powers, horner, stack, smax)) if keep else E


@functools.partial(jax.custom_vjp, nondiff_argnums=(1,))
def _expm_last_diff(M, max_squarings):
    r"""`expm_last` with a fixed squaring budget and a hand-written reverse mode.

    The forward pass is `expm_last`'s (the same products in the same order; the squarings
    in a `jax.lax.fori_loop` up to the block's largest count). The reverse pass recomputes
    it (only `M` is kept) and walks the
    same products backwards, each product $P = AB$ giving $\bar A \mathrel{+}= \bar P B^\top$,
    $\bar B \mathrel{+}= A^\top \bar P$ (batch-last, `mm_last`), through the squarings
    (only where the sample squared: $\bar E_i = \bar E_{i+1}E_i^\top + E_i^\top\bar E_{i+1}$),
    the Horner steps in $X^4$, the powers, and the scaling $\bar M = 2^{-s}\bar X$ ($s$ is
    piecewise constant in $M$, as in `jax.grad` of the plain code). This is exactly the
    derivative `jax.grad` takes of the plain code, without storing every squaring of a
    fixed-length scan or transposing each batch-last product generically. Where a sample needs more than `max_squarings` squarings its value is NaN and its
    cotangent zero (as `jax.grad` of ``jnp.where``). Tested against `jax.grad` of the plain
    code and against SciPy's `expm_frechet`.
    """
    return _expm_diff_forward(M, max_squarings)


def _expm_diff_fwd(M, max_squarings):
    return _expm_diff_forward(M, max_squarings), M


def _expm_diff_bwd(max_squarings, M, Ebar):
    # the parts are recomputed from M (one more forward pass, cheap) instead of saved: as
    # residuals of a `jax.lax.map` over blocks they would be stacked for every block, and
    # writing them costs more than the whole reverse pass
    _, (s, X, powers, horner, stack, smax) = _expm_diff_forward(M, max_squarings, keep=True)
    Ebar = jnp.where((s > max_squarings)[None, None, :], 0.0, Ebar)

    def unsquare(t, Eb):
        i = smax - 1 - t
        Ei = lax.dynamic_index_in_dim(stack, i, 0, keepdims=False)
        return jnp.where((i < s)[None, None, :], _mm_t(Eb, Ei) + _mm_tl(Ei, Eb), Eb)

    Eb = lax.fori_loop(0, smax, unsquare, Ebar)
    nblk = _TAYLOR_DEGREE // _PS_BLOCK + 1
    Pb = [jnp.zeros_like(X) for _ in range(_PS_BLOCK + 1)]

    def chunk_bar(j, Eb):
        for i in range(_PS_BLOCK):
            if j * _PS_BLOCK + i <= _TAYLOR_DEGREE and i > 0:
                Pb[i] = Pb[i] + _taylor_coefficient(j * _PS_BLOCK + i) * Eb

    # forward: E_(j) = E_(j+1) X⁴ + chunk(j), j = nblk-2 .. 0; horner[t] = E_(nblk-1-t)
    for j in range(0, nblk - 1):
        chunk_bar(j, Eb)
        prev = horner[nblk - 2 - j]
        Pb[_PS_BLOCK] = Pb[_PS_BLOCK] + _mm_tl(prev, Eb)
        Eb = _mm_t(Eb, powers[_PS_BLOCK])
    chunk_bar(nblk - 1, Eb)
    for k in range(_PS_BLOCK, 1, -1):  # powers[k] = powers[k-1] X
        Pb[k - 1] = Pb[k - 1] + _mm_t(Pb[k], X)
        Pb[1] = Pb[1] + _mm_tl(powers[k - 1], Pb[k])
    Mbar = Pb[1] * jnp.exp2(-s.astype(X.dtype))[None, None, :]
    return (Mbar,)


_expm_last_diff.defvjp(_expm_diff_fwd, _expm_diff_bwd)


def expm_stack(Z, max_squarings: int = 24):
    """`expm_last` of a stack ``Z`` ``(..., n, n)`` (the batch axes first): one exponential
    per matrix, reverse-differentiable (the custom VJP of `expm_last`); matrices needing
    more than `max_squarings` squarings give NaN."""
    n = Z.shape[-1]
    flat = jnp.moveaxis(Z.reshape((-1, n, n)), 0, -1)
    return jnp.moveaxis(expm_last(flat, max_squarings=max_squarings), -1, 0).reshape(Z.shape)


#: Taylor degree, Paterson–Stockmeyer block and scaling threshold of `expm_first`: for
#: ‖X‖₁ ≤ θ the remainder of the degree-15 Taylor polynomial is
#: ≤ θ¹⁶/16! · e^θ ≈ 2.4e-17 (θ = 0.6); evaluated with 6 products (X², X³, X⁴, then 3
#: Horner steps in X⁴), one fewer than `expm_last`'s degree 18 (θ = 1, 7 products).
_FIRST_DEGREE, _FIRST_BLOCK, _FIRST_THETA = 15, 4, 0.6


# Batch-first matrices of `_multistep_block`, either full (a 1-tuple ``(M,)``) or block
# lower-triangular (``(M11, M21, M22)`` = [[M11, 0], [M21, M22]]: the joint loop with the
# plant first, whose rows do not involve the observers). The same few operations serve both.
def block_mm(P, Q):
    if len(P) == 1:
        return (jnp.matmul(P[0], Q[0]),)
    return (jnp.matmul(P[0], Q[0]), jnp.matmul(P[1], Q[0]) + jnp.matmul(P[2], Q[1]), jnp.matmul(P[2], Q[2]))


def block_row_mm(R, P):
    """Rows times a matrix: ``R`` ``(R,)`` or its column blocks ``(R1, R2)``."""
    if len(P) == 1:
        return (jnp.matmul(R[0], P[0]),)
    return (jnp.matmul(R[0], P[0]) + jnp.matmul(R[1], P[1]), jnp.matmul(R[1], P[2]))


def block_mv(P, w):
    """Matrix times vectors ``(b, N)`` given as ``(w,)`` or ``(w1, w2)``."""
    mv = lambda M, v: jnp.einsum("bij,bj->bi", M, v)  # noqa: E731
    if len(P) == 1:
        return (mv(P[0], w[0]),)
    return (mv(P[0], w[0]), mv(P[1], w[0]) + mv(P[2], w[1]))


def _block_eye(M):
    eye = lambda X: jnp.broadcast_to(jnp.eye(X.shape[-1], dtype=X.dtype), X.shape)  # noqa: E731
    return (eye(M[0]),) if len(M) == 1 else (eye(M[0]), jnp.zeros_like(M[1]), eye(M[2]))


def _block_norm1(M):
    """Induced 1-norm (largest column sum) per sample ``(b,)``."""
    col = lambda X: jnp.max(jnp.sum(jnp.abs(X), axis=1), axis=1)  # noqa: E731
    if len(M) == 1:
        return col(M[0])
    return jnp.maximum(jnp.max(jnp.sum(jnp.abs(M[0]), axis=1) + jnp.sum(jnp.abs(M[1]), axis=1), axis=1), col(M[2]))


def expm_first(M):
    r"""Matrix exponentials of a batch stored batch-first: ``M`` ``(b, N, N)`` → ``(b, N, N)``,
    or a block lower-triangular batch ``(M11, M21, M22)`` → the blocks of its exponential.

    The forward discretisation of `_multistep_block` (large ``N``): scaling and squaring
    of the degree-15 Taylor polynomial (Paterson–Stockmeyer, 6 batched GEMMs
    ``jnp.matmul``), $s_k = \max(0, \lceil\log_2(\|M_k\|_1/0.6)\rceil)$ squarings per
    sample (a loop to the block's largest $s$, each sample squared only ``s_k`` times).
    Truncation ≤ 2.4e-17 relative before squaring. Batch-first products are XLA's
    batched GEMM (faster than `expm_last`'s batch-last einsum for large ``N``), and the
    graph does not grow with ``N``. In block-triangular form a product costs ``(r + q)(r² + q²)`` instead of
    ``(r + q)³`` multiply–adds (about half at ``r = 96``, ``q = 64``), and the zero block
    stays exactly zero. Not reverse-differentiable (data-dependent loop); agrees with
    `scipy.linalg.expm` to rounding (tested).
    """
    full = not isinstance(M, tuple)
    M = (M,) if full else tuple(M)
    s = _squarings(_block_norm1(M), _FIRST_THETA)
    X = tuple(B * jnp.exp2(-s.astype(B.dtype))[:, None, None] for B in M)
    powers = [_block_eye(M), X]
    for _ in range(2, _FIRST_BLOCK + 1):
        powers.append(block_mm(powers[-1], X))
    nblk = _FIRST_DEGREE // _FIRST_BLOCK + 1
    add = lambda P, Q: tuple(a + b for a, b in zip(P, Q))  # noqa: E731

    def chunk(j):  # Σ_i c[j·blk + i] X^i
        terms = [tuple(_taylor_coefficient(j * _FIRST_BLOCK + i) * B for B in powers[i]) for i in range(_FIRST_BLOCK)
                 if j * _FIRST_BLOCK + i <= _FIRST_DEGREE]
        out = terms[0]
        for t in terms[1:]:
            out = add(out, t)
        return out

    E = chunk(nblk - 1)
    for j in range(nblk - 2, -1, -1):
        E = add(block_mm(E, powers[_FIRST_BLOCK]), chunk(j))

    def square(i, E):
        E2 = block_mm(E, E)
        return tuple(jnp.where((i < s)[:, None, None], a, b) for a, b in zip(E2, E))

    E = lax.fori_loop(0, jnp.max(s), square, E)
    return E[0] if full else E


_B13 = (
    64764752532480000.0,
    32382376266240000.0,
    7771770303897600.0,
    1187353796428800.0,
    129060195264000.0,
    10559470521600.0,
    670442572800.0,
    33522128640.0,
    1323241920.0,
    40840800.0,
    960960.0,
    16380.0,
    182.0,
    1.0,
)
_THETA13 = 5.371920351148152


def expm_small(A, max_squarings: int = 24):
    """Matrix exponential of a small square matrix (Padé 13, scaling and squaring).

    The number of squarings ``s = max(0, ceil(log2(‖A‖₁ / θ₁₃)))`` is data-dependent; the
    squarings run in a `lax.scan` of fixed length `max_squarings` (each step squares
    only while ``k < s``), so the function is differentiable in reverse mode and has a
    static shape under `jax.vmap`. Matrices with ``‖A‖₁ > θ₁₃ · 2^max_squarings``
    return NaN (never silently wrong).
    """
    n = A.shape[0]
    if n == 0:
        return A
    norm1 = jnp.max(jnp.sum(jnp.abs(A), axis=0))
    s = jnp.maximum(0.0, jnp.ceil(jnp.log2(jnp.maximum(norm1, 1e-300) / _THETA13)))
    As = A / (2.0**s)
    b = _B13
    eye = jnp.eye(n, dtype=A.dtype)
    A2 = As @ As
    A4 = A2 @ A2
    A6 = A4 @ A2
    U = As @ (A6 @ (b[13] * A6 + b[11] * A4 + b[9] * A2) + b[7] * A6 + b[5] * A4 + b[3] * A2 + b[1] * eye)
    V = A6 @ (b[12] * A6 + b[10] * A4 + b[8] * A2) + b[6] * A6 + b[4] * A4 + b[2] * A2 + b[0] * eye
    R = solve_small(V - U, V + U)

    def square(R, k):
        return jnp.where(k < s, R @ R, R), None

    R, _ = lax.scan(square, R, jnp.arange(max_squarings, dtype=A.dtype))
    return jnp.where(s > max_squarings, jnp.nan, R)
