"""The target of a run: its data tree(s), the objective's terms and their data tables.

Built once per run in the main process (:func:`build_target`); the tables travel to each worker
once (:mod:`.worker`).
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import ConfigError
from ..registry import component

if TYPE_CHECKING:
    from ..config import RunConfig

#: name of the [features]/[distance] term when the objective has more than one
STRUCTURE = "structure"


def feature_set_for(cfg: RunConfig, side: str, settings: dict | None = None, kind: str | None = None):
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


@dataclass(frozen=True)
class Term:
    """One term of the objective: a feature set and a distance (kinds and settings), the term's
    weight in the objective and the weights of its data sets.

    Its data sets are keyed ``prefix + set name`` wherever the terms' sets are pooled
    (``Target.U``, an evaluation's ``per_set``): the ``[features]``/``[distance]`` term has the
    prefix ``""`` (its sets keep their own names), a ``[[objective.terms]]`` entry ``"<name>/"``.
    """

    name: str
    prefix: str
    weight: float
    set_weights: dict[str, float] | None
    features_kind: str
    features: dict
    distance_kind: str
    distance: dict

    def own(self, by_set: Mapping[str, Any]) -> dict[str, Any]:
        """The entries of ``by_set`` (keyed as in ``Target.U``) that are this term's, keyed by its
        own set names."""
        pre = self.prefix
        return {k[len(pre) :]: v for k, v in by_set.items() if k.startswith(pre) and (pre or "/" not in k)}


def size_topology(cfg: RunConfig, side: str) -> tuple[str | None, list[str] | None]:
    """The branch rule under which the size term measures one side's trees (``"target"`` or
    ``"model"``), and the statistics it measures by it: the ``topology`` and ``topology_statistics``
    of the objective's first feature set of tree-level statistics (``FeatureSet.summary_rule``)
    after the per-side rules; (None, None) for each tree's own branches (the QSM's stored ones,
    the model's order mode).

    The clones' fidelity table measures by it, so that it counts first-order branches as the fit
    held them.
    """
    for spec in term_specs(cfg):
        rule = feature_set_for(cfg, side, spec.features, spec.features_kind).summary_rule()
        if rule is not None:
            return rule
    return None, None


def term_specs(cfg: RunConfig) -> list[Term]:
    """The terms of the objective: the ``[features]``/``[distance]`` term first, then each
    ``[[objective.terms]]`` entry."""
    from ..config import part_settings, section_settings

    o = cfg.objective
    specs = [
        Term(
            name=STRUCTURE,
            prefix="",
            weight=float(o.structure_weight),
            set_weights=o.weights,
            features_kind=cfg.features.kind,
            features=section_settings(cfg, "features"),
            distance_kind=cfg.distance.kind,
            distance=section_settings(cfg, "distance"),
        )
    ]
    for t in o.terms:
        specs.append(
            Term(
                name=t.name,
                prefix=f"{t.name}/",
                weight=float(t.weight),
                set_weights=t.weights,
                features_kind=t.features.kind,
                features=part_settings(t.features),
                distance_kind=t.distance.kind,
                distance=part_settings(t.distance),
            )
        )
    return specs


def load_target_trees(cfg: RunConfig) -> list:
    """The data tree(s) of the run: read from the QSM file or grown by the named SSM."""
    from ..config import generated_target_ssm
    from ..io import read_qsm

    t = cfg.target
    if t.generate is not None:
        ssm = generated_target_ssm(t.generate)
        # a grown target stands for a QSM simplified as the config says
        return [ssm.simulate(dict(t.generate.params), int(t.generate.seed)).pruned(t.prune_radius)]
    opts = {}
    if t.select is not None:
        opts["select"] = t.select
    trees = read_qsm(t.qsm, reader=t.reader, **opts)
    return list(trees) if isinstance(trees, (list, tuple)) else [trees]


def scale_bounds(times: dict, m: float, spec) -> tuple[dict, dict]:
    """Bounds given as multiples of a tree's measure ``m`` (``{"lower": a, ...}``, None kept), in
    absolute terms: as they come out (6 significant digits) and kept within the range of the
    parameter's ``spec``."""
    raw = {k: None if v is None else float(f"{v * m:.6g}") for k, v in times.items()}
    return raw, {k: None if v is None else min(max(v, spec.lower), spec.upper) for k, v in raw.items()}


def bounds_from_target(cfg: RunConfig, trees: list) -> RunConfig:
    """``cfg`` with every ``scaled_by`` bound of ``[ssm.free]`` resolved against the target.

    A bound ``{ lower = a, upper = b, scaled_by = m }`` becomes ``[a * M, b * M]`` with ``M`` the
    measure ``m`` of the first target tree (:func:`bforest_core.metrics.measure_tree`), so the
    recipe of one tree suits another of another size. A resolved bound beyond the model's range
    is moved to it, with a warning (the user could not know the tree's measure when writing the
    recipe); nothing left of the range is a ConfigError. ``cfg`` itself is returned when nothing
    is scaled.
    """
    from ..config import build_component
    from ..metrics import measure_tree, summary_unit

    scaled = {n: fp for n, fp in cfg.ssm.free.items() if fp.scaled_by is not None}
    if not scaled:
        return cfg
    ssm = build_component(cfg, "ssm")
    measures = measure_tree(trees[0])
    free = dict(cfg.ssm.free)
    source = cfg.target.qsm or "the generated target"
    for name, fp in scaled.items():
        m = float(getattr(measures, fp.scaled_by))
        spec = ssm.parameter_spec(name)
        unit = "" if summary_unit(fp.scaled_by) == "count" else " m"  # a count (n_whorls) or a length
        what = f"ssm.free.{name}: {fp.lower:g}-{fp.upper:g} x the {fp.scaled_by} of {source} ({m:.4g}{unit})"
        if not (np.isfinite(m) and m > 0):
            raise ConfigError(f"{what}: the measure must be positive; give absolute bounds")
        raw, new = scale_bounds({k: getattr(fp, k) for k in ("lower", "upper", "init_lower", "init_upper")}, m, spec)
        if not new["lower"] < new["upper"]:
            raise ConfigError(
                f"{what} = [{raw['lower']:g}, {raw['upper']:g}] is outside the model's range "
                f"[{spec.lower:g}, {spec.upper:g}] {spec.unit}".rstrip()
            )
        if new != raw:
            warnings.warn(
                f"{what} = [{raw['lower']:g}, {raw['upper']:g}] goes beyond the model's range "
                f"[{spec.lower:g}, {spec.upper:g}] {spec.unit}: the search keeps to "
                f"[{new['lower']:g}, {new['upper']:g}]".rstrip(),
                stacklevel=2,
            )
        if new["init_lower"] is not None and new["init_upper"] is not None and new["init_lower"] >= new["init_upper"]:
            new["init_lower"] = new["init_upper"] = None  # the initial range fell outside: the bounds
        free[name] = fp.model_copy(update=new | {"scaled_by": None})
    return cfg.model_copy(update={"ssm": cfg.ssm.model_copy(update={"free": free})})


@dataclass
class Target:
    trees: list
    U: dict[str, np.ndarray]  # every term's data sets (other terms' as "<term>/<set>")
    columns: dict[str, list[str]]
    feature_settings: dict  # the data-side feature set after prepare (resolved sets)
    terms: list[Term] | None = None  # term_specs with each term's resolved feature settings


def build_target(cfg: RunConfig, trees=None) -> Target:
    trees = load_target_trees(cfg) if trees is None else trees
    U, cols, terms = {}, {}, []
    for spec in term_specs(cfg):
        fs = feature_set_for(cfg, "target", spec.features, spec.features_kind)
        fs.prepare(trees)
        Ut = fs.extract_pooled(trees)
        for k in fs.set_names:
            U[spec.prefix + k] = Ut[k]
            cols[spec.prefix + k] = fs.columns(k)
        terms.append(replace(spec, features=fs.resolved_settings()))
    return Target(trees, U, cols, terms[0].features, terms)
