"""Synthetic laser scans: points on the cylinder surfaces, LAS/XYZ files with the true structure."""

import numpy as np
import pytest

import bforest_core as bf
from bforest_formats.scan import scan_points
from conftest import hand_tree, read_sample


def _one_cylinder(r=0.1, L=2.0):
    return bf.Tree([[1.0, 2.0, 0.5]], [[0, 0, 1.0]], [L], [r], [-1])


def _surface_distance(tree, pts):
    """Distance of each point to the lateral surface of its own cylinder."""
    c = pts["cylinder_id"]
    d = pts["xyz"] - tree.start[c]
    along = np.einsum("ij,ij->i", d, tree.axis[c])
    radial = np.linalg.norm(d - along[:, None] * tree.axis[c], axis=1)
    return radial - tree.radius[c], along


def test_uniform_density_and_surface():
    t = _one_cylinder()
    pts = scan_points(t, density=3000, noise=0.002, seed=3)
    lam = 3000 * 2 * np.pi * 0.1 * 2.0
    assert abs(len(pts["xyz"]) - lam) < 4 * np.sqrt(lam)
    off, along = _surface_distance(t, pts)
    assert np.abs(off).max() < 5 * 0.002 and abs(off.std() - 0.002) < 0.0003
    assert along.min() >= 0 and along.max() <= 2.0
    again = scan_points(t, density=3000, noise=0.002, seed=3)
    assert np.array_equal(pts["xyz"], again["xyz"])
    assert not np.array_equal(pts["xyz"], scan_points(t, density=3000, noise=0.002, seed=4)["xyz"][: len(pts["xyz"])])


def test_points_of_a_real_pine_lie_on_their_cylinders():
    t = read_sample("pine_ruotsinkyla_3.mat")
    pts = scan_points(t, density=500, seed=1)
    off, along = _surface_distance(t, pts)
    assert np.abs(off).max() < 1e-3 and (along >= -1e-9).all() and (along <= t.length[pts["cylinder_id"]] + 1e-9).all()
    assert np.array_equal(pts["branch_order"], t.order[pts["cylinder_id"]])


def test_scanner_mode_sees_only_the_near_side():
    t = _one_cylinder(r=0.2, L=1.0)
    pts = scan_points(t, density=5000, mode="scanner", scanner=(1.0, -8.0, 1.0), seed=2)
    y = pts["xyz"][:, 1] - 2.0
    assert len(y) > 100 and (y < 1e-9).all()  # the scanner is at -y: nothing on the far (+y) side
    # grazing surfaces get fewer points than the face towards the scanner
    facing = np.abs(pts["normal"][:, 1]) > 0.9
    grazing = np.abs(pts["normal"][:, 1]) < 0.3
    assert facing.sum() > 2 * grazing.sum()


def test_las_file_holds_the_points_and_extra_dimensions(tmp_path):
    laspy = pytest.importorskip("laspy")
    t = hand_tree()
    p = bf.write_tree(t, tmp_path / "tree.las", density=4000, seed=5)
    las = laspy.read(p)
    pts = scan_points(t, density=4000, seed=5)
    assert len(las.points) == len(pts["xyz"]) > 1000 and las.header.version == "1.4"
    assert {"cylinder_id", "branch_id", "branch_order"} <= set(las.point_format.extra_dimension_names)
    assert np.array_equal(np.asarray(las.cylinder_id), pts["cylinder_id"])
    assert np.array_equal(np.asarray(las.branch_order), t.order[pts["cylinder_id"]])
    xyz = np.column_stack([las.x, las.y, las.z])
    assert np.abs(xyz - pts["xyz"]).max() <= 0.0005 + 1e-9  # mm precision


def test_xyz_file_and_bad_settings(tmp_path):
    t = hand_tree()
    p = bf.write_tree(t, tmp_path / "tree.xyz", density=500, seed=1)
    rows = np.loadtxt(p)
    assert rows.shape[1] == 6 and rows.shape[0] == len(scan_points(t, density=500, seed=1)["xyz"])
    with pytest.raises(bf.ConfigError, match="density"):
        bf.write_tree(t, tmp_path / "bad.xyz", density=-1)
    with pytest.raises(bf.ConfigError, match="mode"):
        bf.write_tree(t, tmp_path / "bad.xyz", mode="drone")


def test_laz_round_trip(tmp_path):
    laspy = pytest.importorskip("laspy")
    t = hand_tree()
    p = bf.write_tree(t, tmp_path / "tree.laz", density=2000, seed=2)
    las = laspy.read(p)
    assert len(las.points) == len(scan_points(t, density=2000, seed=2)["xyz"])
    assert p.stat().st_size < bf.write_tree(t, tmp_path / "tree.las", density=2000, seed=2).stat().st_size
