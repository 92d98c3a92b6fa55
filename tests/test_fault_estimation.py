"""`fojax.design_fault_estimator`: fault estimation on the fault-augmented §3.3.7 system (eq. 3.196).

Oracles: the thesis's bold L (`fojax.models.example_3_3_7`, ``L_aug``) and the float64
verification; SciPy's ``solve_ivp`` (Radau, rtol 1e-10) on the augmented ODE reduced by hand
(x5, x6 from the two algebraic rows) with constant faults, whose estimation error must decay
at least as fast as the slowest error eigenvalue (NumPy) allows.
"""

import jax.numpy as jnp
import numpy as np
import pytest
import scipy.integrate

import fojax
from fojax.design import design_fault_estimator, Disk


@pytest.fixture(scope="module")
def ex():
    return fojax.models.example_3_3_7()


@pytest.fixture(scope="module")
def estimator(ex):
    sys = fojax.DescriptorSystem(ex.E, ex.A, ex.B, ex.C)
    return design_fault_estimator(sys, ex.L, Fa=ex.Fa, Fs=ex.Fs, kind="generalized", region=Disk(-2.0, 1.0))


def test_bold_L_is_the_thesis_one_and_design_verifies(ex, estimator):
    assert np.array_equal(np.asarray(estimator.design.L), np.asarray(ex.L_aug))
    assert estimator.report.passed and estimator.report.relative_residual <= 1e-8
    assert (estimator.q, estimator.n_faults) == (2, 3)


def test_constant_faults_and_functional_are_estimated(ex, estimator):
    # Independent reference: SciPy on the hand-reduced augmented ODE [x1..x4, f] (x5, x6
    # from the two algebraic rows), with the observer driven by w = [-E⊥B u; y].
    E, A, B, C, Fa, Fs = (np.asarray(getattr(ex, k)) for k in ("E", "A", "B", "C", "Fa", "Fs"))
    f0 = np.array([1.0, -0.5, 0.3])
    obs = estimator.observer
    lm = obs.linear_matrices()
    Ao, Bu, By, Co, Du, Dy = (np.asarray(x) for x in lm)
    A11, A12, A21, A22 = A[:4, :4], A[:4, 4:], A[4:, :4], A[4:, 4:]
    B1, B2, Fa1, Fa2 = B[:4], B[4:], Fa[:4], Fa[4:]

    def u(t):
        return np.array([np.sin(t), 0.5 * np.cos(0.5 * t)])

    def full_x(x1, t):
        x2 = -np.linalg.solve(A22, A21 @ x1 + B2 @ u(t) + Fa2 @ f0)
        return np.concatenate([x1, x2])

    def rhs(t, s):
        x1, xi = s[:4], s[4:]
        x = full_x(x1, t)
        y = C @ x + Fs @ f0
        dx1 = A11 @ x1 + A12 @ x[4:] + B1 @ u(t) + Fa1 @ f0
        return np.concatenate([dx1, Ao @ xi + Bu @ u(t) + By @ y])

    ts = np.linspace(0.0, 12.0, 241)
    s0 = np.zeros(4 + obs.state_size)
    sol = scipy.integrate.solve_ivp(rhs, (0, 12), s0, t_eval=ts, rtol=1e-10, atol=1e-12, method="Radau")
    errs = []
    for k, t in enumerate(ts):
        x = full_x(sol.y[:4, k], t)
        y = C @ x + Fs @ f0
        est = Co @ sol.y[4:, k] + Du @ u(t) + Dy @ y
        zhat, fhat = estimator.split(est)
        errs.append(np.concatenate([zhat - np.asarray(ex.L) @ x, fhat - f0]))
    errs = np.abs(np.asarray(errs))
    slowest = np.linalg.eigvals(estimator.design.error_matrix).real.max()
    assert errs[0].max() > 0.1  # the observer starts wrong (zero initial state)
    # exponential decay at least as fast as the slowest error eigenvalue allows
    bound = errs[0].max() * 50 * np.exp((slowest + 0.05) * ts[-1])
    assert errs[-1].max() < bound < 1e-2, (errs[-1].max(), bound)


def test_fojax_simulation_agrees_with_reference(ex, estimator):
    # constant faults are initial conditions of the augmented state: exact stepping applies
    aug = estimator.augmented
    x0 = jnp.concatenate([jnp.zeros(6), jnp.array([1.0, -0.5, 0.3])])
    ts = jnp.linspace(0.0, 12.0, 1201)
    sol = fojax.simulate(aug, x0, ts, observers=(estimator.observer,))
    zhat, fhat = estimator.split(np.asarray(sol.estimates[0]))
    assert np.abs(fhat[-1] - np.array([1.0, -0.5, 0.3])).max() < 1e-3
    z = np.asarray(sol.xs)[:, :6] @ np.asarray(ex.L).T
    assert np.abs(zhat[-1] - z[-1]).max() < 1e-3


def test_fault_estimator_needs_fault_matrices(ex):
    sys = fojax.DescriptorSystem(ex.E, ex.A, ex.B, ex.C)
    with pytest.raises(fojax.errors.ShapeError, match="at least one fault matrix"):
        design_fault_estimator(sys, ex.L)
