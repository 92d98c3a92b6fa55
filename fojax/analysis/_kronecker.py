r"""Kronecker structure, zeros, properness and mode counts (host-only; SLICOT ``AG08BD``).

The reference numerical library for these questions is SLICOT; fojax wraps its
``AG08BD`` (Van Dooren/Misra staircase reduction of the system pencil
$S(\lambda) = \begin{bmatrix}A - \lambda E & B\\ C & D\end{bmatrix}$, square or not)
through slycot, after fojax's own exact power-of-two balancing (`balance_system`) and
block normalisation (``E``, ``A``, ``B``, ``C`` each divided by its spectral norm; ``D``
by the matching factor, see `_normalised`), so that the rank decisions inside SLICOT do
not depend on units either. ``AG08BD``'s tolerance is passed as ``RANK_RTOL = 1e-10``:
SLICOT counts a rank when the estimated condition number of the leading triangular
factor stays below ``1 / RANK_RTOL`` — the same relative rule as fojax's SVD rank,
measured by a condition estimate instead of singular values.

The finite eigenvalues are the generalized eigenvalues (QZ) of the regular part that
``AG08BD`` extracts, multiplied back by the normalisation factor ``‖A‖/‖E‖``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla

from .._dtype import as_matrix, to_numpy
from .._errors import InputError
from .._linalg import RANK_RTOL
from ..plant import DescriptorSystem
from ._balance import Scaling
from ._common import _host, balanced_units


@dataclass(frozen=True)
class KroneckerStructure:
    r"""Kronecker canonical form data of a pencil $A - \lambda E$ (``l × n``, or of a system pencil).

    - `normal_rank`: rank of $A - \lambda E$ for generic $\lambda$.
    - `right_indices`: right (column) minimal indices $\varepsilon_i$ (blocks $L_{\varepsilon}$);
      one per dimension of the right null space over rational functions.
    - `left_indices`: left (row) minimal indices $\eta_i$ (blocks $L_{\eta}^T$).
    - `infinite_divisors`: sizes of the infinite elementary divisors (Jordan blocks at
      infinity; size 1 = a non-dynamic/static mode, size $k \ge 2$ = $k - 1$ impulsive modes).
    - `finite_eigenvalues`: eigenvalues of the regular part (sorted by real part).
    - `regular`: square and `normal_rank` equals the size (no minimal indices).
    - `scaling`: the balancing applied before the reduction.
    """

    shape: tuple
    normal_rank: int
    right_indices: tuple
    left_indices: tuple
    infinite_divisors: tuple
    finite_eigenvalues: np.ndarray
    scaling: Scaling

    @property
    def regular(self) -> bool:
        l, n = self.shape
        return l == n and self.normal_rank == n

    def __str__(self) -> str:
        def t(x):
            return ", ".join(str(int(v)) for v in x) if len(x) else "none"

        return (
            f"normal rank {self.normal_rank} of {self.shape[0]}x{self.shape[1]}; "
            f"right minimal indices [{t(self.right_indices)}]; left minimal indices "
            f"[{t(self.left_indices)}]; infinite elementary divisors of sizes "
            f"[{t(self.infinite_divisors)}]; {len(self.finite_eigenvalues)} finite eigenvalue(s)"
        )


@dataclass(frozen=True)
class SystemZeros:
    r"""Zeros of the system pencil $\begin{bmatrix}A - \lambda E & B\\ C & D\end{bmatrix}$.

    - `invariant_zeros`: its finite Smith zeros (sorted by real part). For a minimal
      realisation they are the transmission zeros of $G(s) = C(sE - A)^{-1}B + D$.
    - `infinite_zeros`: degrees of the infinite Smith zeros (one entry per zero).
    - `structure`: the full `KroneckerStructure` of the system pencil.
    """

    invariant_zeros: np.ndarray
    infinite_zeros: tuple
    structure: KroneckerStructure

    @property
    def normal_rank(self) -> int:
        return self.structure.normal_rank


def _sort(z: np.ndarray) -> np.ndarray:
    from ._pencil import _sort_poles

    return _sort_poles(np.asarray(z, dtype=complex))


def _ag08bd(E, A, B, C, D, tol: float | None):
    import slycot

    l, n = E.shape
    m, p = B.shape[1], C.shape[0]
    F = dict(order="F")
    Bp = np.array(B if m else np.zeros((l, 1)), **F)
    Cp = np.array(C if p else np.zeros((1, n)), **F)
    Dp = np.array(D if (m and p) else np.zeros((max(p, 1), max(m, 1))), **F)
    return slycot.ag08bd(
        l, n, m, p, np.array(A, **F), np.array(E, **F), Bp, Cp, Dp,
        equil="N", tol=float(RANK_RTOL if tol is None else tol),
    )  # fmt: skip


def _normalised(E, A, B, C, D, balance: bool):
    """Balanced, block-normalised data and the eigenvalue factor ``‖A‖/‖E‖``."""
    sc, ((En, e), (An, a), (Bn, b), (Cn, c)) = balanced_units(E, A, B, C, balance)
    # [An - mu En, Bn; Cn, Dn] = diag(I/a, I/c) [A - lam E, B; C, D] diag(I, a/b I), lam = mu a/e
    Dn = D * (a / (b * c)) if D.size else D
    return En, An, Bn, Cn, Dn, a / e, sc


def _structure(E, A, B, C, D, tol, balance) -> tuple[KroneckerStructure, tuple]:
    En, An, Bn, Cn, Dn, fac, sc = _normalised(E, A, B, C, D, balance)
    l, n = E.shape
    m, p = B.shape[1], C.shape[0]
    if l + p == 0 or n + m == 0:
        ks = KroneckerStructure((l + p, n + m), 0, (0,) * (n + m), (0,) * (l + p), (),
                                np.zeros(0, complex), sc)  # fmt: skip
        return ks, ()
    Af, Ef, nrank, _, infz, kronr, infe, kronl = _ag08bd(En, An, Bn, Cn, Dn, tol)
    z = sla.eigvals(Af, Ef) * fac if Af.size else np.zeros(0, complex)
    ks = KroneckerStructure(
        shape=(l + p, n + m),
        normal_rank=int(nrank),
        right_indices=tuple(int(v) for v in kronr),
        left_indices=tuple(int(v) for v in kronl),
        infinite_divisors=tuple(int(v) for v in infe),
        finite_eigenvalues=_sort(z),
        scaling=sc,
    )
    inf_zeros = tuple(d + 1 for d, k in enumerate(infz) for _ in range(int(k)))
    return ks, inf_zeros


def kronecker_structure(E, A, *, tol: float | None = None, balance: bool = True
                        ) -> KroneckerStructure:
    r"""Kronecker structure of the pencil $A - \lambda E$ (square or not, regular or not).

    Host-only; SLICOT ``AG08BD`` on the balanced, normalised pencil (see the module
    docs). A singular pencil gets its minimal indices instead of only "irregular".

    **Arguments:**

    - `E`, `A`: ``(l, n)`` matrices (a `fojax.DescriptorSystem` as `E` with ``A=None``
      uses its ``E``, ``A``).
    - `tol`: ``AG08BD``'s relative rank tolerance (default ``RANK_RTOL = 1e-10``).
    - `balance`: ``False`` skips the power-of-two balancing.

    **Returns:** a `KroneckerStructure`.
    """
    if isinstance(E, DescriptorSystem):
        if A is not None:
            raise InputError("kronecker_structure: pass a DescriptorSystem or (E, A), not both.")
        E, A = E.E, E.A
    E = to_numpy(as_matrix("E", _host("E", E)))
    A = to_numpy(as_matrix("A", _host("A", A), rows=E.shape[0], cols=E.shape[1],
                           hint="A must have the shape of E."))  # fmt: skip
    l, n = E.shape
    return _structure(E, A, np.zeros((l, 0)), np.zeros((0, n)), np.zeros((0, 0)), tol,
                      balance)[0]  # fmt: skip


def _system(sys, D, fname):
    if not isinstance(sys, DescriptorSystem):
        raise InputError(
            f"{fname} needs a fojax.DescriptorSystem (it uses B and C), got "
            f"{type(sys).__name__}. Build one with fojax.DescriptorSystem(E, A, B, C)."
        )
    E, A, B, C = (_host(k, getattr(sys, k)) for k in "EABC")
    p, m = C.shape[0], B.shape[1]
    if D is None:  # the system's own feedthrough
        D = _host("D", sys.D)
    else:
        D = to_numpy(as_matrix("D", D, rows=p, cols=m,
                               hint=f"D maps the {m} inputs to the {p} outputs."))  # fmt: skip
    return E, A, B, C, D


def system_zeros(sys: DescriptorSystem, D=None, *, tol: float | None = None,
                 balance: bool = True) -> SystemZeros:
    r"""Invariant zeros of $(E, A, B, C, D)$: the finite $\lambda$ where the system pencil
    $\begin{bmatrix}A - \lambda E & B\\ C & D\end{bmatrix}$ drops below its normal rank.

    Host-only; SLICOT ``AG08BD`` (see the module docs). The unknown-input observer
    conditions need them: with unknown-input directions as `B` and ``D = 0``, an observer
    with a stable error exists only if every invariant zero is stable.

    **Arguments:**

    - `sys`: a `fojax.DescriptorSystem` (``B`` ``(n, m)``, ``C`` ``(p, n)``).
    - `D`: the ``(p, m)`` feedthrough (default: the system's own, ``sys.D``).
    - `tol`, `balance`: as `kronecker_structure`.

    **Returns:** a `SystemZeros`.
    """
    E, A, B, C, D = _system(sys, D, "system_zeros")
    ks, inf_zeros = _structure(E, A, B, C, D, tol, balance)
    return SystemZeros(ks.finite_eigenvalues, inf_zeros, ks)


@dataclass(frozen=True)
class ModeCounts:
    r"""Counts of the modes of a regular descriptor system (Dai 1989).

    - `finite`: $\deg\det(sE - A)$ (dynamic modes); `nondynamic`: $n - \mathrm{rank}\,E$;
      `impulsive`: $\mathrm{rank}\,E - \deg\det(sE - A)$.
    - `uncontrollable`: finite modes that are input-decoupling zeros (the finite Smith
      zeros of $[A - \lambda E\;\; B]$), `unobservable`: the output-decoupling zeros
      (of $[A - \lambda E;\; C]$). Their values are in `uncontrollable_modes`,
      `unobservable_modes`.
    """

    finite: int
    nondynamic: int
    impulsive: int
    uncontrollable: int
    unobservable: int
    uncontrollable_modes: np.ndarray
    unobservable_modes: np.ndarray


def mode_counts(sys: DescriptorSystem, *, tol: float | None = None,
                balance: bool = True) -> ModeCounts:
    r"""Dynamic, non-dynamic, impulsive, uncontrollable and unobservable mode counts.

    Host-only. The dynamic/non-dynamic/impulsive counts come from the Kronecker structure
    of $(E, A)$, the decoupling zeros from ``AG08BD`` on $[A - \lambda E\;\; B]$ and
    $[A - \lambda E;\; C]$. For a singular pencil the counts of the regular part are given.
    """
    E, A, B, C, _ = _system(sys, None, "mode_counts")
    n = E.shape[0]
    ks = _structure(E, A, np.zeros((n, 0)), np.zeros((0, n)), np.zeros((0, 0)), tol, balance)[0]
    nfin = len(ks.finite_eigenvalues)
    ninf = int(sum(ks.infinite_divisors))
    nondyn = len(ks.infinite_divisors)
    uc = _structure(E, A, B, np.zeros((0, n)), np.zeros((0, B.shape[1])), tol, balance)[0]
    uo = _structure(E, A, np.zeros((n, 0)), C, np.zeros((C.shape[0], 0)), tol, balance)[0]
    return ModeCounts(
        finite=nfin,
        nondynamic=nondyn,
        impulsive=ninf - nondyn,
        uncontrollable=len(uc.finite_eigenvalues),
        unobservable=len(uo.finite_eigenvalues),
        uncontrollable_modes=uc.finite_eigenvalues,
        unobservable_modes=uo.finite_eigenvalues,
    )


@dataclass(frozen=True)
class Properness:
    r"""Whether $G(s) = C(sE - A)^{-1}B + D$ is proper (bounded as $s \to \infty$).

    With the Weierstrass form, $G(s) = C_1(sI - A_1)^{-1}B_1 + D - \sum_{k \ge 0}
    s^k C_2 N^k B_2$; `markov` holds $\|C_2 N^k B_2\|$ for $k = 1, \dots, \nu - 1$ and
    `reference` the matching $\|C_2\|\,\|N\|^k\,\|B_2\|$. A term counts as zero when it is
    at most ``RANK_RTOL`` times its reference (the fojax relative rule); `proper` is
    ``True`` when every term does.
    """

    proper: bool
    markov: tuple
    reference: tuple


def properness(sys: DescriptorSystem, *, tol: float | None = None,
               balance: bool = True) -> Properness:
    r"""Properness of the transfer function of a regular system (host-only).

    Uses `fojax.analysis.weierstrass_form` (balanced, the fojax rank rule); see `Properness`.
    ``D`` does not affect properness. Raises `fojax.errors.IrregularSystemError` for a singular
    pencil (no transfer function).
    """
    from ._common import as_system, require_regular
    from ._weierstrass import weierstrass_form

    _system(sys, None, "properness")
    if require_regular(as_system(sys, "properness", balance), "properness", tol).index <= 1:
        return Properness(True, (), ())  # N = 0: no polynomial part
    w = weierstrass_form(sys, tol=tol, balance=balance)
    mk, ref = [], []
    if w.n2:
        nN = float(np.linalg.norm(w.N, 2))
        nB = float(np.linalg.norm(w.B2, 2))
        nC = float(np.linalg.norm(w.C2, 2))
        Nk = np.eye(w.n2)
        for k in range(1, max(w.index, 1)):
            Nk = Nk @ w.N
            mk.append(float(np.linalg.norm(w.C2 @ Nk @ w.B2, 2)))
            ref.append(nC * nN**k * nB)
    proper = all(v <= RANK_RTOL * r for v, r in zip(mk, ref))
    return Properness(proper, tuple(mk), tuple(ref))
