"""One-call structural report of a descriptor system (printed by ``fojax check``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._linalg import rank
from ..plant import DescriptorSystem
from ._balance import Scaling
from ._common import as_system, crank, deflate
from ._discrete import time_domain, unstable_mask
from ._kronecker import (
    kronecker_structure,
    KroneckerStructure,
    mode_counts,
    ModeCounts,
    properness,
    system_zeros,
)
from ._observability import (
    _i_ctrl,
    _i_obs,
    _r_ctrl,
    _r_obs,
    functional_ranks,
)
from ._pencil import _poles_from, _sort_poles, _stable_np, AXIS_TOL


@dataclass(frozen=True)
class StructureReport:
    """Every structural property of a descriptor system, with a plain-language verdict.

    Fields that are undefined for a singular pencil are ``None`` (then only `regular`,
    `rank_E`, the dimensions and — if `L` was given — the functional observability
    fields are filled). `functionally_observable` is ``None`` when no `L` was given.
    `max_real_part` is ``-inf`` when there are no finite poles.
    """

    n: int
    m: int
    p: int
    rank_E: int
    regular: bool
    n_finite: int | None
    index: int | None
    finite_poles: np.ndarray | None
    max_real_part: float | None
    impulse_free: bool | None
    stable: bool | None
    admissible: bool
    c_observable: bool | None
    r_observable: bool | None
    i_observable: bool | None
    s_observable: bool | None
    detectable: bool | None
    c_controllable: bool | None
    r_controllable: bool | None
    i_controllable: bool | None
    s_controllable: bool | None
    stabilizable: bool | None
    q: int | None
    functionally_observable: bool | None
    functional_ranks: tuple[int, int] | None
    verdict: str
    #: the power-of-two balancing applied before every rank decision (`balance_system`)
    scaling: Scaling | None = None
    #: Kronecker structure of the pencil (E, A) (SLICOT AG08BD), also for singular pencils
    kronecker: KroneckerStructure | None = None
    #: normal rank of sE - A
    normal_rank: int | None = None
    #: invariant zeros of (E, A, B, C, 0) (``None`` when m = 0 or p = 0)
    invariant_zeros: np.ndarray | None = None
    #: properness of C (sE - A)^{-1} B (``None`` for a singular pencil or m = 0 or p = 0)
    proper: bool | None = None
    #: dynamic / non-dynamic / impulsive / uncontrollable / unobservable mode counts
    modes: ModeCounts | None = None
    #: sampling period of a discrete-time system (``None``: continuous time); then
    #: ``impulse_free`` means causal and ``stable`` means every finite pole has |λ| < 1
    dt: float | None = None

    def __str__(self) -> str:
        def yn(v):
            return "n/a" if v is None else ("yes" if v else "NO")

        def poles_str(z):
            if z is None:
                return "n/a"
            if len(z) == 0:
                return "none"
            parts = []
            for v in z:
                if abs(v.imag) < 1e-12 * max(1.0, abs(v)):
                    parts.append(f"{v.real:.6g}")
                else:
                    parts.append(f"{v.real:.6g}{v.imag:+.6g}i")
            return ", ".join(parts)

        disc = self.dt is not None
        big = (np.max(np.abs(self.finite_poles)) if self.finite_poles is not None and len(self.finite_poles)
               else None)
        lines = [
            f"Descriptor system: n = {self.n} states, m = {self.m} inputs, p = {self.p} outputs, "
            f"rank E = {self.rank_E}; {time_domain(self.dt)}",
            f"  regular           {yn(self.regular)}",
            f"  index             {'n/a' if self.index is None else self.index}"
            + ("" if self.index is None else ("  (0: explicit, 1: causal, >=2: non-causal)" if disc else
                                              "  (0: ODE, 1: impulse-free DAE, >=2: impulsive)")),
            f"  finite poles      {poles_str(self.finite_poles)}",
            (f"  causal            {yn(self.impulse_free)}" if disc else
             f"  impulse-free      {yn(self.impulse_free)}"),
            f"  stable            {yn(self.stable)}"
            + (
                (f"  (max |λ| = {big:.6g})" if big is not None else "") if disc else
                "" if self.max_real_part is None or not np.isfinite(self.max_real_part)
                else f"  (max Re = {self.max_real_part:.6g})"
            ),
            f"  admissible        {yn(self.admissible)}",
        ]
        if self.kronecker is not None:
            k = self.kronecker
            lines.append(
                f"  Kronecker         normal rank {k.normal_rank}; minimal indices right "
                f"{list(k.right_indices)} left {list(k.left_indices)}; infinite elementary "
                f"divisors {list(k.infinite_divisors)}"
            )
        if self.modes is not None:
            md = self.modes
            lines.append(
                f"  modes             {md.finite} dynamic, {md.nondynamic} non-dynamic, "
                f"{md.impulsive} impulsive; {md.uncontrollable} uncontrollable, "
                f"{md.unobservable} unobservable (finite)"
            )
        if self.invariant_zeros is not None:
            lines.append(f"  invariant zeros   {poles_str(self.invariant_zeros)}")
        if self.proper is not None:
            lines.append(f"  proper           {' ' + yn(self.proper)}")
        if self.scaling is not None:
            lines.append(f"  scaling           {self.scaling}")
        lines += [
            "  observability     "
            f"C {yn(self.c_observable)} | R {yn(self.r_observable)} | "
            f"I {yn(self.i_observable)} | S {yn(self.s_observable)} | "
            f"detectable {yn(self.detectable)}",
            "  controllability   "
            f"C {yn(self.c_controllable)} | R {yn(self.r_controllable)} | "
            f"I {yn(self.i_controllable)} | S {yn(self.s_controllable)} | "
            f"stabilizable {yn(self.stabilizable)}",
        ]
        if self.q is not None:
            a, b = self.functional_ranks
            lines.append(
                f"  functional z = Lx (q = {self.q}): Assumption 1 {yn(self.functionally_observable)}"
                f"  (rank [L; E; E⊥A; C] = {a}, rank [E; E⊥A; C] = {b})"
            )
        lines.append("Verdict: " + self.verdict)
        return "\n".join(lines)


def _missing(impulsive: bool, finite: bool, notion: str) -> str:
    """Why detectability (`notion` ``"observable"``) or stabilizability (``"controllable"``)
    fails: the impulsive modes, the unstable finite modes, or both."""
    missing = []
    if not impulsive:
        missing.append(f"impulsive modes are not {notion}")
    if not finite:
        missing.append(f"some unstable finite mode is un{notion}")
    return " and ".join(missing)


def _verdict(r: dict, fd: bool | None, fs: bool | None) -> str:
    if not r["regular"]:
        s = (
            "IRREGULAR - det(sE - A) is identically zero, so the model has no unique "
            "solution and poles, stability and observability are undefined. Check the "
            "equations (a missing, duplicated or inconsistent equation)."
        )
        if r["functionally_observable"] is not None:
            s += " " + _functional_sentence(r) + "."
        return s
    parts = []
    disc = r.get("dt") is not None
    if r["admissible"]:
        parts.append("admissible (regular, causal, |λ| < 1)" if disc else "admissible (regular, impulse-free, stable)")
    else:
        why = []
        if not r["impulse_free"]:
            why.append(f"non-causal (index {r['index']})" if disc else f"impulsive (index {r['index']})")
        if not r["stable"]:
            z = r["finite_poles"]
            bad = z[unstable_mask(z, AXIS_TOL, r.get("dt"))]
            why.append(
                f"unstable ({len(bad)} finite pole(s) with |λ| >= 1, max |λ| = {np.max(np.abs(z)):.4g})" if disc else
                f"unstable ({len(bad)} finite pole(s) with Re >= 0, max Re = {r['max_real_part']:.4g})"
            )
        parts.append("NOT admissible: " + " and ".join(why))
    if r["s_observable"]:
        obs = "C-observable" if r["c_observable"] else "S-observable (R and I)"
        parts.append(obs + "; a full-order observer with admissible error exists")
    elif r["detectable"]:
        parts.append(
            "not S-observable but detectable (impulse-observable, unstable modes observable)"
        )
    else:
        parts.append("NOT detectable: " + _missing(r["i_observable"], fd, "observable"))
    if r["stabilizable"]:
        parts.append("stabilizable by state feedback (a K with (E, A+BK) admissible exists)")
    else:
        parts.append("NOT stabilizable by state feedback: " + _missing(r["i_controllable"], fs, "controllable"))
    if r["functionally_observable"] is not None:
        parts.append(_functional_sentence(r))
    return "; ".join(parts) + "."


def _functional_sentence(r: dict) -> str:
    a, b = r["functional_ranks"]
    if r["functionally_observable"]:
        return "Assumption 1 holds for L (functional observability)"
    return (
        f"Assumption 1 FAILS for L (rank [L; E; E⊥A; C] = {a} > rank [E; E⊥A; C] = {b}): "
        "z = Lx cannot be reconstructed; measure more, or choose L in the row space of "
        "[E; E⊥A; C]"
    )


def structure_report(
    sys: DescriptorSystem,
    L=None,
    *,
    tol: float | None = None,
    axis_tol: float = AXIS_TOL,
    balance: bool = True,
) -> StructureReport:
    """Compute every structural property of `sys` at once (host-only).

    Regularity, rank of ``E``, index, finite poles, impulse-freeness, stability,
    admissibility, C/R/I/S observability and controllability, detectability and
    stabilizability (with the impulse conditions, see `is_detectable`), and — when `L`
    is given — Assumption 1. A singular pencil gives a report (not an error) whose
    undefined fields are ``None``.

    **Arguments:**

    - `sys`: a `fojax.DescriptorSystem`.
    - `L`: optional ``(q, n)`` functional matrix.
    - `tol`: absolute rank threshold (fojax tolerance by default, see `fojax._linalg`).
    - `axis_tol`: imaginary-axis tolerance of `is_stable`.
    - `balance`: ``False`` skips the power-of-two balancing (`balance_system`); the
      report's `scaling` says what was applied.

    Also reported: the Kronecker structure and normal rank of ``sE - A``, the invariant
    zeros of ``(E, A, B, C, 0)``, properness and the mode counts (`kronecker_structure`,
    `system_zeros`, `properness`, `mode_counts`; SLICOT ``AG08BD``).

    A discrete-time system (``dt`` set) is reported with the discrete-time notions
    (`fojax.analysis._discrete`): the summary says "discrete-time (dt = h)", causality in
    place of impulse-freeness, stability and detectability with respect to the unit circle;
    the rank tests are the same.

    **Returns:** a `StructureReport`; ``print(report)`` gives a readable summary.
    """
    pn = as_system(sys, "structure_report", balance)
    n = pn.n
    r: dict = dict(
        n=n,
        m=pn.B.shape[1],
        p=pn.C.shape[0],
        rank_E=rank(pn.En, tol),
        n_finite=None,
        index=None,
        finite_poles=None,
        max_real_part=None,
        impulse_free=None,
        stable=None,
        admissible=False,
        c_observable=None,
        r_observable=None,
        i_observable=None,
        s_observable=None,
        detectable=None,
        c_controllable=None,
        r_controllable=None,
        i_controllable=None,
        s_controllable=None,
        stabilizable=None,
        q=None,
        functionally_observable=None,
        functional_ranks=None,
        scaling=pn.scaling,
        dt=pn.dt,
    )
    d = deflate(pn, tol)
    r["regular"] = d.failed is None
    if n:
        ks = kronecker_structure(pn.E, pn.A, balance=balance)
        r["kronecker"], r["normal_rank"] = ks, ks.normal_rank
        r["modes"] = mode_counts(sys, balance=balance)
        if r["m"] and r["p"]:
            r["invariant_zeros"] = system_zeros(sys, balance=balance).invariant_zeros
            if r["regular"]:
                r["proper"] = properness(sys, tol=tol, balance=balance).proper
    if L is not None:
        fr = functional_ranks(sys, L, tol=tol, balance=balance)
        r["q"] = int(np.shape(L)[0])
        r["functional_ranks"] = fr
        r["functionally_observable"] = fr[0] == fr[1]
    if r["regular"]:
        fname = "structure_report"
        poles = _sort_poles(_poles_from(pn, d, fname) * pn.pole_scale)
        r["n_finite"], r["index"], r["finite_poles"] = d.n1, d.index, poles
        r["max_real_part"] = float(poles.real.max()) if poles.size else -np.inf
        r["impulse_free"] = d.index <= 1
        r["stable"] = _stable_np(poles, 0.0, axis_tol, pn.dt)
        r["admissible"] = r["impulse_free"] and r["stable"]
        ro = _r_obs(pn, tol, fname)
        io = _i_obs(pn, tol)
        rc = _r_ctrl(pn, tol, fname)
        ic = _i_ctrl(pn, tol)
        r["r_observable"], r["i_observable"], r["s_observable"] = ro, io, ro and io
        r["c_observable"] = ro and crank(np.vstack([pn.En, pn.Cn]), tol) == n
        r["r_controllable"], r["i_controllable"], r["s_controllable"] = rc, ic, rc and ic
        r["c_controllable"] = rc and crank(np.hstack([pn.En, pn.Bn]), tol) == n
        fd = _r_obs(pn, tol, fname, unstable_only=True, axis_tol=axis_tol)
        fs = _r_ctrl(pn, tol, fname, unstable_only=True, axis_tol=axis_tol)
        r["detectable"], r["stabilizable"] = io and fd, ic and fs
        r["verdict"] = _verdict(r, fd, fs)
    else:
        r["verdict"] = _verdict(r, None, None)
    return StructureReport(**r)
