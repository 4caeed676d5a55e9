"""CMA-ES (the ``cma`` package) on the parameter box, with restarts and a noise-aware stop.

The search runs in the unit cube (each parameter scaled by its bounds) with cma's own bound
handling, so one step size suits parameters of any unit. Integer parameters: CMA-ES searches
their continuous relaxation (the box widened by half a step at each end, so every whole number
gets the same share) and the point is rounded to the nearest whole number when it is evaluated;
repeats are answered by the fit's cache. Each generation is one batch through
``problem.evaluate`` (so it runs on the executor in parallel). Restarts double the population
(IPOP-CMA-ES, Auger & Hansen 2005). ``starts`` > 1 races several independent runs from distinct
points of the design with successive halving (:class:`_Race`): on a noisy distance one run can
settle in a poor basin on one machine and a good one on another; racing several keeps the answer
from hinging on one trajectory. With ``grow_together`` the racing starts take their turns
together: one generation of each, their points grown as one batch (each generation is a
generator of the batches it needs, :func:`_grow_steps`), so the workers do not wait on one
start's slowest tree. Everything is seeded from ``problem.seed``: given the same
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
``docs/notes/2026-11-25-lq-cma-es.md``).
"""

from __future__ import annotations

import math
from typing import Literal, Optional

import numpy as np
from pydantic import Field

from bforest_core.interfaces import Optimizer, OptimizeResult, Problem, RecipePart, RecipePlan

from .box import (
    MAX_POINTS,
    Box,
    History,
    NoiseSetting,
    NoiseStop,
    OptimizerSettings,
    finite_stats,
    make_result,
    noise_stop_fields,
)

_NOISE = noise_stop_fields()


class CMASettings(OptimizerSettings):
    population: Optional[int] = Field(
        None, ge=4, le=MAX_POINTS, description="points per generation (default cma's 4 + 3 ln p)"
    )
    sigma0: float = Field(0.3, gt=0, le=1, description="initial step size, as a fraction of each parameter's range")
    restarts: int = Field(1, ge=0, description="restarts with doubled population after a run converges (IPOP)")
    init_design: int = Field(
        0,
        ge=0,
        le=MAX_POINTS,
        description="points of a scrambled Sobol' design over the initial box "
        "evaluated first (with [start] estimator: draws of its posterior for the target instead); "
        "CMA-ES then starts at the best of them instead of the box's centre (0: no design)",
    )
    starts: int = Field(
        1,
        ge=1,
        le=MAX_POINTS,
        description="independent CMA-ES runs raced against each other: they start at "
        "the best distinct points of the init_design (then at Sobol' points of the initial box), "
        "take turns generation by generation, and successive halving drops the worse half at "
        "equal shares of the budget, so the answer does not hinge on one trajectory (1: one run)",
    )
    finalists: int = Field(
        1,
        ge=1,
        description="starts the race keeps to the end of the budget: successive halving stops "
        "dropping when this many are left, and each runs on as a search of its own (the answer is "
        "the best point of all, or of [select]'s re-scoring). 2 of 4 starts: two searches, each "
        "with the evaluations the one winner of 2 starts gets",
    )
    grow_together: bool = Field(
        False,
        description="with starts > 1: the starts still racing take their turns together, "
        "each one generation, and the points they grow at each step go to the workers as one "
        "batch, so the workers are not left waiting on one start's slowest tree; the run is as "
        "deterministic as with one start at a time, but the points differ (the race and the "
        "budget meet the generations at other places). false: one start's generation at a time",
    )
    surrogate: Literal["none", "lq"] = Field(
        "none",
        description="'lq': lq-CMA-ES, a quadratic regression of "
        "the distance adds its optimum to every generation and, where it "
        "ranks points as the truth does, stands in for growing them (see "
        "the module); 'none': every point is grown",
    )
    surrogate_batch: int = Field(
        2, ge=1, le=MAX_POINTS, description="with a surrogate: points grown together (set it to the executor's workers)"
    )
    max_generations: Optional[int] = Field(None, ge=1, description="generations per run (default: until cma stops)")
    tolfun: float = Field(1e-4, ge=0, description="cma's stop when the distances of a generation differ by less")
    patience: Optional[int] = _NOISE["patience"]
    noise: NoiseSetting = _NOISE["noise"]
    noise_seeds: int = _NOISE["noise_seeds"]


class CMAES(Optimizer):
    """Covariance matrix adaptation evolution strategy with IPOP restarts and raced starts.

    Log records (one per generation): ``generation``, ``run`` (restart index), ``population``,
    ``sigma`` (cma's step size in the unit cube), ``mean``, ``median``, ``best``; with
    ``starts`` > 1 also ``start``; with an ``init_design``, generation 0 (run -1, no sigma) is the
    design.
    """

    name = "cma"
    summary = "CMA-ES (cma package): bounds, integer rounding, IPOP restarts, noise-aware stop"
    Settings = CMASettings

    def takes_start(self) -> bool:
        return self.settings.init_design > 0

    def draft_recipe(self, plan: RecipePlan) -> RecipePart:
        """The robust search of the real-tree recipes (docs/validation.md section 4): lq-CMA-ES with
        a first step of 0.15 of each range, a Sobol' design, two starts from its best distinct
        points. With one model seed per evaluation the objective is noisier: generations of 32
        (a step that stays wide and moves with the shape of the whole landscape) after 64 Sobol'
        points, both starts running to the end of the budget together (the pine recipes'); with
        more seeds, generations of 16 after 32 points, the starts raced by successive halving. A
        refinement of an amortised posterior (``plan.start``): 32 draws, two runs of 16 together."""
        together = plan.start or plan.draft.seeds == 1
        population, design = (32, 64) if plan.draft.seeds == 1 and not plan.start else (16, 32)
        settings = [
            ("population", population, None),
            ("restarts", 4, None),
            ("sigma0", 0.15, None),
            ("surrogate", "lq", None),
            ("surrogate_batch", 2, None),
            ("init_design", design, None),
            ("starts", 2, None),
        ]
        if together:
            settings += [("finalists", 2, None), ("grow_together", True, None)]
        if plan.start:
            why = (
                f"A short refinement of the estimator's posterior ([start]): {design} draws of it for this tree, "
                f"then 2 lq-CMA-ES runs of {population} points a generation from the best distinct ones, taking "
                "their turns together."
            )
        elif together:
            why = (
                f"A search that does not hinge on one trajectory: {design} Sobol' points over the box, then 2 "
                f"lq-CMA-ES runs of {population} points a generation from the best distinct ones, each to the end "
                "of the budget, taking their turns together (their points go to the workers as one batch); a run "
                "that converges restarts with a doubled population."
            )
        else:
            why = (
                f"A search that does not hinge on one trajectory: {design} Sobol' points over the box, 2 lq-CMA-ES "
                "runs from the best distinct ones raced by successive halving, each restarting with a doubled "
                "population once it converges."
            )
        return RecipePart(self.name, settings, why)

    def expected_evaluations(self, dim: int) -> int | None:
        s = self.settings
        if s.max_generations is None or s.surrogate != "none":
            return None
        pop = s.population or 4 + int(3 * math.log(dim))
        return s.init_design + s.starts * sum(pop * 2**r * s.max_generations for r in range(s.restarts + 1))

    def minimize(self, problem: Problem) -> OptimizeResult:
        s: CMASettings = self.settings
        ev = Box(problem)
        log = History(problem)
        stop = NoiseStop(problem, s.patience, s.noise, s.noise_seeds)
        lo, hi = ev.relaxed_bounds("bounds")
        ilo, ihi = ev.relaxed_bounds("init")
        x0 = ((ilo + ihi) / 2 - lo) / (hi - lo)
        pop0 = s.population or 4 + int(3 * math.log(ev.dim))

        def grow(U):  # unit cube -> parameters -> distances
            return ev(lo + U * (hi - lo))

        X = f = None
        if s.init_design:
            # generation 0: a space-filling look at the initial box, so the search starts in its
            # best region rather than at a centre that may be poor (the points count in the budget)
            X = ev.initial_design(s.init_design, np.random.default_rng([int(problem.seed), 0xC3A]), "sobol")
            f = ev(X)
            log(ev, generation=0, run=-1, population=len(X), sigma=None, **finite_stats(f, "mean", "median"))
            if np.isfinite(f).any():
                x0 = (X[int(np.argmin(f))] - lo) / (hi - lo)
        if s.starts > 1:
            U0 = None if X is None else (X - lo) / (hi - lo)
            starts = _start_points(U0, f, s.starts, ilo, ihi, lo, hi, int(problem.seed))
        else:
            starts = [x0]
        slots = [
            _Start(j, u, _LQSurrogate(s.surrogate_batch) if s.surrogate == "lq" else None) for j, u in enumerate(starts)
        ]
        race = _Race(slots, problem, s.finalists)
        reason, generation = "cma stopped", 0
        while race.active and not ev.stopped:
            turn = list(race.active)
            # one start's generation at a time, or one generation of every start still racing
            for group in [turn] if s.grow_together else [[sl] for sl in turn]:
                steps = []
                for slot in group:
                    if slot not in race.active:  # dropped by the race earlier in this round
                        continue
                    if slot.es is None or slot.es.stop():
                        if slot.es is not None:
                            slot.finish()
                            if slot.run >= s.restarts:
                                race.active.remove(slot)
                                continue
                            slot.run += 1
                        slot.es = self._es(slot, pop0, int(problem.seed))
                    generation += 1
                    steps.append(self._generation(slot, ev, log, generation))
                if not steps:
                    continue
                _grow_steps(steps, grow)
                if any(stop(ev) for _ in steps):
                    reason = stop.reason
                    break
                if ev.stopped:
                    break
                race.halve()
            if stop.reason or ev.stopped:
                break
        else:
            done = [sl for sl in slots if sl.runs]
            last = dict(done[-1].es.stop()) if done and done[-1].es is not None else {}
            reason = f"cma converged ({', '.join(last) or 'stopped'}) after {sum(len(sl.runs) for sl in slots)} run(s)"
        for slot in slots:
            if slot.es is not None and (not slot.runs or slot.runs[-1]["run"] != slot.run):
                slot.finish()
        runs = [r for sl in slots for r in sl.runs]
        diag = {"generations": generation, "runs": runs, "seed_noise": stop.noise}
        if s.starts > 1:
            diag["starts"] = [
                {
                    "start": sl.j,
                    "x0": (lo + sl.x0 * (hi - lo)).tolist(),
                    "best": sl.best_f,
                    "dropped_after": sl.dropped_after,
                }
                for sl in slots
            ]
        return make_result(ev, log, reason, diag)

    def _es(self, slot: _Start, pop0: int, seed: int):
        import cma

        s = self.settings
        opts = {
            "bounds": [0.0, 1.0],
            "popsize": pop0 * 2**slot.run,
            "seed": seed * 1009 + slot.run + 1 + 7919 * slot.j,
            "verbose": -9,
            "tolfun": s.tolfun,
            "tolx": 1e-6,
        }
        if s.max_generations is not None:
            opts["maxiter"] = s.max_generations
        return cma.CMAEvolutionStrategy(slot.x0, s.sigma0, opts)

    def _generation(self, slot: _Start, ev: Box, log: History, generation: int):
        """One generation of one start: ask, grow (or let the surrogate rank), tell, log. A
        generator: it yields the points (unit cube) it needs grown and is sent their distances
        (:func:`_grow_steps` drives it)."""
        es, surrogate = slot.es, slot.surrogate
        U = np.asarray(es.ask())
        if surrogate:
            f, extra = yield from surrogate.rank(U)
        else:
            f, extra = (yield U), {}
        finite = f[np.isfinite(f)]
        worst = finite.max() + 1.0 if finite.size else 1e6
        es.tell(list(U), list(np.where(np.isfinite(f), f, worst)))
        if surrogate and surrogate.model.size > ev.dim:
            es.inject([np.clip(surrogate.model.xopt, 0.0, 1.0)])  # the model's optimum, as lq-CMA-ES
        if finite.size:
            slot.best_f = min(slot.best_f, float(finite.min()))
        if self.settings.starts > 1:
            extra = {"start": slot.j, **extra}
        log(
            ev,
            generation=generation,
            run=slot.run,
            population=len(U),
            sigma=float(es.sigma),
            **extra,
            **finite_stats(f, "mean", "median"),
        )


class _Start:
    """One start of the search: its point in the unit cube, its current CMA-ES (IPOP restarts
    from the same point with a doubled population), its surrogate and its best distance."""

    def __init__(self, j: int, x0: np.ndarray, surrogate):
        self.j, self.x0, self.surrogate = j, np.asarray(x0, float), surrogate
        self.es = None
        self.run = 0
        self.runs: list[dict] = []
        self.best_f = math.inf
        self.dropped_after: int | None = None

    def finish(self) -> None:
        es = self.es
        self.runs.append(
            {
                "start": self.j,
                "run": self.run,
                "population": int(es.popsize),
                "generations": int(es.countiter),
                "stop": {k: (float(v) if isinstance(v, (int, float)) else str(v)) for k, v in dict(es.stop()).items()},
            }
        )


def _grow_steps(steps: list, grow) -> None:
    """Drive generation generators (:meth:`CMAES._generation`) to their ends together: the
    points all of them ask for at a step are grown as one batch (in the steps' order), and each
    is sent its own distances."""
    want = [next(g) for g in steps]
    live = list(range(len(steps)))
    while live:
        f = grow(np.concatenate([want[i] for i in live]))
        at, still = 0, []
        for i in live:
            k = len(want[i])
            try:
                want[i] = steps[i].send(f[at : at + k])
                still.append(i)
            except StopIteration:
                pass
            at += k
        live = still


class _Race:
    """Successive halving over the starts (Jamieson & Talwalkar 2016; the racing of restarts in
    Hutter et al.'s configurators): the evaluation budget left after the design is cut into
    ``R + 1`` equal parts, ``R = ceil(log2(starts / finalists))``; at the end of each of the first
    ``R`` the worse half of the starts still racing (by their best distance) is dropped, never
    below ``finalists``, so the best ``finalists`` starts share the last part. Without a budget
    every start runs until it converges."""

    def __init__(self, slots: list[_Start], problem: Problem, finalists: int = 1):
        self.active = list(slots)
        self.problem = problem
        self.finalists = finalists  # >= 1: validated with the settings
        n0 = int(problem.n_evaluations)
        ratio = len(slots) / self.finalists
        rungs = math.ceil(math.log2(ratio)) if ratio > 1 else 0
        left = None if problem.max_evaluations is None else max(int(problem.max_evaluations) - n0, 0)
        self.marks = [] if left is None else [n0 + left * (r + 1) / (rungs + 1) for r in range(rungs)]

    def halve(self) -> None:
        n = int(self.problem.n_evaluations)
        while self.marks and n >= self.marks[0]:
            self.marks.pop(0)
            if len(self.active) > self.finalists:
                ranked = sorted(self.active, key=lambda sl: (sl.best_f, sl.j))
                for sl in ranked[max(self.finalists, (len(ranked) + 1) // 2) :]:
                    sl.dropped_after = n
                    self.active.remove(sl)


def _start_points(U: np.ndarray | None, f: np.ndarray | None, k: int, ilo, ihi, lo, hi, seed: int) -> list[np.ndarray]:
    """``k`` start points in the unit cube: the best points of the design, each at least a quarter
    of the cube's side from those taken before it (in the largest coordinate), then points of a
    scrambled Sobol' sequence over the initial box, equally spread, where the design has too few."""
    from scipy.stats import qmc

    out: list[np.ndarray] = []
    if U is not None and f is not None:
        for i in np.argsort(np.where(np.isfinite(f), f, np.inf), kind="stable"):
            if not np.isfinite(f[i]):
                break
            if all(np.max(np.abs(U[i] - u)) >= 0.25 for u in out):
                out.append(np.clip(U[i], 0.0, 1.0))
            if len(out) == k:
                return out
    V = qmc.Sobol(len(lo), scramble=True, rng=np.random.default_rng([seed, 0x57A7])).random_base2(
        max(0, math.ceil(math.log2(2 * k)))
    )
    for i, v in enumerate(V):
        u = np.clip((ilo + v * (ihi - ilo) - lo) / (hi - lo), 0.0, 1.0)
        # apart from those taken, unless the points left are only as many as the starts missing
        if all(np.max(np.abs(u - w)) >= 0.25 for w in out) or len(V) - i <= k - len(out):
            out.append(u)
        if len(out) == k:
            break
    return out


class _LQSurrogate:
    """lq-CMA-ES's population evaluation (after cma's ``SurrogatePopulation.__call__``: its model,
    settings and growing schedule, with an out-of-sample rank check and batches; see the module):
    ``surrogate.rank(U)``, a generator that yields the points it grows and is sent their
    distances, returns the values CMA-ES is told and a log record (``grown``: points grown,
    ``tau``: the rank agreement of the model's predictions with them)."""

    def __init__(self, batch: int, min_true: int = 6):
        from cma.fitness_models import LQModel, SurrogatePopulationSettings

        self.model, self.batch, self.S = LQModel(), int(batch), SurrogatePopulationSettings
        self.min_true = int(min_true)

    def rank(self, U: np.ndarray):
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
            f[idx] = yield U[idx]
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
