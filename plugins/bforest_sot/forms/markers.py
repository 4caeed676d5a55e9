"""The crown's space colonised: ``space_claim``, markers of free space inside ``crown_envelope``.

Palubicki et al. (2009) grow the self-organizing tree either by shadow propagation (the papers'
model, docs/models.md B.6) or by *space colonisation* (Runions, Lane & Prusinkiewicz 2007): points
of free space (markers) fill an envelope, a bud that has markers about it has room to grow, and a
metamer claims the markers near it. This form joins the two: the crown's space of the measured
tree (the setting ``crown_envelope``) is filled with markers above its crown base, and the
exposure of every point the light field reads above the crown base is multiplied by
``1 - space_claim * (1 - free)``, ``free`` the share of :data:`FREE_MARKERS` markers still
found within the perception radius of the point (a point with that many free markers about it has
full light). Buds about which the space is taken get less light, so their shoots lose the bud
competition (and, without light, are shed), and the
light-gradient probes turn shoots towards the free space: the crown grows into the far reaches
of the space the tree won, where the shade outside it (``envelope_shade``) only stops it.

Its one parameter is ``space_claim``; the rest is fixed by the model's own scale: the markers
(:data:`MARKERS` of them, drawn once per run from a stream of the form's own, so the growth's
draws are the papers') lie in the crown's space, a metamer claims those within
:data:`CLAIM_NODES` internodes (``node_length``) of its end, at the start of each cycle, and a
point perceives those within :data:`PERCEPTION_NODES` internodes (the paper's 2 and 4-6).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from bforest_core.envelope import CrownEnvelope
from bforest_core.interfaces import ParameterSpec as P

from .envelope import InCrownSpace

#: markers drawn in the crown's space (a fixed number: the cost of a growth does not grow with the tree)
MARKERS = 4000
#: a metamer claims the markers within this many internodes of its end (Palubicki et al. 2009: 2)
CLAIM_NODES = 2.0
#: a point perceives the markers within this many internodes (Palubicki et al. 2009: 4-6)
PERCEPTION_NODES = 4.0
#: a point with this many markers or more within its perception radius has free space about it
FREE_MARKERS = 4
#: the form's own random stream (the markers), apart from the growth's draws
STREAM = 77


class CrownMarkers(InCrownSpace):
    """``space_claim``: the share of the light a point loses where the crown's space about it is taken."""

    parameters = (
        P(
            "space_claim",
            0.0,
            0.0,
            1.0,
            False,
            "",
            "an addition: the share of the light a bud loses where the crown's space (crown_envelope) about "
            "it is taken by the tree's own wood (space colonisation of markers inside the envelope: shoots "
            "grow into the free space); 0 (or no crown_envelope) = the papers' model",
            "II",
        ),
    )
    stream = STREAM
    switch = "space_claim"

    def __init__(self, run, rng):
        super().__init__(run, rng)
        self.base = self.envelope.base
        self.markers = _markers(self.envelope, self.rng)
        node = float(self.p["node_length"])
        self.claim_r = CLAIM_NODES * node
        self.sense_r = PERCEPTION_NODES * node
        self.free = self.markers
        self.tree = cKDTree(self.free) if len(self.free) else None
        self.seen = 0  # rows of the store whose claims are made

    def begin_cycle(self, c: int) -> None:
        """The metamers made since the last cycle claim the markers near their ends."""
        s = self.run.s
        lo, hi = self.seen, s.n
        self.seen = hi
        if hi <= lo or not len(self.free):
            return
        ends = s.start[lo:hi] + s.length[lo:hi, None] * s.h[lo:hi]
        d, _ = cKDTree(ends).query(self.free, distance_upper_bound=self.claim_r)
        keep = ~np.isfinite(d)
        if not keep.all():
            self.free = self.free[keep]
            self.tree = cKDTree(self.free) if len(self.free) else None

    def transmission(self, points: np.ndarray) -> np.ndarray:
        f = np.ones(len(points))
        up = points[:, 2] >= self.base
        if not up.any():
            return f
        if self.tree is None:
            free = np.zeros(int(up.sum()))
        else:
            d, _ = self.tree.query(points[up], k=FREE_MARKERS, distance_upper_bound=self.sense_r)
            free = np.isfinite(d).sum(axis=1) / FREE_MARKERS  # the nearest FREE_MARKERS: as many as are near
        f[up] = 1.0 - self.p["space_claim"] * (1.0 - free)
        return f


def _box(env: CrownEnvelope):
    """The box that holds the crown's space from its base to its top (x, y about the stem)."""
    r = float(env.reach.max()) + env.margin
    lo = np.array([env.stem[:, 0].min() - r, env.stem[:, 1].min() - r, env.base])
    hi = np.array([env.stem[:, 0].max() + r, env.stem[:, 1].max() + r, env.top])
    return lo, hi


def _markers(env: CrownEnvelope, rng: np.random.Generator) -> np.ndarray:
    """:data:`MARKERS` points uniform in the crown's space from its base to its top."""
    lo, hi = _box(env)
    out = np.zeros((0, 3))
    for _ in range(64):  # a space of no volume (no reach, no margin) holds none: then every point is taken
        if len(out) >= MARKERS:
            break
        p = lo + rng.random((4 * MARKERS, 3)) * (hi - lo)
        out = np.vstack([out, p[env.contains(p)]])
    return out[:MARKERS]
