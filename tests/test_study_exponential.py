"""`fojax.run_study` on the exponential engine (`fojax.Exponential`, batched ETDRK4 for
time-varying linear loops): time-varying δ(t), faults and known inputs.

**Faults with breakpoints on and between grid points.**
Oracle: every sample solved independently with SciPy — x4 eliminated by hand from the
algebraic row of the §4.1.3 plant, the 5-state ODE [x1..x3; ξ] integrated with DOP853
(rtol 1e-12, atol 1e-14) piece by piece between the fault's breakpoints, and the metrics
(IAE, ISE, ITAE, peak, settling time of ξ − [x1; x2] on the grid) written again in NumPy
from their definitions. The study: the §4.1.3 loop under state feedback with
δ(t) = a sin(ωt + φ) on entries (1,3), (2,2) of A (`sinusoidal_delta`), a sinusoidal input,
and a `FaultyPlant` fault that also enters the algebraic equation: step and
ramp-then-hold faults whose onsets and ramp ends lie on grid points and between them, on the step grid.

**Per-sample inputs and faults; convergence, plans, chunks.**
The test loop is the thesis §4.1.3 plant under state feedback with a *time-varying*
uncertainty δ_k(t) = a sin(ωt + φ) on entries (1,3), (2,2) of A, and per sample a sinusoidal
input u_k(t) and a constant fault f_k that also enters the algebraic equation (so the algebraic
state has a feedthrough from the fault), both carried by one `FaultyPlant` signal
``[f; u]`` with ``Fa = [F_a, B]``; an LTI observer is driven by y. The independent reference
eliminates x4 by hand from the algebraic row and integrates the 5-state ODE with SciPy's
DOP853 (rtol 1e-12, atol 1e-14); the metrics are the trapezoid rule on the grid. The
metrics of the joint vector ``[x; ξ]`` are read from the signal study ``z = x`` and the
observer's error ``ξ − [x1; x2]``. The LTI cases are checked against the exact engine
(`fojax.Exact`, itself checked against SciPy in ``test_study_exact.py``).
"""

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.integrate
from closed_loop_413 import ACL, AO, B0, BY, C0, DA, E, LTIObserver, X0

import fojax
from fojax import studies as S
from fojax.errors import InputError
from fojax.plant import FaultProfile, FaultyPlant

# private: the exponential kernel is tested itself
from fojax.simulation import _batch, _exponential

# private: the exponential kernel's trace counters and its problem (the plan is tested itself)
from fojax.simulation._batch import TRACE_COUNTS as BATCH_TRACES
from fojax.simulation._exponential_setup import TRACE_COUNTS
from fojax.studies import Family
from fojax.studies._exponential import exponential_problem


# bit-for-bit equality of different programs (device counts, in the per-sample tests below):
# compiled as users get it
pytestmark = pytest.mark.production_codegen


FA = np.array([[0.3], [0.0], [-0.2], [0.5]])  # row 4: the fault moves the algebraic x4
TS = np.linspace(0.0, 2.0, 51)  # grid 0.04 s; ETDRK4 steps 0.01 s (|λ|max(A0) = 39.8: 4 per interval)
U_AMP, U_OMEGA, U_PHASE, U_OFF = np.array([0.5, -0.4]), np.array([1.5, 2.5]), np.array([0.0, 0.3]), np.array([0.1, 0.0])
# onsets and ramp ends on grid points (0.52) and between them on the step grid (0.3 + 0.62 = 0.92, 1.02);
# the step onsets 1e-13 s late (a jump time off the boundary by rounding still belongs to the next
# step: the regression test of the right-limit start of a step, 2.2e-4 relative error without it)
ONSET, RISE = np.array([0.52 + 1e-13, 0.3, 1.02 + 1e-13]), np.array([0.0, 0.62, 0.0])
NU, NF = 3, 3
METRICS = ("iae", "ise", "itae", "peak", "settling_time")
SETTLE_TOL = 0.05


def make_study(key, onset=ONSET, rise=RISE):
    k1, k2 = jax.random.split(key)
    nominal = fojax.DescriptorSystem(jnp.asarray(E), jnp.asarray(ACL), jnp.asarray(B0), jnp.asarray(C0))
    template = fojax.UncertainDescriptorSystem(nominal, dA=jnp.asarray(DA),
                                               delta=fojax.Sine(jnp.zeros(1), jnp.ones(1), jnp.zeros(1)))
    plant = FaultyPlant(template, Fa=jnp.asarray(FA), fault=FaultProfile(jnp.zeros(1)))
    amp = jax.random.uniform(k2, (NF, 1), minval=0.5, maxval=1.5)
    faults = Family(jax.vmap(FaultProfile)(amp, jnp.asarray(onset), jnp.asarray(rise)), ("plant", "fault"))
    u = fojax.Sine(U_AMP, U_OMEGA, U_PHASE, U_OFF)
    return fojax.Study(plant, X0, TS, C0[:2], u,
                       uncertainty=(S.sinusoidal_delta(k1, NU, 1, amplitude=(0.0, 0.3), omega=(0.5, 5.0),
                                                       path=("plant", "base", "delta")),),
                       scenarios=(faults,), signal_names=("z1", "z2"))


OBSERVER = LTIObserver(jnp.asarray(AO), jnp.asarray(BY), jnp.asarray([0.5, -1.0]))


def oracle(study):
    """``(5, Nu, Nf, 2)`` metrics and ``(B, T, 2)`` errors, sample by sample with SciPy."""
    sine = study.uncertainty[0].values
    faults = study.scenarios[0].values
    d, a = [0, 1, 2], 3
    mets, errs = np.zeros((5, NU, NF, 2)), []
    for i in range(NU):
        da, dw, dp = (float(np.asarray(v)[i, 0]) for v in (sine.amplitude, sine.omega, sine.phase))
        for j in range(NF):
            amp, t_on, rise = float(np.asarray(faults.amplitude)[j, 0]), ONSET[j], RISE[j]

            def f(t, amp=amp, t_on=t_on, rise=rise):
                if rise > 0:
                    return amp * min(max((t - t_on) / rise, 0.0), 1.0)
                return amp if t >= t_on else 0.0

            def parts(t, xd, f=f, da=da, dw=dw, dp=dp):
                A = ACL + da * np.sin(dw * t + dp) * DA
                c = B0 @ (U_OFF + U_AMP * np.sin(U_OMEGA * t + U_PHASE)) + FA[:, 0] * f(t)
                x = np.concatenate([xd, [-(A[a, d] @ xd + c[a]) / A[a, a]]])
                return A, c, x

            def rhs(t, w, parts=parts):
                A, c, x = parts(t, w[:3])
                return np.concatenate([A[d] @ x + c[d], AO @ w[3:] + BY @ (C0 @ x)])

            cuts = sorted({TS[0], TS[-1], t_on, t_on + rise})
            w = np.concatenate([X0[:3], [0.5, -1.0]])
            traj = []
            for lo, hi in zip(cuts[:-1], cuts[1:]):
                te = TS[(TS >= lo) & (TS < hi)] if hi < TS[-1] else TS[TS >= lo]
                sol = scipy.integrate.solve_ivp(rhs, (lo, hi), w, method="DOP853", rtol=1e-12, atol=1e-14,
                                                t_eval=te, dense_output=False)
                assert sol.success
                traj.append(sol.y.T)
                w = solve_to(rhs, lo, hi, w)
            W = np.concatenate(traj)
            e = np.stack([W[k, 3:] - parts(t, W[k, :3])[2][:2] for k, t in enumerate(TS)])  # ξ − [x1; x2]
            errs.append(e)
            mets[:, i, j] = np_metrics(e)
    return mets, np.stack(errs)


def solve_to(rhs, lo, hi, w):
    sol = scipy.integrate.solve_ivp(rhs, (lo, hi), w, method="DOP853", rtol=1e-12, atol=1e-14)
    assert sol.success
    return sol.y[:, -1]


def np_metrics(e):
    h = TS[1] - TS[0]
    tr = TS - TS[0]
    ae = np.abs(e)
    trap = lambda g: h * (g.sum(axis=0) - 0.5 * (g[0] + g[-1]))  # noqa: E731
    settle = []
    for s in range(e.shape[1]):
        idx = np.nonzero(ae[:, s] > SETTLE_TOL)[0]
        if idx.size == 0:
            settle.append(0.0)
        elif idx[-1] == len(TS) - 1:
            settle.append(np.inf)
        else:
            settle.append(tr[idx[-1] + 1])
    return np.stack([trap(ae), trap(e * e), trap(tr[:, None] * ae), ae.max(axis=0), np.array(settle)])


def as_array(res):
    return np.stack([res.metrics[k][0] for k in METRICS])  # (5, Nu, Nf, 2)


@pytest.fixture(scope="module")
def study():
    return make_study(jax.random.PRNGKey(0))


@pytest.fixture(scope="module")
def result(study):
    return fojax.run_study(study, OBSERVER, quiet=True, settle_tol=SETTLE_TOL)


@pytest.fixture(scope="module")
def reference(study):
    return oracle(study)


def test_auto_takes_the_exponential_engine(result):
    assert result.attrs["engine"] == "exponential-batch"
    assert result.attrs["method"] == "exponential"
    assert np.all(result.metrics["success"])


def test_metrics_agree_with_scipy(result, reference):
    got, (ref, _) = as_array(result), reference
    np.testing.assert_array_equal(got[4], ref[4])  # settling times: grid times
    scale = np.max(np.abs(ref[:4]), axis=(1, 2), keepdims=True)
    err = np.abs(got[:4] - ref[:4]) / np.maximum(np.abs(ref[:4]), 1e-12 * scale)
    # truncation error of ETDRK4 (steps 0.01 s, 0.005 s in the initial layer): 8.6e-10
    # measured (ISE); 1.4e-8 with 0.02 s steps, it falls as h^4
    assert np.max(err) < 1e-8, np.max(err, axis=(1, 2, 3))
    # the faults and δ(t) matter: metrics differ between scenarios and uncertainty draws
    assert np.min(np.abs(np.diff(ref[0], axis=1))) > 1e-3 and np.min(np.abs(np.diff(ref[0], axis=0))) > 1e-4


def test_quantile_bands_agree_with_scipy(result, reference):
    _, errs = reference
    qs = np.quantile(errs, result.coords["quantile"], axis=0)  # (nq, T, 2)
    np.testing.assert_allclose(result.metrics["quantiles"][0], qs, rtol=0, atol=1e-8 * np.max(np.abs(errs)))


def test_quantile_bands_on_a_coarse_grid_agree_with_scipy(study, result, reference):
    # band_points=11 on 51 grid points: the kernel keeps ts[::5]; the bands are np.quantile
    # of the SciPy errors at those times, and equal the full-resolution bands there
    _, errs = reference
    res = fojax.run_study(study, OBSERVER, quiet=True, settle_tol=SETTLE_TOL, band_points=11)
    assert res.attrs["engine"] == "exponential-batch" and res.attrs["band_stride"] == 5
    assert np.array_equal(res.coords["time"], TS[::5])
    qs = np.quantile(errs, res.coords["quantile"], axis=0)[:, ::5]  # (nq, 11, 2)
    np.testing.assert_allclose(res.metrics["quantiles"][0], qs, rtol=0, atol=1e-8 * np.max(np.abs(errs)))
    assert np.array_equal(res.metrics["quantiles"], result.metrics["quantiles"][:, :, ::5])


def test_padded_chunks_do_not_change_results(study, result):
    # B = 9 in chunks of 4 (3 chunks, the last one padded) on every device
    res = fojax.run_study(study, OBSERVER, quiet=True, settle_tol=SETTLE_TOL, chunk_size=4, stepper=fojax.Exponential())
    assert res.attrs["num_chunks"] == 3 and res.attrs["engine"] == "exponential-batch"
    np.testing.assert_allclose(as_array(res), as_array(result), rtol=1e-12)


def test_no_retrace_for_new_amplitudes_frequencies_and_keys(result):
    other = make_study(jax.random.PRNGKey(7))
    before = (dict(_exponential.TRACE_COUNTS), dict(_batch.TRACE_COUNTS))
    res = fojax.run_study(other, OBSERVER, quiet=True, settle_tol=SETTLE_TOL)
    assert (dict(_exponential.TRACE_COUNTS), dict(_batch.TRACE_COUNTS)) == before
    assert res.attrs["engine"] == "exponential-batch"
    assert not np.allclose(as_array(res)[0], as_array(result)[0])


def test_off_grid_breakpoints_are_refused(study):
    # a fault onset between step points: fourth order is lost, so auto keeps diffrax
    off = make_study(jax.random.PRNGKey(0), onset=np.array([0.535, 0.3, 1.02]))
    prepared, reason = exponential_problem(off, (OBSERVER,), SETTLE_TOL, False, strict=False)
    assert prepared is None and "t = 0.535" in reason
    with pytest.raises(InputError, match="not on the step grid"):
        fojax.run_study(off, OBSERVER, quiet=True, stepper=fojax.Exponential())


# ==================================================================================================
# `fojax.run_study` with `fojax.Exponential`: batched ETDRK4 for time-varying linear loops.
# ==================================================================================================



EXPO_FA = np.array([[0.3], [0.0], [-0.2], [0.5]])  # row 4: the fault enters the algebraic equation
EXPO_TS = np.linspace(0.0, 2.0, 51)  # grid 0.04 s
B = 5
XI0 = np.array([0.7, -1.2])
EXPO_OBSERVER = LTIObserver(jnp.asarray(AO), jnp.asarray(BY), jnp.asarray(XI0))
#: the signals: x itself (a signal study) and the observer error ξ − [x1; x2]
SIGNALS = {"x": (np.eye(4), False), "e": (C0[:2], True)}
SAVE = fojax.Metrics(kinds=("iae", "ise"), bands=None)


def sample_params(seed, b=B):
    rng = np.random.default_rng(seed)
    params = dict(
        a=rng.uniform(0.0, 0.3, b),
        omega=rng.uniform(0.5, 5.0, b),
        phase=rng.uniform(0.0, 2 * np.pi, b),
        fault=rng.uniform(-1.0, 1.0, (b, 1)),
        u_amp=rng.uniform(-1.0, 1.0, (b, 2)),
        u_omega=rng.uniform(1.0, 3.0, (b, 2)),
        u_off=rng.uniform(-0.5, 0.5, (b, 2)),
    )
    x0 = X0 * (1 + 0.1 * rng.normal(size=(b, 4)))
    return params, x0


def study_expo(params, x0, L):
    """The samples as one `Study`: δ_k(t), the signal ``[f_k; u_k(t)]`` and ``x0_k`` per sample."""
    nominal = fojax.DescriptorSystem(jnp.asarray(E), jnp.asarray(ACL), jnp.asarray(B0), jnp.asarray(C0))
    zero = jnp.zeros(1)
    plant = FaultyPlant(
        fojax.UncertainDescriptorSystem(nominal, dA=jnp.asarray(DA), delta=fojax.Sine(zero, zero, zero)),
        Fa=jnp.asarray(np.hstack([EXPO_FA, B0])),
        fault=fojax.Sine(jnp.zeros(3), jnp.ones(3), jnp.zeros(3), jnp.zeros(3)),
    )
    p = {k: jnp.asarray(v) for k, v in params.items()}
    col = lambda v: v[:, None]  # noqa: E731
    delta = fojax.Sine(col(p["a"]), col(p["omega"]), col(p["phase"]))
    zb = jnp.zeros((x0.shape[0], 1))
    signal = fojax.Sine(  # [f; u]: the fault as an offset, the input a sine with an offset
        jnp.concatenate([zb, p["u_amp"]], axis=1),
        jnp.concatenate([zb + 1.0, p["u_omega"]], axis=1),
        jnp.zeros((x0.shape[0], 3)),
        jnp.concatenate([p["fault"], p["u_off"]], axis=1),
    )
    fams = (Family(delta, ("plant", "base", "delta")), Family(signal, ("plant", "fault")),
            Family(jnp.asarray(x0), ("x0",)))
    return fojax.Study(plant, X0, EXPO_TS, L, uncertainty=fams)


def run(params, x0, names=tuple(SIGNALS), **kw):
    """``{name: {"iae": (B, q), "ise": (B, q)}}`` of the studies `names`."""
    out = {}
    for name in names:
        L, observed = SIGNALS[name]
        res = fojax.run_study(study_expo(params, x0, L), EXPO_OBSERVER if observed else None, save=SAVE, quiet=True, **kw)
        assert res.attrs["engine"] == "exponential-batch" and np.all(res.metrics["success"])
        out[name] = {k: res.metrics[k][0, :, 0] for k in ("iae", "ise")}
    return out


def uniform(substeps):
    return fojax.Exponential(substeps=substeps, startup_factor=1)


def trapz(f, h):
    return h * (np.sum(f, axis=0) - 0.5 * (f[0] + f[-1]))


def scipy_reference(p, x0, ts=EXPO_TS):
    """One sample by hand: x4 from the algebraic row, the 5-state ODE [x1..x3; xi], DOP853."""
    d, a = [0, 1, 2], 3

    def matrices(t):
        A = ACL + p["a"] * np.sin(p["omega"] * t + p["phase"]) * DA
        u = p["u_off"] + p["u_amp"] * np.sin(p["u_omega"] * t)
        return A, B0 @ u + EXPO_FA @ p["fault"]

    def state(t, xd):
        A, c = matrices(t)
        return np.concatenate([xd, [-(A[a, d] @ xd + c[a]) / A[a, a]]])

    def rhs(t, w):
        A, c = matrices(t)
        x = state(t, w[:3])
        return np.concatenate([A[d] @ x + c[d], AO @ w[3:] + BY @ (C0 @ x)])

    sol = scipy.integrate.solve_ivp(
        rhs,
        (ts[0], ts[-1]),
        np.concatenate([x0[:3], XI0]),
        method="DOP853",
        rtol=1e-12,
        atol=1e-14,
        t_eval=ts,
    )
    assert sol.success
    traj = np.array([np.concatenate([state(t, w[:3]), w[3:]]) for t, w in zip(ts, sol.y.T)])
    h = ts[1] - ts[0]
    x, xi = traj[:, :4], traj[:, 4:]
    e = xi - x @ C0[:2].T
    return {name: {"iae": trapz(np.abs(v), h), "ise": trapz(v**2, h)} for name, v in (("x", x), ("e", e))}


def max_rel(out, ref):
    return max(
        float(np.max(np.abs(np.asarray(out[n][k]) - np.asarray(ref[n][k])) / np.abs(np.asarray(ref[n][k]))))
        for n in out for k in out[n]
    )


@pytest.fixture(scope="module")
def batch():
    return sample_params(3)


@pytest.fixture(scope="module")
def reference_expo(batch):
    params, x0 = batch
    refs = [scipy_reference({k: v[i] for k, v in params.items()}, x0[i]) for i in range(B)]
    return {n: {k: np.stack([r[n][k] for r in refs]) for k in ("iae", "ise")} for n in SIGNALS}


@pytest.fixture(scope="module")
def by_substeps(batch):
    """The observer error's metrics with 2, 4 and 8 uniform steps per grid interval."""
    params, x0 = batch
    return {s: run(params, x0, names=("e",), stepper=uniform(s)) for s in (2, 4, 8)}


def test_agrees_with_scipy_reference(batch, by_substeps, reference_expo):
    params, x0 = batch
    out = dict(by_substeps[8], **run(params, x0, names=("x",), stepper=uniform(8)))  # h = 0.005
    assert out["x"]["iae"].shape == (B, 4) and out["e"]["ise"].shape == (B, 2)
    assert max_rel(out, reference_expo) < 1e-8


def test_time_variation_and_faults_matter(batch, reference_expo):
    # Sanity of the comparison: with δ(t) ≡ 0 and no fault the metrics differ by far more
    # than the tolerance above, so agreement is not an accident of a weak perturbation.
    params, x0 = batch
    p0 = dict(params, a=np.zeros(B), fault=np.zeros((B, 1)))
    out0 = run(p0, x0, names=("e",), stepper=uniform(2))
    assert max_rel(out0, reference_expo) > 1e-2


def test_fourth_order_convergence(by_substeps, reference_expo):
    errs = [max_rel(by_substeps[s], reference_expo) for s in (2, 4, 8)]
    orders = np.log2(np.array(errs[:-1]) / np.array(errs[1:]))
    assert errs[-1] > 1e-12  # still far above the reference's own error
    assert np.all((orders >= 3.5) & (orders <= 4.5)), (errs, orders)


def test_startup_schedule(batch, by_substeps, reference_expo):
    # The error of the coarse schedule is made in the initial layer, where the perturbation
    # excites the fast pole (-39.8): 8 steps per interval over the first ⌈5/(39.8 · 0.04)⌉ = 4
    # intervals make 2 steps per interval ~100x more accurate, and more accurate than 4
    # everywhere with fewer steps.
    params, x0 = batch
    coarse = max_rel(by_substeps[2], reference_expo)
    graded = max_rel(run(params, x0, names=("e",), stepper=fojax.Exponential(substeps=2, startup_factor=4)),
                     reference_expo)
    assert graded < coarse / 20
    assert graded < max_rel(by_substeps[4], reference_expo)  # 124 steps vs 200


def test_no_retrace_for_new_numbers(by_substeps):
    params, x0 = sample_params(11)
    before = (dict(TRACE_COUNTS), dict(BATCH_TRACES))
    out = run(params, x0, names=("e",), stepper=uniform(4))
    assert (dict(TRACE_COUNTS), dict(BATCH_TRACES)) == before
    assert not np.allclose(out["e"]["iae"], by_substeps[4]["e"]["iae"])


def test_plan_exploits_the_structure(batch):
    # δ(t) touches two entries of A: one shared state term reading only 2 of the kept
    # components. The study's input (zero here, its map B present) and the signal [f; u] only
    # force, and the forcing writes every row (plant and observer: y3 = x4 is moved by the
    # fault). The fault also moves the algebraic x4 (u does not: B's fourth row is zero), so
    # the metrics of x have a feedthrough term from f only; the observer error ξ − [x1; x2]
    # does not read x4 and has none.
    params, x0 = batch
    (problem, _, _), _ = exponential_problem(study_expo(params, x0, C0[:2]), (EXPO_OBSERVER,), 0.05, False, strict=True)
    plan = problem.plan
    assert len(plan.keep) == 5  # 3 slow plant coordinates + 2 observer states
    assert plan.terms == ((1, "shared"),)  # the δ direction; Ā_k = A0 (common nominal)
    assert len(plan.cols) == 2 and plan.rows == tuple(range(5))
    assert plan.fterms == (0, 2, 3, 4)  # the input (term 0) and the three components of [f; u]
    assert plan.gterms == ((0, "shared"),) and plan.hterms == ()
    (problem, _, _), _ = exponential_problem(study_expo(params, x0, np.eye(4)), (), 0.05, False, strict=True)
    plan = problem.plan
    assert len(plan.keep) == 3 and plan.rows == (0, 1, 2) and plan.terms == ((1, "shared"),)
    assert plan.gterms == ((0, "shared"),) and plan.hterms == (2,)  # x4's feedthrough from f


def test_chunks_and_padding_do_not_change_results(batch, by_substeps):
    params, x0 = batch
    out = run(params, x0, names=("e",), stepper=uniform(4), chunk_size=4)  # 2 chunks, the last padded
    for k in ("iae", "ise"):
        np.testing.assert_allclose(out["e"][k], by_substeps[4]["e"][k], rtol=1e-13)


def test_device_count_does_not_change_results(batch, by_substeps):
    # conftest forces 4 host devices; the fixture ran on all of them (blocks round-robin)
    params, x0 = batch
    assert jax.device_count() >= 2
    one = run(params, x0, names=("e",), stepper=uniform(4), devices=jax.devices()[:1])
    two = run(params, x0, names=("e",), stepper=uniform(4), devices=jax.devices()[:2])
    for k in ("iae", "ise"):
        np.testing.assert_array_equal(one["e"][k], by_substeps[4]["e"][k])
        np.testing.assert_allclose(two["e"][k], by_substeps[4]["e"][k], rtol=1e-13)


# ------------------------------------------------------------------- LTI: exact stepping


def lti_study(delta, x0, L, family_of_A=False):
    plant = fojax.DescriptorSystem(jnp.asarray(E), jnp.asarray(ACL), jnp.asarray(B0), jnp.asarray(C0))
    if family_of_A:  # the same matrices for every sample, no signal: g = 0
        A = jnp.asarray(ACL)[None] + jnp.asarray(delta)[:, None, None] * jnp.asarray(DA)[None]
        fams = (Family(A, ("plant", "A")),)
    else:  # constant δ_k around the nominal δ = 0 of A0: g = δ_k ΔA w
        plant = fojax.UncertainDescriptorSystem(plant, dA=jnp.asarray(DA), delta=fojax.Constant(jnp.zeros(1)))
        fams = (Family(fojax.Constant(jnp.asarray(delta)[:, None]), ("plant", "delta")),)
    return fojax.Study(plant, X0, EXPO_TS, L, uncertainty=fams + (Family(jnp.asarray(x0), ("x0",)),))


@pytest.mark.parametrize("name", list(SIGNALS))
def test_reproduces_the_exact_engine(batch, name):
    _, x0 = batch
    L, observed = SIGNALS[name]
    obs = EXPO_OBSERVER if observed else None

    def both(st, stepper):
        exact = fojax.run_study(st, obs, save=SAVE, stepper=fojax.Exact(), quiet=True)
        expo = fojax.run_study(st, obs, save=SAVE, stepper=stepper, quiet=True)
        assert exact.attrs["engine"] == "exact-batch" and expo.attrs["engine"] == "exponential-batch"
        return max(float(np.max(np.abs(expo.metrics[k] - exact.metrics[k]) / np.abs(exact.metrics[k])))
                   for k in ("iae", "ise"))

    # (a) every sample has the same matrices (no signal): g = 0, the method is exact stepping
    assert both(lti_study(np.full(B, 0.17), x0, L, family_of_A=True), fojax.Exponential()) < 1e-12
    # (b) per-sample constant δ_k around the nominal δ = 0: g = δ_k ΔA w, ETDRK4 with h = 2 ms
    varied = np.random.default_rng(5).uniform(-0.3, 0.3, B)
    assert both(lti_study(varied, x0, L), fojax.Exponential(substeps=20)) < 1e-10


def test_observer_shapes_are_checked():
    plant = fojax.DescriptorSystem(jnp.asarray(E), jnp.asarray(ACL), C=jnp.asarray(C0))  # m = 0
    st = fojax.Study(plant, X0, EXPO_TS, C0[:2])
    with pytest.raises(fojax.errors.InputError,
                       match=r"observers\[0\].linear_matrices\(\).Bu has shape \(2, 2\), expected \(2, 0\)"):
        fojax.run_study(st, EXPO_OBSERVER, stepper=fojax.Exponential(), quiet=True)


# ------------------------------------------------------------------- errors


class ClockPlant(fojax.plant.AbstractPlant):
    """Linear in x but with an explicit time dependence (not through a signal)."""

    E: jax.Array
    A: jax.Array
    m: int = eqx.field(static=True)  # 0 inputs
    p: int = eqx.field(static=True)  # 2 outputs
    linear_in_state: ClassVar[bool] = True

    def rhs(self, t, x, u):
        return (self.A + jnp.sin(3.0 * t) * jnp.eye(2)) @ x

    def output(self, t, x, u):
        return x


E2 = jnp.diag(jnp.array([1.0, 0.0]))
A2 = jnp.array([[-1.0, 0.5], [1.0, 1.0]])
X2 = jnp.ones(2)
TS2 = jnp.linspace(0.0, 1.0, 11)


def clock_plant():
    return ClockPlant(E=E2, A=A2, m=0, p=2)


def alg_delta_plant():
    # δ(t) in the algebraic row: the reduced field is not affine in δ
    nominal = fojax.DescriptorSystem(E2, A2)
    dA = jnp.array([[0.0, 0.0], [0.0, 1.0]])
    return fojax.UncertainDescriptorSystem(nominal, dA=dA, delta=fojax.Sine(0.5, 2.0, 0.0))


@pytest.mark.parametrize(
    "make, match",
    [(clock_plant, r"misses the vector field at t = "), (alg_delta_plant, r"random signal values")],
)
def test_non_affine_plants_are_refused(make, match):
    st = fojax.Study(make(), X2, TS2, jnp.eye(2))
    with pytest.raises(fojax.errors.InputError, match=r"affine in the state and in the values of its signals") as e:
        fojax.run_study(st, stepper=fojax.Exponential(), quiet=True)
    assert e.match(match)
    # Auto keeps the adaptive path for them
    assert fojax.run_study(st, quiet=True).attrs["engine"] == "vmap-simulate"


def test_input_errors(batch):
    params, x0 = batch
    bad = study_expo(params, x0, C0[:2])
    bad = fojax.Study(bad.plant, X0, np.r_[0.0, 0.1, 0.25, 0.3], C0[:2], uncertainty=bad.uncertainty)
    with pytest.raises(fojax.errors.InputError, match=r"cannot run this study: the grid is not uniform"):
        fojax.run_study(bad, EXPO_OBSERVER, stepper=fojax.Exponential(), quiet=True)
    with pytest.raises(fojax.errors.InputError, match=r"Exponential\(substeps=...\) must be a positive integer, got 0"):
        fojax.Exponential(substeps=0)
    with pytest.raises(fojax.errors.InputError, match=r"Exponential\(startup_factor=...\) must be a positive integer"):
        fojax.Exponential(startup_factor=-1)
    with pytest.raises(fojax.errors.InputError, match=r"Exponential\(step_rate=...\) must be a positive float"):
        fojax.Exponential(step_rate=0.0)


def test_nonlinear_plants_and_observers_are_refused():
    f = lambda x, u, th: -x + th * x**2  # noqa: E731
    nl = fojax.NonlinearDescriptorSystem(E2, f, lambda x, th: x, jnp.asarray(2.0), m=0, p=2)
    with pytest.raises(fojax.errors.InputError, match=r"linear in the state.*NonlinearDescriptorSystem"):
        fojax.run_study(fojax.Study(nl, X2, TS2, jnp.eye(2)), stepper=fojax.Exponential(), quiet=True)

    class TVObserver(LTIObserver):
        def linear_matrices(self):
            return None

    obs = TVObserver(jnp.asarray(AO), jnp.asarray(BY[:, :2]), jnp.zeros(2))
    st = fojax.Study(fojax.DescriptorSystem(E2, A2, C=jnp.eye(2)), X2, TS2, jnp.eye(2))
    with pytest.raises(fojax.errors.InputError, match=r"cannot run this study: an observer is not LTI"):
        fojax.run_study(st, obs, stepper=fojax.Exponential(), quiet=True)
