r"""`design_functional_observer`: generalized, PI and proportional functional observers
(thesis §3.1) by the Riccati/Stein route (`fojax.design._riccati`) or the region LMI route
(`fojax.design._region_lmi`), chosen by `choose_route`; every result is verified in float64
(`fojax.design._observer_design`) before it is returned.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from .._dtype import require_x64
from .._errors import (
    DesignVerificationError,
    FojaxError,
    InputError,
    LMI_FAILURES,
    LMIInfeasibleError,
    ShapeError,
    SolverStoppedShortError,
)
from ..analysis import e_perp as _e_perp  # analysis decides the rank of E (balanced)
from ..plant import check_functional, DescriptorSystem
from . import _discrete, _lmi, _riccati
from ._base import with_feedthrough
from ._conditions import (
    check_data_range,
    check_detectability,
    check_functional_observability,
    check_order,
    check_regular,
    check_structure,
    default_R,
    UNIT_FREE_CHECK_MAX as UNIT_FREE_CHECK_MAX,
)
from ._eliminated import eliminated_gains, formulation
from ._observer_design import (  # noqa: F401  (names used from here by the other design modules)
    AbstractStructureDesign,
    build_observer,
    carried_extra,
    COMPUTED_EXTRA,
    condition_scales,
    FunctionalObserverDesign,
    model_structure,
    unit_free_check,
    unit_free_failure,
    UNIT_FREE_FIX,
    verify_balanced,
    verify_structure_design,
)
from ._parameterization import (
    error_dynamics,
    FunctionalObserverStructure,
    observer_matrices,
    observer_structure,
    split_Y,
)
from ._region_lmi import (  # noqa: F401
    choose_Z,
    OBJECTIVES,
    SMALL_ORDER,
    solve_gains,
    solve_with_fallbacks,
)
from ._regions import as_region, Disk
from ._verify import RESIDUAL_RTOL


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


def check_q1(kind: str, q1: int | None) -> int | None:
    """`q1` for an observer of `kind`: 0 for a proportional observer (which has no integral
    part; another `q1` is an `InputError`), else `q1` as given (``None``: ``q0``)."""
    if kind != "proportional":
        return q1
    if q1 not in (None, 0):
        raise InputError(f"a proportional observer has q1 = 0 (no integral part); got q1 = {q1}. "
                         "Omit q1, or use kind='PI' or 'generalized'.")
    return 0


def _as_system(sys) -> DescriptorSystem:
    if not isinstance(sys, DescriptorSystem):
        raise TypeError(
            f"expected a fojax.DescriptorSystem, got {type(sys).__name__}; build one with "
            "fojax.DescriptorSystem(E, A, B, C)."
        )
    require_x64("observer design")
    return sys


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
    checked = R is None  # default_R returns an R that passed check_structure and check_detectability
    if R is None:
        R = default_R(E, A, B, C, L, psi=psi, Eperp=Eperp, region=region, q0=q0, q1=q1)
    else:
        R = np.asarray(R, dtype=float)
        if R.ndim != 2 or R.shape[1] != E.shape[0]:
            raise ShapeError("R", ("q0", E.shape[0]), tuple(R.shape), "R needs one column per state.")
        check_order(R, q0)
    s = observer_structure(E, A, B, C, L, R, q1=q1, psi=psi, Eperp=Eperp)
    if not checked:
        check_structure(s)
        check_detectability(s, region)
    return s


# ---------------------------------------------------------------------------- public


#: With ``method=None`` or ``"auto"``, the LMI route is tried after a failed Riccati route only
#: for observers of at most this order ``q0 + q1`` (the LMI's cost grows like its sixth power).
AUTO_LMI_MAX_ORDER = 60


def choose_route(method: str | None, *, objective: str, solver: str | None, order: int) -> str:
    r"""The design route of `design_functional_observer`: ``"riccati"``, ``"lmi"`` or ``"auto"``.

    **The rule** (the one place it is written down):

    - an explicit ``method="lmi"`` or ``"riccati"`` is taken as given (``"riccati"`` raises
      `fojax.errors.InputError` where it does not apply);
    - ``method="auto"``: the Riccati/Stein route (`fojax.design._riccati`: $O(n^3)$ time,
      $O(n^2)$ memory, no SDP) where it applies — one rule, a disk, half-plane or sector
      region, any of the three kinds — and the LMI route otherwise. When the Riccati route
      raises (no stabilizing Riccati solution, or a design that fails its float64
      verification) and the observer order is at most `AUTO_LMI_MAX_ORDER`, the LMI route is
      tried next; the report says that the Riccati route was refused and why;
    - ``method=None`` (the default): ``"lmi"`` for ``objective="hinf"``, ``"h2"`` and
      ``"centre"`` (they solve LMIs anyway, and their base design comes from the region
      LMI), when an LMI `solver` is named, or when the observer order ``q0 + q1`` (`order`)
      is at most `SMALL_ORDER` — there the LMI takes about a second and returns the
      minimum-gain design, whose error dynamics are closer to normal than the Riccati
      design's; ``"auto"`` otherwise, where the LMI's cost (growing like the sixth power of
      the order) makes the Riccati route the only one that scales.

    Both routes return only designs that passed the same float64 verification, so the rule
    decides the cost and which of the many valid observers is returned, never whether an
    unverified one is.
    """
    if method is not None:
        return _riccati.check_method(method)
    if objective != "region" or solver is not None or order <= SMALL_ORDER:
        return "lmi"
    return "auto"


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
    solver: str | None = None,
    method: str | None = None,
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
    - `solver`: the LMI solver, ``"auto"`` (Clarabel, then SCS), ``"CLARABEL"`` or ``"SCS"``
      (`fojax.design._lmi`); naming one selects the LMI route when `method` is not given.
      With ``"auto"`` (``None``), a design that fails its float64 verification is solved
      again with each named solver (`solver_fallback`; the report says so under ``"solver"``)
      before `DesignVerificationError` is raised.
    - `method`: the design route, ``None`` (default), ``"auto"``, ``"riccati"`` or ``"lmi"``;
      the rule that picks it is `choose_route`'s docstring. ``"riccati"``: a discrete
      Riccati equation for the gain and a Stein equation for the certificate (disks,
      half-planes and sectors; $O(n^3)$, `fojax.design._riccati`); ``"lmi"``: the region LMI
      (`fojax.design._region_lmi`). Either route is verified the same way; the route taken is
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
      states: the observer is designed on the model rescaled by
      `fojax.analysis.unit_scaling`'s diagonal factors (the default ``R``, the LMI and its
      coordinates all see the same numbers whatever the units), mapped back exactly and
      verified on the model as given *and* in the unit-free frame (`balanced_design`:
      derivation). The result's `structure` and `params` are then the unit-free ones (so
      `fojax.tune` moves unit-free parameters); ``design.R``, ``L``, ``T``, ``K`` are in the
      model's units and ``design.solver["balance"]`` holds the factors. ``False``: the design
      on the data as given (whose `structure` is the model's own, as code built on
      ``design.structure`` expects); on a badly scaled model it can differ with the units,
      and the relative residual test on the raw data is weak there (terms of size 1e6 hide
      an error of order 1), so every such design is also verified in the unit-free frame
      (`unit_free_check`, models with ``l + n ≤ 200``) and fails with
      `DesignVerificationError` there. **Default ``None``**: the design on the data as
      given, and when it fails its float64 verification (the unit-free check, or a solver
      solution that misses a strict LMI in float64), the ``balance=True`` design instead
      (the report says why under ``"balance"``). Use ``balance=True`` for models whose rows
      or states span several orders of magnitude, and for the start of tuning. For
      ``objective="hinf"``/``"h2"`` the disturbance channel is mapped as $D_lB_w$ (``w`` keeps
      its units; ``Dv`` is unchanged since ``y`` is), so the norm is the same map's, and
      ``design.hinf``/``design.h2`` hold the unit-free frame's ``Bw``. Either way the default
      ``R`` is chosen unit-free (`fojax.design.default_R`).

    **Returns:** a `FunctionalObserverDesign` whose `report` shows residuals of
    conditions a.–d. (≤ 1e-8 relative), the error eigenvalues inside `region` and the
    region LMI re-checked in float64 at the certificate ``X``.

    **Raises:** `IrregularSystemError` (a singular pencil, with the failed rank decision),
    `DataRangeError` (a matrix whose largest entry is outside ``2^±100``: rescale its
    units), `FunctionalObservabilityError`, `RankConditionError`,
    `DetectabilityError` (existence conditions, checked before any LMI, with what to
    change), `LMIInfeasibleError` (solver status other than ``optimal``, a solver
    exception with its message, or no stabilizing Riccati solution), `DesignVerificationError`
    (a float64 check failed: each design condition relative to the norms of its own terms;
    for ``objective="hinf"`` also the bounded-real LMI at ``(X, γ)`` and ``γ ≥ ‖T‖∞`` by
    SLICOT's AB13DD; for ``"h2"`` the Lyapunov inequality at ``X`` and ``ν ≥ ‖T‖₂``),
    `ShapeError`/`InputError` (a channel `Bw`/`Dv` of the wrong shape, or none).

    !!! example
        ```python
        d = fojax.design_functional_observer(sys, L, region=fojax.Disk(-3.0, 2.0))
        d.report.passed, d.solver["lmi"]["route"]
        ```
    """
    check_kind(kind)
    if method is not None:
        _riccati.check_method(method)
    if objective not in OBJECTIVE_NAMES:
        raise InputError(f"objective must be one of {OBJECTIVE_NAMES}; got {objective!r}.")
    if objective not in ("hinf", "h2") and (Bw is not None or Dv is not None):
        raise InputError("Bw/Dv (disturbance and noise channels) are only used with objective='hinf' or "
                         "'h2'; pass one of them or drop Bw/Dv.")
    sys = _as_system(sys)
    region = _discrete.time_region(sys, region, objective)  # discrete time: inside the unit disk
    region = as_region(region if region is not None else Disk(-2.0, 1.0))
    q1 = check_q1(kind, q1)
    s = prepare_structure(sys, L, R=R, q0=q0, q1=0, region=region)
    if q1 is None:
        q1 = s.q0
    s = observer_structure(s.E, s.A, s.B, s.C, s.L, s.R, q1=q1, psi=s.psi, Eperp=s.Eperp)
    method = choose_route(method, objective=objective, solver=solver, order=s.q0 + (0 if kind == "proportional" else q1))
    solver = _lmi.DEFAULT_SOLVER if solver is None else solver
    kw = dict(kind=kind, margin=margin, solver=solver, method=method)
    if objective in ("hinf", "h2"):
        from ._hinf import check_channels

        Bw, Dv = check_channels(s.n, s.p, Bw, Dv, objective=objective)
        perf = dict(objective=objective, Bw=Bw, Dv=Dv)

        def raw(kw):
            return _performance_design(s, region, Bw=Bw, Dv=Dv, objective=objective, **kw)
    else:
        perf = dict(centre=objective == "centre")

        def raw(kw):
            return _design_from_structure(s, region, **kw, **perf)

    d = solver_fallback(lambda kw: unit_free_fallback(lambda: raw(kw), lambda: balanced_design(s, region, **kw, **perf),
                                                      balance, "a.-d."), kw)
    return with_feedthrough(_discrete.with_dt(d, sys.dt), sys.D)


#: Solvers the default ``solver="auto"`` re-solves with, in order, when its design fails its
#: float64 verification (a solution that meets the LMIs to the solver's tolerances but misses
#: a strict one in float64 by a few 1e-9 depends on the solver's last steps, and so on the BLAS
#: kernel: another solver's solution is verified the same way).
VERIFY_RETRY_SOLVERS = ("CLARABEL", "SCS")


def solver_fallback(design, kw: dict):
    """``design(kw)``; with the default solver, when it raises `DesignVerificationError`, the
    first design of ``design(kw | solver=S)`` for ``S`` in `VERIFY_RETRY_SOLVERS` that passes
    (its report says why under ``"solver"``); else the first error, with the others' reasons."""
    try:
        return design(kw)
    except DesignVerificationError as err:
        if kw.get("solver") != _lmi.DEFAULT_SOLVER:
            raise
        reasons = []
        for sv in VERIFY_RETRY_SOLVERS:
            try:
                d = design({**kw, "solver": sv})
            except FojaxError as again:
                reasons.append(f"{sv}: {type(again).__name__}: {again}")
                continue
            note = f"the default solver route's design failed its float64 verification ({err}); re-solved with {sv}"
            return dataclasses.replace(d, report=dataclasses.replace(d.report, extra={**d.report.extra,
                                                                                      "solver": note}))
        raise DesignVerificationError(f"{err} (re-solved with each solver, failed too: {'; '.join(reasons)})",
                                      err.report) from err


def unit_free_fallback(raw, balanced, balance: bool | None, conditions: str):
    """``balanced()`` when `balance` is true; else ``raw()``, and with ``balance=None`` the
    ``balanced()`` design when ``raw()`` failed its float64 verification (its report says
    why under ``"balance"``). The one rule of `design_functional_observer` and
    `design_unknown_input_observer` (`conditions` names theirs).

    Two failures of the raw design are fixed by the unit-free one: conditions a.–d. that hold
    on the data as given but not in the unit-free frame (badly scaled data), and a solver
    solution that misses a strict LMI in float64 (the solver's absolute tolerances act on
    numbers of very different sizes on the raw data). Every balanced design is verified
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
    badly scaled data the relative residual test on the raw model is weak: terms of size
    1e6 can hide an error of order 1 in the estimate. (Mapping the free parameters into a
    structure built on the raw data instead fails the same way: that structure's
    solvability restriction $Z_0$, $\Pi_Z$ is decided on badly scaled numbers.)
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



def lmi_params(s, Z, Ys) -> dict:
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
    return FunctionalObserverDesign.from_matrices(s, mats, out.pop("params"), observer=build_observer(s, mats, kind=kind),
                                                  kind=kind, region=region, **out)


def _design_from_structure(s, region, *, kind, margin, solver, tighten=TIGHTEN, method="lmi", centre=False):
    why_not = _riccati.riccati_applies(region, kind, s.num_rules)
    if method == "riccati" and why_not is not None:
        raise InputError(f"method='riccati' does not apply: {why_not}. Use method='lmi' or 'auto'.")
    if centre and method == "riccati":
        raise InputError("objective='centre' searches the region LMI (method='lmi'); the Riccati route returns "
                         "one gain per region. Use method='lmi' or 'auto'.")
    if centre:
        return _finish(s, region, kind, *_centred_gains(s, region, kind=kind, margin=margin, solver=solver,
                                                         tighten=tighten))
    refused = None
    if method != "lmi" and why_not is None:
        try:
            return _finish(s, region, kind, *_riccati.riccati_gains(s, region, kind=kind), {})
        except (*LMI_FAILURES, DesignVerificationError) as err:  # method "auto": the LMI route next
            if method == "riccati" or s.q0 + (s.q1 if kind != "proportional" else 0) > AUTO_LMI_MAX_ORDER:
                raise
            refused = f"{type(err).__name__}: {err}"
    extra = {} if refused is None else {"Riccati route refused": refused[:500]}
    order = s.q0 + (0 if kind == "proportional" else s.q1)
    if s.num_rules == 1 and order > SMALL_ORDER and (kind != "proportional" or formulation(region) != "full"):
        # the reduced LMI (same feasible set, `fojax.design._eliminated`; a proportional
        # observer's "full" form would be the full LMI); the full LMI only when its solver
        # stopped short or its design failed verification
        try:
            X, Z, Ys, info = eliminated_gains(s, region.tightened(tighten), kind=kind, margin=margin, solver=solver)
            info["lmi"]["method"] = "lmi"
            return _finish(s, region, kind, X, Z, Ys, info, extra)
        except (SolverStoppedShortError, DesignVerificationError) as err:
            extra["eliminated LMI refused"] = f"{type(err).__name__}: {err}"[:500]
    X, Z, Ys, info = solve_gains(s, region.tightened(tighten), kind=kind, margin=margin, solver=solver)
    info["lmi"]["method"] = "lmi"
    return _finish(s, region, kind, X, Z, Ys, info, extra)


def _centred_gains(s, region, *, kind, margin, solver, tighten):
    """``objective="centre"``: the largest tightening of the region that the LMI still meets
    (`fojax.design._centre`); returns ``(X, Z, Ys, info, extra)``."""
    from ._centre import centred_gains

    def solve_inside(reg):
        # a bisection step counts as feasible only if its gains put the error eigenvalues in
        # the tightened region in float64 (an 'optimal' solver status alone is not enough)
        out = solve_gains(s, reg, kind=kind, margin=margin, solver=solver)
        ev = np.linalg.eigvals(np.asarray(error_dynamics(
            observer_matrices(s, **lmi_params(s, out[1], out[2]), xp=np), xp=np))[0])
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
    return X, Z, Ys, info, {"centred": f"region tightened by the fraction {c['fraction']:.3f} ({bracket}); "
                                      f"certified margin >= {c['certified_margin']:.4g}"}


def _finish(s, region, kind, X, Z, Ys, info, extra):
    """Verify the gains ``(X, Z, Ys)`` of a route in float64 and build the design."""
    route_key = "LMI route" if info["lmi"]["method"] == "lmi" else "design route"
    return verified_design(s, region, kind, lmi_params(s, Z, Ys), X, info, {route_key: info["lmi"]["route"], **extra})


def verified_design(s, region, kind: str, params: dict, X, solver: dict, extra: dict,
                    unit_free: str = UNIT_FREE_FIX) -> FunctionalObserverDesign:
    """The design of the free parameters `params` on `s` with certificate `X`, verified in
    float64 (`verify_structure_design`, with the unit-free check whose failure names the fix
    `unit_free`; `extra`: the report's notes); `solver` is stored as its solver information."""
    mats, report = verify_structure_design(s, params, region, X, extra=extra, unit_free=unit_free)
    return FunctionalObserverDesign.from_matrices(s, mats, params, observer=build_observer(s, mats, kind=kind),
                                                  kind=kind, region=region, X=X, report=report, solver=solver)
