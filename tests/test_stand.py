"""`bforest stand`: every tree of a plot fitted as a task, one table, resumes, synthetic stands.

The trees are real QSMs (pine 3 and the coffeetree of ../shared/data/qsm) and a broken file; the
recipe is a small one of 24 evaluations (a stand's behaviour, not a fit's quality, is tested here).
"""

from __future__ import annotations

import os
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from bforest_core.cli import main
from conftest import qsm_path

TINY = """seed = 1
[target]
qsm = "unused.mat"
[ssm]
kind = "sot"
max_live_segments = 20000
fixed = { ran = 0.05 }
free.max_iter     = { lower = 8, upper = 12 }
free.branch_angle = { lower = 20.0, upper = 90.0 }
free.init_width   = { lower = 0.01, upper = 0.04 }
[features]
kind = "branch-segment"
sets = ["S0,1", "B1,2"]
[distance]
kind = "sliced"
statistic = "ks"
lines = 32
[optimizer]
kind = "ga"
population = 8
generations = 3
[stop]
max_evaluations = 24
[select]
top = 2
sets = 2
"""

#: the stem map of the test plot: two trees 5 m apart and a file that is no QSM
MAP = [("p3", "pine_ruotsinkyla_3.mat", 0.0, 0.0), ("cof", "coffeetree_treeqsm_optqsm.mat", 5.0, 2.0)]


@pytest.fixture(scope="module")
def plot(tmp_path_factory):
    """A plot folder: the recipe, the stem map (pine 3, the coffeetree, a broken file)."""
    d = tmp_path_factory.mktemp("plot")
    for _, f, _, _ in MAP:
        os.symlink(qsm_path(f), d / f)
    (d / "broken.mat").write_text("not a QSM\n")
    (d / "tiny.toml").write_text(TINY)
    rows = ["tree,file,x,y"] + [f"{t},{f},{x},{y}" for t, f, x, y in MAP] + ["bad,broken.mat,9,9"]
    (d / "map.csv").write_text("\n".join(rows) + "\n")
    return d


def stand_args(plot):
    return ["stand", "--stem-map", str(plot / "map.csv"), "--recipe", str(plot / "tiny.toml"), "-n", "3"]


@pytest.fixture(scope="module")
def reference(plot, tmp_path_factory):
    """The plot's stand as one uninterrupted command (two process workers)."""
    out = tmp_path_factory.mktemp("ref") / "stand"
    rc = main([*stand_args(plot), "-o", str(out), "--workers", "2", "-q", "--no-report"])
    return out, rc


def _lines(capsys) -> list[str]:
    return [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]


def test_a_broken_file_is_one_line_and_the_other_trees_finish(reference, capsys):
    from bforest_core.pipeline.stand import read_table

    out, rc = reference
    assert rc == 1  # a tree failed: the command says so by its exit code
    rows = {r["tree"]: r for r in read_table(out / "stand.csv")}
    assert list(rows) == ["p3", "cof", "bad"]  # the stem map's order
    assert rows["bad"]["status"] == "failed" and "broken.mat" in rows["bad"]["reason"]
    assert "MAT" in rows["bad"]["reason"] or "QSM" in rows["bad"]["reason"]
    for t in ("p3", "cof"):
        r = rows[t]
        assert r["status"] == "ok" and r["stop_kind"] in ("budget", "convergence")  # the GA's 3 generations
        assert int(r["evaluations"]) == len(_rows(out / "trees" / t / "evaluations.sqlite")) > 12
        assert r["clones"] == "3" and r["verdict"] in ("pass", "warn") and r["heldout_distance"]
        assert set(r["params"]) == {"max_iter", "branch_angle", "init_width"}
        assert (out / "trees" / t / "best.json").exists() and (out / "recipes" / f"{t}.toml").exists()
    # the stem map's places; the heights are the QSMs' own
    assert (float(rows["cof"]["x"]), float(rows["cof"]["y"]), float(rows["cof"]["z"])) == (5.0, 2.0, 0.0)
    assert abs(float(rows["p3"]["height"]) - 9.94) < 0.01


def test_resume_of_a_finished_stand_does_nothing_and_says_so(reference, capsys):
    out, _ = reference
    logs = {p: p.stat().st_mtime_ns for p in out.glob("trees/*/evaluations.sqlite")}
    table = (out / "stand.csv").read_text()
    rc = main(["stand", "--resume", "-o", str(out), "-q", "--no-report"])
    text = capsys.readouterr().out
    assert rc == 1 and "every tree had finished (3 of 3); nothing to do" in text
    assert {p: p.stat().st_mtime_ns for p in out.glob("trees/*/evaluations.sqlite")} == logs
    assert (out / "stand.csv").read_text() == table
    # a stand is never started over an existing one without a flag
    assert main(["stand", str(out / "recipes"), "-o", str(out)]) == 2
    assert "holds a stand already; continue it with --resume" in capsys.readouterr().err


def test_the_synthetic_stand_has_every_tree_at_its_place(reference):
    import laspy

    out, _ = reference
    real = out / "synthetic" / "stand_000"
    las = laspy.read(real / "plot.las")
    xyz = np.column_stack([las.x, las.y, las.z])
    tid = np.asarray(las["tree_id"])
    assert sorted(set(tid.tolist())) == [0, 1]
    trees = (real / "trees.csv").read_text().splitlines()
    assert trees[0].startswith("tree_id,tree,x,y,z,clone,file,model,seed,params") and len(trees) == 3
    for i, (name, _, x, y) in enumerate(MAP):
        pts = xyz[tid == i]
        base = pts[pts[:, 2] < pts[:, 2].min() + 0.3]  # the stem's foot
        assert np.allclose(base[:, :2].mean(axis=0), (x, y), atol=0.25), name
        assert abs(pts[:, 2].min()) < 0.1  # standing on the ground (z = 0 of the stem map)
    assert (real / "plot.ply").read_bytes().startswith(b"ply\n")


def test_an_interrupted_stand_resumed_gives_the_uninterrupted_table(plot, reference, tmp_path, monkeypatch, capsys):
    """Killed after 30 logged evaluations (in the second tree's fit), then resumed: every logged
    evaluation is kept, the finished tree is not refitted, the table equals one run's to the digit."""
    from bforest_core.pipeline.store import RunStore

    ref, _ = reference
    out = tmp_path / "stand"
    real_add, calls = RunStore.add, {"n": 0}

    def killed_add(self, ev):
        if calls["n"] == 30:
            raise KeyboardInterrupt("simulated kill")
        calls["n"] += 1
        real_add(self, ev)

    monkeypatch.setattr(RunStore, "add", killed_add)
    with pytest.raises(KeyboardInterrupt):
        from bforest_core.pipeline.stand import run_stand, settings_from

        s = settings_from(None, plot / "map.csv", recipe=str(plot / "tiny.toml"), clones=3, executor={"kind": "serial"})
        run_stand(s, out, progress=False)
    monkeypatch.setattr(RunStore, "add", real_add)
    first = sorted(out.glob("trees/*/best.json"))
    assert len(first) == 1  # one tree finished, the other stopped in its fit
    stamp = first[0].stat().st_mtime_ns
    assert main(["stand", "--resume", "-o", str(out), "--executor", "serial", "-q", "--no-report"]) == 1
    assert first[0].stat().st_mtime_ns == stamp  # not refitted
    assert (out / "stand.csv").read_text() == (ref / "stand.csv").read_text()


def _rows(log):
    with sqlite3.connect(log) as con:
        return con.execute("SELECT idx, params, seeds, distance, status FROM evaluations ORDER BY idx").fetchall()


@pytest.mark.slow
def test_a_worker_killed_on_a_separate_process_cluster_loses_nothing(plot, reference, tmp_path):
    """`dask scheduler` and two `dask worker` processes (TLS, no HTTP); one worker is killed with
    SIGKILL while the trees are being fitted: the stand finishes (the killed worker's tree goes on
    from its log), --resume has nothing to do, and table and logs equal the uninterrupted stand's."""
    pytest.importorskip("distributed")
    from bforest_core.pipeline.store import logged_count
    from bforest_dask.launch import separate_cluster

    ref, _ = reference
    out = tmp_path / "stand"
    with separate_cluster(tmp_path / "cluster", workers=2) as cluster:
        ex = cluster.executor_settings()
        cfg = tmp_path / "stand.toml"
        lines = [
            "[stand]",
            f'stem_map = "{plot / "map.csv"}"',
            f'recipe = "{plot / "tiny.toml"}"',
            "clones = 3",
            "[executor]",
        ]
        lines += [f'{k} = "{v}"' if isinstance(v, str) else f"{k} = {v}" for k, v in ex.items()]
        cfg.write_text("\n".join(lines) + "\n")
        exe = str(Path(sys.executable).with_name("bforest"))
        proc = subprocess.Popen([exe, "stand", str(cfg), "-o", str(out), "-q", "--no-report"], stderr=subprocess.PIPE)
        from distributed import Client

        from bforest_core.registry import component

        sec = component("executor", "dask", **{k: v for k, v in ex.items() if k != "kind"}).settings.security()
        with Client(scheduler_file=str(cluster.scheduler_file), security=sec, timeout=30) as client:
            client.wait_for_workers(2, timeout=60)
            pids = client.run(os.getpid)
            deadline = time.monotonic() + 120
            while time.monotonic() < deadline:  # kill one worker once both trees have logged evaluations
                counts = [logged_count(p) for p in out.glob("trees/*/evaluations.sqlite")]
                if len(counts) == 2 and min(counts) >= 2:
                    break
                time.sleep(0.2)
            assert proc.poll() is None, "the stand ended before a worker could be killed"
            os.kill(next(iter(pids.values())), signal.SIGKILL)
            rc = proc.wait(300)
        assert rc == 1, proc.stderr.read().decode()  # 1: the broken file
        again = subprocess.run(
            [exe, "stand", "--resume", "-o", str(out), "-q", "--no-report"], capture_output=True, text=True
        )
    assert "nothing to do" in again.stdout
    assert (out / "stand.csv").read_text() == (ref / "stand.csv").read_text()
    for t in ("p3", "cof"):
        assert _rows(out / "trees" / t / "evaluations.sqlite") == _rows(ref / "trees" / t / "evaluations.sqlite")


@pytest.mark.parametrize(
    "rows, message",
    [
        (["tree,file,y", "a,x.mat,0"], "no column 'x'"),
        (["file,x,y", "missing.mat,0,0"], "row 2: file 'missing.mat' not found"),
        (["tree,file,x,y", "a,t1.mat,0,0", "a,t2.mat,1,1"], "rows 2 and 3: the tree 'a' twice"),
        (["file,x,y", "t1.mat,0,0", "t1.mat,1,1"], "rows 2 and 3: the file 't1.mat' twice"),
        (["file,x,y", "t1.mat,0,0", "t2.mat,north,1"], "row 3: x = 'north' is not a number (m)"),
        (["file,x,y", "t1.mat,0,nan"], "row 2: y = 'nan' is not a number (m)"),
    ],
)
def test_a_bad_stem_map_is_one_line(tmp_path, capsys, rows, message):
    for f in ("t1.mat", "t2.mat"):
        (tmp_path / f).write_text("x")
    m = tmp_path / "map.csv"
    m.write_text("\n".join(rows) + "\n")
    assert main(["stand", "--stem-map", str(m), "-o", str(tmp_path / "s")]) == 2
    err = _lines(capsys)
    assert len(err) == 1 and err[0].startswith("error: ") and str(m) in err[0] and message in err[0], err
    assert not (tmp_path / "s").exists()


def test_a_stand_config_names_its_bad_key(tmp_path, capsys):
    cfg = tmp_path / "stand.toml"
    cfg.write_text('[stand]\nqsms = "plot"\nclone = 3\n')
    assert main(["stand", str(cfg), "-o", str(tmp_path / "s")]) == 2
    err = _lines(capsys)
    assert len(err) == 1 and "stand.clone: unknown key" in err[0] and "did you mean 'clones'" in err[0]


def _block(doc: str, marker: str, lang: str) -> str:
    """The fenced ``lang`` block that follows ``marker`` in ``doc``."""
    after = doc[doc.index(marker) :]
    start = after.index(f"```{lang}\n") + len(lang) + 4
    return after[start : after.index("```", start)]


def test_the_slurm_set_up_of_dask_md_builds_and_its_stand_config_validates(plot, tmp_path, monkeypatch):
    """docs/dask.md's stand config validates (with credentials made as the page says) and its
    launcher's SLURM cluster builds: TLS with those credentials, no HTTP, the workers' job script
    presenting them (no job is submitted)."""
    pytest.importorskip("dask_jobqueue", reason="dask-jobqueue is not installed (pip install 'bayesforest[slurm]')")
    from bforest_core.pipeline.stand import load_stand_config
    from bforest_dask.credentials import write_credentials
    from conftest import ROOT

    doc = (ROOT / "docs" / "dask.md").read_text()
    monkeypatch.setenv("HOME", str(tmp_path))
    creds = write_credentials(tmp_path / ".bforest-cluster")
    folder = tmp_path / "site"
    folder.mkdir()
    rows = (plot / "map.csv").read_text().splitlines()
    (folder / "plot.csv").write_text("\n".join([rows[0]] + [r.replace(",", f",{plot}/", 1) for r in rows[1:]]) + "\n")
    (folder / "stand.toml").write_text(_block(doc, "<!-- stand config:", "toml"))
    s = load_stand_config(folder / "stand.toml")
    assert [t.name for t in s.trees] == ["p3", "cof", "bad"] and s.clones == 30 and s.realisations == 3
    assert s.executor["kind"] == "dask" and s.executor["workers"] == 16
    from bforest_core.registry import component

    ex = component("executor", "dask", **{k: v for k, v in s.executor.items() if k != "kind"})
    assert ex.settings.security().require_encryption
    ns = {"__name__": "launch_stand"}
    monkeypatch.chdir(tmp_path)
    exec(compile(_block(doc, "<!-- launcher:", "python"), "launch_stand.py", "exec"), ns)
    cluster = ns["slurm_cluster"](creds["ca"].parent)
    try:
        script = cluster.job_script()
        assert cluster.scheduler_address.startswith("tls://")
        for part in (f"--tls-ca-file {creds['ca']}", f"--tls-cert {creds['cert']}", "--preload bforest_dask.nohttp"):
            assert part in script, script
        assert cluster.scheduler.http_server is None or not any(
            sock.fileno() != -1 for sock in cluster.scheduler.http_server._sockets.values()
        )
    finally:
        cluster.close()


def test_the_stand_report_has_a_row_per_tree_the_parameters_and_the_plot(reference):
    from bforest_core.report.stand import write_stand_report

    out, _ = reference
    md = write_stand_report(out).read_text()
    assert "**2 of 3** trees fitted" in md
    assert "- bad: failed: " in md  # the failed tree among the warnings, with its reason
    rows = [ln for ln in md.splitlines() if ln.startswith("| p3 |") or ln.startswith("| cof |")]
    assert len(rows) == 4  # each fitted tree in the tree table and in the parameter table
    assert "| tree | branch_angle | init_width | max_iter |" in md
    for fig in ("parameters", "plot_map", "real_vs_synthetic"):
        assert (out / "figures" / f"{fig}.png").stat().st_size > 10_000
        assert f"figures/{fig}.png" in md
    assert (out / "report.html").read_text().count("<img") == 3


def test_a_bad_recipe_for_every_tree_is_one_line_before_any_tree_starts(plot, tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text(TINY.replace("population = 8", "populaton = 8"))
    assert main(["stand", "--stem-map", str(plot / "map.csv"), "--recipe", str(bad), "-o", str(tmp_path / "s")]) == 2
    err = _lines(capsys)
    assert len(err) == 1 and str(bad) in err[0] and "populaton" in err[0], err
    assert not (tmp_path / "s").exists()
