"""What the commands share: the one-line-error parser, argument helpers."""

from __future__ import annotations

import argparse
import json
import sys

EXIT_USAGE = 2


class Parser(argparse.ArgumentParser):
    def error(self, message):  # argparse's own usage errors: one line, exit 2
        self.print_usage(sys.stderr)
        print(f"error: {message}", file=sys.stderr)
        sys.exit(EXIT_USAGE)


class UsageError(Exception):
    """A bad command-line value (printed as one line, exit 2)."""


def parse_set(items: list[str]) -> dict:
    out = {}
    for it in items or []:
        if "=" not in it:
            raise UsageError(f"--set expects NAME=VALUE, got {it!r}")
        k, v = it.split("=", 1)
        k = k.strip()
        try:
            out[k] = json.loads(v)
        except json.JSONDecodeError:
            out[k] = v
    return out


def read(path, args=None):
    from ..io import read_qsm

    opts = {}
    if args is not None:
        if getattr(args, "select", None) is not None:
            opts["select"] = args.select
        if getattr(args, "topology", None):
            opts["topology"] = args.topology
    return read_qsm(path, reader=getattr(args, "reader", None), **opts)


def split_sets(text: str) -> list[str]:
    """'S0,1 B2+' or 'S0,1;B2+' -> ['S0,1', 'B2+'] ('+' belongs to open order ranges)."""
    return text.replace(";", " ").split()


def select_arg(text):
    if text == "all":
        return "all"
    if "," in text:
        return [int(x) for x in text.split(",")]
    return int(text)


def report(run_dir):
    try:
        from ..report.build import write_report
    except ImportError:
        return
    p = write_report(run_dir)
    print(f"report: {p}")


# ------------------------------------------------------------------ one vocabulary in --help
# Every subcommand names the same things the same way: a new subcommand takes its arguments from
# here (tests/test_cli.py walks every subcommand's --help and checks them).

#: the placeholder of a run folder (``bforest fit`` output) and of a run configuration
RUN = "RUN"
CONFIG = "CONFIG.toml"
#: a tree file's formats, chosen by its suffix (``simulate -o``, ``export --format``)
TREE_FORMATS = (
    "txt (TreeQSM text), mat (TreeQSM .mat), csv (native), simpleforest-csv, archi-csv, ply, obj, "
    "las, laz, xyz (synthetic laser scans), or any installed writer (bforest plugins)"
)


def command(sub, name: str, summary: str, **kw) -> argparse.ArgumentParser:
    """A subcommand whose ``--help`` opens with its summary as a sentence (the summary is also its
    line in ``bforest --help``)."""
    return sub.add_parser(name, help=summary, description=summary[0].upper() + summary[1:] + ".", **kw)


def run_arg(s, help: str = "a run folder (bforest fit output)") -> None:
    """The positional run folder a command reads."""
    s.add_argument("run_dir", metavar=RUN, help=help)


def run_output(s, default: str) -> None:
    """``-o RUN``: the run folder a command writes."""
    s.add_argument("-o", "--output", metavar=RUN, default=None, help=f"the run folder to write (default: {default})")


def config_arg(s, help: str = "the run configuration (TOML)") -> None:
    """The positional run configuration."""
    s.add_argument("config", metavar=CONFIG, help=help)


def count_arg(s, help: str, **kw) -> None:
    """``-n/--count N``: how many (clones, runs, values)."""
    s.add_argument("-n", "--count", dest="n", type=int, metavar="N", help=help, **kw)


def overwrite_arg(s, help: str, dest: str = "overwrite") -> None:
    """``--overwrite``: the one flag that replaces results a user would otherwise keep."""
    s.add_argument("--overwrite", dest=dest, action="store_true", help=help)


def resume_arg(s, help: str) -> None:
    """``--resume``: continue what an earlier call of the command stored in its folder."""
    s.add_argument("--resume", action="store_true", help=help)


def quiet_arg(s) -> None:
    """``-q/--quiet``: every command that draws progress bars can be asked not to."""
    s.add_argument("-q", "--quiet", action="store_true", help="no progress bars")


def old_spelling(s, flag: str, dest: str, **kw) -> None:
    """An option's former name, still taken but not shown in ``--help`` (scripts keep working)."""
    s.add_argument(flag, dest=dest, help=argparse.SUPPRESS, **kw)


def executor_args(s, what: str) -> None:
    """``--executor``, ``--workers``, ``--address``, ``--scheduler-file``: where a command's tasks run."""
    s.add_argument("--executor", choices=["serial", "process", "dask"], help=f"where {what} run (default: process)")
    s.add_argument("--workers", type=int, help="worker processes (process, local dask) or workers to wait for (dask)")
    s.add_argument("--address", help="a running Dask scheduler (tls://host:8786), with --executor dask")
    s.add_argument("--scheduler-file", help="a Dask scheduler file, with --executor dask")


def executor_spec(args) -> dict | None:
    """The executor :func:`executor_args` ask for (None: none asked for)."""
    if args.executor is None and args.workers is None and args.address is None and args.scheduler_file is None:
        return None
    kind = args.executor or ("dask" if (args.address or args.scheduler_file) else "process")
    spec = {"kind": kind}
    if args.workers is not None:
        spec["workers"] = args.workers
    for key in ("address", "scheduler_file"):
        if getattr(args, key) is not None:
            if kind != "dask":
                raise UsageError(f"--{key.replace('_', '-')} is for --executor dask")
            spec[key] = getattr(args, key)
    return spec
