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

**Factors.** For pencils, Ward's (1981) balancing: the exponents minimise
$\sum (\ell_i + r_j + \log_2|x_{ij}|)^2$ over the non-zero entries of ``E``, ``A``, ``B``,
``C``, solved exactly as a least-squares problem in NumPy (`_ward_exponents`) and rounded
to integers. This is the objective SLICOT ``TG01AD`` targets; fojax does not use
``TG01AD``'s factors because they are rounded to powers of **ten** (adding rounding) and
decide the structure of scaled systems less reliably than the exact least-squares
exponents (`tests/test_analysis_scaling.py` compares the two on systems with exactly known
structure). The least squares also has one free offset per block (see
`_ward_exponents`), which keeps ``C`` in huge units or ``E`` in tiny ones from pulling
the exponents, and weights ``B`` and ``C`` less than the pencil (`IO_WEIGHT`); the free
common shifts keep every block's largest entry near 1 (`_gauge`), so that no scaled
entry overflows. `tg01ad_scaling` keeps SLICOT's factors for
the cross-check in the tests. When ``E = I`` exactly, SLICOT ``TB01ID`` (balancing of
the state matrix with ``B``, ``C``: the similarity $D^{-1} A D$, as LAPACK ``gebal``
does for ``numpy.linalg.eigvals``) is used, its factors rounded to powers of two, so that
``E`` stays the identity: ``D_l = D^{-1}``, ``D_r = D``.

``balance=False`` (a keyword of every host analysis function) skips this step; the
`Scaling` then has all exponents zero and ``method = "none"``.
"""

from __future__ import annotations

import collections
import hashlib
import threading
from dataclasses import dataclass

import numpy as np


#: Largest |exponent| applied: float64 data span 2^-1074..2^1024, so no balancing of
#: finite data needs more. Scaled matrices are formed with `numpy.ldexp` of the summed
#: row and column exponents (no intermediate product can overflow), and the free common
#: shifts are chosen to keep every block's largest entry near 1 (`_gauge`).
_MAX_EXP = 2100


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

    def rows(self, M) -> np.ndarray:
        """``D_l M`` (exact; no intermediate overflow)."""
        M = np.asarray(M, dtype=float)
        return np.ldexp(M, self.row_exponents.reshape((-1,) + (1,) * (M.ndim - 1)))

    def cols(self, M) -> np.ndarray:
        """``M D_r`` (exact; no intermediate overflow)."""
        return np.ldexp(np.asarray(M, dtype=float), self.col_exponents)

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
    if l == n and np.array_equal(E, np.eye(n)):
        # TB01ID gets A, B, C each pre-scaled by a power of two to max |entry| in [1, 2)
        # (SLICOT sums squares and would overflow near 1e300); the factors are applied to
        # the raw data, so the result is an exact similarity whatever found them.
        A, B, C = (_unit2(M) for M in (A, B, C))
        job = "A" if (m and p) else ("B" if m else ("C" if p else "N"))
        _, _, _, _, d = slycot.tb01id(
            n, max(m, 1), max(p, 1), 0.0, np.array(A, order="F"),
            np.array(B if m else np.zeros((n, 1)), order="F"),
            np.array(C if p else np.zeros((1, n)), order="F"), job=job,
        )  # fmt: skip
        e = _exponents(d)
        return Scaling(-e, e, "tb01id")
    el, er = _ward_exponents(E, A, B, C, io_weight=IO_WEIGHT)
    c1, c2 = _gauge(el, er, E, A, B, C)
    return Scaling(el + c1, er + c2, "ward")


def _log2_max(M, rows=None, cols=None) -> float | None:
    """``max log2 |M_ij| + rows_i + cols_j`` over the non-zero entries (``None``: no entry)."""
    a = np.abs(np.asarray(M, dtype=float))
    if not a.size or not np.any(a):
        return None
    lg = np.where(a > 0, np.log2(np.where(a > 0, a, 1.0)), -np.inf)
    if rows is not None:
        lg = lg + rows[:, None]
    if cols is not None:
        lg = lg + cols[None, :]
    return float(lg.max())


def _gauge(el, er, E, A, B, C) -> tuple[int, int]:
    r"""The common shifts ``(c1, c2)`` of the row and column exponents (Ward's least squares
    leaves them free: they multiply ``E``, ``A`` by $2^{c_1 + c_2}$, ``B`` by $2^{c_1}$, ``C``
    by $2^{c_2}$, which the analysis's per-block normalisation removes) that minimise the
    largest $|\log_2|$ of each block's largest scaled entry, so that no block overflows
    or drops into subnormal numbers when scaled (a small linear program; integers)."""
    from scipy.optimize import linprog

    m_ea = [v for v in (_log2_max(E, el, er), _log2_max(A, el, er)) if v is not None]
    terms = []  # (coefficient of c1, of c2, constant)
    if m_ea:
        terms.append((1.0, 1.0, max(m_ea)))
    mb, mc = _log2_max(B, el), _log2_max(C, None, er)
    if mb is not None:
        terms.append((1.0, 0.0, mb))
    if mc is not None:
        terms.append((0.0, 1.0, mc))
    if not terms:
        return 0, 0
    # min t  s.t.  ±(a c1 + b c2 + m) <= t
    A_ub, b_ub = [], []
    for a, b, m in terms:
        A_ub += [[a, b, -1.0], [-a, -b, -1.0]]
        b_ub += [-m, m]
    res = linprog([0.0, 0.0, 1.0], A_ub=A_ub, b_ub=b_ub, bounds=[(None, None)] * 3, method="highs")
    if not res.success:
        return 0, 0
    # among optimal shifts prefer the smallest (the min-norm solution's own scaling)
    c1, c2 = (int(np.rint(v)) for v in res.x[:2])
    return c1, c2


#: Weight of the ``B`` and ``C`` entries in the least squares of `scaling_of` (``E``, ``A``:
#: 1). The pencil's verdicts (regularity, rank E, index, poles) depend on ``E`` and ``A``
#: only; with equal weights, rows of ``B`` (columns of ``C``) whose sizes disagree with
#: those of ``E`` and ``A`` by hundreds of orders of magnitude pulled the balancing of the
#: pencil off, and a regular pencil was called singular.
IO_WEIGHT = 1e-3


def _log2_unit(M) -> np.ndarray:
    """``log2 |M| - log2 max |M|`` entrywise (``-inf`` at zeros)."""
    a = np.abs(M)
    top = a.max(initial=0.0)
    if top == 0:
        return np.full(a.shape, -np.inf)
    with np.errstate(divide="ignore"):
        return np.log2(a) - np.log2(top)


def _ward_exponents(E, A, B, C, *, rounded: bool = True, io_weight: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    r"""Ward's (1981) balancing as an exact least-squares problem, rounded to powers of two.

    Minimise $\sum (\ell_i + r_j + o_X + \log_2|x_{ij}|)^2$ over the non-zero entries
    $x_{ij}$ of each block $X$ = ``E``, ``A`` (row ``i``, column ``j``), ``B`` (no $r_j$)
    and ``C`` (no $\ell_i$), with one free offset $o_X$ per block (the terms of ``B`` and ``C``
    weighted by `io_weight`; `scaling_of` uses `IO_WEIGHT`). The offsets make the
    exponents independent of the scale of each block, which the analysis removes anyway
    (each block is divided by its norm): so ``C`` in huge units or ``E`` in tiny ones
    does not pull the states' exponents. Exact zeros are left out and so are round-off
    entries: at most ``2^-52 max(l, n)`` times the largest entry of both their row and
    their column within the block, or within the pencil ``[E, A]`` with each block divided
    by its largest entry (a row or column of ``E`` can be round-off as a whole where ``A``
    holds the data; a threshold relative to the whole block would drop the
    small entries of a badly scaled model, the ones balancing must see; one relative to
    the row and the column keeps most of them, since an exact scaling changes a row and a
    column together). This is a heuristic: no rule tells round-off from a genuinely tiny
    entry in general; `tests/test_analysis_scaling.py` measures it on both kinds. The normal equations (size ``l + n + 4``) are
    solved for their minimum-norm solution (symmetric eigen-decomposition; the minimum
    norm fixes the free common shifts).
    """
    l, n = E.shape
    N = l + n + 4
    G = np.zeros((N, N))
    rhs = np.zeros(N)
    L, R = slice(0, l), slice(l, l + n)

    tau = 2.0**-52 * max(l, n, 1)
    # the pencil [E, A] with each block divided by its largest entry: its row and column
    # maxima tell round-off in a block whose whole row or column is round-off (a column of
    # E holding 1e-17 where A holds 1), which the block's own maxima cannot
    # (in log2, so that 1e-300 next to 1e300 does not underflow)
    pencil = np.maximum(*(_log2_unit(M) for M in (E, A))) if E.size else None

    def nz(M):
        # Round-off entries (at most tau times the largest entry of BOTH their row and
        # their column in the block, or in the normalised pencil [E, A], e.g. 1e-19 next
        # to 1e4 left by a product that should be zero) are left out: balancing would blow
        # them up to the size of the data.
        a = np.abs(M)
        rmax = a.max(axis=1, keepdims=True)
        cmax = a.max(axis=0, keepdims=True)
        mask = (a > tau * rmax) | (a > tau * cmax) if M.ndim == 2 and M.size else a > 0
        if (M is E or M is A) and pencil is not None:
            u = _log2_unit(M) - np.log2(tau)
            mask &= (u > pencil.max(axis=1, keepdims=True)) | (u > pencil.max(axis=0, keepdims=True))
        mask &= a > 0
        lg = np.where(mask, np.log2(np.where(mask, np.abs(M), 1.0)), 0.0)
        return mask.astype(float), lg

    for o, M in enumerate((E, A, B, C)):
        if not M.size:
            continue
        k, lg = nz(M)
        if o >= 2:  # B, C
            k, lg = io_weight * k, io_weight * lg
        o = l + n + o
        G[o, o] += k.sum()
        rhs[o] -= lg.sum()
        if M is not C:  # rows are equations
            G[L, L] += np.diag(k.sum(1))
            G[L, o] += k.sum(1)
            G[o, L] += k.sum(1)
            rhs[L] -= lg.sum(1)
        if M is not B:  # columns are states
            G[R, R] += np.diag(k.sum(0))
            G[R, o] += k.sum(0)
            G[o, R] += k.sum(0)
            rhs[R] -= lg.sum(0)
        if M is E or M is A:
            G[L, R] += k
            G[R, L] += k.T
    # Minimum-norm solution through the eigen-decomposition of the symmetric PSD G
    # (the null directions are the free common shifts).
    w, V = np.linalg.eigh(G)
    keep = w > 1e-9 * max(float(w[-1]), 1.0)
    x = V[:, keep] @ ((V[:, keep].T @ rhs) / w[keep])
    if not rounded:
        e = np.clip(x[: l + n], -_MAX_EXP, _MAX_EXP)
        return e[:l], e[l:]
    e = np.clip(np.rint(x[: l + n]), -_MAX_EXP, _MAX_EXP).astype(int)
    return e[:l], e[l:]


#: Models whose `unit_scaling` is kept (least recently used dropped first).
_UNIT_SCALING_KEEP = 32
_UNIT_SCALINGS: collections.OrderedDict = collections.OrderedDict()
_UNIT_SCALINGS_LOCK = threading.Lock()


def unit_scaling(E, A, B=None, C=None) -> tuple[np.ndarray, np.ndarray]:
    r"""Diagonal factors ``(d_l, d_r)`` that remove the units of the equations and states.

    Host-only. Ward's least squares of `_ward_exponents` *without* rounding the exponents
    to integers, so that the scaled system $(D_lED_r, D_lAD_r, D_lB, CD_r)$ is the same
    (up to round-off) whatever diagonal units the equations and states were written in:

    *Equivariance (derivation).* Writing the model in other units, $E' = S_rES_c$,
    $A' = S_rAS_c$, $B' = S_rB$, $C' = CS_c$ ($S_r, S_c$ positive diagonal), adds
    $\log_2 s_{r,i} + \log_2 s_{c,j}$ to every $\log_2|x_{ij}|$; the least-squares objective
    is then the old one at $\ell - \log_2 s_r$, $r - \log_2 s_c$, so the set of minimisers
    shifts by exactly that. What it leaves free (the null space of the normal equations,
    which the minimum-norm solution fixes in a unit-dependent way) are, for a connected
    pattern of $(E, A)$, the two gauges $\ell + c_1$ and $r + c_2$ (the per-block offsets
    absorb them): they multiply $D_lED_r$ and $D_lAD_r$ by $2^{c_1 + c_2}$, $D_lB$ by
    $2^{c_1}$ and $CD_r$ by $2^{c_2}$. fojax fixes them by two statements about the scaled
    matrices only, so unit-free too: $\max(|D_lED_r|, |D_lAD_r|) = 1$ and
    $\max|D_lB| = \max|CD_r|$ (the second skipped when ``B`` or ``C`` is zero). A pattern
    of $(E, A)$ that falls into several uncoupled blocks has one more such gauge per block,
    not fixed here. The factors are not powers of two: applying them rounds (≈1e-16
    relative per entry), which is why the rank decisions of `fojax.analysis` keep the exact
    power-of-two `scaling_of`; these factors are for *choices* (the default ``R``, the LMI's
    coordinates) that must not depend on units
    (`fojax.design.design_functional_observer`'s ``balance``).

    **Returns:** ``(d_l, d_r)``, positive ``(l,)`` and ``(n,)`` arrays (ones when `E` and `A`
    are zero or empty).

    Computed once per model (`_UNIT_SCALING_KEEP` models kept, keyed by the matrices' bytes
    and shapes; each call returns fresh copies): `fojax.design.certify` checks every tuning
    iterate in the unit-free frame, on the same model each time.
    """
    E = np.asarray(E, dtype=float)
    A = np.asarray(A, dtype=float)
    l, n = E.shape
    B = np.zeros((l, 0)) if B is None else np.asarray(B, dtype=float)
    C = np.zeros((0, n)) if C is None else np.asarray(C, dtype=float)
    digest = hashlib.sha256()
    for x in (E, A, B, C):
        digest.update(repr(x.shape).encode())
        digest.update(np.ascontiguousarray(x).tobytes())
    key = digest.hexdigest()
    with _UNIT_SCALINGS_LOCK:
        found = _UNIT_SCALINGS.get(key)
        if found is not None:
            _UNIT_SCALINGS.move_to_end(key)
    if found is None:  # computed outside the lock
        found = _unit_scaling(E, A, B, C)
        with _UNIT_SCALINGS_LOCK:
            _UNIT_SCALINGS[key] = found
            while len(_UNIT_SCALINGS) > _UNIT_SCALING_KEEP:
                _UNIT_SCALINGS.popitem(last=False)
    return found[0].copy(), found[1].copy()


def _unit_scaling(E, A, B, C) -> tuple[np.ndarray, np.ndarray]:
    """`unit_scaling` of float arrays ``(E, A, B, C)`` (``B``, ``C`` possibly empty), computed."""
    l, n = E.shape
    if l == 0 or n == 0 or not (np.any(A) or np.any(E)):
        return np.ones(l), np.ones(n)
    el, er = _ward_exponents(E, A, B, C, rounded=False)
    dl, dr = 2.0**el, 2.0**er
    # gauges (docstring): c1 + c2 from max |[E A]| = 1, c1 - c2 from max |B| = max |C|
    s = -np.log2(max(float(np.max(np.abs(dl[:, None] * M * dr[None, :]), initial=0.0)) for M in (E, A)))
    bmax = float(np.max(np.abs(dl[:, None] * B), initial=0.0))
    cmax = float(np.max(np.abs(C * dr[None, :]), initial=0.0))
    d = np.log2(cmax) - np.log2(bmax) if (bmax > 0 and cmax > 0) else 0.0
    return dl * 2.0 ** (0.5 * (s + d)), dr * 2.0 ** (0.5 * (s - d))


def tg01ad_scaling(E, A, B=None, C=None) -> Scaling:
    """SLICOT ``TG01AD``'s factors rounded to powers of two (kept as a cross-check of
    `_ward_exponents` in the tests; not used by the analysis, see the module docs)."""
    import slycot

    E, A = np.asarray(E, dtype=float), np.asarray(A, dtype=float)
    l, n = E.shape
    B = np.zeros((l, 0)) if B is None else np.asarray(B, dtype=float)
    C = np.zeros((0, n)) if C is None else np.asarray(C, dtype=float)
    m, p = B.shape[1], C.shape[0]
    job = "A" if (m and p) else ("B" if m else ("C" if p else "N"))
    out = slycot.tg01ad(
        l, n, m, p, np.array(A, order="F"), np.array(E, order="F"),
        np.array(B if m else np.zeros((l, 1)), order="F"),
        np.array(C if p else np.zeros((1, n)), order="F"), job=job,
    )  # fmt: skip
    return Scaling(_exponents(out[4]), _exponents(out[5]), "tg01ad")


def apply_scaling(s: Scaling, E, A, B=None, C=None):
    """``(D_l E D_r, D_l A D_r, D_l B, C D_r)`` (exact: powers of two, each entry scaled by
    the sum of its row and column exponents, so no intermediate product overflows).

    Raises `fojax.errors.DataRangeError` naming the matrix when a scaled entry would not be a
    finite float64 (balanced data outside ``2^±1024``)."""
    from .._errors import DataRangeError

    both = s.row_exponents[:, None] + s.col_exponents[None, :]
    with np.errstate(over="ignore"):  # checked below
        out = [np.ldexp(np.asarray(E, dtype=float), both), np.ldexp(np.asarray(A, dtype=float), both),
               None if B is None else s.rows(B), None if C is None else s.cols(C)]
    for name, M, X in zip("EABC", (E, A, B, C), out):
        if X is not None and not np.all(np.isfinite(X)) and np.all(np.isfinite(np.asarray(M, dtype=float))):
            raise DataRangeError(name, float(np.max(np.abs(np.asarray(M, dtype=float)))),
                                 (2.0**-1074, float(np.finfo(float).max)), "balancing")
    return tuple(out)


def scale_model(dl, dr, E, A, B=None, C=None):
    """``(D_l E D_r, D_l A D_r, D_l B, C D_r)`` for row factors `dl` ``(l,)`` and state factors
    `dr` ``(n,)`` (`None` for a `B` or `C` not given). `A` and `B` may carry a leading rule
    axis (Takagi–Sugeno: ``(r, l, n)``, ``(r, l, m)``). The one place where a model is
    rescaled: `apply_scaling` (the exact powers of two of the rank decisions) and the
    unit-free frame of `unit_scaling` (the design's ``balance``) both call it."""
    dl, dr = np.asarray(dl, dtype=float), np.asarray(dr, dtype=float)
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
