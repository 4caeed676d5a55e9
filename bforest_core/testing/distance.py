"""Conformance checks of a distance."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ..interfaces import LineDistance
from ._base import Check, Report, _common_checks, _Fail, _instance, _label, _need, _require, _roundtrip, _run
from .samples import sample_tables


# Over 80 lines by design: the nested checks share one prepared instance and its extracted
# tables through the closure; each check on its own is a few lines.
def distance_checks(
    distance,
    tables=None,
    *,
    settings=None,
    atol: float = 1e-9,
    separates: bool = True,
    empty: bool = True,
    registered: bool | str = False,
) -> list[Check]:
    """The conformance checks of a distance.

    Parameters
    ----------
    distance : Distance subclass or instance
    tables : (U_data, U_model, columns), optional
        Named data and model tables (default :func:`sample_tables`: model shifted by 1).
    atol : float
        Tolerance of "zero for identical inputs".
    separates : bool
        The distance of the (different) data and model tables must be positive.
    empty : bool
        Check that an empty model table gives a finite value or ``None`` (never an exception).
    """
    cls, inst, settings, err = _instance(distance, "distance", settings)
    label = _label(cls, "distance")
    U_data, U_model, cols = tables if tables is not None else sample_tables()
    cache: dict[str, Any] = {}

    def prepared():
        if "d" not in cache:
            d = _need(inst, err)
            d.prepare(U_data, cols)
            cache["d"] = d
        return cache["d"]

    def values(d, U):
        per = d.compute_per_set(U, U_data)
        _require(
            isinstance(per, dict) and set(per) == set(U_data),
            f"compute_per_set returned {per!r}, expected a dict with the sets {sorted(U_data)}",
        )
        for k, v in per.items():
            _require(
                v is None or (isinstance(v, (float, int, np.floating)) and math.isfinite(v) and v >= 0),
                f"set {k!r}: distance {v!r} is not a finite non-negative number",
            )
        return per

    def c_identical():
        d = prepared()
        per = values(d, U_data)
        bad = {k: v for k, v in per.items() if v is None or abs(v) > atol}
        _require(not bad, f"identical model and data tables give non-zero distances {bad} (atol {atol})")
        for k in U_data:
            v = d.compute(U_data[k], U_data[k])
            _require(abs(v) <= atol, f"compute(u, u) of set {k!r} is {v!r}, expected 0")

    def c_finite():
        per = values(prepared(), U_model)
        tot = prepared().combine(per)
        _require(math.isfinite(tot) and tot >= 0, f"combined distance {tot!r} is not finite and non-negative")
        return ", ".join(f"{k}={v:.4g}" for k, v in per.items() if v is not None)

    def c_separates():
        per = values(prepared(), U_model)
        zero = [k for k, v in per.items() if v is None or v <= 0]
        _require(
            not zero,
            f"tables shifted by 1 in every column give distance 0 (or None) for sets {zero} "
            "(pass separates=False if that is intended)",
        )

    def c_determinism():
        d = prepared()
        a, b = values(d, U_model), values(d, U_model)
        _require(a == b, f"the same tables gave different distances: {a} vs {b}")

    def c_empty():
        d = prepared()
        U = {k: np.empty((0, v.shape[1])) for k, v in U_model.items()}
        per = values(d, U)
        return f"empty model tables -> {per}"

    def c_capabilities():
        d = prepared()
        if not isinstance(d, LineDistance):
            return "compares the tables as they are (no projection lines)"
        _require(isinstance(d.statistic, str) and d.statistic, f"statistic is {d.statistic!r}, expected a name")
        norms = d.normalizations()
        _require(
            isinstance(norms, dict) and set(norms) <= set(U_data) and all(isinstance(v, dict) for v in norms.values()),
            f"normalizations() returned {norms!r}, expected a dict of dicts keyed by prepared sets",
        )
        k = next(k for k in U_data if len(U_data[k]) and len(U_model[k]))
        try:
            lines = d.line_values(U_model[k], U_data[k], set_name=k)
        except NotImplementedError:
            return f"statistic {d.statistic!r}; no per-line values"
        lines = np.asarray(lines, float)
        try:
            n = d.directions(U_data[k].shape[1]).shape[0]
        except NotImplementedError:
            raise _Fail("line_values gives values but directions() raises: which lines are they?") from None
        _require(
            lines.shape == (n,) and np.all(np.isfinite(lines)),
            f"line_values of set {k!r} has shape {lines.shape}, expected ({n},) finite values, one per direction",
        )
        return f"statistic {d.statistic!r}; {n} lines"

    def c_pickle():
        d = prepared()
        other = _roundtrip(d)
        a, b = values(d, U_model), values(other, U_model)
        _require(a == b, f"the unpickled (prepared) distance gives {b}, the original {a}")

    checks = _common_checks(cls, inst, settings, label, "distance", registered, err) + [
        Check(label, "identical", c_identical),
        Check(label, "finite", c_finite),
    ]
    if separates:
        checks.append(Check(label, "separates", c_separates))
    checks.append(Check(label, "determinism", c_determinism))
    if empty:
        checks.append(Check(label, "empty", c_empty))
    checks.append(Check(label, "capabilities", c_capabilities))
    checks.append(Check(label, "pickle", c_pickle))
    return checks


def check_distance(distance, tables=None, *, raise_on_failure: bool = True, **options) -> Report:
    """Run :func:`distance_checks`; raises :class:`ConformanceError` on failures."""
    checks = distance_checks(distance, tables, **options)
    return _run(checks, checks[0].component, raise_on_failure)
