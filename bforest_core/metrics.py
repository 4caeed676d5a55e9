"""Classical tree metrics: height, girth (or DBH) and crown spread, and their relative errors.

Spec ``shared/spec/features-distance.md`` §5 (GS Methods IV "traditional metrics", after the
toolbox's ``tree_basic_metrics.m`` with its defects fixed). Base point = start of the root
cylinder; point set = all cylinder start and end points.
"""
from __future__ import annotations

import warnings
from typing import Literal, Mapping

import numpy as np

__all__ = ["classical_metrics", "relative_errors", "crown_spread", "dbh"]

BREAST_HEIGHT = 1.3  # m
_RHO_EPS = 1e-9      # m; points closer than this to the vertical through the base have no direction


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


def dbh(tree, breast_height: float = BREAST_HEIGHT, warn: bool = True) -> float:
    """Diameter (m) of the first trunk cylinder (base to tip) spanning ``breast_height``.

    The trunk is branch 0 of the tree's own topology. A cylinder spans the height when
    ``min(z_s, z_e) - z0 <= h <= max(z_s, z_e) - z0``. NaN (with a warning when ``warn``) when
    no trunk cylinder does.
    """
    bt = tree.branches
    trunk = bt.cylinders[bt.ptr[0]:bt.ptr[1]]
    z0 = tree.start[0, 2]
    zs = tree.start[trunk, 2] - z0
    ze = tree.end[trunk, 2] - z0
    hit = np.flatnonzero((np.minimum(zs, ze) <= breast_height) & (breast_height <= np.maximum(zs, ze)))
    if hit.size == 0:
        if warn:
            src = tree.metadata.get("source") or tree.metadata.get("model") or "tree"
            warnings.warn(f"{src}: no trunk cylinder spans breast height {breast_height} m above the "
                          f"base (trunk reaches {float(max(zs.max(), ze.max())):.3f} m); DBH is NaN",
                          RuntimeWarning, stacklevel=2)
        return float("nan")
    return float(2.0 * tree.radius[trunk[hit[0]]])


def classical_metrics(tree, girth: Literal["base", "dbh"] = "base", spoke_step: float = 10.0,
                      empty_sectors: Literal["zero", "drop"] = "zero") -> dict[str, float]:
    """Height, girth, DBH and crown spread of a tree, in metres (spec §5).

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
        ``height`` (highest start/end point minus the base z), ``girth`` (as chosen),
        ``dbh`` (always the diameter at 1.3 m, NaN if none) and ``crown_spread``.
    """
    if girth not in ("base", "dbh"):
        raise ValueError(f"girth must be 'base' or 'dbh', got {girth!r}")
    z0 = tree.start[0, 2]
    height = float(max(tree.start[:, 2].max(), tree.end[:, 2].max()) - z0)
    d = dbh(tree, warn=(girth == "dbh"))
    g = d if girth == "dbh" else float(2.0 * tree.radius[0])
    return {"height": height, "girth": g, "dbh": d,
            "crown_spread": crown_spread(tree, spoke_step, empty_sectors)}


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
    """
    out = {}
    for key, name in (("d_h", "height"), ("d_g", "girth"), ("d_c", "crown_spread")):
        if name not in data_metrics or name not in model_metrics:
            raise KeyError(f"relative_errors: '{name}' missing from the "
                           f"{'data' if name not in data_metrics else 'model'} metrics")
        xd = float(data_metrics[name])
        xm = np.asarray(model_metrics[name], dtype=np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            r = np.abs(xd - xm) / xd if xd != 0 else np.full(xm.shape, np.nan)
        out[key] = float(r) if r.ndim == 0 else r
    return out
