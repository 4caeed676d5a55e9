"""``bforest compare``: optimisers on equal evaluation budgets, repeated with different seeds."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..config import config_to_dict, load_config, parse_config
from .objective import build_target, progress_bar
from ..registry import component_class
from .store import RunDirError, RunStore

def _settings_for_budget(name: str, budget: int, own: dict | None = None) -> dict:
    """Settings that let the shared evaluation budget, not the optimiser's own length limits,
    end each run; ``own`` (the config's settings when the config names this optimiser) is kept
    otherwise, so the recipe's population, restarts or noise stop are what is compared."""
    fields = component_class("optimizer", name).Settings.model_fields
    out = {k: v for k, v in (own or {}).items() if k != "kind"}
    out.update({k: 10**6 for k in ("generations", "maxiter", "stall_generations") if k in fields})
    if "maxeval" in fields:
        out["maxeval"] = budget
    if "steps" in fields:  # MCMC: every step evaluates at least one walker, so this spends the budget
        out["steps"] = int(budget)
    return out


def best_so_far(run_dir: Path) -> np.ndarray:
    """The best distance of a grown tree after each evaluation (inf until the first one): a failed
    simulation's penalty is no fit, as in ``RunStore.best``."""
    with RunStore.open(run_dir) as store:
        evs = store.evaluations()
    return np.minimum.accumulate(np.array([e.distance if e.status == "ok" else np.inf for e in evs], float))


def compare(config_path, optimizers, budget: int, repeats: int = 3, out_dir=None, threshold=None,
            progress: bool = False, resume: bool = False, overwrite: bool = False) -> dict:
    """Run each optimiser ``repeats`` times with ``budget`` evaluations; returns the table, the
    curves and the figure path.

    A run directory of ``out_dir`` that already exists is an error unless ``resume`` (continue
    it, or read it back when it has finished: a run is named ``<optimizer>-<repeat>`` and its
    config must be the one this comparison would write, so an optimiser can be added to an
    earlier comparison without repeating the others) or ``overwrite`` (start it anew).

    ``threshold`` (the distance for "evaluations to reach") is a number, the name of one of the
    compared optimisers (its median final best: "how soon do the others get where it ends?"),
    or None (5 % above the lower quartile of all final bests)."""
    if isinstance(threshold, str):
        try:
            threshold = float(threshold)
        except ValueError:
            if threshold not in optimizers:
                raise ValueError(f"--threshold {threshold!r} is neither a distance nor one of the compared "
                                 f"optimisers ({', '.join(optimizers)})") from None
    from .fit import fit, same_config
    base = load_config(config_path)
    out_dir = Path(out_dir) if out_dir else Path("runs") / f"compare-{Path(config_path).stem}"
    out_dir.mkdir(parents=True, exist_ok=True)
    target = build_target(base)
    raw = config_to_dict(base)
    curves, rows = {}, []
    bar = progress_bar(len(optimizers) * repeats * int(budget), "compare", "eval", progress)
    for name in optimizers:
        curves[name] = []
        for r in range(repeats):
            cfg_raw = dict(raw)
            cfg_raw["seed"] = int(base.seed) + r
            own = raw.get("optimizer") if raw.get("optimizer", {}).get("kind") == name else None
            cfg_raw["optimizer"] = {"kind": name, **_settings_for_budget(name, budget, own)}
            cfg_raw["stop"] = {**raw.get("stop", {}), "max_evaluations": int(budget)}
            cfg = parse_config(cfg_raw, source=f"compare/{name}")
            run = out_dir / f"{name}-{r}"
            state = "new" if overwrite else RunStore.state(run)
            if state != "new" and not resume:
                raise RunDirError(f"{run}: already holds a run; add to this comparison with --resume, replace "
                                  "its runs with --overwrite, or choose another -o")
            if state != "new" and not same_config(run, cfg):
                raise RunDirError(f"{run}: was made with another config (or budget); replace it with "
                                  "--overwrite, or choose another -o")
            bar.set_postfix_str(f"{name} run {r + 1}/{repeats}" + {"finished": " (read back)",
                                "partial": " (resume)"}.get(state, ""), refresh=True)
            if state != "finished":
                fit(cfg, run, resume=state == "partial", progress=False, overwrite=overwrite, target=target)
            # the result as the run recorded it (its clock sums the sessions of a resumed run)
            best = json.loads((run / "best.json").read_text(encoding="utf-8"))
            row = {"best": best["distance"], "evaluations": best["n_evaluations"], "seconds": best["seconds"],
                   "stop_reason": best["stop_reason"]}
            bar.update(int(budget))  # a run that stopped early still takes its share of the total
            curve = best_so_far(run)
            curves[name].append(curve)
            rows.append({"optimizer": name, "repeat": r, **row})
    bar.close()
    finals = np.array([row["best"] for row in rows])
    if threshold is None:
        threshold = float(np.quantile(finals, 0.25)) * 1.05
    elif isinstance(threshold, str):
        threshold = float(np.median([row["best"] for row in rows if row["optimizer"] == threshold]))
    table = []
    for name in optimizers:
        mine = [row for row in rows if row["optimizer"] == name]
        best = np.array([row["best"] for row in mine])
        reach = []
        for c in curves[name]:
            hit = np.flatnonzero(c <= threshold)
            reach.append(int(hit[0]) + 1 if hit.size else None)
        reached = [x for x in reach if x is not None]
        table.append({"optimizer": name, "median_best": float(np.median(best)), "min_best": float(best.min()),
                      "max_best": float(best.max()),
                      "evals_to_threshold": float(np.median(reached)) if reached else None,
                      "reached": f"{len(reached)}/{len(reach)}",
                      "median_seconds": float(np.median([row["seconds"] for row in mine]))})
    lines = [f"budget {budget} evaluations x {repeats} repeats; threshold {threshold:.4f}",
             f"{'optimizer':<10}{'median best':>12}{'range':>20}{'evals to thr.':>15}{'reached':>9}{'wall s':>9}"]
    for t in table:
        e = "-" if t["evals_to_threshold"] is None else f"{t['evals_to_threshold']:.0f}"
        lines.append(f"{t['optimizer']:<10}{t['median_best']:>12.4f}{'[%.4f, %.4f]' % (t['min_best'], t['max_best']):>20}"
                     f"{e:>15}{t['reached']:>9}{t['median_seconds']:>9.1f}")
    text = "\n".join(lines)
    (out_dir / "compare.json").write_text(json.dumps({"budget": budget, "repeats": repeats, "threshold": threshold,
                                                      "table": table, "runs": rows}, indent=2))
    (out_dir / "compare.md").write_text(f"# Optimiser comparison\n\n```\n{text}\n```\n")
    return {"table": table, "table_text": text, "curves": curves, "runs": rows, "threshold": threshold,
            "out_dir": out_dir}
