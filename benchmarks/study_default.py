"""Issue 13: the product path on the default §3.3.7 study — `fojax.run_study` vs a SciPy/NumPy peer.

The study (what `fojax study` tunes and studies on the built-in example, in its exact
LTI form): the fault-augmented §3.3.7 plant (n = 9, rank E = 7) with a constant δ per
sample (uniform in [-0.3, 0.3]) × constant faults (`constant_faults`, magnitudes in
[0.5, 1.5]), zero input, the PO and FGDO observers of `fojax/examples/example_3_3_7.toml`
(disk region centre -3, radius 2), 10 s on a 0.01 s grid (1,001 points); metrics IAE, ISE,
ITAE, peak and settling time per sample, observer and signal (5 signals).

The peer is what a competent SciPy user writes: per-sample index-1 reduction and joint
loop matrix in batched NumPy, ``scipy.linalg.expm`` on the whole ``(B, N, N)`` stack,
then a batched NumPy recurrence over the grid accumulating the same metrics. Both run
on the same samples; their per-sample metrics are checked to agree (≤ 1e-8 relative)
before anything is timed.

    python benchmarks/study_default.py                 # B = 1,000 and 10,000
    python benchmarks/study_default.py --sizes 1000 --repeats 3 --host-devices 2

Timing: the first call of `fojax.run_study` (after `jax.clear_caches()`) is reported
separately and ``compile ≈ first − median``; then the median of ``--repeats`` calls.
Main rows use ``quantiles=()`` (the peer computes no quantile bands); then `run_study`
with its default settings (quantile bands on the default band grid, ``ts[::5]``: 201
points) is timed against both the metrics-only peer and the peer that also keeps its
errors on the same band grid and calls ``np.quantile`` (bands checked to agree first).
Writes ``benchmarks/results/study_latest.json``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path


HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import _common  # noqa: E402


_common.limit_blas_threads()
if any(a.startswith("--host-devices") for a in sys.argv[1:]):
    _common.force_host_devices()
_common.prefer_checkout()

import jax  # noqa: E402


jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from _study_peer import study_peer as peer  # noqa: E402

import fojax  # noqa: E402
from fojax import studies as S  # noqa: E402
from fojax.design import design_functional_observer, Disk  # noqa: E402


T_END, DT, SETTLE_TOL = 10.0, 0.01, 0.05
METRICS = ("iae", "ise", "itae", "peak", "settling_time")


def build(B: int, seed: int = 0, delta: str = "constant"):
    """The default study with ``B`` samples; ``delta="sine"``: its time-varying version,
    δ(t) = a sin(ωt + φ) with |a| ≤ 0.3, ω ∈ [0.5, 5] rad/s (`study_time_varying.py`)."""
    ex = fojax.models.example_3_3_7()
    obs = tuple(
        design_functional_observer(ex.augmented, ex.L_aug, kind=k, region=Disk(-3.0, 2.0)).observer
        for k in ("proportional", "generalized")
    )
    dA = np.zeros((1, 9, 9))
    dA[0, :6, :6] = ex.dA
    template = fojax.Constant(jnp.zeros(1)) if delta == "constant" else fojax.Sine(jnp.zeros(1), jnp.ones(1), jnp.zeros(1))
    plant = fojax.UncertainDescriptorSystem(ex.augmented, dA=dA, delta=template)
    x0 = jnp.concatenate([jnp.full((6,), 0.5), jnp.zeros(3)])
    ts = jnp.linspace(0.0, T_END, int(round(T_END / DT)) + 1)
    nf = 10
    k1, k2 = jax.random.split(jax.random.PRNGKey(seed))
    study = fojax.Study(plant, x0, ts, ex.L_aug, None,
                        uncertainty=(S.constant_delta(k1, B // nf, 1, bounds=(-0.3, 0.3)) if delta == "constant" else
                                     S.sinusoidal_delta(k1, B // nf, 1, amplitude=(-0.3, 0.3), omega=(0.5, 5.0)),),
                        scenarios=(S.constant_faults(k2, nf, x0, 3, magnitude=(0.5, 1.5)),),
                        signal_names=("z1", "z2", "f1", "f2", "f3"))
    return ex, plant, obs, study


def peer_inputs(ex, plant, obs, study):
    """Plain NumPy arrays of the samples (outside the timed region)."""
    B = study.num_samples
    iu = np.arange(B) // study.num_scenarios
    jf = np.arange(B) % study.num_scenarios
    vals = study.uncertainty[0].values
    delta = np.asarray(vals.value)[iu, 0] if isinstance(vals, fojax.Constant) else None  # (B,); None: δ(t)
    x0 = np.asarray(study.scenarios[0].values)[jf]  # (B, 9)
    lms = [o.linear_matrices() for o in obs]
    return dict(
        E=np.asarray(plant.E), A0=np.asarray(plant.nominal.A), dA=np.asarray(plant.dA[0]), C=np.asarray(plant.nominal.C),
        L=np.asarray(ex.L_aug), delta=delta, x0=x0,
        obs=[tuple(np.asarray(m) for m in (lm.A, lm.By, lm.C, lm.Dy)) for lm in lms],
        ts=np.asarray(study.ts),
    )


def fojax_metrics(res):
    """run_study metrics as ``(5, B, K)`` (K = observer × signal), sample order (i, j)."""
    out = []
    for name in METRICS:
        v = res.metrics[name]  # (obs, Nu, Nf, q)
        out.append(np.transpose(v, (1, 2, 0, 3)).reshape(v.shape[1] * v.shape[2], -1))
    return np.stack(out)


def timed(f, repeats):
    """``(median wall s, wall runs, last output, process CPU s per run)``: on the shared
    machine the CPU seconds move less with the load than the wall times (fojax's include
    XLA's second thread; the peer runs single-threaded BLAS)."""
    ts, cs = [], []
    out = None
    for _ in range(repeats):
        t, c = time.perf_counter(), time.process_time()
        out = f()
        ts.append(time.perf_counter() - t)
        cs.append(time.process_time() - c)
    return statistics.median(ts), ts, out, cs


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", type=int, nargs="+", default=[1000, 10000])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--host-devices", type=int, default=None)
    ap.add_argument("--out", default=str(_common.RESULTS / "study_latest.json"))
    args = ap.parse_args()
    info = _common.machine_info()
    rows = []
    joint_states = None
    for B in args.sizes:
        ex, plant, obs, study = build(B)
        # the joint loop stepped per sample: the plant's rank E slow states + the observers'
        # (zero input and faults in the augmented state: no exosystem states)
        joint_states = int(np.linalg.matrix_rank(np.asarray(plant.E))) + sum(o.state_size for o in obs)
        d = peer_inputs(ex, plant, obs, study)
        jax.clear_caches()
        t = time.perf_counter()
        res = fojax.run_study(study, obs, quantiles=(), quiet=True)
        first = time.perf_counter() - t
        assert res.attrs["engine"] == "exact-batch", res.attrs
        ref = peer(d)
        got = fojax_metrics(res)
        fin = np.isfinite(ref)
        rel = np.abs(got[fin] - ref[fin]) / np.maximum(np.abs(ref[fin]), 1e-12 * np.max(np.abs(ref[fin])))
        agree = float(np.max(rel))
        if not (agree <= 1e-8 and np.array_equal(np.isfinite(got), fin)):
            raise SystemExit(f"B={B}: fojax and the peer disagree (max rel {agree:.2e})")
        med, reps, _, cpu = timed(lambda: fojax.run_study(study, obs, quantiles=(), quiet=True), args.repeats)
        pmed, preps, _, pcpu = timed(lambda: peer(d), max(1, args.repeats if B <= 1000 else 1))
        t = time.perf_counter()
        qres = fojax.run_study(study, obs, quiet=True)  # default quantile bands: another structure, compiles once
        qfirst = time.perf_counter() - t
        # the peer with the same bands (errors kept on the same band grid, np.quantile)
        stride, levels = qres.attrs["band_stride"], qres.coords["quantile"]
        _, pbands = peer(d, (stride, levels))
        fb = np.transpose(qres.metrics["quantiles"], (1, 2, 0, 3)).reshape(pbands.shape)  # (nq, T_c, obs*q)
        band_agree = float(np.max(np.abs(fb - pbands)) / np.max(np.abs(pbands)))
        if not band_agree <= 1e-8:
            raise SystemExit(f"B={B}: fojax's and the peer's quantile bands disagree ({band_agree:.2e})")
        qmed, qreps, _, qcpu = timed(lambda: fojax.run_study(study, obs, quiet=True), args.repeats)
        qpmed, qpreps, _, qpcpu = timed(lambda: peer(d, (stride, levels)), 1)
        row = dict(
            B=B, agreement_max_rel=agree,
            fojax_first_call_s=first, fojax_compile_estimate_s=first - med, fojax_median_s=med, fojax_runs_s=reps,
            fojax_samples_per_s=B / med,
            fojax_default_quantiles_first_call_s=qfirst, fojax_default_quantiles_s=qmed,
            fojax_default_quantiles_runs_s=qreps, band_stride=stride, band_points=int(qres.coords["time"].shape[0]),
            band_agreement_max_rel=band_agree,
            speedup_default_settings_vs_metrics_only_peer=pmed / qmed,
            peer_with_bands_s=qpmed, speedup_default_settings_vs_peer_with_bands=qpmed / qmed,
            peer_median_s=pmed, peer_runs_s=preps, peer_samples_per_s=B / pmed,
            speedup_vs_peer=pmed / med,
            cpu_s=dict(fojax_metrics_only_min=min(cpu), fojax_default_quantiles_min=min(qcpu), peer=min(pcpu),
                       peer_with_bands=min(qpcpu)),
            cpu_ratio_default_settings_vs_peer_with_bands=min(qpcpu) / min(qcpu),
            cpu_ratio_default_settings_vs_metrics_only_peer=min(pcpu) / min(qcpu),
            load_average=_common.load_average(),
            num_devices=res.attrs["num_devices"],
        )
        rows.append(row)
        print(json.dumps(row), flush=True)
    result = dict(
        status="complete",
        benchmark="study_default (issue 13): fojax.run_study on the default §3.3.7 study vs SciPy/NumPy peer",
        study=dict(plant="fault-augmented §3.3.7 (n=9, rank E=7), constant delta in [-0.3, 0.3] x constant faults",
                   observers=["PO", "FGDO"], region="Disk(-3, 2)", input="zero", horizon_s=T_END, dt_s=DT,
                   joint_states=joint_states, metrics=list(METRICS)),
        machine=info, rows=rows, load_average_at_end=_common.load_average(),
        note="measured once on a shared 2-core machine under load from other jobs (see load averages)",
    )
    _common.write_result(args.out, result)


if __name__ == "__main__":
    main()
