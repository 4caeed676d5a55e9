"""Writers of the bforest_treeqsm and bforest_formats plugins: TreeQSM text, native CSV + JSON, .mat, PLY, OBJ.

Round trips: written and read back, a tree is the same to the written precision.
"""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

import bforest_core as bf
from bforest_core import QSMFormatError
from bforest_formats.writers import ORDER_PALETTE, cylinder_mesh
from bforest_treeqsm.writers import branch_table
from conftest import hand_tree, qsm_path

ROUND_TRIP_SAMPLES = [
    "itsme_qsm_tree_v240.mat",
    "coffeetree_treeqsm_optqsm.mat",
    "pine_ruotsinkyla_3.mat",
    "itsme_qsm_tree_v200.mat",
    "wytham_tf3.mat",
    "coffeetree_simpleforest.csv",
    "itsme_qsm_trunk.mat",
]


def read_quiet(path, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return bf.read_qsm(path, **kw)


# ------------------------------------------------------------------------------------------
# TreeQSM text
# ------------------------------------------------------------------------------------------


def test_treeqsm_text_layout_of_hand_tree(tmp_path):
    t = hand_tree()
    p = bf.write_tree(t, tmp_path / "cylinder_hand.txt")
    raw = p.read_bytes()
    assert b"\r" not in raw
    lines = raw.decode().split("\n")
    assert lines[0].split("\t") == [
        "radius (m)",
        "length (m)",
        "start_point",
        "axis_direction",
        "parent",
        "extension",
        "branch",
        "branch_order",
        "position_in_branch",
        "mad",
        "SurfCov",
        "added",
        "UnmodRadius (m)",
    ]
    rows = [ln.split("\t") for ln in lines[1:] if ln]
    assert len(rows) == 7 and all(len(r) == 17 for r in rows)
    # row 5 = second cylinder of lateral A: parent 4, no extension, branch 2, order 1, position 2
    r5 = rows[4]
    assert r5[8:13] == ["4", "0", "2", "1", "2"]
    assert r5[13:17] == ["0", "1", "0", "0.04"]  # mad 0, SurfCov 1, added 0, UnmodRadius = radius
    assert rows[4][5] == f"{np.sin(np.radians(60)):.9g}"
    assert rows[0][8:10] == ["0", "2"]  # root: parent 0 = none, extension 2 (1-based)
    back = read_quiet(p)
    assert back.equals(t, atol=1e-8)


@pytest.mark.parametrize("name", ROUND_TRIP_SAMPLES)
def test_treeqsm_text_round_trip(tmp_path, name):
    t = read_quiet(qsm_path(name))
    p = bf.write_tree(t, tmp_path / "cylinder_rt.txt")
    u = read_quiet(p)
    assert u.metadata["format"] == "treeqsm-text" and u.metadata["layout"] == "treeqsm17"
    assert u.n == t.n and u.equals(t, atol=1e-6)


def test_treeqsm_text_decimals(tmp_path):
    t = read_quiet(qsm_path("pine_ruotsinkyla_3.mat"))
    p = bf.write_tree(t, tmp_path / "d4.txt", decimals=4)
    v = np.loadtxt(p, skiprows=1)
    assert np.allclose(v[:, 0], np.round(t.radius, 4), atol=1e-12)
    assert np.array_equal(v[:, 0], np.round(v[:, 0], 4))
    u = read_quiet(p)
    assert u.equals(t, atol=2e-4)
    # the v2.4.0 .mat has a 2.5e-5 m cylinder: with 4 decimals it would be written as 0
    t40 = read_quiet(qsm_path("itsme_qsm_tree_v240.mat"))
    with pytest.raises(QSMFormatError, match=r"length of row \d+ \(2.54e-05 m\) rounds to 0 with decimals=4"):
        bf.write_tree(t40, tmp_path / "bad.txt", decimals=4)
    bf.write_tree(t40, tmp_path / "ok.txt", decimals=5)


def test_treeqsm15_struct_layout(tmp_path):
    t = read_quiet(qsm_path("coffeetree_treeqsm_optqsm.mat"))
    p = bf.write_tree(t, tmp_path / "archi_like.txt", layout="treeqsm15-struct")
    v = np.loadtxt(p)
    assert v.shape == (t.n, 15)
    assert np.array_equal(v[:, 12], t.branch + 1) and np.array_equal(v[:, 13], t.order)
    assert np.allclose(v[:, 11], t.extras["UnmodRadius"], atol=1e-9)
    u = read_quiet(p)
    assert u.metadata["layout"] == "treeqsm15-struct" and u.equals(t, atol=1e-6)


def test_branch_file(tmp_path):
    t = read_quiet(qsm_path("itsme_qsm_tree_v240_notria.mat"))
    bf.write_tree(t, tmp_path / "cylinder_x.txt", branch_file=True)
    p = tmp_path / "branch_x.txt"
    lines = p.read_text().split("\n")
    assert lines[0].split("\t")[:3] == ["order", "parent", "diameter (m)"]
    b = np.loadtxt(p, skiprows=1, ndmin=2)
    assert b.shape == (t.n_branches, 10) == (2, 10)
    assert b[:, 0].tolist() == [0, 1] and b[:, 1].tolist() == [0, 1]
    assert b[:, 3].sum() == pytest.approx(t.volume * 1000)
    assert b[:, 5].sum() == pytest.approx(t.length.sum())
    assert b[0, 2] == pytest.approx(2 * t.radius[0])
    bt = branch_table(t)
    assert bt[0, 7] == 0.0 and 0 < bt[1, 7] < 180


# ------------------------------------------------------------------------------------------
# native CSV
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ROUND_TRIP_SAMPLES)
def test_csv_round_trip_exact(tmp_path, name):
    t = read_quiet(qsm_path(name))
    p = bf.write_tree(t, tmp_path / "tree.csv")
    u = read_quiet(p)
    assert u.metadata["format"] == "bforest-csv"
    assert u.equals(t, atol=1e-12)
    assert np.array_equal(u.start, t.start) and np.array_equal(u.radius, t.radius)
    assert set(k for k in t.extras if not k.startswith("_")) <= set(u.extras)
    for k in u.extras:
        if k in t.extras:
            assert np.array_equal(u.extras[k], np.asarray(t.extras[k], dtype=float))


def test_csv_header_sidecar_and_topology(tmp_path):
    src = read_quiet(qsm_path("pine_ruotsinkyla_3.mat"))
    t = src.with_topology("subtree")
    t.metadata.update({"model": "sot", "params": {"a": 1.5}, "seed": 7})
    p = bf.write_tree(t, tmp_path / "clone.csv")
    header = p.read_text().split("\n", 1)[0].split(",")
    assert header[:18] == [
        "id",
        "parent",
        "extension",
        "branch",
        "order",
        "position_in_branch",
        "added",
        "start_x",
        "start_y",
        "start_z",
        "axis_x",
        "axis_y",
        "axis_z",
        "length",
        "radius",
        "end_x",
        "end_y",
        "end_z",
    ]
    assert "source_extension" in header
    side = json.loads((tmp_path / "clone.json").read_text())
    assert side["topology"] == "subtree" and side["units"] == "m" and side["format_version"] == 1
    assert side["seed"] == 7 and side["params"] == {"a": 1.5} and side["model"] == "sot"
    assert side["source"].endswith("pine_ruotsinkyla_3.mat")
    u = read_quiet(p)
    assert u.topology == "subtree" and u.equals(t, atol=1e-12)
    assert u.metadata["seed"] == 7 and u.metadata["original_source"].endswith("pine_ruotsinkyla_3.mat")
    assert u.with_topology("source").equals(src, atol=1e-12)
    assert u.with_topology("source").n_branches == 300
    # an explicit topology still wins
    assert read_quiet(p, topology="thickest").topology == "thickest"
    # end columns are start + length * axis
    v = np.loadtxt(p, delimiter=",", skiprows=1)
    assert np.allclose(v[:, 15:18], t.end, atol=1e-12)


# ------------------------------------------------------------------------------------------
# .mat
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "name",
    ["itsme_qsm_tree_v240.mat", "coffeetree_treeqsm_optqsm.mat", "pine_ruotsinkyla_1.mat", "itsme_qsm_trunk.mat"],
)
def test_mat_round_trip(tmp_path, name):
    import scipy.io as sio

    t = read_quiet(qsm_path(name))
    p = bf.write_tree(t, tmp_path / "out.mat")
    m = sio.loadmat(str(p), squeeze_me=True, struct_as_record=False)
    c = m["qsm"].cylinder
    assert set(c._fieldnames) >= {
        "radius",
        "length",
        "start",
        "axis",
        "parent",
        "extension",
        "added",
        "UnmodRadius",
        "branch",
        "SurfCov",
        "mad",
        "BranchOrder",
        "PositionInBranch",
    }
    assert c.parent[0] == 0 and c.branch.min() == 1 and np.atleast_1d(c.PositionInBranch)[0] == 1
    u = read_quiet(p)
    assert u.metadata["format"] == "treeqsm-mat" and u.equals(t, atol=1e-12)


def test_one_cylinder_tree_mat_and_text(tmp_path):
    one = bf.Tree([[0, 0, 0]], [[0, 0, 1]], [1.0], [0.1], [-1])
    for name in ("one.mat", "one.txt", "one.csv"):
        u = read_quiet(bf.write_tree(one, tmp_path / name))
        assert u.n == 1 and u.equals(one, atol=1e-9)


# ------------------------------------------------------------------------------------------
# meshes
# ------------------------------------------------------------------------------------------


def _read_ply(path):
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode().split("\n")
    nv = int(next(h for h in header if h.startswith("element vertex")).split()[-1])
    nf = int(next(h for h in header if h.startswith("element face")).split()[-1])
    ftype = "<f8" if "property double x" in header else "<f4"
    if "format ascii 1.0" in header:
        rows = data[end:].decode().split("\n")
        v = np.array([r.split() for r in rows[:nv]], dtype=float)
        f = np.array([r.split() for r in rows[nv : nv + nf]], dtype=np.int64)
        assert np.all(f[:, 0] == 3)
        return header, v[:, :3], v[:, 3:6].astype(np.uint8), f[:, 1:]
    vdt = np.dtype([("x", ftype), ("y", ftype), ("z", ftype), ("r", "u1"), ("g", "u1"), ("b", "u1")])
    vr = np.frombuffer(data, dtype=vdt, count=nv, offset=end)
    fdt = np.dtype([("n", "u1"), ("i", "<i4", (3,))])
    fr = np.frombuffer(data, dtype=fdt, count=nf, offset=end + nv * vdt.itemsize)
    assert end + nv * vdt.itemsize + nf * fdt.itemsize == len(data)
    assert np.all(fr["n"] == 3)
    v = np.column_stack([vr["x"], vr["y"], vr["z"]]).astype(float)
    col = np.column_stack([vr["r"], vr["g"], vr["b"]])
    return header, v, col, fr["i"].astype(np.int64)


def _check_mesh(tree, v, f, k, caps):
    n = tree.n
    per_face = 2 * k + (2 * (k - 2) if caps else 0)
    assert v.shape == (n * 2 * k, 3) and f.shape == (n * per_face, 3)
    # ring vertices at distance r from the axis line, bottom ring in the start plane
    vv = v.reshape(n, 2 * k, 3)
    rel = vv - tree.start[:, None, :]
    along = np.einsum("nvj,nj->nv", rel, tree.axis)
    radial = rel - along[:, :, None] * tree.axis[:, None, :]
    dist = np.linalg.norm(radial, axis=2)
    assert np.allclose(dist, tree.radius[:, None], rtol=1e-5, atol=1e-5)
    assert np.allclose(along[:, :k], 0, atol=1e-4)
    assert np.allclose(along[:, k:], tree.length[:, None], atol=1e-4)
    # outward orientation: side normals point away from the axis, caps along -a / +a
    ff = f.reshape(n, per_face, 3) - (np.arange(n) * 2 * k)[:, None, None]
    assert ff.min() >= 0 and ff.max() < 2 * k
    p0, p1, p2 = (np.take_along_axis(vv, ff[:, :, i : i + 1].repeat(3, axis=2), axis=1) for i in range(3))
    normal = np.cross(p1 - p0, p2 - p0)
    cen = (p0 + p1 + p2) / 3 - tree.start[:, None, :]
    cen_rad = cen - np.einsum("nfj,nj->nf", cen, tree.axis)[:, :, None] * tree.axis[:, None, :]
    side = np.einsum("nfj,nfj->nf", normal[:, : 2 * k], cen_rad[:, : 2 * k])
    assert np.all(side > 0)
    if caps:
        top = np.einsum("nfj,nj->nf", normal[:, 2 * k : 3 * k - 2], tree.axis)
        bottom = np.einsum("nfj,nj->nf", normal[:, 3 * k - 2 :], tree.axis)
        assert np.all(top > 0) and np.all(bottom < 0)
        # Euler characteristic V - E + F = 2 for every closed cylinder
        edges = np.sort(np.concatenate([ff[0][:, [0, 1]], ff[0][:, [1, 2]], ff[0][:, [2, 0]]]), axis=1)
        E = np.unique(edges, axis=0).shape[0]
        assert 2 * k - E + per_face == 2
        # closed and consistently oriented: every directed edge appears once, its reverse once
        d = np.concatenate([ff[0][:, [0, 1]], ff[0][:, [1, 2]], ff[0][:, [2, 0]]])
        assert np.unique(d, axis=0).shape[0] == d.shape[0]
        assert {tuple(e) for e in d} == {tuple(e[::-1]) for e in d}


def test_ply_binary_default(tmp_path):
    t = read_quiet(qsm_path("itsme_qsm_tree_v240_notria.mat"))
    p = bf.write_tree(t, tmp_path / "tree.ply")
    header, v, col, f = _read_ply(p)
    assert header[1] == "format binary_little_endian 1.0"
    _check_mesh(t, v, f, 12, caps=True)
    assert np.array_equal(col, np.repeat(ORDER_PALETTE[t.order % len(ORDER_PALETTE)], 24, axis=0))


def test_ply_ascii_matches_binary(tmp_path):
    t = hand_tree()
    _, vb, cb, fb = _read_ply(bf.write_tree(t, tmp_path / "b.ply", sides=5, caps=False, color_by="radius"))
    header, va, ca, fa = _read_ply(
        bf.write_tree(t, tmp_path / "a.ply", format="ply", ascii=True, sides=5, caps=False, color_by="radius")
    )
    assert header[1] == "format ascii 1.0"
    assert np.allclose(va, vb, atol=1e-6) and np.array_equal(fa, fb) and np.array_equal(ca, cb)
    _check_mesh(t, va, fa, 5, caps=False)
    # radius colouring: thickest (root) and thinnest get the ramp ends
    assert tuple(ca[0]) == (110, 70, 40) and tuple(ca[-1]) == (150, 220, 90)


def test_mesh_options(tmp_path):
    t = hand_tree()
    v, f, fc = cylinder_mesh(t, sides=3, caps=True, min_radius=0.1, translate_to_base=True)
    assert f.shape == (7 * (6 + 2), 3)
    rel = v.reshape(7, 6, 3)[:, :3] - (t.start - t.start[0])[:, None, :]
    assert np.allclose(np.linalg.norm(rel, axis=2), np.maximum(t.radius, 0.1)[:, None])
    with pytest.raises(bf.ConfigError, match="sides"):
        bf.write_tree(t, tmp_path / "x.ply", sides=2)


def test_obj_groups_by_order(tmp_path):
    t = read_quiet(qsm_path("itsme_qsm_tree_v200.mat"))
    p = bf.write_tree(t, tmp_path / "tree.obj", sides=6)
    lines = p.read_text().split("\n")
    verts = np.array([ln.split()[1:] for ln in lines if ln.startswith("v ")], dtype=float)
    faces = np.array([ln.split()[1:] for ln in lines if ln.startswith("f ")], dtype=np.int64)
    groups = [ln for ln in lines if ln.startswith("g ")]
    assert groups == [f"g order_{w}" for w in range(t.max_order + 1)]
    assert verts.shape == (t.n * 12, 3) and faces.shape == (t.n * (12 + 8), 3)
    assert faces.min() == 1 and faces.max() == verts.shape[0]
    # the faces of group "order_0" belong to trunk cylinders only
    g0 = lines.index("g order_0")
    g1 = lines.index("g order_1")
    trunk_faces = np.array([ln.split()[1:] for ln in lines[g0 + 1 : g1]], dtype=np.int64) - 1
    assert np.all(t.order[trunk_faces // 12] == 0)


def test_write_by_format_name_and_unknown_suffix(tmp_path):
    t = hand_tree()
    p = bf.write_tree(t, tmp_path / "x.dat", format="treeqsm-mat")
    import scipy.io as sio

    assert "qsm" in sio.whosmat(str(p))[0]
    with pytest.raises(QSMFormatError, match="no writer for '.stl'"):
        bf.write_tree(t, tmp_path / "x.stl")
