"""The optimisers of bforest_optim (ga, nlopt, emcee, de) on cheap objectives with known minima.

``make_problem`` is a miniature of the fit pipeline's evaluator: serial evaluation in-process,
integer rounding, an evaluation budget after which points get ``inf`` and ``stopped`` is set,
best-point tracking, and a record of every batch.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

import bforest_core as bf
from bforest_core.errors import ConfigError
from bforest_core.interfaces import Problem
from bforest_optim.cma_es import CMAES
from bforest_optim.de import DifferentialEvolution
from bforest_optim.emcee_sampler import EmceeSampler, auto_epsilon
from bforest_optim.ga import GeneticAlgorithm, reflect
from bforest_optim.nlopt_optimizer import NloptOptimizer, resolve_algorithm
from bforest_optim.turbo import Turbo

NAMES = ["a", "b", "n"]
LOWER = np.array([-5.0, -5.0, 0.0])
UPPER = np.array([5.0, 5.0, 10.0])
INTEGER = np.array([False, False, True])
X_MIN = np.array([1.3, -0.7, 3.0])
WEIGHTS = np.array([1.0, 4.0, 0.5])


def quadratic(x):
    """Shifted, scaled quadratic: minimum 0 at X_MIN (the integer parameter n at 3)."""
    return float(np.sum(WEIGHTS * (x - X_MIN) ** 2))


class Recorder:
    """The evaluate of a test problem: evaluates serially, honours the budget, records batches."""

    def __init__(self, fun, problem: Problem, replay=None, target=None):
        self.fun, self.problem, self.target = fun, problem, target
        self.batches: list[tuple[np.ndarray, np.ndarray]] = []
        self.violations: list[str] = []
        self.calls_after_stop = 0
        self.replay = list(replay) if replay is not None else None

    def __call__(self, X):
        pr = self.problem
        X = np.array(X, dtype=float)
        if X.ndim != 2 or X.shape[1] != pr.dim:
            self.violations.append(f"shape {X.shape}")
        if np.any(X < pr.lower) or np.any(X > pr.upper):
            self.violations.append(f"out of bounds: {X[(X < pr.lower).any(1) | (X > pr.upper).any(1)]}")
        if np.any(X[:, pr.integer] != np.rint(X[:, pr.integer])):
            self.violations.append("non-integral integer parameter")
        if pr.stopped:
            self.calls_after_stop += 1
        X = np.where(pr.integer, np.rint(X), X)
        out = np.full(len(X), np.inf)
        if self.replay is not None and self.replay:  # resume: values come from the log
            X_old, f_old = self.replay.pop(0)
            if not np.array_equal(X_old, X):
                self.violations.append(f"replay mismatch in batch {len(self.batches)}")
            out = f_old.copy()
            pr.n_evaluations += int(np.isfinite(f_old).sum())
        else:
            for i, x in enumerate(X):
                if pr.stopped:
                    break
                out[i] = self.fun(x)
                pr.n_evaluations += 1
                if pr.max_evaluations is not None and pr.n_evaluations >= pr.max_evaluations:
                    pr.stopped, pr.stop_reason = True, "budget"
        for x, f in zip(X, out):
            if f < pr.best_f:
                pr.best_f, pr.best_x = float(f), x.copy()
        if self.target is not None and pr.best_f <= self.target and not pr.stopped:
            pr.stopped, pr.stop_reason = True, "target"  # like the pipeline: checked after a batch
        self.batches.append((X.copy(), out.copy()))
        return out

    @property
    def points(self):
        return np.concatenate([b[0] for b in self.batches])

    @property
    def values(self):
        return np.concatenate([b[1] for b in self.batches])


def make_problem(
    fun=quadratic,
    *,
    budget=None,
    seed=0,
    lower=LOWER,
    upper=UPPER,
    integer=INTEGER,
    init_lower=None,
    init_upper=None,
    replay=None,
    target=None,
):
    logs: list[dict] = []
    pr = Problem(
        list(NAMES[: len(lower)]),
        np.asarray(lower, float),
        np.asarray(upper, float),
        np.asarray(integer, bool),
        evaluate=None,
        init_lower=init_lower,
        init_upper=init_upper,
        seed=seed,
        max_evaluations=budget,
        log=logs.append,
    )
    rec = Recorder(fun, pr, replay, target)
    pr.evaluate = rec
    return pr, rec, logs


# optimiser, settings, budget, tolerance on the real parameters, tolerance on the distance
CASES = {
    "ga": (GeneticAlgorithm, {}, None, 0.1, 0.02),
    "ga-intermediate": (GeneticAlgorithm, {"crossover": "intermediate", "selection": "tournament"}, None, 0.1, 0.02),
    "nlopt-crs2": (NloptOptimizer, {}, 1500, 0.05, 1e-3),
    "nlopt-sbplx": (NloptOptimizer, {"algorithm": "sbplx"}, 1500, 0.05, 1e-3),
    "nlopt-direct+bobyqa": (
        NloptOptimizer,
        {"algorithm": "direct_l", "local_algorithm": "LN_BOBYQA"},
        1500,
        0.05,
        1e-3,
    ),
    "emcee": (EmceeSampler, {"epsilon": 0.5, "steps": 150}, None, 0.3, 0.1),
    "de": (DifferentialEvolution, {}, None, 0.05, 1e-3),
    "cma-lq": (CMAES, {"surrogate": "lq", "population": 8}, 600, 0.05, 1e-3),
    "cma-raced-together": (
        CMAES,
        {"surrogate": "lq", "population": 8, "init_design": 16, "starts": 4, "finalists": 2, "grow_together": True},
        600,
        0.05,
        1e-3,
    ),
    "turbo": (Turbo, {"candidates": 256, "max_train": 100, "hyper_every": 10}, 200, 0.05, 1e-3),
}


@pytest.mark.parametrize("case", list(CASES))
def test_finds_known_minimum_with_integer_and_real_parameters(case):
    cls, settings, budget, xtol, ftol = CASES[case]
    pr, rec, logs = make_problem(budget=budget, seed=3)
    res = cls(**settings).minimize(pr)
    assert not rec.violations, rec.violations[:3]
    assert res.x[2] == 3.0
    assert np.all(np.abs(res.x[:2] - X_MIN[:2]) < xtol), res.x
    assert res.fun < ftol
    assert res.fun == pytest.approx(quadratic(res.x))
    # the returned point is the best the problem evaluated
    assert res.fun == pytest.approx(rec.values.min())
    assert res.n_evaluations == pr.n_evaluations
    if budget is not None:
        assert pr.n_evaluations <= budget
    # one log record per generation/iteration, forwarded to problem.log and kept in history
    assert logs and logs == res.history
    assert [r["iteration"] for r in logs] == list(range(len(logs)))
    bests = [r["best"] for r in logs if r["best"] is not None]
    assert bests == sorted(bests, reverse=True) and bests[-1] == pytest.approx(res.fun)


@pytest.mark.parametrize("case", list(CASES))
def test_same_seed_same_result(case):
    cls, settings, *_ = CASES[case]
    runs = []
    for _ in range(2):
        pr, rec, logs = make_problem(budget=400, seed=11)
        res = cls(**settings).minimize(pr)
        runs.append((res, rec))
    (r1, c1), (r2, c2) = runs
    assert np.array_equal(r1.x, r2.x) and r1.fun == r2.fun and r1.history == r2.history
    assert len(c1.batches) == len(c2.batches)
    assert all(np.array_equal(a[0], b[0]) for a, b in zip(c1.batches, c2.batches))


@pytest.mark.parametrize("case", ["ga", "nlopt-crs2", "emcee", "de", "turbo"])
def test_other_seed_other_search(case):
    cls, settings, *_ = CASES[case]
    pts = []
    for seed in (1, 2):
        pr, rec, _ = make_problem(budget=100, seed=seed)
        cls(**settings).minimize(pr)
        pts.append(rec.points)
    assert not np.array_equal(pts[0], pts[1])


@pytest.mark.parametrize("case", list(CASES))
def test_stops_at_budget_and_returns_best_seen(case):
    cls, settings, *_ = CASES[case]
    pr, rec, _ = make_problem(budget=57, seed=5)
    res = cls(**settings).minimize(pr)
    assert pr.stopped and pr.n_evaluations == 57 and res.n_evaluations == 57
    assert res.stop_reason == "budget"
    assert rec.calls_after_stop == 0
    evaluated = rec.values[np.isfinite(rec.values)]
    assert evaluated.size == 57
    assert res.fun == evaluated.min()
    assert np.array_equal(res.x, pr.best_x)


@pytest.mark.parametrize("case", list(CASES) + ["nlopt-isres", "nlopt-mlsl"])
def test_stops_at_target_mid_run_and_returns_best_seen(case):
    """A stop that is not the evaluation budget (target distance, wall time) ends the run at
    once, whatever NLopt's maxeval says."""
    cls, settings, *_ = (
        CASES[case]
        if case in CASES
        else (
            NloptOptimizer,
            {"nlopt-isres": {"algorithm": "GN_ISRES"}, "nlopt-mlsl": {"algorithm": "GN_MLSL_LDS"}}[case],
        )
    )
    pr, rec, _ = make_problem(seed=5, target=10.0)  # reached within the first few points
    res = cls(**settings).minimize(pr)
    assert pr.stopped and res.stop_reason == "target"
    assert rec.calls_after_stop == 0
    assert res.fun <= 10.0 and res.fun == rec.values.min() and np.array_equal(res.x, pr.best_x)


@pytest.mark.parametrize("case", ["ga", "nlopt-crs2", "emcee", "de", "cma-lq", "cma-raced-together", "turbo"])
def test_resume_replay_gives_the_same_batches(case):
    """Resume re-runs the optimiser from the start: the first batches' values come from the log
    (nothing is computed), the rest are computed; the run must ask for the same points."""
    cls, settings, *_ = CASES[case]
    pr, full, _ = make_problem(budget=300, seed=7)
    res_full = cls(**settings).minimize(pr)
    assert len(full.batches) >= 4
    half = full.batches[: len(full.batches) // 2]
    pr2, again, _ = make_problem(fun=quadratic, budget=300, seed=7, replay=half)
    res_again = cls(**settings).minimize(pr2)
    assert not again.violations, again.violations[:3]
    assert len(again.batches) == len(full.batches)
    for (Xa, fa), (Xb, fb) in zip(full.batches, again.batches):
        assert np.array_equal(Xa, Xb)
        assert np.array_equal(fa, fb)
    assert np.array_equal(res_full.x, res_again.x) and res_full.fun == res_again.fun


# ------------------------------------------------------------------------------ bounds, integers
@pytest.mark.parametrize("case", ["ga", "nlopt-crs2", "nlopt-sbplx", "emcee", "de", "turbo"])
def test_evaluations_respect_bounds_and_init_box(case):
    """Integer bounds that are not whole numbers are narrowed; the initial points lie in the
    initial box; every evaluated point is feasible and integral."""
    cls, settings, *_ = CASES[case]
    lower, upper = np.array([-5.0, -5.0, 0.4]), np.array([5.0, 5.0, 9.6])
    ilo, ihi = np.array([2.0, 1.0, 6.0]), np.array([4.0, 3.0, 9.0])
    pr, rec, _ = make_problem(budget=600, seed=2, lower=lower, upper=upper, init_lower=ilo, init_upper=ihi)
    res = cls(**settings).minimize(pr)
    assert not rec.violations, rec.violations[:3]
    P = rec.points
    assert P[:, 2].min() >= 1 and P[:, 2].max() <= 9
    if case != "nlopt-sbplx":
        first = rec.batches[0][0]
        assert np.all(first >= ilo) and np.all(first <= ihi)
    # the search leaves the initial box to reach the minimum outside it
    assert res.x[2] == 3.0 and abs(res.x[0] - 1.3) < 0.5


def test_ga_keeps_integers_integral_and_uses_integer_steps():
    # n starts in {0, 1, 2}: reaching n = 3 takes integer mutation steps
    pr, rec, _ = make_problem(
        budget=None,
        seed=4,
        integer=np.array([False, True, True]),
        init_lower=np.array([-5.0, -5.0, 0.0]),
        init_upper=np.array([5.0, 5.0, 2.0]),
    )
    res = GeneticAlgorithm(generations=20).minimize(pr)
    P = rec.points
    assert np.array_equal(P[:, 1:], np.rint(P[:, 1:]))
    assert set(np.unique(rec.batches[0][0][:, 2])) == {0.0, 1.0, 2.0}
    pop = res.diagnostics["final_population"]
    assert np.array_equal(pop[:, 1:], np.rint(pop[:, 1:]))
    assert res.x[1] == -1.0 and res.x[2] == 3.0  # b = -0.7: the best whole value is -1


def test_ga_elites_survive_and_generations_are_one_batch():
    pr, rec, logs = make_problem(seed=9)
    res = GeneticAlgorithm(population=20, generations=6, elite_count=3, stall_generations=None).minimize(pr)
    assert len(rec.batches) == 7
    assert [len(b[0]) for b in rec.batches] == [20] + [17] * 6
    assert [r["generation"] for r in logs] == list(range(7))
    assert {"mean", "median", "std", "sigma", "n_evaluations"} <= set(logs[-1])
    # mutation scale shrinks geometrically from 0.3 to 0.02
    assert logs[1]["sigma"] == pytest.approx(0.3) and logs[-1]["sigma"] == pytest.approx(0.02)
    # elitism: the best individual is still in the last generation
    pop = res.diagnostics["final_population"]
    assert pop.shape == (20, 3) and any(np.array_equal(row, res.x) for row in pop)


def test_ga_stall_stops_early():
    flat = lambda x: 1.0  # noqa: E731 - nothing ever improves
    pr, rec, _ = make_problem(fun=flat, seed=1)
    res = GeneticAlgorithm(stall_generations=3).minimize(pr)
    assert "no improvement in 3 generations" == res.stop_reason
    assert len(rec.batches) == 4


def test_failed_evaluations_are_never_the_best():
    """NaN/inf (failed simulations) are ignored; the optimisers still find the minimum."""

    def failing(x):
        return math.nan if x[0] > 2.0 else quadratic(x)

    for cls, budget in [(GeneticAlgorithm, None), (DifferentialEvolution, None), (NloptOptimizer, 800)]:
        pr, rec, _ = make_problem(fun=failing, seed=6, budget=budget)
        res = cls().minimize(pr)
        assert math.isfinite(res.fun) and res.fun < 0.05 and res.x[2] == 3.0, cls


def test_reflect_folds_into_the_bounds():
    lo, hi = np.array([0.0, 1.0]), np.array([10.0, 5.0])
    # -3 -> 3; 6 -> 4; 23 -> 20 -> 3 (twice folded); -6 -> 8 -> 2
    X = np.array([[-3.0, 6.0], [23.0, -6.0], [4.0, 3.0]])
    assert np.array_equal(reflect(X, lo, hi), [[3.0, 4.0], [3.0, 2.0], [4.0, 3.0]])


# ------------------------------------------------------------------------------ emcee
def test_emcee_posterior_median_near_minimum_and_diagnostics():
    """D = sum w (x - x0)^2 and epsilon = 1: the posterior is normal around x0 with standard
    deviation sqrt(1 / (2 w)) per real parameter (0.71 for a, 0.35 for b)."""
    pr, rec, logs = make_problem(seed=21)
    res = EmceeSampler(epsilon=1.0, steps=400, burn_in=100).minimize(pr)
    d = res.diagnostics
    post = d["posterior"]
    assert post["a"]["median"] == pytest.approx(1.3, abs=0.25)
    assert post["b"]["median"] == pytest.approx(-0.7, abs=0.15)
    assert post["n"]["median"] == 3.0
    assert (post["a"]["p84"] - post["a"]["p16"]) / 2 == pytest.approx(0.71, rel=0.3)
    assert (post["b"]["p84"] - post["b"]["p16"]) / 2 == pytest.approx(0.35, rel=0.3)
    assert post["a"]["p2.5"] < post["a"]["p16"] < post["a"]["median"] < post["a"]["p84"] < post["a"]["p97.5"]
    assert d["walkers"] == 16 and d["steps"] == 400 and d["burn_in"] == 100
    assert d["chain"].shape == (400, 16, 3) and d["distances"].shape == (400, 16)
    assert 0.2 < d["acceptance_fraction"] < 0.9
    assert set(d["autocorr_time"]) == set(NAMES) and all(t is not None and t > 1 for t in d["autocorr_time"].values())
    assert d["epsilon"] == 1.0
    # walkers go to evaluate together: the initial ensemble, then the in-bounds proposals of
    # each half-ensemble update
    sizes = [len(X) for X, _ in rec.batches]
    assert sizes[0] == 16 and max(sizes[1:]) == 8 and len(sizes) <= 1 + 2 * 400
    assert len(logs) == 401 and logs[-1]["step"] == 400
    # the best point is the smallest distance seen
    assert res.fun == rec.values.min()


def test_emcee_auto_epsilon_is_scaled_mad_of_initial_walkers():
    pr, rec, _ = make_problem(budget=200, seed=8)
    res = EmceeSampler(steps=5, epsilon="auto", epsilon_scale=0.5).minimize(pr)
    f0 = rec.batches[0][1]
    mad = 1.4826 * np.median(np.abs(f0 - np.median(f0)))
    assert res.diagnostics["epsilon"] == pytest.approx(0.5 * mad)
    assert res.diagnostics["epsilon_rule"].startswith("auto")
    assert auto_epsilon(np.array([2.0, 2.0, 2.0])) == 1.0  # no spread: falls back to 1
    assert auto_epsilon(np.array([1.0, 1.0, 1.0, 5.0, np.inf])) == pytest.approx(np.std([1, 1, 1, 5.0]))


def test_emcee_out_of_bounds_proposals_are_not_evaluated():
    # a narrow box around the minimum's edge: many stretch proposals leave it
    pr, rec, _ = make_problem(seed=3, lower=np.array([1.0, -1.0, 2.0]), upper=np.array([1.4, -0.5, 4.0]))
    res = EmceeSampler(steps=60, epsilon=0.01, moves="de").minimize(pr)
    assert not rec.violations
    assert rec.points.shape[0] < 16 + 60 * 16  # rejected proposals never reached evaluate
    assert res.diagnostics["steps"] == 60


def test_emcee_walkers_validation():
    with pytest.raises(ValueError, match="even"):
        EmceeSampler(walkers=15)
    pr, _, _ = make_problem()
    with pytest.raises(ValueError, match="at least 2"):
        EmceeSampler(walkers=4).minimize(pr)


# ------------------------------------------------------------------------------ nlopt
def test_nlopt_algorithm_names():
    assert resolve_algorithm("GN_CRS2_LM") == "GN_CRS2_LM"
    assert resolve_algorithm("crs2_lm") == "GN_CRS2_LM"
    assert resolve_algorithm("gn_isres") == "GN_ISRES"
    assert resolve_algorithm("Sbplx") == "LN_SBPLX"
    assert resolve_algorithm("neldermead") == "LN_NELDERMEAD"
    assert resolve_algorithm("mlsl_lds") == "GN_MLSL_LDS"
    assert NloptOptimizer(algorithm="bobyqa").settings.algorithm == "LN_BOBYQA"
    with pytest.raises(ValueError, match="needs gradients"):
        resolve_algorithm("LD_MMA")
    with pytest.raises(ConfigError, match="unknown NLopt algorithm 'nonsense'.*GN_CRS2_LM"):
        bf.component("optimizer", "nlopt", algorithm="nonsense")
    with pytest.raises(ConfigError, match="local"):
        bf.component("optimizer", "nlopt", local_algorithm="GN_ISRES")
    # the evaluation budget has one name, [stop] max_evaluations (Problem.max_evaluations)
    with pytest.raises(ConfigError, match=r"maxeval is gone: use \[stop\] max_evaluations"):
        bf.component("optimizer", "nlopt", maxeval=300)


def test_nlopt_one_point_per_call_and_polish_after_global():
    # the main run gets the budget less the polish's 200
    pr, rec, logs = make_problem(seed=1, budget=500)
    res = NloptOptimizer(algorithm="GN_ISRES", population=30, local_algorithm="sbplx", local_maxeval=200).minimize(pr)
    assert all(len(X) == 1 for X, _ in rec.batches)
    phases = [r["phase"] for r in logs]
    assert phases.count("global") == 300 and 0 < phases.count("local") <= 200
    assert phases == sorted(phases, key=lambda p: p == "local")
    assert res.diagnostics["nlopt_result"]["global"] == "maxeval reached"
    assert res.fun < 1e-3


# ------------------------------------------------------------------------------ registry, settings
def test_components_are_registered():
    for name, cls in [
        ("ga", GeneticAlgorithm),
        ("nlopt", NloptOptimizer),
        ("emcee", EmceeSampler),
        ("de", DifferentialEvolution),
    ]:
        comp = bf.component("optimizer", name)
        assert type(comp) is cls and comp.kind == "optimizer"
    with pytest.raises(ConfigError, match="elite_count"):
        bf.component("optimizer", "ga", population=10, elite_count=10)
    with pytest.raises(ConfigError):
        bf.component("optimizer", "ga", populaton=10)


def test_bad_problem_is_reported_by_name():
    pr, _, _ = make_problem(lower=np.array([-5.0, 5.0, 0.0]))
    with pytest.raises(ValueError, match="'b'"):
        GeneticAlgorithm().minimize(pr)
    pr, _, _ = make_problem(lower=np.array([-5.0, -5.0, 0.2]), upper=np.array([5.0, 5.0, 0.8]))
    with pytest.raises(ValueError, match="integer parameter 'n'"):
        DifferentialEvolution().minimize(pr)


def test_emcee_noise_epsilon_is_the_seed_spread_at_the_best_initial_walker():
    pr, rec, _ = make_problem(budget=200, seed=8)
    seen = []

    def spread(x, k):
        seen.append((np.array(x), k))
        return 0.2 + 0.05 * np.arange(k)  # sd (ddof 1) of 0.2, 0.25, ... 0.55 over 8 seeds

    pr.seed_spread = spread
    res = EmceeSampler(steps=5, epsilon_scale=2.0).minimize(pr)  # "noise" is the default
    x0, f0 = rec.batches[0]
    assert len(seen) == 1 and seen[0][1] == 8
    assert np.array_equal(seen[0][0], x0[np.argmin(f0)])  # measured at the best initial walker
    assert res.diagnostics["epsilon"] == pytest.approx(2.0 * np.std(0.05 * np.arange(8), ddof=1))
    assert res.diagnostics["epsilon_rule"].startswith("noise")
    # a deterministic model (no seed spread) falls back to the auto rule
    pr2, rec2, _ = make_problem(budget=200, seed=8)
    pr2.seed_spread = lambda x, k: np.full(k, 0.3)
    res2 = EmceeSampler(steps=5).minimize(pr2)
    f0 = rec2.batches[0][1]
    assert res2.diagnostics["epsilon"] == pytest.approx(1.4826 * np.median(np.abs(f0 - np.median(f0))))
