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
from pathlib import Path
from typing import TYPE_CHECKING

from ..config import check_ssm_parameters, did_you_mean, section_settings
from ..errors import BayesForestError, ConfigError, PluginError
from ..registry import component
from .heldout import selection_config
from .target import Target, bounds_from_target, build_target

if TYPE_CHECKING:
    from ..config import RunConfig


def _named_files(cfg: RunConfig) -> list[tuple[str, str]]:
    named = [("target.qsm", cfg.target.qsm)] if cfg.target.qsm else []
    return named + [(f"target.references[{i}]", r) for i, r in enumerate(cfg.target.references)]


def preflight(cfg: RunConfig, target: Target | None = None, trees=None) -> Target:
    """Check ``cfg`` as a fit would, and return its target (``target`` when given; built from
    ``trees`` when they are given, the target's trees already read or grown).

    Raises
    ------
    ConfigError
        Naming every key and value at fault, separated by ``;``.
    """
    problems = []
    if not cfg.ssm.free:
        problems.append("ssm.free: no free parameters to fit (add e.g. free.NAME = { lower = ..., upper = ... })")
    for section in ("optimizer", "executor", "distance"):
        try:
            component(section, getattr(cfg, section).kind, **section_settings(cfg, section))
        except (ConfigError, PluginError) as exc:
            problems.append(f"{section}: {exc}")
    missing = False
    for key, path in _named_files(cfg):
        if not Path(path).is_file():
            problems.append(f"{key}: {'not a file' if Path(path).exists() else 'file not found'}: {path}")
            missing = missing or key == "target.qsm"
    tgt = target
    if tgt is None and not missing:
        try:
            tgt = build_target(cfg, trees)
        except BayesForestError as exc:  # names its own file or key
            problems.append(str(exc))
        except (ValueError, TypeError, KeyError, OSError) as exc:  # a plugin's own complaint
            problems.append(f"target: {type(exc).__name__}: {exc}")
    if tgt is not None:
        problems += _weight_problems(tgt)
        with warnings.catch_warnings():  # a bound moved into the model's range is the fit's to say
            warnings.simplefilter("ignore")
            try:
                resolved = bounds_from_target(cfg, tgt.trees)
                if resolved is not cfg:  # the resolved bounds pass the checks absolute ones pass
                    check_ssm_parameters(resolved)
            except ConfigError as exc:  # a scaled range that leaves nothing of the model's
                problems.append(str(exc))
    if not problems and (cfg.select.features or cfg.select.distance):
        try:  # the tables the answer is chosen by, checked before the search, not after it
            preflight(selection_config(cfg), trees=tgt.trees)  # the same [target]: not read again
        except ConfigError as exc:
            problems.append(str(exc) if str(exc).startswith("select") else f"select: {exc}")
    if problems:
        raise ConfigError("; ".join(problems))
    return tgt


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
