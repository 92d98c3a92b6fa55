"""Design refuses what analysis refuses (issue 15, item 3).

Oracles, independent of fojax: exact determinants and degrees with sympy
(det(sE - A) ≡ 0 for an irregular pencil; deg det(sE - A) < rank E for an impulsive
one), numpy determinants at random complex points s, Dai's rank test
rank [[E, 0], [A, E]] = n + rank E for impulse-freeness (numpy.linalg.matrix_rank), and
the design conditions re-evaluated with numpy (P T E + Q Ψ = L: the estimate equals z).
Every verdict is also compared with `fojax.analysis`.
"""

import numpy as np
import pytest
import sympy

import fojax
from fojax.design import (
    check_functional_observability,
    design_fault_estimator,
    design_finite_time_observer,
    design_functional_observer,
    design_ts_observer,
    design_unknown_input_observer,
)


# det(sE - A) = det([[s + 1, 0], [0, 0]]) ≡ 0: x2 appears in no equation.
E_IRR = np.array([[1.0, 0.0], [0.0, 0.0]])
A_IRR = np.array([[-1.0, 0.0], [0.0, 0.0]])
B_IRR = np.array([[1.0], [1.0]])
C_IRR = np.array([[0.0, 1.0], [1.0, 0.0]])
L_IRR = np.array([[1.0, 1.0]])

# A regular neighbour (0 = x2 + u closes the model): the same data designs fine.
A_REG = np.array([[-1.0, 0.0], [0.0, 1.0]])

# Thesis example 4.1.3 (regular, index 1).
EX = fojax.models.example_4_1_3()
E413, A413, B413, C413 = (np.asarray(x) for x in (EX.system.E, EX.system.A, EX.system.B, EX.system.C))
L413 = np.array([[-8.95, -26.07, 12.1, -4.85], [1.71, 1.31, -3.51, -0.16]])


def sympy_det(E, A):
    s = sympy.symbols("s")
    exact = [[sympy.Rational(str(v)) for v in row] for row in np.asarray(E).tolist()]
    M = s * sympy.Matrix(exact) - sympy.Matrix([[sympy.Rational(str(v)) for v in row] for row in np.asarray(A).tolist()])
    return sympy.Poly(sympy.expand(M.det()), s)


def det_at_random_points(E, A, k=5, seed=0):
    rng = np.random.default_rng(seed)
    s = rng.standard_normal(k) + 1j * rng.standard_normal(k)
    return np.array([abs(np.linalg.det(z * E - A)) for z in s])


def dai_impulse_free(E, A):
    n = E.shape[0]
    T = np.block([[E, np.zeros((n, n))], [A, E]])
    return np.linalg.matrix_rank(T) == n + np.linalg.matrix_rank(E)


def test_oracles_on_the_fixtures():
    assert sympy_det(E_IRR, A_IRR).is_zero
    assert np.all(det_at_random_points(E_IRR, A_IRR) == 0.0)
    assert not fojax.analysis.is_regular(E_IRR, A_IRR)
    p = sympy_det(E_IRR, A_REG)
    assert not p.is_zero and p.degree() == 1 == np.linalg.matrix_rank(E_IRR)
    assert fojax.analysis.is_regular(E_IRR, A_REG) and fojax.analysis.is_impulse_free(E_IRR, A_REG)


IRR = fojax.DescriptorSystem(E_IRR, A_IRR, B_IRR, C_IRR)
ENTRY_POINTS = {
    "generalized": lambda: design_functional_observer(IRR, L_IRR, kind="generalized"),
    "PI": lambda: design_functional_observer(IRR, L_IRR, kind="PI"),
    "proportional": lambda: design_functional_observer(IRR, L_IRR, kind="proportional"),
    "fault estimator": lambda: design_fault_estimator(IRR, L_IRR, Fa=np.array([[1.0], [0.0]])),
    "finite time": lambda: design_finite_time_observer(IRR, L_IRR, h=1.0),
    "unknown input": lambda: design_unknown_input_observer(IRR, np.array([[1.0], [0.0]]), L_IRR),
}


@pytest.mark.parametrize("name", list(ENTRY_POINTS))
def test_irregular_pencil_is_refused_by_every_design(name):
    """On main every one of these returned a 'verified' observer (or failed later, untyped
    as to the cause); now each raises IrregularSystemError with the failed rank decision."""
    with pytest.raises(fojax.errors.IrregularSystemError, match="is not regular") as ei:
        ENTRY_POINTS[name]()
    msg = str(ei.value)
    assert "smallest singular value 0.0e+00" in msg and "threshold 1.0e-10" in msg
    assert ei.value.property == "regularity"


def test_the_regular_neighbour_still_designs():
    """Not vacuous: closing the model (0 = x2 + u) gives a verified observer."""
    sys = fojax.DescriptorSystem(E_IRR, A_REG, B_IRR, C_IRR)
    d = design_functional_observer(sys, L_IRR, kind="proportional")
    assert d.report.passed


def test_ts_design_refuses_an_irregular_rule():
    A = np.stack([A_REG, A_IRR])
    B = np.stack([B_IRR, B_IRR])
    ts = fojax.TakagiSugenoSystem(
        E_IRR, A, B, C_IRR, fojax.plant.SectorMembership(fojax.plant.OutputPremise(0), -1.0, 1.0)
    )
    assert [fojax.analysis.is_regular(E_IRR, Ai) for Ai in A] == [True, False]
    with pytest.raises(fojax.errors.IrregularSystemError, match=r"design_ts_observer: rule 2 \(E, A_2\) is not regular"):
        design_ts_observer(ts, L_IRR)


# ------------------------------------------------------------------ impulsive closed loops

# Index 2 (tests/test_design.py): x1' = -x1 + x2/2 + u, x3' = x2, 0 = x3 + u.
E_IMP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, 0.0]])
A_IMP = np.array([[-1.0, 0.5, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
B_IMP = np.array([[1.0], [0.0], [1.0]])
C_IMP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


def test_ftc_refuses_a_given_feedback_with_an_impulsive_or_irregular_loop():
    """The FTC schemes need (E, A + BL) admissible; a given L is checked before any design."""
    sys = fojax.DescriptorSystem(E_IMP, A_IMP, B_IMP, C_IMP)
    L0 = np.zeros((1, 3))
    p = sympy_det(E_IMP, A_IMP)
    assert p.degree() == 1 < np.linalg.matrix_rank(E_IMP)  # impulsive (Dai)
    assert not dai_impulse_free(E_IMP, A_IMP)
    assert fojax.analysis.nilpotency_index(E_IMP, A_IMP) == 2
    for design in (fojax.control.design_sensor_ftc, fojax.control.design_actuator_ftc,
                   fojax.control.design_simultaneous_ftc):
        kw = {"Fa": B_IMP} if design is not fojax.control.design_sensor_ftc else {}
        with pytest.raises(fojax.errors.ImpulsiveSystemError, match="nilpotency index 2 > 1") as ei:
            design(sys, L=L0, **kw)
        assert ei.value.property == "impulse-freeness" and ei.value.index == 2
        assert design.__name__ in str(ei.value)
    # a feedback that makes the loop irregular: A + BL has a zero row and column
    sys2 = fojax.DescriptorSystem(E_IRR, A_REG, np.array([[0.0], [1.0]]), C_IRR)
    L_bad = np.array([[0.0, -1.0]])
    assert sympy_det(E_IRR, A_REG + np.array([[0.0], [1.0]]) @ L_bad).is_zero
    with pytest.raises(fojax.errors.IrregularSystemError, match="closed loop"):
        fojax.control.design_sensor_ftc(sys2, L=L_bad)


# ------------------------------------------------------------------ huge and tiny entries


@pytest.mark.parametrize("what", ["EAB*1e300", "C*1e300", "L*1e-300", "E*1e-300"])
def test_entries_near_the_double_range_get_a_typed_error(what):
    """On main: E, A, B ~ 1e300 'verified' an observer; C ~ 1e300 gave a wrong
    FunctionalObservabilityError; L ~ 1e-300 a raw ValueError from the default-R search."""
    E, A, B, C, L = E413, A413, B413, C413, L413
    if what == "EAB*1e300":
        E, A, B = E * 1e300, A * 1e300, B * 1e300
    elif what == "C*1e300":
        C = C * 1e300
    elif what == "L*1e-300":
        L = L * 1e-300
    else:
        E = E * 1e-300
    sys = fojax.DescriptorSystem(E, A, B, C)
    assert fojax.analysis.is_regular(sys)  # analysis normalises: regular
    with pytest.raises(fojax.errors.DataRangeError, match="Rescale the model") as ei:
        design_functional_observer(sys, L)
    assert ei.value.name == what[0]
    with pytest.raises(fojax.errors.DataRangeError):
        design_unknown_input_observer(sys, np.eye(4)[:, [2]], L)


def test_a_wrong_observer_is_never_verified_when_C_is_in_tiny_units():
    """C·2^40: on main the design was 'verified' although P T E + Q Ψ - L had norm ~12
    (the common residual scale ‖C‖·‖gains‖ hid it). Either a typed error, or the returned
    observer satisfies condition d. (checked here with numpy) — never a wrong 'verified'."""
    C = C413 * 2.0**40
    sys = fojax.DescriptorSystem(E413, A413, B413, C)
    try:
        d = design_functional_observer(sys, L413)
    except fojax.FojaxError:
        return
    T, s = np.asarray(d.T), d.structure
    Psi = np.vstack([np.asarray(s.Eperp) @ A413, C])
    mats = fojax.design.observer_matrices(s, **d.params, xp=np)
    rd = np.asarray(mats.P[0]) @ T @ E413 + np.asarray(mats.Q[0]) @ Psi - L413
    assert np.linalg.norm(rd, 2) <= 1e-8 * np.linalg.norm(L413, 2)


def test_design_and_analysis_agree_on_functional_observability_under_scaling():
    """The design's check and fojax.analysis.is_functionally_observable give one verdict,
    the unscaled one, for exact power-of-two scalings of E and A (one equation scale), C and
    L up to 2^±40 (on main the design's unnormalised ranks flipped it)."""
    rng = np.random.default_rng(0)
    # an impulsive system where Assumption 1 holds for L_ok and fails for L_bad
    C = np.array([[1.0, 0.0, 0.0]])
    L_ok, L_bad = np.array([[1.0, 0.0, 1.0]]), np.array([[0.0, 1.0, 0.0]])
    for _ in range(40):
        ke, kc, kl = (float(2.0 ** rng.integers(-40, 41)) for _ in range(3))
        E, A, Cs = E_IMP * ke, A_IMP * ke, C * kc
        sys = fojax.DescriptorSystem(E, A, B_IMP * ke, Cs)
        for L, expected in ((L_ok * kl, True), (L_bad * kl, False)):
            assert fojax.analysis.is_functionally_observable(sys, L) is expected
            if expected:
                check_functional_observability(E, A, Cs, L, fojax.analysis.e_perp(E))
            else:
                with pytest.raises(fojax.errors.FunctionalObservabilityError):
                    check_functional_observability(E, A, Cs, L, fojax.analysis.e_perp(E))


def test_solver_exceptions_become_stopped_short_errors(monkeypatch):
    """A solver that raises (SCS: ValueError('ScsWork allocation error!')) gives
    SolverStoppedShortError (nothing shows the LMI infeasible) with the solver's message, the
    problem size and the data magnitude."""
    import cvxpy as cp

    from fojax.design import _lmi  # private: the solver wrapper is tested itself

    X = cp.Variable((2, 2), symmetric=True)
    prob = cp.Problem(cp.Minimize(cp.trace(X)), [X >> 3e5 * np.eye(2)])

    def broken(self, *a, **k):
        raise ValueError("ScsWork allocation error!")

    monkeypatch.setattr(cp.Problem, "solve", broken)
    with pytest.raises(fojax.errors.SolverStoppedShortError, match="ScsWork allocation error!") as ei:
        _lmi.solve(prob, "test LMI", solver="SCS")
    assert ei.value.status == "solver_error"
    assert ei.value.info["variables"] == X.size and ei.value.info["data_magnitude"] == 3e5
    assert "largest data entry 3.0e+05" in str(ei.value) and "enlarge" not in str(ei.value)
    with pytest.raises(fojax.errors.SolverStoppedShortError, match="SCS: solver_error, tolerance 1e-06, ValueError: ScsWork allocation"):
        _lmi.solve(prob, "test LMI")  # auto: Clarabel, then SCS


# ------------------------------------------------------------------ the command line

MODEL = """
name = "irregular"
description = "det(sE - A) = 0 for every s"

[model]
E = [[1, 0], [0, 0]]
A = [[-1, 0], [0, 0]]
B = [[1], [1]]
C = [[0, 1], [1, 0]]
L = [[1, 1]]
x0 = [1, 0]

[[observer]]
name = "po"
kind = "proportional"
region = { disk = { center = -2.0, radius = 1.0 } }
"""


def test_fojax_design_refuses_an_irregular_model(tmp_path, capsys):
    """On main `fojax design` saved a 'verified' observer (exit 0). Now the observer fails
    with the one-line reason naming the property, and nothing verified is saved."""
    import json

    from fojax.cli import main

    path = tmp_path / "irregular.toml"
    path.write_text(MODEL)
    code = main(["design", str(path), "--out", str(tmp_path / "out"), "--name", "run"])
    err = capsys.readouterr().err
    assert code != 0
    assert "IrregularSystemError" in err and "is not regular" in err
    designs = json.loads((tmp_path / "out" / "run" / "designs.json").read_text())["designs"]
    assert [d["status"] for d in designs] == ["failed"]
