"""Small helpers shared by the scaling benchmarks (`scaling.py`, `design_scaling.py`,
`tuning_scaling.py`) and `make_readme.py`.

Scripts call `limit_blas_threads` **before importing NumPy**: like `reference_workload.py`
it sets ``OPENBLAS_NUM_THREADS``/``MKL_NUM_THREADS`` to 1 unless the caller set them (the
NumPy/SciPy peers' small BLAS calls are faster single-threaded on the 2-core reference
machine; XLA uses its own thread pool).

Scripts also call `prefer_checkout`, which puts the repository root on ``sys.path``
(right after ``benchmarks/``), so they measure the fojax of this checkout even when a
non-editable copy is installed in site-packages (``machine_info`` records which
``fojax`` was imported). Importing this module changes nothing.

Contents: the machine/versions/date record (`machine_info`, same fields as
`reference_workload.machine_info` plus the cvxpy/solver/optax versions), the peak resident
set size (`peak_rss_mib`), a repetition timer (`time_repeated`), result files
(`write_results`: ``<name>_<stamp>.{md,json}`` and ``<name>_latest.{md,json}``) and
`run_worker`, which runs one benchmark entry in a fresh Python process (cold JAX caches,
a clean peak-RSS high-water mark, a hard timeout) and returns the JSON the entry printed.
`reference_workload.py` keeps its own copies of the first helpers (unchanged).
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import resource
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
    try:
        import importlib.metadata

        return importlib.metadata.version(mod)
    except Exception:  # noqa: BLE001
        return "not installed"


def utc_now() -> str:
    return datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")


def load_average():
    return list(os.getloadavg()) if hasattr(os, "getloadavg") else None


def machine_info() -> dict:
    """Machine, library versions, git commit, date (UTC) and the load average now."""
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
        "versions": {m: _version(m) for m in VERSION_MODULES},
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


def time_repeated(call, repeats: int, budget: float, after_first=None):
    """First call, then up to `repeats` timed calls, stopping once `budget` s are spent
    (at least one repetition); `after_first()` runs untimed in between. Returns
    ``(result_of_first_call, first_s, [rep_s, ...])``."""
    t0 = time.perf_counter()
    out = call()
    first = time.perf_counter() - t0
    if after_first is not None:
        after_first()
    times: list[float] = []
    spent = 0.0
    while len(times) < max(1, repeats) and (not times or spent < budget):
        t0 = time.perf_counter()
        call()
        times.append(time.perf_counter() - t0)
        spent += times[-1]
    return out, first, times


def rel_diff(m, ref) -> float:
    import numpy as np

    m, ref = np.asarray(m, dtype=float), np.asarray(ref, dtype=float)
    return float(np.max(np.abs(m - ref) / np.abs(ref)))


def stamp_of(date: str) -> str:
    return date.replace(":", "").replace("-", "")[:15]  # as reference_workload.py


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
