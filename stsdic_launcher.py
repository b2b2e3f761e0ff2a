"""The ``stsdic`` console command: signal handling in place before the heavy imports.

Importing torch takes seconds; a Ctrl-C (or SIGTERM) in that time would otherwise end in a
Python traceback. This module (outside the package, so that nothing heavy is imported with
it) makes such a signal a one-line message and the shell's exit code (128 + signal number),
then runs :func:`torch_stsdic.cli.main`, which handles signals during the command itself,
and ignores signals while the interpreter shuts down. An interrupted command's process ends
without that shutdown (:func:`torch_stsdic.cli.signals.leave_if_interrupted`).
"""

from __future__ import annotations

import signal
import sys


def _stop(signum: int, frame: object) -> None:  # noqa: ARG001
    raise KeyboardInterrupt(signum)


def _ignore() -> None:
    """The command is over: nothing is left to interrupt while the interpreter exits."""
    for s in (signal.SIGINT, signal.SIGTERM):
        signal.signal(s, signal.SIG_IGN)


def main() -> int:
    """Run ``stsdic`` with ``sys.argv``; the exit code."""
    for s in (signal.SIGINT, signal.SIGTERM):
        signal.signal(s, _stop)
    started = False
    try:
        from torch_stsdic.allocator import keep_freed_memory
        from torch_stsdic.cli import main as cli_main

        keep_freed_memory()  # the command owns the process: freed memory kept for reuse
        started = True
        code = cli_main()  # handles its own signals while the command runs
        _ignore()
        from torch_stsdic.cli.signals import leave_if_interrupted

        leave_if_interrupted(code)  # interrupted: exits here, without the shutdown
    except KeyboardInterrupt as exc:  # before the command started, or just after it ended
        _ignore()
        num = exc.args[0] if exc.args and isinstance(exc.args[0], int) else signal.SIGINT
        when = "" if started else " (nothing was written)"
        print(f"stsdic: interrupted by {signal.Signals(num).name}{when}", file=sys.stderr,
              flush=True)
        code = 128 + int(num)
    return code


if __name__ == "__main__":
    sys.exit(main())
