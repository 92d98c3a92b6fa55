"""`fojax.studies.study_loss`, the differentiable loss of a study: on the exact kernel in
fixed-width sample blocks, on the exponential engine, and with one joint exponential per
uncertainty sample when the scenarios leave the joint matrix unchanged.

**Sample blocks (exact kernel).**
Oracles: (1) `run_study`'s exact engine (the forward path, itself checked against
`fojax.simulate` and an independent SciPy recurrence in ``test_study_exact.py``): the
loss equals the mean over samples of its per-sample IAE / ISE; (2) central finite
differences of the same loss (ISE: smooth, so a sharp oracle); (3) the same loss and
gradient computed in one block (no `jax.lax.map`). The exact kernel's adjoint has no
plant part: differentiating with respect to the study is refused, not answered with zeros.

**Exponential engine (time-varying δ(t), faults and a known input).**
Oracles: (1) every sample solved independently with SciPy (DOP853, rtol 1e-12; the
oracle of ``tests/test_study_exponential.py``, whose study this module reuses) and the
metrics written again in NumPy; (2) `run_study`'s exponential engine on the same samples
(the same schedule, the plan's shared terms instead of per-sample ones: equal to
round-off); (3) the gradient with respect to the observer against central finite
differences of `study_loss` itself (ISE: smooth in the observer).

**Scenario groups.**
Oracles: (1) the same loss and gradient computed sample by sample (the grouping switched
off: ``scenario_free`` patched to ``False``), itself tested against `run_study`, central
finite differences and one block (the sample-block tests above); (2) `run_study`'s exact
engine (the mean of its per-sample IAE); (3) for the dependency test, which part of the
joint loop a scenario family reaches by construction (initial states and fault onsets do
not enter the joint matrix; a δ drawn per scenario does).
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_study_exponential import make_study, OBSERVER, oracle, SETTLE_TOL

import fojax
from fojax import studies as S
from fojax.design import design_functional_observer, Disk

# private: the traced index-1 split is compared
from fojax.simulation._reduction import svd_split

# private: the exact study kernel is tested itself
from fojax.studies import _exact, SimConfig, study_loss

# private: the no-retrace check
from fojax.studies._exponential import TRACE_COUNTS
from tests.helpers import small_step_input_study


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


# ==================================================================================================
# `study_loss` on the exact kernel in fixed-width sample blocks, accumulating only the loss's
# metric.
# ==================================================================================================


@pytest.fixture(scope="module")
def case():
    # 3 δ × 2 faults = 6 samples; blocks of 4 below: one full block and one padded with 2 copies
    study, d = small_step_input_study(5, 3, 2)
    res = S.run_study(study, (d.observer,), stepper=fojax.Exact(), quantiles=(), quiet=True, devices=jax.devices()[:1])
    assert res.attrs["engine"] == "exact-batch"
    return study, d.observer, res


def _value_and_grad(study, observer, loss):
    dyn, st = eqx.partition(observer, eqx.is_inexact_array)
    f = eqx.filter_jit(eqx.filter_value_and_grad(lambda p: S.study_loss(study, eqx.combine(p, st), loss=loss)))
    return f, dyn


def test_blocked_iae_equals_run_study_and_one_block(case, monkeypatch):
    study, observer, res = case
    want = float(np.mean(np.asarray(res.metrics["iae"])[0]))  # mean over δ, faults and signals
    monkeypatch.setattr(_exact, "DIFF_BLOCK", 4)  # 6 samples: two blocks, the second padded
    f, dyn = _value_and_grad(study, observer, "iae")
    v, g = f(dyn)
    assert abs(float(v) - want) <= 1e-10 * abs(want), (float(v), want)
    monkeypatch.setattr(_exact, "DIFF_BLOCK", 8)  # one block of 6 (padded to 8) ...
    f1, _ = _value_and_grad(study, observer, "iae")
    v1, g1 = f1(dyn)
    assert abs(float(v1) - want) <= 1e-10 * abs(want)
    # ... gives the same gradient: the padded copies carry no cotangent
    for a, b in zip(jax.tree.leaves(g), jax.tree.leaves(g1)):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-13 * float(jnp.max(jnp.abs(b))))


def test_blocked_ise_equals_run_study_and_its_gradient_central_differences(case, monkeypatch):
    study, observer, res = case
    want = float(np.mean(np.asarray(res.metrics["ise"])[0]))
    monkeypatch.setattr(_exact, "DIFF_BLOCK", 4)
    f, dyn = _value_and_grad(study, observer, "ise")
    v, g = f(dyn)
    assert abs(float(v) - want) <= 1e-10 * abs(want), (float(v), want)
    leaves, tree = jax.tree.flatten(dyn)
    gl = jax.tree.leaves(g)
    k = int(np.argmax([float(jnp.max(jnp.abs(x))) for x in gl]))  # the leaf with the largest entry
    idx = np.unravel_index(int(jnp.argmax(jnp.abs(gl[k]))), gl[k].shape)
    eps = 1e-6

    def at(s):
        moved = [x.at[idx].add(s) if i == k else x for i, x in enumerate(leaves)]
        return float(f(jax.tree.unflatten(tree, moved))[0])

    fd = (at(eps) - at(-eps)) / (2 * eps)
    assert abs(float(gl[k][idx]) - fd) <= 1e-6 * abs(fd), (float(gl[k][idx]), fd)


def test_gradient_with_respect_to_the_study_is_refused(case):
    # the plant trajectory is a constant of the split adjoint; a derivative through it
    # (here: the grid, which sets the plant's Φ_pp = e^{A_p h}) must raise, not be dropped
    study, observer, _ = case

    def loss(c):
        return S.study_loss(eqx.tree_at(lambda s: s.ts, study, c * study.ts), observer)

    with pytest.raises(fojax.errors.InputError, match="differentiates the observers only"):
        jax.jit(jax.grad(loss))(1.0)  # raised while tracing the reverse pass: nothing compiles


# ==================================================================================================
# `study_loss` forms one joint exponential per uncertainty sample when the scenarios do not change
# the joint matrix (`fojax.studies._exact.scenario_free`).
# ==================================================================================================


def _problem(study, observer):
    E0 = _exact._unwrap(study.sample(0, 0)[0])[0].E
    return _exact.StudyProblem(study, (observer,), svd_split(E0), E0, jnp.asarray(0.02), None)


def _loss_and_grad(study, observer):
    dyn, st = eqx.partition(observer, eqx.is_inexact_array)
    f = eqx.filter_jit(eqx.filter_value_and_grad(lambda p: S.study_loss(study, eqx.combine(p, st), loss="iae")))
    return f(dyn)


def _faulty_study(scenario_delta: bool):
    """The §3.3.7 plant with a `FaultyPlant` whose faults start at random onsets per
    scenario (jumps of the exosystem state that differ by scenario), 2 δ × 3 scenarios; with
    `scenario_delta` the scenarios also draw δ (so the joint matrix depends on them)."""
    ex = fojax.models.example_3_3_7()
    base = fojax.UncertainDescriptorSystem(ex.system, dA=ex.dA, delta=fojax.Constant(jnp.zeros(1)))
    plant = fojax.FaultyPlant(base, ex.Fa, ex.Fs, fault=fojax.plant.FaultProfile(jnp.zeros(3)))
    obs = design_functional_observer(ex.augmented, ex.L_aug, kind="generalized", region=Disk(-3.0, 2.0)).observer
    k1, k2, k3 = jax.random.split(jax.random.PRNGKey(7), 3)
    x0 = jnp.full((6,), 0.3)
    scenarios = (S.fault_scenarios(k2, 3, 3, onset=(0.1, 0.6), rise=(0.0, 0.3), which="all"),)
    if scenario_delta:
        scenarios = scenarios + (S.constant_delta(k3, 3, 1, bounds=(-0.3, 0.3), path=("plant", "base", "delta")),)
    study = S.Study(plant, x0, jnp.linspace(0.0, 1.0, 41), ex.L, None,
                    uncertainty=(S.constant_delta(k1, 2, 1, bounds=(-0.3, 0.3), path=("plant", "base", "delta")),),
                    scenarios=scenarios, fault_targets=True)
    return study, obs


def test_scenario_free_by_what_the_scenarios_reach():
    study, d = small_step_input_study(5, 3, 2)  # scenarios: initial states (constant faults)
    assert _exact.scenario_free(_problem(study, d.observer), (d.observer,))
    study, obs = _faulty_study(False)  # scenarios: fault onsets and sizes (exosystem state, jumps)
    assert _exact.scenario_free(_problem(study, obs), (obs,))
    study, obs = _faulty_study(True)  # scenarios also set δ: A depends on j
    assert not _exact.scenario_free(_problem(study, obs), (obs,))


def _passes_study():
    """The §3.3.7 fault-augmented study without a jump (no input, constant faults as initial
    states): the loss runs in passes of 8 grid steps (`pass_recurrence_reduce`), as in
    `tune`; 3 δ × 4 scenarios."""
    study, d = small_step_input_study(5, 3, 4)
    study = S.Study(study.plant, study.x0, jnp.linspace(0.0, 1.0, 41), study.L, None,
                    uncertainty=study.uncertainty, scenarios=study.scenarios)
    return study, d.observer


@pytest.mark.parametrize("which", ["passes", "fault_onsets"])
def test_grouped_loss_and_gradient_equal_per_sample(which, monkeypatch):
    # fault_onsets: jumps that differ by scenario (the step-by-step loop)
    study, observer = _passes_study() if which == "passes" else _faulty_study(False)
    assert _exact.scenario_free(_problem(study, observer), (observer,))  # the grouped path is taken
    res = S.run_study(study, (observer,), stepper=fojax.Exact(), quantiles=(), quiet=True, devices=jax.devices()[:1])
    assert res.attrs["engine"] == "exact-batch" and res.metrics["success"].all()
    want = float(np.mean(np.asarray(res.metrics["iae"])[0]))
    before = _exact.TRACE_COUNTS["study_loss_exact"]
    v, g = _loss_and_grad(study, observer)
    assert _exact.TRACE_COUNTS["study_loss_exact"] > before  # the exact kernel ran
    monkeypatch.setattr(_exact, "scenario_free", lambda problem, observers: False)
    v1, g1 = _loss_and_grad(study, observer)
    assert abs(float(v) - want) <= 1e-10 * abs(want), (float(v), want)
    assert abs(float(v) - float(v1)) <= 1e-13 * abs(float(v1))
    for a, b in zip(jax.tree.leaves(g), jax.tree.leaves(g1)):
        np.testing.assert_allclose(a, b, rtol=1e-11, atol=1e-13 * float(jnp.max(jnp.abs(b))))
