"""`fojax.tune` on a time-varying δ(t) study trains on the exponential engine (issue 13, item 3).

Oracles: `fojax.run_study`'s exponential engine on the same samples (its values are checked
against SciPy's DOP853 in ``tests/test_study_exponential.py`` and the differentiable path
against it and against central differences in ``tests/test_study_loss.py``);
the trace counters of the jitted tuning step. Before this change `tune`'s step (where the
study is traced) fell back to `vmap(simulate)` with diffrax, whose loss differs from the
exponential engine's at diffrax's tolerance (~1e-8 relative) and whose step cost 29 s CPU
at 20 samples (§3.3.7, 1,000 steps; benchmarks/tuning_time_varying.py).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import uncertain_plant_3_3_7

import fojax
from fojax import studies as S, tuning
from fojax.design import design_functional_observer, Disk

# private: TRACE_COUNTS: the no-retrace check
from fojax.studies import _exponential
from fojax.tuning import _tune


@pytest.fixture(scope="module")
def setup():
    ex = fojax.models.example_3_3_7()
    d = design_functional_observer(ex.augmented, ex.L_aug, kind="generalized", region=Disk(-3.0, 2.0))
    plant = uncertain_plant_3_3_7(ex, delta=fojax.Sine(jnp.zeros(1), jnp.ones(1), jnp.zeros(1)))
    x0 = jnp.concatenate([jnp.full((6,), 0.5), jnp.zeros(3)])

    def study(seed):
        k1, k2 = jax.random.split(jax.random.PRNGKey(seed))
        return S.Study(plant, x0, jnp.linspace(0.0, 2.0, 41), ex.L_aug, None,
                       uncertainty=(S.sinusoidal_delta(k1, 2, 1, amplitude=(-0.3, 0.3), omega=(0.5, 5.0)),),
                       scenarios=(S.constant_faults(k2, 2, x0, 3, magnitude=(0.5, 1.5)),))

    return d, study


def test_tune_trains_on_the_exponential_engine_without_retracing(setup):
    d, study = setup
    train = study(0)
    res = tuning.tune(d, train, steps=1, barrier=0.0, quiet=True)
    ref = fojax.run_study(train, d.observer, quiet=True, quantiles=())
    assert ref.attrs["engine"] == "exponential-batch"
    # the step's training loss is the exponential engine's mean IAE (diffrax: ~1e-8 away)
    np.testing.assert_allclose(res.history["train_loss"][0], ref.metrics["iae"][0].mean(), rtol=1e-11)
    assert res.design.report.passed
    steps, losses = _tune.TRACE_COUNTS["tune_step"], _exponential.TRACE_COUNTS["study_loss_exponential"]
    res2 = tuning.tune(d, study(1), heldout=study(2), steps=2, barrier=0.0, quiet=True)  # new samples: data
    assert _tune.TRACE_COUNTS["tune_step"] == steps
    assert _exponential.TRACE_COUNTS["study_loss_exponential"] == losses + 1  # the held-out evaluation only
    assert np.all(np.isfinite(res2.history["train_loss"])) and res2.design.report.passed
    held = fojax.run_study(study(2), res2.design.observer, quiet=True, quantiles=())
    np.testing.assert_allclose(res2.final_heldout, held.metrics["iae"][0].mean(), rtol=1e-9)


def test_tune_over_several_devices_refuses_a_study_off_the_exact_engine(setup):
    """The diffrax path's reverse mode fails inside `jax.shard_map` (equinox 0.13.8:
    "Closure-converted function called with different dynamic arguments";
    patrick-kidger/diffrax#765): measured on this study and on the Takagi–Sugeno robot arm
    before the check. `tune` now refuses before compiling anything, naming `devices`, and
    `fojax study` passes one device for such a study."""
    # private: the device rule is tested itself
    from fojax.cli import _distributed

    d, study = setup
    train = study(0)
    assert S.exact_refusal(train, (d.observer,)) is not None  # time-varying δ(t): not the exact engine
    steps = _tune.TRACE_COUNTS["tune_step"]
    with pytest.raises(fojax.errors.InputError, match=r"devices=None.*diffrax#765|diffrax#765.*devices=None"):
        tuning.tune(d, train, steps=1, quiet=True, devices=jax.devices()[:2])
    assert _tune.TRACE_COUNTS["tune_step"] == steps  # refused before the step was traced
    assert _distributed.tuning_devices(exact=False) is None  # the CLI's choice on one process
