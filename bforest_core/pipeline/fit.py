"""The fit pipeline (paper stages A1-A2, B1-B4): target -> data sets -> optimiser -> best fit.

Resume: the optimiser is re-run from the start with the same seed; evaluations already in the
run's ``evaluations.sqlite`` are replayed from the log instead of being simulated again, so a
resumed run repeats no simulation, loses nothing and reaches the same result as an
uninterrupted one.
"""

from __future__ import annotations

import contextlib
import json
import math
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..config import (
    RunConfig,
    build_component,
    config_to_dict,
    load_config,
    parse_config,
    read_toml,
    section_settings,
    selection_config,
)
from ..errors import BayesForestError, ConfigError
from ..interfaces import LineDistance, OptimizeResult, Problem, parameter_value
from ..io import jsonable
from ..processes import one_blas_thread
from .checks import preflight
from .heldout import select_answer
from .interrupts import stoppable
from .progress import progress_bar
from .rundir import holding_run_lock
from .scoring import _simulate_with_timeout, _Timeout, set_summaries
from .seeds import model_seeds, spread_seeds
from .store import Evaluation, RunDirError, RunFiles, RunStore, stop_fields
from .target import Target, build_target
from .worker import evaluate_task, started_workers, summary_task


@dataclass
class FitResult:
    """Outcome of :func:`fit`."""

    params: dict[str, float]
    distance: float
    per_set: dict[str, float | None]
    n_evaluations: int
    stop_reason: str
    run_dir: Path
    history: list[dict] = field(default_factory=list)
    diagnostics: dict[str, Any] = field(default_factory=dict)
    already_finished: bool = False  # a --resume of a run that had finished: nothing new was simulated
    #: the search's lowest distance on its own model seeds (what its progress bar ends at)
    best_own: float | None = None
    #: the answer's distance on held-out model seeds, when ``[select]`` chose it (else None)
    heldout_distance: float | None = None
    #: the answer's evaluation index
    evaluation: int | None = None


class Evaluator:
    """``Problem.evaluate`` of a run: replay from the store, cache, executor, stop criteria."""

    def __init__(
        self,
        cfg: RunConfig,
        store: RunStore,
        executor,
        ssm,
        names,
        problem: Problem,
        progress=None,
        failures_as_inf: bool = False,
    ):
        self.cfg = cfg
        self.failures_as_inf = failures_as_inf  # Optimizer.failures_as_inf
        self.store = store
        self.executor = executor
        self.names = names
        self.problem = problem
        self.fixed = {k: parameter_value(v, ssm.parameter_spec(k).integer) for k, v in cfg.ssm.fixed.items()}
        self.integer = problem.integer
        self.replay = store.replay()
        self.cache: dict[tuple, float] = {}
        self.seeds_of: dict[tuple, list[int]] = {}  # point -> model seeds of its first logged evaluation
        self.next_index = 0
        self.t0 = time.monotonic()
        self.elapsed_before = float(store.get_meta("elapsed", 0.0) or 0.0)
        self.progress = progress
        self.stop = cfg.stop
        self.k = cfg.objective.seeds
        self.explicit_seeds = list(cfg.objective.model_seeds) if cfg.objective.model_seeds else None
        self.mode = cfg.objective.seed_mode
        #: why the search stopped, when this layer stopped it (``store.STOP_KINDS``): None while
        #: it runs, and when the optimiser ends on its own rules (``"convergence"``)
        self.stop_kind: str | None = None

    def _params(self, x) -> dict:
        p = dict(self.fixed)
        for name, v, is_int in zip(self.names, x, self.integer):
            p[name] = parameter_value(v, is_int)
        return p

    @staticmethod
    def _point(params) -> tuple:
        return tuple(sorted(params.items()))

    def _key(self, params, seeds):
        return (self._point(params), tuple(seeds))

    def _value(self, distance: float, status: str) -> float:
        """What ``evaluate`` returns for a logged evaluation: its distance, or ``inf`` for a failed
        simulation when the optimiser asks for that (``Optimizer.failures_as_inf``)."""
        return math.inf if self.failures_as_inf and status != "ok" else float(distance)

    def _stop_at_budget(self, pending: int = 0) -> bool:
        """Stop the problem once its evaluations, with ``pending`` more on their way, reach
        ``Problem.max_evaluations`` (``[stop] max_evaluations``): the one place the budget is enforced
        (optimisers read ``Problem.remaining()`` to plan, ``Problem.stopped`` to end)."""
        pr = self.problem
        left = pr.remaining()
        if left is not None and pending >= left:
            pr.stopped, pr.stop_reason = True, f"evaluation budget ({pr.max_evaluations}) reached"
            self.stop_kind = self.stop_kind or "budget"
        return pr.stopped

    def _check_stop(self):
        pr, st = self.problem, self.stop
        if self._stop_at_budget():
            return
        replaying = self.next_index <= max(self.replay, default=-1)  # logged rows still ahead
        if st.wall_time is not None and not replaying and self.elapsed() >= st.wall_time:
            pr.stopped, pr.stop_reason = True, f"wall time ({st.wall_time:g} s) reached"
            self.stop_kind = "wall_time"
        elif st.target_distance is not None and pr.best_f <= st.target_distance:
            pr.stopped, pr.stop_reason = True, f"target distance {st.target_distance:g} reached"
            self.stop_kind = "target"

    def seed_spread(self, x, k: int) -> np.ndarray:
        """``Problem.seed_spread``: the objective at ``x`` under ``k`` sets of fresh model seeds,
        each set as large as an evaluation's (so the spread is that of the objective itself; run
        on the executor; not logged)."""
        params = self._params(np.clip(np.asarray(x, float), self.problem.lower, self.problem.upper))
        per = len(self.explicit_seeds) if self.explicit_seeds else int(self.k)
        seeds = spread_seeds(self.cfg.seed, int(k) * per)
        tasks = [(params, seeds[i * per : (i + 1) * per]) for i in range(int(k))]
        return np.array(
            [self._value(r["distance"], r["status"]) for r in self.executor.map(evaluate_task, tasks)], float
        )

    def summaries(self, X) -> np.ndarray:
        """``Problem.summaries``: the summary statistics of the trees of points this run has
        evaluated, regrown with their logged model seeds on the executor (not logged)."""
        X = np.clip(np.atleast_2d(np.asarray(X, float)), self.problem.lower, self.problem.upper)
        tasks = []
        for x in X:
            params = self._params(x)
            seeds = self.seeds_of.get(self._point(params))
            if seeds is None:
                raise ValueError(f"summaries: the point {params} was not evaluated in this run")
            tasks.append((params, seeds))
        got = list(self.executor.map(summary_task, tasks))
        m = next((len(g) for g in got if g is not None), 0)
        return np.array([np.full(m, np.nan) if g is None else g for g in got], float).reshape(len(X), m)

    def foreign_rows(self) -> list[int]:
        """Logged evaluations the search never came to: rows this run did not make (added to the
        log by hand or by another program), which the answer must not be taken from. Every row
        the search came to was checked against its point and seeds when it was replayed."""
        return sorted(i for i in self.replay if i >= self.next_index)

    def elapsed(self) -> float:
        return self.elapsed_before + time.monotonic() - self.t0

    def _record(self, x, f):
        pr = self.problem
        if f < pr.best_f:
            pr.best_f, pr.best_x = float(f), np.array(x, float)

    def __call__(self, X) -> np.ndarray:
        X = np.atleast_2d(np.asarray(X, dtype=float))
        pr = self.problem
        X = np.clip(X, pr.lower, pr.upper)
        out = np.full(X.shape[0], np.inf)
        todo, pending = [], {}  # new evaluations; key -> rows waiting for the same point
        for r, x in enumerate(X):
            if pr.stopped:
                continue
            params = self._params(x)
            seeds = self.explicit_seeds or model_seeds(self.cfg.seed, self.k, self.mode, self.next_index)
            key = self._key(params, seeds)
            if self.cfg.objective.cache and key in self.cache:
                out[r] = self.cache[key]
                self._record(x, out[r])
                continue
            if self.cfg.objective.cache and key in pending:
                pending[key].append(r)  # identical point twice in one batch: evaluate once
                continue
            if self._stop_at_budget(pending=len(todo)):
                continue
            idx = self.next_index
            self.next_index += 1
            ev = self.replay.get(idx)
            if ev is not None:
                if ev.params != json.loads(json.dumps(params)) or ev.seeds != seeds:
                    raise RunDirError(
                        f"{self.store.path}: evaluation {idx} in the log has other parameters "
                        "than this run asks for (config or code changed?); start a new run"
                    )
                out[r] = self.cache[key] = self._value(ev.distance, ev.status)
                self.seeds_of.setdefault(key[0], seeds)
                pr.n_evaluations += 1
                self._record(x, out[r])
                if self.progress:
                    self.progress(pr, replayed=True)
                continue
            pending[key] = []
            todo.append((r, idx, params, seeds, key))
        if todo:
            tasks = [(t[2], t[3]) for t in todo]
            for j, res in self.executor.map_unordered(evaluate_task, tasks):
                r, idx, params, seeds, key = todo[j]
                ev = Evaluation(
                    idx,
                    params,
                    seeds,
                    res["distance"],
                    res["per_set"],
                    res["status"],
                    res["message"],
                    res["seconds"],
                    res["worker"],
                    res["n_rows"],
                )
                self.store.add(ev)
                out[r] = self.cache[key] = self._value(ev.distance, ev.status)
                self.seeds_of.setdefault(key[0], seeds)
                for r2 in pending[key]:
                    out[r2] = out[r]
                pr.n_evaluations += 1
                self._record(X[r], out[r])
                if self.progress:
                    self.progress(pr, replayed=False)
            self.store.set_meta("elapsed", self.elapsed())
        if not pr.stopped:
            self._check_stop()
        return out


class _Progress:
    """Progress of a fit: evaluations done, best distance, ETA (to the budget when there is one)."""

    def __init__(self, total, enabled=True):
        self.bar = progress_bar(total, "fit", "eval", enabled)

    def __call__(self, pr, replayed):
        self.bar.update(1)
        self.bar.set_postfix_str(f"best={pr.best_f:.4f}" + (" (replay)" if replayed else ""), refresh=False)

    def close(self, reason: str = ""):
        if reason:  # the bar ends with why the fit stopped (budget, the optimiser's own stop, ...)
            self.bar.set_postfix_str(
                f"{getattr(self.bar, 'postfix', '') or ''} stopped: {reason}".strip(), refresh=True
            )
        self.bar.close()


def _expected_total(cfg: RunConfig, optimizer, dim: int) -> int | None:
    """Evaluations the progress bar counts to: the budget, or what the optimiser plans
    (``Optimizer.expected_evaluations``), whichever is smaller."""
    planned = optimizer.expected_evaluations(dim)
    totals = [t for t in (cfg.stop.max_evaluations, planned) if t]
    return min(totals) if totals else None


#: settings a resume may change: when the search stops, where it runs and what it reports (dotted
#: keys of the config, a section for all its keys). Every other setting changes what an evaluation
#: computes (the target, the model, the objective, the seeds, the bounds) or what the answer is
#: chosen by ([select]), or the clones the run's folder already holds ([clones]).
RESUMABLE = ("stop.max_evaluations", "stop.wall_time", "stop.target_distance", "executor", "report")


def _flat(value, key: str = "") -> dict:
    """``{dotted key: value}`` of a config table (lists of tables as ``key[i]``)."""
    if isinstance(value, dict):
        out = {}
        for k, v in value.items():
            out.update(_flat(v, f"{key}.{k}" if key else str(k)))
        return out
    if isinstance(value, list) and value and all(isinstance(v, dict) for v in value):
        out = {f"{key}[#]": len(value)}
        for i, v in enumerate(value):
            out.update(_flat(v, f"{key}[{i}]"))
        return out
    return {key: value}


def config_changes(old: dict, new: dict, allowed=()) -> list[str]:
    """The settings in which two configs (as TOML tables, :func:`config_to_dict`) differ, as
    ``key: old -> new`` (``unset`` for a key one of them leaves out), except those under the
    dotted keys or sections of ``allowed``."""
    a, b = _flat(old), _flat(new)

    def free(key: str) -> bool:
        return any(key == p or key.startswith(p + ".") for p in allowed)

    def show(v) -> str:
        return "unset" if v is None else json.dumps(v)

    keys = sorted({k for k in a.keys() | b.keys() if a.get(k) != b.get(k) and not free(k)})
    return [f"{k}: {show(a.get(k))} -> {show(b.get(k))}" for k in keys]


def same_config(run_dir, cfg: RunConfig) -> bool:
    """Whether the run in ``run_dir`` was made with ``cfg`` (up to the executor and the report,
    which do not change results); False when its config.toml is missing or unreadable."""
    path = RunFiles(run_dir).config_path
    try:
        old = parse_config(read_toml(path), source=str(path))
    except (OSError, BayesForestError):
        return False
    return not config_changes(config_to_dict(old), config_to_dict(cfg), allowed=("executor", "report"))


def _check_resume(store: RunStore, text: str, cfg: RunConfig) -> None:
    """Refuse to resume the run of ``store`` with the config ``text`` (``cfg``) when it changes
    anything but :data:`RESUMABLE`: the logged evaluations and the new ones would answer two
    questions. The run's own config is the one its log was begun with (kept in the log, so an
    edit of ``config.toml`` is seen too; a run written before that: its ``config.toml``)."""
    import tomllib

    own = store.get_meta("config")
    try:
        old = tomllib.loads(own if isinstance(own, str) else store.config_path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise RunDirError(f"{store.config_path}: the run's own config cannot be read ({exc})") from None
    changes = config_changes(old, tomllib.loads(text), allowed=RESUMABLE)
    if changes:
        raise RunDirError(
            f"{store.path}: the config differs from the run's in what an evaluation computes "
            f"({'; '.join(changes)}): the logged evaluations and new ones would not be comparable; "
            f"resume with the run's own settings, or start a new run (another -o, or --overwrite); "
            f"a resume may change only {', '.join(RESUMABLE)}"
        )
    held, budget, own_budget = store.count(), cfg.stop.max_evaluations, old.get("stop", {}).get("max_evaluations")
    if budget is not None and budget < held and (own_budget is None or budget < own_budget):
        raise RunDirError(
            f"{store.path}: stop.max_evaluations = {budget} is below the {held} evaluations the run "
            f"holds; resume with a budget of at least {held} (the answer of a smaller budget is "
            "in the report's convergence table)"
        )


def _free_specs(cfg: RunConfig, ssm):
    names, lo, hi, ilo, ihi, integer = [], [], [], [], [], []
    for name, fp in cfg.ssm.free.items():
        if fp.scaled_by is not None:
            raise ConfigError(
                f"ssm.free.{name}: bounds scaled by the target's {fp.scaled_by} are resolved by a fit "
                "against its target; give absolute bounds here"
            )
        spec = ssm.parameter_spec(name)
        names.append(name)
        lo.append(fp.lower)
        hi.append(fp.upper)
        ilo.append(fp.lower if fp.init_lower is None else fp.init_lower)
        ihi.append(fp.upper if fp.init_upper is None else fp.init_upper)
        integer.append(spec.integer if fp.integer is None else fp.integer)
    if not names:
        raise ConfigError("ssm.free: no free parameters to fit (add e.g. free.NAME = { lower = ..., upper = ... })")
    return names, np.array(lo), np.array(hi), np.array(ilo), np.array(ihi), np.array(integer, bool)


@stoppable
@holding_run_lock
def fit(
    cfg: RunConfig | str | Path,
    run_dir,
    resume: bool = False,
    progress: bool = True,
    overwrite: bool = False,
    target=None,
) -> FitResult:
    """Fit the SSM of ``cfg`` to its target; everything is written to ``run_dir``.

    Parameters
    ----------
    cfg : RunConfig or path
        A validated config (:func:`load_config`) or the path of a TOML file.
    run_dir : path
        The run directory (created; with ``resume`` an existing one is continued).
    resume : bool
        Continue a run that was stopped or killed.
    """
    import tomli_w

    if not isinstance(cfg, RunConfig):
        cfg = load_config(cfg)
    run_dir = Path(run_dir)
    checked = preflight(cfg, target)  # every check before the run directory is touched
    for note in checked.notes:  # a bound scaled to the target moved into the model's range
        warnings.warn(note.message, note.category, stacklevel=3)
    tgt, cfg = checked.target, checked.cfg  # the run's config.toml holds the resolved bounds
    text = tomli_w.dumps(config_to_dict(cfg))
    store = RunStore.open(run_dir) if resume else RunStore.create(run_dir, text, overwrite=overwrite)
    with store:
        if resume:
            _check_resume(store, text, cfg)
            finished = store.finished()  # resuming it replays the log, simulates nothing new unless extended
            # the executor and the budget may change between sessions (results never depend on them)
            store.config_path.write_text(text, encoding="utf-8")
            store.set_meta("config", text)
            store.clear_log()
        else:
            finished = False
        held = store.count()
        _save_target(store, tgt, cfg, checked.components["distance"])
        ssm = build_component(cfg, "ssm")
        names, lo, hi, ilo, ihi, integer = _free_specs(cfg, ssm)
        optimizer, executor = checked.components["optimizer"], checked.components["executor"]
        problem = Problem(
            names=names,
            lower=lo,
            upper=hi,
            integer=integer,
            evaluate=None,
            init_lower=ilo,
            init_upper=ihi,
            seed=int(cfg.seed),
            max_evaluations=cfg.stop.max_evaluations,
            log=store.log,
        )
        bar = _Progress(_expected_total(cfg, optimizer, len(names)), enabled=progress)
        evaluator = Evaluator(
            cfg, store, executor, ssm, names, problem, progress=bar, failures_as_inf=bool(optimizer.failures_as_inf)
        )
        problem.evaluate = evaluator
        problem.seed_spread = evaluator.seed_spread
        problem.summaries = evaluator.summaries
        problem.target_summaries = set_summaries(tgt.U, list(tgt.U), trees=len(tgt.trees))
        problem.start = _start(cfg, store, tgt, names, lo, hi)
        result = selection = None
        scfg = selection_config(cfg)  # the candidates' scoring: the search's own unless [select] names tables
        try:
            with started_workers(cfg, tgt, executor):
                try:
                    with one_blas_thread():  # the same answer on any number of cores
                        result = optimizer.minimize(problem)
                finally:  # the search's bar ends before the re-scoring's starts
                    bar.close(problem.stop_reason or getattr(result, "stop_reason", "") or "")
                foreign = evaluator.foreign_rows()
                if foreign:
                    raise RunDirError(
                        f"{store.evaluations_path}: evaluation{'s' * (len(foreign) > 1)} "
                        f"{', '.join(map(str, foreign[:10]))}{' ...' if len(foreign) > 10 else ''} "
                        f"of the log {'are' if len(foreign) > 1 else 'is'} not this run's: its search "
                        f"ended at evaluation {evaluator.next_index - 1} (rows added by hand or by "
                        "another program?); the answer is never taken from them: restore the log, or "
                        "start the run anew with --overwrite"
                    )
                if store.count() and scfg is cfg:
                    selection = select_answer(
                        cfg, store, lambda: contextlib.nullcontext(executor), progress, tgt.trees[0]
                    )
            if store.count() and scfg is not cfg:  # the workers start again on the selection's tables
                selection = select_answer(
                    cfg,
                    store,
                    lambda: started_workers(scfg, build_target(scfg, tgt.trees), executor),
                    progress,
                    tgt.trees[0],
                )
        finally:
            store.set_meta("elapsed", evaluator.elapsed())
        stop_reason = problem.stop_reason or result.stop_reason or "optimiser finished"
        stop_kind = evaluator.stop_kind or "convergence"
        if store.count() == 0:
            raise BayesForestError(f"{run_dir}: the optimiser evaluated nothing ({stop_reason})")
        out = finish_fit(
            cfg,
            store,
            tgt,
            stop_reason,
            evaluator.elapsed(),
            result,
            ssm,
            selection,
            posterior_kind=getattr(optimizer, "posterior_kind", None),
            stop_kind=stop_kind,
        )
        return FitResult(
            params=out["params"],
            distance=out["distance"],
            per_set=out["per_set"],
            n_evaluations=store.count(),
            stop_reason=stop_reason,
            run_dir=run_dir,
            history=store.log_records(),
            diagnostics=result.diagnostics,
            already_finished=finished and store.count() == held,
            best_own=store.best().distance,
            heldout_distance=out.get("heldout_distance"),
            evaluation=out["evaluation"],
        )


def _start(cfg: RunConfig, store: RunStore, tgt: Target, names, lo, hi) -> np.ndarray | None:
    """``Problem.start``: the ``[start] estimator``'s posterior draws for the target, drawn once and
    kept in the run's store, so a resumed fit starts from the same points on any machine."""
    if cfg.start.estimator is None:
        return None
    kept = store.get_meta("start_points")
    if kept is not None:
        return np.asarray(kept, float).reshape(-1, len(names))
    from .amortised import start_points

    X = start_points(cfg, tgt.trees[0], names, lo, hi)
    store.set_meta("start_points", X.tolist())
    return X


def _save_target(store: RunStore, tgt: Target, cfg: RunConfig, dist) -> None:
    """The data tables, and the distance's (``dist``, the ``[distance]`` section's) frozen
    data-side transforms and directions, so every number of the run can be recomputed from the
    run directory."""
    np.savez_compressed(store.target_sets_path, **tgt.U)
    own = {k: v for k, v in tgt.U.items() if "/" not in k}  # the [distance] term's sets
    cols = {k: v for k, v in tgt.columns.items() if "/" not in k}
    dist.prepare(own, cols)
    frozen = {"distance": cfg.distance.kind, "settings": section_settings(cfg, "distance"), "columns": cols}
    lines = isinstance(dist, LineDistance)  # a sliced distance: its transforms and directions are kept
    norms = dist.normalizations() if lines else {}
    if norms:  # a distance that compares the tables in their own units has none
        frozen["normalization"] = norms
    store.write_json(store.DISTANCE, frozen)
    if lines:
        dims = sorted({u.shape[1] for u in own.values() if u.ndim == 2})
        np.savez_compressed(store.directions_path, **{f"d{d}": dist.directions(d) for d in dims})
    try:
        from ..io import write_tree

        write_tree(tgt.trees[0], store.target_tree_path)
    except Exception:  # writing a copy of the target is a convenience, never fatal
        pass


def finish_fit(
    cfg: RunConfig,
    store: RunStore,
    tgt: Target,
    stop_reason: str,
    seconds: float,
    result,
    ssm,
    selection: dict | None = None,
    posterior_kind: str | None = None,
    stop_kind: str = "convergence",
) -> dict:
    """Write ``best.json`` (the answer: the best logged evaluation, or the candidate chosen on
    held-out seeds when there is a ``selection``; classical metrics of target and answer tree)
    and ``best_tree.txt`` (the answer regrown with its first model seed). A sampler's posterior
    goes to ``posterior.csv``/``posterior.nc``, its ``posterior_kind`` to ``best.json``."""
    from ..io import write_tree
    from ..metrics import classical_metrics, relative_errors

    ev = store.evaluation(selection["chosen"]) if selection else store.best()
    target_metrics = classical_metrics(tgt.trees[0])
    best = {
        "params": ev.params,
        "distance": ev.distance,
        "per_set": ev.per_set,
        "status": ev.status,
        "evaluation": ev.idx,
        "seeds": ev.seeds,
        "stop_reason": stop_reason,
        **stop_fields(stop_kind, store, selection),
        "n_evaluations": store.count(),
        "seconds": seconds,
        "target_metrics": target_metrics,
        "optimizer": cfg.optimizer.kind,
        "diagnostics": jsonable(store.write_diagnostics(getattr(result, "diagnostics", {}) or {}), loose=True),
    }
    if selection:
        best["heldout_distance"] = next(c["heldout"] for c in selection["candidates"] if c["evaluation"] == ev.idx)
        best["selection"] = selection
    from .posterior import posterior_outputs

    post = result.posterior(list(ev.params), posterior_kind) if isinstance(result, OptimizeResult) else None
    if post is not None:
        names, lo, hi, _, _, integer = _free_specs(cfg, ssm)
        best["posterior_kind"] = post.kind
        best["posterior_summary"] = posterior_outputs(
            store.path,
            post,
            prior_box={n: (float(a), float(b), bool(i)) for n, a, b, i in zip(names, lo, hi, integer)},
            observed=tgt.U,
            columns=tgt.columns,
            attrs={"optimizer": cfg.optimizer.kind, "ssm": cfg.ssm.kind},
            seed=int(cfg.seed),
        )
        best["posterior_files"] = [store.POSTERIOR_CSV, store.POSTERIOR_NC]
    if ev.status != "ok":
        best["model_metrics"] = None
        best["note"] = f"no evaluation succeeded (best status: {ev.status})"
        store.write_json(store.BEST, best)
        return best
    try:
        tree = _simulate_with_timeout(ssm, ev.params, ev.seeds[0], cfg.objective.timeout, cfg.target.prune_radius)
        m = classical_metrics(tree)
        best["model_metrics"] = m
        best["relative_errors"] = relative_errors(target_metrics, m)
        write_tree(tree, store.best_tree_path)
    except (BayesForestError, _Timeout) as exc:
        best["model_metrics"] = None
        best["note"] = f"best tree could not be regrown or written: {exc or 'timeout'}"
    store.write_json(store.BEST, best)
    return best
