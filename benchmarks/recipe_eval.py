"""Time per evaluation of a real-tree recipe's objective, against another revision of the code.

A fit's wall time is its evaluations' time over the workers, so this is the figure the fit-time
targets rest on. The script scores ``--points`` parameter vectors of a scrambled Sobol' design
over the recipe's bounds (or of a fit's log, ``--run``) with the recipe's own model seeds,
features, terms and distance, in one process (single core), and prints the median and total seconds per evaluation. With ``--against
REV`` it runs the same points with the code of git revision REV (checked out into a temporary
worktree) in the same session and prints the ratio and whether the distances agree.

    .venv/bin/python benchmarks/recipe_eval.py examples/real/pine_sot.toml --points 64 --against HEAD~3
    .venv/bin/python benchmarks/recipe_eval.py examples/real/pine_sot.toml --run runs/pine3 --against HEAD~3
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

ROOT = Path(__file__).resolve().parents[1]


def measure(recipe: str, points: int, seed: int, run: str | None = None) -> dict:
    """Seconds and distances of ``points`` evaluations with the code on ``sys.path``: a Sobol'
    design over the bounds, or (``run``) evaluations spread evenly over a fit's log."""
    import time

    import numpy as np
    from scipy.stats import qmc

    from bforest_core.config import config_to_dict, load_config
    from bforest_core.pipeline.fit import _free_specs

    try:  # the objective's modules since issue 34 (--against may run a revision before the split)
        from bforest_core.pipeline import seeds as sd_mod
        from bforest_core.pipeline import target as tg_mod
        from bforest_core.pipeline import worker as ob
    except ImportError:
        from bforest_core.pipeline import objective as ob

        sd_mod = tg_mod = ob

    cfg = load_config(recipe)
    tgt = tg_mod.build_target(cfg)
    if hasattr(tg_mod, "bounds_from_target"):  # bounds scaled by the target, resolved as a fit does
        cfg = tg_mod.bounds_from_target(cfg, tgt.trees)
    if hasattr(ob, "_SCORING"):  # a worker takes the validated config and holds a Scoring (issue 34)
        ob.init_worker(cfg, tgt.U, tgt.columns, tgt.feature_settings, tgt.terms)
        ssm = ob.worker_context().ssm
    else:  # a revision before: the config as a dict, the context a dict
        ob.init_worker(config_to_dict(cfg), tgt.U, tgt.columns, tgt.feature_settings, tgt.terms)
        ssm = ob._CTX["ssm"]
    names, lo, hi, _, _, integer = _free_specs(cfg, ssm)
    seeds = sd_mod.model_seeds(int(cfg.seed), cfg.objective.seeds)
    if run:
        from bforest_core.pipeline.store import RunStore

        evs = RunStore.open(run).evaluations()
        tasks = [(evs[i].params, list(evs[i].seeds)) for i in np.linspace(0, len(evs) - 1, points).astype(int)]
    else:
        m = int(np.ceil(np.log2(max(points, 2))))
        U = qmc.Sobol(len(names), scramble=True, rng=np.random.default_rng(seed)).random_base2(m)[:points]
        tasks = [
            ({n: (int(round(v)) if i else float(v)) for n, v, i in zip(names, lo + u * (hi - lo), integer)}, seeds)
            for u in U
        ]
    ob.evaluate_task(tasks[0])  # warm-up (imports, first allocations)
    secs, dists = [], []
    for params, sd in tasks:
        t0 = time.perf_counter()
        out = ob.evaluate_task((params, sd))
        secs.append(time.perf_counter() - t0)
        dists.append(out["distance"])
    return {"seconds": secs, "distances": dists}


def in_worktree(rev: str, recipe: str, points: int, seed: int, run: str | None) -> dict:
    """:func:`measure` with the code of ``rev`` (a temporary git worktree, same interpreter)."""
    with tempfile.TemporaryDirectory() as tmp:
        wt = Path(tmp) / "rev"
        subprocess.run(
            ["git", "-C", str(ROOT), "worktree", "add", "--detach", str(wt), rev], check=True, capture_output=True
        )
        try:
            env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(wt), str(wt / "plugins")])}
            code = (
                f"import sys, json; sys.path.insert(0, {str(ROOT / 'benchmarks')!r}); "
                f"from recipe_eval import measure; "
                f"print(json.dumps(measure({str(Path(recipe).resolve())!r}, {points}, {seed}, "
                f"{str(Path(run).resolve()) if run else None!r})))"
            )
            out = subprocess.run(
                [sys.executable, "-c", code], env=env, cwd=wt, check=True, capture_output=True, text=True
            )
            return json.loads(out.stdout.strip().splitlines()[-1])
        finally:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(wt)], capture_output=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("recipe", help="a run config (TOML), e.g. examples/real/pine_sot.toml")
    ap.add_argument("--points", type=int, default=64, help="parameter vectors (default 64)")
    ap.add_argument("--seed", type=int, default=1, help="seed of the Sobol' design")
    ap.add_argument(
        "--run",
        metavar="DIR",
        help="take the parameters from this fit's evaluation log instead "
        "(evenly spread over it: the mix of tree sizes a fit meets)",
    )
    ap.add_argument("--against", metavar="REV", help="also time the code of this git revision")
    a = ap.parse_args(argv)
    import numpy as np

    runs = {"this code": measure(a.recipe, a.points, a.seed, a.run)}
    if a.against:
        runs[a.against] = in_worktree(a.against, a.recipe, a.points, a.seed, a.run)
    where = f"spread over the log of {a.run}" if a.run else "of a Sobol' design over the bounds"
    print(f"{a.recipe}: {a.points} evaluations {where}, single core")
    print(f"  {'code':12s} {'median s/eval':>14s} {'total s':>9s}")
    for name, r in runs.items():
        print(f"  {name:12s} {np.median(r['seconds']):14.3f} {sum(r['seconds']):9.1f}")
    if a.against:
        mine, theirs = runs["this code"], runs[a.against]
        print(
            f"  ratio (total): {sum(theirs['seconds']) / sum(mine['seconds']):.2f}x; distances "
            + ("identical" if mine["distances"] == theirs["distances"] else "DIFFER")
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
