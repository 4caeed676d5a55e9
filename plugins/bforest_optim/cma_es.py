"""CMA-ES (the ``cma`` package) on the parameter box, with restarts and a noise-aware stop.

The search runs in the unit cube (each parameter scaled by its bounds) with cma's own bound
handling, so one step size suits parameters of any unit. Integer parameters: CMA-ES searches
their continuous relaxation (the box widened by half a step at each end, so every whole number
gets the same share) and the point is rounded to the nearest whole number when it is evaluated;
repeats are answered by the fit's cache. Each generation is one batch through
``problem.evaluate`` (so it runs on the executor in parallel). Restarts double the population
(IPOP-CMA-ES, Auger & Hansen 2005). Everything is seeded from ``problem.seed``: given the same
returned values the run asks for the same points, so a resumed fit replays.
"""
from __future__ import annotations

import math
from typing import Optional, Union

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
        if s.max_generations is None:
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
                f = ev(lo + U * (hi - lo))
                finite = f[np.isfinite(f)]
                worst = finite.max() + 1.0 if finite.size else 1e6
                es.tell(list(U), list(np.where(np.isfinite(f), f, worst)))
                generation += 1
                log(ev, generation=generation, run=run, population=len(U), sigma=float(es.sigma),
                    **finite_stats(f, "mean", "median"))
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
