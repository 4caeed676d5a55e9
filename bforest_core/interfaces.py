"""Abstract interfaces of the five parts of the method, plus executors.

Every component class has a class attribute ``kind`` (one of :data:`KINDS`), a ``name`` (what a
config's ``kind = "..."`` selects) and a pydantic ``Settings`` model (``extra="forbid"``) holding
its own options. ``bf.component(kind, name, **settings)`` validates the settings and returns an
instance; the instance keeps them in ``self.settings``.
"""

from __future__ import annotations

import abc
import math
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np
from pydantic import BaseModel, ConfigDict

from .errors import quiet_read_repairs
from .metrics import SIZE_LIMITS
from .processes import one_thread_process

if TYPE_CHECKING:
    from .envelope import CrownEnvelope
    from .metrics import TreeMeasures
    from .tree import Tree

KINDS = ("qsm_reader", "qsm_writer", "ssm", "features", "distance", "optimizer", "executor", "amortised")


class ComponentSettings(BaseModel):
    """Base of every component's settings model: unknown keys are errors, numbers finite.

    NaN or an infinity in a setting is an error naming the setting.
    """

    model_config = ConfigDict(extra="forbid", validate_assignment=True, allow_inf_nan=False)


class Component(abc.ABC):
    """Base of every pluggable component.

    Parameters
    ----------
    settings : ComponentSettings or mapping, optional
        The settings, as the class's ``Settings`` model or a mapping validated by it.
    **kwargs
        Settings that override those in ``settings``.

    Raises
    ------
    pydantic.ValidationError
        For unknown or invalid settings.
    """

    kind: ClassVar[str]
    name: ClassVar[str]
    Settings: ClassVar[type[ComponentSettings]] = ComponentSettings
    #: one-line description shown by ``bforest plugins``
    summary: ClassVar[str] = ""

    def __init__(self, settings: ComponentSettings | Mapping[str, Any] | None = None, **kwargs):
        if isinstance(settings, ComponentSettings):
            if kwargs:
                settings = settings.model_copy(update=kwargs)
        else:
            settings = self.Settings(**{**dict(settings or {}), **kwargs})
        self.settings = settings

    def __repr__(self) -> str:
        """Show the class name and every setting."""
        opts = ", ".join(f"{k}={v!r}" for k, v in self.settings.model_dump().items())
        return f"{type(self).__name__}({opts})"


# ------------------------------------------------------------------------------------ readers
class QSMReader(Component):
    """Reads one QSM file layout into a :class:`~bforest_core.Tree`.

    Readers are tried in turn by :func:`bforest_core.read_qsm`; ``sniff`` looks at the file's
    content (the suffix only narrows the candidates).
    """

    kind = "qsm_reader"
    #: file suffixes this reader may handle, lower case with the dot (".mat", ".txt", ...)
    suffixes: ClassVar[tuple[str, ...]] = ()
    #: Order among the readers of one suffix (optional, default 0): ``read_qsm`` tries the
    #: readers of a file's suffix from the highest priority down, so a reader of a specific
    #: layout goes before a lenient one of the same suffix.
    priority: ClassVar[int] = 0

    @abc.abstractmethod
    def sniff(self, path: Path, head: bytes) -> bool:
        """Tell whether the file is in this reader's layout.

        Parameters
        ----------
        path : Path
            The file.
        head : bytes
            Its first 4096 bytes.

        Returns
        -------
        bool
            True when this reader can read the file.
        """

    @abc.abstractmethod
    def read(self, path: Path, **options) -> Tree | list[Tree]:
        """Read the file.

        Parameters
        ----------
        path : Path
            The file.
        **options
            Options of :func:`bforest_core.read_qsm` (``select``, ``topology``, ``fragments``,
            ``drop_degenerate``), passed through.

        Returns
        -------
        Tree or list of Tree
            The tree, or the selected reconstructions.

        Raises
        ------
        QSMFormatError
            Naming the file and the problem.
        """


class QSMWriter(Component):
    """Writes a tree to one file format (chosen by suffix or ``format=`` name)."""

    kind = "qsm_writer"
    #: file suffixes this writer may write, lower case with the dot
    suffixes: ClassVar[tuple[str, ...]] = ()
    #: Which writer a suffix chooses when several write it (optional, default 0): the highest.
    priority: ClassVar[int] = 0

    @abc.abstractmethod
    def write(self, tree, path: Path, **options) -> Path:
        """Write ``tree`` to ``path``.

        Parameters
        ----------
        tree : Tree
            The tree.
        path : Path
            The output file.
        **options
            The writer's options.

        Returns
        -------
        Path
            The path written.
        """

    def write_plot(self, trees, path: Path, names=None, **options) -> Path:
        """Write several trees, each at its own place, to one file (a plot).

        ``bforest stand`` writes its synthetic stands so. Optional: a writer whose format holds
        one tree keeps this default.

        Parameters
        ----------
        trees : list of Tree
            The trees, in the plot's coordinates (m).
        path : Path
            The output file.
        names : list of str, optional
            The trees' names (groups, comments), default ``tree_0``, ``tree_1``, ...
        **options
            The writer's options.

        Returns
        -------
        Path
            The path written.

        Raises
        ------
        QSMFormatError
            The format holds one tree (this default).
        """
        from .errors import QSMFormatError

        raise QSMFormatError(
            path, f"the {self.name} format holds one tree, not a plot (write a plot as .ply, .obj, .las)"
        )


# ------------------------------------------------------------------------------------ SSM
@dataclass(frozen=True)
class ParameterSpec:
    """One growth-model parameter.

    Parameters
    ----------
    name : str
        The parameter's name.
    default : float
        Value when none is given.
    lower, upper : float
        The plausible range a fit may explore (and the default bounds of a ``free`` entry).
    integer : bool, optional
        Whether the parameter takes whole values.
    unit : str, optional
        Unit of the value (e.g. ``"m"``, ``"deg"``).
    description : str, optional
        What the parameter is, in words.
    group : str, optional
        Group the parameter is listed under.
    """

    name: str
    default: float
    lower: float
    upper: float
    integer: bool = False
    unit: str = ""
    description: str = ""
    group: str = ""


def parameter_value(value, integer: bool) -> int | float:
    """Return a parameter's value as a model takes it.

    For a whole-number parameter (``years``, say) an ``int``, rounded half to even, else a
    ``float``. The one rounding of a parameter: the fit's points, ``SSM.resolve_params``,
    profiles and posterior clones all round through it, so a model receives whole numbers and
    never rounds again.

    Parameters
    ----------
    value : float
        The value (a float from an optimiser, a config or a posterior draw).
    integer : bool
        Whether the parameter takes whole values (``ParameterSpec.integer``, or a ``free``
        entry's own ``integer``).

    Returns
    -------
    int or float
        The value.
    """
    return int(round(float(value))) if integer else float(value)


#: seconds of wall time a recipe's search may take (``RecipeDraft.wall_time``, ``[stop] wall_time``):
#: a safety net only, far above a normal fit (2-8 minutes on 2 cores), which stops on its evaluation
#: budget, so that the answer never depends on the machine's speed or load; a run that reaches it
#: is marked in ``best.json`` (``stop_kind = "wall_time"``) and warned of
SAFETY_WALL_TIME = 3600.0


@dataclass
class RecipeDraft:
    """A growth model's part of a recipe for one tree (:meth:`SSM.draft_recipe`).

    What the model asks of the recipe in no other plugin's terms: its own settings and search
    box, the size term's balance, the model seeds and the evaluation budget of the search and how
    the answer is chosen. The search's, the tables' and the size term's own settings are written
    by their plugins (:class:`RecipePart`) from these.

    Attributes
    ----------
    suits : float
        How well the model suits the tree, 0-1 (``bforest init`` without ``--model`` takes the
        model that suits it best).
    why : str
        One sentence saying why the model does or does not suit the tree.
    settings, fixed : list of (name, value, comment)
        Component settings and fixed parameter values.
    free : list of (name, lower, upper, comment)
        Bounds of the fitted parameters.
    scaled : dict
        Free parameters whose bounds are multiples of a measure of the tree (name -> a measure
        of ``[ssm] free.NAME.scaled_by``), written as such so that the recipe suits another tree
        of the same kind; resolved, and kept within the model's range, when the fit starts.
    timeout : float
        Seconds one growth may take before it counts as a failure.
    wall_time : float
        Seconds the search may take (``[stop] wall_time``): a safety net far above the normal run
        (:data:`SAFETY_WALL_TIME`); the search stops on its evaluation budget.
    notes : list of str
        What the user should know about this tree's recipe (printed and written as comments).
    size_weights : dict
        Weights of the size term's statistics where the model has its own calibrated balance
        (empty: the recipe's default, the inverse of the errors a forester tolerates).
    size_extra : dict
        Statistics the size term adds to the summary's default set (name -> weight).
    size_why : str
        Why the size term holds ``size_extra`` (written as a comment above the term).
    size_limits : dict
        A relative error per headline statistic (a fraction of the tree's value) beyond which its
        term grows ``size_steep`` times as fast, so that a fit cannot trade that statistic for
        structure past what a forester accepts (default: two thirds of each tolerance,
        ``metrics.SIZE_LIMITS``, the rule of both bundled models' recipes; empty: no limits).
    size_steep : float
        How many times as fast a term grows beyond its limit.
    seeds, max_evaluations : int
        Model seeds per evaluation (``[objective] seeds``) and the evaluation budget (``[stop]
        max_evaluations``), which the search's plugin plans its search by.
    select_top, select_sets : int
        The best distinct points grown again as candidate answers (``[select] top``) and the sets
        of held-out seeds each is grown with (``[select] sets``).
    select_tables : bool
        Whether the candidates are scored on the tables a clone is judged by (the features' and
        distance's plugins say which, :attr:`RecipePart.select`) rather than the search's own.
    select_sizes : dict
        A relative error per headline statistic that the candidates' held-out trees must keep on
        average to come first (``[select] sizes``; empty: none, the lowest held-out distance wins).
    search_why : str
        Why the model asks for its seeds and budget (written as a comment above the search).
    """

    suits: float
    why: str
    settings: list = field(default_factory=list)
    fixed: list = field(default_factory=list)
    free: list = field(default_factory=list)
    timeout: float = 20.0
    wall_time: float = SAFETY_WALL_TIME
    notes: list = field(default_factory=list)
    size_weights: dict = field(default_factory=dict)
    scaled: dict = field(default_factory=dict)
    size_extra: dict = field(default_factory=dict)
    size_why: str = ""
    size_limits: dict = field(default_factory=lambda: dict(SIZE_LIMITS))
    size_steep: float = 3.0
    seeds: int = 3
    max_evaluations: int = 1200
    select_top: int = 16
    select_sets: int = 16
    select_tables: bool = True
    select_sizes: dict = field(default_factory=dict)
    search_why: str = ""


@dataclass
class RecipePlan:
    """What a recipe asks of one component (the search, a term's tables or distance).

    In no plugin's terms: given to the component's :meth:`~FeatureSet.draft_recipe`.

    Attributes
    ----------
    term : str
        ``"structure"`` (the ``[features]``/``[distance]`` term: how branches look) or ``"size"``
        (the size term of ``[[objective.terms]]``: tree-level statistics); for an optimiser
        ``"search"``.
    draft : RecipeDraft
        The growth model's draft: its seeds per evaluation, budget, size term's balance.
    measures : TreeMeasures or None
        What the tree measured.
    dim : int
        The number of free parameters.
    start : bool
        For an optimiser: the search refines draws of an amortised estimator's posterior for the
        tree (``[start] estimator``, :attr:`Problem.start`) instead of exploring the whole box.
    """

    term: str
    draft: RecipeDraft
    measures: TreeMeasures | None = None
    dim: int = 0
    start: bool = False


@dataclass
class RecipePart:
    """A component's part of a recipe (:meth:`~FeatureSet.draft_recipe`): its section, in its own terms.

    Attributes
    ----------
    kind : str
        The component's name (the section's ``kind``).
    settings : list of (name, value, comment)
        The section's settings (comment None: none), written in order.
    why : str
        What the section does, written as a comment above it.
    select : dict
        Settings merged over the section when the candidate answers are scored on the tables a
        clone is judged by (``[select] features``/``distance``; empty: the search's own).
    select_why : str
        What those tables are, in a few words (``"S1 and B1 as sets of their own"``).
    reach : float or None
        The most this distance can reach for a grown tree (a failed growth must score above the
        objective's most: ``[objective] penalty``); None: not bounded by the recipe's settings.
    """

    kind: str
    settings: list = field(default_factory=list)
    why: str = ""
    select: dict = field(default_factory=dict)
    select_why: str = ""
    reach: float | None = None


class SSM(Component):
    """A stochastic structure (growth) model."""

    kind = "ssm"
    #: Version of the model's growth rules (optional, default ``"1"``): raise it when the same
    #: parameters and seed grow another tree than before. An amortised estimator records the
    #: version it was trained on and is refused by another (``bforest posterior``).
    model_version: ClassVar[str] = "1"

    @property
    @abc.abstractmethod
    def parameters(self) -> list[ParameterSpec]:
        """The model's parameter specs (for the current preset, if any)."""

    @abc.abstractmethod
    def simulate(self, params: Mapping[str, float], seed: int) -> Tree:
        """Grow one tree.

        Parameters
        ----------
        params : mapping
            Values by parameter name; missing names take their defaults, unknown names raise
            ``ValueError`` naming them.
        seed : int
            Seeds the model's single ``numpy.random.Generator``: the same params and seed give a
            bit-identical tree.

        Returns
        -------
        Tree
            With its growth topology (``source``) and metadata (``model``, ``params``, ``seed``,
            ``status``).

        Raises
        ------
        SimulationFailed
            For any non-ok status.
        """

    def draft_recipe(self, measures: TreeMeasures) -> RecipeDraft | None:
        """Draft this model's part of a recipe for a measured tree (optional, ``bforest init``).

        Parameters
        ----------
        measures : TreeMeasures
            What the tree measures (height, crown, branch angles, crown form; see
            :func:`bforest_core.metrics.measure_tree`).

        Returns
        -------
        RecipeDraft or None
            Settings, fixed values and free bounds, each with the comment saying what in the
            tree set it, and how well the model suits the tree; None (the default) when the
            model writes no recipes.
        """
        return None

    def crown_space(self, params: Mapping[str, float]) -> CrownEnvelope | None:
        """Return the crown's space the model grows its trees in (optional).

        Parameters
        ----------
        params : mapping
            Parameter values by name (missing names take their defaults).

        Returns
        -------
        CrownEnvelope or None
            The envelope (:mod:`bforest_core.envelope`) outside which the model's trees get no
            light with these parameters; None (the default) when they grow in an open world. The
            report draws it beside the tree and its clones.
        """
        return None

    def parameter_spec(self, name: str) -> ParameterSpec:
        """Return the spec of one parameter.

        Parameters
        ----------
        name : str
            The parameter's name.

        Returns
        -------
        ParameterSpec
            Its spec.

        Raises
        ------
        KeyError
            For an unknown name (listing the known ones).
        """
        for p in self.parameters:
            if p.name == name:
                return p
        raise KeyError(f"{self.name} has no parameter {name!r} (known: {', '.join(p.name for p in self.parameters)})")

    def defaults(self) -> dict[str, float]:
        """Return the default value of every parameter.

        Returns
        -------
        dict of str to float
            Default by parameter name.
        """
        return {p.name: p.default for p in self.parameters}

    def resolve_params(self, params: Mapping[str, float]) -> dict[str, float]:
        """Return the defaults overridden by ``params``.

        Parameters
        ----------
        params : mapping
            Values by parameter name.

        Returns
        -------
        dict
            Every parameter's value; integer parameters rounded (:func:`parameter_value`) and
            returned as ``int``.

        Raises
        ------
        ValueError
            Naming the parameter, for an unknown name or a value that is not a finite number.
        """
        known = self.defaults()
        unknown = sorted(set(params) - set(known))
        if unknown:
            raise ValueError(
                f"unknown parameter(s) for SSM '{self.name}': {', '.join(unknown)} (known: {', '.join(known)})"
            )
        out = dict(known)
        out.update(params)
        for p in self.parameters:
            v = out[p.name]
            try:
                fv = float(v)
            except (TypeError, ValueError):
                raise ValueError(f"parameter {p.name!r} of SSM '{self.name}' must be a number, got {v!r}") from None
            if not math.isfinite(fv):
                raise ValueError(f"parameter {p.name!r} of SSM '{self.name}' must be finite, got {v!r}")
            if p.integer:
                out[p.name] = parameter_value(fv, integer=True)
        return out


class RecipeWriter:
    """A component that may write its part of a recipe: a feature set, a distance, an optimiser.

    ``bforest init`` asks the kinds of ``config.RECIPE_KINDS`` for their parts.
    """

    def draft_recipe(self, plan: RecipePlan) -> RecipePart | None:
        """Write this component's part of a recipe (optional, ``bforest init``).

        Parameters
        ----------
        plan : RecipePlan
            What the recipe asks of it: its term (or the search), the growth model's draft
            (seeds per evaluation, budget, the size term's balance), the tree's measures.

        Returns
        -------
        RecipePart or None
            Its section's settings, each with its comment, and what it does; None (the default)
            when the component writes no recipes (``bforest init`` takes the bundled one of
            ``config.RECIPE_KINDS``).
        """
        return None


# ------------------------------------------------------------------------------------ features
class FeatureSet(RecipeWriter, Component):
    """Turns a tree into named tables of multi-dimensional points (structural data sets U)."""

    kind = "features"

    def summary_rule(self) -> tuple[str | None, list[str] | None] | None:
        """Return the branch rule of a feature set of tree-level statistics (optional).

        The clones' fidelity table measures the statistics as the fit's size term held them.

        Returns
        -------
        tuple or None
            ``(topology, statistics)``: the rule the statistics are measured by (None: each
            tree's own branches) and which of them (None: all); None (the default) for a feature
            set that does not summarise whole trees.
        """
        return None

    @property
    @abc.abstractmethod
    def set_names(self) -> list[str]:
        """Names of the data sets this feature set produces, in order."""

    def prepare(self, data_trees: Sequence[Tree]) -> None:
        """Resolve data-dependent choices and check minimum sizes on the data tree(s).

        Called once at set-up (e.g. resolves ``"2+"`` orders). Default: nothing to do.

        Parameters
        ----------
        data_trees : sequence of Tree
            The data tree(s) (repeated reconstructions of one tree).
        """

    def resolved_settings(self) -> dict:
        """Return the settings with the data-dependent choices of :meth:`prepare` resolved.

        A model-side instance built from them extracts exactly the same tables.

        Returns
        -------
        dict
            The settings (default: as given).
        """
        return self.settings.model_dump()

    @abc.abstractmethod
    def extract(self, tree) -> dict[str, np.ndarray]:
        """Extract the data sets of one tree.

        Parameters
        ----------
        tree : Tree
            The tree.

        Returns
        -------
        dict of str to ndarray
            Set name -> ``(n_i, d_i)`` float64 array (rows with NaN dropped per ``nan_policy``).
        """

    def extract_pooled(self, trees: Sequence[Tree]) -> dict[str, np.ndarray]:
        """Extract the data sets of several trees, rows pooled per set (repeated reconstructions).

        Parameters
        ----------
        trees : sequence of Tree
            The trees.

        Returns
        -------
        dict of str to ndarray
            Set name -> the trees' rows stacked.
        """
        parts = [self.extract(t) for t in trees]
        return {k: np.concatenate([p[k] for p in parts], axis=0) for k in self.set_names}

    @abc.abstractmethod
    def columns(self, set_name: str) -> list[str]:
        """Return the column names of one set.

        Circular pairs are named ``"sin(x)"``, ``"cos(x)"`` so a distance can scale each pair
        jointly.

        Parameters
        ----------
        set_name : str
            One of :attr:`set_names`.

        Returns
        -------
        list of str
            One name per column.
        """


# ------------------------------------------------------------------------------------ distance
class Distance(RecipeWriter, Component):
    """A structural distance between model and data tables."""

    kind = "distance"

    def prepare(self, U_data: Mapping[str, np.ndarray], columns: Mapping[str, list[str]] | None = None) -> None:
        """Fit normalisation on the data side and cache data-side work once per run.

        Parameters
        ----------
        U_data : mapping of str to ndarray
            The data tables by set name.
        columns : mapping of str to list of str, optional
            Column names by set name (see :meth:`FeatureSet.columns`).
        """

    @abc.abstractmethod
    def compute(self, u_model: np.ndarray, u_data: np.ndarray) -> float:
        """Compute the distance of one pair of tables.

        Parameters
        ----------
        u_model : ndarray, shape (n, d)
            The model table.
        u_data : ndarray, shape (m, d)
            The data table.

        Returns
        -------
        float
            The distance.
        """

    def compute_per_set(
        self, U_model: Mapping[str, np.ndarray], U_data: Mapping[str, np.ndarray]
    ) -> dict[str, float | None]:
        """Compute the distance of every set.

        Parameters
        ----------
        U_model, U_data : mapping of str to ndarray
            Tables by set name (the same sets on both sides).

        Returns
        -------
        dict of str to float or None
            Distance by set name; ``None`` for a pair that is skipped (both sides empty).

        Raises
        ------
        ValueError
            If the two sides have different sets.
        """
        if set(U_model) != set(U_data):
            raise ValueError(f"model sets {sorted(U_model)} differ from data sets {sorted(U_data)}")
        return {k: self.compute_pair(k, U_model[k], U_data[k]) for k in U_data}

    def compute_pair(self, set_name: str, u_model: np.ndarray, u_data: np.ndarray) -> float | None:
        """Compute the distance of one named pair (lets implementations use per-set prepared state).

        Parameters
        ----------
        set_name : str
            The set the pair belongs to.
        u_model, u_data : ndarray
            The model and data tables.

        Returns
        -------
        float or None
            The distance; ``None`` for a skipped pair.
        """
        return self.compute(u_model, u_data)

    @staticmethod
    def combine(per_set: Mapping[str, float | None], weights: Mapping[str, float] | None = None) -> float:
        """Combine per-set distances into their weighted mean over the pairs that take part.

        Parameters
        ----------
        per_set : mapping of str to float or None
            Distance by set name; ``None`` marks a skipped pair, which leaves the normalisation.
        weights : mapping of str to float, optional
            Set weights (default 1 each).

        Returns
        -------
        float
            The weighted mean; 0.0 when every pair is skipped.
        """
        num = den = 0.0
        for k, v in per_set.items():
            if v is None:
                continue
            w = 1.0 if weights is None else float(weights.get(k, 1.0))
            num += w * v
            den += w
        return num / den if den > 0 else 0.0

    def compute_sets(self, U_model, U_data, weights=None) -> float:
        """Compute the weighted mean distance over sets (docs/features-and-distance.md §4.5).

        Parameters
        ----------
        U_model, U_data : mapping of str to ndarray
            Tables by set name.
        weights : mapping of str to float, optional
            Set weights.

        Returns
        -------
        float
            The distance.
        """
        return self.combine(self.compute_per_set(U_model, U_data), weights)


class LineDistance(Distance):
    """A distance that compares the tables on projection lines (a sliced distance).

    What only such a distance has, which the run folder (its directions and frozen data-side
    transforms), the report (the worst lines) and ``bforest distance --test`` use where a
    distance is one (``isinstance(dist, LineDistance)``).
    """

    @abc.abstractmethod
    def directions(self, d: int) -> np.ndarray:
        """Return the unit vectors the distance projects on.

        Parameters
        ----------
        d : int
            Number of columns of the tables.

        Returns
        -------
        ndarray, shape (lines, d)
            The directions.
        """

    @property
    def statistic(self) -> str:
        """Name of the one-dimensional statistic compared on each line.

        Returns
        -------
        str
            Default ``"ks"``: the report then computes the Kolmogorov-Smirnov gap per line itself.
        """
        return "ks"

    def line_values(self, u_model: np.ndarray, u_data: np.ndarray, set_name: str | None = None) -> np.ndarray:
        """Per-line values of the statistic for one pair of tables (optional).

        Parameters
        ----------
        u_model, u_data : ndarray
            ``(n, d)`` tables, both non-empty (data side second, as in :meth:`compute`).
        set_name : str, optional
            The set the pair belongs to, so a prepared set's frozen transform is used.

        Returns
        -------
        ndarray
            ``(lines,)`` values, one per row of :meth:`directions`.

        Raises
        ------
        NotImplementedError
            By default: the report computes the statistic per line itself.
        """
        raise NotImplementedError(f"distance '{self.name}' has no per-line values")

    def normalizations(self) -> dict[str, dict]:
        """Return the frozen data-side transforms of the prepared sets (optional).

        Returns
        -------
        dict
            Set name -> ``{"method", "center", "scale", ...}`` as fitted by :meth:`prepare`
            (the fit keeps it in the run folder). Default ``{}``: the distance compares the
            tables in their own units.
        """
        return {}

    def permutation_test(
        self,
        U_model: Mapping[str, np.ndarray],
        U_data: Mapping[str, np.ndarray],
        weights: Mapping[str, float] | None = None,
        *,
        seed: int = 0,
    ):
        """Whether the model tables can be told from the data tables (optional).

        Parameters
        ----------
        U_model, U_data : mapping
            Tables by set name.
        weights : mapping, optional
            Set weights, as in :meth:`compute_sets`.
        seed : int
            Seeds the shuffles.

        Returns
        -------
        object
            With ``summary()`` (one line), ``per_set`` and ``per_set_holm`` (set -> p-value).

        Raises
        ------
        NotImplementedError
            By default: the distance offers no permutation test (``bforest distance --test``
            then says so).
        """
        raise NotImplementedError(f"distance '{self.name}' offers no permutation test")


# ------------------------------------------------------------------------------------ optimiser
@dataclass
class Problem:
    """Describe what an optimiser sees: a bounded box, integer flags and a batch objective.

    ``evaluate(X)`` takes a ``(k, p)`` array of points (in parameter order ``names``), evaluates
    them (in parallel through the run's executor, logging each to the run store) and returns
    ``k`` objective values. Once a stop criterion (budget, wall time, target) is met,
    ``evaluate`` evaluates what still fits in the budget, sets ``stopped`` and returns; the
    optimiser must then return its best point. Integer parameters are rounded by ``evaluate``.

    Parameters
    ----------
    names : list of str
        The free parameters, in order.
    lower, upper : ndarray
        Bounds of the box, one per parameter.
    integer : ndarray of bool
        Which parameters take whole values.
    evaluate : callable
        The batch objective, as above.
    init_lower, init_upper : ndarray, optional
        Box to draw initial points from (default: the bounds).
    seed : int, optional
        Seeds the optimiser.
    max_evaluations : int, optional
        The evaluation budget (see the attribute).
    stopped, n_evaluations, best_x, best_f, stop_reason
        Progress state, maintained by ``evaluate``.
    log, seed_spread, summaries, target_summaries, start
        Callbacks and data, see the attributes.
    """

    names: list[str]
    lower: np.ndarray
    upper: np.ndarray
    integer: np.ndarray
    evaluate: Callable[[np.ndarray], np.ndarray]
    init_lower: np.ndarray | None = None
    init_upper: np.ndarray | None = None
    seed: int = 0
    #: the evaluation budget, by its one name (a fit's ``[stop] max_evaluations``; ``None``: none).
    #: ``evaluate`` enforces it (it evaluates what still fits, then sets ``stopped``); an optimiser
    #: reads ``remaining()`` to plan and ``stopped`` to end, and keeps no budget setting of its own
    max_evaluations: int | None = None
    # progress state, maintained by the caller's evaluate
    stopped: bool = False
    n_evaluations: int = 0
    best_x: np.ndarray | None = None
    best_f: float = math.inf
    stop_reason: str = ""
    #: diagnostics callback; optimisers call ``problem.log(dict)`` once per generation/iteration
    log: Callable[[dict], None] = field(default=lambda rec: None)
    #: ``seed_spread(x, k)`` -> ``k`` objective values of the point ``x`` under ``k`` model seeds
    #: other than the fit's own: the objective's seed noise, i.e. what a perfect model would still
    #: show. Deterministic for a given ``x`` and ``k``; not logged and not counted in
    #: ``n_evaluations``. ``None`` where the caller cannot provide it.
    seed_spread: Callable[[np.ndarray, int], np.ndarray] | None = None
    #: ``summaries(X)`` -> ``(k, m)`` summary statistics of the trees of ``k`` points the run has
    #: evaluated, regrown with their logged model seeds (per data set of every term: the log of one
    #: plus its rows and its columns' means, averaged over the seeds; a row of NaN where the
    #: simulation fails); ``target_summaries`` the same ``m`` statistics of the target. For a
    #: sampler's regression adjustment (``abc-smc``, ``adjust = "linear"``). Not logged and not
    #: counted in ``n_evaluations``. ``None`` where the caller cannot provide them.
    summaries: Callable[[np.ndarray], np.ndarray] | None = None
    target_summaries: np.ndarray | None = None
    #: ``(k, p)`` points to start from, inside the bounds, best guesses first: draws of an
    #: amortised estimator's posterior for the target (``[start] estimator``). An optimiser with
    #: an initial design (``cma``'s ``init_design``) evaluates these in its place; ``None``: none.
    start: np.ndarray | None = None

    @property
    def dim(self) -> int:
        """Number of free parameters."""
        return len(self.names)

    def init_box(self):
        """Return the box initial points are drawn from.

        Returns
        -------
        lower, upper : ndarray of float
            ``init_lower``/``init_upper`` where given, else the bounds.
        """
        lo = self.lower if self.init_lower is None else self.init_lower
        hi = self.upper if self.init_upper is None else self.init_upper
        return np.asarray(lo, float), np.asarray(hi, float)

    def remaining(self) -> int | None:
        """Return the evaluations left in the budget.

        Returns
        -------
        int or None
            Evaluations left (at least 0); ``None`` without a budget.
        """
        return None if self.max_evaluations is None else max(0, self.max_evaluations - self.n_evaluations)


#: the kinds of posterior a sampler gives (:attr:`Optimizer.posterior_kind`)
POSTERIOR_KINDS = ("chain", "population")


@dataclass(frozen=True)
class Posterior:
    """A sampler's posterior over the free parameters, as one typed object.

    A sampler's result carries it in its diagnostics (the keys :attr:`Optimizer.posterior_kind`
    lists, which a run folder stores); :meth:`from_diagnostics` is the one place they are read.

    Parameters
    ----------
    kind : {"chain", "population"}
        ``chain``: the walkers of an MCMC sampler, each walker a chain; ``population``: the
        weighted particles of an SMC/ABC sampler.
    samples : ndarray
        ``(n, p)``: one row per posterior draw (a chain's draws after burn-in, every walker's).
    weights : ndarray
        ``(n,)``, summing to 1 (equal for a chain).
    names : tuple of str
        The parameters, in the order of the columns.
    chain : ndarray or None
        ``(steps, walkers, p)``: a chain's every step, burn-in included.
    burn_in : int
        A chain's steps before its draws count.
    distances : ndarray or None
        Distances of a chain's steps ``(steps, walkers)`` or of a population's particles ``(n,)``.
    """

    kind: str
    samples: np.ndarray
    weights: np.ndarray
    names: tuple
    chain: np.ndarray | None = None
    burn_in: int = 0
    distances: np.ndarray | None = None

    @classmethod
    def from_diagnostics(cls, diag, names, kind: str | None = None) -> Posterior | None:
        """Read the posterior in a sampler's diagnostics (None when they hold none).

        Parameters
        ----------
        diag : dict
            A sampler's diagnostics (``OptimizeResult.diagnostics``, a run's stored ones):
            ``particles`` and ``weights`` (with ``distances``), or ``chain`` with ``burn_in`` (and
            ``distances``); ``names`` there, when present, name the columns.
        names : sequence of str
            The fitted parameters, when the diagnostics do not name them.
        kind : {"chain", "population"}, optional
            The sampler's declared kind; else the diagnostics' keys tell (a run written before
            samplers declared it).
        """
        if not isinstance(diag, dict):
            return None
        has_population = diag.get("particles") is not None and diag.get("weights") is not None
        if kind not in POSTERIOR_KINDS:
            kind = "population" if has_population else "chain" if diag.get("chain") is not None else None
        names = tuple(diag.get("names") or names)
        try:
            if kind == "population" and has_population:
                X = np.asarray(diag["particles"], float)
                w = np.asarray(diag["weights"], float)
                if X.ndim != 2 or X.shape[1] != len(names) or w.shape != (X.shape[0],) or not w.sum() > 0:
                    return None
                d = diag.get("distances")
                d = np.asarray(d, float) if d is not None and np.shape(d) == (X.shape[0],) else None
                return cls("population", X, w / w.sum(), names, distances=d)
            if kind == "chain" and diag.get("chain") is not None:
                chain = np.asarray(diag["chain"], float)
                if chain.ndim == 2:  # one walker
                    chain = chain[:, None, :]
                if chain.ndim != 3 or 0 in chain.shape[:2] or chain.shape[2] != len(names):
                    return None
                burn = min(max(int(diag.get("burn_in") or 0), 0), chain.shape[0] - 1)
                X = chain[burn:].reshape(-1, chain.shape[2])
                d = diag.get("distances")
                d = np.asarray(d, float) if d is not None and np.shape(d) == chain.shape[:2] else None
                return cls("chain", X, np.full(X.shape[0], 1.0 / X.shape[0]), names, chain, burn, d)
        except (TypeError, ValueError):
            return None
        return None

    def draws(self) -> dict[str, np.ndarray]:
        """Return per parameter an array (chain, draw), as ArviZ takes a posterior.

        A chain's walkers after burn-in; for weighted particles, one chain of a deterministic
        systematic resample by weight.
        """
        if self.kind == "chain":
            kept = self.chain[self.burn_in :].transpose(1, 0, 2)  # (walkers, steps, p)
            return {n: kept[:, :, j] for j, n in enumerate(self.names)}
        n = self.samples.shape[0]
        idx = np.searchsorted(np.cumsum(self.weights), (np.arange(n) + 0.5) / n).clip(0, n - 1)
        return {name: self.samples[idx, j][None, :] for j, name in enumerate(self.names)}


@dataclass
class OptimizeResult:
    """Outcome of one optimisation.

    Parameters
    ----------
    x : ndarray
        The best point found.
    fun : float
        Its objective value.
    n_evaluations : int
        Evaluations spent.
    stop_reason : str, optional
        Why the search ended.
    history : list of dict, optional
        Per generation/iteration records.
    diagnostics : dict, optional
        Optimiser-specific results (a sampler's posterior sample, ...).
    """

    x: np.ndarray
    fun: float
    n_evaluations: int
    stop_reason: str = ""
    history: list[dict] = field(default_factory=list)
    diagnostics: dict[str, Any] = field(default_factory=dict)

    def posterior(self, names, kind: str | None = None) -> Posterior | None:
        """Return the sampler's posterior (:meth:`Posterior.from_diagnostics`), None for an optimiser."""
        return Posterior.from_diagnostics(self.diagnostics, names, kind)


class Optimizer(RecipeWriter, Component):
    """Minimises a :class:`Problem`."""

    kind = "optimizer"

    #: True for a sampler to which a failed simulation (collapsed, too large, timed out) is a tree
    #: that matches nothing: ``evaluate`` (and ``seed_spread``) then return ``inf`` for it instead of
    #: the config's ``[objective] penalty``, which an optimiser needs as a finite value but a
    #: sampler could accept as a good fit once its tolerance is above it (the store still logs the
    #: penalty and the status).
    failures_as_inf: bool = False

    # --- what a sampler's posterior is (the report's wording and figures) ---------------------
    #: The kind of posterior sample a sampler gives, the one declaration that it is a sampler (its
    #: result's diagnostics carry the sample: the fit writes posterior.csv, ``bforest calibrate``
    #: accepts it), stored in ``best.json`` so the report words and draws it without knowing the
    #: sampler:
    #:
    #: ``"chain"``
    #:     MCMC: ``diagnostics["chain"]`` ``(steps, walkers, parameters)`` and ``burn_in``; the
    #:     posterior is every walker's draws after burn-in, each walker a chain.
    #: ``"population"``
    #:     SMC/ABC: ``diagnostics["particles"]`` with ``weights``; a weighted population per
    #:     generation, with ``epsilon``, ``acceptance`` and ``ess`` lists per generation.
    #: ``None``
    #:     no posterior (an optimiser).
    #:
    #: A sampler that stops short of its own target (a tolerance above its target, a cap on
    #: generations, evaluations or time before it finished) says why in one line in
    #: ``diagnostics["stopped_short"]``; the report and ``bforest fit`` print it as a warning.
    posterior_kind: ClassVar[str | None] = None

    @abc.abstractmethod
    def minimize(self, problem: Problem) -> OptimizeResult:
        """Search the box for the minimum.

        Must be deterministic given ``problem.seed`` and the values returned by
        ``problem.evaluate`` (the run store replays evaluations on resume).

        Parameters
        ----------
        problem : Problem
            The box and objective.

        Returns
        -------
        OptimizeResult
            The best point and how the search went.
        """

    def takes_start(self) -> bool:
        """Whether the search evaluates ``Problem.start``'s points first (optional).

        Returns
        -------
        bool
            Default False: the optimiser starts on its own (a fit with ``[start] estimator`` is
            then refused, naming the optimiser).
        """
        return False

    def expected_evaluations(self, dim: int) -> int | None:
        """Return the evaluations a run plans when no stop comes first (optional).

        Parameters
        ----------
        dim : int
            Number of free parameters.

        Returns
        -------
        int or None
            What the settings let a run evaluate at most (the fit's progress bar counts to the
            smaller of it and ``Problem.max_evaluations``). Default ``None``: unknown in advance.
        """
        return None

    @classmethod
    def budget_settings(cls, settings: Mapping[str, Any], budget: int) -> dict[str, Any]:
        """Return settings under which ``Problem.max_evaluations``, not the optimiser's limits, ends a run.

        ``bforest compare`` runs every optimiser on the same evaluation budget: each optimiser
        lifts (or sets to the budget) its own limits, such as a number of generations,
        iterations or steps, and keeps every other setting, so the compared runs are the
        configured searches cut at equal budgets.

        Parameters
        ----------
        settings : mapping
            The optimiser's settings (without ``kind``), as a config gives them.
        budget : int
            The evaluations each run may spend.

        Returns
        -------
        dict
            The settings to run with. Default: ``settings`` unchanged (an optimiser whose only
            length limit is ``Problem.max_evaluations``).
        """
        return dict(settings)


# ------------------------------------------------------------------------------------ executor
class Executor(Component):
    """Runs evaluations, possibly in parallel.

    Usage::

        with executor.started(initializer, initargs):
            for index, result in executor.map_unordered(fn, items):
                ...
    """

    kind = "executor"

    #: Optional hooks, honoured by an executor that can stop a worker stuck in a task (the
    #: ``process`` executor) and ignored by others; the fit sets them before :meth:`start`.
    #: ``time_limit(item)`` -> seconds the task of ``item`` may run (None: no limit).
    time_limit: Callable[[Any], float | None] | None = None
    #: ``on_lost(fn, item, status, message)`` -> the stand-in result of a task whose worker died
    #: or was stopped, or ``NotImplemented`` (the executor then raises ``WorkerLost``).
    on_lost: Callable[..., Any] | None = None

    @property
    def workers(self) -> int:
        """Evaluations that run at once (default 1)."""
        return 1

    @abc.abstractmethod
    def start(self, initializer: Callable | None = None, initargs: tuple = ()) -> None:
        """Start workers.

        Parameters
        ----------
        initializer : callable, optional
            Runs once in each worker (loads the target).
        initargs : tuple, optional
            Its arguments.
        """

    @abc.abstractmethod
    def map_unordered(self, fn: Callable, items: Sequence) -> Iterator[tuple[int, Any]]:
        """Run ``fn`` on every item, yielding results as each finishes.

        Parameters
        ----------
        fn : callable
            The task.
        items : sequence
            Its arguments, one per task.

        Yields
        ------
        tuple of (int, object)
            ``(index, fn(items[index]))``.
        """

    def map(self, fn: Callable, items: Sequence) -> list:
        """Run ``fn`` on every item and return the results in order.

        Parameters
        ----------
        fn : callable
            The task.
        items : sequence
            Its arguments, one per task.

        Returns
        -------
        list
            ``fn(item)`` for each item, in the order of ``items``.
        """
        out = [None] * len(items)
        for i, r in self.map_unordered(fn, items):
            out[i] = r
        return out

    def shutdown(self) -> None:
        """Stop workers."""

    @staticmethod
    def worker_setup() -> None:
        """Prepare a worker process.

        An executor calls it in each worker before the initializer (the ``process`` and ``dask``
        executors do).

        It limits the worker to one BLAS/OpenMP thread (:meth:`limit_worker_threads`) and keeps
        a QSM's read repairs quiet there (:func:`~bforest_core.errors.quiet_read_repairs`).
        """
        Executor.limit_worker_threads()
        quiet_read_repairs()

    @staticmethod
    def limit_worker_threads() -> None:
        """Limit this process to one BLAS/OpenMP thread.

        Workers that together keep every core busy would only have their own thread pools
        compete with the other workers (:meth:`worker_setup` calls it).
        """
        one_thread_process()

    def started(self, initializer: Callable | None = None, initargs: tuple = ()):
        """Return a context manager that starts the workers and shuts them down on exit.

        Parameters
        ----------
        initializer : callable, optional
            Runs once in each worker (see :meth:`start`).
        initargs : tuple, optional
            Its arguments.

        Returns
        -------
        context manager
            Entering it calls :meth:`start` and gives the executor; leaving it calls
            :meth:`shutdown`.
        """
        return _Started(self, initializer, initargs)


class _Started:
    def __init__(self, ex, init, args):
        self.ex, self.init, self.args = ex, init, args

    def __enter__(self):
        self.ex.start(self.init, self.args)
        return self.ex

    def __exit__(self, *exc):
        self.ex.shutdown()
        return False


# ------------------------------------------------------------------------------------ amortised
class AmortisedEstimator(Component):
    """A conditional density estimator of a growth model's parameters given a tree's summaries.

    Trained once on simulations from a prior (``bforest train``), it then gives a posterior for
    any tree in one pass (amortised simulation-based inference; ``bforest posterior``). The
    pipeline draws the prior, grows and summarises the trees and writes the estimator's file; the
    component only learns the density and draws from it. Parameters arrive in their own units
    within ``[lower, upper]``; what the component does inside (transforms, standardisation) is its
    own and travels in its state.
    """

    kind = "amortised"

    def missing(self) -> str | None:
        """Say what to install when the estimator's libraries are missing (optional).

        Returns
        -------
        str or None
            One line naming what to install (``pip install 'bayesforest[amortised]'``), or None
            (the default) when the estimator can run.
        """
        return None

    def library_versions(self) -> dict[str, str]:
        """Return the versions of the libraries the estimator runs on (optional, default none).

        Returns
        -------
        dict of str to str
            Library name -> version, recorded in a trained estimator's file.
        """
        return {}

    @abc.abstractmethod
    def train(self, theta: np.ndarray, x: np.ndarray, lower, upper, integer, seed: int) -> dict:
        """Learn the density of ``theta`` given ``x``.

        Parameters
        ----------
        theta : ndarray, shape (n, p)
            Parameter vectors drawn from the prior, within ``[lower, upper]``.
        x : ndarray, shape (n, m)
            The summaries of the tree each grew (finite).
        lower, upper : ndarray, shape (p,)
            Bounds of the prior's support.
        integer : ndarray of bool, shape (p,)
            Parameters that take whole values.
        seed : int
            Seeds every random choice of the training.

        Returns
        -------
        dict
            What the training did (JSON values: epochs, losses, seconds), kept in the file.
        """

    @abc.abstractmethod
    def sample(self, x: np.ndarray, n: int, seed: int) -> np.ndarray:
        """Draw from the posterior of each row of ``x``.

        Parameters
        ----------
        x : ndarray, shape (k, m)
            Summaries of ``k`` trees.
        n : int
            Draws per tree.
        seed : int
            Seeds the draws: the same ``x``, ``n`` and seed give the same draws.

        Returns
        -------
        ndarray, shape (k, n, p)
            Draws within ``[lower, upper]``, whole numbers for integer parameters.

        Raises
        ------
        RuntimeError
            Before the estimator is trained or loaded.
        """

    @abc.abstractmethod
    def state(self) -> tuple[dict, bytes]:
        """Return the trained estimator as data.

        Returns
        -------
        meta : dict
            JSON values (dimensions, bounds, transforms) that :meth:`load_state` needs.
        blob : bytes
            The learned weights.
        """

    @abc.abstractmethod
    def load_state(self, meta: dict, blob: bytes) -> None:
        """Restore a trained estimator from :meth:`state`'s output (with the same settings).

        Parameters
        ----------
        meta : dict
            As :meth:`state` returned it.
        blob : bytes
            As :meth:`state` returned it.
        """

    @classmethod
    def shipped(cls) -> dict[str, Path]:
        """Return the trained estimator files shipped with the plugin (optional, default none).

        Returns
        -------
        dict of str to Path
            A growth model's name -> its file; ``bforest posterior --model NAME`` takes it when no
            ``--estimator`` is given.
        """
        return {}


INTERFACES = {
    "qsm_reader": QSMReader,
    "qsm_writer": QSMWriter,
    "ssm": SSM,
    "features": FeatureSet,
    "distance": Distance,
    "optimizer": Optimizer,
    "executor": Executor,
    "amortised": AmortisedEstimator,
}
