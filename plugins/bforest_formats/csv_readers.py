"""CSV readers: SimpleForest CSV (docs/qsm-formats.md §6), aRchi CSV (§7) and the native CSV (§9).

Each reads the header, parses the table with :func:`bforest_core.tables.parse_table`, turns the
file's own ids into rows and hands a :class:`~bforest_core.cylinders.RawCylinders` table to
:func:`~bforest_core.cylinders.build_tree`.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import numpy as np

from bforest_core.cylinders import (
    BaseReader,
    RawCylinders,
    build_tree,
    labels_to_int,
    plural,
    rows_text,
    select_models,
    sniff_safely,
    warn,
)
from bforest_core.errors import QSMFormatError
from bforest_core.tables import looks_binary, parse_table, read_bytes, split_lines_head
from bforest_core.tree import remap_ids

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


#: the required columns of each CSV layout, by reader name, and what a user calls the layout
LAYOUTS = {
    "simpleforest-csv": ("a SimpleForest CSV", SIMPLEFOREST_REQUIRED),
    "archi-csv": ("an aRchi CSV", ARCHI_REQUIRED),
    "bforest-csv": ("a native CSV", NATIVE_REQUIRED),
}


def closest_layout(names) -> Optional[str]:
    """The layout whose required columns the header holds the largest share of (at least half),
    for a header that names none in full: an aRchi CSV without ``parent_ID`` is named as an aRchi
    CSV that lacks it, not as a native CSV that lacks ten columns."""
    have = set(names)
    share = {k: len(have.intersection(req)) / len(req) for k, (_, req) in LAYOUTS.items()}
    best = max(share, key=share.get)
    return best if share[best] >= 0.5 else None


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
            near = closest_layout(names) if det is None else None
            if near is not None and near != self.name:  # claimed as the fallback, but it is another layout
                label, req = LAYOUTS[near]
                lack = [c for c in req if c not in names]
                raise QSMFormatError(
                    path,
                    f"line 1: the header looks like {label} (reader '{near}': {len(req) - len(lack)} of its "
                    f"{len(req)} required columns) but lacks column(s) {', '.join(lack)} (found: {', '.join(names[:20])})",
                )
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
    """The native CSV of :class:`~bforest_formats.writers.CSVWriter` (docs/qsm-formats.md §9): 0-based ids,
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
        added = cols.get("added")  # build_tree refuses NaN (naming 'added') and takes non-zero for True
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
            want = remap_ids(want, inv)
            diff = np.flatnonzero(want != tree.extension)
            if diff.size:
                warn(
                    path,
                    f"{plural(diff.size, 'row')} have a stored extension that differs from the "
                    f"'{rule}' rule recomputed on read (rows {rows_text(srow[diff] + 1)}); the "
                    "recomputed one is used",
                )
        return [tree] if as_list else tree
