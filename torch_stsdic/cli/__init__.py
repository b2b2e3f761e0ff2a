"""The ``stsdic`` command line: ``run``, ``export``, ``plot``, ``synth`` and ``demo``.

One module per sub-command, the options they share in :mod:`.options`, the parser and
:func:`main` in :mod:`.app`, error reporting in :mod:`.errors`. Heavy modules (the solver,
matplotlib) are imported inside the commands.
"""

from torch_stsdic.cli.app import build_parser, main
from torch_stsdic.cli.errors import CommandError, UsageError

__all__ = ["main", "build_parser", "UsageError", "CommandError"]
