"""TuRBO: trust-region Bayesian optimisation (Eriksson et al. 2019, NeurIPS), one trust region,
adapted to the noisy distances of stochastic growth models.

A sample-efficient optimiser for a budget of a few hundred to a few thousand evaluations of an
expensive objective in 5-30 dimensions, where a global Gaussian-process model is too coarse and
an evolution strategy spends too many evaluations learning its covariance.

* The search runs in the unit cube (each parameter scaled by its bounds). It starts with a
  scrambled Sobol' design over the initial box (``init_points``, default 2 x the dimension).
* A Gaussian process (scikit-learn: constant x Matern-5/2 with one length scale per parameter,
  plus a white-noise term for the model seeds' noise, at least TuRBO's floor; hyperparameters by
  maximum likelihood every ``hyper_every`` batches, warm-started from the previous fit) is fitted
  to the ``max_train`` points nearest the best one.
* The next ``batch`` points come from a trust region: a box of side ``length`` shaped by the
  length scales (long where the distance changes slowly), centred on the evaluated point the GP
  expects lowest (``centre = "model"``: a tree distance's best value is partly a lucky draw of
  the model seeds, and a box around a lucky point finds nothing better; ``"best"`` is TuRBO's
  lowest value). Candidates are Sobol' points in the box that move only some coordinates (each
  with probability ``min(1, 20 / dimension)``); each point of the batch is the minimum of one
  joint posterior draw over the candidates (Thompson sampling), so a batch explores and exploits
  in proportion to the model's uncertainty.
* ``success_tol`` batches in a row that improve the best distance (by more than 0.1 %) double the
  box (up to ``length_max``); ``failure_tol`` batches that do not halve it. Below ``length_min``
  a new run starts: with ``restart = "best"`` (default) at ``length_init`` around the GP's best
  point with every point kept, which suits budgets too small to throw evaluations away; with
  ``"design"`` from a fresh design with the earlier points dropped (TuRBO-1).

Integer parameters: the model sees their continuous relaxation (the box widened by half a step
at each end) and points are rounded when they are grown; the model is fitted on the rounded
points. Failed simulations count as the worst distance so far. Everything is seeded from
``problem.seed`` and the GP fit is deterministic, so the same returned values give the same
points: a resumed fit replays. Settings compared on the LIGNUM pine recipe, and the cost of the
model per batch: ``docs/notes/2026-11-25-turbo.md``.
"""

from __future__ import annotations

import math
import warnings
from typing import Literal, Optional

import numpy as np
from pydantic import Field

from bforest_core.interfaces import Optimizer, OptimizeResult, Problem

from . import box
from .box import Box, History, NoiseStop, OptimizerSettings, finite_stats, make_result, noise_stop_fields

_NOISE = noise_stop_fields()


class TurboSettings(OptimizerSettings):
    batch: int = Field(
        2,
        ge=1,
        le=box.MAX_POINTS,
        description="points per iteration, grown together (set it to the executor's workers)",
    )
    init_points: Optional[int] = Field(
        None,
        ge=2,
        le=box.MAX_POINTS,
        description="points of the Sobol' design that starts each run (default 2 x the number of free parameters)",
    )
    length_init: float = Field(0.8, gt=0, le=2, description="initial side of the trust region (unit cube)")
    length_min: float = Field(0.5**7, gt=0, description="a trust region smaller than this restarts the run")
    length_max: float = Field(1.6, gt=0, le=2, description="largest side of the trust region")
    success_tol: int = Field(3, ge=1, description="improving batches in a row that double the trust region")
    failure_tol: Optional[int] = Field(
        None,
        ge=1,
        description="batches in a row without improvement that halve it (default ceil(max(4, dimension) / batch))",
    )
    candidates: int = Field(1000, ge=10, le=box.MAX_POINTS, description="candidate points per Thompson draw")
    centre: Literal["best", "model"] = Field(
        "model",
        description="centre of the trust region: 'best', the point "
        "with the lowest distance; 'model', the point the GP expects lowest "
        "(robust to a lucky draw of a noisy distance)",
    )
    restart: Literal["best", "design"] = Field(
        "best",
        description="when the trust region has shrunk below "
        "length_min: 'best', it starts again at length_init around its "
        "centre with every point kept (for budgets of a few hundred "
        "evaluations per dimension or less); 'design', a fresh Sobol' "
        "design and the earlier points dropped (TuRBO-1)",
    )
    restarts: int = Field(
        10,
        ge=0,
        description="new runs after the first one's trust region has shrunk below "
        "length_min (the budget or a stop usually ends the search first)",
    )
    hyper_every: int = Field(
        5,
        ge=1,
        description="batches between maximum-likelihood fits of the GP's "
        "hyperparameters (in between the GP takes the new points with the last ones)",
    )
    max_train: int = Field(
        300,
        ge=10,
        le=box.MAX_POINTS,
        description="points the Gaussian process is fitted to: the run's points nearest its best one",
    )
    patience: Optional[int] = _NOISE["patience"]
    noise: box.NoiseSetting = _NOISE["noise"]
    noise_seeds: int = _NOISE["noise_seeds"]


class Turbo(Optimizer):
    """Trust-region Bayesian optimisation with Thompson sampling (after TuRBO-1) and restarts.

    Log records (one per batch): ``generation``, ``run`` (restart index), ``length`` (side of the
    trust region, ``None`` for the design), ``population`` (points in the batch), ``mean``
    (their mean distance), ``noise`` (the GP's noise sd in distance units).

    With a ``patience``, the noise-aware stop (``box.NoiseStop``) ends the search when the best
    distance has not improved by more than the objective's seed noise in that many batches.
    """

    name = "turbo"
    summary = "TuRBO trust-region Bayesian optimisation (scikit-learn GP, Thompson sampling, restarts)"
    Settings = TurboSettings

    def minimize(self, problem: Problem) -> OptimizeResult:
        s: TurboSettings = self.settings
        ev = Box(problem)
        log = History(problem)
        stop = NoiseStop(problem, s.patience, s.noise, s.noise_seeds)
        dim = ev.dim
        lo, hi = ev.relaxed_bounds("bounds")
        n_init = s.init_points or 2 * dim
        fail_tol = s.failure_tol or int(math.ceil(max(4.0, dim) / s.batch))
        prob_perturb = min(1.0, 20.0 / dim)
        rng = np.random.default_rng([int(problem.seed), 0x7B0])

        def grow(X):  # parameters -> (unit-cube points as grown, distances)
            X = ev.project(X)
            return (X - lo) / (hi - lo), ev(X)

        reason, generation, runs = "", 0, []
        run, gp = -1, None
        while not ev.stopped and run < s.restarts:
            run += 1
            if run == 0 or s.restart == "design":
                U, f = grow(ev.sample_init(n_init, rng, "sobol"))
                generation += 1
                log(ev, generation=generation, run=run, length=None, population=len(f), **finite_stats(f, "mean"))
                gp = _GP(dim)
            length, succ, fail = s.length_init, 0, 0
            n_batches = 0
            while not ev.stopped and length >= s.length_min:
                y = _finite_or_worst(f)
                best_i = int(np.argmin(y))
                idx = _nearest(U, U[best_i], gp.length_scales, s.max_train)
                gp.fit(U[idx], y[idx], hyper=n_batches % s.hyper_every == 0)
                centre = U[idx[int(np.argmin(gp.mean(U[idx])))] if s.centre == "model" else best_i]
                w = gp.length_scales / np.exp(np.mean(np.log(gp.length_scales)))
                half = 0.5 * length * w
                tr_lo, tr_hi = np.clip(centre - half, 0.0, 1.0), np.clip(centre + half, 0.0, 1.0)
                cand = _candidates(centre, tr_lo, tr_hi, s.candidates, prob_perturb, rng)
                Unew = gp.thompson(cand, min(s.batch, ev.problem.remaining() or s.batch), rng)
                Ubatch, fb = grow(lo + Unew * (hi - lo))
                before = float(y[best_i])
                U, f = np.vstack([U, Ubatch]), np.concatenate([f, fb])
                fin = fb[np.isfinite(fb)]
                if fin.size and fin.min() < before - 1e-3 * abs(before):
                    succ, fail = succ + 1, 0
                else:
                    succ, fail = 0, fail + 1
                if succ == s.success_tol:
                    length, succ = min(2.0 * length, s.length_max), 0
                elif fail == fail_tol:
                    length, fail = length / 2.0, 0
                generation += 1
                n_batches += 1
                log(
                    ev,
                    generation=generation,
                    run=run,
                    length=float(length),
                    population=len(fb),
                    noise=gp.noise_sd,
                    **finite_stats(fb, "mean"),
                )
                if stop(ev):
                    reason = stop.reason
                    break
            runs.append(
                {
                    "run": run,
                    "points": int(len(f)),
                    "batches": n_batches,
                    "best": float(np.min(f)) if np.isfinite(f).any() else None,
                    "end": "trust region below length_min" if length < s.length_min else "stopped",
                }
            )
            if reason:
                break
        reason = reason or f"the trust region shrank below length_min in {run + 1} run(s)"
        return make_result(ev, log, reason, {"generations": generation, "runs": runs, "seed_noise": stop.noise})


def _finite_or_worst(f: np.ndarray) -> np.ndarray:
    """Distances with failed points (inf) set to the worst finite one (0 when none is finite)."""
    fin = np.isfinite(f)
    return np.where(fin, f, f[fin].max() if fin.any() else 0.0)


def _nearest(U: np.ndarray, centre: np.ndarray, scales: np.ndarray, k: int) -> np.ndarray:
    """Indices of the ``k`` points nearest ``centre`` in the model's metric (all when fewer),
    in their original order."""
    if len(U) <= k:
        return np.arange(len(U))
    d = (((U - centre) / scales) ** 2).sum(axis=1)
    return np.sort(np.argsort(d, kind="stable")[:k])


def _candidates(centre, lo, hi, n, prob, rng) -> np.ndarray:
    """Sobol' points in the box ``[lo, hi]`` that keep the centre's value in each coordinate
    except those a Bernoulli(``prob``) mask moves (at least one per point)."""
    from scipy.stats import qmc

    d = len(centre)
    m = int(math.ceil(math.log2(n)))
    pert = lo + qmc.Sobol(d, scramble=True, rng=rng).random_base2(m)[:n] * (hi - lo)
    mask = rng.random((n, d)) <= prob
    none = ~mask.any(axis=1)
    mask[np.flatnonzero(none), rng.integers(0, d, size=int(none.sum()))] = True
    return np.where(mask, pert, centre)


class _GP:
    """A scikit-learn Gaussian process on the unit cube whose hyperparameters carry over from
    one fit to the next (a warm start: the fit is then a few quasi-Newton steps)."""

    def __init__(self, dim: int):
        from sklearn.gaussian_process.kernels import ConstantKernel, Matern, WhiteKernel

        self.kernel = ConstantKernel(1.0, (0.05, 20.0)) * Matern(
            length_scale=np.full(dim, 0.5), length_scale_bounds=(0.005, 2.0), nu=2.5
        ) + WhiteKernel(0.01, (5e-4, 0.5))  # TuRBO's noise floor (standardised units)
        self.model = None

    @property
    def length_scales(self) -> np.ndarray:
        return np.asarray(self.kernel.k1.k2.length_scale, float)

    @property
    def noise_sd(self) -> float | None:
        if self.model is None:
            return None
        return float(math.sqrt(self.kernel.k2.noise_level) * self.model._y_train_std)  # in the GP's units

    def fit(self, U: np.ndarray, y: np.ndarray, hyper: bool = True) -> None:
        """Fit to ``(U, y)``; ``hyper``: by maximum likelihood from the last hyperparameters, else
        with them as they are."""
        from sklearn.exceptions import ConvergenceWarning
        from sklearn.gaussian_process import GaussianProcessRegressor

        gp = GaussianProcessRegressor(
            self.kernel,
            normalize_y=True,
            n_restarts_optimizer=0,
            random_state=0,
            optimizer="fmin_l_bfgs_b" if hyper or self.model is None else None,
        )
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ConvergenceWarning)
            gp.fit(U, y)
        self.model, self.kernel = gp, gp.kernel_

    def mean(self, U: np.ndarray) -> np.ndarray:
        """The GP's posterior mean at ``U`` (in its own units: only the order matters)."""
        return self.model.kernel_.k1(U, self.model.X_train_) @ self.model.alpha_

    def thompson(self, cand: np.ndarray, q: int, rng: np.random.Generator) -> np.ndarray:
        """``q`` distinct candidates, each the minimum of one joint draw of the latent function
        (the noise term left out) over ``cand``."""
        from scipy.linalg import cholesky, solve_triangular

        gp = self.model
        k_signal = gp.kernel_.k1
        Ks = k_signal(cand, gp.X_train_)
        mean = Ks @ gp.alpha_  # as mean(), with Ks kept for the covariance
        v = solve_triangular(gp.L_, Ks.T, lower=True)
        cov = k_signal(cand) - v.T @ v
        cov = 0.5 * (cov + cov.T)
        jitter = 1e-8 * max(float(np.mean(np.diag(cov))), 1e-12)
        for _ in range(6):
            try:
                L = cholesky(cov + jitter * np.eye(len(cand)), lower=True, check_finite=False)
                break
            except np.linalg.LinAlgError:
                jitter *= 10.0
        else:  # pragma: no cover - a covariance that will not factor: draw from the diagonal
            L = np.diag(np.sqrt(np.clip(np.diag(cov), 0.0, None)))
        draws = mean[:, None] + L @ rng.standard_normal((len(cand), q))
        out, taken = [], np.zeros(len(cand), bool)
        for j in range(q):
            col = np.where(taken, np.inf, draws[:, j])
            i = int(np.argmin(col))
            taken[i] = True
            out.append(cand[i])
        return np.array(out)
