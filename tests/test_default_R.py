"""The default R must not depend on the basis an SVD returns (fojax._linalg.canonical_row_space).

Oracles: the orthogonal projector onto a row space computed independently with SciPy
(``scipy.linalg.orth``), its closed-form first canonical row $Pe_{J_1}/\\|Pe_{J_1}\\|$ with
$J_1 = \\arg\\max_j P_{jj}$, and invariance itself: every orthonormal basis $WQ$ of the same
subspace ($W$ from ``scipy.stats.ortho_group``) is a valid output of ``row_space`` and must
give the same rows, the same default R and, for a twin rescaled exactly by powers of two, the
same functional $Rx$.

Regression (the defect): before, `_order_candidates` took ``rows[:j]`` of an SVD basis of a
complement whose singular values are all 1; rotating that basis moved the order-2 default R
of `fojax.models.flexible_drive` by a projector distance of 0.30-0.38 (seeds 1-3).
"""

import numpy as np
import pytest
import scipy.linalg
import scipy.stats

import fojax._linalg as la
import fojax.design._conditions as conditions  # private: its row-space basis is rotated here
from fojax.analysis import e_perp
from fojax.design import default_R, HalfPlane
from fojax.models import flexible_drive


def _projector(Q):
    return Q.T @ Q


def _rotated_row_space(monkeypatch, seed):
    """Make `row_space` return another orthonormal basis W Q of the same row space."""
    orig = la.row_space
    rng = np.random.default_rng(seed)

    def rotated(M, tol=None):
        Q = orig(M, tol)
        if Q.shape[0] < 2:
            return -Q if Q.shape[0] else Q  # a sign is a rotation too
        W = scipy.stats.ortho_group.rvs(Q.shape[0], random_state=rng)
        return W @ Q

    monkeypatch.setattr(la, "row_space", rotated)
    # and where a caller imported it by name (the pre-fix `_order_candidates` did)
    monkeypatch.setattr(conditions, "row_space", rotated, raising=False)


@pytest.mark.parametrize("kind", ["projector", "generic", "wide"])
def test_canonical_row_space_is_invariant_under_rotation(monkeypatch, kind):
    rng = np.random.default_rng(7)
    if kind == "projector":  # the defect's case: all nonzero singular values are 1
        Q0 = scipy.linalg.orth(rng.normal(size=(7, 3))).T
        M = _projector(Q0)
    elif kind == "generic":
        M = rng.normal(size=(4, 6)) @ np.diag([1.0, 2.0, 4.0, 8.0, 0.5, 0.25])
    else:
        M = rng.normal(size=(2, 5))
    ref = la.canonical_row_space(M)
    k = np.linalg.matrix_rank(M)
    assert ref.shape == (k, M.shape[1])
    np.testing.assert_allclose(ref @ ref.T, np.eye(k), atol=1e-13)
    P = _projector(scipy.linalg.orth(M.T).T)  # SciPy's basis of the same row space
    np.testing.assert_allclose(_projector(ref), P, atol=1e-12)
    j1 = int(np.argmax(np.diag(P)))
    np.testing.assert_allclose(ref[0], P[:, j1] / np.linalg.norm(P[:, j1]), atol=1e-12)
    for seed in range(3):
        with monkeypatch.context() as mp:
            _rotated_row_space(mp, seed)
            np.testing.assert_allclose(la.canonical_row_space(M), ref, atol=1e-12)


def test_exact_ties_go_to_the_lower_index(monkeypatch):
    """Span{e0 + e1, e2}: columns 0 and 1 tie exactly (up to rounding) and column 2 has norm 1;
    the pivots are 2 (largest), then 0 (tie with 1: the lower index)."""
    M = np.array([[1.0, 1.0, 0.0, 0.0], [0.0, 0.0, 3.0, 0.0]])
    s = np.sqrt(0.5)
    want = np.array([[0.0, 0.0, 1.0, 0.0], [s, s, 0.0, 0.0]])
    np.testing.assert_allclose(la.canonical_row_space(M), want, atol=1e-14)
    for seed in range(4):
        with monkeypatch.context() as mp:
            _rotated_row_space(mp, seed)
            np.testing.assert_allclose(la.canonical_row_space(M), want, atol=1e-12)


@pytest.fixture(scope="module")
def drive():
    ex = flexible_drive()
    s = ex.system
    E, A, B, C = (np.asarray(x) for x in (s.E, s.A, s.B, s.C))
    return E, A, B, C, np.asarray(ex.L)


def _default(E, A, B, C, L, **kw):
    return default_R(E, A, B, C, L, psi="descriptor", Eperp=e_perp(E), region=HalfPlane(1.0), **kw)


@pytest.mark.parametrize("q0", [None, 2])
def test_regression_default_R_does_not_depend_on_the_svd_basis(monkeypatch, drive, q0):
    """Order 2 takes one row of a 2-row complement block (L has rank 1): a partial block."""
    R = _default(*drive, q0=q0)
    assert R.shape == (2, 8)
    for seed in (1, 2, 3):
        with monkeypatch.context() as mp:
            _rotated_row_space(mp, seed)
            Rw = _default(*drive, q0=q0)
        np.testing.assert_allclose(_projector(scipy.linalg.orth(Rw.T).T),
                                   _projector(scipy.linalg.orth(R.T).T), atol=1e-10)
        np.testing.assert_allclose(Rw, R, atol=1e-10 * np.abs(R).max())


def test_power_of_two_twin_gets_the_same_functional(drive):
    """Twin: E' = D_l E D_r, A' = D_l A D_r, B' = D_l B, C' = C D_r, L' = L D_r with exact
    powers of two; x = D_r x', so the same observer needs R' = R D_r (the same R x)."""
    E, A, B, C, L = drive
    n = E.shape[0]
    dl = 2.0 ** np.array([3, -5, 0, 7, -2, 1, 4, -6][:n])
    dr = 2.0 ** np.array([-4, 6, 2, -3, 5, 0, -7, 3][:n])
    twin = (dl[:, None] * E * dr, dl[:, None] * A * dr, dl[:, None] * B, C * dr, L * dr)
    R = _default(E, A, B, C, L)
    Rt = _default(*twin)
    np.testing.assert_allclose(Rt, R * dr[None, :], atol=1e-10 * np.abs(R * dr).max())


def test_unknown_input_candidates_do_not_depend_on_the_svd_basis(monkeypatch):
    """The unknown-input observer's candidate R's (`_candidate_Rs`, greedy prefixes of the
    same kind of complement bases) on §4.1.3's closed loop with d in the row of x3."""
    from fojax.design._unknown_input import _candidate_Rs  # private: the candidates are tested
    from fojax.models import example_4_1_3

    ex = example_4_1_3()
    E, A, B, C, L = (np.asarray(x) for x in (ex.E, ex.A, ex.B, ex.C, ex.L))
    A = A + B @ L
    D = np.eye(4)[:, [2]]
    Ep = la.perp(np.hstack([E, D]))
    Psi = np.vstack([Ep @ A, C])
    Gam = np.vstack([E, Psi])
    ref = _candidate_Rs(Gam, Psi, L, None)
    for seed in (1, 2, 3):
        with monkeypatch.context() as mp:
            _rotated_row_space(mp, seed)
            mp.setattr("fojax.design._unknown_input.row_space", la.row_space, raising=False)
            got = _candidate_Rs(Gam, Psi, L, None)
        assert [R.shape for R in got] == [R.shape for R in ref]
        for Rg, Rr in zip(got, ref):
            np.testing.assert_allclose(Rg, Rr, atol=1e-10)
