"""`fojax.models.two_area_power` (issue 14's third model, not from the thesis) against an
independent derivation.

Oracles:
- the classical 7-state load-frequency-control ODE written by hand (swing equations with
  $\\Delta P_{12} = P_s\\Delta\\delta_{12}$ and $\\Delta P_{ei} = D_i\\Delta\\omega_i \\pm \\Delta P_{12}$
  substituted, governor and turbine lags): its eigenvalues (NumPy) are the finite poles of the
  pencil (SciPy QZ), matched one to one, at the defaults and at other parameters;
- the closed-form steady state for a constant set point (the textbook
  $\\Delta\\omega = \\Delta P_{\\text{ref}}/(\\beta_1 + \\beta_2)$, $\\beta_i = 1/R_i + D_i$):
  equals $(-A)^{-1}Bu$ of the descriptor model;
- index 1 by closed form (the algebraic block has determinant -1): rank E = 7 finite poles and
  `fojax.analysis.nilpotency_index` = 1;
- the uncertainty: $A + \\delta\\,\\Delta A$ is the model rebuilt with $H_1/(1 + a\\delta)$.
"""

import numpy as np
import pytest
import scipy.linalg as sl
from helpers import assert_eigenvalues_match

import fojax
import fojax.models as fm


#: the model's per-unit defaults (the hand-derived ODE below is checked at these values)
POWER_PARAMS = dict(fm.two_area_power().params)


def _finite_poles(A, E):
    w = sl.eigvals(np.asarray(A), np.asarray(E))
    return w[np.isfinite(w)]


def _hand_ode(p):
    """A of x = (w1, d12, w2, Pm1, Pv1, Pm2, Pv2), the algebraic powers substituted by hand."""
    H1, D1, R1, tg1, tt1 = p["H_1"], p["D_1"], p["R_1"], p["tau_g1"], p["tau_t1"]
    H2, D2, R2, tg2, tt2, Ps = p["H_2"], p["D_2"], p["R_2"], p["tau_g2"], p["tau_t2"], p["P_s"]
    return np.array([
        [-D1 / (2 * H1), -Ps / (2 * H1), 0, 1 / (2 * H1), 0, 0, 0],
        [1, 0, -1, 0, 0, 0, 0],
        [0, Ps / (2 * H2), -D2 / (2 * H2), 0, 0, 1 / (2 * H2), 0],
        [0, 0, 0, -1 / tt1, 1 / tt1, 0, 0],
        [-1 / (R1 * tg1), 0, 0, 0, -1 / tg1, 0, 0],
        [0, 0, 0, 0, 0, -1 / tt2, 1 / tt2],
        [0, 0, -1 / (R2 * tg2), 0, 0, 0, -1 / tg2],
    ])


OTHER = dict(H_1=3.0, D_1=1.0, R_1=0.04, tau_g1=0.1, tau_t1=0.4, H_2=6.0, D_2=0.5, R_2=0.08, tau_g2=0.25,
             tau_t2=0.7, P_s=1.2)


@pytest.mark.parametrize("params", [{}, OTHER], ids=["defaults", "other"])
def test_finite_poles_are_the_hand_reduced_odes(params):
    ex = fm.two_area_power(**params)
    poles = _finite_poles(ex.A, ex.E)
    assert poles.size == 7 == np.linalg.matrix_rank(ex.E)  # index 1: rank E finite poles
    assert_eigenvalues_match(poles, np.linalg.eigvals(_hand_ode({**POWER_PARAMS, **params})), rtol=1e-9)
    assert poles.real.max() < 0
    assert fojax.analysis.nilpotency_index(ex.system) == 1


@pytest.mark.parametrize("params", [{}, OTHER], ids=["defaults", "other"])
def test_steady_state_closed_form(params):
    ex = fm.two_area_power(**params)
    p = {**POWER_PARAMS, **params}
    u = 0.1
    w = u / (1 / p["R_1"] + p["D_1"] + 1 / p["R_2"] + p["D_2"])
    pm1, pm2 = u - w / p["R_1"], -w / p["R_2"]
    p12 = pm1 - p["D_1"] * w
    expected = [w, p12 / p["P_s"], w, pm1, pm1, pm2, pm2, p12, pm1, pm2]
    x_ss = np.linalg.solve(-ex.A, ex.B[:, 0] * u)
    np.testing.assert_allclose(x_ss, expected, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(ex.L @ x_ss, [pm1], rtol=1e-12)


def test_uncertainty_is_the_inverse_inertia_of_area_1():
    a, delta = 0.4, -0.7
    ex = fm.two_area_power(inertia_uncertainty=a)
    other = fm.two_area_power(H_1=POWER_PARAMS["H_1"] / (1 + a * delta))
    np.testing.assert_allclose(ex.A + delta * ex.dA, other.A, rtol=0, atol=1e-15)
    assert np.linalg.matrix_rank(ex.dA) == 1 and np.count_nonzero(ex.dA[1:]) == 0
    assert ex.states[int(np.argmax(ex.L[0]))] == "P_m1" and ex.C.shape == (3, 10)


def test_bad_parameters_are_named():
    with pytest.raises(ValueError, match="H_1 must be positive"):
        fm.two_area_power(H_1=0.0)
    with pytest.raises(ValueError, match="inertia_uncertainty must be in"):
        fm.two_area_power(inertia_uncertainty=1.0)
    with pytest.raises(TypeError, match="unknown parameters \\['H3'\\]"):
        fm.two_area_power(H3=1.0)
