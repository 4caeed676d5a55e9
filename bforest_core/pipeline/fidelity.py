"""Fidelity of clones: how well they reproduce the target tree's size and shape.

The structural distance compares distributions of branch and segment rows; it does not see how
tall a tree is, how many branches it has or where its crown starts. These pure functions put the
clones beside the target on every tree-level summary statistic
(:func:`bforest_core.metrics.tree_summary`), flag fitted parameters that ended at a bound of
their search box, and warn loudly on every statistic that has a limit (:data:`LIMITS`) when the
clones miss it. Errors are shown in percent; the JSON keeps the fraction under ``error``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np

from ..metrics import OFFSET_TOLERANCE, summary_definition, summary_label, summary_unit

#: the statistics a forester checks first, and the relative error above which clones are not
#: taken as clones of the tree
KEY_STATISTICS = ("height", "dbh", "crown_spread")
WARN_ABOVE = 0.20
#: relative-error limit of every statistic that has one: 20 % for height, DBH and crown spread
#: (the papers' traditional metrics), 30 % for the crown base height and for the branch count of
#: every order (the limits the SOT real-tree recipe must meet for crown base and first-order
#: branches), and 30 % for the stem's length along its axis: a stem that much longer than the
#: tree's winds or bends over, where the height alone does not show it
#: (docs/notes/2026-12-06-broadleaved-stem-length-warning.md: the
#: fits whose stems zigzag, lean or bend over are +31 to +79 %, every fit accepted by eye -13 to +21 %)
LIMITS = {
    "height": WARN_ABOVE,
    "dbh": WARN_ABOVE,
    "crown_spread": WARN_ABOVE,
    "crown_base_height": 0.30,
    "stem_length": 0.30,
}
BRANCH_COUNT_LIMIT = 0.30
#: the crown's side: the clones' mean crown offset (a vector from the stem, in crown radii,
#: :func:`bforest_core.metrics.crown_offset`) may lie this far from the tree's
CROWN_OFFSET_LIMIT = OFFSET_TOLERANCE
#: statistics that are vectors: their name in the table -> their components in a summary; their
#: error is the distance from the clones' mean vector to the tree's, in their unit (not a fraction)
VECTORS = {"crown_offset": ("crown_offset_x", "crown_offset_y")}
LIMITS["crown_offset"] = CROWN_OFFSET_LIMIT


def limit_of(name: str):
    """The relative-error limit of a statistic (fraction), or None when it has none."""
    if name in LIMITS:
        return LIMITS[name]
    if name.startswith("n_branches_o"):
        return BRANCH_COUNT_LIMIT
    return None


def percent(fraction, digits: int = 1) -> str:
    """A relative error as the one convention every table uses: ``+12.3 %`` (``–`` for None)."""
    if fraction is None or not math.isfinite(fraction):
        return "–"
    return f"{100 * fraction:+.{digits}f} %"


#: a fitted parameter within this fraction of its search box from a bound is flagged
BOUND_FRACTION = 0.05


def finite_means(rows: Sequence[Mapping[str, float]], names: Sequence[str]) -> dict[str, float]:
    """The mean of each statistic over the rows that have a value of it, as the fidelity table
    averages the clones' (a tree without a DBH is left out of that mean); NaN when none has one."""
    out = {}
    for k in names:
        x = np.array([r.get(k, np.nan) for r in rows], float)
        x = x[np.isfinite(x)]
        out[k] = float(x.mean()) if x.size else float("nan")
    return out


def fidelity_table(
    target: Mapping[str, float], clones: Sequence[Mapping[str, float]], units: Mapping[str, str] | None = None
) -> list[dict]:
    """One row per statistic: the target's value, the clones' mean and sd, the error of the mean.

    Parameters
    ----------
    target : mapping
        Summary statistics of the target tree.
    clones : sequence of mappings
        Summary statistics of each clone (statistics missing from a clone are skipped).
    units : mapping, optional
        Unit of each statistic (shown beside its name); a statistic not in it gets
        :func:`~bforest_core.metrics.summary_unit`.

    Returns
    -------
    list of dict
        ``statistic``, ``label`` (in words), ``unit``, ``target``, ``mean``, ``sd``, ``p5`` and
        ``p95`` (the clones' 5-95 % band, numpy's linear percentiles), ``n``,
        ``error`` (relative error of the mean, ``(mean - target) / target``, a fraction; ``None``
        when the target is 0), ``limit`` (fraction, or None) and ``warn`` (error beyond the limit).
    """
    units = dict(units or {})
    rows = []
    parts = {c: name for name, cs in VECTORS.items() for c in cs}
    for name, tv in target.items():
        if name in parts:
            if name == VECTORS[parts[name]][0]:
                rows += _vector_row(parts[name], target, clones, units)
            continue
        x = np.array([c[name] for c in clones if c.get(name) is not None], float)
        x = x[np.isfinite(x)]
        if tv is None or not np.isfinite(tv) or x.size == 0:
            continue
        mean = float(x.mean())
        rows.append(_row(name, units, float(tv), mean, x, (mean - tv) / tv if tv != 0 else None))
    return rows


def _row(name: str, units, target: float, mean: float, x: np.ndarray, err, **more) -> dict:
    """A row of the table: the target's value and the clones' mean, the sd and 5-95 % band of the
    clones' values ``x``, the error and the limit."""
    lim = limit_of(name)
    return {
        "statistic": name,
        "label": summary_label(name),
        "unit": units[name] if name in units else summary_unit(name),
        "target": target,
        "mean": mean,
        "sd": float(x.std(ddof=1)) if x.size > 1 else 0.0,
        "p5": float(np.percentile(x, 5)),
        "p95": float(np.percentile(x, 95)),
        "n": int(x.size),
        "error": err,
        **more,
        "limit": lim,
        "warn": bool(err is not None and lim is not None and abs(err) > lim),
    }


def _vector_row(name: str, target: Mapping[str, float], clones: Sequence[Mapping[str, float]], units) -> list[dict]:
    """The row of a vector statistic (:data:`VECTORS`): its size and direction for the tree and for
    the clones' mean vector, its error the distance between the two (none without values)."""
    keys = VECTORS[name]
    tv = np.array([target.get(k, np.nan) for k in keys], float)
    x = np.array([[c.get(k, np.nan) for k in keys] for c in clones], float).reshape(-1, len(keys))
    x = x[np.isfinite(x).all(axis=1)]
    if not np.isfinite(tv).all() or x.size == 0:
        return []
    mean = x.mean(axis=0)
    err = float(np.hypot(*(mean - tv)))
    size = np.hypot(x[:, 0], x[:, 1])
    more = {"difference": True, "target_azimuth": _azimuth(tv), "mean_azimuth": _azimuth(mean)}
    return [_row(name, units, float(np.hypot(*tv)), float(np.hypot(*mean)), size, err, **more)]


def _azimuth(v) -> float:
    """The direction of a horizontal vector, deg counter-clockwise from +x."""
    return float(np.degrees(np.arctan2(v[1], v[0])))


def error_text(r: Mapping) -> str:
    """A row's error as every table shows it: a relative error in percent, a vector's distance in its unit."""
    if r.get("difference"):
        return "–" if r["error"] is None else f"{r['error']:.2f}"
    return percent(r["error"])


def limit_text(r: Mapping) -> str:
    """A row's limit as every table shows it (``–`` for none)."""
    lim = r.get("limit", limit_of(r["statistic"]))
    if lim is None:
        return "–"
    return f"{lim:g}" if r.get("difference") else f"±{100 * lim:g} %"


def at_bounds(
    params: Mapping[str, float], bounds: Mapping[str, tuple[float, float]], fraction: float = BOUND_FRACTION
) -> dict[str, str]:
    """The fitted parameters within ``fraction`` of their box width from a bound: name -> "lower"
    or "upper" (the one rule the fidelity table and the report flag by)."""
    out = {}
    for name, (lo, hi) in bounds.items():
        v = params.get(name)
        if v is None or not hi > lo:
            continue
        tol = fraction * (hi - lo)
        if v - lo <= tol:
            out[name] = "lower"
        elif hi - v <= tol:
            out[name] = "upper"
    return out


def bound_flags(
    params: Mapping[str, float], bounds: Mapping[str, tuple[float, float]], fraction: float = BOUND_FRACTION
) -> list[str]:
    """Fitted parameters within ``fraction`` of their box width from a bound (the optimum may
    lie outside the box: widen it or reconsider the model)."""
    return [
        f"{name} = {params[name]:.6g} is at its {side} bound {bounds[name][0 if side == 'lower' else 1]:g}"
        for name, side in at_bounds(params, bounds, fraction).items()
    ]


def fidelity_warnings(rows: Sequence[Mapping], limits: Mapping[str, float] | None = None) -> list[str]:
    """A warning for every statistic whose clone mean is off the target by more than its limit
    (``limits``, else :func:`limit_of`)."""
    out = []
    for r in rows:
        lim = (limits or {}).get(r["statistic"], limit_of(r["statistic"]))
        if lim is not None and r["error"] is not None and abs(r["error"]) > lim:
            u = f" {r['unit']}" if r.get("unit") and r["unit"] != "count" else ""
            if r.get("difference"):
                out.append(
                    f"the clones' crowns lie on another side of their stems than the target's [{r['statistic']}]: "
                    f"their mean offset, {r['mean']:.2f}{u} towards {r['mean_azimuth']:.0f} deg, lies "
                    f"{r['error']:.2f}{u} from the target's {r['target']:.2f}{u} towards {r['target_azimuth']:.0f} deg "
                    f"(limit {lim:g}{u})"
                )
                continue
            out.append(
                f"clones miss the target's {r.get('label') or summary_label(r['statistic'])} "
                f"[{r['statistic']}]: mean {r['mean']:.3g}{u} vs {r['target']:.3g}{u} "
                f"({percent(r['error'])}, limit ±{100 * lim:g} %)"
            )
    return out


#: widest line of the fidelity table in a terminal, and of its label column
TEXT_WIDTH = 100
_LABEL = 34


def fidelity_text(rows: Sequence[Mapping], flags: Sequence[str] = (), warnings: Sequence[str] = ()) -> str:
    """The table as fixed-width text for a terminal of 100 columns (a long label wraps onto the
    next line; the clones' sd is in the JSON and the report), then what its words mean, the flags
    and the warnings; ``!`` marks a row beyond its limit."""
    import textwrap

    lines = [
        f"{'statistic':<{_LABEL}}{'unit':>6}{'target':>10}{'clones':>10}{'5-95 % band':>18}{'error':>9}{'limit':>8}"
    ]
    for r in rows:
        lim = limit_text(r)
        mark = " !" if r.get("warn") else ""
        label = textwrap.wrap(row_label(r), _LABEL - 1) or [r["statistic"]]
        lines.append(
            f"{label[0]:<{_LABEL}}{_unit(r):>6}{_num(r['target']):>10}{_num(r['mean']):>10}{_band(r):>18}"
            f"{error_text(r):>9}{'' if lim == '–' else lim:>8}{mark}"
        )
        lines += [f"  {more}" for more in label[1:]]
    said = [summary_definition(r["statistic"]) for r in rows]
    notes = [d for d in dict.fromkeys(said) if d] + [f"note: {f} of the search box" for f in flags]
    notes += [f"WARNING: {w}" for w in warnings]
    for text in notes:
        lines += textwrap.wrap(text, TEXT_WIDTH, subsequent_indent="  ")
    return "\n".join(lines)


def row_label(r: Mapping) -> str:
    """A row's label; a vector's with the tree's and the clones' directions."""
    label = r.get("label") or r["statistic"]
    if r.get("difference"):
        label += f" (towards {r['target_azimuth']:.0f} deg; clones {r['mean_azimuth']:.0f} deg)"
    return label


def _unit(r: Mapping) -> str:
    """A row's unit in the terminal's narrow column."""
    return "radii" if r["unit"] == "crown radii" else r["unit"]


def _band(r: Mapping) -> str:
    if r.get("p5") is None or r.get("p95") is None:  # a table written before the band was kept
        return "–"
    return f"{_num(r['p5'])}–{_num(r['p95'])}"


def _num(v: float) -> str:
    if v == 0 or not math.isfinite(v):
        return f"{v:g}"
    return f"{v:.4g}" if abs(v) < 1e4 else f"{v:.3e}"
