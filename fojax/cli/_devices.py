"""JAX host devices for ``fojax study``: ``--devices N`` / ``FOJAX_DEVICES``.

XLA exposes a single CPU device unless ``--xla_force_host_platform_device_count=N`` is in
``XLA_FLAGS`` when JAX starts; fojax shards its sample batches over every device
(`fojax.studies.run_study`; `fojax.tune` with ``devices=``), and the results are the same
bits on any number of devices (`fojax.studies._sharding`, ``tests/test_cli_devices.py``).
When the process is the ``fojax`` program running ``study``, `configure_host_devices`
(called by the program's entry point ``_fojax_program.py``, before JAX is imported) adds that
flag with ``N`` from ``--devices N`` on the command line, else the environment variable
``FOJAX_DEVICES``; ``auto`` is one device per core this process may use
(``os.sched_getaffinity``).

**Default: one device** (nothing set). Sharding compiles the tuning step and the
held-out evaluation for several devices, which takes longer, and the default study's
batches (128 training samples, 64 study samples) are too small for the parallel steps to
pay that back; larger studies may gain from ``--devices auto``
(``benchmarks/cli_study.py`` measures both).

Nothing is changed when ``XLA_FLAGS`` already sets a device count (the user's choice
wins), when ``JAX_PLATFORMS`` names another platform than ``cpu`` first, for the other
commands, and when JAX is already imported (a Python session calling `fojax.cli.main`:
then ``--devices`` must match the devices JAX has, `check_devices`).

**Compilation** (`configure_compiler`, every command of the ``fojax`` program). The
program's runs are dominated by XLA:CPU compiling fojax's programs once each; without
XLA's CPU fusion emitters (``--xla_cpu_use_fusion_emitters=false``, the older loop emitter)
they compile faster, with the same results bit for bit, and some programs run slower (the
differentiable study loss on thousands of samples). So the flag pays where compiling
dominates, as in the default study, and costs time per step in long tuning runs on large
batches: set ``XLA_FLAGS=--xla_cpu_use_fusion_emitters=true`` for those.

An XLA flag that a jaxlib does not know aborts the process, so the flag is added only for
the jaxlib versions it was checked on (`COMPILE_FLAG_JAXLIB`; others run with XLA's
defaults), and never when ``XLA_FLAGS`` mentions it (the user's choice wins), when
``JAX_PLATFORMS`` names another platform first, or once JAX is imported. A Python session
importing fojax is untouched (a library does not change how XLA compiles the user's other
programs).
"""

from __future__ import annotations

import os
import sys


FLAG = "--xla_force_host_platform_device_count"
ENV = "FOJAX_DEVICES"
#: commands that run studies or tuning (the others run nothing batched)
COMMANDS = ("study",)


#: What `configure_compiler` adds to ``XLA_FLAGS`` (module docstring).
COMPILE_FLAG = "--xla_cpu_use_fusion_emitters=false"
#: ``(major, minor)`` versions of jaxlib on which `COMPILE_FLAG` is known.
COMPILE_FLAG_JAXLIB = ((0, 10),)


def usable_cores() -> int:
    """The cores this process may run on."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return max(1, os.cpu_count() or 1)


def _positive_int(raw) -> int | None:
    """A device count: a positive integer, or ``auto`` (one per usable core); None if bad."""
    if str(raw).strip().lower() == "auto":
        return usable_cores()
    try:
        value = int(str(raw).strip())
    except ValueError:
        return None
    return value if value >= 1 else None


def _command_and_devices(argv: list[str]) -> tuple[str | None, str | None]:
    """The command (first positional argument) and the raw ``--devices`` value of `argv`."""
    command, devices = None, None
    for i, a in enumerate(argv):
        if a == "--devices" and i + 1 < len(argv):
            devices = argv[i + 1]
        elif a.startswith("--devices="):
            devices = a.split("=", 1)[1]
        elif command is None and not a.startswith("-") and not (i > 0 and argv[i - 1] == "--devices"):
            command = a
    return command, devices


def requested_devices(argv: list[str], environ=os.environ) -> int | None:
    """The device count asked for by ``--devices`` or ``FOJAX_DEVICES`` (None: not asked,
    or not a positive integer: `fojax.cli.main` reports a bad ``--devices``; a bad
    ``FOJAX_DEVICES`` is reported by `check_devices`)."""
    _, raw = _command_and_devices(argv)
    if raw is None:
        raw = environ.get(ENV) or None
    return None if raw is None else _positive_int(raw)


def configure_host_devices(argv: list[str] | None = None, environ=None, jax_started: bool | None = None
                           ) -> int | None:
    """Add ``--xla_force_host_platform_device_count=N`` to ``environ["XLA_FLAGS"]`` for
    ``fojax study`` (module docstring); returns ``N``, or None when nothing was changed.
    Must run before JAX is imported (`jax_started`, default: whether it is)."""
    argv = sys.argv[1:] if argv is None else argv
    environ = os.environ if environ is None else environ
    jax_started = "jax" in sys.modules if jax_started is None else jax_started
    command, _ = _command_and_devices(argv)
    if command not in COMMANDS or jax_started:
        return None
    if FLAG.lstrip("-") in environ.get("XLA_FLAGS", ""):
        return None
    if not _cpu_platform(environ):
        return None
    n = requested_devices(argv, environ)
    if n is None:  # not asked (the default: one device), or a bad value (reported by the CLI)
        return None
    environ["XLA_FLAGS"] = (environ.get("XLA_FLAGS", "") + f" {FLAG}={n}").strip()
    return n


def _cpu_platform(environ) -> bool:
    """Whether JAX starts on the CPU (``JAX_PLATFORMS`` unset, or naming ``cpu`` first)."""
    platforms = (environ.get("JAX_PLATFORMS") or "").strip()
    return not platforms or platforms.split(",")[0].strip().lower() == "cpu"


def _jaxlib_version() -> tuple[int, int] | None:
    """``(major, minor)`` of the installed jaxlib (from its metadata: JAX is not imported)."""
    from importlib import metadata

    try:
        major, minor = metadata.version("jaxlib").split(".")[:2]
        return int(major), int(minor)
    except (metadata.PackageNotFoundError, ValueError):
        return None


def configure_compiler(environ=None, jax_started: bool | None = None, jaxlib=None) -> bool:
    """Add `COMPILE_FLAG` to ``environ["XLA_FLAGS"]`` (module docstring, **Compilation**);
    returns whether it did. Must run before JAX is imported (`jax_started`, default: whether
    it is); `jaxlib` (``(major, minor)``, default: the installed one) for tests."""
    environ = os.environ if environ is None else environ
    jax_started = "jax" in sys.modules if jax_started is None else jax_started
    jaxlib = _jaxlib_version() if jaxlib is None else tuple(jaxlib)
    name = COMPILE_FLAG.lstrip("-").split("=")[0]
    if jax_started or name in environ.get("XLA_FLAGS", "") or not _cpu_platform(environ):
        return False
    if jaxlib not in COMPILE_FLAG_JAXLIB:
        return False
    environ["XLA_FLAGS"] = (environ.get("XLA_FLAGS", "") + f" {COMPILE_FLAG}").strip()
    return True


def check_devices(requested: int | None) -> int:
    """The number of JAX devices this ``fojax study`` uses; `requested` (``--devices``, or
    ``FOJAX_DEVICES`` when it is None) must equal it when given.

    **Raises:** `fojax.errors.InputError` when ``FOJAX_DEVICES`` is not a positive integer, or when
    the count asked for differs from JAX's (JAX was started before fojax could set it:
    a Python session, or ``XLA_FLAGS`` setting another count).
    """
    import jax

    from .._errors import InputError

    where = "--devices"
    if requested is None and os.environ.get(ENV):
        where = f"{ENV}={os.environ[ENV]!r}"
        requested = _positive_int(os.environ[ENV])
        if requested is None:
            raise InputError(f"{where}: expected a positive integer (the number of JAX CPU devices) or 'auto' "
                             "(one per core).")
    have = jax.local_device_count()
    if requested is not None and requested != have:
        raise InputError(
            f"{where} asks for {requested} JAX devices but this process has {have}: the count is fixed "
            f"when JAX starts. Run the `fojax` program (it sets {FLAG} before JAX starts), or set "
            f"XLA_FLAGS={FLAG}={requested} before importing JAX (XLA_FLAGS now: "
            f"{os.environ.get('XLA_FLAGS', '')!r})."
        )
    return have
