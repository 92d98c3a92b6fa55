r"""Functional observers for discrete-time descriptor systems.

For a plant $Ex[k+1] = Ax[k] + Bu[k]$, $y[k] = Cx[k]$ (a `fojax.DescriptorSystem` with
``dt=h``) the generalized functional observer (thesis eq. 3.5) becomes the recursion

$$\zeta[k+1] = N\zeta[k] + Jv[k] + Fw[k] + Hu[k],\quad v[k+1] = S\zeta[k] + Gv[k] + Mw[k],
\quad \hat z[k] = P\zeta[k] + Qw[k],$$

with $w[k] = [-E^\perp Bu[k];\; y[k]]$.

**The design conditions are the same (derived).** Set $\varepsilon[k] = \zeta[k] - TEx[k]$.
Then $\varepsilon[k+1] = N\zeta + Jv + Fw + Hu - TAx - TBu$ at time $k$, which is the
continuous computation with $\dot x$ replaced by $x[k+1]$: the measured signal uses
$E^\perp E = 0$, hence $E^\perp Ax[k] = -E^\perp Bu[k]$ at every $k$, exactly as
$E^\perp Ax(t) = -E^\perp Bu(t)$ in continuous time, and every other step is algebraic.
So conditions a.–d. of the thesis (and Assumption 1, the rank conditions, the choice of
$R$) are unchanged, and when they hold
$[\varepsilon; v][k+1] = \mathbb A[\varepsilon; v][k]$, $\hat z[k] - Lx[k] = P\varepsilon[k]$,
with the same $\mathbb A = [N\;J;\;S\;G]$. Only the stability requirement changes: the
error decays iff every eigenvalue of $\mathbb A$ lies in the open unit disk, so the
region must lie inside it. A disk $\mathcal Q(\alpha, \tau)$ with $|\alpha| + \tau < 1$
(`fojax.design.DiscreteDisk`) has the same Chilali–Gahinet LMI, the same Riccati (DARE)
gain and the same Stein certificate as in continuous time — those routes are already
stated for a disk anywhere in the plane — so `fojax.design_functional_observer` runs its
usual LMI or Riccati/Stein route and its usual float64 verification (residuals of a.–d.,
eigenvalues in the region, the region LMI at the certificate); this module chooses and
checks the region and sets `dt` on the result. $H_\infty$/$H_2$ objectives (continuous-time
norms) are refused.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .._errors import DesignVerificationError, InputError, RegionError
from ._regions import AbstractRegion, as_region, DiscreteDisk, Disk, Intersection


#: The region of a discrete-time design when none is given: error decays like 0.5^k.
DEFAULT_DISCRETE_REGION = (0.0, 0.5)


def inside_unit_disk(region: AbstractRegion) -> bool:
    """Whether `region` lies in the open unit disk: a disk with ``|center| + radius < 1``,
    or an intersection with such a disk among its parts."""
    if isinstance(region, Intersection):
        return any(inside_unit_disk(p) for p in region.parts)
    if isinstance(region, Disk):
        return abs(float(region.center)) + float(region.radius) < 1.0
    return False


def _has_discrete_disk(region) -> bool:
    parts = region.parts if isinstance(region, Intersection) else (region,)
    return any(isinstance(p, DiscreteDisk) for p in parts)


def time_region(sys, region, objective: str = "region"):
    """The region of a design on `sys`, checked against its time domain.

    Continuous time (``sys.dt is None``): `region` unchanged, but a `DiscreteDisk` is refused.
    Discrete time: ``None`` gives ``DiscreteDisk(0.0, 0.5)``, a ``(center, radius)`` pair a
    `DiscreteDisk`; the region must lie inside the open unit disk (`inside_unit_disk`), else
    `fojax.errors.RegionError` naming it; objectives ``"hinf"``/``"h2"`` raise `fojax.errors.InputError`.
    """
    dt = getattr(sys, "dt", None)
    if dt is None:
        if isinstance(region, AbstractRegion) and _has_discrete_disk(region):
            raise RegionError(
                f"the region {region.describe()} is a z-plane disk for discrete-time models, but this model is "
                "continuous-time (dt=None). Use fojax.Disk(center, radius) with center + radius < 0, or build "
                "the model with DescriptorSystem(..., dt=h)."
            )
        return region
    if objective in ("hinf", "h2"):
        raise InputError(
            f"objective={objective!r} bounds a continuous-time norm; a discrete-time model (dt = {dt:g}) is "
            "designed with objective='region' or 'centre'."
        )
    if region is None:
        region = DEFAULT_DISCRETE_REGION
    if isinstance(region, tuple | list) and len(region) == 2:
        region = DiscreteDisk(*region)
    region = as_region(region)
    if not inside_unit_disk(region):
        raise RegionError(
            f"the region {region.describe()} is not inside the open unit disk, so it does not guarantee a "
            f"decaying error e[k+1] = N e[k] of the discrete-time model (dt = {dt:g}). Use "
            "fojax.design.DiscreteDisk(center, radius) with |center| + radius < 1 (alone or intersected "
            "with other regions)."
        )
    return region


def with_dt(design, dt):
    """`design` with `dt` set on its observer and a note in its report (``dt=None``:
    `design` unchanged). Re-checks in float64 that the error eigenvalues are inside the
    unit disk (`fojax.errors.DesignVerificationError` otherwise; the design's verification has
    already placed them in its region)."""
    if dt is None:
        return design
    ev = np.linalg.eigvals(np.asarray(design.observer.error_matrix, dtype=float))
    rho = float(np.max(np.abs(ev))) if ev.size else 0.0
    if not rho < 1.0:
        raise DesignVerificationError(
            f"discrete-time design: the error matrix has spectral radius {rho:.6g} >= 1 (the error does not "
            "decay); choose a region inside the unit disk.", design.report)
    obs = dataclasses.replace(design.observer, dt=float(dt))
    note = (f"discrete-time (dt = {float(dt):g}): error e[k+1] = 𝔸 e[k], spectral radius {rho:.6g} < 1")
    report = dataclasses.replace(design.report, extra={**design.report.extra, "time": note})
    return dataclasses.replace(design, observer=obs, report=report)


def continuous_only(sys, fname: str) -> None:
    """`fojax.errors.InputError` when `sys` is a discrete-time model: `fname` designs continuous-time
    observers or controllers only (its regions and certificates are continuous-time)."""
    dt = getattr(sys, "dt", None)
    if dt is not None:
        raise InputError(
            f"{fname} designs for continuous-time models; this model is discrete-time (dt = {dt:g}). Discrete-time "
            "observers come from design_functional_observer (regions inside the unit disk); or design on the "
            "continuous model and sample the result with fojax.discretize."
        )
