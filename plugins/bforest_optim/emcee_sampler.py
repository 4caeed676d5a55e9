"""An ensemble MCMC sampler (emcee) of the approximate posterior ``exp(-D / epsilon)``.

The prior is uniform in the bounds (integer parameters: uniform over their whole numbers — the
walkers move in a continuous box widened by 0.5 on each side of an integer range and the point
is rounded before evaluation). The likelihood is ``exp(-D(x) / epsilon)``, the ABC-style kernel
of the structural distance ``D``; ``epsilon`` sets how much worse than the best a parameter set
may fit and still carry posterior weight.

``epsilon = "noise"`` (the default) takes the distance's own noise: the standard deviation of
``D`` at the best initial walker under ``noise_seeds`` other model seeds (``problem.seed_spread``),
times ``epsilon_scale``. That is the spread a *perfect* model would still show against the data,
so parameter sets whose distance is within a few noise widths of the best are kept plausible and
no others: the posterior's width comes from the data and the model's stochasticity, not from the
initial box. Where the problem cannot measure seed noise (no ``seed_spread``, or a deterministic
model with zero spread) it falls back to ``auto``.

``epsilon = "auto"`` (the earlier default) takes the spread of the distances of the initial
walkers (spread over the initial box): ``1.4826 * MAD`` (the median absolute deviation scaled to a
standard deviation for normal data, robust to failed simulations), falling back to their standard
deviation, then to 1, and multiplied by ``epsilon_scale``. That is a *tempered* choice: it keeps
every region that fits about as well as a typical initial guess plausible, so its intervals are
wide and their coverage is not known. A number sets epsilon directly.

Parallelism: emcee's moves update the ensemble in two halves (the red-blue split its detailed
balance needs), and ``vectorize=True`` hands each half to the log-probability at once, so each
``problem.evaluate`` call holds ``walkers / 2`` points (the initial ensemble: all walkers).
Proposals outside the bounds get ``-inf`` without being evaluated.
"""

from __future__ import annotations

import logging
import math
import warnings
from typing import Literal

import numpy as np
from pydantic import Field, model_validator

from bforest_core.interfaces import Optimizer, OptimizeResult, Problem

from .box import (
    MAX_NOISE_SEEDS,
    MAX_POINTS,
    Box,
    History,
    OptimizerSettings,
    SamplingName,
    finite_or_none,
    make_result,
    sampling_field,
    seed_noise,
)

PERCENTILES = (2.5, 16.0, 50.0, 84.0, 97.5)
#: the most walker positions the chain holds (emcee keeps it in memory, allocated up front)
MAX_CHAIN = 5_000_000


class EmceeSettings(OptimizerSettings):
    """Settings of the ``emcee`` sampler."""

    walkers: int | None = Field(
        None,
        ge=2,
        le=MAX_POINTS,
        description="walkers (even, at least 2 * dimension; default max(2 * dimension + 2, 16))",
    )
    steps: int = Field(
        200,
        ge=1,
        description="length of the chain: ensemble steps, each evaluating every walker once (not the "
        "evaluation budget, which is [stop] max_evaluations and may end the chain earlier); the chain "
        f"is held in memory: walkers x steps at most {MAX_CHAIN:,}",
    )
    burn_in: int = Field(50, ge=0, description="steps discarded before the posterior summaries")
    moves: Literal["stretch", "de", "de_snooker", "walk"] = Field(
        "stretch", description="emcee move: stretch (affine-invariant), de (differential evolution), de_snooker, walk"
    )
    epsilon: float | Literal["noise", "auto"] = Field(
        "noise",
        description="temperature of exp(-D/epsilon): noise = the sd of D between model seeds at the "
        "best initial walker (falls back to auto where there is no seed noise), auto = 1.4826 * MAD of the "
        "initial walkers' distances, or a positive number",
    )
    epsilon_scale: float = Field(1.0, gt=0, description="multiplies the noise or auto epsilon")
    noise_seeds: int = Field(8, ge=2, le=MAX_NOISE_SEEDS, description="model seeds of the noise epsilon's measurement")
    init_sampling: SamplingName = sampling_field("lhs")

    @model_validator(mode="after")
    def _check(self):
        if self.walkers is not None and self.walkers % 2:
            raise ValueError(f"walkers must be even (got {self.walkers})")
        if (self.walkers or 16) * self.steps > MAX_CHAIN:
            raise ValueError(
                f"walkers x steps = {self.walkers or 16} x {self.steps} exceeds {MAX_CHAIN:,} positions: the "
                "chain is held in memory (fewer steps: the budget, [stop] max_evaluations, ends a chain anyway)"
            )
        if not isinstance(self.epsilon, str) and not (self.epsilon > 0 and math.isfinite(self.epsilon)):
            raise ValueError(f"epsilon must be a positive number, 'noise' or 'auto' (got {self.epsilon})")
        return self


def auto_epsilon(f: np.ndarray) -> float:
    """``1.4826 * MAD`` of the finite values of ``f``; else their standard deviation; else 1."""
    fin = f[np.isfinite(f)]
    if fin.size >= 2:
        mad = 1.4826 * float(np.median(np.abs(fin - np.median(fin))))
        if mad > 0:
            return mad
        sd = float(fin.std())
        if sd > 0:
            return sd
    return 1.0


def _move(name: str):
    import emcee

    return {
        "stretch": emcee.moves.StretchMove,
        "de": emcee.moves.DEMove,
        "de_snooker": emcee.moves.DESnookerMove,
        "walk": emcee.moves.WalkMove,
    }[name]()


class EmceeSampler(Optimizer):
    """Affine-invariant ensemble sampling of ``exp(-D/epsilon)`` under a uniform prior.

    Seeded through ``sampler.random_state`` (a ``numpy.random.RandomState`` from
    ``problem.seed``); the initial walkers come from a seeded Latin hypercube over the initial
    box.

    Returns
    -------
    OptimizeResult
        ``x``/``fun``: the best point seen (the MAP of the approximate posterior = the smallest
        distance). ``history``: one record per step (``step``, ``mean`` distance of the walkers,
        ``acceptance`` fraction so far). ``diagnostics``: ``epsilon``, ``walkers``, ``steps``
        (done), ``burn_in`` (used), ``acceptance_fraction`` (mean over walkers),
        ``autocorr_time`` (per parameter, None where the chain is too short to tell) and
        ``autocorr_reliable`` (chain after burn-in longer than 50 autocorrelation times),
        ``posterior`` (per parameter: median, p2.5, p16, p84, p97.5, mean, std after burn-in;
        integer parameters rounded), ``names``, ``chain`` ``(steps, walkers, dim)`` and
        ``distances`` ``(steps, walkers)`` arrays (for corner and trace plots).
    """

    name = "emcee"
    summary = "emcee ensemble sampler of exp(-D/epsilon): best fit plus posterior summaries"
    Settings = EmceeSettings
    posterior_kind = "chain"

    @classmethod
    def budget_settings(cls, settings, budget):
        """As many ``steps`` as the budget: every step evaluates at least one walker, so the
        budget ends the run."""
        return {**settings, "steps": int(budget)}

    def minimize(self, problem: Problem) -> OptimizeResult:
        import emcee

        s: EmceeSettings = self.settings
        ev = Box(problem)
        log = History(problem)
        p = ev.dim
        nw = s.walkers if s.walkers is not None else max(2 * p + 2, 16)
        nw += nw % 2
        if nw < 2 * p:
            raise ValueError(f"emcee needs at least 2 * dimension = {2 * p} walkers (got walkers = {nw})")
        blo, bhi = ev.relaxed_bounds("bounds")
        ilo, ihi = ev.relaxed_bounds("init")
        init_ss, mcmc_ss = np.random.SeedSequence([int(problem.seed), 0xE3]).spawn(2)
        coords = self._initial_walkers(ev, nw, ilo, ihi, np.random.default_rng(init_ss), s.init_sampling)
        f0 = ev(coords)
        eps, eps_rule = self._epsilon(problem, ev, f0)

        def log_prob(X):
            X = np.atleast_2d(X)
            out = np.full(X.shape[0], -np.inf)
            inside = np.all((X >= blo) & (X <= bhi), axis=1)
            if inside.any():
                f = ev(X[inside])
                out[inside] = np.where(np.isfinite(f), -f / eps, -np.inf)
            return out

        lp0 = np.where(np.isfinite(f0), -f0 / eps, -np.inf)
        sampler = emcee.EnsembleSampler(nw, p, log_prob, moves=_move(s.moves), vectorize=True)
        sampler.random_state = np.random.RandomState(np.random.MT19937(mcmc_ss)).get_state()
        log(
            ev, step=0, mean=float(np.mean(f0[np.isfinite(f0)])) if np.isfinite(f0).any() else math.inf, acceptance=None
        )
        reason = f"{s.steps} steps done"
        if not ev.stopped:
            state = emcee.State(coords, log_prob=lp0)
            for i, state in enumerate(sampler.sample(state, iterations=s.steps, progress=False), start=1):  # noqa: B020
                d = -state.log_prob * eps
                fin = np.isfinite(d)
                log(
                    ev,
                    step=i,
                    mean=float(d[fin].mean()) if fin.any() else math.inf,
                    acceptance=float(np.mean(sampler.acceptance_fraction)),
                )
                if ev.stopped:
                    break
        diagnostics = self._summaries(sampler, ev, eps, nw)
        diagnostics["epsilon_rule"] = eps_rule
        if int(sampler.iteration) < s.steps:
            diagnostics["stopped_short"] = (
                f"stopped after {int(sampler.iteration)} of {s.steps} steps "
                f"({ev.stop_reason('stopped')}): the chain may not have mixed"
            )
        return make_result(ev, log, reason, diagnostics)

    def _epsilon(self, problem: Problem, ev: Box, f0: np.ndarray) -> tuple[float, str]:
        """The temperature and the rule that gave it (see the module text)."""
        s: EmceeSettings = self.settings
        if not isinstance(s.epsilon, str):
            return float(s.epsilon), "given"
        if s.epsilon == "noise" and ev.best_x is not None:
            noise = seed_noise(problem, ev.best_x, s.noise_seeds)
            if noise > 0 and math.isfinite(noise):
                return noise * s.epsilon_scale, f"noise: sd of D over {s.noise_seeds} model seeds at the best walker"
        return auto_epsilon(f0) * s.epsilon_scale, "auto: 1.4826 * MAD of the initial walkers' distances"

    @staticmethod
    def _autocorr(sampler, burn: int, dim: int) -> np.ndarray:
        """Integrated autocorrelation time per parameter (``quiet``: emcee's "chain too short"
        warning is dropped; :attr:`autocorr_reliable` carries that information)."""
        lg = logging.getLogger("emcee.autocorr")
        disabled, lg.disabled = lg.disabled, True
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                return np.asarray(sampler.get_autocorr_time(discard=burn, quiet=True), float).reshape(dim)
        except Exception:  # too short a chain to estimate anything
            return np.full(dim, np.nan)
        finally:
            lg.disabled = disabled

    @staticmethod
    def _initial_walkers(ev, nw, ilo, ihi, rng, method):
        """Walkers spread over the (relaxed) initial box; continuous even in integer directions,
        so the ensemble is not degenerate."""
        from scipy.stats import qmc

        if method == "random":
            U = rng.random((nw, ev.dim))
        elif method == "lhs":
            U = qmc.LatinHypercube(ev.dim, rng=rng).random(nw)
        elif method == "halton":
            U = qmc.Halton(ev.dim, rng=rng).random(nw)
        else:
            m = int(math.ceil(math.log2(nw)))
            U = qmc.Sobol(ev.dim, rng=rng).random_base2(m)[:nw]
        w = ihi - ilo
        # a degenerate initial range (init_lower == init_upper) gets a small spread in the bounds
        tiny = 1e-3 * ev.width
        lo = np.where(w > 0, ilo, np.maximum(ilo - tiny, ev.lower))
        hi = np.where(w > 0, ihi, np.minimum(ihi + tiny, ev.upper))
        return lo + U * (hi - lo)

    def _summaries(self, sampler, ev: Box, eps: float, nw: int) -> dict:
        n_done = int(sampler.iteration)
        out = {"epsilon": eps, "walkers": nw, "steps": n_done, "names": list(ev.names)}
        if n_done == 0:
            return {
                **out,
                "burn_in": 0,
                "posterior": {},
                "acceptance_fraction": None,
                "autocorr_time": None,
                "chain": np.empty((0, nw, ev.dim)),
                "distances": np.empty((0, nw)),
            }
        burn = self.settings.burn_in
        if burn >= n_done:  # stopped early: keep the second half of what there is
            out["note"] = f"only {n_done} steps done (burn_in {burn}); summaries use the last {n_done - n_done // 2}"
            burn = n_done // 2
        chain = sampler.get_chain()
        flat = chain[burn:].reshape(-1, ev.dim)
        flat = np.clip(np.where(ev.integer, np.rint(flat), flat), ev.lower, ev.upper)
        q = np.percentile(flat, PERCENTILES, axis=0)
        posterior = {
            n: {
                "median": float(q[2, j]),
                "p2.5": float(q[0, j]),
                "p16": float(q[1, j]),
                "p84": float(q[3, j]),
                "p97.5": float(q[4, j]),
                "mean": float(flat[:, j].mean()),
                "std": float(flat[:, j].std()),
            }
            for j, n in enumerate(ev.names)
        }
        tau = self._autocorr(sampler, burn, ev.dim)
        n_kept = n_done - burn
        return {
            **out,
            "burn_in": burn,
            "posterior": posterior,
            "acceptance_fraction": float(np.mean(sampler.acceptance_fraction)),
            "acceptance_fraction_per_walker": np.asarray(sampler.acceptance_fraction, float),
            "autocorr_time": {n: finite_or_none(t) for n, t in zip(ev.names, tau)},
            # emcee's rule of thumb: the estimate is trustworthy for chains longer than 50 tau
            "autocorr_reliable": bool(np.all(np.isfinite(tau)) and n_kept >= 50 * np.max(tau)),
            "chain": chain,
            "distances": -sampler.get_log_prob() * eps,
        }
