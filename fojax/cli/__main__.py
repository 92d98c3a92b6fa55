"""``python -m fojax.cli ARGS``: the ``fojax`` command, run once fojax is imported. The console
script ``fojax`` (``python -m _fojax_program``) also sets its signal handler and XLA flags first."""

import sys

from ._main import main


sys.exit(main())
