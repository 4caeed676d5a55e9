"""Fidelity of clones: how well they reproduce the target tree's size and shape.

The structural distance compares distributions of branch and segment rows; it does not see how
tall a tree is, how many branches it has or where its crown starts. These pure functions put the
clones beside the target on every tree-level summary statistic
(:func:`bforest_core.metrics.tree_summary`), flag fitted parameters that ended at a bound of
their search box, and warn loudly when the clones miss the target's height, DBH or crown spread.
"""
from __future__ import annotations

import math
from typing import Mapping, Sequence

import numpy as np

#: the statistics a forester checks first, and the relative error above which clones are not
#: taken as clones of the tree
KEY_STATISTICS = ("height", "dbh", "crown_spread")
WARN_ABOVE = 0.20
#: a fitted parameter within this fraction of its search box from a bound is flagged
BOUND_FRACTION = 0.05


def fidelity_table(target: Mapping[str, float], clones: Sequence[Mapping[str, float]],
                   units: Mapping[str, str] | None = None) -> list[dict]:
    """One row per statistic: the target's value, the clones' mean and sd, the error of the mean.

    Parameters
    ----------
    target : mapping
        Summary statistics of the target tree.
    clones : sequence of mappings
        Summary statistics of each clone (statistics missing from a clone are skipped).
    units : mapping, optional
        Unit of each statistic (shown beside its name).

    Returns
    -------
    list of dict
        ``statistic``, ``unit``, ``target``, ``mean``, ``sd``, ``n``, ``error`` (relative error of
        the mean, ``(mean - target) / target``; ``None`` when the target is 0).
    """
    units = dict(units or {})
    rows = []
    for name, tv in target.items():
        x = np.array([c[name] for c in clones if c.get(name) is not None], float)
        x = x[np.isfinite(x)]
        if tv is None or not np.isfinite(tv) or x.size == 0:
            continue
        mean = float(x.mean())
        rows.append({"statistic": name, "unit": units.get(name, ""), "target": float(tv), "mean": mean,
                     "sd": float(x.std(ddof=1)) if x.size > 1 else 0.0, "n": int(x.size),
                     "error": (mean - tv) / tv if tv != 0 else None})
    return rows


def bound_flags(params: Mapping[str, float], bounds: Mapping[str, tuple[float, float]],
                fraction: float = BOUND_FRACTION) -> list[str]:
    """Fitted parameters within ``fraction`` of their box width from a bound (the optimum may
    lie outside the box: widen it or reconsider the model)."""
    out = []
    for name, (lo, hi) in bounds.items():
        v = params.get(name)
        if v is None or not hi > lo:
            continue
        tol = fraction * (hi - lo)
        if v - lo <= tol:
            out.append(f"{name} = {v:.6g} is at its lower bound {lo:g}")
        elif hi - v <= tol:
            out.append(f"{name} = {v:.6g} is at its upper bound {hi:g}")
    return out


def fidelity_warnings(rows: Sequence[Mapping], keys: Sequence[str] = KEY_STATISTICS,
                      limit: float = WARN_ABOVE) -> list[str]:
    """A warning for each key statistic whose clone mean is off the target by more than ``limit``."""
    out = []
    for r in rows:
        if r["statistic"] in keys and r["error"] is not None and abs(r["error"]) > limit:
            out.append(f"clones miss the target's {r['statistic']}: mean {r['mean']:.3g} {r['unit']} vs "
                       f"{r['target']:.3g} {r['unit']} ({100 * r['error']:+.0f} %, limit ±{100 * limit:.0f} %)")
    return out


def fidelity_text(rows: Sequence[Mapping], flags: Sequence[str] = (), warnings: Sequence[str] = ()) -> str:
    """The table as fixed-width text (for the terminal), then the flags and warnings."""
    lines = [f"{'statistic':<22}{'unit':>6}{'target':>11}{'clones mean':>13}{'sd':>10}{'error':>9}"]
    for r in rows:
        err = "–" if r["error"] is None else f"{100 * r['error']:+.1f}%"
        lines.append(f"{r['statistic']:<22}{r['unit']:>6}{_num(r['target']):>11}{_num(r['mean']):>13}"
                     f"{_num(r['sd']):>10}{err:>9}")
    lines += [f"note: {f} of the search box" for f in flags]
    lines += [f"WARNING: {w}" for w in warnings]
    return "\n".join(lines)


def _num(v: float) -> str:
    if v == 0 or not math.isfinite(v):
        return f"{v:g}"
    return f"{v:.4g}" if abs(v) < 1e4 else f"{v:.3e}"
