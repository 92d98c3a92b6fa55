"""Discrete-time descriptor systems E x[k+1] = A x[k] + B u[k]: analysis, design, simulation.

Oracles: NumPy/SciPy generalized eigenvalues (``scipy.linalg.eig(A, E)``, infinite ones
dropped by |β|) and NumPy ranks for the analysis verdicts, hand-built pencils with known
poles and index; for designs, a plain NumPy recursion of the observer's own matrices
driven by a plain NumPy recursion of the plant (the estimation error must decay to
round-off) and ``numpy.linalg.eigvals`` of the error matrix; for `simulate`, the same plain
NumPy recursion (the algebraic row solved by hand) and central finite differences for
the gradient.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg as sla
from helpers import assert_eigenvalues_match

import fojax
from fojax.analysis import is_causal, structure_report
from fojax.design import DiscreteDisk, region_from_dict
from fojax.simulation import Discrete


H = 0.1
# A model used by no other test: one algebraic row, an unstable finite pole (|λ| ≈ 1.08).
E4 = np.diag([1.0, 1.0, 1.0, 0.0])
A4 = np.array([[1.1, 0.2, 0.0, 0.0], [0.0, 0.9, 0.3, 0.0], [0.1, 0.0, 0.7, 1.0], [0.2, 0.0, 1.0, 1.0]])
B4 = np.array([[1.0], [0.0], [0.5], [1.0]])
C4 = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
L4 = np.array([[0.0, 1.0, 1.0, 0.0]])


def plant(dt=H):
    return fojax.DescriptorSystem(E4, A4, B4, C4, dt=dt)


def finite_eigs(E, A):
    alpha, beta = sla.eig(A, E, right=False, homogeneous_eigvals=True)
    keep = np.abs(beta) > 1e-9 * np.abs(alpha)
    return alpha[keep] / beta[keep]


def u_of(t):
    return np.array([np.sin(1.3 * t) + 0.2])


U_SIG = fojax.Sine(np.array([1.0]), 1.3, offset=0.2)


def consistent(x0, t0):
    """x0 with its algebraic state x4 solved from 0 = A[3] x + B[3] u(t0)."""
    x = np.array(x0, float)
    x[3] = -(A4[3, :3] @ x[:3] + B4[3] @ u_of(t0)) / A4[3, 3]
    return x


def plant_recursion(x0, ts):
    """x[k+1]: rows 0..2 explicit (E = I there), row 3 algebraic at k+1."""
    xs = [consistent(x0, ts[0])]
    for k in range(len(ts) - 1):
        x = xs[-1]
        x1 = A4[:3] @ x + B4[:3] @ u_of(ts[k])
        xn = np.r_[x1, 0.0]
        xn[3] = -(A4[3, :3] @ x1 + B4[3] @ u_of(ts[k + 1])) / A4[3, 3]
        xs.append(xn)
    return np.array(xs)


def observer_recursion(obs, xs, ts):
    """ẑ[k] of the observer's matrices, in NumPy, driven by u[k], y[k] = C x[k]."""
    N, J, F, Hh, S, G, M, P, Q, Wu, Wy = (np.asarray(getattr(obs, k)) for k in
                                          ("N", "J", "F", "H", "S", "G", "M", "P", "Q", "Wu", "Wy"))
    zeta, v = np.zeros(N.shape[0]), np.zeros(G.shape[0])
    out = []
    for k, x in enumerate(xs):
        u = u_of(ts[k])
        w = Wu @ u + Wy @ (C4 @ x)
        out.append(P @ zeta + Q @ w)
        zeta, v = N @ zeta + J @ v + F @ w + Hh @ u, S @ zeta + G @ v + M @ w
    return np.array(out)


# ------------------------------------------------------------------------------ the model


@pytest.mark.parametrize("bad", [0.0, -0.1, float("nan"), float("inf"), "fast", True])
def test_dt_is_validated(bad):
    with pytest.raises(fojax.errors.InputError, match="dt"):
        fojax.DescriptorSystem(E4, A4, B4, C4, dt=bad)


def test_dt_is_static_and_kept():
    s = plant()
    assert s.dt == H and plant(None).dt is None
    assert s.replace(A=2 * A4).dt == H
    assert "dt=0.1" in repr(s)
    assert fojax.DescriptorSystem.from_state_space(A4[:3, :3], dt=0.5).dt == 0.5
    assert jax.tree_util.tree_leaves(s).__len__() == 5  # E, A, B, C, D; dt is not a leaf


# ------------------------------------------------------------------------------ analysis


def test_discrete_stability_against_scipy_eigenvalues():
    rng = np.random.default_rng(7)
    for _ in range(12):
        A = rng.normal(size=(4, 4)) * rng.uniform(0.2, 0.6)
        E = np.diag([1.0, 1.0, 1.0, 0.0]) @ rng.normal(size=(4, 4))
        lam = finite_eigs(E, A)
        s = fojax.DescriptorSystem(E, A, dt=0.2)
        assert_eigenvalues_match(fojax.analysis.finite_poles(s), lam, rtol=1e-8, atol=1e-12)
        assert fojax.analysis.is_stable(s) == bool(np.all(np.abs(lam) < 1))
        assert fojax.analysis.is_stable(s.replace(dt=None)) == bool(np.all(lam.real < 0))


def test_unit_circle_is_the_boundary():
    # poles 0.5 (continuous-unstable, discrete-stable) and -2 (the reverse), one algebraic row
    E = np.diag([1.0, 1.0, 0.0])
    A = np.diag([0.5, -2.0, 1.0])
    s = fojax.DescriptorSystem(E, A, dt=1.0)
    assert not fojax.analysis.is_stable(s) and not fojax.analysis.is_stable(s.replace(dt=None))
    s2 = fojax.DescriptorSystem(E, np.diag([0.5, -0.9, 1.0]), dt=1.0)
    assert fojax.analysis.is_stable(s2) and fojax.analysis.is_admissible(s2)
    assert not fojax.analysis.is_stable(s2.replace(dt=None))  # 0.5 > 0
    on = fojax.DescriptorSystem(E, np.diag([0.5, -1.0, 1.0]), dt=1.0)  # |λ| = 1: not stable
    assert not fojax.analysis.is_stable(on)
    assert fojax.analysis.is_stable(fojax.DescriptorSystem(E, np.diag([0.5, -0.5, 1.0]), dt=1.0), margin=0.4)
    assert not fojax.analysis.is_stable(fojax.DescriptorSystem(E, np.diag([0.5, -0.7, 1.0]), dt=1.0), margin=0.4)


def test_causality_is_the_rank_test():
    # index 2 (N = [[0, 1], [0, 0]]): x2[k] = -u[k+1]... needs future inputs: not causal
    E = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    A = np.eye(3) * np.array([1.0, 1.0, 0.3])
    for EE, AA in ((E, A), (E4, A4)):
        n, r = 3 if EE is E else 4, np.linalg.matrix_rank(EE)
        Z = np.zeros_like(EE)
        oracle = np.linalg.matrix_rank(np.block([[EE, Z], [AA, EE]])) == EE.shape[0] + r
        s = fojax.DescriptorSystem(EE, AA, dt=0.3)
        assert is_causal(s) == oracle == fojax.analysis.is_impulse_free(s)
        assert n == EE.shape[0]
    assert not is_causal(fojax.DescriptorSystem(E, A, dt=0.3))
    assert not fojax.analysis.is_admissible(fojax.DescriptorSystem(E, A, dt=0.3))


def test_observability_rank_tests_identical_detectability_on_the_unit_circle():
    # an unobservable mode at z = 0.5: continuous-unstable, discrete-stable
    E = np.diag([1.0, 1.0, 0.0])
    A = np.array([[0.5, 0.0, 0.0], [0.0, -0.3, 0.0], [0.0, 1.0, 1.0]])
    C = np.array([[0.0, 1.0, 0.0]])
    rank_at = np.linalg.matrix_rank(np.vstack([0.5 * E - A, C]))
    assert rank_at < 3  # the oracle: R-observability fails at 0.5
    sd = fojax.DescriptorSystem(E, A, C=C, dt=0.1)
    sc = sd.replace(dt=None)
    rd, rc = structure_report(sd), structure_report(sc)
    for k in ("r_observable", "i_observable", "c_observable", "s_observable", "r_controllable", "i_controllable"):
        assert getattr(rd, k) == getattr(rc, k), k
    assert not rd.r_observable
    assert rd.detectable and not rc.detectable
    assert fojax.analysis.is_detectable(sd) and not fojax.analysis.is_detectable(sc)
    assert rd.dt == 0.1 and rc.dt is None


def test_continuous_certificate_refused_for_a_discrete_system():
    with pytest.raises(fojax.errors.InputError, match="continuous-time admissibility"):
        fojax.analysis.admissibility_certificate(plant())


def test_structure_report_says_discrete_time():
    r = structure_report(plant(), L4)
    text = str(r)
    assert "discrete-time (dt = 0.1)" in text and "causal" in text and "max |λ|" in text
    lam = finite_eigs(E4, A4)
    assert not r.stable and np.max(np.abs(lam)) > 1
    assert "|λ| >= 1" in r.verdict
    assert "continuous-time" in str(structure_report(plant(None)))


# ------------------------------------------------------------------------------ design


@pytest.mark.parametrize("kind, method", [("generalized", "lmi"), ("proportional", "lmi"),
                                          ("generalized", "riccati"), ("proportional", "riccati")])
def test_discrete_design_verified_inside_the_disk(kind, method):
    region = DiscreteDisk(0.1, 0.6)
    d = fojax.design_functional_observer(plant(), L4, kind=kind, method=method, region=region)
    assert d.dt == H and d.observer.dt == H
    assert d.report.passed and d.verify().passed
    ev = np.linalg.eigvals(np.asarray(d.observer.error_matrix))
    assert np.all(np.abs(ev - 0.1) < 0.6)
    # independent: plant and observer as plain NumPy recursions; the error decays to round-off
    ts = H * np.arange(120)
    xs = plant_recursion([1.0, -1.0, 0.5, 0.0], ts)
    err = observer_recursion(d.observer, xs, ts)[:, 0] - xs @ L4[0]
    assert abs(err[0]) > 0.1
    assert np.max(np.abs(err[-10:])) < 1e-9 * max(1.0, np.max(np.abs(xs)))


@pytest.mark.parametrize("options", [dict(objective="centre"), dict(balance=True), dict(kind="PI")])
def test_other_design_options_keep_the_discrete_region(options):
    region = DiscreteDisk(0.2, 0.5)
    d = fojax.design_functional_observer(plant(), L4, region=region, **options)
    assert d.dt == H and d.report.passed
    assert np.all(np.abs(np.linalg.eigvals(d.error_matrix) - 0.2) < 0.5)


def test_tune_refuses_a_discrete_design():
    d = fojax.design_functional_observer(plant(), L4, kind="proportional")
    study = fojax.Study(plant(), consistent([1.0, 0.0, 0.0, 0.0], 0.0), H * jnp.arange(20), L4, u=U_SIG)
    with pytest.raises(fojax.errors.InputError, match="continuous-time designs"):
        fojax.tune(d, study, steps=1)


def test_saved_design_keeps_dt(tmp_path):
    d = fojax.design_functional_observer(plant(), L4, kind="proportional", method="riccati")
    fojax.save_design(d, tmp_path / "d")
    d2 = fojax.load_design(tmp_path / "d")
    assert d2.dt == H and d2.region == d.region and d2.verify().passed


def test_default_region_and_tuple():
    d = fojax.design_functional_observer(plant(), L4, kind="proportional")
    assert d.region == DiscreteDisk(0.0, 0.5) and d.dt == H
    d2 = fojax.design_functional_observer(plant(), L4, kind="proportional", region=(0.2, 0.3))
    assert isinstance(d2.region, DiscreteDisk)
    assert np.all(np.abs(np.linalg.eigvals(d2.error_matrix) - 0.2) < 0.3)


def test_region_errors():
    with pytest.raises(fojax.errors.RegionError, match="Re\\(s\\) < -1.*not inside the open unit disk"):
        fojax.design_functional_observer(plant(), L4, region=fojax.HalfPlane(1.0))
    with pytest.raises(fojax.errors.RegionError, match="disk centred at -2 with radius 1 is not inside"):
        fojax.design_functional_observer(plant(), L4, region=fojax.Disk(-2.0, 1.0))
    with pytest.raises(fojax.errors.RegionError, match="not inside the open unit disk"):
        DiscreteDisk(0.5, 0.6)
    with pytest.raises(fojax.errors.RegionError, match="z-plane disk.*continuous-time"):
        fojax.design_functional_observer(plant(None), L4, region=DiscreteDisk(-0.5, 0.2))
    with pytest.raises(fojax.errors.InputError, match="continuous-time norm"):
        fojax.design_functional_observer(plant(), L4, objective="hinf")
    # an intersection with a disk inside the unit disk is accepted
    reg = DiscreteDisk(0.0, 0.7) & fojax.Sector(0.2)
    assert fojax.design.DiscreteDisk(0.0, 0.7).contains([0.5])
    assert region_from_dict(reg.to_dict()) == reg


def test_fault_estimator_on_a_discrete_plant():
    # constant actuator fault f on row 0: f[k+1] = f[k] (the augmented A has I, not 0, there)
    Fa = np.array([[1.0], [0.0], [0.0], [0.0]])
    aug = fojax.plant.augment_faults(plant(), Fa=Fa)
    assert aug.dt == H
    np.testing.assert_allclose(aug.A, np.block([[A4, Fa], [np.zeros((1, 4)), np.eye(1)]]))
    ramp = fojax.plant.augment_faults(plant(), Fa=Fa, ramp=True)
    np.testing.assert_allclose(ramp.A[4:, 4:], [[1.0, H], [0.0, 1.0]])
    d = fojax.design_fault_estimator(plant(), L4, Fa=Fa)
    assert d.design.dt == H and d.design.report.passed
    # NumPy recursion of the faulty plant and of the observer: the fault estimate converges to f
    f, ts = 0.7, H * np.arange(150)
    x = consistent([0.5, 0.0, 0.0, 0.0], 0.0)
    obs = d.design.observer
    N, F, Hh, P, Q, Wu, Wy = (np.asarray(getattr(obs, k)) for k in ("N", "F", "H", "P", "Q", "Wu", "Wy"))
    J, S, G, M = (np.asarray(getattr(obs, k)) for k in ("J", "S", "G", "M"))
    zeta, v = np.zeros(N.shape[0]), np.zeros(G.shape[0])
    for k in range(len(ts)):
        u = u_of(ts[k])
        w = Wu @ u + Wy @ (C4 @ x)
        est = P @ zeta + Q @ w
        zeta, v = N @ zeta + J @ v + F @ w + Hh @ u, S @ zeta + G @ v + M @ w
        x1 = A4[:3] @ x + B4[:3] @ u + Fa[:3, 0] * f
        xn = np.r_[x1, 0.0]
        xn[3] = -(A4[3, :3] @ x1 + B4[3] @ u_of(ts[k + 1] if k + 1 < len(ts) else ts[k])) / A4[3, 3]
        z_true = np.r_[L4 @ x, f]
        x = xn
    np.testing.assert_allclose(est, z_true, atol=1e-8)


def test_continuous_only_designs_refuse_discrete_models():
    with pytest.raises(fojax.errors.InputError, match="design_unknown_input_observer designs for continuous-time"):
        fojax.design_unknown_input_observer(plant(), np.array([[0.0], [1.0], [0.0], [0.0]]), L4)
    with pytest.raises(fojax.errors.InputError, match="design_state_feedback designs for continuous-time"):
        fojax.control.design_state_feedback(plant())


# ------------------------------------------------------------------------------ simulation


def test_simulate_matches_numpy_recursion():
    d = fojax.design_functional_observer(plant(), L4, kind="generalized")
    ts = 0.5 + H * jnp.arange(80)
    x0 = consistent([1.0, -1.0, 0.5, 0.0], 0.5)
    sol = fojax.simulate(plant(), x0, ts, U_SIG, observers=d.observer)
    xs = plant_recursion(x0, np.asarray(ts))
    assert sol.method == "discrete"
    np.testing.assert_allclose(sol.xs, xs, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(sol.estimates[0], observer_recursion(d.observer, xs, np.asarray(ts)),
                               rtol=1e-10, atol=1e-12)
    assert float(sol.stats["constraint_residual"]) < 1e-12
    assert float(jnp.abs(sol.estimates[0][-1, 0] - xs[-1] @ L4[0])) < 1e-9


def test_simulate_vmap_and_grad():
    ts = H * jnp.arange(30)
    s = plant()
    x0s = jnp.array([consistent([a, 0.0, 1.0, 0.0], 0.0) for a in (0.0, 1.0, -2.0)])
    batch = jax.vmap(lambda x0: fojax.simulate(s, x0, ts, U_SIG).xs)(x0s)
    for i in range(3):
        np.testing.assert_allclose(batch[i], plant_recursion(np.asarray(x0s[i]), np.asarray(ts)), rtol=1e-10,
                                   atol=1e-12)

    def loss(a):
        p = fojax.DescriptorSystem(E4, jnp.asarray(A4).at[0, 0].set(a), B4, C4, dt=H)
        return jnp.sum(fojax.simulate(p, x0s[1], ts, U_SIG).xs[:, 1:3] ** 2)

    g = jax.jit(jax.grad(loss))(0.7)
    eps = 1e-6
    fd = (loss(0.7 + eps) - loss(0.7 - eps)) / (2 * eps)
    np.testing.assert_allclose(g, fd, rtol=1e-6)


def test_new_numbers_do_not_recompile():
    # private: TRACE_COUNTS, the no-retrace check
    from fojax.simulation._discrete import TRACE_COUNTS

    ts = H * jnp.arange(20)
    fojax.simulate(plant(), consistent([1.0, 0.0, 0.0, 0.0], 0.0), ts, U_SIG)
    before = TRACE_COUNTS["simulate"]
    p2 = fojax.DescriptorSystem(E4, 0.9 * A4, 2.0 * B4, C4, dt=H)
    fojax.simulate(p2, jnp.array([0.5, 1.0, -1.0, 0.0]), ts + 1.0, fojax.Sine(np.array([2.0]), 0.5))
    assert TRACE_COUNTS["simulate"] == before


def test_simulate_errors():
    s = plant()
    x0 = consistent([1.0, 0.0, 0.0, 0.0], 0.0)
    with pytest.raises(fojax.errors.InputError, match="t0 \\+ k\\*dt"):
        fojax.simulate(s, x0, 0.05 * jnp.arange(10), U_SIG)
    with pytest.raises(fojax.errors.InputError, match="steps continuous-time models"):
        fojax.simulate(s, x0, H * jnp.arange(10), U_SIG, stepper=fojax.Exact())
    with pytest.raises(fojax.errors.InputError, match="Discrete\\(\\) steps discrete-time plants"):
        fojax.simulate(plant(None), x0, H * jnp.arange(10), U_SIG, stepper=Discrete())
    obs = fojax.design_functional_observer(plant(), L4, kind="proportional").observer
    for other in (0.2, None):  # another period, or a continuous-time observer
        with pytest.raises(fojax.errors.InputError, match="same sampling period"):
            fojax.simulate(s, x0, H * jnp.arange(10), U_SIG, observers=dataclasses.replace(obs, dt=other))


def test_run_study_on_a_discrete_plant():
    d = fojax.design_functional_observer(plant(), L4, kind="proportional")
    ts = H * jnp.arange(60)
    x0 = consistent([1.0, -1.0, 0.5, 0.0], 0.0)
    res = fojax.run_study(fojax.Study(plant(), x0, ts, L4, u=U_SIG), [d.observer])
    xs = plant_recursion(x0, np.asarray(ts))
    err = observer_recursion(d.observer, xs, np.asarray(ts))[:, 0] - xs @ L4[0]
    assert res.attrs["engine"] == "vmap-simulate"
    np.testing.assert_allclose(np.asarray(res.metrics["peak"]).ravel()[0], np.max(np.abs(err)), rtol=1e-9)
    # study_loss takes the same path (trapezoidal IAE on the sample grid)
    iae = np.sum(0.5 * (np.abs(err[1:]) + np.abs(err[:-1])) * np.diff(np.asarray(ts)))
    loss = fojax.studies.study_loss(fojax.Study(plant(), x0, ts, L4, u=U_SIG), d.observer, loss="iae")
    np.testing.assert_allclose(loss, iae, rtol=1e-9)
    np.testing.assert_allclose(np.asarray(res.metrics["iae"]).ravel()[0], iae, rtol=1e-9)
