"""Figures of the data sets: data against model per set, ECDFs on the worst projection lines."""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from matplotlib.lines import Line2D

from ..interfaces import LineDistance
from .canvas import DATA_COLOR, MODEL_COLOR, capped_size, column_label, new_figure, save_figure
from .document import slug

if TYPE_CHECKING:  # annotations only: run_view imports this module's neighbours
    from .run_view import RunView


# ---------------------------------------------------------------------------------- data sets
_CIRC = re.compile(r"^(sin|cos)\((.+)\)$")


def display_columns(table: np.ndarray, columns: Sequence[str]):
    """Turn circular pairs ``sin(x)``, ``cos(x)`` back into the angle x in degrees for display.

    Returns ``(table, names)`` with one column per original feature (the angle takes the place
    of its ``sin`` column).
    """
    table = np.asarray(table, float)
    columns = list(columns)
    idx = {c: i for i, c in enumerate(columns)}
    out, names, used = [], [], set()
    for i, c in enumerate(columns):
        if i in used:
            continue
        m = _CIRC.match(c)
        if m:
            base = m.group(2)
            si, ci = idx.get(f"sin({base})"), idx.get(f"cos({base})")
            if si is not None and ci is not None:
                out.append(np.degrees(np.arctan2(table[:, si], table[:, ci])))
                names.append(base)
                used.update((si, ci))
                continue
        out.append(table[:, i])
        names.append(c)
        used.add(i)
    arr = np.column_stack(out) if out else np.empty((table.shape[0], 0))
    return arr, names


def _subsample(x: np.ndarray, k: int, rng) -> np.ndarray:
    if x.shape[0] <= k:
        return x
    return x[np.sort(rng.choice(x.shape[0], k, replace=False))]


def set_scatter_figure(
    data: np.ndarray,
    model: np.ndarray,
    columns: Sequence[str],
    path,
    title: str | None = None,
    max_points: int = 4000,
    seed: int = 0,
    dpi: int = 120,
) -> Path:
    """Data (QSM, blue) against model (SSM, red) for one data set: every pair of variates as a
    scatter (lower triangle), each variate's distribution on the diagonal (GigaScience Fig. 3).

    Circular ``sin``/``cos`` pairs are shown as angles in degrees. At most ``max_points`` rows
    per side are drawn (a seeded random subset; the legend gives the full counts).
    """
    d_tab, names = display_columns(data, columns)
    m_tab, _ = display_columns(model, columns)
    k = len(names)
    rng = np.random.default_rng(seed)
    d_pts, m_pts = _subsample(d_tab, max_points, rng), _subsample(m_tab, max_points, rng)
    size = 1.9 if k > 3 else 2.6
    fig = new_figure(max(5.0, size * k), max(4.6, size * k + 0.4))
    axes = fig.subplots(k, k, squeeze=False)
    both = np.concatenate([d_tab, m_tab]) if m_tab.size else d_tab
    lims = []
    for j in range(k):
        col = both[:, j][np.isfinite(both[:, j])]
        if col.size == 0:
            lims.append((0.0, 1.0))
            continue
        lo, hi = np.quantile(col, [0.0, 1.0])
        pad = 0.04 * (hi - lo) if hi > lo else 0.5
        lims.append((lo - pad, hi + pad))
    ms = 3.0 if max(len(d_pts), len(m_pts)) > 1500 else 6.0
    for i in range(k):
        for j in range(k):
            ax = axes[i, j]
            if j > i:
                ax.set_visible(False)
                continue
            if i == j:
                bins = np.linspace(*lims[j], 31)
                if d_tab.shape[0]:
                    ax.hist(d_tab[:, j], bins=bins, density=True, histtype="stepfilled", color=DATA_COLOR, alpha=0.35)
                    ax.hist(d_tab[:, j], bins=bins, density=True, histtype="step", color=DATA_COLOR, lw=1.0)
                if m_tab.shape[0]:
                    ax.hist(m_tab[:, j], bins=bins, density=True, histtype="step", color=MODEL_COLOR, lw=1.4)
                ax.set_yticks([])
            else:
                ax.scatter(d_pts[:, j], d_pts[:, i], s=ms, c=DATA_COLOR, alpha=0.45, lw=0, rasterized=True)
                if m_pts.shape[0]:
                    ax.scatter(m_pts[:, j], m_pts[:, i], s=ms, c=MODEL_COLOR, alpha=0.45, lw=0, rasterized=True)
                ax.set_ylim(*lims[i])
            ax.set_xlim(*lims[j])
            ax.tick_params(labelsize="x-small")
            if i == k - 1:
                ax.set_xlabel(column_label(names[j]), fontsize="small")
            else:
                ax.set_xticklabels([])
            if j == 0 and i > 0:
                ax.set_ylabel(column_label(names[i]), fontsize="small")
            elif j > 0 and i != j:
                ax.set_yticklabels([])
    handles = [
        Line2D([], [], marker="o", ls="", color=DATA_COLOR, label=f"data: target (n = {d_tab.shape[0]})"),
        Line2D([], [], marker="o", ls="", color=MODEL_COLOR, label=f"model: best fit (n = {m_tab.shape[0]})"),
    ]
    if k > 1:  # in the empty upper triangle, outside the layout
        fig.legend(handles=handles, loc="upper right", bbox_to_anchor=(0.98, 0.93), fontsize="medium", frameon=False)
    else:
        axes[0, 0].legend(handles=handles, fontsize="small")
    if title:
        fig.suptitle(title)
    return save_figure(fig, path, dpi)


def per_line_ks(u_model: np.ndarray, u_data: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Two-sample KS statistic of the projections on every line, vectorised over lines.

    Equals ``scipy.stats.ks_2samp(u_model @ a, u_data @ a).statistic`` for each row ``a`` of
    ``directions`` (ties handled: the ECDF difference is taken after each run of equal values).
    """
    u_model = np.asarray(u_model, float)
    u_data = np.asarray(u_data, float)
    A = np.asarray(directions, float)
    nm, nd = u_model.shape[0], u_data.shape[0]
    if nm == 0 or nd == 0:
        return np.ones(A.shape[0])
    z = np.concatenate([u_data @ A.T, u_model @ A.T], axis=0)  # (N, L)
    w = np.concatenate([np.full(nd, 1.0 / nd), np.full(nm, -1.0 / nm)])
    order = np.argsort(z, axis=0, kind="stable")
    zs = np.take_along_axis(z, order, axis=0)
    c = np.cumsum(w[order], axis=0)
    last = np.ones_like(zs, dtype=bool)
    last[:-1] = zs[1:] != zs[:-1]
    return np.max(np.abs(c) * last, axis=0)


def column_gaps(u_model: np.ndarray, u_data: np.ndarray, columns: Sequence[str]) -> list[dict]:
    """Each feature column compared on its own: two-sample KS statistic (1 when a side has no
    rows) and the medians of both sides (None for a side without rows), largest gap first.

    Circular pairs ``sin(x)``, ``cos(x)`` are compared as the angle x in degrees
    (:func:`display_columns`). The sliced distance looks at projections on many lines; this is its
    view along the axes, the place to start when a distance is large (which column differs, and
    which way).
    """
    dm, names = display_columns(u_model, columns)
    dd, _ = display_columns(u_data, columns)
    ks = per_line_ks(dm, dd, np.eye(len(names)))
    med = lambda t, i: float(np.median(t[:, i])) if t.shape[0] else None  # noqa: E731  (None: no rows)
    rows = [
        {"column": n, "ks": float(ks[i]), "median_model": med(dm, i), "median_data": med(dd, i)}
        for i, n in enumerate(names)
    ]
    return sorted(rows, key=lambda r: -r["ks"])


def _ecdf(x):
    x = np.sort(np.asarray(x, float))
    return x, np.arange(1, x.size + 1) / x.size


def plot_ecdf_line(ax, x_model: np.ndarray, x_data: np.ndarray, label: str | None = None):
    """ECDFs of data (blue) and model (red) projections on one line, with the KS gap marked.

    Returns the KS statistic.
    """
    xd, Fd = _ecdf(x_data)
    xm, Fm = _ecdf(x_model)
    if xd.size:
        ax.step(np.r_[xd[0], xd], np.r_[0, Fd], where="post", color=DATA_COLOR, lw=1.4, label="data (target)")
    if xm.size:
        ax.step(np.r_[xm[0], xm], np.r_[0, Fm], where="post", color=MODEL_COLOR, lw=1.4, label="model (best fit)")
    ks = 1.0
    if xd.size and xm.size:
        z = np.concatenate([xd, xm])
        F1 = np.searchsorted(xd, z, side="right") / xd.size
        F2 = np.searchsorted(xm, z, side="right") / xm.size
        k = int(np.argmax(np.abs(F1 - F2)))
        ks = float(abs(F1[k] - F2[k]))
        ax.plot([z[k], z[k]], [F1[k], F2[k]], color="black", lw=2.0, solid_capstyle="butt")
        ax.annotate(
            f"KS = {ks:.3f}",
            (z[k], 0.5 * (F1[k] + F2[k])),
            xytext=(6, 0),
            textcoords="offset points",
            fontsize="small",
            va="center",
        )
    ax.set_ylim(-0.02, 1.02)
    ax.set_ylabel("ECDF")
    if label:
        ax.set_title(label, fontsize="small")
    return ks


def _line_formula(a: np.ndarray, names: Sequence[str], top: int = 3) -> str:
    idx = np.argsort(-np.abs(a))[:top]
    parts = []
    for n, i in enumerate(idx):
        c = a[i]
        sign = "-" if c < 0 else ("+" if n else "")
        parts.append(f"{sign}{abs(c):.2f}·{names[i]}")
    more = " …" if len(a) > top else ""
    return " ".join(parts) + more


def worst_lines_figure(
    u_model: np.ndarray,
    u_data: np.ndarray,
    directions: np.ndarray,
    columns: Sequence[str],
    path,
    line_values: np.ndarray | None = None,
    statistic: str = "ks",
    k: int = 4,
    title: str | None = None,
    normalised: bool = False,
    dpi: int = 120,
) -> Path:
    """Where the model misses the data: the distribution of the per-line statistic and the
    ECDFs of both sides on the ``k`` worst lines, with the KS gap marked.

    ``u_model``/``u_data`` must already be in the distance's units (normalised if it
    normalises); ``line_values`` are the distance's own per-line values when it provides them,
    else the KS statistic is computed on every line (:func:`per_line_ks`).
    """
    A = np.asarray(directions, float)
    vals = per_line_ks(u_model, u_data, A) if line_values is None else np.asarray(line_values, float)
    stat_name = (statistic if line_values is not None else "ks").upper()
    worst = np.argsort(-vals, kind="stable")[:k]
    ncol = min(k + 1, 4)  # panels wrap into rows: the figure stays readable at a normal size
    nrow = -(-(k + 1) // ncol)
    fig = new_figure(*capped_size(3.6 * ncol, 3.4 * nrow, dpi))
    axes = fig.subplots(nrow, ncol, squeeze=False).ravel()
    for ax in axes[k + 1 :]:
        ax.set_visible(False)
    ax = axes[0]
    ax.hist(vals, bins=min(30, max(5, vals.size // 4)), color="#bbbbbb", edgecolor="#777777")
    ax.axvline(vals.mean(), color="black", lw=1.5, label=f"mean = {vals.mean():.3f}")
    for i in worst:
        ax.axvline(vals[i], color=MODEL_COLOR, lw=0.8, ls=":")
    ax.set_xlabel(f"{stat_name} per line")
    ax.set_ylabel("number of lines")
    ax.set_title(f"{A.shape[0]} lines", fontsize="small")
    ax.legend(fontsize="x-small")
    for ax, i in zip(axes[1:], worst):
        a = A[i]
        plot_ecdf_line(
            ax,
            u_model @ a,
            u_data @ a,
            label=f"line {i} ({stat_name} {vals[i]:.3f})\n{_line_formula(a, list(columns))}",
        )
        ax.set_xlabel("projection" + (" (normalised units)" if normalised else ""), fontsize="small")
    axes[1].legend(fontsize="x-small", loc="lower right")
    if title:
        fig.suptitle(title)
    return save_figure(fig, path, dpi)


# ---------------------------------------------------------------------------------- run report
def distance_view(dist: LineDistance, name: str, um: np.ndarray, ud: np.ndarray):
    """Tables in the distance's own units and its per-line values, when it exposes them.

    Uses the frozen per-set normalisation of a prepared sliced distance
    (``normalizations()[set] = {"center", "scale"}``) and its per-line statistic
    (``line_values(u_model, u_data, set_name)``); a distance without them is shown in raw units
    with the KS statistic computed per line by the figure.

    Returns ``(um, ud, line_values or None, statistic, normalised)``.
    """
    stat = str(dist.statistic)
    try:
        lines = np.asarray(dist.line_values(um, ud, set_name=name), float).reshape(-1)
    except (TypeError, ValueError, NotImplementedError):
        lines = None
    normalised = False
    nd = dist.normalizations().get(name)
    if nd and nd.get("method", "none") != "none":
        c = np.asarray(nd["center"], float)
        sc = np.asarray(nd["scale"], float)
        if c.shape == (ud.shape[1],) and sc.shape == (ud.shape[1],):
            um, ud, normalised = (um - c) / sc, (ud - c) / sc, True
    return um, ud, lines, stat, normalised


def fig_sets(v: RunView):
    out = []
    if not v.U_data:
        return out
    Um = v.U_model
    if Um is None:
        v.note("data-set figures show the data only: the best-fit tree's data sets are not available")
    dist = v.worker_parts[1] if v.worker_parts is not None else None
    per_set = (v.best or {}).get("per_set", {})
    for name, ud in v.U_data.items():
        if "/" in name:  # a set of another objective term (e.g. a one-row summary): no scatter
            continue
        um = Um.get(name, np.empty((0, ud.shape[1]))) if Um is not None else np.empty((0, ud.shape[1]))
        cols = v.columns.get(name) or [f"x{i}" for i in range(ud.shape[1])]
        D = per_set.get(name)
        title = f"data set {name}: data (target) vs best-fit model (SSM)" + (f", D = {D:.4f}" if D is not None else "")
        p = set_scatter_figure(ud, um, cols, v.store.figures_dir / f"set_{slug(name)}.png", title=title)
        out.append((p, f"Set {name}: every pair of variates, data blue, model red (angles in degrees)"))
        if dist is None or um.shape[0] == 0 or ud.shape[0] == 0:
            continue
        if not isinstance(dist, LineDistance):
            v.note(f"worst-lines figures skipped: distance '{dist.name}' does not project on lines")
            dist = None
            continue
        A = np.asarray(dist.directions(ud.shape[1]), float)
        um2, ud2, lines, stat, normalised = distance_view(dist, name, um, ud)
        p = worst_lines_figure(
            um2,
            ud2,
            A,
            cols,
            v.store.figures_dir / f"lines_{slug(name)}.png",
            line_values=lines,
            statistic=stat,
            normalised=normalised,
            title=f"data set {name}: the worst-fitting projection lines",
        )
        out.append(
            (
                p,
                f"Set {name}: per-line statistic over all {A.shape[0]} lines and the ECDFs of data "
                "(blue) and model (red) on the worst lines, KS gap in black",
            )
        )
    return out
