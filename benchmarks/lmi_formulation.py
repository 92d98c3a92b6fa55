r"""The LMI route's two formulations, side by side: the full region LMI of the error dynamics
(`fojax.design._region_lmi.solve_gains`: certificate of order q0 + q1 and the gains as variables)
and the reduced one (`fojax.design._eliminated.eliminated_gains`: the ε-block's certificate
alone, gains eliminated or kept by region kind), which `design_functional_observer(...,
method="lmi")` uses above observer order 12.

What is measured
----------------
For each n in ``--dims``, each kind in ``--kinds`` and each region in ``--regions`` (a disk,
a half-plane, a sector, a disk & half-plane, a half-plane & sector), on the ``half`` problem
shape of ``design_routes.py`` (random stable index-1 plant, ``q = q0 = n // 2``): both
formulations solve the region LMI of the same structure (``R`` from fojax's default) for the
region tightened as the design does, and both designs are verified in float64 (the same
``verify()`` as the public call). Recorded per formulation: the process CPU time of the gains
(LMI build, cvxpy or the direct conic build, solver, gain recovery), and per solve the wall
time, cvxpy's own canonicalisation time (``Problem.compilation_time``; 0 for the reduced
LMI's programs, which go to Clarabel without cvxpy) and the solver's reported time (wall
times: the machine is shared, see the load averages), the cone sizes, the number of scalar
variables, the solver statuses, whether the design verified and the largest gain entry. The
speed-up is full CPU / reduced CPU. A (kind, region) stops measuring the full formulation
once one of its solves took longer than ``--budget`` s CPU.

    python benchmarks/lmi_formulation.py
    python benchmarks/lmi_formulation.py --dims 24 --kinds generalized --regions disk
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path


HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import _common  # noqa: E402


if __name__ == "__main__":
    _common.limit_blas_threads()  # before NumPy (see _common)
    _common.prefer_checkout()  # measure this checkout's fojax

import numpy as np  # noqa: E402


DIMS = (24, 36, 48)
KINDS = ("generalized", "PI", "proportional")
REGIONS = ("disk", "half-plane", "sector", "disk & half-plane", "half-plane & sector")
SEED = 20261206


def region_of(name: str):
    from fojax.design import Disk, HalfPlane, Sector

    return {"disk": Disk(-3.0, 2.0), "half-plane": HalfPlane(1.0), "sector": Sector(0.6),
            "disk & half-plane": Disk(-3.0, 2.0) & HalfPlane(1.5),
            "half-plane & sector": HalfPlane(1.0) & Sector(0.6)}[name]


def structure(n: int, kind: str, region):
    from design_routes import problem

    import fojax
    from fojax.design._functional import prepare_structure
    from fojax.design._parameterization import observer_structure

    E, A, B, C, L, q0 = problem("half", n, SEED)
    s = prepare_structure(fojax.DescriptorSystem(E, A, B, C), L, q0=q0, q1=0, region=region)
    q1 = 0 if kind == "proportional" else s.q0
    return observer_structure(s.E, s.A, s.B, s.C, s.L, s.R, q1=q1, psi=s.psi, Eperp=s.Eperp)


def measure(s, kind: str, region, form: str) -> dict:
    import cvxpy as cp
    from design_scaling import record_cvxpy_solves

    from fojax import FojaxError
    from fojax.design import _region_lmi
    from fojax.design._eliminated import eliminated_gains
    from fojax.design._functional import _finish, TIGHTEN
    from fojax.design._region_lmi import solve_gains

    f = eliminated_gains if form == "reduced" else solve_gains
    out: dict = {"formulation": form}
    cpu_calls: list = []
    direct: list = []  # conic programs handed to Clarabel without cvxpy (fojax.design._lmi.solve_conic)
    with record_cvxpy_solves() as calls:
        recording, conic = cp.Problem.solve, _region_lmi.solve_conic

        def timed(self, *a, **kw):  # process CPU of each solve call (canonicalisation + solver)
            c0 = time.process_time()
            try:
                return recording(self, *a, **kw)
            finally:
                cpu_calls.append(time.process_time() - c0)

        def timed_conic(prob, *a, **kw):
            c0, t0 = time.process_time(), time.perf_counter()
            row = {"solver": "CLARABEL (direct)", "canonicalisation_wall_s": 0.0, "solver_wall_s": None,
                   "scalar_variables": int(prob.c.size) + (0 if prob.norm is None else 1)}
            try:
                x, info = conic(prob, *a, **kw)
                row.update(status=info["status"], solver_wall_s=info.get("solve_time"))
                return x, info
            except FojaxError as e:
                row["status"] = getattr(e, "status", type(e).__name__)
                raise
            finally:
                row.update(cpu_s=time.process_time() - c0, wall_s=time.perf_counter() - t0)
                direct.append(row)

        cp.Problem.solve, _region_lmi.solve_conic = timed, timed_conic
        c0, t0 = time.process_time(), time.perf_counter()
        try:
            X, Z, Ys, info = f(s, region.tightened(TIGHTEN), kind=kind)
            out["status"] = "ok"
        except FojaxError as e:
            X, out["status"], out["error"] = None, f"failed: {type(e).__name__}", str(e)[:600]
        finally:
            cp.Problem.solve, _region_lmi.solve_conic = recording, conic
        out["cpu_s"] = time.process_time() - c0
        out["wall_s"] = time.perf_counter() - t0
    out["solves"] = [{"status": c["status"], "solver": c["solver"], "wall_s": c["wall_s"],
                      "canonicalisation_wall_s": float(getattr(c["problem"], "compilation_time", 0.0) or 0.0),
                      "solver_wall_s": c["solver_time_s"], "cpu_s": cpu,
                      "scalar_variables": int(c["problem"].size_metrics.num_scalar_variables)}
                     for c, cpu in zip(calls, cpu_calls)] + direct
    out["canonicalisation_wall_s"] = sum(c["canonicalisation_wall_s"] for c in out["solves"])
    out["solver_wall_s"] = sum(c["solver_wall_s"] or 0.0 for c in out["solves"])
    out["solve_calls_cpu_s"] = sum(cpu_calls)
    if out["solves"]:
        out["scalar_variables"] = out["solves"][-1]["scalar_variables"]
    if X is not None:
        info["lmi"]["method"] = "lmi"
        out["route"] = str(info["lmi"].get("route"))[:400]
        out["lmi_size"] = info["lmi"].get("lmi_size")
        try:
            d = _finish(s, region, kind, X, Z, Ys, info, {})
            out["verified"] = bool(d.report.passed)
            out["max_gain_entry"] = float(max(np.abs(Ys[0]).max(initial=0.0), np.abs(Z).max(initial=0.0)))
            out["max_real_eig"] = float(np.max(np.real(d.report.eigenvalues)))
        except FojaxError as e:
            out["verified"], out["verify_error"] = False, str(e)[:600]
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dims", type=int, nargs="+", default=list(DIMS))
    ap.add_argument("--kinds", nargs="+", default=list(KINDS), choices=KINDS)
    ap.add_argument("--regions", nargs="+", default=list(REGIONS), choices=REGIONS)
    ap.add_argument("--budget", type=float, default=60.0, help="CPU seconds of a full solve before it stops growing n")
    ap.add_argument("--out", type=Path, default=_common.RESULTS)
    ap.add_argument("--name", default="lmi_formulation")
    args = ap.parse_args(argv)
    import jax

    jax.config.update("jax_enable_x64", True)
    info = _common.machine_info()
    print(f"# LMI formulations ({info['date']}, {info['cpu']}, {info['cores_available']} cores)", flush=True)
    measure(structure(8, "generalized", region_of("disk")), "generalized", region_of("disk"), "reduced")  # warm-up
    rows, stopped = [], {}
    for n in sorted(set(args.dims)):
        for kind in args.kinds:
            for rname in args.regions:
                region = region_of(rname)
                s = structure(n, kind, region)
                row = {"n": n, "kind": kind, "region": rname, "q0": int(s.q0),
                       "q1": 0 if kind == "proportional" else int(s.q1),
                       "load_average_before": list(os.getloadavg())}
                row["reduced"] = measure(s, kind, region, "reduced")
                key = f"{kind}/{rname}"
                if key not in stopped:
                    row["full"] = measure(s, kind, region, "full")
                    if row["full"]["cpu_s"] > args.budget:
                        stopped[key] = f"full formulation took {row['full']['cpu_s']:.0f} s CPU at n = {n}"
                if "full" in row and row["reduced"]["status"] == row["full"]["status"] == "ok":
                    row["speedup_cpu"] = row["full"]["cpu_s"] / max(row["reduced"]["cpu_s"], 1e-9)
                row["load_average_after"] = list(os.getloadavg())
                rows.append(row)
                r, fu = row["reduced"], row.get("full", {})
                print(f"  n = {n:3d} {kind:12s} {rname:20s} reduced {r['status']} {r['cpu_s']:.3g} s CPU "
                      f"(verified {r.get('verified')}), full {fu.get('status', '—')} {_common.fmt(fu.get('cpu_s'))} s CPU "
                      f"(verified {fu.get('verified', '—')}): ×{_common.fmt(row.get('speedup_cpu'))}", flush=True)
                write(info, args, rows, stopped, "partial")
    write(info, args, rows, stopped, "complete", echo=True)
    return 0


def write(info, args, rows, stopped, status, echo=False):
    payload = _common.result_payload(
        args.name, status, info, args, rows=rows, stopped=stopped, shape="half (design_routes.py), q0 = n // 2",
        note="2-core machine shared with other jobs (loaded: see load_average_before/after per row): CPU times are "
             "process CPU; the canonicalisation and solver split is cvxpy's and the solver's wall time")
    _common.write_results(args.out, args.name, payload, render_markdown(payload), echo=echo)


def render_markdown(d: dict) -> str:
    lines = ["# The LMI route's formulations: full region LMI vs reduced (gains eliminated)", "",
             f"- status: {d['status']}", *_common.machine_lines(d["machine"]), ""]
    lines += table(d)
    return "\n".join(lines) + "\n"


def table(d: dict) -> list[str]:
    fmt = _common.fmt
    out = ["| n | kind | region | q0 + q1 | full CPU (s) | reduced CPU (s) | speed-up | full: canon. / solver wall (s) | "
           "reduced: canon. / solver wall (s) | variables full / reduced | verified full / reduced | "
           "max gain full / reduced | load |",
           "|---:|---|---|---:|---:|---:|---:|---|---|---|---|---|---:|"]
    for r in d["rows"]:
        fu, re_ = r.get("full") or {}, r["reduced"]

        def split(m):
            return f"{fmt(m.get('canonicalisation_wall_s'), '.2g')} / {fmt(m.get('solver_wall_s'), '.2g')}" if m else "—"

        out.append(
            f"| {r['n']} | {r['kind']} | {r['region']} | {r['q0'] + r['q1']} | {fmt(fu.get('cpu_s'), '.3g')} | "
            f"{fmt(re_.get('cpu_s'), '.3g')} | {fmt(r.get('speedup_cpu'), '.3g')} | {split(fu)} | {split(re_)} | "
            f"{fu.get('scalar_variables', '—')} / {re_.get('scalar_variables', '—')} | "
            f"{fu.get('verified', fu.get('status', '—'))} / {re_.get('verified', re_.get('status'))} | "
            f"{fmt(fu.get('max_gain_entry'), '.3g')} / {fmt(re_.get('max_gain_entry'), '.3g')} | "
            f"{fmt((r.get('load_average_before') or [None])[0], '.1f')} |")
    if d.get("stopped"):
        out += ["", "Full formulation stopped: " + "; ".join(f"{k}: {v}" for k, v in d["stopped"].items())]
    return out


if __name__ == "__main__":
    raise SystemExit(main())
