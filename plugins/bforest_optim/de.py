"""Differential evolution (``scipy.optimize.differential_evolution``).

Run vectorised with deferred updating: scipy hands each whole generation to the objective at
once, which passes it to ``problem.evaluate`` in one call (so it runs in parallel). Integer
parameters use scipy's ``integrality``; the initial population is spread over the initial box.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field

from bforest_core.interfaces import Optimizer, OptimizeResult, Problem

from .box import (
    MAX_POINTS,
    UNLIMITED,
    Box,
    History,
    OptimizerSettings,
    SamplingName,
    StopOptimization,
    finite_stats,
    make_result,
    sampling_field,
)

Strategy = Literal[
    "best1bin",
    "best1exp",
    "rand1bin",
    "rand1exp",
    "rand2bin",
    "rand2exp",
    "randtobest1bin",
    "randtobest1exp",
    "currenttobest1bin",
    "currenttobest1exp",
    "best2bin",
    "best2exp",
]


class DESettings(OptimizerSettings):
    """Settings of the ``de`` optimiser (scipy's defaults except ``polish``)."""

    popsize: int = Field(15, ge=1, le=MAX_POINTS // 20, description="population = popsize * dimension (at least 5)")
    maxiter: int = Field(100, ge=1, description="maximum number of generations")
    strategy: Strategy = Field("best1bin", description="scipy differential evolution strategy")
    mutation: float | tuple[float, float] = Field(
        (0.5, 1.0), description="differential weight, or a (min, max) range for dithering"
    )
    recombination: float = Field(0.7, ge=0, le=1, description="crossover probability")
    tol: float = Field(0.01, ge=0, description="relative convergence tolerance on the population's distances")
    atol: float = Field(0.0, ge=0, description="absolute convergence tolerance")
    polish: bool = Field(
        False,
        description="polish the best point with L-BFGS-B (finite differences: "
        "one evaluation at a time, rarely useful for a stochastic-model distance)",
    )
    init_sampling: SamplingName = sampling_field("lhs")


class DifferentialEvolution(Optimizer):
    """``scipy.optimize.differential_evolution``, one ``problem.evaluate`` call per generation.

    Seeded with ``numpy.random.default_rng`` from ``problem.seed``. Stops at ``maxiter``, at
    scipy's convergence test (``std(D) <= atol + tol * |mean(D)|``) or when the problem stops.

    Returns
    -------
    OptimizeResult
        ``history`` one record per generation (``generation``, ``mean`` distance of the
        population, ``convergence``); ``diagnostics`` scipy's message and generations.
    """

    name = "de"
    summary = "scipy differential evolution (vectorised generations, integrality)"
    Settings = DESettings

    @classmethod
    def budget_settings(cls, settings, budget):
        """No generation limit (``maxiter``): the budget ends the run."""
        return {**settings, "maxiter": UNLIMITED}

    def minimize(self, problem: Problem) -> OptimizeResult:
        from scipy.optimize import differential_evolution

        s: DESettings = self.settings
        ev = Box(problem)
        log = History(problem)
        init_ss, de_ss = np.random.SeedSequence([int(problem.seed), 0xDE]).spawn(2)
        n_pop = max(5, s.popsize * ev.dim)
        init = ev.sample_init(n_pop, np.random.default_rng(init_ss), s.init_sampling)

        def func(Xt):  # scipy's vectorised layout: (p, S) in, (S,) out
            if ev.stopped:
                raise StopOptimization
            return ev(np.asarray(Xt).T)

        def callback(intermediate_result):
            e = np.asarray(intermediate_result.population_energies, float)
            log(
                ev,
                generation=int(intermediate_result.nit),
                **finite_stats(e, "mean"),
                convergence=float(getattr(intermediate_result, "convergence", np.nan)),
            )
            return ev.stopped

        message, nit = "", None
        try:
            res = differential_evolution(
                func,
                bounds=list(zip(ev.lower, ev.upper)),
                strategy=s.strategy,
                maxiter=s.maxiter,
                popsize=s.popsize,
                tol=s.tol,
                atol=s.atol,
                mutation=s.mutation,
                recombination=s.recombination,
                rng=np.random.default_rng(de_ss),
                callback=callback,
                polish=s.polish,
                init=init,
                updating="deferred",
                vectorized=True,
                integrality=ev.integer,
            )
            message, nit = str(res.message), int(res.nit)
        except StopOptimization:
            message = "stopped"
        diagnostics = {"message": message, "generations": nit, "population": n_pop}
        return make_result(ev, log, f"differential evolution: {message}", diagnostics)
