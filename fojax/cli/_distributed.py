"""``fojax study --distributed``: one study over the processes of a `jax.distributed` run.

Every process runs the same command on the same model file; JAX's own multi-process
runtime joins them (`jax.distributed.initialize`), and `run_study` / `tune` spread the
samples over the global mesh of every process's devices (`fojax.studies._sharding`).

Environment (JAX's names; on SLURM, and the other clusters JAX detects, all may be left
unset):

- ``JAX_COORDINATOR_ADDRESS``: ``host:port`` of process 0 (read by JAX itself);
- ``JAX_NUM_PROCESSES``, ``JAX_PROCESS_ID``: number of processes and this one's id;
- ``FOJAX_HEARTBEAT_TIMEOUT`` (s, default 100, JAX's): a process silent this long counts as
  dead and every other process stops with an error;
- ``FOJAX_INITIALIZATION_TIMEOUT`` (s, default 300): how long to wait for all processes.

Only process 0 writes the results folder. The others run the identical computation (the
collectives need every process) in a private temporary folder that is deleted at the end;
with ``--resume FOLDER`` process 0 reads FOLDER before anything is written and sends the
files a resume needs (config, options, designs, tuning checkpoints) to the others, which
continue from that copy: every process agrees on what is done, and FOLDER need only be on
process 0's host.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import sys
import tempfile

from .._errors import DistributedError, InputError


ENV_INT = {
    "JAX_NUM_PROCESSES": None,
    "JAX_PROCESS_ID": None,
    "FOJAX_HEARTBEAT_TIMEOUT": 100,
    "FOJAX_INITIALIZATION_TIMEOUT": 300,
}


def _env_int(name):
    raw = os.environ.get(name)
    if raw is None or raw == "":
        return ENV_INT[name]
    try:
        value = int(raw)
    except ValueError:
        value = -1
    if value < 0 or (name == "JAX_NUM_PROCESSES" and value < 1):
        raise InputError(f"environment variable {name}={raw!r}: expected a non-negative integer "
                         f"({'>= 1' if name == 'JAX_NUM_PROCESSES' else 'process ids start at 0'}).")
    return value


def initialize() -> None:
    """`jax.distributed.initialize` from the environment (module docstring); before any
    JAX computation of the process."""
    import jax

    n, pid = _env_int("JAX_NUM_PROCESSES"), _env_int("JAX_PROCESS_ID")
    if n is not None and pid is not None and pid >= n:
        raise InputError(f"JAX_PROCESS_ID={pid} must be smaller than JAX_NUM_PROCESSES={n}.")
    address = os.environ.get("JAX_COORDINATOR_ADDRESS") or None
    try:
        jax.distributed.initialize(
            coordinator_address=address, num_processes=n, process_id=pid,
            initialization_timeout=_env_int("FOJAX_INITIALIZATION_TIMEOUT"),
            heartbeat_timeout_seconds=_env_int("FOJAX_HEARTBEAT_TIMEOUT"),
        )
    except (RuntimeError, ValueError) as err:
        raise DistributedError(
            f"--distributed: jax.distributed.initialize failed ({str(err).splitlines()[0][:300]}). Set "
            "JAX_COORDINATOR_ADDRESS=host:port (process 0's host, a free port), JAX_NUM_PROCESSES and "
            "JAX_PROCESS_ID on every process (unneeded under SLURM), and start every process."
        ) from err


#: Files of a results folder that ``fojax study --resume`` never reads (the last stage
#: writes them again): not sent to the other processes.
_REGENERATED = ("metrics", "study", "study-samples")


def _snapshot(folder) -> bytes | None:
    """Process 0: the files of `folder` a resume reads (config, options, manifest, designs,
    tuning checkpoints: every top-level ``.toml``/``.json``/``.npz`` but the regenerated
    study outputs), as the bytes of an uncompressed zip; None if there is no such folder."""
    import io
    import pathlib
    import zipfile

    folder = pathlib.Path(folder)
    if not folder.is_dir():
        return None
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_STORED) as z:
        for p in sorted(folder.iterdir()):
            if (p.is_file() and not p.is_symlink() and p.suffix in (".toml", ".json", ".npz")
                    and not p.name.startswith(".") and p.stem not in _REGENERATED):
                z.writestr(p.name, p.read_bytes())
    return buf.getvalue()


@contextlib.contextmanager
def process_folders(out_dir, resume):
    """``(out_dir, resume, quiet)`` for this process: unchanged on process 0; on the others a
    temporary folder, removed at the end. With `resume`, process 0 reads the files of that
    folder a resume needs *before* it writes anything and sends them to every other process
    (`fojax.studies.broadcast_bytes`), which continue from that copy: every
    process sees the same designs and tuning checkpoints, and the folder need not be
    visible to the other hosts."""
    import io
    import zipfile

    import jax

    from ..studies import broadcast_bytes

    snapshot = None
    if resume is not None:  # every process takes part, before any can fail or write
        snapshot = broadcast_bytes(_snapshot(resume) if jax.process_index() == 0 else None,
                                   f"--resume {resume}: sending the folder to every process")
    if jax.process_index() == 0:
        yield out_dir, resume, None
        return
    tmp = tempfile.mkdtemp(prefix=f"fojax-process{jax.process_index()}-")
    try:
        if resume is not None:
            if not snapshot:  # process 0 stops with the same words
                raise InputError(f"--resume {resume}: no such results folder (on process 0's host: process 0 "
                                 "reads it for every process).")
            copy = os.path.join(tmp, os.path.basename(os.path.normpath(resume)))  # the folder's name
            os.mkdir(copy)
            with zipfile.ZipFile(io.BytesIO(snapshot)) as z:
                z.extractall(copy)
            resume = copy
        # --resume reuses its folder (no --out, as on process 0); a new study: its own folder
        yield (os.path.join(tmp, "out") if resume is None else None), resume, True
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def run(command) -> int:
    """Run ``command()`` (the study) after `initialize`. A `fojax.errors.DistributedError` (another
    process died) ends this process at once with its one-line reason (exit code 2),
    without JAX's shutdown barrier, which the dead process can never join."""
    import jax

    try:
        return command()
    except DistributedError as err:
        print(f"fojax: error (process {jax.process_index()}): {err}", file=sys.stderr, flush=True)
        sys.stdout.flush()
        os._exit(2)


def tuning_devices(exact: bool = True):
    """The devices `tune` spreads its samples over: every device of the run (all processes'
    in a distributed run; the host devices of ``fojax study --devices N``), or None with a
    single device. The iterates are the same bits either way (`fojax.studies._sharding`).
    A study that is not on the exact engine (`exact`: ``fojax.studies.exact_refusal`` is
    None; Takagi–Sugeno observers, time-varying δ(t)) tunes on one device of one process:
    `tune` refuses to differentiate the diffrax path over several devices (see its
    ``devices`` argument); over several processes it raises that error."""
    import jax

    if jax.process_count() > 1:
        return jax.devices()
    return jax.devices() if jax.device_count() > 1 and exact else None
