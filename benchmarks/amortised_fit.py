"""Fits that start from an amortised posterior against the shipped recipes, side by side in one run.

For every model (sot, lignum), pine of the Ruotsinkylä stand and run seed:

* ``amortised``: the recipe `bforest init PINE --amortised shipped --model MODEL` writes (the
  shipped estimator's posterior for the pine as the first points, a short lq-CMA-ES refinement,
  the answer among 8 points on 16 held-out sets), with its run seed set;
* ``recipe`` (with ``--recipes``): the shipped real-tree recipe (examples/real/pine_<model>.toml)
  with only its target and run seed changed, as examples/real/run_fidelity.py fits it.

Each fit grows 30 clones and is judged as docs/validation.md section 4 judges the recipes
(examples/real/run_fidelity.py: the clones' height within 7.5 %, DBH 20 %, crown spread 25 %,
crown base and first-order branches 30 % of the pine's, and the fixed judge's median distance from
the pine to its clones no larger than the median distance from the pine to its stand-mates). The
table gives per fit the growths (every simulated tree: the search's evaluations times their model
seeds, and the held-out scores of the candidates), the fit's wall time (the posterior's draws
included) and the verdict, and per model the worst case.

    .venv/bin/python benchmarks/amortised_fit.py --out runs/amortised_fit [--models sot lignum] [--pines 1 2 3] [--seeds 1 2 3 4 5] [--recipes [SEED ...]]

Finished fits are kept in ``OUT/amortised_fit.json`` and not refitted (``--again`` refits them).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "examples" / "real"))

from run_fidelity import PINES, code_version, fit_and_judge, judge_distance, recipe_for, verdict  # noqa: E402

import bforest_core as bf  # noqa: E402
from bforest_core.pipeline.amortised import write_amortised_recipe  # noqa: E402
from bforest_core.pipeline.store import RunStore  # noqa: E402


def growths(run: Path) -> int:
    """Every tree the fit grew: its evaluations' model seeds and its candidates' held-out seeds."""
    with RunStore.open(run) as st:
        return st.growths()


def amortised_recipe(model: str, k: int, seed: int, out: Path) -> Path:
    path = out / f"amortised_{model}_pine{k}_seed{seed}.toml"
    out.mkdir(parents=True, exist_ok=True)
    write_amortised_recipe(str(PINES[k]), path, "shipped", model)
    text = re.sub(r"(?m)^seed = \d+$", f"seed = {seed}", path.read_text(), count=1)
    path.write_text(text)
    return path


def run_one(kind: str, model: str, k: int, seed: int, out: Path, n_clones: int) -> dict:
    run = out / f"{kind}_{model}_pine{k}_seed{seed}"
    if kind == "amortised":
        cfg_path = amortised_recipe(model, k, seed, out)
    else:
        cfg_path = recipe_for(ROOT / "examples" / "real" / f"pine_{model}.toml", PINES[k], out, seed)
    t0 = time.monotonic()
    res, fit_seconds, best, s, fid, d_clones = fit_and_judge(cfg_path, run, PINES[k], n_clones)
    pine = bf.read_qsm(PINES[k])

    row = {
        "kind": kind,
        "model": model,
        "pine": k,
        "seed": seed,
        "run": str(run),
        "code": code_version(),
        "fit_seconds": fit_seconds,
        "seconds_with_clones": time.monotonic() - t0,
        "load": os.getloadavg()[0],
        "evaluations": res.n_evaluations,
        "growths": growths(run),
        "heldout_distance": best.get("heldout_distance"),
        "errors": {n: fid[n]["error"] for n in ("height", "dbh", "crown_spread", "crown_base_height", "n_branches_o1")},
        "judge_clones_median": float(np.median(d_clones)) if d_clones else None,
        "judge_stand_mates": {j: judge_distance(bf.read_qsm(PINES[j]), pine) for j in PINES if j != k},
    }
    row["verdict"] = verdict(row)
    return row


def table(results: dict) -> str:
    lines = [
        f"{'fit':<34}{'growths':>8}{'fit s':>8}{'load':>6}  verdict",
    ]
    for key in sorted(results):
        r = results[key]
        lines.append(f"{key:<34}{r['growths']:>8}{r['fit_seconds']:>8.0f}{r['load']:>6.1f}  {r['verdict']}")
    by = {}
    for r in results.values():
        by.setdefault((r["kind"], r["model"]), []).append(r)
    for (kind, model), rows in sorted(by.items()):
        ok = sum(r["verdict"] == "meets the limits" for r in rows)
        lines.append(
            f"{kind} {model}: {ok} of {len(rows)} fits meet every limit; growths {min(r['growths'] for r in rows)}-"
            f"{max(r['growths'] for r in rows)}, fit wall {min(r['fit_seconds'] for r in rows):.0f}-"
            f"{max(r['fit_seconds'] for r in rows):.0f} s"
        )
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default="runs/amortised_fit")
    ap.add_argument("--models", nargs="+", default=["sot", "lignum"])
    ap.add_argument("--pines", nargs="+", type=int, default=[1, 2, 3])
    ap.add_argument("--seeds", nargs="+", type=int, default=[1, 2, 3, 4, 5])
    ap.add_argument(
        "--recipes",
        nargs="*",
        type=int,
        metavar="SEED",
        help="also fit the shipped recipes (examples/real/) on these run seeds (none named: every one of --seeds)",
    )
    ap.add_argument("--clones", type=int, default=30)
    ap.add_argument("--again", action="store_true")
    args = ap.parse_args(argv)
    warnings.filterwarnings("ignore", category=RuntimeWarning)
    out = Path(args.out)
    path = out / "amortised_fit.json"
    results = json.loads(path.read_text()) if path.exists() else {}
    recipe_seeds = set(args.seeds if args.recipes == [] else args.recipes or [])
    for model in args.models:
        for k in args.pines:
            for seed in args.seeds:
                for kind in ["amortised", "recipe"] if seed in recipe_seeds else ["amortised"]:
                    key = f"{kind}_{model}_pine{k}_seed{seed}"
                    if key in results and not args.again:
                        continue
                    row = run_one(kind, model, k, seed, out, args.clones)
                    results[key] = row
                    out.mkdir(parents=True, exist_ok=True)
                    path.write_text(json.dumps(results, indent=2))
                    print(
                        f"{key}: {row['growths']} growths, fit {row['fit_seconds']:.0f} s "
                        f"(load {row['load']:.1f}) -> {row['verdict']}",
                        flush=True,
                    )
    print(table(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
