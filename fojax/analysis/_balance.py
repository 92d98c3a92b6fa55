r"""Balancing of descriptor systems by exact power-of-two diagonal scaling (host-only).

Every host rank decision and eigenvalue computation of `fojax.analysis` (and so of the
design layer, which calls it) runs on the balanced system

$$(D_l E D_r,\; D_l A D_r,\; D_l B,\; C D_r),\qquad
  D_l = \mathrm{diag}(2^{\ell_i}),\; D_r = \mathrm{diag}(2^{r_j}),$$

a strict equivalence of the system pencil
$\begin{bmatrix}A - sE & B\\ C & 0\end{bmatrix}$. It changes no rank of any matrix built
from it (every test of fojax multiplies rows and columns by $D_l$, $D_r$), no finite
or infinite eigenvalue, no Kronecker index and no zero; and since the factors are powers
of two it is *exact* in floating point: no rounding is added. What it changes is the
size of the entries: after balancing, rows and columns of the system pencil have
comparable norms, so the single relative rank tolerance of `fojax._linalg` no longer
depends on the units in which the equations and the states are written.

**Factors.** SLICOT ``TG01AD`` (Ward 1981's algorithm for pencils; slycot wrapper)
computes ``lscale``, ``rscale``; SLICOT rounds them to powers of **ten**, which would add
rounding, so fojax rounds their base-2 logarithms to the nearest integer (a deviation from
SLICOT, documented here; the balancing quality is the same within a factor ``√10``).
When ``E = I`` exactly, SLICOT ``TB01ID`` (balancing of the state matrix, the similarity
$D^{-1} A D$, as LAPACK ``gebal`` does for ``numpy.linalg.eigvals``) is used instead, so
that ``E`` stays the identity: ``D_l = D^{-1}``, ``D_r = D``.

``balance=False`` (a keyword of every host analysis function) skips this step; the
`Scaling` then has all exponents zero and ``method = "none"``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


#: Largest |exponent| applied. Balancing never needs more for float64 data that fojax
#: accepts (entries within 2^±1000); the cap only guards against overflow.
_MAX_EXP = 900


@dataclass(frozen=True)
class Scaling:
    r"""The exact diagonal scaling applied before the rank decisions.

    ``D_l = diag(2**row_exponents)`` multiplies the equations (rows of ``E``, ``A``,
    ``B``), ``D_r = diag(2**col_exponents)`` the states (columns of ``E``, ``A``, ``C``):
    the analysed system is ``(D_l E D_r, D_l A D_r, D_l B, C D_r)``; its state is
    ``D_r^{-1} x``. `method` is ``"tg01ad"``, ``"tb01id"`` (``E = I``) or ``"none"``.
    """

    row_exponents: np.ndarray
    col_exponents: np.ndarray
    method: str

    @property
    def left(self) -> np.ndarray:
        """The diagonal of ``D_l`` (powers of two)."""
        return np.ldexp(1.0, self.row_exponents)

    @property
    def right(self) -> np.ndarray:
        """The diagonal of ``D_r`` (powers of two)."""
        return np.ldexp(1.0, self.col_exponents)

    @property
    def identity(self) -> bool:
        return not (np.any(self.row_exponents) or np.any(self.col_exponents))

    def __str__(self) -> str:
        if self.identity:
            return f"none ({self.method})"

        def rng(e):
            return f"2^{int(e.min())}..2^{int(e.max())}" if e.size else "-"

        return (
            f"{self.method}: equations x {rng(self.row_exponents)}, "
            f"states x {rng(self.col_exponents)}"
        )


def _exponents(scale: np.ndarray) -> np.ndarray:
    s = np.asarray(scale, dtype=float)
    ok = np.isfinite(s) & (s > 0)
    e = np.where(ok, np.rint(np.log2(np.where(ok, s, 1.0))), 0.0)
    return np.clip(e, -_MAX_EXP, _MAX_EXP).astype(int)


def _unit2(M: np.ndarray) -> np.ndarray:
    mx = float(np.max(np.abs(M), initial=0.0))
    if mx == 0.0 or not np.isfinite(mx):
        return M
    return np.ldexp(M, -int(np.frexp(mx)[1] - 1))


def _none(n_rows: int, n_cols: int) -> Scaling:
    return Scaling(np.zeros(n_rows, dtype=int), np.zeros(n_cols, dtype=int), "none")


def scaling_of(E, A, B=None, C=None, *, balance: bool = True) -> Scaling:
    r"""The power-of-two `Scaling` that balances $(E, A, B, C)$ (host-only).

    `E`, `A` are ``(l, n)`` (square or not), `B` ``(l, m)``, `C` ``(p, n)`` (``None`` =
    empty). Zero-size or all-zero data, and ``balance=False``, give the identity scaling.
    """
    import slycot

    E = np.asarray(E, dtype=float)
    A = np.asarray(A, dtype=float)
    l, n = E.shape
    B = np.zeros((l, 0)) if B is None else np.asarray(B, dtype=float)
    C = np.zeros((0, n)) if C is None else np.asarray(C, dtype=float)
    m, p = B.shape[1], C.shape[0]
    if not balance or l == 0 or n == 0:
        return _none(l, n)
    if not (np.any(A) or np.any(E)):
        return _none(l, n)
    # The factors are computed on the blocks each pre-scaled by a power of two to max |entry|
    # in [1, 2) (SLICOT sums squares and would overflow near 1e300); they are then applied
    # to the raw data, so the result is an exact equivalence whatever found the factors.
    E, A, B, C = (_unit2(M) for M in (E, A, B, C))
    if l == n and np.array_equal(E, np.eye(n)):
        job = "A" if (m and p) else ("B" if m else ("C" if p else "N"))
        _, _, _, _, d = slycot.tb01id(
            n, max(m, 1), max(p, 1), 0.0, np.array(A, order="F"),
            np.array(B if m else np.zeros((n, 1)), order="F"),
            np.array(C if p else np.zeros((1, n)), order="F"), job=job,
        )  # fmt: skip
        e = _exponents(d)
        return Scaling(-e, e, "tb01id")
    job = "A" if (m and p) else ("B" if m else ("C" if p else "N"))
    out = slycot.tg01ad(
        l, n, m, p, np.array(A, order="F"), np.array(E, order="F"),
        np.array(B if m else np.zeros((l, 1)), order="F"),
        np.array(C if p else np.zeros((1, n)), order="F"), job=job,
    )  # fmt: skip
    return Scaling(_exponents(out[4]), _exponents(out[5]), "tg01ad")


def apply_scaling(s: Scaling, E, A, B=None, C=None):
    """``(D_l E D_r, D_l A D_r, D_l B, C D_r)`` (exact: powers of two)."""
    dl, dr = s.left, s.right
    E = np.asarray(E, dtype=float)
    A = np.asarray(A, dtype=float)
    out = [dl[:, None] * E * dr[None, :], dl[:, None] * A * dr[None, :]]
    out.append(None if B is None else dl[:, None] * np.asarray(B, dtype=float))
    out.append(None if C is None else np.asarray(C, dtype=float) * dr[None, :])
    return tuple(out)


@dataclass(frozen=True)
class Balancing:
    """A balanced system and its `Scaling` (the result of `balance_system`)."""

    E: np.ndarray
    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    scaling: Scaling


def balance_system(sys, A=None, *, balance: bool = True) -> Balancing:
    r"""Balance a descriptor system (or a pencil) by exact power-of-two diagonal scaling.

    Host-only. The matrices every analysis function works on; see the module docs of
    `fojax.analysis._balance` for the method (SLICOT ``TG01AD``/``TB01ID`` factors rounded
    to powers of two).

    **Arguments:**

    - `sys`: a `fojax.DescriptorSystem`, or the matrix ``E`` (``(l, n)``, square or not)
      when `A` is given.
    - `A`: the matrix ``A`` when `sys` is ``E``.
    - `balance`: ``False`` returns the data unchanged with the identity scaling.

    **Returns:** a `Balancing` with ``E``, ``A``, ``B``, ``C`` (``B``/``C`` empty for a
    pencil) and the `Scaling`.
    """
    from .._dtype import as_matrix, to_numpy
    from ..plant import DescriptorSystem

    if isinstance(sys, DescriptorSystem):
        E, A_, B, C = (to_numpy(M) for M in (sys.E, sys.A, sys.B, sys.C))
    else:
        E = to_numpy(as_matrix("E", sys))
        A_ = to_numpy(as_matrix("A", A, rows=E.shape[0], cols=E.shape[1],
                                hint="A must have the shape of E."))
        B, C = np.zeros((E.shape[0], 0)), np.zeros((0, E.shape[1]))
    s = scaling_of(E, A_, B, C, balance=balance)
    Eb, Ab, Bb, Cb = apply_scaling(s, E, A_, B, C)
    return Balancing(Eb, Ab, Bb, Cb, s)
