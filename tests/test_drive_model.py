"""`fojax.models.flexible_drive` (issue 14's second model, not from the thesis) against an
independent derivation.

Oracles:
- the ODE written directly from Newton's and Kirchhoff's laws with the algebraic variables
  substituted by hand ($i = (u - K_b\\omega_m)/R$, $\\tau_1 = k_1\\varphi_1 + c_1(\\omega_m/N - \\omega_1)$,
  $\\tau_2 = k_2\\varphi_2 + c_2(\\omega_1 - \\omega_2)$): its eigenvalues (NumPy) are the finite
  poles of the pencil (SciPy QZ), matched one to one, at the defaults and at other parameters;
- the closed-form steady state for a constant voltage (all speeds equal after the gear,
  $\\tau_2 = b_2\\omega_2$): equals $L(-A)^{-1}B\\,u$ of the descriptor model;
- index 1 by closed form: the algebraic block is diag(-R, -1, -1), so rank E = 5 finite poles
  and `fojax.analysis.nilpotency_index` = 1;
- exact ranks in rational arithmetic (sympy) for the observer structure's rank conditions on
  the badly scaled twin.
"""

import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.linalg as sl
from helpers import assert_eigenvalues_match

import fojax
import fojax.models as fm


#: the model's per-unit defaults (the hand-derived ODE below is checked at these values)
DRIVE_PARAMS = dict(fm.flexible_drive().params)


ROOT = Path(__file__).resolve().parents[1]


def _finite_poles(A, E):
    w = sl.eigvals(np.asarray(A), np.asarray(E))
    return w[np.isfinite(w)]


def _hand_ode(p):
    """(A_ode, b_ode) of x = (w_m, phi_1, w_1, phi_2, w_2) from the physics, algebraic variables substituted."""
    Jm, bm, Kt, Kb, R, N = p["J_m"], p["b_m"], p["K_t"], p["K_b"], p["R"], p["N"]
    k1, c1, J1, b1, k2, c2, J2, b2 = p["k_1"], p["c_1"], p["J_1"], p["b_1"], p["k_2"], p["c_2"], p["J_2"], p["b_2"]
    # tau_1 = [c1/N, k1, -c1, 0, 0] . x ; tau_2 = [0, 0, c2, k2, -c2] . x ; i = (u - Kb w_m) / R
    tau1 = np.array([c1 / N, k1, -c1, 0, 0])
    tau2 = np.array([0, 0, c2, k2, -c2])
    e = np.eye(5)
    A = np.vstack([
        (-Kt * Kb / R * e[0] - bm * e[0] - tau1 / N) / Jm,
        e[0] / N - e[2],
        (tau1 - tau2 - b1 * e[2]) / J1,
        e[2] - e[4],
        (tau2 - b2 * e[4]) / J2,
    ])
    b = np.array([Kt / R / Jm, 0, 0, 0, 0])
    return A, b


OTHER = dict(J_m=0.3, b_m=0.02, K_t=0.7, K_b=0.9, R=2.5, N=5.0, k_1=10.0, c_1=0.3, J_1=2.0, b_1=0.1,
             k_2=0.8, c_2=0.01, J_2=4.0, b_2=0.2)


@pytest.mark.parametrize("params", [{}, OTHER], ids=["defaults", "other"])
def test_finite_poles_are_the_hand_reduced_odes(params):
    ex = fm.flexible_drive(**params)
    p = {**DRIVE_PARAMS, **params}
    A_ode, _ = _hand_ode(p)
    poles = _finite_poles(ex.A, ex.E)
    assert poles.size == 5 == np.linalg.matrix_rank(ex.E)  # index 1: rank E finite poles
    assert_eigenvalues_match(poles, np.linalg.eigvals(A_ode), rtol=1e-9)
    assert poles.real.max() < 0  # damped: a study's samples stay bounded
    assert fojax.analysis.nilpotency_index(ex.system) == 1


def test_defaults_poles_as_documented():
    ex = fm.flexible_drive()
    documented = [-0.876, -0.201 + 1.567j, -0.201 - 1.567j, -0.174 + 2.880j, -0.174 - 2.880j]
    assert_eigenvalues_match(_finite_poles(ex.A, ex.E), documented, atol=1e-3, rtol=0.0)


@pytest.mark.parametrize("params", [{}, OTHER], ids=["defaults", "other"])
def test_steady_state_torque_closed_form(params):
    ex = fm.flexible_drive(**params)
    p = {**DRIVE_PARAMS, **params}
    # constant u: w_m = N w, w_1 = w_2 = w; tau_2 = b_2 w; tau_1 = (b_1 + b_2) w;
    # K_t (u - K_b N w) / R = b_m N w + tau_1 / N
    w = p["K_t"] / p["R"] / (p["K_t"] * p["K_b"] * p["N"] / p["R"] + p["b_m"] * p["N"] + (p["b_1"] + p["b_2"]) / p["N"])
    x_ss = np.linalg.solve(-ex.A, ex.B[:, 0])
    np.testing.assert_allclose(ex.L @ x_ss, [p["b_2"] * w], rtol=1e-12)
    np.testing.assert_allclose(x_ss[[0, 2, 4]], [p["N"] * w, w, w], rtol=1e-12)
    # the hand ODE has the same steady state (its B enters through the current)
    A_ode, b_ode = _hand_ode(p)
    np.testing.assert_allclose(np.linalg.solve(-A_ode, b_ode), x_ss[:5], rtol=1e-10, atol=1e-14)


def test_uncertainty_is_the_output_shaft_stiffness():
    a, delta = 0.5, -0.6
    ex = fm.flexible_drive(k_2_uncertainty=a)
    softer = fm.flexible_drive(k_2=DRIVE_PARAMS["k_2"] * (1 + a * delta))
    np.testing.assert_allclose(ex.A + delta * ex.dA, softer.A, rtol=0, atol=1e-15)
    assert np.count_nonzero(ex.dA) == 1
    assert ex.states[int(np.argmax(ex.L[0]))] == "tau_2" and ex.C.shape == (2, 8)


def test_bad_parameters_are_named():
    with pytest.raises(ValueError, match="k_2 must be positive"):
        fm.flexible_drive(k_2=0.0)
    with pytest.raises(TypeError, match="unknown parameters \\['J3'\\]"):
        fm.flexible_drive(J3=1.0)


def test_structure_rank_decisions_are_unit_free():
    """Regression (issue 14): on the drive rescaled by 1e-3…1e3 (`benchmarks/tuning_circuit.py`'s
    twin) the rank conditions of the observer structure were decided on the raw data: rank Γ =
    rank [E; E⊥A; C] came out 7 and the default R failed "rank [R; Γ] = rank Γ". Oracle: exact
    ranks of the twin's own float matrices in rational arithmetic (sympy)."""
    import sympy

    from fojax.design import check_structure, observer_structure

    sys.path.insert(0, str(ROOT / "benchmarks"))
    from lc_filter import rescaled
    from tuning_circuit import DRIVE_TWIN_ROWS, DRIVE_TWIN_STATES

    ex = fm.flexible_drive()
    m = rescaled({k: np.asarray(getattr(ex, k)) for k in ("E", "A", "B", "C", "L", "dA")},
                 DRIVE_TWIN_ROWS, DRIVE_TWIN_STATES)
    # R: z = tau_2 and the two twists, written in the twin's states (rows in the row space of Γ)
    R = np.zeros((3, 8))
    R[0, 7], R[1, 1], R[2, 3] = 1.0, 1.0, 1.0
    R = R @ m["Dc"]
    def exact_rank(M):  # of the float values themselves (Rational(float) is exact)
        return sympy.Matrix([[sympy.Rational(float(v)) for v in row] for row in M]).rank()

    gamma = np.vstack([m["E"], m["A"][5:], m["C"]])  # E⊥ = the algebraic rows (rows 6-8 of E are zero)
    assert exact_rank(gamma) == 8 and exact_rank(np.vstack([R, gamma])) == 8
    s = observer_structure(m["E"], m["A"], m["B"], m["C"], m["L"], R, q1=3)
    check_structure(s)  # raised RankConditionError (rank [R; E; Ψ] = 8 but rank [E; Ψ] = 7) before
