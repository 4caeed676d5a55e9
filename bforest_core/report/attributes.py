"""Figure of TreeQSM's distributions: the target tree against the clones' median and 5-95 % band
(wood volume and length by cylinder diameter and by height, branch volume, length and count by
order, branch count by branching angle), read like TreeQSM's own distribution plots."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from matplotlib.lines import Line2D
from matplotlib.patches import Patch

from ..attributes import distributions
from .canvas import DATA_COLOR, MODEL_COLOR, new_figure, save_figure

if TYPE_CHECKING:
    from .run_view import RunView

#: (distribution, y label, x label, class width, first class value) of each panel
PANELS = (
    ("VolCylDia", "wood volume (m³)", "cylinder diameter (cm)", 1.0, 0.0),
    ("LenCylDia", "wood length (m)", "cylinder diameter (cm)", 1.0, 0.0),
    ("VolCylHei", "wood volume (m³)", "height (m)", 1.0, 0.0),
    ("LenCylHei", "wood length (m)", "height (m)", 1.0, 0.0),
    ("VolBranchOrd", "branch volume (m³)", "branch order", 1.0, 1.0),
    ("LenBranchOrd", "branch length (m)", "branch order", 1.0, 1.0),
    ("NumBranchOrd", "branches", "branch order", 1.0, 1.0),
    ("NumBranchAng", "branches", "branching angle (deg)", 10.0, 0.0),
)


def _padded(arrays: Sequence[np.ndarray]) -> np.ndarray:
    n = max((a.size for a in arrays), default=0)
    out = np.zeros((len(arrays), n))
    for i, a in enumerate(arrays):
        out[i, : a.size] = a
    return out


def band(clone_values: Sequence[np.ndarray], lo: float = 5.0, hi: float = 95.0):
    """(median, lo %, hi %) per class over the clones (a clone without a class counts 0 there)."""
    m = _padded(clone_values)
    if m.shape[0] == 0:
        return np.zeros(0), np.zeros(0), np.zeros(0)
    return (np.median(m, axis=0), np.percentile(m, lo, axis=0), np.percentile(m, hi, axis=0))


def distributions_figure(target, clones: Sequence, path, dpi: int = 130, title: str | None = None) -> Path:
    """The target's distributions (blue steps) against the clones' median (red) and 5-95 % band
    (pink), one panel per entry of :data:`PANELS`, every class a bar of its width."""
    td = distributions(target)
    cd = [distributions(c) for c in clones]
    fig = new_figure(14.0, 6.4)
    axes = fig.subplots(2, 4).ravel()
    for ax, (name, ylab, xlab, width, x0) in zip(axes, PANELS):
        med, lo, hi = band([d[name] for d in cd])
        n = max(td[name].size, med.size)
        t = np.zeros(n)
        t[: td[name].size] = td[name]
        pad = lambda a: np.concatenate([a, np.zeros(n - a.size)])
        med, lo, hi = pad(med), pad(lo), pad(hi)
        edges = x0 + width * np.arange(n + 1) - (0.5 * width if x0 else 0.0)
        if cd:
            ax.stairs(hi, edges, baseline=lo, fill=True, color=MODEL_COLOR, alpha=0.22, lw=0)
            ax.stairs(med, edges, color=MODEL_COLOR, lw=1.4)
        ax.stairs(t, edges, color=DATA_COLOR, lw=1.8)
        ax.set_xlabel(xlab)
        ax.set_ylabel(ylab)
        ax.set_ylim(bottom=0)
    handles = [
        Line2D([], [], color=DATA_COLOR, lw=1.8, label="target"),
        Line2D([], [], color=MODEL_COLOR, lw=1.4, label=f"clones: median (n = {len(cd)})"),
        Patch(facecolor=MODEL_COLOR, alpha=0.22, label="clones: 5–95 %"),
    ]
    fig.legend(handles=handles, loc="outside lower center", ncols=3, fontsize="small")
    if title:
        fig.suptitle(title)
    return save_figure(fig, path, dpi)


def fig_distributions(v: RunView):
    """The report's distributions figure (target against every readable ok clone)."""
    from ..io import read_tree

    ok = [r for r in v.clone_rows if r.get("status") == "ok" and r.get("file")]
    if not ok or v.target_tree is None:
        return []
    trees = []
    for r in ok:
        p = v.store.clones_dir() / r["file"]
        if p.exists():
            trees.append(read_tree(p))
    if not trees:
        return []
    p = distributions_figure(
        v.target_tree,
        trees,
        v.store.figures_dir / "distributions.png",
        title=f"TreeQSM's distributions: target and {len(trees)} clones",
    )
    return [
        (
            p,
            "TreeQSM's distributions (docs/tree-attributes.md) of the target (blue) against the clones' "
            "median (red) and 5–95 % band: wood volume and length by cylinder diameter and by height, "
            "branch volume, length and count by order, branch count by branching angle",
        )
    ]
