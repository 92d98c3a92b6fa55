r"""The SciPy/NumPy peer of `fojax.run_study` on LTI studies (NumPy and SciPy only: a
process running it never imports JAX, so its peak RSS is the peer's own).

What a competent SciPy user writes for a Monte Carlo study of an uncertain index-1
descriptor plant $E\dot x = (A_0 + \delta_k\,dA)x$, $y = Cx$ with LTI observers: the
index-1 reduction in the SVD coordinates of $E$ for the whole batch in NumPy (the
coordinates are affine in $\delta_k$), the joint plant + observer matrix, one
``scipy.linalg.expm`` on the ``(B, N, N)`` stack, then a batched recurrence over the grid
accumulating the metrics of `run_study` (IAE, ISE, ITAE, peak, settling time; trapezoid
rule on the grid). Used by ``study_default.py`` (the §3.3.7 study) and ``scaling.py``
(random plants of size n).
"""

from __future__ import annotations

import time

import numpy as np
import scipy.linalg


def study_peer(d, bands=None, settle_tol=0.05, timings: dict | None = None):
    """The SciPy/NumPy peer: metrics ``(5, B, K)``; with ``bands = (stride, quantiles)`` also
    the quantile bands the way a NumPy user computes them (errors kept on ``ts[::stride]``,
    then ``np.quantile`` over the samples): ``(nq, T_c, K)``. With a dict `timings`, the
    wall time of its stages is written into it (``build_s``: reduction and joint matrices;
    ``expm_s``; ``stepping_s``: the recurrence and the metrics)."""
    t0 = time.perf_counter()
    E, C, L, ts = d["E"], d["C"], d["L"], d["ts"]
    B = d["delta"].shape[0]
    U, s, Vt = np.linalg.svd(E)
    r = int(np.sum(s > 1e-12 * s[0]))
    V = Vt.T
    # A_k = A0 + δ_k dA is affine in δ: its SVD coordinates U^T A_k V too (two n×n products
    # once instead of 2B)
    At = (U.T @ d["A0"] @ V)[None] + d["delta"][:, None, None] * (U.T @ d["dA"] @ V)[None]
    K = -np.linalg.solve(At[:, r:, r:], At[:, r:, :r])  # (B, n-r, r)
    Tx = V[None, :, :r] + V[None, :, r:] @ K  # (B, n, r)
    As = (At[:, :r, :r] + At[:, :r, r:] @ K) / s[None, :r, None]
    sizes = [o[0].shape[0] for o in d["obs"]]
    N = r + sum(sizes)
    Aj = np.zeros((B, N, N))
    Aj[:, :r, :r] = As
    G = []
    off = r
    for (Ao, By, Co, Dy), sz in zip(d["obs"], sizes):
        Aj[:, off : off + sz, :r] = By @ C @ Tx
        Aj[:, off : off + sz, off : off + sz] = Ao
        g = np.zeros((B, Co.shape[0], N))
        g[:, :, :r] = (Dy @ C - L) @ Tx
        g[:, :, off : off + sz] = Co
        G.append(g)
        off += sz
    G = np.concatenate(G, axis=1)  # (B, K, N)
    h = ts[1] - ts[0]
    t1 = time.perf_counter()
    Phi = scipy.linalg.expm(h * Aj)  # (B, N, N)
    t2 = time.perf_counter()
    w = np.zeros((B, N))
    w[:, :r] = d["x0"] @ V[:, :r]
    PhiT, GT = np.swapaxes(Phi, 1, 2), np.swapaxes(G, 1, 2)
    e = np.einsum("bn,bnk->bk", w, GT)
    a = np.abs(e)
    a0, e0 = a, e
    s1 = np.zeros_like(a)
    s2 = np.zeros_like(a)
    s3 = np.zeros_like(a)
    peak = a.copy()
    last = np.where(a > settle_tol, 0, -1)
    tr = ts - ts[0]
    kept = [e] if bands is not None else None
    for k in range(1, ts.shape[0]):
        w = np.einsum("bn,bnm->bm", w, PhiT)
        e = np.einsum("bn,bnk->bk", w, GT)
        a = np.abs(e)
        s1 += a
        s2 += e * e
        s3 += tr[k] * a
        np.maximum(peak, a, out=peak)
        last = np.where(a > settle_tol, k, last)
        if bands is not None and k % bands[0] == 0:
            kept.append(e)
    T = ts.shape[0]
    if timings is not None:
        timings.update(build_s=t1 - t0, expm_s=t2 - t1, stepping_s=time.perf_counter() - t2)
    iae = h * (s1 + 0.5 * a0 - 0.5 * a)
    ise = h * (s2 + 0.5 * e0**2 - 0.5 * e**2)
    itae = h * (s3 - 0.5 * tr[-1] * a)
    settle = np.where(last < 0, 0.0, np.where(last == T - 1, np.inf, tr[np.minimum(last + 1, T - 1)]))
    mets = np.stack([iae, ise, itae, peak, settle])  # (5, B, K)
    if bands is None:
        return mets
    return mets, np.quantile(np.stack(kept, axis=1), bands[1], axis=0)  # (nq, T_c, K)


