"""Test configuration: 64-bit JAX, strict rank promotion, a deterministic key factory."""

import gc
import os
import subprocess
import sys


# Several tests exercise the sharded path; give the CPU 4 host devices before JAX starts.
os.environ.setdefault("XLA_FLAGS", "--xla_force_host_platform_device_count=4")
os.environ.setdefault("MPLBACKEND", "Agg")

# One persistent XLA compilation cache for the whole run, shared by the xdist workers, the
# notebook kernels and the CLI subprocesses (they inherit the environment): a program that
# several modules or processes compile (after ``jax.clear_caches()`` below, or in a fresh
# kernel) is compiled once. Created by the first process that loads this file (the xdist
# controller, or the single process under ``-n 0``) and removed when that process exits.
# Keys include the jax/jaxlib versions, the HLO and the device set, so a hit is always the
# same executable.
if "JAX_COMPILATION_CACHE_DIR" not in os.environ:
    import atexit
    import shutil
    import tempfile

    _JAX_CACHE = tempfile.mkdtemp(prefix="fojax-tests-jax-cache-")
    os.environ["JAX_COMPILATION_CACHE_DIR"] = _JAX_CACHE
    atexit.register(shutil.rmtree, _JAX_CACHE, True)
# Every program goes into that cache, however short its compilation (JAX's default keeps only
# those over 1 s): the suite compiles many small programs again in later modules (after the
# ``jax.clear_caches()`` below) and in the CLI subprocesses. Measured on a clean clone, two
# workers, Intel Xeon: the test times summed 3,003 s -> 2,705 s and the run took 23 min 0 s
# instead of 25 min 30 s (that run also had this stop's faster live-parameter count, ~1 s of
# compiling per design less). Programs with host callbacks (the diffrax path) are never cached.
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")


# Every test module compiles with most of XLA's optimizations off (``jax_disable_most_optimizations``:
# LLVM at -O0, no expensive passes), unless it is marked ``production_codegen`` (below). The
# suite is dominated by compilation, and a test proves numbers against a tolerance, not the
# code XLA generates for them. Measured on an Intel Xeon (2 cores): the XLA part of the tuning
# step's compilation (benchmarks/tuning_step.py, without the fusion emitters, quiet machine)
# 1.35 s instead of 3.2 s (the step then runs 0.85 s instead of 0.25 s); the whole suite (clean
# clone, two workers, `.ci/run`) 10 min 50 s - 12 min 8 s in four runs (three OpenBLAS kernels)
# instead of 15 min 13 s the same evening.
# Inherited by the notebook kernels and the CLI subprocesses (``JAX_DISABLE_MOST_OPTIMIZATIONS=0``
# runs the whole suite with the optimizations users get).
os.environ.setdefault("JAX_DISABLE_MOST_OPTIMIZATIONS", "1")
#: The suite's setting above (for the subprocesses), restored after each ``production_codegen`` module.
_FAST_CODEGEN = os.environ["JAX_DISABLE_MOST_OPTIMIZATIONS"]


def _program_compile_flag() -> str:
    """``COMPILE_FLAG`` of fojax/cli/_devices.py, the flag the ``fojax`` program adds (one
    literal; the module is loaded from its file: importing fojax here would import JAX
    before the environment above is set)."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "fojax" / "cli" / "_devices.py"
    spec = importlib.util.spec_from_file_location("_fojax_cli_devices_for_tests", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.COMPILE_FLAG


#: XLA:CPU flag of the test runs: compile without the fusion emitters. The suite is dominated
#: by single-threaded XLA compilation. Measured on an Intel Xeon (2 cores): a tuning step of
#: benchmarks/tuning_step.py compiled in 8.2 s instead of 11.8 s (but ran 0.52 s instead of
#: 0.40 s: some kernels run slower, see fojax/cli/_devices.py), test_adjoint_passes +
#: test_study_loss_blocks + test_exponential took 80 s instead of 121 s, and the whole suite
#: (clean clone, 2 workers) 16 min 46 s instead of 23 min 0 s. It changes how XLA generates
#: code, not what it computes (the tests hold on any BLAS kernel, so on either code
#: generator). An XLA flag that a jaxlib does not know aborts the process, so it is added
#: only after a child process with it has started JAX's CPU backend (once, in the first
#: process; the xdist workers, notebook kernels and CLI subprocesses inherit the result;
#: ``FOJAX_TEST_XLA_FLAG=`` (empty) runs the suite with XLA's default; an ``XLA_FLAGS`` that
#: names the flag wins, as in the ``fojax`` program, fojax/cli/_devices.py).
TEST_XLA_FLAG = _program_compile_flag()
if "FOJAX_TEST_XLA_FLAG" not in os.environ and TEST_XLA_FLAG.split("=")[0] not in os.environ["XLA_FLAGS"]:
    _flags = f"{os.environ['XLA_FLAGS']} {TEST_XLA_FLAG}"
    try:
        _probe = subprocess.run([sys.executable, "-c", "import jax; jax.devices('cpu')"], capture_output=True,
                                env=dict(os.environ, XLA_FLAGS=_flags), timeout=300).returncode
    except subprocess.TimeoutExpired:
        _probe = None
    os.environ["FOJAX_TEST_XLA_FLAG"] = TEST_XLA_FLAG if _probe == 0 else ""
    if _probe == 0:
        os.environ["XLA_FLAGS"] = _flags

import jax  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402


jax.config.update("jax_enable_x64", True)


def _empty_safe_matrix_rank(matrix_rank):
    """NumPy < 2.4.5 raises on `np.linalg.matrix_rank` of an empty matrix instead of
    returning its rank, 0; the tests' rank oracles take such matrices (E of full rank has an
    empty E⊥), so at the NumPy floor (pyproject.toml) they get the mathematical value."""

    def rank(A, *args, **kwargs):
        a = np.asarray(A)
        if a.size == 0 and a.ndim >= 2:
            return np.zeros(a.shape[:-2], dtype=int) if a.ndim > 2 else 0
        return matrix_rank(A, *args, **kwargs)

    return rank


if tuple(int(p) for p in np.__version__.split(".")[:3] if p.isdigit()) < (2, 4, 5):
    np.linalg.matrix_rank = _empty_safe_matrix_rank(np.linalg.matrix_rank)
#: The same setting as JAX read it from ``JAX_DISABLE_MOST_OPTIMIZATIONS`` (restored in this
#: process after each ``production_codegen`` module).
_FAST_CODEGEN_FLAG = jax.config.read("jax_disable_most_optimizations")
jax.config.update("jax_numpy_rank_promotion", "raise")
# in case a plugin imported JAX before the environment variable above was set
jax.config.update("jax_compilation_cache_dir", os.environ["JAX_COMPILATION_CACHE_DIR"])
jax.config.update("jax_persistent_cache_min_compile_time_secs",
                  float(os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"]))


@pytest.fixture
def getkey():
    """Return a function producing fresh, deterministic PRNG keys."""
    counter = [0]

    def _getkey():
        counter[0] += 1
        return jax.random.PRNGKey(counter[0])

    return _getkey


@pytest.fixture
def rng():
    return np.random.default_rng(20261121)


@pytest.fixture(scope="module", autouse=True)
def _module_codegen_and_release(request):
    """Compile the module's programs as users get them if it is marked ``production_codegen``;
    drop JAX's compiled executables after every test module.

    ``production_codegen`` (``pytestmark = pytest.mark.production_codegen``) is for modules that
    compare two *different* programs bit for bit (1 device against several, one process
    against several, chunks and blocks of other sizes, eager against compiled): that equality
    is a property of the code XLA generates with its default optimizations, which is what
    users run; with LLVM at -O0 it does not hold everywhere (measured: six such tests failed,
    by 3e-16). The setting goes to the module's subprocesses through the environment; JAX's
    in-memory caches are cleared on either side (the option is not part of their keys; the
    persistent cache's keys include it).

    Each XLA:CPU executable keeps its own memory mappings; the whole suite compiles
    thousands of them, and one process would exceed Linux's default limit of 65,530
    mappings per process (``vm.max_map_count``), which ends in a segmentation fault inside
    the compiler. Modules compile their own kernels anyway (module-scoped fixtures).
    """
    production = request.node.get_closest_marker("production_codegen") is not None
    if production:
        jax.clear_caches()
        jax.config.update("jax_disable_most_optimizations", False)
        os.environ["JAX_DISABLE_MOST_OPTIMIZATIONS"] = "0"
    try:
        yield
    finally:
        jax.clear_caches()
        gc.collect()
        if production:
            os.environ["JAX_DISABLE_MOST_OPTIMIZATIONS"] = _FAST_CODEGEN
            jax.config.update("jax_disable_most_optimizations", _FAST_CODEGEN_FLAG)


#: Test modules by the time they take in a CI run, longest first (measured 2026-11-27 with
#: ``--junitxml``, the sum of each module's test times in a full run on 2 workers; the executed
#: notebooks and the CLI modules spend most of it in subprocesses). pytest-xdist (``--dist
#: loadfile``, two workers) hands out whole modules in collection order — ``--no-loadscope-reorder``
#: in pyproject.toml, otherwise it reorders them by their number of tests and the one-test
#: notebook modules ran last, alone — so this order is longest-processing-time-first scheduling.
HEAVY_FIRST = (
    "test_distributed.py",
    "test_simulation.py",
    "test_cli_config.py",
    "test_tuning_ts.py",
    "test_cli_ts.py",
    "test_studies.py",
    "test_cli_signals.py",
    "test_study_exact.py",
    "test_cli_devices.py",
    "test_parameterization.py",
    "test_study_exponential.py",
    "test_adjoint.py",
    "test_tuning.py",
    "test_implicit_solver.py",
    "test_notebook_quickstart.py",
    "test_steppers.py",
    "test_study_signal.py",
    "test_study_loss.py",
    "test_tuning_time_varying.py",
    "test_tuning_robustness.py",
    "test_notebook_observers.py",
    "test_design.py",
    "test_notebook_monte_carlo.py",
    "test_cli.py",
    "test_control.py",
    "test_unknown_input.py",
    "test_takagi_sugeno.py",
    "test_notebook_control.py",
)


def pytest_collection_modifyitems(session, config, items):
    rank = {name: i for i, name in enumerate(HEAVY_FIRST)}
    order = {id(item): k for k, item in enumerate(items)}
    items.sort(key=lambda it: (rank.get(it.path.name, len(rank)), order[id(it)]))
