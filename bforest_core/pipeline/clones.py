"""Morphological clones (paper stage B5): the best-fit SSM run with fresh seeds."""
from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from ..config import load_config
from ..errors import SimulationFailed
from .objective import _CTX, build_target, clone_seeds, combine_terms, progress_bar, score_tree, started_workers, with_term_values
from .store import RunStore

METRIC_KEYS = ("height", "girth", "crown_spread")


def _clone_task(task):
    """Grow one clone in a worker, write it, and score it against the target."""
    from ..io import write_tree
    from ..metrics import classical_metrics
    i, params, seed, out_dir = task
    c = _CTX
    try:
        tree = c["ssm"].simulate(params, seed)
    except SimulationFailed as exc:
        return dict(index=i, seed=seed, status=exc.status, message=str(exc))
    path = Path(out_dir) / f"clone_{i:03d}.txt"
    write_tree(tree, path)
    per_set, _ = score_tree(tree)
    total, values = combine_terms(per_set)
    return dict(index=i, seed=seed, status="ok", message="", file=path.name, distance=total,
                per_set=with_term_values(per_set, values), n_cylinders=tree.n, **classical_metrics(tree))


def clones(run_dir, n: int | None = None, executor=None, progress: bool = True) -> dict:
    """Grow ``n`` clones of a finished fit; writes ``clones/clone_NNN.txt``, ``clones/clones.csv``
    and ``clones/summary.json``. Returns the summary."""
    from ..metrics import relative_errors
    run_dir = Path(run_dir)
    store = RunStore.open(run_dir)
    cfg = load_config(store.config_path)
    best = store.read_json("best.json")
    n = cfg.clones.count if n is None else int(n)
    tgt = build_target(cfg)
    tm = best.get("target_metrics")
    seeds = clone_seeds(cfg.seed, n, cfg.clones.seed)
    out_dir = run_dir / "clones"
    out_dir.mkdir(exist_ok=True)
    for old in out_dir.glob("clone_*.txt"):
        old.unlink()
    tasks = [(i, best["params"], s, str(out_dir)) for i, s in enumerate(seeds)]
    rows = [None] * n
    bar = progress_bar(n, "clones", "clone", progress)
    with started_workers(cfg, tgt, executor) as ex:
        for j, res in ex.map_unordered(_clone_task, tasks):
            if res["status"] == "ok":
                res.update(relative_errors(tm, {k: res[k] for k in METRIC_KEYS}))
            rows[j] = res
            bar.update(1)
    bar.close()
    set_names = list(tgt.U) + ([f"term:{t['name']}" for t in tgt.terms] if len(tgt.terms or []) > 1 else [])
    cols = ["index", "seed", "status", "file", "distance"] + [f"D[{s}]" for s in set_names] + \
        ["n_cylinders", "height", "girth", "crown_spread", "d_h", "d_g", "d_c"]
    with open(out_dir / "clones.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(cols)
        for r in rows:
            w.writerow([r.get("index"), r.get("seed"), r.get("status"), r.get("file", ""), r.get("distance", "")]
                       + [(r.get("per_set") or {}).get(s, "") for s in set_names]
                       + [r.get(k, "") for k in cols[-7:]])
    ok = [r for r in rows if r["status"] == "ok"]
    summary = {"count": n, "ok": len(ok), "failed": n - len(ok), "target_metrics": tm,
               "best_params": best["params"], "fit_distance": best["distance"]}
    for key in ["distance", "height", "girth", "crown_spread", "d_h", "d_g", "d_c"]:
        vals = np.array([r[key] for r in ok if r.get(key) is not None and np.isfinite(r[key])], float)
        if vals.size:
            summary[key] = {"mean": float(vals.mean()), "sd": float(vals.std(ddof=1)) if vals.size > 1 else 0.0,
                            "median": float(np.median(vals)), "min": float(vals.min()), "max": float(vals.max())}
    for s in set_names:
        vals = np.array([r["per_set"][s] for r in ok if r["per_set"].get(s) is not None], float)
        if vals.size:
            summary[f"D[{s}]"] = {"mean": float(vals.mean()), "median": float(np.median(vals))}
    summary["rows"] = rows
    store.write_json("clones/summary.json", summary)
    return summary
