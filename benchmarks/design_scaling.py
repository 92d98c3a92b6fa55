r"""Issues 7 and 16 (design): time of fojax's verified observer design against the state
dimension n, by the LMI route and the Riccati route, so users know what to expect.

What is measured
----------------
For each n in ``--dims`` (default 4, 8, 16, 32, 50, 100, 200, 300, 500), each kind in
``--kinds`` (default ``generalized`` and ``proportional``) and each route in ``--methods``
(default ``riccati`` and ``lmi``; the LMI route only up to ``--lmi-max-n``, default 50,
where it already takes minutes): one call of the public entry point
`fojax.design.design_functional_observer(sys, L, kind=kind, q0=q0, solver=--solver,
method=method)` with the default region (``Disk(-2, 1)``) on a random system (see
`random_design_problem`):

- a random stable index-1 descriptor plant $E\dot x = Ax + Bu$, $y = Cx$ (the generator of
  `scaling.py`: $E = U\,\mathrm{diag}(I_r, 0)V$, $n_{\rm alg} = \max(1, n/4)$ algebraic
  equations), $m = 2$ inputs, $p = \max(1, \lfloor n/4\rfloor)$ random outputs ($C$ with
  i.i.d. normal entries);
- a random functional $z = Lx$ with $q = \max(1, \lfloor n/2\rfloor)$ rows, and observer
  order $q_0 = q$ (so $q_0 \approx n/2$; $R$ is fojax's default choice for that order);
- checked with `fojax.analysis.is_functionally_observable` (true for every $L$ here: the
  plant is impulse free) before the design.

Reported per (n, kind): the total wall time of the design call (structure and existence
checks, default $R$, building and solving the LMI, float64 verification), the time spent
inside cvxpy's ``Problem.solve`` (canonicalisation + solver; summed over the attempts
fojax makes, e.g. a fallback from the min-gain to the feasibility problem) and the solver's
own reported solve time, the solver that produced the design, the cvxpy problem size of
the accepted problem (scalar variables, LMI blocks and their sizes, scalar equality
constraints), the error eigenvalues' largest real part, and the peak RSS. Failures (a
typed fojax error, a timeout, a crash) are rows, not crashes. The size metrics are
captured by wrapping ``cvxpy.Problem.solve`` for the duration of the call (fojax itself
is only called through its public API).

Each (n, kind) runs in a fresh Python process that first makes one untimed warm-up
design (n = 4, same kind, solver and method: imports and first-call overheads, reported as
``warmup_s``). For each (kind, method), n stops increasing once one design takes longer
than ``--budget`` s (default 120) or is killed after ``--hard-timeout`` s.

**Agreement.** There is no unique observer (the routes choose different gains), so the
routes agree when both designs pass the same float64 verification (conditions a.–d.,
eigenvalues in the region, the region LMI at the certificate): ``agreement`` lists, per
(n, kind) where both ran, whether both verified. Each row also records the load average
before and after the design (``os.getloadavg()``): the machine is shared.

Results: ``results/design_scaling_<date>.{md,json}`` and ``..._latest.{md,json}``.

Examples::

    python benchmarks/design_scaling.py                        # full study
    python benchmarks/design_scaling.py --dims 4 6 8 --kinds proportional
    python benchmarks/design_scaling.py --solver SCS --budget 60
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
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
from scaling import random_stable_index1  # noqa: E402


DIMS = (4, 8, 16, 32, 50, 100, 200, 300, 500)
KINDS = ("generalized", "proportional")
METHODS = ("riccati", "lmi")
LMI_MAX_N = 50
DEFAULT_SEED = 20261121
N_INPUTS = 2


@dataclasses.dataclass(frozen=True)
class DesignProblem:
    n: int
    E: np.ndarray
    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    L: np.ndarray
    q0: int


def random_design_problem(n: int, seed: int) -> DesignProblem:
    """Random stable index-1 plant with ``m = 2``, ``p = max(1, n // 4)``, ``q = q0 =
    max(1, n // 2)`` (see the module docstring); deterministic in ``(n, seed)``."""
    loop = random_stable_index1(n, seed + n)
    rng = np.random.default_rng([seed, n, 1])
    p, q = max(1, n // 4), max(1, n // 2)
    return DesignProblem(
        n=n,
        E=loop.E,
        A=loop.A,
        B=rng.standard_normal((n, N_INPUTS)),
        C=rng.standard_normal((p, n)),
        L=rng.standard_normal((q, n)),
        q0=q,
    )


# ============================================================================ cvxpy probe
def problem_size(prob) -> dict:
    """Scalar variables, LMI blocks (PSD constraints) and scalar equalities of a cvxpy problem."""
    import cvxpy as cp

    sm = prob.size_metrics
    sides = []
    for c in prob.constraints:
        if isinstance(c, cp.constraints.PSD):
            sides.append(int(c.args[0].shape[0]))
    return {
        "scalar_variables": int(sm.num_scalar_variables),
        "lmi_blocks": len(sides),
        "lmi_sizes": sides,
        "lmi_rows_total": int(sum(sides)),
        "lmi_scalar_entries": int(sum(s * (s + 1) // 2 for s in sides)),
        "scalar_eq_constraints": int(sm.num_scalar_eq_constr),
        "scalar_leq_constraints": int(sm.num_scalar_leq_constr),
    }


@contextlib.contextmanager
def record_cvxpy_solves():
    """Wrap ``cvxpy.Problem.solve``: for every call, its wall time, the solver keyword,
    status and the solver's reported time (sizes are computed afterwards, untimed)."""
    import cvxpy as cp

    calls: list = []
    orig = cp.Problem.solve

    def solve(self, *a, **kw):
        t0 = time.perf_counter()
        try:
            return orig(self, *a, **kw)
        finally:
            stats = getattr(self, "solver_stats", None)
            calls.append({
                "problem": self,
                "solver": kw.get("solver"),
                "wall_s": time.perf_counter() - t0,
                "status": self.status,
                "solver_time_s": getattr(stats, "solve_time", None),
                "iterations": getattr(stats, "num_iters", None),
            })

    cp.Problem.solve = solve
    try:
        yield calls
    finally:
        cp.Problem.solve = orig


# ============================================================================ worker
def worker(spec: dict) -> dict:
    import jax

    jax.config.update("jax_enable_x64", True)
    import os

    import fojax
    from fojax.analysis import is_functionally_observable
    from fojax.design import design_functional_observer

    n, kind, solver = spec["n"], spec["kind"], spec["solver"]
    method = spec.get("method", "lmi")
    res: dict = {"n": n, "kind": kind, "method": method, "solver_requested": solver}

    def design(pb):
        sysm = fojax.DescriptorSystem(pb.E, pb.A, pb.B, pb.C)
        return sysm, design_functional_observer(sysm, pb.L, kind=kind, q0=pb.q0, solver=solver, method=method)

    t0 = time.perf_counter()
    try:
        design(random_design_problem(4, spec["seed"] + 1000))
        res["warmup_s"] = time.perf_counter() - t0
    except fojax.FojaxError as e:  # not fatal: the timed design below still runs
        res["warmup_s"] = time.perf_counter() - t0
        res["warmup_error"] = f"{type(e).__name__}: {e}"
    pb = random_design_problem(n, spec["seed"])
    res.update(p=int(pb.C.shape[0]), q=int(pb.L.shape[0]), q0=pb.q0, m=int(pb.B.shape[1]))
    res["functionally_observable"] = bool(
        is_functionally_observable(fojax.DescriptorSystem(pb.E, pb.A, pb.B, pb.C), pb.L)
    )
    if not res["functionally_observable"]:
        res["status"] = "failed: not functionally observable (generator bug)"
        return res
    rss0 = _common.current_rss_mib()
    res["load_average_before"] = list(os.getloadavg())
    with record_cvxpy_solves() as calls:
        c0 = time.process_time()
        t0 = time.perf_counter()
        try:
            _, d = design(pb)
            res["status"] = "ok"
        except fojax.FojaxError as e:
            d = None
            res["status"] = f"failed: {type(e).__name__}"
            res["error"] = str(e)[:2000]
        except Exception as e:  # noqa: BLE001 - reported as a row
            d = None
            res["status"] = f"crashed: {type(e).__name__}"
            res["error"] = traceback.format_exc()[-3000:]
        res["total_s"] = time.perf_counter() - t0
        # CPU time of this process (all threads): what the design costs independently of
        # how much of the shared machine the process got
        res["cpu_s"] = time.process_time() - c0
    res["load_average_after"] = list(os.getloadavg())
    res["rss_before_mib"] = rss0
    res["peak_rss_mib"] = _common.peak_rss_mib()
    res["cvxpy_solve_calls"] = len(calls)
    res["cvxpy_solve_wall_s"] = sum(c["wall_s"] for c in calls)
    st = [c["solver_time_s"] for c in calls if c["solver_time_s"] is not None]
    res["solver_time_s"] = sum(st) if st else None
    res["outside_cvxpy_s"] = res["total_s"] - res["cvxpy_solve_wall_s"]
    res["attempts"] = [{k: v for k, v in c.items() if k != "problem"} for c in calls]
    if calls:
        ok = [c for c in calls if c["status"] == "optimal"]
        res["problem_size"] = problem_size((ok[-1] if ok else calls[-1])["problem"])
    if d is not None:
        lmi = d.solver.get("lmi", d.solver)
        res["solver_used"] = lmi.get("solver")
        res["objective"] = lmi.get("objective")
        res["route"] = lmi.get("route")
        res["route_method"] = lmi.get("method")
        res["iterations"] = lmi.get("iterations")
        res["verification_passed"] = bool(d.report.passed)
        res["max_real_error_eig"] = float(np.max(np.real(d.report.eigenvalues)))
        res["observer_order"] = {"q0": int(d.observer.q0), "q1": int(d.observer.q1)}
    return res


# ============================================================================ driver
def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    ap.add_argument("--dims", type=int, nargs="+", default=list(DIMS), help="state dimensions n (default 4 … 500)")
    ap.add_argument("--kinds", nargs="+", default=list(KINDS), choices=("generalized", "PI", "proportional"))
    ap.add_argument("--methods", nargs="+", default=list(METHODS), choices=("riccati", "lmi", "auto"),
                    help="design routes (design_functional_observer's method argument)")
    ap.add_argument("--lmi-max-n", type=int, default=LMI_MAX_N,
                    help="largest n for the LMI route (default 50: it takes minutes there)")
    ap.add_argument("--solver", default="auto", choices=("auto", "CLARABEL", "SCS"),
                    help="fojax's solver argument (default auto: Clarabel, SCS as fallback)")
    ap.add_argument("--budget", type=float, default=120.0,
                    help="stop increasing n for a kind once one design takes longer than this (s)")
    ap.add_argument("--hard-timeout", type=float, default=1800.0, help="kill a design after this many seconds")
    ap.add_argument("--seed", type=int, default=DEFAULT_SEED)
    ap.add_argument("--out", type=Path, default=_common.RESULTS)
    args = ap.parse_args(argv)
    if _common.served_as_worker(args, worker):
        return 0

    info = _common.machine_info()
    print(f"# design scaling ({info['date']}, {info['cpu']}, {info['cores_available']} cores)")
    rows: list[dict] = []
    stopped: dict[str, str] = {}
    for n in sorted(set(args.dims)):
        for kind, method in [(k, m) for k in args.kinds for m in args.methods]:
            key = f"{kind}/{method}"
            if key in stopped or (method == "lmi" and n > args.lmi_max_n):
                continue
            spec = dict(n=n, kind=kind, solver=args.solver, seed=args.seed, method=method)
            res = _common.run_worker(Path(__file__), spec, args.hard_timeout)
            res.setdefault("n", n)
            res.setdefault("kind", kind)
            res.setdefault("method", method)
            rows.append(res)
            size = res.get("problem_size", {})
            print(
                f"  n = {n:3d} {kind:12s} {method:7s} {res.get('status')}: total {_common.fmt(res.get('total_s'), '.3g')} s, "
                f"CPU {_common.fmt(res.get('cpu_s'), '.3g')} s, peak RSS {_common.fmt(res.get('peak_rss_mib'), '.0f')} MiB, "
                f"cvxpy solve {_common.fmt(res.get('cvxpy_solve_wall_s'), '.3g')} s "
                f"(solver {_common.fmt(res.get('solver_time_s'), '.3g')} s, {res.get('solver_used')}), "
                f"{size.get('scalar_variables', '—')} variables, LMIs {size.get('lmi_sizes', '—')}",
                flush=True,
            )
            reason = _common.stop_reason(res, n, args.hard_timeout, args.budget)
            if reason:
                stopped[key] = reason
            write(info, args, rows, stopped, "partial")
    write(info, args, rows, stopped, "complete", echo=True)
    return 0


def write(info, args, rows, stopped, status, echo=False):
    payload = _common.result_payload(
        "design_scaling",
        status,
        info,
        args,
        problem=dict(
            plant="random stable index-1 (scaling.random_stable_index1), n_alg = max(1, n // 4)",
            m=N_INPUTS, p="max(1, n // 4)", q="max(1, n // 2)", q0="q", region="default (Disk(-2, 1))",
        ),
        rows=rows,
        stopped=stopped,
        agreement=agreement(rows),
        load_average_at_end=_common.load_average(),
        note="measured under load: the 2-core machine was shared (see each row's load_average_before/after)",
    )
    _common.write_results(args.out, "design_scaling", payload, render_markdown(payload), echo=echo)


def agreement(rows) -> list[dict]:
    """Per (n, kind) with both routes: did both designs pass the float64 verification?"""
    out = []
    by = {(r["n"], r["kind"], r.get("method", "lmi")): r for r in rows}
    for (n, kind, method), r in sorted(by.items()):
        other = by.get((n, kind, "lmi"))
        if method != "riccati" or other is None:
            continue
        both = bool(r.get("verification_passed")) and bool(other.get("verification_passed"))
        out.append({"n": n, "kind": kind, "both_verified": both,
                    "riccati_s": r.get("total_s"), "lmi_s": other.get("total_s"),
                    "speedup": (other["total_s"] / r["total_s"]) if both else None})
    return out


def render_markdown(d: dict) -> str:
    fmt, s = _common.fmt, d["settings"]
    lines = [
        "# Observer design time vs state dimension, LMI and Riccati routes (issues 7, 16)",
        "",
        f"- status: {d['status']}",
        *_common.machine_lines(d["machine"]),
        "- `fojax.design.design_functional_observer(sys, L, kind, q0 = q)`, default region Disk(-2, 1), "
        f"solver `{s['solver']}`, method = route; random stable index-1 plant, m = 2, p = max(1, n // 4), q = q0 = max(1, n // 2); "
        "one fresh process per design after an untimed n = 4 warm-up design",
        "",
        "total = wall time of the whole design call (CPU = its process CPU time; checks, default R, LMI build + solve, float64 verification); "
        "cvxpy = time inside `Problem.solve` (all attempts); solver = the solver's own time; rest = total − cvxpy "
        "(existence checks, default R, building the LMI, verification, observer construction). "
        "Size = the accepted cvxpy problem: scalar variables, LMI blocks (sizes).",
        "",
        "| n | kind | method | q0 | p | status | total (s) | CPU (s) | cvxpy solve (s) | solver (s) | rest (s) | solver used | attempts | "
        "variables | LMIs (sizes) | max Re λ(error) | peak RSS (MiB) |",
        "|---:|---|---|---:|---:|---|---:|---:|---:|---:|---:|---|---:|---:|---|---:|---:|",
    ]
    for r in d["rows"]:
        size = r.get("problem_size", {})
        sizes = size.get("lmi_sizes")
        lmis = "—" if sizes is None else f"{len(sizes)} ({', '.join(map(str, sizes))})"
        lines.append(
            f"| {r['n']} | {r['kind']} | {r.get('method', 'lmi')} | {r.get('q0', '—')} | {r.get('p', '—')} | {r.get('status')} | "
            f"{fmt(r.get('total_s'), '.3g')} | {fmt(r.get('cpu_s'), '.3g')} | {fmt(r.get('cvxpy_solve_wall_s'), '.3g')} | "
            f"{fmt(r.get('solver_time_s'), '.3g')} | {fmt(r.get('outside_cvxpy_s'), '.3g')} | {r.get('solver_used') or '—'} | {r.get('cvxpy_solve_calls', '—')} | "
            f"{size.get('scalar_variables', '—')} | {lmis} | {fmt(r.get('max_real_error_eig'), '.3f')} | "
            f"{fmt(r.get('peak_rss_mib'), '.0f')} |"
        )
    if d.get("agreement"):
        lines += ["", "Agreement (both routes' designs pass the float64 verification; speedup = LMI time / "
                  "Riccati time):", ""]
        for a in d["agreement"]:
            lines.append(f"- n = {a['n']}, {a['kind']}: both verified = {a['both_verified']}, "
                         f"speedup {fmt(a.get('speedup'), '.3g')}")
    lines += _common.stop_and_failure_lines(d, lambda r: f"n = {r['n']}, {r['kind']}, {r.get('method', 'lmi')}")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
