"""fojax.interop: python-control, SciPy and MATLAB files in and out; the feedthrough D.

Oracles: python-control (`control.ss`, `control.evalfr`, `control.forced_response`,
`control.poles`), SciPy (`scipy.signal.lsim`, `scipy.signal.StateSpace`,
`scipy.io.savemat` / `loadmat`) and the descriptor system's transfer function
C (sE - A)^{-1} B + D evaluated by `numpy.linalg.solve`.
"""

import control
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.io
import scipy.signal as sig
from helpers import assert_eigenvalues_match, random_descriptor

import fojax
from fojax.interop import (
    from_control,
    from_scipy,
    load_mat,
    save_mat,
    state_space,
    to_control,
    to_scipy,
)


def _plant(seed=7, n=4, m=2, p=2):
    """A stable state-space model with feedthrough, built in python-control."""
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((n, n)) - 2.5 * np.eye(n)
    B, C, D = rng.standard_normal((n, m)), rng.standard_normal((p, n)), rng.standard_normal((p, m))
    return control.ss(A, B, C, D), rng.standard_normal((1, n))


def _tf(E, A, B, C, D, s):
    return C @ np.linalg.solve(s * E - A, B) + D


def test_control_model_with_D_designs_and_exports_with_poles_in_the_region():
    P, L = _plant()
    plant = from_control(P)
    np.testing.assert_array_equal(np.asarray(plant.D), P.D)
    np.testing.assert_array_equal(np.asarray(plant.E), np.eye(4))
    region = fojax.Disk(-3.0, 1.5)
    design = fojax.design_functional_observer(plant, L, region=region)
    Obs = to_control(design)
    assert (Obs.ninputs, Obs.noutputs) == (plant.m + plant.p, 1)
    assert Obs.input_labels == ["u[0]", "u[1]", "y[0]", "y[1]"]
    poles = control.poles(Obs)
    assert len(poles) == design.observer.state_size
    assert all(abs(lam + 3.0) < 1.5 for lam in poles)
    assert_eigenvalues_match(poles, np.linalg.eigvals(np.asarray(design.observer.error_matrix)))
    # the exported plant is the python-control model itself
    back = to_control(plant)
    for k in "ABCD":
        np.testing.assert_array_equal(getattr(back, k), getattr(P, k))


def test_observer_for_a_plant_with_D_estimates_Lx():
    """The observer takes the measured y = Cx + Du: on data simulated by SciPy (lsim of the
    plant) its python-control simulation converges to L x; the D-free observer does not."""
    P, L = _plant(seed=11)
    plant = from_control(P)
    design = fojax.design_functional_observer(plant, L, region=fojax.Disk(-3.0, 1.5))
    nominal = fojax.design_functional_observer(plant.replace(D=np.zeros((2, 2))), L, region=fojax.Disk(-3.0, 1.5))
    ts = np.linspace(0.0, 10.0, 1001)
    u = np.stack([np.sin(1.1 * ts), 0.5 + np.cos(0.4 * ts)], axis=1)
    _, y, x = sig.lsim((P.A, P.B, P.C, P.D), u, ts, X0=np.ones(4))
    zx = x @ L.T
    for d, converges in ((design, True), (nominal, False)):
        zh = control.forced_response(to_control(d), T=ts, U=np.vstack([u.T, y.T])).outputs.reshape(-1, len(ts))[0]
        err = np.abs(zh[-100:] - zx[-100:, 0]).max()
        assert (err < 1e-4 * np.abs(zx).max()) == converges, err


def test_feedthrough_in_simulation_and_in_augment_faults():
    """fojax.simulate's plant output carries D u and the folded observer converges (exact
    and diffrax steppers); augment_faults keeps D. Oracle: y = C x + D u from the states."""
    sys0, L, _, _ = random_descriptor(3)
    D = np.array([[0.5], [-1.0], [2.0]])
    sys_ = sys0.replace(D=D)
    design = fojax.design_functional_observer(sys_, L)
    np.testing.assert_allclose(np.asarray(design.observer.Wu),
                               np.asarray(fojax.design_functional_observer(sys0, L).observer.Wu)
                               - np.asarray(design.observer.Wy) @ D, atol=1e-12)
    ts = jnp.linspace(0.0, 8.0, 161)
    u = fojax.Sine(jnp.ones(1), 1.3)
    for stepper in (fojax.Exact(), fojax.Diffrax()):
        sol = fojax.simulate(sys_, jnp.ones(5), ts, u, observers=[design.observer], stepper=stepper)
        np.testing.assert_allclose(sol.ys, sol.xs @ np.asarray(sys_.C).T + sol.us @ D.T, atol=1e-10)
        e = np.abs(np.asarray(sol.estimates[0] - sol.xs @ L.T))
        assert e[-1].max() < 1e-3 * e[0].max()
    aug = fojax.plant.augment_faults(sys_, Fs=np.eye(3)[:, :1])
    np.testing.assert_array_equal(np.asarray(aug.D), D)


def test_descriptor_export_is_its_exact_state_space_equivalent():
    """An impulse-free descriptor system exports to the state-space model with the same
    transfer function C (sE - A)^{-1} B + D (at several s, python-control's evalfr)."""
    sys0, _, _, _ = random_descriptor(5)
    D = np.arange(3.0)[:, None]
    sys_ = sys0.replace(D=D)
    E, A, B, C = (np.asarray(getattr(sys_, k)) for k in "EABC")
    P = to_control(sys_)
    assert P.nstates == 4  # rank E
    for s in (0.3, 2.0 + 1.0j, -0.7 + 3.0j, 10.0j):
        np.testing.assert_allclose(control.evalfr(P, s), _tf(E, A, B, C, D, s), rtol=1e-10, atol=1e-12)
    S = to_scipy(sys_)
    assert isinstance(S, sig.StateSpace)
    for k in "ABCD":
        np.testing.assert_array_equal(getattr(S, k), getattr(P, k))


def test_impulsive_and_irregular_systems_are_refused():
    E = np.array([[0.0, 1.0], [0.0, 0.0]])
    A = np.eye(2)
    with pytest.raises(fojax.errors.ImpulsiveSystemError):
        to_control(fojax.DescriptorSystem(E, A, np.ones((2, 1)), np.ones((1, 2))))
    with pytest.raises(fojax.errors.IrregularSystemError):
        to_control(fojax.DescriptorSystem(np.diag([1.0, 0.0]), np.diag([1.0, 0.0]), np.ones((2, 1))))


def test_scipy_models_and_tuples_convert():
    P, _ = _plant(seed=2, m=1, p=1)
    for model in (sig.StateSpace(P.A, P.B, P.C, P.D), (P.A, P.B, P.C, P.D)):
        plant = from_scipy(model)
        for k in "ABCD":
            np.testing.assert_allclose(np.asarray(getattr(plant, k)), getattr(P, k))
    # a transfer function: SciPy's own state-space realisation, same frequency response
    tf = sig.TransferFunction([1.0, 3.0], [1.0, 2.0, 5.0])
    plant = from_scipy(tf)
    A, B, C, D = state_space(plant)
    for w in (0.7, 2.0):
        want = np.polyval(tf.num, 1j * w) / np.polyval(tf.den, 1j * w)
        np.testing.assert_allclose(_tf(np.eye(2), A, B, C, D, 1j * w)[0, 0], want, rtol=1e-12)
    E = np.diag([2.0, 1.0])
    assert np.array_equal(np.asarray(from_scipy(tf, E=E).E), E)
    # a python-control transfer function
    plant = from_control(control.tf([1.0], [1.0, 1.0]))
    assert (plant.n, plant.m, plant.p) == (1, 1, 1)


def test_every_observer_kind_exports_with_inputs_u_y():
    """Generalized / PI / proportional, unknown-input and finite-time observers: the export's
    response to [u; y] is the observer's own (linear_matrices), checked on one frequency."""
    ex = fojax.models.example_3_1_2()
    kinds = [fojax.design_functional_observer(ex.system, ex.L, kind=k) for k in ("generalized", "PI", "proportional")]
    kinds.append(fojax.design_finite_time_observer(ex.system, ex.L, h=0.5))
    for d in kinds:
        lm = d.observer.linear_matrices()
        S = to_control(d.observer)
        assert S.ninputs == ex.system.m + ex.system.p
        s = 0.4 + 1.1j
        want = np.asarray(lm.C) @ np.linalg.solve(s * np.eye(lm.A.shape[0]) - np.asarray(lm.A),
                                                  np.hstack([lm.Bu, lm.By])) + np.hstack([lm.Du, lm.Dy])
        np.testing.assert_allclose(control.evalfr(S, s), want, rtol=1e-10, atol=1e-12)


def test_takagi_sugeno_observer_export_names_the_rule_fix():
    ex = fojax.models.robot_arm_ts()
    d = fojax.design_ts_observer(ex.system, np.asarray(ex.system.C)[:1])
    with pytest.raises(fojax.errors.InputError, match=r"observer\.rule\(i\)"):
        to_control(d)
    assert to_control(d.observer.rule(0)).ninputs == ex.system.m + ex.system.p


def test_wrong_objects_get_clear_errors():
    P, _ = _plant()
    with pytest.raises(fojax.errors.InputError, match="from_control"):
        fojax.DescriptorSystem(P)
    with pytest.raises(fojax.errors.InputError, match="from_control"):
        fojax.DescriptorSystem.from_state_space(P)
    with pytest.raises(fojax.errors.InputError, match="from_scipy"):
        fojax.DescriptorSystem.from_state_space(sig.StateSpace(P.A, P.B, P.C, P.D))
    with pytest.raises(fojax.errors.InputError, match="from_scipy"):
        from_control(sig.StateSpace(P.A, P.B, P.C, P.D))
    with pytest.raises(fojax.errors.InputError, match="from_control"):
        from_scipy(P)
    with pytest.raises(fojax.errors.ShapeError, match="D has shape"):
        fojax.DescriptorSystem(np.eye(2), np.eye(2), np.ones((2, 1)), np.ones((1, 2)), np.ones((2, 1)))
    with pytest.raises(fojax.errors.InputError, match="DescriptorSystem"):
        to_control("not a model")


# ------------------------------------------------------------------------------ .mat files


def test_load_mat_reads_any_case_and_defaults(tmp_path):
    """Oracle: scipy.io.savemat writes the file."""
    rng = np.random.default_rng(0)
    mats = {"e": np.diag([1.0, 1.0, 0.0]), "A": rng.standard_normal((3, 3)) - 3 * np.eye(3),
            "b": rng.standard_normal((3, 1)), "C": rng.standard_normal((2, 3)), "D": np.ones((2, 1)),
            "l": rng.standard_normal((1, 3)), "notes": np.array([1.0])}
    f = tmp_path / "plant.mat"
    scipy.io.savemat(f, mats)
    sys_, L = load_mat(f)
    for k in "EABCD":
        np.testing.assert_array_equal(np.asarray(getattr(sys_, k)), mats[k if k in mats else k.lower()])
    np.testing.assert_array_equal(L, mats["l"])
    scipy.io.savemat(f2 := tmp_path / "ss.mat", {"A": -np.eye(2), "B": np.ones((2, 1)), "C": np.ones((1, 2))})
    sys2, L2 = load_mat(f2)
    assert L2 is None and np.array_equal(np.asarray(sys2.E), np.eye(2)) and not np.any(np.asarray(sys2.D))


def test_load_mat_errors_name_the_variable(tmp_path):
    f = tmp_path / "bad.mat"
    scipy.io.savemat(f, {"A": -np.eye(2), "C": np.ones((1, 2))})
    with pytest.raises(fojax.errors.InputError, match=r"no variable 'B'.*it has: A, C"):
        load_mat(f)
    scipy.io.savemat(f, {"A": -np.eye(2), "a": -np.eye(2), "B": np.ones((2, 1)), "C": np.ones((1, 2))})
    with pytest.raises(fojax.errors.InputError, match="both 'A' and 'a'"):
        load_mat(f)
    scipy.io.savemat(f, {"A": -np.eye(2), "B": np.ones((3, 1)), "C": np.ones((1, 2))})
    with pytest.raises(fojax.errors.ShapeError, match="B has shape"):
        load_mat(f)
    with pytest.raises(fojax.errors.InputError, match="no .mat file"):
        load_mat(tmp_path / "missing.mat")
    (tmp_path / "text.mat").write_text("not a mat file")
    with pytest.raises(fojax.errors.InputError, match="not a readable MATLAB"):
        load_mat(tmp_path / "text.mat")


def test_save_mat_round_trip_and_never_overwrites(tmp_path):
    """A design written by save_mat, read by scipy.io.loadmat: the observer's matrices and
    its state-space form (whose python-control response equals the observer's), and the
    plant back through load_mat."""
    P, L = _plant(seed=5)
    plant = from_control(P)
    design = fojax.design_functional_observer(plant, L, region=fojax.Disk(-3.0, 1.5))
    f = tmp_path / "design.mat"
    assert save_mat(f, design) == f
    got = scipy.io.loadmat(f)
    o = design.observer
    for k in ("N", "J", "F", "H", "S", "G", "M", "P", "Q", "Wu", "Wy"):
        np.testing.assert_array_equal(got[k], np.atleast_2d(np.asarray(getattr(o, k))).reshape(got[k].shape))
    A, B, C, D = state_space(design)
    for k, want in zip(("Ao", "Bo", "Co", "Do"), (A, B, C, D)):
        np.testing.assert_array_equal(got[k], want)
    for k in "ABCD":
        np.testing.assert_array_equal(got[k], getattr(P, k))
    sys_, L2 = load_mat(f)
    np.testing.assert_array_equal(L2, L)
    np.testing.assert_array_equal(np.asarray(sys_.D), P.D)
    with pytest.raises(FileExistsError):
        save_mat(f, plant)
    save_mat(f, plant, overwrite=True)
    assert set(k for k in scipy.io.loadmat(f) if not k.startswith("__")) == set("EABCD")
    assert not list(tmp_path.glob("*.tmp*"))


def test_config_model_from_a_mat_file(tmp_path):
    """``[model] mat = "plant.mat"`` (relative to the config file) with an inline L and the
    D key; the model is the one scipy.io.savemat wrote."""
    rng = np.random.default_rng(4)
    mats = {"E": np.diag([1.0, 1.0, 0.0]), "A": rng.standard_normal((3, 3)) - 3 * np.eye(3),
            "B": rng.standard_normal((3, 1)), "C": rng.standard_normal((2, 3)), "D": np.array([[1.0], [2.0]])}
    scipy.io.savemat(tmp_path / "plant.mat", mats)
    cfg = tmp_path / "model.toml"
    cfg.write_text('[model]\nmat = "plant.mat"\nL = [[1.0, 0.0, 0.0]]\n')
    c = fojax.load_config(cfg)
    s = c.system()
    for k in "EABCD":
        np.testing.assert_array_equal(np.asarray(getattr(s, k)), mats[k])
    cfg.write_text('[model]\nmat = "plant.mat"\nA = [[1.0]]\nL = [[1.0, 0.0, 0.0]]\n')
    with pytest.raises(fojax.errors.ConfigError, match="model.A.*inline and as variable"):
        fojax.load_config(cfg)
    cfg.write_text('[model]\nmat = "nope.mat"\nL = [[1.0, 0.0, 0.0]]\n')
    with pytest.raises(fojax.errors.ConfigError, match="model.mat.*no .mat file"):
        fojax.load_config(cfg)
    cfg.write_text("[model]\nE = [[1.0]]\nA = [[-1.0]]\nB = [[1.0]]\nC = [[1.0]]\nD = [[1.0, 2.0]]\nL = [[1.0]]\n")
    with pytest.raises(fojax.errors.ConfigError, match=r"model.D.*expected \(1, 1\)"):
        fojax.load_config(cfg)


def test_saved_design_with_D_round_trips_and_tunes_with_the_fold(tmp_path):
    """save_design / load_design keep D (structure and observer); an observer rebuilt from
    the structure (what tuning does) has the folded Wu. A plant saved before D existed
    (its file has no D) loads with D = 0."""
    sys0, L, _, _ = random_descriptor(8)
    D = np.array([[1.0], [0.0], [-2.0]])
    design = fojax.design_functional_observer(sys0.replace(D=D), L)
    path = design.save(tmp_path / "d.npz")
    back = fojax.load_design(path)
    np.testing.assert_array_equal(np.asarray(back.structure.D), D)
    np.testing.assert_array_equal(np.asarray(back.observer.Wu), np.asarray(design.observer.Wu))
    from fojax.design import observer_matrices
    from fojax.design._functional import build_observer  # private: the builder is tested itself

    rebuilt = build_observer(design.structure, observer_matrices(design.structure, **design.params))
    np.testing.assert_allclose(np.asarray(rebuilt.Wu), np.asarray(design.observer.Wu), atol=1e-12)
    # private: the stored skeleton is read
    from fojax import _serialize

    arrays: dict = {}
    tree = _serialize.encode(sys0, arrays)
    del tree["fields"]["D"]
    old = _serialize.decode(tree, arrays)
    assert np.array_equal(np.asarray(old.D), np.zeros((3, 1)))


def test_closed_loops_refuse_a_plant_with_feedthrough():
    sys0, L, _, _ = random_descriptor(3)
    design = fojax.design_functional_observer(sys0, np.ones((1, 5)))
    with pytest.raises(fojax.errors.InputError, match="feedthrough"):
        fojax.control.closed_loop(sys0.replace(D=np.ones((3, 1))), design)


def test_study_of_a_plant_with_feedthrough():
    """run_study's Exact and Exponential steppers agree on a plant with D (the plant's
    output carries D u); their IAE matches a fine-grid fojax.simulate (trapezoid rule)."""
    sys0, L, _, _ = random_descriptor(3)
    sys_ = sys0.replace(D=np.array([[0.5], [-1.0], [2.0]]))
    obs = [fojax.design_functional_observer(sys_, L).observer, fojax.design_functional_observer(sys0, L).observer]
    u = fojax.Sine(jnp.ones(1), 1.3)
    study = fojax.Study(sys_, jnp.ones(5), jnp.linspace(0.0, 6.0, 121), L, u)
    exact = fojax.run_study(study, obs, stepper=fojax.Exact()).metrics["iae"]
    expo = fojax.run_study(study, obs, stepper=fojax.Exponential()).metrics["iae"]
    np.testing.assert_allclose(exact, expo, rtol=1e-8)
    ts = jnp.linspace(0.0, 6.0, 2401)
    sol = fojax.simulate(sys_, jnp.ones(5), ts, u, observers=obs)
    for k in range(2):
        e = np.abs(np.asarray(sol.estimates[k] - sol.xs @ L.T))
        np.testing.assert_allclose(np.asarray(exact)[k].ravel(), np.trapezoid(e, np.asarray(ts), axis=0), rtol=2e-3)
    assert np.asarray(exact)[0].sum() < 0.5 * np.asarray(exact)[1].sum()  # the unfolded observer is worse


def test_system_zeros_use_the_feedthrough():
    """Invariant zeros of a model with D: python-control's `control.zeros` as oracle."""
    P, _ = _plant(seed=9, m=1, p=1)
    zeros = fojax.analysis.system_zeros(from_control(P)).invariant_zeros
    want = control.zeros(P)
    assert len(want) == 4 and len(zeros) == 4  # D != 0: n finite zeros
    assert_eigenvalues_match(zeros, want, rtol=1e-8)


def test_finite_time_observer_for_a_plant_with_feedthrough():
    """Both observers of a finite-time design take y = Cx + Du: the reconstruction is exact
    (to 1e-7) after the delay h (closed form of §3.1.2 against fojax.simulate's states)."""
    ex = fojax.models.example_3_1_2()
    sys_ = ex.system.replace(D=np.ones((ex.system.p, ex.system.m)))
    design = fojax.design_finite_time_observer(sys_, ex.L, h=0.5)
    ts = jnp.linspace(0.0, 3.0, 301)
    sol = fojax.simulate(sys_, jnp.linspace(0.2, 1.0, sys_.n), ts, fojax.Sine(jnp.ones(sys_.m), 1.0),
                         observers=[design.observer])
    ft = design.observer.finite_time_estimates(ts, sol.observer_states[0], sol.us, sol.ys)
    z = np.asarray(sol.xs @ np.asarray(ex.L).T)
    assert np.abs(np.asarray(ft) - z)[60:].max() < 1e-7 * np.abs(z).max()


def test_discrete_time_models_keep_dt():
    P, _ = _plant(seed=3)
    Pd = control.c2d(P, 0.1)
    plant = from_control(Pd)
    assert plant.dt == 0.1
    back = to_control(plant)
    assert back.dt == 0.1
    for k in "ABCD":
        np.testing.assert_array_equal(getattr(back, k), getattr(Pd, k))
    S = to_scipy(plant)
    assert isinstance(S, sig.dlti) and S.dt == 0.1
    assert from_scipy(S).dt == 0.1
