"""The tuning package's dependencies on the rest of fojax (issue 14, item 1).

Oracle: the source itself, parsed with `ast`. Before this change `fojax/tuning/` imported
18 names from private modules of other subpackages (``design._tunable``,
``studies._runner``, ``studies._sharding``), 8 of them not public anywhere
(``unflatten``, ``_atomic_write``, ``broadcast_bytes``, ``spans_processes``,
``writes_files``, ``check_same_on_every_process``, ``distributed_errors``, ``replicate``),
and a second entry point ``tune_takagi_sugeno`` wrapped ``tune``.
"""

import ast
import importlib
import pathlib

import fojax
import fojax.tuning


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
