r"""State-feedback design for descriptor systems (thesis Theorem 4.1.1 / Proof 9).

**Sign convention.** fojax uses $u = Lx$ throughout: the closed loop is
$E\dot x = (A + BL)x$. (The thesis mixes $A + BL$ (eq. 4.2, 4.9, 4.13) with $A - BL$
(§3.1.2, "λ(E, A − BL)"); the printed poles of every example are those of $A + BL$.)

**Method 1: ``"dual-lmi"`` (Proof 9, corrected and made strict).** $(E, A_c)$ is
admissible (regular, impulse-free, stable) iff there is $P_c$ with

$$E P_c = P_c^\top E^\top \succeq 0,\qquad A_c P_c + P_c^\top A_c^\top \prec 0$$

(the dual of Theorem 2.1.3, i.e. the Xu–Lam condition for $(E^\top, A_c^\top)$). The
equality and the semidefinite constraint are eliminated by the strict-LMI
parameterisation

$$P_c = X E^\top + S\Phi,\qquad X = X^\top \succ 0,\ \Phi\ \text{free},\ ES = 0,$$

($S$ an orthonormal basis of $\ker E$, so that $EP_c = EXE^\top$). With
$A_c = A + BL$ and the change of variables $W_L = LP_c$ (Proof 9) the condition is
the LMI

$$\operatorname{sym}(AP_c + BW_L) \prec 0$$

in $(X, \Phi, W_L)$. Any solution has $P_c$ nonsingular (if $P_cv = 0$ then
$v^\top(\cdot)v = 0$), and $L = W_LP_c^{-1}$. A decay rate $\alpha$ (every finite
pole with $\operatorname{Re}s < -\alpha$) is the same LMI for $(E, A + \alpha E)$,
whose finite poles are shifted by $+\alpha$ and whose impulse structure is unchanged.
This is necessary and sufficient: it is feasible iff some $L$ achieves the decay rate.

The thesis's eq. 4.19/4.20 print $P_c^\top A$ and $W_L^\top A^\top$ where
$P_c^\top A^\top$ and $W_L^\top B^\top$ are meant; and Proof 9 alone is not a strict LMI
(the constraint $EP_c = P_c^\top E^\top \succeq 0$ is an equality plus a semidefinite
condition). Both are corrected above.

**Method 2: ``"slow-subsystem"`` (any LMI region, e.g. a disk).** Chilali–Gahinet
regions do not carry over to the descriptor LMI directly ($E P_c$ is singular, so the
$L_R \otimes EP_c$ term cannot be negative definite). In SVD coordinates
$x = V[x_1; x_2]$, $\operatorname{diag}(\Sigma^{-1}, I)U^\top E V = \operatorname{diag}(I, 0)$,
split $u = \tilde L_1x_1 + \tilde L_2x_2$. First $\tilde L_2$ makes
$\bar A_{22} = \tilde A_{22} + \tilde B_2\tilde L_2$ invertible (impulse-freeness; $\tilde L_2 = 0$
when $\tilde A_{22}$ is already well conditioned, otherwise an explicit choice that
exists iff the system is impulse controllable, $\operatorname{rank}[\tilde A_{22}\
\tilde B_2] = n - \operatorname{rank}E$). With $\tilde L_2$ fixed the slow closed-loop
matrix is *affine* in $\tilde L_1$:

$$A_s + B_s\tilde L_1,\quad A_s = \tilde A_{11} - \bar A_{12}\bar A_{22}^{-1}\tilde A_{21},\quad
B_s = \tilde B_1 - \bar A_{12}\bar A_{22}^{-1}\tilde B_2,\quad
\bar A_{12} = \tilde A_{12} + \tilde B_1\tilde L_2,$$

so the Chilali–Gahinet region LMI with $W = \tilde L_1X$ is exact for this
$\tilde L_2$ (the finite poles of $(E, A + BL)$ are the eigenvalues of
$A_s + B_s\tilde L_1$). $(A_s, B_s)$ is stabilizable iff the descriptor system is (the
$\tilde L_2$ feedback does not change the uncontrollable finite modes).

**Fallbacks.** Interior-point solvers at fojax's tight tolerances sometimes stop at
``optimal_inaccurate`` when the certificate is ill conditioned (weakly controllable
modes, poles pushed far). `design_state_feedback` then re-solves with a larger penalty
on the certificate (`REG_LADDER`), and with ``method="auto"`` tries the other
formulation and finally ``"place"``: `scipy.signal.place_poles` on $(A_s, B_s)$ with
distinct real poles around ``region.target()`` (larger gains, no certificate). Which
one succeeded is recorded in `StateFeedbackDesign.method` / ``.solver``.

All methods target the region tightened by `fojax.design` 's 5 % rule and every
result is re-verified in float64 on the original matrices (finite poles with
`fojax.analysis.finite_poles`, impulse-freeness, region margin, and for the dual LMI
the certificate $P_c$ itself) before it is returned.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .._dtype import require_x64
from .._errors import (
    DesignVerificationError,
    LMI_FAILURES,
    LMIInfeasibleError,
    StabilizabilityError,
)
from .._linalg import null_space, rank
from ..analysis import finite_poles, is_impulse_free, is_regular, is_stabilizable
from ..design import (
    _ladder,
    _lmi,
    AbstractDesign,
    AbstractRegion,
    as_region,
    HalfPlane,
    Intersection,
)
from ..design._discrete import continuous_only
from ..design._verify import margin_failure, required_margin
from ..plant import DescriptorSystem


METHODS = ("auto", "dual-lmi", "slow-subsystem", "place")
#: Regions are tightened by this fraction for the LMI (`AbstractRegion.tightened`), so that
#: the verified poles keep a margin inside the requested region.
TIGHTEN = 0.05
#: Verified poles must be inside the region by this absolute margin.
POLE_MARGIN = 1e-9
#: LMI normalisation: ``X ⪰ I``, objective ``‖W‖_F + REG (‖X‖_F + ‖Φ‖_F)``: small gains,
#: and the small penalty on the certificate keeps the minimum attained (without it the
#: infimum of ‖W‖ can be approached only as X → ∞ and the solvers stop "inaccurate").
#: When the solver stops "inaccurate" (ill-conditioned certificates, e.g. weakly
#: controllable modes), the LMI is re-solved with a larger penalty (better conditioned
#: certificate, larger gains), in this order; ``method="auto"`` then also tries the other
#: formulation.
REG_LADDER = (1e-4, 1e-2, 1.0)
#: ``Ã22`` counts as well conditioned (no fast-state feedback needed) below this condition number.
A22_COND_MAX = 1e8


@dataclasses.dataclass(frozen=True)
class StateFeedbackDesign(AbstractDesign):
    r"""A verified state feedback $u = Lx$ with $(E, A + BL)$ admissible.

    **Fields:**

    - `L`: ``(m, n)`` gain (convention $u = Lx$, closed loop $A + BL$).
    - `system`: the plant.
    - `region`: the region the finite poles were placed in (``HalfPlane(0)`` =
      plain stability).
    - `poles`: finite poles of $(E, A + BL)$ (`fojax.analysis.finite_poles`).
    - `region_margin`: smallest margin of a pole inside `region` (``> 0``).
    - `method`: ``"dual-lmi"``, ``"slow-subsystem"`` or ``"place"``.
    - `certificate`: the LMI variables (``P``, ``X``, ``Phi``, ``W`` for the dual LMI;
      ``X``, ``W``, ``L2`` for the slow-subsystem LMI), float64.
    - `checks`: the float64 re-verification numbers.
    - `solver`: solver status and statistics.
    """

    L: np.ndarray
    system: DescriptorSystem
    region: AbstractRegion
    poles: np.ndarray
    region_margin: float
    method: str
    certificate: dict
    checks: dict
    solver: dict

    @property
    def observer(self) -> None:
        """A state feedback has no observer (`fojax.design.AbstractDesign`)."""
        return None

    @property
    def report(self) -> dict:
        """The float64 verification numbers (`checks`)."""
        return self.checks

    def verify(self) -> dict:
        """Re-run the float64 verification of `L` (`fojax.design.AbstractDesign.verify`):
        regularity, impulse freedom and the finite poles of $(E, A + BL)$ in `region`, and
        for the dual LMI the certificate's inequalities; returns the `checks`, raises
        `fojax.errors.DesignVerificationError` on a failure."""
        return _verify(self.system, np.asarray(self.L), self.region, self.method, self.certificate)[2]

    def closed_loop(self) -> DescriptorSystem:
        """The state-feedback loop $(E, A + BL, B, C)$ (input: the reference $u_r$)."""
        s = self.system
        return DescriptorSystem(s.E, s.A + s.B @ self.L, s.B, s.C)

    def __str__(self) -> str:
        p = ", ".join(f"{z:.4g}" for z in self.poles)
        return (
            f"state feedback u = Lx ({self.method}): finite poles of (E, A + BL) = [{p}] "
            f"in {self.region.describe()} (margin {self.region_margin:.3e}); "
            f"‖L‖ = {np.linalg.norm(self.L, 2):.4g}"
        )


# --------------------------------------------------------------------------- helpers


def _target_region(region, decay) -> AbstractRegion:
    parts = []
    if region is not None:
        parts.append(as_region(region))
    if decay is not None:
        parts.append(HalfPlane(decay))
    if not parts:
        return HalfPlane(0.0)
    return parts[0] if len(parts) == 1 else Intersection(tuple(parts))


def _is_halfplane(region: AbstractRegion) -> bool:
    if isinstance(region, HalfPlane):
        return True
    return isinstance(region, Intersection) and all(isinstance(p, HalfPlane) for p in region.parts)


def _decay_of(region: AbstractRegion) -> float:
    if isinstance(region, HalfPlane):
        return region.decay
    return max(p.decay for p in region.parts)


def _svd_coordinates(E, A, B):
    """``Ẽ = diag(I_r, 0) = Ul E V``, ``Ã = Ul A V``, ``B̃ = Ul B`` (restricted equivalence)."""
    from ..analysis import index1_split

    n = E.shape[0]
    sp = index1_split(E, A, fname="design_state_feedback")  # fojax.analysis's rank of E
    r, s, U = sp.rank, sp.s, sp.U
    Ul = np.diag(np.concatenate([1.0 / s[:r], np.ones(n - r)])) @ U.T
    V = sp.Vt.T
    return r, Ul @ A @ V, Ul @ B, V


def _fast_feedback(A22, B2):
    r"""``L̃2`` with ``Ã22 + B̃2 L̃2`` invertible (None when impossible: not impulse controllable)."""
    k, m = B2.shape
    if k == 0:
        return np.zeros((m, 0))
    if rank(A22) == k and np.linalg.cond(A22) < A22_COND_MAX:
        return np.zeros((m, k))
    if rank(np.hstack([A22, B2])) < k:
        return None
    Ub_full, sb, Vbt = np.linalg.svd(B2)
    kb = rank(B2)
    Ub, Uo = Ub_full[:, :kb], Ub_full[:, kb:]
    # Rows orthogonal to the row space of Uoᵀ Ã22 (dimension kb by impulse controllability).
    Nr = null_space(Uo.T @ A22).T if Uo.shape[1] else np.eye(k)
    scale = max(1.0, float(np.linalg.norm(A22, 2)))
    target = scale * Nr - Ub.T @ A22
    B2pinv_Ub = Vbt[:kb].T / sb[:kb]  # B̃2⁺ Ub
    return B2pinv_Ub @ target


def _slow_pair(A_t, B_t, r, L2):
    A11, A12, A21, A22 = A_t[:r, :r], A_t[:r, r:], A_t[r:, :r], A_t[r:, r:]
    B1, B2 = B_t[:r], B_t[r:]
    if A22.shape[0] == 0:
        return A11, B1
    A22b = A22 + B2 @ L2
    A12b = A12 + B1 @ L2
    As = A11 - A12b @ np.linalg.solve(A22b, A21)
    Bs = B1 - A12b @ np.linalg.solve(A22b, B2)
    return As, Bs


def _uncontrollable_modes(As, Bs, tol=None) -> np.ndarray:
    """Eigenvalues λ of ``As`` with ``rank [λI − As, Bs] < r`` (PBH test)."""
    r = As.shape[0]
    if r == 0:
        return np.zeros(0, complex)
    scale = max(1.0, float(np.linalg.norm(As, 2)), float(np.linalg.norm(Bs, 2)) if Bs.size else 0.0)
    out = []
    for lam in np.linalg.eigvals(As):
        M = np.hstack([lam * np.eye(r) - As, Bs]) / scale
        s = np.linalg.svd(M, compute_uv=False)
        thr = tol if tol is not None else max(1e-10 * s[0], 1e-12) if s.size else 1e-12
        if s.size == 0 or s[-1] <= max(thr, 1e-8):
            out.append(lam)
    return np.asarray(out, complex)


def _existence_checks(sys: DescriptorSystem, E, A, B, region: AbstractRegion):
    """Raise `StabilizabilityError` with the reason, or return the slow-subsystem data.

    `fojax.analysis.is_stabilizable` decides first (regular plants); the rank tests below
    find the reason (and handle pole regions and irregular open loops, which feedback
    can regularise).
    """
    n, m = B.shape
    stabilizable = None
    if is_regular(sys):
        stabilizable = is_stabilizable(sys)
    r, A_t, B_t, V = _svd_coordinates(E, A, B)
    L2 = _fast_feedback(A_t[r:, r:], B_t[r:])
    if L2 is None:
        k = n - r
        lhs = rank(np.hstack([A_t[r:, r:], B_t[r:]]))
        raise StabilizabilityError(
            "impulse controllability",
            f"rank [Ã22, B̃2] = {lhs} < n - rank E = {k} (equivalently rank [E 0 0; A E B] < "
            "n + rank E): no feedback u = Lx makes (E, A + BL) impulse-free.",
            "Add actuators acting on the algebraic equations (columns of B outside the range "
            "of E), or use a derivative/proportional-derivative feedback (not provided).",
            lhs=lhs,
            rhs=k,
        )
    As, Bs = _slow_pair(A_t, B_t, r, L2)
    modes = _uncontrollable_modes(As, Bs)
    bad = modes[region.margin(modes) <= 0] if modes.size else modes
    if bad.size:
        plain = isinstance(region, HalfPlane) and region.decay == 0.0
        cond = "stabilizability" if plain else "pole-region assignability"
        listed = ", ".join(f"{z:.6g}" for z in bad)
        raise StabilizabilityError(
            cond,
            f"the finite mode(s) {listed} of (E, A) are not controllable (rank [λE − A, B] < n) "
            f"and lie outside the requested region ({region.describe()}); no u = Lx moves them.",
            "Add an actuator that reaches these modes, or enlarge the region so that it "
            "contains them.",
            lhs=bad,
            rhs=region.describe(),
        )
    if stabilizable is False:  # pragma: no cover - the reasons above are exhaustive
        raise StabilizabilityError(
            "stabilizability",
            "fojax.analysis.is_stabilizable(sys) is False.",
            "Check fojax.structure_report(sys).",
        )
    return r, A_t, B_t, V, L2, As, Bs


def _solve_dual_lmi(E, A, B, decay, margin, solver, reg):
    import cvxpy as cp
    n, m = B.shape
    A_a = A + decay * E
    e = float(np.linalg.norm(E, 2)) or 1.0
    a = float(np.linalg.norm(A_a, 2)) or 1.0
    b = float(np.linalg.norm(B, 2)) or 1.0
    En, An, Bn = E / e, A_a / a, B / b
    S = null_space(En)  # (n, k), En S = 0
    k = S.shape[1]
    X = cp.Variable((n, n), symmetric=True)
    W = cp.Variable((m, n))
    if k:
        Phi = cp.Variable((k, n))
        P = X @ En.T + S @ Phi
    else:
        Phi = None
        P = X @ En.T
    M = An @ P + Bn @ W
    Msym = 0.5 * (M + M.T)
    cons = [X >> np.eye(n), Msym << -margin * np.eye(n)]
    obj = cp.norm(W, "fro") + reg * (cp.norm(X, "fro") + (cp.norm(Phi, "fro") if k else 0))
    info = _lmi.solve(
        cp.Problem(cp.Minimize(obj), cons),
        "state feedback (dual admissibility LMI, P = X Eᵀ + S Φ, W = L P)",
        hint="No u = Lx makes (E, A + BL) admissible with this decay rate: lower the decay "
        "rate, or check fojax.analysis.is_stabilizable(sys).",
        solver=solver,
    )
    Xv = _lmi.value(X)
    Xv = 0.5 * (Xv + Xv.T)
    Phiv = _lmi.value(Phi) if k else np.zeros((0, n))
    Wv = _lmi.value(W)
    Pn = Xv @ En.T + S @ Phiv
    Ln = np.linalg.solve(Pn.T, Wv.T).T  # W P⁻¹
    L = (a / b) * Ln
    # Certificate for the original (un-normalised) matrices: P = Pn works with W = L P.
    return L, {"P": Pn, "X": Xv, "Phi": Phiv, "W": L @ Pn, "S": S, "decay": decay}, info


def _solve_slow_lmi(As, Bs, region: AbstractRegion, margin, solver, reg):
    import cvxpy as cp
    r, m = Bs.shape
    if r == 0:
        return (
            np.zeros((m, 0)),
            {"X": np.zeros((0, 0)), "W": np.zeros((m, 0))},
            {"status": "trivial"},
        )
    X = cp.Variable((r, r), symmetric=True)
    W = cp.Variable((m, r))
    Phi = (As @ X + Bs @ W).T  # so that L⊗X + M⊗(A_cl X) + Mᵀ⊗(A_cl X)ᵀ (Chilali–Gahinet for A_cl)
    Mx = _lmi.region_lmi(region, X, Phi)
    cons = [X >> np.eye(r), Mx << -margin * np.eye(Mx.shape[0])]
    info = _lmi.solve(
        cp.Problem(cp.Minimize(cp.norm(W, "fro") + reg * cp.norm(X, "fro")), cons),
        "state feedback (slow-subsystem region LMI, W = L̃1 X)",
        hint="No u = Lx places the finite poles in the region: enlarge the region.",
        solver=solver,
    )
    Xv = _lmi.value(X)
    Xv = 0.5 * (Xv + Xv.T)
    Wv = _lmi.value(W)
    return np.linalg.solve(Xv, Wv.T).T, {"X": Xv, "W": Wv}, info


def _place_slow(As, Bs, region: AbstractRegion):
    """Pole placement fallback for the slow pair: distinct real poles well inside `region`."""
    import scipy.signal

    r = As.shape[0]
    if r == 0:
        return np.zeros((Bs.shape[1], 0)), {"poles": np.zeros(0)}, {"status": "trivial"}
    target = region.target().real
    for spread in (0.5, 0.25, 0.1, 0.02):
        poles = target * (1.0 + spread * np.linspace(-1.0, 1.0, r)) if r > 1 else np.array([target])
        if region.contains(poles, tol=required_margin(region, POLE_MARGIN)):
            break
    else:  # pragma: no cover - target() is inside every fojax region
        raise DesignVerificationError(f"no target poles inside {region.describe()}")
    K = -scipy.signal.place_poles(As, Bs, poles).gain_matrix  # As + Bs K has the poles
    return K, {"poles": poles}, {"status": "pole placement (scipy.signal.place_poles)"}


def _verify(sys, L, region, method, cert) -> tuple[np.ndarray, float, dict]:
    r"""The float64 verification of a state feedback (also `StateFeedbackDesign.verify`).

    Not `fojax.design.verify`, on purpose: a state feedback is checked on the descriptor
    pencil $(E, A + BL)$ — regularity, impulse freedom, *finite* poles (by
    `fojax.analysis`) in the region, and the dual LMI's $EP = (EP)^\top \succeq 0$ — while
    `verify` checks an observer's standard error dynamics $\mathbb A$ and its region LMI.
    The region test is shared (`required_margin`, `margin_failure`).
    """
    E, A, B = (np.asarray(x, float) for x in (sys.E, sys.A, sys.B))
    Acl = A + B @ L
    failures, checks = [], {}
    regular = is_regular(E, Acl)
    checks["regular"] = regular
    if not regular:
        failures.append("(E, A + BL) is not regular")
        poles = np.zeros(0, complex)
    else:
        poles = finite_poles(E, Acl)
        impulse_free = is_impulse_free(E, Acl)
        checks["impulse_free"] = impulse_free
        checks["n_finite_poles"] = int(poles.size)
        checks["rank_E"] = rank(E)
        if not impulse_free or poles.size != rank(E):
            failures.append(
                f"(E, A + BL) is impulsive ({poles.size} finite poles, rank E = {rank(E)})"
            )
    margin = float(np.min(region.margin(poles))) if poles.size else np.inf
    checks["region_margin"] = margin
    if not margin > required_margin(region, POLE_MARGIN):
        worst = poles[np.argmin(region.margin(poles))]
        failures.append(margin_failure("finite pole", worst, margin, required_margin(region, POLE_MARGIN), region))
    if method == "dual-lmi":
        P = cert["P"]
        e = float(np.linalg.norm(E, 2)) or 1.0
        En = E / e
        EP = En @ P
        nP = max(float(np.linalg.norm(P, 2)), 1e-300)
        sym_res = float(np.linalg.norm(EP - EP.T, 2)) / nP
        psd = float(np.linalg.eigvalsh(0.5 * (EP + EP.T))[0]) / nP
        Aa = Acl + cert["decay"] * E
        lyap = float(np.linalg.eigvalsh(0.5 * (Aa @ P + P.T @ Aa.T))[-1])
        lyap_rel = lyap / max(float(np.linalg.norm(Aa, 2)) * nP, 1e-300)
        checks.update(symmetry_residual=sym_res, psd_min_eig=psd, lyapunov_max_eig_rel=lyap_rel)
        if not sym_res <= 1e-9:
            failures.append(f"‖E P − (E P)ᵀ‖/‖P‖ = {sym_res:.2e} > 1e-9")
        if not psd >= -1e-9:
            failures.append(f"λ_min(E P)/‖P‖ = {psd:.2e} < −1e-9")
        if not lyap_rel < -1e-10:
            failures.append(
                f"λ_max(sym((A + BL + αE) P))/(‖·‖‖P‖) = {lyap_rel:.2e} is not negative"
            )
    checks["failures"] = tuple(failures)
    if failures:
        raise DesignVerificationError(
            "state feedback failed its float64 verification: " + "; ".join(failures), checks
        )
    return poles, margin, checks


# --------------------------------------------------------------------------- public


def design_state_feedback(
    sys: DescriptorSystem,
    *,
    region=None,
    decay: float | None = None,
    method: str = "auto",
    margin: float = 1e-3,
    solver: str = "CLARABEL",
) -> StateFeedbackDesign:
    r"""Design $L$ such that $(E, A + BL)$ is admissible (thesis Theorem 4.1.1 / Proof 9).

    Convention: **$u = Lx$, closed loop $E\dot x = (A + BL)x$** (the thesis also writes
    $A - BL$; its printed poles are those of $A + BL$). See the module docstring for
    the two LMI formulations and how they correct Proof 9.

    **Arguments:**

    - `sys`: a `fojax.DescriptorSystem` (it need not be regular, impulse-free or stable).
    - `region`: where the finite closed-loop poles must lie: a `fojax.Disk`,
      `fojax.HalfPlane`, `fojax.Sector`, an intersection (``&``) or a
      ``(center, radius)`` tuple. Default: the open left half-plane.
    - `decay`: a decay rate $\alpha \ge 0$: every finite pole with
      $\operatorname{Re}s < -\alpha$ (intersected with `region` when both are given).
    - `method`: ``"dual-lmi"`` (Proof 9 as a strict LMI; half-planes only),
      ``"slow-subsystem"`` (any region), ``"place"`` (pole placement of the slow
      subsystem) or ``"auto"`` (default: the dual LMI for a half-plane target, then the
      slow-subsystem LMI, then placement — the first that passes verification).
    - `margin`: strictness of the LMIs (``⪯ −margin·I`` with ``X ⪰ I``).
    - `solver`: ``"CLARABEL"`` (default) or ``"SCS"`` (see `fojax.design.DEFAULT_SOLVER`).

    **Returns:** a verified `StateFeedbackDesign` (``.L``, ``.poles``, ...).

    **Raises:** `fojax.errors.StabilizabilityError` (checked before any LMI: not impulse
    controllable, or an uncontrollable finite mode outside the region — the message
    lists them), `fojax.errors.LMIInfeasibleError`, `fojax.errors.DesignVerificationError`.

    !!! example

        ```python
        fb = fojax.control.design_state_feedback(sys, decay=0.5)
        fojax.analysis.finite_poles(sys.E, sys.A + sys.B @ fb.L)
        ```
    """
    if not isinstance(sys, DescriptorSystem):
        raise TypeError(
            f"expected a fojax.DescriptorSystem, got {type(sys).__name__}; build one with "
            "fojax.DescriptorSystem(E, A, B, C)."
        )
    require_x64("state-feedback design")
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    continuous_only(sys, "design_state_feedback")
    if sys.m == 0:
        raise StabilizabilityError(
            "stabilizability",
            "the system has no inputs (m = 0).",
            "Give B with at least one column.",
        )
    target = _target_region(region, decay)
    auto = method == "auto"
    if method == "dual-lmi" and not _is_halfplane(target):
        raise ValueError(
            f"method='dual-lmi' handles decay rates (half-planes) only; got {target.describe()}. "
            "Use method='slow-subsystem' (or 'auto') for disks and sectors."
        )
    E, A, B = (np.asarray(x, float) for x in (sys.E, sys.A, sys.B))
    r, A_t, B_t, V, L2, As, Bs = _existence_checks(sys, E, A, B, target)
    lmi_target = target.tightened(TIGHTEN)
    methods = (
        [method]
        if not auto
        else (
            ["dual-lmi", "slow-subsystem", "place"]
            if _is_halfplane(target)
            else ["slow-subsystem", "place"]
        )
    )
    def rung(meth, reg):
        if meth == "place":
            L1, cert, info = _place_slow(As, Bs, target)
            L = np.hstack([L1, L2]) @ V.T
            cert = dict(cert, L2=L2)
        elif meth == "dual-lmi":
            L, cert, info = _solve_dual_lmi(E, A, B, _decay_of(lmi_target), margin, solver, reg)
        else:
            L1, cert, info = _solve_slow_lmi(As, Bs, lmi_target, margin, solver, reg)
            L = np.hstack([L1, L2]) @ V.T
            cert = dict(cert, L2=L2)
        return L, cert, info, _verify(sys, L, target, meth, cert)

    rungs = [((meth, reg), (lambda meth=meth, reg=reg: rung(meth, reg)))
             for meth in methods for reg in (REG_LADDER if meth != "place" else (None,))]
    try:
        (meth, reg), (L, cert, info, (poles, pmargin, checks)), refused = _ladder.climb(
            rungs,
            refusals=(*LMI_FAILURES, DesignVerificationError, np.linalg.LinAlgError, ValueError),
            # a larger penalty does not make an infeasible LMI feasible: next method
            give_up=lambda label, err: isinstance(err, LMIInfeasibleError)
            and str(err.status).startswith("infeasible"),
        )
    except _ladder.Refused as every:
        raise every.refused[-1][1] from None
    attempts = [{"method": m, "reg": r, "error": str(err)} for (m, r), err in refused]
    info = dict(info, reg=reg, failed_attempts=attempts)
    return StateFeedbackDesign(
        L=L,
        system=sys,
        region=target,
        poles=poles,
        region_margin=pmargin,
        method=meth,
        certificate=cert,
        checks=checks,
        solver=info,
    )
