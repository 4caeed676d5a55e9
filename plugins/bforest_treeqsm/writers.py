"""Writers for ``bf.write_tree`` (docs/qsm-formats.md §9): TreeQSM text, native CSV + JSON sidecar, TreeQSM
``.mat`` struct, PLY and OBJ cylinder meshes.

Text output is produced by one ``%`` formatting of a repeated row template over the flattened
table (no Python loop over cylinders).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Literal, Optional

import numpy as np
from pydantic import Field, ValidationError

from bforest_core.errors import ConfigError, QSMFormatError
from bforest_core.interfaces import ComponentSettings, QSMWriter

from ._text import NATIVE_COLUMNS, TREEQSM17_NAMES

CSV_FORMAT_VERSION = 1


def _options(writer, options) -> ComponentSettings:
    try:
        return writer.Settings(**{**writer.settings.model_dump(), **options})
    except ValidationError as exc:
        parts = [f"{'.'.join(str(x) for x in e.get('loc', ()))}: {e.get('msg')}" for e in exc.errors()]
        raise ConfigError(f"qsm_writer '{writer.name}': invalid option(s): " + "; ".join(parts)) from None


def format_rows(values: np.ndarray, formats: list[str], sep: str = "\t") -> str:
    """Rows of ``values`` (n, k) formatted with one printf format per column, LF line ends."""
    n = values.shape[0]
    if n == 0:
        return ""
    row = sep.join(formats) + "\n"
    return (row * n) % tuple(values.ravel().tolist())


def _extra(tree, name, default):
    v = tree.extras.get(name)
    if v is not None:
        v = np.asarray(v, dtype=np.float64).reshape(-1)
        if v.shape == (tree.n,) and np.all(np.isfinite(v)):
            return v
    return np.broadcast_to(np.asarray(default, dtype=np.float64), (tree.n,)).astype(np.float64)


def _one_based(a: np.ndarray) -> np.ndarray:
    return np.where(a >= 0, a + 1, 0).astype(np.float64)


def jsonable(obj, depth: int = 0):
    """Metadata as plain JSON values (numpy scalars/arrays converted, unknown objects as str)."""
    if depth > 8:
        return str(obj)
    if obj is None or isinstance(obj, (bool, int, str)):
        return obj
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else str(obj)
    if isinstance(obj, np.generic):
        return jsonable(obj.item(), depth + 1)
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist(), depth + 1)
    if isinstance(obj, dict):
        return {str(k): jsonable(v, depth + 1) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v, depth + 1) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    return str(obj)


def provenance(tree, **extra) -> dict:
    """Where a tree came from, for the file that holds it: the Bayes Forest version and, when the
    tree's metadata has them, model, parameters, fixed parameters, seed, role, run folder and
    source file (``extra`` adds e.g. scan settings). JSON-ready."""
    from bforest_core import __version__

    md = tree.metadata
    out = {"software": f"Bayes Forest {__version__}"}
    for k in ("model", "params", "fixed", "seed", "role", "run", "source"):
        if md.get(k) is not None:
            out[k] = jsonable(md[k])
    out.update(jsonable(extra))
    return out


def provenance_line(tree, **extra) -> str:
    """:func:`provenance` as one line of compact JSON (for PLY, OBJ and XYZ comments)."""
    return "provenance " + json.dumps(provenance(tree, **extra), separators=(",", ":"), allow_nan=False)


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
        o = _options(self, options)
        path = Path(path)
        c = treeqsm_columns(tree)
        fcols = ["radius", "length", "start", "axis", "mad", "SurfCov", "UnmodRadius"]
        if o.decimals is not None:
            d = o.decimals
            c = dict(c)
            for k in fcols:
                c[k] = np.round(c[k], d)
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
        if o.layout == "treeqsm17":
            order = [
                "radius",
                "length",
                "start",
                "axis",
                "parent",
                "extension",
                "branch",
                "BranchOrder",
                "PositionInBranch",
                "mad",
                "SurfCov",
                "added",
                "UnmodRadius",
            ]
            header = "\t".join(TREEQSM17_NAMES) + "\n"
        else:
            order = [
                "radius",
                "length",
                "start",
                "axis",
                "parent",
                "extension",
                "added",
                "UnmodRadius",
                "branch",
                "BranchOrder",
                "PositionInBranch",
            ]
            header = ""
        blocks, fmts = [], []
        for k in order:
            v = np.asarray(c[k], dtype=np.float64)
            v = v.reshape(tree.n, -1)
            blocks.append(v)
            fmts += [ff if k in fcols else "%d"] * v.shape[1]
        table = np.hstack(blocks)
        with open(path, "w", encoding="ascii", newline="\n") as fh:
            fh.write(header)
            fh.write(format_rows(table, fmts))
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
# native CSV + JSON sidecar
# ------------------------------------------------------------------------------------------


class CSVSettings(ComponentSettings):
    #: write ``<name>.json`` beside the CSV
    sidecar: bool = True


class CSVWriter(QSMWriter):
    """Native CSV (docs/qsm-formats.md §9): named columns, 0-based ids, -1 = none, floats at ``repr``
    precision (``%.17g``), plus 1-D numeric extras as further columns and, for a tree under a
    non-source topology, its ``source_extension``; a JSON sidecar keeps format version, units,
    topology rule, source, model, parameters and seed, and the ``provenance`` the other formats
    write as a comment (with the Bayes Forest version). The CSV itself has no comment line, so
    any CSV reader (pandas, R's ``read.csv``) takes its first line as the header. Read back it
    gives the same tree."""

    name = "bforest-csv"
    summary = "Bayes Forest native cylinder CSV with a JSON sidecar"
    suffixes = (".csv",)
    Settings = CSVSettings
    priority = 10

    def write(self, tree, path, **options) -> Path:
        o = _options(self, options)
        path = Path(path)
        n = tree.n
        cols = [
            np.arange(n),
            tree.parent,
            tree.extension,
            tree.branch,
            tree.order,
            tree.position_in_branch,
            tree.added.astype(np.int64),
            tree.start,
            tree.axis,
            tree.length,
            tree.radius,
            tree.end,
        ]
        names = list(NATIVE_COLUMNS)
        fmts = ["%d"] * 7 + ["%.17g"] * 11
        src = tree.extras.get("_source_extension")
        if tree.topology != "source" and src is not None and np.shape(src) == (n,):
            cols.append(np.asarray(src))
            names.append("source_extension")
            fmts.append("%d")
        for k, v in tree.extras.items():
            v = np.asarray(v)
            if k.startswith("_") or k in names or v.shape != (n,) or v.dtype.kind not in "iufb":
                continue
            if "," in k or "\n" in k:
                continue
            cols.append(v.astype(np.float64))
            names.append(k)
            fmts.append("%.17g")
        table = np.hstack([np.asarray(c, dtype=np.float64).reshape(n, -1) for c in cols])
        with open(path, "w", encoding="utf-8", newline="\n") as fh:
            fh.write(",".join(names) + "\n")
            fh.write(format_rows(table, fmts, sep=","))
        if o.sidecar:
            md = dict(tree.metadata)
            side = {
                "format": "bforest-csv",
                "format_version": CSV_FORMAT_VERSION,
                "units": "m",
                "topology": tree.topology,
                "source": md.get("source"),
                "model": md.get("model"),
                "params": md.get("params"),
                "seed": md.get("seed"),
                "provenance": provenance(tree),
                "metadata": jsonable({k: v for k, v in md.items() if k not in ("topology",)}),
            }
            path.with_suffix(".json").write_text(json.dumps(side, indent=2, allow_nan=False), encoding="utf-8")
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
    for k in (
        "radius",
        "length",
        "start",
        "axis",
        "parent",
        "extension",
        "added",
        "UnmodRadius",
        "branch",
        "SurfCov",
        "mad",
        "BranchOrder",
        "PositionInBranch",
    ):
        v = np.asarray(c[k])
        if k in ("parent", "extension", "added", "branch", "BranchOrder", "PositionInBranch"):
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
            bf[k] = json.dumps(jsonable(v)) if isinstance(v, (dict, list, tuple)) else str(v)
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

        o = _options(self, options)
        path = Path(path)
        sio.savemat(str(path), {o.variable: treeqsm_struct(tree)}, do_compression=True, oned_as="column")
        return path


# ------------------------------------------------------------------------------------------
# meshes
# ------------------------------------------------------------------------------------------


class MeshSettings(ComponentSettings):
    #: sides of each prism (>= 3)
    sides: int = Field(default=12, ge=3, le=1024)
    #: close both ends of every cylinder
    caps: bool = True
    #: per-vertex colour
    color_by: Literal["order", "branch", "radius", "none"] = "order"
    #: thinner cylinders are drawn with this radius (m)
    min_radius: float = Field(default=0.0, ge=0.0)
    #: move the tree so that the base (root start point) is at the origin
    translate_to_base: bool = False


def cylinder_mesh(tree, sides: int = 12, caps: bool = True, min_radius: float = 0.0, translate_to_base: bool = False):
    """Triangle mesh of every cylinder as a ``sides``-sided prism (docs/qsm-formats.md §9).

    Frame: u = normalise(a x e) with e the coordinate axis least aligned with a, w = a x u; ring
    vertices s + r(u cos t + w sin t), top ring shifted by l a. Faces are counter-clockwise seen
    from outside.

    Returns
    -------
    vertices : (n * 2k, 3) float64
    faces : (F, 3) int64, F = n * (2k + (2(k - 2) if caps))
    face_cyl : (F,) int64
        Cylinder of every face.
    """
    k = int(sides)
    n = tree.n
    a = np.asarray(tree.axis, dtype=np.float64)
    e = np.eye(3)[np.argmin(np.abs(a), axis=1)]
    u = np.cross(a, e)
    u /= np.linalg.norm(u, axis=1)[:, None]
    w = np.cross(a, u)
    t = 2 * np.pi * np.arange(k) / k
    r = np.maximum(tree.radius, min_radius)
    s = tree.start - (tree.start[0] if translate_to_base else 0.0)
    ring = r[:, None, None] * (u[:, None, :] * np.cos(t)[None, :, None] + w[:, None, :] * np.sin(t)[None, :, None])
    bottom = s[:, None, :] + ring
    top = bottom + (tree.length[:, None] * a)[:, None, :]
    vertices = np.concatenate([bottom, top], axis=1).reshape(-1, 3)
    j = np.arange(k)
    j1 = (j + 1) % k
    side = np.concatenate([np.stack([j, j1, k + j1], axis=1), np.stack([j, k + j1, k + j], axis=1)])
    local = [side]
    if caps and k >= 3:
        m = np.arange(1, k - 1)
        local.append(np.stack([np.full(k - 2, k), k + m, k + m + 1], axis=1))  # top, normal +a
        local.append(np.stack([np.zeros(k - 2, dtype=np.int64), m + 1, m], axis=1))  # bottom, -a
    local = np.concatenate(local).astype(np.int64)
    base = (np.arange(n, dtype=np.int64) * 2 * k)[:, None, None]
    faces = (base + local[None, :, :]).reshape(-1, 3)
    face_cyl = np.repeat(np.arange(n, dtype=np.int64), local.shape[0])
    return vertices, faces, face_cyl


ORDER_PALETTE = np.array(
    [
        [120, 72, 38],
        [214, 140, 45],
        [235, 200, 60],
        [120, 190, 70],
        [40, 150, 110],
        [50, 120, 200],
        [120, 80, 200],
        [200, 70, 160],
        [220, 60, 60],
        [140, 140, 140],
    ],
    dtype=np.uint8,
)


def _hsv_to_rgb(h, s, v):
    i = np.floor(h * 6).astype(np.int64) % 6
    f = h * 6 - np.floor(h * 6)
    p, q, t = v * (1 - s), v * (1 - f * s), v * (1 - (1 - f) * s)
    r = np.choose(i, [v, q, p, p, t, v])
    g = np.choose(i, [t, v, v, q, p, p])
    b = np.choose(i, [p, p, t, v, v, q])
    return np.stack([r, g, b], axis=1)


def cylinder_colors(tree, by: str) -> np.ndarray:
    """(n, 3) uint8 colour of every cylinder: by order (fixed palette), branch (golden-ratio
    hues) or radius (log-scaled ramp from brown to green)."""
    n = tree.n
    if by == "order":
        return ORDER_PALETTE[np.asarray(tree.order) % len(ORDER_PALETTE)]
    if by == "branch":
        h = (np.asarray(tree.branch) * 0.618033988749895) % 1.0
        return (_hsv_to_rgb(h, np.full(n, 0.65), np.full(n, 0.9)) * 255).round().astype(np.uint8)
    if by == "radius":
        lr = np.log(np.asarray(tree.radius))
        span = lr.max() - lr.min()
        x = (lr - lr.min()) / span if span > 0 else np.zeros(n)
        lo, hi = np.array([110, 70, 40.0]), np.array([150, 220, 90.0])
        return (hi[None, :] * (1 - x[:, None]) + lo[None, :] * x[:, None]).round().astype(np.uint8)
    return np.full((n, 3), 200, dtype=np.uint8)


class PLYSettings(MeshSettings):
    #: ASCII instead of binary little-endian
    ascii: bool = False


class PLYWriter(QSMWriter):
    """PLY cylinder mesh (binary little-endian by default, ``ascii=True`` option) with per-vertex
    RGB colours (by order, branch or radius). Coordinates are float32, or float64 when they
    exceed 1e4 m in magnitude (georeferenced trees)."""

    name = "ply"
    summary = "PLY cylinder mesh (binary LE or ASCII, RGB by order/branch/radius)"
    suffixes = (".ply",)
    Settings = PLYSettings
    priority = 10

    def write(self, tree, path, **options) -> Path:
        o = _options(self, options)
        path = Path(path)
        v, f, _ = cylinder_mesh(tree, o.sides, o.caps, o.min_radius, o.translate_to_base)
        col = np.repeat(cylinder_colors(tree, o.color_by), 2 * o.sides, axis=0)
        big = np.abs(v).max() > 1e4 if v.size else False
        ftype = "double" if big else "float"
        header = [
            "ply",
            f"format {'ascii' if o.ascii else 'binary_little_endian'} 1.0",
            f"comment Bayes Forest cylinder mesh: {tree.n} cylinders, {o.sides} sides, "
            f"caps {'on' if o.caps else 'off'}, colour by {o.color_by}",
            "comment " + provenance_line(tree),
            f"element vertex {v.shape[0]}",
            f"property {ftype} x",
            f"property {ftype} y",
            f"property {ftype} z",
            "property uchar red",
            "property uchar green",
            "property uchar blue",
            f"element face {f.shape[0]}",
            "property list uchar int vertex_indices",
            "end_header",
        ]
        with open(path, "wb") as fh:
            fh.write(("\n".join(header) + "\n").encode("ascii"))
            if o.ascii:
                vt = np.hstack([v, col.astype(np.float64)])
                fh.write(format_rows(vt, ["%.9g"] * 3 + ["%d"] * 3, sep=" ").encode("ascii"))
                ft = np.hstack([np.full((f.shape[0], 1), 3.0), f.astype(np.float64)])
                fh.write(format_rows(ft, ["%d"] * 4, sep=" ").encode("ascii"))
            else:
                fdt = "<f8" if big else "<f4"
                vrec = np.empty(
                    v.shape[0], dtype=[("x", fdt), ("y", fdt), ("z", fdt), ("r", "u1"), ("g", "u1"), ("b", "u1")]
                )
                vrec["x"], vrec["y"], vrec["z"] = v[:, 0], v[:, 1], v[:, 2]
                vrec["r"], vrec["g"], vrec["b"] = col[:, 0], col[:, 1], col[:, 2]
                frec = np.empty(f.shape[0], dtype=[("n", "u1"), ("i", "<i4", (3,))])
                frec["n"] = 3
                frec["i"] = f
                fh.write(vrec.tobytes())
                fh.write(frec.tobytes())
        return path


class OBJWriter(QSMWriter):
    """Wavefront OBJ cylinder mesh with one group per branch order (``g order_<w>``)."""

    name = "obj"
    summary = "Wavefront OBJ cylinder mesh (one group per order)"
    suffixes = (".obj",)
    Settings = MeshSettings
    priority = 10

    def write(self, tree, path, **options) -> Path:
        o = _options(self, options)
        path = Path(path)
        v, f, fc = cylinder_mesh(tree, o.sides, o.caps, o.min_radius, o.translate_to_base)
        order = np.asarray(tree.order)[fc]
        srt = np.argsort(order, kind="stable")
        f, order = f[srt], order[srt]
        with open(path, "w", encoding="ascii", newline="\n") as fh:
            fh.write(f"# Bayes Forest cylinder mesh: {tree.n} cylinders, {o.sides} sides\n")
            fh.write(f"# {provenance_line(tree)}\n")
            fh.write(format_rows(v, ["v %.9g", "%.9g", "%.9g"], sep=" "))
            bounds = np.flatnonzero(np.diff(order)) + 1
            for chunk, w in zip(np.split(f + 1, bounds), order[np.concatenate([[0], bounds])] if f.size else []):
                fh.write(f"g order_{int(w)}\n")
                fh.write(format_rows(chunk.astype(np.float64), ["f %d", "%d", "%d"], sep=" "))
        return path
