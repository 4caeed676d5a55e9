"""The answer of a fit chosen on held-out model seeds (``[select]``): the right candidate, kept
scores, a resumable re-scoring, and the report showing both distances."""

import json
import warnings

import numpy as np
import pytest

import bforest_core as bf
from bforest_core.pipeline import heldout as heldout_mod
from bforest_core.pipeline.fidelity import finite_means
from bforest_core.pipeline.heldout import candidates, heldout_sizes, point_key, size_errors
from bforest_core.pipeline.scoring import grow_tree
from bforest_core.pipeline.seeds import heldout_seeds
from bforest_core.pipeline.store import Evaluation, RunStore
from bforest_core.pipeline.target import build_target
from bforest_core.pipeline.worker import evaluate_task, heldout_task, started_workers, worker_context
from conftest import toy_config

#: a noisy toy objective (lateral angles scattered by 20 deg per tree): with run seed 3 the point
#: of lowest own distance is a lucky one, and another candidate is better on fresh seeds
SELECT = "\n[select]\ntop = 5\nsets = 6\n"


def noisy_config(tmp_path, seed=3):
    p = toy_config(tmp_path, budget=40)
    p.write_text(
        p.read_text()
        .replace("fixed = { noise = 2.0 }", "fixed = { noise = 20.0 }")
        .replace("seed = 3", f"seed = {seed}", 1)
        + SELECT
    )
    return p


def test_the_answer_is_the_candidate_best_on_held_out_seeds_not_the_luckiest(toy_plugin, tmp_path):
    p = noisy_config(tmp_path)
    cfg = bf.load_config(p)
    res = bf.fit(cfg, tmp_path / "run", progress=False)
    best = json.loads((tmp_path / "run" / "best.json").read_text())
    sel = best["selection"]
    with RunStore.open(tmp_path / "run") as store:
        evs = store.evaluations()
    # the candidates: the 5 best distinct grown points, best first
    own = sorted((e for e in evs if e.status == "ok"), key=lambda e: (e.distance, e.idx))
    assert [c["evaluation"] for c in sel["candidates"]] == [e.idx for e in own[:5]]
    # their held-out distances, recomputed seed set by seed set outside the fit
    sets = heldout_seeds(cfg.seed, 6, 1)
    used = {s for e in evs for s in e.seeds}
    assert not used & {s for ss in sets for s in ss}  # seeds the search never used
    with started_workers(cfg, build_target(cfg)):
        expect = {
            c["evaluation"]: np.mean([evaluate_task((c["params"], s))["distance"] for s in sets])
            for c in sel["candidates"]
        }
    assert {c["evaluation"]: c["heldout"] for c in sel["candidates"]} == pytest.approx(expect, rel=1e-12)
    chosen = min(expect, key=expect.get)
    assert sel["chosen"] == chosen == best["evaluation"]
    assert chosen != own[0].idx  # the luckiest point is not the answer
    assert best["params"] == next(c["params"] for c in sel["candidates"] if c["evaluation"] == chosen)
    assert best["heldout_distance"] == pytest.approx(expect[chosen], rel=1e-12)
    assert res.params == best["params"]


def test_candidates_are_distinct_points():
    ev = lambda i, x, d: Evaluation(i, {"a": x, "b": 0.0}, [1], d, {}, "ok", "", 0.0, "", {})
    log = [
        ev(0, 0.50, 0.10),
        ev(1, 0.505, 0.11),
        ev(2, 0.90, 0.12),
        ev(3, 0.10, 0.13),
        Evaluation(4, {"a": 0.3, "b": 0.0}, [1], 0.01, {}, "error", "", 0.0, "", {}),
    ]
    got = candidates(log, 3, [0.0, 0.0], [1.0, 1.0], ["a", "b"], spacing=0.02)
    assert [e.idx for e in got] == [0, 2, 3]  # 1 is a near-copy of 0; 4 failed


def test_a_killed_rescoring_resumes_to_the_identical_answer_growing_nothing_twice(toy_plugin, tmp_path, monkeypatch):
    p = noisy_config(tmp_path)
    bf.fit(bf.load_config(p), tmp_path / "whole", progress=False)
    whole = json.loads((tmp_path / "whole" / "best.json").read_text())
    real_add, calls = RunStore.add_heldout, {"n": 0}

    def dying_add(self, *a, **kw):
        calls["n"] += 1
        if calls["n"] > 7:
            raise KeyboardInterrupt  # Ctrl-C in the middle of the re-scoring
        return real_add(self, *a, **kw)

    monkeypatch.setattr(RunStore, "add_heldout", dying_add)
    with pytest.raises(KeyboardInterrupt):
        bf.fit(bf.load_config(p), tmp_path / "cut", progress=False)
    monkeypatch.setattr(RunStore, "add_heldout", real_add)
    assert not (tmp_path / "cut" / "best.json").exists()
    grown = []
    monkeypatch.setattr(heldout_mod, "heldout_task", lambda task: grown.append(task) or heldout_task(task))
    bf.fit(bf.load_config(p), tmp_path / "cut", resume=True, progress=False)
    cut = json.loads((tmp_path / "cut" / "best.json").read_text())
    assert len(grown) == 5 * 6 - 7  # the 7 kept scores are not grown again
    for k in ("params", "evaluation", "distance", "heldout_distance", "selection"):
        assert cut[k] == whole[k], k


def test_the_report_shows_own_and_held_out_distances(toy_plugin, tmp_path):
    p = noisy_config(tmp_path)
    bf.fit(bf.load_config(p), tmp_path / "run", progress=False)
    from bforest_core.report.build import write_report

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        write_report(tmp_path / "run", figures=False, html=False)
    md = (tmp_path / "run" / "report.md").read_text()
    best = json.loads((tmp_path / "run" / "best.json").read_text())
    assert "chosen on held-out model seeds" in md
    assert "| evaluation | own distance | held-out distance |" in md
    for c in best["selection"]["candidates"]:
        assert f"| {c['evaluation']} | " in md
    assert "seeds' luck" in md  # the answer is not the point of lowest own distance here


def test_select_off_keeps_the_best_own_distance(toy_plugin, tmp_path):
    p = noisy_config(tmp_path)
    p.write_text(p.read_text().replace(SELECT, ""))
    bf.fit(bf.load_config(p), tmp_path / "run", progress=False)
    best = json.loads((tmp_path / "run" / "best.json").read_text())
    with RunStore.open(tmp_path / "run") as store:
        assert best["evaluation"] == store.best().idx
    assert "selection" not in best and "heldout_distance" not in best
    assert point_key({"b": 1, "a": 2}) == '{"a": 2, "b": 1}'


def test_compare_reports_each_search_by_its_best_own_distance(toy_plugin, tmp_path):
    """compare compares searches: a recipe's [select] does not replace a run's best by a candidate
    chosen on held-out seeds (compare --heldout scores runs on fresh seeds itself)."""
    from bforest_core.pipeline.compare import compare

    p = noisy_config(tmp_path)
    res = compare(p, ["toy-random"], budget=20, repeats=1, out_dir=tmp_path / "cmp")
    best = json.loads((tmp_path / "cmp" / "toy-random-0" / "best.json").read_text())
    with RunStore.open(tmp_path / "cmp" / "toy-random-0") as store:
        assert best["evaluation"] == store.best().idx
    assert "selection" not in best and res["runs"][0]["best"] == best["distance"]


#: the candidates scored on other tables than the search's: the toy model's trees as first-order
#: branches under the sliced KS (the search keeps the toy distance)
OWN_TABLES = '\nfeatures = { kind = "branch-segment", sets = ["B1"] }\ndistance = { kind = "sliced", lines = 64 }\n'


def test_select_features_score_the_candidates_on_their_own_tables_and_leave_the_search_alone(toy_plugin, tmp_path):
    from bforest_core.config import selection_config

    plain = noisy_config(tmp_path)
    bf.fit(bf.load_config(plain), tmp_path / "plain", progress=False)
    p = tmp_path / "own.toml"
    p.write_text(plain.read_text() + OWN_TABLES)
    cfg = bf.load_config(p)
    bf.fit(cfg, tmp_path / "own", progress=False)
    with RunStore.open(tmp_path / "plain") as a, RunStore.open(tmp_path / "own") as b:
        assert [(e.params, e.distance) for e in a.evaluations()] == [(e.params, e.distance) for e in b.evaluations()]
    sel = json.loads((tmp_path / "own" / "best.json").read_text())["selection"]
    plain_sel = json.loads((tmp_path / "plain" / "best.json").read_text())["selection"]
    assert [c["evaluation"] for c in sel["candidates"]] == [c["evaluation"] for c in plain_sel["candidates"]]
    assert plain_sel["scored_by"] is None
    assert sel["scored_by"] == {
        "features": {"kind": "branch-segment", "sets": ["B1"]},
        "distance": {"kind": "sliced", "lines": 64},
    }
    # the held-out scores are the sliced KS of B1 (not the toy distance), recomputed outside the fit
    scfg = selection_config(cfg)
    assert scfg.features.kind == "branch-segment" and cfg.features.kind == "toy-features"
    sets = heldout_seeds(cfg.seed, 6, 1)
    with started_workers(scfg, build_target(scfg)):
        expect = {
            c["evaluation"]: np.mean([evaluate_task((c["params"], s))["distance"] for s in sets])
            for c in sel["candidates"]
        }
    assert {c["evaluation"]: c["heldout"] for c in sel["candidates"]} == pytest.approx(expect, rel=1e-12)
    assert sel["chosen"] == min(expect, key=expect.get)
    assert expect != pytest.approx({c["evaluation"]: c["heldout"] for c in plain_sel["candidates"]})
    from bforest_core.report.build import write_report

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        write_report(tmp_path / "own", figures=False, html=False)
    md = (tmp_path / "own" / "report.md").read_text()
    assert "scored on the tables of [select] (features branch-segment, sets B1; distance sliced, lines 64)" in md


def test_select_features_naming_no_table_are_refused_before_the_search(toy_plugin, tmp_path):
    """Refused as the config is read (the file and the key named), so before the first evaluation."""
    p = tmp_path / "bad.toml"
    p.write_text(noisy_config(tmp_path).read_text() + OWN_TABLES.replace('["B1"]', '["Q7"]'))
    with pytest.raises(bf.ConfigError, match=r"bad\.toml: select: features\.sets: set 'Q7'"):
        bf.load_config(p)


#: a second term beside the toy structure term (as test_objective_terms), so held-out scores have terms
TWO_TERMS = """
[objective]
structure_weight = 1.0

[[objective.terms]]
name = "extra"
weight = 3.0
features = { kind = "toy-features", sets = ["A", "B"] }
distance = { kind = "toy-distance" }
weights = { A = 3.0, B = 1.0 }
"""


def test_held_out_scores_keep_each_term_and_the_report_shows_them(toy_plugin, tmp_path):
    """Each candidate's held-out value of each term is the mean over the held-out sets of that
    term's value on those seeds (recomputed outside the fit); the weighted mean of the terms is
    the held-out distance the answer was chosen on; the report gives one column per term."""
    p = noisy_config(tmp_path)
    p.write_text(p.read_text() + TWO_TERMS)
    cfg = bf.load_config(p)
    bf.fit(cfg, tmp_path / "run", progress=False)
    sel = json.loads((tmp_path / "run" / "best.json").read_text())["selection"]
    sets = heldout_seeds(cfg.seed, 6, 1)
    with started_workers(cfg, build_target(cfg)):
        for c in sel["candidates"]:
            grown = [evaluate_task((c["params"], s)) for s in sets]
            assert c["failed"] == 0
            got = c["heldout_per_set"]
            for term in ("term:structure", "term:extra", "extra/A", "L"):
                assert got[term] == pytest.approx(np.mean([r["per_set"][term] for r in grown]), rel=1e-12), term
            assert (got["term:structure"] + 3.0 * got["term:extra"]) / 4.0 == pytest.approx(c["heldout"], rel=1e-12)
    with RunStore.open(tmp_path / "run") as store:  # kept in the run store, one row per point and set
        kept = store.heldout_scores(heldout_mod.scoring_fingerprint(cfg))
    assert len(kept) == 5 * 6 and all(set(r["per_set"]) >= {"term:structure", "term:extra"} for r in kept.values())
    from bforest_core.report.build import write_report

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        write_report(tmp_path / "run", figures=False, html=False)
    md = (tmp_path / "run" / "report.md").read_text()
    assert "| held-out distance | held out - own | held-out extra | held-out structure | failed sets |" in md


def test_a_run_written_before_scores_kept_their_terms_is_read_and_resumed(toy_plugin, tmp_path, monkeypatch):
    """An older run store (its held-out table without the per_set and sizes columns) gains them when
    opened; its kept scores are used as they are (nothing grown again), without per-term values."""
    import sqlite3

    p = noisy_config(tmp_path)
    bf.fit(bf.load_config(p), tmp_path / "run", progress=False)
    whole = json.loads((tmp_path / "run" / "best.json").read_text())
    con = sqlite3.connect(tmp_path / "run" / "evaluations.sqlite")
    con.execute("ALTER TABLE heldout DROP COLUMN per_set")
    con.execute("ALTER TABLE heldout DROP COLUMN sizes")
    con.commit()
    con.close()
    (tmp_path / "run" / "best.json").unlink()
    grown = []
    monkeypatch.setattr(heldout_mod, "heldout_task", lambda task: grown.append(task) or heldout_task(task))
    bf.fit(bf.load_config(p), tmp_path / "run", resume=True, progress=False)
    again = json.loads((tmp_path / "run" / "best.json").read_text())
    assert grown == []
    assert again["selection"]["chosen"] == whole["selection"]["chosen"]
    assert again["heldout_distance"] == whole["heldout_distance"]
    assert all(c["heldout_per_set"] is None for c in again["selection"]["candidates"])


def test_the_fit_names_its_best_own_and_its_held_out_answer_in_one_line(toy_plugin, tmp_path, capsys):
    """Issue 78, item 6: the progress bar ended at best=<the search's best own distance> and the
    result line showed another number (the answer chosen on held-out seeds) with nothing to say
    which is which. The line names both."""
    from bforest_core.cli import main

    assert main(["fit", str(noisy_config(tmp_path)), "-o", str(tmp_path / "run"), "-q", "--no-report"]) == 0
    best = json.loads((tmp_path / "run" / "best.json").read_text())
    with RunStore.open(tmp_path / "run") as store:
        own = store.best()
    assert own.idx != best["evaluation"]  # the luckiest point is not the answer (test above)
    line = next(ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("best"))
    assert line.startswith(
        f"best own {own.distance:.4f} after 40 evaluations (evaluation budget (40) reached); "
        f"answer {best['heldout_distance']:.4f} on held-out model seeds (evaluation {best['evaluation']}, "
        f"own {best['distance']:.4f};"
    ), line


def test_select_sizes_put_the_candidates_within_them_first(toy_plugin, tmp_path):
    """With ``[select] sizes`` each candidate's held-out trees are measured as the clones' fidelity
    table measures them; the answer is the lowest held-out distance among the candidates whose
    trees' mean keeps within every size. The toy's distance does not see the height: the plain
    answer is 23 segments tall (+88 %), the one within 20 % of the height is 10 segments (-16 %)."""
    from bforest_core.attributes import fidelity_statistics
    from bforest_core.pipeline.target import size_topology

    plain = noisy_config(tmp_path)
    bf.fit(bf.load_config(plain), tmp_path / "plain", progress=False)
    plain_sel = json.loads((tmp_path / "plain" / "best.json").read_text())["selection"]
    assert plain_sel["sizes"] is None and all(c["size_errors"] is None for c in plain_sel["candidates"])
    p = tmp_path / "sizes.toml"
    p.write_text(plain.read_text() + "sizes = { height = 0.2 }\n")
    cfg = bf.load_config(p)
    bf.fit(cfg, tmp_path / "sizes", progress=False)
    best = json.loads((tmp_path / "sizes" / "best.json").read_text())
    sel = best["selection"]
    tgt = build_target(cfg)
    height = fidelity_statistics(tgt.trees[0], *size_topology(cfg, "target"))["height"]
    assert sel["sizes"] == {"limits": {"height": 0.2}, "target": {"height": height}}
    # the same candidates and held-out distances; each one's height error recomputed outside the fit
    assert [(c["evaluation"], c["heldout"]) for c in sel["candidates"]] == [
        (c["evaluation"], c["heldout"]) for c in plain_sel["candidates"]
    ]
    with started_workers(cfg, tgt):
        ctx = worker_context()
        for c in sel["candidates"]:
            trees = [grow_tree(cfg, c["params"], s[0]) for s in heldout_seeds(cfg.seed, 6, 1)]
            mean = np.mean([fidelity_statistics(t, *ctx.size_topology)["height"] for t in trees])
            assert c["size_errors"]["height"] == pytest.approx(mean / height - 1.0, rel=1e-12)
            assert c["within"] == (abs(mean / height - 1.0) <= 0.2)
    within = [c for c in sel["candidates"] if c["within"]]
    assert 0 < len(within) < len(sel["candidates"])
    answer = min(within, key=lambda c: c["heldout"])
    assert sel["chosen"] == best["evaluation"] == answer["evaluation"] != plain_sel["chosen"]
    assert answer["heldout"] > min(c["heldout"] for c in sel["candidates"])  # not the lowest of all
    from bforest_core.report.build import write_report

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        write_report(tmp_path / "sizes", figures=False, html=False)
    md = (tmp_path / "sizes" / "report.md").read_text()
    assert f"among the {len(within)} whose held-out trees' mean kept within [select] sizes (height 20 %" in md
    assert "| held-out height |" in md and f"| {100 * answer['size_errors']['height']:+.1f} % |" in md


def test_select_sizes_none_within_warns_and_keeps_the_lowest(toy_plugin, tmp_path):
    p = noisy_config(tmp_path)
    p.write_text(p.read_text() + "sizes = { height = 0.05 }\n")
    with pytest.warns(UserWarning, match=r"none of the 5 candidates' held-out trees kept within \[select\] sizes"):
        bf.fit(bf.load_config(p), tmp_path / "run", progress=False)
    sel = json.loads((tmp_path / "run" / "best.json").read_text())["selection"]
    assert not any(c["within"] for c in sel["candidates"])
    assert sel["chosen"] == min(sel["candidates"], key=lambda c: c["heldout"])["evaluation"]


@pytest.mark.parametrize(
    "sizes, message",
    [
        ("{ hieght = 0.1 }", r"select\.sizes: no statistic 'hieght' in the clones' fidelity table \(it has: .*height"),
        ("{ height = 1.5 }", r"select\.sizes.*between 0 and 1"),
    ],
)
def test_select_sizes_naming_no_statistic_or_no_fraction_are_refused_before_the_search(
    toy_plugin, tmp_path, sizes, message
):
    p = noisy_config(tmp_path)
    p.write_text(p.read_text() + f"sizes = {sizes}\n")
    with pytest.raises(bf.ConfigError, match=message):
        bf.fit(bf.load_config(p), tmp_path / "run", progress=False)
    assert not (tmp_path / "run").exists()


def test_held_out_sizes_average_the_values_the_trees_have_as_the_fidelity_table_does():
    """A failed set has no sizes; a tree without a value (no DBH below 1.3 m) is left out of that
    statistic's mean, as the fidelity table leaves such a clone out; no tree with one: NaN, which
    no size limit holds."""
    nan = float("nan")
    known = {
        ("p", (1,)): {"status": "ok", "sizes": {"height": 10.0, "dbh": 0.10}},
        ("p", (2,)): {"status": "ok", "sizes": {"height": 12.0, "dbh": nan}},
        ("p", (3,)): {"status": "error", "sizes": None},
        ("q", (1,)): {"status": "ok", "sizes": {"height": 9.0, "dbh": nan}},
        ("r", (1,)): {"status": "error", "sizes": None},
    }
    got = heldout_sizes(known, "p", [[1], [2], [3]], ("height", "dbh"))
    assert got == {"height": 11.0, "dbh": 0.10}
    assert size_errors(got, {"height": 10.0, "dbh": 0.08}) == pytest.approx({"height": 0.1, "dbh": 0.25})
    q = heldout_sizes(known, "q", [[1]], ("height", "dbh"))
    assert q["height"] == 9.0 and np.isnan(q["dbh"])
    assert heldout_sizes(known, "r", [[1]], ("height",)) is None
    # a worker's set of several trees is averaged the same way (heldout_task), by the one rule
    trees = [{"height": 10.0, "dbh": nan}, {"height": 14.0, "dbh": 0.2}, {"height": 12.0}]
    assert finite_means(trees, ("height", "dbh")) == {"height": 12.0, "dbh": 0.2}
