"""Scores on held-out model seeds: how good a point is on trees no fit saw.

A fit with fixed model seeds keeps the point whose trees, grown with *those* seeds, score best;
part of that best is the seeds' luck (GigaScience 2017 grows its clones with fresh seeds, and so
does :mod:`.clones`). Here a point is grown again with sets of model seeds from a stream of their
own (:func:`~.objective.heldout_seeds`), each set as large as an evaluation's, and scored with the
fit's objective; a set whose simulation fails scores the objective's penalty, as in a fit.

Two users: the end of a fit, which re-scores its best candidates and answers with the best of
them on held-out seeds (:func:`select_answer`, ``[select]`` in the config), and ``bforest compare
--heldout``. The candidates may be scored on other tables than the search's (``[select]
features``/``distance``, :func:`selection_config`): a search wants a smooth objective (pooled
sets, fewer projection lines), the answer the tables its clones are judged by. Every score is
written to the run's ``evaluations.sqlite`` (table ``heldout``) as soon as it is known, keyed
by what it depends on (:func:`scoring_fingerprint`), so a killed scoring loses nothing and no
tree is grown twice.

``[select] sizes`` holds the answer to the sizes a forester checks: the held-out trees are
measured as the clones' fidelity table measures them, and the candidates whose trees keep, on
average, within every given relative error of the tree's come first (:func:`size_errors`). The
mean of a candidate's 16 held-out trees is what its clones' mean will be, within a few percent:
the search's own distance, on one model seed an evaluation, is not.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import warnings
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from ..config import config_to_dict, selection_config
from ..errors import ConfigError
from .fidelity import finite_means
from .progress import progress_bar
from .scoring import mean_per_set
from .seeds import heldout_seeds
from .store import Evaluation, RunStore
from .target import size_topology
from .worker import heldout_task

if TYPE_CHECKING:
    from ..config import RunConfig

__all__ = [
    "scoring_fingerprint",
    "point_key",
    "score_points",
    "heldout_mean",
    "heldout_parts",
    "heldout_sizes",
    "target_sizes",
    "size_errors",
    "candidates",
    "select_answer",
]


def scoring_fingerprint(cfg: RunConfig) -> str:
    """What a held-out score depends on besides the point and the seeds: the target, the model
    and the objective (not the optimiser, the budget, the run seed or the executor)."""
    raw = config_to_dict(cfg)
    part = {k: raw.get(k) for k in ("target", "ssm", "features", "distance", "objective")}
    return hashlib.sha256(json.dumps(part, sort_keys=True, default=str).encode()).hexdigest()[:16]


def point_key(params: dict) -> str:
    """A point as text: the key of its held-out scores."""
    return json.dumps(params, sort_keys=True)


def _seeds_key(seeds) -> str:
    return json.dumps([int(s) for s in seeds])


def score_points(
    points: dict[str, dict],
    seed_sets: list[list[int]],
    stores: dict[str, list[RunStore]],
    scoring: str,
    workers: Callable[[], contextlib.AbstractContextManager],
    progress: bool = False,
    measure: tuple[str, ...] = (),
) -> dict[tuple[str, tuple], dict]:
    """The held-out score of every point on every seed set.

    Parameters
    ----------
    points : dict
        Point key (:func:`point_key`) -> parameters.
    seed_sets : list of list of int
        The held-out model seeds, one list per set.
    stores : dict
        Point key -> the open run stores that keep its scores (read first, written as each
        score arrives; a timeout is not kept: it is the machine's load, not the point's).
    scoring : str
        :func:`scoring_fingerprint` of the config.
    workers : callable
        Returns a context manager giving an executor; entered only when a tree must be grown.
    measure : tuple of str
        Statistics to measure on every grown set's trees (:func:`~.worker.heldout_task`); a kept
        score that lacks one of them is grown again.

    Returns
    -------
    dict
        ``(point key, tuple of seeds)`` -> ``{"distance", "status", "per_set", "sizes"}`` (the
        distance per set and, with several terms, per ``term:<name>``; None for a score an older
        run kept; ``sizes``: the trees' mean of each measured statistic, or None).
    """
    kept = {id(s): s.heldout_scores(scoring) for ss in stores.values() for s in ss}
    known, tasks = {}, []
    for k in points:
        for seeds in seed_sets:
            sk = _seeds_key(seeds)
            hit = next((kept[id(s)][(k, sk)] for s in stores[k] if (k, sk) in kept[id(s)]), None)
            if hit is not None and measure and hit["status"] == "ok" and not set(measure) <= set(hit["sizes"] or ()):
                hit = None  # kept before these statistics were asked for
            if hit is None:
                tasks.append((k, seeds))
            else:
                known[(k, tuple(seeds))] = hit
    if tasks:
        bar = progress_bar(len(tasks), "held out", "eval", progress)
        try:
            with workers() as ex:
                for i, r in ex.map_unordered(heldout_task, [(points[k], s, measure) for k, s in tasks]):
                    k, seeds = tasks[i]
                    hit = {
                        "distance": float(r["distance"]),
                        "status": r["status"],
                        "per_set": r["per_set"],
                        "sizes": r.get("sizes"),
                    }
                    known[(k, tuple(seeds))] = hit
                    if hit["status"] != "timeout":
                        for s in stores[k]:
                            s.add_heldout(scoring, k, _seeds_key(seeds), **hit)
                    bar.update(1)
        finally:
            bar.close()
    return known


def heldout_mean(known: dict, key: str, seed_sets) -> tuple[float, int]:
    """Mean held-out distance of one point over the sets, and how many sets failed."""
    rows = [known[(key, tuple(s))] for s in seed_sets]
    return float(np.mean([r["distance"] for r in rows])), sum(r["status"] != "ok" for r in rows)


def heldout_parts(known: dict, key: str, seed_sets) -> dict[str, float] | None:
    """Mean held-out distance of one point per set and per ``term:<name>`` over the sets that grew
    (a failed set has none: it counts in :func:`heldout_mean` at the penalty), as
    :func:`~.scoring.mean_per_set`; None when no grown set kept them (scores of an older run) — so
    a reader sees which term set a candidate apart."""
    parts = [r["per_set"] for s in seed_sets if (r := known[(key, tuple(s))])["status"] == "ok" and r["per_set"]]
    return mean_per_set(parts) if parts else None


def target_sizes(cfg: RunConfig, tree) -> dict[str, float]:
    """The tree's value of each statistic of ``[select] sizes``, measured as the clones' fidelity
    table measures the target (a statistic the tree has no value of, such as the DBH of a tree
    shorter than 1.3 m, is left out: nothing to hold it to). ``ConfigError`` for a name the
    fidelity table does not know."""
    from ..attributes import fidelity_statistics

    if not cfg.select.sizes:
        return {}
    have = fidelity_statistics(tree, *size_topology(cfg, "target"))
    unknown = sorted(set(cfg.select.sizes) - set(have))
    if unknown:
        raise ConfigError(
            f"select.sizes: no statistic {', '.join(map(repr, unknown))} in the clones' fidelity table "
            f"(it has: {', '.join(sorted(have))})"
        )
    return {k: float(have[k]) for k in cfg.select.sizes if np.isfinite(have[k]) and have[k] != 0}


def size_errors(sizes: dict | None, target: dict[str, float]) -> dict[str, float] | None:
    """Relative error of each measured mean from the tree's value (None when not measured)."""
    if sizes is None:
        return None
    return {k: float(sizes[k]) / v - 1.0 for k, v in target.items()}


def heldout_sizes(known: dict, key: str, seed_sets, names) -> dict[str, float] | None:
    """The mean of each statistic over the sets that grew, of the values a set has
    (:func:`~.fidelity.finite_means`; None when none grew)."""
    rows = [r["sizes"] for s in seed_sets if (r := known[(key, tuple(s))])["status"] == "ok" and r.get("sizes")]
    return finite_means(rows, names) if rows else None


def candidates(evaluations: list[Evaluation], top: int, lower, upper, names, spacing: float) -> list[Evaluation]:
    """The ``top`` best grown points of a log, best first, each at least ``spacing`` (a fraction of
    every parameter's range, in the largest coordinate) from those kept before it: distinct
    points, not the many near-copies a converged search leaves around its best."""
    lo, width = np.asarray(lower, float), np.maximum(np.asarray(upper, float) - np.asarray(lower, float), 1e-300)
    ok = sorted((e for e in evaluations if e.status == "ok"), key=lambda e: (e.distance, e.idx))
    kept, xs = [], []
    for e in ok:
        x = (np.array([float(e.params[n]) for n in names]) - lo) / width
        if all(np.max(np.abs(x - y)) > spacing for y in xs):
            kept.append(e)
            xs.append(x)
            if len(kept) == top:
                break
    return kept


def select_answer(cfg: RunConfig, store: RunStore, workers, progress: bool = False, tree=None) -> dict | None:
    """The answer of a fit chosen on held-out seeds (``[select]``; None when ``top = 0``).

    The ``top`` best distinct points of the log are each scored on ``sets`` sets of held-out
    model seeds with :func:`selection_config`'s objective; the answer is the one of lowest mean
    held-out distance (ties: the lower own distance). With ``[select] sizes`` the held-out trees
    are measured too (``tree``: the target's tree, :func:`target_sizes`), and the candidates whose
    trees' means keep within every size's relative error come first; when none does, the answer
    is the lowest of all and the fit warns. ``workers`` returns a context manager giving an
    executor started on that config's scoring, entered only when a tree must be grown. Returns
    ``{"sets", "model_seeds_per_set", "spacing", "scored_by", "sizes", "chosen": evaluation index,
    "candidates": [{"evaluation", "params", "own", "heldout", "failed", "timeouts", "heldout_per_set",
    "size_errors", "within"}, ...]}``, candidates in the order of their own distance
    (``heldout_per_set``: :func:`heldout_parts`; ``size_errors``: the held-out trees' mean
    relative error of each size, :func:`size_errors`; ``within``: all of them within ``[select]
    sizes``); ``sizes`` is ``{"limits", "target"}`` or None; ``scored_by`` is None for the search's
    own objective, else ``[select]``'s ``{"features", "distance"}`` settings.
    """
    sel = cfg.select
    if not sel.top:
        return None
    names = list(cfg.ssm.free)
    lower = [cfg.ssm.free[n].lower for n in names]
    upper = [cfg.ssm.free[n].upper for n in names]
    cands = candidates(store.evaluations(), sel.top, lower, upper, names, sel.spacing)
    if not cands:
        return None
    per = len(cands[0].seeds)
    seed_sets = heldout_seeds(int(cfg.seed), int(sel.sets), per)
    points = {point_key(e.params): e.params for e in cands}
    scfg = selection_config(cfg)
    target = target_sizes(cfg, tree) if sel.sizes else {}
    measure = tuple(target)
    known = score_points(
        points, seed_sets, {k: [store] for k in points}, scoring_fingerprint(scfg), workers, progress, measure
    )
    rows = []
    for e in cands:
        key = point_key(e.params)
        h, failed = heldout_mean(known, key, seed_sets)
        errors = size_errors(heldout_sizes(known, key, seed_sets, measure), target) if measure else None
        rows.append(
            {
                "evaluation": e.idx,
                "params": e.params,
                "own": float(e.distance),
                "heldout": h,
                "failed": failed,
                "timeouts": sum(known[(key, tuple(s))]["status"] == "timeout" for s in seed_sets),
                "heldout_per_set": heldout_parts(known, key, seed_sets),
                "size_errors": errors,
                "within": errors is not None and all(abs(errors[k]) <= sel.sizes[k] for k in errors),
            }
        )
    # candidates within the sizes first (without sizes none is: the lowest held-out of all)
    best = min(rows, key=lambda r: (not r["within"], r["heldout"], r["own"], r["evaluation"]))
    if measure and not best["within"]:
        warnings.warn(
            f"none of the {len(rows)} candidates' held-out trees kept within [select] sizes "
            f"({', '.join(f'{k} {100 * v:g} %' for k, v in sel.sizes.items())}): the answer is the lowest "
            "held-out distance of all; see the fidelity table of its clones",
            UserWarning,
            stacklevel=2,
        )
    return {
        "sets": int(sel.sets),
        "model_seeds_per_set": per,
        "spacing": float(sel.spacing),
        "scored_by": None
        if scfg is cfg
        else {"features": dict(sel.features or {}), "distance": dict(sel.distance or {})},
        "sizes": {"limits": dict(sel.sizes), "target": target} if measure else None,
        "chosen": best["evaluation"],
        "candidates": rows,
    }
