"""Receiver-only pyramid shadow of the simplified LIGNUM (spec ssm-models.md A.6).

Every segment midpoint sits in a voxel (X, Y, Z) = floor(p / V_S) of an unbounded lattice anchored
at the origin. A source voxel j shades a receiver voxel i with S_max (1 - dZ / q_max) when
dZ = Z_j - Z_i is in [1, q_max - 1] and max(|dX|, |dY|) <= dZ (a 45 degree pyramid with linear
fall-off, no self-shading; sources in one voxel add up).

The weights are accumulated as the integers (q_max - dZ) and scaled by S_max / q_max once, so
the fast kernel and the brute-force reference give bit-identical sums.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

__all__ = ["q_max_of", "voxel_coords", "shadow_fast", "shadow_brute"]


def q_max_of(shadow_len: float, voxel_size: float) -> int:
    """Number of voxel layers of the pyramid, q_max = ceil(round(S_L / V_S, 9))."""
    return int(math.ceil(round(shadow_len / voxel_size, 9)))


def voxel_coords(points: np.ndarray, voxel_size: float) -> np.ndarray:
    """Integer voxel coordinates floor(p / V_S) of ``(n, 3)`` points."""
    return np.floor(np.asarray(points, dtype=np.float64) / voxel_size).astype(np.int64)


def _finish(counts: np.ndarray, shadow_max: float, q_max: int) -> np.ndarray:
    return counts * (shadow_max / q_max)


def shadow_fast(vox: np.ndarray, shadow_max: float, q_max: int) -> np.ndarray:
    """Shadow S_i at every voxel point, by a kd-tree pair search (equal to :func:`shadow_brute`).

    Parameters
    ----------
    vox : (n, 3) int array
        Voxel coordinates of the points (sources and receivers are the same set).
    shadow_max : float
        S_max, the shadow one source casts one layer below (before the linear fall-off).
    q_max : int
        Pyramid depth in layers.

    Returns
    -------
    (n,) float64
        The summed shadow at every point.
    """
    vox = np.asarray(vox, dtype=np.int64)
    n = vox.shape[0]
    if n < 2 or q_max < 2:
        return np.zeros(n)
    # sort by Z: query_pairs returns i < j, so the source is always j and dZ = Z_j - Z_i >= 0
    o = np.argsort(vox[:, 2], kind="stable")
    vs = vox[o]
    lo = vs.min(axis=0)
    X, Y, Z = ((vs[:, k] - lo[k]).astype(np.int32) for k in range(3))
    tree = cKDTree(vs.astype(np.float64), leafsize=24, balanced_tree=False, compact_nodes=False)
    pairs = tree.query_pairs(r=float(q_max - 1), p=np.inf, output_type="ndarray")
    if pairs.shape[0] == 0:
        return np.zeros(n)
    i = np.ascontiguousarray(pairs[:, 0])
    j = np.ascontiguousarray(pairs[:, 1])
    dz = Z[j] - Z[i]  # <= q_max - 1 by the search radius
    keep = (np.abs(X[j] - X[i]) <= dz) & (np.abs(Y[j] - Y[i]) <= dz) & (dz > 0)
    w = np.where(keep, q_max - dz, 0).astype(np.float64)
    counts = np.empty(n)
    counts[o] = np.bincount(i, weights=w, minlength=n)
    return _finish(counts, shadow_max, q_max)


def shadow_brute(vox: np.ndarray, shadow_max: float, q_max: int, chunk: int = 512) -> np.ndarray:
    """Reference O(n^2) evaluation of the pyramid sum (for tests; chunked over receivers)."""
    vox = np.asarray(vox, dtype=np.int64)
    n = vox.shape[0]
    counts = np.zeros(n)
    for a in range(0, n, chunk):
        r = vox[a:a + chunk]
        d = vox[None, :, :] - r[:, None, :]          # (m, n, 3): source - receiver
        dz = d[..., 2]
        dxy = np.maximum(np.abs(d[..., 0]), np.abs(d[..., 1]))
        ok = (dz >= 1) & (dz <= q_max - 1) & (dxy <= dz)
        w = np.where(ok, q_max - dz, 0).astype(np.float64)
        # integer-valued terms: any summation order gives the same float
        counts[a:a + chunk] = w.sum(axis=1)
    return _finish(counts, shadow_max, q_max)
