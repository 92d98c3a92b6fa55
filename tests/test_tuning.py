"""Gradient tuning: starts at the LMI design, stays certified, improves held-out IAE, resumes exactly."""

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from helpers import uncertain_plant_3_3_7, WeightedPenalty

import fojax
from fojax import studies as S, tuning
from fojax.design import design_functional_observer, Disk

# private: TRACE_COUNTS, the no-retrace check
from fojax.tuning import _tune


# bit-for-bit equality of different programs (a shared optimizer's step against optax's own object (another program)): compiled as users get it
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
