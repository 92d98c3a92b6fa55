"""Rank-revealing linear algebra with one documented tolerance.

Host (NumPy) versions are used by analysis and design code outside jit; JAX
versions (prefix ``j``) are traceable and differentiable where the rank is fixed.

**Rank tolerance.** A singular value ``s`` counts as non-zero when
``s > max(rtol * s_max, atol)`` with ``rtol = RANK_RTOL = 1e-10`` and
``atol = RANK_ATOL = 1e-12``. The relative part makes decisions independent of the
overall scale of a matrix; the absolute floor makes a matrix of round-off
(e.g. ``1e-17``) count as zero. Both can be overridden per call with ``tol=``
(an absolute threshold).

**Relative to what.** ``s_max`` is the largest singular value of the matrix whose rank
is decided. Host analysis (`fojax.analysis`, and the design layer through it) never
applies the rule to raw user data: it first balances the system by an exact
power-of-two diagonal scaling of equations and states (`fojax.analysis.balance_system`),
then divides each block ``E``, ``A``, ``B``, ``C``, ``L`` by its spectral norm, and
only then decides ranks of the block matrices built from them. So a verdict does not
change with the units of the equations or the states. SLICOT's ``AG08BD``
(`fojax.analysis.kronecker_structure`) gets the same data with ``tol = RANK_RTOL``. This is the
one place the rule is defined; `fojax.analysis` documents how it is applied.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np


RANK_RTOL = 1e-10
RANK_ATOL = 1e-12


def _threshold(s: np.ndarray, tol: float | None) -> float:
    if tol is not None:
        return float(tol)
    smax = float(s[0]) if s.size else 0.0
    return max(RANK_RTOL * smax, RANK_ATOL)


def rank(M, tol: float | None = None) -> int:
    """Numerical rank of `M` (0 for empty matrices)."""
    M = np.asarray(M, dtype=float)
    if M.size == 0:
        return 0
    s = np.linalg.svd(M, compute_uv=False)
    return int(np.sum(s > _threshold(s, tol)))


def left_null_space(M, tol: float | None = None) -> np.ndarray:
    """Orthonormal rows `N` with ``N @ M = 0`` spanning the left null space of `M`.

    For an ``(r, c)`` matrix of rank ``k`` the result is ``(r - k, r)``; an empty
    ``(0, r)`` array when `M` has full row rank.
    """
    return _null_basis(M, tol, side=0)


def null_space(M, tol: float | None = None) -> np.ndarray:
    """Orthonormal columns `V` with ``M @ V = 0`` (``(c, c - k)``)."""
    return _null_basis(M, tol, side=1)


def _null_basis(M, tol: float | None, side: int) -> np.ndarray:
    """Orthonormal basis of the left (``side=0``, as rows) or right (``side=1``, as
    columns) null space of `M`, from one full SVD and the rank rule."""
    M = np.asarray(M, dtype=float)
    if M.size == 0:
        return np.eye(M.shape[side])
    U, s, Vt = np.linalg.svd(M, full_matrices=True)
    k = int(np.sum(s > _threshold(s, tol)))
    return U[:, k:].T.copy() if side == 0 else Vt[k:].T.copy()


def row_null_split(M, tol: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(R, N, U, s)`` from one full SVD and the rank rule: orthonormal rows `R` spanning the
    row space of `M` (as `row_space`), orthonormal columns `N` spanning its null space (as
    `null_space`), and ``M = U diag(s) R``."""
    M = np.asarray(M, dtype=float)
    r, c = M.shape
    if M.size == 0:
        return np.zeros((0, c)), np.eye(c), np.zeros((r, 0)), np.zeros(0)
    U, s, Vt = np.linalg.svd(M, full_matrices=True)
    k = int(np.sum(s > _threshold(s, tol)))
    return Vt[:k].copy(), Vt[k:].T.copy(), U[:, :k].copy(), s[:k].copy()


def row_space(M, tol: float | None = None) -> np.ndarray:
    """Orthonormal rows spanning the row space of `M` (``(k, c)``)."""
    M = np.asarray(M, dtype=float)
    c = M.shape[1]
    if M.size == 0:
        return np.zeros((0, c))
    _, s, Vt = np.linalg.svd(M, full_matrices=False)
    k = int(np.sum(s > _threshold(s, tol)))
    return Vt[:k].copy()


#: Relative tolerance under which two residual norms count as tied in `canonical_row_space`'s
#: pivoting (the lower column index wins). Rounding moves them by ~1e-15 relative.
PIVOT_TIE_RTOL = 1e-8


def canonical_row_space(M, tol: float | None = None) -> np.ndarray:
    r"""Orthonormal rows spanning the row space of `M`, in an order and with signs that depend
    only on the subspace (and the coordinate order), not on the basis an SVD returns.

    `row_space` returns the leading right singular vectors: when singular values are equal
    (e.g. $M$ is an orthogonal projector, all of them 1) that basis is an arbitrary rotation
    $WQ$ decided by rounding, and even distinct singular values leave the signs to LAPACK.
    Callers that take only the *first* rows of a basis, or search along its rows, must not
    depend on that. Derivation: let $Q$ ($k \times c$) be any orthonormal basis and
    $P = Q^\top Q$ the orthogonal projector onto the subspace (the same for every $WQ$, $W$
    orthogonal). Pivoted Gram–Schmidt on the columns $Qe_j$ selects $J_1$ = the column of
    largest norm $\|Qe_j\|^2 = P_{jj}$, then the column of largest residual after removing
    the span of the columns chosen so far, and so on; these norms are functions of the Gram
    matrix $(Qe_i)^\top Qe_j = P_{ij}$ only, so the pivots $J = (J_1, \dots, J_k)$ do not
    depend on $W$. With the QR factorization $Q_{:,J} = U R_J$ ($R_J$ upper triangular with
    positive diagonal, unique) the result is $U^\top Q$: for $WQ$ the factorization is
    $(WU)R_J$ and $(WU)^\top WQ = U^\top Q$, exactly the same rows. Row $i$ is the
    normalised component of $Pe_{J_i}$ orthogonal to $Pe_{J_1}, \dots, Pe_{J_{i-1}}$; in
    particular the first row is $Pe_{J_1}/\|Pe_{J_1}\|$, the direction of the subspace
    closest to coordinate $J_1$, the coordinate the subspace sees best. Since the first $i$
    rows span $\{Pe_{J_1}, \dots, Pe_{J_i}\}$, taking a prefix of the rows is well defined.

    **Ties.** Residual norms within `PIVOT_TIE_RTOL` (relative) of the largest count as equal
    and the lowest column index wins, so exact ties (symmetric models) are broken by the
    order of the coordinates, not by rounding. Only a genuine difference of about
    `PIVOT_TIE_RTOL` between two residuals could still be resolved differently by rounding.
    Coordinates matter: pivots are chosen among columns, so rescaling columns changes the
    choice (fojax's design layer calls this in the unit-free frame of
    `fojax.analysis.unit_scaling`).

    **Returns:** ``(k, c)`` with ``k`` the numerical rank of `M` (fojax's rank rule).
    """
    Q = row_space(M, tol)
    k = Q.shape[0]
    if k == 0:
        return Q
    Res = Q.copy()
    J: list[int] = []
    for _ in range(k):
        nrm = np.einsum("ij,ij->j", Res, Res)
        nrm[J] = -1.0
        j = int(np.flatnonzero(nrm >= nrm.max() * (1.0 - PIVOT_TIE_RTOL))[0])
        J.append(j)
        u = Res[:, j] / np.sqrt(nrm[j])
        Res = Res - np.outer(u, u @ Res)
        Res = Res - np.outer(u, u @ Res)  # twice is enough (Kahan–Parlett)
    U, RJ = np.linalg.qr(Q[:, J])
    U = U * np.where(np.diag(RJ) < 0, -1.0, 1.0)[None, :]
    return U.T @ Q


def pinv(M, tol: float | None = None) -> np.ndarray:
    """Moore–Penrose pseudo-inverse with the fojax rank tolerance."""
    M = np.asarray(M, dtype=float)
    if M.size == 0:
        return np.zeros(M.shape[::-1])
    U, s, Vt = np.linalg.svd(M, full_matrices=False)
    keep = s > _threshold(s, tol)
    sinv = np.where(keep, 1.0 / np.where(keep, s, 1.0), 0.0)
    return (Vt.T * sinv) @ U.T


def in_row_space(X, M, tol: float = 1e-9) -> tuple[bool, float]:
    """Whether the rows of `X` lie in the row space of `M`.

    Returns ``(ok, residual)`` with ``residual = ‖X (I - M⁺M)‖ / max(1, ‖X‖)``.
    """
    X = np.asarray(X, dtype=float)
    M = np.asarray(M, dtype=float)
    if X.size == 0:
        return True, 0.0
    res = X - X @ pinv(M) @ M
    r = float(np.linalg.norm(res, 2)) / max(1.0, float(np.linalg.norm(X, 2)))
    return r <= tol, r


def perp(M, tol: float | None = None) -> np.ndarray:
    """The thesis's ``M⊥``: a maximal-row-rank matrix with ``M⊥ M = 0`` (orthonormal rows)."""
    return left_null_space(M, tol)


# ------------------------------------------------------------------ JAX (traceable)


def jpinv(M, rtol: float = RANK_RTOL):
    """Traceable pseudo-inverse (``jnp.linalg.pinv`` with fojax's relative tolerance).

    Differentiable wherever the numerical rank of `M` does not change.
    """
    if M.size == 0:
        return jnp.zeros(M.shape[::-1], dtype=M.dtype)
    return jnp.linalg.pinv(M, rtol=rtol)


def jsqrtm_psd(S):
    """Symmetric square root of a symmetric positive (semi)definite matrix, traceable."""
    S = 0.5 * (S + S.T)
    w, V = jnp.linalg.eigh(S)
    return (V * jnp.sqrt(jnp.clip(w, 0.0))) @ V.T


def clusters(points, tol) -> list[np.ndarray]:
    """Groups of indices of `points` (complex numbers) linked by single linkage: ``i`` and
    ``j`` are in one group when a chain of points each within the tolerance of the next
    joins them. `tol` is one number or one per point (``|p_i - p_j| <= tol[i]``)."""
    pts = np.asarray(points, dtype=complex).ravel()
    n = pts.size
    tols = np.broadcast_to(np.asarray(tol, dtype=float), (n,))
    parent = list(range(n))

    def find(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i in range(n):
        for j in range(i + 1, n):
            if abs(pts[i] - pts[j]) <= tols[i]:
                parent[find(i)] = find(j)
    groups: dict[int, list[int]] = {}
    for i in range(n):
        groups.setdefault(find(i), []).append(i)
    return [np.asarray(g) for g in groups.values()]
