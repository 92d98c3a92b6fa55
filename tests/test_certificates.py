"""Tight H∞/H2 certificates, typed solver failures, the H2 feedthrough rank rule, and verdicts
on extreme or nearly singular pencils.

Oracles, independent of the code under test:

- **SLICOT AB13DD** (slycot), called here on the error system of the returned observer, for
  ‖T‖∞; **SciPy** ``solve_continuous_lyapunov`` for ‖T‖₂;
- **SLICOT AG08BD** (slycot), called here on the pencil, for its normal rank (regular iff
  normal rank = n);
- **exact rational arithmetic** (``fractions.Fraction`` of the stored floats): a nonzero
  ``det(s0 E - A)`` proves the pencil regular (the published MatrixPencils.jl case below);
- **exact equivalences**: multiplying the equations by an invertible matrix or the states
  by a diagonal one keeps the pencil regular and its finite eigenvalues (those of the
  unscaled pencil, from ``scipy.linalg.eigvals``) and keeps a disturbance with
  ``Bw = E W`` on the differential equations only (E⊥Bw = 0 exactly in the unscaled frame).
"""

from __future__ import annotations

import sys
import warnings
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest
import scipy.linalg as sla
import slycot
from helpers import assert_eigenvalues_match, random_descriptor

import fojax
from fojax.analysis import algebraic_channel, is_regular, kronecker_structure, structure_report
from fojax.design import design_functional_observer, Disk


sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from gamma_tightness import random_case  # noqa: E402  (the benchmark's own random family)


def ab13dd(A, B, C, D):
    n = A.shape[0]
    return float(slycot.ab13dd("C", "I", "N", "D", n, B.shape[1], C.shape[0], A, np.eye(n), B, C, D)[0])


def error_system(design, Bw, Dv):
    # private: the observer's base matrices, the oracle's input
    from fojax.design._hinf import base_mats

    s = design.structure
    return fojax.design.error_system(s, base_mats(s, design.params), Bw, Dv)


# ------------------------------------------------------------------ tight certificates


@pytest.mark.parametrize("seed", [2, 3, 5])
def test_gamma_is_the_returned_observers_own_bound(seed):
    """Seeds of the benchmark family where the design LMI's shared certificate gave γ 9-29 %
    above the norm: γ is now certified for the returned observer alone, within 1e-5 of its
    AB13DD norm, never below it, and never more than that above the region-only norm."""
    sys_, L, Bw, Dv, region, _ = random_case(seed)
    d = design_functional_observer(sys_, L, region=region, objective="hinf", Bw=Bw, Dv=Dv)
    norm = ab13dd(*error_system(d, Bw, Dv))
    assert norm * (1 - 1e-9) <= d.hinf.gamma <= norm * (1 + 1e-5), (d.hinf.gamma, norm)
    assert d.hinf.gamma <= d.hinf.region_only_norm * (1 + 1e-5)
    assert d.hinf.certificate_X is not None and d.hinf.brl_max_eig < 0
    assert d.verify().passed  # the BRL at (certificate_X, γ) and γ ≥ AB13DD, re-checked


def test_h2_nu_is_the_returned_observers_own_bound():
    sys_, L, Bw, _, region, _ = random_case(1)
    Bw = np.asarray(sys_.E) @ Bw  # on the differential equations only: no feedthrough
    d = design_functional_observer(sys_, L, region=region, objective="h2", Bw=Bw)
    A, B, C, _ = error_system(d, Bw, np.zeros((np.asarray(sys_.C).shape[0], 0)))
    P = sla.solve_continuous_lyapunov(A, -B @ B.T)
    norm = float(np.sqrt(np.trace(C @ P @ C.T)))
    assert norm * (1 - 1e-9) <= d.h2.nu <= norm * (1 + 1e-5), (d.h2.nu, norm)


def test_observer_gamma_on_a_closed_form():
    """First-order lag 1/(s + a) with feedthrough 0: ‖T‖∞ = 1/a at ω = 0."""
    # private: tested itself on a closed form
    from fojax.design._certify import observer_gamma

    a = 2.0
    g, X, top = observer_gamma(np.array([[-a]]), np.ones((1, 1)), np.ones((1, 1)), np.zeros((1, 1)), 1 / a)
    assert 1 / a <= g <= (1 / a) * (1 + 1e-5) and top < 0 and X[0, 0] > 0


# ------------------------------------------------------------------ solver stops short


@pytest.mark.parametrize("seed", [14, 23])
def test_feasible_hinf_problems_that_stopped_short_now_design(seed):
    """Two feasible H∞ problems of the benchmark family on which both solvers stopped at
    optimal_inaccurate (raised as LMIInfeasibleError before): the gain-penalty ladder
    (`fojax.design._hinf.GAIN_PENALTIES`) gives verified designs with tight γ."""
    sys_, L, Bw, Dv, region, _ = random_case(seed)
    d = design_functional_observer(sys_, L, region=region, objective="hinf", Bw=Bw, Dv=Dv)
    norm = ab13dd(*error_system(d, Bw, Dv))
    assert norm * (1 - 1e-9) <= d.hinf.gamma <= norm * (1 + 1e-5)
    ev = np.linalg.eigvals(np.asarray(d.observer.error_matrix))
    assert np.all(np.abs(ev - region.center) < region.radius)


def test_stopped_short_on_every_penalty_is_typed(monkeypatch):
    import cvxpy as cp

    sys_, L, Bw, Dv = random_descriptor(0)
    orig = cp.Problem.solve

    def inaccurate(self, *a, **k):
        out = orig(self, *a, **k)
        if any(isinstance(v, cp.Variable) and v.ndim == 0 for v in self.variables()):  # the γ problem
            self._status = cp.OPTIMAL_INACCURATE
        return out

    monkeypatch.setattr(cp.Problem, "solve", inaccurate)
    with pytest.raises(fojax.errors.SolverStoppedShortError) as ei:
        design_functional_observer(sys_, L, region=Disk(-3.0, 2.5), objective="hinf", Bw=Bw, Dv=Dv,
                                   balance=False, solver="CLARABEL")
    assert "gain penalty 0.01" in ei.value.status and "enlarge" not in str(ei.value)
    assert not isinstance(ei.value, fojax.errors.LMIInfeasibleError)


# ------------------------------------------------------------------ H2 feedthrough rank rule


def _transformed(sys_, L, Bw, M, dr):
    E, A, B, C = (np.asarray(x) for x in (sys_.E, sys_.A, sys_.B, sys_.C))
    return fojax.DescriptorSystem(M @ E * dr, M @ A * dr, M @ B, C * dr), L * dr, M @ Bw


def test_differential_disturbance_has_no_feedthrough_in_any_coordinates():
    """Bw = E W: E⊥Bw is exactly zero after the rank rule, for the equations multiplied by a
    random orthogonal matrix, by diagonal scalings (2^±20) and states scaled; a genuine
    algebraic disturbance keeps its rank."""
    sys_, L, Bw, _ = random_descriptor(3, disturb_algebraic_row=False)
    rng = np.random.default_rng(7)
    U = np.linalg.qr(rng.standard_normal((5, 5)))[0]
    for M in (np.eye(5), U, np.diag(2.0 ** rng.integers(-20, 21, 5)) @ U, U @ np.diag(rng.uniform(0.1, 10, 5))):
        dr = rng.uniform(0.1, 10, 5)
        s2, _, Bw2 = _transformed(sys_, L, Bw, M, dr)
        raw = fojax.analysis.e_perp(s2.E) @ Bw2
        assert np.abs(algebraic_channel(s2.E, Bw2)).max() == 0.0, np.abs(raw).max()
        Bw_alg = Bw2 + M @ np.eye(5)[:, [4]] @ np.ones((1, 2))  # a disturbance on the algebraic row
        assert np.linalg.matrix_rank(algebraic_channel(s2.E, Bw_alg)) == 1


def test_h2_design_is_the_same_after_orthogonal_and_diagonal_equation_scalings():
    """The same plant with its equations multiplied by a random orthogonal matrix (default
    balance) or by diagonal scalings and its states scaled (balance=True, the unit-free
    frame): every version is accepted (a disturbance on the differential part only) and gets
    the same H2 norm. Measured agreement 5e-6 / 1e-5 relative: each design solves its own
    LMIs, whose minimisers an interior-point solver determines only to about the square root
    of its gap tolerance; the feedthrough decision itself is exact (previous test)."""
    sys_, L, Bw, _ = random_descriptor(0, disturb_algebraic_row=False)
    region = Disk(-3.0, 2.5)
    rng = np.random.default_rng(5)
    U = np.linalg.qr(rng.standard_normal((5, 5)))[0]
    D = np.diag(2.0 ** rng.integers(-8, 9, 5))
    dr = 2.0 ** rng.integers(-8, 9, 5)
    for balance, variants in ((None, [(np.eye(5), np.ones(5)), (U, np.ones(5))]),
                              (True, [(np.eye(5), np.ones(5)), (D, np.ones(5)), (D, dr)])):
        norms = []
        for M, d_r in variants:
            s2, L2, Bw2 = _transformed(sys_, L, Bw, M, d_r)
            d = design_functional_observer(s2, L2, region=region, objective="h2", Bw=Bw2, balance=balance)
            norms.append(d.h2.norm)
            assert d.h2.feedthrough == 0.0
        np.testing.assert_allclose(norms, norms[0], rtol=1e-4)


# ------------------------------------------------------------------ extreme and nearly singular data


def _regular_3x3(seed=0):
    rng = np.random.default_rng(seed)
    E = np.diag([1.0, 0, 0])
    A = rng.standard_normal((3, 3))
    A[1:, 1:] += 3 * np.eye(2)
    U = np.linalg.qr(rng.standard_normal((3, 3)))[0]
    V = np.linalg.qr(rng.standard_normal((3, 3)))[0]
    return U @ E @ V, U @ A @ V, E, A


@pytest.mark.parametrize("rows", [(1e300, 1e300, 1e300), (1e-300, 1e-300, 1e-300), (1e300, 1.0, 1e-300)])
def test_extreme_pencils_get_the_right_verdict_without_warnings(rows):
    E, A, E0, A0 = _regular_3x3()
    Dl = np.diag(rows)
    Es, As = Dl @ E, Dl @ A
    B, C = np.ones((3, 1)), np.ones((1, 3))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert is_regular(Es, As)
        rep = structure_report(fojax.DescriptorSystem(Es, As, Dl @ B, C))
        mixed = structure_report(fojax.DescriptorSystem(Es, As, B * 1e-300, C * 1e300))
    assert rep.regular and rep.rank_E == 1 and mixed.regular and mixed.rank_E == 1
    truth = sla.eigvals(A0, E0)
    assert_eigenvalues_match(rep.finite_poles, truth[np.isfinite(truth)], rtol=1e-8)


def test_balancing_that_cannot_be_represented_names_the_matrix():
    # private: tested itself
    from fojax.analysis._balance import apply_scaling

    s = fojax.analysis.Scaling(np.array([60]), np.array([0]), "ward")
    with pytest.raises(fojax.errors.DataRangeError, match="largest entry of E") as ei:
        apply_scaling(s, np.array([[1e300]]), np.array([[1.0]]))
    assert ei.value.name == "E" and ei.value.magnitude == 1e300


def _nearly_singular_4x4(seed):
    """A regular 4x4 pencil (rank E = 2) whose A restricted to ker E has a singular value
    eps: within the rank tolerance's band, so two algorithms may decide differently."""
    rng = np.random.default_rng(seed)
    U = np.linalg.qr(rng.standard_normal((4, 4)))[0]
    V = np.linalg.qr(rng.standard_normal((4, 4)))[0]
    A0 = rng.standard_normal((4, 4))
    eps = 10.0 ** rng.uniform(-13, -8)
    A0[2:, 2:] = np.diag([1.0, eps])
    A0[3, :2] = 0
    return U @ np.diag([1.0, 1, 0, 0]) @ V, U @ A0 @ V


def _ag08bd_regular(E, A):
    n = E.shape[0]
    out = slycot.ag08bd(n, n, 0, 0, A.copy(order="F"), E.copy(order="F"), np.zeros((n, 1), order="F"),
                        np.zeros((1, n), order="F"), np.zeros((1, 1), order="F"), equil="S", tol=1e-10)
    return int(out[2]) == n


def test_nearly_singular_pencil_is_reported_undecidable():
    """Seed 13: fojax's deflation at the default tolerance called it regular, AG08BD singular."""
    E, A = _nearly_singular_4x4(13)
    with pytest.raises(fojax.errors.NumericallyUndecidableError, match="undecidable at tolerance 1.0e-10") as ei:
        is_regular(E, A)
    assert ei.value.tol == 1e-10 and ei.value.deflation_regular != ei.value.ag08bd_regular
    with pytest.raises(fojax.errors.NumericallyUndecidableError):
        structure_report(fojax.DescriptorSystem(E, A, np.ones((4, 1)), np.ones((1, 4))))
    assert is_regular(E, A, tol=1e-14)  # an explicit tolerance far from the value decides


@pytest.mark.parametrize("seed", range(0, 40))
def test_near_threshold_verdicts_agree_with_the_reference_or_are_undecidable(seed):
    E, A = _nearly_singular_4x4(seed)
    try:
        verdict = is_regular(E, A)
    except fojax.errors.NumericallyUndecidableError:
        return
    ref = _ag08bd_regular(E, A)
    if verdict != ref:  # AG08BD's own scaling (equil="S") may still differ far from the band
        # private: the deflation's distance to the band is checked
        from fojax.analysis._common import as_pencil, deflate

        assert deflate(as_pencil(E, A), None).nearest[0] >= 100.0


# MatrixPencils.jl (A. Varga), test/test_regular.jl, testset "_svdlikeAE": a 4x4 pencil A - λE
# whose columns 1-2 of E and row 1 of A hold round-off (1e-34 .. 3e-16); the reference reduces
# it to its SVD-like form with rank E = 2 and rank A22 = 1 (`@test ... rE == 2 && rA22 == 1`).
_MP_A = np.array([
    [-3.330669073875470e-16, 0, 0, 0],
    [-5.336424998587595e-17, 4.999999999999997e-01, 0, 0],
    [7.882634225314346e-01, 4.926646390821473e-02, 1.017643702629568e+00, 0],
    [-7.804970910378840e-02, -5.073231091746246e-01, -3.602232247129060e-01, 1.906644727694980e+00],
])
_MP_E = np.array([
    [9.708552809960075e-34, -4.715554847257422e-19, 7.905694150420953e-01, 0],
    [-1.002546820843656e-17, -9.625586024907403e-20, 9.682458365518573e-02, 4.743416490252569e-01],
    [-9.878387353077869e-19, 2.181405497860925e-19, -3.720759787739367e-01, 4.673827146373172e-02],
    [1.017230340487078e-17, 7.512741891975197e-20, -6.045704470706158e-02, -4.812889603890242e-01],
])


def _exact_det(M) -> Fraction:
    """Determinant in exact rational arithmetic (fraction-free elimination on Fractions)."""
    M = [[Fraction(x) for x in row] for row in M]
    n, det = len(M), Fraction(1)
    for k in range(n):
        piv = next((i for i in range(k, n) if M[i][k] != 0), None)
        if piv is None:
            return Fraction(0)
        if piv != k:
            M[k], M[piv], det = M[piv], M[k], -det
        det *= M[k][k]
        for i in range(k + 1, n):
            f = M[i][k] / M[k][k]
            M[i] = [a - f * b for a, b in zip(M[i], M[k])]
    return det


def test_reference_nearly_singular_pencil_gets_the_reference_verdict():
    """The MatrixPencils.jl pencil is regular (exactly, and far from singular: det(E - A) is
    about 0.59), with rank E = 2 and, as rank A22 = 1 < n - rank E says, impulsive. Its
    round-off entries are left out of the balancing, which would otherwise lift them into the
    rank decisions (a deciding singular value 5e-14 of the balanced pencil)."""
    E, A = _MP_E, _MP_A
    assert abs(float(_exact_det(E - A))) > 0.5  # the oracle: regular, with a wide margin
    assert is_regular(E, A) and is_regular(E, A, balance=False)
    rep = structure_report(fojax.DescriptorSystem(E, A, np.ones((4, 1)), np.ones((1, 4))))
    assert rep.regular and rep.rank_E == 2 and not rep.impulse_free
    assert kronecker_structure(E, A).normal_rank == 4


@pytest.mark.parametrize("k", [1e2, 1e4])
def test_round_off_lifted_by_balancing_never_makes_a_regular_pencil_singular(k):
    """The same pencil with its round-off entries k times larger (1e-15 .. 1e-12, too large to
    be told from data): still exactly regular; its deciding singular values fall near the
    threshold, where AG08BD is asked too, so the answer is regular or undecidable, and
    regular on the data as given, as the error says."""
    E, A = _MP_E.copy(), _MP_A.copy()
    E[:, :2] *= k
    A[0, 0] *= k
    assert abs(float(_exact_det(E - A))) > 0.5
    try:
        assert is_regular(E, A)
    except fojax.errors.NumericallyUndecidableError as e:
        assert e.ag08bd_regular != e.deflation_regular and "balance=False" in str(e)
    assert is_regular(E, A, balance=False)
