r"""Properties of the pencil $sE - A$: regularity, poles, impulses, stability, admissibility.

All functions here are **host-only** (NumPy/SciPy; rank decisions and QZ cannot be
traced). For screening inside `jax.jit`/`jax.vmap` see `fojax.analysis._traced`.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg as sla

from .._dtype import as_matrix, to_numpy
from .._errors import IrregularSystemError
from .._linalg import left_null_space
from ..plant import DescriptorSystem
from ._balance import apply_scaling, scaling_of
from ._common import _unit, as_pencil, deflate, Deflation, Pencil, require_regular
from ._discrete import unstable_mask


#: Default tolerance of `is_stable`: a pole counts as on the imaginary axis (hence not
#: stable) when ``Re λ >= -margin - AXIS_TOL * max(1, |λ|)``.
AXIS_TOL = 1e-9


def e_perp(E, tol: float | None = None, *, balance: bool = True, D=None) -> np.ndarray:
    r"""The thesis's $E^\perp$: orthonormal rows spanning the left null space of `E`.

    $E^\perp E = 0$ and $E^\perp (E^\perp)^T = I$. Host-only (SVD with a rank decision).

    **Arguments:**

    - `E`: an ``(n, n)`` matrix, or a `fojax.DescriptorSystem` (its ``E`` is used).
    - `tol`: absolute singular-value threshold overriding the fojax rank tolerance
      (``max(RANK_RTOL * s_max, RANK_ATOL)``, see `fojax._linalg`), applied to the
      balanced ``E``.
    - `balance`: the rank of ``E`` is decided on ``D_l E D_r`` (exact powers of two,
      `balance_system`); the null space found there is mapped back (``N D_l``, then
      orthonormalised: still ``E⊥ E = 0``). ``False`` decides on the raw ``E``.
    - `D`: ``(n, l)`` unknown-input directions: the rows then span the left null space of
      $[E\;D]$ (the unknown-input observer's annihilator), decided on
      ``[D_l E D_r / ‖·‖, D_l D / ‖·‖]`` (each block balanced and divided by its norm, as
      `fojax.analysis.functional_rank_pair` does).

    **Returns:** a float64 NumPy array of shape ``(n - rank E, n)`` (``n - rank [E D]``
    with `D`); ``(0, n)`` when `E` is invertible (and ``(0, 0)`` when ``n = 0``).
    """
    if isinstance(E, DescriptorSystem):
        E = E.E
    E = to_numpy(as_matrix("E", E))
    sc = scaling_of(E, np.zeros_like(E), balance=balance)
    if D is not None:
        D = to_numpy(as_matrix("D", D, rows=E.shape[0]))
        Eb = E if sc.identity else apply_scaling(sc, E, E)[0]
        Db = D if sc.identity else sc.left[:, None] * D
        K = np.hstack([_unit(Eb)[0], _unit(Db)[0]])
        Nb = left_null_space(K, tol)
        if sc.identity or Nb.shape[0] == 0:
            return Nb
    elif sc.identity:
        return left_null_space(E, tol)
    else:
        Nb = left_null_space(apply_scaling(sc, E, E)[0], tol)
        if Nb.shape[0] == 0:
            return Nb
    dl = sc.left
    Q, _ = np.linalg.qr((Nb * dl[None, :]).T)
    return Q.T.copy()


def algebraic_channel(E, W, Eperp=None, tol: float | None = None, *, balance: bool = True) -> np.ndarray:
    r"""$E^\perp W$, the part of the input matrix `W` that enters the algebraic equations, with
    its round-off removed by fojax's one rank rule.

    Its rank is $k = \operatorname{rank}[E\;W] - \operatorname{rank}E$, decided as `e_perp`
    decides with ``D=W``: on ``[D_l E D_r / ‖·‖, D_l W / ‖·‖]`` (the exact power-of-two
    balancing of `E`, each block divided by its norm), so the decision does not change when
    the equations are multiplied by a diagonal or an orthogonal matrix or the states by a
    diagonal one. The result is the best rank-$k$ approximation of $E^\perp W$ (its $k$
    leading singular triples): exactly zero when `W` lies in the range of `E` (a
    disturbance on the differential equations only), where the product itself would be
    round-off of order $10^{-16}\|W\|$ in directions that depend on the coordinates.

    **Arguments:**

    - `E`: ``(n, n)``; `W`: ``(n, m)``.
    - `Eperp`: the $E^\perp$ to multiply by (default `e_perp` of `E`).
    - `tol`, `balance`: as for `e_perp`.

    **Returns:** ``(n - rank E, m)``.
    """
    E = to_numpy(as_matrix("E", E))
    W = to_numpy(as_matrix("W", W, rows=E.shape[0]))
    Ep = e_perp(E, tol, balance=balance) if Eperp is None else np.asarray(Eperp, dtype=float)
    out = Ep @ W
    if out.size == 0 or not np.any(out):
        return out
    k = Ep.shape[0] - e_perp(E, tol, balance=balance, D=W).shape[0]
    if k >= min(out.shape):
        return out
    U, sv, Vt = np.linalg.svd(out, full_matrices=False)
    return (U[:, :k] * sv[:k]) @ Vt[:k]


def is_regular(sys, A=None, *, tol: float | None = None, balance: bool = True) -> bool:
    r"""Whether the pencil is regular: $\det(sE - A) \not\equiv 0$ (thesis Def. 2.1.1).

    Host-only. Decided by the orthogonal deflation of the infinite eigenvalues
    (Van Dooren 1979): repeatedly split off $\ker E_{11}$ of the remaining leading block;
    the pencil is singular iff at some step $A_{11}$ annihilates a direction of
    $\ker E_{11}$ (then $\det(sE - A) \equiv 0$), regular iff the process ends with an
    invertible $E_{11}$. Rank decisions on the normalised pencil $(E/\|E\|, A/\|A\|)$:
    singular values above ``max(RANK_RTOL, RANK_ATOL) = 1e-10`` count (or above `tol`).
    The same deflation feeds `finite_poles`, `nilpotency_index`, `is_impulse_free` and
    `weierstrass_form`, so all of them take the same decisions. For a traceable check at
    a given point see `fojax.analysis.regular_at`.

    **Arguments:**

    - `sys`: a `fojax.DescriptorSystem`, or the matrix ``E`` when `A` is given.
    - `A`: the matrix ``A`` when `sys` is ``E``.
    - `tol`: absolute rank threshold.

    **Returns:** ``True`` or ``False`` (``True`` for ``n = 0``). Never raises for a
    singular pencil.

    **Raises:** `fojax.errors.NumericallyUndecidableError` when a deciding singular value is
    within a factor 100 of the tolerance and SLICOT ``AG08BD`` gives the other verdict
    (`fojax.analysis._common.deflate`): the verdict then depends on the last digits.
    """
    p = as_pencil(sys, A, fname="is_regular", balance=balance)
    return deflate(p, tol).failed is None


def _poles_from(p: Pencil, d: Deflation, fname: str) -> np.ndarray:
    """Finite poles of the normalised pencil (unsorted) from its deflation."""
    n1 = d.n1
    if n1 == 0:
        return np.zeros(0, dtype=complex)
    z = sla.eigvals(d.At[:n1, :n1], d.Et[:n1, :n1])
    if not np.all(np.isfinite(z)):
        raise IrregularSystemError(
            f"{fname}: numerically ambiguous pencil; after deflating the infinite "
            "eigenvalues, the remaining E block is nearly singular (QZ returns infinite "
            "values). The pencil is too close to a singular or higher-index one for the "
            "rank tolerance; rescale the model or pass tol=."
        )
    return z.astype(complex)


def _poles_normalized(p: Pencil, tol: float | None, fname: str) -> np.ndarray:
    return _poles_from(p, require_regular(p, fname, tol), fname)


def _sort_poles(z: np.ndarray) -> np.ndarray:
    """Sort by real part, then imaginary part; real parts equal to ~1e-9 relative count as
    equal so that each conjugate pair comes out as (-imag, +imag)."""
    z = np.asarray(z, dtype=complex)
    scale = max(1.0, float(np.max(np.abs(z), initial=0.0)))
    return z[np.lexsort((z.imag, np.round(z.real / scale, 9)))]


def finite_poles(sys, A=None, *, tol: float | None = None, balance: bool = True) -> np.ndarray:
    r"""Finite generalized eigenvalues of $(E, A)$: the roots of $\det(sE - A)$.

    Host-only. The infinite eigenvalues are first removed by the orthogonal deflation
    described in `is_regular`; the $n_1 = \deg\det(sE - A)$ finite poles are then the
    generalized eigenvalues (SciPy QZ) of the remaining $n_1 \times n_1$ pencil, whose
    $E$ block is invertible. This avoids reading infinite eigenvalues off a QZ of the full
    pencil, where an index-$\nu$ block is perturbed by $O(\varepsilon^{1/\nu})$ and shows
    up as spurious huge "finite" eigenvalues. Rank decisions use the fojax tolerance on
    the normalised pencil (overridable by `tol`).

    **Arguments:**

    - `sys`: a `fojax.DescriptorSystem`, or the matrix ``E`` when `A` is given.
    - `A`: the matrix ``A`` when `sys` is ``E``.
    - `tol`: absolute rank threshold (applied to the normalised matrices).

    **Returns:** a complex NumPy array of length $n_1$, sorted by real part (then by
    imaginary part). Empty for a purely algebraic system and for ``n = 0``.

    **Raises:** `fojax.errors.IrregularSystemError` when the pencil is singular (no poles exist).
    """
    p = as_pencil(sys, A, fname="finite_poles", balance=balance)
    return _sort_poles(_poles_normalized(p, tol, "finite_poles") * p.pole_scale)


def nilpotency_index(sys, A=None, *, tol: float | None = None, balance: bool = True) -> int:
    r"""The nilpotency index $\nu$ of $N$ in the Weierstrass form (the DAE index).

    Convention: $\nu = 0$ when $E$ is invertible (no $N$ block, an ODE); $\nu = 1$ for a
    singular but impulse-free system ($N = 0$); $\nu \ge 2$ for impulsive systems
    ($N \neq 0$, $N^\nu = 0$). Host-only, computed without QZ as the number of steps of
    the orthogonal deflation of `is_regular` (step $j$ removes the $j$-th level of the
    Jordan chains of $N$). The tests cross-check it against the rank sequence of the
    block matrices $T_k$ (``E`` on the block diagonal, ``A`` below it), for which
    $(k+1)n - \mathrm{rank}\,T_k = \dim\ker N^{k+1}$.

    **Arguments:** as `finite_poles`.

    **Returns:** the integer $\nu$.

    **Raises:** `fojax.errors.IrregularSystemError` for a singular pencil.
    """
    p = as_pencil(sys, A, fname="nilpotency_index", balance=balance)
    return require_regular(p, "nilpotency_index", tol).index


def is_impulse_free(sys, A=None, *, tol: float | None = None, balance: bool = True) -> bool:
    r"""Whether the regular system has no impulsive modes.

    Equivalent conditions (thesis §2.1.2, Dai 1989): $N = 0$ in the Weierstrass form;
    $\deg\det(sE - A) = \mathrm{rank}\,E$; $\mathrm{rank}\begin{bmatrix}E&0\\A&E\end{bmatrix}
    = n + \mathrm{rank}\,E$; equivalently the index is $\le 1$, which is what is tested
    (one deflation step, see `nilpotency_index`; the tests check the agreement with the
    rank condition). Host-only.

    **Arguments:** as `finite_poles`.

    **Returns:** ``True`` or ``False`` (``True`` when $E$ is invertible or ``n = 0``).

    **Raises:** `fojax.errors.IrregularSystemError` for a singular pencil (impulse-freeness is
    defined for regular systems only; `is_admissible` answers ``False`` instead).
    """
    p = as_pencil(sys, A, fname="is_impulse_free", balance=balance)
    return require_regular(p, "is_impulse_free", tol).index <= 1


def _stable_np(poles: np.ndarray, margin: float, axis_tol: float, dt: float | None = None) -> bool:
    if poles.size == 0:
        return True
    return not bool(np.any(unstable_mask(poles, axis_tol, dt, margin)))


def is_stable(
    sys,
    A=None,
    *,
    margin: float = 0.0,
    axis_tol: float = AXIS_TOL,
    tol: float | None = None,
    balance: bool = True,
) -> bool:
    r"""Whether every finite pole satisfies $\mathrm{Re}\,\lambda < -\text{margin}$.

    The thesis's Definition 2.1.2 writes $\mathrm{Re}\,s \le 0$; that is a typo —
    asymptotic stability needs the strict inequality, which is what the rest of the
    thesis (and Dai 1989) uses. Infinite eigenvalues (impulsive or static modes) are
    ignored: a stable system may still be impulsive, see `is_admissible`. A system
    without finite poles is stable.

    **Discrete time** (a system with ``dt``): every finite pole satisfies
    $|\lambda| < 1 - \text{margin} - \text{axis\_tol}$ (the same tolerance rule with the
    unit circle as the boundary; `fojax.analysis._discrete`).

    Host-only (uses `finite_poles`).

    **Arguments:**

    - `sys`, `A`, `tol`: as `finite_poles`.
    - `margin`: required decay rate ($\ge 0$); the default ``0`` tests plain asymptotic
      stability, ``margin = α`` tests that every mode decays at least like
      $e^{-\alpha t}$.
    - `axis_tol`: a pole with $\mathrm{Re}\,\lambda \ge -\text{margin} -
      \text{axis\_tol}\cdot\max(1, |\lambda|)$ counts as not stable, so that a pole
      on the boundary computed as ``-1e-17`` is not declared stable. Default ``1e-9``.

    **Raises:** `fojax.errors.IrregularSystemError` for a singular pencil.
    """
    p = as_pencil(sys, A, fname="is_stable", balance=balance)
    poles = _poles_normalized(p, tol, "is_stable") * p.pole_scale
    return _stable_np(poles, float(margin), float(axis_tol), p.dt)


def is_admissible(
    sys,
    A=None,
    *,
    margin: float = 0.0,
    axis_tol: float = AXIS_TOL,
    tol: float | None = None,
    balance: bool = True,
) -> bool:
    r"""Whether $(E, A)$ is admissible: regular, impulse-free and stable (for a
    discrete-time system: regular, causal and $|\lambda| < 1$, see `is_stable`).

    Host-only. For a certificate (Theorem 2.1.3) see `admissibility_certificate`.

    **Arguments:** as `is_stable`.

    **Returns:** ``True`` or ``False``; ``False`` (no error) for a singular pencil.
    """
    p = as_pencil(sys, A, fname="is_admissible", balance=balance)
    d = deflate(p, tol)
    if d.failed is not None or d.index > 1:
        return False
    poles = _poles_from(p, d, "is_admissible") * p.pole_scale
    return _stable_np(poles, float(margin), float(axis_tol), p.dt)
