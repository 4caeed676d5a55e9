"""Amortised inference: the training prior, the summaries, the estimator's file and its refusals,
bforest train (killed and resumed), bforest posterior, the estimator's calibration, and a fit
that starts from its posterior (bforest init --amortised).

The tests that train need the extra (JAX and flowjax: pip install 'bayesforest[amortised]') and
skip saying so without it; the others run everywhere.
"""

from __future__ import annotations

import csv
import json
import os
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import bforest_core as bf
from bforest_core.cli.main import main
from bforest_core.errors import ConfigError
from bforest_core.pipeline import amortised as am
from conftest import qsm_path

MISSING = bf.component("amortised", "flow").missing()
needs_extra = pytest.mark.skipif(MISSING is not None, reason=str(MISSING))
EXE = [str(Path(sys.executable).with_name("bforest"))]
#: a flow that trains in seconds (the shipped ones: examples/amortised/)
SMALL_FLOW = {"kind": "flow", "layers": 4, "width": 16, "max_epochs": 12, "patience": 4, "batch": 32}


def _pines(*which):
    return [str(qsm_path(f"pine_ruotsinkyla_{i}.mat")) for i in which]


# ------------------------------------------------------------------------------ the prior
def test_a_draw_is_init_box_of_a_reference_scaled_to_its_height():
    refs = am.reference_trees(_pines(3))
    prior = am.TrainingPrior.build("lignum", refs, (8.0, 12.0))
    d = prior.draw(5, 17)
    again = am.TrainingPrior.from_dict(json.loads(json.dumps(prior.to_dict()))).draw(5, 17)
    assert d.theta.tolist() == again.theta.tolist() and d.seed == again.seed and d.height == again.height
    assert 8.0 <= d.height <= 12.0
    m = am.scaled_measures(refs[0][1], d.height)
    assert m.height == pytest.approx(d.height) and m.beta_q50 == refs[0][1].beta_q50  # lengths scaled, angles kept
    assert m.branch_spacing / refs[0][1].branch_spacing == pytest.approx(d.height / refs[0][1].height)
    box = am.recipe_box("lignum", m)
    # LIGNUM's growth years: 0.8-1.4 per whorl of the tree; the whorls scale with the height (a
    # taller tree of the form is older), so the years do
    j = box.names.index("years")
    assert m.n_whorls == pytest.approx(refs[0][1].n_whorls * d.height / refs[0][1].height)
    assert (box.lower[j], box.upper[j]) == (
        pytest.approx(0.8 * m.n_whorls, rel=1e-4),
        pytest.approx(1.4 * m.n_whorls, rel=1e-4),
    )
    assert np.all((d.theta >= box.lower - 1e-12) & (d.theta <= box.upper + 1e-12))
    assert d.theta[j] == round(d.theta[j])  # whole years
    # every draw lies in the prior's overall bounds, and other indices give other draws
    thetas = np.array([prior.draw(5, i).theta for i in range(40)])
    assert np.all((thetas >= prior.lower) & (thetas <= prior.upper))
    assert len({tuple(t) for t in thetas}) == 40


@pytest.mark.filterwarnings("ignore::UserWarning")
def test_references_of_other_crown_forms_are_refused():
    refs = am.reference_trees(_pines(3) + [str(qsm_path("wytham_tf3.mat"))])
    with pytest.raises(ConfigError, match="must share a crown form"):
        am.TrainingPrior.build("sot", refs, (8.0, 16.0))


def test_the_summaries_of_a_tree_are_its_statistics_and_table_quantiles():
    tree = bf.read_qsm(qsm_path("pine_ruotsinkyla_3.mat"))
    s = am.Summaries()
    x = s.vector(tree, 9.0)
    labels = s.labels()
    assert x.shape == (len(labels),) and np.all(np.isfinite(x))
    from bforest_core.metrics import tree_summary

    ts = tree_summary(tree, min_diameter=0.0)
    assert x[0] == pytest.approx(np.log(9.0))  # the height the box was scaled for
    assert x[labels.index("stat:height")] == pytest.approx(np.log(ts["height"] + 0.05))
    assert x[labels.index("stat:n_branches_o1")] == pytest.approx(np.log(ts["n_branches_o1"] + 1.0))
    assert x[labels.index("stat:angle_o1")] == pytest.approx(ts["angle_o1"])
    U = s.feature_set().extract(tree)["B1,2"]
    assert x[labels.index("B1,2:log_rows")] == pytest.approx(np.log1p(len(U)))
    assert x[labels.index("B1,2:beta:q50")] == pytest.approx(np.median(U[:, 0]))


# ------------------------------------------------------------------------------ the file
def _fake_file(path: Path, **changes) -> Path:
    """An estimator file of the current layout whose header differs as asked (no weights)."""
    prior = am.TrainingPrior.build("lignum", am.reference_trees(_pines(3)), (8.0, 12.0))
    header = {
        "format": am.FORMAT,
        "format_version": am.FORMAT_VERSION,
        "model": "lignum",
        "model_version": am.model_version("lignum"),
        "prior": prior.to_dict(),
        "summary": am.Summaries().definition(),
        "estimator": {"kind": "flow", "settings": {}, "state": {}},
        "training": {},
    }
    for key, value in changes.items():
        if key == "labels":
            header["summary"]["labels"] = value
        else:
            header[key] = value
    text = json.dumps(header).encode()
    np.savez(path, header=np.frombuffer(text, np.uint8), weights=np.zeros(4, np.uint8))
    return path


@pytest.mark.parametrize(
    "change,message",
    [
        ({"model_version": "0.1"}, "trained on lignum version 0.1, the installed lignum is version 1"),
        ({"labels": ["size:log_height_m"]}, "its summaries .* differ from this version's"),
        ({"format_version": 99}, "an estimator file of layout 99"),
        ({"model": "nonesuch"}, "trained on the growth model 'nonesuch', which is not installed"),
    ],
)
def test_an_estimator_of_another_version_is_refused_in_one_line(tmp_path, change, message):
    path = _fake_file(tmp_path / "e.npz", **change)
    with pytest.raises(ConfigError, match=message) as exc:
        am.checked_header(path)
    assert "\n" not in str(exc.value) and str(path) in str(exc.value)


def test_what_is_not_an_estimator_is_named(tmp_path):
    (tmp_path / "x.npz").write_text("no zip")
    for path, message in ((tmp_path / "x.npz", "not an estimator file"), (tmp_path / "none.npz", "not found")):
        with pytest.raises(ConfigError, match=message):
            am.checked_header(path)


def test_without_the_extra_the_commands_say_what_to_install(tmp_path, monkeypatch, capsys):
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "flowjax" else real(name, *a))
    cfg = tmp_path / "t.toml"
    cfg.write_text(
        f'[train]\nmodel = "lignum"\nreferences = [{json.dumps(_pines(3)[0])}]\nheights = [8.0, 12.0]\nsimulations = 10\n'
    )
    assert main(["train", str(cfg), "-o", str(tmp_path / "t")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        "error: the amortised estimator needs JAX and flowjax (flowjax is not installed): "
        "pip install 'bayesforest[amortised]'"
    ]
    assert not (tmp_path / "t").exists()  # refused before the folder is made


# ------------------------------------------------------------------------------ the search's start
def test_a_start_the_fit_cannot_use_is_named_by_config_check(tmp_path):
    _fake_file(tmp_path / "e.npz")
    base = f'seed = 1\n[target]\nqsm = {json.dumps(_pines(3)[0])}\n[ssm]\nkind = "lignum"\n'
    cases = (
        ("q_mean = { lower = 0.2, upper = 0.4 }", 'kind = "cma"\ninit_design = 8', None),
        ("q_mean = { lower = 0.2, upper = 0.4 }", 'kind = "ga"', "the optimizer 'ga' with these settings takes no"),
        ("radiation = { lower = 20, upper = 40 }", 'kind = "cma"\ninit_design = 8', "free parameter(s) radiation"),
    )
    for free, optimizer, message in cases:
        cfg = tmp_path / "r.toml"
        cfg.write_text(base + f"free.{free}\n[start]\nestimator = 'e.npz'\n[optimizer]\n{optimizer}\n")
        problems = am.start_problems(bf.load_config(cfg))
        assert (problems == []) if message is None else (len(problems) == 1 and message in problems[0]), problems


def test_cma_starts_from_the_problems_start_points():
    from bforest_core.interfaces import Problem

    seen = []

    def evaluate(X):
        seen.append(np.array(X))
        pr.n_evaluations += len(X)
        if pr.n_evaluations >= pr.budget:
            pr.stopped = True
        return np.sum((np.asarray(X) - 0.3) ** 2, axis=1)

    start = np.array([[0.31, 0.29, 2.0], [0.9, 0.1, 7.4], [5.0, -3.0, 3.0]])
    pr = Problem(["a", "b", "k"], np.zeros(3), np.array([1.0, 1.0, 9.0]), np.array([False, False, True]), evaluate)
    pr.budget, pr.start = 30, start
    bf.component("optimizer", "cma", init_design=5, population=6).minimize(pr)
    first = seen[0]
    assert first.shape == (5, 3)
    # the start points, moved into the box and rounded, then the design's own points
    assert first[:3].tolist() == [[0.31, 0.29, 2.0], [0.9, 0.1, 7.0], [1.0, 0.0, 3.0]]


# ------------------------------------------------------------------------------ end to end
@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A small LIGNUM estimator of pine 3's form, trained by `bforest train` that is killed (-9)
    once some simulations are stored and resumed: (folder, the stored count when killed, stdout)."""
    if MISSING:
        pytest.skip(MISSING)
    tmp = tmp_path_factory.mktemp("amortised")
    cfg = tmp / "train.toml"
    est = ", ".join(f"{k} = {json.dumps(v)}" for k, v in SMALL_FLOW.items())
    cfg.write_text(
        "seed = 2\n[train]\nmodel = 'lignum'\n"
        f"references = [{json.dumps(_pines(3)[0])}]\nheights = [8.0, 12.0]\nsimulations = 200\n"
        f"[estimator]\n{est.replace(', ', chr(10))}\n[executor]\nkind = 'process'\nworkers = 2\n"
    )
    out = tmp / "train"
    proc = subprocess.Popen(EXE + ["train", str(cfg), "-o", str(out), "-q"], start_new_session=True)
    db, held = out / "simulations.sqlite", 0
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and held < 30 and proc.poll() is None:
        time.sleep(0.05)
        try:
            with sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=0.2) as con:
                held = con.execute("SELECT COUNT(*) FROM simulations").fetchone()[0]
        except sqlite3.Error:
            pass
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    assert 30 <= held < 200, f"the training was not caught mid-way ({held} stored)"
    with sqlite3.connect(db) as con:
        kept = con.execute("SELECT COUNT(*) FROM simulations").fetchone()[0]
    import contextlib
    import io

    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        assert main(["train", str(cfg), "-o", str(out), "--resume", "-q"]) == 0
    return out, kept, printed.getvalue(), cfg


@needs_extra
def test_a_killed_training_resumes_without_growing_a_stored_tree_again(trained):
    out, kept, stdout, cfg = trained
    assert f"({kept} stored before, {200 - kept} grown now;" in stdout
    with sqlite3.connect(out / "simulations.sqlite") as con:
        rows = con.execute("SELECT idx, params, seed FROM simulations ORDER BY idx").fetchall()
    assert [r[0] for r in rows] == list(range(200))  # each draw once
    te = am.read_estimator(out / "estimator.npz")
    for idx, params, seed in rows[::37]:  # each stored as the prior draws it
        d = te.prior.draw(2, idx)
        assert json.loads(params) == json.loads(json.dumps(d.params(te.names, te.prior.integer))) and seed == d.seed
    rec = json.loads((out / "training.json").read_text())
    assert rec["pairs"] == rec["statuses"]["ok"] == te.header["training"]["pairs"]
    head = te.header
    assert head["model_version"] == am.model_version("lignum") and head["summary"]["version"] == am.SUMMARY_VERSION
    assert set(head["provenance"]["libraries"]) >= {"jax", "flowjax"}
    # a second training into the folder needs --resume or --overwrite
    assert main(["train", str(cfg), "-o", str(out), "-q"]) == 2


@needs_extra
def test_posterior_of_a_tree_from_a_trained_file(trained, tmp_path, capsys):
    out, *_ = trained
    tree = _pines(3)[0]
    dest = tmp_path / "post"
    args = ["posterior", tree, "--estimator", str(out / "estimator.npz"), "-o", str(dest), "-n", "300"]
    assert main([*args, "--clones", "2", "--no-figure", "-q"]) == 0
    printed = capsys.readouterr().out
    assert "excurrent crown; flow estimator of lignum" in printed and "years" in printed
    te = am.read_estimator(out / "estimator.npz")
    with (dest / "posterior.csv").open() as fh:
        rows = list(csv.reader(fh))
    assert rows[0] == [*te.names, "weight"] and len(rows) == 301
    X = np.array(rows[1:], float)[:, :-1]
    assert np.all((X >= te.prior.lower) & (X <= te.prior.upper))
    summary = json.loads((dest / "posterior.json").read_text())
    assert summary["draws"] == 300 and set(summary["posterior_summary"]) == set(te.names)
    assert (dest / "posterior.nc").exists()
    clones = list(csv.DictReader((dest / "clones" / "clones.csv").open()))
    assert len(clones) == 2 and all(c["status"] == "ok" and (dest / "clones" / c["file"]).exists() for c in clones)
    assert [float(c["years"]) for c in clones] == X[:2, te.names.index("years")].tolist()  # draw i grows clone i
    # the same seed gives the same draws; a posterior is never written over without --overwrite
    assert main(args + ["--no-figure", "-q"]) == 2
    assert "holds a posterior already" in capsys.readouterr().err
    assert main([*args, "--no-figure", "-q", "--overwrite"]) == 0
    with (dest / "posterior.csv").open() as fh:
        assert np.array(list(csv.reader(fh))[1:], float)[:, :-1].tolist() == X.tolist()


@needs_extra
def test_calibration_of_the_estimator_on_targets_from_its_prior(trained, tmp_path, capsys):
    out, *_ = trained
    dest = tmp_path / "sbc"
    args = ["calibrate", "--estimator", str(out / "estimator.npz"), "-n", "8", "-o", str(dest), "-q"]
    assert main([*args, "--workers", "2"]) == 0
    printed = capsys.readouterr().out
    assert "calibration of the amortised flow estimator on lignum: 8 runs" in printed
    res = json.loads((dest / "calibration.json").read_text())
    te = am.read_estimator(out / "estimator.npz")
    assert [t["parameter"] for t in res["table"]] == te.names
    for run in res["runs"]:  # each target is a draw of the prior's calibration stream, never a training draw
        idx = int(run["run"].split("_")[1])
        d = te.prior.draw(1, idx, am.CALIBRATION_STREAM)
        assert [run["truth"][k] for k in te.names] == d.theta.tolist()
    assert (dest / "calibration.png").exists() and (dest / "calibration.csv").exists()
    # resumed, nothing is grown again and the table is the same
    with sqlite3.connect(dest / "simulations.sqlite") as con:
        before = con.execute("SELECT COUNT(*) FROM simulations").fetchone()[0]
    assert main([*args, "--resume"]) == 0
    again = json.loads((dest / "calibration.json").read_text())
    with sqlite3.connect(dest / "simulations.sqlite") as con:
        assert con.execute("SELECT COUNT(*) FROM simulations").fetchone()[0] == before
    assert again["table"] == res["table"]


@needs_extra
def test_a_fit_starts_from_the_estimators_posterior(trained, tmp_path, capsys):
    out, *_ = trained
    recipe = tmp_path / "pine3.toml"
    assert main(["init", _pines(3)[0], "--amortised", str(out / "estimator.npz"), "-o", str(recipe)]) == 0
    text = recipe.read_text()
    assert "[start]" in text and "max_evaluations = 576" in text and "top = 8" in text and "init_design = 32" in text
    assert main(["config", "check", str(recipe)]) == 0
    # the answer is held to four fifths of a forester's tolerances (height 7.5 %, DBH 20 %, ...)
    assert bf.load_config(recipe).select.sizes == {
        "height": 0.06,
        "dbh": 0.16,
        "crown_spread": 0.2,
        "crown_base_height": 0.24,
        "n_branches_o1": 0.24,
    }
    # a short version of the recipe: its first points are the posterior's draws for the tree
    short = (
        text.replace("max_evaluations = 576", "max_evaluations = 24")
        .replace("init_design = 32", "init_design = 8")
        .replace("population = 16", "population = 8")
        .replace("top = 8", "top = 2")
        .replace("sets = 16", "sets = 2")
    )
    recipe.write_text(short)
    run = tmp_path / "run"
    assert main(["fit", str(recipe), "-o", str(run), "-q", "--no-report"]) == 0
    from bforest_core.pipeline.store import RunStore

    with RunStore.open(run) as st:
        start = np.array(st.get_meta("start_points"))
        first = [st.evaluation(i).params for i in range(8)]
    cfg = bf.load_config(recipe)
    names = list(cfg.ssm.free)
    te = am.read_estimator(out / "estimator.npz")
    post = am.start_points(cfg, bf.read_qsm(_pines(3)[0]), names, *_box(cfg, names))
    assert np.allclose(start, post)
    lo, hi = (np.array(b) for b in _box(cfg, names))
    whole = te.prior.integer[[te.names.index(k) for k in names]]
    want = np.where(whole, np.clip(np.rint(start[:8]), np.ceil(lo), np.floor(hi)), start[:8])  # as the box projects
    assert np.array([[p[k] for k in names] for p in first]) == pytest.approx(want)
    # resumed, the run starts from the points it kept
    assert main(["fit", str(run / "config.toml"), "-o", str(run), "--resume", "-q", "--no-report"]) == 0


def _box(cfg, names):
    from bforest_core.pipeline.target import bounds_from_target, load_target_trees

    c = bounds_from_target(cfg, load_target_trees(cfg))
    return [c.ssm.free[k].lower for k in names], [c.ssm.free[k].upper for k in names]
