"""Figures of an optimiser run: distance per evaluation and where the search went."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .canvas import MODEL_COLOR, capped_size, new_figure, save_figure
from .document import cfg_kind

if TYPE_CHECKING:  # annotations only: run_view imports this module's neighbours
    from .run_view import RunView


# ---------------------------------------------------------------------------------- fit diagnostics
def convergence_figure(
    distances: np.ndarray,
    path,
    statuses: Sequence[str] | None = None,
    records: Sequence[Mapping] | None = None,
    title: str | None = None,
    dpi: int = 130,
) -> Path:
    """Distance of every evaluation with the best so far (left) and, when the optimiser logs
    generations/iterations, the best and mean distance per generation (right).

    Failed evaluations are marked at the top edge (their penalty distance is off the scale).
    """
    d = np.asarray(distances, float)
    ok = np.ones(d.size, bool) if statuses is None else np.array([s == "ok" for s in statuses], bool)
    gen = _generation_series(records or [])
    ncol = 2 if gen is not None else 1
    fig = new_figure(6.2 * ncol, 4.0)
    axes = fig.subplots(1, ncol, squeeze=False)[0]
    ax = axes[0]
    x = np.arange(1, d.size + 1)
    if ok.any():
        ax.scatter(x[ok], d[ok], s=8, color="#7f7f7f", alpha=0.55, lw=0, label="evaluation")
    best = np.minimum.accumulate(np.where(np.isfinite(d), d, np.inf)) if d.size else d
    ax.step(x, best, where="post", color=MODEL_COLOR, lw=1.8, label="best so far")
    if (~ok).any():
        ax.scatter(
            x[~ok],
            np.full((~ok).sum(), 0.97),
            transform=ax.get_xaxis_transform(),
            marker="x",
            color="#e6550d",
            s=18,
            lw=1.0,
            label=f"failed ({(~ok).sum()}, penalty)",
            clip_on=False,
        )
    if ok.any():
        lo, hi = float(np.min(d[ok])), float(np.max(d[ok]))
        pad = 0.05 * (hi - lo) if hi > lo else 0.05 * max(abs(hi), 1e-3)
        ax.set_ylim(lo - pad, hi + 3 * pad)
    ax.set_xlabel("evaluation")
    ax.set_ylabel("distance D")
    ax.set_xlim(0, max(1, d.size) + 1)
    ax.grid(True, lw=0.3, alpha=0.5)
    ax.legend(fontsize="small", loc="upper right")
    ax.set_title("every evaluation", fontsize="medium")
    if gen is not None:
        ax = axes[1]
        xkey, xs, series = gen
        for key, style in (
            ("best", dict(color=MODEL_COLOR, lw=1.8, marker="o", ms=3)),
            ("mean", dict(color="#1f77b4", lw=1.2, marker=".", ms=3)),
            ("median", dict(color="#2ca02c", lw=1.2, ls="--")),
        ):
            if key in series:
                ax.plot(xs, series[key], label=key, **style)
        if "mean" in series and "std" in series:
            m, s = series["mean"], series["std"]
            ax.fill_between(xs, m - s, m + s, color="#1f77b4", alpha=0.15, lw=0, label="mean ± sd")
        ax.set_xlabel(xkey)
        ax.xaxis.get_major_locator().set_params(integer=True)
        ax.set_ylabel("distance D")
        ax.grid(True, lw=0.3, alpha=0.5)
        ax.legend(fontsize="small")
        ax.set_title(f"per {xkey}", fontsize="medium")
    if title:
        fig.suptitle(title)
    return save_figure(fig, path, dpi)


def _generation_series(records):
    """(x key, x values, {series: values}) from optimiser log records, or None."""
    recs = [r for r in records if isinstance(r, Mapping)]
    if not recs:
        return None
    xkey = next((k for k in ("generation", "step", "iteration", "round") if all(k in r for r in recs)), None)
    series = {}
    for key in ("best", "mean", "median", "std"):
        vals = [r.get(key) for r in recs]
        if all(v is None for v in vals):
            continue
        series[key] = np.array([np.nan if v is None else float(v) for v in vals])
    if "best" not in series and "mean" not in series:
        return None
    xs = np.array([r[xkey] for r in recs], float) if xkey else np.arange(len(recs), dtype=float)
    return (xkey or "record"), xs, series


def parameter_scatter_figure(
    names: Sequence[str],
    X: np.ndarray,
    distances: np.ndarray,
    path,
    best: Mapping[str, float] | None = None,
    bounds: Mapping[str, tuple[float, float]] | None = None,
    units: Mapping[str, str] | None = None,
    title: str | None = None,
    dpi: int = 130,
) -> Path:
    """Distance against each free parameter over the successful evaluations, coloured by
    evaluation number (where the optimiser looked, and when); the best fit is a red star."""
    X = np.asarray(X, float).reshape(len(distances), len(names))
    d = np.asarray(distances, float)
    p = len(names)
    ncol = min(p, 3) if p <= 9 else 4
    nrow = math.ceil(p / ncol)
    # rows get lower as they get more, so 18 parameters still fit a page
    fig = new_figure(*capped_size(4.3 * ncol + 0.8, (3.4 if nrow <= 3 else 2.6) * nrow + 0.8, dpi))
    axes = fig.subplots(nrow, ncol, squeeze=False).ravel()
    sc = None
    for j, (ax, name) in enumerate(zip(axes, names)):
        sc = ax.scatter(X[:, j], d, c=np.arange(d.size), cmap="viridis", s=10, alpha=0.7, lw=0)
        if best and name in best:
            ax.scatter(
                [best[name]],
                [np.min(d)] if d.size else [np.nan],
                marker="*",
                s=160,
                color=MODEL_COLOR,
                edgecolor="black",
                lw=0.6,
                zorder=5,
                label=f"best {best[name]:.4g}",
            )
            ax.legend(fontsize="small")
        if bounds and name in bounds:
            lo, hi = bounds[name]
            pad = 0.02 * (hi - lo)
            ax.set_xlim(lo - pad, hi + pad)
        unit = (units or {}).get(name)
        ax.set_xlabel(f"{name} ({unit})" if unit else name)
        ax.set_ylabel("distance D")
        ax.grid(True, lw=0.3, alpha=0.5)
    for ax in axes[p:]:
        ax.set_visible(False)
    if sc is not None:
        if nrow == 1:
            fig.colorbar(sc, ax=list(axes[:p]), label="evaluation", shrink=0.9)
        else:  # a bar across the top, as long as a row, not the whole figure's height
            fig.colorbar(sc, ax=list(axes[:ncol]), location="top", label="evaluation", shrink=0.6, aspect=40)
    if title:
        fig.suptitle(title)
    return save_figure(fig, path, dpi)


# ---------------------------------------------------------------------------------- run report
def fig_convergence(v: RunView):
    evs = v.evaluations
    if not evs:
        v.note("no evaluations logged: convergence figures skipped")
        return []
    d = np.array([e.distance for e in evs], float)
    st = [e.status for e in evs]
    out = [
        (
            convergence_figure(
                d,
                v.store.figures_dir / "convergence.png",
                statuses=st,
                records=v.records,
                title=f"Convergence ({(v.best or {}).get('optimizer') or cfg_kind(v, 'optimizer')})",
            ),
            "Distance of every evaluation and the best so far; per-generation best and mean when the "
            "optimiser logs generations",
        )
    ]
    names = [n for n in v.free_names if all(n in e.params for e in evs)]
    ok = [e for e in evs if e.ok]
    if names and ok:
        X = np.array([[e.params[n] for n in names] for e in ok], float)
        bounds = {}
        if v.cfg is not None:
            bounds = {n: (v.cfg.ssm.free[n].lower, v.cfg.ssm.free[n].upper) for n in names}
        out.append(
            (
                parameter_scatter_figure(
                    names,
                    X,
                    [e.distance for e in ok],
                    v.store.figures_dir / "parameters.png",
                    best=v.best_params,
                    bounds=bounds,
                    units={n: s.unit for n, s in v.param_specs.items()},
                    title="Where the optimiser searched",
                ),
                "Distance against each free parameter over the successful evaluations (colour: "
                "evaluation number; star: best fit; x-range: the bounds)",
            )
        )
    return out
