"""The ``stsdic`` console command: signal handling in place before the heavy imports.

Importing torch takes seconds; a Ctrl-C (or SIGTERM) in that time would otherwise end in a
Python traceback. This module (outside the package, so that nothing heavy is imported with
it) makes such a signal a one-line message and the shell's exit code (128 + signal number),
then runs :func:`torch_stsdic.cli.main`, which handles signals during the command itself,
and ignores signals while the interpreter shuts down.
"""

from __future__ import annotations

import signal
import sys


def _stop(signum: int, frame: object) -> None:  # noqa: ARG001
    raise KeyboardInterrupt(signum)


def main() -> int:
    """Run ``stsdic`` with ``sys.argv``; the exit code."""
    for s in (signal.SIGINT, signal.SIGTERM):
        signal.signal(s, _stop)
    try:
        from torch_stsdic.cli import main as cli_main

        code = cli_main()
    except KeyboardInterrupt as exc:  # before or after the command (it handles its own)
        num = exc.args[0] if exc.args and isinstance(exc.args[0], int) else signal.SIGINT
        name = signal.Signals(num).name
        print(f"stsdic: interrupted by {name} (nothing was written)", file=sys.stderr,
              flush=True)
        code = 128 + int(num)
    for s in (signal.SIGINT, signal.SIGTERM):  # the process is ending: nothing to interrupt
        signal.signal(s, signal.SIG_IGN)
    return code


if __name__ == "__main__":
    sys.exit(main())
