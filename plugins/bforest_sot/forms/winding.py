"""Winding axes: clone noise that bends each branch metamer (``heading_sd``, docs/models.md B.10).

At each metamer step, after the phyllotaxis draws, one standard normal per active shoot from the
growth's own generator: the metamer of a branch (order > 0) bends by N(0, heading_sd) degrees
about its up vector, whose phyllotaxis roll turns the bending plane from metamer to metamer; the
stem stays straight, as a leader held by gravitropism does. With ``heading_sd = 0`` nothing is
drawn.
"""

from __future__ import annotations

import numpy as np

from bforest_core.interfaces import ParameterSpec as P

from .base import GROWTH_STREAM, GrowthForm


class Winding(GrowthForm):
    """``heading_sd``: the sd of each branch metamer's bend (deg)."""

    parameters = (
        P(
            "heading_sd",
            0.0,
            0.0,
            90.0,
            False,
            "deg",
            "clone noise (an addition): sd of a bend of each branch metamer "
            "about its up vector, so that branches wind as scanned ones do (the stem stays straight); 0 = smooth axes",
            "V",
        ),
    )
    stream = GROWTH_STREAM
    switch = "heading_sd"

    def bend(self, shoots, act) -> np.ndarray:
        z = self.rng.standard_normal(act.size)
        return np.radians(self.p["heading_sd"] * z) * (shoots.order[act] > 0)
