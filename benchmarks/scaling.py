r"""Issue 16 (and 7, item 3): how fojax scales with the state dimension n, and its memory
with the batch size B.

Study workload (the default, ``--workload study``: what users run)
--------------------------------------------------------------------
For each n in ``--dims`` (default 4 … 256): the public `fojax.run_study` on a `fojax.Study`
of an uncertain descriptor plant of size n (`study_plant`: the random stable index-1
system of `random_stable_index1`, ``p = max(1, n // 4)`` random outputs, zero input,
$A_k = A + \delta_k\,dA$ with $\delta_k \in [-0.3, 0.3]$, random initial states) with one
proportional functional observer of $z = Lx$ (``L`` 2 random rows; designed by fojax's
Riccati route before anything is timed, `design_observer`), ``--batch`` samples
(default 1,000), 1001 grid points; metrics of the estimation error only (IAE, ISE, ITAE,
peak, settling time: the 2 outputs of ẑ − z, not all n states). Against
`_study_peer.study_peer`, the vectorised NumPy/SciPy peer (``scipy.linalg.expm`` on the
``(B, N, N)`` stack, a batched recurrence), on the same samples; a check entry on
``--check-b`` samples must agree to ``<= 1e-8`` relative before anything is timed, and
the timed outputs are compared again. Each entry (design, check, fojax, peer) runs in a
fresh process (`_common.run_worker`): fojax's compile time (first call − median, caches
cleared) and each method's peak RSS (the peer's process never imports JAX) are its own.
Memory rows (``--memory-sizes``, default B = 100,000 at ``--memory-n`` = 8) run
`run_study` with ``quantiles=()`` (``metrics``) and with its default settings
(``default``: quantile bands on 201 points) against the peer computing the same. Each
row records the peer's stage times and a flop model (`flop_model`), and the run the
machine's measured peak float64 GEMM rate (`peak_gemm_gflops`), so the speed ratio can
be compared with what the machine allows. Results: ``results/scaling_latest.json``.

Kernel workload (``--workload kernel``; results ``scaling_kernel_*``)
-------------------------------------------------------------------
`fojax.run_study` on a signal study of every state (``L = I``: all K = n outputs per step,
not what an observer study asks for), IAE of ``‖x‖₁`` only. Described below.

What is measured
----------------
1. **Time vs state dimension** (the main table). For each n in ``--dims`` (default
   4, 8, 16, 32, 64, 128, 256): a random *stable, index-1* descriptor system
   $E\dot x = A_k x$ (see `random_stable_index1`), ``--batch`` samples (default 1,000),
   horizon [0, 10] s, 0.01 s output grid (1001 points), float64; per sample one metric, the
   IAE of $\|x(t)\|_1$ (trapezoid rule on the grid). Two methods:

   - fojax: `fojax.run_study(study, stepper=fojax.Exact(), save=fojax.Metrics(kinds="iae",
     reduce="sum", bands=None))` on the `fojax.Study` of ``E x' = A_k x`` from ``x0_k`` with
     ``L = I`` and no observers (public API only; fojax does its own index-1 reduction and
     exact discretisation, all inside the timed call; the `Study` is built before it);
   - peer (d) written as `peers.py` writes it, generically: the hand reduction
     $A^{\rm s}_k$, $T$ (outside the timed region, as in `peers.py`),
     ``scipy.linalg.expm(A^s_k dt)`` for the stacked samples, a recurrence vectorised over
     the batch accumulating the metric while stepping; both axis orders (batch first /
     batch last) are timed and the faster is kept.

   Before any timing the two methods are run on ``--check-b`` samples (default 100) and
   must agree to ``<= 1e-8`` relative (the entry is reported as ``disagree`` without
   timings otherwise); at the timed B they are compared again.
   Reported per n: fojax compile time (≈ first call − median; the JAX caches are cleared
   first), first call, median of up to ``--repeats`` repetitions, samples/s, the
   peer's first call and median, the ratio t_peer / t_fojax, and the peak RSS.

2. **Memory (and time) vs B** (``--memory-sizes``, default 1 … 100,000, at
   ``--memory-n`` = 8): the same two methods, fojax and (d), at each B; reported with the
   peak resident set size (``getrusage`` high-water mark) of the process, its value just
   before the first call (imports and inputs built) and the increase, so that "memory grows
   linearly with B" can be read off.

3. **Time vs B on the reference workload** is *not* re-measured: the table is copied
   from ``results/reference_workload_latest.json`` (with that file's date) when it exists.

Every entry (one method at one (n, B)) runs in a fresh Python process
(`_common.run_worker`): the compile time is a cold start, the peak RSS belongs to that
entry alone, and a hung entry is killed after ``--hard-timeout`` s and reported as such.
Results: ``results/scaling_kernel_<date>.{md,json}`` and ``results/scaling_kernel_latest.{md,json}``.

Examples::

    python benchmarks/scaling.py                                  # the study workload
    python benchmarks/scaling.py --dims 8 32 --batch 200 --memory-sizes 2000 --repeats 2
    python benchmarks/scaling.py --workload kernel --dims 4 8 --batch 100 --memory-sizes 1 100
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path


HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import _common  # noqa: E402


if __name__ == "__main__":
    _common.limit_blas_threads()  # before NumPy (see _common)
    _common.prefer_checkout()  # measure this checkout's fojax

import numpy as np  # noqa: E402
import scipy.linalg  # noqa: E402
from scipy.optimize import linear_sum_assignment  # noqa: E402
from scipy.stats import ortho_group  # noqa: E402


DIMS = (4, 8, 16, 32, 64, 128, 256)
MEMORY_SIZES = (1, 10, 100, 1_000, 10_000, 100_000)
T_END, DT = 10.0, 0.01
DELTA = 0.3  # samples: A_k = A + delta_k dA, delta_k ~ U[-DELTA, DELTA], ||dA||_2 = 1
ABSCISSA_BOUND = -1.0  # every sample's log-norm (hence every finite pole) is <= this
TOL = 1e-8
DEFAULT_SEED = 20261121


# ============================================================================ the systems
@dataclasses.dataclass(frozen=True)
class RandomLoop:
    r"""A random stable index-1 descriptor system and its hand reduction.

    $E = U\,\mathrm{diag}(I_r, 0)\,V$, $A = U A_0 V$ with $U, V$ random orthogonal; in the
    coordinates $\tilde x = Vx = [\tilde x_1; \tilde x_2]$ the algebraic rows read
    $0 = A_{0,21}\tilde x_1 + A_{0,22}\tilde x_2$ ($A_{0,22}$ invertible: index 1) and
    $\dot{\tilde x}_1 = A^{\rm s}\tilde x_1$ with
    $A^{\rm s} = A_{0,11} - A_{0,12}A_{0,22}^{-1}A_{0,21}$; $x = T\tilde x_1$ with
    $T = V^\top[I_r; -A_{0,22}^{-1}A_{0,21}]$. Samples perturb only the $(1,1)$ block,
    $\Delta A = U\,\mathrm{blkdiag}(D, 0)\,V$ with $\|D\|_2 = 1$, so $T$ is common to all.
    """

    n: int
    r: int
    E: np.ndarray  # (n, n)
    A: np.ndarray  # (n, n) nominal
    dA: np.ndarray  # (n, n) perturbation direction
    As: np.ndarray  # (r, r) nominal slow matrix
    D: np.ndarray  # (r, r) slow perturbation (As_k = As + delta_k D)
    T: np.ndarray  # (n, r) slow coordinates -> x
    shift: float  # how far A_{0,11} was shifted left


def log_norm(M: np.ndarray) -> float:
    """Logarithmic 2-norm (numerical abscissa): max eigenvalue of the symmetric part."""
    return float(np.linalg.eigvalsh(0.5 * (M + M.T)).max())


def random_stable_index1(n: int, seed: int, n_alg: int | None = None) -> RandomLoop:
    r"""A random stable index-1 descriptor system of dimension `n` (see `RandomLoop`).

    - $n_{\rm alg}$ = ``max(1, n // 4)`` algebraic equations by default ($r = n - n_{\rm alg}$);
    - $A_0$ has i.i.d. $\mathcal N(0, 1/n)$ entries, $A_{0,22} \leftarrow A_{0,22} - I$
      redrawn until its condition number is below 50 (a well-posed index-1 part);
    - $A_{0,11}$ is shifted left by the amount that puts the logarithmic norm of every
      sample's slow matrix, $\mu_2(A^{\rm s} + \delta D) \le \mu_2(A^{\rm s}) + |\delta|$,
      at or below ``ABSCISSA_BOUND`` = −1 for $|\delta| \le$ ``DELTA``. Hence every finite
      pole of every sample has real part ≤ −1 < −0.5 (and
      $\|e^{A^{\rm s}_k t}\| \le e^{-t}$: no transient growth), whatever the batch size.
    """
    rng = np.random.default_rng(seed)
    n_alg = max(1, n // 4) if n_alg is None else int(n_alg)
    r = n - n_alg
    if not 1 <= r < n:
        raise ValueError(f"need 1 <= n - n_alg < n, got n = {n}, n_alg = {n_alg}")
    A0 = rng.standard_normal((n, n)) / np.sqrt(n)
    A0[r:, r:] -= np.eye(n_alg)
    while np.linalg.cond(A0[r:, r:]) > 50.0:
        A0[r:, r:] = rng.standard_normal((n_alg, n_alg)) / np.sqrt(n) - np.eye(n_alg)
    K = np.linalg.solve(A0[r:, r:], A0[r:, :r])  # x2 = -K x1
    As = A0[:r, :r] - A0[:r, r:] @ K
    shift = log_norm(As) + DELTA - ABSCISSA_BOUND
    A0[:r, :r] -= shift * np.eye(r)
    As = As - shift * np.eye(r)
    D = rng.standard_normal((r, r))
    D /= np.linalg.norm(D, 2)
    U = ortho_group.rvs(n, random_state=rng)
    V = ortho_group.rvs(n, random_state=rng)
    S = np.diag([1.0] * r + [0.0] * n_alg)
    Dfull = np.zeros((n, n))
    Dfull[:r, :r] = D
    T = V.T @ np.vstack([np.eye(r), -K])
    return RandomLoop(n=n, r=r, E=U @ S @ V, A=U @ A0 @ V, dA=U @ Dfull @ V, As=As, D=D, T=T, shift=shift)


@dataclasses.dataclass(frozen=True)
class Samples:
    delta: np.ndarray  # (B,)
    A: np.ndarray  # (B, n, n) descriptor matrices (fojax's input)
    x0: np.ndarray  # (B, n) consistent initial states
    As: np.ndarray  # (B, r, r) slow matrices (the peer's input)
    z0: np.ndarray  # (B, r) slow initial states


def make_samples(loop: RandomLoop, B: int, seed: int) -> Samples:
    """Sample k: ``delta_k ~ U[-DELTA, DELTA]``, slow initial state ``z0_k ~ N(0, I)``,
    ``x0_k = T z0_k`` (consistent). Two independent streams of one SeedSequence, so sample k
    is the same for every B > k."""
    s_delta, s_x0 = np.random.SeedSequence([seed, loop.n]).spawn(2)
    delta = np.random.default_rng(s_delta).uniform(-DELTA, DELTA, B)
    z0 = np.random.default_rng(s_x0).standard_normal((B, loop.r))
    A = loop.A[None] + delta[:, None, None] * loop.dA[None]
    As = loop.As[None] + delta[:, None, None] * loop.D[None]
    return Samples(delta=delta, A=A, x0=z0 @ loop.T.T, As=As, z0=z0)


def check_loop(loop: RandomLoop, samples: Samples, pencil_samples: int = 10) -> dict:
    """Independent checks: finite generalized eigenvalues of the pencils ``(A_k, E)``
    (``scipy.linalg.eigvals``, QZ) for the nominal system, the extreme ``delta = ±DELTA``
    and the first `pencil_samples` samples: exactly ``r`` finite ones (index 1 / impulse
    free) equal to ``eig(As_k)``; every sample's slow matrix: max real eigenvalue < −0.5.
    Raises ``AssertionError`` when a claim fails."""
    B = samples.A.shape[0]
    cases = [(loop.A, loop.As), (loop.A + DELTA * loop.dA, loop.As + DELTA * loop.D),
             (loop.A - DELTA * loop.dA, loop.As - DELTA * loop.D)]
    cases += [(samples.A[k], samples.As[k]) for k in range(min(B, pencil_samples))]
    worst_pencil = -np.inf
    for Ak, Ask in cases:
        lam = scipy.linalg.eigvals(Ak, loop.E)
        fin = lam[np.isfinite(lam) & (np.abs(lam) < 1e8)]
        assert fin.size == loop.r, f"{fin.size} finite poles, expected r = {loop.r} (index 1)"
        ref = np.linalg.eigvals(Ask)
        i, j = linear_sum_assignment(np.abs(fin[:, None] - ref[None, :]))
        err = np.abs(fin[i] - ref[j]).max() / max(1.0, np.abs(ref).max())
        assert err <= 1e-8, f"pencil poles differ from eig(As) by {err:.1e}"
        worst_pencil = max(worst_pencil, float(fin.real.max()))
    worst = float(np.linalg.eigvals(samples.As).real.max())
    assert worst < -0.5 and worst_pencil < -0.5, (worst, worst_pencil)
    return {
        "n": loop.n,
        "r": loop.r,
        "n_alg": loop.n - loop.r,
        "max_real_finite_pole_pencil": worst_pencil,
        "max_real_slow_eig_all_samples": worst,
        "nominal_fastest_pole": float(np.abs(np.linalg.eigvals(loop.As)).max()),
        "shift": loop.shift,
    }


# ============================================================================ the methods
def grid() -> np.ndarray:
    return np.linspace(0.0, T_END, int(round(T_END / DT)) + 1)


# Peer (d) for this study's single metric: deliberately its own copy of the recurrences of
# `peers.expm_batch_first`/`expm_batch_last` (which accumulate the reference workload's two
# metrics); both are timed code, and sharing one loop would change what either study times.
def expm_batch_first(As, T, z0, dt=DT, n_points=None):
    """Peer (d), ``(B, r)`` layout: ``Z <- einsum('bij,bj->bi', Phi, Z)``; IAE of |T z|_1."""
    n_points = grid().size if n_points is None else n_points
    Phi = scipy.linalg.expm(As * dt)  # SciPy maps over the leading axis
    Z = z0.copy()
    f0 = np.abs(Z @ T.T).sum(1)
    acc = 0.5 * f0
    f = f0
    for _ in range(n_points - 1):
        Z = np.einsum("bij,bj->bi", Phi, Z)
        f = np.abs(Z @ T.T).sum(1)
        acc += f
    return dt * (acc - 0.5 * f)


def expm_batch_last(As, T, z0, dt=DT, n_points=None):
    """Peer (d), ``(r, B)`` layout: ``Z <- einsum('ijb,jb->ib', Phi, Z)``; IAE of |T z|_1."""
    n_points = grid().size if n_points is None else n_points
    Phi = np.ascontiguousarray(np.moveaxis(scipy.linalg.expm(As * dt), 0, -1))
    Z = np.ascontiguousarray(z0.T)
    f = np.abs(T @ Z).sum(0)
    acc = 0.5 * f
    for _ in range(n_points - 1):
        Z = np.einsum("ijb,jb->ib", Phi, Z)
        f = np.abs(T @ Z).sum(0)
        acc += f
    return dt * (acc - 0.5 * f)


PEER_VARIANTS = {"batch-first": expm_batch_first, "batch-last": expm_batch_last}


def fojax_call(loop: RandomLoop, samples: Samples, chunk_size: int | None = None):
    """``() -> (B,)`` metrics (IAE of ``‖x‖₁``) with `fojax.run_study` on the signal study
    ``z = x`` of the samples (the `Study` is built here, outside the timed call; needs x64 on)."""
    import jax.numpy as jnp

    import fojax
    from fojax.studies import Family

    n = loop.n
    plant = fojax.DescriptorSystem(jnp.asarray(loop.E), jnp.asarray(loop.A), jnp.zeros((n, 1)), jnp.eye(n)[:1])
    fams = (Family(jnp.asarray(samples.A), ("plant", "A")), Family(jnp.asarray(samples.x0), ("x0",)))
    study = fojax.Study(plant, jnp.zeros(n), jnp.asarray(grid()), jnp.eye(n), uncertainty=fams)
    save = fojax.Metrics(kinds="iae", reduce="sum", bands=None)

    def call():
        res = fojax.run_study(study, stepper=fojax.Exact(), save=save, chunk_size=chunk_size, quiet=True)
        assert res.attrs["engine"] == "exact-batch", res.attrs["engine"]
        return res.metrics["iae"][0, :, 0]

    return call


# ============================================================================ worker
def worker(spec: dict) -> dict:
    """One entry in this (fresh) process: ``spec["task"]`` is "check", "fojax" or "peer".

    Memory: ``rss_before_first_call_mib`` (current RSS with the inputs built),
    ``peak_rss_first_call_mib`` (``getrusage`` high-water mark after the first call; for
    fojax it includes compilation), then the mark is reset and ``peak_rss_repeats_mib`` is
    the high-water mark over the repetitions (the steady-state working memory);
    ``rss_increase_mib`` = repeats peak − before.
    """
    n, B, seed = spec["n"], spec["B"], spec["seed"]
    if spec["task"] != "peer":  # the peer never imports JAX (its RSS is NumPy/SciPy only)
        import jax

        jax.config.update("jax_enable_x64", True)
    loop = random_stable_index1(n, seed + n)
    samples = make_samples(loop, B, seed)
    res: dict = {"task": spec["task"], "n": n, "B": B, "status": "ok"}
    if spec["task"] == "check":
        res["system"] = check_loop(loop, samples)
        out_f = np.asarray(fojax_call(loop, samples, spec.get("chunk"))())
        res["rel_diff"] = {
            v: _common.rel_diff(out_f, fn(samples.As, loop.T, samples.z0)) for v, fn in PEER_VARIANTS.items()
        }
        res["metric_range"] = [float(out_f.min()), float(out_f.max())]
        return res
    mem: dict = {}

    def after_first():
        mem["peak_rss_first_call_mib"] = _common.peak_rss_mib()
        mem["peak_reset"] = _common.reset_peak_rss()

    def timed(call):
        mem.clear()
        out, first, times = _common.time_repeated(call, spec["repeats"], spec["budget"], after_first)
        return out, first, times, dict(mem, peak_rss_repeats_mib=_common.peak_rss_mib())

    rss_before = _common.current_rss_mib()
    if spec["task"] == "fojax":
        import jax

        call = fojax_call(loop, samples, spec.get("chunk"))
        cpu = []  # CPU time of this process per call (less sensitive to other jobs than wall time)

        def call_cpu():
            c = time.process_time()
            o = call()
            cpu.append(time.process_time() - c)
            return o

        jax.clear_caches()
        out, first, times, m = timed(call_cpu)
        med = statistics.median(times)
        res.update(first_s=first, median_s=med, all_s=times, reps=len(times),
                   compile_s=max(first - med, 0.0), compile_note="first call - median (caches cleared)",
                   first_cpu_s=cpu[0], median_cpu_s=statistics.median(cpu[1:]) if len(cpu) > 1 else None)
        if len(cpu) > 1:
            res["compile_cpu_s"] = max(cpu[0] - res["median_cpu_s"], 0.0)
    else:
        cands = []
        for v in spec["variants"]:
            fn = PEER_VARIANTS[v]
            cpu = []

            def call_cpu(fn=fn, cpu=cpu):
                c = time.process_time()
                o = fn(samples.As, loop.T, samples.z0)
                cpu.append(time.process_time() - c)
                return o

            o, first, times, m = timed(call_cpu)
            cands.append((statistics.median(times), v, first, times, o, m, statistics.median(cpu)))
        med, v, first, times, out, m, med_cpu = min(cands, key=lambda c: c[0])
        res.update(first_s=first, median_s=med, all_s=times, reps=len(times), variant=v,
                   all_variants={c[1]: c[0] for c in cands}, median_cpu_s=med_cpu)
    res.update(m, rss_before_first_call_mib=rss_before, peak_rss_mib=max(m["peak_rss_first_call_mib"],
                                                                         m["peak_rss_repeats_mib"]))
    if rss_before is not None and m["peak_reset"]:
        res["rss_increase_mib"] = m["peak_rss_repeats_mib"] - rss_before
    np.save(spec["save"], np.asarray(out))
    return res


# ============================================================================ the study workload
# (the default: what users run) -- `fojax.run_study` on a Study of an uncertain descriptor
# plant of size n with a functional observer, metrics of the estimation error only
N_FUNCTIONALS = 2  # z = L x: the error has this many outputs (not all n)
QUANTILES = (0.05, 0.25, 0.5, 0.75, 0.95)  # run_study's default quantile levels
BAND_POINTS = 201  # run_study's default band_points


def band_stride(T: int, band_points: int = BAND_POINTS) -> int:
    """`fojax.studies._runner.band_stride` (restated: the peer process never imports fojax)."""
    return max(1, -(-int(T) // int(band_points)))


@dataclasses.dataclass(frozen=True)
class StudyPlant:
    r"""The plant of the study workload: `random_stable_index1` (``E``, ``A``, ``dA``) with
    ``p = max(1, n // 4)`` random outputs ``C`` and a random functional ``L`` of
    ``N_FUNCTIONALS`` rows (i.i.d. normal entries); one input column (zero input)."""

    loop: RandomLoop
    B: np.ndarray  # (n, 1)
    C: np.ndarray  # (p, n)
    L: np.ndarray  # (2, n)


def study_plant(n: int, seed: int) -> StudyPlant:
    loop = random_stable_index1(n, seed + n)
    rng = np.random.default_rng([seed, n, 2])
    return StudyPlant(loop=loop, B=rng.standard_normal((n, 1)), C=rng.standard_normal((max(1, n // 4), n)),
                      L=rng.standard_normal((N_FUNCTIONALS, n)))


def study_samples(n: int, B: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``delta`` ``(B,)`` uniform in ``[-DELTA, DELTA]`` (every sample stable, see
    `random_stable_index1`) and ``x0`` ``(B, n)`` standard normal (not consistent: fojax
    and the peer both keep its slow part in the SVD coordinates of ``E``, as
    `fojax.simulate` does); two streams of one SeedSequence, sample k the same for every B."""
    s_delta, s_x0 = np.random.SeedSequence([seed, n, 3]).spawn(2)
    return (np.random.default_rng(s_delta).uniform(-DELTA, DELTA, B),
            np.random.default_rng(s_x0).standard_normal((B, n)))


def design_observer(sp: StudyPlant, path: Path) -> dict:
    """The observer of the study (fojax, outside every timed region): a proportional
    functional observer for ``z = L x`` by the Riccati route (`design_functional_observer`,
    default region ``Disk(-2, 1)``, verified), order ``q0 = max(2, n // 2)`` (random plants
    with few outputs need about that many; raised by ``n // 4`` when the rank conditions
    fail). Saved to `path` (``.npz``, fojax's design file) and its linear matrices to
    ``path.with_suffix('.obs.npz')`` for the peer."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import fojax
    from fojax.design import design_functional_observer

    plant = fojax.DescriptorSystem(sp.loop.E, sp.loop.A, sp.B, sp.C)
    n = sp.loop.n
    q0 = max(2, n // 2)
    t = time.perf_counter()
    while True:
        try:
            d = design_functional_observer(plant, sp.L, kind="proportional", method="riccati", q0=q0)
            break
        except fojax.errors.RankConditionError:
            if q0 >= n:
                raise
            q0 = min(n, q0 + max(1, n // 4))
    design_s = time.perf_counter() - t
    d.save(path, overwrite=True)
    lm = d.observer.linear_matrices()
    np.savez(path.with_suffix(".obs.npz"), **{k: np.asarray(getattr(lm, k)) for k in ("A", "By", "C", "Dy")})
    return {"q0": int(d.observer.state_size), "design_s": design_s,
            "joint_states": int(sp.loop.r + d.observer.state_size)}


def study_peer_inputs(sp: StudyPlant, delta, x0, obs_path: Path) -> dict:
    m = np.load(obs_path)
    return dict(E=sp.loop.E, A0=sp.loop.A, dA=sp.loop.dA, C=sp.C, L=sp.L, delta=delta, x0=x0,
                obs=[tuple(m[k] for k in ("A", "By", "C", "Dy"))], ts=grid())


def study_fojax_call(sp: StudyPlant, delta, x0, design_path: Path, mode: str, chunk_size=None):
    """``() -> (metrics (5, B, K), bands (nq, T_c, K) or None)`` by the public
    `fojax.run_study` (``mode``: ``"metrics"``, ``quantiles=()``; ``"default"``: its
    default settings, quantile bands included)."""
    import jax
    import jax.numpy as jnp

    import fojax
    from fojax.studies import Family

    obs = fojax.load_design(design_path, verify=False).observer
    plant = fojax.UncertainDescriptorSystem(fojax.DescriptorSystem(sp.loop.E, sp.loop.A, sp.B, sp.C),
                                            dA=sp.loop.dA[None], delta=fojax.Constant(jnp.zeros(1)))
    fams = (Family(jax.vmap(fojax.Constant)(jnp.asarray(delta)[:, None]), ("plant", "delta")),
            Family(jnp.asarray(x0), ("x0",)))
    study = fojax.Study(plant, jnp.zeros(sp.loop.n), jnp.asarray(grid()), sp.L, None, uncertainty=fams)
    kw = dict(quiet=True, chunk_size=chunk_size)
    if mode == "metrics":
        kw["quantiles"] = ()

    def call():
        res = fojax.run_study(study, obs, **kw)
        assert res.attrs["engine"] == "exact-batch", res.attrs
        mets = np.stack([res.metrics[k][0, :, 0, :] for k in STUDY_METRICS])  # (5, B, K)
        bands = None if mode == "metrics" else res.metrics["quantiles"][0]  # (nq, T_c, K)
        return mets, bands

    return call


STUDY_METRICS = ("iae", "ise", "itae", "peak", "settling_time")


def study_agreement(a, b) -> float:
    """Largest relative difference of two metric stacks over their finite entries
    (``inf`` when the finite patterns differ)."""
    fin = np.isfinite(b)
    if not np.array_equal(np.isfinite(a), fin):
        return float("inf")
    ref = np.abs(b[fin])
    return float(np.max(np.abs(a[fin] - b[fin]) / np.maximum(ref, 1e-12 * ref.max())))


def study_worker(spec: dict) -> dict:
    """One entry of the study workload in this (fresh) process: ``spec["task"]`` is
    ``"design"``, ``"check"`` (fojax and the peer on ``B`` samples, agreement), ``"fojax"``
    or ``"peer"`` (timed, with peak RSS as `worker` records it); ``spec["mode"]``:
    ``"metrics"`` or ``"default"`` (quantile bands)."""
    from _study_peer import study_peer

    n, B, seed, mode = spec["n"], spec["B"], spec["seed"], spec.get("mode", "metrics")
    sp = study_plant(n, seed)
    design_path = Path(spec["design"])
    res: dict = {"task": spec["task"], "n": n, "B": B, "mode": mode, "status": "ok"}
    if spec["task"] == "design":
        res.update(design_observer(sp, design_path))
        return res
    if spec["task"] != "peer":  # the peer never imports JAX (its RSS is NumPy/SciPy only)
        import jax

        jax.config.update("jax_enable_x64", True)
    delta, x0 = study_samples(n, B, seed)
    d = study_peer_inputs(sp, delta, x0, design_path.with_suffix(".obs.npz"))
    bands_arg = None if mode == "metrics" else (band_stride(grid().size), QUANTILES)

    stages: dict = {}

    def peer_call():
        out = study_peer(d, bands_arg, timings=stages)
        return (out, None) if bands_arg is None else out

    if spec["task"] == "check":
        fm, fb = study_fojax_call(sp, delta, x0, design_path, mode, spec.get("chunk"))()
        pm, pb = peer_call()
        res["rel_diff"] = study_agreement(fm, pm)
        if fb is not None:
            res["bands_rel_diff"] = float(np.max(np.abs(fb - pb)) / np.max(np.abs(pb)))
        res["iae_range"] = [float(np.min(fm[0])), float(np.max(fm[0]))]
        return res
    mem: dict = {}

    def after_first():
        mem["peak_rss_first_call_mib"] = _common.peak_rss_mib()
        mem["peak_reset"] = _common.reset_peak_rss()

    rss_before = _common.current_rss_mib()
    call = study_fojax_call(sp, delta, x0, design_path, mode, spec.get("chunk")) if spec["task"] == "fojax" \
        else peer_call
    cpu = []

    def call_cpu():
        c = time.process_time()
        o = call()
        cpu.append(time.process_time() - c)
        return o

    if spec["task"] == "fojax":
        import jax

        jax.clear_caches()
    out, first, times = _common.time_repeated(call_cpu, spec["repeats"], spec["budget"], after_first,
                                              first_counts=spec["task"] == "peer")
    med = statistics.median(times)
    res.update(first_s=first, median_s=med, all_s=times, reps=len(times), first_cpu_s=cpu[0],
               median_cpu_s=statistics.median(cpu[1:]) if len(cpu) > 1 else cpu[0],
               peak_rss_repeats_mib=_common.peak_rss_mib(), rss_before_first_call_mib=rss_before, **mem)
    res["peak_rss_mib"] = max(res["peak_rss_first_call_mib"], res["peak_rss_repeats_mib"])
    if rss_before is not None and mem.get("peak_reset"):
        res["rss_increase_mib"] = res["peak_rss_repeats_mib"] - rss_before
    if spec["task"] == "fojax":
        res.update(compile_s=max(first - med, 0.0), compile_note="first call - median (caches cleared)",
                   compile_cpu_s=max(cpu[0] - res["median_cpu_s"], 0.0) if len(cpu) > 1 else None)
    else:
        res["stages_last_call_s"] = dict(stages)
    np.save(spec["save"], out[0])
    return res


def peak_gemm_gflops(sizes=(1000, 2000), repeats: int = 3) -> tuple[float, float]:
    """The machine's measured float64 GEMM rate (``numpy.matmul`` of random square matrices,
    the BLAS thread count of `_common.limit_blas_threads`: one thread), best of `repeats`
    per size, GFLOP/s (``2 k³`` flops per product), per second of wall time (under the
    same load as the rows) and per second of this process's CPU time (one core's rate)."""
    best, best_cpu = 0.0, 0.0
    rng = np.random.default_rng(0)
    for k in sizes:
        a, b = rng.standard_normal((k, k)), rng.standard_normal((k, k))
        a @ b
        for _ in range(repeats):
            t, c = time.perf_counter(), time.process_time()
            a @ b
            best = max(best, 2 * k**3 / (time.perf_counter() - t) / 1e9)
            best_cpu = max(best_cpu, 2 * k**3 / max(time.process_time() - c, 1e-9) / 1e9)
    return best, best_cpu


def flop_model(n: int, B: int, dsg: dict, peer: dict, peak: float | None, peak_cpu: float | None = None) -> dict:
    r"""Flop counts of one row (``T`` grid points, ``N = r + q_0`` joint states, ``K``
    error outputs), for the statement of what is reachable:

    - ``peer_stepping``: the peer's recurrence, exactly ``B (T-1) (2N^2 + 2KN)`` (one
      ``N × N`` and one ``K × N`` matrix-vector product per sample and step), and the rate
      it achieved (its ``stepping_s`` stage);
    - ``min_stepping``: a lower bound of any method that steps the joint loop on the grid:
      the loop matrix is block lower-triangular (the plant does not depend on the observer),
      so a step needs at least ``2 (r^2 + r q_0 + q_0^2)`` flops per sample (``Φ_{pp}``,
      ``Φ_{op}``, ``Φ_{oo}``), without the matrix exponential and the outputs;
    - ``ratio_bound_at_peak``: the peer's median time over ``min_stepping / peak`` (the
      machine's measured GEMM rate): no stepping method can beat the peer by more than this
      on this machine (an upper bound of ``t_peer / t_fojax``; computing ``Φ`` costs more);
    - ``cheapest_exact_model``: that stepping plus ``Φ`` by a block-triangular degree-7
      Padé approximant (5 product-equivalents; a model, not a bound), and the ratio the
      peer's time allows at the peak GEMM rate (wall time at the wall-time rate; CPU time
      at one core's CPU-time rate)."""
    T = grid().size
    N, q0 = dsg["joint_states"], dsg["q0"]
    r = N - q0
    K = N_FUNCTIONALS
    out = dict(T=T, N=N, r=r, q0=q0, K=K, peak_gemm_gflops=peak)
    st = B * (T - 1) * (2 * N * N + 2 * K * N)
    out["peer_stepping_gflop"] = st / 1e9
    stages = peer.get("stages_last_call_s") or {}
    if stages.get("stepping_s"):
        out["peer_stepping_gflops_achieved"] = st / stages["stepping_s"] / 1e9
        out["peer_stages_s"] = stages
    mn = B * (T - 1) * 2 * (r * r + r * q0 + q0 * q0)
    out["min_stepping_gflop"] = mn / 1e9
    # the cheapest exact method modelled: the block-triangular stepping above plus Φ by a
    # degree-7 Padé approximant (what scipy's expm picks for ||h A||_1 <= 0.95: 4 products
    # and one solve, counted as 5 products) done block-triangularly: (r³ + q0³ + r q0 N)
    # per product instead of N³; no output cost, no Φ^m for multistep passes
    cheapest = mn + B * 5 * 2 * (r**3 + q0**3 + r * q0 * N)
    out["cheapest_exact_model_gflop"] = cheapest / 1e9
    if peak:
        out["min_stepping_s_at_peak"] = mn / (peak * 1e9)
        out["ratio_bound_at_peak"] = peer["median_s"] / out["min_stepping_s_at_peak"]
        out["cheapest_exact_s_at_peak"] = cheapest / (peak * 1e9)
        out["ratio_cheapest_exact_at_peak"] = peer["median_s"] / out["cheapest_exact_s_at_peak"]
    if peak_cpu:  # CPU seconds: the peer's CPU time over the cheapest method's at one core's peak
        out["peak_gemm_gflops_cpu"] = peak_cpu
        out["cheapest_exact_cpu_s_at_peak"] = cheapest / (peak_cpu * 1e9)
        out["ratio_cheapest_exact_at_peak_cpu"] = peer["median_cpu_s"] / out["cheapest_exact_cpu_s_at_peak"]
    return out


def _run_study(args, state: dict, tmp: Path) -> int:
    state["peak_gemm_gflops"], state["peak_gemm_gflops_cpu"] = peak_gemm_gflops()
    print(f"# peak float64 GEMM (numpy, 1 BLAS thread): {state['peak_gemm_gflops']:.1f} GFLOP/s wall, "
          f"{state['peak_gemm_gflops_cpu']:.1f} per CPU second", flush=True)
    base = dict(seed=args.seed, chunk=args.chunk, repeats=args.repeats, budget=args.budget)

    def entry(task, n, B, mode, tag):
        spec = dict(base, task=task, n=n, B=B, mode=mode, design=str(tmp / f"design-{n}.npz"),
                    save=str(tmp / f"{tag}-{task}-{mode}-{n}-{B}.npy"))
        res = _common.run_worker(Path(__file__), spec, args.hard_timeout)
        if res.get("status") == "ok" and task in ("fojax", "peer"):
            res["_out"] = np.load(spec["save"])
        return res

    designed: dict = {}

    def measure(n, B, mode, tag) -> dict:
        row: dict = {"n": n, "B": B, "mode": mode, "load_average_at_start": _common.load_average()}
        if n not in designed:
            designed[n] = entry("design", n, 1, "metrics", tag)
        dsg = designed[n]
        if dsg.get("status") != "ok":
            row.update(status=f"design {dsg.get('status')}", error=dsg.get("error"), stderr=dsg.get("stderr"))
            return row
        row["observer"] = {k: dsg[k] for k in ("q0", "design_s", "joint_states")}
        chk = entry("check", n, min(args.check_b, B), mode, tag)
        if chk.get("status") != "ok":
            row.update(status=f"check {chk.get('status')}", error=chk.get("error"), stderr=chk.get("stderr"))
            return row
        row["check_B"], row["check_rel_diff"] = chk["B"], chk["rel_diff"]
        if "bands_rel_diff" in chk:
            row["check_bands_rel_diff"] = chk["bands_rel_diff"]
        if not (chk["rel_diff"] <= TOL and chk.get("bands_rel_diff", 0.0) <= TOL):
            row["status"] = f"disagree ({chk['rel_diff']:.1e}): not timed"
            return row
        f = entry("fojax", n, B, mode, tag)
        row["fojax"] = {k: v for k, v in f.items() if not k.startswith("_")}
        p = entry("peer", n, B, mode, tag) if not args.no_peer else None
        if p is not None:
            row["peer"] = {k: v for k, v in p.items() if not k.startswith("_")}
        if f.get("status") != "ok":
            row["status"] = f"fojax {f.get('status')}"
            return row
        row["status"] = "ok"
        row["load_average_at_end"] = _common.load_average()
        if p is not None and p.get("status") == "ok":
            row["rel_diff"] = study_agreement(f["_out"], p["_out"])
            row["peer_over_fojax"] = p["median_s"] / f["median_s"]
            row["peer_over_fojax_cpu"] = p["median_cpu_s"] / f["median_cpu_s"]
            row["fojax_over_peer_peak_rss"] = f["peak_rss_mib"] / p["peak_rss_mib"]
            row["flops"] = flop_model(n, B, dsg, p, state.get("peak_gemm_gflops"), state.get("peak_gemm_gflops_cpu"))
            if not row["rel_diff"] <= TOL:
                row["status"] = f"disagree at B ({row['rel_diff']:.1e})"
        return row

    for n in args.dims:
        print(f"\n## n = {n}, B = {args.batch} (study, metrics only)", flush=True)
        row = measure(n, args.batch, "metrics", "dims")
        state["dims"].append(row)
        _print_row(row)
        if not row["status"].startswith("ok"):
            state["failed"].append(f"n={n}: {row['status']}")
        write(state, "partial", name="scaling")
    for B in sorted(set(args.memory_sizes)):
        for mode in args.memory_modes:
            print(f"\n## memory: n = {args.memory_n}, B = {B}, {mode}", flush=True)
            row = measure(args.memory_n, B, mode, "mem")
            state["memory"].append(row)
            _print_row(row)
            write(state, "partial", name="scaling")
    write(state, "complete", echo=True, name="scaling")
    return 1 if state["failed"] else 0


# ============================================================================ driver
def batch_scaling_from_reference(path: Path) -> dict | None:
    """fojax and peer (d) vs B from reference_workload's JSON (not re-measured)."""
    if not path.exists():
        return None
    d = json.loads(path.read_text())
    rows = []
    for r in d.get("rows", []):
        if r.get("method") in ("fojax", "expm") and not r.get("extrapolated"):
            rows.append({k: r.get(k) for k in ("method", "label", "variant", "B", "compile_s", "first_s",
                                               "median_s", "samples_per_s", "fojax_speedup")})
    return {"file": path.name, "date": d.get("machine", {}).get("date"), "status": d.get("status"), "rows": rows}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    ap.add_argument("--dims", type=int, nargs="*", default=list(DIMS), help="state dimensions n (default 4 … 256)")
    ap.add_argument("--batch", type=int, default=1000, help="samples B of the n study (default 1000)")
    ap.add_argument("--check-b", type=int, default=100, help="samples of the agreement check before timing")
    ap.add_argument("--workload", choices=("study", "kernel"), default="study",
                    help="study (default): fojax.run_study with an observer, the product workload; kernel: "
                         "run_study on the signal study z = x (all n outputs), written as scaling_kernel_*")
    ap.add_argument("--memory-n", type=int, default=8, help="state dimension of the memory-vs-B sweep")
    ap.add_argument("--memory-sizes", type=int, nargs="*", default=None,
                    help="batch sizes of the memory-vs-B sweep (none: skip it; default: 100,000 for the "
                         "study workload, 1 ... 100,000 for the kernel workload)")
    ap.add_argument("--memory-modes", nargs="+", default=["metrics", "default"], choices=["metrics", "default"],
                    help="study workload: run_study settings of the memory rows (metrics only / default bands)")
    ap.add_argument("--no-peer", action="store_true", help="time fojax only (agreement is still checked)")
    ap.add_argument("--peer-variants", nargs="+", default=list(PEER_VARIANTS), choices=list(PEER_VARIANTS),
                    help="axis orders of peer (d) to time (the faster is kept)")
    ap.add_argument("--repeats", type=int, default=5, help="timed repetitions after the first call")
    ap.add_argument("--budget", type=float, default=60.0, help="seconds of repetitions per entry")
    ap.add_argument("--chunk", type=int, default=None, help="fojax chunk_size (default: fojax's default)")
    ap.add_argument("--hard-timeout", type=float, default=1800.0, help="kill an entry after this many seconds")
    ap.add_argument("--seed", type=int, default=DEFAULT_SEED)
    ap.add_argument("--reference-json", type=Path, default=_common.RESULTS / "reference_workload_latest.json",
                    help="where the time-vs-B table of the reference workload is read from")
    ap.add_argument("--out", type=Path, default=_common.RESULTS)
    args = ap.parse_args(argv)
    if args.worker:
        spec = json.loads(args.worker)
        _common.emit_worker_result(study_worker(spec) if "mode" in spec else worker(spec))
        return 0
    if args.memory_sizes is None:
        args.memory_sizes = [100_000] if args.workload == "study" else list(MEMORY_SIZES)
    if args.repeats < 1:
        ap.error("--repeats must be at least 1")

    info = _common.machine_info()
    print(f"# scaling ({info['date']}, {info['cpu']}, {info['cores_available']} cores)")
    state = {"info": info, "args": args, "dims": [], "memory": [], "failed": []}
    tmp = Path(tempfile.mkdtemp(prefix="fojax-scaling-"))  # the workers' outputs (.npy), removed at the end
    try:
        return _run_study(args, state, tmp) if args.workload == "study" else _run(args, state, tmp)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _run(args, state: dict, tmp: Path) -> int:
    base = dict(seed=args.seed, chunk=args.chunk, repeats=args.repeats, budget=args.budget,
                variants=args.peer_variants)

    def entry(task, n, B, tag):
        spec = dict(base, task=task, n=n, B=B, save=str(tmp / f"{tag}-{task}-{n}-{B}.npy"))
        res = _common.run_worker(Path(__file__), spec, args.hard_timeout)
        if res.get("status") == "ok" and task != "check":
            res["_out"] = np.load(spec["save"])
        return res

    def measure(n, B, tag, check_first: bool) -> dict:
        row: dict = {"n": n, "B": B, "load_average_at_start": _common.load_average()}
        if check_first:
            chk = entry("check", n, min(args.check_b, B), tag)
            if chk.get("status") != "ok":
                row.update(status=f"check {chk.get('status')}", error=chk.get("error"), stderr=chk.get("stderr"))
                return row
            row["system"] = chk["system"]
            row["check_B"] = chk["B"]
            row["check_rel_diff"] = max(chk["rel_diff"].values())
            if not row["check_rel_diff"] <= TOL:
                row["status"] = f"disagree ({row['check_rel_diff']:.1e} > {TOL:.0e}): not timed"
                return row
        f = entry("fojax", n, B, tag)
        row["fojax"] = {k: v for k, v in f.items() if not k.startswith("_")}
        p = entry("peer", n, B, tag) if not args.no_peer else None
        if p is not None:
            row["peer"] = {k: v for k, v in p.items() if not k.startswith("_")}
        if f.get("status") != "ok":
            row["status"] = f"fojax {f.get('status')}"
            return row
        row["status"] = "ok"
        row["load_average_at_end"] = _common.load_average()
        if p is not None and p.get("status") == "ok":
            row["rel_diff"] = _common.rel_diff(f["_out"], p["_out"])
            row["peer_over_fojax"] = p["median_s"] / f["median_s"]
            if p.get("median_cpu_s") and f.get("median_cpu_s"):  # CPU time of each process (load-robust)
                row["peer_over_fojax_cpu"] = p["median_cpu_s"] / f["median_cpu_s"]
            if not row["rel_diff"] <= TOL:
                row["status"] = f"disagree at B ({row['rel_diff']:.1e})"
        return row

    for n in args.dims:
        print(f"\n## n = {n}, B = {args.batch}", flush=True)
        row = measure(n, args.batch, "dims", check_first=True)
        state["dims"].append(row)
        _print_row(row)
        if not row["status"].startswith("ok"):
            state["failed"].append(f"n={n}: {row['status']}")
        write(state, "partial", name="scaling_kernel")
    if args.memory_sizes:
        print(f"\n## memory vs B (n = {args.memory_n})", flush=True)
        chk_done = False
        for B in sorted(set(args.memory_sizes)):
            row = measure(args.memory_n, B, "mem", check_first=not chk_done)
            chk_done = chk_done or "check_rel_diff" in row
            state["memory"].append(row)
            _print_row(row)
            write(state, "partial", name="scaling_kernel")
    state["reference"] = batch_scaling_from_reference(args.reference_json)
    write(state, "complete", echo=True, name="scaling_kernel")
    return 1 if state["failed"] else 0


def _print_row(row):
    f, p = row.get("fojax", {}), row.get("peer", {})
    print(
        f"  status {row['status']}; check rel diff {_common.fmt(row.get('check_rel_diff'), '.1e')}; "
        f"fojax compile {_common.fmt(f.get('compile_s'), '.2f')} s first {_common.fmt(f.get('first_s'), '.3g')} s "
        f"median {_common.fmt(f.get('median_s'), '.3g')} s peak RSS {_common.fmt(f.get('peak_rss_mib'), '.0f')} MiB; "
        f"peer (d) median {_common.fmt(p.get('median_s'), '.3g')} s peak RSS {_common.fmt(p.get('peak_rss_mib'), '.0f')} MiB; "
        f"t_peer/t_fojax {_common.fmt(row.get('peer_over_fojax'), '.3g')}",
        flush=True,
    )


def write(state: dict, status: str, echo: bool = False, name: str = "scaling") -> None:
    args = state["args"]
    for rows in (state["dims"], state["memory"]):
        for r in rows:
            for m in ("fojax", "peer"):
                if r.get(m, {}).get("median_s"):
                    r[m]["samples_per_s"] = r["B"] / r[m]["median_s"]
    if args.workload == "study":
        payload = _common.result_payload(
            name, status, state["info"], args,
            note="measured under load: a 2-core machine shared with other jobs (see the load averages)",
            workload=dict(entry_point="fojax.run_study", horizon_s=T_END, dt=DT, points=grid().size, delta=DELTA,
                          abscissa_bound=ABSCISSA_BOUND, functionals=N_FUNCTIONALS,
                          observer="proportional functional observer, Riccati route, Disk(-2, 1), q0 ~ n/2",
                          metrics=list(STUDY_METRICS), band_quantiles=list(QUANTILES), band_points=BAND_POINTS,
                          peer="_study_peer.study_peer (NumPy/SciPy, scipy.linalg.expm on the stack)", tolerance=TOL),
            peak_gemm_gflops=state.get("peak_gemm_gflops"), peak_gemm_gflops_cpu=state.get("peak_gemm_gflops_cpu"),
            dims=state["dims"], memory=state["memory"], failures=state["failed"],
        )
        _common.write_results(args.out, name, payload, render_study_markdown(payload), echo=echo)
        return
    payload = _common.result_payload(
        name,
        status,
        state["info"],
        args,
        workload=dict(entry_point="fojax.run_study (signal study z = x)", horizon_s=T_END, dt=DT,
                      points=grid().size, delta=DELTA, abscissa_bound=ABSCISSA_BOUND,
                      metric="IAE of |x|_1 (trapezoid on the grid)", tolerance=TOL),
        dims=state["dims"],
        memory=state["memory"],
        batch_scaling_reference=state.get("reference"),
        failures=state["failed"],
    )
    _common.write_results(args.out, name, payload, render_markdown(payload), echo=echo)


def render_study_markdown(d: dict) -> str:
    s, fmt = d["settings"], _common.fmt
    lines = [
        "# Scaling of fojax.run_study with the state dimension n (issue 16)",
        "",
        f"- status: {d['status']}; {d['note']}",
        *_common.machine_lines(d["machine"]),
        f"- a Study of an uncertain random stable index-1 descriptor plant (n_alg = max(1, n // 4), δ ∈ "
        f"[-{DELTA}, {DELTA}], random x0), one proportional functional observer of z = L x ({N_FUNCTIONALS} rows), "
        f"[0, {T_END:g}] s on a {DT} s grid; metrics IAE/ISE/ITAE/peak/settling time of ẑ − z; peer: "
        "NumPy/SciPy (`_study_peer`), same samples, agreement checked first; every entry a fresh process",
        "",
        "| n | mode | B | N joint | agreement | fojax compile (s) | fojax median (s) | peer median (s) | "
        "t_peer/t_fojax | CPU ratio | peak RSS fojax (MiB) | peak RSS peer (MiB) | status |",
        "|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|",
    ]
    for r in d["dims"] + d["memory"]:
        f, p = r.get("fojax", {}), r.get("peer", {})
        lines.append(
            f"| {r['n']} | {r['mode']} | {r['B']} | {r.get('observer', {}).get('joint_states', '—')} | "
            f"{fmt(r.get('rel_diff', r.get('check_rel_diff')), '.1e')} | {fmt(f.get('compile_s'), '.2f')} | "
            f"{fmt(f.get('median_s'), '.3g')} | {fmt(p.get('median_s'), '.3g')} | {fmt(r.get('peer_over_fojax'), '.3g')} | "
            f"{fmt(r.get('peer_over_fojax_cpu'), '.3g')} | {fmt(f.get('peak_rss_mib'), '.0f')} | "
            f"{fmt(p.get('peak_rss_mib'), '.0f')} | {r['status']} |"
        )
    if d["failures"]:
        lines += ["", "**Failures:** " + "; ".join(d["failures"])]
    _ = s
    return "\n".join(lines) + "\n"


def render_markdown(d: dict) -> str:
    s, fmt = d["settings"], _common.fmt
    lines = [
        "# Scaling of fojax's batched LTI simulation (issue 7)",
        "",
        f"- status: {d['status']}",
        *_common.machine_lines(d["machine"]),
        f"- float64; horizon [0, {T_END:g}] s, {DT} s grid ({grid().size} points); random stable index-1 "
        f"descriptor systems (n_alg = max(1, n // 4), every finite pole Re ≤ {ABSCISSA_BOUND}); metric: IAE of "
        f"‖x‖₁; median of up to {s['repeats']} repetitions after a separately timed first call; every entry in "
        "a fresh process",
        "",
        f"## Time vs state dimension n (B = {s['batch']})",
        "",
        "fojax = `run_study` of z = x (compile ≈ first call − median, caches cleared); (d) = "
        "`scipy.linalg.expm` per sample + vectorised recurrence (faster axis order). "
        "`t_(d)/t_fojax` > 1: fojax faster. Peak RSS = process high-water mark.",
        "",
        "| n | r | agreement | compile (s) | fojax first (s) | fojax median (s) | fojax samples/s | "
        "(d) median (s) | (d) samples/s | t_(d)/t_fojax | peak RSS fojax (MiB) | peak RSS (d) (MiB) | status |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|",
    ]
    for r in d["dims"]:
        f, p = r.get("fojax", {}), r.get("peer", {})
        lines.append(
            f"| {r['n']} | {r.get('system', {}).get('r', '—')} | {fmt(r.get('rel_diff', r.get('check_rel_diff')), '.1e')} | "
            f"{fmt(f.get('compile_s'), '.2f')} | {fmt(f.get('first_s'), '.3g')} | {fmt(f.get('median_s'), '.3g')} | "
            f"{fmt(f.get('samples_per_s'), '.3g')} | {fmt(p.get('median_s'), '.3g')} | {fmt(p.get('samples_per_s'), '.3g')} | "
            f"{fmt(r.get('peer_over_fojax'), '.3g')} | {fmt(f.get('peak_rss_mib'), '.0f')} | "
            f"{fmt(p.get('peak_rss_mib'), '.0f')} | {r['status']} |"
        )
    if d["memory"]:
        lines += [
            "",
            f"## Memory (and time) vs B (n = {s['memory_n']})",
            "",
            "RSS (MiB) of the entry's process: *before* = current RSS after imports and building the inputs; "
            "*first* = high-water mark after the first call (fojax: includes compilation); *reps* = high-water "
            "mark over the repetitions (reset after the first call: the working memory of a compiled run); "
            "*increase* = reps − before. The peer (d) process does not import JAX.",
            "",
            "| B | fojax median (s) | fojax samples/s | fojax RSS before | first | reps | increase | "
            "(d) median (s) | (d) RSS before | reps | increase | t_(d)/t_fojax | status |",
            "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|",
        ]
        for r in d["memory"]:
            f, p = r.get("fojax", {}), r.get("peer", {})
            lines.append(
                f"| {r['B']} | {fmt(f.get('median_s'), '.3g')} | {fmt(f.get('samples_per_s'), '.3g')} | "
                f"{fmt(f.get('rss_before_first_call_mib'), '.0f')} | {fmt(f.get('peak_rss_first_call_mib'), '.0f')} | "
                f"{fmt(f.get('peak_rss_repeats_mib'), '.0f')} | {fmt(f.get('rss_increase_mib'), '.1f')} | "
                f"{fmt(p.get('median_s'), '.3g')} | {fmt(p.get('rss_before_first_call_mib'), '.0f')} | "
                f"{fmt(p.get('peak_rss_repeats_mib'), '.0f')} | {fmt(p.get('rss_increase_mib'), '.1f')} | "
                f"{fmt(r.get('peer_over_fojax'), '.3g')} | {r['status']} |"
            )
    ref = d.get("batch_scaling_reference")
    lines += ["", "## Time vs B on the reference workload (copied from reference_workload's JSON)", ""]
    if not ref:
        lines.append("*not available* (run `python benchmarks/reference_workload.py` first)")
    else:
        lines += [
            f"From `{ref['file']}` dated {ref['date']} (status: {str(ref['status'])[:80]}).",
            "",
            "| B | method | compile (s) | median (s) | samples/s |",
            "|---:|---|---:|---:|---:|",
        ]
        for r in sorted(ref["rows"], key=lambda r: (r["B"], r["method"])):
            lines.append(
                f"| {r['B']} | {r['label']} | {fmt(r.get('compile_s'), '.2f')} | {fmt(r.get('median_s'), '.4g')} | "
                f"{fmt(r.get('samples_per_s'), '.4g')} |"
            )
    if d["failures"]:
        lines += ["", "**Failures:** " + "; ".join(d["failures"])]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
