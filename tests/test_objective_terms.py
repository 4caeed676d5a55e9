"""An objective of several terms: [[objective.terms]] beside the [features]/[distance] term."""

import json
import pickle

import numpy as np
import pytest

import bforest_core as bf
from bforest_core.pipeline import scoring, worker
from bforest_core.pipeline.store import RunStore
from bforest_core.pipeline.target import build_target
from conftest import toy_config

TERM = """
[objective]
structure_weight = {w0}

[[objective.terms]]
name = "extra"
weight = {w1}
features = {{ kind = "toy-features", sets = ["A", "B"] }}
distance = {{ kind = "toy-distance" }}
weights = {{ A = 3.0, B = 1.0 }}
"""


def _config(tmp_path, w0=1.0, w1=3.0, budget=16):
    p = toy_config(tmp_path, budget=budget)
    p.write_text(p.read_text() + TERM.format(w0=w0, w1=w1))
    return p


def test_a_fit_scores_the_weighted_mean_of_its_terms(toy_plugin, tmp_path):
    cfg = bf.load_config(_config(tmp_path))
    res = bf.fit(cfg, tmp_path / "run", progress=False)
    evs = RunStore.open(tmp_path / "run").evaluations()
    assert len(evs) == 16 and res.n_evaluations == 16
    for e in evs:
        ps = e.per_set
        # the extra term's sets are stored under its name, and each term's value beside them
        assert set(ps) == {"L", "extra/A", "extra/B", "term:structure", "term:extra"}
        assert ps["term:structure"] == pytest.approx(ps["L"])
        assert ps["term:extra"] == pytest.approx((3 * ps["extra/A"] + ps["extra/B"]) / 4)
        assert e.distance == pytest.approx((1.0 * ps["term:structure"] + 3.0 * ps["term:extra"]) / 4.0)
        assert e.n_rows["extra/A"] == e.n_rows["L"] > 0
    best = json.loads((tmp_path / "run" / "best.json").read_text())
    assert "term:extra" in best["per_set"]
    # the target's tables of every term are saved for the report
    with np.load(tmp_path / "run" / "target_sets.npz") as z:
        assert set(z.files) == {"L", "extra/A", "extra/B"}


def test_the_weights_change_the_objective(toy_plugin, tmp_path):
    """With the extra term weighted to nothing but a token, the objective is the structure term."""
    (tmp_path / "a").mkdir()
    cfg = bf.load_config(_config(tmp_path / "a", w0=1.0, w1=1e-9, budget=8))
    bf.fit(cfg, tmp_path / "a" / "run", progress=False)
    for e in RunStore.open(tmp_path / "a" / "run").evaluations():
        assert e.distance == pytest.approx(e.per_set["L"], rel=1e-6)


def test_score_tree_and_combine_terms(toy_plugin, tmp_path):
    cfg = bf.load_config(_config(tmp_path))
    tgt = build_target(cfg)
    ctx = scoring.build_scoring(cfg, tgt.U, tgt.columns, tgt.feature_settings, tgt.terms)
    per_set, rows = scoring.score_tree(tgt.trees[0], ctx)
    total, values = scoring.combine_terms(per_set, ctx)
    assert total == pytest.approx(0.0) and values == {"structure": 0.0, "extra": 0.0}  # the target scores 0
    assert rows == {"L": 12, "extra/A": 12, "extra/B": 12}
    # a grown tree scores above 0, and a worker built from the config's dict scores it the same
    tree = ctx.ssm.simulate({}, 5)
    per_set, _ = scoring.score_tree(tree, ctx)
    assert scoring.combine_terms(per_set, ctx)[0] > 0
    saved = worker._SCORING
    try:  # a worker given the config as it travels to one (pickled) scores it the same
        worker.init_worker(pickle.loads(pickle.dumps(cfg)), tgt.U, tgt.columns, tgt.feature_settings, tgt.terms)
        assert scoring.score_tree(tree, worker.worker_context())[0] == per_set
    finally:
        worker._SCORING = saved


@pytest.mark.parametrize(
    "term, message",
    [
        (
            'name = "x"\nfeatures = { kind = "nope" }\ndistance = { kind = "toy-distance" }',
            "objective.terms[0] (x).features",
        ),
        ('name = "x"\nfeatures = { kind = "toy-features", bogus = 1 }\ndistance = { kind = "toy-distance" }', "bogus"),
        ('name = "x"\nfeatures = { sets = ["A"] }\ndistance = { kind = "toy-distance" }', "needs kind"),
        (
            'name = "structure"\nfeatures = { kind = "toy-features" }\ndistance = { kind = "toy-distance" }',
            "used twice",
        ),
    ],
)
def test_bad_terms_are_named(toy_plugin, tmp_path, term, message):
    p = toy_config(tmp_path)
    p.write_text(p.read_text() + "\n[[objective.terms]]\n" + term + "\n")
    with pytest.raises(bf.ConfigError, match=message.replace("[", r"\[").replace("(", r"\(").replace(")", r"\)")):
        bf.load_config(p)
