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
from fojax.cli._main import main
from fojax.config import example_path, load_config, parse_config
from fojax.design import TakagiSugenoObserverDesign
from fojax.results import load_design


def _arm_file():
    return tomllib.loads(example_path("robot_arm_ts").read_text())


@pytest.fixture(scope="module")
def ts_study(tmp_path_factory):
    """One small study: the proportional observer only, 2 samples, 0.5 s, 1 tuning step."""
    tmp = tmp_path_factory.mktemp("ts")
    d = _arm_file()
    # fojax's default R (q0 = 2): the cheapest tuning step to compile
    d["observer"] = [{k: v for k, v in o.items() if k != "R"} for o in d["observer"] if o["kind"] == "proportional"]
    d["study"] = {"samples": 2, "horizon": 0.5, "dt": 0.05, "seed": 3}
    d["tuning"] = {"steps": 1, "learning_rate": 0.05}
    path = tmp / "arm.toml"
    path.write_text(dumps(d))
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
    assert options["samples_run"] == 2 and options["steps"] == 1


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
    with pytest.raises(fojax.ConfigError, match=what) as info:
        parse_config(_bad(mutate), "arm.toml")
    assert info.value.key == key


def test_ts_only_keys_are_refused_for_lti_models():
    d = tomllib.loads(example_path("example_3_3_7").read_text())
    d["initial_state"] = {"spread": 0.1}
    with pytest.raises(fojax.ConfigError, match="only available for Takagi-Sugeno") as info:
        parse_config(d, "lti.toml")
    assert info.value.key == "initial_state"
    d = tomllib.loads(example_path("example_3_3_7").read_text())
    d["uncertainty"]["parameters"] = {"k": 0.1}
    with pytest.raises(fojax.ConfigError, match="is for Takagi-Sugeno models") as info:
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
    with pytest.raises(fojax.ConfigError, match=what) as info:
        parse_config(_with_observer(example, **obs), "x.toml")
    assert info.value.key == key


def test_study_of_a_finite_time_observer_is_refused_with_the_key(tmp_path, capsys):
    assert main(["study", "finite_time_3_1_2", "--out", str(tmp_path)]) == 2
    assert "[observer[0].kind] 'finite-time' observers have no Monte Carlo study" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())
