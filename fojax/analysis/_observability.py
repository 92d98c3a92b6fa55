r"""Observability and controllability notions of regular descriptor systems (Dai 1989).

All functions are **host-only** (rank tests with SVD, poles with QZ) and need a
`fojax.DescriptorSystem` (they use ``C`` and/or ``B``). They are defined for regular
systems only and raise `fojax.errors.IrregularSystemError` for a singular pencil, except
`is_functionally_observable`, which is a pure rank condition.

Rank tests (each on the normalised matrices ``E/‖E‖``, ``A/‖A‖``, ``B/‖B‖``,
``C/‖C‖``, with the fojax rank tolerance ``max(RANK_RTOL * s_max, RANK_ATOL)`` or the
absolute `tol`):

| notion | observability | controllability (dual) |
|---|---|---|
| R | $\mathrm{rank}\begin{bmatrix}sE-A\\C\end{bmatrix}=n$ at every finite pole | $\mathrm{rank}[sE-A,\;B]=n$ at every finite pole |
| I | $\mathrm{rank}\begin{bmatrix}E&A\\0&E\\0&C\end{bmatrix}=n+\mathrm{rank}E$ | $\mathrm{rank}\begin{bmatrix}E&0&0\\A&E&B\end{bmatrix}=n+\mathrm{rank}E$ |
| C | R and $\mathrm{rank}\begin{bmatrix}E\\C\end{bmatrix}=n$ | R and $\mathrm{rank}[E,\;B]=n$ |
| S | R and I | R and I |

For a discrete-time system (``dt`` set) the same rank tests decide the same notions with
$z$ in place of $s$ (they are algebraic statements about the pencil, see
`fojax.analysis._discrete`); only detectability and stabilizability test the poles with
$|z| \ge 1$ instead of $\mathrm{Re}\,s \ge 0$.

C ⇒ S ⇒ R. The "at every finite pole" tests are evaluated at the computed poles *and*
at the mean of every cluster of nearby poles (defective poles are computed only to
$O(\epsilon^{1/k})$, their cluster mean to $O(\epsilon)$); a rank drop at any of these
points counts.
"""

from __future__ import annotations

import numpy as np

from .._linalg import clusters, left_null_space, rank
from ..plant import check_functional, DescriptorSystem
from ._balance import apply_scaling, scaling_of
from ._common import _unit, as_system, crank, Pencil, require_regular
from ._discrete import unstable_mask
from ._pencil import _poles_normalized, AXIS_TOL


#: Poles closer than ``CLUSTER_RTOL * max(1, |λ|)`` (normalised pencil) form a cluster
#: whose mean is tested as well.
CLUSTER_RTOL = 1e-4


def _test_points(poles: np.ndarray) -> list[complex]:
    pts = [complex(z) for z in poles]
    k = len(pts)
    if k < 2:
        return pts
    rtol = CLUSTER_RTOL * np.maximum(1.0, np.abs(np.asarray(pts)))
    groups = [[pts[i] for i in g] for g in clusters(pts, rtol)]
    for g in groups:
        if len(g) > 1:
            pts.append(complex(np.mean(g)))
    return pts


def _poles_for(p: Pencil, tol, fname, unstable_only=False, axis_tol=AXIS_TOL):
    z = _poles_normalized(p, tol, fname)
    if unstable_only and z.size:
        z = z[unstable_mask(z * p.pole_scale, axis_tol, p.dt)]
    return z


def _pbh(p: Pencil, tol, fname, stack, X, **kw) -> bool:
    """``rank stack([sE - A, X]) = n`` at every test point (`_test_points`) of the poles."""
    n = p.n
    for s in _test_points(_poles_for(p, tol, fname, **kw)):
        if crank(stack([s * p.En - p.An, X]), tol) < n:
            return False
    return True


def _r_obs(p: Pencil, tol, fname, **kw) -> bool:
    return _pbh(p, tol, fname, np.vstack, p.Cn, **kw)


def _r_ctrl(p: Pencil, tol, fname, **kw) -> bool:
    return _pbh(p, tol, fname, np.hstack, p.Bn, **kw)


def _i_obs(p: Pencil, tol) -> bool:
    n, q = p.n, p.Cn.shape[0]
    if n == 0:
        return True
    M = np.block(
        [
            [p.En, p.An],
            [np.zeros((n, n)), p.En],
            [np.zeros((q, n)), p.Cn],
        ]
    )
    return crank(M, tol) == n + rank(p.En, tol)


def _i_ctrl(p: Pencil, tol) -> bool:
    n, m = p.n, p.Bn.shape[1]
    if n == 0:
        return True
    M = np.block(
        [
            [p.En, np.zeros((n, n)), np.zeros((n, m))],
            [p.An, p.En, p.Bn],
        ]
    )
    return crank(M, tol) == n + rank(p.En, tol)


def _prep(sys, fname, tol, balance=True) -> Pencil:
    p = as_system(sys, fname, balance)
    require_regular(p, fname, tol)
    return p


def _decide(sys, notion: str, dual: bool, fname: str, tol, balance, impulse=True, **kw) -> bool:
    """One notion of the module table, in its observability column or (``dual``) its
    controllability column: ``"r"``, ``"i"``, ``"c"``, ``"s"``, or ``"d"`` (detectability /
    stabilizability: I when `impulse`, and R at the poles selected by `kw`)."""
    p = _prep(sys, fname, tol, balance)
    stack, X, i_test = (np.hstack, p.Bn, _i_ctrl) if dual else (np.vstack, p.Cn, _i_obs)
    if notion == "r":
        return _pbh(p, tol, fname, stack, X)
    if notion == "i":
        return i_test(p, tol)
    if notion == "c":
        return crank(stack([p.En, X]), tol) == p.n and _pbh(p, tol, fname, stack, X)
    if impulse and not i_test(p, tol):  # "s" and "d"
        return False
    return _pbh(p, tol, fname, stack, X, **kw)


_ARGS = """
    **Arguments:**

    - `sys`: a `fojax.DescriptorSystem`.
    - `tol`: absolute rank threshold overriding the fojax tolerance (applied to the
      balanced, normalised matrices).
    - `balance`: ``False`` skips the power-of-two balancing (`fojax.analysis.balance_system`).

    **Raises:** `fojax.errors.IrregularSystemError` for a singular pencil.
"""


def is_r_observable(sys: DescriptorSystem, *, tol: float | None = None, balance: bool = True) -> bool:
    r"""R-observability (observable within the reachable set; Dai 1989).

    $\mathrm{rank}\begin{bmatrix}sE-A\\C\end{bmatrix} = n$ for every finite $s$,
    equivalently at every finite pole; equivalently the slow subsystem $(A_1, C_1)$ of
    the Weierstrass form is observable. True when there are no finite poles. Host-only.
    """
    return _decide(sys, "r", False, "is_r_observable", tol, balance)


def is_i_observable(sys: DescriptorSystem, *, tol: float | None = None, balance: bool = True) -> bool:
    r"""I-observability (impulse observability; Dai 1989).

    $\mathrm{rank}\begin{bmatrix}E&A\\0&E\\0&C\end{bmatrix} = n + \mathrm{rank}\,E$,
    equivalently $\mathrm{rank}[E; E^\perp A; C] = n$ (thesis Remark 1 — the thesis
    orders the block rows as $[E, A; 0, C; 0, E]$, which has the same rank). Every
    impulse-free system is I-observable. Host-only.
    """
    return _decide(sys, "i", False, "is_i_observable", tol, balance)


def is_c_observable(sys: DescriptorSystem, *, tol: float | None = None, balance: bool = True) -> bool:
    r"""C-observability (complete observability; Dai 1989, thesis Def. 2.1.7).

    R-observable and $\mathrm{rank}\begin{bmatrix}E\\C\end{bmatrix} = n$ (the latter is
    observability of the fast subsystem $(N, C_2)$). Implies S-observability. Host-only.
    """
    return _decide(sys, "c", False, "is_c_observable", tol, balance)


def is_s_observable(sys: DescriptorSystem, *, tol: float | None = None, balance: bool = True) -> bool:
    r"""S-observability (strong observability): R-observable and I-observable. Host-only."""
    return _decide(sys, "s", False, "is_s_observable", tol, balance)


def is_r_controllable(sys: DescriptorSystem, *, tol: float | None = None, balance: bool = True) -> bool:
    r"""R-controllability (controllable within the reachable set; Dai 1989, thesis Def. 2.1.5).

    $\mathrm{rank}[sE-A,\;B] = n$ at every finite pole; equivalently $(A_1, B_1)$ is
    controllable. True when there are no finite poles. Host-only.
    """
    return _decide(sys, "r", True, "is_r_controllable", tol, balance)


def is_i_controllable(sys: DescriptorSystem, *, tol: float | None = None, balance: bool = True) -> bool:
    r"""I-controllability (impulse controllability; Dai 1989, thesis Def. 2.1.6).

    $\mathrm{rank}\begin{bmatrix}E&0&0\\A&E&B\end{bmatrix} = n + \mathrm{rank}\,E$.
    Holds iff some state feedback $u = Kx$ makes $(E, A+BK)$ impulse-free. Every
    impulse-free system is I-controllable. Host-only.
    """
    return _decide(sys, "i", True, "is_i_controllable", tol, balance)


def is_c_controllable(sys: DescriptorSystem, *, tol: float | None = None, balance: bool = True) -> bool:
    r"""C-controllability (complete controllability; Dai 1989, thesis Def. 2.1.4).

    R-controllable and $\mathrm{rank}[E,\;B] = n$. Host-only.
    """
    return _decide(sys, "c", True, "is_c_controllable", tol, balance)


def is_s_controllable(sys: DescriptorSystem, *, tol: float | None = None, balance: bool = True) -> bool:
    r"""S-controllability (strong controllability): R- and I-controllable. Host-only."""
    return _decide(sys, "s", True, "is_s_controllable", tol, balance)


def is_detectable(
    sys: DescriptorSystem,
    *,
    impulse: bool = True,
    axis_tol: float = AXIS_TOL,
    tol: float | None = None,
    balance: bool = True,
) -> bool:
    r"""Detectability of a regular descriptor system.

    Definition used (Dai 1989, §3): the finite-mode condition
    $\mathrm{rank}\begin{bmatrix}sE-A\\C\end{bmatrix} = n$ at every finite pole with
    $\mathrm{Re}\,s \ge 0$ (poles within `axis_tol` of the axis count as unstable, as in
    `is_stable`; $|s| \ge 1$ for a discrete-time system), **and**, when `impulse=True` (default), I-observability. With both,
    an output injection $K$ exists such that $(E, A - KC)$ is admissible, which is what a
    state (or full-order) observer with admissible error dynamics needs. With
    ``impulse=False`` only the finite-mode condition (Dai's plain "detectable") is tested.
    Host-only.
    """
    return _decide(sys, "d", False, "is_detectable", tol, balance, impulse, unstable_only=True, axis_tol=axis_tol)


def is_stabilizable(
    sys: DescriptorSystem,
    *,
    impulse: bool = True,
    axis_tol: float = AXIS_TOL,
    tol: float | None = None,
    balance: bool = True,
) -> bool:
    r"""Stabilizability of a regular descriptor system (dual of `is_detectable`).

    Finite-mode condition $\mathrm{rank}[sE-A,\;B] = n$ at every finite pole with
    $\mathrm{Re}\,s \ge 0$, and (default `impulse=True`) I-controllability; together they
    are equivalent to the existence of $K$ with $(E, A + BK)$ admissible. Host-only.
    """
    return _decide(sys, "d", True, "is_stabilizable", tol, balance, impulse, unstable_only=True, axis_tol=axis_tol)


for _f in (
    is_r_observable,
    is_i_observable,
    is_c_observable,
    is_s_observable,
    is_r_controllable,
    is_i_controllable,
    is_c_controllable,
    is_s_controllable,
    is_detectable,
    is_stabilizable,
):
    _f.__doc__ = (_f.__doc__ or "") + _ARGS
del _f


def functional_rank_pair(E, A, C, L, *, D=None, output_only: bool = False,
                         tol: float | None = None, balance: bool = True) -> tuple[int, int]:
    r"""``(rank [L; Γ], rank Γ)`` with $\Gamma = [E; E^\perp A; C]$ on normalised blocks (host-only).

    The one functional-observability rank test of fojax (`is_functionally_observable`,
    `structure_report` and every observer design call it). Each block is divided by its
    spectral norm (``E``, ``A``, ``C``, ``L``, and ``D``) before the rank decisions, after
    the exact power-of-two balancing of ``(E, A, C)`` (`fojax.analysis.balance_system`;
    ``L`` is scaled with the states, ``D`` with the equations), so the verdict does not
    change with the units of the equations, states, outputs or functional.

    **Arguments:**

    - `E`, `A` (``(n, n)``), `C` (``(p, n)``), `L` (``(q, n)``): float64 matrices.
    - `D`: ``(n, l)`` unknown-input directions; then $E^\perp$ spans the left null space
      of $[E\;D]$ (the unknown-input observer, `fojax.design.design_unknown_input_observer`).
    - `output_only`: $\Gamma = [E; C]$ (the Takagi–Sugeno observer measures $y$ only).
    - `tol`: absolute rank threshold on the normalised blocks.
    - `balance`: ``False`` skips the balancing.
    """
    E, A, C, L = (np.asarray(x, dtype=float) for x in (E, A, C, L))
    sc = scaling_of(E, A, None, C, balance=balance)
    E, A, _, C = apply_scaling(sc, E, A, None, C)
    L = L * sc.right[None, :]
    if D is not None:
        D = sc.left[:, None] * np.asarray(D, dtype=float)
    En, An, Cn, Ln = (_unit(M)[0] for M in (E, A, C, L))
    if output_only:
        Gamma = np.vstack([En, Cn])
    else:
        K = En if D is None else np.hstack([En, _unit(np.asarray(D, dtype=float))[0]])
        Ep = left_null_space(K, tol)
        Gamma = np.vstack([En, Ep @ An, Cn])
    return rank(np.vstack([Ln, Gamma]), tol), rank(Gamma, tol)


def functional_ranks(sys: DescriptorSystem, L, *, tol: float | None = None,
                     balance: bool = True) -> tuple[int, int]:
    r"""``(rank [L; E; E⊥A; C], rank [E; E⊥A; C])`` on normalised blocks (host-only)."""
    p = as_system(sys, "is_functionally_observable", balance=False)
    L = np.asarray(check_functional(sys, L), dtype=float)
    return functional_rank_pair(p.E, p.A, p.C, L, tol=tol, balance=balance)


def is_functionally_observable(sys: DescriptorSystem, L, *, tol: float | None = None,
                               balance: bool = True) -> bool:
    r"""Assumption 1 (Darouach 2012): the functional $z = Lx$ is observable.

    $$\mathrm{rank}\begin{bmatrix}L\\E\\E^\perp A\\C\end{bmatrix}
      = \mathrm{rank}\begin{bmatrix}E\\E^\perp A\\C\end{bmatrix}.$$

    Pure rank condition: no regularity is required and no error is raised for singular
    pencils. Note that $\mathrm{rank}[E; E^\perp A] = n$ for every regular impulse-free
    pencil, so the condition holds for *every* $L$ when $(E, A)$ is impulse-free; it can
    only fail for impulsive (or singular) pencils. Host-only.

    **Arguments:**

    - `sys`: a `fojax.DescriptorSystem`.
    - `L`: the ``(q, n)`` functional matrix (``q = 0`` gives ``True``).
    - `tol`: absolute rank threshold overriding the fojax tolerance (applied to the
      normalised blocks ``L/‖L‖``, ``E/‖E‖``, ``E⊥A/‖A‖``, ``C/‖C‖``).
    """
    a, b = functional_ranks(sys, L, tol=tol, balance=balance)
    return a == b
