r"""LMI design of Takagi–Sugeno functional observers (thesis §3.3, Theorem 3.3.1, Algorithm 1).

**Problem.** For the T-S descriptor model $E\dot x = \sum_i w_i(y,u)(A_ix + B_iu)$,
$y = Cx$ (eq. 3.150) and $z = Lx$, the observer (3.152) uses the measured output
only ($w = y$, i.e. $\Psi = C$ and $\Gamma = [E; C]$, `psi="output"` in
`fojax.design.observer_structure`), one common $T$ and per-rule gains. Conditions
a.–d. of Lemma 11 must hold for every rule $i$:
$N_iTE + F_iC - TA_i = 0$, $H_i = TB_i$, $S_iTE + M_iC = 0$, $P_iTE + Q_iC = L$.

**Algorithm (Algorithm 1, linearized; see `fojax.design.design_functional_observer`).**

1. Assumption 2 (impulse observability, $\operatorname{rank}[E; E^\perp A_i; C] = n$
   for every rule) and functional observability with $\Gamma = [E; C]$ are checked
   first; then the rank conditions and the fixed modes (Lemma 8) for every rule.
   (Conditions a.–d. do not use Assumption 2 — with $w = y$ only $[E; C]$ matters —
   but the thesis states the design under it, and it is what makes the T-S model's
   algebraic part well posed for every rule, so fojax enforces it.)
2. $R$ (default: `fojax.design.default_R` with ``psi="output"`` over all rules).
3. One region LMI with a **common** certificate $X$ for all rules, a common $Z$
   (hence a common $T$) and per-rule $\mathbb Y_i$ (`solve_gains`), in place of the
   elimination (3.177) + explicit parameterization (3.178): for fixed $Z$ the two
   describe the same feasible set, and the LMI gives $X$ directly.
4. $Y_{i3} = 0$ (step 5 of Algorithm 1).

**What the common certificate proves.** The region LMI
$L_R\otimes X + M_R\otimes(\mathbb A^\top X) + M_R^\top\otimes(X\mathbb A) \prec 0$ is
affine in $\mathbb A$, so it holds for every convex combination
$\mathbb A(w) = \sum_i w_i\mathbb A_i$: *frozen-time* region placement for all
weights. For the regions fojax offers (disks in the open left half-plane,
half-planes, sectors and their intersections) it also implies
$\mathbb A(w)^\top X + X\mathbb A(w) \prec 0$, i.e. quadratic stability of the
error $\dot\sigma = \mathbb A(w(t))\sigma$ for *arbitrarily time-varying* weights —
which is what the T-S observer needs. This Lyapunov inequality is re-checked in
float64 for every rule (`report.extra["lyapunov_max_eig"]`).

**Limits.** The thesis's T-S observer uses $w = y$: functionals involving
directions outside the row space of $[E; C]$ (e.g. the algebraic state $x_5$ of
the robot arm, only determined through the rule-dependent row $E^\perp A_i$) are
refused with `fojax.errors.FunctionalObservabilityError`. The convergence guarantee holds
for the T-S model; for a nonlinear plant it holds where the T-S model is exact
(sector nonlinearity), robustness to model errors is not certified.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .._dtype import require_x64
from .._errors import (
    FunctionalObservabilityError,
    ImpulseObservabilityError,
)
from .._linalg import row_space
from ..observer import TakagiSugenoObserver
from ..plant import check_functional, TakagiSugenoSystem
from . import _lmi
from ._conditions import check_regular
from ._functional import (
    AbstractStructureDesign,
    carried_extra,
    check_kind,
    check_q1,
    prepare_structure,
    solve_gains,
    split_Y,
    TIGHTEN,
    verify_structure_design,
)
from ._parameterization import observer_structure
from ._regions import AbstractRegion, as_region, Disk
from ._verify import VerificationReport


@dataclasses.dataclass(frozen=True)
class TakagiSugenoObserverDesign(AbstractStructureDesign):
    """A verified Takagi–Sugeno functional-observer design.

    Attributes (besides `structure`, `params`, `T`, `K`, `Z_eff`, `X`, `report` and `solver`,
    which every design on a `FunctionalObserverStructure` has):
        observer: the `TakagiSugenoObserver` (per-rule matrices, common T, the plant's membership).
        kind: ``"generalized"``, ``"PI"`` or ``"proportional"``.
        region: the pole region of every rule's (and every convex combination's) error dynamics.

    Here `structure` has ``psi="output"`` and rule-stacked A, B; `params` are ``Z`` (common)
    and ``Y1, Y2, Y3, J, G`` with a leading rule axis; `T`, `K`, `Z_eff` are the common
    matrices of ``T E + K C = R``; `X` is the common LMI certificate; `report` covers all
    rules (``extra`` holds the Lyapunov re-check ``lyapunov_max_eig``).
    """

    observer: TakagiSugenoObserver
    kind: str
    region: AbstractRegion

    @property
    def num_rules(self) -> int:
        return self.observer.num_rules

    @property
    def error_matrices(self) -> np.ndarray:
        """``(k, q0+q1, q0+q1)``: 𝔸_i of every rule."""
        return np.asarray(self.observer.error_matrices)

    def verify(self) -> VerificationReport:
        """Re-run the float64 verification (`fojax.design.AbstractDesign.verify`): conditions
        a.–d. of every rule, every rule's eigenvalues in `region`, the region LMI and the
        common Lyapunov inequality at the common `X`."""
        return verify_structure_design(self.structure, self.params, self.region, self.X,
                                       extra=carried_extra(self.report), common_lyapunov=True)[1]

    def __str__(self) -> str:
        o = self.observer
        return (
            f"{self.kind} Takagi–Sugeno functional observer ({o.num_rules} rules, common T): "
            f"q0 = {o.q0}, q1 = {o.q1}, estimates q = {o.output_size} functions; error poles of "
            f"every rule in {self.region.describe()}\n{self.report}"
        )


# ---------------------------------------------------------------------------- checks


def check_impulse_observability(E, A_rules, C) -> None:
    """Assumption 2: ``rank [E; E⊥A_i; C] = n`` for every rule; raises `ImpulseObservabilityError`."""
    from ..analysis._observability import functional_rank_pair

    E, C = np.asarray(E, float), np.asarray(C, float)
    n = E.shape[0]
    for i, Ai in enumerate(np.asarray(A_rules, float)):
        # rank Γ_i = rank [E; E⊥A_i; C] as fojax.analysis decides it (normalised blocks)
        _, r = functional_rank_pair(E, Ai, C, np.zeros((0, n)))
        if r != n:
            raise ImpulseObservabilityError(
                "impulse observability (Assumption 2)",
                f"rank [E; E⊥A_{i + 1}; C] = {r} < n = {n} for rule {i + 1}: the algebraic "
                f"(fast) part of rule {i + 1}'s model is not seen by the outputs.",
                "Add outputs (rows of C) that measure the algebraic variables, or remodel the "
                "algebraic equations of that rule so that they determine the fast states.",
                lhs=r,
                rhs=n,
            )


def check_output_functional_observability(E, C, L) -> None:
    """Functional observability with Γ = [E; C] (the T-S observer measures w = y only)."""
    from ..analysis._observability import functional_rank_pair

    E, C, L = (np.asarray(x, float) for x in (E, C, L))
    Gam = np.vstack([E, C])
    r1, r0 = functional_rank_pair(E, np.zeros_like(E), C, L, output_only=True)
    if r1 != r0:
        basis = row_space(Gam)
        resid = L - L @ basis.T @ basis
        bad = [j + 1 for j in range(L.shape[0]) if np.linalg.norm(resid[j]) > 1e-9 * max(1.0, np.linalg.norm(L[j]))]
        raise FunctionalObservabilityError(
            "functional observability with Γ = [E; C] (Assumption 1, §3.3.2)",
            f"rank [L; E; C] = {r1} but rank [E; C] = {r0}: row(s) {bad} of L are not in the row "
            "space of [E; C]. The Takagi–Sugeno observer (3.152) uses only the measured output "
            "y, so a functional that is only determined through the rule-dependent algebraic "
            "rows E⊥A_i (e.g. an algebraic state) cannot be estimated.",
            "Estimate another functional (rows of L in the row space of [E; C]), or add outputs "
            "(rows of C) measuring the missing directions.",
            lhs=r1,
            rhs=r0,
        )


# ---------------------------------------------------------------------------- public


def design_ts_observer(
    ts_sys: TakagiSugenoSystem,
    L,
    *,
    kind: str = "generalized",
    region=None,
    R=None,
    q0: int | None = None,
    q1: int | None = None,
    margin: float = 1e-3,
    solver: str = _lmi.DEFAULT_SOLVER,
) -> TakagiSugenoObserverDesign:
    r"""Design a verified Takagi–Sugeno functional observer (thesis §3.3, Algorithm 1).

    See the module docstring for the method and what the common certificate proves.

    **Arguments:**

    - `ts_sys`: a `fojax.TakagiSugenoSystem` (common $E$, $C$; rules $A_i$, $B_i$).
    - `L`: ``(q, n)`` functional; its rows must lie in the row space of $[E; C]$.
    - `kind`: ``"generalized"`` (eq. 3.152), ``"PI"`` ($S_i = 0$) or
      ``"proportional"`` ($q_1 = 0$, §3.3.4, eq. 3.185).
    - `region`: pole region of every rule's error dynamics (a `fojax.Disk`,
      `fojax.HalfPlane`, `fojax.Sector`, an intersection, or ``(center, radius)``).
      Default ``Disk(-2, 1)``.
    - `R`: ``(q0, n)`` with rows in the row space of $[E; C]$; default chosen by
      `fojax.design.default_R` (over all rules).
    - `q0`: observer order when `R` is not given.
    - `q1`: size of ``v`` (default ``q0`` for generalized/PI, 0 for proportional).
    - `margin`: strictness of the LMIs (``⪯ -margin·I`` with ``X ⪰ I``).
    - `solver`: ``"auto"`` (default), ``"CLARABEL"`` or ``"SCS"``.

    **Returns:** a `TakagiSugenoObserverDesign` (residuals of a.–d. for every rule
    ≤ 1e-8 relative, eigenvalues of every $\mathbb A_i$ in `region`, the region LMI
    and the Lyapunov inequality re-checked at the common $X$ in float64).

    **Raises:** `IrregularSystemError` (a rule whose pencil $sE - A_i$ is singular,
    naming the rule), `DataRangeError`, `ImpulseObservabilityError` (Assumption 2,
    naming the rule),
    `FunctionalObservabilityError` (with Γ = [E; C]), `RankConditionError`,
    `DetectabilityError` (naming the rule), `LMIInfeasibleError`,
    `DesignVerificationError`.
    """
    if not isinstance(ts_sys, TakagiSugenoSystem):
        raise TypeError(
            f"expected a fojax.TakagiSugenoSystem, got {type(ts_sys).__name__}; for a linear "
            "plant use fojax.design.design_functional_observer."
        )
    require_x64("observer design")
    check_kind(kind)
    region = as_region(region if region is not None else Disk(-2.0, 1.0))
    q1 = check_q1(kind, q1)
    E, A, B, C = (np.asarray(x, float) for x in (ts_sys.E, ts_sys.A, ts_sys.B, ts_sys.C))
    L = np.asarray(check_functional(ts_sys, L))
    for i, Ai in enumerate(A):  # every rule's pencil, as fojax.analysis.is_regular decides
        check_regular(E, Ai, fname="design_ts_observer", what=f"rule {i + 1} (E, A_{i + 1})")
    check_impulse_observability(E, A, C)
    check_output_functional_observability(E, C, L)
    s = prepare_structure(
        ts_sys.rule(0), L, R=R, q0=q0, q1=0, region=region, psi="output", A_rules=A, B_rules=B,
        fname="design_ts_observer",
    )
    if q1 is None:
        q1 = s.q0
    s = observer_structure(s.E, s.A, s.B, s.C, s.L, s.R, q1=q1, psi="output", Eperp=s.Eperp)
    X, Z, Ys, info = solve_gains(s, region.tightened(TIGHTEN), kind=kind, margin=margin, solver=solver)
    c = s.q0 + s.nw
    blocks = [split_Y(Y, s.q0, c) for Y in Ys]
    params = {
        "Z": np.asarray(Z),
        "Y1": np.stack([b["Y1"] for b in blocks]),
        "Y2": np.stack([b["Y2"] for b in blocks]),
        "Y3": np.zeros((s.num_rules, s.q, c)),
        "J": np.stack([b["J"] for b in blocks]),
        "G": np.stack([b["G"] for b in blocks]),
    }
    mats, report = verify_structure_design(s, params, region, X, extra={"LMI route": info["lmi"]["route"]},
                                           common_lyapunov=True)
    p, m = C.shape[0], B.shape[-1]
    Wu, Wy = np.zeros((p, m)), np.eye(p)  # w = y (psi="output")
    obs = TakagiSugenoObserver(
        mats.N, mats.J, mats.F, mats.H, mats.S, mats.G, mats.M, mats.P, mats.Q,
        Wu, Wy, mats.T, ts_sys.membership, kind=kind,
    )  # fmt: skip
    return TakagiSugenoObserverDesign.from_matrices(s, mats, params, observer=obs, kind=kind, region=region,
                                                    X=np.asarray(X), report=report, solver=info)
