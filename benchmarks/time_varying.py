"""Issue 7, study 2: the §4.1.3 loop with a time-varying δ(t) and a constant actuator fault.

Exact discretisation does not apply (the loop is time-varying), so fojax's entry is
`fojax.run_study` with ``stepper=fojax.Exponential(substeps=s, startup_factor=f)`` (a
fourth-order exponential integrator around the nominal loop, batched) on the workload as a
`fojax.Study` (no observers: the signals ``[x; ẑ − Lx]`` of the 8-state loop, their
per-signal IAEs summed into the two metrics), and the peers are (a) a Python loop of `solve_ivp` (RK45, rtol 1e-6,
atol 1e-9) and (c) NumPy RK4 with dt = 1e-3 vectorised over the batch (both axis orders,
the faster kept). Every method is first compared with a tight reference (DOP853, rtol
1e-12, atol 1e-14) on `--ref-b` samples; fojax is then timed at equal or better accuracy
than RK4 in two schedules: *uniform* — the largest uniform step (fewest substeps per 0.01 s
grid interval) whose error is at most RK4's — and *start-up* — the cheapest schedule with
finer steps over the initial layer (the first ~5 time constants of the fastest nominal
pole, as `fojax.Exponential` chooses it) and coarse ones after it whose error is at most RK4's. Timings and the table as in
`reference_workload.py`:

    python benchmarks/time_varying.py                       # B = 1, 100, 1000, 10000
    python benchmarks/time_varying.py --sizes 1 100 1000 --repeats 3
    python benchmarks/time_varying.py --substeps 3 --no-startup --loop-max-b 100

Timing rules: imports, drawing the samples and the peers' hand reduction are outside the
timed region; the first call of every method is timed separately (for fojax after
`jax.clear_caches()`, so it includes compilation, reported as first call − median); then up
to `--repeats` repetitions within `--budget` seconds, median reported, fojax's output
through `jax.block_until_ready`. The solve_ivp loop runs up to `--loop-max-b` samples and is
extrapolated linearly beyond (marked *extrap.*).
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path


HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import _common  # noqa: E402


_common.limit_blas_threads()  # before NumPy: favours the peers (see README)
_common.prefer_checkout()  # before the first `import fojax`: measure this checkout's fojax
HOST_DEVICES = _common.force_host_devices()

import jax  # noqa: E402


jax.config.update("jax_enable_x64", True)

import _workload as wlmod  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import peers_tv  # noqa: E402


SIZES = (1, 100, 1_000, 10_000)
SUBSTEP_CANDIDATES = (1, 2, 3, 4, 5, 6, 8)
#: Start-up schedules: (bulk substeps, substeps in the start-up intervals); the start-up
#: covers ~5 time constants of the fastest nominal pole (`startup_intervals`).
STARTUP_CANDIDATES = ((1, 2), (1, 4), (1, 8), (2, 4), (2, 8))
NAME = "time_varying"


def startup_intervals() -> int:
    """Grid intervals covering 5 / |fastest nominal pole| (13 for this loop: 5 / 39.8 s)."""
    lam = wlmod.nominal_finite_poles()
    return int(np.ceil(5.0 / np.max(np.abs(lam.real)) / wlmod.DT_GRID))


def schedule_steps(substeps: int, startup) -> int:
    n = wlmod.TS.size - 1
    if startup is None:
        return substeps * n
    k, s = startup
    return s * k + substeps * (n - k)


def schedule_label(substeps: int, startup) -> str:
    if startup is None:
        return f"substeps={substeps}"
    return f"substeps={substeps}, startup=({startup[0]}, {startup[1]})"


# ================================================================================ fojax
_E_CL = jnp.asarray(wlmod.E_CL)
_A_CL0 = jnp.asarray(wlmod.closed_loop_A(wlmod.A))
_DA_CL = jnp.asarray(wlmod.DELTA_A_CL)
_B_F = jnp.asarray(wlmod.B_FAULT_CL)
_C_FULL = jnp.asarray(wlmod.full_output_rows())  # (6, 8): [x; ẑ − L x]
N_STATE = 4  # the first four signals are the plant state


def tv_study(wl: wlmod.TimeVaryingWorkload):
    """The batch as one `fojax.Study` (public API only): the 8-state closed loop
    (`fojax.DescriptorSystem`) with δ(t) = a sin(ωt + φ) on ΔA
    (`fojax.UncertainDescriptorSystem` with a `fojax.Sine` uncertainty), wrapped in
    `fojax.plant.FaultyPlant` with the constant fault entering through ``[B; 0]``; sample ``k``
    is ``(δ_k, f_k, x0_k)`` (three families of the same size on the uncertainty axis), the
    signals are ``[x; ẑ − Lx]``."""
    import fojax
    from fojax.plant import FaultyPlant
    from fojax.studies import Family

    zero = jnp.zeros(1)
    nominal = fojax.DescriptorSystem(_E_CL, _A_CL0)
    plant = FaultyPlant(fojax.UncertainDescriptorSystem(nominal, dA=_DA_CL, delta=fojax.Sine(zero, zero, zero)),
                        Fa=_B_F, fault=fojax.Constant(jnp.zeros(_B_F.shape[1])))
    col = lambda a: jnp.asarray(a, dtype=jnp.float64)[:, None]  # noqa: E731
    families = (
        Family(fojax.Sine(col(wl.amplitude), col(wl.omega), col(wl.phase)), ("plant", "base", "delta")),
        Family(fojax.Constant(jnp.asarray(wl.fault, dtype=jnp.float64)), ("plant", "fault")),
        Family(jnp.asarray(wl.x0_cl, dtype=jnp.float64), ("x0",)),
    )
    return fojax.Study(plant, jnp.asarray(wl.x0_cl[0]), jnp.asarray(wl.ts), _C_FULL, uncertainty=families)


def stepper(substeps: int, startup=None):
    """`fojax.Exponential` with `substeps` per grid interval; ``startup = (k, s)``: ``s`` steps
    per interval over the initial layer (``k`` = `startup_intervals`, chosen by the stepper),
    i.e. ``startup_factor = s / substeps``."""
    import fojax

    if startup is None:
        return fojax.Exponential(substeps=substeps, startup_factor=1)
    factor, rest = divmod(startup[1], substeps)
    assert rest == 0, "start-up substeps must be a multiple of the bulk substeps"
    return fojax.Exponential(substeps=substeps, startup_factor=factor)


def run_fojax(wl: wlmod.TimeVaryingWorkload, substeps: int, chunk: int = 4096, startup=None, study=None):
    """``(B, 2)`` metrics (IAE of |x|_1, of |zhat - Lx|_1) from `fojax.run_study` (`study`:
    `tv_study` of `wl`, built by the caller outside a timed region)."""
    import fojax

    study = tv_study(wl) if study is None else study
    res = fojax.run_study(study, stepper=stepper(substeps, startup), chunk_size=chunk, quiet=True,
                          save=fojax.Metrics(kinds="iae", bands=None))
    assert res.attrs["engine"] == "exponential-batch", res.attrs["engine"]
    iae = np.asarray(res.metrics["iae"])[0, :, 0, :]  # (B, 6)
    return np.stack([iae[:, :N_STATE].sum(axis=1), iae[:, N_STATE:].sum(axis=1)], axis=1)


# ================================================================================ study
def accuracy(ref_b: int, seed: int, fixed_substeps, with_startup: bool, chunk: int) -> dict:
    """Each method's max relative error vs the tight reference on the first `ref_b` samples,
    and the fojax schedules to time: the largest uniform step (fewest substeps) and the
    cheapest start-up schedule whose error is at most RK4's."""
    wl = wlmod.make_tv_workload(ref_b, seed)
    ref = peers_tv.tight_reference(wl)
    # the reference's own accuracy: DOP853 with tolerances 10x tighter on a few samples
    few = wlmod.make_tv_workload(min(ref_b, 5), seed)
    tighter = peers_tv.tight_reference(few, rtol=1e-13, atol=1e-15)
    res = {"reference_self_check": _common.rel_diff(ref[: few.size], tighter)}
    for name, (_, variants) in peers_tv.PEERS_TV.items():
        for vname, fn in variants.items():
            res[f"{name}:{vname}"] = _common.rel_diff(fn(wl), ref)
    rk4_err = max(v for k, v in res.items() if k.startswith("rk4:"))
    k = startup_intervals()
    schedules = [(s, None) for s in ([fixed_substeps] if fixed_substeps else SUBSTEP_CANDIDATES)]
    if with_startup:
        schedules += [(b, (k, s)) for b, s in STARTUP_CANDIDATES]
    table = []
    for sub, st in schedules:
        err = _common.rel_diff(np.asarray(run_fojax(wl, sub, chunk, st)), ref)
        table.append(dict(substeps=sub, startup=st, steps=schedule_steps(sub, st), error=err,
                          label=schedule_label(sub, st)))
    res["fojax_schedules"] = table
    res["rk4_error"] = rk4_err
    chosen = {}
    for kind, rows in (("uniform", [r for r in table if r["startup"] is None]),
                       ("startup", [r for r in table if r["startup"] is not None])):
        ok = [r for r in rows if r["error"] <= rk4_err]
        if fixed_substeps and kind == "uniform":
            ok = rows
        if ok:
            chosen[kind] = min(ok, key=lambda r: r["steps"])
        elif rows and kind == "uniform":
            chosen[kind] = min(rows, key=lambda r: r["error"])  # none as accurate: the finest
    if "startup" in chosen and chosen["startup"]["steps"] >= chosen["uniform"]["steps"]:
        del chosen["startup"]  # not cheaper: nothing to show
    res["chosen"] = chosen
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=list(SIZES))
    ap.add_argument("--peers", nargs="+", default=list(peers_tv.PEERS_TV), choices=list(peers_tv.PEERS_TV))
    ap.add_argument("--repeats", type=int, default=5, help="timed repetitions after the first call")
    ap.add_argument("--budget", type=float, default=60.0, help="seconds of repetitions per method and B")
    ap.add_argument(
        "--loop-max-b",
        type=int,
        default=1000,
        help="largest B run by the solve_ivp loop (a); beyond it its time is extrapolated",
    )
    ap.add_argument(
        "--variant-max-b",
        type=int,
        default=10_000,
        help="up to this B both axis orders of RK4 are timed; above it only the faster one",
    )
    ap.add_argument(
        "--ref-b",
        type=int,
        default=100,
        help="samples of the tight reference (accuracy check); the worst samples (a near 0.3, "
        "omega near 5 rad/s) set the max error, so keep enough to draw some",
    )
    ap.add_argument(
        "--substeps",
        type=int,
        default=None,
        help="fojax steps per 0.01 s grid interval of the uniform entry (default: the fewest "
        f"that are at least as accurate as RK4 among {SUBSTEP_CANDIDATES})",
    )
    ap.add_argument(
        "--no-startup",
        action="store_true",
        help="do not time the start-up schedule entry (finer steps over the initial layer)",
    )
    ap.add_argument("--chunk", type=int, default=4096, help="fojax chunk_size")
    ap.add_argument("--host-devices", type=int, default=HOST_DEVICES,
                    help="JAX host devices fojax spreads the samples over (default: one per usable core; "
                    "read before JAX is imported). The NumPy/SciPy peers are single-threaded.")
    ap.add_argument("--seed", type=int, default=wlmod.DEFAULT_SEED)
    ap.add_argument("--out", type=Path, default=_common.RESULTS)
    args = ap.parse_args(argv)
    if args.repeats < 1:
        ap.error("--repeats must be at least 1")
    sizes = sorted(set(args.sizes))

    info = _common.machine_info()
    print(f"# time-varying study ({info['date']}, {info['cpu']}, {info['cores_available']} cores)")
    P, worst = wlmod.quadratic_stability_certificate()
    print(
        "common Lyapunov matrix for |delta| <= 0.3, decay rate 0.5: largest vertex eigenvalue "
        f"{worst:.3g} (< 0: every sample is stable for any delta(t) profile)"
    )
    if not worst < 0:
        print("!! stability certificate failed")
        return 1

    # ---------------------------------------------------------------- accuracy first
    print(f"\n## accuracy on {args.ref_b} samples (max relative error vs DOP853 rtol 1e-12, atol 1e-14)")
    acc = accuracy(args.ref_b, args.seed, args.substeps, not args.no_startup, args.chunk)
    print(f"  reference vs DOP853 rtol 1e-13 (5 samples)   {acc['reference_self_check']:9.2e}")
    for key in [k for k in acc if ":" in k]:
        print(f"  {key:45s} {acc[key]:9.2e}")
    for r in acc["fojax_schedules"]:
        print(f"  fojax {r['label']:38s} {r['error']:9.2e}  ({r['steps']} steps)")
    entries = acc["chosen"]
    for kind, r in entries.items():
        print(f"  -> fojax ({kind}) runs with {r['label']}: error {r['error']:.2e} vs RK4 {acc['rk4_error']:.2e}")
    if not entries["uniform"]["error"] <= acc["rk4_error"]:
        print("!! no uniform step is as accurate as RK4; timing the most accurate one anyway")

    rows: list[dict] = []
    state = dict(info=info, acc=acc, rows=rows, args=args)

    # ---------------------------------------------------------------- timing
    best_variant: dict[str, str] = {}
    for B in sizes:
        wl = wlmod.make_tv_workload(B, args.seed)
        print(f"\n## B = {B}")
        outs = {}
        for name in args.peers:
            label, variants = peers_tv.PEERS_TV[name]
            row, out = _common.time_peer(rows, name, label, variants, lambda fn: fn(wl), B, args, best_variant,
                                         loop_peer=name == "solve_ivp", width=40)
            if row is None:
                continue
            if not row["extrapolated"]:
                outs[name] = out
            rows.append(row)
        study = tv_study(wl)  # the call's input, built outside the timed region
        for kind, sched in entries.items():
            jax.clear_caches()  # a cold start at every B: the first call compiles
            sub, st = sched["substeps"], sched["startup"]
            out, first, times = _common.time_repeated(
                lambda: run_fojax(wl, sub, args.chunk, st, study=study), args.repeats, args.budget
            )
            med = statistics.median(times)
            compile_s = max(first - med, 0.0)
            method = "fojax" if kind == "uniform" else "fojax-startup"
            label = f"fojax.run_study, Exponential ({sched['label']})"
            _common.print_timing(label, f"compile {compile_s:6.2f} s", first, times, 40)
            row = dict(method=method, label=label, variant=f"chunk={args.chunk}", B=B, compile_s=compile_s,
                       compile_note="first call - median (caches cleared)", first_s=first, median_s=med,
                       reps=len(times), all_s=times, extrapolated=False, schedule=sched)
            if "rk4" in outs:
                row["rel_diff_vs_rk4"] = _common.rel_diff(np.asarray(out), outs["rk4"])
                print(f"  {method} vs RK4 at this B: max relative difference {row['rel_diff_vs_rk4']:.2e}")
            rows.append(row)
        write_results(state, status=f"partial (done up to B = {B} of {sizes})")

    write_results(state, status="complete", echo=True)
    return 0


#: The timed fojax entries and the suffix of their speed-up fields in the peers' rows.
FOJAX_METHODS = {"fojax": "", "fojax-startup": "_startup"}


def _method_error(acc, row):
    """The method's max relative error vs the tight reference (accuracy check)."""
    if row["method"] in FOJAX_METHODS:
        return row["schedule"]["error"]
    return acc.get(f"{row['method']}:{row['variant']}")


def write_results(state: dict, status: str, echo: bool = False) -> None:
    info, acc, args = state["info"], state["acc"], state["args"]
    rows = [dict(r) for r in state["rows"]]
    for r in rows:
        r["samples_per_s"] = r["B"] / r["median_s"]
        r["max_rel_error_vs_reference"] = _method_error(acc, r)
    _common.add_speedups(rows, FOJAX_METHODS)
    payload = _common.result_payload(
        NAME,
        status,
        info,
        args,
        workload=dict(
            delta="a_k sin(omega_k t + phi_k)",
            amplitude=[0.0, wlmod.TV_AMPLITUDE_MAX],
            omega_rad_s=list(wlmod.TV_OMEGA_RANGE),
            phase=[0.0, "2 pi"],
            fault=f"constant, each of 2 components U[-{wlmod.FAULT_MAX}, {wlmod.FAULT_MAX}], plant input u + f",
            horizon_s=float(wlmod.T_END),
            grid_s=float(wlmod.DT_GRID),
        ),
        accuracy=dict(reference="solve_ivp DOP853 rtol 1e-12 atol 1e-14", samples=args.ref_b, **acc),
        rows=rows,
    )
    md = render_markdown(payload["machine"], acc, rows, args, status)
    _common.write_results(args.out, NAME, payload, md, echo=echo)


def render_markdown(info, acc, rows, args, status) -> str:
    fmt = _common.fmt
    chosen = acc["chosen"]
    lines = [
        "# Study 2 (issue 7): §4.1.3 loop with a time-varying δ(t) and a constant actuator fault",
        "",
        f"- status: {status}",
        *_common.machine_lines(info),
        f"- float64; horizon [0, 10] s, 0.01 s grid (1001 points); δ_k(t) = a_k sin(ω_k t + φ_k), "
        f"a ~ U[0, {wlmod.TV_AMPLITUDE_MAX}], ω ~ U{list(wlmod.TV_OMEGA_RANGE)} rad/s, φ ~ U[0, 2π); "
        f"fault f_k ~ U[-{wlmod.FAULT_MAX}, {wlmod.FAULT_MAX}]² on the plant input; seed {args.seed}; "
        f"median of up to {args.repeats} repetitions (budget {args.budget:.0f} s per entry) after a "
        "separately timed first call",
        "",
        f"## Accuracy (max relative error of the per-sample metrics vs DOP853 rtol 1e-12, atol 1e-14; "
        f"{args.ref_b} samples)",
        "",
        "| method | integration steps | max rel. error |",
        "|---|---:|---|",
        f"| reference itself (vs DOP853 rtol 1e-13, atol 1e-15, 5 samples) | — | {acc['reference_self_check']:.1e} |",
    ]
    for key in [k for k in acc if ":" in k]:
        steps = "adaptive" if key.startswith("solve_ivp") else str(int(round(wlmod.T_END / peers_tv.RK4_DT)))
        lines.append(f"| {key} | {steps} | {acc[key]:.1e} |")
    for r in acc["fojax_schedules"]:
        mark = "".join(f" **(timed: {kind})**" for kind, c in chosen.items() if c["label"] == r["label"])
        lines.append(f"| fojax, {r['label']}{mark} | {r['steps']} | {r['error']:.1e} |")
    lines += [
        "",
        "Timed fojax entries: *uniform* — the largest uniform step (fewest steps per 0.01 s interval) "
        "whose error is at most RK4's; *start-up* — the cheapest schedule with finer steps over the "
        f"first {startup_intervals()} intervals (5 time constants of the fastest nominal pole, where "
        "the perturbation excites the fast modes) whose error is at most RK4's. Both are at equal "
        "or better accuracy than RK4." if args.substeps is None else f"Uniform fojax substeps fixed to {args.substeps}.",
        "",
        "## Timings",
        "",
        "`speed-up` = t_peer / t_fojax (> 1: fojax faster), for the uniform and the start-up entry. "
        "*extrap.* = not run, extrapolated linearly from the largest measured B. `rel. diff vs RK4`: "
        "fojax's metrics against RK4's at that B.",
        "",
        "| B | method | variant | compile (s) | first call (s) | median (s) | reps | samples/s | "
        "max rel. error | rel. diff vs RK4 | speed-up (uniform) | speed-up (start-up) |",
        "|---:|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        med = f"{r['median_s']:.4g}" + (" *extrap.*" if r["extrapolated"] else "")
        lines.append(
            f"| {r['B']} | {r['label']} | {r['variant']} | {fmt(r.get('compile_s'), '.2f')} | "
            f"{fmt(r['first_s'], '.4g')} | {med} | {r['reps']} | {r['samples_per_s']:.4g} | "
            f"{fmt(r.get('max_rel_error_vs_reference'), '.1e')} | {fmt(r.get('rel_diff_vs_rk4'), '.1e')} | "
            f"{fmt(r.get('fojax_speedup'), '.3g')} | {fmt(r.get('fojax_speedup_startup'), '.3g')} |"
        )
    peer_names = [p for p in peers_tv.PEERS_TV if any(r["method"] == p for r in rows)]
    cols = [(p, sfx) for p in peer_names for sfx in ("", "_startup")
            if any(("fojax_speedup" + sfx) in r for r in rows if r["method"] == p)]
    if cols:
        lines += _common.speedup_table(
            rows, [(p, sfx, f"{peers_tv.PEERS_TV[p][0]} vs fojax {'start-up' if sfx else 'uniform'}") for p, sfx in cols]
        )
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
