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
