"""How far a calibration study's intervals are from calibrated: leave-one-out recalibration.

    .venv/bin/python examples/calibration/recalibration_loo.py runs/calibration/sot_abc_smc_recycled

For each run of a finished ``bforest calibrate`` study, u = the run's posterior CDF at the truth
(read from its posterior.csv). Recalibration (Rodrigues, Prangle and Sisson 2018) replaces a
central interval at level a by the posterior quantiles at the empirical (1 - a)/2 and (1 + a)/2
quantiles of u over the other runs. The script prints, per parameter and level, the coverage of
those leave-one-out intervals and their width relative to the sampler's own intervals (median over
runs): a width factor below 1 says by how much the sampler's intervals are too wide. The coverage
is close to nominal by construction (the runs are exchangeable), so it is a check of the script,
not of the sampler. An analysis of docs/calibration.md, not part of the product.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from bforest_core.metrics import weighted_quantiles
from bforest_core.pipeline.posterior import read_posterior_csv


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("study", type=Path, help="output folder of bforest calibrate (holds calibration.json)")
    args = ap.parse_args()
    res = json.loads((args.study / "calibration.json").read_text())
    names = res["names"]
    runs = []
    for r in res["runs"]:
        if r["status"] != "ok":
            continue
        cols, X, w = read_posterior_csv(args.study / r["run"] / "posterior.csv")
        X = X[:, [list(cols).index(n) for n in names]]
        truth = np.array([r["params"][n]["truth"] for n in names])
        runs.append((truth, X, w))
    U = np.array([[w[X[:, j] <= t[j]].sum() for j in range(len(names))] for t, X, w in runs])
    print(f"{args.study}: {len(runs)} runs")
    for j, name in enumerate(names):
        cells = []
        for a in (0.5, 0.9):
            covered, factor = [], []
            for i, (t, X, w) in enumerate(runs):
                ql, qh = np.quantile(np.delete(U[:, j], i), [(1 - a) / 2, (1 + a) / 2])
                lo, hi = weighted_quantiles(X[:, j], w, [100 * ql, 100 * qh])
                lo0, hi0 = weighted_quantiles(X[:, j], w, [50 * (1 - a), 50 * (1 + a)])
                covered.append(lo <= t[j] <= hi)
                factor.append((hi - lo) / (hi0 - lo0) if hi0 > lo0 else np.nan)
            cells.append(f"{100 * a:.0f} %: covers {100 * np.mean(covered):.1f} %, width x{np.nanmedian(factor):.2f}")
        print(f"{name:16s}" + " | ".join(cells))


if __name__ == "__main__":
    main()
