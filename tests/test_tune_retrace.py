"""Data are leaves: tuning with new numbers (region, δ range, key, gains) reuses the compiled step.

Oracles: the trace counters of the jitted tuning step and of the differentiable study loss
(`fojax._tune.TRACE_COUNTS`, `fojax.studies._exact.TRACE_COUNTS`), and
`equinox.debug.assert_max_traces`; for the regions' host behaviour, the values given to
the constructors (equality, hashing, JSON round trip).
"""

import json

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import uncertain_plant_3_3_7

import fojax
from fojax import studies as S, tuning
from fojax.design import design_functional_observer, Disk, HalfPlane, region_from_dict, Sector

# private: the exact study kernel is tested itself
from fojax.studies import _exact
from fojax.tuning import _tune


# bit-for-bit equality of different programs (held-out evaluation on several devices against one): compiled as users get it
pytestmark = pytest.mark.production_codegen


@pytest.fixture(scope="module")
def setup():
    ex = fojax.models.example_3_3_7()
    plant = uncertain_plant_3_3_7(ex)
    x0 = jnp.zeros(9).at[:6].set(0.5)

    def study(seed, bounds):
        k1, k2 = jax.random.split(jax.random.PRNGKey(seed))
        return S.Study(plant, x0, jnp.linspace(0.0, 1.0, 21), ex.L_aug, None,
                       uncertainty=(S.constant_delta(k1, 2, 1, bounds=bounds),),
                       scenarios=(S.constant_faults(k2, 2, x0, 3),))

    return ex, study


def test_regions_numbers_are_leaves_with_float_host_behaviour():
    d = Disk(-2.5, 1.2)
    assert d == Disk(-2.5, 1.2) and d != Disk(-2.0, 1.0) and hash(d) == hash(Disk(-2.5, 1.2))
    assert d.describe() == "disk centred at -2.5 with radius 1.2"
    for r in (d, HalfPlane(0.5), Sector(0.7), d & HalfPlane(1.0)):
        assert region_from_dict(json.loads(json.dumps(r.to_dict()))) == r
        assert all(eqx.is_array(x) for x in jax.tree.leaves(r))

    @eqx.filter_jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def shift(region, z):
        return z - region.center + region.radius

    assert float(shift(Disk(-2.0, 1.0), 0.0)) == 3.0
    assert float(shift(Disk(-2.5, 1.2), 0.0)) == 3.7  # new numbers: no second trace


def test_tune_with_new_region_delta_range_key_and_gains_does_not_retrace(setup):
    ex, study = setup
    d1 = design_functional_observer(ex.augmented, ex.L_aug, kind="generalized", region=Disk(-2.0, 1.0))
    d2 = design_functional_observer(ex.augmented, ex.L_aug, kind="generalized", region=Disk(-2.5, 1.2))
    assert not np.allclose(d1.params["Y1"], d2.params["Y1"])  # other gains
    tuning.tune(d1, study(0, (-0.3, 0.3)), steps=1, stepper=fojax.Exact())  # compiles the step once
    steps, losses = _tune.TRACE_COUNTS["tune_step"], _exact.TRACE_COUNTS["study_loss_exact"]
    runs = [
        dict(design=d1, train_study=study(0, (-0.3, 0.3)), region=Disk(-2.1, 1.5)),  # new region numbers
        dict(design=d1, train_study=study(1, (-0.8, 0.5))),  # new δ range and samples
        dict(design=d1, train_study=study(0, (-0.3, 0.3)), key=jax.random.PRNGKey(5)),  # new key
        dict(design=d2, train_study=study(0, (-0.3, 0.3))),  # new gains, new region (the design's)
    ]
    for kw in runs:
        res = tuning.tune(steps=1, stepper=fojax.Exact(), **kw)
        assert np.isfinite(res.history["train_loss"][0])
        assert res.design.report.passed
    assert _tune.TRACE_COUNTS["tune_step"] == steps
    assert _exact.TRACE_COUNTS["study_loss_exact"] == losses


def test_heldout_evaluation_on_several_devices_compiles_once(setup):
    """With `devices` (as `fojax study` passes on one JAX device per core) the held-out loss
    of the starting design and of every iterate is one program: the iterates live on the
    mesh (replicated), so the starting parameters are placed there too (they were not, and
    the evaluation compiled twice: issue 13). Oracle: the trace counter of the evaluation,
    and the one-device run's history (the same bits on any number of devices)."""
    ex, study = setup
    d = design_functional_observer(ex.augmented, ex.L_aug, kind="generalized", region=Disk(-2.0, 1.0))
    kw = dict(train_study=study(0, (-0.3, 0.3)), heldout=study(3, (-0.3, 0.3)), steps=2, eval_every=1,
              stepper=fojax.Exact())
    before = _tune.TRACE_COUNTS["evaluate"]
    two = tuning.tune(d, devices=jax.devices()[:2], **kw)
    assert _tune.TRACE_COUNTS["evaluate"] - before == 1
    one = tuning.tune(d, **kw)
    assert two.initial_heldout == one.initial_heldout and two.final_heldout == one.final_heldout
    assert two.history["heldout_loss"] == one.history["heldout_loss"]
    assert two.history["train_loss"] == one.history["train_loss"]
