"""A stem along the measured one: ``stem_guide`` with the setting ``stem_path`` (docs/growth-forms.md).

The growth keeps the stem's length so far (the apical shoots from the seed on, order 0). Each
cycle the stem's shoot, before its first metamer, takes as its target the point of the path one
shoot length beyond that length: its target direction is (1 - w) t + w g (t the papers' target,
g the unit vector to the path's point, w = ``stem_guide``) and it turns the share (1 - w) tau + w
of its angle per metamer. No draws: at 0, or without a path, the tree is the papers' bit for bit.
"""

from __future__ import annotations

import numpy as np

from bforest_core.interfaces import ParameterSpec as P

from ..model import _norm
from .base import GrowthForm


class Guide:
    """A polyline (points from the stem base, base first) read by arc length: :meth:`at` gives the
    point at each arc length, on the line through the last two points beyond the end."""

    def __init__(self, points):
        pts = np.asarray(points, dtype=float).reshape(-1, 3)
        step = np.linalg.norm(np.diff(pts, axis=0), axis=1)
        keep = np.r_[True, step > 1e-9]  # repeated points carry no direction
        self.pts = pts[keep]
        self.arc = np.r_[0.0, np.cumsum(step[step > 1e-9])]  # two distinct points at least (the settings' check)
        d = self.pts[-1] - self.pts[-2]
        self.end_dir = d / np.linalg.norm(d)

    def at(self, a: np.ndarray) -> np.ndarray:
        a = np.asarray(a, dtype=float)
        out = np.stack([np.interp(a, self.arc, self.pts[:, k]) for k in range(3)], axis=-1)
        beyond = np.maximum(a - self.arc[-1], 0.0)
        return out + beyond[..., None] * self.end_dir


class StemGuide(GrowthForm):
    """``stem_guide``: how far the stem's shoots follow the setting ``stem_path``."""

    parameters = (
        P(
            "stem_guide",
            0.0,
            0.0,
            1.0,
            False,
            "",
            "an addition: how far the stem's (order 0) shoots are steered along the setting stem_path, the "
            "stem of the measured tree (a guide curve, as TreeSketch grows the self-organizing tree along strokes): "
            "each cycle's stem shoot heads for the point of the path one shoot length beyond its own arc length; "
            "1 = the stem follows the path, 0 (or no stem_path) = the papers' model",
            "II",
        ),
    )

    @classmethod
    def acts(cls, p, settings) -> bool:
        return p["stem_guide"] > 0.0 and len(settings.stem_path) > 0

    @classmethod
    def check(cls, p, need) -> None:
        need(0 <= p["stem_guide"] <= 1, "stem_guide", "in [0, 1]")

    def __init__(self, run, rng):
        super().__init__(run, rng)
        self.guide = Guide(run.settings.stem_path)
        self.arc = 0.0  # length of the stem (order 0) grown so far

    def seeded(self) -> None:
        self.arc = float(self.p["node_length"])

    def shape_shoots(self, shoots) -> None:
        """The stem's shoot heads for the point of the path one shoot length beyond the stem's
        arc length, blended with its own target by ``stem_guide``."""
        self.stem = np.flatnonzero(shoots.order == 0)
        if not self.stem.size:
            return
        st, w = self.stem, self.p["stem_guide"]
        g = self.guide.at(self.arc + shoots.planned[st] * shoots.metamer_length[st]) - shoots.pos[st]
        g = (1.0 - w) * shoots.target[st] + w * g / np.maximum(_norm(g), 1e-12)[:, None]
        shoots.target[st] = g / np.maximum(_norm(g), 1e-12)[:, None]
        shoots.tau[st] = (1.0 - w) * shoots.tau[st] + w

    def shoots_built(self, shoots) -> None:
        if self.stem.size:
            self.arc += float((shoots.built[self.stem] * shoots.metamer_length[self.stem]).sum())
