"""`fojax.config`: TOML model and study files. The shipped examples reproduce `fojax.models`
exactly, and malformed files fail with a ConfigError naming the file and the key.

Oracles: `fojax.models`' own arrays (bit for bit: ``np.array_equal``) for every shipped example,
the closed loop $A + BL$ and the algebraic row of the consistent initial state written out,
``tomllib`` for the round trip of the dumper, the regions' constructors for the region tables,
and the expected `fojax.errors.ConfigError` message (file and key) for each malformed file.
"""

import importlib.resources

import jax.numpy as jnp
import numpy as np
import pytest

import fojax
from fojax.config import example_names, example_path, load_config, parse_config
from fojax.design import Disk, HalfPlane, Intersection, Sector


EXAMPLES = [
    "example_3_1_2", "example_3_1_3", "example_3_3_7", "example_4_1_3",
    "example_4_2_2", "example_4_3_2", "example_4_4_2", "finite_time_3_1_2", "robot_arm_ts",
    "unknown_input_4_1_3",
]


def _toml_value(v):
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return '"' + v.replace('"', '\\"') + '"'
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{k} = {_toml_value(x)}" for k, x in v.items()) + " }"
    if isinstance(v, float) and not np.isfinite(v):
        return "nan" if np.isnan(v) else ("inf" if v > 0 else "-inf")
    return repr(v)


def dumps(data: dict) -> str:
    """A minimal TOML writer for the test documents (tables, arrays of tables, inline values)."""
    lines = [f"{k} = {_toml_value(v)}" for k, v in data.items() if not isinstance(v, dict | list) or (
        isinstance(v, list) and not (v and isinstance(v[0], dict)))]
    for k, v in data.items():
        if isinstance(v, dict):
            lines += ["", f"[{k}]"] + [f"{kk} = {_toml_value(vv)}" for kk, vv in v.items()]
        elif isinstance(v, list) and v and isinstance(v[0], dict):
            for item in v:
                lines += ["", f"[[{k}]]"] + [f"{kk} = {_toml_value(vv)}" for kk, vv in item.items()]
    return "\n".join(lines) + "\n"


def base() -> dict:
    ex = fojax.models.example_4_1_3()
    return {
        "name": "t",
        "model": {k: np.asarray(getattr(ex, k)).tolist() for k in ("E", "A", "B", "C", "L")},
        "observer": [{"kind": "generalized", "region": {"disk": {"center": -2.0, "radius": 1.0}}}],
        "study": {"samples": 4, "horizon": 1.0, "dt": 0.1, "seed": 0},
        "tuning": {"steps": 2, "learning_rate": 0.01},
    }


def write(tmp_path, data, name="bad.toml"):
    p = tmp_path / name
    p.write_text(dumps(data))
    return p


def test_dumper_round_trip(tmp_path):
    cfg = load_config(write(tmp_path, base(), "ok.toml"))
    ex = fojax.models.example_4_1_3()
    assert np.array_equal(cfg.A, ex.A) and np.array_equal(cfg.L, ex.L)
    assert cfg.observers[0].region == Disk(-2.0, 1.0) and cfg.study.samples == 4
    assert cfg.study.stepper == "auto"  # the default
    d = base()
    d["study"]["stepper"] = "exact"
    assert load_config(write(tmp_path, d, "exact.toml")).study.stepper == "exact"


def test_examples_are_package_data():
    root = importlib.resources.files("fojax").joinpath("examples")
    assert sorted(p.name for p in root.iterdir() if p.name.endswith(".toml")) == [f"{e}.toml" for e in EXAMPLES]
    assert example_names() == EXAMPLES
    assert example_path("example_3_3_7").is_file()
    with pytest.raises(fojax.errors.ConfigError, match="Did you mean 'example_3_3_7'"):
        example_path("example_3_3_8")


@pytest.mark.parametrize("name", EXAMPLES)
def test_every_example_loads(name):
    cfg = load_config(example_path(name))
    assert cfg.name == name and cfg.path.endswith(f"{name}.toml")
    assert cfg.E.dtype == np.float64


def test_example_3_3_7_matches_models_exactly():
    cfg = load_config(example_path("example_3_3_7"))
    ex = fojax.models.example_3_3_7()
    for k in ("E", "A", "B", "C", "L", "Fa", "Fs"):
        assert np.array_equal(getattr(cfg, k), getattr(ex, k)), k
    assert np.array_equal(cfg.dA[0], ex.dA) and cfg.dA.shape == (1, 6, 6)
    assert np.array_equal(cfg.design_L(), ex.L_aug)
    aug, ref = cfg.design_system(), ex.augmented
    for k in ("E", "A", "B", "C"):
        assert np.array_equal(np.asarray(getattr(aug, k)), np.asarray(getattr(ref, k))), k
    assert cfg.profile == {"kind": "uniform", "bound": 0.3}
    assert [o.name for o in cfg.observers] == ["PO", "FGDO"]
    assert [o.kind for o in cfg.observers] == ["proportional", "generalized"]
    assert cfg.study.samples == 64 and cfg.tuning.steps == 60 and cfg.tuning.learning_rate == 0.1
    assert cfg.tuning.loss == "ise"
    # the uncertain plant: A + delta dA for a constant delta
    plant = parse_config({**cfg.raw, "uncertainty": {"dA": cfg.raw["uncertainty"]["dA"],
                                                     "profile": {"kind": "constant", "value": [0.2]}}},
                         "x.toml").plant()
    assert isinstance(plant, fojax.UncertainDescriptorSystem)
    assert np.allclose(np.asarray(plant.nominal_at(0.0).A), ex.A + 0.2 * ex.dA, rtol=0, atol=1e-15)


def test_fault_examples_design_functionals():
    ex = fojax.models.example_4_4_2()
    cfg = load_config(example_path("example_4_4_2"))
    assert np.array_equal(cfg.design_L(), ex.Lbar)
    ex2 = fojax.models.example_4_2_2()
    cfg2 = load_config(example_path("example_4_2_2"))
    assert np.array_equal(cfg2.design_L(), ex2.Lbar)  # estimate_faults = false: [L 0]
    ex3 = fojax.models.example_4_3_2()
    cfg3 = load_config(example_path("example_4_3_2"))
    assert np.array_equal(np.asarray(cfg3.design_system().A), np.asarray(ex3.augmented.A))


def test_feedback_gives_the_closed_loop():
    cfg = load_config(example_path("example_4_1_3"))
    ex = fojax.models.example_4_1_3()
    assert np.array_equal(np.asarray(cfg.system().A), ex.A + ex.B @ ex.L)
    # consistent x0 (algebraic row -x1 - 2 x2 + x4 = 0)
    assert cfg.x0 @ ex.A[3] == 0.0


def test_takagi_sugeno_example_matches_models():
    cfg = load_config(example_path("robot_arm_ts"))
    ex = fojax.models.robot_arm_ts()
    s, ref = cfg.system(), ex.system
    assert isinstance(s, fojax.TakagiSugenoSystem)
    for k in ("E", "A", "B", "C"):
        assert np.array_equal(np.asarray(getattr(s, k)), np.asarray(getattr(ref, k))), k
    for y in ([0.0, 0.3], [1.0, 2.5], [0.0, -4.0]):
        y = jnp.asarray(y)
        assert np.array_equal(s.membership(y, jnp.zeros(1)), ref.membership(y, jnp.zeros(1)))
    assert len(cfg.rule_systems()) == 2


def test_region_combinations(tmp_path):
    d = base()
    d["observer"] = [
        {"region": {"decay": 0.5}},
        {"region": {"damping": 0.7}},
        {"name": "all", "kind": "PI", "region": {"disk": {"center": -3.0, "radius": 2.0}, "decay": 1.0, "damping": 0.6}},
    ]
    cfg = load_config(write(tmp_path, d))
    r = [o.region for o in cfg.observers]
    assert r[0] == HalfPlane(0.5) and r[1] == Sector(0.7)
    assert r[2] == Intersection((Disk(-3.0, 2.0), HalfPlane(1.0), Sector(0.6)))
    assert [o.name for o in cfg.observers] == ["generalized-1", "generalized-2", "all"]


def _mutate(path, value):
    d = base()
    *head, last = path
    t = d
    for k in head:
        t = t[k]
    if value is _DELETE:
        del t[last]
    else:
        t[last] = value
    return d


_DELETE = object()
A_BAD = fojax.models.example_4_1_3().A.tolist()
A_BAD[1][2] = "x"
E_RAGGED = fojax.models.example_4_1_3().E.tolist()
E_RAGGED[2] = [0.0, 0.0, 1.0]

MALFORMED = [
    # (path, value, key named in the message, what the message says)
    (("model", "B"), [[1.0, 0.0]] * 3, "model.B", r"has shape \(3, 2\), expected \(4, m\)"),
    (("model", "A"), A_BAD, "model.A", r"entry model\.A\[1\]\[2\] is 'x' \(string\)"),
    (("model", "Bb"), [[1.0]], "model.Bb", r"unknown key 'Bb'\. Did you mean 'B'\?"),
    (("model", "C"), _DELETE, "model.C", r"missing required key 'C'"),
    (("model", "L"), [[1.0, 0.0, 0.0]], "model.L", r"has shape \(1, 3\), expected \(q, 4\)"),
    (("model", "E"), E_RAGGED, "model.E", r"ragged"),
    (("model", "E"), 3.0, "model.E", r"expected a square matrix \(nested lists of numbers\), got float"),
    (("model", "x0"), [1.0, 2.0], "model.x0", r"has shape \(2,\), expected \(4,\)"),
    (("model", "feedback"), [[1.0, 2.0, 3.0, 4.0]], "model.feedback", r"expected \(2, 4\)"),
    (("observer", 0, "region", "disk", "radius"), -1.0, "observer[0].region.disk.radius", r"expected a positive number, got -1\.0"),
    (("observer", 0, "region", "disk", "center"), -0.5, "observer[0].region.disk", r"reaches into the closed right half-plane"),
    (("observer", 0, "region", "damping"), 1.5, "observer[0].region.damping", r"damping ratio in \(0, 1\)"),
    (("observer", 0, "region", "decay"), "fast", "observer[0].region.decay", r"expected a number, got 'fast'"),
    (("observer", 0, "region", "disc"), {"center": -2.0, "radius": 1.0}, "observer[0].region.disc", r"Did you mean 'disk'"),
    (("observer", 0, "kind"), "generalised", "observer[0].kind", r"Did you mean 'generalized'"),
    (("observer", 0, "R"), [[1.0, 0.0]], "observer[0].R", r"expected \(q0, 4\)"),
    (("observer", 0, "q0"), 1.5, "observer[0].q0", r"expected an integer"),
    (("observer", 0, "balance"), "yes", "observer[0].balance", r"expected true or false, got 'yes' \(string\)"),
    (("observer", 0, "balance"), 1, "observer[0].balance", r"expected true or false, got 1 \(int\)"),
    (("observer", 0, "balanced"), True, "observer[0].balanced", r"Did you mean 'balance'"),
    (("study", "samples"), 0, "study.samples", r"expected a positive number, got 0"),
    (("study", "dt"), 2.0, "study.dt", r"smaller than study\.horizon"),
    (("study", "sample"), 3, "study.sample", r"Did you mean 'samples'"),
    (("study", "stepper"), "exponentail", "study.stepper", r"Did you mean 'exponential'"),
    (("tuning", "learning_rate"), -0.1, "tuning.learning_rate", r"positive"),
    (("tuning", "loss"), "mse", "tuning.loss", r"expected one of 'ise', 'iae', got 'mse'"),
    (("tuning", "loss"), "IAE", "tuning.loss", r"expected one of 'ise', 'iae', got 'IAE'\. Did you mean 'iae'"),
    (("observers",), [{"kind": "PI"}], "observers", r"unknown key 'observers'\. Did you mean 'observer'"),
    (("faults",), {"Fa": [[1.0]] * 4, "Fs": [[1.0, 0.0]] * 3}, "faults.Fs", r"has 2 columns but faults\.Fa has 1"),
    (("faults",), {"Fs": [[1.0]] * 2}, "faults.Fs", r"expected \(3, nf\)"),
    (("faults",), {"ramp": True}, "faults.Fa", r"needs Fa .* Fs .* or both"),
    (("uncertainty",), {"dA": [[[1.0, 0.0], [0.0, 1.0]]]}, "uncertainty.dA", r"expected \(k, 4, 4\)"),
    (("uncertainty",), {"dA": [[[0.0] * 4] * 4], "profile": {"kind": "gauss"}}, "uncertainty.profile.kind", r"one of 'constant', 'uniform', 'sine'"),
    (("uncertainty",), {"dA": [[[0.0] * 4] * 4], "profile": {"kind": "sine", "amplitude": 0.1}}, "uncertainty.profile.omega", r"missing required key 'omega'"),
    # the matrix of the wrong size is named, whichever it is (E used to set n and A was blamed)
    (("model", "E"), np.eye(5).tolist(), "model.E", r"has shape \(5, 5\), expected \(4, 4\) \(E must be square, n x n with n = 4 from A, B, C and L\)"),
    (("model", "E"), np.eye(4)[:3].tolist(), "model.E", r"has shape \(3, 4\), expected \(4, 4\)"),
    (("model", "A"), np.eye(3).tolist(), "model.A", r"has shape \(3, 3\), expected \(4, 4\) \(n = 4 from E, B, C and L\)"),
    (("model", "B"), [[1.0]] * 5, "model.B", r"has shape \(5, 1\), expected \(4, m\) \(one row per state, n = 4 from E, A, C and L\)"),
]


@pytest.mark.parametrize("path,value,key,what", MALFORMED, ids=[m[2] + ":" + m[3][:20] for m in MALFORMED])
def test_malformed_config_names_file_and_key(tmp_path, path, value, key, what):
    p = write(tmp_path, _mutate(path, value))
    with pytest.raises(fojax.errors.ConfigError, match=what) as info:
        load_config(p)
    err = info.value
    assert err.key == key and err.file == str(p)
    assert str(err).startswith(f"{p}: [{key}] ")


def test_balance_key_reaches_the_design(tmp_path):
    """``[[observer]] balance``: absent -> the library default (no keyword); true/false -> passed to
    design_functional_observer, whose design is then the unit-free one (``solver["balance"]``
    holds the factors) or the one on the data as given."""
    cfg = load_config(write(tmp_path, base(), "default.toml"))
    assert cfg.observers[0].balance is None and "balance" not in cfg.observers[0].design_kwargs()
    for value in (True, False):
        d = base()
        d["observer"][0]["balance"] = value
        d["observer"][0]["objective"] = "centre"
        spec = load_config(write(tmp_path, d, f"{value}.toml")).observers[0]
        assert spec.balance is value
        assert spec.design_kwargs() == {"objective": "centre", "Bw": None, "Dv": None, "balance": value}
    d = base()
    d["observer"][0]["balance"] = True
    cfg = load_config(write(tmp_path, d, "true.toml"))
    o = cfg.observers[0]
    assert o.design_kwargs() == {"balance": True}
    design = fojax.design.design_functional_observer(cfg.design_system(), cfg.design_L(), kind=o.kind,
                                                     region=o.region, **o.design_kwargs())
    assert design.report.passed and "balance" in design.solver


def test_balance_key_reaches_the_unknown_input_design(tmp_path):
    """``balance = true`` on an ``unknown-input`` observer reaches
    `design_unknown_input_observer` through the CLI's design step (the design is the unit-free
    one: ``solver["balance"]`` holds the factors)."""
    # private: the CLI's per-observer design step is tested itself
    from fojax.cli._design import _design_observer

    d = base()
    d["observer"][0].update(kind="unknown-input", D=[[0.0], [0.0], [1.0], [0.0]], balance=True)
    cfg = load_config(write(tmp_path, d))
    spec = cfg.observers[0]
    assert spec.balance is True
    design = _design_observer(None, cfg.design_system(), cfg.design_L(), spec)
    assert design.report.passed and "balance" in design.solver


@pytest.mark.parametrize("extra,what", [
    ({"kind": "finite-time", "delay": 0.5, "regions": [{"center": -5.0, "radius": 0.5},
                                                       {"center": -2.0, "radius": 0.5}]},
     r"not 'finite-time': remove the key"),
])
def test_balance_key_refused_where_the_design_has_none(tmp_path, extra, what):
    d = base()
    d["observer"][0].update(balance=True, **extra)
    if "regions" in extra:  # a finite-time observer has two regions instead of one
        del d["observer"][0]["region"]
    p = write(tmp_path, d)
    with pytest.raises(fojax.errors.ConfigError, match=what) as info:
        load_config(p)
    assert info.value.key == "observer[0].balance"


def test_balance_key_refused_for_takagi_sugeno():
    d = load_config(example_path("robot_arm_ts")).raw
    bad = {**d, "observer": [{**d.get("observer", [{}])[0], "balance": True}]}
    with pytest.raises(fojax.errors.ConfigError, match=r"\[observer\[0\]\.balance\] is for linear models"):
        parse_config(bad, "ts.toml")


def test_takagi_sugeno_errors(tmp_path):
    d = load_config(example_path("robot_arm_ts")).raw
    bad = {**d, "takagi_sugeno": {**d["takagi_sugeno"], "index": 2}}
    with pytest.raises(fojax.errors.ConfigError, match=r"\[takagi_sugeno\.index\] is 2; expected an output index in 0\.\.1"):
        parse_config(bad, "ts.toml")
    bad = {**d, "takagi_sugeno": {**d["takagi_sugeno"], "premise": "sin"}}
    with pytest.raises(fojax.errors.ConfigError, match=r"\[takagi_sugeno\.premise\].*Did you mean 'sinc'"):
        parse_config(bad, "ts.toml")
    bad = {**d, "model": {**d["model"], "A": d["model"]["A"][0]}}
    with pytest.raises(fojax.errors.ConfigError, match=r"\[model\.A\] expected a list of n x n rule matrices"):
        parse_config(bad, "ts.toml")


def test_file_level_errors(tmp_path):
    with pytest.raises(fojax.errors.ConfigError, match=r"nope\.toml: \[\(file\)\] does not exist"):
        load_config(tmp_path / "nope.toml")
    p = tmp_path / "syntax.toml"
    p.write_text("[model]\nE = [[1, 0]\n")
    with pytest.raises(fojax.errors.ConfigError, match=r"syntax\.toml: \[\(syntax\)\] is not valid TOML"):
        load_config(p)
    p.write_text("name = 'x'\n")
    with pytest.raises(fojax.errors.ConfigError, match=r"\[model\] missing required key 'model'"):
        load_config(p)
    p.write_text("[model]\nE = [[1.0, nan], [0.0, 1.0]]\nA = [[1.0]]\nB = [[1.0]]\nC = [[1.0]]\nL = [[1.0]]\n")
    with pytest.raises(fojax.errors.ConfigError, match=r"\[model\.E\] entry model\.E\[0\]\[1\] is nan; every entry must be finite"):
        load_config(p)
    p.write_text("[model]\nE = [[1.0, true], [0.0, 1.0]]\nA = [[1.0]]\nB = [[1.0]]\nC = [[1.0]]\nL = [[1.0]]\n")
    with pytest.raises(fojax.errors.ConfigError, match=r"\[model\.E\].*is True \(boolean\)"):
        load_config(p)


def test_model_keys_outside_the_model_table(tmp_path):
    model = "E = [[1.0]]\nA = [[-1.0]]\nB = [[1.0]]\nC = [[1.0]]\nL = [[1.0]]\n"
    p = tmp_path / "noheader.toml"
    p.write_text("name = 'x'\n" + model)  # the [model] header forgotten (was: "unknown key 'E'")
    with pytest.raises(fojax.errors.ConfigError, match=r"\[model\] missing \[model\] table: E, A, B, C, L are at the "
                       r"top level\. Put them under a \[model\] table \(a line `\[model\]` above E\)"):
        load_config(p)
    p.write_text("E = [[1.0]]\n[model]\n" + model.split("\n", 1)[1])  # the header one line too low
    with pytest.raises(fojax.errors.ConfigError, match=r"\[E\] E is at the top level of the file, outside the \[model\] "
                       r"table.*Move them below the \[model\] header"):
        load_config(p)


@pytest.mark.parametrize("doc", ["docs/config.md", "docs/getting-started.md"])
def test_documented_example_config_is_valid(tmp_path, doc):
    import pathlib
    import re

    text = (pathlib.Path(__file__).resolve().parents[1] / doc).read_text()
    block = re.search(r"```toml\n(.*?)```", text, re.S).group(1)
    p = tmp_path / "doc.toml"
    p.write_text(block)
    cfg = load_config(p)
    assert cfg.E.shape == (3, 3) and cfg.L.shape == (1, 3) and cfg.observers


# Names become file and folder names (<observer>.npz, design-<name>-<time>/): the oracle is
# the rule itself (portable single path component), checked on hand-picked escapes.
BAD_NAMES = [
    ("../../../obs_escaped", r"path separator.*e\.g\. 'obs_escaped'"),
    ("a/b", r"path separator"),
    ("..", r"starts with '\.'"),
    (".hidden", r"starts with '\.'"),
    ("-rf", r"starts with '-'"),
    ("", r"it is empty"),
    ("two words", r"contains ' '"),
    ("naïve", r"contains 'ï'"),
    ("x" * 65, r"65 characters \(at most 64\)"),
    ("CON", r"Windows device name"),
    ("nul.tar", r"Windows device name"),
    ("ends.", r"ends with '\.'"),
]


@pytest.mark.parametrize("value,what", BAD_NAMES, ids=[repr(b[0])[:12] for b in BAD_NAMES])
def test_names_that_become_files_are_validated(tmp_path, value, what):
    for path, key in ((("observer", 0, "name"), "observer[0].name"), (("name",), "name")):
        p = write(tmp_path, _mutate(path, value))
        with pytest.raises(fojax.errors.ConfigError, match=what) as info:
            load_config(p)
        assert info.value.key == key and info.value.file == str(p)
        assert f"[{key}] {value!r} cannot be used" in str(info.value)
        assert "letters, digits" in str(info.value)  # the rule, with a valid example


def test_valid_names_and_the_default_model_name(tmp_path):
    d = base()
    d["name"] = "Plant_2.v1-a"
    d["observer"] = [{"name": n} for n in ("PO", "FGDO-1", "_x", "a.b", "9")]
    cfg = load_config(write(tmp_path, d))
    assert cfg.name == "Plant_2.v1-a" and [o.name for o in cfg.observers] == ["PO", "FGDO-1", "_x", "a.b", "9"]
    del d["name"]  # the file name, made portable
    assert load_config(write(tmp_path, d, "my model (v2).toml")).name == "my_model_v2_"
    assert load_config(write(tmp_path, d, "..toml")).name == "model"
    assert load_config(write(tmp_path, d, "con.toml")).name == "con_"
    # private: the file-name rule is tested itself
    from fojax._io import name_problem

    assert name_problem("a\\b") == "it contains a path separator ('/' or '\\')"


@pytest.mark.parametrize("names,what", [
    (["po", "po"], r"\[observer\[1\]\.name\] 'po' is the name of observer\[0\] too"),
    (["po", "PO"], r"\[observer\[1\]\.name\] 'PO' clashes with observer\[0\] 'po': its design PO\.npz would be the same file as its design po\.npz"),
    (["po", "po-tuned"], r"'po-tuned' clashes with observer\[0\] 'po': its design po-tuned\.npz .* tuned design po-tuned\.npz"),
    (["tuning-x", "x"], r"'x' clashes with observer\[0\] 'tuning-x': its tuning checkpoint tuning-x\.npz"),
    (["Study"], r"'Study' is reserved: `fojax study` writes study\.npz"),
    (["ok", "metrics"], r"\[observer\[1\]\.name\] 'metrics' is reserved"),
])
def test_observer_names_must_give_distinct_files(tmp_path, names, what):
    d = base()
    d["observer"] = [{"name": n} for n in names]
    with pytest.raises(fojax.errors.ConfigError, match=what):
        load_config(write(tmp_path, d))


# ``method`` of the generalized / PI / proportional kinds: the oracle is what
# `fojax.design.design_functional_observer` accepts (its `_riccati.riccati_applies` rule),
# checked at load time with the key named, so a file is refused before any design runs.
METHOD_ERRORS = [
    ({"kind": "PI", "method": "riccati"}, r"a PI observer's S = 0 constrains the gain"),
    ({"kind": "generalized", "method": "riccati", "region": {"disk": {"center": -2.0, "radius": 1.0}, "decay": 1.5}},
     r"needs one disk, half-plane or sector; region is"),
    ({"kind": "generalized", "method": "riccati", "objective": "centre"}, r"objective = 'centre' searches the region LMI"),
    ({"kind": "generalized", "method": "ricatti"}, r"Did you mean 'riccati'"),
    ({"kind": "unknown-input", "method": "lmi", "D": [[0.0], [0.0], [1.0], [0.0]]},
     r"is not a key of kind = 'unknown-input' observers"),
]


@pytest.mark.parametrize("observer,what", METHOD_ERRORS, ids=[m[1][:30] for m in METHOD_ERRORS])
def test_design_method_key_is_checked_at_load(tmp_path, observer, what):
    d = {**base(), "observer": [observer]}
    with pytest.raises(fojax.errors.ConfigError, match=what) as info:
        load_config(write(tmp_path, d))
    assert info.value.key == "observer[0].method"


def test_design_method_key_reaches_the_design(tmp_path):
    obs = [{"name": "ric", "kind": "generalized", "method": "riccati"},
           {"name": "auto", "kind": "proportional", "method": "auto", "region": {"decay": 1.0}},
           {"name": "pi", "kind": "PI", "method": "lmi"},
           {"name": "plain", "kind": "generalized"}]
    cfg = load_config(write(tmp_path, {**base(), "observer": obs}, "ok.toml"))
    kw = {o.name: o.design_kwargs() for o in cfg.observers}
    assert kw == {"ric": {"method": "riccati"}, "auto": {"method": "auto"}, "pi": {"method": "lmi"}, "plain": {}}
    ric = cfg.observers[0]
    d = fojax.design.design_functional_observer(cfg.design_system(), cfg.design_L(), kind=ric.kind,
                                                region=ric.region, **ric.design_kwargs())
    assert d.report.passed and d.solver["lmi"]["method"] == "riccati"
    # a Takagi-Sugeno model's observers need the common-certificate LMI
    ts = load_config(example_path("robot_arm_ts")).raw
    bad = {**ts, "observer": [{**ts["observer"][0], "method": "auto"}]}
    with pytest.raises(fojax.errors.ConfigError, match=r"one certificate common to all rules"):
        parse_config(bad, "ts.toml")


# ------------------------------------------------------------ [model] dt: discrete-time models
# Oracles: SciPy's generalized eigenvalues of (A, E) (finite ones inside the unit circle, as
# many as rank E: causal and stable) for the file's model, and the rules of the key
# (a finite number > 0; z-plane disks with |c| + r < 1) for the refusals.

DISCRETE = {
    "name": "sampled",
    "model": {
        "dt": 0.05,
        "E": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 0]],
        "A": [[0.96, 0.024, 0.0, 0.0], [0.0, 0.93, 0.02, 0.0], [0.01, 0.015, 1.02, 0.05], [0.6, 0.0, 1.0, 1.5]],
        "B": [[0.05], [0.0], [0.025], [1.0]],
        "C": [[1, 0, 0, 0], [0, 0, 0, 1]],
        "L": [[0, 1, 1, 0]],
    },
    "observer": [{"name": "fast", "region": {"disk": {"center": 0.2, "radius": 0.3}}}, {"kind": "proportional"}],
}


def test_discrete_model_file_loads_and_checks(tmp_path, capsys):
    import scipy.linalg as sla

    from fojax.cli import main
    from fojax.design import DiscreteDisk

    cfg = load_config(write(tmp_path, DISCRETE, "sampled.toml"))
    assert cfg.dt == 0.05
    sys_ = cfg.system()
    assert sys_.dt == 0.05 and cfg.design_system().dt == 0.05
    np.testing.assert_array_equal(np.asarray(sys_.A), np.asarray(DISCRETE["model"]["A"], dtype=float))
    fast, default = (o.region for o in cfg.observers)
    assert isinstance(fast, DiscreteDisk) and (float(fast.center), float(fast.radius)) == (0.2, 0.3)
    assert isinstance(default, DiscreteDisk) and (float(default.center), float(default.radius)) == (0.0, 0.5)
    # the oracle: causal (finite eigenvalues = rank E) and stable in discrete time (|λ| < 1)
    ev = sla.eigvals(np.asarray(DISCRETE["model"]["A"], float), np.asarray(DISCRETE["model"]["E"], float))
    finite = ev[np.isfinite(ev)]
    assert finite.size == 3 and np.abs(finite).max() < 1
    assert main(["check", str(tmp_path / "sampled.toml")]) == 0
    out = capsys.readouterr().out
    assert "discrete-time (dt = 0.05)" in out and "causal            yes" in out
    # without dt the same matrices are continuous-time and not stable (eigenvalues near 1 > 0)
    cont = {**DISCRETE, "model": {k: v for k, v in DISCRETE["model"].items() if k != "dt"},
            "observer": [{"name": "o"}]}
    assert load_config(write(tmp_path, cont, "cont.toml")).system().dt is None
    assert main(["check", str(tmp_path / "cont.toml")]) == 1


def _discrete(**changes):
    d = {**DISCRETE, "model": dict(DISCRETE["model"]), "observer": [dict(DISCRETE["observer"][0])]}
    for path, value in changes.items():
        *head, last = path.split("__")
        t = d
        for k in head:
            t = t[int(k)] if isinstance(t, list) else t[k]
        t[last] = value
    return d


DT_REFUSED = [
    (dict(model__dt=0), "model.dt", r"expected a positive number, got 0"),
    (dict(model__dt=-0.1), "model.dt", r"expected a positive number, got -0\.1"),
    (dict(model__dt="0.1"), "model.dt", r"expected a number, got '0\.1' \(string\)"),
    (dict(model__dt=True), "model.dt", r"expected a number, got True"),
    (dict(model__dt=float("inf")), "model.dt", r"expected a finite number"),
    (dict(uncertainty={"dA": [[[0.0] * 4] * 4]}), "model.dt", r"an uncertain model \(\[uncertainty\]\) is continuous-time"),
    (dict(observer__0__region={"disk": {"center": -0.5, "radius": 0.6}}), "observer[0].region.disk",
     r"not inside the open unit disk \(\|center\| \+ radius = 1\.1\)"),
    (dict(observer__0__region={"disk": {"center": 0.0, "radius": 0.5}, "decay": 1.0}), "observer[0].region.decay",
     r"s-plane region"),
    (dict(observer__0__kind="finite-time"), "observer[0].kind", r"continuous-time models only"),
    (dict(observer__0__objective="hinf", observer__0__Bw=[[1.0]] * 4), "observer[0].objective",
     r"'hinf', a continuous-time norm"),
]


@pytest.mark.parametrize("changes,key,what", DT_REFUSED, ids=[d[1] + ":" + d[2][:16] for d in DT_REFUSED])
def test_discrete_model_keys_are_checked(tmp_path, changes, key, what):
    p = write(tmp_path, _discrete(**changes))
    with pytest.raises(fojax.errors.ConfigError, match=what) as info:
        load_config(p)
    assert info.value.key == key


def test_study_refuses_a_discrete_model(tmp_path, capsys):
    from fojax.cli import main

    p = write(tmp_path, DISCRETE, "sampled.toml")
    assert main(["study", str(p), "--out", str(tmp_path)]) == 2
    assert "[model.dt] is 0.05: fojax study runs continuous-time models only" in capsys.readouterr().err
    assert not any(tmp_path.glob("study-*"))


def test_discrete_model_file_designs(tmp_path, capsys):
    # `fojax design` of a discrete model file without [[observer]]: the default z-plane disk
    # (0, 0.5); oracle: NumPy's eigenvalues of the saved observer's error matrix.
    from fojax.cli import main
    from fojax.results import load_design

    p = write(tmp_path, {k: v for k, v in DISCRETE.items() if k != "observer"}, "sampled.toml")
    assert main(["design", str(p), "--out", str(tmp_path), "--name", "run"]) == 0
    assert "max |eig|" in capsys.readouterr().out
    d = load_design(tmp_path / "run" / "generalized.npz")
    assert d.dt == 0.05 and d.observer.dt == 0.05
    assert np.abs(np.linalg.eigvals(np.asarray(d.error_matrix))).max() < 0.5
