"""The ``lignum`` SSM component: simplified stochastic LIGNUM (docs/models.md part A)."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Literal

from pydantic import Field

from bforest_core.envelope import SETTING_DESCRIPTION, EnvelopeSetting, grown_in
from bforest_core.interfaces import SSM, ComponentSettings, ParameterSpec
from bforest_core.tree import Tree

from . import params as P
from .model import _Simulation
from .recipe import lignum_recipe


class LignumSettings(ComponentSettings):
    """Settings of the ``lignum`` SSM.

    Attributes
    ----------
    preset : {"sf_synthetic", "sf_real", "p98", "s08", "sf_test16"}
        Parameter defaults (docs/models.md A.4); ``sf_synthetic`` (SF Table 2) by default.
    order_mode : {"growth", "thickest"}
        Output topology: the growth (bud) rule with the apical child as extension (``source``
        topology), or QSM-like ``thickest`` (largest-radius child continues the branch).
    max_live_segments : int
        A run with more live segments after a growth year fails with ``too_many_segments``.
    piece_length : float
        Output only: each shoot is drawn as pieces at most this long (m), as a scan's QSM draws a
        branch as short cylinders, each bent by the parameter ``wind_sd``; the growth is
        unchanged (0 = one cylinder per shoot). A setting, not a parameter: it changes only how
        the tree is drawn, and no fit varies it.
    crown_envelope : dict
        The measured tree's crown space (:class:`bforest_core.envelope.CrownEnvelope` as a
        setting), outside which the parameter ``envelope_shade`` takes the light; empty = none.
    """

    preset: Literal["sf_synthetic", "sf_real", "p98", "s08", "sf_test16"] = "sf_synthetic"
    order_mode: Literal["growth", "thickest"] = "growth"
    max_live_segments: int = Field(50_000, gt=0, le=10**7)
    piece_length: float = Field(
        0.0,
        ge=0.0,
        allow_inf_nan=False,
        description="output only (an addition): each shoot is drawn as pieces at most this long (m), as a "
        "scan's QSM draws a branch as short cylinders, bent by the parameter wind_sd; the growth is "
        "unchanged (0 = one cylinder per shoot)",
    )
    crown_envelope: EnvelopeSetting = Field(default_factory=dict, description=SETTING_DESCRIPTION)


class LignumSSM(SSM):
    """Simplified stochastic LIGNUM (Potapov et al. 2016, Silva Fennica 50(1):1413).

    Examples
    --------
    >>> import bforest_core as bf
    >>> ssm = bf.component("ssm", "lignum", preset="sf_real")
    >>> tree = ssm.simulate({"years": 20}, seed=3)
    """

    name = "lignum"
    summary = "simplified stochastic LIGNUM: carbon balance, pyramid shadow, pipe model (pine)"
    Settings = LignumSettings

    @property
    def parameters(self) -> list[ParameterSpec]:
        """Parameter specs of A.3 with the current preset's values as defaults."""
        return P.parameter_specs(self.settings.preset)

    def crown_space(self, params):
        """The measured crown's space (``crown_envelope``) when ``envelope_shade`` shades outside it."""
        return grown_in(self.settings.crown_envelope, self.resolve_params(params)["envelope_shade"])

    def draft_recipe(self, measures):
        """LIGNUM's recipe for a measured tree (:func:`bforest_lignum.recipe.lignum_recipe`)."""
        return lignum_recipe(measures)

    def resolve_params(self, params: Mapping[str, object]) -> dict:
        """Preset defaults overridden by ``params`` (categorical spellings mapped to codes);
        unknown names and non-numeric values raise ``ValueError``; the result is validated."""
        out = super().resolve_params(P.normalise_inputs(params))
        P.validate(out)
        return out

    def simulate(
        self, params: Mapping[str, float], seed: int, on_step: Callable | None = None, *, trace: list | None = None
    ) -> Tree:
        """Grow one tree.

        Parameters
        ----------
        params : mapping
            Parameter values overriding the preset's defaults (unknown names raise
            ``ValueError``; invalid values raise ``ValueError`` naming the parameter).
        seed : int
            Seed of the single ``numpy.random.Generator(PCG64(seed))``.
        on_step : callable, optional
            ``on_step(t, view)`` after the light step of every year t = 1..T, with a read-only
            :class:`~bforest_lignum.model.LignumView`; ``view.tree()`` equals the output of a
            ``years = t`` run (prefix property).
        trace : list, optional
            Debug hook: one :class:`~bforest_lignum.model.YearTrace` per growth year is
            appended (internal arrays; for tests).

        Returns
        -------
        Tree
            Live segments (dead remnants included, ``extras["is_dead"]``), growth topology.

        Raises
        ------
        SimulationFailed
            ``negative_balance``, ``too_many_segments`` or ``no_root``, carrying the partial tree.
        """
        p = self.resolve_params(params)
        return _Simulation(p, int(seed), self.settings, on_step=on_step, trace=trace).run()
