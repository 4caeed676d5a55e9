"""B^w / S^w feature tables (docs/features-and-distance.md §2, §7): hand-built trees with known
answers, invariances, set parsing and preparation, and real-data regressions."""

import warnings

import numpy as np
import pytest

import bforest_core as bf
from bforest_core import ConfigError, Tree
from bforest_core.tree import remap_ids
from bforest_features.branch_segment import (
    BranchSegmentFeatures,
    _segment_angles,
    azimuth_frame,
    branch_table,
    parse_set,
    segment_table,
)
from conftest import hand_tree, read_sample

S60, C60 = np.sin(np.radians(60)), np.cos(np.radians(60))


def feats(**kw):
    kw.setdefault("topology", "source")
    kw.setdefault("angles", "linear")
    kw.setdefault("min_rows", 0)
    return bf.component("features", "branch-segment", **kw)


def random_tree(n, seed=0, topology="source"):
    """A random tree (parent before child) with random geometry; extension = first child."""
    rng = np.random.default_rng(seed)
    parent = np.empty(n, dtype=np.int64)
    parent[0] = -1
    back = rng.integers(1, 4, size=n)  # mostly chains, some forks
    parent[1:] = np.maximum(np.arange(1, n) - back[1:], 0)
    axis = rng.normal(size=(n, 3))
    axis[:, 2] = np.abs(axis[:, 2]) + 0.2
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    length = rng.uniform(0.05, 0.5, n)
    radius = rng.uniform(0.005, 0.1, n)
    start = rng.normal(size=(n, 3))
    ext = np.full(n, -1)
    # first child of each parent continues its branch
    rows = np.arange(1, n)
    first = np.ones(n - 1, dtype=bool)
    first[1:] = parent[2:] != parent[1:-1]
    ext[parent[1:][first]] = rows[first]
    return Tree(start, axis, length, radius, parent, ext, topology=topology)


def transformed(tree, R=np.eye(3), shift=(0, 0, 0), k=1.0):
    return Tree(
        k * tree.start @ R.T + np.asarray(shift),
        tree.axis @ R.T,
        k * tree.length,
        k * tree.radius,
        tree.parent,
        tree.extension,
        topology="source",
    )


def rotz(psi_deg):
    c, s = np.cos(np.radians(psi_deg)), np.sin(np.radians(psi_deg))
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


# ------------------------------------------------------------------------------ hand-built tree


def test_hand_tree_branch_table_known_values():
    U = feats(sets=["B1"]).extract(hand_tree())
    expected = [[60, -90, 1.3, 0.05, 1.0], [90, 0, 0.6, 0.04, 1.5], [90, 90, 0.6, 0.03, 2.25]]
    np.testing.assert_allclose(U["B1"], expected, atol=1e-12)


def test_hand_tree_segment_tables_known_values():
    U = feats(sets=["S0", "S1", "S0,1"]).extract(hand_tree())
    np.testing.assert_allclose(U["S0"], [[0.20, 0, 0, 0], [0.15, 1, 0, 0], [0.10, 2, 0, 0]], atol=1e-12)
    np.testing.assert_allclose(
        U["S1"], [[0.05, 0, 0, 0], [0.04, 0.8, 0, 0], [0.04, 0, 0, 0], [0.03, 0, 0, 0]], atol=1e-12
    )
    # pooled: rows ordered by branch id then position
    np.testing.assert_allclose(U["S0,1"], np.vstack([U["S0"], U["S1"]]), atol=0)


def test_turned_segment_row():
    t = hand_tree()
    c20, s20 = np.cos(np.radians(20)), np.sin(np.radians(20))
    axis = np.array(t.axis)
    axis[4] = [S60 * c20, S60 * s20, C60]
    start = np.array(t.start)
    t2 = Tree(start, axis, t.length, t.radius, t.parent, t.extension)
    row = feats(sets=["S1"]).extract(t2)["S1"][1]
    zeta = np.degrees(np.arctan2(S60 * C60 * (1 - c20), S60**2 * c20 + C60**2))
    np.testing.assert_allclose(row, [0.04, 0.8, 20, zeta], atol=1e-12)
    assert abs(zeta - 1.5667) < 5e-5


def test_thickest_rule_on_hand_tree_gives_two_laterals():
    fs = feats(sets=["B1", "S0"], topology="thickest")
    U = fs.extract(hand_tree())  # the tree is built with 'source'; the set applies 'thickest'
    np.testing.assert_allclose(U["B1"], [[60, -90, 1.3, 0.05, 1.0], [90, 0, 0.6, 0.04, 1.5]], atol=1e-12)
    # the third lateral continues the trunk: a horizontal segment after a vertical one
    np.testing.assert_allclose(
        U["S0"][:, :2], [[0.2, 0], [0.15, 1], [0.1, 2], [0.03, 3.0]], atol=1e-12
    )  # L sums lengths
    # vertical p, t along -X: gamma = 0 and zeta = -(angle between them) = -90
    np.testing.assert_allclose(U["S0"][3, 2:], [0, -90], atol=1e-12)


def test_branch_alpha_on_plus_x_parent():
    # parent +X, child (0, cos 30, sin 30) -> alpha = 30, beta = 90
    start = [[0, 0, 0], [0.5, 0, 0]]
    axis = [[1, 0, 0], [0, np.cos(np.radians(30)), np.sin(np.radians(30))]]
    t = Tree(start, axis, [1, 1], [0.1, 0.05], [-1, 0], [-1, -1])
    _, B = branch_table(t)
    np.testing.assert_allclose(B[0], [90, 30, 1, 0.05, 0.5], atol=1e-12)


def test_la_clip_and_parity():
    # child starting beyond the parent's end: clipped to l_p (docs/features-and-distance.md §2.1), unclipped in parity mode
    start = [[0, 0, 0], [0, 0, 1.2]]
    t = Tree(start, [[0, 0, 1], [1, 0, 0]], [1, 1], [0.1, 0.05], [-1, 0], [-1, -1])
    assert feats(sets=["B1"]).extract(t)["B1"][0, 4] == pytest.approx(1.0, abs=1e-12)
    assert feats(sets=["B1"], clip_la=False).extract(t)["B1"][0, 4] == pytest.approx(1.2, abs=1e-12)


@pytest.mark.parametrize("e,phi", [(0, 0), (30, 45), (-20, 100), (60, -150), (10, 179), (45, -90)])
def test_segment_angles_after_plus_x(e, phi):
    er, pr = np.radians(e), np.radians(phi)
    t = np.array([[np.cos(er) * np.cos(pr), np.cos(er) * np.sin(pr), np.sin(er)]])
    g, z = _segment_angles(np.array([[1.0, 0, 0]]), t)
    assert g[0] == pytest.approx(phi, abs=1e-12)
    assert z[0] == pytest.approx(np.degrees(np.arctan2(np.sin(er), np.cos(er) * np.cos(pr))), abs=1e-12)


@pytest.mark.parametrize("side", [0, 45, 90, 200, -170])
def test_vertical_parent_tilted_child(side):
    s = np.radians(side)
    t = np.array([[np.sin(np.radians(30)) * np.cos(s), np.sin(np.radians(30)) * np.sin(s), np.cos(np.radians(30))]])
    g, z = _segment_angles(np.array([[0, 0, 1.0]]), t)
    assert g[0] == pytest.approx(0, abs=1e-12)
    assert z[0] == pytest.approx(-30, abs=1e-12)


def test_vertical_to_vertical_is_zero_and_finite():
    g, z = _segment_angles(np.array([[0, 0, 1.0], [0, 0, 1.0]]), np.array([[0, 0, 1.0], [0, 0, -1.0]]))
    assert np.all(np.isfinite(g)) and np.all(np.isfinite(z))
    np.testing.assert_allclose(g, [0, 0], atol=0)
    assert z[0] == 0 and abs(z[1]) == pytest.approx(180)


def test_azimuth_frame_equals_rodrigues_and_is_orthonormal():
    rng = np.random.default_rng(3)
    p = rng.normal(size=(200, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    v, w = azimuth_frame(p)
    X = np.array([1.0, 0, 0])
    for i in range(p.shape[0]):
        k = np.cross(X, p[i])
        s = np.linalg.norm(k)
        k /= s
        c = X @ p[i]
        K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        R = np.eye(3) + s * K + (1 - c) * K @ K
        np.testing.assert_allclose(R @ X, p[i], atol=1e-12)
        np.testing.assert_allclose(v[i], R @ [0, 1, 0], atol=1e-12)
        np.testing.assert_allclose(w[i], R @ [0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(np.einsum("ij,ij->i", v, w), 0, atol=1e-12)
    np.testing.assert_allclose(np.einsum("ij,ij->i", v, p), 0, atol=1e-12)
    np.testing.assert_allclose(np.einsum("ij,ij->i", w, p), 0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(v, axis=1), 1, atol=1e-12)
    # vertical parent: v = +Y, w = -X; parent along -X: the fixed fallback
    v, w = azimuth_frame(np.array([[0, 0, 1.0], [-1.0, 0, 0]]))
    np.testing.assert_allclose(v, [[0, 1, 0], [0, -1, 0]], atol=1e-15)
    np.testing.assert_allclose(w, [[-1, 0, 0], [0, 0, 1]], atol=1e-15)


# ------------------------------------------------------------------------------ invariances


def test_translation_changes_nothing():
    t = random_tree(400, seed=1)
    fs = feats(sets=["S0,1,2,3+", "B1+"])
    fs.prepare(t)
    a = fs.extract(t)
    b = fs.extract(transformed(t, shift=(12.5, -3, 7)))
    for k in a:
        np.testing.assert_allclose(a[k], b[k], atol=1e-9)


def test_rotation_about_vertical_on_hand_tree_shifts_alpha():
    fs = feats(sets=["B1", "S0,1"])
    a = fs.extract(hand_tree())
    b = fs.extract(transformed(hand_tree(), R=rotz(40)))
    np.testing.assert_allclose(b["B1"][:, 1], [-50, 40, 130], atol=1e-9)
    np.testing.assert_allclose(np.delete(b["B1"], 1, axis=1), np.delete(a["B1"], 1, axis=1), atol=1e-9)
    np.testing.assert_allclose(b["S0,1"], a["S0,1"], atol=1e-9)


def test_rotation_about_vertical_random_tree():
    t = random_tree(500, seed=2)
    fs = feats(sets=["S0+", "B1+"])
    fs.prepare(t)
    a = fs.extract(t)
    b = fs.extract(transformed(t, R=rotz(73.0)))
    np.testing.assert_allclose(b["S0+"], a["S0+"], atol=1e-9)
    keep = [0, 2, 3, 4]  # beta, L_t, R_f, L_a (alpha moves unless the parent is vertical)
    np.testing.assert_allclose(b["B1+"][:, keep], a["B1+"][:, keep], atol=1e-9)
    assert np.max(np.abs(b["B1+"][:, 1] - a["B1+"][:, 1])) > 1  # the test sees alpha at all


def test_scaling_scales_lengths_keeps_angles():
    t = random_tree(300, seed=4)
    fs = feats(sets=["S0+", "B1+"])
    fs.prepare(t)
    a = fs.extract(t)
    b = fs.extract(transformed(t, k=2.5))
    np.testing.assert_allclose(b["S0+"][:, :2], 2.5 * a["S0+"][:, :2], atol=1e-9)
    np.testing.assert_allclose(b["S0+"][:, 2:], a["S0+"][:, 2:], atol=1e-9)
    np.testing.assert_allclose(b["B1+"][:, 2:], 2.5 * a["B1+"][:, 2:], atol=1e-9)
    np.testing.assert_allclose(b["B1+"][:, :2], a["B1+"][:, :2], atol=1e-9)


def _as_multiset(a):
    a = np.round(a, 9)
    return a[np.lexsort(a.T[::-1])]


@pytest.mark.parametrize("rule", ["source", "subtree", "thickest"])
def test_renumbering_gives_same_multisets(rule):
    t = random_tree(300, seed=5)
    # a parent-before-child permutation: sort by depth with random tie-break
    from bforest_core.tree import depth_of

    rng = np.random.default_rng(0)
    perm = np.lexsort((rng.random(t.n), depth_of(t.parent)))
    inv = np.empty(t.n, dtype=np.int64)
    inv[perm] = np.arange(t.n)
    t2 = Tree(
        t.start[perm],
        t.axis[perm],
        t.length[perm],
        t.radius[perm],
        remap_ids(t.parent[perm], inv),
        remap_ids(t.extension[perm], inv),
    )
    assert not np.array_equal(perm, np.arange(t.n))
    fs = feats(sets=["S0+", "B1+"], topology=rule)
    fs.prepare(t)
    a, b = fs.extract(t), fs.extract(t2)
    for k in a:
        np.testing.assert_allclose(_as_multiset(a[k]), _as_multiset(b[k]), atol=1e-8)


def test_same_code_for_any_input_topology():
    # a tree built with 'thickest' and one built with 'source' give the same 'subtree' tables
    t = random_tree(200, seed=6)
    t_th = t.with_topology("thickest")
    fs = feats(sets=["S0+", "B1+"], topology="subtree")
    fs.prepare(t)
    a, b = fs.extract(t), fs.extract(t_th)
    for k in a:
        np.testing.assert_allclose(a[k], b[k], rtol=0, atol=1e-10)  # Tree() renormalises axes (ulps)


# ------------------------------------------------------------------------------ vectorised kernels vs a reference


def test_tables_match_a_per_cylinder_reference():
    t = random_tree(150, seed=7)
    rows, S = segment_table(t)
    ids, B = branch_table(t)
    seg_L = {}
    for r in range(t.n):  # reference: walk each cylinder to its branch base
        L, c = 0.0, r
        while t.position_in_branch[c] > 0:
            c = t.parent[c]
            L += t.length[c]
        seg_L[r] = L
    np.testing.assert_allclose(S[:, 1], [seg_L[r] for r in rows], atol=1e-12)
    for j, b in enumerate(ids):
        cyl = np.flatnonzero(t.branch == b)
        f = cyl[t.position_in_branch[cyl] == 0][0]
        p = t.parent[f]
        assert B[j, 2] == pytest.approx(t.length[cyl].sum(), abs=1e-12)
        assert B[j, 3] == t.radius[f]
        proj = np.clip((t.start[f] - t.start[p]) @ t.axis[p], 0, t.length[p])
        assert B[j, 4] == pytest.approx(seg_L[p] + proj, abs=1e-12)
        assert B[j, 0] == pytest.approx(np.degrees(np.arccos(np.clip(t.axis[f] @ t.axis[p], -1, 1))), abs=1e-9)


# ------------------------------------------------------------------------------ sets, embedding, policies


def test_parse_set_forms():
    assert parse_set("S0,1").orders == (0, 1)
    assert parse_set("b2-4") == parse_set("B2,3,4").__class__("B2-4", "B", (2, 3, 4), None)
    s = parse_set("B2+")
    assert s.open_from == 2 and s.orders == () and s.pooled
    assert parse_set("S1").pooled is False
    for bad in ["B0", "B0,1", "X1", "S", "S3-2", "S1;2", "B0+"]:
        with pytest.raises(ValueError):
            parse_set(bad)


def test_bad_settings_are_config_errors():
    with pytest.raises(ConfigError, match="B0"):
        bf.component("features", "branch-segment", sets=["B0"])
    with pytest.raises(ConfigError, match="twice"):
        bf.component("features", "branch-segment", sets=["S1", "s1"])
    with pytest.raises(ConfigError):
        bf.component("features", "branch-segment", sets=["S1"], topology="apical")


def test_circular_embedding_and_columns():
    fs = feats(sets=["B1", "S1"], angles="circular")
    assert fs.columns("B1") == ["beta", "sin(alpha)", "cos(alpha)", "L_t", "R_f", "L_a"]
    assert fs.columns("S1") == ["R", "L", "sin(gamma)", "cos(gamma)", "sin(zeta)", "cos(zeta)"]
    U = fs.extract(hand_tree())
    a = np.radians([-90, 0, 90])
    np.testing.assert_allclose(U["B1"][:, 1], np.sin(a), atol=1e-12)
    np.testing.assert_allclose(U["B1"][:, 2], np.cos(a), atol=1e-12)
    assert U["S1"].shape == (4, 6)
    np.testing.assert_allclose(U["S1"][:, 3], 1.0)  # cos 0


def test_order_column_only_on_pooled_sets():
    fs = feats(sets=["S0,1", "B1"], order_column=True)
    assert fs.columns("S0,1")[-1] == "order" and fs.columns("B1")[-1] == "L_a"
    U = fs.extract(hand_tree())
    np.testing.assert_array_equal(U["S0,1"][:, -1], [0, 0, 0, 1, 1, 1, 1])


def test_open_range_needs_prepare_and_resolves_on_data():
    fs = feats(sets=["S1+", "B1+"])
    with pytest.raises(ConfigError, match="prepare"):
        fs.extract(hand_tree())
    fs.prepare(hand_tree())
    assert fs.orders("S1+") == (1,) and fs.orders("B1+") == (1,)
    # a model tree's higher orders are not in a set resolved on the data
    model = random_tree(300, seed=8)
    assert model.max_order > 1
    U = fs.extract(model)
    assert U["S1+"].shape[0] == np.count_nonzero(model.with_topology("source").order == 1)


def test_resolved_settings_rebuild_the_same_sets_on_the_model_side():
    data = random_tree(400, seed=9)
    fs = feats(sets=["S0,1", "B2+", "B1", "s3,99"], min_rows=5, small_sets="drop")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fs.prepare(data)
    s = fs.resolved_settings()
    assert s["sets"] == fs.set_names and len(s["sets"]) < 4  # small sets were dropped
    model_fs = BranchSegmentFeatures(**s)  # what the objective builds in each worker, without prepare
    model = random_tree(500, seed=10)
    a, b = fs.extract(model), model_fs.extract(model)
    assert list(a) == list(b) == fs.set_names
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])
    assert model_fs.orders("B2+") == fs.orders("B2+") and len(fs.orders("B2+")) >= 2
    assert fs.orders("S3,99") == (3,)  # order 99 is absent from the data tree
    with pytest.raises(ConfigError, match="unknown set"):
        BranchSegmentFeatures(sets=["S1"], orders={"S2": [2]})


def test_missing_orders():
    fs = feats(sets=["B2"])
    with pytest.raises(ConfigError, match="order 2"):
        fs.prepare(hand_tree())
    fs = feats(sets=["B1,2"])
    with pytest.warns(RuntimeWarning, match="absent"):
        fs.prepare(hand_tree())
    assert fs.orders("B1,2") == (1,)


def test_min_rows_policies():
    with pytest.raises(ConfigError, match="B1.*3 rows.*pool"):
        feats(sets=["B1"], min_rows=10).prepare(hand_tree())
    fs = feats(sets=["B1", "S0,1"], min_rows=5, small_sets="drop")
    with pytest.warns(RuntimeWarning, match="dropped"):
        fs.prepare(hand_tree())
    assert fs.set_names == ["S0,1"] and list(fs.extract(hand_tree())) == ["S0,1"]
    fs = feats(sets=["B1"], min_rows=10, small_sets="keep")
    fs.prepare(hand_tree())
    assert fs.set_names == ["B1"]
    # several data trees are pooled before the check
    fs = feats(sets=["B1"], min_rows=6)
    fs.prepare([hand_tree(), hand_tree()])
    assert fs.extract_pooled([hand_tree(), hand_tree()])["B1"].shape == (6, 5)


def test_nan_policy_drop_and_error():
    t = hand_tree()
    t.radius.flags.writeable = True
    t.radius[4] = np.nan  # corrupt input after validation
    fs = feats(sets=["S1", "B1"])
    U = fs.extract(t)
    assert U["S1"].shape == (3, 4) and fs.last_dropped == {"S1": 1, "B1": 0}
    with pytest.raises(ValueError, match="S1.*1 row"):
        feats(sets=["S1"], nan_policy="error").extract(t)


def test_exclude_added_keeps_lengths():
    t = hand_tree()
    t2 = Tree(
        t.start,
        t.axis,
        t.length,
        t.radius,
        t.parent,
        t.extension,
        added=[False, False, False, True, False, False, False],
    )
    U = feats(sets=["S1", "B1"], exclude_added=True).extract(t2)
    np.testing.assert_allclose(U["S1"][:, :2], [[0.04, 0.8], [0.04, 0], [0.03, 0]], atol=1e-12)
    assert U["B1"][0, 2] == pytest.approx(1.3)


def test_trunk_only_tree_has_empty_branch_table():
    t = Tree([[0, 0, 0], [0, 0, 1]], [[0, 0, 1]] * 2, [1, 1], [0.1, 0.1], [-1, 0], [1, -1])
    U = feats(sets=["B1", "S1"]).extract(t)
    assert U["B1"].shape == (0, 5) and U["S1"].shape == (0, 4)


def test_registered_and_defaults():
    fs = bf.component("features", "branch-segment")
    assert isinstance(fs, BranchSegmentFeatures)
    assert fs.settings.topology == "subtree" and fs.settings.angles == "circular"


# ------------------------------------------------------------------------------ real data


def test_real_pine3_branch_counts_by_rule():
    t = read_sample("pine_ruotsinkyla_3.mat")
    src = t.with_topology("source")
    assert src.n_branches == 300
    fs = feats(sets=["S1"])
    fs.prepare(src)
    assert fs.extract(src)["S1"].shape[0] == 290
    th = feats(sets=["S1"], topology="thickest")
    th.prepare(src)
    assert th.extract(src)["S1"].shape[0] == 96  # the 0.35 m twig takes over the trunk (§1.1)
    assert src.with_topology("subtree").max_order == 4
    assert src.with_topology("thickest").max_order == 7


def test_real_coffee_branch_count():
    t = read_sample("coffeetree_treeqsm_optqsm.mat")
    assert t.with_topology("source").n_branches == 82


def test_real_tables_are_finite():
    t = read_sample("pine_ruotsinkyla_1.mat")
    fs = feats(sets=["S0+", "B1+"], angles="circular", topology="subtree")
    fs.prepare(t)
    U = fs.extract(t)
    assert all(np.isfinite(v).all() for v in U.values())
    assert sum(fs.last_dropped.values()) == 0


@pytest.mark.parametrize(
    "name,branches",
    [
        ("pine_ruotsinkyla_1.mat", 805),
        ("pine_ruotsinkyla_2.mat", 587),
        ("pine_ruotsinkyla_3.mat", 300),
        ("archi_tree1_treeqsm_v23.txt", 233),
        ("coffeetree_treeqsm_optqsm.mat", 82),
        ("itsme_qsm_tree_v240.mat", 410),
        ("itsme_qsm_trunk.mat", 1),
    ],
)
def test_real_source_topology_branch_counts(name, branches):
    # docs/features-and-distance.md §7: 'source' reproduces TreeQSM's branch count (after detached fragments are removed)
    assert read_sample(name).with_topology("source").n_branches == branches


@pytest.mark.parametrize(
    "name,share,share_stored",
    [
        ("pine_ruotsinkyla_3.mat", 59, 54),
        ("pine_ruotsinkyla_1.mat", 49, 45),
        ("wytham_tf1.mat", 39, 35),
        ("itsme_qsm_tree_v240.mat", 20, 20),
        ("coffeetree_treeqsm_optqsm.mat", 18, 18),
    ],
)
def test_real_fork_shares_where_thickest_is_not_the_qsm_continuation(name, share, share_stored):
    # docs/features-and-distance.md §1.1: share of forks (>= 2 children) whose thickest child is not TreeQSM's continuation
    t = read_sample(name).with_topology("source")
    th = t.with_topology("thickest")
    forks = np.flatnonzero(np.bincount(t.parent[1:], minlength=t.n) >= 2)
    differ = th.extension[forks] != t.extension[forks]
    stored = t.extension[forks] >= 0
    assert round(100 * differ.mean()) == share
    assert round(100 * differ[stored].mean()) == share_stored
