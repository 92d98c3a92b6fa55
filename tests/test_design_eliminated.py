"""The reduced region LMI of the LMI route (`fojax.design._eliminated`): gains eliminated.

Oracles (independent of the reduced LMI and of fojax's region classes):

- feasibility: the modes no output injection can move, found by the PBH rank test with NumPy
  (`numpy.linalg.matrix_rank` of ``[λI - A; C]``) on systems built with hidden modes placed
  inside or outside the region by a clear margin, and the *full* Chilali–Gahinet LMI in
  ``(X, W = XK)`` written out here with cvxpy (the formulation before the elimination);
- designs: conditions a.–d. recomputed with NumPy from the observer matrices, the error
  eigenvalues by `scipy.linalg.eigvals` tested against each region's closed form, and the
  region LMI at the returned certificate written out by hand (disk, half-plane, sector);
- infeasible structures (fixed modes outside the region, PBH): the reduced LMI raises
  `LMIInfeasibleError`; the full LMI of `fojax.design._region_lmi.solve_gains` finds no
  solution either (its solver shows infeasibility or stops short).
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import scipy.linalg as sla
from helpers import assert_design_conditions, index1_system
from scipy.stats import ortho_group

import fojax
from fojax.design import (
    design_functional_observer,
    Disk,
    HalfPlane,
    observer_structure,
    Sector,
)

# private: the reduced LMI and the full one are compared directly
from fojax.design._eliminated import (
    eliminated_gains,
    epsilon_block_lmi,
    formulation,
    inscribed_disk,
)
from fojax.design._functional import prepare_structure
from fojax.design._region_lmi import solve_gains


REGIONS = {
    "disk": Disk(-2.5, 1.6),
    "half-plane": HalfPlane(1.0),
    "sector": Sector(0.8),
    "half-plane & sector": HalfPlane(1.0) & Sector(0.8),
    "disk & half-plane": Disk(-2.5, 1.6) & HalfPlane(1.0),
}


def parts(region):
    return region.parts if hasattr(region, "parts") else (region,)


def inside(region, eigs):
    """Closed-form margin (> 0 inside) of every part, the minimum over parts."""
    eigs = np.asarray(eigs, complex)
    out = []
    for p in parts(region):
        if isinstance(p, Disk):
            out.append(p.radius - np.abs(eigs - p.center))
        elif isinstance(p, HalfPlane):
            out.append(-p.decay - eigs.real)
        else:
            th = math.acos(p.damping)
            out.append(-eigs.real * math.sin(th) - np.abs(eigs.imag) * math.cos(th))
    return np.min(out, axis=0)


def region_lmi_by_hand(region, X, A):
    """Largest eigenvalue of each part's Chilali–Gahinet matrix at ``X`` (``< 0``: certified)."""
    XA = X @ A
    worst = []
    for p in parts(region):
        if isinstance(p, Disk):
            a, r = p.center, p.radius
            H = np.block([[-r * X, XA.T - a * X], [XA - a * X, -r * X]])
        elif isinstance(p, HalfPlane):
            H = XA + XA.T + 2 * p.decay * X
        else:
            th = math.acos(p.damping)
            S1, S2 = math.sin(th) * (XA + XA.T), math.cos(th) * (XA.T - XA)
            H = np.block([[S1, S2], [-S2, S1]])
        worst.append(np.linalg.eigvalsh(0.5 * (H + H.T)).max())
    return max(worst)


def hidden_modes(A, C):
    """PBH: eigenvalues λ of A with rank [λI - A; C] < n (NumPy)."""
    n = A.shape[0]
    return [lam for lam in np.linalg.eigvals(A)
            if np.linalg.matrix_rank(np.vstack([lam * np.eye(n) - A, C]), tol=1e-7) < n]


def full_lmi_verdict(A, C, region, margin=1e-3) -> str:
    """The Chilali–Gahinet LMI in (X, W = X K), written out here (the full formulation):
    ``"feasible"``, ``"infeasible"`` (Clarabel's certificate) or ``"undecided"`` (Clarabel
    stopped short with the min-trace and the pure feasibility objective)."""
    import cvxpy as cp

    n = A.shape[0]
    X = cp.Variable((n, n), symmetric=True)
    W = cp.Variable((n, C.shape[0]))
    Phi = X @ A - W @ C
    cons = [X >> np.eye(n)]
    for p in parts(region):
        Lr, Mr = p.characteristic()
        F = cp.kron(Lr, X) + cp.kron(Mr, Phi.T) + cp.kron(Mr.T, Phi)
        cons.append(0.5 * (F + F.T) << -margin * np.eye(F.shape[0]))
    for objective in (cp.trace(X) + cp.norm(W, "fro"), cp.Constant(0)):
        prob = cp.Problem(cp.Minimize(objective), cons)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                prob.solve(solver="CLARABEL")
            except cp.SolverError:
                continue
        if prob.status in ("optimal", "infeasible"):
            return "feasible" if prob.status == "optimal" else "infeasible"
    return "undecided"


def output_injection_case(seed, n, k_hidden, region, outside: bool):
    """(A, C): an observable part with modes outside the region (the gain must move them) and
    `k_hidden` modes no gain can move, placed inside the region or (`outside`) outside it by a
    margin of at least 0.3 (one of them), rotated by a random orthogonal matrix."""
    rng = np.random.default_rng([seed, n, k_hidden, int(outside)])
    no = n - k_hidden
    Ao = rng.standard_normal((no, no)) / np.sqrt(no) + 0.5 * np.eye(no)  # unstable: the gain has work to do
    Co = rng.standard_normal((2, no))
    target = region.target().real
    hidden = target + 0.2 * rng.uniform(-1, 1, k_hidden)
    if outside:
        hidden[0] = 0.5  # right half-plane: outside every region here by more than 0.3
    Ah = np.diag(hidden)
    A0 = np.block([[Ao, np.zeros((no, k_hidden))], [rng.standard_normal((k_hidden, no)) / np.sqrt(no), Ah]])
    C0 = np.hstack([Co, np.zeros((2, k_hidden))])
    Q = ortho_group.rvs(n, random_state=rng)
    return Q @ A0 @ Q.T, C0 @ Q.T


@pytest.mark.parametrize("name", list(REGIONS))
def test_reduced_and_full_lmi_agree_on_feasibility(name):
    """Random output-injection problems (n = 6, 2 outputs, 2 hidden modes), feasible and
    infeasible by a clear margin: the reduced LMI's verdict equals the PBH oracle's and the full
    LMI's; feasible gains put every eigenvalue inside the region (SciPy, closed forms) and the
    certificate satisfies the region LMI written out by hand."""
    region = REGIONS[name].tightened(0.05)
    for seed in range(3):
        for outside in (False, True):
            A, C = output_injection_case(seed, 6, 2, region, outside)
            oracle = bool(np.all(inside(region, hidden_modes(A, C)) > 0))
            assert oracle is (not outside)
            # the full LMI agrees, or (infeasible cases) its solver stops short: it never
            # finds a solution the reduced LMI misses, nor the other way round
            assert full_lmi_verdict(A, C, region) in (("feasible",) if oracle else ("infeasible", "undecided"))
            if not oracle:
                # infeasibility shown (LMIInfeasibleError), or a solver that stopped short
                # (SolverStoppedShortError) — never a design; the eliminated forms show it
                with pytest.raises((fojax.errors.LMIInfeasibleError, fojax.errors.SolverStoppedShortError)) as err:
                    epsilon_block_lmi(A, C, region)
                if formulation(region) in ("disk", "finsler"):
                    assert isinstance(err.value, fojax.errors.LMIInfeasibleError)
                continue
            K, X, info = epsilon_block_lmi(A, C, region)
            Acl = A - K @ C
            assert np.all(inside(region, sla.eigvals(Acl)) > 0)
            assert np.linalg.eigvalsh(X).min() > 0
            assert region_lmi_by_hand(region, X, Acl) < 0
            assert info["formulation"] == formulation(region) or (
                formulation(region) == "inscribed disk" and info["formulation"] == "full")


def test_formulation_per_region_kind():
    assert formulation(Disk(-2, 1)) == "disk"
    assert formulation(fojax.design.DiscreteDisk(0, 0.5)) == "disk"
    assert formulation(HalfPlane(1)) == formulation(Sector(0.5)) == "finsler"
    assert formulation(HalfPlane(1) & Sector(0.5) & HalfPlane(2)) == "finsler"
    assert formulation(Disk(-2, 1) & HalfPlane(1)) == "inscribed disk"


def test_inscribed_disk_is_inside_the_region():
    """Disk(-2.5, 1.6) ∩ Re s < -1: the real segment [-4.1, -1] is its diameter (closed form);
    points of its boundary circle are inside every part (closed-form margins)."""
    d = inscribed_disk(Disk(-2.5, 1.6) & HalfPlane(1.0))
    assert d.center == pytest.approx(-2.55, abs=2e-3) and d.radius == pytest.approx(1.55, abs=2e-3)
    for region in (REGIONS["disk & half-plane"], Disk(-3.0, 2.0) & Sector(0.7) & HalfPlane(1.5)):
        d = inscribed_disk(region)
        circle = d.center + d.radius * np.exp(1j * np.linspace(0, 2 * np.pi, 721))
        assert np.min(inside(region, circle)) > -1e-9


def test_fixed_modes_outside_the_inscribed_disk_go_to_the_full_form():
    """Hidden modes -2.5 ± 1.8j (PBH) inside Disk(-3, 2.5) ∩ Re s < -2 but outside its
    inscribed disk (centre -3.75, radius 1.75): the inscribed disk's LMI has no solution, the
    intersection's own LMI (gain kept) designs; eigenvalues (SciPy) and the region LMI at X (by
    hand) check it."""
    region = Disk(-3.0, 2.5) & HalfPlane(2.0)
    rng = np.random.default_rng(7)
    Ao = rng.standard_normal((4, 4)) / 2 + 0.5 * np.eye(4)
    Ah = np.array([[-2.5, 1.8], [-1.8, -2.5]])
    A0 = np.block([[Ao, np.zeros((4, 2))], [rng.standard_normal((2, 4)) / 2, Ah]])
    C0 = np.hstack([rng.standard_normal((2, 4)), np.zeros((2, 2))])
    Q = ortho_group.rvs(6, random_state=rng)
    A, C = Q @ A0 @ Q.T, C0 @ Q.T
    fixed = hidden_modes(A, C)
    tight = region.tightened(0.05)
    inner = inscribed_disk(tight)
    assert len(fixed) == 2 and np.min(inside(tight, fixed)) > 0.3
    assert np.max(np.abs(np.asarray(fixed) - inner.center)) > inner.radius + 0.3
    K, X, info = epsilon_block_lmi(A, C, tight)
    assert info["formulation"] == "full" and any("inscribed disk" in n for n in info["notes"])
    Acl = A - K @ C
    assert np.all(inside(tight, sla.eigvals(Acl)) > 0)
    assert np.linalg.eigvalsh(X).min() > 0 and region_lmi_by_hand(tight, X, Acl) < 0


def assert_design(d, sysm, L, region):
    """a.–d. with NumPy, eigenvalues by SciPy in the region, region LMI at X by hand."""
    assert d.report.passed and not d.report.failures
    b, Aerr = assert_design_conditions(d, sysm, L)
    assert np.all(inside(region, sla.eigvals(Aerr)) > 0)
    X = 0.5 * (d.X + d.X.T)
    assert np.linalg.eigvalsh(X).min() > 0
    assert region_lmi_by_hand(region, X, Aerr) < 0
    return b


@pytest.mark.parametrize("kind", ["generalized", "PI"])
@pytest.mark.parametrize("name", list(REGIONS))
def test_lmi_route_designs_verify(kind, name):
    """method='lmi' above `SMALL_ORDER` (q0 = 11, order 22) takes the reduced LMI for every
    region kind; the design passes the independent checks; a generalized design is coupled
    (J ≠ 0), a PI design keeps S = 0."""
    sysm, L = index1_system(20, 2, 3, 6, 2)
    region = REGIONS[name]
    d = design_functional_observer(sysm, L, kind=kind, region=region, method="lmi")
    assert d.observer.q0 + d.observer.q1 > 12
    route = d.solver["lmi"]["route"]
    assert "reduced to the ε-block" in route and "eliminated LMI refused" not in d.report.extra
    b = assert_design(d, sysm, L, region)
    assert np.any(b["J"])
    if kind == "PI":
        assert not np.any(b["S"])


@pytest.mark.parametrize("name", ["disk", "half-plane", "sector"])
def test_proportional_reduced_and_full_designs(name):
    """A proportional observer (q0 = 14 above `SMALL_ORDER`) from the reduced LMI and from the
    full LMI: both feasible, both verify independently."""
    sysm, L = index1_system(24, 3, 4, 6, 0)
    region = REGIONS[name]
    s = prepare_structure(sysm, L, q0=14, q1=0, region=region)
    d = design_functional_observer(sysm, L, kind="proportional", region=region, R=s.R, method="lmi")
    assert "reduced to the ε-block" in d.solver["lmi"]["route"]
    assert_design(d, sysm, L, region)
    X, Z, Ys, _ = solve_gains(s, region.tightened(0.05), kind="proportional")  # the full LMI: feasible too
    assert np.all(np.isfinite(X))


# A structure whose ε-block modes are all fixed (no gain moves them): -3.007, -2.345 ± 1.033j,
# -1.784 ± 0.399j, -1.651, -2.192 (PBH oracle in the test); the regions below exclude -1.651
# (by 0.35) or the damping 0.915 of -2.345 ± 1.033j (vs 0.95).
INFEASIBLE = {
    "half-plane": HalfPlane(2.0),
    "sector": Sector(0.95),
    "half-plane & sector": HalfPlane(1.0) & Sector(0.95),
    "disk & half-plane": Disk(-2.5, 1.6) & HalfPlane(2.0),
}


@pytest.mark.parametrize("kind,name", [("generalized", name) for name in INFEASIBLE]
                         + [("PI", "sector"), ("proportional", "half-plane & sector")])
def test_infeasible_structures_raise_from_both_formulations(kind, name):
    """Fixed modes outside the region by a clear margin: the reduced LMI raises
    `LMIInfeasibleError` (infeasibility shown by the solver), the full LMI of `solve_gains`
    finds no solution either; the same structure in a region containing the fixed modes gives
    a verified design."""
    sysm, L = index1_system(16, 2, 3, 5, 2)
    region = INFEASIBLE[name]
    s = prepare_structure(sysm, L, q1=0, region=Disk(-2.5, 1.6))
    q1 = 0 if kind == "proportional" else s.q0
    s = observer_structure(s.E, s.A, s.B, s.C, s.L, s.R, q1=q1, psi=s.psi, Eperp=s.Eperp)
    from fojax.design import pieces

    pc = pieces(s)
    N1 = np.asarray(pc.N1)[0]
    fixed = hidden_modes(N1, np.vstack([np.asarray(pc.N2)[0], np.asarray(pc.N3)]))
    assert len(fixed) == s.q0 and np.min(inside(region, fixed)) < -0.03
    with pytest.raises(fojax.errors.LMIInfeasibleError):
        eliminated_gains(s, region.tightened(0.05), kind=kind)
    # the full LMI: no solution either (shown infeasible, or its solver stops short)
    with pytest.raises((fojax.errors.LMIInfeasibleError, fojax.errors.SolverStoppedShortError)):
        solve_gains(s, region.tightened(0.05), kind=kind)
    feasible = REGIONS[name]
    assert np.min(inside(feasible.tightened(0.05), fixed)) > 0.03
    eliminated_gains(s, feasible.tightened(0.05), kind=kind)
    d = design_functional_observer(sysm, L, kind=kind, region=feasible, R=s.R, method="lmi")
    assert_design(d, sysm, L, feasible)


def test_stopped_short_falls_back_to_the_full_lmi(monkeypatch):
    """A reduced LMI whose solver stops short is not an infeasibility: the full LMI designs, and
    the report says why (the reduced LMI forced to stop short)."""
    from fojax.design import _functional

    def stop(*a, **k):
        raise fojax.errors.SolverStoppedShortError("reduced LMI", "optimal_inaccurate", {})

    monkeypatch.setattr(_functional, "eliminated_gains", stop)
    sysm, L = index1_system(20, 2, 3, 6, 2)
    d = design_functional_observer(sysm, L, kind="generalized", region=HalfPlane(1.0), method="lmi")
    assert "optimal_inaccurate" in d.report.extra["eliminated LMI refused"]
    assert_design(d, sysm, L, HalfPlane(1.0))


@pytest.mark.parametrize("name", list(REGIONS))
def test_output_seeing_every_direction_needs_no_lmi(name):
    """C of rank n (no null space left, step 3): no LMI is solved, X = I for the eliminated
    forms; eigenvalues (SciPy) inside the region and the region LMI at X by hand."""
    rng = np.random.default_rng(11)
    A = rng.standard_normal((5, 5)) + np.eye(5)
    C = rng.standard_normal((6, 5))
    region = REGIONS[name].tightened(0.05)
    K, X, info = epsilon_block_lmi(A, C, region)
    if info["formulation"] in ("finsler", "disk", "inscribed disk"):
        assert info["lmi_size"] == [] and info["solver"] is None
    Acl = A - K @ C
    assert np.all(inside(region, sla.eigvals(Acl)) > 0)
    assert np.linalg.eigvalsh(X).min() > 0 and region_lmi_by_hand(region, X, Acl) < 0


@pytest.mark.parametrize("name", ["disk", "half-plane"])
def test_staircase_design_refused_falls_back_to_step_2(monkeypatch, name):
    """A staircase design that fails its float64 check (forced here) is not returned: the step-2
    form (certificate of order n) designs, the notes say so; eigenvalues (SciPy) and the region
    LMI at X (by hand) check the result."""
    from fojax.design import _eliminated

    monkeypatch.setattr(_eliminated, "_holds", lambda *a: False)
    region = REGIONS[name].tightened(0.05)
    A, C = output_injection_case(0, 6, 2, region, False)
    K, X, info = epsilon_block_lmi(A, C, region)
    assert any("step 2 form solved" in n for n in info["notes"])
    assert info["lmi_size"] == ([6 + 4] if name == "disk" else [6, 4])
    Acl = A - K @ C
    assert np.all(inside(region, sla.eigvals(Acl)) > 0)
    assert np.linalg.eigvalsh(X).min() > 0 and region_lmi_by_hand(region, X, Acl) < 0
