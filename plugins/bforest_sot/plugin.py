"""Entry point of this plugin: the self-organizing tree (SOT) growth model.

``bf.component("ssm", "sot").simulate(params, seed)`` grows one tree with the SOT model of
Palubicki et al. (2009) with multiplicative shadow propagation, as used by Potapov et al. (2017),
following docs/models.md part B (calibrated for the 12 m cube of B.4), with the growth forms of
:mod:`bforest_sot.forms` (docs/growth-forms.md), each off by default.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any, ClassVar, Literal

import numpy as np
from pydantic import Field, field_validator

from bforest_core.envelope import SETTING_DESCRIPTION, EnvelopeSetting, grown_in
from bforest_core.hookspecs import hookimpl
from bforest_core.interfaces import SSM, ComponentSettings, ParameterSpec
from bforest_core.tree import Tree

from .forms.base import GrowthForm
from .forms.buds import BudsPerNode
from .forms.envelope import CrownSpace
from .forms.leader_death import LeaderDeath
from .forms.markers import CrownMarkers
from .forms.shade import GapShade, StandShade
from .forms.short_shoots import ShortShoots
from .forms.side import CrownSide
from .forms.stem_guide import StemGuide
from .forms.sympodial import Sympodial
from .forms.winding import Winding
from .model import MODEL_VERSION, SOTGrowth, grow
from .params import model_parameters, validate
from .recipe import sot_recipe

#: the bundled growth forms, in the order the growth calls their hooks (their parameters are
#: listed group by group after the papers', in this order within a group)
FORMS: tuple[type[GrowthForm], ...] = (
    StandShade,
    GapShade,
    CrownSpace,
    CrownSide,
    CrownMarkers,
    StemGuide,
    BudsPerNode,
    Winding,
    LeaderDeath,
    ShortShoots,
    Sympodial,
)


class SOTSettings(ComponentSettings):
    """Switches of the SOT model (not fitted)."""

    order_mode: Literal["growth", "thickest"] = Field(
        "growth",
        description="branch topology of the output: 'growth' (apical bud continues the "
        "branch) or 'thickest' (the thickest child continues it, as in QSMs)",
    )
    max_live_segments: int = Field(
        200_000, ge=1, le=10**7, description="status 'too_many_segments' above this (at most 10 million)"
    )
    sympodial: bool = Field(False, description="remove apical buds (sympodial branching)")
    buds_per_node: int = Field(
        1,
        ge=1,
        le=6,
        description=(
            "lateral buds per node, an addition to the papers' model: 1 = one bud per node in a spiral "
            "(the papers' model), 2 = opposite buds (maples, ash; phyllotaxis 90 makes them decussate), "
            "3 or more = a whorl; see docs/growth-forms.md"
        ),
    )
    stem_path: list[tuple[float, float, float]] = Field(
        default_factory=list,
        description=(
            "an addition to the papers' model: the stem of the measured tree as points (x, y, z) in m from "
            "its base, base first, which the stem's shoots follow as far as the parameter stem_guide says "
            "(`bforest init` writes a leaning QSM stem here); empty = no guide; see docs/growth-forms.md"
        ),
    )

    crown_envelope: EnvelopeSetting = Field(default_factory=dict, description=SETTING_DESCRIPTION)

    @field_validator("stem_path")
    @classmethod
    def _path(cls, v):
        if not v:
            return v
        pts = np.asarray(v, dtype=float)
        if not np.isfinite(pts).all():
            raise ValueError(f"stem_path point {int(np.flatnonzero(~np.isfinite(pts).all(1))[0])} is not finite")
        if len(v) < 2 or not (np.linalg.norm(np.diff(pts, axis=0), axis=1) > 1e-9).any():
            raise ValueError(f"stem_path needs at least 2 distinct points (base first), got {len(v)}")
        return v


class SOT(SSM):
    """Self-organizing tree model with shadow propagation (Palubicki et al. 2009; GS 2017).

    Each growth cycle: bud exposures are read from a multiplicative voxel light field, light and
    bud counts accumulate basipetally, vigor is allocated acropetally by the Borchert-Honda model
    with apical control lambda, under-supplied branches are shed, and buds grow shoots of
    ``floor(v)`` metamers that turn towards the light gradient and the vertical. Widths follow
    the pipe model. The growth forms (:attr:`forms`) add to that cycle through their hooks; a
    model with a form of one's own is a subclass with ``forms = SOT.forms + (MyForm,)``
    (docs/growth-forms.md).

    Settings
    --------
    order_mode : "growth" | "thickest"
    max_live_segments : int (200 000)
    sympodial : bool (False)
    buds_per_node : int (1)
    stem_path : list of (x, y, z) (empty)
    crown_envelope : dict (empty)
    """

    name = "sot"
    summary = "self-organizing tree growth model with shadow propagation (Palubicki 2009, GS 2017)"
    Settings = SOTSettings
    model_version = MODEL_VERSION
    #: the growth forms of this model (:mod:`bforest_sot.forms`), in the order of their hooks
    forms: ClassVar[tuple[type[GrowthForm], ...]] = FORMS

    @property
    def parameters(self) -> list[ParameterSpec]:
        return list(model_parameters(self.forms))

    def crown_space(self, params):
        """The measured crown's space (``crown_envelope``) when ``envelope_shade`` shades outside it."""
        return grown_in(self.settings.crown_envelope, self.resolve_params(params)["envelope_shade"])

    def draft_recipe(self, measures):
        """SOT's recipe for a measured tree (:func:`bforest_sot.recipe.sot_recipe`)."""
        return sot_recipe(measures)

    def simulate(
        self, params: Mapping[str, float], seed: int, on_step: Callable[[int, Any], None] | None = None
    ) -> Tree:
        """Grow one tree.

        Parameters
        ----------
        params : mapping
            Parameter values by name (see :attr:`parameters`); missing names take their
            calibrated defaults; unknown names, non-integer ``max_iter``/``depth`` and invalid
            values raise ``ValueError`` naming the parameter, before the run.
        seed : int
            Seed of the run's ``numpy.random.Generator(PCG64(seed))`` (and of the forms' own streams).
        on_step : callable, optional
            ``on_step(cycle, view)`` after every cycle with a read-only
            :class:`~bforest_sot.model.StepView` (``view.tree()`` is the output at that cycle).

        Returns
        -------
        Tree
            Growth topology (``source``, or ``thickest`` with ``order_mode="thickest"``),
            radius = width / 2, extras ``age`` (cycles since creation) and ``is_lateral``,
            metadata ``model``, ``params``, ``seed``, ``status``, ``cycles``.

        Raises
        ------
        ValueError
            Invalid parameters.
        SimulationFailed
            Status ``collapsed`` (< 10 live segments at the end of a cycle >= 5),
            ``too_many_segments`` (a cycle would exceed ``max_live_segments``) or ``no_root``;
            carries the partial tree (widths updated).
        """
        p = self.resolve_params(params)  # whole-number parameters come back as int
        whole = {spec.name for spec in self.parameters if spec.integer}
        p = {k: (v if k in whole else float(v)) for k, v in p.items()}
        validate(p, self.forms)
        return grow(SOTGrowth(p, int(seed), self.settings, self.forms, model=self.name, on_step=on_step))


@hookimpl
def bforest_components():
    return [SOT]
