"""`fojax.run_study` on the exact batch-last kernel (`fojax.Exact`): LTI samples, known signals,
metrics accumulated in the loop.

**Known signals and faults.**
Oracles: (1) the path `run_study` took before (one `fojax.simulate` per sample, exact
matrix-exponential stepping with Gauss–Legendre input quadrature, or diffrax at tight
tolerances for faults with onsets between grid points) followed by `error_metrics`;
(2) an independent NumPy/SciPy computation: index-1 reduction by the SVD of ``E``,
``scipy.linalg.expm`` of the joint loop, a plain recurrence and the trapezoidal rule.

**Many LTI samples of one loop.**
Oracles: (1) `jax.vmap(fojax.simulate)` trajectories and (2) an independent SciPy
recurrence (index partition of the diagonal E by hand, `scipy.linalg.expm`, trapezoid rule),
on the thesis §4.1.3 closed loop with a per-sample parameter perturbation ``A_k = A + δ_k ΔA``,
per-sample initial states and an LTI observer driven by y. The metrics of the joint vector
``[x; ξ]`` are read from three studies of the same samples: the signal study ``z = x``
(IAE and ISE per state), the observer's error ``ξ − [x1; x2]`` and the observer state itself
(``L = 0``).
"""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
from closed_loop_413 import (  # the §4.1.3 loop shared with test_study_exponential.py
    ACL,
    AO,
    B0,
    BY,
    C0,
    DA,
    E,
    E as E413,
    LTIObserver,
    X0,
    X0 as X413,
)
from helpers import count_equations, uncertain_plant_3_3_7

import fojax
from fojax import studies as S
from fojax.design import design_functional_observer, Disk

# private: the exact kernel and its driver are tested themselves
from fojax.simulation import _batch, _driver

# private: TRACE_COUNTS (the no-retrace check), and the kernel's parts tested themselves
from fojax.simulation._batch import TRACE_COUNTS
from fojax.studies import _exact, Family


# bit-for-bit equality of different programs (chunk sizes and device counts; compile_only's program
# against the run's): compiled as users get it
pytestmark = pytest.mark.production_codegen


SIGNALS = ("z1", "z2", "f1", "f2", "f3")
TS = jnp.linspace(0.0, 1.0, 51)
METRICS = ("iae", "ise", "itae", "peak", "settling_time")


@pytest.fixture(scope="module")
def ex337():
    """The default §3.3.7 study's model: fault-augmented plant with a constant δ, PO and FGDO."""
    ex = fojax.models.example_3_3_7()
    po = design_functional_observer(ex.augmented, ex.L_aug, kind="proportional", region=Disk(-3.0, 2.0))
    fg = design_functional_observer(ex.augmented, ex.L_aug, kind="generalized", region=Disk(-3.0, 2.0))
    plant = uncertain_plant_3_3_7(ex)
    x0 = jnp.zeros(9).at[:6].set(0.5)
    return ex, (po.observer, fg.observer), plant, x0


def study337(ex337, seed, nu=3, nf=2, u=None):
    ex, _, plant, x0 = ex337
    k1, k2 = jax.random.split(jax.random.PRNGKey(seed))
    return S.Study(plant, x0, TS, ex.L_aug, u, uncertainty=(S.constant_delta(k1, nu, 1, bounds=(-0.3, 0.3)),),
                   scenarios=(S.constant_faults(k2, nf, x0, 3),), signal_names=SIGNALS)


def reference(study, observers, i, j, **opts):
    """Per-sample metrics and errors through `fojax.simulate` (the former run_study path)."""
    plant, x0 = study.sample(i, j)
    sol = fojax.simulate(plant, x0, study.ts, study.u, observers=observers, **opts)
    z = study.target(plant, study.ts, sol.xs)
    errs = [np.asarray(zh - z) for zh in sol.estimates]
    return [{k: np.asarray(v) for k, v in S.error_metrics(study.ts, e).items()} for e in errs], errs


def assert_metrics_close(res, refs, i, j, rtol):
    for o, ref in enumerate(refs):
        for name in METRICS:
            got, want = res.metrics[name][o, i, j], ref[name]
            atol = 1e-12 * max(1.0, float(np.max(np.abs(want[np.isfinite(want)]), initial=0.0)))
            assert np.allclose(got, want, rtol=rtol, atol=atol), (name, o, i, j, got, want)


def scipy_oracle(E, A, C, L, obs_mats, x0, ts, errors=False):
    """IAE/ISE/ITAE/peak per error signal of one LTI sample (zero input), in NumPy/SciPy
    (with `errors`, also the error trajectory ``(T, K)``)."""
    U, s, Vt = np.linalg.svd(E)
    r = int(np.sum(s > 1e-12 * s[0]))
    V = Vt.T
    At = U.T @ A @ V
    K = -np.linalg.solve(At[r:, r:], At[r:, :r])
    Tx = V @ np.vstack([np.eye(r), K])  # x = Tx x1
    As = np.diag(1 / s[:r]) @ (At[:r, :r] + At[:r, r:] @ K)
    G, w0 = [], [V[:, :r].T @ x0]
    sizes = [m[0].shape[0] for m in obs_mats]
    N = r + sum(sizes)
    Aj = np.zeros((N, N))
    Aj[:r, :r] = As
    off = r
    for (Ao, By, Co, Dy), sz in zip(obs_mats, sizes):
        Aj[off : off + sz, :r] = By @ C @ Tx
        Aj[off : off + sz, off : off + sz] = Ao
        g = np.zeros((Co.shape[0], N))
        g[:, :r] = (Dy @ C - L) @ Tx
        g[:, off : off + sz] = Co
        G.append(g)
        w0.append(np.zeros(sz))
        off += sz
    G = np.vstack(G)
    h = float(ts[1] - ts[0])
    Phi = scipy.linalg.expm(h * Aj)
    w = np.concatenate(w0)
    e = [G @ w]
    for _ in range(len(ts) - 1):
        w = Phi @ w
        e.append(G @ w)
    e = np.array(e)
    a = np.abs(e)
    tr = np.asarray(ts) - float(ts[0])
    trap = lambda v: np.sum(0.5 * (v[1:] + v[:-1]) * h, axis=0)  # noqa: E731
    mets = {"iae": trap(a), "ise": trap(e**2), "itae": trap(tr[:, None] * a), "peak": a.max(axis=0)}
    return (mets, e) if errors else mets


def test_default_337_study_runs_exact_and_matches_simulate_and_scipy(ex337):
    ex, observers, plant, _ = ex337
    one = jax.devices()[:1]
    study = study337(ex337, 0)
    before = dict(_batch.TRACE_COUNTS)
    res = S.run_study(study, observers, devices=one, quantiles=(0.1, 0.5, 0.9), quiet=True)
    assert res.attrs["engine"] == "exact-batch" and res.metrics["success"].all()
    compiled = _batch.TRACE_COUNTS["StudyProblem"]
    assert compiled == before.get("StudyProblem", 0) + 1
    all_errs = []
    for i in range(3):
        for j in range(2):
            refs, errs = reference(study, observers, i, j, stepper=fojax.Exact())
            assert_metrics_close(res, refs, i, j, rtol=1e-8)
            all_errs.append(errs)
    # quantile bands over all samples, from the former path's error trajectories
    for o in range(2):
        E = np.stack([e[o] for e in all_errs])
        want = np.quantile(E, (0.1, 0.5, 0.9), axis=0)
        assert np.allclose(res.metrics["quantiles"][o], want, rtol=1e-8, atol=1e-12)
    # the independent SciPy oracle on a few samples
    mats = [(np.asarray(m.A), np.asarray(m.By), np.asarray(m.C), np.asarray(m.Dy))
            for m in (o.linear_matrices() for o in observers)]
    for i, j in [(0, 0), (2, 1)]:
        p, x0 = study.sample(i, j)
        A, _, C = (np.asarray(a) for a in p.matrices(0.0))
        ref = scipy_oracle(np.asarray(p.E), A, C, np.asarray(ex.L_aug), mats, np.asarray(x0), np.asarray(TS))
        for name, want in ref.items():
            got = res.metrics[name][:, i, j].reshape(-1)
            assert np.allclose(got, want, rtol=1e-8, atol=1e-12), name
    # new numbers (δ draws, fault sizes, observer gains) reuse the compiled kernel
    other = design_functional_observer(ex.augmented, ex.L_aug, kind="generalized", region=Disk(-2.5, 1.5))
    res2 = S.run_study(study337(ex337, 1), (observers[0], other.observer), devices=one,
                       quantiles=(0.1, 0.5, 0.9), quiet=True)
    assert _batch.TRACE_COUNTS["StudyProblem"] == compiled
    assert res2.metrics["success"].all() and not np.allclose(res2.metrics["iae"], res.metrics["iae"])


def test_quantile_bands_on_the_coarse_grid_are_np_quantile_of_the_full_errors(ex337):
    # band_points=8 on 51 grid points: stride ceil(51/8) = 7, band grid ts[0], ts[7], ..., ts[49]
    # (8 points; the last step, 50, is stepped but not kept): the kernel keeps only those
    # outputs, and the bands equal np.quantile of fojax.simulate's full-resolution errors there
    ex, observers, _, _ = ex337
    one = jax.devices()[:1]
    study = study337(ex337, 3)
    res = S.run_study(study, observers, devices=one, quantiles=(0.0, 0.1, 0.5, 0.9, 1.0), band_points=8, quiet=True)
    assert res.attrs["engine"] == "exact-batch" and res.attrs["band_stride"] == 7
    assert np.array_equal(res.coords["time"], np.asarray(TS)[::7]) and res.coords["time"].shape == (8,)
    assert res.metrics["quantiles"].shape == (2, 5, 8, 5)
    all_errs = []
    for i in range(3):
        for j in range(2):
            refs, errs = reference(study, observers, i, j, stepper=fojax.Exact())
            assert_metrics_close(res, refs, i, j, rtol=1e-8)  # the metrics still use every step
            all_errs.append(errs)
    for o in range(2):
        full = np.stack([e[o] for e in all_errs])  # (B, 51, 5)
        want = np.quantile(full, res.coords["quantile"], axis=0)[:, ::7]
        assert np.allclose(res.metrics["quantiles"][o], want, rtol=1e-8, atol=1e-12)


def test_faulty_plant_steps_ramps_and_sine_input_match_tight_diffrax(ex337):
    # FaultyPlant (not LTI for fojax.simulate): step and ramp faults with onsets between
    # grid points, a sine input and a step input off the grid; all exact on the kernel.
    ex, _, _, x0 = ex337
    base = fojax.UncertainDescriptorSystem(ex.system, dA=ex.dA, delta=fojax.Constant(jnp.zeros(1)))
    plant = fojax.FaultyPlant(base, ex.Fa, ex.Fs, fault=fojax.plant.FaultProfile(jnp.zeros(3)))
    po = design_functional_observer(ex.augmented, ex.L_aug, kind="proportional", region=Disk(-3.0, 2.0))
    obs = po.observer
    key = jax.random.PRNGKey(4)
    u = fojax.Sine(jnp.array([1.0, 0.5]), jnp.array([1.0, 3.0]), 0.2, 0.1) + fojax.Step(jnp.array([0.3, -0.2]), 0.233)
    assert _exact.exactly_generated(u)
    ts = jnp.linspace(0.0, 1.0, 41)  # h = 0.025
    study = S.Study(plant, x0[:6], ts, ex.L, u,
                    uncertainty=(S.constant_delta(key, 2, 1, bounds=(-0.3, 0.3), path=("plant", "base", "delta")),),
                    scenarios=(S.fault_scenarios(key, 3, 3, onset=(0.1, 0.6), rise=(0.0, 0.3), which="all"),),
                    fault_targets=True)
    res = S.run_study(study, obs, quantiles=(), quiet=True)
    assert res.attrs["engine"] == "exact-batch" and res.metrics["success"].all()
    rises = np.asarray(study.scenarios[0].values.rise)
    assert np.any(rises > 0)
    for i, j in [(0, 0), (1, 2)]:
        refs, _ = reference(study, (obs,), i, j, stepper=fojax.Diffrax(diffrax.Tsit5(), rtol=1e-12, atol=1e-14))
        assert_metrics_close(res, refs, i, j, rtol=1e-8)


def test_413_loop_matches_simulate():
    plant = fojax.UncertainDescriptorSystem(fojax.DescriptorSystem(E413, ACL, B0, C0), dA=DA[None],
                                            delta=fojax.Constant(jnp.zeros(1)))
    obs = LTIObserver(jnp.asarray([[-2.0, 0.5], [0.0, -3.0]]), jnp.asarray([[1.0, 0.0, 0.2], [0.0, 1.0, -0.1]]),
                      jnp.zeros(2))
    ts = jnp.linspace(0.0, 2.0, 101)
    study = S.Study(plant, X413, ts, C0[:2], None,
                    uncertainty=(S.constant_delta(jax.random.PRNGKey(2), 5, 1, bounds=(-0.5, 0.5)),))
    one = jax.devices()[:1]
    res = S.run_study(study, obs, quantiles=(), quiet=True, chunk_size=2, devices=one)  # 3 chunks, padded
    assert res.attrs["engine"] == "exact-batch" and res.attrs["num_chunks"] == 3 and res.attrs["chunk_size"] == 2
    assert "quantiles" not in res.metrics
    assert res.metrics["success"].all()
    for i in range(5):
        refs, _ = reference(study, (obs,), i, 0, stepper=fojax.Exact())
        assert_metrics_close(res, refs, i, 0, rtol=1e-8)


def test_studies_that_do_not_qualify_keep_the_former_path(ex337):
    ex, observers, plant, x0 = ex337
    tv = S.Study(plant, x0, TS, ex.L_aug, None,
                 uncertainty=(S.sinusoidal_delta(jax.random.PRNGKey(0), 2, 1),), signal_names=SIGNALS)
    prepared, reason = _exact.exact_problem(tv, observers, 0.05, False)
    assert prepared is None and "not LTI" in reason
    uneven = S.Study(plant, x0, jnp.array([0.0, 0.1, 0.3]), ex.L_aug, None, signal_names=SIGNALS)
    assert _exact.exact_problem(uneven, observers, 0.05, False)[1] == "the grid is not uniform"


def test_study_loss_runs_exact_kernel_and_its_gradient_matches_finite_differences(ex337):
    # study_loss (what tune differentiates) on the exact kernel, reverse mode through it
    import equinox as eqx

    from fojax.tuning import initial_parameters, observer_from_parameters

    ex, _, plant, x0 = ex337
    d = design_functional_observer(ex.augmented, ex.L_aug, kind="generalized", region=Disk(-2.0, 1.0))
    k1, k2 = jax.random.split(jax.random.PRNGKey(7))
    study = S.Study(plant, x0, jnp.linspace(0.0, 1.0, 21), ex.L_aug, fojax.Sine(jnp.array([1.0, 0.5]), 1.0),
                    uncertainty=(S.constant_delta(k1, 2, 1, bounds=(-0.3, 0.3)),),
                    scenarios=(S.constant_faults(k2, 2, x0, 3),), signal_names=SIGNALS)
    fx, params = initial_parameters(d, parameterization="disk")
    cfg = S.SimConfig(stepper=fojax.Exact())

    def f(p, st):
        obs, _ = observer_from_parameters(fx, p)
        return S.study_loss(st, obs, cfg=cfg)

    before = _exact.TRACE_COUNTS["study_loss_exact"]
    vg = eqx.filter_jit(jax.value_and_grad(f))
    value, g = vg(params, study)
    assert _exact.TRACE_COUNTS["study_loss_exact"] == before + 1
    # the value equals the mean over samples of the former path's per-sample IAE
    obs0, _ = observer_from_parameters(fx, params)
    per = [np.mean(reference(study, (obs0,), i, j, stepper=fojax.Exact())[0][0]["iae"]) for i in range(2) for j in range(2)]
    assert np.isclose(float(value), np.mean(per), rtol=1e-10)
    eps = 1e-5
    for name in ("Theta", "Y3"):
        idx = tuple(int(i) for i in np.unravel_index(np.argmax(np.abs(g[name])), g[name].shape))
        e = jnp.zeros_like(params[name]).at[idx].set(eps)
        fd = (vg({**params, name: params[name] + e}, study)[0] - vg({**params, name: params[name] - e}, study)[0]) / (2 * eps)
        assert abs(float(g[name][idx]) - float(fd)) <= 1e-5 * abs(float(fd)), (name, float(g[name][idx]), float(fd))


def test_metrics_and_bands_do_not_change_with_chunk_size(ex337):
    # run_study streams chunks into one host array (run_batched(host=True)) so that memory
    # follows the chunk, not the batch: the numbers must not depend on the chunking. Oracle:
    # the same study in one chunk (other block widths: <= 1e-12), and run_batched without
    # `host` at the same chunk size (the same kernel calls: bit for bit).
    _, obs, _, _ = ex337
    study = study337(ex337, 5, nu=5, nf=2)  # 10 samples
    one = jax.devices()[:1]
    ref = S.run_study(study, obs, quiet=True, devices=one)
    res = S.run_study(study, obs, quiet=True, devices=one, chunk_size=4)
    assert ref.attrs["num_chunks"] == 1 and res.attrs["num_chunks"] == 3  # 4 + 4 + 2 (padded)
    assert ref.attrs["engine"] == res.attrs["engine"] == "exact-batch"
    for k in METRICS + ("quantiles", "success"):
        np.testing.assert_allclose(res.metrics[k], ref.metrics[k], rtol=1e-12, atol=0, err_msg=k)
    prepared, _ = _exact.exact_problem(study, obs, 0.05, res.attrs["band_stride"])
    problem, basis, idx = prepared
    kw = dict(chunk_size=4, block=_batch.DEFAULT_BLOCK, devices=one, basis=basis)
    streamed, layout = _driver.run_batched(problem, idx, study.ts, host=True, **kw)
    joined, _ = _driver.run_batched(problem, idx, study.ts, **kw)
    assert layout["num_chunks"] == 3
    for a, b in zip(jax.tree.leaves(streamed), jax.tree.leaves(joined), strict=True):
        assert isinstance(a, np.ndarray) and a.shape == b.shape and a.shape[-1] == 10
        np.testing.assert_array_equal(a, np.asarray(b))


@pytest.fixture(scope="module")
def multistep_study():
    """A random stable index-1 plant (n = 8, rank E = 6) with a Riccati-designed proportional
    observer of q0 = 4 states: joint size N = 10, no jumps, so `run_study` takes the
    forward kernel `_batch._multistep_block` (several steps per pass from precomputed
    powers; the per-sample reduction eliminates only the algebraic block)."""
    rng = np.random.default_rng(16)
    n, r = 8, 6
    U, _ = np.linalg.qr(rng.standard_normal((n, n)))
    V, _ = np.linalg.qr(rng.standard_normal((n, n)))
    A0 = rng.standard_normal((n, n)) / np.sqrt(n)
    A0[:r, :r] -= (np.max(np.linalg.eigvalsh(A0[:r, :r] + A0[:r, :r].T)) / 2 + 1.0) * np.eye(r)
    A0[r:, r:] = -2.0 * np.eye(n - r) + 0.1 * A0[r:, r:]
    E = U @ np.diag([1.0] * r + [0.0] * (n - r)) @ V
    A = U @ A0 @ V
    dA = 0.2 * U @ rng.standard_normal((n, n)) @ V / np.sqrt(n)
    C, L = rng.standard_normal((2, n)), rng.standard_normal((2, n))
    base = fojax.DescriptorSystem(E, A, np.zeros((n, 1)), C)
    obs = design_functional_observer(base, L, kind="proportional", method="riccati", q0=4).observer
    plant = fojax.UncertainDescriptorSystem(base, dA=dA[None], delta=fojax.Constant(jnp.zeros(1)))
    fam = S.Family(jax.vmap(fojax.Constant)(jnp.asarray([[-0.3], [0.1], [0.3]])), ("plant", "delta"))
    x0 = S.Family(jnp.asarray(rng.standard_normal((2, n))), ("x0",))
    ts = jnp.linspace(0.0, 2.0, 86)  # T - 1 = 85 = 5·16 + 5: passes plus a remainder
    study = S.Study(plant, jnp.zeros(n), ts, L, None, uncertainty=(fam,), scenarios=(x0,))
    return study, obs, (E, A, dA, C, L)


def test_multistep_kernel_matches_scipy(multistep_study, monkeypatch):
    # Issue 16: the large-N forward kernel (outputs G Φ^j w of m steps per pass, Φ^m w to move
    # on; Φ by `expm_first`; a per-sample reduction of the algebraic block only). Oracle: the
    # independent SciPy recurrence (`scipy_oracle`); bands (stride 11: m = 22 steps per pass,
    # not a power of two, kept points inside the remainder) against np.quantile of its errors.
    study, obs, (E, A, dA, C, L) = multistep_study
    one = jax.devices()[:1]
    prepared, _ = _exact.exact_problem(study, (obs,), 0.05, 0)
    problem, _, idx = prepared
    Aj = problem.joint((idx[0][0], idx[1][0]))[0]
    assert Aj.shape[0] >= _batch.MULTISTEP_MIN_N  # the multistep path, not the batch-last matvec
    res = S.run_study(study, obs, devices=one, quantiles=(), quiet=True)
    # the bands run (a structure of its own, compiled here) in block lower-triangular form,
    # the metrics run above in full form (N = 10 < TRIANGULAR_MIN_N)
    assert Aj.shape[0] < _batch.TRIANGULAR_MIN_N and problem.plant_first(Aj.shape[0]) is not None
    monkeypatch.setattr(_batch, "TRIANGULAR_MIN_N", 0)
    bands = S.run_study(study, obs, devices=one, quantiles=(0.2, 0.5, 0.8), band_points=8, quiet=True)
    assert bands.attrs["band_stride"] == 11 and res.metrics["success"].all()
    lm = obs.linear_matrices()
    mats = [tuple(np.asarray(getattr(lm, k)) for k in ("A", "By", "C", "Dy"))]
    errs = []
    for i, d in enumerate((-0.3, 0.1, 0.3)):
        for j in range(2):
            _, x0 = study.sample(i, j)
            ref, e = scipy_oracle(E, A + d * dA, C, L, mats, np.asarray(x0), np.asarray(study.ts), errors=True)
            for name, want in ref.items():
                for r_ in (res, bands):
                    np.testing.assert_allclose(r_.metrics[name][0, i, j], want, rtol=1e-8, atol=1e-14, err_msg=name)
            errs.append(e)
    want = np.quantile(np.stack(errs), (0.2, 0.5, 0.8), axis=0)[:, ::11]
    np.testing.assert_allclose(bands.metrics["quantiles"][0], want, rtol=1e-8, atol=1e-12)


def test_repeated_run_study_traces_nothing(multistep_study):
    # Issue 16 (fixed cost): a second run_study of the same structure with new numbers runs
    # compiled programs only; the shape evaluations that traced the joint system in Python
    # on every call (~10-60 ms at n = 4) are cached by structure (eval_shape_cached).
    # Oracle: the count of Python traces of StudyProblem.joint, and the results of a
    # fresh-structure computation (equal metrics for equal numbers).
    study, obs, _ = multistep_study
    one = jax.devices()[:1]
    first = S.run_study(study, obs, devices=one, quantiles=(), quiet=True)
    before = _exact.TRACE_COUNTS["StudyProblem.joint"]
    other = eqx.tree_at(lambda s: s.ts, study, study.ts * 1.5)  # new numbers, same structure
    res = S.run_study(other, obs, devices=one, quantiles=(), quiet=True)
    again = S.run_study(study, obs, devices=one, quantiles=(), quiet=True)
    assert _exact.TRACE_COUNTS["StudyProblem.joint"] == before
    assert not np.allclose(res.metrics["iae"], first.metrics["iae"])
    np.testing.assert_array_equal(again.metrics["iae"], first.metrics["iae"])


def test_compile_only_compiles_the_program_the_run_then_uses(ex337):
    """``run_study(..., compile_only=True)`` (what `fojax study` runs on a thread while it
    tunes, issue 13) compiles the chunk program and runs no sample; the run afterwards, with
    other observer numbers of the same structure (a tuned observer), compiles nothing.
    Oracle: JAX's compilation log (jax_log_compiles) of the chunk kernel, and the run's
    metrics against a plain run of the same call (equal bits)."""
    import logging

    _, (po, fg), _, _ = ex337
    study = study337(ex337, 11, nu=2, nf=3)
    one = jax.devices()[:1]
    kw = dict(observer_names=("a", "b"), devices=one, chunk_size=5, quiet=True)  # a new chunk shape
    compiled = []

    class Log(logging.Handler):
        def emit(self, record):
            if "XLA compilation of jit(_chunk_core)" in record.getMessage():
                compiled.append(record.getMessage())

    handler, logger = Log(level=logging.DEBUG), logging.getLogger("jax")
    logger.addHandler(handler)
    try:
        with jax.log_compiles(True):
            assert S.run_study(study, (po, fg), compile_only=True, **kw) is None
            assert len(compiled) == 1
            tuned = jax.tree.map(lambda a: a * (1 + 1e-3) if eqx.is_inexact_array(a) else a, fg)
            res = S.run_study(study, (po, tuned), **kw)
            assert len(compiled) == 1  # nothing compiled again
    finally:
        logger.removeHandler(handler)
    ref = S.run_study(study, (po, tuned), **kw)
    for name in METRICS:
        np.testing.assert_array_equal(res.metrics[name], ref.metrics[name])


# ==================================================================================================
# `fojax.run_study` on the exact batch kernel: many LTI samples of one loop, metrics in the loop.
# ==================================================================================================



BATCH_TS = np.linspace(0.0, 4.0, 401)
B = 7
XI0 = np.array([0.7, -1.2])
OBSERVER = LTIObserver(jnp.asarray(AO), jnp.asarray(BY), jnp.asarray(XI0))
#: the signals of the three studies: x itself, the observer error ξ − [x1; x2], ξ itself
BATCH_SIGNALS = {"x": (np.eye(4), False), "e": (C0[:2], True), "xi": (np.zeros((2, 4)), True)}
SAVE = fojax.Metrics(kinds=("iae", "ise"), bands=None)


def sample_params(seed, b=B):
    rng = np.random.default_rng(seed)
    return rng.uniform(-0.3, 0.3, b), X0 * (1 + 0.1 * rng.normal(size=(b, 4)))


def study(delta, x0, L, ts=BATCH_TS, E_k=None):
    """The samples ``A_k = A + δ_k ΔA`` (and optionally ``E_k``) from ``x0_k`` as one `Study`."""
    plant = fojax.DescriptorSystem(jnp.asarray(E), jnp.asarray(ACL), jnp.asarray(B0), jnp.asarray(C0))
    A = jnp.asarray(ACL)[None] + jnp.asarray(delta)[:, None, None] * jnp.asarray(DA)[None]
    fams = (Family(A, ("plant", "A")), Family(jnp.asarray(x0), ("x0",)))
    if E_k is not None:
        fams += (Family(jnp.asarray(E_k), ("plant", "E")),)
    return fojax.Study(plant, X0, ts, L, uncertainty=fams)


def run(delta, x0, ts=BATCH_TS, names=tuple(BATCH_SIGNALS), **kw):
    """``{name: (B, q) iae, (B, q) ise}`` of the three studies (or of `names`), and their results."""
    out, results = {}, {}
    for name in names:
        L, observed = BATCH_SIGNALS[name]
        res = fojax.run_study(study(delta, x0, L, ts), OBSERVER if observed else None, save=SAVE, stepper=fojax.Exact(), quiet=True, **kw)
        results[name] = res
        out[name] = {k: res.metrics[k][0, :, 0] for k in ("iae", "ise")}
    return out, results


def trapz(f, h):
    return h * (np.sum(f, axis=0) - 0.5 * (f[0] + f[-1]))


def host_metrics(traj, h):
    """``(T, 6)`` joint trajectory ``[x; ξ]`` -> the metrics of the three studies."""
    x, xi = traj[:, :4], traj[:, 4:]
    e = xi - x @ C0[:2].T
    return {name: {"iae": trapz(np.abs(v), h), "ise": trapz(v**2, h)} for name, v in (("x", x), ("e", e), ("xi", xi))}


def scipy_reference(delta, x0, e=1.0):
    """Hand index partition (x4 algebraic), joint ODE, scipy expm recurrence.

    `e`: the plant with E = diag(e, 1, 1, 0), i.e. the first row of A + δΔA divided by e."""
    A = ACL + delta * DA
    A[0] /= e
    d, a = [0, 1, 2], [3]
    K = -np.linalg.solve(A[np.ix_(a, a)], A[np.ix_(a, d)])  # x4 = K xd
    As = A[np.ix_(d, d)] + A[np.ix_(d, a)] @ K
    Tx = np.zeros((4, 3))
    Tx[d, :] = np.eye(3)
    Tx[a, :] = K
    Aj = np.block([[As, np.zeros((3, 2))], [BY @ C0 @ Tx, AO]])
    h = BATCH_TS[1] - BATCH_TS[0]
    Phi = scipy.linalg.expm(h * Aj)
    w = np.concatenate([x0[:3], XI0])
    ws = [w]
    for _ in range(len(BATCH_TS) - 1):
        w = Phi @ w
        ws.append(w)
    ws = np.array(ws)
    traj = np.hstack([ws[:, :3] @ Tx.T, ws[:, 3:]])
    return host_metrics(traj, h)


def assert_close(got, ref, k, rtol=1e-10):
    for name in BATCH_SIGNALS:
        for kind in ("iae", "ise"):
            np.testing.assert_allclose(got[name][kind][k], ref[name][kind], rtol=rtol, err_msg=f"{name} {kind}")


@pytest.fixture(scope="module")
def batch_result():
    delta, x0 = sample_params(0)
    before = TRACE_COUNTS["StudyProblem"]
    out, results = run(delta, x0, chunk_size=8)
    return delta, x0, out, results, TRACE_COUNTS["StudyProblem"] - before


def test_exact_engine_and_shapes(batch_result):
    _, _, out, results, _ = batch_result
    for name, res in results.items():
        assert res.attrs["engine"] == "exact-batch", name
        assert np.all(res.metrics["success"])
    assert out["x"]["iae"].shape == (B, 4) and out["e"]["ise"].shape == (B, 2) and out["xi"]["ise"].shape == (B, 2)


def test_matches_independent_scipy_recurrence(batch_result):
    delta, x0, out, _, _ = batch_result
    for k in range(B):
        assert_close(out, scipy_reference(delta[k], x0[k]), k)


def test_matches_vmapped_simulate(batch_result):
    delta, x0, out, _, _ = batch_result
    ks = slice(0, 3)

    def one(d, x):
        plant = fojax.DescriptorSystem(jnp.asarray(E), jnp.asarray(ACL) + d * jnp.asarray(DA), jnp.asarray(B0),
                                       jnp.asarray(C0))
        sol = fojax.simulate(plant, x, jnp.asarray(BATCH_TS), observers=(OBSERVER,))
        return jnp.concatenate([sol.xs, sol.observer_states[0]], axis=1)

    trajs = np.asarray(jax.vmap(one)(jnp.asarray(delta[ks]), jnp.asarray(x0[ks])))
    h = BATCH_TS[1] - BATCH_TS[0]
    for k in range(3):
        assert_close(out, host_metrics(trajs[k], h), k)


def test_second_call_with_new_numbers_does_not_retrace(batch_result):
    _, _, _, _, traces = batch_result
    assert traces == 2  # one kernel per structure: z = x, and the observer's (e and ξ differ only in L's numbers)
    delta, x0 = sample_params(1)
    before = TRACE_COUNTS["StudyProblem"]
    run(delta, x0, BATCH_TS + 1.0, chunk_size=8)
    assert TRACE_COUNTS["StudyProblem"] == before


def test_chunked_equals_unchunked_exactly(batch_result):
    delta, x0, out, _, _ = batch_result
    before = TRACE_COUNTS["StudyProblem"]
    chunked, results = run(delta, x0, chunk_size=4)  # 4 + 3 (padded)
    assert TRACE_COUNTS["StudyProblem"] == before + 2  # one kernel per structure for all chunks
    assert all(res.attrs["num_chunks"] == 2 for res in results.values())
    for name in BATCH_SIGNALS:
        for kind in ("iae", "ise"):
            np.testing.assert_array_equal(chunked[name][kind], out[name][kind])


def test_vmapped_simulate_traceable_inside_jit(batch_result):
    # `simulate`'s method resolution inspects a concrete ts with NumPy (no float() of a tracer).
    delta, x0, _, _, _ = batch_result
    ts = jnp.asarray(BATCH_TS)  # a concrete jax.Array closed over by the jitted function

    def plant_of(d):
        return fojax.DescriptorSystem(jnp.asarray(E), jnp.asarray(ACL) + d * jnp.asarray(DA), jnp.asarray(B0),
                                      jnp.asarray(C0))

    @jax.jit
    def last_states(d, x):
        return jax.vmap(lambda dk, xk: fojax.simulate(plant_of(dk), xk, ts).xs[-1])(d, x)

    got = last_states(jnp.asarray(delta[:2]), jnp.asarray(x0[:2]))
    ref = fojax.simulate(plant_of(delta[0]), jnp.asarray(x0[0]), jnp.asarray(BATCH_TS)).xs[-1]
    np.testing.assert_allclose(np.asarray(got[0]), np.asarray(ref), rtol=1e-12, atol=1e-14)


def test_refuses_what_the_exact_kernel_cannot_step(batch_result):
    delta, x0, _, _, _ = batch_result
    bad_ts = study(delta, x0, np.eye(4), BATCH_TS**2)  # not uniform: the exact kernel does not apply
    reason = fojax.studies.exact_refusal(bad_ts, ())
    assert reason is not None and "uniform" in reason
    with pytest.raises(fojax.errors.InputError, match="Metrics"):
        fojax.Metrics(kinds=("peak", "nonsense"))

    def f(x, u, th):
        return jnp.asarray(ACL) @ x

    nonlinear = fojax.NonlinearDescriptorSystem(jnp.asarray(E), f, lambda x, th: x[:3], {}, m=2, p=3)
    st = fojax.Study(nonlinear, X0, BATCH_TS, np.eye(4))
    assert "not LTI" in fojax.studies.exact_refusal(st, ())
    with pytest.raises(fojax.errors.InputError, match="linear time-invariant"):
        fojax.run_study(st, stepper=fojax.Exact(), quiet=True)


def test_output_coordinates_path_matches_scipy(batch_result):
    # Few metric rows: |x| (4 rows, rank 3 since x4 is algebraic) on the 3 slow states, and the
    # observer error (2 rows) on the 5 joint states: the kernel steps in output coordinates
    delta, x0, out, _, _ = batch_result
    # private: the path is really taken (exact_problem's output basis) and tested itself
    from fojax.simulation._batch import _output_basis
    from fojax.studies._exact import exact_problem

    A = ACL + delta[0] * DA
    Tx = np.vstack([np.eye(3), -A[3:, :3] / A[3, 3]])  # x = Tx x_d (hand index partition)
    out_map = scipy.linalg.block_diag(Tx, np.eye(2))  # (6, 5): joint state from [x_d; xi]
    MX = np.hstack([np.eye(4), np.zeros((4, 2))])  # x and the error ξ − [x1; x2] on [x; ξ]
    basis = _output_basis(np.vstack([MX, np.hstack([-C0[:2], np.eye(2)])]) @ out_map)
    assert len(basis.ind) == 5 and basis.Nc.shape == (0, 5)  # 5 independent outputs span the 5 states
    # S = [G_ind; Nc]: its leading coordinates are the outputs themselves
    np.testing.assert_allclose(basis.S0[:5], basis.G0[list(basis.ind)], rtol=1e-15, atol=0)
    np.testing.assert_allclose(basis.S0 @ basis.S0inv, np.eye(5), atol=1e-12)
    for name, (L, observed) in BATCH_SIGNALS.items():
        (_, basis, _), _ = exact_problem(study(delta, x0, L), (OBSERVER,) if observed else (), 0.05, 0)
        if name != "xi":  # ξ alone: 2 rows on 5 states, an orthonormal complement of 3 rows
            assert basis is not None, name
    for k in range(B):
        assert_close(out, scipy_reference(delta[k], x0[k]), k)


def test_independent_of_device_count(batch_result):
    # conftest forces 4 host devices: the default spreads blocks over all of them
    delta, x0, out, _, _ = batch_result
    assert jax.device_count() >= 2
    one, _ = run(delta, x0, names=("e",), chunk_size=8, devices=jax.devices()[:1])
    two, _ = run(delta, x0, names=("e",), chunk_size=2, devices=jax.devices()[:2])
    for name in ("e",):
        for kind in ("iae", "ise"):
            np.testing.assert_array_equal(one[name][kind], out[name][kind])
            np.testing.assert_array_equal(two[name][kind], out[name][kind])


def test_per_sample_E_matches_scipy(batch_result):
    # E_k = diag(e_k, 1, 1, 0): dividing the first equation by e_k gives the plant with E
    # and A's first row scaled by 1/e_k, which the independent SciPy reference uses. The
    # samples do not share E, so run_study steps them one by one (vmap of fojax.simulate).
    delta, x0, _, _, _ = batch_result
    e = np.random.default_rng(5).uniform(0.5, 2.0, B)
    E_k = np.stack([np.diag([ek, 1.0, 1.0, 0.0]) for ek in e])
    st = study(delta, x0, np.eye(4), E_k=E_k)
    res = fojax.run_study(st, save=SAVE, stepper=fojax.Exact(), quiet=True)
    assert res.attrs["engine"] == "vmap-simulate"
    for k in range(3):
        ref = scipy_reference(delta[k], x0[k], e[k])["x"]
        for kind in ("iae", "ise"):
            np.testing.assert_allclose(res.metrics[kind][0, k, 0], ref[kind], rtol=1e-10, err_msg=kind)


def test_forward_kernel_graph_does_not_grow_with_n():
    # The forward time loop of large loops (`_multistep_block`: m steps per pass as batched
    # matrix products) has a graph of the same size for every N (a batch-last matvec unrolled
    # over N columns would grow the compile time with n)
    # private: the kernel and the study problem are tested themselves
    from fojax.simulation._batch import _block_kernel
    from fojax.studies._exact import exact_problem

    def count(n, keep):
        plant = fojax.DescriptorSystem(jnp.eye(n), -jnp.eye(n), jnp.zeros((n, 1)), jnp.eye(n)[:1])
        fam = Family(-jnp.eye(n)[None].repeat(3, axis=0), ("plant", "A"))
        st = fojax.Study(plant, jnp.ones(n), jnp.linspace(0.0, 1.0, 11), jnp.eye(n), uncertainty=(fam,))
        (problem, _, idx), _ = exact_problem(st, (), 0.05, keep, kinds=("iae",))
        return count_equations(lambda p: _block_kernel(problem, p, 0.01, st.ts, None), idx)

    # from TRIANGULAR_MIN_N on (`_multistep_block`); below it `_multistep_last`'s column FMAs
    # grow linearly with N, as the step-by-step matvec below MULTISTEP_MIN_N does
    from fojax.simulation._batch import TRIANGULAR_MIN_N

    assert count(TRIANGULAR_MIN_N, 0) == count(40, 0)
    assert count(TRIANGULAR_MIN_N, 3) == count(40, 3)


def test_kernel_compiler_options_leave_a_vector_width_in_xla_flags_alone():
    # private: the driver's compile options are tested themselves. Oracle: the rule itself
    # (512-bit vectors preferred unless XLA_FLAGS already sets the width).
    from fojax.simulation._driver import kernel_compiler_options

    assert kernel_compiler_options({}) == {"xla_cpu_prefer_vector_width": 512}
    assert kernel_compiler_options({"XLA_FLAGS": "--xla_force_host_platform_device_count=4"}) == {
        "xla_cpu_prefer_vector_width": 512}
    assert kernel_compiler_options({"XLA_FLAGS": "--xla_cpu_prefer_vector_width=256"}) == {}
