"""``bforest data``: the sample trees, fetched from the public repositories they come from."""

from __future__ import annotations

from .common import Parser, UsageError, command, overwrite_arg


def cmd_data_list(args):
    from ..samples import SAMPLES, data_dir

    where = data_dir()
    print(f"sample trees (fetched ones are in {where}; name one as sample:NAME where a QSM file goes)")
    for s in SAMPLES.values():
        have = "fetched" if (where / s.filename).is_file() else f"{s.size / 1000:.0f} kB"
        print(f"{s.name:<28} {have:>8}  {s.about}")
        print(f"    from     github.com/{s.source}")
        print(f"    licence  {s.licence}")
        print(f"    cite     {s.cite}")
    return 0


def cmd_data_fetch(args):
    from ..samples import SAMPLES, sample
    from ..samples import fetch as fetch_one

    if args.all and args.names:
        raise UsageError("data fetch: name samples or give --all, not both")
    if not args.all and not args.names:
        raise UsageError("data fetch: name at least one sample (bforest data list), or give --all")
    names = list(SAMPLES) if args.all else [sample(n).name for n in args.names]  # unknown names before any download
    for name in names:
        path, fetched = fetch_one(name, dest=args.output, overwrite=args.overwrite)
        s = SAMPLES[name]
        what = "fetched" if fetched else "already there"
        print(f"{name}: {what}, {path} (SHA-256 checked; licence: {s.licence})")
    if not args.output:
        print("name them as sample:NAME, e.g. bforest info sample:" + names[0])
    return 0


def cmd_data_path(args):
    from ..samples import PREFIX, resolve

    print(resolve(PREFIX + args.name.removeprefix(PREFIX)))
    return 0


def add_commands(sub) -> None:
    """Register ``data`` and its actions."""
    s = command(sub, "data", "the sample trees: list them, fetch them from their sources, find them")
    acts = s.add_subparsers(dest="action", metavar="ACTION", parser_class=Parser, required=True)
    a = command(acts, "list", "every sample tree, where it comes from, its licence and whether it is fetched")
    a.set_defaults(func=cmd_data_list)
    a = command(
        acts,
        "fetch",
        "download sample trees from the public repositories they come from and check each file's SHA-256",
    )
    a.add_argument("names", nargs="*", metavar="NAME", help="samples to fetch (bforest data list names them)")
    a.add_argument("--all", action="store_true", help="every sample")
    a.add_argument(
        "-o",
        "--output",
        metavar="DIR",
        default=None,
        help="a folder to write them to (default: the cache, where sample:NAME finds them)",
    )
    overwrite_arg(a, "replace a file of a sample's name in the folder that is not the sample")
    a.set_defaults(func=cmd_data_fetch)
    a = command(acts, "path", "where a fetched sample's file is (for other programs)")
    a.add_argument("name", metavar="NAME", help="a sample's name")
    a.set_defaults(func=cmd_data_path)
