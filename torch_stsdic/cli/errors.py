"""How errors and warnings reach the user: one ``stsdic: error: ...`` line, an exit code.

:class:`UsageError` (exit code 2) is a bad command line: an option value, or an option that
does not fit the input. :class:`CommandError` (exit code 1) is a command that cannot be
carried out: missing or unreadable files, data that do not fit.
"""

from __future__ import annotations

import contextlib
import sys
import warnings
from collections.abc import Iterator

PROG = "stsdic"


class UsageError(Exception):
    """A bad command line (option value, option that does not fit the input): exit code 2."""


class CommandError(Exception):
    """A command that cannot be carried out (files, data): exit code 1."""


def one_line(exc: BaseException) -> str:
    """The exception's message on one line (KeyError without its quotes, OSError as
    'PATH: reason')."""
    if isinstance(exc, KeyError) and len(exc.args) == 1 and isinstance(exc.args[0], str):
        msg = exc.args[0]
    elif isinstance(exc, OSError) and exc.strerror:  # without '[Errno N]', the path first
        msg = f"{exc.filename}: {exc.strerror}" if exc.filename else exc.strerror
    else:
        msg = str(exc)
    msg = " ".join(part.strip() for part in msg.splitlines() if part.strip())
    return msg or type(exc).__name__


def print_error(msg: str) -> None:
    """Write ``stsdic: error: msg`` to stderr."""
    print(f"{PROG}: error: {msg}", file=sys.stderr, flush=True)


@contextlib.contextmanager
def warnings_on_stderr() -> Iterator[None]:
    """Show Python warnings as single ``stsdic: warning: ...`` lines."""

    def show(message, category, filename, lineno, file=None, line=None):  # noqa: ARG001
        text = " ".join(str(message).split())
        print(f"{PROG}: warning: {text}", file=sys.stderr, flush=True)

    with warnings.catch_warnings():
        warnings.simplefilter("default")
        warnings.showwarning = show
        yield
