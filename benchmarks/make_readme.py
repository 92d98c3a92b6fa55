"""Write the benchmark tables from the shipped result files (issues 7 and 17).

Every ``benchmarks/results/<name>_latest.json`` present (these files are tracked in git;
the dated ones are not) is rendered as Markdown tables by the renderer registered for
``<name>`` in `RENDER` (reference workload, time-varying study, scaling, design scaling,
tuning scaling); a ``*_latest.json`` without a renderer is shown as a generic table of its
``rows`` when it has them, else listed with a note. Renderers with no shipped file are
listed as "no shipped result yet". The tables replace the text between
``<!-- benchmarks:start -->`` and ``<!-- benchmarks:end -->`` of ``benchmarks/README.md``;
the same markers in the top-level ``README.md`` get a short list of the shipped result
files with a link to the tables. Nothing else in either file changes.

Every number is copied from a JSON file; each table names its file, the date and the
machine it was measured on. Nothing is typed by hand; a file whose JSON has unexpected
keys is skipped with a note.

    python benchmarks/make_readme.py                 # update benchmarks/README.md and README.md
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
    fojax = {r["B"]: r for r in rows if r["method"] == "fojax"}
    peers = [p for p in PEER_SHORT if any(r["method"] == p for r in rows)]
    peers += sorted({r["method"] for r in rows} - set(PEER_SHORT) - {"fojax"})
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
            sp = None if r is None else r.get("fojax_speedup")
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
                  for r in rows if r["B"] == Bmin and r["method"] != "fojax" and r.get("first_s") is not None]
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


# The renderer of each benchmark, by the <name> of its results/<name>_latest.json.
RENDER = {"reference_workload": reference_workload, "time_varying": time_varying, "scaling": scaling,
          "design_scaling": design_scaling, "tuning_scaling": tuning_scaling,
          "study_time_varying": study_time_varying}
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


def render_summary(results: Path) -> str:
    """The short section of the top-level README: which result files are shipped, with links."""
    names = shipped(results)
    if not names:
        return ("No benchmark result files are shipped in this version yet; run the scripts to "
                "measure on your machine (see [benchmarks/README.md](benchmarks/README.md)).\n")
    lines = ["Shipped results (tables in [benchmarks/README.md](benchmarks/README.md#results)):", ""]
    for name in names:
        d, err = load(results, name)
        m = (d or {}).get("machine", {}) or {} if isinstance(d, dict) else {}
        when = (" (unreadable)" if not d else f", measured {m['date']} on {m.get('cpu', '?')}" if m.get("date")
                else " (no date or machine recorded in the file)")
        lines.append(f"- [`{name}`](benchmarks/results/{name}_latest.json){when}")
    return "\n".join(lines) + "\n"


def update_readme(readme: Path, section: str) -> None:
    text = readme.read_text()
    # the markers on lines of their own (a sentence may quote them)
    m_start = re.search(rf"^{re.escape(START)}$", text, flags=re.M)
    m_end = re.search(rf"^{re.escape(END)}$", text, flags=re.M)
    i, j = (m_start.start() if m_start else -1), (m_end.start() if m_end else -1)
    if i < 0 or j < i:
        raise SystemExit(f"{readme}: markers {START} ... {END} not found; add them to the Benchmarks section.")
    readme.write_text(text[: i + len(START)] + "\n" + section + text[j:])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--results", type=Path, default=HERE / "results", help="folder of the *_latest.json files")
    ap.add_argument("--tables", type=Path, default=HERE / "README.md", help="file that gets the tables")
    ap.add_argument("--readme", type=Path, default=HERE.parent / "README.md",
                    help="file that gets the list of shipped results")
    ap.add_argument("--stdout", action="store_true", help="print the tables instead of writing the files")
    args = ap.parse_args(argv)
    section = render(args.results)
    if args.stdout:
        print(section)
    else:
        update_readme(args.tables, section)
        update_readme(args.readme, render_summary(args.results))
        print(f"updated the benchmark sections of {args.tables} and {args.readme}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
