"""The genetic algorithm of the papers (Matlab ``ga`` style, Potapov et al. 2016, 2017).

One generation of ``population`` individuals is

* the ``elite_count`` best individuals of the previous generation, copied unchanged (their
  distances are kept, not recomputed: the objective is deterministic for a fixed SSM seed);
* ``round(crossover_fraction * (population - elite_count))`` crossover children (scattered:
  each gene from one of two parents picked by a fair coin; or intermediate: a random point on
  the segment between the parents);
* the rest mutation children: Gaussian steps on a random subset of genes (``mutation_rate``)
  whose standard deviation, relative to each parameter's initial range, shrinks geometrically
  from ``mutation_scale`` in the first generation to ``mutation_scale_final`` in the last;
  steps are reflected at the bounds, so every child is feasible; integer genes take whole steps
  (at least one unit when the gene mutates), so integer parameters stay integral.

Parents are chosen by stochastic uniform selection on rank-scaled fitness (Matlab's default,
expectation proportional to ``1/sqrt(rank)``) or by tournaments. The initial population is spread
over the *initial* box (``init_lower``/``init_upper``) with a scrambled low-discrepancy sequence;
the search itself ranges over the global bounds. Each generation's new individuals are
evaluated in one ``problem.evaluate`` call, so they run in parallel.

The run stops after ``generations`` generations, after ``stall_generations`` generations in a
row without the best distance improving by more than ``function_tolerance * max(1, |best|)``,
or when the problem stops (budget, wall time, target).
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
from pydantic import Field, model_validator

from bforest_core.interfaces import Optimizer, OptimizeResult, Problem

from .box import (
    MAX_POINTS,
    UNLIMITED,
    Box,
    History,
    NoiseSetting,
    NoiseStop,
    OptimizerSettings,
    SamplingName,
    finite_stats,
    make_result,
    noise_stop_fields,
    sampling_field,
)

_NOISE = noise_stop_fields()


class GASettings(OptimizerSettings):
    """Settings of the ``ga`` optimiser (defaults: the papers' population 40, 30 generations)."""

    population: int = Field(40, ge=4, le=MAX_POINTS, description="individuals per generation")
    generations: int = Field(30, ge=1, description="maximum number of generations after the initial one")
    elite_count: int | None = Field(
        None,
        ge=0,
        le=MAX_POINTS,
        description="best individuals copied unchanged into the "
        "next generation (default: 5 % of the population, at least 1)",
    )
    crossover_fraction: float = Field(
        0.8, ge=0.0, le=1.0, description="share of the non-elite children made by crossover (the rest by mutation)"
    )
    crossover: Literal["scattered", "intermediate"] = Field(
        "scattered",
        description="scattered: each gene from either parent; intermediate: a random "
        "point between the parents (integer genes rounded)",
    )
    selection: Literal["stochastic_uniform", "tournament"] = Field(
        "stochastic_uniform",
        description="parent selection: stochastic uniform sampling on "
        "rank-scaled fitness, or tournaments of tournament_size",
    )
    tournament_size: int = Field(
        4, ge=2, le=MAX_POINTS, description="individuals per tournament (selection = tournament)"
    )
    mutation_rate: float = Field(
        0.2,
        gt=0.0,
        le=1.0,
        description="probability that a gene of a mutation child is mutated (at least one gene always is)",
    )
    mutation_scale: float = Field(
        0.3,
        gt=0.0,
        description="standard deviation of a mutation step in "
        "generation 1, as a fraction of the initial range of the parameter",
    )
    mutation_scale_final: float = Field(
        0.02,
        gt=0.0,
        description="the same in the last generation; the step shrinks geometrically from mutation_scale to this",
    )
    stall_generations: int | None = Field(
        10, ge=1, description="stop after this many generations without improvement (None: never)"
    )
    function_tolerance: float = Field(
        1e-6, ge=0.0, description="an improvement smaller than function_tolerance * max(1, |best|) does not count"
    )
    init_sampling: SamplingName = sampling_field("halton")
    patience: int | None = _NOISE["patience"]
    noise: NoiseSetting = _NOISE["noise"]
    noise_seeds: int = _NOISE["noise_seeds"]

    @model_validator(mode="after")
    def _elite_fits(self):
        if self.elite_count is not None and self.elite_count >= self.population:
            raise ValueError(f"elite_count ({self.elite_count}) must be below population ({self.population})")
        return self

    def n_elite(self) -> int:
        if self.elite_count is not None:
            return self.elite_count
        return max(1, math.ceil(0.05 * self.population))


def reflect(X: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Fold values back into ``[lo, hi]`` by reflection at the bounds (whole numbers stay whole
    when the bounds are whole)."""
    w = hi - lo
    with np.errstate(invalid="ignore", divide="ignore"):
        t = np.mod(X - lo, 2 * w)
    t = np.where(t > w, 2 * w - t, t)
    return np.where(w > 0, lo + t, lo)


class GeneticAlgorithm(Optimizer):
    """Genetic algorithm with elitism, crossover, shrinking Gaussian mutation and native integers.

    See the module docstring for the scheme. Deterministic given ``problem.seed`` and the values
    ``problem.evaluate`` returns.

    Returns
    -------
    OptimizeResult
        ``x``/``fun`` the best individual seen; ``history`` one record per generation
        (``generation``, ``best``, ``mean``, ``median``, ``std`` of the finite distances of the
        generation, ``n_new`` points evaluated, ``sigma`` mutation scale, ``stall``,
        ``n_evaluations``); ``diagnostics`` the final population and its distances.
    """

    name = "ga"
    summary = "genetic algorithm of the papers (Matlab ga style, integer-aware)"
    Settings = GASettings

    @classmethod
    def budget_settings(cls, settings, budget):
        """No generation limit and no stall stop: the budget ends the run."""
        return {**settings, "generations": UNLIMITED, "stall_generations": UNLIMITED}

    def minimize(self, problem: Problem) -> OptimizeResult:
        s: GASettings = self.settings
        ev = Box(problem)
        log = History(problem)
        init_ss, breed_ss = np.random.SeedSequence([int(problem.seed), 0x6A]).spawn(2)
        rng = np.random.default_rng(breed_ss)
        n, n_elite = s.population, s.n_elite()
        pop = ev.sample_init(n, np.random.default_rng(init_ss), s.init_sampling)
        f = ev(pop)
        self._log(log, ev, 0, f, n, sigma=s.mutation_scale, stall=0)
        noise_stop = NoiseStop(problem, s.patience, s.noise, s.noise_seeds)
        noise_stop(ev)
        prev_best, stall, reason, done = ev.best_f, 0, f"{s.generations} generations done", 0
        for g in range(1, s.generations + 1):
            if ev.stopped:
                break
            order = np.argsort(f, kind="stable")
            pop, f = pop[order], f[order]
            sigma = self._sigma(g)
            kids = self._breed(pop, f, n - n_elite, sigma, ev, rng)
            fk = ev(kids)
            pop = np.concatenate([pop[:n_elite], kids])
            f = np.concatenate([f[:n_elite], fk])
            tol = s.function_tolerance * max(1.0, abs(prev_best)) if math.isfinite(prev_best) else 0.0
            if ev.best_f < prev_best - tol or (not math.isfinite(prev_best) and math.isfinite(ev.best_f)):
                stall = 0
            else:
                stall += 1
            prev_best = min(prev_best, ev.best_f)
            done = g
            self._log(log, ev, g, f, len(kids), sigma=sigma, stall=stall)
            if s.stall_generations is not None and stall >= s.stall_generations:
                reason = f"no improvement in {stall} generations"
                break
            if noise_stop(ev):
                reason = noise_stop.reason
                break
        diagnostics = {
            "generations": done,
            "elite_count": n_elite,
            "final_population": pop,
            "final_distances": f,
            "seed_noise": noise_stop.noise,
        }
        return make_result(ev, log, reason, diagnostics)

    @staticmethod
    def _log(log, ev, g, f, n_new, *, sigma, stall):
        log(
            ev,
            generation=g,
            **finite_stats(f, "mean", "median", "std"),
            n_new=int(n_new),
            n_failed=int(np.count_nonzero(~np.isfinite(f))),
            sigma=float(sigma),
            stall=int(stall),
        )

    def expected_evaluations(self, dim: int) -> int:
        """Population x (generations + 1): what the run evaluates when no stop comes first."""
        return self.settings.population * (self.settings.generations + 1)

    def _sigma(self, g: int) -> float:
        """Mutation scale of generation ``g`` (1-based): geometric from the first to the final."""
        s: GASettings = self.settings
        t = (g - 1) / max(1, s.generations - 1)
        return s.mutation_scale * (s.mutation_scale_final / s.mutation_scale) ** t

    # ------------------------------------------------------------------ operators
    def _select(self, f: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
        """Indices of ``k`` parents; ``f`` is sorted ascending (best first)."""
        s: GASettings = self.settings
        n = f.size
        if s.selection == "tournament":
            cand = rng.integers(0, n, size=(k, s.tournament_size))
            return cand.min(axis=1)  # rows are sorted best-first, so the smallest index wins
        # rank scaling (Matlab fitscalingrank): expectation 1/sqrt(rank); failures get none
        expect = 1.0 / np.sqrt(np.arange(1, n + 1))
        finite = np.isfinite(f)
        if finite.sum() >= 2:
            expect = np.where(finite, expect, 0.0)
        cum = np.cumsum(expect / expect.sum())
        cum[-1] = 1.0
        pos = (rng.random() + np.arange(k)) / k  # stochastic universal sampling
        idx = np.minimum(np.searchsorted(cum, pos, side="right"), n - 1)
        return rng.permutation(idx)

    def _breed(self, pop, f, n_kids, sigma, ev: Box, rng) -> np.ndarray:
        s: GASettings = self.settings
        p = pop.shape[1]
        n_x = int(round(s.crossover_fraction * n_kids))
        n_m = n_kids - n_x
        parents = pop[self._select(f, 2 * n_x + n_m, rng)]
        a, b, m = parents[:n_x], parents[n_x : 2 * n_x], parents[2 * n_x :]
        # crossover
        if s.crossover == "scattered":
            xkids = np.where(rng.random((n_x, p)) < 0.5, a, b)
        else:
            xkids = a + rng.random((n_x, p)) * (b - a)
            xkids = np.where(ev.integer, np.rint(xkids), xkids)
        # mutation: Gaussian steps on a random subset of genes (never none)
        mask = rng.random((n_m, p)) < s.mutation_rate
        forced = rng.integers(0, p, size=n_m)
        mask[np.arange(n_m), forced] |= ~mask.any(axis=1)
        step = rng.standard_normal((n_m, p)) * (sigma * ev.init_width)
        sign = np.where(rng.random((n_m, p)) < 0.5, -1.0, 1.0)
        istep = np.rint(step)
        istep = np.where(istep == 0, sign, istep)  # a mutating integer gene moves by >= 1
        step = np.where(ev.integer, istep, step)
        mkids = reflect(m + np.where(mask, step, 0.0), ev.lower, ev.upper)
        return ev.project(np.concatenate([xkids, mkids]))
