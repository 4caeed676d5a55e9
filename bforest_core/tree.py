"""The cylinder tree: the one structure every QSM reader and every growth model returns.

Columns follow docs/features-and-distance.md §1: numpy arrays, metres, 0-based ids,
``-1`` for "none". ``branch``, ``order`` and ``position_in_branch`` are always recomputed
from ``parent`` + ``extension`` by :func:`derive_branches`; a *topology rule* only chooses
``extension`` (:func:`choose_extension`).

All derivations are vectorised (pointer jumping, level-synchronous accumulation); there is no
Python loop over cylinders.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import TreeError

TOPOLOGY_RULES = ("source", "subtree", "thickest")
_AXIS_TOL = 1e-6  # silently renormalised below this deviation; readers renormalise larger ones


MAX_ROWS_SHOWN = 10


def rows_text(rows, limit: int = MAX_ROWS_SHOWN, count: bool = False) -> str:
    """List rows for a message: ``"1, 3020, 3582"``.

    Parameters
    ----------
    rows : array_like of int
        The rows (as they are to be shown: 0- or 1-based).
    limit : int, optional
        Rows shown; past it, the total count follows (``", ... (12 rows)"``).
    count : bool, optional
        Give the count of 2...``limit`` rows too (``"12, 40 (2 rows)"``).

    Returns
    -------
    str
        The text.
    """
    rows = [int(r) for r in np.asarray(rows).ravel()]
    shown = ", ".join(str(r) for r in rows[:limit])
    if len(rows) > limit:
        return f"{shown}, ... ({len(rows)} rows)"
    if count and len(rows) > 1:
        return f"{shown} ({len(rows)} rows)"
    return shown


# ----------------------------------------------------------------------------------------------
# vectorised topology kernels
# ----------------------------------------------------------------------------------------------


def remap_ids(ids: np.ndarray, new: np.ndarray) -> np.ndarray:
    """Translate row ids through a table of new ids, keeping -1 (no row) as -1.

    The one form of ``np.where(ids >= 0, new[np.maximum(ids, 0)], -1)``: parent or extension
    links after rows were dropped, reordered or renumbered.

    Parameters
    ----------
    ids : ndarray of int
        Old ids, -1 for none.
    new : ndarray of int
        ``new[old]`` is the new id of row ``old`` (-1 where the row is gone).

    Returns
    -------
    ndarray of int
        The new id of each entry of ``ids``; -1 where ``ids`` is negative.
    """
    return np.where(ids >= 0, new[np.maximum(ids, 0)], -1)


def jump_to_head(link: np.ndarray, is_head: np.ndarray):
    """Find, by pointer jumping, the head of each node's chain and the number of links to it.

    O(n log L) for chains of length L.

    Parameters
    ----------
    link : ndarray of int, shape (n,)
        ``link[i]`` is the predecessor of i (ignored where ``is_head``).
    is_head : ndarray of bool, shape (n,)
        The chains' heads.

    Returns
    -------
    head : ndarray of int
        Head of each node's chain (a head is its own).
    dist : ndarray of int64
        Links from each node to its head.
    """
    n = link.shape[0]
    idx = np.arange(n)
    anc = np.where(is_head, idx, link)
    dist = (~is_head).astype(np.int64)
    active = np.flatnonzero(~is_head & ~is_head[np.where(is_head, idx, link)])
    # invariant: dist[i] = links from i to anc[i]; a head has anc = itself and dist 0
    while active.size:
        a = anc[active]
        dist[active] += dist[a]
        anc[active] = anc[a]
        active = active[~is_head[anc[active]]]
    return anc, dist


def depth_of(parent: np.ndarray) -> np.ndarray:
    """Count the links from each cylinder to the root.

    Parameters
    ----------
    parent : ndarray of int, shape (n,)
        Parent rows, -1 for the root.

    Returns
    -------
    ndarray of int64, shape (n,)
        The depth of each cylinder (root 0).
    """
    _, d = jump_to_head(parent, parent < 0)
    return d


def group_by_level(level: np.ndarray):
    """Group indices by a non-negative integer level (e.g. depth).

    Parameters
    ----------
    level : ndarray of int, shape (n,)
        Level of each index.

    Returns
    -------
    order : ndarray of int
        The indices sorted by level; those of level k are ``order[bounds[k]:bounds[k+1]]``, in
        increasing index order.
    bounds : ndarray of int64
        Start of each level in ``order`` (one more entry than levels).
    """
    level = np.asarray(level)
    order = np.argsort(level, kind="stable")
    bounds = np.zeros(int(level.max()) + 2 if level.size else 1, dtype=np.int64)
    np.cumsum(np.bincount(level), out=bounds[1:])
    return order, bounds


def levels(parent: np.ndarray):
    """Group rows by depth.

    Parameters
    ----------
    parent : ndarray of int, shape (n,)
        Parent rows, -1 for the root.

    Returns
    -------
    order, bounds : ndarray
        Rows of depth k are ``order[bounds[k]:bounds[k+1]]`` (see :func:`group_by_level`).
    """
    return group_by_level(depth_of(parent))


def subtree_sum(parent: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Sum ``values`` over each node and all its descendants (O(n), level by level).

    Parameters
    ----------
    parent : ndarray of int, shape (n,)
        Parent rows, -1 for the root.
    values : array_like, shape (n,)
        One value per node.

    Returns
    -------
    ndarray of float64, shape (n,)
        The subtree sums.
    """
    out = np.array(values, dtype=np.float64, copy=True)
    order, bounds = levels(parent)
    for k in range(len(bounds) - 1, 1, -1):
        rows = order[bounds[k - 1] : bounds[k]]
        np.add.at(out, parent[rows], out[rows])
    return out


def children_csr(parent: np.ndarray):
    """Return the children lists as CSR arrays.

    Parameters
    ----------
    parent : ndarray of int, shape (n,)
        Parent rows, -1 for the root.

    Returns
    -------
    ptr : ndarray of int64, shape (n + 1,)
        Offsets into ``idx``.
    idx : ndarray of int
        Children of i are ``idx[ptr[i]:ptr[i+1]]``, in increasing row order.
    """
    n = parent.shape[0]
    nonroot = np.flatnonzero(parent >= 0)
    p = parent[nonroot]
    srt = np.argsort(p, kind="stable")
    idx = nonroot[srt]
    ptr = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(np.bincount(p, minlength=n), out=ptr[1:])
    return ptr, idx


def choose_extension(parent, extension, radius, length, rule: str) -> np.ndarray:
    """Pick the continuing child of every cylinder under a topology rule (docs/features-and-distance.md §1.1).

    ``source`` returns ``extension`` unchanged. ``thickest`` takes the child with the largest
    radius, ``subtree`` the child whose subtree holds the most wood (sum of pi r^2 L); ties go
    to the current extension, then to the earlier row.

    Parameters
    ----------
    parent, extension : ndarray of int64, shape (n,)
        Parent and extension rows, -1 for none.
    radius, length : ndarray of float64, shape (n,)
        Radii and lengths (m).
    rule : {"source", "subtree", "thickest"}
        The topology rule.

    Returns
    -------
    ndarray of int64, shape (n,)
        The extension (continuing child) of every cylinder, -1 for none.
    """
    if rule not in TOPOLOGY_RULES:
        raise TreeError(f"unknown topology rule {rule!r} (choose from {', '.join(TOPOLOGY_RULES)})")
    if rule == "source":
        return np.asarray(extension, dtype=np.int64).copy()
    n = parent.shape[0]
    if rule == "thickest":
        key = np.asarray(radius, dtype=np.float64)
    else:
        key = subtree_sum(parent, np.pi * np.asarray(radius, float) ** 2 * np.asarray(length, float))
    rows = np.flatnonzero(parent >= 0)
    p = parent[rows]
    not_ext = extension[p] != rows
    # lexsort: last key is primary -> parent, then -key, then not-extension, then row
    srt = np.lexsort((rows, not_ext, -key[rows], p))
    ps = p[srt]
    first = np.ones(ps.shape[0], dtype=bool)
    first[1:] = ps[1:] != ps[:-1]
    new_ext = np.full(n, -1, dtype=np.int64)
    new_ext[ps[first]] = rows[srt][first]
    return new_ext


def derive_branches(parent: np.ndarray, extension: np.ndarray):
    """Branch id, Gravelius order and position of every cylinder from ``parent`` + ``extension``.

    Branches are the maximal extension chains, numbered in increasing row order of their first
    cylinder; the trunk (the root's branch) is 0 and has order 0; a lateral branch has its parent
    branch's order + 1.

    Parameters
    ----------
    parent, extension : ndarray of int64, shape (n,)
        Parent and extension rows, -1 for none, parents before children.

    Returns
    -------
    branch, order, position : ndarray of int64, shape (n,)
        Per cylinder: branch id, branch order and 0-based position in its branch.
    firsts : ndarray of int
        Per branch: its first cylinder.
    parent_cyl, parent_branch : ndarray of int
        Per branch: parent cylinder and parent branch of its first cylinder (-1 for the trunk).
    border : ndarray of int
        Per branch: its order.
    """
    n = parent.shape[0]
    rows = np.arange(n)
    has_parent = parent >= 0
    is_first = np.ones(n, dtype=bool)
    is_first[has_parent] = extension[parent[has_parent]] != rows[has_parent]
    head, position = jump_to_head(parent, is_first)
    firsts = np.flatnonzero(is_first)  # increasing rows: branch ids by first row
    bid_of_first = np.full(n, -1, dtype=np.int64)
    bid_of_first[firsts] = np.arange(firsts.size)
    branch = bid_of_first[head]
    parent_cyl = parent[firsts]
    parent_branch = remap_ids(parent_cyl, branch)
    _, border = jump_to_head(parent_branch, parent_branch < 0)
    order = border[branch]
    return branch, order.astype(np.int64), position.astype(np.int64), firsts, parent_cyl, parent_branch, border


def parent_first_order(parent: np.ndarray):
    """Return a topological order (parents before children) of a valid tree.

    A valid tree has one root and no cycle (see :func:`id_problems`, :func:`cycle_problems`).

    Parameters
    ----------
    parent : ndarray of int, shape (n,)
        Parent rows, -1 for the root.

    Returns
    -------
    ndarray of int or None
        The rows in the new order; ``None`` when the table is already sorted (it is kept as
        it is).
    """
    n = parent.shape[0]
    roots = np.flatnonzero(parent < 0)
    if roots[0] == 0 and np.all(parent[1:] < np.arange(1, n)):
        return None  # already in order
    # depth of every row, level by level from the root
    ptr, idx = children_csr(parent)
    frontier = roots
    depth = np.zeros(n, dtype=np.int64)
    k = 0
    while frontier.size:
        counts = ptr[frontier + 1] - ptr[frontier]
        starts = np.repeat(ptr[frontier], counts)
        offs = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
        ch = idx[starts + offs]
        k += 1
        depth[ch] = k
        frontier = ch
    # a depth-stable sort is a valid topological order and keeps already-sorted prefixes
    return np.lexsort((np.arange(n), depth))


# ----------------------------------------------------------------------------------------------
# the checks of a cylinder table: Tree and the QSM readers (bforest_core.cylinders) share them
# ----------------------------------------------------------------------------------------------


def value_problems(start, axis, length, radius, *, zero_length_ok: bool = False, row_base: int = 0):
    """Find the errors of a cylinder table's values, each naming all its rows.

    Non-finite values in any column are reported alone (nothing else is checked then); else
    radius <= 0, length < 0 (or <= 0 unless ``zero_length_ok``: readers remove zero-length
    cylinders) and axes of zero length (of cylinders with a length).

    Parameters
    ----------
    start, axis : (n, 3) float arrays
        Start points (m) and axis directions.
    length, radius : (n,) float arrays
        Lengths and radii (m).
    zero_length_ok : bool
        Accept lengths of exactly 0 (readers remove such cylinders later).
    row_base : int
        Rows in messages are counted from it (1: a file's rows).

    Returns
    -------
    list of (str, ndarray)
        Message and 0-based rows of every problem; empty when the values are fine.
    """
    problems = []
    for name, a in (("radius", radius), ("length", length), ("start", start), ("axis", axis)):
        ok = np.isfinite(a) if a.ndim == 1 else np.isfinite(a).all(axis=1)
        if not ok.all():
            bad = np.flatnonzero(~ok)
            problems.append((f"non-finite values in '{name}' at rows {rows_text(bad + row_base, count=True)}", bad))
    if problems:
        return problems
    bad = np.flatnonzero(radius <= 0)
    if bad.size:
        problems.append(
            (
                f"radius <= 0 at rows {rows_text(bad + row_base)} (value {radius[bad[0]]:g}); "
                "a cylinder needs a positive radius",
                bad,
            )
        )
    bad = np.flatnonzero(length < 0 if zero_length_ok else length <= 0)
    if bad.size:
        sign = "<" if zero_length_ok else "<="
        problems.append((f"length {sign} 0 at rows {rows_text(bad + row_base)} (value {length[bad[0]]:g})", bad))
    zero_axis = np.einsum("ij,ij->i", axis, axis) == 0
    if zero_length_ok:
        zero_axis &= length != 0
    bad = np.flatnonzero(zero_axis)
    if bad.size:
        problems.append((f"axis has zero length at rows {rows_text(bad + row_base)}", bad))
    return problems


def id_problems(parent, extension, *, row_base: int = 0):
    """Find the first error of a cylinder table's ids.

    That is a parent or extension out of range, or a cylinder that is its own parent.

    Parameters
    ----------
    parent, extension : ndarray of int64, shape (n,)
        0-based rows, -1 = none.
    row_base : int, optional
        Rows in messages are counted from it, as in :func:`value_problems`.

    Returns
    -------
    list of (str, ndarray)
        ``[(message, rows)]`` (0-based rows) or ``[]``.
    """
    n = parent.shape[0]
    for name, ids in (("parent", parent), ("extension", extension)):
        bad = np.flatnonzero((ids < -1) | (ids >= n))
        if bad.size:
            values = (ids[bad][:5] + row_base).tolist()
            valid = f"{row_base}...{n - 1 + row_base}, {row_base - 1} = none"
            return [(f"{name} out of range at rows {rows_text(bad + row_base)} (values {values}; valid {valid})", bad)]
    bad = np.flatnonzero(parent == np.arange(n))
    if bad.size:
        return [(f"cylinder {bad[0] + row_base} is its own parent (rows {rows_text(bad + row_base)})", bad)]
    return []


def extension_problems(parent, extension, *, row_base: int = 0):
    """Find extensions that are not a child of their cylinder.

    Parameters
    ----------
    parent, extension : ndarray of int64, shape (n,)
        0-based rows, -1 = none, in range (see :func:`id_problems`).
    row_base : int, optional
        Rows in messages are counted from it.

    Returns
    -------
    list of (str, ndarray)
        ``[(message, rows)]`` (0-based rows) or ``[]``.
    """
    has_ext = np.flatnonzero(extension >= 0)
    bad = has_ext[parent[extension[has_ext]] != has_ext]
    if bad.size:
        i = int(bad[0])
        j = int(extension[i])
        pj = int(parent[j])
        more = f" ({bad.size} rows: {rows_text(bad + row_base)})" if bad.size > 1 else ""
        whose = f"row {pj + row_base}" if pj >= 0 else "none"
        return [(f"extension of row {i + row_base} is row {j + row_base}, whose parent is {whose}{more}", bad)]
    return []


def components(parent: np.ndarray):
    """Find the root row of every row's connected part, by pointer doubling (O(n log depth)).

    Parameters
    ----------
    parent : ndarray of int, shape (n,)
        Parent rows in ``-1 .. n-1``.

    Returns
    -------
    label : ndarray of int
        ``label[i]`` is the root above row i (-1 where no root is reached, i.e. rows on or
        below a parent cycle).
    reached : ndarray of bool
        Whether a root is reached from each row.
    """
    n = parent.shape[0]
    is_root = parent < 0
    anc = np.where(is_root, np.arange(n), parent)
    # after k rounds anc is the 2^k-th ancestor (roots are fixed points); a row on or below a
    # cycle never reaches a root, so ceil(log2 n) + 1 rounds decide every row
    for _ in range(max(1, int(np.ceil(np.log2(max(n, 2))))) + 1):
        nxt = anc[anc]
        if np.array_equal(nxt, anc):
            break
        anc = nxt
    reached = is_root[anc]
    return np.where(reached, anc, -1), reached


def _find_cycle(parent: np.ndarray, start: int) -> list[int]:
    """Rows of one parent cycle reached from ``start`` (error path only)."""
    seen: dict[int, int] = {}
    i = int(start)
    path = []
    while i >= 0 and i not in seen and len(path) <= parent.shape[0]:
        seen[i] = len(path)
        path.append(i)
        i = int(parent[i])
    if i in seen:
        return path[seen[i] :] + [i]
    return path


def cycle_problems(parent, *, row_base: int = 0):
    """Find the rows on or below a parent cycle (connected to no root).

    One cycle is walked for the message.

    Parameters
    ----------
    parent : ndarray of int64, shape (n,)
        Parent rows, -1 for a root, in range (see :func:`id_problems`).
    row_base : int, optional
        Rows in messages are counted from it.

    Returns
    -------
    list of (str, ndarray)
        ``[(message, rows)]`` (0-based rows) or ``[]``.
    """
    if np.all(parent < np.arange(parent.shape[0])):
        return []  # every parent comes first: no cycle
    _, reached = components(parent)
    if reached.all():
        return []
    bad = np.flatnonzero(~reached)
    cyc = _find_cycle(parent, int(bad[0]))
    path = " -> ".join(str(c + row_base) for c in cyc)
    return [(f"cylinders {path} form a cycle ({bad.size} cylinders are not connected to a root)", bad)]


def _raise(problems) -> None:
    """Raise the problems of the check functions above as one :class:`TreeError`."""
    if problems:
        raise TreeError("; ".join(m for m, _ in problems), np.concatenate([r for _, r in problems]))


# ----------------------------------------------------------------------------------------------
# the Tree
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class BranchTable:
    """One row per branch (docs/features-and-distance.md §1; ``gen_scatter2.m``).

    ``cylinders[ptr[b]:ptr[b+1]]`` are the cylinders of branch b from base to tip.
    """

    first: np.ndarray  # first cylinder
    parent_cyl: np.ndarray  # parent cylinder of the first cylinder, -1 for the trunk
    parent_branch: np.ndarray  # -1 for the trunk
    order: np.ndarray
    n_cyl: np.ndarray
    ptr: np.ndarray
    cylinders: np.ndarray

    def __len__(self) -> int:
        """Return the number of branches."""
        return int(self.first.shape[0])


def _unit_axes(axis: np.ndarray) -> np.ndarray:
    """Return the (non-zero) axes checked to be unit vectors.

    Rows off by no more than rounding are renormalised; larger deviations are errors.
    """
    norm = np.linalg.norm(axis, axis=1)
    bad = np.flatnonzero(np.abs(norm - 1.0) > _AXIS_TOL)
    if bad.size:
        raise TreeError(
            f"axis is not a unit vector at rows {rows_text(bad, count=True)} (norm {norm[bad[0]]:.6g}); "
            "renormalise it before building the tree",
            bad,
        )
    # renormalise only rows that are off by more than rounding, so rebuilding a tree
    # (with_topology, round trips) leaves its axes bit-identical
    off = np.abs(norm - 1.0) > 4e-15
    if off.any():
        axis = axis.copy()
        axis[off] /= norm[off, None]
    return axis


def _parent_first(start, axis, length, radius, parent, extension, added, source_row, extras):
    """Reorder the rows so that every parent precedes its children (unchanged if they do)."""
    perm = parent_first_order(parent)
    if perm is not None:
        n = parent.size
        inv = np.empty(n, dtype=np.int64)
        inv[perm] = np.arange(n)
        start, axis, length, radius, added, source_row = (
            start[perm],
            axis[perm],
            length[perm],
            radius[perm],
            added[perm],
            source_row[perm],
        )
        parent = remap_ids(parent[perm], inv)
        extension = remap_ids(extension[perm], inv)
        extras = {k: v[perm] for k, v in extras.items()}
        if "_source_extension" in extras:  # holds row ids: renumber like extension
            extras["_source_extension"] = remap_ids(extras["_source_extension"], inv)
    return start, axis, length, radius, parent, extension, added, source_row, extras


class Tree:
    """A tree as a table of cylinders with parent links (docs/features-and-distance.md §1).

    Parameters
    ----------
    start, axis : (n, 3) array_like
        Start points (m) and axis directions (unit vectors; deviations up to 1e-6 are
        renormalised, larger ones and zero axes are errors -- readers renormalise and warn).
    length, radius : (n,) array_like
        Cylinder length and radius, m, both > 0.
    parent : (n,) array_like of int
        Row of the parent cylinder, -1 for the root. Rows not in parent-before-child order are
        re-sorted (stably); ``source_row`` keeps the original row.
    extension : (n,) array_like of int, optional
        The child continuing the same branch, -1 for none. Required for ``topology="source"``
        unless absent, in which case every child starts a new branch (use another rule then).
    topology : {"source", "subtree", "thickest"}
        Rule choosing ``extension`` (docs/features-and-distance.md §1.1).
    added : (n,) bool, optional
        QSM gap-filling cylinders.
    extras : dict of (n,) arrays, optional
        Extra per-cylinder columns (never read by features).
    metadata : dict, optional
        Source path, format, version, model index, units, parameters, seed, ...
    source_row : (n,) array_like of int, optional
        Row of each cylinder in its source (default: the given row order).

    Raises
    ------
    TreeError
        With the problem and the offending rows.
    """

    __slots__ = (
        "start",
        "axis",
        "length",
        "radius",
        "parent",
        "extension",
        "branch",
        "order",
        "position_in_branch",
        "added",
        "source_row",
        "extras",
        "metadata",
        "topology",
        "_cache",
    )

    def __init__(
        self,
        start,
        axis,
        length,
        radius,
        parent,
        extension=None,
        *,
        topology="source",
        added=None,
        source_row=None,
        extras=None,
        metadata=None,
    ):
        start = np.asarray(start, dtype=np.float64)
        axis = np.asarray(axis, dtype=np.float64)
        length = np.asarray(length, dtype=np.float64).reshape(-1)
        radius = np.asarray(radius, dtype=np.float64).reshape(-1)
        parent = np.asarray(parent)
        n = length.shape[0]
        if n == 0:
            raise TreeError("the tree has no cylinders")
        start = start.reshape(-1, 3) if start.size == 3 * n else start
        axis = axis.reshape(-1, 3) if axis.size == 3 * n else axis
        for name, arr, shape in (
            ("start", start, (n, 3)),
            ("axis", axis, (n, 3)),
            ("radius", radius, (n,)),
            ("parent", parent, (n,)),
        ):
            if arr.shape != shape:
                raise TreeError(f"'{name}' has shape {arr.shape}, expected {shape} (n = {n} cylinders from 'length')")
        if not np.issubdtype(parent.dtype, np.integer):
            if not np.all(np.isfinite(parent)) or np.any(parent != np.round(parent)):
                bad = np.flatnonzero(~np.isfinite(parent) | (parent != np.round(np.nan_to_num(parent))))
                raise TreeError(f"'parent' holds non-integer values at rows {rows_text(bad, count=True)}", bad)
        parent = parent.astype(np.int64)
        if extension is None:
            extension = np.full(n, -1, dtype=np.int64)
        extension = np.asarray(extension)
        if extension.shape != (n,):
            raise TreeError(f"'extension' has shape {extension.shape}, expected {(n,)}")
        extension = extension.astype(np.int64)
        _raise(value_problems(start, axis, length, radius))
        axis = _unit_axes(axis)
        if topology not in TOPOLOGY_RULES:
            raise TreeError(f"unknown topology rule {topology!r} (choose from {', '.join(TOPOLOGY_RULES)})")
        if added is None:
            added = np.zeros(n, dtype=bool)
        added = np.asarray(added).astype(bool).reshape(-1)
        if added.shape != (n,):
            raise TreeError(f"'added' has shape {added.shape}, expected {(n,)}")
        source_row = np.arange(n, dtype=np.int64) if source_row is None else np.asarray(source_row, dtype=np.int64)
        extras = {k: np.asarray(v) for k, v in (extras or {}).items()}
        for k, v in extras.items():
            if v.shape[:1] != (n,):
                raise TreeError(f"extra column '{k}' has shape {v.shape}, expected ({n}, ...)")

        _raise(id_problems(parent, extension))
        roots = np.flatnonzero(parent < 0)
        if roots.size == 0:
            raise TreeError("no root: every cylinder has a parent (the parent links form a cycle)")
        if roots.size > 1:
            raise TreeError(
                f"{roots.size} cylinders have no parent (rows {rows_text(roots, count=True)}); "
                "a tree has exactly one root",
                roots,
            )
        _raise(cycle_problems(parent))
        _raise(extension_problems(parent, extension))
        start, axis, length, radius, parent, extension, added, source_row, extras = _parent_first(
            start, axis, length, radius, parent, extension, added, source_row, extras
        )

        self.start = start
        self.axis = axis
        self.length = length
        self.radius = radius
        self.parent = parent
        self.added = added
        self.source_row = source_row
        self.extras = extras
        self.metadata = dict(metadata or {})
        self.topology = topology
        self._cache = {}
        self.extension = choose_extension(parent, extension, radius, length, topology)
        self._set_branches()
        self.metadata["topology"] = topology
        for a in (
            self.start,
            self.axis,
            self.length,
            self.radius,
            self.parent,
            self.extension,
            self.branch,
            self.order,
            self.position_in_branch,
            self.added,
            self.source_row,
        ):
            a.flags.writeable = False

    def _set_branches(self):
        (self.branch, self.order, self.position_in_branch, firsts, parent_cyl, parent_branch, border) = derive_branches(
            self.parent, self.extension
        )
        self._cache["_branch_parts"] = (firsts, parent_cyl, parent_branch, border)

    # ------------------------------------------------------------------ basic properties
    @property
    def n(self) -> int:
        """Number of cylinders."""
        return int(self.length.shape[0])

    def __len__(self) -> int:
        """Return the number of cylinders."""
        return self.n

    @property
    def end(self) -> np.ndarray:
        """End points ``start + length * axis`` (m)."""
        e = self._cache.get("end")
        if e is None:
            e = self.start + self.length[:, None] * self.axis
            e.flags.writeable = False
            self._cache["end"] = e
        return e

    @property
    def n_branches(self) -> int:
        """Number of branches."""
        return int(self._cache["_branch_parts"][0].shape[0])

    @property
    def max_order(self) -> int:
        """Highest branch order (0: the trunk alone)."""
        return int(self.order.max())

    @property
    def volume(self) -> float:
        """Total wood volume (m^3)."""
        return float(np.sum(np.pi * self.radius**2 * self.length))

    def children(self):
        """Return the children as CSR arrays (see :func:`children_csr`).

        Returns
        -------
        ptr, idx : ndarray
            Children of i are ``idx[ptr[i]:ptr[i+1]]``.
        """
        c = self._cache.get("children")
        if c is None:
            c = children_csr(self.parent)
            self._cache["children"] = c
        return c

    @property
    def branches(self) -> BranchTable:
        """The branch table (first cylinder, parent branch/cylinder, order, cylinders base-to-tip)."""
        bt = self._cache.get("branches")
        if bt is None:
            firsts, parent_cyl, parent_branch, border = self._cache["_branch_parts"]
            nb = firsts.shape[0]
            cyl = np.lexsort((self.position_in_branch, self.branch))
            n_cyl = np.bincount(self.branch, minlength=nb)
            ptr = np.zeros(nb + 1, dtype=np.int64)
            np.cumsum(n_cyl, out=ptr[1:])
            bt = BranchTable(
                first=firsts,
                parent_cyl=parent_cyl,
                parent_branch=parent_branch,
                order=border.astype(np.int64),
                n_cyl=n_cyl,
                ptr=ptr,
                cylinders=cyl,
            )
            self._cache["branches"] = bt
        return bt

    # ------------------------------------------------------------------ derived trees
    def with_topology(self, rule: str) -> Tree:
        """Return the same cylinders with branches chosen by another topology rule.

        ``source`` restores the tree's own stored branching when this tree was built from it.

        Parameters
        ----------
        rule : {"source", "subtree", "thickest"}
            The topology rule.

        Returns
        -------
        Tree
            The tree (this one when ``rule`` is its own).
        """
        if rule == self.topology:
            return self
        src_ext = self.extras.get("_source_extension")
        base_ext = src_ext if src_ext is not None else self.extension
        extras = dict(self.extras)
        extras.setdefault("_source_extension", np.asarray(self.extension if self.topology == "source" else base_ext))
        return Tree(
            self.start,
            self.axis,
            self.length,
            self.radius,
            self.parent,
            extras["_source_extension"],
            topology=rule,
            added=self.added,
            source_row=self.source_row,
            extras=extras,
            metadata=self.metadata,
        )

    def subset(self, keep) -> Tree:
        """Return the tree restricted to some rows.

        Parameters
        ----------
        keep : array_like
            A bool mask or indices of the rows to keep; closed under ``parent`` (every kept
            row's parent is kept).

        Returns
        -------
        Tree
            The subtree.

        Raises
        ------
        TreeError
            If ``keep`` is not closed under parent links.
        """
        keep = np.asarray(keep)
        mask = np.zeros(self.n, dtype=bool)
        mask[keep] = True
        rows = np.flatnonzero(mask)
        p = self.parent[rows]
        if np.any((p >= 0) & ~mask[np.maximum(p, 0)]):
            raise TreeError("subset is not closed under parent links")
        new = np.full(self.n, -1, dtype=np.int64)
        new[rows] = np.arange(rows.size)
        return Tree(
            self.start[rows],
            self.axis[rows],
            self.length[rows],
            self.radius[rows],
            remap_ids(self.parent[rows], new),
            remap_ids(self.extension[rows], new),
            topology=self.topology,
            added=self.added[rows],
            source_row=self.source_row[rows],
            extras={k: v[rows] for k, v in self.extras.items()},
            metadata=self.metadata,
        )

    def pruned(self, min_radius: float) -> Tree:
        """Return the tree as a simplified QSM draws it, without its thin cylinders.

        Every cylinder thinner than ``min_radius`` is removed with everything beyond it (the
        root cylinder stays).

        Parameters
        ----------
        min_radius : float
            Radius (m) below which a cylinder and all it carries are removed; 0 keeps every
            cylinder.

        Returns
        -------
        Tree
            The pruned tree (this tree itself when nothing is removed).
        """
        thin = (self.radius < min_radius) & (self.parent >= 0)
        if not thin.any():
            return self
        # the nearest thin cylinder or root at or above each row: kept where that is a root
        head, _ = jump_to_head(self.parent, thin | (self.parent < 0))
        return self.subset(self.parent[head] < 0)

    def translated(self, offset) -> Tree:
        """Return a copy moved by ``offset``.

        Parameters
        ----------
        offset : array_like, shape (3,)
            The shift (m).

        Returns
        -------
        Tree
            The moved tree.
        """
        return Tree(
            self.start + np.asarray(offset, float),
            self.axis,
            self.length,
            self.radius,
            self.parent,
            self.extension,
            topology=self.topology,
            added=self.added,
            source_row=self.source_row,
            extras=self.extras,
            metadata=self.metadata,
        )

    def __getstate__(self):
        """Return the columns for pickling (without the cache)."""
        return {k: getattr(self, k) for k in self.__slots__ if k != "_cache"}

    def __setstate__(self, state):
        """Restore the columns and recompute the branches."""
        for k, v in state.items():
            object.__setattr__(self, k, v)
        self._cache = {}
        self._set_branches()

    def __repr__(self) -> str:
        """Show the size, topology rule and source of the tree."""
        src = self.metadata.get("source") or self.metadata.get("model") or ""
        return (
            f"Tree({self.n} cylinders, {self.n_branches} branches, max order {self.max_order}, "
            f"topology={self.topology!r}{', ' + str(src) if src else ''})"
        )

    def equals(self, other: Tree, atol: float = 0.0) -> bool:
        """Tell whether both trees have the same columns (geometry within ``atol``).

        Parameters
        ----------
        other : Tree
            The other tree.
        atol : float, optional
            Absolute tolerance (m) of the geometry columns.

        Returns
        -------
        bool
            True when they are the same.
        """
        if self.n != other.n:
            return False
        same_int = all(
            np.array_equal(getattr(self, k), getattr(other, k))
            for k in ("parent", "extension", "branch", "order", "position_in_branch", "added")
        )
        same_f = all(
            np.allclose(getattr(self, k), getattr(other, k), rtol=0, atol=atol)
            for k in ("start", "axis", "length", "radius")
        )
        return same_int and same_f
