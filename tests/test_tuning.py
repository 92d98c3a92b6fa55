"""`fojax.tune`: gradient tuning of observer gains over a study. It starts at the LMI design,
stays certified, improves the held-out IAE and resumes exactly; its step rule at the region's
boundary; new numbers (region, δ range, key, gains) reuse the compiled step; the tuning
package imports other packages only through their public paths.

**Tuning.** Oracles: the LMI design's own observer (reproduced by `initial_parameters`),
SciPy's Stein solver and the disk test by NumPy eigenvalues, the float64 verification of the
tuned design and the Stein inequality of its certificate, the held-out IAE of samples never
seen in training, the uninterrupted run for a resumed one (bit for bit), and the trace counter
of the jitted step.

**Step rule** (`fojax.tuning._loop.backtracked_update`, on the host, a private piece tested
itself).
Oracle: closed forms. The admissible set is the unit disk of the parameters,
``margin(θ) = 1 − ‖θ‖²`` (gradient ``−2θ``), so which halving of an update stays inside, and
what the update without its outward component is, follow by hand.

Regression (issue 14): at an iterate on the boundary whose update points outside, every halving
of the update is outside, the step was rejected and the next update pointed the same way — the
iterate stopped moving (the LC filter tuned with ``barrier=0``: 79 of 100 steps rejected). Now
the halvings of the tangential update are tried when no halving of the update is admissible.

**Data are leaves.**
Oracles: the trace counters of the jitted tuning step and of the differentiable study loss
(`fojax._tune.TRACE_COUNTS`, `fojax.studies._exact.TRACE_COUNTS`), and
`equinox.debug.assert_max_traces`; for the regions' host behaviour, the values given to
the constructors (equality, hashing, JSON round trip).

**Dependencies.**
Oracle: the source itself, parsed with `ast`. Before this change `fojax/tuning/` imported
18 names from private modules of other subpackages (``design._tunable``,
``studies._runner``, ``studies._sharding``), 8 of them not public anywhere
(``unflatten``, ``_atomic_write``, ``broadcast_bytes``, ``spans_processes``,
``writes_files``, ``check_same_on_every_process``, ``distributed_errors``, ``replicate``),
and a second entry point ``tune_takagi_sugeno`` wrapped ``tune``.
"""

import ast
import importlib
import json
import pathlib

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from helpers import uncertain_plant_3_3_7, WeightedPenalty

import fojax
import fojax.tuning
from fojax import studies as S, tuning
from fojax.design import design_functional_observer, Disk, HalfPlane, region_from_dict, Sector

# private: the exact study kernel is tested itself
from fojax.studies import _exact

# private: TRACE_COUNTS, the no-retrace check
from fojax.tuning import _tune
from fojax.tuning._loop import backtracked_update  # private: the step rule is tested itself


# bit-for-bit equality of different programs (a shared optimizer's step against optax's own object,
# held-out evaluation on several devices against one): compiled as users get it
pytestmark = pytest.mark.production_codegen


SIGNALS = ("z1", "z2", "f1", "f2", "f3")


@pytest.fixture(scope="module")
def setup():
    ex = fojax.models.example_3_3_7()
    region = Disk(-2.0, 1.0)
    d = design_functional_observer(ex.augmented, ex.L_aug, kind="generalized", region=region)
    plant = uncertain_plant_3_3_7(ex)
    x0 = jnp.zeros(9).at[:4].set(jnp.array([1.0, -0.5, 0.5, 0.2]))
    u = fojax.Sine(jnp.array([1.0, 0.5]), jnp.array([1.0, 2.0]))
    ts = jnp.linspace(0.0, 4.0, 81)
    key = jax.random.PRNGKey(11)
    k1, k2, k3, k4 = jax.random.split(key, 4)

    def study(kd, kf, nu, nf):
        return S.Study(plant, x0, ts, ex.L_aug, u,
                       uncertainty=(S.constant_delta(kd, nu, 1, bounds=(-1.0, 1.0)),),
                       scenarios=(S.constant_faults(kf, nf, x0, 3),), signal_names=SIGNALS)

    # training and held-out samples come from independent keys (never shared)
    # the error is linear in the fault: many fault directions in training, few δ values
    return ex, d, study(k1, k2, 8, 32), study(k3, k4, 16, 16)


@pytest.mark.parametrize("parameterization", ["direct", "disk"])
def test_initial_parameters_reproduce_the_lmi_design(setup, parameterization):
    _, d, _, _ = setup
    fx, params = tuning.initial_parameters(d, parameterization=parameterization)
    obs, margin = tuning.observer_from_parameters(fx, params)
    assert float(margin) > 0
    for name in ("N", "J", "F", "H", "S", "G", "M", "P", "Q"):
        assert np.allclose(getattr(obs, name), getattr(d.observer, name), atol=1e-9), name


def test_stein_certificate_matches_scipy_and_detects_the_disk(setup, rng):
    _, d, _, _ = setup
    import scipy.linalg

    from fojax.design import stein_certificate

    for shift in (0.0, 0.5, -0.5):
        A = d.error_matrix + shift * np.eye(d.error_matrix.shape[0])
        inside = bool(np.all(np.abs(np.linalg.eigvals(A) + 2.0) < 1.0))
        P = np.asarray(stein_certificate(jnp.asarray(A), -2.0, 1.0))
        if inside:
            X = scipy.linalg.solve_discrete_lyapunov((A + 2.0 * np.eye(len(A))).T, np.eye(len(A)))
            np.testing.assert_allclose(P, X, rtol=1e-9, atol=1e-9)
            assert np.linalg.eigvalsh(P)[0] >= 1 - 1e-12
        else:  # the doubling overflows outside the disk: no finite positive definite P
            assert not (np.all(np.isfinite(P)) and np.linalg.eigvalsh(P)[0] > 0)


#: the jitted tuning step is keyed on the optimizer object: the tests below ask
#: `shared_optimizer` for the same configuration each time and so share one compilation
ADAM = tuning.shared_optimizer("adam", learning_rate=0.1)


def _gain_size(obs, p):  # a user term: the size of the output-injection gain F, ‖F‖²
    return jnp.sum(obs.F**2)


GAIN_WEIGHT = 0.05
NO_PENALTY = WeightedPenalty(0.0, _gain_size)  # the module's tunings: one compiled step (helpers)


def test_tuning_improves_heldout_iae_and_stays_certified(setup):
    _, d, train, heldout = setup
    before = _tune.TRACE_COUNTS["tune_step"]
    res = tuning.tune(d, train, heldout=heldout, steps=30, optimizer=ADAM, stepper=fojax.Exact(),
                      eval_every=30, extra_loss=NO_PENALTY)
    assert _tune.TRACE_COUNTS["tune_step"] == before + 1  # one jitted step, compiled once
    assert all(res.history["accepted"]) and min(res.history["margin"]) > 0
    reduction = 1 - res.final_heldout / res.initial_heldout
    print(f"held-out mean IAE: LMI {res.initial_heldout:.4f} → tuned {res.final_heldout:.4f} "
          f"({100 * reduction:.1f} % lower)")
    # The issue asks for 30 %. The notebook's run (60 steps, 256 training and 1,024 held-out
    # samples) reaches 19 %, and its last cell measures why 30 % is out of reach on this
    # benchmark. This short run (30 steps, measured 15 %) must reach 10 % (the fixed-certificate
    # "disk" parameterization reached 8 % with Z fixed).
    assert reduction > 0.10
    rep = res.design.report
    assert rep.relative_residual <= 1e-8
    eigs = np.linalg.eigvals(res.design.error_matrix)
    assert d.region.contains(eigs) and np.all(np.abs(eigs + 2.0) < 1.0)
    # the returned certificate is the Stein solution of the tuned error dynamics
    A = res.design.error_matrix + 2.0 * np.eye(len(eigs))
    assert np.linalg.eigvalsh(A.T @ res.design.X @ A - res.design.X)[-1] < 0


def test_resume_from_checkpoint_equals_uninterrupted(setup, tmp_path):
    # the same study, optimizer and settings as above: the compiled step is reused
    _, d, train, _ = setup
    # asked for anew: the same configuration gives the same object, hence the same compiled step
    opts = dict(optimizer=tuning.shared_optimizer("adam", learning_rate=0.1), stepper=fojax.Exact(),
                extra_loss=NO_PENALTY)
    assert opts["optimizer"] is ADAM
    before = _tune.TRACE_COUNTS["tune_step"]
    full = tuning.tune(d, train, steps=4, **opts)
    path = tmp_path / "ckpt"
    tuning.tune(d, train, steps=2, checkpoint=path, **opts)
    resumed = tuning.tune(d, train, steps=4, checkpoint=path, resume=True, **opts)
    for k in full.params:
        assert np.array_equal(np.asarray(full.params[k]), np.asarray(resumed.params[k])), k
    assert full.history.keys() == resumed.history.keys()
    for k in full.history:
        assert np.array_equal(np.asarray(full.history[k], dtype=float),
                              np.asarray(resumed.history[k], dtype=float), equal_nan=True), k
    assert resumed.history["step"] == [1, 2, 3, 4]
    # the parameters moved (a resume that silently restarted or froze would still be equal)
    assert any(not np.array_equal(np.asarray(full.params[k]), np.asarray(v))
               for k, v in tuning.initial_parameters(d)[1].items())
    assert _tune.TRACE_COUNTS["tune_step"] <= before + 1


def test_tune_shows_progress_unless_quiet(setup, capsys):
    # long-running work shows progress (a tqdm bar on stderr, like run_study's); quiet=True: none
    _, d, train, _ = setup
    opts = dict(steps=2, stepper=fojax.Exact(), extra_loss=NO_PENALTY, optimizer=ADAM)
    tuning.tune(d, train, **opts)
    err = capsys.readouterr().err
    assert "tune" in err and "2/2" in err, err
    tuning.tune(d, train, quiet=True, **opts)
    assert capsys.readouterr().err == ""


def test_resume_refuses_the_checkpoint_of_another_run(tmp_path):
    # A checkpoint is the state of one run: resuming it with another optimizer (another state
    # layout) or other coordinates must say so, not fail on a missing array or load the wrong
    # arrays into the state.
    # private: the checkpoint pair is tested itself
    from fojax.tuning._loop import load_checkpoint, save_checkpoint

    path = str(tmp_path / "ckpt")
    xi = {"xi": jnp.arange(3.0)}
    adam = optax.adam(0.1)
    state = adam.init(xi)
    save_checkpoint(path, xi, state, 2, jax.random.PRNGKey(0), {"step": [1, 2]})
    p, s, step, _, _ = load_checkpoint(path, xi, state)  # the same run: restored
    assert step == 2 and np.array_equal(p["xi"], xi["xi"])
    others = [(xi, optax.sgd(0.1, momentum=0.9).init(xi)),  # another optimizer: fewer arrays
              (xi, optax.sgd(0.1).init(xi)),  # one without state
              (xi, optax.chain(optax.scale_by_adam(), optax.trace(0.9)).init(xi)),  # more arrays
              ({"xi": jnp.zeros(4)}, adam.init({"xi": jnp.zeros(4)}))]  # other coordinates: shapes
    for params, st in others:
        with pytest.raises(fojax.errors.InputError, match="holds the tuning state of another run"):
            load_checkpoint(path, params, st)


def test_non_disk_region_is_refused(setup):
    _, d, _, _ = setup
    with pytest.raises(fojax.errors.InputError, match="disk regions only"):
        tuning.initial_parameters(d, fojax.design.HalfPlane(0.5))


def test_shared_optimizer_is_one_object_per_configuration_and_refuses_bad_input():
    a = tuning.shared_optimizer("adam", learning_rate=0.1)
    assert tuning.shared_optimizer(learning_rate=0.1, name="adam") is a
    assert tuning.shared_optimizer("adam", learning_rate=0.2) is not a
    assert tuning.shared_optimizer("sgd", learning_rate=0.1) is not a
    # the same transformation as optax's: one update from the same state agrees
    p = {"w": jnp.array([1.0, -2.0])}
    g = {"w": jnp.array([0.3, 0.5])}
    ours, _ = a.update(g, a.init(p), p)
    ref = optax.adam(0.1)
    theirs, _ = ref.update(g, ref.init(p), p)
    np.testing.assert_array_equal(ours["w"], theirs["w"])
    with pytest.raises(fojax.errors.InputError, match="no optimizer named 'adamm'"):
        tuning.shared_optimizer("adamm", learning_rate=0.1)
    with pytest.raises(fojax.errors.InputError, match="must be hashable"):
        tuning.shared_optimizer("adam", learning_rate=[0.1])


def test_a_new_learning_rate_reuses_the_compiled_step(setup):
    # A learning-rate sweep must not recompile the step (issue 13: new numbers never
    # recompile): `shared_optimizer` gives the step its float hyperparameters as data.
    # Oracle: the same run with optax's own object, whose learning rate is a constant of its
    # own program (compiled once more): the same iterates bit for bit.
    _, d, train, _ = setup
    opts = dict(steps=3, stepper=fojax.Exact(), extra_loss=NO_PENALTY)
    tuning.tune(d, train, optimizer=ADAM, **opts)  # the module's step (learning rate 0.1)
    before = _tune.TRACE_COUNTS["tune_step"]
    runs = {lr: tuning.tune(d, train, optimizer=tuning.shared_optimizer("adam", learning_rate=lr), **opts)
            for lr in (0.05, 0.2)}
    assert _tune.TRACE_COUNTS["tune_step"] == before  # two new learning rates, no new trace
    plain = tuning.tune(d, train, optimizer=optax.adam(0.2), **opts)
    assert _tune.TRACE_COUNTS["tune_step"] == before + 1  # a plain optax object: its own program
    for k in plain.params:
        assert np.array_equal(np.asarray(plain.params[k]), np.asarray(runs[0.2].params[k])), k
    assert plain.history["train_loss"] == runs[0.2].history["train_loss"]
    # the learning rate took effect: the two shared runs moved differently
    assert runs[0.05].history["train_loss"][-1] != runs[0.2].history["train_loss"][-1]


def test_a_new_quantile_level_reuses_the_compiled_step(setup):
    # The quantile level is data of the step too. Oracle: the first step's training loss
    # (barrier 0: the loss alone) at the LMI design is `np.quantile` of the per-sample IAEs
    # (mean over the signals) that `run_study` reports on the same samples (exact engine).
    _, d, train, _ = setup
    opts = dict(steps=1, stepper=fojax.Exact(), extra_loss=NO_PENALTY, optimizer=ADAM, barrier=0.0)
    tuning.tune(d, train, quantile=0.9, **opts)
    before = _tune.TRACE_COUNTS["tune_step"]
    res = fojax.run_study(train, [d.observer], quantiles=(), stepper=fojax.Exact())
    per = np.asarray(res.metrics["iae"])[0].reshape(-1, train.num_signals).mean(axis=1)
    for q in (0.5, 0.75):
        first = tuning.tune(d, train, quantile=q, **opts).history["train_loss"][0]
        assert first == pytest.approx(np.quantile(per, q), rel=1e-9), q
    assert _tune.TRACE_COUNTS["tune_step"] == before  # two new levels, no new trace
    for bad in (1.5, -0.1, "high"):
        with pytest.raises(fojax.errors.InputError, match="quantile must be a number in"):
            tuning.tune(d, train, quantile=bad, **opts)


def test_shared_optimizer_keeps_untraceable_hyperparameters_as_constants(monkeypatch):
    # an optax function that branches on a float hyperparameter in Python cannot take it as
    # data: `shared_optimizer` then hands tune the object itself (one program per value)
    import optax as _optax

    # private: the optimizer spec is tested itself
    from fojax.tuning import _optimizer

    def branching(learning_rate):
        if learning_rate > 0.5:  # a Python branch on the value: fails on a tracer
            return _optax.sgd(learning_rate)
        return _optax.adam(learning_rate)

    monkeypatch.setattr(_optax, "fojax_test_branching", branching, raising=False)
    opt = tuning.shared_optimizer("fojax_test_branching", learning_rate=0.1)
    assert _optimizer.step_optimizer(opt) is opt
    spec = _optimizer.step_optimizer(tuning.shared_optimizer("adam", learning_rate=0.3, nesterov=True))
    assert isinstance(spec, _optimizer.OptimizerSpec)
    assert spec.static == (("nesterov", True),) and float(spec.numeric["learning_rate"]) == 0.3


def test_extra_loss_is_part_of_the_objective_and_changes_the_result(setup):
    _, d, train, _ = setup
    opts = dict(steps=5, optimizer=ADAM, stepper=fojax.Exact())
    before = _tune.TRACE_COUNTS["tune_step"]
    plain = tuning.tune(d, train, extra_loss=NO_PENALTY, **opts)  # both: the module's compiled step
    pen = tuning.tune(d, train, extra_loss=WeightedPenalty(GAIN_WEIGHT, _gain_size), **opts)
    assert _tune.TRACE_COUNTS["tune_step"] == before  # a new weight is new data, not a new program
    # step 0 is evaluated at the LMI design: the objectives differ by the term, computed here
    # from the design's own F in NumPy
    F0 = np.asarray(d.observer.F)
    np.testing.assert_allclose(pen.history["train_loss"][0] - plain.history["train_loss"][0],
                               GAIN_WEIGHT * np.sum(F0**2), rtol=1e-10)
    # its gradient acts: after 5 steps the penalized run has the smaller gain, and a valid design
    normF = [float(np.linalg.norm(np.asarray(r.design.observer.F))) for r in (plain, pen)]
    assert normF[1] < normF[0] and normF[1] < np.linalg.norm(F0)
    assert pen.design.report.passed and pen.design.report.relative_residual <= 1e-8
    assert pen.design.solver["tuning"]["extra_loss"] == "WeightedPenalty"


@pytest.mark.parametrize("bad, match", [
    (3.0, "must be a function"),
    (lambda obs, p: obs.F, "must return a real scalar"),
    (lambda obs, p: jnp.inf * jnp.sum(obs.F), "must be finite"),
])
def test_extra_loss_is_checked_before_compiling(setup, bad, match):
    _, d, train, _ = setup
    before = _tune.TRACE_COUNTS["tune_step"]
    with pytest.raises(fojax.errors.InputError, match=match):
        tuning.tune(d, train, steps=1, optimizer=ADAM, extra_loss=bad)
    assert _tune.TRACE_COUNTS["tune_step"] == before


# ==================================================================================================
# Data are leaves: tuning with new numbers (region, δ range, key, gains) reuses the compiled step.
# ==================================================================================================



@pytest.fixture(scope="module")
def setup_retrace():
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


def test_tune_with_new_region_delta_range_key_and_gains_does_not_retrace(setup_retrace):
    ex, study = setup_retrace
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


def test_heldout_evaluation_on_several_devices_compiles_once(setup_retrace):
    """With `devices` (as `fojax study` passes on one JAX device per core) the held-out loss
    of the starting design and of every iterate is one program: the iterates live on the
    mesh (replicated), so the starting parameters are placed there too (they were not, and
    the evaluation compiled twice: issue 13). Oracle: the trace counter of the evaluation,
    and the one-device run's history (the same bits on any number of devices)."""
    ex, study = setup_retrace
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


# ==================================================================================================
# The tuning package's dependencies on the rest of fojax (issue 14, item 1).
# ==================================================================================================


#: The ground floor every package may use (ARCHITECTURE.md).
GROUND = {"_errors", "_io", "_dtype", "_linalg", "_background"}  # + docs/CONTRIBUTING.md's worker-thread helper


def _cross_package_imports():
    for path in sorted(pathlib.Path(fojax.tuning.__file__).parent.glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.level >= 2:  # from ..x import y
                yield path.name, node.module or "", [a.name for a in node.names]


def test_tuning_imports_only_public_subpackage_names():
    seen = 0
    for fname, module, names in _cross_package_imports():
        parts = module.split(".")
        if parts[0] in GROUND:
            continue
        assert not any(p.startswith("_") for p in parts), f"{fname}: from ..{module} (a private module)"
        sub = importlib.import_module(f"fojax.{module}")
        for name in names:
            assert not name.startswith("_"), f"{fname}: {name} from ..{module}"
            assert hasattr(sub, name), f"{fname}: fojax.{module} does not export {name}"
            seen += 1
    assert seen >= 14  # design: 7 names, studies: 7 + 3 (the check is not vacuous)


def test_one_tune():
    assert not hasattr(fojax.tuning, "tune_takagi_sugeno")
    assert fojax.tuning.tune.__module__ == "fojax.tuning._tune"


# ==================================================================================================
# The step rule of `fojax.tuning.tune` (`fojax.tuning._loop.backtracked_update`, on the host) at the
# region's boundary.
# ==================================================================================================


MIN_MARGIN = 1e-6
N_BACK = 8


def margin(theta):
    return 1.0 - jnp.sum(theta["a"] ** 2) - jnp.sum(theta["b"] ** 2)


margin_host = jax.jit(margin)
CALLS = {"margin": 0, "grad": 0}


def counted_margin(theta):
    CALLS["margin"] += 1
    return float(margin_host(theta))


def counted_grad(theta):
    CALLS["grad"] += 1
    return jax.grad(margin)(theta)


def step(p, u):
    CALLS.update(margin=0, grad=0)
    return backtracked_update(p, u, counted_margin, MIN_MARGIN, N_BACK, counted_grad)


def at_boundary(m0=1e-5):
    """θ on the a-axis with margin m0 (a = √(1 − m0)); parameters as a pytree of two leaves."""
    return {"a": jnp.array([np.sqrt(1.0 - m0), 0.0]), "b": jnp.array([0.0])}


def test_regression_outward_update_at_the_boundary_slides_along_it():
    p = at_boundary()
    u = {"a": jnp.array([0.1, 0.1]), "b": jnp.array([0.05])}  # outward (first entry) and tangential
    # every halving of u is outside: 1e-5 − 0.2·s·a − 0.0125·s² < 0 for s ≥ 2^-8 (closed form)
    s = 0.5 ** np.arange(N_BACK + 1)
    a0 = float(p["a"][0])
    assert np.all(1e-5 - 2 * 0.1 * s * a0 - (0.01 + 0.01 + 0.0025) * s**2 <= MIN_MARGIN)
    new, m, accepted, backtracks = step(p, u)
    assert bool(accepted)  # failed before the fix (rejected, parameters unchanged)
    # the tangential update removes u's component along g = −2θ = (−2a, 0; 0): u_t = (0, 0.1; 0.05);
    # its halvings: margin 1e-5 − 0.0125 s² > 1e-6 first at s = 2^-6 (closed form)
    expected_s = next(sc for sc in s if 1e-5 - 0.0125 * sc**2 > MIN_MARGIN)
    assert expected_s == 0.5**6
    np.testing.assert_allclose(np.asarray(new["a"]), [a0, 0.1 * expected_s], rtol=0, atol=1e-15)
    np.testing.assert_allclose(np.asarray(new["b"]), [0.05 * expected_s], rtol=0, atol=1e-15)
    np.testing.assert_allclose(float(m), 1e-5 - 0.0125 * expected_s**2, rtol=1e-9)
    assert int(backtracks) == N_BACK + 1 + 6
    assert float(margin(new)) > MIN_MARGIN
    # every halving of u, then those of u_t up to the first admissible; one gradient
    assert CALLS == {"margin": N_BACK + 1 + 7, "grad": 1}


@pytest.mark.parametrize("outward", [False, True])
def test_an_admissible_halving_of_the_update_is_taken_unchanged(outward):
    """Away from the boundary the rule is the old one: the first admissible halving of u itself."""
    p = {"a": jnp.array([0.5, 0.0]), "b": jnp.array([0.0])}
    # an inward update (scale 1 admissible), and an outward one whose first admissible halving is
    # 2^-4: margin(0.5 + 4s) = 0.75 − 4s − 16 s² is 0 at s = 1/8 and 0.4375 at s = 1/16 (closed form)
    u = ({"a": jnp.array([4.0, 0.0]), "b": jnp.array([0.0])} if outward
         else {"a": jnp.array([-0.2, 0.1]), "b": jnp.array([0.1])})
    s = 0.5 ** np.arange(N_BACK + 1)
    ms = [float(margin(jax.tree.map(lambda x, d: x + sc * d, p, u))) for sc in s]
    first = next(i for i, v in enumerate(ms) if v > MIN_MARGIN)
    assert first == (4 if outward else 0)
    new, m, accepted, backtracks = step(p, u)
    assert bool(accepted) and int(backtracks) == first
    for k in ("a", "b"):
        np.testing.assert_allclose(np.asarray(new[k]), np.asarray(p[k] + s[first] * u[k]), rtol=0, atol=1e-15)
    np.testing.assert_allclose(float(m), ms[first], rtol=1e-12)
    # evaluated in turn up to the first admissible candidate; no gradient needed
    assert CALLS == {"margin": first + 1, "grad": 0}


def test_no_admissible_candidate_keeps_the_parameters():
    """An update straight outward has no tangential part: the step is rejected, θ unchanged."""
    p = at_boundary()
    u = {"a": jnp.array([0.1, 0.0]), "b": jnp.array([0.0])}
    new, m, accepted, _ = step(p, u)
    assert not bool(accepted)
    for k in ("a", "b"):
        np.testing.assert_array_equal(np.asarray(new[k]), np.asarray(p[k]))
    assert float(m) < 0  # the full step's margin
