"""Explicit gain parameterizations: every parameter value gives a certified observer."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fojax
from fojax.design import (
    contraction,
    design_functional_observer,
    Disk,
    disk_gain,
    lemma10_gain,
    pieces,
)


@pytest.fixture(scope="module")
def design_data():
    ex = fojax.models.example_4_1_3()
    d = design_functional_observer(ex.system, ex.L, kind="generalized", region=Disk(-2.0, 1.0))
    s = d.structure
    pc = pieces(s, xp=np)
    q0, q1, c = s.q0, s.q1, pc.N3.shape[0]
    Z = d.params["Z"]
    A1 = np.block([[pc.N1[0] - Z @ pc.N2[0], np.zeros((q0, q1))], [np.zeros((q1, q0 + q1))]])
    A2 = np.block([[pc.N3, np.zeros((c, q1))], [np.zeros((q1, q0)), -np.eye(q1)]])
    return d, A1, A2


def test_contraction_is_inside_unit_ball(rng):
    for scale in (0.1, 1.0, 100.0):
        Lc = np.asarray(contraction(jnp.asarray(scale * rng.normal(size=(5, 3)))))
        assert np.linalg.norm(Lc, 2) < 1.0


def test_disk_gain_every_parameter_is_in_the_disk(design_data, rng):
    d, A1, A2 = design_data
    X = d.X
    k = np.linalg.matrix_rank(A2)
    region = Disk(-2.0, 1.0)
    for _ in range(20):
        Lc = contraction(jnp.asarray(3.0 * rng.normal(size=(X.shape[0], k))))
        Yp = jnp.asarray(rng.normal(size=(X.shape[0], A2.shape[0])))
        Y, margin = disk_gain(jnp.asarray(X), jnp.asarray(A1), jnp.asarray(A2), -2.0, 1.0, Lc, Yp, rank=k)
        assert float(margin) > 0
        Aa = A1 - np.asarray(Y) @ A2
        assert region.contains(np.linalg.eigvals(Aa))
        # X certifies it: the region LMI evaluated in float64 is negative definite
        assert np.linalg.eigvalsh(region.lmi_matrix(X, X @ Aa)).max() < 0


def test_disk_gain_reproduces_the_lmi_gain(design_data):
    # The LMI's own gain lies in the parameterized set: choosing Lc from it recovers 𝔸.
    d, A1, A2 = design_data
    Aa_lmi = d.error_matrix
    X = d.X
    k = np.linalg.matrix_rank(A2)
    Lx = np.linalg.cholesky(X)
    LxinvT = np.linalg.inv(Lx.T)
    M = Lx.T @ (Aa_lmi + 2.0 * np.eye(X.shape[0])) @ LxinvT
    U, s, Vt = np.linalg.svd(A2 @ LxinvT)
    Vb, Vp = Vt[:k].T, Vt[k:].T
    M0 = Lx.T @ (A1 + 2.0 * np.eye(X.shape[0])) @ LxinvT
    F = np.linalg.cholesky(np.eye(X.shape[0]) - (M0 @ Vp) @ (M0 @ Vp).T)
    Lc = np.linalg.solve(F, M @ Vb)
    assert np.linalg.norm(Lc, 2) < 1.0
    Y, _ = disk_gain(jnp.asarray(X), jnp.asarray(A1), jnp.asarray(A2), -2.0, 1.0, jnp.asarray(Lc), rank=k)
    assert np.allclose(A1 - np.asarray(Y) @ A2, Aa_lmi, atol=1e-8)


def test_lemma10_gain_is_hurwitz_with_certificate(design_data, rng):
    d, A1, A2 = design_data
    X = d.X
    for gamma in (10.0, 100.0):
        Lc = contraction(jnp.asarray(rng.normal(size=(A2.shape[0], X.shape[0]))))
        Y, margin = lemma10_gain(jnp.asarray(X), jnp.asarray(A1), jnp.asarray(A2), Lc, gamma)
        if float(margin) <= 0:
            continue
        Aa = A1 - np.asarray(Y) @ A2
        assert np.linalg.eigvals(Aa).real.max() < 0
        assert np.linalg.eigvalsh(X @ Aa + Aa.T @ X).max() < 0


def test_disk_gain_gradients_match_finite_differences(design_data, rng):
    d, A1, A2 = design_data
    X = jnp.asarray(d.X)
    k = int(np.linalg.matrix_rank(A2))
    Theta0 = jnp.asarray(rng.normal(size=(X.shape[0], k)))

    def f(Theta):
        Y, _ = disk_gain(X, jnp.asarray(A1), jnp.asarray(A2), -2.0, 1.0, contraction(Theta), rank=k)
        Aa = jnp.asarray(A1) - Y @ jnp.asarray(A2)
        return jnp.sum(Aa**2)

    g = jax.jit(jax.grad(f))(Theta0)
    eps = 1e-6
    for idx in [(0, 0), (1, 0), (X.shape[0] - 1, k - 1)]:
        e = jnp.zeros_like(Theta0).at[idx].set(eps)
        fd = (f(Theta0 + e) - f(Theta0 - e)) / (2 * eps)
        assert np.isclose(float(g[idx]), float(fd), rtol=1e-5, atol=1e-8)
    # vmap over a batch of parameters
    batch = jnp.asarray(rng.normal(size=(4,) + Theta0.shape))
    vals = jax.vmap(f)(batch)
    assert np.allclose(np.asarray(vals), [float(f(b)) for b in batch])
