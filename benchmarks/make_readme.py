"""Write ``benchmarks/README.md`` from the shipped result files.

Every ``benchmarks/results/<name>_latest.json`` present (these files are tracked in git;
the dated ones are not) is rendered as Markdown tables by the renderer registered for
``<name>`` in `RENDER` (reference workload, time-varying study, scaling, design scaling,
tuning scaling); a ``*_latest.json`` without a renderer is shown as a generic table of its
``rows`` when it has them, else listed with a note. Renderers with no shipped file are
listed as "no shipped result yet". The page is `INTRO` (how to run the scripts and what
they measure), `NARRATIVE` (the measurements made while developing fojax, in prose) and the
tables between ``<!-- benchmarks:start -->`` and ``<!-- benchmarks:end -->``; the top-level
``README.md`` only links to it.

Every number is copied from a JSON file; each table names its file, the date and the
machine it was measured on. Nothing is typed by hand; a file whose JSON has unexpected
keys is skipped with a note.

    python benchmarks/make_readme.py                 # write benchmarks/README.md
    python benchmarks/make_readme.py --stdout        # print the tables only

To add a benchmark: write ``results/<name>_latest.json`` from its script and add
``"<name>": render_function`` to `RENDER` (a function ``(data, name) -> (lines, caveats)``).
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path


HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from _common import fmt  # noqa: E402


START, END = "<!-- benchmarks:start -->", "<!-- benchmarks:end -->"
# how the results folder is named in the source lines, and its link from benchmarks/README.md
_LABEL = {"results": "benchmarks/results", "link": "results"}
PEER_SHORT = {"solve_ivp": "(a) solve_ivp loop", "control": "(b) python-control loop",
              "rk4": "(c) NumPy RK4", "expm": "(d) expm + recurrence"}


def load(results: Path, name: str) -> tuple[dict | None, str | None]:
    path = results / f"{name}_latest.json"
    if not path.exists():
        return None, None
    try:
        return json.loads(path.read_text()), None
    except (OSError, json.JSONDecodeError) as e:
        return None, f"`{path.name}` could not be read ({type(e).__name__}); skipped."


def source_line(d: dict, name: str) -> str:
    m = d.get("machine", {}) or {}
    v = m.get("versions", {}) or {}
    la = m.get("load_average_at_start")
    load_txt = f"; load average at start {la[0]:.2f}" if isinstance(la, list | tuple) and la else ""
    vers = ", ".join(f"{k} {v[k]}" for k in ("jax", "jaxlib", "numpy", "scipy", "cvxpy", "fojax") if k in v)
    status = str(d.get("status", "?"))
    if status != "complete":
        status = f"**{status[:160]}{'…' if len(status) > 160 else ''}**"
    return (f"*Source: [`{_LABEL['results']}/{name}_latest.json`]({_LABEL['link']}/{name}_latest.json), "
            f"measured {m.get('date', '?')} "
            f"(git {m.get('git_commit', '?')}) on {m.get('cpu', '?')}, {m.get('cores_available', '?')} cores, "
            f"{m.get('memory', '?')}{load_txt}; {vers}; status: {status}.*")


# ============================================================================ studies
def reference_workload(d: dict, name: str) -> tuple[list[str], list[str]]:
    rows = d.get("rows")
    if not isinstance(rows, list) or not all(isinstance(r, dict) and "method" in r and "B" in r for r in rows):
        return _schema_note(name, d), []
    # fojax's row: `fojax.run_study` (the default entry) when measured, else the other fojax mode
    main = "fojax_run_study" if any(r["method"] == "fojax_run_study" for r in rows) else "fojax"
    sfx = "_run_study" if main == "fojax_run_study" else ""
    fojax = {r["B"]: r for r in rows if r["method"] == main}
    peers = [p for p in PEER_SHORT if any(r["method"] == p for r in rows)]
    peers += sorted({r["method"] for r in rows} - set(PEER_SHORT) - {"fojax", "fojax_run_study"})
    sizes = sorted({r["B"] for r in rows})
    out = [
        "### Reference workload (thesis §4.1.3 loop, B Monte Carlo samples)",
        "",
        source_line(d, name),
        "",
        "Speed-up = t_peer / t_fojax (median seconds; > 1: fojax faster). *extrap.* = the loop peer was not "
        "run at that B; its time is extrapolated linearly by the script.",
        "",
        "| B | fojax median (s) | fojax samples/s | fojax compile (s) | "
        + " | ".join(f"speed-up vs {PEER_SHORT.get(p, p)}" for p in peers) + " |",
        "|---:|---:|---:|---:|" + "---:|" * len(peers),
    ]
    slower: list[str] = []
    for B in sizes:
        f = fojax.get(B, {})
        cells = []
        for p in peers:
            r = next((x for x in rows if x["method"] == p and x["B"] == B), None)
            sp = None if r is None else r.get("fojax_speedup" + sfx)
            cells.append(fmt(sp) + (" *extrap.*" if r and r.get("extrapolated") and sp is not None else ""))
            if sp is not None and sp < 1:
                slower.append(f"{PEER_SHORT.get(p, p)} at B = {B} ({fmt(sp, '.2g')}×)")
        sps = f.get("samples_per_s") or (B / f["median_s"] if f.get("median_s") else None)
        med = fmt(f.get("median_s"), ".4g") if f else "not measured"
        out.append(f"| {B} | {med} | {fmt(sps, '.4g')} | {fmt(f.get('compile_s'), '.2f')} | "
                   + " | ".join(cells) + " |")
    agree = (d.get("agreement_check") or {}).get("max_rel_diff_vs_expm") or {}
    if agree:
        out += ["", f"Agreement before timing (B = {(d.get('agreement_check') or {}).get('B', '?')}, max relative "
                "difference of the per-sample metrics to (d)): "
                + ", ".join(f"{k} {fmt(v, '.1e')}" for k, v in agree.items()) + "."]
    honest = []
    if slower:
        honest.append("Reference workload: fojax is slower than " + "; ".join(slower) + ".")
    b1 = fojax.get(min(fojax)) if fojax else None
    if b1 and b1.get("first_s") is not None:
        Bmin = min(fojax)
        firsts = [f"{PEER_SHORT.get(r['method'], r['method'])} {fmt(r.get('first_s'), '.3g')} s"
                  for r in rows if r["B"] == Bmin and r["method"] in peers and r.get("first_s") is not None]
        honest.append(
            f"At B = {Bmin} fojax's first call, which compiles, takes {fmt(b1['first_s'], '.3g')} s "
            f"(compile ≈ {fmt(b1.get('compile_s'), '.2f')} s)" + (f" against the peers' first calls: {', '.join(firsts)}"
                                                                   if firsts else "") + "; the medians exclude it."
        )
    if fojax and max(fojax) < 100_000:
        honest.append(f"Reference workload measured only up to B = {max(fojax)} for fojax in this file.")
    return out, honest


def time_varying(d: dict, name: str) -> tuple[list[str], list[str]]:
    """Defensive: any ``rows`` of dicts with ``method``, ``B`` and ``median_s``; accuracy
    columns are the numeric row keys whose name contains ``acc`` or ``err``."""
    rows = d.get("rows")
    ok = isinstance(rows, list) and rows and all(
        isinstance(r, dict) and {"method", "B", "median_s"} <= set(r) for r in rows)
    if not ok:
        return _schema_note(name, d), []
    acc_keys = sorted({k for r in rows for k, v in r.items()
                       if re.search(r"acc|err", k) and isinstance(v, int | float) and not isinstance(v, bool)})
    out = [
        "### Time-varying study (δ(t) sinusoid per sample, actuator fault; no exact discretisation)",
        "",
        source_line(d, name),
        "",
        "| B | method | median (s) | samples/s | fojax speed-up | " + " | ".join(acc_keys) + (" |" if acc_keys else ""),
        "|---:|---|---:|---:|---:|" + "---:|" * len(acc_keys),
    ]
    honest, slower = [], []
    for r in sorted(rows, key=lambda r: (r["B"], str(r["method"]))):
        sps = r.get("samples_per_s") or (r["B"] / r["median_s"] if r.get("median_s") else None)
        sp = r.get("fojax_speedup")
        if isinstance(sp, int | float) and sp < 1:
            slower.append(f"{r.get('label', r['method'])} at B = {r['B']} ({fmt(sp, '.2g')}×)")
        out.append(f"| {r['B']} | {r.get('label', r['method'])} | {fmt(r.get('median_s'), '.4g')} | {fmt(sps, '.4g')} | "
                   f"{fmt(sp)} | " + " | ".join(fmt(r.get(k), '.2e') for k in acc_keys) + (" |" if acc_keys else ""))
    if not acc_keys:
        out += ["", "*(no accuracy fields found in this file's rows)*"]
    if slower:
        honest.append("Time-varying study: fojax is slower than " + "; ".join(slower) + ".")
    return out, honest


def scaling(d: dict, name: str) -> tuple[list[str], list[str]]:
    dims = d.get("dims")
    if not isinstance(dims, list):
        return _schema_note(name, d), []
    B = (d.get("settings") or {}).get("batch", "?")
    out = [
        f"### Time vs state dimension (random stable index-1 systems, B = {B})",
        "",
        source_line(d, name),
        "",
        # files without an entry point were measured with the kernel entry of their time
        f"fojax `{(d.get('workload') or {}).get('entry_point', 'simulate_lti_batch')}` vs peer (d) "
        "(`scipy.linalg.expm` per sample + vectorised recurrence); "
        "each entry in a fresh process; speed-up = t_(d) / t_fojax.",
        "",
        "| n | fojax compile (s) | fojax median (s) | fojax samples/s | (d) median (s) | speed-up | max rel. diff | "
        "peak RSS fojax / (d) (MiB) | status |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---|",
    ]
    honest, slower = [], []
    unseparated = []
    for r in dims:
        f, p = r.get("fojax", {}) or {}, r.get("peer", {}) or {}
        sp = r.get("peer_over_fojax")
        if isinstance(sp, int | float) and sp < 1:
            slower.append(f"n = {r.get('n')} ({fmt(sp, '.2g')}×)")
        compile_s = f.get("compile_s")
        if isinstance(compile_s, int | float) and compile_s <= 0:
            # first call - median <= 0: the run's own variation hides the compile time
            compile_s = "n/a¹"
            unseparated.append(f"n = {r.get('n')} (first call {fmt(f.get('first_s'), '.3g')} s, "
                               f"median {fmt(f.get('median_s'), '.3g')} s)")
        else:
            compile_s = fmt(compile_s, ".2f")
        out.append(
            f"| {r.get('n')} | {compile_s} | {fmt(f.get('median_s'), '.3g')} | "
            f"{fmt(f.get('samples_per_s'), '.3g')} | {fmt(p.get('median_s'), '.3g')} | {fmt(sp)} | "
            f"{fmt(r.get('rel_diff', r.get('check_rel_diff')), '.1e')} | {fmt(f.get('peak_rss_mib'), '.0f')} / "
            f"{fmt(p.get('peak_rss_mib'), '.0f')} | {r.get('status')} |"
        )
    if unseparated:
        out += ["", "¹ compile time not separable (first call − median ≤ 0): " + ", ".join(unseparated) + "."]
    mem = d.get("memory")
    if isinstance(mem, list) and mem:
        n = (d.get("settings") or {}).get("memory_n", "?")
        out += [
            "",
            f"Memory vs B (n = {n}; RSS in MiB; *before* = after imports and inputs, *reps* = high-water mark "
            "during the compiled repetitions):",
            "",
            "| B | settings | fojax median (s) | fojax RSS before → reps | (d) median (s) | (d) RSS before → reps |",
            "|---:|---|---:|---:|---:|---:|",
        ]
        for r in mem:
            f, p = r.get("fojax", {}) or {}, r.get("peer", {}) or {}
            out.append(
                f"| {r.get('B')} | {r.get('mode', '')} | {fmt(f.get('median_s'), '.3g')} | "
                f"{fmt(f.get('rss_before_first_call_mib'), '.0f')} → "
                f"{fmt(f.get('peak_rss_repeats_mib'), '.0f')} | {fmt(p.get('median_s'), '.3g')} | "
                f"{fmt(p.get('rss_before_first_call_mib'), '.0f')} → {fmt(p.get('peak_rss_repeats_mib'), '.0f')} |"
            )
    if slower:
        honest.append("Scaling with n: fojax is slower than peer (d) at " + ", ".join(slower) + ".")
    return out, honest


def design_scaling(d: dict, name: str) -> tuple[list[str], list[str]]:
    rows = d.get("rows")
    if not isinstance(rows, list):
        return _schema_note(name, d), []
    s = d.get("settings") or {}
    out = [
        "### Verified design time vs state dimension, LMI and Riccati routes (q0 ≈ n/2, default region)",
        "",
        source_line(d, name),
        "",
        f"`design_functional_observer(..., method=...)` on random stable index-1 systems, solver `{s.get('solver', '?')}`; "
        "total = the whole verified design; cvxpy = inside `Problem.solve` (LMI route only).",
        "",
        "| n | kind | method | total (s) | cvxpy solve (s) | solver | scalar variables | LMI sizes | peak RSS (MiB) | status |",
        "|---:|---|---|---:|---:|---|---:|---|---:|---|",
    ]
    for r in rows:
        size = r.get("problem_size") or {}
        out.append(
            f"| {r.get('n')} | {r.get('kind')} | {r.get('method', 'lmi')} | {fmt(r.get('total_s'), '.3g')} | "
            f"{fmt(r.get('cvxpy_solve_wall_s'), '.3g')} | "
            f"{r.get('solver_used') or '—'} | {size.get('scalar_variables', '—')} | "
            f"{', '.join(map(str, size.get('lmi_sizes', []))) or '—'} | {fmt(r.get('peak_rss_mib'), '.0f')} | "
            f"{r.get('status')} |"
        )
    stopped = d.get("stopped") or {}
    if stopped:
        out += ["", "Stopped: " + "; ".join(f"{k}: {v}" for k, v in stopped.items()) + "."]
    return out, []


def tuning_scaling(d: dict, name: str) -> tuple[list[str], list[str]]:
    rows = d.get("rows")
    if not isinstance(rows, list):
        return _schema_note(name, d), []
    s = d.get("settings") or {}
    out = [
        "### One gradient-tuning step vs training batch size (§3.3.7, `fojax.tuning.tune`)",
        "",
        source_line(d, name),
        "",
        f"per step = (t(1 + k) − t(1)) / k, k = {s.get('extra_steps', '?')}; compile ≈ first call − per step.",
        "",
        "| B | first call (s) | per step (s) | compile ≈ (s) | retraced on every call | status |",
        "|---:|---:|---:|---:|---|---|",
    ]
    honest = []
    for r in rows:
        rt = r.get("retraced_on_warm_calls")
        out.append(
            f"| {r.get('B')} | {fmt(r.get('t_cold_s'), '.3g')} | {fmt(r.get('per_step_s'), '.3g')} | "
            f"{fmt(r.get('compile_s'), '.3g')} | {'yes' if rt else 'no' if rt is not None else '—'} | {r.get('status')} |"
        )
    if any(r.get("retraced_on_warm_calls") for r in rows):
        honest.append("Tuning: every `tune` call recompiles its step (the compile time is paid per call, not once).")
    return out, honest


def _schema_note(name: str, d: dict) -> list[str]:
    """A result file without a table renderer: its scalar top-level values, as a list."""
    if not isinstance(d, dict):
        return [f"### {name}", "", f"*`{name}_latest.json` holds a {type(d).__name__}, not a result dict.*"]
    out = [f"### {name.replace('_', ' ')}", "",
           f"*Source: [`{_LABEL['results']}/{name}_latest.json`]({_LABEL['link']}/{name}_latest.json); "
           "no table renderer for this file: its scalar entries follow, the rest is in the file.*", ""]
    rest = []
    for k, v in d.items():
        if v is None or isinstance(v, str | int | float | bool):
            out.append(f"- `{k}`: {fmt(v, '.4g') if isinstance(v, float) else v}")
        else:
            rest.append(f"`{k}`")
    if rest:
        out.append(f"- other entries (in the file): {', '.join(rest)}")
    return out


def generic(d: dict, name: str) -> tuple[list[str], list[str]]:
    """Any result file with ``rows``, a list of flat dicts: one column per scalar key, in
    the order of first appearance (for a new benchmark before it has its own renderer)."""
    rows = d.get("rows") if isinstance(d, dict) else None
    if not (isinstance(rows, list) and rows and all(isinstance(r, dict) for r in rows)):
        return _schema_note(name, d), []
    keys: list[str] = []
    for r in rows:
        keys += [k for k, v in r.items() if k not in keys and (v is None or isinstance(v, str | int | float))]
    def cell(v):
        return "—" if v is None else fmt(v, ".4g") if isinstance(v, float) else str(v)

    out = [f"### {name.replace('_', ' ')}", "", source_line(d, name), "",
           "| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
    for r in rows:
        out.append("| " + " | ".join(cell(r.get(k)) for k in keys) + " |")
    return out, []


def _first_load(la) -> str:
    """The 1-minute load average of a row's ``[1, 5, 15]``-minute triple (list or its JSON text)."""
    try:
        la = json.loads(la) if isinstance(la, str) else la
        return fmt(float(la[0]), ".3g")
    except (TypeError, ValueError, IndexError):
        return "?"


def study_time_varying(d: dict, name: str) -> tuple[list[str], list[str]]:
    """`study_time_varying.py`: the public `run_study` on the time-varying default study vs
    a `solve_ivp` loop, with both errors against the tight reference."""
    rows = d.get("rows")
    keys = {"B", "fojax_samples_per_s", "peer_samples_per_s", "speedup_vs_solve_ivp",
            "fojax_error_vs_reference_max_rel", "peer_error_vs_reference_max_rel", "fojax_first_call_s"}
    if not (isinstance(rows, list) and rows and all(isinstance(r, dict) and keys <= set(r) for r in rows)):
        return _schema_note(name, d), []
    out = ["### Time-varying default study through `fojax.run_study` (δ(t) sinusoid per sample; exponential engine)",
           "", source_line(d, name), "",
           "| B | fojax samples/s | solve_ivp loop samples/s | speed-up | fojax error | solve_ivp error "
           "| fojax first call (s) | load average |",
           "|---:|---:|---:|---:|---:|---:|---:|---|"]
    honest = []
    for r in rows:
        out.append(f"| {r['B']} | {fmt(r['fojax_samples_per_s'], '.4g')} | {fmt(r['peer_samples_per_s'], '.3g')} | "
                   f"{fmt(r['speedup_vs_solve_ivp'])}× | {fmt(r['fojax_error_vs_reference_max_rel'], '.1e')} | "
                   f"{fmt(r['peer_error_vs_reference_max_rel'], '.1e')} | {fmt(r['fojax_first_call_s'], '.3g')} | "
                   f"{_first_load(r.get('load_average_start'))} |")
        honest.append(f"Time-varying study: fojax's first call at B = {r['B']} (compilation included) took "
                      f"{fmt(r['fojax_first_call_s'], '.3g')} s, the time the solve_ivp loop needs for "
                      f"{fmt(r['fojax_first_call_s'] * r['peer_samples_per_s'], '.3g')} samples.")
    out += ["", "*Errors: largest relative error of IAE, ISE, ITAE and peak against DOP853 (rtol 1e-12) on "
            "the reference samples; the solve_ivp loop is timed on a subset and reported per sample.*"]
    return out, honest


def lmi_formulation(d: dict, name: str) -> tuple[list[str], list[str]]:
    """`lmi_formulation.py`: the full and the reduced region LMI of the LMI route, side by side."""
    from lmi_formulation import table

    rows = d.get("rows")
    if not (isinstance(rows, list) and rows and all(isinstance(r, dict) and "reduced" in r for r in rows)):
        return _schema_note(name, d), []
    out = ["### The LMI route: full region LMI vs reduced (gains eliminated)", "", source_line(d, name), "",
           "CPU = process CPU time of the gains (LMI build, cvxpy or the direct conic build, solver, gain "
           "recovery); speed-up = full / reduced; canonicalisation (cvxpy's; none for the reduced LMI's direct "
           "Clarabel programs) and solver times are wall times.", ""] + table(d)
    slow = [f"{r['kind']} in a {r['region']} at n = {r['n']} (×{fmt(r['speedup_cpu'], '.2g')})"
            for r in rows if isinstance(r.get("speedup_cpu"), int | float) and r["speedup_cpu"] < 10]
    honest = ["LMI formulations: the reduced LMI is less than 10× cheaper than the full one for "
              + "; ".join(slow) + "."] if slow else []
    return out, honest


# The renderer of each benchmark, by the <name> of its results/<name>_latest.json.
RENDER = {"reference_workload": reference_workload, "time_varying": time_varying, "scaling": scaling,
          "design_scaling": design_scaling, "tuning_scaling": tuning_scaling,
          "study_time_varying": study_time_varying, "lmi_formulation": lmi_formulation,
          "lmi_formulation_n48": lmi_formulation}
STUDIES = tuple(RENDER)  # the order of the tables


def shipped(results: Path) -> list[str]:
    """Names of the ``<name>_latest.json`` files in `results`: registered ones in `RENDER`
    order, then the others alphabetically."""
    found = sorted(p.name[: -len("_latest.json")] for p in Path(results).glob("*_latest.json"))
    return [n for n in RENDER if n in found] + [n for n in found if n not in RENDER]


def _set_label(results: Path) -> None:
    try:
        _LABEL["results"] = str(Path(results).resolve().relative_to(HERE.parent))
    except ValueError:
        _LABEL["results"] = str(results)
    try:
        _LABEL["link"] = str(Path(results).resolve().relative_to(HERE))
    except ValueError:
        _LABEL["link"] = _LABEL["results"]


def render(results: Path) -> str:
    """The tables of every shipped result file (the section of ``benchmarks/README.md``)."""
    _set_label(results)
    parts: list[str] = []
    honest: list[str] = []
    for name in shipped(results):
        d, err = load(results, name)
        if err:
            parts += [err, ""]
            continue
        try:
            lines, h = RENDER.get(name, generic)(d, name)
        except (KeyError, TypeError, ValueError, AttributeError) as e:  # a schema we did not foresee
            lines, h = _schema_note(name, d) + [f"*({type(e).__name__}: {e})*"], []
        parts += lines + [""]
        honest += h
    head = [
        "Generated by `python benchmarks/make_readme.py` from the result files shipped in "
        "`benchmarks/results/` (`*_latest.json`, tracked in git); every number below is copied from "
        "those files (see each table's source line for the date and machine). Re-run a script "
        "(see above) and this command to refresh. Timings on a shared or loaded machine are noisy.",
        "",
    ]
    if not parts:
        head.append("No benchmark result is shipped in this version yet.")
        head.append("")
    tail = []
    if honest:
        tail += ["**Where fojax is not faster, and other caveats** (from the same files):", ""] + [f"- {h}" for h in honest] + [""]
    missing = [n for n in RENDER if n not in shipped(results)]
    if missing:
        tail.append("No shipped result yet (no `results/<name>_latest.json`): "
                    + ", ".join(f"`{m}`" for m in missing) + ".")
    return "\n".join(head + parts + tail).rstrip() + "\n"


def build(results: Path) -> str:
    """The whole of ``benchmarks/README.md``: the text below, then the tables of `render`."""
    return (INTRO + "\n" + TABLES_DOC + NARRATIVE + "\n## Results\n\n" + START + "\n"
            + render(results) + END + "\n")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--results", type=Path, default=HERE / "results", help="folder of the *_latest.json files")
    ap.add_argument("--out", type=Path, default=HERE / "README.md", help="the page to write")
    ap.add_argument("--stdout", action="store_true", help="print the tables instead of writing the page")
    args = ap.parse_args(argv)
    if args.stdout:
        print(render(args.results))
    else:
        args.out.write_text(build(args.results))
        print(f"wrote {args.out}")
    return 0




# ============================================================================ the page's text
INTRO = """# fojax benchmarks

Studies that measure fojax against the tools an engineer would otherwise use
They are scripts, not tests: timings never run in the test suite. The test
suite only checks that each workload is built correctly and that all methods agree
(`tests/test_benchmarks.py`).

```bash
pip install ".[bench]"                      # fojax + the peer libraries (python-control)
python benchmarks/reference_workload.py     # the full study, B = 1 ... 100,000 (~20-30 min)
python benchmarks/reference_workload.py --sizes 1 10 100 1000 --repeats 3   # a quick run
python benchmarks/reference_workload.py --help
```

Results (Markdown table + JSON with every repetition, the machine, the library
versions and the date) are written to `benchmarks/results/`:
`reference_workload_<date>.{md,json}` and `reference_workload_latest.{md,json}`. The
`*_latest.json` files are tracked in git (they are the shipped results the tables at the
end of this page come from); everything else there is git-ignored.

## Study 1: the reference workload (`reference_workload.py`)

**Workload** (`_workload.py`, NumPy only, independent of fojax). The observer-based
controller of thesis §4.1.3 with the printed gains (N, J, F, H, S, G, M, P, Q, state
feedback L; u = ẑ, u_r = 0). The observer's input is w = [−E⊥B u; y] with E⊥ = [0 0 0 1];
since E⊥B = [0, 0] for this plant the algebraic loop in u vanishes (asserted). Closing
the loop gives an 8-state index-1 descriptor system (plant x (4), observer ζ (2), v (2))
with one algebraic equation (plant row 4). It is reduced by hand to a 7-state ODE (the
reduction is derived in the module docstring of `_workload.py`), whose nominal
eigenvalues are printed by the script: −39.78, −4.48, −2.21, −2.00, −2.00, −1.69 ± 1.99i.

B samples: A_k = A + δ_k ΔA (ΔA ones at (1,3), (2,2)), δ_k ~ U[−0.3, 0.3];
x(0)_k = [16, −1, 3, 7] ⊙ (1 + 0.1 ξ_k), ξ_k standard normal, then x₄(0) is solved from
the algebraic row (x₄ = x₁ + 2x₂) so that x(0) is consistent; observer states start at 0.
Every sample is stable (asserted; the worst real part over δ ∈ [−0.3, 0.3] is −1.25).
Horizon [0, 10] s, 0.01 s grid (1001 points), float64. Per sample, two metrics: the IAE
of ‖x(t)‖₁ and of ‖ẑ(t) − Lx(t)‖₁ (trapezoid rule on the grid). Sample k is the same for
every B (δ and ξ come from separate streams of one `numpy.random.SeedSequence`).

**Methods** (`peers.py` for the peers; every method returns the (B, 2) metrics):

| | method | notes |
|---|---|---|
| fojax | `fojax.run_study(study, save=fojax.Metrics(kinds="iae", bands=None))` on the workload as a `fojax.Study` (`_workload_study.py`: the 8-state loop built by `fojax.control.closed_loop`, no observers, the signals [x; ẑ − Lx], the two metrics summed from the per-signal IAEs): its exact engine, one exact `expm` per sample (the reduction and discretisation of `fojax.simulate`), all samples stepped together with the batch as the last axis, the metrics accumulated inside the time loop (no trajectory stored) | public API only; `run-study` (= `auto`, chunks of `--chunk` = 4096 samples, the last padded; the `Study` is built outside the timed call); `vmap-simulate` is `jax.vmap(fojax.simulate)` (full trajectories, ~8x slower than (d)). Rows labelled `fojax.simulate_lti_batch (eager)` in older result files were measured with the batch kernel's former direct entry. |
| (a) | Python loop of `scipy.integrate.solve_ivp` (RK45, rtol 1e-6, atol 1e-9, `t_eval` on the grid) | on the reduced ODE |
| (b) | Python loop of python-control `initial_response` on the reduced state space | python-control discretises exactly on the uniform grid |
| (c) | NumPy fixed-step RK4, dt = 1e-3, vectorised over the batch | both axis orders (batch-first `(B, n)`, batch-last `(n, B)`) are timed, the faster is kept |
| (d) | exact discretisation: `scipy.linalg.expm(A_k·0.01)` (SciPy maps it over the stacked `(B, 7, 7)` array) + a recurrence vectorised over the batch | both axis orders, the faster is kept; **(d) is the accuracy reference** |

The vectorised peers accumulate the metrics while stepping, so their memory is linear
in B and no (B, T, n) trajectory is stored.

## Fairness rules

- **Agreement before timing.** All methods are first run on the same `--check-b`
  samples (default 100) and the largest relative difference of the per-sample metrics to
  peer (d) is printed; the script stops without timings if any method exceeds its
  tolerance (fojax and python-control 1e-8 / 1e-10, RK4 1e-8, solve_ivp 1e-4). At every
  timed B the results are compared with (d) again and reported in the table.
- **What is timed.** Only the computation from prepared inputs to the (B, 2) metrics.
  Imports, drawing the samples, building the matrices and the peers' hand reduction are
  outside the timed region (fojax does its own reduction inside `simulate`, which is timed).
- **Compilation separately.** Before fojax's first call at each B the JAX caches are
  cleared. In `jit` mode the ahead-of-time lower + compile is timed on its own; in `vmap`
  mode the compile time is estimated as first call − median. Every method's first call is
  reported separately from the repetitions.
- **Repetitions.** After the first call, up to `--repeats` (default 5) repetitions, stopping
  when `--budget` seconds (default 60) are spent; the **median** is reported together with
  the number of repetitions. If the first call alone exceeds the budget it is the single
  measurement (reps = 1). fojax's output goes through `jax.block_until_ready`.
- **Slow loop peers.** (a) and (b) run up to `--loop-max-b` (default 1,000); for larger B
  their time is extrapolated linearly from the per-sample time at the largest measured B
  and marked *extrap.* in the table and `"extrapolated": true` in the JSON (pass e.g.
  `--loop-max-b 100000` to run them, which takes hours for solve_ivp).
- **Axis orders** of (c) and (d) are both timed up to `--variant-max-b` (default 10,000);
  above it only the variant that won at the largest such B is run.
- **BLAS threads.** The script sets `OPENBLAS_NUM_THREADS=1` (and MKL) unless you set them
  yourself: on the 2-core reference machine the peers' small 7×7 BLAS/LAPACK calls run
  2–10× *faster* single-threaded (threads only contend), so this favours the peers. XLA
  (fojax) uses its own thread pool. NumPy's `einsum` kernels are single-threaded anyway.
- **Load.** The machine's load average at the start and the end is recorded; timings on a
  shared machine are noisy, so compare runs made under the same load.

The table reports seconds (median), samples/s, the relative difference to (d),
`t_fojax/t_peer` and the fojax speed-up `t_peer/t_fojax` (> 1 means fojax is faster), plus a
speed-up-by-B summary. At B = 1 compilation dominates fojax's first call; the median
excludes it, so read the compile column too.

## Known problem: fojax can deadlock on jax/jaxlib 0.10.x (2-core CPU)

With jax 0.10.2 the vmapped `fojax.simulate` sometimes never returns (seen at B = 1,000 and
10,000, more often under load). All XLA pool threads are parked in
`jax::ParallelBatchMap` ← `lapack_dgetrf_ffi` (batched LU behind `jnp.linalg.solve`/`expm`
under `vmap`): each batched LAPACK call blocks on sub-tasks queued on the same intra-op pool,
and with two such calls running concurrently on a 2-thread pool nothing is left to run them.
jaxlib ≥ 0.11 compiles that parallel path out; `--xla_cpu_multi_thread_eigen=false` does
*not* help (it hung on the first call). The script therefore runs every fojax call under a
watchdog: if the process makes no CPU progress for `--idle-timeout` s (default 120) or a
fojax entry exceeds `--hang-timeout` s (default 1800), it prints the diagnosis, writes the
partial results (status `ABORTED: …`) and exits with code 3. Results are also written after
every B, so a later hang does not lose the earlier sizes.

## The product path: `fojax.run_study` on the default §3.3.7 study (`study_default.py`)

Times the public `fojax.run_study` (what `fojax study` and the notebooks call) on the
default §3.3.7 study in its exact LTI form: fault-augmented plant (n = 9, rank E = 7),
constant δ ∈ [−0.3, 0.3] × constant faults, zero input, PO + FGDO observers (disk
centre −3, radius 2; 22-state joint slow loop), 10 s on a 0.01 s grid, IAE / ISE / ITAE /
peak / settling time per sample, observer and signal. `run_study` takes its exact engine
(`attrs["engine"] == "exact-batch"`: the batch-last kernel of `fojax.simulation._batch`). The
peer is a vectorised SciPy/NumPy user (batched index-1 reduction, `scipy.linalg.expm` on
the `(B, N, N)` stack, batched NumPy recurrence accumulating the same metrics). Per-sample
metrics are checked to agree (≤ 1e-8 relative; measured 2.4e-12) before timing.

```bash
python benchmarks/study_default.py                      # B = 1,000 and 10,000, median of 3
python benchmarks/study_default.py --host-devices 2     # shard the batch over 2 host devices
```

One run, 2026-11-25 14:44 UTC, 2-core CPU **shared with other jobs (load average 5–6)**,
one JAX device, `quantiles=()` (`benchmarks/results/study_latest.json`):

| B | `fojax.run_study` (samples/s) | SciPy/NumPy peer (samples/s) | ratio | first call (compile ≈) | with default quantile bands |
|---:|---:|---:|---:|---:|---:|
| 1,000 | 4,892 | 2,295 | 2.1× | 4.1 s (3.9 s) | 0.57 s |
| 10,000 | 4,638 | 1,236 | 3.8× | 6.4 s (4.2 s) | 8.0 s |

The peer's rate moves with the machine's load (696 samples/s at B = 10,000 in the run
before this one, 1,236 here), and so does the ratio. Measured back to back at B = 10,000
under the same load, the kernel before the compile fix (git d5d9b61) ran 3,395 samples/s
(3.6× its peer run, first call 25.9 s) and this one 4,638 samples/s (3.8×, first call 6.4 s).

Where fojax is still slow: the default time-wise quantile bands, which keep every sample's
`(T, q)` error trajectory and call `np.quantile` on the host (8.0 s of the 10,000-sample
run; the former `vmap(simulate)` path paid the same). Compilation was 30–40 s under load
until the unrolled 22 × 22 Gaussian elimination of the kernel's output basis (`solve_small`)
and the unrolled products of `expm_last` became `fori_loop`s (issue 13); the compiled graph
no longer grows with the number of joint states. Before issue 13 (quiet machine) `run_study`
ran 697 samples/s on this study, 0.53× the peer.

## Study 2: time-varying δ(t) and an actuator fault (`time_varying.py`)

```bash
python benchmarks/time_varying.py                    # B = 1, 100, 1,000, 10,000 (~10-15 min)
python benchmarks/time_varying.py --sizes 1 100 1000 --repeats 3 --ref-b 10   # a quick run
```

**Workload** (`_workload.make_tv_workload`, NumPy only). The loop of study 1 with a
time-varying uncertainty and a fault: A_k(t) = A + δ_k(t) ΔA with δ_k(t) = a_k sin(ω_k t + φ_k),
a_k ~ U[0, 0.3], ω_k ~ U[0.5, 5] rad/s, φ_k ~ U[0, 2π), and a constant actuator fault
f_k ∈ ℝ², each component ~ U[−1, 1]: the plant receives u + f_k, the observer the commanded
u = ẑ, so the closed loop is 𝓔 x̄' = 𝓐(δ_k(t)) x̄ + [B; 0] f_k. x(0)_k is study 1's (same
stream). ΔA and the fault touch differential rows only, so the hand reduction is affine in δ
(asserted): x_d' = (A_red0 + δ_k(t) ΔA_red) x_d + b f_k. **Stability of every sample, for any
δ(t) with |δ| ≤ 0.3 whatever its rate**: a common quadratic Lyapunov function with decay rate
0.5 exists at both vertices (an LMI solved with cvxpy/Clarabel, then verified with NumPy
eigenvalues; printed by the script, checked in the tests). Horizon, grid and the two IAE
metrics as in study 1.

**Accuracy first.** Exact discretisation does not apply, so "equal accuracy" is measured:
a tight reference (`peers_tv.tight_reference`: `solve_ivp` DOP853, rtol 1e-12, atol 1e-14,
on `--ref-b` samples, default 100; its own error is estimated against rtol 1e-13 on 5
samples) and every method's **max relative error of the per-sample metrics** against it.
The max is set by the worst samples (a near 0.3, ω near 5 rad/s), so the check needs enough
samples to draw some: with 20, a schedule with one step per 0.01 s after the start-up looked
as accurate as RK4 (6.8e-11 vs 8.6e-11), with 100 it is not (2.7e-10 vs 1.0e-10). fojax
is then timed in two schedules, each at equal or better accuracy than RK4:

- *uniform*: the largest uniform step (fewest `substeps` per 0.01 s grid interval, among
  1, 2, 3, 4, 5, 6, 8) whose error is at most RK4's (`--substeps` fixes it instead);
- *start-up*: the cheapest schedule `substeps=s, startup=(k, s0)` (s0 steps per interval over
  the first k intervals, s after) whose error is at most RK4's, with k = 13 intervals = 5 time
  constants of the fastest nominal pole (−39.8) and (s, s0) among (1, 2), (1, 4), (1, 8), (2, 4),
  (2, 8) (`--no-startup` skips it). Why: the initial state excites the fast pole, and the
  perturbation δ(t)ΔA couples it into the part of the field the exponential integrator
  approximates; almost all of the uniform schedule's error is made in the first ~0.05 s.
  Resolving that layer lets the rest run with one step per 0.01 s.

Every candidate's error is in the accuracy table (with its number of steps), so either entry
can be judged. At every timed B, fojax's metrics are also compared with RK4's
(`rel. diff vs RK4`).

| | method | notes |
|---|---|---|
| fojax | `fojax.run_study(study, stepper=fojax.Exponential(substeps=s, startup_factor=s0 / s))` on the batch as a `fojax.Study` (no observers, the signals [x; ẑ − Lx]): the template is `FaultyPlant(UncertainDescriptorSystem(nominal, dA, delta=Sine(a, ω, φ)), Fa=[B; 0], fault=Constant(f))`, sample k is (δ_k, f_k, x0_k) (rows labelled `simulate_batch_exponential` in older result files were measured with the kernel's former direct entry); fojax reduces the descriptor loop itself, takes the nominal (δ = 0) loop as the common linear part and integrates it exactly with Krogstad's 4th-order exponential Runge–Kutta method, all samples together (batch last), metrics accumulated in the loop | public API only; one compiled kernel per chunk size (`--chunk` = 4096); compile time = first call − median after `jax.clear_caches()` |
| (a) | Python loop of `solve_ivp` (RK45, rtol 1e-6, atol 1e-9, `t_eval` on the grid) on the reduced ODE | up to `--loop-max-b` (default 1,000), extrapolated linearly beyond (*extrap.*) |
| (c) | NumPy RK4, dt = 1e-3, vectorised over the batch, both axis orders (the faster kept) | the careful version: common matrices applied as one product for the whole batch (`X @ A0.T`, `X @ dA.T`, δ scaling per sample), δ evaluated twice per step, metrics accumulated while stepping |

Timing rules are those of study 1 (imports, sampling and the peers' hand reduction
outside the timed region; first call separately; median of up to `--repeats` within
`--budget` s; `block_until_ready`; single-threaded BLAS for the peers). Results:
`results/time_varying_<date>.{md,json}` and `time_varying_latest.{md,json}`, with the
accuracy table, the machine, versions and date. The fojax entry makes no batched LAPACK
call (the φ-functions use a Taylor exponential, the per-sample eliminations the LAPACK-free
`solve_small`; the one SVD of the common E is not batched), so the deadlock of the known
problem above should not apply to it; the script has no watchdog.

## Scaling with the state dimension and memory with B (`scaling.py`)

```bash
python benchmarks/scaling.py                     # n = 4 ... 64 at B = 1,000, memory sweep B = 1 ... 100,000
python benchmarks/scaling.py --dims 4 8 --batch 100 --memory-sizes 1 100 --repeats 2   # a quick run
```

**Systems** (`random_stable_index1`, NumPy only): E = U diag(I_r, 0) V and A = U A₀ V with
U, V random orthogonal, n_alg = max(1, n // 4) algebraic equations, A₀ entries N(0, 1/n),
the algebraic block A₀,₂₂ − I redrawn until its condition number is < 50 (index 1). Samples
perturb the differential block, A_k = A + δ_k ΔA with ‖D‖₂ = 1 in those coordinates and
δ_k ~ U[−0.3, 0.3]; A₀,₁₁ is shifted left so that the logarithmic norm of every sample's
slow matrix is ≤ −1, hence every finite pole of every sample has Re ≤ −1 (< −0.5) for any
B. The script checks the pencils with `scipy.linalg.eigvals` (exactly r finite poles equal
to the slow matrix's eigenvalues) before timing. x(0)_k = T z_k (consistent), z_k ~ N(0, I).
Horizon [0, 10] s, 0.01 s grid; metric per sample: IAE of ‖x(t)‖₁.

**Methods**: fojax = `fojax.run_study(study, stepper=fojax.Exact(), save=fojax.Metrics(kinds="iae",
reduce="sum", bands=None))` on the signal study z = x of the samples (L = I, no observers;
fojax reduces and discretises itself, inside the timed call; rows measured before carry the
former kernel entry `simulate_lti_batch` in their file's label); peer (d) = the same code as `peers.py`'s (d) written for any n (hand reduction
outside the timed region, `scipy.linalg.expm` on the stacked slow matrices, recurrence
vectorised over the batch, both axis orders, the faster kept).

**Rules**: agreement ≤ 1e-8 relative on `--check-b` samples before any timing (and again
at the timed B); every entry (one method at one (n, B)) runs in a fresh process, so the
fojax compile time is a cold start (reported as first call − median) and the memory
numbers belong to that entry: RSS before the first call, high-water mark after it (fojax:
includes compilation) and over the repetitions (the mark is reset in between with Linux's
`clear_refs`). The memory sweep (`--memory-n`, default 8) runs fojax and (d) at each
`--memory-sizes` B. The time-vs-B table on the reference workload is *not* re-measured: it
is copied from the reference workload's own result file (written by `reference_workload.py`,
with its date) into the report.

## Design time vs state dimension, LMI and Riccati routes (`design_scaling.py`)

```bash
python benchmarks/design_scaling.py              # n = 4 ... 500, both kinds, both routes (LMI up to n = 50)
python benchmarks/design_scaling.py --lmi-max-n 32 --hard-timeout 900   # the shipped run
python benchmarks/design_scaling.py --dims 4 6 8 --kinds proportional --methods lmi --solver SCS
```

One call of the public entry point `fojax.design.design_functional_observer(sys, L,
kind=..., q0=q0, method=...)` per (n, kind, method) with the default region Disk(−2, 1);
`method="lmi"` with fojax's default solver (`auto`: Clarabel, SCS as fallback; `--solver
SCS` for SCS only), `method="riccati"` the Riccati route (`fojax/design/_riccati.py`: a
discrete Riccati equation for the gain, a Stein equation for the certificate, no SDP). The
LMI route runs only up to `--lmi-max-n` (default 50, where it already takes minutes).
The plant is the random stable index-1
system above with m = 2 random inputs and p = max(1, n // 4) random outputs; L has
q = max(1, n // 2) random rows and q0 = q (so q0 ≈ n/2; R is fojax's default for that
order). `fojax.analysis.is_functionally_observable` is checked first (it holds for every L
here because the plant is impulse free). Reported: total design time (existence checks,
default R, LMI build and solve or Riccati/Stein solves, float64 verification) and the
process's CPU time for it, the time inside cvxpy's
`Problem.solve` over all of fojax's attempts and the solver's own time, the solver used,
the accepted problem's size (scalar variables, LMI blocks and sizes, equalities, captured
by wrapping `cvxpy.Problem.solve` during the call), the error poles, the peak RSS, and the
load average before and after each design (the machine may be shared). Typed
fojax errors, crashes and timeouts are rows. Each design runs in a fresh process after an
untimed n = 4 warm-up design; for each (kind, method), n stops increasing once a design
takes longer than `--budget` s (default 120). **Agreement:** observers are not unique (the
routes choose different gains), so the routes agree when both designs pass the same
float64 verification; `agreement` in the JSON lists this per (n, kind).

## The LMI route's formulations, full vs reduced (`lmi_formulation.py`)

```bash
python benchmarks/lmi_formulation.py             # n = 24, 36, 48; three kinds; five regions
python benchmarks/lmi_formulation.py --dims 24 36   # the shipped run
python benchmarks/lmi_formulation.py --dims 48 --name lmi_formulation_n48
```

On the `half` shape of `design_routes.py` (q0 = n // 2, R by fojax's default), the region LMI
of one structure solved in the two formulations of the LMI route: the full Chilali–Gahinet
LMI of the error dynamics (`fojax/design/_region_lmi.py`, certificate of order q0 + q1, the
gains as variables) and the reduced one that `method="lmi"` uses above observer order 12
(`fojax/design/_eliminated.py`: the ε-block's certificate, the gain eliminated for disks,
half-planes, sectors and their intersections and then reduced by one step of the
observability staircase, a disk intersected with another region solved in its inscribed disk
first; built with NumPy and solved by Clarabel without cvxpy). Both
designs go through the same float64 verification. Reported per formulation: process CPU
time, cvxpy's canonicalisation and the solver's time (wall), scalar variables, the largest
gain entry, verification; the speed-up is the ratio of CPU times.

## One tuning step vs training batch size (`tuning_scaling.py`)

```bash
python benchmarks/tuning_scaling.py              # B = 8, 32, 128, 512, 2048
python benchmarks/tuning_scaling.py --sizes 8 32 --extra-steps 2
```

The setup of `notebooks/monte_carlo_and_tuning.ipynb` (§3.3.7 fault-augmented benchmark,
generalized LMI design in Disk(−2, 1), constant δ × constant faults, 81 grid points,
`optax.adam(0.3)`, `stepper=fojax.Exact()`), with a training study of B = N_u × N_f samples (as
square as possible). In a fresh process per B: `tune(steps=1)` cold, `tune(steps=1)` warm
and `tune(steps=1 + k)` warm; per step = (t(1 + k) − t(1)) / k, compile ≈ first call − per
step; `fojax.tuning._tune.TRACE_COUNTS` tells whether the warm calls retraced the step.
"""

TABLES_DOC = """## Tables (`make_readme.py`)

This page is generated: `python benchmarks/make_readme.py` writes it from the text kept in
`make_readme.py` and the `results/*_latest.json` files present. In the "Results" section every
number is copied from a file, each table names its file, date and machine once, a list says
where fojax is slower, and a file whose keys are not the expected ones is skipped with a note
(`--stdout` prints the tables instead). Each benchmark has one renderer in the `RENDER`
registry of `make_readme.py`, keyed by the `<name>` of its `<name>_latest.json`; a result file
without one is shown as a generic table of its `rows`.

"""

NARRATIVE = """## Measurements from development

What the project measured while building fojax, with the date, machine and load of each run where it matters; the result files named here hold the numbers. These paragraphs were the measurement notes of earlier versions of the top-level README.

### `fojax study` and the test suite

The first command installs fojax and runs its main job, the built-in robustness study
(thesis §3.3.7: an uncertain descriptor system with actuator and sensor faults): it checks
the model's structure, designs a proportional and a generalized functional observer by LMI
(verified), tunes the generalized one by gradient descent, runs the Monte Carlo study of all
three over 64 independent draws of (δ, fault scenario), prints mean IAE, peak error and
settling time per observer and signal, and writes a results folder (designs, metrics, the
samples it drew, figures, `report.md`) under `./fojax-results`. On a 2-core Intel Xeon at
load 0.9–1.5 (2026-11-28 00:0x UTC, this tree, install and imports excluded; `benchmarks/cli_study.py`,
[result](results/cli_study_latest.json)) the study took 19.2 s and 18.9 s in two runs
(27.7 and 27.8 s of CPU; 25.1 and 22.6 s at load 1.2–2 earlier that day, tree c496705: mostly
the load, since the tuning changes in between left this command's time unchanged in paired
runs): tuning about 13 s (60 Adam
steps on 128 samples, compilation included; the
Monte Carlo program compiles on a thread meanwhile), Monte Carlo 0.1 s after that, structure
checks and LMI designs 2 s — under issue
13's 30 s target. Most of it is XLA compiling fojax's
programs; the `fojax` program compiles them without XLA:CPU's fusion emitters
(`fojax/cli/_devices.py`, jaxlib 0.10), which on that machine took the command from 37.7 s
(59.8 s of CPU) to 29.2 s with the same results bit for bit; it also makes some kernels
slower (a tuning step at 2,048 training samples 0.40 → 0.52 s, so long tuning runs on large
batches are better off with `XLA_FLAGS=--xla_cpu_use_fusion_emitters=true`; the numbers are in
that file's docstring). (On the AMD EPYC of the earlier measurements, before that flag: 28.4 s
and 28.2 s.)
The install took 21 s on 2026-11-25 (pip's download
cache warm; 50 s measured earlier without it). The tuning minimises the mean ISE ∫e² dt of the
estimation errors (`[tuning] loss`, [docs/config.md](../docs/config.md)): on that default run it
lowers the study's mean IAE by 11.6 % and the summed mean peak errors by 29.3 % (f1's peak
rises 23 %, and the mean settling times to |e| ≤ 0.05 of z1 and f1 rise from 1.5 to 3.3 s and
from 5.2 to 6.2 s (with IAE: to 3.0 and 6.0 s); the report shows IAE, peak and settling time per signal). Trained on the mean IAE
instead, as until 2026-11-27, the tuned observer's fault estimates overshoot: IAE −0.8 % with
the summed peaks +139 % on the same 64 samples, and on 512 evaluation samples IAE −1.7 % and
peaks +154 % against −9.8 % and −30 % for ISE (one run each; on `fojax study robot_arm_ts`,
IAE −48 % / −54 % and peaks −51 % / −44 % for its two observers with ISE, against −44 % / −52 %
and −30 % / −9 % with IAE). What tuning buys on this benchmark as δ's range varies is measured
in the notebook `notebooks/monte_carlo_and_tuning.ipynb` (issue 14). `fojax demo` is a 20-second tour on thesis example 4.1.3.
The second command installs the test dependencies and runs the whole test suite (what CI
runs, via `.ci/run`): 1,023 tests on two worker processes, about 11–13 minutes on a 2-core CPU
(`.ci/run` on clean clones, Intel Xeon, one run at a time; on the final code of 2026-11-28:
11 min 26 s of tests (11 min 33 s with the install) with `OPENBLAS_CORETYPE` unset and 11 min
35 s (11 min 44 s) with `Haswell`, at load 0–4; on 2026-11-27/28, 10 min 50 s – 13 min 17 s
with the default, `Haswell` and `Sandybridge` kernels; 15 min 13 s the evening before, and 15–17 min
before that). Most of it is compilation each test needs once (a tuning step, a diffrax solve, a
study in each of 2–3 processes of the multi-process tests), so the test runs compile without
XLA:CPU's fusion emitters and with most of XLA's optimizations off
(`JAX_DISABLE_MOST_OPTIMIZATIONS=1`, LLVM at -O0: a test checks numbers against tolerances and
independent computations, not the code XLA generates), except the modules that compare
different programs bit for bit (other device counts, processes, block and chunk sizes), which
compile as users do; `tests/conftest.py` has the measurements (the fusion-emitter flag alone
took the suite from 23 min 0 s to 16 min 46 s, 997 tests then).

### Benchmarks of the product path

fojax against the tools engineers use today (a `solve_ivp` loop, python-control, vectorised
NumPy RK4, exact discretisation with `scipy.linalg.expm`), scaling with the state dimension,
LMI design time and tuning-step time: the scripts, their fairness rules and the tables of the
shipped results are in [benchmarks/README.md](README.md).

Measured on 2026-11-26 (21:4x UTC) on the 2-core CPU at light load (load average 1.1 at the
start, no other jobs), this tree, the default §3.3.7 study (22-state loop, 1,001 grid points),
B = 10,000 samples, through the public `fojax.run_study`, against a vectorised SciPy peer
(`scipy.linalg.expm` on the batch plus a NumPy recurrence) on the same samples, after checking
that the per-sample metrics agree to 5e-12 ([result](results/study_latest.json)):

| | fojax | peer | ratio |
|---|---:|---:|---:|
| default settings (metrics + quantile bands), one device | 1.31 s | 6.65 s (same bands) / 6.35 s (no bands) | **5.1×** / 4.8× |
| metrics only, one JAX device | 1.14 s | 6.35 s | 5.6× |
| first call (compilation included) | 4.5 s (compile 3.3 s) | | |
| *earlier tree:* metrics only, two host devices | 0.57 s | 5.41 s | 9.5× |

With the default quantile bands fojax is **at the 5× target** against a peer that computes
the same bands: four runs alternating this tree and the tree before this stop's kernel
changes gave 4.8×–5.1× for both (the JSON keeps all four), so read it as "about 5×", within
the machine's run-to-run noise of the threshold. On the Intel Xeon of the later runs (2026-11-27,
five runs back to back at load ~1, where both sides are slower: fojax 1.83–2.14 s, the peer
9.8–10.7 s) the ratio was 4.63× / 4.79× / 5.15× / 5.24× / 5.59×, median 5.15×
([result](results/study_latest.json), `intel_xeon_runs`).
Keeping the errors on the 201-point band grid costs about 0.13 s: the kept columns are turned
batch-last inside each pass and the blocks are written side by side, so putting a chunk back
in sample order is a reshape, and the host sorts its own buffer in place (bit-identical to
`np.quantile`). One `fojax.tune` step at B = 2,048 on the same study takes **0.21–0.23 s** on the
Intel Xeon at light load (0.27 s of CPU; four runs back to back on 2026-11-27 23:27–23:29 UTC,
load average 0.95–1.4, mostly the benchmark itself; target 0.3 s: met), and 0.231–0.302 s
(median 0.246 s) in four earlier runs at load 1.7–2.1 from other jobs
([result](results/tuning_step_latest.json): `light_load_runs`, `paired_runs`).
The study's 10 fault scenarios of one δ share their joint matrix, so the loss forms its
exponential, the exponential's reverse pass and the pass matrices once per δ instead of once per
sample (`fojax.studies._exact.scenario_free` decides it from the model's computation graph;
value and gradient equal the per-sample computation to rounding): the value-and-gradient takes
0.21–0.30 s instead of 0.49–0.51 s. The loss's time loop runs in
passes of 8 grid steps (Φ⁸ and the stacked output rows [GΦ; …; GΦ⁸] per sample, so the state's
update, the adjoint's λ scan and its outer products are 8× fewer; loss and gradient equal the
step-by-step loop to 7e-15), the matrix exponential's reverse pass is hand-written, and the
adjoint handles plain sums of |e| or e² one segment at a time (`fojax/studies/_adjoint.py` has
the breakdown). The step's own program (the loss, its gradient and the optax update; the step
rule, which halves an update until the iterate is admissible, runs on the host, outside
the program) compiles in **7.1–7.3 s** at light load (tracing 1.6 s, lowering 0.4–0.5 s, XLA
5.1–5.3 s), and the first `tune` call, which also counts the live parameters, certifies the
start and compiles 18 other, small programs, takes **8.0–8.2 s** (the same four runs; target
≤ 10 s: met). At load 1.7–2.1 the same code took 8.4–10.7 s (median 9.3 s) and 9.4–12.0 s
(median 10.3 s): the target holds on this machine when it is not shared, and is at its edge
when it is (the tree before the step rule moved to the host: 9.9–11.6 s and 11.3–13.3 s at that
load).
The step program compiles on a thread while `tune` analyses the live parameters, and its host
checks are one compiled program (0.016 s each). Most of XLA's time is LLVM code generation (436 kernels in the tree before),
many of them data movement (transposes, the stacking of the 32-sample blocks' outputs and
residuals).
`fojax study` (the README's first command, install and imports excluded) takes **19.2 s and
18.9 s** on the Intel Xeon in two runs at load ~1 (target 30 s: met; 37.7 s without the program's
compile flag, see above; on the AMD EPYC before that flag 28.4 s and 28.2 s;
[result](results/cli_study_latest.json)):
the Monte Carlo and held-out programs compile on threads while the tuning runs, and the
samplers, the starting margin and the host checks are compiled programs instead of hundreds
of small eager ones. Time-varying δ(t) studies on the exponential engine run **61×** a
`solve_ivp` loop (B = 1,000) at 5e-10 from a DOP853 reference; their first call compiles in
3.9 s wall, 5.4 s of CPU (target 5 s; load 1.5; [result](results/study_time_varying_latest.json)),
and `tune` on such a study trains on that engine (one step at B = 256: 6.9 s of CPU under
load; the diffrax path it replaced needed 22.8 s at B = 20; gradient checked against central
differences; [result](results/tuning_time_varying_latest.json)).
`fojax study --devices N` (or `auto`, or `FOJAX_DEVICES`) spreads the samples over N JAX CPU
devices with bit-identical results; on the default study it is not faster (20.1 s and 21.4 s
against 19.0 s and 21.2 s on one device, alternating on the Intel Xeon at load ~2, 2026-11-28;
27.5 s against 26.9 s on the AMD EPYC before; the sharded programs compile longer and its
batches are small; [result](results/cli_study_2devices_latest.json)), so the
default is one device.
Through `run_study` on random index-1 models with an observer (B = 1,000, 1,001 points, each
entry in a fresh process, [scaling](results/scaling_latest.json), measured
2026-11-26 21:51–22:03 UTC on this tree, load average 0.9–1.4 at the start of every row)
fojax runs 4.9× / 4.9× / 8.0× / 8.4× / 10.0× / 6.9× / 6.3× the SciPy peer's wall time at
n = 4 / 8 / 16 / 32 / 64 / 128 / 256 (3.6–7.3× in CPU time; agreement ≤ 7.1e-13): **≥ 3× for
every n**. What made it: the per-call shape evaluations are cached by structure, each pass
computes the next m outputs as one product from precomputed rows and moves on with Φ^m, from
N = 32 the plant and observer blocks of the block-triangular joint matrix are stepped
separately, and below N = 10 the blocks of samples are sized so that their Φ stay in L1 cache.
Compilation (first call − median, caches cleared) 4.0–6.2 s wall, 5.9–9.8 s CPU for every n
up to 128 (target ≤ 10 s); at n = 256 the first call takes 17.5 s and the median 12.3 s. Memory
at n = 8, B = 100,000 (each entry's peak RSS is its own process's): 548 MiB against the peer's
526 MiB with metrics only (1.04×; target ≤ 2×), 909 against 1,387 MiB with the default quantile
bands (0.66×); at B = 1,000 fojax's peak is mostly the JAX runtime (476–600 MiB), below the
peer's from n = 128 on.

The thesis §4.1.3 observer-based control loop (the reference workload of
`benchmarks/_workload.py`) runs through the same entry point: without observers,
`run_study(study)` reports the metrics of the study's signal z = L x itself, and
`fojax.control.LoopMaps.signal_rows` gives the rows of [x; ẑ − Lx] on the loop's state, so the
summed per-signal IAEs equal the workload's two metrics (to 2e-14). At B = 10,000, one JAX
device, at light load (1.0): 0.0746 s against the raw kernel's 0.0735 s (its former direct entry, `simulate_lti_batch`)
(1.01×; target ≤ 1.2×: met) and the vectorised SciPy-expm peer's 0.4065 s: **5.45× in wall
time, 3.17× in CPU time** (0.1275 vs 0.4035 s). The target of 4× at one device is met in wall
time on a quiet machine, where XLA's thread pool uses the second core and the peer runs
single-threaded (its 7×7 BLAS calls are slower with threads; benchmarks/README.md), and missed
in CPU time; under load the two ratios converge (2.75× last stop at load 3). This stop sized
the blocks of the batch kernel for N < 10 so that the samples' Φ stay in L1 cache (the
time loop 11.7 → about 7–9 ns per sample-step) and made the output-basis change two batch-last
products; the loop is now bound by XLA's loads (it reloads the state for every row), which a
hand-written kernel could halve ([result](results/reference_workload_run_study_latest.json)).

### Designs and tuning beyond the thesis

**Units do not change verdicts.** Before every rank decision and eigenvalue computation,
`fojax.analysis` rescales equations and states exactly, by powers of two (Ward's
least-squares balancing rounded to powers of two; SLICOT's TB01ID when E = I), and reports
the scaling (`balance=False` turns it off). On 200 random systems whose equations and states
were scaled by up to 2^±40, every verdict and every pole stayed the same
(`tests/test_analysis_scaling.py`; without balancing most verdicts change). The issue's
badly scaled examples are now answered correctly, e.g. diag(1, 1e-11)·(s + 1) is regular with
poles [−1, −1], and pencils T·diag(D), T with cond(T) ≈ 1e18 give D to 6e-15.
`fojax.analysis.kronecker_structure`, `system_zeros`, `properness` and `mode_counts` (SLICOT AG08BD after
balancing) give normal rank, minimal indices, infinite elementary divisors, finite eigenvalues
and invariant zeros; `fojax check` prints them.

**H∞ functional observers.** `design_functional_observer(..., objective="hinf", Bw=, Dv=)`
(or `objective = "hinf"` in a model file) minimises a bound γ on the L2 gain from a
disturbance w (E ẋ = Ax + Bu + B_w w) and measurement noise ν (y = Cx + D_v ν) to ẑ − z, with
the error eigenvalues still in the region. Every γ is re-checked in float64 (bounded-real LMI
at the returned certificate) and against the H∞ norm of the error system computed
independently by SLICOT's AB13DD; `fojax design` reports both. Measured γ/‖T‖∞: 1.0000 on
the scalar case, on example 4.1.3 and on every benchmark row, at most 1.0015 on random n = 5
descriptor systems. On §3.3.7 with output noise σ = 0.5 it lowers the Monte Carlo mean IAE
by 20–32 % against the region-only LMI design; with weak noise (σ = 0.05), or when constant
faults are estimated as states (every admissible observer then has the same ‖T‖∞, at ω = 0),
it does not improve on it ([result](results/hinf_vs_region_latest.json), few samples,
measured on a loaded machine). Z is taken from the region-only design (the problem is not
convex in Z), and region + H∞ share one certificate, which is conservative.
Tuning can keep robustness in the loss: `tune(..., robustness=fojax.tuning.HinfTerm(w))`. On
§3.3.7 with σ = 0.5 (8 held-out samples, measured under load), tuned from the H∞ design: weight
0 gives mean IAE 1.82 and ‖T‖∞ 0.246, weight 1 changes nothing measurable (1.86, 0.248), weight
10 gives ‖T‖∞ 0.174 — below the H∞ LMI design's certified 0.209 — at mean IAE 2.57
([result](results/hinf_vs_region_term10_latest.json)).
On a model not from the thesis (the two-stage LC filter below, load ±50 %, noise on both
outputs, 8 held-out samples, measured under load) the H∞ design is *not* better than the
region-only one: at the default order it is the same observer (γ = the region-only ‖T‖∞; one
live parameter); at order 4 it lowers ‖T‖∞ (0.26 → 0.16 at σ = 0.05) and cuts the IAE of the
noise-driven error by 40 %, but with a nonzero initial state its mean IAE is worse (1.76 vs
1.25): ‖T‖∞ does not weigh the initial transient. There the tuned observer is best (0.67),
and under strong noise (σ = 0.5) the H2 design (2.81 vs 4.39 for the region-only design)
([results](results/hinf_vs_region_lc_q4_latest.json); re-run with the canonical
default R, which changed the order-4 region-only design — the earlier run is kept in the file:
0.31 → 0.16, −54 %, 1.18, 0.77, 5.50).

**H2 functional observers.** `objective="h2"` (or `objective = "h2"` in a model file)
minimises a certified bound ν on the H2 norm from [w; ν] to ẑ − z, with the error
eigenvalues in the region. The feedthrough from the noise to ẑ − z must be zero: fojax imposes
it exactly, or refuses before any LMI and names the fix (on §3.3.7 a larger order, q0 = 4).
Every ν is re-checked in float64 and against the H2 norm SciPy's Lyapunov solver gives.
Measured ν/‖T‖₂: 1.0000 on the scalar Kalman case (the closed-form optimum), 1.001–1.05 on
§3.3.7, up to 1.18 on random descriptor systems (one certificate serves the H2 and the region
constraints, which is conservative). On §3.3.7 with output noise σ = 0.5 (8 held-out samples,
measured under load) the mean IAE of ẑ − z was 4.07 for the region-only design, 3.27 for H∞,
2.09 after tuning and 1.48 for H2 (an order-4 observer; the others have order 2); the mean peak
errors did not improve ([result](results/hinf_vs_region_h2_tuned_latest.json)).

**Well-centred designs and tuning on a model not from the thesis.** The LMI solver returns a
point on the edge of the feasible set: the error poles sit near the region's boundary.
`objective="centre"` returns instead the largest concentric tightening of a bounded region
that the region LMI still meets (bisection; verified against the requested region). On a
two-stage LC filter written as a user would (index 1, n = 6, z = the unmeasured output
inductor current; `benchmarks/lc_filter.py`; 32 training and 128 held-out samples of another
seed, measured under load, [result](results/tuning_circuit_latest.json)): the centred
design's held-out mean IAE is 28.3 % below the plain LMI design's; gradient tuning from it
(100 Adam steps, every iterate verified, 7 of 97 parameters live) lowers it by a further
21.9 % (−44 % against the plain LMI design). **The target of 25 % below the centred design is
not met, and the measurements say the region is what limits it:** fitting the 128 held-out
samples themselves (L-BFGS-B with JAX gradients, every optimum certified; local searches, so
these are measurements, not bounds, and optimistic ones: the samples are then in-sample)
reaches at best −24.8 % in the requested Disk(−3, 2) from 17 starts (the centred design, the
min-gain, H2 and H∞ designs, 12 random perturbations of the centred one; then the barrier lowered
to 1e-5), with all six poles at −4.4 … −4.9, against the disk's fast edge (−25.2 % at q0 = 5;
`--diagnose-multistart`, the result's `"multistart"`); in larger disks −23.7 % in Disk(−6, 5.9)
and −25.8 % in Disk(−30, 29.9) (from the centred design only), with poles at −28.5 and
−0.41 ± 2.01i, outside Disk(−3, 2) on both sides. What the 32 training samples allow is less:
their own local optimum is −22.1 % held-out, which `tune` reaches (−21.9 %). And at q0 = 5 the
best LMI design is no longer the centred one: the H∞ design on the initial-state channels is
17 % below it (0.5645 against 0.681), and the best observer the in-sample search found at that
order is only 9.8 % below that H∞ design (the training samples' optimum 5.4 %).
`tune` with `barrier=0` used to stop at the region's boundary (79 of 100 steps rejected, −15.2 %): when no halving of an update is admissible the step now
tries it without its outward component and slides along the boundary (0 rejected, −21.6 %;
`tests/test_tuning.py`). At equal wall-clock (3.9 s, the gradient run's time in this run; 129 s in
an earlier run under heavy load, with the same outcome), Powell and Nelder–Mead on the same
parameters, every candidate verified as `tune` does, end 21.9 % and 20.7 % above the tuned
design ([result](results/tuning_circuit_latest.json); the `"diagnosis"` there was
measured with the earlier default R, whose row space is the same on this model).

A second model, also not from the thesis, with the LC filter's settings fixed before its first
run (`fojax.models.flexible_drive`: a DC motor driving two inertias through a gear and two
flexible shafts, index 1, n = 8, z = the unmeasured output-shaft torque, output-shaft
stiffness ±50 %; `python benchmarks/tuning_circuit.py --model flexible_drive`,
[result](results/tuning_flexible_drive_latest.json)): tuning lowers the
held-out mean IAE by **11.2 %** against the centred design (5 of 113 parameters live; the
centred design is itself 53 % below the plain LMI design) — the 25 % target is missed here
too; at equal wall-clock it beats Powell and Nelder–Mead by 11.2 % and 10.1 % (target 10 %:
met), and the twin rescaled by 1e-3…1e3 tunes to within +0.3 % (target 5 %: met). (With the
earlier, rounding-dependent default R — see below — the same run gave −13.4 %, 6 live; the
follow-ups measured then: L-BFGS-B on the same training problem stopped at Adam's training
loss, and fitting the held-out samples themselves reached −19.2 % in Disk(−3, 2) and passed
−25 % only in Disk(−30, 29.9) or at q0 = 5: as on the filter, the region limits the gain;
local searches, so measurements, not bounds. With the canonical R, from 17 starts in
Disk(−3, 2): −20.7 % in-sample, −15.3 % for the training samples' own optimum; the result's
`"multistart"`.)
Building it found three defects, now fixed with regression tests: rank decisions of the
structure checks taken on the raw data (the rescaled twin could not be designed: rank Γ decided
7, exactly 8 — they are now taken in the unit-free frame), the H2/H∞ tuning terms of a
`balance=True` design using the user's `Bw` in the wrong units, and the centred design's
bisection accepting a step on solver status alone (a step now counts only if its float64
eigenvalues lie in the tightened region).

A third model, chosen because a physical parameter's uncertainty should matter to the
estimate (`fojax.models.two_area_power`: two-area load-frequency control with the network's
power balance as algebraic rows, index 1, n = 10, z = area 1's unmeasured mechanical power,
area 1's inverse inertia ±40 %; the derivation, the a-priori argument and the settings were
committed before the first tuning run; `python benchmarks/tuning_circuit.py --model
two_area_power`, [result](results/tuning_two_area_power_latest.json)). Tuning lowers
the held-out mean IAE by 94.2 % against the centred design (0.1269 → 0.0073; 10 of 251
parameters live; 100 steps, none rejected, every iterate verified) and by 90.9 % against the
plain LMI design with `balance=True` (0.0799); Powell and Nelder–Mead at equal wall-clock (4 s,
251 parameters) find no better point; the rescaled twin tunes to within −0.6 % with the default
`precondition="live"` (its `"whiten"` run reaches 0.0072 while the plain model's stalls at
0.0094: −23 %). **That −94 % does not show what tuning adds, and the 25 % target is not met on
this model either.** The centred design is a poor start here: every error eigenvalue assignable,
the bisection reaches the largest tightening (99 %) and puts all ten at the disk's centre with
gains up to 1.7e6. Against every LMI design `design_functional_observer` offers in the same disk
at the same order (`python benchmarks/tuning_circuit.py --model two_area_power --lmi-baselines`,
the result's `"lmi_baselines"`): min-gain 0.0799 (`balance=True`) / 0.0105 (default), centred
0.1269 / 0.1180, H2 with the initial-state channels B_w = E·diag(x0 bounds) 0.0260, H∞ with
them 0.0174, and **H∞ with the initial-state and the uncertainty channels
(`hinf_uncertainty_channel`) 0.00750** — 2.7 % above the design tuned from the centred one;
tuning from that H∞ design lowers it by a further 10.6 % (0.00671). Against that design, the
in-sample search (17 starts, every one ending at 0.0055) gives −26.8 %, but the training
samples' own optimum from it only −14.1 % held-out: the 128 held-out samples hold 8 draws of
δ, so the in-sample figure is optimistic (`"multistart"`). On the filter and the drive
the centred design is the best LMI design of the same list (filter: H2/H∞ 0.85–1.17 vs 0.681;
drive: H2/H∞ 3.52, equal to the min-gain design, vs 1.641), so their −21.9 % and −13.3 % (tuning
from the best start, the drive's default-balance centred design) stand. What tuning reshapes on
the power model is the initial-error transient that reaches ẑ (with δ = 0 the centred design's
IAE is 0.108, the tuned one's 0.0069; δ causes 15 % of the centred design's IAE, 28 % on the
filter, 24 % on the drive; `"delta_share"` in each result), and an H∞ design with the right
channels already captures most of it.

**Default R is reproducible.** The default observer order's R takes rows from blocks of Γ's
row space; those bases were the SVD's, whose rotation inside a block of equal singular values
is decided by rounding, so R — and the default design — could change with the BLAS kernel or a
power-of-two rescaling of the model wherever R takes part of a block (the flexible drive at
q0 = 2: R's row space moved by 0.30–0.38 under rotations of the SVD basis). The bases are now
canonical (`fojax._linalg.canonical_row_space`: pivots chosen from the Gram matrix, invariant
under any rotation of the basis; ≤ 1.4e-14 under the same rotations; `tests/test_default_R.py`).
The thesis examples are unchanged (their default R is L itself).

**Designs that do not depend on units.** `design_functional_observer(..., balance=True)`
designs on the model rescaled by `fojax.analysis.unit_scaling` (Ward's least squares without
rounding, both gauges fixed by unit-free statements) and maps the observer back exactly; it is
verified on the model as given and in the unit-free frame. The LC filter and its twin with
rows and states rescaled by 1e-3…1e3 then give the same observer at the default order
(eigenvalues, frequency response and region margin to about 1e-14; at q0 = 3 the region LMI's
solution is not unique and solver round-off can move it — poles 3.6e-2 apart under another
BLAS kernel, both designs verified) and tune to the same held-out IAE (+1.4e-9
relative; before, +6.2 %; [result](results/tuning_circuit_latest.json)). The number
of live parameters is now the rank of the observer's input–output map (channel-weighted, so
unit-free): 1 of 20 for the proportional design, 13 of 97 at q0 = 3, equal on model and twin.
*A defect this found:* on the twin, the design made on the raw data at the default order
passed the relative residual test at 8e-10 (its terms are ~1e6) while its transfer function
misses z by 1.87. Every design on the data as given is now also verified in the unit-free frame
(models with l + n ≤ 200), where that observer's residual is 2.5e-3: with `balance=False` it is
refused with `DesignVerificationError`, and by default (`balance=None`) fojax designs on the
unit-free model instead and says so in the report (as it does after any other failed float64
verification of the design on the data as given: the two-area power model's H2 design, whose
SCS solution on the raw data missed the strict region LMI by 1.3e-8).
The unknown-input observer (§3.2) had the same gap and was not covered: on the §4.1.3
unknown-input example with rows and states rescaled by 1e-6…1e6 it returned an observer whose
conditions a.–f. held to 2e-19 relative on the data as given and failed by 0.14 in the
unit-free frame — run against the unscaled plant (SciPy), its estimate of the constant unknown
input d = 0.7 settled at 0.356. `design_unknown_input_observer` now checks each of a.–f.
relative to its own terms and in the unit-free frame, and has the same `balance` option
(also `balance = true` in a model file); by default it falls back to the unit-free design,
whose error obeys σ(t) = e^{𝔸t}σ(0) against the unscaled plant to 1e-7 and whose d̂ reaches
0.7 (`tests/test_unknown_input.py`). `balance` also applies to `objective="hinf"`/`"h2"` now (it was
ignored there, and the LC filter's twin at the default order was refused by the unit-free check
with a message pointing to `balance=True`): with the same physical disturbance, model and twin
get the same certified bound to 1e-8 (`tests/test_unit_invariance.py`).

**Large models.** `design_functional_observer(..., method="riccati")` (or `"auto"`) maps a
disk (or a disk inside a half-plane or sector) onto the unit disk and solves a discrete
Riccati equation for the gain and a Stein equation for the certificate — no SDP — and the
result goes through the same float64 verification. Measured on this tree on a 2-core
machine under load (load average 4–6): verified generalized designs at n = 100 in 0.53 s and
n = 500 in 18 s (proportional: 0.53 s and 19 s); the LMI route takes 13 s at n = 32 and 149 s
at n = 50 ([result](results/design_scaling_latest.json)). With Q = R = I its
generalized observer decouples (J = 0, S = 0): use the LMI route or `tune` for coupled
designs, which is why `"lmi"` stays the default. `scipy.sparse` matrices are accepted
(densified at the boundary; beyond 2^27 entries they are refused with the size it would take).

**Several processes and hosts.** `fojax study --distributed [--resume FOLDER]` (JAX's
`jax.distributed`: `JAX_COORDINATOR_ADDRESS`, `JAX_NUM_PROCESSES`, `JAX_PROCESS_ID`, detected on
SLURM) and, in Python, `run_study(..., devices=jax.devices())` and `tune(..., devices=jax.devices())`
split the samples over every process's devices. Tested on the CPU of one machine, with 2
processes × 2 devices and 3 processes × 1 device: studies (exact and exponential engines,
uneven splits), tuning iterates and the tuning checkpoint equal one process bit for bit; a
distributed `fojax study` stopped after its first tuning step and resumed on 2 processes
gives the uninterrupted one-process folder bit for bit. Only process 0 writes; on resume it
sends what it read to the others (no shared file system needed). A killed process ends the
others with `fojax.errors.DistributedError` (or JAX's heartbeat message, when JAX notices first).
Nothing has been run on a GPU or on more than one host, and no multi-process speed has been
measured; [docs/distributed.md](../docs/distributed.md) has a SLURM script and a single-host
multi-GPU example.

### Figure 3.6 of the thesis (robot arm)

| thesis result | fojax | where |
|---|---|---|
| Figure 3.6 (T-S generalized vs proportional on the robot arm) | *not confirmed*, also with tuned designs: on 64 held-out robot-arm samples (±20 % on k, m, J_l), each observer tuned the same way (30 Adam steps on 16 training samples), the tuned proportional T-S observer of the same order (q0 = 4) and region has a lower mean IAE of [x2, x4] than the tuned generalized one (0.938 vs 1.187; paired difference +0.248 ± 0.040, generalized better on 14 of 64 samples). The generalized observer wins only against a lower-order (q0 = 2) proportional one (1.187 vs 2.005). One tuning budget and learning rate, local descent from the LMI designs; measured on a loaded machine | `benchmarks/ts_generalized_vs_proportional.py`, [result](results/ts_generalized_vs_proportional_latest.json) |

### Many studies in one process

Each study structure compiles once and stays compiled. A script or notebook that runs
hundreds of *different* structures (sizes, observer sets, solvers) in one process keeps
every executable in memory; call `jax.clear_caches()` between groups of studies (the test
suite does so after every module; without it one process exceeded Linux's default
`vm.max_map_count` of 65,530 memory mappings and crashed in the compiler).

Tuning compiles its step once per optimizer. An optax transformation is a pair of closures,
which JAX can only tell apart by identity, with its hyperparameters as constants inside:
`optax.adam(0.1)` written in two `tune` calls compiles the step twice, and `optax.adam(0.05)`
a third time (10–13 s each on the default §3.3.7 study, `benchmarks/tuning_step.py`). Ask
`fojax.tuning.shared_optimizer("adam", learning_rate=0.1)` instead (`tune`'s default is
`shared_optimizer("adam", learning_rate=1e-2)`): it hands the step its float hyperparameters as
data, so a learning-rate sweep compiles once, with the same iterates bit for bit as optax's own
object (`tests/test_tuning.py`).

### LMI solvers

LMIs are solved by cvxpy on the host, outside `jit`. `solver="auto"` (default) uses Clarabel
and falls back to SCS when Clarabel's status is not `optimal`; both come with cvxpy. Only
`optimal` is accepted. (On the thesis's example 4.1.3 SCS alone stopped at
`optimal_inaccurate` after 100,000 iterations while Clarabel reached `optimal` in 19.)
After `optimal_inaccurate` each solver is retried once with looser settings (Clarabel at its
default tolerances 1e-8 instead of 1e-9, SCS with more iterations) before the minimum-gain
problem falls back to the plain feasibility problem: whether a solver meets the tighter
tolerance can depend on the last digits of the BLAS kernel. Whatever route produced a design,
it passed the same float64 verification; `design.solver` records the settings and the refused
attempts, and the reports of functional, PI, T-S and finite-time designs print the route
(`LMI route: ...`).
"""


if __name__ == "__main__":
    sys.exit(main())
