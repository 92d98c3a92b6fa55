r"""The final tunable parameterizations of `fojax.design.AbstractParameterization`:
`SteinDisk` and `FixedCertificateDisk` (linear time-invariant designs in a disk) and
`CommonCertificate` (Takagi–Sugeno designs). The protocol, the live-parameter count and
`fojax.design.certify` are in `fojax.design._tunable`.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._errors import InputError
from ._functional import verify_structure_design
from ._gain_parameterization import contraction, disk_gain
from ._parameterization import (
    error_dynamics,
    FunctionalObserverStructure,
    pieces,
)
from ._regions import AbstractRegion, as_region, Disk
from ._stein import host_stein_certificate
from ._tunable import (
    _check_kind,
    _design_blocks,
    _disk,
    _full,
    _lti_design,
    _stein_margin,
    _stein_margin_jit,
    _stein_P,
    AbstractParameterization,
)


class SteinDisk(AbstractParameterization):
    r"""The free parameters themselves, certified by the Stein solution of each iterate.

    The parameters are $Z, Y_1, Y_2, Y_3, J, G$ of `fojax.design.observer_matrices` (``Z``
    frozen with ``tune_Z=False``; the blocks that are empty for a proportional design are
    omitted). For the error dynamics $\mathbb A$, `stein_certificate` gives ``P ≻ 0`` iff
    every eigenvalue is in the disk $\mathcal Q(\alpha, \tau)$; the margin is
    ``1/λ_max(P) ∈ (0, 1]`` inside (→ 0 at the boundary, −1 outside), the barrier
    ``log tr P``. The certificate of `certify` is ``P`` recomputed in float64 by SciPy.

    *Deviation from the thesis:* the thesis tunes through the $(\mathcal L, \gamma)$ map
    with a fixed certificate (`FixedCertificateDisk`); with a fixed certificate the error
    modes set by ``Z`` cannot move freely.
    """

    structure: FunctionalObserverStructure
    region: Disk
    Z: jax.Array
    kind: str = eqx.field(static=True)
    tune_Z: bool = eqx.field(static=True)

    def __init__(self, design, region=None, *, tune_Z: bool = True):
        _lti_design(design, "SteinDisk")
        self.region = _disk(design, region, "SteinDisk")
        self.structure = design.structure
        self.Z = jnp.asarray(np.asarray(design.params["Z"]))
        self.kind = design.kind
        self.tune_Z = bool(tune_Z)
        if not self.host_margin(self.init(design)) > 0:
            raise InputError(
                f"the design's error dynamics are not inside {self.region.describe()}; pass the region the "
                "design was made for (or one containing its eigenvalues)."
            )

    def init(self, design) -> dict:
        return _design_blocks(design, self.tune_Z)

    def design_params(self, params) -> dict:
        return _full(self.structure, params, self.Z)

    def _P(self, params):
        return _stein_P(self.structure, self.region, self.Z, params)

    def margin(self, params):
        return _stein_margin(self.structure, self.region, self.Z, params)

    def host_margin(self, params) -> float:
        # from the fields: the same program in __init__ (before the module exists) and after
        return float(_stein_margin_jit(self.structure, self.region, self.Z, params))

    def barrier(self, params):
        return jnp.log(jnp.trace(self._P(params)))

    def certificate(self, params) -> np.ndarray:
        A = self.host_error_matrices(params)[0]
        if not np.all(np.abs(np.linalg.eigvals(A) - self.region.center) < self.region.radius):
            return np.full(A.shape, np.nan)
        return host_stein_certificate(A, self.region.center, self.region.radius)


def _inverse_contraction(Lc: np.ndarray) -> np.ndarray:
    """Θ with ``contraction(Θ) = Lc`` (``‖Lc‖ < 1``): ``Θ = Lc C_u``, ``C_u C_uᵀ = (I − LcᵀLc)^{-1}``
    with ``C_u`` upper triangular (a reversed Cholesky factor)."""
    k = Lc.shape[1]
    S = np.linalg.inv(np.eye(k) - Lc.T @ Lc)
    S = 0.5 * (S + S.T)
    Jr = np.eye(k)[::-1]
    Cu = Jr @ np.linalg.cholesky(Jr @ S @ Jr) @ Jr
    return Lc @ Cu


class FixedCertificateDisk(AbstractParameterization):
    r"""All gains with the LMI certificate $X$ of a disk, fixed (`fojax.design.disk_gain`).

    The exact disk counterpart of the thesis's Lemma 10 $(\mathcal L, \gamma)$ map: every
    ``Theta`` ``(d, k)`` (through the contraction
    $\mathcal L = \Theta(I + \Theta^\top\Theta)^{-1/2}$) gives a gain $\mathbb Y$ with
    $(\mathbb A - \alpha I)^\top X(\mathbb A - \alpha I) \prec \tau^2 X$ as long as the margin
    $\tau - \|A_\perp(Z)\|$ is positive. Parameters: ``Theta``, ``Y3`` (enters only $P, Q$)
    and, with ``tune_Z=True``, ``Z`` (it moves $\mathbb A_1$, so the margin can shrink).
    The component $Y_\perp$ of the gain outside the range of $\tilde B$ is kept at the
    design's value (it changes nothing). The certificate of `certify` is $X$.
    """

    structure: FunctionalObserverStructure
    region: Disk
    X: jax.Array
    N1: jax.Array
    N2: jax.Array
    A2: jax.Array
    Z: jax.Array
    Yperp: jax.Array
    kind: str = eqx.field(static=True)
    rank: int = eqx.field(static=True)
    tune_Z: bool = eqx.field(static=True)

    def __init__(self, design, region=None, *, tune_Z: bool = False):
        _lti_design(design, "FixedCertificateDisk")
        region = _disk(design, region, "FixedCertificateDisk")
        s = design.structure
        pc = pieces(s, xp=np)
        q0, q1 = s.q0, s.q1
        c = pc.N3.shape[0]
        N1, N2, N3 = np.asarray(pc.N1[0]), np.asarray(pc.N2[0]), np.asarray(pc.N3)
        A2 = N3 if q1 == 0 else np.block([[N3, np.zeros((c, q1))], [np.zeros((q1, q0)), -np.eye(q1)]])
        p = design.params
        Y = np.asarray(p["Y1"]) if q1 == 0 else np.block([[p["Y1"], p["J"]], [p["Y2"], p["G"]]])
        X = 0.5 * (design.X + design.X.T)
        Lx = np.linalg.cholesky(X)
        self.structure, self.region, self.kind, self.tune_Z = s, region, design.kind, bool(tune_Z)
        self.X, self.N1, self.N2, self.A2 = (jnp.asarray(a) for a in (X, N1, N2, A2))
        self.Z = jnp.asarray(np.asarray(p["Z"]))
        self.Yperp = jnp.asarray(Lx.T @ Y)
        self.rank = int(np.linalg.matrix_rank(A2)) if np.size(A2) else 0  # NumPy < 2.4.5 raises on empty

    def _A1(self, Z):
        s = self.structure
        top = self.N1 - Z @ self.N2
        if s.q1 == 0:
            return top
        return jnp.block([[top, jnp.zeros((s.q0, s.q1))], [jnp.zeros((s.q1, s.q0 + s.q1))]])

    def _gain(self, params):
        Z = params.get("Z", self.Z)
        Y, margin = disk_gain(self.X, self._A1(Z), self.A2, self.region.center, self.region.radius,
                              contraction(params["Theta"]), self.Yperp, rank=self.rank)
        return Z, Y, margin

    def init(self, design) -> dict:
        s = self.structure
        p = design.params
        q1 = s.q1
        Z = np.asarray(p["Z"])
        Y = np.asarray(p["Y1"]) if q1 == 0 else np.block([[p["Y1"], p["J"]], [p["Y2"], p["G"]]])
        A1, A2, X = np.asarray(self._A1(jnp.asarray(Z))), np.asarray(self.A2), np.asarray(self.X)
        d = X.shape[0]
        al, tau = self.region.center, self.region.radius
        Lx = np.linalg.cholesky(X)
        LxinvT = np.linalg.inv(Lx.T)
        M = Lx.T @ (A1 - Y @ A2 - al * np.eye(d)) @ LxinvT
        _, _, Vt = np.linalg.svd(A2 @ LxinvT)
        Vb, Vp = Vt[:self.rank].T, Vt[self.rank:].T
        M0 = Lx.T @ (A1 - al * np.eye(d)) @ LxinvT
        F = np.linalg.cholesky(tau**2 * np.eye(d) - (M0 @ Vp) @ (M0 @ Vp).T)
        Lc = np.linalg.solve(F, M @ Vb)
        if not np.linalg.norm(Lc, 2) < 1.0:
            raise InputError(
                f"the design's certificate X does not certify {self.region.describe()} for its own gain "
                f"(‖𝓛‖ = {np.linalg.norm(Lc, 2):.4f} ≥ 1); pass the region the design was made for."
            )
        params = {"Theta": jnp.asarray(_inverse_contraction(Lc)), "Y3": jnp.asarray(p["Y3"])}
        if self.tune_Z:
            params["Z"] = jnp.asarray(Z)
        return params

    def design_params(self, params) -> dict:
        s = self.structure
        Z, Y, _ = self._gain(params)
        q0, c = s.q0, s.q0 + s.nw
        return {"Z": Z, "Y1": Y[:q0, :c], "J": Y[:q0, c:], "Y2": Y[q0:, :c], "G": Y[q0:, c:], "Y3": params["Y3"]}

    def margin(self, params):
        return self._gain(params)[2]

    def certificate(self, params) -> np.ndarray:
        return np.asarray(self.X)


class CommonCertificate(AbstractParameterization):
    r"""Takagi–Sugeno: the design's common certificate $X$ fixed; parameters moved directly.

    Parameters: the common ``Z`` (frozen with ``tune_Z=False``) and the per-rule
    ``Y1, Y2, Y3, J, G`` with their leading rule axis (the blocks that are empty for a
    proportional design are omitted). Admissible when, for every rule $i$, the region LMI
    $L_R\otimes X + M_R\otimes(\mathbb A_i^\top X) + M_R^\top\otimes(X\mathbb A_i) \prec 0$
    (`fojax.design.AbstractRegion.lmi_matrix`) and the Lyapunov inequality
    $\mathbb A_i^\top X + X\mathbb A_i \prec 0$ hold; both are affine in $\mathbb A_i$, so they
    then hold for every convex combination of the rules. The margin is the smallest
    eigenvalue of all $-\mathcal R_i/\|X\|$, $-\mathcal L_i/\|X\|$; the barrier
    $-\sum_i(\log\det(-\mathcal R_i/\|X\|) + \log\det(-\mathcal L_i/\|X\|))$. Any region the
    T-S design accepts works (disks, half-planes, sectors, intersections). `certify`
    verifies like `fojax.design.design_ts_observer` (plus the Lyapunov re-check).

    *Deviation from the thesis:* the thesis gives no tuning of T-S observers; with a common
    certificate the explicit $(\mathcal L, \gamma)$ map of one rule does not apply.
    """

    structure: FunctionalObserverStructure
    region: AbstractRegion
    membership: eqx.Module
    X: jax.Array
    LR: jax.Array
    MR: jax.Array
    Z: jax.Array
    Wu: jax.Array
    Wy: jax.Array
    xnorm: jax.Array
    kind: str = eqx.field(static=True)
    tune_Z: bool = eqx.field(static=True)

    def __init__(self, design, region=None, *, tune_Z: bool = True):
        from ._takagi_sugeno import TakagiSugenoObserverDesign

        if not isinstance(design, TakagiSugenoObserverDesign):
            raise InputError(
                f"CommonCertificate needs a TakagiSugenoObserverDesign (fojax.design.design_ts_observer), got "
                f"{type(design).__name__}; for LTI designs use SteinDisk or FixedCertificateDisk."
            )
        _check_kind(design, "CommonCertificate")
        region = design.region if region is None else as_region(region)
        X = 0.5 * (np.asarray(design.X, dtype=float) + np.asarray(design.X, dtype=float).T)
        LR, MR = (np.asarray(a, dtype=float) for a in region.characteristic())
        obs = design.observer
        self.structure, self.region, self.membership = design.structure, region, obs.membership
        self.X, self.LR, self.MR = jnp.asarray(X), jnp.asarray(LR), jnp.asarray(MR)
        self.Z = jnp.asarray(np.asarray(design.params["Z"]))
        self.Wu, self.Wy = jnp.asarray(obs.Wu), jnp.asarray(obs.Wy)
        self.xnorm = jnp.asarray(float(np.linalg.norm(X, 2)))
        self.kind, self.tune_Z = design.kind, bool(tune_Z)
        margin = float(self.margin(self.init(design)))
        if not margin > 0:
            raise InputError(
                f"the design's certificate X does not satisfy the LMI of {region.describe()} and the Lyapunov "
                f"inequality for every rule (relative margin {margin:.3e} <= 0); pass the region the "
                "design was made for."
            )

    def init(self, design) -> dict:
        return _design_blocks(design, self.tune_Z)

    def design_params(self, params) -> dict:
        return _full(self.structure, params, self.Z, rules=self.structure.num_rules)

    def _observer_of(self, m):
        from ..observer import TakagiSugenoObserver

        return TakagiSugenoObserver(m.N, m.J, m.F, m.H, m.S, m.G, m.M, m.P, m.Q, self.Wu, self.Wy, m.T,
                                    self.membership, kind=self.kind)

    def lmi_blocks(self, params):
        """``(region, lyapunov)``: ``-𝓡_i/‖X‖`` and ``-𝓛_i/‖X‖`` per rule (``≻ 0`` iff admissible)."""
        As = error_dynamics(self.matrices(params))
        X = self.X
        XA = jnp.einsum("ij,kjl->kil", X, As)
        XAt = jnp.swapaxes(XA, -1, -2)

        def kron(a, b):  # a (r, r), b (k, d, d) -> (k, r d, r d)
            r, d = a.shape[0], b.shape[-1]
            return jnp.einsum("ij,kab->kiajb", a, b).reshape(b.shape[0], r * d, r * d)

        k = As.shape[0]
        reg = kron(self.LR, jnp.broadcast_to(X, (k,) + X.shape)) + kron(self.MR, XAt) + kron(self.MR.T, XA)
        reg = 0.5 * (reg + jnp.swapaxes(reg, -1, -2))
        lyap = 0.5 * (XAt + XA + jnp.swapaxes(XAt + XA, -1, -2))
        return -reg / self.xnorm, -lyap / self.xnorm

    def _margin_and_logdet(self, params):
        R, Ly = self.lmi_blocks(params)
        er, el = jnp.linalg.eigvalsh(R), jnp.linalg.eigvalsh(Ly)
        margin = jnp.minimum(jnp.min(er), jnp.min(el))
        inside = margin > 0
        safe = lambda e: jnp.where(inside, e, 1.0)  # noqa: E731
        logdet = jnp.sum(jnp.log(safe(er))) + jnp.sum(jnp.log(safe(el)))
        margin = jnp.where(jnp.isfinite(margin), margin, -jnp.inf)
        return margin, jnp.where(inside, logdet, -jnp.inf)

    def margin(self, params):
        return self._margin_and_logdet(params)[0]

    def barrier(self, params):
        return -self._margin_and_logdet(params)[1]

    def certificate(self, params) -> np.ndarray:
        return np.asarray(self.X)

    def certify(self, params):
        from ..observer import TakagiSugenoObserver
        from ._takagi_sugeno import TakagiSugenoObserverDesign

        p = {k: np.asarray(v, dtype=float) for k, v in self.design_params(params).items()}
        X = np.asarray(self.X)
        mats, report = verify_structure_design(self.structure, p, self.region, X, common_lyapunov=True)
        obs = TakagiSugenoObserver(mats.N, mats.J, mats.F, mats.H, mats.S, mats.G, mats.M, mats.P, mats.Q,
                                   np.asarray(self.Wu), np.asarray(self.Wy), mats.T, self.membership, kind=self.kind)
        return TakagiSugenoObserverDesign.from_matrices(self.structure, mats, p, observer=obs, kind=self.kind,
                                                        region=self.region, X=X, report=report,
                                                        solver={"parameterization": type(self).__name__})
