"""MAT-file readers: TreeQSM structs (§1), flat variables (§2, §3) and the 14-column CylData
matrix (§4), from MAT v5 (scipy) and MAT v7.3 / HDF5 (h5py) containers alike."""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from bforest_core.cylinders import (
    BaseReader,
    RawCylinders,
    ReaderSettings,
    build_tree,
    float_column,
    ids_to_rows,
    labels_to_int,
    select_models,
    sniff_safely,
)
from bforest_core.errors import QSMFormatError
from bforest_core.tables import mat_kind

from .columns import POINT_FIELDS, STRUCT_FIELDS, table_to_raw

STRUCT_NAMES = ("qsm", "QSM", "OptQSM", "QSMs")
FLAT_NAMES = ("Rad", "Len", "Sta", "Axe", "CPar")
NON_NUMERIC = {"struct", "cell", "char", "function_handle", "object", "opaque", "sparse", "?"}


# ------------------------------------------------------------------------------------------
# container level
# ------------------------------------------------------------------------------------------


def describe_non_mat(head: bytes) -> str:
    """Message for a ``.mat`` file without a MAT header."""
    sample = head[:2048]
    if sample and all(32 <= b < 127 or b in (9, 10, 13) for b in sample):
        first = sample.split(b"\n", 1)[0]
        if first.count(b",") >= 1:
            return "content looks like CSV text, not a MAT-file"
        return "content looks like plain text, not a MAT-file"
    return "not a MAT-file (no MATLAB 5.0 or 7.3 header)"


def _container_name(kind: str) -> str:
    return "MAT v5 reader" if kind == "v5" else "MAT v7.3/HDF5 reader"


def _corrupt(path, kind, exc) -> QSMFormatError:
    return QSMFormatError(path, f"file is truncated or corrupt ({_container_name(kind)}: {type(exc).__name__}: {exc})")


class MatFile:
    """A MAT-file of either kind, with variables listed in MATLAB orientation."""

    def __init__(self, path: Path, kind: str):
        self.path = path
        self.kind = kind
        self._h5 = None
        try:
            if kind == "v5":
                import scipy.io as sio

                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    info = sio.whosmat(str(path))
                self.variables = {name: (tuple(shape), cls) for name, shape, cls in info}
            else:
                import h5py

                self._h5 = h5py.File(str(path), "r")
                self.variables = {}
                for name in self._h5.keys():
                    if name.startswith("#"):
                        continue
                    obj = self._h5[name]
                    cls = _attr_str(obj, "MATLAB_class")
                    shape = tuple(reversed(obj.shape)) if hasattr(obj, "shape") else ()
                    if _attr(obj, "MATLAB_empty"):
                        shape = (0, 0)
                    self.variables[name] = (shape, cls or ("struct" if not hasattr(obj, "shape") else "?"))
        except QSMFormatError:
            raise
        except Exception as exc:
            self.close()
            raise _corrupt(path, kind, exc) from None

    def close(self):
        if self._h5 is not None:
            try:
                self._h5.close()
            except Exception:
                pass
            self._h5 = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False

    def present(self) -> str:
        names = sorted(self.variables)
        return ", ".join(names[:15]) + (f", ... ({len(names)} variables)" if len(names) > 15 else "") or "none"

    def load_v5(self, names, squeeze: bool):
        import scipy.io as sio

        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                return sio.loadmat(
                    str(self.path),
                    squeeze_me=squeeze,
                    struct_as_record=False,
                    variable_names=list(names),
                    verify_compressed_data_integrity=True,
                )
        except QSMFormatError:
            raise
        except Exception as exc:
            raise _corrupt(self.path, self.kind, exc) from None

    def array(self, name: str):
        """A numeric/char variable in MATLAB orientation (HDF5 arrays transposed)."""
        if self.kind == "v5":
            return self.load_v5([name], squeeze=False)[name]
        return h5_value(self._h5, self._h5[name])

    def arrays(self, names):
        names = [n for n in names if n in self.variables]
        if self.kind == "v5":
            m = self.load_v5(names, squeeze=False)
            return {n: m[n] for n in names if n in m}
        return {n: h5_value(self._h5, self._h5[n]) for n in names}

    def numeric_14(self):
        """Names of numeric variables with 14 columns."""
        out = []
        for name, (shape, cls) in self.variables.items():
            if cls in NON_NUMERIC or len(shape) != 2 or shape[0] < 1:
                continue
            if shape[1] == 14:
                out.append(name)
        return sorted(out)


def _attr(obj, key):
    try:
        return obj.attrs.get(key)
    except Exception:
        return None


def _attr_str(obj, key) -> str:
    v = _attr(obj, key)
    if v is None:
        return ""
    if isinstance(v, (bytes, np.bytes_)):
        return bytes(v).decode("latin-1")
    return str(v)


# ------------------------------------------------------------------------------------------
# HDF5 (MAT v7.3) values and structs
# ------------------------------------------------------------------------------------------


def _is_ref_dataset(ds) -> bool:
    import h5py

    return h5py.check_dtype(ref=ds.dtype) is not None


def h5_value(f, obj):
    """A MATLAB value from an HDF5 object: arrays transposed to MATLAB orientation, ``char``
    decoded, structs wrapped in :class:`H5Struct`, cells as object arrays of values."""
    import h5py

    if isinstance(obj, h5py.Group):
        return H5Struct(f, obj)
    if _attr(obj, "MATLAB_empty"):
        return np.zeros((0, 0))
    cls = _attr_str(obj, "MATLAB_class")
    if _is_ref_dataset(obj):
        refs = np.asarray(obj[()]).ravel()
        out = np.empty(refs.size, dtype=object)
        for i, r in enumerate(refs):  # cells: a handful of elements, not cylinders
            out[i] = h5_value(f, f[r])
        return out
    data = np.asarray(obj[()])
    if cls == "char":
        return "".join(chr(int(c)) for c in data.T.ravel()[:10000])
    data = data.T
    if cls == "logical":
        data = data.astype(bool)
    return data


class H5Struct:
    """A MATLAB struct stored in HDF5: a group whose members are the fields. In a struct array
    every field is a dataset of object references (one per element); ``index`` picks one."""

    def __init__(self, f, group, index: Optional[int] = None):
        self.f = f
        self.group = group
        self.index = index

    @property
    def _fieldnames(self):
        return [k for k in self.group.keys()]

    def _field_objs(self):
        return [self.group[k] for k in self.group.keys()]

    def is_array(self) -> bool:
        """True for a struct array: every field is a dataset of references (not a cell)."""
        import h5py

        objs = self._field_objs()
        return bool(objs) and all(
            isinstance(o, h5py.Dataset) and _is_ref_dataset(o) and _attr_str(o, "MATLAB_class") != "cell" for o in objs
        )

    def n_elements(self) -> int:
        objs = self._field_objs()
        return int(np.prod(objs[0].shape)) if objs else 0

    def __getattr__(self, name):
        if name.startswith("_") and name != "_fieldnames":
            raise AttributeError(name)
        import h5py

        try:
            obj = self.group[name]
        except KeyError:
            raise AttributeError(name) from None
        if self.index is not None and isinstance(obj, h5py.Dataset) and _is_ref_dataset(obj):
            refs = np.asarray(obj[()]).ravel()
            return h5_value(self.f, self.f[refs[self.index]])
        return h5_value(self.f, obj)


def _fields(obj) -> list[str]:
    return list(getattr(obj, "_fieldnames", []) or [])


def _get(obj, name, default=None):
    if name not in _fields(obj):
        return default
    return getattr(obj, name)


def _is_struct(obj) -> bool:
    return hasattr(obj, "_fieldnames")


def struct_elements(path, f_kind, value, label: str):
    """The reconstructions held by a variable: a scalar struct, a struct array or a cell."""
    if isinstance(value, H5Struct):
        if value.is_array():
            k = value.n_elements()
            return [H5Struct(value.f, value.group, i) for i in range(k)]
        return [value]
    if _is_struct(value):
        return [value]
    if isinstance(value, np.ndarray) and value.dtype == object:
        elems = list(value.ravel())
        for i, e in enumerate(elems):
            if not _is_struct(e):
                raise QSMFormatError(path, f"{label}({i + 1}) is not a struct ({type(e).__name__})")
        return elems
    raise QSMFormatError(
        path,
        f"variable '{label}' is not a struct (found {type(value).__name__}"
        f"{' ' + str(value.dtype) if hasattr(value, 'dtype') else ''})",
    )


# ------------------------------------------------------------------------------------------
# detection (docs/qsm-formats.md §8, .mat)
# ------------------------------------------------------------------------------------------


@dataclass
class MatDetection:
    reader: Optional[str]
    error: Optional[str] = None


def detect_mat(path: Path, head: bytes) -> MatDetection:
    kind = mat_kind(head)
    if kind is None:
        return MatDetection(None, describe_non_mat(head))
    try:
        with MatFile(path, kind) as mf:
            v = mf.variables
            if any(s in v for s in STRUCT_NAMES):
                return MatDetection("treeqsm-mat")
            if all(s in v for s in FLAT_NAMES):
                return MatDetection("treeqsm-flat")
            if mf.numeric_14():
                return MatDetection("cyldata-mat")
            return MatDetection(None, f"no QSM variables found (present: {mf.present()})")
    except QSMFormatError as exc:
        return MatDetection(None, exc.problem)


# ------------------------------------------------------------------------------------------
# readers
# ------------------------------------------------------------------------------------------


class _MatReader(BaseReader):
    suffixes = (".mat",)
    container = "MAT reader"

    @sniff_safely
    def sniff(self, path, head):
        return detect_mat(Path(path), head).reader == self.name

    def _open(self, path: Path) -> MatFile:
        with open(path, "rb") as fh:
            head = fh.read(4096)
        if not head:
            raise QSMFormatError(path, "file is empty")
        kind = mat_kind(head)
        if kind is None:
            raise QSMFormatError(path, describe_non_mat(head))
        self.container = _container_name(kind)
        return MatFile(path, kind)

    def _wrong_layout(self, path, mf: MatFile, wanted: str):
        with open(path, "rb") as fh:
            det = detect_mat(path, fh.read(4096))
        if det.error:
            raise QSMFormatError(path, det.error)
        hint = f"; it looks like reader '{det.reader}'" if det.reader and det.reader != self.name else ""
        raise QSMFormatError(path, f"no {wanted} found (present: {mf.present()}){hint}")


class StructSettings(ReaderSettings):
    #: read this variable instead of the first of qsm, QSM, OptQSM, QSMs
    variable: Optional[str] = None


class TreeQSMMatReader(_MatReader):
    """TreeQSM 2.3/2.4 structs ``qsm``, ``QSM``, ``OptQSM`` and ``QSMs`` (docs/qsm-formats.md §1), in MAT v5
    or v7.3 (HDF5) files.

    ``select`` picks reconstructions of a ``QSMs`` struct array or cell (0-based int, list,
    ``"all"``); without it the first is used (with a warning when there are several).
    """

    name = "treeqsm-mat"
    summary = "TreeQSM 2.3/2.4 .mat structs qsm/QSM/OptQSM/QSMs (MAT v5 and v7.3)"
    Settings = StructSettings
    priority = 30

    @sniff_safely
    def sniff(self, path, head):
        det = detect_mat(Path(path), head)
        # also claims unreadable .mat files so that read() reports the precise problem
        return det.reader == self.name or det.error is not None

    def _read(self, path, opts):
        with self._open(path) as mf:
            if opts.variable is not None:
                if opts.variable not in mf.variables:
                    raise QSMFormatError(path, f"variable '{opts.variable}' not found (present: {mf.present()})")
                var = opts.variable
            else:
                var = next((s for s in STRUCT_NAMES if s in mf.variables), None)
                if var is None:
                    self._wrong_layout(path, mf, "TreeQSM struct (qsm, QSM, OptQSM or QSMs)")
            if mf.kind == "v5":
                value = mf.load_v5([var], squeeze=True).get(var)
                if value is None:
                    raise QSMFormatError(path, f"variable '{var}' could not be loaded")
            else:
                value = h5_value(mf._h5, mf._h5[var])
            models = struct_elements(path, mf.kind, value, var)
            idx, as_list, note = select_models(path, models, opts.select, var)
            trees = [self._one(path, mf, var, models[i], i, len(models), note, opts) for i in idx]
        return trees if as_list else trees[0]

    def _one(self, path, mf, var, q, index, k, note, opts):
        label = var if k == 1 else f"{var}({index + 1})"
        cyl = _get(q, "cylinder")
        if cyl is None or not _is_struct(cyl):
            raise QSMFormatError(
                path, f"'{label}' has no struct field 'cylinder' (fields: {', '.join(_fields(q)) or 'none'})"
            )
        raw, has24 = cylinder_struct_to_raw(path, cyl, f"{label}.cylinder")
        version = None
        rd = _get(q, "rundata")
        if rd is not None and _is_struct(rd):
            v = _get(rd, "version")
            if isinstance(v, str) and v.strip():
                version = v.strip()
            elif isinstance(v, np.ndarray) and v.dtype.kind in "US" and v.size:
                version = str(v.ravel()[0]).strip()
        if version is None:
            version = "2.4.x" if has24 else "2.3.x"
        meta = {
            "variable": var,
            "model_index": index,
            "n_models": k,
            "container": "MAT v5" if mf.kind == "v5" else "MAT v7.3 (HDF5)",
        }
        if note:
            meta["select_note"] = note
        return build_tree(path, raw, fmt=self.name, version=version, opts=opts, metadata=meta)


def cylinder_struct_to_raw(path, cyl, label: str):
    """The TreeQSM ``cylinder`` struct (fields of §1) as :class:`RawCylinders`."""
    fields = _fields(cyl)

    def need(name):
        if name not in fields:
            raise QSMFormatError(path, f"'{label}' has no field '{name}' (fields: {', '.join(fields) or 'none'})")
        return getattr(cyl, name)

    radius = float_column(path, f"{label}.radius", need("radius"))
    n = radius.shape[0]
    length = float_column(path, f"{label}.length", need("length"), n)
    start = float_column(path, f"{label}.start", need("start"), n, 3)
    axis = float_column(path, f"{label}.axis", need("axis"), n, 3)
    parent = ids_to_rows(path, f"{label}.parent", need("parent"), n, 1, what="parent")
    extension = (
        ids_to_rows(path, f"{label}.extension", cyl.extension, n, 1, what="extension")
        if "extension" in fields
        else None
    )
    added = None
    if "added" in fields:
        added = float_column(path, f"{label}.added", cyl.added, n)  # NaN is refused in build_tree, not taken for True
    branch = labels_to_int(path, f"{label}.branch", cyl.branch, n) if "branch" in fields else None
    order = labels_to_int(path, f"{label}.BranchOrder", cyl.BranchOrder, n) if "BranchOrder" in fields else None
    used = set(STRUCT_FIELDS) - set(POINT_FIELDS)  # the point-derived fields stay as extras
    extras = {}
    for name in fields:
        if name in used:
            continue
        try:
            v = np.atleast_1d(np.asarray(getattr(cyl, name)))
        except Exception:
            continue
        if v.ndim == 2 and v.shape == (1, n):
            v = v[0]
        elif v.ndim == 2 and v.shape == (n, 1):
            v = v[:, 0]
        if v.dtype.kind in "iufb" and v.shape == (n,):
            extras[name] = v.astype(np.float64)
    has24 = "SurfCov" in fields or "mad" in fields
    return RawCylinders(radius, length, start, axis, parent, extension, added, branch, order, extras), has24


class TreeQSMFlatReader(_MatReader):
    """Flat cylinder variables ``Rad``, ``Len``, ``Sta``, ``Axe``, ``CPar``, ``CExt``, ``BoC``,
    ``Added``: TreeQSM 2.0 (``BoC`` n x 3, docs/qsm-formats.md §2) and the older layout with ``BoC`` = branch
    index and ``BOrd`` per branch (the Ruotsinkylä pines, MAT v7.3, docs/qsm-formats.md §3)."""

    name = "treeqsm-flat"
    summary = "TreeQSM 2.0 and older flat variables Rad/Len/Sta/Axe/CPar/CExt/BoC (MAT v5 and v7.3)"
    priority = 20

    def _read(self, path, opts):
        with self._open(path) as mf:
            if not all(s in mf.variables for s in FLAT_NAMES):
                self._wrong_layout(path, mf, "flat cylinder variables (Rad, Len, Sta, Axe, CPar)")
            want = ["Rad", "Len", "Sta", "Axe", "CPar", "CExt", "BoC", "Added", "BOrd", "out_fn"]
            a = mf.arrays(want)
            kind = mf.kind
        _, as_list, _ = select_models(path, [0], opts.select, "file")
        radius = float_column(path, "Rad", a["Rad"])
        n = radius.shape[0]
        length = float_column(path, "Len", a["Len"], n)
        start = float_column(path, "Sta", a["Sta"], n, 3)
        axis = float_column(path, "Axe", a["Axe"], n, 3)
        parent = ids_to_rows(path, "CPar", a["CPar"], n, 1, what="parent (CPar)")
        extension = ids_to_rows(path, "CExt", a["CExt"], n, 1, what="extension (CExt)") if "CExt" in a else None
        added = float_column(path, "Added", a["Added"], n) if "Added" in a else None  # 0/1; NaN refused later
        branch = order = None
        meta = {"container": "MAT v5" if kind == "v5" else "MAT v7.3 (HDF5)", "model_index": 0, "n_models": 1}
        version = None
        fmt_layout = "old-flat"
        if "BoC" in a:
            boc = np.asarray(a["BoC"])
            if boc.ndim == 2 and boc.shape == (n, 3) and not (n == 1 and "BOrd" in a):
                fmt_layout = "treeqsm-2.0"
                version = "2.0"
                branch = labels_to_int(path, "BoC(:,1)", boc[:, 0], n)
                order = labels_to_int(path, "BoC(:,2)", boc[:, 1], n)
            elif boc.size == n:
                branch = labels_to_int(path, "BoC", boc, n)
                if "BOrd" in a:
                    bord = labels_to_int(path, "BOrd", np.asarray(a["BOrd"]).ravel(), np.asarray(a["BOrd"]).size)
                    bad = np.flatnonzero((branch < 1) | (branch > bord.size))
                    if bad.size:
                        raise QSMFormatError(
                            path,
                            f"BoC {branch[bad[0]]} at row {bad[0] + 1} is outside "
                            f"1...{bord.size} (BOrd has {bord.size} branches)",
                            bad + 1,
                        )
                    order = bord[branch - 1]
            else:
                raise QSMFormatError(
                    path, f"'BoC' has shape {boc.shape}; expected {n}x3 (TreeQSM 2.0) or {n} values (branch index)"
                )
        if "out_fn" in a and isinstance(a["out_fn"], str):
            meta["out_fn"] = a["out_fn"]
        meta["layout"] = fmt_layout
        raw = RawCylinders(radius, length, start, axis, parent, extension, added, branch, order)
        tree = build_tree(path, raw, fmt=self.name, version=version, opts=opts, metadata=meta)
        return [tree] if as_list else tree


class CylDataSettings(ReaderSettings):
    #: name of the n x 14 variable when the file holds several
    variable: Optional[str] = None


class CylDataMatReader(_MatReader):
    """One n x 14 ``CylData`` matrix in a MAT-file (docs/qsm-formats.md §4; the Wytham files hold
    ``CylData_updated``): radius, length, start, axis, parent, extension, branch, order,
    position, added (1-based ids, 0 = none)."""

    name = "cyldata-mat"
    summary = "14-column CylData matrix in a .mat file (TreeQSM <= 2.2 layout)"
    Settings = CylDataSettings
    priority = 10

    def _read(self, path, opts):
        with self._open(path) as mf:
            if opts.variable is not None:
                if opts.variable not in mf.variables:
                    raise QSMFormatError(path, f"variable '{opts.variable}' not found (present: {mf.present()})")
                var = opts.variable
            else:
                cands = mf.numeric_14()
                if not cands:
                    self._wrong_layout(path, mf, "n x 14 numeric matrix")
                if len(cands) > 1:
                    raise QSMFormatError(
                        path, f"several n x 14 matrices ({', '.join(cands)}); pass variable=... to choose one"
                    )
                var = cands[0]
            data = np.asarray(mf.array(var))
        if data.dtype.kind not in "iufb" or data.ndim != 2 or data.shape[1] != 14:
            raise QSMFormatError(
                path, f"variable '{var}' has shape {data.shape} ({data.dtype}); expected n x 14 numbers"
            )
        _, as_list, _ = select_models(path, [0], opts.select, var)
        raw = table_to_raw(path, data, "cyldata14", var)
        meta = {
            "variable": var,
            "container": "MAT v5" if mf.kind == "v5" else "MAT v7.3 (HDF5)",
            "model_index": 0,
            "n_models": 1,
        }
        tree = build_tree(path, raw, fmt=self.name, version=None, opts=opts, metadata=meta)
        return [tree] if as_list else tree
