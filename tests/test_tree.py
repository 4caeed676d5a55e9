import pickle

import numpy as np
import pytest

from bforest_core import Tree, TreeError
from bforest_core.tree import children_csr, subtree_sum
from conftest import hand_tree


def test_hand_tree_branches():
    t = hand_tree()
    assert t.n == 7 and t.n_branches == 4
    assert t.branch.tolist() == [0, 0, 0, 1, 1, 2, 3]
    assert t.order.tolist() == [0, 0, 0, 1, 1, 1, 1]
    assert t.position_in_branch.tolist() == [0, 1, 2, 0, 1, 0, 0]
    bt = t.branches
    assert bt.first.tolist() == [0, 3, 5, 6]
    assert bt.parent_cyl.tolist() == [-1, 0, 1, 2]
    assert bt.parent_branch.tolist() == [-1, 0, 0, 0]
    assert bt.n_cyl.tolist() == [3, 2, 1, 1]
    assert bt.cylinders[bt.ptr[1] : bt.ptr[2]].tolist() == [3, 4]
    np.testing.assert_allclose(t.end[2], [0, 0, 3])


def test_thickest_rule_continues_lateral_when_no_extension():
    # docs/features-and-distance.md §7: under thickest the third lateral continues the trunk (its parent has no extension)
    t = hand_tree("thickest")
    assert t.n_branches == 3
    assert t.branch[6] == 0 and t.order[6] == 0


def _fork(r_ext, r_lat, with_ext=True):
    start = [[0, 0, 0], [0, 0, 1], [0, 0, 1]]
    axis = [[0, 0, 1], [0, 0, 1], [1, 0, 0]]
    return Tree(
        start,
        axis,
        [1, 1, 1],
        [0.1, r_ext, r_lat],
        [-1, 0, 0],
        [1, -1, -1] if with_ext else [-1, -1, -1],
        topology="thickest",
    )


def test_thickest_ties_and_takeover():
    assert _fork(0.05, 0.06).extension[0] == 2  # thicker lateral continues
    assert _fork(0.05, 0.05).extension[0] == 1  # tie -> old extension
    assert _fork(0.05, 0.05, with_ext=False).extension[0] == 1  # no extension, tie -> lower row


def test_subtree_rule_follows_volume_not_radius():
    # the continuation is thinner but carries a long subtree; a fat short twig must not win
    start = [[0, 0, 0], [0, 0, 1], [0, 0, 1], [0, 0, 2]]
    axis = [[0, 0, 1], [0, 0, 1], [1, 0, 0], [0, 0, 1]]
    t = Tree(start, axis, [1, 1, 0.3, 5], [0.1, 0.05, 0.06, 0.05], [-1, 0, 0, 1], [-1, -1, -1, -1], topology="subtree")
    assert t.extension[0] == 1 and t.extension[1] == 3
    assert t.with_topology("thickest").extension[0] == 2


def test_pruned_removes_thin_cylinders_and_everything_beyond_them():
    t = hand_tree()  # radii: trunk 0.20, 0.15, 0.10; lateral A 0.05, 0.04; B 0.04; C 0.03
    p = t.pruned(0.045)  # lateral A's tip and laterals B and C go
    assert p.n == 4 and p.radius.tolist() == [0.20, 0.15, 0.10, 0.05]
    assert p.parent.tolist() == [-1, 0, 1, 0] and p.extension.tolist() == [1, 2, -1, -1]
    assert p.source_row.tolist() == [0, 1, 2, 3]
    assert t.pruned(0.12).n == 2  # the trunk's top cylinder goes, and lateral C beyond it
    assert t.pruned(1.0).n == 1  # the root stays, however thin
    assert t.pruned(0.0) is t and t.pruned(0.03) is t  # nothing thinner: the tree itself
    # a thick cylinder beyond a thin one goes with it (the cut removes everything beyond)
    r = t.radius.copy()
    r[4] = 0.06
    thick_tip = Tree(t.start, t.axis, t.length, r, t.parent, t.extension)
    assert thick_tip.pruned(0.055).radius.tolist() == [0.20, 0.15, 0.10]


def test_subtree_sum_and_children():
    parent = np.array([-1, 0, 0, 1, 1, 3])
    np.testing.assert_allclose(subtree_sum(parent, np.ones(6)), [6, 4, 1, 2, 1, 1])
    ptr, idx = children_csr(parent)
    assert idx[ptr[1] : ptr[2]].tolist() == [3, 4] and ptr[-1] == 5


def test_unsorted_rows_are_resorted_and_keep_source_row():
    # child listed before its parent
    t = Tree([[0, 0, 1], [0, 0, 0]], [[0, 0, 1]] * 2, [1, 1], [0.1, 0.2], [1, -1], [-1, 0])
    assert t.parent.tolist() == [-1, 0] and t.source_row.tolist() == [1, 0]
    assert t.extension.tolist() == [1, -1] and t.radius[0] == 0.2


@pytest.mark.parametrize(
    "kw, msg",
    [
        (dict(length=[1, 0]), "length <= 0 at rows 1"),
        (dict(radius=[0.1, -0.1]), "radius <= 0 at rows 1"),
        (dict(radius=[0.1, np.nan]), "non-finite values in 'radius' at rows 1"),
        (dict(start=[[0, 0, 0], [0, np.inf, 1]]), "non-finite values in 'start' at rows 1"),
        (dict(axis=[[0, 0, 1], [0, 0, 0]]), "axis has zero length at rows 1"),
        (dict(axis=[[0, 0, 1], [0, 0, 2]]), "axis is not a unit vector at rows 1"),
        (dict(parent=[-1, 5]), "parent out of range at rows 1"),
        (dict(parent=[-1, -1]), "2 cylinders have no parent"),
        (dict(parent=[1, 0]), "no root"),
        (dict(parent=[-1, 1]), "cylinder 1 is its own parent"),
        (dict(extension=[1, 0]), "extension of row 1 is row 0"),
        (dict(radius=[0.1, 0.1, 0.1]), "'radius' has shape (3,)"),
        (dict(length=[]), "no cylinders"),
    ],
)
def test_validation_messages(kw, msg):
    base = dict(
        start=[[0, 0, 0], [0, 0, 1]],
        axis=[[0, 0, 1], [0, 0, 1]],
        length=[1, 1],
        radius=[0.2, 0.1],
        parent=[-1, 0],
        extension=[1, -1],
    )
    base.update(kw)
    with pytest.raises(TreeError, match=msg.replace("(", r"\(").replace(")", r"\)")):
        Tree(**base)


def test_cycle_is_reported():
    with pytest.raises(TreeError, match="form a cycle"):
        Tree(np.zeros((4, 3)), [[0, 0, 1]] * 4, np.ones(4), np.ones(4), [-1, 3, 1, 2])


def test_small_axis_deviation_is_renormalised():
    t = Tree([[0, 0, 0]], [[0, 0, 1 + 5e-7]], [1], [0.1], [-1])
    assert np.linalg.norm(t.axis[0]) == pytest.approx(1, abs=1e-15)


def test_pickle_roundtrip_and_readonly():
    t = hand_tree()
    t2 = pickle.loads(pickle.dumps(t))
    assert t2.equals(t) and t2.n_branches == t.n_branches
    with pytest.raises(ValueError):
        t.radius[0] = 1.0


def test_large_random_tree_orders_consistent():
    rng = np.random.default_rng(3)
    n = 5000
    parent = np.concatenate([[-1], rng.integers(np.maximum(0, np.arange(1, n) - 20), np.arange(1, n))])
    t = Tree(
        np.zeros((n, 3)), np.tile([0, 0, 1.0], (n, 1)), np.ones(n), rng.random(n) + 0.01, parent, topology="subtree"
    )
    # brute-force check of the derivation rules in row order
    branch = np.zeros(n, int)
    order = np.zeros(n, int)
    pos = np.zeros(n, int)
    nb = 1
    for i in range(1, n):
        p = parent[i]
        if t.extension[p] == i:
            branch[i], order[i], pos[i] = branch[p], order[p], pos[p] + 1
        else:
            branch[i], order[i], pos[i] = nb, order[p] + 1, 0
            nb += 1
    assert t.branch.tolist() == branch.tolist()
    assert t.order.tolist() == order.tolist()
    assert t.position_in_branch.tolist() == pos.tolist()
    vol = subtree_sum(parent, np.pi * t.radius**2 * t.length)
    for p in range(n):
        ch = np.flatnonzero(parent == p)
        if ch.size:
            assert vol[t.extension[p]] == vol[ch].max()


def test_rebuilding_keeps_axes_bit_identical_and_source_topology():
    rng = np.random.default_rng(1)
    t = hand_tree()
    ax = rng.normal(size=(7, 3))
    ax /= np.linalg.norm(ax, axis=1)[:, None]
    t = Tree(t.start, ax, t.length, t.radius, t.parent, t.extension)
    for rule in ("thickest", "subtree", "source"):
        t2 = t.with_topology(rule)
        assert np.array_equal(t2.axis, t.axis)
    assert t.with_topology("thickest").with_topology("source").equals(t)


def test_resort_renumbers_source_extension():
    # rows out of order (child before parent), built under thickest with the file's own branching kept
    ext = np.array([-1, 0, -1])
    t = Tree(
        [[0, 0, 1], [0, 0, 0], [0, 0, 1]],
        [[0, 0, 1], [0, 0, 1], [1, 0, 0]],
        [1, 1, 1],
        [0.05, 0.2, 0.06],
        [1, -1, 1],
        ext,
        topology="thickest",
        extras={"_source_extension": ext},
    )
    assert t.parent.tolist() == [-1, 0, 0] and t.extension[0] == 2  # thicker lateral continues
    assert t.with_topology("source").extension.tolist() == [1, -1, -1]
