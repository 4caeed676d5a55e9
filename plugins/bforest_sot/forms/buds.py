"""Several lateral buds per node: opposite buds (maples, ash) and whorls (docs/growth-forms.md).

A metamer with k buds is stored as the metamer followed by k - 1 zero-length *bud nodes* on its
apical slot (store rows marked ``bud_node``), each holding one more lateral bud whose up vector is
the metamer's rolled by 360 j / k degrees about the heading, so the buds of a node point to evenly
spaced sides (2: opposite; 3 or more: a whorl). The axis goes on from the last bud node. Bud
nodes take part in the light, allocation and pipe-model passes like segments (each of the k
Borchert-Honda splits of a node takes lambda^(1/k), so the axis keeps the papers' share lambda
of the node), cast no shadow and are folded away in the output tree (the growth loop's treatment
of bud nodes). No draws.
"""

from __future__ import annotations

import math

import numpy as np

from ..model import BUD, CHILD, rotate
from .base import GrowthForm


class BudsPerNode(GrowthForm):
    """The setting ``buds_per_node`` (1 = the papers' model, one bud per node in a spiral)."""

    @classmethod
    def acts(cls, p, settings) -> bool:
        return settings.buds_per_node > 1

    def __init__(self, run, rng):
        super().__init__(run, rng)
        self.k = int(run.settings.buds_per_node)
        self.extra_rows = self.k - 1

    def cycle_lambda(self, lam: float) -> float:
        """A node of k buds is k Borchert-Honda splits in a row: each takes lambda^(1/k)."""
        return lam ** (1.0 / self.k)

    def seeded(self) -> None:
        s = self.run.s
        s.reserve(self.k)
        end = s.start[:1] + s.length[0] * s.h[:1]
        last = self.metamers_added(1, np.zeros(1, np.int64), end, s.h[:1], s.u[:1], s.order[:1])
        s.api_state[last] = BUD

    def metamers_added(self, c, nid, end, h, u, order) -> np.ndarray:
        """The chain of k - 1 bud nodes at the ends of the metamers ``nid``; returns its last nodes."""
        s = self.run.s
        prev = nid
        m = nid.size
        for j in range(1, self.k):
            tid = s.n + np.arange(m)
            new = slice(s.n, s.n + m)
            up = rotate(u, h, np.full(m, 2.0 * math.pi * j / self.k))
            s.append(new, end, h, up, 0.0, self.p["init_width"], prev, False, order, c)
            s.bud_node[new] = True
            s.api_state[prev] = CHILD
            s.api_child[prev] = tid
            s.n += m
            prev = tid
        return prev
