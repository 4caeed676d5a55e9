"""TuRBO (trust-region Bayesian optimisation) on problems with known answers: its trust-region
rules, its restarts, and its sample efficiency against CMA-ES at a small budget."""

import numpy as np
import pytest

import bforest_core as bf
from test_cma import _ellipsoid, _problem

FAST = {"candidates": 256, "max_train": 120}


def test_turbo_needs_far_fewer_evaluations_than_cma_on_an_ill_conditioned_quadratic():
    """At 150 evaluations of a 12-D ellipsoid (axis scales 1..100) the Gaussian process's trust
    region gets an order of magnitude closer than CMA-ES, which is still learning its covariance."""
    f, c = _ellipsoid()
    got = {}
    for name, settings in (("cma", {}), ("turbo", FAST)):
        pr, _ = _problem(f, [0] * 12, [1] * 12, budget=150, seed=2)
        got[name] = bf.component("optimizer", name, **settings).minimize(pr)
        assert got[name].n_evaluations == 150
    assert got["turbo"].fun < got["cma"].fun / 10, (got["turbo"].fun, got["cma"].fun)


@pytest.mark.parametrize("restart", ["design", "best"])
def test_a_flat_objective_halves_the_trust_region_after_each_failure_tolerance_and_restarts(restart):
    """Nothing improves on a constant: every ``failure_tol`` batches halve the box, from 0.8 to
    below 0.5**7 in 7 halvings; then a new run starts, with a fresh design (``design``, TuRBO-1)
    or at full size around the best point with every point kept (``best``)."""
    pr, asked = _problem(lambda x: 1.0, [0] * 3, [1] * 3, budget=10_000, seed=1)
    res = bf.component(
        "optimizer", "turbo", batch=2, failure_tol=3, init_points=6, restarts=1, restart=restart, **FAST
    ).minimize(pr)
    runs = [r["run"] for r in res.history]
    first = [r for r in res.history if r["run"] == 0]
    assert first[0]["length"] is None and first[0]["population"] == 6  # the design
    lengths = [r["length"] for r in first[1:]]
    assert lengths == [0.8 / 2 ** (i // 3 + 1) if i % 3 == 2 else 0.8 / 2 ** (i // 3) for i in range(21)]
    second = [r for r in res.history if r["run"] == 1]
    assert len(runs) == len(first) + len(second) and len(first) == 22  # restarts = 1: two runs, then the end
    assert "length_min" in res.stop_reason
    X = np.array(asked)
    if restart == "design":  # a fresh design, not the first run's again
        assert len(second) == 22 and res.n_evaluations == 2 * (6 + 21 * 2)
        assert second[0]["length"] is None and not np.array_equal(X[:6], X[48:54])
    else:  # no design: the same halvings again, from the first run's points
        assert [r["length"] for r in second] == lengths and res.n_evaluations == 6 + 2 * 21 * 2


def test_turbo_points_move_only_some_coordinates_of_the_best_point():
    """With the box centred on the best point so far (``centre = "best"``), each point after the
    design keeps the centre's value in every coordinate that the candidates' mask does not move:
    above 20 dimensions each moves with probability 20 / dimension, so not all of them do."""
    f, _ = _ellipsoid(dim=25, seed=3)
    pr, asked = _problem(f, [0] * 25, [1] * 25, budget=80, seed=5)
    res = bf.component("optimizer", "turbo", init_points=50, batch=2, centre="best", **FAST).minimize(pr)
    X = np.array(asked)
    vals = np.array([f(x) for x in X])
    moved = []
    for k in range(50, 80, 2):
        centre = X[:k][np.argmin(vals[:k])]
        moved.extend((X[k : k + 2] != centre).sum(axis=1))
    assert np.mean(moved) < 25 * 0.9  # each coordinate moves with probability 20 / 25
    assert res.fun == pytest.approx(vals.min())


def test_turbo_in_a_fit_resumes_after_a_kill_to_the_same_evaluations(toy_plugin, tmp_path, monkeypatch):
    """A fit killed after 17 evaluations and resumed asks for the same points and ends where an
    uninterrupted run ends (the GP fits replay on the logged distances)."""
    from bforest_core.pipeline.store import RunStore
    from conftest import fit_killed_after, toy_config

    cfg_path = toy_config(tmp_path, optimizer="turbo", optimizer_settings="batch = 2\ncandidates = 128", budget=40)
    full = bf.fit(bf.load_config(cfg_path), tmp_path / "full", progress=False)
    assert full.n_evaluations == 40 and isinstance(full.params["segments"], int)
    fit_killed_after(bf.load_config(cfg_path), tmp_path / "killed", 17, monkeypatch)
    assert RunStore.open(tmp_path / "killed").count() == 17
    res = bf.fit(bf.load_config(cfg_path), tmp_path / "killed", resume=True, progress=False)
    ev = lambda run: [(e.params, e.distance) for e in RunStore.open(run).evaluations()]  # noqa: E731
    assert ev(tmp_path / "killed") == ev(tmp_path / "full")
    assert res.params == full.params and res.distance == full.distance
