r"""LMI regions of the complex plane (Chilali & Gahinet, thesis §2.2).

An LMI region is $\mathcal R = \{s \in \mathbb C : L_R + M_R s + M_R^\top \bar s \prec 0\}$
with $L_R = L_R^\top$. A real matrix $\mathbb A$ has all its eigenvalues in
$\mathcal R$ iff there is $X \succ 0$ with

$$L_R \otimes X + M_R \otimes (\mathbb A^\top X) + M_R^\top \otimes (X\mathbb A) \prec 0,$$

(the form for $\mathbb A^\top$ of Chilali–Gahinet's theorem, which is linear in
$X\mathbb A$ — the product that observer gains enter). Intersections of regions are
LMI regions with block-diagonal $L_R, M_R$: a user can ask for a disk, a decay
rate and a minimum damping at once::

    region = fojax.Disk(-3.0, 2.0) & fojax.HalfPlane(decay=1.0) & fojax.Sector(damping=0.7)

Every region also has an exact pointwise test (`margin`), used to verify designs
independently of the LMI.
"""

from __future__ import annotations

import abc
import math

import equinox as eqx
import numpy as np

from .._errors import RegionError


class AbstractRegion(eqx.Module):
    """An LMI region. Its numbers are `numpy.float64` leaves (not static fields): they
    behave as Python floats on the host (LMI code, reports, JSON, equality, hashing), and
    `equinox.filter_jit` traces them as data, so a region with new numbers reuses compiled
    code (a static float recompiled the tuning step for every new `Disk`)."""

    @abc.abstractmethod
    def characteristic(self) -> tuple[np.ndarray, np.ndarray]:
        """``(L_R, M_R)`` of the characteristic function."""

    @abc.abstractmethod
    def margin(self, eigs) -> np.ndarray:
        """Signed distance-like margin per eigenvalue: ``> 0`` inside, ``< 0`` outside."""

    @abc.abstractmethod
    def describe(self) -> str: ...

    @abc.abstractmethod
    def tightened(self, fraction: float) -> AbstractRegion:
        """A slightly smaller region (designs target it so that eigenvalues keep a margin)."""

    @abc.abstractmethod
    def target(self) -> complex:
        """A well-inside point (used to place modes fixed by the structure)."""

    def size(self) -> float:
        """A length scale of the region (``inf`` if unbounded): verification asks for
        margins small against it (`fojax.design._verify.required_margin`)."""
        return math.inf

    def contains(self, eigs, tol: float = 0.0) -> bool:
        eigs = np.atleast_1d(np.asarray(eigs))
        return bool(eigs.size == 0 or np.min(self.margin(eigs)) > tol)

    def __and__(self, other: AbstractRegion) -> Intersection:
        return Intersection((self, other))

    def lmi_matrix(self, X: np.ndarray, XA: np.ndarray) -> np.ndarray:
        """``L⊗X + M⊗(XA)ᵀ + Mᵀ⊗(XA)`` evaluated in float64 (for verification)."""
        L, M = self.characteristic()
        out = np.kron(L, X) + np.kron(M, XA.T) + np.kron(M.T, XA)
        return 0.5 * (out + out.T)

    @abc.abstractmethod
    def to_dict(self) -> dict:
        """A JSON-able description (inverse: `region_from_dict`)."""

    def __str__(self) -> str:
        return self.describe()


class Disk(AbstractRegion):
    r"""Disk $\mathcal Q(\alpha, \tau)$ centred at $(\alpha, 0)$ with radius $\tau$ (Lemma 5)."""

    center: float
    radius: float

    def __init__(self, center: float, radius: float):
        center, radius = float(center), float(radius)
        if not (math.isfinite(center) and math.isfinite(radius)) or radius <= 0:
            raise RegionError(
                f"{type(self).__name__} needs a finite center and a positive radius; got center={center}, "
                f"radius={radius}."
            )
        self._check_stable(center, radius)
        self.center, self.radius = np.float64(center), np.float64(radius)

    @staticmethod
    def _check_stable(center: float, radius: float) -> None:
        """Raise `RegionError` unless the disk's eigenvalues are stable (here: continuous time)."""
        if center + radius >= 0:
            raise RegionError(
                f"Disk(center={center}, radius={radius}) reaches into the closed right half-plane "
                f"(rightmost point {center + radius}); observer error dynamics would not be stable. "
                "Choose center + radius < 0."
            )

    def characteristic(self):
        a, r = self.center, self.radius
        return np.array([[-r, -a], [-a, -r]]), np.array([[0.0, 1.0], [0.0, 0.0]])

    def margin(self, eigs):
        return self.radius - np.abs(np.asarray(eigs) - self.center)

    def size(self):
        return self.radius

    def describe(self):
        return f"disk centred at {self.center:g} with radius {self.radius:g}"

    def tightened(self, fraction):
        return type(self)(self.center, self.radius * (1.0 - fraction))

    def target(self):
        return complex(self.center)

    def to_dict(self):
        return {"type": "disk", "center": float(self.center), "radius": float(self.radius)}


class DiscreteDisk(Disk):
    r"""A disk of the $z$-plane for discrete-time error dynamics $e[k+1] = \mathbb A e[k]$:
    centre $(\alpha, 0)$, radius $\tau$, inside the open unit disk ($|\alpha| + \tau < 1$).

    The eigenvalues in $\mathcal Q(\alpha, \tau)$ make the error decay at least like
    $(|\alpha| + \tau)^k$. The LMI, the pointwise margin, the Riccati/Stein route and the
    verification are those of `fojax.Disk` (a disk is a disk); only the validation differs:
    `Disk` must lie in the left half-plane (continuous time), `DiscreteDisk` in the unit
    disk. The default region of a discrete-time design is ``DiscreteDisk(0.0, 0.5)``.

    **Arguments:** `center` $\alpha$ (real), `radius` $\tau > 0$.

    **Raises:** `fojax.errors.RegionError` when the disk is not inside the open unit disk.

    !!! example

        ```python
        sys = fojax.DescriptorSystem(E, A, B, C, dt=0.1)
        d = fojax.design_functional_observer(sys, L, region=fojax.design.DiscreteDisk(0.2, 0.5))
        ```
    """

    @staticmethod
    def _check_stable(center: float, radius: float) -> None:
        if abs(center) + radius >= 1:
            raise RegionError(
                f"DiscreteDisk(center={center}, radius={radius}) is not inside the open unit disk "
                f"(|center| + radius = {abs(center) + radius:g} >= 1); discrete-time error dynamics with "
                "eigenvalues there would not decay. Choose |center| + radius < 1."
            )

    def describe(self):
        return f"z-plane disk centred at {self.center:g} with radius {self.radius:g}"

    def to_dict(self):
        return {"type": "discrete_disk", "center": float(self.center), "radius": float(self.radius)}


class HalfPlane(AbstractRegion):
    r"""$\{\operatorname{Re} s < -\sigma\}$: decay rate at least $\sigma \ge 0$."""

    decay: float

    def __init__(self, decay: float = 0.0):
        decay = float(decay)
        if not math.isfinite(decay) or decay < 0:
            raise RegionError(f"HalfPlane needs a decay rate >= 0; got decay={decay}.")
        self.decay = np.float64(decay)

    def characteristic(self):
        return np.array([[2.0 * self.decay]]), np.array([[1.0]])

    def margin(self, eigs):
        return -self.decay - np.real(np.asarray(eigs))

    def describe(self):
        return f"Re(s) < {-self.decay:g}"

    def tightened(self, fraction):
        return HalfPlane(self.decay + fraction * max(1.0, self.decay))

    def target(self):
        return complex(-self.decay - max(1.0, self.decay))

    def to_dict(self):
        return {"type": "halfplane", "decay": float(self.decay)}


class Sector(AbstractRegion):
    r"""Conic sector around the negative real axis: damping ratio at least `damping`.

    $\{s : |\operatorname{Im} s| < -\operatorname{Re}(s)\tan\theta\}$ with
    $\cos\theta = \zeta_{\min}$.
    """

    damping: float

    def __init__(self, damping: float):
        damping = float(damping)
        if not (0.0 < damping < 1.0):
            raise RegionError(f"Sector needs a damping ratio in (0, 1); got damping={damping}.")
        self.damping = np.float64(damping)

    def characteristic(self):
        th = math.acos(self.damping)
        s, c = math.sin(th), math.cos(th)
        return np.zeros((2, 2)), np.array([[s, c], [-c, s]])

    def margin(self, eigs):
        eigs = np.asarray(eigs)
        th = math.acos(self.damping)
        # distance-like: -Re(s) sin θ - |Im(s)| cos θ  (> 0 strictly inside the cone)
        return -np.real(eigs) * math.sin(th) - np.abs(np.imag(eigs)) * math.cos(th)

    def describe(self):
        return f"damping >= {self.damping:g}"

    def tightened(self, fraction):
        return Sector(self.damping + fraction * (1.0 - self.damping))

    def target(self):
        return complex(-1.0)

    def to_dict(self):
        return {"type": "sector", "damping": float(self.damping)}


class Intersection(AbstractRegion):
    """Intersection of LMI regions (block-diagonal characteristic matrices)."""

    parts: tuple[AbstractRegion, ...]

    def __init__(self, parts):
        flat = []
        for p in parts:
            flat.extend(p.parts if isinstance(p, Intersection) else [p])
        if not flat:
            raise RegionError("Intersection needs at least one region.")
        self.parts = tuple(flat)

    def characteristic(self):
        from scipy.linalg import block_diag

        Ls, Ms = zip(*(p.characteristic() for p in self.parts))
        return block_diag(*Ls), block_diag(*Ms)

    def margin(self, eigs):
        return np.min(np.stack([p.margin(eigs) for p in self.parts]), axis=0)

    def size(self):
        return min(p.size() for p in self.parts)

    def describe(self):
        return " and ".join(p.describe() for p in self.parts)

    def tightened(self, fraction):
        return Intersection(tuple(p.tightened(fraction) for p in self.parts))

    def target(self):
        # The point of largest margin among the parts' targets and a scan of the real
        # axis (every region here is symmetric and meets the real axis when non-empty).
        cands = np.concatenate(
            [[p.target().real for p in self.parts], -np.logspace(-3, 4, 400)]
        )
        best = cands[np.argmax(self.margin(cands.astype(complex)))]
        return complex(best)

    def to_dict(self):
        return {"type": "intersection", "parts": [p.to_dict() for p in self.parts]}


def region_from_dict(d: dict) -> AbstractRegion:
    """Inverse of `AbstractRegion.to_dict` (used by saved designs and config files)."""
    kind = d.get("type")
    if kind == "disk":
        return Disk(d["center"], d["radius"])
    if kind == "discrete_disk":
        return DiscreteDisk(d["center"], d["radius"])
    if kind == "halfplane":
        return HalfPlane(d.get("decay", 0.0))
    if kind == "sector":
        return Sector(d["damping"])
    if kind == "intersection":
        return Intersection(tuple(region_from_dict(p) for p in d["parts"]))
    raise RegionError(f"unknown region type {kind!r}; expected disk, discrete_disk, halfplane, sector or intersection.")


def as_region(region) -> AbstractRegion:
    """Accept a region, a ``(center, radius)`` disk tuple or a dict."""
    if isinstance(region, AbstractRegion):
        return region
    if isinstance(region, dict):
        return region_from_dict(region)
    if isinstance(region, tuple | list) and len(region) == 2:
        return Disk(*region)
    raise RegionError(
        f"cannot interpret {region!r} as a pole region; pass fojax.Disk(center, radius), "
        "fojax.HalfPlane(decay), fojax.Sector(damping), an intersection with '&', or (center, radius)."
    )
