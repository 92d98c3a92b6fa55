r"""Functional observers with unknown-input estimation (thesis §3.2, Lemma 9, Theorem 3.2.1).

**Problem.** For $E\dot x = Ax + Bu + Dd$, $y = Cx$, $z = Lx$ with an unknown
input $d \in \mathbb R^l$ (constant, or slowly varying), the observer
(`fojax.observer.UnknownInputObserver`)

$$\dot\zeta = N\zeta + Jv + Fw + Hu + \Delta\hat d,\quad
  \dot v = S\zeta + Gv + Mw,\quad
  \dot{\hat d} = \Phi\zeta + \Lambda v - Ww,\quad
  \hat z = P\zeta + Qw$$

estimates $z$ and $d$. With $\varepsilon = \zeta - TEx$, $\tilde d = \hat d - d$,
$\dot d = 0$ and

- a. $NTE + F\Psi - TA = 0$, b. $H = TB$, c. $\Delta = TD$,
- d. $STE + M\Psi = 0$, e. $\Phi TE - W\Psi = 0$, f. $PTE + Q\Psi = L$,

the error $\sigma = [\varepsilon; v; \tilde d]$ obeys $\dot\sigma = \mathbb A\sigma$,
$\mathbb A = \begin{bmatrix}N&J&\Delta\\S&G&0\\\Phi&\Lambda&0\end{bmatrix}$, and
$\hat z - z = P\varepsilon$.

**Deviations from the thesis (and why).**

1. $E^\perp$ is a basis of the left null space of $[E\;D]$, not of $E$: the measured
   signal $w = [-E^\perp Bu;\, y]$ must equal $\Psi x$, $\Psi = [E^\perp A; C]$, *with*
   the unknown input present, which needs $E^\perp D = 0$. (The thesis's proof uses
   $E^\perp D = 0$ without stating it as a choice of $E^\perp$.)
2. $W$ acts on the whole measured vector $w$ (the thesis writes $Wy$), and the
   $\hat d$ dynamics carry a free $\Lambda v$ term ($\Lambda = 0$ is the thesis's form).
3. Condition e. is solved exactly. The thesis's (3.137–3.140) takes $W$ arbitrary
   and $[\Phi\;\;-\bar K]\Sigma = WC$, which silently requires $\bar K = \Phi K$ — not
   guaranteed by its general solution. Instead, with
   $[TE; \Psi] = \begin{bmatrix}I&-K\\0&I\end{bmatrix}\Sigma$,
   e. reads $[\Phi,\; -\Phi K - W]\Sigma = 0$, whose general solution is
   $[\Phi,\; -\Phi K - W] = -Y_4(I - \Sigma\Sigma^+)$, i.e.

   $$\Phi = -Y_4N_3,\qquad W = Y_4F_3$$

   ($N_3 = (I-\Sigma\Sigma^+)[I;0]$, $F_3 = (I-\Sigma\Sigma^+)[K;I]$), for a free $Y_4$.
   Check: $[\Phi,\,-\Phi K - W]\Sigma = -Y_4(I - \Sigma\Sigma^+)\Sigma = 0$.

**Error dynamics as a linear-in-𝕐 expression.** With $N = N_1 - ZN_2 - Y_1N_3$,
$S = -Y_2N_3$ (see `fojax.design.observer_matrices`), $\Phi = -Y_4N_3$ and
$\Delta = TD$ (which depends on $Z$ only):

$$\mathbb A = \mathbb A_1 - \mathbb Y\mathbb A_2,\quad
  \mathbb A_1 = \begin{bmatrix}N_1 - ZN_2 & 0 & \Delta\\ 0&0&0\\0&0&0\end{bmatrix},\quad
  \mathbb Y = \begin{bmatrix}Y_1 & J\\ Y_2 & G\\ Y_4 & \Lambda\end{bmatrix},\quad
  \mathbb A_2 = \begin{bmatrix}N_3 & 0 & 0\\ 0 & -I & 0\end{bmatrix}.$$

(Check: $\mathbb Y\mathbb A_2 = [Y_1N_3,\,-J,\,0;\; Y_2N_3,\,-G,\,0;\; Y_4N_3,\,-\Lambda,\,0]$.)
The thesis's $\mathbb A_1$ contains $\Phi$ and its $\mathbb Y$ has no $\Lambda$.

**Design (Z fixed, full Lyapunov matrix).** $Z$ is chosen first (`choose_Z`: $Z = 0$
unless a mode of $N_1$ unobservable through $N_3$ lies outside the region; then the
proportional region LMI with $W = X_1Z$). With $Z$ fixed, $\mathbb A_1$ is constant
and the Chilali–Gahinet condition with $\mathcal W = X\mathbb Y$,

$$L_R\otimes X + M_R\otimes(X\mathbb A_1 - \mathcal W\mathbb A_2)^\top
  + M_R^\top\otimes(X\mathbb A_1 - \mathcal W\mathbb A_2) \prec 0,\qquad X \succ 0,$$

is an LMI in $(X, \mathcal W)$; $\mathbb Y = X^{-1}\mathcal W$ (minimising
$\|\mathcal W\|_F$, i.e. small gains). Its certificate is often ill-conditioned, so it is
solved in coordinates preconditioned by one pole-placement solution (see `_solve_lmi`);
the result is verified in the original coordinates. $X$ must be a *full*
matrix: for a block-diagonal $X = \operatorname{diag}(X_{\varepsilon v}, X_d)$ the
$\tilde d$-block of the LMI is $L_R\otimes X_d$ (the $\tilde d$-row of $X\mathbb A$ is
$X_d[\Phi\;\Lambda\;0]$, so the $(\tilde d, \tilde d)$ block of $X\mathbb A$ is $X_d\cdot 0$), and $L_R\otimes X_d \prec 0$ means that $s = 0$ lies in the region — never
true for a stable region (for a disk it needs $|\alpha| < \tau$, for the
Lyapunov region $0 < 0$). The coupling $X_{d\varepsilon}$ is what lets $\Delta$ make
the $\tilde d$ modes decay. (The thesis's Theorem 3.2.1 also uses a full $X$, with
the Lyapunov region only.)

**Existence conditions** (checked before any LMI, each with a typed error):
$D$ has full column rank; functional observability with the new $E^\perp$
(rank $[L; \Gamma]$ = rank $\Gamma$, $\Gamma = [E; E^\perp A; C]$); the rank
conditions of the parameterization (`check_structure`); the fixed modes of
$N_1$ (Lemma 8); and the **unknown-input mode**: $\tilde d$ contributes the
eigenvalue $0$ to $\mathbb A_1$, which must be observable through $\mathbb A_2$:
$\operatorname{rank}\begin{bmatrix}N_1 - ZN_2 & TD\\ N_3 & 0\end{bmatrix} = q_0 + l$
(two $Z$-independent necessary versions are checked first: the rank of the same
matrix with $Z$ eliminated, and $\operatorname{rank}N_3 \ge l$ — the $\tilde d$ columns
are seen only through $N_3\varepsilon$). It needs, e.g., $\operatorname{rank}(TD) = l$,
so $q_0 \ge l$. When the check fails at the chosen $Z$ but not for every $Z$, a few
seeded perturbations of $Z$ are tried (documented in `_ui_observable_Z`).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .._dtype import as_matrix
from .._errors import (
    combined_failure,
    DetectabilityError,
    ExistenceConditionError,
    FunctionalObservabilityError,
    LMI_FAILURES,
    RankConditionError,
    ShapeError,
)
from .._linalg import canonical_row_space, rank
from ..observer import UnknownInputObserver
from ..plant import check_functional, DescriptorSystem
from . import _ladder, _lmi
from ._base import with_feedthrough
from ._conditions import (
    check_data_range,
    check_detectability,
    check_order,
    check_regular,
    check_structure,
    default_R,
    require_equal_rank,
    unobservable_modes,
)
from ._discrete import continuous_only
from ._functional import (
    _as_system,
    carried_extra,
    choose_Z,
    TIGHTEN,
    unit_free_fallback,
)
from ._parameterization import (
    FunctionalObserverStructure,
    observer_matrices,
    observer_structure,
    pieces,
)
from ._regions import AbstractRegion, as_region, Disk
from ._stein import host_stein_certificate
from ._unknown_input_matrices import (
    UnknownInputObserverDesign,
    verify_unknown_input_design,
)


# ---------------------------------------------------------------------------- checks


def _check_D(D: np.ndarray) -> None:
    l = D.shape[1]
    if l == 0:
        raise ShapeError("D", ("n", "l >= 1"), tuple(D.shape), "Give at least one unknown-input direction.")
    r = rank(D)
    require_equal_rank("full column rank of D", r, l,
                       f"D is {D.shape[0]} x {l} but has rank {r}: the unknown inputs are not distinguishable "
                       "(some combination of them does not act on the plant), so d cannot be estimated.",
                       "Remove dependent columns of D (merge unknown inputs that enter along the same direction).")


def _check_functional_observability(E, A, C, L, Ep, D) -> None:
    from ..analysis._observability import functional_rank_pair

    # the ranks of fojax.analysis (normalised blocks), E⊥ spanning the left null space of [E D]
    r1, r0 = functional_rank_pair(E, A, C, L, D=D)
    if r1 != r0:
        raise FunctionalObservabilityError(
            "functional observability with the unknown input (Assumption 1, E⊥ annihilating [E D])",
            f"rank [L; E; E⊥A; C] = {r1} but rank [E; E⊥A; C] = {r0}, where E⊥ spans the left null "
            f"space of [E D] ({Ep.shape[0]} rows): the algebraic equations the unknown input enters "
            "no longer constrain x, and z = Lx is not determined by the measured signals.",
            "Estimate another functional (rows of L in the row space of [E; E⊥A; C]), add outputs "
            "measuring the missing directions, or model the unknown input so that it does not "
            "enter the algebraic equations.",
            lhs=r1,
            rhs=r0,
        )


def _fixed_part(s: FunctionalObserverStructure, Z) -> tuple[np.ndarray, np.ndarray]:
    r"""``(N1 - Z N2, T)`` at `Z` (host, float64): $N$ with the gains $Y_1 = 0$ (the constant
    block of $\mathbb A_1$) and $T$, both from `fojax.design.observer_matrices`, the one map
    from the free parameters to the observer matrices (so the dead components of `Z` are
    projected out exactly as in the observer that is verified and returned)."""
    shapes = s.param_shapes()
    gains = {k: np.zeros(shapes[k]) for k in ("Y1", "Y2", "Y3", "J", "G")}
    m = observer_matrices(s, np.asarray(Z, float), **gains, xp=np)
    return np.asarray(m.N[0]), np.asarray(m.T)


def _ui_mode_matrix_any_Z(s: FunctionalObserverStructure, D: np.ndarray) -> np.ndarray:
    """``[[N1', T1' D], [N2', Π T2 D], [N3, 0]]``: rank < q0 + l ⇒ no Z works.

    ``N1', T1'`` are ``N, T`` at ``Z = 0`` (`_fixed_part`); ``N2' = Π_Z N2`` and ``Π_Z T2``
    are the coefficients of ``-Z`` in them (``T(Z) = T1' - Z Π_Z T2``, checked against
    `observer_matrices` in the tests)."""
    pc = pieces(s, xp=np)
    N1p, T1p = _fixed_part(s, np.zeros(s.param_shapes()["Z"]))
    l = D.shape[1]
    N3 = np.asarray(pc.N3)
    return np.block(
        [
            [N1p, T1p @ D],
            [pc.N2[0], pc.PiZ @ pc.T2 @ D],
            [N3, np.zeros((N3.shape[0], l))],
        ]
    )


def _raise_ui_mode(r: int, need: int, q0: int, l: int, rTD: int | None, every_Z: bool):
    where = "for every Z" if every_Z else "at the chosen Z (and nearby Z)"
    extra = ""
    if rTD is not None and rTD < l:
        extra = f" (rank TD = {rTD} < l = {l}: some unknown input does not reach ζ)"
    raise DetectabilityError(
        "detectability of the unknown-input error (mode s = 0 of d̃, Lemma 9)",
        f"rank [[N1 - Z N2, T D], [N3, 0]] = {r} < q0 + l = {need} {where}{extra}: a constant "
        "unknown input cannot be told apart from a shift of the observer state, so d̂ - d "
        "would not converge.",
        f"Use a larger observer order q0 (now {q0}; at least l = {l} is needed) or another R whose "
        "rows see the directions D excites, add outputs, or estimate fewer unknown inputs.",
        lhs=r,
        rhs=need,
    )


def check_unknown_input_modes(s: FunctionalObserverStructure, D: np.ndarray, region: AbstractRegion,
                              Z: np.ndarray | None = None) -> None:
    """Detectability of the pair (𝔸2, 𝔸1) of the unknown-input observer.

    Without `Z`: the Z-independent necessary condition for the ``d̃`` mode. With `Z`:
    the modes of ``N1 - Z N2`` unobservable through ``N3`` must lie in `region`, and
    ``rank [[N1 - Z N2, T D], [N3, 0]] = q0 + l``.
    """
    q0, l = s.q0, D.shape[1]
    need = q0 + l
    if Z is None:
        # rank ≤ rank [[N1', T1'D], [N2', ΠT2D], [N3, 0]] and ≤ q0 + rank N3 for every Z.
        r = min(rank(_ui_mode_matrix_any_Z(s, D)), q0 + rank(np.asarray(pieces(s, xp=np).N3)))
        if r < need:
            _raise_ui_mode(r, need, q0, l, None, True)
        return
    N1z, T = _fixed_part(s, Z)
    N3 = np.asarray(pieces(s, xp=np).N3)
    bad = [lam for lam in unobservable_modes(N1z, N3) if not region.contains([lam])]
    if bad:
        raise DetectabilityError(
            "detectability of (𝔸2, 𝔸1) (Lemma 8 / Remark 3)",
            f"the mode(s) {', '.join(f'{b:.4g}' for b in bad)} of N1 - Z N2 cannot be moved by the "
            f"gains and are not in the requested region ({region.describe()}).",
            "Choose another R (or a larger observer order q0), add outputs, or enlarge the region.",
            lhs=bad,
            rhs=region.describe(),
        )
    TD = T @ D
    Mx = np.block([[N1z, TD], [N3, np.zeros((N3.shape[0], l))]])
    r = rank(Mx)
    if r < need:
        _raise_ui_mode(r, need, q0, l, rank(TD), False)


def _ui_observable_Z(s, D, region, Z, tries: int = 8) -> np.ndarray:
    """`Z` itself if the unknown-input mode is observable there; else the first of a few
    seeded perturbations ``Z + t Zr`` that makes it observable (the failing set of Z is
    algebraic, so a generic perturbation avoids it when any Z works) while keeping the
    other modes detectable. Raises the error of the unperturbed `Z` otherwise."""
    try:
        check_unknown_input_modes(s, D, region, Z)
        return Z
    except DetectabilityError as err:
        first = err
    rng = np.random.default_rng(0)
    scale = max(1.0, float(np.abs(Z).max()) if Z.size else 1.0)
    for k in range(tries):
        Zr = rng.standard_normal(Z.shape)
        Zt = Z + scale * (0.1 * 2.0 ** (k // 2)) * Zr / max(np.abs(Zr).max(), 1e-300)
        try:
            check_unknown_input_modes(s, D, region, Zt)
            return Zt
        except DetectabilityError:
            continue
    raise first


def _candidate_Rs(Gam: np.ndarray, Psi: np.ndarray, L: np.ndarray, q0: int | None) -> list[np.ndarray]:
    """Candidate R's of increasing order for unknown-input observers.

    Start from a row basis of ``L``; add, one at a time, directions of the row space of
    Γ that are new to Σ = [R; Ψ] (as `fojax.design.default_R` does), then rows of the
    row space of Ψ. The latter make Σ row-redundant, i.e. create the output-injection
    directions N3 ≠ 0 through which the unknown-input error is seen (rank N3 ≥ l is
    necessary); the plain functional observer never needs them. The bases are
    `fojax._linalg.canonical_row_space`, so the rows taken first do not depend on the rotation
    or signs an SVD returns (see `fojax.design._conditions._order_candidates`).
    """
    base = L if rank(L) == L.shape[0] else canonical_row_space(L)
    S0 = np.vstack([base, Psi])
    G_rows = canonical_row_space(Gam)
    extra = canonical_row_space(G_rows - G_rows @ np.linalg.pinv(S0) @ S0) if S0.size else G_rows
    pool = [*extra, *canonical_row_space(Psi), *G_rows]
    cands, R = [base], base
    for r in pool:
        if rank(np.vstack([R, r])) > R.shape[0]:
            R = np.vstack([R, r])
            cands.append(R)
    if q0 is None:
        return cands
    sel = [c for c in cands if c.shape[0] == q0]
    if not sel:
        raise RankConditionError(
            "observer order",
            f"q0 = {q0} is not between rank L = {base.shape[0]} and rank Γ = {G_rows.shape[0]} "
            "(Γ = [E; E⊥A; C], E⊥ annihilating [E D]).",
            "Choose q0 in that range, or pass R.",
            lhs=q0,
            rhs=(base.shape[0], G_rows.shape[0]),
        )
    return sel


def _choose_R(E, A, B, C, L, D, Ep, region, q0):
    """fojax's default R for unknown-input observers (see `_candidate_Rs`): the first
    candidate that passes every existence check; when only a fixed mode is outside the
    region, `default_R`'s search over R of the same order is tried."""
    Psi = np.vstack([Ep @ A, C])
    Gam = np.vstack([E, Psi])
    last: ExistenceConditionError | None = None

    def checks(R):
        s = observer_structure(E, A, B, C, L, R, q1=0, psi="descriptor", Eperp=Ep)
        check_structure(s)
        check_detectability(s, region)
        check_unknown_input_modes(s, D, region)

    for R0 in _candidate_Rs(Gam, Psi, L, q0):
        try:
            checks(R0)
            return R0
        except DetectabilityError as err:
            last = err
            if "mode s = 0" in str(err):
                continue
            try:  # fixed modes outside the region: search R of this order
                R = default_R(E, A, B, C, L, psi="descriptor", Eperp=Ep, region=region, q0=R0.shape[0], q1=0)
                checks(R)
                return R
            except ExistenceConditionError as err2:
                last = err2
        except ExistenceConditionError as err:
            last = err
    assert last is not None
    raise last


# ---------------------------------------------------------------------------- public


def design_unknown_input_observer(
    sys: DescriptorSystem,
    D,
    L,
    *,
    region=None,
    R=None,
    q0: int | None = None,
    q1: int | None = None,
    margin: float = 1e-3,
    solver: str = _lmi.DEFAULT_SOLVER,
    balance: bool | None = None,
) -> UnknownInputObserverDesign:
    r"""Design a verified functional observer that also estimates an unknown input (§3.2).

    See the module docstring for the formulas, the deviations from the thesis and the
    existence conditions.

    **Arguments:**

    - `sys`: the plant $E\dot x = Ax + Bu$, $y = Cx$ (a `fojax.DescriptorSystem`);
      the unknown input enters as $+Dd$.
    - `D`: ``(n, l)`` unknown-input directions (full column rank).
    - `L`: ``(q, n)`` functional to estimate.
    - `region`: region for all eigenvalues of $\mathbb A$ (default ``Disk(-2, 1)``);
      any `fojax` region or ``(center, radius)``.
    - `R`: ``(q0, n)`` with rows in the row space of $[E; E^\perp A; C]$. Default: the
      first of candidates of increasing order (a row basis of $L$, then new directions of
      $\Gamma$, then measured directions of $\Psi$ — these create the output-injection
      directions $N_3$ through which $\tilde d$ is seen) that passes every existence
      check, including the unknown-input mode; when only a fixed mode is outside the
      region, `fojax.design.default_R`'s search at that order is tried.
    - `q0`: observer order when `R` is not given.
    - `q1`: size of ``v`` (default ``q0``; 0 gives a proportional observer with
      unknown-input estimation).
    - `margin`: strictness of the LMI (``⪯ -margin·I`` with ``X ⪰ I``).
    - `solver`: ``"auto"`` (default), ``"CLARABEL"`` or ``"SCS"``.
    - `balance`: as for `fojax.design.design_functional_observer`. ``True``: the default
      ``R``, the LMI and its coordinates are computed on the model rescaled by
      `fojax.analysis.unit_scaling`'s diagonal factors ($E_b = D_lED_r$, $A_b = D_lAD_r$,
      $B_b = D_lB$, $C_b = CD_r$, $D_b = D_lD$, $L_b = LD_r$; the unknown input keeps its
      units) and mapped back exactly (the same observer; $T = T_bD_l$, $R = R_bD_r^{-1}$);
      verified on the model as given and in the unit-free frame. ``False``: on the data as
      given, also verified in the unit-free frame. **Default ``None``**: on the data as
      given, and the ``balance=True`` design when that design fails its float64
      verification (the unit-free check, or a solver solution that misses a strict LMI in
      float64; the report says why under ``"balance"``; `unit_free_fallback`): on badly
      scaled data a residual that is round-off on the data as given can be O(0.1) in the
      unit-free frame.

    **Returns:** an `UnknownInputObserverDesign`; its `report` lists the residuals of
    a.–f. (≤ 1e-8 relative, each relative to the norms of its own terms), the
    eigenvalues of $\mathbb A$ (inside `region`), the region LMI re-checked at $X$ and the
    unit-free relative residual. A ``balance=True`` design holds the unit-free `structure`
    and `params` (``design.R``, ``design.L``, ``design.T``, ``design.D`` are in the model's
    units; ``design.solver["balance"]`` has the factors).

    **Raises:** `IrregularSystemError` (singular pencil), `DataRangeError`, `ShapeError`,
    `RankConditionError` (rank of D, rank conditions),
    `FunctionalObservabilityError`, `DetectabilityError` (fixed modes, unknown-input
    mode), `LMIInfeasibleError` (infeasibility shown), `SolverStoppedShortError`,
    `DesignVerificationError`.
    """
    sys = _as_system(sys)
    continuous_only(sys, "design_unknown_input_observer")
    region = as_region(region if region is not None else Disk(-2.0, 1.0))
    E, A, B, C = (np.asarray(x, float) for x in (sys.E, sys.A, sys.B, sys.C))
    n = E.shape[0]
    D = np.asarray(as_matrix("D", D, rows=n, hint=f"D needs one row per state (n = {n})."))
    check_regular(E, A, fname="design_unknown_input_observer")
    _check_D(D)
    L = np.asarray(check_functional(sys, L))
    check_data_range({"E": E, "A": A, "B": B, "C": C, "D": D, "L": L},
                     fname="design_unknown_input_observer")
    if R is not None:
        R = np.asarray(as_matrix("R", R, cols=n, hint=f"R needs one column per state (n = {n})."))
    kw = dict(region=region, q0=q0, q1=q1, margin=margin, solver=solver)
    return with_feedthrough(unit_free_fallback(lambda: _design(E, A, B, C, D, L, R, **kw),
                                               lambda: _balanced_design(E, A, B, C, D, L, R, **kw), balance,
                                               "a.-f."), sys.D)


def _balanced_design(E, A, B, C, D, L, R, **kw) -> UnknownInputObserverDesign:
    """``balance=True`` (`design_unknown_input_observer`): design on the unit-free model, map back."""
    from ..analysis._balance import scale_model, unit_scaling

    dl, dr = unit_scaling(E, A, B, C)
    Rb = None if R is None else R * dr[None, :]
    Eb, Ab, Bb, Cb = scale_model(dl, dr, E, A, B, C)
    db = _design(Eb, Ab, Bb, Cb, dl[:, None] * D, L * dr, Rb, **kw)
    balance = {"row_factors": dl.tolist(), "state_factors": dr.tolist()}
    _, report = verify_unknown_input_design(db.structure, D, db.params, db.region, db.X,
                                            extra=carried_extra(db.report), balance=balance)
    return dataclasses.replace(db, D=D, T=np.asarray(db.T) * dl[None, :], report=report,
                               solver={**db.solver, "balance": balance})


def _design(E, A, B, C, D, L, R, *, region, q0, q1, margin, solver) -> UnknownInputObserverDesign:
    """The design on the data as given (`design_unknown_input_observer`, after its checks of the input)."""
    from ..analysis import (
        e_perp,  # analysis decides rank [E D] (balanced, blocks normalised)
    )

    Ep = e_perp(E, D=D)
    _check_functional_observability(E, A, C, L, Ep, D)
    if R is None:
        R = _choose_R(E, A, B, C, L, D, Ep, region, q0)
    else:
        check_order(R, q0)
    s = observer_structure(E, A, B, C, L, R, q1=0, psi="descriptor", Eperp=Ep)
    check_structure(s)
    check_detectability(s, region)
    check_unknown_input_modes(s, D, region)
    if q1 is None:
        q1 = s.q0
    s = observer_structure(E, A, B, C, L, R, q1=int(q1), psi="descriptor", Eperp=Ep)
    lmi_region = region.tightened(TIGHTEN)
    pc = pieces(s, xp=np)
    if all(lmi_region.contains([lam]) for lam in unobservable_modes(pc.N1[0], pc.N3)):
        # what `choose_Z` decides too, without its (JAX-traced, slow to compile) pieces
        Z, info = np.zeros((s.q0, pc.N2.shape[1])), {"step1": "Z = 0 (no fixed mode outside the region)"}
    else:
        Z, info = choose_Z(s, lmi_region, margin=margin, solver=solver)
    Z = _ui_observable_Z(s, D, region, Z)
    X, Yb, info["lmi"] = _solve_lmi(s, D, Z, lmi_region, margin=margin, solver=solver)
    q0, c = s.q0, s.q0 + s.nw
    params = {
        "Z": Z,
        "Y1": Yb[:q0, :c],
        "Y2": Yb[q0 : q0 + q1, :c],
        "Y3": np.zeros((s.q, c)),
        "J": Yb[:q0, c:],
        "G": Yb[q0 : q0 + q1, c:],
        "Y4": Yb[q0 + q1 :, :c],
        "Lambda": Yb[q0 + q1 :, c:],
    }
    mats, report = verify_unknown_input_design(s, D, params, region, X)
    p, m = C.shape[0], B.shape[1]
    Wu = np.vstack([-Ep @ B, np.zeros((p, m))])  # w = [-E⊥B u; y] (numpy: no JAX dispatch)
    Wy = np.vstack([np.zeros((Ep.shape[0], p)), np.eye(p)])
    obs = UnknownInputObserver(
        mats.N, mats.J, mats.F, mats.H, mats.Delta, mats.S, mats.G, mats.M, mats.Phi,
        mats.Lambda, mats.W, mats.P, mats.Q, Wu, Wy,
    )  # fmt: skip
    return UnknownInputObserverDesign.from_matrices(s, mats, params, observer=obs, region=region, D=D, X=X,
                                                    report=report, solver=info)


def _target_poles(region: AbstractRegion, k: int) -> np.ndarray:
    """``k`` distinct real points inside `region` around ``region.target()``."""
    c = region.target().real
    for spread in (0.5, 0.25, 0.1, 0.03, 0.01):
        pts = c + spread * max(1.0, abs(c)) * np.linspace(-1.0, 1.0, k) if k > 1 else np.array([c])
        if region.contains(pts):
            return pts
    return c * (1.0 + 1e-3 * np.arange(k))


def _preconditioner(A1: np.ndarray, A2: np.ndarray, region: AbstractRegion) -> np.ndarray:
    """``S = X0^{1/2}`` from one stabilizing output injection (pole placement) and a Lyapunov
    equation: in the coordinates ``S σ`` a certificate close to ``I`` exists, which keeps
    the LMI well conditioned (the region LMI is invariant under this congruence)."""
    import scipy.linalg
    import scipy.signal

    from .._linalg import row_space

    Cb = row_space(A2)
    K = scipy.signal.place_poles(A1.T, Cb.T, _target_poles(region, A1.shape[0])).gain_matrix.T
    A0 = A1 - K @ Cb
    if isinstance(region, Disk):
        # the one Stein certificate, of the transposed dynamics: Ã P Ãᵀ - P + I = 0 with
        # Ã = (A0 - αI)/τ; X0 = P⁻¹ is a disk certificate of A0 (the dual form, by a Schur
        # complement), the one this preconditioner is tested with
        X0 = np.linalg.inv(host_stein_certificate(A0.T, region.center, region.radius))
    else:
        X0 = scipy.linalg.solve_continuous_lyapunov(A0.T, -np.eye(A0.shape[0]))
    w, V = np.linalg.eigh(0.5 * (X0 + X0.T))
    if not np.all(w > 0):
        raise np.linalg.LinAlgError("Lyapunov solution is not positive definite")
    w = w / w.max()
    return (V * np.sqrt(w)) @ V.T


def _lmi_data(s: FunctionalObserverStructure, D: np.ndarray, Z) -> tuple[np.ndarray, np.ndarray]:
    r"""$(\mathbb A_1, \mathbb A_2)$ of the module docstring at `Z` (host): $\mathbb A_1$ from
    `_fixed_part` (i.e. `observer_matrices`), so $\mathbb A_1 - \mathbb Y\mathbb A_2$ is
    the error matrix of the observer built from the same parameters."""
    q0, q1, l = s.q0, s.q1, D.shape[1]
    N3 = np.asarray(pieces(s, xp=np).N3)
    c = N3.shape[0]
    d = q0 + q1 + l
    N1z, T = _fixed_part(s, Z)
    A1 = np.zeros((d, d))
    A1[:q0, :q0] = N1z
    A1[:q0, q0 + q1 :] = T @ D
    A2 = np.zeros((c + q1, d))
    A2[:c, :q0] = N3
    A2[c:, q0 : q0 + q1] = -np.eye(q1)
    return A1, A2


def _solve_lmi(s, D, Z, region, *, margin, solver):
    """Region LMI in (X full, 𝒲 = X𝕐) with Z fixed (module docstring). Returns ``(X, 𝕐, info)``.

    The certificate is often ill-conditioned (a rank-deficient ``N3`` needs large
    gains; on example 4.1.3 with ``D = e3`` cond X ≈ 3e4) and both solvers then stop at
    ``optimal_inaccurate``. The LMI is therefore solved first in the
    coordinates ``σ' = Sσ`` with ``S = X0^{1/2}``, ``X0`` the Lyapunov matrix of one
    pole-placement solution (`_preconditioner`): with ``𝔸1' = S𝔸1S⁻¹``,
    ``𝔸2' = 𝔸2S⁻¹``, ``𝕐' = S𝕐`` the region LMI is congruent to the original one,
    and ``X = SᵀX'S`` (for a disk ``X0`` is the Stein certificate of the disk), with
    the bound ``X' ⪯ κI`` (κ = 1e2, then 1e4): minimising ‖𝒲‖ alone drives the
    certificate towards an unbounded, ill-conditioned optimum (observed on the closed
    loop of example 4.1.3 with ``D = e3``: Clarabel ``optimal_inaccurate`` without the
    bound, ``optimal`` with κ = 1e2). If the pole placement fails (e.g. an
    unobservable mode inside the region) or these LMIs are not solved, the plain LMI
    is tried.
    """
    A1, A2 = _lmi_data(s, D, Z)
    d = A1.shape[0]
    name = "unknown-input observer (region LMI in X, 𝒲 = X 𝕐, Z fixed)"
    hint = (
        "No gain places the error dynamics (including the unknown-input modes) in the "
        "region: enlarge the region, or choose another R / observer order."
    )
    attempts = []
    try:
        S = _preconditioner(A1, A2, region)
        # X' ⪯ κI keeps the minimiser of ‖𝒲‖ away from an unbounded, ill-conditioned X'.
        attempts += [(S, 1e2, name + " (preconditioned, X' ⪯ 1e2 I)"),
                     (S, 1e4, name + " (preconditioned, X' ⪯ 1e4 I)")]
    except (ValueError, np.linalg.LinAlgError):
        pass
    attempts.append((np.eye(d), None, name))
    rungs = [(nm, (lambda S=S, kappa=kappa, nm=nm: _region_lmi(A1, A2, S, region, margin, solver, nm, hint, kappa)))
             for S, kappa, nm in attempts]
    try:
        nm, (Xv, Y, info), refused = _ladder.climb(rungs, refusals=LMI_FAILURES)
    except _ladder.Refused as every:
        errors = [e for _, e in every.refused]
        raise errors[0] if len(errors) == 1 else combined_failure(
            name, "; ".join(f"{e.status} ({e.problem})" for e in errors), errors,
            {f"attempt {i}": e.info for i, e in enumerate(errors)}, hint,
        ) from None
    info["problem"] = nm
    if refused:
        info["previous_attempts"] = [f"{e.status} ({e.problem})" for _, e in refused]
    # Components of 𝕐 outside the row space of 𝔸2 do not change 𝔸 (they would only
    # enlarge F, M, W): project them away.
    Pr = A2 @ np.linalg.pinv(A2)
    return Xv, Y @ Pr, info


def _region_lmi(A1, A2, S, region, margin, solver, name, hint, kappa=None):
    import cvxpy as cp
    d = A1.shape[0]
    Si = np.linalg.inv(S)
    A1s, A2s = S @ A1 @ Si, A2 @ Si
    X = cp.Variable((d, d), symmetric=True)
    Wv = cp.Variable((d, A2.shape[0]))
    Mx = _lmi.region_lmi(region, X, X @ A1s - Wv @ A2s)
    cons = [X >> np.eye(d), Mx << -float(margin) * np.eye(Mx.shape[0])]
    if kappa is not None:
        cons.append(X << float(kappa) * np.eye(d))
    info = _lmi.solve(cp.Problem(cp.Minimize(cp.norm(Wv, "fro")), cons), name, hint=hint, solver=solver)
    Xs = _lmi.value(X)
    Xs = 0.5 * (Xs + Xs.T)
    Ys = np.linalg.solve(Xs, _lmi.value(Wv))
    Xv = S.T @ Xs @ S
    return 0.5 * (Xv + Xv.T), Si @ Ys, info
