"""TreeQSM's cylinder columns: names, widths and the order of every layout (the text files of
docs/qsm-formats.md §4-§5 and the 2.4 ``.mat`` struct of §1), for the readers and the writers
alike, and the one function that turns a numeric table in a TreeQSM layout into
:class:`~bforest_core.cylinders.RawCylinders`.
"""

from __future__ import annotations

import numpy as np

from bforest_core.cylinders import RawCylinders, ids_to_rows, labels_to_int, rows_text
from bforest_core.errors import QSMFormatError

#: fields wider than one column
WIDTH = {"start": 3, "axis": 3}
#: TreeQSM 2.4's ``cylinder`` struct, in its field order
STRUCT_FIELDS = (
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
)
#: the fields holding ids, flags and counts (written as integers)
INTEGER_FIELDS = ("parent", "extension", "added", "branch", "BranchOrder", "PositionInBranch")
#: per-cylinder values TreeQSM derives from the points: kept as extras on read, written back
POINT_FIELDS = ("mad", "SurfCov", "UnmodRadius")
#: TreeQSM <= 2.2's CylData matrix, in its column order
CYLDATA14 = (
    "radius",
    "length",
    "start",
    "axis",
    "parent",
    "extension",
    "branch",
    "BranchOrder",
    "PositionInBranch",
    "added",
)
#: the text layouts, field by field (docs/qsm-formats.md §4, §5a, §5b)
LAYOUTS = {
    "treeqsm17": (
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
    ),
    "treeqsm15-struct": (
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
    ),
    "treeqsm15-cyldata": CYLDATA14 + ("UnmodRadius",),
    "cyldata14": CYLDATA14,
}
#: how messages name a field
_SAID = {"BranchOrder": "branch order"}


def layout_columns(layout: str) -> dict[str, int | slice]:
    """Where each field of a text layout sits in a row: a 0-based column, or a slice for the
    3-wide ``start`` and ``axis``."""
    out, c = {}, 0
    for name in LAYOUTS[layout]:
        w = WIDTH.get(name, 1)
        out[name] = c if w == 1 else slice(c, c + w)
        c += w
    return out


def table_to_raw(path, values: np.ndarray, layout: str, label: str = "") -> RawCylinders:
    """A numeric table in a TreeQSM layout (1-based ids, 0 = none) as :class:`RawCylinders`;
    messages name a column by its 1-based number (after ``label``, e.g. the MAT variable)."""
    v = np.asarray(values, dtype=np.float64)
    n = v.shape[0]
    col = layout_columns(layout)
    said = lambda name: f"{label + ' ' if label else ''}column {col[name] + 1} ({_SAID.get(name, name)})"
    return RawCylinders(
        radius=v[:, col["radius"]],
        length=v[:, col["length"]],
        start=v[:, col["start"]],
        axis=v[:, col["axis"]],
        parent=ids_to_rows(path, said("parent"), v[:, col["parent"]], n, 1, what="parent"),
        extension=ids_to_rows(path, said("extension"), v[:, col["extension"]], n, 1, what="extension"),
        added=flag_column(path, said("added"), v[:, col["added"]]),
        branch=labels_to_int(path, said("branch"), v[:, col["branch"]], n),
        order=labels_to_int(path, said("BranchOrder"), v[:, col["BranchOrder"]], n),
        extras={k: v[:, col[k]] for k in POINT_FIELDS if k in col},
    )


def flag_column(path, name: str, values) -> np.ndarray:
    """A 0/1 column as bool; NaN or infinity is an error naming the column, not True."""
    v = np.asarray(values, dtype=np.float64)
    bad = np.flatnonzero(~np.isfinite(v))
    if bad.size:
        raise QSMFormatError(path, f"non-finite values in '{name}' at rows {rows_text(bad + 1)}", bad + 1)
    return v != 0
