"""Conformance checks of a feature set."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from ..tree import Tree
from ._base import Check, Report, _common_checks, _instance, _label, _need, _require, _roundtrip, _run, _tables_diff
from .samples import sample_trees


# Over 80 lines by design: the nested checks share one prepared instance and its extracted
# tables through the closure; each check on its own is a few lines.
def feature_set_checks(
    features,
    trees: Sequence[Tree] | None = None,
    *,
    settings=None,
    allow_nan: bool = False,
    registered: bool | str = False,
) -> list[Check]:
    """The conformance checks of a feature set.

    Parameters
    ----------
    features : FeatureSet subclass or instance
    trees : sequence of Tree, optional
        Data trees for ``prepare`` and ``extract`` (default :func:`sample_trees`).
    settings : mapping, optional
        Component settings (only with a class).
    allow_nan : bool
        Tables may hold NaN (only for a ``nan_policy`` that keeps them); inf is never allowed.
    registered : bool or str
        See :func:`ssm_checks`.
    """
    cls, inst, settings, err = _instance(features, "features", settings)
    label = _label(cls, "features")
    trees = list(trees) if trees is not None else sample_trees()
    cache: dict[str, Any] = {}

    def prepared():
        if "fs" not in cache:
            fs = _need(inst, err)
            fs.prepare(trees)
            cache["fs"] = fs
        return cache["fs"]

    def c_names():
        fs = prepared()
        names = fs.set_names
        _require(isinstance(names, list) and len(names) > 0, f"set_names is {names!r}, expected a non-empty list")
        _require(all(isinstance(n, str) and n for n in names), f"set names must be non-empty strings: {names!r}")
        _require(len(set(names)) == len(names), f"duplicate set names: {names!r}")
        for n in names:
            cols = fs.columns(n)
            _require(
                isinstance(cols, list) and len(cols) > 0 and all(isinstance(c, str) and c for c in cols),
                f"columns({n!r}) is {cols!r}, expected a non-empty list of strings",
            )
            _require(len(set(cols)) == len(cols), f"columns({n!r}) has duplicates: {cols!r}")
        return ", ".join(f"{n} ({len(fs.columns(n))} columns)" for n in names)

    def c_extract():
        fs = prepared()
        rows = {}
        for i, t in enumerate(trees):
            U = fs.extract(t)
            _require(isinstance(U, dict), f"extract returned a {type(U).__name__}, not a dict")
            _require(list(U) == list(fs.set_names), f"extract gave sets {list(U)}, set_names is {fs.set_names}")
            for k, a in U.items():
                cols = fs.columns(k)
                _require(isinstance(a, np.ndarray), f"set {k!r} is a {type(a).__name__}, not a numpy array")
                _require(a.ndim == 2, f"set {k!r} has shape {a.shape}; tables are 2-D (rows, columns)")
                _require(a.dtype == np.float64, f"set {k!r} has dtype {a.dtype}, expected float64")
                _require(
                    a.shape[1] == len(cols),
                    f"set {k!r} has {a.shape[1]} columns but columns({k!r}) names {len(cols)}: {cols}",
                )
                _require(not np.isinf(a).any(), f"set {k!r} of tree {i} holds inf values")
                if not allow_nan:
                    bad = np.flatnonzero(np.isnan(a).any(axis=1))
                    _require(bad.size == 0, f"set {k!r} of tree {i} holds NaN in rows {bad[:5].tolist()}")
                rows[k] = rows.get(k, 0) + a.shape[0]
        return ", ".join(f"{k}: {v} rows" for k, v in rows.items())

    def c_determinism():
        fs = prepared()
        d = _tables_diff(fs.extract(trees[0]), fs.extract(trees[0]))
        _require(d is None, f"extracting the same tree twice differs: {d}")

    def c_pooled():
        fs = prepared()
        pooled = fs.extract_pooled(trees)
        _require(list(pooled) == list(fs.set_names), f"extract_pooled gave sets {list(pooled)}")
        for k in fs.set_names:
            n = sum(fs.extract(t)[k].shape[0] for t in trees)
            _require(
                pooled[k].shape[0] == n,
                f"extract_pooled set {k!r} has {pooled[k].shape[0]} rows, the trees have {n} together",
            )

    def c_pickle():
        fs = prepared()
        other = _roundtrip(fs)
        d = _tables_diff(fs.extract(trees[0]), other.extract(trees[0]))
        _require(d is None, f"the unpickled (prepared) feature set extracts different tables: {d}")

    return _common_checks(cls, inst, settings, label, "features", registered, err) + [
        Check(label, "set_names", c_names),
        Check(label, "extract", c_extract),
        Check(label, "determinism", c_determinism),
        Check(label, "pooled", c_pooled),
        Check(label, "pickle", c_pickle),
    ]


def check_feature_set(features, trees=None, *, raise_on_failure: bool = True, **options) -> Report:
    """Run :func:`feature_set_checks`; raises :class:`ConformanceError` on failures."""
    checks = feature_set_checks(features, trees, **options)
    return _run(checks, checks[0].component, raise_on_failure)
