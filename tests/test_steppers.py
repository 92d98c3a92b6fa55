"""Stepper and save objects: `stepper=` / `save=`, the removed keywords (``method=``, ``solver=``,
``rtol=``, ...: a `TypeError` naming the stepper), `Auto`'s choice, refused combinations, compile
reuse, and the one metric vocabulary.

Oracles:
- the same call spelled another way (`Auto` where it picks `Exact`, ``quantiles=`` for
  ``save=Metrics(bands=...)``): the same code path, so the results must be equal bit for bit;
- for the metric vocabulary, the trapezoid rule written again in NumPy on the errors of one
  `fojax.simulate` trajectory (checked against `error_metrics` and `run_study`'s
  ``Metrics(reduce="none")`` and ``Metrics(reduce="sum")``);
- trace counters (`fojax.simulation._simulate.TRACE_COUNTS`, `fojax.simulation._batch.TRACE_COUNTS`)
  for "no recompile when only numbers change".

The systems are the §4.1.3 loop of ``closed_loop_413.py`` (4 states, 2-state LTI observer) on a
21-point grid and a 2-state nonlinear descriptor plant; studies have 3–4 samples.
"""

import dataclasses

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from closed_loop_413 import ACL, AO, B0, BY, C0, DA, E, LTIObserver, X0

import fojax
from fojax import studies as S
from fojax.plant import as_signal

# private: the kernels' internals are checked
from fojax.simulation import _batch, _simulate
from fojax.studies import error_metrics, SimConfig


# bit-for-bit equality of different programs (the stepper objects against the earlier entry points, metric subsets): compiled as users get it
pytestmark = pytest.mark.production_codegen


TS = np.linspace(0.0, 1.0, 21)
OBS = LTIObserver(jnp.asarray(AO), jnp.asarray(BY), jnp.asarray([0.5, -1.0]))
SETTLE = 0.05


def lti_plant():
    return fojax.DescriptorSystem(jnp.asarray(E), jnp.asarray(ACL), jnp.asarray(B0), jnp.asarray(C0))


def uncertain_template():
    return fojax.UncertainDescriptorSystem(lti_plant(), dA=jnp.asarray(DA), delta=fojax.Constant(jnp.zeros(1)))


def lti_study(key=0):
    fam = S.constant_delta(jax.random.PRNGKey(key), 3, 1, bounds=(-0.3, 0.3))
    return fojax.Study(uncertain_template(), X0, TS, C0[:2], uncertainty=(fam,))


def sine_study():
    fam = S.sinusoidal_delta(jax.random.PRNGKey(1), 2, 1, amplitude=(0.0, 0.3), omega=(0.5, 2.0))
    template = fojax.UncertainDescriptorSystem(lti_plant(), dA=jnp.asarray(DA),
                                               delta=fojax.Sine(jnp.zeros(1), jnp.ones(1), jnp.zeros(1)))
    return fojax.Study(template, X0, TS, C0[:2], uncertainty=(fam,))


def _nl_f(x, u, th):
    return jnp.array([-th["a"] * x[0] + x[1], x[0] ** 2 - x[1]])


def _nl_g(x, u, th):
    return x


def nonlinear_plant():
    """``x1' = -a x1 + x2``, ``0 = x1² − x2`` (index 1: ∂/∂x2 of the algebraic row is −1)."""
    return fojax.NonlinearDescriptorSystem(jnp.diag(jnp.array([1.0, 0.0])), _nl_f, _nl_g,
                                           {"a": jnp.asarray(1.0)}, m=1, p=2)


def assert_results_equal(a, b):
    assert a.metrics.keys() == b.metrics.keys()
    for k in a.metrics:
        np.testing.assert_array_equal(a.metrics[k], b.metrics[k], err_msg=k)
    assert a.attrs == b.attrs


# --------------------------------------------------------------------------- objects


def test_steppers_are_hashable_and_equal_by_value():
    assert Auto_() == fojax.Auto() and hash(Auto_()) == hash(fojax.Auto())
    assert fojax.Diffrax(diffrax.Tsit5(), rtol=1e-6) == fojax.Diffrax(diffrax.Tsit5(), rtol=1e-6)
    assert fojax.Exponential(substeps=2) != fojax.Exponential()
    # SimConfig: equal steppers give one (hashable) config, its attrs read the stepper back,
    # and replace() keeps it
    a = SimConfig(stepper=fojax.Diffrax(rtol=1e-6))
    b = SimConfig(stepper=fojax.Diffrax(rtol=1e-6))
    assert a == b and hash(a) == hash(b) and (b.attrs()["method"], b.attrs()["rtol"]) == ("diffrax", 1e-6)
    assert dataclasses.replace(b, settle_tol=0.1).stepper == b.stepper
    assert SimConfig() == SimConfig(stepper=fojax.Auto())
    assert fojax.Metrics() == fojax.Metrics(bands=fojax.Bands())


def Auto_():
    return fojax.Auto(diffrax=fojax.Diffrax())


def test_removed_keywords_raise_type_error_naming_the_stepper():
    # method=, solver=, rtol=, atol=, max_steps= were replaced by the stepper object: each entry
    # point rejects them with a TypeError that names what to pass instead.
    with pytest.raises(TypeError, match=r"simulate\(\) got the removed keyword\(s\) rtol=.*fojax.Diffrax\(rtol="):
        fojax.simulate(lti_plant(), X0, TS, stepper=fojax.Exact(), rtol=1e-6)
    with pytest.raises(TypeError, match=r"simulate\(\) got the removed keyword\(s\) method=, solver=.*"
                                        r"stepper=fojax.Auto\(\) \| fojax.Exact\(\)"):
        fojax.simulate(lti_plant(), X0, TS, method="exact", solver=diffrax.Tsit5())
    with pytest.raises(TypeError, match=r"run_study\(\) got the removed keyword\(s\) method="):
        fojax.run_study(lti_study(), OBS, method="exact")
    with pytest.raises(TypeError, match=r"tune\(\) got the removed keyword\(s\) max_steps=.*Diffrax\(max_steps="):
        fojax.tune(None, None, max_steps=10)
    with pytest.raises(TypeError, match=r"SimConfig\(\) got the removed keyword\(s\) atol="):
        SimConfig(atol=1e-9)


def test_bad_objects_and_mixed_spellings_raise_input_error():
    with pytest.raises(fojax.errors.InputError, match=r"Diffrax\(rtol=...\) must be a positive float"):
        fojax.Diffrax(rtol=-1.0)
    with pytest.raises(fojax.errors.InputError, match=r"Exponential\(substeps=...\)"):
        fojax.Exponential(substeps=0)
    with pytest.raises(fojax.errors.InputError, match=r"reduce='sum'.*'peak'"):
        fojax.Metrics(kinds=("iae", "peak"), reduce="sum")
    with pytest.raises(fojax.errors.InputError, match=r"Metrics\(kinds=...\)"):
        fojax.Metrics(kinds=("iae", "l2"))
    with pytest.raises(fojax.errors.InputError, match=r"Bands\(points=...\)"):
        fojax.Bands(points=1)
    with pytest.raises(fojax.errors.InputError, match=r"simulate\(stepper=...\) must be fojax.Auto\(\)"):
        fojax.simulate(lti_plant(), X0, TS, stepper="exact")
    with pytest.raises(fojax.errors.InputError, match=r"run_study: pass either save= or the legacy keywords \['quantiles'\]"):
        fojax.run_study(lti_study(), OBS, save=fojax.Metrics(), quantiles=(0.5,))
    with pytest.raises(fojax.errors.InputError, match=r"run_study\(save=...\) must be fojax.Metrics"):
        fojax.run_study(lti_study(), OBS, save=fojax.Trajectory())
    with pytest.raises(fojax.errors.InputError, match=r"simulate\(save=...\) keeps one trajectory"):
        fojax.simulate(lti_plant(), X0, TS, save=fojax.Metrics())
    with pytest.raises(fojax.errors.InputError, match=r"stepper Exponential\(\) runs studies"):
        fojax.simulate(lti_plant(), X0, TS, stepper=fojax.Exponential())


# --------------------------------------------------------------------------- Auto's choice


def test_auto_picks_exact_for_lti_and_diffrax_otherwise_and_exact_refuses_nonlinear():
    ts = jnp.asarray(TS)
    auto = fojax.Auto(diffrax=fojax.Diffrax(diffrax.Tsit5()))
    assert auto.select(lti_plant(), (OBS,), ts, fojax.Step(jnp.ones(2), 0.5)) == fojax.Exact()
    # a step between grid points: the exact stepper would lose O(h) there
    assert auto.select(lti_plant(), (OBS,), ts, fojax.Step(jnp.ones(2), 0.525)) is auto.diffrax
    sine = fojax.UncertainDescriptorSystem(lti_plant(), dA=jnp.asarray(DA),
                                           delta=fojax.Sine(jnp.ones(1), jnp.ones(1), jnp.zeros(1)))
    assert auto.select(sine, (OBS,), ts, as_signal(None, 2)) is auto.diffrax  # δ(t): one simulate runs diffrax
    assert auto.select(nonlinear_plant(), (), ts, as_signal(None, 1)) is auto.diffrax
    with pytest.raises(fojax.errors.InputError, match=r"stepper Exact\(\).*needs a linear time-invariant plant.*"
                                               r"NonlinearDescriptorSystem"):
        fojax.Exact().select(nonlinear_plant(), (), ts, as_signal(None, 1))
    with pytest.raises(fojax.errors.InputError, match=r"stepper Exact\(\).*uniform grid"):
        fojax.Exact().select(lti_plant(), (), jnp.asarray(TS ** 2), as_signal(None, 2))
    # the batch kernels, in the order run_study tries them (then every sample through simulate)
    assert auto.batch_candidates == (fojax.Exact(), fojax.Exponential()) and auto.simulates
    assert fojax.Exponential(substeps=2).batch_candidates == (fojax.Exponential(substeps=2),)
    assert not fojax.Exponential.simulates  # an explicit Exponential has no simulate path
    assert fojax.Diffrax().batch_candidates == () and fojax.Diffrax().simulates


# --------------------------------------------------------------------------- simulate


def test_simulate_exact_and_auto_bit_for_bit_without_recompiling():
    plant, u = lti_plant(), fojax.Step(jnp.array([1.0, -0.5]), 0.5)
    before = _simulate.TRACE_COUNTS["simulate"]
    new = fojax.simulate(plant, X0, TS, u, observers=(OBS,), stepper=fojax.Exact(), save=fojax.Trajectory())
    old = fojax.simulate(plant, X0, TS, u, observers=(OBS,), stepper=fojax.Auto())  # Auto → Exact
    auto = fojax.simulate(plant, 2.0 * X0, TS, u, observers=(OBS,))  # Auto → Exact; new numbers
    assert _simulate.TRACE_COUNTS["simulate"] == before + 1  # one compilation for all three
    assert new.method == old.method == auto.method == "exact"
    np.testing.assert_array_equal(new.xs, old.xs)
    np.testing.assert_array_equal(new.estimates[0], old.estimates[0])
    d_new = fojax.simulate(plant, X0, TS, u, observers=(OBS,),
                           stepper=fojax.Diffrax(diffrax.Tsit5(), rtol=1e-6, atol=1e-9))
    d_old = fojax.simulate(plant, X0, TS, u, observers=(OBS,),
                           stepper=fojax.Diffrax(diffrax.Tsit5(), rtol=1e-6, atol=1e-9))
    assert d_new.method == "diffrax"
    np.testing.assert_array_equal(d_new.xs, d_old.xs)


# --------------------------------------------------------------------------- run_study


@pytest.fixture(scope="module")
def lti_results():
    st = lti_study()
    new = fojax.run_study(st, OBS, stepper=fojax.Exact(), save=fojax.Metrics(bands=fojax.Bands((0.1, 0.9), 11)),
                          quiet=True)
    old = fojax.run_study(st, OBS, stepper=fojax.Exact(), quantiles=(0.1, 0.9), band_points=11, quiet=True)
    return st, new, old


def test_run_study_exact_and_auto_equal_legacy_bit_for_bit(lti_results):
    st, new, old = lti_results
    assert new.attrs["engine"] == "exact-batch"
    assert_results_equal(new, old)
    auto = fojax.run_study(st, OBS, save=fojax.Metrics(bands=fojax.Bands((0.1, 0.9), 11)), quiet=True)
    assert auto.attrs["engine"] == "exact-batch"  # Auto picks the exact kernel for an LTI study
    for k in fojax.Metrics().kinds:  # every metric of the one vocabulary (the default kinds)
        np.testing.assert_array_equal(auto.metrics[k], new.metrics[k])


def test_run_study_no_recompile_for_new_numbers():
    cfg = dict(stepper=fojax.Exact(), save=fojax.Metrics(bands=None), quiet=True)
    fojax.run_study(lti_study(0), OBS, **cfg)
    before = dict(_batch.TRACE_COUNTS)
    obs2 = LTIObserver(jnp.asarray(AO) * 1.1, jnp.asarray(BY), jnp.asarray([0.1, 0.2]))
    res = fojax.run_study(lti_study(5), obs2, **cfg)
    assert dict(_batch.TRACE_COUNTS) == before
    assert "quantiles" not in res.metrics


def test_run_study_exponential_and_auto_on_a_time_varying_delta():
    st = sine_study()
    save = fojax.Metrics(bands=None)
    new = fojax.run_study(st, OBS, stepper=fojax.Exponential(), save=save, quiet=True)
    old = fojax.run_study(st, OBS, stepper=fojax.Exponential(), quantiles=(), quiet=True)
    auto = fojax.run_study(st, OBS, save=save, quiet=True)
    assert new.attrs["engine"] == auto.attrs["engine"] == "exponential-batch"
    assert_results_equal(new, old)
    assert_results_equal(auto, new)
    # the options reach the schedule: substeps fixed at 6 instead of the rate rule's choice
    six = fojax.run_study(st, OBS, stepper=fojax.Exponential(substeps=6, startup_factor=1), save=save, quiet=True)
    assert six.attrs["solver"].startswith("ETDRK4, 6 steps per grid interval (6 in the first")
    np.testing.assert_allclose(six.metrics["iae"], new.metrics["iae"], rtol=1e-6)


def test_explicit_stepper_that_is_not_exact_for_the_study_names_itself():
    plant = nonlinear_plant()
    st = fojax.Study(plant, jnp.array([0.5, 0.25]), TS, jnp.eye(2))
    obs = LTIObserver(-jnp.eye(2), jnp.zeros((2, 2)), jnp.zeros(2))
    with pytest.raises(fojax.errors.InputError, match=r"stepper Exponential\(\) cannot run"):
        fojax.run_study(st, obs, stepper=fojax.Exponential(), quiet=True)
    with pytest.raises(fojax.errors.InputError, match=r"stepper Exact\(\).*needs a linear time-invariant plant"):
        fojax.run_study(st, obs, stepper=fojax.Exact(), quiet=True)
    with pytest.raises(fojax.errors.InputError, match=r"study_loss: stepper Exponential\(\) cannot run this study"):
        S.study_loss(st, obs, cfg=SimConfig(stepper=fojax.Exponential()))


# --------------------------------------------------------------------------- one vocabulary


def _trap(ts, v):
    return np.sum(0.5 * (v[1:] + v[:-1]) * np.diff(ts)[:, None], axis=0)


def test_metric_vocabulary_is_the_same_everywhere(lti_results):
    """`error_metrics` and `run_study`'s `Metrics(reduce="none" | "sum")` (exact kernel)
    against the trapezoid rule in NumPy on one trajectory (sample 0 of the LTI study)."""
    st, res, _ = lti_results
    plant, x0 = st.sample(0, 0)
    sol = fojax.simulate(plant, x0, TS, observers=(OBS,), stepper=fojax.Exact())
    e = np.asarray(sol.estimates[0] - sol.xs @ st.L.T)  # (T, 2)
    a, tr = np.abs(e), TS - TS[0]
    oracle = {"iae": _trap(TS, a), "ise": _trap(TS, e**2), "itae": _trap(TS, tr[:, None] * a),
              "peak": a.max(axis=0)}
    got = error_metrics(jnp.asarray(TS), jnp.asarray(e), SETTLE)
    for k, v in oracle.items():
        np.testing.assert_allclose(got[k], v, rtol=1e-13, err_msg=k)
        np.testing.assert_allclose(res.metrics[k][0, 0, 0], v, rtol=1e-9, err_msg=k)  # run_study, exact kernel
    # run_study: Metrics(kinds, reduce="sum") keeps the named metrics, summed over the signals
    summed = fojax.run_study(st, OBS, stepper=fojax.Exact(), quiet=True,
                             save=fojax.Metrics(kinds=("iae", "ise"), reduce="sum", bands=None))
    assert set(summed.metrics) == {"iae", "ise", "success"}
    assert summed.axes["iae"] == ("observer", "uncertainty", "fault")
    for k in ("iae", "ise"):
        np.testing.assert_allclose(summed.metrics[k], res.metrics[k].sum(axis=-1), rtol=1e-14)
        np.testing.assert_allclose(summed.metrics[k][0, 0, 0], oracle[k].sum(), rtol=1e-9, err_msg=k)
    with pytest.raises(fojax.errors.InputError, match=r"reduce='sum'.*Drop 'peak'"):
        fojax.Metrics(kinds=("iae", "peak"), reduce="sum")


def test_batch_engines_accumulate_only_the_requested_metrics(lti_results):
    """`Metrics(kinds)` on the exact and exponential kernels: only the named metrics (and the
    peak when no integral is named) are accumulated in the time loop, and they equal the full run's
    bit for bit (the same sums in the same order). Oracle: the default `Metrics()` run."""
    st, full, _ = lti_results
    kinds = ("iae", "settling_time")
    save = fojax.Metrics(kinds=kinds, bands=fojax.Bands((0.1, 0.9), 11))
    res = fojax.run_study(st, OBS, stepper=fojax.Exact(), save=save, quiet=True)
    assert set(res.metrics) == {"iae", "settling_time", "success", "quantiles"}
    for k in ("iae", "settling_time", "success", "quantiles"):
        np.testing.assert_array_equal(res.metrics[k], full.metrics[k], err_msg=k)
    (problem, _, _), _ = S._exact.exact_problem(st, (OBS,), SETTLE, 0, kinds=kinds)
    assert problem.computed == ("iae", "settling_time")
    assert len(problem.init(jnp.zeros((2, 3)))) == 2  # two accumulators, not five
    (alone, _, _), _ = S._exact.exact_problem(st, (OBS,), SETTLE, 0, kinds=("settling_time",))
    assert alone.computed == ("peak", "settling_time")  # the peak's finiteness: the success test
    # the exponential engine reduces with the same problem
    tv = sine_study()
    one = fojax.run_study(tv, OBS, stepper=fojax.Exponential(), save=fojax.Metrics(kinds=("ise",), bands=None),
                          quiet=True)
    all_ = fojax.run_study(tv, OBS, stepper=fojax.Exponential(), save=fojax.Metrics(bands=None), quiet=True)
    assert set(one.metrics) == {"ise", "success"}
    np.testing.assert_array_equal(one.metrics["ise"], all_.metrics["ise"])
    np.testing.assert_array_equal(one.metrics["success"], all_.metrics["success"])


def test_one_uniform_grid_test_for_every_entry():
    # private: tested itself (the batch kernels' grid check and the one deviation measure)
    from fojax.simulation._driver import _step_size
    from fojax.simulation._steppers import grid_deviation

    assert grid_deviation(np.linspace(0.0, 1.0, 11))[0] <= 1e-12
    assert grid_deviation(np.linspace(1.0, 0.0, 11))[0] == np.inf  # decreasing: never uniform
    bad = TS.copy()
    bad[3] += 1e-4
    with pytest.raises(fojax.errors.InputError, match=r"run_study steps on a uniform increasing grid.*2\.00e-03"):
        _step_size(jnp.asarray(bad))
    study = fojax.Study(uncertain_template(), X0, bad, C0[:2], uncertainty=lti_study().uncertainty)
    with pytest.raises(fojax.errors.InputError, match=r"stepper Exponential\(\) cannot run this study: the grid is not uniform"):
        fojax.run_study(study, OBS, stepper=fojax.Exponential(), quiet=True)
    with pytest.raises(fojax.errors.InputError, match=r"stepper Exact\(\).*not uniform \(max .* = 2\.00e-03"):
        fojax.Exact().select(lti_plant(), (), jnp.asarray(bad), as_signal(None, 2))
