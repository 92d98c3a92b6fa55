r"""Issue 13, item 3: one `fojax.tune` step on the time-varying §3.3.7 study (δ(t) = a sin(ωt + φ)).

The study is `study_default.build(B, delta="sine")` (fault-augmented §3.3.7 plant, |a| ≤ 0.3,
ω ∈ [0.5, 5] rad/s, 10 constant fault scenarios, zero input, 10 s on a 0.01 s grid: 1,000
grid steps, 1,140 ETDRK4 steps); the tuned design is the generalized LMI design in
``Disk(-3, 2)``. Engines (public API only):

- ``exponential``: ``fojax.tune(design, study)`` (default `fojax.Auto()`: since this change
  the jitted step runs `study_loss` on the exponential engine, reverse mode through the
  checkpointed ETDRK4 recurrence);
- ``diffrax`` (``--before``): ``fojax.tune(..., stepper=fojax.Diffrax())``, what the step
  ran before (`vmap(simulate)` with diffrax's Kvaerno5: `Auto`'s fallback for δ(t)); slow,
  so only at the sizes given by ``--before-sizes``.

Per engine and B: ``t_cold`` (``steps=1``, first call: host passes + compilation of the
step), ``t_1`` (``steps=1`` again) and ``t_{1+k}``; a step costs ``(t_{1+k} − t_1)/k``
(the per-call costs cancel: set-up, host passes, final certification). Agreement first: the
first step's training loss of both engines (diffrax at its tolerances) and of
`fojax.run_study`'s exponential engine (the same ETDRK4, another code path). Wall and
process CPU seconds and ``os.getloadavg()``: measured under load on a shared 2-core machine.

    python benchmarks/tuning_time_varying.py --sizes 256 1024
    python benchmarks/tuning_time_varying.py --sizes 256 --before --before-sizes 20
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import _common  # noqa: E402


_common.limit_blas_threads()
_common.prefer_checkout()

import jax  # noqa: E402


jax.config.update("jax_enable_x64", True)

import study_default  # noqa: E402

import fojax  # noqa: E402
from fojax.design import design_functional_observer, Disk  # noqa: E402


def measure(design, study, k, **opts):
    row, r0, _ = _common.time_tune_steps(
        lambda s: fojax.tune(design, study, steps=s, barrier=0.0, quiet=True, **opts), k)
    return row, float(r0.history["train_loss"][0])


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", type=int, nargs="+", default=[256, 1024])
    ap.add_argument("--extra-steps", type=int, default=2)
    ap.add_argument("--before", action="store_true", help="also time the diffrax step (what tune ran before)")
    ap.add_argument("--before-sizes", type=int, nargs="+", default=[20])
    ap.add_argument("--out", default=str(_common.RESULTS / "tuning_time_varying_latest.json"))
    args = ap.parse_args()
    info = _common.machine_info()
    load0 = _common.load_average()
    rows = []
    sizes = sorted(set(args.sizes) | (set(args.before_sizes) if args.before else set()))
    for B in sizes:
        ex, _, _, study = study_default.build(B, delta="sine")
        design = design_functional_observer(ex.augmented, ex.L_aug, kind="generalized", region=Disk(-3.0, 2.0))
        ref = fojax.run_study(study, design.observer, quiet=True, quantiles=())
        ref_loss = float(ref.metrics["iae"][0].mean())
        engines = (["exponential"] if B in args.sizes else []) + (
            ["diffrax"] if args.before and B in args.before_sizes else [])
        for engine in engines:
            opts = {} if engine == "exponential" else dict(stepper=fojax.Diffrax())
            row, first_loss = measure(design, study, args.extra_steps, **opts)
            row.update(B=B, engine=engine, grid_steps=int(study.ts.shape[0]) - 1,
                       run_study_engine=ref.attrs["engine"],
                       first_train_loss_rel_diff_vs_run_study=abs(first_loss - ref_loss) / abs(ref_loss),
                       load_average=_common.load_average())
            print(json.dumps(row), flush=True)
            rows.append(row)
    result = dict(
        status="complete",
        benchmark="tuning_time_varying (issue 13, item 3): one fojax.tune step on the time-varying 3.3.7 study",
        study=dict(plant="fault-augmented 3.3.7, delta(t) = a sin(w t + phi), |a| <= 0.3, w in [0.5, 5] rad/s, "
                         "x 10 constant faults", design="generalized, Disk(-3, 2)",
                   horizon_s=study_default.T_END, dt_s=study_default.DT),
        engines=dict(exponential="tune default (Auto): study_loss on the exponential engine (ETDRK4, reverse mode "
                                 "through the checkpointed recurrence)",
                     diffrax="tune(stepper=Diffrax()): vmap(simulate) with Kvaerno5, what the step ran before"),
        machine=info, rows=rows, load_average_at_start=load0, load_average_at_end=_common.load_average(),
        note="measured under load: once, on a shared 2-core machine busy with other jobs (see the load averages); "
             "CPU seconds are this process's",
    )
    _common.write_result(args.out, result)


if __name__ == "__main__":
    main()
