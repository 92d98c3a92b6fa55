"""The matrix exponentials of `fojax.simulation._expm` (batch-last, batch-first, stacks, one small
matrix) and the reverse mode of the batch-last one.

Oracle: `scipy.linalg.expm` (values) and `scipy.linalg.expm_frechet` (derivatives), per matrix;
central finite differences for the Padé form's gradient.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
from helpers import count_equations

# private: the matrix exponentials are tested themselves
from fojax.simulation._expm import expm_small, expm_stack


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


@pytest.mark.parametrize("size", [3, 6, 14])  # unrolled column FMAs, fori_loop rank-1 updates, einsum
def test_expm_last_matches_scipy(rng, size):
    # private: tested itself
    from fojax.simulation._expm import _MM_LOOP_MAX, _MM_UNROLL_MAX, expm_last

    assert [size <= _MM_UNROLL_MAX, _MM_UNROLL_MAX < size <= _MM_LOOP_MAX, size > _MM_LOOP_MAX].count(True) == 1
    # norms from 1e-3 to 40: 0 ... 7 squarings; non-normal matrices
    Ms = [s * rng.standard_normal((size, size)) + np.triu(5 * s * rng.standard_normal((size, size)), 1)
          for s in (1e-3, 0.1, 1.0, 3.0, 8.0)]
    Ms.append(np.zeros((size, size)))
    got = np.asarray(expm_last(jnp.asarray(np.stack(Ms, axis=-1))))
    for k, M in enumerate(Ms):
        ref = scipy.linalg.expm(M)
        assert np.max(np.abs(got[:, :, k] - ref)) <= 1e-13 * max(1.0, np.max(np.abs(ref)))
    # the reverse-differentiable form (fixed-length squaring scan; study_loss uses it): the
    # same values, NaN beyond max_squarings, and d/da Σ expm(a M) = Σ M expm(a M) at a = 1
    fixed = np.asarray(expm_last(jnp.asarray(np.stack(Ms, axis=-1)), max_squarings=24))
    np.testing.assert_array_equal(fixed, got)
    assert np.all(np.isnan(np.asarray(expm_last(jnp.asarray(Ms[-2])[..., None] * 1e3, max_squarings=3))))
    M = jnp.asarray(np.stack(Ms[2:4], axis=-1))
    g = jax.grad(lambda a: jnp.sum(expm_last(a * M, max_squarings=24)))(1.0)
    want = sum(np.sum(Mk @ scipy.linalg.expm(Mk)) for Mk in Ms[2:4])
    assert np.isclose(float(g), want, rtol=1e-11)


@pytest.mark.parametrize("size", [3, 14])  # unrolled column FMAs, einsum (the compile of each costs ~5 s)
def test_expm_last_reverse_mode_matches_scipy_frechet(rng, size):
    # The hand-written VJP of the differentiable `expm_last`. Oracle: SciPy's Fréchet derivative,
    # d/dM <C, expm(M)> = L(Mᵀ, C) (scipy.linalg.expm_frechet), per sample, with 0 ... 7
    # squarings in one block (each sample squares only as often as its own norm asks); a
    # sample beyond max_squarings is NaN with a zero cotangent, and its neighbours are exact.
    # private: tested itself
    from fojax.simulation._expm import expm_last

    Ms = [s * rng.standard_normal((size, size)) + np.triu(5 * s * rng.standard_normal((size, size)), 1)
          for s in (1e-3, 0.1, 1.0, 3.0, 8.0)]
    Ms.append(np.zeros((size, size)))
    Ms.append(1e6 * rng.standard_normal((size, size)))  # beyond max_squarings = 12
    Cs = rng.standard_normal((len(Ms), size, size))
    M, C = jnp.asarray(np.stack(Ms, axis=-1)), jnp.asarray(np.moveaxis(Cs, 0, -1))

    def loss(M):
        return jnp.sum(jnp.where(jnp.isnan(E := expm_last(M, max_squarings=12)), 0.0, E * C))

    g = np.asarray(jax.jit(jax.grad(loss))(M))
    for k, Mk in enumerate(Ms[:-1]):
        want = scipy.linalg.expm_frechet(Mk.T, Cs[k], compute_expm=False)
        assert np.max(np.abs(g[:, :, k] - want)) <= 1e-12 * max(1.0, np.max(np.abs(want))), k
    assert np.all(g[:, :, -1] == 0.0)
    assert np.all(np.isnan(np.asarray(expm_last(M, max_squarings=12))[:, :, -1]))
    if size == 3:
        return
    # the same numbers under jax.vmap of the gradient (two batches of the same samples)
    gv = np.asarray(jax.vmap(jax.grad(loss))(jnp.stack([M, M])))
    np.testing.assert_allclose(gv[1], g, rtol=1e-14, atol=1e-14 * np.max(np.abs(g[:, :, :-1])))


def test_expm_first_matches_scipy_full_and_block_triangular(rng):
    # `expm_first` (batch-first degree-15 Taylor, the discretisation of
    # `_multistep_block`), full and in block lower-triangular form [[M11, 0], [M21, M22]].
    # Oracle: scipy.linalg.expm of the full matrices. Norms 1e-3 ... 8: 0 ... 4 squarings.
    # private: tested itself
    from fojax.simulation._expm import expm_first

    k, q = 5, 3
    Ms = []
    for s in (1e-3, 0.1, 0.5, 3.0, 8.0):
        M = s * rng.standard_normal((k + q, k + q)) + np.tril(3 * s * rng.standard_normal((k + q, k + q)), -1)
        M[:k, k:] = 0.0
        Ms.append(M)
    Ms.append(np.zeros((k + q, k + q)))
    Ms = np.stack(Ms)
    full = np.asarray(expm_first(jnp.asarray(Ms)))
    E11, E21, E22 = (np.asarray(a) for a in expm_first((jnp.asarray(Ms[:, :k, :k]), jnp.asarray(Ms[:, k:, :k]),
                                                         jnp.asarray(Ms[:, k:, k:]))))
    for j, M in enumerate(Ms):
        ref = scipy.linalg.expm(M)
        # 1e-12 of the largest entry: up to 9 squarings of non-normal matrices (‖M‖₁ ~ 190) amplify
        # both methods' rounding (measured ≤ 2.3e-13 here; expm_last's error on the same matrices is alike)
        tol = 1e-12 * max(1.0, np.max(np.abs(ref)))
        assert np.max(np.abs(full[j] - ref)) <= tol
        assert np.max(np.abs(E11[j] - ref[:k, :k])) <= tol and np.max(np.abs(E22[j] - ref[k:, k:])) <= tol
        assert np.max(np.abs(E21[j] - ref[k:, :k])) <= tol


def test_expm_last_graph_does_not_grow_with_n():
    # The fori_loop and einsum forms of the batch-last products have a graph of the same
    # size for every N in their range (the compile does not grow with N).
    # private: tested itself
    from fojax.simulation._expm import _MM_LOOP_MAX, _MM_UNROLL_MAX, expm_last

    def count(N):
        return count_equations(expm_last, jnp.zeros((N, N, 3)))

    assert len({count(N) for N in (_MM_UNROLL_MAX + 1, 8, _MM_LOOP_MAX)}) == 1
    assert len({count(N) for N in (_MM_LOOP_MAX + 1, 22, 40)}) == 1


def test_expm_stack_matches_scipy_and_frechet(rng):
    # A stack (2, 3, n, n) of one-off exponentials (the φ-function augmented matrices of the
    # exponential integrator are such stacks): values, then the reverse mode of Σ <C, expm(Z)>.
    n = 7
    Z = np.stack([s * rng.standard_normal((3, n, n)) for s in (0.05, 2.0)])
    Z[1, 2] += np.triu(20.0 * rng.standard_normal((n, n)), 1)  # non-normal, several squarings
    C = rng.standard_normal(Z.shape)
    got = np.asarray(jax.jit(expm_stack)(jnp.asarray(Z)))
    g = np.asarray(jax.grad(lambda z: jnp.sum(expm_stack(z) * jnp.asarray(C)))(jnp.asarray(Z)))
    for idx in np.ndindex(Z.shape[:2]):
        ref = scipy.linalg.expm(Z[idx])
        assert np.max(np.abs(got[idx] - ref)) <= 1e-13 * max(1.0, np.max(np.abs(ref))), idx
        want = scipy.linalg.expm_frechet(Z[idx].T, C[idx], compute_expm=False)
        assert np.max(np.abs(g[idx] - want)) <= 1e-12 * max(1.0, np.max(np.abs(want))), idx
