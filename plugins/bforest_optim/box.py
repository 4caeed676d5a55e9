"""The box an optimiser searches, as the optimisers of this plugin see it: the checked box and
its geometry, logging, results, the noise-aware stop.

Every optimiser of this plugin talks to its :class:`~bforest_core.interfaces.Problem` through a
:class:`Box`, which

* checks the bounds and narrows integer parameters' bounds to whole numbers;
* rounds integer parameters and clips every point into those bounds (:meth:`Box.project`), spreads
  initial points over the initial box (:meth:`Box.sample_init`);
* sends a projected batch to ``problem.evaluate``, turns NaN values into ``+inf`` and remembers
  the best point of the batches it sent (the optimiser's own answer).

Evaluating is the problem's: ``problem.evaluate`` (in a fit, the pipeline's evaluator) caches,
replays, logs, enforces the evaluation budget and every other stop, and sets
``problem.stopped``; a :class:`Box` sends nothing once the problem has stopped.

Log records (``problem.log``) of all optimisers share the keys ``iteration`` (0-based counter of
records), ``best`` (best distance so far, ``None`` while nothing finite was seen) and
``n_evaluations`` (``problem.n_evaluations``); each optimiser adds its own (``generation``,
``mean``, ``step``, ``acceptance``...). Values are plain Python numbers (JSON friendly).
"""

from __future__ import annotations

import math
from typing import Annotated, Literal, Union

import numpy as np
from pydantic import AfterValidator, Field

from bforest_core.interfaces import ComponentSettings, OptimizeResult, Problem

SamplingName = Literal["halton", "sobol", "lhs", "random"]


#: a length limit (generations, iterations) high enough that the evaluation budget ends the run
#: first (``Optimizer.budget_settings``)
UNLIMITED = 10**6


class StopOptimization(Exception):
    """Raised inside a library callback to unwind an optimiser when the problem has stopped."""


#: the most points an optimiser of this plugin holds or asks for at once (a population, an
#: initial design, a batch, candidates): what a 2-core laptop's memory holds, however large the box
MAX_POINTS = 10_000
#: the most model seeds of a noise measurement
MAX_NOISE_SEEDS = 1000


def _noise_value(v):
    if v != "auto" and v < 0:
        raise ValueError(f"must be 'auto' or a distance >= 0 (got {v})")
    return v


#: ``noise`` of the noise-aware stop: a distance (>= 0) or "auto"
NoiseSetting = Annotated[Union[float, Literal["auto"]], AfterValidator(_noise_value)]


class OptimizerSettings(ComponentSettings):
    """Settings common to every optimiser of this plugin (none yet; a place for them)."""


def _as_vector(value, p: int, what: str) -> np.ndarray:
    a = np.asarray(value, dtype=float).reshape(-1)
    if a.shape != (p,):
        raise ValueError(f"problem.{what} has {a.size} values for {p} parameters")
    return a


class Box:
    """The optimiser-side view of a :class:`Problem`: its checked box, and batches sent to
    ``problem.evaluate``.

    Parameters
    ----------
    problem : Problem
        The problem to evaluate.

    Attributes
    ----------
    lower, upper : ndarray
        Effective bounds: for integer parameters ``ceil(lower)`` and ``floor(upper)``.
    integer : ndarray of bool
        Integer flags.
    init_lower, init_upper : ndarray
        The initial box, clipped into the bounds (integer parameters rounded inwards).
    best_x, best_f
        Best (finite) point and value returned by ``problem.evaluate`` so far.
    n_batches, n_points
        Calls made to ``problem.evaluate`` and points sent.

    Raises
    ------
    ValueError
        Naming the parameter, for non-finite bounds, ``lower >= upper``, an integer parameter
        whose range holds no whole number, or an initial box outside the bounds.
    """

    def __init__(self, problem: Problem):
        self.problem = problem
        names = list(problem.names)
        p = len(names)
        if p == 0:
            raise ValueError("problem has no parameters")
        lo = _as_vector(problem.lower, p, "lower")
        hi = _as_vector(problem.upper, p, "upper")
        integer = np.asarray(problem.integer, dtype=bool).reshape(-1)
        if integer.shape != (p,):
            raise ValueError(f"problem.integer has {integer.size} flags for {p} parameters")
        for i, n in enumerate(names):
            if not (math.isfinite(lo[i]) and math.isfinite(hi[i])):
                raise ValueError(f"parameter {n!r}: bounds must be finite (got [{lo[i]}, {hi[i]}])")
            if not lo[i] < hi[i]:
                raise ValueError(f"parameter {n!r}: lower bound {lo[i]} is not below upper bound {hi[i]}")
        lo = np.where(integer, np.ceil(lo), lo)
        hi = np.where(integer, np.floor(hi), hi)
        for i in np.flatnonzero(integer & (lo > hi)):
            raise ValueError(
                f"integer parameter {names[i]!r}: the bounds "
                f"[{problem.lower[i]}, {problem.upper[i]}] hold no whole number"
            )
        ilo, ihi = problem.init_box()
        ilo = np.clip(_as_vector(ilo, p, "init_lower"), lo, hi)
        ihi = np.clip(_as_vector(ihi, p, "init_upper"), lo, hi)
        ilo = np.where(integer, np.ceil(ilo), ilo)
        ihi = np.where(integer, np.floor(ihi), ihi)
        for i in np.flatnonzero(ilo > ihi):
            raise ValueError(
                f"parameter {names[i]!r}: the initial range "
                f"[{problem.init_box()[0][i]}, {problem.init_box()[1][i]}] lies outside "
                f"the bounds [{problem.lower[i]}, {problem.upper[i]}] or holds no whole number"
            )
        self.names = names
        self.lower, self.upper, self.integer = lo, hi, integer
        self.init_lower, self.init_upper = ilo, ihi
        self.best_x: np.ndarray | None = None
        self.best_f = math.inf
        self.n_batches = 0
        self.n_points = 0

    # ------------------------------------------------------------------ geometry
    @property
    def dim(self) -> int:
        return len(self.names)

    @property
    def width(self) -> np.ndarray:
        """Width of the bounds per parameter."""
        return self.upper - self.lower

    @property
    def init_width(self) -> np.ndarray:
        """Width of the initial box; where it is zero, the width of the bounds."""
        w = self.init_upper - self.init_lower
        return np.where(w > 0, w, self.width)

    def relaxed_bounds(self, box: str = "bounds") -> tuple[np.ndarray, np.ndarray]:
        """A continuous box in which rounding gives every whole number the same measure.

        Integer parameters are widened by 0.5 on each side (minus one ulp), real ones are kept.
        ``box`` is ``"bounds"`` or ``"init"``.
        """
        lo, hi = (self.lower, self.upper) if box == "bounds" else (self.init_lower, self.init_upper)
        rlo = np.where(self.integer, np.nextafter(lo - 0.5, np.inf), lo)
        rhi = np.where(self.integer, np.nextafter(hi + 0.5, -np.inf), hi)
        return rlo, rhi

    def project(self, X) -> np.ndarray:
        """Round integer parameters and clip into the bounds; ``(k, p)`` in, ``(k, p)`` out."""
        X = np.atleast_2d(np.asarray(X, dtype=float))
        if X.ndim != 2 or X.shape[1] != self.dim:
            raise ValueError(f"points must have shape (k, {self.dim}), got {X.shape}")
        X = np.where(self.integer, np.rint(X), X)
        return np.clip(X, self.lower, self.upper)

    def sample_init(self, n: int, rng: np.random.Generator, method: str = "halton") -> np.ndarray:
        """``n`` points spread over the initial box (integer parameters uniform over the whole
        numbers of their initial range), drawn with ``rng``.

        ``method``: ``"halton"``/``"sobol"`` (scrambled low-discrepancy), ``"lhs"`` (Latin
        hypercube) or ``"random"`` (independent uniform).
        """
        from scipy.stats import qmc

        p = self.dim
        if method == "random":
            U = rng.random((n, p))
        elif method == "halton":
            U = qmc.Halton(p, scramble=True, rng=rng).random(n)
        elif method == "sobol":
            # Sobol' points are balanced for powers of two; draw the next one and keep n
            m = max(0, int(math.ceil(math.log2(max(n, 1)))))
            U = qmc.Sobol(p, scramble=True, rng=rng).random_base2(m)[:n]
        elif method == "lhs":
            U = qmc.LatinHypercube(p, rng=rng).random(n)
        else:
            raise ValueError(f"unknown sampling method {method!r} (halton, sobol, lhs, random)")
        rlo, rhi = self.relaxed_bounds("init")
        return self.project(rlo + U * (rhi - rlo))

    def initial_design(self, n: int, rng: np.random.Generator, method: str = "halton") -> np.ndarray:
        """``n`` points to start from: the problem's own start points first (``Problem.start``:
        an amortised estimator's posterior draws for the target), projected into the bounds, and
        where it has fewer (or none), points of :meth:`sample_init`."""
        start = self.problem.start
        X = np.zeros((0, self.dim)) if start is None else self.project(np.asarray(start, float)[:n])
        if len(X) < n:
            X = np.vstack([X, self.sample_init(n - len(X), rng, method)])
        return X

    # ------------------------------------------------------------------ evaluation
    @property
    def stopped(self) -> bool:
        """True once the problem has stopped (it stops itself at its budget)."""
        return bool(self.problem.stopped)

    def __call__(self, X) -> np.ndarray:
        """Evaluate a batch through ``problem.evaluate``; returns ``k`` values (``inf`` for points
        that were not evaluated or failed).

        Nothing is evaluated once the problem has stopped (all values ``inf``).
        """
        X = self.project(X)
        k = X.shape[0]
        if k == 0 or self.stopped:
            return np.full(k, np.inf)
        f = np.asarray(self.problem.evaluate(X), dtype=float).reshape(-1)
        if f.shape != (k,):
            raise ValueError(f"problem.evaluate returned {f.size} values for {k} points")
        f = np.where(np.isnan(f), np.inf, f)
        self.n_batches += 1
        self.n_points += k
        i = int(np.argmin(f))
        if f[i] < self.best_f:
            self.best_f, self.best_x = float(f[i]), X[i].copy()
        return f

    def stop_reason(self, own: str) -> str:
        """The problem's stop reason when it stopped, else ``own``."""
        pr = self.problem
        if pr.stopped:
            return pr.stop_reason or "stopped by the problem"
        return own


def finite_stats(f: np.ndarray, *names: str) -> dict[str, float]:
    """``mean``, ``median`` and/or ``std`` of the finite values of ``f`` (inf when there are
    none): the population statistics of a log record."""
    fin = f[np.isfinite(f)]
    fns = {"mean": np.mean, "median": np.median, "std": np.std}
    return {k: float(fns[k](fin)) if fin.size else math.inf for k in names}


def finite_or_none(v) -> float | None:
    v = float(v)
    return v if math.isfinite(v) else None


class History:
    """Collects log records and forwards each to ``problem.log``."""

    def __init__(self, problem: Problem):
        self.problem = problem
        self.records: list[dict] = []

    def __call__(self, ev: Box, **fields) -> dict:
        rec = {"iteration": len(self.records)}
        for k, v in fields.items():
            if isinstance(v, (np.floating, float)):
                v = finite_or_none(v)
            elif isinstance(v, np.integer):
                v = int(v)
            rec[k] = v
        rec["best"] = finite_or_none(ev.best_f)
        rec["n_evaluations"] = int(self.problem.n_evaluations)
        self.records.append(rec)
        self.problem.log(rec)
        return rec


def make_result(ev: Box, history: History, own_reason: str, diagnostics: dict) -> OptimizeResult:
    """The :class:`OptimizeResult` of a run: the best point the optimiser saw (else the problem's
    best, else the centre of the initial box with ``fun = inf``)."""
    pr = ev.problem
    if ev.best_x is not None:
        x, fun = ev.best_x.copy(), ev.best_f
    elif pr.best_x is not None:
        x, fun = ev.project(pr.best_x)[0], float(pr.best_f)
    else:
        x, fun = ev.project(0.5 * (ev.init_lower + ev.init_upper))[0], math.inf
    diagnostics = {"n_batches": ev.n_batches, "n_points": ev.n_points, **diagnostics}
    return OptimizeResult(
        x=x,
        fun=float(fun),
        n_evaluations=int(pr.n_evaluations),
        stop_reason=ev.stop_reason(own_reason),
        history=list(history.records),
        diagnostics=diagnostics,
    )


def sampling_field(default: str = "halton"):
    return Field(
        default,
        description="how the initial points are spread over the initial box: "
        "halton or sobol (scrambled low-discrepancy), lhs (Latin hypercube), random",
    )


def noise_stop_fields():
    """The settings of the noise-aware early stop (:class:`NoiseStop`), shared by optimisers."""
    return dict(
        patience=Field(
            None,
            ge=1,
            description="stop when the best distance has not improved by more than the "
            "objective's seed noise in this many generations (None: off)",
        ),
        noise=Field(
            "auto",
            description="the noise of that stop: 'auto' = the sd of the distance over "
            "noise_seeds model seeds at the best point (Problem.seed_spread), or a number",
        ),
        noise_seeds=Field(5, ge=2, le=MAX_NOISE_SEEDS, description="model seeds of the 'auto' noise"),
    )


def seed_noise(problem: Problem, x: np.ndarray, k: int) -> float:
    """The objective's seed noise at ``x``: the standard deviation of its value under ``k`` other
    model seeds (``problem.seed_spread``); 0 where the problem cannot tell."""
    fn = problem.seed_spread
    if fn is None:
        return 0.0
    vals = np.asarray(fn(np.asarray(x, float), int(k)), float)
    vals = vals[np.isfinite(vals)]
    return float(vals.std(ddof=1)) if vals.size > 1 else 0.0


class NoiseStop:
    """Early stop that does not cost quality: no improvement of the best distance by more than
    the distance's own seed noise in ``patience`` generations.

    The noise is what a perfect model would still show between model seeds, so an improvement
    smaller than it is not evidence of a better point. ``"auto"`` measures it at the end of each
    window of ``patience`` generations, at the best point, with ``problem.seed_spread`` (0 where
    the problem cannot provide it: then only a real standstill stops).
    """

    def __init__(self, problem: Problem, patience: int | None, noise="auto", noise_seeds: int = 5):
        self.problem, self.patience, self.noise_setting, self.k = problem, patience, noise, int(noise_seeds)
        self.noise: float | None = None if noise == "auto" else float(noise)
        self.anchor = math.inf  # best value that last counted as an improvement
        self.since = 0  # generations since then
        self.reason = ""

    def _measure(self, ev: Box) -> float:
        return 0.0 if ev.best_x is None else seed_noise(self.problem, ev.best_x, self.k)

    def __call__(self, ev: Box) -> bool:
        """Call once per generation; True when the run should stop (``reason`` says why).

        Generations are judged in windows of ``patience``: at the end of a window the noise is
        measured at the current best point (``"auto"``) and the run stops unless the best
        distance improved over the window by more than that noise.
        """
        if self.patience is None:
            return False
        best = ev.best_f
        if not math.isfinite(self.anchor):
            self.anchor, self.since = best, 0
            return False
        self.since += 1
        if self.since < self.patience:
            return False
        if self.noise_setting == "auto":
            self.noise = self._measure(ev)
        gain = self.anchor - best
        if gain > self.noise:
            self.anchor, self.since = best, 0
            return False
        self.reason = (
            f"the best distance improved by {gain:.4g}, not more than the seed noise {self.noise:.4g}, "
            f"in {self.since} generations"
        )
        return True
