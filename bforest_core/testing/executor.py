"""Conformance checks of an executor."""

from __future__ import annotations

from ._base import Check, Report, _common_checks, _instance, _label, _need, _require, _roundtrip, _run

_WORKER_OFFSET = None


def _conformance_init(offset):
    """Executor initializer used by the executor checks (module level: picklable)."""
    global _WORKER_OFFSET
    _WORKER_OFFSET = offset


def _conformance_task(x):
    if _WORKER_OFFSET is None:
        raise RuntimeError("initializer did not run in this worker")
    return x * x + _WORKER_OFFSET


def _no_time_limit(item):
    return None


def _no_stand_in(fn, item, status, message):
    return NotImplemented


def executor_checks(executor, *, settings=None, items: int = 12, registered: bool | str = False) -> list[Check]:
    """The conformance checks of an executor: the initializer runs in every worker before any
    task, ``map_unordered`` yields every index exactly once with its result, ``map`` keeps the
    order, and the executor can be started again after ``shutdown``."""
    cls, inst, settings, err = _instance(executor, "executor", settings)
    label = _label(cls, "executor")
    xs = list(range(items))

    def c_map():
        ex = _need(inst, err)
        _require(isinstance(ex.workers, int) and ex.workers >= 1, f"workers is {ex.workers!r}")
        with ex.started(_conformance_init, (7,)):
            got = list(ex.map_unordered(_conformance_task, xs))
            idx = sorted(i for i, _ in got)
            _require(
                idx == list(range(items)), f"map_unordered yielded indices {idx}, expected each of 0..{items - 1} once"
            )
            bad = [(i, r) for i, r in got if r != xs[i] ** 2 + 7]
            _require(not bad, f"wrong results (index, result): {bad[:3]}")
            ordered = ex.map(_conformance_task, xs)
            _require(ordered == [x * x + 7 for x in xs], f"map returned {ordered}")
        with ex.started(_conformance_init, (1,)):
            again = ex.map(_conformance_task, xs[:3])
            _require(
                again == [x * x + 1 for x in xs[:3]],
                f"after a restart with a new initializer argument map returned {again}",
            )
        return f"{ex.workers} worker(s)"

    def c_hooks():
        ex = _need(inst, err)
        _require(
            ex.time_limit is None and ex.on_lost is None,
            "a new instance has time_limit "
            f"{ex.time_limit!r} and on_lost {ex.on_lost!r}, expected None (Executor's defaults)",
        )
        ex.time_limit, ex.on_lost = _no_time_limit, _no_stand_in  # what a fit sets before start
        try:
            with ex.started(_conformance_init, (2,)):
                got = ex.map(_conformance_task, xs[:4])
        finally:
            ex.time_limit = ex.on_lost = None
        _require(got == [x * x + 2 for x in xs[:4]], f"with time_limit and on_lost set map returned {got}")

    def c_pickle():
        _roundtrip(_need(inst, err))

    return _common_checks(cls, inst, settings, label, "executor", registered, err) + [
        Check(label, "map", c_map),
        Check(label, "hooks", c_hooks),
        Check(label, "pickle", c_pickle),
    ]


def check_executor(executor, *, raise_on_failure: bool = True, **options) -> Report:
    """Run :func:`executor_checks`; raises :class:`ConformanceError` on failures."""
    checks = executor_checks(executor, **options)
    return _run(checks, checks[0].component, raise_on_failure)
