r"""Weierstrass canonical form of a regular pencil (thesis eq. 2.16)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ._common import as_pencil, require_regular


@dataclass(frozen=True)
class WeierstrassForm:
    r"""Result of `weierstrass_form`: invertible $P$, $Q$ with

    $$P E Q = \begin{bmatrix}I_{n_1}&0\\0&N\end{bmatrix},\qquad
      P A Q = \begin{bmatrix}A_1&0\\0&I_{n_2}\end{bmatrix},\qquad
      P B = \begin{bmatrix}B_1\\B_2\end{bmatrix},\qquad C Q = [C_1\;\;C_2],$$

    $N$ nilpotent (strictly block lower triangular here) with index `index`. In the
    coordinates $x = Q[x_1; x_2]$ the system splits into the slow subsystem
    $\dot x_1 = A_1x_1 + B_1u$ and the fast subsystem $N\dot x_2 = x_2 + B_2u$
    (thesis eq. 2.17).

    **Fields:** `P`, `Q` (``(n, n)``), `A1` (``(n1, n1)``), `N` (``(n2, n2)``), `B1`,
    `B2`, `C1`, `C2` (empty when only ``(E, A)`` were given), `n1` (number of finite
    poles), `n2 = n - n1`, `index` (nilpotency index of `N`, convention of
    `nilpotency_index`), `residuals` (dict of float64 checks: ``"E"`` and ``"A"`` are the
    max-abs entries of ``P E Q - diag(I, N)`` and ``P A Q - diag(A1, I)``;
    ``"nilpotency"`` is ``max|N^index|`` (exactly 0 by construction); ``"dropped"`` the
    largest entry set to zero by the rank decisions, relative to the normalised pencil).
    """

    P: np.ndarray
    Q: np.ndarray
    A1: np.ndarray
    N: np.ndarray
    B1: np.ndarray
    B2: np.ndarray
    C1: np.ndarray
    C2: np.ndarray
    n1: int
    n2: int
    index: int
    residuals: dict = field(default_factory=dict)

    def __repr__(self) -> str:
        res = ", ".join(f"{k}={v:.1e}" for k, v in self.residuals.items())
        return f"WeierstrassForm(n1={self.n1}, n2={self.n2}, index={self.index}, residuals: {res})"


def weierstrass_form(sys, A=None, *, tol: float | None = None, balance: bool = True) -> WeierstrassForm:
    r"""Weierstrass canonical form of a regular pencil (thesis eq. 2.16).

    Host-only. Algorithm: (i) orthogonal deflation of the infinite eigenvalues of the
    normalised pencil (see `fojax.analysis.is_regular`), giving the block lower triangular pencil
    $W^T(sE - A)V = \begin{bmatrix}sE_f - A_f & 0\\ sE_{21} - A_{21} & sE_\infty -
    A_\infty\end{bmatrix}$ with $E_f$ and $A_\infty$ invertible and
    $A_\infty^{-1}E_\infty$ strictly block lower triangular; (ii) decoupling by the
    generalized Sylvester equations $L E_f + E_\infty R = -E_{21}$,
    $L A_f + A_\infty R = -A_{21}$ (solved through their Kronecker form — fine for the
    small systems of fojax); (iii) normalisation by $E_f^{-1}$ and $A_\infty^{-1}$. The
    structural zeros of $N = A_\infty^{-1}E_\infty$ are set exactly, so $N$ is exactly
    nilpotent ($N^{\nu} = 0$ in floating point); everything dropped is reported.
    No QZ is needed (the eigenvalues of `A1` are the finite poles).

    The thesis calls this decomposition an "SVD"; it is not one (an SVD of $E$ does not
    make $A$ block diagonal). The thesis also swaps the names $P, Q$ in §2.1.2's
    observability part ($QEP$); here it is always $PEQ$.

    Rank decisions: fojax tolerance on the normalised matrices (overridable by `tol`).

    **Arguments:** `sys` (a `fojax.DescriptorSystem`, or ``E`` with `A` given), `tol`.

    **Returns:** a `WeierstrassForm`.

    **Raises:** `fojax.errors.IrregularSystemError` for a singular pencil (no such form exists).
    """
    p = as_pencil(sys, A, fname="weierstrass_form", balance=balance)
    d = require_regular(p, "weierstrass_form", tol)
    n, m, q = p.n, p.B.shape[1], p.C.shape[0]
    n1 = d.n1
    n2 = n - n1
    if n == 0:
        z = np.zeros((0, 0))
        return WeierstrassForm(
            z, z, z, z, np.zeros((0, m)), np.zeros((0, m)), np.zeros((q, 0)), np.zeros((q, 0)),
            0, 0, 0, {"E": 0.0, "A": 0.0, "nilpotency": 0.0, "dropped": 0.0},
        )  # fmt: skip
    Et, At = d.Et, d.At
    Ef, Af = Et[:n1, :n1], At[:n1, :n1]
    E21, A21 = Et[n1:, :n1], At[n1:, :n1]
    Einf, Ainf = Et[n1:, n1:], At[n1:, n1:]

    k = n1 * n2
    if k:
        I1, I2 = np.eye(n1), np.eye(n2)
        K = np.block(
            [
                [np.kron(Ef.T, I2), np.kron(I1, Einf)],
                [np.kron(Af.T, I2), np.kron(I1, Ainf)],
            ]
        )
        rhs = -np.concatenate([E21.ravel(order="F"), A21.ravel(order="F")])
        sol = np.linalg.solve(K, rhs)
        Lm = sol[:k].reshape((n2, n1), order="F")
        R = sol[k:].reshape((n2, n1), order="F")
    else:
        Lm = np.zeros((n2, n1))
        R = np.zeros((n2, n1))
    left = np.eye(n)
    left[n1:, :n1] = Lm
    right = np.eye(n)
    right[n1:, :n1] = R
    Pl = left @ d.W.T
    Qr = d.V @ right

    dropped_n = 0.0
    if n2:
        N_ = np.linalg.solve(Ainf, Einf)
        # Level j = coordinates split off at deflation step j+1 (level 0 at the bottom).
        # E_inf[r, c] != 0 only if level(r) < level(c), A_inf[r, c] only if
        # level(r) <= level(c); hence N[r, c] != 0 only if level(r) < level(c).
        level = np.empty(n2, dtype=int)
        pos = n2
        for j, kj in enumerate(d.blocks):
            level[pos - kj : pos] = j
            pos -= kj
        keep = level[:, None] < level[None, :]
        dropped_n = float(np.max(np.abs(N_[~keep]), initial=0.0))
        N_ = np.where(keep, N_, 0.0)
    else:
        N_ = np.zeros((0, 0))
    A1_ = np.linalg.solve(Ef, Af) if n1 else np.zeros((0, 0))
    D = np.zeros((n, n))
    if n1:
        D[:n1, :n1] = np.linalg.inv(Ef)
    if n2:
        D[n1:, n1:] = np.linalg.inv(Ainf)
    P_ = D @ Pl

    # Undo the normalisation Dl E Dr = e En, Dl A Dr = a An and the balancing Dl, Dr.
    dl, dr = p.scaling.left, p.scaling.right
    e = float(np.linalg.norm(dl[:, None] * p.E * dr[None, :], 2)) or 1.0
    a = float(np.linalg.norm(dl[:, None] * p.A * dr[None, :], 2)) or 1.0
    scale = np.concatenate([np.full(n1, 1.0 / e), np.full(n2, 1.0 / a)])
    P = scale[:, None] * P_ * dl[None, :]
    Q = dr[:, None] * Qr
    A1 = (a / e) * A1_
    N = (e / a) * N_

    targetE = np.zeros((n, n))
    targetE[:n1, :n1] = np.eye(n1)
    targetE[n1:, n1:] = N
    targetA = np.zeros((n, n))
    targetA[:n1, :n1] = A1
    targetA[n1:, n1:] = np.eye(n2)
    PB = P @ p.B
    CQ = p.C @ Q
    nil = np.linalg.matrix_power(N, d.index) if n2 else np.zeros((0, 0))
    residuals = {
        "E": float(np.max(np.abs(P @ p.E @ Q - targetE))),
        "A": float(np.max(np.abs(P @ p.A @ Q - targetA))),
        "nilpotency": float(np.max(np.abs(nil), initial=0.0)),
        "dropped": max(d.dropped, dropped_n),
    }
    return WeierstrassForm(
        P=P,
        Q=Q,
        A1=A1,
        N=N,
        B1=PB[:n1],
        B2=PB[n1:],
        C1=CQ[:, :n1],
        C2=CQ[:, n1:],
        n1=n1,
        n2=n2,
        index=d.index,
        residuals=residuals,
    )
