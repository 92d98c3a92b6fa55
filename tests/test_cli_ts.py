"""`fojax study` of a Takagi–Sugeno model file (issue 18): the nonlinear robot arm with
physical-parameter and initial-state distributions, T-S observers, tuning, report.

Oracles: the closed form of the arm's algebraic equation ($0 = l\\sin x_3 - x_5$, so the
consistent initial state has $x_5 = l\\sin x_3$ and keeps $E x_0$); the distributions'
definitions (each parameter in nominal·[1 - s, 1 + s], x0 in x0 ± spread, the samples
differ); the tuned design's float64 verification (every rule's error poles in the disk,
common Lyapunov certificate); the file's rules against `fojax.models.robot_arm_ts` (a
model that is not the plant's sector form is refused). Config errors name the key.
"""

import json
import tomllib

import numpy as np
import pytest
from test_config import dumps

import fojax
from fojax.cli import main
from fojax.config import example_path, load_config, parse_config
from fojax.design import TakagiSugenoObserverDesign
from fojax.results import load_design


def _arm_file():
    return tomllib.loads(example_path("robot_arm_ts").read_text())


#: The faults of the small study (the commented [faults] block of robot_arm_ts.toml): f1 an
#: actuator fault entering like the input, f2 an offset of the motor-angle sensor y1.
ARM_FAULTS = {"Fa": [[0, 0], [20, 0], [0, 0], [0, 0], [0, 0]], "Fs": [[0, 0.1], [0, 0]], "estimate_faults": False}


def _small_arm_file():
    """The proportional observer only (fojax's default R, q0 = 2: the cheapest tuning step to
    compile), the faults above, 2 samples, 0.5 s, 2 tuning steps."""
    d = _arm_file()
    d["observer"] = [{k: v for k, v in o.items() if k != "R"} for o in d["observer"] if o["kind"] == "proportional"]
    d["faults"] = dict(ARM_FAULTS)
    d["study"] = {"samples": 2, "horizon": 0.5, "dt": 0.05, "seed": 3}
    d["tuning"] = {"steps": 2, "learning_rate": 0.05}
    return d


@pytest.fixture(scope="module")
def ts_study(tmp_path_factory):
    """One small study of the arm with faults (`_small_arm_file`), run in this process, so
    that the resume test below reuses its compiled programs."""
    tmp = tmp_path_factory.mktemp("ts")
    path = tmp / "arm.toml"
    path.write_text(dumps(_small_arm_file()))
    code = main(["--quiet", "study", str(path), "--out", str(tmp / "out")])
    (folder,) = (tmp / "out").iterdir()
    return code, folder, load_config(path)


def test_ts_study_runs_the_nonlinear_arm_from_a_file(ts_study):
    code, folder, cfg = ts_study
    assert code == 0
    s = np.load(folder / "study-samples.npz")
    x0, x0c = s["evaluation/x0"], s["evaluation/x0_consistent"]
    assert x0.shape == (2, 5)
    # x0 drawn in x0 ± spread, different per sample; consistent: E x0 kept, x5 = l sin x3
    nominal, spread = np.asarray(cfg.x0), cfg.x0_spread
    assert np.all(np.abs(x0 - nominal) <= spread) and not np.allclose(x0[0], x0[1])
    np.testing.assert_allclose(x0c[:, :4], x0[:, :4], rtol=0, atol=1e-12)
    np.testing.assert_allclose(x0c[:, 4], 0.18 * np.sin(x0c[:, 2]), rtol=0, atol=1e-10)
    # physical parameters: nominal (Table 3.1) * (1 + s U(-1, 1)), s = 0.2, per sample
    table = {"k": 0.3, "m": 0.15, "J_l": 0.08}
    for name, nom in table.items():
        v = s[f"evaluation/theta/{name}"]
        assert np.all(np.abs(v / nom - 1) <= 0.2) and v[0] != v[1], name
    np.testing.assert_array_equal(s["evaluation/theta/J_m"], [0.01, 0.01])  # not uncertain
    # the training samples are other draws (another key)
    assert not np.allclose(s["training/theta/k"][0], s["evaluation/theta/k"])


def test_ts_study_tunes_and_verifies_and_reports(ts_study):
    code, folder, _ = ts_study
    for name in ("proportional", "proportional-tuned"):
        d = load_design(folder / f"{name}.npz")
        assert type(d) is TakagiSugenoObserverDesign and d.report.passed
        eig = np.asarray(d.report.eigenvalues)
        assert np.all(np.abs(eig + 2.0) < 1.0)  # every rule's error poles in Disk(-2, 1)
        assert d.report.extra["lyapunov_max_eig"] < 0  # common certificate kept by the tuning
    metrics = json.loads((folder / "metrics.json").read_text())
    assert set(metrics["mean_iae"]) == {"proportional", "proportional-tuned"}
    assert all(np.isfinite(v).all() for v in map(np.asarray, metrics["mean_iae"].values()))
    report = (folder / "report.md").read_text()
    assert "nonlinear plant 'robot_arm'" in report and "rule 2:" in report
    options = json.loads((folder / "study-options.json").read_text())
    assert options["samples_run"] == 2 and options["steps"] == 2


# ------------------------------------------------------------------ faults of a T-S file


def _arm_by_hand(theta, x0c, amplitude, onset, obs, Fa, Fs, ts):
    """Oracle for one sample, independent of fojax's simulator: the arm's reduced ODE (x1..x4;
    z = [x2, x4] and y = [x1, x3] do not involve x5, and Fa has no x5 row) with the step
    fault a·1(t ≥ onset), jointly with the T-S observer (eq. 3.152, written out below from
    its matrices), integrated by SciPy's DOP853 in two pieces split at the onset; u = sin t.
    Returns the IAE of ẑ - z per signal (trapezoidal rule on `ts`, as the study defines it)."""
    from scipy.integrate import solve_ivp, trapezoid

    th = {k: float(v) for k, v in theta.items()}
    N, J, F, H, S, G, M, P, Q = (np.asarray(getattr(obs, k)) for k in "NJFHSGMPQ")
    Wu, Wy = np.asarray(obs.Wu), np.asarray(obs.Wy)
    lo, hi = float(obs.membership.lower), float(obs.membership.upper)
    q0 = N.shape[1]

    def signals(t, s, f):
        x, zeta, v = s[:4], s[4:4 + q0], s[4 + q0:]
        u = np.array([np.sin(t)])
        y = np.array([x[0], x[2]]) + Fs @ f
        w = Wu @ u + Wy @ y
        rho = np.clip(np.sin(y[1]) / y[1] if y[1] != 0 else 1.0, lo, hi)  # sin(y2)/y2 premise
        h = np.array([(hi - rho) / (hi - lo), (rho - lo) / (hi - lo)])  # rule 1 at rho = lower
        return x, zeta, v, u, w, h

    def rhs(t, s, f):
        x, zeta, v, u, w, h = signals(t, s, f)
        dx = np.array([
            x[1],
            (-th["k"] * x[0] - th["beta"] * x[1] + th["k"] * x[2] + th["K_tau"] * u[0]) / th["J_m"],
            x[3],
            (th["k"] * x[0] - th["k"] * x[2] - th["l_c"] * th["m"] * th["g"] * np.sin(x[2])) / th["J_l"],
        ]) + Fa[:4] @ f
        dzeta = np.einsum("k,kij,j->i", h, N, zeta) + np.einsum("k,kij,j->i", h, J, v) + \
            np.einsum("k,kij,j->i", h, F, w) + np.einsum("k,kij,j->i", h, H, u)
        dv = np.einsum("k,kij,j->i", h, S, zeta) + np.einsum("k,kij,j->i", h, G, v) + np.einsum("k,kij,j->i", h, M, w)
        return np.concatenate([dx, dzeta, dv])

    def error(t, s, f):
        x, zeta, _, _, w, h = signals(t, s, f)
        return np.einsum("k,kij,j->i", h, P, zeta) + np.einsum("k,kij,j->i", h, Q, w) - np.array([x[1], x[3]])

    s0 = np.concatenate([x0c[:4], np.asarray(obs.initial_state())])
    kw = dict(method="DOP853", rtol=1e-11, atol=1e-12, dense_output=True)
    zero = np.zeros_like(amplitude)
    first = solve_ivp(rhs, (ts[0], onset), s0, args=(zero,), **kw)
    second = solve_ivp(rhs, (onset, ts[-1]), first.y[:, -1], args=(amplitude,), **kw)
    e = np.array([error(t, first.sol(t), zero) if t < onset else error(t, second.sol(t), amplitude) for t in ts])
    return trapezoid(np.abs(e), ts, axis=0)


def test_ts_study_with_faults_matches_the_arm_simulated_by_hand(ts_study):
    """The faults of a T-S file act on the simulated nonlinear arm: the study's IAE of every
    sample and observer equals an independent simulation of that sample with its drawn fault,
    and differs from the same sample without the fault by far more than that agreement."""
    code, folder, cfg = ts_study
    assert code == 0 and cfg.has_faults and not cfg.augments_faults
    s = np.load(folder / "study-samples.npz")
    amp, onset = s["evaluation/fault_amplitude"], s["evaluation/fault_onset"]
    # the drawn scenarios: one fault per sample, |a| in [0.5, 1.5], onset in [0.1 T, 0.4 T]
    assert amp.shape == (2, 2) and np.all((amp != 0).sum(axis=1) == 1)
    assert np.all((np.abs(amp).max(axis=1) >= 0.5) & (np.abs(amp).max(axis=1) <= 1.5))
    assert np.all((onset >= 0.05) & (onset <= 0.2))
    # ... from fold_in(fault key, 1), as documented (the fault key itself draws x0)
    import jax

    key = jax.random.fold_in(jax.random.split(jax.random.PRNGKey(3))[1], 1)
    ref = fojax.studies.fault_scenarios(key, 2, 2, magnitude=(0.5, 1.5), onset=(0.05, 0.2)).values
    np.testing.assert_array_equal(amp, np.asarray(ref.amplitude))
    metrics = np.load(folder / "metrics.npz")
    Fa, Fs = np.asarray(cfg.Fa, float), np.asarray(cfg.Fs, float)
    assert not Fa[4].any()
    ts = s["evaluation/ts"]
    theta = {k[len("evaluation/theta/"):]: s[k] for k in s.files if k.startswith("evaluation/theta/")}
    for name in ("proportional", "proportional-tuned"):
        obs = load_design(folder / f"{name}.npz").observer
        iae = metrics[f"iae/{name}"]
        assert iae.shape == (2, 2)
        for k in range(2):
            th = {n: v[k] for n, v in theta.items()}
            args = (th, s["evaluation/x0_consistent"][k])
            faulty = _arm_by_hand(*args, amp[k], onset[k], obs, Fa, Fs, ts)
            healthy = _arm_by_hand(*args, np.zeros(2), onset[k], obs, Fa, Fs, ts)
            agree = np.abs(iae[k] - faulty)
            np.testing.assert_allclose(iae[k], faulty, rtol=1e-6, atol=1e-9, err_msg=f"{name}, sample {k}")
            assert np.abs(faulty - healthy).max() > 1e3 * agree.max() + 1e-3, (name, k, faulty, healthy)


def test_ts_faults_config_loads_and_designs_for_z_only():
    d = _arm_file()
    d["faults"] = dict(ARM_FAULTS)
    cfg = parse_config(d, "arm.toml")
    np.testing.assert_array_equal(cfg.Fa, ARM_FAULTS["Fa"])
    np.testing.assert_array_equal(cfg.Fs, ARM_FAULTS["Fs"])
    assert cfg.has_faults and not cfg.augments_faults and cfg.estimate_faults is False
    # designed for the nominal T-S model and z = L x (R with n = 5 columns is accepted)
    assert isinstance(cfg.design_system(), fojax.TakagiSugenoSystem) and cfg.design_system().n == 5
    np.testing.assert_array_equal(cfg.design_L(), cfg.L)
    assert cfg.observers[0].R.shape == (4, 5)
    # the shipped file's commented block is this one
    lines = example_path("robot_arm_ts").read_text().splitlines()
    start = lines.index("# [faults]")
    block = []
    for line in lines[start:]:
        if not line.startswith("# "):
            break
        block.append(line[2:])
    assert tomllib.loads("\n".join(block)) == {"faults": ARM_FAULTS}


def test_check_and_design_of_a_ts_file_with_faults(tmp_path, capsys):
    """`fojax check` says what a T-S file's faults do; `fojax design` designs its observers for
    z = L x (verified; the refusal of T-S files with [faults] is gone)."""
    d = _arm_file()
    d["faults"] = dict(ARM_FAULTS)
    d["observer"] = [o for o in d["observer"] if o["kind"] == "proportional"]
    path = tmp_path / "arm.toml"
    path.write_text(dumps(d))
    # rule 1 of the arm is open-loop unstable (not admissible: exit code 1); its observers
    # need detectability only, and are designed below
    assert main(["check", str(path)]) == 1
    out, err = capsys.readouterr()
    assert "the Takagi-Sugeno observers estimate z = L x only" in out
    assert "required but not established: rule 1: admissible (exit code 1)" in err
    assert main(["--quiet", "design", str(path), "--out", str(tmp_path / "out")]) == 0
    (folder,) = (tmp_path / "out").iterdir()
    design = load_design(folder / "proportional.npz")
    assert type(design) is TakagiSugenoObserverDesign and design.report.passed
    assert np.asarray(design.observer.P).shape[1] == 2  # estimates z = [x2, x4] only


def _with_faults(**faults):
    return lambda d: d.update(faults=faults)


FA, FS = ARM_FAULTS["Fa"], ARM_FAULTS["Fs"]
BAD_FAULTS = [
    (_with_faults(Fa=FA, Fs=FS), "faults.estimate_faults", r"is missing \(default true\).*Set estimate_faults = false"),
    (_with_faults(Fa=FA, estimate_faults=True), "faults.estimate_faults", "is true: Takagi-Sugeno observers estimate z"),
    (_with_faults(Fa=FA, estimate_faults=False, ramp=True), "faults.ramp", "fault-augmented design"),
    (_with_faults(Fa=FA[:4], estimate_faults=False), "faults.Fa", r"has shape \(4, 2\), expected \(5, nf\)"),
    (_with_faults(Fa=FA, Fs=[[0], [0]], estimate_faults=False), "faults.Fs", "has 1 columns but faults.Fa has 2"),
    (_with_faults(Fa=FA, estimate_faults=False, profile="step"), "faults.profile", "unknown key 'profile'"),
    (_with_faults(estimate_faults=False), "faults.Fa", "needs Fa"),
]


@pytest.mark.parametrize("mutate, key, what", BAD_FAULTS, ids=[b[1] + ":" + b[2][:12] for b in BAD_FAULTS])
def test_bad_ts_faults_keys_name_the_key(mutate, key, what):
    with pytest.raises(fojax.errors.ConfigError, match=what) as info:
        parse_config(_bad(mutate), "arm.toml")
    assert info.value.key == key


def test_sample_read_back_compiles_once_per_structure():
    """Regression (issue 18 timing): `describe_samples` jitted a new closure per call, so
    every sample set recompiled its read-back (3 compiles in a robot-arm study, 2 needed).
    New draws of one structure must not trace again (on a small LTI model with faults: the
    same function, compiled in seconds)."""
    from fojax.cli import _study_samples as ss  # private: the drawn samples are checked

    cfg = load_config(example_path("example_4_2_2"))
    a = ss.describe_samples(ss.make_study(cfg, 11, 2, 0.5, 0.05), cfg, {})
    traces = ss.READ_TRACES["read_back"]
    b = ss.describe_samples(ss.make_study(cfg, 12, 2, 0.5, 0.05), cfg, {})
    assert ss.READ_TRACES["read_back"] == traces
    assert not np.array_equal(a["fault_onset"], b["fault_onset"])  # new numbers


# ------------------------------------------------------------------ study --resume


@pytest.fixture(scope="module")
def ts_resumed(ts_study, tmp_path_factory):
    """What the `ts_study` run (--steps 2) leaves when interrupted after its first tuning
    step, resumed. A --steps 1 run computes the same bits up to there (a step does not depend
    on the total, and the held-out curve is evaluated at every step for both: eval_every =
    max(1, steps // 10) = 1), so, as the distributed resume test does: a --steps 1 run of the
    same config file, its options set to steps = 2, the files written after the tuning
    removed, then ``fojax study --resume``. In this process: the programs `ts_study` compiled
    are reused."""
    _, first, cfg = ts_study
    out = tmp_path_factory.mktemp("ts-resume")
    assert main(["--quiet", "study", cfg.path, "--steps", "1", "--out", str(out)]) == 0
    (folder,) = out.iterdir()
    options = json.loads((folder / "study-options.json").read_text())
    (folder / "study-options.json").write_text(json.dumps(dict(options, steps=2)))
    for p in folder.iterdir():
        if p.name.endswith("-tuned.npz") or p.suffix == ".png" or p.stem in ("metrics", "study", "study-samples",
                                                                                "report"):
            p.unlink()
    assert json.loads((folder / "tuning-proportional.json").read_text())["step"] == 1
    code = main(["--quiet", "study", "--resume", str(folder)])
    return code, first, folder


def test_resumed_ts_study_equals_the_uninterrupted_one_bit_for_bit(ts_resumed):
    """Every array of every .npz equal bit for bit; in the .npz metadata and the tuning
    checkpoint's .json only the creation time and the LMI solver's wall-clock solve_time
    differ (each run designs the LMI afresh)."""
    from helpers import json_differences

    code, first, folder = ts_resumed
    assert code == 0
    assert json.loads((folder / "tuning-proportional.json").read_text())["step"] == 2
    names = sorted(p.name for p in first.glob("*.npz"))
    assert names == sorted(p.name for p in folder.glob("*.npz"))
    assert {"proportional.npz", "proportional-tuned.npz", "tuning-proportional.npz", "metrics.npz",
            "study.npz", "study-samples.npz"} <= set(names)
    for name in names:
        with np.load(first / name, allow_pickle=False) as za, np.load(folder / name, allow_pickle=False) as zb:
            assert sorted(za.files) == sorted(zb.files), name
            for k in za.files:
                x, y = za[k], zb[k]
                if k == "__metadata__":
                    x, y = ({kk: v for kk, v in json.loads(str(m)).items() if kk != "created"} for m in (x, y))
                    assert not json_differences(x, y), (name, json_differences(x, y))
                    continue
                assert x.dtype == y.dtype and np.array_equal(x, y, equal_nan=x.dtype.kind in "fc"), (name, k)
    ha = json.loads((first / "tuning-proportional.json").read_text())
    hb = json.loads((folder / "tuning-proportional.json").read_text())
    assert ha["history"] == hb["history"]


def test_shipped_arm_file_describes_the_plant_it_simulates():
    cfg = load_config(example_path("robot_arm_ts"))
    assert cfg.takagi_sugeno["plant"] == "robot_arm"
    assert cfg.parameter_spread == {"k": 0.2, "m": 0.2, "J_l": 0.2}
    ref = fojax.models.robot_arm_ts().system
    np.testing.assert_array_equal(cfg.A, np.asarray(ref.A))
    assert isinstance(cfg.plant(), fojax.NonlinearDescriptorSystem)


def _bad(mutate):
    d = _arm_file()
    mutate(d)
    return d


BAD = [
    (lambda d: d["uncertainty"]["parameters"].update(kk=0.1), "uncertainty.parameters.kk", "unknown key 'kk'"),
    (lambda d: d["uncertainty"]["parameters"].update(k=1.5), "uncertainty.parameters.k", r"relative spread in \[0, 1\)"),
    (lambda d: d["takagi_sugeno"].pop("plant"), "uncertainty.parameters", r"needs \[takagi_sugeno\] plant"),
    (lambda d: d["uncertainty"].update(dA=[[0] * 5] * 5), "uncertainty.dA", "is for LTI models"),
    (lambda d: d["takagi_sugeno"].update(plant="robot"), "takagi_sugeno.plant", "Did you mean 'robot_arm'"),
    (lambda d: d["model"]["A"][0][1].__setitem__(0, -31.0), "model.A", "differs from the Takagi-Sugeno form"),
    (lambda d: d["initial_state"].update(spread=[0.1, 0.1]), "initial_state.spread", r"expected \(5,\)"),
    (lambda d: d["initial_state"].update(spread=-0.1), "initial_state.spread", "negative entry"),
    (lambda d: d["initial_state"].update(width=0.1), "initial_state.width", "unknown key 'width'"),
]


@pytest.mark.parametrize("mutate, key, what", BAD, ids=[b[1] + ":" + b[2][:12] for b in BAD])
def test_bad_ts_study_keys_name_the_key(mutate, key, what):
    with pytest.raises(fojax.errors.ConfigError, match=what) as info:
        parse_config(_bad(mutate), "arm.toml")
    assert info.value.key == key


def test_ts_only_keys_are_refused_for_lti_models():
    d = tomllib.loads(example_path("example_3_3_7").read_text())
    d["initial_state"] = {"spread": 0.1}
    with pytest.raises(fojax.errors.ConfigError, match="only available for Takagi-Sugeno") as info:
        parse_config(d, "lti.toml")
    assert info.value.key == "initial_state"
    d = tomllib.loads(example_path("example_3_3_7").read_text())
    d["uncertainty"]["parameters"] = {"k": 0.1}
    with pytest.raises(fojax.errors.ConfigError, match="is for Takagi-Sugeno models") as info:
        parse_config(d, "lti.toml")
    assert info.value.key == "uncertainty.parameters"


def test_initial_conditions_family_under_strict_rank_promotion():
    """Regression: `fojax.studies.initial_conditions` broadcast (count, n) against (n,)
    implicitly, which raises under ``jax_numpy_rank_promotion="raise"`` (conftest), so a
    study with ``[initial_state]`` failed. Oracle: the definition, with the same draws."""
    import jax

    from fojax.studies import initial_conditions

    mean, lo, hi = np.array([1.0, -2.0, 0.5]), np.array([-0.1, 0.0, -0.3]), np.array([0.1, 0.0, 0.2])
    key = jax.random.PRNGKey(7)
    x = np.asarray(initial_conditions(key, 4, mean, bounds=(lo, hi)).values)
    r = np.asarray(jax.random.uniform(key, (4, 3), dtype=np.float64))
    np.testing.assert_allclose(x, mean + r * (hi - lo) + lo, rtol=0, atol=1e-15)
    assert np.all((x >= mean + lo) & (x <= mean + hi))
    g = np.asarray(initial_conditions(key, 4, mean, std=[1.0, 0.0, 2.0]).values)
    z = np.asarray(jax.random.normal(key, (4, 3), dtype=np.float64))
    np.testing.assert_allclose(g, mean + np.array([1.0, 0.0, 2.0]) * z, rtol=0, atol=1e-15)


# ----------------------------------------------------------- unknown-input and finite-time


@pytest.fixture(scope="module")
def special_designs(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("special")
    code = main(["--quiet", "design", "finite_time_3_1_2", "unknown_input_4_1_3", "--out", str(tmp)])
    return code, {p.name.split("-")[1]: p for p in tmp.iterdir()}


def _in_disk(eig, center, radius):
    return np.all(np.abs(np.asarray(eig) - center) < radius)


def test_unknown_input_config_designs_a_verified_observer(special_designs):
    code, folders = special_designs
    assert code == 0
    cfg = load_config(example_path("unknown_input_4_1_3"))
    (spec,) = cfg.observers
    assert spec.kind == "unknown-input" and np.array_equal(spec.D, np.eye(4)[:, [2]])
    d = load_design(folders["unknown_input_4_1_3"] / "unknown_input.npz")
    assert type(d) is fojax.design.UnknownInputObserverDesign and d.report.passed
    np.testing.assert_array_equal(d.D, spec.D)
    # oracle: the eigenvalues of the saved error matrix [N J Δ; S G 0; Φ Λ 0], recomputed
    assert _in_disk(np.linalg.eigvals(d.error_matrix), -2.0, 1.0)
    ex = fojax.models.example_4_1_3()  # the plant is §4.1.3's closed loop (feedback = L)
    np.testing.assert_array_equal(np.asarray(cfg.system().A), ex.A + ex.B @ ex.L)


def test_finite_time_config_designs_a_verified_pair(special_designs):
    code, folders = special_designs
    assert code == 0
    cfg = load_config(example_path("finite_time_3_1_2"))
    (spec,) = cfg.observers
    ex = fojax.models.example_3_1_2()
    assert spec.kind == "finite-time" and spec.delay == ex.h
    assert [(r.center, r.radius) for r in spec.regions] == [(ex.alpha1, ex.tau1), (ex.alpha2, ex.tau2)]
    d = load_design(folders["finite_time_3_1_2"] / "finite_time.npz")
    assert type(d) is fojax.design.FiniteTimeObserverDesign and d.h == 0.5
    for sub, (c, r) in zip(d.designs, [(-5.0, 0.5), (-2.0, 0.5)]):
        assert sub.report.passed and _in_disk(np.linalg.eigvals(sub.error_matrix), c, r)
    assert d.reconstruction_residual < 1e-8


def _with_observer(example, **obs):
    d = tomllib.loads(example_path(example).read_text())
    d["observer"] = [obs]
    return d


BAD_SPECIAL = [
    (("unknown_input_4_1_3", {"kind": "unknown-input"}), "observer[0].D", "missing"),
    (("unknown_input_4_1_3", {"kind": "unknown-input", "D": [[1], [0]]}), "observer[0].D", r"expected \(4, l\)"),
    (("finite_time_3_1_2", {"kind": "finite-time"}), "observer[0].delay", "missing"),
    (("finite_time_3_1_2", {"kind": "finite-time", "delay": -1}), "observer[0].delay", "positive"),
    (("finite_time_3_1_2", {"kind": "finite-time", "delay": 0.5, "regions": [{"center": -2, "radius": 1},
                                                                            {"center": -2.5, "radius": 1}]}),
     "observer[0].regions", "overlap"),
    (("finite_time_3_1_2", {"kind": "finite-time", "delay": 0.5, "region": {"decay": 1}}),
     "observer[0].region", "two regions"),
    (("finite_time_3_1_2", {"kind": "generalized", "delay": 0.5}), "observer[0].delay", "kind = 'finite-time'"),
    (("robot_arm_ts", {"kind": "unknown-input", "D": [[0]] * 5}), "observer[0].kind", "LTI models without"),
]


@pytest.mark.parametrize("case, key, what", BAD_SPECIAL, ids=[b[1] + ":" + b[2][:10] for b in BAD_SPECIAL])
def test_bad_special_observer_keys_name_the_key(case, key, what):
    example, obs = case
    with pytest.raises(fojax.errors.ConfigError, match=what) as info:
        parse_config(_with_observer(example, **obs), "x.toml")
    assert info.value.key == key


def test_study_of_a_finite_time_observer_is_refused_with_the_key(tmp_path, capsys):
    assert main(["study", "finite_time_3_1_2", "--out", str(tmp_path)]) == 2
    assert "[observer[0].kind] 'finite-time' observers have no Monte Carlo study" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())
