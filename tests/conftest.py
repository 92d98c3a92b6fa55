"""Test configuration: 64-bit JAX, strict rank promotion, a deterministic key factory."""

import gc
import os


# Several tests exercise the sharded path; give the CPU 4 host devices before JAX starts.
os.environ.setdefault("XLA_FLAGS", "--xla_force_host_platform_device_count=4")
os.environ.setdefault("MPLBACKEND", "Agg")

import jax  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402


jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")


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
def _release_compiled_code():
    """Drop JAX's compiled executables after every test module.

    Each XLA:CPU executable keeps its own memory mappings; the whole suite compiles
    thousands of them, and one process would exceed Linux's default limit of 65,530
    mappings per process (``vm.max_map_count``), which ends in a segmentation fault inside
    the compiler. Modules compile their own kernels anyway (module-scoped fixtures).
    """
    yield
    jax.clear_caches()
    gc.collect()
