"""Topology derivation on a synthetic 100 000-cylinder tree (issue: core framework).

Prints the median of 5 runs of building a ``Tree`` (validation + extension choice + branches,
orders, positions) under each topology rule, and the branch table, against a baseline measured
in the same run: a plain Python forward pass in row order (the obvious non-vectorised way).

    .venv/bin/python benchmarks/topology.py
"""

from __future__ import annotations

import numpy as np
from _timing import median_time

from bforest_core import Tree
from bforest_core.tree import subtree_sum


def synthetic_tree_arrays(n=100_000, seed=0):
    """A random tree shaped like a QSM: long axes (parent mostly the previous row), forks."""
    rng = np.random.default_rng(seed)
    parent = np.empty(n, dtype=np.int64)
    parent[0] = -1
    jump = rng.random(n) < 0.12
    back = rng.integers(1, 400, n)
    idx = np.arange(n)
    parent[1:] = np.where(jump[1:], np.maximum(0, idx[1:] - back[1:]), idx[1:] - 1)
    axis = rng.normal(size=(n, 3))
    axis[:, 2] = np.abs(axis[:, 2]) + 1
    axis /= np.linalg.norm(axis, axis=1)[:, None]
    length = rng.uniform(0.02, 0.3, n)
    radius = rng.uniform(0.002, 0.2, n)
    start = np.zeros((n, 3))
    return start, axis, length, radius, parent


def python_forward_pass(parent, extension):
    n = parent.shape[0]
    branch = np.zeros(n, int)
    order = np.zeros(n, int)
    pos = np.zeros(n, int)
    nb = 1
    par = parent.tolist()
    ext = extension.tolist()
    for i in range(1, n):
        p = par[i]
        if ext[p] == i:
            branch[i], order[i], pos[i] = branch[p], order[p], pos[p] + 1
        else:
            branch[i], order[i], pos[i] = nb, order[p] + 1, 0
            nb += 1
    return branch, order, pos


def main():
    n = 100_000
    start, axis, length, radius, parent = synthetic_tree_arrays(n)
    print(f"synthetic tree: {n} cylinders")
    ref = Tree(start, axis, length, radius, parent, topology="subtree")
    for rule in ("thickest", "subtree"):
        t = median_time(lambda: Tree(start, axis, length, radius, parent, topology=rule))
        tr = Tree(start, axis, length, radius, parent, topology=rule)
        print(
            f"  Tree(..., topology={rule!r}): {t * 1000:7.1f} ms  ({tr.n_branches} branches, max order {tr.max_order})"
        )
    t = median_time(lambda: Tree(start, axis, length, radius, parent, ref.extension, topology="source"))
    print(f"  Tree(..., topology='source'):  {t * 1000:7.1f} ms")
    t = median_time(lambda: Tree(start, axis, length, radius, parent, ref.extension).branches)
    print(f"  + branch table:                {t * 1000:7.1f} ms")
    t = median_time(lambda: subtree_sum(parent, radius))
    print(f"  subtree volumes alone:         {t * 1000:7.1f} ms")
    tb = median_time(lambda: python_forward_pass(parent, ref.extension), repeats=3)
    b, o, p = python_forward_pass(parent, ref.extension)
    assert (b == ref.branch).all() and (o == ref.order).all() and (p == ref.position_in_branch).all()
    print(f"  baseline, Python forward pass (branches/orders/positions only): {tb * 1000:7.1f} ms (same result)")


if __name__ == "__main__":
    main()
