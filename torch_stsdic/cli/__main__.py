"""``python -m torch_stsdic.cli``: the ``stsdic`` command line."""

import sys

from torch_stsdic.cli import main
from torch_stsdic.cli.signals import leave_if_interrupted

if __name__ == "__main__":
    sys.exit(leave_if_interrupted(main()))
