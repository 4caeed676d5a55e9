"""Exports say where a tree came from (PLY/OBJ/XYZ comments, LAS header and VLR); LAS points are
valid single returns with a class; scan settings from the command line."""

from __future__ import annotations

import json

import numpy as np
import pytest

import bforest_core as bf
from conftest import hand_tree


def _model_tree():
    t = hand_tree()
    t.metadata.update(model="sot", params={"max_iter": 9.0}, seed=4)
    return t


def _prov(line: str) -> dict:
    return json.loads(line.split("provenance ", 1)[1])


def test_mesh_and_xyz_files_record_provenance(tmp_path):
    t = _model_tree()
    ply = bf.write_tree(t, tmp_path / "t.ply", ascii=True)
    head = ply.read_text().split("end_header")[0].splitlines()
    pv = _prov(next(x for x in head if x.startswith("comment provenance ")))
    assert pv == {"software": f"Bayes Forest {bf.__version__}", "model": "sot", "params": {"max_iter": 9.0}, "seed": 4}
    obj = bf.write_tree(t, tmp_path / "t.obj").read_text().splitlines()
    assert _prov(obj[1])["seed"] == 4 and obj[1].startswith("# provenance ")
    xyz = bf.write_tree(t, tmp_path / "t.xyz", density=300, seed=2).read_text().splitlines()
    pv = _prov(xyz[1])
    assert pv["model"] == "sot" and pv["scan"]["density"] == 300 and pv["scan"]["seed"] == 2
    assert np.loadtxt(tmp_path / "t.xyz").shape[1] == 6  # comments do not break a plain reader


def test_las_points_are_valid_single_returns_with_provenance(tmp_path):
    laspy = pytest.importorskip("laspy")
    las = laspy.read(bf.write_tree(_model_tree(), tmp_path / "t.las", density=1000, seed=3, noise=0.001))
    n = len(las.points)
    assert n > 100
    assert np.all(np.asarray(las.return_number) == 1) and np.all(np.asarray(las.number_of_returns) == 1)
    assert np.all(np.asarray(las.classification) == 5)
    assert las.header.generating_software.startswith("Bayes Forest")
    vlr = next(v for v in las.header.vlrs if v.user_id == "BayesForest")
    pv = json.loads(vlr.record_data.decode())
    assert (pv["model"], pv["seed"], pv["params"]) == ("sot", 4, {"max_iter": 9.0})
    assert pv["scan"]["noise"] == 0.001 and pv["scan"]["density"] == 1000


def test_export_scan_settings_on_the_command_line(toy_plugin, tmp_path_factory):
    from bforest_core.cli.main import main
    from conftest import toy_config

    base = tmp_path_factory.mktemp("scanexport")
    bf.fit(bf.load_config(toy_config(base, budget=8)), base / "run", progress=False)
    out = base / "out"
    assert (
        main(
            [
                "export",
                str(base / "run"),
                "--what",
                "best",
                "--format",
                "xyz,ply",
                "-o",
                str(out),
                "--scan",
                "density=123",
                "--scan",
                "mode=scanner",
                "--scan",
                "scanner=0,-5,1",
            ]
        )
        == 0
    )
    line = (out / "best_tree.xyz").read_text().splitlines()[1]
    pv = _prov(line)
    assert pv["scan"]["density"] == 123 and pv["scan"]["mode"] == "scanner" and pv["scan"]["scanner"] == [0, -5, 1]
    assert pv["model"] == "toy" and pv["role"] == "best fit"
    assert (
        main(
            [
                "export",
                str(base / "run"),
                "--what",
                "best",
                "--format",
                "xyz",
                "-o",
                str(out / "b"),
                "--scan",
                "scanner=a,b",
            ]
        )
        == 2
    )


def test_simulate_takes_scan_settings(tmp_path, capsys):
    from bforest_core.cli.main import main

    out = tmp_path / "t.xyz"
    assert (
        main(
            [
                "simulate",
                "--ssm",
                "sot",
                "--set",
                "max_iter=8",
                "--seed",
                "2",
                "-o",
                str(out),
                "--scan",
                "density=50",
                "--scan",
                "noise=0.002",
            ]
        )
        == 0
    )
    pv = _prov(out.read_text().splitlines()[1])
    assert pv["scan"]["density"] == 50 and pv["scan"]["noise"] == 0.002
    assert (pv["model"], pv["seed"], pv["params"]["max_iter"]) == ("sot", 2, 8)
    assert (
        main(["simulate", "--ssm", "sot", "--set", "max_iter=8", "-o", str(tmp_path / "t.ply"), "--scan", "density=50"])
        == 2
    )
    assert "--scan applies to a synthetic scan output" in capsys.readouterr().err


def test_native_csv_records_provenance_in_its_sidecar_and_stays_a_plain_table(tmp_path):
    """The native CSV's sidecar holds the same provenance as the other formats' comments (the
    Bayes Forest version too); the CSV itself starts with its header, so pandas or R read it with
    their defaults, and it reads back as the same tree."""
    t = _model_tree()
    p = bf.write_tree(t, tmp_path / "t.csv")
    side = json.loads(p.with_suffix(".json").read_text())
    assert side["provenance"] == {
        "software": f"Bayes Forest {bf.__version__}",
        "model": "sot",
        "params": {"max_iter": 9.0},
        "seed": 4,
    }
    assert p.read_text().splitlines()[0].startswith("id,parent,")
    back = bf.read_qsm(p)
    assert np.allclose(back.start, t.start) and back.metadata["seed"] == 4
