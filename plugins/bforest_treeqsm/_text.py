"""Text readers: TreeQSM cylinder text (17 columns with header, 15-column headerless layouts,
14-column CylData; docs/qsm-formats.md §4, §5), SimpleForest CSV (§6), aRchi CSV (§7) and the native CSV (§9).

Parsing is vectorised: the field count of every line comes from byte masks (so a ragged line is
reported by its number), the numbers from one ``np.loadtxt`` call.
"""

from __future__ import annotations

import io
import json
import warnings
from pathlib import Path
from typing import Literal, Optional

import numpy as np

from bforest_core.errors import QSMFormatError

from ._mat import cyldata14_to_raw, mat_kind
from .raw_cylinders import (
    BaseReader,
    RawCylinders,
    ReaderSettings,
    build_tree,
    ids_to_rows,
    labels_to_int,
    plural,
    rows_text,
    select_models,
    sniff_safely,
    warn,
)

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
_SEP_TABLE = bytes.maketrans(b",\r\x0b\x0c", b"    ")
_ZERO_HINT = "TreeQSM text rounds to 0.1 mm"


# ------------------------------------------------------------------------------------------
# vectorised table parsing
# ------------------------------------------------------------------------------------------


def read_bytes(path: Path) -> bytes:
    with open(path, "rb") as fh:
        return fh.read()


def looks_binary(head: bytes) -> Optional[str]:
    """A message when ``head`` is not text, else ``None``."""
    if mat_kind(head) is not None:
        return "content looks like a MAT-file, not text"
    if head[:8] == b"\x89HDF\r\n\x1a\n":
        return "content looks like an HDF5 file, not text"
    if b"\x00" in head[:4096]:
        return "content looks like binary data, not text"
    return None


def split_lines_head(data: bytes, k: int):
    """First ``k`` lines (decoded, stripped of CR/LF) and the byte offset after them."""
    lines = []
    pos = 0
    for _ in range(k):
        j = data.find(b"\n", pos)
        if j < 0:
            lines.append(data[pos:].decode("latin-1").rstrip("\r"))
            pos = len(data)
            break
        lines.append(data[pos:j].decode("latin-1").rstrip("\r"))
        pos = j + 1
    return lines, pos


def field_counts(body: bytes):
    """Number of fields on every line of ``body`` (separators: whitespace/control bytes and
    commas). Returns ``(counts, line_index)`` for the non-blank lines (0-based line index)."""
    arr = np.frombuffer(body, dtype=np.uint8)
    if arr.size == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    sep = (arr <= 32) | (arr == 44)
    starts = ~sep
    starts[1:] &= sep[:-1]
    tok = np.flatnonzero(starts)
    nl = np.flatnonzero(arr == 10)
    counts = np.bincount(np.searchsorted(nl, tok), minlength=nl.size + 1)
    lines = np.flatnonzero(counts)
    return counts[lines], lines


def first_line_fields(body: bytes) -> int:
    """Fields on the first non-blank line of ``body``."""
    for line in body[: 1 << 16].split(b"\n"):
        k = len(line.translate(_SEP_TABLE).split())
        if k:
            return k
    return 0


def _ragged(path, body: bytes, first_line: int, k: int, what: str):
    """Error path: report the first line whose field count is not ``k``."""
    counts, lines = field_counts(body)
    bad = np.flatnonzero(counts != k)
    if bad.size:
        i = int(bad[0])
        more = f" (and {bad.size - 1} more lines)" if bad.size > 1 else ""
        raise QSMFormatError(
            path,
            f"line {int(lines[i]) + first_line}: {int(counts[i])} {what}, expected {k}{more}",
            (lines[bad[:10]] + first_line).tolist(),
        )


def parse_table(path, body: bytes, first_line: int, expected: Optional[int], what: str = "fields"):
    """Parse whitespace/comma separated numbers with one ``np.loadtxt`` call.

    The fast path trusts ``np.loadtxt`` (which refuses ragged rows and bad numbers); only when it
    fails are the lines examined, to report the first ragged line or the first field that is
    not a number with its file line.

    Parameters
    ----------
    body : bytes
        The data part of the file.
    first_line : int
        1-based line number of the first line of ``body`` (for messages).
    expected : int or None
        Required fields per line; ``None`` takes the first line's count.

    Returns
    -------
    values : (m, k) float64
    """
    k = first_line_fields(body) if expected is None else int(expected)
    if k == 0:
        raise QSMFormatError(path, "file contains no cylinders")
    if b"," in body or b"\r" in body or b"\x0b" in body or b"\x0c" in body:
        body = body.translate(_SEP_TABLE)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            values = np.loadtxt(io.BytesIO(body), dtype=np.float64, comments=None, ndmin=2, encoding="latin1")
    except Exception:
        _ragged(path, body, first_line, k, what)
        _locate_bad_token(path, body.decode("latin-1"), first_line)
        raise QSMFormatError(path, "could not read the numbers of the table") from None
    if values.shape[0] == 0:
        raise QSMFormatError(path, "file contains no cylinders")
    if values.shape[1] != k:
        _ragged(path, body, first_line, k, what)
        raise QSMFormatError(path, f"{values.shape[1]} {what} per line, expected {k}")
    return values


def _locate_bad_token(path, text: str, first_line: int) -> None:
    """Error path only: find the first field that is not a number and raise."""
    for j, line in enumerate(text.split("\n")):
        for c, tok in enumerate(line.split()):
            try:
                float(tok)
            except ValueError:
                shown = tok if len(tok) <= 40 else tok[:37] + "..."
                raise QSMFormatError(
                    path, f"line {j + first_line}, field {c + 1}: cannot read {shown!r} as a number", [j + first_line]
                ) from None


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
        raw = text_to_raw(path, values, layout)
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


def text_to_raw(path, v: np.ndarray, layout: str) -> RawCylinders:
    n = v.shape[0]
    if layout == "cyldata14":
        return cyldata14_to_raw(path, v, "column")
    if layout == "treeqsm17":
        cols = {"branch": 10, "order": 11, "added": 15}
        extras = {"mad": v[:, 13], "SurfCov": v[:, 14], "UnmodRadius": v[:, 16]}
    elif layout == "treeqsm15-struct":
        cols = {"added": 10, "branch": 12, "order": 13}
        extras = {"UnmodRadius": v[:, 11]}
    else:  # treeqsm15-cyldata
        cols = {"branch": 10, "order": 11, "added": 13}
        extras = {"UnmodRadius": v[:, 14]}
    c = cols
    return RawCylinders(
        radius=v[:, 0],
        length=v[:, 1],
        start=v[:, 2:5],
        axis=v[:, 5:8],
        parent=ids_to_rows(path, "column 9 (parent)", v[:, 8], n, 1, what="parent"),
        extension=ids_to_rows(path, "column 10 (extension)", v[:, 9], n, 1, what="extension"),
        added=_flag(path, f"column {c['added'] + 1} (added)", v[:, c["added"]]),
        branch=labels_to_int(path, f"column {c['branch'] + 1} (branch)", v[:, c["branch"]], n),
        order=labels_to_int(path, f"column {c['order'] + 1} (branch order)", v[:, c["order"]], n),
        extras=extras,
    )


def _flag(path, name, v):
    bad = np.flatnonzero(~np.isfinite(v))
    if bad.size:
        raise QSMFormatError(path, f"non-finite values in '{name}' at rows {rows_text(bad + 1)}", bad + 1)
    return v != 0


# ------------------------------------------------------------------------------------------
# CSV layouts
# ------------------------------------------------------------------------------------------

SIMPLEFOREST_REQUIRED = [
    "ID",
    "parentID",
    "startX",
    "startY",
    "startZ",
    "endX",
    "endY",
    "endZ",
    "radius",
    "branchOrder",
]
ARCHI_REQUIRED = [
    "startX",
    "startY",
    "startZ",
    "endX",
    "endY",
    "endZ",
    "cyl_ID",
    "parent_ID",
    "radius_cyl",
    "axis_ID",
    "branching_order",
]
NATIVE_COLUMNS = [
    "id",
    "parent",
    "extension",
    "branch",
    "order",
    "position_in_branch",
    "added",
    "start_x",
    "start_y",
    "start_z",
    "axis_x",
    "axis_y",
    "axis_z",
    "length",
    "radius",
    "end_x",
    "end_y",
    "end_z",
]
NATIVE_REQUIRED = [
    "id",
    "parent",
    "extension",
    "start_x",
    "start_y",
    "start_z",
    "axis_x",
    "axis_y",
    "axis_z",
    "length",
    "radius",
]


def csv_header_names(first_line: str) -> list[str]:
    return [s.strip().lstrip("\ufeff").strip('"').strip() for s in first_line.split(",")]


def detect_csv(head: bytes) -> Optional[str]:
    """Which CSV layout the header line names (docs/qsm-formats.md §8), or ``None``."""
    if looks_binary(head):
        return None
    if head[:3] == b"\xef\xbb\xbf":
        head = head[3:]
    names = set(csv_header_names(head.split(b"\n", 1)[0].decode("latin-1").rstrip("\r")))
    if {"parentID", "branchOrder"} <= names:
        return "simpleforest-csv"
    if {"cyl_ID", "parent_ID", "axis_ID"} <= names:
        return "archi-csv"
    if {"id", "parent", "extension", "start_x"} <= names:
        return "bforest-csv"
    return None


class _CSVReader(BaseReader):
    suffixes = (".csv",)
    container = "CSV reader"
    required: list[str] = []
    layout_label = "CSV"

    @sniff_safely
    def sniff(self, path, head):
        return detect_csv(head) == self.name

    def _table(self, path):
        data = read_bytes(path)
        if not data.strip():
            raise QSMFormatError(path, "file is empty")
        msg = looks_binary(data[:4096])
        if msg:
            raise QSMFormatError(path, msg)
        if data[:3] == b"\xef\xbb\xbf":
            data = data[3:]
        (first,), after = split_lines_head(data, 1)
        names = csv_header_names(first)
        missing = [c for c in self.required if c not in names]
        if missing:
            det = detect_csv(data[:4096])
            hint = f"; it looks like reader '{det}'" if det and det != self.name else ""
            raise QSMFormatError(
                path,
                f"line 1: {self.layout_label} header lacks column(s) "
                f"{', '.join(missing)} (found: {', '.join(names[:20])}){hint}",
            )
        dup = sorted({c for c in names if names.count(c) > 1})
        if dup:
            raise QSMFormatError(path, f"line 1: column name(s) {', '.join(dup)} appear more than once")
        values = parse_table(path, data[after:], 2, len(names), what="fields")
        return {nm: values[:, i] for i, nm in enumerate(names)}, names


def id_rows(path, ids_col, parent_col, id_name: str, parent_name: str, none_value: int):
    """Rows of the parent ids through the file's own ``ID`` column (ids need not equal rows)."""
    n = ids_col.shape[0]
    ids = labels_to_int(path, id_name, ids_col, n)
    pids = labels_to_int(path, parent_name, parent_col, n)
    srt = np.argsort(ids, kind="stable")
    sids = ids[srt]
    dup = np.flatnonzero(sids[1:] == sids[:-1])
    if dup.size:
        v = sids[dup[0]]
        rows = np.flatnonzero(ids == v) + 1
        times = "twice" if rows.size == 2 else f"{rows.size} times"
        raise QSMFormatError(path, f"{id_name} {v} appears {times} (rows {rows_text(rows)})", rows)
    return ids, srt, sids, lookup_ids(path, pids, srt, sids, parent_name, none_value)


def lookup_ids(path, pids, srt, sids, name, none_value):
    n = sids.shape[0]
    none = pids == none_value
    pos = np.clip(np.searchsorted(sids, pids), 0, n - 1)
    found = sids[pos] == pids
    bad = np.flatnonzero(~none & ~found)
    if bad.size:
        raise QSMFormatError(
            path,
            f"{name} {pids[bad[0]]} at row {bad[0] + 1} is not an id of the file "
            f"({none_value} = none){f' ({bad.size} rows)' if bad.size > 1 else ''}",
            bad + 1,
        )
    return np.where(none, -1, srt[pos]).astype(np.int64)


def geometry_from_ends(path, cols, length_col: Optional[str]):
    start = np.column_stack([cols["startX"], cols["startY"], cols["startZ"]])
    end = np.column_stack([cols["endX"], cols["endY"], cols["endZ"]])
    d = end - start
    length = np.sqrt(np.einsum("ij,ij->i", d, d))
    with np.errstate(invalid="ignore", divide="ignore"):
        axis = np.where(length[:, None] > 0, d / np.where(length > 0, length, 1.0)[:, None], 0.0)
    # non-finite end points make non-finite axes: build_tree reports them as such
    axis = np.where(np.isfinite(d), axis, np.nan)
    if length_col is not None and length_col in cols:
        lc = cols[length_col]
        diff = np.abs(lc - length)
        off = np.flatnonzero(np.isfinite(diff) & (diff > 1e-3))
        if off.size:
            warn(
                path,
                f"the '{length_col}' column differs from the end-point distance by more than "
                f"1 mm in {plural(off.size, 'row')} (rows {rows_text(off + 1)}; up to "
                f"{diff[off].max():.4g} m); the end points are used",
            )
    return start, axis, length


def extension_by_label(path, parent: np.ndarray, label: np.ndarray, what: str) -> np.ndarray:
    """Extension = the child carrying its parent's ``label`` (same branch order / axis id).

    When several children qualify, the earliest row continues and a warning is given."""
    n = parent.shape[0]
    rows = np.flatnonzero(parent >= 0)
    cand = rows[label[rows] == label[parent[rows]]]
    ext = np.full(n, -1, dtype=np.int64)
    if cand.size == 0:
        return ext
    p = parent[cand]
    srt = np.lexsort((cand, p))
    ps = p[srt]
    first = np.ones(ps.size, dtype=bool)
    first[1:] = ps[1:] != ps[:-1]
    ext[ps[first]] = cand[srt][first]
    multi = np.unique(ps[~first])
    if multi.size:
        warn(
            path,
            f"{plural(multi.size, 'cylinder')} have several children with their {what} "
            f"(rows {rows_text(multi + 1)}); the earliest child continues the branch",
        )
    return ext


class SimpleForestCSVReader(_CSVReader):
    """SimpleForest CSV (docs/qsm-formats.md §6): 0-based ``ID``/``parentID`` (-1 = none), end points instead of
    axis and length; extension = the child with its parent's ``branchOrder``."""

    name = "simpleforest-csv"
    summary = "SimpleForest cylinder CSV (0-based ids, end points)"
    priority = 20
    required = SIMPLEFOREST_REQUIRED
    layout_label = "SimpleForest"

    def _read(self, path, opts):
        cols, names = self._table(path)
        _, as_list, _ = select_models(path, [0], opts.select, "file")
        _, _, _, parent = id_rows(path, cols["ID"], cols["parentID"], "ID", "parentID", -1)
        n = parent.shape[0]
        order = labels_to_int(path, "branchOrder", cols["branchOrder"], n)
        start, axis, length = geometry_from_ends(path, cols, "length")
        ext = extension_by_label(path, parent, order, "branchOrder")
        used = set(SIMPLEFOREST_REQUIRED) | {"length"}
        extras = {k: v for k, v in cols.items() if k not in used}
        raw = RawCylinders(cols["radius"], length, start, axis, parent, ext, None, None, order, extras)
        tree = build_tree(path, raw, fmt=self.name, version=None, opts=opts, metadata={"model_index": 0, "n_models": 1})
        return [tree] if as_list else tree


class ArchiCSVReader(_CSVReader):
    """aRchi CSV (docs/qsm-formats.md §7): 1-based ``cyl_ID``/``parent_ID`` (0 = none), trunk order 1, branch =
    ``axis_ID``; extension = the child on its parent's axis (``extension_ID`` is not trusted)."""

    name = "archi-csv"
    summary = "aRchi cylinder CSV (1-based ids, end points, axis_ID branches)"
    priority = 20
    required = ARCHI_REQUIRED
    layout_label = "aRchi"

    def _read(self, path, opts):
        cols, names = self._table(path)
        _, as_list, _ = select_models(path, [0], opts.select, "file")
        ids, srt, sids, parent = id_rows(path, cols["cyl_ID"], cols["parent_ID"], "cyl_ID", "parent_ID", 0)
        n = parent.shape[0]
        axis_id = labels_to_int(path, "axis_ID", cols["axis_ID"], n)
        order = labels_to_int(path, "branching_order", cols["branching_order"], n) - 1
        start, axis, length = geometry_from_ends(path, cols, "length")
        ext = extension_by_label(path, parent, axis_id, "axis_ID")
        meta = {"model_index": 0, "n_models": 1}
        if "extension_ID" in cols:
            eid = cols["extension_ID"]
            ok = np.isfinite(eid) & (eid == np.round(eid))
            stored = np.full(n, -2, dtype=np.int64)
            e = np.where(ok, eid, -1).astype(np.int64)
            none = e == 0
            pos = np.clip(np.searchsorted(sids, e), 0, n - 1)
            found = sids[pos] == e
            stored[none] = -1
            stored[found & ~none] = srt[pos[found & ~none]]
            meta["extension_ID_disagreements"] = int(np.count_nonzero(stored != ext))
        used = set(ARCHI_REQUIRED) | {"length"}
        extras = {k: v for k, v in cols.items() if k not in used}
        raw = RawCylinders(cols["radius_cyl"], length, start, axis, parent, ext, None, axis_id, order, extras)
        tree = build_tree(path, raw, fmt=self.name, version=None, opts=opts, metadata=meta)
        return [tree] if as_list else tree


class NativeCSVReader(_CSVReader):
    """The native CSV of :class:`~bforest_treeqsm.writers.CSVWriter` (docs/qsm-formats.md §9): 0-based ids,
    -1 = none, named columns, optional JSON sidecar ``<name>.json`` with the metadata.

    Without an explicit ``topology`` the rule recorded in the sidecar is used, so a written tree
    reads back identical. Unknown columns go to ``extras``. Also claims CSV files of no known
    layout, to report what their header lacks.
    """

    name = "bforest-csv"
    summary = "Bayes Forest native cylinder CSV (+ JSON sidecar)"
    priority = 10
    required = NATIVE_REQUIRED
    layout_label = "native CSV"

    @sniff_safely
    def sniff(self, path, head):
        det = detect_csv(head)
        return det == self.name or det is None

    def _read(self, path, opts):
        cols, names = self._table(path)
        _, as_list, _ = select_models(path, [0], opts.select, "file")
        side = {}
        sp = Path(path).with_suffix(".json")
        if sp.exists():
            try:
                side = json.loads(sp.read_text(encoding="utf-8"))
                if not isinstance(side, dict):
                    raise ValueError("not a JSON object")
            except Exception as exc:
                raise QSMFormatError(sp, f"sidecar is not valid JSON ({exc})") from None
        ids, srt, sids, parent = id_rows(path, cols["id"], cols["parent"], "id", "parent", -1)
        n = parent.shape[0]
        ext_col = labels_to_int(path, "extension", cols["extension"], n)
        ext = lookup_ids(path, ext_col, srt, sids, "extension", -1)
        rule = side.get("topology", "source")
        if rule not in ("source", "subtree", "thickest"):
            raise QSMFormatError(sp, f"sidecar: topology {rule!r} is not one of source, subtree, thickest")
        if not isinstance(side.get("metadata") or {}, dict):
            raise QSMFormatError(sp, "sidecar: metadata is not a JSON object")
        src_ext = None
        if "source_extension" in cols:
            se = labels_to_int(path, "source_extension", cols["source_extension"], n)
            src_ext = lookup_ids(path, se, srt, sids, "source_extension", -1)
        start = np.column_stack([cols["start_x"], cols["start_y"], cols["start_z"]])
        axis = np.column_stack([cols["axis_x"], cols["axis_y"], cols["axis_z"]])
        added = _flag(path, "added", cols["added"]) if "added" in cols else None
        used = set(NATIVE_COLUMNS) | {"source_extension"}
        extras = {k: v for k, v in cols.items() if k not in used}
        meta = {}
        for k, v in dict(side.get("metadata") or {}).items():
            # keys this read sets itself keep the written values under "original_<key>"
            if k in (
                "source",
                "format",
                "version",
                "units",
                "repairs",
                "n_file_rows",
                "height",
                "base",
                "model_index",
                "n_models",
                "topology",
            ):
                meta["original_" + k] = v
            else:
                meta[k] = v
        for k in ("model", "params", "seed"):
            if side.get(k) is not None:
                meta.setdefault(k, side[k])
        meta.update(
            {"model_index": 0, "n_models": 1, "written_topology": rule, "format_version": side.get("format_version")}
        )
        # the stored extension is the written tree's; with a source_extension column the source
        # links are rebuilt first and the written rule applied on top (same result, and
        # with_topology('source') still restores the original branching)
        base_ext = src_ext if src_ext is not None else ext
        default_rule = rule
        raw = RawCylinders(cols["radius"], cols["length"], start, axis, parent, base_ext, added, extras=extras)
        tree = build_tree(
            path,
            raw,
            fmt=self.name,
            version=str(side.get("format_version", "1")),
            opts=opts,
            metadata=meta,
            default_topology=default_rule,
        )
        if (opts.topology or default_rule) == rule and tree.n == n:
            srow = tree.source_row
            want = ext[srow]
            inv = np.full(n, -1, dtype=np.int64)
            inv[srow] = np.arange(tree.n)
            want = np.where(want >= 0, inv[np.maximum(want, 0)], -1)
            diff = np.flatnonzero(want != tree.extension)
            if diff.size:
                warn(
                    path,
                    f"{plural(diff.size, 'row')} have a stored extension that differs from the "
                    f"'{rule}' rule recomputed on read (rows {rows_text(srow[diff] + 1)}); the "
                    "recomputed one is used",
                )
        return [tree] if as_list else tree
