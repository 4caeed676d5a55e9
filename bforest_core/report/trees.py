"""Figures of trees, data sets, fits, clones and optimiser runs (matplotlib, headless).

Every ``*_figure`` function draws on a fresh :class:`matplotlib.figure.Figure` (no pyplot, no
global backend switch: it renders with Agg and never needs a display) and writes a PNG. The
drawing primitives (:func:`plot_tree`, :func:`plot_ecdf_line`, ...) take an ``Axes`` so they can
be reused in notebooks and other figures.

Conventions follow Potapov et al. (GigaScience 2017): the data side (QSM) is blue, the model side
(SSM) red; cylinders are drawn as segments whose width is proportional to the radius and whose
colour is the branch order; lengths are in metres and angles in degrees.
"""
from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
from matplotlib.collections import LineCollection
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch
from matplotlib.ticker import MaxNLocator

__all__ = ["ORDER_COLORS", "DATA_COLOR", "MODEL_COLOR", "VIEWS", "order_colors", "radius_linewidths",
           "tree_segments", "plot_tree", "order_legend", "save_tree_figure", "tree_comparison_figure",
           "clones_figure", "clone_metrics_figure", "display_columns", "set_scatter_figure",
           "per_line_ks", "plot_ecdf_line", "worst_lines_figure", "convergence_figure",
           "parameter_scatter_figure", "chain_figure", "corner_figure", "profile_figure",
           "compare_figure", "new_figure", "save_figure"]

#: colours of branch orders 0 (trunk), 1, 2, ...; the last one repeats for higher orders
ORDER_COLORS = ("#5a3a1a", "#1f77b4", "#2ca02c", "#ff7f0e", "#9467bd", "#d62728", "#17becf",
                "#e377c2", "#8c8c8c")
DATA_COLOR = "#1f5fbf"   # QSM / target (blue, as in the GigaScience figures)
MODEL_COLOR = "#d62728"  # SSM / model (red)
TARGET_LINE = "black"

#: view name -> (horizontal coordinate, vertical coordinate, coordinate pointing at the viewer,
#: sign). "xz" looks along +y (y points away), "yz" along -x, "xy" down from above.
VIEWS = {"xz": (0, 2, 1, -1.0), "yz": (1, 2, 0, 1.0), "xy": (0, 1, 2, 1.0)}
_AXIS_NAMES = "xyz"
_VIEW_TITLES = {"xz": "side view (XZ)", "yz": "side view (YZ)", "xy": "top view (XY)"}

#: units of the branch-segment feature columns (spec features-distance §2)
COLUMN_UNITS = {"beta": "deg", "alpha": "deg", "gamma": "deg", "zeta": "deg", "L_t": "m", "R_f": "m",
                "L_a": "m", "R": "m", "L": "m", "angle": "deg", "length": "m"}
_GREEK = {"beta": r"$\beta$", "alpha": r"$\alpha$", "gamma": r"$\gamma$", "zeta": r"$\zeta$",
          "L_t": r"$L_t$", "R_f": r"$R_f$", "L_a": r"$L_a$"}


# ---------------------------------------------------------------------------------- figures
def new_figure(width: float, height: float, layout: str | None = "constrained") -> Figure:
    """A new Agg-backed figure (inches)."""
    fig = Figure(figsize=(width, height), layout=layout)
    return fig


def save_figure(fig: Figure, path, dpi: int = 130) -> Path:
    """Write ``fig`` as PNG (creating the folder) and return the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi, facecolor="white")
    return path


def column_label(name: str) -> str:
    """Axis label of a feature column with its unit, e.g. ``"β (deg)"``."""
    unit = COLUMN_UNITS.get(name)
    shown = _GREEK.get(name, name)
    return f"{shown} ({unit})" if unit else shown


# ---------------------------------------------------------------------------------- trees
def order_colors(order: np.ndarray) -> np.ndarray:
    """RGBA colour of each cylinder from its branch order (vectorised lookup)."""
    from matplotlib.colors import to_rgba_array
    palette = to_rgba_array(ORDER_COLORS)
    return palette[np.clip(np.asarray(order, int), 0, len(ORDER_COLORS) - 1)]


def radius_linewidths(radius: np.ndarray, lw_max: float = 4.0, lw_min: float = 0.35,
                      r_max: float | None = None) -> np.ndarray:
    """Line widths in points proportional to the cylinder radius.

    The thickest cylinder (or ``r_max``, to draw several trees on one scale) gets ``lw_max``;
    widths are floored at ``lw_min`` so the thinnest twigs stay visible.
    """
    radius = np.asarray(radius, float)
    if r_max is None:
        r_max = float(radius.max()) if radius.size else 1.0
    r_max = r_max if r_max > 0 else 1.0
    return np.maximum(lw_min, lw_max * radius / r_max)


def _origin_of(tree, origin) -> np.ndarray:
    if origin is None or origin == "data":
        return np.zeros(3)
    if isinstance(origin, str):
        if origin != "base":
            raise ValueError(f"origin must be 'base', 'data' or a point, got {origin!r}")
        return np.asarray(tree.start[0], float)  # root cylinder (row 0 after parent-first sort)
    return np.asarray(origin, float).reshape(3)


def tree_segments(tree, view: str = "xz", origin="base", offset=(0.0, 0.0)):
    """Projected segments of a tree for one view.

    Returns
    -------
    segments : (n, 2, 2) array
        Start and end point of every cylinder in the view's (horizontal, vertical) plane, sorted
        far-to-near so nearer cylinders are drawn on top.
    order : (n,) int array
        Row of the tree of each segment (the sort permutation).
    """
    if view not in VIEWS:
        raise ValueError(f"view must be one of {', '.join(VIEWS)}, got {view!r}")
    h, v, d, sign = VIEWS[view]
    o = _origin_of(tree, origin)
    s = np.asarray(tree.start, float) - o
    e = np.asarray(tree.end, float) - o
    depth = sign * 0.5 * (s[:, d] + e[:, d])
    perm = np.argsort(depth, kind="stable")
    segs = np.empty((tree.n, 2, 2))
    segs[:, 0, 0] = s[perm, h] + offset[0]
    segs[:, 0, 1] = s[perm, v] + offset[1]
    segs[:, 1, 0] = e[perm, h] + offset[0]
    segs[:, 1, 1] = e[perm, v] + offset[1]
    return segs, perm


def plot_tree(ax, tree, view: str = "xz", color_by: str = "order", *, origin="base", offset=(0.0, 0.0),
              lw_max: float = 4.0, lw_min: float = 0.35, r_max: float | None = None, cmap: str = "viridis",
              alpha: float = 1.0, label_axes: bool = True, autoscale: bool = True, zorder: float = 2):
    """Draw a cylinder tree in one 2-D projection as a single :class:`LineCollection`.

    Parameters
    ----------
    ax : matplotlib Axes
    tree : Tree
    view : {"xz", "yz", "xy"}
        Projection plane: side views XZ and YZ, top view XY.
    color_by : {"order", "radius", "branch"} or a matplotlib colour
        Branch order (trunk brown, order 1 blue, ...; see :data:`ORDER_COLORS`), radius
        (colormap ``cmap``), branch id (random distinct colours), or one colour for all.
    origin : "base", "data" or (3,) point
        "base" puts the base of the trunk (start of the root cylinder) at (0, 0, 0), so heights
        are above the stem base; "data" keeps the file's coordinates.
    offset : (dx, dy)
        Shift in the view plane (m), to place several trees side by side on one axes.
    lw_max, lw_min, r_max
        Line widths in points: proportional to radius, thickest (or ``r_max``) = ``lw_max``,
        floored at ``lw_min`` (see :func:`radius_linewidths`).

    Returns
    -------
    LineCollection
    """
    segs, perm = tree_segments(tree, view, origin, offset)
    radius = np.asarray(tree.radius)[perm]
    lw = radius_linewidths(radius, lw_max=lw_max, lw_min=lw_min, r_max=r_max)
    kw = {}
    if color_by == "order":
        kw["colors"] = order_colors(np.asarray(tree.order)[perm])
    elif color_by == "branch":
        rng = np.random.default_rng(0)
        pal = rng.random((int(np.asarray(tree.branch).max()) + 1, 3)) * 0.8
        kw["colors"] = pal[np.asarray(tree.branch)[perm]]
    elif color_by == "radius":
        pass
    else:
        kw["colors"] = color_by
    lc = LineCollection(segs, linewidths=lw, capstyle="round", joinstyle="round", alpha=alpha,
                        zorder=zorder, **kw)
    if color_by == "radius":
        lc.set_array(radius * 100.0)
        lc.set_cmap(cmap)
    ax.add_collection(lc, autolim=True)
    h, v = VIEWS[view][:2]
    if autoscale:
        ax.set_aspect("equal", adjustable="datalim")
        ax.autoscale_view()
    if label_axes:
        ax.set_xlabel(f"{_AXIS_NAMES[h]} (m)")
        ax.set_ylabel(f"{_AXIS_NAMES[v]} (m)")
    return lc


def order_legend(ax, orders: Sequence[int], loc: str = "upper right", title: str = "branch order", **kw):
    """Legend of the branch-order colours present in ``orders`` (``ax`` may be an Axes or a
    Figure)."""
    return ax.legend(handles=order_handles(orders), loc=loc, title=title, fontsize="small",
                     title_fontsize="small", framealpha=0.85, **kw)


def order_handles(orders: Sequence[int]) -> list:
    """Legend handles of the branch-order colours present in ``orders``."""
    orders = sorted({int(o) for o in orders})
    last = len(ORDER_COLORS) - 1
    handles, seen = [], set()
    for o in orders:
        key = min(o, last)
        if key in seen:
            continue
        seen.add(key)
        label = "0 (trunk)" if o == 0 else (f"{o}" if o < last else f"{last}+")
        handles.append(Line2D([], [], color=ORDER_COLORS[key], lw=3, label=label))
    return handles


def _extent(trees, view, origin="base"):
    """(hmin, hmax, vmin, vmax) over trees in one view, relative to each tree's origin."""
    h, v = VIEWS[view][:2]
    lo, hi = np.full(2, np.inf), np.full(2, -np.inf)
    for t in trees:
        o = _origin_of(t, origin)
        pts = np.concatenate([t.start, t.end]) - o
        lo = np.minimum(lo, pts[:, [h, v]].min(0))
        hi = np.maximum(hi, pts[:, [h, v]].max(0))
    return lo[0], hi[0], lo[1], hi[1]


def _set_limits(ax, ext, pad=0.04):
    h0, h1, v0, v1 = ext
    ph = max(h1 - h0, 1e-3) * pad
    pv = max(v1 - v0, 1e-3) * pad
    ax.set_xlim(h0 - ph, h1 + ph)
    ax.set_ylim(v0 - pv, v1 + pv)
    ax.set_aspect("equal", adjustable="box")


def _tree_caption(tree) -> str:
    try:
        from .metrics import classical_metrics
        m = classical_metrics(tree)
        return (f"{tree.n} cylinders, {tree.n_branches} branches, height {m['height']:.2f} m, "
                f"girth {m['girth']:.3f} m, crown spread {m['crown_spread']:.2f} m")
    except Exception:
        return f"{tree.n} cylinders, {tree.n_branches} branches, max order {tree.max_order}"


def _view_ratios(trees, views, lo: float = 0.4, hi: float = 2.5):
    """Width/height of each view's panel: the trees' own proportions, clipped to [lo, hi]."""
    ratios = []
    for vw in views:
        h0, h1, v0, v1 = _extent(trees, vw)
        ratios.append(float(np.clip((h1 - h0) / max(v1 - v0, 1e-9), lo, hi)))
    return ratios


def _fit_ratio(ext, ratio: float):
    """Grow an extent (about its centre) to the width/height ``ratio`` of its panel, so an
    equal-aspect plot fills the panel (a very slender tree gets room beside it)."""
    h0, h1, v0, v1 = ext
    w, h = max(h1 - h0, 1e-6), max(v1 - v0, 1e-6)
    if w / h < ratio:
        c, w = 0.5 * (h0 + h1), ratio * h
        h0, h1 = c - w / 2, c + w / 2
    elif w / h > ratio:
        c, h = 0.5 * (v0 + v1), w / ratio
        v0, v1 = c - h / 2, c + h / 2
    return h0, h1, v0, v1


def save_tree_figure(tree, path, title: str | None = None, views: Sequence[str] = ("xz", "yz", "xy"),
                     color_by: str = "order", dpi: int = 130) -> Path:
    """One tree in three projections (side views XZ, YZ and the top view XY), coloured by
    branch order, line width proportional to radius (GigaScience Fig. 6)."""
    return tree_comparison_figure({"": tree}, path, title=title, views=views, color_by=color_by, dpi=dpi)


def tree_comparison_figure(trees: Mapping[str, object], path, title: str | None = None,
                           views: Sequence[str] = ("xz", "yz", "xy"), color_by: str = "order",
                           dpi: int = 130, captions: bool = True) -> Path:
    """Several trees (rows, e.g. target and best fit) in the same projections (columns), on one
    scale: every panel of a column has the same limits and widths use one radius scale."""
    items = list(trees.items())
    tlist = [t for _, t in items]
    ratios = _view_ratios(tlist, views)
    row_h = 4.2
    fig = new_figure(max(6.0, row_h * sum(ratios) + 1.4), (row_h + 0.3) * len(items) + (0.4 if title else 0.0))
    rows = fig.subfigures(len(items), 1, squeeze=False)[:, 0] if len(items) > 1 else [fig]
    r_max = max(float(np.max(t.radius)) for t in tlist)
    exts = {vw: _fit_ratio(_extent(tlist, vw), r) for vw, r in zip(views, ratios)}
    orders = set(int(o) for t in tlist for o in np.unique(t.order))
    first_axes = None
    for sub, (label, tree) in zip(rows, items):
        axes = sub.subplots(1, len(views), squeeze=False, gridspec_kw={"width_ratios": ratios})[0]
        first_axes = axes if first_axes is None else first_axes
        for ax, vw in zip(axes, views):
            plot_tree(ax, tree, vw, color_by, r_max=r_max, autoscale=False)
            _set_limits(ax, exts[vw])
            ax.grid(True, lw=0.3, alpha=0.4)
            ax.set_title(_VIEW_TITLES[vw], fontsize="medium")
        if captions or label:
            head = f"{label}: " if label else ""
            cap = _tree_caption(tree) if captions else ""
            if len(items) > 1:
                sub.suptitle(head + cap, fontsize="medium", fontweight="bold" if label else "normal")
            elif cap:
                sub.supxlabel(head + cap, fontsize="medium")
    if color_by == "order":  # one legend for all rows, beside them
        order_legend(fig, orders, loc="outside right upper")
    if title:
        fig.suptitle(title, fontsize="large")
    return save_figure(fig, path, dpi)


def _slots(trees, min_width: float = 0.0, gap_frac: float = 0.1):
    """Horizontal (x) offsets placing trees side by side, each centred on its stem base in a
    slot at least ``min_width`` wide; returns ``(offsets, slot_edges)``."""
    exts = [_extent([t], "xy") for t in trees]  # x range (and y) about each stem base
    widths = [max(e[1] - e[0], min_width) for e in exts]
    gap = gap_frac * max(max(widths), 1e-3)
    offs, edges, x = [], [], 0.0
    for e, w in zip(exts, widths):
        centre = 0.5 * (e[0] + e[1])
        offs.append(x + 0.5 * w - centre)
        edges.append((x, x + w))
        x += w + gap
    return offs, edges


def clones_figure(target, clones: Sequence[tuple[str, object]], path, title: str | None = None,
                  views: Sequence[str] = ("xz", "xy"), dpi: int = 130) -> Path:
    """The target and several clones side by side on one scale (GigaScience Fig. 5): one row
    per view ("xz" side view, "xy" top view); a tree keeps the same x slot in every row, so its
    top view sits under its side view."""
    for vw in views:
        if vw not in ("xz", "xy"):
            raise ValueError(f"clones_figure draws the views 'xz' and 'xy' (x along the row), got {vw!r}")
    trees = [("target", target)] + list(clones)
    tl = [t for _, t in trees]
    r_max = max(float(np.max(t.radius)) for t in tl)
    height = max(_extent([t], "xz")[3] - min(0.0, _extent([t], "xz")[2]) for t in tl)
    offs, edges = _slots(tl, min_width=0.3 * height if "xz" in views else 0.0)
    x0, x1 = edges[0][0], edges[-1][1]
    vext = {}
    slot = max(e1 - e0 for e0, e1 in edges)
    for vw in views:
        es = [_extent([t], vw) for t in tl]
        lo, hi = min(e[2] for e in es), max(e[3] for e in es)
        if vw == "xy" and hi - lo < slot:  # top views get (at least) square slots
            c = 0.5 * (lo + hi)
            lo, hi = c - slot / 2, c + slot / 2
        vext[vw] = (lo, hi)
    hr = [max(0.08, (vext[vw][1] - vext[vw][0]) / (x1 - x0)) for vw in views]
    fig_w = 14.0
    fig_w = min(fig_w, 9.5 / sum(hr)) if fig_w * sum(hr) > 9.5 else fig_w
    fig = new_figure(max(fig_w, 7.0), fig_w * sum(hr) + 0.5 + 0.45 * len(views))
    axes = fig.subplots(len(views), 1, squeeze=False, gridspec_kw={"height_ratios": hr})[:, 0]
    for r, (ax, vw) in enumerate(zip(axes, views)):
        for (label, t), off, (e0, e1) in zip(trees, offs, edges):
            plot_tree(ax, t, vw, "order", offset=(off, 0.0), r_max=r_max, lw_max=3.0, lw_min=0.3,
                      autoscale=False, label_axes=False)
            if r == 0:
                if label == "target":
                    label = f"target\n{t.n} cylinders"
                ax.text(0.5 * (e0 + e1), 1.01, label, transform=ax.get_xaxis_transform(), ha="center",
                        va="bottom", fontsize="small", color=DATA_COLOR if label.startswith("target") else "black",
                        fontweight="bold" if label.startswith("target") else "normal")
        _set_limits(ax, (x0, x1, vext[vw][0], vext[vw][1]), pad=0.02)
        h, v = VIEWS[vw][:2]
        ax.set_ylabel(f"{_AXIS_NAMES[v]} (m)")
        ax.set_xlabel(f"{_AXIS_NAMES[h]} (m; trees side by side, each centred on its stem base)", fontsize="small")
        ax.grid(True, lw=0.3, alpha=0.4)
    orders = set()
    for t in tl:
        orders.update(np.unique(t.order).tolist())
    order_legend(axes[0], orders, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    if title:
        fig.suptitle(title)
    return save_figure(fig, path, dpi)


_METRIC_PANELS = (("height", "height (m)"), ("girth", "girth (m)"), ("crown_spread", "crown spread (m)"),
                  ("distance", "structural distance D"),
                  ("d_h", "$d_h$ (height, rel. error)"), ("d_g", "$d_g$ (girth, rel. error)"),
                  ("d_c", "$d_c$ (crown spread, rel. error)"), ("n_cylinders", "cylinders"))


def clone_metrics_figure(values: Mapping[str, np.ndarray], path, target: Mapping[str, float] | None = None,
                         best: Mapping[str, float] | None = None, title: str | None = None,
                         dpi: int = 130) -> Path:
    """Distributions over the clones of height, girth, crown spread, distance and the relative
    errors d_h, d_g, d_c (GigaScience Fig. 5D); the target's value is a black line, the best-fit
    tree's a red dashed line."""
    panels = [(k, lab) for k, lab in _METRIC_PANELS if k in values and np.isfinite(values[k]).any()]
    ncol = 4
    nrow = max(1, math.ceil(len(panels) / ncol))
    fig = new_figure(3.3 * ncol, 2.8 * nrow + 0.5)
    axes = fig.subplots(nrow, ncol, squeeze=False).ravel()
    target, best = dict(target or {}), dict(best or {})
    for ax, (key, lab) in zip(axes, panels):
        x = np.asarray(values[key], float)
        x = x[np.isfinite(x)]
        bins = min(30, max(5, int(np.sqrt(x.size)) + 2))
        ax.hist(x, bins=bins, color="#9bbcd9", edgecolor="#4a6f94", lw=0.6)
        ax.set_xlabel(lab)
        ax.set_ylabel("clones")
        ax.yaxis.get_major_locator().set_params(integer=True)
        ax.xaxis.set_major_locator(MaxNLocator(nbins=4))  # narrow ranges print long tick labels
        tv = target.get(key)
        if key in ("d_h", "d_g", "d_c"):
            tv = 0.0 if target else None
        if tv is not None and np.isfinite(tv):
            ax.axvline(tv, color=TARGET_LINE, lw=1.8, label="target")
        bv = best.get(key)
        if bv is not None and np.isfinite(bv):
            ax.axvline(bv, color=MODEL_COLOR, lw=1.5, ls="--", label="best fit")
        ax.set_title(f"median {np.median(x):.3g}, n = {x.size}", fontsize="small")
    for ax in axes[len(panels):]:
        ax.set_visible(False)
    if panels:
        handles = [Line2D([], [], color=TARGET_LINE, lw=1.8, label="target"),
                   Line2D([], [], color=MODEL_COLOR, lw=1.5, ls="--", label="best-fit tree"),
                   Patch(facecolor="#9bbcd9", edgecolor="#4a6f94", label="clones")]
        fig.legend(handles=handles, loc="outside lower center", ncols=3, fontsize="small")
    if title:
        fig.suptitle(title)
    return save_figure(fig, path, dpi)


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


def set_scatter_figure(data: np.ndarray, model: np.ndarray, columns: Sequence[str], path,
                       title: str | None = None, max_points: int = 4000, seed: int = 0,
                       dpi: int = 120) -> Path:
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
                    ax.hist(d_tab[:, j], bins=bins, density=True, histtype="stepfilled", color=DATA_COLOR,
                            alpha=0.35)
                    ax.hist(d_tab[:, j], bins=bins, density=True, histtype="step", color=DATA_COLOR, lw=1.0)
                if m_tab.shape[0]:
                    ax.hist(m_tab[:, j], bins=bins, density=True, histtype="step", color=MODEL_COLOR, lw=1.4)
                ax.set_yticks([])
            else:
                ax.scatter(d_pts[:, j], d_pts[:, i], s=ms, c=DATA_COLOR, alpha=0.45, lw=0, rasterized=True)
                if m_pts.shape[0]:
                    ax.scatter(m_pts[:, j], m_pts[:, i], s=ms, c=MODEL_COLOR, alpha=0.45, lw=0,
                               rasterized=True)
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
    handles = [Line2D([], [], marker="o", ls="", color=DATA_COLOR, label=f"data: target (n = {d_tab.shape[0]})"),
               Line2D([], [], marker="o", ls="", color=MODEL_COLOR, label=f"model: best fit (n = {m_tab.shape[0]})")]
    if k > 1:  # in the empty upper triangle, outside the layout
        fig.legend(handles=handles, loc="upper right", bbox_to_anchor=(0.98, 0.93), fontsize="medium",
                   frameon=False)
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
    z = np.concatenate([u_data @ A.T, u_model @ A.T], axis=0)          # (N, L)
    w = np.concatenate([np.full(nd, 1.0 / nd), np.full(nm, -1.0 / nm)])
    order = np.argsort(z, axis=0, kind="stable")
    zs = np.take_along_axis(z, order, axis=0)
    c = np.cumsum(w[order], axis=0)
    last = np.ones_like(zs, dtype=bool)
    last[:-1] = zs[1:] != zs[:-1]
    return np.max(np.abs(c) * last, axis=0)


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
        ax.annotate(f"KS = {ks:.3f}", (z[k], 0.5 * (F1[k] + F2[k])), xytext=(6, 0), textcoords="offset points",
                    fontsize="small", va="center")
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


def worst_lines_figure(u_model: np.ndarray, u_data: np.ndarray, directions: np.ndarray,
                       columns: Sequence[str], path, line_values: np.ndarray | None = None,
                       statistic: str = "ks", k: int = 4, title: str | None = None, normalised: bool = False,
                       dpi: int = 120) -> Path:
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
    fig = new_figure(3.4 * (k + 1), 3.3)
    axes = fig.subplots(1, k + 1, squeeze=False)[0]
    ax = axes[0]
    ax.hist(vals, bins=min(30, max(5, vals.size // 4)), color="#bbbbbb", edgecolor="#777777")
    ax.axvline(vals.mean(), color="black", lw=1.5, label=f"mean = {vals.mean():.3f}")
    for i in worst:
        ax.axvline(vals[i], color=MODEL_COLOR, lw=0.8, ls=":")
    ax.set_xlabel(f"{stat_name} per line")
    ax.set_ylabel("lines")
    ax.set_title(f"{A.shape[0]} lines", fontsize="small")
    ax.legend(fontsize="x-small")
    for ax, i in zip(axes[1:], worst):
        a = A[i]
        plot_ecdf_line(ax, u_model @ a, u_data @ a,
                       label=f"line {i} ({stat_name} {vals[i]:.3f})\n{_line_formula(a, list(columns))}")
        ax.set_xlabel("projection" + (" (normalised units)" if normalised else ""), fontsize="small")
    axes[1].legend(fontsize="x-small", loc="lower right")
    if title:
        fig.suptitle(title)
    return save_figure(fig, path, dpi)


# ---------------------------------------------------------------------------------- fit diagnostics
def convergence_figure(distances: np.ndarray, path, statuses: Sequence[str] | None = None,
                       records: Sequence[Mapping] | None = None, title: str | None = None,
                       dpi: int = 130) -> Path:
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
        ax.scatter(x[~ok], np.full((~ok).sum(), 0.97), transform=ax.get_xaxis_transform(), marker="x",
                   color="#e6550d", s=18, lw=1.0, label=f"failed ({(~ok).sum()}, penalty)", clip_on=False)
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
        for key, style in (("best", dict(color=MODEL_COLOR, lw=1.8, marker="o", ms=3)),
                           ("mean", dict(color="#1f77b4", lw=1.2, marker=".", ms=3)),
                           ("median", dict(color="#2ca02c", lw=1.2, ls="--"))):
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


def parameter_scatter_figure(names: Sequence[str], X: np.ndarray, distances: np.ndarray, path,
                             best: Mapping[str, float] | None = None,
                             bounds: Mapping[str, tuple[float, float]] | None = None,
                             units: Mapping[str, str] | None = None,
                             title: str | None = None, dpi: int = 130) -> Path:
    """Distance against each free parameter over the successful evaluations, coloured by
    evaluation number (where the optimiser looked, and when); the best fit is a red star."""
    X = np.asarray(X, float).reshape(len(distances), len(names))
    d = np.asarray(distances, float)
    p = len(names)
    ncol = min(p, 3)
    nrow = math.ceil(p / ncol)
    fig = new_figure(4.3 * ncol + 0.8, 3.4 * nrow)
    axes = fig.subplots(nrow, ncol, squeeze=False).ravel()
    sc = None
    for j, (ax, name) in enumerate(zip(axes, names)):
        sc = ax.scatter(X[:, j], d, c=np.arange(d.size), cmap="viridis", s=10, alpha=0.7, lw=0)
        if best and name in best:
            ax.scatter([best[name]], [np.min(d)] if d.size else [np.nan], marker="*", s=160, color=MODEL_COLOR,
                       edgecolor="black", lw=0.6, zorder=5, label=f"best {best[name]:.4g}")
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
        fig.colorbar(sc, ax=list(axes[:p]), label="evaluation", shrink=0.9)
    if title:
        fig.suptitle(title)
    return save_figure(fig, path, dpi)


def chain_figure(chain: np.ndarray, names: Sequence[str], path, burn_in: int = 0,
                 distances: np.ndarray | None = None, title: str | None = None, dpi: int = 120) -> Path:
    """Trace of every walker of an MCMC chain ``(steps, walkers, parameters)`` per parameter
    (and of each walker's distance, ``(steps, walkers)``), the burn-in shaded."""
    chain = np.asarray(chain, float)
    steps, walkers, p = chain.shape
    rows = p + (1 if distances is not None else 0)
    fig = new_figure(9.0, 1.7 * rows + 0.6)
    axes = fig.subplots(rows, 1, squeeze=False, sharex=True)[:, 0]
    t = np.arange(steps)
    for j in range(p):
        ax = axes[j]
        ax.plot(t, chain[:, :, j], color="black", alpha=max(0.05, min(0.5, 8.0 / walkers)), lw=0.6)
        ax.set_ylabel(names[j] if j < len(names) else f"p{j}", fontsize="small")
    if distances is not None:
        dd = np.asarray(distances, float)
        ax = axes[p]
        ax.plot(t, np.where(np.isfinite(dd), dd, np.nan), color="#1f77b4",
                alpha=max(0.05, min(0.5, 8.0 / walkers)), lw=0.6)
        ax.set_ylabel("distance D", fontsize="small")
    for ax in axes:
        if burn_in > 0:
            ax.axvspan(0, burn_in, color="#dddddd", alpha=0.6, lw=0)
        ax.grid(True, lw=0.3, alpha=0.4)
    axes[-1].set_xlabel(f"step ({walkers} walkers" + (f", burn-in {burn_in} shaded)" if burn_in else ")"))
    if title:
        fig.suptitle(title)
    return save_figure(fig, path, dpi)


def corner_figure(samples: np.ndarray, names: Sequence[str], path, truths: Sequence[float] | None = None,
                  bins: int | None = None, bounds: Sequence[tuple[float, float]] | None = None,
                  smooth: float = 1.0, title: str | None = None, dpi: int = 120) -> Path:
    """Corner plot of posterior samples ``(n, p)``: marginal histograms with the 16/50/84 %
    quantiles on the diagonal, 2-D histograms (Gaussian-smoothed by ``smooth`` bins) with
    39/86 % (1σ/2σ) contours below; ``truths`` (e.g. the best fit) in red. ``bins`` defaults
    to about sqrt(n)/2, between 8 and 30."""
    from scipy.ndimage import gaussian_filter
    S = np.asarray(samples, float)
    S = S[np.isfinite(S).all(1)]
    n, p = S.shape
    if bins is None:
        bins = int(np.clip(np.sqrt(max(n, 1)) / 2, 8, 30))
    size = 2.3 if p > 2 else 3.0
    fig = new_figure(size * p + 0.5, size * p + 0.5)
    axes = fig.subplots(p, p, squeeze=False)
    rng = []
    for j in range(p):
        lo, hi = (float(S[:, j].min()), float(S[:, j].max())) if n else (0.0, 1.0)
        if bounds is not None:
            lo, hi = max(lo, bounds[j][0]) if n else bounds[j][0], min(hi, bounds[j][1]) if n else bounds[j][1]
        if hi <= lo:
            lo, hi = lo - 0.5 * max(abs(lo), 1e-3), hi + 0.5 * max(abs(hi), 1e-3)
        rng.append((lo, hi))
    for i in range(p):
        for j in range(p):
            ax = axes[i, j]
            if j > i:
                ax.set_visible(False)
                continue
            if i == j:
                ax.hist(S[:, j], bins=bins, range=rng[j], histtype="step", color="black", lw=1.2)
                if n:
                    q = np.quantile(S[:, j], [0.16, 0.5, 0.84])
                    for v, ls in zip(q, (":", "-", ":")):
                        ax.axvline(v, color="#1f77b4", ls=ls, lw=1.0)
                    ax.set_title(f"{names[j]} = {q[1]:.3g}$^{{+{q[2] - q[1]:.2g}}}_{{-{q[1] - q[0]:.2g}}}$",
                                 fontsize="small")
                ax.set_yticks([])
                if truths is not None:
                    ax.axvline(truths[j], color=MODEL_COLOR, lw=1.2)
            else:
                H, xe, ye = np.histogram2d(S[:, j], S[:, i], bins=bins, range=[rng[j], rng[i]])
                if smooth:
                    H = gaussian_filter(H, smooth, mode="constant")
                ax.pcolormesh(xe, ye, H.T, cmap="Greys", shading="flat", rasterized=True)
                levels = _hpd_levels(H, (0.393, 0.865)) if n >= 50 else None
                if levels is not None:
                    xc, yc = 0.5 * (xe[1:] + xe[:-1]), 0.5 * (ye[1:] + ye[:-1])
                    ax.contour(xc, yc, H.T, levels=levels, colors="#1f77b4", linewidths=0.9)
                if truths is not None:
                    ax.axvline(truths[j], color=MODEL_COLOR, lw=1.0)
                    ax.axhline(truths[i], color=MODEL_COLOR, lw=1.0)
                    ax.plot(truths[j], truths[i], "s", color=MODEL_COLOR, ms=4)
                ax.set_ylim(*rng[i])
            ax.set_xlim(*rng[j])
            ax.tick_params(labelsize="x-small")
            if i == p - 1:
                ax.set_xlabel(names[j], fontsize="small")
            else:
                ax.set_xticklabels([])
            if j == 0 and i > 0:
                ax.set_ylabel(names[i], fontsize="small")
            elif i != j:
                ax.set_yticklabels([])
    if title:
        fig.suptitle(title)
    return save_figure(fig, path, dpi)


def _hpd_levels(H: np.ndarray, masses=(0.393, 0.865)):
    """Density thresholds enclosing the given probability masses of a 2-D histogram."""
    flat = np.sort(H.ravel())[::-1]
    total = flat.sum()
    if total <= 0:
        return None
    cum = np.cumsum(flat) / total
    levels = []
    for m in masses:
        k = min(int(np.searchsorted(cum, m)), flat.size - 1)
        levels.append(flat[k])
    levels = np.unique(levels)
    levels = levels[levels > 0]
    return levels if levels.size else None


# ---------------------------------------------------------------------------------- profiles, comparison
def profile_figure(values: np.ndarray, distances: np.ndarray, path, param: str,
                   failed: np.ndarray | None = None, best_value: float | None = None,
                   best_distance: float | None = None, unit: str = "", title: str | None = None,
                   dpi: int = 130) -> Path:
    """Distance profile along one parameter (GigaScience Fig. 4): one thin line per seed (a
    realisation of the distance surface), the median over seeds, the interquartile and
    min-max bands, and the best-fit value marked.

    ``distances`` is ``(len(values), seeds)``; ``failed`` (same shape) marks failed
    simulations (their penalty distance is included in the statistics).
    """
    v = np.asarray(values, float)
    D = np.asarray(distances, float).reshape(v.size, -1)
    k = D.shape[1]
    fig = new_figure(7.5, 4.6)
    ax = fig.subplots()
    for j in range(1, k):
        ax.plot(v, D[:, j], color="#888888", lw=0.7, alpha=0.6, label="other seeds" if j == 1 else None)
    ax.plot(v, D[:, 0], color="black", lw=0.9, ls="--", alpha=0.8, label="the fit's own seed")
    med = np.nanmedian(D, axis=1)
    if k > 1:
        ax.fill_between(v, np.nanmin(D, 1), np.nanmax(D, 1), color=MODEL_COLOR, alpha=0.08, lw=0, label="min–max")
        q1, q3 = np.nanquantile(D, [0.25, 0.75], axis=1)
        ax.fill_between(v, q1, q3, color=MODEL_COLOR, alpha=0.2, lw=0, label="interquartile range")
    ax.plot(v, med, color=MODEL_COLOR, lw=2.0, marker="o", ms=4, label=f"median of {k} seeds")
    if failed is not None and np.asarray(failed).any():
        f = np.asarray(failed, bool).reshape(D.shape)
        ii, jj = np.nonzero(f)
        ax.scatter(v[ii], D[ii, jj], marker="x", color="#e6550d", s=25, label="failed simulation", zorder=4)
    if best_value is not None:
        ax.axvline(best_value, color="black", lw=1.0, ls="--")
        ax.annotate(f"best fit {best_value:.4g}", (best_value, 1.0), xycoords=("data", "axes fraction"),
                    xytext=(4, -12), textcoords="offset points", ha="left", fontsize="small")
        if best_distance is not None:
            ax.plot([best_value], [best_distance], marker="v", color="black", ms=9, ls="",
                    label=f"best fit (D = {best_distance:.3f})")
    ax.set_xlabel(f"{param} ({unit})" if unit else param)
    ax.set_ylabel("distance D")
    ax.grid(True, lw=0.3, alpha=0.5)
    ax.legend(fontsize="small")
    ax.set_title(title or f"distance profile along {param} (other parameters at the best fit)", fontsize="medium")
    return save_figure(fig, path, dpi)


def _pad_curves(curves: Sequence[np.ndarray]) -> np.ndarray:
    """Best-so-far curves of unequal length as one ``(repeats, n)`` array; a finished run keeps
    its last value (its best does not change after it stops)."""
    curves = [np.minimum.accumulate(np.asarray(c, float).ravel()) for c in curves if np.size(c)]
    if not curves:
        return np.empty((0, 0))
    n = max(c.size for c in curves)
    out = np.empty((len(curves), n))
    for r, c in enumerate(curves):
        out[r, :c.size] = c
        out[r, c.size:] = c[-1]
    return out


def compare_figure(curves: Mapping[str, Sequence[np.ndarray]], path, threshold: float | None = None,
                   title: str | None = None, dpi: int = 130) -> Path:
    """Optimiser comparison: best-so-far distance against evaluations, median over repeats
    (line) and the interquartile and min-max spread (bands), one colour per optimiser.

    Parameters
    ----------
    curves : dict
        Optimiser name -> list of best-so-far (or raw distance) arrays, one per repeat, indexed by
        evaluation; shorter runs keep their last value.
    threshold : float, optional
        A target distance drawn as a dashed line (for "evaluations to reach").
    """
    from matplotlib import colormaps
    pal = colormaps["tab10"].colors
    fig = new_figure(7.8, 4.8)
    ax = fig.subplots()
    all_pos = True
    lo_all, hi_all = np.inf, -np.inf
    for c, (name, runs) in enumerate(curves.items()):
        M = _pad_curves(runs)
        if M.size == 0:
            continue
        col = pal[c % len(pal)]
        x = np.arange(1, M.shape[1] + 1)
        med = np.median(M, axis=0)
        if M.shape[0] > 1:
            ax.fill_between(x, M.min(0), M.max(0), color=col, alpha=0.08, lw=0, step="post")
            q1, q3 = np.quantile(M, [0.25, 0.75], axis=0)
            ax.fill_between(x, q1, q3, color=col, alpha=0.25, lw=0, step="post")
        ax.step(x, med, where="post", color=col, lw=2.0, label=f"{name} (median of {M.shape[0]}: {med[-1]:.4g})")
        fin = M[np.isfinite(M)]
        all_pos &= bool(np.all(fin > 0))
        lo_all, hi_all = min(lo_all, fin.min(initial=np.inf)), max(hi_all, fin.max(initial=-np.inf))
    if threshold is not None:
        ax.axhline(threshold, color="black", ls="--", lw=1.0, label=f"threshold {threshold:.4g}")
        lo_all = min(lo_all, threshold)
    if all_pos and np.isfinite(lo_all) and lo_all > 0 and hi_all / lo_all > 20:
        ax.set_yscale("log")  # best distances spanning decades
    ax.set_xlabel("evaluations")
    ax.set_ylabel("best distance so far")
    ax.grid(True, which="both", lw=0.3, alpha=0.5)
    ax.legend(fontsize="small", title="optimizer (final median)", title_fontsize="small")
    ax.set_title(title or "optimiser comparison (bands: interquartile and min–max over repeats)",
                 fontsize="medium")
    return save_figure(fig, path, dpi)
