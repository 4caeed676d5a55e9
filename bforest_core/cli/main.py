"""The ``bforest`` command.

Every error a user can cause prints one line ``error: ...`` and exits with code 2; ``--debug``
shows the traceback instead. The subcommands live in one module per group: ``runs`` (demo, fit,
clones, report, compare, profile, calibrate), ``amortised`` (train, posterior), ``trees`` (info,
simulate, distance), ``export``,
``data`` (the sample trees), ``plugins_config`` (plugins, config).
"""

from __future__ import annotations

import argparse
import errno
import os
import signal
import sys
import warnings
from concurrent.futures import BrokenExecutor

from ..pipeline.interrupts import user_stops
from ..pipeline.progress import end_open_bars
from . import amortised, data, export, init, plugins_config, runs, stand, trees
from .common import EXIT_USAGE, Parser, UsageError

#: the warnings this command has printed: a file read twice (the clones, then the report) warns once
_SHOWN: set[str] = set()


def _warning_line(message, category, filename, lineno, file=None, line=None):
    text = f"warning: {_printable(message)}"
    if text not in _SHOWN:
        _SHOWN.add(text)
        print(text, file=sys.stderr)


def build_parser() -> argparse.ArgumentParser:
    from .. import __version__

    p = Parser(
        prog="bforest",
        description="Bayes Forest: fit growth models to laser-scanned trees and grow morphological clones.",
    )
    p.add_argument("--version", action="version", version=f"bforest {__version__}")
    p.add_argument("--debug", action="store_true", help="show tracebacks")
    p.set_defaults(on_interrupt=None)
    sub = p.add_subparsers(dest="command", metavar="COMMAND", parser_class=Parser)
    for group in (runs, init, stand, amortised, trees, export, data, plugins_config):
        group.add_commands(sub)
    return p


def main(argv=None) -> int:
    from ..errors import BayesForestError

    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "command", None):
        parser.print_help()
        return EXIT_USAGE
    old_show = warnings.showwarning
    _SHOWN.clear()
    if not args.debug:
        warnings.showwarning = _warning_line
    try:
        with user_stops():  # Ctrl-C and SIGTERM: the command unwinds, stopping every process it started
            return int(args.func(args) or 0)
    except KeyboardInterrupt as exc:
        signum = getattr(exc, "signum", signal.SIGINT)
        hint = args.on_interrupt(args) if callable(args.on_interrupt) else args.on_interrupt
        _say(f"stopped by {signal.Signals(signum).name}" + (f" ({hint})" if hint else ""))
        return 128 + signum
    except BrokenPipeError:  # the reader of the output has gone (`bforest info ... | head`): not an error
        _quiet_stdout()
        return 0
    except (BayesForestError, UsageError, FileNotFoundError, IsADirectoryError, PermissionError) as exc:
        if args.debug:
            raise
        _say(f"error: {_one_line(exc)}")
        return EXIT_USAGE
    except BrokenExecutor as exc:  # a worker process died: its start-up failed, or it was killed
        if args.debug:
            raise
        _say(
            f"error: the worker processes stopped ({_one_line(exc)}); a worker's start-up failed "
            "(its message is above) or it was killed, e.g. out of memory; finished evaluations are "
            "saved: continue with --resume"
        )
        return EXIT_USAGE
    except (ValueError, OSError) as exc:  # an SSM rejecting a value; a path that cannot be written
        if args.debug:
            raise
        full = getattr(exc, "errno", None) == errno.ENOSPC
        advice = "; the disk is full: free space and run the command again (a fit continues with --resume)"
        _say(f"error: {_one_line(exc)}{advice if full else ''}")
        return EXIT_USAGE
    except MemoryError:
        if args.debug:
            raise
        _say("error: out of memory (ask for less: fewer lines, clones or workers)")
        return EXIT_USAGE
    finally:
        warnings.showwarning = old_show


def _say(line: str) -> None:
    """Print the command's last line to stderr on a line of its own: a progress bar that an
    interrupt or an error left open is ended first."""
    end_open_bars()
    print(line, file=sys.stderr)


def _quiet_stdout() -> None:
    """Point standard output at the null device, so the interpreter's final flush of a closed pipe
    prints nothing (Python's documented way of leaving quietly on SIGPIPE)."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError):
        pass


def _one_line(exc) -> str:
    """The message on one line, control characters (terminal escapes in a file name) shown as
    escapes, never sent to the terminal."""
    return _printable(" ".join((str(exc).strip() or type(exc).__name__).split("\n")))


def _printable(text) -> str:
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in str(text))


if __name__ == "__main__":
    sys.exit(main())
