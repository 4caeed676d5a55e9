"""Fidelity of the real-tree recipes: fit each recipe to each pine, grow clones, and check them.

For every recipe (``pine_sot.toml``, ``pine_lignum.toml``) and every pine of the Ruotsinkylä
stand, the recipe is used exactly as a user would: only its ``[target] qsm`` line changes. The
script fits, grows 30 clones, and records

* the fidelity table (height, DBH, crown spread, crown base height, first-order branch count, ...:
  the clones' mean against the pine);
* a fixed judge the recipes do not optimise: S¹ and B¹, sliced KS, z-score, 256 gp2 lines,
  subtree topology; the median judge distance from the pine to its clones beside the judge
  distance from the pine to the other pines of the stand;
* the wall time of the fit;
* a figure of the pine beside 5 of its clones on one scale.

Usage (from the repository root; the pines are read from ../shared/data/qsm)::

    .venv/bin/python examples/real/run_fidelity.py --out runs/fidelity [--recipes sot lignum] [--pines 3 1 2]

``--recipes`` also takes the path of a recipe file (``my_pine.toml``): a variant is checked on the
three pines without editing the shipped recipe.

Results go to ``OUT/fidelity.json`` and ``OUT/<recipe>_pine<k>/`` (run directories); the figures
to ``docs/img/validation/fidelity_<recipe>_pine<k>.png`` with ``--figures``; ``--doc`` rewrites the
real-tree fidelity section at the end of ``docs/validation.md`` from ``OUT/fidelity.json``
(``--doc`` alone, without fits: ``--pines`` empty, i.e. ``--pines``).
"""
from __future__ import annotations

import argparse
import json
import re
import time
import warnings
from pathlib import Path

import numpy as np

import bforest_core as bf
from bforest_core.pipeline.clones import clones
from bforest_core.report.trees import clones_figure

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
DATA = ROOT.parent / "shared" / "data" / "qsm"
PINES = {k: DATA / f"pine_ruotsinkyla_{k}.mat" for k in (1, 2, 3)}
#: the limits of the acceptance (pine 3) and the relaxed ones (the other pines)
LIMITS = {"height": 0.05, "dbh": 0.15, "crown_spread": 0.20, "crown_base_height": 0.25, "n_branches_o1": 0.25}


def judge():
    """The fixed judge: S1 and B1, sliced KS, z-score, 256 gp2 lines, subtree topology."""
    fs = bf.component("features", "branch-segment", sets=["S1", "B1"], topology="subtree")
    dist = bf.component("distance", "sliced", statistic="ks", lines=256, net="gp2", normalize="zscore")
    return fs, dist


def judge_distance(tree_model, tree_data) -> float:
    fs, dist = judge()
    fs.prepare([tree_data])
    Ud = fs.extract(tree_data)
    dist.prepare(Ud, {k: fs.columns(k) for k in fs.set_names})
    return float(dist.compute_sets(fs.extract(tree_model), Ud))


def recipe_for(recipe: Path, pine: Path, out: Path) -> Path:
    """The recipe with only its [target] qsm line changed (written into the run's folder)."""
    text = recipe.read_text()
    new, n = re.subn(r'(?m)^qsm\s*=\s*".*"$', f'qsm = "{pine.as_posix()}"', text)
    if n != 1:
        raise SystemExit(f"{recipe}: expected exactly one 'qsm = ...' line, found {n}")
    out.mkdir(parents=True, exist_ok=True)
    p = out / f"{recipe.stem}_{pine.stem}.toml"
    p.write_text(new)
    return p


def run_one(recipe: Path, k: int, out: Path, n_clones: int, figures: bool) -> dict:
    run = out / f"{recipe.stem}_pine{k}"
    cfg_path = recipe_for(recipe, PINES[k], out)
    t0 = time.monotonic()
    res = bf.fit(bf.load_config(cfg_path), run, overwrite=True, progress=False)
    fit_seconds = time.monotonic() - t0
    s = clones(run, n=n_clones, replace=True, progress=False)
    fid = {r["statistic"]: r for r in s["fidelity"]["table"]}
    pine = bf.read_qsm(PINES[k])
    clone_trees = [bf.read_qsm(run / "clones" / r["file"]) for r in s["rows"] if r["status"] == "ok"]
    d_clones = [judge_distance(t, pine) for t in clone_trees]
    d_mates = {j: judge_distance(bf.read_qsm(PINES[j]), pine) for j in PINES if j != k}
    row = {"recipe": recipe.stem, "pine": k, "fit_seconds": fit_seconds, "evaluations": res.n_evaluations,
           "best_distance": res.distance, "params": res.params, "stop_reason": res.stop_reason,
           "clones_ok": s["ok"], "errors": {name: fid[name]["error"] for name in LIMITS if name in fid},
           "target": {name: fid[name]["target"] for name in LIMITS if name in fid},
           "clones_mean": {name: fid[name]["mean"] for name in LIMITS if name in fid},
           "judge_clones_median": float(np.median(d_clones)) if d_clones else None,
           "judge_stand_mates": d_mates, "warnings": s["fidelity"]["warnings"],
           "flags": s["fidelity"]["flags"]}
    if figures and clone_trees:
        shown = [(f"clone {i}", t) for i, t in enumerate(clone_trees[:5])]
        clones_figure(pine, shown, ROOT / "docs" / "img" / "validation" / f"fidelity_{recipe.stem}_pine{k}.png",
                      title=f"Pine {k} (left) and 5 clones of the {recipe.stem} recipe, one scale")
    return row


def verdict(row: dict) -> str:
    relax = 1.0 if row["pine"] == 3 else 1.5
    bad = [f"{k} {100 * v:+.0f}%" for k, v in row["errors"].items()
           if v is None or abs(v) > relax * LIMITS[k]]
    mates = np.median(list(row["judge_stand_mates"].values()))
    if row["judge_clones_median"] is not None and row["judge_clones_median"] > mates:
        bad.append(f"judge {row['judge_clones_median']:.3f} > stand-mates {mates:.3f}")
    return "meets the limits" if not bad else "misses: " + ", ".join(bad)


DOC = ROOT / "docs" / "validation.md"
#: docs/validation.md keeps everything above this line; the section below it is this script's
MARKER = "<!-- real-tree fidelity: written by examples/real/run_fidelity.py --doc -->"
NAMES = {"height": "height", "dbh": "DBH", "crown_spread": "crown spread",
         "crown_base_height": "crown base", "n_branches_o1": "1st-order branches"}


def doc_section(results: dict) -> str:
    """The fidelity section of docs/validation.md from the rows of fidelity.json."""
    head = ("| recipe | pine | fit | evaluations | " + " | ".join(NAMES.values())
            + " | judge: clones (median) | judge: stand-mates | verdict |")
    lines = [MARKER, "", "## 4. Real trees: clones that look like the scanned pine", "",
             "The real-tree recipes `examples/real/pine_sot.toml` and `examples/real/pine_lignum.toml` "
             "fitted to each pine of the Ruotsinkylä stand with only the `[target] qsm` line changed; "
             "30 clones per fit. Errors are those of the clones' mean against the QSM; branch counts "
             "leave out branches thinner than 1 cm at the base in both (the scan's detection limit). "
             "The judge is a distance no recipe optimises (S¹ and B¹, sliced KS, z-score, 256 gp2 lines, "
             "subtree topology): the median over clones of their distance to the pine, beside the "
             "pine's distance to the other two pines. Limits: height 5 %, DBH 15 %, crown spread 20 %, "
             "crown base and first-order branches 25 % on pine 3; half as much again on pines 1 and 2. "
             "Fit times are the wall times of these runs on the 2-core machine (shared with other jobs "
             "when they were made: quiet-machine timings are in performance.md).", "",
             "```", ".venv/bin/python examples/real/run_fidelity.py --out runs/fidelity --figures --doc", "```",
             "", head, "|" + "---|" * (head.count("|") - 1)]
    for key in sorted(results, key=lambda k: (results[k]["recipe"], [3, 1, 2].index(results[k]["pine"]))):
        r = results[key]
        errs = " | ".join("–" if r["errors"].get(n) is None else f"{100 * r['errors'][n]:+.1f} %" for n in NAMES)
        mates = ", ".join(f"{v:.3f}" for v in r["judge_stand_mates"].values())
        judge = "–" if r["judge_clones_median"] is None else f"{r['judge_clones_median']:.3f}"
        lines.append(f"| {r['recipe']} | {r['pine']} | {r['fit_seconds']:.0f} s | {r['evaluations']} | {errs} | "
                     f"{judge} | {mates} | {verdict(r)} |")
    lines.append("")
    for key in sorted(results):
        r = results[key]
        img = f"img/validation/fidelity_{r['recipe']}_pine{r['pine']}.png"
        if (DOC.parent / img).exists():
            lines += [f"![pine {r['pine']} and 5 clones, {r['recipe']}]({img})", ""]
    return "\n".join(lines)


def write_doc(results: dict) -> None:
    text = DOC.read_text(encoding="utf-8")
    keep = text.split(MARKER)[0].rstrip() + "\n\n"
    notes = text.split(MARKER)[1].split("<!-- notes -->", 1) if MARKER in text else []
    tail = ("\n<!-- notes -->" + notes[1]) if len(notes) == 2 else ""
    DOC.write_text(keep + doc_section(results) + tail, encoding="utf-8")
    print(f"wrote {DOC}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default="runs/fidelity", help="folder of the runs and fidelity.json")
    ap.add_argument("--recipes", nargs="+", default=["sot", "lignum"],
                    help="recipes: sot, lignum (examples/real/pine_<name>.toml) or the path of your own .toml")
    ap.add_argument("--pines", nargs="*", type=int, default=[3, 1, 2],
                    help="pines of the stand (1, 2, 3); none with --doc only rewrites the page")
    ap.add_argument("--clones", type=int, default=30, help="clones per fit")
    ap.add_argument("--figures", action="store_true", help="write docs/img/validation/fidelity_*.png")
    ap.add_argument("--doc", action="store_true", help="rewrite the fidelity section of docs/validation.md")
    args = ap.parse_args(argv)
    warnings.filterwarnings("ignore", category=RuntimeWarning)
    out = Path(args.out)
    result_path = out / "fidelity.json"
    results = json.loads(result_path.read_text()) if result_path.exists() else {}
    for arg in args.recipes:
        recipe = Path(arg) if arg.endswith(".toml") else HERE / f"pine_{arg}.toml"
        if not recipe.is_file():
            raise SystemExit(f"run_fidelity: no recipe file {recipe}")
        name = recipe.stem.removeprefix("pine_")
        for k in args.pines:
            row = run_one(recipe, k, out, args.clones, args.figures)
            results[f"{name}_pine{k}"] = row
            result_path.write_text(json.dumps(results, indent=2))
            errs = ", ".join(f"{key} {100 * v:+.1f}%" for key, v in row["errors"].items() if v is not None)
            print(f"{name} pine {k}: fit {row['fit_seconds']:.0f} s ({row['evaluations']} evaluations); {errs}; "
                  f"judge clones {row['judge_clones_median']:.3f} vs stand-mates "
                  f"{', '.join(f'{v:.3f}' for v in row['judge_stand_mates'].values())} -> {verdict(row)}",
                  flush=True)
    if args.doc:
        write_doc(results)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
