"""Figures of trees: one tree in three views, target beside best fit, clones beside the target,
and the clones' classical metrics. The drawing primitives (:func:`plot_tree`, ...) take an ``Axes``
so they can be reused in notebooks and other figures."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from matplotlib.collections import LineCollection
from matplotlib.lines import Line2D
from matplotlib.patches import Patch
from matplotlib.ticker import MaxNLocator

from .canvas import (
    _AXIS_NAMES,
    _VIEW_TITLES,
    DATA_COLOR,
    MODEL_COLOR,
    ORDER_COLORS,
    TARGET_LINE,
    VIEWS,
    new_figure,
    save_figure,
)

if TYPE_CHECKING:  # annotations only: run_view imports this module's neighbours
    from .run_view import RunView


# ---------------------------------------------------------------------------------- trees
def order_colors(order: np.ndarray) -> np.ndarray:
    """RGBA colour of each cylinder from its branch order (vectorised lookup)."""
    from matplotlib.colors import to_rgba_array

    palette = to_rgba_array(ORDER_COLORS)
    return palette[np.clip(np.asarray(order, int), 0, len(ORDER_COLORS) - 1)]


def radius_linewidths(
    radius: np.ndarray, lw_max: float = 4.0, lw_min: float = 0.35, r_max: float | None = None
) -> np.ndarray:
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


def plot_tree(
    ax,
    tree,
    view: str = "xz",
    color_by: str = "order",
    *,
    origin="base",
    offset=(0.0, 0.0),
    lw_max: float = 4.0,
    lw_min: float = 0.35,
    r_max: float | None = None,
    cmap: str = "viridis",
    alpha: float = 1.0,
    label_axes: bool = True,
    autoscale: bool = True,
    zorder: float = 2,
):
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
    lc = LineCollection(segs, linewidths=lw, capstyle="round", joinstyle="round", alpha=alpha, zorder=zorder, **kw)
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


#: how the crown's space (its envelope) is drawn beside a tree
ENVELOPE_STYLE = {"color": "#6f6f6f", "lw": 0.9, "ls": "--"}


def envelope_lines(envelope, view: str, heights: int = 97, grid: int = 220) -> list[np.ndarray]:
    """The outline of a crown's space (:class:`~bforest_core.envelope.CrownEnvelope`, with its
    margin) in one view, relative to the stem base: the side view "xz" as one closed line (the
    envelope's reach either side, height by height), the top view "xy" as the outline of its
    footprint (every height's outline together), each a (k, 2) array."""
    if view not in ("xz", "xy"):
        raise ValueError(f"a crown's space is drawn in the views 'xz' and 'xy', got {view!r}")
    zs = np.linspace(0.0, envelope.top + envelope.margin, heights)
    rings = [envelope.outline(z) for z in zs]
    if view == "xz":
        lo = [(r[:, 0].min(), z) for r, z in zip(rings, zs)]
        hi = [(r[:, 0].max(), z) for r, z in zip(rings, zs)]
        return [np.array(lo + hi[::-1] + lo[:1])]
    from matplotlib.path import Path as MplPath

    pts = np.concatenate(rings)
    (x0, y0), (x1, y1) = pts.min(0), pts.max(0)
    pad = 0.05 * max(x1 - x0, y1 - y0, 1e-3)
    gx, gy = np.meshgrid(np.linspace(x0 - pad, x1 + pad, grid), np.linspace(y0 - pad, y1 + pad, grid))
    cells = np.stack([gx.ravel(), gy.ravel()], axis=1)
    inside = np.zeros(cells.shape[0], bool)
    for r in rings:
        inside |= MplPath(r).contains_points(cells)
    import matplotlib.pyplot as plt

    from .canvas import new_figure

    fig = new_figure(2, 2)  # contour's lines, measured on a scratch figure
    cs = fig.subplots().contour(gx, gy, inside.reshape(gx.shape).astype(float), levels=[0.5])
    lines = [seg for seg in cs.allsegs[0] if len(seg) > 2]
    plt.close(fig)
    return lines


def order_legend(
    ax, orders: Sequence[int], loc: str = "upper right", title: str = "branch order", extra: Sequence = (), **kw
):
    """Legend of the branch-order colours present in ``orders`` (``ax`` may be an Axes or a
    Figure), and the ``extra`` handles after them."""
    return ax.legend(
        handles=order_handles(orders) + list(extra),
        loc=loc,
        title=title,
        fontsize="small",
        title_fontsize="small",
        framealpha=0.85,
        **kw,
    )


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
        from ..metrics import classical_metrics

        m = classical_metrics(tree)
        return (  # a value and its unit stay on one line (no-break spaces)
            f"{tree.n} cylinders, {tree.n_branches} branches, height {m['height']:.2f}\u00a0m, "
            f"base diameter {m['base_diameter']:.3f}\u00a0m, crown spread {m['crown_spread']:.2f}\u00a0m"
        )
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


def save_tree_figure(
    tree,
    path,
    title: str | None = None,
    views: Sequence[str] = ("xz", "yz", "xy"),
    color_by: str = "order",
    dpi: int = 130,
) -> Path:
    """One tree in three projections (side views XZ, YZ and the top view XY), coloured by
    branch order, line width proportional to radius (GigaScience Fig. 6)."""
    return tree_comparison_figure({"": tree}, path, title=title, views=views, color_by=color_by, dpi=dpi)


def tree_comparison_figure(
    trees: Mapping[str, object],
    path,
    title: str | None = None,
    views: Sequence[str] = ("xz", "yz", "xy"),
    color_by: str = "order",
    dpi: int = 130,
    captions: bool = True,
) -> Path:
    """Several trees (rows, e.g. target and best fit) in the same projections (columns), on one
    scale: every panel of a column has the same limits and widths use one radius scale."""
    items = list(trees.items())
    tlist = [t for _, t in items]
    ratios = _view_ratios(tlist, views)
    row_h = 4.2
    fig = new_figure(max(6.0, row_h * sum(ratios) + 1.4), (row_h + 0.3) * len(items) + (0.4 if title else 0.0))
    rows = fig.subfigures(len(items), 1, squeeze=False)[:, 0]  # each row's caption on top of it
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
            if head + cap:
                sub.suptitle(
                    _wrapped(head + cap, fig.get_figwidth()),
                    fontsize="medium",
                    fontweight="bold" if label else "normal",
                )
    if color_by == "order":  # one legend for all rows, under them: beside them it covered the titles' ends
        n = len(order_handles(orders))
        order_legend(fig, orders, loc="outside lower center", ncols=n if n <= 5 else (n + 1) // 2)
    if title:
        fig.suptitle(_wrapped(title, fig.get_figwidth()), fontsize="large")
    return save_figure(fig, path, dpi)


def _wrapped(text: str, width_in: float, points: float = 11.0) -> str:
    """``text`` broken into lines that fit ``width_in`` inches in a font of ``points`` (a
    slender tree's figure is narrower than its captions)."""
    import textwrap

    return "\n".join(textwrap.wrap(text, max(20, int(width_in * 72 / (0.62 * points))))) or text


def _slots(trees, min_width: float = 0.0, gap_frac: float = 0.1, extent=None):
    """Horizontal (x) offsets placing trees side by side, each centred on its stem base in a
    slot at least ``min_width`` wide; returns ``(offsets, slot_edges)``. ``extent(tree, view)``
    gives what is drawn of a tree (default: :func:`_extent` of the tree)."""
    extent = extent or (lambda t, vw: _extent([t], vw))
    exts = [extent(t, "xy") for t in trees]  # x range (and y) about each stem base
    widths = [max(e[1] - e[0], min_width) for e in exts]
    gap = gap_frac * max(max(widths), 1e-3)
    offs, edges, x = [], [], 0.0
    for e, w in zip(exts, widths):
        centre = 0.5 * (e[0] + e[1])
        offs.append(x + 0.5 * w - centre)
        edges.append((x, x + w))
        x += w + gap
    return offs, edges


def clones_figure(
    target,
    clones: Sequence[tuple[str, object]],
    path,
    title: str | None = None,
    views: Sequence[str] = ("xz", "xy"),
    dpi: int = 130,
    envelope=None,
    envelope_label: str = "the crown's space",
) -> Path:
    """The target and several clones side by side on one scale (GigaScience Fig. 5): one row
    per view ("xz" side view, "xy" top view); a tree keeps the same x slot in every row, so its
    top view sits under its side view. With ``envelope`` (a
    :class:`~bforest_core.envelope.CrownEnvelope`, in the target's frame about its stem base) its
    outline is drawn over every tree, dashed, named ``envelope_label`` in the legend."""
    for vw in views:
        if vw not in ("xz", "xy"):
            raise ValueError(f"clones_figure draws the views 'xz' and 'xy' (x along the row), got {vw!r}")
    trees = [("target", target)] + list(clones)
    tl = [t for _, t in trees]
    r_max = max(float(np.max(t.radius)) for t in tl)
    drawn = {vw: envelope_lines(envelope, vw) for vw in views} if envelope is not None else {}
    outline = {vw: np.concatenate(lines) for vw, lines in drawn.items() if lines}  # its points, per view

    def extent(t, vw):  # the tree, and the crown's space drawn over it
        e = _extent([t], vw)
        if vw not in outline:
            return e
        pts = outline[vw]
        return (
            min(e[0], pts[:, 0].min()),
            max(e[1], pts[:, 0].max()),
            min(e[2], pts[:, 1].min()),
            max(e[3], pts[:, 1].max()),
        )

    height = max(extent(t, "xz")[3] - min(0.0, extent(t, "xz")[2]) for t in tl)
    offs, edges = _slots(tl, min_width=0.3 * height if "xz" in views else 0.0, extent=extent)
    x0, x1 = edges[0][0], edges[-1][1]
    vext = {}
    slot = max(e1 - e0 for e0, e1 in edges)
    for vw in views:
        es = [extent(t, vw) for t in tl]
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
            plot_tree(
                ax,
                t,
                vw,
                "order",
                offset=(off, 0.0),
                r_max=r_max,
                lw_max=3.0,
                lw_min=0.3,
                autoscale=False,
                label_axes=False,
            )
            for line in drawn.get(vw, []):
                ax.plot(line[:, 0] + off, line[:, 1], zorder=3, **ENVELOPE_STYLE)
            if r == 0:
                if label == "target":
                    label = f"target\n{t.n} cylinders"
                ax.text(
                    0.5 * (e0 + e1),
                    1.01,
                    label,
                    transform=ax.get_xaxis_transform(),
                    ha="center",
                    va="bottom",
                    fontsize="small",
                    color=DATA_COLOR if label.startswith("target") else "black",
                    fontweight="bold" if label.startswith("target") else "normal",
                )
        _set_limits(ax, (x0, x1, vext[vw][0], vext[vw][1]), pad=0.02)
        h, v = VIEWS[vw][:2]
        ax.set_ylabel(f"{_AXIS_NAMES[v]} (m)")
        ax.set_xlabel(f"{_AXIS_NAMES[h]} (m; trees side by side, each centred on its stem base)", fontsize="small")
        ax.grid(True, lw=0.3, alpha=0.4)
    orders = set()
    for t in tl:
        orders.update(np.unique(t.order).tolist())
    extra = [Line2D([], [], **ENVELOPE_STYLE, label=envelope_label)] if envelope is not None else []
    order_legend(axes[0], orders, loc="upper left", bbox_to_anchor=(1.0, 1.0), extra=extra)
    if title:
        fig.suptitle(title)
    return save_figure(fig, path, dpi)


_METRIC_PANELS = (
    ("height", "height (m)"),
    ("girth", "base diameter (m)"),
    ("crown_spread", "crown spread (m)"),
    ("distance", "structural distance D"),
    ("d_h", "$d_h$: height error (%)"),
    ("d_g", "$d_g$: base diameter error (%)"),
    ("d_c", "$d_c$: crown spread error (%)"),
    ("n_cylinders", "cylinders"),
)


def clone_metrics_figure(
    values: Mapping[str, np.ndarray],
    path,
    target: Mapping[str, float] | None = None,
    best: Mapping[str, float] | None = None,
    title: str | None = None,
    dpi: int = 130,
) -> Path:
    """Distributions over the clones of height, base diameter, crown spread, distance and the relative
    errors d_h, d_g, d_c (GigaScience Fig. 5D); the target's value is a black line, the best-fit
    tree's a red dashed line."""
    panels = [(k, lab) for k, lab in _METRIC_PANELS if k in values and np.isfinite(values[k]).any()]
    ncol = 4
    nrow = max(1, math.ceil(len(panels) / ncol))
    fig = new_figure(3.3 * ncol, 2.8 * nrow + 0.5)
    axes = fig.subplots(nrow, ncol, squeeze=False).ravel()
    target, best = dict(target or {}), dict(best or {})
    for ax, (key, lab) in zip(axes, panels):
        pct = 100.0 if key in ("d_h", "d_g", "d_c") else 1.0  # errors in percent, as every table
        x = np.asarray(values[key], float) * pct
        x = x[np.isfinite(x)]
        bins = min(30, max(5, int(np.sqrt(x.size)) + 2))
        ax.hist(x, bins=bins, color="#9bbcd9", edgecolor="#4a6f94", lw=0.6)
        ax.set_xlabel(lab)
        ax.set_ylabel("number of clones")
        ax.yaxis.get_major_locator().set_params(integer=True)
        ax.xaxis.set_major_locator(MaxNLocator(nbins=4))  # narrow ranges print long tick labels
        tv = target.get(key)
        if key in ("d_h", "d_g", "d_c"):
            tv = 0.0 if target else None
        if tv is not None and np.isfinite(tv):
            ax.axvline(tv, color=TARGET_LINE, lw=1.8, label="target")
        bv = best.get(key)
        if bv is not None and np.isfinite(bv):
            bv = bv * pct
            ax.axvline(bv, color=MODEL_COLOR, lw=1.5, ls="--", label="best fit")
        ax.set_title(f"median {np.median(x):.3g}, n = {x.size}", fontsize="small")
    for ax in axes[len(panels) :]:
        ax.set_visible(False)
    if panels:
        handles = [
            Line2D([], [], color=TARGET_LINE, lw=1.8, label="target"),
            Line2D([], [], color=MODEL_COLOR, lw=1.5, ls="--", label="best-fit tree"),
            Patch(facecolor="#9bbcd9", edgecolor="#4a6f94", label="clones"),
        ]
        fig.legend(handles=handles, loc="outside lower center", ncols=3, fontsize="small")
    if title:
        fig.suptitle(title)
    return save_figure(fig, path, dpi)


# ---------------------------------------------------------------------------------- run report
def fig_trees(v: RunView):
    trees = {}
    if v.target_tree is not None:
        trees["target (QSM)" if v.cfg is None or v.cfg.target.qsm else "target"] = v.target_tree
    if v.best_tree is not None:
        trees["best fit"] = v.best_tree
    if not trees:
        v.note("trees figure skipped: neither the target nor the best-fit tree is available")
        return []
    p = tree_comparison_figure(
        trees,
        v.store.figures_dir / "trees.png",
        title="Target and best-fit tree (line width ∝ radius, colour = branch order)",
    )
    cap = "Target and best-fit tree in the side views XZ, YZ and the top view XY, on one scale"
    if v.best_tree_source == "regrown":
        cap += " (best fit grown with the best parameters and the first model seed)"
    return [(p, cap)]


def fig_clones(v: RunView):
    rows = v.clone_rows
    ok = [r for r in rows if r.get("status") == "ok"]
    if not ok:
        return []
    out = []
    k = v.cfg.report.clones_in_figure if v.cfg is not None else 6
    shown = v.clone_trees(k)
    if shown and v.target_tree is not None:
        space, words = v.crown_space
        out.append(
            (
                clones_figure(
                    v.target_tree,
                    shown,
                    v.store.figures_dir / "clones.png",
                    title=f"Target and {len(shown)} morphological clones of the best fit",
                    envelope=space,
                    envelope_label=words,
                ),
                f"The target and {len(shown)} clones (the best-fit model with fresh seeds) on one scale, "
                "side view XZ and top view XY"
                + (f"; dashed: {words} (docs/growth-forms.md, the crown's space)" if space is not None else ""),
            )
        )
    keys = ("height", "girth", "crown_spread", "distance", "d_h", "d_g", "d_c", "n_cylinders")
    values = {k: np.array([r.get(k, np.nan) for r in ok], float) for k in keys}
    tm = dict(v.target_metrics or {})
    if v.target_tree is not None:
        tm["n_cylinders"] = v.target_tree.n
    bm = dict(v.model_metrics or {})
    if v.best is not None:
        bm["distance"] = v.best.get("distance")
        bm.update(v.best.get("relative_errors") or {})
    if v.best_tree is not None:
        bm["n_cylinders"] = v.best_tree.n
    out.append(
        (
            clone_metrics_figure(
                values,
                v.store.figures_dir / "clone_metrics.png",
                target=tm,
                best=bm,
                title=f"Classical metrics of {len(ok)} clones",
            ),
            "Distributions over the clones: height, base diameter, crown spread, structural distance and the "
            "relative errors d_h, d_g, d_c; black: target, red dashed: best-fit tree",
        )
    )
    return out
