"""TreeQSM text reader: cylinder text with 17 columns and header, the 15-column headerless layouts
and 14-column CylData (docs/qsm-formats.md §4, §5); the table is parsed by
:func:`bforest_core.tables.parse_table`.
"""

from __future__ import annotations

from typing import Literal, Optional

import numpy as np

from bforest_core.cylinders import (
    BaseReader,
    ReaderSettings,
    build_tree,
    select_models,
    sniff_safely,
)
from bforest_core.errors import QSMFormatError
from bforest_core.tables import first_line_fields, looks_binary, parse_table, read_bytes, split_lines_head

from .columns import table_to_raw

TREEQSM17_NAMES = [
    "radius (m)",
    "length (m)",
    "start_point",
    "axis_direction",
    "parent",
    "extension",
    "branch",
    "branch_order",
    "position_in_branch",
    "mad",
    "SurfCov",
    "added",
    "UnmodRadius (m)",
]
TEXT_SUFFIXES = (".txt", ".dat")
_ZERO_HINT = "TreeQSM text rounds to 0.1 mm"


def is_integral(col: np.ndarray) -> bool:
    return bool(np.all(np.isfinite(col)) and np.all(col == np.round(col)))


# ------------------------------------------------------------------------------------------
# TreeQSM text
# ------------------------------------------------------------------------------------------


class TextSettings(ReaderSettings):
    #: column layout; ``None`` detects it from the header / field count / content
    layout: Optional[Literal["treeqsm17", "treeqsm15-struct", "treeqsm15-cyldata", "cyldata14"]] = None


LAYOUT_VERSION = {
    "treeqsm17": "2.4.x",
    "treeqsm15-cyldata": "2.3.x",
    "treeqsm15-struct": "2.3.x",
    "cyldata14": "<= 2.2",
}


class TreeQSMTextReader(BaseReader):
    """TreeQSM cylinder text files (docs/qsm-formats.md §5a, §5b, §4 text).

    * ``treeqsm17``: ``save_model_text`` 1.1.0 (TreeQSM 2.4), 13-name header and 17 columns
      (also accepted without the header);
    * ``treeqsm15-struct`` / ``treeqsm15-cyldata``: the two headerless 15-column orders, told
      apart by which columns are integral;
    * ``cyldata14``: the 14-column CylData layout.
    """

    name = "treeqsm-text"
    summary = "TreeQSM cylinder text (17 columns + header, 15-column layouts, 14-column CylData)"
    suffixes = TEXT_SUFFIXES
    Settings = TextSettings
    priority = 0
    container = "text reader"

    @sniff_safely
    def sniff(self, path, head):
        # the only text reader of this plugin: it also claims files it cannot read, so that
        # read() reports the precise problem (field counts, binary content)
        return True

    def _read(self, path, opts):
        data = read_bytes(path)
        if not data.strip():
            raise QSMFormatError(path, "file is empty" if not data else "file contains no cylinders")
        msg = looks_binary(data[:4096])
        if msg:
            raise QSMFormatError(path, msg)
        if data[:3] == b"\xef\xbb\xbf":
            data = data[3:]
        (first,), after = split_lines_head(data, 1)
        header = first.strip().lower().startswith("radius (m)")
        layout = opts.layout
        if header:
            names = [s.strip() for s in first.split("\t") if s.strip()]
            if names != TREEQSM17_NAMES and layout is None:
                # tolerate a different header only when it names the 13 fields in order
                if [s.lower() for s in names] != [s.lower() for s in TREEQSM17_NAMES]:
                    raise QSMFormatError(
                        path,
                        f"line 1: header has {len(names)} names "
                        f"({', '.join(names[:5])}, ...); expected the 13 TreeQSM names",
                    )
            body, first_line = data[after:], 2
            if layout is None:
                layout = "treeqsm17"
        else:
            body, first_line = data, 1
        k0 = first_line_fields(body)
        if k0 == 0:
            raise QSMFormatError(path, "file contains no cylinders")
        if layout is None:
            if k0 == 17:
                layout = "treeqsm17"
            elif k0 == 15:
                layout = "treeqsm15"
            elif k0 == 14:
                layout = "cyldata14"
            else:
                # a non-numeric first line that is not the TreeQSM header
                try:
                    [float(t) for t in first.replace(",", " ").split()]
                except ValueError:
                    raise QSMFormatError(
                        path, f"line 1 is neither numbers nor the TreeQSM header (starts {first[:40]!r})"
                    ) from None
                raise QSMFormatError(path, f"{k0} columns per row; expected 14, 15 or 17")
        ncol = {"treeqsm17": 17, "treeqsm15": 15, "treeqsm15-struct": 15, "treeqsm15-cyldata": 15, "cyldata14": 14}[
            layout
        ]
        values = parse_table(path, body, first_line, ncol)
        if layout == "treeqsm15":
            layout = detect_15(path, values)
        _, as_list, _ = select_models(path, [0], opts.select, "file")
        raw = table_to_raw(path, values, layout)
        meta = {"layout": layout, "model_index": 0, "n_models": 1, "header": bool(header)}
        tree = build_tree(
            path,
            raw,
            fmt=self.name,
            version=LAYOUT_VERSION[layout],
            opts=opts,
            metadata=meta,
            zero_length_hint=_ZERO_HINT,
        )
        return [tree] if as_list else tree


def detect_15(path, values: np.ndarray) -> str:
    """Column order of a headerless 15-column file (docs/qsm-formats.md §5b), from which columns are integral."""
    integ = [is_integral(values[:, c]) for c in range(15)]
    # 0-based: struct -> 12..14 integral, 11 (UnmodRadius) not; cyldata -> 10..13 integral, 14 not
    struct = integ[12] and integ[13] and integ[14] and not integ[11]
    cyldata = integ[10] and integ[11] and integ[12] and integ[13] and not integ[14]
    if struct and not cyldata:
        return "treeqsm15-struct"
    if cyldata and not struct:
        return "treeqsm15-cyldata"
    raise QSMFormatError(
        path,
        "15 columns per row, but the column order cannot be told from the "
        "content; pass layout='treeqsm15-struct' or layout='treeqsm15-cyldata'",
    )
