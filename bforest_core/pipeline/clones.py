"""Morphological clones (paper stage B5): the best-fit SSM run with fresh seeds.

Clone ``i`` always has the same seed (``clone_seeds`` spawns one child seed per index), so a set
of clones can grow: asking for more clones than exist grows only the missing ones, asking for
fewer deletes nothing. Regrowing an existing set needs ``replace=True``. Clones of other
parameters (a fit resumed to a different best) are never mixed into a set.

Posterior-predictive clones (``posterior=True``, a sampler's run: ``abc-smc``, ``emcee``) go to a
set of their own, ``clones_posterior/``: clone ``i`` draws its parameter vector from the run's
``posterior.csv`` by weight, with a generator seeded by its own clone seed, so the set carries
the parameter uncertainty and still grows reproducibly.
"""

from __future__ import annotations

import csv
import shutil
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..config import load_config
from ..errors import BayesForestError, SimulationFailed
from ..interfaces import parameter_value
from ..io import whole_file
from .fidelity import bound_flags, fidelity_table, fidelity_text, fidelity_warnings
from .interrupts import stoppable
from .progress import progress_bar
from .rundir import holding_run_lock
from .scoring import (
    _MODEL_ERRORS,
    _simulate_with_timeout,
    _Timeout,
    combine_terms,
    fault_message,
    score_tree,
    with_term_values,
)
from .seeds import clone_seeds
from .store import RunFiles, RunStore
from .target import build_target, size_topology
from .worker import started_workers, worker_context

if TYPE_CHECKING:
    from ..config import RunConfig

METRIC_KEYS = ("height", "girth", "crown_spread")
#: clones.csv column of each per-clone value (units in the header; girth is the base diameter)
CSV_COLUMNS = {
    "n_cylinders": "n_cylinders",
    "height": "height_m",
    "girth": "base_diameter_m",
    "dbh": "dbh_m",
    "crown_spread": "crown_spread_m",
    "d_h": "d_h",
    "d_g": "d_g",
    "d_c": "d_c",
}


class ClonesError(BayesForestError):
    """The clones folder cannot take the requested clones (e.g. other parameters)."""


def _clone_task(task):
    """Grow one clone in a worker, write it, and score it against the target."""
    from ..attributes import fidelity_statistics
    from ..io import write_tree
    from ..metrics import classical_metrics

    i, params, seed, out_dir = task
    c = worker_context()
    try:
        tree = _simulate_with_timeout(c.ssm, params, seed, c.timeout, c.prune_radius)
    except SimulationFailed as exc:
        return dict(index=i, seed=seed, status=exc.status, message=str(exc), params=params)
    except _Timeout:
        return dict(index=i, seed=seed, status="timeout", message=f"simulation exceeded {c.timeout} s", params=params)
    except _MODEL_ERRORS as exc:
        return dict(index=i, seed=seed, status="error", message=fault_message(exc), params=params)
    path = Path(out_dir) / f"clone_{i:03d}.txt"
    write_tree(tree, path)
    per_set, _ = score_tree(tree, c)
    total, values = combine_terms(per_set, c)
    return dict(
        index=i,
        seed=seed,
        status="ok",
        message="",
        file=path.name,
        distance=total,
        per_set=with_term_values(per_set, values),
        n_cylinders=tree.n,
        summary=fidelity_statistics(tree, *c.size_topology),
        params=params,
        **classical_metrics(tree),
    )


def _lost_clone(task, status, message):
    """The row of a clone whose worker died or was stopped (the process executor's stand-in)."""
    i, params, seed, _ = task
    return dict(index=i, seed=seed, status=status, message=message, params=params)


_clone_task.lost_result = _lost_clone


def _reference_task(task):
    """Score a reference tree of the stand against the target, like a clone."""
    from ..attributes import fidelity_statistics
    from ..io import read_tree

    path = task
    tree = read_tree(path)
    c = worker_context()
    per_set, _ = score_tree(tree, c)
    total, values = combine_terms(per_set, c)
    return dict(
        file=str(path),
        distance=total,
        per_set=with_term_values(per_set, values),
        summary=fidelity_statistics(tree, *c.size_topology),
    )


def posterior_draw(run_dir: Path, base: dict, seed: int) -> dict:
    """The parameters of one posterior-predictive clone: ``base`` (the best fit, for the fixed
    parameters) with the fitted ones drawn from ``posterior.csv`` by weight."""
    path = RunFiles(run_dir).posterior_csv_path
    if not path.exists():
        raise ClonesError(
            f"{run_dir}: no {path.name}; posterior clones need a sampler's run (optimizer kind abc-smc or emcee)"
        )
    with path.open(newline="", encoding="utf-8") as fh:
        rows = list(csv.reader(fh))
    names, data = rows[0][:-1], np.array(rows[1:], float)
    w = data[:, -1] / data[:, -1].sum()
    k = int(np.random.default_rng(seed).choice(len(w), p=w))
    out = dict(base)
    for j, name in enumerate(names):
        v = float(data[k, j])
        out[name] = parameter_value(v, isinstance(base.get(name), int))
    return out


def _existing(out_dir: Path, store: RunStore, params: dict) -> list[dict]:
    """The rows of the clones already in ``out_dir`` (checked to be clones of ``params``)."""
    if not (out_dir / RunFiles.CLONE_SUMMARY).exists():
        if any(out_dir.glob("clone_*.txt")):
            raise ClonesError(
                f"{out_dir}: holds clone files but no {RunFiles.CLONE_SUMMARY}; regrow them with --overwrite, "
                "or move the folder to keep them"
            )
        return []
    old = store.read_json(f"{out_dir.name}/{RunFiles.CLONE_SUMMARY}")
    if old.get("best_params") != params:
        raise ClonesError(
            f"{out_dir}: holds clones of other parameters ({old.get('best_params')}); "
            "regrow them with --overwrite, or move the folder to keep them"
        )
    return [r for r in old.get("rows", []) if (out_dir / r.get("file", "-")).exists() or r.get("status") != "ok"]


@stoppable
@holding_run_lock
def clones(
    run_dir,
    n: int | None = None,
    executor=None,
    progress: bool = True,
    replace: bool = False,
    posterior: bool = False,
    resume: bool = False,
) -> dict:
    """Grow clones of a finished fit until the set holds ``n``; writes ``clones/clone_NNN.txt``,
    ``clones/clones.csv``, ``clones/summary.json`` and ``clones/fidelity.json``.

    Parameters
    ----------
    run_dir : path
        A finished fit.
    n : int, optional
        Clones the set should hold (default ``[clones] count``). Existing clones are kept; only
        the missing ones are grown.
    replace : bool
        Delete the existing clones first and grow ``n`` anew.
    resume : bool
        Continue the last call on this set (one that was stopped): ``n`` is the count that call
        asked for (giving ``n`` too is an error).
    posterior : bool
        Posterior-predictive clones in ``clones_posterior/``: each clone's parameters are one
        draw from the run's posterior (see the module text).

    Returns
    -------
    dict
        The summary (also in ``clones/summary.json``): counts, per-measure statistics,
        ``grown`` (clones grown by this call), ``fidelity`` (table, flags, warnings) and
        ``references``.
    """
    run_dir = Path(run_dir)
    with RunStore.open(run_dir) as store:
        cfg = load_config(store.config_path)
        best = store.read_best()
        out_dir = store.clones_dir(posterior)
        if resume:
            n = _stopped_request(store, out_dir, n, replace)
        n = cfg.clones.count if n is None else int(n)
        if n < 0:
            raise ClonesError(f"clones: n must be at least 0 (got {n})")
        if replace and out_dir.exists():
            shutil.rmtree(out_dir)
        out_dir.mkdir(exist_ok=True)
        rows = sorted(_existing(out_dir, store, best["params"]), key=lambda r: r["index"])
        have = {int(r["index"]) for r in rows}
        want = [i for i in range(max(n, 0)) if i not in have]
        tgt = build_target(cfg)
        tm = best.get("target_metrics")
        seeds = clone_seeds(cfg.seed, max(n, len(rows)), cfg.clones.seed)
        tasks = [
            (
                i,
                posterior_draw(run_dir, best["params"], seeds[i]) if posterior else best["params"],
                seeds[i],
                str(out_dir),
            )
            for i in want
        ]
        refs = list(cfg.target.references)
        new_rows, references, ref_errors = [], [], []
        if tasks or refs:
            # written before the first clone and after each one: a killed call is continued by the
            # next, which keeps every clone listed here and grows only the others
            _write_progress(store, out_dir, rows, tgt, best, tm, n)
            bar = progress_bar(len(tasks), "clones", "clone", progress and bool(tasks))
            with started_workers(cfg, tgt, executor) as ex:
                for _, res in ex.map_unordered(_clone_task, tasks):
                    if res["status"] == "ok":
                        from ..metrics import relative_errors

                        res.update(relative_errors(tm, {k: res[k] for k in METRIC_KEYS}))
                    new_rows.append(res)
                    _write_progress(store, out_dir, rows + new_rows, tgt, best, tm, n)
                    bar.update(1)
                bar.close()
                for r in refs:
                    try:
                        references.append(ex.map(_reference_task, [r])[0])
                    except (BayesForestError, OSError) as exc:  # one bad reference file loses nothing else
                        ref_errors.append({"file": str(r), "error": f"{type(exc).__name__}: {exc}"})
        rows = sorted(rows + new_rows, key=lambda r: r["index"])
        summary = _summarise(rows, tgt, best, tm)
        summary["grown"] = len(new_rows)
        summary["requested"] = n
        summary["fidelity"] = _fidelity(cfg, tgt, best, rows)
        summary["references"] = references
        summary["reference_errors"] = ref_errors
        summary["posterior"] = bool(posterior)
        summary["complete"] = True
        _write_csv(out_dir / RunFiles.CLONE_TABLE, rows, tgt)
        store.write_json(f"{out_dir.name}/{RunFiles.CLONE_FIDELITY}", summary["fidelity"])
        store.write_json(f"{out_dir.name}/{RunFiles.CLONE_SUMMARY}", summary)
        return summary


def _stopped_request(store: RunStore, out_dir: Path, n, replace: bool) -> int:
    """The count the last call on ``out_dir`` asked for (what ``resume`` continues)."""
    if n is not None or replace:
        raise ClonesError("clones: resume continues the count the last call asked for: give it without n or replace")
    if not (out_dir / RunFiles.CLONE_SUMMARY).exists():
        raise ClonesError(f"{out_dir}: no clones call to resume; grow clones with 'bforest clones {store.path} -n N'")
    last = store.read_json(f"{out_dir.name}/{RunFiles.CLONE_SUMMARY}")
    return int(last.get("requested", last.get("count", 0)))


def _write_progress(store: RunStore, out_dir: Path, rows, tgt, best, tm, requested: int) -> None:
    """``summary.json`` of the clones grown so far (``complete`` false until the call ends) and
    the count the call asked for (what ``resume`` continues)."""
    summary = _summarise(sorted(rows, key=lambda r: r["index"]), tgt, best, tm)
    summary["complete"] = False
    summary["requested"] = requested
    store.write_json(f"{out_dir.name}/{RunFiles.CLONE_SUMMARY}", summary)


def _fidelity(cfg: RunConfig, tgt, best, rows) -> dict:
    from ..attributes import fidelity_statistics
    from ..metrics import SUMMARY_UNITS

    target = fidelity_statistics(tgt.trees[0], *size_topology(cfg, "target"))
    ok = [r["summary"] for r in rows if r.get("status") == "ok" and r.get("summary")]
    table = fidelity_table(target, ok, SUMMARY_UNITS)
    bounds = {k: (fp.lower, fp.upper) for k, fp in cfg.ssm.free.items()}
    flags = bound_flags(best["params"], bounds)
    warns = fidelity_warnings(table)
    return {"table": table, "flags": flags, "warnings": warns, "text": fidelity_text(table, flags, warns)}


def _summarise(rows, tgt, best, tm) -> dict:
    ok = [r for r in rows if r["status"] == "ok"]
    summary = {
        "count": len(rows),
        "ok": len(ok),
        "failed": len(rows) - len(ok),
        "target_metrics": tm,
        "best_params": best["params"],
        "fit_distance": best["distance"],
    }
    for key in ["distance", "height", "girth", "crown_spread", "d_h", "d_g", "d_c"]:
        vals = np.array([r[key] for r in ok if r.get(key) is not None and np.isfinite(r[key])], float)
        if vals.size:
            summary[key] = {
                "mean": float(vals.mean()),
                "sd": float(vals.std(ddof=1)) if vals.size > 1 else 0.0,
                "median": float(np.median(vals)),
                "min": float(vals.min()),
                "max": float(vals.max()),
            }
    for s in _set_columns(tgt):
        vals = np.array([r["per_set"][s] for r in ok if r["per_set"].get(s) is not None], float)
        if vals.size:
            summary[f"D[{s}]"] = {"mean": float(vals.mean()), "median": float(np.median(vals))}
    summary["rows"] = rows
    return summary


def _set_columns(tgt) -> list[str]:
    return list(tgt.U) + ([f"term:{t.name}" for t in tgt.terms] if len(tgt.terms or []) > 1 else [])


def _write_csv(path: Path, rows, tgt) -> None:
    sets = _set_columns(tgt)
    header = ["index", "seed", "status", "file", "distance"] + [f"D[{s}]" for s in sets] + list(CSV_COLUMNS.values())
    with whole_file(path) as part, open(part, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        for r in rows:
            w.writerow(
                [r.get("index"), r.get("seed"), r.get("status"), r.get("file", ""), r.get("distance", "")]
                + [(r.get("per_set") or {}).get(s, "") for s in sets]
                + [r.get(k, "") for k in CSV_COLUMNS]
            )
