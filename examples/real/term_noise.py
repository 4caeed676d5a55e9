"""Seed noise of each objective term at a fitted point: how much of a fit's best is its seeds' luck.

Scores the best parameters of a finished run with one model seed at a time (seeds the fit did not
use), under one or more configs, with the fit's own objective code, and prints per config the mean
and sd of the objective and of each term, and each term's share of the objective's sd.

Usage (from the repository root)::

    .venv/bin/python examples/real/term_noise.py runs/t8 examples/real/pine_lignum.toml [other.toml ...] --seeds 12
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

import bforest_core as bf
from bforest_core.pipeline.target import build_target, term_specs
from bforest_core.pipeline.worker import evaluate_task, init_worker


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("run", type=Path, help="finished run whose best.json gives the parameters")
    ap.add_argument("configs", nargs="+", type=Path, help="configs whose objectives score them")
    ap.add_argument("--seeds", type=int, default=12, help="model seeds, one at a time (from 1000)")
    args = ap.parse_args(argv)
    best_path = args.run / "best.json"
    if not best_path.is_file():
        raise SystemExit(f"term_noise: {best_path} not found (is {args.run} a finished run?)")
    best = json.loads(best_path.read_text())
    params = best["params"]
    print(f"{args.run}: best of the fit {best['distance']:.4f} with its own seeds")
    for path in args.configs:
        cfg = bf.load_config(path)
        tgt = build_target(cfg)
        init_worker(cfg, tgt.U, tgt.columns, tgt.feature_settings, tgt.terms)
        rows = [evaluate_task((params, [s])) for s in range(1000, 1000 + args.seeds)]
        bad = [r["message"] for r in rows if r["status"] != "ok"]
        if bad:
            raise SystemExit(f"term_noise: {path}: {len(bad)} seed(s) failed: {bad[0]}")
        total = np.array([r["distance"] for r in rows])
        weights = {t.name: t.weight for t in term_specs(cfg)}
        parts = [f"objective {total.mean():.4f} ± {total.std(ddof=1):.4f}"]
        for name, w in weights.items():
            v = np.array([r["per_set"].get(f"term:{name}", r["distance"]) for r in rows])
            share = w / sum(weights.values()) * v.std(ddof=1)
            parts.append(f"{name} {v.mean():.4f} ± {v.std(ddof=1):.4f} (in the objective ± {share:.4f})")
        print(f"{path} ({args.seeds} seeds, mean ± sd): " + "; ".join(parts))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
