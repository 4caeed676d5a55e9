"""TreeQSM's tree attributes and distributions (bforest_core.attributes): hand-computed values on
hand-built trees, and TreeQSM 2.4's own treedata/branch of the coffee tree sample."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from bforest_core import Tree
from bforest_core.attributes import branch_table, distributions, stem_taper, tree_attributes
from conftest import hand_tree, qsm_path

PI = np.pi


def _by_height(b):
    """Rows of the hand tree's laterals A (z = 1), B (z = 1.5), C (z = 2.25)."""
    h = b["height"]
    return [int(np.flatnonzero(np.isclose(h, z))[0]) for z in (1.0, 1.5, 2.25)]


def test_hand_tree_branch_table():
    b = branch_table(hand_tree())
    A, B, C = _by_height(b)
    assert b["order"].tolist()[0] == 0 and b["parent"][0] == -1
    assert [b["parent"][i] for i in (A, B, C)] == [0, 0, 0]
    assert b["diameter"][[A, B, C]] == pytest.approx([0.10, 0.08, 0.06])
    assert b["length"][[0, A, B, C]] == pytest.approx([3.0, 1.3, 0.6, 0.6])
    assert b["volume"][A] == pytest.approx(PI * (0.05**2 * 0.8 + 0.04**2 * 0.5))
    assert b["area"][A] == pytest.approx(2 * PI * (0.05 * 0.8 + 0.04 * 0.5))
    assert b["angle"][[0, A, B, C]] == pytest.approx([0, 60, 90, 90])
    assert b["azimuth"][[A, B, C]] == pytest.approx([0, 90, 180])
    assert b["zenith"][[0, A, B, C]] == pytest.approx([0, 60, 90, 90])


def test_hand_tree_attributes():
    a = tree_attributes(hand_tree())
    assert a["trunk_volume"] == pytest.approx(PI * (0.04 + 0.0225 + 0.01))
    assert a["branch_volume"] == pytest.approx(PI * (0.0025 * 0.8 + 0.0016 * 0.5 + 0.0016 * 0.6 + 0.0009 * 0.6))
    assert a["total_volume"] == pytest.approx(a["trunk_volume"] + a["branch_volume"])
    assert (a["trunk_length"], a["branch_length"], a["total_length"]) == pytest.approx((3.0, 2.5, 5.5))
    assert a["trunk_area"] == pytest.approx(2 * PI * 0.45)
    assert a["branch_area"] == pytest.approx(2 * PI * (0.04 + 0.02 + 0.024 + 0.018))
    assert (a["n_branches"], a["max_branch_order"], a["tree_height"]) == (3, 1, pytest.approx(3.0))
    taper = stem_taper(hand_tree())
    assert np.allclose(taper, [[0, 1, 2, 3], [0.4, 0.3, 0.2, 0.2]])


def test_hand_tree_distributions():
    d = distributions(hand_tree())
    # cylinder diameters 40, 30, 20, 10, 8, 8, 6 cm -> 1 cm classes 0..40
    assert d["LenCylDia"].size == 41
    want = np.zeros(41)
    want[[40, 30, 20, 10, 8, 6]] = [1, 1, 1, 0.8, 1.1, 0.6]
    assert d["LenCylDia"] == pytest.approx(want)
    assert d["VolCylDia"][8] == pytest.approx(PI * 0.04**2 * 1.1)
    # heights: trunk cylinders one per metre, A (1...1.65 m) and B (1.5 m) in class 1, C (2.25 m) in 2
    assert d["LenCylHei"] == pytest.approx([1.0, 2.9, 1.6])
    zen = np.zeros(18)
    zen[[0, 6, 9]] = [3.0, 1.3, 1.2]
    assert d["LenCylZen"] == pytest.approx(zen)
    azi = np.zeros(36)
    azi[[18, 27, 35]] = [3.0 + 1.3, 0.6, 0.6]  # C points to 180 deg: the closed top of the last class
    assert d["LenCylAzi"] == pytest.approx(azi)
    ang = np.zeros(18)
    ang[[6, 9]] = [1, 2]
    assert d["NumBranchAng"] == pytest.approx(ang) and d["NumBranch1Ang"] == pytest.approx(ang)
    assert d["VolBranchAng"][9] == pytest.approx(PI * (0.0016 * 0.6 + 0.0009 * 0.6))
    dia = np.zeros(11)
    dia[[10, 8, 6]] = 1
    assert d["NumBranchDia"] == pytest.approx(dia)
    assert d["NumBranchHei"] == pytest.approx([0, 2, 1]) and d["LenBranchHei"] == pytest.approx([0, 1.9, 0.6])
    assert d["NumBranchOrd"].tolist() == [3] and d["LenBranchOrd"] == pytest.approx([2.5])


def test_height_classes_split_a_slanted_cylinder():
    t = Tree([[0, 0, 0]], [[0.6, 0, 0.8]], [2.5], [0.1], [-1])
    d = distributions(t)  # rises 2 m: half of it in each 1 m class
    assert d["LenCylHei"] == pytest.approx([1.25, 1.25])
    assert d["VolCylHei"] == pytest.approx([PI * 0.01 * 1.25] * 2)


def _cross_tree():
    """A 2 m trunk (two cylinders) with four 1 m horizontal branches at 1 m, pointing to 5, 95,
    185 and 275 deg; every radius 1 mm."""
    ang = np.radians([5, 95, 185, 275])
    axes = np.column_stack([np.cos(ang), np.sin(ang), np.zeros(4)])
    start = [[0, 0, 0], [0, 0, 1]] + [[0, 0, 1]] * 4
    axis = [[0, 0, 1], [0, 0, 1]] + axes.tolist()
    return Tree(start, axis, [1, 1, 1, 1, 1, 1], [0.001] * 6, [-1, 0, 0, 0, 0, 0], [1, -1, -1, -1, -1, -1])


def test_crown_measures_of_a_cross():
    a = tree_attributes(_cross_tree())
    # tips at distance 1 from the hull's centroid in two pairs of opposite 10-deg sectors: two
    # diameters of 2 m among 18
    assert a["crown_diameter_mean"] == pytest.approx(4 / 18, abs=1e-9)
    assert a["crown_diameter_max"] == pytest.approx(2.0, abs=1e-9)
    assert a["crown_area_conv"] == pytest.approx(2.0, abs=1e-9)  # the square with diagonals 2 m
    assert a["crown_base_height"] == pytest.approx(1.0)
    assert (a["crown_length"], a["crown_ratio"]) == pytest.approx((1.0, 0.5))
    # the pyramid over that square up to the trunk top: 2 x 1 / 3 (plus the 1 mm radii)
    assert a["crown_volume_conv"] == pytest.approx(2 / 3, rel=0.01)
    assert 0 < a["crown_area_alpha"] <= a["crown_area_conv"] + 1e-9


def test_fidelity_statistics_add_volumes_and_crown_to_the_summary():
    from bforest_core.attributes import FIDELITY_ATTRIBUTES, fidelity_statistics
    from bforest_core.metrics import summary_label, summary_unit, tree_summary

    t = _cross_tree()
    f, a = fidelity_statistics(t), tree_attributes(t)
    assert set(f) == set(tree_summary(t)) | set(FIDELITY_ATTRIBUTES) | {"crown_offset_x", "crown_offset_y"}
    assert f["crown_volume_conv"] == pytest.approx(a["crown_volume_conv"]) and f["crown_ratio"] == pytest.approx(0.5)
    assert all(summary_unit(k) and summary_label(k) != k for k in FIDELITY_ATTRIBUTES)
    assert np.isnan(tree_attributes(t, alpha=False)["crown_volume_alpha"])


def test_trunk_only_tree_has_no_crown():
    t = Tree([[0, 0, 0], [0, 0, 1]], [[0, 0, 1]] * 2, [1, 1], [0.1, 0.08], [-1, 0], [1, -1])
    a = tree_attributes(t)
    assert a["n_branches"] == 0 and a["crown_base_height"] == pytest.approx(2.0)
    assert a["crown_length"] == 0 and a["crown_volume_conv"] == 0
    d = distributions(t)
    assert d["NumBranchOrd"].tolist() == [0.0] and d["NumBranchAng"].sum() == 0


# ------------------------------------------------------------------------------------------
# against TreeQSM 2.4's own treedata (coffee tree sample)
# ------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def coffee():
    import scipy.io as sio

    from bforest_core import read_qsm

    p = qsm_path("coffeetree_treeqsm_optqsm.mat")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        t = read_qsm(p)
    q = sio.loadmat(str(p), squeeze_me=True, struct_as_record=False)["OptQSM"]
    return t, q


def test_branch_table_equals_treeqsm_branch(coffee):
    t, q = coffee
    b = branch_table(t)
    # TreeQSM's branch of each of our branches, from its first cylinder's stored branch id
    tq = np.asarray(q.cylinder.branch, int)[t.source_row[t.branches.first]] - 1
    for col in ("order", "diameter", "area", "length", "angle", "height", "azimuth", "zenith"):
        assert b[col] == pytest.approx(np.asarray(getattr(q.branch, col), float)[tq], rel=1e-5, abs=1e-4), col
    assert 1000 * b["volume"] == pytest.approx(np.asarray(q.branch.volume, float)[tq], rel=1e-5)
    parent = np.asarray(q.branch.parent, int)[tq] - 1
    assert np.array_equal(tq[b["parent"][1:]], parent[1:])


def test_attributes_agree_with_treeqsm_treedata(coffee):
    t, q = coffee
    td = q.treedata
    a = tree_attributes(t)
    same = {
        "TotalVolume": 1000 * a["total_volume"],
        "TrunkVolume": 1000 * a["trunk_volume"],
        "BranchVolume": 1000 * a["branch_volume"],
        "TreeHeight": a["tree_height"],
        "TrunkLength": a["trunk_length"],
        "BranchLength": a["branch_length"],
        "TotalLength": a["total_length"],
        "MaxBranchOrder": a["max_branch_order"],
        "TrunkArea": a["trunk_area"],
        "BranchArea": a["branch_area"],
        "TotalArea": a["total_area"],
        "DBHqsm": a["dbh"],
        "CrownDiamAve": a["crown_diameter_mean"],
    }
    for k, v in same.items():
        assert v == pytest.approx(float(getattr(td, k)), rel=1e-5), k
    # the crown hull: our sampling of the cylinder surfaces differs in orientation only
    assert a["crown_area_conv"] == pytest.approx(float(td.CrownAreaConv), rel=1e-3)
    assert a["crown_area_alpha"] == pytest.approx(float(td.CrownAreaAlpha), rel=1e-2)
    # TreeQSM measures from one hull vertex; the hull's diameter is at least that
    assert float(td.CrownDiamMax) * (1 - 1e-3) <= a["crown_diameter_max"] <= float(td.CrownDiamMax) * 1.001
    # TreeQSM lists 4 branches without cylinders; we count branches from the cylinders
    empty = int(np.count_nonzero(np.asarray(q.branch.length) == 0))
    assert (empty, a["n_branches"]) == (4, float(td.NumberBranches) - 4)
    # the crown base differs by definition: the lowest first-order branch here (1.30 m), TreeQSM's
    # first "major" branch above it (1.67 m)
    assert a["crown_base_height"] == pytest.approx(float(np.asarray(q.branch.height)[1]), rel=1e-6)
    assert float(td.CrownBaseHeight) == pytest.approx(1.668, abs=1e-3)


def test_distributions_agree_with_treeqsm_treedata(coffee):
    t, q = coffee
    td = q.treedata
    d = distributions(t)
    empty = np.asarray(q.branch.length) == 0
    for k, v in d.items():
        ref = np.atleast_1d(np.asarray(getattr(td, k), float))
        got = 1000 * v if k.startswith("Vol") else v
        if "BranchDia" in k or "Branch1Dia" in k:
            # TreeQSM 2.4 bins branch diameters in 0.5 cm classes (and only up to half the largest):
            # our 1 cm class j is its classes 2j and 2j+1
            m = ref.size // 2
            if k == "NumBranchDia":
                ref = ref - np.eye(ref.size)[0] * empty.sum()  # the empty branches: diameter 0
            assert got[:m] == pytest.approx(ref[: 2 * m : 2] + ref[1 : 2 * m : 2], rel=1e-4, abs=1e-6), k
            continue
        if k.startswith("NumBranch") and not k.startswith("NumBranch1") and not k.endswith("Ord"):
            # TreeQSM's branches without cylinders count in the class of height, angle, zenith 0 (and
            # of azimuth 0, class 18)
            ref = ref.copy()
            ref[18 if k.endswith("Azi") else 0] -= empty.sum()
        assert got.shape == ref.shape and got == pytest.approx(ref, rel=1e-4, abs=1e-6), k


# ------------------------------------------------------------------------------------------
# bforest info
# ------------------------------------------------------------------------------------------


def test_info_shows_attributes_and_distributions(capsys):
    import csv
    import io
    import json

    from bforest_core.cli.main import main

    p = str(qsm_path("pine_ruotsinkyla_3.mat"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        t = __import__("bforest_core").read_qsm(p)
        a = tree_attributes(t)
        assert main(["info", p]) == 0
        out = capsys.readouterr().out
        assert f"trunk volume                {a['trunk_volume']:.4g} m^3" in out
        assert f"crown ratio                 {a['crown_ratio']:.4g}\n" in out
        assert "branches by branching angle (10 deg classes; empty ones left out)" in out
        assert "wood by height (1 m classes; empty ones left out)" in out
        assert "\n       10-20             0" not in out  # pine 3 has no branch at 10-20 deg
        assert main(["info", p, "--json"]) == 0
        js = json.loads(capsys.readouterr().out)
        assert js["attributes"]["crown_length"] == pytest.approx(a["crown_length"])
        assert js["attribute_units"]["crown_volume_conv"] == "m^3" and js["distribution_units"]["VolCylDia"] == "m^3"
        assert sum(js["distributions"]["NumBranchOrd"]) == t.n_branches - 1
        assert main(["info", p, "--csv", "--table", "branches"]) == 0
        rows = list(csv.DictReader(io.StringIO(capsys.readouterr().out)))
        assert len(rows) == t.n_branches == 300
        assert list(rows[0])[:5] == ["reconstruction", "branch", "order", "parent", "diameter_m"]
        assert float(rows[0]["volume_m^3"]) == pytest.approx(a["trunk_volume"])
        assert main(["info", p, "--csv", "--table", "attributes"]) == 0
        rows = {r["attribute"]: r for r in csv.DictReader(io.StringIO(capsys.readouterr().out))}
        assert (
            float(rows["branch_area"]["value"]) == pytest.approx(a["branch_area"])
            and rows["branch_area"]["unit"] == "m^2"
        )
        assert main(["info", p, "--csv", "--table", "distributions"]) == 0
        rows = [r for r in csv.DictReader(io.StringIO(capsys.readouterr().out)) if r["distribution"] == "NumBranchAng"]
        assert len(rows) == 18 and rows[3]["class_lower"] == "30.0" and rows[3]["class_unit"] == "deg"


def test_clone_band_and_distributions_figure(tmp_path):
    from bforest_core.report.attributes import band, distributions_figure

    med, lo, hi = band([np.array([1.0, 2.0]), np.array([3.0]), np.array([5.0, 4.0, 1.0])])
    # a clone without a class counts 0 there; numpy's linear percentiles of (1, 3, 5), (2, 0, 4), (0, 0, 1)
    assert med.tolist() == [3.0, 2.0, 0.0]
    assert lo == pytest.approx([1.2, 0.2, 0.0]) and hi == pytest.approx([4.8, 3.8, 0.9])
    t = hand_tree()
    p = distributions_figure(t, [t, _cross_tree()], tmp_path / "d.png", dpi=60)
    from PIL import Image

    im = np.asarray(Image.open(p).convert("L"))
    assert im.shape[1] > 600 and im.std() > 5  # drawn, not blank


# ------------------------------------------------------------------------------ large trees
def _comb(trunk: int = 1000, per: int = 199, seed: int = 0) -> Tree:
    """A 30 m trunk of ``trunk`` cylinders, each bearing ``per`` laterals of one cylinder
    (0.5 m, random azimuth, 30-80 deg from the vertical): ``trunk * (per + 1)`` cylinders."""
    rng = np.random.default_rng(seed)
    n_lat = trunk * per
    dz = 30.0 / trunk
    host = np.repeat(np.arange(trunk), per)
    az, ang = rng.uniform(0, 2 * PI, n_lat), np.radians(rng.uniform(30, 80, n_lat))
    lat_axis = np.c_[np.sin(ang) * np.cos(az), np.sin(ang) * np.sin(az), np.cos(ang)]
    start = np.r_[np.c_[np.zeros((trunk, 2)), np.arange(trunk) * dz], np.c_[np.zeros((n_lat, 2)), (host + 0.5) * dz]]
    axis = np.r_[np.tile([0.0, 0.0, 1.0], (trunk, 1)), lat_axis]
    length = np.r_[np.full(trunk, dz), np.full(n_lat, 0.5)]
    radius = np.r_[np.linspace(0.3, 0.02, trunk), np.full(n_lat, 0.005)]
    parent = np.r_[-1, np.arange(trunk - 1), host]
    ext = np.r_[np.arange(1, trunk), -1, np.full(n_lat, -1)]
    return Tree(start, axis, length, radius, parent, ext)


def test_height_distributions_of_a_large_tree_take_little_memory():
    """A cylinder reaches one height class or two: the shares of 200 000 cylinders in 30 classes
    are kept per cylinder and class reached (a dense table of every cylinder and class held
    200 000 x 30 floats several times over, gigabytes at a million cylinders)."""
    import tracemalloc

    t = _comb()
    assert t.n == 200_000
    tracemalloc.start()
    d = distributions(t)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 60e6, f"{peak / 1e6:.0f} MB"
    assert d["LenCylHei"].sum() == pytest.approx(30.0 + 0.5 * 199_000)  # every metre in some class
    assert d["LenCylHei"].size == 31  # the laterals of the top reach above the trunk's 30 m
    trunk = distributions(_comb(per=0))  # 1000 cylinders of 3 cm, cut by the class edges
    assert trunk["LenCylHei"] == pytest.approx(np.ones(30))
    assert trunk["VolCylHei"].sum() == pytest.approx(float(np.sum(PI * np.linspace(0.3, 0.02, 1000) ** 2 * 0.03)))


def test_the_alpha_shapes_of_a_large_crown_are_measured_on_a_thinned_cloud(monkeypatch):
    """Above ALPHA_POINTS the crown is thinned to one point per cube of a grid 16 times finer
    than alpha (coarser until few enough are left): a crown of 150 straight branches sampled
    every 2 cm keeps its alpha volume within 1 %, and the thinning says so."""
    from bforest_core import attributes as A

    rng = np.random.default_rng(1)
    base, d = rng.uniform(0, [4.0, 3.0, 2.0], (150, 3)), rng.normal(size=(150, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    along = np.linspace(0, 1.5, 80)
    crown = (base[:, None, :] + along[None, :, None] * d[:, None, :]).reshape(-1, 3)
    crown += rng.normal(0, 0.002, crown.shape)
    full = A._alpha_measure(crown, 0.8)
    kept, side = A.thinned(crown, 0.8, crown.shape[0])
    assert side == 0 and kept is crown  # within the limit: every point
    kept, side = A.thinned(crown, 0.8, 5_000)
    assert side == pytest.approx(0.1) and kept.shape[0] <= 5_000  # 0.05 m left 6 000
    cells = np.floor((kept - crown.min(0)) / side).astype(int)
    assert len({tuple(c) for c in cells}) == kept.shape[0]  # one point per cube
    assert np.array_equal(kept, A.thinned(crown, 0.8, 5_000)[0])  # the same points every time
    monkeypatch.setitem(A.ALPHA_POINTS, 3, 5_000)
    notes = []
    assert A._alpha_measure(crown, 0.8, notes) == pytest.approx(full, rel=0.01)
    assert len(notes) == 1 and f"the 3-D alpha shape is measured on {kept.shape[0]:,} of the 12,000" in notes[0]


def test_info_says_when_the_crown_was_thinned(tmp_path, monkeypatch, capsys):
    from bforest_core import attributes as A
    from bforest_core.cli.main import main
    from bforest_core.io import write_tree

    write_tree(_comb(trunk=200, per=49), tmp_path / "comb.txt")
    monkeypatch.setitem(A.ALPHA_POINTS, 3, 2_000)
    assert main(["info", str(tmp_path / "comb.txt")]) == 0
    out = capsys.readouterr().out
    assert "    note: the 3-D alpha shape is measured on " in out and "docs/tree-attributes.md" in out
    assert "2-D alpha shape is measured" not in out  # the projection's 100 000 points are not reached
