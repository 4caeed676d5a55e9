"""bforest export: trees of a run in other formats, the evaluation log as one CSV."""

import csv
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import bforest_core as bf
from bforest_core.pipeline.clones import clones
from bforest_core.pipeline.export import ExportError, export_evaluations, export_trees
from bforest_core.pipeline.store import RunStore
from conftest import toy_config


@pytest.fixture(scope="module")
def run(toy_plugin, tmp_path_factory):
    base = tmp_path_factory.mktemp("export")
    bf.fit(bf.load_config(toy_config(base, budget=12)), base / "run", progress=False)
    clones(base / "run", n=2, progress=False)
    return base / "run"


def test_trees_in_other_formats(run, tmp_path):
    files = export_trees(run, ["ply", "treeqsm-mat"], tmp_path / "out")
    assert sorted(p.name for p in files) == [
        "best_tree.mat",
        "best_tree.ply",
        "clone_000.mat",
        "clone_000.ply",
        "clone_001.mat",
        "clone_001.ply",
    ]
    back = bf.read_qsm(tmp_path / "out" / "clone_001.mat")
    assert back.n == bf.read_qsm(run / "clones" / "clone_001.txt").n
    with pytest.raises(ExportError, match="exists.*--overwrite"):
        export_trees(run, ["ply"], tmp_path / "out")
    assert len(export_trees(run, ["ply"], tmp_path / "out", what=("best",), overwrite=True)) == 1
    with pytest.raises(ExportError, match="unknown export format 'lass'.*known: .*ply"):
        export_trees(run, ["lass"], tmp_path / "x")
    both = export_trees(run, ["csv", "simpleforest-csv", "archi-csv"], tmp_path / "csv", what=("best",))
    assert sorted(p.name for p in both) == [
        "best_tree_archi-csv.csv",
        "best_tree_bforest-csv.csv",
        "best_tree_simpleforest-csv.csv",
    ]
    assert bf.read_qsm(tmp_path / "csv" / "best_tree_archi-csv.csv").metadata["format"] == "archi-csv"


def test_evaluations_as_one_table(run, tmp_path):
    n = export_evaluations(run, tmp_path / "ev.csv")
    rows = list(csv.DictReader(open(tmp_path / "ev.csv")))
    evs = RunStore.open(run).evaluations()
    assert n == len(rows) == len(evs) == 12
    assert {"evaluation", "status", "distance", "angle", "segments", "noise", "D[L]", "seeds"} <= set(rows[0])
    assert float(rows[3]["distance"]) == evs[3].distance and float(rows[3]["angle"]) == evs[3].params["angle"]


def test_export_command(run, tmp_path):
    exe = shutil.which("bforest") or str(Path(sys.executable).with_name("bforest"))
    r = subprocess.run(
        [
            exe,
            "export",
            str(run),
            "--format",
            "obj",
            "-o",
            str(tmp_path / "o"),
            "--evaluations",
            str(tmp_path / "ev.csv"),
        ],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0 and "wrote 3 files" in r.stdout and (tmp_path / "o" / "clone_000.obj").exists()
    r = subprocess.run([exe, "export", str(run)], capture_output=True, text=True)
    assert r.returncode == 2 and "at least one --format" in r.stderr


def test_exported_mat_and_csv_record_model_parameters_and_seed(run, tmp_path):
    import json

    import scipy.io as sio

    summary = json.loads((run / "clones" / "summary.json").read_text())
    row = next(r for r in summary["rows"] if r["file"] == "clone_001.txt")
    export_trees(run, ["mat", "csv"], tmp_path / "p", what=("clones",))
    rd = sio.loadmat(str(tmp_path / "p" / "clone_001.mat"), squeeze_me=True, struct_as_record=False)["qsm"].rundata
    prov = rd.bforest
    assert prov.model == "toy" and int(prov.seed) == row["seed"] and prov.version == bf.__version__
    assert float(prov.params.angle) == pytest.approx(row["params"]["angle"])
    assert float(prov.fixed.noise) == 2.0 and prov.role == "clone 1"
    side = json.loads((tmp_path / "p" / "clone_001.json").read_text())
    assert side["model"] == "toy" and side["seed"] == row["seed"] and side["params"] == row["params"]


def test_posterior_clones_are_exported_with_their_own_names_and_provenance(run, tmp_path):
    import json

    import scipy.io as sio

    r = tmp_path / "run"
    shutil.copytree(run, r)
    # the posterior clones of `bforest clones --posterior` (here: the clone set under that name)
    shutil.copytree(r / "clones", r / "clones_posterior")
    s = json.loads((r / "clones_posterior" / "summary.json").read_text())
    s["rows"][1]["seed"] = 4242
    (r / "clones_posterior" / "summary.json").write_text(json.dumps(s))
    files = export_trees(r, ["mat"], tmp_path / "o", what=("clones", "posterior"))
    assert sorted(p.name for p in files) == [
        "clone_000.mat",
        "clone_001.mat",
        "posterior_clone_000.mat",
        "posterior_clone_001.mat",
    ]
    prov = sio.loadmat(str(tmp_path / "o" / "posterior_clone_001.mat"), squeeze_me=True, struct_as_record=False)[
        "qsm"
    ].rundata.bforest
    assert prov.role == "posterior clone 1" and int(prov.seed) == 4242
    exe = shutil.which("bforest") or str(Path(sys.executable).with_name("bforest"))
    res = subprocess.run(
        [exe, "export", str(r), "--what", "posteriors", "--format", "ply"], capture_output=True, text=True
    )
    assert res.returncode == 2 and "best, clones and/or posterior" in res.stderr
