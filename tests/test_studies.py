"""`fojax.Study`, `fojax.run_study` and `fojax.studies` families: compile-once batches,
agreement with single runs, sharding, gradients, I/O.

Oracles: ``np.quantile`` itself (bit for bit) for the band quantiles; closed forms of the error
metrics (IAE, ISE, ITAE, peak, settling time of e(t) = exp(-t)); single `fojax.simulate` runs of
the same samples followed by `fojax.studies.error_metrics`; the eager draws of the samplers (the
compiled samplers must draw the same bits); one device and one chunk for the sharded and chunked
runs (bit for bit); central finite differences for `study_loss`'s gradient; the trace counter
(`_runner.TRACE_COUNTS`) for compile-once.
"""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import uncertain_plant_3_3_7

import fojax
from fojax import studies as S
from fojax.design import design_functional_observer, Disk

# private: the runner's band quantiles, metrics and TRACE_COUNTS are checked
from fojax.studies import _runner


# bit-for-bit equality of different programs (sharded against unsharded, chunks, compiled samplers against eager draws): compiled as users get it
pytestmark = pytest.mark.production_codegen


SIGNALS = ("z1", "z2", "f1", "f2", "f3")
TS = jnp.linspace(0.0, 0.5, 6)
# the vmap(simulate) engine (with "auto" these sinusoidal-δ(t) studies take the exponential one)
OPTS = dict(stepper=fojax.Diffrax(diffrax.Tsit5(), rtol=1e-6, atol=1e-8))


@pytest.fixture(scope="module")
def bench():
    ex = fojax.models.example_3_3_7()
    d = design_functional_observer(ex.augmented, ex.L_aug, kind="generalized", region=Disk(-2.0, 1.0))
    plant = uncertain_plant_3_3_7(ex, delta=fojax.Sine(jnp.zeros(1), jnp.ones(1)))
    x0 = jnp.zeros(9).at[:4].set(jnp.array([1.0, -0.5, 0.5, 0.2]))
    u = fojax.Sine(jnp.array([1.0, 0.5]), jnp.array([1.0, 2.0]))
    return ex, d, plant, x0, u


def make_study(bench, key, nu, nf, ts=TS):
    ex, _, plant, x0, u = bench
    k1, k2 = jax.random.split(key)
    return S.Study(
        plant, x0, ts, ex.L_aug, u,
        uncertainty=(S.sinusoidal_delta(k1, nu, 1, amplitude=(0.0, 0.5)),),
        scenarios=(S.constant_faults(k2, nf, x0, 3),),
        signal_names=SIGNALS,
    )


def single_metrics(study, observer, i, j, **opts):
    plant, x0 = study.sample(i, j)
    sol = fojax.simulate(plant, x0, study.ts, study.u, observers=(observer,), **opts)
    z = study.target(plant, study.ts, sol.xs)
    return {k: np.asarray(v) for k, v in S.error_metrics(study.ts, sol.estimates[0] - z).items()}


def test_band_stride_and_band_quantiles_equal_np_quantile():
    # oracle: np.quantile (method "linear") itself, bit for bit, NaN and ±inf rows included
    assert S._runner.band_stride(1001, 201) == 5 and S._runner.band_stride(1001, None) == 1
    assert S._runner.band_stride(51, 8) == 7 and S._runner.band_stride(6, 201) == 1
    for bad in (1, 0, 2.5, True):
        with pytest.raises(fojax.errors.InputError, match="band_points must be an integer >= 2"):
            S._runner.band_stride(100, bad)
    rng = np.random.default_rng(0)
    E = rng.standard_normal((7, 3, 101))
    E[2, 1, 5] = np.nan
    E[4, 0, :3] = np.inf
    E[5, 2, 7] = -np.inf
    E[6] = np.round(E[6], 1)  # ties
    q = (0.0, 0.05, 0.25, 0.333, 0.5, 0.75, 0.95, 1.0)
    with np.errstate(invalid="ignore"):
        want = np.quantile(E, q, axis=-1)
        got = S._runner.band_quantiles(E, q)
        one = np.quantile(E[..., :1], q, axis=-1)
    assert got.shape == want.shape and np.array_equal(got, want, equal_nan=True)
    assert np.array_equal(S._runner.band_quantiles(E[..., :1], q), one, equal_nan=True)
    # overwrite=True (the exact engine's own buffer) sorts in place: same numbers; a
    # read-only array is copied, never written
    F = E.copy()
    with np.errstate(invalid="ignore"):
        assert np.array_equal(S._runner.band_quantiles(F, q, overwrite=True), want, equal_nan=True)
    assert np.array_equal(F, np.sort(E, axis=-1), equal_nan=True)
    R = E.copy()
    R.flags.writeable = False
    with np.errstate(invalid="ignore"):
        assert np.array_equal(S._runner.band_quantiles(R, q, overwrite=True), want, equal_nan=True)
    assert np.array_equal(R, E, equal_nan=True)


def test_vmap_engine_bands_on_the_coarse_grid(bench):
    # the vmap-simulate engine keeps the errors on the same band grid (band_stride): the
    # bands equal its full-resolution bands at those times
    _, d, _, _, _ = bench
    study = make_study(bench, jax.random.PRNGKey(7), 2, 2)
    one = jax.devices()[:1]
    full = S.run_study(study, d.observer, devices=one, quantiles=(0.1, 0.5, 0.9), band_points=None, quiet=True,
                       **OPTS)
    coarse = S.run_study(study, d.observer, devices=one, quantiles=(0.1, 0.5, 0.9), band_points=3, quiet=True,
                         **OPTS)
    assert coarse.attrs["engine"] == "vmap-simulate" and coarse.attrs["band_stride"] == 2
    assert np.array_equal(coarse.coords["time"], np.asarray(TS)[::2])
    assert np.array_equal(full.coords["time"], np.asarray(TS))
    assert np.array_equal(coarse.metrics["quantiles"], full.metrics["quantiles"][:, :, ::2])
    assert np.array_equal(coarse.metrics["iae"], full.metrics["iae"])


def test_samplers_are_reproducible_and_distinct():
    k = jax.random.PRNGKey(3)
    a = S.sinusoidal_delta(k, 5, 2)
    b = S.sinusoidal_delta(k, 5, 2)
    c = S.sinusoidal_delta(jax.random.PRNGKey(4), 5, 2)
    assert all(np.array_equal(x, y) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)))
    assert not np.array_equal(a.values.amplitude, c.values.amplitude)
    f = S.fault_scenarios(k, 50, 3, magnitude=(1.0, 2.0), onset=(1.0, 2.0), rise=(0.0, 1.0))
    amp = np.asarray(f.values.amplitude)
    assert np.all(np.count_nonzero(amp, axis=1) == 1)  # which="one": one active fault
    assert np.all((np.abs(amp).max(axis=1) >= 1.0) & (np.abs(amp).max(axis=1) <= 2.0))
    pc = S.piecewise_constant_delta(k, 4, 1, t_end=2.0, pieces=4, dt=0.1)
    times = np.asarray(pc.values.times)
    assert np.allclose(times / 0.1, np.round(times / 0.1)) and np.all(np.diff(times, axis=1) >= 0)
    arm = fojax.models.robot_arm()
    th = S.parameter_uncertainty(k, 8, arm.system.theta, {"k": 0.2, "m": 0.1, "J_l": 0.1})
    ratio = np.asarray(th.values["k"]) / float(arm.system.theta["k"])
    assert np.all(np.abs(ratio - 1) <= 0.2) and np.ptp(ratio) > 0
    assert np.all(np.asarray(th.values["g"]) == float(arm.system.theta["g"]))
    noise = S.output_noise(k, 3, 2, 0.0, 1.0, 0.1, std=0.01)
    assert noise.values.values.shape == (3, 11, 2)


def test_compiled_samplers_draw_the_eager_bits_and_compile_once_per_shape():
    """`constant_delta`, `fault_scenarios`, `constant_faults` draw in one compiled program
    (issue 13: eagerly every jax.random primitive compiled on its own). Oracle: the same
    jax.random calls made eagerly here, compared byte for byte (the sign of zero included);
    new ranges and keys do not compile again."""
    # private: the families' internals are checked
    from fojax.studies import _families

    def eager_faults(key, count, nf, magnitude, onset, rise, which):
        km, ks, kw, ko, kr = jax.random.split(key, 5)
        a = jax.random.uniform(km, (count, nf), minval=magnitude[0], maxval=magnitude[1], dtype=jnp.float64)
        a = a * jnp.where(jax.random.bernoulli(ks, 0.5, (count, nf)), 1.0, -1.0)
        if which == "one":
            a = a * jax.nn.one_hot(jax.random.randint(kw, (count,), 0, nf), nf, dtype=a.dtype)
        return [a, jax.random.uniform(ko, (count,), minval=onset[0], maxval=onset[1], dtype=jnp.float64),
                jax.random.uniform(kr, (count,), minval=rise[0], maxval=rise[1], dtype=jnp.float64)]

    def same(xs, ys):
        return all(np.asarray(x).tobytes() == np.asarray(y).tobytes() for x, y in zip(xs, ys, strict=True))

    sizes = [f._cached._cache_size() for f in (_families._fault_scenarios, _families._constant_delta)]
    for seed, (lo, hi), which in ((0, (0.5, 2.0), "one"), (5, (1.0, 1.5), "one"), (9, (0.2, 0.3), "all")):
        k = jax.random.PRNGKey(seed)
        f = S.fault_scenarios(k, 13, 3, magnitude=(lo, hi), onset=(1.0, 4.0), rise=(0.0, 0.5), which=which)
        ref = eager_faults(k, 13, 3, (lo, hi), (1.0, 4.0), (0.0, 0.5), which)
        assert same([f.values.amplitude, f.values.onset, f.values.rise], ref)
        assert which == "all" or np.signbit(np.asarray(f.values.amplitude)).any()  # -0.0 kept
        d = S.constant_delta(k, 13, 2, bounds=(-lo, lo))
        assert same([d.values.value], [jax.random.uniform(k, (13, 2), minval=-lo, maxval=lo, dtype=jnp.float64)])
        x0 = jnp.arange(7.0)
        cf = S.constant_faults(k, 13, x0, 3, magnitude=(lo, hi))
        amp = S.fault_scenarios(k, 13, 3, magnitude=(lo, hi), which="all").values.amplitude
        assert same([cf.values], [jnp.concatenate([jnp.broadcast_to(x0[:4], (13, 4)), amp], axis=1)])
    # one program per shape and option set: the three keys and ranges above compiled it once
    assert _families._fault_scenarios._cached._cache_size() - sizes[0] <= 2  # which="one" and "all"
    assert _families._constant_delta._cached._cache_size() - sizes[1] <= 1


def test_fault_profile_shapes():
    step = fojax.plant.FaultProfile(jnp.array([2.0]), onset=1.0, rise=0.0)
    ramp = fojax.plant.FaultProfile(jnp.array([2.0]), onset=1.0, rise=2.0)
    assert float(step(0.99)[0]) == 0.0 and float(step(1.0)[0]) == 2.0
    assert np.isclose(float(ramp(2.0)[0]), 1.0) and float(ramp(5.0)[0]) == 2.0


def test_error_metrics_closed_forms():
    # e(t) = exp(-t) sampled finely: IAE → 1 - e^{-T}, ISE → (1 - e^{-2T})/2, ITAE → 1 - (T+1)e^{-T}
    ts = jnp.linspace(0.0, 3.0, 30001)
    e = jnp.exp(-ts)[:, None]
    m = S.error_metrics(ts, e, settle_tol=np.exp(-1.0) + 1e-12)
    T = 3.0
    assert np.isclose(float(m["iae"][0]), 1 - np.exp(-T), rtol=1e-8)
    assert np.isclose(float(m["ise"][0]), (1 - np.exp(-2 * T)) / 2, rtol=1e-8)
    assert np.isclose(float(m["itae"][0]), 1 - (T + 1) * np.exp(-T), rtol=1e-8)
    assert float(m["peak"][0]) == 1.0
    assert np.isclose(float(m["settling_time"][0]), 1.0, atol=2e-4)
    assert np.isinf(float(S.error_metrics(ts, jnp.ones_like(e), 0.5)["settling_time"][0]))


def test_ten_thousand_samples_compile_once_and_match_single_runs(bench):
    _, d, _, _, _ = bench
    one = jax.devices()[:1]
    study = make_study(bench, jax.random.PRNGKey(0), 100, 100)
    before = _runner.TRACE_COUNTS["run_study"]
    res = S.run_study(study, d.observer, devices=one, quantiles=(0.1, 0.5, 0.9), quiet=True, **OPTS)
    assert _runner.TRACE_COUNTS["run_study"] == before + 1
    study2 = make_study(bench, jax.random.PRNGKey(1), 100, 100)
    res2 = S.run_study(study2, d.observer, devices=one, quantiles=(0.1, 0.5, 0.9), quiet=True, **OPTS)
    assert _runner.TRACE_COUNTS["run_study"] == before + 1  # new numbers: no retrace
    assert res.metrics["iae"].shape == (1, 100, 100, 5) and res.metrics["success"].all()
    assert not np.allclose(res.metrics["iae"], res2.metrics["iae"])
    assert res.metrics["quantiles"].shape == (1, 3, TS.shape[0], 5)
    for i, j in [(0, 0), (37, 81), (99, 99)]:
        ref = single_metrics(study, d.observer, i, j, **OPTS)
        for name in S._runner.METRICS:
            got = res.metrics[name][0, i, j]
            assert np.allclose(got, ref[name], rtol=1e-10, atol=1e-12), name


def test_sharded_equals_unsharded_and_chunks(bench, tmp_path):
    _, d, _, _, _ = bench
    assert len(jax.devices()) == 4
    study = make_study(bench, jax.random.PRNGKey(5), 6, 5)  # 30 samples: padded on 4 devices
    pd = design_functional_observer(bench[0].augmented, bench[0].L_aug, kind="proportional",
                                    region=Disk(-2.0, 1.0))
    obs = (d.observer, pd.observer)
    r1 = S.run_study(study, obs, devices=jax.devices()[:1], quiet=True, **OPTS)
    r4 = S.run_study(study, obs, devices=jax.devices(), chunk_size=8, quiet=True, **OPTS)
    assert r4.attrs["num_chunks"] == 4 and r4.attrs["num_devices"] == 4
    for k in r1.metrics:
        assert np.array_equal(r1.metrics[k], r4.metrics[k]) or np.allclose(
            r1.metrics[k], r4.metrics[k], rtol=1e-13, atol=1e-15
        ), k
    # save / load without loss
    path = tmp_path / "study"
    r4.save(path)
    back = S.StudyResult.load(path)
    assert back.axes == r4.axes and back.attrs == r4.attrs
    for k in r4.metrics:
        assert np.array_equal(back.metrics[k], r4.metrics[k])
    assert back.coords["observer"] == ("observer0", "observer1")
    assert np.array_equal(back.coords["time"], np.asarray(TS))


def test_noise_and_fault_wrappers(bench):
    ex, d, _, x0, u = bench
    nf = 3
    base = fojax.UncertainDescriptorSystem(ex.system, dA=ex.dA, delta=fojax.Constant(jnp.zeros(1)))
    fault = fojax.plant.FaultProfile(jnp.zeros(nf), 0.0, 0.0)
    plant = fojax.NoisyPlant(fojax.FaultyPlant(base, ex.Fa, ex.Fs, fault), fojax.Constant(jnp.zeros(3)))
    key = jax.random.PRNGKey(2)
    study = S.Study(
        plant, x0[:6], TS, ex.L, u,
        uncertainty=(S.constant_delta(key, 3, 1, path=("plant", "base", "base", "delta")),
                     S.output_noise(key, 3, 3, 0.0, 0.5, 0.1, std=0.0, path=("plant", "noise"))),
        scenarios=(S.fault_scenarios(key, 2, nf, onset=(0.0, 0.0), path=("plant", "base", "fault")),),
    )
    # fault targets come from the FaultyPlant; here it is wrapped, so estimate z only with a
    # zero-noise, zero-fault sample checked against the fault-augmented simulation.
    p, x = study.sample(1, 0)
    assert isinstance(p.noise, fojax.PiecewiseConstant)
    y_clean = fojax.simulate(p, x, TS, u, **OPTS).ys
    aug = fojax.UncertainDescriptorSystem(ex.augmented, dA=np.pad(ex.dA, ((0, 3), (0, 3))),
                                          delta=p.base.base.delta)
    chi0 = jnp.concatenate([x, p.base.fault.amplitude])
    y_aug = fojax.simulate(aug, chi0, TS, u, **OPTS).ys
    assert np.allclose(y_clean, y_aug, atol=1e-5)


def test_study_loss_gradient_matches_finite_differences(bench):
    # Constant δ per sample (exact LTI stepping): smooth in the observer parameters.
    ex, d, plant, x0, u = bench
    key = jax.random.PRNGKey(7)
    const_plant = fojax.UncertainDescriptorSystem(ex.augmented, dA=plant.dA, delta=fojax.Constant(jnp.zeros(1)))
    study = S.Study(const_plant, x0, jnp.linspace(0.0, 2.0, 41), ex.L_aug, u,
                    uncertainty=(S.constant_delta(key, 4, 1, bounds=(-0.5, 0.5)),),
                    scenarios=(S.constant_faults(key, 2, x0, 3),), signal_names=SIGNALS)
    from fojax.tuning import initial_parameters, observer_from_parameters

    fx, params = initial_parameters(d, parameterization="disk")
    cfg = S.SimConfig(stepper=fojax.Exact())

    def f(p, st):
        obs, _ = observer_from_parameters(fx, p)
        return S.study_loss(st, obs, cfg=cfg)

    # one compiled value-and-gradient serves both the gradient and the finite differences
    vg = eqx.filter_jit(jax.value_and_grad(f))
    g = vg(params, study)[1]

    def fj(p, st):
        return vg(p, st)[0]

    eps = 1e-5
    worst = 0.0
    # the entries with the largest gradient of each free parameter (tiny components are
    # dominated by finite-difference round-off), plus one fixed entry of Theta
    picks = [(n, tuple(int(i) for i in np.unravel_index(np.argmax(np.abs(g[n])), g[n].shape)))
             for n in ("Theta", "Y3")] + [("Theta", (0, 0))]
    for name, idx in picks:
        e = jnp.zeros_like(params[name]).at[idx].set(eps)
        fd = (fj({**params, name: params[name] + e}, study) - fj({**params, name: params[name] - e}, study)) / (2 * eps)
        rel = abs(float(g[name][idx]) - float(fd)) / max(abs(float(fd)), 1e-12)
        worst = max(worst, rel)
        assert rel < 1e-5, (name, idx, float(g[name][idx]), float(fd))
    print(f"worst relative gradient error {worst:.2e}")
