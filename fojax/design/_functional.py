r"""LMI design of generalized, PI and proportional functional observers (thesis §3.1).

**Method (documented choice: linearizing change of variables, in two steps).**
The error dynamics are $\mathbb A = \mathbb A_1(Z) - \mathbb Y\mathbb A_2$ (see
`fojax.design.observer_matrices`); they are bilinear in $(Z, \mathbb Y)$.

1. *Choose Z.* If every mode of $N_1'$ is observable through $N_3$ or already
   inside the region, $Z = 0$. Otherwise solve the proportional region LMI for the
   $\varepsilon$-block with the variables $X_1 \succ 0$, $W = X_1Z$,
   $\mathcal W_1 = X_1 Y_1$ (the thesis's $W_i = X_{i1}Z_i$ substitution, Theorem 1),
   which is linear, and recover $Z = X_1^{-1}W$.
2. *Choose 𝕐 with Z fixed.* With $\Phi = X\mathbb A_1 - \mathcal W\mathbb A_2$ and
   $\mathcal W = X\mathbb Y$ the Chilali–Gahinet region condition
   $L_R\otimes X + M_R\otimes\Phi^\top + M_R^\top\otimes\Phi \prec 0$ is an LMI in
   $(X, \mathcal W)$ with a *full* Lyapunov matrix $X$ (no block structure is imposed,
   unlike the thesis's $X = [X_1\;X_1;\,X_1\;X_2]$, which silently assumes
   $q_0 = q_1$). $\mathbb Y = X^{-1}\mathcal W$. For PI observers ($S = 0$, i.e.
   $Y_2 = 0$) $X$ is block-diagonal and the $Y_2$ block of $\mathcal W$ is zero.

The LMIs are normalised by $X \succeq I$, require a strict margin
($\preceq -\epsilon I$) and minimise $\|\mathcal W\|_F$ (small gains). Compared with the
elimination lemma (Theorem 1, eq. 3.36) this yields the same feasible set of
error dynamics for fixed $Z$, and gives the certificate $X$ directly. The explicit
parameterization of all admissible 𝕐 (Lemma 7/10) is in `fojax.design.region_gain`
and `fojax.design.lemma10_gain`.

Every result is verified in float64 (`fojax.design.verify`) before it is returned.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from .._dtype import require_x64
from .._errors import (
    combined_failure,
    DesignVerificationError,
    FojaxError,
    InputError,
    LMI_FAILURES,
    LMIInfeasibleError,
    RankConditionError,
    ShapeError,
    SolverStoppedShortError,
)
from ..analysis._pencil import e_perp as _e_perp  # analysis decides the rank of E (balanced)
from ..observer._generalized import GeneralizedFunctionalObserver
from ..plant._descriptor import check_functional, DescriptorSystem
from . import _discrete, _ladder, _lmi, _riccati
from ._base import AbstractDesign, with_feedthrough
from ._conditions import (
    check_data_range,
    check_detectability,
    check_functional_observability,
    check_regular,
    check_structure,
    default_R,
    UNIT_FREE_CHECK_MAX as UNIT_FREE_CHECK_MAX,
    unit_free_structure,
    unobservable_modes,
)
from ._parameterization import (
    design_residuals,
    error_dynamics,
    FunctionalObserverStructure,
    observer_matrices,
    observer_structure,
    pieces,
    split_Y,
)
from ._regions import AbstractRegion, as_region, Disk
from ._verify import relative_residual, RESIDUAL_RTOL, VerificationReport, verify


KINDS = ("generalized", "PI", "proportional")
#: ``objective=`` of `design_functional_observer`.
OBJECTIVE_NAMES = ("region", "hinf", "h2", "centre")
#: LMIs target the region shrunk by this fraction (`AbstractRegion.tightened`), so that the
#: returned eigenvalues keep a margin inside the requested region.
TIGHTEN = 0.05


def check_kind(kind) -> str:
    """`kind` if it is one of `KINDS`, else `InputError` listing them and the closest one."""
    if kind in KINDS:
        return kind
    import difflib

    close = difflib.get_close_matches(str(kind), KINDS, n=1, cutoff=0.4) or difflib.get_close_matches(
        str(kind).lower(), [k.lower() for k in KINDS], n=1, cutoff=0.4)
    hint = ""
    if close:
        best = next(k for k in KINDS if k.lower() == close[0].lower())
        hint = f" Did you mean {best!r}?"
    raise InputError(
        f"kind must be one of {', '.join(map(repr, KINDS))} (the observer "
        f"structure); got {kind!r}.{hint}"
    )


class StructureDesignMixin:
    """``R`` and ``L`` of a design object that holds a `FunctionalObserverStructure`."""

    structure: FunctionalObserverStructure

    def _state_factors(self):
        b = (getattr(self, "solver", None) or {}).get("balance")
        return None if b is None else np.asarray(b["state_factors"], dtype=float)

    @property
    def R(self) -> np.ndarray:
        """``R`` in the model's own state units (a ``balance=True`` design holds ``R D_r``)."""
        dr = self._state_factors()
        return np.asarray(self.structure.R) if dr is None else np.asarray(self.structure.R) / dr[None, :]

    @property
    def L(self) -> np.ndarray:
        dr = self._state_factors()
        return np.asarray(self.structure.L) if dr is None else np.asarray(self.structure.L) / dr[None, :]

    @property
    def certificate(self) -> np.ndarray:
        """The certificate of the region placement: the Lyapunov matrix ``X``."""
        return self.X


#: Entries of `VerificationReport.extra` that `verify` computes (not carried over by a re-run).
COMPUTED_EXTRA = ("lyapunov_max_eig", "H∞")


@dataclasses.dataclass(frozen=True)
class FunctionalObserverDesign(StructureDesignMixin, AbstractDesign):
    """A verified functional-observer design.

    Attributes:
        observer: the `GeneralizedFunctionalObserver` (proportional/PI are special cases).
        kind: ``"generalized"``, ``"PI"`` or ``"proportional"``.
        region: the pole region the error dynamics were placed in.
        structure: the `FunctionalObserverStructure` (plant, L, R, E⊥).
        params: the free parameters ``Z, Y1, Y2, Y3, J, G`` (numpy arrays).
        T, K, Z_eff: the matrices of ``T E + K Ψ = R``; ``Z_eff`` is the Z of eq. 3.17.
        X: the LMI certificate (Lyapunov matrix) of the error dynamics.
        report: the float64 `VerificationReport`.
        solver: solver information (status, iterations, LMI steps).
        hinf: the `fojax.design.HinfCertificate` (γ, the independent norm) of an
            ``objective="hinf"`` design, else ``None``.
        h2: the `fojax.design.H2Certificate` (ν, the independent norm) of an
            ``objective="h2"`` design, else ``None``.
    """

    observer: GeneralizedFunctionalObserver
    kind: str
    region: AbstractRegion
    structure: FunctionalObserverStructure
    params: dict
    T: np.ndarray
    K: np.ndarray
    Z_eff: np.ndarray
    X: np.ndarray
    report: VerificationReport
    solver: dict
    hinf: Any = None
    h2: Any = None

    @property
    def error_matrix(self) -> np.ndarray:
        return np.asarray(self.observer.error_matrix)

    @property
    def dt(self) -> float | None:
        """The sampling period of a discrete-time design (``None``: continuous time)."""
        return self.observer.dt

    def verify(self) -> VerificationReport:
        """Re-run the float64 verification (`fojax.design.AbstractDesign.verify`): conditions
        a.–d. at `params`, the eigenvalues in `region`, the region LMI at `X` and, for an
        H∞ design, the bounded-real LMI at ``(X, γ)`` and ``γ ≥ ‖T‖∞`` (SLICOT AB13DD)."""
        checks = () if self.hinf is None else tuple(self.hinf.checks(self.structure, self.params, self.X))
        if (self.solver or {}).get("balance") is not None:
            return verify_balanced(self.structure, self.params, self.solver["balance"], self.region, self.X,
                                   extra=carried_extra(self.report), checks=checks)[1]
        return verify_structure_design(self.structure, self.params, self.region, self.X,
                                       extra=carried_extra(self.report), checks=checks, unit_free=UNIT_FREE_FIX)[1]

    def __str__(self) -> str:
        o = self.observer
        return (
            f"{self.kind} functional observer: q0 = {o.q0}, q1 = {o.q1}, estimates q = "
            f"{o.output_size} functions; error poles in {self.region.describe()}\n{self.report}"
        )


# ---------------------------------------------------------------------------- helpers


def _as_system(sys) -> DescriptorSystem:
    if not isinstance(sys, DescriptorSystem):
        raise TypeError(
            f"expected a fojax.DescriptorSystem, got {type(sys).__name__}; build one with "
            "fojax.DescriptorSystem(E, A, B, C)."
        )
    require_x64("observer design")
    return sys


def _eps(region: AbstractRegion, margin: float) -> float:
    return float(margin)


def choose_Z(
    s: FunctionalObserverStructure,
    region: AbstractRegion,
    *,
    margin: float = 1e-3,
    force_lmi: bool = False,
    solver: str = _lmi.DEFAULT_SOLVER,
) -> tuple[np.ndarray, dict]:
    """Step 1: the free Z (see module docstring). Returns ``(Z, info)``."""
    import cvxpy as cp
    pc = pieces(s)
    N1, N2, N3 = (np.asarray(x) for x in (pc.N1, pc.N2, pc.N3))
    k, q0 = N1.shape[0], s.q0
    nZ = N2.shape[1]
    need = force_lmi
    for i in range(k):
        modes = unobservable_modes(N1[i], N3)
        if any(not region.contains([lam]) for lam in modes):
            need = True
    if not need:
        return np.zeros((q0, nZ)), {"step1": "Z = 0 (every mode is assignable through N3 or inside the region)"}
    X1 = cp.Variable((q0, q0), symmetric=True)
    W = cp.Variable((q0, nZ))
    Ws = [cp.Variable((q0, N3.shape[0])) for _ in range(k)]
    cons = [X1 >> np.eye(q0)]
    eps = _eps(region, margin)
    for i in range(k):
        Phi = X1 @ N1[i] - W @ N2[i] - Ws[i] @ N3
        Mx = _lmi.region_lmi(region, X1, Phi)
        cons.append(Mx << -eps * np.eye(Mx.shape[0]))
    obj = cp.Minimize(cp.norm(W, "fro") + sum(cp.norm(w, "fro") for w in Ws))
    info = _lmi.solve(
        cp.Problem(obj, cons),
        "choose Z (proportional region LMI, W = X1 Z)",
        hint="The fixed modes are outside the region for every Z: choose another R, a larger "
        "observer order q0, more outputs, or a larger region.",
        solver=solver,
    )
    Z = np.linalg.solve(_lmi.value(X1), _lmi.value(W))
    return Z, {"step1": info}


def solve_gains(
    s: FunctionalObserverStructure,
    region: AbstractRegion | tuple[AbstractRegion, ...],
    *,
    kind: str,
    margin: float = 1e-3,
    solver: str = _lmi.DEFAULT_SOLVER,
    Z: np.ndarray | None = None,
):
    """The joint region LMI in ``(X1, X2, W = X1 Z, 𝒲 = X 𝕐)`` (Theorem 1, linearized).

    The certificate is ``X = [[X1, X1 Π], [Πᵀ X1, X2]]`` with ``Π = I`` (padded to
    ``q0 × q1``) for generalized observers — the thesis's structure, which makes
    ``X 𝔸1(Z)`` linear in ``(X1, W)`` and couples ε and v — and ``Π = 0`` for PI
    observers, whose constraint ``S = -Y2 N3 = 0`` is then the linear constraint
    ``𝒲[v-rows, :c] N3 = 0``. When `Z` is given it is kept fixed.

    `region` may be a tuple of regions: then one observer per region is designed
    with a *common* ``Z`` (hence a common ``T``) and a common block ``X1`` — what the
    finite-time observer needs. Every rule of a Takagi–Sugeno structure gets its own
    𝕐 with the common certificate.

    Returns ``(X, Z, [𝕐_i], info)`` for one region, or ``([X_r], Z, [[𝕐_ri]], info)``
    for a tuple of regions; ``𝕐 = [[Y1, J], [Y2, G]]``.
    """
    import cvxpy as cp
    multi = isinstance(region, tuple | list)
    regions = tuple(region) if multi else (region,)
    pc = pieces(s, xp=np)
    N1, N2, N3 = (np.asarray(x) for x in (pc.N1, pc.N2, pc.N3))
    k, q0, q1 = N1.shape[0], s.q0, s.q1
    c, nZ = N3.shape[0], N2.shape[1]
    d = q0 + q1
    A2 = np.block([[N3, np.zeros((c, q1))], [np.zeros((q1, q0)), -np.eye(q1)]])
    # Π couples ε and v in the certificate (thesis); it is only needed to linearize
    # W = X1 Z, so with Z given the generalized certificate is a full matrix.
    Pi = np.eye(q0, q1) if kind == "generalized" else np.zeros((q0, q1))
    full_X = Z is not None and kind == "generalized"
    # With Z free, the regions share X1 (so that W = X1 Z is one variable); with Z
    # given, every region has its own certificate.
    X1 = cp.Variable((q0, q0), symmetric=True)
    W = cp.Variable((q0, nZ)) if Z is None else None
    Xs, Wss = [], []
    cons = []
    eps = float(margin)
    for r, reg in enumerate(regions):
        if Z is not None and r > 0:
            X1 = cp.Variable((q0, q0), symmetric=True)
        if full_X:
            X = cp.Variable((d, d), symmetric=True)
        elif q1:
            X2 = cp.Variable((q1, q1), symmetric=True)
            X = cp.bmat([[X1, X1 @ Pi], [Pi.T @ X1, X2]])
        else:
            X = X1
        cons.append(X >> np.eye(d))
        Ws = [cp.Variable((d, c + q1)) for _ in range(k)]
        for i in range(k):
            if full_X:
                A1i = np.block([[N1[i] - Z @ N2[i], np.zeros((q0, q1))], [np.zeros((q1, d))]])
                XA1 = X @ A1i
            else:
                top = X1 @ N1[i] - (W @ N2[i] if Z is None else X1 @ (Z @ N2[i]))
                XA1 = cp.bmat([[top, np.zeros((q0, q1))], [Pi.T @ top, np.zeros((q1, q1))]]) if q1 else top
            Phi = XA1 - Ws[i] @ A2
            Mx = _lmi.region_lmi(reg, X, Phi)
            cons.append(Mx << -eps * np.eye(Mx.shape[0]))
            if kind == "PI" and q1:
                cons.append(Ws[i][q0:, :c] @ N3 == 0)
        Xs.append(X)
        Wss.append(Ws)
    # Minimum gain, plus tr X: without it the infimum of the gain norms is approached only
    # as an eigenvalue of X grows without bound (X ⪰ I is the only normalization), and the
    # solvers stop at "optimal_inaccurate"; with it the optimum is attained.
    obj = (
        sum(cp.norm(w, "fro") for Ws in Wss for w in Ws)
        + (cp.norm(W, "fro") if W is not None else 0)
        + sum(cp.trace(X) for X in Xs)
    )
    name = f"{kind} observer (region LMI in X, W = X1 Z, 𝒲 = X 𝕐)"
    hint = ("No observer gain places the error dynamics in the region: enlarge the region, "
            "or choose another R / observer order.")
    info = solve_with_fallbacks(obj, cons, name, hint, solver)
    if Z is None:
        X1v = _lmi.value(X1)
        Zv = np.linalg.solve(0.5 * (X1v + X1v.T), _lmi.value(W))
    else:
        Zv = np.asarray(Z)
    # Components of 𝕐 outside the range of 𝔸2 do not change 𝔸 but enlarge F and M:
    # project them away (projector onto the column space of 𝔸2).
    Pr = A2 @ np.linalg.pinv(A2)
    Xvs, Yss = [], []
    for X, Ws in zip(Xs, Wss):
        Xv = np.asarray(X.value, dtype=float)
        Xv = 0.5 * (Xv + Xv.T)
        Ys = [np.linalg.solve(Xv, _lmi.value(w)) @ Pr for w in Ws]
        if kind == "PI" and q1:
            for Y in Ys:
                # After the projection onto the range of 𝔸2, Y2 N3 = 0 implies Y2 = 0 exactly.
                Y[q0:, :c] = 0.0
        Xvs.append(Xv)
        Yss.append(Ys)
    if multi:
        return Xvs, Zv, Yss, {"lmi": info}
    return Xvs[0], Zv, Yss[0], {"lmi": info}


#: The objectives `solve_with_fallbacks` tries, in order, with each solver.
OBJECTIVES = ("min-gain", "feasibility")


def solve_with_fallbacks(obj, cons, name: str, hint: str, solver: str) -> dict:
    """Solve ``min obj s.t. cons``, falling back to the feasibility problem.

    Minimum-gain solutions sit on the boundary of the feasible set, where the solvers
    sometimes stop at "optimal_inaccurate". The pure feasibility problem (interior
    point) is better conditioned; it is a fallback because its gains are larger.
    With ``solver="auto"`` the order is: Clarabel (min-gain), Clarabel (feasibility),
    SCS (min-gain), SCS (feasibility); each of these first retries the same solver with
    looser settings (`fojax.design._lmi.solve`), so that the min-gain problem does not
    fall back because of the last digits of a BLAS kernel. Only status ``optimal`` is
    ever accepted, and the caller verifies the solution in float64 whatever route
    produced it. ``info["route"]`` says which one did (also shown in the design's report).
    """
    import cvxpy as cp
    solvers = ("CLARABEL", "SCS") if _lmi.check_solver(solver) == "AUTO" else (solver,)
    rungs = [((sv, o), (lambda sv=sv, o=o: _lmi.solve(cp.Problem(cp.Minimize(obj if o == "min-gain" else 0), cons),
                                                        name, hint=hint, solver=sv)))
             for sv in solvers for o in OBJECTIVES]

    def status(label, err):
        why = f": {err.info['message']}" if err.info.get("message") else ""
        return f"{err.status} ({label[0]}, {label[1]}{why})"

    try:
        (sv, o), info, refused = _ladder.climb(rungs, refusals=LMI_FAILURES)
    except _ladder.Refused as every:
        raise combined_failure(name, "; ".join(status(lb, e) for lb, e in every.refused),
                               [e for _, e in every.refused], {lb[0]: e.info for lb, e in every.refused}, hint) from None
    statuses = [status(lb, e) for lb, e in refused]
    info["objective"] = o
    if statuses:
        info["failed_attempts"] = list(statuses)
    info["route"] = _lmi.describe_route(info, o) + (
        f"; refused before: {'; '.join(statuses)}" if statuses else "")
    return info


def build_observer(s: FunctionalObserverStructure, mats, rule: int = 0, kind: str = "generalized"):
    """A `GeneralizedFunctionalObserver` from parameterized matrices (rule `rule`)."""
    Wu, Wy = s.w_matrices(s.rules_B()[min(rule, s.rules_B().shape[0] - 1)])
    return GeneralizedFunctionalObserver(
        mats.N[rule], mats.J[rule], mats.F[rule], mats.H[rule], mats.S[rule], mats.G[rule],
        mats.M[rule], mats.P[rule], mats.Q[rule], Wu, Wy, kind=kind,
    )


def carried_extra(report: VerificationReport) -> dict:
    """The notes of a stored report that a re-verification carries over (the route taken),
    without the entries `verify` computes again."""
    return {k: v for k, v in report.extra.items() if k not in COMPUTED_EXTRA}


def verify_structure_design(s, params, region, X, *, rtol=None, extra=None, common_lyapunov=False,
                            checks=(), unit_free: str | None = None) -> tuple[Any, VerificationReport]:
    """Compute the matrices for `params` and verify them (residuals, eigenvalues, LMI; the
    common Lyapunov inequality of every rule with `common_lyapunov`; `checks` as in
    `fojax.design.verify`). With `unit_free` (the fix its failure names, e.g.
    `UNIT_FREE_FIX`) also a.–d. in the unit-free frame (`unit_free_check`, after `checks`)."""
    if unit_free is not None:
        checks = tuple(checks) + tuple(c for c in (unit_free_check(s, params, unit_free),) if c)
    mats = observer_matrices(s, **{k: np.asarray(v) for k, v in params.items()}, xp=np)
    res = design_residuals(s, mats, xp=np)
    scale = float(res.pop("scale"))
    kw = {} if rtol is None else {"rtol": rtol}
    report = verify(
        {k: float(v) for k, v in res.items()},
        scale,
        np.asarray(error_dynamics(mats, xp=np)),
        region,
        X,
        extra=extra,
        scales=condition_scales(s, mats),
        common_lyapunov=common_lyapunov,
        checks=checks,
        **kw,
    )
    return mats, report


def condition_scales(s, mats) -> dict:
    """Per condition, the sum of the norms of its terms (host): the scale its residual is
    relative to in `verify` —
    a. ``‖N‖‖TE‖ + ‖F‖‖Ψ‖ + ‖T‖‖A‖``, b. ``‖H‖ + ‖T‖‖B‖``, c. ``‖S‖‖TE‖ + ‖M‖‖Ψ‖``,
    d. ``‖P‖‖TE‖ + ‖Q‖‖Ψ‖ + ‖L‖`` (max over rules, spectral norms)."""

    def nrm(x):
        x = np.asarray(x, dtype=float)
        if x.size == 0:
            return 0.0
        return float(np.max(np.linalg.norm(x.reshape((-1,) + x.shape[-2:]), ord=2, axis=(-2, -1))))

    As, Bs = np.asarray(s.rules_A()), np.asarray(s.rules_B())
    Psi = np.vstack([np.asarray(s.Eperp) @ As[0], np.asarray(s.C)])
    T = np.asarray(mats.T)
    TE, nP, nT = nrm(T @ np.asarray(s.E)), nrm(Psi), nrm(T)
    return {
        "a": nrm(mats.N) * TE + nrm(mats.F) * nP + nT * nrm(As),
        "b": nrm(mats.H) + nT * nrm(Bs),
        "c": nrm(mats.S) * TE + nrm(mats.M) * nP,
        "d": nrm(mats.P) * TE + nrm(mats.Q) * nP + nrm(s.L),
    }


def prepare_structure(sys: DescriptorSystem, L, *, R=None, q0=None, q1=0, region, psi="descriptor",
                      Eperp=None, A_rules=None, B_rules=None,
                      fname: str = "design_functional_observer") -> FunctionalObserverStructure:
    """Existence checks (regularity of every rule, the data range, Assumption 1, rank
    conditions, detectability) and the structure; `fname` names the caller in errors."""
    E, A, B, C = (np.asarray(x) for x in (sys.E, sys.A, sys.B, sys.C))
    if A_rules is not None:
        A, B = np.asarray(A_rules), np.asarray(B_rules)
    L = np.asarray(check_functional(sys, L))
    if Eperp is None:
        Eperp = _e_perp(E) if psi == "descriptor" else np.zeros((0, E.shape[0]))
    As = A if A.ndim == 3 else A[None]
    for i, Ai in enumerate(As):
        check_regular(E, Ai, fname=fname,
                      what=f"rule {i + 1} (E, A_{i + 1})" if len(As) > 1 else "the plant (E, A)")
    check_data_range({"E": E, "A": As, "B": B, "C": C, "L": L}, fname=fname)
    for Ai in As:
        check_functional_observability(E, Ai, C, L, Eperp, output_only=psi == "output")
    if R is None:
        R = default_R(E, A, B, C, L, psi=psi, Eperp=Eperp, region=region, q0=q0, q1=q1)
    else:
        R = np.asarray(R, dtype=float)
        if R.ndim != 2 or R.shape[1] != E.shape[0]:
            raise ShapeError("R", ("q0", E.shape[0]), tuple(R.shape), "R needs one column per state.")
        if q0 is not None and q0 != R.shape[0]:
            raise RankConditionError("observer order", f"q0 = {q0} but R has {R.shape[0]} rows.",
                                     "Give either R or q0.", lhs=q0, rhs=R.shape[0])
    s = observer_structure(E, A, B, C, L, R, q1=q1, psi=psi, Eperp=Eperp)
    check_structure(s)
    check_detectability(s, region)
    return s


# ---------------------------------------------------------------------------- public


def design_functional_observer(
    sys: DescriptorSystem,
    L,
    *,
    kind: str = "generalized",
    region: Any = None,
    R=None,
    q0: int | None = None,
    q1: int | None = None,
    margin: float = 1e-3,
    solver: str = _lmi.DEFAULT_SOLVER,
    method: str = "lmi",
    objective: str = "region",
    Bw=None,
    Dv=None,
    balance: bool | None = None,
) -> FunctionalObserverDesign:
    r"""Design a verified functional observer for $z = Lx$ (thesis §3.1, Theorems 1–2).

    **Arguments:**

    - `sys`: the plant, a `fojax.DescriptorSystem`: regular (checked first, with
      `fojax.analysis.is_regular`'s decision); $E$ may be singular, and the plant may even
      be impulsive when Assumption 1 holds (partial impulse observability with respect
      to $L$, thesis §3.1: the observer only uses $w = [-E^\perp Bu;\ y]$).
    - `L`: ``(q, n)`` functional to estimate.
    - `kind`: ``"generalized"`` (eq. 3.5), ``"PI"`` ($S = 0$) or ``"proportional"``
      ($q_1 = 0$).
    - `region`: where the error-dynamics eigenvalues must lie: a `fojax.Disk`,
      `fojax.HalfPlane`, `fojax.Sector`, an intersection (``&``) or a
      ``(center, radius)`` tuple. Default: ``Disk(-2, 1)``. For a discrete-time `sys`
      (``dt`` set) a region inside the unit disk, e.g. `fojax.design.DiscreteDisk`
      (default ``DiscreteDisk(0, 0.5)``); the result then has ``dt`` (`fojax.design._discrete`).
    - `R`: ``(q0, n)``; default chosen by `fojax.design.default_R` (documented there).
    - `q0`: observer order when `R` is not given.
    - `q1`: size of the auxiliary state ``v`` (default ``q0`` for generalized/PI, 0
      for proportional).
    - `margin`: strictness of the LMIs (``⪯ -margin·I`` with ``X ⪰ I``).
    - `solver`: ``"CLARABEL"`` (default) or ``"SCS"`` (see `fojax.design` notes on solvers).
    - `method`: ``"lmi"`` (default: the region LMI), ``"riccati"`` (a discrete Riccati
      equation for the gain and a Stein equation for the certificate, no SDP: disks,
      half-planes and sectors, generalized and proportional observers; O(n³), see
      `fojax.design._riccati`) or ``"auto"`` (the Riccati route where it applies, the
      LMI route otherwise). Either route is verified the same way; the route taken is
      in ``design.solver["lmi"]["route"]`` and printed in the report.
    - `objective`: ``"region"`` (default: eigenvalues in the region, minimum gains) or
      ``"hinf"``: also minimise a certified bound γ on the L2 gain from the disturbance
      ``w`` ($E\dot x = Ax + Bu + B_w w$) and the noise ``ν`` ($y = Cx + D_v\nu$) to
      $\hat z - z$ (`fojax.design._hinf`: derivation, conservatism, verification by
      SLICOT's AB13DD); the result's `hinf` holds γ and the independent norm; or
      ``"h2"``: minimise a certified bound ν on the H2 norm of the same map (it must have
      no feedthrough, else `InputError`; verified by SciPy's Lyapunov solver); the
      result's `h2` holds ν and the independent norm; or
      ``"centre"``: the error eigenvalues as far inside a bounded `region` (a disk, or an
      intersection with one) as the region LMI allows — the largest concentric tightening
      found by bisection (`fojax.design._centre`: derivation, relation to the thesis's LMI);
      ``design.solver["centre"]`` holds the fraction and the certified margin,
      ``design.report.region_margin`` the achieved one.
    - `Bw`, `Dv`: ``(n, mw)`` and ``(p, mv)`` channels of ``objective="hinf"``/``"h2"``.
    - `balance`: ``True`` makes the design independent of the units of the equations and
      states (issue 14 item 3): the observer is designed on the model rescaled by
      `fojax.analysis.unit_scaling`'s diagonal factors (the default ``R``, the LMI and its
      coordinates all see the same numbers whatever the units), mapped back exactly and
      verified on the model as given *and* in the unit-free frame (`balanced_design`:
      derivation). The result's `structure` and `params` are then the unit-free ones (so
      `fojax.tune` moves unit-free parameters); ``design.R``, ``L``, ``T``, ``K`` are in the
      model's units and ``design.solver["balance"]`` holds the factors. Measured on the LC
      filter of ``benchmarks/lc_filter.py`` and its twin with rows and states rescaled by
      1e-3…1e3: the same error eigenvalues, transfer function and region margin to
      round-off (``tests/test_unit_invariance.py``). ``False``: the design on the data as
      given (whose `structure` is the model's own, as code built on ``design.structure``
      expects); on a badly scaled model it can differ with the units and, in the extreme,
      miss $z$ — measured on that twin at the default order: an observer whose transfer
      function misses $z$ by 1.87 at $s = 0.3i$ passed the relative residual test on the
      raw data at 7e-10, because its terms are ~1e6. Every such design is therefore also
      verified in the unit-free frame (`unit_free_check`, models with ``l + n ≤ 200``), and
      fails with `DesignVerificationError` there. **Default ``None``**: the design on the
      data as given, and when it fails its float64 verification (the unit-free check, or a
      solver solution that misses a strict LMI in float64), the ``balance=True`` design
      instead (the report says why under ``"balance"``). Use ``balance=True`` for models
      whose rows or states span several orders of magnitude, and for the start of tuning. For
      ``objective="hinf"``/``"h2"`` the disturbance channel is mapped as $D_lB_w$ (``w`` keeps
      its units; ``Dv`` is unchanged since ``y`` is), so the norm is the same map's, and
      ``design.hinf``/``design.h2`` hold the unit-free frame's ``Bw``. Either way the default
      ``R`` is chosen unit-free
      (`fojax.design.default_R`).

    **Returns:** a `FunctionalObserverDesign` whose `report` shows residuals of
    conditions a.–d. (≤ 1e-8 relative), the error eigenvalues inside `region` and the
    region LMI re-checked in float64 at the certificate ``X``.

    **Raises:** `IrregularSystemError` (a singular pencil, with the failed rank decision),
    `DataRangeError` (a matrix whose largest entry is outside ``2^±100``: rescale its
    units), `FunctionalObservabilityError`, `RankConditionError`,
    `DetectabilityError` (existence conditions, checked before any LMI, with what to
    change), `LMIInfeasibleError` (solver status other than ``optimal``, or a solver
    exception, with its message), `DesignVerificationError` (a float64 check failed:
    each design condition relative to the norms of its own terms; for ``objective="hinf"``
    also the bounded-real LMI at ``(X, γ)`` and ``γ ≥ ‖T‖∞`` by SLICOT's AB13DD; for
    ``"h2"`` the Lyapunov inequality at ``X`` and ``ν ≥ ‖T‖₂``),
    `ShapeError`/`InputError` (a channel `Bw`/`Dv` of the wrong shape, or none).
    """
    check_kind(kind)
    _riccati.check_method(method)
    if objective not in OBJECTIVE_NAMES:
        raise InputError(f"objective must be one of {OBJECTIVE_NAMES}; got {objective!r}.")
    if objective not in ("hinf", "h2") and (Bw is not None or Dv is not None):
        raise InputError("Bw/Dv (disturbance and noise channels) are only used with objective='hinf' or "
                         "'h2'; pass one of them or drop Bw/Dv.")
    sys = _as_system(sys)
    region = _discrete.time_region(sys, region, objective)  # discrete time: inside the unit disk
    region = as_region(region if region is not None else Disk(-2.0, 1.0))
    if kind == "proportional":
        if q1 not in (None, 0):
            raise InputError(f"a proportional observer has q1 = 0 (no integral part); got q1 = {q1}. "
                             "Omit q1, or use kind='PI' or 'generalized'.")
        q1 = 0
    s = prepare_structure(sys, L, R=R, q0=q0, q1=0, region=region)
    if q1 is None:
        q1 = s.q0
    s = observer_structure(s.E, s.A, s.B, s.C, s.L, s.R, q1=q1, psi=s.psi, Eperp=s.Eperp)
    kw = dict(kind=kind, margin=margin, solver=solver, method=method)
    if objective in ("hinf", "h2"):
        from ._hinf import check_channels

        Bw, Dv = check_channels(s.n, s.p, Bw, Dv, objective=objective)
        perf = dict(objective=objective, Bw=Bw, Dv=Dv)

        def raw():
            return _performance_design(s, region, Bw=Bw, Dv=Dv, objective=objective, **kw)
    else:
        perf = dict(centre=objective == "centre")

        def raw():
            return _design_from_structure(s, region, **kw, **perf)

    d = unit_free_fallback(raw, lambda: balanced_design(s, region, **kw, **perf), balance, "a.-d.")
    return with_feedthrough(_discrete.with_dt(d, sys.dt), sys.D)


def unit_free_fallback(raw, balanced, balance: bool | None, conditions: str):
    """``balanced()`` when `balance` is true; else ``raw()``, and with ``balance=None`` the
    ``balanced()`` design when ``raw()`` failed its float64 verification (its report says
    why under ``"balance"``). The one rule of `design_functional_observer` and
    `design_unknown_input_observer` (`conditions` names theirs).

    Two failures of the raw design are fixed by the unit-free one: conditions a.–d. that hold
    on the data as given but not in the unit-free frame (badly scaled data), and a solver
    solution that misses a strict LMI in float64 (measured: the two-area power model's H2
    design, q0 = 5, region LMI at 1.3e-8 against the required < −2.4e-10 with SCS on the raw
    data; the unit-free design verifies with margin 0.126). Every balanced design is verified
    on the model as given as well, so this only changes which verified design is returned.
    When the balanced design fails too, the raw design's error is raised with its reason."""
    if balance:
        return balanced()
    try:
        return raw()
    except SolverStoppedShortError as err:  # balance=None: a solver that stopped short, again unit-free
        if balance is False:
            raise
        try:
            d = balanced()
        except FojaxError as again:
            raise SolverStoppedShortError(err.problem, err.status, err.info, balanced_error=again) from err
        note = f"the design on the data as given: {err}; designed on the unit-free model instead (balance=True)"
        return dataclasses.replace(d, report=dataclasses.replace(d.report, extra={**d.report.extra,
                                                                                  "balance": note}))
    except DesignVerificationError as err:  # balance=None: redesign unit-free
        if balance is False:
            raise
        rel = (getattr(err.report, "extra", None) or {}).get("unit-free relative residual")
        try:
            d = balanced()
        except FojaxError as again:
            raise DesignVerificationError(f"{err} (the design on the unit-free model, tried next, failed too: "
                                          f"{type(again).__name__}: {again})", err.report) from err
        if rel is not None and rel > RESIDUAL_RTOL:
            note = (f"the design on the data as given failed conditions {conditions} in the unit-free frame "
                    f"(relative residual {rel:.2e}; on the data as given {err.report.relative_residual:.2e}): "
                    "designed on the unit-free model instead (balance=True)")
        else:
            note = f"the design on the data as given: {err}; designed on the unit-free model instead (balance=True)"
        return dataclasses.replace(d, report=dataclasses.replace(d.report, extra={**d.report.extra,
                                                                                  "balance": note}))


def balanced_design(s, region, *, kind, margin, solver, method="lmi", centre=False, objective=None, Bw=None,
                    Dv=None):
    r"""Design on the unit-free model and map the observer back (``balance=True``).

    With $d_l, d_r$ of `fojax.analysis.unit_scaling` ($D_l, D_r$ diagonal), the scaled model
    is $E_b = D_lED_r$, $A_b = D_lAD_r$, $B_b = D_lB$, $C_b = CD_r$, $L_b = LD_r$, state
    $x_b = D_r^{-1}x$; the same $u$, $y$, $z$. Its design has $R_b = RD_r$ and
    $E_b^\perp$ (orthonormal). **The map back** (derived): take $E^\perp = E_b^\perp D_l$
    (still $E^\perp E = 0$, and $E^\perp B = E_b^\perp B_b$, $E^\perp A = E_b^\perp A_bD_r^{-1}$),
    so the measured signal $w$ is the same and $\Psi = \Psi_bD_r^{-1}$. The observer
    matrices $N, J, F, H, S, G, M, P, Q$ are unchanged (it is the same observer, driven by
    the same $u$, $w$); $T = T_bD_l$, $K = K_b$, since
    $\zeta - T_bE_bx_b = \zeta - T_bD_lEx$. Each condition is the balanced one times
    $D_r^{-1}$ on the right (a.: $NTE + F\Psi - TA = (N T_bE_b + F\Psi_b - T_bA_b)D_r^{-1}$,
    likewise c., d.; b.: $H = T_bB_b = TB$), so a.–d. are invariant statements. The
    certificate $X$ (of the error dynamics, which are unchanged) is the same.

    **What the design holds.** Its `structure` and `params` are the unit-free ones (so
    `fojax.tune` moves parameters that do not depend on the units either); ``design.R``,
    ``design.L``, ``design.T``, ``design.K`` are in the model's own units;
    ``design.solver["balance"]`` has $d_l$, $d_r$. **Verification** (`verify_balanced`,
    also what ``design.verify()`` runs): a.–d., eigenvalues and the region LMI in the
    unit-free frame, *and* a.–d. on the model as given, with the matrices above; the
    report is the latter's, the former's relative residual in its notes. Why both: on
    badly scaled data the relative residual test on the raw model is weak — measured on
    the LC filter's twin with ``balance=False``, an order-1 observer whose transfer
    function misses $z$ by 1.87 (absolute, at $s = 0.3i$) passed it at 7e-10, because
    its terms are ~1e6. (Mapping the free parameters into a structure built on the raw
    data instead fails the same way: that structure's solvability restriction $Z_0$,
    $\Pi_Z$ is decided on badly scaled numbers; measured: a wrong pole.)
    """
    from ..analysis._balance import scale_model, unit_scaling

    E, A, B, C, L = (np.asarray(x, dtype=float) for x in (s.E, s.A, s.B, s.C, s.L))
    dl, dr = unit_scaling(E, A, B, C)
    sb = observer_structure(*scale_model(dl, dr, E, A, B, C), L * dr, np.asarray(s.R) * dr, q1=s.q1, psi=s.psi)
    checks = ()
    if objective in ("hinf", "h2"):
        db = _performance_design(sb, region, kind=kind, margin=margin, solver=solver, Bw=dl[:, None] * np.asarray(Bw),
                                 Dv=Dv, method=method, objective=objective)
        checks = () if db.hinf is None else tuple(db.hinf.checks(sb, db.params, db.X))
    else:
        db = _design_from_structure(sb, region, kind=kind, margin=margin, solver=solver, method=method,
                                    centre=centre)
    solver_info = dict(db.solver)
    solver_info["balance"] = {"row_factors": dl.tolist(), "state_factors": dr.tolist()}
    mats, report = verify_balanced(sb, db.params, solver_info["balance"], region, db.X,
                                   extra=carried_extra(db.report), checks=checks)
    return FunctionalObserverDesign(
        observer=db.observer, kind=kind, region=region, structure=sb, params=db.params,
        T=np.asarray(mats.T) * dl[None, :], K=np.asarray(mats.K), Z_eff=np.asarray(mats.Z_eff), X=db.X,
        report=report, solver=solver_info, hinf=db.hinf, h2=db.h2,
    )  # fmt: skip


#: What a failed unit-free check of a design with ``balance`` tells the user.
UNIT_FREE_FIX = "design with balance=True"


def unit_free_check(s, params, fix: str = UNIT_FREE_FIX) -> tuple | None:
    r"""``("unit-free relative residual", value, failure or None)``: conditions a.–d. of the
    observer of `params` on `s`, re-checked in the unit-free frame of
    `fojax.analysis.unit_scaling` (a named check for `fojax.design.verify`), or ``None``
    when the model is larger than `UNIT_FREE_CHECK_MAX` or has rules.

    Why: the relative residual test on the data as given is weak on badly scaled models.
    Measured on the LC filter's twin (rows and states rescaled by 1e-3…1e3,
    ``benchmarks/lc_filter.py``): an order-1 observer designed on the raw data passed it at
    7e-10, because its terms are ~1e6, while its transfer function misses $z$ by 1.87 at
    $s = 0.3i$. In the unit-free frame ($E_b = D_lED_r$, …, $T_b = TD_l^{-1}$, the same
    $N, J, F, H, \dots$; each condition is the raw one times $D_r$ on the right, see
    `balanced_design`) its residual is 2.5e-3 relative. A.–d. are statements about the
    observer, not the units, so a correct observer passes in both frames.
    """
    uf = unit_free_structure(s)
    if uf is None:
        return None
    sb, dl, _ = uf
    mats = observer_matrices(s, **{k: np.asarray(v) for k, v in params.items()}, xp=np)
    mb = mats._replace(T=np.asarray(mats.T) / dl[None, :])
    res = design_residuals(sb, mb, xp=np)
    scale = float(res.pop("scale"))
    rel = relative_residual(res, scale, condition_scales(sb, mb))
    return ("unit-free relative residual", rel, unit_free_failure(rel, "a.-d.", fix))


def unit_free_failure(rel: float, conditions: str, fix: str = UNIT_FREE_FIX) -> str | None:
    """The failure of a unit-free check of `conditions` at relative residual `rel` (``None``:
    passed); `fix` says what to change."""
    return None if rel <= RESIDUAL_RTOL else (
        f"conditions {conditions} in the unit-free frame (fojax.analysis.unit_scaling) have relative residual "
        f"{rel:.2e} > {RESIDUAL_RTOL:.0e}: on this badly scaled model the observer passes the test on the "
        f"data as given only because its terms are large; {fix}")


def model_structure(sb, dl, dr):
    r"""The unit-free structure `sb` of a ``balance=True`` design back in the model's units:
    $E = D_l^{-1}E_bD_r^{-1}$, $A = D_l^{-1}A_bD_r^{-1}$, $B = D_l^{-1}B_b$, $C = C_bD_r^{-1}$,
    $L = L_bD_r^{-1}$, $R = R_bD_r^{-1}$, $E^\perp = E_b^\perp D_l$ (`balanced_design`)."""
    Eb, Ab, Bb, Cb, Lb = (np.asarray(x, dtype=float) for x in (sb.E, sb.A, sb.B, sb.C, sb.L))
    return observer_structure(Eb / dl[:, None] / dr, Ab / dl[:, None] / dr, Bb / dl[:, None], Cb / dr, Lb / dr,
                              np.asarray(sb.R) / dr, q1=sb.q1, psi=sb.psi, Eperp=np.asarray(sb.Eperp) * dl[None, :])


def verify_balanced(sb, params, balance: dict, region, X, *, extra=None, checks=()):
    r"""``(unit-free matrices, report)``: the verification of a ``balance=True`` design
    (`balanced_design`): in the unit-free frame of `sb`, then a.–d. on the model as given
    ($E = D_l^{-1}E_bD_r^{-1}$, …, $E^\perp = E_b^\perp D_l$, $T = T_bD_l$, $K = K_b$); the
    returned report is the latter, with the former's relative residual in its notes.
    Raises `fojax.DesignVerificationError` when either fails."""
    dl, dr = np.asarray(balance["row_factors"], float), np.asarray(balance["state_factors"], float)
    mats, rep_b = verify_structure_design(sb, params, region, X, extra=extra, checks=checks)
    so = model_structure(sb, dl, dr)
    mo = mats._replace(T=np.asarray(mats.T) * dl[None, :])
    res = design_residuals(so, mo, xp=np)
    scale = float(res.pop("scale"))
    note = (f"designed and verified on the unit-free model (fojax.analysis.unit_scaling: equations x "
            f"{dl.min():.3g}..{dl.max():.3g}, states x {dr.min():.3g}..{dr.max():.3g}), relative residual there "
            f"{rep_b.relative_residual:.2e}; the residuals above are on the model as given")
    report = verify({k: float(v) for k, v in res.items()}, scale, np.asarray(error_dynamics(mats, xp=np)), region,
                    X, extra={**rep_b.extra, "balanced": note}, scales=condition_scales(so, mo))
    return mats, report


def _lmi_params(s, Z, Ys) -> dict:
    """The free parameters of an LMI (or Riccati) solution ``(Z, Ys)`` (``Y3 = 0``)."""
    c = s.q0 + s.nw
    blocks = split_Y(Ys[0], s.q0, c)
    return {"Z": Z, "Y1": blocks["Y1"], "Y2": blocks["Y2"], "Y3": np.zeros((s.q, c)), "J": blocks["J"],
            "G": blocks["G"]}


def _performance_design(s, region, *, kind, margin, solver, Bw, Dv, objective, method="lmi"):
    """The H∞/H2 design (`fojax.design._hinf.design_hinf`) on the region-only design of `s`."""
    from ._hinf import design_hinf

    base = _design_from_structure(s, region, kind=kind, margin=margin, solver=solver, method=method)
    out = design_hinf(s, region, base=base, kind=kind, solver=solver, Bw=Bw, Dv=Dv, tighten=TIGHTEN,
                      objective=objective, verify=lambda *a, **k: verify_structure_design(*a, **k, unit_free=UNIT_FREE_FIX))
    mats = out.pop("mats")
    return FunctionalObserverDesign(observer=build_observer(s, mats, kind=kind), kind=kind, region=region, structure=s,
                                    T=np.asarray(mats.T), K=np.asarray(mats.K), Z_eff=np.asarray(mats.Z_eff), **out)


def _design_from_structure(s, region, *, kind, margin, solver, tighten=TIGHTEN, method="lmi", centre=False):
    why_not = _riccati.riccati_applies(region, kind, s.num_rules)
    if method == "riccati" and why_not is not None:
        raise InputError(f"method='riccati' does not apply: {why_not}. Use method='lmi' or 'auto'.")
    if centre and method == "riccati":
        raise InputError("objective='centre' searches the region LMI (method='lmi'); the Riccati route returns "
                         "one gain per region. Use method='lmi' or 'auto'.")
    extra = {}
    if centre:  # the largest tightening of the region that the LMI still meets (fojax.design._centre)
        from ._centre import centred_gains

        def solve_inside(reg):
            # a bisection step counts as feasible only if its gains put the error eigenvalues in
            # the tightened region in float64 (an 'optimal' solver status alone is not enough:
            # measured on fojax.models.flexible_drive at q0 = 2 with balance=True, the step at
            # fraction 0.99 returned an eigenvalue at +0.80 and the design failed verification)
            out = solve_gains(s, reg, kind=kind, margin=margin, solver=solver)
            ev = np.linalg.eigvals(np.asarray(error_dynamics(
                observer_matrices(s, **_lmi_params(s, out[1], out[2]), xp=np), xp=np))[0])
            if not reg.contains(ev):
                raise LMIInfeasibleError("region LMI (centre bisection step)", "optimal, but the float64 error "
                                         f"eigenvalues are outside the tightened region (max margin violation "
                                         f"{-float(np.min(reg.margin(ev))):.3g})", out[3].get("lmi"))
            return out

        X, Z, Ys, info = centred_gains(solve_inside, region, tighten)
        info["lmi"]["method"] = "lmi"
        c = info["centre"]
        bracket = (f"LMI infeasible above {c['infeasible_above']:.3f}" if c["infeasible_above"] is not None
                   else "the largest fraction tried")
        extra["centred"] = (f"region tightened by the fraction {c['fraction']:.3f} ({bracket}); certified "
                            f"margin >= {c['certified_margin']:.4g}")
    elif method != "lmi" and why_not is None:
        X, Z, Ys, info = _riccati.riccati_gains(s, region, kind=kind)
    else:
        X, Z, Ys, info = solve_gains(s, region.tightened(tighten), kind=kind, margin=margin, solver=solver)
        info["lmi"]["method"] = "lmi"
    params = _lmi_params(s, Z, Ys)
    route_key = "LMI route" if info["lmi"]["method"] == "lmi" else "design route"
    mats, report = verify_structure_design(s, params, region, X, extra={route_key: info["lmi"]["route"], **extra},
                                           unit_free=UNIT_FREE_FIX)
    obs = build_observer(s, mats, kind=kind)
    return FunctionalObserverDesign(
        observer=obs,
        kind=kind,
        region=region,
        structure=s,
        params={k: np.asarray(v) for k, v in params.items()},
        T=np.asarray(mats.T),
        K=np.asarray(mats.K),
        Z_eff=np.asarray(mats.Z_eff),
        X=X,
        report=report,
        solver=info,
    )
