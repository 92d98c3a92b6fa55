"""Studies and tuning across processes: `jax.distributed` on the loopback address.

Oracle: the single-process, single-device run of the same public calls on the same samples
(`run_study` with one device, `tune` with ``devices=None``), computed in this process;
the multi-process results must equal it bit for bit (`np.array_equal`), because each
sample's arithmetic does not depend on which process or device computes it and the
reductions over samples run in one fixed order (`fojax.studies._sharding`). The
in-process tests compare several local devices with one device the same way.

The loopback runs start 2 or 3 worker processes (`tests/distributed_worker.py`, CPU
backend, gloo collectives, 1 or 2 forced host devices each) on free ports with bounded
timeouts, and kill them all at the end. The tuning checkpoint of a multi-process `tune`
is compared, file for file, with the one of the single-process `tune`; `fojax study
--distributed --resume` with `fojax study` run once, uninterrupted.
"""

import json
import os
import pathlib
import socket
import subprocess
import sys

import jax
import numpy as np
import pytest
from distributed_worker import studies, study_and_tuning
from helpers import child_xla_flags, json_differences as _differences

import fojax
from fojax import studies as S
from fojax.design import design_functional_observer, Disk
from fojax.studies import SimConfig


# bit-for-bit equality of different programs (the same results on 1 and several devices and processes): compiled as users get it
pytestmark = pytest.mark.production_codegen


HERE = pathlib.Path(__file__).parent
# s per loopback run: a worker costs ~12-20 s of CPU, but took 280 s on a 2-core machine at load 19
# (FOJAX_DISTRIBUTED_TEST_TIMEOUT: more on a busier machine)
TIMEOUT = int(os.environ.get("FOJAX_DISTRIBUTED_TEST_TIMEOUT", "600"))


@pytest.fixture(scope="module")
def design():
    ex = fojax.models.example_3_3_7()
    return design_functional_observer(ex.augmented, ex.L_aug, kind="generalized", region=Disk(-2.0, 1.0))


@pytest.fixture(scope="module")
def reference(design, tmp_path_factory):
    """The single-process, single-device result (the oracle): `run_study` on one device,
    `tune` with ``devices=None`` (one block on the default device, as before); and the
    folder of its tuning checkpoint."""
    folder = tmp_path_factory.mktemp("reference-checkpoint")
    return study_and_tuning(design, jax.devices()[:1], None, str(folder / "tune")), folder


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _launch(tmp_path, design, n, devices_each, kill=None, when=None):
    """Start `n` workers, wait (bounded), kill any left; returns (outputs, logs, return codes)."""
    path = tmp_path / "design.npz"
    if not path.exists():
        fojax.save_design(design, path)
    port = _free_port()
    env = dict(os.environ, XLA_FLAGS=child_xla_flags(devices_each),
               PYTHONPATH=os.pathsep.join([str(HERE), str(HERE.parent), os.environ.get("PYTHONPATH", "")]),
               JAX_PLATFORMS="cpu")
    procs, logs = [], []
    for pid in range(n):
        log = open(tmp_path / f"worker{pid}.log", "w")
        args = [sys.executable, str(HERE / "distributed_worker.py"), str(port), str(n), str(pid), str(path),
                str(tmp_path / f"out{pid}.npz")] + ([] if kill is None else [str(kill), when])
        procs.append(subprocess.Popen(args, env=env, stdout=log, stderr=subprocess.STDOUT))
        logs.append(log)
    codes = []
    try:
        for p in procs:
            try:
                codes.append(p.wait(timeout=TIMEOUT))
            except subprocess.TimeoutExpired:
                codes.append(None)
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
        for log in logs:
            log.close()
    texts = [(tmp_path / f"worker{pid}.log").read_text() for pid in range(n)]
    return codes, texts


def _assert_bit_identical(got, want):
    for k in want:
        if k in ("engine", "tv_engine", "num_devices", "tune_traces"):
            continue
        assert got[k].dtype == want[k].dtype and got[k].shape == want[k].shape, k
        assert np.array_equal(got[k], want[k], equal_nan=True), (k, np.max(np.abs(got[k] - want[k])))


def _assert_same_checkpoint(folder, want):
    """`folder` holds exactly one checkpoint pair (no temporary file), equal to the one in
    `want`: every array bit for bit, the JSON (step, history) equal."""
    assert sorted(p.name for p in folder.iterdir()) == ["tune.json", "tune.npz"], list(folder.iterdir())
    assert json.loads((folder / "tune.json").read_text()) == json.loads((want / "tune.json").read_text())
    with np.load(folder / "tune.npz") as got, np.load(want / "tune.npz") as ref:
        assert sorted(got.files) == sorted(ref.files)
        for k in ref.files:
            assert got[k].dtype == ref[k].dtype and np.array_equal(got[k], ref[k]), k


@pytest.mark.parametrize("n, devices_each, kill, when", [(2, 2, 1, "tune"), (3, 1, 2, "run_study")])
def test_processes_on_loopback_return_the_single_process_result_bit_for_bit(tmp_path, design, reference, n,
                                                                               devices_each, kill, when):
    # 2 processes x 2 devices, then process 1 is killed (SIGKILL) during a tuning (after step
    # 1); 3 processes x 1 device (7 evaluation samples in blocks of 2 dealt unevenly: 2 + 2 +
    # 2, then 1; 5 time-varying samples: 2 + 2 + 1), then process 2 is killed while the
    # others run a study
    reference, reference_checkpoint = reference
    codes, logs = _launch(tmp_path, design, n, devices_each, kill=kill, when=when)
    survivors = [pid for pid in range(n) if pid != kill]
    for pid in survivors:
        assert codes[pid] is not None, (pid, codes, logs[pid][-3000:])  # no hang
    for pid in range(n):  # every process received the whole result
        got = dict(np.load(tmp_path / f"out{pid}.npz"))
        assert int(got["process_count"]) == n and int(got["local_devices"]) == devices_each
        assert str(got["engine"]) == "exact-batch" and int(got["num_devices"]) == n * devices_each
        assert str(got["tv_engine"]) == "exponential-batch"
        assert int(got["tune_traces"]) == 1  # resuming (new parameters) did not recompile
        _assert_bit_identical(got, reference)
    # tune(checkpoint=...): process 0 wrote its path, the single-process checkpoint; the
    # others wrote nothing (and resumed from process 0's, sent to them)
    _assert_same_checkpoint(tmp_path / "out0.npz.ckpt", reference_checkpoint)
    for pid in range(1, n):
        assert not list((tmp_path / f"out{pid}.npz.ckpt").iterdir()), pid
    assert codes[kill] == -9  # SIGKILL
    for pid in survivors:  # a clear error on every other process, in bounded time
        err = tmp_path / f"out{pid}.npz.error"
        if err.exists():  # fojax's: a collective lost its peer
            text = err.read_text()
            assert f"{when} stopped on process {pid} of {n}" in text
            assert "another process of the distributed run failed or was killed" in text
            assert "--resume" in text
        else:  # JAX's, when the peer's death is noticed by the heartbeat first
            assert "Terminating process because the JAX distributed service detected fatal errors" in logs[pid]


@pytest.fixture(scope="module")
def loss_case(design):
    _, train = studies()
    return train, design.observer


def test_study_loss_and_gradient_on_several_devices_equal_one_device(loss_case):
    # regression: without the per-sample copies of the observer (_broadcast_rows), reverse
    # mode sums each device's samples and then psums the partial sums; on 3 devices the
    # gradient then differed from one device in the last bits (measured 1.4e-17)
    train, obs = loss_case
    import equinox as eqx

    def value_and_grad(devices):
        cfg = SimConfig(devices=devices)
        return eqx.filter_jit(eqx.filter_value_and_grad(lambda o: S.study_loss(train, o, cfg=cfg)))(obs)

    v1, g1 = value_and_grad(None)
    v3, g3 = value_and_grad(tuple(jax.devices()[:3]))  # 6 samples: 2 per device
    assert np.array_equal(np.asarray(v3), np.asarray(v1))
    for a, b in zip(jax.tree.leaves(eqx.filter(g3, eqx.is_inexact_array)),
                    jax.tree.leaves(eqx.filter(g1, eqx.is_inexact_array))):
        assert np.array_equal(np.asarray(a), np.asarray(b))


def test_devices_must_be_jax_devices(loss_case):
    train, obs = loss_case
    with pytest.raises(fojax.errors.InputError, match="devices must be a non-empty sequence of jax.Device"):
        S.study_loss(train, obs, cfg=SimConfig(devices=("cpu:0",)))


@pytest.mark.parametrize("env, message", [
    ({"JAX_NUM_PROCESSES": "two"}, "environment variable JAX_NUM_PROCESSES='two': expected a non-negative integer"),
    ({"JAX_NUM_PROCESSES": "2", "JAX_PROCESS_ID": "2"}, "JAX_PROCESS_ID=2 must be smaller than JAX_NUM_PROCESSES=2"),
    ({"FOJAX_HEARTBEAT_TIMEOUT": "-5"}, "FOJAX_HEARTBEAT_TIMEOUT='-5'"),
])
def test_study_distributed_refuses_bad_environment_before_joining(monkeypatch, capsys, env, message):
    # checked before jax.distributed.initialize (which this test process must never call)
    from fojax.cli import main

    for k, v in env.items():
        monkeypatch.setenv(k, v)
    assert main(["study", "--distributed", "--quiet"]) == 2
    assert message in capsys.readouterr().err


def _study_folder(out: pathlib.Path) -> pathlib.Path:
    (folder,) = [p for p in out.iterdir() if p.is_dir()]
    return folder


def _fojax_study(args, *, processes=None, timeout=TIMEOUT):
    """Run ``python -m _fojax_program study ARGS`` (the `fojax` program) in one process (``processes=None``) or with
    ``--distributed`` on that many local processes (one device each, the same command line,
    as on a cluster); returns the processes' (return code, output)."""
    env = dict(os.environ, JAX_PLATFORMS="cpu", XLA_FLAGS=child_xla_flags(1))
    cmd = [sys.executable, "-m", "_fojax_program", "study", *args]
    if processes is None:
        r = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=timeout)
        return [(r.returncode, r.stdout + r.stderr)]
    env.update(JAX_COORDINATOR_ADDRESS=f"127.0.0.1:{_free_port()}", JAX_NUM_PROCESSES=str(processes),
               # (every program goes into the run's persistent cache, tests/conftest.py: the
               # resumed run, on the same 2 processes, reads the first run's instead of compiling)
               FOJAX_INITIALIZATION_TIMEOUT="120", FOJAX_HEARTBEAT_TIMEOUT="60")
    procs = [subprocess.Popen([*cmd, "--distributed"], env=dict(env, JAX_PROCESS_ID=str(pid)),
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
             for pid in range(processes)]
    outs = []
    try:
        for p in procs:
            outs.append(p.communicate(timeout=timeout)[0])
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.communicate()
    return [(p.returncode, o) for p, o in zip(procs, outs)]


def test_fojax_study_distributed_resume_of_a_missing_folder_stops_every_process(tmp_path):
    # process 0 reads the folder for every process: none finds it, none hangs
    runs = _fojax_study(["--resume", str(tmp_path / "nowhere"), "--quiet"], processes=2, timeout=300)
    assert [c for c, _ in runs] == [2, 2], [o[-3000:] for _, o in runs]
    for _, text in runs:
        assert f"--resume {tmp_path / 'nowhere'}: no such results folder" in text


def test_fojax_study_distributed_resumed_writes_the_single_process_folder(tmp_path):
    """`fojax study --distributed` on 2 local processes, interrupted after its first tuning
    step, then `--distributed --resume` on 2 processes, against `fojax study` run once in
    one process: one results folder (process 0's), and every array of every .npz in it
    equal bit for bit (metrics, samples, designs, the tuning checkpoint)."""
    import threading

    args = ["--samples", "3", "--horizon", "1", "--quiet"]
    single = {}
    thread = threading.Thread(target=lambda: single.update(
        run=_fojax_study([*args, "--steps", "2", "--out", str(tmp_path / "single")])))
    thread.start()  # beside the distributed run (the 2 cores are shared anyway)
    first = _fojax_study([*args, "--steps", "1", "--out", str(tmp_path / "dist")], processes=2)
    thread.join()
    ((code, text),) = single["run"]
    assert code == 0, text[-3000:]
    assert [c for c, _ in first] == [0, 0], [o[-3000:] for _, o in first]
    # What a run with --steps 2 leaves when interrupted after its first tuning step: the
    # designs and the step-1 checkpoint (a --steps 1 run computes the same bits up to there:
    # each step does not depend on the total, and the held-out curve is evaluated at every
    # step for both, eval_every = max(1, steps // 10) = 1), and nothing written after it.
    a, b = _study_folder(tmp_path / "dist"), _study_folder(tmp_path / "single")
    options = json.loads((a / "study-options.json").read_text())
    (a / "study-options.json").write_text(json.dumps(dict(options, steps=2)))
    for p in a.iterdir():
        if p.name.endswith("-tuned.npz") or p.suffix == ".png" or p.stem in ("metrics", "study", "study-samples",
                                                                                "report"):
            p.unlink()
    assert json.loads((a / "tuning-FGDO.json").read_text())["step"] == 1
    resumed = _fojax_study(["--resume", str(a)], processes=2)  # not quiet: process 0 says what it does
    assert [c for c, _ in resumed] == [0, 0], [o[-3000:] for _, o in resumed]
    assert "steps 2..2 (resumed from the checkpoint at step 1)" in resumed[0][1], resumed[0][1][-3000:]
    assert [p.name for p in (tmp_path / "dist").iterdir()] == [a.name]  # nothing else written
    assert json.loads((a / "tuning-FGDO.json").read_text())["step"] == 2
    names = sorted(p.name for p in b.glob("*.npz"))
    assert names and names == sorted(p.name for p in a.glob("*.npz"))
    for name in names:
        with np.load(a / name, allow_pickle=False) as za, np.load(b / name, allow_pickle=False) as zb:
            assert sorted(za.files) == sorted(zb.files), name
            for k in zb.files:
                x, y = za[k], zb[k]
                if k == "__metadata__":  # the same record but for its creation time
                    x, y = ({kk: v for kk, v in json.loads(str(m)).items() if kk != "created"} for m in (x, y))
                    assert not _differences(x, y), (name, _differences(x, y))
                    continue
                assert x.dtype == y.dtype and np.array_equal(x, y, equal_nan=x.dtype.kind in "fc"), (name, k)
