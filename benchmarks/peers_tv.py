"""Peers of study 2 (time-varying δ(t) and a constant actuator fault), and its tight reference.

Every function works on the hand-reduced 7-state ODE of `_workload.make_tv_workload`,

    d/dt x_d = (A_red0 + δ_k(t) dA_red) x_d + b_fault f_k,   δ_k(t) = a_k sin(ω_k t + φ_k),

and returns the ``(B, 2)`` metrics (IAE of ``|x|_1`` and of ``|zhat - L x|_1``, trapezoid rule
on the 0.01 s grid), like the peers of study 1 (`peers.py`).

- `tight_reference`: a Python loop of `scipy.integrate.solve_ivp` with DOP853,
  rtol 1e-12, atol 1e-14 (``t_eval`` on the grid): the accuracy reference.
- (a) `solve_ivp_loop`: the same loop with RK45, rtol 1e-6, atol 1e-9 (what an engineer
  would write first).
- (c) `rk4_batch_first` / `rk4_batch_last`: fixed-step RK4 (dt = 1e-3) vectorised over the
  batch in both axis orders; the harness times both and keeps the faster. Written as a
  careful user would: the common matrices are applied as one matrix product for the whole
  batch (``X @ A0.T`` and ``X @ dA.T``, δ scaling per sample) rather than per-sample
  ``(B, 7, 7)`` matrices, and δ is evaluated twice per step (at ``t + dt/2``, shared by the
  two middle stages, and at ``t + dt``, reused as the next step's ``t``), not four times.
  The metrics are accumulated while stepping (memory linear in B).

Exact discretisation (peers (b), (d) of study 1) does not apply: the loop is time-varying.
"""

from __future__ import annotations

import numpy as np
import scipy.integrate
from _workload import metrics_from_outputs, TimeVaryingWorkload
from peers import _grid_steps, _Trapz


RK4_DT = 1e-3


def _solve_ivp(wl: TimeVaryingWorkload, k: int, method: str, rtol: float, atol: float) -> np.ndarray:
    sol = scipy.integrate.solve_ivp(
        wl.rhs(k),
        (wl.ts[0], wl.ts[-1]),
        wl.xd0[k],
        method=method,
        t_eval=wl.ts,
        rtol=rtol,
        atol=atol,
    )
    if not sol.success:  # pragma: no cover
        raise RuntimeError(f"solve_ivp ({method}) failed on sample {k}: {sol.message}")
    return metrics_from_outputs((wl.C_out @ sol.y).T)


def tight_reference(wl: TimeVaryingWorkload, rtol: float = 1e-12, atol: float = 1e-14) -> np.ndarray:
    """The accuracy reference: DOP853 at rtol 1e-12, atol 1e-14, sample by sample."""
    return np.stack([_solve_ivp(wl, k, "DOP853", rtol, atol) for k in range(wl.size)])


# ------------------------------------------------------------------------------ (a)
def solve_ivp_loop(wl: TimeVaryingWorkload) -> np.ndarray:
    """(a) Python loop of ``solve_ivp`` (RK45, rtol 1e-6, atol 1e-9, t_eval on the grid)."""
    out = np.empty((wl.size, 2))
    for k in range(wl.size):
        out[k] = _solve_ivp(wl, k, "RK45", 1e-6, 1e-9)
    return out


# ------------------------------------------------------------------------------ (c)
def _rk4(wl: TimeVaryingWorkload, dt: float, batch_last: bool) -> np.ndarray:
    a, om, ph = wl.amplitude, wl.omega, wl.phase
    if batch_last:  # state (7, B)
        A0, dA = wl.A_red0, wl.dA_red
        X = np.ascontiguousarray(wl.xd0.T)
        F = np.ascontiguousarray(wl.forcing().T)

        def f(X, d):
            return A0 @ X + d * (dA @ X) + F

        def delta(t):
            return a * np.sin(om * t + ph)  # (B,), broadcasts over the rows of (7, B)

    else:  # state (B, 7)
        A0T, dAT = np.ascontiguousarray(wl.A_red0.T), np.ascontiguousarray(wl.dA_red.T)
        X = wl.xd0.copy()
        F = wl.forcing()

        def f(X, d):
            return X @ A0T + d * (X @ dAT) + F

        def delta(t):
            return (a * np.sin(om * t + ph))[:, None]

    sub, n_out = _grid_steps(dt, wl)
    acc = _Trapz(wl.C_out, batch_last=batch_last)
    acc.add(X, first=True)
    h2, h6 = dt / 2, dt / 6
    t0 = wl.ts[0]
    d0 = delta(t0)
    for i in range(n_out):
        for j in range(sub):
            t = t0 + (i * sub + j) * dt
            dh, d1 = delta(t + h2), delta(t + dt)
            k1 = f(X, d0)
            k2 = f(X + h2 * k1, dh)
            k3 = f(X + h2 * k2, dh)
            k4 = f(X + dt * k3, d1)
            X = X + h6 * (k1 + 2 * k2 + 2 * k3 + k4)
            d0 = d1
        acc.add(X)
    return acc.result()


def rk4_batch_first(wl: TimeVaryingWorkload, dt: float = RK4_DT) -> np.ndarray:
    """(c) RK4, state ``(B, 7)``: ``f = X A0ᵀ + δ ⊙ (X dAᵀ) + F``."""
    return _rk4(wl, dt, batch_last=False)


def rk4_batch_last(wl: TimeVaryingWorkload, dt: float = RK4_DT) -> np.ndarray:
    """(c) RK4, state ``(7, B)``: ``f = A0 X + δ ⊙ (dA X) + F``."""
    return _rk4(wl, dt, batch_last=True)


#: name -> (label, variants). The harness times every variant and keeps the fastest.
PEERS_TV = {
    "solve_ivp": ("(a) solve_ivp RK45 loop", {"loop": solve_ivp_loop}),
    "rk4": (
        "(c) NumPy RK4 dt=1e-3, batched",
        {"batch-first": rk4_batch_first, "batch-last": rk4_batch_last},
    ),
}
