"""The tables ``bforest info`` shows besides the classical metrics: TreeQSM's tree attributes,
its distributions and the per-branch table (:mod:`bforest_core.attributes`), as text, JSON rows
and CSV rows."""

from __future__ import annotations

import textwrap

from ..attributes import (
    ATTRIBUTE_UNITS,
    BRANCH_COLUMNS,
    DISTRIBUTION_UNITS,
    branch_table,
    distributions,
    tree_attributes,
)
from ..metrics import summary_definition

#: what the attributes are called where a user reads them
ATTRIBUTE_LABELS = {
    "total_volume": "total wood volume",
    "trunk_volume": "trunk volume",
    "branch_volume": "branch volume",
    "tree_height": "tree height",
    "trunk_length": "trunk length",
    "branch_length": "total branch length",
    "total_length": "total length",
    "n_branches": "branches (no trunk)",
    "max_branch_order": "max branch order",
    "trunk_area": "trunk area",
    "branch_area": "total branch area",
    "total_area": "total area",
    "dbh": "DBH (1.3 m)",
    "crown_diameter_mean": "crown diameter, mean",
    "crown_diameter_max": "crown diameter, max",
    "crown_area_conv": "crown area (convex hull)",
    "crown_area_alpha": "crown area (alpha shape)",
    "crown_base_height": "crown base height",
    "crown_length": "crown length",
    "crown_ratio": "crown ratio",
    "crown_volume_conv": "crown volume (convex hull)",
    "crown_volume_alpha": "crown volume (alpha shape)",
}

#: (title, class name, class width, class unit, distribution names) of the distributions shown
DISTRIBUTION_TABLES = [
    ("wood by cylinder diameter", "Dia", 1.0, "cm", ["VolCylDia", "LenCylDia"]),
    ("wood by height", "Hei", 1.0, "m", ["VolCylHei", "LenCylHei"]),
    ("branches by order", "Ord", 1.0, "", ["NumBranchOrd", "VolBranchOrd", "LenBranchOrd"]),
    ("branches by base diameter", "Dia", 1.0, "cm", ["NumBranchDia", "VolBranchDia", "LenBranchDia"]),
    ("branches by base height", "Hei", 1.0, "m", ["NumBranchHei", "VolBranchHei", "LenBranchHei"]),
    ("branches by branching angle", "Ang", 10.0, "deg", ["NumBranchAng", "VolBranchAng", "LenBranchAng"]),
]
_HEAD = {"Num": "branches", "Vol": "volume (m^3)", "Len": "length (m)", "Are": "area (m^2)"}


def distribution_unit(name: str) -> str:
    return DISTRIBUTION_UNITS[name[:3].lower()]


def class_bounds(name: str, k: int) -> tuple[float, float, str]:
    """(lower, upper, unit) of class k (0-based) of a distribution."""
    if name.endswith("Ord"):
        return float(k + 1), float(k + 1), "order"
    if name.endswith("Dia"):
        return float(k), float(k + 1), "cm"
    if name.endswith("Hei"):
        return float(k), float(k + 1), "m"
    if name.endswith("Azi"):
        return 10.0 * k - 180, 10.0 * k - 170, "deg"
    return 10.0 * k, 10.0 * (k + 1), "deg"


def info_text(tree) -> list[str]:
    """The attribute block and the distribution tables of ``bforest info``."""
    notes: list[str] = []
    a = tree_attributes(tree, notes=notes)
    d = distributions(tree)
    lines = ["  tree attributes (TreeQSM's, SI units; definitions: docs/tree-attributes.md)"]
    for k, label in ATTRIBUTE_LABELS.items():
        v, u = a[k], ATTRIBUTE_UNITS[k]
        if k in ("n_branches", "max_branch_order"):
            txt = f"{int(v)}"
        elif v != v:
            txt = "–"
        else:
            txt = f"{v:.4g}" + (f" {u}" if u else "")
        lines.append(f"    {label:<28}{txt}")
    lines += [f"    note: {n}" for n in notes]
    lines.append("  the two crown widths, defined otherwise:")
    for key in ("crown_spread", "crown_diameter_mean"):
        lines += textwrap.wrap(summary_definition(key), 100, initial_indent="    ", subsequent_indent="      ")
    for title, _, width, unit, names in DISTRIBUTION_TABLES:
        n = max(d[x].size for x in names)
        nz = [k for k in range(n) if any(d[x][k] != 0 for x in names)]
        if not nz:
            continue
        lines.append(f"  {title}" + (f" ({width:g} {unit} classes; empty ones left out)" if unit else ""))
        lines.append("    " + f"{'class':>9}" + "".join(f"{_HEAD[x[:3]]:>14}" for x in names))
        for k in nz:
            lo, hi, _u = class_bounds(names[0], k)
            cls = f"{int(lo)}" if names[0].endswith("Ord") else f"{lo:g}-{hi:g}"
            cells = "".join(f"{int(d[x][k]):>14}" if x.startswith("Num") else f"{d[x][k]:>14.4g}" for x in names)
            lines.append(f"    {cls:>9}{cells}")
    return lines


def info_json(tree) -> dict:
    """Attributes, distributions (with units and class bounds) for ``bforest info --json``."""
    d = distributions(tree)
    return {
        "attributes": tree_attributes(tree),
        "attribute_units": dict(ATTRIBUTE_UNITS),
        "distributions": {k: v.tolist() for k, v in d.items()},
        "distribution_units": {k: distribution_unit(k) for k in d},
        "distribution_classes": "class k (0-based): diameters [k, k+1) cm, heights [k, k+1) m above the lowest "
        "cylinder, angles and zenith [10k, 10k+10) deg, azimuth [10k-180, 10k-170) deg, "
        "orders k+1",
    }


def csv_rows(tree, table: str) -> tuple[list[str], list[list]]:
    """(header, rows) of ``bforest info --csv --table attributes|distributions|branches``."""
    if table == "attributes":
        a = tree_attributes(tree)
        return ["attribute", "value", "unit"], [[k, a[k], ATTRIBUTE_UNITS[k]] for k in ATTRIBUTE_UNITS]
    if table == "distributions":
        rows = []
        for k, v in distributions(tree).items():
            for i, x in enumerate(v):
                lo, hi, cu = class_bounds(k, i)
                rows.append([k, i, lo, hi, cu, float(x), distribution_unit(k)])
        return ["distribution", "class", "class_lower", "class_upper", "class_unit", "value", "unit"], rows
    b = branch_table(tree)
    cols = list(BRANCH_COLUMNS)
    head = ["branch"] + [f"{c}_{BRANCH_COLUMNS[c]}" if BRANCH_COLUMNS[c] else c for c in cols]
    n = b["order"].size
    return head, [[i] + [int(b[c][i]) if c in ("order", "parent") else float(b[c][i]) for c in cols] for i in range(n)]
