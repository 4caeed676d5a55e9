"""The ``bforest`` command.

Every error a user can cause prints one line ``error: ...`` and exits with code 2; ``--debug``
shows the traceback instead.
"""
from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path

EXIT_USAGE = 2


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # argparse's own usage errors: one line, exit 2
        self.print_usage(sys.stderr)
        print(f"error: {message}", file=sys.stderr)
        sys.exit(EXIT_USAGE)


def _warning_line(message, category, filename, lineno, file=None, line=None):
    print(f"warning: {message}", file=sys.stderr)


def _parse_set(items: list[str]) -> dict:
    out = {}
    for it in items or []:
        if "=" not in it:
            raise _UsageError(f"--set expects NAME=VALUE, got {it!r}")
        k, v = it.split("=", 1)
        k = k.strip()
        try:
            out[k] = json.loads(v)
        except json.JSONDecodeError:
            out[k] = v
    return out


class _UsageError(Exception):
    pass


# ---------------------------------------------------------------------------------- commands
def cmd_plugins(args):
    from ..registry import discover
    reg = discover()
    rows = sorted(reg.components.values(), key=lambda e: (e.kind, e.name))
    print(f"{'kind':<11} {'name':<16} {'distribution':<28} summary")
    for e in rows:
        dist = f"{e.distribution} {e.version}"
        summ = getattr(e.cls, "summary", "") or (e.cls.__doc__ or "").strip().split("\n")[0]
        print(f"{e.kind:<11} {e.name:<16} {dist:<28} {summ}")
    for (kind, name), entries in sorted(reg.conflicts.items()):
        who = ", ".join(f"{x.distribution} {x.version}" for x in entries)
        print(f"{kind:<11} {name:<16} CONFLICT: registered by {who}")
    if reg.errors:
        print("\nload errors:")
        for err in reg.errors:
            print(f"  plugin '{err.plugin}' from {err.distribution}: {err.error}")
    return 0


def cmd_config(args):
    from ..config import config_schema, load_config
    if args.action == "schema":
        print(json.dumps(config_schema(), indent=2))
        return 0
    cfg = load_config(args.file)
    print(f"{args.file}: ok (ssm {cfg.ssm.kind}, {len(cfg.ssm.free)} free parameters, "
          f"features {cfg.features.kind}, distance {cfg.distance.kind}, optimizer {cfg.optimizer.kind}, "
          f"executor {cfg.executor.kind})")
    return 0


def _read(path, args=None):
    from ..io import read_qsm
    opts = {}
    if args is not None:
        if getattr(args, "select", None) is not None:
            opts["select"] = args.select
        if getattr(args, "topology", None):
            opts["topology"] = args.topology
    return read_qsm(path, reader=getattr(args, "reader", None), **opts)


def cmd_info(args):
    from ..metrics import classical_metrics
    tree = _read(args.tree, args)
    trees = tree if isinstance(tree, list) else [tree]
    for k, t in enumerate(trees):
        m = classical_metrics(t)
        md = t.metadata
        head = f"{args.tree}" + (f" [reconstruction {md.get('model_index', k)}]" if len(trees) > 1 else "")
        print(head)
        fmt = md.get("format", "?") + (f" (version {md['version']})" if md.get("version") else "")
        print(f"  format        {fmt}")
        print(f"  cylinders     {t.n}" + (f" ({int(t.added.sum())} added)" if t.added.any() else ""))
        print(f"  branches      {t.n_branches} (topology {t.topology})")
        print(f"  max order     {t.max_order}")
        print(f"  height        {m['height']:.2f} m")
        print(f"  girth (base)  {m['girth']:.3f} m")
        if m.get("dbh") is not None and m["dbh"] == m["dbh"]:
            print(f"  DBH (1.3 m)   {m['dbh']:.3f} m")
        print(f"  crown spread  {m['crown_spread']:.2f} m")
        print(f"  wood volume   {t.volume:.4f} m^3")
        for note in md.get("repairs", []) or []:
            print(f"  repaired      {note}")
    return 0


def cmd_simulate(args):
    from ..io import write_tree
    from ..metrics import classical_metrics
    from ..registry import component
    settings = _parse_set(args.setting)
    if args.preset:
        settings["preset"] = args.preset
    ssm = component("ssm", args.ssm, **settings)
    params = _parse_set(args.set)
    tree = ssm.simulate(params, args.seed)
    m = classical_metrics(tree)
    print(f"{args.ssm} seed {args.seed}: {tree.n} cylinders, {tree.n_branches} branches, "
          f"height {m['height']:.2f} m, girth {m['girth']:.3f} m, crown spread {m['crown_spread']:.2f} m")
    if args.output:
        p = write_tree(tree, args.output)
        print(f"wrote {p}")
    if args.png:
        from ..report.trees import save_tree_figure
        save_tree_figure(tree, args.png, title=f"{args.ssm}, seed {args.seed}")
        print(f"wrote {args.png}")
    return 0


def cmd_distance(args):
    from ..metrics import classical_metrics, relative_errors
    from ..registry import component
    a, b = _read(args.tree_a), _read(args.tree_b)
    a = a[0] if isinstance(a, list) else a
    b = b[0] if isinstance(b, list) else b
    fs_settings = {"sets": _split_sets(args.sets)}
    if args.topology:
        fs_settings["topology"] = args.topology
    fs = component("features", args.features, **fs_settings)
    fs.prepare([b])
    Ub, Ua = fs.extract(b), fs.extract(a)
    dset = {"statistic": args.statistic, "lines": args.lines}
    if args.normalize:
        dset["normalize"] = args.normalize
    dist = component("distance", args.distance, **dset)
    dist.prepare(Ub, {k: fs.columns(k) for k in fs.set_names})
    per = dist.compute_per_set(Ua, Ub)
    total = dist.combine(per)
    print(f"data (B): {args.tree_b}\nmodel (A): {args.tree_a}")
    print(f"distance ({args.distance}, {args.statistic}, {args.lines} lines): {total:.4f}")
    for k, v in per.items():
        print(f"  {k:<10} {'skipped' if v is None else f'{v:.4f}'}  (rows A {Ua[k].shape[0]}, B {Ub[k].shape[0]})")
    ma, mb = classical_metrics(a), classical_metrics(b)
    err = relative_errors(mb, ma)
    print(f"{'metric':<14}{'A':>10}{'B':>10}{'rel. error':>12}")
    for key, ek in (("height", "d_h"), ("girth", "d_g"), ("crown_spread", "d_c")):
        print(f"{key:<14}{ma[key]:>10.3f}{mb[key]:>10.3f}{err[ek]:>12.3f}")
    if args.test:
        if not hasattr(dist, "permutation_test"):
            raise _UsageError(f"distance '{args.distance}' offers no permutation test")
        res = dist.permutation_test(Ua, Ub, seed=args.seed)
        print(f"permutation test: {res.summary()}")
        for k, p in res.per_set.items():
            print(f"  {k:<10} p = {p:.4f} (Holm-corrected {res.per_set_holm.get(k, float('nan')):.4f})")
        print("  (rows of one tree are not independent: a screening measure, not an exact test)")
    return 0


def _split_sets(text: str) -> list[str]:
    """'S0,1 B2+' or 'S0,1;B2+' -> ['S0,1', 'B2+'] ('+' belongs to open order ranges)."""
    return text.replace(";", " ").split()


def cmd_fit(args):
    from ..config import load_config
    from ..pipeline.fit import fit
    cfg = load_config(args.config)
    if args.max_evaluations:
        cfg.stop.max_evaluations = args.max_evaluations
    out = Path(args.output) if args.output else Path("runs") / Path(args.config).stem
    res = fit(cfg, out, resume=args.resume, progress=not args.quiet, overwrite=args.overwrite)
    print(f"best distance {res.distance:.4f} after {res.n_evaluations} evaluations ({res.stop_reason})")
    for k, v in res.params.items():
        print(f"  {k} = {v:.6g}" if isinstance(v, float) else f"  {k} = {v}")
    print(f"run directory: {out}")
    if cfg.report.enabled and not args.no_report:
        _report(out)
    return 0


def _report(run_dir):
    try:
        from ..report.build import write_report
    except ImportError:
        return
    p = write_report(run_dir)
    print(f"report: {p}")


def cmd_clones(args):
    from ..pipeline.clones import clones
    s = clones(args.run_dir, n=args.n, progress=not args.quiet)
    print(f"{s['ok']} of {s['count']} clones grown in {Path(args.run_dir) / 'clones'}")
    for key in ("distance", "height", "girth", "crown_spread", "d_h", "d_g", "d_c"):
        if key in s:
            v = s[key]
            print(f"  {key:<13} mean {v['mean']:.4f}  sd {v['sd']:.4f}  [{v['min']:.4f}, {v['max']:.4f}]")
    if not args.no_report:
        _report(args.run_dir)
    return 0


def cmd_report(args):
    from ..report.build import write_report
    p = write_report(args.run_dir)
    print(f"report: {p}")
    return 0


def cmd_compare(args):
    from ..pipeline.compare import compare
    res = compare(args.config, optimizers=[o.strip() for o in args.optimizers.split(",") if o.strip()],
                  budget=args.budget, repeats=args.repeats, out_dir=args.output, threshold=args.threshold)
    from ..report.comparison import write_compare_figure
    print(res["table_text"])
    print(f"figure: {write_compare_figure(res)}")
    return 0


def cmd_profile(args):
    from ..pipeline.profile import profile
    res = profile(args.run_dir, args.param, values=args.values, seeds=args.seeds, n=args.n)
    from ..report.comparison import write_profile_figure
    print(res["table_text"])
    print(f"figure: {write_profile_figure(res)}")
    return 0


def cmd_demo(args):
    from .demo import run_demo
    return run_demo(Path(args.output), quick=args.quick, progress=not args.quiet)


# ---------------------------------------------------------------------------------- parser
def build_parser() -> argparse.ArgumentParser:
    from .. import __version__
    p = _Parser(prog="bforest", description="Bayes Forest: fit growth models to laser-scanned trees "
                "and grow morphological clones.")
    p.add_argument("--version", action="version", version=f"bforest {__version__}")
    p.add_argument("--debug", action="store_true", help="show tracebacks")
    sub = p.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)

    s = sub.add_parser("demo", help="the main job on the embedded default target, end to end")
    s.add_argument("-o", "--output", default="demo-run", help="run directory (default: demo-run)")
    s.add_argument("--quick", action="store_true", help="a smaller fit (for tests)")
    s.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    s.set_defaults(func=cmd_demo)

    s = sub.add_parser("fit", help="fit a growth model as configured in RUN.toml")
    s.add_argument("config", metavar="RUN.toml")
    s.add_argument("-o", "--output", help="run directory (default: runs/<config name>)")
    s.add_argument("--resume", action="store_true", help="continue a stopped or killed run in -o")
    s.add_argument("--overwrite", action="store_true", help="replace an existing run in -o")
    s.add_argument("--max-evaluations", type=int, help="override [stop] max_evaluations")
    s.add_argument("--no-report", action="store_true")
    s.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    s.set_defaults(func=cmd_fit)

    s = sub.add_parser("clones", help="clones of a finished fit, with their distances and metrics")
    s.add_argument("run_dir", metavar="DIR")
    s.add_argument("-n", type=int, default=None, help="number of clones (default: [clones] count)")
    s.add_argument("--no-report", action="store_true")
    s.add_argument("-q", "--quiet", action="store_true")
    s.set_defaults(func=cmd_clones)

    s = sub.add_parser("report", help="figures (PNG) and a summary (Markdown/HTML) of a run")
    s.add_argument("run_dir", metavar="DIR")
    s.set_defaults(func=cmd_report)

    s = sub.add_parser("compare", help="compare optimisers on equal evaluation budgets")
    s.add_argument("config", metavar="RUN.toml")
    s.add_argument("--optimizers", default="ga,nlopt,emcee,de")
    s.add_argument("--budget", type=int, required=True, help="evaluations per optimiser run")
    s.add_argument("--repeats", type=int, default=3)
    s.add_argument("--threshold", type=float, default=None, help="distance for 'evaluations to reach'")
    s.add_argument("-o", "--output", default=None, help="output directory (default: runs/compare-<config>)")
    s.set_defaults(func=cmd_compare)

    s = sub.add_parser("profile", help="distance along one parameter for several seeds")
    s.add_argument("run_dir", metavar="DIR")
    s.add_argument("--param", required=True)
    s.add_argument("--values", type=float, nargs="+", default=None, help="values (default: 11 across the bounds)")
    s.add_argument("--n", type=int, default=11)
    s.add_argument("--seeds", type=int, default=5)
    s.set_defaults(func=cmd_profile)

    s = sub.add_parser("distance", help="structural distance between two QSM files (B is the data side)")
    s.add_argument("tree_a", metavar="TREE_A")
    s.add_argument("tree_b", metavar="TREE_B")
    s.add_argument("--sets", default="S1 B1", help="data sets, e.g. 'S0,1 B2,3,4' (default: 'S1 B1')")
    s.add_argument("--statistic", default="ks")
    s.add_argument("--lines", type=int, default=256)
    s.add_argument("--normalize", default=None)
    s.add_argument("--topology", default=None, choices=["source", "subtree", "thickest"])
    s.add_argument("--features", default="branch-segment")
    s.add_argument("--distance", default="sliced")
    s.add_argument("--test", action="store_true", help="permutation test p-value")
    s.add_argument("--seed", type=int, default=1)
    s.set_defaults(func=cmd_distance)

    s = sub.add_parser("simulate", help="grow one tree with a growth model")
    s.add_argument("--ssm", required=True)
    s.add_argument("--seed", type=int, default=1)
    s.add_argument("--set", action="append", metavar="NAME=VALUE", help="model parameter (repeatable)")
    s.add_argument("--setting", action="append", metavar="NAME=VALUE", help="component setting (repeatable)")
    s.add_argument("--preset", default=None, help="parameter preset (LIGNUM)")
    s.add_argument("-o", "--output", help="tree file (.txt TreeQSM text, .csv, .ply, .obj)")
    s.add_argument("--png", help="figure of the tree")
    s.set_defaults(func=cmd_simulate)

    s = sub.add_parser("info", help="what a QSM file holds")
    s.add_argument("tree", metavar="TREE")
    s.add_argument("--reader", default=None)
    s.add_argument("--select", default=None, type=_select_arg, help="reconstruction index, list or 'all'")
    s.add_argument("--topology", default=None, choices=["source", "subtree", "thickest"])
    s.set_defaults(func=cmd_info)

    s = sub.add_parser("plugins", help="every discovered plugin, its kind, version, and load errors")
    s.set_defaults(func=cmd_plugins)

    s = sub.add_parser("config", help="config schema | check RUN.toml")
    cs = s.add_subparsers(dest="action", metavar="ACTION", parser_class=_Parser, required=True)
    cs.add_parser("schema", help="print the JSON schema of run configs")
    c2 = cs.add_parser("check", help="validate a run config")
    c2.add_argument("file", metavar="RUN.toml")
    s.set_defaults(func=cmd_config)
    return p


def _select_arg(text):
    if text == "all":
        return "all"
    if "," in text:
        return [int(x) for x in text.split(",")]
    return int(text)


def main(argv=None) -> int:
    from ..errors import BayesForestError
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "command", None):
        parser.print_help()
        return EXIT_USAGE
    old_show = warnings.showwarning
    if not args.debug:
        warnings.showwarning = _warning_line
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("interrupted (finished evaluations are saved; continue with --resume)", file=sys.stderr)
        return 130
    except (BayesForestError, _UsageError, FileNotFoundError, IsADirectoryError, PermissionError) as exc:
        if args.debug:
            raise
        print(f"error: {_one_line(exc)}", file=sys.stderr)
        return EXIT_USAGE
    except ValueError as exc:  # e.g. an SSM rejecting a parameter value
        if args.debug:
            raise
        print(f"error: {_one_line(exc)}", file=sys.stderr)
        return EXIT_USAGE
    finally:
        warnings.showwarning = old_show


def _one_line(exc) -> str:
    text = str(exc).strip() or type(exc).__name__
    return " ".join(text.split("\n"))


if __name__ == "__main__":
    sys.exit(main())
