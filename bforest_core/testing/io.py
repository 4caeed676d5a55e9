"""Conformance checks of QSM readers and writers."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..tree import Tree
from ._base import (
    Check,
    Report,
    _common_checks,
    _instance,
    _label,
    _need,
    _priority_check,
    _require,
    _roundtrip,
    _run,
    _tree_diff,
    check_tree,
)
from .samples import sample_tree


def reader_checks(
    reader,
    paths: Sequence[str | Path],
    *,
    settings=None,
    foreign: Sequence[str | Path] = (),
    options: Mapping[str, Any] | None = None,
    registered: bool | str = False,
) -> list[Check]:
    """The conformance checks of a QSM reader.

    Parameters
    ----------
    reader : QSMReader subclass or instance
    paths : sequence of path
        Sample files in the reader's layout (each must be recognised and read).
    foreign : sequence of path
        Files in other layouts that ``sniff`` must reject.
    options : mapping, optional
        Keyword options passed to ``read``.
    """
    cls, inst, settings, err = _instance(reader, "qsm_reader", settings)
    label = _label(cls, "qsm_reader")
    paths = [Path(p) for p in paths]
    options = dict(options or {})

    def head(p):
        with open(p, "rb") as f:
            return f.read(4096)

    def trees_of(r, p):
        out = r.read(p, **options)
        lst = out if isinstance(out, (list, tuple)) else [out]
        _require(len(lst) > 0, f"read({p.name}) returned no trees")
        for i, t in enumerate(lst):
            check_tree(t, f"tree {i} of {p.name}")
        return lst

    def c_suffixes():
        s = cls.suffixes
        _require(isinstance(s, tuple) and len(s) > 0, f"suffixes is {s!r}, expected a non-empty tuple")
        _require(
            all(isinstance(x, str) and x.startswith(".") and x == x.lower() for x in s),
            f"suffixes must be lower-case strings with the dot: {s!r}",
        )
        bad = [p.name for p in paths if p.suffix.lower() not in s]
        _require(not bad, f"sample files {bad} have suffixes outside {s}")

    def c_sniff():
        r = _need(inst, err)
        for p in paths:
            _require(r.sniff(p, head(p)) is True, f"sniff does not recognise its own sample {p.name}")
        for p in map(Path, foreign):
            _require(not r.sniff(p, head(p)), f"sniff claims the foreign file {p.name}")

    def c_read():
        r = _need(inst, err)
        n = [len(trees_of(r, p)) for p in paths]
        return f"{sum(n)} trees from {len(paths)} files"

    def c_determinism():
        r = _need(inst, err)
        for p in paths:
            a, b = trees_of(r, p), trees_of(r, p)
            for x, y in zip(a, b):
                d = _tree_diff(x, y)
                _require(d is None, f"reading {p.name} twice gave different trees: {d}")

    def c_pickle():
        r = _need(inst, err)
        other = _roundtrip(r)
        for x, y in zip(trees_of(r, paths[0]), trees_of(other, paths[0])):
            d = _tree_diff(x, y)
            _require(d is None, f"the unpickled reader reads {paths[0].name} differently: {d}")

    if not paths:
        raise ValueError("reader_checks needs at least one sample file in `paths`")
    return _common_checks(cls, inst, settings, label, "qsm_reader", registered, err) + [
        Check(label, "suffixes", c_suffixes),
        _priority_check(cls, label),
        Check(label, "sniff", c_sniff),
        Check(label, "read", c_read),
        Check(label, "determinism", c_determinism),
        Check(label, "pickle", c_pickle),
    ]


def check_reader(reader, paths, *, raise_on_failure: bool = True, **options) -> Report:
    """Run :func:`reader_checks`; raises :class:`ConformanceError` on failures."""
    checks = reader_checks(reader, paths, **options)
    return _run(checks, checks[0].component, raise_on_failure)


def writer_checks(
    writer,
    out_dir: str | Path,
    tree: Tree | None = None,
    *,
    settings=None,
    roundtrip: bool = False,
    atol: float = 1e-6,
    registered: bool | str = False,
) -> list[Check]:
    """The conformance checks of a QSM writer.

    Parameters
    ----------
    writer : QSMWriter subclass or instance
    out_dir : path
        A writable (temporary) folder.
    tree : Tree, optional
        The tree to write (default :func:`sample_tree`).
    roundtrip : bool
        Read the written file back with :func:`bforest_core.read_qsm` and compare (geometry
        within ``atol``, same parent links).
    """
    cls, inst, settings, err = _instance(writer, "qsm_writer", settings)
    label = _label(cls, "qsm_writer")
    tree = tree if tree is not None else sample_tree()
    out_dir = Path(out_dir)

    def c_write():
        w = _need(inst, err)
        _require(isinstance(cls.suffixes, tuple) and cls.suffixes, f"suffixes is {cls.suffixes!r}")
        path = out_dir / f"conformance_{cls.name}{cls.suffixes[0]}"
        out = w.write(tree, path)
        _require(
            out is not None and Path(out).exists() and Path(out).stat().st_size > 0,
            f"write returned {out!r}, which is not a non-empty file",
        )
        if roundtrip:
            from ..io import read_qsm

            back = read_qsm(out)
            back = back[0] if isinstance(back, (list, tuple)) else back
            _require(back.n == tree.n, f"read back {back.n} cylinders of {tree.n}")
            _require(np.array_equal(back.parent, tree.parent), "parent links changed through write + read")
            for k in ("start", "axis", "length", "radius"):
                diff = float(np.max(np.abs(getattr(back, k) - getattr(tree, k))))
                _require(diff <= atol, f"'{k}' changed by up to {diff:g} through write + read (atol {atol})")
        return f"wrote {Path(out).name} ({Path(out).stat().st_size} bytes)"

    def c_pickle():
        _roundtrip(_need(inst, err))

    return _common_checks(cls, inst, settings, label, "qsm_writer", registered, err) + [
        _priority_check(cls, label),
        Check(label, "write", c_write),
        Check(label, "pickle", c_pickle),
    ]


def check_writer(writer, out_dir, tree=None, *, raise_on_failure: bool = True, **options) -> Report:
    """Run :func:`writer_checks`; raises :class:`ConformanceError` on failures."""
    checks = writer_checks(writer, out_dir, tree, **options)
    return _run(checks, checks[0].component, raise_on_failure)
