r"""Design time and peak memory against the state dimension n, for three problem shapes and
both design routes of `fojax.design_functional_observer` (the Riccati/Stein route and the
region LMI route), and for the default call (``method=None``).

What is measured
----------------
For each shape in ``--shapes``, each n in ``--dims`` (default 25, 50, 100, 200, 500, 1000)
and each route in ``--methods`` (``default`` = ``method=None``, ``riccati``, ``lmi``): one call
of the public entry point

    fojax.design_functional_observer(sys, L, kind=--kind, region=Disk(-3, 2), q0=q0, method=...)

on a random stable index-1 descriptor plant (`scaling.random_stable_index1`: $E = U\,
\mathrm{diag}(I_r, 0)V$ with ``n_alg`` algebraic equations) with ``m = 2`` inputs, ``p``
random outputs and a random functional $L$ with ``q`` rows. The shapes:

- ``half``: ``n_alg = n // 4``, ``p = n // 4``, ``q = q0 = n // 2`` (the family of
  ``design_scaling.py``; ``q0`` given);
- ``few-outputs``: ``n_alg = n // 3``, ``p = max(2, n // 10)``, ``q = 3``, ``R`` and ``q0`` by
  fojax's default (`fojax.design.default_R`);
- ``many-outputs``: ``n_alg = n // 5``, ``p = n // 2``, ``q = max(2, n // 10)``, default ``R``.

Each design runs in a fresh Python process (``_common.run_worker``) after an untimed n = 8
warm-up design of the same shape and route (imports, JAX compilation of small kernels).
Recorded per row: the wall and CPU time of the call, the peak resident set size of the
process (``resource.getrusage``, includes the interpreter, JAX and SciPy: ``rss_before_mib``
is the level before the call), the observer order, the route the design reports, whether it
passed its float64 verification, the error eigenvalues' largest distance into the region,
the load average before and after (the machine is shared) and, for LMI solves, the time
inside cvxpy's ``Problem.solve`` split into cvxpy's canonicalisation
(``Problem.compilation_time``) and the solver's own time. Failures (typed errors, a timeout)
are rows. A (shape, route) stops at the first n whose design takes longer than
``--budget`` s or is killed after ``--hard-timeout`` s.

Results: ``results/design_routes_<date>.{md,json}`` and ``..._latest.{md,json}``.

Examples::

    python benchmarks/design_routes.py
    python benchmarks/design_routes.py --shapes few-outputs --dims 25 50 --methods lmi
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import traceback
from pathlib import Path


HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import _common  # noqa: E402


if __name__ == "__main__":
    _common.limit_blas_threads()  # before NumPy (see _common)
    _common.prefer_checkout()  # measure this checkout's fojax

import numpy as np  # noqa: E402
from design_scaling import record_cvxpy_solves  # noqa: E402
from scaling import random_stable_index1  # noqa: E402


DIMS = (25, 50, 100, 200, 500, 1000)
SHAPES = ("half", "few-outputs", "many-outputs")
METHODS = ("default", "riccati", "lmi")
DEFAULT_SEED = 20261206
N_INPUTS = 2
REGION = (-3.0, 2.0)


def problem(shape: str, n: int, seed: int):
    """``(E, A, B, C, L, q0)`` of `shape` at dimension `n` (module docstring)."""
    n_alg, p, q, q0 = {
        "half": (max(1, n // 4), max(1, n // 4), max(1, n // 2), max(1, n // 2)),
        "few-outputs": (max(1, n // 3), max(2, n // 10), 3, None),
        "many-outputs": (max(1, n // 5), max(1, n // 2), max(2, n // 10), None),
    }[shape]
    loop = random_stable_index1(n, seed + n, n_alg=n_alg)
    rng = np.random.default_rng([seed, n, SHAPES.index(shape)])
    return loop.E, loop.A, rng.standard_normal((n, N_INPUTS)), rng.standard_normal((p, n)), \
        rng.standard_normal((q, n)), q0


def worker(spec: dict) -> dict:
    import jax

    jax.config.update("jax_enable_x64", True)
    import fojax
    from fojax.design import design_functional_observer, Disk

    shape, n, method, kind = spec["shape"], spec["n"], spec["method"], spec["kind"]
    res: dict = {"shape": shape, "n": n, "method": method, "kind": kind}

    def design(n_):
        E, A, B, C, L, q0 = problem(shape, n_, spec["seed"])
        return design_functional_observer(fojax.DescriptorSystem(E, A, B, C), L, kind=kind, region=Disk(*REGION),
                                          q0=q0, method=None if method == "default" else method)

    t0 = time.perf_counter()
    try:
        design(8)
    except fojax.FojaxError as e:
        res["warmup_error"] = f"{type(e).__name__}: {e}"[:500]
    res["warmup_s"] = time.perf_counter() - t0
    E, A, B, C, L, q0 = problem(shape, n, spec["seed"])
    res.update(p=int(C.shape[0]), q=int(L.shape[0]), rank_E=int(np.linalg.matrix_rank(E)), q0_given=q0)
    res["rss_before_mib"] = _common.current_rss_mib()
    res["load_average_before"] = list(os.getloadavg())
    with record_cvxpy_solves() as calls:
        c0, t0 = time.process_time(), time.perf_counter()
        try:
            d = design(n)
            res["status"] = "ok"
        except fojax.FojaxError as e:
            d, res["status"], res["error"] = None, f"failed: {type(e).__name__}", str(e)[:1500]
        except Exception as e:  # noqa: BLE001 - a row, not a crash
            d, res["status"], res["error"] = None, f"crashed: {type(e).__name__}", traceback.format_exc()[-2000:]
        res["total_s"] = time.perf_counter() - t0
        res["cpu_s"] = time.process_time() - c0
    res["peak_rss_mib"] = _common.peak_rss_mib()
    res["load_average_after"] = list(os.getloadavg())
    if calls:
        res["cvxpy_solve_s"] = sum(c["wall_s"] for c in calls)
        res["cvxpy_solver_s"] = sum(c["solver_time_s"] or 0.0 for c in calls)
        res["cvxpy_canonicalisation_s"] = sum(float(getattr(c["problem"], "compilation_time", None) or 0.0)
                                              for c in calls)
        res["cvxpy_calls"] = len(calls)
        res["cvxpy_scalar_variables"] = int(calls[-1]["problem"].size_metrics.num_scalar_variables)
    if d is not None:
        lmi = d.solver.get("lmi", {})
        res.update(route=lmi.get("method"), route_line=str(lmi.get("route"))[:300], q0=int(d.observer.q0),
                   q1=int(d.observer.q1), verified=bool(d.report.passed),
                   region_margin=float(np.min(Disk(*REGION).margin(np.asarray(d.report.eigenvalues)))))
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    ap.add_argument("--dims", type=int, nargs="+", default=list(DIMS))
    ap.add_argument("--shapes", nargs="+", default=list(SHAPES), choices=SHAPES)
    ap.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
    ap.add_argument("--kind", default="generalized", choices=("generalized", "PI", "proportional"))
    ap.add_argument("--budget", type=float, default=120.0,
                    help="stop increasing n for a (shape, route) once one design takes longer (s)")
    ap.add_argument("--hard-timeout", type=float, default=300.0, help="kill a design after this many seconds")
    ap.add_argument("--seed", type=int, default=DEFAULT_SEED)
    ap.add_argument("--out", type=Path, default=_common.RESULTS)
    ap.add_argument("--name", default="design_routes", help="result file name")
    ap.add_argument("--merge", nargs="+", type=Path,
                    help="combine these result JSONs (rows with status ok, stops, each run's machine record) "
                         "into results/<--name>_latest instead of measuring")
    ap.add_argument("--stopped", nargs="*", default=[], help="with --merge: 'key=reason' stops to record")
    args = ap.parse_args(argv)
    if _common.served_as_worker(args, worker):
        return 0
    if args.merge:
        runs = [json.loads(Path(f).read_text()) for f in args.merge]
        rows = sorted((r for run in runs for r in run["rows"] if r.get("status") == "ok"),
                      key=lambda r: (r["n"], SHAPES.index(r["shape"]), METHODS.index(r["method"])))
        stopped = {k: v for run in runs for k, v in run["stopped"].items()}
        stopped.update(dict(kv.split("=", 1) for kv in args.stopped))
        payload = dict(runs[0], study=args.name, status="merged", rows=rows, stopped=stopped,
                       runs=[{"settings": run["settings"], "machine": run["machine"]} for run in runs])
        _common.write_results(args.out, args.name, payload, render_markdown(payload), echo=True)
        return 0
    info = _common.machine_info()
    print(f"# design routes ({info['date']}, {info['cpu']}, {info['cores_available']} cores)", flush=True)
    rows, stopped = [], {}
    for n in sorted(set(args.dims)):
        for shape in args.shapes:
            for method in args.methods:
                key = f"{shape}/{method}"
                if key in stopped:
                    continue
                spec = dict(shape=shape, n=n, method=method, kind=args.kind, seed=args.seed)
                res = _common.run_worker(Path(__file__), spec, args.hard_timeout)
                for k, v in spec.items():
                    res.setdefault(k, v)
                rows.append(res)
                print(f"  n = {n:4d} {shape:13s} {method:8s} {res.get('status')}: "
                      f"{_common.fmt(res.get('total_s'), '.3g')} s, peak {_common.fmt(res.get('peak_rss_mib'), '.0f')} MiB, "
                      f"route {res.get('route')}, q0 = {res.get('q0')}, verified {res.get('verified')}", flush=True)
                reason = _common.stop_reason(res, n, args.hard_timeout, args.budget)
                if reason:
                    stopped[key] = reason
                write(info, args, rows, stopped, "partial")
    write(info, args, rows, stopped, "complete", echo=True)
    return 0


def write(info, args, rows, stopped, status, echo=False):
    payload = _common.result_payload(
        args.name, status, info, args, region=f"Disk{REGION}", rows=rows, stopped=stopped,
        note="2-core machine shared with other jobs: see load_average_before/after per row and the machine's "
             "load_average_at_start/end; peak RSS includes the interpreter, JAX and SciPy (rss_before_mib)")
    _common.write_results(args.out, args.name, payload, render_markdown(payload), echo=echo)


def render_markdown(d: dict) -> str:
    fmt = _common.fmt
    lines = [
        "# Observer design time and memory vs n: three shapes, both routes and the default call",
        "",
        f"- status: {d['status']}",
        *_common.machine_lines(d["machine"]),
        f"- `design_functional_observer(sys, L, kind={d['settings']['kind']!r}, region=Disk{REGION}, q0, method)`; "
        f"budget {d['settings']['budget']} s, hard timeout {d['settings']['hard_timeout']} s",
        "",
        "| n | shape | method | route | q0 | p | q | status | total (s) | CPU (s) | peak RSS (MiB) | RSS before (MiB) | "
        "cvxpy canon. (s) | solver (s) | verified | load before |",
        "|---:|---|---|---|---:|---:|---:|---|---:|---:|---:|---:|---:|---:|---|---|",
    ]
    for r in d["rows"]:
        lines.append(
            f"| {r['n']} | {r['shape']} | {r['method']} | {r.get('route') or '—'} | {r.get('q0', '—')} | "
            f"{r.get('p', '—')} | {r.get('q', '—')} | {r.get('status')} | {fmt(r.get('total_s'), '.3g')} | "
            f"{fmt(r.get('cpu_s'), '.3g')} | {fmt(r.get('peak_rss_mib'), '.0f')} | {fmt(r.get('rss_before_mib'), '.0f')} | "
            f"{fmt(r.get('cvxpy_canonicalisation_s'), '.3g')} | {fmt(r.get('cvxpy_solver_s'), '.3g')} | "
            f"{r.get('verified', '—')} | {fmt((r.get('load_average_before') or [None])[0], '.2f')} |")
    lines += _common.stop_and_failure_lines(d, lambda r: f"n = {r['n']}, {r['shape']}, {r['method']}")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
