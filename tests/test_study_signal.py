"""Signal studies: `run_study(study)` without observers reports the metrics of z = L x itself.

Oracles: (1) an independent NumPy/SciPy computation per sample: the index-1 reduction of
the descriptor plant written by hand (E = diag(1, 1, 0)), ``scipy.linalg.expm`` of the
reduced system augmented with the constant input, a plain recurrence, the trapezoidal
rule, and ``np.quantile`` over the samples; with a step fault or a time-varying δ(t),
``scipy.integrate.solve_ivp`` (DOP853, rtol 1e-12) on the same reduced ODE; (2) `fojax.simulate`
trajectories with `fojax.studies.error_metrics` (what a user computes by hand); (3) for
the §4.1.3 observer-based controller loop built with the public API
(benchmarks/_workload_study.py), the reference workload's own NumPy metrics
(benchmarks/_workload.py, `peers.expm_reference`: its hand-written loop, reduction and
trapezoid rule), to 1e-10 relative.
"""

import sys
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.integrate
import scipy.linalg

import fojax
from fojax import studies as S

# private: the batch kernel's signal handling is tested itself
from fojax.simulation import _batch


BENCH = Path(__file__).resolve().parents[1] / "benchmarks"
sys.path.insert(0, str(BENCH))

import _workload as wl  # noqa: E402
import _workload_study as ws  # noqa: E402
import peers  # noqa: E402


# bit-for-bit equality of different programs (blocks sized for the cache against one block): compiled as users get it
pytestmark = pytest.mark.production_codegen


E = np.diag([1.0, 1.0, 0.0])
A = np.array([[-1.0, 0.5, 0.2], [0.1, -2.0, 0.3], [0.2, 0.1, 1.0]])
B = np.array([[1.0], [0.0], [0.5]])
DA = np.zeros((1, 3, 3))
DA[0, 0, 1] = 1.0  # uncertainty on a differential row
L = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, -1.0]])  # z = [x1; x2 - x3] (x3 algebraic)
U0 = 0.4
TS = jnp.linspace(0.0, 2.0, 101)
NU = 4
QS = (0.1, 0.5, 0.9)
ONE = jax.devices()[:1]
METRICS = ("iae", "ise", "itae", "peak", "settling_time")


def study(seed, u=U0, delta=None):
    k1, k2 = jax.random.split(jax.random.PRNGKey(seed))
    sys_ = fojax.DescriptorSystem(E, A, B, np.eye(3))
    fam = S.constant_delta(k1, NU, 1, (-0.3, 0.3)) if delta is None else delta(k1)
    return S.Study(fojax.UncertainDescriptorSystem(sys_, dA=DA), jnp.array([1.0, -1.0, 0.0]), TS, L, u,
                   uncertainty=(fam, S.initial_conditions(k2, NU, [1.0, -1.0, 0.0], 0.2)),
                   signal_names=("x1", "x2-x3"))


def reduced(Ak):
    """Hand index-1 reduction of E x' = Ak x + B u: (A_red, B_red, T, Tu), x = T x_d + Tu u."""
    d, a = [0, 1], [2]
    Aaa = Ak[np.ix_(a, a)]
    K = -np.linalg.solve(Aaa, Ak[np.ix_(a, d)])
    Ku = -np.linalg.solve(Aaa, B[a])
    A_red = Ak[np.ix_(d, d)] + Ak[np.ix_(d, a)] @ K
    B_red = B[d] + Ak[np.ix_(d, a)] @ Ku
    T = np.vstack([np.eye(2), K])
    Tu = np.vstack([np.zeros((2, 1)), Ku])
    return A_red, B_red, T, Tu


def metrics_np(ts, z, tol=0.05):
    """The metric definitions written in NumPy (trapezoid rule; settling time on the grid)."""
    h = ts[1] - ts[0]
    a = np.abs(z)
    tr = ts - ts[0]
    trap = lambda v: h * (v.sum(0) - 0.5 * (v[0] + v[-1]))  # noqa: E731
    above = np.where(a > tol, np.arange(len(ts))[:, None], -1).max(0)
    settle = np.where(above < 0, 0.0, np.where(above == len(ts) - 1, np.inf, tr[np.minimum(above + 1, len(ts) - 1)]))
    return dict(iae=trap(a), ise=trap(z * z), itae=trap(tr[:, None] * a), peak=a.max(0), settling_time=settle)


def scipy_signals(st, u0):
    """``(B, T, 2)`` trajectories of z for every sample of `st` (constant δ, constant input)."""
    ts = np.asarray(st.ts)
    h = ts[1] - ts[0]
    out = []
    for i in range(st.num_samples):
        plant, x0 = st.sample(i, 0)
        Ak = A + float(plant.delta.value[0]) * DA[0]
        A_red, B_red, T, Tu = reduced(Ak)
        M = np.zeros((3, 3))
        M[:2, :2], M[:2, 2:] = A_red, B_red
        Phi = scipy.linalg.expm(h * M)  # [x_d; u] with u' = 0
        w = np.concatenate([np.asarray(x0)[:2], [u0]])
        zs = []
        for _ in ts:
            zs.append(L @ (T @ w[:2] + Tu[:, 0] * w[2]))
            w = Phi @ w
        out.append(np.array(zs))
    return np.array(out)


@pytest.fixture(scope="module")
def exact_run():
    st = study(0)
    before = _batch.TRACE_COUNTS["StudyProblem"]
    res = S.run_study(st, devices=ONE, save=fojax.Metrics(bands=fojax.Bands(QS, points=None)), quiet=True)
    return st, res, _batch.TRACE_COUNTS["StudyProblem"] - before


def test_signal_study_exact_matches_scipy(exact_run):
    st, res, traces = exact_run
    assert res.attrs["engine"] == "exact-batch" and res.metrics["success"].all() and traces == 1
    assert res.coords["observer"] == ("z",) and res.coords["signal"] == ("x1", "x2-x3")
    Z = scipy_signals(st, U0)
    ts = np.asarray(TS)
    for i in range(NU):
        want = metrics_np(ts, Z[i])
        for name in METRICS:
            np.testing.assert_allclose(res.metrics[name][0, i, 0], want[name], rtol=1e-10, atol=1e-13, err_msg=name)
    # the bands are the quantiles of z itself (not of -z): np.quantile over the samples
    want_q = np.quantile(Z, QS, axis=0)  # (nq, T, 2)
    np.testing.assert_allclose(res.metrics["quantiles"][0], want_q, rtol=1e-10, atol=1e-13)


def test_signal_study_equals_metrics_of_simulate_trajectories(exact_run):
    # what a user computes by hand: fojax.simulate, z = L x, error_metrics
    st, res, _ = exact_run
    for i in (0, NU - 1):
        plant, x0 = st.sample(i, 0)
        sol = fojax.simulate(plant, x0, st.ts, st.u)
        want = S.error_metrics(st.ts, sol.xs @ st.L.T)
        for name in METRICS:
            np.testing.assert_allclose(res.metrics[name][0, i, 0], want[name], rtol=1e-10, atol=1e-13, err_msg=name)


def test_signal_study_new_numbers_do_not_recompile(exact_run):
    st, res, _ = exact_run
    before = _batch.TRACE_COUNTS["StudyProblem"]
    other = study(1)  # new δ, x0 draws: same structure
    res2 = S.run_study(other, devices=ONE, save=fojax.Metrics(bands=fojax.Bands(QS, points=None)), quiet=True)
    assert _batch.TRACE_COUNTS["StudyProblem"] == before
    assert not np.allclose(res2.metrics["iae"], res.metrics["iae"])
    Z = scipy_signals(other, U0)
    np.testing.assert_allclose(res2.metrics["iae"][0, :, 0], [metrics_np(np.asarray(TS), z)["iae"] for z in Z],
                               rtol=1e-10)
    # reduce="sum": the integral of ||z||_1, the sum of the per-signal values
    summed = S.run_study(other, devices=ONE, save=fojax.Metrics(kinds="iae", reduce="sum", bands=None), quiet=True)
    np.testing.assert_allclose(summed.metrics["iae"], res2.metrics["iae"].sum(-1), rtol=1e-13)


def faulty_signals(x0, delta_of_t, ts, amp=0.7, onset=0.5):
    """``(T, 3)`` z = [x1; x2 - x3; f(t)] of the faulty plant (fault = B-direction step `amp`
    from `onset`, on the grid) by solve_ivp (DOP853, rtol 1e-12) on each side of the onset."""

    def f(t, xd, fv):
        A_red, B_red, _, _ = reduced(A + delta_of_t(t) * DA[0])
        return A_red @ xd + B_red[:, 0] * fv

    opts = dict(method="DOP853", rtol=1e-12, atol=1e-14)
    on = ts >= onset
    s1 = scipy.integrate.solve_ivp(f, (ts[0], onset), x0, t_eval=ts[~on], args=(0.0,), **opts)
    xe = scipy.integrate.solve_ivp(f, (ts[0], onset), x0, args=(0.0,), **opts).y[:, -1]
    s2 = scipy.integrate.solve_ivp(f, (onset, ts[-1]), xe, t_eval=ts[on], args=(amp,), **opts)
    xd = np.concatenate([s1.y.T, s2.y.T])
    fv = np.where(on, amp, 0.0)
    _, _, T, Tu = reduced(A)  # the algebraic row is not perturbed: x = T x_d + Tu f for every δ
    x = xd @ T.T + fv[:, None] * Tu[:, 0][None]
    return np.concatenate([x @ L.T, fv[:, None]], axis=1)


@pytest.mark.parametrize("engine", ["exact-batch", "exponential-batch"])
def test_signal_study_with_fault_targets_matches_solve_ivp(engine):
    # a step fault entering like the input (also the algebraic row) from t = 0.5 (on the grid),
    # fault_targets: z = [x1; x2 - x3; f(t)]; constant δ (exact engine) or δ(t) = a sin(ω t + φ)
    # (exponential engine)
    k1, k2 = jax.random.split(jax.random.PRNGKey(2))
    base = fojax.UncertainDescriptorSystem(fojax.DescriptorSystem(E, A, B, np.eye(3)), dA=DA)
    plant = fojax.FaultyPlant(base, Fa=B, fault=fojax.plant.FaultProfile(jnp.array([0.7]), 0.5))
    path = ("plant", "base", "delta")
    delta = (S.constant_delta(k1, NU, 1, (-0.3, 0.3), path=path) if engine == "exact-batch"
             else S.sinusoidal_delta(k1, NU, 1, amplitude=(0.1, 0.3), path=path))
    st = S.Study(plant, jnp.array([1.0, -1.0, 0.0]), TS, L, fault_targets=True,
                 uncertainty=(delta, S.initial_conditions(k2, NU, [1.0, -1.0, 0.0], 0.2)))
    res = S.run_study(st, devices=ONE, save=fojax.Metrics(bands=None), quiet=True)
    assert res.attrs["engine"] == engine and res.metrics["success"].all()
    assert res.coords["signal"] == ("z1", "z2", "f1")
    ts = np.asarray(TS)
    for i in (0, NU - 1):
        p, x0 = st.sample(i, 0)
        sig = p.base.delta
        if engine == "exact-batch":
            d = float(np.asarray(sig.value)[0])
            delta_of_t = lambda t, d=d: d  # noqa: E731
        else:
            a, w, ph = (float(np.asarray(v)[0]) for v in (sig.amplitude, sig.omega, sig.phase))
            delta_of_t = lambda t, a=a, w=w, ph=ph: a * np.sin(w * t + ph)  # noqa: E731
        want = metrics_np(ts, faulty_signals(np.asarray(x0)[:2], delta_of_t, ts))
        for name in ("iae", "ise", "itae", "peak"):
            np.testing.assert_allclose(res.metrics[name][0, i, 0], want[name], rtol=1e-7, err_msg=name)


def test_signal_study_refusals():
    st = study(0)
    with pytest.raises(fojax.errors.InputError, match="observers=None"):
        S.run_study(st, [], quiet=True)
    with pytest.raises(fojax.errors.ShapeError, match="observer_names"):
        S.run_study(st, observer_names=("a", "b"), quiet=True)
    maps = fojax.control.loop_maps(fojax.models.example_4_1_3().system, _printed_observer())
    with pytest.raises(fojax.errors.ShapeError, match="L has shape"):
        maps.signal_rows(np.zeros((2, 3)))


def _printed_observer():
    ex = fojax.models.example_4_1_3()
    Wu = np.vstack([-np.asarray(ex.E_perp) @ np.asarray(ex.B), np.zeros((3, 2))])
    Wy = np.vstack([np.zeros((1, 3)), np.eye(3)])
    return fojax.GeneralizedFunctionalObserver(ex.N, ex.J, ex.F, ex.H, ex.S, ex.G, ex.M, ex.P, ex.Q, Wu, Wy)


def test_loop_413_study_sums_to_the_reference_workload_metrics():
    # the §4.1.3 controller loop u = ẑ through the public API: closed_loop, loop_maps.signal_rows,
    # UncertainDescriptorSystem on the plant rows, the workload's own samples
    batch = wl.make_workload(12, seed=7)
    loop, rows = ws.loop_413()
    np.testing.assert_allclose(np.asarray(loop.A), wl.closed_loop_A(wl.A), rtol=0, atol=1e-13)
    np.testing.assert_array_equal(np.asarray(loop.E), wl.E_CL)
    np.testing.assert_allclose(rows, wl.full_output_rows(), rtol=0, atol=1e-13)
    res = S.run_study(ws.of_workload(batch), devices=ONE, save=fojax.Metrics(kinds="iae", bands=None), quiet=True)
    assert res.attrs["engine"] == "exact-batch" and res.metrics["success"].all()
    assert res.coords["signal"] == ws.SIGNAL_NAMES
    got, ref = ws.two_metrics(res), peers.expm_reference(batch)
    np.testing.assert_allclose(got, ref, rtol=1e-10)


def test_signal_study_vmap_engine_matches_scipy(exact_run):
    # the diffrax engine (fojax.simulate under jax.vmap, error_metrics of z): equal to the
    # SciPy oracle to the solver's tolerance (a second fojax.simulate compile is not paid here:
    # the exact engine is compared with fojax.simulate trajectories above)
    import diffrax

    st, _, _ = exact_run
    stepper = fojax.Diffrax(diffrax.Tsit5(), rtol=1e-10, atol=1e-12)
    got = S.run_study(st, stepper=stepper, devices=ONE, save=fojax.Metrics(kinds=("iae", "peak"), bands=None),
                      quiet=True)
    assert got.attrs["engine"] == "vmap-simulate" and got.metrics["success"].all()
    want = [metrics_np(np.asarray(TS), z) for z in scipy_signals(st, U0)]
    for name in ("iae", "peak"):
        np.testing.assert_allclose(got.metrics[name][0, :, 0], [w[name] for w in want], rtol=1e-8, err_msg=name)


def test_iae_only_accumulates_one_sum_and_still_flags_a_blown_up_sample():
    # kinds=("iae",): no peak accumulator (StudyProblem.computed); the success test is the
    # IAE's finiteness. Oracle: the default Metrics() run (every metric, the peak included)
    # on a scalar plant x' = δ x whose second sample overflows (e^{800 t}, t up to 2 s).
    plant = fojax.UncertainDescriptorSystem(fojax.DescriptorSystem([[1.0]], [[-1.0]], [[0.0]], [[1.0]]),
                                            dA=np.ones((1, 1, 1)))
    fam = S.Family(jax.vmap(fojax.Constant)(jnp.array([[0.0], [801.0]])), ("plant", "delta"))
    st = S.Study(plant, jnp.ones(1), TS, np.eye(1), uncertainty=(fam,))
    (problem, _, _), _ = S._exact.exact_problem(st, (), 0.05, 0, kinds=("iae",))
    assert problem.computed == ("iae",)
    one = S.run_study(st, devices=ONE, save=fojax.Metrics(kinds="iae", bands=None), quiet=True)
    full = S.run_study(st, devices=ONE, save=fojax.Metrics(bands=None), quiet=True)
    np.testing.assert_array_equal(one.metrics["success"], [[True], [False]])
    np.testing.assert_array_equal(one.metrics["success"], full.metrics["success"])
    np.testing.assert_array_equal(one.metrics["iae"], full.metrics["iae"])  # the same sums; NaN where failed
    # the trapezoid rule of e^{-t} on the grid, in closed form (a geometric sum)
    h, N = float(TS[1] - TS[0]), TS.shape[0] - 1
    r = np.exp(-h)
    want = h * ((1 - r ** (N + 1)) / (1 - r) - 0.5 * (1.0 + r**N))
    np.testing.assert_allclose(one.metrics["iae"][0, 0, 0, 0], want, rtol=1e-12)


def test_loop_413_blocks_sized_for_the_cache_do_not_change_the_metrics(monkeypatch):
    # The batch-last kernel sizes its blocks so that one block's Φ and state
    # (8 b (N² + 2N) bytes) stay in the L1 cache (`_batch.block_for`, N < MULTISTEP_MIN_N):
    # 64 samples at the loop's N = 7 instead of 256. Oracles: the workload's own NumPy
    # metrics (`peers.expm_reference`), and the same study in one block of all 160 samples,
    # bit for bit: each sample's arithmetic does not depend on the block it is stepped in.
    assert _batch.block_for(7, _batch.DEFAULT_BLOCK) == 64 and 8 * 64 * (49 + 14) <= _batch.LOOP_BLOCK_BYTES
    assert _batch.block_for(3, _batch.DEFAULT_BLOCK) == _batch.DEFAULT_BLOCK  # tiny loops: unchanged
    batch = wl.make_workload(160, seed=11)
    st = ws.of_workload(batch)
    save = fojax.Metrics(kinds="iae", bands=None)

    small = S.run_study(st, devices=ONE, save=save, quiet=True)  # blocks of 64, 64 and 32
    monkeypatch.setattr(_batch, "LOOP_BLOCK_BYTES", 2**30)
    assert _batch.block_for(7, _batch.DEFAULT_BLOCK) == _batch.DEFAULT_BLOCK
    one = S.run_study(st, devices=ONE, save=save, quiet=True)  # one block of 160
    np.testing.assert_array_equal(small.metrics["iae"], one.metrics["iae"])
    np.testing.assert_allclose(ws.two_metrics(small), peers.expm_reference(batch), rtol=1e-10)


def test_loop_413_shared_and_per_sample_output_coordinates_agree(monkeypatch):
    # The §4.1.3 uncertainty leaves the algebraic equation and the output rows alone, so every
    # sample has the first sample's metric map G0 bit for bit, and the kernel takes the host's
    # output transform S0, S0⁻¹ for the whole block (`_batch.OutputBasis`). Forcing the
    # per-sample branch (a G0 no sample has) must give the same metrics; both are checked
    # against the workload's own NumPy oracle (`peers.expm_reference`).
    batch = wl.make_workload(40, seed=5)
    st = ws.of_workload(batch)
    save = fojax.Metrics(kinds="iae", bands=None)
    shared = S.run_study(st, devices=ONE, save=save, quiet=True)
    real = _batch._output_basis

    def never_shared(G0):
        basis = real(G0)
        return eqx.tree_at(lambda b: b.G0, basis, basis.G0 + 1.0)

    from fojax.studies import _exact

    monkeypatch.setattr(_exact, "_output_basis", never_shared)
    per_sample = S.run_study(st, devices=ONE, save=save, quiet=True)
    assert np.all(shared.metrics["success"]) and np.all(per_sample.metrics["success"])
    np.testing.assert_allclose(per_sample.metrics["iae"], shared.metrics["iae"], rtol=1e-12)
    for res in (shared, per_sample):
        np.testing.assert_allclose(ws.two_metrics(res), peers.expm_reference(batch), rtol=1e-10)
