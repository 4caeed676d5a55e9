"""The neighbours' shade: a stand's canopy above and around the tree, a gap on one side.

Both multiply the exposure of every point the light field reads (buds and the light-gradient
probes, docs/models.md B.6) and draw nothing (docs/growth-forms.md, "A gap on one side").
"""

from __future__ import annotations

import numpy as np

from bforest_core.interfaces import ParameterSpec as P

from .base import GrowthForm


class StandShade(GrowthForm):
    """``stand_shade``: exposure times exp(-stand_shade * depth below the tree's top)."""

    parameters = (
        P(
            "stand_shade",
            0.0,
            0.0,
            2.0,
            False,
            "1/m",
            "extinction of the surrounding stand's canopy: exposure "
            "times exp(-stand_shade * depth below the tree's top); 0 = open-grown (the papers' model)",
            "II",
        ),
    )
    switch = "stand_shade"

    def __init__(self, run, rng):
        super().__init__(run, rng)
        self.z_top = 0.0  # the stand's canopy grows with the tree: its top is the tree's

    def begin_cycle(self, c: int) -> None:
        s = self.run.s
        live = s.live
        self.z_top = float((s.start[live, 2] + s.length[live] * s.h[live, 2]).max())

    def transmission(self, points: np.ndarray) -> np.ndarray:
        return np.exp(-self.p["stand_shade"] * np.maximum(0.0, self.z_top - points[:, 2]))


class GapShade(GrowthForm):
    """``gap_shade`` and ``gap_azimuth``: exposure times exp(-gap_shade * distance behind the
    stem base, away from the gap), so the crown grows into the gap and the stem leans towards it."""

    parameters = (
        P(
            "gap_shade",
            0.0,
            0.0,
            5.0,
            False,
            "1/m",
            "an addition: extinction of the neighbours' shade on one side of the tree: exposure times "
            "exp(-gap_shade * distance behind the stem base, away from gap_azimuth), so the crown grows "
            "into the gap and the stem leans towards it; 0 = no gap (the papers' model)",
            "II",
        ),
        P(
            "gap_azimuth",
            0.0,
            -180.0,
            180.0,
            False,
            "deg",
            "an addition: direction of the open side (gap_shade), counterclockwise from +x in the tree's frame",
            "II",
        ),
    )
    switch = "gap_shade"

    @classmethod
    def check(cls, p, need) -> None:
        need(p["gap_shade"] >= 0, "gap_shade", ">= 0")

    def __init__(self, run, rng):
        super().__init__(run, rng)
        a = np.radians(float(self.p["gap_azimuth"]))
        self.gap_dir = np.array([np.cos(a), np.sin(a)])  # the gap's horizontal direction

    def transmission(self, points: np.ndarray) -> np.ndarray:
        return np.exp(-self.p["gap_shade"] * np.maximum(0.0, -(points[:, :2] @ self.gap_dir)))
