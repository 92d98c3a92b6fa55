r"""Certified H∞ and H2 bounds of a fixed error system, each checked in float64.

The error system $(\mathbb A, \mathbb B, \mathbb C, \mathbb D)$ of $d = [w;\nu]\mapsto\hat z - z$
(`fojax.design.error_system`, derived in `fojax.design._hinf`) is fixed here: these functions
certify bounds on its norms and compute the norms independently.

**H∞.** The bounded-real lemma: $\|T\|_\infty < \gamma$ with $\mathbb A$ Hurwitz iff some
$X \succ 0$ makes

$$\begin{bmatrix}\operatorname{He}(X\mathbb A) & X\mathbb B & \mathbb C^\top\\
  \star & -\gamma I & \mathbb D^\top\\ \star & \star & -\gamma I\end{bmatrix} \prec 0$$

(`brl_matrix`; Gahinet & Apkarian 1994). `certify_gamma` re-checks it in float64 at a given
$X$; `observer_gamma` builds $X$ for the observer alone from the stabilizing solution of the
bounded-real Riccati equation, within a small relative gap of the norm; the norm itself is
SLICOT's ``AB13DD`` (`hinf_norm`).

**H2.** Without feedthrough, $\operatorname{He}(X\mathbb A) + \mathbb C^\top\mathbb C \prec 0$
(`lyapunov_matrix`) gives $X \succ L_o$ (the observability Gramian), hence
$\|T\|_2 \le \sqrt{\operatorname{tr}(\mathbb B^\top X\mathbb B)}$; `certify_nu` re-checks it in
float64, `observer_nu` builds $X$ from $L_o$, and the norm itself is SciPy's
``solve_continuous_lyapunov`` (`h2_norm`).
"""

from __future__ import annotations

import numpy as np

from .._errors import DesignVerificationError


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


def h2_norm(A, B, C) -> float:
    r"""$\|T\|_2 = \sqrt{\operatorname{tr}(C P C^\top)}$, $AP + PA^\top + BB^\top = 0$ (SciPy
    ``solve_continuous_lyapunov``): the independent norm every H2 design is checked against
    (`A` Hurwitz, no feedthrough)."""
    import scipy.linalg as sla

    if A.shape[0] == 0 or B.shape[1] == 0 or C.shape[0] == 0:
        return 0.0
    P = sla.solve_continuous_lyapunov(A, -B @ B.T)
    return float(np.sqrt(max(float(np.trace(C @ (0.5 * (P + P.T)) @ C.T)), 0.0)))


def lyapunov_matrix(X, A, C):
    r"""$\begin{bmatrix}\operatorname{He}(XA) & C^\top\\ C & -I\end{bmatrix}$ (float64, symmetrised)."""
    XA = X @ A
    out = np.block([[XA + XA.T, C.T], [C, -np.eye(C.shape[0])]])
    return 0.5 * (out + out.T)


def certify_nu(X, A, B, C) -> tuple[float, float]:
    r"""``(ν, max eig)``: the smallest ``t ∈ {1, 1 + 1e-9·10^k}`` at which the Lyapunov
    inequality holds at ``tX`` in float64 (strictly, relative to its scale, with ``tX ≻ 0``),
    and the certified $\nu = \sqrt{\operatorname{tr}(B^\top tX B)}$. Raises
    `DesignVerificationError` if even ``t = 1.01`` fails."""
    for bump in (0.0, 1e-9, 1e-8, 1e-7, 1e-6, 1e-5, 1e-4, 1e-3, 1e-2):
        Xt = (1.0 + bump) * X
        M = lyapunov_matrix(Xt, A, C)
        top = float(np.linalg.eigvalsh(M).max())
        if top < -1e-12 * max(1.0, float(np.abs(M).max())) and float(np.linalg.eigvalsh(Xt).min()) > 0:
            return float(np.sqrt(max(float(np.trace(B.T @ Xt @ B)), 0.0))), top
    raise DesignVerificationError(
        f"the H2 Lyapunov inequality He(X𝔸) + ℂᵀℂ ≺ 0 re-checked in float64 at the certificate X "
        f"fails even at 1.01 X (max eigenvalue {top:.3e}): the solver's H2 bound is not certified")


#: Relative gaps between the AB13DD norm and the γ0 at which `observer_gamma` tries to certify
#: (the smallest that passes is returned; `certify_gamma` may add up to 1 % more).
RICCATI_GAPS = (1e-9, 1e-8, 1e-7, 1e-6, 1e-5, 1e-4, 1e-3, 1e-2)


def observer_gamma(A, B, C, D, norm):
    r"""The tightest certified bound γ ≥ ‖T‖∞ of a fixed error system, with its certificate:
    ``(γ, X, max eig)`` or ``None``.

    The observer is fixed, so the bounded-real lemma needs no region constraint and no
    shared certificate: the stabilizing solution $Y$ of the bounded-real Riccati equation at
    $\gamma_0 = $ `norm` ``·(1 + gap)`` (`RICCATI_GAPS`, smallest first),
    $A^\top Y + YA + C^\top C + \epsilon I + (YB + C^\top D)(\gamma_0^2I - D^\top D)^{-1}
    (B^\top Y + D^\top C) = 0$ (SciPy ``solve_continuous_are`` with the negative definite
    weight $-(\gamma_0^2I - D^\top D)$), gives $X = Y/\gamma_0$ at which the BRL matrix
    (`brl_matrix`) is negative definite (Schur complement); `certify_gamma` re-checks it in
    float64. The first gap whose certificate passes is used, so γ exceeds the AB13DD norm
    by at most that gap (plus `certify_gamma`'s bump). ``None`` when no gap certifies."""
    import warnings

    import scipy.linalg as sla

    if not (np.isfinite(norm) and norm > 0) or A.shape[0] == 0:
        return None
    # the Riccati data in units where the bound is 1: B, D divided by norm (X is unchanged
    # by that scaling up to the factor applied below)
    Bs, Ds = B / norm, D / norm
    Q = C.T @ C
    Q = Q + 1e-9 * max(1.0, float(np.abs(Q).max())) * np.eye(A.shape[0])
    for gap in RICCATI_GAPS:  # the Riccati equation is ill-conditioned as γ0 → ‖T‖∞: widen the gap
        g0 = 1.0 + gap
        Rt = g0 * g0 * np.eye(B.shape[1]) - Ds.T @ Ds
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                Y = sla.solve_continuous_are(A, Bs, Q, -Rt, s=C.T @ Ds)
            if np.all(np.isfinite(Y)):
                # BRL of (A, Bs, C, Ds) at (Y/g0, g0) ⇔ BRL of (A, B, C, D) at (Y/(g0·norm), g0·norm)
                X = 0.5 * (Y + Y.T) / (g0 * norm)
                gamma, top = certify_gamma(X, A, B, C, D, g0 * norm)
                return float(gamma), X, top
        except (np.linalg.LinAlgError, ValueError, DesignVerificationError):
            pass
    return None


def riccati_gamma(A, B, C, D, norm) -> float | None:
    """A certified bound γ ≥ ‖T‖∞ for a system without an LMI certificate (a tuned design):
    `observer_gamma`'s γ, ``None`` when it fails (reported as "not certified")."""
    out = observer_gamma(A, B, C, D, norm)
    return None if out is None else out[0]


def observer_nu(A, B, C, norm):
    r"""The tightest certified bound ν ≥ ‖T‖₂ of a fixed error system without feedthrough:
    ``(ν, X, max eig)`` or ``None``.

    With the observability Gramian $L_o$ ($A^\top L_o + L_oA + C^\top C = 0$) and $P_1$
    ($A^\top P_1 + P_1A + I = 0$), $X = L_o + \delta P_1$ satisfies
    $\operatorname{He}(XA) + C^\top C = -\delta I \prec 0$, and
    $\nu^2 = \operatorname{tr}(B^\top XB) = \|T\|_2^2 + \delta\operatorname{tr}(B^\top P_1B)$.
    δ grows from $10^{-10}$ of the data's scale until `certify_nu` passes in float64."""
    import scipy.linalg as sla

    if A.shape[0] == 0 or not np.isfinite(norm):
        return None
    try:
        Lo = sla.solve_continuous_lyapunov(A.T, -C.T @ C)
        P1 = sla.solve_continuous_lyapunov(A.T, -np.eye(A.shape[0]))
    except (np.linalg.LinAlgError, ValueError):
        return None
    Lo, P1 = 0.5 * (Lo + Lo.T), 0.5 * (P1 + P1.T)
    size = max(float(np.abs(C.T @ C).max()), float(np.abs(Lo @ A).max()), 1e-300)
    for rel in (1e-10, 1e-9, 1e-8, 1e-7, 1e-6, 1e-5, 1e-4):
        X = Lo + rel * size * P1
        try:
            nu, top = certify_nu(X, A, B, C)
        except DesignVerificationError:
            continue
        return nu, X, top
    return None
