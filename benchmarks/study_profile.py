"""Issue 13: where the time of the two product paths that miss their targets goes.

1. **Quantile bands** of `run_study` on the default §3.3.7 study (`study_default.build`):
   process CPU seconds of the exact kernel (`run_batched` on `exact_problem`, what
   `run_study` calls) without and with the band trajectories (``keep = 0`` / the default
   band stride 5, and 16), at chunk sizes 2,048 (what `_run_batch` uses when
   bands are kept) and 4,096; then the host's ``band_quantiles`` (one ``np.sort``) against
   ``np.partition`` on only the needed order statistics (the same numbers: checked equal
   here) on the same ``(201, 2, 5, B)`` errors.
2. **The study-loss gradient** (`fojax.studies.study_loss`, IAE, the generalized design of
   `tuning_step.py`): jitted value-and-gradient and forward, CPU seconds, on the 10 s
   horizon (1,000 steps) and on a 0.5 s one (50 steps): the short horizon's cost is mostly
   the per-sample set-up (joint matrices, the differentiable ``expm``) and its reverse mode.

Process CPU time is reported (min of ``--repeats``) because the reference machine is a
shared 2-core box: wall times there are measured under load (``os.getloadavg()`` recorded).

    python benchmarks/study_profile.py --B 10000 --B-grad 512
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path


HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import _common  # noqa: E402


_common.limit_blas_threads()
_common.prefer_checkout()

import jax  # noqa: E402


jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import numpy as np  # noqa: E402
import study_default  # noqa: E402

import fojax  # noqa: E402
from fojax.design import design_functional_observer, Disk  # noqa: E402
from fojax.simulation._batch import DEFAULT_BLOCK  # noqa: E402
from fojax.simulation._driver import run_batched  # noqa: E402
from fojax.studies._exact import exact_problem  # noqa: E402
from fojax.studies._runner import band_quantiles  # noqa: E402


def cpu(f, repeats):
    """``(min wall, min CPU)`` seconds of ``f()`` (outputs ready) after one warm-up call."""
    jax.block_until_ready(f())
    ws, cs = [], []
    for _ in range(repeats):
        w, c = time.perf_counter(), time.process_time()
        jax.block_until_ready(f())
        ws.append(time.perf_counter() - w)
        cs.append(time.process_time() - c)
    return min(ws), min(cs)


def bands(B, repeats):
    ex, plant, obs, study = study_default.build(B)
    rows = []
    for keep in (0, 5, 16):
        (problem, basis, idx), _ = exact_problem(study, obs, 0.05, keep)
        for chunk in (2048, 4096):
            w, c = cpu(lambda: run_batched(problem, idx, study.ts, chunk_size=chunk, block=DEFAULT_BLOCK,
                                           basis=basis)[0], repeats)
            rows.append(dict(keep_stride=keep, chunk_size=chunk, wall_s=w, cpu_s=c, load_average=_common.load_average()))
            print(rows[-1], flush=True)
    (problem, basis, idx), _ = exact_problem(study, obs, 0.05, 5)
    traj = run_batched(problem, idx, study.ts, chunk_size=4096, block=DEFAULT_BLOCK, basis=basis)[0][1]
    E = np.asarray(traj).reshape(traj.shape[0], len(obs), -1, B)
    q = (0.05, 0.25, 0.5, 0.75, 0.95)
    ref = np.quantile(E, q, axis=-1)
    got = band_quantiles(E, q)
    virt = (B - 1) * np.asarray(q)
    kth = np.unique(np.concatenate([np.floor(virt), np.minimum(np.floor(virt) + 1, B - 1)]).astype(int))
    part = np.partition(E, kth, axis=-1)
    lo = np.floor(virt).astype(int)
    hi = np.minimum(lo + 1, B - 1)
    a, b = np.moveaxis(part[..., lo], -1, 0), np.moveaxis(part[..., hi], -1, 0)
    g = (virt - lo).reshape((-1,) + (1,) * (a.ndim - 1))
    via_partition = np.where(g >= 0.5, b - (b - a) * (1 - g), a + (b - a) * g)
    host = dict(
        band_quantiles_equal_np_quantile=bool(np.array_equal(got, ref)),
        partition_equal_np_quantile=bool(np.array_equal(via_partition, ref)),
        band_quantiles_sort=cpu(lambda: band_quantiles(E, q), repeats),
        np_partition_needed_order_statistics=cpu(lambda: np.partition(E, kth, axis=-1), repeats),
        np_quantile=cpu(lambda: np.quantile(E, q, axis=-1), 1),
        load_average=_common.load_average(),
    )
    print(host, flush=True)
    return dict(B=B, kernel=rows, host_quantiles_wall_cpu_s=host)


def grad(B, repeats):
    out = []
    for t_end in (10.0, 0.5):
        study_default.T_END = t_end
        ex, plant, obs, study = study_default.build(B)
        design = design_functional_observer(ex.augmented, ex.L_aug, kind="generalized", region=Disk(-3.0, 2.0))
        dyn, st = eqx.partition(design.observer, eqx.is_inexact_array)
        loss = eqx.filter_jit(lambda p, s: fojax.studies.study_loss(s, eqx.combine(p, st)))
        vg = eqx.filter_jit(lambda p, s: eqx.filter_value_and_grad(
            lambda q: fojax.studies.study_loss(s, eqx.combine(q, st)))(p))
        w, c = cpu(lambda: vg(dyn, study), repeats)
        fw, fc = cpu(lambda: loss(dyn, study), repeats)
        out.append(dict(horizon_s=t_end, steps=int(study.ts.shape[0]) - 1, B=B, value_and_grad_wall_s=w,
                        value_and_grad_cpu_s=c, forward_wall_s=fw, forward_cpu_s=fc,
                        load_average=_common.load_average()))
        print(out[-1], flush=True)
    study_default.T_END = 10.0
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--B", type=int, default=10000)
    ap.add_argument("--B-grad", type=int, default=512)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", default=str(_common.RESULTS / "study_profile_latest.json"))
    args = ap.parse_args()
    info = _common.machine_info()
    load0 = _common.load_average()
    result = dict(
        status="complete",
        benchmark="study_profile (issue 13): band cost of run_study and set-up vs time loop of the study-loss gradient",
        bands=bands(args.B, args.repeats), study_loss_gradient=grad(args.B_grad, args.repeats),
        machine=info, load_average_before=load0, load_average_after=_common.load_average(),
        note="measured once on a shared 2-core machine under load (see load averages); CPU seconds are min of repeats",
    )
    _common.write_result(args.out, result)


if __name__ == "__main__":
    main()
