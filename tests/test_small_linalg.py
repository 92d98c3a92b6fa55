"""`fojax._small_linalg.solve_small`, the LAPACK-free solve of the batched kernels.

Oracle: `numpy.linalg.solve` and the closed-form derivative of ``A⁻¹ b``.
"""

import jax
import jax.numpy as jnp
import numpy as np
from helpers import count_equations

# private: tested itself
from fojax._small_linalg import solve_small, SOLVE_UNROLL_MAX


def test_solve_small_matches_numpy_including_pivoting(rng):
    for n in (1, 2, 5, 9):
        A = rng.normal(size=(n, n))
        if n > 1:
            A[0, 0] = 0.0  # forces a row exchange
        B = rng.normal(size=(n, 3))
        X = np.asarray(jax.jit(solve_small)(jnp.asarray(A), jnp.asarray(B)))
        np.testing.assert_allclose(X, np.linalg.solve(A, B), rtol=1e-10, atol=1e-12)
    v = rng.normal(size=4)
    A = rng.normal(size=(4, 4))
    np.testing.assert_allclose(np.asarray(solve_small(jnp.asarray(A), jnp.asarray(v))),
                               np.linalg.solve(A, v), rtol=1e-10)


def test_solve_small_graph_does_not_grow_with_n(rng):
    # Issue 13: the elimination unrolled in Python made the graph (and the XLA compile,
    # 9 s for the 22-state study loop under vmap) grow with n. Above SOLVE_UNROLL_MAX it
    # is a fori_loop: the same number of equations for every n, results still LAPACK's.
    sizes = (SOLVE_UNROLL_MAX + 1, 12, 30)
    counts = {n: count_equations(solve_small, jnp.eye(n), jnp.ones((n, n))) for n in sizes}
    assert len(set(counts.values())) == 1, counts
    for n in (7, 30):
        A = rng.normal(size=(n, n))
        A[0, 0] = 0.0  # forces a row exchange
        B = rng.normal(size=(n, 2))
        np.testing.assert_allclose(np.asarray(jax.jit(solve_small)(jnp.asarray(A), jnp.asarray(B))),
                                   np.linalg.solve(A, B), rtol=1e-9, atol=1e-11)
    # reverse mode through the loop: d/dA sum(A⁻¹ b) = -A⁻ᵀ 1 xᵀ
    A, b = rng.normal(size=(7, 7)) + 7 * np.eye(7), rng.normal(size=7)
    g = np.asarray(jax.grad(lambda a: jnp.sum(solve_small(a, jnp.asarray(b))))(jnp.asarray(A)))
    x = np.linalg.solve(A, b)
    np.testing.assert_allclose(g, -np.outer(np.linalg.solve(A.T, np.ones(7)), x), rtol=1e-10, atol=1e-12)
