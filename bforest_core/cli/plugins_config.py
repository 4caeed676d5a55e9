"""Commands about the installation: plugins, config."""

from __future__ import annotations

import json

from .common import CONFIG, Parser, command


def cmd_plugins(args):
    from ..registry import discover

    reg = discover()
    rows = sorted(reg.components.values(), key=lambda e: (e.kind, e.name))
    print(f"{'kind':<11} {'name':<16} {'distribution':<28} summary")
    for e in rows:
        dist = f"{e.distribution} {e.version}"
        summ = e.cls.summary or (e.cls.__doc__ or "").strip().split("\n")[0]
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
    from ..errors import ConfigError
    from ..pipeline.checks import preflight

    if args.action == "schema":
        print(json.dumps(config_schema(), indent=2))
        return 0
    cfg = load_config(args.file)
    try:
        preflight(cfg)  # what fit checks before its first evaluation, the same code
    except ConfigError as exc:
        raise ConfigError(f"{args.file}: {exc}") from None
    print(
        f"{args.file}: ok (ssm {cfg.ssm.kind}, {len(cfg.ssm.free)} free parameters, "
        f"features {cfg.features.kind}, distance {cfg.distance.kind}, optimizer {cfg.optimizer.kind}, "
        f"executor {cfg.executor.kind})"
    )
    return 0


def add_commands(sub) -> None:
    """Register this group's subcommands."""
    s = command(sub, "plugins", "every discovered plugin, its kind, version, and load errors")
    s.set_defaults(func=cmd_plugins)

    s = command(sub, "config", f"the schema of run configurations, or check one ({CONFIG})")
    cs = s.add_subparsers(dest="action", metavar="ACTION", parser_class=Parser, required=True)
    command(cs, "schema", "print the JSON schema of run configurations")
    c2 = command(cs, "check", "check a run configuration as a fit would before its first evaluation")
    c2.add_argument("file", metavar=CONFIG, help="the run configuration (TOML)")
    s.set_defaults(func=cmd_config)
