"""CMA-ES (the ``cma`` package) on the parameter box, with restarts and a noise-aware stop.

The search runs in the unit cube (each parameter scaled by its bounds) with cma's own bound
handling, so one step size suits parameters of any unit. Integer parameters: CMA-ES searches
their continuous relaxation (the box widened by half a step at each end, so every whole number
gets the same share) and the point is rounded to the nearest whole number when it is evaluated;
repeats are answered by the fit's cache. Each generation is one batch through
``problem.evaluate`` (so it runs on the executor in parallel). Restarts double the population
(IPOP-CMA-ES, Auger & Hansen 2005). Everything is seeded from ``problem.seed``: given the same
returned values the run asks for the same points, so a resumed fit replays.

``surrogate = "lq"`` is lq-CMA-ES (Hansen 2019, GECCO; cma's ``fitness_models.LQModel``): a
linear, then diagonal-quadratic, then full quadratic regression on the best points evaluated so
far. (1) Its optimum joins every generation (cma's ``inject``), a point where the regression,
which averages the model seeds' noise over many evaluations, expects the lowest distance.
(2) Each generation is grown in the model's order; once the model's ranking of the points just
grown, predicted before it saw them, agrees with their true distances (Kendall tau >= 0.85 over at
least 6 points), the rest of the generation is ranked by the model instead of being grown. Unlike
cma's own ``SurrogatePopulation``, which checks the ranking in-sample (a full quadratic with few
points fits the seed noise and then passes) and evaluates one point at a time, the check here is
out-of-sample and the true evaluations go out in batches of ``surrogate_batch`` (the workers), so
no worker waits. On a smooth distance (2) saves most evaluations; on a real tree's distance the
seed noise keeps tau at 0.2-0.5, nearly every point is grown, and the gain is (1) (see
``docs/performance.md``).
"""
from __future__ import annotations

import math
from typing import Literal, Optional, Union

import numpy as np
from pydantic import Field

from bforest_core.interfaces import OptimizeResult, Optimizer, Problem

from ._common import (BoxEvaluator, History, NoiseStop, OptimizerSettings, finite_stats, make_result,
                      noise_stop_fields)

_NOISE = noise_stop_fields()


class CMASettings(OptimizerSettings):
    population: Optional[int] = Field(None, ge=4, description="points per generation (default cma's 4 + 3 ln p)")
    sigma0: float = Field(0.3, gt=0, le=1, description="initial step size, as a fraction of each parameter's range")
    restarts: int = Field(1, ge=0, description="restarts with doubled population after a run converges (IPOP)")
    init_design: int = Field(0, ge=0, description="points of a scrambled Sobol' design over the initial box "
                             "evaluated first; CMA-ES then starts at the best of them instead of the box's "
                             "centre (0: no design)")
    surrogate: Literal["none", "lq"] = Field("none", description="'lq': lq-CMA-ES, a quadratic regression of "
                                             "the distance adds its optimum to every generation and, where it "
                                             "ranks points as the truth does, stands in for growing them (see "
                                             "the module); 'none': every point is grown")
    surrogate_batch: int = Field(2, ge=1, description="with a surrogate: points grown together (set it to the "
                                 "executor's workers)")
    max_generations: Optional[int] = Field(None, ge=1, description="generations per run (default: until cma stops)")
    tolfun: float = Field(1e-4, ge=0, description="cma's stop when the distances of a generation differ by less")
    patience: Optional[int] = _NOISE["patience"]
    noise: Union[float, str] = _NOISE["noise"]
    noise_seeds: int = _NOISE["noise_seeds"]


class CMAES(Optimizer):
    """Covariance matrix adaptation evolution strategy with IPOP restarts.

    Log records (one per generation): ``generation``, ``run`` (restart index), ``population``,
    ``sigma`` (cma's step size in the unit cube), ``mean``, ``median``, ``best``; with an
    ``init_design``, generation 0 (run -1, no sigma) is the design.
    """

    name = "cma"
    summary = "CMA-ES (cma package): bounds, integer rounding, IPOP restarts, noise-aware stop"
    Settings = CMASettings

    def expected_evaluations(self, dim: int) -> int | None:
        s = self.settings
        if s.max_generations is None or s.surrogate != "none":
            return None
        pop = s.population or 4 + int(3 * math.log(dim))
        return s.init_design + sum(pop * 2 ** r * s.max_generations for r in range(s.restarts + 1))

    def minimize(self, problem: Problem) -> OptimizeResult:
        import cma
        s: CMASettings = self.settings
        ev = BoxEvaluator(problem)
        log = History(problem)
        stop = NoiseStop(problem, s.patience, s.noise, s.noise_seeds)
        lo, hi = ev.relaxed_bounds("bounds")
        ilo, ihi = ev.relaxed_bounds("init")
        x0 = ((ilo + ihi) / 2 - lo) / (hi - lo)
        pop0 = s.population or 4 + int(3 * math.log(ev.dim))
        surrogate = _LQSurrogate(s.surrogate_batch) if s.surrogate == "lq" else None

        def grow(U):  # unit cube -> parameters -> distances
            return ev(lo + U * (hi - lo))

        reason, generation, runs = "cma stopped", 0, []
        if s.init_design:
            # generation 0: a space-filling look at the initial box, so the search starts in its
            # best region rather than at a centre that may be poor (the points count in the budget)
            X = ev.sample_init(s.init_design, np.random.default_rng([int(problem.seed), 0xC3A]), "sobol")
            f = ev(X)
            log(ev, generation=0, run=-1, population=len(X), sigma=None, **finite_stats(f, "mean", "median"))
            if np.isfinite(f).any():
                x0 = (X[int(np.argmin(f))] - lo) / (hi - lo)
        for run in range(s.restarts + 1):
            opts = {"bounds": [0.0, 1.0], "popsize": pop0 * 2 ** run, "seed": int(problem.seed) * 1009 + run + 1,
                    "verbose": -9, "tolfun": s.tolfun, "tolx": 1e-6}
            if s.max_generations is not None:
                opts["maxiter"] = s.max_generations
            es = cma.CMAEvolutionStrategy(x0, s.sigma0, opts)
            while not es.stop() and not ev.stopped:
                U = np.asarray(es.ask())
                f, extra = surrogate(U, grow) if surrogate else (grow(U), {})
                finite = f[np.isfinite(f)]
                worst = finite.max() + 1.0 if finite.size else 1e6
                es.tell(list(U), list(np.where(np.isfinite(f), f, worst)))
                if surrogate and surrogate.model.size > ev.dim:
                    es.inject([np.clip(surrogate.model.xopt, 0.0, 1.0)])  # the model's optimum, as lq-CMA-ES
                generation += 1
                log(ev, generation=generation, run=run, population=len(U), sigma=float(es.sigma),
                    **extra, **finite_stats(f, "mean", "median"))
                if stop(ev):
                    reason = stop.reason
                    break
            runs.append({"run": run, "population": pop0 * 2 ** run, "generations": int(es.countiter),
                         "stop": {k: (float(v) if isinstance(v, (int, float)) else str(v))
                                  for k, v in dict(es.stop()).items()}})
            if stop.reason or ev.stopped:
                break
            reason = f"cma converged ({', '.join(dict(es.stop())) or 'stopped'}) after {run + 1} run(s)"
        return make_result(ev, log, reason, {"generations": generation, "runs": runs,
                                             "seed_noise": stop.noise})


class _LQSurrogate:
    """lq-CMA-ES's population evaluation (after cma's ``SurrogatePopulation.__call__``: its model,
    settings and growing schedule, with an out-of-sample rank check and batches; see the module):
    ``surrogate(U, grow)`` returns the values CMA-ES is told and a log record (``grown``: points
    grown, ``tau``: the rank agreement of the model's predictions with them)."""

    def __init__(self, batch: int, min_true: int = 6):
        from cma.fitness_models import LQModel, SurrogatePopulationSettings
        self.model, self.batch, self.S = LQModel(), int(batch), SurrogatePopulationSettings
        self.min_true = int(min_true)

    def __call__(self, U: np.ndarray, grow) -> tuple[np.ndarray, dict]:
        m, S, lam = self.model, self.S, len(U)
        if S.model_max_size_factor * lam > m.settings.max_absolute_size:
            if m.settings.max_absolute_size:  # a restart's larger population: start a new model
                m.reset()
            m.settings.max_absolute_size = S.model_max_size_factor * lam
        f, pred = np.full(lam, np.inf), np.full(lam, np.nan)
        done = np.zeros(lam, bool)
        # cma's first count, 1 + max(2 % of the population, 3 / truncation_ratio - model size), is
        # at most 5 below 250 points: the rank check's minimum decides
        number = max(self.min_true, int(1 + lam * S.min_evals_percent / 100))
        tau = 0.0
        while not done.all():
            # the model's values (NaN, and grown in CMA-ES's order, while it has too few points)
            F = np.array([m.eval(u) for u in U], float) if m.size > U.shape[1] + 1 else np.full(lam, np.nan)
            order = np.argsort(np.nan_to_num(F), kind="stable")
            todo = [int(i) for i in order if not done[i]]
            k = max(number - int(done.sum()), 1)
            k = min(len(todo), -(-k // self.batch) * self.batch)  # whole batches: no worker waits
            idx = todo[:k]
            pred[idx] = F[idx]  # what the model said before it saw these points
            f[idx] = grow(U[idx])
            done[idx] = True
            for i in idx:
                if np.isfinite(f[i]):
                    m.add_data_row(U[i], float(f[i]))
            m.sort(int(done.sum()))
            ok = done & np.isfinite(f) & np.isfinite(pred)
            tau = _kendall(pred[ok], f[ok]) if ok.sum() >= self.min_true else 0.0
            if tau >= S.tau_truth_threshold:
                break
            number = int(done.sum()) + int(math.ceil(done.sum() / 2))
        m.sort(S.model_sort_globally or int(done.sum()))
        m.adapt_max_relative_size(tau)
        extra = {"grown": int(done.sum()), "tau": float(tau)}
        if done.all() or not np.isfinite(f).any():
            return f, extra
        F = np.array([m.eval(u) for u in U], float)  # the model's values, offset to the best grown one
        return F - F.min() + float(np.min(f[np.isfinite(f)])), extra


def _kendall(a: np.ndarray, b: np.ndarray) -> float:
    from scipy.stats import kendalltau
    t = kendalltau(a, b).statistic
    return float(t) if np.isfinite(t) else 0.0
