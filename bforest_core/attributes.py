"""TreeQSM's tree attributes and distributions, one implementation for QSMs and model trees.

What a TreeQSM user reads first (TreeQSM 2.4, Raumonen et al. 2013, Remote Sensing 5:491-520;
its ``treedata`` and ``branch`` structs): volume, length and surface area of the trunk and the
branches, the crown's diameters, area, volume, length and ratio, the per-branch table and the
distributions of wood by cylinder diameter, height, zenith and azimuth and of branches by
diameter, height, angle, azimuth, zenith and order. The definitions, and where they differ from
TreeQSM 2.4's, are stated in ``docs/tree-attributes.md``; in short:

* SI units throughout (m, m^2, m^3; angles in degrees). TreeQSM gives volumes in litres; the
  ``.mat`` writer converts.
* The trunk is branch 0 of the tree's own topology (TreeQSM's branch 1).
* Height, DBH and the crown base are the kernel's (:mod:`bforest_core.metrics`): one definition
  of each in the project.
* Crown points: every cylinder's start and end point plus points on the cylinder surface (four
  around the middle of a branch cylinder, rings of twelve at 1/4 ... 4/4 of a trunk cylinder),
  as TreeQSM samples its cylinder model.

Every function takes a :class:`~bforest_core.tree.Tree` and is vectorised over cylinders and
branches (loops run over classes, layers or sectors only).
"""

from __future__ import annotations

import numpy as np

from .metrics import axis_angles, classical_metrics, crown_base_height, crown_offset, ruled_summary

__all__ = [
    "branch_table",
    "tree_attributes",
    "distributions",
    "crown_points",
    "ATTRIBUTE_UNITS",
    "BRANCH_COLUMNS",
    "DISTRIBUTION_UNITS",
    "stem_taper",
    "crown_spreads",
    "fidelity_statistics",
    "FIDELITY_ATTRIBUTES",
]

#: per-branch columns of :func:`branch_table` with their units (TreeQSM's ``qsm.branch``)
BRANCH_COLUMNS = {
    "order": "",
    "parent": "",
    "diameter": "m",
    "volume": "m^3",
    "area": "m^2",
    "length": "m",
    "angle": "deg",
    "height": "m",
    "azimuth": "deg",
    "zenith": "deg",
}

#: units of :func:`tree_attributes`
ATTRIBUTE_UNITS = {
    "total_volume": "m^3",
    "trunk_volume": "m^3",
    "branch_volume": "m^3",
    "tree_height": "m",
    "trunk_length": "m",
    "branch_length": "m",
    "total_length": "m",
    "n_branches": "",
    "max_branch_order": "",
    "trunk_area": "m^2",
    "branch_area": "m^2",
    "total_area": "m^2",
    "dbh": "m",
    "crown_diameter_mean": "m",
    "crown_diameter_max": "m",
    "crown_area_conv": "m^2",
    "crown_area_alpha": "m^2",
    "crown_base_height": "m",
    "crown_length": "m",
    "crown_ratio": "",
    "crown_volume_conv": "m^3",
    "crown_volume_alpha": "m^3",
}

#: unit of each distribution quantity (the first three letters of a distribution's name)
DISTRIBUTION_UNITS = {"vol": "m^3", "are": "m^2", "len": "m", "num": ""}


# ------------------------------------------------------------------------------------------
# branches
# ------------------------------------------------------------------------------------------


def branch_table(tree) -> dict[str, np.ndarray]:
    """Tabulate the branches: one row per branch (branch 0 = the trunk), TreeQSM's ``qsm.branch``.

    Parameters
    ----------
    tree : Tree
        The tree.

    Returns
    -------
    dict of (n_branches,) arrays
        ``order``; ``parent`` (parent branch, -1 for the trunk); ``diameter`` (m, 2 x the radius
        of the branch's first cylinder); ``volume`` (m^3), ``area`` (m^2, lateral surface) and
        ``length`` (m) summed over the branch's cylinders; ``angle`` (deg) between the branch's
        first cylinder and its parent cylinder (0 for the trunk; when the first cylinder is a
        gap-filling ``added`` one, the second cylinder's axis, as TreeQSM does); ``height`` (m,
        the first cylinder's start above the tree's base point); ``azimuth`` (deg, -180...180,
        ``atan2(a_y, a_x)``) and ``zenith`` (deg, 0 = straight up) of the first cylinder's axis
        (added or not, as TreeQSM).
    """
    bt = tree.branches
    nb = len(bt)
    vol = np.bincount(tree.branch, weights=np.pi * tree.radius**2 * tree.length, minlength=nb)
    area = np.bincount(tree.branch, weights=2 * np.pi * tree.radius * tree.length, minlength=nb)
    length = np.bincount(tree.branch, weights=tree.length, minlength=nb)
    f = bt.first
    # the direction cylinder: the second one when the first fills a gap and there is a second
    second = bt.cylinders[np.minimum(bt.ptr[:-1] + 1, bt.ptr[1:] - 1)]
    fc = np.where(tree.added[f] & (bt.n_cyl > 1), second, f)
    a0 = tree.axis[f]
    pc = bt.parent_cyl
    ang = np.where(pc >= 0, axis_angles(tree, fc, np.maximum(pc, 0)), 0.0)
    return {
        "order": bt.order.astype(np.int64),
        "parent": bt.parent_branch.astype(np.int64),
        "diameter": 2.0 * tree.radius[f],
        "volume": vol,
        "area": area,
        "length": length,
        "angle": ang,
        "height": tree.start[f, 2] - tree.start[0, 2],
        "azimuth": np.degrees(np.arctan2(a0[:, 1], a0[:, 0])),
        "zenith": np.degrees(np.arccos(np.clip(a0[:, 2], -1.0, 1.0))),
    }


# ------------------------------------------------------------------------------------------
# crown geometry
# ------------------------------------------------------------------------------------------


def _frames(axis: np.ndarray):
    """Two unit vectors u, w orthogonal to each axis and to each other."""
    e = np.eye(3)[np.argmin(np.abs(axis), axis=1)]
    u = np.cross(axis, e)
    u /= np.linalg.norm(u, axis=1)[:, None]
    return u, np.cross(axis, u)


def crown_points(tree) -> np.ndarray:
    """Sample the cylinder model with points (the crown points).

    Every start and end point (each once: a child starts where its parent ends), four points
    around the middle of each branch cylinder and rings of twelve points at 1/4, 2/4, 3/4 and
    4/4 of the length of each trunk cylinder (on the cylinder surface).

    Parameters
    ----------
    tree : Tree
        The tree.

    Returns
    -------
    ndarray of float64, shape (k, 3)
        The points (m).
    """
    u, w = _frames(tree.axis)
    trunk = tree.branch == 0
    parts = [_unique_rows(np.concatenate([tree.start, tree.end]))]
    br = ~trunk
    if br.any():
        t = np.arange(4) * (np.pi / 2)
        mid = tree.start[br] + 0.5 * tree.length[br, None] * tree.axis[br]
        ring = np.cos(t)[None, :, None] * u[br][:, None, :] + np.sin(t)[None, :, None] * w[br][:, None, :]
        parts.append((mid[:, None, :] + tree.radius[br, None, None] * ring).reshape(-1, 3))
    if trunk.any():
        t = np.arange(12) * (np.pi / 6)
        ring = np.cos(t)[None, :, None] * u[trunk][:, None, :] + np.sin(t)[None, :, None] * w[trunk][:, None, :]
        ring = tree.radius[trunk, None, None] * ring  # (m, 12, 3)
        for k in (1, 2, 3, 4):
            c = tree.start[trunk] + (k / 4) * tree.length[trunk, None] * tree.axis[trunk]
            parts.append((c[:, None, :] + ring).reshape(-1, 3))
    return np.concatenate(parts)


def _unique_rows(P: np.ndarray) -> np.ndarray:
    """Return the distinct rows of the float table ``P`` in a fixed order (by their bytes).

    Three times as fast as ``np.unique(P, axis=0)`` on the millions of points of a large tree.
    """
    P = np.ascontiguousarray(P + 0.0)  # -0.0 -> 0.0: one point, one byte pattern
    rows = P.view(np.dtype((np.void, P.dtype.itemsize * P.shape[1]))).ravel()
    return np.unique(rows).view(P.dtype).reshape(-1, P.shape[1])


def _hull2d(xy: np.ndarray):
    """Return (vertices in order, area, centroid) of the convex hull of 2-D points.

    None when the points span no area.
    """
    from scipy.spatial import ConvexHull, QhullError

    if xy.shape[0] < 3:  # (qhull passes over repeated points: no need to remove them first)
        return None
    try:
        h = ConvexHull(xy)
    except (QhullError, ValueError):
        return None
    v = xy[h.vertices]
    x, y = v[:, 0], v[:, 1]
    x1, y1 = np.roll(x, -1), np.roll(y, -1)
    cross = x * y1 - x1 * y
    a = cross.sum() / 2.0
    if a <= 0:
        return None
    c = np.array([((x + x1) * cross).sum(), ((y + y1) * cross).sum()]) / (6.0 * a)
    return v, float(a), c


def _sector_diameters(xy: np.ndarray, centre: np.ndarray, n: int = 18) -> np.ndarray:
    """Return diameters through ``centre`` in ``n`` directions (each covers 180/n deg).

    Each is the farthest point in a sector plus the farthest in the opposite sector (0 for an
    empty sector).
    """
    v = xy - centre
    ang = np.arctan2(v[:, 1], v[:, 0]) + np.pi  # 0 ... 2 pi
    sec = np.minimum((ang / (np.pi / n)).astype(np.int64), 2 * n - 1)
    far = np.zeros(2 * n)
    np.maximum.at(far, sec, np.hypot(v[:, 0], v[:, 1]))
    return far[:n] + far[n:]


def crown_spreads(tree, points: np.ndarray | None = None) -> np.ndarray:
    """Measure crown diameters (m) in horizontal layers (TreeQSM's ``spreads``).

    The points' height range is cut into 20 layers (tree taller than 10 m), 10 (taller than 2 m)
    or 5; in each layer with more than five points the diameters in 18 directions pass through
    the centroid of the layer's convex hull (:func:`_sector_diameters`); a layer with fewer
    points, or points on one line, gets zeros. Its row means are TreeQSM's ``VerticalProfile``.

    Parameters
    ----------
    tree : Tree
        The tree.
    points : ndarray, shape (k, 3), optional
        The crown points (default: :func:`crown_points` of the tree).

    Returns
    -------
    ndarray, shape (layers, 18)
        Diameters (m) per layer (bottom first) and direction.
    """
    P = crown_points(tree) if points is None else points
    bot, top = P[:, 2].min(), P[:, 2].max()
    hei = top - bot
    m = 20 if hei > 10 else 10 if hei > 2 else 5
    layer = np.minimum(((P[:, 2] - bot) / max(hei, 1e-12) * m).astype(np.int64), m - 1)
    out = np.zeros((m, 18))
    for j in range(m):  # one loop over layers, not points
        X = P[layer == j]
        if X.shape[0] <= 5:
            continue
        h = _hull2d(X[:, :2])
        if h is not None:
            out[j] = _sector_diameters(X[:, :2], h[2])
    return out


#: the most points an alpha shape is triangulated on (2-D, 3-D): a larger cloud is thinned first
#: (:func:`thinned`), so the crown measures of a QSM of a million cylinders take seconds, not minutes
ALPHA_POINTS = {2: 100_000, 3: 50_000}


def thinned(pts: np.ndarray, alpha: float, limit: int) -> tuple[np.ndarray, float]:
    """Return the points of ``pts`` an alpha shape of ``alpha`` is measured on.

    All of them when they are at most ``limit``, else one per cube (square in 2-D) of a grid,
    the last of each in the points' order, the grid's side ``alpha / 16`` doubled until at
    most ``limit`` are left. With cubes 16 times smaller than ``alpha`` the alpha shape loses
    1 % of its volume or less (0.2 % of its area in 2-D), at 1/8 about 2 % (a 140 000-cylinder
    synthetic crown; docs/tree-attributes.md).

    Parameters
    ----------
    pts : ndarray, shape (k, d)
        The points (m).
    alpha : float
        The alpha of the shape (m).
    limit : int
        The most points to keep.

    Returns
    -------
    tuple of (ndarray, float)
        The points kept and the side of the grid (m; 0 when nothing was thinned).
    """
    if pts.shape[0] <= limit:
        return pts, 0.0
    lo = pts.min(axis=0)
    side = alpha / 16
    while np.prod(np.floor((pts.max(axis=0) - lo) / side) + 1) >= 2**62:  # a grid too fine to number
        side *= 2
    cells = np.floor((pts - lo) / side).astype(np.int64)
    span = cells.max(axis=0) + 1
    key = np.ravel_multi_index(cells.T, span)
    if np.prod(span) <= 8 * pts.shape[0]:  # a grid the size of the cloud: one pass, no sort
        slot = np.full(int(np.prod(span)), -1, dtype=np.int64)
        slot[key] = np.arange(key.size)  # a repeated cell keeps its last point
        keep = slot[slot >= 0]
    else:
        _, keep = np.unique(key[::-1], return_index=True)
        keep = key.size - 1 - keep  # the last point of each cell
    cells = cells[keep]  # the occupied cells, each with the last of its points
    while keep.size > limit:  # twice the side: the cells merge in eights (fours), each keeps its last point
        cells //= 2
        side *= 2
        key = np.ravel_multi_index(cells.T, cells.max(axis=0) + 1)
        order = np.lexsort((-keep, key))
        head = np.r_[True, key[order][1:] != key[order][:-1]]
        cells, keep = cells[order][head], keep[order][head]
    return pts[np.sort(keep)], float(side)


def _alpha_measure(pts: np.ndarray, alpha: float, notes: list | None = None) -> float:
    """Return the area (2-D) or volume (3-D) of the alpha shape of ``pts``.

    The alpha shape is the Delaunay triangles (tetrahedra) whose circumradius is at most
    ``alpha``, of at most :data:`ALPHA_POINTS` points (:func:`thinned`; a line saying so is
    appended to ``notes``).
    """
    from scipy.spatial import Delaunay, QhullError

    d = pts.shape[1]
    n = pts.shape[0]
    pts, side = thinned(pts, alpha, ALPHA_POINTS[d])
    if not side:  # a cloud of repeated points (the crown's projection): each once
        pts = _unique_rows(pts)
    if side and notes is not None:
        notes.append(
            f"the {d}-D alpha shape is measured on {pts.shape[0]:,} of the {n:,} crown points, one per "
            f"{side:.3g} m {'cube' if d == 3 else 'square'} (alpha {alpha:.3g} m; docs/tree-attributes.md)"
        )
    if pts.shape[0] < d + 1:
        return 0.0
    try:
        tri = Delaunay(pts)
    except (QhullError, ValueError):
        return 0.0
    s = pts[tri.simplices]  # (k, d+1, d)
    e = s[:, 1:, :] - s[:, :1, :]  # edge vectors from vertex 0
    det = np.linalg.det(e)
    size = np.abs(det) / (2.0 if d == 2 else 6.0)
    # circumcentre c solves 2 e c = |e|^2 (relative to vertex 0)
    rhs = 0.5 * np.einsum("kij,kij->ki", e, e)
    ok = np.abs(det) > 1e-15
    r = np.full(det.shape, np.inf)
    if ok.any():
        c = np.linalg.solve(e[ok], rhs[ok][..., None])[..., 0]
        r[ok] = np.linalg.norm(c, axis=1)
    return float(size[r <= alpha].sum())


def _hull3d_volume(pts: np.ndarray) -> float:
    from scipy.spatial import ConvexHull, QhullError

    if pts.shape[0] < 4:
        return 0.0
    try:
        return float(ConvexHull(pts).volume)
    except (QhullError, ValueError):
        return 0.0


def stem_taper(tree) -> np.ndarray:
    """Return TreeQSM's ``StemTaper``: the trunk diameter along the trunk.

    Parameters
    ----------
    tree : Tree
        The tree.

    Returns
    -------
    ndarray, shape (2, n_trunk + 1)
        Row 0: distance along the trunk from its base (m); row 1: the trunk diameter there (m):
        the first cylinder's diameter at 0, then each cylinder's at its start, the last one's
        again at the tip.
    """
    bt = tree.branches
    c = bt.cylinders[bt.ptr[0] : bt.ptr[1]]
    d = 2.0 * tree.radius[c]
    dist = np.concatenate([[0.0], np.cumsum(tree.length[c])])
    diam = np.concatenate([d[:1], d[1:], d[-1:]])
    return np.vstack([dist, diam])


# ------------------------------------------------------------------------------------------
# tree attributes
# ------------------------------------------------------------------------------------------


def tree_attributes(
    tree, points: np.ndarray | None = None, alpha: bool = True, notes: list | None = None
) -> dict[str, float]:
    """TreeQSM's tree attributes in SI units (:data:`ATTRIBUTE_UNITS`).

    Parameters
    ----------
    tree : Tree
        The tree.
    points : ndarray, shape (k, 3), optional
        The crown points (default: :func:`crown_points` of the tree).
    alpha : bool, optional
        Compute the alpha shapes; ``False`` leaves them out (NaN): they cost a Delaunay
        triangulation (of at most :data:`ALPHA_POINTS` points: a larger crown is thinned).
    notes : list, optional
        Receives a line for each alpha shape measured on a thinned crown.

    Returns
    -------
    dict
        ``total_volume``, ``trunk_volume``, ``branch_volume`` (m^3: sum of pi r^2 l over all,
        trunk, non-trunk cylinders); ``tree_height`` (m, :func:`~bforest_core.metrics.classical_metrics`);
        ``trunk_length``, ``branch_length``, ``total_length`` (m, sums of cylinder lengths);
        ``n_branches`` (branches other than the trunk), ``max_branch_order``; ``trunk_area``,
        ``branch_area``, ``total_area`` (m^2, sums of 2 pi r l); ``dbh`` (m, the kernel's);
        ``crown_diameter_mean`` (m: mean of 18 diameters through the centroid of the convex hull
        of the crown points' horizontal projection, each the farthest cylinder tip in a 10 deg
        sector plus the farthest in the opposite sector); ``crown_diameter_max`` (m, the largest
        distance between two vertices of that hull); ``crown_area_conv`` (m^2, the hull's area);
        ``crown_area_alpha`` (m^2, the 2-D alpha shape with alpha = max(0.5 m, mean diameter / 10));
        ``crown_base_height`` (m, :func:`~bforest_core.metrics.crown_base_height`);
        ``crown_length`` = height - crown base height; ``crown_ratio`` = crown length / height;
        ``crown_volume_conv`` (m^3, the 3-D convex hull of the crown points at or above the crown
        base) and ``crown_volume_alpha`` (m^3, their alpha shape with alpha = max(0.5 m, mean
        diameter / 5)). A tree without first-order branches has crown base = height and zero
        crown length, ratio and volumes (as TreeQSM).
    """
    P = crown_points(tree) if points is None else points
    vol = np.pi * tree.radius**2 * tree.length
    area = 2 * np.pi * tree.radius * tree.length
    trunk = tree.branch == 0
    m = classical_metrics(tree)
    h = m["height"]
    out = {
        "total_volume": float(vol.sum()),
        "trunk_volume": float(vol[trunk].sum()),
        "branch_volume": float(vol[~trunk].sum()),
        "tree_height": h,
        "trunk_length": float(tree.length[trunk].sum()),
        "branch_length": float(tree.length[~trunk].sum()),
        "total_length": float(tree.length.sum()),
        "n_branches": float(tree.n_branches - 1),
        "max_branch_order": float(tree.max_order),
        "trunk_area": float(area[trunk].sum()),
        "branch_area": float(area[~trunk].sum()),
        "total_area": float(area.sum()),
        "dbh": m["dbh"],
    }
    hull = _hull2d(P[:, :2])
    if hull is None:
        out.update(crown_diameter_mean=0.0, crown_diameter_max=0.0, crown_area_conv=0.0, crown_area_alpha=0.0)
    else:
        v, a, c = hull
        out["crown_diameter_mean"] = float(_sector_diameters(tree.end[:, :2], c).mean())
        dv = v[:, None, :] - v[None, :, :]
        out["crown_diameter_max"] = float(np.sqrt((dv**2).sum(-1)).max())
        out["crown_area_conv"] = a
        out["crown_area_alpha"] = (
            _alpha_measure(P[:, :2], max(0.5, out["crown_diameter_mean"] / 10), notes) if alpha else np.nan
        )
    cbh = crown_base_height(tree)
    if not np.isfinite(cbh):
        out.update(
            crown_base_height=h, crown_length=0.0, crown_ratio=0.0, crown_volume_conv=0.0, crown_volume_alpha=0.0
        )
        return out
    out["crown_base_height"] = cbh
    out["crown_length"] = h - cbh
    out["crown_ratio"] = (h - cbh) / h if h > 0 else 0.0
    X = P[P[:, 2] >= tree.start[0, 2] + cbh]
    out["crown_volume_conv"] = _hull3d_volume(X)
    out["crown_volume_alpha"] = _alpha_measure(X, max(0.5, out["crown_diameter_mean"] / 5), notes) if alpha else np.nan
    return out


#: TreeQSM attributes in the clones' fidelity table: volumes and crown measures (branch length and
#: area are left out: a model tree holds twigs no scan resolves, and the table's branch lengths
#: already apply the detection limit; the alpha shapes cost a triangulation per clone)
FIDELITY_ATTRIBUTES = (  # (TreeQSM's trunk volume is the summary's stem wood volume, volume_o0: not twice)
    "branch_volume",
    "crown_diameter_mean",
    "crown_area_conv",
    "crown_length",
    "crown_ratio",
    "crown_volume_conv",
)


def fidelity_statistics(tree, topology: str | None = None, statistics=None) -> dict[str, float]:
    """Compute the statistics the clones' fidelity table compares.

    Parameters
    ----------
    tree : Tree
        The tree.
    topology : {"source", "subtree", "thickest"} or None, optional
        The branch rule to measure by (:meth:`Tree.with_topology`): the size term's, so that the
        table counts branches as the fit held them; None keeps the tree's own branches.
    statistics : sequence of str, optional
        The statistics measured by ``topology`` (default: all); the others by the tree's own branches.

    Returns
    -------
    dict of str to float
        :func:`~bforest_core.metrics.tree_summary`, the :data:`FIDELITY_ATTRIBUTES` (units:
        :func:`~bforest_core.metrics.summary_unit`) and the crown's offset from its stem,
        ``crown_offset_x`` and ``crown_offset_y`` (crown radii, :func:`~bforest_core.metrics.crown_offset`,
        measured on the tree's own stem whatever ``topology``).
    """
    # measured wholly by the rule: the tree converted once (ruled_summary finds it in that rule)
    whole = tree.with_topology(topology) if topology is not None and statistics is None else tree
    out = ruled_summary(whole, topology, statistics)
    a = tree_attributes(whole, alpha=False)
    out.update({k: a[k] for k in FIDELITY_ATTRIBUTES})
    out["crown_offset_x"], out["crown_offset_y"] = (float(v) for v in crown_offset(tree))
    return out


# ------------------------------------------------------------------------------------------
# distributions
# ------------------------------------------------------------------------------------------

#: a value this close below a class edge (in class widths) is on the edge: QSMs store single
#: precision (0.005 m is 0.00499999989 in float32), and TreeQSM compares in single precision
_EDGE_TOL = 1e-6


def _classes(par: np.ndarray, width: float, n: int | None = None) -> tuple[np.ndarray, int]:
    """Return the 0-based class ``floor(par / width)`` of half-open classes ``[k w, (k+1) w)``.

    Also the number of classes (enough for the largest value unless ``n`` is given).
    """
    k = np.floor(par / width + _EDGE_TOL).astype(np.int64) if par.size else np.zeros(0, np.int64)
    if n is None:
        n = int(k.max()) + 1 if k.size else 0
    return k, n


def _sums(k: np.ndarray, n: int, weights: dict) -> dict[str, np.ndarray]:
    keep = (k >= 0) & (k < n)
    return {
        name: np.bincount(k[keep], weights=None if w is None else w[keep], minlength=n)[:n].astype(float)
        for name, w in weights.items()
    }


def _height_overlap(b: np.ndarray, t: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return the share of each cylinder in each 1 m height class it reaches.

    As (cylinder, class, share) triplets: a cylinder reaches one class or a few, so the table of
    a million cylinders stays small (a dense (n_cyl, n) table took gigabytes).

    A cylinder spans height b to t (m above the bottom); a level cylinder lies wholly in the
    class of its height.
    """
    lo, hi = np.minimum(b, t), np.maximum(b, t)
    first = np.clip(np.floor(lo).astype(np.int64), 0, n - 1)
    last = np.clip(np.ceil(hi).astype(np.int64) - 1, first, n - 1)
    count = last - first + 1
    row = np.repeat(np.arange(lo.size), count)
    cls = first[row] + (np.arange(row.size) - np.repeat(np.cumsum(count) - count, count))
    ov = np.clip(np.minimum(hi[row], cls + 1.0) - np.maximum(lo[row], cls), 0, None)
    span = (hi - lo)[row]
    tall = span > 1e-12
    share = np.where(tall, ov / np.where(tall, span, 1.0), (cls == first[row]).astype(float))
    return row, cls, share


def distributions(tree) -> dict[str, np.ndarray]:
    """Compute TreeQSM's distributions, SI units (volumes m^3, areas m^2, lengths m, counts).

    Cylinders (wood parts): ``VolCylDia``/``AreCylDia``/``LenCylDia`` per 1 cm cylinder-diameter
    class (class k holds diameters in [k, k+1) cm, k = 0, 1, ...); ``...CylHei`` per 1 m height
    class above the lowest cylinder start (a cylinder counts in each class with the share of its
    vertical extent inside it); ``...CylZen`` per 10 deg zenith class (18); ``...CylAzi`` per
    10 deg azimuth class (36, from -180 deg).

    Branches (the trunk left out): ``VolBranch<X>``, ``AreBranch<X>``, ``LenBranch<X>``,
    ``NumBranch<X>`` and the same for first-order branches only (``VolBranch1<X>``...) with X =
    ``Dia`` (1 cm base-diameter classes), ``Hei`` (1 m classes of the branch's base height),
    ``Ang`` (10 deg branching-angle classes, 18), ``Azi`` (10 deg, 36, from -180 deg), ``Zen``
    (10 deg, 18); and per branch order 1 ... max: ``VolBranchOrd``, ``AreBranchOrd``,
    ``LenBranchOrd``, ``NumBranchOrd``.

    The names are TreeQSM 2.4's ``treedata`` names; the values are in SI units (TreeQSM gives
    volumes in litres). Class k of every array is element k (0-based).

    Parameters
    ----------
    tree : Tree
        The tree.

    Returns
    -------
    dict of str to ndarray
        The distributions by name.
    """
    out: dict[str, np.ndarray] = {}
    r, l, ax = tree.radius, tree.length, tree.axis
    cw = {"Vol": np.pi * r**2 * l, "Are": 2 * np.pi * r * l, "Len": l}
    k, n = _classes(2 * r, 0.01)
    for q, v in _sums(k, n, cw).items():
        out[f"{q}CylDia"] = v
    bot = tree.start[:, 2].min()
    top = max(tree.start[:, 2].max(), tree.end[:, 2].max())
    nh = max(int(np.ceil(top - bot - 1e-9)), 1)
    row, cls, share = _height_overlap(tree.start[:, 2] - bot, tree.end[:, 2] - bot, nh)
    for q, w in cw.items():
        out[f"{q}CylHei"] = np.bincount(cls, weights=w[row] * share, minlength=nh)
    zen = np.degrees(np.arccos(np.clip(ax[:, 2], -1, 1)))
    k, _ = _classes(zen, 10.0, 18)
    for q, v in _sums(np.minimum(k, 17), 18, cw).items():
        out[f"{q}CylZen"] = v
    azi = np.degrees(np.arctan2(ax[:, 1], ax[:, 0])) + 180.0
    k, _ = _classes(azi, 10.0, 36)
    for q, v in _sums(np.minimum(k, 35), 36, cw).items():
        out[f"{q}CylAzi"] = v

    b = branch_table(tree)
    sel = np.arange(b["order"].size) > 0  # the trunk is branch 0
    bw = {"Vol": b["volume"][sel], "Are": b["area"][sel], "Len": b["length"][sel], "Num": None}
    first = b["order"][sel] == 1
    pars = {
        "Dia": (b["diameter"][sel], 0.01, None),
        "Hei": (b["height"][sel], 1.0, nh),
        "Ang": (b["angle"][sel], 10.0, 18),
        "Azi": (b["azimuth"][sel] + 180.0, 10.0, 36),
        "Zen": (b["zenith"][sel], 10.0, 18),
    }
    for name, (par, width, n) in pars.items():
        k, n = _classes(par, width, n)
        if name in ("Ang", "Azi", "Zen"):
            k = np.minimum(k, n - 1)  # the closed upper end (180 deg) belongs to the last class
        all_ = _sums(k, n, bw)
        one = _sums(np.where(first, k, -1), n, bw)
        for q in bw:
            out[f"{q}Branch{name}"] = all_[q]
            out[f"{q}Branch1{name}"] = one[q]
    no = int(b["order"].max()) if b["order"].size else 0
    k = b["order"][sel] - 1
    for q, v in _sums(k, max(no, 1), bw).items():
        out[f"{q}BranchOrd"] = v
    return out
