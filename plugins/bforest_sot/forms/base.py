"""The growth-form interface of the SOT model: an optional form of growth as one object.

The papers' model (docs/models.md part B) is the growth loop of :mod:`bforest_sot.model`; every
addition to it (opposite buds, dying leaders, short shoots, a stem along a measured path, a
stand's or a gap's shade, winding axes) is a :class:`GrowthForm` of its own module in this
package, and a third party adds one the same way (docs/growth-forms.md, "A growth form of your
own"). A form

* declares its parameters (``parameters``), listed with the model's in their group, and checks
  their values (``check``);
* says whether it acts on a run (``acts``): a form that does not is not made, so the tree is the
  one without it, draw for draw;
* draws from its own random stream (``stream``): a key of its own gives it a generator of the
  run's seed and that key (``numpy.random.SeedSequence(seed, spawn_key=(key,))``), so the
  growth's draws stay as they are; ``GROWTH_STREAM`` hands it the growth's own generator, its
  draws taking their place in the growth's draw order (docs/models.md B.7) at its hook: the
  three forms that predate this interface (dying leaders, short shoots, winding) keep their
  trees so, bit for bit; a new form takes a key of its own;
* hooks into the growth step by overriding the methods below; the run calls the hooks a form
  overrides, in the order of the model's ``forms``, and nothing else of it.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, ClassVar

import numpy as np

from bforest_core.interfaces import ParameterSpec

if TYPE_CHECKING:
    from ..model import BudChoice, Shoots, SOTGrowth

#: a form's ``stream``: the growth's own generator (the draws at the form's hook are part of the
#: growth's draw order, docs/models.md B.7)
GROWTH_STREAM = "growth"

#: the hooks of a form, in the order a growth cycle reaches them
HOOKS = (
    "seeded",
    "begin_cycle",
    "cycle_lambda",
    "transmission",
    "select_buds",
    "plan_shoots",
    "shape_shoots",
    "bend",
    "metamers_added",
    "rows_made",
    "shoots_built",
)

#: ``need(ok, name, rule)``: raise the model's ValueError naming parameter ``name`` unless ``ok``
Need = Callable[[bool, str, str], None]


class GrowthForm:
    """One optional growth form of SOT: its parameters, its random stream, its hooks.

    Made once per run (``form(run, rng)``) when :meth:`acts` says so; ``self.run`` is the
    :class:`~bforest_sot.model.SOTGrowth` (its store ``run.s``, light field ``run.field``,
    parameters ``run.p``, settings ``run.settings``), ``self.rng`` the form's generator.
    """

    #: the form's parameters (their ``group`` places them among the model's, docs/models.md B.3)
    parameters: ClassVar[tuple[ParameterSpec, ...]] = ()
    #: its random stream: an int key of its own, :data:`GROWTH_STREAM`, or None (it draws nothing)
    stream: ClassVar[int | str | None] = None
    #: rows of the segment store a metamer adds besides itself (bud nodes), reserved in advance
    extra_rows: ClassVar[int] = 0
    #: the parameter that turns the form on when above 0 (the default :meth:`acts`), or None
    switch: ClassVar[str | None] = None

    @classmethod
    def acts(cls, p: Mapping[str, float], settings) -> bool:
        """Whether the form acts on a run of parameters ``p`` and the model's ``settings``.

        By default when its :attr:`switch` parameter is above 0 (never without one)."""
        return cls.switch is not None and p[cls.switch] > 0.0

    @classmethod
    def check(cls, p: Mapping[str, float], need: Need) -> None:
        """Check the form's parameter values (every run, whether the form acts or not)."""

    def __init__(self, run: SOTGrowth, rng: np.random.Generator | None):
        self.run = run
        self.p = run.p
        self.rng = rng

    # ---------------------------------------------------------------- hooks (defaults: nothing)
    def seeded(self) -> None:
        """After the seed metamer (row 0) is made, before its shadow and before ``rows_made``."""

    def begin_cycle(self, c: int) -> None:
        """At the start of growth cycle ``c`` (2 ..), after the cycle's lambda is drawn."""

    def cycle_lambda(self, lam: float) -> float:
        """The apical control the passes of this cycle use, given the cycle's ``lam``."""
        return lam

    def transmission(self, points: np.ndarray) -> np.ndarray:
        """A factor on the exposure at ``points`` ((m, 3), m): the light field multiplies by it."""
        return np.ones(len(points))

    def select_buds(self, c: int, buds: BudChoice) -> None:
        """Change which buds grow this cycle (``buds.grow_a``, ``buds.grow_l``), in place."""

    def plan_shoots(self, c: int, shoots: Shoots) -> None:
        """The cycle's shoots in draw order, before their frames: change ``shoots.planned``."""

    def shape_shoots(self, shoots: Shoots) -> None:
        """After the shoots' frames, metamer lengths and targets: change them in place."""

    def bend(self, shoots: Shoots, act: np.ndarray) -> np.ndarray:
        """At each metamer step, after the phyllotaxis draws: the bend (radians) of the active
        shoots ``act`` about their up vectors (the run adds the forms' bends)."""
        return np.zeros(act.size)

    def metamers_added(self, c: int, nid: np.ndarray, end, h, u, order) -> np.ndarray:
        """After the metamers ``nid`` (ending at ``end``, frames ``h``, ``u``, axis ``order``)
        are appended: returns the node each axis goes on from (``nid`` itself by default)."""
        return nid

    def rows_made(self, lo: int) -> None:
        """The rows ``lo ..`` of the store were made in this step (the seed, or a cycle's shoots),
        their lateral buds in place, before their tips become buds and their shadows fall."""

    def shoots_built(self, shoots: Shoots) -> None:
        """After the cycle's shoots are built (``shoots.first``, ``shoots.built``, ``shoots.last``)."""


def overrides(form: GrowthForm, hook: str) -> bool:
    """Whether ``form`` has a hook of its own (the run calls only those)."""
    return getattr(type(form), hook) is not getattr(GrowthForm, hook)


def own_stream(seed: int, key: int) -> np.random.Generator:
    """A generator of the run's seed and a stream of its own (``key``), apart from the growth's draws."""
    return np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(int(key),)))


def form_generator(form: type[GrowthForm], seed: int, growth: np.random.Generator) -> np.random.Generator | None:
    """The generator a form draws from in a run of ``seed`` (``growth``: the growth's own)."""
    if form.stream == GROWTH_STREAM:
        return growth
    return None if form.stream is None else own_stream(seed, form.stream)


def check_forms(forms, core: list[ParameterSpec]) -> None:
    """Raise ``ValueError`` when forms clash: a parameter named twice, or a stream key shared."""
    names = [p.name for p in core] + [p.name for f in forms for p in f.parameters]
    twice = sorted({n for n in names if names.count(n) > 1})
    keys = [f.stream for f in forms if isinstance(f.stream, int)]
    shared = sorted({k for k in keys if keys.count(k) > 1})
    if twice or shared:
        raise ValueError(
            f"SOT growth forms clash: parameter(s) {twice} named twice, stream key(s) {shared} shared "
            "(each form declares parameters and a stream of its own)"
        )
