"""Small inputs the checks run on: a sample tree with known branches, sample tables."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ..tree import Tree


def _branches(parent_rows, starts, dirs, ncyl, clen, rad, offset):
    """Rows of straight branches (vectorised): branch b has ``ncyl[b]`` cylinders of ``clen[b]``."""
    ncyl = np.asarray(ncyl, np.int64)
    bi = np.repeat(np.arange(ncyl.size), ncyl)
    pos = np.arange(bi.size) - np.repeat(np.cumsum(ncyl) - ncyl, ncyl)
    rows = offset + np.arange(bi.size)
    start = starts[bi] + (pos * clen[bi])[:, None] * dirs[bi]
    parent = np.where(pos == 0, parent_rows[bi], rows - 1)
    ext = np.where(pos < ncyl[bi] - 1, rows + 1, -1)
    radius = rad[bi] * (1.0 - 0.4 * pos / ncyl[bi])
    return start, dirs[bi], np.asarray(clen)[bi], radius, parent, ext


def _directions(rng, up, beta_deg, n):
    """Unit vectors at ``beta`` degrees from the rows of ``up``, random azimuth."""
    ref = np.where(np.abs(up[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
    u = np.cross(up, ref)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    w = np.cross(up, u)
    b = np.radians(beta_deg)[:, None]
    az = rng.uniform(0, 2 * np.pi, n)[:, None]
    d = np.cos(b) * up + np.sin(b) * (np.cos(az) * u + np.sin(az) * w)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def sample_tree(seed: int = 0, trunk: int = 16, laterals: int = 2) -> Tree:
    """A small synthetic tree (orders 0-2, a few hundred cylinders) to feed feature sets and
    writers; deterministic in ``seed``.

    Parameters
    ----------
    seed : int
        Seeds the branching angles, lengths and which sub-laterals exist.
    trunk : int
        Trunk cylinders (0.5 m each).
    laterals : int
        First-order branches per trunk node (from the third node up).

    Returns
    -------
    Tree
        With ``source`` topology and metadata ``{"model": "conformance-sample", "seed": seed}``.
    """
    rng = np.random.default_rng(seed)
    parts = [
        _branches(
            np.array([-1]), np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]), [trunk], np.array([0.5]), np.array([0.15]), 0
        )
    ]
    n = trunk
    # first order: `laterals` branches on trunk cylinders 2..trunk-1 (at their start)
    host = np.repeat(np.arange(2, trunk), laterals)
    k = host.size
    up = np.tile([0.0, 0.0, 1.0], (k, 1))
    d1 = _directions(rng, up, rng.uniform(40, 75, k), k)
    nc1 = rng.integers(3, 6, k)
    parts.append(_branches(host, parts[0][0][host], d1, nc1, rng.uniform(0.25, 0.45, k), np.full(k, 0.04), n))
    s1, a1, l1 = parts[1][0], parts[1][1], parts[1][2]
    rows1 = n + np.arange(s1.shape[0])
    n += s1.shape[0]
    # second order: on 70 % of the first-order cylinders, at their end
    sel = rows1[rng.random(rows1.size) < 0.7]
    loc = sel - rows1[0]
    m = sel.size
    d2 = _directions(rng, a1[loc], rng.uniform(30, 70, m), m)
    parts.append(
        _branches(
            sel,
            s1[loc] + l1[loc, None] * a1[loc],
            d2,
            rng.integers(1, 4, m),
            rng.uniform(0.1, 0.25, m),
            np.full(m, 0.012),
            n,
        )
    )
    start, axis, length, radius, parent, ext = (np.concatenate(c) for c in zip(*parts))
    return Tree(start, axis, length, radius, parent, ext, metadata={"model": "conformance-sample", "seed": seed})


def sample_trees(n: int = 2) -> list[Tree]:
    """``n`` sample trees (seeds 0..n-1) of :func:`sample_tree`."""
    return [sample_tree(s) for s in range(n)]


def sample_tables(dims: Sequence[int] = (2, 4), seed: int = 0, shift: float = 1.0):
    """Data and model tables to feed a distance: ``(U_data, U_model, columns)``.

    Set ``"T{d}"`` has ``d`` columns; the data side is standard normal (200 rows), the model
    side (150 rows) is shifted by ``shift`` in every column.
    """
    rng = np.random.default_rng(seed)
    U_data, U_model, cols = {}, {}, {}
    for d in dims:
        U_data[f"T{d}"] = rng.standard_normal((200, d))
        U_model[f"T{d}"] = rng.standard_normal((150, d)) + shift
        cols[f"T{d}"] = [f"c{i}" for i in range(d)]
    return U_data, U_model, cols
