"""Every check a fit makes before its first evaluation, in one place.

:func:`preflight` is what ``fit`` runs before it touches the run directory and what
``bforest config check`` runs, so a config that passes the check is one the fit accepts. The
static checks (keys, kinds, values, the SSM's parameters) are :func:`bforest_core.load_config`'s;
these need the installed components and the data: the files the config names, the target read or
grown and its data sets resolved, the weights naming those sets. Every problem is reported at
once, in one :class:`ConfigError`.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from ..config import build_component, check_ssm_parameters, did_you_mean, selection_config
from ..errors import BayesForestError, ConfigError, PluginError
from ..samples import SampleError
from ..samples import resolve as resolve_sample
from .heldout import target_sizes
from .target import Target, bounds_from_target, build_target

if TYPE_CHECKING:
    from ..config import RunConfig


def _named_files(cfg: RunConfig) -> list[tuple[str, str]]:
    named = [("target.qsm", cfg.target.qsm)] if cfg.target.qsm else []
    return named + [(f"target.references[{i}]", r) for i, r in enumerate(cfg.target.references)]


@dataclass
class Checked:
    """What :func:`preflight` made while it checked a config, for the fit to use, not make again."""

    #: the target: its trees read (or grown) and its data sets
    target: Target
    #: the config with every bound scaled to the target resolved (the run's config.toml)
    cfg: RunConfig
    #: the components the config's sections select: ``optimizer``, ``executor``, ``distance``
    components: dict[str, Any]
    #: the warnings of the bounds' resolution (a bound moved into the model's range), the fit's to say
    notes: list = field(default_factory=list)


def preflight(cfg: RunConfig, target: Target | None = None, trees=None) -> Checked:
    """Check ``cfg`` as a fit would, and return what it made: the target (``target`` when given;
    built from ``trees`` when they are given, the target's trees already read or grown), the config
    with its scaled bounds resolved and the components.

    Raises
    ------
    ConfigError
        Naming every key and value at fault, separated by ``;``.
    """
    problems = []
    if not cfg.ssm.free:
        problems.append("ssm.free: no free parameters to fit (add e.g. free.NAME = { lower = ..., upper = ... })")
    built = {}
    for section in ("optimizer", "executor", "distance"):
        try:
            built[section] = build_component(cfg, section)
        except (ConfigError, PluginError) as exc:
            problems.append(f"{section}: {exc}")
    missing = False
    for key, path in _named_files(cfg):
        try:
            file = resolve_sample(path)
        except SampleError as exc:  # unknown, or not fetched: the message says how to fetch it
            problems.append(f"{key}: {exc}")
            missing = missing or key == "target.qsm"
            continue
        if not file.is_file():
            problems.append(f"{key}: {'not a file' if file.exists() else 'file not found'}: {path}")
            missing = missing or key == "target.qsm"
    tgt = target
    if tgt is None and not missing:
        try:
            tgt = build_target(cfg, trees)
        except BayesForestError as exc:  # names its own file or key
            problems.append(str(exc))
        except (ValueError, TypeError, KeyError, OSError) as exc:  # a plugin's own complaint
            problems.append(f"target: {type(exc).__name__}: {exc}")
    resolved, notes = cfg, []
    if tgt is not None:
        problems += _weight_problems(tgt)
        with warnings.catch_warnings(record=True) as notes:  # a bound moved into the model's range is the fit's to say
            warnings.simplefilter("always")
            try:
                resolved = bounds_from_target(cfg, tgt.trees)
                if resolved is not cfg:  # the resolved bounds pass the checks absolute ones pass
                    check_ssm_parameters(resolved)
            except ConfigError as exc:  # a scaled range that leaves nothing of the model's
                problems.append(str(exc))
    if cfg.start.estimator is not None:
        from .amortised import start_problems

        problems += start_problems(cfg)
    if tgt is not None and cfg.select.sizes:
        try:
            target_sizes(cfg, tgt.trees[0])
        except ConfigError as exc:
            problems.append(str(exc))
    if not problems and (cfg.select.features or cfg.select.distance):
        try:  # the tables the answer is chosen by, checked before the search, not after it
            preflight(selection_config(cfg), trees=tgt.trees)  # the same [target]: not read again
        except ConfigError as exc:
            problems.append(str(exc) if str(exc).startswith("select") else f"select: {exc}")
    if problems:
        raise ConfigError("; ".join(problems))
    return Checked(tgt, resolved, built, list(notes))


def _weight_problems(tgt: Target) -> list[str]:
    """Weights that name no data set of their term (after the feature set resolved its sets)."""
    out = []
    for i, t in enumerate(tgt.terms or []):
        sets = list(t.own(tgt.U))
        key = "objective.weights" if not t.prefix else f"objective.terms[{i - 1}].weights"
        for name in t.set_weights or {}:
            if name not in sets:
                out.append(f"{key}.{name}: no data set {name!r}{did_you_mean(name, sets)} (sets: {', '.join(sets)})")
        if t.set_weights and sets and all(t.set_weights.get(s, 1.0) == 0 for s in sets):
            out.append(f"{key}: every data set's weight is 0, so every distance would be 0 (sets: {', '.join(sets)})")
    return out
