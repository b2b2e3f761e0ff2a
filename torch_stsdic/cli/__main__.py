"""``python -m torch_stsdic.cli``: the ``stsdic`` command line."""

import sys

from torch_stsdic.cli import main

if __name__ == "__main__":
    sys.exit(main())
