"""``bforest export``: the best fit and the clones in other formats, the evaluation log as CSV."""
from __future__ import annotations

from .common import UsageError


def cmd_export(args):
    from ..pipeline.export import export_evaluations, export_trees
    if not args.format and not args.evaluations:
        raise UsageError("export: name at least one --format or --evaluations FILE.csv")
    if args.evaluations:
        n = export_evaluations(args.run_dir, args.evaluations, overwrite=args.overwrite)
        print(f"wrote {args.evaluations} ({n} evaluations)")
    if args.format:
        formats = [f.strip() for f in ",".join(args.format).split(",") if f.strip()]
        what = tuple(w.strip() for w in args.what.split(",") if w.strip())
        bad = [w for w in what if w not in ("best", "clones")]
        if bad:
            raise UsageError(f"export: --what takes best and/or clones (got {', '.join(bad)})")
        files = export_trees(args.run_dir, formats, args.output, what, overwrite=args.overwrite)
        where = files[0].parent if files else args.output
        print(f"wrote {len(files)} files to {where}")
    return 0


def add_commands(sub) -> None:
    """Register ``export``."""
    s = sub.add_parser("export", help="the best fit and the clones in other formats; evaluations as CSV")
    s.add_argument("run_dir", metavar="RUN", help="a run directory (bforest fit output)")
    s.add_argument("--format", action="append", metavar="FMT",
                   help="writer name or suffix, repeatable or comma separated: txt (TreeQSM text), mat (TreeQSM "
                        ".mat), csv (native), simpleforest-csv, archi-csv, ply, obj, las, laz, xyz (synthetic "
                        "laser scans), or any installed writer (bforest plugins)")
    s.add_argument("--what", default="best,clones", help="trees to export: best, clones or both (default)")
    s.add_argument("-o", "--output", default=None, help="folder of the tree files (default: RUN/export)")
    s.add_argument("--evaluations", metavar="FILE.csv", help="also flatten evaluations.sqlite into this CSV")
    s.add_argument("--overwrite", action="store_true", help="replace files that exist")
    s.set_defaults(func=cmd_export)
