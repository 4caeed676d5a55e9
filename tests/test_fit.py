"""The fit pipeline on the toy plugin: store, seeds, executors, resume, failures, clones."""

import importlib
import json
import os
import signal
import sqlite3
import subprocess
import sys
import time

import numpy as np
import pytest

import bforest_core as bf
from bforest_core.pipeline.store import RunStore
from conftest import TOY_DIR, fit_killed_after, toy_config

fit_mod = importlib.import_module("bforest_core.pipeline.fit")


def _evals(run):
    return [(e.idx, e.params, e.seeds, e.distance, e.status) for e in RunStore.open(run).evaluations()]


def test_fit_writes_run_directory_and_improves(toy_plugin, tmp_path):
    cfg = bf.load_config(toy_config(tmp_path, budget=48))
    res = bf.fit(cfg, tmp_path / "run", progress=False)
    run = tmp_path / "run"
    assert res.n_evaluations == 48 and "budget" in res.stop_reason
    evs = RunStore.open(run).evaluations()
    assert [e.idx for e in evs] == list(range(48))
    assert all(e.status == "ok" and e.seconds >= 0 and ":" in e.worker for e in evs)
    # the toy target has angle 30, segments 12: the best of 48 random points is far better than the mean
    d = np.array([e.distance for e in evs])
    assert res.distance <= np.quantile(d, 0.1)
    best = json.loads((run / "best.json").read_text())
    assert set(best) >= {"params", "distance", "per_set", "target_metrics", "model_metrics", "relative_errors"}
    assert best["params"]["noise"] == 2.0 and isinstance(best["params"]["segments"], int)
    assert (run / "config.toml").exists() and (run / "best_tree.txt").exists()
    assert json.loads((run / "distance.json").read_text())["distance"] == "toy-distance"
    # the toy model grows 2 cylinders per trunk segment: the written best tree is the best fit
    assert bf.read_qsm(run / "best_tree.txt").n == 2 * best["params"]["segments"]
    assert bf.read_qsm(run / "target.txt").n == 2 * 12
    assert bf.load_config(run / "config.toml").ssm.free["angle"].upper == 80.0
    recs = RunStore.open(run).log_records()
    assert len(recs) == 6 and recs[-1]["best"] == pytest.approx(res.distance)


def test_same_seed_same_result_serial_and_process(toy_plugin, tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    a = bf.fit(bf.load_config(toy_config(tmp_path / "a", budget=24)), tmp_path / "a" / "run", progress=False)
    pb = toy_config(tmp_path / "b", executor="process", executor_settings="workers = 2", budget=24)
    # each simulation sleeps long enough that the second worker has started before the first is
    # through the 24 (0.02 s was not enough on a loaded machine: one worker did them all)
    pb.write_text(pb.read_text().replace('kind = "toy"\n', 'kind = "toy"\nsleep = 0.1\n', 1))
    cfg_b = bf.load_config(pb)
    b = bf.fit(cfg_b, tmp_path / "b" / "run", progress=False)
    ea, eb = _evals(tmp_path / "a" / "run"), _evals(tmp_path / "b" / "run")
    assert ea == eb and a.params == b.params and a.distance == b.distance
    workers = {e.worker for e in RunStore.open(tmp_path / "b" / "run").evaluations()}
    assert len(workers) == 2


def test_resume_after_crash_repeats_nothing_and_matches(toy_plugin, tmp_path, monkeypatch):
    full = bf.fit(bf.load_config(toy_config(tmp_path, budget=40)), tmp_path / "full", progress=False)
    fit_killed_after(bf.load_config(toy_config(tmp_path, budget=40)), tmp_path / "crashed", 19, monkeypatch)
    assert RunStore.open(tmp_path / "crashed").count() == 19
    simulated = {"n": 0}
    real_task = fit_mod.evaluate_task

    def counting(task):
        simulated["n"] += 1
        return real_task(task)

    monkeypatch.setattr(fit_mod, "evaluate_task", counting)
    res = bf.fit(
        bf.load_config(tmp_path / "crashed" / "config.toml"), tmp_path / "crashed", resume=True, progress=False
    )
    assert simulated["n"] == 40 - 19
    assert _evals(tmp_path / "crashed") == _evals(tmp_path / "full")
    assert res.params == full.params and res.distance == full.distance


def test_resume_refuses_other_config(toy_plugin, tmp_path):
    bf.fit(bf.load_config(toy_config(tmp_path, budget=8)), tmp_path / "run", progress=False)
    other = bf.load_config(toy_config(tmp_path, budget=9))
    other.seed = 4
    with pytest.raises(bf.BayesForestError, match="config differs.*seed: 3 -> 4"):
        bf.fit(other, tmp_path / "run", resume=True, progress=False)
    with pytest.raises(bf.BayesForestError, match="already holds a run"):
        bf.fit(other, tmp_path / "run", progress=False)
    # another executor is fine: results never depend on it
    p = toy_config(tmp_path, budget=8, executor="process", executor_settings="workers = 2")
    res = bf.fit(bf.load_config(p), tmp_path / "run", resume=True, progress=False)
    assert res.n_evaluations == 8 and 'kind = "process"' in (tmp_path / "run" / "config.toml").read_text()
    assert res.already_finished  # the run had finished: it says so


def test_failing_and_hanging_simulations_are_logged(toy_plugin, tmp_path):
    p = toy_config(tmp_path, budget=16)
    text = p.read_text().replace('kind = "toy"\n', 'kind = "toy"\nfail_above = 40.0\n', 1)
    p.write_text(text)
    res = bf.fit(bf.load_config(p), tmp_path / "fail", progress=False)
    evs = RunStore.open(tmp_path / "fail").evaluations()
    failed = [e for e in evs if e.status != "ok"]
    assert failed and all(e.status == "collapsed" and e.distance == 1.0 and e.params["angle"] > 40 for e in failed)
    assert res.n_evaluations == 16
    # a hanging model is stopped by the per-evaluation time limit
    (tmp_path / "h").mkdir()
    p2 = toy_config(tmp_path / "h", budget=3)
    t2 = p2.read_text().replace('kind = "toy"\n', 'kind = "toy"\nsleep = 30.0\n', 1) + "\n[objective]\ntimeout = 0.3\n"
    t2 = t2.replace('[optimizer]\nkind = "toy-random"\n', '[optimizer]\nkind = "toy-random"\nbatch = 3\n')
    p2.write_text(
        t2.replace('[target.generate]\nssm = "toy"', '[target.generate]\nssm = "toy"\nsettings = { sleep = 0.0 }')
    )
    t0 = time.monotonic()
    bf.fit(bf.load_config(p2), tmp_path / "hang", progress=False)
    evs = RunStore.open(tmp_path / "hang").evaluations()
    assert [e.status for e in evs] == ["timeout"] * 3 and time.monotonic() - t0 < 20


def test_clones_table_and_summary(toy_plugin, tmp_path):
    bf.fit(bf.load_config(toy_config(tmp_path, budget=16)), tmp_path / "run", progress=False)
    from bforest_core.pipeline.clones import clones

    s = clones(tmp_path / "run", n=5, progress=False)
    assert s["ok"] == 5 and len(list((tmp_path / "run" / "clones").glob("clone_*.txt"))) == 5
    header = (tmp_path / "run" / "clones" / "clones.csv").read_text().splitlines()[0].split(",")
    assert header[:5] == ["index", "seed", "status", "file", "distance"] and "d_h" in header and "D[L]" in header
    seeds = [r["seed"] for r in s["rows"]]
    assert len(set(seeds)) == 5
    assert s["height"]["sd"] >= 0 and 0 <= s["d_h"]["mean"]


def _cli_env(toy_site):
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(toy_site), str(TOY_DIR), env.get("PYTHONPATH", "")])
    return env


def test_kill_9_then_resume_equals_uninterrupted(toy_plugin, tmp_path):
    """A real `bforest fit` process killed with SIGKILL mid-run, then `--resume`. The killed
    process waits at a gate after 12 simulations (12 evaluations), so it is killed there however
    fast or loaded the machine is."""
    p, gate = toy_config(tmp_path, budget=48), tmp_path / "gate"
    p.write_text(
        p.read_text()
        .replace('kind = "toy"\n', f'kind = "toy"\ngate = "{gate}"\ngate_after = 12\n', 1)
        .replace('[target.generate]\nssm = "toy"', '[target.generate]\nssm = "toy"\nsettings = {}')
    )
    gate.touch()  # the uninterrupted fit passes the gate
    exe = [sys.executable, "-m", "bforest_core.cli"]
    env = _cli_env(toy_plugin)
    subprocess.run(
        exe + ["fit", str(p), "-o", str(tmp_path / "full"), "-q", "--no-report"],
        env=env,
        check=True,
        capture_output=True,
    )
    gate.unlink()
    proc = subprocess.Popen(
        exe + ["fit", str(p), "-o", str(tmp_path / "killed"), "-q", "--no-report"],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    db = tmp_path / "killed" / "evaluations.sqlite"
    deadline = time.monotonic() + 60
    n = 0
    while time.monotonic() < deadline:
        if db.exists():
            try:
                n = sqlite3.connect(db).execute("SELECT COUNT(*) FROM evaluations").fetchone()[0]
            except sqlite3.Error:
                n = 0
            if n >= 12:
                break
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert RunStore.open(tmp_path / "killed").count() == 12
    gate.touch()
    r = subprocess.run(
        exe
        + [
            "fit",
            str(tmp_path / "killed" / "config.toml"),
            "-o",
            str(tmp_path / "killed"),
            "--resume",
            "-q",
            "--no-report",
        ],
        env=env,
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0, r.stderr
    assert _evals(tmp_path / "killed") == _evals(tmp_path / "full")
    assert (
        json.loads((tmp_path / "killed" / "best.json").read_text())["params"]
        == json.loads((tmp_path / "full" / "best.json").read_text())["params"]
    )


def test_cli_fit_bad_input_one_line(toy_plugin, tmp_path, capsys):
    from bforest_core.cli import main

    p = toy_config(tmp_path)
    p.write_text(
        p.read_text().replace(
            "free.angle = { lower = 5.0, upper = 80.0 }", "free.angle = { lower = 5.0, upper = 800.0 }"
        )
    )
    assert main(["fit", str(p), "-o", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "ssm.free.angle" in err and "\n" not in err
    assert main(["fit", str(tmp_path / "missing.toml")]) == 2
    assert "file not found" in capsys.readouterr().err


def test_explicit_model_seeds(toy_plugin, tmp_path):
    p = toy_config(tmp_path, budget=8)
    p.write_text(p.read_text() + "\n[objective]\nmodel_seeds = [2, 5]\n")
    bf.fit(bf.load_config(p), tmp_path / "run", progress=False)
    assert {tuple(e.seeds) for e in RunStore.open(tmp_path / "run").evaluations()} == {(2, 5)}


def test_compare_optimizers_on_equal_budgets(toy_plugin, tmp_path):
    from bforest_core.pipeline.compare import compare

    # budget 100 is not a multiple of emcee's default 16 walkers: every optimiser still spends all of it
    res = compare(
        toy_config(tmp_path), ["ga", "de", "emcee", "toy-random"], budget=100, repeats=2, out_dir=tmp_path / "cmp"
    )
    assert [t["optimizer"] for t in res["table"]] == ["ga", "de", "emcee", "toy-random"]
    assert len(res["runs"]) == 8 and all(r["evaluations"] == 100 for r in res["runs"])
    for curves in res["curves"].values():
        assert len(curves) == 2 and all(len(c) == 100 and (np.diff(c) <= 0).all() for c in curves)
    # repeats use different run seeds, so their evaluation sequences differ
    assert not np.array_equal(res["curves"]["ga"][0], res["curves"]["ga"][1])
    from bforest_core.report.comparison import write_compare_figure

    fig = write_compare_figure(res)
    assert fig.exists() and fig.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "](compare.png)" in (tmp_path / "cmp" / "compare.md").read_text()
    assert "median best" in res["table_text"] and (tmp_path / "cmp" / "compare.json").exists()


def test_compare_draws_its_repeats_run_seeds_from_the_base_seeds_own_stream(toy_plugin, tmp_path):
    """A repeat's run seed comes from the base seed's SeedSequence stream (tag 6), not base + r: a
    comparison from base seed 1 and one from base seed 2 share no run (they shared one before)."""
    from bforest_core.pipeline.compare import compare
    from bforest_core.pipeline.seeds import repeat_seeds

    s1, s2 = repeat_seeds(1, 3), repeat_seeds(2, 3)
    expected = [int(s.generate_state(1, np.uint32)[0]) for s in np.random.SeedSequence([1, 6]).spawn(3)]
    assert s1 == expected and len(set(s1)) == 3 and not set(s1) & set(s2)
    assert repeat_seeds(1, 2) == s1[:2]  # a longer comparison keeps the shorter one's runs
    text = toy_config(tmp_path, budget=6).read_text()
    runs = {}
    for base in (1, 2):
        cfg = tmp_path / f"base{base}.toml"
        cfg.write_text(text.replace("\nseed = 3\n", f"\nseed = {base}\n", 1))
        res = compare(cfg, ["toy-random"], budget=6, repeats=2, out_dir=tmp_path / f"cmp{base}")
        runs[base] = [bf.load_config(tmp_path / f"cmp{base}" / f"toy-random-{r}" / "config.toml").seed for r in (0, 1)]
        assert [r["seed"] for r in res["runs"]] == runs[base] == repeat_seeds(base, 2)
    assert not set(runs[1]) & set(runs[2])


def test_compare_lets_each_optimiser_lift_its_own_limits_for_the_budget(toy_plugin, tmp_path):
    """A plugin's optimiser with a length limit of its own (toy-random's ``batches``) spends the
    whole budget in a comparison through its ``budget_settings``; a fit keeps the limit."""
    from bforest_core.pipeline.compare import compare

    p = toy_config(tmp_path, optimizer_settings="batch = 4\nbatches = 2", budget=40)
    assert bf.fit(bf.load_config(p), tmp_path / "fit", progress=False).n_evaluations == 8
    res = compare(p, ["toy-random"], budget=22, repeats=1, out_dir=tmp_path / "cmp")
    assert [r["evaluations"] for r in res["runs"]] == [22]
    run_cfg = bf.load_config(tmp_path / "cmp" / "toy-random-0" / "config.toml")
    assert run_cfg.optimizer.batch == 4 and run_cfg.optimizer.batches == 6  # the config's batch is kept


def test_a_fit_that_failed_before_its_first_evaluation_does_not_block_the_retry(toy_plugin, tmp_path):
    bad = toy_config(tmp_path, budget=4)
    text = bad.read_text()
    bad.write_text(
        text.replace(text[text.index("[target.generate]") : text.index("[ssm]")], '[target]\nqsm = "missing.txt"\n')
    )  # fails while reading the target
    with pytest.raises((bf.BayesForestError, FileNotFoundError)):
        bf.fit(bf.load_config(bad), tmp_path / "run", progress=False)
    assert not (tmp_path / "run" / "evaluations.sqlite").exists()  # refused before the run was written
    res = bf.fit(bf.load_config(toy_config(tmp_path, budget=4)), tmp_path / "run", progress=False)
    assert res.n_evaluations == 4
    with pytest.raises(bf.BayesForestError, match="--resume.*--overwrite"):
        bf.fit(bf.load_config(toy_config(tmp_path, budget=4)), tmp_path / "run", progress=False)


def test_compare_threshold_by_name_and_the_configs_own_settings(toy_plugin, tmp_path):
    import tomllib

    from bforest_core.pipeline.compare import compare

    cfg = toy_config(tmp_path, optimizer="ga", optimizer_settings="population = 6")
    res = compare(cfg, ["ga", "toy-random"], budget=24, repeats=2, out_dir=tmp_path / "cmp", threshold="ga")
    ga_best = [r["best"] for r in res["runs"] if r["optimizer"] == "ga"]
    assert res["threshold"] == pytest.approx(float(np.median(ga_best)))
    # the GA kept the config's population of 6: its first generation is 6 evaluations wide
    run_cfg = tomllib.loads(RunStore.open(tmp_path / "cmp" / "ga-0").config_path.read_text())
    assert run_cfg["optimizer"]["population"] == 6
    with pytest.raises(ValueError, match="neither a distance nor one of the compared"):
        compare(cfg, ["ga"], budget=6, repeats=1, out_dir=tmp_path / "cmp2", threshold="cma")


def test_compare_keeps_earlier_runs_and_adds_an_optimiser_with_resume(toy_plugin, tmp_path):
    from bforest_core.pipeline.compare import compare
    from bforest_core.pipeline.store import RunDirError

    cfg = toy_config(tmp_path)
    first = compare(cfg, ["ga"], budget=24, repeats=2, out_dir=tmp_path / "cmp")
    stamp = (tmp_path / "cmp" / "ga-0" / "evaluations.sqlite").stat().st_mtime_ns
    with pytest.raises(RunDirError, match="ga-0.*--resume.*--overwrite"):
        compare(cfg, ["ga", "toy-random"], budget=24, repeats=2, out_dir=tmp_path / "cmp")
    res = compare(cfg, ["ga", "toy-random"], budget=24, repeats=2, out_dir=tmp_path / "cmp", resume=True)
    # the GA's runs were read back, not fitted again: same curves, same wall times, same log
    for a, b in zip(first["curves"]["ga"], res["curves"]["ga"]):
        np.testing.assert_array_equal(a, b)
    assert [r["seconds"] for r in res["runs"][:2]] == [r["seconds"] for r in first["runs"]]
    assert (tmp_path / "cmp" / "ga-0" / "evaluations.sqlite").stat().st_mtime_ns == stamp
    assert [t["optimizer"] for t in res["table"]] == ["ga", "toy-random"]
    assert all(r["evaluations"] == 24 for r in res["runs"])


def test_compare_curves_never_count_a_failed_simulation_as_a_fit(toy_plugin, tmp_path):
    """With a penalty below every real distance (0.0), a failure is still no fit: the curves and
    the threshold count only grown trees, and each curve ends at the run's best.json distance."""
    import json

    from bforest_core.pipeline.compare import compare

    p = toy_config(tmp_path)
    p.write_text(
        p.read_text().replace('kind = "toy"\n', 'kind = "toy"\nfail_above = 50.0\n') + "[objective]\npenalty = 0.0\n"
    )
    res = compare(p, ["toy-random"], budget=30, repeats=2, out_dir=tmp_path / "cmp")
    for r, curve in enumerate(res["curves"]["toy-random"]):
        evs = RunStore.open(tmp_path / "cmp" / f"toy-random-{r}").evaluations()
        assert any(e.status != "ok" for e in evs) and any(e.status == "ok" for e in evs)
        best = json.loads((tmp_path / "cmp" / f"toy-random-{r}" / "best.json").read_text())["distance"]
        assert curve[-1] == best > 0.0
    assert res["threshold"] > 0.0
    # a curve that starts at inf (a failure first) beside a grown tree draws without a warning
    import warnings

    from bforest_core.report.comparison import write_compare_figure

    res["curves"]["toy-random"][0][0] = np.inf
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert write_compare_figure(res).exists()


def test_compare_scores_best_points_on_held_out_model_seeds(toy_plugin, tmp_path):
    """--heldout: each run's best point (after N evaluations and final) is scored on K sets of
    model seeds no fit used; the values are recomputed here from the model, the features and
    the distance directly, seed by seed."""
    import json

    from bforest_core.pipeline.compare import compare
    from bforest_core.pipeline.seeds import heldout_seeds
    from bforest_core.pipeline.target import build_target

    p = toy_config(tmp_path)
    p.write_text(p.read_text() + "[objective]\nseeds = 2\n")
    res = compare(
        p, ["ga", "toy-random"], budget=24, repeats=2, out_dir=tmp_path / "cmp", threshold="ga", heldout=3, at=[8]
    )
    cfg = bf.load_config(p)
    sets = heldout_seeds(cfg.seed, 3, 2)
    own = {
        s
        for r in range(2)
        for name in ("ga", "toy-random")
        for e in RunStore.open(tmp_path / "cmp" / f"{name}-{r}").evaluations()
        for s in e.seeds
    }
    assert len({s for st in sets for s in st} | own) == 6 + len(own)  # 6 held-out seeds, none a fit's
    ssm, feats, dist = (
        bf.component("ssm", "toy"),
        bf.component("features", "toy-features"),
        bf.component("distance", "toy-distance"),
    )
    target = build_target(cfg).U["L"]
    for row in res["runs"]:
        store = RunStore.open(tmp_path / "cmp" / f"{row['optimizer']}-{row['repeat']}")
        for cp, before in (("8", 8), ("final", None)):
            e = store.best(before=before)
            want = np.mean(
                [
                    np.mean(
                        [
                            dist.compute(feats.extract(ssm.simulate({**e.params, "noise": 2.0}, s))["L"], target)
                            for s in st
                        ]
                    )
                    for st in sets
                ]
            )
            got = row["heldout"][cp]
            assert got["heldout"] == pytest.approx(want, rel=1e-12)
            assert (got["own"], got["evaluations"]) == (e.distance, e.idx + 1)
        assert row["heldout"]["final"]["own"] == row["best"]
    # medians over repeats, the GA's median held-out final best as the held-out threshold
    ga_final = [r["heldout"]["final"]["heldout"] for r in res["runs"] if r["optimizer"] == "ga"]
    assert res["heldout"]["threshold"] == pytest.approx(float(np.median(ga_final)))
    for t in res["table"]:
        mine = [r["heldout"]["8"]["heldout"] for r in res["runs"] if r["optimizer"] == t["optimizer"]]
        assert t["heldout"]["8"] == pytest.approx(float(np.median(mine)))
    held_lines = res["table_text"].split("held out:")[1].splitlines()
    assert held_lines[2].split() == ["optimizer", "after", "8", "final"]
    ga_line = next(l for l in held_lines if l.startswith("ga ")).split()
    # the median of two is their mean: the lower one is at or below it, the higher one only if equal
    thr = res["heldout"]["threshold"]
    assert ga_line[-2:] == [f"{np.median(ga_final):.4f}", f"{sum(v <= thr for v in ga_final)}/2"]
    saved = json.loads((tmp_path / "cmp" / "compare.json").read_text())
    assert saved["heldout"]["sets"] == 3 and saved["heldout"]["model_seeds_per_set"] == 2
    assert "held out" in (tmp_path / "cmp" / "compare.md").read_text()
    from bforest_core.report.comparison import write_compare_figure

    assert write_compare_figure(res).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(ValueError, match="--at, which needs --heldout"):
        compare(p, ["ga"], budget=24, repeats=2, out_dir=tmp_path / "cmp", resume=True, at=[8])


def test_held_out_scores_are_kept_in_the_runs_and_not_grown_twice(toy_plugin, tmp_path, monkeypatch):
    """The held-out scores live in each run directory: a later comparison without --heldout
    (which rewrites compare.json) loses none of them, and --heldout again grows no tree and gives
    the same values; a changed objective scores anew."""
    import json

    import bforest_core.pipeline.compare as cmp_mod

    p = toy_config(tmp_path)
    p.write_text(p.read_text() + "[objective]\nseeds = 2\n")
    first = cmp_mod.compare(p, ["ga"], budget=24, repeats=2, out_dir=tmp_path / "cmp", heldout=3, at=[8])
    cmp_mod.compare(p, ["ga"], budget=24, repeats=2, out_dir=tmp_path / "cmp", resume=True)
    assert "heldout" not in json.loads((tmp_path / "cmp" / "compare.json").read_text())
    from bforest_core.pipeline.heldout import scoring_fingerprint

    for r in range(2):
        with RunStore.open(tmp_path / "cmp" / f"ga-{r}") as store:
            assert store.heldout_scores(scoring_fingerprint(bf.load_config(p)))
    grown = []
    import bforest_core.pipeline.heldout as heldout_mod

    real = heldout_mod.heldout_task
    monkeypatch.setattr(heldout_mod, "heldout_task", lambda task: grown.append(task) or real(task))
    again = cmp_mod.compare(p, ["ga"], budget=24, repeats=2, out_dir=tmp_path / "cmp", resume=True, heldout=3, at=[8])
    assert grown == []
    assert [r["heldout"] for r in again["runs"]] == [r["heldout"] for r in first["runs"]]
    # more sets: only the new ones are grown (3 more sets of 2 seeds for each distinct point)
    cmp_mod.compare(p, ["ga"], budget=24, repeats=2, out_dir=tmp_path / "cmp", resume=True, heldout=6)
    points = {json.dumps(RunStore.open(tmp_path / "cmp" / f"ga-{r}").best().params, sort_keys=True) for r in range(2)}
    assert len(grown) == 3 * len(points)
    # another objective is another score: grown again, the earlier scores kept beside it
    from bforest_core.pipeline.compare import score_heldout
    from bforest_core.pipeline.target import build_target

    cfg = bf.load_config(p).model_copy(
        update={"objective": bf.load_config(p).objective.model_copy(update={"penalty": 2.0})}
    )
    grown.clear()
    score_heldout({"ga": [tmp_path / "cmp" / "ga-0"]}, cfg, build_target(cfg), 3)
    assert len(grown) == 3
    with RunStore.open(tmp_path / "cmp" / "ga-0") as store:
        assert len(store._con.execute("SELECT DISTINCT scoring FROM heldout").fetchall()) == 2


def test_bounds_scaled_by_a_measure_of_the_target(toy_plugin, tmp_path):
    from bforest_core.metrics import measure_tree
    from bforest_core.pipeline.target import load_target_trees

    p = toy_config(tmp_path, budget=16)
    scaled = 'free.angle = { lower = 1.0, upper = 5.0, init_upper = 4.0, scaled_by = "height" }'
    p.write_text(p.read_text().replace("free.angle = { lower = 5.0, upper = 80.0 }", scaled))
    cfg = bf.load_config(p)
    h = measure_tree(load_target_trees(cfg)[0]).height
    assert 2.0 < h < 16.0  # the toy tree of 12 segments: the resolved bounds stay inside angle's 0-90
    bf.fit(cfg, tmp_path / "run", progress=False)
    fp = bf.load_config(tmp_path / "run" / "config.toml").ssm.free["angle"]
    assert fp.scaled_by is None
    assert (fp.lower, fp.upper, fp.init_upper) == pytest.approx((h, 5 * h, 4 * h), rel=1e-5)
    angles = [e.params["angle"] for e in RunStore.open(tmp_path / "run").evaluations()]
    assert min(angles) >= fp.lower and max(angles) <= fp.upper
    # resuming with the recipe itself resolves to the same bounds: the run is the same run
    res = bf.fit(bf.load_config(p), tmp_path / "run", resume=True, progress=False)
    assert res.already_finished
    # a resolved bound beyond the model's range (angle: 0-90 deg) is moved to it, with a warning
    p.write_text(p.read_text().replace(scaled, scaled.replace("upper = 5.0", "upper = 50.0")))
    with pytest.warns(
        UserWarning, match=r"ssm\.free\.angle: 1-50 x the height of .* \([\d.]+ m\).* the search keeps to \["
    ):
        bf.fit(bf.load_config(p), tmp_path / "run2", progress=False)
    assert bf.load_config(tmp_path / "run2" / "config.toml").ssm.free["angle"].upper == 90.0
    # nothing left of the range: an error naming the parameter, the measure and the range
    p.write_text(p.read_text().replace("lower = 1.0, upper = 50.0, init_upper = 4.0", "lower = 40.0, upper = 50.0"))
    with pytest.raises(bf.ConfigError, match=r"ssm\.free\.angle: 40-50 x the height .* outside the model's range"):
        bf.fit(bf.load_config(p), tmp_path / "run3", progress=False)
    assert not (tmp_path / "run3" / "config.toml").exists()  # nothing written but the lock
    from bforest_core.pipeline.checks import preflight  # `bforest config check` says the same

    with pytest.raises(bf.ConfigError, match=r"40-50 x the height .* outside the model's range"):
        preflight(bf.load_config(p))
    # a study that draws from the bounds without a fit's target refuses them by name
    from bforest_core.pipeline.calibrate import _study_spec

    with pytest.raises(bf.ConfigError, match=r"ssm\.free\.angle: bounds scaled by the target's height"):
        _study_spec(bf.load_config(p))


def test_scaled_bounds_are_checked_when_the_config_is_read(toy_plugin, tmp_path):
    p = toy_config(tmp_path)
    text = p.read_text()
    p.write_text(text.replace("upper = 80.0 }", 'upper = 80.0, scaled_by = "girth" }'))
    with pytest.raises(bf.ConfigError, match=r"scaled_by"):
        bf.load_config(p)
    p.write_text(text.replace("lower = 5.0, upper = 80.0 }", 'lower = -1.0, upper = 2.0, scaled_by = "height" }'))
    with pytest.raises(bf.ConfigError, match=r"must be >= 0: the bounds are multiples of height"):
        bf.load_config(p)


def test_the_search_runs_on_one_blas_thread_on_any_machine(toy_plugin, tmp_path, monkeypatch):
    """The stand benchmark (issue 75) found SOT fits of one tree, run seed and recipe ending on
    other answers in a 2-thread process and in a one-thread Dask worker: lq-CMA-ES's linear algebra
    rounds with the number of BLAS threads and the runs parted at the last digit after ~900
    evaluations. The search now runs on one BLAS thread wherever it runs; the limit ends with it."""
    from threadpoolctl import threadpool_info, threadpool_limits

    from bforest_core.pipeline import fit as fit_module

    def blas_threads():
        return [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]

    seen = []
    call = fit_module.Evaluator.__call__

    def watched(self, X):
        seen.append(blas_threads())
        return call(self, X)

    monkeypatch.setattr(fit_module.Evaluator, "__call__", watched)
    with threadpool_limits(limits=2, user_api="blas"):
        assert blas_threads() and set(blas_threads()) == {2}  # the machine's BLAS takes 2 threads
        bf.fit(bf.load_config(toy_config(tmp_path, budget=8)), tmp_path / "run", progress=False)
        assert set(blas_threads()) == {2}
    assert seen and all(t and set(t) == {1} for t in seen), seen
