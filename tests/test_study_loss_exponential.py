"""`study_loss` on the exponential engine: time-varying δ(t), faults and a known input.

Oracles: (1) every sample solved independently with SciPy (DOP853, rtol 1e-12; the
oracle of ``tests/test_study_exponential.py``, whose study this module reuses) and the
metrics written again in NumPy; (2) `run_study`'s exponential engine on the same samples
(the same schedule, the plan's shared terms instead of per-sample ones: equal to
round-off); (3) the gradient with respect to the observer against central finite
differences of `study_loss` itself (ISE: smooth in the observer).
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_study_exponential import make_study, OBSERVER, oracle, SETTLE_TOL

import fojax
from fojax.studies import SimConfig, study_loss

# private: the no-retrace check
from fojax.studies._exponential import TRACE_COUNTS


CFG = SimConfig(settle_tol=SETTLE_TOL)


@pytest.fixture(scope="module")
def study():
    return make_study(jax.random.PRNGKey(0))


@pytest.fixture(scope="module")
def value_and_grad(study):
    # one compilation for every observer value (the study is concrete: host decisions)
    return eqx.filter_jit(eqx.filter_value_and_grad(lambda o, lo: study_loss(study, o, loss=lo, cfg=CFG)))


def _loss(value_and_grad, observer, loss="ise"):
    return value_and_grad(observer, loss)


def test_study_loss_matches_scipy_and_run_study(study, value_and_grad):
    mets, _ = oracle(study)  # (5, Nu, Nf, 2)
    res = fojax.run_study(study, OBSERVER, quiet=True, settle_tol=SETTLE_TOL, quantiles=())
    assert res.attrs["engine"] == "exponential-batch"
    got = float(_loss(value_and_grad, OBSERVER)[0])  # ISE, under jit and grad
    assert TRACE_COUNTS["study_loss_exponential"] >= 1  # the exponential path was taken
    # equal to round-off (the vmap/diffrax path would differ at its tolerance, ~1e-8)
    np.testing.assert_allclose(got, res.metrics["ise"][0].mean(), rtol=1e-12)
    np.testing.assert_allclose(got, mets[1].mean(), rtol=1e-8)  # ETDRK4 truncation, as run_study


def test_gradient_matches_central_differences(study, value_and_grad):
    v0, g = _loss(value_and_grad, OBSERVER)
    rng = np.random.default_rng(3)
    params, static = eqx.partition(OBSERVER, eqx.is_inexact_array)
    direction = jax.tree.map(lambda a: jnp.asarray(rng.standard_normal(a.shape)), params)
    dd = sum(float(jnp.vdot(a, b)) for a, b in zip(jax.tree.leaves(g), jax.tree.leaves(direction)))
    eps = 1e-5
    shifted = [eqx.combine(jax.tree.map(lambda p, d: p + s * eps * d, params, direction), static) for s in (1, -1)]
    fd = (float(_loss(value_and_grad, shifted[0])[0]) - float(_loss(value_and_grad, shifted[1])[0])) / (2 * eps)
    # measured 4e-11 relative (eps 1e-5) and 5e-11 (eps 1e-4): the FD truncation and round-off
    assert abs(dd - fd) <= 1e-7 * abs(fd), (dd, fd)
    assert np.isfinite(float(v0)) and all(np.all(np.isfinite(np.asarray(a))) for a in jax.tree.leaves(g))


def test_no_retrace_for_new_observer_numbers(value_and_grad):
    _loss(value_and_grad, OBSERVER)
    before = dict(TRACE_COUNTS)
    other = eqx.tree_at(lambda o: o.xi0, OBSERVER, jnp.asarray([0.1, 0.2]))
    v1, _ = _loss(value_and_grad, other)
    v0, _ = _loss(value_and_grad, OBSERVER)
    assert dict(TRACE_COUNTS) == before
    assert float(v1) != float(v0)


def test_traced_study_with_resolved_schedule_equals_the_concrete_path_and_does_not_retrace(study, value_and_grad):
    # `fojax.tune`'s situation: the study is an argument of the jitted function (traced); the
    # schedule was decided on the host by resolve_engine. Oracles: the concrete path (its value
    # and gradient, the latter checked against central differences above) and run_study.
    cfg = fojax.studies.resolve_engine(study, OBSERVER, CFG)
    assert cfg.exponential_schedule is not None and CFG.exponential_schedule is None

    @eqx.filter_jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def traced(o, s):
        return eqx.filter_value_and_grad(lambda o: study_loss(s, o, loss="ise", cfg=cfg))(o)

    v, g = traced(OBSERVER, study)
    v0, g0 = _loss(value_and_grad, OBSERVER)
    np.testing.assert_allclose(float(v), float(v0), rtol=1e-12)
    for a, b in zip(jax.tree.leaves(g), jax.tree.leaves(g0)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-9, atol=1e-12)
    # new δ(t) samples and fault amplitudes, same shapes and schedule: data, no new trace
    other = make_study(jax.random.PRNGKey(7))
    assert fojax.studies.resolve_engine(other, OBSERVER, CFG).exponential_schedule == cfg.exponential_schedule
    before = dict(TRACE_COUNTS)
    v1, _ = traced(OBSERVER, other)
    assert dict(TRACE_COUNTS) == before
    res = fojax.run_study(other, OBSERVER, quiet=True, settle_tol=SETTLE_TOL, quantiles=())
    assert res.attrs["engine"] == "exponential-batch"
    np.testing.assert_allclose(float(v1), res.metrics["ise"][0].mean(), rtol=1e-12)
    assert float(v1) != float(v)


def test_traced_study_without_schedule_does_not_take_the_exponential_engine(study):
    # without resolve_engine a traced study cannot be checked on the host: exponential_metrics_traced
    # refuses it (study_loss then falls back to vmap(simulate))
    # private: tested itself
    from fojax.studies._exponential import exponential_metrics_traced

    seen = []
    jax.eval_shape(lambda s: seen.append(exponential_metrics_traced(s, (OBSERVER,), SETTLE_TOL)), study)
    assert seen == [None]
