r"""Well-centred LMI design: the error eigenvalues as far inside the region as the LMI allows.

`fojax.design.design_functional_observer(..., objective="centre")`.

**Why.** The region LMI with a minimum-gain objective (the default) returns a point on the
boundary of the feasible set: its error eigenvalues sit on the slow edge of the region
(e.g. −1.10 in ``Disk(-3, 2)``), an arbitrary feasible point. A design whose eigenvalues
keep the largest margin to the region's boundary is a better-defined starting point (for
tuning, and for "% better than the LMI design").

**Derivation.** For a disk $\mathcal Q(\alpha, \tau)$ the Chilali–Gahinet matrix of the
region LMI (thesis Lemma 5, `fojax.design._lmi.region_lmi`) is
$\mathcal M(X, \Phi) = L\otimes X + M\otimes\Phi^\top + M^\top\otimes\Phi$ with
$L = [[-\tau, -\alpha], [-\alpha, -\tau]]$, $M = [[0, 1], [0, 0]]$ and $\Phi = X\mathbb A$.
Asking for a margin $t$,

$$\mathcal M(X, \Phi) + t\,(I_2\otimes X) \prec 0,$$

replaces $\tau$ by $\tau - t$: it is the same LMI for the concentric disk
$\mathcal Q(\alpha, \tau - t)$, and it certifies every eigenvalue of $\mathbb A$ at distance
$\ge t$ from the boundary of $\mathcal Q(\alpha, \tau)$ (the disk's margin,
`Disk.margin`, is $\tau - |\lambda - \alpha|$). The term $t X$ is bilinear in $(t, X)$: maximising
$t$ is a *generalized eigenvalue problem* (Boyd, El Ghaoui, Feron, Balakrishnan, *Linear
Matrix Inequalities in System and Control Theory*, SIAM 1994, §2.2.3 and §5.1), which is
quasi-convex: the feasible $t$ form an interval $[0, t^*)$ because the disks are nested.
It is solved by bisection, each step the ordinary (convex) design LMI of `solve_gains`
— the thesis's Theorem 1 LMI with its linearizing change of variables, normalised by
$X \succeq I$ — for the region `region.tightened(f)` (for a disk $\mathcal Q(\alpha,
\tau(1-f))$, i.e. $t = \tau f$; an intersection tightens every part by the same
fraction). The returned design is the minimum-gain solution at the largest feasible
fraction found, $f_{\mathrm{lo}}$, within `CENTRE_TOL` of $f^*$; it is verified in float64
like every design (`fojax.design.verify`), against the *requested* region, and its
report shows the achieved spectral margin (``report.region_margin``) beside the certified
one ($\tau f_{\mathrm{lo}}$).

**Deviation from the thesis.** The thesis fixes a region and returns any feasible point;
it has no margin objective. Here the region is the same, the LMI the same, only the
radius is searched. Bisection steps at which the solver does not reach status
``optimal`` count as infeasible (a solver failure near $f^*$ makes $f_{\mathrm{lo}}$
smaller, never wrong: the returned point is verified).

**Bounded regions only.** A half-plane or a sector has no centre: its margin grows without
bound as the eigenvalues move left (and the gains with them). ``objective="centre"``
needs a `Disk` or an intersection with one.
"""

from __future__ import annotations

from .._errors import InputError, LMI_FAILURES
from ._regions import AbstractRegion, Disk, HalfPlane, Intersection


#: The bisection stops when the bracket [f_lo, f_hi] of the tightening fraction is this narrow.
CENTRE_TOL = 0.01
#: Largest fraction tried: a disk shrunk by 99 % (eigenvalues within 1 % of the radius of the centre).
CENTRE_MAX = 0.99


def check_bounded(region: AbstractRegion) -> None:
    """`InputError` unless `region` is a `Disk` or an intersection with one."""
    parts = region.parts if isinstance(region, Intersection) else (region,)
    if not any(isinstance(p, Disk) for p in parts):
        raise InputError(
            f"objective='centre' needs a bounded region (a Disk, or an intersection with one); got "
            f"{region.describe()}, which has no centre (its margin grows without bound as the eigenvalues "
            "move left, and the gains with them). Use region=fojax.Disk(center, radius).")


def centred_gains(solve, region: AbstractRegion, lo: float):
    r"""Bisection on the tightening fraction (module docstring).

    `solve(region)` returns ``(X, Z, Ys, info)`` or raises `LMIInfeasibleError`; `lo` is a
    fraction at which the plain design is solved first (it must be feasible: its error is
    the design's error). Returns ``(X, Z, Ys, info)`` of the largest feasible fraction
    found, with ``info["centre"]`` = the fraction, the certified margin bound and the steps.
    """
    check_bounded(region)
    best = solve(region.tightened(lo))
    f_lo, f_hi, steps = lo, CENTRE_MAX, []
    try:  # the top of the bracket is often feasible (every eigenvalue assignable)
        best, f_lo = solve(region.tightened(f_hi)), f_hi
        steps.append((f_hi, True))
    except LMI_FAILURES:
        steps.append((f_hi, False))
    while f_hi - f_lo > CENTRE_TOL and f_lo < CENTRE_MAX:
        f = 0.5 * (f_lo + f_hi)
        try:
            best, f_lo = solve(region.tightened(f)), f
            steps.append((f, True))
        except LMI_FAILURES:
            f_hi = f
            steps.append((f, False))
    X, Z, Ys, info = best
    info["centre"] = {
        "fraction": float(f_lo),
        "infeasible_above": float(f_hi) if f_hi > f_lo else None,
        "certified_margin": float(_certified_margin(region, f_lo)),
        "steps": [[float(f), bool(ok)] for f, ok in steps],
    }
    return X, Z, Ys, info


def _certified_margin(region: AbstractRegion, fraction: float) -> float:
    """The margin to `region` that every point of ``region.tightened(fraction)`` has: ``τ·f``
    for a disk, the shift ``f·max(1, σ)`` for a half-plane, 0 for a sector (a tighter cone
    touches the original at the origin); the smallest over an intersection's parts."""
    parts = region.parts if isinstance(region, Intersection) else (region,)
    out = []
    for p in parts:
        if isinstance(p, Disk):
            out.append(float(p.radius) * fraction)
        elif isinstance(p, HalfPlane):
            out.append(fraction * max(1.0, float(p.decay)))
        else:
            out.append(0.0)
    return min(out)
