"""Input handling and rank helpers shared by the host-side analysis functions.

Every host function first turns its argument into float64 NumPy matrices, then
*balances* them by an exact power-of-two diagonal scaling of equations and states
(`fojax.analysis._balance`; ``balance=False`` skips it), then *normalises* them:
``E``, ``A``, ``B``, ``C`` are each divided by their spectral norm (a zero matrix is left alone). Normalisation changes neither ranks nor the
sign of any pole (the finite poles of ``(E/e, A/a)`` are those of ``(E, A)``
multiplied by ``e/a > 0``), but it makes the single relative rank tolerance of
`fojax._linalg` meaningful for block matrices such as ``[[E, A], [0, E]]`` whose
blocks have very different scales.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import numpy as np

from .._dtype import as_matrix, to_numpy
from .._errors import InputError, IrregularSystemError, NumericallyUndecidableError, ShapeError
from .._linalg import _threshold, RANK_ATOL, RANK_RTOL
from ..plant import DescriptorSystem
from ._balance import apply_scaling, Scaling, scaling_of


def crank(M, tol: float | None = None) -> int:
    """Numerical rank of a real *or complex* matrix with the fojax tolerance.

    Same rule as `fojax._linalg.rank`: singular values above
    ``max(RANK_RTOL * s_max, RANK_ATOL)`` (or above `tol` when given) count.
    """
    M = np.asarray(M)
    if M.size == 0:
        return 0
    s = np.linalg.svd(M, compute_uv=False)
    return int(np.sum(s > _threshold(s, tol)))


def _unit(M: np.ndarray) -> tuple[np.ndarray, float]:
    if M.size == 0:
        return M, 1.0
    nrm = float(np.linalg.norm(M, 2))
    if nrm == 0.0:
        return M, 1.0
    return M / nrm, nrm


def balanced_units(E, A, B, C, balance: bool):
    """The power-of-two balancing of ``(E, A, B, C)`` (`scaling_of`) and each balanced block
    divided by its spectral norm: ``(scaling, ((En, ‖E‖), (An, ‖A‖), (Bn, ‖B‖), (Cn, ‖C‖)))``
    (a zero or empty block keeps norm ``1``)."""
    sc = scaling_of(E, A, B, C, balance=balance)
    return sc, tuple(_unit(M) for M in apply_scaling(sc, E, A, B, C))


@dataclass(frozen=True)
class Pencil:
    """Host copy of a system: raw (``E``...), and balanced then normalised (``En``...).

    ``En = D_l E D_r / ‖D_l E D_r‖`` etc. with the power-of-two `scaling`.
    """

    E: np.ndarray
    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    En: np.ndarray
    An: np.ndarray
    Bn: np.ndarray
    Cn: np.ndarray
    #: finite poles of (E, A) = pole_scale * finite poles of (En, An)
    pole_scale: float
    has_io: bool
    scaling: Scaling | None = None
    #: sampling period of a discrete-time system (``None``: continuous time)
    dt: float | None = None

    @property
    def n(self) -> int:
        return self.E.shape[0]


def _host(name: str, M) -> np.ndarray:
    if isinstance(M, jax.core.Tracer):
        raise InputError(
            f"{name} is a traced JAX value: this analysis function runs on the host "
            "(NumPy/SciPy, QZ or SVD with rank decisions) and cannot be called inside "
            "jax.jit / jax.vmap / jax.grad. Call it on concrete arrays, or use the "
            "traceable screens fojax.analysis.impulse_free_margin, fojax.analysis.stability_margin_index1, "
            "fojax.analysis.functional_observability_gap, fojax.analysis.regular_at."
        )
    M = to_numpy(M)
    if M.ndim != 2:
        raise ShapeError(
            name,
            "a 2-d matrix",
            tuple(M.shape),
            "Host analysis takes one system at a time; for a batch of systems loop on the "
            "host or use the traceable screens (fojax.analysis.impulse_free_margin, ...) under jax.vmap.",
        )
    return M


def as_pencil(sys, A=None, *, fname: str = "this function", balance: bool = True) -> Pencil:
    """Accept a `DescriptorSystem`, or raw matrices ``(E, A)``.

    With raw matrices ``B`` and ``C`` are empty (``m = p = 0``). The system is balanced
    (`fojax.analysis._balance`, unless ``balance=False``) and then normalised.
    """
    if isinstance(sys, DescriptorSystem):
        if A is not None:
            raise InputError(
                f"{fname}: pass either a DescriptorSystem or the two matrices (E, A), not both."
            )
        E = _host("E", sys.E)
        A_ = _host("A", sys.A)
        B = _host("B", sys.B)
        C = _host("C", sys.C)
        has_io = True
        dt = sys.dt
    else:
        dt = None
        if A is None:
            raise InputError(
                f"{fname} expects a fojax.DescriptorSystem or the two matrices (E, A); "
                f"got a single {type(sys).__name__}. Call {fname}(E, A) or build "
                "fojax.DescriptorSystem(E, A, B, C)."
            )
        for name, M in (("E", sys), ("A", A)):
            if isinstance(M, jax.core.Tracer):
                _host(name, M)
        E = to_numpy(as_matrix("E", sys))
        n = E.shape[0]
        if E.shape[1] != n:
            raise ShapeError("E", (n, n), tuple(E.shape), "E must be square (n, n).")
        A_ = to_numpy(as_matrix("A", A, rows=n, cols=n, hint="A must be square and match E."))
        B = np.zeros((n, 0))
        C = np.zeros((0, n))
        has_io = False
    sc, ((En, e), (An, a), (Bn, _), (Cn, _)) = balanced_units(E, A_, B, C, balance)
    return Pencil(E, A_, B, C, En, An, Bn, Cn, a / e, has_io, sc, dt)


def as_system(sys, fname: str, balance: bool = True) -> Pencil:
    """Like `as_pencil` but a `DescriptorSystem` is required (B and C are needed)."""
    if not isinstance(sys, DescriptorSystem):
        raise InputError(
            f"{fname} needs a fojax.DescriptorSystem (it uses B and/or C), got "
            f"{type(sys).__name__}. Build one with fojax.DescriptorSystem(E, A, B, C)."
        )
    return as_pencil(sys, fname=fname, balance=balance)


@dataclass(frozen=True)
class Deflation:
    r"""Orthogonal deflation of the infinite eigenvalues of a (normalised) regular pencil.

    Orthogonal `W`, `V` with ``Et = W.T @ En @ V``, ``At = W.T @ An @ V`` of the form

    $$E_t = \begin{bmatrix}E_f&0\\E_{21}&E_\infty\end{bmatrix},\qquad
      A_t = \begin{bmatrix}A_f&0\\A_{21}&A_\infty\end{bmatrix},$$

    $E_f$ (``n1 × n1``) invertible, $A_\infty$ invertible and block lower triangular,
    $E_\infty$ strictly block lower triangular (so $A_\infty^{-1}E_\infty$ is nilpotent).
    `blocks` are the sizes deflated at each step (the first is ``n - rank E``); their
    number is the nilpotency index. `dropped` is the largest entry set to zero.
    `failed` is an explanation when the pencil turned out to be singular.
    """

    W: np.ndarray
    V: np.ndarray
    Et: np.ndarray
    At: np.ndarray
    n1: int
    blocks: tuple
    dropped: float
    failed: str | None = None
    #: ``(factor, singular value)`` of the rank decision closest to the threshold
    #: (``factor = max(σ/t, t/σ) ≥ 1``); ``None`` when no decision was taken.
    nearest: tuple | None = None

    @property
    def index(self) -> int:
        return len(self.blocks)


def deflate(p: Pencil, tol: float | None) -> Deflation:
    r"""Deflate the infinite eigenvalues of ``(En, An)`` by orthogonal transformations.

    Step (Van Dooren 1979 style): with the current leading block ``(E11, A11)`` of size
    ``m``, take an orthonormal basis ``V2`` of ``ker E11`` (SVD, ``k`` directions); a
    regular pencil maps it injectively by ``A11`` (else some ``x`` has
    ``E11 x = A11 x = 0`` and ``det(sE - A) ≡ 0``); a QR factorisation of ``A11 V2``
    moves its range to the last ``k`` rows. The last ``k`` rows/columns then carry
    ``k`` infinite eigenvalues and are split off; repeat until ``E11`` is invertible.
    Each step is orthogonal, so the result is backward stable up to the rank decisions —
    unlike reading infinite eigenvalues off QZ, which perturbs an index-``ν`` block by
    ``O(ε^{1/ν})``.

    Rank decisions: a singular value counts when it exceeds ``tol`` (absolute) or by
    default ``max(RANK_RTOL, RANK_ATOL)`` — the fojax rule relative to
    ``‖En‖ = ‖An‖ = 1``. When a decision's singular value lies within `UNDECIDED_BAND`
    of that threshold, the regularity verdict is cross-checked with SLICOT ``AG08BD``
    (normal rank of the same pencil at the same tolerance); if the two disagree the
    pencil is numerically undecidable at that tolerance and
    `fojax.errors.NumericallyUndecidableError` is raised (never a silent guess).
    """
    d = _deflate(p, tol)
    if d.nearest is not None and d.nearest[0] < UNDECIDED_BAND:
        _cross_check(p, d, tol)
    return d


#: A rank decision of `deflate` whose singular value is within this factor of the threshold
#: (either side) is cross-checked against SLICOT ``AG08BD`` (`_cross_check`).
UNDECIDED_BAND = 100.0


def _cross_check(p: Pencil, d: Deflation, tol: float | None) -> None:
    """Raise `NumericallyUndecidableError` when SLICOT ``AG08BD`` at the same tolerance, on
    the balanced, normalised pencil or on the data as given, with or without its own
    balancing (with ``balance=False`` only on the unbalanced pencil, without), gives the
    other regularity verdict."""
    import slycot

    n = p.En.shape[0]
    thr = float(tol) if tol is not None else max(RANK_RTOL, RANK_ATOL)
    ours = d.failed is None
    # on the pencil fojax decided on and on the data as given, each with and without
    # AG08BD's own balancing ("S")
    # (``balance=False``: only the data as given, unbalanced, as the caller asked)
    unbalanced = p.scaling is None or p.scaling.method == "none"
    for (E, A), equil in ([((p.En, p.An), "N")] if unbalanced else
                          [(pair, eq) for pair in ((p.En, p.An), (p.E, p.A)) for eq in ("N", "S")]):
        if not (np.all(np.isfinite(E)) and np.all(np.isfinite(A))):
            continue
        nrank = int(slycot.ag08bd(n, n, 0, 0, np.array(A, order="F"), np.array(E, order="F"),
                                  np.zeros((n, 1), order="F"), np.zeros((1, n), order="F"),
                                  np.zeros((1, 1), order="F"), equil=equil, tol=thr)[2])
        if ours != (nrank == n):
            raise NumericallyUndecidableError(thr, d.nearest[1], ours, nrank == n, nrank)


def _deflate(p: Pencil, tol: float | None) -> Deflation:
    En, An = p.En, p.An
    n = En.shape[0]
    thr = float(tol) if tol is not None else max(RANK_RTOL, RANK_ATOL)
    W, V = np.eye(n), np.eye(n)
    Et, At = En.copy(), An.copy()
    m = n
    blocks: list[int] = []
    dropped = 0.0
    nearest = None  # (factor to the threshold, singular value) of the closest rank decision

    def near(values):
        nonlocal nearest
        for v in np.asarray(values, dtype=float):
            f = max(v / thr, thr / v) if v > 0 else np.inf
            if nearest is None or f < nearest[0]:
                nearest = (f, float(v))

    while m > 0:
        _, s, Vh = np.linalg.svd(Et[:m, :m])
        r = int(np.sum(s > thr))
        near(s)
        if r == m:
            break
        k = m - r
        Vs = Vh.T
        AV2 = At[:m, :m] @ Vs[:, r:]
        sv = np.linalg.svd(AV2, compute_uv=False)
        near(sv)
        if sv[-1] <= thr:
            why = (
                f"A annihilates a direction of ker E (smallest singular value {sv[-1]:.1e} of "
                f"A restricted to ker E, threshold {thr:.1e})"
                if not blocks
                else f"at deflation step {len(blocks) + 1} the reduced pencil has a direction "
                f"x with E11 x = A11 x = 0 (singular value {sv[-1]:.1e}, threshold {thr:.1e})"
            )
            return Deflation(W, V, Et, At, m, tuple(blocks), dropped, failed=why, nearest=nearest)
        Qf, _ = np.linalg.qr(AV2, mode="complete")
        Ws = np.hstack([Qf[:, k:], Qf[:, :k]])
        Et[:, :m] = Et[:, :m] @ Vs
        At[:, :m] = At[:, :m] @ Vs
        V[:, :m] = V[:, :m] @ Vs
        Et[:m, :] = Ws.T @ Et[:m, :]
        At[:m, :] = Ws.T @ At[:m, :]
        W[:, :m] = W[:, :m] @ Ws
        dropped = max(dropped, float(np.abs(Et[:m, r:m]).max()))
        if r:
            dropped = max(dropped, float(np.abs(At[:r, r:m]).max()))
        Et[:m, r:m] = 0.0
        At[:r, r:m] = 0.0
        blocks.append(k)
        m = r
    return Deflation(W, V, Et, At, m, tuple(blocks), dropped, nearest=nearest)


def irregular_error(fname: str, d: Deflation) -> IrregularSystemError:
    return IrregularSystemError(
        f"{fname}: the pencil sE - A is singular (det(sE - A) = 0 for every s): "
        f"{d.failed}. The descriptor system is irregular: its solutions are not unique (or "
        "do not exist), and its poles, Weierstrass form, stability and observability "
        "notions are undefined. Check the model: a missing or duplicated equation, or a "
        "state that appears in no equation, typically causes this. See fojax.analysis.is_regular."
    )


def require_regular(p: Pencil, fname: str, tol: float | None) -> Deflation:
    """The `Deflation` of a regular pencil; raises `IrregularSystemError` otherwise."""
    d = deflate(p, tol)
    if d.failed is not None:
        raise irregular_error(fname, d)
    return d


def block_toeplitz(En: np.ndarray, An: np.ndarray, k: int) -> np.ndarray:
    """The ``(k+1) n`` square block matrix with ``E`` on the diagonal and ``A`` below it.

    ``k = 1`` gives ``[[E, 0], [A, E]]``.
    """
    n = En.shape[0]
    T = np.zeros(((k + 1) * n, (k + 1) * n))
    for i in range(k + 1):
        T[i * n : (i + 1) * n, i * n : (i + 1) * n] = En
        if i < k:
            T[(i + 1) * n : (i + 2) * n, i * n : (i + 1) * n] = An
    return T


def kernel_chain(p: Pencil, tol: float | None, fname: str) -> tuple[int, int, int]:
    r"""``(n1, n2, index)`` of a regular pencil from ranks of block Toeplitz matrices.

    Not used by the public functions (they use `deflate`); kept as an independent
    cross-check for the tests.

    For a regular pencil with Weierstrass form ``(diag(I, N), diag(A1, I))`` the matrix
    $T_k$ of `block_toeplitz` has rank $(k+1)n - \dim\ker N^{k+1}$. The kernel dimensions
    $d_k = \dim\ker N^{k+1}$ increase strictly until $k + 1 = \nu$ (the nilpotency index)
    and are constant afterwards, with final value $n_2$. No inversion and no QZ is
    needed, which makes the count robust where QZ's infinite eigenvalues are perturbed.
    """
    n = p.n
    dims: list[int] = []
    for k in range(n + 1):
        d = (k + 1) * n - crank(block_toeplitz(p.En, p.An, k), tol)
        dims.append(d)
        if k == 0 and d == 0:
            return n, 0, 0
        if k > 0 and d == dims[-2]:
            if d > n:
                break
            return n - d, d, k
    raise IrregularSystemError(
        f"{fname}: the kernel dimensions {dims} of the block matrices [[E, 0], [A, E]], ... "
        "do not settle at a value <= n, which happens only for a (numerically) singular "
        "pencil. Check regularity with fojax.analysis.is_regular, or pass a larger tol=."
    )
