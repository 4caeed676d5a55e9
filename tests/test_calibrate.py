"""``bforest calibrate``: coverage and SBC-rank arithmetic with known answers, a tiny study end to
end through the console script (files, resume without refitting, a stopped run resumed), bad input."""

import json
import shutil
import sqlite3
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bforest_core.pipeline.calibrate import (
    RANK_DRAWS,
    central_interval,
    coverage_table,
    prior_draw,
    rank_bins,
    rank_counts,
    rank_inside,
    sbc_rank,
    uniform_band,
)


# ------------------------------------------------------------------ arithmetic
def test_central_intervals_of_hand_made_posteriors():
    x = np.arange(10.0)  # equal weights: the 'hazen' quantiles of 0..9
    assert central_interval(x, np.ones(10), 50) == pytest.approx((2.0, 7.0))
    assert central_interval(x, np.ones(10), 90) == pytest.approx(np.percentile(x, [5, 95], method="hazen"))
    # two particles, the second with three times the weight: the weighted ECDF midpoints are 1/8 and 5/8
    lo, hi = central_interval(np.array([0.0, 4.0]), np.array([1.0, 3.0]), 50)
    assert lo == pytest.approx(4.0 * (0.25 - 0.125) / 0.5) and hi == pytest.approx(4.0)


def _row(truth, x, w=None):
    w = np.ones_like(x) if w is None else w
    p = {"truth": truth, "rank": sbc_rank(x, w, truth)}
    for lev in (50, 90):
        p[f"lo{lev}"], p[f"hi{lev}"] = central_interval(x, w, lev)
    return {"status": "ok", "params": {"a": p}}


def test_coverage_counts_truths_inside_and_outside():
    x = np.linspace(0.0, 1.0, 1001)  # posterior uniform on [0, 1]: 50 % interval [0.25, 0.75], 90 % [0.05, 0.95]
    rows = [
        _row(0.5, x),
        _row(0.3, x),
        _row(0.1, x),
        _row(0.97, x),
        _row(1.5, x),
        {"status": "fit failed: boom", "params": {}},
    ]
    t = coverage_table(rows, ["a"], [0.0], [2.0])[0]
    assert t["runs"] == 5  # the failed run is left out
    assert (t["covered50"], t["covered90"]) == (2, 3) and t["coverage90"] == pytest.approx(0.6)
    assert t["width50"] == pytest.approx(0.5 / 2.0, abs=1e-3) and t["width90"] == pytest.approx(0.9 / 2.0, abs=1e-3)
    assert sum(t["rank_counts"]) == 5


def test_an_integer_parameter_is_covered_as_its_rank_says():
    # a posterior all on one whole number: its central intervals are [3, 3] and hold the truth 3
    # every time (over-coverage); the rank, ties split at random, is uniform over 0..L and lies in
    # the central 50 % of the ranks half the time, in the central 90 % nine times in ten
    rng = np.random.default_rng(4)
    x, w = np.full(200, 3.0), np.ones(200)
    rows = []
    for _ in range(2000):
        p = {"truth": 3, "rank": sbc_rank(x, w, 3.0, RANK_DRAWS, rng)}
        for lev in (50, 90):
            p[f"lo{lev}"], p[f"hi{lev}"] = central_interval(x, w, lev)
        rows.append({"status": "ok", "params": {"k": p}})
    as_interval = coverage_table(rows, ["k"], [0.0], [6.0])[0]
    assert (as_interval["coverage50"], as_interval["coverage90"]) == (1.0, 1.0)
    t = coverage_table(rows, ["k"], [0.0], [6.0], integer=[True])[0]
    assert t["coverage50"] == pytest.approx(0.5, abs=0.035) and t["coverage90"] == pytest.approx(0.9, abs=0.02)
    # the central 50 % of the ranks 0..99 are 25..74, the central 90 % 5..94
    assert [r for r in range(RANK_DRAWS + 1) if rank_inside(r, 50)] == list(range(25, 75))
    assert [r for r in range(RANK_DRAWS + 1) if rank_inside(r, 90)] == list(range(5, 95))


def test_sbc_rank_is_the_number_of_posterior_draws_below_the_truth():
    x = np.linspace(0.0, 1.0, 100_001)
    w = np.ones_like(x)
    assert sbc_rank(x, w, -1.0) == 0 and sbc_rank(x, w, 2.0) == RANK_DRAWS
    # the truth at the posterior's own quantile u has rank floor(u (L + 1))
    for u in (0.005, 0.305, 0.5, 0.777, 0.995):
        assert sbc_rank(x, w, u) == int(np.floor(u * (RANK_DRAWS + 1)))
    # weights move the quantiles: all weight on the upper half puts the truth 0.5 at the bottom
    assert sbc_rank(x, (x > 0.5).astype(float), 0.5) == 0
    # ties (an integer parameter whose posterior is one value): split at random, else half
    same = np.full(50, 7.0)
    assert sbc_rank(same, np.ones(50), 7.0) == RANK_DRAWS // 2
    rng = np.random.default_rng(0)
    r = [sbc_rank(same, np.ones(50), 7.0, rng=rng) for _ in range(400)]
    assert min(r) < 15 and max(r) > 85


def test_ranks_of_truths_drawn_from_the_posterior_are_uniform():
    """SBC's premise with a known answer: when the truth is a draw of the posterior, its rank is
    uniform over 0..L (a weighted posterior: particles of N(0, 1) with weights tilting it)."""
    rng = np.random.default_rng(4)
    x = rng.normal(size=5000)
    w = np.exp(0.5 * x)  # tilts N(0, 1) into N(0.5, 1)
    truths = rng.normal(0.5, 1.0, size=1000)
    ranks = np.array([sbc_rank(x, w, t) for t in truths])
    counts = rank_counts(ranks, 10)
    lo, hi = uniform_band(1000, 10, prob=0.999)
    assert counts.sum() == 1000 and np.all((counts >= lo) & (counts <= hi))
    # a posterior too narrow by half piles ranks at both ends
    narrow = np.array([sbc_rank(0.5 + 0.5 * (x - x.mean()), np.ones_like(x), t) for t in truths])
    c = rank_counts(narrow, 10)
    assert c[0] > hi and c[-1] > hi


def test_rank_bins_and_prior_draws():
    assert rank_bins(40) == 10 and rank_bins(3) == 2 and rank_bins(200) == 50
    assert (RANK_DRAWS + 1) % rank_bins(17) == 0
    lo, hi, integer = [0.35, 30.0, 2.0], [0.65, 80.0, 6.0], [False, False, True]
    draws = np.array([prior_draw(1, i, lo, hi, integer)[0] for i in range(300)])
    assert np.all(draws >= lo) and np.all(draws <= hi)
    assert set(draws[:, 2]) == {2.0, 3.0, 4.0, 5.0, 6.0}  # whole numbers, the bounds included
    assert np.array_equal(prior_draw(1, 7, lo, hi, integer)[0], draws[7])  # run i is the same whatever N
    assert prior_draw(1, 7, lo, hi, integer)[1] != prior_draw(1, 8, lo, hi, integer)[1]  # fresh target seeds
    assert not np.array_equal(prior_draw(2, 7, lo, hi, integer)[0], draws[7])


# ------------------------------------------------------------------ end to end
STUDY = """
seed = 5
[ssm]
kind = "sot"
fixed = { max_iter = 9 }
free.init_lambda  = { lower = 0.4, upper = 0.6 }
free.branch_angle = { lower = 40.0, upper = 70.0 }
[features]
kind = "branch-segment"
sets = ["S0,1", "B1"]
small_sets = "keep"
[distance]
kind = "sliced"
lines = 16
[objective]
seed_mode = "per_evaluation"
[optimizer]
kind = "abc-smc"
particles = 6
generations = 2
[executor]
kind = "serial"
"""


def _bforest(*args, cwd=None):
    exe = shutil.which("bforest") or str(Path(sys.executable).with_name("bforest"))
    return subprocess.run([exe, *map(str, args)], capture_output=True, text=True, cwd=cwd)


def _evaluations(run: Path) -> int:
    with sqlite3.connect(run / "evaluations.sqlite") as con:
        return con.execute("SELECT COUNT(*) FROM evaluations").fetchone()[0]


def test_calibrate_end_to_end_files_and_resume(tmp_path):
    cfg = tmp_path / "study.toml"
    cfg.write_text(STUDY)
    out = tmp_path / "study"
    r = _bforest("calibrate", cfg, "-n", 2, "-o", out, "-q")
    assert r.returncode == 0, r.stderr
    assert "2 fitted, 0 resumed, 0 read back" in r.stdout and "50 % covers" in r.stdout
    assert "init_lambda" in r.stdout and "branch_angle" in r.stdout
    res = json.loads((out / "calibration.json").read_text())
    assert [x["run"] for x in res["runs"]] == ["run_000", "run_001"] and res["optimizer"] == "abc-smc"
    assert res["units"] == ["", "deg"] and (out / "calibration.png").stat().st_size > 10_000
    lines = (out / "calibration.csv").read_text().splitlines()
    assert len(lines) == 3 and lines[0].startswith("run,truth_init_lambda,median_init_lambda,lo50_init_lambda")
    for row in res["runs"]:  # the truth is the run's target, grown with a seed the fit does not use
        run_cfg = (out / row["run"] / "config.toml").read_text()
        truth = row["params"]["branch_angle"]["truth"]
        assert f"branch_angle = {truth!r}" in run_cfg and 40.0 <= truth <= 70.0
        p = row["params"]["init_lambda"]
        assert p["lo90"] <= p["lo50"] <= p["median"] <= p["hi50"] <= p["hi90"] and 0 <= p["rank"] <= RANK_DRAWS
    first = {d: (_evaluations(out / d), (out / d / "best.json").stat().st_mtime_ns) for d in ("run_000", "run_001")}

    # more runs: the finished ones are read back, not refitted
    r = _bforest("calibrate", cfg, "-n", 3, "-o", out, "-q", "--resume")
    assert r.returncode == 0, r.stderr
    assert "1 fitted, 0 resumed, 2 read back" in r.stdout
    assert {d: (_evaluations(out / d), (out / d / "best.json").stat().st_mtime_ns) for d in first} == first
    again = json.loads((out / "calibration.json").read_text())
    assert again["runs"][:2] == res["runs"] and len(again["runs"]) == 3

    # a run stopped half-way is resumed with the fit's own resume: same evaluations, same posterior
    run1 = out / "run_001"
    posterior = (run1 / "posterior.csv").read_text()
    n1 = _evaluations(run1)
    (run1 / "best.json").unlink()
    with sqlite3.connect(run1 / "evaluations.sqlite") as con:
        con.execute("DELETE FROM evaluations WHERE idx >= ?", (n1 // 2,))
    r = _bforest("calibrate", cfg, "-n", 3, "-o", out, "-q", "--resume")
    assert r.returncode == 0, r.stderr
    assert "0 fitted, 1 resumed, 2 read back" in r.stdout
    assert _evaluations(run1) == n1 and (run1 / "posterior.csv").read_text() == posterior

    # never over an earlier study without a flag
    r = _bforest("calibrate", cfg, "-n", 3, "-o", out)
    assert r.returncode == 2 and "already holds a calibration study" in r.stderr and "--resume" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1


def test_calibrate_bad_input_gives_one_line_errors(tmp_path, capsys):
    from bforest_core.cli.main import main

    ok = tmp_path / "ok.toml"
    ok.write_text(STUDY)
    ga = tmp_path / "ga.toml"
    ga.write_text(STUDY.replace('kind = "abc-smc"\nparticles = 6\ngenerations = 2', 'kind = "ga"'))
    bad = tmp_path / "bad.toml"
    bad.write_text(STUDY.replace("free.init_lambda ", "free.no_such_parameter "))
    never = tmp_path / "never.toml"  # every drawn target fails its data sets: no run gives a posterior
    never.write_text(STUDY.replace('small_sets = "keep"', "min_rows = 100000"))
    cases = [
        ([ga, "-n", 2], "needs a sampler whose result is a posterior (e.g. abc-smc, emcee); 'ga'"),
        ([ok, "-n", 0], "-n must be at least 1"),
        ([ok, "-n", 2, "--resume", "--overwrite"], "exclude each other"),
        ([tmp_path / "missing.toml", "-n", 2], "missing.toml: file not found"),
        ([bad, "-n", 2], "no_such_parameter"),
        ([never, "-n", 2], "no run gave a posterior (run_000: fit failed: features: data set"),
    ]
    for k, (args, words) in enumerate(cases):
        code = main(["calibrate", *map(str, args), "-q", "-o", str(tmp_path / f"out{k}")])
        err = capsys.readouterr().err
        assert code == 2 and words in err and len(err.strip().splitlines()) == 1, (args, err)
    assert not (tmp_path / "out0").exists()  # nothing written before the config is known good
