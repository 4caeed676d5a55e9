"""One-dimensional two-sample statistics on sorted arrays (docs/features-and-distance.md §4.2-§4.3).

All functions work on a block of lines at once: rows are lines, columns are points.
``F1`` is the data ECDF, ``F2`` the model ECDF, both right-continuous; the pooled sorted values
are the evaluation points and a tied run is evaluated after the whole run. Everything is exact
with ties.

Two engines:

* :func:`ks_sorted` -- KS from the sorted data ``X`` and the sorted model ``Y`` with
  ``np.searchsorted`` (the hot path of a fit: the data side is sorted once per run).
* :func:`stat_from_labels` -- any statistic from the pooled sorted values ``Z`` and a boolean
  "is model" label per pooled position (cumulative counts give both ECDFs). Used for the other
  statistics (after :func:`merge_sorted`) and by the permutation test, where the pooled values
  of a pair are sorted once and only the labels move.
"""

from __future__ import annotations

import sys
import threading

import numpy as np

_LOW_BYTE = 0 if sys.byteorder == "little" else 7  # byte holding the last mantissa bit

_tls = threading.local()


def _workspace(name: str, shape: tuple, dtype) -> np.ndarray:
    """A per-thread scratch array, reused across calls.

    Blocks of a few MB allocated and freed on every call are returned to the OS and come back
    as fresh pages; the page faults cost more than a third of the kernel's time.
    """
    ws = getattr(_tls, "ws", None)
    if ws is None:
        ws = _tls.ws = {}
    size = int(np.prod(shape))
    a = ws.get(name)
    if a is None or a.size < size or a.dtype != np.dtype(dtype):
        a = ws[name] = np.empty(size, dtype=dtype)
    return a[:size].reshape(shape)


STATISTICS = ("ks", "cvm", "ad", "w1", "energy", "l1", "l2")
ALIASES = {"wasserstein": "w1"}


def ks_sorted(X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """Exact two-sample KS statistic per row, ties included.

    Parameters
    ----------
    X : (B, n) array
        Data projections, each row sorted ascending.
    Y : (B, m) array
        Model projections, each row sorted ascending.

    Returns
    -------
    (B,) array
        ``max_t |F1(t) - F2(t)|`` per row.

    Notes
    -----
    With ``r_k = #{x <= y_k}`` and ``l_k = #{x < y_k}`` the supremum is the largest of
    ``|r_k/n - k/m|`` over the last ``k`` of every run of equal ``y`` and
    ``|l_k/n - (k-1)/m|`` over the first ``k`` of every run (docs/features-and-distance.md §6). ``l_k`` differs from
    ``r_k`` only where ``y_k`` equals some ``x``; it is searched only for rows with such a tie.
    """
    B, n = X.shape
    m = Y.shape[1]
    R = np.empty((B, m), dtype=np.int64)
    Lf = np.empty((B, m), dtype=np.int64)
    for i in range(B):
        x = X[i]
        y = Y[i]
        r = np.searchsorted(x, y, side="right")
        R[i] = r
        # ties across the samples: x[r-1] == y for some k
        if r[-1] > 0 and np.any(x[np.maximum(r - 1, 0)] == y):
            Lf[i] = np.searchsorted(x, y, side="left")
        else:
            Lf[i] = r
    # integer numerators: exact zeros, one rounding per value
    k = np.arange(1, m + 1, dtype=np.int64) * n
    inv = 1.0 / (n * m)
    t1 = np.abs(R * m - k) * inv
    t2 = np.abs(Lf * m - (k - n)) * inv
    neq = Y[:, 1:] != Y[:, :-1]
    if neq.all():  # no ties inside the model sample: every k is first and last of its run
        return np.maximum(t1.max(axis=1), t2.max(axis=1))
    last = np.ones((B, m), dtype=bool)
    last[:, :-1] = neq
    first = np.ones((B, m), dtype=bool)
    first[:, 1:] = neq
    return np.maximum(np.max(t1, axis=1, where=last, initial=0.0), np.max(t2, axis=1, where=first, initial=0.0))


def ks_encoded(
    Xs: np.ndarray, Y: np.ndarray | None = None, *, A: np.ndarray | None = None, UT: np.ndarray | None = None
) -> np.ndarray:
    """Exact KS per row from sorted data ``Xs`` and *unsorted* model projections.

    The fast path of a fit. The sample label is written into the last mantissa bit (data
    cleared, model set), the pooled block is sorted once with NumPy's vectorised sort, and a
    positions of the model labels give the extremes of the walk
    ``w_k = m c_x(k) - n c_y(k) = n m (F1 - F2)``. This costs one sort of the stacked block --
    the floor of any exact method -- plus a few linear passes, instead of a sort of the model
    side and ``m log n`` binary searches.

    Exactness: clearing/setting the last bit keeps the order of values that differ in more than
    the last bit, and ties within one sample do not change the supremum (between two points of
    one sample the other ECDF is constant, so ``|F1 - F2|`` is largest at an end of the run).
    A data value and a model value within one ulp of each other (true cross-sample ties
    included) end up adjacent with bit patterns differing only in the last bit; such rows are
    recomputed with the exact searchsorted kernel :func:`ks_sorted`.

    Parameters
    ----------
    Xs : (B, n) array
        Data projections, rows sorted, zeros normalised to +0.0 (add ``0.0``).
    Y : (B, m) array, optional
        Model projections in any order (not modified).
    A, UT : (B, d) and (d, m) arrays, optional
        Instead of ``Y``: directions and the transposed model table; the projections
        ``A @ UT`` are written straight into the work buffer.

    Returns
    -------
    (B,) array
    """
    B, n = Xs.shape
    m = Y.shape[1] if Y is not None else UT.shape[1]
    N = n + m
    buf = _workspace("pooled", (B, N), np.float64)
    bits = buf.view(np.int64)
    np.bitwise_and(Xs.view(np.int64), ~np.int64(1), out=bits[:, :n])
    yv = buf[:, n:]
    if Y is not None:
        np.add(Y, 0.0, out=yv)  # also turns -0.0 into +0.0: equal values, equal bits
    else:
        np.matmul(A, UT, out=yv)
        yv += 0.0
    yb = bits[:, n:]
    np.bitwise_or(yb, 1, out=yb)
    buf.sort(axis=1)
    # label = last bit = lowest byte's bit 0; positions of the model points per row
    lab = np.bitwise_and(buf.view(np.uint8)[:, _LOW_BYTE::8], 1, out=_workspace("label", (B, N), np.uint8))
    q = np.flatnonzero(lab.view(np.bool_)).reshape(B, m)  # bool: numpy's fast nonzero path
    q -= (np.arange(B, dtype=np.int64) * N)[:, None]
    # The walk w = n m (F1 - F2) rises by m at a data point and falls by n at a model point, so
    # its maximum is just before a model point (or 0) and its minimum just after one. After the
    # j-th model point (pooled 0-based position q_j) q_j - j + 1 data points have been seen.
    jm1 = np.arange(m, dtype=np.int64)
    q -= jm1
    q *= m
    q -= (jm1 + 1) * n  # w just after model point j
    D = np.maximum(np.maximum(q.max(axis=1) + n, 0), -q.min(axis=1)) * (1.0 / (n * m))
    x = np.bitwise_xor(bits[:, 1:], bits[:, :-1], out=_workspace("xor", (B, N - 1), np.int64))
    near = np.equal(x, 1, out=_workspace("near", (B, N - 1), np.bool_))
    if near.any():
        rows = np.flatnonzero(near.any(axis=1))
        Yr = Y[rows] if Y is not None else A[rows] @ UT
        D[rows] = ks_sorted(Xs[rows], np.sort(Yr, axis=1))
    return D


def merge_sorted(X: np.ndarray, Y: np.ndarray):
    """Merge row-sorted ``X`` (B, n) and ``Y`` (B, m) into ``Z`` (B, n+m) with model labels.

    Returns
    -------
    Z : (B, N) array
        Pooled sorted values per row.
    lab : (B, N) bool
        True where the pooled value comes from ``Y``.
    """
    B, n = X.shape
    m = Y.shape[1]
    N = n + m
    pos = np.empty((B, m), dtype=np.int64)
    ar = np.arange(m)
    for i in range(B):
        pos[i] = np.searchsorted(X[i], Y[i], side="left") + ar
    lab = np.zeros((B, N), dtype=bool)
    lab[np.arange(B)[:, None], pos] = True
    Z = np.empty((B, N))
    Z[lab] = Y.ravel()
    Z[~lab] = X.ravel()
    return Z, lab


def stat_from_labels(
    Z: np.ndarray, lab: np.ndarray, n: int, m: int, statistic: str, scaled: bool = False
) -> np.ndarray:
    """A two-sample statistic per row from pooled sorted values and model labels.

    Parameters
    ----------
    Z : (..., N) array
        Pooled values, sorted along the last axis (may broadcast against ``lab``).
    lab : (..., N) bool
        True for model points, False for data points; exactly ``m`` True per row.
    n, m : int
        Data and model sample sizes (both >= 1).
    statistic : {"ks", "cvm", "ad", "w1", "energy", "l1", "l2"}
    scaled : bool
        The sample-size-scaled value (``scale_by_sample_size``; §4.3 table).

    Returns
    -------
    array of shape ``lab.shape[:-1]``
    """
    N = n + m
    cy = np.cumsum(lab, axis=-1, dtype=np.int64)
    kk = np.arange(1, N + 1, dtype=np.int64)
    cx = kk - cy
    diff = (cx * m - cy * n) * (1.0 / (n * m))  # F1 - F2 at each position (exact at run ends)
    end = np.ones(Z.shape, dtype=bool)
    end[..., :-1] = Z[..., 1:] != Z[..., :-1]
    allends = bool(end.all())
    if statistic == "ks":
        D = np.abs(diff).max(axis=-1) if allends else np.max(np.abs(diff), axis=-1, where=end, initial=0.0)
        return np.sqrt(n * m / N) * D if scaled else D
    if statistic in ("w1", "energy"):
        gap = np.diff(Z, axis=-1)  # zero inside a tied run, so positions before a run end do not count
        if statistic == "w1":
            return np.sum(gap * np.abs(diff[..., :-1]), axis=-1)
        E = 2.0 * np.sum(gap * diff[..., :-1] ** 2, axis=-1)
        return (n * m / N) * E if scaled else E
    # the rest weigh every pooled position with the value after its tied run
    if allends:
        runlen = None
    else:
        start = np.ones(Z.shape, dtype=bool)
        start[..., 1:] = end[..., :-1]
        idx = np.arange(N)
        s = np.maximum.accumulate(np.where(start, idx, 0), axis=-1)
        runlen = np.where(end, idx - s + 1, 0)
        runlen = np.broadcast_to(runlen, diff.shape)
    if statistic in ("cvm", "l1", "l2"):
        f = np.abs(diff) if statistic == "l1" else diff * diff
        total = f.sum(axis=-1) if runlen is None else np.sum(f * runlen, axis=-1)
        if statistic == "cvm":
            W2 = total / N
            return (n * m / N) * W2 if scaled else W2
        return total
    if statistic == "ad":
        # Scholz & Stephens (1987) right-continuous A^2 over the distinct values z*_1..z*_{J-1}
        Bj = kk[:-1].astype(np.float64)
        den = Bj * (N - Bj)
        tx = (N * cx[..., :-1] - n * Bj) ** 2 / (n * den)
        ty = (N * cy[..., :-1] - m * Bj) ** 2 / (m * den)
        w = np.broadcast_to(end, diff.shape)[..., :-1] if runlen is None else runlen[..., :-1]
        A2 = np.sum(w * (tx + ty), axis=-1) / N
        return A2 if scaled else A2 * N / (n * m)
    raise ValueError(f"unknown statistic {statistic!r} (choose from {', '.join(STATISTICS)})")


def stat_sorted(X: np.ndarray, Y: np.ndarray, statistic: str, scaled: bool = False) -> np.ndarray:
    """Any statistic per row from row-sorted data ``X`` and model ``Y``."""
    n, m = X.shape[1], Y.shape[1]
    if statistic == "ks":
        D = ks_sorted(X, Y)
        return np.sqrt(n * m / (n + m)) * D if scaled else D
    Z, lab = merge_sorted(X, Y)
    return stat_from_labels(Z, lab, n, m, statistic, scaled)
