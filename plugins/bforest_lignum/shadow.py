"""Receiver-only pyramid shadow of the simplified LIGNUM (docs/models.md A.6).

Every segment midpoint sits in a voxel (X, Y, Z) = floor(p / V_S) of an unbounded lattice anchored
at the origin. A source voxel j shades a receiver voxel i with S_max (1 - dZ / q_max) when
dZ = Z_j - Z_i is in [1, q_max - 1] and max(|dX|, |dY|) <= dZ (a 45 degree pyramid with linear
fall-off, no self-shading; sources in one voxel add up).

Four exact evaluations, chosen per call by a cost estimate (:func:`shadow_fast`):

* ``"grid"``: sources bucketed in columns of q_max x q_max voxels, sorted by Z; a compiled
  (numba) loop scans, for each receiver, the Z range of its pyramid in the 3 x 3 neighbouring
  columns. The default for all but dense crowns in coarse voxels (3x faster than the kd-tree
  searches on sf_real at T = 32-40; benchmarks/ssm_lignum.py);
* ``"pairs"``: one symmetric ``cKDTree.query_pairs`` (Chebyshev radius q_max - 1) over all
  points, filtered with the integer pyramid rule (best when most points are receivers);
* ``"two_tree"``: receivers only, searching the slab above each of them (z shifted by q_max / 2
  and scaled so that the slab is a Chebyshev ball), for few receivers among many sources;
* ``"sat"``: per-layer integral images (summed-area tables) of the cropped occupied box,
  S_i = sum_q w_q BoxSum(layer Z_i + q, half-width q), built in chunks of layers; best for dense
  crowns in coarse voxels, where the pair count explodes.

The weights are accumulated as the integers (q_max - dZ) and scaled by S_max / q_max once, so
every method and the brute-force reference give bit-identical sums.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from scipy.spatial import cKDTree

__all__ = ["q_max_of", "voxel_coords", "shadow_fast", "shadow_brute", "METHODS"]

METHODS = ("auto", "grid", "pairs", "two_tree", "sat")
# rough per-item costs (s) of the methods, measured on this implementation; only ratios matter
_C_GRID = 3e-9  # per candidate of the compiled bucket scan (numba)
_C_PAIR = 120e-9  # per estimated symmetric pair (query + filter)
_C_TWO = 250e-9  # per estimated receiver-source candidate of the two-tree search
_C_CELL = 13e-9  # per cell of the layer integral images
_C_QUERY = 60e-9  # per receiver and layer of the box-sum queries
_SAT_CHUNK_CELLS = 4_000_000  # integral-image cells built at once (memory bound)


def q_max_of(shadow_len: float, voxel_size: float) -> int:
    """Number of voxel layers of the pyramid, q_max = ceil(round(S_L / V_S, 9))."""
    return int(math.ceil(round(shadow_len / voxel_size, 9)))


def voxel_coords(points: np.ndarray, voxel_size: float) -> np.ndarray:
    """Integer voxel coordinates floor(p / V_S) of ``(n, 3)`` points."""
    return np.floor(np.asarray(points, dtype=np.float64) / voxel_size).astype(np.int64)


def shadow_fast(
    vox: np.ndarray, shadow_max: float, q_max: int, receivers: np.ndarray | None = None, method: str = "auto"
) -> np.ndarray:
    """Shadow S_i at voxel points, equal (bit for bit) to :func:`shadow_brute`.

    Parameters
    ----------
    vox : (n, 3) int array
        Voxel coordinates of all points (every point is a source).
    shadow_max : float
        S_max, the shadow of one source one layer above a receiver (before the linear fall-off).
    q_max : int
        Pyramid depth in layers.
    receivers : (n,) bool array, optional
        Points at which S is wanted (default: all). Others get NaN.
    method : {"auto", "pairs", "two_tree", "sat"}
        Evaluation method; ``auto`` picks the cheapest by :func:`choose_method`.

    Returns
    -------
    (n,) float64
        The summed shadow at every receiver, NaN elsewhere.
    """
    if method not in METHODS:
        raise ValueError(f"unknown shadow method {method!r} (choose from {', '.join(METHODS)})")
    vox = np.asarray(vox, dtype=np.int64)
    n = vox.shape[0]
    rcv = np.arange(n) if receivers is None else np.flatnonzero(receivers)
    out = np.full(n, np.nan)
    out[rcv] = 0.0
    if n < 2 or q_max < 2 or rcv.size == 0:
        return out
    rel = vox - vox.min(axis=0)
    if method == "auto":
        method = choose_method(rel, rcv.size, q_max)
    if method == "grid":
        counts = _counts_grid(rel, rcv, q_max)
    elif method == "pairs":
        counts = _counts_pairs(rel, q_max)[rcv]
    elif method == "two_tree":
        counts = _counts_two_tree(rel, rcv, q_max)
    else:
        counts = _counts_sat(rel, rcv, q_max)
    out[rcv] = counts * (shadow_max / q_max)
    return out


def choose_method(rel: np.ndarray, n_rcv: int, q_max: int) -> str:
    """Cheapest method by a cost model: the pair count is estimated from a histogram of cells
    of edge q_max (each point against its 27 neighbouring cells), the integral-image cost from
    the occupied box.

    The grid scan costs less than the pair and two-tree searches whatever the pair count (its
    cost per candidate is the smallest), so only the integral images can beat it; when the grid's
    cost at the most pairs there can be (every point near every other) is no more than theirs,
    the grid wins without the histogram, the same choice the full model makes (most years of a
    tree: benchmarks/ssm_lignum.py)."""
    sat = _sat_cost(rel, n_rcv, q_max)
    if _grid_cost_bound(rel.shape[0], n_rcv, q_max) <= sat:
        return "grid"
    return _cheapest(rel, n_rcv, q_max, sat)


def _sat_cost(rel: np.ndarray, n_rcv: int, q_max: int) -> float:
    """The integral images' cost: their cells (the occupied box) and one query per receiver and layer."""
    return _C_CELL * float(np.prod(rel.max(axis=0) + 1)) + _C_QUERY * n_rcv * (q_max - 1)


def _grid_cost_bound(n: int, n_rcv: int, q_max: int) -> float:
    """The grid scan's cost at the most pairs ``n`` points can make (every one near every other)."""
    return _C_GRID * float(n) * n * _near_share(q_max) * (n_rcv / n)


def _near_share(q_max: int) -> float:
    """Of the ordered pairs of points in 27 neighbouring cells of edge q_max, those in the cube."""
    return ((2 * q_max - 1) / (3.0 * q_max)) ** 3


def _cheapest(rel: np.ndarray, n_rcv: int, q_max: int, sat: float) -> str:
    """The cost model in full (:func:`choose_method`), ``sat`` the integral images' cost."""
    n = rel.shape[0]
    c = rel // q_max
    dims = c.max(axis=0) + 3
    flat = ((c[:, 0] + 1) * dims[1] + (c[:, 1] + 1)) * dims[2] + (c[:, 2] + 1)
    h = np.bincount(flat, minlength=int(np.prod(dims))).reshape(dims)
    nb = np.zeros_like(h)
    core = (slice(1, -1),) * 3
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            for dz in (-1, 0, 1):
                nb[core] += h[1 + dx : dims[0] - 1 + dx, 1 + dy : dims[1] - 1 + dy, 1 + dz : dims[2] - 1 + dz]
    near = float(np.sum(h * nb)) * _near_share(q_max)  # ordered pairs in the cube
    cost = {
        "grid": _C_GRID * near * (n_rcv / n),
        "pairs": _C_PAIR * near / 2,
        "two_tree": _C_TWO * near / 2 * (n_rcv / n),
        "sat": sat,
    }
    return min(cost, key=cost.get)


def _counts_grid(rel: np.ndarray, rcv: np.ndarray, q_max: int) -> np.ndarray:
    """Integer pyramid sums at the receivers: sources bucketed in columns of q_max x q_max voxels
    and sorted by Z inside each column; every receiver scans the Z range [Z + 1, Z + q_max - 1]
    of its own and the eight neighbouring columns (compiled loop, :func:`_grid_kernel`)."""
    cx = rel[:, 0] // q_max
    cy = rel[:, 1] // q_max
    ny = int(cy.max()) + 3  # one empty column of padding on each side
    key = (cx + 1) * ny + (cy + 1)
    o = np.lexsort((rel[:, 2], key))
    start = np.searchsorted(key[o], np.arange(int(key.max()) + ny + 3))
    src = np.ascontiguousarray(rel[o])
    return _grid_kernel(src, start, np.ascontiguousarray(rel[rcv]), key[rcv], ny, q_max)


@numba.njit(cache=True, nogil=True)
def _grid_kernel(src, start, r, rkey, ny, q_max):  # pragma: no cover - compiled
    out = np.zeros(r.shape[0])
    for k in range(r.shape[0]):
        x, y, z = r[k, 0], r[k, 1], r[k, 2]
        acc = 0
        for dcx in (-1, 0, 1):
            for dcy in (-1, 0, 1):
                b = rkey[k] + dcx * ny + dcy
                lo, hi = start[b], start[b + 1]
                # first source of the column with Z >= z + 1 (binary search)
                while lo < hi:
                    mid = (lo + hi) // 2
                    if src[mid, 2] <= z:
                        lo = mid + 1
                    else:
                        hi = mid
                for j in range(lo, start[b + 1]):
                    dz = src[j, 2] - z
                    if dz >= q_max:
                        break
                    if abs(src[j, 0] - x) <= dz and abs(src[j, 1] - y) <= dz:
                        acc += q_max - dz
        out[k] = acc
    return out


def _counts_pairs(rel: np.ndarray, q_max: int) -> np.ndarray:
    """Integer pyramid sums at every point: one symmetric ``query_pairs``."""
    n = rel.shape[0]
    # sort by Z: query_pairs returns i < j, so the source is always j and dZ = Z_j - Z_i >= 0
    o = np.argsort(rel[:, 2], kind="stable")
    vs = rel[o]
    X, Y, Z = (vs[:, k].astype(np.int32) for k in range(3))
    tree = cKDTree(vs.astype(np.float64), leafsize=24, balanced_tree=False, compact_nodes=False)
    pairs = tree.query_pairs(r=float(q_max - 1), p=np.inf, output_type="ndarray")
    counts = np.zeros(n)
    if pairs.shape[0]:
        i = np.ascontiguousarray(pairs[:, 0])
        j = np.ascontiguousarray(pairs[:, 1])
        dz = Z[j] - Z[i]  # <= q_max - 1 by the search radius
        keep = (np.abs(X[j] - X[i]) <= dz) & (np.abs(Y[j] - Y[i]) <= dz) & (dz > 0)
        w = np.where(keep, q_max - dz, 0).astype(np.float64)
        counts[o] = np.bincount(i, weights=w, minlength=n)
    return counts


def _counts_two_tree(rel: np.ndarray, rcv: np.ndarray, q_max: int) -> np.ndarray:
    """Integer pyramid sums at the receivers: a kd-tree of the receivers, shifted up by
    q_max / 2 and with z scaled so that the slab dZ in [1, q_max - 1], |dX|, |dY| <= q_max - 1
    is a Chebyshev ball of radius q_max - 1, against a kd-tree of all sources."""
    H = q_max - 1
    if q_max >= 3:
        c, s = q_max / 2.0, 2.0 * (q_max - 1) / (q_max - 2)
    else:  # q_max = 2: only dZ = 1 counts; search dZ in [0, 2] and filter
        c, s = 1.0, 1.0
    src_pts = rel.astype(np.float64)
    src_pts[:, 2] *= s
    rcv_pts = rel[rcv].astype(np.float64)
    rcv_pts[:, 2] = (rcv_pts[:, 2] + c) * s
    t_src = cKDTree(src_pts, leafsize=24, balanced_tree=False, compact_nodes=False)
    t_rcv = cKDTree(rcv_pts, leafsize=24, balanced_tree=False, compact_nodes=False)
    m = t_rcv.sparse_distance_matrix(t_src, H * (1.0 + 1e-9), p=np.inf, output_type="ndarray")
    if m.shape[0] == 0:
        return np.zeros(rcv.size)
    i = m["i"]
    j = m["j"]
    X, Y, Z = (rel[:, k].astype(np.int32) for k in range(3))
    ri = rcv[i]
    dz = Z[j] - Z[ri]
    keep = (dz >= 1) & (dz <= H) & (np.abs(X[j] - X[ri]) <= dz) & (np.abs(Y[j] - Y[ri]) <= dz)
    w = np.where(keep, q_max - dz, 0).astype(np.float64)
    return np.bincount(i, weights=w, minlength=rcv.size)


def _counts_sat(rel: np.ndarray, rcv: np.ndarray, q_max: int) -> np.ndarray:
    """Integer pyramid sums at the receivers from per-layer integral images of source counts,
    built over chunks of layers (loops over layer chunks and receiver blocks only)."""
    nx, ny, nz = (int(v) + 1 for v in rel.max(axis=0))
    sy = ny + 1
    sz = (nx + 1) * (ny + 1)
    d = np.arange(1, q_max, dtype=np.int64)
    wq = (q_max - d).astype(np.float64)
    Xr, Yr, Zr = rel[rcv, 0], rel[rcv, 1], rel[rcv, 2]
    o_r = np.argsort(Zr, kind="stable")
    Zs = Zr[o_r]
    o_s = np.argsort(rel[:, 2], kind="stable")
    src = rel[o_s]
    Zsrc = src[:, 2]
    counts = np.zeros(rcv.size)
    layers = max(1, _SAT_CHUNK_CELLS // sz)
    block = max(1, 2_000_000 // (q_max - 1))
    for z0 in range(0, nz, layers):
        z1 = min(nz, z0 + layers)
        a, b = np.searchsorted(Zsrc, [z0, z1])
        if a == b:
            continue
        s = src[a:b]
        flat = ((s[:, 2] - z0) * nx + s[:, 0]) * ny + s[:, 1]
        g = np.bincount(flat, minlength=(z1 - z0) * nx * ny).reshape(z1 - z0, nx, ny)
        P = np.zeros((z1 - z0, nx + 1, ny + 1), dtype=np.int64)
        np.cumsum(g, axis=1, out=P[:, 1:, 1:])
        np.cumsum(P[:, 1:, 1:], axis=2, out=P[:, 1:, 1:])
        Pf = P.reshape(-1)
        # receivers whose pyramid reaches into [z0, z1): Z_r + 1 <= z1 - 1 and Z_r + q - 1 >= z0
        ra, rb = np.searchsorted(Zs, [z0 - q_max + 1, z1 - 1])
        for c0 in range(ra, rb, block):
            rows = o_r[c0 : min(rb, c0 + block)]
            x = Xr[rows, None]
            y = Yr[rows, None]
            z = Zr[rows, None] + d
            ok = (z >= z0) & (z < z1)
            zb = (np.clip(z, z0, z1 - 1) - z0) * sz
            x0 = np.clip(x - d, 0, nx) * sy
            x1 = np.clip(x + d + 1, 0, nx) * sy
            y0 = np.clip(y - d, 0, ny)
            y1 = np.clip(y + d + 1, 0, ny)
            box = Pf[zb + x1 + y1] - Pf[zb + x0 + y1] - Pf[zb + x1 + y0] + Pf[zb + x0 + y0]
            counts[rows] += np.where(ok, box, 0) @ wq
    return counts


def shadow_brute(
    vox: np.ndarray, shadow_max: float, q_max: int, receivers: np.ndarray | None = None, chunk: int = 512
) -> np.ndarray:
    """Reference O(n^2) evaluation of the pyramid sum (for tests; chunked over receivers)."""
    vox = np.asarray(vox, dtype=np.int64)
    n = vox.shape[0]
    rcv = np.arange(n) if receivers is None else np.flatnonzero(receivers)
    counts = np.full(n, np.nan)
    for a in range(0, rcv.size, chunk):
        rows = rcv[a : a + chunk]
        r = vox[rows]
        d = vox[None, :, :] - r[:, None, :]  # (m, n, 3): source - receiver
        dz = d[..., 2]
        dxy = np.maximum(np.abs(d[..., 0]), np.abs(d[..., 1]))
        ok = (dz >= 1) & (dz <= q_max - 1) & (dxy <= dz)
        w = np.where(ok, q_max - dz, 0).astype(np.float64)
        # integer-valued terms: any summation order gives the same float
        counts[rows] = w.sum(axis=1)
    return counts * (shadow_max / q_max)
