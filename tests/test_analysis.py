"""Structural analysis: hand-checked catalogue, SciPy/closed-form oracles, thesis example 4.1.3.

Every expected value in CATALOGUE was derived by hand; the reasoning is the comment
above each case. Conventions: "poles" are the finite generalized eigenvalues of
(E, A); index 0 = ODE, 1 = impulse-free DAE, >= 2 impulsive. Pole sets are compared by
a one-to-one matching (`helpers.assert_eigenvalues_match`), never by sorting both sides;
the order `finite_poles` documents is checked on its own (`_assert_documented_order`).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg as sla
from helpers import assert_eigenvalues_match

import fojax
from fojax.analysis._common import as_pencil, kernel_chain  # private: tested itself


I2 = np.eye(2)
J2 = np.array([[0.0, 1.0], [0.0, 0.0]])  # nilpotent Jordan block, N^2 = 0
OBS = ("c_observable", "r_observable", "i_observable", "s_observable")
CTRL = ("c_controllable", "r_controllable", "i_controllable", "s_controllable")
HOST = {
    "c_observable": fojax.analysis.is_c_observable,
    "r_observable": fojax.analysis.is_r_observable,
    "i_observable": fojax.analysis.is_i_observable,
    "s_observable": fojax.analysis.is_s_observable,
    "c_controllable": fojax.analysis.is_c_controllable,
    "r_controllable": fojax.analysis.is_r_controllable,
    "i_controllable": fojax.analysis.is_i_controllable,
    "s_controllable": fojax.analysis.is_s_controllable,
    "detectable": fojax.analysis.is_detectable,
    "stabilizable": fojax.analysis.is_stabilizable,
}


@dataclasses.dataclass
class Case:
    name: str
    E: np.ndarray
    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    regular: bool
    expect: dict = dataclasses.field(default_factory=dict)  # property -> bool/int
    poles: tuple = ()  # hand-computed finite poles
    L_true: np.ndarray | None = None  # functional satisfying Assumption 1
    L_false: np.ndarray | None = None  # functional violating it

    def sys(self):
        return fojax.DescriptorSystem(self.E, self.A, self.B, self.C)


def _yes(**kw):
    base = dict.fromkeys(OBS + CTRL + ("detectable", "stabilizable"), True)
    base.update(kw)
    return base


CATALOGUE = [
    # ODE in companion form: s^2 + 3s + 2 = (s+1)(s+2). [C; CA] = I and [B, AB] =
    # [[0,1],[1,-3]] are invertible, E = I so rank[E;C] = rank[E,B] = n: everything holds.
    Case(
        "ode_companion",
        I2,
        np.array([[0.0, 1.0], [-2.0, -3.0]]),
        np.array([[0.0], [1.0]]),
        np.array([[1.0, 0.0]]),
        True,
        _yes(impulse_free=True, stable=True, admissible=True, index=0),
        (-2.0, -1.0),
        L_true=np.array([[0.0, 1.0]]),
    ),
    # Decoupled modes -1, 2; C = e1 never sees x2 (the unstable mode): PBH at s = 2 gives
    # [[0,0],[0,0]... rank 1 -> not R/C/S-observable and not detectable. E = I makes it
    # I-observable. B = [1;1] excites both distinct modes: all controllability notions.
    Case(
        "ode_unobservable_unstable",
        I2,
        np.diag([-1.0, 2.0]),
        np.array([[1.0], [1.0]]),
        np.array([[1.0, 0.0]]),
        True,
        _yes(
            impulse_free=True,
            stable=False,
            admissible=False,
            index=0,
            c_observable=False,
            r_observable=False,
            s_observable=False,
            detectable=False,
        ),
        (-1.0, 2.0),
    ),
    # Modes -1 (seen, actuated) and -3 (hidden from both C and B). Stable, so detectable
    # and stabilizable, but not R-observable nor R-controllable.
    Case(
        "ode_stable_hidden_mode",
        I2,
        np.diag([-1.0, -3.0]),
        np.array([[1.0], [0.0]]),
        np.array([[1.0, 0.0]]),
        True,
        _yes(
            impulse_free=True,
            stable=True,
            admissible=True,
            index=0,
            c_observable=False,
            r_observable=False,
            s_observable=False,
            c_controllable=False,
            r_controllable=False,
            s_controllable=False,
        ),
        (-3.0, -1.0),
    ),
    # Semi-explicit index 1: 0 = x1 - x2 (A22 = -1 invertible) => x2 = x1 and
    # x1' = -2 x1 + x2 + u = -x1 + u. det(sE - A) = (s+2) - 1 = s + 1: one pole -1 =
    # rank E -> impulse-free, admissible. C = x2: PBH at -1 [[1,-1],[-1,1],[0,1]] rank 2,
    # rank[E;C] = 2 -> C-observable. B = e1: PBH [[1,-1,1],[-1,1,0]] rank 2 (R), but
    # rank[E,B] = 1 -> not C-controllable; impulse-free -> I, hence S-controllable.
    Case(
        "index1_admissible",
        np.diag([1.0, 0.0]),
        np.array([[-2.0, 1.0], [1.0, -1.0]]),
        np.array([[1.0], [0.0]]),
        np.array([[0.0, 1.0]]),
        True,
        _yes(impulse_free=True, stable=True, admissible=True, index=1, c_controllable=False),
        (-1.0,),
    ),
    # Same pencil, C = x1, B = e2: rank[E;C] = rank[[1,0],[0,0],[1,0]] = 1 -> not
    # C-observable, still R (PBH [[1,-1],[-1,1],[1,0]] rank 2) and I (impulse-free) -> S.
    # rank[E,B] = 2 and PBH [[1,-1,0],[-1,1,1]] rank 2 -> C-controllable.
    Case(
        "index1_measure_x1",
        np.diag([1.0, 0.0]),
        np.array([[-2.0, 1.0], [1.0, -1.0]]),
        np.array([[0.0], [1.0]]),
        np.array([[1.0, 0.0]]),
        True,
        _yes(impulse_free=True, stable=True, admissible=True, index=1, c_observable=False),
        (-1.0,),
    ),
    # Pure fast subsystem N x' = x with N = J2: det(sN - I) = 1, no finite poles, index 2
    # (impulsive). Stable vacuously, not admissible. Impulse x = -delta N x0 = -delta
    # [x0_2; 0] lands in x1, which C = e1 sees: rank[E; E^perp A; C] = rank[e2; e2; e1] = 2
    # -> I-observable; rank[E; C] = 2 -> C-observable. B = e2: rank[E, B] = 2 -> C-ctrl.
    # Functional: Gamma has rank 2 = n, so every L works.
    Case(
        "index2_sees_impulse",
        J2,
        I2,
        np.array([[0.0], [1.0]]),
        np.array([[1.0, 0.0]]),
        True,
        _yes(impulse_free=False, stable=True, admissible=False, index=2),
        (),
        L_true=np.array([[1.0, 0.0]]),
    ),
    # Same pencil, C = e2 never sees the impulse in x1: rank[E; E^perp A; C] = rank[e2; e2;
    # e2] = 1 -> neither I, S nor C-observable; R trivially (no finite poles); not
    # detectable. B = e1: [E, A ker E, B] = [[0,1,1,1],[0,0,0,0]] rank 1 -> not
    # I-controllable. Functional: Gamma spans e2 only -> L = e2 yes, L = e1 no.
    Case(
        "index2_blind_to_impulse",
        J2,
        I2,
        np.array([[1.0], [0.0]]),
        np.array([[0.0, 1.0]]),
        True,
        _yes(
            impulse_free=False,
            stable=True,
            admissible=False,
            index=2,
            c_observable=False,
            i_observable=False,
            s_observable=False,
            detectable=False,
            c_controllable=False,
            i_controllable=False,
            s_controllable=False,
            stabilizable=False,
        ),
        (),
        L_true=np.array([[0.0, 1.0]]),
        L_false=np.array([[1.0, 0.0]]),
    ),
    # 0 = x2 - x3 => x3 = x2, x2' = -2 x2 + x3 = -x2, x1' = x1: det = (s-1)(s+1), poles
    # {-1, 1}, index 1, unstable. C = x2 misses the unstable x1 -> not R/C/S, not
    # detectable; impulse-free -> I-observable. B = e1 drives only x1: the stable mode -1
    # is uncontrollable (not R) but the unstable one is (PBH at 1 has rank 3) ->
    # stabilizable.
    Case(
        "index1_unstable_partial",
        np.diag([1.0, 1.0, 0.0]),
        np.array([[1.0, 0.0, 0.0], [0.0, -2.0, 1.0], [0.0, 1.0, -1.0]]),
        np.array([[1.0], [0.0], [0.0]]),
        np.array([[0.0, 1.0, 0.0]]),
        True,
        _yes(
            impulse_free=True,
            stable=False,
            admissible=False,
            index=1,
            c_observable=False,
            r_observable=False,
            s_observable=False,
            detectable=False,
            c_controllable=False,
            r_controllable=False,
            s_controllable=False,
        ),
        (-1.0, 1.0),
    ),
    # Already in Weierstrass form: slow x1' = -x1 (pole -1), fast (x2, x3) with N = J2
    # (index 2). C = e1: PBH at -1 [[0,0,0],[0,-1,-1],[0,0,-1],[1,0,0]] rank 3 (R);
    # E^perp = e3', E^perp A = e3', Gamma = span{e1, e3} rank 2 < 3 -> not I, S, C,
    # detectable. B = e1 + e3: [E, B] has columns e1, 0, e2, e1+e3 -> rank 3 (C-ctrl, so
    # I, S, R). Functional: L = e1 + e3 in span{e1, e3} yes; L = e2 no.
    Case(
        "index2_with_slow_part",
        np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, 0.0]]),
        np.diag([-1.0, 1.0, 1.0]),
        np.array([[1.0], [0.0], [1.0]]),
        np.array([[1.0, 0.0, 0.0]]),
        True,
        _yes(
            impulse_free=False,
            stable=True,
            admissible=False,
            index=2,
            c_observable=False,
            i_observable=False,
            s_observable=False,
            detectable=False,
        ),
        (-1.0,),
        L_true=np.array([[1.0, 0.0, 1.0]]),
        L_false=np.array([[0.0, 1.0, 0.0]]),
    ),
    # Index 3 chain N = shift (N^3 = 0, N^2 != 0), A = I. C = e1 sees delta and delta'
    # (x = -delta N x0 - delta' N^2 x0): Gamma = [e2; e3; 0; e3; e1] rank 3 -> I; rank[E;C]
    # = 3 -> C. B = e3: [E, B] has columns 0, e1, e2, e3 -> C-controllable.
    Case(
        "index3_chain",
        np.diag([1.0, 1.0], 1),
        np.eye(3),
        np.array([[0.0], [0.0], [1.0]]),
        np.array([[1.0, 0.0, 0.0]]),
        True,
        _yes(impulse_free=False, stable=True, admissible=False, index=3),
        (),
    ),
    # Purely algebraic 0 = -x (E = 0, A = -I) with m = p = 0: det(sE - A) = 1, no poles,
    # N = 0 -> index 1, impulse-free, admissible. rank[E;C] = rank[E,B] = 0 < 2 -> not
    # C-observable / C-controllable; R trivially; I: rank[[0,-I],[0,0]] = 2 = n + 0.
    Case(
        "purely_algebraic_no_io",
        np.zeros((2, 2)),
        -I2,
        np.zeros((2, 0)),
        np.zeros((0, 2)),
        True,
        _yes(
            impulse_free=True,
            stable=True,
            admissible=True,
            index=1,
            c_observable=False,
            c_controllable=False,
        ),
        (),
        L_true=np.eye(2),
    ),
    # x3 = x1 from 0 = x1 - x3, then x2' = -5 x1 - 2 x2 + x1: slow ODE [[0,1],[-4,-2]],
    # s^2 + 2 s + 4 = 0 -> s = -1 +- i sqrt(3). C = x1: [C_s; C_s A_s] = I (R); x3 = x1 is
    # then known, but rank[E;C] = 2 < 3 -> not C-observable (x3' never appears);
    # I by impulse-freeness. B = e2: (A_s, [0;1]) controllable, rank[E,B] = 2.
    Case(
        "index1_complex_poles",
        np.diag([1.0, 1.0, 0.0]),
        np.array([[0.0, 1.0, 0.0], [-5.0, -2.0, 1.0], [1.0, 0.0, -1.0]]),
        np.array([[0.0], [1.0], [0.0]]),
        np.array([[1.0, 0.0, 0.0]]),
        True,
        _yes(
            impulse_free=True,
            stable=True,
            admissible=True,
            index=1,
            c_observable=False,
            c_controllable=False,
        ),
        (-1.0 - np.sqrt(3.0) * 1j, -1.0 + np.sqrt(3.0) * 1j),
    ),
    # det(sE - A) = det diag(s - 1, 0) = 0 for all s: irregular (x2 appears in no equation).
    # Functional: E^perp = e2', E^perp A = 0, Gamma = [e1; 0; [1,1]] has rank 2 -> any L.
    Case(
        "irregular_free_variable",
        np.diag([1.0, 0.0]),
        np.diag([1.0, 0.0]),
        np.array([[1.0], [1.0]]),
        np.array([[1.0, 1.0]]),
        False,
        L_true=np.array([[0.0, 1.0]]),
    ),
    # E = A = 0: sE - A = 0, irregular. Gamma = [0; 0; C] = span{e1}.
    Case(
        "irregular_zero",
        np.zeros((2, 2)),
        np.zeros((2, 2)),
        np.zeros((2, 1)),
        np.array([[1.0, 0.0]]),
        False,
        L_true=np.array([[2.0, 0.0]]),
        L_false=np.array([[0.0, 1.0]]),
    ),
    # n = 0: every property holds vacuously.
    Case(
        "empty",
        np.zeros((0, 0)),
        np.zeros((0, 0)),
        np.zeros((0, 0)),
        np.zeros((0, 0)),
        True,
        _yes(impulse_free=True, stable=True, admissible=True, index=0),
        (),
        L_true=np.zeros((1, 0)),
    ),
]
REGULAR = [c for c in CATALOGUE if c.regular]
IRREGULAR = [c for c in CATALOGUE if not c.regular]


def _id(case):
    return case.name


# Thesis example 4.1.3.
TE = np.diag([1.0, 1.0, 1.0, 0.0])
TA = np.array(
    [[-3.0, 2.0, 1.0, 1.0], [1.0, -2.0, 1.0, -2.0], [3.0, 0.0, 1.0, -0.5], [-1.0, -2.0, 0.0, 1.0]]
)
TB = np.array([[1.0, 0.0], [0.5, -1.0], [0.0, 1.0], [0.0, 0.0]])
TC = np.eye(4)[[0, 1, 3]]
TL = np.array([[-8.95, -26.07, 12.1, -4.85], [1.71, 1.31, -3.51, -0.16]])
# Hand reduction: the last row 0 = -x1 - 2 x2 + x4 gives x4 = x1 + 2 x2; substituting
# into the first three rows gives x' = A_s x + B_s u on (x1, x2, x3):
TA_SLOW = np.array([[-2.0, 4.0, 1.0], [-1.0, -6.0, 1.0], [2.5, -1.0, 1.0]])
TB_SLOW = TB[:3]


def _assert_documented_order(poles):
    """`finite_poles` returns its poles sorted by real part, then imaginary part (real parts
    within ~1e-9 relative count as equal): checked as a property, with that tolerance."""
    z = np.asarray(poles)
    scale = max(1.0, float(np.max(np.abs(z), initial=0.0)))
    for a, b in zip(z[:-1], z[1:]):
        assert b.real >= a.real - 2e-9 * scale, poles
        if abs(b.real - a.real) <= 1e-12 * scale:  # a tie (a conjugate pair): by imaginary part
            assert b.imag >= a.imag, poles


def _dual(c: Case) -> fojax.DescriptorSystem:
    return fojax.DescriptorSystem(c.E.T, c.A.T, c.C.T, c.B.T)


# ----------------------------------------------------------------------------- catalogue


def test_catalogue_size_and_coverage():
    assert len(CATALOGUE) >= 12
    for key in OBS + CTRL + ("impulse_free", "stable", "detectable", "stabilizable"):
        values = {c.expect[key] for c in REGULAR}
        assert values == {True, False}, key  # every notion is exercised both ways
    assert any(c.L_false is not None for c in CATALOGUE)


@pytest.mark.parametrize("case", CATALOGUE, ids=_id)
def test_regularity(case):
    assert fojax.analysis.is_regular(case.sys()) is case.regular
    assert fojax.analysis.is_regular(case.E, case.A) is case.regular
    # oracle: a regular pencil is invertible at a generic point, a singular one nowhere
    n = case.E.shape[0]
    s0 = 0.6180339887 + 1.4142135624j
    assert bool(np.linalg.matrix_rank(s0 * case.E - case.A) == n) is case.regular


@pytest.mark.parametrize("case", REGULAR, ids=_id)
def test_pencil_properties(case):
    s = case.sys()
    ex = case.expect
    assert fojax.analysis.is_impulse_free(s) is ex["impulse_free"]
    assert fojax.analysis.is_stable(s) is ex["stable"]
    assert fojax.analysis.is_admissible(s) is ex["admissible"]
    assert fojax.analysis.nilpotency_index(s) == ex["index"]
    poles = fojax.analysis.finite_poles(s)
    assert poles.dtype == np.complex128
    assert_eigenvalues_match(poles, case.poles, atol=1e-10)
    _assert_documented_order(poles)
    # deg det(sE - A) = rank E exactly when impulse-free (thesis §2.1.2, item 2)
    assert (len(poles) == int(np.linalg.matrix_rank(case.E))) is ex["impulse_free"]
    _check_against_rank_sequences(case.E, case.A)


def _check_against_rank_sequences(E, A):
    """Independent oracle: ranks of [[E,0],[A,E]] and of the block Toeplitz T_k."""
    n = E.shape[0]
    p = as_pencil(E, A)
    n1, _, index = kernel_chain(p, None, "test")
    assert fojax.analysis.nilpotency_index(E, A) == index
    assert len(fojax.analysis.finite_poles(E, A)) == n1
    if n:
        T1 = np.block([[E, np.zeros((n, n))], [A, E]])
        by_rank = np.linalg.matrix_rank(T1) == n + np.linalg.matrix_rank(E)
        assert fojax.analysis.is_impulse_free(E, A) is bool(by_rank)


@pytest.mark.parametrize("case", REGULAR, ids=_id)
def test_observability_controllability(case):
    s = case.sys()
    for key, fn in HOST.items():
        assert fn(s) is case.expect[key], key


@pytest.mark.parametrize("case", REGULAR, ids=_id)
def test_duality_and_hierarchy(case):
    s, d = case.sys(), _dual(case)
    for o, c in zip(OBS, CTRL):
        assert HOST[c](s) is HOST[o](d)
        assert HOST[o](s) is HOST[c](d)
    assert fojax.analysis.is_stabilizable(s) is fojax.analysis.is_detectable(d)
    # C => S => R, S = R and I
    for kind in (OBS, CTRL):
        c_, r_, i_, s_ = (HOST[k](s) for k in kind)
        assert s_ == (r_ and i_)
        assert (not c_) or s_
    # detectable without the impulse condition is implied by the full one
    if fojax.analysis.is_detectable(s):
        assert fojax.analysis.is_detectable(s, impulse=False)


@pytest.mark.parametrize(
    "case", [c for c in CATALOGUE if c.L_true is not None or c.L_false is not None], ids=_id
)
def test_functional_observability(case):
    s = case.sys()
    if case.L_true is not None:
        assert fojax.analysis.is_functionally_observable(s, case.L_true)
    if case.L_false is not None:
        assert not fojax.analysis.is_functionally_observable(s, case.L_false)


def test_functional_observability_automatic_when_impulse_free(rng):
    # rank [E; E^perp A] = n for impulse-free pencils, so Assumption 1 holds for any L.
    for c in REGULAR:
        if c.expect["impulse_free"] and c.E.shape[0]:
            L = rng.standard_normal((2, c.E.shape[0]))
            assert fojax.analysis.is_functionally_observable(c.sys(), L)
    with pytest.raises(fojax.errors.ShapeError, match="L has shape"):
        fojax.analysis.is_functionally_observable(CATALOGUE[0].sys(), np.ones((1, 3)))


@pytest.mark.parametrize("case", IRREGULAR, ids=_id)
def test_irregular_systems_give_typed_errors(case):
    s = case.sys()
    assert not fojax.analysis.is_admissible(s)
    fns = [
        fojax.analysis.finite_poles,
        fojax.analysis.nilpotency_index,
        fojax.analysis.is_impulse_free,
        fojax.analysis.is_stable,
        fojax.analysis.weierstrass_form,
        *HOST.values(),
    ]
    for fn in fns:
        with pytest.raises(fojax.errors.IrregularSystemError, match=r"pencil sE - A is singular"):
            fn(s)
    rep = fojax.structure_report(s, case.L_true)
    assert not rep.regular and rep.finite_poles is None and rep.c_observable is None
    assert rep.functionally_observable is True
    assert "IRREGULAR" in rep.verdict and "IRREGULAR" in str(rep)


# ----------------------------------------------------------------------------- oracles


def _scipy_finite(E, A):
    w = sla.eigvals(A, E)
    return w[np.isfinite(w) & (np.abs(w) < 1e8)]


@pytest.mark.parametrize("case", [c for c in REGULAR if c.E.size], ids=_id)
def test_finite_poles_match_scipy_on_catalogue(case):
    assert_eigenvalues_match(fojax.analysis.finite_poles(case.E, case.A), _scipy_finite(case.E, case.A), atol=1e-9)


def test_finite_poles_match_scipy_random(rng):
    # Random E of rank r and random A: generically regular, index 1, with r finite poles.
    for n, r in [(3, 2), (5, 3), (6, 6), (4, 1)]:
        U, V = rng.standard_normal((2, n, n))
        E = U @ np.diag([1.0] * r + [0.0] * (n - r)) @ V
        A = rng.standard_normal((n, n))
        ours = fojax.analysis.finite_poles(E, A)
        assert len(ours) == r
        assert_eigenvalues_match(ours, _scipy_finite(E, A), rtol=1e-8, atol=1e-9)
        assert fojax.analysis.nilpotency_index(E, A) == (0 if r == n else 1)


def test_poles_of_transformed_impulsive_pencil(rng):
    # U (E0, A0) V with E0 = diag(1, 1, J2), A0 = [[-1, 3], [0, 2]] (+) I: same poles
    # {-1, 2} (upper triangular slow block), index 2, whatever U and V.
    E0 = np.zeros((4, 4))
    E0[0, 0] = E0[1, 1] = E0[2, 3] = 1.0
    A0 = np.diag([-1.0, 2.0, 1.0, 1.0])
    A0[0, 1] = 3.0
    U, V = rng.standard_normal((2, 4, 4))
    E, A = U @ E0 @ V, U @ A0 @ V
    assert_eigenvalues_match(fojax.analysis.finite_poles(E, A), [-1.0, 2.0], atol=1e-9)
    assert fojax.analysis.nilpotency_index(E, A) == 2
    assert not fojax.analysis.is_impulse_free(E, A)


def test_poles_robust_for_transformed_index3_pencil(rng):
    # U (E0, A0) V with slow part diag(-1, -2) and a 3x3 shift N (index 3). A plain QZ
    # perturbs the index-3 infinite eigenvalue by O(eps^(1/3)) and returns spurious
    # huge "finite" eigenvalues; the deflation must return exactly {-2, -1}.
    E0 = np.zeros((5, 5))
    E0[0, 0] = E0[1, 1] = E0[2, 3] = E0[3, 4] = 1.0
    A0 = np.diag([-1.0, -2.0, 1.0, 1.0, 1.0])
    U, V = np.random.default_rng(5).standard_normal((2, 5, 5))
    E, A = U @ E0 @ V, U @ A0 @ V
    naive = sla.eigvals(A, E)
    assert np.sum(np.isfinite(naive)) > 2  # the pitfall is real for this pencil
    assert_eigenvalues_match(fojax.analysis.finite_poles(E, A), [-2.0, -1.0], atol=1e-9)
    assert fojax.analysis.nilpotency_index(E, A) == 3
    _check_against_rank_sequences(E, A)
    w = fojax.analysis.weierstrass_form(E, A)
    assert w.residuals["E"] < 1e-10 and w.residuals["A"] < 1e-10
    assert np.all(np.linalg.matrix_power(w.N, 3) == 0)


def test_thesis_example_4_1_3():
    s = fojax.DescriptorSystem(TE, TA, TB, TC)
    poles = fojax.analysis.finite_poles(s)
    # Thesis: 1.79, -4.4 -+ 1.72i (brief: 1.795, -4.397 -+ 1.717i).
    assert_eigenvalues_match(poles, [-4.397 - 1.717j, -4.397 + 1.717j, 1.795], atol=6e-4)
    # independent: the hand-reduced ODE
    assert_eigenvalues_match(poles, np.linalg.eigvals(TA_SLOW), atol=1e-10)
    closed = fojax.analysis.finite_poles(TE, TA + TB @ TL)
    # Thesis prints -39.78 (truncated); the value is -39.7897.
    assert_eigenvalues_match(closed, [-39.79, -1.698 - 1.991j, -1.698 + 1.991j], atol=6e-4)
    assert_eigenvalues_match(
        closed,
        np.linalg.eigvals(TA_SLOW + TB_SLOW @ (TL[:, :3] + TL[:, 3:] @ [[1.0, 2.0, 0.0]])),
        atol=1e-9,
    )
    assert fojax.analysis.is_impulse_free(s) and not fojax.analysis.is_stable(s) and not fojax.analysis.is_admissible(s)
    assert fojax.analysis.is_admissible(TE, TA + TB @ TL)
    assert fojax.analysis.nilpotency_index(s) == 1
    # measuring x1, x2, x4 with E's rows e1..e3: rank[E; C] = 4 -> C-observable
    assert fojax.analysis.is_c_observable(s)
    # rank[E, B] = 3 (B's last row is zero) -> not C-controllable; R-controllability is
    # controllability of the hand-reduced ODE (Kalman rank test):
    kalman = np.hstack([np.linalg.matrix_power(TA_SLOW, k) @ TB_SLOW for k in range(3)])
    assert fojax.analysis.is_r_controllable(s) is bool(np.linalg.matrix_rank(kalman) == 3)
    assert not fojax.analysis.is_c_controllable(s)
    assert fojax.analysis.is_stabilizable(s)  # the thesis's L stabilizes it
    assert fojax.analysis.is_functionally_observable(s, TL)


def test_is_stable_margin_and_axis():
    s = CATALOGUE[0].sys()  # poles -1, -2
    assert fojax.analysis.is_stable(s, margin=0.5)
    assert not fojax.analysis.is_stable(s, margin=1.5)
    # a pole exactly on the axis (x' = 0) is not stable
    assert not fojax.analysis.is_stable(np.eye(1), np.zeros((1, 1)))
    assert not fojax.analysis.is_stable(np.diag([1.0, 0.0]), np.array([[0.0, 1.0], [0.0, 1.0]]))


def test_nilpotency_index_conventions():
    assert fojax.analysis.nilpotency_index(np.eye(2), -np.eye(2)) == 0  # ODE
    assert fojax.analysis.nilpotency_index(np.diag([1.0, 0.0]), -np.eye(2)) == 1  # N = 0
    assert fojax.analysis.nilpotency_index(J2, I2) == 2
    assert fojax.analysis.nilpotency_index(np.diag([1.0, 1.0, 1.0], 1), np.eye(4)) == 4


# ----------------------------------------------------------------------------- Weierstrass


def _weierstrass_cases(rng):
    out = [(c.name, c.E, c.A, c.B, c.C) for c in REGULAR]
    E0 = np.zeros((4, 4))
    E0[0, 0] = E0[1, 1] = E0[2, 3] = 1.0
    A0 = np.diag([-1.0, 2.0, 1.0, 1.0])
    A0[0, 1] = 3.0
    U, V = rng.standard_normal((2, 4, 4))
    out.append(("transformed_index2", U @ E0 @ V, U @ A0 @ V, U[:, :1], V[:1]))
    W_, Z_ = rng.standard_normal((2, 5, 5))
    E1 = np.zeros((5, 5))
    E1[0, 0] = E1[1, 2] = E1[2, 3] = 1.0  # slow 1x1 + 4x4 shift (index 4)
    E1[3, 4] = 1.0
    A1 = np.eye(5)
    A1[0, 0] = -0.5
    out.append(("transformed_index4", W_ @ E1 @ Z_, W_ @ A1 @ Z_, W_[:, :2], Z_[:1]))
    out.append(("thesis", TE, TA, TB, TC))
    return out


def test_weierstrass_form(rng):
    for name, E, A, B, C in _weierstrass_cases(rng):
        w = fojax.analysis.weierstrass_form(fojax.DescriptorSystem(E, A, B, C))
        n = E.shape[0]
        poles = fojax.analysis.finite_poles(E, A)
        assert w.n1 == len(poles) and w.n1 + w.n2 == n, name
        assert w.index == fojax.analysis.nilpotency_index(E, A), name
        tE = sla.block_diag(np.eye(w.n1), w.N) if n else np.zeros((0, 0))
        tA = sla.block_diag(w.A1, np.eye(w.n2)) if n else np.zeros((0, 0))
        assert np.max(np.abs(w.P @ E @ w.Q - tE), initial=0.0) <= 1e-10, name
        assert np.max(np.abs(w.P @ A @ w.Q - tA), initial=0.0) <= 1e-10, name
        np.testing.assert_allclose(w.P @ B, np.vstack([w.B1, w.B2]), atol=1e-12)
        np.testing.assert_allclose(C @ w.Q, np.hstack([w.C1, w.C2]), atol=1e-12)
        assert_eigenvalues_match(np.linalg.eigvals(w.A1), poles, atol=1e-9)
        if w.n2:
            assert np.all(np.linalg.matrix_power(w.N, w.index) == 0), name  # nilpotent
            if w.index >= 2:
                assert np.any(np.linalg.matrix_power(w.N, w.index - 1) != 0), name
            else:
                assert np.all(w.N == 0)
        if n:
            assert np.linalg.cond(w.P) < 1e8 and np.linalg.cond(w.Q) < 1e8
        assert max(w.residuals.values()) <= 1e-10


# ----------------------------------------------------------------------------- E perp


def test_e_perp(rng):
    U, V = rng.standard_normal((2, 5, 5))
    E = U @ np.diag([3.0, 1.0, 0.5, 0.0, 0.0]) @ V
    Ep = fojax.analysis.e_perp(E)
    assert Ep.shape == (2, 5)
    np.testing.assert_allclose(Ep @ E, 0.0, atol=1e-12)
    np.testing.assert_allclose(Ep @ Ep.T, np.eye(2), atol=1e-12)
    assert fojax.analysis.e_perp(np.eye(3)).shape == (0, 3)
    assert fojax.analysis.e_perp(np.zeros((0, 0))).shape == (0, 0)
    np.testing.assert_allclose(np.abs(fojax.analysis.e_perp(TE)), [[0.0, 0.0, 0.0, 1.0]])
    assert fojax.analysis.e_perp(fojax.DescriptorSystem(TE, TA)).shape == (1, 4)


# ----------------------------------------------------------------------------- certificate


def _check_certificate(cert, E, A):
    P = cert.P
    EtP = E.T @ P
    np.testing.assert_allclose(EtP, EtP.T, atol=1e-10 * np.linalg.norm(P))
    assert np.linalg.eigvalsh((EtP + EtP.T) / 2)[0] >= -1e-9 * np.linalg.norm(P)
    assert np.linalg.eigvalsh(A.T @ P + P.T @ A)[-1] < 0
    assert cert.status == "optimal" and cert.lyapunov_margin > 1e-9


def test_admissibility_certificate_verified():
    c = CATALOGUE[3]  # index1_admissible
    cert = fojax.analysis.admissibility_certificate(c.sys())
    _check_certificate(cert, c.E, c.A)
    closed = TA + TB @ TL
    cert = fojax.analysis.admissibility_certificate(TE, closed)
    _check_certificate(cert, TE, closed)
    assert "optimal" in repr(cert)


@pytest.mark.parametrize(
    "E,A",
    [(TE, TA), (J2, -I2), (np.diag([1.0, 0.0]), np.diag([1.0, 0.0]))],
    ids=["unstable_thesis", "impulsive", "irregular"],
)
def test_admissibility_certificate_infeasible(E, A):
    with pytest.raises(
        fojax.errors.LMIInfeasibleError, match="solver status 'infeasible.*not admissible"
    ) as info:
        fojax.analysis.admissibility_certificate(E, A)
    assert info.value.status.startswith("infeasible")


def test_admissibility_certificate_rejects_inaccurate_and_bad_verification():
    c = CATALOGUE[3]
    with pytest.raises(fojax.errors.SolverStoppedShortError, match=r"was not solved.*raise max_iters") as info:
        fojax.analysis.admissibility_certificate(c.sys(), max_iters=2)
    assert info.value.status != "optimal"
    # An absurd verification margin must fail the float64 re-check, with the numbers.
    with pytest.raises(fojax.errors.DesignVerificationError, match=r"Lyapunov margin .* < 1\.0e\+01"):
        fojax.analysis.admissibility_certificate(c.sys(), verify_rtol=10.0)


def test_admissibility_certificate_empty():
    cert = fojax.analysis.admissibility_certificate(np.zeros((0, 0)), np.zeros((0, 0)))
    assert cert.status == "trivial" and cert.P.shape == (0, 0)


# ----------------------------------------------------------------------------- report


def test_structure_report_thesis():
    rep = fojax.structure_report(fojax.DescriptorSystem(TE, TA, TB, TC), TL)
    assert rep.regular and rep.rank_E == 3 and rep.index == 1 and rep.n_finite == 3
    assert rep.impulse_free and not rep.stable and not rep.admissible
    assert rep.c_observable and not rep.c_controllable and rep.stabilizable
    assert rep.functionally_observable and rep.functional_ranks == (4, 4)
    np.testing.assert_allclose(rep.max_real_part, 1.79487, atol=1e-5)
    text = str(rep)
    assert "rank E = 3" in text and "1.79487" in text and "Verdict: NOT admissible" in text
    assert "unstable" in rep.verdict


@pytest.mark.parametrize("case", REGULAR, ids=_id)
def test_structure_report_matches_functions(case):
    rep = fojax.structure_report(case.sys(), case.L_false if case.L_false is not None else None)
    for key, value in case.expect.items():
        assert getattr(rep, key) == value, key
    assert str(rep).startswith("Descriptor system")
    if case.L_false is not None:
        assert rep.functionally_observable is False and "FAILS" in rep.verdict


# ----------------------------------------------------------------------------- inputs


def test_input_errors():
    with pytest.raises(fojax.errors.InputError, match=r"expects a fojax.DescriptorSystem or the two"):
        fojax.analysis.finite_poles(TE)
    with pytest.raises(fojax.errors.InputError, match="needs a fojax.DescriptorSystem"):
        fojax.analysis.is_c_observable((TE, TA))
    with pytest.raises(fojax.errors.ShapeError, match="A has shape"):
        fojax.analysis.is_regular(TE, np.ones((3, 3)))
    with pytest.raises(fojax.errors.InputError, match="traced JAX value"):
        jax.jit(lambda E, A: fojax.analysis.is_regular(E, A))(TE, TA)


# ----------------------------------------------------------------------------- traced


@pytest.fixture(scope="module")
def batch():
    r = np.random.default_rng(7)
    k = 64
    E = np.repeat(TE[None], k, axis=0)
    E[:, :3, :3] *= 1.0 + 0.05 * r.standard_normal((k, 1, 1))
    A = TA[None] + 0.1 * r.standard_normal((k, 4, 4))
    return E, A


def test_traced_index1_screens_agree_with_host(batch):
    E, A = batch
    margin = jax.jit(jax.vmap(lambda e, a: fojax.analysis.impulse_free_margin(e, a, rank_E=3)))(E, A)
    stab = jax.jit(jax.vmap(lambda e, a: fojax.analysis.stability_margin_index1(e, a, rank_E=3)))(E, A)
    gap = jax.jit(jax.vmap(lambda e, a: fojax.analysis.functional_observability_gap(e, a, TC, TL, 3)))(E, A)
    s0 = 0.3 + 0.7j
    reg = jax.jit(jax.vmap(lambda e, a: fojax.analysis.regular_at(e, a, s0)))(E, A)
    for i in range(E.shape[0]):
        # E = diag(*, *, *, 0): null spaces are e4 on both sides, so A22 = A[3, 3].
        np.testing.assert_allclose(margin[i], abs(A[i, 3, 3]), rtol=1e-12)
        assert fojax.analysis.is_impulse_free(E[i], A[i]) is bool(
            margin[i] > 1e-10 * np.linalg.norm(A[i], 2)
        )
        poles = fojax.analysis.finite_poles(E[i], A[i])
        np.testing.assert_allclose(stab[i], poles.real.max(), rtol=1e-9, atol=1e-10)
        assert fojax.analysis.is_stable(E[i], A[i]) is bool(stab[i] < 0)
        assert gap[i] < 1e-10
        assert bool(reg[i]) is fojax.analysis.is_regular(E[i], A[i])
    assert bool(jnp.all(reg))


def test_traced_functional_gap_and_regularity_negative_cases():
    r = np.random.default_rng(3)
    k = 64
    c = CATALOGUE[8]  # index2_with_slow_part
    A = np.repeat(c.A[None], k, axis=0)
    A[:, :2, :] += 0.1 * r.standard_normal((k, 2, 3))  # rows 1-2 free
    A[:, 2, 2] = 1.0 + 0.1 * r.standard_normal(k)  # keep E^perp A = a33 e3'
    gap = jax.jit(
        jax.vmap(
            lambda a, L: fojax.analysis.functional_observability_gap(c.E, a, c.C, L, rank_E=2),
            in_axes=(0, None),
        )
    )
    g_false = gap(A, c.L_false)
    g_true = gap(A, c.L_true)
    for i in range(k):
        s = fojax.DescriptorSystem(c.E, A[i], c.B, c.C)
        assert not fojax.analysis.is_functionally_observable(s, c.L_false)
        assert fojax.analysis.is_functionally_observable(s, c.L_true)
        np.testing.assert_allclose(g_false[i], 1.0, atol=1e-12)  # e2 is orthogonal to Gamma
        assert g_true[i] < 1e-10
        assert fojax.analysis.impulse_free_margin(c.E, A[i]) < 1e-12  # impulsive: A22 = 0
        assert not fojax.analysis.is_impulse_free(c.E, A[i])
    # irregular pencils: singular at every s
    d = np.abs(1.0 + 0.1 * r.standard_normal(k))
    Ei = np.zeros((k, 2, 2))
    Ei[:, 0, 0] = d
    reg = jax.jit(jax.vmap(lambda e: fojax.analysis.regular_at(e, e, 0.3 + 0.7j)))(Ei)
    marg = jax.vmap(lambda e: fojax.analysis.regularity_margin_at(e, e, 0.3 + 0.7j))(Ei)
    assert not bool(jnp.any(reg)) and float(jnp.max(marg)) < 1e-15
    assert not any(fojax.analysis.is_regular(Ei[i], Ei[i]) for i in range(k))


def test_traced_needs_static_rank():
    with pytest.raises(fojax.errors.InputError, match="Pass rank_E="):
        jax.jit(fojax.analysis.impulse_free_margin)(TE, TA)
    # concrete inputs: rank inferred on the host
    np.testing.assert_allclose(fojax.analysis.impulse_free_margin(TE, TA), 1.0)
    np.testing.assert_allclose(fojax.analysis.impulse_free_margin(np.eye(2), TA[:2, :2]), np.inf)
    np.testing.assert_allclose(
        fojax.analysis.stability_margin_index1(TE, TA), fojax.analysis.finite_poles(TE, TA).real.max(), rtol=1e-10
    )
    assert fojax.analysis.stability_margin_index1(np.zeros((2, 2)), -I2) == -np.inf
    np.testing.assert_allclose(
        fojax.analysis.stability_margin_index1(I2, np.diag([-1.0, -2.0])), -1.0, rtol=1e-12
    )
