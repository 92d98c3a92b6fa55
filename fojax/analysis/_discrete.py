r"""Discrete-time notions for descriptor systems $Ex[k+1] = Ax[k] + Bu[k]$, $y[k] = Cx[k]$.

A `fojax.DescriptorSystem` with a sampling period (``dt=h``) is analysed with the
discrete-time meaning of each property; the rank decisions are the same functions,
tolerances and balancing as in continuous time (analysis's one rule, `fojax._linalg`).

| continuous notion | discrete-time notion | test |
|---|---|---|
| impulse-free ($\deg\det(sE-A) = \mathrm{rank}\,E$) | **causal**: $x[k]$ depends on $u[0..k]$ only, not on future inputs | identical rank test (index $\le 1$) |
| stable ($\mathrm{Re}\,\lambda < 0$) | stable: every finite generalized eigenvalue has $\lvert\lambda\rvert < 1$ | QZ poles, unit circle |
| admissible | regular, causal and stable | both of the above |
| R-observable | $\mathrm{rank}[zE-A;\,C] = n$ at every finite $z$ | identical |
| I-observable (impulse observable) | the non-causal (infinite) modes are observable | identical |
| C-observable | R and $\mathrm{rank}[E;\,C] = n$ | identical |
| detectable | the finite-mode rank test at every pole with $\lvert z\rvert \ge 1$ (and I) | unit circle instead of the imaginary axis |

Why the rank tests carry over unchanged: each is an algebraic statement about the pencil
$zE - A$ and the matrices $B$, $C$ (Dai 1989, §2–3: the Weierstrass form
$x = Q[x_1; x_2]$ splits both time axes alike into the slow part $x_1[k+1] = A_1x_1[k] +
B_1u[k]$ and the fast part $Nx_2[k+1] = x_2[k] + B_2u[k]$, whose solution
$x_2[k] = -\sum_{i<\nu} N^iB_2u[k+i]$ needs the future inputs exactly when $N \ne 0$).
Only where a notion refers to the *location* of the poles (stability, detectability,
stabilizability) does the stability boundary change, from the imaginary axis to the
unit circle, with the same tolerance rule: a pole counts as on the boundary (hence not
stable) when $\lvert\lambda\rvert \ge 1 - \text{margin} - \text{axis\_tol}$.
"""

from __future__ import annotations

import numpy as np


def is_discrete(sys) -> bool:
    """Whether `sys` is a discrete-time model (a `dt` that is not ``None``)."""
    return getattr(sys, "dt", None) is not None


def time_domain(dt) -> str:
    """``"continuous-time"`` or ``"discrete-time (dt = h)"``."""
    return "continuous-time" if dt is None else f"discrete-time (dt = {float(dt):g})"


def unstable_mask(poles, axis_tol: float, dt=None, margin: float = 0.0) -> np.ndarray:
    r"""Which `poles` are not strictly stable: $\mathrm{Re}\,\lambda \ge -\text{margin} -
    \text{axis\_tol}\max(1, |\lambda|)$ in continuous time, $|\lambda| \ge 1 - \text{margin}
    - \text{axis\_tol}$ in discrete time (``dt`` not ``None``)."""
    z = np.asarray(poles, dtype=complex)
    if dt is None:
        return z.real >= -margin - axis_tol * np.maximum(1.0, np.abs(z))
    return np.abs(z) >= 1.0 - margin - axis_tol


def is_causal(sys, *, tol: float | None = None, balance: bool = True) -> bool:
    r"""Whether a regular discrete-time descriptor system is causal: its state $x[k]$ is
    determined by $x[0]$ and $u[0], \dots, u[k]$, without future inputs.

    Equivalent to $\deg\det(zE - A) = \mathrm{rank}\,E$ (index $\le 1$, $N = 0$ in the
    Weierstrass form), the discrete analogue of impulse-freeness and the same rank test:
    this calls `fojax.analysis.is_impulse_free`. Host-only.

    **Arguments:** `sys` a `fojax.DescriptorSystem` (continuous or discrete: the test is
    the same); `tol`, `balance` as `is_impulse_free`.

    **Returns:** ``True`` or ``False``.

    **Raises:** `fojax.errors.IrregularSystemError` for a singular pencil.

    !!! example

        ```python
        sys = fojax.DescriptorSystem(E, A, B, C, dt=0.1)
        fojax.analysis.is_causal(sys), fojax.analysis.is_stable(sys)  # |λ| < 1
        ```
    """
    from ._pencil import is_impulse_free

    return is_impulse_free(sys, tol=tol, balance=balance)
