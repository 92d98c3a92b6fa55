r"""Design of finite-time functional observers (thesis §3.1.2–3.1.3, Lemma 6)."""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np
import scipy.linalg

from .._errors import (
    DesignVerificationError,
    DetectabilityError,
    ExistenceConditionError,
    LMI_FAILURES,
    RegionError,
)
from .._linalg import row_space
from ..observer import FiniteTimeObserver
from ..plant import DescriptorSystem
from . import _lmi
from ._base import AbstractDesign, with_feedthrough
from ._conditions import check_detectability, unobservable_modes
from ._discrete import continuous_only
from ._functional import (
    _as_system,
    check_kind,
    FunctionalObserverDesign,
    lmi_params,
    prepare_structure,
    solve_gains,
    TIGHTEN,
    verified_design,
)
from ._parameterization import observer_structure, pieces
from ._regions import as_region, Disk
from ._stein import host_stein_certificate
from ._verify import combine_reports, VerificationReport


#: What a failed unit-free check tells the user (the finite-time design has no ``balance``).
UNIT_FREE_FIX = ("rescale the equations and states of the model (fojax.analysis.unit_scaling gives diagonal "
                 "factors that remove their units) and design on the rescaled model")


#: Smallest singular value of 𝕄 (relative to its largest) accepted for the reconstruction.
RECONSTRUCTION_RCOND = 1e-8


@dataclasses.dataclass(frozen=True)
class FiniteTimeObserverDesign(AbstractDesign):
    """A verified finite-time observer: two designs with a common ``T`` and the delay ``h``.

    Attributes: `observer` (`FiniteTimeObserver`), `designs` (the two
    `FunctionalObserverDesign` s), `h`, `reconstruction_rcond` (conditioning of 𝕄),
    `reconstruction_residual` (algebraic exactness check of the reconstruction).
    `region`, `certificate` and `report` are those of the pair (`combine_reports`).
    """

    observer: FiniteTimeObserver
    designs: tuple[FunctionalObserverDesign, FunctionalObserverDesign]
    h: float
    reconstruction_rcond: float
    reconstruction_residual: float

    @property
    def region(self) -> tuple:
        """The two disks (observer 1, observer 2)."""
        return tuple(d.region for d in self.designs)

    @property
    def certificate(self) -> tuple:
        return tuple(d.X for d in self.designs)

    @property
    def report(self) -> VerificationReport:
        """The two designs' reports and the reconstruction checks made at design time, as one."""
        return combine_reports({"observer 1": self.designs[0].report, "observer 2": self.designs[1].report},
                               _reconstruction_checks(self.reconstruction_rcond, self.reconstruction_residual),
                               raise_on_failure=False)

    def verify(self) -> VerificationReport:
        """Re-run the float64 verification (`fojax.design.AbstractDesign.verify`) of both
        designs and of the reconstruction: the conditioning of 𝕄 and the exactness of the
        stored ``Γ_now``, ``Γ_delay`` (`reconstruction_residual`) at ``h``."""
        reports = {f"observer {i + 1}": d.verify() for i, d in enumerate(self.designs)}
        o = self.observer
        A1, A2 = (d.error_matrix for d in self.designs)
        rcond = reconstruction_matrices(A1, A2, self.designs[0].structure.q0, float(self.h))[2]
        resid = reconstruction_residual(A1, A2, self.designs[0].structure.q0, float(self.h),
                                        np.asarray(o.Gamma_now), np.asarray(o.Gamma_delay))
        return combine_reports(reports, _reconstruction_checks(rcond, resid))

    def __str__(self) -> str:
        d1, d2 = self.designs
        return (
            f"finite-time functional observer, h = {self.h:g}: observer 1 in {d1.region}, "
            f"observer 2 in {d2.region}; reconstruction rcond {self.reconstruction_rcond:.2e}, "
            f"exactness residual {self.reconstruction_residual:.2e}\n"
            f"[observer 1] {d1.report}\n[observer 2] {d2.report}"
        )


def _reconstruction_checks(rcond: float, resid: float) -> tuple:
    """The finite-time checks in the form of `fojax.design.verify`'s `checks`."""
    return (
        ("reconstruction rcond", rcond, None if rcond >= RECONSTRUCTION_RCOND else (
            f"the finite-time reconstruction matrix 𝕄 is ill-conditioned (rcond {rcond:.2e} < "
            f"{RECONSTRUCTION_RCOND:.0e}); condition (3.108)/Lemma 6 is violated numerically. "
            "Separate the two disks further or change h.")),
        ("reconstruction residual", resid, None if resid <= 1e-8 else (
            f"finite-time reconstruction is not exact (relative residual {resid:.2e} > 1e-8).")),
    )


def reconstruction_residual(A1, A2, q0: int, h: float, G_now, G_del, seed: int = 0) -> float:
    """Exactness of the reconstruction ``m̂ = Γ_now ξ(t) − Γ_delay ξ(t−h)``: random
    ``m(t)``, ``m(t−h)``, ``ϑ(t−h)`` consistent with 𝔸_i; the relative error of ``m̂``."""
    rng = np.random.default_rng(seed)
    m_now, m_del = rng.normal(size=q0), rng.normal(size=q0)
    xis_now, xis_del = [], []
    for Ai in (A1, A2):
        th_del = rng.normal(size=Ai.shape[0])
        th_now = scipy.linalg.expm(Ai * h) @ th_del
        pad = np.zeros(Ai.shape[0] - q0)
        xis_del.append(th_del + np.concatenate([m_del, pad]))
        xis_now.append(th_now + np.concatenate([m_now, pad]))
    m_hat = G_now @ np.concatenate(xis_now) - G_del @ np.concatenate(xis_del)
    return float(np.linalg.norm(m_hat - m_now) / max(1.0, np.linalg.norm(m_now)))


def _check_separated(r1: Disk, r2: Disk) -> None:
    lo, hi = sorted([r1, r2], key=lambda d: d.center)
    if not lo.center + lo.radius < hi.center - hi.radius:
        raise RegionError(
            "finite-time estimation needs two disks separated along the real axis (Lemma 6: "
            f"Re λ(𝔸_a) < σ < Re λ(𝔸_b)); {lo.describe()} reaches {lo.center + lo.radius:g} and "
            f"{hi.describe()} starts at {hi.center - hi.radius:g}. Move the disks apart or shrink them."
        )


def reconstruction_matrices(A1: np.ndarray, A2: np.ndarray, q0: int, h: float):
    """``(Γ_now, Γ_delay, rcond)`` of the exact reconstruction (module docstring of
    `fojax.observer.FiniteTimeObserver`)."""
    s1, s2 = A1.shape[0], A2.shape[0]
    E1, E2 = scipy.linalg.expm(A1 * h), scipy.linalg.expm(A2 * h)
    P1 = np.eye(s1, q0)
    P2 = np.eye(s2, q0)
    Mm = np.block([[P1, -E1 @ P1], [P2, -E2 @ P2]])
    sv = np.linalg.svd(Mm, compute_uv=False)
    rcond = float(sv[-1] / sv[0]) if sv.size else 1.0
    Mp = np.linalg.pinv(Mm)
    sel = Mp[:q0]  # rows giving m(t)
    Gamma_now = sel
    Gamma_delay = sel @ scipy.linalg.block_diag(E1, E2)
    return Gamma_now, Gamma_delay, rcond


def _target_poles(region: Disk, q: int) -> np.ndarray:
    """``q`` distinct real poles spread over the middle of a disk."""
    if q == 1:
        return np.array([region.center])
    return region.center + 0.6 * region.radius * np.linspace(-1.0, 1.0, q)


def _place_gains(s, Z, region: Disk, kind: str):
    """Pole placement of the ε-block through N3 (scipy `place_poles`), v-block G = αI.

    Used when the LMI cannot be solved because the certificate would need an extreme
    condition number (e.g. a rank-one N3 with gains in the thousands, thesis §3.1.3).
    Returns ``(X, 𝕐)``; the result is verified like any design.
    """
    import scipy.signal

    from .._linalg import row_space

    pc = pieces(s, xp=np)
    N1 = pc.N1[0] - Z @ pc.N2[0]
    N3 = pc.N3
    q0, q1, c = s.q0, s.q1, N3.shape[0]
    Cb = row_space(N3)
    if Cb.shape[0] == 0:
        raise DetectabilityError(
            "assignability through N3",
            "N3 = 0: no mode of the observer can be assigned by Y1 with this R.",
            "Use a larger observer order (more rows in R).",
        )
    K = scipy.signal.place_poles(N1.T, Cb.T, _target_poles(region, q0)).gain_matrix.T
    Y1 = K @ Cb @ np.linalg.pinv(N3)
    Y = np.zeros((q0 + q1, c + q1))
    Y[:q0, :c] = Y1
    Y[q0:, c:] = region.center * np.eye(q1)
    A2 = np.block([[N3, np.zeros((c, q1))], [np.zeros((q1, q0)), -np.eye(q1)]])
    A1 = np.block([[N1, np.zeros((q0, q1))], [np.zeros((q1, q0 + q1))]])
    # Smith's doubling keeps X positive definite for these highly non-normal dynamics
    X = host_stein_certificate(A1 - Y @ A2, region.center, region.radius, method="doubling")
    return X, Y


def design_finite_time_observer(
    sys: DescriptorSystem,
    L,
    *,
    h: float,
    regions=((-5.0, 0.5), (-2.0, 0.5)),
    kind: str = "generalized",
    R=None,
    q0: int | None = None,
    q1: int | None = None,
    margin: float = 1e-3,
    solver: str = _lmi.DEFAULT_SOLVER,
    method: str = "auto",
    seed: int = 0,
) -> FiniteTimeObserverDesign:
    r"""Design a finite-time functional observer with delay `h` (thesis §3.1.2).

    **Arguments:**

    - `sys`, `L`: plant and functional, as in `design_functional_observer`.
    - `h`: the convergence time (delay), ``> 0``.
    - `regions`: two disks (``Disk`` or ``(center, radius)``) separated along the real
      axis (Lemma 6); each observer's error eigenvalues are placed in one of them.
    - `kind`, `R`, `q0`, `q1`, `margin`, `solver`: as in `design_functional_observer`.
      Both observers share ``R`` and ``Z`` (hence ``T``), which the exact
      reconstruction needs. With ``R = None`` fojax's default ``R`` is tried first and,
      if no finite-time pair exists for it, the full-order choice (rows spanning the
      row space of Γ), whose larger ``N3`` makes every mode assignable by ``Y1`` alone.
    - `method`: ``"lmi"`` (region LMIs), ``"place"`` (pole placement of the ε-block
      through N3 with ``G = αI``, ``J = S = 0``, and a discrete-Lyapunov (Stein)
      certificate for each disk) or ``"auto"`` (LMI, then placement when the LMI
      fails). Either way the result is verified in float64.

    **Returns:** a `FiniteTimeObserverDesign`; its `observer.reconstruct` /
    `finite_time_estimates` equal ``z(t)`` for ``t ≥ h`` on the nominal model.

    **Raises:** `IrregularSystemError`, `DataRangeError` (as
    `design_functional_observer`), `RegionError` (regions not two separated disks),
    `DetectabilityError` (a mode that no gain moves: it would be common to both
    observers, violating Lemma 6), `LMIInfeasibleError`, `DesignVerificationError`
    (including an ill-conditioned reconstruction, ``rcond < 1e-8``).
    """
    check_kind(kind)
    kw = dict(h=h, regions=regions, kind=kind, q1=q1, margin=margin, solver=solver,
              method=method, seed=seed)
    if R is not None or q0 is not None:
        return with_feedthrough(_design_ft(sys, L, R=R, q0=q0, **kw), sys.D)
    try:
        return with_feedthrough(_design_ft(sys, L, R=None, q0=None, **kw), sys.D)
    except (*LMI_FAILURES, DesignVerificationError, ExistenceConditionError) as first:
        E, A, C = (np.asarray(x) for x in (sys.E, sys.A, sys.C))
        from ..analysis import e_perp  # analysis decides the rank of E (balanced)

        Ep = e_perp(E)
        R_full = row_space(np.vstack([E, Ep @ A, C]))
        try:
            return with_feedthrough(_design_ft(sys, L, R=R_full, q0=None, **kw), sys.D)
        except (*LMI_FAILURES, DesignVerificationError, ExistenceConditionError):
            raise first from None


def _design_ft(sys, L, *, h, regions, kind, R, q0, q1, margin, solver, method, seed) -> FiniteTimeObserverDesign:
    """Implementation of `design_finite_time_observer` for a given R (or q0); the arguments
    (all given by it) are its own."""
    sys = _as_system(sys)
    continuous_only(sys, "design_finite_time_observer")
    h = float(h)
    if not (np.isfinite(h) and h > 0):
        raise ValueError(f"h must be a positive number, got {h}")
    r1, r2 = (as_region(r) for r in regions)
    if not (isinstance(r1, Disk) and isinstance(r2, Disk)):
        raise RegionError("finite-time observers need two Disk regions (bounded, separable).")
    _check_separated(r1, r2)
    s = prepare_structure(sys, L, R=R, q0=q0, q1=0, region=r1, fname="design_finite_time_observer")
    check_detectability(s, r2)
    if kind == "proportional":
        q1 = 0
    elif q1 is None:
        q1 = s.q0
    s = observer_structure(s.E, s.A, s.B, s.C, s.L, s.R, q1=q1, psi=s.psi, Eperp=s.Eperp)
    # Observer 1 fixes Z (joint LMI); observer 2 reuses it: common T.
    t1, t2 = r1.tightened(TIGHTEN), r2.tightened(TIGHTEN)
    # Z is common (one T). If every mode of N1' is assignable through N3 alone, Z = 0 and
    # each observer gets its own certificate; otherwise Z comes from a joint LMI over both
    # regions with a shared X1 block (more conservative).
    pc = pieces(s, xp=np)
    if all(unobservable_modes(pc.N1[i], pc.N3).size == 0 for i in range(pc.N1.shape[0])):
        Z = np.zeros((s.q0, pc.N2.shape[1]))
    else:
        _, Z, _, _ = solve_gains(s, (t1, t2), kind=kind, margin=margin, solver=solver)
    if method not in ("auto", "lmi", "place"):
        raise ValueError(f"method must be 'auto', 'lmi' or 'place', got {method!r}")
    lmi_error = None
    if method in ("auto", "lmi"):
        try:
            (X1, X2), Z, (Ys1, Ys2), info = solve_gains(
                s, (t1, t2), kind=kind, margin=margin, solver=solver, Z=Z
            )
            info1 = info2 = info
        except LMI_FAILURES as err:
            if method == "lmi":
                raise
            lmi_error = err
    if method == "place" or lmi_error is not None:
        X1, Y1 = _place_gains(s, Z, t1, kind)
        X2, Y2 = _place_gains(s, Z, t2, kind)
        Ys1, Ys2 = [Y1], [Y2]
        info1 = info2 = {
            "method": "pole placement",
            "lmi_status": None if lmi_error is None else lmi_error.status,
        }
    designs = []
    for Ys, X, reg, info in ((Ys1, X1, r1, info1), (Ys2, X2, r2, info2)):
        route = (info["lmi"]["route"] if "lmi" in info else "pole placement" + (
            f" (LMI refused: {info['lmi_status']})" if info["lmi_status"] else ""))
        # verified as every functional-observer design (the unit-free check included, as in its verify())
        designs.append(verified_design(s, reg, kind, lmi_params(s, Z, Ys), X, info, {"LMI route": route},
                                       unit_free=UNIT_FREE_FIX))
    A1, A2 = designs[0].error_matrix, designs[1].error_matrix
    G_now, G_del, rcond = reconstruction_matrices(A1, A2, s.q0, h)
    resid = reconstruction_residual(A1, A2, s.q0, h, G_now, G_del, seed) if rcond >= RECONSTRUCTION_RCOND else np.nan
    for _, _, failure in _reconstruction_checks(rcond, resid if np.isfinite(resid) else 0.0):
        if failure is not None:
            raise DesignVerificationError(failure)
    obs = FiniteTimeObserver(
        designs[0].observer, designs[1].observer, jnp.asarray(h), jnp.asarray(G_now), jnp.asarray(G_del)
    )
    return FiniteTimeObserverDesign(obs, tuple(designs), h, rcond, resid)
