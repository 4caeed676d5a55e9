"""Derivative-free bounded optimisers of NLopt, selected by name.

NLopt calls the objective one point at a time, so every evaluation is a separate
``problem.evaluate(x[None, :])`` call (no parallelism inside one run: use ``ga``, ``de`` or
``emcee`` to keep several workers busy).
"""

from __future__ import annotations

import math

import numpy as np
from pydantic import Field, field_validator, model_validator

from bforest_core.interfaces import Optimizer, OptimizeResult, Problem

from .box import MAX_POINTS, Box, History, OptimizerSettings, make_result

#: algorithms that need a local optimiser (``set_local_optimizer``)
_NEEDS_LOCAL = {"GN_MLSL", "GN_MLSL_LDS", "G_MLSL", "G_MLSL_LDS"}
#: what NLopt's objective gets for a failed simulation (some local methods choke on inf)
_FAILED = 1e30


def derivative_free_algorithms() -> list[str]:
    """Names of the derivative-free bound-constrained NLopt algorithms of the installed NLopt."""
    import nlopt

    return sorted(a for a in dir(nlopt) if (a.startswith(("GN_", "LN_")) or a in _NEEDS_LOCAL) and "AUGLAG" not in a)


def resolve_algorithm(name: str) -> str:
    """The NLopt constant name for ``name``: case-insensitive, with or without the ``GN_``/``LN_``
    prefix (``"crs2_lm"`` -> ``"GN_CRS2_LM"``, ``"sbplx"`` -> ``"LN_SBPLX"``).

    Raises
    ------
    ValueError
        For a gradient-based or unknown algorithm, listing the known ones.
    """
    known = derivative_free_algorithms()
    key = str(name).strip().upper().replace("-", "_")
    for cand in (key, "GN_" + key, "LN_" + key, "G_" + key):
        if cand in known:
            return cand
    if key.startswith(("GD_", "LD_")) or key in ("MMA", "CCSAQ", "SLSQP", "LBFGS", "TNEWTON", "STOGO"):
        raise ValueError(
            f"NLopt algorithm {name!r} needs gradients, which the structural distance does "
            f"not have; use a derivative-free one: {', '.join(known)}"
        )
    raise ValueError(f"unknown NLopt algorithm {name!r}; derivative-free ones: {', '.join(known)}")


class NloptSettings(OptimizerSettings):
    """Settings of the ``nlopt`` optimiser."""

    algorithm: str = Field(
        "GN_CRS2_LM",
        description="a derivative-free NLopt algorithm, with or without "
        "the GN_/LN_ prefix, any case: GN_CRS2_LM, GN_ISRES, GN_ESCH, GN_DIRECT_L, "
        "GN_MLSL_LDS, LN_SBPLX, LN_NELDERMEAD, LN_BOBYQA, LN_COBYLA, ...",
    )
    population: int | None = Field(
        None, ge=1, le=MAX_POINTS, description="population of CRS2, ISRES, ESCH, MLSL (default: NLopt's own)"
    )
    local_algorithm: str | None = Field(
        None,
        description="local derivative-free algorithm: polishes the "
        "best point after the main run, or serves as MLSL's local "
        "optimiser (MLSL default: LN_SBPLX)",
    )
    local_maxeval: int | None = Field(
        None, ge=1, description="evaluations of the local polish (default 20 * (dimension + 1))"
    )
    xtol_rel: float | None = Field(
        None, gt=0, description="stop when a step changes every parameter by less than this relative amount"
    )
    ftol_rel: float | None = Field(
        None, gt=0, description="stop when the distance changes by less than this relative amount"
    )
    initial_step: float | None = Field(
        None,
        gt=0,
        le=1,
        description="first step of local algorithms as a fraction of each parameter's initial range (default: NLopt's)",
    )

    @model_validator(mode="before")
    @classmethod
    def _no_own_budget(cls, data):
        if isinstance(data, dict) and "maxeval" in data:
            raise ValueError("maxeval is gone: use [stop] max_evaluations, the evaluation budget")
        return data

    @field_validator("algorithm")
    @classmethod
    def _known(cls, v):
        return resolve_algorithm(v)

    @field_validator("local_algorithm")
    @classmethod
    def _known_local(cls, v):
        if v is None:
            return v
        v = resolve_algorithm(v)
        if not v.startswith("LN_"):
            raise ValueError(f"local_algorithm must be a local (LN_) algorithm, got {v}")
        return v


class NloptOptimizer(Optimizer):
    """Any derivative-free bounded NLopt algorithm, optionally followed by a local polish.

    Integer parameters are rounded before evaluation (NLopt sees a piecewise-constant function
    of them). NLopt's random numbers are seeded with ``nlopt.srand(problem.seed)`` just before
    each run, so results are reproducible. The main run starts from the centre of the initial box
    (global algorithms sample the global bounds; CRS2 and MLSL include the start point). When the
    problem stops, the callback calls ``opt.force_stop()`` (NLopt then raises ``nlopt.ForcedStop``,
    which is caught) and the best point seen is returned.

    Returns
    -------
    OptimizeResult
        ``history`` has one record per evaluation (``phase`` "global"/"local", ``f``, ``best``);
        ``diagnostics`` the algorithm names and NLopt's return codes.
    """

    name = "nlopt"
    summary = "NLopt derivative-free algorithms (CRS2, ISRES, ESCH, DIRECT, SBPLX, BOBYQA, ...)"
    Settings = NloptSettings

    def minimize(self, problem: Problem) -> OptimizeResult:
        import nlopt

        s: NloptSettings = self.settings
        ev = Box(problem)
        log = History(problem)
        p = ev.dim
        lo, hi = ev.relaxed_bounds("bounds")
        polish = s.local_algorithm is not None and s.algorithm not in _NEEDS_LOCAL
        local_maxeval = s.local_maxeval or 20 * (p + 1)
        # NLopt's own call limit of the main run: the budget left (less the polish), 1000 without
        # one (repeats of an evaluated point count here but not in the budget)
        rem = problem.remaining()
        maxeval = 1000 if rem is None else max(1, rem - (local_maxeval if polish else 0))

        def objective(x, grad):
            if ev.stopped:
                # Not ``raise nlopt.ForcedStop``: CRS2 and DIRECT keep calling after a Python
                # exception and NLopt's wrapper then fails with SystemError. force_stop() makes
                # every algorithm return at once (optimize() raises ForcedStop, caught below).
                current.force_stop()
                return _FAILED
            val = float(ev(x[None, :])[0])
            log(ev, phase=phase, f=val)
            return val if math.isfinite(val) else _FAILED

        def build(alg, n_eval):
            opt = nlopt.opt(getattr(nlopt, alg), p)
            opt.set_lower_bounds(lo)
            opt.set_upper_bounds(hi)
            opt.set_min_objective(objective)
            opt.set_maxeval(int(n_eval))
            if s.xtol_rel is not None:
                opt.set_xtol_rel(s.xtol_rel)
            if s.ftol_rel is not None:
                opt.set_ftol_rel(s.ftol_rel)
            if s.initial_step is not None:
                opt.set_initial_step(
                    s.initial_step * np.where(ev.integer, np.maximum(ev.init_width, 1.0), ev.init_width)
                )
            return opt

        codes = {}
        phase = "global"
        opt = current = build(s.algorithm, maxeval)
        if s.population is not None:
            opt.set_population(int(s.population))
        if s.algorithm in _NEEDS_LOCAL:
            local = nlopt.opt(getattr(nlopt, s.local_algorithm or "LN_SBPLX"), p)
            local.set_xtol_rel(s.xtol_rel or 1e-4)
            local.set_ftol_rel(s.ftol_rel or 1e-6)
            opt.set_local_optimizer(local)
        x0 = np.clip(ev.project(0.5 * (ev.init_lower + ev.init_upper))[0], lo, hi)
        codes["global"] = self._run(opt, x0, seed=problem.seed)
        if polish and not ev.stopped and ev.best_x is not None:
            phase = "local"
            opt = current = build(s.local_algorithm, local_maxeval)
            codes["local"] = self._run(opt, np.clip(ev.best_x, lo, hi), seed=problem.seed)
        reason = f"NLopt {s.algorithm}: {codes['global']}" + (
            f"; polish {s.local_algorithm}: {codes['local']}" if "local" in codes else ""
        )
        diagnostics = {
            "algorithm": s.algorithm,
            "local_algorithm": s.local_algorithm,
            "maxeval": maxeval,
            "nlopt_result": codes,
        }
        return make_result(ev, log, reason, diagnostics)

    @staticmethod
    def _run(opt, x0, seed) -> str:
        import nlopt

        names = {
            nlopt.SUCCESS: "success",
            nlopt.STOPVAL_REACHED: "stopval reached",
            nlopt.FTOL_REACHED: "ftol reached",
            nlopt.XTOL_REACHED: "xtol reached",
            nlopt.MAXEVAL_REACHED: "maxeval reached",
            nlopt.MAXTIME_REACHED: "maxtime reached",
            nlopt.FORCED_STOP: "forced stop",
            nlopt.ROUNDOFF_LIMITED: "roundoff limited",
        }
        nlopt.srand(int(seed) % (2**63))
        try:
            opt.optimize(np.asarray(x0, float))
        except nlopt.ForcedStop:
            return "forced stop (the problem stopped)"
        except nlopt.RoundoffLimited:
            return "roundoff limited"
        code = opt.last_optimize_result()
        return names.get(code, f"code {code}")
