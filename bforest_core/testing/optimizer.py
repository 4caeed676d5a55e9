"""Conformance checks of an optimiser (on a known problem)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ..interfaces import OptimizeResult, Problem
from ._base import Check, Report, _common_checks, _Fail, _instance, _label, _need, _require, _roundtrip, _run


class _Harness:
    """A Problem over a shifted quadratic bowl whose ``evaluate`` behaves like the fit's:
    rounds integer parameters, stops at the budget, tracks the best point and later calls."""

    lower = np.array([-2.0, -2.0, 0.0])
    upper = np.array([3.0, 3.0, 10.0])
    integer = np.array([False, False, True])
    optimum = np.array([1.0, -0.5, 4.0])

    def __init__(self, seed: int, budget: int):
        self.points: list[np.ndarray] = []
        self.calls_after_stop = 0
        self.problem = Problem(
            names=["x", "y", "k"],
            lower=self.lower.copy(),
            upper=self.upper.copy(),
            integer=self.integer.copy(),
            evaluate=self.evaluate,
            seed=seed,
            max_evaluations=budget,
        )

    def f(self, x):
        return float(np.sum(((x - self.optimum) / (self.upper - self.lower)) ** 2))

    def evaluate(self, X):
        pr = self.problem
        X = np.atleast_2d(np.asarray(X, dtype=float))
        if X.ndim != 2 or X.shape[1] != pr.dim:
            raise _Fail(f"evaluate was called with an array of shape {X.shape}, expected (k, {pr.dim})")
        if pr.stopped:
            self.calls_after_stop += 1
        X = np.clip(X, pr.lower, pr.upper)
        X[:, pr.integer] = np.round(X[:, pr.integer])
        out = np.full(X.shape[0], np.inf)
        for r, x in enumerate(X):
            if pr.stopped or pr.n_evaluations >= pr.max_evaluations:
                pr.stopped, pr.stop_reason = True, f"evaluation budget ({pr.max_evaluations}) reached"
                continue
            out[r] = self.f(x)
            self.points.append(x.copy())
            pr.n_evaluations += 1
            if out[r] < pr.best_f:
                pr.best_f, pr.best_x = out[r], x.copy()
        if pr.n_evaluations >= pr.max_evaluations:
            pr.stopped, pr.stop_reason = True, f"evaluation budget ({pr.max_evaluations}) reached"
        return out


def optimizer_checks(
    optimizer, *, settings=None, budget: int = 60, seed: int = 3, registered: bool | str = False
) -> list[Check]:
    """The conformance checks of an optimiser, on a 3-parameter bowl (one integer parameter).

    ``minimize`` must return an :class:`OptimizeResult` inside the bounds, never exceed the
    evaluation budget, return promptly once the problem has stopped (at most one more
    ``evaluate`` call), find a point better than the median of what it evaluated, and repeat
    exactly the same evaluations for the same seed. ``budget``: ``expected_evaluations`` is None
    or a positive int, and ``budget_settings`` gives valid settings (a new dict) under which the
    optimiser plans no fewer evaluations than the budget and still keeps to ``Problem.max_evaluations``.
    """
    cls, inst, settings, err = _instance(optimizer, "optimizer", settings)
    label = _label(cls, "optimizer")
    cache: dict[str, Any] = {}

    def run(opt=None):
        h = _Harness(seed, budget)
        res = (opt or _need(inst, err)).minimize(h.problem)
        return h, res

    def first():
        if "run" not in cache:
            cache["run"] = run()
        return cache["run"]

    def c_minimize():
        h, res = first()
        pr = h.problem
        _require(isinstance(res, OptimizeResult), f"minimize returned a {type(res).__name__}, not an OptimizeResult")
        _require(len(h.points) > 0, "minimize evaluated nothing")
        _require(pr.n_evaluations <= budget, f"{pr.n_evaluations} evaluations for a budget of {budget}")
        _require(
            h.calls_after_stop <= 1,
            f"evaluate was called {h.calls_after_stop} times after the problem "
            "stopped; return once problem.stopped is set",
        )
        x = np.asarray(res.x, float).reshape(-1)
        _require(x.shape == (pr.dim,), f"result.x has shape {x.shape}, expected ({pr.dim},)")
        _require(np.all(x >= pr.lower - 1e-9) and np.all(x <= pr.upper + 1e-9), f"result.x {x} is outside the bounds")
        _require(math.isfinite(res.fun), f"result.fun is {res.fun!r}")
        vals = np.array([h.f(p) for p in h.points])
        _require(
            res.fun <= np.median(vals) and (res.fun < np.median(vals) or np.ptp(vals) == 0),
            f"best value {res.fun:.4g} is not below the median {np.median(vals):.4g} of the evaluated points",
        )
        return f"{pr.n_evaluations} evaluations, best {res.fun:.3g} (median {np.median(vals):.3g})"

    def c_determinism():
        h1, r1 = first()
        h2, r2 = run()
        same = len(h1.points) == len(h2.points) and all(np.array_equal(a, b) for a, b in zip(h1.points, h2.points))
        _require(
            same,
            "the same seed and objective gave a different sequence of evaluated points (the run "
            "store replays evaluations on resume, so the search must be deterministic)",
        )

    def c_budget():
        opt = _need(inst, err)
        _require(isinstance(opt.takes_start(), bool), f"takes_start() is {opt.takes_start()!r}, expected a bool")
        plan = opt.expected_evaluations(3)
        _require(
            plan is None or (isinstance(plan, int) and plan >= 1),
            f"expected_evaluations(3) is {plan!r}, expected None or a positive int",
        )
        own = opt.settings.model_dump()
        given = dict(own)
        try:
            lifted = cls.budget_settings(given, 10 * budget)
            other = cls(**lifted)
        except Exception as exc:
            raise _Fail(
                f"budget_settings(settings, {10 * budget}) gave settings the class rejects "
                f"({type(exc).__name__}: {exc})"
            ) from None
        _require(given == own, "budget_settings changed the mapping it was given (return a new dict)")
        lplan = other.expected_evaluations(3)
        _require(
            lplan is None or lplan >= 10 * budget,
            f"with budget_settings for {10 * budget} evaluations the "
            f"optimiser plans only {lplan}: its own limits, not the budget, would end a comparison's run",
        )
        h = _Harness(seed, budget)
        other.minimize(h.problem)
        _require(
            h.problem.n_evaluations <= budget,
            f"with budget_settings it evaluated {h.problem.n_evaluations} points for a Problem.max_evaluations of {budget}",
        )
        return f"plans {plan}; with budget_settings {lplan}, {h.problem.n_evaluations}/{budget} evaluations"

    def c_pickle():
        other = _roundtrip(_need(inst, err))
        h1, _ = first()
        h2, _ = run(other)
        _require(
            len(h1.points) == len(h2.points) and all(np.array_equal(a, b) for a, b in zip(h1.points, h2.points)),
            "the unpickled optimiser searches differently",
        )

    return _common_checks(cls, inst, settings, label, "optimizer", registered, err) + [
        Check(label, "minimize", c_minimize),
        Check(label, "determinism", c_determinism),
        Check(label, "budget", c_budget),
        Check(label, "pickle", c_pickle),
    ]


def check_optimizer(optimizer, *, raise_on_failure: bool = True, **options) -> Report:
    """Run :func:`optimizer_checks`; raises :class:`ConformanceError` on failures."""
    checks = optimizer_checks(optimizer, **options)
    return _run(checks, checks[0].component, raise_on_failure)
