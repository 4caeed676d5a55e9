"""The raw cylinder table every QSM reader makes, and how it becomes a Tree.

Option handling, id conversion, validation, repairs, Tree building (kernel: readers of every
plugin share it). Every reader turns its file into a :class:`RawCylinders` table (file row order, 0-based ids,
-1 = none) and hands it to :func:`build_tree`, which applies the rules of
docs/qsm-formats.md §0 in one place: always-errors (non-finite values, negative
radii, zero axes, cycles, out-of-range ids, extensions that are not children: the checks of
:class:`~bforest_core.tree.Tree`, which ``bforest_core.tree`` holds once), the default
repairs (detached fragments, zero-length cylinders) with one warning each, axis
renormalisation, the check of the stored branch/order against the recomputed ones, and the
topology rule. Writers share :func:`resolve_options` with the readers. Everything is vectorised; Python loops only run over repaired *chains* (a handful
of iterations) or in error paths.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Optional, Union

import numpy as np
from pydantic import ValidationError

from .errors import ConfigError, QSMFormatError, QSMReadWarning, TreeError
from .interfaces import ComponentSettings, QSMReader, QSMWriter
from .tree import (
    MAX_ROWS_SHOWN,
    Tree,
    components,
    cycle_problems,
    extension_problems,
    id_problems,
    remap_ids,
    rows_text,
    value_problems,
)

#: a deviation of the axis norm from 1 above this is reported (docs/qsm-formats.md §0)
AXIS_WARN_TOL = 1e-3


class Repair(dict):
    """One repair done while reading.

    A dict with ``repair``, counts, 1-based rows and ``message``; ``str()`` gives the message, so
    it prints well in ``bforest info``.
    """

    def __str__(self) -> str:
        """Return the repair's message."""
        return str(self.get("message", dict.__repr__(self)))


def plural(k: int, word: str, many: str | None = None) -> str:
    """Count a word: ``plural(2, "axis", "axes")`` -> ``"2 axes"``.

    Parameters
    ----------
    k : int
        The count.
    word : str
        The singular.
    many : str, optional
        The plural (default: ``word + "s"``).

    Returns
    -------
    str
        ``"{k} {word}"`` in the number ``k`` asks for.
    """
    return f"{k} {word if k == 1 else (many or word + 's')}"


def _caller_level() -> int:
    """Return the stack level of the user's call.

    That is the first frame outside the core and the bundled plugins (``bforest_*``: the reader's
    own modules).
    """
    import sys

    level, f = 1, sys._getframe(1)
    while f is not None:
        name = f.f_globals.get("__name__", "")
        if not name.startswith("bforest_"):
            return level
        f = f.f_back
        level += 1
    return 2


def warn(path, message: str) -> None:
    """Issue one user-facing warning naming the file (attributed to the caller's line).

    Parameters
    ----------
    path : str or Path
        The file.
    message : str
        What happened.

    Warns
    -----
    QSMReadWarning
        Always.
    """
    warnings.warn(f"{path}: {message}", QSMReadWarning, stacklevel=_caller_level())


# ------------------------------------------------------------------------------------------
# options
# ------------------------------------------------------------------------------------------


class ReaderSettings(ComponentSettings):
    """Options every QSM reader accepts (``bf.read_qsm(path, **options)``).

    Attributes
    ----------
    select : int, list of int, "all" or None
        Reconstruction(s) to read from a file holding several (``QSMs``); 0-based.
        ``None`` takes the first with a warning.
    topology : {"source", "subtree", "thickest"} or None
        Topology rule (docs/features-and-distance.md §1.1). ``None`` means ``"source"``, except for
        the native CSV, where it means the rule recorded in its JSON sidecar.
    fragments : {"drop", "error"}
        Detached parts (extra parentless cylinders): drop them with a warning, or raise.
    drop_degenerate : bool
        Remove zero-length cylinders (children reattached) with a warning; ``False`` raises.
    """

    select: Union[None, Literal["all"], int, list[int]] = None
    topology: Optional[Literal["source", "subtree", "thickest"]] = None
    fragments: Literal["drop", "error"] = "drop"
    drop_degenerate: bool = True


def resolve_options(component: QSMReader | QSMWriter, options: dict) -> ComponentSettings:
    """Merge per-call options into a reader's or writer's settings.

    Parameters
    ----------
    component : QSMReader or QSMWriter
        The reader or writer.
    options : dict
        The per-call options.

    Returns
    -------
    ComponentSettings
        The component's settings updated by ``options``.

    Raises
    ------
    ConfigError
        For unknown or invalid options, naming them (``qsm_reader 'treeqsm-text': invalid
        option(s): ...``).
    """
    try:
        return component.Settings(**{**component.settings.model_dump(), **options})
    except ValidationError as exc:
        parts = []
        for e in exc.errors():
            loc = ".".join(str(x) for x in e.get("loc", ()))
            parts.append(f"{loc}: {e.get('msg')}")
        raise ConfigError(f"{component.kind} '{component.name}': invalid option(s): " + "; ".join(parts)) from None


def select_models(path, models: list, select, label: str):
    """Apply ``select`` to the list of reconstructions of one file.

    Parameters
    ----------
    path : str or Path
        The file (for messages).
    models : list
        The reconstructions the file holds.
    select : int, list of int, "all" or None
        The ``select`` option (0-based; ``None`` takes the first, with a warning when there are
        several).
    label : str
        What holds the reconstructions, for messages (the MATLAB variable, or "file").

    Returns
    -------
    indices : list of int
        Reconstructions to read.
    as_list : bool
        Whether the caller gets a list.
    note : str or None
        A metadata note.

    Raises
    ------
    QSMFormatError
        For a file with no reconstructions or a selection out of range.
    """
    k = len(models)
    if k == 0:
        raise QSMFormatError(path, f"{label} holds no reconstructions (empty struct array)")
    if select is None:
        if k > 1:
            note = f"holds {k} reconstructions ({label} 1x{k}); using select=0 (choose 0...{k - 1} or 'all')"
            warn(path, note)
            return [0], False, note
        return [0], False, None
    if isinstance(select, str):  # "all"
        return list(range(k)), True, None
    as_list = isinstance(select, list)
    idx = list(select) if as_list else [select]
    bad = [i for i in idx if not (0 <= i < k)]
    if bad:
        raise QSMFormatError(
            path,
            f"select={bad[0]} is outside 0...{k - 1}: the file holds {k} "
            f"reconstruction{'s' if k > 1 else ''} ({label} 1x{k}; "
            f"MATLAB {label}({bad[0] + 1}))",
        )
    return idx, as_list, None


# ------------------------------------------------------------------------------------------
# id conversion
# ------------------------------------------------------------------------------------------


def ids_to_rows(path, name: str, values, n: int, base: int = 1, *, what: str | None = None) -> np.ndarray:
    """Convert file ids (``base``-based, ``base - 1`` = none) to 0-based rows (-1 = none).

    The values are cast to int64 **before** the subtraction (TreeQSM stores ids as uint8/uint16,
    where ``0 - 1`` wraps around).

    Parameters
    ----------
    path : str or Path
        The file (for messages).
    name : str
        The column's name (for messages).
    values : array_like
        The ids, one per cylinder.
    n : int
        Number of cylinders.
    base : int, optional
        The id of the first row (1 for MATLAB files).
    what : str, optional
        What the ids are called in messages (default: ``name``).

    Returns
    -------
    ndarray of int64, shape (n,)
        The rows.

    Raises
    ------
    QSMFormatError
        For non-finite, non-integral and out-of-range values, naming the column, the 1-based
        rows and the values.
    """
    v = np.asarray(values).reshape(-1)
    what = what or name
    if v.shape[0] != n:
        raise QSMFormatError(path, f"'{name}' has {v.shape[0]} values, expected {n} (one per cylinder)")
    if v.dtype.kind == "b":
        v = v.astype(np.int64)
    if v.dtype.kind not in "iuf":
        raise QSMFormatError(path, f"'{name}' is not numeric (dtype {v.dtype})")
    if v.dtype.kind == "f":
        bad = np.flatnonzero(~np.isfinite(v))
        if bad.size:
            raise QSMFormatError(path, f"non-finite values in '{name}' at rows {rows_text(bad + 1)}", bad + 1)
        bad = np.flatnonzero(v != np.round(v))
        if bad.size:
            raise QSMFormatError(
                path, f"'{name}' holds non-integer values at rows {rows_text(bad + 1)} (value {v[bad[0]]:g})", bad + 1
            )
        lo, hi = base - 1, n - 1 + base
        bad = np.flatnonzero((v < lo) | (v > hi))
        if bad.size:
            raise QSMFormatError(path, _range_msg(what, v, bad, n, base), bad + 1)
        return v.astype(np.int64) - base
    out = v.astype(np.int64)  # uint8/uint16 -> int64 first
    bad = np.flatnonzero((out < base - 1) | (out > n - 1 + base))
    if bad.size:
        raise QSMFormatError(path, _range_msg(what, out, bad, n, base), bad + 1)
    return out - base


def _range_msg(name, v, bad, n, base):
    i = int(bad[0])
    val = v[i]
    val = int(val) if float(val).is_integer() else float(val)
    lo, hi = base, n - 1 + base
    more = f" ({len(bad)} rows: {rows_text(bad + 1)})" if len(bad) > 1 else ""
    return f"{name} {val} at row {i + 1} is outside {lo}...{hi} ({base - 1} = none){more}"


def labels_to_int(path, name: str, values, n: int) -> np.ndarray:
    """Convert integral labels (branch ids, orders) to int64.

    Parameters
    ----------
    path : str or Path
        The file (for messages).
    name : str
        The column's name.
    values : array_like
        The labels, one per cylinder.
    n : int
        Number of cylinders.

    Returns
    -------
    ndarray of int64, shape (n,)
        The labels.

    Raises
    ------
    QSMFormatError
        For a wrong count or non-finite/non-integer values.
    """
    v = np.asarray(values).reshape(-1)
    if v.shape[0] != n:
        raise QSMFormatError(path, f"'{name}' has {v.shape[0]} values, expected {n} (one per cylinder)")
    if v.dtype.kind == "b":
        return v.astype(np.int64)
    if v.dtype.kind not in "iuf":
        raise QSMFormatError(path, f"'{name}' is not numeric (dtype {v.dtype})")
    if v.dtype.kind == "f":
        bad = np.flatnonzero(~np.isfinite(v) | (np.abs(v) > 2.0**53))
        if bad.size:
            raise QSMFormatError(path, f"non-finite or huge values in '{name}' at rows {rows_text(bad + 1)}", bad + 1)
        bad = np.flatnonzero(v != np.round(v))
        if bad.size:
            raise QSMFormatError(
                path, f"'{name}' holds non-integer values at rows {rows_text(bad + 1)} (value {v[bad[0]]:g})", bad + 1
            )
    return v.astype(np.int64)


def float_column(path, name: str, values, n: int | None = None, width: int | None = None) -> np.ndarray:
    """Convert a numeric column to float64 of shape ``(n,)`` or ``(n, width)``.

    Takes MATLAB vectors of any orientation and ``squeeze_me`` scalars for one-cylinder trees.

    Parameters
    ----------
    path : str or Path
        The file (for messages).
    name : str
        The column's name.
    values : array_like
        The values.
    n : int, optional
        Number of cylinders (checked when given; inferred for a ``width``-wide column).
    width : int, optional
        Columns per cylinder (3 for points and axes); ``None`` for a vector.

    Returns
    -------
    ndarray of float64
        Shape ``(n,)`` or ``(n, width)``, C-contiguous.

    Raises
    ------
    QSMFormatError
        For non-numeric values or a wrong count.
    """
    a = np.asarray(values)
    if a.dtype.kind not in "iufb":
        raise QSMFormatError(path, f"'{name}' is not numeric (dtype {a.dtype})")
    a = np.atleast_1d(a).astype(np.float64)
    if width is None:
        a = a.reshape(-1)
        if n is not None and a.shape[0] != n:
            raise QSMFormatError(path, f"'{name}' has {a.shape[0]} values, expected {n} (one per cylinder)")
        return a
    if n is None:
        n = a.size // width
    if a.size != n * width:
        raise QSMFormatError(path, f"'{name}' has {a.size} values, expected {n}x{width}")
    if a.ndim == 2 and a.shape == (width, n) and n != width:
        a = a.T  # stored transposed
    return np.ascontiguousarray(a.reshape(n, width))


# ------------------------------------------------------------------------------------------
# the raw table and the Tree builder
# ------------------------------------------------------------------------------------------


@dataclass
class RawCylinders:
    """Cylinder columns in file row order (0-based ids, -1 = none), before validation.

    Parameters
    ----------
    radius, length : ndarray, shape (n,)
        Radii and lengths (m).
    start, axis : ndarray, shape (n, 3)
        Start points (m) and axis directions.
    parent : ndarray of int, shape (n,)
        Parent row, -1 for a root.
    extension : ndarray of int, optional
        Extension (the child continuing the branch) row, -1 for none; ``None`` means "no
        extension information".
    added : ndarray of bool, optional
        TreeQSM's flag of cylinders added to fill gaps.
    branch, order : ndarray of int, optional
        The file's stored labels (any integer ids), used only to check against the recomputed
        topology.
    extras : dict, optional
        Further per-cylinder columns, kept on the tree.
    """

    radius: np.ndarray
    length: np.ndarray
    start: np.ndarray
    axis: np.ndarray
    parent: np.ndarray
    extension: Optional[np.ndarray] = None
    added: Optional[np.ndarray] = None
    branch: Optional[np.ndarray] = None
    order: Optional[np.ndarray] = None
    extras: dict = field(default_factory=dict)

    @property
    def n(self) -> int:
        """Number of cylinders."""
        return int(np.asarray(self.length).shape[0])


def _resolve_through(mask: np.ndarray, link: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Follow ``link`` from ``values`` while the target is in ``mask``.

    Pointer chasing over the removed rows only; iterations = longest chain of removed rows.
    """
    out = values.copy()
    while True:
        hit = (out >= 0) & mask[np.maximum(out, 0)]
        if not hit.any():
            return out
        out[hit] = link[out[hit]]


def build_tree(
    path,
    raw: RawCylinders,
    *,
    fmt: str,
    version=None,
    opts=None,
    metadata=None,
    zero_length_hint: str = "",
    default_topology: str = "source",
) -> Tree:
    """Validate and repair a raw cylinder table and build the :class:`Tree` (docs/qsm-formats.md §0).

    The phases, in order: the columns as arrays; the always-errors on values and on ids (the
    checks :class:`Tree` makes, shared with it: :func:`~bforest_core.tree.value_problems`,
    :func:`~bforest_core.tree.id_problems`, :func:`~bforest_core.tree.extension_problems`,
    :func:`~bforest_core.tree.cycle_problems`, here on the whole file before any repair and
    naming 1-based file rows); the repairs (detached
    fragments, zero-length cylinders, axes); the Tree; the comparison of the file's stored
    branches and orders with the recomputed ones; the plausibility of the units.

    Parameters
    ----------
    path : Path
        For messages and metadata.
    raw : RawCylinders
        Columns in file order with 0-based ids.
    fmt, version : str
        Format name and version for the metadata.
    opts : ReaderSettings
        ``topology``, ``fragments``, ``drop_degenerate``.
    metadata : dict, optional
        Extra metadata (variable, model index, notes).
    zero_length_hint : str
        Appended to the zero-length message (e.g. the TreeQSM text rounding).
    default_topology : str
        The topology rule when ``opts`` sets none.

    Raises
    ------
    QSMFormatError
        For every always-error condition, and for repairs when the strict options are set.

    Returns
    -------
    Tree
        The validated tree, with ``metadata`` on format, source and repairs.
    """
    topology = getattr(opts, "topology", None) or default_topology
    n = raw.n
    if n == 0:
        raise QSMFormatError(path, "file contains no cylinders")
    radius, length, start, axis, parent, extension, added = _columns(path, raw)
    _check_values(path, start, axis, length, radius)
    _check_ids(path, parent, extension)
    repairs: list[dict] = []
    norms = np.sqrt(np.einsum("ij,ij->i", axis, axis))

    keep = _drop_fragments(path, parent, start, getattr(opts, "fragments", "drop"), repairs)
    parent, extension, keep = _drop_zero_length(
        path,
        parent,
        extension,
        (length == 0) & keep,
        keep,
        getattr(opts, "drop_degenerate", True),
        zero_length_hint,
        repairs,
    )
    file_rows = np.flatnonzero(keep)
    if file_rows.size < n:
        new = np.full(n, -1, dtype=np.int64)
        new[file_rows] = np.arange(file_rows.size)
        radius, length, start, axis, added, norms = (
            radius[file_rows],
            length[file_rows],
            start[file_rows],
            axis[file_rows],
            added[file_rows],
            norms[file_rows],
        )
        parent = remap_ids(parent[file_rows], new)
        extension = remap_ids(extension[file_rows], new)
    axis = _renormalised_axes(path, axis, norms, file_rows, repairs)
    extras = {}
    for k, v in (raw.extras or {}).items():
        v = np.asarray(v)
        if v.shape[:1] == (n,):
            extras[k] = v[file_rows]
    _check_sizes(path, start, axis, length, radius, file_rows)

    meta = {"source": str(path), "format": fmt, "version": version, "units": "m", "n_file_rows": n, "repairs": repairs}
    meta.update(metadata or {})
    try:
        tree = Tree(
            start,
            axis,
            length,
            radius,
            parent,
            extension,
            topology="source",
            added=added,
            source_row=file_rows,
            extras=extras,
            metadata=meta,
        )
    except TreeError as exc:
        rows_ = [int(file_rows[r]) + 1 for r in exc.rows if 0 <= r < file_rows.size]
        raise QSMFormatError(path, f"invalid cylinder tree: {exc.problem}", rows_) from None
    _compare_stored_topology(path, tree, raw, file_rows)
    _check_units(path, tree)
    if topology != "source":
        tree = tree.with_topology(topology)
    return tree


def _columns(path, raw: RawCylinders):
    """Return the raw columns as float64/int64/bool arrays of one length.

    For ``added``, NaN is an error, not True.
    """
    n = raw.n
    radius = np.asarray(raw.radius, dtype=np.float64).reshape(-1)
    length = np.asarray(raw.length, dtype=np.float64).reshape(-1)
    start = np.asarray(raw.start, dtype=np.float64).reshape(n, 3)
    axis = np.asarray(raw.axis, dtype=np.float64).reshape(n, 3)
    parent = np.asarray(raw.parent, dtype=np.int64).reshape(-1)
    extension = (
        np.full(n, -1, dtype=np.int64)
        if raw.extension is None
        else np.asarray(raw.extension, dtype=np.int64).reshape(-1)
    )
    added = np.zeros(n, dtype=bool) if raw.added is None else np.asarray(raw.added).reshape(-1)
    if added.dtype.kind == "f" and not np.all(np.isfinite(added)):
        bad = np.flatnonzero(~np.isfinite(added))
        raise QSMFormatError(path, f"non-finite values in 'added' at rows {rows_text(bad + 1)}", bad + 1)
    added = added != 0
    for name, a in (("radius", radius), ("parent", parent), ("extension", extension), ("added", added)):
        if a.shape[0] != n:
            raise QSMFormatError(path, f"'{name}' has {a.shape[0]} values, expected {n} (one per cylinder)")
    return radius, length, start, axis, parent, extension, added


def _check_values(path, start, axis, length, radius) -> None:
    """Raise the always-errors on values (non-finite, radius <= 0, length < 0, zero axis).

    All are reported together with the first rows of each; zero lengths are repaired later.
    """
    problems = value_problems(start, axis, length, radius, zero_length_ok=True, row_base=1)
    if problems:
        rows = np.concatenate([r[:MAX_ROWS_SHOWN] + 1 for _, r in problems])
        raise QSMFormatError(path, "; ".join(m for m, _ in problems), rows)


def _check_ids(path, parent, extension) -> None:
    """Always-errors on ids: out of range, own parent, extension not a child, cycles."""
    for check in (id_problems, extension_problems):
        for message, rows in check(parent, extension, row_base=1):
            raise QSMFormatError(path, message, rows + 1)
    for message, rows in cycle_problems(parent, row_base=1):
        raise QSMFormatError(path, message, rows + 1)


def _drop_fragments(path, parent, start, fragments: str, repairs: list) -> np.ndarray:
    """Repair 1: return the rows to keep when several cylinders have no parent.

    The connected part with the lowest start (the stem base; ties: the earlier row), with a
    warning (an error with ``fragments="error"``).
    """
    n = parent.shape[0]
    roots = np.flatnonzero(parent < 0)
    if roots.size <= 1:
        return np.ones(n, dtype=bool)
    label, _ = components(parent)
    base = int(roots[np.argmin(start[roots, 2])])  # lowest start z; ties -> earlier row
    sizes = np.bincount(label, minlength=n)
    keep = label == base
    kept = int(keep.sum())
    msg = (
        f"{roots.size} cylinders have no parent (rows {rows_text(roots + 1)}); "
        f"kept the connected part with the stem base ({kept} of {n} cylinders)"
    )
    biggest = int(roots[np.argmax(sizes[roots])])
    if sizes[biggest] > sizes[base]:
        msg += (
            f"; note: the stem base (row {base + 1}, lowest start) is not the root of the "
            f"largest part (row {biggest + 1}, {int(sizes[biggest])} cylinders)"
        )
    if fragments == "error":
        raise QSMFormatError(path, msg + " [fragments='error']", roots + 1)
    warn(path, msg)
    dropped = np.flatnonzero(~keep)
    repairs.append(
        Repair(
            {
                "repair": "dropped_fragments",
                "roots": (roots + 1).tolist(),
                "stem_base_row": base + 1,
                "n_dropped": int(dropped.size),
                "dropped_rows": (dropped + 1).tolist(),
                "message": msg,
            }
        )
    )
    return keep


def _drop_zero_length(path, parent, extension, zero, keep, drop_degenerate: bool, hint: str, repairs: list):
    """Repair 2: remove the kept cylinders of length exactly 0 as read (``zero``).

    Their children are attached to the nearest kept ancestor and a removed extension is replaced
    by its own; a warning (an error with ``drop_degenerate=False`` or for the root). Returns the
    new ``(parent, extension, keep)``.
    """
    zl = np.flatnonzero(zero)
    if not zl.size:
        return parent, extension, keep
    hint = f"; {hint}" if hint else ""
    zrows = rows_text(zl + 1)
    if not drop_degenerate:
        raise QSMFormatError(
            path,
            f"length <= 0 at row{'s' if zl.size > 1 else ''} {zrows} (value 0{hint}) [drop_degenerate=False]",
            zl + 1,
        )
    zroot = zl[parent[zl] < 0]
    if zroot.size:
        raise QSMFormatError(path, f"the root cylinder (row {zroot[0] + 1}) has zero length", zroot + 1)
    removed = np.zeros(parent.shape[0], dtype=bool)
    removed[zl] = True
    # children -> nearest kept ancestor
    parent = _resolve_through(removed, parent, parent)
    # a removed extension is replaced by its own extension (resolved through removed rows)
    ext_new = _resolve_through(removed, extension, extension)
    extension = np.where(removed, -1, ext_new)
    msg = (
        f"removed {plural(zl.size, 'zero-length cylinder')} (row{'s' if zl.size > 1 else ''} "
        f"{zrows}{hint}); children were attached to the parent"
    )
    warn(path, msg)
    repairs.append(
        Repair({"repair": "removed_zero_length", "rows": (zl + 1).tolist(), "n_removed": int(zl.size), "message": msg})
    )
    return parent, extension, keep & ~removed


def _renormalised_axes(path, axis, norms, file_rows, repairs: list) -> np.ndarray:
    """Repair 3: return the axes divided by their norms (float64).

    Norms off 1 by more than :data:`AXIS_WARN_TOL` are reported.
    """
    off = np.flatnonzero(np.abs(norms - 1.0) > AXIS_WARN_TOL)
    if off.size:
        msg = (
            f"{plural(off.size, 'axis', 'axes')} not unit vectors (norms {norms[off].min():.4g}..."
            f"{norms[off].max():.4g}; rows {rows_text(file_rows[off] + 1)}); renormalised"
        )
        warn(path, msg)
        repairs.append(
            Repair(
                {
                    "repair": "renormalised_axes",
                    "n_rows": int(off.size),
                    "rows": (file_rows[off] + 1).tolist(),
                    "message": msg,
                }
            )
        )
    return axis / norms[:, None]


def _check_sizes(path, start, axis, length, radius, file_rows) -> None:
    """Sizes whose volume or end point overflows (radius 1e300) make no tree, in any unit."""
    with np.errstate(over="ignore", invalid="ignore"):
        finite = np.isfinite(np.pi * radius**2 * length) & np.isfinite(start + axis * length[:, None]).all(axis=1)
    if not finite.all():
        bad = file_rows[np.flatnonzero(~finite)] + 1
        raise QSMFormatError(
            path,
            f"cylinder sizes too large to compute with (volume or end point not a finite "
            f"number; largest radius {radius.max():.4g}, length {length.max():.4g}) at rows "
            f"{rows_text(bad)}",
            bad,
        )


def _compare_stored_topology(path, tree: Tree, raw: RawCylinders, file_rows) -> None:
    """Compare the file's stored branch/order with the recomputed ones.

    Under the file's own extension links: a warning and ``metadata["stored_topology_mismatch"]``
    where they differ.
    """
    pos = np.full(raw.n, -1, dtype=np.int64)
    pos[file_rows] = np.arange(file_rows.size)
    at = pos[tree.source_row]  # tree row -> index into the compressed stored arrays
    mism = {}
    if raw.order is not None:
        so = np.asarray(raw.order, dtype=np.int64)[file_rows][at]
        bad = np.flatnonzero(so != tree.order)
        if bad.size:
            mism["order"] = np.sort(tree.source_row[bad] + 1)
    if raw.branch is not None:
        sb = np.asarray(raw.branch, dtype=np.int64)[file_rows][at]
        firsts = tree.branches.first
        lab = sb[firsts]  # stored label of each recomputed branch's first cylinder
        bad = sb != lab[tree.branch]
        # two recomputed branches with the same stored label: flag the later ones
        srt = np.lexsort((firsts, lab))
        dup = np.zeros(firsts.size, dtype=bool)
        dup[srt[1:]] = lab[srt[1:]] == lab[srt[:-1]]
        bad |= dup[tree.branch]
        bad = np.flatnonzero(bad)
        if bad.size:
            mism["branch"] = np.sort(tree.source_row[bad] + 1)
    if mism:
        parts = [
            f"{plural(v.size, 'row')} with a stored {k} that differs from the recomputed one (rows {rows_text(v)})"
            for k, v in mism.items()
        ]
        msg = "; ".join(parts) + " -- the recomputed branches and orders are used"
        warn(path, msg)
        tree.metadata["stored_topology_mismatch"] = {k: v.tolist() for k, v in mism.items()}
        tree.metadata["stored_topology_message"] = msg


def _check_units(path, tree: Tree) -> None:
    """Height and base into the metadata; a warning when the sizes look like millimetres."""
    height = float(max(tree.start[:, 2].max(), tree.end[:, 2].max()) - tree.start[0, 2])
    tree.metadata["height"] = height
    tree.metadata["base"] = tree.start[0].tolist()
    if tree.radius.max() > 5.0 or height > 150.0:
        warn(
            path,
            f"values look like millimetres (largest radius {tree.radius.max():.4g}, height "
            f"{height:.4g}); QSM readers never convert units, metres are expected",
        )


class BaseReader(QSMReader):
    """Base of the bundled readers: a common ``read`` wrapper around the reader's ``_read``.

    It handles the options and converts every low-level exception into
    :class:`QSMFormatError` (readers never leak scipy/h5py/numpy exceptions).
    """

    Settings = ReaderSettings
    priority = 0
    #: what a low-level failure is called in the message
    container = "reader"

    def read(self, path, **options):
        """Read the file with this reader's ``_read(path, opts)``.

        Parameters
        ----------
        path : str or Path
            The file.
        **options
            Per-call options (see :class:`ReaderSettings`).

        Returns
        -------
        Tree or list of Tree
            What ``_read`` returns.

        Raises
        ------
        QSMFormatError
            For a missing file, an invalid cylinder tree or any low-level failure, naming the file.
        ConfigError
            For invalid options.
        """
        path = Path(path)
        opts = resolve_options(self, options)
        if not path.exists():
            raise QSMFormatError(path, "file not found")
        try:
            return self._read(path, opts)
        except (QSMFormatError, ConfigError):
            raise
        except TreeError as exc:
            raise QSMFormatError(path, f"invalid cylinder tree: {exc.problem}", [r + 1 for r in exc.rows]) from None
        except MemoryError:
            raise QSMFormatError(
                path,
                f"file is truncated or corrupt ({self.container}: a size field asks for more memory than available)",
            ) from None
        except (KeyboardInterrupt, SystemExit):
            raise
        except Exception as exc:  # scipy/h5py/struct/zlib/ValueError/IndexError/...
            raise QSMFormatError(
                path, f"file is truncated or corrupt ({self.container}: {type(exc).__name__}: {exc})"
            ) from None

    def _read(self, path: Path, opts):  # pragma: no cover - abstract
        raise NotImplementedError


def sniff_safely(fn):
    """Wrap a sniffer so that it never raises (a broken file just does not match).

    Parameters
    ----------
    fn : callable
        ``fn(self, path, head)``, a reader's ``sniff``.

    Returns
    -------
    callable
        The wrapper, returning a bool (False where ``fn`` raises).
    """

    def wrapper(self, path, head):
        try:
            return bool(fn(self, path, head))
        except Exception:
            return False

    wrapper.__name__ = fn.__name__
    wrapper.__doc__ = fn.__doc__
    return wrapper
