"""Posterior samples of a sampler's run (``abc-smc`` particles, ``emcee`` chains) as a table."""
from __future__ import annotations

import csv
from pathlib import Path

import numpy as np


def posterior_samples(diag: dict, names: list[str]) -> tuple[np.ndarray, np.ndarray] | None:
    """``(samples (n, p), weights (n,))`` from optimiser diagnostics, or None when the optimiser
    gave no posterior: the weighted particles of ``abc-smc``, or the post-burn-in draws of every
    walker of ``emcee`` (equal weights)."""
    if not isinstance(diag, dict):
        return None
    if diag.get("particles") is not None and diag.get("weights") is not None:
        X = np.asarray(diag["particles"], float)
        w = np.asarray(diag["weights"], float)
    elif diag.get("chain") is not None:
        chain = np.asarray(diag["chain"], float)
        if chain.ndim != 3 or chain.shape[0] == 0:
            return None
        burn = min(int(diag.get("burn_in") or 0), chain.shape[0] - 1)
        X = chain[burn:].reshape(-1, chain.shape[2])
        w = np.full(X.shape[0], 1.0 / X.shape[0])
    else:
        return None
    if X.ndim != 2 or X.shape[1] != len(names) or w.shape != (X.shape[0],):
        return None
    return X, w / w.sum()


def write_posterior_csv(path: Path, diag: dict, names: list[str]) -> Path | None:
    """Write ``posterior.csv`` (one column per parameter and ``weight``); None without a posterior."""
    got = posterior_samples(diag, names)
    if got is None:
        return None
    X, w = got
    path = Path(path)
    with path.open("w", newline="", encoding="utf-8") as f:
        out = csv.writer(f)
        out.writerow([*names, "weight"])
        for row, wi in zip(X, w):
            out.writerow([f"{v:.10g}" for v in row] + [f"{wi:.10g}"])
    return path
