"""The ``fojax`` command line (``demo``, ``check``, ``design``, ``study``, ``examples``): orchestration
and printing only. The program starts in ``_fojax_program.py``, outside this package."""

from ._main import main as main
