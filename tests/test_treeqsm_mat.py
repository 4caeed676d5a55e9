"""The TreeQSM 2.4 .mat export: every field of TreeQSM's own struct (the coffee tree sample, field
by field), the same tables back through our reader, provenance in rundata."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import scipy.io as sio

import bforest_core as bf
from conftest import hand_tree, qsm_path


def _struct(path, var):
    return sio.loadmat(str(path), squeeze_me=False, struct_as_record=True)[var][0, 0]


def _fields(s):
    return list(s.dtype.names)


@pytest.fixture(scope="module")
def sample():
    return _struct(qsm_path("coffeetree_treeqsm_optqsm.mat"), "OptQSM")


@pytest.fixture(scope="module")
def model_tree():
    return bf.component("ssm", "sot").simulate({"max_iter": 8}, 3)


def test_every_field_of_the_treeqsm_24_sample(tmp_path, sample, model_tree):
    p = bf.write_tree(model_tree, tmp_path / "clone.mat")
    got = _struct(p, "qsm")
    assert (
        _fields(got) == _fields(sample) == ["cylinder", "branch", "treedata", "rundata", "pmdistance", "triangulation"]
    )
    n, nb = model_tree.n, model_tree.n_branches
    for top in ("cylinder", "branch", "treedata", "pmdistance", "triangulation"):
        r, g = sample[top][0, 0], got[top][0, 0]
        assert _fields(g) == _fields(r), top
        for f in _fields(r):
            a, b = r[f], g[f]
            if top == "cylinder" or (top == "pmdistance" and f == "CylDist"):
                assert b.shape == (n, a.shape[1]), f  # one row per cylinder, same columns
            elif top == "branch":
                assert b.shape == (nb, 1), f
            elif a.shape[0] == 1 and a.shape[1] in (1, 3, 18, 36):
                assert b.shape == a.shape, f  # scalars, location, fixed classes
            else:
                assert b.ndim == 2 and (b.shape[0] == a.shape[0] or b.shape[1] == a.shape[1]), f
            assert (
                b.dtype.kind == a.dtype.kind
                or top == "triangulation"
                or (a.dtype.kind in "iuf" and b.dtype.kind in "iuf")
            ), f
    # integer ids in TreeQSM's unsigned classes, 1-based
    cyl = got["cylinder"][0, 0]
    assert cyl["parent"].dtype.kind == "u" and int(cyl["parent"][0, 0]) == 0 and int(cyl["branch"][0, 0]) == 1
    # rundata: TreeQSM's fields (inputs with every sub-field of the sample) plus our provenance
    rr, rg = sample["rundata"][0, 0], got["rundata"][0, 0]
    assert set(_fields(rr)) <= set(_fields(rg))
    assert set(_fields(rr["inputs"][0, 0])) <= set(_fields(rg["inputs"][0, 0]))
    assert set(_fields(rr["inputs"][0, 0]["filter"][0, 0])) == set(_fields(rg["inputs"][0, 0]["filter"][0, 0]))
    prov = rg["bforest"][0, 0]
    assert str(prov["model"][0]) == "sot" and float(prov["seed"][0, 0]) == 3
    assert float(prov["params"][0, 0]["max_iter"][0, 0]) == 8
    assert str(prov["version"][0]) == bf.__version__


def test_mat_gives_the_same_tables_back(tmp_path, model_tree):
    back = bf.read_qsm(bf.write_tree(model_tree, tmp_path / "t.mat"))
    for k in ("parent", "extension", "branch", "order", "position_in_branch", "added", "start", "length", "radius"):
        assert np.array_equal(getattr(back, k), getattr(model_tree, k)), k
    # the reader renormalises every axis: within one rounding step
    assert np.abs(back.axis - model_tree.axis).max() <= 4e-16
    assert back.metadata["version"] == f"bforest {bf.__version__} (TreeQSM 2.4.1 layout)"


def test_mat_treedata_and_branch_of_the_hand_tree(tmp_path):
    t = hand_tree()
    q = sio.loadmat(str(bf.write_tree(t, tmp_path / "h.mat")), squeeze_me=True, struct_as_record=False)["qsm"]
    td = q.treedata
    # TreeQSM's units: volumes in litres, lengths in m, areas in m^2
    assert float(td.TrunkVolume) == pytest.approx(1000 * np.pi * 0.0725, rel=1e-6)
    assert float(td.BranchLength) == pytest.approx(2.5) and float(td.NumberBranches) == 3
    assert float(td.TriaTrunkLength) == 0 and float(td.MixTotalVolume) == pytest.approx(float(td.TotalVolume))
    assert np.asarray(td.location).tolist() == [0, 0, 0]
    assert np.asarray(td.NumBranchAng).shape == (18,) and float(np.asarray(td.NumBranchAng)[9]) == 2
    assert np.asarray(q.branch.parent).tolist() == [0, 1, 1, 1]
    assert float(np.asarray(q.branch.volume)[0]) == pytest.approx(1000 * np.pi * 0.0725, rel=1e-6)
    assert np.isnan(np.asarray(q.pmdistance.CylDist)).all() and np.asarray(q.triangulation.vert).size == 0


def test_treeqsm_sample_written_back_keeps_its_tables(tmp_path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        t = bf.read_qsm(qsm_path("coffeetree_treeqsm_optqsm.mat"))
    back = bf.read_qsm(bf.write_tree(t, tmp_path / "c.mat"))
    assert back.equals(t, atol=1e-15)
