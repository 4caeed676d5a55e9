"""Parameter recovery (docs/recovery.md): runs the fits of this folder and writes that page.

    .venv/bin/python examples/validation/run_validation.py            # everything (about 1 h on 2 cores)
    .venv/bin/python examples/validation/run_validation.py --only sot_synthetic
    .venv/bin/python examples/validation/run_validation.py --report   # tables/figures from finished runs
    .venv/bin/python examples/validation/run_validation.py --check runs/validation-check
        # refit the synthetic recoveries into a fresh folder and compare with the page (no rewrite)

Fits already finished in runs/validation/<name> (best.json present) are reused; an interrupted
fit is resumed. Every number in docs/recovery.md comes from these runs; docs/validation.md
summarises them (update its rows by hand when this page changes).
"""

from __future__ import annotations

import argparse
import json
import re
import time
from pathlib import Path

import numpy as np

import bforest_core as bf
from bforest_core.pipeline.clones import clones

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
RUNS = ROOT / "runs" / "validation"
DOC = ROOT / "docs" / "recovery.md"
IMG = ROOT / "docs" / "img" / "validation"
QSM = ROOT.parent / "shared" / "data" / "qsm"

PAPER_TABLE2 = {  # Silva Fennica 2016, Table 2: relative error, %
    "lr_mean": 4.65,
    "lr_sd": 6.95,
    "q_mean": 2.88,
    "q_sd": 28.88,
    "years": 6.67,
    "beta_incr": 2.33,
    "zeta_sd": 12.58,
    "beta_init": 15.61,
}
SYMBOL = {
    "lr_mean": "L_R mean",
    "lr_sd": "L_R sd",
    "q_mean": "Q mean",
    "q_sd": "Q sd",
    "years": "T",
    "beta_incr": "Δβ",
    "zeta_sd": "Δζ",
    "beta_init": "β_init",
    "alpha1": "α₁",
    "branch_angle": "branch angle",
    "drop_thresh": "drop threshold",
    "shadow_a": "shadow a",
    "init_lambda": "λ (initial)",
}


def run_fit(name: str, clones_n: int | None = None, runs: Path = RUNS) -> Path:
    cfg_path = HERE / f"{name}.toml"
    out = runs / name
    if (out / "best.json").exists():
        print(f"[{name}] reusing finished fit in {out}")
    else:
        resume = (out / "evaluations.sqlite").exists()
        print(f"[{name}] fitting ({'resume' if resume else 'new'}) ...", flush=True)
        t0 = time.monotonic()
        cfg = bf.load_config(out / "config.toml" if resume else cfg_path)
        res = bf.fit(cfg, out, resume=resume, progress=False)
        print(
            f"[{name}] best {res.distance:.4f} after {res.n_evaluations} evaluations, {time.monotonic() - t0:.0f} s",
            flush=True,
        )
    if clones_n and not (out / "clones" / "summary.json").exists():
        print(f"[{name}] {clones_n} clones ...", flush=True)
        clones(out, n=clones_n, progress=False)
    return out


def recovery_table(kind: str, seeds=(1, 2, 3)) -> tuple[str, dict]:
    rows, errs = [], {}
    names = None
    for s in seeds:
        out = RUNS / f"{kind}_seed{s}"
        if not (out / "best.json").exists():
            continue
        cfg = bf.load_config(out / "config.toml")
        best = json.loads((out / "best.json").read_text())
        target = cfg.target.generate.params
        names = list(cfg.ssm.free)
        for n in names:
            t, e = float(target[n]), float(best["params"][n])
            errs.setdefault(n, []).append(abs(e - t) / abs(t) * 100)
        rows.append((s, best))
    if not rows:
        return "(not run)\n", {}
    first_cfg = bf.load_config(RUNS / f"{kind}_seed{rows[0][0]}" / "config.toml")
    target = first_cfg.target.generate.params
    head = (
        "| parameter | target | bounds | "
        + " | ".join(f"estimate (seed {s})" for s, _ in rows)
        + " | rel. error % (per seed) | median error % |"
        + (" paper error % |" if kind.startswith("lignum") else "")
    )
    sep = "|" + "---|" * (head.count("|") - 1)
    lines = [head, sep]
    for n in names:
        fp = first_cfg.ssm.free[n]
        ests = " | ".join(f"{float(b['params'][n]):.4g}" for _, b in rows)
        e = errs[n]
        line = (
            f"| {SYMBOL.get(n, n)} (`{n}`) | {float(target[n]):.4g} | {fp.lower:g}–{fp.upper:g} | {ests} | "
            f"{', '.join(f'{x:.1f}' for x in e)} | {np.median(e):.1f} |"
        )
        if kind.startswith("lignum"):
            line += f" {PAPER_TABLE2[n]:.2f} |"
        lines.append(line)
    all_e = np.array([x for v in errs.values() for x in v])
    per_seed = [np.median([errs[n][i] for n in names]) for i in range(len(rows))]
    within15 = [all(errs[n][i] <= 15 for n in names) for i in range(len(rows))]
    dist = [f"{b['distance']:.4f} ({b['n_evaluations']} eval.)" for _, b in rows]
    summary = {
        "median_error_per_seed": per_seed,
        "all_within_15": within15,
        "median_all": float(np.median(all_e)),
        "max_all": float(all_e.max()),
        "best_distance": dist,
    }
    if kind.startswith("lignum"):
        better = [SYMBOL.get(n, n) for n in names if np.median(errs[n]) < PAPER_TABLE2[n]]
        worse = [SYMBOL.get(n, n) for n in names if np.median(errs[n]) > PAPER_TABLE2[n]]
        summary["better_than_paper"] = better
        lines += [
            "",
            f"Median error (over the three targets) below the paper's single-run error for "
            f"{len(better)} of {len(names)} parameters ({', '.join(better) or 'none'}); above it for "
            f"{', '.join(worse) or 'none'}.",
        ]
    lines += [
        "",
        f"Best distance per seed: {', '.join(dist)}. Median relative error per seed: "
        f"{', '.join(f'{x:.1f} %' for x in per_seed)}; over all parameters and seeds: median "
        f"{np.median(all_e):.1f} %, maximum {all_e.max():.1f} %. Every parameter within 15 %: "
        f"{', '.join('yes' if w else 'no' for w in within15)} (per seed).",
    ]
    return "\n".join(lines) + "\n", summary


def real_tree_section(name: str = "lignum_pine3") -> str:
    out = RUNS / name
    if not (out / "best.json").exists():
        return "(not run)\n"
    best = json.loads((out / "best.json").read_text())
    summ = (
        json.loads((out / "clones" / "summary.json").read_text())
        if (out / "clones" / "summary.json").exists()
        else None
    )
    cfg = bf.load_config(out / "config.toml")
    lines = [
        f"Best distance {best['distance']:.4f} after {best['n_evaluations']} evaluations "
        f"({best['stop_reason']}); per set: "
        + ", ".join(f"{k} {v:.4f}" for k, v in best["per_set"].items() if v is not None)
        + ".",
        "",
        "| parameter | bounds | best fit | paper (SF Fig. 4) |",
        "|---|---|---|---|",
    ]
    paper = {
        "lr_mean": 0.01,
        "lr_sd": 0.002,
        "q_mean": 0.11,
        "q_sd": 0.03,
        "years": 32,
        "shadow_len": 0.87,
        "shadow_max": 72.4,
        "r_env_mean": 0.83,
        "r_env_sd": 0.23,
        "beta_init": 34.6,
        "beta_incr": 5.5,
        "zeta_sd": 8.9,
        "beta_max": 77.1,
        "gamma_sd": 7.6,
        "shed_year": 12,
        "shed_mu": 5.2,
    }
    for n, fp in cfg.ssm.free.items():
        lines.append(f"| `{n}` | {fp.lower:g}–{fp.upper:g} | {float(best['params'][n]):.4g} | {paper.get(n, '–')} |")
    lines.append("")
    if summ:
        tm = summ["target_metrics"]
        lines += [
            f"**{summ['ok']} clones** (of {summ['count']}; fresh seeds, the best-fit parameters). "
            "Classical metrics of the clones against the QSM (not fitted):",
            "",
            "| metric | QSM | clones: mean ± sd [min, max] | relative error: mean (median) | paper |",
            "|---|---|---|---|---|",
        ]
        for key, ek, paper_txt in (
            ("height", "d_h", "height underestimated by about 7 %"),
            ("girth", "d_g", "breast-height diameter overestimated by about 55 %"),
            ("crown_spread", "d_c", "–"),
        ):
            v, e = summ.get(key), summ.get(ek)
            if v and e:
                lines.append(
                    f"| {key} (m) | {tm[key]:.3f} | {v['mean']:.3f} ± {v['sd']:.3f} [{v['min']:.3f}, "
                    f"{v['max']:.3f}] | {100 * e['mean']:.1f} % ({100 * e['median']:.1f} %) | {paper_txt} |"
                )
        dbh = [r.get("dbh") for r in summ["rows"] if r.get("status") == "ok" and r.get("dbh") is not None]
        dbh = np.array([x for x in dbh if np.isfinite(x)], float)
        if dbh.size and np.isfinite(tm.get("dbh", np.nan)):
            e = np.abs(dbh - tm["dbh"]) / tm["dbh"]
            lines.append(
                f"| DBH at 1.3 m (m) | {tm['dbh']:.3f} | {dbh.mean():.3f} ± {dbh.std(ddof=1):.3f} "
                f"[{dbh.min():.3f}, {dbh.max():.3f}] | {100 * e.mean():.1f} % ({100 * np.median(e):.1f} %) | "
                "overestimated by about 55 % |"
            )
        lines.append("")
        lines += stand_mates_section(out, cfg, summ)
    return "\n".join(lines) + "\n"


def stand_mates_section(out, cfg, summ) -> list[str]:
    """Distances of the clones to pine 3 against those of its two stand-mates (same features,
    distance and data-side normalisation as the fit)."""
    from bforest_core.pipeline.target import build_target

    tgt = build_target(cfg)
    fs = bf.component("features", cfg.features.kind, **tgt.feature_settings)
    dist = bf.component("distance", cfg.distance.kind, **cfg.distance.model_dump(exclude={"kind"}))
    dist.prepare(tgt.U, tgt.columns)
    mates = {}
    for name in ("pine_ruotsinkyla_1.mat", "pine_ruotsinkyla_2.mat"):
        p = QSM / name
        if p.exists():
            U = fs.extract(bf.read_qsm(p))
            per = dist.compute_per_set(U, tgt.U)
            mates[name] = (dist.combine(per, cfg.objective.weights), per)
    clone_d = np.array([r["distance"] for r in summ["rows"] if r.get("status") == "ok"], float)
    lines = [
        "Structural distance to pine 3 (KS, 256 gp2 lines, z-scored on pine 3, circular angles, "
        f"subtree topology; sets {', '.join(tgt.U)}):",
        "",
        "| tree | distance to pine 3 | per set |",
        "|---|---|---|",
    ]
    set_names = list(tgt.U)
    per_clone = {
        s: np.array([r["per_set"][s] for r in summ["rows"] if r.get("status") == "ok"], float) for s in set_names
    }
    lines.append(
        f"| clones (n = {clone_d.size}): median [min, max] | {np.median(clone_d):.3f} "
        f"[{clone_d.min():.3f}, {clone_d.max():.3f}] | "
        + ", ".join(f"{s} {np.median(v):.3f}" for s, v in per_clone.items())
        + " |"
    )
    for name, (d, per) in mates.items():
        frac = float(np.mean(clone_d < d)) if clone_d.size else float("nan")
        lines.append(
            f"| {name} (stand-mate) | {d:.3f} | "
            + ", ".join(f"{k} {v:.3f}" for k, v in per.items())
            + f" (clones closer than this tree: {100 * frac:.0f} %) |"
        )
    return lines + [""]


def figures():
    """Copy the run figures the doc shows into docs/img/validation."""
    import shutil

    IMG.mkdir(parents=True, exist_ok=True)
    picks = [
        ("lignum_synthetic_seed1", "trees.png"),
        ("lignum_synthetic_seed1", "convergence.png"),
        ("sot_synthetic_seed1", "trees.png"),
        ("lignum_pine3", "trees.png"),
        ("lignum_pine3", "clones.png"),
        ("lignum_pine3", "clone_metrics.png"),
        ("lignum_pine3", "set_S1.png"),
        ("lignum_pine3", "convergence.png"),
        ("lignum_pine3_rich", "clones.png"),
        ("lignum_pine3_trunk", "clones.png"),
    ]
    shown = {}
    for run, fig in picks:
        src = RUNS / run / "figures" / fig
        if src.exists():
            dst = IMG / f"{run}_{fig}"
            shutil.copy(src, dst)
            shown[(run, fig)] = dst.relative_to(DOC.parent)
    return shown


def write_doc():
    from bforest_core.report import write_report

    for name in (
        "lignum_synthetic_seed1",
        "sot_synthetic_seed1",
        "lignum_pine3",
        "lignum_pine3_rich",
        "lignum_pine3_trunk",
    ):
        if (RUNS / name / "best.json").exists():
            write_report(RUNS / name)
    lig, lig_s = recovery_table("lignum_synthetic")
    lig3, lig3_s = recovery_table("lignum_synthetic_k3")
    ligr, ligr_s = recovery_table("lignum_synthetic_rich")
    sot, sot_s = recovery_table("sot_synthetic")
    sot3, sot3_s = recovery_table("sot_synthetic_k3")
    shown = figures()

    def img(run, fig, caption):
        p = shown.get((run, fig))
        return f"![{caption}]({p})\n\n*{caption}*\n" if p else ""

    text = f"""# Parameter recovery: synthetic targets and the Silva Fennica pine

Can a fit find the parameters a tree was grown with? Sections 1 and 2 grow a target tree with
known parameters and fit them back (the Silva Fennica 2016 protocol, its Table 2); section 3 fits
LIGNUM to the Silva Fennica pine with the paper's data sets. The summary of these and the other
results: [validation](validation.md).

Every number on this page comes from the runs of `examples/validation/` (configs beside the
driver), made by

```
.venv/bin/python examples/validation/run_validation.py
```

which fits (or resumes) each run into `runs/validation/<name>/` and rewrites this page (about 1 h
on 2 cores). `run_validation.py --check DIR` refits the synthetic recoveries into DIR and compares
them with this page instead. A single run:
`bforest fit examples/validation/<name>.toml -o runs/validation/<name>`. Distances: sliced KS, 256
gp2 lines, z-scored on the data side, circular angles, `subtree` topology on both sides.

## 1. Synthetic recovery, simplified LIGNUM (Silva Fennica Table 2 protocol)

Target: LIGNUM with preset `sf_synthetic` (Perttunen set, R = 30, S_max = 10, S_L = 0.55 m,
V_S = 0.02 m, R_env = 1.33 m, β_max = 95°, Δγ = 5°) and the 8 target values below, grown with
target seed 1, 2 or 3. Fit: the 8 parameters with model seed 2 (`[objective] model_seeds = [2]`),
bounds 50–150 % of each target value, data set S¹ (the paper's taper (R, L) and curvature (γ, ζ)
sets of the first-order branches, pooled in one table), GA population 40, elite 4, 22 generations
(880 evaluations).

{lig}
{img("lignum_synthetic_seed1", "trees.png", "LIGNUM synthetic target (seed 1) and the best fit (model seed 2)")}

{img("lignum_synthetic_seed1", "convergence.png", "GA convergence of the LIGNUM recovery (target seed 1)")}

### 1b. Doing better than the protocol: three model seeds per evaluation

With one model seed the fit also fits that realisation's noise, and the GA stops once 10
generations bring no improvement. Configs `lignum_synthetic_k3_seed*.toml`: each evaluation is
the mean distance over model seeds 2, 3 and 4 (common random numbers: the same three seeds for
every parameter vector), the GA runs all 22 generations with intermediate crossover; everything
else as above.

{lig3}
### 1c. More of the tree's structure

The remaining errors are mostly compensations that one target realisation cannot resolve
through S¹ alone (on target seed 1, a thinner radius:length ratio L_R together with a stronger
apical dominance Q reproduces the same taper). Configs `lignum_synthetic_rich_seed*.toml` add
the trunk's segments and the branch tables: data sets S⁰˒¹ and B¹˒², three model seeds, full GA.

{ligr}
With the trunk in the data the age T is recovered within one year for every target, and L_R,
Q and β_init come close; Δβ (the mean yearly bending) is then under-estimated by about 15 % for
all three targets alike — a bias, not noise, so some fixed parameter or the bending cap β_max
compensates for it. The stretch aim of the issue (every parameter within 15 %, median within
5 %) is met for one target of three (see the last line of the table).


## 2. Synthetic recovery, SOT (5 parameters)

Target: SOT at 16 cycles with α₁ = 1.5, branch angle 50°, drop threshold 0.2, shadow a = 0.5,
initial λ = 0.55 (other parameters at the calibrated defaults, clone noise on), target seed 1, 2
or 3; fit with model seed 2, bounds 50–150 % (λ: its whole range 0.35–0.65), data sets S⁰˒¹ and
B¹˒², GA population 40, elite 4, 22 generations.

{sot}
{img("sot_synthetic_seed1", "trees.png", "SOT synthetic target (seed 1) and the best fit")}

### 2b. Three model seeds per evaluation

Configs `sot_synthetic_k3_seed*.toml`: as above, but each evaluation averages model seeds 2, 3
and 4 (common random numbers) and the GA runs all 22 generations with intermediate crossover.

{sot3}

## 3. Real tree: LIGNUM fitted to pine_ruotsinkyla_3 (the Silva Fennica pine)

Config `examples/validation/lignum_pine3.toml`: preset `sf_real`, the paper's 16 free parameters
and bounds, data sets S¹ and B¹ (taper, curvature and branching angles of the first-order
branches), GA population 50, elite 2, 24 generations; then 100 clones.

{real_tree_section()}
How to read this: the fit sees only the first-order branches (S¹, B¹), as in the paper. The
clones' crowns are denser than the scanned pine's because branches of order ≥ 2 are not fitted
and the QSM misses most fine branching (occlusion of the upper crown, 28 % of its cylinders are
gap fillers); the paper reports the same effect. Crown spread and girth are therefore
over-estimated, while the structural distance of the clones to pine 3 is smaller than that of
its two stand-mates. Fitting S⁰ (the trunk) and B² as well is the obvious next step for girth.

{img("lignum_pine3", "trees.png", "pine_ruotsinkyla_3 (QSM) and the best-fit LIGNUM tree")}
{img("lignum_pine3", "clones.png", "Six clones of the best fit beside the QSM")}
{img("lignum_pine3", "clone_metrics.png", "Classical metrics over the 100 clones; the QSM's value marked")}
{img("lignum_pine3", "set_S1.png", "Data set S¹: QSM (blue) against the best fit (red)")}

### 3b. The same fit with the trunk and second-order branches

Config `examples/validation/lignum_pine3_rich.toml`: as above, with data sets S⁰˒¹ (trunk and
first-order segments) and B¹˒² (first- and second-order branches).

{real_tree_section("lignum_pine3_rich")}
{img("lignum_pine3_rich", "clones.png", "Variant 3b: six clones of the best fit beside the QSM")}

This variant is a negative result: pooling the trunk's ~150 segments with ~360 first-order
segments in one table dilutes the trunk, and the scan's second-order branches (sparse: the QSM
misses most fine branching to occlusion) pull the model towards other trees. The clones are far
taller than the pine and further from it than either stand-mate.

### 3c. The paper's sets plus the trunk as a set of its own

Config `examples/validation/lignum_pine3_trunk.toml`: data sets S⁰, S¹ and B¹, equal weights.

{real_tree_section("lignum_pine3_trunk")}
{img("lignum_pine3_trunk", "clones.png", "Variant 3c: six clones of the best fit beside the QSM")}

With the trunk as a set of its own, the trunk's taper enters the fit with a full weight: the
girth and breast-height diameter errors of the clones fall well below those of the paper's sets
(compare with section 3), at a small cost in height; crown spread is still over-estimated, since
higher-order branches remain unfitted. S⁰ itself stays the hardest table to match (its per-set
distance is the largest), so the simplified LIGNUM cannot reproduce this pine's trunk exactly.
"""
    DOC.write_text(text, encoding="utf-8")
    (RUNS / "summary.json").write_text(
        json.dumps(
            {"lignum": lig_s, "lignum_k3": lig3_s, "lignum_rich": ligr_s, "sot": sot_s, "sot_k3": sot3_s}, indent=2
        )
    )
    print(f"wrote {DOC}")


#: heading of each synthetic recovery's section on the page -> its configs (seed appended)
RECOVERIES = {
    "## 1. ": "lignum_synthetic_seed",
    "### 1b. ": "lignum_synthetic_k3_seed",
    "### 1c. ": "lignum_synthetic_rich_seed",
    "## 2. ": "sot_synthetic_seed",
    "### 2b. ": "sot_synthetic_k3_seed",
}


def check_recoveries(runs: Path) -> bool:
    """Refit every synthetic recovery into ``runs`` (fits already there are reused) and compare
    its best distance, evaluation count and estimates (as the page rounds them) with the page's
    tables; prints one line per run and returns whether every run gives the recorded result."""
    page = DOC.read_text(encoding="utf-8")
    heads = [m.start() for m in re.finditer(r"(?m)^##+ ", page)]
    same_all = True
    for head, stem in RECOVERIES.items():
        i = page.index(head)
        text = page[i : min([k for k in heads if k > i] or [len(page)])]
        recorded = re.search(r"Best distance per seed: (.*?)\. ", text).group(1).split("), ")
        for s in (1, 2, 3):
            b = json.loads((run_fit(f"{stem}{s}", runs=runs) / "best.json").read_text())
            got = f"{b['distance']:.4f} ({b['n_evaluations']} eval."
            diffs = []
            for name, v in b["params"].items():
                row = re.search(rf"(?m)^\| [^|]*\(`{name}`\) \|([^\n]*)$", text)
                cell = [c.strip() for c in row.group(1).split("|")][1 + s] if row else None
                if cell is not None and cell != f"{v:.4g}":
                    diffs.append(f"{name} {cell} -> {v:.4g}")
            same = recorded[s - 1].startswith(got) and not diffs
            same_all &= same
            print(
                f"{head.strip('# ')}{stem}{s}: page {recorded[s - 1].rstrip(')')}), re-run {got}); "
                f"estimates {'as on the page' if not diffs else ', '.join(diffs)} -> {'same' if same else 'DIFFERENT'}"
            )
    print("every recovery gives the recorded result" if same_all else "some recoveries differ from the page")
    return same_all


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--only", default=None, help="run only configs whose name starts with this")
    ap.add_argument("--report", action="store_true", help="only rewrite docs/recovery.md")
    ap.add_argument(
        "--check",
        type=Path,
        metavar="DIR",
        help="refit the synthetic recoveries into DIR and "
        "compare them with docs/recovery.md (the page is not rewritten)",
    )
    args = ap.parse_args()
    if args.check:
        raise SystemExit(0 if check_recoveries(args.check) else 1)
    RUNS.mkdir(parents=True, exist_ok=True)
    if not args.report:
        plan = (
            [f"sot_synthetic_seed{s}" for s in (1, 2, 3)]
            + [f"lignum_synthetic_seed{s}" for s in (1, 2, 3)]
            + ["lignum_pine3"]
            + [f"lignum_synthetic_{v}_seed{s}" for v in ("k3", "rich") for s in (1, 2, 3)]
            + ["lignum_pine3_rich"]
            + [f"sot_synthetic_k3_seed{s}" for s in (1, 2, 3)]
            + ["lignum_pine3_trunk"]
        )
        for name in plan:
            if args.only and not name.startswith(args.only):
                continue
            run_fit(name, clones_n=100 if name.startswith("lignum_pine3") else None)
    write_doc()


if __name__ == "__main__":
    main()
