r"""Explicit parameterizations of *all* stabilizing gains $\mathbb Y$ for a given certificate.

The error dynamics are $\mathbb A = \mathbb A_1 - \mathbb Y\mathbb A_2$
(`fojax.design.observer_matrices`). For a fixed Lyapunov matrix $X \succ 0$ these maps
send an unconstrained parameter to a gain $\mathbb Y$ for which $X$ certifies the
requested property, so gradient-based tuning can move freely and never leaves the
set of valid observers (as long as the existence condition, returned as a margin,
stays positive).

**Lemma 10 (Hurwitz; thesis eqs. 3.178–3.179).** With $\mathcal Q = X\mathbb A_1 +
\mathbb A_1^\top X$, $\mathcal B = \mathbb A_2^\top$, $\Omega = \gamma\mathcal B\mathcal B^\top
- \mathcal Q \succ 0$ and $\|\mathcal L\| < 1$,
$\mathcal X = -\gamma\mathcal B^\top + \sqrt\gamma\,\mathcal L F$ with $F^\top F = \Omega$
gives $\mathcal Q + \mathcal B\mathcal X + (\mathcal B\mathcal X)^\top \prec 0$, and
$\mathbb Y = -X^{-1}\mathcal X^\top$ makes $X\mathbb A + \mathbb A^\top X \prec 0$.
*Deviation:* the thesis uses $\Omega^{1/2}$; any factor $F$ works (the proof only needs
$F^\top\mathcal L^\top\mathcal L F \prec F^\top F$), and fojax uses the Cholesky factor,
whose derivative stays finite where $\Omega$ has repeated eigenvalues (the symmetric
square root's does not).

**Disk $\mathcal Q(\alpha, \tau)$ (exact, derived for fojax).** With $X = L_xL_x^\top$,
the disk condition $(\mathbb A - \alpha I)^\top X(\mathbb A - \alpha I) \prec \tau^2X$ is
$\|M\| < \tau$ for $M = L_x^\top(\mathbb A - \alpha I)L_x^{-\top} = M_0 - \tilde Y\tilde B$,
$M_0 = L_x^\top(\mathbb A_1 - \alpha I)L_x^{-\top}$, $\tilde B = \mathbb A_2L_x^{-\top}$,
$\tilde Y = L_x^\top\mathbb Y$. Let $\tilde B = U_bS_bV_b^\top$ (rank $k$) and $V_\perp$ complete
$V_b$. Then $MV_\perp = M_0V_\perp =: A_\perp$ is fixed and $MV_b$ is free, so the gains
with certificate $X$ exist iff $\|A_\perp\| < \tau$ and are exactly

$$\tilde Y = (M_0V_b - F\mathcal L)S_b^{-1}U_b^\top + Y_\perp(I - U_bU_b^\top),\qquad
  FF^\top = \tau^2I - A_\perp A_\perp^\top,\; \|\mathcal L\| < 1,$$

with $Y_\perp$ arbitrary (it changes the observer's input gains $F, M$ but not $\mathbb A$).
The returned margin is $\tau - \|A_\perp\|$.
"""

from __future__ import annotations

import jax.numpy as jnp
import jax.scipy.linalg as jsl


def contraction(Theta):
    r"""Smooth map onto the open unit ball: $\mathcal L = \Theta(I + \Theta^\top\Theta)^{-1/2}$.

    Singular values $\sigma \mapsto \sigma/\sqrt{1+\sigma^2} < 1$; differentiable everywhere.
    """
    k = Theta.shape[-1]
    Mx = jnp.eye(k) + Theta.T @ Theta
    # (I + ΘᵀΘ)^{-1/2} via eigh of a matrix with eigenvalues >= 1; use a Cholesky-based
    # solve instead (any factor works for a contraction: Θ C^{-1} with CᵀC = I + ΘᵀΘ).
    Cu = jnp.linalg.cholesky(Mx).T  # upper: CuᵀCu = Mx
    return jsl.solve_triangular(Cu, Theta.T, trans="T", lower=False).T


def lemma10_gain(X, A1, A2, Lc, gamma):
    r"""Lemma 10: the gain $\mathbb Y$ with $X\mathbb A + \mathbb A^\top X \prec 0$ (module docstring).

    **Arguments:** `X` ``(d, d)`` ≻ 0, `A1` ``(d, d)``, `A2` ``(c, d)``, `Lc` ``(c, d)`` with
    ``‖Lc‖ < 1`` (e.g. from `contraction`), `gamma` > 0.

    **Returns:** ``(Y, margin)`` with ``Y`` ``(d, c)`` and ``margin`` the smallest
    eigenvalue of Ω (the construction is valid iff ``margin > 0``).
    """
    Qm = X @ A1 + A1.T @ X
    Bm = A2.T
    Om = gamma * Bm @ Bm.T - Qm
    Om = 0.5 * (Om + Om.T)
    margin = jnp.linalg.eigvalsh(Om)[0]
    F = jnp.linalg.cholesky(Om).T  # FᵀF = Ω
    Xc = -gamma * Bm.T + jnp.sqrt(gamma) * Lc @ F
    Y = -jnp.linalg.solve(X, Xc.T)
    return Y, margin


def disk_gain(X, A1, A2, center, radius, Lc, Yperp=None, rank: int | None = None):
    r"""All gains with disk certificate `X` (module docstring).

    **Arguments:**

    - `X` ``(d, d)`` ≻ 0, `A1` ``(d, d)``, `A2` ``(c, d)``.
    - `center`, `radius`: the disk.
    - `Lc` ``(d, k)``, ``‖Lc‖ < 1`` (``k`` = rank of ``A2``).
    - `Yperp` ``(d, c)`` or ``None``: the part that does not affect 𝔸.
    - `rank`: the rank ``k`` of ``A2`` (static; computed on the host when ``None``).

    **Returns:** ``(Y, margin)``: ``Y`` ``(d, c)``; ``margin = radius - ‖A⊥‖`` (the
    eigenvalues of ``A1 - Y A2`` lie in the disk with certificate ``X`` iff ``margin > 0``).
    """
    d = X.shape[0]
    if rank is None:
        import numpy as np

        a2 = np.asarray(A2)
        rank = int(np.linalg.matrix_rank(a2)) if a2.size else 0  # NumPy < 2.4.5 raises on empty
    Lx = jnp.linalg.cholesky(0.5 * (X + X.T))
    LxinvT = jsl.solve_triangular(Lx.T, jnp.eye(d), lower=False)  # Lx^{-T}
    M0 = Lx.T @ (A1 - center * jnp.eye(d)) @ LxinvT
    Bt = A2 @ LxinvT
    U, s, Vt = jnp.linalg.svd(Bt, full_matrices=True)
    Ub, Sb, Vb = U[:, :rank], s[:rank], Vt[:rank].T
    Vp = Vt[rank:].T
    Aperp = M0 @ Vp
    Sm = radius**2 * jnp.eye(d) - Aperp @ Aperp.T
    Sm = 0.5 * (Sm + Sm.T)
    normA = jnp.linalg.norm(Aperp, 2) if Aperp.size else jnp.zeros(())
    margin = radius - normA
    F = jnp.linalg.cholesky(Sm)  # F Fᵀ = τ²I - A⊥A⊥ᵀ
    Ytil = ((M0 @ Vb - F @ Lc) / Sb[None, :]) @ Ub.T
    if Yperp is not None:
        Ytil = Ytil + Yperp @ (jnp.eye(U.shape[0]) - Ub @ Ub.T)
    Y = LxinvT @ Ytil
    return Y, margin
