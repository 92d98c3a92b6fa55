r"""LAPACK-free linear algebra for the small matrices of batched simulations.

Why: under `jax.vmap`, `jnp.linalg.solve` and `jax.scipy.linalg.expm` lower to batched
LAPACK custom calls (``getrf``) that jaxlib 0.10.2 runs on XLA's CPU thread pool with a
nested parallel batch map. When XLA schedules two such calls at once on a 2-core
machine, both wait for pool threads held by the other and the computation deadlocks
(observed with gdb in the benchmark of issue 7: both threads parked in
``ParallelBatchMap`` / ``lapack_dgetrf_ffi``). The kernels below are plain XLA
operations (loops over the matrix size are `jax.lax.fori_loop`s, unrolled only for
tiny matrices, so the compiled graph does not grow with the size), so they vmap, jit
and differentiate like any other array code, cannot deadlock, and for the sizes fojax
simulates (n ≲ 40) are as fast as LAPACK.

- `solve_small(A, B)`: Gaussian elimination with partial pivoting.
- `expm_small(A)`: scaling and squaring with the degree-13 Padé approximant (Higham
  2005, the same approximant and θ₁₃ = 5.37 as SciPy/JAX, without the branch on the
  norm), the Padé solve done by `solve_small`.
"""

from __future__ import annotations

import jax.numpy as jnp
from jax import lax


#: Largest size for which `solve_small` unrolls the elimination in Python; above it the
#: elimination and back substitution run as `jax.lax.fori_loop`s, whose graph (and so
#: compile time) does not grow with ``n``. Measured under `jax.vmap` over 256 systems
#: with ``n`` right-hand sides (XLA CPU, loaded 2-core machine): compile unrolled
#: 0.34 / 0.88 / 2.8 s at n = 3 / 9 / 22 (reverse mode 0.65 / 2.2 / 7.3 s) against
#: 0.3–0.45 s for the loop at every n (reverse mode 0.8–1.2 s); run time equal within
#: ±30 % from n = 6 on, the unrolled form 2× faster only at n ≤ 3.
SOLVE_UNROLL_MAX = 4


def solve_small(A, B):
    """Solve ``A X = B`` for a small square ``A`` (``(n, n)``) and ``B`` (``(n,)`` or ``(n, k)``).

    Gaussian elimination with partial pivoting: statically unrolled for
    ``n ≤ SOLVE_UNROLL_MAX``, otherwise two `jax.lax.fori_loop`s (elimination, back
    substitution) so that the compile time does not grow with ``n``. Both forms are
    differentiable in forward and reverse mode and vmap."""
    vec = B.ndim == 1
    if vec:
        B = B[:, None]
    n = A.shape[0]
    if n == 0:
        return B[:, 0] if vec else B
    X = _solve_unrolled(A, B) if n <= SOLVE_UNROLL_MAX else _solve_loop(A, B)
    return X[:, 0] if vec else X


def _solve_unrolled(A, B):
    n = A.shape[0]
    M = jnp.concatenate([A, B], axis=1)
    rows = jnp.arange(n)
    for i in range(n):
        col = jnp.where(rows >= i, jnp.abs(M[:, i]), -1.0)
        p = jnp.argmax(col)
        ri, rp = M[i], M[p]
        M = M.at[i].set(rp).at[p].set(ri)
        factors = jnp.where(rows > i, M[:, i] / M[i, i], 0.0)
        M = M - factors[:, None] * M[i][None, :]
    U, X = M[:, :n], M[:, n:]
    for i in reversed(range(n)):
        xi = (X[i] - U[i, i + 1 :] @ X[i + 1 :]) / U[i, i]
        X = X.at[i].set(xi)
    return X


def _solve_loop(A, B):
    n = A.shape[0]
    M = jnp.concatenate([A, B], axis=1)
    rows = jnp.arange(n)
    row = lambda a, i: lax.dynamic_index_in_dim(a, i, 0, keepdims=False)  # noqa: E731

    def eliminate(i, M):
        col = lax.dynamic_index_in_dim(M, i, 1, keepdims=False)
        p = jnp.argmax(jnp.where(rows >= i, jnp.abs(col), -1.0))
        ri, rp = row(M, i), row(M, p)
        M = lax.dynamic_update_index_in_dim(M, ri, p, 0)  # swap rows i and p
        M = lax.dynamic_update_index_in_dim(M, rp, i, 0)
        pivot = lax.dynamic_index_in_dim(rp, i, 0, keepdims=False)
        factors = jnp.where(rows > i, lax.dynamic_index_in_dim(M, i, 1, keepdims=False) / pivot, 0.0)
        return M - factors[:, None] * rp[None, :]

    M = lax.fori_loop(0, n, eliminate, M)
    U, X = M[:, :n], M[:, n:]

    def substitute(k, X):
        i = n - 1 - k
        ui = row(U, i)
        xi = (row(X, i) - jnp.where(rows > i, ui, 0.0) @ X) / lax.dynamic_index_in_dim(ui, i, 0, keepdims=False)
        return lax.dynamic_update_index_in_dim(X, xi, i, 0)

    return lax.fori_loop(0, n, substitute, X)


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
