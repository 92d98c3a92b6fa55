"""The Riccati design route (`fojax.design._riccati`, issue 16).

Oracles (independent of the route's own computations):

- the error eigenvalues: `scipy.linalg.eigvals` of the observer's error matrix
  ``[[N, J], [S, G]]``, tested against the region pointwise (|λ - α| < τ, Re λ < -σ,
  the sector's closed form), not with the region classes' own `margin`;
- the certificate: the Stein inequality ``Mᵀ X M - X ≺ 0`` with ``M = (𝔸 - αI)/τ``
  (NumPy `eigvalsh`), and for half-planes/sectors the region's LMI written out by hand;
- the design conditions a.–d.: recomputed from the returned observer matrices with NumPy
  (``N TE + F Ψ = T A``, ``H = T B``, ``S TE + M Ψ = 0``, ``P TE + Q Ψ = L``);
- the thesis's examples (`fojax.models`) and random well-conditioned impulse-free systems;
  infeasible problems raise the same typed error for both routes.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.linalg as sla
from helpers import assert_design_conditions, assert_eigenvalues_match, index1_system
from scipy.stats import ortho_group

import fojax
from fojax import models
from fojax.design import design_functional_observer, Disk, HalfPlane, Sector


def random_system(n, seed):
    """Regular, impulse-free E x' = A x + B u (E = U diag(I_r, 0) V, A = U A0 V with an
    invertible algebraic block), p = n // 2 outputs, q = 2 functionals."""
    rng = np.random.default_rng([seed, n])
    r = n - max(1, n // 4)
    A0 = rng.standard_normal((n, n))
    A0[r:, r:] += 3.0 * np.eye(n - r)
    U, V = ortho_group.rvs(n, random_state=rng), ortho_group.rvs(n, random_state=rng)
    E = U @ np.diag([1.0] * r + [0.0] * (n - r)) @ V
    return (fojax.DescriptorSystem(E, U @ A0 @ V, rng.standard_normal((n, 2)),
                                   rng.standard_normal((max(1, n // 2), n))),
            rng.standard_normal((2, n)))


def blocks(d):
    o = d.observer
    return {k: np.asarray(getattr(o, k)) for k in "N J F H S G M P Q".split()}


def inside(region, eigs):
    """Pointwise oracle: margin > 0 iff inside (closed forms, not the region classes)."""
    eigs = np.asarray(eigs)
    if isinstance(region, Disk):
        return region.radius - np.abs(eigs - region.center)
    if isinstance(region, HalfPlane):
        return -region.decay - eigs.real
    th = math.acos(region.damping)
    return -eigs.real * math.sin(th) - np.abs(eigs.imag) * math.cos(th)


def assert_riccati_design(d, sysm, L, region, method="riccati"):
    """Everything a Riccati design promises, checked independently (with ``method="lmi"``:
    a disk design of the LMI route whose certificate is a Stein certificate)."""
    assert d.report.passed and not d.report.failures
    assert d.solver["lmi"]["method"] == method
    if method == "riccati":
        assert d.solver["lmi"]["route"].startswith("Riccati")
        assert "design route: Riccati" in str(d)
    b, Aerr = assert_design_conditions(d, sysm, L)
    eigs = sla.eigvals(Aerr)
    assert np.all(inside(region, eigs) > 0), eigs
    X = 0.5 * (d.X + d.X.T)
    assert np.linalg.eigvalsh(X).min() > 0
    dim = Aerr.shape[0]
    disk = d.solver["lmi"]["disk"] if method == "riccati" else region.to_dict()
    M = (Aerr - disk["center"] * np.eye(dim)) / disk["radius"]
    stein = M.T @ X @ M - X
    assert np.linalg.eigvalsh(0.5 * (stein + stein.T)).max() < 0  # Stein inequality
    if isinstance(region, HalfPlane):  # X A + Aᵀ X + 2σ X ≺ 0
        H = X @ Aerr + Aerr.T @ X + 2 * region.decay * X
        assert np.linalg.eigvalsh(0.5 * (H + H.T)).max() < 0
    if isinstance(region, Sector):  # Chilali–Gahinet sector LMI, written out
        th = math.acos(region.damping)
        XA = X @ Aerr
        S1 = math.sin(th) * (XA + XA.T)
        S2 = math.cos(th) * (XA - XA.T)
        H = np.block([[S1, S2], [-S2, S1]])
        assert np.linalg.eigvalsh(0.5 * (H + H.T)).max() < 0
    return eigs


@pytest.mark.parametrize("n,seed,q0", [(4, 0, None), (8, 1, None), (16, 2, 8)])
@pytest.mark.parametrize("kind", ["generalized", "PI", "proportional"])
def test_random_systems_verify(n, seed, q0, kind):
    sysm, L = random_system(n, seed)
    region = Disk(-2.0, 1.0)
    d = design_functional_observer(sysm, L, kind=kind, region=region, q0=q0, method="riccati")
    assert_riccati_design(d, sysm, L, region)
    # the gain does the work: without it some modes of N1' are outside the disk
    from fojax.design import pieces

    pc = pieces(d.structure)
    N1 = np.asarray(pc.N1)[0]
    assert np.any(inside(region, sla.eigvals(N1)) <= 0)
    b = blocks(d)
    if kind == "PI":
        # the decoupled Riccati design: J = 0, S = -Y2 N3 = 0, G = g I
        assert d.observer.q1 == d.observer.q0
        assert not np.any(b["J"]) and not np.any(b["S"]) and not np.any(d.params["Y2"])
        np.testing.assert_array_equal(b["G"], b["G"][0, 0] * np.eye(d.observer.q1))
    if kind == "generalized":
        # the coupled design: the integral state drives ε (J ≠ 0) and is driven by the
        # measured residual (S ≠ 0 whenever N3 ≠ 0)
        assert np.any(b["J"])
        if np.any(np.asarray(pc.N3)) and np.any(d.params["Y1"]):
            assert np.any(b["S"])


@pytest.mark.parametrize("region", [HalfPlane(1.0), Sector(0.7)], ids=["halfplane", "sector"])
def test_half_plane_and_sector_through_a_disk(region):
    sysm, L = random_system(6, 3)
    d = design_functional_observer(sysm, L, kind="generalized", region=region, method="riccati")
    assert_riccati_design(d, sysm, L, region)
    disk = d.solver["lmi"]["disk"]
    # the disk used lies inside the region (closed forms)
    if isinstance(region, HalfPlane):
        assert disk["center"] + disk["radius"] <= -region.decay + 1e-12
    else:
        assert disk["radius"] <= -disk["center"] * math.sin(math.acos(region.damping)) * (1 + 1e-12)
    assert "inside " + region.describe() in d.solver["lmi"]["route"]


THESIS = [
    ("example_3_1_2", None),
    ("example_3_1_3", "R"),
    ("example_3_3_7", None),
    ("example_4_1_3", None),
]


@pytest.mark.parametrize("name,R", THESIS, ids=[t[0] for t in THESIS])
def test_thesis_examples_verify_by_both_routes(name, R):
    ex = getattr(models, name)()
    region = Disk(ex.alpha, ex.tau) if name == "example_4_1_3" else Disk(-2.0, 1.0)
    kw = {} if R is None else {"R": getattr(ex, R)}
    ric = design_functional_observer(ex.system, ex.L, kind="proportional", region=region, method="riccati", **kw)
    assert_riccati_design(ric, ex.system, ex.L, region)
    lmi = design_functional_observer(ex.system, ex.L, kind="proportional", region=region, method="lmi", **kw)
    assert lmi.report.passed and lmi.solver["lmi"]["method"] == "lmi"
    assert "LMI route" in lmi.report.extra and "design route" not in lmi.report.extra
    assert np.asarray(ric.observer.N).shape == np.asarray(lmi.observer.N).shape


def test_thesis_413_generalized():
    ex = models.example_4_1_3()
    region = Disk(ex.alpha, ex.tau)
    d = design_functional_observer(ex.system, ex.L, kind="generalized", region=region, method="riccati")
    assert_riccati_design(d, ex.system, ex.L, region)


def test_pi_gain_is_the_full_riccati_solution():
    """The blocks of the PI (decoupled) design that fojax solves separately equal SciPy's
    DARE of the whole pair (𝔸1(Z), 𝔸2) in the disk's Möbius coordinates (oracle:
    scipy.linalg.solve_discrete_are)."""
    from fojax.design import pieces

    ex = models.example_4_1_3()
    region = Disk(ex.alpha, ex.tau)
    d = design_functional_observer(ex.system, ex.L, kind="PI", region=region, method="riccati")
    pc = pieces(d.structure)
    N1, N2, N3 = np.asarray(pc.N1)[0], np.asarray(pc.N2)[0], np.asarray(pc.N3)
    q0, q1, c = d.observer.q0, d.observer.q1, N3.shape[0]
    disk = d.solver["lmi"]["disk"]
    alpha, tau = disk["center"], disk["radius"] * 0.95
    A1 = sla.block_diag(N1 - d.params["Z"] @ N2, np.zeros((q1, q1)))
    A2 = sla.block_diag(N3, -np.eye(q1))
    Ad, Cd = (A1 - alpha * np.eye(q0 + q1)) / tau, A2 / tau
    P = sla.solve_discrete_are(Ad.T, Cd.T, np.eye(q0 + q1), np.eye(c + q1))
    Yfull = Ad @ P @ Cd.T @ np.linalg.inv(np.eye(c + q1) + Cd @ P @ Cd.T)
    scale = np.abs(Yfull).max()
    np.testing.assert_allclose(Yfull[:q0, c:], 0, atol=1e-9 * scale)  # J
    np.testing.assert_allclose(Yfull[q0:, :c], 0, atol=1e-9 * scale)  # Y2
    np.testing.assert_allclose(Yfull[q0:, c:], d.params["G"], atol=1e-9 * scale)  # G = g I


def test_unobservable_modes_shortcut_agrees_with_the_pbh_loop():
    """`unobservable_modes` skips the per-eigenvalue SVDs when Cm has full column rank
    (σ_min([λI - A; Cm]) ≥ σ_min(Cm)); oracle: the PBH rank test with NumPy's matrix_rank."""
    from fojax.design._conditions import unobservable_modes  # private: tested itself

    rng = np.random.default_rng(5)
    A = rng.standard_normal((6, 6))
    full = rng.standard_normal((8, 6))
    assert unobservable_modes(A, full).size == 0
    for lam in np.linalg.eigvals(A):
        assert np.linalg.matrix_rank(np.vstack([lam * np.eye(6) - A, full])) == 6
    # a rank-deficient Cm still finds the hidden mode: A = diag(3, B), Cm blind to e1
    A2 = sla.block_diag([[3.0]], rng.standard_normal((5, 5)))
    Cm = np.hstack([np.zeros((8, 1)), rng.standard_normal((8, 5))])
    modes = unobservable_modes(A2, Cm)
    assert modes.size == 1 and abs(modes[0] - 3.0) < 1e-12
    # tall rank-deficient Cm (the QR-compressed path), hidden modes placed by construction
    for seed in range(4):
        r = np.random.default_rng([seed, 7])
        k = int(r.integers(1, 3))  # number of hidden modes
        A0 = sla.block_diag(np.diag(r.uniform(-3.0, 3.0, k)), r.standard_normal((5, 5)))
        C0 = np.hstack([np.zeros((12, k)), r.standard_normal((12, 5))])
        Q = sla.qr(r.standard_normal((5 + k, 5 + k)))[0]
        got = unobservable_modes(Q @ A0 @ Q.T, C0 @ Q.T)
        want = [lam for lam in np.linalg.eigvals(A0)
                if np.linalg.matrix_rank(np.vstack([lam * np.eye(5 + k) - A0, C0]), tol=1e-8) < 5 + k]
        assert_eigenvalues_match(got, want, atol=1e-9)


def test_auto_dispatch():
    ex = models.example_4_1_3()
    auto = design_functional_observer(ex.system, ex.L, kind="proportional", region=Disk(-2.0, 1.0), method="auto")
    assert auto.solver["lmi"]["method"] == "riccati"
    both = Disk(-2.0, 1.0) & HalfPlane(1.5)
    inter = design_functional_observer(ex.system, ex.L, kind="proportional", region=both, method="auto")
    assert inter.solver["lmi"]["method"] == "lmi" and inter.report.passed
    with pytest.raises(fojax.errors.InputError, match="method='riccati' does not apply.*not a single disk"):
        design_functional_observer(ex.system, ex.L, kind="proportional", region=both, method="riccati")
    pi = design_functional_observer(ex.system, ex.L, kind="PI", method="riccati")
    assert pi.report.passed and not np.any(np.asarray(pi.observer.S))
    with pytest.raises(fojax.errors.InputError, match="method must be one of"):
        design_functional_observer(ex.system, ex.L, method="ricatti")


def test_undetectable_raises_the_same_error_for_both_routes():
    # x1' = x1 (unstable, not measured, not in the functional's reach): the observer of
    # z = x1 + x2 cannot move the mode +1 (thesis Lemma 8).
    E = np.eye(2)
    A = np.array([[1.0, 0.0], [0.0, -1.0]])
    sysm = fojax.DescriptorSystem(E, A, np.ones((2, 1)), np.array([[0.0, 1.0]]))
    L = np.array([[1.0, 1.0]])
    errs = []
    for method in ("riccati", "lmi"):
        with pytest.raises(fojax.FojaxError) as ei:
            design_functional_observer(sysm, L, kind="proportional", method=method)
        errs.append(type(ei.value))
    assert errs[0] is errs[1]
    assert issubclass(errs[0], (fojax.errors.FunctionalObservabilityError, fojax.errors.DetectabilityError))


def test_output_injection_failure_is_typed():
    from fojax.design._riccati import output_injection_gain  # private: tested itself

    # Ad = diag(2, 0.5) with only the stable mode measured: the mode 2 (outside the unit
    # disk) is unobservable, so no gain makes Ad - Y Cd Schur
    with pytest.raises(fojax.errors.LMIInfeasibleError, match="no observer gain can move|outside the disk"):
        output_injection_gain(np.diag([2.0, 0.5]), np.array([[0.0, 1.0]]))
    # a detectable pair: Schur closed loop (independent eigenvalue check)
    Ad, Cd = np.array([[1.5, 1.0], [0.0, 0.5]]), np.array([[1.0, 0.0]])
    Y = output_injection_gain(Ad, Cd)
    assert np.max(np.abs(sla.eigvals(Ad - Y @ Cd))) < 1.0


# ============================================================== the default route at size


def test_choose_route_rule():
    """The documented rule of `choose_route` (its docstring), case by case."""
    # private: the route rule is tested itself
    from fojax.design._functional import AUTO_LMI_MAX_ORDER, choose_route, SMALL_ORDER

    assert AUTO_LMI_MAX_ORDER > SMALL_ORDER
    big, small = SMALL_ORDER + 1, SMALL_ORDER
    for method in ("lmi", "riccati", "auto"):
        assert choose_route(method, objective="region", solver=None, order=big) == method
    assert choose_route(None, objective="region", solver=None, order=big) == "auto"
    assert choose_route(None, objective="region", solver=None, order=small) == "lmi"
    assert choose_route(None, objective="region", solver="SCS", order=big) == "lmi"
    for objective in ("hinf", "h2", "centre"):
        assert choose_route(None, objective=objective, solver=None, order=big) == "lmi"
    with pytest.raises(fojax.errors.InputError, match="method must be one of"):
        choose_route("fast", objective="region", solver=None, order=big)


@pytest.mark.parametrize("kind", ["generalized", "PI", "proportional"])
def test_default_call_at_moderate_n_verifies(kind):
    """n = 48, 4 outputs, 3 functionals, 14 algebraic equations, default R: the default call
    takes the Riccati route (observer order above `SMALL_ORDER`) and its design passes the
    independent checks (a.–d. with NumPy, error eigenvalues by SciPy inside the disk, the
    Stein inequality at the certificate)."""
    sysm, L = index1_system(48, 4, 3, 14, 0)
    region = Disk(-3.0, 2.0)
    d = design_functional_observer(sysm, L, kind=kind, region=region)
    assert d.observer.q0 + d.observer.q1 > 12
    eigs = assert_riccati_design(d, sysm, L, region)
    assert len(eigs) == d.observer.q0 + d.observer.q1
    b = blocks(d)
    if kind == "generalized":  # coupled: J ≠ 0, and S = -Y2 N3 ≠ 0 wherever N3 and Y1 are not zero
        from fojax.design import pieces

        assert np.any(b["J"])
        if np.any(np.asarray(pieces(d.structure).N3)) and np.any(d.params["Y1"]):
            assert np.any(b["S"])
    if kind == "PI":
        assert not np.any(b["S"])


def test_auto_falls_back_to_the_lmi_route(monkeypatch):
    """method='auto': a refused Riccati route (forced) gives the LMI route's verified design,
    and the report says the Riccati route was refused."""
    # private: the Riccati route is forced to refuse
    from fojax.design import _riccati

    def refuse(*a, **k):
        raise fojax.errors.LMIInfeasibleError("output-injection Riccati equation", "no_stabilizing_solution", {},
                                       "forced by the test")

    monkeypatch.setattr(_riccati, "riccati_gains", refuse)
    ex = models.example_4_1_3()
    d = design_functional_observer(ex.system, ex.L, kind="generalized", region=Disk(ex.alpha, ex.tau),
                                   method="auto")
    assert d.report.passed and d.solver["lmi"]["method"] == "lmi"
    assert "forced by the test" in d.report.extra["Riccati route refused"]
    with pytest.raises(fojax.errors.LMIInfeasibleError, match="forced by the test"):
        design_functional_observer(ex.system, ex.L, kind="generalized", region=Disk(ex.alpha, ex.tau),
                                   method="riccati")


def test_unobservable_modes_staircase_agrees_with_the_pbh_loop():
    """Above `PBH_SCREEN_MIN` the candidates come from SLICOT's staircase form; oracle: hidden
    modes placed by construction (an orthogonally hidden block the output never sees) and
    the PBH rank test of every eigenvalue with NumPy's matrix_rank."""
    # private: the staircase screen's threshold is read
    from fojax.design import _conditions

    n, k = _conditions.PBH_SCREEN_MIN + 12, 5
    for seed in range(2):
        r = np.random.default_rng([seed, 11])
        A0 = r.standard_normal((n, n)) / np.sqrt(n)
        A0[: n - k, n - k:] = 0.0  # the last k states never reach the first n - k
        A0[n - k:, n - k:] = np.diag(r.uniform(-3.0, 3.0, k))
        C0 = np.hstack([r.standard_normal((6, n - k)), np.zeros((6, k))])
        Q = sla.qr(r.standard_normal((n, n)))[0]
        A, Cm = Q @ A0 @ Q.T, C0 @ Q.T
        got = _conditions.unobservable_modes(A, Cm)
        want = [lam for lam in np.linalg.eigvals(A0)
                if np.linalg.matrix_rank(np.vstack([lam * np.eye(n) - A0, C0]), tol=1e-8) < n]
        assert len(want) == k
        assert_eigenvalues_match(got, want, atol=1e-8)


@pytest.mark.parametrize("kind", ["generalized", "proportional"])
def test_lmi_route_with_the_gain_eliminated(kind):
    """method='lmi' on a disk with observer order above `SMALL_ORDER`: the LMI in X alone
    (gain eliminated, closed-form gain) gives a design that passes the independent checks
    (a.–d. with NumPy, eigenvalues by SciPy inside the disk, the Stein inequality at X)."""
    sysm, L = index1_system(20, 3, 2, 5, 1)
    region = Disk(-3.0, 2.0)
    d = design_functional_observer(sysm, L, kind=kind, region=region, q0=13, method="lmi")
    assert "gain eliminated" in d.solver["lmi"]["route"]
    assert_riccati_design(d, sysm, L, region, method="lmi")
