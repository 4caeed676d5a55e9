"""Sympodial branching: no apical bud grows (the setting ``sympodial``, docs/models.md B.3)."""

from __future__ import annotations

from ..model import BUD, EMPTY
from .base import GrowthForm


class Sympodial(GrowthForm):
    """The switch of the original SOT that removes the apical buds: every axis ends each cycle."""

    @classmethod
    def acts(cls, p, settings) -> bool:
        return bool(settings.sympodial)

    def select_buds(self, c, buds) -> None:
        self.run.s.api_state[buds.ids[buds.keep & (buds.api_state0 == BUD)]] = EMPTY
        buds.grow_a[:] = False
