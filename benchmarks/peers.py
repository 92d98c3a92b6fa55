"""The four peers of issue 7, written the way a competent NumPy/SciPy user would write them.

Every peer works on the hand-reduced 7-state ODE of `_workload` (``wl.A_red``, ``wl.xd0``,
``wl.C_out``) and returns the ``(B, 2)`` metrics array (IAE of ``|x|_1`` and of
``|zhat - L x|_1``, trapezoid rule on the 0.01 s grid).

- (a) `solve_ivp_loop`: a Python loop of `scipy.integrate.solve_ivp` (RK45, rtol 1e-6,
  atol 1e-9, ``t_eval`` on the grid).
- (b) `control_loop`: a Python loop of python-control's `initial_response` on the reduced
  state space (python-control discretises exactly on the evenly spaced grid).
- (c) `rk4_batch_first` / `rk4_batch_last`: fixed-step RK4 (dt = 1e-3) vectorised over the
  batch in both axis orders; the harness times both and keeps the faster.
- (d) `expm_batch_first` / `expm_batch_last`: exact discretisation ``Phi_k = expm(A_k dt)``
  with `scipy.linalg.expm` (called once on the stacked ``(B, 7, 7)`` array, which SciPy
  evaluates sample by sample) and a recurrence vectorised over the batch; both axis orders,
  the harness keeps the faster. Peer (d) is the accuracy reference.

The vectorised peers accumulate the metrics while stepping (memory linear in B, no
``(B, T, n)`` trajectory is stored), which is what one does when B = 100,000.
Imports of the peer libraries happen at module import, outside any timed region.
"""

from __future__ import annotations

import numpy as np
import scipy.integrate
import scipy.linalg


try:  # python-control is in the optional extra fojax[bench]
    import control as _ct
except ImportError:  # pragma: no cover
    _ct = None

from _workload import DT_GRID, metrics_from_outputs, Workload


RK4_DT = 1e-3


# ------------------------------------------------------------------------------ (a)
def solve_ivp_loop(wl: Workload) -> np.ndarray:
    """(a) Python loop of ``solve_ivp`` (RK45, rtol 1e-6, atol 1e-9, t_eval on the grid)."""
    ts = wl.ts
    out = np.empty((wl.size, 2))
    for k in range(wl.size):
        Ak = wl.A_red[k]
        sol = scipy.integrate.solve_ivp(
            lambda t, x, Ak=Ak: Ak @ x,
            (ts[0], ts[-1]),
            wl.xd0[k],
            method="RK45",
            t_eval=ts,
            rtol=1e-6,
            atol=1e-9,
        )
        if not sol.success:  # pragma: no cover
            raise RuntimeError(f"solve_ivp failed on sample {k}: {sol.message}")
        out[k] = metrics_from_outputs((wl.C_out @ sol.y).T)
    return out


# ------------------------------------------------------------------------------ (b)
def control_loop(wl: Workload) -> np.ndarray:
    """(b) Python loop of ``control.initial_response`` on the reduced state space."""
    if _ct is None:  # pragma: no cover
        raise ImportError("python-control is missing: pip install 'fojax[bench]'")
    n = wl.A_red.shape[-1]
    Bz = np.zeros((n, 1))
    Dz = np.zeros((wl.C_out.shape[0], 1))
    out = np.empty((wl.size, 2))
    for k in range(wl.size):
        sys = _ct.ss(wl.A_red[k], Bz, wl.C_out, Dz)
        resp = _ct.initial_response(sys, T=wl.ts, X0=wl.xd0[k])
        out[k] = metrics_from_outputs(np.asarray(resp.outputs).T)
    return out


# ------------------------------------------------------------------------------ helpers
class _Trapz:
    """Running trapezoid sums of ``|x|_1`` and ``|zhat - Lx|_1`` on the output grid."""

    def __init__(self, C_out: np.ndarray, batch_last: bool):
        self.Cx, self.Ce = C_out[:4], C_out[4:]
        self.batch_last = batch_last
        self.acc = None
        self.last = None

    def _f(self, X):
        if self.batch_last:  # X (n, B)
            return np.abs(self.Cx @ X).sum(0), np.abs(self.Ce @ X).sum(0)
        return np.abs(X @ self.Cx.T).sum(1), np.abs(X @ self.Ce.T).sum(1)  # X (B, n)

    def add(self, X, first: bool = False):
        fx, fe = self._f(X)
        if first:
            self.acc = [0.5 * fx, 0.5 * fe]
        else:
            self.acc[0] += fx
            self.acc[1] += fe
        self.last = (fx, fe)

    def result(self, dt: float = DT_GRID) -> np.ndarray:
        fx, fe = self.last  # the last point was added with weight 1: remove a half
        return dt * np.stack([self.acc[0] - 0.5 * fx, self.acc[1] - 0.5 * fe], axis=1)


def _grid_steps(dt_inner: float, wl: Workload) -> tuple[int, int]:
    sub = int(round(DT_GRID / dt_inner))
    assert abs(sub * dt_inner - DT_GRID) < 1e-15
    return sub, wl.ts.size - 1


# ------------------------------------------------------------------------------ (c)
def rk4_batch_first(wl: Workload, dt: float = RK4_DT) -> np.ndarray:
    """(c) RK4, state ``(B, n)``, matrices ``(B, n, n)``; ``f(X) = einsum('bij,bj->bi')``."""
    Ab = np.ascontiguousarray(wl.A_red)
    X = wl.xd0.copy()
    sub, n_out = _grid_steps(dt, wl)
    acc = _Trapz(wl.C_out, batch_last=False)
    acc.add(X, first=True)

    def f(Y):
        return np.einsum("bij,bj->bi", Ab, Y)

    h2, h6 = dt / 2, dt / 6
    for _ in range(n_out):
        for _ in range(sub):
            k1 = f(X)
            k2 = f(X + h2 * k1)
            k3 = f(X + h2 * k2)
            k4 = f(X + dt * k3)
            X = X + h6 * (k1 + 2 * k2 + 2 * k3 + k4)
        acc.add(X)
    return acc.result()


def rk4_batch_last(wl: Workload, dt: float = RK4_DT) -> np.ndarray:
    """(c) RK4, state ``(n, B)``, matrices ``(n, n, B)``; ``f(X)_i = sum_j A_ij * X_j``."""
    Ab = np.ascontiguousarray(np.moveaxis(wl.A_red, 0, -1))  # (n, n, B)
    X = np.ascontiguousarray(wl.xd0.T)  # (n, B)
    sub, n_out = _grid_steps(dt, wl)
    acc = _Trapz(wl.C_out, batch_last=True)
    acc.add(X, first=True)

    def f(Y):
        return np.einsum("ijb,jb->ib", Ab, Y)

    h2, h6 = dt / 2, dt / 6
    for _ in range(n_out):
        for _ in range(sub):
            k1 = f(X)
            k2 = f(X + h2 * k1)
            k3 = f(X + h2 * k2)
            k4 = f(X + dt * k3)
            X = X + h6 * (k1 + 2 * k2 + 2 * k3 + k4)
        acc.add(X)
    return acc.result()


# ------------------------------------------------------------------------------ (d)
def _transition(wl: Workload) -> np.ndarray:
    """``expm(A_k * dt)`` for every sample; SciPy's expm maps over the leading axis."""
    return scipy.linalg.expm(wl.A_red * DT_GRID)


def expm_batch_first(wl: Workload) -> np.ndarray:
    """(d) Exact discretisation, recurrence ``X <- einsum('bij,bj->bi', Phi, X)``."""
    Phi = _transition(wl)
    X = wl.xd0.copy()
    acc = _Trapz(wl.C_out, batch_last=False)
    acc.add(X, first=True)
    for _ in range(wl.ts.size - 1):
        X = np.einsum("bij,bj->bi", Phi, X)
        acc.add(X)
    return acc.result()


def expm_batch_last(wl: Workload) -> np.ndarray:
    """(d) Exact discretisation, ``(n, n, B)`` layout: ``X <- einsum('ijb,jb->ib', Phi, X)``."""
    Phi = np.ascontiguousarray(np.moveaxis(_transition(wl), 0, -1))
    X = np.ascontiguousarray(wl.xd0.T)
    acc = _Trapz(wl.C_out, batch_last=True)
    acc.add(X, first=True)
    for _ in range(wl.ts.size - 1):
        X = np.einsum("ijb,jb->ib", Phi, X)
        acc.add(X)
    return acc.result()


def expm_reference(wl: Workload) -> np.ndarray:
    """(d) written plainly (full trajectory stored); for small B in tests and checks."""
    Phi = _transition(wl)
    X = np.empty((wl.size, wl.ts.size, wl.A_red.shape[-1]))
    X[:, 0] = wl.xd0
    for i in range(1, wl.ts.size):
        X[:, i] = np.einsum("bij,bj->bi", Phi, X[:, i - 1])
    return metrics_from_outputs(X @ wl.C_out.T)


#: name -> (label, variants). The harness times every variant and keeps the fastest.
PEERS = {
    "solve_ivp": ("(a) solve_ivp RK45 loop", {"loop": solve_ivp_loop}),
    "control": ("(b) python-control initial_response loop", {"loop": control_loop}),
    "rk4": (
        "(c) NumPy RK4 dt=1e-3, batched",
        {"batch-first": rk4_batch_first, "batch-last": rk4_batch_last},
    ),
    "expm": (
        "(d) expm + batched recurrence",
        {"batch-first": expm_batch_first, "batch-last": expm_batch_last},
    ),
}
