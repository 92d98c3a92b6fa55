"""LMI programs handed to Clarabel directly (`fojax.design._lmi.ConicLMI`, `solve_conic`).

Oracles (independent of the direct builder):

- the svec convention: ``svec(S)·svec(T) = tr(ST)`` and the largest eigenvalue of a symmetric
  matrix (``numpy.linalg.eigvalsh``) as the optimum of ``min t s.t. tI - S ⪰ 0``;
- the same LMI written out with cvxpy's own symmetric matrix variable (cvxpy canonicalises it,
  Clarabel solves): same status, same optimal value to a relative 1e-5, and the direct
  solution satisfies the LMI, checked with ``eigvalsh`` at the returned point;
- infeasibility: a matrix with an eigenvalue in the right half-plane has no Lyapunov
  certificate (closed form), and a mode no output injection moves (PBH with NumPy) outside
  the region makes the ε-block's LMI infeasible: `LMIInfeasibleError`, and cvxpy's status is
  ``infeasible`` too.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import fojax
from fojax.design import Disk, HalfPlane, Sector

# private: the direct conic builder is what this module tests
from fojax.design._eliminated import _full_lmi, epsilon_block_lmi, epsilon_output
from fojax.design._lmi import ConicLMI, smat, solve_conic, svec, sym_basis
from fojax.design._region_lmi import solve_conic_with_fallbacks


def random_sym(rng, m):
    S = rng.standard_normal((m, m))
    return S + S.T


def test_svec_is_an_isometry_and_sym_basis_its_inverse():
    rng = np.random.default_rng(0)
    S, T = random_sym(rng, 5), random_sym(rng, 5)
    assert svec(S) @ svec(T) == pytest.approx(np.trace(S @ T), rel=1e-12)
    assert np.allclose(smat(svec(S), 5), S)
    B = sym_basis(4)
    assert B.shape == (10, 4, 4)
    assert np.allclose(svec(B), np.eye(10))


def test_largest_eigenvalue_as_an_lmi():
    """min t s.t. tI - S ⪰ 0 has the optimum λ_max(S): checks the svec order, the √2 scaling
    and the sign convention of the PSD cone against NumPy."""
    rng = np.random.default_rng(1)
    S = random_sym(rng, 7)
    prob = ConicLMI(np.ones(1), ((-S, np.eye(7)[None]),))
    x, info = solve_conic(prob, "λmax")
    assert info["status"] == "optimal" and info["interface"] == "direct"
    assert x[0] == pytest.approx(np.linalg.eigvalsh(S)[-1], rel=1e-7, abs=1e-7)


def lyapunov_lmi(A, margin=1e-3):
    """min tr X s.t. X ⪰ I, AᵀX + XA ⪯ -margin I, in svec coordinates."""
    q = A.shape[0]
    B = sym_basis(q)
    BA = B @ A
    return ConicLMI(svec(np.eye(q)), ((-np.eye(q), B), (-margin * np.eye(q), -(BA + np.swapaxes(BA, 1, 2)))))


def lyapunov_cvxpy(A, margin=1e-3):
    import cvxpy as cp
    q = A.shape[0]
    X = cp.Variable((q, q), symmetric=True)
    prob = cp.Problem(cp.Minimize(cp.trace(X)), [X >> np.eye(q), A.T @ X + X @ A << -margin * np.eye(q)])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        prob.solve(solver="CLARABEL")
    return prob


def test_direct_and_cvxpy_agree_on_a_lyapunov_lmi():
    rng = np.random.default_rng(2)
    A = rng.standard_normal((6, 6)) - 3.0 * np.eye(6)
    assert np.linalg.eigvals(A).real.max() < 0
    x, info = solve_conic(lyapunov_lmi(A), "Lyapunov")
    ref = lyapunov_cvxpy(A)
    assert info["status"] == ref.status == "optimal"
    X = smat(x, 6)
    assert np.trace(X) == pytest.approx(ref.value, rel=1e-5)
    assert np.linalg.eigvalsh(X).min() > 1 - 1e-6
    assert np.linalg.eigvalsh(A.T @ X + X @ A).max() < -1e-3 + 1e-6


def test_infeasible_lmi_raises_like_cvxpy_reports():
    A = np.diag([1.0, -2.0, -3.0])  # eigenvalue +1: no X ≻ 0 with AᵀX + XA ≺ 0
    with pytest.raises(fojax.errors.LMIInfeasibleError):
        solve_conic(lyapunov_lmi(A), "Lyapunov")
    assert lyapunov_cvxpy(A).status == "infeasible"


def test_gain_kept_form_matches_the_lmi_written_in_cvxpy():
    """The ε-block's LMI with its gain (`_full_lmi`, one cone per part, norm term) and the same
    LMI written with cvxpy: equal optimal values; the direct solution satisfies every part."""
    import cvxpy as cp
    rng = np.random.default_rng(3)
    A = rng.standard_normal((6, 6)) / np.sqrt(6) - np.eye(6)
    C = rng.standard_normal((4, 6))
    region = Disk(-2.5, 1.6) & HalfPlane(1.0)
    R, _, _ = epsilon_output(C)
    prob, gain = _full_lmi(A, R, region, 1e-3)
    x, info = solve_conic(prob, "full form")
    X = cp.Variable((6, 6), symmetric=True)
    W = cp.Variable((6, R.shape[0]))
    cons = [X >> np.eye(6)]
    for part in region.parts:
        Lr, Mr = part.characteristic()
        Phi = X @ A - W @ R
        F = cp.kron(Lr, X) + cp.kron(Mr, Phi.T) + cp.kron(Mr.T, Phi)
        cons.append(0.5 * (F + F.T) << -1e-3 * np.eye(F.shape[0]))
    ref = cp.Problem(cp.Minimize(cp.trace(X) + cp.norm(W, "fro")), cons)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ref.solve(solver="CLARABEL")
    assert info["status"] == ref.status == "optimal"
    p = 21
    assert np.trace(smat(x[:p], 6)) + np.linalg.norm(x[p:]) == pytest.approx(ref.value, rel=1e-5)
    Xv, K = gain(x)
    for part in region.parts:
        assert np.linalg.eigvalsh(part.lmi_matrix(Xv, Xv @ (A - K @ R))).max() < 0


def test_scs_rungs_go_through_cvxpy(monkeypatch):
    """When the direct Clarabel rungs stop short, the ladder's SCS rungs solve the same program
    through cvxpy (`ConicLMI.to_cvxpy`); the solution satisfies the LMI."""
    from fojax.design import _region_lmi

    def stop(*a, **k):
        raise fojax.errors.SolverStoppedShortError("direct", "optimal_inaccurate", {})

    monkeypatch.setattr(_region_lmi, "solve_conic", stop)
    A = np.array([[-1.0, 2.0], [0.0, -3.0]])
    x, info = solve_conic_with_fallbacks(lyapunov_lmi(A), "Lyapunov", "", "auto")
    assert info["solver"] == "SCS" and "optimal_inaccurate (CLARABEL, min-gain)" in info["route"]
    X = smat(x, 2)
    assert np.linalg.eigvalsh(X).min() > 1 - 1e-5
    assert np.linalg.eigvalsh(A.T @ X + X @ A).max() < 0


@pytest.mark.parametrize("region", [Disk(-2.5, 1.6), HalfPlane(1.0), Sector(0.8)], ids=str)
def test_fixed_mode_outside_the_region_is_infeasible(region):
    """A mode of A that the output cannot see (PBH) at +0.5: every form raises
    `LMIInfeasibleError` from the solver's certificate."""
    rng = np.random.default_rng(4)
    A = np.block([[rng.standard_normal((4, 4)) / 2, np.zeros((4, 1))], [rng.standard_normal((1, 4)), np.full((1, 1), 0.5)]])
    C = np.hstack([rng.standard_normal((2, 4)), np.zeros((2, 1))])
    assert np.linalg.matrix_rank(np.vstack([0.5 * np.eye(5) - A, C])) < 5
    with pytest.raises(fojax.errors.LMIInfeasibleError):
        epsilon_block_lmi(A, C, region)


def test_row_null_split_is_one_svd_of_both_spaces():
    """`_linalg.row_null_split` against SciPy's `orth`/`null_space` (same subspaces, compared
    by projectors) and the factorization M = U diag(s) R, on a rank-deficient matrix."""
    import scipy.linalg as sla

    from fojax._linalg import row_null_split  # private: the helper of the ε-block's reduction
    rng = np.random.default_rng(5)
    M = rng.standard_normal((5, 3)) @ rng.standard_normal((3, 7))  # rank 3
    R, N, U, s = row_null_split(M)
    assert R.shape == (3, 7) and N.shape == (7, 4)
    assert np.allclose(np.vstack([R, N.T]) @ np.vstack([R, N.T]).T, np.eye(7))
    assert np.allclose(R.T @ R, sla.orth(M.T) @ sla.orth(M.T).T)
    assert np.allclose(N @ N.T, sla.null_space(M) @ sla.null_space(M).T)
    assert np.allclose(U * s @ R, M)
