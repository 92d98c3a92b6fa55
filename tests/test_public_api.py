"""The public API: at most 60 names at the top of `fojax`, one home per object, every name documented.

Oracle: the objects themselves (identity with their subpackage path, `__doc__`), the text of
each subpackage's docstring, and a fresh interpreter's `sys.modules` (what `import fojax` loads).
"""

import inspect
import os
import subprocess
import sys
import types

import pytest

import fojax


#: the cap of `fojax/__init__.py`'s docstring (submodules included)
MAX_TOP_LEVEL = 60


def _public(namespace):
    return [n for n in dir(namespace) if not n.startswith("_")]


def _subpackages():
    """The public subpackages and modules of fojax: ``{"fojax.design": module, ...}``. A data
    folder that some test opened as a namespace package (``importlib.resources.files
    ("fojax.examples")`` adds ``fojax.examples``, with no ``__file__``) is not one."""
    return {f"fojax.{n}": m for n in _public(fojax)
            if isinstance(m := getattr(fojax, n), types.ModuleType) and getattr(m, "__file__", None)}


def _objects_with_identity(module):
    """``{name: obj}`` of the classes and functions `module` exports (constants are values:
    the same float may sit under two names without being an alias)."""
    return {n: o for n in _public(module) if inspect.isclass(o := getattr(module, n)) or callable(o)
            and not isinstance(o, types.ModuleType)}


def test_at_most_60_names_at_the_top():
    # in a fresh interpreter: a test that imported fojax.cli has added `cli` to this one
    code = "import fojax; print(' '.join(n for n in dir(fojax) if not n.startswith('_')))"
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    names = out.stdout.split()
    assert 40 <= len(names) <= MAX_TOP_LEVEL, (len(names), names)
    assert "cli" not in names


def test_every_top_level_object_is_its_home_subpackage_object():
    homes = _subpackages()
    for name in _public(fojax):
        obj = getattr(fojax, name)
        if isinstance(obj, types.ModuleType):
            assert obj.__name__ == f"fojax.{name}", name
            continue
        found = [path for path, mod in homes.items() if getattr(mod, name, None) is obj]
        assert len(found) == 1, (name, found)


def test_no_object_has_two_public_paths():
    """Across the subpackages, each class or function sits at exactly one path (no alias
    names, no re-export from a second subpackage)."""
    paths = {}
    for path, mod in _subpackages().items():
        for name, obj in _objects_with_identity(mod).items():
            paths.setdefault(id(obj), []).append(f"{path}.{name}")
    doubles = [p for p in paths.values() if len(p) > 1]
    assert doubles == [], doubles


def test_every_public_name_is_documented():
    undocumented = []
    for path, mod in {"fojax": fojax, **_subpackages()}.items():
        if not (mod.__doc__ or "").strip():
            undocumented.append(path)
        for name in _public(mod):
            obj = getattr(mod, name)
            if isinstance(obj, types.ModuleType):
                continue
            if inspect.isclass(obj) or callable(obj):
                if not (inspect.getdoc(obj) or "").strip():
                    undocumented.append(f"{path}.{name}")
            elif name not in (mod.__doc__ or ""):
                undocumented.append(f"{path}.{name}")  # a constant: named in its package's docstring
    assert undocumented == [], undocumented


@pytest.mark.parametrize("path", sorted({"fojax", *_subpackages(), "fojax.cli"}))
def test_every_package_says_in_two_lines_what_lives_there(path):
    """Each ``__init__`` (and `fojax.errors`) starts with a docstring whose first paragraph
    is at most two lines."""
    import importlib

    doc = importlib.import_module(path).__doc__
    assert doc and doc.strip(), path
    first = doc.strip().split("\n\n")[0]
    assert len(first.splitlines()) <= 2, (path, first)


def test_entry_points_are_top_level_and_the_same_objects():
    assert fojax.simulate is fojax.simulation.simulate
    assert fojax.Study is fojax.studies.Study
    assert fojax.run_study is fojax.studies.run_study
    assert fojax.StudyResult is fojax.studies.StudyResult
    assert fojax.tune is fojax.tuning.tune
    assert fojax.FaultyPlant is fojax.plant.FaultyPlant
    assert fojax.FojaxError is fojax.errors.FojaxError


def test_import_fojax_makes_studies_and_tuning_attributes_without_cvxpy_or_the_cli():
    code = (
        "import sys, fojax; "
        "print(hasattr(fojax, 'studies'), hasattr(fojax, 'tuning'), 'cvxpy' in sys.modules, "
        "'fojax.cli' in sys.modules)"
    )
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    assert out.stdout.split() == ["True", "True", "False", "False"], out.stdout + out.stderr


def test_stepper_and_save_objects_are_top_level_and_instrumentation_is_not_public():
    for name in ("Auto", "Exact", "Exponential", "Diffrax", "Trajectory", "Metrics", "Bands"):
        assert getattr(fojax, name) is getattr(fojax.simulation, name), name
    assert "importlib" not in dir(fojax)
    assert "TRACE_COUNTS" not in dir(fojax.studies)
    assert "TRACE_COUNTS" not in dir(fojax.tuning)
