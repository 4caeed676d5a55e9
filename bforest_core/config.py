"""Run configuration: TOML validated by pydantic.

The component sections (``[ssm]``, ``[features]``, ``[distance]``, ``[optimizer]``,
``[executor]``) are discriminated unions on ``kind`` built from the registry at start-up, so a
third-party plugin's settings are validated exactly like a bundled one's. Example::

    seed = 1
    [target]
    qsm = "sample:pine_ruotsinkyla_3"     # or a path, relative to this file
    [ssm]
    kind = "lignum"
    fixed = { radiation = 60.0 }
    free.q_mean = { lower = 0.05, upper = 0.4 }
    [features]
    sets = ["S1", "B1"]
    [executor]
    workers = 2

A section left out, or its ``kind``, takes the bundled default (:data:`DEFAULT_KINDS`).
"""

from __future__ import annotations

import difflib
import functools
import math
import tomllib
import types
import typing
from pathlib import Path
from typing import Annotated, Any, Literal, Optional, Union

import pydantic
from pydantic import BaseModel, ConfigDict, Field, create_model, field_validator, model_validator

from .errors import UNION_TAGS, ConfigError, validation_error_text
from .metrics import checked_fractions
from .registry import discover
from .samples import is_sample

#: config section -> component kind
SECTIONS = {
    "ssm": "ssm",
    "features": "features",
    "distance": "distance",
    "optimizer": "optimizer",
    "executor": "executor",
}
#: the bundled default kinds, the one table of the core that names bundled plugins: per section,
#: the kind a config that leaves the section out (or its ``kind``) takes, and the kind ``bforest
#: init`` writes a recipe with (``size.*``: the size term of ``[[objective.terms]]``); each of
#: those plugins writes its own part of the recipe (``draft_recipe``)
BUNDLED_KINDS = {
    "features": ("branch-segment", "branch-segment"),
    "distance": ("sliced", "sliced"),
    "optimizer": ("ga", "cma"),
    "executor": ("process", "process"),
    "size.features": (None, "tree-summary"),
    "size.distance": (None, "summary"),
}
#: the kind of a component section a config leaves out
DEFAULT_KINDS = {section: kinds[0] for section, kinds in BUNDLED_KINDS.items() if kinds[0] is not None}
#: the kinds ``bforest init`` writes a recipe with
RECIPE_KINDS = {section: kinds[1] for section, kinds in BUNDLED_KINDS.items()}


class _Strict(BaseModel):
    # every number of a config is finite: NaN or an infinity is an error naming the key
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


#: the largest value of each numeric setting that sizes the work or the memory of a run: what a
#: 2-core laptop can run (a config beyond it is refused by the config check and the fit alike)
MAX_SEEDS = 1000  # model seeds per evaluation ([objective] seeds, model_seeds)
MAX_TIMEOUT = 86400.0  # s, a day: one simulation's time limit
MAX_SELECT = 1000  # [select] top and sets
MAX_CLONES = 10000


#: measures of the target tree that bounds may be scaled by (``bforest_core.metrics.TreeMeasures``)
SCALE_MEASURES = (
    "height",
    "dbh",
    "crown_spread",
    "crown_base_height",
    "crown_length",
    "branch_spacing",
    "longest_limb",
    "thinnest_branch",
    "n_whorls",
)


class FreeParameter(_Strict):
    """A parameter the optimiser varies, within ``[lower, upper]``.

    With ``scaled_by`` the four bounds are multiples of that measure of the target tree, resolved
    to absolute bounds when the fit starts (the run folder's config.toml holds the resolved ones):
    one recipe then fits trees of another size.
    """

    lower: float
    upper: float
    init_lower: Optional[float] = Field(None, description="initial population range (default: bounds)")
    init_upper: Optional[float] = None
    integer: Optional[bool] = Field(None, description="whole values only (default: from the SSM's spec)")
    scaled_by: Optional[Literal[SCALE_MEASURES]] = Field(
        None,
        description=(
            "a measure of the target tree (m; n_whorls a count): the bounds are multiples of it, e.g. node_length = "
            "{ lower = 0.8, upper = 1.45, scaled_by = 'branch_spacing' }"
        ),
    )

    @model_validator(mode="after")
    def _order(self):
        if not self.lower < self.upper:
            raise ValueError(f"lower ({self.lower}) must be below upper ({self.upper})")
        if self.scaled_by is not None and self.lower < 0:
            raise ValueError(f"lower ({self.lower}) must be >= 0: the bounds are multiples of {self.scaled_by}")
        ilo = self.lower if self.init_lower is None else self.init_lower
        ihi = self.upper if self.init_upper is None else self.init_upper
        if not (self.lower <= ilo < ihi <= self.upper):
            raise ValueError(
                f"need lower <= init_lower < init_upper <= upper (got {self.lower}, {ilo}, {ihi}, {self.upper})"
            )
        return self


class GeneratedTarget(_Strict):
    """A target grown by a registered SSM (no external file needed)."""

    ssm: str
    seed: int = Field(1, ge=0)
    params: dict[str, float] = Field(default_factory=dict)
    settings: dict[str, Any] = Field(
        default_factory=dict,
        description="the SSM's own settings (e.g. preset), checked as its [ssm] section's are when the config is read",
    )


class TargetConfig(_Strict):
    """The data tree(s): a QSM file, or a tree generated by a model."""

    qsm: Optional[str] = Field(
        None, description="path of the QSM file (relative to the config file), or sample:NAME for a fetched sample tree"
    )
    generate: Optional[GeneratedTarget] = None
    reader: Optional[str] = Field(None, description="force a reader by name (default: detect)")
    select: Union[int, list[int], Literal["all"], None] = Field(None, description="reconstruction(s) of a QSMs file")
    topology: Optional[Literal["source", "subtree", "thickest"]] = Field(
        None, description="topology rule of the data side (default: the feature set's)"
    )
    references: list[str] = Field(
        default_factory=list,
        description="QSM files of other trees of the stand (relative to the config file): "
        "the report shows the target's distance to each beside the clones' distances",
    )
    prune_radius: float = Field(
        0.0,
        ge=0,
        le=0.2,
        allow_inf_nan=False,
        description="radius (m) below which the QSM was simplified (twigs removed): every tree the model "
        "grows loses its cylinders thinner than this and everything beyond them before it is scored, and "
        "clones are written so, so that both sides show the same branches (0: nothing removed)",
    )

    @model_validator(mode="after")
    def _one(self):
        if (self.qsm is None) == (self.generate is None):
            raise ValueError("give exactly one of 'qsm' (a file) or 'generate' (a model-grown target)")
        return self


def _check_weights(weights):
    """Weights of data sets: finite numbers, none negative (the error names the set)."""
    for k, w in (weights or {}).items():
        if not math.isfinite(w) or w < 0:
            raise ValueError(f"the weight of {k!r} must be a finite number >= 0 (got {w})")
    return weights


class ComponentPart(BaseModel):
    """A component named inside an entry of the config: ``{ kind = NAME, settings... }``.

    The declared type only: the model :func:`run_config_model` builds types each such entry as
    the named plugin's settings model (a discriminated union on ``kind``, as the component
    sections are), so its settings are validated when the config is read.
    """

    model_config = ConfigDict(extra="allow")

    kind: str = Field(..., description="the plugin name")


def part_settings(part: BaseModel, written: bool = False, exclude=frozenset({"kind"})) -> dict[str, Any]:
    """Return the settings of a component entry or section: its fields but ``kind``, as the plugin takes them.

    ``written``: as a config file holds them (JSON values, unset ones left out); ``exclude``: the
    keys that are not the plugin's (``kind``; an SSM section's also the run's ``fixed``, ``free``
    and ``topology``).
    """
    if written:
        return part.model_dump(mode="json", exclude_none=True, exclude=set(exclude))
    return part.model_dump(exclude=set(exclude))


class TermConfig(_Strict):
    """One more term of the objective: its own feature set and distance, and a weight.

    The objective is the weighted mean of its terms: the ``[features]``/``[distance]`` term
    (weight ``objective.structure_weight``) and each ``[[objective.terms]]`` entry. Its data
    sets are stored as ``<name>/<set>``.
    """

    name: str = Field(
        ..., pattern=r"^[A-Za-z][A-Za-z0-9_-]*$", description="name of the term (its sets are stored as NAME/SET)"
    )
    weight: float = Field(1.0, gt=0, description="weight of the term in the objective")
    features: ComponentPart = Field(
        ..., description="feature set: { kind = NAME, settings... }, the plugin's settings as in [features]"
    )
    distance: ComponentPart = Field(
        ..., description="distance: { kind = NAME, settings... }, the plugin's settings as in [distance]"
    )
    weights: Optional[dict[str, float]] = Field(None, description="weight per data set within the term")

    _weights = field_validator("weights")(lambda cls, v: _check_weights(v))

    @model_validator(mode="before")
    @classmethod
    def _kinds(cls, data):
        for part in ("features", "distance"):
            value = data.get(part) if isinstance(data, dict) else None
            if isinstance(value, dict) and not isinstance(value.get("kind"), str):
                raise ValueError(f'{part}: needs kind = "<{part} plugin name>"')
        return data


class ObjectiveConfig(_Strict):
    """How one parameter vector is scored."""

    seeds: int = Field(
        1, ge=1, le=MAX_SEEDS, description="model seeds per evaluation (mean distance; common random numbers)"
    )
    seed_mode: Literal["fixed", "per_evaluation"] = Field(
        "fixed",
        description="fixed: the same model seed(s) for every evaluation (the paper); "
        "per_evaluation: from the run seed and the evaluation index",
    )
    model_seeds: Optional[list[int]] = Field(
        None,
        max_length=MAX_SEEDS,
        description="explicit model seeds held fixed for every evaluation (overrides seeds/seed_mode)",
    )
    weights: Optional[dict[str, float]] = Field(None, description="weight per data set (default equal)")
    penalty: float = Field(
        1.0,
        ge=0,
        allow_inf_nan=False,
        description="distance of a failed simulation, for optimisers: keep it above every "
        "real distance (1.0 suits statistics bounded by 1, such as KS); "
        "samplers that say so (abc-smc) treat a failure as inf instead",
    )
    timeout: Optional[float] = Field(
        60.0, gt=0, le=MAX_TIMEOUT, description="seconds before a simulation is stopped (at most a day; None: no limit)"
    )
    cache: bool = Field(True, description="never simulate identical params and seeds twice")
    structure_weight: float = Field(
        1.0, gt=0, description="weight of the [features]/[distance] term when [[objective.terms]] adds others"
    )
    terms: list[TermConfig] = Field(
        default_factory=list,
        description="more terms of the objective, e.g. a summary-statistics term beside the structural distance",
    )

    _weights = field_validator("weights")(lambda cls, v: _check_weights(v))

    @field_validator("model_seeds")
    @classmethod
    def _seeds(cls, v):
        if v is not None and any(s < 0 for s in v):
            raise ValueError(f"seeds must be >= 0 (got {v})")
        return v

    @model_validator(mode="after")
    def _unique_terms(self):
        names = [t.name for t in self.terms]
        dup = sorted({n for n in names if names.count(n) > 1} | ({"structure"} & set(names)))
        if dup:
            raise ValueError(
                f"terms: the name {dup[0]!r} is used twice ('structure' is the [features]/[distance] term)"
            )
        return self


class StopConfig(_Strict):
    """When a fit stops: an evaluation budget, a wall time (seconds) or a target distance."""

    max_evaluations: Optional[int] = Field(None, ge=1, description="evaluation budget")
    wall_time: Optional[float] = Field(None, gt=0, description="seconds")
    target_distance: Optional[float] = Field(None, description="stop once the best distance is at or below this")


class SelectConfig(_Strict):
    """How the answer of a fit is chosen: on model seeds the search never used."""

    top: int = Field(
        0,
        ge=0,
        le=MAX_SELECT,
        description="best distinct points of the search re-scored on held-out model seeds "
        "at the end of the fit; the answer is the one of lowest held-out distance (0: the answer "
        "is the point of lowest own distance, with no re-scoring)",
    )
    sets: int = Field(
        8,
        ge=1,
        le=MAX_SELECT,
        description="sets of held-out model seeds per candidate, each as large as an evaluation's ([objective] seeds)",
    )
    spacing: float = Field(
        0.02,
        ge=0,
        le=1,
        description="candidates differ by more than this fraction of a "
        "parameter's range in at least one parameter (distinct points, not near-copies)",
    )
    features: Optional[dict[str, Any]] = Field(
        None,
        description="settings merged over [features] when the candidates are scored, e.g. "
        '{ sets = ["S1", "B1"] }: the tables the answer is chosen by, when they are not the '
        "search's own (the [[objective.terms]] stay as they are); a kind of its own replaces the section; "
        "checked, merged, as a [features] section when the config is read",
    )
    distance: Optional[dict[str, Any]] = Field(
        None,
        description="settings merged over [distance] when the candidates are scored, e.g. { lines = 256 }",
    )
    sizes: dict[str, float] = Field(
        default_factory=dict,
        description="relative errors (fractions) the candidates' held-out trees must keep, on average, from the "
        "tree's statistics as the clones' fidelity table measures them, e.g. { height = 0.06, dbh = 0.16 }: "
        "the candidates within every one come first, and among them the lowest held-out distance is the "
        "answer (none within: the lowest of all, with a warning)",
    )

    _sizes = field_validator("sizes")(lambda cls, v: checked_fractions(v, "sizes"))


class StartConfig(_Strict):
    """Where the search starts: draws of an amortised estimator's posterior for the target."""

    estimator: Optional[str] = Field(
        None,
        description="an amortised estimator (bforest train's estimator.npz, relative to this file; 'shipped': the "
        "one shipped for the [ssm] model): the search's first points are draws of its posterior for the target "
        "(cma's init_design); none: the optimiser's own start",
    )
    draws: int = Field(256, ge=1, description="posterior draws handed to the optimiser (it takes what it needs)")


class ClonesConfig(_Strict):
    """The clones of the answer: model trees grown with its parameters on other seeds."""

    count: int = Field(100, ge=1, le=MAX_CLONES)
    seed: Optional[int] = Field(None, ge=0, description="seed of the clone seeds (default: derived from the run seed)")


class ReportConfig(_Strict):
    """Whether a fit writes its report, and how many clones its figure draws."""

    enabled: bool = True
    clones_in_figure: int = Field(6, ge=1, le=100)


class RunConfig(_Strict):
    """A validated run configuration: the type of every ``cfg``.

    Made by :func:`load_config` and :func:`parse_config`. The sections every run has are declared here; the component sections (``ssm``, ``features``,
    ``distance``, ``optimizer``, ``executor``) are the installed plugins' settings models, added
    by :func:`run_config_model`, whose model this is the base of. A config pickles (by reference
    to its models), so it travels to the executor's workers as the validated object.
    """

    seed: int = Field(1, ge=0, description="run seed: every evaluation seed and clone seed derives from it")
    target: TargetConfig
    objective: ObjectiveConfig = Field(default_factory=ObjectiveConfig)
    stop: StopConfig = Field(default_factory=StopConfig)
    select: SelectConfig = Field(default_factory=SelectConfig)
    start: StartConfig = Field(default_factory=StartConfig)
    clones: ClonesConfig = Field(default_factory=ClonesConfig)
    report: ReportConfig = Field(default_factory=ReportConfig)


#: the models built from the installed plugins, by the module-level name pickle finds them under
_BUILT: dict[str, type[BaseModel]] = {}


def _register_built(model: type[BaseModel], name: str) -> type[BaseModel]:
    """Give a model built at run time a name in this module.

    Its instances then pickle by reference and a process that unpickles one (a worker) finds the
    class (:func:`__getattr__`).
    """
    model.__module__ = __name__
    model.__qualname__ = name
    _BUILT[name] = model
    return model


def __getattr__(name: str):
    """Return a model built from the installed plugins, built on first use.

    A worker unpickling a config looks its models up here.

    Parameters
    ----------
    name : str
        The attribute's name (``_built_...`` for a built model).

    Returns
    -------
    type
        The model class.

    Raises
    ------
    AttributeError
        For any other name.
    """
    if name.startswith("_built_"):
        run_config_model()
        if name in _BUILT:
            return _BUILT[name]
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def _section_model(kind: str, name: str, cls: type) -> type[BaseModel]:
    """Build the config model of one component: its Settings plus ``kind`` (and SSM extras)."""
    fields: dict[str, Any] = {"kind": (Literal[name], Field(..., description=f"{kind} plugin name"))}
    if kind == "ssm":
        fields["fixed"] = (dict[str, float], Field(default_factory=dict, description="parameters held at these values"))
        fields["free"] = (
            dict[str, FreeParameter],
            Field(default_factory=dict, description="parameters the optimiser varies"),
        )
        fields["topology"] = (
            Optional[Literal["source", "subtree", "thickest"]],
            Field(None, description="topology rule of the model side (default: the feature set's)"),
        )
    base = cls.Settings
    model = create_model(f"{cls.__name__}_{kind}_config", __base__=base, **fields)
    model.__doc__ = (cls.__doc__ or "").strip().split("\n")[0]
    return _register_built(model, f"_built_{kind}_{name}")


def _union(models: list, tag: str = "kind"):
    """One model, or a union of several discriminated by the field ``tag``."""
    return models[0] if len(models) == 1 else Annotated[Union[tuple(models)], Field(discriminator=tag)]


def _typed(base: type[BaseModel], **annotations) -> type[BaseModel]:
    """Return ``base`` with fields retyped (defaults and descriptions kept), registered as ``_built_<name>``."""
    typed = {}
    for name, ann in annotations.items():
        f = base.model_fields[name]  # a new Field: a copy of the old one would keep its type's metadata
        default = {"default_factory": f.default_factory} if f.default_factory else {"default": f.default}
        typed[name] = (ann, Field(**default, description=f.description))
    return _register_built(create_model(base.__name__, __base__=base, **typed), f"_built_{base.__name__}")


def _generated_target(name: str, cls: type) -> type[BaseModel]:
    """``[target.generate]`` for the SSM ``name``: its settings typed as the plugin's Settings."""
    model = create_model(
        f"GeneratedTarget_{name}",
        __base__=GeneratedTarget,
        ssm=(Literal[name], Field(..., description="the SSM plugin name")),
        settings=(
            cls.Settings,
            Field(default_factory=cls.Settings, description=GeneratedTarget.model_fields["settings"].description),
        ),
    )
    return _register_built(model, f"_built_generate_{name}")


@functools.cache
def _run_config_model(registry_id: int):
    reg = discover()
    fields, unions = {}, {}
    for section, kind in SECTIONS.items():
        names = reg.names(kind)
        models = [_section_model(kind, n, reg.get(kind, n)) for n in names if (kind, n) in reg.components]
        if not models:
            fields[section] = (Optional[dict], None)
            continue
        unions[section] = _union(models)
        fields[section] = (unions[section], ...)  # parse_config fills the default kinds first
    # a component named inside an entry is typed as its plugin's settings, as the sections are
    if "features" in unions and "distance" in unions:
        term = _typed(TermConfig, features=unions["features"], distance=unions["distance"])
        objective = _typed(ObjectiveConfig, terms=list[term])
        fields["objective"] = (objective, Field(default_factory=objective))
    ssms = [_generated_target(n, reg.get("ssm", n)) for n in reg.names("ssm") if ("ssm", n) in reg.components]
    if ssms:
        target = _typed(TargetConfig, generate=Optional[_union(ssms, "ssm")])
        fields["target"] = (target, ...)
    return _register_built(create_model("RunConfig", __base__=RunConfig, **fields), "_built_RunConfig")


def run_config_model() -> type[RunConfig]:
    """Return the pydantic model of a run configuration, with the installed plugins' components.

    Returns
    -------
    type of RunConfig
        A subclass of :class:`RunConfig` whose component sections are discriminated unions of
        the installed plugins' settings models.
    """
    return _run_config_model(id(discover()))


def _fill_defaults(raw: dict) -> dict:
    raw = dict(raw)
    for section, name in DEFAULT_KINDS.items():
        sec = raw.get(section)
        if sec is None:
            raw[section] = {"kind": name}
        elif isinstance(sec, dict) and "kind" not in sec:
            raw[section] = {"kind": name, **sec}
    if isinstance(raw.get("ssm"), dict) and "kind" not in raw["ssm"]:
        raw["ssm"] = dict(raw["ssm"])  # let pydantic report the missing kind
    return raw


def did_you_mean(word, options) -> str:
    """Suggest the option closest to ``word``.

    Parameters
    ----------
    word : object
        What was given (compared as text).
    options : iterable
        The allowed values.

    Returns
    -------
    str
        `` (did you mean 'x'?)`` for a close option, else ``""``.
    """
    close = difflib.get_close_matches(str(word), [str(o) for o in options], n=1, cutoff=0.6)
    return f" (did you mean '{close[0]}'?)" if close else ""


def _model_in(ann, data):
    """Return the pydantic model a value of annotation ``ann`` is validated by, or None.

    For a discriminated union, the member that ``data``'s tag (``kind``, or ``ssm`` in
    ``[target.generate]``) selects.
    """
    if isinstance(ann, type) and issubclass(ann, BaseModel):
        return ann
    origin, args = typing.get_origin(ann), typing.get_args(ann)
    if origin is Annotated:
        return _model_in(args[0], data)
    if origin in (Union, types.UnionType):
        models = [m for m in (_model_in(a, data) for a in args) if m is not None]
        for m in models:
            for tag in UNION_TAGS:
                f = m.model_fields.get(tag)
                if f is not None and isinstance(data, dict) and typing.get_args(f.annotation) == (data.get(tag),):
                    return m
        return models[0] if len(models) == 1 else None
    return None


def _allowed_keys(model, raw, loc) -> list[str]:
    """Return the keys allowed beside the last part of ``loc`` (a validation error's location)."""
    cur, data, inner = model, raw, None  # inner: the annotation of a dict's values or a list's items
    for part in loc[:-1]:
        if inner is not None:  # the key of a dict of models (ssm.free.NAME) or an index (objective.terms.0)
            if isinstance(data, list):
                data = data[int(part)] if part.isdigit() and int(part) < len(data) else None
            else:
                data = data.get(part) if isinstance(data, dict) else None
            cur, inner = _model_in(inner, data), None
            continue
        if cur is None or not isinstance(data, dict):
            return []
        if part in cur.model_fields:
            ann, data = cur.model_fields[part].annotation, data.get(part)
            if typing.get_origin(ann) in (dict, list):
                inner = typing.get_args(ann)[-1]
            else:
                cur = _model_in(ann, data)
        elif part not in [data.get(t) for t in UNION_TAGS]:  # (a union's tag is skipped)
            return []
    return list(cur.model_fields) if cur is not None else []


def parameter_problems(where: str, model: str, specs: dict, values: dict) -> list[str]:
    """Check parameter entries of a config against a model's ``ParameterSpec``s.

    The one check of a parameter's name and range (``ssm.fixed``, ``ssm.free``,
    ``target.generate.params``).

    Parameters
    ----------
    where : str
        The entries' key path in the config (``"ssm.fixed"``).
    model : str
        The SSM's name, for messages.
    specs : dict
        ``ParameterSpec`` by name.
    values : dict
        Name -> a value, a ``(lower, upper, integer)`` triple of bounds (``integer`` None: the
        parameter's own), or None (the name alone is checked).

    Returns
    -------
    list of str
        One message per unknown name, value outside its parameter's range or not whole where it
        must be, bounds outside the range or holding no whole number of a whole-number parameter.
    """
    problems = []
    for name, val in values.items():
        s = specs.get(name)
        if s is None:
            problems.append(
                f"{where}.{name}: unknown parameter of '{model}' (known: {', '.join(specs)}){did_you_mean(name, specs)}"
            )
        elif isinstance(val, tuple):
            lo, hi, whole = val[0], val[1], s.integer if len(val) < 3 or val[2] is None else val[2]
            if lo < s.lower or hi > s.upper:
                problems.append(
                    f"{where}.{name}: bounds [{lo}, {hi}] exceed the allowed range [{s.lower}, {s.upper}] {s.unit}".rstrip()
                )
            if whole and math.ceil(lo) > math.floor(hi):
                problems.append(
                    f"{where}.{name}: the bounds [{lo}, {hi}] of a whole-number parameter hold no whole number "
                    "(widen them, or set integer = false)"
                )
        elif val is not None and _value_problem(val, s):
            problems.append(f"{where}.{name}: {_value_problem(val, s)}")
    return problems


def check_ssm_parameters(cfg: RunConfig) -> None:
    """Check that ``fixed`` and ``free`` entries name parameters of the SSM, within its ranges.

    Parameters
    ----------
    cfg : RunConfig
        The config.

    Raises
    ------
    ConfigError
        Listing every problem.
    PluginError
        If the SSM is not installed.
    """
    specs = {p.name: p for p in build_component(cfg, "ssm").parameters}
    problems = [
        f"ssm '{cfg.ssm.kind}': the plugin's parameter name {n!r} is not a Python identifier (it is a "
        "TOML key, a column name and a report label)"
        for n in specs
        if not _identifier(n)
    ]
    kind = cfg.ssm.kind
    problems += parameter_problems("ssm.fixed", kind, specs, cfg.ssm.fixed)
    # a bound scaled to the tree is checked once resolved (pipeline.target)
    bounds = {
        n: None if fp.scaled_by is not None else (fp.lower, fp.upper, fp.integer) for n, fp in cfg.ssm.free.items()
    }
    problems += parameter_problems("ssm.free", kind, specs, bounds)
    problems += [f"ssm.free.{n}: also listed in ssm.fixed" for n in cfg.ssm.free if n in specs and n in cfg.ssm.fixed]
    if problems:
        raise ConfigError("; ".join(problems))


def _value_problem(val: float, spec) -> str | None:
    """Return what is wrong with ``val`` as a value of the parameter ``spec``, or None.

    Outside its range, or not a whole number of a whole-number parameter (which would be cut
    silently).
    """
    if not spec.lower <= val <= spec.upper:
        return f"{val} is outside the allowed range [{spec.lower}, {spec.upper}] {spec.unit}".rstrip()
    if spec.integer and val != int(val):
        return f"{val} is not a whole number ({spec.name} counts whole {spec.unit or 'steps'})"
    return None


def _identifier(name) -> bool:
    import keyword

    return isinstance(name, str) and name.isidentifier() and not keyword.iskeyword(name)


def check_generated_target(cfg: RunConfig) -> None:
    """Check that ``[target.generate] params`` name parameters of its SSM, within their ranges.

    (The SSM's name and settings are checked as the config is validated.)

    Parameters
    ----------
    cfg : RunConfig
        The config (nothing to check without a generated target).

    Raises
    ------
    ConfigError
        For an unknown parameter, or one outside its range.
    """
    gen = cfg.target.generate
    if gen is None:
        return
    specs = {p.name: p for p in generated_target_ssm(gen).parameters}
    problems = parameter_problems("target.generate.params", gen.ssm, specs, gen.params)
    if problems:
        raise ConfigError("; ".join(problems))


def generated_target_ssm(gen: GeneratedTarget):
    """Build the SSM that ``[target.generate]`` grows its target with, with its settings."""
    from .registry import component

    return component("ssm", gen.ssm, **part_settings(gen.settings, exclude=()))


def build_component(cfg: RunConfig, section: str):
    """Build the component a section of the config selects: the one place a run's components are made.

    Parameters
    ----------
    cfg : RunConfig
        The config.
    section : str
        ``"ssm"``, ``"features"``, ``"distance"``, ``"optimizer"`` or ``"executor"``.

    Returns
    -------
    Component
        The plugin's component, with the section's settings (an SSM's without ``fixed``, ``free``
        and ``topology``, which are the run's, not the plugin's).

    Raises
    ------
    PluginError
        If the plugin is not installed.
    """
    from .registry import component

    return component(SECTIONS[section], getattr(cfg, section).kind, **section_settings(cfg, section))


@functools.cache
def _section_holder(section: str, name: str) -> type[BaseModel] | None:
    """Return a model with the one field ``section`` of plugin ``name``'s section (None: not installed)."""
    run_config_model()  # builds the section models of the installed plugins
    model = _BUILT.get(f"_built_{SECTIONS[section]}_{name}")
    return None if model is None else create_model(f"_{section}_{name}", __base__=_Strict, **{section: (model, ...)})


def with_section(cfg: RunConfig, section: str, data: dict, source: str = "config") -> RunConfig:
    """Return ``cfg`` with one component section replaced.

    A derived config, the new section validated alone and the rest shared (``model_copy``),
    never a dict round trip of the whole config.

    Parameters
    ----------
    cfg : RunConfig
        The config.
    section : str
        ``"features"``, ``"distance"``, ``"optimizer"`` or ``"executor"``.
    data : dict
        The new section: ``{"kind": NAME, settings...}``.
    source : str, optional
        Name of the derived config in messages (``"select"`` gives ``select: features.sets: ...``).

    Returns
    -------
    RunConfig
        A new config sharing every other section with ``cfg``.

    Raises
    ------
    ConfigError
        For an unknown kind or invalid settings, naming the key path.
    """
    model = _section_holder(section, str(data.get("kind")))
    if model is None:
        names = discover().names(SECTIONS[section])
        raise ConfigError(
            f"{source}: {section}.kind: unknown {SECTIONS[section]} {data.get('kind')!r} (known: {', '.join(names)})"
            f"{did_you_mean(data.get('kind'), names)}"
        )
    try:  # held by a model of the one section, so that messages name it: "features.sets: ..."
        value = getattr(model.model_validate({section: data}), section)
    except pydantic.ValidationError as exc:
        raise ConfigError(f"{source}: {validation_error_text(exc)}") from None
    return cfg.model_copy(update={section: value})


def selection_config(cfg: RunConfig) -> RunConfig:
    """Return the config the candidate answers are scored with (``[select]``).

    ``cfg`` itself, or with ``[select] features``/``distance`` merged over its
    ``[features]``/``[distance]`` (a ``kind`` of their own replaces the section), each validated
    as the typed section it makes; checked as the config is read (:func:`parse_config`), so a
    ConfigError's message starts ``select:`` when they do not validate.
    """
    sel = cfg.select
    if not sel.features and not sel.distance:
        return cfg
    out = cfg.model_copy(update={"select": sel.model_copy(update={"features": None, "distance": None})})
    for part in ("features", "distance"):
        extra = getattr(sel, part)
        if extra:
            own = {"kind": getattr(cfg, part).kind, **section_settings(cfg, part, written=True)}
            same = extra.get("kind", own["kind"]) == own["kind"]
            out = with_section(out, part, {**own, **extra} if same else dict(extra), source="select")
    return out  # its messages: "select: features.sets: ..."


def section_settings(cfg: RunConfig, section: str, written: bool = False) -> dict:
    """Return a component section's settings: the plugin's own.

    Without ``kind`` (an SSM's also without the run's ``fixed``, ``free`` and ``topology``);
    ``written``: as a config file holds them (JSON values, unset ones left out).

    Parameters
    ----------
    cfg : RunConfig
        The config.
    section : str
        The section: ``"ssm"``, ``"features"``, ``"distance"``, ``"optimizer"`` or ``"executor"``.
    written : bool, optional
        The settings as a config file writes them.

    Returns
    -------
    dict
        The component's settings.
    """
    return part_settings(getattr(cfg, section), written, _RUN_KEYS if section == "ssm" else {"kind"})


#: keys of the ``[ssm]`` section that are the run's, not the plugin's settings
_RUN_KEYS = {"kind", "fixed", "free", "topology"}


def parse_config(raw: dict, base_dir: Path | None = None, source: str = "config"):
    """Validate a config dict.

    Parameters
    ----------
    raw : dict
        The config, as read from TOML; sections left out take their defaults.
    base_dir : Path, optional
        Folder relative target paths are resolved against.
    source : str, optional
        Name of the config in messages (its file).

    Returns
    -------
    RunConfig
        The validated config.

    Raises
    ------
    ConfigError
        Naming every problem with its key path.
    """
    model = run_config_model()
    if "target" not in raw:
        raise ConfigError(
            f'{source}: no [target]: add the tree to fit, e.g. [target] qsm = "path/to/tree.mat" '
            '(relative to this file), or [target.generate] ssm = "sot" for a model-grown target'
        )
    raw = _fill_defaults(raw)
    problems, bad = _unknown_kinds(raw)  # every problem of the file, reported at once
    cfg = None
    try:
        cfg = model.model_validate({k: v for k, v in raw.items() if k not in bad})
    except pydantic.ValidationError as exc:
        text = validation_error_text(
            exc, raw, skip=tuple(bad), hint=lambda loc: did_you_mean(loc[-1], _allowed_keys(model, raw, loc))
        )
        if text:
            problems.append(text)
    if cfg is None or problems:
        raise ConfigError(f"{source}: " + "; ".join(problems))
    if base_dir is not None:
        if cfg.target.qsm is not None:
            cfg.target.qsm = resolve_path(cfg.target.qsm, base_dir)
        cfg.target.references = [resolve_path(r, base_dir) for r in cfg.target.references]
        if cfg.start.estimator not in (None, "shipped"):
            cfg.start.estimator = resolve_path(cfg.start.estimator, base_dir)
    for check in (check_ssm_parameters, check_generated_target, selection_config):
        try:
            check(cfg)
        except ConfigError as exc:
            problems.append(str(exc))
    if problems:
        raise ConfigError(f"{source}: " + "; ".join(problems))
    return cfg


def _unknown_kinds(raw: dict) -> tuple[list[str], set[str]]:
    """Return the components a config names that are not installed, and the keys to leave out.

    One message each; the top-level keys are left out of validation (their other problems are
    told once the name is right). The component sections (``kind``), the entries of ``[[objective.terms]]`` (their
    ``features``/``distance`` kinds) and ``[target.generate] ssm``.
    """
    reg, problems, bad = discover(), [], set()

    def unknown(where, kind, name):
        names = reg.names(kind)
        problems.append(
            f"{where}: unknown {kind} {name!r} (known: {', '.join(names) or 'none installed'}){did_you_mean(name, names)}"
        )

    for section, kind in SECTIONS.items():
        sec = raw.get(section)
        if isinstance(sec, dict) and "kind" in sec and sec["kind"] not in reg.names(kind):
            unknown(f"{section}.kind", kind, sec["kind"])
            bad.add(section)
    objective = raw.get("objective")
    terms = objective.get("terms") if isinstance(objective, dict) else None
    for i, t in enumerate(terms if isinstance(terms, list) else []):
        for kind in ("features", "distance"):
            part = t.get(kind) if isinstance(t, dict) else None
            if isinstance(part, dict) and isinstance(part.get("kind"), str) and part["kind"] not in reg.names(kind):
                unknown(f"objective.terms[{i}] ({t.get('name')}).{kind}", kind, part["kind"])
                bad.add("objective")
    target = raw.get("target")
    gen = target.get("generate") if isinstance(target, dict) else None
    if isinstance(gen, dict) and isinstance(gen.get("ssm"), str) and gen["ssm"] not in reg.names("ssm"):
        unknown("target.generate.ssm", "ssm", gen["ssm"])
        bad.add("target")
    return problems, bad


def resolve_path(path: str, base_dir: Path) -> str:
    """Return a file named in a config as an absolute path.

    Parameters
    ----------
    path : str
        As the config gives it: relative to its folder, absolute, ``~/...`` or ``sample:NAME``
        (kept as it is: it names a fetched sample wherever the config is).
    base_dir : Path
        The config's folder.

    Returns
    -------
    str
        The absolute path, or the ``sample:NAME``.
    """
    if is_sample(path):  # sample:NAME names a fetched sample wherever the config is
        return path
    p = Path(path).expanduser()
    return str(p if p.is_absolute() else (base_dir / p).resolve())


def load_config(path) -> BaseModel:
    """Read and validate a run configuration (TOML).

    Parameters
    ----------
    path : str or Path
        The config file; relative paths in it are resolved against its folder.

    Returns
    -------
    RunConfig
        The validated config.

    Raises
    ------
    ConfigError
        Naming the file, the key path and the allowed values.
    """
    path = Path(path)
    return parse_config(read_toml(path), base_dir=path.resolve().parent, source=str(path))


def read_toml(path) -> dict:
    """Read the TOML table of a config file.

    Parameters
    ----------
    path : str or Path
        The file.

    Returns
    -------
    dict
        The table.

    Raises
    ------
    ConfigError
        Naming the file, when it is missing, a folder, not text or not valid TOML.
    """
    path = Path(path)
    try:
        return tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError(f"{path}: file not found") from None
    except IsADirectoryError:
        raise ConfigError(f"{path}: is a folder, not a config file") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc})") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: not a text file") from None


def config_to_dict(cfg: RunConfig) -> dict:
    """Return the resolved config as plain data (``None`` values removed, so it writes as TOML).

    Parameters
    ----------
    cfg : RunConfig
        The config.

    Returns
    -------
    dict
        JSON-mode values.
    """

    def clean(x):
        if isinstance(x, dict):
            return {k: clean(v) for k, v in x.items() if v is not None}
        if isinstance(x, (list, tuple)):
            return [clean(v) for v in x]
        return x

    return clean(cfg.model_dump(mode="json"))


def dump_config(cfg: RunConfig, path) -> None:
    """Write the resolved config as TOML (see :func:`config_to_dict`).

    Parameters
    ----------
    cfg : RunConfig
        The config.
    path : str or Path
        The output file.
    """
    import tomli_w

    Path(path).write_text(tomli_w.dumps(config_to_dict(cfg)), encoding="utf-8")


def config_schema() -> dict:
    """Return the JSON schema of the run configuration with the installed plugins.

    Returns
    -------
    dict
        The schema.
    """
    return run_config_model().model_json_schema()
