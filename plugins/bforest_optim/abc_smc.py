"""ABC-SMC: sequential Monte Carlo approximate Bayesian computation over the fit's distance.

The posterior of the parameters given the tree is approximated by the particles that simulate
trees within a tolerance epsilon of the data, tightened generation by generation (Toni et al.
2009; Beaumont et al. 2009; Del Moral et al. 2012):

* **Prior**: uniform in the bounds (integer parameters uniform over their whole numbers: the
  particles live in the bounds widened by 0.5 on each side of an integer range, and are rounded
  before evaluation, as in the other optimisers of this plugin).
* **Generation 0**: ``particles`` draws from the prior, all accepted with equal weights.
* **Generation t**: epsilon_t is the ``quantile`` of the previous population's distances. A
  proposal picks a parent by weight, perturbs it with the kernel, and is dropped without
  evaluation when it leaves the bounds (prior density 0). Proposals are evaluated in batches
  through ``problem.evaluate`` (so they run on the executor in parallel); those with a distance
  at most epsilon_t are accepted until the population is full. The weight of an accepted
  particle is prior / sum_j W_j K(theta | theta_j).
* **Kernels**: ``mvn``, a normal with twice the weighted covariance of the previous population
  (Beaumont et al. 2009); ``local``, a normal per parent with twice the covariance of its
  ``neighbours`` nearest particles (in the spirit of Filippi et al. 2013's local kernels; better
  when the posterior is curved or has several modes).
* **Epsilon target**: epsilon never goes below ``epsilon_target`` (the last generation runs at it)
  and the sampler stops once it is reached. ``"noise"`` takes the distance's own noise floor: the
  median distance under ``noise_seeds`` fresh model seeds (``problem.seed_spread``) at the best
  particle or at the population's weighted mean, whichever is lower, measured before every
  generation: what a perfect model still shows against the data. Above it the truth passes the
  tolerance almost surely and the posterior is wider than the data warrant (the calibration study
  in docs/calibration.md found the 50 % intervals covering about two thirds of the truths when the
  run stopped at 1.4 times the floor); at it a perfect model passes half the time; below it the
  acceptance rate, and so the cost, falls fast for little gain.
* **Posterior** (``posterior``): ``"population"``, the last complete generation's particles;
  ``"recycled"``, every proposal the run made, of every generation (the incomplete last one
  included), with a distance at most a lower tolerance eps_post. Each generation's proposals with
  a distance at most eps are an importance sample of the ABC posterior at eps under that
  generation's proposal (its kernel mixture, divided by its share inside the bounds), and the
  balance heuristic of multiple importance sampling weighs them all as drawn from the mixture of
  the proposals, w = prior / sum_t (m_t / M) g_t. eps_post is the lowest tolerance at which they
  still have an effective sample size of ``particles``: the posterior has a population's Monte
  Carlo precision at a lower tolerance, so it is closer to the exact posterior (ABC's posterior
  is the exact one widened by the tolerance; for a Gaussian location by eps^2 / 3 in variance),
  and it costs no evaluation. ``diagnostics`` then keeps the last population too.
* **Regression adjustment** (``adjust = "linear"``; Beaumont, Zhang & Balding 2002): any tolerance
  above zero widens the posterior, and near the distance's noise floor a lower one costs more
  evaluations than it is worth. The adjustment takes that width out from the evaluations already
  made: every proposal within the last tolerance is regrown once with its logged model seeds
  (``problem.summaries``: per data set the log of one plus its rows and its columns' means), each
  parameter (the logit of its place in the bounds) is regressed on those statistics by weighted
  ridge regression (weights: the multiple-importance weights above times the Epanechnikov kernel
  1 - (D / eps)^2; penalty by generalised cross-validation), and each particle moves to the fit at
  the data's statistics plus its residual, inflated by sqrt(n / (n - df)) so that the spread is
  not the fit's underestimate. The adjusted particles are the posterior (``posterior`` then
  chooses the unadjusted one kept in ``diagnostics.unadjusted``). On the calibration study of
  docs/calibration.md it turned intervals that were too wide into calibrated ones. It assumes the
  parameters depend on the statistics about linearly within the tolerance; ``adjustment.r2`` per
  parameter says how much of their spread the statistics explain.
* **Failed simulations** (a tree that collapses, grows too large or times out) match nothing:
  the sampler asks the fit for ``inf`` in their place (``failures_as_inf``), so no tolerance
  accepts them; in a quantile (epsilon, the noise floor) they rank above every grown tree. The
  fit's ``[objective] penalty`` (logged with the status) suits optimisers only: with a distance
  larger than it (e.g. the sliced distance with ``scale_by_sample_size``) it would look like a
  good fit.
* **Stops**: epsilon at or below the target; a generation that needs more than
  ``particles / min_acceptance`` proposals (the acceptance rate fell below ``min_acceptance``);
  ``generations`` done; the run's evaluation budget or wall time. The posterior is always the
  last *complete* generation.

Everything random comes from the run seed, and the proposals depend only on earlier results, so a
run killed and resumed (the fit replays logged evaluations) proposes and accepts exactly the same
particles. With ``[objective] model_seeds`` (or the default ``seed_mode = "fixed"``) every proposal
is simulated with the same model seeds (common random numbers), which makes the acceptance
decisions less noisy, but the posterior is then that of those seeds: as epsilon falls it
concentrates around the parameters that fit best *with those seeds* and leaves the seed-to-seed
variation out, so its intervals are expected to be too narrow (not measured). For intervals meant
to cover the truth use ``seed_mode = "per_evaluation"``, as the calibration study does.

``diagnostics`` holds the posterior's particles (``particles``, ``weights``, ``distances``) and
its tolerance ``epsilon_posterior`` (with ``posterior = "recycled"`` also the last generation's
``population``), the ``epsilon`` schedule (and with ``epsilon_target = "noise"`` the measured
target per generation, ``epsilon_target``), the ``acceptance`` rate and effective sample size
(``ess``) per generation, and ``posterior``: weighted mean, sd and 2.5/5/16/25/50/75/84/95/97.5 %
quantiles per parameter. With ``adjust = "linear"`` it also holds ``adjustment`` (``regrown``
trees, ``summaries`` per tree, and per parameter the ridge ``penalty``, the fit's ``df`` and
``r2``; or a ``note`` saying why the posterior was not adjusted) and ``unadjusted`` (the
posterior before the adjustment).
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
from pydantic import Field, model_validator
from scipy.spatial import cKDTree

from bforest_core.interfaces import Optimizer, OptimizeResult, Problem
from bforest_core.metrics import weighted_quantiles

from .box import MAX_NOISE_SEEDS, MAX_POINTS, UNLIMITED, Box, History, OptimizerSettings, make_result

QUANTILES = (2.5, 5.0, 16.0, 25.0, 50.0, 75.0, 84.0, 95.0, 97.5)


class AbcSmcSettings(OptimizerSettings):
    """Settings of the ``abc-smc`` sampler."""

    particles: int = Field(100, ge=4, le=MAX_POINTS, description="population size (accepted particles per generation)")
    generations: int = Field(30, ge=1, description="largest number of generations (generation 0 = the prior)")
    quantile: float = Field(
        0.5, gt=0, lt=1, description="epsilon_t = this quantile of the previous generation's distances"
    )
    epsilon_target: float | Literal["noise"] = Field(
        0.0,
        description="epsilon never goes below this distance and the run stops once it is reached (0: "
        "never); noise = the median distance under noise_seeds fresh model seeds at the best particle or the "
        "population's weighted mean, whichever is lower (what a perfect model still shows), measured before "
        "every generation",
    )
    noise_seeds: int = Field(8, ge=2, le=MAX_NOISE_SEEDS, description="model seeds of the noise target's measurement")
    min_acceptance: float = Field(
        0.02,
        gt=0,
        le=1,
        description="stop when a generation's acceptance rate "
        "falls below this (it would need more than particles / min_acceptance proposals)",
    )
    kernel: Literal["mvn", "local"] = Field(
        "mvn",
        description="perturbation kernel: mvn (normal, twice the "
        "weighted population covariance) or local (normal per parent, twice "
        "the covariance of its nearest particles)",
    )
    neighbours: int | None = Field(
        None,
        ge=2,
        le=MAX_POINTS,
        description="particles per local covariance (local kernel; default max(2 * dimension + 1, particles / 5))",
    )
    posterior: Literal["population", "recycled"] = Field(
        "population",
        description="the posterior reported: population, the last complete generation's particles; "
        "recycled, every proposal of every generation with a distance at or below the lowest tolerance at which "
        "they still have the effective sample size of a population, weighted by multiple importance sampling "
        "(a lower tolerance, so closer to the exact posterior, for no extra evaluation)",
    )
    adjust: Literal["none", "linear"] = Field(
        "none",
        description="regression adjustment of the posterior (Beaumont et al. 2002): linear regresses "
        "the parameters (logit of their place in the bounds) on the summary statistics of every proposal within "
        "the last tolerance (Epanechnikov weights; ridge chosen by generalised cross-validation) and moves each "
        "particle to the data's statistics, which takes out most of the width the tolerance adds; regrows those "
        "proposals' trees once with their logged seeds (not counted as evaluations)",
    )
    batch: int | None = Field(
        None,
        ge=1,
        le=MAX_POINTS,
        description="proposals per evaluation batch (default: the "
        "expected number still needed, from the last acceptance rate, at least workers' "
        "worth; at most particles)",
    )

    @model_validator(mode="after")
    def _check(self):
        if not isinstance(self.epsilon_target, str) and not (
            self.epsilon_target >= 0 and math.isfinite(self.epsilon_target)
        ):
            raise ValueError(f"epsilon_target must be a distance >= 0 or 'noise' (got {self.epsilon_target})")
        if self.neighbours is not None and self.neighbours > self.particles:
            raise ValueError(f"neighbours ({self.neighbours}) must not exceed particles ({self.particles})")
        return self


def _ess(w: np.ndarray) -> float:
    return float(1.0 / np.sum((w / w.sum()) ** 2))


def _log_mvn(diff: np.ndarray, chol: np.ndarray) -> np.ndarray:
    """log N(diff; 0, L L^T) up to the constant common to all kernels of one width."""
    z = np.linalg.solve(chol, diff.T)
    return -0.5 * np.sum(z * z, axis=0) - np.sum(np.log(np.diag(chol)))


class _Pool:
    """Every proposal of a run with its distance and the density it was drawn from, for the
    recycled posterior: the proposals of all generations with a distance at most epsilon are an
    importance sample of the ABC posterior at epsilon, each generation's under its own proposal,
    and the balance heuristic of multiple importance sampling (Veach & Guibas 1995) weighs them as
    drawn from the mixture of all proposals: w = prior / sum_t (m_t / M) g_t."""

    def __init__(self, lo: np.ndarray, hi: np.ndarray):
        self.log_prior = -float(np.sum(np.log(hi - lo)))
        self.X, self.d, self.sources, self.m = [], [], [], []

    def add(self, X: np.ndarray, d: np.ndarray, source, inside: float) -> None:
        """``source``: ``None`` (drawn from the prior) or ``(kernels, parents, weights)`` of a
        generation's proposal; ``inside``: its mass inside the bounds (proposals outside are
        drawn again, so the density is the kernel mixture divided by it)."""
        self.X.append(np.asarray(X, float))
        self.d.append(np.where(np.isfinite(d), d, np.inf))
        self.sources.append((source, math.log(max(inside, 1e-300))))
        self.m.append(len(X))

    def posterior(self, eps: float, target_ess: float, log_kernel_mix):
        """``(particles, weights, distances, tolerance)``: the proposals with a distance at most
        the lowest tolerance (at most ``eps``) whose weights have an effective sample size of
        ``target_ess``, or all within ``eps`` when they have less."""
        X, d = np.vstack(self.X), np.concatenate(self.d)
        keep = d <= eps
        X, d = X[keep], d[keep]
        order = np.argsort(d, kind="stable")
        X, d = X[order], d[order]
        M = float(sum(self.m))
        p = X.shape[1]
        terms = []
        for (source, log_inside), m in zip(self.sources, self.m):
            if source is None:
                log_g = np.full(len(X), self.log_prior)
            else:
                log_g = log_kernel_mix(*source, X) - 0.5 * p * math.log(2 * math.pi) - log_inside
            terms.append(math.log(m / M) + log_g)
        terms = np.array(terms)
        top = terms.max(axis=0)
        log_q = top + np.log(np.exp(terms - top).sum(axis=0))
        w = np.exp(self.log_prior - log_q - np.max(self.log_prior - log_q))
        ess = np.cumsum(w) ** 2 / np.cumsum(w**2)
        reach = np.flatnonzero(ess >= target_ess)
        k = len(X) if reach.size == 0 else int(np.searchsorted(d, d[reach[0]], side="right"))
        return X[:k], w[:k] / w[:k].sum(), d[:k], float(d[k - 1])


def regression_adjust(
    X: np.ndarray, w: np.ndarray, S: np.ndarray, s_obs: np.ndarray, lo, hi, penalties=np.logspace(-4, 2, 13)
) -> tuple[np.ndarray, dict]:
    """Local-linear regression adjustment of weighted ABC particles (Beaumont, Zhang & Balding
    2002): per parameter, y = logit of its place in ``[lo, hi]`` is regressed on the standardised
    summaries ``S - s_obs`` by weighted ridge regression (the penalty chosen by generalised
    cross-validation among ``penalties``, in units of the summed weight), and each particle becomes
    ``b0 + f * r``: the fit at the data's summaries plus its residual, inflated by
    ``f = sqrt(n / (n - df))`` (``n`` the weights' effective sample size, ``df`` the trace of the
    hat matrix) so the residuals' spread is not the fit's underestimate of it. Returns the
    adjusted particles (inside the bounds) and per parameter the ``penalty``, ``df`` and ``r2``."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    w = np.asarray(w, float) / np.sum(w)
    n_eff = 1.0 / np.sum(w**2)
    Z = np.asarray(S, float) - np.asarray(s_obs, float)
    sd = np.sqrt(w @ (Z - w @ Z) ** 2)
    Z = Z[:, sd > 0] / sd[sd > 0]
    A = np.hstack([np.ones((len(Z), 1)), Z])
    u = np.clip((np.asarray(X, float) - lo) / (hi - lo), 1e-9, 1 - 1e-9)
    Y = np.log(u / (1 - u))
    WA = A * w[:, None]
    gram = A.T @ WA
    fits = []  # per penalty: the map from y to the coefficients, and its degrees of freedom
    for lam in penalties:
        R = lam * np.eye(A.shape[1])
        R[0, 0] = 0.0  # the intercept is not shrunk
        M = np.linalg.solve(gram + R, WA.T)
        df = float(np.sum(A * M.T))  # trace of the hat matrix A M
        if df < n_eff - 1:
            fits.append((lam, M, df))
    out = np.empty_like(Y)
    fit = {"penalty": [], "df": [], "r2": []}
    for j in range(Y.shape[1]):
        best = None
        for lam, M, df in fits:
            beta = M @ Y[:, j]
            r = Y[:, j] - A @ beta
            gcv = float(w @ r**2) / (1.0 - df / n_eff) ** 2
            if best is None or gcv < best[0]:
                best = (gcv, lam, beta, r, df)
        if best is None:  # too few particles for any fit: this parameter stays unadjusted
            out[:, j] = Y[:, j]
            lam, df, r2 = None, 0.0, 0.0
        else:
            _, lam, beta, r, df = best
            out[:, j] = beta[0] + math.sqrt(n_eff / (n_eff - df)) * r
            tot = float(w @ (Y[:, j] - w @ Y[:, j]) ** 2)
            lam, r2 = float(lam), (1.0 - float(w @ r**2) / tot if tot > 0 else 0.0)
        fit["penalty"].append(lam)
        fit["df"].append(df)
        fit["r2"].append(r2)
    return lo + (hi - lo) / (1.0 + np.exp(-out)), fit


class AbcSmc(Optimizer):
    """Sequential Monte Carlo ABC under a uniform prior (see the module text)."""

    name = "abc-smc"
    summary = "ABC-SMC sampler: a weighted posterior population and the best particle"
    Settings = AbcSmcSettings
    posterior_kind = "population"
    failures_as_inf = True

    @classmethod
    def budget_settings(cls, settings, budget):
        """No generation limit: the budget ends the run."""
        return {**settings, "generations": UNLIMITED}

    def minimize(self, problem: Problem) -> OptimizeResult:
        s: AbcSmcSettings = self.settings
        ev = Box(problem)
        log = History(problem)
        lo, hi = ev.relaxed_bounds("bounds")
        rng = np.random.default_rng(np.random.SeedSequence([int(problem.seed), 0xABC5]))
        n = s.particles
        # generation 0: the prior
        theta = lo + rng.random((n, ev.dim)) * (hi - lo)
        dist = ev(theta)
        # every proposal with its distance and the proposal it came from, for the recycled posterior
        pool = _Pool(lo, hi)
        pool.add(theta, dist, None, 1.0)
        weights = np.full(n, 1.0 / n)
        eps_hist, acc_hist, ess_hist, target_hist = [math.inf], [1.0], [float(n)], []
        log(ev, generation=0, epsilon=None, acceptance=1.0, ess=float(n), proposals=n)
        reason = f"{s.generations} generations done"
        if ev.stopped:
            reason = "stopped during the prior draws"
        for t in range(1, s.generations):
            if ev.stopped:
                break
            fin = np.isfinite(dist)
            if not fin.any():
                reason = "no finite distance in the population"
                break
            target = self._target(problem, ev, theta, weights)
            target_hist.append(target)
            if eps_hist[-1] <= target:
                reason = f"epsilon {eps_hist[-1]:.4g} at or below the target {target:.4g}" + (
                    " (the distance's noise floor)" if s.epsilon_target == "noise" else ""
                )
                break
            # a failure (inf) ranks above every grown tree: where the quantile falls among the
            # failures, epsilon is the largest distance of a grown tree
            eps = max(float(np.quantile(np.where(fin, dist, dist[fin].max()), s.quantile)), target)
            kern = self._kernel(theta, weights)
            gen_X, gen_d, got, proposals, rate = [], [], 0, 0, 1.0
            drawn_inside = [0, 0]
            limit = int(math.ceil(n / s.min_acceptance))
            while got < n and proposals < limit and not ev.stopped:
                k = s.batch or int(min(n, max((n - got) / max(rate, s.min_acceptance), 8)))
                k = min(k, limit - proposals)
                if problem.remaining() is not None:
                    k = min(k, problem.remaining())
                X = self._propose(kern, theta, weights, k, lo, hi, rng, drawn_inside)
                d = ev(X)
                proposals += k
                gen_X.append(X)
                gen_d.append(d)
                got += int(np.sum(np.isfinite(d) & (d <= eps)))
                rate = max(got / proposals, 1.0 / (proposals + 1))
            if gen_X:  # the share of the kernel mixture inside the bounds normalises its density
                pool.add(
                    np.vstack(gen_X),
                    np.concatenate(gen_d),
                    (kern, theta, weights),
                    drawn_inside[1] / max(drawn_inside[0], 1),
                )
            if got < n:
                reason = f"generation {t} incomplete ({got} of {n} particles): " + (
                    ev.stop_reason("stopped")
                    if ev.stopped
                    else f"acceptance {got / max(proposals, 1):.3g} below min_acceptance {s.min_acceptance:g}"
                )
                log(
                    ev,
                    generation=t,
                    epsilon=eps,
                    acceptance=got / max(proposals, 1),
                    ess=None,
                    proposals=proposals,
                    complete=False,
                )
                break
            X, d = np.vstack(gen_X), np.concatenate(gen_d)
            ok = np.isfinite(d) & (d <= eps)
            cand, cand_d = X[ok][:n], d[ok][:n]
            w = 1.0 / np.exp(self._log_kernel_mix(kern, theta, weights, cand))
            theta, dist, weights = cand, cand_d, w / w.sum()
            eps_hist.append(eps)
            acc_hist.append(n / proposals)
            ess_hist.append(_ess(weights))
            log(
                ev,
                generation=t,
                epsilon=eps,
                acceptance=n / proposals,
                ess=ess_hist[-1],
                proposals=proposals,
                complete=True,
            )
        population = (theta, weights, dist)
        if s.posterior == "recycled" and len(eps_hist) > 1:
            theta, weights, dist, eps_post = pool.posterior(eps_hist[-1], n, self._log_kernel_mix)
        else:
            eps_post = eps_hist[-1]
        adjusted, unadjusted = None, None
        if s.adjust == "linear" and len(eps_hist) > 1:
            adjusted = self._adjusted(problem, ev, pool, eps_hist[-1], lo, hi)
            if "particles" in adjusted:
                unadjusted = {
                    "particles": ev.project(theta),
                    "weights": weights,
                    "distances": dist,
                    "epsilon": eps_post,
                }
                theta, weights, dist, eps_post = (
                    adjusted.pop("particles"),
                    adjusted.pop("weights"),
                    adjusted.pop("distances"),
                    eps_hist[-1],
                )
        diag = self._diagnostics(ev, theta, weights, dist, eps_hist, acc_hist, ess_hist)
        diag["epsilon_posterior"] = None if not math.isfinite(eps_post) else float(eps_post)
        if adjusted is not None:
            diag["adjustment"] = adjusted
        if unadjusted is not None:
            diag["unadjusted"] = unadjusted
        if s.posterior == "recycled":
            diag["population"] = {
                "particles": ev.project(population[0]),
                "weights": population[1],
                "distances": population[2],
            }
        if s.epsilon_target == "noise":
            diag["epsilon_target"] = target_hist
        diag["note"] = f"{reason}; the posterior is generation {len(eps_hist) - 1}, the last complete one"
        short = self._stopped_short(reason, eps_hist, target_hist, ev.stopped)
        if short:
            diag["stopped_short"] = short
        return make_result(ev, log, reason, diag)

    def _stopped_short(self, reason: str, eps_hist: list, target_hist: list, capped: bool) -> str | None:
        """One line when the run stopped short of its target: the last complete generation's
        epsilon above the target (the noise floor), or, without a target, a stop at a cap
        (generations, evaluations, wall time); None when it ended where it was meant to."""
        s = self.settings
        eps = eps_hist[-1]
        noise = s.epsilon_target == "noise"
        target = target_hist[-1] if target_hist else (0.0 if noise else float(s.epsilon_target))
        floor = ", the distance's noise floor," if noise else ""
        if len(eps_hist) == 1:
            return f"stopped before its first generation ({reason}): the posterior is the prior draws, not a posterior"
        if target > 0 and eps > target:
            return (
                f"epsilon stopped at {eps:.4g}, above its target {target:.4g}{floor} ({reason}): the "
                "intervals are wider than the data warrant; raise generations or the budget"
            )
        if target <= 0 and (capped or reason.endswith("generations done")):
            return (
                f"stopped at a cap with epsilon {eps:.4g} and no epsilon target ({reason}): the posterior "
                "may still be narrowing"
            )
        return None

    def _target(self, problem: Problem, ev: Box, theta: np.ndarray, w: np.ndarray) -> float:
        """The epsilon target of the next generation (see the module text); 0 where the noise
        cannot be measured (no ``problem.seed_spread``, or most seeds fail at both points)."""
        s = self.settings
        if s.epsilon_target != "noise":
            return float(s.epsilon_target)
        if problem.seed_spread is None or ev.best_x is None:
            return 0.0
        medians = []
        # the best particle won on one lucky draw and may sit off the mode; the weighted mean is
        # central but may fall between modes: the lower median of the two is the floor
        for x in (np.asarray(ev.best_x, float), ev.project(w @ theta)[0]):
            vals = np.asarray(problem.seed_spread(x, int(s.noise_seeds)), float)
            vals = vals[~np.isnan(vals)]  # a failure counts as infinitely far
            median = float(np.median(vals)) if vals.size else math.inf
            if math.isfinite(median):  # not when most seeds fail
                medians.append(median)
        return min(medians) if medians else 0.0

    def _adjusted(self, problem: Problem, ev: Box, pool: _Pool, eps: float, lo, hi) -> dict:
        """The regression-adjusted posterior (``adjust = "linear"``): ``particles``, ``weights``,
        ``distances`` and the fit's figures, or only a ``note`` saying why there is none."""
        if problem.summaries is None or problem.target_summaries is None:
            return {"note": "the problem gives no summary statistics; the posterior is not adjusted"}
        X, w, d, _ = pool.posterior(eps, math.inf, self._log_kernel_mix)
        if len(X) < 3:
            return {"note": f"{len(X)} proposals within the last tolerance; the posterior is not adjusted"}
        S = np.asarray(problem.summaries(ev.project(X)), float)
        kept = np.all(np.isfinite(S), axis=1)
        k = w * np.clip(1.0 - (d / eps) ** 2, 0.0, None) if eps > 0 else w
        k = np.where(kept, k, 0.0)
        if k.sum() <= 0:
            return {"note": "no regrown proposal has weight; the posterior is not adjusted"}
        k /= k.sum()
        Xa, fit = regression_adjust(X[kept], k[kept], S[kept], np.asarray(problem.target_summaries, float), lo, hi)
        return {
            "method": "linear",
            "particles": ev.project(Xa),
            "weights": k[kept],
            "distances": d[kept],
            "regrown": int(len(X)),
            "summaries": int(S.shape[1]),
            **fit,
        }

    # ------------------------------------------------------------------ kernels
    def _kernel(self, theta: np.ndarray, w: np.ndarray) -> list[np.ndarray]:
        """Cholesky factors of the perturbation covariance: one (mvn) or one per particle (local)."""
        p = theta.shape[1]
        floor = 1e-12 + 1e-9 * np.ptp(theta, axis=0) ** 2

        def chol(cov):
            return np.linalg.cholesky(cov + np.diag(floor + 1e-10 * np.trace(cov) / p))

        if self.settings.kernel == "mvn":
            mu = w @ theta
            c = theta - mu
            return [chol(2.0 * (c * w[:, None]).T @ c / (1.0 - np.sum(w**2) + 1e-12))]
        m = self.settings.neighbours or max(2 * p + 1, theta.shape[0] // 5)
        scale = np.where(np.ptp(theta, axis=0) > 0, np.ptp(theta, axis=0), 1.0)
        _, idx = cKDTree(theta / scale).query(theta / scale, k=min(m, theta.shape[0]))
        out = []
        for i in range(theta.shape[0]):
            nb = theta[idx[i]]
            c = nb - nb.mean(axis=0)
            out.append(chol(2.0 * c.T @ c / max(len(nb) - 1, 1)))
        return out

    @staticmethod
    def _propose(kern, theta, w, k, lo, hi, rng, counts=None) -> np.ndarray:
        """``k`` perturbed particles inside the (relaxed) bounds; parents drawn by weight.
        ``counts`` (a list of two) adds the draws made and those inside the bounds."""
        out = np.empty((0, theta.shape[1]))
        while out.shape[0] < k:
            m = 2 * (k - out.shape[0])
            parent = rng.choice(theta.shape[0], size=m, p=w)
            z = rng.standard_normal((m, theta.shape[1]))
            if len(kern) == 1:
                X = theta[parent] + z @ kern[0].T
            else:
                X = theta[parent] + np.einsum("mij,mj->mi", np.asarray(kern)[parent], z)
            inside = np.all((X >= lo) & (X <= hi), axis=1)
            if counts is not None:
                counts[0] += m
                counts[1] += int(inside.sum())
            out = np.vstack([out, X[inside]])
        return out[:k]

    @staticmethod
    def _log_kernel_mix(kern, theta, w, X) -> np.ndarray:
        """log sum_j w_j K_j(X | theta_j) for every row of X."""
        terms = np.empty((X.shape[0], theta.shape[0]))
        for j in range(theta.shape[0]):
            L = kern[0] if len(kern) == 1 else kern[j]
            terms[:, j] = _log_mvn(X - theta[j], L) + math.log(w[j])
        top = terms.max(axis=1, keepdims=True)
        return (top + np.log(np.exp(terms - top).sum(axis=1, keepdims=True)))[:, 0]

    # ------------------------------------------------------------------ outputs
    @staticmethod
    def _diagnostics(ev, theta, w, dist, eps_hist, acc_hist, ess_hist) -> dict:
        X = ev.project(theta)
        post = {}
        for j, name in enumerate(ev.names):
            q = weighted_quantiles(X[:, j], w, QUANTILES)
            mean = float(w @ X[:, j])
            post[name] = {
                "mean": mean,
                "std": float(np.sqrt(w @ (X[:, j] - mean) ** 2)),
                **{f"p{q_:g}": float(v) for q_, v in zip(QUANTILES, q)},
                "median": float(q[QUANTILES.index(50.0)]),
            }
        return {
            "names": list(ev.names),
            "particles": X,
            "weights": w,
            "distances": dist,
            "epsilon": [None if not math.isfinite(e) else e for e in eps_hist],
            "acceptance": acc_hist,
            "ess": ess_hist,
            "generations": len(eps_hist),
            "posterior": post,
        }
