r"""H∞ functional-observer design: a guaranteed L2-gain bound inside the region LMI.

**The plant with exogenous inputs.** $E\dot x = Ax + Bu + B_w w$, $y = Cx + D_v\nu$,
$z = Lx$. The observer (thesis eq. 3.5) is driven by the measured signal
$\omega = [-E^\perp Bu;\, y]$. Since $E^\perp E = 0$, the algebraic rows give
$-E^\perp Bu = E^\perp Ax + E^\perp B_w w$, so

$$\omega = \Psi x + \mathcal D d,\qquad d = \begin{bmatrix}w\\ \nu\end{bmatrix},\qquad
  \mathcal D = \begin{bmatrix}E^\perp B_w & 0\\ 0 & D_v\end{bmatrix}.$$

**Error system (derived here; the thesis has no disturbance channels).** With
$\varepsilon = \zeta - TEx$ and conditions a.–d. (`fojax.design.observer_matrices`):

$$\dot\varepsilon = N\varepsilon + Jv + (F\mathcal D - T\bar B_w)d,\quad
  \dot v = S\varepsilon + Gv + M\mathcal D d,\quad
  \hat z - z = P\varepsilon + Q\mathcal D d,$$

$\bar B_w = [B_w\; 0]$. Write $e = [\varepsilon; v]$, $\dot e = \mathbb A e + \mathbb B d$,
$\hat z - z = \mathbb C e + \mathbb D d$. With $Z$ fixed and the free parameters
$\mathbb Y = [Y_1\,J;\,Y_2\,G]$, $Y_3$ every matrix is *affine*:

$$\mathbb A = \mathbb A_1 - \mathbb Y\mathbb A_2,\quad
  \mathbb B = \mathbb B_1 - \mathbb Y\mathbb B_2,\quad
  \mathbb C = \mathbb C_1 - Y_3\mathbb C_2,\quad \mathbb D = \mathbb D_1 - Y_3 F_3\mathcal D,$$

$\mathbb A_2 = \operatorname{diag}(N_3, -I)$, $\mathbb B_1 = [F_0\mathcal D - T\bar B_w;\,0]$,
$\mathbb B_2 = [F_3\mathcal D;\,0]$, $\mathbb C_1 = [P_0\;0]$, $\mathbb C_2 = [N_3\;0]$,
$\mathbb D_1 = Q_0\mathcal D$ ($F_0, P_0, Q_0$: the matrices at $\mathbb Y = 0$, $Y_3 = 0$).

**LMI.** The bounded-real lemma on $(\mathbb A, \mathbb B, \mathbb C, \mathbb D)$ with the
linearizing change of variables of the region LMI, $\mathcal W = X\mathbb Y$
($X\mathbb A = X\mathbb A_1 - \mathcal W\mathbb A_2$, $X\mathbb B = X\mathbb B_1 - \mathcal W\mathbb B_2$):

$$\min\gamma\ \text{s.t.}\ X \succ 0,\
  \begin{bmatrix}\operatorname{He}(X\mathbb A) & X\mathbb B & \mathbb C^\top\\
  \star & -\gamma I & \mathbb D^\top\\ \star & \star & -\gamma I\end{bmatrix} \prec 0,\
  L_R\otimes X + M_R\otimes(X\mathbb A)^\top + M_R^\top\otimes X\mathbb A \prec 0,$$

linear in $(X, \mathcal W, Y_3, \gamma)$. The first LMI is equivalent to
$\|T_{d\to\hat z - z}\|_\infty < \gamma$ with $\mathbb A$ Hurwitz (bounded-real lemma,
e.g. Gahinet & Apkarian 1994); the second places the eigenvalues of $\mathbb A$ in the
region (Chilali & Gahinet 1996).

**Conservatism (stated, and measured in the report).** One certificate $X$ serves both
constraints — the multi-objective approach of Chilali & Gahinet (1996) / Scherer, Gahinet
& Chilali (1997): $\gamma$ is a guaranteed bound, but it may exceed the smallest $\|T\|_\infty$
attainable in the region, and the returned design's own $\|T\|_\infty$ may lie below
$\gamma$. Without a binding region constraint the bound is lossless: at the optimum $\gamma$
equals the design's $\|T\|_\infty$ (else the BRL certificate of that design would give
a smaller $\gamma$). Every design reports ``tightness = γ / ‖T‖∞``.

**Deviations from the literature.**
(1) $Z$ (hence $T$) is *not* optimised: $F = TA\Sigma^+[K;I] - Y_1F_3$ is quadratic in $Z$
($T$ and $K$ are both affine in it), so the joint problem is not an LMI; $Z$ is taken from the
region-only design (`fojax.design.design_functional_observer`, step 1/joint region LMI).
(2) The region LMI is imposed on the region shrunk by `TIGHTEN` (as for region-only
designs) with the full Lyapunov matrix $X$ (block-diagonal for PI observers, whose
$Y_2 = 0$ is then the linear constraint $\mathcal W_{21} = 0$).
(3) Unlike the region LMI, the BRL is not homogeneous in $X$: the normalisation
$X \succeq I$ of the region-only design would restrict $\gamma$, so only $X \succ 0$ is
asked; the channels are scaled by the region-only design's norm $\gamma_0$ so that the
scaled problem has $\gamma \approx 1$.
(4) **Uncertainty.** An affine uncertainty $E\dot x = (A + \delta\Delta A)x + \dots$,
$\Delta A = B_\delta C_\delta$, $|\delta| \le \bar\delta$, enters the error dynamics only as
the signal $w_\delta = \delta C_\delta x$ through $B_\delta$: the observer does not feed back
into the plant, so the LFT loop of the standard robust bound never closes and the bound is
the L2 gain of the channel $B_w = \bar\delta B_\delta$:
$\|\hat z - z\|_{L_2} \le \gamma\,\|[w;\,\nu;\,C_\delta x]\|_{L_2}$ (for a stable plant).
Pass it as a column block of `Bw` (`hinf_uncertainty_channel`).

**When γ cannot improve.** A plant mode on the imaginary axis can fix part of the error
response for every admissible observer: for $\dot x = 0$, $y = x + \nu$, $z = x$ the gain from
$\nu$ to $\hat z - z$ at $\omega = 0$ is 1 whatever the observer (a constant noise is
indistinguishable from a constant state). If the peak gain is attained there, no observer does
better than the region-only design: on §3.3.7 with the faults as constant states every design
has the same $\|T\|_\infty$, attained at $\omega = 0$ (`benchmarks/hinf_vs_region.py`, case
``faults``).

**Verification (float64, independent of the solver).** The design conditions, the region
and the region LMI (`fojax.design.verify`); the BRL re-evaluated at $(X, \gamma)$; and the
norm of the error system built from the *observer matrices* computed by SLICOT's
``AB13DD`` (slycot): $\gamma \ge \|T\|_\infty$ must hold, else `DesignVerificationError`.

??? cite "References"

    Chilali, M., Gahinet, P. (1996). H∞ design with pole placement constraints: an LMI
    approach. IEEE TAC 41(3), 358–367.
    Scherer, C., Gahinet, P., Chilali, M. (1997). Multiobjective output-feedback control
    via LMI optimization. IEEE TAC 42(7), 896–911.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .._errors import DesignVerificationError, InputError, ShapeError
from .._linalg import RANK_RTOL
from . import _lmi
from ._parameterization import observer_matrices, pieces


#: Strictness of the BRL and region LMIs in the scaled problem (γ ≈ 1 there).
HINF_MARGIN = 1e-7
#: Relative slack accepted between γ and the independently computed norm (AB13DD's
#: own tolerance is 1e-10; γ must be ≥ norm · (1 - NORM_RTOL)).
NORM_RTOL = 1e-6


@dataclasses.dataclass(frozen=True)
class HinfCertificate:
    r"""What an H∞ design guarantees, with the independent check.

    Attributes:
        gamma: the certified bound on $\|T_{d\to\hat z - z}\|_\infty$ (BRL re-checked in float64).
        norm: $\|T\|_\infty$ of the returned design's error system (SLICOT ``AB13DD``).
        peak_frequency: the frequency (rad/s) where the norm is attained.
        tightness: ``gamma / norm`` (≥ 1).
        region_only_norm: $\|T\|_\infty$ of the region-only design (same structure, same Z).
        Bw, Dv: the disturbance and noise channels (``(n, mw)``, ``(p, mv)``).
        brl_max_eig: largest eigenvalue of the BRL at ``(X, gamma)`` (``< 0``; in the scaled
            problem, channels divided by `region_only_norm`).
    """

    gamma: float
    norm: float
    peak_frequency: float
    tightness: float
    region_only_norm: float
    Bw: np.ndarray
    Dv: np.ndarray
    brl_max_eig: float

    def describe(self) -> str:
        return (f"H∞ bound γ = {self.gamma:.6g} ≥ ‖T‖∞ = {self.norm:.6g} (SLICOT AB13DD, peak at "
                f"ω = {self.peak_frequency:.4g} rad/s; tightness γ/‖T‖∞ = {self.tightness:.4f}); "
                f"region-only design: ‖T‖∞ = {self.region_only_norm:.6g}")

    def to_dict(self) -> dict:
        return {"gamma": self.gamma, "norm": self.norm, "peak_frequency": self.peak_frequency,
                "tightness": self.tightness, "region_only_norm": self.region_only_norm,
                "brl_max_eig": self.brl_max_eig, "Bw": np.asarray(self.Bw).tolist(),
                "Dv": np.asarray(self.Dv).tolist()}

    def checks(self, s, params, X) -> list:
        """The H∞ checks of a re-verification (`fojax.design.AbstractDesign.verify`), as
        ``(name, value, failure)`` for `fojax.design.verify`: the bounded-real LMI at
        ``(X, γ)`` in float64 (in the scaled problem of `design_hinf`, channels divided by
        `region_only_norm`) and ``γ ≥ ‖T‖∞`` by SLICOT's AB13DD on the observer of `params`."""
        A, B, C, D = error_system(s, base_mats(s, params), np.asarray(self.Bw), np.asarray(self.Dv))
        scale = self.region_only_norm if self.region_only_norm > 0 else 1.0
        M = brl_matrix(np.asarray(X), A, B / scale, C, D / scale, self.gamma / scale)
        top = float(np.linalg.eigvalsh(M).max())
        norm, freq = hinf_norm(A, B, C, D)
        out = [("H∞", self.describe(), None)]
        if not top < -1e-12 * max(1.0, float(np.abs(M).max())):
            out.append(("H∞ BRL max eig", top, f"the bounded-real LMI at (X, γ = {self.gamma:.8g}) has max "
                        f"eigenvalue {top:.3e} in float64: γ is not certified"))
        if not self.gamma >= norm * (1.0 - NORM_RTOL):
            out.append(("H∞ norm (AB13DD)", norm, f"the certified γ = {self.gamma:.8g} is below the norm of the "
                        f"error system computed by SLICOT AB13DD, {norm:.8g} (peak at ω = {freq:.4g} rad/s)"))
        return out

    @classmethod
    def from_dict(cls, m: dict) -> HinfCertificate:
        """Inverse of `to_dict` (`fojax.results.load_design`)."""
        return cls(**{k: float(m[k]) for k in ("gamma", "norm", "peak_frequency", "tightness",
                                                  "region_only_norm", "brl_max_eig")},
                   Bw=_matrix(m["Bw"]), Dv=_matrix(m["Dv"]))


def _matrix(rows: list) -> np.ndarray:
    """A JSON list of rows as an ``(r, c)`` array, also when ``c = 0``."""
    return np.asarray(rows, dtype=float).reshape(len(rows), len(rows[0]) if rows else 0)


def check_channels(n: int, p: int, Bw, Dv) -> tuple[np.ndarray, np.ndarray]:
    """``(Bw, Dv)`` as float arrays ``(n, mw)``, ``(p, mv)``; `InputError` naming the
    channel for a bad shape or value. ``None`` is an empty channel; at least one must be given."""
    def one(name, M, rows, what):
        if M is None:
            return np.zeros((rows, 0))
        M = np.asarray(M, dtype=float)
        if M.ndim == 1 and M.shape[0] == rows:
            M = M[:, None]
        if M.ndim != 2 or M.shape[0] != rows:
            raise ShapeError(name, (rows, "m"), tuple(M.shape),
                             f"{name} maps the {what} into the {'state equation' if name == 'Bw' else 'output'}: "
                             f"it needs {rows} rows ({'n' if name == 'Bw' else 'p'} = {rows}).")
        if not np.all(np.isfinite(M)):
            raise InputError(f"{name} has non-finite entries; give a finite matrix.")
        return M

    Bw = one("Bw", Bw, n, "disturbance w")
    Dv = one("Dv", Dv, p, "measurement noise")
    if Bw.shape[1] + Dv.shape[1] == 0 or not (np.any(Bw) or np.any(Dv)):
        raise InputError("objective='hinf' needs a disturbance channel Bw (n x mw) or a measurement-"
                         "noise channel Dv (p x mv) with a nonzero entry; got neither. "
                         "Give e.g. Dv=np.eye(p) for noise on every output.")
    return Bw, Dv


def hinf_uncertainty_channel(dA, delta_max: float, tol: float = 1e-12) -> tuple[np.ndarray, np.ndarray]:
    r"""``(Bδ, Cδ)`` with ``δ̄·ΔA = Bδ Cδ`` (SVD, rank-revealing): ``Bδ`` is the `Bw` block
    of an uncertainty ``|δ| ≤ δ̄`` (module docstring, deviation 4)."""
    dA = np.asarray(dA, dtype=float)
    U, s, Vt = np.linalg.svd(dA)
    r = int(np.sum(s > tol * max(1.0, s[0] if s.size else 0.0)))
    return float(delta_max) * U[:, :r] * np.sqrt(s[:r]), np.sqrt(s[:r])[:, None] * Vt[:r]


def error_system(s, mats, Bw, Dv):
    r"""$(\mathbb A, \mathbb B, \mathbb C, \mathbb D)$ of $d = [w;\nu] \mapsto \hat z - z$
    from the observer matrices (rule 0), host float64."""
    N, J, S, G = (np.asarray(x)[0] for x in (mats.N, mats.J, mats.S, mats.G))
    F, M, P, Q = (np.asarray(x)[0] for x in (mats.F, mats.M, mats.P, mats.Q))
    T = np.asarray(mats.T)
    Dcal = _dcal(s, Bw, Dv)
    Bbar = np.hstack([Bw, np.zeros((Bw.shape[0], Dv.shape[1]))])
    A = np.block([[N, J], [S, G]])
    B = np.vstack([F @ Dcal - T @ Bbar, M @ Dcal])
    C = np.hstack([P, np.zeros((P.shape[0], G.shape[0]))])
    D = Q @ Dcal
    return A, B, C, D


def _dcal(s, Bw, Dv):
    Ep = np.asarray(s.Eperp)
    r1, p = Ep.shape[0], np.asarray(s.C).shape[0]
    return np.block([[Ep @ Bw, np.zeros((r1, Dv.shape[1]))], [np.zeros((p, Bw.shape[1])), Dv]])


def hinf_norm(A, B, C, D) -> tuple[float, float]:
    """``(‖T‖∞, peak frequency)`` of a standard state-space system by SLICOT ``AB13DD``
    (slycot), the independent norm every H∞ design is checked against."""
    import slycot

    n, m, p = A.shape[0], B.shape[1], C.shape[0]
    if n == 0:
        return float(np.linalg.norm(D, 2)) if D.size else 0.0, 0.0
    g, f = slycot.ab13dd("C", "I", "S", "D", n, m, p, A, np.eye(n), B, C, D)
    return float(g), float(f)


def brl_matrix(X, A, B, C, D, gamma):
    """The bounded-real-lemma matrix at ``(X, γ)`` (float64, symmetrised)."""
    m, p = B.shape[1], C.shape[0]
    XA, XB = X @ A, X @ B
    out = np.block([
        [XA + XA.T, XB, C.T],
        [XB.T, -gamma * np.eye(m), D.T],
        [C, D, -gamma * np.eye(p)],
    ])
    return 0.5 * (out + out.T)


def solve_hinf(s, region, *, kind, Z, Bw, Dv, scale, solver):
    """The LMI of the module docstring with `Z` fixed; channels divided by `scale`.

    Returns ``(X, 𝕐, Y3, γ_scaled, info)``."""
    import cvxpy as cp

    q0, q1, c = s.q0, s.q1, s.q0 + s.nw
    d = q0 + q1
    mats0 = observer_matrices(s, Z, *(np.zeros(shape) for k, shape in s.param_shapes().items() if k != "Z"), xp=np)
    pc = pieces(s, xp=np)
    N3, F3 = np.asarray(pc.N3), np.asarray(mats0.F3)
    N0, F0 = np.asarray(mats0.N)[0], np.asarray(mats0.F)[0]
    P0, Q0 = np.asarray(mats0.P)[0], np.asarray(mats0.Q)[0]
    T = np.asarray(mats0.T)
    Dcal = _dcal(s, Bw, Dv) / scale
    Bbar = np.hstack([Bw, np.zeros((Bw.shape[0], Dv.shape[1]))]) / scale
    nd, q = Dcal.shape[1], P0.shape[0]
    A1 = np.block([[N0, np.zeros((q0, q1))], [np.zeros((q1, d))]])
    A2 = np.block([[N3, np.zeros((c, q1))], [np.zeros((q1, q0)), -np.eye(q1)]])
    B1 = np.vstack([F0 @ Dcal - T @ Bbar, np.zeros((q1, nd))])
    B2 = np.vstack([F3 @ Dcal, np.zeros((q1, nd))])
    C1 = np.hstack([P0, np.zeros((q, q1))])
    C2 = np.hstack([N3, np.zeros((c, q1))])
    D1 = Q0 @ Dcal
    D2 = F3 @ Dcal

    if kind == "PI" and q1:
        X1 = cp.Variable((q0, q0), symmetric=True)
        X2 = cp.Variable((q1, q1), symmetric=True)
        X = cp.bmat([[X1, np.zeros((q0, q1))], [np.zeros((q1, q0)), X2]])
    else:
        X = cp.Variable((d, d), symmetric=True)
    Wv = cp.Variable((d, c + q1))
    Y3 = cp.Variable((q, c))
    gam = cp.Variable()
    XA = X @ A1 - Wv @ A2
    XB = X @ B1 - Wv @ B2
    Cm = C1 - Y3 @ C2
    Dm = D1 - Y3 @ D2
    brl = cp.bmat([
        [XA + XA.T, XB, Cm.T],
        [XB.T, -gam * np.eye(nd), Dm.T],
        [Cm, Dm, -gam * np.eye(q)],
    ])
    eps = HINF_MARGIN
    cons = [X >> eps * np.eye(d), _lmi.sym(brl) << -eps * np.eye(d + nd + q)]
    Mx = _lmi.region_lmi(region, X, XA)
    cons.append(Mx << -eps * np.eye(Mx.shape[0]))
    if kind == "PI" and q1:
        cons.append(Wv[q0:, :c] == 0)
    # γ, plus a small gain penalty: without measurement noise the infimum of γ may be
    # approached only with unbounded gains (then no solver reaches "optimal").
    obj = cp.Minimize(gam + 1e-6 * (cp.norm(Wv, "fro") + cp.norm(Y3, "fro") + cp.trace(X)))
    name = f"{kind} observer, H∞ LMI (bounded-real lemma + region, 𝒲 = X 𝕐, Z fixed)"
    hint = ("No observer with this Z places the error eigenvalues in the region with a finite "
            "L2 gain: enlarge the region, or check the channels Bw/Dv (their scale).")
    info = _lmi.solve(cp.Problem(obj, cons), name, hint=hint, solver=solver)
    Xv = np.asarray(X.value, dtype=float)
    Xv = 0.5 * (Xv + Xv.T)
    Yv = np.linalg.solve(Xv, _lmi.value(Wv))
    # components of 𝕐 (Y3) that change neither 𝔸, 𝔹 (ℂ, 𝔻) only enlarge the gains: drop them
    AB = np.hstack([A2, B2])
    Yv = Yv @ _range_projector(AB)
    CD = np.hstack([C2, D2])
    Y3v = _lmi.value(Y3) @ _range_projector(CD)
    if kind == "PI" and q1:
        Yv[q0:, :c] = 0.0
    return Xv, Yv, Y3v, float(gam.value), info


def _range_projector(M):
    """Orthogonal projector onto the column space of `M`, its rank decided by fojax's one
    rule (`RANK_RTOL`): a pseudo-inverse keeping round-off singular values (1e-15) would
    make the projector wrong by O(1) in those directions."""
    U, sv, _ = np.linalg.svd(M, full_matrices=False)
    r = int(np.sum(sv > RANK_RTOL * (sv[0] if sv.size else 0.0)))
    return U[:, :r] @ U[:, :r].T


def certify_gamma(X, A, B, C, D, gamma) -> tuple[float, float]:
    """The smallest ``γ' ∈ {γ, γ(1+1e-9·10^k)}`` at which the BRL holds at `X` in float64
    (strictly, relative to its scale), and the BRL's max eigenvalue there. Raises
    `DesignVerificationError` if even ``1.01 γ`` fails."""
    for bump in (0.0, 1e-9, 1e-8, 1e-7, 1e-6, 1e-5, 1e-4, 1e-3, 1e-2):
        g = gamma * (1.0 + bump)
        M = brl_matrix(X, A, B, C, D, g)
        top = float(np.linalg.eigvalsh(M).max())
        if top < -1e-12 * max(1.0, float(np.abs(M).max())):
            return g, top
    raise DesignVerificationError(
        f"the bounded-real LMI re-checked in float64 at the certificate X fails for γ up to "
        f"{1.01 * gamma:.6g} (max eigenvalue {top:.3e}): the solver's γ is not certified")


def design_hinf(s, region, *, kind, margin, solver, Bw, Dv, tighten, method="lmi"):
    """`design_functional_observer(..., objective="hinf")` once the structure is built."""
    from ._functional import (
        _design_from_structure,
        build_observer,
        FunctionalObserverDesign,
        split_Y,
        verify_structure_design,
    )

    if s.num_rules != 1:
        raise InputError("objective='hinf' is for linear (single-rule) plants.")
    Bw, Dv = check_channels(s.n, s.p, Bw, Dv)
    base = _design_from_structure(s, region, kind=kind, margin=margin, solver=solver, tighten=tighten,
                                  method=method)
    Z = base.params["Z"]
    g0, _ = hinf_norm(*error_system(s, base_mats(s, base.params), Bw, Dv))
    scale = g0 if g0 > 0 else 1.0
    X, Y, Y3, gs, info = solve_hinf(s, region.tightened(tighten), kind=kind, Z=Z, Bw=Bw, Dv=Dv,
                                    scale=scale, solver=solver)
    c = s.q0 + s.nw
    blocks = split_Y(Y, s.q0, c)
    params = {"Z": Z, "Y1": blocks["Y1"], "Y2": blocks["Y2"], "Y3": Y3, "J": blocks["J"], "G": blocks["G"]}
    route = _lmi.describe_route(info, "min-γ")
    mats, report = verify_structure_design(s, params, region, X, extra={"LMI route": route})
    A, B, C, D = error_system(s, mats, Bw, Dv)
    gamma, brl_top = certify_gamma(X, A, B / scale, C, D / scale, gs)
    gamma *= scale
    norm, freq = hinf_norm(A, B, C, D)
    if not gamma >= norm * (1.0 - NORM_RTOL):
        raise DesignVerificationError(
            f"H∞ verification failed: the certified γ = {gamma:.8g} is below the norm of the "
            f"error system computed by SLICOT AB13DD, {norm:.8g} (peak at ω = {freq:.4g} rad/s)", report)
    cert = HinfCertificate(gamma=gamma, norm=norm, peak_frequency=freq,
                           tightness=gamma / norm if norm > 0 else float("inf"),
                           region_only_norm=g0, Bw=Bw, Dv=Dv, brl_max_eig=brl_top)
    report = dataclasses.replace(report, extra={**report.extra, "H∞": cert.describe()})
    return FunctionalObserverDesign(
        observer=build_observer(s, mats, kind=kind), kind=kind, region=region, structure=s,
        params={k: np.asarray(v) for k, v in params.items()}, T=np.asarray(mats.T),
        K=np.asarray(mats.K), Z_eff=np.asarray(mats.Z_eff), X=X, report=report,
        solver={"lmi": info, "region_only": base.solver}, hinf=cert,
    )


def base_mats(s, params):
    return observer_matrices(s, **{k: np.asarray(v) for k, v in params.items()}, xp=np)

