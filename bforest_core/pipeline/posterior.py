"""Posterior outputs of a sampler's run (weighted particles of a population, or the walkers of
an MCMC chain): a table (``posterior.csv``), an ArviZ ``InferenceData`` file (``posterior.nc``
with the ``posterior``, ``prior``, ``observed_data`` and ``sample_stats`` groups) and a summary
(mean, sd, 5/50/95 % quantiles, 90 % HDI; R-hat and bulk ESS for MCMC chains).

Each takes the sampler's posterior as one object (:class:`~bforest_core.interfaces.Posterior`:
its kind, ``"chain"`` or ``"population"``, its draws and weights).
"""

from __future__ import annotations

import csv
import warnings
from pathlib import Path

import numpy as np

from ..interfaces import Posterior
from ..metrics import weighted_quantiles
from .store import RunFiles

HDI_PROB = 0.90


def write_posterior_csv(path: Path, post: Posterior) -> Path:
    """Write ``posterior.csv``: one column per parameter and ``weight``, a row per draw."""
    path = Path(path)
    with path.open("w", newline="", encoding="utf-8") as f:
        out = csv.writer(f)
        out.writerow([*post.names, "weight"])
        for row, wi in zip(post.samples, post.weights):
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


def uniform_draw(rng: np.random.Generator, lower, upper, integer) -> np.ndarray:
    """One draw uniform in ``[lower, upper]`` (integer parameters uniform over the whole numbers in
    their bounds), from one uniform number per parameter of ``rng``."""
    lo, hi = np.asarray(lower, float), np.asarray(upper, float)
    u = rng.random(lo.size)
    ilo, ihi = np.ceil(lo), np.floor(hi)
    whole = np.minimum(ilo + np.floor(u * (ihi - ilo + 1)), ihi)
    return np.where(np.asarray(integer, bool), whole, lo + u * (hi - lo))


def prior_draws(box: dict, n: int, seed: int = 1) -> dict[str, np.ndarray]:
    """``n`` draws ``(1, n)`` per parameter of the uniform prior over the search box that every
    sampler of a fit is given: ``box`` maps a name to ``(lower, upper, integer)``; an integer
    parameter is uniform over the whole numbers in its bounds."""
    rng = np.random.default_rng([int(seed), 0x9F10])
    out = {}
    for name, (lo, hi, integer) in box.items():
        if integer:
            a, b = int(np.ceil(lo)), int(np.floor(hi))
            out[name] = rng.integers(a, max(a, b) + 1, size=n).astype(float)[None, :]
        else:
            out[name] = (lo + (hi - lo) * rng.random(n))[None, :]
    return out


def _safe_name(name: str) -> str:
    """A netCDF variable name for a data set name (``S0,1`` -> ``S0_1``, ``size/summary`` ->
    ``size_summary``)."""
    import re

    return re.sub(r"[^A-Za-z0-9_]", "_", name)


def _observed(observed: dict | None, columns: dict | None):
    """(data, dims, coords) of the ``observed_data`` group: each data set of the target a
    ``(rows, columns)`` table with its column names."""
    data, dims, coords = {}, {}, {}
    for name, U in (observed or {}).items():
        U = np.asarray(U, float)
        if U.ndim != 2:
            continue
        var = _safe_name(name)
        data[var] = U
        dims[var] = [f"{var}_row", f"{var}_column"]
        cols = list((columns or {}).get(name) or [])
        if len(cols) == U.shape[1]:
            coords[f"{var}_column"] = cols
    return data, dims, coords


def posterior_outputs(
    run_dir: Path,
    post: Posterior,
    prior_box: dict | None = None,
    observed: dict | None = None,
    columns: dict | None = None,
    attrs: dict | None = None,
    seed: int = 1,
) -> dict:
    """Write ``posterior.csv`` and ``posterior.nc`` into ``run_dir``; return the summary table per
    parameter.

    Parameters
    ----------
    run_dir : Path
        The run directory.
    post : Posterior
        The sampler's posterior (``OptimizeResult.posterior``).
    prior_box : dict, optional
        ``{name: (lower, upper, integer)}``: the ``prior`` group holds as many draws of the
        uniform prior over this box as the posterior has samples.
    observed : dict, optional
        The target's data sets ``{set: (rows, columns)}``: the ``observed_data`` group (set names
        made netCDF-safe, ``S0,1`` -> ``S0_1``; the group's ``sets`` attribute maps them back).
    columns : dict, optional
        Column names per data set (the coordinates of ``observed_data``).
    attrs : dict, optional
        Attributes of the file (e.g. the optimiser's name).
    seed : int
        Seed of the prior draws.

    Notes
    -----
    A chain's ``posterior`` has one ArviZ chain per walker (the draws after burn-in), and
    ``sample_stats.distance`` the walkers' distances. A population's ``posterior`` is one chain
    of a systematic resample by weight; ``sample_stats`` holds each particle's raw ``weight``
    and ``distance`` in the order of ``posterior.csv``.
    """
    run_dir = Path(run_dir)
    write_posterior_csv(RunFiles(run_dir).posterior_csv_path, post)
    X, w, names = post.samples, post.weights, list(post.names)
    import arviz as az

    draws = post.draws()
    stats = {}
    if post.kind == "chain":
        if post.distances is not None:
            stats["distance"] = post.distances[post.burn_in :].T
    else:
        stats["weight"] = w[None, :]
        if post.distances is not None:
            stats["distance"] = post.distances[None, :]
    n_draws = int(np.prod(next(iter(draws.values())).shape))
    prior = prior_draws({k: prior_box[k] for k in names if k in prior_box}, n_draws, seed) if prior_box else None
    obs, obs_dims, obs_coords = _observed(observed, columns)
    file_attrs = {"posterior_kind": post.kind, **{k: str(v) for k, v in (attrs or {}).items() if v is not None}}
    if obs:
        import json

        file_attrs["sets"] = json.dumps({_safe_name(k): k for k in (observed or {})})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # arviz's future-change notices
        idata = az.from_dict(
            posterior=draws,
            sample_stats=stats or None,
            prior=prior or None,
            observed_data=obs or None,
            dims=obs_dims or None,
            coords=obs_coords or None,
            attrs=file_attrs,
        )
        try:
            idata.to_netcdf(str(RunFiles(run_dir).posterior_nc_path))
        except Exception:  # no netCDF engine: the CSV still holds everything
            pass
        hdi = az.hdi(idata.posterior, hdi_prob=HDI_PROB)
        diag_stats = (
            az.summary(idata.posterior, kind="diagnostics")
            if post.kind == "chain" and next(iter(draws.values())).shape[0] > 1
            else None
        )
    table = {}
    for j, name in enumerate(names):
        q = weighted_quantiles(X[:, j], w, [5, 50, 95])
        mean = float(w @ X[:, j])
        row = {
            "mean": mean,
            "sd": float(np.sqrt(w @ (X[:, j] - mean) ** 2)),
            "p5": float(q[0]),
            "p50": float(q[1]),
            "p95": float(q[2]),
            f"hdi{int(100 * HDI_PROB)}_low": float(hdi[name].values[0]),
            f"hdi{int(100 * HDI_PROB)}_high": float(hdi[name].values[1]),
        }
        if diag_stats is not None:
            row["r_hat"] = float(diag_stats.loc[name, "r_hat"])
            row["ess_bulk"] = float(diag_stats.loc[name, "ess_bulk"])
        table[name] = row
    return table
