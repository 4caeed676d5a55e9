"""Tree-level summary statistics and the summary distance, with known answers."""

import math

import numpy as np
import pytest

import bforest_core as bf
from bforest_core.metrics import crown_base_height, order_summary, summary_unit, tree_summary, whorls
from conftest import hand_tree, read_sample

PI = math.pi


def test_tree_summary_of_the_hand_built_tree():
    """Trunk 3 x 1 m (radii 0.2, 0.15, 0.1); laterals A (z = 1, 0.8 + 0.5 m at 60 deg), B (z = 1.5,
    0.6 m), C (z = 2.25, 0.6 m)."""
    s = tree_summary(hand_tree(), max_order=2, bands=5)
    assert s["height"] == pytest.approx(3.0) and s["base_diameter"] == pytest.approx(0.4)
    assert s["dbh"] == pytest.approx(0.3)  # 1.3 m lies in trunk cylinder 1 (radius 0.15)
    assert s["stem_length"] == pytest.approx(3.0)
    assert s["n_branches_o1"] == 3 and s["n_branches_o2"] == 0
    assert s["length_o1"] == pytest.approx(2.5) and s["length_o2"] == 0
    assert s["volume_o0"] == pytest.approx(PI * (0.04 + 0.0225 + 0.01))
    assert s["volume_o1"] == pytest.approx(PI * (0.0025 * 0.8 + 0.0016 * 0.5 + 0.0016 * 0.6 + 0.0009 * 0.6))
    # bases at 1/3, 1/2 and 3/4 of the height: bands 1, 2, 3 of 5
    assert [s[f"profile_n_b{k}"] for k in range(5)] == [0, 1, 1, 1, 0]
    assert [s[f"profile_len_b{k}"] for k in range(5)] == pytest.approx([0, 1.3, 0.6, 0.6, 0])
    assert s["crown_base_height"] == pytest.approx(1.0)
    assert s["crown_spread"] == pytest.approx(bf.classical_metrics(hand_tree())["crown_spread"])


def test_detection_limit_leaves_thin_branches_out_of_counts_lengths_and_profile():
    # base diameters of A, B, C are 0.10, 0.08 and 0.06 m: a 7 cm limit keeps A and B only
    s = tree_summary(hand_tree(), max_order=2, bands=5, min_diameter=0.07)
    assert s["n_branches_o1"] == 2 and s["n_all_branches_o1"] == 3
    assert s["length_o1"] == pytest.approx(1.9)
    assert [s[f"profile_n_b{k}"] for k in range(5)] == [0, 1, 1, 0, 0]
    assert s["volume_o1"] == pytest.approx(tree_summary(hand_tree())["volume_o1"])  # wood is wood
    fs = bf.component("features", "tree-summary", statistics=["n_branches_o1"], min_branch_diameter=0.07)
    assert fs.extract(hand_tree())["summary"][0].tolist() == [2.0]


def test_crown_base_height_weighs_branch_length():
    t = hand_tree()
    # 5 % of 2.5 m lies below A's base: A; 60 % (1.5 m) is more than A (1.3 m): B's base, 1.5 m
    assert crown_base_height(t, share=0.05) == pytest.approx(1.0)
    assert crown_base_height(t, share=0.6) == pytest.approx(1.5)
    assert crown_base_height(t, share=0.99) == pytest.approx(2.25)


def test_dead_remnants_are_not_crown():
    t = hand_tree()
    dead = np.zeros(t.n, bool)
    dead[[3, 4]] = True  # lateral A (its two cylinders) is a dead remnant
    t2 = bf.Tree(t.start, t.axis, t.length, t.radius, t.parent, t.extension, extras={"is_dead": dead})
    s = tree_summary(t2)
    assert s["n_branches_o1"] == 2 and s["length_o1"] == pytest.approx(1.2)
    assert s["crown_base_height"] == pytest.approx(1.5)
    assert s["volume_o1"] == pytest.approx(tree_summary(t)["volume_o1"])  # dead wood is still wood


def test_whorls_group_branch_bases_by_height_and_keep_dead_branches():
    # bases at 1.0, 1.5 and 2.25 m: three whorls 15 cm apart or more; with a 60 cm gap A and B
    # (0.5 m apart) are one whorl, C (0.75 m above B) another
    t = hand_tree()
    assert tree_summary(t)["n_whorls"] == 3
    assert [g.tolist() for g in whorls(t, gap=0.6)] == [[1.0, 1.5], [2.25]]
    assert tree_summary(t, min_diameter=0.07)["n_whorls"] == 2  # C (6 cm) is not seen
    dead = np.zeros(t.n, bool)
    dead[[3, 4]] = True  # A dead: it still marks its whorl, as a scan shows it
    t2 = bf.Tree(t.start, t.axis, t.length, t.radius, t.parent, t.extension, extras={"is_dead": dead})
    assert tree_summary(t2)["n_whorls"] == 3 and tree_summary(t2)["n_branches_o1"] == 2
    assert summary_unit("n_whorls") == "count"


def test_lignum_sets_one_whorl_a_year():
    # the leader puts on one shoot a year with its whorl of buds at the top: T years, T - 1 whorls
    ssm = bf.component("ssm", "lignum", preset="sf_real")
    for years in (10, 20):
        assert tree_summary(ssm.simulate({"years": years}, 1), min_diameter=0.0)["n_whorls"] == years - 1


def test_order_summary_of_the_hand_built_tree():
    rows = order_summary(hand_tree())
    assert [r["order"] for r in rows] == [0, 1]
    assert rows[0]["n_branches"] == 1 and rows[0]["length_m"] == pytest.approx(3.0)
    assert math.isnan(rows[0]["mean_angle_deg"]) and rows[0]["mean_base_diameter_m"] == pytest.approx(0.4)
    assert rows[1]["n_branches"] == 3 and rows[1]["length_m"] == pytest.approx(2.5)
    assert rows[1]["mean_angle_deg"] == pytest.approx((60 + 90 + 90) / 3)
    assert rows[1]["mean_base_diameter_m"] == pytest.approx(2 * (0.05 + 0.04 + 0.03) / 3)


def test_order_summary_of_a_degenerate_chain_one_order_per_cylinder():
    """Every cylinder a lateral of the one below: as many orders as cylinders (one pass per
    sum, not one per order: a 1M-cylinder chain took minutes)."""
    n = 3000
    z = np.arange(n, dtype=float)
    t = bf.Tree(
        np.c_[np.zeros(n), np.zeros(n), z],
        np.tile([0, 0, 1.0], (n, 1)),
        np.ones(n),
        np.linspace(0.3, 0.01, n),
        np.r_[-1, np.arange(n - 1)],
        np.full(n, -1),
    )
    rows = order_summary(t)
    assert [r["order"] for r in rows] == list(range(n))
    assert all(r["n_branches"] == 1 and r["length_m"] == pytest.approx(1.0) for r in rows)
    assert math.isnan(rows[0]["mean_angle_deg"]) and rows[5]["mean_angle_deg"] == pytest.approx(0.0)
    assert rows[-1]["mean_base_diameter_m"] == pytest.approx(0.02)
    assert rows[7]["volume_m3"] == pytest.approx(np.pi * t.radius[7] ** 2)


def test_summary_of_a_real_pine_against_an_independent_count():
    t = read_sample("pine_ruotsinkyla_3.mat")
    s = tree_summary(t)
    br = t.branches
    lengths = np.array([t.length[br.cylinders[br.ptr[b] : br.ptr[b + 1]]].sum() for b in range(len(br))])
    assert s["n_all_branches_o1"] == np.count_nonzero(br.order == 1) == 73
    # the detection limit: first-order branches at least 1 cm thick at the base
    seen = (br.order == 1) & (2 * t.radius[br.first] >= 0.01)
    assert s["n_branches_o1"] == np.count_nonzero(seen) == 72
    assert s["length_o1"] == pytest.approx(lengths[seen].sum())
    assert tree_summary(t, min_diameter=0)["length_o1"] == pytest.approx(lengths[br.order == 1].sum())
    assert s["height"] == pytest.approx(9.936, abs=1e-3)
    assert sum(s[f"profile_n_b{k}"] for k in range(5)) == 72
    assert 1.0 < s["crown_base_height"] < 6.0
    assert (
        summary_unit("length_o2") == "m"
        and summary_unit("volume_o0") == "m^3"
        and summary_unit("n_branches_o1") == "count"
    )


# ------------------------------------------------------------------------------ the components
def test_tree_summary_feature_set():
    fs = bf.component("features", "tree-summary", statistics=["height", "n_branches_o1", "profile_len_b1"])
    assert fs.set_names == ["summary"] and fs.columns("summary") == ["height", "n_branches_o1", "profile_len_b1"]
    U = fs.extract(hand_tree())
    assert U["summary"].shape == (1, 3) and U["summary"][0].tolist() == pytest.approx([3.0, 3.0, 1.3])
    bad = bf.component("features", "tree-summary", statistics=["height", "heigth"])
    with pytest.raises(ValueError, match="unknown statistic.*heigth.*known"):
        bad.prepare([hand_tree()])


def _dist(**settings):
    d = bf.component("distance", "summary", **settings)
    d.prepare({"summary": np.zeros((1, 2))}, {"summary": ["height", "n_branches_o1"]})
    return d


def test_summary_distance_known_answers():
    m, d = np.array([[10.0, 0.0]]), np.array([[5.0, 0.0]])
    x = abs(math.log(10.05 / 5.05))  # offset 0.05 m for a length; a count of 0 against 0 is 0
    assert _dist().compute_pair("summary", m, d) == pytest.approx(x / 2)
    assert _dist(weights={"height": 3.0}).compute_pair("summary", m, d) == pytest.approx(3 * x / 4)
    assert _dist(scales={"height": 0.5}).compute_pair("summary", m, d) == pytest.approx(min(x / 0.5, 2.0) / 2)
    assert _dist(form="relative").compute_pair("summary", m, d) == pytest.approx((1.0 + 0.0) / 2)
    # symmetric: the log ratio does not care which side is larger
    assert _dist().compute_pair("summary", d, m) == pytest.approx(x / 2)
    # counts: 3 against 0 branches is log(4)
    assert _dist().compute_pair("summary", np.array([[5.0, 3.0]]), d) == pytest.approx(math.log(4) / 2)


def test_summary_distance_missing_values_and_caps():
    d = _dist(cap=1.5)
    assert d.compute_pair("summary", np.empty((0, 2)), np.array([[5.0, 1.0]])) == 1.5
    # a NaN model value (no DBH) costs the cap; a NaN data value leaves the statistic out
    assert d.compute_pair("summary", np.array([[np.nan, 1.0]]), np.array([[5.0, 1.0]])) == pytest.approx(0.75)
    assert d.compute_pair("summary", np.array([[7.0, 1.0]]), np.array([[np.nan, 1.0]])) == 0.0
    with pytest.raises(ValueError, match="does not have: hieght"):
        _dist(weights={"hieght": 2.0})


def test_a_signed_statistic_counts_its_difference_and_its_limit_is_a_difference():
    # the crown's offset (crown radii) has no ratio: -0.5 against 0.5 misses by 1, in either form
    d = bf.component("distance", "summary", weights={"height": 1e-9}, limits={"crown_offset_x": 0.2}, steep=3.0)
    d.prepare({"summary": np.zeros((1, 2))}, {"summary": ["height", "crown_offset_x"]})
    data = np.array([[10.0, 0.5]])
    terms = d.per_statistic(np.array([[10.0, 0.4]]), data, ["height", "crown_offset_x"])
    assert terms == pytest.approx({"height": 0.0, "crown_offset_x": 0.1})  # within the limit: the plain difference
    terms = d.per_statistic(np.array([[10.0, -0.5]]), data, ["height", "crown_offset_x"])
    assert terms["crown_offset_x"] == pytest.approx(1.0 + 3.0 * (1.0 - 0.2))  # beyond it: steep by the difference
    rel = bf.component("distance", "summary", form="relative")
    rel.prepare({"summary": np.zeros((1, 1))}, {"summary": ["crown_offset_y"]})
    assert rel.compute_pair("summary", np.array([[-0.3]]), np.array([[0.1]])) == pytest.approx(0.4)
    # two model trees: their mean, as for every statistic
    assert rel.compute_pair("summary", np.array([[-0.3], [0.5]]), np.array([[0.1]])) == pytest.approx(0.0)


def test_summary_distance_limits_make_a_miss_beyond_them_steep():
    d = np.array([[10.0, 20.0]])
    within = np.array([[11.0, 20.0]])  # 10 % taller: inside a 20 % limit, the plain log ratio
    x = math.log(11.05 / 10.05)
    lim = _dist(limits={"height": 0.2}, weights={"n_branches_o1": 1e-9})
    assert lim.compute_pair("summary", within, d) == pytest.approx(x)
    # 30 % taller: the log ratio beyond log(1.2) counts 1 + steep times
    y = math.log(13.05 / 10.05)
    over = y + 10 * (y - math.log(1.2))
    assert lim.compute_pair("summary", np.array([[13.0, 20.0]]), d) == pytest.approx(over)
    # 30 % shorter: the limit on that side is -log(0.8), not log(1.2)
    z = abs(math.log(7.05 / 10.05))
    under = z + 10 * (z + math.log(0.8))
    assert lim.compute_pair("summary", np.array([[7.0, 20.0]]), d) == pytest.approx(under)
    assert under > over > 2 * y  # a miss beyond the limit costs far more than the plain ratio
    # 18 % shorter: beyond log(1.2) as a ratio (0.199) but within -log(0.8) (0.223): no extra
    w = abs(math.log(8.25 / 10.05))
    assert w > math.log(1.2) and lim.compute_pair("summary", np.array([[8.2, 20.0]]), d) == pytest.approx(w)
    # the relative form: |m - d| / d beyond the limit, steep 4; the cap (2) bounds the plain term
    # and the extra grows with it: 3x the branches still costs more than 2.2x, 4x the same as 3x
    rel = _dist(form="relative", limits={"n_branches_o1": 0.25}, steep=4.0, weights={"height": 1e-9})
    assert rel.compute_pair("summary", np.array([[10.0, 27.0]]), d) == pytest.approx(0.35 + 4 * 0.10)
    assert rel.compute_pair("summary", np.array([[10.0, 44.0]]), d) == pytest.approx(1.2 + 4 * 0.95)
    assert rel.compute_pair("summary", np.array([[10.0, 60.0]]), d) == pytest.approx(2.0 + 4 * 1.75)
    assert rel.compute_pair("summary", np.array([[10.0, 80.0]]), d) == pytest.approx(2.0 + 4 * 1.75)
    # a scale divides the limit as it divides the term
    sc = _dist(limits={"height": 0.2}, scales={"height": 0.5}, weights={"n_branches_o1": 1e-9})
    assert sc.compute_pair("summary", np.array([[13.0, 20.0]]), d) == pytest.approx(
        y / 0.5 + 10 * (y - math.log(1.2)) / 0.5
    )
    # no limits: the same distance as before, to the bit
    assert _dist(steep=50.0).compute_pair("summary", np.array([[13.0, 27.0]]), d) == _dist().compute_pair(
        "summary", np.array([[13.0, 27.0]]), d
    )
    with pytest.raises(ValueError, match="does not have: dhb"):
        _dist(limits={"dhb": 0.2})
    with pytest.raises(ValueError, match="between 0 and 1"):
        _dist(limits={"height": 1.5})


def test_branching_angles_of_the_hand_built_tree():
    # laterals A, B, C leave the trunk at 60, 90 and 90 deg (base diameters 0.10, 0.08, 0.06 m)
    s = tree_summary(hand_tree(), max_order=2)
    assert s["angle_o1"] == pytest.approx(90.0)
    assert s["angle_iqr_o1"] == pytest.approx(90.0 - 75.0)  # quartiles of (60, 90, 90): 75 and 90
    assert np.isnan(s["angle_o2"]) and np.isnan(s["angle_iqr_o2"])  # no second-order branches
    thick = tree_summary(hand_tree(), max_order=2, min_diameter=0.07)  # A and B only
    assert (thick["angle_o1"], thick["angle_iqr_o1"]) == (pytest.approx(75.0), pytest.approx(15.0))
    assert summary_unit("angle_iqr_o1") == "deg" and summary_unit("angle_o1") == "deg"
    assert [r["mean_angle_deg"] for r in order_summary(hand_tree()) if r["order"] == 1] == [pytest.approx(80.0)]


def _forked_tree():
    """A 2 m trunk (r 0.2) whose stored continuation is a 1 m spire (r 0.1, no branches) while a
    limb beside it (1 m at 45 deg, r 0.15, then 3 m up, r 0.12) carries two 0.5 m twigs (r 0.03):
    the QSM's stem ends in the spire, the wood runs on into the limb."""
    s = math.sqrt(0.5)
    start = [[0, 0, 0], [0, 0, 2], [0, 0, 2], [s, 0, 2 + s], [s, 0, 3 + s], [s, 0, 4 + s]]
    axis = [[0, 0, 1], [0, 0, 1], [s, 0, s], [0, 0, 1], [1, 0, 0], [0, 1, 0]]
    return bf.Tree(
        start,
        axis,
        [2, 1, 1, 3, 0.5, 0.5],
        [0.2, 0.1, 0.15, 0.12, 0.03, 0.03],
        [-1, 0, 0, 2, 3, 3],
        [1, -1, 3, -1, -1, -1],
    )


def test_tree_summary_topology_counts_branches_by_one_rule_on_any_tree():
    t = _forked_tree()
    # the stored branching: the limb is the one first-order branch, its twigs second-order
    own = tree_summary(t, min_diameter=0.0)
    assert (own["n_branches_o1"], own["n_branches_o2"], own["stem_length"]) == (1, 2, 3.0)
    # by wood volume the stem runs on into the limb (pi (0.0225 + 3 x 0.0144 + ...) against pi 0.01
    # for the spire) and on into the first twig (a tie with the second goes to the earlier row):
    # the spire and the other twig are first-order, the stem 2 + 1 + 3 + 0.5 m long
    fs = bf.component("features", "tree-summary", statistics=["n_branches_o1", "n_branches_o2", "stem_length"])
    assert fs.settings.topology is None and fs.extract(t)["summary"][0].tolist() == [1, 2, 3.0]
    sub = bf.component("features", "tree-summary", topology="subtree", statistics=fs.settings.statistics)
    assert sub.extract(t)["summary"][0].tolist() == pytest.approx([2, 0, 6.5])
    # the rule for the count alone: the stem's length by the tree's own branches
    one = bf.component(
        "features",
        "tree-summary",
        topology="subtree",
        topology_statistics=["n_branches_o1"],
        statistics=fs.settings.statistics,
    )
    assert one.extract(t)["summary"][0].tolist() == pytest.approx([2, 2, 3.0])
    with pytest.raises(ValueError, match="unknown statistic.*n_branch_o1"):
        bf.component("features", "tree-summary", topology="subtree", topology_statistics=["n_branch_o1"]).prepare([t])
    # a list of statistics without a rule to measure them by would do nothing: refused
    with pytest.raises(ValueError, match="topology_statistics.*needs a topology"):
        bf.component("features", "tree-summary", topology_statistics=["n_branches_o1"])
    # the fidelity table measures by the same rule
    from bforest_core.attributes import fidelity_statistics

    assert fidelity_statistics(t)["n_branches_o1"] == 1 and fidelity_statistics(t, "subtree")["n_branches_o1"] == 2
    alone = fidelity_statistics(t, "subtree", ["n_branches_o1"])
    assert (alone["n_branches_o1"], alone["n_branches_o2"], alone["stem_length"]) == (2, 2, 3.0)
