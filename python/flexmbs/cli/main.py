"""The command line: ``flexmbs simulate``, ``flexmbs demo``, and subcommands added by other modules.

Usage::

    flexmbs --version
    flexmbs simulate CASE [--design P1,P2,...] [--t-end T] [--h H] [--rho-inf R]
                          [--set KEY=VALUE ...] [--out result.npz] [--plot FILE.png] [--json]
    flexmbs animate CASE [--design P1,P2,...] [--set KEY=VALUE ...] --out motion.gif|.mp4|.pvd
                         [--frames N] [--fps F] [--magnify S] [--color-by deviation|stress|none]
    flexmbs modes CASE [--design P1,P2,...] [--count N] [--at T[,T...]] [--plot FILE.png]
                       [--animate FILE.gif|.mp4 [--mode K]] [--json]
    flexmbs demo [--out DIR] [--workers N]
    flexmbs reproduce [--study FILE] [--table N ...|--all] [--out DIR] [--workers N | --dask ADDRESS] [--quick]

CASE is the name of a shipped case (``flexmbs.model.casefile.available_cases()``: the files of cases/)
or a path to a TOML case file (docs/case-format.md). Errors in the input or in the simulation, and files that cannot be
written, print one line on stderr and exit with status 2 (``--debug`` before or after the
subcommand, or the environment variable ``FLEXMBS_DEBUG=1``, also prints the traceback). Output
paths (--out, --plot, --history) are checked before the run: the folder must be writable, a
figure's extension must be a format matplotlib writes. Files are written to a temporary name and
renamed when complete. Ctrl-C prints one line (what is kept, how to resume) and exits with 130
within a step of the simulation; SIGTERM does the same (the same cleanup, nothing half-written
left) and exits with 143.

Adding a subcommand
-------------------
Each subcommand is registered by a function ``register(subparsers)`` that adds its parser and
sets its handler with ``set_defaults(func=handler)``; a handler takes the parsed arguments and
returns an exit status. Import the module in flexmbs.cli.main and list the function in `COMMANDS`. `add_case_arguments` and `problem_from_args` give every subcommand the same
CASE, --set, --t-end, --h and --rho-inf options; `design_from_text` reads a --design value.
"""
from __future__ import annotations

import argparse
import contextlib
import os
import re
import signal
import sys
import threading
import traceback
import warnings


from flexmbs.cli import animate
from flexmbs.cli import check
from flexmbs.cli import evaluate
from flexmbs.cli import modes
from flexmbs.cli import optimize
from flexmbs.cli import reproduce
from flexmbs.cli import simulate
from flexmbs.cli.common import printable
from flexmbs.errors import FlexmbsError, Interrupted
from flexmbs.version import __version__

__all__ = ["main", "build_parser", "COMMANDS"]

#: Subcommand registration functions, in the order of the help text.
COMMANDS = [simulate.register_simulate, reproduce.register_demo, evaluate.register, check.register, modes.register, animate.register, optimize.register, reproduce.register]


# ----------------------------------------------------------------------------- main
class _UsageError(Exception):
    """A command-line usage error, raised by _Parser.error instead of exiting at once (so
    that `main` can add a hint that needs the command line)."""

    def __init__(self, parser, message):
        super().__init__(message)
        self.parser = parser
        self.message = message


class _Parser(argparse.ArgumentParser):
    def error(self, message):
        raise _UsageError(self, message)


#: A value that argparse takes for an option: "-40,30" or "-4e1" (a plain "-40" is a number).
_DASH_VALUE = re.compile(r"^-[\d.]")


def _usage_hint(message, argv):
    """For "argument --design: expected one argument" when the next word is a negative value,
    the form that works: --design=-40,30,..."""
    m = re.match(r"argument ([-\w/]+)(?:/[-\w]+)*: expected one argument", message)
    if not m:
        return ""
    names = m.group(1).split("/")
    for k, word in enumerate(argv[:-1]):
        if word in names and _DASH_VALUE.match(argv[k + 1]):
            return (f"; a value that starts with '-' must be attached with '=': write "
                    f"{word}={argv[k + 1]}")
    return ""


def build_parser():
    """The argument parser with every registered subcommand."""
    parser = _Parser(
        prog="flexmbs",
        description="Planar flexible multibody simulation and structural optimization of "
                    "mechanism components (shipped cases: cases/*.toml, format: "
                    "docs/case-format.md).")
    parser.add_argument("--debug", action="store_true",
                        help="print the traceback of an error (also: FLEXMBS_DEBUG=1); "
                             "accepted after the subcommand too")
    parser.add_argument("--version", action="version", version=f"flexmbs {__version__}",
                        help="print the version of flexmbs and exit")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for register in COMMANDS:
        register(sub)
    return parser


def _one_line(exc):
    text = str(exc)
    if isinstance(exc, OSError) and exc.filename is not None and exc.strerror:
        text = f"{exc.strerror}: {exc.filename!r}"
    return printable(" ".join(text.split()))


def _show_warning(message, category, filename, lineno, file=None, line=None):
    """Warnings on the command line: one line each, without the source line."""
    print(f"flexmbs: {category.__name__}: {printable(' '.join(str(message).split()))}",
          file=file or sys.stderr)


@contextlib.contextmanager
def _sigterm_interrupts():
    """SIGTERM raises flexmbs.errors.Interrupted (a KeyboardInterrupt) in the main thread, as
    Ctrl-C raises KeyboardInterrupt, so that both take the same way out: the compiled run stops
    at its next step, temporary files are removed, finished results are kept. Yields the list
    of the SIGTERMs received. Only where SIGTERM has its default action (a handler of the
    program that calls `main` is kept), and restored afterwards."""
    received = []
    if threading.current_thread() is not threading.main_thread() \
            or signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL:
        yield received
        return

    def handler(signum, frame):
        received.append(signum)
        raise Interrupted("terminated (SIGTERM)", signal=signum)

    old = signal.signal(signal.SIGTERM, handler)
    try:
        yield received
    finally:
        signal.signal(signal.SIGTERM, old)


def main(argv=None):
    """Entry point of the ``flexmbs`` command; returns the exit status."""
    argv = list(sys.argv[1:] if argv is None else argv)
    debug = os.environ.get("FLEXMBS_DEBUG", "").strip() not in ("", "0")
    if "--debug" in argv:           # anywhere: before or after the subcommand
        debug = True
        argv = [a for a in argv if a != "--debug"]
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except _UsageError as exc:
        # one line, as every other error (the usage is in `--help`)
        message = printable(" ".join(f"{exc.message}{_usage_hint(exc.message, argv)}".split()))
        print(f"{exc.parser.prog}: error: {message} (see '{exc.parser.prog} --help')",
              file=sys.stderr)
        return 2
    if getattr(args, "func", None) is None:
        parser.print_help(sys.stderr)
        return 2
    with warnings.catch_warnings(), _sigterm_interrupts() as terminated:
        if not debug:
            warnings.showwarning = _show_warning
        try:
            code = int(args.func(args) or 0)
        except (FlexmbsError, OSError, MemoryError) as exc:
            if debug:
                traceback.print_exc()
            kind = type(exc).__name__
            print(f"flexmbs {args.command}: {kind}: {_one_line(exc)}", file=sys.stderr)
            return 2
        except KeyboardInterrupt:
            if debug:
                traceback.print_exc()
            what = "terminated (SIGTERM)" if terminated else "interrupted"
            print(f"flexmbs {args.command}: {what}", file=sys.stderr)
            code = 130
        # the subcommands' own Ctrl-C handling (optimize, reproduce) returns 130 too
        return 128 + signal.SIGTERM if terminated and code == 130 else code
