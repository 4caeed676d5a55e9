"""Clones: a set that only grows unless asked, fidelity against the target, reference trees."""

import json
import shutil

import numpy as np
import pytest

import bforest_core as bf
from bforest_core.pipeline.clones import ClonesError, clones
from bforest_core.pipeline.fidelity import bound_flags, fidelity_table, fidelity_text, fidelity_warnings
from conftest import toy_config


# ------------------------------------------------------------------------------ pure functions
def test_fidelity_table_known_answers():
    target = {"height": 10.0, "dbh": 0.2, "n_branches_o1": 0.0}
    clones_ = [{"height": 9.0, "dbh": 0.25, "n_branches_o1": 3}, {"height": 11.0, "dbh": 0.35, "n_branches_o1": 5}]
    rows = {r["statistic"]: r for r in fidelity_table(target, clones_, {"height": "m", "dbh": "m"})}
    assert rows["height"]["mean"] == 10.0 and rows["height"]["error"] == 0.0
    assert rows["height"]["sd"] == pytest.approx(np.std([9, 11], ddof=1)) and rows["height"]["unit"] == "m"
    assert rows["dbh"]["error"] == pytest.approx(0.5)
    assert (rows["height"]["p5"], rows["height"]["p95"]) == pytest.approx((9.1, 10.9))  # linear percentiles
    assert rows["n_branches_o1"]["error"] is None  # a target of 0 has no relative error
    warns = fidelity_warnings(list(rows.values()))
    assert warns == ["clones miss the target's DBH (1.3 m) [dbh]: mean 0.3 m vs 0.2 m (+50.0 %, limit ±20 %)"]
    text = fidelity_text(list(rows.values()), [], warns)
    assert "WARNING: clones miss the target's DBH (1.3 m) [dbh]" in text
    # one convention: percent with its limit, and a mark on the row beyond it
    assert "DBH (1.3 m)" in text and "+50.0 %   ±20 % !" in text and "9.1–10.9" in text


def test_warning_limit_is_twenty_percent_of_height_dbh_and_crown():
    rows = fidelity_table(
        {"height": 10.0, "crown_spread": 4.0, "length_o1": 100.0},
        [{"height": 8.1, "crown_spread": 5.2, "length_o1": 10.0}],
    )
    warns = fidelity_warnings(rows)
    assert len(warns) == 1 and "[crown_spread]" in warns[0]  # height -19 % passes; length has no limit


def test_a_stem_much_longer_than_the_trees_is_warned_of():
    # a 20 m stem grown 26.6 m long along its axis on a tree of the same height winds or bends
    # over: +33 % beyond the 30 % limit; 25 m (+25 %) within it
    rows = fidelity_table({"height": 18.0, "stem_length": 20.0}, [{"height": 17.5, "stem_length": 26.6}])
    warns = fidelity_warnings(rows)
    assert warns == ["clones miss the target's stem length [stem_length]: mean 26.6 m vs 20 m (+33.0 %, limit ±30 %)"]
    assert not fidelity_warnings(fidelity_table({"stem_length": 20.0}, [{"stem_length": 25.0}]))


def test_the_crown_offset_row_sets_the_clones_side_of_the_stem_beside_the_trees():
    # the tree's crown 0.8 crown radii off its stem towards +y; clones 0.8 off towards +x and -x
    # have a mean offset of 0: it lies 0.8 from the tree's (the warning); clones 0.7 and 0.5 off
    # towards +y lie 0.2 from it (within the limit 0.25)
    target = {"height": 18.0, "crown_offset_x": 0.0, "crown_offset_y": 0.8}
    apart = [
        {"height": 18.0, "crown_offset_x": 0.8, "crown_offset_y": 0.0},
        {"crown_offset_x": -0.8, "crown_offset_y": 0.0},
    ]
    rows = {r["statistic"]: r for r in fidelity_table(target, apart)}
    assert "crown_offset_x" not in rows and "crown_offset_y" not in rows  # one row for the vector
    r = rows["crown_offset"]
    assert (r["target"], r["mean"], r["error"], r["limit"]) == pytest.approx((0.8, 0.0, 0.8, 0.25))
    assert r["target_azimuth"] == pytest.approx(90.0) and r["warn"] and r["unit"] == "crown radii"
    assert r["p5"] == pytest.approx(0.8) and r["n"] == 2
    warns = fidelity_warnings(list(rows.values()))
    assert (
        len(warns) == 1 and "[crown_offset]" in warns[0] and "lies 0.80 crown radii from the target's 0.80" in warns[0]
    )
    text = fidelity_text(list(rows.values()), [], warns)
    assert "0.80    0.25 !" in text and "(towards 90 deg; clones 0 deg)" in text
    same = [{"crown_offset_x": 0.0, "crown_offset_y": 0.7}, {"crown_offset_x": 0.0, "crown_offset_y": 0.5}]
    r = next(x for x in fidelity_table(target, same) if x["statistic"] == "crown_offset")
    assert r["error"] == pytest.approx(0.2) and not r["warn"] and not fidelity_warnings([r])


def test_crown_base_and_branch_counts_have_limits_and_every_row_a_unit():
    from bforest_core.metrics import SUMMARY_UNITS

    target = {
        "crown_base_height": 2.0,
        "n_branches_o1": 50.0,
        "n_branches_o2": 100.0,
        "length_o1": 40.0,
        "volume_o0": 0.04,
        "profile_n_b0": 4.0,
    }
    clone = {
        "crown_base_height": 2.5,
        "n_branches_o1": 20.0,
        "n_branches_o2": 75.0,
        "length_o1": 20.0,
        "volume_o0": 0.05,
        "profile_n_b0": 1.0,
    }
    rows = {r["statistic"]: r for r in fidelity_table(target, [clone], SUMMARY_UNITS)}
    # crown base +25 % within its 30 %; first-order branches -60 % beyond it; second order -25 % within
    assert [rows[k]["warn"] for k in ("crown_base_height", "n_branches_o1", "n_branches_o2")] == [False, True, False]
    assert rows["length_o1"]["limit"] is None and not rows["length_o1"]["warn"]
    assert [rows[k]["unit"] for k in target] == ["m", "count", "count", "m", "m^3", "count"]
    assert rows["profile_n_b0"]["label"] == "order-1 branches based at 0-20 % of the height"
    warns = fidelity_warnings(list(rows.values()))
    assert warns == [
        "clones miss the target's branches of order 1 (base >= 1 cm) [n_branches_o1]: mean 20 vs 50 "
        "(-60.0 %, limit ±30 %)"
    ]
    rows["crown_base_height"]["error"] = -0.35
    assert len(fidelity_warnings(list(rows.values()))) == 2


def test_bound_flags():
    flags = bound_flags({"a": 0.02, "b": 0.5, "c": 9.9, "d": 3}, {"a": (0, 1), "b": (0, 1), "c": (0, 10)})
    assert flags == ["a = 0.02 is at its lower bound 0", "c = 9.9 is at its upper bound 10"]


# ------------------------------------------------------------------------------ the clone set
@pytest.fixture(scope="module")
def toy_fit(toy_plugin, tmp_path_factory):
    base = tmp_path_factory.mktemp("clones")
    cfg = bf.load_config(toy_config(base, budget=16))
    bf.fit(cfg, base / "run", progress=False)
    return base / "run"


def _files(run):
    return {p.name: p.read_bytes() for p in sorted((run / "clones").glob("clone_*.txt"))}


def test_the_clone_set_only_grows_unless_replaced(toy_fit, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(toy_fit, run)
    s = clones(run, n=2, progress=False)
    assert s["grown"] == 2 and s["count"] == 2
    first = _files(run)
    s = clones(run, n=4, progress=False)
    assert s["grown"] == 2 and s["count"] == 4
    now = _files(run)
    assert len(now) == 4 and all(now[k] == v for k, v in first.items())  # the first two untouched
    for n in (0, 1):  # fewer than exist: nothing is deleted
        s = clones(run, n=n, progress=False)
        assert s["grown"] == 0 and s["count"] == 4 and _files(run) == now
    # clone i has the same seed however the set was grown
    other = tmp_path / "other"
    shutil.copytree(toy_fit, other)
    clones(other, n=4, progress=False)
    assert _files(other) == now
    rows = json.loads((run / "clones" / "summary.json").read_text())["rows"]
    assert [r["index"] for r in rows] == [0, 1, 2, 3]
    header = (run / "clones" / "clones.csv").read_text().splitlines()[0]
    assert "height_m" in header and "base_diameter_m" in header and "crown_spread_m" in header
    s = clones(run, n=1, progress=False, replace=True)
    assert s["count"] == 1 and list(_files(run)) == ["clone_000.txt"]


def test_clones_of_other_parameters_are_not_mixed(toy_fit, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(toy_fit, run)
    clones(run, n=1, progress=False)
    best = json.loads((run / "best.json").read_text())
    best["params"]["angle"] = best["params"]["angle"] + 1.0
    (run / "best.json").write_text(json.dumps(best))
    with pytest.raises(ClonesError, match="other parameters.*--overwrite"):
        clones(run, n=2, progress=False)
    assert len(_files(run)) == 1


def test_fidelity_and_references_of_a_run(toy_fit, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(toy_fit, run)
    ref = tmp_path / "ref.txt"
    bf.write_tree(bf.read_qsm(run / "target.txt"), ref)  # the target itself: distance 0
    cfg = (run / "config.toml").read_text()
    assert "references = []" in cfg
    (run / "config.toml").write_text(cfg.replace("references = []", f'references = ["{ref}"]', 1))
    s = clones(run, n=3, progress=False)
    fid = s["fidelity"]
    stats = {r["statistic"]: r for r in fid["table"]}
    assert {"height", "dbh", "crown_spread", "crown_base_height", "n_branches_o1"} <= set(stats)
    # TreeQSM's volumes and crown measures too, each with its unit
    assert {"volume_o0", "branch_volume", "crown_length", "crown_ratio", "crown_volume_conv"} <= set(stats)
    assert "trunk_volume" not in stats  # the stem wood volume once, not twice (issue 78, item 7)
    assert (stats["crown_volume_conv"]["unit"], stats["crown_ratio"]["unit"]) == ("m^3", "fraction")
    assert stats["height"]["n"] == 3
    assert json.loads((run / "clones" / "fidelity.json").read_text())["table"] == fid["table"]
    assert len(s["references"]) == 1 and s["references"][0]["distance"] == pytest.approx(
        0.0, abs=1e-6
    )  # text file precision
    from bforest_core.report import write_report

    text = write_report(run, figures=False, html=False).read_text()
    assert "Fidelity: do the clones look like the target?" in text and "ref.txt" in text


def test_what_a_user_reads_says_base_diameter_and_percent(toy_fit, tmp_path, capsys):
    from bforest_core.cli.main import main
    from bforest_core.report import write_report

    run = tmp_path / "run"
    shutil.copytree(toy_fit, run)
    assert main(["clones", str(run), "-n", "2", "--no-report", "-q"]) == 0
    out = capsys.readouterr().out
    assert "girth" not in out.lower() and "base diameter (m)" in out and "height error (%)" in out
    assert "limit" in out and " %" in out
    text = write_report(run, figures=False, html=False).read_text()
    assert "girth" not in text.lower() and "base diameter (m)" in text
    assert "height error d_h (%)" in text and "| clones 5–95 % | error | limit |" in text and "| ±30 % |" in text
    tgt = str(run / "target.txt")
    assert main(["distance", tgt, tgt, "--lines", "16"]) == 0
    out = capsys.readouterr().out
    assert "girth" not in out.lower() and "base diameter (m)" in out and "0.0 %" in out


def test_a_simplified_target_prunes_every_grown_tree_alike(toy_plugin, tmp_path):
    # the toy tree: a trunk tapering from 0.2 to 0.05 m with one 0.02 m lateral per segment; a
    # QSM simplified below 0.03 m holds the trunk alone, and so does every tree the model grows
    p = toy_config(tmp_path, budget=4)
    p.write_text(p.read_text().replace("[target.generate]", "[target]\nprune_radius = 0.03\n[target.generate]"))
    cfg = bf.load_config(p)
    run = tmp_path / "run"
    bf.fit(cfg, run, progress=False)
    clones(run, n=2, progress=False)
    target = bf.read_qsm(run / "target.txt")
    assert target.n == 12 and target.radius.min() == pytest.approx(0.05)  # segments = 12, no laterals
    best = json.loads((run / "best.json").read_text())
    for f in ["best_tree.txt", *(f"clones/clone_00{i}.txt" for i in (0, 1))]:
        t = bf.read_qsm(run / f)
        assert t.n == best["params"]["segments"] and t.radius.min() >= 0.03 and t.n_branches == 1, f
    # the same fit without it: every tree carries its laterals
    p.write_text(p.read_text().replace("prune_radius = 0.03\n", ""))
    bf.fit(bf.load_config(p), tmp_path / "full", progress=False)
    assert bf.read_qsm(tmp_path / "full" / "best_tree.txt").radius.min() == pytest.approx(0.02)


def test_the_fidelity_table_counts_branches_by_the_size_terms_rule(toy_plugin, tmp_path):
    from bforest_core.pipeline.target import size_topology

    p = toy_config(tmp_path)
    base = p.read_text()
    assert size_topology(bf.load_config(p), "target") == (None, None)  # no size term: each tree's own branches
    term = (
        '\n[[objective.terms]]\nname = "size"\nfeatures = { kind = "tree-summary", topology = "subtree" }\n'
        'distance = { kind = "summary" }\n'
    )
    p.write_text(base + term)
    cfg = bf.load_config(p)
    assert size_topology(cfg, "target") == size_topology(cfg, "model") == ("subtree", None)
    # a per-side rule overrides it on its side, as it does the branch tables'
    p.write_text(base.replace("[ssm]\n", '[ssm]\ntopology = "thickest"\n', 1) + term)
    cfg = bf.load_config(p)
    assert (size_topology(cfg, "target")[0], size_topology(cfg, "model")[0]) == ("subtree", "thickest")
    # ... and the statistics it measures by it
    p.write_text(
        base + term.replace('topology = "subtree"', 'topology = "subtree", topology_statistics = ["n_branches_o1"]')
    )
    assert size_topology(bf.load_config(p), "model") == ("subtree", ["n_branches_o1"])
