"""A run folder nothing can corrupt: one owner at a time, --overwrite that clears the old run,
no command overwriting a file it did not write, clones that can be continued."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

import bforest_core as bf
from bforest_core.pipeline.store import RunDirError, RunStore
from conftest import TOY_DIR, toy_config

EXE = [sys.executable, "-m", "bforest_core.cli"]


def _env(toy_site, *more):
    return {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(toy_site), str(TOY_DIR), *map(str, more), os.environ.get("PYTHONPATH", "")]),
    }


def _slow(p: Path, sleep: float) -> Path:
    """The toy config with a model that sleeps per simulation (the target grows at once)."""
    p.write_text(
        p.read_text()
        .replace('kind = "toy"\n', f'kind = "toy"\nsleep = {sleep}\n', 1)
        .replace('[target.generate]\nssm = "toy"', '[target.generate]\nssm = "toy"\nsettings = { sleep = 0.0 }')
    )
    return p


def _gated(p: Path, gate: Path, after: int) -> Path:
    """The toy config with a model that, in each process, runs ``after`` simulations and then
    waits until the file ``gate`` exists (the target grows at once): a test holds a command at a
    known point, however fast or loaded the machine, and lets it go on by creating the file."""
    p.write_text(
        p.read_text()
        .replace('kind = "toy"\n', f'kind = "toy"\ngate = "{gate}"\ngate_after = {after}\n', 1)
        .replace('[target.generate]\nssm = "toy"', '[target.generate]\nssm = "toy"\nsettings = {}')
    )
    return p


# ------------------------------------------------------------------------------ one owner
@pytest.mark.skipif(os.name != "posix", reason="flock")
def test_two_fits_into_one_folder_exactly_one_runs(toy_plugin, tmp_path):
    """Two `bforest fit` of different configs into one folder at once: one runs, the other exits 2
    with one line naming the holder, and the folder holds the winner's run only."""
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    gate = tmp_path / "gate"  # the first fit holds the folder until the test creates this file
    a = _gated(toy_config(tmp_path / "a", budget=16), gate, after=2)
    b = toy_config(tmp_path / "b", budget=8)
    b.write_text(b.read_text().replace("seed = 3", "seed = 4", 1))
    run, env = tmp_path / "run", _env(toy_plugin)
    first = subprocess.Popen(
        EXE + ["fit", str(a), "-o", str(run), "-q", "--no-report"],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and not (run / "evaluations.sqlite").exists():
        time.sleep(0.05)
    others = [
        subprocess.run(EXE + args + ["-q", "--no-report"], env=env, capture_output=True, text=True, timeout=120)
        for args in (["fit", str(b), "-o", str(run)], ["fit", str(run / "config.toml"), "-o", str(run), "--resume"])
    ]
    assert first.poll() is None  # still held at the gate: both others met it at work
    gate.touch()
    out, err = first.communicate(timeout=120)
    assert first.returncode == 0, err
    for r in others:
        assert r.returncode == 2, r.stderr
        lines = [ln for ln in r.stderr.strip().splitlines() if not ln.startswith("warning: bforest plugin 'broken'")]
        assert len(lines) == 1 and "in use by another bforest command" in lines[0], r.stderr
        assert f"pid {first.pid}" in lines[0] and "bforest fit" in lines[0]
    assert bf.load_config(run / "config.toml").seed == 3  # the winner's config beside the winner's evaluations
    with RunStore.open(run) as s:
        assert s.count() == 16
    assert json.loads((run / "best.json").read_text())["n_evaluations"] == 16


def test_the_lock_is_reentrant_in_a_process_and_freed_after(toy_plugin, tmp_path):
    from bforest_core.pipeline.rundir import run_lock
    from bforest_core.pipeline.store import RunFiles

    with run_lock(tmp_path / "r"):
        with run_lock(tmp_path / "r"):  # demo holds it while its fit takes it again
            pass
        info = json.loads(RunFiles(tmp_path / "r").lock_path.read_text())
        assert info["pid"] == os.getpid()
        # another process cannot take it meanwhile
        code = (
            "import sys; from bforest_core.pipeline.rundir import run_lock\n"
            "try:\n    run_lock(sys.argv[1]).__enter__()\nexcept Exception as e:\n    print(e); sys.exit(2)\n"
        )
        r = subprocess.run([sys.executable, "-c", code, str(tmp_path / "r")], capture_output=True, text=True)
        assert r.returncode == 2 and f"pid {os.getpid()}" in r.stdout
    r = subprocess.run([sys.executable, "-c", code, str(tmp_path / "r")], capture_output=True, text=True)
    assert r.returncode == 0, r.stdout  # released at the end of the block
    with pytest.raises(RunDirError, match="not a run directory"):
        with run_lock(tmp_path / "missing", create=False):
            pass
    assert not (tmp_path / "missing").exists()


# ------------------------------------------------------------------------------ --overwrite, foreign files
def test_overwrite_clears_everything_the_old_run_wrote(toy_plugin, tmp_path):
    from bforest_core.pipeline.clones import clones

    run = tmp_path / "run"
    cfg = bf.load_config(toy_config(tmp_path, budget=8))
    bf.fit(cfg, run, progress=False)
    clones(run, n=2, progress=False)
    for name in ("report.md", "report.html", "figures/trees.png", "export/clone_000.ply", "clones_posterior/x.txt"):
        (run / name).parent.mkdir(exist_ok=True)
        (run / name).write_text("old")
    (run / "notes.txt").write_text("mine")  # not the run's: kept
    cfg.seed = 5
    bf.fit(cfg, run, progress=False, overwrite=True)
    left = sorted(p.relative_to(run).as_posix() for p in run.rglob("*") if p.is_file())
    assert "notes.txt" in left
    assert not [p for p in left if p.startswith(("clones/", "clones_posterior", "export", "figures/", "report"))], left
    assert bf.load_config(run / "config.toml").seed == 5


def test_overwrite_keeps_the_old_run_when_the_new_config_is_invalid(toy_plugin, tmp_path):
    from bforest_core.cli import main

    run = tmp_path / "run"
    p = toy_config(tmp_path, budget=8)
    assert main(["fit", str(p), "-o", str(run), "-q", "--no-report"]) == 0
    bad = tmp_path / "bad.toml"
    bad.write_text(p.read_text().replace("upper = 80.0", "upper = 800.0"))
    assert main(["fit", str(bad), "-o", str(run), "-q", "--overwrite", "--no-report"]) == 2
    assert (run / "best.json").exists() and RunStore.held(run) == 8


def test_fit_into_the_configs_own_folder_never_overwrites_the_users_config(toy_plugin, tmp_path, capsys):
    from bforest_core.cli import main

    p = toy_config(tmp_path, budget=8)
    mine = tmp_path / "config.toml"
    mine.write_text("# my notes\n" + p.read_text())
    before = mine.read_bytes()
    for extra in ([], ["--overwrite"]):
        assert main(["fit", str(mine), "-o", str(tmp_path), "-q", "--no-report", *extra]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "config.toml, not written by a run" in err[0], err
    assert mine.read_bytes() == before
    assert not (tmp_path / "evaluations.sqlite").exists()


def test_demo_never_replaces_a_run_or_a_file_it_did_not_write(toy_plugin, tmp_path, capsys):
    from bforest_core.cli import main

    run = tmp_path / "x"
    bf.fit(bf.load_config(toy_config(tmp_path, budget=8)), run, progress=False)
    assert main(["demo", "-o", str(run), "--quick", "-q"]) == 2
    assert "holds a run that is not a demo's" in capsys.readouterr().err
    assert RunStore.held(run) == 8


def test_demo_writes_nothing_beside_its_run_folder(tmp_path, monkeypatch):
    """Issue 33: the demo left ``demo-run.toml`` in the folder it was started from (the
    repository root); its config is the run's own config.toml now."""
    import bforest_core.pipeline.fit as fit_mod
    from bforest_core.cli import demo

    class Stop(Exception):
        pass

    seen = {}

    def fake_fit(cfg, out, **kw):  # the demo's fit is not the subject: stop once it is called
        seen["cfg"] = cfg
        raise Stop

    monkeypatch.setattr(fit_mod, "fit", fake_fit)
    monkeypatch.chdir(tmp_path)
    with pytest.raises(Stop):
        demo.run_demo(Path("demo-run"), quick=True, progress=False)
    assert seen["cfg"].optimizer.kind == "ga" and seen["cfg"].target.generate is not None
    assert not [p.name for p in tmp_path.iterdir() if p.name != "demo-run"]  # (an empty one is removed)


# ------------------------------------------------------------------------------ clones can be continued
def _clones_held_at_two(toy_site, config: Path, run: Path, gate: Path, args: list[str]) -> subprocess.Popen:
    """Fit ``config`` (gated) into ``run``, then start `bforest clones RUN *args` and return it once
    it has grown two clones and waits at the gate (stdout and stderr piped)."""
    gate.touch()  # the fit passes; the clones' process grows two clones and waits
    bf.fit(bf.load_config(config), run, progress=False)
    gate.unlink()
    proc = subprocess.Popen(
        EXE + ["clones", str(run), *args], env=_env(toy_site), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    summary, deadline, rows = run / "clones" / "summary.json", time.monotonic() + 60, []
    while time.monotonic() < deadline and len(rows) < 2:
        try:
            rows = json.loads(summary.read_text())["rows"] if summary.exists() else []
        except ValueError:
            rows = []
        time.sleep(0.05)
    return proc


@pytest.mark.skipif(os.name != "posix", reason="kill -9")
def test_a_killed_clones_call_is_continued_without_regrowing_its_clones(toy_plugin, tmp_path):
    import signal

    from bforest_core.pipeline.clones import clones

    run, gate = tmp_path / "run", tmp_path / "gate"
    p = _gated(toy_config(tmp_path, budget=4), gate, after=2)
    proc = _clones_held_at_two(toy_plugin, p, run, gate, ["-n", "8", "-q", "--no-report"])
    proc.send_signal(signal.SIGKILL)
    proc.communicate()
    kept = json.loads((run / "clones" / "summary.json").read_text())
    assert kept["complete"] is False and kept["count"] == 2  # every finished clone listed as it was grown
    stamps = {r["file"]: (run / "clones" / r["file"]).stat().st_mtime_ns for r in kept["rows"]}
    gate.touch()
    s = clones(run, n=8, progress=False)
    assert s["complete"] and s["count"] == 8 and s["grown"] == 8 - kept["count"]
    assert {f: (run / "clones" / f).stat().st_mtime_ns for f in stamps} == stamps  # not regrown


def test_a_missing_reference_file_loses_no_clone(toy_plugin, tmp_path, capsys):
    from bforest_core.cli import main

    p = toy_config(tmp_path, budget=4)
    p.write_text(
        p.read_text()
        .replace("[target.generate]", 'seed = 3\n[target]\nreferences = ["gone.txt"]\n[target.generate]', 1)
        .replace("seed = 3\n", "", 1)
    )
    run = tmp_path / "run"
    (tmp_path / "gone.txt").write_text("")  # there when the fit checked it, gone by the clones
    bf.fit(bf.load_config(p), run, progress=False)
    (tmp_path / "gone.txt").unlink()
    assert main(["clones", str(run), "-n", "3", "-q", "--no-report"]) == 0
    err = capsys.readouterr().err
    assert "warning: reference" in err and "gone.txt" in err
    s = json.loads((run / "clones" / "summary.json").read_text())
    assert s["count"] == 3 and s["references"] == [] and "gone.txt" in s["reference_errors"][0]["file"]


@pytest.mark.skipif(os.name != "posix", reason="SIGINT")
def test_ctrl_c_during_clones_says_so_on_its_own_line_and_resume_continues(toy_plugin, tmp_path):
    """Issue 78, item 1: Ctrl-C during `bforest clones` ended its progress bar's line with the
    message (and named fit's --resume, which clones did not take). The message now starts a line
    of its own and names the command that continues: `bforest clones RUN --resume` grows the
    clones the stopped call asked for."""
    import signal

    run, gate = tmp_path / "run", tmp_path / "gate"
    p = _gated(toy_config(tmp_path, budget=4), gate, after=2)
    proc = _clones_held_at_two(toy_plugin, p, run, gate, ["-n", "6", "--no-report"])  # with its progress bar
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    last = err.rstrip("\n").split("\n")[-1]  # a bar redraws its line with "\r"
    assert last == f"stopped by SIGINT (finished clones are saved; continue with 'bforest clones {run} --resume')", err
    assert "clones:" in err  # the bar was drawn, and ended before the message
    gate.touch()
    r = subprocess.run(
        EXE + ["clones", str(run), "--resume", "-q", "--no-report"],
        env=_env(toy_plugin),
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0, r.stderr
    assert r.stdout.startswith(f"4 clones grown, 2 kept: 6 of 6 clones ok in {run / 'clones'}\n"), r.stdout
    r = subprocess.run(
        EXE + ["clones", str(run), "--resume", "-n", "8", "-q"], env=_env(toy_plugin), capture_output=True, text=True
    )
    lines = [ln for ln in r.stderr.splitlines() if not ln.startswith("warning: bforest plugin 'broken'")]
    assert r.returncode == 2 and lines[-1] == "error: argument -n/--count: not allowed with argument --resume", r.stderr
