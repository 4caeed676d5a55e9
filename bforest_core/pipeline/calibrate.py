"""``bforest calibrate CONFIG.toml -n N``: simulation-based calibration (SBC) of a sampler's intervals.

Does the sampler's "90 % interval" contain the truth in 90 % of cases? For run ``i = 0..N-1``:

1. a parameter vector theta_i is drawn from the prior: uniform in the config's free bounds
   (integer parameters uniform over the whole numbers in their bounds), exactly the prior the
   samplers (``abc-smc``, ``emcee``) assume;
2. a target tree is grown from theta_i (and the fixed parameters) with a fresh model seed;
3. the configured sampler is fitted to that tree as a normal fit in ``DIR/run_<i>`` (the config's
   own ``[target]`` is replaced; everything else, executor included, is the config's);
4. its posterior (``posterior.csv``) gives per parameter the central 50 % and 90 % intervals
   (weighted quantiles 25-75 % and 5-95 %) and the rank of the truth among ``L`` posterior draws.

If the posterior is calibrated, the intervals contain the truth in 50 % and 90 % of the runs and
the ranks are uniform over 0..L (Talts et al. 2018, "Validating Bayesian inference algorithms
with simulation-based calibration"). Ranks piling up at both ends mean intervals too narrow
(over-confident), a hump in the middle intervals too wide, a slope a biased posterior.

The L draws are the posterior's weighted quantiles at the levels k / (L + 1), k = 1..L: a
stratified, deterministic sample of the posterior (for weighted ABC particles and autocorrelated
MCMC chains alike), so the rank, the number of draws below the truth, is uniform over 0..L
exactly when the truth's posterior quantile is uniform. Ties (integer parameters) are split at
random with a generator seeded by the study.

Seeds: run ``i``'s prior draw and target seed come from ``SeedSequence([seed, 0xCA1B, i])``, so
run ``i`` is the same whatever N (a study grows by asking for more runs with ``--resume``); the
fit of run ``i`` has the run seed ``seed + i``. A target seed never equals one of the fit's fixed
model seeds.

Resume: a finished run (``best.json``) is read back, not refitted; a run stopped half-way is
continued with the fit's own resume (its logged evaluations are replayed). Nothing is deleted
without ``overwrite``.
"""

from __future__ import annotations

import csv
import math
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pydantic

from ..config import (
    check_generated_target,
    config_to_dict,
    parse_config,
    read_toml,
    section_settings,
)
from ..errors import BayesForestError, ConfigError, validation_error_text
from ..io import write_json
from ..metrics import weighted_quantiles
from .fit import _free_specs, fit, same_config
from .posterior import uniform_draw
from .store import RunDirError, RunFiles, RunStore

if TYPE_CHECKING:
    from ..config import RunConfig

__all__ = [
    "calibrate",
    "central_interval",
    "sbc_rank",
    "prior_draw",
    "uniform_draw",
    "coverage_table",
    "rank_inside",
    "rank_counts",
    "uniform_band",
    "rank_bins",
    "LEVELS",
    "RANK_DRAWS",
]

#: central interval levels checked, in %
LEVELS = (50, 90)
#: posterior draws the truth is ranked among (ranks 0..L: 100 possible values)
RANK_DRAWS = 99
_STREAM = 0xCA1B


# ------------------------------------------------------------------------- arithmetic
def central_interval(x: np.ndarray, w: np.ndarray, level: float) -> tuple[float, float]:
    """The central ``level`` % interval of a weighted sample: its weighted quantiles
    ``(100 - level) / 2`` and ``(100 + level) / 2`` (see :func:`bforest_core.metrics.weighted_quantiles`)."""
    a = (100.0 - float(level)) / 2.0
    lo, hi = weighted_quantiles(np.asarray(x, float), np.asarray(w, float), [a, 100.0 - a])
    return float(lo), float(hi)


def sbc_rank(
    x: np.ndarray, w: np.ndarray, truth: float, draws: int = RANK_DRAWS, rng: np.random.Generator | None = None
) -> int:
    """Rank of ``truth`` among ``draws`` (L) posterior draws: how many of the posterior's weighted
    quantiles at the levels k / (L + 1), k = 1..L, lie below it (0..L). Draws equal to the truth
    (integer parameters) are split at random: a uniform number of them, 0..ties, counts below
    (``rng``; without one, half of them), as SBC prescribes for discrete parameters."""
    levels = 100.0 * np.arange(1, int(draws) + 1) / (int(draws) + 1)
    q = weighted_quantiles(np.asarray(x, float), np.asarray(w, float), levels)
    below = int(np.sum(q < truth))
    ties = int(np.sum(q == truth))
    if ties:
        below += int(rng.integers(0, ties + 1)) if rng is not None else ties // 2
    return below


def rank_bins(n_runs: int, draws: int = RANK_DRAWS) -> int:
    """Bins of the rank histogram: the largest divisor of L + 1 (so every bin holds equally many
    ranks) leaving at least about 4 runs per bin; at least 2."""
    divisors = [b for b in range(2, draws + 2) if (draws + 1) % b == 0]
    fit = [b for b in divisors if b <= max(2, n_runs // 4)]
    return max(fit) if fit else divisors[0]


def rank_counts(ranks, bins: int, draws: int = RANK_DRAWS) -> np.ndarray:
    """Histogram of ranks (0..L) in ``bins`` equal bins."""
    r = np.asarray(ranks, int)
    return np.bincount(r * bins // (draws + 1), minlength=bins)[:bins]


def _binomial_range(n_runs: int, p: float, prob: float) -> tuple[float, float]:
    """The central ``prob`` range of a Binomial(n_runs, p) count."""
    from scipy.stats import binom

    a = (1.0 - prob) / 2.0
    return float(binom.ppf(a, n_runs, p)), float(binom.ppf(1.0 - a, n_runs, p))


def uniform_band(n_runs: int, bins: int, prob: float = 0.99) -> tuple[float, float]:
    """The central ``prob`` range of one bin's count when the ranks are uniform
    (Binomial(n, 1/bins); the grey band of the SBC histogram)."""
    return _binomial_range(n_runs, 1.0 / bins, prob)


def coverage_range(n_runs: int, level: float, prob: float = 0.95) -> tuple[float, float]:
    """The central ``prob`` range of the coverage (%) of a calibrated ``level`` % interval over
    ``n_runs`` runs (Binomial)."""
    lo, hi = _binomial_range(n_runs, level / 100.0, prob)
    return 100.0 * lo / n_runs, 100.0 * hi / n_runs


def prior_draw(seed: int, i: int, lower, upper, integer) -> tuple[np.ndarray, int]:
    """Run ``i``'s truth (uniform in ``[lower, upper]``; integer parameters uniform over the
    whole numbers in the bounds) and its target seed, from ``SeedSequence([seed, 0xCA1B, i])``."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), _STREAM, int(i)]))
    theta = uniform_draw(rng, lower, upper, integer)
    target_seed = int(rng.integers(1, 2**31 - 1))
    return theta, target_seed


def rank_inside(rank: int, level: float, draws: int = RANK_DRAWS) -> bool:
    """Whether an SBC rank (0..L, ties split at random) lies in the central ``level`` % of the L + 1
    ranks: the coverage of a discrete parameter's central interval counted as SBC counts it (a
    whole-number interval holds ``level`` % of the posterior and more, so it over-covers)."""
    half = (int(draws) + 1) * float(level) / 200.0
    mid = (int(draws) + 1) / 2.0
    return mid - half <= rank + 0.5 <= mid + half


def coverage_table(rows: list[dict], names: list[str], lower, upper, integer=None) -> list[dict]:
    """Per parameter: runs, coverage of each central interval (fraction), mean interval width
    relative to the prior's width, and the chi-square p-value of the ranks' uniformity. An
    integer parameter (``integer``, per name) is covered when its rank is (:func:`rank_inside`)."""
    from scipy.stats import chisquare

    ok = [r for r in rows if r["status"] == "ok"]
    n = len(ok)
    bins = rank_bins(n) if n else 2
    whole = [False] * len(names) if integer is None else [bool(v) for v in integer]
    out = []
    for j, name in enumerate(names):
        width = float(upper[j] - lower[j])
        row = {"parameter": name, "runs": n}
        for lev in LEVELS:
            inside = [
                rank_inside(r["params"][name]["rank"], lev)
                if whole[j]
                else r["params"][name][f"lo{lev}"] <= r["params"][name]["truth"] <= r["params"][name][f"hi{lev}"]
                for r in ok
            ]
            row[f"covered{lev}"] = int(sum(inside))
            row[f"coverage{lev}"] = float(np.mean(inside)) if n else math.nan
            row[f"width{lev}"] = (
                float(np.mean([r["params"][name][f"hi{lev}"] - r["params"][name][f"lo{lev}"] for r in ok])) / width
                if n
                else math.nan
            )
        counts = rank_counts([r["params"][name]["rank"] for r in ok], bins) if n else np.zeros(bins, int)
        row["rank_counts"] = counts.tolist()
        row["rank_p"] = float(chisquare(counts).pvalue) if n >= bins else math.nan
        out.append(row)
    return out


# ------------------------------------------------------------------------- the study
def _read_study_config(path: Path):
    """The study's config; a ``[target]`` is optional (each run grows its own)."""
    raw = read_toml(path)
    if "target" not in raw and isinstance(raw.get("ssm"), dict) and isinstance(raw["ssm"].get("kind"), str):
        raw["target"] = {"generate": {"ssm": raw["ssm"]["kind"]}}  # replaced per run
    return parse_config(raw, base_dir=path.resolve().parent, source=str(path))


def _check_sampler(cfg: RunConfig, source: str) -> None:
    from ..registry import component_class

    cls = component_class("optimizer", cfg.optimizer.kind)
    if cls.posterior_kind is None:
        raise ConfigError(
            f"{source}: optimizer.kind: calibrate needs a sampler whose result is a posterior "
            f"(e.g. abc-smc, emcee); {cfg.optimizer.kind!r} gives a best fit only"
        )


def _fixed_model_seeds(cfg: RunConfig) -> set[int]:
    from .seeds import model_seeds

    o = cfg.objective
    if o.model_seeds:
        return {int(s) for s in o.model_seeds}
    return set(model_seeds(cfg.seed, o.seeds, "fixed")) if o.seed_mode == "fixed" else set()


def run_config(base: RunConfig, i: int, truth: dict, target_seed: int):
    """Run ``i``'s config: the study's, with a target grown from ``truth`` (plus the fixed
    parameters) with ``target_seed``, and the run seed ``seed + i``."""
    grown = {
        "ssm": base.ssm.kind,
        "seed": int(target_seed),
        "params": {**base.ssm.fixed, **truth},
        "settings": section_settings(base, "ssm", written=True),
    }
    raw = {"generate": grown, "topology": base.target.topology}
    try:  # the config's own [target] model: the SSM's settings typed as in any config
        target = type(base.target).model_validate(raw)
        cfg = base.model_copy(update={"target": target, "seed": int(base.seed) + int(i)})
        check_generated_target(cfg)
    except pydantic.ValidationError as exc:
        raise ConfigError(f"calibrate/run_{i:03d}: {validation_error_text(exc, raw, prefix=('target',))}") from None
    except ConfigError as exc:
        raise ConfigError(f"calibrate/run_{i:03d}: {exc}") from None
    taken = _fixed_model_seeds(cfg)
    if target_seed in taken:  # the target must not be grown with a seed the fit uses
        return run_config(base, i, truth, (target_seed * 7919 + 1) % (2**31 - 1))
    return cfg


def _study_spec(cfg: RunConfig):
    from ..config import build_component

    ssm = build_component(cfg, "ssm")
    names, lo, hi, _, _, integer = _free_specs(cfg, ssm)
    units = [ssm.parameter_spec(n).unit or "" for n in names]
    return names, lo, hi, integer, units


def _held_runs(out_dir: Path) -> list[Path]:
    """Run folders of an earlier study in ``out_dir`` holding evaluations or results."""
    return [d for d in sorted(out_dir.glob("run_*")) if RunStore.state(d) != "new"]


def _evaluate_run(run_dir: Path, names, theta, integer, seed: int, i: int) -> dict:
    """The row of one finished run: truth, intervals, median and rank per parameter."""
    from .posterior import read_posterior_csv

    files = RunFiles(run_dir)
    best = files.read_best()
    diag = best.get("diagnostics") or {}
    eps = diag.get("epsilon")
    if isinstance(eps, list):
        eps = next((e for e in reversed(eps) if e is not None), None)
    row = {
        "run": run_dir.name,
        "status": "ok",
        "n_evaluations": best.get("n_evaluations"),
        "seconds": best.get("seconds"),
        "stop_reason": best.get("stop_reason"),
        "epsilon": eps,
        "best_distance": best.get("distance"),
        "params": {},
    }
    try:
        got, X, w = read_posterior_csv(files.posterior_csv_path)
    except RunDirError as exc:
        row["status"] = f"no posterior ({exc})"
        return row
    if got != list(names):
        row["status"] = f"{RunFiles.POSTERIOR_CSV} has parameters {got}, not {list(names)}"
        return row
    row["params"] = posterior_params(X, w, names, theta, integer, seed, i)
    return row


def posterior_params(X: np.ndarray, w: np.ndarray, names, theta, integer, seed: int, i: int) -> dict:
    """Per parameter of run ``i``: truth, posterior median, central intervals and the SBC rank of
    the truth, from weighted draws ``X`` (rows) with weights ``w``."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), _STREAM, int(i), 1]))
    out = {}
    for j, name in enumerate(names):
        t = float(theta[j])
        p = {
            "truth": int(t) if integer[j] else t,
            "median": float(weighted_quantiles(X[:, j], w, [50])[0]),
            "rank": sbc_rank(X[:, j], w, t, RANK_DRAWS, rng),
        }
        for lev in LEVELS:
            p[f"lo{lev}"], p[f"hi{lev}"] = central_interval(X[:, j], w, lev)
        out[name] = p
    return out


def _plan_runs(cfg: RunConfig, out_dir: Path, n: int, overwrite: bool, names, lo, hi, integer) -> list:
    """Per run: (index, truth vector, run config, run folder, state new/partial/finished); a
    held run made with another config is an error."""
    plans = []
    for i in range(n):
        theta, tseed = prior_draw(cfg.seed, i, lo, hi, integer)
        truth = {nm: (int(v) if integer[j] else float(v)) for j, (nm, v) in enumerate(zip(names, theta))}
        run_cfg = run_config(cfg, i, truth, tseed)
        run_dir = out_dir / f"run_{i:03d}"
        state = "new" if overwrite else RunStore.state(run_dir)
        if state != "new" and not same_config(run_dir, run_cfg):
            raise ConfigError(
                f"{run_dir}: was made with another config (or another version of this one); "
                "refit the study with --overwrite, or choose another -o"
            )
        plans.append((i, theta, run_cfg, run_dir, state))
    return plans


# Over 80 lines, a third of it the docstring: the run loop keeps the bar, the counts and the rows
# together (set-up and per-run steps are helpers above).
def calibrate(
    config_path, n: int, out_dir=None, resume: bool = False, overwrite: bool = False, progress: bool = False
) -> dict:
    """Simulation-based calibration of the configured sampler (see the module text).

    Parameters
    ----------
    config_path : path
        A run config whose optimiser gives a posterior (``abc-smc``, ``emcee``); its ``[target]``
        is optional and replaced in every run.
    n : int
        Calibration runs (prior draws).
    out_dir : path, optional
        Study folder (default ``runs/calibrate-<config name>``): ``run_000``... and the results.
    resume : bool
        Continue an earlier study in ``out_dir``: finished runs are read back, stopped ones resumed.
    overwrite : bool
        Refit every run of an earlier study in ``out_dir`` (its results are replaced).

    Returns
    -------
    dict
        ``names``, ``units``, ``lower``/``upper`` (prior bounds), ``runs`` (one row per run),
        ``table`` (:func:`coverage_table`), ``table_text``, ``bins``, ``band`` (the uniform
        99 % band of a bin's count), ``counts`` (fitted / resumed / read back), ``wall_seconds``
        (summed fit time of the runs), ``json``/``csv`` paths, ``out_dir``.
    """
    from .progress import progress_bar

    config_path = Path(config_path)
    if int(n) < 1:
        raise ConfigError(f"calibrate: -n must be at least 1 (got {n})")
    if resume and overwrite:
        raise ConfigError("calibrate: --resume and --overwrite exclude each other (continue the study, or refit it)")
    cfg = _read_study_config(config_path)
    _check_sampler(cfg, str(config_path))
    names, lo, hi, integer, units = _study_spec(cfg)
    out_dir = Path(out_dir) if out_dir else Path("runs") / f"calibrate-{config_path.stem}"
    if out_dir.exists() and not out_dir.is_dir():
        raise ConfigError(f"{out_dir}: exists and is not a folder")
    held = _held_runs(out_dir) if out_dir.is_dir() else []
    if held and not (resume or overwrite):
        raise ConfigError(
            f"{out_dir}: already holds a calibration study ({len(held)} runs); continue it with "
            "--resume, refit it with --overwrite, or choose another -o"
        )
    out_dir.mkdir(parents=True, exist_ok=True)
    plans = _plan_runs(cfg, out_dir, int(n), overwrite, names, lo, hi, integer)
    counts = {"fitted": 0, "resumed": 0, "read back": 0, "failed": 0}
    rows = []
    t0 = time.monotonic()
    bar = progress_bar(int(n), "calibrate", "run", progress)
    try:
        for i, theta, run_cfg, run_dir, state in plans:
            bar.set_postfix_str(
                f"run {i + 1}/{n}" + {"finished": " (read back)", "partial": " (resume)"}.get(state, ""), refresh=True
            )
            if state == "finished":
                counts["read back"] += 1
            else:
                try:
                    fit(run_cfg, run_dir, resume=state == "partial", progress=False, overwrite=overwrite)
                except (BayesForestError, ValueError) as exc:
                    # the run configs were validated above, so what fails here depends on the drawn
                    # target (e.g. a data set with too few rows, a model that collapses): the run is
                    # recorded and left out of the coverage; a run folder problem stops the study
                    if isinstance(exc, RunDirError):
                        raise
                    rows.append(
                        {
                            "run": run_dir.name,
                            "status": f"fit failed: {exc}".replace("\n", " ")[:300],
                            "params": {},
                            "truth": dict(zip(names, map(float, theta))),
                        }
                    )
                    counts["failed"] += 1
                    bar.update(1)
                    continue
                counts["resumed" if state == "partial" else "fitted"] += 1
            rows.append(_evaluate_run(run_dir, names, theta, integer, cfg.seed, i))
            bar.update(1)
    finally:
        bar.close()
    for (_, theta, *_), row in zip(plans, rows):
        row.setdefault("truth", {nm: float(v) for nm, v in zip(names, theta)})
    if not any(r["status"] == "ok" for r in rows):
        raise BayesForestError(f"calibrate: no run gave a posterior ({rows[0]['run']}: {rows[0]['status']})")
    table = coverage_table(rows, names, lo, hi, integer)
    ok = [r for r in rows if r["status"] == "ok"]
    bins = rank_bins(len(ok)) if ok else 2
    band = uniform_band(len(ok), bins) if ok else (0.0, 0.0)
    wall = float(sum(r.get("seconds") or 0.0 for r in rows))
    written = config_to_dict(cfg)  # the study's config as its file holds it
    res = {
        "config": str(config_path),
        "optimizer": cfg.optimizer.kind,
        "ssm": cfg.ssm.kind,
        "optimizer_settings": written.get("optimizer"),
        "objective": written.get("objective"),
        "n": int(n),
        "names": list(names),
        "units": units,
        "lower": lo.tolist(),
        "upper": hi.tolist(),
        "levels": list(LEVELS),
        "rank_draws": RANK_DRAWS,
        "bins": bins,
        "band": list(band),
        "table": table,
        "runs": rows,
        "counts": counts,
        "wall_seconds": wall,
        "session_seconds": time.monotonic() - t0,
        "out_dir": out_dir,
    }
    res["table_text"] = table_text(res)
    res["json"] = write_json(
        out_dir / "calibration.json", {k: v for k, v in res.items() if k not in ("json", "csv")}, strict=True
    )
    res["csv"] = _write_csv(out_dir / "calibration.csv", rows, names)
    return res


def table_text(res: dict) -> str:
    """The coverage table as printed at the end of the study."""
    ok = [r for r in res["runs"] if r["status"] == "ok"]
    n_ok = len(ok)
    lines = [
        f"calibration of {res['optimizer']} on {res['ssm']}: {len(res['runs'])} runs, {n_ok} with a "
        f"posterior; central intervals from weighted quantiles, ranks among {res['rank_draws']} "
        f"posterior draws in {res['bins']} bins"
    ]
    if n_ok:
        r50, r90 = coverage_range(n_ok, 50), coverage_range(n_ok, 90)
        lines.append(
            f"a calibrated sampler covers 50 % and 90 %; over {n_ok} runs 95 % of calibrated studies "
            f"fall within {r50[0]:.0f}-{r50[1]:.0f} % and {r90[0]:.0f}-{r90[1]:.0f} %"
        )
    lines.append(
        f"{'parameter':<16}{'unit':<11}{'50 % covers':>16}{'90 % covers':>16}{'rank p':>9}"
        f"{'width50/prior':>15}{'width90/prior':>15}"
    )
    for t, unit in zip(res["table"], res["units"]):
        c50 = f"{100 * t['coverage50']:.1f} % ({t['covered50']}/{t['runs']})" if t["runs"] else "-"
        c90 = f"{100 * t['coverage90']:.1f} % ({t['covered90']}/{t['runs']})" if t["runs"] else "-"
        p = "-" if not math.isfinite(t["rank_p"]) else f"{t['rank_p']:.3f}"
        lines.append(
            f"{t['parameter']:<16}{(unit or '-'):<11}{c50:>16}{c90:>16}{p:>9}{t['width50']:>15.3f}{t['width90']:>15.3f}"
        )
    failed = [r for r in res["runs"] if r["status"] != "ok"]
    if failed:
        lines.append(
            f"{len(failed)} run{'' if len(failed) == 1 else 's'} without a posterior, left out: "
            + "; ".join(f"{r['run']}: {r['status']}" for r in failed[:3])
            + (" ..." if len(failed) > 3 else "")
        )
    secs = [r["seconds"] for r in ok if r.get("seconds")]
    evals = [r["n_evaluations"] for r in ok if r.get("n_evaluations")]
    if secs:
        lines.append(
            f"fit time: {res['wall_seconds']:.0f} s in all, median {np.median(secs):.1f} s and "
            f"{np.median(evals):.0f} evaluations per run"
        )
    return "\n".join(lines)


def _write_csv(path: Path, rows: list[dict], names) -> Path:
    """One row per run: for each parameter the truth, posterior median, interval bounds and
    rank; then the run's evaluations, fit seconds, final epsilon and status."""
    cols = ["truth", "median"] + [f"{b}{lev}" for lev in LEVELS for b in ("lo", "hi")] + ["rank"]
    with path.open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(
            ["run"]
            + [f"{c}_{nm}" for nm in names for c in cols]
            + ["n_evaluations", "seconds", "epsilon", "best_distance", "status"]
        )
        for r in rows:
            vals = []
            for nm in names:
                p = r["params"].get(nm) or {"truth": r.get("truth", {}).get(nm)}
                vals += [
                    "" if p.get(c) is None else (f"{p[c]:.10g}" if isinstance(p[c], float) else p[c]) for c in cols
                ]
            extra = [r.get(k) for k in ("n_evaluations", "seconds", "epsilon", "best_distance")]
            w.writerow(
                [r["run"]]
                + vals
                + ["" if v is None else (f"{v:.6g}" if isinstance(v, float) else v) for v in extra]
                + [r["status"]]
            )
    return path
