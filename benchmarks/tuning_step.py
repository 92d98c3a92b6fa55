r"""Issue 13 (tuning speed): one `fojax.tune` step on the default §3.3.7 study.

What is measured (public API only, one process, float64):

- the study: `study_default.build(B)` (fault-augmented §3.3.7 plant, constant δ in
  [-0.3, 0.3] × 10 constant fault scenarios, zero input, 10 s on a 0.01 s grid: 1,000 steps);
  the tuned design is the generalized LMI design in ``Disk(-3, 2)`` (the FGDO of the study);
- ``fojax.tune(design, study, steps=s)``: ``t_cold`` (s = 1, first call: compiles the step),
  ``t_1`` (s = 1 again) and ``t_{1+k}`` (s = 1 + k); a step costs ``(t_{1+k} − t_1)/k`` (the
  per-call costs cancel: initial parameters, final verification). It includes the
  host-side certification of every iterate (eigenvalues of the error dynamics);
- the gradient part alone: ``jax.value_and_grad`` of ``fojax.studies.study_loss`` with
  respect to the observer's matrices, jitted (compile = first call − warm call);
- the host-side certification of one iterate (``parameterization.host_check``: the traced
  margin, the error dynamics' eigenvalues and the float64 ``certify``), which `tune` runs on
  every accepted candidate;
- with ``--finite-differences`` only (slower: a second loss, its compilations and six more
  forward passes each): gradient agreement, the directional derivative along a random unit
  direction against a central finite difference (steps 1e-4, 1e-5, 1e-6), for IAE and ISE
  of the same ``study_loss``; without it the IAE loss (what `tune` trains) is timed alone;
- wall and process CPU seconds, and ``os.getloadavg()`` before and after: the reference
  machine is a shared 2-core box, so wall times are measured under load.

There is no peer: no SciPy/NumPy library tunes these observers; a user's alternative is
finite differences, whose cost is (number of parameters + 1) forward passes (recorded).

    python benchmarks/tuning_step.py                        # B = 2048, quick
    python benchmarks/tuning_step.py --finite-differences   # + gradient agreement (IAE and ISE)
    python benchmarks/tuning_step.py --B 256 --extra-steps 1
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path


HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import _common  # noqa: E402


_common.limit_blas_threads()
_common.prefer_checkout()

import jax  # noqa: E402


jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import study_default  # noqa: E402

import fojax  # noqa: E402
from fojax.design import design_functional_observer, Disk  # noqa: E402


clock = _common.clock


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--B", type=int, default=2048)
    ap.add_argument("--extra-steps", type=int, default=3)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--finite-differences", action="store_true",
                    help="also check the gradient against central differences, for IAE and ISE")
    ap.add_argument("--out", default=str(_common.RESULTS / "tuning_step_latest.json"))
    args = ap.parse_args()
    info = _common.machine_info()
    load0 = _common.load_average()
    ex, plant, obs, study = study_default.build(args.B)
    design = design_functional_observer(ex.augmented, ex.L_aug, kind="generalized", region=Disk(-3.0, 2.0))

    # the gradient of study_loss alone (IAE: what tune trains; ISE: a smooth loss, where a
    # central difference is a sharp oracle; |e| has kinks where an error crosses zero)
    dyn, st = eqx.partition(design.observer, eqx.is_inexact_array)
    leaves = jax.tree.leaves(dyn)
    keys = jax.random.split(jax.random.PRNGKey(1), len(leaves))
    v = [jax.random.normal(k, x.shape) for k, x in zip(keys, leaves)]
    nrm = float(jnp.sqrt(sum(jnp.sum(x * x) for x in v)))
    v = jax.tree.unflatten(jax.tree.structure(dyn), [x / nrm for x in v])
    n_params = int(sum(x.size for x in leaves))
    grad_rows = {}
    for name in ("iae", "ise") if args.finite_differences else ("iae",):
        loss = eqx.filter_jit(lambda p, s, name=name: fojax.studies.study_loss(s, eqx.combine(p, st), loss=name))
        vg = eqx.filter_jit(lambda p, s, name=name: eqx.filter_value_and_grad(
            lambda q: fojax.studies.study_loss(s, eqx.combine(q, st), loss=name))(p))
        (_, g), vg_first_w, vg_first_c = clock(lambda: vg(dyn, study))
        runs = [clock(lambda: vg(dyn, study))[1:] for _ in range(args.repeats)]
        _, fwd_first_w, _ = clock(lambda: loss(dyn, study))
        fruns = [clock(lambda: loss(dyn, study))[1:] for _ in range(args.repeats)]
        fwd_w = statistics.median(r[0] for r in fruns)
        grad_rows[name] = dict(
            value_and_grad_s=statistics.median(r[0] for r in runs),
            value_and_grad_cpu_s=statistics.median(r[1] for r in runs),
            value_and_grad_compile_s=vg_first_w - statistics.median(r[0] for r in runs),
            forward_s=fwd_w, forward_cpu_s=statistics.median(r[1] for r in fruns),
            forward_compile_s=fwd_first_w - fwd_w,
            # what a user without reverse mode would pay: 2 forward passes per parameter
            finite_difference_gradient_estimate_s=(2 * n_params) * fwd_w,
        )
        if args.finite_differences:
            an = float(sum(jnp.sum(a * b) for a, b in zip(jax.tree.leaves(g), jax.tree.leaves(v))))
            fds = {}
            for eps in (1e-4, 1e-5, 1e-6):
                fds[f"{eps:g}"] = (float(loss(jax.tree.map(lambda a, b: a + eps * b, dyn, v), study))
                                   - float(loss(jax.tree.map(lambda a, b: a - eps * b, dyn, v), study))) / (2 * eps)
            grad_rows[name].update(grad_directional=an, central_differences=fds,
                                   rel_error={e: abs(an - fd) / max(abs(fd), 1e-300) for e, fd in fds.items()})
        print(name, json.dumps(grad_rows[name]), flush=True)

    # the host-side certification of one iterate (tune runs it on every accepted candidate)
    par, params0 = fojax.tuning.initial_parameters(design)
    par.host_check(params0)  # first call compiles the traced margin
    host = [clock(lambda: par.host_check(params0))[1:] for _ in range(args.repeats)]
    host_check_s = min(h[0] for h in host)
    host_check_cpu_s = min(h[1] for h in host)
    print("host_check", host_check_s, host_check_cpu_s, flush=True)

    # the public tuning step
    steps, _, _ = _common.time_tune_steps(
        lambda s: fojax.tune(design, study, steps=s, stepper=fojax.Exact(), quiet=True), args.extra_steps)
    row = dict(
        B=args.B, grid_steps=int(study.ts.shape[0]) - 1, **steps,
        host_check_s=host_check_s, host_check_cpu_s=host_check_cpu_s,
        observer_parameters=n_params, study_loss=grad_rows,
    )
    print(json.dumps(row), flush=True)
    result = dict(
        status="complete",
        benchmark="tuning_step (issue 13): one fojax.tune step on the default 3.3.7 study (exact kernel, adjoint VJP)",
        study=dict(plant="fault-augmented 3.3.7, constant delta in [-0.3, 0.3] x 10 constant faults",
                   design="generalized, Disk(-3, 2)", horizon_s=study_default.T_END, dt_s=study_default.DT),
        target="one tuning step at B = 2,048 <= 0.3 s; compile of a tuning step <= 10 s",
        machine=info, rows=[row], load_average_at_start=load0, load_average_at_end=_common.load_average(),
        note="measured under load: once, on a shared 2-core machine busy with other jobs (see the load "
             "averages); CPU seconds are this process's",
        finite_differences=bool(args.finite_differences),
    )
    _common.write_result(args.out, result)


if __name__ == "__main__":
    main()
