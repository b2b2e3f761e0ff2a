"""SIGINT and SIGTERM while a command runs: stop once, cleanly, with the signal's exit code.

:func:`stop_on_signals` makes the first SIGINT (Ctrl-C) or SIGTERM raise :class:`Interrupted`
in the main thread; the command's ``finally``/``except`` blocks then close the result file
(finished frames kept), and :func:`~torch_stsdic.cli.app.main` prints one line and returns
``128 + signal number`` (130 for SIGINT, 143 for SIGTERM), the shell's convention. Later
signals are ignored until the command has returned, so that the clean-up cannot itself be
interrupted half-way. The C++ kernels and torch's worker threads never see the signal:
Python runs its handlers in the main thread between two bytecodes, i.e. after a kernel
call has returned.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
from collections.abc import Iterator
from typing import Any

__all__ = ["Interrupted", "SIGNALS", "exit_code", "stop_on_signals", "signal_name",
           "checkpoint", "leave_if_interrupted"]

#: the signals that stop a command cleanly
SIGNALS: tuple[int, ...] = (signal.SIGINT, signal.SIGTERM)


def signal_name(signum: int) -> str:
    """'SIGINT', 'SIGTERM', ... for a signal number."""
    try:
        return signal.Signals(signum).name
    except ValueError:
        return f"signal {signum}"


def exit_code(signum: int) -> int:
    """The exit code of a command stopped by ``signum``: 128 + signum (130, 143)."""
    return 128 + int(signum)


class Interrupted(KeyboardInterrupt):
    """A command stopped by SIGINT or SIGTERM (a KeyboardInterrupt, so every clean-up that
    handles Ctrl-C handles it). ``signum``: the signal; ``detail``: what was kept."""

    def __init__(self, signum: int = signal.SIGINT, detail: str = "") -> None:
        super().__init__(signal_name(signum))
        self.signum = int(signum)
        self.detail = detail

    def with_detail(self, detail: str) -> Interrupted:
        """The same interruption, saying what was kept (e.g. the result file)."""
        return Interrupted(self.signum, detail)

    @property
    def exit_code(self) -> int:
        """128 + the signal number."""
        return exit_code(self.signum)

    def __str__(self) -> str:
        return f"interrupted by {signal_name(self.signum)}" + (
            f": {self.detail}" if self.detail else "")


@contextlib.contextmanager
def stop_on_signals() -> Iterator[None]:
    """Within the block, the first SIGINT/SIGTERM raises :class:`Interrupted`, later ones are
    ignored; the previous handlers come back at the end. Outside the main thread (signals
    cannot be caught there) the block runs unchanged."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    hit: list[int] = []

    def handler(signum: int, frame: object) -> None:  # noqa: ARG001
        if hit:  # already stopping: let the clean-up finish
            return
        hit.append(signum)
        # kept too: raised inside a finalizer (``__del__``, a weakref callback) the exception
        # is dropped by Python, and the run then stops at the next checkpoint()
        _PENDING.append(signum)
        raise Interrupted(signum)

    old_hook = sys.unraisablehook

    def unraisable(info: Any) -> None:  # the dropped Interrupted: no traceback printed
        if not isinstance(info.exc_value, Interrupted):
            old_hook(info)

    old = {s: signal.getsignal(s) for s in SIGNALS}
    for s in SIGNALS:
        signal.signal(s, handler)
    _PENDING.clear()
    sys.unraisablehook = unraisable
    try:
        yield
    finally:
        _PENDING.clear()
        sys.unraisablehook = old_hook
        for s, h in old.items():
            signal.signal(s, h if h is not None else signal.SIG_DFL)


#: the signal being handled, raised again at the next :func:`checkpoint` (where its first
#: raise was dropped inside a finalizer)
_PENDING: list[int] = []


def checkpoint() -> None:
    """Raise :class:`Interrupted` again for a signal whose first raise was dropped (it
    arrived inside a finalizer); called between the blocks of a run."""
    if _PENDING:
        raise Interrupted(_PENDING.pop())


def leave_if_interrupted(code: int) -> int:
    """For the process's entry points, once the command has returned: after an interrupted
    command (``code`` 130 or 143; its files are closed and its message printed) end the
    process at once with that code, without the interpreter's shutdown; any other code is
    returned for a normal exit.

    The shutdown stops each daemon thread that then takes the GIL with ``pthread_exit``; a
    thread inside a torch op (torch releases the GIL there: a frame reader that did not stop
    within its wait, a server's request) unwinds through a ``noexcept`` destructor and the
    process aborts ("terminate called without an active exception", exit 134 instead of
    130). And the shutdown costs ~0.6 s of CPU (the garbage collection of ~1,700 modules,
    torch's operator registry): tens of seconds on an oversubscribed CPU, seen as a hang."""
    if code not in {exit_code(s) for s in SIGNALS}:
        return code
    if "logging" in sys.modules:  # (its handlers flush at the shutdown skipped here)
        sys.modules["logging"].shutdown()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (AttributeError, OSError, ValueError):  # closed or replaced by None
            pass
    os._exit(code)
