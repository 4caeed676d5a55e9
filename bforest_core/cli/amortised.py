"""`bforest train` and `bforest posterior`: amortised inference (an estimator trained once per model
and crown form, then a posterior for any tree in seconds)."""

from __future__ import annotations

from .common import CONFIG, UsageError, command, config_arg, count_arg, overwrite_arg, quiet_arg, resume_arg


def cmd_train(args):
    from ..pipeline.train import train

    if args.output is None:
        raise UsageError("give the training folder with -o DIR")
    r = train(args.config, args.output, resume=args.resume, overwrite=args.overwrite, progress=not args.quiet)
    st = ", ".join(f"{k} {v}" for k, v in sorted(r["statuses"].items(), key=lambda kv: -kv[1]))
    print(
        f"simulations: {r['simulations']} drawn ({r['stored_before']} stored before, {r['grown_now']} grown now; {st}) "
        f"in {r['simulation_wall_seconds']:.0f} s"
    )
    members = r["estimator"].get("members", [])
    epochs = ", ".join(str(m["epochs"]) for m in members)
    print(
        f"training: {r['pairs']} trees, {len(members)} flow(s), epochs {epochs}, in {r['training_wall_seconds']:.0f} s"
    )
    print(f"estimator: {r['estimator_file']}")
    print(f"next: bforest posterior QSM --estimator {r['estimator_file']} -o DIR")
    return 0


def cmd_posterior(args):
    from ..pipeline.amortised import posterior_for, warn_lines

    if args.output is None:
        raise UsageError("give the folder to write with -o DIR")
    if args.model is None and args.estimator is None:
        raise UsageError("give --model sot|lignum (its shipped estimator) or --estimator FILE")
    n = 2000 if args.n is None else args.n
    if n < 10:
        raise UsageError(f"-n: at least 10 posterior draws (got {n})")
    if args.clones < 0 or args.clones > n:
        raise UsageError(f"--clones: between 0 and the draws ({n}) (got {args.clones})")
    r = posterior_for(
        args.qsm,
        args.output,
        model=args.model,
        estimator=args.estimator,
        n=n,
        seed=args.seed,
        clones=args.clones,
        overwrite=args.overwrite,
        progress=not args.quiet,
    )
    s, te = r["summary"], r["estimator"]
    warn_lines(s["warnings"])
    print(f"{args.qsm}: {s['height_m']:.2f} m, {s['crown_form']} crown; {te.label()}")
    from ..registry import component

    ssm = component("ssm", te.model)
    print(f"{'parameter':<16}{'unit':<9}{'5 %':>11}{'50 %':>11}{'95 %':>11}   prior")
    for k in s["names"]:
        row, (a, b) = s["posterior_summary"][k], s["prior"][k]
        unit = ssm.parameter_spec(k).unit or "-"
        print(f"{k:<16}{unit:<9}{row['p5']:>11.4g}{row['p50']:>11.4g}{row['p95']:>11.4g}   {a:.4g}-{b:.4g}")
    files = r["files"]
    print(f"posterior: {files.path / files.POSTERIOR_CSV}, {files.path / files.POSTERIOR_NC}, {files.summary_path}")
    print(f"in {r['seconds']:.1f} s ({n} draws, reading the tree included)")
    if not args.no_figure:
        from ..report.posterior import corner_figure

        units = [ssm.parameter_spec(k).unit for k in s["names"]]
        fig = corner_figure(
            r["samples"],
            s["names"],
            files.corner_path,
            bounds=[tuple(s["prior"][k]) for k in s["names"]],
            units=units,
            title=f"{s['tree_name']}: posterior of {te.model} ({te.header['estimator']['kind']} estimator)",
        )
        print(f"figure: {fig}")
    if s["clones"]:
        ok = sum(1 for c in s["clones"] if c["status"] == "ok")
        print(f"clones: {ok} of {len(s['clones'])} grown in {files.clones_dir} (each from its own posterior draw)")
    return 0


def add_commands(sub):
    s = command(sub, "train", "train an amortised estimator of a model's parameters on trees grown from its prior")
    config_arg(s, f"a training configuration ({CONFIG}: [train] model, references, heights, simulations)")
    s.add_argument("-o", "--output", metavar="DIR", help="the training folder to write")
    resume_arg(
        s, "continue the training in -o: stored simulations are kept, the missing ones grown (also to a larger count)"
    )
    overwrite_arg(s, "delete the training in -o (its simulations too) and start anew")
    quiet_arg(s)
    s.set_defaults(func=cmd_train, on_interrupt="every finished simulation is saved; continue with --resume")

    s = command(sub, "posterior", "the posterior of a model's parameters for a tree, from a trained estimator")
    s.add_argument("qsm", metavar="QSM", help="the tree: a QSM file or sample:NAME (bforest data list)")
    s.add_argument("--model", help="the growth model (sot, lignum): its shipped estimator unless --estimator")
    s.add_argument("--estimator", metavar="FILE", help="a trained estimator (bforest train's estimator.npz)")
    s.add_argument("-o", "--output", metavar="DIR", help="the folder to write")
    count_arg(s, "posterior draws (default 2000)")
    s.add_argument("--clones", type=int, default=0, metavar="N", help="posterior-predictive clones to grow (default 0)")
    s.add_argument("--seed", type=int, default=1, help="seeds the draws and the clones (default 1)")
    s.add_argument("--no-figure", action="store_true", help="do not draw the corner plot")
    overwrite_arg(s, "replace a posterior in -o")
    quiet_arg(s)
    s.set_defaults(func=cmd_posterior)
