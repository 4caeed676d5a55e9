"""The objective: params -> simulate -> data sets -> weighted distance.

Set-up happens once per run in the main process (:func:`build_target`) and once per worker
(:func:`init_worker`, the executor's initializer): the worker builds the SSM, feature sets and
the distance from the resolved config and prepares the distance on the data tables it receives,
so the target is loaded once per worker, never per evaluation.

Seeds: with ``seed_mode = "fixed"`` (the paper: the SSM seed is held fixed while optimising)
every evaluation uses the same K model seeds; with ``"per_evaluation"`` they come from the run
seed and the evaluation index. Either way they derive from :class:`numpy.random.SeedSequence`,
never from worker state, so results do not depend on the executor or the number of workers.
"""
from __future__ import annotations

import functools
import os
import signal
import socket
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import SimulationFailed
from ..registry import component


# ---------------------------------------------------------------------------------- seeds
def _seed_stream(key: list[int], k: int) -> list[int]:
    """``k`` independent 32-bit seeds of the stream ``key`` (a run seed and the stream's tag)."""
    return [int(s.generate_state(1, np.uint32)[0]) for s in np.random.SeedSequence(key).spawn(k)]


def model_seeds(run_seed: int, k: int, mode: str = "fixed", index: int = 0) -> list[int]:
    """The K model seeds of one evaluation."""
    return _seed_stream([int(run_seed), 1] if mode == "fixed" else [int(run_seed), 2, int(index)], k)


def spread_seeds(run_seed: int, k: int) -> list[int]:
    """Model seeds for measuring the objective's seed noise (distinct from fitting and clone seeds)."""
    return _seed_stream([int(run_seed), 4], k)


def heldout_seeds(run_seed: int, sets: int, per: int) -> list[list[int]]:
    """``sets`` sets of ``per`` model seeds that no fit, noise measurement or clone of this run
    seed uses: for scoring best points on trees the fits never saw (``bforest compare --heldout``)."""
    flat = _seed_stream([int(run_seed), 5], sets * per)
    return [flat[i * per:(i + 1) * per] for i in range(sets)]


def clone_seeds(run_seed: int, n: int, base: int | None = None) -> list[int]:
    """Fresh seeds for clones (distinct from the fitting seeds)."""
    return _seed_stream([int(run_seed if base is None else base), 3], n)


# ---------------------------------------------------------------------------------- target
#: name of the [features]/[distance] term when the objective has more than one
STRUCTURE = "structure"


def feature_set_for(cfg, side: str, settings: dict | None = None, kind: str | None = None):
    """The feature set of one side (``"target"`` or ``"model"``), honouring per-side topology.

    ``settings`` defaults to the ``[features]`` section; the model side passes the data side's
    resolved settings so it extracts exactly the same sets. ``kind`` defaults to
    ``[features] kind`` (other terms name their own).
    """
    from ..config import section_settings
    settings = dict(section_settings(cfg, "features") if settings is None else settings)
    rule = cfg.target.topology if side == "target" else getattr(cfg.ssm, "topology", None)
    if rule is not None and "topology" in settings:
        settings["topology"] = rule
    return component("features", kind or cfg.features.kind, **settings)


def term_specs(cfg) -> list[dict]:
    """The terms of the objective: the ``[features]``/``[distance]`` term first (prefix ``""``,
    so a one-term run stores its sets under their own names), then ``[[objective.terms]]``
    (prefix ``"<name>/"``). Each: name, prefix, weight, set weights, features and distance
    kinds and settings."""
    from ..config import section_settings
    o = cfg.objective
    specs = [dict(name=STRUCTURE, prefix="", weight=float(o.structure_weight), set_weights=o.weights,
                  features_kind=cfg.features.kind, features=section_settings(cfg, "features"),
                  distance_kind=cfg.distance.kind, distance=section_settings(cfg, "distance"))]
    for t in o.terms:
        specs.append(dict(name=t.name, prefix=f"{t.name}/", weight=float(t.weight), set_weights=t.weights,
                          features_kind=t.features["kind"],
                          features={k: v for k, v in t.features.items() if k != "kind"},
                          distance_kind=t.distance["kind"],
                          distance={k: v for k, v in t.distance.items() if k != "kind"}))
    return specs


def load_target_trees(cfg) -> list:
    """The data tree(s) of the run: read from the QSM file or grown by the named SSM."""
    from ..io import read_qsm
    t = cfg.target
    if t.generate is not None:
        ssm = component("ssm", t.generate.ssm, **t.generate.settings)
        return [ssm.simulate(dict(t.generate.params), int(t.generate.seed))]
    opts = {}
    if t.select is not None:
        opts["select"] = t.select
    trees = read_qsm(t.qsm, reader=t.reader, **opts)
    return list(trees) if isinstance(trees, (list, tuple)) else [trees]


@dataclass
class Target:
    trees: list
    U: dict[str, np.ndarray]         # every term's data sets (other terms' as "<term>/<set>")
    columns: dict[str, list[str]]
    feature_settings: dict          # the data-side feature set after prepare (resolved sets)
    terms: list[dict] | None = None  # term_specs with each term's resolved feature settings


def build_target(cfg, trees=None) -> Target:
    trees = load_target_trees(cfg) if trees is None else trees
    U, cols, terms = {}, {}, []
    for spec in term_specs(cfg):
        fs = feature_set_for(cfg, "target", spec["features"], spec["features_kind"])
        fs.prepare(trees)
        Ut = fs.extract_pooled(trees)
        for k in fs.set_names:
            U[spec["prefix"] + k] = Ut[k]
            cols[spec["prefix"] + k] = fs.columns(k)
        terms.append({**spec, "features": fs.resolved_settings()})
    return Target(trees, U, cols, terms[0]["features"], terms)


# ---------------------------------------------------------------------------------- worker side
_CTX: dict[str, Any] = {}


class _Timeout(Exception):
    pass


#: what a model's simulation or feature extraction may raise besides SimulationFailed: the
#: evaluation is then a failure with status "error", never a crash of the run. A plugin's code
#: may raise anything (AttributeError, its own exception classes, even SystemExit from sys.exit()).
_MODEL_ERRORS = (Exception, SystemExit)


def init_worker(cfg_dict: dict, U_data: dict, columns: dict, feature_settings: dict,
                terms: list[dict] | None = None) -> None:
    """Executor initializer: build the components of every term once in this process and
    prepare each distance on its data sets."""
    from ..config import parse_config, ssm_settings
    cfg = parse_config(cfg_dict)
    if terms is None:  # rebuilt from the config (a report reading an older or partial run)
        terms = term_specs(cfg)
        terms[0]["features"] = feature_settings
    built = []
    for spec in terms:
        pre = spec["prefix"]
        Ud = {k[len(pre):]: v for k, v in U_data.items() if k.startswith(pre) and (pre or "/" not in k)}
        cd = {k[len(pre):]: v for k, v in columns.items() if k.startswith(pre) and (pre or "/" not in k)}
        dist = component("distance", spec["distance_kind"], **spec["distance"])
        dist.prepare(Ud, cd)
        built.append(dict(name=spec["name"], prefix=pre, weight=spec["weight"], set_weights=spec["set_weights"],
                          features=feature_set_for(cfg, "model", spec["features"], spec["features_kind"]),
                          distance=dist, U_data=Ud))
    _CTX.clear()
    _CTX.update(
        ssm=component("ssm", cfg.ssm.kind, **ssm_settings(cfg)),
        features=built[0]["features"], distance=built[0]["distance"], terms=built,
        U_data=U_data, weights=cfg.objective.weights, penalty=cfg.objective.penalty,
        timeout=cfg.objective.timeout, worker=f"{socket.gethostname()}:{os.getpid()}")


def score_tree(tree) -> tuple[dict[str, float | None], dict[str, int]]:
    """Distance per data set of every term (keys as in ``Target.U``) and the model's rows per
    set, for one tree, in an initialised worker."""
    per_set, n_rows = {}, {}
    for t in _CTX["terms"]:
        U = t["features"].extract(tree)
        for k, v in t["distance"].compute_per_set(U, t["U_data"]).items():
            per_set[t["prefix"] + k] = v
        for k, v in U.items():
            n_rows[t["prefix"] + k] = int(v.shape[0])
    return per_set, n_rows


def set_summaries(U: dict[str, np.ndarray], names, trees: int = 1) -> np.ndarray:
    """Summary statistics of data sets ``U`` (keys as in ``Target.U``) pooled over ``trees`` trees,
    in the order of ``names``: per set the log of one plus its rows per tree, then its columns'
    means (0 for an empty set). What a regression adjustment regresses the parameters on
    (``Problem.summaries``)."""
    out = []
    for k in names:
        v = np.asarray(U[k], float)
        if v.ndim != 2:  # a set of one column, or nothing
            v = v.reshape(-1, 1)
        out.append(np.log1p(v.shape[0] / max(int(trees), 1)))
        out.extend(v.mean(axis=0) if v.shape[0] else np.zeros(v.shape[1]))
    return np.asarray(out, float)


def summary_task(task: tuple[dict, list[int]]) -> np.ndarray | None:
    """The summary statistics (:func:`set_summaries`) of one parameter vector's trees, averaged
    over its model seeds, in an initialised worker; None when a simulation or its data sets fail,
    as :func:`evaluate_task` counts them."""
    params, seeds = task
    c = _CTX
    if not c:
        raise RuntimeError("worker not initialised (init_worker was not run)")
    rows = []
    for seed in seeds:
        try:
            tree = _simulate_with_timeout(c["ssm"], params, seed, c["timeout"])
            U = {}
            for t in c["terms"]:
                U.update({t["prefix"] + k: v for k, v in t["features"].extract(tree).items()})
        except (SimulationFailed, _Timeout, *_MODEL_ERRORS):
            return None
        rows.append(set_summaries(U, list(c["U_data"])))
    return np.mean(rows, axis=0)


def combine_terms(per_set: dict[str, float | None]) -> tuple[float, dict[str, float]]:
    """The objective (weighted mean of the terms) and each term's own value."""
    terms = _CTX["terms"]
    values, num, den = {}, 0.0, 0.0
    for t in terms:
        pre = t["prefix"]
        mine = {k[len(pre):]: v for k, v in per_set.items() if k.startswith(pre) and (pre or "/" not in k)}
        values[t["name"]] = float(t["distance"].combine(mine, t["set_weights"]))
        num += t["weight"] * values[t["name"]]
        den += t["weight"]
    return num / den, values


def with_term_values(per_set: dict, values: dict[str, float]) -> dict:
    """``per_set`` plus ``term:<name>`` entries when the objective has more than one term."""
    if len(values) < 2:
        return dict(per_set)
    return {**per_set, **{f"term:{k}": v for k, v in values.items()}}


def run_executor(cfg):
    """The executor of the run's ``[executor]`` section."""
    from ..config import section_settings
    return component("executor", cfg.executor.kind, **section_settings(cfg, "executor"))


def started_workers(cfg, tgt: Target, executor=None):
    """The run's executor (or ``executor``) started with :func:`init_worker` on the target, as a
    context manager: the target's tables travel to each worker once."""
    from ..config import config_to_dict
    ex = run_executor(cfg) if executor is None else executor
    # Executor.on_lost/time_limit: what a dead or stuck worker's task becomes, and when a task is
    # stuck (honoured by an executor that can stop a worker, ignored by the others)
    ex.on_lost = functools.partial(_lost_task, cfg.objective.penalty, list(tgt.U))
    timeout = cfg.objective.timeout
    ex.time_limit = None if timeout is None else functools.partial(_task_limit, timeout)
    return ex.started(init_worker, (config_to_dict(cfg), tgt.U, tgt.columns, tgt.feature_settings, tgt.terms))


class _NoBar:
    def update(self, n=1):
        pass

    def set_postfix_str(self, s, refresh=True):
        pass

    def close(self):
        pass


def progress_bar(total, desc: str, unit: str, enabled: bool = True):
    """A tqdm progress bar, or a silent stand-in when ``enabled`` is false."""
    if not enabled:
        return _NoBar()
    from tqdm.auto import tqdm
    return tqdm(total=total, unit=unit, desc=desc, dynamic_ncols=True)


def _alarm(signum, frame):
    raise _Timeout()


def _simulate_with_timeout(ssm, params, seed, timeout):
    use_alarm = (timeout is not None and hasattr(signal, "setitimer")
                 and threading.current_thread() is threading.main_thread())
    if not use_alarm:
        return _checked_tree(ssm, ssm.simulate(params, seed))
    old = signal.signal(signal.SIGALRM, _alarm)
    signal.setitimer(signal.ITIMER_REAL, float(timeout))
    try:
        tree = ssm.simulate(params, seed)
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)
    return _checked_tree(ssm, tree)


def _checked_tree(ssm, tree):
    """What ``simulate`` returned, when it is a :class:`Tree` (a plugin may return None)."""
    from ..tree import Tree
    if not isinstance(tree, Tree):
        raise TypeError(f"ssm '{getattr(ssm, 'name', '?')}': simulate returned {type(tree).__name__}, not a Tree")
    return tree


def _task_limit(timeout: float, item) -> float:
    """Seconds a task of ``item`` may run before the process executor stops its worker: each
    of its simulations' ``[objective] timeout`` (the worker's own alarm stops one that runs
    Python code; this stops one stuck in C) plus a margin for scoring."""
    seeds = item[1] if isinstance(item, tuple) and len(item) == 2 and isinstance(item[1], (list, tuple)) else (0,)
    return max(1, len(seeds)) * float(timeout) + max(2.0, float(timeout))


def _lost_task(penalty: float, names: list, fn, item, status: str, message: str):
    """The result of a task whose worker died or was stopped (the process executor's
    ``on_lost``): a failed evaluation with the penalty, no summaries, or the task's own
    ``lost_result``; ``NotImplemented`` (the executor raises) for any other task."""
    if fn is evaluate_task:
        return dict(distance=float(penalty), per_set={k: None for k in names}, status=status, message=message[:500],
                    seconds=0.0, worker="", n_rows={})
    if fn is summary_task:
        return None
    hook = getattr(fn, "lost_result", None)
    return NotImplemented if hook is None else hook(item, status, message)


def evaluate_task(task: tuple[dict, list[int]]) -> dict:
    """Score one parameter vector with K seeds in this worker. Never raises: failures come
    back with a status and the penalty distance."""
    params, seeds = task
    c = _CTX
    if not c:
        raise RuntimeError("worker not initialised (init_worker was not run)")
    t0 = time.perf_counter()
    per_seed, n_rows = [], {}
    status, message = "ok", ""
    for seed in seeds:
        try:
            tree = _simulate_with_timeout(c["ssm"], params, seed, c["timeout"])
            ps, rows = score_tree(tree)
            per_seed.append(ps)
            for k, v in rows.items():
                n_rows[k] = n_rows.get(k, 0) + v
        except SimulationFailed as exc:
            status, message = exc.status, str(exc)
            break
        except _Timeout:
            status, message = "timeout", f"simulation exceeded {c['timeout']} s"
            break
        except _MODEL_ERRORS as exc:
            status = "error"
            message = f"{type(exc).__name__}: {exc}"[:500]
            break
    seconds = time.perf_counter() - t0
    if status != "ok":
        names = list(c["U_data"])
        return dict(distance=float(c["penalty"]), per_set={k: None for k in names}, status=status,
                    message=message, seconds=seconds, worker=c["worker"], n_rows={})
    per_set = {}
    for k in per_seed[0]:
        vals = [p[k] for p in per_seed if p[k] is not None]
        per_set[k] = float(np.mean(vals)) if vals else None
    total, values = combine_terms(per_set)
    return dict(distance=float(total), per_set=with_term_values(per_set, values), status="ok", message="", seconds=seconds,
                worker=c["worker"], n_rows={k: v // len(seeds) for k, v in n_rows.items()})
