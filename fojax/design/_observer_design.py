"""The verified functional-observer design object and its float64 verification.

`FunctionalObserverDesign` is what `fojax.design_functional_observer` returns;
`verify_structure_design` computes the observer matrices of free parameters and verifies
them (`fojax.design.verify`: conditions a.–d. relative to the norms of their own terms,
eigenvalues in the region, the region LMI at the certificate); `verify_balanced` does the
same for a design made on the unit-free model (``balance=True``), and `unit_free_check`
re-checks a design made on the data as given in the unit-free frame.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from ..observer import GeneralizedFunctionalObserver
from ._base import AbstractDesign
from ._conditions import unit_free_structure
from ._parameterization import (
    design_residuals,
    error_dynamics,
    FunctionalObserverStructure,
    observer_matrices,
    observer_structure,
)
from ._regions import AbstractRegion
from ._verify import relative_residual, RESIDUAL_RTOL, VerificationReport, verify


@dataclasses.dataclass(frozen=True, kw_only=True)
class AbstractStructureDesign(AbstractDesign):
    """The fields of a design made on a `FunctionalObserverStructure` (functional,
    Takagi–Sugeno and unknown-input designs), and its ``R``, ``L`` and ``certificate``.

    Attributes:
        structure: the `FunctionalObserverStructure` (plant, L, R, E⊥).
        params: the free parameters (numpy arrays).
        T, K, Z_eff: the matrices of ``T E + K Ψ = R``; ``Z_eff`` is the Z of eq. 3.17.
        X: the LMI certificate (Lyapunov matrix) of the error dynamics.
        report: the float64 `VerificationReport`.
        solver: solver information (status, iterations, LMI steps).
    """

    structure: FunctionalObserverStructure
    params: dict
    T: np.ndarray
    K: np.ndarray
    Z_eff: np.ndarray
    X: np.ndarray
    report: VerificationReport
    solver: dict

    @classmethod
    def from_matrices(cls, structure, mats, params: dict, **fields):
        """The design of the free parameters `params` on `structure`, with ``T``, ``K`` and
        ``Z_eff`` from their observer matrices `mats`; `fields`: the other fields."""
        return cls(structure=structure, params={k: np.asarray(v) for k, v in params.items()}, T=np.asarray(mats.T),
                   K=np.asarray(mats.K), Z_eff=np.asarray(mats.Z_eff), **fields)

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
class FunctionalObserverDesign(AbstractStructureDesign):
    """A verified functional-observer design.

    Attributes (besides `structure`, `params` (``Z, Y1, Y2, Y3, J, G``), `T`, `K`, `Z_eff`,
    `X`, `report` and `solver`, which every design on a `FunctionalObserverStructure` has,
    `AbstractStructureDesign`):
        observer: the `GeneralizedFunctionalObserver` (proportional/PI are special cases).
        kind: ``"generalized"``, ``"PI"`` or ``"proportional"``.
        region: the pole region the error dynamics were placed in.
        hinf: the `fojax.design.HinfCertificate` (γ, the independent norm) of an
            ``objective="hinf"`` design, else ``None``.
        h2: the `fojax.design.H2Certificate` (ν, the independent norm) of an
            ``objective="h2"`` design, else ``None``.
    """

    observer: GeneralizedFunctionalObserver
    kind: str
    region: AbstractRegion
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



#: What a failed unit-free check of a design with ``balance`` tells the user.
UNIT_FREE_FIX = "design with balance=True"


def unit_free_check(s, params, fix: str = UNIT_FREE_FIX) -> tuple | None:
    r"""``("unit-free relative residual", value, failure or None)``: conditions a.–d. of the
    observer of `params` on `s`, re-checked in the unit-free frame of
    `fojax.analysis.unit_scaling` (a named check for `fojax.design.verify`), or ``None``
    when the model is larger than `UNIT_FREE_CHECK_MAX` or has rules.

    Why: the relative residual test on the data as given is weak on badly scaled models:
    terms of size 1e6 can hide an error of order 1 in the estimate. In the unit-free frame ($E_b = D_lED_r$, …, $T_b = TD_l^{-1}$, the same
    $N, J, F, H, \dots$; each condition is the raw one times $D_r$ on the right, see
    `balanced_design`) such an observer's residual is large. A.–d. are statements about the
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
    Raises `fojax.errors.DesignVerificationError` when either fails."""
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

