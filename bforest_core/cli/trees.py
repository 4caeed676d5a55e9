"""Commands on single trees: info, simulate, distance."""

from __future__ import annotations

import numpy as np

from ..config import DEFAULT_KINDS
from ..io import json_text, read_tree
from .common import TREE_FORMATS, UsageError, command, parse_set, read, select_arg, split_sets


def cmd_info(args):
    from ..metrics import classical_metrics, order_summary

    tree = read(args.tree, args)
    trees = tree if isinstance(tree, list) else [tree]
    if args.json or args.csv:
        return _info_table(args, trees)
    for k, t in enumerate(trees):
        m = classical_metrics(t)
        md = t.metadata
        head = f"{args.tree}" + (f" [reconstruction {md.get('model_index', k)}]" if len(trees) > 1 else "")
        print(head)
        fmt = md.get("format", "?") + (f" (version {md['version']})" if md.get("version") else "")
        print(f"  format        {fmt}")
        added = f" ({int(t.added.sum())} added by the reconstruction to bridge gaps)" if t.added.any() else ""
        print(f"  cylinders     {t.n}{added}")
        print(f"  branches      {t.n_branches} (topology {t.topology})")
        print(f"  max order     {t.max_order}")
        print(f"  height        {m['height']:.2f} m")
        print(f"  base diameter {m['base_diameter']:.3f} m")
        if m.get("dbh") is not None and m["dbh"] == m["dbh"]:
            print(f"  DBH (1.3 m)   {m['dbh']:.3f} m")
        print(f"  crown spread  {m['crown_spread']:.2f} m")
        print(f"  wood volume   {t.volume:.4f} m^3")
        for note in md.get("repairs", []) or []:
            print(f"  repaired      {note}")
        print(
            f"  {'order':>5} {'branches':>9} {'length (m)':>11} {'volume (m^3)':>13} {'mean angle (deg)':>17} "
            f"{'base diam. (m)':>15}"
        )
        for r in order_summary(t):
            ang = "–" if r["mean_angle_deg"] != r["mean_angle_deg"] else f"{r['mean_angle_deg']:.1f}"
            print(
                f"  {r['order']:>5} {r['n_branches']:>9} {r['length_m']:>11.2f} {r['volume_m3']:>13.5f} {ang:>17} "
                f"{r['mean_base_diameter_m']:>15.4f}"
            )
        from .tree_tables import info_text

        print("\n".join(info_text(t)))
    return 0


def _info_table(args, trees) -> int:
    """``info --json`` (metrics and the per-order table of each reconstruction) or ``--csv``
    (the per-order table, one row per reconstruction and order)."""
    import csv
    import sys

    from ..metrics import classical_metrics, order_summary
    from .tree_tables import csv_rows, info_json

    if args.csv and args.table != "orders":
        w = csv.writer(sys.stdout)
        for k, t in enumerate(trees):
            head, rows = csv_rows(t, args.table)
            if k == 0:
                w.writerow(["reconstruction"] + head)
            w.writerows([k] + r for r in rows)
        return 0
    out = [
        {
            "file": str(args.tree),
            "reconstruction": k,
            "cylinders": t.n,
            "branches": t.n_branches,
            "metrics_m": classical_metrics(t),
            "orders": order_summary(t),
            **info_json(t),
        }
        for k, t in enumerate(trees)
    ]
    if args.json:
        print(json_text(out if len(out) > 1 else out[0], strict=True))
        return 0
    cols = ["order", "n_branches", "length_m", "volume_m3", "mean_angle_deg", "mean_base_diameter_m"]
    w = csv.writer(sys.stdout)
    w.writerow(["reconstruction"] + cols)
    for item in out:
        for r in item["orders"]:
            w.writerow([item["reconstruction"]] + [r[c] for c in cols])
    return 0


def cmd_simulate(args):
    from ..io import write_tree, writer_for
    from ..metrics import classical_metrics
    from ..registry import component

    scan = parse_set(args.scan)
    if args.output:
        writer_for(args.output)  # a wrong output name fails before the tree is grown
    if scan and not str(args.output or "").lower().endswith((".las", ".laz", ".xyz")):
        raise UsageError(f"--scan applies to a synthetic scan output (-o x.las, .laz, .xyz), not {args.output}")
    if isinstance(scan.get("scanner"), str):
        try:
            scan["scanner"] = [float(v) for v in scan["scanner"].split(",")]
        except ValueError:
            raise UsageError(f"--scan scanner expects x,y,z in m, got {scan['scanner']!r}") from None
    settings = parse_set(args.setting)
    if args.preset:
        settings["preset"] = args.preset
    ssm = component("ssm", args.ssm, **settings)
    params = parse_set(args.set)
    _check_ranges(ssm, params)
    tree = ssm.simulate(params, args.seed)
    m = classical_metrics(tree)
    print(
        f"{args.ssm} seed {args.seed}: {tree.n} cylinders, {tree.n_branches} branches, "
        f"height {m['height']:.2f} m, base diameter {m['base_diameter']:.3f} m, crown spread {m['crown_spread']:.2f} m"
    )
    if args.output:
        p = write_tree(tree, args.output, **scan)
        print(f"wrote {p}")
    if args.png:
        from ..report.trees import save_tree_figure

        save_tree_figure(tree, args.png, title=f"{args.ssm}, seed {args.seed}")
        print(f"wrote {args.png}")
    return 0


def _check_ranges(ssm, params: dict) -> None:
    """``--set`` values within the model's allowed ranges (as a config's are)."""
    specs = {p.name: p for p in ssm.parameters}
    for name, v in params.items():
        s = specs.get(name)
        if s is not None and isinstance(v, (int, float)) and not s.lower <= v <= s.upper:
            raise UsageError(f"--set {name}={v}: outside the allowed range [{s.lower}, {s.upper}] {s.unit}".rstrip())


#: most projection lines `bforest distance` draws (each line holds both trees' projections)
MAX_LINES = 1 << 16


def cmd_distance(args):
    from ..errors import ConfigError
    from ..interfaces import LineDistance
    from ..metrics import classical_metrics, relative_errors
    from ..registry import component

    a, b = read_tree(args.tree_a), read_tree(args.tree_b)
    if not 1 <= args.lines <= MAX_LINES:
        raise UsageError(f"--lines must be between 1 and {MAX_LINES} (got {args.lines})")
    dset = {"statistic": args.statistic, "lines": args.lines}
    if args.normalize:
        dset["normalize"] = args.normalize
    if args.empty_cost is not None:
        dset["empty_cost"] = args.empty_cost
    try:
        dist = component("distance", args.distance, **dset)
    except ConfigError as exc:
        if args.empty_cost is None and "empty_cost" in str(exc):  # the distance needs one for this statistic
            raise UsageError(
                f"--statistic {args.statistic} needs --empty-cost X: the distance of a set that one tree lacks ({exc})"
            ) from None
        raise
    fs_settings = {"sets": split_sets(args.sets)}
    if args.topology:
        fs_settings["topology"] = args.topology
    fs = component("features", args.features, **fs_settings)
    fs.prepare([b])
    Ub, Ua = fs.extract(b), fs.extract(a)
    dist.prepare(Ub, {k: fs.columns(k) for k in fs.set_names})
    per = dist.compute_per_set(Ua, Ub)
    total = dist.combine(per)
    gaps = {}
    if args.columns:
        from ..report.datasets import column_gaps

        gaps = {k: column_gaps(Ua[k], Ub[k], fs.columns(k)) for k in per}
    if args.json:
        ma, mb = classical_metrics(a), classical_metrics(b)
        print(
            json_text(
                {
                    "data": str(args.tree_b),
                    "model": str(args.tree_a),
                    "distance": total,
                    "settings": {
                        "distance": args.distance,
                        "statistic": args.statistic,
                        "lines": args.lines,
                        "sets": list(per),
                    },
                    "per_set": per,
                    "rows": {k: [int(Ua[k].shape[0]), int(Ub[k].shape[0])] for k in per},
                    "metrics_model_m": ma,
                    "metrics_data_m": mb,
                    "relative_errors": relative_errors(mb, ma),
                    **({"columns": gaps} if args.columns else {}),
                },
                strict=True,
            )
        )
        return 0
    print(f"data (B): {args.tree_b}\nmodel (A): {args.tree_a}")
    print(f"distance ({args.distance}, {args.statistic}, {args.lines} lines): {total:.4f}")
    for k, v in per.items():
        print(f"  {k:<10} {'skipped' if v is None else f'{v:.4f}'}  (rows A {Ua[k].shape[0]}, B {Ub[k].shape[0]})")
        for g in gaps.get(k, []):
            ma_, mb_ = ("–" if m is None else f"{m:.4g}" for m in (g["median_model"], g["median_data"]))
            print(f"    {g['column']:<12} KS {g['ks']:.3f}   median A {ma_}, B {mb_}")
    ma, mb = classical_metrics(a), classical_metrics(b)
    err = relative_errors(mb, ma)
    print(f"{'metric':<18}{'A':>10}{'B':>10}{'rel. error':>12}")
    for key, label, ek in (
        ("height", "height (m)", "d_h"),
        ("girth", "base diameter (m)", "d_g"),
        ("crown_spread", "crown spread (m)", "d_c"),
    ):
        e = "–" if not np.isfinite(err[ek]) else f"{100 * err[ek]:.1f} %"
        print(f"{label:<18}{ma[key]:>10.3f}{mb[key]:>10.3f}{e:>12}")
    if args.test:
        try:
            if not isinstance(dist, LineDistance):
                raise NotImplementedError
            res = dist.permutation_test(Ua, Ub, seed=args.seed)
        except NotImplementedError:
            raise UsageError(f"distance '{args.distance}' offers no permutation test") from None
        print(f"permutation test: {res.summary()}")
        for k, p in res.per_set.items():
            print(f"  {k:<10} p = {p:.4f} (Holm-corrected {res.per_set_holm.get(k, float('nan')):.4f})")
        print("  (rows of one tree are not independent: a screening measure, not an exact test)")
    return 0


def add_commands(sub) -> None:
    """Register this group's subcommands."""
    s = command(sub, "distance", "structural distance between two QSM files (B is the data side)")
    s.add_argument("tree_a", metavar="TREE_A", help="QSM file of the model side (A), or sample:NAME")
    s.add_argument("tree_b", metavar="TREE_B", help="QSM file of the data side (B), or sample:NAME")
    s.add_argument("--sets", default="S1 B1", help="data sets, e.g. 'S0,1 B2,3,4' (default: 'S1 B1')")
    s.add_argument(
        "--statistic", default="ks", help="two-sample statistic per line: ks, cvm, ad, w1, energy (default ks)"
    )
    s.add_argument("--lines", type=int, default=256, help="projection lines (default 256)")
    s.add_argument("--normalize", default=None, help="column normalisation (default: the distance's, zscore)")
    s.add_argument(
        "--empty-cost",
        type=float,
        default=None,
        metavar="X",
        help="distance of a set one tree lacks (needed by every statistic but ks, whose maximum is 1)",
    )
    s.add_argument(
        "--topology",
        default=None,
        choices=["source", "subtree", "thickest"],
        help="branch topology rule (default: the feature set's, subtree)",
    )
    s.add_argument("--features", default="branch-segment", help="feature set plugin (default branch-segment)")
    s.add_argument(
        "--distance", default=DEFAULT_KINDS["distance"], help=f"distance plugin (default {DEFAULT_KINDS['distance']})"
    )
    s.add_argument("--test", action="store_true", help="permutation test p-value")
    s.add_argument(
        "--columns",
        action="store_true",
        help="each set's columns on their own: KS and both medians (angles in degrees), largest gap first",
    )
    s.add_argument("--json", action="store_true", help="print the result as JSON")
    s.add_argument("--seed", type=int, default=1, help="seed of the permutation test")
    s.set_defaults(func=cmd_distance)

    s = command(sub, "simulate", "grow one tree with a growth model")
    s.add_argument("--ssm", required=True, help="growth model plugin, e.g. sot or lignum")
    s.add_argument("--seed", type=int, default=1, help="model seed (default 1)")
    s.add_argument("--set", action="append", metavar="NAME=VALUE", help="model parameter (repeatable)")
    s.add_argument("--setting", action="append", metavar="NAME=VALUE", help="component setting (repeatable)")
    s.add_argument("--preset", default=None, help="parameter preset (LIGNUM)")
    s.add_argument("-o", "--output", metavar="FILE", help=f"tree file, its format by its suffix: {TREE_FORMATS}")
    s.add_argument(
        "--scan",
        action="append",
        metavar="NAME=VALUE",
        help="synthetic-scan setting for a .las/.laz/.xyz output, repeatable: density=POINTS_PER_M2, "
        "mode=uniform|scanner, scanner=X,Y,Z (m), reference_range=M, noise=SD_M, seed=N",
    )
    s.add_argument("--png", help="figure of the tree")
    s.set_defaults(func=cmd_simulate)

    s = command(sub, "info", "what a QSM file holds")
    s.add_argument(
        "tree",
        metavar="TREE",
        help="a QSM file (TreeQSM .mat/.txt, SimpleForest or aRchi CSV, ...), or sample:NAME (bforest data list)",
    )
    s.add_argument("--reader", default=None, help="force a reader by name (default: detect)")
    s.add_argument("--select", default=None, type=select_arg, help="reconstruction index, list or 'all'")
    s.add_argument(
        "--topology",
        default=None,
        choices=["source", "subtree", "thickest"],
        help="branch topology rule (default: the reader's)",
    )
    out = s.add_mutually_exclusive_group()
    out.add_argument("--json", action="store_true", help="metrics and the per-order table as JSON")
    out.add_argument("--csv", action="store_true", help="a table as CSV (--table; default the per-order table)")
    s.add_argument(
        "--table",
        default="orders",
        choices=["orders", "attributes", "distributions", "branches"],
        help="with --csv: per order (default), TreeQSM's tree attributes, its distributions, or one row "
        "per branch like TreeQSM's qsm.branch (order, parent, diameter, volume, area, length, angle, "
        "height, azimuth, zenith)",
    )
    s.set_defaults(func=cmd_info)
