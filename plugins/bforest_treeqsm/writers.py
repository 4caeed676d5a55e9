"""TreeQSM writers for ``bf.write_tree`` (docs/qsm-formats.md §9): TreeQSM cylinder text (and its
branch file) and the TreeQSM 2.4 ``.mat`` struct.

Text output is assembled by :func:`bforest_core.tables.format_columns` (no Python loop over
cylinders).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Literal, Optional

import numpy as np
from pydantic import Field

from bforest_core.cylinders import resolve_options
from bforest_core.errors import QSMFormatError
from bforest_core.interfaces import ComponentSettings, QSMWriter
from bforest_core.io import jsonable
from bforest_core.tables import format_columns, format_rows

from ._text import TREEQSM17_NAMES
from .columns import INTEGER_FIELDS, LAYOUTS, STRUCT_FIELDS


def _extra(tree, name, default):
    v = tree.extras.get(name)
    if v is not None:
        v = np.asarray(v, dtype=np.float64).reshape(-1)
        if v.shape == (tree.n,) and np.all(np.isfinite(v)):
            return v
    return np.broadcast_to(np.asarray(default, dtype=np.float64), (tree.n,)).astype(np.float64)


def _one_based(a: np.ndarray) -> np.ndarray:
    return np.where(a >= 0, a + 1, 0).astype(np.float64)


# ------------------------------------------------------------------------------------------
# TreeQSM text
# ------------------------------------------------------------------------------------------


class TreeQSMTextSettings(ComponentSettings):
    #: ``None``: ``%.9g`` (round trip within 1e-6 m); an int copies TreeQSM's rounding
    decimals: Optional[int] = Field(default=None, ge=1, le=12)
    layout: Literal["treeqsm17", "treeqsm15-struct"] = "treeqsm17"
    #: also write TreeQSM's ``branch_<name>.txt`` (10 columns) beside the file
    branch_file: bool = False


def treeqsm_columns(tree) -> dict[str, np.ndarray]:
    """The TreeQSM cylinder columns of a tree (1-based ids, 0 = none; trunk branch = 1)."""
    return {
        "radius": tree.radius,
        "length": tree.length,
        "start": tree.start,
        "axis": tree.axis,
        "parent": _one_based(tree.parent),
        "extension": _one_based(tree.extension),
        "branch": (tree.branch + 1).astype(np.float64),
        "BranchOrder": tree.order.astype(np.float64),
        "PositionInBranch": (tree.position_in_branch + 1).astype(np.float64),
        "mad": _extra(tree, "mad", 0.0),
        "SurfCov": _extra(tree, "SurfCov", 1.0),
        "added": tree.added.astype(np.float64),
        "UnmodRadius": _extra(tree, "UnmodRadius", tree.radius),
    }


class TreeQSMTextWriter(QSMWriter):
    """TreeQSM cylinder text (``save_model_text`` 1.1.0 layout, docs/qsm-formats.md §5a/§9): the 13-name header
    and 17 tab-separated columns, LF; ``layout="treeqsm15-struct"`` writes the headerless
    15-column file that aRchi reads. ``mad`` = 0, ``SurfCov`` = 1 and ``UnmodRadius`` = radius
    unless the tree carries them as extras."""

    name = "treeqsm-text"
    summary = "TreeQSM cylinder text (17 columns + header, or treeqsm15-struct)"
    suffixes = (".txt", ".dat")
    Settings = TreeQSMTextSettings
    priority = 10

    def write(self, tree, path, **options) -> Path:
        o = resolve_options(self, options)
        path = Path(path)
        c = treeqsm_columns(tree)
        if o.decimals is not None:
            d = o.decimals
            c = {k: v if k in INTEGER_FIELDS else np.round(v, d) for k, v in c.items()}
            for k in ("radius", "length"):
                bad = np.flatnonzero(c[k] <= 0)
                if bad.size:
                    raise QSMFormatError(
                        path,
                        f"{k} of row {bad[0] + 1} ({getattr(tree, k)[bad[0]]:.3g} m) "
                        f"rounds to 0 with decimals={d} ({bad.size} rows); "
                        "use more decimals",
                        bad + 1,
                    )
            ff = f"%.{d}f"
        else:
            ff = "%.9g"
        header = "\t".join(TREEQSM17_NAMES) + "\n" if o.layout == "treeqsm17" else ""
        rows = format_columns([(c[k], "%d" if k in INTEGER_FIELDS else ff) for k in LAYOUTS[o.layout]])
        with open(path, "w", encoding="ascii", newline="\n") as fh:
            fh.write(header)
            fh.write(rows)
        if o.branch_file:
            stem = path.name[len("cylinder_") :] if path.name.startswith("cylinder_") else path.name
            write_branch_file(tree, path.with_name("branch_" + stem))
        return path


BRANCH_NAMES = [
    "order",
    "parent",
    "diameter (m)",
    "volume (L)",
    "area (m^2)",
    "length (m)",
    "height (m)",
    "angle (deg)",
    "azimuth (deg)",
    "zenith (deg)",
]


def branch_table(tree) -> np.ndarray:
    """TreeQSM's 10 branch columns (:data:`BRANCH_NAMES`, one row per branch) from the kernel's
    :func:`bforest_core.attributes.branch_table`: parent 1-based (0 for the trunk), volume in
    litres."""
    from bforest_core.attributes import branch_table as btab

    b = btab(tree)
    return np.column_stack(
        [
            b["order"],
            _one_based(b["parent"]),
            b["diameter"],
            1000.0 * b["volume"],
            b["area"],
            b["length"],
            b["height"],
            b["angle"],
            b["azimuth"],
            b["zenith"],
        ]
    )


def write_branch_file(tree, path: Path) -> Path:
    t = branch_table(tree)
    with open(path, "w", encoding="ascii", newline="\n") as fh:
        fh.write("\t".join(BRANCH_NAMES) + "\n")
        fh.write(format_rows(t, ["%d", "%d"] + ["%.9g"] * 8))
    return path


# ------------------------------------------------------------------------------------------
# TreeQSM .mat
# ------------------------------------------------------------------------------------------


class MatSettings(ComponentSettings):
    #: MATLAB variable name of the struct
    variable: Literal["qsm", "QSM", "OptQSM"] = "qsm"


#: TreeQSM 2.4's ``treedata`` fields in its order (``tree_data.m`` with triangulation on)
TREEDATA_FIELDS = (
    "TotalVolume",
    "TrunkVolume",
    "BranchVolume",
    "TreeHeight",
    "TrunkLength",
    "BranchLength",
    "TotalLength",
    "NumberBranches",
    "MaxBranchOrder",
    "TrunkArea",
    "BranchArea",
    "TotalArea",
    "DBHqsm",
    "DBHcyl",
    "CrownDiamAve",
    "CrownDiamMax",
    "CrownAreaConv",
    "CrownAreaAlpha",
    "CrownBaseHeight",
    "CrownLength",
    "CrownRatio",
    "CrownVolumeConv",
    "CrownVolumeAlpha",
    "DBHtri",
    "TriaTrunkVolume",
    "MixTrunkVolume",
    "MixTotalVolume",
    "TriaTrunkArea",
    "MixTrunkArea",
    "MixTotalArea",
    "TriaTrunkLength",
    "location",
    "StemTaper",
    "VerticalProfile",
    "spreads",
)
#: the distributions after them, in TreeQSM's order
DISTRIBUTION_FIELDS = tuple(
    [f"{q}Cyl{x}" for x in ("Dia", "Hei", "Zen", "Azi") for q in ("Vol", "Are", "Len")]
    + [f"{q}BranchOrd" for q in ("Vol", "Are", "Len", "Num")]
    + [
        f"{q}Branch{one}{x}"
        for x in ("Dia", "Hei", "Ang", "Azi", "Zen")
        for q in ("Vol", "Are", "Len", "Num")
        for one in ("", "1")
    ]
)
#: our attribute behind each scalar treedata field (volumes are converted to litres)
_TREEDATA_FROM = {
    "TotalVolume": "total_volume",
    "TrunkVolume": "trunk_volume",
    "BranchVolume": "branch_volume",
    "TreeHeight": "tree_height",
    "TrunkLength": "trunk_length",
    "BranchLength": "branch_length",
    "TotalLength": "total_length",
    "NumberBranches": "n_branches",
    "MaxBranchOrder": "max_branch_order",
    "TrunkArea": "trunk_area",
    "BranchArea": "branch_area",
    "TotalArea": "total_area",
    "DBHqsm": "dbh",
    "DBHcyl": "dbh",
    "CrownDiamAve": "crown_diameter_mean",
    "CrownDiamMax": "crown_diameter_max",
    "CrownAreaConv": "crown_area_conv",
    "CrownAreaAlpha": "crown_area_alpha",
    "CrownBaseHeight": "crown_base_height",
    "CrownLength": "crown_length",
    "CrownRatio": "crown_ratio",
    "CrownVolumeConv": "crown_volume_conv",
    "CrownVolumeAlpha": "crown_volume_alpha",
    # without a point cloud there is no triangulation: TreeQSM then repeats the cylinder values
    "DBHtri": "dbh",
    "TriaTrunkVolume": "trunk_volume",
    "MixTrunkVolume": "trunk_volume",
    "MixTotalVolume": "total_volume",
    "TriaTrunkArea": "trunk_area",
    "MixTrunkArea": "trunk_area",
    "MixTotalArea": "total_area",
}
#: TreeQSM 2.4's reconstruction inputs (``rundata.inputs``): NaN, as no reconstruction made the tree
TREEQSM_INPUTS = (
    "PatchDiam1",
    "PatchDiam2Min",
    "PatchDiam2Max",
    "BallRad1",
    "BallRad2",
    "nmin1",
    "nmin2",
    "OnlyTree",
    "Tria",
    "Dist",
    "MinCylRad",
    "ParentCor",
    "TaperCor",
    "GrowthVolCor",
    "GrowthVolFac",
)
TREEQSM_FILTER_INPUTS = ("k", "radius", "nsigma", "PatchDiam1", "BallRad1", "ncomp", "EdgeLength", "plot")
PMDISTANCE_FIELDS = ("CylDist", "median", "mean", "max", "std") + tuple(
    f"{p}{s}" for p in ("Trunk", "Branch", "Branch1", "Branch2") for s in ("Median", "Mean", "Max", "Std")
)


def _uint(a) -> np.ndarray:
    """Non-negative integers as a column in the smallest unsigned class TreeQSM uses."""
    a = np.asarray(a).reshape(-1, 1)
    top = int(a.max()) if a.size else 0
    dt = np.uint8 if top < 2**8 else np.uint16 if top < 2**16 else np.uint32
    return a.astype(dt)


def _col(a, dtype=np.float64) -> np.ndarray:
    return np.ascontiguousarray(np.asarray(a, dtype=dtype).reshape(-1, 1))


def _single(v) -> np.ndarray:
    """A treedata value as MATLAB single: scalars 1x1, vectors 1 x n (TreeQSM's row vectors)."""
    a = np.asarray(v, dtype=np.float32)
    return a.reshape(1, 1) if a.ndim == 0 else a.reshape(1, -1) if a.ndim == 1 else a


def treeqsm_struct(tree, provenance: Optional[dict] = None) -> dict:
    """The TreeQSM 2.4 struct of a tree: ``cylinder``, ``branch``, ``treedata``, ``rundata``,
    ``pmdistance``, ``triangulation`` with TreeQSM's field names, shapes, classes and units.

    Cylinder geometry is written in double precision (our reader gives the same table back);
    ids are TreeQSM's unsigned classes (1-based, 0 = none); ``branch`` and ``treedata`` are
    single like TreeQSM's, volumes in litres. There is no point cloud behind a model tree, so
    ``pmdistance`` holds NaN and ``triangulation`` is TreeQSM's empty one (the triangulation
    fields of ``treedata`` repeat the cylinder values, as TreeQSM writes them then).
    ``rundata.bforest`` records where the tree came from (``provenance``, else the tree's
    metadata: model, parameters, seed, source file) and the Bayes Forest version.
    """
    from bforest_core import __version__
    from bforest_core.attributes import branch_table as btab
    from bforest_core.attributes import crown_points, crown_spreads, distributions, stem_taper, tree_attributes

    c = treeqsm_columns(tree)
    n = tree.n
    cyl = {}
    for k in STRUCT_FIELDS:
        v = np.asarray(c[k])
        if k in INTEGER_FIELDS:
            cyl[k] = _uint(v)
        else:
            cyl[k] = np.ascontiguousarray(np.asarray(v, dtype=np.float64).reshape(n, -1))
    b = btab(tree)
    branch = {
        "order": _uint(b["order"]),
        "parent": _uint(_one_based(b["parent"])),
        "diameter": _col(b["diameter"], np.float32),
        "volume": _col(1000.0 * b["volume"], np.float32),
        "area": _col(b["area"], np.float32),
        "length": _col(b["length"], np.float32),
        "angle": _col(b["angle"], np.float32),
        "height": _col(b["height"], np.float32),
        "azimuth": _col(b["azimuth"], np.float32),
        "zenith": _col(b["zenith"], np.float32),
    }
    P = crown_points(tree)
    att = tree_attributes(tree, P)
    spreads = crown_spreads(tree, P)
    td = {}
    for k in TREEDATA_FIELDS:
        if k in _TREEDATA_FROM:
            v = att[_TREEDATA_FROM[k]]
            td[k] = _single(1000.0 * v if k.endswith("Volume") and not k.startswith("Crown") else v)
        elif k == "TriaTrunkLength":
            td[k] = _single(0.0)
        elif k == "location":
            td[k] = _single(tree.start[0])
        elif k == "StemTaper":
            td[k] = stem_taper(tree).astype(np.float32)
        elif k == "VerticalProfile":
            td[k] = spreads.mean(axis=1).astype(np.float32).reshape(-1, 1)
        elif k == "spreads":
            td[k] = spreads.astype(np.float32)
    dist = distributions(tree)
    for k in DISTRIBUTION_FIELDS:
        v = dist[k]
        td[k] = _single(1000.0 * v if k.startswith("Vol") else v)
    md = dict(tree.metadata)
    prov = {k: md.get(k) for k in ("model", "params", "fixed", "seed", "role", "run", "source")}
    prov.update(provenance or {})
    bf = {"version": str(__version__), "created": _now_iso()}
    for k, v in prov.items():
        if v is None:
            continue
        if k in ("params", "fixed") and isinstance(v, dict):
            bf[k] = {str(p): (float(x) if isinstance(x, (int, float, np.number)) else str(x)) for p, x in v.items()}
        elif isinstance(v, (int, float, np.number)) and not isinstance(v, bool):
            bf[k] = float(v)
        else:
            bf[k] = json.dumps(jsonable(v, loose=True, strict=True)) if isinstance(v, (dict, list, tuple)) else str(v)
    name = Path(str(md.get("source") or prov.get("model") or "tree")).stem
    inputs = {k: np.array([[np.nan]]) for k in TREEQSM_INPUTS}
    inputs["filter"] = {k: np.array([[np.nan]]) for k in TREEQSM_FILTER_INPUTS}
    inputs.update(name=name, tree=1.0, model=1.0, savemat=0.0, savetxt=0.0, plot=0.0, disp=0.0, metric="")
    rundata = {
        "inputs": inputs,
        "time": np.zeros((12, 1), np.float32),
        "date": np.zeros((2, 6), np.float32),
        "version": f"bforest {__version__} (TreeQSM 2.4.1 layout)",
        "bforest": bf,
    }
    nan = np.float64("nan")
    pmd = {k: (np.full((n, 1), np.nan, np.float32) if k == "CylDist" else np.array([[nan]])) for k in PMDISTANCE_FIELDS}
    tri = {"vert": np.zeros((0, 3)), "facet": np.zeros((0, 3)), "fvd": np.zeros((0, 1))}
    tri.update(
        {
            k: np.array([[0.0]])
            for k in ("volume", "SideArea", "BottomArea", "TopArea", "bottom", "top", "triah", "triaw", "cylind")
        }
    )
    return {
        "cylinder": cyl,
        "branch": branch,
        "treedata": td,
        "rundata": rundata,
        "pmdistance": pmd,
        "triangulation": tri,
    }


def _now_iso() -> str:
    import datetime

    return datetime.datetime.now(datetime.UTC).replace(microsecond=0).isoformat()


class TreeQSMMatWriter(QSMWriter):
    """A MAT v5 file with the TreeQSM 2.4 struct ``qsm`` (``cylinder``, ``branch``,
    ``treedata``, ``rundata``, ``pmdistance``, ``triangulation``; :func:`treeqsm_struct`) that
    rTwig, ITSMe and TreeQSM's own plotting read; ``rundata.bforest`` records the model,
    parameters, seed and Bayes Forest version."""

    name = "treeqsm-mat"
    summary = "TreeQSM 2.4 .mat struct qsm (cylinder, branch, treedata, rundata, pmdistance, triangulation)"
    suffixes = (".mat",)
    Settings = MatSettings
    priority = 10

    def write(self, tree, path, **options) -> Path:
        import scipy.io as sio

        o = resolve_options(self, options)
        path = Path(path)
        sio.savemat(str(path), {o.variable: treeqsm_struct(tree)}, do_compression=True, oned_as="column")
        return path
