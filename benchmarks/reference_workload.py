"""Issue 7, study 1: the reference workload (thesis §4.1.3 loop, B Monte Carlo samples).

Runs fojax and the four peers of `peers.py` on the same samples, checks that all of
them agree on the per-sample metrics, then times them and writes a table
(Markdown + JSON) to ``benchmarks/results/``.

    pip install ".[bench]"
    python benchmarks/reference_workload.py                      # the full study
    python benchmarks/reference_workload.py --sizes 1 10 100 1000 --repeats 3
    python benchmarks/reference_workload.py --peers expm rk4 --loop-max-b 100
    # issue 13: fojax.run_study on the workload's Study vs peer (d), one device
    python benchmarks/reference_workload.py --fojax-mode run-study --peers expm \
        --sizes 1000 10000 --host-devices 1

Timing rules: imports and workload construction are outside the timed region; the
first call of every method is timed and reported separately (for fojax the JAX caches
are cleared first, and compilation is estimated as first call - median; see `FojaxRunner`);
then the method is repeated and the median is reported, with
``jax.block_until_ready`` on fojax's output. The Python-loop peers (a) and (b) are run
up to ``--loop-max-b`` samples; for larger B their time is extrapolated linearly from
the per-sample time at the largest measured B and marked ``extrapolated`` everywhere.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import threading
import time
from pathlib import Path


HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import _common  # noqa: E402


# Single-threaded BLAS unless the caller says otherwise: on this 2-core machine the NumPy/SciPy
# peers' tiny 7x7 BLAS/LAPACK calls are 2-10x *faster* with one OpenBLAS thread (threads only
# contend), so this favours the peers. Must happen before NumPy is imported. XLA (fojax) uses
# its own thread pool and is not affected.
_common.limit_blas_threads()
_common.prefer_checkout()  # before the first `import fojax`: measure this checkout's fojax
# fojax spreads the samples over all JAX devices with jax.shard_map (one code path); on a CPU,
# XLA exposes one device unless told otherwise, so the benchmark asks for one host device per
# core (the standard XLA flag; must be set before JAX is imported). --host-devices 1 measures
# fojax on one core.
HOST_DEVICES = _common.force_host_devices()

import jax  # noqa: E402


jax.config.update("jax_enable_x64", True)

import _workload as wlmod  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import peers  # noqa: E402


SIZES = (1, 10, 100, 1_000, 10_000, 100_000)

#: Largest acceptable relative difference of each method's metrics to the exact peer (d).
#: solve_ivp's rtol = 1e-6 bounds its accuracy (measured ~1e-7); RK4 with dt = 1e-3 has a
#: local error ~ (39.78e-3)^5 / 120 on the fastest mode (measured ~1e-10 on the metrics);
#: python-control and fojax are exact discretisations like (d), up to rounding.
TOLERANCES = {"solve_ivp": 1e-4, "control": 1e-10, "rk4": 1e-8, "expm": 1e-12, "fojax": 1e-8,
              "fojax_run_study": 1e-8}
#: Issue 13's target for `fojax.run_study` on this workload at one device.
TARGET_VS_EXPM = 4.0  # t_expm_peer / t_run_study at least
#: The library versions recorded (and printed) for this study.
VERSION_MODULES = ("numpy", "scipy", "control", "jax", "jaxlib", "equinox", "diffrax", "fojax")


# ================================================================================ fojax
class FojaxUnavailable(RuntimeError):
    pass


def _closed_loop_jnp(A_plant):
    """The 8×8 closed-loop matrix from the printed gains, with jax.numpy (see `_workload`).

    Deliberately a jax.numpy twin of `_workload.closed_loop_A`, not a call to it: it is
    traced per sample inside the ``vmap-simulate`` entry (the NumPy version assigns in place
    and cannot be traced), and `_workload` stays NumPy only.
    """
    g = {k: jnp.asarray(getattr(wlmod, k)) for k in "B C L N J F H S G M P Q E_PERP".split()}
    # w = [-E_perp B u; y] with u = zhat = P zeta + Q w: an algebraic loop in u, but
    # E_perp B = [0, 0] for this plant (checked here and in _workload), so w = [0; C] x.
    assert not np.any(wlmod.E_PERP @ wlmod.B)
    W = jnp.concatenate([jnp.zeros((1, 4)), g["C"]], axis=0)
    BQW = g["B"] @ g["Q"] @ W
    HQW = g["H"] @ g["Q"] @ W
    Z = jnp.zeros((4, 2))
    return jnp.block(
        [
            [A_plant + BQW, g["B"] @ g["P"], Z],
            [g["F"] @ W + HQW, g["N"] + g["H"] @ g["P"], g["J"]],
            [g["M"] @ W, g["S"], g["G"]],
        ]
    )


class FojaxRunner:
    """The fojax entry: the batch's ``(B, 2)`` metrics, public API only.

    - ``mode="run-study"`` (``"auto"``): what users run, `fojax.run_study` on the workload
      as a `fojax.Study` (`_workload_study`: the loop built by `fojax.control.closed_loop`,
      no observers, ``save=fojax.Metrics(kinds="iae", bands=None)``, chunks of `chunk`; its
      exact engine: one matrix exponential per sample, all samples stepped together with
      the batch as the last axis, the metrics accumulated inside the time loop), the two
      metrics summed from its per-signal IAEs (inside the timed call). Its input is the
      `Study` of the batch (built outside the timed region). Compile time reported as
      first call − median.
    - ``mode="vmap-simulate"``: ``jax.vmap(fojax.simulate)`` on ``(A_plant (B,4,4), x0
      (B,8))`` with the metrics computed from the stored trajectories (kept for comparison).
    """

    def __init__(self, chunk: int = 4096, mode: str = "auto"):
        import fojax

        if not hasattr(fojax, "run_study"):
            raise FojaxUnavailable(
                "fojax.run_study does not exist in this checkout; this entry is written against "
                "`fojax.run_study(study) -> StudyResult` and `fojax.simulate(plant, x0, ts) -> Solution(.xs (T, n))`."
            )

        self.fojax = fojax
        self.chunk = int(chunk)
        self.requested_mode = mode
        self.mode = "run-study" if mode == "auto" else mode
        self.method = "fojax_run_study" if self.mode == "run-study" else "fojax"
        self.fallback_reason = ""
        self.E_cl = jnp.asarray(wlmod.E_CL)
        self.ts = jnp.asarray(wlmod.TS)
        self.dt = float(wlmod.DT_GRID)
        self.Ce = jnp.asarray(wlmod.full_output_rows())[4:]  # (2, 8): rows of zhat - L x
        self._metrics = jax.jit(self._metrics_from_xs)
        self._vmapped = jax.vmap(self._trajectory)

    # -- vmap of simulate, metrics from trajectories ------------------------------------
    def _trajectory(self, Ak, x0):
        plant = self.fojax.DescriptorSystem(self.E_cl, _closed_loop_jnp(Ak))
        return self.fojax.simulate(plant, x0, self.ts).xs  # (T, 8)

    def _metrics_from_xs(self, xs):  # (..., T, 8) -> (..., 2); jnp twin of _workload.metrics_from_outputs
        fx = jnp.sum(jnp.abs(xs[..., :4]), axis=-1)
        fe = jnp.sum(jnp.abs(xs @ self.Ce.T), axis=-1)
        f = jnp.stack([fx, fe], axis=-1)
        return self.dt * (jnp.sum(f, axis=-2) - 0.5 * (f[..., 0, :] + f[..., -1, :]))

    # -- public ------------------------------------------------------------------
    def inputs(self, wl: wlmod.Workload) -> tuple:
        """The call's arguments for the batch `wl` (built outside the timed region)."""
        if self.mode == "run-study":
            import _workload_study

            return (_workload_study.of_workload(wl),)
        return fojax_inputs(wl)

    def _run_study(self, study):
        import _workload_study

        res = self.fojax.run_study(study, save=self.fojax.Metrics(kinds="iae", bands=None), chunk_size=self.chunk,
                                   quiet=True)
        self.engine = res.attrs["engine"]
        return _workload_study.two_metrics(res)

    def prepare(self, A_plant, x0=None) -> float | None:
        """The compile time when it is measured on its own (never here: every mode's first
        call compiles, reported as first call − median)."""
        return None

    def __call__(self, A_plant, x0=None):
        if self.mode == "run-study":
            return self._run_study(A_plant)
        B = A_plant.shape[0]
        if B <= self.chunk:
            return self._metrics(self._vmapped(A_plant, x0))
        n_chunks = -(-B // self.chunk)
        pad = n_chunks * self.chunk - B
        if pad:
            A_plant = jnp.concatenate([A_plant, jnp.repeat(A_plant[-1:], pad, axis=0)])
            x0 = jnp.concatenate([x0, jnp.repeat(x0[-1:], pad, axis=0)])
        outs = []
        for i in range(n_chunks):
            sl = slice(i * self.chunk, (i + 1) * self.chunk)
            outs.append(self._metrics(self._vmapped(A_plant[sl], x0[sl])))
        return jnp.concatenate(outs)[:B]

    @property
    def label(self) -> str:
        if self.mode == "run-study":
            return "fojax.run_study (no observers)"
        return "fojax.simulate (vmap)"


def fojax_inputs(wl: wlmod.Workload):
    return jnp.asarray(wl.A_plant), jnp.asarray(wl.x0_cl)


def run_fojax(batch: wlmod.Workload, chunk: int = 4096, mode: str = "auto") -> np.ndarray:
    """fojax on the reference workload: ``(B, 2)`` metrics (IAE of |x|_1, of |zhat - Lx|_1).

    Uses only fojax's public API (`fojax.run_study` on the workload's `fojax.Study`, or
    `jax.vmap(fojax.simulate)`) and JAX.
    """
    runner = FojaxRunner(chunk, mode)
    return np.asarray(jax.block_until_ready(runner(*runner.inputs(batch))))


# ================================================================================ watchdog
HANG_NOTE = (
    "Known cause with jax/jaxlib 0.10.x on small CPUs: batched LAPACK kernels (LU via "
    "jnp.linalg.solve / expm under vmap) run jax::ParallelBatchMap on XLA's intra-op thread pool "
    "and block on it; when as many independent batched LAPACK calls as pool threads run at once, "
    "every pool thread waits and the program deadlocks (jaxlib >= 0.11 compiles that parallel "
    "path out). Confirm with `gdb -p <pid> -batch -ex 'thread apply all bt'` (look for "
    "ParallelBatchMap / lapack_dgetrf_ffi)."
)


class Watchdog:
    """Abort the process if a fojax call deadlocks (no CPU progress) or exceeds `limit` s.

    JAX releases the GIL while XLA executes, so this thread keeps running during a hang.
    `on_abort(reason)` is called (e.g. to write the partial results) before ``os._exit(3)``.
    """

    def __init__(self, limit: float, idle: float, on_abort):
        self.limit, self.idle, self.on_abort = limit, idle, on_abort
        self.what = None
        self._stop = threading.Event()
        self._lock = threading.Lock()
        threading.Thread(target=self._run, daemon=True).start()

    def watch(self, what: str):
        watchdog = self

        class _Ctx:
            def __enter__(self):
                with watchdog._lock:
                    watchdog.what = (what, time.monotonic())
                    watchdog._cpu = (time.process_time(), time.monotonic())

            def __exit__(self, *exc):
                with watchdog._lock:
                    watchdog.what = None

        return _Ctx()

    def _run(self):
        while not self._stop.wait(5.0):
            with self._lock:
                if self.what is None:
                    continue
                what, t_start = self.what
                cpu_then, t_then = self._cpu
                now, cpu_now = time.monotonic(), time.process_time()
                if cpu_now - cpu_then > 0.5:
                    self._cpu = (cpu_now, now)
                    stalled = False
                else:
                    stalled = now - t_then > self.idle
                over = now - t_start > self.limit
            if stalled or over:
                why = (
                    f"no CPU progress for {self.idle:.0f} s (deadlock)"
                    if stalled
                    else f"exceeded --hang-timeout {self.limit:.0f} s"
                )
                reason = f"ABORTED: {what} {why}. {HANG_NOTE}"
                print(f"\n!! {reason}", file=sys.stderr, flush=True)
                try:
                    self.on_abort(reason)
                finally:
                    os._exit(3)


# ================================================================================ study
def agreement(check_b: int, which: list[str], fojax_fns, seed: int, watchdog) -> dict:
    wl = wlmod.make_workload(check_b, seed)
    ref = peers.expm_reference(wl)
    res = {}
    for name in which:
        label, variants = peers.PEERS[name]
        for vname, fn in variants.items():
            res[f"{name}:{vname}"] = _common.rel_diff(fn(wl), ref)
    for fojax_fn in fojax_fns:
        with watchdog.watch(f"fojax agreement check (B = {check_b}, {fojax_fn.label})"):
            res[fojax_fn.method] = _common.rel_diff(np.asarray(fojax_fn(*fojax_fn.inputs(wl))), ref)
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=list(SIZES))
    ap.add_argument("--peers", nargs="+", default=list(peers.PEERS), choices=list(peers.PEERS))
    ap.add_argument("--no-fojax", action="store_true", help="time the peers only")
    ap.add_argument("--repeats", type=int, default=5, help="timed repetitions after the first call")
    ap.add_argument("--budget", type=float, default=60.0, help="seconds of repetitions per method and B")
    ap.add_argument(
        "--loop-max-b",
        type=int,
        default=1000,
        help="largest B run by the Python-loop peers (a), (b); beyond it their time is extrapolated",
    )
    ap.add_argument(
        "--variant-max-b",
        type=int,
        default=10_000,
        help="up to this B both axis orders of peers (c), (d) are timed; above it only the "
        "faster one at the largest such B",
    )
    ap.add_argument("--check-b", type=int, default=100, help="samples of the agreement check")
    ap.add_argument("--chunk", type=int, default=4096, help="fojax streaming chunk (samples per compiled call)")
    ap.add_argument(
        "--host-devices",
        type=int,
        default=HOST_DEVICES,
        help="JAX host devices fojax shards the samples over (default: one per usable core; read before "
        "JAX is imported; 1 = fojax on one core). The NumPy/SciPy peers are single-threaded.",
    )
    ap.add_argument(
        "--fojax-mode",
        choices=("auto", "vmap-simulate", "run-study"),
        nargs="+",
        default=["auto"],
        help="run-study (= auto): fojax.run_study on the workload's Study (public API); vmap-simulate: "
        "jax.vmap(fojax.simulate) with the metrics from the trajectories. Both: timed on the same samples",
    )
    ap.add_argument("--cpu-repeats", type=int, default=5,
                    help="with run-study and peer (d): rounds of the interleaved process-CPU-time comparison "
                    "(issue13_targets[*].cpu_time; 0: off)")
    ap.add_argument("--name", default=None,
                    help="results file name (default reference_workload, or reference_workload_run_study "
                    "with --fojax-mode ... run-study)")
    ap.add_argument(
        "--hang-timeout",
        type=float,
        default=1800.0,
        help="abort (writing partial results) if one fojax entry takes longer than this",
    )
    ap.add_argument(
        "--idle-timeout",
        type=float,
        default=120.0,
        help="abort if a fojax call makes no CPU progress for this long (a deadlock)",
    )
    ap.add_argument("--seed", type=int, default=wlmod.DEFAULT_SEED)
    ap.add_argument("--out", type=Path, default=HERE / "results")
    args = ap.parse_args(argv)
    if args.repeats < 1:
        ap.error("--repeats must be at least 1")
    sizes = sorted(set(args.sizes))

    info = _common.machine_info(VERSION_MODULES)
    print(f"# reference workload ({info['date']}, {info['cpu']}, {info['cores_available']} cores)")
    poles = wlmod.nominal_finite_poles()
    print("nominal finite poles:", np.array2string(poles, precision=3, max_line_width=200))
    assert wlmod.poles_match(poles, wlmod.EXPECTED_POLES, atol=0.011), (poles, wlmod.EXPECTED_POLES)
    worst = wlmod.max_real_pole_over_interval()
    print(f"max Re(finite pole) over delta in [-0.3, 0.3]: {worst:.3f} (every sample is stable)")

    # ---------------------------------------------------------------- fojax setup
    fojax_fns: list[FojaxRunner] = []
    fojax_msg = ""
    if not args.no_fojax:
        try:
            fojax_fns = [FojaxRunner(args.chunk, mode) for mode in dict.fromkeys(args.fojax_mode)]
        except FojaxUnavailable as e:
            fojax_msg = str(e)
            print(f"!! fojax entry skipped: {fojax_msg}")
        if len({f.method for f in fojax_fns}) != len(fojax_fns):
            ap.error("--fojax-mode: run-study (= auto) and vmap-simulate at most once each")
    if args.name is None:
        args.name = "reference_workload" + ("_run_study" if any(f.mode == "run-study" for f in fojax_fns) else "")

    rows: list[dict] = []
    failed: list[str] = []
    agree: dict = {}
    state = dict(info=info, agree=agree, rows=rows, args=args, fojax_fns=fojax_fns, fojax_msg=fojax_msg, failed=failed,
                 cpu={})
    watchdog = Watchdog(args.hang_timeout, args.idle_timeout, lambda reason: write_results(state, reason))

    # ---------------------------------------------------------------- agreement first
    print(f"\n## agreement on {args.check_b} samples (max relative difference to exact peer (d))")
    agree.update(agreement(args.check_b, args.peers, fojax_fns, args.seed, watchdog))
    for key, val in agree.items():
        tol = TOLERANCES[key.split(":")[0]]
        ok = val <= tol
        print(f"  {key:22s} {val:9.2e}  (tolerance {tol:.0e}) {'ok' if ok else 'FAIL'}")
        if not ok:
            failed.append(key)
    if failed:
        print(f"!! methods disagree: {failed}; no timings reported")
        return 1

    # ---------------------------------------------------------------- timing
    best_variant: dict[str, str] = {}
    for B in sizes:
        wl = wlmod.make_workload(B, args.seed)
        ref_B = None
        print(f"\n## B = {B}")
        for name in args.peers:
            label, variants = peers.PEERS[name]
            row, out = _common.time_peer(
                rows, name, label, variants, lambda fn: fn(wl), B, args, best_variant,
                loop_peer=name in ("solve_ivp", "control"), width=45, first_counts=True,
            )
            if row is None:
                continue
            if row["extrapolated"]:
                row["rel_diff_vs_expm"] = None
            else:
                row["_out"] = out
                if name == "expm":
                    ref_B = out
            rows.append(row)
        for fojax_fn in fojax_fns:
            xin = fojax_fn.inputs(wl)
            jax.clear_caches()  # a cold start at every B: the first call compiles
            with watchdog.watch(f"fojax at B = {B}"):
                compile_s = fojax_fn.prepare(*xin)  # AOT compile (jit mode), None otherwise
                out, first, times = _common.time_repeated(
                    lambda: jax.block_until_ready(fojax_fn(*xin)), args.repeats, args.budget
                )
            med = statistics.median(times)
            compile_note = "AOT lower+compile"
            if compile_s is None:  # eager modes: the first call traces and compiles
                compile_s = max(first - med, 0.0)
                compile_note = "first call - median"
            _common.print_timing(fojax_fn.label, f"compile {compile_s:6.2f} s", first, times, 45)
            rows.append(
                dict(
                    method=fojax_fn.method,
                    label=fojax_fn.label,
                    load_average_after=_common.load_average(),
                    engine=getattr(fojax_fn, "engine", None),
                    variant=f"chunk={args.chunk}",
                    B=B,
                    compile_s=compile_s,
                    compile_note=compile_note,
                    first_s=first,
                    median_s=med,
                    reps=len(times),
                    all_s=times,
                    extrapolated=False,
                    _out=np.asarray(out),
                )
            )
        for r in rows:
            if r["B"] == B and "_out" in r:
                out = r.pop("_out")
                r["rel_diff_vs_expm"] = None if ref_B is None else _common.rel_diff(out, ref_B)
                if ref_B is not None:
                    tol = TOLERANCES[r["method"]]
                    if r["rel_diff_vs_expm"] > tol:
                        print(f"!! {r['method']} disagrees with (d) at B = {B}: {r['rel_diff_vs_expm']:.2e}")
                        failed.append(f"{r['method']}@{B}")
        if args.cpu_repeats and "expm" in args.peers and any(f.mode == "run-study" for f in fojax_fns):
            state["cpu"][B] = cpu_times(wl, fojax_fns, best_variant.get("expm", "batch-last"), args.cpu_repeats)
            print("  process CPU time, min of interleaved repeats: "
                  + ", ".join(f"{k} {v:.4g} s" for k, v in state["cpu"][B].items() if k.endswith("_s")))
        write_results(state, status=f"partial (done up to B = {B} of {sizes})")

    write_results(state, status="complete", echo=True)
    return 1 if failed else 0


def cpu_times(wl, fojax_fns, expm_variant: str, repeats: int) -> dict:
    """Process CPU time (``time.process_time``) of fojax's calls and peer (d) on the batch
    `wl`, the minimum over `repeats` rounds that call each in turn (interleaved, after the
    wall-clock timing, so every call is warm): a load-robust comparison on a shared machine,
    where a descheduled process's wall time grows and its CPU time does not. fojax runs on
    one device here and uses one core (checked: CPU ≤ wall); the peer is single-threaded."""
    calls = {f"{f.method}_s": (lambda f=f, xin=f.inputs(wl): jax.block_until_ready(f(*xin))) for f in fojax_fns}
    calls["expm_s"] = lambda: peers.PEERS["expm"][1][expm_variant](wl)
    best = {k: float("inf") for k in calls}
    for _ in range(repeats):
        for k, call in calls.items():
            c0 = time.process_time()
            call()
            best[k] = min(best[k], time.process_time() - c0)
    out = dict(best, repeats=repeats, expm_variant=expm_variant, load_average_after=_common.load_average())
    rs = best.get("fojax_run_study_s")
    if rs is not None:
        out["speedup_vs_expm_peer"] = best["expm_s"] / rs
    return out


def write_results(state: dict, status: str, echo: bool = False) -> None:
    """Markdown + JSON into ``args.out`` (called after every B, on abort and at the end)."""
    info, agree, rows, args = state["info"], state["agree"], state["rows"], state["args"]
    fojax_fns, fojax_msg, failed = state["fojax_fns"], state["fojax_msg"], state["failed"]
    rows = [{k: v for k, v in r.items() if not k.startswith("_")} for r in rows]
    for r in rows:
        r["samples_per_s"] = r["B"] / r["median_s"]
    _common.add_speedups(rows, {"fojax": "", "fojax_run_study": "_run_study"})
    fojax_note = ""
    for fojax_fn in fojax_fns:
        fojax_note += (f"{'; ' if fojax_note else ''}fojax mode: {fojax_fn.mode} (requested "
                       f"{fojax_fn.requested_mode}), chunk {args.chunk}")
        if fojax_fn.fallback_reason:
            fojax_note += f" ({fojax_fn.fallback_reason})"
    if fojax_fns:
        fojax_note += f"; {jax.device_count()} JAX host device(s) (jax.shard_map over the samples)"
    targets = issue13_targets(rows)
    for t in targets:
        if t["B"] in state.get("cpu", {}):
            t["cpu_time"] = state["cpu"][t["B"]]
    payload = _common.result_payload(
        args.name,
        status,
        info,
        args,
        tolerances=TOLERANCES,
        agreement_check=dict(B=args.check_b, max_rel_diff_vs_expm=agree),
        fojax_unavailable=fojax_msg or None,
        fojax_note=fojax_note or None,
        issue13_targets=targets or None,
        rows=rows,
        disagreements=failed,
    )
    md = render_markdown(payload["machine"], agree, rows, fojax_msg, fojax_note, args, status, targets)
    _common.write_results(args.out, args.name, payload, md, echo=echo)


def issue13_targets(rows) -> list[dict]:
    """Per B with `fojax.run_study` and peer (d) measured: issue 13's ratio
    ``t_expm / t_run_study`` (≥ `TARGET_VS_EXPM`) from the medians, and the load average
    after the run_study measurement."""
    out = []
    for B in sorted({r["B"] for r in rows}):
        pick = {m: next((r for r in rows if r["method"] == m and r["B"] == B), None)
                for m in ("fojax_run_study", "expm")}
        rs, expm = pick["fojax_run_study"], pick["expm"]
        if rs is None:
            continue
        row = dict(B=B, run_study_s=rs["median_s"], load_average_after_run_study=rs.get("load_average_after"))
        if expm is not None and not expm["extrapolated"]:
            speed = expm["median_s"] / rs["median_s"]
            row.update(expm_peer_s=expm["median_s"], speedup_vs_expm_peer=speed,
                       target_speedup_vs_expm_peer_min=TARGET_VS_EXPM, expm_target_met=speed >= TARGET_VS_EXPM)
        out.append(row)
    return out


def render_markdown(info, agree, rows, fojax_msg, fojax_note, args, status, targets=()) -> str:
    fmt = _common.fmt
    lines = [
        "# Reference workload (issue 7): thesis §4.1.3 observer-based control loop",
        "",
        f"- status: {status}",
        *_common.machine_lines(info),
        f"- float64; horizon [0, 10] s, 0.01 s grid (1001 points); seed {args.seed}; "
        f"median of up to {args.repeats} repetitions (budget {args.budget:.0f} s per entry) after a "
        "separately timed first call",
        "",
        f"## Agreement (B = {args.check_b}; max relative difference of the per-sample metrics to the exact peer (d))",
        "",
        "| method | max rel. diff | tolerance |",
        "|---|---|---|",
    ]
    for key, val in agree.items():
        lines.append(f"| {key} | {val:.2e} | {TOLERANCES[key.split(':')[0]]:.0e} |")
    if fojax_msg:
        lines += ["", f"**fojax not measured:** {fojax_msg}"]
    if fojax_note:
        lines += ["", f"- {fojax_note}"]
    lines += [
        "",
        "## Timings",
        "",
        "`fojax speed-up` = t_peer / t_fojax (> 1: fojax faster); `t_fojax/t_peer` is its inverse. "
        "*extrap.* = not run, extrapolated linearly from the largest measured B.",
        "",
        "| B | method | variant | compile (s) | first call (s) | median (s) | reps | samples/s | "
        "rel. diff vs (d) | t_fojax/t_peer | fojax speed-up |",
        "|---:|---|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        med = f"{r['median_s']:.4g}" + (" *extrap.*" if r["extrapolated"] else "")
        lines.append(
            f"| {r['B']} | {r['label']} | {r['variant']} | {fmt(r.get('compile_s'), '.2f')} | "
            f"{fmt(r['first_s'], '.4g')} | {med} | {r['reps']} | {r['samples_per_s']:.4g} | "
            f"{fmt(r.get('rel_diff_vs_expm'), '.1e')} | {fmt(r.get('t_fojax_over_t_peer'), '.3g')} | "
            f"{fmt(r.get('fojax_speedup'), '.3g')} |"
        )
    peer_names = [p for p in peers.PEERS if any(r["method"] == p for r in rows)]
    cols = [(p, sfx, f"{peers.PEERS[p][0]}{tag}") for sfx, tag, m in
            (("", "", "fojax"), ("_run_study", " [run_study]", "fojax_run_study"))
            if any(r["method"] == m for r in rows) for p in peer_names]
    if cols:
        lines += _common.speedup_table(rows, cols)
    if targets:
        lines += ["", f"## Issue 13: `fojax.run_study` on this workload (target: ≥ {TARGET_VS_EXPM}× peer (d))", "",
                  "| B | run_study (s) | peer (d) (s) | speed-up vs (d) | load avg after |", "|---:|---:|---:|---:|---|"]
        for t in targets:
            load = t.get("load_average_after_run_study")
            lines.append(
                f"| {t['B']} | {t['run_study_s']:.4g} | {fmt(t.get('expm_peer_s'), '.4g')} | "
                f"{fmt(t.get('speedup_vs_expm_peer'), '.3g')} | "
                f"{'' if load is None else ', '.join(f'{x:.2f}' for x in load)} |")
        cpu = [t for t in targets if "cpu_time" in t]
        if cpu:
            lines += ["", "Process CPU time (min of interleaved repeats; robust to a busy machine's descheduling):", "",
                      "| B | run_study (s) | peer (d) (s) | speed-up vs (d) |", "|---:|---:|---:|---:|"]
            for t in cpu:
                c = t["cpu_time"]
                lines.append(f"| {t['B']} | {c['fojax_run_study_s']:.4g} | {c['expm_s']:.4g} | "
                             f"{c['speedup_vs_expm_peer']:.3g} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
