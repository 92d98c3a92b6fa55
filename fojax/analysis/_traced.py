r"""JAX-traceable structural screens, for `jax.jit` and `jax.vmap` over many samples.

The host functions of `fojax.analysis` (QZ, rank decisions) cannot be traced. The
screens here take raw float64 JAX arrays, have fixed output shapes, and return
*continuous margins* rather than booleans, so that thousands of uncertain samples can
be checked in one vmapped call and thresholded afterwards.

The one discrete quantity they need, ``rank_E``, fixes array shapes and must be a
Python ``int`` known at trace time (it is computed on the host from a concrete `E`
when omitted outside of tracing). The samples of a batch must share this rank — which
is the case for the thesis's uncertain models, where only ``A`` (and the non-zero
part of ``E``) is uncertain.

Tolerances: `regular_at` uses the fojax rank tolerance
``max(RANK_RTOL * s_max, RANK_ATOL)``; `functional_observability_gap` uses
`fojax._linalg.jpinv` (relative cut-off ``RANK_RTOL``); the other screens return raw
numbers for the caller to threshold.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, Float

from .._errors import InputError, ShapeError
from .._linalg import jpinv, rank, RANK_ATOL, RANK_RTOL


def _rank_e(E, rank_E, fname) -> int:
    if rank_E is not None:
        r = int(rank_E)
        if not 0 <= r <= E.shape[-1]:
            raise InputError(f"{fname}: rank_E = {r} is outside [0, n = {E.shape[-1]}].")
        return r
    if isinstance(E, jax.core.Tracer):
        raise InputError(
            f"{fname}: E is traced (inside jax.jit / jax.vmap), so its rank cannot be "
            "decided at trace time. Pass rank_E=<int> (the structural rank of E, e.g. "
            "fojax._linalg.rank(E_nominal)); it must be the same for every sample of a batch."
        )
    return rank(np.asarray(E, dtype=float))


def _check_square(name, M, n=None):
    if M.ndim != 2 or M.shape[0] != M.shape[1] or (n is not None and M.shape[0] != n):
        exp = (n, n) if n is not None else "(n, n)"
        raise ShapeError(
            name,
            exp,
            tuple(M.shape),
            "Traceable screens take one system; batch them with jax.vmap.",
        )


def _square_pair(E, A):
    """``(E, A)`` as JAX arrays, both checked to be ``(n, n)`` with the same ``n``."""
    E = jnp.asarray(E)
    A = jnp.asarray(A)
    _check_square("E", E)
    _check_square("A", A, E.shape[0])
    return E, A


def _svd_blocks(E, r):
    """Left/right singular bases of E split at the structural rank ``r``."""
    U, s, Vt = jnp.linalg.svd(E, full_matrices=True)
    return U[:, :r], U[:, r:], s[:r], Vt[:r].T, Vt[r:].T


def impulse_free_margin(E, A, rank_E: int | None = None):
    r"""Smallest singular value of $A_{22} = U_2^T A V_2$ (traceable).

    $U_2$, $V_2$ are orthonormal bases of the left and right null spaces of $E$ (from
    its SVD, split at `rank_E`). With $E$ of rank `rank_E`, the pencil is regular and
    impulse-free (index $\le 1$) iff $A_{22}$ is invertible, i.e. iff the margin is
    $> 0$; it is the distance (in the 2-norm, for perturbations of $A$ that act on
    $\ker E$) to the nearest impulsive pencil. Compare with
    ``RANK_RTOL * ‖A‖₂`` to reproduce `fojax.analysis.is_impulse_free`. Returns ``inf`` when
    ``rank_E = n`` (no algebraic part). The value does not depend on the choice of bases.

    **Arguments:** `E`, `A` (``(n, n)`` float64 JAX arrays); `rank_E` (static ``int``,
    required under tracing).

    **Returns:** a float64 scalar.
    """
    E, A = _square_pair(E, A)
    n = E.shape[0]
    r = _rank_e(E, rank_E, "impulse_free_margin")
    if r == n:
        return jnp.asarray(jnp.inf, dtype=A.dtype)
    _, U2, _, _, V2 = _svd_blocks(E, r)
    return jnp.linalg.svd(U2.T @ A @ V2, compute_uv=False)[-1]


def slow_matrix_index1(E, A, rank_E: int | None = None):
    r"""The state matrix $A_s$ of the slow ODE of an index-$\le 1$ pencil (traceable).

    With $U^TEV = \mathrm{diag}(\Sigma_1, 0)$ and $U^TAV = [A_{ij}]$, eliminating the
    algebraic part $x_2 = -A_{22}^{-1}A_{21}x_1$ gives
    $\dot x_1 = \Sigma_1^{-1}(A_{11} - A_{12}A_{22}^{-1}A_{21})x_1$; its eigenvalues are the
    finite poles of $(E, A)$. Meaningless (NaN/inf entries) when $A_{22}$ is singular,
    i.e. when `impulse_free_margin` is 0.

    **Returns:** an ``(r, r)`` array with ``r = rank_E``.
    """
    E, A = _square_pair(E, A)
    n = E.shape[0]
    r = _rank_e(E, rank_E, "slow_matrix_index1")
    if r == n:
        return jnp.linalg.solve(E, A)
    if r == 0:
        return jnp.zeros((0, 0), dtype=A.dtype)
    U1, U2, s1, V1, V2 = _svd_blocks(E, r)
    A11 = U1.T @ A @ V1
    A12 = U1.T @ A @ V2
    A21 = U2.T @ A @ V1
    A22 = U2.T @ A @ V2
    As = A11 - A12 @ jnp.linalg.solve(A22, A21)
    return As / s1[:, None]


def stability_margin_index1(E, A, rank_E: int | None = None):
    r"""Largest real part of the finite poles of an index-$\le 1$ pencil (traceable, no QZ).

    The pencil is reduced to its slow ODE (`slow_matrix_index1`) and
    ``max(real(eigvals(A_s)))`` is returned: negative iff the (impulse-free) system is
    stable. ``-inf`` when there are no finite poles (``rank_E = 0``). Only meaningful
    where `impulse_free_margin` is clearly positive; for impulsive pencils use the host
    function `fojax.analysis.finite_poles`. Uses ``jnp.linalg.eigvals`` (a non-symmetric
    eigensolver; available on CPU, and on GPU only in recent JAX versions) and is not
    meant to be differentiated at repeated poles.

    **Arguments:** as `impulse_free_margin`. **Returns:** a float64 scalar.
    """
    As = slow_matrix_index1(E, A, rank_E)
    if As.shape[0] == 0:
        return jnp.asarray(-jnp.inf, dtype=jnp.asarray(A).dtype)
    return jnp.max(jnp.real(jnp.linalg.eigvals(As)))


def functional_observability_gap(E, A, C, L, rank_E: int | None = None):
    r"""Relative distance of the rows of $L$ from the row space of $\Gamma$ (traceable).

    $\Gamma = [E; E^\perp A; C]$ with $E^\perp = U_2^T$ from the SVD of $E$ split at
    `rank_E`; the gap is $\|L(I - \Gamma^+\Gamma)\|_2 / \|L\|_2$ (``0`` for ``L = 0``),
    with the pseudo-inverse `fojax._linalg.jpinv` (relative cut-off ``RANK_RTOL``).
    Assumption 1 ($\mathrm{rank}[L;\Gamma] = \mathrm{rank}\,\Gamma$) holds iff the gap
    is 0; numerically, compare with e.g. ``1e-8``.

    **Arguments:** `E`, `A` (``(n, n)``), `C` (``(p, n)``), `L` (``(q, n)``), `rank_E`.

    **Returns:** a float64 scalar in ``[0, 1]``.
    """
    E, A = _square_pair(E, A)
    C = jnp.asarray(C)
    L = jnp.asarray(L)
    n = E.shape[0]
    if C.ndim != 2 or C.shape[1] != n:
        raise ShapeError("C", ("p", n), tuple(C.shape), "C needs one column per state.")
    if L.ndim != 2 or L.shape[1] != n:
        raise ShapeError("L", ("q", n), tuple(L.shape), "L needs one column per state.")
    r = _rank_e(E, rank_E, "functional_observability_gap")
    if L.shape[0] == 0 or n == 0:
        return jnp.asarray(0.0, dtype=A.dtype)
    _, U2, _, _, _ = _svd_blocks(E, r)
    Gamma = jnp.concatenate([E, U2.T @ A, C], axis=0)
    proj = jpinv(Gamma) @ Gamma
    res = L - L @ proj
    nL = jnp.linalg.norm(L, 2)
    safe = jnp.where(nL > 0, nL, 1.0)
    return jnp.where(nL > 0, jnp.linalg.norm(res, 2) / safe, 0.0)


def regularity_margin_at(E, A, s):
    r"""$\sigma_{\min}(sE - A) / \sigma_{\max}(sE - A)$ at a (complex) point $s$ (traceable).

    Positive (above rounding) proves that the pencil is regular and that $s$ is not a
    pole. ``0`` for the zero matrix; ``1`` for ``n = 0``.
    """
    E, A = _square_pair(E, A)
    if E.shape[0] == 0:
        return jnp.asarray(1.0, dtype=A.dtype)
    sv = jnp.linalg.svd(s * E - A, compute_uv=False)
    smax = sv[0]
    return jnp.where(smax > 0, sv[-1] / jnp.where(smax > 0, smax, 1.0), 0.0)


def regular_at(E, A, s):
    r"""Whether $sE - A$ is numerically non-singular at $s$ (traceable boolean).

    Uses the fojax rank rule: $\sigma_{\min} > \max(\text{RANK\_RTOL}\,\sigma_{\max},
    \text{RANK\_ATOL})$. ``True`` proves regularity of the pencil (a regular pencil is
    singular only at its poles, so a generic `s` should be used); ``False`` means
    either a singular pencil or that `s` is (numerically) a pole. For the host decision
    see `fojax.analysis.is_regular`.
    """
    E, A = _square_pair(E, A)
    if E.shape[0] == 0:
        return jnp.asarray(True)
    sv = jnp.linalg.svd(s * E - A, compute_uv=False)
    return sv[-1] > jnp.maximum(RANK_RTOL * sv[0], RANK_ATOL)


# --------------------------------------------------------------------------- traced split of E


class SVDSplit(eqx.Module):
    r"""Full SVD coordinates of ``E`` with a slow mask (traceable, static shapes).

    ``x = V z``; ``slow[i] = 1`` where ``σ_i`` counts as non-zero, else ``0``;
    ``sigma`` holds ``σ_i`` on slow components and ``1`` on fast ones.
    """

    U: Float[Array, "n n"]
    V: Float[Array, "n n"]
    sigma: Float[Array, " n"]
    slow: Float[Array, " n"]

    @property
    def fast(self):
        return 1.0 - self.slow

    def newton_matrix(self, J):
        """``D_f J D_f + D_s``: Jacobian of the algebraic part w.r.t. the fast components."""
        return J * self.fast[None, :] * self.fast[:, None] + jnp.diag(self.slow)


def svd_split(E) -> SVDSplit:
    """SVD split of ``stop_gradient(E)`` with the fojax rank tolerance (traceable).

    The traced twin of the host `fojax.analysis.index1_split` (used by simulation and
    studies under ``jit``): the rule of `fojax._linalg` on the raw ``E``, without
    balancing (a rank decision under tracing cannot change shapes, so it cannot use
    data-dependent scalings); `fojax.simulate`'s host check refuses data on which the
    two disagree.
    """
    E = lax.stop_gradient(jnp.asarray(E))
    U, s, Vt = jnp.linalg.svd(E, full_matrices=True)
    tol = jnp.maximum(RANK_RTOL * s[0], RANK_ATOL)
    slow = (s > tol).astype(E.dtype)
    sigma = jnp.where(s > tol, s, 1.0)
    return SVDSplit(U, Vt.T, sigma, slow)
