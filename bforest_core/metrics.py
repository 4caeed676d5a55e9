"""Tree metrics.

The classical ones (height, DBH, base diameter, crown spread) with their relative errors, the
tree-level summary statistics a forester checks (:func:`tree_summary`) and the per-order table of
branches (:func:`order_summary`).

"Girth" in the papers (GS) is the *base diameter* (2 x radius of the root cylinder), not a
circumference; :func:`classical_metrics` returns it as ``base_diameter`` and keeps ``girth`` as
an alias of it for the papers' d_g.

Reference: docs/features-and-distance.md §5 (GS Methods IV "traditional metrics", after the
toolbox's ``tree_basic_metrics.m`` with its defects fixed). Base point = start of the root
cylinder; point set = all cylinder start and end points.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Literal

import numpy as np

from .envelope import CrownEnvelope, stem_at

__all__ = [
    "classical_metrics",
    "relative_errors",
    "crown_spread",
    "crown_offset",
    "crown_envelope",
    "dbh",
    "tree_summary",
    "ruled_summary",
    "order_summary",
    "SUMMARY_DEFAULT",
    "SIZE_WEIGHTS",
    "SIZE_TOLERANCES",
    "SELECT_SIZES",
    "checked_fractions",
    "SIZE_LIMITS",
    "OFFSET_TOLERANCE",
    "OFFSET_TOLERANCES",
    "tolerance_weights",
    "tolerance_limits",
    "SIGNED_UNITS",
    "SUMMARY_UNITS",
    "summary_unit",
    "summary_label",
    "branching_angles",
    "TreeMeasures",
    "measure_tree",
    "DECURRENT_LIMB_RATIO",
    "ONE_SIDED",
]

BREAST_HEIGHT = 1.3  # m
_RHO_EPS = 1e-9  # m; points closer than this to the vertical through the base have no direction


def _points(tree) -> np.ndarray:
    return np.concatenate([tree.start, tree.end], axis=0)


def crown_spread(tree, spoke_step: float = 10.0, empty_sectors: Literal["zero", "drop"] = "zero") -> float:
    """Crown spread (m): twice the mean of the longest horizontal spokes per sector.

    Parameters
    ----------
    tree : Tree
    spoke_step : float
        Sector width in degrees; must divide 360.
    empty_sectors : {"zero", "drop"}
        ``zero`` counts an empty sector as a spoke of length 0 (GS "all spokes"); ``drop``
        averages the non-empty sectors only (toolbox).

    Returns
    -------
    float
        The crown spread in metres.

    Raises
    ------
    ValueError
        If ``spoke_step`` is not a positive divisor of 360 or ``empty_sectors`` is unknown.

    Notes
    -----
    Every start and end point with a horizontal distance rho > 1e-9 m from the base point gets
    the sector ``floor((phi + 180) / step) mod (360 / step)`` with ``phi`` its angle about the
    base point (half-open sectors). Spoke = largest rho in the sector.
    """
    if empty_sectors not in ("zero", "drop"):
        raise ValueError(f"empty_sectors must be 'zero' or 'drop', got {empty_sectors!r}")
    step = float(spoke_step)
    nsec_f = 360.0 / step if step > 0 else float("nan")
    nsec = int(round(nsec_f)) if np.isfinite(nsec_f) else 0
    if nsec < 1 or abs(nsec - nsec_f) > 1e-9:
        raise ValueError(f"spoke_step must be a positive divisor of 360 degrees, got {spoke_step!r}")
    base = tree.start[0]
    pts = _points(tree)
    dx = pts[:, 0] - base[0]
    dy = pts[:, 1] - base[1]
    rho = np.hypot(dx, dy)
    keep = rho > _RHO_EPS
    if not keep.any():
        return 0.0
    phi = np.degrees(np.arctan2(dy[keep], dx[keep]))
    sector = np.floor((phi + 180.0) / step).astype(np.int64) % nsec
    spokes = np.zeros(nsec)
    np.maximum.at(spokes, sector, rho[keep])
    if empty_sectors == "drop":
        filled = np.zeros(nsec, dtype=bool)
        filled[sector] = True
        return float(2.0 * spokes[filled].mean())
    return float(2.0 * spokes.mean())


def crown_offset(tree) -> np.ndarray:
    """Return the crown's offset from the stem, in crown radii: which side of the stem the crown lies.

    The horizontal vector from the stem, taken at the height of the crown's centre
    (:func:`stem_at`), to the centre of the branches above the crown base (cylinders of order 1 and
    up whose midpoint lies at or above :func:`crown_base_height`, weighted by wood volume), divided
    by the crown radius (half :func:`crown_spread`). A crown all around its stem lies near 0; a
    crown grown to one side, where a neighbour took the other, lies half a radius or more off it.

    Parameters
    ----------
    tree : Tree
        A QSM, or a model's tree (its stem: its branch 0).

    Returns
    -------
    ndarray
        (x, y) in crown radii (x, y as the tree's file has them); (0, 0) for a tree without branches
        above its crown base.
    """
    cb = crown_base_height(tree)
    vol = np.pi * tree.radius**2 * tree.length
    mid = tree.start + 0.5 * tree.length[:, None] * tree.axis - tree.start[0]
    crown = (tree.order > 0) & (mid[:, 2] >= cb) if np.isfinite(cb) else np.zeros(tree.n, bool)
    radius = 0.5 * crown_spread(tree)
    if not (vol[crown].sum() > 0 and radius > 0):
        return np.zeros(2)
    centre = (mid[crown] * vol[crown, None]).sum(0) / vol[crown].sum()
    return (centre[:2] - stem_at(tree, centre[2])[:2]) / radius


def crown_envelope(tree, margin: float | None = None) -> CrownEnvelope:
    """Return the crown's space of ``tree``: its star-shaped envelope above the crown base.

    Parameters
    ----------
    tree : Tree
    margin : float, optional
        How far beyond the tree's own reach the envelope reaches (m); default
        :data:`~bforest_core.envelope.MARGIN_SHARE` of the crown radius.

    Returns
    -------
    CrownEnvelope
        See :mod:`bforest_core.envelope`; measured above :func:`crown_base_height`, with the crown
        radius half :func:`crown_spread`.
    """
    return CrownEnvelope.measure(tree, crown_base_height(tree), 0.5 * crown_spread(tree), margin)


def dbh(tree, breast_height: float = BREAST_HEIGHT, warn: bool = True) -> float:
    """Diameter (m) of the first trunk cylinder (base to tip) spanning ``breast_height``.

    The trunk is branch 0 of the tree's own topology. A cylinder spans the height when
    ``min(z_s, z_e) - z0 <= h <= max(z_s, z_e) - z0``.

    Parameters
    ----------
    tree : Tree
        The tree.
    breast_height : float, optional
        Height (m) above the start of the root cylinder.
    warn : bool, optional
        Warn when no trunk cylinder spans the height.

    Returns
    -------
    float
        The diameter in metres; NaN when no trunk cylinder spans the height.

    Warns
    -----
    RuntimeWarning
        With ``warn``, when the DBH is NaN.
    """
    bt = tree.branches
    trunk = bt.cylinders[bt.ptr[0] : bt.ptr[1]]
    z0 = tree.start[0, 2]
    zs = tree.start[trunk, 2] - z0
    ze = tree.end[trunk, 2] - z0
    hit = np.flatnonzero((np.minimum(zs, ze) <= breast_height) & (breast_height <= np.maximum(zs, ze)))
    if hit.size == 0:
        if warn:
            src = tree.metadata.get("source") or tree.metadata.get("model") or "tree"
            warnings.warn(
                f"{src}: no trunk cylinder spans breast height {breast_height} m above the "
                f"base (trunk reaches {float(max(zs.max(), ze.max())):.3f} m); DBH is NaN",
                RuntimeWarning,
                stacklevel=2,
            )
        return float("nan")
    return float(2.0 * tree.radius[trunk[hit[0]]])


def classical_metrics(
    tree,
    girth: Literal["base", "dbh"] = "base",
    spoke_step: float = 10.0,
    empty_sectors: Literal["zero", "drop"] = "zero",
) -> dict[str, float]:
    """Height, girth, DBH and crown spread of a tree, in metres (docs/features-and-distance.md §5).

    Parameters
    ----------
    tree : Tree
    girth : {"base", "dbh"}
        ``base``: 2 x radius of the root cylinder (GS); ``dbh``: the diameter at 1.3 m
        (:func:`dbh`, NaN with a warning when the trunk is shorter).
    spoke_step, empty_sectors
        See :func:`crown_spread`.

    Returns
    -------
    dict
        ``height`` (highest start/end point minus the base z), ``girth`` (as chosen: the
        base diameter by default, *not* a circumference), ``base_diameter`` (2 x the root
        cylinder's radius), ``dbh`` (always the diameter at 1.3 m, NaN if none) and
        ``crown_spread``.

    Raises
    ------
    ValueError
        For an unknown ``girth`` or a bad ``spoke_step``/``empty_sectors``.
    """
    if girth not in ("base", "dbh"):
        raise ValueError(f"girth must be 'base' or 'dbh', got {girth!r}")
    z0 = tree.start[0, 2]
    height = float(max(tree.start[:, 2].max(), tree.end[:, 2].max()) - z0)
    d = dbh(tree, warn=(girth == "dbh"))
    g = d if girth == "dbh" else float(2.0 * tree.radius[0])
    return {
        "height": height,
        "girth": g,
        "base_diameter": float(2.0 * tree.radius[0]),
        "dbh": d,
        "crown_spread": crown_spread(tree, spoke_step, empty_sectors),
    }


def relative_errors(data_metrics: Mapping[str, float], model_metrics: Mapping[str, float]) -> dict:
    """Relative errors ``d_x = |x_d - x_m| / x_d`` of height, girth and crown spread (GS).

    Parameters
    ----------
    data_metrics : dict
        Metrics of the QSM (``height``, ``girth``, ``crown_spread``).
    model_metrics : dict
        Metrics of the model tree; values may be arrays (one entry per clone), giving arrays.

    Returns
    -------
    dict
        ``d_h``, ``d_g``, ``d_c`` (floats, or arrays for array input; NaN where the data value
        is 0 or missing).

    Raises
    ------
    KeyError
        If ``height``, ``girth`` or ``crown_spread`` is missing from either mapping.
    """
    out = {}
    for key, name in (("d_h", "height"), ("d_g", "girth"), ("d_c", "crown_spread")):
        if name not in data_metrics or name not in model_metrics:
            raise KeyError(
                f"relative_errors: '{name}' missing from the {'data' if name not in data_metrics else 'model'} metrics"
            )
        xd = float(data_metrics[name])
        xm = np.asarray(model_metrics[name], dtype=np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            r = np.abs(xd - xm) / xd if xd != 0 else np.full(xm.shape, np.nan)
        out[key] = float(r) if r.ndim == 0 else r
    return out


# ------------------------------------------------------------------------------ tree summary
#: the error a forester tolerates in the clones' mean of each headline statistic (a fraction of
#: the tree's value; the limits of docs/validation.md section 4)
SIZE_TOLERANCES = {"height": 0.075, "dbh": 0.20, "crown_spread": 0.25, "crown_base_height": 0.30, "n_branches_o1": 0.30}
#: how far (crown radii) the clones' mean crown offset may lie from the tree's (a vector,
#: :func:`crown_offset`): seen from above, a half-moon crown 0.9 radii off its stem and clones whose
#: crowns sit all around theirs (0.2-0.4 radii off, every way) differ by more
OFFSET_TOLERANCE = 0.25
#: the crown's side as a size term holds it: each component of the offset within the tolerance
OFFSET_TOLERANCES = {"crown_offset_x": OFFSET_TOLERANCE, "crown_offset_y": OFFSET_TOLERANCE}


def tolerance_weights(tolerances: Mapping[str, float]) -> dict[str, float]:
    """Return a size term's weight of each statistic: the inverse of its tolerance (to 0.1)."""
    return {k: round(1.0 / t, 1) for k, t in tolerances.items()}


def tolerance_limits(tolerances: Mapping[str, float]) -> dict[str, float]:
    """Return where a size term turns steep for each statistic: two thirds of its tolerance (to 0.01)."""
    return {k: round(2.0 / 3.0 * t, 2) for k, t in tolerances.items()}


#: what a size term weighs by default: each headline statistic by the inverse of its tolerance
#: (13.3, 5, 4, 3.3, 3.3); a model's recipe may weigh some of them otherwise
#: (``RecipeDraft.size_weights``)
SIZE_WEIGHTS = tolerance_weights(SIZE_TOLERANCES)
#: where a size term may turn steep (the summary distance's ``limits``, ``RecipeDraft.size_limits``):
#: two thirds of each tolerance, so that a fit judged on a few model seeds keeps its clones' mean
#: inside the tolerance
SIZE_LIMITS = tolerance_limits(SIZE_TOLERANCES)
#: what the candidate answers' held-out trees must keep on average to come first (``[select]
#: sizes``): four fifths of each tolerance, as the mean of 16 held-out trees differs from the mean
#: of the 30 clones by up to a tenth of the tolerance for 9 in 10 candidates of SOT's short fits on
#: the pines, a third for LIGNUM's (docs/notes/2026-12-07-select-sizes.md)
SELECT_SIZES = {k: round(0.8 * t, 3) for k, t in SIZE_TOLERANCES.items()}


def checked_fractions(v: dict, what: str) -> dict:
    """Check that every relative error of ``v`` (statistic -> error) lies between 0 and 1.

    Returns ``v``; ValueError naming ``what`` and the values at fault otherwise (a config check).
    """
    bad = {k: x for k, x in v.items() if not 0 < x < 1}
    if bad:
        raise ValueError(f"{what} are relative errors between 0 and 1 (exclusive): {bad}")
    return v


#: the statistics of the summary set by default (``tree-summary``): size, stem, crown, branch
#: counts and the vertical profile
SUMMARY_DEFAULT = (
    "height",
    "dbh",
    "crown_spread",
    "crown_base_height",
    "n_branches_o1",
    "n_branches_o2",
    "length_o1",
    "length_o2",
    "volume_o0",
    "profile_len_b0",
    "profile_len_b1",
    "profile_len_b2",
    "profile_len_b3",
    "profile_len_b4",
)

#: unit of each summary statistic, by name prefix (longest prefix wins)
SUMMARY_UNITS = {
    "height": "m",
    "dbh": "m",
    "base_diameter": "m",
    "crown_spread": "m",
    "crown_base_height": "m",
    "stem_length": "m",
    "n_branches": "count",
    "n_whorls": "count",
    "length": "m",
    "volume": "m^3",
    "profile_n": "count",
    "profile_len": "m",
    "n_all_branches": "count",
    "angle": "deg",
    "angle_iqr": "deg",
    "trunk_volume": "m^3",
    "branch_volume": "m^3",
    "crown_diameter_mean": "m",
    "crown_area_conv": "m^2",
    "crown_length": "m",
    "crown_ratio": "fraction",
    "crown_volume_conv": "m^3",
    "crown_offset": "crown radii",
}
#: share of the living first-order branch length that may lie below the crown base
CROWN_BASE_SHARE = 0.05
#: base diameter (m) below which a branch is left out of the branch counts, lengths and profile:
#: a QSM from terrestrial laser scanning rarely resolves thinner branches, so a model tree,
#: which holds every twig, is compared with what a scan of it would show
DETECTION_DIAMETER = 0.01
#: height (m) between the bases of two first-order branches at or below which they belong to one
#: whorl: a conifer sets one whorl a year at the top of that year's leader shoot (on the Ruotsinkylä
#: pines 0.3-0.5 m apart, the median), and a QSM places the branches of one whorl a few cm apart
WHORL_GAP = 0.15


#: units of signed statistics: no ratio of two of them means anything, their difference does
SIGNED_UNITS = frozenset({"crown radii"})


def summary_unit(name: str) -> str:
    """Return the unit of a summary statistic (``"length_o2"`` -> ``"m"``).

    Parameters
    ----------
    name : str
        The statistic's name, as in :func:`tree_summary`.

    Returns
    -------
    str
        The unit of the longest entry of :data:`SUMMARY_UNITS` that ``name`` is or starts with
        (followed by ``_``); ``""`` for none.
    """
    best = max((k for k in SUMMARY_UNITS if name == k or name.startswith(k + "_")), key=len, default=None)
    return SUMMARY_UNITS[best] if best is not None else ""


#: what the measures a forester might take for one another mean, one line each (``bforest info``,
#: the fidelity table): the papers' crown spread and TreeQSM's crown diameter differ by design
DEFINITIONS = {
    "crown_spread": "crown spread: twice the mean, over 36 sectors of 10 deg around the stem base, of the "
    "longest horizontal reach of the tree in the sector (the papers' measure; an empty sector counts 0)",
    "crown_diameter_mean": "crown diameter, mean: TreeQSM's, the mean of 18 diameters through the centre of "
    "the crown's outline seen from above (each the farthest branch tip in a 10 deg sector plus the "
    "farthest in the opposite one)",
    "crown_offset": "crown's offset from its stem: the horizontal vector from the stem, taken at the height of "
    "the crown's centre, to the centre of the branches above the crown base (weighted by wood volume), in "
    "crown radii (half the crown spread), and its direction counter-clockwise from +x; its error is the "
    "distance from the clones' mean vector to the target's",
}


def summary_definition(name: str) -> str | None:
    """Say what a statistic means, when its name alone leaves a forester guessing.

    Parameters
    ----------
    name : str
        The statistic's name, as in :func:`tree_summary` or a TreeQSM attribute.

    Returns
    -------
    str or None
        One line (``"crown spread: ..."``), or None for a statistic its label explains.
    """
    return DEFINITIONS.get(name)


def summary_label(name: str, bands: int = 5) -> str:
    """Say what a summary statistic is, in words.

    ``"profile_n_b0"`` -> ``"order-1 branches based at 0-20 % of the height"``.

    Parameters
    ----------
    name : str
        The statistic's name, as in :func:`tree_summary`.
    bands : int, optional
        Number of height bands of the profile statistics.

    Returns
    -------
    str
        The description; the name itself for one this function does not know.
    """
    fixed = {
        "height": "height",
        "dbh": "DBH (1.3 m)",
        "base_diameter": "base diameter",
        "crown_spread": "crown spread",
        "crown_base_height": "crown base height",
        "stem_length": "stem length",
        "n_whorls": f"whorls of first-order branches, dead ones too (bases within {100 * WHORL_GAP:g} cm are one)",
        "trunk_volume": "trunk volume",
        "branch_volume": "branch volume",
        "crown_diameter_mean": "crown diameter, mean",
        "crown_area_conv": "crown area (convex hull)",
        "crown_length": "crown length",
        "crown_ratio": "crown ratio",
        "crown_volume_conv": "crown volume (convex hull)",
        "crown_offset": "crown's offset from its stem",
        "crown_offset_x": "crown's offset from its stem, x",
        "crown_offset_y": "crown's offset from its stem, y",
    }
    if name in fixed:
        return fixed[name]
    head, _, tail = name.rpartition("_")
    if not tail[1:].isdigit():
        return name
    k = int(tail[1:])
    if tail[0] == "o":
        return {
            "n_branches": f"branches of order {k} (base >= {100 * DETECTION_DIAMETER:g} cm)",
            "n_all_branches": f"branches of order {k} (all)",
            "length": f"length of order-{k} branches (base >= {100 * DETECTION_DIAMETER:g} cm)",
            "volume": "stem (trunk) wood volume" if k == 0 else f"wood volume of order {k}",
            "angle": f"branching angle of order-{k} branches, median",
            "angle_iqr": f"branching angle of order-{k} branches, interquartile range",
        }.get(head, name)
    if tail[0] == "b" and head in ("profile_n", "profile_len"):
        lo, hi = 100 * k / bands, 100 * (k + 1) / bands
        what = "order-1 branches" if head == "profile_n" else "length of order-1 branches"
        return f"{what} based at {lo:g}-{hi:g} % of the height"
    return name


def _living(tree) -> np.ndarray:
    """Tell, per branch, whether it holds a living cylinder.

    Models mark dead remnants in ``extras["is_dead"]``; a QSM has none, so all its branches count.
    """
    dead = tree.extras.get("is_dead") if tree.extras else None
    if dead is None:
        return np.ones(tree.n_branches, bool)
    alive = np.bincount(tree.branch, weights=~np.asarray(dead, bool), minlength=tree.n_branches)
    return alive > 0


def crown_base_height(tree, share: float = CROWN_BASE_SHARE) -> float:
    """Return the crown base height (m above the stem base).

    That is the branch-base height below which only ``share`` of the living first-order branch
    length sits. The lowest living first-order branch itself is a fragile definition on real data: a QSM
    carries stray stubs near the ground (on the Ruotsinkylä pines 0.2-0.6 m) that no forester
    would call the crown, and a model may keep one survivor far below the others. Weighting
    branch bases by branch length lets such stubs move the crown base only as much as their
    length weighs.

    Parameters
    ----------
    tree : Tree
        The tree (a model's dead remnants, ``extras["is_dead"]``, are left out).
    share : float, optional
        Share (0-1) of the living first-order branch length allowed below the crown base.

    Returns
    -------
    float
        Height in metres above the start of the root cylinder; NaN for a tree without living
        first-order branches.
    """
    br = tree.branches
    z0 = tree.start[0, 2]
    blen = np.bincount(tree.branch, weights=tree.length, minlength=len(br))
    keep = (br.order == 1) & _living(tree)
    if not keep.any():
        return float("nan")
    z = tree.start[br.first[keep], 2] - z0
    w = blen[keep]
    order = np.argsort(z, kind="stable")
    cum = np.cumsum(w[order])
    k = int(np.searchsorted(cum, share * cum[-1], side="right"))
    return float(z[order][min(k, z.size - 1)])


def whorls(tree, min_diameter: float = DETECTION_DIAMETER, gap: float = WHORL_GAP) -> list[np.ndarray]:
    """Group the first-order branches into whorls by the height of their base.

    A branch whose base lies at most ``gap`` m above the base of the one below it (sorted by
    height) belongs to that one's whorl: a conifer's yearly whorls along its stem (a broadleaved
    tree's first-order branches group the same way, without the meaning). Dead branches count: a
    dead branch marks its year's whorl as a living one does, and a scan cannot tell them apart (a
    model's dead remnants, ``extras["is_dead"]``, are kept, unlike in the branch counts).

    Parameters
    ----------
    tree : Tree
        The tree.
    min_diameter : float, optional
        Branches thinner than this (m) at the base are left out (:data:`DETECTION_DIAMETER`).
    gap : float, optional
        :data:`WHORL_GAP`.

    Returns
    -------
    list of ndarray
        One array per whorl, lowest first: the heights (m above the stem base) of its branches'
        bases, ascending. Empty for a tree without such branches.
    """
    br = tree.branches
    keep = (br.order == 1) & (2.0 * tree.radius[br.first] >= min_diameter)
    z = np.sort(tree.start[br.first[keep], 2] - tree.start[0, 2])
    if z.size == 0:
        return []
    return np.split(z, np.flatnonzero(np.diff(z) > gap) + 1)


def ruled_summary(tree, topology: str | None = None, statistics=None, **options) -> dict[str, float]:
    """:func:`tree_summary` with branches chosen by another topology rule.

    Parameters
    ----------
    tree : Tree
        The tree.
    topology : {"source", "subtree", "thickest"} or None, optional
        The branch rule (:meth:`Tree.with_topology`); None keeps the tree's own branches.
    statistics : sequence of str, optional
        The statistics measured by ``topology`` (default: all); the others by the tree's own
        branches.
    **options
        Passed to :func:`tree_summary`.

    Returns
    -------
    dict of str to float
        The statistics of :func:`tree_summary`.
    """
    if topology is None:
        return tree_summary(tree, **options)
    ruled = tree_summary(tree.with_topology(topology), **options)
    if statistics is None:
        return ruled
    return {**tree_summary(tree, **options), **{k: ruled[k] for k in statistics if k in ruled}}


def tree_summary(
    tree, max_order: int = 3, bands: int = 5, min_diameter: float = DETECTION_DIAMETER
) -> dict[str, float]:
    """Tree-level summary statistics, one implementation for QSMs and model trees.

    Parameters
    ----------
    tree : Tree
    max_order : int
        Branch orders 1..max_order get their own counts and lengths (0..max_order volumes).
    bands : int
        Height bands of the vertical profile: band k covers ``[k, k+1) / bands`` of the tree
        height (branch bases at the very top fall in the last band).
    min_diameter : float
        Detection limit (m): branches whose first cylinder is thinner are left out of the
        counts, lengths and profile (:data:`DETECTION_DIAMETER`; 0 counts every branch).

    Returns
    -------
    dict
        ``height``, ``dbh``, ``base_diameter``, ``crown_spread``, ``crown_base_height``,
        ``stem_length`` (m); ``crown_offset_x`` and ``crown_offset_y`` (the crown's offset from its
        stem, :func:`crown_offset`, crown radii: signed, compared by their difference); ``n_whorls`` (whorls of the first-order branches at least ``min_diameter`` thick,
        dead ones too, :func:`whorls`); per order w: ``n_branches_o{w}`` (living branches at least
        ``min_diameter`` thick at the base), ``n_all_branches_o{w}`` (every living branch),
        ``length_o{w}`` (the counted branches' total length, m), ``volume_o{w}`` (wood volume,
        m^3, of every cylinder, dead remnants included, order 0 = the stem), ``angle_o{w}`` and
        ``angle_iqr_o{w}`` (median and interquartile range, deg, of the counted branches'
        branching angles, :func:`branching_angles`; NaN without such branches); the profile
        ``profile_n_b{k}`` and ``profile_len_b{k}`` (counted first-order branches whose base lies
        in band k, and their length). Units: :func:`summary_unit`.
    """
    m = classical_metrics(tree)
    br = tree.branches
    order = tree.order
    blen = np.bincount(tree.branch, weights=tree.length, minlength=len(br))
    living = _living(tree)
    seen = living & (2.0 * tree.radius[br.first] >= min_diameter)
    vol = np.pi * tree.radius**2 * tree.length
    angle = branching_angles(tree)
    out = {
        "height": m["height"],
        "dbh": m["dbh"],
        "base_diameter": m["base_diameter"],
        "crown_spread": m["crown_spread"],
        "crown_base_height": crown_base_height(tree),
        "stem_length": float(tree.length[order == 0].sum()),
        "n_whorls": float(len(whorls(tree, min_diameter))),
    }
    out["crown_offset_x"], out["crown_offset_y"] = (float(c) for c in crown_offset(tree))
    for w in range(1, max_order + 1):
        sel = (br.order == w) & seen
        out[f"n_branches_o{w}"] = float(np.count_nonzero(sel))
        out[f"n_all_branches_o{w}"] = float(np.count_nonzero((br.order == w) & living))
        out[f"length_o{w}"] = float(blen[sel].sum())
        a = angle[sel & np.isfinite(angle)]
        q25, q50, q75 = np.percentile(a, [25, 50, 75]) if a.size else (np.nan,) * 3
        out[f"angle_o{w}"], out[f"angle_iqr_o{w}"] = float(q50), float(q75 - q25)
    for w in range(0, max_order + 1):
        out[f"volume_o{w}"] = float(vol[order == w].sum())
    o1 = (br.order == 1) & seen
    rel = (tree.start[br.first[o1], 2] - tree.start[0, 2]) / max(m["height"], 1e-12)
    band = np.clip(np.floor(rel * bands).astype(np.int64), 0, bands - 1)
    counts = np.bincount(band, minlength=bands)
    lengths = np.bincount(band, weights=blen[o1], minlength=bands)
    for k in range(bands):
        out[f"profile_n_b{k}"] = float(counts[k])
        out[f"profile_len_b{k}"] = float(lengths[k])
    return out


def axis_angles(tree, rows, other_rows) -> np.ndarray:
    """Angles (deg, 0-180) between the axes of the cylinders ``rows`` and ``other_rows``, pairwise."""
    cos = np.einsum("ij,ij->i", tree.axis[rows], tree.axis[other_rows])
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def branching_angles(tree) -> np.ndarray:
    """Return the branching angle of every branch, in degrees.

    The angle between a branch's first cylinder and the cylinder it grows from (B^w's beta,
    docs/features-and-distance.md); NaN for the stem.

    Parameters
    ----------
    tree : Tree

    Returns
    -------
    ndarray
        One angle per branch of ``tree.branches``, 0-180 deg.
    """
    br = tree.branches
    has_parent = br.parent_cyl >= 0
    ang = np.full(len(br), np.nan)
    ang[has_parent] = axis_angles(tree, br.first[has_parent], br.parent_cyl[has_parent])
    return ang


def order_summary(tree) -> list[dict]:
    """Summarise the branches per branch order (like rTwig's summarise).

    Parameters
    ----------
    tree : Tree
        The tree.

    Returns
    -------
    list of dict
        One row per order present, with ``order``, ``n_branches``, total ``length_m`` (m),
        wood ``volume_m3`` (m^3), ``mean_angle_deg`` (mean branching angle in degrees, between a
        branch's first cylinder and its parent cylinder; NaN for the stem) and
        ``mean_base_diameter_m`` (m).
    """
    br = tree.branches
    blen = np.bincount(tree.branch, weights=tree.length, minlength=len(br))
    bvol = np.bincount(tree.branch, weights=np.pi * tree.radius**2 * tree.length, minlength=len(br))
    angle = branching_angles(tree)
    if not len(br):
        return []
    order = np.asarray(br.order, dtype=np.int64)  # one pass per sum: linear in branches, whatever the orders
    count = np.bincount(order)
    has_angle = np.isfinite(angle)
    n_angle = np.bincount(order, weights=has_angle.astype(float), minlength=count.size)
    sum_angle = np.bincount(order, weights=np.where(has_angle, angle, 0.0), minlength=count.size)
    sums = {
        k: np.bincount(order, weights=v, minlength=count.size)
        for k, v in (("length_m", blen), ("volume_m3", bvol), ("base", 2.0 * tree.radius[br.first]))
    }
    rows = []
    for w in np.flatnonzero(count):
        rows.append(
            {
                "order": int(w),
                "n_branches": int(count[w]),
                "length_m": float(sums["length_m"][w]),
                "volume_m3": float(sums["volume_m3"][w]),
                "mean_angle_deg": float(sum_angle[w] / n_angle[w]) if n_angle[w] else float("nan"),
                "mean_base_diameter_m": float(sums["base"][w] / count[w]),
            }
        )
    return rows


def weighted_quantiles(x: np.ndarray, w: np.ndarray, qs) -> np.ndarray:
    """Compute weighted quantiles.

    The inverse of the weighted ECDF with the midpoint rule, so equal weights give numpy's
    'hazen' quantiles. Points of zero weight are left out.

    Parameters
    ----------
    x : ndarray
        The values.
    w : ndarray
        Their weights (non-negative, not all zero).
    qs : array_like
        Quantile levels in percent (0-100).

    Returns
    -------
    ndarray
        The quantiles, one per level.
    """
    x = np.asarray(x, float)
    w = np.asarray(w, float)
    keep = w > 0  # a point of zero weight is not in the distribution (it must not stretch a tail)
    x, w = x[keep], w[keep]
    o = np.argsort(x, kind="stable")
    ws = w[o]
    ws = ws / ws.sum()
    cdf = np.cumsum(ws) - 0.5 * ws
    return np.interp(np.asarray(qs, float) / 100.0, cdf, x[o])


# ------------------------------------------------------------------------------------------
# what a recipe is scaled from (`bforest init`)
# ------------------------------------------------------------------------------------------

#: a crown whose centre lies this many crown radii or more from its stem (at the centre's height,
#: :func:`crown_offset`) is one-sided: Wytham Woods' broadleaved trees 0.26-0.65 (tf1 0.26, tf3 and
#: tf5 0.62-0.65), the coffeetree 0.37, the Ruotsinkylä pines 0.04-0.17
ONE_SIDED = 1.0 / 3.0
#: wood of the three largest limbs over the stem's wood in the crown above which a crown is
#: decurrent (the stem divides into limbs, like a maple's) rather than excurrent (a leader to
#: the top, like a pine's): Scots pines 0.34-0.48, broadleaved trees of Wytham Woods 1.7-2.4
DECURRENT_LIMB_RATIO = 1.0


@dataclass(frozen=True)
class TreeMeasures:
    """What a recipe for a tree is scaled from (:func:`measure_tree`; lengths in m, angles in deg).

    Attributes
    ----------
    height, dbh, crown_spread, crown_base_height, crown_length : float
        As :func:`tree_summary` (crown length = height - crown base height).
    n_branches_o1 : int
        Living first-order branches (every one, whatever its diameter).
    max_order : int
        Highest branch order.
    branch_spacing : float
        Crown length per first-order branch (m): how far apart along the stem limbs arise.
    beta_q10, beta_q50, beta_q90 : float
        10, 50 and 90 % quantiles of the first-order branches' angles to their parent cylinder.
    limb_ratio : float
        Wood volume of the three largest first-order limbs (each with every branch it bears)
        over the stem's wood volume in the crown; above :data:`DECURRENT_LIMB_RATIO` the crown
        is decurrent.
    longest_limb : float
        Length (m) of the longest first-order branch.
    thinnest_branch : float
        Smallest base diameter (m) of a branch: a QSM simplified for its use (twigs removed)
        has a floor here.
    radius_length : float
        Median over the first-order branches of their base radius over their length.
    stem_rise : float
        Vertical component of the stem's first cylinder (1 = straight up).
    crown_offset, crown_azimuth : float
        How far (m) and towards which azimuth (deg, counterclockwise from +x) the centre of the
        crown's branches (length-weighted, above the crown base) lies from the stem base: a
        one-sided crown, grown towards a gap, lies a large part of its radius to one side.
    stem_lean : float
        Angle (deg) from the vertical of the chord of the stem's upper half, from the stem at
        half the tree's height to its highest point: a stem that bends over into a gap.
    stem_path : tuple of (x, y, z)
        The stem as the tree has it (its branch 0: a QSM's own stem), from its base, as points (m)
        relative to the base: the start of each stem cylinder, kept where it lies at least
        :data:`PATH_STEP` further along the stem than the last one kept, and the stem's end.
    stem_length : float
        Length (m) of the stem: its cylinders' lengths summed (:func:`tree_summary`'s ``stem_length``).
    branch_turn : float
        Median angle (deg) between the axes of consecutive cylinders of one branch (orders 1 and
        up): how much the tree's branches wind from cylinder to cylinder.
    n_whorls : int
        Whorls of the first-order branches, every one whatever its diameter (:func:`whorls`): a
        conifer's record of its yearly leader shoots.
    crown_side : tuple of (x, y)
        The crown's offset from the stem in crown radii (:func:`crown_offset`): which side of its
        stem the crown lies, volume-weighted, the stem taken at the crown centre's height.
    envelope : dict or None
        The crown's space (:func:`crown_envelope`, as a setting:
        :meth:`~bforest_core.envelope.CrownEnvelope.setting`), with the default margin.
    """

    height: float
    dbh: float
    crown_spread: float
    crown_base_height: float
    crown_length: float
    n_branches_o1: int
    max_order: int
    branch_spacing: float
    beta_q10: float
    beta_q50: float
    beta_q90: float
    limb_ratio: float
    longest_limb: float
    thinnest_branch: float
    radius_length: float
    stem_rise: float
    crown_offset: float
    crown_azimuth: float
    stem_lean: float
    stem_path: tuple = ()
    stem_length: float = 0.0
    branch_turn: float = 0.0
    n_whorls: int = 0
    crown_side: tuple = (0.0, 0.0)
    envelope: dict | None = None

    @property
    def decurrent(self) -> bool:
        """True when the stem divides into limbs (see :data:`DECURRENT_LIMB_RATIO`)."""
        return self.limb_ratio > DECURRENT_LIMB_RATIO

    def crown_space_why(self) -> str | None:
        """Say why a recipe grows this tree's clones in its crown space, or None.

        A crown that is decurrent or one-sided (which, and by how much) is one a wood shaped; a
        conifer's excurrent crown all around its stem is set by its leader and whorls in any
        stand, and gets None.
        """
        form = self.wood_shaped()
        if not self.envelope or form is None:
            return None
        reach = self.envelope["reach"]
        return (
            f"{form}: a broadleaved crown in a wood fills the space its neighbours "
            "left it, where a growth model grows into an open world; the clones grow in this tree's crown space "
            f"(crown_envelope: its reach from the stem in {len(reach[0])} directions at {len(reach)} heights, "
            f"plus a margin of {self.envelope['margin']:g} m), where buds outside get no light and their shoots "
            "are shed (docs/growth-forms.md)"
        )

    def wood_shaped(self) -> str | None:
        """Say which forms of a crown a wood shaped this one has (decurrent, one-sided), or None."""
        side = float(np.hypot(*self.crown_side))
        az = float(np.degrees(np.arctan2(self.crown_side[1], self.crown_side[0])))
        which = []
        if self.decurrent:
            which.append(f"decurrent (its limbs hold {self.limb_ratio:.1f} x the stem's wood in the crown)")
        if self.one_sided:
            which.append(f"one-sided (its centre lies {side:.2f} crown radii off the stem, towards {az:.0f} deg)")
        return f"the crown is {' and '.join(which)}" if which else None

    @property
    def one_sided(self) -> bool:
        """True when the crown lies a third of its radius or more to one side of its stem.

        See :data:`ONE_SIDED` and :attr:`crown_side`.
        """
        return bool(np.hypot(*self.crown_side) >= ONE_SIDED)


def measure_tree(tree) -> TreeMeasures:
    """Measure what a recipe is scaled from (see :class:`TreeMeasures`).

    Parameters
    ----------
    tree : Tree
        A measured tree (a QSM).

    Returns
    -------
    TreeMeasures
        The measures.

    Raises
    ------
    ValueError
        For a tree that cannot be fitted, saying why: no stem rising from the base (a QSM
        without a trunk), or no first-order branch.
    """
    s = tree_summary(tree, min_diameter=0.0)
    br = tree.branches
    stem = tree.order == 0
    h = s["height"]
    rise = float(tree.axis[0, 2])
    stem_start, stem_end = tree.start[stem], tree.end[stem]
    stem_top = float(stem_end[:, 2].max() - tree.start[0, 2])
    if rise < 0.5 or stem_top < 0.5 * h:
        raise ValueError(
            f"no trunk: the stem's first cylinder rises at {rise:.2f} (1 = vertical; "
            f"needs >= 0.5) and the stem reaches {stem_top:.2f} m of the tree's {h:.2f} m "
            "(needs half): a growth model grows a tree from one upright stem"
        )
    o1 = np.flatnonzero((br.order == 1) & _living(tree))
    if o1.size == 0:
        raise ValueError("no first-order branch: a stem alone gives a growth model nothing to fit")
    vol = np.pi * tree.radius**2 * tree.length
    sub = np.bincount(tree.branch, weights=vol, minlength=len(br))
    for b in np.argsort(-br.order, kind="stable"):  # each branch's wood into its parent's, deepest first
        if br.parent_branch[b] >= 0 and br.order[b] > 1:
            sub[br.parent_branch[b]] += sub[b]
    cb = s["crown_base_height"]
    mid = tree.start + 0.5 * tree.length[:, None] * tree.axis  # cylinder midpoints
    zmid = mid[:, 2] - tree.start[0, 2]
    stem_crown = float(vol[stem & (zmid >= cb)].sum())
    limbs = np.sort(sub[o1])[::-1][:3].sum()
    blen = np.bincount(tree.branch, weights=tree.length, minlength=len(br))
    pc = br.parent_cyl[o1]
    a = axis_angles(tree, br.first[o1], pc)
    q10, q50, q90 = (float(v) for v in np.percentile(a, [10, 50, 90]))
    crown_length = max(h - cb, 1e-9)
    crown = (tree.order > 0) & (zmid >= cb)
    w = tree.length[crown]
    top = stem_end[np.argmax(stem_end[:, 2])]
    half = stem_start[np.argmin(np.abs(stem_start[:, 2] - tree.start[0, 2] - 0.5 * h))]
    chord = top - half
    centre = np.zeros(2)
    if w.sum() > 0:
        centre = (mid[crown, :2] * w[:, None]).sum(0) / w.sum() - tree.start[0, :2]
    path = stem_points(tree)
    # consecutive cylinders of one branch: the turn between their axes
    kid = np.flatnonzero((tree.parent >= 0) & (tree.order > 0))
    kid = kid[tree.branch[tree.parent[kid]] == tree.branch[kid]]
    turn = axis_angles(tree, kid, tree.parent[kid])
    return TreeMeasures(
        height=h,
        dbh=s["dbh"],
        crown_spread=s["crown_spread"],
        crown_base_height=cb,
        crown_length=h - cb,
        n_branches_o1=int(o1.size),
        max_order=int(br.order.max()),
        branch_spacing=crown_length / o1.size,
        beta_q10=q10,
        beta_q50=q50,
        beta_q90=q90,
        limb_ratio=float(limbs / stem_crown) if stem_crown > 0 else float("inf"),
        longest_limb=float(blen[o1].max()),
        thinnest_branch=float(2.0 * tree.radius[br.first[1:]].min()),
        radius_length=float(np.median(tree.radius[br.first[o1]] / np.maximum(blen[o1], 1e-9))),
        stem_rise=rise,
        crown_offset=float(np.hypot(*centre)),
        crown_azimuth=float(np.degrees(np.arctan2(centre[1], centre[0]))),
        stem_lean=float(np.degrees(np.arctan2(np.hypot(chord[0], chord[1]), chord[2]))),
        stem_path=tuple(tuple(round(float(c), 2) for c in q) for q in path),
        stem_length=float(s["stem_length"]),
        branch_turn=float(np.median(turn)) if turn.size else 0.0,
        n_whorls=int(s["n_whorls"]),
        crown_side=tuple(round(float(v), 4) for v in crown_offset(tree)),
        envelope=crown_envelope(tree).setting(),
    )


#: spacing (m) of the points kept of a stem (:func:`stem_points`)
PATH_STEP = 0.5


def stem_points(tree) -> np.ndarray:
    """Return the tree's stem as points from its base (see ``TreeMeasures.stem_path``)."""
    cyl = np.flatnonzero(tree.order == 0)  # in row order, so base first
    pts = np.vstack([tree.start[cyl], tree.end[cyl[-1]]]) - tree.start[0]
    arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))]
    keep = [0]
    for i in range(1, len(pts) - 1):
        if arc[i] - arc[keep[-1]] >= PATH_STEP - 1e-6:  # a hair below: 0.5 m cylinders keep every point
            keep.append(i)
    keep.append(len(pts) - 1)
    return pts[keep]
