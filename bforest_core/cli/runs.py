"""Commands that run or read a fit: demo, fit, clones, report, compare, profile, calibrate."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import TYPE_CHECKING

from ..pipeline.rundir import run_lock
from ..pipeline.store import RunFiles, clock_warning
from .common import (
    CONFIG,
    RUN,
    UsageError,
    command,
    config_arg,
    count_arg,
    executor_args,
    executor_spec,
    old_spelling,
    overwrite_arg,
    quiet_arg,
    report,
    resume_arg,
    run_arg,
    run_output,
)

if TYPE_CHECKING:
    from ..config import RunConfig


def cmd_fit(args):
    from ..config import load_config
    from ..pipeline.fit import fit

    cfg = load_config(args.config)
    if args.max_evaluations is not None:
        if args.max_evaluations < 1:
            raise UsageError(f"--max-evaluations must be at least 1 (got {args.max_evaluations})")
        cfg.stop.max_evaluations = args.max_evaluations
    out = Path(args.output) if args.output else Path("runs") / Path(args.config).stem
    with run_lock(out, create=not args.resume):  # the whole command, its report included
        return _fit_and_report(args, cfg, out, fit)


def _fit_and_report(args, cfg: RunConfig, out, fit):
    res = fit(cfg, out, resume=args.resume, progress=not args.quiet, overwrite=args.overwrite)
    if res.already_finished:
        print(
            f"{out}: this run had already finished; nothing was simulated (grow clones with "
            f"'bforest clones {out}', or start anew with --overwrite)"
        )
    print(result_line(res))
    short = (res.diagnostics or {}).get("stopped_short")
    if short:
        print(f"WARNING: the sampler stopped short of its target: {short}")
    clock = clock_warning(RunFiles(out).read_best())
    if clock:
        print(f"WARNING: {clock}")
    for title, names in (("fitted", list(cfg.ssm.free)), ("fixed", [k for k in res.params if k not in cfg.ssm.free])):
        if names:
            print(f"{title}:")
        for k in names:
            v = res.params[k]
            print(f"  {k} = {v:.6g}" if isinstance(v, float) else f"  {k} = {v}")
    print(f"run directory: {out}")
    if cfg.report.enabled and not args.no_report:
        report(out)
    return _all_failed(out)


def result_line(res) -> str:
    """The fit's result in one line. With ``[select]`` the search's best (on its own model seeds,
    where its progress bar ends) and the answer (chosen on held-out seeds) differ: both are named."""
    head = f"after {res.n_evaluations} evaluations ({res.stop_reason})"
    if res.heldout_distance is None:
        return f"best distance {res.distance:.4f} {head}"
    return (
        f"best own {res.best_own:.4f} {head}; answer {res.heldout_distance:.4f} on held-out model seeds "
        f"(evaluation {res.evaluation}, own {res.distance:.4f}; chosen among the search's best on seeds it never used)"
    )


def _all_failed(out) -> int:
    """1 with a loud line when no evaluation of the run succeeded (its "best" fits nothing), else 0."""
    from collections import Counter

    from ..pipeline.store import RunStore

    with RunStore.open(out) as store:
        evs = store.evaluations()
    if not evs or any(e.ok for e in evs):
        return 0
    counts = ", ".join(f"{k} {v}" for k, v in Counter(e.status for e in evs).most_common())
    print(
        f"error: every one of the {len(evs)} evaluations failed ({counts}; the first: {evs[0].message or '-'}); "
        "the parameters above fit nothing: check the model on its own (bforest simulate) and the bounds",
        file=sys.stderr,
    )
    return 1


def cmd_clones(args):
    with run_lock(args.run_dir, create=False):  # the whole command, its report included
        return _clones_and_report(args)


def _clones_and_report(args):
    from ..pipeline.clones import clones

    s = clones(
        args.run_dir,
        n=args.n,
        progress=not args.quiet,
        replace=args.overwrite,
        posterior=args.posterior,
        resume=args.resume,
    )
    where = RunFiles(args.run_dir).clones_dir(args.posterior)
    kept = s["count"] - s["grown"]
    print(
        f"{s['grown']} clones grown, {kept} kept: {s['ok']} of {s['count']} clones ok in {where}"
        + (
            ""
            if s["requested"] >= s["count"]
            else f" (asked for {s['requested']}; nothing is deleted without --overwrite)"
        )
    )
    for key, label, scale in (
        ("distance", "distance D", 1),
        ("height", "height (m)", 1),
        ("girth", "base diameter (m)", 1),
        ("crown_spread", "crown spread (m)", 1),
        ("d_h", "height error (%)", 100),
        ("d_g", "base diam. error (%)", 100),
        ("d_c", "crown error (%)", 100),
    ):
        if key in s:
            v = {k: scale * s[key][k] for k in ("mean", "sd", "min", "max")}
            d = 1 if scale == 100 else 4
            print(f"  {label:<21} mean {v['mean']:.{d}f}  sd {v['sd']:.{d}f}  [{v['min']:.{d}f}, {v['max']:.{d}f}]")
    fid = s.get("fidelity") or {}
    if fid.get("table"):
        print("\nfidelity: the clones against the target on every summary statistic")
        print(fid["text"])
    for r in s.get("references", []):
        print(f"reference {r['file']}: distance to the target {r['distance']:.4f}")
    for r in s.get("reference_errors", []):
        print(f"warning: reference {r['file']} could not be scored: {r['error']}", file=sys.stderr)
    if not args.no_report:
        report(args.run_dir)
    return 0


def _clones_interrupted(args) -> str:
    again = f"bforest clones {args.run_dir} --resume" + (" --posterior" if args.posterior else "")
    return f"finished clones are saved; continue with '{again}'"


def cmd_report(args):
    from ..report.build import write_report
    from ..report.canvas import check_dpi

    check_dpi(args.dpi)  # before the run is read
    p = write_report(args.run_dir, format=args.format, dpi=args.dpi)
    print(f"report: {p}")
    return 0


def cmd_compare(args):
    from ..pipeline.compare import compare

    res = compare(
        args.config,
        optimizers=[o.strip() for o in args.optimizers.split(",") if o.strip()],
        budget=args.budget,
        repeats=args.repeats,
        out_dir=args.output,
        threshold=args.threshold,
        progress=not args.quiet,
        resume=args.resume,
        overwrite=args.overwrite,
        heldout=args.heldout,
        at=args.at,
    )
    from ..report.comparison import write_compare_figure

    print(res["table_text"])
    print(f"figure: {write_compare_figure(res)}")
    return 0


def cmd_profile(args):
    from ..pipeline.profile import profile

    res = profile(args.run_dir, args.param, values=args.values, seeds=args.seeds, n=args.n, progress=not args.quiet)
    from ..report.comparison import write_profile_figure

    print(res["table_text"])
    print(f"figure: {write_profile_figure(res)}")
    return 0


def cmd_calibrate(args):
    from ..report.calibration import write_calibration_figure

    if (args.config is None) == (args.estimator is None):
        raise UsageError("give a sampler's run configuration or --estimator FILE (an amortised estimator), not both")
    if args.estimator is not None:
        from ..pipeline.train import calibrate_estimator

        if args.output is None:
            raise UsageError("give the study folder with -o DIR")
        res = calibrate_estimator(
            args.estimator,
            args.n,
            args.output,
            executor=executor_spec(args),
            seed=1 if args.seed is None else args.seed,
            resume=args.resume,
            overwrite=args.overwrite,
            progress=not args.quiet,
        )
        c = res["counts"]
        print(f"targets: {c['targets']} grown of {c['draws']} prior draws in {res['out_dir']}")
    else:
        if args.seed is not None or executor_spec(args) is not None:
            raise UsageError("--seed and the executor options are for --estimator (a sampler's config has its own)")
        from ..pipeline.calibrate import calibrate

        res = calibrate(
            args.config,
            args.n,
            out_dir=args.output,
            resume=args.resume,
            overwrite=args.overwrite,
            progress=not args.quiet,
        )
        c = res["counts"]
        print(
            f"runs: {c['fitted']} fitted, {c['resumed']} resumed, {c['read back']} read back"
            + (f", {c['failed']} failed" if c["failed"] else "")
            + f" in {res['out_dir']}"
        )
    print(res["table_text"])
    print(f"table: {res['csv']}, {res['json']}")
    print(f"figure: {write_calibration_figure(res)}")
    return 0


def cmd_demo(args):
    from .demo import run_demo

    return run_demo(Path(args.output), quick=args.quick, progress=not args.quiet, overwrite=args.overwrite)


def add_commands(sub) -> None:
    """Register this group's subcommands."""
    s = command(sub, "demo", "the main job on the embedded default target, end to end")
    s.add_argument(
        "-o", "--output", metavar=RUN, default="demo-run", help="the run folder to write (default: demo-run)"
    )
    s.add_argument("--quick", action="store_true", help="a smaller fit (for tests)")
    overwrite_arg(
        s,
        "replace a run in -o that an earlier demo did not write (an earlier demo's is replaced without it)",
    )
    quiet_arg(s)
    s.set_defaults(
        func=cmd_demo,
        on_interrupt=f"finished evaluations are saved; continue its fit with bforest fit {RUN}/{RunFiles.CONFIG} -o {RUN} --resume",
    )

    s = command(sub, "fit", "fit a growth model as a run configuration says")
    config_arg(s)
    run_output(s, "runs/<config name>")
    resume_arg(s, "continue a stopped or killed run in -o")
    overwrite_arg(s, "replace an existing run in -o")
    s.add_argument("--max-evaluations", type=int, metavar="N", help="override [stop] max_evaluations")
    s.add_argument("--no-report", action="store_true", help="do not write the report afterwards")
    quiet_arg(s)
    s.set_defaults(func=cmd_fit, on_interrupt="finished evaluations are saved; continue with --resume")

    s = command(sub, "clones", "clones of a finished fit, with their distances and fidelity table")
    run_arg(s)
    how_many = s.add_mutually_exclusive_group()
    count_arg(
        how_many,
        "clones the set should hold (default: [clones] count); existing clones are kept, only missing ones are grown",
    )
    how_many.add_argument(
        "--resume",
        action="store_true",
        help="continue a stopped clones call: grow the clones it asked for that are missing",
    )
    overwrite_arg(s, "delete the existing clones and grow the set anew")
    old_spelling(s, "--replace", "overwrite", action="store_true")
    s.add_argument(
        "--posterior",
        action="store_true",
        help="posterior-predictive clones (abc-smc or emcee runs): each clone's parameters are one "
        f"draw from {RunFiles.POSTERIOR_CSV}; written to {RUN}/{RunFiles.CLONES_POSTERIOR}",
    )
    s.add_argument("--no-report", action="store_true", help="do not update the report afterwards")
    quiet_arg(s)
    s.set_defaults(func=cmd_clones, on_interrupt=_clones_interrupted)

    s = command(sub, "report", "figures (PNG, SVG or PDF) and a summary (Markdown and HTML) of a run")
    run_arg(s)
    s.add_argument(
        "--format",
        default=None,
        choices=("png", "svg", "pdf"),
        help="format of every figure, kept for the run's later reports (default: the last report's, "
        f"else png; pdf also writes PNG previews for {RunFiles.REPORT_HTML})",
    )
    s.add_argument(
        "--dpi",
        type=int,
        default=None,
        help="resolution of raster figures and of the raster parts of vector ones, kept like --format "
        "(default: the last report's, else 120-130)",
    )
    s.set_defaults(func=cmd_report, on_interrupt="the report is incomplete; run bforest report again")

    s = command(sub, "compare", "compare optimisers on equal evaluation budgets")
    config_arg(s)
    s.add_argument(
        "--optimizers", default="ga,nlopt,emcee,de", help="comma-separated optimiser names (default: ga,nlopt,emcee,de)"
    )
    s.add_argument("--budget", type=int, required=True, metavar="N", help="evaluations per optimiser run")
    s.add_argument(
        "--repeats", type=int, default=3, metavar="N", help="runs per optimiser with different run seeds (default 3)"
    )
    s.add_argument(
        "--threshold",
        default=None,
        help="distance for 'evaluations to reach', or an optimiser's name: its median final best "
        "(default: 5%% above the lower quartile of all final bests)",
    )
    s.add_argument(
        "--heldout",
        type=int,
        default=0,
        metavar="K",
        help="also score each run's best point on K sets of model seeds no fit saw (what clones see; "
        "the fits' own distances include their seeds' luck)",
    )
    s.add_argument(
        "--at",
        type=int,
        nargs="+",
        default=[],
        metavar="N",
        help="with --heldout: also score each run's best after N evaluations",
    )
    s.add_argument("-o", "--output", default=None, metavar="DIR", help="study folder (default: runs/compare-<config>)")
    resume_arg(
        s,
        "continue the runs of an earlier comparison in -o; "
        "finished runs are read back (so another optimiser can be added to it)",
    )
    overwrite_arg(s, "replace the runs of an earlier comparison in -o")
    quiet_arg(s)
    s.set_defaults(func=cmd_compare, on_interrupt="finished runs are saved; continue with --resume")

    s = command(sub, "profile", "distance along one parameter of a fit for several model seeds")
    run_arg(s)
    s.add_argument("--param", required=True, help="the SSM parameter to profile")
    s.add_argument("--values", type=float, nargs="+", default=None, help="values (default: 11 across the bounds)")
    count_arg(s, "number of values across the bounds (default 11)", default=11)
    old_spelling(s, "--n", "n", type=int)
    s.add_argument("--seeds", type=int, default=5, metavar="N", help="model seeds per value (default 5)")
    quiet_arg(s)
    s.set_defaults(func=cmd_profile, on_interrupt="nothing of the profile was written; run it again")

    s = command(
        sub,
        "calibrate",
        "simulation-based calibration: coverage of the sampler's intervals on targets grown from prior draws",
    )
    s.add_argument(
        "config",
        metavar=CONFIG,
        nargs="?",
        help="a run configuration with a sampler (abc-smc, emcee); its [target] is optional and replaced in every run",
    )
    s.add_argument(
        "--estimator",
        metavar="FILE",
        help="calibrate an amortised estimator (bforest train's estimator.npz) instead: targets drawn from its prior",
    )
    count_arg(s, "calibration runs (prior draws, one fit or posterior each)", required=True)
    s.add_argument(
        "-o", "--output", default=None, metavar="DIR", help="study folder (default: runs/calibrate-<config>)"
    )
    s.add_argument("--seed", type=int, help="with --estimator: seeds the targets and the draws (default 1)")
    executor_args(s, "the targets grow (with --estimator)")
    resume_arg(s, "continue a study in -o: finished runs are read back, stopped ones resumed")
    overwrite_arg(s, "refit every run of an earlier study in -o")
    quiet_arg(s)
    s.set_defaults(func=cmd_calibrate, on_interrupt="finished runs are saved; continue with --resume")
