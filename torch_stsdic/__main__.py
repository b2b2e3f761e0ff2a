"""``python -m torch_stsdic``: the ``stsdic`` command line (see :mod:`torch_stsdic.cli`)."""

import sys

from torch_stsdic.allocator import keep_freed_memory
from torch_stsdic.cli import main

if __name__ == "__main__":
    keep_freed_memory()  # as the ``stsdic`` command does
    sys.exit(main())
