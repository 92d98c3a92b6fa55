"""Float64 verification of designs, independent of the LMI solver's output."""

from __future__ import annotations

import dataclasses

import numpy as np

from .._errors import DesignVerificationError
from ._regions import AbstractRegion


#: Residuals of the design conditions must be below this, relative to the data's scale.
RESIDUAL_RTOL = 1e-8
#: Floor of a per-condition scale, relative to the common scale (see `verify`).
CONDITION_SCALE_FLOOR = 1e-6
#: Eigenvalues must be inside the region by at least this (absolute) margin, or by
#: 1e-3 of the region's size when that is smaller (`required_margin`).
EIG_MARGIN = 1e-9
#: The region LMI re-evaluated in float64 must have max eigenvalue below -LMI_MARGIN·‖X‖.
LMI_MARGIN = 1e-10


def required_margin(region: AbstractRegion, margin: float = EIG_MARGIN) -> float:
    """The margin eigenvalues must keep inside `region`: `margin`, or 1e-3 of the
    region's size (`AbstractRegion.size`, e.g. a disk's radius) for tiny regions, which
    an absolute 1e-9 would make impossible to satisfy."""
    return float(min(margin, 1e-3 * region.size()))


def margin_failure(what: str, worst, margin: float, required: float, region: AbstractRegion) -> str | None:
    """The failure message for the region check (``None`` if it passes).

    The margin is signed: ``> 0`` inside the region, ``< 0`` outside. A point inside by
    less than `required` is reported as inside, with both numbers.
    """
    if margin > required:
        return None
    where = f"the region ({region.describe()})"
    if not np.isfinite(margin):
        return f"{what} {worst} has no finite margin to {where}"
    if margin <= 0:
        return f"{what} {worst:.6g} is outside {where} by {-margin:.3e}"
    return (f"{what} {worst:.6g} is inside {where} by only {margin:.3e}, less than the required "
            f"margin {required:.1e}")


@dataclasses.dataclass(frozen=True)
class VerificationReport:
    """What was checked, with the numbers.

    Attributes:
        residuals: absolute residuals of the design conditions (``a``..``f``).
        scale: the data scale the residuals are compared against.
        relative_residual: ``max(residuals) / scale``.
        eigenvalues: eigenvalues of the error dynamics (all rules concatenated).
        region: description of the region checked.
        region_margin: min over eigenvalues of the region margin (``> 0`` inside).
        lmi_max_eig: largest eigenvalue of the region LMI at the certificate (``< 0``), or None.
        certificate_min_eig: smallest eigenvalue of the certificate ``X`` (``> 0``), or None.
        passed: whether every check passed.
        failures: human-readable list of failed checks.
    """

    residuals: dict
    scale: float
    relative_residual: float
    eigenvalues: np.ndarray
    region: str
    region_margin: float
    lmi_max_eig: float | None
    certificate_min_eig: float | None
    passed: bool
    failures: tuple[str, ...]
    extra: dict = dataclasses.field(default_factory=dict)

    def __str__(self) -> str:
        lines = [
            f"verification {'PASSED' if self.passed else 'FAILED'}",
            "  condition residuals: "
            + ", ".join(f"{k}={v:.2e}" for k, v in self.residuals.items())
            + f" (relative {self.relative_residual:.2e}, tolerance {RESIDUAL_RTOL:.0e})",
            f"  eigenvalues in {self.region}: margin {self.region_margin:.3e} (> 0 inside, < 0 outside)",
        ]
        if self.lmi_max_eig is not None:
            lines.append(
                f"  LMI re-check: max eig {self.lmi_max_eig:.3e}, certificate min eig "
                f"{self.certificate_min_eig:.3e}"
            )
        for k, v in self.extra.items():
            lines.append(f"  {k}: {v}")
        for f in self.failures:
            lines.append(f"  FAILED: {f}")
        return "\n".join(lines)

    def to_dict(self) -> dict:
        return {
            "residuals": {k: float(v) for k, v in self.residuals.items()},
            "scale": float(self.scale),
            "relative_residual": float(self.relative_residual),
            "eigenvalues_real": np.real(self.eigenvalues).tolist(),
            "eigenvalues_imag": np.imag(self.eigenvalues).tolist(),
            "region": self.region,
            "region_margin": float(self.region_margin),
            "lmi_max_eig": None if self.lmi_max_eig is None else float(self.lmi_max_eig),
            "certificate_min_eig": None
            if self.certificate_min_eig is None
            else float(self.certificate_min_eig),
            "passed": bool(self.passed),
            "failures": list(self.failures),
            "extra": {k: (v if isinstance(v, str | int | float | bool) else str(v)) for k, v in self.extra.items()},
        }


def relative_residual(residuals: dict, scale: float, scales: dict | None = None) -> float:
    """The relative residual `verify` compares with ``rtol`` (its docstring has the rule)."""
    res = {k: float(v) for k, v in residuals.items()}
    if scales is not None and res:
        floor = CONDITION_SCALE_FLOOR * max(float(scale), 1.0)
        return max(v / max(float(scales[k]), floor) for k, v in res.items())
    return max(res.values()) / max(float(scale), 1.0) if res else 0.0


def verify(
    residuals: dict,
    scale: float,
    error_matrices: np.ndarray,
    region: AbstractRegion,
    X: np.ndarray | None = None,
    *,
    rtol: float = RESIDUAL_RTOL,
    raise_on_failure: bool = True,
    extra: dict | None = None,
    scales: dict | None = None,
    common_lyapunov: bool = False,
    checks: tuple = (),
) -> VerificationReport:
    """Check residuals, eigenvalue locations and (if `X` is given) the region LMI.

    `error_matrices` is ``(k, d, d)``: the LMI is re-checked for every rule with the
    common certificate `X`. With `scales` (one per residual: the sum of the norms of the
    terms of that condition), the relative residual is
    ``max_k residual_k / max(scales_k, CONDITION_SCALE_FLOOR * max(scale, 1))`` — each
    condition relative to its own terms, so that one large matrix (e.g. ``C`` in small
    units) cannot hide a wrong condition d. (``PTE + QΨ = L``) behind a large common
    scale; the floor keeps a condition whose terms all vanish (e.g. ``S = M = 0``) from
    turning rounding (1e-30) into a failure: with ``rtol = 1e-8`` it accepts residuals
    below ``1e-14 · scale``, the rounding level of the whole design. Without `scales`:
    ``max(residuals) / max(scale, 1)``.

    With ``common_lyapunov=True`` (Takagi–Sugeno designs) it also checks
    ``max_i λmax(𝔸_iᵀX + X𝔸_i) < -LMI_MARGIN·‖X‖`` — quadratic stability of the error for
    arbitrarily time-varying weights, which the region LMI implies for fojax's regions —
    and records it as ``extra["lyapunov_max_eig"]``. `checks` are further named checks of
    the caller, ``(name, value, failure)`` with ``failure`` ``None`` when it passed (the H∞
    bound, a finite-time reconstruction): each value goes into `extra`, each failure into
    `failures`. This is the one verification routine of every design result
    (`fojax.design.AbstractDesign.verify`).
    """
    error_matrices = np.asarray(error_matrices, dtype=float)
    if error_matrices.ndim == 2:
        error_matrices = error_matrices[None]
    res = {k: float(v) for k, v in residuals.items()}
    rel = relative_residual(res, scale, scales)
    eigs = (
        np.concatenate([np.linalg.eigvals(Ai) for Ai in error_matrices])
        if error_matrices.shape[-1]
        else np.zeros(0, complex)
    )
    margin = float(np.min(region.margin(eigs))) if eigs.size else np.inf
    failures = []
    if not np.isfinite(rel) or rel > rtol:
        failures.append(f"design-condition residual {rel:.2e} exceeds {rtol:.0e} (relative)")
    worst = eigs[np.argmin(region.margin(eigs))] if eigs.size else None
    failure = margin_failure("eigenvalue", worst, margin, required_margin(region), region)
    if failure is not None:
        failures.append(failure)
    lmi_max = xmin = None
    if X is not None:
        X = 0.5 * (X + X.T)
        xmin = float(np.linalg.eigvalsh(X).min())
        xnorm = float(np.linalg.norm(X, 2))
        lmi_max = max(
            float(np.linalg.eigvalsh(region.lmi_matrix(X, X @ Ai)).max()) for Ai in error_matrices
        )
        if not xmin > 0:
            failures.append(f"certificate X is not positive definite (min eigenvalue {xmin:.3e})")
        if not lmi_max < -LMI_MARGIN * xnorm:
            failures.append(
                f"region LMI re-checked in float64 has max eigenvalue {lmi_max:.3e} "
                f"(must be < {-LMI_MARGIN * xnorm:.1e})"
            )
    extra = dict(extra or {})
    if common_lyapunov and X is not None:
        lyap = max(float(np.linalg.eigvalsh(Ai.T @ X + X @ Ai).max()) for Ai in error_matrices)
        extra["lyapunov_max_eig"] = lyap
        if not lyap < -LMI_MARGIN * float(np.linalg.norm(X, 2)):
            failures.append(
                f"common Lyapunov inequality 𝔸_iᵀX + X𝔸_i ≺ 0 fails (max eigenvalue {lyap:.3e}): "
                "quadratic stability under time-varying weights is not certified")
    for name, value, failure in checks:
        extra[name] = value
        if failure is not None:
            failures.append(failure)
    report = VerificationReport(
        residuals=res,
        scale=float(scale),
        relative_residual=float(rel),
        eigenvalues=eigs,
        region=region.describe(),
        region_margin=margin,
        lmi_max_eig=lmi_max,
        certificate_min_eig=xmin,
        passed=not failures,
        failures=tuple(failures),
        extra=extra,
    )
    if failures and raise_on_failure:
        raise DesignVerificationError(
            "design failed its float64 verification: " + "; ".join(failures), report
        )
    return report


def combine_reports(reports: dict, checks: tuple = (), *, raise_on_failure: bool = True) -> VerificationReport:
    """One `VerificationReport` of a design made of several (a finite-time pair):
    residuals and failures prefixed by their label, eigenvalues concatenated, the worst
    margin, LMI eigenvalue and certificate eigenvalue, plus the `checks` of `verify`."""
    res, failures, extra = {}, [], {}
    for label, r in reports.items():
        res.update({f"{label}.{k}": v for k, v in r.residuals.items()})
        failures += [f"{label}: {f}" for f in r.failures]
        extra.update({f"{label} {k}": v for k, v in r.extra.items()})
    for name, value, failure in checks:
        extra[name] = value
        if failure is not None:
            failures.append(failure)
    rs = list(reports.values())
    lmis = [r.lmi_max_eig for r in rs if r.lmi_max_eig is not None]
    xmins = [r.certificate_min_eig for r in rs if r.certificate_min_eig is not None]
    report = VerificationReport(
        residuals=res,
        scale=max(r.scale for r in rs),
        relative_residual=max(r.relative_residual for r in rs),
        eigenvalues=np.concatenate([np.asarray(r.eigenvalues) for r in rs]),
        region="; ".join(f"{label}: {r.region}" for label, r in reports.items()),
        region_margin=min(r.region_margin for r in rs),
        lmi_max_eig=max(lmis) if lmis else None,
        certificate_min_eig=min(xmins) if xmins else None,
        passed=not failures,
        failures=tuple(failures),
        extra=extra,
    )
    if failures and raise_on_failure:
        raise DesignVerificationError("design failed its float64 verification: " + "; ".join(failures), report)
    return report
