"""The crown's space: ``envelope_shade`` with the setting ``crown_envelope`` (docs/growth-forms.md).

The setting holds the measured tree's crown envelope (:class:`bforest_core.envelope.CrownEnvelope`:
the crown's reach from the stem per height band and azimuth sector, with its margin), in the
tree's frame, so the clones' crowns grow where the scanned one does. The exposure of every point
the light field reads (buds and the light-gradient probes) is multiplied by
1 - ``envelope_shade`` (1 - the envelope's light share there): outside the envelope the neighbours
take that share of the light. At 1 a bud outside gets no light, so no vigor: its shoot does not
grow, and a branch with no lit bud is shed (the model's own rule, ``drop_thresh``); across the
margin the light falls off, so shoots that seek light turn back into the crown's space. The
growth's own stem keeps a corridor of the margin's width (its order-0 metamers, as they stand at
the start of each cycle), so a stem that grows upright where the tree's leans is not shaded out
of the crown; its branches are. No draws:
at 0, or without an envelope, the tree is the papers' bit for bit.
"""

from __future__ import annotations

import numpy as np

from bforest_core.envelope import SHADE_MEANING, SHADE_SPEC, CrownEnvelope
from bforest_core.interfaces import ParameterSpec as P

from .base import GrowthForm


class InCrownSpace(GrowthForm):
    """A form that acts in the measured crown's space: its :attr:`switch` parameter, a share in
    [0, 1], above 0, and the setting ``crown_envelope`` given (else the papers' tree, draw for draw)."""

    @classmethod
    def acts(cls, p, settings) -> bool:
        return super().acts(p, settings) and bool(settings.crown_envelope)

    @classmethod
    def check(cls, p, need) -> None:
        need(0 <= p[cls.switch] <= 1, cls.switch, "in [0, 1]")

    def __init__(self, run, rng):
        super().__init__(run, rng)
        self.envelope = CrownEnvelope.from_setting(run.settings.crown_envelope)


class AboutOwnStem(InCrownSpace):
    """A crown-space form that knows the growth's own stem as it stands (:attr:`stem`, points
    (x, y, z) from its base: the ends of the living metamers of order 0), each cycle."""

    def __init__(self, run, rng):
        super().__init__(run, rng)
        self.stem = np.zeros((1, 3))  # the growth's own stem, from its base

    def begin_cycle(self, c: int) -> None:
        """The stem as it stands: the living metamers of order 0 (base first), their ends."""
        s = self.run.s
        live = s.live
        stem = live[(s.order[live] == 0) & ~s.bud_node[live]]
        self.stem = np.vstack([np.zeros((1, 3)), s.start[stem] + s.length[stem, None] * s.h[stem]])


class CrownSpace(AboutOwnStem):
    """``envelope_shade``: the share of the light the neighbours take outside ``crown_envelope``."""

    parameters = (
        P(
            **SHADE_SPEC,
            description=f"{SHADE_MEANING}: exposure times 1 - envelope_shade (1 - the envelope's light there); 1 = buds "
            "outside get no light and their shoots are shed, 0 (or no crown_envelope) = the papers' model",
            group="II",
        ),
    )

    switch = "envelope_shade"

    def transmission(self, points: np.ndarray) -> np.ndarray:
        return 1.0 - self.p["envelope_shade"] * (1.0 - self.envelope.light(points, self.stem))
