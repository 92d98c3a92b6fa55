r"""The batch-last time loop's block width and vector width, swept (`fojax.run_study`).

Below ``MULTISTEP_MIN_N`` joint states, `fojax.run_study`'s exact engine steps a block of
``b`` samples together, one ``N × N`` product per grid step with the batch as the last axis
(`fojax.simulation._batch`), so the step reads all of the block's ``Φ`` (``8 N² b`` bytes)
at every step. `block_for` caps ``b`` so that ``Φ`` and the state fit in the L1 data cache
(`LOOP_BLOCK_BYTES`), and the driver compiles the chunk program with 512-bit vectors
preferred (`kernel_compiler_options`). This script measures both choices on what users run.

For each ``N`` in ``--dims``: a signal study (`fojax.Study`, no observers) of a random
stable ODE ``x' = A_k x`` of size ``N`` (``E = I``, ``A_k = A + δ_k dA``), ``L = I`` (the
metrics of every state), ``--batch`` samples, 1,001 grid points, IAE only, one device. For
each block width in ``--blocks`` the driver's block is set to it (``block_for`` patched),
and for each vector width in ``--widths`` the whole sweep runs in a fresh process with
``XLA_FLAGS=--xla_cpu_prefer_vector_width=<w>`` (which the driver then leaves alone).
Reported: the median wall time of ``--repeats`` calls after the first (the whole call, set-up
included) divided by the samples and the 1,000 grid steps, with the metrics checked equal (to
1e-12) across block widths before timing, and the width `block_for` picks. Results: ``results/loop_block_latest.json``.

    python benchmarks/loop_block.py
    python benchmarks/loop_block.py --dims 7 --blocks 32 64 128 --widths 512
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path


HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import _common  # noqa: E402


DIMS = (2, 3, 4, 5, 6, 7, 8, 9)
BLOCKS = (32, 64, 128, 256)
WIDTHS = (256, 512)


def study_of(N: int, B: int, seed: int = 0):
    """The signal study of the sweep (module docstring)."""
    import jax.numpy as jnp
    import numpy as np

    import fojax
    from fojax.studies import Family

    rng = np.random.default_rng(seed + N)
    Q = np.linalg.qr(rng.standard_normal((N, N)))[0]
    A = Q @ np.diag(-rng.uniform(0.5, 5.0, N)) @ Q.T + 0.3 * rng.standard_normal((N, N)) / np.sqrt(N)
    A -= (max(0.0, np.max(np.linalg.eigvals(A).real)) + 0.5) * np.eye(N)
    dA = np.zeros((1, N, N))
    dA[0, 0, -1] = 1.0
    plant = fojax.UncertainDescriptorSystem(fojax.DescriptorSystem(np.eye(N), A), dA=dA)
    delta = jnp.asarray(rng.uniform(-0.3, 0.3, (B, 1)))
    x0 = jnp.asarray(rng.standard_normal((B, N)))
    import jax

    fams = (Family(jax.vmap(fojax.Constant)(delta), ("plant", "delta")), Family(x0, ("x0",)))
    ts = jnp.linspace(0.0, 10.0, 1001)
    return fojax.Study(plant, x0[0], ts, np.eye(N), uncertainty=fams)


def worker(spec: dict) -> dict:
    """One vector width (this process's ``XLA_FLAGS``): every ``N`` and block width."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import numpy as np

    import fojax
    from fojax.simulation import _batch, _driver

    rows = []
    save = fojax.Metrics(kinds="iae", bands=None)
    for N in spec["dims"]:
        study = study_of(N, spec["batch"])
        picked = _batch.block_for(N, _batch.DEFAULT_BLOCK)
        ref = None
        for b in spec["blocks"]:
            _driver.block_for = lambda N_, block, b=b: b  # the block width of this entry

            def call():
                return np.asarray(fojax.run_study(study, save=save, devices=jax.devices()[:1], quiet=True,
                                                  chunk_size=spec["batch"]).metrics["iae"])

            got = call()
            if ref is None:
                ref = got
            agree = float(np.max(np.abs(got - ref) / np.abs(ref)))
            if not agree <= 1e-12:
                raise AssertionError(f"N = {N}, block {b}: metrics differ from block {spec['blocks'][0]} by {agree:.1e}")
            times = []
            for _ in range(spec["repeats"]):
                t = time.perf_counter()
                call()
                times.append(time.perf_counter() - t)
            med = statistics.median(times)
            rows.append(dict(N=N, block=b, width=spec["width"], median_s=med,
                             ns_per_sample_step=med / spec["batch"] / 1000 * 1e9, picked=b == picked,
                             max_rel_diff_vs_first_block=agree))
            print(f"width {spec['width']} N {N} block {b}: {rows[-1]['ns_per_sample_step']:.2f} ns/sample-step"
                  + (" (block_for's)" if b == picked else ""), file=sys.stderr, flush=True)
    return dict(status="complete", rows=rows)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    ap.add_argument("--dims", type=int, nargs="+", default=list(DIMS))
    ap.add_argument("--blocks", type=int, nargs="+", default=list(BLOCKS))
    ap.add_argument("--widths", type=int, nargs="+", default=list(WIDTHS))
    ap.add_argument("--batch", type=int, default=4096)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--out", type=Path, default=_common.RESULTS)
    args = ap.parse_args(argv)
    if _common.served_as_worker(args, worker):
        return 0
    info = _common.machine_info()
    rows = []
    for w in args.widths:
        os.environ["XLA_FLAGS"] = f"--xla_cpu_prefer_vector_width={w}"
        spec = dict(dims=args.dims, blocks=args.blocks, batch=args.batch, repeats=args.repeats, width=w)
        res = _common.run_worker(Path(__file__), spec, timeout=3600)
        if res.get("status") != "complete":
            print(res, file=sys.stderr)
            return 1
        rows += res["rows"]
    payload = _common.result_payload("loop_block", "complete", info, args, rows=rows)
    md = ["| N | block | vector width | call time / (B · steps), ns | block_for's |", "|---:|---:|---:|---:|---|"]
    md += [f"| {r['N']} | {r['block']} | {r['width']} | {r['ns_per_sample_step']:.2f} | {'yes' if r['picked'] else ''} |"
           for r in rows]
    _common.write_results(args.out, "loop_block", payload, "\n".join(md) + "\n", echo=True)
    return 0


if __name__ == "__main__":
    _common.limit_blas_threads()
    _common.prefer_checkout()
    sys.exit(main())
