"""Fit-pipeline figures (issue: fit pipeline). Prints, in one run:

1. loop overhead per evaluation: wall time of a serial GA run minus the time spent inside the
   evaluations (simulate + features + distance, as logged), relative to the latter (target < 5 %);
2. process executor with 2 workers vs the serial executor on the same GA run (same evaluations;
   target >= 1.7x throughput);
3. (--full) the GA fit of examples/sot_pine3.toml: SOT to pine_ruotsinkyla_3 with S^{0,1} and
   B^{2,3,4}, population 40 x 25 generations, 2 workers (target < 4 minutes);
4. (--together RECIPE) a raced CMA-ES recipe (e.g. examples/real/pine_sot.toml) cut to
   --evaluations, with its starts taking turns one at a time and together
   (``[optimizer] grow_together``): wall time and how busy the workers were (their time inside
   evaluations over workers x the span of the evaluations).

    .venv/bin/python benchmarks/fit.py [--full] [--together examples/real/pine_sot.toml]
"""

from __future__ import annotations

import argparse
import shutil
import sqlite3
import tempfile
import time
from pathlib import Path

import bforest_core as bf
from bforest_core.config import config_to_dict, parse_config
from bforest_core.pipeline.store import RunStore

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "examples" / "sot_pine3.toml"


def _run(cfg_raw, out, generations, executor):
    raw = dict(cfg_raw)
    raw["optimizer"] = {**raw["optimizer"], "generations": generations}
    raw["executor"] = executor
    raw["stop"] = {}
    cfg = parse_config(raw, source="benchmark")
    t0 = time.perf_counter()
    res = bf.fit(cfg, out, progress=False, overwrite=True)
    wall = time.perf_counter() - t0
    evs = RunStore.open(out).evaluations()
    inside = sum(e.seconds for e in evs)
    return res, wall, inside, evs


def _noop_init():
    import bforest_core

    bforest_core.discover()


def _noop(x):
    return x


def _together(recipe: Path, evaluations: int) -> None:
    """Part 4: the recipe with its starts one at a time, then together, in the same run."""
    raw = config_to_dict(bf.load_config(recipe))
    workers = int(raw.get("executor", {}).get("workers", 1))
    tmp = Path(tempfile.mkdtemp(prefix="bforest-bench-"))
    try:
        rows = {}
        for together in (False, True):
            r = dict(raw)
            r["optimizer"] = {**raw["optimizer"], "grow_together": together}
            r["stop"] = {**raw.get("stop", {}), "max_evaluations": evaluations}
            out = tmp / f"together_{together}"
            t0 = time.perf_counter()
            res = bf.fit(parse_config(r, source=str(recipe)), out, progress=False, overwrite=True)
            wall = time.perf_counter() - t0
            with sqlite3.connect(out / "evaluations.sqlite") as db:  # when each evaluation ended
                n, inside, span = db.execute(
                    "select count(*), sum(seconds), max(finished) - min(finished) from evaluations"
                ).fetchone()
            rows[together] = wall
            print(
                f"{recipe.name}, {n} evaluations, starts {'together' if together else 'one at a time'}: "
                f"wall {wall:.1f} s, workers busy {inside / (workers * span):.0%}, "
                f"{res.diagnostics.get('n_batches')} batches; best {res.distance:.4f}"
            )
        print(f"  together against one at a time: {rows[False] / rows[True]:.2f}x")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--full", action="store_true", help="also the full 40 x 25 GA fit")
    ap.add_argument("--generations", type=int, default=10, help="generations for parts 1 and 2")
    ap.add_argument(
        "--together", metavar="RECIPE", help="part 4 only: a raced CMA-ES recipe, starts one at a time and together"
    )
    ap.add_argument("--evaluations", type=int, default=1200, help="part 4: the recipe's budget (default 1200)")
    args = ap.parse_args()
    if args.together:
        return _together(Path(args.together), args.evaluations)
    if not CONFIG.exists():
        raise SystemExit(f"{CONFIG} missing")
    base = bf.load_config(CONFIG)
    raw = config_to_dict(base)
    tmp = Path(tempfile.mkdtemp(prefix="bforest-bench-"))
    try:
        # the target is read and its tables extracted once per run: not part of the loop
        res_s, wall_s, inside_s, evs_s = _run(raw, tmp / "serial", args.generations, {"kind": "serial"})
        n = len(evs_s)
        setup_t0 = time.perf_counter()
        from bforest_core.pipeline.target import build_target

        build_target(base)
        setup = time.perf_counter() - setup_t0
        loop = wall_s - inside_s - setup
        print(
            f"serial GA, {args.generations} generations: {n} evaluations, wall {wall_s:.2f} s, "
            f"inside evaluations {inside_s:.2f} s ({inside_s / n * 1000:.1f} ms each), target set-up {setup:.2f} s"
        )
        print(
            f"  loop overhead (optimiser, seeds, cache, SQLite log, final best tree): "
            f"{loop:.2f} s = {100 * loop / inside_s:.1f} % of the evaluation time "
            f"({loop / n * 1000:.2f} ms per evaluation)  [target < 5 %]"
        )
        res_p, wall_p, inside_p, evs_p = _run(raw, tmp / "process", args.generations, {"kind": "process", "workers": 2})
        same = [(e.params, e.distance) for e in evs_s] == [(e.params, e.distance) for e in evs_p]
        ex = bf.component("executor", "process", workers=2)
        t0 = time.perf_counter()
        with ex.started(_noop_init, ()):
            list(ex.map_unordered(_noop, [0, 1]))
        startup = time.perf_counter() - t0
        print(
            f"process executor, 2 workers: wall {wall_p:.2f} s -> throughput {wall_s / wall_p:.2f}x serial "
            f"[target >= 1.7x]; identical evaluations: {same}"
        )
        print(
            f"  of which starting the 2 workers (imports, plugin discovery): about {startup:.2f} s; "
            f"excluding it: {wall_s / (wall_p - startup):.2f}x"
        )
        if args.full:
            cfg = bf.load_config(CONFIG)
            t0 = time.perf_counter()
            res = bf.fit(cfg, tmp / "full", progress=True, overwrite=True)
            wall = time.perf_counter() - t0
            evs = RunStore.open(tmp / "full").evaluations()
            fails = sum(e.status != "ok" for e in evs)
            print(
                f"full GA fit (40 x 25) of SOT to pine_ruotsinkyla_3, S0,1 + B2,3,4, 2 workers: "
                f"{len(evs)} evaluations ({fails} failed), wall {wall:.1f} s = {wall / 60:.2f} min "
                f"[target < 4 min]; best distance {res.distance:.4f}"
            )
            print("  best params: " + ", ".join(f"{k}={v:.4g}" for k, v in res.params.items()))
            keep = ROOT / "runs" / "bench-sot-pine3"
            shutil.rmtree(keep, ignore_errors=True)
            shutil.copytree(tmp / "full", keep)
            print(f"  run kept in {keep}")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
