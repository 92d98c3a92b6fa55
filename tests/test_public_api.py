"""The public entry points at the top of `fojax` (one name per concept, one path per name).

Oracle: the objects themselves (identity with their subpackage path) and a fresh
interpreter's `sys.modules` (what `import fojax` loads).
"""

import os
import subprocess
import sys

import fojax


def test_entry_points_are_top_level_and_the_same_objects():
    assert fojax.simulate is fojax.simulation.simulate
    assert fojax.Study is fojax.studies.Study
    assert fojax.run_study is fojax.studies.run_study
    assert fojax.StudyResult is fojax.studies.StudyResult
    assert fojax.tune is fojax.tuning.tune


def test_import_fojax_makes_studies_and_tuning_attributes_without_cvxpy():
    code = (
        "import sys, fojax; "
        "print(hasattr(fojax, 'studies'), hasattr(fojax, 'tuning'), 'cvxpy' in sys.modules)"
    )
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    assert out.stdout.split() == ["True", "True", "False"], out.stdout + out.stderr


def test_stepper_and_save_objects_are_top_level_and_instrumentation_is_not_public():
    for name in ("Auto", "Exact", "Exponential", "Diffrax", "AbstractStepper", "Trajectory", "Metrics", "Bands"):
        assert getattr(fojax, name) is getattr(fojax.simulation, name), name
    assert "importlib" not in dir(fojax)
    assert "TRACE_COUNTS" not in dir(fojax.studies)
    assert "TRACE_COUNTS" not in dir(fojax.tuning)
