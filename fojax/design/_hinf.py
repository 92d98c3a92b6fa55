r"""H∞ and H2 functional-observer design: a guaranteed L2-gain or H2-norm bound inside the region LMI.

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

**H2 (``objective="h2"``; derived here).** $\|T\|_2$ is finite only without feedthrough,
so $\mathbb D = \mathbb D_1 - Y_3\mathbb D_2 = 0$ ($\mathbb D_2 = F_3\mathcal D$) is imposed
*exactly*: its solutions are $Y_3 = \mathbb D_1\mathbb D_2^+ + V\Pi_n$ ($\Pi_n$ the projector
onto the orthogonal complement of the columns of $\mathbb D_2$, rank by fojax's one rule),
$V$ free. If $\mathbb D_1\mathbb D_2^+\mathbb D_2 \ne \mathbb D_1$ no observer of this structure
(this $Z$, $q_0$) avoids the feedthrough, and the design is refused with `InputError`
before any LMI (typically: noise on outputs the minimal-order observer passes straight to
$\hat z$; a larger $q_0$ can remove it, on §3.3.7 $q_0 = 4$ does). Then, with the same
$\mathcal W = X\mathbb Y$,

$$\min\operatorname{tr}W\ \text{s.t.}\ X \succ 0,\
  \begin{bmatrix}\operatorname{He}(X\mathbb A) & \mathbb C^\top\\ \mathbb C & -I\end{bmatrix} \prec 0,\
  \begin{bmatrix}W & (X\mathbb B)^\top\\ X\mathbb B & X\end{bmatrix} \succ 0,\
  \text{region LMI},$$

linear in $(X, \mathcal W, V, W)$. Why it bounds the norm: the first LMI is (Schur)
$\mathbb A^\top X + X\mathbb A + \mathbb C^\top\mathbb C \prec 0$, so $\mathbb A$ is Hurwitz and
$X - L_o$ ($L_o$ the observability Gramian, $\mathbb A^\top L_o + L_o\mathbb A + \mathbb C^\top
\mathbb C = 0$) satisfies a strict Lyapunov inequality, hence $X \succ L_o$; the second is
$W \succ \mathbb B^\top X\mathbb B$. So $\|T\|_2^2 = \operatorname{tr}(\mathbb B^\top L_o\mathbb B)
\le \operatorname{tr}(\mathbb B^\top X\mathbb B) < \operatorname{tr}W = \nu^2$. This is the
observability-Gramian ("filtering") form of the H2 LMI, chosen because $X\mathbb B$ and
$\mathbb C$ are affine in the unknowns, whereas the controllability form needs $\mathbb B$
multiplied by the inverse certificate. The returned $\nu$ is re-certified in float64 at the
design's own matrices: $\nu = \sqrt{\operatorname{tr}(\mathbb B^\top X\mathbb B)}$ once the
Lyapunov inequality holds at $X$ (`certify_nu`); the design's $Q\mathcal D$ must be round-off
(``H2Certificate.feedthrough`` ≤ `FEEDTHROUGH_RTOL`; a round-off feedthrough is treated as
zero), and $\nu \ge \|T\|_2$ computed by SciPy's ``solve_continuous_lyapunov`` on the error
system (`h2_norm`) is checked, else `DesignVerificationError`. The region-only design usually
has a feedthrough ($Y_3 = 0$), so its H2 norm (``region_only_norm``) is often ``inf``.

**Conservatism of the design, not of the bound.** One certificate $X$ serves both
constraints of the design LMI — the multi-objective approach of Chilali & Gahinet (1996) /
Scherer, Gahinet & Chilali (1997): its $\gamma$ may exceed the smallest $\|T\|_\infty$
attainable in the region and the returned observer's own $\|T\|_\infty$. The returned bound
is therefore certified for the returned observer *alone*, with no region constraint: the
bounded-real Riccati equation with the observer fixed (`fojax.design._certify`: `observer_gamma`; H2: the
observability Gramian, `observer_nu`) gives a certificate within a relative gap of
$10^{-9}$–$10^{-2}$ (the first that verifies) of the AB13DD norm, and the smaller of that
bound and the design LMI's is returned. Every design reports ``tightness = γ / ‖T‖∞``
(H2: ``ν / ‖T‖₂``); `benchmarks/gamma_tightness.py` measures it on a random sweep.
**Solver stops.** The design LMI adds a small gain penalty to γ (`GAIN_PENALTIES`); when
the solvers stop short of "optimal" it is retried with a larger penalty, and a solver that
stops short on every penalty raises `fojax.errors.SolverStoppedShortError` (never
`fojax.errors.LMIInfeasibleError`, which needs a certificate of infeasibility).

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
and the region LMI (`fojax.design.verify`); the BRL re-evaluated at the certificate of
$\gamma$ (``HinfCertificate.certificate_X``); and the
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

from .._errors import DesignVerificationError, InputError, ShapeError, SolverStoppedShortError
from .._linalg import RANK_RTOL
from . import _ladder, _lmi
from ._certify import (
    brl_matrix,
    certify_gamma,
    certify_nu,
    h2_norm,
    hinf_norm,
    observer_gamma,
    observer_nu,
    riccati_gamma,
)
from ._parameterization import observer_matrices, pieces, split_Y


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
        brl_max_eig: largest eigenvalue of the BRL at ``(certificate_X, gamma)`` (``< 0``).
        certificate_X: the BRL certificate of ``gamma`` for the returned observer alone
            (`observer_gamma`), or the design LMI's own $X$ when that certifies a smaller
            bound. ``None`` only for certificates saved without it: their BRL is checked at
            the design's $X$ with the channels divided by `region_only_norm`.
    """

    gamma: float
    norm: float
    peak_frequency: float
    tightness: float
    region_only_norm: float
    Bw: np.ndarray
    Dv: np.ndarray
    brl_max_eig: float
    certificate_X: np.ndarray | None = None

    def describe(self) -> str:
        return (f"H∞ bound γ = {self.gamma:.6g} ≥ ‖T‖∞ = {self.norm:.6g} (SLICOT AB13DD, peak at "
                f"ω = {self.peak_frequency:.4g} rad/s; tightness γ/‖T‖∞ = {self.tightness:.4f}); "
                f"region-only design: ‖T‖∞ = {self.region_only_norm:.6g}")

    def checks(self, s, params, X) -> list:
        """The H∞ checks of a re-verification (`fojax.design.AbstractDesign.verify`), as
        ``(name, value, failure)`` for `fojax.design.verify`: the bounded-real LMI at
        ``(X, γ)`` in float64 (in the scaled problem of `design_hinf`, channels divided by
        `region_only_norm`) and ``γ ≥ ‖T‖∞`` by SLICOT's AB13DD on the observer of `params`."""
        A, B, C, D = error_system(s, base_mats(s, params), np.asarray(self.Bw), np.asarray(self.Dv))
        if self.certificate_X is not None:
            M = brl_matrix(np.asarray(self.certificate_X), A, B, C, D, self.gamma)
        else:  # a certificate saved without its own X: the design's X, in the scaled problem
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


@dataclasses.dataclass(frozen=True)
class H2Certificate:
    r"""What an H2 design guarantees, with the independent check.

    Attributes:
        nu: the certified bound $\nu \ge \|T_{d\to\hat z - z}\|_2$ (Lyapunov inequality re-checked
            in float64 at $X$; $\nu = \sqrt{\operatorname{tr}(\mathbb B^\top X\mathbb B)}$).
        norm: $\|T\|_2$ of the returned design's error system (SciPy ``solve_continuous_lyapunov``).
        tightness: ``nu / norm`` (≥ 1).
        region_only_norm: $\|T\|_2$ of the region-only design (same structure, same Z); ``inf``
            when that design has a feedthrough from $d$ to $\hat z - z$.
        feedthrough: $\|\mathbb D\|_2 / (\|Q\|_2\|\mathcal D\|_2)$ of the design (round-off).
        Bw, Dv: the disturbance and noise channels (``(n, mw)``, ``(p, mv)``).
        lyapunov_max_eig: largest eigenvalue of the Lyapunov LMI at $X$ (``< 0``).
    """

    nu: float
    norm: float
    tightness: float
    region_only_norm: float
    feedthrough: float
    Bw: np.ndarray
    Dv: np.ndarray
    lyapunov_max_eig: float

    def describe(self) -> str:
        return (f"H2 bound ν = {self.nu:.6g} ≥ ‖T‖₂ = {self.norm:.6g} (SciPy Lyapunov; tightness "
                f"ν/‖T‖₂ = {self.tightness:.4f}); region-only design: ‖T‖₂ = {self.region_only_norm:.6g}")


def check_channels(n: int, p: int, Bw, Dv, objective: str = "hinf") -> tuple[np.ndarray, np.ndarray]:
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
        raise InputError(f"objective={objective!r} needs a disturbance channel Bw (n x mw) or a measurement-"
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


def error_system(s, mats, Bw, Dv, xp=np):
    r"""$(\mathbb A, \mathbb B, \mathbb C, \mathbb D)$ of $d = [w;\nu] \mapsto \hat z - z$
    from the observer matrices (rule 0): host float64 (``xp=numpy``), or traceable
    (``xp=jax.numpy``: the robustness terms of `fojax.tuning.tune` use the same formulas)."""
    N, J, S, G = (xp.asarray(x)[0] for x in (mats.N, mats.J, mats.S, mats.G))
    F, M, P, Q = (xp.asarray(x)[0] for x in (mats.F, mats.M, mats.P, mats.Q))
    T = xp.asarray(mats.T)
    Bw, Dv = xp.asarray(Bw), xp.asarray(Dv)
    Dcal = _dcal(s, Bw, Dv, xp)
    Bbar = xp.concatenate([Bw, xp.zeros((Bw.shape[0], Dv.shape[1]))], axis=1)
    A = xp.concatenate([xp.concatenate([N, J], axis=1), xp.concatenate([S, G], axis=1)], axis=0)
    B = xp.concatenate([F @ Dcal - T @ Bbar, M @ Dcal], axis=0)
    C = xp.concatenate([P, xp.zeros((P.shape[0], G.shape[0]))], axis=1)
    D = Q @ Dcal
    return A, B, C, D


def _dcal(s, Bw, Dv, xp=np):
    r"""$\mathcal D = [E^\perp B_w, 0; 0, D_v]$; on the host $E^\perp B_w$ with its round-off
    removed by the analysis's rank rule (`fojax.analysis.algebraic_channel`), so that a
    disturbance on the differential equations only has exactly no feedthrough whatever
    coordinates the equations are written in. Traced (``xp=jax.numpy``): the product."""
    Ep = xp.asarray(s.Eperp)
    r1, p = Ep.shape[0], s.C.shape[0]
    EpBw = Ep @ Bw
    if xp is np and EpBw.size:
        from ..analysis import algebraic_channel

        EpBw = algebraic_channel(np.asarray(s.E), Bw, Eperp=Ep)
    top = xp.concatenate([EpBw, xp.zeros((r1, Dv.shape[1]))], axis=1)
    bot = xp.concatenate([xp.zeros((p, Bw.shape[1])), Dv], axis=1)
    return xp.concatenate([top, bot], axis=0)


@dataclasses.dataclass(frozen=True)
class _AffinePieces:
    """The affine error system of the module docstring (channels divided by ``scale``)."""

    A1: np.ndarray
    A2: np.ndarray
    B1: np.ndarray
    B2: np.ndarray
    C1: np.ndarray
    C2: np.ndarray
    D1: np.ndarray
    D2: np.ndarray


def affine_pieces(s, Z, Bw, Dv, scale) -> _AffinePieces:
    r"""$\mathbb A_{1,2}, \mathbb B_{1,2}, \mathbb C_{1,2}, \mathbb D_{1,2}$ at fixed `Z`
    ($\mathbb D_2 = F_3\mathcal D$), host float64, channels divided by `scale`."""
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
    return _AffinePieces(
        A1=np.block([[N0, np.zeros((q0, q1))], [np.zeros((q1, d))]]),
        A2=np.block([[N3, np.zeros((c, q1))], [np.zeros((q1, q0)), -np.eye(q1)]]),
        B1=np.vstack([F0 @ Dcal - T @ Bbar, np.zeros((q1, nd))]),
        B2=np.vstack([F3 @ Dcal, np.zeros((q1, nd))]),
        C1=np.hstack([P0, np.zeros((q, q1))]),
        C2=np.hstack([N3, np.zeros((c, q1))]),
        D1=Q0 @ Dcal,
        D2=F3 @ Dcal,
    )


def feedthrough_free_Y3(ap: _AffinePieces) -> tuple[np.ndarray, np.ndarray, float]:
    r"""``(Y3p, Πn, residual)``: every $Y_3$ with $\mathbb D = \mathbb D_1 - Y_3\mathbb D_2 = 0$ is
    $Y_{3p} + V\Pi_n$ ($Y_{3p} = \mathbb D_1\mathbb D_2^+$, $\Pi_n$ the projector onto the
    orthogonal complement of the columns of $\mathbb D_2$), if ``residual`` (the relative
    $\|\mathbb D_1 - Y_{3p}\mathbb D_2\|$) is round-off; rank by fojax's one rule."""
    D1, D2 = ap.D1, ap.D2
    U, sv, Vt = np.linalg.svd(D2, full_matrices=False)
    r = int(np.sum(sv > RANK_RTOL * (sv[0] if sv.size else 0.0)))
    pinv = (Vt[:r].T / sv[:r]) @ U[:, :r].T
    Y3p = D1 @ pinv
    Pn = np.eye(D2.shape[0]) - U[:, :r] @ U[:, :r].T
    scale = max(float(np.linalg.norm(D1, 2)) if D1.size else 0.0, 1e-300)
    res = float(np.linalg.norm(D1 - Y3p @ D2, 2)) / scale if D1.size and np.any(D1) else 0.0
    return Y3p, Pn, res


#: Relative residual of $\mathbb D_1 - Y_3\mathbb D_2$ below which the feedthrough of an
#: ``objective="h2"`` design counts as removable (round-off).
FEEDTHROUGH_RTOL = 1e-9


#: Weights of the gain penalty added to the bound in `solve_performance`, tried in turn when
#: the solvers stop short: without measurement noise the infimum of γ may be approached only
#: with unbounded gains, where no solver reaches "optimal"; a larger weight keeps the gains
#: bounded (the returned observer's own bound is certified afterwards, `observer_gamma`).
GAIN_PENALTIES = (1e-6, 1e-4, 1e-2)


def solve_performance(s, region, *, kind, Z, Bw, Dv, scale, solver, objective="hinf", penalty=GAIN_PENALTIES[0]):
    r"""The LMI of the module docstring with `Z` fixed; channels divided by `scale`:
    ``objective="hinf"`` (bounded-real lemma, minimise γ) or ``"h2"`` (Lyapunov inequality
    with $\mathbb D = 0$, minimise $\operatorname{tr}W = \nu^2$), plus `penalty` times the
    gains' and the certificate's size.

    Returns ``(X, 𝕐, Y3, γ or ν (scaled), info)``."""
    import cvxpy as cp

    q0, q1, c = s.q0, s.q1, s.q0 + s.nw
    d = q0 + q1
    ap = affine_pieces(s, Z, Bw, Dv, scale)
    q, nd = ap.D1.shape

    if kind == "PI" and q1:
        X1 = cp.Variable((q0, q0), symmetric=True)
        X2 = cp.Variable((q1, q1), symmetric=True)
        X = cp.bmat([[X1, np.zeros((q0, q1))], [np.zeros((q1, q0)), X2]])
    else:
        X = cp.Variable((d, d), symmetric=True)
    Wv = cp.Variable((d, c + q1))
    XA = X @ ap.A1 - Wv @ ap.A2
    XB = X @ ap.B1 - Wv @ ap.B2
    eps = HINF_MARGIN
    if objective == "hinf":
        Y3 = cp.Variable((q, c))
        Y3expr = Y3
        gam = cp.Variable()
        Cm = ap.C1 - Y3 @ ap.C2
        Dm = ap.D1 - Y3 @ ap.D2
        perf = cp.bmat([
            [XA + XA.T, XB, Cm.T],
            [XB.T, -gam * np.eye(nd), Dm.T],
            [Cm, Dm, -gam * np.eye(q)],
        ])
        cons = [X >> eps * np.eye(d), _lmi.sym(perf) << -eps * np.eye(d + nd + q)]
        target = gam
        name = f"{kind} observer, H∞ LMI (bounded-real lemma + region, 𝒲 = X 𝕐, Z fixed)"
        hint = ("No observer with this Z places the error eigenvalues in the region with a finite "
                "L2 gain: enlarge the region, or check the channels Bw/Dv (their scale).")
    else:
        Y3p, Pn, _ = feedthrough_free_Y3(ap)
        V = cp.Variable((q, c))
        Y3 = V
        Y3expr = Y3p + V @ Pn  # 𝔻 = 0 for every V
        W = cp.Variable((nd, nd), symmetric=True)
        Cm = ap.C1 - Y3expr @ ap.C2
        lyap = cp.bmat([[XA + XA.T, Cm.T], [Cm, -np.eye(q)]])
        gram = cp.bmat([[W, XB.T], [XB, X]])
        cons = [X >> eps * np.eye(d), _lmi.sym(lyap) << -eps * np.eye(d + q),
                _lmi.sym(gram) >> eps * np.eye(nd + d)]
        target = cp.trace(W)
        name = f"{kind} observer, H2 LMI (Lyapunov inequality + trace bound + region, 𝒲 = X 𝕐, Z fixed)"
        hint = ("No observer with this Z places the error eigenvalues in the region with a finite "
                "H2 norm: enlarge the region, or check the channels Bw/Dv (their scale).")
    Mx = _lmi.region_lmi(region, X, XA)
    cons.append(Mx << -eps * np.eye(Mx.shape[0]))
    if kind == "PI" and q1:
        cons.append(Wv[q0:, :c] == 0)
    # the bound, plus a small gain penalty (`GAIN_PENALTIES`)
    obj = cp.Minimize(target + penalty * (cp.norm(Wv, "fro") + cp.norm(Y3, "fro") + cp.trace(X)))
    info = _lmi.solve(cp.Problem(obj, cons), name, hint=hint, solver=solver)
    Xv = np.asarray(X.value, dtype=float)
    Xv = 0.5 * (Xv + Xv.T)
    Yv = np.linalg.solve(Xv, _lmi.value(Wv))
    # components of 𝕐 (Y3) that change neither 𝔸, 𝔹 (ℂ, 𝔻) only enlarge the gains: drop them
    Yv = Yv @ _range_projector(np.hstack([ap.A2, ap.B2]))
    Y3v = _lmi.value(Y3expr)
    Y3v = Y3v @ _range_projector(np.hstack([ap.C2, ap.D2]))
    if kind == "PI" and q1:
        Yv[q0:, :c] = 0.0
    bound = float(target.value) if objective == "hinf" else float(np.sqrt(max(float(target.value), 0.0)))
    return Xv, Yv, Y3v, bound, info


def _range_projector(M):
    """Orthogonal projector onto the column space of `M`, its rank decided by fojax's one
    rule (`RANK_RTOL`): a pseudo-inverse keeping round-off singular values (1e-15) would
    make the projector wrong by O(1) in those directions."""
    U, sv, _ = np.linalg.svd(M, full_matrices=False)
    r = int(np.sum(sv > RANK_RTOL * (sv[0] if sv.size else 0.0)))
    return U[:, :r] @ U[:, :r].T


def _feedthrough(mats, Y3, Dcal) -> float:
    r"""$\|\mathbb D\|_2 = \|Q\mathcal D\|_2$ relative to the norms of its terms,
    $(\|Q_0\|_2 + \|Y_3\|_2\|F_3\|_2)\|\mathcal D\|_2$ ($Q = Q_0 - Y_3F_3$); 0 if it is zero."""
    Q, F3, Y3 = np.asarray(mats.Q)[0], np.asarray(mats.F3), np.asarray(Y3)
    D = Q @ Dcal
    if D.size == 0 or not np.any(D):
        return 0.0
    terms = np.linalg.norm(Q + Y3 @ F3, 2) + np.linalg.norm(Y3, 2) * np.linalg.norm(F3, 2)
    return float(np.linalg.norm(D, 2)) / max(float(terms * np.linalg.norm(Dcal, 2)), 1e-300)


def design_hinf(s, region, *, base, verify, kind, solver, Bw, Dv, tighten, objective="hinf") -> dict:
    """`design_functional_observer(..., objective="hinf" | "h2")` once the structure and the
    region-only design `base` are built: the fields of the `FunctionalObserverDesign`
    (``params``, ``X``, ``report``, ``solver``, ``hinf``/``h2``) and ``mats`` (the observer
    matrices), which `fojax.design._functional` assembles. `verify` is its
    ``verify_structure_design`` (``(s, params, region, X, extra=) -> (mats, report)``)."""
    if s.num_rules != 1:
        raise InputError(f"objective={objective!r} is for linear (single-rule) plants.")
    Bw, Dv = check_channels(s.n, s.p, Bw, Dv, objective=objective)
    Z = base.params["Z"]
    g0, _ = hinf_norm(*error_system(s, base_mats(s, base.params), Bw, Dv))
    scale = g0 if g0 > 0 else 1.0
    if objective == "h2":
        _, _, res = feedthrough_free_Y3(affine_pieces(s, Z, Bw, Dv, scale))
        if res > FEEDTHROUGH_RTOL:
            raise InputError(
                f"objective='h2' needs ẑ − z to have no direct feedthrough from d = [w; ν] (else its H2 "
                f"norm is infinite), but every observer of this structure passes part of the channels "
                f"straight into the estimate: min over Y3 of ‖Q 𝒟‖ is {res:.3g} relative to ‖Q0 𝒟‖ (𝒟 = "
                f"[E⊥Bw, 0; 0, Dv]: noise Dv, or disturbance Bw on the algebraic rows). Use objective='hinf' "
                f"(it allows feedthrough), or remove that part of Bw/Dv, or choose R (q0) so that the "
                f"observer state carries z.")
    rungs = [(w, (lambda w=w: solve_performance(s, region.tightened(tighten), kind=kind, Z=Z, Bw=Bw, Dv=Dv,
                                                scale=scale, solver=solver, objective=objective, penalty=w)))
             for w in GAIN_PENALTIES]
    try:  # an infeasible LMI stays infeasible with another penalty: only a stop short climbs
        w, (X, Y, Y3, gs, info), refused = _ladder.climb(rungs, refusals=(SolverStoppedShortError,))
    except _ladder.Refused as every:
        last = every.refused[-1][1]
        raise SolverStoppedShortError(
            last.problem, "; ".join(f"{e.status} (gain penalty {lb:g})" for lb, e in every.refused),
            {**last.info}) from None
    info = {**info, "gain_penalty": w}
    if refused:
        info["refused_penalties"] = [{"gain_penalty": lb, "status": e.status} for lb, e in refused]
    c = s.q0 + s.nw
    blocks = split_Y(Y, s.q0, c)
    params = {"Z": Z, "Y1": blocks["Y1"], "Y2": blocks["Y2"], "Y3": Y3, "J": blocks["J"], "G": blocks["G"]}
    route = _lmi.describe_route(info, "min-γ" if objective == "hinf" else "min-tr(W)")
    if refused:
        route += f"; gain penalty {w:g} after " + ", ".join(f"{e.status} at {lb:g}" for lb, e in refused)
    mats, report = verify(s, params, region, X, extra={"LMI route": route})
    A, B, C, D = error_system(s, mats, Bw, Dv)
    if objective == "h2":
        Dcal = _dcal(s, Bw, Dv)
        ft = _feedthrough(mats, Y3, Dcal)
        if ft > FEEDTHROUGH_RTOL:
            raise DesignVerificationError(
                f"H2 verification failed: the designed observer's feedthrough ‖Q 𝒟‖ is {ft:.3e} relative "
                f"to ‖Q‖‖𝒟‖ (tolerance {FEEDTHROUGH_RTOL:g}): its H2 norm is infinite", report)
        nu, lyap_top = certify_nu(X, A, B / scale, C)
        nu *= scale
        norm = h2_norm(A, B, C)
        own = observer_nu(A, B, C, norm)  # the returned observer alone (tighter than the shared X)
        if own is not None and own[0] < nu:
            nu, _, lyap_top = own
        if not nu >= norm * (1.0 - NORM_RTOL):
            raise DesignVerificationError(
                f"H2 verification failed: the certified ν = {nu:.8g} is below the H2 norm of the error "
                f"system computed by SciPy's Lyapunov solver, {norm:.8g}", report)
        mb = base_mats(s, base.params)
        Ab, Bb, Cb, _ = error_system(s, mb, Bw, Dv)
        n0 = h2_norm(Ab, Bb, Cb) if _feedthrough(mb, base.params["Y3"], Dcal) <= FEEDTHROUGH_RTOL else float("inf")
        cert = H2Certificate(nu=nu, norm=norm, tightness=nu / norm if norm > 0 else float("inf"),
                             region_only_norm=n0, feedthrough=ft, Bw=Bw, Dv=Dv, lyapunov_max_eig=lyap_top)
        report = dataclasses.replace(report, extra={**report.extra, "H2": cert.describe()})
        extra = {"h2": cert}
    else:
        gamma, brl_top = certify_gamma(X, A, B / scale, C, D / scale, gs)
        gamma *= scale
        norm, freq = hinf_norm(A, B, C, D)
        if not gamma >= norm * (1.0 - NORM_RTOL):
            raise DesignVerificationError(
                f"H∞ verification failed: the certified γ = {gamma:.8g} is below the norm of the "
                f"error system computed by SLICOT AB13DD, {norm:.8g} (peak at ω = {freq:.4g} rad/s)", report)
        # the LMI's γ is certified with the X it shares with the region LMI; the returned
        # observer alone has a tighter certificate (bounded-real Riccati equation, observer fixed)
        Xc = X / scale
        own = observer_gamma(A, B, C, D, norm)
        if own is not None and own[0] < gamma:
            gamma, Xc, _ = own
        brl_top = float(np.linalg.eigvalsh(brl_matrix(Xc, A, B, C, D, gamma)).max())
        cert = HinfCertificate(gamma=gamma, norm=norm, peak_frequency=freq,
                               tightness=gamma / norm if norm > 0 else float("inf"),
                               region_only_norm=g0, Bw=Bw, Dv=Dv, brl_max_eig=brl_top, certificate_X=Xc)
        report = dataclasses.replace(report, extra={**report.extra, "H∞": cert.describe()})
        extra = {"hinf": cert}
    return dict(params={k: np.asarray(v) for k, v in params.items()}, mats=mats, X=X, report=report,
                solver={"lmi": info, "region_only": base.solver}, **extra)


def base_mats(s, params):
    return observer_matrices(s, **{k: np.asarray(v) for k, v in params.items()}, xp=np)


def error_norms(s, params, Bw, Dv) -> dict:
    r"""The norms of $d = [w;\nu]\mapsto\hat z - z$ for the observer of `params` (host, float64),
    by the same independent computations every H∞/H2 design is verified with:
    ``hinf_norm`` and ``peak_frequency`` (SLICOT AB13DD), ``h2_norm`` (SciPy Lyapunov; ``inf``
    when the feedthrough $Q\mathcal D$ is not round-off, `FEEDTHROUGH_RTOL`) and ``feedthrough``
    (relative, `_feedthrough`), and ``gamma``: a certified bound ≥ ``hinf_norm`` by
    `riccati_gamma` (``None`` if it fails). Used for the tuned designs of `fojax.tuning.tune`."""
    Bw, Dv = check_channels(s.n, s.p, Bw, Dv)
    mats = base_mats(s, params)
    A, B, C, D = error_system(s, mats, Bw, Dv)
    if not np.max(np.linalg.eigvals(A).real) < 0:
        return {"hinf_norm": float("inf"), "peak_frequency": float("nan"), "gamma": None,
                "h2_norm": float("inf"), "feedthrough": float("nan")}
    g, f = hinf_norm(A, B, C, D)
    ft = _feedthrough(mats, np.asarray(params["Y3"]), _dcal(s, Bw, Dv))
    h2 = h2_norm(A, B, C) if ft <= FEEDTHROUGH_RTOL else float("inf")
    return {"hinf_norm": g, "peak_frequency": f, "gamma": riccati_gamma(A, B, C, D, g), "h2_norm": h2,
            "feedthrough": ft}
