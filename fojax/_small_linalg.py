r"""LAPACK-free linear solves for the small matrices of batched simulations.

Under `jax.vmap`, `jnp.linalg.solve` and `jax.scipy.linalg.expm` lower to batched LAPACK
custom calls (``getrf``) that jaxlib runs on XLA's CPU thread pool with a nested parallel
batch map; two such calls scheduled at once on a small machine can each wait for pool
threads held by the other and deadlock. The kernel below is plain XLA (loops over the
matrix size are `jax.lax.fori_loop`s, unrolled only for tiny matrices, so the compiled
graph does not grow with the size): it vmaps, jits and differentiates like any other
array code, cannot deadlock, and for the sizes fojax simulates (n ≲ 40) is as fast as
LAPACK.

- `solve_small(A, B)`: Gaussian elimination with partial pivoting.

The matrix exponentials built on it live in `fojax.simulation._expm`.
"""

from __future__ import annotations

import jax.numpy as jnp
from jax import lax


#: Largest size for which `solve_small` unrolls the elimination in Python; above it the
#: elimination and back substitution run as `jax.lax.fori_loop`s, whose graph (and so
#: compile time) does not grow with ``n``. The unrolled form compiles in time growing
#: with ``n²`` and runs faster only for the tiniest systems; from a handful of unknowns
#: on both run equally fast and the loop compiles much sooner.
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
