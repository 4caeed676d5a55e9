"""A stand of six sample trees on a Dask cluster of separate processes (issue 75). Prints, in one run:

1. the baseline: the stand with the ``serial`` executor, its trees one after another in one
   process (each tree's fit and 30 clones on one core): wall time, and each tree's time;
2. the same stand on ``dask scheduler`` + 2 ``dask worker`` processes started by this script
   (TLS, no HTTP; ``bforest_dask.launch``): wall time, and its ratio to the baseline (target
   <= 0.6: two workers give close to twice the throughput);
3. the same stand on a fresh cluster, one worker killed with SIGKILL once the trees have logged a
   third of the stand's evaluations, then ``bforest stand --resume``: the finished trees are not
   refitted, and its ``stand.csv`` and every tree's evaluation log equal the baseline's, row for
   row (the tree fitted alone on one core, and beside the other on busy workers: the same answer).

The trees are pines 1-3, wytham_tf2, wytham_tf3 and the coffeetree of ../shared/data/qsm, each
with the recipe ``bforest init`` writes for it, placed by a stem map 8 m apart.

    .venv/bin/python benchmarks/stand.py --out runs/bench_stand [--trees ...] [--skip-serial]

Run it alone on the machine (it takes 40-55 minutes on 2 cores): the ratio compares
wall times of the same run. A stand already in OUT is kept (delete OUT to measure again).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("BFOREST_QSM_DIR", ROOT.parent / "shared" / "data" / "qsm"))
TREES = [
    "pine_ruotsinkyla_1",
    "pine_ruotsinkyla_2",
    "pine_ruotsinkyla_3",
    "wytham_tf2",
    "wytham_tf3",
    "coffeetree_treeqsm_optqsm",
]
BFOREST = str(Path(sys.executable).with_name("bforest"))


def stem_map(out: Path, trees: list[str]) -> Path:
    rows = ["tree,file,x,y"] + [
        f"{t},{DATA / (t + '.mat')},{8.0 * (i % 3)},{8.0 * (i // 3)}" for i, t in enumerate(trees)
    ]
    path = out / "plot.csv"
    path.write_text("\n".join(rows) + "\n")
    return path


#: ``--quick``: every tree's evaluation budget (a check of this script, not a measurement)
QUICK = None


def config(out: Path, name: str, plot: Path, executor: dict) -> Path:
    lines = ["[stand]", f'stem_map = "{plot}"', "clones = 30", "realisations = 1"]
    lines += [f"max_evaluations = {QUICK}"] if QUICK else []
    lines += ["", "[executor]"]
    lines += [f'{k} = "{v}"' if isinstance(v, str) else f"{k} = {v}" for k, v in executor.items()]
    path = out / f"{name}.toml"
    path.write_text("\n".join(lines) + "\n")
    return path


def run_stand(cfg: Path, stand: Path, log: Path, kill=None) -> float:
    """``bforest stand CFG -o STAND`` (kept when STAND holds a finished stand): wall seconds."""
    done = stand / "stand.toml"
    if done.exists():
        print(f"  {stand} exists: kept (delete it to measure again)")
        return float("nan")
    t0 = time.perf_counter()
    with open(log, "w") as fh:
        proc = subprocess.Popen(
            [BFOREST, "stand", str(cfg), "-o", str(stand), "-q", "--no-report"], stdout=fh, stderr=fh
        )
        if kill is not None:
            kill(proc)
        proc.wait()
    return time.perf_counter() - t0


def tree_seconds(stand: Path) -> dict:
    """Each tree's fit time (best.json) and its clones' (the clones' files' times)."""
    out = {}
    for run in sorted((stand / "trees").iterdir()):
        best = json.loads((run / "best.json").read_text())
        clones = sorted((run / "clones").glob("clone_*.txt"), key=lambda p: p.stat().st_mtime)
        grow = clones[-1].stat().st_mtime - (run / "best.json").stat().st_mtime if clones else 0.0
        out[run.name] = (best["seconds"], grow)
    return out


def log_rows(path: Path):
    with sqlite3.connect(path) as con:
        return con.execute("SELECT idx, params, seeds, distance, status FROM evaluations ORDER BY idx").fetchall()


def budget(plot_trees: list[str], out: Path) -> int:
    import tomllib

    total = 0
    for t in plot_trees:
        r = out / "serial" / "recipes" / f"{t}.toml"
        total += QUICK or (tomllib.loads(r.read_text())["stop"]["max_evaluations"] if r.exists() else 3000)
    return total


def killer(stand: Path, cluster, share: float, total: int, note: dict):
    """Kill one worker (SIGKILL) once the stand's logs hold ``share`` of its evaluations."""
    from distributed import Client

    from bforest_core.pipeline.store import logged_count
    from bforest_core.registry import component

    ex = cluster.executor_settings()
    sec = component("executor", "dask", **{k: v for k, v in ex.items() if k != "kind"}).settings.security()

    def kill(proc):
        with Client(scheduler_file=str(cluster.scheduler_file), security=sec, timeout=60) as client:
            client.wait_for_workers(2, timeout=120)
            pids = client.run(os.getpid)
            while proc.poll() is None:
                n = sum(logged_count(p) for p in stand.glob("trees/*/evaluations.sqlite"))
                if n >= share * total:
                    victim = sorted(pids.items())[0]
                    os.kill(victim[1], signal.SIGKILL)
                    note.update(killed=victim[0], at_evaluations=n, of=total)
                    return
                time.sleep(1.0)

    return kill


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="runs/bench_stand", help="folder of the stands (kept)")
    ap.add_argument("--trees", nargs="+", default=TREES, help="sample trees (names in ../shared/data/qsm)")
    ap.add_argument("--kill-at", type=float, default=1 / 3, help="share of the evaluations at which a worker dies")
    ap.add_argument("--quick", type=int, help="every tree's budget cut to this (checks the script; measures nothing)")
    args = ap.parse_args(argv)
    global QUICK
    QUICK = args.quick
    if not DATA.is_dir():
        print(f"the sample trees are not in {DATA} (needs ../shared/data/qsm beside the repository)")
        return 2
    from bforest_dask.launch import separate_cluster

    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    plot = stem_map(out, args.trees)
    print(f"1. baseline: {len(args.trees)} trees, one after another on one core (serial executor)")
    t_serial = run_stand(config(out, "serial", plot, {"kind": "serial"}), out / "serial", out / "serial.log")
    per = tree_seconds(out / "serial")
    for name, (fit_s, clone_s) in per.items():
        print(f"   {name:28s} fit {fit_s:7.1f} s, clones {clone_s:6.1f} s")
    if t_serial != t_serial:  # kept from an earlier run: its sum of tree times stands for it
        t_serial = sum(a + b for a, b in per.values())
    print(f"   wall {t_serial:.0f} s")
    print("2. the same stand on dask scheduler + 2 dask worker processes (TLS, no HTTP)")
    with separate_cluster(out / "cluster_2w", workers=2) as cluster:
        t_dask = run_stand(config(out, "dask", plot, cluster.executor_settings()), out / "dask", out / "dask.log")
    print(f"   wall {t_dask:.0f} s: {t_dask / t_serial:.2f} x the baseline (target <= 0.6)")
    print(f"3. again on a fresh cluster, one worker SIGKILLed at {args.kill_at:.0%} of the evaluations, then --resume")
    note: dict = {}
    with separate_cluster(out / "cluster_kill", workers=2) as cluster:
        cfg = config(out, "killed", plot, cluster.executor_settings())
        total = budget(args.trees, out)
        t_kill = run_stand(
            cfg, out / "killed", out / "killed.log", killer(out / "killed", cluster, args.kill_at, total, note)
        )
        before = {p.parent.name: p.stat().st_mtime_ns for p in (out / "killed").glob("trees/*/best.json")}
        r = subprocess.run(
            [BFOREST, "stand", "--resume", "-o", str(out / "killed"), "-q", "--no-report"],
            capture_output=True,
            text=True,
        )
    print(
        f"   killed {note.get('killed', '-')} after {note.get('at_evaluations', '-')} of {total} evaluations; wall {t_kill:.0f} s"
    )
    print(f"   --resume: {r.stdout.strip().splitlines()[0] if r.stdout.strip() else r.stderr.strip()}")
    after = {p.parent.name: p.stat().st_mtime_ns for p in (out / "killed").glob("trees/*/best.json")}
    refit = [k for k in before if after.get(k) != before[k]]
    same_table = (out / "killed" / "stand.csv").read_text() == (out / "serial" / "stand.csv").read_text()
    same_dask = (out / "dask" / "stand.csv").read_text() == (out / "serial" / "stand.csv").read_text()
    logs = [
        t
        for t in args.trees
        if log_rows(out / "killed" / "trees" / t / "evaluations.sqlite")
        != log_rows(out / "serial" / "trees" / t / "evaluations.sqlite")
    ]
    print(f"   finished trees refitted by --resume: {refit or 'none'}")
    print(f"   stand.csv equal to the baseline's: killed-and-resumed {same_table}, 2 workers {same_dask}")
    print(f"   evaluation logs that differ from the baseline's: {logs or 'none'}")
    ok = t_dask / t_serial <= 0.6 and same_table and same_dask and not logs and not refit
    print("all targets met" if ok else "a target was missed")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
