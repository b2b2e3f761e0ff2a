"""``python -m torch_stsdic``: the ``stsdic`` command line (see :mod:`torch_stsdic.cli`)."""

import sys

from torch_stsdic.cli import main

if __name__ == "__main__":
    sys.exit(main())
