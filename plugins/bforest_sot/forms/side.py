"""The crown's short side: ``side_shade`` with the setting ``crown_envelope`` (docs/growth-forms.md).

In a wood a crown reaches far where its neighbours stand far and short where they stand near
(the crown's space, :mod:`bforest_core.envelope`). The near neighbours shade that side of the
crown from the first years on, so its limbs get less light than the open side's, lose the bud
competition and are shed, and the crown grows to the open side. ``crown_envelope`` records how far
the crown reaches in each direction; this form reads it as how open each side is: the exposure
of every point the light field reads is multiplied by ``1 - side_shade * w * (1 - side)``, where
``side`` is the crown's reach in the point's direction from the stem over its widest reach at the
point's height (:meth:`~bforest_core.envelope.CrownEnvelope.side`, 1 on the open side) and ``w``
grows linearly from 0 at the growth's own stem to 1 at the envelope's margin from it (the stem
itself is lit as before; across the first margin the light-gradient probes turn shoots towards
the open side). No draws: at 0, or without an envelope, the tree is the papers' bit for bit.
"""

from __future__ import annotations

import numpy as np

from bforest_core.envelope import path_at
from bforest_core.interfaces import ParameterSpec as P

from .envelope import AboutOwnStem


class CrownSide(AboutOwnStem):
    """``side_shade``: the share of the light the near neighbours take on the crown's short side."""

    parameters = (
        P(
            "side_shade",
            0.0,
            0.0,
            1.0,
            False,
            "",
            "an addition: the share of the light the near neighbours take on the crown's short side: exposure "
            "times 1 - side_shade * (1 - the crown's reach in the point's direction over its widest, from "
            "crown_envelope); 1 = a side the crown does not reach gets no light, 0 (or no crown_envelope) = the "
            "papers' model",
            "II",
        ),
    )
    switch = "side_shade"

    def __init__(self, run, rng):
        super().__init__(run, rng)
        self.fade = max(self.envelope.margin, float(self.p["node_length"]))

    def transmission(self, points: np.ndarray) -> np.ndarray:
        d = points[:, :2] - path_at(self.stem, points[:, 2])[:, :2]
        w = np.clip(np.hypot(d[:, 0], d[:, 1]) / self.fade, 0.0, 1.0)
        return 1.0 - self.p["side_shade"] * w * (1.0 - self.envelope.side(points))
