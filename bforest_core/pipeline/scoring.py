"""Scoring: a tree's distance to the target, per data set and term, and the objective.

:func:`build_scoring` builds, from a config and the target's tables, everything that scores a
tree: the growth model, and per term of the objective its model-side feature set and its
distance prepared on the term's data sets. The fit's workers hold one (:mod:`.worker`); the
report builds one to recompute a run's numbers. :func:`score_tree` and :func:`combine_terms` use
it; ``_simulate_with_timeout`` grows a tree under the objective's time limit.
"""

from __future__ import annotations

import os
import signal
import socket
import threading
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from ..interfaces import SSM, Distance, FeatureSet
from ..registry import component
from .interrupts import users_stop
from .target import Term, feature_set_for, size_topology, term_specs

if TYPE_CHECKING:
    from ..config import RunConfig


@dataclass
class PreparedTerm:
    """A term of the objective ready to score model trees: its model-side feature set and its
    distance prepared on the term's data sets."""

    term: Term
    features: FeatureSet
    distance: Distance
    U_data: dict[str, np.ndarray]


class _Timeout(Exception):
    pass


#: what a model's simulation or feature extraction may raise besides SimulationFailed: the
#: evaluation is then a failure with status "error", never a crash of the run. A plugin's code
#: may raise anything (AttributeError, its own exception classes, SystemExit from sys.exit(), a
#: KeyboardInterrupt or BaseException of its own); only the user's own stop ends the run
#: (:func:`fault_message` lets it through).
_MODEL_ERRORS = (BaseException,)


def fault_message(exc: BaseException) -> str:
    """The logged message of a plugin's fault ``exc`` (caught as :data:`_MODEL_ERRORS`); the
    user's own stop (Ctrl-C, SIGTERM: :func:`.interrupts.users_stop`) is raised again instead."""
    if users_stop(exc):
        raise exc
    return f"{type(exc).__name__}: {exc}"[:500]


@dataclass
class Scoring:
    """What scores a tree against the target (:func:`build_scoring`): a fit's worker holds one."""

    #: the growth model
    ssm: SSM
    #: every term of the objective, the ``[features]``/``[distance]`` term first
    terms: list[PreparedTerm]
    #: the target's data sets of every term (keys as in ``Target.U``)
    U_data: dict[str, np.ndarray]
    #: ``[objective] penalty``: the distance of a failed simulation
    penalty: float
    #: ``[objective] timeout``: seconds a simulation may take (None: no limit)
    timeout: float | None
    #: ``[target] prune_radius``: the model's trees lose what is thinner, as the QSM did
    prune_radius: float
    #: the branch rule of the size term on the model side and the statistics it measures by it
    #: (:func:`.target.size_topology`): the clones' fidelity statistics are measured so
    size_topology: tuple[str | None, list[str] | None]
    #: the process that scores, ``host:pid`` (logged with each evaluation)
    worker: str

    @property
    def features(self) -> FeatureSet:
        """The model-side feature set of the ``[features]`` term."""
        return self.terms[0].features

    @property
    def distance(self) -> Distance:
        """The distance of the ``[distance]`` term, prepared on its data sets."""
        return self.terms[0].distance


def build_scoring(
    cfg: RunConfig, U_data: dict, columns: dict, feature_settings: dict, terms: list[Term] | None = None
) -> Scoring:
    """What scores a tree against the target, built as the fit's workers build it.

    Parameters
    ----------
    cfg : RunConfig
        The run's validated config.
    U_data, columns : dict
        The target's data tables and their column names (``Target.U``, ``Target.columns``).
    feature_settings : dict
        The data-side feature set's resolved settings (``Target.feature_settings``).
    terms : list of Term, optional
        ``Target.terms``; rebuilt from the config when None (a run written before they were kept).

    Returns
    -------
    Scoring
    """
    from ..config import build_component

    if terms is None:  # rebuilt from the config (a report reading an older or partial run)
        terms = term_specs(cfg)
        terms[0] = replace(terms[0], features=feature_settings)
    built = []
    for spec in terms:
        Ud = spec.own(U_data)
        dist = component("distance", spec.distance_kind, **spec.distance)
        dist.prepare(Ud, spec.own(columns))
        built.append(PreparedTerm(spec, feature_set_for(cfg, "model", spec.features, spec.features_kind), dist, Ud))
    return Scoring(
        ssm=build_component(cfg, "ssm"),
        terms=built,
        U_data=U_data,
        penalty=cfg.objective.penalty,
        timeout=cfg.objective.timeout,
        prune_radius=cfg.target.prune_radius,
        size_topology=size_topology(cfg, "model"),
        worker=f"{socket.gethostname()}:{os.getpid()}",
    )


def score_tree(tree, scoring: Scoring) -> tuple[dict[str, float | None], dict[str, int]]:
    """Distance per data set of every term (keys as in ``Target.U``) and the model's rows per
    set, for one tree (``scoring`` from :func:`build_scoring`)."""
    per_set, n_rows = {}, {}
    for t in scoring.terms:
        U = t.features.extract(tree)
        for k, v in t.distance.compute_per_set(U, t.U_data).items():
            per_set[t.term.prefix + k] = v
        for k, v in U.items():
            n_rows[t.term.prefix + k] = int(v.shape[0])
    return per_set, n_rows


def combine_terms(per_set: dict[str, float | None], scoring: Scoring) -> tuple[float, dict[str, float]]:
    """The objective (weighted mean of the terms) and each term's own value."""
    values, num, den = {}, 0.0, 0.0
    for t in scoring.terms:
        term = t.term
        values[term.name] = float(t.distance.combine(term.own(per_set), term.set_weights))
        num += term.weight * values[term.name]
        den += term.weight
    return num / den, values


def with_term_values(per_set: dict, values: dict[str, float]) -> dict:
    """``per_set`` plus ``term:<name>`` entries when the objective has more than one term."""
    if len(values) < 2:
        return dict(per_set)
    return {**per_set, **{f"term:{k}": v for k, v in values.items()}}


def mean_per_set(per_set_list: list[dict]) -> dict[str, float | None]:
    """The mean of each key (a set, or ``term:<name>``) over several trees' or seed sets' per-set
    distances (keys of the first), skipping those that have none for it (an empty set); None
    where none has a value."""
    out = {}
    for k in per_set_list[0]:
        vals = [p[k] for p in per_set_list if p.get(k) is not None]
        out[k] = float(np.mean(vals)) if vals else None
    return out


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


def grow_tree(cfg: RunConfig, params: dict, seed: int, timeout: float | None = None):
    """The tree the run's model grows from ``params`` and ``seed``, pruned as the target's QSM was:
    the tree a worker scores (a report regrowing a run's answer uses this, not the model itself)."""
    from ..config import build_component

    ssm = build_component(cfg, "ssm")
    return _simulate_with_timeout(ssm, params, seed, timeout, cfg.target.prune_radius)


def _alarm(signum, frame):
    raise _Timeout()


def _simulate_with_timeout(ssm, params, seed, timeout, prune_radius: float = 0.0):
    """The tree ``ssm`` grows from ``params`` and ``seed`` within ``timeout`` seconds, pruned
    at ``prune_radius`` as the target's QSM was (``[target] prune_radius``)."""
    use_alarm = (
        timeout is not None and hasattr(signal, "setitimer") and threading.current_thread() is threading.main_thread()
    )
    if not use_alarm:
        return _checked_tree(ssm, ssm.simulate(params, seed)).pruned(prune_radius)
    old = signal.signal(signal.SIGALRM, _alarm)
    signal.setitimer(signal.ITIMER_REAL, float(timeout))
    try:
        tree = ssm.simulate(params, seed)
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)
    return _checked_tree(ssm, tree).pruned(prune_radius)


def _checked_tree(ssm, tree):
    """What ``simulate`` returned, when it is a :class:`Tree` (a plugin may return None)."""
    from ..tree import Tree

    if not isinstance(tree, Tree):
        raise TypeError(f"ssm '{ssm.name}': simulate returned {type(tree).__name__}, not a Tree")
    return tree
