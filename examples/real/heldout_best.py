"""How good an optimiser's best points are on model seeds the fits never saw, across folders.

``bforest compare --heldout K --at N ...`` does this for one comparison folder. This script does
the same (:func:`bforest_core.pipeline.compare.score_heldout`) for several ``bforest compare``
folders of one recipe and target, e.g. one optimiser run at 1 800 evaluations and another at 600,
which one comparison cannot hold (its runs share one budget). The held-out seed sets come from the
first run's seed, the same sets for every point.

Usage (from the repository root)::

    .venv/bin/python examples/real/heldout_best.py runs/p1_ga runs/p1_new --at 300 600 --sets 16 --threshold ga
"""

from __future__ import annotations

import argparse
from collections import defaultdict
from pathlib import Path

import bforest_core as bf
from bforest_core.pipeline.compare import heldout_table, score_heldout
from bforest_core.pipeline.target import build_target


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument(
        "compare_dirs",
        type=Path,
        nargs="+",
        help="bforest compare folders (runs <optimizer>-<repeat>) of one recipe and target",
    )
    ap.add_argument("--at", type=int, nargs="+", default=[], help="also score the best after N evaluations")
    ap.add_argument("--sets", type=int, default=16, help="held-out sets of model seeds (default 16)")
    ap.add_argument(
        "--threshold",
        default=None,
        help="an optimiser's name: count the repeats at or below its median held-out final best",
    )
    args = ap.parse_args(argv)
    runs = defaultdict(list)
    for d in args.compare_dirs:
        for p in sorted(d.glob("*-*")):
            if (p / "best.json").is_file():
                runs[p.name.rsplit("-", 1)[0]].append(p)
    if not runs:
        raise SystemExit(f"heldout_best: no finished run in {', '.join(map(str, args.compare_dirs))}")
    cfg = bf.load_config(next(iter(runs.values()))[0] / "config.toml")
    scores, per = score_heldout(dict(runs), cfg, build_target(cfg), args.sets, args.at, progress=True)
    if args.threshold and args.threshold not in scores:
        raise SystemExit(f"heldout_best: --threshold {args.threshold!r} is not one of {', '.join(scores)}")
    lines, _, _ = heldout_table(scores, args.sets, per, args.threshold)
    print("\n".join(lines))
    for name, reps in scores.items():
        for r, cps in enumerate(reps):
            print(
                f"{name}-{r}: "
                + "; ".join(
                    f"{cp} (evaluation {v['evaluations']}): own {v['own']:.4f}, held out "
                    f"{v['heldout']:.4f}" + (f", {v['failed']} failed" if v["failed"] else "")
                    for cp, v in cps.items()
                )
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
