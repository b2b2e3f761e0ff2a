"""The ``stsdic`` parser and :func:`main`: parse, run one sub-command, turn errors into exit codes.

Each sub-command is a module (``run``, ``export``, ``plot``, ``synth``, ``demo``) with
``NAME``, ``HELP``, ``DESCRIPTION``, ``EPILOG``, ``add_arguments(parser)`` and
``execute(args) -> int``. :func:`main` turns every error into one line on stderr
(``stsdic: error: ...``) and an exit code: 2 for usage errors (a bad option value, an option
that does not fit the images), 1 for everything else (missing or unreadable files, failed
runs), 128 + the signal number when SIGINT (Ctrl-C, 130) or SIGTERM (143) stops it
(:mod:`.signals`: one line saying what was kept). ``--debug`` shows the Python traceback too.
"""

from __future__ import annotations

import argparse
import sys
import textwrap
import traceback
from collections.abc import Sequence
from typing import Any

from torch_stsdic.cli import demo, export, options, plot, run, stereo, synth, view
from torch_stsdic.cli.demo import DEMO_TIME
from torch_stsdic.cli.errors import (
    PROG,
    CommandError,
    UsageError,
    one_line,
    print_error,
    warnings_on_stderr,
)
from torch_stsdic.cli.signals import Interrupted, stop_on_signals

#: the sub-command modules, in the order of ``stsdic --help``
COMMANDS = (run, stereo, export, plot, view, synth, demo)

DESCRIPTION = """\
STS-DIC: short-time-series digital image correlation (Wang & Ma) in PyTorch.

Each solve matches a subset of the reference image against 2m+1 consecutive frames at
once, with a displacement that is linear in time (u + ut*dt, v + vt*dt): the frames'
noise is averaged, and the velocity comes out directly. m = 0 is classical subset DIC.
"""

EPILOG = f"""\
examples:
  stsdic demo                                   # {DEMO_TIME}; plots in ./stsdic-demo
  stsdic synth --out movie --motion strain      # synthetic test movie + ground truth
  stsdic run movie/movie.tif --m 2 --step 10 --out result.h5
  stsdic run movie/movie.tif --scale 0.02 --unit mm --out result_mm.h5   # calibrated
  stsdic export result.h5 --out csv/            # or --format vtk (ParaView) / mat (MATLAB)
  stsdic plot result.h5 --frame last --out plots/
  stsdic view result.h5                         # in the browser: scrub, click points

Run 'stsdic COMMAND --help' for the options of a command. Coordinates are pixels with
x = column (right), y = row (down), 0-based; times are frame numbers unless --timestamps.
A run with --scale and --unit keeps pixels in its file; export and plot convert to the unit.
"""

#: errors whose message alone says what went wrong (others get their type and a hint)
KNOWN_ERRORS = (CommandError, ValueError, TypeError, OSError, KeyError, IndexError)


class _Parser(argparse.ArgumentParser):
    """ArgumentParser whose errors are one line (raised as UsageError, printed by main)."""

    def error(self, message: str) -> Any:  # type: ignore[override]
        raise UsageError(f"{message} (see '{self.prog} --help')")


class _Formatter(argparse.RawDescriptionHelpFormatter):
    """Keeps the descriptions' line breaks; lists the sub-commands without a 'COMMAND' line."""

    def __init__(self, prog: str) -> None:
        super().__init__(prog, max_help_position=32, width=100)

    def _format_action(self, action: argparse.Action) -> str:
        text = super()._format_action(action)
        first, _, rest = text.partition("\n")
        if action.nargs == argparse.PARSER and first.strip() == action.metavar:
            return textwrap.indent(textwrap.dedent(rest), "  ")  # one command a line
        return text


def _version() -> str:
    try:
        from importlib.metadata import version

        return version("torch_stsdic")
    except Exception:
        return "unknown"


def build_parser() -> argparse.ArgumentParser:
    """The ``stsdic`` argument parser (all sub-commands)."""
    parser = _Parser(prog=PROG, description=DESCRIPTION, epilog=EPILOG, formatter_class=_Formatter)
    parser.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    parser.add_argument(
        "--debug", action="store_true", default=False, help="show the Python traceback of an error"
    )
    sub = parser.add_subparsers(
        title="commands", dest="command", metavar="COMMAND", parser_class=_Parser
    )
    for command in COMMANDS:
        p = sub.add_parser(
            command.NAME,
            help=command.HELP,
            description=command.DESCRIPTION,
            epilog=command.EPILOG,
            formatter_class=_Formatter,
        )
        command.add_arguments(p)
        options.add_debug(p)
        p.set_defaults(func=command.execute)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``stsdic`` with ``argv`` (default ``sys.argv[1:]``); return the exit code.

    SIGINT/SIGTERM stop the command cleanly (:func:`~.signals.stop_on_signals`)."""
    with stop_on_signals():
        try:
            return _main(list(sys.argv[1:] if argv is None else argv))
        except KeyboardInterrupt as exc:  # stopped while parsing or reporting
            return _report(exc)


def _main(argv: list[str]) -> int:
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as exc:  # --help, --version
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 2)
    except UsageError as exc:
        print_error(one_line(exc))
        return 2
    if args.command is None:
        names = ", ".join(c.NAME for c in COMMANDS[:-1]) + f" or {COMMANDS[-1].NAME}"
        print_error(f"a command is required: {names} (see 'stsdic --help')")
        return 2
    debug = "--debug" in argv or bool(getattr(args, "debug", False))
    threads = None
    try:
        if getattr(args, "threads", None):
            import torch

            threads = torch.get_num_threads()
            torch.set_num_threads(args.threads)
        with warnings_on_stderr():
            return int(args.func(args) or 0)
    except (KeyboardInterrupt, Exception) as exc:
        if debug:
            traceback.print_exc()
        return _report(exc)
    finally:
        if threads is not None:  # main() may be called in-process: leave torch as it was
            import torch

            torch.set_num_threads(threads)


def _report(exc: BaseException) -> int:
    """Print ``exc`` as one error line; its exit code."""
    if isinstance(exc, UsageError):
        print_error(one_line(exc))
        return 2
    if isinstance(exc, KeyboardInterrupt):
        stop = exc if isinstance(exc, Interrupted) else Interrupted()
        print(f"{PROG}: {stop}", file=sys.stderr, flush=True)
        return stop.exit_code
    msg = one_line(exc)
    if not isinstance(exc, KNOWN_ERRORS):
        msg = f"{type(exc).__name__}: {msg} (run with --debug for the traceback)"
    print_error(msg)
    return 1
