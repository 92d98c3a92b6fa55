r"""The one Stein (discrete Lyapunov) certificate of a disk region, host and traced.

For error dynamics $\mathbb A$ and the disk $\mathcal Q(\alpha, \tau)$ let
$\bar A = (\mathbb A - \alpha I)/\tau$. The Stein equation
$\bar A^\top X\bar A - X + I = 0$ has a solution $X \succ 0$ (then $X \succeq I$) iff every
eigenvalue of $\mathbb A$ lies in the open disk, and by a Schur complement that $X$
satisfies the disk's Chilali–Gahinet LMI
$L\otimes X + M\otimes(\mathbb A^\top X) + M^\top\otimes(X\mathbb A) \prec 0$: it is a
certificate $X$ of the region LMI without an SDP. Every route that needs one calls this
module: the Riccati route (`fojax.design._riccati`), the pole-placement fallback of
finite-time designs, the unknown-input LMI's preconditioner (on the transposed dynamics)
and the tuning parameterizations (`fojax.design.SteinDisk`).

Two algorithms, one equation (``method=``):

- ``"scipy"`` (default): `scipy.linalg.solve_discrete_lyapunov` (direct for small, the
  bilinear transformation for larger matrices); its ill-conditioning warnings are returned
  in `notes` instead of being raised (the caller verifies the certificate anyway).
- ``"doubling"``: Smith's doubling $X = \sum_k (\bar A^\top)^k\bar A^k$, which keeps $X$
  positive definite for the highly non-normal $\mathbb A$ of high-gain pole placement
  (where a direct Kronecker solve can lose definiteness, e.g. the §3.1.3 finite-time
  fallback); it raises `fojax.errors.DesignVerificationError` when the sum overflows float64.

`stein_certificate` is the traced twin (Smith's doubling over $2^{40}$ terms by
`lax.fori_loop`: matrix products only, cheap to compile and differentiate) used inside
the tuning step.
"""

from __future__ import annotations

import warnings

import jax.numpy as jnp
import numpy as np
from jax import lax

from .._errors import DesignVerificationError


METHODS = ("scipy", "doubling")


def host_stein_certificate(A, center: float = 0.0, radius: float = 1.0, *, method: str = "scipy",
                           notes: list | None = None) -> np.ndarray:
    r"""``X`` (symmetrised) with $\bar A^\top X\bar A - X + I = 0$, $\bar A = (A - \alpha I)/\tau$,
    in float64 on the host (module docstring).

    **Arguments:** `A` ``(d, d)``; `center` $\alpha$ and `radius` $\tau$ of the disk (default
    the unit disk: `A` already in disk coordinates); `method` ``"scipy"`` or ``"doubling"``;
    `notes`: a list that receives the solver's warnings (``"scipy"``).

    **Returns:** ``X``, ``(d, d)``; not positive definite (or not finite) when an
    eigenvalue of `A` is outside the disk — callers verify it (`fojax.design.verify`).
    """
    import scipy.linalg

    A = np.asarray(A, dtype=float)
    if A.size == 0:
        return np.zeros(A.shape)
    d = A.shape[0]
    Ab = (A - center * np.eye(d)) / radius
    if method == "scipy":
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            X = scipy.linalg.solve_discrete_lyapunov(Ab.T, np.eye(d))
        if caught and notes is not None:
            notes.append("Stein equation: " + "; ".join(str(w.message) for w in caught))
    elif method == "doubling":
        X, Mk = np.eye(d), Ab
        with np.errstate(over="ignore", invalid="ignore"):
            for _ in range(64):
                Xn = X + Mk.T @ X @ Mk
                Mk = Mk @ Mk
                if not (np.all(np.isfinite(Xn)) and np.all(np.isfinite(Mk))):
                    raise DesignVerificationError(
                        "the placed error dynamics are so non-normal that their Lyapunov certificate "
                        "overflows float64 (observer gains far beyond the data's scale); such an "
                        "observer cannot be verified. Use fojax's default R, a larger observer order "
                        "or disks closer to the open-loop modes."
                    )
                X = Xn
                if np.linalg.norm(Mk, 2) < 1e-18:
                    break
    else:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    return 0.5 * (X + X.T)


def stein_certificate(A, center, radius):
    r"""``P`` solving $\bar A^\top P\bar A - P = -I$, $\bar A = (A - \alpha I)/\tau$ (traceable).

    All eigenvalues of $A$ lie in the open disk $\mathcal Q(\alpha, \tau)$ iff ``P ≻ 0``
    (then ``P ⪰ I``), and $(A-\alpha I)^\top P(A-\alpha I) - \tau^2P = -\tau^2 I$, so ``P`` is
    a certificate $X$ of the disk LMI. Smith's doubling, $P = \sum_k (\bar A^\top)^k\bar A^k$
    over $2^{40}$ terms (matrix products only: cheap to compile and differentiate); outside
    the disk $\bar A^{2^j}$ overflows and ``P`` is not finite positive definite. The host
    twin is `host_stein_certificate`.
    """
    d = A.shape[0]
    Ab = (A - center * jnp.eye(d)) / radius

    def double(_, carry):
        P, Ak = carry
        return P + Ak.T @ P @ Ak, Ak @ Ak

    P, _ = lax.fori_loop(0, 40, double, (jnp.eye(d), Ab))
    return 0.5 * (P + P.T)
