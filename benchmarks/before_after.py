"""Before/after: the product-path and reference benchmarks on two checkouts, alternated.

Runs ``study_default.py`` (the product path: `fojax.run_study` on the §3.3.7 study, default
settings and metrics only, against its NumPy/SciPy peer) and ``reference_workload.py
--fojax-mode run-study --peers expm`` (the thesis §4.1.3 loop against peer (d), SciPy's exact
discretisation) in each checkout, in the order old, new, old, new, ... (``--rounds``), each in
a fresh process on one host device, and writes the medians of both sides, with the peer
measured in the same process, to ``results/before_after_latest.json``. Each script checks
agreement with its peer before it times anything.

    python benchmarks/before_after.py --old /path/to/old/checkout --new . --sizes 1000 10000
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path


HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import _common  # noqa: E402


def _git(checkout: Path) -> str:
    return subprocess.run(["git", "-C", str(checkout), "rev-parse", "--short", "HEAD"], capture_output=True,
                          text=True).stdout.strip()


def _study(checkout: Path, sizes, tmp: Path) -> dict:
    out = tmp / "study.json"
    subprocess.run([sys.executable, "benchmarks/study_default.py", "--sizes", *map(str, sizes), "--repeats", "5",
                    "--host-devices", "1", "--out", str(out)], cwd=checkout, check=True, capture_output=True)
    d = json.loads(out.read_text())
    return {r["B"]: dict(fojax_metrics_s=r["fojax_median_s"], peer_metrics_s=r["peer_median_s"],
                         fojax_bands_s=r["fojax_default_quantiles_s"], peer_bands_s=r["peer_with_bands_s"],
                         fojax_first_call_s=r["fojax_first_call_s"],
                         fojax_bands_first_call_s=r["fojax_default_quantiles_first_call_s"])
            for r in d["rows"]}


def _reference(checkout: Path, sizes, tmp: Path) -> dict:
    out = tmp / "ref"
    subprocess.run([sys.executable, "benchmarks/reference_workload.py", "--fojax-mode", "run-study", "--peers", "expm",
                    "--sizes", *map(str, sizes), "--host-devices", "1", "--out", str(out)], cwd=checkout, check=True,
                   capture_output=True)
    d = json.loads(next(out.glob("*_latest.json")).read_text())
    res: dict = {}
    for r in d["rows"]:
        key = "peer_s" if r["method"] == "expm" else "fojax_s" if r["method"] in ("fojax", "fojax_run_study") else None
        if key:
            res.setdefault(r["B"], {})[key] = r["median_s"]
            if key == "fojax_s":
                res[r["B"]]["fojax_first_call_s"] = r["first_s"]
    return res


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--old", type=Path, required=True)
    ap.add_argument("--new", type=Path, default=HERE.parent)
    ap.add_argument("--sizes", type=int, nargs="+", default=[1000, 10000])
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--out", type=Path, default=_common.RESULTS)
    args = ap.parse_args()
    info = _common.machine_info()
    sides = {"old": args.old.resolve(), "new": args.new.resolve()}
    runs = {s: {"study": [], "reference": []} for s in sides}
    for k in range(args.rounds):
        for side, checkout in sides.items():
            with tempfile.TemporaryDirectory() as tmp:
                print(f"round {k + 1}/{args.rounds}: {side} ({_git(checkout)})", file=sys.stderr, flush=True)
                runs[side]["study"].append(_study(checkout, args.sizes, Path(tmp)))
                runs[side]["reference"].append(_reference(checkout, args.sizes, Path(tmp)))
    rows = []
    for bench in ("study", "reference"):
        for B in args.sizes:
            for side in sides:
                per = [r[B] for r in runs[side][bench]]
                med = {key: statistics.median(p[key] for p in per) for key in per[0]}
                row = dict(benchmark=bench, B=B, side=side, commit=_git(sides[side]), rounds=len(per), **med)
                if bench == "study":
                    row["speedup_metrics"] = med["peer_metrics_s"] / med["fojax_metrics_s"]
                    row["speedup_bands"] = med["peer_bands_s"] / med["fojax_bands_s"]
                else:
                    row["speedup"] = med["peer_s"] / med["fojax_s"]
                rows.append(row)
    payload = _common.result_payload("before_after", "complete", info, args, rows=rows)
    path = args.out / "before_after_latest.json"
    _common.write_result(path, payload)
    print(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
