"""CMA-ES and the noise-aware early stop on problems with known answers."""

import numpy as np

import bforest_core as bf
from bforest_core.interfaces import Problem
from conftest import toy_config


def _problem(f, lo, hi, integer=None, budget=600, seed=1, seed_spread=None):
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    pr = Problem(
        names=[f"x{i}" for i in range(lo.size)],
        lower=lo,
        upper=hi,
        integer=np.zeros(lo.size, bool) if integer is None else np.asarray(integer, bool),
        evaluate=None,
        seed=seed,
        max_evaluations=budget,
        seed_spread=seed_spread,
    )
    asked = []

    def evaluate(X):
        X = np.atleast_2d(X)
        k = min(len(X), pr.remaining())
        asked.extend(map(tuple, X[:k]))
        out = np.full(len(X), np.inf)
        out[:k] = [f(x) for x in X[:k]]
        pr.n_evaluations += k
        if pr.remaining() == 0:
            pr.stopped, pr.stop_reason = True, "budget"
        for x, v in zip(X[:k], out[:k]):
            if v < pr.best_f:
                pr.best_f, pr.best_x = float(v), np.array(x)
        return out

    pr.evaluate = evaluate
    return pr, asked


SHIFT = np.array([0.3, -1.2, 2.5, 0.7])


def sphere(x):
    return float(((x - SHIFT) ** 2).sum())


def test_cma_finds_the_minimum_of_a_shifted_sphere():
    pr, _ = _problem(sphere, [-5] * 4, [5] * 4, budget=800)
    res = bf.component("optimizer", "cma").minimize(pr)
    assert res.fun < 1e-6 and np.allclose(res.x, SHIFT, atol=1e-3)
    assert res.n_evaluations <= 800 and res.history and "sigma" in res.history[-1]


def test_cma_beats_the_ga_at_equal_budget_on_rosenbrock():
    def rosen(x):
        return float(((1 - x[:-1]) ** 2 + 100 * (x[1:] - x[:-1] ** 2) ** 2).sum())

    best = {}
    for name in ("cma", "ga"):
        pr, _ = _problem(rosen, [-2] * 4, [2] * 4, budget=1500)
        best[name] = bf.component("optimizer", name).minimize(pr).fun
    assert best["cma"] < 1e-3 and best["cma"] < best["ga"] / 10


def test_cma_integer_parameters_are_whole_and_bounds_hold():
    pr, asked = _problem(
        lambda x: (x[0] - 7.2) ** 2 + (x[1] - 0.25) ** 2, [0, 0], [20, 1], integer=[True, False], budget=300
    )
    res = bf.component("optimizer", "cma").minimize(pr)
    X = np.array(asked)
    assert np.all(X[:, 0] == np.round(X[:, 0])) and X[:, 0].min() >= 0 and X[:, 0].max() <= 20
    assert X[:, 1].min() >= 0 and X[:, 1].max() <= 1
    assert res.x[0] == 7 and abs(res.x[1] - 0.25) < 1e-3


def test_cma_is_deterministic_for_a_seed():
    runs = []
    for _ in range(2):
        pr, asked = _problem(sphere, [-5] * 4, [5] * 4, budget=200, seed=4)
        bf.component("optimizer", "cma", restarts=2).minimize(pr)
        runs.append(asked)
    assert runs[0] == runs[1]
    pr, asked = _problem(sphere, [-5] * 4, [5] * 4, budget=200, seed=5)
    bf.component("optimizer", "cma").minimize(pr)
    assert asked != runs[0]


def test_noise_stop_waits_for_patience_and_uses_the_seed_noise():
    """A flat objective with noise 0.1: improvements below the noise do not count."""
    rng = np.random.default_rng(0)
    calls = []

    def spread(x, k):
        calls.append(k)
        return 5.0 + 0.1 * rng.standard_normal(k) * np.sqrt(k / (k - 1))

    f = lambda x: 5.0 + 0.01 * rng.random()  # noise far below 0.1: never an improvement
    pr, _ = _problem(f, [-1] * 3, [1] * 3, budget=5000, seed_spread=spread)
    res = bf.component("optimizer", "cma", patience=6, noise_seeds=8).minimize(pr)
    assert "seed noise" in res.stop_reason and "in 6 generations" in res.stop_reason
    assert calls == [8]  # measured once, at the end of the first window
    gens = [r["generation"] for r in res.history]
    assert gens[-1] == 7  # the first generation sets the anchor, then a window of 6
    assert 0.03 < res.diagnostics["seed_noise"] < 0.3


def test_noise_stop_keeps_going_while_the_objective_improves():
    pr, _ = _problem(sphere, [-5] * 4, [5] * 4, budget=400, seed_spread=lambda x, k: np.full(k, 1.0))
    res = bf.component("optimizer", "cma", patience=10, noise=1e-12).minimize(pr)
    assert res.fun < 1e-3


def test_cma_in_a_fit(toy_plugin, tmp_path):
    p = toy_config(
        tmp_path, optimizer="cma", optimizer_settings="population = 6\nmax_generations = 4\nrestarts = 0", budget=60
    )
    res = bf.fit(bf.load_config(p), tmp_path / "run", progress=False)
    assert 0 < res.n_evaluations <= 24 and (tmp_path / "run" / "best.json").exists()
    assert isinstance(res.params["segments"], int)


def test_the_ga_stops_on_the_seed_noise_too():
    rng = np.random.default_rng(1)
    pr, _ = _problem(
        lambda x: 5.0 + 0.01 * rng.random(),
        [-1] * 3,
        [1] * 3,
        budget=5000,
        seed_spread=lambda x, k: 5.0 + 0.1 * rng.standard_normal(k),
    )
    res = bf.component("optimizer", "ga", population=10, generations=50, stall_generations=None, patience=4).minimize(
        pr
    )
    assert "seed noise" in res.stop_reason and res.history[-1]["generation"] == 4


def test_cma_init_design_is_a_sobol_look_and_the_search_starts_at_its_best():
    corner = np.array([4.0, 4.0, -4.0, 4.0])
    f = lambda x: float(((x - corner) ** 2).sum())
    pr, asked = _problem(f, [-5] * 4, [5] * 4, budget=400, seed=3)
    res = bf.component("optimizer", "cma", init_design=32, population=8, sigma0=0.05).minimize(pr)
    X = np.array(asked)
    design = X[:32]
    # the design: 32 distinct points spread over the box (every half of every axis is visited)
    assert len({tuple(x) for x in design}) == 32
    assert all(((design[:, j] < 0).sum() == 16) for j in range(4))  # a Sobol' design is balanced
    assert res.history[0]["generation"] == 0 and res.history[0]["population"] == 32
    assert res.history[1]["generation"] == 1 and res.history[1]["sigma"] is not None
    # the first CMA generation is centred on the design's best point, not on the box centre
    best = design[np.argmin([f(x) for x in design])]
    first = X[32:40].mean(axis=0)  # 8 points of sd 0.5 per axis around the start
    assert np.linalg.norm(best) > 3.0 and np.linalg.norm(first - best) < 1.0
    assert res.fun < 1e-3 and res.n_evaluations == 400


def _ellipsoid(dim=12, seed=0):
    """An ill-conditioned quadratic (axis scales 1..100) in the unit cube; minimum 0 at ``c``."""
    c = np.random.default_rng(seed).uniform(0.2, 0.8, dim)
    w = np.logspace(0, 2, dim)
    return (lambda x: float((w * (x - c) ** 2).sum())), c


def test_lq_surrogate_needs_far_fewer_evaluations_on_a_quadratic():
    """lq-CMA-ES (Hansen 2019): on a quadratic the model ranks whole generations, so at equal
    budget it gets orders of magnitude closer than plain CMA-ES; its true evaluations go out in
    whole batches of ``surrogate_batch`` points."""
    f, c = _ellipsoid()
    got = {}
    for sur in ("none", "lq"):
        pr, asked = _problem(f, [0] * 12, [1] * 12, budget=400, seed=2)
        sizes = []
        inner = pr.evaluate
        pr.evaluate = lambda X: (sizes.append(len(X)), inner(X))[1]
        got[sur] = res = bf.component("optimizer", "cma", population=12, surrogate=sur, surrogate_batch=3).minimize(pr)
        assert res.n_evaluations <= 400
    plain, lq = got["none"], got["lq"]
    assert plain.fun > 1e-2 and lq.fun < 1e-6 and np.allclose(lq.x, c, atol=1e-3)
    assert all(n % 3 == 0 for n in sizes[:-1])  # whole batches (the last one may be cut by the budget)
    grown = [r["grown"] for r in lq.history]
    assert min(grown) < 12 and all(g <= r["population"] for g, r in zip(grown, lq.history))
    assert max(r["tau"] for r in lq.history) >= 0.85  # the model ranked some generation as the truth does


def test_lq_surrogate_is_deterministic_and_grows_every_point_of_a_noise_only_objective():
    """Pure noise: the model never ranks as the truth does (tau stays low), so every point of
    every generation is grown, as without a surrogate."""
    runs = []
    for _ in range(2):
        rng = np.random.default_rng(7)
        pr, asked = _problem(lambda x: float(rng.random()), [0] * 5, [1] * 5, budget=200, seed=4)
        res = bf.component("optimizer", "cma", population=8, surrogate="lq").minimize(pr)
        runs.append(asked)
        assert all(r["grown"] == r["population"] for r in res.history[2:])
    assert runs[0] == runs[1]


def test_raced_starts_begin_apart_and_successive_halving_drops_the_worse_half_at_equal_shares():
    pr, _ = _problem(sphere, [-5] * 4, [5] * 4, budget=616)
    res = bf.component("optimizer", "cma", init_design=16, starts=4, population=8).minimize(pr)
    starts = res.diagnostics["starts"]
    assert len(starts) == 4
    U = (np.array([s["x0"] for s in starts]) + 5) / 10
    assert all(np.max(np.abs(U[i] - U[j])) >= 0.25 for i in range(4) for j in range(i))
    # the 600 evaluations after the design in three equal parts: two starts dropped after the
    # first 200 (within one generation of 8), one after 400, the best one runs to the end
    dropped = sorted(s["dropped_after"] for s in starts if s["dropped_after"] is not None)
    assert len(dropped) == 3
    assert 216 <= dropped[0] == dropped[1] < 216 + 8 and 416 <= dropped[2] < 416 + 8
    winner = next(s for s in starts if s["dropped_after"] is None)
    assert winner["best"] == min(s["best"] for s in starts)
    # every generation names its start; the dropped ones stop asking after their drop
    recs = [r for r in res.history if r.get("run", -1) >= 0]
    for s in starts:
        if s["dropped_after"] is not None:
            assert max(r["n_evaluations"] for r in recs if r["start"] == s["start"]) <= s["dropped_after"]
    assert res.fun < 1e-4 and res.n_evaluations == 616


def test_one_start_is_the_plain_ipop_search():
    a, _ = _problem(sphere, [-5] * 4, [5] * 4, budget=300)
    b, _ = _problem(sphere, [-5] * 4, [5] * 4, budget=300)
    ra = bf.component("optimizer", "cma").minimize(a)
    rb = bf.component("optimizer", "cma", starts=1).minimize(b)
    assert ra.fun == rb.fun and "starts" not in ra.diagnostics
    assert all("start" not in r for r in ra.history)


def test_there_are_as_many_starts_as_asked_even_where_few_points_lie_apart():
    from bforest_optim.cma_es import _start_points

    lo, hi = np.zeros(1), np.ones(1)
    for seed in range(1, 6):  # one parameter: at most 4 points of [0, 1] lie 0.25 apart
        pts = _start_points(None, None, 6, lo, hi, lo, hi, seed)
        assert len(pts) == 6 and all(0 <= p[0] <= 1 for p in pts)


def test_a_race_with_two_finalists_halves_once_and_keeps_two_starts_to_the_end():
    """4 starts, 2 finalists: the 600 evaluations after the design in two equal parts; the worse
    two starts dropped after the first 300, the better two both ask until the budget ends."""
    pr, _ = _problem(sphere, [-5] * 4, [5] * 4, budget=616)
    res = bf.component("optimizer", "cma", init_design=16, starts=4, finalists=2, population=8).minimize(pr)
    starts = res.diagnostics["starts"]
    dropped = sorted(s["dropped_after"] for s in starts if s["dropped_after"] is not None)
    assert len(dropped) == 2 and 316 <= dropped[0] == dropped[1] < 316 + 8
    kept = [s for s in starts if s["dropped_after"] is None]
    assert len(kept) == 2 and max(s["best"] for s in kept) <= min(s["best"] for s in starts if s not in kept)
    recs = [r for r in res.history if r.get("run", -1) >= 0]
    for s in kept:  # both finalists still searching in the last generations of the budget
        assert max(r["n_evaluations"] for r in recs if r["start"] == s["start"]) > 616 - 3 * 8
    assert res.n_evaluations == 616


def _batch_sizes(pr) -> list[int]:
    """The sizes of the batches ``pr.evaluate`` is called with, in order (filled as they come)."""
    sizes, inner = [], pr.evaluate
    pr.evaluate = lambda X: (sizes.append(len(X)), inner(X))[1]
    return sizes


def test_starts_growing_together_send_one_batch_per_turn_and_repeat_for_a_seed():
    """grow_together: each turn grows one generation of every start still racing as one batch
    (4 x 8 points before the halving, 2 x 8 after), the halving still comes at half the budget
    (within a turn), and the same seed asks for the same points."""
    runs = []
    for _ in range(2):
        pr, asked = _problem(sphere, [-5] * 4, [5] * 4, budget=616)
        sizes = _batch_sizes(pr)
        res = bf.component(
            "optimizer", "cma", init_design=16, starts=4, finalists=2, population=8, grow_together=True
        ).minimize(pr)
        runs.append(asked)
    assert sizes[0] == 16 and set(sizes[1:-1]) == {32, 16} and sizes[-1] <= 32
    first16 = sizes.index(16, 1)
    assert sizes[1:first16] == [32] * (first16 - 1) and set(sizes[first16:-1]) == {16}
    dropped = sorted(s["dropped_after"] for s in res.diagnostics["starts"] if s["dropped_after"] is not None)
    assert len(dropped) == 2 and 316 <= dropped[0] == dropped[1] < 316 + 32
    assert res.n_evaluations == 616 and res.fun < 1e-2  # from distances of ~10 at the design
    assert runs[0] == runs[1]
    # one start at a time (the default) sends a batch per generation of one start
    pr, _ = _problem(sphere, [-5] * 4, [5] * 4, budget=616)
    sizes = _batch_sizes(pr)
    bf.component("optimizer", "cma", init_design=16, starts=4, finalists=2, population=8).minimize(pr)
    assert set(sizes[1:-1]) == {8}


def test_starts_growing_together_with_the_surrogate_tell_each_start_its_own_points():
    """With lq-CMA-ES each start grows its generation in steps; the steps of the starts go out
    together, and each start's log record counts only its own grown points."""
    pr, asked = _problem(sphere, [-5] * 4, [5] * 4, budget=800)
    res = bf.component(
        "optimizer", "cma", init_design=16, starts=4, finalists=2, population=8, surrogate="lq", grow_together=True
    ).minimize(pr)
    recs = [r for r in res.history if r.get("run", -1) >= 0]
    assert {r["start"] for r in recs} == {0, 1, 2, 3}
    assert all(1 <= r["grown"] <= r["population"] for r in recs)
    assert "converged" in res.stop_reason  # every generation ended, so every point grown is logged
    assert sum(r["grown"] for r in recs) + 16 == len(asked)
    assert res.fun < 1e-4
