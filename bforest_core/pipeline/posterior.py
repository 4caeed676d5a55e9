"""Posterior outputs of a sampler's run (``abc-smc`` particles, ``emcee`` chains): a table
(``posterior.csv``), an ArviZ ``InferenceData`` file (``posterior.nc``) and a summary (mean, sd,
5/50/95 % quantiles, 90 % HDI; R-hat and bulk ESS for MCMC chains)."""
from __future__ import annotations

import csv
import warnings
from pathlib import Path

import numpy as np

from ..metrics import weighted_quantiles

HDI_PROB = 0.90


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


def read_posterior_csv(path) -> tuple[list[str], np.ndarray, np.ndarray]:
    """``(names, samples (n, p), weights (n,) summing to 1)`` from a ``posterior.csv``.

    Raises
    ------
    RunDirError
        When the file is missing, empty or not a posterior table.
    """
    from .store import RunDirError
    path = Path(path)
    try:
        with path.open(newline="", encoding="utf-8") as fh:
            rows = list(csv.reader(fh))
    except FileNotFoundError:
        raise RunDirError(f"{path}: not found (the run gave no posterior)") from None
    if len(rows) < 2 or not rows[0] or rows[0][-1] != "weight":
        raise RunDirError(f"{path}: not a posterior table (needs a header ending in 'weight' and rows)")
    try:
        data = np.array(rows[1:], float)
    except ValueError:
        raise RunDirError(f"{path}: non-numeric values") from None
    w = data[:, -1]
    if not (np.all(w >= 0) and w.sum() > 0):
        raise RunDirError(f"{path}: weights must be non-negative and not all zero")
    return rows[0][:-1], data[:, :-1], w / w.sum()


def _draws(diag: dict, names: list[str], X: np.ndarray, w: np.ndarray) -> dict[str, np.ndarray]:
    """Per parameter an array (chain, draw): the walkers of an MCMC chain after burn-in, or for
    weighted particles one chain of a deterministic systematic resample by weight."""
    if diag.get("chain") is not None and diag.get("particles") is None:
        chain = np.asarray(diag["chain"], float)
        burn = min(int(diag.get("burn_in") or 0), chain.shape[0] - 1)
        kept = chain[burn:].transpose(1, 0, 2)  # (walkers, steps, p)
        return {n: kept[:, :, j] for j, n in enumerate(names)}
    n = X.shape[0]
    idx = np.searchsorted(np.cumsum(w), (np.arange(n) + 0.5) / n).clip(0, n - 1)
    return {name: X[idx, j][None, :] for j, name in enumerate(names)}


def posterior_outputs(run_dir: Path, diag: dict, names: list[str]) -> dict | None:
    """Write ``posterior.csv`` and ``posterior.nc`` (ArviZ InferenceData; for weighted particles
    the posterior group is a systematic resample by weight and ``sample_stats.weight`` holds
    the raw weights) into ``run_dir``; return the summary table per parameter, or None when the
    optimiser gave no posterior."""
    got = posterior_samples(diag, names)
    if got is None:
        return None
    run_dir = Path(run_dir)
    write_posterior_csv(run_dir / "posterior.csv", diag, names)
    X, w = got
    import arviz as az
    draws = _draws(diag, names, X, w)
    mcmc = next(iter(draws.values())).shape[0] > 1
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # arviz's future-change notices
        idata = az.from_dict(posterior=draws,
                             sample_stats=None if mcmc else {"weight": w[None, :]},
                             attrs={"sampler": "emcee" if mcmc else "abc-smc"})
        try:
            idata.to_netcdf(str(run_dir / "posterior.nc"))
        except Exception:  # no netCDF engine: the CSV still holds everything
            pass
        hdi = az.hdi(idata, hdi_prob=HDI_PROB)
        diag_stats = az.summary(idata, kind="diagnostics") if mcmc else None
    table = {}
    for j, name in enumerate(names):
        q = weighted_quantiles(X[:, j], w, [5, 50, 95])
        mean = float(w @ X[:, j])
        row = {"mean": mean, "sd": float(np.sqrt(w @ (X[:, j] - mean) ** 2)), "p5": float(q[0]),
               "p50": float(q[1]), "p95": float(q[2]),
               f"hdi{int(100 * HDI_PROB)}_low": float(hdi[name].values[0]),
               f"hdi{int(100 * HDI_PROB)}_high": float(hdi[name].values[1])}
        if diag_stats is not None:
            row["r_hat"] = float(diag_stats.loc[name, "r_hat"])
            row["ess_bulk"] = float(diag_stats.loc[name, "ess_bulk"])
        table[name] = row
    return table
