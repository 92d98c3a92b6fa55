r"""The region LMI route of generalized, PI and proportional functional observers (thesis §3.1).

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

Above observer order `SMALL_ORDER`, one rule's LMI is solved in the reduced form of
`fojax.design._eliminated` (same feasible set, the gains eliminated); this full LMI is its
fallback and serves rules, several regions and the centred and performance objectives.

Every result is verified in float64 (`fojax.design.verify`) before it is returned.
"""

from __future__ import annotations

import numpy as np

from .._errors import combined_failure, LMI_FAILURES
from .._linalg import row_space
from . import _ladder
from ._conditions import unobservable_modes
from ._lmi import (
    check_solver,
    ConicLMI,
    DEFAULT_SOLVER,
    describe_route,
    region_lmi,
    solve,
    solve_conic,
    value,
)
from ._parameterization import FunctionalObserverStructure, pieces
from ._regions import AbstractRegion


def choose_Z(
    s: FunctionalObserverStructure,
    region: AbstractRegion,
    *,
    margin: float = 1e-3,
    force_lmi: bool = False,
    solver: str = DEFAULT_SOLVER,
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
    eps = float(margin)
    for i in range(k):
        Phi = X1 @ N1[i] - W @ N2[i] - Ws[i] @ N3
        Mx = region_lmi(region, X1, Phi)
        cons.append(Mx << -eps * np.eye(Mx.shape[0]))
    obj = cp.Minimize(cp.norm(W, "fro") + sum(cp.norm(w, "fro") for w in Ws))
    info = solve(
        cp.Problem(obj, cons),
        "choose Z (proportional region LMI, W = X1 Z)",
        hint="The fixed modes are outside the region for every Z: choose another R, a larger "
        "observer order q0, more outputs, or a larger region.",
        solver=solver,
    )
    Z = np.linalg.solve(value(X1), value(W))
    return Z, {"step1": info}


def solve_gains(
    s: FunctionalObserverStructure,
    region: AbstractRegion | tuple[AbstractRegion, ...],
    *,
    kind: str,
    margin: float = 1e-3,
    solver: str = DEFAULT_SOLVER,
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
    c = N3.shape[0]
    d = q0 + q1
    # The gains act only through W N2 and 𝒲 𝔸2: W = W' U_Zᵀ and 𝒲 = 𝒲' diag(U_3, I)ᵀ with
    # orthonormal bases U_Z, U_3 of the column spaces of [N2_1 … N2_k] and N3 lose no
    # feasible error dynamics and no part of the minimum-gain objective (the dropped
    # components change no constraint and only add to the norms), with fewer variables.
    # (Observers of order at most SMALL_ORDER keep the full variables: their LMIs are cheap.)
    reduce = d > SMALL_ORDER
    if reduce:
        UZ = row_space(np.hstack(list(N2)).T).T if N2.size else np.zeros((N2.shape[1], 0))
        U3 = row_space(N3.T).T if N3.size else np.zeros((c, 0))
    else:
        UZ, U3 = np.eye(N2.shape[1]), np.eye(c)
    r3 = U3.shape[1]
    N2r = [UZ.T @ N2i for N2i in N2]
    A2 = np.block([[U3.T @ N3, np.zeros((r3, q1))], [np.zeros((q1, q0)), -np.eye(q1)]])
    back = np.block([[U3.T, np.zeros((r3, q1))], [np.zeros((q1, c)), np.eye(q1)]])  # 𝕐 = 𝕐' back
    # Π couples ε and v in the certificate (thesis); it is only needed to linearize
    # W = X1 Z, so with Z given the generalized certificate is a full matrix.
    Pi = np.eye(q0, q1) if kind == "generalized" else np.zeros((q0, q1))
    full_X = Z is not None and kind == "generalized"
    # With Z free, the regions share X1 (so that W = X1 Z is one variable); with Z
    # given, every region has its own certificate.
    X1 = cp.Variable((q0, q0), symmetric=True)
    W = cp.Variable((q0, UZ.shape[1])) if Z is None else None
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
        Ws = [cp.Variable((d, r3 + q1)) for _ in range(k)]
        for i in range(k):
            if full_X:
                A1i = np.block([[N1[i] - Z @ N2[i], np.zeros((q0, q1))], [np.zeros((q1, d))]])
                XA1 = X @ A1i
            else:
                top = X1 @ N1[i] - (W @ N2r[i] if Z is None else X1 @ (Z @ N2[i]))
                XA1 = cp.bmat([[top, np.zeros((q0, q1))], [Pi.T @ top, np.zeros((q1, q1))]]) if q1 else top
            Phi = XA1 - Ws[i] @ A2
            Mx = region_lmi(reg, X, Phi)
            cons.append(Mx << -eps * np.eye(Mx.shape[0]))
            if kind == "PI" and q1 and reduce:
                if r3:  # (with r3 = 0, N3 = 0 and S = 0 already)
                    cons.append(Ws[i][q0:, :r3] == 0)  # S = -Y2 N3 = 0 (U_3ᵀ N3 has full row rank)
            elif kind == "PI" and q1:
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
        X1v = value(X1)
        Zv = np.linalg.solve(0.5 * (X1v + X1v.T), value(W)) @ UZ.T
    else:
        Zv = np.asarray(Z)
    Xvs, Yss = [], []
    for X, Ws in zip(Xs, Wss):
        Xv = np.asarray(X.value, dtype=float)
        Xv = 0.5 * (Xv + Xv.T)
        # 𝕐 in the range of 𝔸2 by construction (components outside it would not change 𝔸
        # but enlarge F and M)
        # (the full variables: components outside the range of 𝔸2 projected away)
        Ys = [np.linalg.solve(Xv, value(w)) @ (back if reduce else A2 @ np.linalg.pinv(A2)) for w in Ws]
        if kind == "PI" and q1:
            for Y in Ys:
                Y[q0:, :c] = 0.0  # exactly zero already up to the solver's round-off
        Xvs.append(Xv)
        Yss.append(Ys)
    if multi:
        return Xvs, Zv, Yss, {"lmi": info}
    return Xvs[0], Zv, Yss[0], {"lmi": info}


#: Observers of at most this order ``q0 + q1`` take the LMI route by default
#: (`fojax.design._functional.choose_route`) and keep the LMI's full gain variables.
SMALL_ORDER = 12
#: The objectives `solve_with_fallbacks` tries, in order, with each solver.
OBJECTIVES = ("min-gain", "feasibility")


def solve_with_fallbacks(obj, cons, name: str, hint: str, solver: str) -> dict:
    """Solve ``min obj s.t. cons``, falling back to the feasibility problem.

    Minimum-gain solutions sit on the boundary of the feasible set, where the solvers
    sometimes stop at "optimal_inaccurate". The pure feasibility problem (interior
    point) is better conditioned; it is a fallback because its gains are larger.
    With ``solver="auto"`` the order is: Clarabel (min-gain), Clarabel (feasibility),
    SCS (min-gain), SCS (feasibility); each of these first retries the same solver with
    looser settings (`fojax.design.solve`), so that the min-gain problem does not
    fall back because of the last digits of a BLAS kernel. Only status ``optimal`` is
    ever accepted, and the caller verifies the solution in float64 whatever route
    produced it. ``info["route"]`` says which one did (also shown in the design's report).
    """
    import cvxpy as cp

    def rung(sv, o):
        return lambda: solve(cp.Problem(cp.Minimize(obj if o == "min-gain" else 0), cons), name, hint=hint, solver=sv)

    return _climb(rung, name, hint, solver)


def solve_conic_with_fallbacks(prob: ConicLMI, name: str, hint: str, solver: str,
                               objectives: tuple | None = None) -> tuple[np.ndarray, dict]:
    """`solve_with_fallbacks` for a `fojax.design._lmi.ConicLMI`: the same ladder (over
    `objectives`, default `OBJECTIVES`), with the Clarabel rungs solving the conic program directly
    (`fojax.design._lmi.solve_conic`: no cvxpy canonicalisation) and the SCS rungs through
    cvxpy (`ConicLMI.to_cvxpy`, built once, when first needed). Returns ``(x, info)``."""
    built: dict = {}

    def rung(sv, o):
        p = prob if o == "min-gain" else prob.feasibility()
        if sv == "CLARABEL":
            return lambda: solve_conic(p, name, hint)

        def via_cvxpy():
            import cvxpy as cp
            if "x" not in built:
                built["x"], built["obj"], built["cons"] = prob.to_cvxpy()
            obj = built["obj"] if o == "min-gain" else 0
            info = solve(cp.Problem(cp.Minimize(obj), built["cons"]), name, hint=hint, solver=sv)
            return value(built["x"]), info
        return via_cvxpy

    info = _climb(rung, name, hint, solver, objectives)
    return info.pop("x"), info


def _climb(rung, name: str, hint: str, solver: str, objectives: tuple | None = None) -> dict:
    """The ladder of `solve_with_fallbacks`: ``rung(solver, objective)`` makes the thunk of
    one rung (returning ``info``, or ``(x, info)``: then ``info["x"] = x``)."""
    solvers = ("CLARABEL", "SCS") if check_solver(solver) == "AUTO" else (check_solver(solver),)
    rungs = [((sv, o), rung(sv, o)) for sv in solvers for o in (OBJECTIVES if objectives is None else objectives)]

    def status(label, err):
        why = f": {err.info['message']}" if err.info.get("message") else ""
        return f"{err.status} ({label[0]}, {label[1]}{why})"

    try:
        (sv, o), info, refused = _ladder.climb(rungs, refusals=LMI_FAILURES)
    except _ladder.Refused as every:
        raise combined_failure(name, "; ".join(status(lb, e) for lb, e in every.refused),
                               [e for _, e in every.refused], {lb[0]: e.info for lb, e in every.refused}, hint) from None
    if isinstance(info, tuple):
        x, info = info
        info["x"] = x
    statuses = [status(lb, e) for lb, e in refused]
    info["objective"] = o
    if statuses:
        info["failed_attempts"] = list(statuses)
    info["route"] = describe_route(info, o) + (
        f"; refused before: {'; '.join(statuses)}" if statuses else "")
    return info
