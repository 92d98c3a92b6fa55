r"""Issue 7, item 4 (tuning): time of one gradient-tuning step against the training batch size.

What is measured
----------------
The setup of ``notebooks/monte_carlo_and_tuning.ipynb``: the fault-augmented §3.3.7
benchmark (`fojax.models.example_3_3_7()`, 9 states), its generalized LMI design in
``Disk(-2, 1)``, the uncertain plant $A + \delta\Delta A$ with a constant $\delta$ per
sample, the sine input, ``ts = linspace(0, 4, 81)`` and a training `fojax.studies.Study`
of ``B = N_u × N_f`` samples (``constant_delta`` × ``constant_faults``; the factorisation
is as square as possible, e.g. 32 = 8 × 4, and is recorded). For each B in ``--sizes``
(default 8, 32, 128, 512, 2048), in a fresh process (cold JAX caches):

1. ``t_cold``  = wall time of ``fojax.tuning.tune(design, study, steps=1, ...)`` — the first
   call: it compiles the tuning step, makes one step and verifies the result;
2. ``t_1``     = the same call again (warm);
3. ``t_{1+k}`` = ``tune(design, study, steps=1 + k, ...)`` (warm), ``k = --extra-steps`` (5).

Reported: per-step time ``(t_{1+k} − t_1) / k`` (the fixed per-call costs cancel), the
compile time ≈ ``t_cold − per-step`` (it also holds the one-off host work of the first call),
the warm fixed overhead per call ``t_1 − per-step``, samples·steps/s, whether the warm calls
retraced the step (``fojax.tuning._tune.TRACE_COUNTS``), the training losses (finite) and the peak
RSS. With ``--repeats r`` the warm pair (2, 3) is repeated and the medians are used.
Options as in the notebook: ``optax.adam(0.3)``, ``stepper=fojax.Exact()`` (``--method exact``),
``quiet=True``; only the public `tune` API is used.

Results: ``results/tuning_scaling_<date>.{md,json}`` and ``..._latest.{md,json}``.

Examples::

    python benchmarks/tuning_scaling.py
    python benchmarks/tuning_scaling.py --sizes 8 32 --extra-steps 2
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from pathlib import Path


HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import _common  # noqa: E402


if __name__ == "__main__":
    _common.limit_blas_threads()  # before NumPy (see _common)
    _common.prefer_checkout()  # measure this checkout's fojax


SIZES = (8, 32, 128, 512, 2048)


def factor(B: int) -> tuple[int, int]:
    """``(N_u, N_f)`` with ``N_u * N_f = B`` and ``N_f`` the largest divisor ``<= sqrt(B)``."""
    nf = max(d for d in range(1, math.isqrt(B) + 1) if B % d == 0)
    return B // nf, nf


def build(nu: int, nf: int):
    """The notebook's design and a training study of ``nu * nf`` samples."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    import fojax
    from fojax import studies as S
    from fojax.design import design_functional_observer, Disk

    ex = fojax.models.example_3_3_7()
    gen = design_functional_observer(ex.augmented, ex.L_aug, kind="generalized", region=Disk(-2.0, 1.0))
    dA = np.zeros((1, 9, 9))
    dA[0, :6, :6] = ex.dA
    plant = fojax.UncertainDescriptorSystem(ex.augmented, dA=dA, delta=fojax.Constant(jnp.zeros(1)))
    x0 = jnp.zeros(9).at[:4].set(jnp.array([1.0, -0.5, 0.5, 0.2]))
    u = fojax.Sine(jnp.array([1.0, 0.5]), jnp.array([1.0, 2.0]))
    ts = jnp.linspace(0.0, 4.0, 81)
    kd, kf = jax.random.split(jax.random.PRNGKey(1))
    study = S.Study(plant, x0, ts, ex.L_aug, u, uncertainty=(S.constant_delta(kd, nu, 1),),
                    scenarios=(S.constant_faults(kf, nf, x0, 3),), signal_names=("z1", "z2", "f1", "f2", "f3"))
    return gen, study


def worker(spec: dict) -> dict:
    import jax

    jax.config.update("jax_enable_x64", True)
    import optax

    import fojax
    from fojax import tuning

    B, k = spec["B"], spec["extra_steps"]
    nu, nf = factor(B)
    res: dict = {"B": B, "N_u": nu, "N_f": nf, "extra_steps": k, "method": spec["method"]}
    t0 = time.perf_counter()
    design, study = build(nu, nf)
    res["setup_s"] = time.perf_counter() - t0

    # one optimizer object for every call: the jitted step is compiled per optimizer object
    # (optax transformations are closures), so a new `optax.adam(...)` per call would retrace
    opt = optax.adam(0.3)

    def run(steps):
        before = sum(tuning._tune.TRACE_COUNTS.values())
        t0 = time.perf_counter()
        stepper = {"auto": fojax.Auto(), "exact": fojax.Exact(), "exponential": fojax.Exponential(),
                   "diffrax": fojax.Diffrax()}[spec["method"]]
        out = tuning.tune(design, study, steps=steps, optimizer=opt, stepper=stepper, quiet=True)
        t = time.perf_counter() - t0
        return t, sum(tuning._tune.TRACE_COUNTS.values()) - before, out

    rss0 = _common.current_rss_mib()
    res["t_cold_s"], res["traces_cold"], out = run(1)
    t1s, tks, traces_warm = [], [], 0
    for _ in range(max(1, spec["repeats"])):
        t1, tr1, _ = run(1)
        tk, trk, out = run(1 + k)
        t1s.append(t1)
        tks.append(tk)
        traces_warm += tr1 + trk
    t1, tk = statistics.median(t1s), statistics.median(tks)
    per_step = (tk - t1) / k
    res.update(
        t_1_s=t1,
        t_1_all_s=t1s,
        t_1pk_s=tk,
        t_1pk_all_s=tks,
        per_step_s=per_step,
        compile_s=res["t_cold_s"] - per_step,
        warm_fixed_overhead_s=t1 - per_step,
        sample_steps_per_s=B / per_step if per_step > 0 else None,
        traces_warm_calls=traces_warm,
        retraced_on_warm_calls=traces_warm > 0,
        train_loss=[float(x) for x in out.history["train_loss"]],
        rss_before_mib=rss0,
        peak_rss_mib=_common.peak_rss_mib(),
        status="ok",
    )
    if not all(math.isfinite(x) for x in res["train_loss"]):
        res["status"] = "non-finite training loss"
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    ap.add_argument("--sizes", type=int, nargs="+", default=list(SIZES), help="training batch sizes B")
    ap.add_argument("--extra-steps", type=int, default=5, help="k: per-step time = (t(1+k) - t(1)) / k")
    ap.add_argument("--repeats", type=int, default=1, help="repetitions of the warm pair t(1), t(1+k)")
    ap.add_argument("--method", default="exact", choices=("auto", "exact", "exponential", "diffrax"),
                    help="tune's stepper: fojax.Auto/Exact/Exponential/Diffrax() (notebook: exact)")
    ap.add_argument("--hard-timeout", type=float, default=1800.0, help="kill one B's process after this many s")
    ap.add_argument("--out", type=Path, default=_common.RESULTS)
    args = ap.parse_args(argv)
    if _common.served_as_worker(args, worker):
        return 0
    if args.extra_steps < 1:
        ap.error("--extra-steps must be at least 1")

    info = _common.machine_info()
    print(f"# tuning scaling ({info['date']}, {info['cpu']}, {info['cores_available']} cores)")
    rows = []
    for B in sorted(set(args.sizes)):
        spec = dict(B=B, extra_steps=args.extra_steps, repeats=args.repeats, method=args.method)
        res = _common.run_worker(Path(__file__), spec, args.hard_timeout)
        res.setdefault("B", B)
        res.setdefault("status", "crashed")
        rows.append(res)
        print(
            f"  B = {B:5d}: {res['status']}; cold {_common.fmt(res.get('t_cold_s'), '.3g')} s, "
            f"per step {_common.fmt(res.get('per_step_s'), '.3g')} s, compile ≈ {_common.fmt(res.get('compile_s'), '.3g')} s, "
            f"retraced on warm calls: {res.get('retraced_on_warm_calls')}",
            flush=True,
        )
        write(info, args, rows, "partial")
    write(info, args, rows, "complete", echo=True)
    return 0 if all(r["status"] == "ok" for r in rows) else 1


def write(info, args, rows, status, echo=False):
    payload = _common.result_payload(
        "tuning_scaling",
        status,
        info,
        args,
        setup="notebooks/monte_carlo_and_tuning.ipynb: example_3_3_7, generalized design in Disk(-2, 1), "
        "constant delta x constant faults, ts = linspace(0, 4, 81), optax.adam(0.3)",
        rows=rows,
    )
    _common.write_results(args.out, "tuning_scaling", payload, render_markdown(payload), echo=echo)


def render_markdown(d: dict) -> str:
    fmt, s = _common.fmt, d["settings"]
    lines = [
        "# One gradient-tuning step vs training batch size (issue 7)",
        "",
        f"- status: {d['status']}",
        *_common.machine_lines(d["machine"]),
        f"- `fojax.tuning.tune(design, study, steps, optimizer=optax.adam(0.3), stepper=<{s['method']}>, quiet=True)` "
        "on the §3.3.7 setup of notebooks/monte_carlo_and_tuning.ipynb (9 states, 81 grid points, 5 signals); "
        f"per step = (t(1+k) − t(1)) / k with k = {s['extra_steps']}; compile ≈ first call − per step; "
        "one fresh process per B",
        "",
        "| B (N_u × N_f) | first call (s) | per step (s) | sample-steps/s | compile ≈ (s) | warm overhead/call (s) | "
        "retraced when warm | peak RSS (MiB) | status |",
        "|---:|---:|---:|---:|---:|---:|---|---:|---|",
    ]
    for r in d["rows"]:
        lines.append(
            f"| {r['B']} ({r.get('N_u', '?')} × {r.get('N_f', '?')}) | {fmt(r.get('t_cold_s'), '.3g')} | "
            f"{fmt(r.get('per_step_s'), '.3g')} | {fmt(r.get('sample_steps_per_s'), '.3g')} | "
            f"{fmt(r.get('compile_s'), '.3g')} | {fmt(r.get('warm_fixed_overhead_s'), '.3g')} | "
            f"{ {True: 'yes', False: 'no'}.get(r.get('retraced_on_warm_calls'), '—') } | {fmt(r.get('peak_rss_mib'), '.0f')} | {r['status']} |"
        )
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
