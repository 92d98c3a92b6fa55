"""LAPACK-free kernels used in the batched simulation hot path (see fojax/_small_linalg.py)."""

import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg
from helpers import count_equations

from fojax._small_linalg import expm_small, solve_small, SOLVE_UNROLL_MAX


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


def test_expm_small_matches_scipy_over_scales(rng):
    for scale in (1e-3, 0.3, 4.0, 60.0, 400.0):
        A = scale * rng.normal(size=(6, 6)) / 6
        E = np.asarray(jax.jit(expm_small)(jnp.asarray(A)))
        ref = scipy.linalg.expm(A)
        assert np.linalg.norm(E - ref) <= 1e-12 * max(1.0, np.linalg.norm(ref)) * max(1.0, scale)
    # a stiff, non-normal matrix like the thesis loops (poles near -275, gains in the thousands)
    A = np.array([[-275.0, 3000.0], [0.0, -2.0]]) * 0.01
    np.testing.assert_allclose(np.asarray(expm_small(jnp.asarray(A))), scipy.linalg.expm(A), rtol=1e-12)


def test_batched_grad_and_vmap(rng):
    As = jnp.asarray(rng.normal(size=(64, 5, 5)))
    Es = jax.vmap(expm_small)(As)
    for k in (0, 17, 63):
        np.testing.assert_allclose(np.asarray(Es[k]), scipy.linalg.expm(np.asarray(As[k])), rtol=1e-11, atol=1e-13)

    def f(a):
        return jnp.sum(expm_small(a * jnp.asarray(np.asarray(As[0]))))

    g = jax.grad(f)(1.0)
    fd = (f(1.0 + 1e-6) - f(1.0 - 1e-6)) / 2e-6
    assert np.isclose(float(g), float(fd), rtol=1e-6)


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
