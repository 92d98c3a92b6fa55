"""`fojax.design.AbstractDesign`: one base for every design result — verify(), summary(),
save()/load() with no code per class (format 3), and old files (formats 1/2) still load.

Oracles:
- the design files written by fojax *before* format 3 (``tests/data/designs_v2``, written at
  commit 964645a by the format-2 writer, one per design kind, all from thesis examples:
  §4.1.3 closed loop, §4.1.3 H∞, the robot-arm T-S model, §4.1.3 with an unknown input,
  §3.1.2 finite time, §3.3.7 fault estimation): their raw ``.npz`` entries are the expected
  arrays, compared bit for bit (``np.array_equal``, same dtype and shape);
- the one float64 verification routine (`fojax.design.verify`: residuals of the design
  conditions, eigenvalues by ``np.linalg.eigvals``, the region LMI by ``eigvalsh``) must pass
  on every loaded design and fail on numbers changed after the design;
- hand-made damage to a file (a missing entry, a wrong shape) must be named in the error.

No LMI is solved here: every design comes from the committed files (cheap).
"""

import dataclasses
import json
import pathlib

import numpy as np
import pytest
from helpers import assert_designs_identical

import fojax
from fojax.design import (
    AbstractDesign,
    FaultEstimatorDesign,
    FiniteTimeObserverDesign,
    FunctionalObserverDesign,
    TakagiSugenoObserverDesign,
    UnknownInputObserverDesign,
    VerificationReport,
)
from fojax.results import load_design, read_design_metadata, save_design


V2 = pathlib.Path(__file__).parent / "data" / "designs_v2"
CLASSES = {
    "functional": FunctionalObserverDesign,
    "hinf": FunctionalObserverDesign,
    "ts": TakagiSugenoObserverDesign,
    "uio": UnknownInputObserverDesign,
    "finite_time": FiniteTimeObserverDesign,
    "fault": FaultEstimatorDesign,
}
KINDS = tuple(CLASSES)


@pytest.fixture(scope="module")
def old():
    """Every committed format-2 file, loaded (and re-verified) once."""
    return {k: load_design(V2 / f"{k}.npz") for k in KINDS}


@pytest.fixture(scope="module")
def resaved(old, tmp_path_factory):
    """Every design saved in format 3 and loaded back: ``{kind: (path, loaded)}``."""
    tmp = tmp_path_factory.mktemp("v3")
    return {k: (p := d.save(tmp / f"{k}.npz", metadata={"case": k}), AbstractDesign.load(p)) for k, d in old.items()}


def _raw(kind):
    with np.load(V2 / f"{kind}.npz", allow_pickle=False) as data:
        return {k: data[k] for k in data.files}


def _observer_prefix(kind):
    return {"finite_time": "designs/0/", "fault": "design/"}.get(kind, "")


@pytest.mark.parametrize("kind", KINDS)
def test_old_format_file_loads_bit_identical_and_verifies(old, kind):
    d, raw = old[kind], _raw(kind)
    assert type(d) is CLASSES[kind] and isinstance(d, AbstractDesign)
    assert json.loads(str(raw["__metadata__"][()]))["format_version"] == 2
    p = _observer_prefix(kind)
    inner = d.designs[0] if kind == "finite_time" else d.design if kind == "fault" else d
    # the oracle: the file's own arrays
    for name in ("N", "F", "P", "Q"):
        assert np.array_equal(np.asarray(getattr(inner.observer, name)), raw[f"{p}observer/{name}"]), name
    for name in ("X", "T"):
        assert np.array_equal(getattr(inner, name), raw[p + name]), name
    assert np.array_equal(inner.structure.E, raw[f"{p}structure/E"])
    assert np.array_equal(inner.report.eigenvalues, raw[f"{p}report/eigenvalues"])
    report = d.verify()
    assert isinstance(report, VerificationReport) and report.passed and report.relative_residual <= 1e-8
    assert report.region_margin > 0 and (report.lmi_max_eig is None or report.lmi_max_eig < 0)


@pytest.mark.parametrize("kind", KINDS)
def test_every_kind_round_trips_save_load_verify(old, resaved, kind):
    d, (path, loaded) = old[kind], resaved[kind]
    assert type(loaded) is CLASSES[kind]
    n = assert_designs_identical(d, loaded)
    assert n >= {"functional": 30, "hinf": 32, "ts": 30, "uio": 35, "finite_time": 60, "fault": 35}[kind], n
    assert str(loaded) == str(d) and loaded.summary() == str(d)
    before, after = d.verify(), loaded.verify()
    assert after.passed and before.to_dict() == after.to_dict()  # the same numbers, re-checked
    meta = read_design_metadata(path)
    assert meta["format_version"] == 3 and meta["design_class"] == CLASSES[kind].__name__
    assert meta["user"] == {"case": kind} and meta["tree"]["$"] == "object"
    assert type(CLASSES[kind].load(path)) is CLASSES[kind]


def test_base_attributes_of_every_kind(old):
    for kind, d in old.items():
        assert d.report.passed and d.observer is not None, kind
        if kind == "finite_time":
            assert [r.center for r in d.region] == [-5.0, -2.0]
            assert [x.shape for x in d.certificate] == [di.X.shape for di in d.designs]
            assert d.report.residuals.keys() >= {"observer 1.a", "observer 2.d"}
            assert d.report.extra["reconstruction rcond"] == d.reconstruction_rcond
        else:
            assert d.certificate is (d.design.X if kind == "fault" else d.X)
            assert np.all(np.linalg.eigvalsh(0.5 * (d.certificate + d.certificate.T)) > 0)
            assert isinstance(d.region, fojax.design.AbstractRegion)
    assert old["hinf"].hinf is not None and "H∞" in old["hinf"].verify().extra
    assert old["ts"].verify().extra["lyapunov_max_eig"] < 0
    assert fojax.design.AbstractDesign is AbstractDesign


@pytest.mark.parametrize("kind", ["functional", "ts", "uio", "hinf"])
def test_verify_rechecks_the_numbers_not_the_stored_report(old, kind):
    """Regression: verify() re-runs the checks; a gain changed after the design (the stored
    report still says PASSED) fails with the failed condition named."""
    d = old[kind]
    G = np.asarray(d.params["G"])  # the v-block of the error dynamics: eigenvalues move right
    assert G.size
    bad = dataclasses.replace(d, params={**d.params, "G": G + 10.0 * (1.0 + np.abs(G))})
    assert bad.report.passed
    with pytest.raises(fojax.errors.DesignVerificationError, match="outside the region|region LMI|Lyapunov") as info:
        bad.verify()
    assert not info.value.report.passed


def test_finite_time_verify_rechecks_the_reconstruction(old):
    import equinox as eqx

    d = old["finite_time"]
    o = eqx.tree_at(lambda o: o.Gamma_now, d.observer, d.observer.Gamma_now * 1.001)
    with pytest.raises(fojax.errors.DesignVerificationError, match="reconstruction is not exact"):
        dataclasses.replace(d, observer=o).verify()


def _rewrite(src, dst, change):
    with np.load(src, allow_pickle=False) as data:
        arrays = {k: data[k] for k in data.files}
    change(arrays)
    np.savez(dst, **arrays)
    return dst


def test_damaged_files_give_clear_errors(resaved, tmp_path):
    path = resaved["functional"][0]
    wrong = _rewrite(path, tmp_path / "shape.npz", lambda a: a.update({"observer/N": np.zeros((3, 3))}))
    with pytest.raises(fojax.errors.InputError, match=r"array 'observer/N' has shape \(3, 3\).*expects shape \(\d+, \d+\)"
                       r".*Re-create it"):
        load_design(wrong)
    missing = _rewrite(path, tmp_path / "missing.npz", lambda a: a.pop("structure/E"))
    with pytest.raises(fojax.errors.InputError, match=r"has no array 'structure/E'.*changed or truncated"):
        load_design(missing)
    dtype = _rewrite(path, tmp_path / "dtype.npz", lambda a: a.update({"X": a["X"].astype(np.float32)}))
    with pytest.raises(fojax.errors.InputError, match=r"array 'X' has shape .* dtype float32.*dtype float64"):
        load_design(dtype)
    numbers = _rewrite(path, tmp_path / "numbers.npz", lambda a: a.update({"params/Y1": a["params/Y1"] + 50.0}))
    with pytest.raises(fojax.errors.DesignVerificationError):
        load_design(numbers)
    unchecked = load_design(numbers, verify=False)  # the caller's choice; verify() still says no
    with pytest.raises(fojax.errors.DesignVerificationError):
        unchecked.verify()
    with pytest.raises(fojax.errors.InputError, match="holds a FunctionalObserverDesign, not a FiniteTimeObserverDesign"):
        FiniteTimeObserverDesign.load(path)


def test_damaged_old_format_file_names_the_missing_entry(tmp_path):
    bad = _rewrite(V2 / "uio.npz", tmp_path / "uio.npz", lambda a: a.pop("observer/Delta"))
    with pytest.raises(fojax.errors.InputError, match=r"has no array 'observer/Delta', which a format-2 design needs"):
        load_design(bad)


def test_a_file_never_makes_fojax_import_code(resaved, tmp_path):
    path = resaved["functional"][0]

    def foreign(a):
        meta = json.loads(str(a["__metadata__"][()]))
        meta["tree"]["fields"]["region"]["class"] = "os:system"
        a["__metadata__"] = np.array(json.dumps(meta))

    with pytest.raises(fojax.errors.InputError, match=r"os:system is not a fojax class \(fojax never imports"):
        load_design(_rewrite(path, tmp_path / "foreign.npz", foreign))


def test_save_is_atomic_and_never_clobbers(old, tmp_path):
    d = old["functional"]
    p = d.save(tmp_path / "d.npz")
    before = p.read_bytes()
    with pytest.raises(FileExistsError, match="overwrite=True"):
        save_design(d, p)
    assert p.read_bytes() == before and sorted(q.name for q in tmp_path.iterdir()) == ["d.npz"]
    with pytest.raises(TypeError, match="AbstractDesign"):
        save_design(object(), tmp_path / "x.npz")


def test_state_feedback_is_a_design_result_too(tmp_path):
    """`fojax.control`'s state feedback (§4.1.3, dual LMI and slow-subsystem routes) round-trips
    and re-verifies; a gain changed afterwards fails its re-verification."""
    ex = fojax.models.example_4_1_3()
    for kw in ({}, {"region": fojax.Disk(-3.0, 2.0)}):
        sf = fojax.design_state_feedback(ex.system, **kw)
        loaded = AbstractDesign.load(sf.save(tmp_path / f"sf{len(kw)}.npz"))
        assert type(loaded) is type(sf) and assert_designs_identical(sf, loaded) >= 6
        assert loaded.observer is None and loaded.report is loaded.checks
        assert loaded.verify()["region_margin"] == sf.checks["region_margin"] > 0
        with pytest.raises(fojax.errors.DesignVerificationError):
            dataclasses.replace(sf, L=-np.asarray(sf.L)).verify()


@dataclasses.dataclass
class _Foreign:
    a: int = 1


def test_free_form_solver_info_never_blocks_a_load(old, tmp_path):
    """Regression: a callable or a non-fojax object in ``solver`` (e.g. a custom tuning loss)
    is stored as its str, so the design still loads; its arrays stay exact."""
    d = old["functional"]
    d2 = dataclasses.replace(d, solver={**d.solver, "tuning": {"loss": len, "obj": _Foreign(), "steps": 3}})
    loaded = load_design(d2.save(tmp_path / "tuned.npz"))
    assert loaded.solver["tuning"] == {"loss": str(len), "obj": "_Foreign(a=1)", "steps": 3}
    assert assert_designs_identical(d2, loaded) >= 30
