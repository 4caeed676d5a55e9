"""The worker side of a run: each worker's scoring context and the tasks it runs.

The executor starts each worker with :func:`init_worker` as initializer (:func:`started_workers`):
the worker builds its scoring context (:func:`~.scoring.build_scoring`) once, so the target is
loaded once per worker, never per evaluation. :func:`evaluate_task`, :func:`heldout_task` and
:func:`summary_task` run in an initialised worker; a task whose worker dies or is stopped becomes a failed evaluation
(:func:`_lost_task`, the executor's ``on_lost``).
"""

from __future__ import annotations

import functools
import time
from typing import TYPE_CHECKING

import numpy as np

from ..attributes import fidelity_statistics
from ..errors import SimulationFailed
from .fidelity import finite_means
from .scoring import (
    _MODEL_ERRORS,
    Scoring,
    _simulate_with_timeout,
    _Timeout,
    build_scoring,
    combine_terms,
    fault_message,
    mean_per_set,
    score_tree,
    set_summaries,
    with_term_values,
)
from .target import Target, Term

if TYPE_CHECKING:
    from ..config import RunConfig

#: this worker's scoring context (:func:`~.scoring.build_scoring`), set by :func:`init_worker`
_SCORING: Scoring | None = None


def init_worker(
    cfg: RunConfig, U_data: dict, columns: dict, feature_settings: dict, terms: list[Term] | None = None
) -> None:
    """Executor initializer: build the components of every term once in this process and
    prepare each distance on its data sets (``cfg`` arrives as the validated object)."""
    global _SCORING
    _SCORING = build_scoring(cfg, U_data, columns, feature_settings, terms)


def worker_context() -> Scoring:
    """This worker's scoring context; RuntimeError when :func:`init_worker` has not run here."""
    if _SCORING is None:
        raise RuntimeError("worker not initialised (init_worker was not run)")
    return _SCORING


def summary_task(task: tuple[dict, list[int]]) -> np.ndarray | None:
    """The summary statistics (:func:`~.scoring.set_summaries`) of one parameter vector's trees,
    averaged over its model seeds, in an initialised worker; None when a simulation or its data
    sets fail, as :func:`evaluate_task` counts them."""
    params, seeds = task
    c = worker_context()
    rows = []
    for seed in seeds:
        try:
            tree = _simulate_with_timeout(c.ssm, params, seed, c.timeout, c.prune_radius)
            U = {}
            for t in c.terms:
                U.update({t.term.prefix + k: v for k, v in t.features.extract(tree).items()})
        except (SimulationFailed, _Timeout):
            return None
        except _MODEL_ERRORS as exc:
            fault_message(exc)  # the user's stop goes on; a plugin's fault is a tree that failed
            return None
        rows.append(set_summaries(U, list(c.U_data)))
    return np.mean(rows, axis=0)


def started_workers(cfg: RunConfig, tgt: Target, executor=None):
    """The run's executor (or ``executor``) started with :func:`init_worker` on the target, as a
    context manager: the target's tables travel to each worker once."""
    from ..config import build_component

    ex = build_component(cfg, "executor") if executor is None else executor
    # Executor.on_lost/time_limit: what a dead or stuck worker's task becomes, and when a task is
    # stuck (honoured by an executor that can stop a worker, ignored by the others)
    ex.on_lost = functools.partial(_lost_task, cfg.objective.penalty, list(tgt.U), cfg.objective.timeout)
    timeout = cfg.objective.timeout
    ex.time_limit = None if timeout is None else functools.partial(_task_limit, timeout)
    return ex.started(init_worker, (cfg, tgt.U, tgt.columns, tgt.feature_settings, tgt.terms))


def _task_limit(timeout: float, item) -> float:
    """Seconds a task of ``item`` may run before the process executor stops its worker: each
    of its simulations' ``[objective] timeout`` (the worker's own alarm stops one that runs
    Python code; this stops one stuck in C) plus a margin for scoring."""
    seeds = item[1] if isinstance(item, tuple) and len(item) in (2, 3) and isinstance(item[1], (list, tuple)) else (0,)
    return max(1, len(seeds)) * float(timeout) + max(2.0, float(timeout))


def _lost_task(penalty: float, names: list, timeout: float | None, fn, item, status: str, message: str):
    """The result of a task whose worker died or was stopped (the process executor's
    ``on_lost``): a failed evaluation with the penalty, no summaries, or the task's own
    ``lost_result``; ``NotImplemented`` (the executor raises) for any other task. A task stopped
    at its time limit ran that long (its ``seconds``); a dead worker's time is not known (0)."""
    if fn is evaluate_task or fn is heldout_task:
        seconds = _task_limit(timeout, item) if status == "timeout" and timeout is not None else 0.0
        return _failed(float(penalty), names, status, message[:500], seconds, "")
    if fn is summary_task:
        return None
    hook = getattr(fn, "lost_result", None)
    return NotImplemented if hook is None else hook(item, status, message)


def evaluate_task(task: tuple[dict, list[int]]) -> dict:
    """Score one parameter vector with K seeds in this worker. Never raises: failures come
    back with a status and the penalty distance."""
    params, seeds = task
    return _evaluate(params, seeds, ())


def heldout_task(task: tuple[dict, list[int], tuple[str, ...]]) -> dict:
    """:func:`evaluate_task` on held-out seeds, also measuring the grown trees: ``sizes``, the
    mean over the seeds of each named statistic as the clones' fidelity table measures it
    (:func:`~bforest_core.attributes.fidelity_statistics`; a failed task has none). What
    ``[select] sizes`` holds the candidates to."""
    params, seeds, names = task
    return _evaluate(params, seeds, tuple(names))


def _evaluate(params: dict, seeds, measure: tuple[str, ...]) -> dict:
    """Grow and score the trees of ``seeds`` (and measure ``measure`` on each)."""
    c = worker_context()
    t0 = time.perf_counter()
    per_seed, n_rows, sizes = [], {}, []
    status, message = "ok", ""
    for seed in seeds:
        try:
            tree = _simulate_with_timeout(c.ssm, params, seed, c.timeout, c.prune_radius)
            ps, rows = score_tree(tree, c)
            per_seed.append(ps)
            for k, v in rows.items():
                n_rows[k] = n_rows.get(k, 0) + v
            if measure:
                sizes.append(fidelity_statistics(tree, *c.size_topology))
        except SimulationFailed as exc:
            status, message = exc.status, str(exc)
            break
        except _Timeout:
            status, message = "timeout", f"simulation exceeded {c.timeout} s"
            break
        except _MODEL_ERRORS as exc:
            status, message = "error", fault_message(exc)
            break
    seconds = time.perf_counter() - t0
    if status != "ok":
        return _failed(float(c.penalty), list(c.U_data), status, message, seconds, c.worker)
    per_set = mean_per_set(per_seed)
    total, values = combine_terms(per_set, c)
    out = dict(
        distance=float(total),
        per_set=with_term_values(per_set, values),
        status="ok",
        message="",
        seconds=seconds,
        worker=c.worker,
        n_rows={k: v // len(seeds) for k, v in n_rows.items()},
    )
    if measure:
        out["sizes"] = finite_means(sizes, measure)
    return out


def _failed(penalty: float, names: list, status: str, message: str, seconds: float, worker: str) -> dict:
    """A failed evaluation: the penalty, no distances per set."""
    return dict(
        distance=penalty,
        per_set={k: None for k in names},
        status=status,
        message=message,
        seconds=seconds,
        worker=worker,
        n_rows={},
    )
