"""Writers of the CSV layouts of other QSM tools: SimpleForest and aRchi (docs/qsm-formats.md §6,
§7), so that clones open where those tools' users work. Written back through the bundled readers
they give the same cylinder table (at ``%.9g``, about 1e-6 m)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bforest_core.cylinders import resolve_options
from bforest_core.interfaces import ComponentSettings, QSMWriter
from bforest_core.tables import format_columns
from bforest_core.tree import jump_to_head, levels, remap_ids, subtree_sum

SIMPLEFOREST_HEADER = (
    " ID, parentID, startX, startY, startZ, endX, endY, endZ, radius, length, growthLength, "
    "averagePointDistance,segmentID, parentSegmentID, branchOrder, reverseBranchOrder, branchID"
)
ARCHI_HEADER = (
    "startX,startY,startZ,endX,endY,endZ,cyl_ID,parent_ID,extension_ID,radius_cyl,length,volume,"
    "axis_ID,segment_ID,node_ID,branching_order"
)


def segments(tree):
    """Chains between forks: ``(seg, seg_parent, seg_last, reverse)`` with the 0-based segment of
    each cylinder, the parent segment of each segment (-1 for the first), the last cylinder of
    each segment and its reverse order (1 for a segment ending in a tip, else 1 + the largest of
    its child segments')."""
    parent = tree.parent
    nchild = np.bincount(parent[parent >= 0], minlength=tree.n)
    is_head = (parent < 0) | (nchild[np.maximum(parent, 0)] > 1)
    head, dist = jump_to_head(parent, is_head)
    heads = np.flatnonzero(is_head)
    seg_of_head = np.full(tree.n, -1)
    seg_of_head[heads] = np.arange(heads.size)
    seg = seg_of_head[head]
    seg_parent = remap_ids(parent[heads], seg)
    last = np.full(heads.size, -1)
    best = np.full(heads.size, -1)
    o = np.argsort(dist, kind="stable")  # the largest distance in a segment is written last
    last[seg[o]] = o
    best[seg[o]] = dist[o]
    reverse = np.ones(heads.size, dtype=np.int64)
    order, bounds = levels(seg_parent)
    for k in range(len(bounds) - 1, 1, -1):
        rows = order[bounds[k - 1] : bounds[k]]
        np.maximum.at(reverse, seg_parent[rows], reverse[rows] + 1)
    return seg, seg_parent, last, reverse


def stem_branch_id(tree) -> np.ndarray:
    """Per cylinder: 0 on the stem, else k = 1, 2, ... for the stem-attached branch it belongs to
    (with all its sub-branches), as SimpleForest's ``branchID``."""
    br = tree.branches
    top, _ = jump_to_head(br.parent_branch, br.order <= 1)
    first_order = np.flatnonzero(br.order == 1)
    label = np.zeros(len(br), dtype=np.int64)
    label[first_order] = np.arange(1, first_order.size + 1)
    return np.where(br.order[tree.branch] == 0, 0, label[top[tree.branch]])


class SimpleForestCSVWriter(QSMWriter):
    """SimpleForest CSV: 0-based ids, start and end points, segments between forks."""

    name = "simpleforest-csv"
    summary = "SimpleForest QSM CSV (0-based ids, end points, segments, branch orders)"
    suffixes = (".csv",)
    Settings = ComponentSettings

    def write(self, tree, path, **options) -> Path:
        resolve_options(self, options)
        path = Path(path)
        seg, seg_parent, _, reverse = segments(tree)
        rows = format_columns(
            [
                (np.arange(tree.n), "%d"),
                (tree.parent, "%d"),
                (tree.start, "%.9g"),
                (tree.end, "%.9g"),
                (tree.radius, "%.9g"),
                (tree.length, "%.9g"),
                (subtree_sum(tree.parent, tree.length), "%.9g"),
                (np.zeros(tree.n), "%g"),
                (seg, "%d"),
                (seg_parent[seg], "%d"),
                (tree.order, "%d"),
                (reverse[seg], "%d"),
                (stem_branch_id(tree), "%d"),
            ],
            sep=",",
        )
        path.write_text(SIMPLEFOREST_HEADER + "\n" + rows, encoding="utf-8")
        return path


class ArchiCSVWriter(QSMWriter):
    """aRchi CSV: 1-based ids (0 = none), start and end points, axis = branch, order from 1."""

    name = "archi-csv"
    summary = "aRchi QSM CSV (1-based ids, end points, axes, segments, branching order from 1)"
    suffixes = (".csv",)
    Settings = ComponentSettings

    def write(self, tree, path, **options) -> Path:
        resolve_options(self, options)
        path = Path(path)
        seg, seg_parent, last, _ = segments(tree)
        node = np.where(seg_parent[seg] >= 0, last[np.maximum(seg_parent[seg], 0)] + 1, 0)
        rows = format_columns(
            [
                (tree.start, "%.9g"),
                (tree.end, "%.9g"),
                (np.arange(1, tree.n + 1), "%d"),
                (tree.parent + 1, "%d"),
                (tree.extension + 1, "%d"),
                (tree.radius, "%.9g"),
                (tree.length, "%.9g"),
                (np.pi * tree.radius**2 * tree.length, "%.9g"),
                (tree.branch + 1, "%d"),
                (last[seg] + 1, "%d"),
                (node, "%d"),
                (tree.order + 1, "%d"),
            ],
            sep=",",
        )
        path.write_text(ARCHI_HEADER + "\n" + rows, encoding="utf-8")
        return path
