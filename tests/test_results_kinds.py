"""save_design / load_design for every design class of fojax.design: Takagi–Sugeno,
unknown-input, finite-time and fault-estimator designs round-trip bit-exactly (every
array, every number of the report), load as the same class, and their observers give
identical vector fields and outputs; foreign membership classes are never imported."""

import dataclasses
import json
import pathlib
import zipfile

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import assert_designs_identical

import fojax
from fojax.design import (
    design_fault_estimator,
    design_finite_time_observer,
    design_ts_observer,
    design_unknown_input_observer,
    Disk,
    FaultEstimatorDesign,
    FiniteTimeObserverDesign,
    FunctionalObserverDesign,
    TakagiSugenoObserverDesign,
    UnknownInputObserverDesign,
)
from fojax.results import load_design, read_design_metadata, save_design


KINDS = ("ts", "uio", "finite_time", "fault")
CLASSES = {
    "ts": TakagiSugenoObserverDesign,
    "uio": UnknownInputObserverDesign,
    "finite_time": FiniteTimeObserverDesign,
    "fault": FaultEstimatorDesign,
}


@pytest.fixture(scope="module")
def designs():
    """One small thesis design of every kind (each LMI solved once per module)."""
    arm = fojax.models.robot_arm_ts().system
    ex413 = fojax.models.example_4_1_3()
    E, A, B, C, L = (np.asarray(x) for x in (ex413.E, ex413.A, ex413.B, ex413.C, ex413.L))
    closed = fojax.DescriptorSystem(E, A + B @ L, B, C)
    ex312 = fojax.models.example_3_1_2()
    ex337 = fojax.models.example_3_3_7()
    sys337 = fojax.DescriptorSystem(ex337.E, ex337.A, ex337.B, ex337.C)
    return {
        # z = [x2, x4] of the robot arm (x5 is refused by the T-S observer, see test_ts_uio)
        "ts": design_ts_observer(arm, np.eye(5)[[1, 3]], kind="generalized"),
        "uio": design_unknown_input_observer(closed, np.eye(4)[:, [2]], L),
        "finite_time": design_finite_time_observer(
            ex312.system, ex312.L, h=0.5, regions=((-5, 0.5), (-2, 0.5))
        ),
        "fault": design_fault_estimator(
            sys337, ex337.L, Fa=ex337.Fa, Fs=ex337.Fs, kind="generalized", region=Disk(-2.0, 1.0)
        ),
    }


@pytest.fixture(scope="module")
def saved(designs, tmp_path_factory):
    """Every design saved and loaded back once: ``{kind: (path, loaded)}``."""
    tmp = tmp_path_factory.mktemp("kinds")
    out = {}
    for k, d in designs.items():
        path = save_design(d, tmp / f"{k}.npz", metadata={"case": k})
        out[k] = (path, load_design(path))
    return out


@pytest.mark.parametrize("kind", KINDS)
def test_round_trip_same_class_bit_identical(designs, saved, kind):
    d, (path, loaded) = designs[kind], saved[kind]
    assert type(loaded) is CLASSES[kind]
    n = assert_designs_identical(d, loaded)
    # every matrix was compared (observer, structure, params, T, K, Z_eff, X, eigenvalues, ...)
    assert n >= {"ts": 30, "uio": 35, "finite_time": 60, "fault": 35}[kind], n
    assert str(loaded.report if kind != "finite_time" else loaded) == str(
        d.report if kind != "finite_time" else d
    )
    meta = read_design_metadata(path)
    assert meta["format_version"] == 3 and meta["design_class"] == CLASSES[kind].__name__
    assert meta["user"] == {"case": kind} and meta["fojax_version"] == fojax.__version__
    # the file holds plain arrays only (no pickled objects)
    with zipfile.ZipFile(path) as z, np.load(path, allow_pickle=False) as data:
        assert all(n.endswith(".npy") for n in z.namelist())
        assert all(data[k].dtype != object for k in data.files)


def _node(meta, *path):
    """The skeleton node of a saved design at a field path (format 3: ``meta["tree"]``)."""
    node = meta["tree"]
    for p in path:
        node = node["items"][p] if isinstance(p, int) else node["fields"][p]
    return node


def test_metadata_per_class(designs, saved):
    ts = read_design_metadata(saved["ts"][0])
    assert ts["summary"]["kind"] == "generalized" and _node(ts, "observer", "membership")["class"] == (
        "fojax.plant._takagi_sugeno:SectorMembership")
    assert ts["summary"]["report"]["extra"]["lyapunov_max_eig"] == designs["ts"].report.extra["lyapunov_max_eig"]
    assert _node(ts, "structure", "A")["shape"] == [2, 5, 5]  # two rules
    uio = read_design_metadata(saved["uio"][0])
    assert uio["summary"]["sizes"] == {"n": 4, "m": 2, "p": 3, "q": 2, "q0": designs["uio"].structure.q0}
    assert _node(uio, "D")["shape"] == [4, 1]
    ft = read_design_metadata(saved["finite_time"][0])
    assert _node(ft, "h") == {"$": "float", "repr": "0.5"}
    assert [_node(ft, "designs", i, "region")["class"] for i in (0, 1)] == ["fojax.design._regions:Disk"] * 2
    fault = read_design_metadata(saved["fault"][0])
    assert (_node(fault, "q"), _node(fault, "n_faults"), _node(fault, "ramp")) == (2, 3, False)
    assert _node(fault, "design", "structure", "E")["shape"] == [9, 9]  # 6 states + 3 constant faults
    # what the inner designs of a loaded object carry
    loaded_ft = saved["finite_time"][1]
    assert all(di.solver["saved"]["user"] == {"case": "finite_time"} for di in loaded_ft.designs)
    assert saved["uio"][1].solver["saved"]["user"] == {"case": "uio"}


def _random_inputs(obs, m, p, seed):
    rng = np.random.default_rng(seed)
    xi = jnp.asarray(rng.normal(size=obs.state_size))
    return xi, jnp.asarray(rng.normal(size=m)), jnp.asarray(3.0 * rng.normal(size=p))


@pytest.mark.parametrize("kind", KINDS)
def test_loaded_observer_gives_identical_vector_field_and_output(designs, saved, kind):
    d, loaded = designs[kind], saved[kind][1]
    o1, o2 = d.observer, loaded.observer
    s = (d.designs[0] if kind == "finite_time" else d.design if kind == "fault" else d).structure
    for seed in range(4):  # y of size 3: the T-S weights cover both clipped ends and the inside
        xi, u, y = _random_inputs(o1, s.m, s.p, seed)
        f1, f2 = o1.vector_field(0.0, xi, u, y), o2.vector_field(0.0, xi, u, y)
        assert np.array_equal(f1, f2) and np.all(np.isfinite(f1))
        assert np.array_equal(o1.output(0.0, xi, u, y), o2.output(0.0, xi, u, y))
    if kind == "ts":
        ys = jnp.asarray([[0.0, 0.0], [0.0, 1.0], [0.0, 4.0], [0.0, -2.5]])
        w1 = jax.vmap(lambda y: o1.weights(jnp.zeros(1), y))(ys)
        assert np.array_equal(w1, jax.vmap(lambda y: o2.weights(jnp.zeros(1), y))(ys))
        assert np.unique(np.round(np.asarray(w1[:, 0]), 12)).size == 4  # the weights vary
    if kind == "finite_time":
        xi2 = _random_inputs(o1, s.m, s.p, 9)[0]
        assert np.array_equal(o1.reconstruct(xi, xi2, u, y), o2.reconstruct(xi, xi2, u, y))


class _ForeignMembership(fojax.plant.AbstractMembership):
    """Two rules, w1 = logistic(a * y0), and a Python callable: not storable in a file."""

    a: jax.Array
    squash: object = eqx.field(static=True)

    @property
    def num_rules(self):
        return 2

    def __call__(self, y, u):
        w1 = self.squash(self.a * y[0])
        return jnp.stack([w1, 1.0 - w1])


class _ForeignArraysOnly(fojax.plant.AbstractMembership):
    a: jax.Array

    @property
    def num_rules(self):
        return 2

    def __call__(self, y, u):
        w1 = jax.nn.sigmoid(self.a * y[0])
        return jnp.stack([w1, 1.0 - w1])


def test_foreign_membership_is_never_imported_and_can_be_passed(designs, tmp_path):
    d = designs["ts"]
    custom = _ForeignMembership(jnp.asarray(0.7), jax.nn.sigmoid)
    d2 = dataclasses.replace(d, observer=eqx.tree_at(lambda o: o.membership, d.observer, custom))
    path = save_design(d2, tmp_path / "custom.npz")
    meta = _node(read_design_metadata(path), "observer", "membership")
    assert meta["$"] == "unstored" and meta["reason"].startswith("_ForeignMembership.squash is a ")
    with pytest.raises(fojax.errors.InputError, match=r"cannot be rebuilt: it was not stored.*membership=plant\.membership"):
        load_design(path)
    loaded = load_design(path, membership=custom)
    assert_designs_identical(d2, loaded)
    # a tree of arrays is stored, but its class is outside fojax: never imported from a file
    arrays_only = _ForeignArraysOnly(jnp.asarray(0.7))
    d3 = dataclasses.replace(d, observer=eqx.tree_at(lambda o: o.membership, d.observer, arrays_only))
    path3 = save_design(d3, tmp_path / "arrays.npz")
    assert _node(read_design_metadata(path3), "observer", "membership", "a")["$"] == "array"
    with pytest.raises(fojax.errors.InputError, match=r"_ForeignArraysOnly is not a fojax class \(fojax never imports"):
        load_design(path3)
    xi, u, y = _random_inputs(d3.observer, 1, 2, 0)
    o = load_design(path3, membership=arrays_only).observer
    assert np.array_equal(o.vector_field(0.0, xi, u, y), d3.observer.vector_field(0.0, xi, u, y))


def test_format_1_files_load_and_membership_argument_is_ts_only(designs, tmp_path):
    """Format 1 = format 2 without ``design_class`` (functional designs only): made from the
    committed format-2 file written by fojax before format 3 (tests/data/designs_v2)."""
    v2 = pathlib.Path(__file__).parent / "data" / "designs_v2" / "functional.npz"
    with np.load(v2, allow_pickle=False) as data:
        arrays = {k: data[k] for k in data.files}
    meta = json.loads(str(arrays["__metadata__"][()]))
    assert meta.pop("design_class") == "FunctionalObserverDesign" and meta["format_version"] == 2
    meta["format_version"] = 1
    arrays["__metadata__"] = np.array(json.dumps(meta))
    np.savez(tmp_path / "v1.npz", **arrays)
    old = load_design(tmp_path / "v1.npz")
    assert type(old) is FunctionalObserverDesign
    assert_designs_identical(load_design(v2), old)
    with pytest.raises(fojax.errors.InputError, match="membership= applies to Takagi–Sugeno designs only"):
        load_design(v2, membership=designs["ts"].observer.membership)
    with pytest.raises(fojax.errors.InputError, match="membership= applies to Takagi–Sugeno designs only"):
        load_design(save_design(designs["uio"], tmp_path / "uio.npz"), membership=designs["ts"].observer.membership)
    meta["format_version"], meta["design_class"] = 2, "FancyDesign"
    arrays["__metadata__"] = np.array(json.dumps(meta))
    np.savez(tmp_path / "fancy.npz", **arrays)
    with pytest.raises(fojax.errors.InputError, match="class 'FancyDesign', which this fojax version cannot load"):
        load_design(tmp_path / "fancy.npz")
