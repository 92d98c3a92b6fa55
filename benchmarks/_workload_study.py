r"""The reference workload of `_workload` as a `fojax.Study`, built with fojax's public API only.

The §4.1.3 observer-based controller loop $u = \hat z$ is assembled by
`fojax.control.closed_loop` from the thesis's printed plant and gains
(`fojax.models.example_4_1_3`, the same printed numbers `_workload` types in NumPy); the
study's plant is that 8-state loop with the uncertainty $\delta_k\,\Delta A$ on the plant
rows (`fojax.UncertainDescriptorSystem`, ``dA`` = ``blkdiag(ΔA, 0)``), the samples are
`_workload`'s own draws (two `fojax.studies.Family` of the same size on the uncertainty
axis, so sample ``k`` is ``(δ_k, x0_k)``: `delta` and the consistent loop state
`x0_cl`), and the functional is `fojax.control.LoopMaps.signal_rows`: the stacked
$[x;\ \hat z - Lx]$. `fojax.run_study(study)` (no observers: the metrics of $z$ itself)
then gives per sample and signal the IAE of $|x_i|$ and of $|\hat z_j - L_j x|$, whose
sums over the first four and the last two signals are `_workload`'s two metrics (IAE of
$\lVert x\rVert_1$ and of $\lVert\hat z - Lx\rVert_1$: the trapezoid rule is linear).
Used by `reference_workload.py` (``--fojax-mode run-study``) and
tests/test_study_signal.py, which checks that equality against `peers.expm_reference`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


SIGNAL_NAMES = ("x1", "x2", "x3", "x4", "e1", "e2")  # [x; ẑ − L x]
N_STATE = 4  # the first four signals are the plant state


def loop_413():
    """``(loop, rows)``: the implementable §4.1.3 loop (8 states, `fojax.DescriptorSystem`)
    and the ``(6, 8)`` rows of ``[x; ẑ − L x]`` on its state ``[x; ζ; v]``."""
    import fojax

    ex = fojax.models.example_4_1_3()
    p, m = ex.C.shape[0], ex.B.shape[1]
    E_perp = np.asarray(ex.E_perp)
    Wu = np.vstack([-E_perp @ np.asarray(ex.B), np.zeros((p, m))])  # w = [−E⊥ B u; y]
    Wy = np.vstack([np.zeros((E_perp.shape[0], p)), np.eye(p)])
    obs = fojax.GeneralizedFunctionalObserver(ex.N, ex.J, ex.F, ex.H, ex.S, ex.G, ex.M, ex.P, ex.Q, Wu, Wy)
    loop = fojax.control.closed_loop(ex.system, obs)
    rows = fojax.control.loop_maps(ex.system, obs).signal_rows(ex.L)
    return loop, np.asarray(rows)


def workload_study(delta, x0_cl, ts, delta_A):
    """The `fojax.Study` of the samples ``delta`` ``(B,)``, ``x0_cl`` ``(B, 8)`` on the grid
    ``ts``, with the plant's uncertainty direction ``delta_A`` ``(4, 4)``."""
    import fojax
    from fojax.studies import Family

    loop, rows = loop_413()
    n = loop.n
    dA = np.zeros((1, n, n))
    dA[0, : delta_A.shape[0], : delta_A.shape[1]] = delta_A  # the plant rows of the loop only
    plant = fojax.UncertainDescriptorSystem(loop, dA=dA)
    delta = jnp.asarray(delta, dtype=jnp.float64)[:, None]
    x0_cl = jnp.asarray(x0_cl, dtype=jnp.float64)
    families = (Family(jax.vmap(fojax.Constant)(delta), ("plant", "delta")), Family(x0_cl, ("x0",)))
    return fojax.Study(plant, x0_cl[0], ts, rows, uncertainty=families, signal_names=SIGNAL_NAMES)


def of_workload(wl):
    """`workload_study` of a `_workload.Workload` batch."""
    import _workload

    return workload_study(wl.delta, wl.x0_cl, wl.ts, _workload.DELTA_A)


def two_metrics(result) -> np.ndarray:
    """``(B, 2)``: the summed per-signal IAEs of a `run_study` result of that study (the
    workload's IAE of ‖x‖₁ and of ‖ẑ − Lx‖₁)."""
    iae = np.asarray(result.metrics["iae"])[0, :, 0, :]  # (B, 6): observer "z", fault axis of size 1
    return np.stack([iae[:, :N_STATE].sum(axis=1), iae[:, N_STATE:].sum(axis=1)], axis=1)
