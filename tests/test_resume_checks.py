"""A resume continues the run it was begun as, or refuses: an edited config never mixes two
objectives into one log; the budget, the executor and the report may change (a finished run is
extended with a larger budget)."""

from __future__ import annotations

import os
import sqlite3
import subprocess
import sys

import pytest

import bforest_core as bf
from bforest_core.pipeline.store import RunDirError, RunStore
from conftest import TOY_DIR, toy_config

EXE = [sys.executable, "-m", "bforest_core.cli"]


def _env(*sites) -> dict:
    """The environment of a `bforest` subprocess that finds the toy plugins."""
    path = [*map(str, sites), str(TOY_DIR), os.environ.get("PYTHONPATH", "")]
    return {**os.environ, "PYTHONPATH": os.pathsep.join(path)}


def _rows(run):
    with RunStore.open(run) as s:
        return [(e.idx, e.params, e.seeds, e.distance, e.status) for e in s.evaluations()]


def _cut(run, keep: int) -> None:
    """Delete the log's rows from ``keep`` on, as a run killed there would have left it."""
    con = sqlite3.connect(run / "evaluations.sqlite")
    con.execute("DELETE FROM evaluations WHERE idx >= ?", (keep,))
    con.commit()
    con.close()
    (run / "best.json").unlink()


@pytest.mark.parametrize(
    "old,new,key",
    [
        ("penalty = 1.0", "penalty = 2.0", "objective.penalty: 1.0 -> 2.0"),
        ("timeout = 60.0", "timeout = 5.0", "objective.timeout: 60.0 -> 5.0"),
        ("fail_above = 1000000000.0", "fail_above = 70.0", "ssm.fail_above: 1000000000.0 -> 70.0"),
        ('sets = [\n    "L",\n]', 'sets = ["L", "M"]', 'features.sets: ["L"] -> ["L", "M"]'),
        ("upper = 80.0", "upper = 85.0", "ssm.free.angle.upper: 80.0 -> 85.0"),
        ("seed = 3", "seed = 4", "seed: 3 -> 4"),
    ],
)
def test_a_resume_refuses_an_edit_of_the_runs_own_config_naming_the_setting(toy_plugin, tmp_path, old, new, key):
    """The probe's attack: rows cut from the log, RUN/config.toml edited, resumed with that very
    file; refused with the dotted key and both values, and the log is left as it was."""
    run = tmp_path / "run"
    bf.fit(bf.load_config(toy_config(tmp_path, budget=16)), run, progress=False)
    _cut(run, 10)
    before = _rows(run)
    cfg_path = run / "config.toml"
    text = cfg_path.read_text()
    assert old in text
    cfg_path.write_text(text.replace(old, new, 1))
    with pytest.raises(RunDirError, match="differs from the run's") as err:
        bf.fit(bf.load_config(cfg_path), run, resume=True, progress=False)
    assert key in str(err.value), str(err.value)
    assert _rows(run) == before


def test_budget_wall_time_executor_and_report_may_change_and_a_finished_run_is_extended(toy_plugin, tmp_path):
    """--max-evaluations on a finished run extends it to exactly the run a larger budget gives;
    another executor, wall time and report settings change nothing; a budget below the rows
    held is refused."""
    (tmp_path / "a").mkdir()
    whole = bf.fit(bf.load_config(toy_config(tmp_path / "a", budget=32)), tmp_path / "whole", progress=False)
    run = tmp_path / "run"
    bf.fit(bf.load_config(toy_config(tmp_path, budget=16)), run, progress=False)
    cfg_path = run / "config.toml"
    cfg_path.write_text(
        cfg_path.read_text()
        .replace("[stop]\n", "[stop]\nwall_time = 3600.0\n", 1)
        .replace("clones_in_figure = 6", "clones_in_figure = 3")
    )
    cfg = bf.load_config(cfg_path)
    cfg.stop.max_evaluations = 32
    cfg.executor = bf.load_config(
        toy_config(tmp_path / "a", executor="process", executor_settings="workers = 2")
    ).executor
    res = bf.fit(cfg, run, resume=True, progress=False)
    assert not res.already_finished and res.n_evaluations == 32
    assert _rows(run) == _rows(tmp_path / "whole") and res.params == whole.params
    again = bf.fit(bf.load_config(cfg_path), run, resume=True, progress=False)
    assert again.already_finished  # the extended run resumed once more: nothing new
    cfg = bf.load_config(cfg_path)
    cfg.stop.max_evaluations = 20
    with pytest.raises(RunDirError, match="max_evaluations = 20 is below the 32 evaluations"):
        bf.fit(cfg, run, resume=True, progress=False)


def test_the_cli_extends_a_finished_run_with_max_evaluations(toy_plugin, tmp_path):
    env = _env(toy_plugin)
    run = tmp_path / "run"
    p = toy_config(tmp_path, budget=8)
    r = subprocess.run(
        EXE + ["fit", str(p), "-o", str(run), "-q", "--no-report"], env=env, capture_output=True, text=True
    )
    assert r.returncode == 0, r.stderr
    args = ["fit", str(run / "config.toml"), "-o", str(run), "--resume", "-q", "--no-report"]
    r = subprocess.run(EXE + args + ["--max-evaluations", "16"], env=env, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert "after 16 evaluations" in r.stdout and "already finished" not in r.stdout
    r = subprocess.run(EXE + args, env=env, capture_output=True, text=True)
    assert r.returncode == 0 and "already finished" in r.stdout, r.stdout + r.stderr
