"""`study_loss` forms one joint exponential per uncertainty sample when the scenarios do not
change the joint matrix (`fojax.studies._exact.scenario_free`).

Oracles: (1) the same loss and gradient computed sample by sample (the grouping switched
off: ``scenario_free`` patched to ``False``), itself tested against `run_study`, central
finite differences and one block in ``test_study_loss_blocks.py``; (2) `run_study`'s exact
engine (the mean of its per-sample IAE); (3) for the dependency test, which part of the
joint loop a scenario family reaches by construction (initial states and fault onsets do
not enter the joint matrix; a δ drawn per scenario does).
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fojax
from fojax import studies as S
from fojax.design import design_functional_observer, Disk

# private: the traced index-1 split is compared
from fojax.simulation._reduction import svd_split
from fojax.studies import _exact
from tests.helpers import small_step_input_study


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
