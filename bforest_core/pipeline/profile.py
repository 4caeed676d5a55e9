"""``bforest profile RUN --param NAME``: the distance along one parameter (GigaScience Fig. 4).

Every other parameter stays at the best fit; for each value the model is grown with several
seeds (the same seeds at every value: common random numbers, so each seed traces one
realisation of the stochastic distance surface). The first seed is the fit's own first model
seed, so its curve passes through the best fit. Writes ``figures/profile_<param>.png`` and
``profile_<param>.csv`` (one row per value and seed, with the per-set distances).
"""

from __future__ import annotations

import csv
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..errors import ConfigError
from ..interfaces import parameter_value

if TYPE_CHECKING:
    from ..config import RunConfig

__all__ = ["profile", "profile_values"]


def profile_values(
    lower: float, upper: float, n: int = 11, integer: bool = False, include: float | None = None
) -> np.ndarray:
    """``n`` values spread evenly over ``[lower, upper]`` (whole numbers for integer
    parameters, without repeats), plus ``include`` (the best fit) when given."""
    if not upper > lower:
        raise ConfigError(f"profile: upper bound {upper} must exceed lower bound {lower}")
    if n < 2:
        raise ConfigError(f"profile: need at least 2 values (n = {n})")
    v = np.linspace(lower, upper, int(n))
    if include is not None and np.isfinite(include):
        v = np.append(v, float(include))
    if integer:
        v = np.round(v)
    return np.unique(v)


def _profile_grid(cfg: RunConfig, spec, param: str, values, n: int, best_value: float):
    """The values to profile and whether they are whole numbers: ``n`` across the fit bounds (or
    the model's range for a fixed parameter) plus the best value, or the user's ``values``
    checked against the model's range."""
    integer = bool(spec.integer)
    if param in cfg.ssm.free:
        fp = cfg.ssm.free[param]
        lo, hi = fp.lower, fp.upper
        integer = spec.integer if fp.integer is None else bool(fp.integer)
    else:
        lo, hi = spec.lower, spec.upper
    if values is None:
        return profile_values(lo, hi, n, integer, include=best_value), integer
    vals = np.unique(np.asarray(list(values), float))
    if vals.size == 0:
        raise ConfigError("profile: --values is empty")
    bad = vals[(vals < spec.lower) | (vals > spec.upper)]
    if bad.size:
        raise ConfigError(
            f"profile: {param} = {bad[0]:g} is outside the model's allowed range "
            f"[{spec.lower:g}, {spec.upper:g}] {spec.unit}".rstrip()
        )
    return (np.unique(np.round(vals)) if integer else vals), integer


def profile(
    run_dir,
    param: str,
    values: Sequence[float] | None = None,
    seeds: int = 5,
    n: int = 11,
    executor=None,
    progress: bool = False,
) -> dict:
    """Distance profile along one parameter of a finished fit.

    Parameters
    ----------
    run_dir : path
        A run directory with ``best.json``.
    param : str
        A parameter of the run's SSM (free or fixed in the fit).
    values : sequence of float, optional
        Values to evaluate; default ``n`` values across the parameter's fit bounds (or the
        model's allowed range for a parameter that was fixed), plus the best-fit value.
    seeds : int
        Model seeds per value (the first is the fit's own first seed).
    n : int
        Number of values when ``values`` is not given.
    executor : Executor, optional
        Default: the run's configured executor.

    Returns
    -------
    dict
        ``table_text`` (one line per value: median, quartiles, range, failures), ``csv`` (path), ``param``, ``values`` (k,), ``seeds`` (list),
        ``distances`` (k, seeds), ``status`` (k, seeds), ``best_value``, ``best_distance``.
    """
    from ..config import build_component, load_config
    from .progress import progress_bar
    from .seeds import model_seeds
    from .store import RunFiles, RunStore, slug
    from .target import build_target
    from .worker import evaluate_task, started_workers

    run_dir = Path(run_dir)
    with RunStore.open(run_dir) as store:
        cfg = load_config(store.config_path)
        best = store.read_best()
    ssm = build_component(cfg, "ssm")
    try:
        spec = ssm.parameter_spec(param)
    except KeyError:
        known = ", ".join(p.name for p in ssm.parameters)
        raise ConfigError(f"profile: '{param}' is not a parameter of SSM '{cfg.ssm.kind}' (known: {known})") from None
    base = dict(best["params"])
    best_value = base.get(param, spec.default)
    vals, integer = _profile_grid(cfg, spec, param, values, n, best_value)
    if int(seeds) < 1:
        raise ConfigError(f"profile: seeds must be at least 1 (got {seeds})")
    seed_list = model_seeds(cfg.seed, int(seeds), "fixed")

    tasks, where = [], []
    for i, x in enumerate(vals):
        p = dict(base)
        p[param] = parameter_value(x, integer)
        for j, s in enumerate(seed_list):
            tasks.append((p, [s]))
            where.append((i, j))
    tgt = build_target(cfg)
    D = np.full((vals.size, len(seed_list)), np.nan)
    status = np.full(D.shape, "", dtype=object)
    per_set: dict[tuple[int, int], dict] = {}
    bar = progress_bar(len(tasks), f"profile {param}", "eval", progress)
    with started_workers(cfg, tgt, executor) as ex:
        for k, res in ex.map_unordered(evaluate_task, tasks):
            i, j = where[k]
            D[i, j] = res["distance"]
            status[i, j] = res["status"]
            per_set[(i, j)] = res["per_set"]
            bar.update(1)
    bar.close()

    csv_path = _write_profile_csv(
        RunFiles(run_dir).profile_path(slug(param)), vals, seed_list, D, status, per_set, list(tgt.U), spec.unit
    )
    failed = status != "ok"
    # the best fit's own distance (mean over the fit's seeds), drawn as a marker
    best_distance = best.get("distance")
    lines = _profile_table(param, spec.unit, vals, seed_list, D, failed, best_value)
    return {
        "table_text": "\n".join(lines),
        "csv": csv_path,
        "param": param,
        "values": vals,
        "seeds": seed_list,
        "distances": D,
        "status": status,
        "failed": failed,
        "best_value": best_value,
        "best_distance": best_distance,
        "unit": spec.unit,
        "run_dir": run_dir,
    }


def _write_profile_csv(csv_path, vals, seed_list, D, status, per_set, set_names, unit: str = ""):
    """One row per (value, seed): the distance, status and per-set distances (the value column
    carries the parameter's unit, e.g. ``value_deg``)."""
    with open(csv_path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(
            [f"value_{unit}" if unit else "value", "seed", "distance", "status"] + [f"D[{s}]" for s in set_names]
        )
        for i, x in enumerate(vals):
            for j, s in enumerate(seed_list):
                ps = per_set.get((i, j)) or {}
                w.writerow(
                    [f"{x:.10g}", s, f"{D[i, j]:.10g}", status[i, j]]
                    + ["" if ps.get(n) is None else f"{ps[n]:.10g}" for n in set_names]
                )
    return csv_path


def _profile_table(param, unit, vals, seed_list, D, failed, best_value) -> list[str]:
    """The printed table: median, quartiles and range of the distance per value."""
    med = np.median(D, axis=1)
    q1, q3 = np.quantile(D, [0.25, 0.75], axis=1)
    lines = [
        f"profile of {param} ({unit or 'no unit'}): {vals.size} values x {len(seed_list)} seeds, "
        f"other parameters at the best fit; best fit {param} = {best_value:.6g}",
        f"{'value':>12}{'median':>10}{'q25':>10}{'q75':>10}{'min':>10}{'max':>10}{'failed':>8}",
    ]
    for i, x in enumerate(vals):
        mark = "  <- best fit" if np.isclose(x, best_value) else ""
        lines.append(
            f"{x:>12.6g}{med[i]:>10.4f}{q1[i]:>10.4f}{q3[i]:>10.4f}{D[i].min():>10.4f}"
            f"{D[i].max():>10.4f}{int(failed[i].sum()):>8d}{mark}"
        )
    k = int(np.argmin(med))
    lines.append(f"lowest median distance {med[k]:.4f} at {param} = {vals[k]:.6g}")
    return lines
