"""How tight are the certified bounds of ``objective="hinf"`` and ``objective="h2"`` designs?

A random sweep of plants no test uses: for each seed, a descriptor plant of order n
(uniform in 4..12) with rank E = n - 1 or n - 2, index 1, its equations and states mixed by
random orthogonal matrices (so E is not diagonal), p = max(2, n // 2) outputs, q = 2
functionals, a disturbance channel ``Bw`` (n x 2) and output noise ``Dv = 0.3 I``, in a
"tight" disk (centre uniform in [-4, -2.5], radius uniform in [1, 1.6]). Each case is designed
with the public `fojax.design_functional_observer(..., kind="generalized", objective=...)`:

- ``hinf``: the ratio of the returned γ to the true ‖T‖∞ of the returned observer's error
  system d = [w; ν] → ẑ − z (SLICOT AB13DD via slycot, recomputed here from the observer
  matrices) and whether γ stays at or below the region-only design's norm the result reports;
- ``h2``: the disturbance acts on the differential part only (``Bw = E W``, no noise), so
  ẑ − z has no feedthrough; the ratio of ν to ‖T‖₂ (SciPy Lyapunov, recomputed here).

A case that raises records the error type and message instead. The JSON holds every case and
the min / median / max ratio per objective.

    python benchmarks/gamma_tightness.py                       # 25 seeds, both objectives
    python benchmarks/gamma_tightness.py --seeds 5 --objectives hinf
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path


sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common  # noqa: E402


_common.prefer_checkout()
_common.limit_blas_threads()

import jax  # noqa: E402
import numpy as np  # noqa: E402
import scipy.linalg as sla  # noqa: E402


jax.config.update("jax_enable_x64", True)


#: A bound counts as above the region-only design's norm when it exceeds it by more than this
#: (relative): a certified bound lies strictly above the norm it bounds, by the certification
#: gap, and the two designs often have the same norm.
ABOVE_RTOL = 1e-5


def random_case(seed: int):
    """``(system, L, Bw, Dv, region, info)`` of the sweep (module docstring)."""
    import fojax

    rng = np.random.default_rng(seed)
    n = int(rng.integers(4, 13))
    r = n - int(rng.integers(1, 3))
    p, q = max(2, n // 2), 2
    E0 = np.diag(np.r_[np.ones(r), np.zeros(n - r)])
    A0 = rng.standard_normal((n, n))
    A0[r:, r:] += 3.0 * np.eye(n - r)  # A22 away from singular: index 1
    U = np.linalg.qr(rng.standard_normal((n, n)))[0]
    V = np.linalg.qr(rng.standard_normal((n, n)))[0]
    E, A = U @ E0 @ V, U @ A0 @ V
    B = rng.standard_normal((n, 1))
    C = rng.standard_normal((p, n))
    L = rng.standard_normal((q, n))
    Bw = rng.standard_normal((n, 2))
    Dv = 0.3 * np.eye(p)
    region = fojax.Disk(float(rng.uniform(-4.0, -2.5)), float(rng.uniform(1.0, 1.6)))
    info = {"seed": seed, "n": n, "rank_E": r, "p": p, "q": q,
            "disk": [float(region.center), float(region.radius)]}
    return fojax.DescriptorSystem(E, A, B, C), L, Bw, Dv, region, info


def true_norms(design, Bw, Dv):
    """``(‖T‖∞, ‖T‖₂)`` of the returned observer's error system, recomputed here (`Bw`, `Dv` in
    the frame of ``design.structure``)."""
    import slycot

    from fojax.design._hinf import base_mats, error_system

    s = design.structure
    A, B, C, D = error_system(s, base_mats(s, design.params), Bw, Dv)
    n = A.shape[0]
    hinf = float(slycot.ab13dd("C", "I", "S", "D", n, B.shape[1], C.shape[0], A, np.eye(n), B, C, D)[0])
    P = sla.solve_continuous_lyapunov(A, -B @ B.T)
    h2 = float(np.sqrt(max(float(np.trace(C @ P @ C.T)), 0.0)))
    return hinf, h2


def run_case(seed: int, objective: str) -> dict:
    import fojax

    sys_, L, Bw, Dv, region, row = random_case(seed)
    if objective == "h2":
        Bw = np.asarray(sys_.E) @ np.random.default_rng(seed + 1000).standard_normal((sys_.E.shape[0], 2))
        Dv = None
    row["objective"] = objective
    t0 = time.perf_counter()
    try:
        d = fojax.design_functional_observer(sys_, L, kind="generalized", region=region,
                                             objective=objective, Bw=Bw, Dv=Dv)
    except fojax.FojaxError as e:
        row.update(error=type(e).__name__, message=str(e)[:600], seconds=time.perf_counter() - t0)
        return row
    row["seconds"] = time.perf_counter() - t0
    cert = d.hinf if objective == "hinf" else d.h2
    # the certificate's channels: those of the unit-free frame when the design was made there
    hinf, h2 = true_norms(d, np.asarray(cert.Bw), np.asarray(cert.Dv))
    row["unit_free"] = d.solver.get("balance") is not None
    if objective == "hinf":
        cert = d.hinf
        row.update(bound=cert.gamma, norm=hinf, ratio=cert.gamma / hinf, region_only_norm=cert.region_only_norm,
                   above_region_only=bool(cert.gamma > cert.region_only_norm * (1 + ABOVE_RTOL)))
    else:
        cert = d.h2
        row.update(bound=cert.nu, norm=h2, ratio=cert.nu / h2, region_only_norm=cert.region_only_norm,
                   above_region_only=bool(cert.nu > cert.region_only_norm * (1 + ABOVE_RTOL)))
    return row


def summary(rows) -> dict:
    ratios = [r["ratio"] for r in rows if "ratio" in r]
    out = {"cases": len(rows), "designed": len(ratios),
           "errors": {r["error"]: sum(1 for x in rows if x.get("error") == r["error"])
                      for r in rows if "error" in r},
           "above_region_only": sum(1 for r in rows if r.get("above_region_only"))}
    if ratios:
        out.update(min_ratio=min(ratios), median_ratio=statistics.median(ratios), max_ratio=max(ratios),
                   within_5_percent=sum(1 for x in ratios if x <= 1.05))
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=25)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--objectives", nargs="+", default=["hinf", "h2"], choices=["hinf", "h2"])
    ap.add_argument("--out", type=Path, default=_common.RESULTS / "gamma_tightness_latest.json")
    ap.add_argument("--baseline", type=Path, default=None,
                    help="a result JSON of an earlier run (e.g. another commit): its summaries are copied "
                         "into this one under 'baseline'")
    args = ap.parse_args(argv)
    info = _common.machine_info()
    results = {}
    for obj in args.objectives:
        rows = []
        for seed in range(args.first_seed, args.first_seed + args.seeds):
            row = run_case(seed, obj)
            rows.append(row)
            print(obj, seed, {k: row.get(k) for k in ("n", "rank_E", "ratio", "error")}, flush=True)
        results[obj] = {"summary": summary(rows), "cases": rows}
        print(obj, results[obj]["summary"], flush=True)
    extra = {}
    if args.baseline is not None:
        import json

        old = json.loads(args.baseline.read_text())
        extra["baseline"] = {"machine": {k: old["machine"].get(k) for k in ("date", "git_commit")},
                             "summaries": {k: v["summary"] for k, v in old["results"].items()}}
    payload = _common.result_payload("gamma_tightness", "ok", info, args, results=results, **extra)
    _common.write_result(args.out, payload)


if __name__ == "__main__":
    main()
