"""Classical metrics (docs/features-and-distance.md §5): height, girth/DBH, crown spread, relative errors."""

import numpy as np
import pytest

import bforest_core as bf
from bforest_core import Tree
from bforest_core.metrics import crown_spread, dbh
from conftest import hand_tree, read_sample

S60 = np.sin(np.radians(60))


def test_hand_tree_height_girth_dbh():
    m = bf.classical_metrics(hand_tree())
    assert m["height"] == pytest.approx(3.0, abs=1e-12)
    assert m["girth"] == pytest.approx(0.40, abs=1e-12)  # 2 x root radius
    assert m["dbh"] == pytest.approx(0.30, abs=1e-12)  # trunk cylinder 1 spans z = 1.3
    assert bf.classical_metrics(hand_tree(), girth="dbh")["girth"] == pytest.approx(0.30, abs=1e-12)


def test_hand_tree_crown_spread_by_sectors():
    # points off the vertical: A ends at rho 0.8 sin60 and 1.3 sin60 (phi 0), B at 0.6 (phi 90),
    # C at 0.6 (phi 180 -> sector 0, half-open sectors)
    spokes = [1.3 * S60, 0.6, 0.6]
    assert crown_spread(hand_tree()) == pytest.approx(2 * sum(spokes) / 36, abs=1e-12)
    assert crown_spread(hand_tree(), empty_sectors="drop") == pytest.approx(2 * sum(spokes) / 3, abs=1e-12)
    assert crown_spread(hand_tree(), spoke_step=90) == pytest.approx(2 * sum(spokes) / 4, abs=1e-12)
    # with 180-degree sectors phi = 0 and phi = 90 share sector 1, phi = 180 is sector 0
    assert crown_spread(hand_tree(), spoke_step=180) == pytest.approx(2 * (1.3 * S60 + 0.6) / 2, abs=1e-12)


def test_sector_edges_and_centre():
    # one horizontal twig per direction, about a base point away from the origin
    base = np.array([5.0, -3.0, 2.0])
    dirs = np.radians([-180, -170, 0, 10, 95])
    n = dirs.size
    start = np.vstack([base, np.repeat(base[None] + [0, 0, 1], n, axis=0)])
    axis = np.vstack([[0, 0, 1], np.column_stack([np.cos(dirs), np.sin(dirs), np.zeros(n)])])
    t = Tree(start, axis, [1] + [1.0] * n, [0.1] + [0.01] * n, [-1] + [0] * n)
    # the toolbox measured angles about the origin; here about the base point -> 5 filled sectors
    assert crown_spread(t, empty_sectors="drop") == pytest.approx(2.0, abs=1e-12)
    assert crown_spread(t) == pytest.approx(2 * 5 / 36, abs=1e-12)
    m = bf.classical_metrics(t)
    assert m["height"] == pytest.approx(1.0)
    assert m["girth"] == pytest.approx(0.2)


def test_translation_invariant():
    a = bf.classical_metrics(hand_tree())
    b = bf.classical_metrics(hand_tree().translated([10, -4, 3]))
    assert a == pytest.approx(b, abs=1e-12)


def test_dbh_missing_warns_and_is_nan():
    t = Tree([[0, 0, 0]], [[0, 0, 1]], [1.0], [0.1], [-1])
    with pytest.warns(RuntimeWarning, match="breast height"):
        m = bf.classical_metrics(t, girth="dbh")
    assert np.isnan(m["girth"]) and np.isnan(m["dbh"])
    assert np.isnan(dbh(t, warn=False))
    assert bf.classical_metrics(t)["girth"] == pytest.approx(0.2)  # base girth needs no DBH
    assert crown_spread(t) == 0.0  # no point off the vertical


def test_bad_options():
    with pytest.raises(ValueError, match="divisor"):
        crown_spread(hand_tree(), spoke_step=7)
    with pytest.raises(ValueError):
        crown_spread(hand_tree(), empty_sectors="skip")
    with pytest.raises(ValueError):
        bf.classical_metrics(hand_tree(), girth="bh")


def test_relative_errors():
    d = {"height": 10.0, "girth": 0.5, "crown_spread": 4.0}
    m = {"height": 9.2, "girth": 0.6, "crown_spread": 6.0}
    r = bf.relative_errors(d, m)
    assert r == pytest.approx({"d_h": 0.08, "d_g": 0.2, "d_c": 0.5})
    clones = {"height": [10.0, 12.0], "girth": [0.5, 0.25], "crown_spread": [4.0, 2.0]}
    r = bf.relative_errors(d, clones)
    np.testing.assert_allclose(r["d_h"], [0, 0.2])
    np.testing.assert_allclose(r["d_g"], [0, 0.5])
    with pytest.raises(KeyError, match="crown_spread"):
        bf.relative_errors({"height": 1, "girth": 1}, m)


# ------------------------------------------------------------------------------ real data


@pytest.mark.parametrize(
    "name,h,g",
    [
        ("coffeetree_treeqsm_optqsm.mat", 3.72, 0.093),
        ("coffeetree_simpleforest.csv", 3.70, 0.094),
        ("coffeetree_archi.csv", 3.65, 0.086),
    ],
)
def test_real_coffee_tree_height_and_girth(name, h, g):
    m = bf.classical_metrics(read_sample(name))
    assert m["height"] == pytest.approx(h, abs=0.005)
    assert m["girth"] == pytest.approx(g, abs=0.0005)


def test_real_coffee_crown_spread():
    t = read_sample("coffeetree_treeqsm_optqsm.mat")
    assert crown_spread(t) == pytest.approx(1.35, abs=0.005)
    assert crown_spread(t, empty_sectors="drop") == pytest.approx(1.80, abs=0.005)
