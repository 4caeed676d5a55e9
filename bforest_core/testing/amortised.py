"""Conformance checks of an amortised estimator (on a problem with a known posterior)."""

from __future__ import annotations

from typing import Any

import numpy as np

from ._base import Check, Report, _common_checks, _Fail, _instance, _label, _need, _require, _roundtrip, _run


class _Problem:
    """Two continuous parameters and a whole-number one, each read off one summary with small
    noise, beside a summary of pure noise: the posterior of an observation lies at it."""

    lower = np.array([0.0, -1.0, 1.0])
    upper = np.array([1.0, 1.0, 5.0])
    integer = np.array([False, False, True])
    noise = np.array([0.03, 0.03, 0.15, 1.0])
    observed = np.array([0.3, -0.5, 3.0, 0.0])
    truth = np.array([0.3, -0.5, 3.0])

    def __init__(self, n: int, seed: int):
        rng = np.random.default_rng([seed, 0xA3])
        u = rng.random((n, 3))
        theta = self.lower + u * (self.upper - self.lower + np.array([0, 0, 1]))
        theta[:, 2] = np.minimum(np.floor(theta[:, 2]), self.upper[2])
        x = np.column_stack([theta, np.zeros(n)]) + rng.normal(size=(n, 4)) * self.noise
        self.theta, self.x = theta, x


def amortised_checks(
    estimator, *, settings=None, pairs: int = 1500, seed: int = 3, registered: bool | str = False
) -> list[Check]:
    """The conformance checks of an amortised estimator.

    ``train`` learns a known posterior from ``pairs`` pairs (each parameter read off its summary
    with small noise) and returns a JSON-able record; ``sample`` gives ``(k, n, p)`` draws inside
    the bounds, whole numbers for the integer parameter, and medians near the observation;
    ``determinism``: the same seed gives the same draws, another seed others; ``state``: the
    estimator restored from :meth:`state` into a new instance draws the same; ``pickle``: the
    unpickled instance draws the same. An estimator whose libraries are missing (``missing()``
    names them) fails the checks that need them with that line.
    """
    cls, inst, settings, err = _instance(estimator, "amortised", settings)
    label = _label(cls, "amortised")
    cache: dict[str, Any] = {}
    prob = _Problem(pairs, seed)

    def trained():
        est = _need(inst, err)
        problem = est.missing()
        _require(problem is None, f"cannot run: {problem}")
        if "record" not in cache:
            cache["record"] = est.train(prob.theta, prob.x, prob.lower, prob.upper, prob.integer, seed)
        return est

    def draws(est, n=400, s=1):
        return np.asarray(est.sample(prob.observed[None, :], n, s))

    def c_train():
        import json

        trained()
        rec = cache["record"]
        _require(isinstance(rec, dict), f"train returned a {type(rec).__name__}, not a dict")
        try:
            json.dumps(rec)
        except (TypeError, ValueError) as exc:
            raise _Fail(f"train's record is not JSON ({exc})") from None

    def c_sample():
        est = trained()
        X = draws(est)
        _require(X.shape == (1, 400, 3), f"sample(x (1, 4), 400) has shape {X.shape}, expected (1, 400, 3)")
        X = X[0]
        inside = np.all((X >= prob.lower - 1e-9) & (X <= prob.upper + 1e-9))
        _require(inside, "draws outside the bounds")
        _require(np.all(X[:, 2] == np.round(X[:, 2])), "the integer parameter has draws that are not whole")
        med = np.median(X, axis=0)
        err_ = np.abs(med - prob.truth) / (prob.upper - prob.lower)
        _require(
            np.all(err_ < 0.1),
            f"posterior medians {np.round(med, 3).tolist()} are not within 10 % of the range of "
            f"{prob.truth.tolist()}, where the summaries put them",
        )
        two = np.asarray(est.sample(np.vstack([prob.observed, prob.observed + [0.4, 0.8, 1.0, 0]]), 50, 1))
        _require(two.shape == (2, 50, 3), f"sample(x (2, 4), 50) has shape {two.shape}, expected (2, 50, 3)")
        return f"medians {np.round(med, 3).tolist()} for {prob.truth.tolist()}"

    def c_determinism():
        est = trained()
        a, b, c = draws(est, s=1), draws(est, s=1), draws(est, s=2)
        _require(np.array_equal(a, b), "the same seed gave other draws")
        _require(not np.array_equal(a, c), "another seed gave the same draws")

    def c_state():
        est = trained()
        meta, blob = est.state()
        _require(isinstance(meta, dict) and isinstance(blob, bytes), "state() must return (dict, bytes)")
        import json

        meta = json.loads(json.dumps(meta))
        other = cls(**est.settings.model_dump())
        other.load_state(meta, blob)
        _require(np.array_equal(draws(other), draws(est)), "the estimator restored from its state draws otherwise")
        return f"{len(blob)} bytes"

    def c_pickle():
        est = trained()
        other = _roundtrip(est)
        _require(np.array_equal(draws(other), draws(est)), "the unpickled estimator draws otherwise")

    return _common_checks(cls, inst, settings, label, "amortised", registered, err) + [
        Check(label, "train", c_train),
        Check(label, "sample", c_sample),
        Check(label, "determinism", c_determinism),
        Check(label, "state", c_state),
        Check(label, "pickle", c_pickle),
    ]


def check_amortised(estimator, *, raise_on_failure: bool = True, **options) -> Report:
    """Run :func:`amortised_checks`; raises :class:`ConformanceError` on failures."""
    checks = amortised_checks(estimator, **options)
    return _run(checks, checks[0].component, raise_on_failure)
