"""Imported first by ``fojax/__init__.py``: when this process is the ``fojax`` program, a
SIGINT/SIGTERM while Python imports fojax and its dependencies ends it with one line
(`fojax.cli._signals.quiet_while_starting`), ``fojax study --devices N`` gets its JAX
host devices (`fojax.cli._devices.configure_host_devices`, before JAX is imported), and
XLA:CPU compiles without its fusion emitters (`fojax.cli._devices.configure_compiler`); a
Python session importing fojax is untouched."""

from ._signals import _is_program, quiet_while_starting


quiet_while_starting()
if _is_program():
    from ._devices import configure_compiler, configure_host_devices

    configure_host_devices()
    configure_compiler()
