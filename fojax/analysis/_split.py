r"""The one host index-1 split of $(E, A)$ (SVD coordinates of $E$) and its verdict.

Design, control and simulation call `index1_split` (host) instead of splitting $E$
themselves, so that the rank of $E$ and the regular / impulse-free verdict are the ones
of `fojax.analysis` (balanced, normalised, the rule of `fojax._linalg`):

- ``rank`` = $\mathrm{rank}\,E$ as `structure_report` decides it;
- ``regular`` and ``index`` from the same orthogonal deflation as `is_regular` and
  `nilpotency_index` (index $\le 1$ iff impulse-free);
- the coordinates: the full SVD $E = U \mathrm{diag}(s) V^T$ of the *raw* $E$ (orthogonal,
  so the callers' formulas $U_1^T A V_1$, ... keep their meaning), split at ``rank``.

The traceable twin for code under `jax.jit` is `fojax.analysis._traced.svd_split` (fixed
shapes, the fojax rule on the raw $E$, no balancing: rank decisions under tracing cannot
change shapes).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._linalg import rank
from ._common import as_pencil, deflate


@dataclass(frozen=True)
class Index1Split:
    r"""SVD coordinates of ``E`` split at its rank, and the analysis verdict on ``(E, A)``.

    ``E = U diag(s) Vt``; ``U1 = U[:, :rank]``, ``U2 = U[:, rank:]``, ``V1 = Vt[:rank].T``,
    ``V2 = Vt[rank:].T``. `regular` and `index` (``None`` when irregular) are
    `fojax.analysis.is_regular`'s and `fojax.analysis.nilpotency_index`'s; `failed` explains a singular
    pencil.
    """

    rank: int
    U: np.ndarray
    s: np.ndarray
    Vt: np.ndarray
    regular: bool
    index: int | None
    failed: str | None

    @property
    def U1(self):
        return self.U[:, : self.rank]

    @property
    def U2(self):
        return self.U[:, self.rank :]

    @property
    def V1(self):
        return self.Vt[: self.rank].T

    @property
    def V2(self):
        return self.Vt[self.rank :].T

    @property
    def impulse_free(self) -> bool:
        return self.regular and self.index <= 1

    def blocks(self, A):
        """``(A11, A12, A21, A22)`` = ``U_iᵀ A V_j``."""
        A = np.asarray(A, dtype=float)
        U1, U2, V1, V2 = self.U1, self.U2, self.V1, self.V2
        return U1.T @ A @ V1, U1.T @ A @ V2, U2.T @ A @ V1, U2.T @ A @ V2


def index1_split(E, A, *, tol: float | None = None, balance: bool = True,
                 fname: str = "index1_split") -> Index1Split:
    r"""Split ``(E, A)`` in the SVD coordinates of ``E`` with analysis's rank and verdict.

    Host-only; never raises for a singular or impulsive pencil (see `regular`, `index`);
    the callers raise their own typed errors with their context.

    **Arguments:** `E`, `A` (``(n, n)``); `tol`, `balance` as `fojax.analysis.is_regular`.
    """
    E = np.asarray(E, dtype=float)
    A = np.asarray(A, dtype=float)
    p = as_pencil(E, A, fname=fname, balance=balance)
    d = deflate(p, tol)
    n = E.shape[0]
    if d.failed is None:
        r = n - d.blocks[0] if d.blocks else n
    else:
        r = rank(p.En, tol)
    U, s, Vt = np.linalg.svd(E) if n else (np.zeros((0, 0)), np.zeros(0), np.zeros((0, 0)))
    return Index1Split(
        rank=int(r), U=U, s=s, Vt=Vt, regular=d.failed is None,
        index=d.index if d.failed is None else None, failed=d.failed,
    )  # fmt: skip
