"""Projection directions of the sliced distance (docs/features-and-distance.md §4.1).

Quasi-random nets on ``[0, 1)^(d-1)`` mapped onto the unit sphere with the Fang-Wang
construction (*Number-theoretic methods in statistics*, pp. 167-170; toolbox
``dt_distance/lin_1d_transforms.m``). Results are cached by
``(net, d, lines, scramble, seed, parity)`` and returned as read-only arrays.
"""

from __future__ import annotations

import threading

import numpy as np

from .grid import DIRECTION_BITS, snap

NETS = ("gp2", "sobol", "halton", "random")

_cache: dict[tuple, np.ndarray] = {}
_lock = threading.Lock()


def gp2_net(lines: int, dim: int, d: int | None = None) -> np.ndarray:
    """The good-point net of the toolbox (``generate_NT_net.m`` method 2).

    ``c[k-1, i-1] = frac(k * 2**(i/d))`` for ``k = 1 ... lines``, ``i = 1 ... dim`` with
    ``d = dim + 1`` unless given.
    """
    d = dim + 1 if d is None else d
    k = np.arange(1, lines + 1, dtype=np.float64)[:, None]
    q = 2.0 ** (np.arange(1, dim + 1, dtype=np.float64) / d)[None, :]
    return np.mod(k * q, 1.0)


def net_points(net: str, lines: int, dim: int, *, scramble: bool = False, seed: int = 0) -> np.ndarray:
    """``(lines, dim)`` points of a net in ``[0, 1)^dim`` (origin skipped for Sobol/Halton)."""
    if net == "gp2":
        return gp2_net(lines, dim)
    from scipy.stats import qmc

    if net == "sobol":
        m = int(np.ceil(np.log2(lines + 1)))
        pts = qmc.Sobol(dim, scramble=scramble, seed=seed if scramble else None).random_base2(m)
        return pts[1 : lines + 1]
    if net == "halton":
        return qmc.Halton(dim, scramble=scramble, seed=seed if scramble else None).random(lines + 1)[1:]
    raise ValueError(f"unknown net {net!r} (choose from {', '.join(NETS)})")


def fang_wang(c: np.ndarray, d: int, parity: bool = False) -> np.ndarray:
    """Map net points ``c`` (L, d-1) in ``[0, 1)`` to unit vectors in R^d (d >= 3).

    ``parity=True`` reproduces the toolbox's indexing of the last pairs for odd d >= 7
    (column ``c_{2l}`` instead of ``c_{m+l}``).
    """
    c = np.asarray(c, dtype=np.float64)
    L = c.shape[0]
    col = lambda j: c[:, j - 1]  # 1-based column access, as in docs/features-and-distance.md §4.1
    a = np.empty((L, d))
    two_pi = 2.0 * np.pi
    if d % 2 == 0:
        m = d // 2
        g = np.ones((L, m + 1))  # g[:, j] for j = 1..m
        for j in range(m - 1, 0, -1):
            g[:, j] = g[:, j + 1] * col(j) ** (1.0 / j)
        delta = np.sqrt(np.maximum(np.diff(np.concatenate([np.zeros((L, 1)), g[:, 1:]], axis=1), axis=1), 0.0))
        for l in range(1, m + 1):
            ang = two_pi * col(m + l - 1)
            a[:, 2 * l - 2] = delta[:, l - 1] * np.cos(ang)
            a[:, 2 * l - 1] = delta[:, l - 1] * np.sin(ang)
    else:
        m = (d - 1) // 2
        g = np.ones((L, m + 1))
        for j in range(m - 1, 0, -1):
            g[:, j] = g[:, j + 1] * col(j) ** (2.0 / (2 * j + 1))
        delta = np.sqrt(np.maximum(np.diff(np.concatenate([np.zeros((L, 1)), g[:, 1:]], axis=1), axis=1), 0.0))
        cm = col(m)
        ang = two_pi * col(m + 1)
        rad = 2.0 * delta[:, 0] * np.sqrt(np.maximum(cm * (1.0 - cm), 0.0))
        a[:, 0] = delta[:, 0] * (1.0 - 2.0 * cm)
        a[:, 1] = rad * np.cos(ang)
        a[:, 2] = rad * np.sin(ang)
        for l in range(2, m + 1):
            ang = two_pi * (col(2 * l) if parity else col(m + l))
            a[:, 2 * l - 1] = delta[:, l - 1] * np.cos(ang)
            a[:, 2 * l] = delta[:, l - 1] * np.sin(ang)
    return a


def make_directions(
    d: int, lines: int, net: str = "gp2", *, scramble: bool = False, seed: int = 0, parity: bool = False
) -> np.ndarray:
    """Compute (uncached) the ``(lines, d)`` unit directions; see :func:`directions`."""
    if d < 1:
        raise ValueError(f"directions need a dimension >= 1, got d = {d}")
    if lines < 1:
        raise ValueError(f"lines must be >= 1, got {lines}")
    if net not in NETS:
        raise ValueError(f"unknown net {net!r} (choose from {', '.join(NETS)})")
    if d == 1:
        return np.ones((1, 1))
    if net == "random":
        g = np.random.default_rng(seed).standard_normal((lines, d))
        n = np.linalg.norm(g, axis=1, keepdims=True)
        return g / np.where(n > 0, n, 1.0)
    if d == 2:
        if net == "gp2":
            theta = 0.5 * np.pi * (2.0 * np.arange(1, lines + 1) - 1.0) / lines
        else:
            theta = np.pi * net_points(net, lines, 1, scramble=scramble, seed=seed)[:, 0]
        return np.column_stack([np.cos(theta), np.sin(theta)])
    a = fang_wang(net_points(net, lines, d - 1, scramble=scramble, seed=seed), d, parity=parity)
    # the construction is unit by algebra; renormalise away the last ulp
    return a / np.linalg.norm(a, axis=1, keepdims=True)


def directions(
    d: int, lines: int, net: str = "gp2", *, scramble: bool = False, seed: int = 0, parity: bool = False
) -> np.ndarray:
    """Cached, read-only ``(lines, d)`` unit directions (one line for d = 1), each component
    snapped to the distance's grid of ``2**-DIRECTION_BITS`` (:mod:`.grid`: the projections
    are then exact).

    Parameters
    ----------
    d : int
        Dimension of the table.
    lines : int
        Number of lines L.
    net : {"gp2", "sobol", "halton", "random"}
        ``gp2`` is the toolbox's good-point net; ``random`` uses Gaussian vectors from
        ``numpy.random.default_rng(seed)``.
    scramble, seed : optional
        Scrambling of Sobol/Halton nets (and the seed of ``random``).
    parity : bool
        Toolbox indexing of the Fang-Wang mapping for odd d >= 7.
    """
    seed_key = seed if (scramble or net == "random") else 0
    key = (net, int(d), int(lines), bool(scramble) and net in ("sobol", "halton"), seed_key, bool(parity))
    with _lock:
        a = _cache.get(key)
    if a is None:
        a = snap(make_directions(d, lines, net, scramble=scramble, seed=seed, parity=parity), DIRECTION_BITS)
        a = np.ascontiguousarray(a, dtype=np.float64)
        a.flags.writeable = False
        with _lock:
            a = _cache.setdefault(key, a)
    return a
