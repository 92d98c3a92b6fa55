"""`fojax study --devices N` / ``FOJAX_DEVICES``: JAX host devices (`fojax.cli._devices`, issue 13).

Oracle: the one-device run of the same command. A small study (example 4.1.3, 4 samples,
0.5 s, 1 tuning step) run as the ``fojax`` program in two subprocesses, one with
``FOJAX_DEVICES=1`` and one on two devices, must write the same bits into every result
array (metrics, study, samples, designs, the tuned design, the tuning checkpoint); only
the device count and the time stamps may differ. The device count of the pytest process
itself (4, tests/conftest.py) is never touched. The flag logic is checked on explicit
argv/environment dicts against the rules stated in the module docstring; so is the
compile flag the program adds (`configure_compiler`), and a child started as the program
must show it in its environment and start JAX's CPU backend with it.
"""

import json
import os
import subprocess
import sys

import jax
import numpy as np
import pytest
from helpers import child_xla_flags

from fojax.cli import main

# private: the program's device and compile-flag set-up is what this module tests
from fojax.cli._devices import (
    _jaxlib_version,
    COMPILE_FLAG,
    COMPILE_FLAG_JAXLIB,
    configure_compiler,
    configure_host_devices,
    FLAG,
    usable_cores,
)


# bit-for-bit equality of different programs (`fojax study` on two devices against one): compiled as users get it
pytestmark = pytest.mark.production_codegen


ARGS = ("study", "example_4_1_3", "--samples", "4", "--horizon", "0.5", "--steps", "1")


def _env(**extra):
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "FOJAX_DEVICES")}
    env["XLA_FLAGS"] = child_xla_flags()
    return env | extra


@pytest.fixture(scope="module")
def two_runs(tmp_path_factory):
    """The same small study on 1 and on 2 devices, started concurrently."""
    tmp = tmp_path_factory.mktemp("devices")
    procs = {}
    for n, env in ((1, _env(FOJAX_DEVICES="1")), (2, _env(FOJAX_DEVICES="2"))):
        procs[n] = subprocess.Popen([sys.executable, "-m", "_fojax_program", *ARGS, "--out", str(tmp / f"d{n}")],
                                    stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    out = {}
    for n, p in procs.items():
        stdout, stderr = p.communicate(timeout=900)
        assert p.returncode == 0, stderr
        (folder,) = (tmp / f"d{n}").iterdir()
        out[n] = (stdout, folder)
    return out


def test_study_on_two_devices_writes_the_same_bits_as_on_one(two_runs):
    (out1, f1), (out2, f2) = two_runs[1], two_runs[2]
    assert "devices: 1 JAX cpu device\n" in out1
    assert "devices: 2 JAX cpu devices\n" in out2
    assert json.loads((f2 / "study-options.json").read_text())["jax_devices"] == "2 JAX cpu devices"
    npz = sorted(p.name for p in f1.glob("*.npz"))
    assert npz == sorted(p.name for p in f2.glob("*.npz"))
    assert {"metrics.npz", "study.npz", "study-samples.npz", "generalized-tuned.npz",
            "tuning-generalized.npz"} <= set(npz)
    for name in npz:
        with np.load(f1 / name) as a, np.load(f2 / name) as b:
            assert a.files == b.files, name
            for k in a.files:
                if k == "__metadata__":  # JSON with the creation time
                    continue
                assert a[k].dtype == b[k].dtype and a[k].shape == b[k].shape, (name, k)
                assert a[k].tobytes() == b[k].tobytes(), (name, k)
    for name in ("metrics.json", "study-samples.json", "tuning-generalized.json"):
        assert (f1 / name).read_text() == (f2 / name).read_text(), name
    # the tables printed (4 significant digits) are the same too
    tables1, tables2 = (o.split("Mean IAE", 1)[1].rsplit("results:", 1)[0] for o in (out1, out2))
    assert tables1 == tables2


def test_pytest_process_keeps_its_devices(two_runs):
    assert jax.local_device_count() == 4  # tests/conftest.py; the subprocesses changed nothing here


@pytest.mark.parametrize(
    "argv, environ, expected",
    [
        (["study"], {}, None),                                                 # default: one device
        (["--quiet", "study", "my.toml", "--devices", "auto"], {}, usable_cores()),  # one per core
        (["study", "--devices", "3"], {}, 3),                                  # --devices
        (["study", "--devices=1"], {}, 1),
        (["study"], {"FOJAX_DEVICES": "5"}, 5),                                # environment
        (["study"], {"FOJAX_DEVICES": "auto"}, usable_cores()),
        (["study", "--devices", "2"], {"FOJAX_DEVICES": "5"}, 2),              # argv first
        (["study", "--devices", "2"], {"XLA_FLAGS": f"{FLAG}=7"}, None),       # the user's count wins
        (["study", "--devices", "2"], {"JAX_PLATFORMS": "cuda"}, None),        # not the CPU platform
        (["study", "--devices", "2"], {"JAX_PLATFORMS": "cpu"}, 2),
        (["design", "x.toml", "--devices", "2"], {}, None),                    # runs no study
        (["check", "study", "--devices", "2"], {}, None),                      # a config named study
        (["study", "--devices", "0"], {}, None),                               # bad: argparse says so
        (["study"], {"FOJAX_DEVICES": "two"}, None),                           # bad: check_devices says so
    ],
)
def test_flag_rules(argv, environ, expected):
    env = dict(environ, XLA_FLAGS=environ.get("XLA_FLAGS", "--xla_cpu_foo=1"))
    before = env["XLA_FLAGS"]
    assert configure_host_devices(argv, env, jax_started=False) == expected
    if expected is None:
        assert env["XLA_FLAGS"] == before
    else:
        assert env["XLA_FLAGS"] == f"{before} {FLAG}={expected}"  # the user's other flags kept


def test_nothing_is_changed_once_jax_started():
    env = {"XLA_FLAGS": ""}
    assert configure_host_devices(["study", "--devices", "2"], env, jax_started=True) is None
    assert env == {"XLA_FLAGS": ""}


@pytest.mark.parametrize(
    "environ, jax_started, jaxlib, added",
    [
        ({}, False, COMPILE_FLAG_JAXLIB[0], True),
        ({"XLA_FLAGS": f"{FLAG}=2"}, False, COMPILE_FLAG_JAXLIB[0], True),                 # others kept
        ({"XLA_FLAGS": "--xla_cpu_use_fusion_emitters=true"}, False, COMPILE_FLAG_JAXLIB[0], False),  # user's
        ({}, True, COMPILE_FLAG_JAXLIB[0], False),                                        # too late
        ({}, False, (0, 4), False),                                                       # not measured there
        ({}, False, (99, 0), False),
        ({"JAX_PLATFORMS": "cuda,cpu"}, False, COMPILE_FLAG_JAXLIB[0], False),            # not the CPU
        ({"JAX_PLATFORMS": "cpu"}, False, COMPILE_FLAG_JAXLIB[0], True),
    ],
)
def test_compile_flag_rules(environ, jax_started, jaxlib, added):
    env = dict(environ)
    before = env.get("XLA_FLAGS")
    assert configure_compiler(env, jax_started=jax_started, jaxlib=jaxlib) is added
    if added:
        assert env["XLA_FLAGS"] == f"{before or ''} {COMPILE_FLAG}".strip()
    else:
        assert env.get("XLA_FLAGS") == before


def test_the_program_compiles_with_the_flag_on_the_measured_jaxlib():
    # a child that starts as the `fojax` program does (_fojax_program.start, before fojax is
    # imported): the flag is in its XLA_FLAGS exactly on a measured jaxlib, and JAX starts with it
    env = _env()
    env["XLA_FLAGS"] = " ".join(f for f in env["XLA_FLAGS"].split() if "fusion_emitters" not in f)
    code = ("import sys; sys.argv = ['fojax']; import _fojax_program; _fojax_program.start(); "
            "import os, fojax, jax; "
            "print(os.environ.get('XLA_FLAGS', '')); print(jax.devices('cpu')[0].platform)")
    r = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    flags, platform = r.stdout.split("\n")[:2]
    assert (COMPILE_FLAG in flags.split()) is (_jaxlib_version() in COMPILE_FLAG_JAXLIB), flags
    assert platform == "cpu"


def test_devices_that_jax_does_not_have_are_refused(capsys, monkeypatch):
    """In a Python session JAX has started already: ``--devices`` must match its count."""
    monkeypatch.delenv("FOJAX_DEVICES", raising=False)
    assert main(["study", "--devices", "3", "--samples", "1"]) == 2
    err = capsys.readouterr().err
    assert "--devices asks for 3 JAX devices but this process has 4" in err and FLAG in err
    monkeypatch.setenv("FOJAX_DEVICES", "two")
    assert main(["study"]) == 2
    assert "FOJAX_DEVICES='two': expected a positive integer" in capsys.readouterr().err
