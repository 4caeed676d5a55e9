"""Compiled loops of SOT's growth cycle, each the same arithmetic as the numpy it replaced.

The frames of the growing shoots (B.5 step 7, ii-iii). A growth cycle builds its shoots metamer
by metamer; at each step every active shoot turns its frame (heading ``h``, up vector ``u``)
partly towards its target, bends by its clone noise and rolls by the phyllotaxis angle. Written as
numpy over the active shoots, each step cost some thirty array calls on a few dozen rows, most of
the time of a pine-sized tree. These two loops do the same arithmetic, operation for operation and
in the same order as :func:`bforest_sot.model.rotate` and its helpers, so the trees are the same
to the bit (tests/test_sot.py compares each loop with that numpy, and the recorded trees stay).
The one function whose bits numpy and the C library do not share here, ``arctan2`` (numpy's is a
SIMD one), stays in numpy between the two loops; numpy's float64 ``cos`` and ``sin`` are the C
library's, which the loops call, and ``sqrt`` is exact in both.

The basipetal sums (B.5 step 3): the level-by-level pass of :func:`bforest_sot.model.accumulate`
was a numpy loop over the tree's depth levels, a hundred and more of a few rows each.

The shadows (:meth:`bforest_sot.light.LightField.cast`): a ``bincount`` over the range of voxels
between the first and last touched one (most of the grid for a tree-wide batch) became a sum
into the touched voxels only, in the same order.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(inline="always")
def _dot(a0, a1, a2, b0, b1, b2):  # pragma: no cover - compiled
    """``np.einsum("ij,ij->i")`` of one row of three: numpy adds the first and last products
    first (its SIMD order), which is not the order of a plain loop."""
    return (a0 * b0 + a2 * b2) + a1 * b1


@numba.njit(inline="always")
def _cross(a0, a1, a2, b0, b1, b2):  # pragma: no cover - compiled
    """:func:`bforest_sot.model.cross` of one row."""
    return a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0


@numba.njit(inline="always")
def _norm(v0, v1, v2):  # pragma: no cover - compiled
    """:func:`bforest_sot.model._norm` of one row."""
    return np.sqrt(v0 * v0 + v1 * v1 + v2 * v2)


@numba.njit(cache=True, nogil=True)
def turn_geometry(h, target, act):  # pragma: no cover - compiled
    """For the shoots ``act``: the axis ``h x target`` (rows), its norm and ``h . target``."""
    m = act.size
    ax = np.empty((m, 3))
    sn = np.empty(m)
    cs = np.empty(m)
    for i in range(m):
        g = act[i]
        a0, a1, a2 = h[g, 0], h[g, 1], h[g, 2]
        b0, b1, b2 = target[g, 0], target[g, 1], target[g, 2]
        x0, x1, x2 = _cross(a0, a1, a2, b0, b1, b2)
        ax[i, 0], ax[i, 1], ax[i, 2] = x0, x1, x2
        sn[i] = _norm(x0, x1, x2)
        cs[i] = _dot(a0, a1, a2, b0, b1, b2)
    return ax, sn, cs


@numba.njit(inline="always")
def _rotate(v0, v1, v2, k0, k1, k2, theta):  # pragma: no cover - compiled
    c = np.cos(theta)
    s = np.sin(theta)
    kdv = _dot(k0, k1, k2, v0, v1, v2)
    r = kdv * (1.0 - c)
    c0, c1, c2 = _cross(k0, k1, k2, v0, v1, v2)
    return v0 * c + c0 * s + k0 * r, v1 * c + c1 * s + k1 * r, v2 * c + c2 * s + k2 * r


@numba.njit(inline="always")
def _unit(v0, v1, v2):  # pragma: no cover - compiled
    n = _norm(v0, v1, v2)
    return v0 / n, v1 / n, v2 / n


@numba.njit(cache=True, nogil=True)
def advance_frames(h, u, act, ax, sn, th, bend, phi):  # pragma: no cover - compiled
    """Turn, bend and roll the frames of the shoots ``act`` in place (rows of ``h``, ``u``).

    ``ax``, ``sn`` from :func:`turn_geometry`; ``th`` the turn angle of each shoot whose axis
    is not degenerate (``sn > 1e-12``; its other entries are not read), ``bend`` the clone
    noise's bend about ``u`` (an empty array: no bend), ``phi`` the phyllotaxis roll about ``h``.
    """
    bent = bend.size > 0
    for i in range(act.size):
        g = act[i]
        h0, h1, h2 = h[g, 0], h[g, 1], h[g, 2]
        u0, u1, u2 = u[g, 0], u[g, 1], u[g, 2]
        if sn[i] > 1e-12:  # h parallel or antiparallel to the target: no turn
            k0, k1, k2 = ax[i, 0] / sn[i], ax[i, 1] / sn[i], ax[i, 2] / sn[i]
            h0, h1, h2 = _rotate(h0, h1, h2, k0, k1, k2, th[i])
            u0, u1, u2 = _rotate(u0, u1, u2, k0, k1, k2, th[i])
        h0, h1, h2 = _unit(h0, h1, h2)
        if bent:  # u is the axis: it stays perpendicular to h
            h0, h1, h2 = _rotate(h0, h1, h2, u0, u1, u2, bend[i])
            h0, h1, h2 = _unit(h0, h1, h2)
        u0, u1, u2 = _rotate(u0, u1, u2, h0, h1, h2, phi[i])
        d = _dot(u0, u1, u2, h0, h1, h2)
        u0, u1, u2 = _unit(u0 - d * h0, u1 - d * h1, u2 - d * h2)
        h[g, 0], h[g, 1], h[g, 2] = h0, h1, h2
        u[g, 0], u[g, 1], u[g, 2] = u0, u1, u2


@numba.njit(cache=True, nogil=True)
def sum_levels(base, ac, lc, order, bounds, d0n):  # pragma: no cover - compiled
    """The basipetal sums of :func:`bforest_sot.model.accumulate`: per node, deepest level
    first, its own row of ``base`` plus the sums of its apical and lateral children (``ac``,
    ``lc``: the row ``m``, all zeros, where the slot holds no child); a width sum (column 2)
    that is not positive becomes ``d0n``. ``order``/``bounds`` are the levels of
    :func:`bforest_core.tree.group_by_level`. Returns the sums, with the zero row ``m``."""
    V = np.zeros(base.shape)
    for j in range(bounds.shape[0] - 2, -1, -1):
        for t in range(bounds[j], bounds[j + 1]):
            n = order[t]
            a, b = ac[n], lc[n]
            for c in range(3):
                V[n, c] = base[n, c] + V[a, c] + V[b, c]
            if V[n, 2] <= 0.0:
                V[n, 2] = d0n
    return V


@numba.njit(cache=True, nogil=True)
def add_shadows(log, acc, base, cnt, off, wf):  # pragma: no cover - compiled
    """``log[b + off[j]] += sum over shadows`` of ``cnt[i] * wf[j]`` for the voxels ``base``
    (unique, with their counts ``cnt``): each touched voxel's sum is formed first, in the order
    of ``np.bincount`` over the flat (voxel, offset) list, and then added, as
    ``log[lo:hi] += np.bincount(...)`` did. ``acc`` is a scratch array of ``log``'s size, all
    zeros, and left so."""
    for i in range(base.size):
        c = float(cnt[i])
        for j in range(off.size):
            acc[base[i] + off[j]] += c * wf[j]
    for i in range(base.size):
        for j in range(off.size):
            f = base[i] + off[j]
            log[f] += acc[f]  # once per voxel: a second visit adds the 0 left behind
            acc[f] = 0.0
