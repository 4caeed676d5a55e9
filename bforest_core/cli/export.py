"""``bforest export``: the best fit and the clones in other formats, the evaluation log as CSV."""

from __future__ import annotations

from ..pipeline.store import RunFiles
from .common import RUN, TREE_FORMATS, UsageError, command, overwrite_arg, parse_set, run_arg


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
        bad = [w for w in what if w not in ("best", "clones", "posterior")]
        if bad:
            raise UsageError(f"export: --what takes best, clones and/or posterior (got {', '.join(bad)})")
        scan = parse_set(args.scan)
        if "scanner" in scan and isinstance(scan["scanner"], str):
            try:
                scan["scanner"] = [float(v) for v in scan["scanner"].split(",")]
            except ValueError:
                raise UsageError(f"--scan scanner expects x,y,z in m, got {scan['scanner']!r}") from None
        files = export_trees(args.run_dir, formats, args.output, what, overwrite=args.overwrite, scan=scan)
        where = files[0].parent if files else args.output
        print(f"wrote {len(files)} files to {where}")
    return 0


def add_commands(sub) -> None:
    """Register ``export``."""
    s = command(sub, "export", "the best fit and the clones in other formats; evaluations as CSV")
    run_arg(s)
    s.add_argument(
        "--format",
        action="append",
        metavar="FMT",
        help=f"writer name or suffix, repeatable or comma separated: {TREE_FORMATS}",
    )
    s.add_argument(
        "--what",
        default="best,clones",
        help="trees to export, comma separated: best, clones, posterior (the posterior clones of "
        "bforest clones --posterior, written as posterior_clone_*) (default best,clones)",
    )
    s.add_argument(
        "-o", "--output", default=None, metavar="DIR", help=f"folder of the tree files (default: {RUN}/export)"
    )
    s.add_argument("--evaluations", metavar="FILE.csv", help=f"also flatten {RunFiles.EVALUATIONS} into this CSV")
    s.add_argument(
        "--scan",
        action="append",
        metavar="NAME=VALUE",
        help="synthetic-scan setting for las/laz/xyz, repeatable: density=POINTS_PER_M2 (2000), "
        "mode=uniform|scanner, scanner=X,Y,Z (m), reference_range=M (10), noise=SD_M (0), seed=N (0)",
    )
    overwrite_arg(s, "replace files that exist")
    s.set_defaults(func=cmd_export)
