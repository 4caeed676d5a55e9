"""`bforest init`: measure a tree and write a ready-to-run recipe for it."""

from __future__ import annotations

from pathlib import Path

from .common import CONFIG, UsageError, command, overwrite_arg


def cmd_init(args):
    from ..pipeline.recipe import measured_lines, not_chosen, write_recipe
    from ..samples import stem

    qsm, tree = args.qsm, stem(args.qsm)
    out = Path(args.output) if args.output else Path(f"{tree}.toml")
    if out.exists() and not args.overwrite:
        raise UsageError(f"{out}: exists; choose another -o, or replace it with --overwrite")
    if args.open_world and args.crown_space:
        raise UsageError("--open-world and --crown-space: choose one (the crown's space is the default)")
    if args.amortised and args.crown_space:
        raise UsageError(
            "--amortised and --crown-space: an estimator's recipe grows in the open world, where its "
            "estimator learnt its trees; drop one of them"
        )
    if args.amortised:
        from ..pipeline.amortised import write_amortised_recipe

        r = write_amortised_recipe(qsm, out, args.amortised, args.model)
    else:
        r = write_recipe(qsm, out, args.model, crown_space=not args.open_world)
    print(f"{qsm}:")
    for line in measured_lines(r.measures):
        print(f"  {line}")
    how = "asked for" if args.model else "the estimator's" if args.amortised else "suits it best"
    print(f"model: {r.model} ({how}): {r.draft.why}")
    for name, suits, why in r.choices:
        if name != r.model:
            print(f"  {not_chosen(name, suits, r.model, r.draft.suits, why)}")
    for note in r.draft.notes:
        print(f"note: {note}")
    print(f"wrote {out}: {len(r.draft.free)} free parameters, bounds scaled to the tree (each line says why)")
    if args.amortised:
        print(
            f"the search starts from the posterior of {args.amortised} and refines it in {r.draft.max_evaluations} evaluations"
        )
    print(f"next: bforest fit {out} -o runs/{tree}")
    return 0


def add_commands(sub):
    s = command(sub, "init", f"measure a tree and write a commented recipe to fit it (a run configuration, {CONFIG})")
    s.add_argument(
        "qsm",
        metavar="QSM",
        help="the tree: a QSM file (TreeQSM .mat/.txt, SimpleForest or aRchi CSV, ...) or sample:NAME (bforest data list)",
    )
    s.add_argument("--model", help="growth model (default: the one that suits the tree, and why)")
    s.add_argument(
        "--amortised",
        metavar="FILE",
        help="start the search from this amortised estimator's posterior for the tree (bforest train's "
        "estimator.npz, or 'shipped' for the model's shipped one) with a short refinement; the model is the estimator's, "
        "and the clones grow in the open world, as the estimator's trees did",
    )
    s.add_argument(
        "--open-world",
        action="store_true",
        help="grow a decurrent or one-sided crown's clones into an open world, as the papers' models do; by "
        "default they grow in the tree's crown space (crown_envelope; docs/growth-forms.md)",
    )
    s.add_argument(
        "--crown-space",
        action="store_true",
        help="the default since 2026-12-07 (kept so that commands written before then still run)",
    )
    s.add_argument(
        "-o", "--output", metavar=CONFIG, help="recipe file to write (default: the QSM's name with .toml, here)"
    )
    overwrite_arg(s, "replace an existing recipe file")
    s.set_defaults(func=cmd_init)
