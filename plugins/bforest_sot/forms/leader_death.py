"""Dying leaders (sympodial forks) and a monopodial stem (docs/growth-forms.md).

From cycle ``death_delay + 1`` on, each growing apical bud draws one uniform number and dies when
it is below ``leader_death`` (the stem's own buds, order 0, below ``stem_death x leader_death``):
its shoot does not grow and its slot stays empty, so the lateral buds of its node take over
(with opposite buds, a fork). The draws come from the growth's own generator, after the cycle's
lambda draw, one per growing apical bud in the order of their bearing segments (docs/models.md
B.10); with ``leader_death = 0`` nothing is drawn.
"""

from __future__ import annotations

import numpy as np

from bforest_core.interfaces import ParameterSpec as P

from ..model import EMPTY
from .base import GROWTH_STREAM, GrowthForm


class LeaderDeath(GrowthForm):
    """``leader_death``, ``stem_death`` and ``death_delay``."""

    parameters = (
        P(
            "leader_death",
            0.0,
            0.0,
            1.0,
            False,
            "",
            "an addition: probability per cycle that a growing apical bud "
            "dies (terminal flowering, frost, damage), so the lateral buds below it take over; with opposite buds a "
            "fork (sympodial growth of many broadleaved trees; 1 = every shoot forks); 0 = the papers' model (no draws)",
            "V",
        ),
        P(
            "stem_death",
            1.0,
            0.0,
            1.0,
            False,
            "",
            "an addition: the stem's (order 0) apical buds die at stem_death x leader_death; 1 = as every "
            "leader's, 0 = a monopodial trunk whose branches fork (Scarrone's architectural model)",
            "V",
        ),
        P(
            "death_delay",
            0.0,
            0.0,
            30.0,
            False,
            "cycles",
            "an addition: apical buds die (leader_death) from cycle death_delay + 1 on, e.g. from the onset of flowering",
            "V",
        ),
    )
    stream = GROWTH_STREAM
    switch = "leader_death"

    @classmethod
    def check(cls, p, need) -> None:
        need(0 <= p["stem_death"] <= 1, "stem_death", "in [0, 1]")

    def select_buds(self, c, buds) -> None:
        if c <= self.p["death_delay"]:
            return
        s, ids = self.run.s, buds.ids
        ga = np.flatnonzero(buds.grow_a)
        ld = self.p["leader_death"]
        rate = np.where(s.order[ids[ga]] == 0, ld * self.p["stem_death"], ld)
        died = ga[self.rng.random(ga.size) < rate]
        s.api_state[ids[died]] = EMPTY
        buds.grow_a[died] = False
