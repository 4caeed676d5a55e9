"""Short shoots: laterals of one internode whose buds never grow (spurs; docs/growth-forms.md).

When lateral shoots grow in a cycle, each draws one uniform number from the growth's own
generator (after the leader-death draws, before the branch-angle draws of docs/models.md B.7)
and is a short shoot when it is below ``short_shoot``: it is built as one metamer of
``node_length`` whatever its vigor, and its metamer and bud nodes are marked dormant (their buds
take light and vigor but never grow). With ``short_shoot = 0`` nothing is drawn.
"""

from __future__ import annotations

import numpy as np

from bforest_core.interfaces import ParameterSpec as P

from .base import GROWTH_STREAM, GrowthForm


class ShortShoots(GrowthForm):
    """``short_shoot``: the probability that a lateral shoot is a short shoot."""

    parameters = (
        P(
            "short_shoot",
            0.0,
            0.0,
            1.0,
            False,
            "",
            "an addition: probability that a lateral shoot is a short shoot (one internode of node_length whose "
            "buds never grow: the spurs and short shoots of broadleaved trees); 0 = the papers' model (no draws)",
            "V",
        ),
    )
    stream = GROWTH_STREAM
    switch = "short_shoot"

    def plan_shoots(self, c, shoots) -> None:
        self.short = np.zeros(shoots.bearing.size, bool)
        li = np.flatnonzero(shoots.lateral)
        self.short[li[self.rng.random(li.size) < self.p["short_shoot"]]] = True
        shoots.planned[self.short] = 1

    def shape_shoots(self, shoots) -> None:
        shoots.metamer_length[self.short] = self.p["node_length"]

    def shoots_built(self, shoots) -> None:
        """A short shoot's metamer and its bud nodes never grow on."""
        for rows in self.run.node_rows(shoots.first[self.short & (shoots.first >= 0)]):
            self.run.s.dormant[rows] = True
