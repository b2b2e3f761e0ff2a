"""``python -m torch_stsdic``: the ``stsdic`` command line (see :mod:`torch_stsdic.cli`)."""

import sys

from torch_stsdic.allocator import keep_freed_memory
from torch_stsdic.cli import main
from torch_stsdic.cli.signals import leave_if_interrupted

if __name__ == "__main__":
    keep_freed_memory()  # as the ``stsdic`` command does
    sys.exit(leave_if_interrupted(main()))
