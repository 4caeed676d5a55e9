"""How good an optimiser's best point is on model seeds the fit never saw.

A fit with fixed model seeds (common random numbers) keeps the point whose trees, grown with
*those* seeds, score best; part of that best is the seeds' luck (term_noise.py measures how
much). This script takes the best-so-far point of each run of a ``bforest compare`` folder after
given numbers of evaluations and scores it with ``--sets`` other sets of model seeds (each as large
as the fit's), the same sets for every point, so the points are compared on equal terms. It prints
per optimiser and evaluation count the held-out objective (mean over the sets) of each repeat and
their median, beside the fit's own value.

Usage (from the repository root)::

    .venv/bin/python examples/real/heldout_best.py runs/c16 --at 300 600 1800 --sets 16

Several folders of the same recipe and target (e.g. one run at each budget) are read together.
"""
from __future__ import annotations

import argparse
import json
from collections import defaultdict
from pathlib import Path

import numpy as np

import bforest_core as bf
from bforest_core.pipeline.objective import build_target, evaluate_task, spread_seeds, started_workers
from bforest_core.pipeline.store import RunStore

#: seeds of the held-out sets (spread_seeds of this number: distinct from every fit's own seeds)
HELDOUT_SEED = 20261126


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("compare_dirs", type=Path, nargs="+", help="bforest compare folders (runs <optimizer>-<repeat>) "
                    "of one recipe and target")
    ap.add_argument("--at", type=int, nargs="+", default=[600], help="evaluation counts (default 600)")
    ap.add_argument("--sets", type=int, default=8, help="held-out sets of model seeds (default 8)")
    args = ap.parse_args(argv)
    runs = sorted(p for d in args.compare_dirs for p in d.glob("*-*") if (p / "best.json").is_file())
    if not runs:
        raise SystemExit(f"heldout_best: no finished run in {', '.join(map(str, args.compare_dirs))}")
    cfg = bf.load_config(runs[0] / "config.toml")
    per = len(json.loads((runs[0] / "best.json").read_text())["seeds"])
    seeds = spread_seeds(HELDOUT_SEED, args.sets * per)
    sets = [seeds[i * per:(i + 1) * per] for i in range(args.sets)]
    points = []  # (optimizer, repeat, n, params, own distance)
    for run in runs:
        name, rep = run.name.rsplit("-", 1)
        with RunStore.open(run) as store:
            for n in args.at:
                e = store.best(before=n)
                if e is not None and e.status == "ok":  # a grown tree among the first n
                    points.append((name, int(rep), n, e.params, e.distance))
    tgt = build_target(cfg)
    tasks = [(p[3], s) for p in points for s in sets]
    with started_workers(cfg, tgt) as ex:
        res = list(ex.map(evaluate_task, tasks))
    table = defaultdict(list)
    for i, p in enumerate(points):
        rows = res[i * args.sets:(i + 1) * args.sets]
        vals = np.array([r["distance"] if r["status"] == "ok" else np.nan for r in rows])
        table[(p[0], p[2])].append((p[1], p[4], float(np.nanmean(vals)), int(np.isnan(vals).sum())))
    print(f"{', '.join(map(str, args.compare_dirs))}: best point after N evaluations, its own distance -> mean over {args.sets} "
          f"held-out sets of {per} model seeds")
    for (name, n), reps in sorted(table.items()):
        cells = "; ".join(f"repeat {r}: {own:.4f} -> {held:.4f}" + (f" ({bad} failed)" if bad else "")
                          for r, own, held, bad in sorted(reps))
        print(f"{name:<8} N = {n:<5} median held-out {np.median([h for _, _, h, _ in reps]):.4f}  ({cells})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
