"""The ``fojax`` program's entry point (the console script of ``pyproject.toml``), kept outside
the fojax package so that it runs before fojax, JAX, SciPy and cvxpy are imported.

Importing fojax takes seconds. Before it starts, `main` installs the start-up signal handler
(`fojax.cli._signals.quiet_while_starting`: a SIGINT/SIGTERM ends the program with one line
and exit code 130/143) and the program's XLA flags (`fojax.cli._devices.configure_host_devices`
for ``fojax study --devices N``, `fojax.cli._devices.configure_compiler`), which must be set
before JAX starts; then it runs `fojax.cli.main`. The two modules use only the standard
library and are loaded from their files: importing them as ``fojax.cli._signals`` would import
the fojax package (and JAX) first. ``python -m _fojax_program ARGS`` is the same program.
A Python session that imports fojax is untouched.
"""

import importlib.util
import os
import sys


def _load(name: str):
    """``fojax/cli/<name>.py`` as a stand-alone module (``find_spec`` locates the package
    without importing it)."""
    package = importlib.util.find_spec("fojax")
    path = os.path.join(package.submodule_search_locations[0], "cli", f"{name}.py")
    spec = importlib.util.spec_from_file_location(f"_fojax_program_{name}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def start() -> None:
    """Everything the program does before fojax is imported (module docstring)."""
    _load("_signals").quiet_while_starting()
    devices = _load("_devices")
    devices.configure_host_devices()
    devices.configure_compiler()


def main() -> int:
    """Start the ``fojax`` program and run its command line (``sys.argv[1:]``)."""
    start()
    from fojax.cli import main as run

    return run()


if __name__ == "__main__":
    sys.exit(main())
