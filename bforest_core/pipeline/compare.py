"""``bforest compare``: optimisers on equal evaluation budgets, repeated with different seeds."""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..config import load_config, section_settings, with_section
from ..io import write_json
from ..registry import component_class
from .heldout import heldout_mean, point_key, score_points, scoring_fingerprint
from .progress import progress_bar
from .seeds import heldout_seeds, repeat_seeds
from .store import RunDirError, RunFiles, RunStore
from .target import build_target
from .worker import started_workers

if TYPE_CHECKING:
    from ..config import RunConfig


def _run_config(base: RunConfig, name: str, budget: int, seed: int) -> RunConfig:
    """A comparison's run of optimiser ``name``: the base config with its settings (the config's
    own when the config names this optimiser, so the recipe's population, restarts or noise stop
    are what is compared, else its defaults) with its own length limits lifted so that the shared
    evaluation budget ends each run (``Optimizer.budget_settings``), the run seed ``seed``, and no
    ``[select]`` re-scoring: each run's answer is its best own distance."""
    settings = section_settings(base, "optimizer", written=True) if base.optimizer.kind == name else {}
    settings = component_class("optimizer", name).budget_settings(settings, budget)
    cfg = with_section(base, "optimizer", {"kind": name, **settings}, source=f"compare/{name}")
    return cfg.model_copy(
        update={
            "seed": seed,
            "stop": base.stop.model_copy(update={"max_evaluations": budget}),
            "select": base.select.model_copy(update={"top": 0}),
        }
    )


def best_so_far(run_dir: Path) -> np.ndarray:
    """The best distance of a grown tree after each evaluation (inf until the first one): a failed
    simulation's penalty is no fit, as in ``RunStore.best``."""
    with RunStore.open(run_dir) as store:
        evs = store.evaluations()
    return np.minimum.accumulate(np.array([e.distance if e.status == "ok" else np.inf for e in evs], float))


def score_heldout(runs, cfg: RunConfig, target, sets: int, at=(), progress: bool = False) -> tuple[dict, int]:
    """How good each run's best points are on model seeds no fit saw.

    A fit with fixed model seeds keeps the point whose trees, grown with *those* seeds, score
    best; part of that best is the seeds' luck, and an optimiser's long end game buys mostly
    luck. Each run's best point after each ``at`` evaluations, and its final best, is scored with
    ``sets`` held-out sets of model seeds (each as large as the fits' own, from
    :func:`heldout_seeds` of ``cfg``'s seed), the same sets for every point, so points are
    compared on equal terms. A set whose simulation fails scores the objective's penalty, as in a
    fit.

    ``runs`` maps an optimiser's name to its run directories (repeats). Returns the same mapping
    to one dict per run, checkpoint (``"300"``, ..., ``"final"``) -> ``{"evaluations": index of
    the point + 1, "own": the fit's own distance, "heldout": mean over the sets, "failed": failed
    sets}`` (a checkpoint before the run's first grown tree is left out), and the model seeds per
    set. The scores are kept in each run directory (its ``evaluations.sqlite``, for this target,
    model and objective: :mod:`.heldout`): scoring the same points and sets again grows no tree."""
    points = {}  # (name, repeat, checkpoint) -> Evaluation
    for name, dirs in runs.items():
        for r, run in enumerate(dirs):
            with RunStore.open(run) as store:
                for n in [*sorted({int(n) for n in at}), None]:
                    e = store.best(before=n)
                    if e is not None and e.status == "ok":
                        points[(name, r, "final" if n is None else str(n))] = e
    out = {name: [{} for _ in dirs] for name, dirs in runs.items()}
    if not points:
        return out, 0
    per = len(next(iter(points.values())).seeds)
    seed_sets = heldout_seeds(int(cfg.seed), int(sets), per)
    unique = {point_key(e.params): e.params for e in points.values()}  # a point best at several checkpoints: once
    dirs_of = {}  # point key -> the run directories whose best points it is (they keep its scores)
    for (name, r, _), e in points.items():
        dirs_of.setdefault(point_key(e.params), set()).add(Path(runs[name][r]))
    with contextlib.ExitStack() as stack:
        open_ = {d: stack.enter_context(RunStore.open(d)) for ds in dirs_of.values() for d in ds}
        known = score_points(
            unique,
            seed_sets,
            {k: [open_[d] for d in sorted(ds)] for k, ds in dirs_of.items()},
            scoring_fingerprint(cfg),
            lambda: started_workers(cfg, target),
            progress,
        )
    for (name, r, cp), e in points.items():
        h, failed = heldout_mean(known, point_key(e.params), seed_sets)
        out[name][r][cp] = {"evaluations": e.idx + 1, "own": float(e.distance), "heldout": h, "failed": failed}
    return out, per


def heldout_table(
    scores: dict, sets: int, per: int, threshold_name: str | None = None
) -> tuple[list[str], dict, float | None]:
    """The held-out lines of a comparison's table (from :func:`score_heldout`), the medians over
    repeats (optimiser -> checkpoint -> median held-out distance) and the held-out threshold:
    with ``threshold_name`` (one of the optimisers) its median held-out final best, and each
    cell counts the repeats at or below it."""
    cps = sorted(
        {cp for runs in scores.values() for run in runs for cp in run},
        key=lambda c: (c == "final", int(c) if c != "final" else 0),
    )
    medians = {
        name: {
            cp: float(np.median([run[cp]["heldout"] for run in runs if cp in run]))
            for cp in cps
            if any(cp in run for run in runs)
        }
        for name, runs in scores.items()
    }
    threshold = medians.get(threshold_name, {}).get("final")
    lines = [
        f"held out: each run's best point on {sets} sets of {per} model seeds no fit saw (mean distance, "
        "median over repeats)"
    ]
    if threshold is not None:
        lines.append(
            f"threshold {threshold:.4f} ({threshold_name}'s median final); beside each median the "
            "repeats at or below it"
        )
    lines.append(f"{'optimizer':<10}" + "".join(f"{('after ' + c) if c != 'final' else 'final':>17}" for c in cps))
    for name, runs in scores.items():
        cells = []
        for cp in cps:
            vals = [run[cp]["heldout"] for run in runs if cp in run]
            if not vals:
                cells.append(f"{'-':>17}")
                continue
            hit = f" {sum(v <= threshold for v in vals)}/{len(runs)}" if threshold is not None else ""
            cells.append(f"{medians[name][cp]:.4f}{hit}".rjust(17))
        lines.append(f"{name:<10}" + "".join(cells))
    return lines, medians, threshold


def compare(
    config_path,
    optimizers,
    budget: int,
    repeats: int = 3,
    out_dir=None,
    threshold=None,
    progress: bool = False,
    resume: bool = False,
    overwrite: bool = False,
    heldout: int = 0,
    at=(),
) -> dict:
    """Run each optimiser ``repeats`` times with ``budget`` evaluations; returns the table, the
    curves and the figure path.

    A run directory of ``out_dir`` that already exists is an error unless ``resume`` (continue
    it, or read it back when it has finished: a run is named ``<optimizer>-<repeat>`` and its
    config must be the one this comparison would write, so an optimiser can be added to an
    earlier comparison without repeating the others) or ``overwrite`` (start it anew).

    ``threshold`` (the distance for "evaluations to reach") is a number, the name of one of the
    compared optimisers (its median final best: "how soon do the others get where it ends?"),
    or None (5 % above the lower quartile of all final bests).

    ``heldout`` > 0 also scores each run's final best point, and its best after each of ``at``
    evaluations, on that many held-out sets of model seeds (:func:`score_heldout`): the fits' own
    distances include their seeds' luck, the held-out ones are what clones see. With an
    optimiser's name as ``threshold`` the held-out threshold is that optimiser's median held-out
    final best."""
    if isinstance(threshold, str):
        try:
            threshold = float(threshold)
        except ValueError:
            if threshold not in optimizers:
                raise ValueError(
                    f"--threshold {threshold!r} is neither a distance nor one of the compared "
                    f"optimisers ({', '.join(optimizers)})"
                ) from None
    if heldout < 0 or (at and not heldout) or any(int(n) < 1 for n in at):
        raise ValueError(
            f"--heldout {heldout} --at {' '.join(map(str, at))}: --heldout is a number of seed sets "
            "(0: none) and --at, which needs --heldout, numbers of evaluations (1 or more)"
        )
    from .fit import fit, same_config

    base = load_config(config_path)
    out_dir = Path(out_dir) if out_dir else Path("runs") / f"compare-{Path(config_path).stem}"
    out_dir.mkdir(parents=True, exist_ok=True)
    target = build_target(base)
    curves, rows = {}, []
    run_seeds = repeat_seeds(int(base.seed), repeats)
    bar = progress_bar(len(optimizers) * repeats * int(budget), "compare", "eval", progress)
    for name in optimizers:
        curves[name] = []
        for r in range(repeats):
            # the comparison is of the searches (the recipe's [select] re-scoring would replace
            # each run's answer); --heldout scores runs on fresh seeds
            cfg = _run_config(base, name, int(budget), run_seeds[r])
            run = out_dir / f"{name}-{r}"
            state = "new" if overwrite else RunStore.state(run)
            if state != "new" and not resume:
                raise RunDirError(
                    f"{run}: already holds a run; add to this comparison with --resume, replace "
                    "its runs with --overwrite, or choose another -o"
                )
            if state != "new" and not same_config(run, cfg):
                raise RunDirError(
                    f"{run}: was made with another config (or budget); replace it with "
                    "--overwrite, or choose another -o"
                )
            bar.set_postfix_str(
                f"{name} run {r + 1}/{repeats}" + {"finished": " (read back)", "partial": " (resume)"}.get(state, ""),
                refresh=True,
            )
            if state != "finished":
                fit(cfg, run, resume=state == "partial", progress=False, overwrite=overwrite, target=target)
            # the result as the run recorded it (its clock sums the sessions of a resumed run)
            best = RunFiles(run).read_best()
            row = {
                "best": best["distance"],
                "evaluations": best["n_evaluations"],
                "seconds": best["seconds"],
                "stop_reason": best["stop_reason"],
            }
            bar.update(int(budget))  # a run that stopped early still takes its share of the total
            curve = best_so_far(run)
            curves[name].append(curve)
            rows.append({"optimizer": name, "repeat": r, "seed": run_seeds[r], **row})
    bar.close()
    finals = np.array([row["best"] for row in rows])
    threshold_name = None
    if threshold is None:
        threshold = float(np.quantile(finals, 0.25)) * 1.05
    elif isinstance(threshold, str):
        threshold_name = threshold
        threshold = float(np.median([row["best"] for row in rows if row["optimizer"] == threshold]))
    table = []
    for name in optimizers:
        mine = [row for row in rows if row["optimizer"] == name]
        best = np.array([row["best"] for row in mine])
        reach = []
        for c in curves[name]:
            hit = np.flatnonzero(c <= threshold)
            reach.append(int(hit[0]) + 1 if hit.size else None)
        reached = [x for x in reach if x is not None]
        table.append(
            {
                "optimizer": name,
                "median_best": float(np.median(best)),
                "min_best": float(best.min()),
                "max_best": float(best.max()),
                "evals_to_threshold": float(np.median(reached)) if reached else None,
                "reached": f"{len(reached)}/{len(reach)}",
                "median_seconds": float(np.median([row["seconds"] for row in mine])),
            }
        )
    lines = [
        f"budget {budget} evaluations x {repeats} repeats; threshold {threshold:.4f}",
        f"{'optimizer':<10}{'median best':>12}{'range':>20}{'evals to thr.':>15}{'reached':>9}{'wall s':>9}",
    ]
    for t in table:
        e = "-" if t["evals_to_threshold"] is None else f"{t['evals_to_threshold']:.0f}"
        spread = f"[{t['min_best']:.4f}, {t['max_best']:.4f}]"
        lines.append(
            f"{t['optimizer']:<10}{t['median_best']:>12.4f}{spread:>20}"
            f"{e:>15}{t['reached']:>9}{t['median_seconds']:>9.1f}"
        )
    held = {}
    if heldout:
        scores, per = score_heldout(
            {name: [out_dir / f"{name}-{r}" for r in range(repeats)] for name in optimizers},
            base,
            target,
            heldout,
            at,
            progress,
        )
        h_lines, medians, h_thr = heldout_table(scores, heldout, per, threshold_name)
        lines += ["", *h_lines]
        held = {"sets": int(heldout), "model_seeds_per_set": per, "threshold": h_thr}
        for t in table:
            t["heldout"] = medians[t["optimizer"]]
        for row in rows:
            row["heldout"] = scores[row["optimizer"]][row["repeat"]]
    text = "\n".join(lines)
    write_json(
        out_dir / "compare.json",
        {
            "budget": budget,
            "repeats": repeats,
            "threshold": threshold,
            **({"heldout": held} if held else {}),
            "table": table,
            "runs": rows,
        },
    )
    (out_dir / "compare.md").write_text(f"# Optimiser comparison\n\n```\n{text}\n```\n")
    return {
        "table": table,
        "table_text": text,
        "curves": curves,
        "runs": rows,
        "threshold": threshold,
        "heldout": held,
        "out_dir": out_dir,
    }
