"""Imported first by ``fojax/__init__.py``: when this process is the ``fojax`` program, a
SIGINT/SIGTERM while Python imports fojax and its dependencies ends it with one line
(`fojax.cli._signals.quiet_while_starting`); a Python session importing fojax is untouched."""

from ._signals import quiet_while_starting


quiet_while_starting()
