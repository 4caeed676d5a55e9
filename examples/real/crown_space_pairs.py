"""Clones are still clones: the judge between pairs of clones grown with and without the crown's space.

The crown's space (docs/growth-forms.md) shapes a crown; the model must still grow the branches,
so that two clones differ from each other as much as clones grown in the open world do. For each
fit whose model grew its clones in the crown's space (``envelope_shade`` > 0 with a
``crown_envelope``), the script grows its clones again with the same parameters and model seeds
but every crown-space form off (``envelope_shade``, ``side_shade`` and ``space_claim`` 0: the open
world; the stem still along the tree's where the recipe guides it) and takes the fixed judge of run_fidelity.py (S¹ and
B¹, sliced KS, z-score, 256 gp2 lines, subtree topology) between pairs of clones of each set:
clone i against clone j (normalised on j), every pair of the first ``--clones`` of the set. If
the envelope made the clones copies of one tree, its pairs would lie far nearer one another than
the open world's. Beside the pairs: each set's judge against the tree (the median over its
clones) and its crowns' offset from their stems (the mean vector, crown radii, and its
direction), against the tree's. ``--against RUN`` adds the clones of another fit (the recipe
without the crown's space) as a third set.

Usage (from the repository root; the runs of ``run_broadleaved.py``)::

    .venv/bin/python examples/real/crown_space_pairs.py runs/env/wytham_tf5_seed1 [RUN ...] [--clones 12] [--against RUN2] [--out pairs.json]

Each run's numbers are printed and written to ``--out`` (JSON); ``--figures DIR`` draws the tree
beside 5 clones of each set, the crown's space dashed.
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
import warnings
from pathlib import Path

import numpy as np

import bforest_core as bf
from bforest_core.config import build_component
from bforest_core.metrics import crown_offset
from bforest_core.pipeline.scoring import grow_tree
from bforest_core.pipeline.target import load_target_trees
from bforest_core.report.trees import clones_figure

sys.path.insert(0, str(Path(__file__).resolve().parent))
from run_fidelity import judge_distance  # noqa: E402  (the same judge)


def clone_set(run: Path) -> tuple[list, list[int]]:
    """The clones a run grew (``bforest clones``: clones/summary.json), in order, and their seeds."""
    summary = json.loads((run / "clones" / "summary.json").read_text())
    ok = [r for r in summary["rows"] if r["status"] == "ok"]
    return [bf.read_qsm(run / "clones" / r["file"]) for r in ok], [int(r["seed"]) for r in ok]


def pairs_judge(trees: list) -> np.ndarray:
    """The judge of clone i against clone j for every pair i < j."""
    return np.array([judge_distance(a, b) for a, b in itertools.combinations(trees, 2)])


def describe(name: str, trees: list, target) -> dict:
    """A set's pairs, its judge against the tree and its crowns' mean offset."""
    d = pairs_judge(trees)
    off = np.array([crown_offset(t) for t in trees])
    mean = off.mean(axis=0)
    out = {
        "set": name,
        "clones": len(trees),
        "pairs": int(d.size),
        "pairs_judge": {
            "median": float(np.median(d)),
            "q25": float(np.percentile(d, 25)),
            "q75": float(np.percentile(d, 75)),
        },
        "judge_to_tree": float(np.median([judge_distance(t, target) for t in trees])),
        "crown_offset": float(np.hypot(*mean)),
        "crown_azimuth": float(np.degrees(np.arctan2(mean[1], mean[0]))),
        "crown_offset_each": float(np.median(np.hypot(off[:, 0], off[:, 1]))),
    }
    o = crown_offset(target)
    out["offset_from_tree"] = float(np.hypot(*(mean - o)))
    return out


def run_one(run: Path, n: int, against: Path | None, figures: Path | None) -> dict:
    cfg = bf.load_config(run / "config.toml")
    best = json.loads((run / "best.json").read_text())
    params = best["params"]
    if build_component(cfg, "ssm").crown_space(params) is None:
        raise SystemExit(f"{run}: its model grew no crown's space (envelope_shade 0 or no crown_envelope)")
    target = load_target_trees(cfg)[0]
    inside, seeds = clone_set(run)
    inside, seeds = inside[:n], seeds[:n]
    off = {k: 0.0 for k in ("envelope_shade", "side_shade", "space_claim") if k in params}
    open_world = [grow_tree(cfg, {**params, **off}, s) for s in seeds]
    sets = [("crown's space", inside), ("open world, same parameters", open_world)]
    if against is not None:
        sets.append((f"open world, fit {against.name}", clone_set(against)[0][:n]))
    o = crown_offset(target)
    out = {
        "run": str(run),
        "tree_crown_offset": float(np.hypot(*o)),
        "tree_crown_azimuth": float(np.degrees(np.arctan2(o[1], o[0]))),
        "sets": [describe(name, trees, target) for name, trees in sets],
    }
    if figures is not None:
        space = build_component(cfg, "ssm").crown_space(params)
        for (name, trees), tag in zip(sets, ("space", "open", "against")):
            clones_figure(
                target,
                [(f"clone {i}", t) for i, t in enumerate(trees[:5])],
                figures / f"{run.name}_{tag}.png",
                title=f"{run.name}: the tree (left) and 5 clones, {name}; dashed: the crown's space",
                envelope=space,
            )
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("runs", nargs="+", type=Path, help="run folders of fits grown in the crown's space, with clones")
    ap.add_argument(
        "--clones", type=int, default=12, help="clones of each set whose pairs are judged (default 12: 66 pairs)"
    )
    ap.add_argument(
        "--against", type=Path, default=None, help="a fit without the crown's space: its clones as a third set"
    )
    ap.add_argument("--out", type=Path, default=Path("crown_space_pairs.json"), help="the numbers, as JSON")
    ap.add_argument("--figures", type=Path, default=None, help="draw each set beside the tree into this folder")
    args = ap.parse_args(argv)
    warnings.filterwarnings("ignore")
    if args.figures is not None:
        args.figures.mkdir(parents=True, exist_ok=True)
    results = []
    for run in args.runs:
        r = run_one(run, args.clones, args.against, args.figures)
        results.append(r)
        print(
            f"{run}: the tree's crown {r['tree_crown_offset']:.2f} crown radii off its stem, towards {r['tree_crown_azimuth']:.0f} deg"
        )
        for s in r["sets"]:
            p = s["pairs_judge"]
            print(
                f"  {s['set']:<34} pairs {p['median']:.3f} [{p['q25']:.3f}, {p['q75']:.3f}] ({s['pairs']}), "
                f"to the tree {s['judge_to_tree']:.3f}; crowns {s['crown_offset']:.2f} towards {s['crown_azimuth']:.0f} deg "
                f"(each {s['crown_offset_each']:.2f}), {s['offset_from_tree']:.2f} from the tree's"
            )
    args.out.write_text(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
