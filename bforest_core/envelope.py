"""The crown's space: a star-shaped envelope of a tree's crown, measured from its cylinders.

In a wood the neighbours set the form of a broadleaved crown: it fills the space the tree won,
one-sided where a neighbour took the other side (docs/growth-forms.md, "The crown's space"). The
scan records that space; this module measures it from any reader's :class:`~bforest_core.tree.Tree`
and answers, for points of a growing tree, how much of the light they would get in it.

The envelope is the crown's horizontal reach from the stem: the crown above the crown base
(``metrics.crown_base_height``) is cut into :data:`BANDS` height bands of equal
height and :data:`SECTORS` azimuth sectors about the stem, and the reach of a band and sector is
the largest horizontal distance from the stem, taken at each point's own height, of the tree's
cylinders there (every cylinder sampled every :data:`STEP_SHARE` of the crown radius along its
axis). It is the crown radii a forester measures in a few directions (Pretzsch 2009, "Forest
Dynamics, Growth and Yield", crown projection from 8 radii), in 16 directions and 8 heights. The
stem's position at each band edge (the tree's own stem, branch 0) is kept with it, so a leaning
stem carries its crown with it. A point lies inside when it is no farther from the stem than its
band's and sector's reach plus the **margin**, the envelope's one setting, at any height: the
envelope has no lid (above the tree's top the top band's reach holds), since a lid cut the clones'
tops flat at the tree's height where the fit's size term already holds the height
(docs/notes/2026-12-07-crown-space-by-eye.md). Below the crown base the crown's widest reach in each sector
holds, about the stem's straight line from its base to the crown base: the young tree grew in
the space its crown stands over (its own and the stand's shade shed those branches later).

The margin is how far beyond the tree's own branches a clone's crown may reach: by default
:data:`MARGIN_SHARE` of the crown radius (a year or two of a branch's growth; 0.5 m on wytham_tf1,
0.26 m on tf5). In the margin the light falls linearly from full at the tree's reach to none at
the margin's edge (:meth:`CrownEnvelope.light`), so a shoot that reaches into it turns back
towards the light. A growing tree's own stem keeps a corridor of the margin's width about it
(``light(points, stem=...)``): a clone's stem, which grows upright where the tree's leans a few
degrees, is never shaded out of the crown by the envelope, and its branches are.

Why a star-shaped envelope, not a dilated voxel occupancy or an alpha shape: a crown's
cylinders fill a small share of the crown's volume, and a simplified QSM has no twigs, so an
occupancy is full of holes unless it is dilated by about a branch spacing, which also fills the
gaps between limbs and the bare side of a one-sided crown; an alpha shape needs a radius of the
same kind and a library this project does not use. The star is filled by construction (whatever
lies between the stem and the outermost branch in a direction is the crown's), holds every point
of the tree's own crown (tested), holds the stem at every height, and is small enough to live in
the recipe: 8 x 16 reaches and 9 stem points.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Annotated

import numpy as np
from pydantic import AfterValidator

__all__ = ["BANDS", "SECTORS", "MARGIN_SHARE", "STEP_SHARE", "CrownEnvelope", "grown_in", "path_at", "stem_at"]

#: height bands of the crown, from the crown base to the top
BANDS = 8
#: azimuth sectors about the stem (22.5 deg each)
SECTORS = 16
#: the margin by default: this share of the crown radius (half the crown spread)
MARGIN_SHARE = 0.10
#: cylinders are sampled along their axes every this share of the crown radius
STEP_SHARE = 1.0 / 40.0
#: the keys of the envelope as a setting (:meth:`CrownEnvelope.setting`), and what they hold
KEYS = ("margin", "base", "top", "stem", "reach")
SETTING_WHAT = (
    "the crown's space measured from the QSM: the margin, the crown base and the top (m above the stem "
    "base), the stem's (x, y) at each band edge, and for each height band from the base up the crown's reach "
    "from the stem (m) in each azimuth sector from -180 deg, counter-clockwise"
)


def draft_crown_space(measures, settings: list, fixed: list, notes: list) -> bool:
    """Add a tree's crown space to a growth model's recipe draft, for a decurrent or one-sided crown.

    The note why, the setting ``crown_envelope`` and ``envelope_shade`` fixed at 1 (no new free
    parameter), appended to the draft's lists; nothing for a crown a wood did not shape, or when
    ``measures`` carry no envelope (``bforest init --open-world``). Returns whether it
    added them.
    """
    why = measures.crown_space_why()
    if why is None:
        return False
    notes.append(why)
    settings.append(("crown_envelope", measures.envelope, f"Why: {why}. What: {SETTING_WHAT}."))
    fixed.append(("envelope_shade", 1.0, "no light outside the crown's space: the neighbours' (crown_envelope)"))
    return True


@dataclass(frozen=True)
class CrownEnvelope:
    """A star-shaped envelope of a crown (see the module text).

    Lengths in m, in the tree's frame with its stem base at the origin.

    Attributes
    ----------
    margin : float
        How far beyond the measured reach the envelope reaches: the one setting.
    base, top : float
        Height of the crown base and of the tree's top above the stem base.
    stem : (bands + 1, 2) array
        The stem's (x, y) at each band edge, from the crown base to the top.
    reach : (bands, sectors) array
        The crown's horizontal reach from the stem in each height band (from the base up) and
        azimuth sector (sector j covers azimuths from -180 + j * 360 / sectors deg, counter-clockwise
        from +x).
    """

    margin: float
    base: float
    top: float
    stem: np.ndarray
    reach: np.ndarray

    # ------------------------------------------------------------------ measuring
    @classmethod
    def measure(cls, tree, base: float, radius: float, margin: float | None = None) -> CrownEnvelope:
        """Measure the envelope of ``tree``'s crown (any reader's tree, or a model's).

        :func:`bforest_core.metrics.crown_envelope` measures its crown base and radius first.

        Parameters
        ----------
        tree : Tree
            The tree; its stem is its branch 0 (a QSM's own stem).
        base : float
            The crown base (m above the stem base).
        radius : float
            The crown radius (m): the margin's and the sampling's scale.
        margin : float, optional
            The margin (m); default :data:`MARGIN_SHARE` of the crown radius.

        Returns
        -------
        CrownEnvelope

        Raises
        ------
        ValueError
            For a tree without a crown above its crown base (no first-order branch).
        """
        z0 = tree.start[0]
        top = float(max(tree.start[:, 2].max(), tree.end[:, 2].max()) - z0[2])
        if not np.isfinite(base) or top <= base:
            raise ValueError("no crown: the tree has no first-order branch above a crown base")
        margin = MARGIN_SHARE * radius if margin is None else float(margin)
        if not (np.isfinite(margin) and margin >= 0):
            raise ValueError(f"the margin must be a length >= 0 (m), got {margin!r}")
        edges = base + (top - base) * np.arange(BANDS + 1) / BANDS
        stem = stem_at(tree, edges)[:, :2]
        pts = _samples(tree, max(STEP_SHARE * radius, 1e-3)) - z0
        env = cls(margin, float(base), top, stem, np.zeros((BANDS, SECTORS)))
        d = pts[:, :2] - env._centre(pts[:, 2])
        cell = env._band(pts[:, 2]) * SECTORS + env._sector(np.arctan2(d[:, 1], d[:, 0]))
        keep = (pts[:, 2] >= base) & (pts[:, 2] <= top)
        reach = np.zeros(BANDS * SECTORS)
        np.maximum.at(reach, cell[keep], np.hypot(d[keep, 0], d[keep, 1]))
        return cls(margin, float(base), top, stem, reach.reshape(BANDS, SECTORS))

    def _centre(self, z: np.ndarray) -> np.ndarray:
        """Return the stem's (x, y) at heights ``z``.

        Between its band-edge points, held above the top; below the crown base on the straight
        line from the stem base (the origin) to the stem at the crown base.
        """
        bands = self.reach.shape[0]
        z = np.asarray(z, float)
        t = np.clip((z - self.base) / (self.top - self.base) * bands, 0.0, bands)
        xy = np.stack([np.interp(t, np.arange(bands + 1), self.stem[:, k]) for k in (0, 1)], axis=-1)
        low = np.clip(z / max(self.base, 1e-9), 0.0, 1.0)[..., None] * self.stem[0]
        return np.where((z < self.base)[..., None], low, xy)

    def _sector(self, az: np.ndarray) -> np.ndarray:
        """Return the sector of azimuths ``az`` (radians, counter-clockwise from +x)."""
        sectors = self.reach.shape[1]
        return np.floor((az + np.pi) / (2.0 * np.pi) * sectors).astype(np.int64) % sectors

    def _band(self, z: np.ndarray) -> np.ndarray:
        """Return the band of heights ``z``: -1 below the crown base, the top band above the top."""
        bands = self.reach.shape[0]
        u = np.floor((np.asarray(z, float) - self.base) / (self.top - self.base) * bands)
        return np.where(u < 0, -1, np.minimum(u, bands - 1)).astype(np.int64)

    def _reach(self, points: np.ndarray):
        """Return the reach at each point and the point's horizontal distance from the stem.

        The reach (without the margin) of the point's band and its sector about the stem at its
        height; below the crown base the crown's widest reach in the sector, over all its bands.
        """
        d = points[:, :2] - self._centre(points[:, 2])
        sector = self._sector(np.arctan2(d[:, 1], d[:, 0]))
        return self._rows()[self._band(points[:, 2]), sector], np.hypot(d[:, 0], d[:, 1])

    def _rows(self) -> np.ndarray:
        """Return the reaches by band, and after them (row -1) the widest of each sector."""
        return np.vstack([self.reach, self.reach.max(axis=0)])

    # ------------------------------------------------------------------ reading
    def light(self, points, stem=None) -> np.ndarray:
        """Return the share of the light that reaches each point in the crown's space.

        1 within the tree's reach, 0 beyond the margin, falling linearly across it (above the
        top, the top band's reach: no lid).

        Parameters
        ----------
        points : (m, 3) array_like
            Points in the tree's frame (stem base at the origin).
        stem : (k, 3) array_like, optional
            The growing tree's own stem, points (x, y, z) from its base: within the margin of it
            (at each point's height, and up to the margin above its top, not above the envelope's)
            the light falls off as beyond the envelope's reach, and the larger of the two holds.

        Returns
        -------
        (m,) float array in [0, 1]
        """
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        reach, r = self._reach(p)
        f = self._fall(r - reach)  # no lid: the height is the fit's (its size term), not the envelope's
        if stem is not None:  # the growing tree's own stem: a corridor of the margin's width
            path = np.asarray(stem, dtype=np.float64).reshape(-1, 3)
            d = p[:, :2] - path_at(path, p[:, 2])[:, :2]
            corridor = self._fall(np.hypot(d[:, 0], d[:, 1])) * self._fall(p[:, 2] - min(path[:, 2].max(), self.top))
            f = np.maximum(f, corridor)
        return f

    def side(self, points) -> np.ndarray:
        """Return the crown's reach in each point's direction over its band's widest reach.

        The reach between the sectors' middles is linear in the azimuth about the stem (at the
        point's height), so it changes smoothly round the stem; below the crown base the widest
        reach of each sector over the bands holds (as in :meth:`light`). A wood's crown reaches
        far where its neighbours stand far and short where they stand near: this is how open the
        point's side of the crown is, 1 on the side where the crown reaches farthest.

        Parameters
        ----------
        points : (m, 3) array_like
            Points in the tree's frame (stem base at the origin).

        Returns
        -------
        (m,) float array in [0, 1] (1 for a band that reaches nowhere)
        """
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        rows = self._rows()[self._band(p[:, 2])]
        sectors = rows.shape[1]
        d = p[:, :2] - self._centre(p[:, 2])
        u = (np.arctan2(d[:, 1], d[:, 0]) + np.pi) / (2.0 * np.pi) * sectors - 0.5  # 0 at sector 0's middle
        j = np.floor(u).astype(np.int64)
        t = u - j
        k = np.arange(len(p))
        reach = (1.0 - t) * rows[k, j % sectors] + t * rows[k, (j + 1) % sectors]
        widest = rows.max(axis=1)
        return np.where(widest > 0, reach / np.where(widest > 0, widest, 1.0), 1.0)

    def _fall(self, beyond: np.ndarray) -> np.ndarray:
        """Light left ``beyond`` metres past an edge: 1 within it, 0 past the margin, linear between."""
        if self.margin > 0:
            return np.clip(1.0 - beyond / self.margin, 0.0, 1.0)
        return (beyond <= 0).astype(float)

    def contains(self, points) -> np.ndarray:
        """Tell whether each point lies inside the envelope.

        Inside: any light at all (:meth:`light` > 0), or on its edge.
        """
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        reach, r = self._reach(p)
        return r <= reach + self.margin

    def outline(self, z: float, step_deg: float = 2.0) -> np.ndarray:
        """Return the envelope's horizontal outline (with the margin) at height ``z``.

        A closed polygon (k, 2) of the sectors' arcs about the stem (above the top, the top band's).
        """
        az = np.radians(np.arange(-180.0, 180.0 + 1e-9, step_deg))
        rr = self._rows()[int(self._band(z)), self._sector(az)] + self.margin
        return self._centre(z) + rr[:, None] * np.stack([np.cos(az), np.sin(az)], axis=1)

    # ------------------------------------------------------------------ as a setting
    def setting(self, digits: int = 2) -> dict:
        """Return the envelope as a recipe's setting.

        The margin, the crown base and top, the stem's (x, y) per band edge and the reaches per
        band, lengths rounded to ``digits`` decimals (cm).
        """
        rnd = lambda a: [[round(float(x), digits) for x in row] for row in a]  # noqa: E731
        return {
            "margin": round(float(self.margin), digits),
            "base": round(float(self.base), digits),
            "top": round(float(self.top), digits),
            "stem": rnd(self.stem),
            "reach": rnd(self.reach),
        }

    @classmethod
    def from_setting(cls, value: Mapping) -> CrownEnvelope:
        """Return the envelope of a setting (:meth:`setting`); ``ValueError`` names the key that is wrong."""
        if not isinstance(value, Mapping):
            raise ValueError(f"a crown envelope is a table of {', '.join(KEYS)}, got {type(value).__name__}")
        missing = [k for k in KEYS if k not in value]
        extra = [k for k in value if k not in KEYS]
        if missing or extra:
            raise ValueError(
                f"a crown envelope has the keys {', '.join(KEYS)}"
                + (f"; missing {', '.join(missing)}" if missing else "")
                + (f"; unknown {', '.join(map(str, extra))}" if extra else "")
            )
        num = {}
        for k in KEYS:
            try:
                num[k] = np.asarray(value[k], dtype=np.float64)
            except (TypeError, ValueError):
                raise ValueError(f"crown envelope {k}: not numbers ({value[k]!r:.60})") from None
            if not np.isfinite(num[k]).all():
                raise ValueError(f"crown envelope {k}: holds a value that is not finite")
        reach, stem = num["reach"], num["stem"]
        if reach.ndim != 2 or reach.shape[0] < 1 or reach.shape[1] < 3:
            raise ValueError(
                f"crown envelope reach: one row of 3 or more sector reaches per height band, got shape {reach.shape}"
            )
        if stem.shape != (reach.shape[0] + 1, 2):
            raise ValueError(
                f"crown envelope stem: one (x, y) per band edge, {reach.shape[0] + 1} for {reach.shape[0]} "
                f"band(s), got shape {stem.shape}"
            )
        if (reach < 0).any() or num["margin"].ndim or num["margin"] < 0:
            raise ValueError("crown envelope reach and margin: lengths >= 0 (m)")
        if num["base"].ndim or num["top"].ndim or not num["top"] > num["base"] >= 0:
            raise ValueError(
                f"crown envelope base and top: heights with 0 <= base < top (m), got {value['base']!r}, {value['top']!r}"
            )
        return cls(float(num["margin"]), float(num["base"]), float(num["top"]), stem, reach)


#: the parameter ``envelope_shade`` of a growth model (a ``ParameterSpec``'s name, default, range
#: and unit), and what it means (each model says where it takes the light, and its group)
SHADE_SPEC = {"name": "envelope_shade", "default": 0.0, "lower": 0.0, "upper": 1.0, "integer": False, "unit": ""}
SHADE_MEANING = (
    "an addition: the share of the light the neighbours take outside the crown's envelope (the setting "
    "crown_envelope, the space the measured tree's crown fills)"
)


def _checked(value: dict) -> dict:
    if value:
        CrownEnvelope.from_setting(value)  # ValueError naming the key that is wrong
    return value


#: a growth model's setting ``crown_envelope`` (pydantic): a crown's space as :meth:`CrownEnvelope.setting`
#: writes it, checked when the settings are read; empty = none
EnvelopeSetting = Annotated[dict, AfterValidator(_checked)]
#: its description in the model's settings
SETTING_DESCRIPTION = (
    "an addition: the crown's space of the measured tree (margin, base, top, stem, reach: its reach from the "
    "stem per height band and azimuth sector, m), outside which the neighbours take the share envelope_shade "
    "of the light (`bforest init` writes it for a decurrent or one-sided crown, unless --open-world); empty = none; see "
    "docs/growth-forms.md"
)


def grown_in(setting: Mapping, shade: float) -> CrownEnvelope | None:
    """Return the crown's space a model grows in, or None (an open world).

    The envelope of its ``crown_envelope`` setting when its ``envelope_shade`` takes light outside it.
    """
    return CrownEnvelope.from_setting(setting) if shade > 0 and setting else None


def path_at(path: np.ndarray, heights) -> np.ndarray:
    """Return the points of a stem at ``heights``.

    Parameters
    ----------
    path : (k, 3) array
        The stem as points (x, y, z) from its base, base first.
    heights : float or array_like
        Heights in the frame of ``path``.

    Returns
    -------
    ndarray
        (..., 3) points, one per height: where the stem first rises to the height (between two of
        its points), its highest point above its top, its first point below it.
    """
    rise = np.maximum.accumulate(path[:, 2])
    keep = np.r_[True, np.diff(rise) > 0]  # where the stem reaches a new height
    z = np.clip(np.asarray(heights, dtype=np.float64), path[0, 2], rise[-1])
    return np.stack([np.interp(z, rise[keep], path[keep, k]) for k in range(3)], axis=-1)


def stem_at(tree, heights) -> np.ndarray:
    """Return the stem's points (x, y, z) at ``heights`` above the stem base, relative to the base.

    The stem is the tree's branch 0 (a QSM's own stem), a polyline through its cylinders from the
    base (:func:`path_at`: a height is met where the stem first rises to it, and above the stem's
    top its highest point holds).

    Parameters
    ----------
    tree : Tree
    heights : float or array_like
        Heights (m) above the start of the root cylinder.

    Returns
    -------
    ndarray
        (..., 3) points, one per height.
    """
    cyl = np.flatnonzero(tree.order == 0)  # in row order, so base first
    return path_at(np.vstack([tree.start[cyl], tree.end[cyl[-1]]]) - tree.start[0], heights)


def _samples(tree, step: float) -> np.ndarray:
    """Return points along every cylinder's axis, its ends among them, no farther apart than ``step``."""
    k = np.maximum(1, np.ceil(tree.length / step).astype(np.int64))
    row = np.repeat(np.arange(tree.n), k + 1)
    first = np.cumsum(k + 1) - (k + 1)
    t = (np.arange(row.size) - first[row]) / k[row]
    return tree.start[row] + (t * tree.length[row])[:, None] * tree.axis[row]
