"""`bforest stand`: fit every tree of a plot, grow its clones and synthetic stands."""

from __future__ import annotations

import sys
from pathlib import Path

from .common import (
    CONFIG,
    UsageError,
    command,
    count_arg,
    executor_args,
    executor_spec,
    overwrite_arg,
    quiet_arg,
    resume_arg,
)


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
    executor = executor_spec(args)
    options = dict(recipe=_absolute(args.recipe), model=args.model, seed=args.seed, clones=args.n)
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
    s = command(
        sub,
        "stand",
        "fit every tree of a plot (a folder of QSMs or a stem map), grow their clones and synthetic stands: "
        "one recipe per tree (bforest init's, or --recipe for all), the trees as tasks on the executor, one "
        "table STAND/stand.csv and a report",
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
    s.add_argument(
        "--recipe",
        metavar=CONFIG,
        help="one run configuration for every tree (default: bforest init's recipe for each)",
    )
    s.add_argument("--model", help="growth model of init's recipes (default: the one that suits each tree)")
    s.add_argument("--seed", type=int, help="run seed of every tree's fit (default: the recipe's)")
    count_arg(s, "clones per tree (default 30)")
    s.add_argument(
        "--max-evaluations", type=int, help="every tree's evaluation budget (default: its recipe's; less: a quick look)"
    )
    s.add_argument("--realisations", type=int, help="synthetic stands to grow from the clones (default 1)")
    executor_args(s, "the trees")
    resume_arg(s, "continue the stand in -o: unfinished trees only")
    overwrite_arg(s, "delete the stand in -o (its fits too) and start anew")
    s.add_argument("--no-report", action="store_true", help="do not write the stand report")
    quiet_arg(s)
    s.set_defaults(
        func=cmd_stand,
        on_interrupt="finished trees and every logged evaluation are saved; continue with bforest stand --resume -o STAND",
    )
