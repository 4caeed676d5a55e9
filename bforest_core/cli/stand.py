"""`bforest stand`: fit every tree of a plot, grow its clones and synthetic stands."""

from __future__ import annotations

import sys
from pathlib import Path

from .common import UsageError


def _executor(args) -> dict | None:
    """The executor the command line asks for (None: the config's, or the stand's own)."""
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


def _absolute(p):
    return None if p is None else str(Path(p).expanduser().resolve())


def cmd_stand(args):
    from ..pipeline.stand import (
        StandError,
        check_stand_dir,
        load_stand_config,
        read_settings,
        run_stand,
        settings_from,
    )

    if args.output is None:
        raise UsageError("give the stand folder with -o STAND")
    out = Path(args.output)
    check_stand_dir(out, args.resume, args.overwrite)  # before the trees are read
    executor = _executor(args)
    options = dict(recipe=_absolute(args.recipe), model=args.model, seed=args.seed, clones=args.count)
    options.update(realisations=args.realisations, max_evaluations=args.max_evaluations)
    if args.resume:
        if args.source or args.stem_map or any(v is not None for v in options.values()):
            raise UsageError("--resume continues the stand in -o as it was started: give only -o (and the executor)")
        settings = read_settings(out)
        if executor is not None:
            settings.executor = executor
    elif args.source and Path(args.source).suffix.lower() == ".toml":
        settings = load_stand_config(args.source, stem_map=args.stem_map, executor=executor, **options)
    elif args.source is None and args.stem_map is None:
        raise UsageError("give the trees: a folder or glob of QSMs, a stand config (.toml), or --stem-map CSV")
    else:
        settings = settings_from(args.source, args.stem_map, executor=executor, **options)
    res = run_stand(
        settings,
        out,
        resume=args.resume,
        overwrite=args.overwrite,
        progress=not args.quiet,
        warn=lambda line: print(line, file=sys.stderr),
    )
    n = len(res.rows)
    if res.fitted == 0 and args.resume:
        print(f"{out}: every tree had finished ({n} of {n}); nothing to do")
    else:
        print(f"{out}: {n - len(res.failed)} of {n} trees fitted ({res.fitted} by this command, {res.already} before)")
    for r in res.rows:
        if r.get("status") == "ok" and r.get("stop_kind") in ("wall_time", "timeout"):
            print(f"WARNING: {r['tree']}: {r['reason']}")
    for r in res.failed:
        print(f"error: {r['tree']}: {r.get('reason', '')}", file=sys.stderr)
    print(f"table: {out / 'stand.csv'}")
    if res.synthetic:
        print(f"synthetic stands: {len(res.synthetic)} in {res.synthetic[0].parent}")
    if not args.no_report and len(res.failed) < n:
        from ..report.stand import write_stand_report

        try:
            print(f"report: {write_stand_report(out)}")
        except StandError as exc:
            print(f"warning: the report could not be written: {exc}", file=sys.stderr)
    return 1 if res.failed else 0


def add_commands(sub):
    s = sub.add_parser(
        "stand",
        help="fit every tree of a plot (a folder of QSMs or a stem map), grow clones and synthetic stands",
        description=(
            "Fit every tree of a scanned plot and grow its clones: one recipe per tree (bforest init's, or --recipe "
            "for all), the trees as tasks on the executor (process or dask), one table STAND/stand.csv, a report "
            "and synthetic stands (a clone of each tree at its place: mesh, LAS scan, trees.csv)."
        ),
    )
    s.add_argument(
        "source",
        metavar="SOURCE",
        nargs="?",
        help="the trees: a folder of QSMs, a glob ('plot/*.mat'), or a stand config (.toml: [stand] and [executor])",
    )
    s.add_argument("-o", "--output", metavar="STAND", help="the stand folder (new, or the stand to --resume)")
    s.add_argument(
        "--stem-map",
        metavar="CSV",
        help="the trees as a stem map: columns file, x, y (m), optionally tree, z, model, recipe",
    )
    s.add_argument("--recipe", metavar="RUN.toml", help="one recipe for every tree (default: bforest init's for each)")
    s.add_argument("--model", help="growth model of init's recipes (default: the one that suits each tree)")
    s.add_argument("--seed", type=int, help="run seed of every tree's fit (default: the recipe's)")
    s.add_argument("-n", "--count", type=int, help="clones per tree (default 30)")
    s.add_argument(
        "--max-evaluations", type=int, help="every tree's evaluation budget (default: its recipe's; less: a quick look)"
    )
    s.add_argument("--realisations", type=int, help="synthetic stands to grow from the clones (default 1)")
    s.add_argument("--executor", choices=["serial", "process", "dask"], help="where the trees run (default: process)")
    s.add_argument("--workers", type=int, help="worker processes (process, local dask) or workers to wait for (dask)")
    s.add_argument("--address", help="a running Dask scheduler (tls://host:8786), with --executor dask")
    s.add_argument("--scheduler-file", help="a Dask scheduler file, with --executor dask")
    s.add_argument("--resume", action="store_true", help="continue the stand in -o: unfinished trees only")
    s.add_argument("--overwrite", action="store_true", help="delete the stand in -o (its fits too) and start anew")
    s.add_argument("--no-report", action="store_true", help="do not write the stand report")
    s.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    s.set_defaults(func=cmd_stand)
