"""Small helpers shared by the benchmark scripts (`reference_workload.py`, `time_varying.py`,
`scaling.py`, `design_scaling.py`, `tuning_scaling.py`) and `make_readme.py`.

Scripts call `limit_blas_threads` **before importing NumPy**: it sets
``OPENBLAS_NUM_THREADS``/``MKL_NUM_THREADS`` to 1 unless the caller set them (the
NumPy/SciPy peers' small BLAS calls are faster single-threaded on the 2-core reference
machine; XLA uses its own thread pool). The two studies with JAX in the main process also
call `force_host_devices` (one JAX host device per core, read from ``--host-devices``)
before importing JAX.

Scripts also call `prefer_checkout` before the first ``import fojax``: it puts the
repository root on ``sys.path`` (right after ``benchmarks/``), so they measure the fojax of
this checkout even when a non-editable copy is installed in site-packages
(``machine_info`` records which ``fojax`` was imported). Importing this module changes
nothing.

Contents: the machine/versions/date record (`machine_info`), the peak resident set size
(`peak_rss_mib`), a repetition timer (`time_repeated`), one call's wall and CPU time
(`clock`) and a public `fojax.tune` step (`time_tune_steps`), the harness that times the peers of
the two studies (`time_peer`, `print_timing`, `add_speedups`, `speedup_table`), result files
(`result_payload`: the fields every JSON starts with; `write_results`:
``<name>_<stamp>.{md,json}`` and ``<name>_latest.{md,json}``) and `run_worker`, which runs
one benchmark entry in a fresh Python process (cold JAX caches, a clean peak-RSS high-water
mark, a hard timeout) and returns the JSON the entry printed.
"""

from __future__ import annotations

import contextlib
import datetime
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path


HERE = Path(__file__).resolve().parent
REPO = HERE.parent
RESULTS = HERE / "results"


def prefer_checkout() -> None:
    """Import fojax from this checkout (call before the first ``import fojax``)."""
    if str(REPO) not in sys.path:
        sys.path.insert(1 if sys.path and Path(sys.path[0]).resolve() == HERE else 0, str(REPO))


BLAS_VARS = ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def host_devices_from_argv() -> int:
    """``--host-devices N`` (default: the usable cores), read before JAX is imported."""
    argv = sys.argv[1:]
    for i, a in enumerate(argv):
        if a.startswith("--host-devices="):
            return int(a.split("=", 1)[1])
        if a == "--host-devices" and i + 1 < len(argv):
            return int(argv[i + 1])
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def force_host_devices() -> int:
    """One JAX host device per core (fojax shards its batches over all devices with
    `jax.shard_map`; XLA exposes one CPU device unless told otherwise). Call before JAX is
    imported; returns the count (``--host-devices 1``: fojax on one core)."""
    n = host_devices_from_argv()
    if "xla_force_host_platform_device_count" not in os.environ.get("XLA_FLAGS", ""):
        os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") +
                                   f" --xla_force_host_platform_device_count={n}").strip()
    return n


def program_compile_flags() -> bool:
    """XLA's compile flags as the ``fojax`` program sets them before JAX starts
    (``configure_compiler`` of fojax/cli/_devices.py, loaded from its file: importing the
    fojax package would import JAX). Call before JAX is imported; returns whether a flag was added."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("_fojax_cli_devices", REPO / "fojax" / "cli" / "_devices.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.configure_compiler()


def limit_blas_threads() -> dict:
    """Single-threaded BLAS unless the caller set the variables (call before NumPy)."""
    return {v: os.environ.setdefault(v, "1") for v in BLAS_VARS}

#: Marker in front of the JSON line a worker prints on stdout.
WORKER_MARK = "@@FOJAX-BENCH-RESULT@@ "

VERSION_MODULES = (
    "numpy",
    "scipy",
    "jax",
    "jaxlib",
    "equinox",
    "diffrax",
    "optax",
    "cvxpy",
    "clarabel",
    "scs",
    "control",
    "fojax",
)


def _version(mod: str) -> str:
    """The version of the module as imported (``__version__`` when it is imported already:
    for fojax, the copy being measured), else of its installed distribution."""
    v = getattr(sys.modules.get(mod), "__version__", None)
    if isinstance(v, str):
        return v
    try:
        import importlib.metadata

        return importlib.metadata.version(mod)
    except Exception:  # noqa: BLE001
        return "not installed"


def utc_now() -> str:
    return datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")


def load_average():
    return list(os.getloadavg()) if hasattr(os, "getloadavg") else None


def machine_info(modules=VERSION_MODULES) -> dict:
    """Machine, versions of `modules`, git commit, date (UTC) and the load average now."""
    cpu = platform.processor() or ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    mem = None
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal"):
                mem = f"{int(line.split()[1]) / 2**20:.1f} GiB"
    except OSError:
        pass
    try:
        commit = subprocess.run(
            ["git", "-C", str(HERE), "rev-parse", "--short", "HEAD"],
            capture_output=True,
            text=True,
            check=False,
        ).stdout.strip()
    except OSError:
        commit = ""
    try:
        import jax

        backend, devices = jax.default_backend(), jax.device_count()
    except Exception:  # noqa: BLE001
        backend, devices = None, None
    try:
        import fojax

        fojax_path = str(Path(fojax.__file__).resolve().parent)
    except Exception:  # noqa: BLE001
        fojax_path = None
    return {
        "date": utc_now(),
        "cpu": cpu,
        "logical_cores": os.cpu_count(),
        "cores_available": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
        "memory": mem,
        "platform": platform.platform(),
        "python": platform.python_version(),
        "jax_backend": backend,
        "jax_devices": devices,
        "dtype": "float64",
        "blas_threads": {v: os.environ.get(v) for v in BLAS_VARS},
        "versions": {m: _version(m) for m in modules},
        "git_commit": commit,
        "fojax_imported_from": fojax_path,
        "load_average_at_start": load_average(),
    }


def peak_rss_mib() -> float:
    """Peak resident set size of this process (``getrusage`` high-water mark), MiB."""
    kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux
    return kib / 1024.0


def current_rss_mib() -> float | None:
    """Current resident set size (``VmRSS`` of /proc/self/status), MiB; None elsewhere."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return None


def reset_peak_rss() -> bool:
    """Reset the high-water mark to the current RSS (Linux ``clear_refs`` 5; it also resets
    ``getrusage``'s ``ru_maxrss``). Returns whether it worked."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return True
    except OSError:
        return False


def time_repeated(call, repeats: int, budget: float, after_first=None, first_counts: bool = False):
    """First call, then up to `repeats` timed calls, stopping once `budget` s are spent
    (at least one repetition); `after_first()` runs untimed in between. With `first_counts`
    (calls that compile nothing: the NumPy/SciPy peers of `reference_workload.py`) a first
    call longer than `budget` is the single measurement, no repetition. Returns
    ``(result_of_first_call, first_s, [rep_s, ...])``."""
    t0 = time.perf_counter()
    out = call()
    first = time.perf_counter() - t0
    if after_first is not None:
        after_first()
    if first_counts and first > budget:
        return out, first, [first]
    times: list[float] = []
    spent = 0.0
    while len(times) < max(1, repeats) and (not times or spent < budget):
        t0 = time.perf_counter()
        call()
        times.append(time.perf_counter() - t0)
        spent += times[-1]
    return out, first, times


def clock(f):
    """``(output, wall s, process CPU s)`` of one call ``f()``, waiting for JAX's
    asynchronous results when JAX is loaded (this module does not import it)."""
    w, c = time.perf_counter(), time.process_time()
    out = f()
    jax = sys.modules.get("jax")
    if jax is not None:
        jax.block_until_ready(out)
    return out, time.perf_counter() - w, time.process_time() - c


def time_tune_steps(run, k: int) -> tuple[dict, object, object]:
    """One public `fojax.tune` step, timed from whole calls: ``run(steps)`` runs
    ``fojax.tune(..., steps=steps)``. A cold 1-step call (compilation included), a warm
    1-step call, a warm ``1 + k``-step call; the step is the difference over ``k``, and the
    tuning step's trace count tells whether a warm call compiled again. Returns ``(row,
    cold result, last result)``."""
    import fojax.tuning._tune as tune_module

    with compile_events() as events:
        r0, t_cold, c_cold = clock(lambda: run(1))
    before = tune_module.TRACE_COUNTS["tune_step"]
    _, t1, c1 = clock(lambda: run(1))
    res, tk, ck = clock(lambda: run(1 + k))
    row = dict(
        tune_step_s=(tk - t1) / k, tune_step_cpu_s=(ck - c1) / k, tune_first_call_s=t_cold,
        tune_first_call_cpu_s=c_cold, tune_compile_estimate_s=t_cold - t1, tune_warm_call_steps1_s=t1,
        tune_warm_call_steps1_cpu_s=c1, tune_retraced_on_warm_calls=tune_module.TRACE_COUNTS["tune_step"] - before,
        train_loss=[float(x) for x in res.history["train_loss"]], accepted=[bool(a) for a in res.history["accepted"]],
        tune_step_program_compile_s=program_compile(events, "_step"),
        tune_first_call_compile_events_s=program_compile(events),
    )
    return row, r0, res


_COMPILE_EVENTS = {"/jax/core/compile/jaxpr_trace_duration": "trace",
                   "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower",
                   "/jax/core/compile/backend_compile_duration": "xla"}


@contextlib.contextmanager
def compile_events():
    """The JAX compile events of the block, as a list of ``(stage, function name, seconds)``
    (``jax.monitoring``: tracing, lowering to MLIR, XLA compilation; recorded by whatever
    thread runs them, so a program `tune` compiles on a thread is included)."""
    import jax.monitoring

    events, on = [], [True]

    def listen(event, duration, **kw):
        if on[0] and event in _COMPILE_EVENTS:
            events.append((_COMPILE_EVENTS[event], kw.get("fun_name"), float(duration)))

    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        yield events
    finally:
        on[0] = False  # (JAX has no public way to remove a listener)


def program_compile(events, name: str | None = None) -> dict:
    """Seconds per stage of the program `name`'s compile events and their total; with
    ``None``, the lowering and XLA seconds of every program and their number (not the
    tracing: a program traced inside another is counted in the outer one's trace too)."""
    stages = ("trace", "lower", "xla") if name is not None else ("lower", "xla")
    names = (name, f"jit({name})")  # (JAX names the trace by the function, the rest by its jit)
    out = {stage: sum(sec for st, fun, sec in events if st == stage and (name is None or fun in names))
           for stage in stages}
    out["total"] = sum(out.values())
    if name is None:
        out["programs"] = sum(1 for st, _, _ in events if st == "xla")
    return out


# ------------------------------------------------- the peers' harness of the two studies
def print_timing(label: str, tag: str, first: float, times, width: int) -> float:
    """Print one timed entry (``label [tag] first … median … (n reps)``); returns the median."""
    med = statistics.median(times)
    print(f"  {label:{width}s} [{tag}] first {first:9.3f} s  median {med:9.3f} s  ({len(times)} reps)")
    return med


def time_peer(rows, name: str, label: str, variants: dict, run, B: int, args, best_variant: dict, *,
              loop_peer: bool, width: int, first_counts: bool = False):
    """One peer at batch size `B` (`reference_workload.py`, `time_varying.py`): ``(row, out)``.

    A Python-loop peer (`loop_peer`) is not run above ``args.loop_max_b``: its time is
    extrapolated linearly from its largest measured B in `rows` (``(None, None)`` if there is
    none) and the row is marked ``extrapolated``. Otherwise every variant (axis order) is
    timed with `time_repeated` (``args.repeats``, ``args.budget``, `first_counts`) — above
    ``args.variant_max_b`` only the one that was fastest at the largest B up to it, kept in
    `best_variant` — and the fastest is reported; `out` is its result. ``run(fn)`` calls one
    variant on the workload. The caller appends the row.
    """
    if loop_peer and B > args.loop_max_b:
        base = [r for r in rows if r["method"] == name and not r["extrapolated"]]
        if not base:
            return None, None
        b0 = base[-1]
        t = b0["median_s"] * B / b0["B"]
        print(f"  {label:{width}s} {t:10.3f} s  (EXTRAPOLATED from B = {b0['B']})")
        row = dict(method=name, label=label, variant=b0["variant"], B=B, first_s=None, median_s=t, reps=0,
                   all_s=[], extrapolated=True, extrapolated_from_B=b0["B"])
        return row, None
    if B > args.variant_max_b and name in best_variant:
        vitems = [(best_variant[name], variants[best_variant[name]])]
    else:
        vitems = list(variants.items())
    cand = []
    for vname, fn in vitems:
        out, first, times = time_repeated(lambda fn=fn: run(fn), args.repeats, args.budget,
                                          first_counts=first_counts)
        med = print_timing(label, f"{vname:11s}", first, times, width)
        cand.append((med, vname, first, times, out))
    med, vname, first, times, out = min(cand, key=lambda c: c[0])
    if B <= args.variant_max_b and len(variants) > 1:
        best_variant[name] = vname
    row = dict(method=name, label=label, variant=vname, B=B, first_s=first, median_s=med, reps=len(times),
               all_s=times, extrapolated=False, all_variants={c[1]: c[0] for c in cand})
    return row, out


def add_speedups(rows, fojax_methods: dict | None = None) -> None:
    """For every peer row and each fojax method measured at the same B (`fojax_methods`:
    method -> suffix, default ``{"fojax": ""}``): ``t_fojax_over_t_peer<suffix>`` and
    ``fojax_speedup<suffix>`` (= t_peer / t_fojax)."""
    fojax_methods = {"fojax": ""} if fojax_methods is None else fojax_methods
    for r in rows:
        if r["method"] in fojax_methods:
            continue
        for fm, suffix in fojax_methods.items():
            f = [x for x in rows if x["method"] == fm and x["B"] == r["B"]]
            if f:
                r["t_fojax_over_t_peer" + suffix] = f[0]["median_s"] / r["median_s"]
                r["fojax_speedup" + suffix] = r["median_s"] / f[0]["median_s"]


def speedup_table(rows, cols) -> list[str]:
    """Markdown section "fojax speed-up by B", one column per ``(peer, suffix, header)``."""
    lines = [
        "",
        "## fojax speed-up (t_peer / t_fojax) by B",
        "",
        "| B | " + " | ".join(h for _, _, h in cols) + " |",
        "|---:|" + "---:|" * len(cols),
    ]
    for B in sorted({r["B"] for r in rows}):
        cells = []
        for p, sfx, _ in cols:
            r = [x for x in rows if x["method"] == p and x["B"] == B]
            if r and ("fojax_speedup" + sfx) in r[0]:
                cells.append(f"{r[0]['fojax_speedup' + sfx]:.3g}" + (" *extrap.*" if r[0]["extrapolated"] else ""))
            else:
                cells.append("—")
        lines.append(f"| {B} | " + " | ".join(cells) + " |")
    return lines


def rel_diff(m, ref) -> float:
    import numpy as np

    m, ref = np.asarray(m, dtype=float), np.asarray(ref, dtype=float)
    return float(np.max(np.abs(m - ref) / np.abs(ref)))


def stamp_of(date: str) -> str:
    return date.replace(":", "").replace("-", "")[:15]


def result_payload(study: str, status: str, info: dict, args, **fields) -> dict:
    """The head of every result JSON: ``study``, ``status``, ``machine`` (`info` with
    ``load_average_at_end`` = now), ``settings`` (the command line; ``--worker`` left out,
    paths as strings), then `fields` in order."""
    settings = {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items() if k != "worker"}
    machine = dict(info, load_average_at_end=load_average())
    return dict(study=study, status=status, machine=machine, settings=settings, **fields)


def write_results(out: Path, name: str, payload: dict, md: str, echo: bool = False) -> Path:
    """``<name>_<stamp>.{md,json}`` and ``<name>_latest.{md,json}`` in `out`."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    stamp = stamp_of(payload["machine"]["date"])
    text = json.dumps(payload, indent=2, default=_json_default)
    for base in (f"{name}_{stamp}", f"{name}_latest"):
        (out / f"{base}.md").write_text(md)
        (out / f"{base}.json").write_text(text)
    if echo:
        print("\n" + md)
        print(f"written to {out}/{name}_{stamp}.{{md,json}} (and {name}_latest)")
    return out / f"{name}_{stamp}.json"


def _json_default(x):
    try:
        return float(x)
    except (TypeError, ValueError):
        return str(x)


def emit_worker_result(result: dict) -> None:
    """Print the worker's result as the last line of stdout (read by `run_worker`)."""
    sys.stdout.flush()
    print(WORKER_MARK + json.dumps(result, default=_json_default), flush=True)


def served_as_worker(args, worker) -> bool:
    """With ``--worker JSON`` on the command line (a child of `run_worker`): run
    ``worker(spec)`` and print its result (`emit_worker_result`); returns whether it did."""
    if not getattr(args, "worker", None):
        return False
    emit_worker_result(worker(json.loads(args.worker)))
    return True


def run_worker(script: Path, spec: dict, timeout: float) -> dict:
    """Run ``python script --worker JSON`` in a fresh process; return the dict it emitted.

    On a timeout the child (and only it) is killed and ``{"status": "timeout", ...}`` is
    returned; a crash gives ``{"status": "crashed", "stderr": <tail>}``. The parent's own
    stdout shows the child's stderr tail on failure only.
    """
    cmd = [sys.executable, str(script), "--worker", json.dumps(spec)]
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, check=False)
    except subprocess.TimeoutExpired as e:
        return {
            "status": "timeout",
            "error": f"killed after {timeout:.0f} s (--hard-timeout)",
            "wall_s": time.perf_counter() - t0,
            "stderr": _tail(e.stderr),
        }
    for line in reversed(proc.stdout.splitlines()):
        if line.startswith(WORKER_MARK):
            res = json.loads(line[len(WORKER_MARK) :])
            res.setdefault("wall_s", time.perf_counter() - t0)
            return res
    return {
        "status": "crashed",
        "error": f"worker exited with code {proc.returncode} without a result",
        "stderr": _tail(proc.stderr),
        "wall_s": time.perf_counter() - t0,
    }


def _tail(text, n: int = 2000) -> str:
    if text is None:
        return ""
    if isinstance(text, bytes):
        text = text.decode(errors="replace")
    return text[-n:]


def fmt(x, spec: str = ".3g") -> str:
    """Table cell: ``—`` for missing values."""
    if x is None:
        return "—"
    try:
        return format(x, spec)
    except (TypeError, ValueError):
        return str(x)


def machine_lines(info: dict) -> list[str]:
    """Markdown bullet lines describing the machine record of `machine_info`."""
    v = info.get("versions", {})
    la0 = info.get("load_average_at_start") or ()
    la1 = info.get("load_average_at_end") or ()
    return [
        f"- date: {info.get('date')}; git {info.get('git_commit')}",
        f"- machine: {info.get('cpu')}, {info.get('cores_available')} cores available "
        f"({info.get('logical_cores')} logical), {info.get('memory')}; {info.get('platform')}; "
        f"load average at start {tuple(round(x, 2) for x in la0)}, at end {tuple(round(x, 2) for x in la1)}",
        f"- Python {info.get('python')}; " + ", ".join(f"{k} {val}" for k, val in v.items()),
    ]


def stop_reason(res: dict, n: int, hard_timeout: float, budget: float) -> str | None:
    """Why a size sweep stops after the entry of size `n` (killed at `hard_timeout`, or its
    ``total_s`` over `budget`), or ``None`` to go on."""
    t = res.get("total_s")
    if res.get("status") == "timeout":
        return f"killed at n = {n} after {hard_timeout:.0f} s"
    if t is not None and t > budget:
        return f"n = {n} took {t:.0f} s > budget {budget:.0f} s"
    return None


def stop_and_failure_lines(d: dict, label) -> list[str]:
    """Markdown lines closing a result table: why the run stopped (``d["stopped"]``) and a
    ``## Failures`` list with the first line of the error of every row whose status is not
    ``ok``, each row named by ``label(row)``."""
    lines = []
    if d["stopped"]:
        lines += ["", "Stopped: " + "; ".join(f"{k}: {v}" for k, v in d["stopped"].items())]
    errs = [r for r in d["rows"] if r.get("status") != "ok"]
    if errs:
        lines += ["", "## Failures", ""]
        for r in errs:
            msg = (r.get("error") or "").strip().splitlines()
            lines.append(f"- {label(r)}: {r.get('status')} — {msg[0][:300] if msg else ''}")
    return lines


def write_result(path, result: dict) -> None:
    """Write a benchmark's result JSON atomically (a temporary file, then `os.replace`)."""
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(result, indent=1))
    os.replace(tmp, out)
    print("wrote", out)
