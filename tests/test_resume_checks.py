"""A resume continues the run it was begun as, or refuses: an edited config never mixes two
objectives into one log; the budget, the executor and the report may change (a finished run is
extended with a larger budget). A damaged, lost or hand-edited log, or a full disk, is one line
naming the file and what to do, never a traceback, never a silent start from zero."""

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
        # the target's settings are written first (typed: every one, defaults too), the [ssm] section's after
        ("fail_above = 1000000000.0", "fail_above = 70.0", "target.generate.settings.fail_above: 1000000000.0 -> 70.0"),
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
    if key.startswith("ssm.fail_above"):  # the [ssm] section's: the last one written
        head, _, tail = text.rpartition(old)
        cfg_path.write_text(head + new + tail)
    else:
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


# ------------------------------------------------------------------------------ damaged, lost, full
def _cli(capsys, *args) -> tuple[int, list[str]]:
    """``bforest ARGS`` in this process: the exit code and the lines of standard error (the
    toy plugins' load warning left out)."""
    from bforest_core.cli.main import main

    capsys.readouterr()
    code = main([str(a) for a in args])
    err = [ln for ln in capsys.readouterr().err.splitlines() if "plugin 'broken'" not in ln]
    return code, err


@pytest.fixture
def finished_run(toy_plugin, tmp_path):
    run = tmp_path / "run"
    bf.fit(bf.load_config(toy_config(tmp_path, budget=40)), run, progress=False)
    from bforest_core.pipeline.clones import clones

    clones(run, n=2, progress=False)
    return run


def test_a_damaged_log_is_one_line_naming_the_file_for_every_command(finished_run, capsys):
    db = finished_run / "evaluations.sqlite"
    size = db.stat().st_size
    assert size > 3 * 4096
    with open(db, "r+b") as fh:  # the probe's `truncate -s`: the log loses its second half
        fh.truncate(size // 2)
    for args in (
        ["fit", finished_run / "config.toml", "-o", finished_run, "--resume", "-q", "--no-report"],
        ["report", finished_run],
        ["clones", finished_run, "-n", "3", "-q", "--no-report"],
        ["export", finished_run, "--format", "ply"],
    ):
        code, err = _cli(capsys, *args)
        assert code == 2 and len(err) == 1, (args, err)
        assert err[0].startswith(f"error: {db}: the evaluation log is damaged (") and "--overwrite" in err[0], err


def test_a_damaged_or_full_simulation_log_of_a_training_is_one_line_too(tmp_path):
    """The training's store shares the run's guard: a truncated file and a full disk (a cap on
    its pages) each give one RunDirError naming the file, never an sqlite3 traceback."""
    from bforest_core.pipeline.store import SimulationStore

    db = tmp_path / "simulations.sqlite"
    with SimulationStore(db) as st:
        for i in range(300):
            st.add(i, 0, 10.0, {"a": float(i)}, i, {"status": "ok", "summaries": list(range(40))})
        assert st.count("ok") == 300
    size = db.stat().st_size
    with open(db, "r+b") as fh:
        fh.truncate(size // 2)
    with pytest.raises(RunDirError, match=r"simulations\.sqlite: the training's log of simulations is damaged \("):
        with SimulationStore(db) as st:
            st.done()
    full = tmp_path / "full.sqlite"
    with SimulationStore(full) as st:
        pages = st._sql("PRAGMA page_count")[0][0]
        st._sql(f"PRAGMA max_page_count={pages + 1}")
        with pytest.raises(RunDirError, match=r"full\.sqlite: the disk is full \(database or disk is full\)"):
            for i in range(1000):
                st.add(i, 0, 10.0, {"a": float(i)}, i, {"status": "ok", "summaries": list(range(400))})


def test_a_full_disk_during_a_fit_is_one_line_and_a_resume_gives_the_identical_run(toy_plugin, tmp_path, capsys):
    """SQLite's "database or disk is full" (a cap on the log's pages stands in for the disk):
    one line naming the log and saying what to do; a resume once there is room gives the run an
    uninterrupted fit gives."""
    from bforest_core.pipeline import store as store_mod

    p = toy_config(tmp_path, budget=400)
    bf.fit(bf.load_config(p), tmp_path / "whole", progress=False)
    real_create = store_mod.RunStore.create.__func__

    def small_disk(cls, *a, **kw):
        s = real_create(cls, *a, **kw)
        pages = s._sql("PRAGMA page_count")[0][0]
        s._sql(f"PRAGMA max_page_count = {pages + 4}")
        return s

    run = tmp_path / "run"
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(store_mod.RunStore, "create", classmethod(small_disk))
        code, err = _cli(capsys, "fit", p, "-o", run, "-q", "--no-report")
    assert code == 2 and len(err) == 1, err
    assert err[0].startswith(f"error: {run / 'evaluations.sqlite'}: the disk is full (database or disk is full)")
    assert "--resume" in err[0]
    held = RunStore.open(run)
    n = held.count()
    held.close()
    assert 0 < n < 400
    code, err = _cli(capsys, "fit", run / "config.toml", "-o", run, "--resume", "-q", "--no-report")
    assert code == 0, err
    assert _rows(run) == _rows(tmp_path / "whole")


def test_a_full_disk_under_any_other_file_of_the_run_is_one_line_too(toy_plugin, tmp_path, capsys, monkeypatch):
    import errno

    def full(self, name, data):
        raise OSError(errno.ENOSPC, "No space left on device", str(self.path / name))

    monkeypatch.setattr(RunStore, "write_json", full)
    code, err = _cli(capsys, "fit", toy_config(tmp_path, budget=8), "-o", tmp_path / "run", "-q", "--no-report")
    assert code == 2 and len(err) == 1, err
    assert "No space left on device" in err[0] and "the disk is full: free space and run the command again" in err[0]
    assert "distance.json" in err[0]


@pytest.mark.parametrize("damage", ["deleted", "empty", "table-less"])
def test_a_resume_over_a_lost_log_refuses_instead_of_starting_from_zero(finished_run, damage):
    db = finished_run / "evaluations.sqlite"
    db.unlink()
    if damage == "empty":
        db.write_bytes(b"")
    elif damage == "table-less":
        sqlite3.connect(db).execute("CREATE TABLE notes (x)").connection.close()
    expect = "missing: the run's evaluations are gone" if damage == "deleted" else "holds no evaluation table"
    with pytest.raises(RunDirError, match=expect):
        bf.fit(bf.load_config(finished_run / "config.toml"), finished_run, resume=True, progress=False)
    assert db.exists() == (damage != "deleted")  # nothing was created or begun in its place
    if damage == "empty":
        assert db.stat().st_size == 0


def test_a_row_added_to_the_log_by_hand_is_never_taken_as_the_answer(finished_run):
    """A row of distance 0 beyond the run's last evaluation (a copy of a real row's point and
    seeds): the resumed search never comes to it, and the resume refuses instead of answering
    with it; a row whose point the search does ask for, with other seeds, is refused too."""
    con = sqlite3.connect(finished_run / "evaluations.sqlite")
    row = con.execute("SELECT * FROM evaluations WHERE idx = 5").fetchone()
    con.execute("INSERT INTO evaluations VALUES (?,?,?,?,?,?,?,?,?,?,?)", (40, row[1], row[2], 0.0, *row[4:]))
    con.commit()
    with pytest.raises(
        RunDirError, match=r"evaluation 40 of the log is not this run's: its search ended at evaluation 39"
    ):
        bf.fit(bf.load_config(finished_run / "config.toml"), finished_run, resume=True, progress=False)
    cfg = bf.load_config(finished_run / "config.toml")
    cfg.stop.max_evaluations = 48  # the search comes to row 40 now: its point is not the search's
    with pytest.raises(RunDirError, match="evaluation 40 in the log has other parameters"):
        bf.fit(cfg, finished_run, resume=True, progress=False)
    con.execute("DELETE FROM evaluations WHERE idx = 40")
    con.execute("UPDATE evaluations SET seeds = '[99]' WHERE idx = 7")
    con.commit()
    con.close()
    with pytest.raises(RunDirError, match="evaluation 7 in the log has other parameters"):
        bf.fit(bf.load_config(finished_run / "config.toml"), finished_run, resume=True, progress=False)


def test_a_run_stopped_on_its_wall_time_resumes_over_every_row_it_logged(toy_plugin, tmp_path, monkeypatch):
    """The clock does not stop a resumed search while logged rows are still ahead of it: the
    replay comes to every row (none is taken for a stranger's), then the wall time applies."""
    from bforest_core.pipeline import fit as fit_mod

    p = toy_config(tmp_path, budget=64)
    p.write_text(p.read_text().replace("[stop]\n", "[stop]\nwall_time = 100.0\n", 1))
    clock = {"t": 0.0}

    def ticking():  # the clock of the fit: 15 s a reading
        clock["t"] += 15.0
        return clock["t"]

    monkeypatch.setattr(fit_mod.time, "monotonic", ticking)
    res = bf.fit(bf.load_config(p), tmp_path / "run", progress=False)
    assert res.stop_reason.startswith("wall time") and 0 < res.n_evaluations < 64
    res2 = bf.fit(bf.load_config(tmp_path / "run" / "config.toml"), tmp_path / "run", resume=True, progress=False)
    assert res2.n_evaluations == res.n_evaluations and res2.already_finished
    assert len(res2.history) == len(res.history) > 1  # the resumed search went as far as the first
