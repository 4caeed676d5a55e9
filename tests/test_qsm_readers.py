"""QSM readers (plugins bforest_treeqsm and bforest_formats) on the real samples and on small hand-made bad files.

Known numbers come from docs/qsm-formats.md (the sample files of §11 and the formats; cylinder
counts, branch counts, heights) or are read independently from the raw file in the test.
Branch counts are under the file's own (``source``) topology after fragment removal.
"""

from __future__ import annotations

import re
import shutil
import warnings

import numpy as np
import pytest

import bforest_core as bf
from bforest_core import QSMFormatError, Tree, cylinders
from bforest_core.cylinders import QSMReadWarning
from bforest_core.tree import remap_ids
from conftest import hand_tree, qsm_path


def read_quiet(path, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return bf.read_qsm(path, **kw)


def height(t: Tree) -> float:
    """Data README definition: highest start/end z minus the root's start z (unit axes)."""
    return float(max(t.start[:, 2].max(), t.end[:, 2].max()) - t.start[0, 2])


# name, reader, cylinders, branches, height (m, README), first radius (as stored), version
SAMPLES = [
    ("archi_tree1_treeqsm_v23.txt", "treeqsm-text", 2271, 233, 22.04, 0.2469613, "2.3.x"),
    ("coffeetree_archi.csv", "archi-csv", 1231, 121, 3.65, 0.042817738, None),
    ("coffeetree_simpleforest.csv", "simpleforest-csv", 1149, 69, 3.70, 0.047199, None),
    ("coffeetree_treeqsm_optqsm.mat", "treeqsm-mat", 1136, 82, 3.72, 0.046467911, "2.4.1"),
    ("itsme_qsm_tree_v200.mat", "treeqsm-flat", 115, 23, 5.44, 0.025375254, "2.0"),
    ("itsme_qsm_tree_v230.mat", "treeqsm-mat", 88, 3, 20.80, 0.079175822, "2.3.x"),
    ("itsme_qsm_tree_v230_notria.mat", "treeqsm-mat", 1807, 242, 28.12, 0.61286062, "2.3.x"),
    ("itsme_qsm_tree_v240.mat", "treeqsm-mat", 3780, 410, 28.40, 0.43681055, "2.4.0"),
    ("itsme_qsm_tree_v240_notria.mat", "treeqsm-mat", 66, 2, 20.94, 0.08678285, "2.4.0"),
    ("itsme_qsm_trunk.mat", "treeqsm-mat", 48, 1, 24.01, 0.43681055, "2.4.0"),
    ("itsme_qsms_tree_v230.mat", "treeqsm-mat", 110, 3, 21.02, 0.079904705, "2.3.x"),
    ("itsme_qsms_tree_v240_notria.mat", "treeqsm-mat", 66, 2, 20.94, 0.08678285, "2.4.0"),
    ("itsme_tree_v240_cylinder.txt", "treeqsm-text", 3779, 410, 28.40, 0.4368, "2.4.x"),
    ("pine_ruotsinkyla_1.mat", "treeqsm-flat", 2726, 805, 13.28, 0.101315, None),
    ("pine_ruotsinkyla_2.mat", "treeqsm-flat", 2248, 587, 11.05, 0.0527325, None),
    ("pine_ruotsinkyla_3.mat", "treeqsm-flat", 876, 300, 9.94, 0.0578074, None),
    ("wytham_tf1.mat", "cyldata-mat", 2498, 1136, 18.29, 0.33680001, None),
    ("wytham_tf2.mat", "cyldata-mat", 1192, 483, 17.41, 0.20127679, None),
    ("wytham_tf3.mat", "cyldata-mat", 590, 272, 17.85, 0.11565076, None),
    ("wytham_tf4.mat", "cyldata-mat", 1647, 631, 19.65, 0.18385166, None),
    ("wytham_tf5.mat", "cyldata-mat", 1276, 510, 19.81, 0.2085, None),
]


@pytest.mark.parametrize("name,reader,n,nb,h,r0,version", SAMPLES, ids=[s[0] for s in SAMPLES])
def test_sample_counts_and_known_values(name, reader, n, nb, h, r0, version):
    p = qsm_path(name)
    t = read_quiet(p)
    assert isinstance(t, Tree)
    assert t.metadata["format"] == reader
    assert t.n == n
    assert t.n_branches == nb
    assert height(t) == pytest.approx(h, abs=0.006)
    assert t.radius[0] == pytest.approx(r0, rel=5e-8)
    assert t.metadata["version"] == version
    md = t.metadata
    assert md["source"] == str(p) and md["units"] == "m" and md["topology"] == "source"
    assert "repairs" in md and md["model_index"] == 0
    # the same reader, chosen by name, gives the same tree
    assert read_quiet(p, reader=reader).equals(t)
    assert np.allclose(np.linalg.norm(t.axis, axis=1), 1.0, atol=1e-12)


def test_repeated_reconstructions_select():
    p = qsm_path("itsme_qsms_tree_v230.mat")
    with pytest.warns(QSMReadWarning, match=r"holds 4 reconstructions \(QSMs 1x4\); using select=0"):
        t = bf.read_qsm(p)
    assert "holds 4 reconstructions" in t.metadata["select_note"]
    trees = bf.read_qsm(p, select="all")
    assert [x.n for x in trees] == [110, 102, 106, 102]  # README
    assert [x.metadata["model_index"] for x in trees] == [0, 1, 2, 3]
    assert [round(height(x), 2) for x in trees] == [21.02, 21.04, 20.99, 20.89]  # 20.89-21.04
    two = bf.read_qsm(p, select=[2, 0])
    assert [x.n for x in two] == [106, 110]
    assert bf.read_qsm(p, select=2).n == 106
    with pytest.raises(QSMFormatError, match=r"select=4 is outside 0\.\.\.3.*QSMs\(5\)"):
        bf.read_qsm(p, select=4)
    ten = bf.read_qsm(qsm_path("itsme_qsms_tree_v240_notria.mat"), select="all")
    assert [x.n for x in ten] == [66, 73, 68, 69, 66, 66, 63, 69, 68, 68]  # README
    # a 1x1 QSMs: no warning, and "all" gives a one-element list
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert bf.read_qsm(qsm_path("itsme_qsm_tree_v230.mat")).n == 88
    assert [x.n for x in bf.read_qsm(qsm_path("itsme_qsm_tree_v230.mat"), select="all")] == [88]


def test_fragments_dropped_with_one_warning_and_recorded():
    p = qsm_path("itsme_qsm_tree_v240.mat")
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        t = bf.read_qsm(p)
    msgs = [str(w.message) for w in rec if issubclass(w.category, QSMReadWarning)]
    assert len(msgs) == 1
    assert "6 cylinders have no parent (rows 1, 3020, 3582, 3648, 3718, 3770)" in msgs[0]
    assert "(3780 of 3791 cylinders)" in msgs[0]
    rep = t.metadata["repairs"][0]
    assert rep["repair"] == "dropped_fragments" and rep["n_dropped"] == 11 and rep["stem_base_row"] == 1
    assert set(rep["dropped_rows"]).isdisjoint((t.source_row + 1).tolist())
    assert 3020 in rep["dropped_rows"] and len(rep["dropped_rows"]) == 11
    with pytest.raises(QSMFormatError, match="6 cylinders have no parent") as ei:
        bf.read_qsm(p, fragments="error")
    assert ei.value.rows == [1, 3020, 3582, 3648, 3718, 3770]


def test_text_zero_length_row_removed_and_children_reattached():
    p = qsm_path("itsme_tree_v240_cylinder.txt")
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        t = bf.read_qsm(p)
    msgs = [str(w.message) for w in rec if issubclass(w.category, QSMReadWarning)]
    assert len(msgs) == 2 and "zero-length cylinder (row 1005" in msgs[1]
    assert [r["repair"] for r in t.metadata["repairs"]] == ["dropped_fragments", "removed_zero_length"]
    assert 1004 not in t.source_row
    raw = np.loadtxt(p, skiprows=1)
    assert raw.shape == (3791, 17) and raw[1004, 1] == 0.0
    par = int(raw[1004, 8]) - 1  # 0-based file row of the removed cylinder's parent
    kids = np.flatnonzero(raw[:, 8] == 1005)
    assert kids.size >= 1
    row_of = {int(s): i for i, s in enumerate(t.source_row)}
    for k in kids:
        assert t.parent[row_of[int(k)]] == row_of[par]
    if int(raw[par, 9]) == 1005:  # it was its parent's extension: its own extension takes over
        assert t.extension[row_of[par]] == row_of[int(raw[1004, 9]) - 1]
    with (
        pytest.raises(QSMFormatError, match=r"length <= 0 at row 1005 \(value 0; TreeQSM text rounds"),
        pytest.warns(QSMReadWarning, match="6 cylinders have no parent"),
    ):
        bf.read_qsm(p, drop_degenerate=False)


def test_text_matches_mat_to_the_rounding():
    a = read_quiet(qsm_path("itsme_qsm_tree_v240.mat"))
    b = read_quiet(qsm_path("itsme_tree_v240_cylinder.txt"))
    row_of = {int(s): i for i, s in enumerate(a.source_row)}
    ia = np.array([row_of[int(s)] for s in b.source_row])
    assert np.allclose(a.radius[ia], b.radius, atol=5.1e-5)
    assert np.allclose(a.start[ia], b.start, atol=5.1e-5)
    assert np.allclose(a.axis[ia], b.axis, atol=2e-4)
    assert np.array_equal(a.order[ia], b.order)
    assert np.allclose(b.extras["UnmodRadius"], np.round(a.extras["UnmodRadius"][ia], 4), atol=1e-9)


def test_uint8_ids_are_cast_before_subtracting():
    import scipy.io as sio

    p = qsm_path("itsme_qsm_tree_v200.mat")
    raw = sio.loadmat(str(p), variable_names=["CPar", "BoC"])
    assert raw["CPar"].dtype == np.uint8  # the pitfall is real
    t = read_quiet(p)
    assert t.parent.dtype == np.int64 and t.parent[0] == -1 and t.parent.max() < t.n
    assert np.array_equal(t.order, raw["BoC"][:, 1].astype(np.int64)[t.source_row])


def test_ruotsinkyla_orders_from_bord_and_topologies():
    import h5py

    p = qsm_path("pine_ruotsinkyla_3.mat")
    t = read_quiet(p)
    with h5py.File(p, "r") as f:
        boc = f["BoC"][()].ravel().astype(np.int64)
        bord = f["BOrd"][()].ravel().astype(np.int64)
        added = f["Added"][()].ravel()
    assert np.array_equal(t.order, bord[boc - 1][t.source_row])
    assert len(np.unique(boc)) == t.n_branches == 300
    assert 0.24 <= added.mean() <= 0.28 and t.added.sum() == int(added.sum())
    assert t.metadata["out_fn"] == "pine_Ruotsinkyla_tree3_model1.mat"
    sub = read_quiet(p, topology="subtree")
    assert sub.topology == "subtree" and sub.n_branches < 300
    assert sub.with_topology("source").equals(t, atol=1e-12)
    # docs/features-and-distance.md §1.1: the thickest rule inflates orders on pine 1 (12 instead of 6)
    t1 = read_quiet(qsm_path("pine_ruotsinkyla_1.mat"))
    assert t1.max_order == 6
    assert read_quiet(qsm_path("pine_ruotsinkyla_1.mat"), topology="thickest").max_order == 12


def test_wytham_axes_renormalised_and_branch_gaps_relabelled():
    import scipy.io as sio

    p = qsm_path("wytham_tf1.mat")
    with pytest.warns(QSMReadWarning, match=r"278 axes not unit vectors"):
        t = bf.read_qsm(p)
    d = sio.loadmat(str(p))["CylData_updated"]
    assert len(np.unique(d[:, 10])) == t.n_branches == 1136 and d[:, 10].max() == 1733
    assert t.metadata["repairs"][0]["n_rows"] == 278
    assert np.allclose(np.linalg.norm(t.axis, axis=1), 1.0)
    # direction kept: renormalised axis is parallel to the stored one
    raw_axis = d[:, 5:8].astype(np.float64)
    assert np.allclose(t.axis, raw_axis / np.linalg.norm(raw_axis, axis=1)[:, None])


def test_simpleforest_ids_extension_and_extras():
    p = qsm_path("coffeetree_simpleforest.csv")
    t = read_quiet(p)
    data = np.genfromtxt(p, delimiter=",", names=True)
    bo = data["branchOrder"].astype(int)
    assert np.array_equal(t.order, bo[t.source_row])  # order = branchOrder (0 = trunk)
    assert t.extras["growthLength"][0] == pytest.approx(31.426363)
    assert "averagePointDistance" in t.extras and "reverseBranchOrder" in t.extras
    assert not t.added.any()
    ch = np.bincount(t.parent[t.parent >= 0], minlength=t.n)
    forks = np.flatnonzero(ch >= 2)
    th = t.with_topology("thickest")
    assert (
        forks.size == 64 and np.count_nonzero(th.extension[forks] != t.extension[forks]) == 17
    )  # docs/qsm-formats.md §6


def test_archi_ids_orders_and_untrusted_extension_id():
    p = qsm_path("coffeetree_archi.csv")
    t = read_quiet(p)
    data = np.genfromtxt(p, delimiter=",", names=True)
    assert np.array_equal(t.order, data["branching_order"].astype(int)[t.source_row] - 1)
    assert len(np.unique(data["axis_ID"])) == t.n_branches
    assert t.metadata["extension_ID_disagreements"] == 64  # docs/qsm-formats.md §7
    assert t.extras["volume"][0] == pytest.approx(np.pi * t.radius[0] ** 2 * t.length[0], rel=1e-6)


def test_struct_extras_versions_and_empty_branch_entries():
    t = read_quiet(qsm_path("coffeetree_treeqsm_optqsm.mat"))
    assert {"UnmodRadius", "SurfCov", "mad"} <= set(t.extras)
    assert t.metadata["variable"] == "OptQSM"
    assert t.start[0] == pytest.approx(
        [0.768, -16.361, 253.887], abs=1e-3
    )  # file frame kept (docs/qsm-formats.md §0: 0.76, -16.36, 253.9)
    t23 = read_quiet(qsm_path("itsme_qsm_tree_v230_notria.mat"))
    assert "SurfCov" not in t23.extras and t23.metadata["version"] == "2.3.x"
    trunk = read_quiet(qsm_path("itsme_qsm_trunk.mat"))
    assert trunk.n_branches == 1 and trunk.max_order == 0


def test_detection_is_by_content_not_suffix(tmp_path):
    src = qsm_path("archi_tree1_treeqsm_v23.txt")
    dat = tmp_path / "renamed.dat"
    shutil.copy(src, dat)
    assert read_quiet(dat).metadata["layout"] == "treeqsm15-struct"
    m = tmp_path / "anything.mat"
    shutil.copy(qsm_path("wytham_tf3.mat"), m)
    assert read_quiet(m).metadata["format"] == "cyldata-mat"


# ------------------------------------------------------------------------------------------
# MAT v7.3 structs written with h5py (no sample exists)
# ------------------------------------------------------------------------------------------


def _mat73_header(path):
    hdr = b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: Mon Jan  1 00:00:00 2024 HDF5 schema 1.00 ."
    hdr = hdr.ljust(116, b" ") + b"\x00" * 8 + b"\x00\x02" + b"IM"
    with open(path, "r+b") as fh:
        fh.write(hdr.ljust(512, b"\x00"))


def _h5_cylinder(group, tree):
    """MATLAB n x k arrays appear transposed (k x n) in HDF5."""
    one = lambda a: np.where(a >= 0, a + 1, 0).astype(np.float64)
    fields = {
        "radius": tree.radius,
        "length": tree.length,
        "start": tree.start,
        "axis": tree.axis,
        "parent": one(tree.parent),
        "extension": one(tree.extension),
        "added": tree.added.astype(np.float64),
        "branch": tree.branch + 1.0,
        "BranchOrder": tree.order.astype(np.float64),
        "UnmodRadius": tree.radius * 1.01,
    }
    group.attrs["MATLAB_class"] = np.bytes_("struct")
    for k, v in fields.items():
        ds = group.create_dataset(k, data=np.asarray(v, dtype=np.float64).reshape(tree.n, -1).T)
        ds.attrs["MATLAB_class"] = np.bytes_("double")


def _h5_char(group, name, text):
    ds = group.create_dataset(name, data=np.array([[ord(c)] for c in text], dtype=np.uint16))
    ds.attrs["MATLAB_class"] = np.bytes_("char")
    ds.attrs["MATLAB_int_decode"] = np.int32(2)


def test_mat73_struct_and_struct_array_written_with_h5py(tmp_path):
    import h5py

    a = hand_tree()
    b = read_quiet(qsm_path("itsme_qsm_tree_v240_notria.mat"))
    p = tmp_path / "qsm73.mat"
    with h5py.File(p, "w", userblock_size=512) as f:
        q = f.create_group("qsm")
        q.attrs["MATLAB_class"] = np.bytes_("struct")
        _h5_cylinder(q.create_group("cylinder"), b)
        rd = q.create_group("rundata")
        _h5_char(rd, "version", "2.4.1")
    _mat73_header(p)
    t = bf.read_qsm(p)
    assert t.metadata["format"] == "treeqsm-mat" and t.metadata["container"] == "MAT v7.3 (HDF5)"
    assert t.metadata["version"] == "2.4.1"
    assert t.equals(b, atol=1e-12)
    assert np.allclose(t.extras["UnmodRadius"], b.radius * 1.01)

    # a 1x2 struct array QSMs: every field is a (2 x 1) dataset of object references
    p2 = tmp_path / "qsms73.mat"
    with h5py.File(p2, "w", userblock_size=512) as f:
        refs = f.create_group("#refs#")
        cyl_refs = []
        for i, tr in enumerate((a, b)):
            g = refs.create_group(f"c{i}")
            _h5_cylinder(g, tr)
            cyl_refs.append(g.ref)
        top = f.create_group("QSMs")
        top.attrs["MATLAB_class"] = np.bytes_("struct")
        top.create_dataset("cylinder", data=np.array(cyl_refs, dtype=h5py.ref_dtype).reshape(2, 1))
    _mat73_header(p2)
    with pytest.warns(QSMReadWarning, match="holds 2 reconstructions"):
        first = bf.read_qsm(p2)
    assert first.equals(a, atol=1e-12)
    both = bf.read_qsm(p2, select="all")
    assert [x.n for x in both] == [7, 66] and both[1].equals(b, atol=1e-12)
    assert both[0].metadata["version"] == "2.3.x"  # no rundata, no SurfCov/mad


# ------------------------------------------------------------------------------------------
# bad input (docs/qsm-formats.md §10) on small files
# ------------------------------------------------------------------------------------------


def _write_text17(path, tree, mutate=None):
    """The hand tree as a TreeQSM 17-column text file, with an optional row mutation."""
    bf.write_tree(tree, path)
    lines = path.read_text().split("\n")
    if mutate:
        mutate(lines)
    path.write_text("\n".join(lines))
    return path


def _set(lines, row, col, value):
    """Set 1-based data ``row``, 1-based ``col`` of a 17-column text (line = row + 1)."""
    f = lines[row].split("\t")
    f[col - 1] = str(value)
    lines[row] = "\t".join(f)


def test_every_text_layout_names_the_bad_column_by_its_number(tmp_path):
    """The layouts share one column table (bforest_treeqsm.columns): a NaN flag or a fractional
    order is reported with the column's number in that layout, in text and in a CylData .mat."""
    import scipy.io as sio

    t = hand_tree()
    cyl = np.column_stack(
        [t.radius, t.length, t.start, t.axis, t.parent + 1, t.extension + 1, t.branch + 1, t.order]
        + [t.position_in_branch + 1, t.added]
    )
    for col, value, words in (
        (13, np.nan, "non-finite values in '{}column 14 (added)'"),
        (11, 0.5, "'{}column 12 (branch order)'"),
    ):
        bad = cyl.copy()
        bad[2, col] = value
        np.savetxt(tmp_path / "c14.txt", bad, fmt="%.9g")
        sio.savemat(tmp_path / "c14.mat", {"CylData": bad})
        for name, label in (("c14.txt", ""), ("c14.mat", "CylData ")):
            with pytest.raises(QSMFormatError) as ei:
                bf.read_qsm(tmp_path / name)
            assert words.format(label) in str(ei.value) and ei.value.rows == [3], str(ei.value)
    np.savetxt(tmp_path / "c14.txt", cyl, fmt="%.9g")
    assert bf.read_qsm(tmp_path / "c14.txt").equals(t, atol=1e-8)


def test_unsupported_suffix_and_wrong_content(tmp_path):
    p = tmp_path / "tree.xyz"
    p.write_text("1 2 3\n")
    with pytest.raises(QSMFormatError, match=r"unsupported file type '\.xyz' \(supported: .*\.mat"):
        bf.read_qsm(p)
    m = tmp_path / "csv_in_disguise.mat"
    m.write_text("a,b,c\n1,2,3\n")
    with pytest.raises(QSMFormatError, match="content looks like CSV text, not a MAT-file"):
        bf.read_qsm(m)
    import scipy.io as sio

    m2 = tmp_path / "other.mat"
    sio.savemat(str(m2), {"P": np.zeros((5, 3)), "foo": np.ones(3)})
    with pytest.raises(QSMFormatError, match=r"no QSM variables found \(present: P, foo\)"):
        bf.read_qsm(m2)
    t = tmp_path / "twelve.txt"
    t.write_text("\n".join(" ".join(["1"] * 12) for _ in range(3)) + "\n")
    with pytest.raises(QSMFormatError, match="12 columns per row; expected 14, 15 or 17"):
        bf.read_qsm(t)
    b = tmp_path / "binary.txt"
    shutil.copy(qsm_path("wytham_tf3.mat"), b)
    with pytest.raises(QSMFormatError, match="content looks like a MAT-file, not text"):
        bf.read_qsm(b)


def test_truncated_containers(tmp_path):
    for name, label in (
        ("coffeetree_treeqsm_optqsm.mat", "MAT v5 reader"),
        ("pine_ruotsinkyla_3.mat", "MAT v7.3/HDF5 reader"),
    ):
        data = qsm_path(name).read_bytes()
        p = tmp_path / ("half_" + name)
        p.write_bytes(data[: len(data) // 2])
        with pytest.raises(QSMFormatError, match=r"file is truncated or corrupt \(" + label.replace("/", "/")) as ei:
            bf.read_qsm(p)
        assert str(ei.value).startswith(str(p))


def test_ragged_text_line_reported(tmp_path):
    lines = qsm_path("itsme_tree_v240_cylinder.txt").read_text().split("\n")
    lines[1005] = "\t".join(lines[1005].split("\t")[:9])  # line 1006
    p = tmp_path / "ragged.txt"
    p.write_text("\n".join(lines))
    with pytest.raises(QSMFormatError, match=r"line 1006: 9 fields, expected 17"):
        bf.read_qsm(p)


def test_non_finite_values_rows(tmp_path):
    lines = qsm_path("itsme_tree_v240_cylinder.txt").read_text().split("\n")
    for row in (12, 40):
        _set(lines, row, 1, "NaN")
    p = tmp_path / "nan.txt"
    p.write_text("\n".join(lines))
    with pytest.raises(QSMFormatError, match=r"non-finite values in 'radius' at rows 12, 40 \(2 rows\)") as ei:
        bf.read_qsm(p)
    assert ei.value.rows == [12, 40]


def test_parent_out_of_range_message(tmp_path):
    lines = qsm_path("archi_tree1_treeqsm_v23.txt").read_bytes().decode().split("\r\n")
    f = lines[14].split("\t")
    f[8] = "2300"
    lines[14] = "\t".join(f)
    p = tmp_path / "oor.txt"
    p.write_text("\r\n".join(lines))
    with pytest.raises(QSMFormatError, match=r"parent 2300 at row 15 is outside 1\.\.\.2271 \(0 = none\)"):
        bf.read_qsm(p)


@pytest.mark.parametrize(
    "mutate,pattern",
    [
        (lambda L: _set(L, 2, 1, -0.1), r"radius <= 0 at rows 2"),
        (lambda L: _set(L, 2, 1, 0), r"radius <= 0 at rows 2"),
        (lambda L: _set(L, 3, 2, -1), r"length < 0 at rows 3"),
        (lambda L: [_set(L, 7, c, 0) for c in (6, 7, 8)], r"axis has zero length at rows 7"),
        (lambda L: _set(L, 4, 9, 5), r"cylinders (4 -> 5 -> 4|5 -> 4 -> 5) form a cycle"),
        (lambda L: (_set(L, 2, 9, 3), _set(L, 3, 9, 2)), r"extension of row 1 is row 2, whose parent is row 3"),
        (lambda L: _set(L, 4, 9, 4), r"cylinder 4 is its own parent"),
        (lambda L: _set(L, 4, 10, 7), r"extension of row 4 is row 7, whose parent is row 3"),
        (lambda L: _set(L, 1, 1, "abc"), r"line 2, field 1: cannot read 'abc' as a number"),
        (lambda L: _set(L, 2, 9, 1.5), r"'column 9 \(parent\)' holds non-integer values at rows 2"),
        (lambda L: _set(L, 1, 2, 0), r"the root cylinder \(row 1\) has zero length"),
        (lambda L: L.__setitem__(slice(1, None), []), r"file contains no cylinders"),
    ],
)
def test_always_errors(tmp_path, mutate, pattern):
    p = _write_text17(tmp_path / "hand.txt", hand_tree(), mutate)
    with pytest.raises(QSMFormatError, match=pattern) as ei:
        bf.read_qsm(p)
    assert str(ei.value).startswith(str(p))


def test_zero_length_chain_is_bridged(tmp_path):
    # hand tree: trunk 1 -> 2 -> 3, lateral A = 4 -> 5 on 1, B = 6 on 2, C = 7 on 3
    def mutate(L):
        _set(L, 2, 2, 0)  # trunk cylinder 2 has zero length: 3 and 6 attach to 1, 3 continues 1

    p = _write_text17(tmp_path / "zl.txt", hand_tree(), mutate)
    with pytest.warns(QSMReadWarning, match=r"removed 1 zero-length cylinder \(row 2"):
        t = bf.read_qsm(p)
    assert t.n == 6
    rows = (t.source_row + 1).tolist()
    assert rows == [1, 3, 4, 5, 6, 7]
    r = {v: i for i, v in enumerate(rows)}
    assert t.parent[r[3]] == r[1] and t.parent[r[6]] == r[1]
    assert t.extension[r[1]] == r[3]  # 2 was 1's extension -> its extension 3 takes over
    assert t.branch[r[3]] == 0 and t.order[r[6]] == 1

    def chain(L):  # two consecutive zero-length cylinders: 2 and 3
        _set(L, 2, 2, 0)
        _set(L, 3, 2, 0)

    p2 = _write_text17(tmp_path / "zl2.txt", hand_tree(), chain)
    t2 = read_quiet(p2)
    rows = (t2.source_row + 1).tolist()
    r = {v: i for i, v in enumerate(rows)}
    assert rows == [1, 4, 5, 6, 7] and t2.parent[r[7]] == r[1] and t2.parent[r[6]] == r[1]
    assert t2.extension[r[1]] == -1 and t2.n_branches == 4


def test_stored_order_mismatch_warns_once(tmp_path):
    def mutate(L):
        _set(L, 5, 12, 3)  # stored order of row 5 (lateral A, order 1)
        _set(L, 7, 11, 2)  # stored branch of row 7 (lateral C) merged with lateral A's id

    p = _write_text17(tmp_path / "ord.txt", hand_tree(), mutate)
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        t = bf.read_qsm(p)
    msgs = [str(w.message) for w in rec if issubclass(w.category, QSMReadWarning)]
    assert len(msgs) == 1
    assert "1 row with a stored order that differs from the recomputed one (rows 5)" in msgs[0]
    assert "stored branch" in msgs[0] and "(rows 7)" in msgs[0]
    assert t.metadata["stored_topology_mismatch"] == {"order": [5], "branch": [7]}
    assert t.equals(hand_tree(), atol=1e-9)  # recomputed ones are used


def test_csv_duplicate_ids_and_unknown_parent(tmp_path):
    lines = qsm_path("coffeetree_simpleforest.csv").read_text().split("\n")
    f = lines[240].split(",")
    f[0] = "17"
    dup = tmp_path / "dup.csv"
    dup.write_text("\n".join(lines[:240] + [",".join(f)] + lines[241:]))
    with pytest.raises(QSMFormatError, match=r"ID 17 appears twice \(rows 18, 240\)"):
        bf.read_qsm(dup)
    f = lines[15].split(",")
    f[1] = "5000"
    bad = tmp_path / "par.csv"
    bad.write_text("\n".join(lines[:15] + [",".join(f)] + lines[16:]))
    with pytest.raises(QSMFormatError, match=r"parentID 5000 at row 15 is not an id of the file"):
        bf.read_qsm(bad)
    unk = tmp_path / "unknown.csv"
    unk.write_text("a,b,c\n1,2,3\n")
    with pytest.raises(QSMFormatError, match="native CSV header lacks column"):
        bf.read_qsm(unk)


@pytest.mark.parametrize(
    "fmt, drop, looks",
    [
        ("archi-csv", "parent_ID", "an aRchi CSV (reader 'archi-csv': 10 of its 11 required columns)"),
        ("simpleforest-csv", "parentID", "a SimpleForest CSV (reader 'simpleforest-csv': 9 of its 10 required"),
    ],
)
def test_a_foreign_csv_without_its_parent_column_is_named_by_its_layout(tmp_path, fmt, drop, looks):
    """Issue 78, item 4: an aRchi CSV without parent_ID was named a native CSV lacking ten
    columns; only --reader archi-csv named parent_ID. The error now says which layout the header
    looks like and the one column it lacks, read with the reader detected or forced alike."""
    from bforest_core.cli import main

    src = tmp_path / f"t.{fmt}.csv"
    bf.write_tree(hand_tree(), src, format=fmt)
    lines = src.read_text().splitlines()
    k = [c.strip() for c in lines[0].split(",")].index(drop)
    cut = tmp_path / "cut.csv"
    cut.write_text("\n".join(",".join(c for i, c in enumerate(ln.split(",")) if i != k) for ln in lines) + "\n")
    with pytest.raises(QSMFormatError, match=rf"looks like {re.escape(looks)}.* but lacks column\(s\) {drop} \(found"):
        bf.read_qsm(cut)
    with pytest.raises(QSMFormatError, match=rf"header lacks column\(s\) {drop} \("):
        bf.read_qsm(cut, reader=fmt)
    assert main(["info", str(cut)]) == 2


def test_fifteen_column_layouts(tmp_path):
    t = hand_tree()
    p = tmp_path / "s.txt"
    bf.write_tree(t, p, layout="treeqsm15-struct")
    assert read_quiet(p).metadata["layout"] == "treeqsm15-struct"
    # reorder into the cyldata order: ..., branch, order, position, added, UnmodRadius
    v = np.loadtxt(p)
    cyl = np.column_stack([v[:, :10], v[:, 12:15], v[:, 10], v[:, 11]])
    q = tmp_path / "c.txt"
    np.savetxt(q, cyl, fmt="%.9g", delimiter="\t")
    u = read_quiet(q)
    assert u.metadata["layout"] == "treeqsm15-cyldata" and u.metadata["version"] == "2.3.x"
    assert u.equals(t, atol=1e-8)
    # integral radii make the order undecidable: ask for layout=
    amb = v.copy()
    amb[:, 0] = 1.0
    amb[:, 11] = 1.0
    r = tmp_path / "amb.txt"
    np.savetxt(r, amb, fmt="%.9g", delimiter="\t")
    with pytest.raises(QSMFormatError, match="pass layout="):
        bf.read_qsm(r)
    assert read_quiet(r, layout="treeqsm15-struct").n == 7


def test_millimetre_warning(tmp_path):
    def mutate(L):
        for row in range(1, 8):
            _set(L, row, 1, 30)

    p = _write_text17(tmp_path / "mm.txt", hand_tree(), mutate)
    with pytest.warns(QSMReadWarning, match="values look like millimetres"):
        bf.read_qsm(p)


def test_low_level_exceptions_are_converted(tmp_path, monkeypatch):
    """Whatever a container library raises comes out as QSMFormatError naming the file."""
    import scipy.io

    p = qsm_path("itsme_qsm_tree_v230.mat")

    def boom(*a, **k):
        raise IndexError("index 3 is out of bounds")

    monkeypatch.setattr(scipy.io, "loadmat", boom)
    with pytest.raises(QSMFormatError, match=r"truncated or corrupt \(MAT v5 reader: IndexError"):
        bf.read_qsm(p)


def test_invalid_options_are_config_errors():
    p = qsm_path("itsme_qsm_tree_v230.mat")
    with pytest.raises(bf.ConfigError, match="bogus"):
        bf.read_qsm(p, bogus=1)
    with pytest.raises(bf.ConfigError, match="topology"):
        bf.read_qsm(p, topology="widest")


def test_ids_helper_rejects_wraparound_and_reports_range():
    v = np.array([0, 1, 2, 9], dtype=np.uint8)
    with pytest.raises(QSMFormatError, match=r"parent 9 at row 4 is outside 1\.\.\.4 \(0 = none\)"):
        cylinders.ids_to_rows("f.mat", "parent", v, 4, 1)
    out = cylinders.ids_to_rows("f.mat", "parent", v[:3], 3, 1)
    assert out.dtype == np.int64 and out.tolist() == [-1, 0, 1]


def test_unsorted_rows_are_resorted_and_keep_file_rows(tmp_path):
    """A valid tree stored child-before-parent: re-sorted, source_row = file row, and the
    stored branch/order check maps rows correctly (no warning)."""
    t = hand_tree()
    p = bf.write_tree(t, tmp_path / "sorted.txt")
    v = np.loadtxt(p, skiprows=1)
    perm = np.array([6, 4, 2, 0, 5, 3, 1])  # new file row k holds old row perm[k]
    new_of_old = np.empty(7, dtype=int)
    new_of_old[perm] = np.arange(7)
    w = v[perm].copy()
    for c in (8, 9):  # parent, extension (1-based, 0 = none)
        w[:, c] = np.where(w[:, c] > 0, new_of_old[np.maximum(w[:, c].astype(int) - 1, 0)] + 1, 0)
    q = tmp_path / "shuffled.txt"
    q.write_text(p.read_text().split("\n", 1)[0] + "\n" + "\n".join("\t".join(f"{x:.9g}" for x in row) for row in w))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        u = bf.read_qsm(q)
    old = perm[u.source_row]  # original hand-tree row of every tree row
    assert old[0] == 0 and sorted(old.tolist()) == list(range(7))
    assert np.allclose(u.start, t.start[old]) and np.allclose(u.radius, t.radius[old])
    assert np.array_equal(remap_ids(u.parent, old), t.parent[old])
    assert u.n_branches == t.n_branches and np.array_equal(u.order, t.order[old])


def test_csv_ids_need_not_equal_rows(tmp_path):
    p = qsm_path("coffeetree_simpleforest.csv")
    t = read_quiet(p)
    lines = p.read_text().rstrip("\n").split("\n")
    rng = np.random.default_rng(3)
    body = [lines[1 + i] for i in rng.permutation(len(lines) - 1)]
    q = tmp_path / "shuffled.csv"
    q.write_text("\n".join([lines[0]] + body) + "\n")
    u = read_quiet(q)
    assert u.n == t.n and u.n_branches == t.n_branches
    assert np.isclose(u.volume, t.volume) and np.allclose(np.sort(u.radius), np.sort(t.radius))
    assert np.array_equal(np.bincount(u.order), np.bincount(t.order))


def test_qsms_cell_array_in_mat_v5(tmp_path):
    import scipy.io as sio

    trees = read_quiet(qsm_path("itsme_qsms_tree_v230.mat"), select=[0, 1])

    def cyl(t):
        one = lambda a: np.where(a >= 0, a + 1, 0).astype(float)
        return {
            "radius": t.radius,
            "length": t.length,
            "start": t.start,
            "axis": t.axis,
            "parent": one(t.parent),
            "extension": one(t.extension),
            "added": t.added.astype(float),
        }

    cell = np.empty((1, 2), dtype=object)
    for i, t in enumerate(trees):
        cell[0, i] = {"cylinder": cyl(t)}
    p = tmp_path / "cell.mat"
    sio.savemat(str(p), {"QSMs": cell})
    got = bf.read_qsm(p, select="all")
    assert [g.n for g in got] == [110, 102]
    assert all(g.equals(t, atol=1e-12) for g, t in zip(got, trees))
