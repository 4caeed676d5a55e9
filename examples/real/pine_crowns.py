"""A pine's crown by height beside its clones': whorls, live branches, the crown's density by metre.

For each fit (a run folder of a pine), the tree and ``--clones`` clones regrown from the answer
with the clone seeds are measured alike:

- whorls: the first-order branches (base diameter >= 1 cm, dead ones too, as a scan shows them)
  grouped by the height of their base (``bforest_core.metrics.whorls``: branches within ``--gap`` m
  of the one below are one whorl); the number of whorls, the whorls' spacing (median, m) and its variation (coefficient of
  variation: 0 for a ladder of equal steps), branches per whorl (mean) and its variation;
- the crown base (the fidelity table's) and the lowest living first-order branch;
- the crown by metre: the length of living first-order branches whose base lies in each 2-m band
  of height above the stem base (m of branch per band).

A pine of the stand grows its whorls one a year, at the spacing of that year's leader shoot: the
scans' whorls vary with the years; the question is whether the clones' do.

    .venv/bin/python examples/real/pine_crowns.py runs/pines_init/pine_ruotsinkyla_1_seed1 ... [--clones 10]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

import bforest_core as bf
from bforest_core.errors import SimulationFailed
from bforest_core.metrics import DETECTION_DIAMETER, WHORL_GAP, _living, crown_base_height, whorls
from bforest_core.pipeline.seeds import clone_seeds

BAND = 2.0  # m


def crown_by_height(tree, gap: float) -> dict:
    groups = whorls(tree, DETECTION_DIAMETER, gap)
    if len(groups) < 2:
        return {"whorls": len(groups)}
    heights = np.array([g.min() for g in groups])
    counts = np.array([g.size for g in groups], float)
    br = tree.branches
    keep = (br.order == 1) & _living(tree) & (2.0 * tree.radius[br.first] >= DETECTION_DIAMETER)
    z = tree.start[br.first[keep], 2] - tree.start[0, 2]  # living branches: the crown
    steps = np.diff(heights)
    blen = np.bincount(tree.branch, weights=tree.length, minlength=len(br))
    top = float(tree.end[:, 2].max() - tree.start[0, 2])
    bands = np.bincount(np.floor(z / BAND).astype(int), weights=blen[keep], minlength=int(top // BAND) + 1)
    return {
        "whorls": len(groups),
        "step_median": float(np.median(steps)),
        "step_cv": float(np.std(steps) / np.mean(steps)),
        "per_whorl": float(counts.mean()),
        "per_whorl_cv": float(counts.std() / counts.mean()),
        "crown_base": crown_base_height(tree),
        "lowest_live": float(z.min()) if z.size else float("nan"),
        "bands": bands.tolist(),
    }


def clones_of(run: Path, n: int):
    best = json.loads((run / "best.json").read_text())
    cfg = bf.load_config(run / "config.toml")
    from bforest_core.config import build_component

    ssm = build_component(cfg, "ssm")
    for seed in clone_seeds(cfg.seed, n, cfg.clones.seed):
        try:
            yield ssm.simulate(best["params"], seed)
        except SimulationFailed as exc:  # a clone that dies is left out, as bforest clones does
            print(f"  {run.name}: clone seed {seed} left out: {exc}", file=sys.stderr)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", help="run folders of fits to pines")
    ap.add_argument("--clones", type=int, default=10)
    ap.add_argument("--gap", type=float, default=WHORL_GAP, help="m between branch bases of one whorl")
    args = ap.parse_args(argv)
    keys = ("whorls", "step_median", "step_cv", "per_whorl", "per_whorl_cv", "crown_base", "lowest_live")
    for run in map(Path, args.runs):
        cfg = bf.load_config(run / "config.toml")
        tree = bf.read_qsm(cfg.target.qsm)
        t = crown_by_height(tree, args.gap)
        cs = [crown_by_height(c, args.gap) for c in clones_of(run, args.clones)]
        print(f"{run.name} ({cfg.ssm.kind}): tree / clones' mean (sd)")
        for k in keys:
            vals = np.array([c[k] for c in cs if k in c], float)
            print(f"  {k:13s} {t.get(k, float('nan')):7.2f} / {vals.mean():7.2f} ({vals.std():.2f})")
        nb = max(len(t["bands"]), *(len(c["bands"]) for c in cs))
        mean = np.mean([np.pad(c["bands"], (0, nb - len(c["bands"]))) for c in cs], axis=0)
        tb = np.pad(t["bands"], (0, nb - len(t["bands"])))
        print("  live first-order branch length by 2-m band (m): band tree / clones")
        for i in range(nb):
            print(f"    {i * BAND:4.0f}-{(i + 1) * BAND:<4.0f} {tb[i]:6.1f} / {mean[i]:6.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
