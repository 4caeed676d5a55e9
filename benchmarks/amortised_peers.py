"""The amortised estimator beside the tools a user would pick instead, in one run, on the same SOT
synthetic targets and simulator: pyABC 0.13's ABC-SMC, sbi's sequential NPE, and this project's
abc-smc (the calibrated settings of docs/calibration.md), each given ``--budget`` simulations per
target; the amortised estimator spends none per target (its training is counted once).

The targets are the first ``--targets`` draws of the shipped SOT estimator's calibration stream that
grow a tree (a pine-form crown scaled to 8-16 m, parameters uniform in bforest init's box for it).
Every method infers the target's 19 parameters with that box as its (uniform) prior and grows trees
as the target was grown (the same model settings and world); pyABC and sbi compare the trees'
summaries (the estimator's 95 values: pyABC by its adaptive Euclidean distance, each summary
scaled by its median absolute deviation over the trees that grew),
this project's abc-smc its own objective (the sliced distance on S0,1 and B1,2). Per method it
prints the simulations and wall time per target, the coverage of the central 50 % and 90 %
intervals (over targets and parameters) and the median error of the posterior mean (a share of
the prior's range).

It needs torch, sbi and pyABC, which Bayes Forest does not: install them into a venv of their own,
the CPU build of torch lying on the machine pinned exactly::

    python3 -m venv peers && peers/bin/pip install torch==2.13.0
    peers/bin/pip install pyabc==0.13.0 sbi && peers/bin/pip install -e '.[amortised]'
    peers/bin/python benchmarks/amortised_peers.py --targets 10 --budget 2000 --out runs/peers

Finished targets are kept in ``OUT/peers.json`` per method and not redone.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np

import bforest_core as bf
from bforest_core.errors import SimulationFailed
from bforest_core.pipeline import amortised as am
from bforest_core.pipeline.calibrate import central_interval
from bforest_core.pipeline.recipe import recipe_box

LEVELS = (50, 90)


class Target:
    """Draw ``i`` of the estimator's calibration stream: its box, its simulator and its tree."""

    def __init__(self, te, i: int, seed: int):
        self.te, self.i = te, i
        self.draw = te.prior.draw(seed, i, am.CALIBRATION_STREAM)
        m = am.scaled_measures(te.prior.references[self.draw.reference][1], self.draw.height)
        self.box = recipe_box(te.model, m)
        order = [self.box.names.index(k) for k in te.names]
        self.lower, self.upper = self.box.lower[order], self.box.upper[order]
        self.integer = self.box.integer[order]
        self.ssm = bf.component("ssm", te.model, **self.box.settings)
        self.fs = te.summaries.feature_set()
        self.tree = self.grow(self.draw.theta, self.draw.seed)
        self.x = None if self.tree is None else te.summaries.vector(self.tree, self.draw.height, self.fs)

    def params(self, theta) -> dict:
        v = [int(round(t)) if b else float(t) for t, b in zip(theta, self.integer)]
        return {**self.box.fixed, **dict(zip(self.te.names, v))}

    def grow(self, theta, seed: int):
        try:
            return self.ssm.simulate(self.params(np.clip(theta, self.lower, self.upper)), int(seed))
        except SimulationFailed:
            return None

    def summaries(self, theta, seed: int) -> np.ndarray | None:
        tree = self.grow(theta, seed)
        if tree is None:
            return None
        x = self.te.summaries.vector(tree, self.draw.height, self.fs)
        return x if np.all(np.isfinite(x)) else None


def scores(X: np.ndarray, w: np.ndarray, t: Target) -> dict:
    """Coverage of the central intervals and the error of the posterior mean, per parameter."""
    w = np.asarray(w, float) / np.sum(w)
    out = {f"covered{lev}": [] for lev in LEVELS}
    out["mean_error"] = []
    for j in range(X.shape[1]):
        truth = float(t.draw.theta[j])
        for lev in LEVELS:
            lo, hi = central_interval(X[:, j], w, lev)
            out[f"covered{lev}"].append(bool(lo <= truth <= hi))
        out["mean_error"].append(abs(float(w @ X[:, j]) - truth) / float(t.upper[j] - t.lower[j]))
    return out


# ------------------------------------------------------------------------------ the methods
def amortised(t: Target, budget: int, seed: int):
    X = t.te.estimator.sample(t.x[None, :], 1000, seed)[0]
    return X, np.ones(len(X)), 0


def pyabc_smc(t: Target, budget: int, seed: int, folder: Path):
    import pyabc

    rng = np.random.default_rng([seed, t.i])
    calls = {"n": 0}
    big = np.full(len(t.x), FAILED)

    def model(par):
        calls["n"] += 1
        x = t.summaries(np.array([par[k] for k in t.te.names]), int(rng.integers(1, 2**31 - 1)))
        return {"x": big if x is None else x}

    prior = pyabc.Distribution(
        **{k: pyabc.RV("uniform", lo, hi - lo) for k, lo, hi in zip(t.te.names, t.lower, t.upper)}
    )
    distance = pyabc.AdaptivePNormDistance(p=2, scale_function=_mad_of_grown)
    abc = pyabc.ABCSMC(model, prior, distance, population_size=200, sampler=pyabc.sampler.SingleCoreSampler())
    history = abc.new(f"sqlite:///{folder / f'pyabc_{t.i}.db'}", {"x": t.x})
    try:
        abc.run(max_total_nr_simulations=budget)
    except (AssertionError, ValueError) as exc:  # pyABC 0.13 on a population whose weights are NaN
        STOPPED[f"pyabc/{t.i}"] = f"stopped in generation {history.max_t + 1}: {exc}; its last population taken"
    df, w = history.get_distribution()
    return df[t.te.names].to_numpy(float), np.asarray(w, float), calls["n"]


#: why a method stopped early on a target, when it did (kept in its row of peers.json)
STOPPED: dict[str, str] = {}


#: the summaries pyABC is given for a tree that did not grow: far from every grown tree's
FAILED = 1e6


def _mad_of_grown(*, samples: np.ndarray, **_) -> np.ndarray:
    """pyABC's scale of each summary (the median absolute deviation) over the trees that grew.
    Over all simulations the failures (about half of SOT's prior draws: one constant vector each)
    made every summary's MAD 0, so every weight 0, every distance 0 and ε 0: pyABC accepted its
    first 200 draws and stopped, its posterior the prior."""
    grown = samples[np.all(samples < 0.5 * FAILED, axis=1)]
    s = grown if len(grown) >= 2 else samples
    return np.median(np.abs(s - np.median(s, axis=0)), axis=0)


def sbi_snpe(t: Target, budget: int, seed: int, rounds: int = 4):
    """sbi's sequential NPE (SNPE-C, ``rounds`` rounds of ``budget / rounds`` simulations) in the
    box's logit coordinates ``z`` (``theta = lower + (upper - lower) * sigmoid(z)``), where the
    uniform prior is the standard logistic distribution: the flow's support is then the whole
    space. In the box itself the flow's mass leaked out of it and sbi's rejection of the draws
    outside ran for over 20 minutes on the first target."""
    import torch
    from sbi.inference import NPE

    torch.manual_seed(seed * 1000 + t.i)
    rng = np.random.default_rng([seed, t.i, 5])

    def theta(z: torch.Tensor) -> np.ndarray:
        return t.lower + (t.upper - t.lower) / (1.0 + np.exp(-z.numpy().astype(float)))

    prior = _logistic(len(t.lower))
    inference, proposal, n = NPE(prior=prior), prior, 0
    x_o = torch.tensor(t.x, dtype=torch.float32)
    for _ in range(rounds):
        z = proposal.sample((budget // rounds,))
        xs = [t.summaries(theta(zi), int(rng.integers(1, 2**31 - 1))) for zi in z]
        n += len(xs)
        keep = [j for j, x in enumerate(xs) if x is not None]
        x = torch.tensor(np.array([xs[j] for j in keep]), dtype=torch.float32)
        est = inference.append_simulations(z[keep], x, proposal=proposal).train(show_train_summary=False)
        proposal = inference.build_posterior(est).set_default_x(x_o)
    X = theta(proposal.sample((1000,), show_progress_bars=False))
    return X, np.ones(len(X)), n


def _logistic(d: int):
    """``d`` independent standard logistic variables (the logit of a uniform one) as a torch
    distribution, its log density computed without overflow far in the tails."""
    import math

    import torch
    from torch.distributions import Distribution, constraints

    class Logistic(Distribution):
        arg_constraints: dict = {}
        support = constraints.real_vector

        def __init__(self):
            super().__init__(torch.Size(), torch.Size([d]), validate_args=False)

        @property
        def mean(self):
            return torch.zeros(d)

        @property
        def variance(self):
            return torch.full((d,), math.pi**2 / 3)

        def sample(self, sample_shape=torch.Size()):
            u = torch.rand(*sample_shape, d).clamp(1e-7, 1 - 1e-7)
            return torch.log(u) - torch.log1p(-u)

        def log_prob(self, z):
            a = z.abs()
            return (-a - 2 * torch.nn.functional.softplus(-a)).sum(-1)

    return Logistic()


def bforest_abc_smc(t: Target, budget: int, seed: int, folder: Path):
    from bforest_core.config import parse_config

    free = {k: {"lower": float(lo), "upper": float(hi)} for k, lo, hi in zip(t.te.names, t.lower, t.upper)}
    raw = {
        "seed": seed,
        "target": {
            "generate": {
                "ssm": t.te.model,
                "seed": t.draw.seed,
                "params": t.params(t.draw.theta),
                "settings": t.box.settings,
            }
        },
        "ssm": {"kind": t.te.model, **t.box.settings, "fixed": t.box.fixed, "free": free},
        "features": {"kind": "branch-segment", "sets": ["S0,1", "B1,2"], "small_sets": "keep"},
        "distance": {"kind": "sliced", "lines": 64},
        "objective": {"seed_mode": "per_evaluation", "timeout": 30.0},
        "optimizer": {
            "kind": "abc-smc",
            "particles": 100,
            "generations": 30,
            "epsilon_target": "noise",
            "posterior": "recycled",
            "adjust": "linear",
        },
        "stop": {"max_evaluations": budget},
        "select": {"top": 0},
        "report": {"enabled": False},
        "executor": {"kind": "serial"},
    }
    run = folder / f"abc_smc_{t.i}"
    res = bf.fit(parse_config(raw), run, overwrite=True, progress=False)
    from bforest_core.pipeline.posterior import read_posterior_csv

    names, X, w = read_posterior_csv(run / "posterior.csv")
    return X[:, [names.index(k) for k in t.te.names]], w, res.n_evaluations


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--targets", type=int, default=10)
    ap.add_argument("--budget", type=int, default=2000, help="simulations per target of each per-target method")
    ap.add_argument("--methods", nargs="+", default=["amortised", "pyabc", "sbi", "bforest-abc-smc"])
    ap.add_argument("--estimator", help="default: the shipped SOT estimator")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--out", default="runs/peers")
    args = ap.parse_args(argv)
    warnings.filterwarnings("ignore")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    path = out / "peers.json"
    results = json.loads(path.read_text()) if path.exists() else {}
    te = am.read_estimator(am.estimator_for("sot", args.estimator))
    targets, i = [], 0
    while len(targets) < args.targets:
        t = Target(te, i, args.seed)
        if t.x is not None and np.all(np.isfinite(t.x)):
            targets.append(t)
        i += 1
    run = {
        "amortised": lambda t: amortised(t, args.budget, args.seed),
        "pyabc": lambda t: pyabc_smc(t, args.budget, args.seed, out),
        "sbi": lambda t: sbi_snpe(t, args.budget, args.seed),
        "bforest-abc-smc": lambda t: bforest_abc_smc(t, args.budget, args.seed, out),
    }
    for method in args.methods:
        for t in targets:
            key = f"{method}/{t.i}"
            if key in results:
                continue
            t0 = time.monotonic()
            X, w, n = run[method](t)
            results[key] = {
                "method": method,
                "target": t.i,
                "simulations": n,
                "seconds": time.monotonic() - t0,
                **scores(X, w, t),
                **({"stopped": STOPPED[key]} if key in STOPPED else {}),
            }
            path.write_text(json.dumps(results, indent=1))
            print(f"{key}: {n} simulations, {results[key]['seconds']:.0f} s {STOPPED.get(key, '')}", flush=True)
    tr = te.header["training"]  # wall seconds are those of the training's last call (a resumed one grew nothing)
    print(
        f"training of the amortised estimator, once: {tr['simulations']} simulations "
        f"({tr['simulation_worker_seconds']:.0f} s of worker time), its flow {tr['training_wall_seconds']:.0f} s"
    )
    print(
        f"{'method':<18}{'targets':>8}{'sims/target':>12}{'s/target':>10}{'50 % covers':>13}{'90 % covers':>13}{'mean error':>12}"
    )
    for method in args.methods:
        rows = [r for r in results.values() if r["method"] == method]
        if not rows:
            continue
        c50 = np.mean([c for r in rows for c in r["covered50"]])
        c90 = np.mean([c for r in rows for c in r["covered90"]])
        err = np.median([e for r in rows for e in r["mean_error"]])
        print(
            f"{method:<18}{len(rows):>8}{np.median([r['simulations'] for r in rows]):>12.0f}"
            f"{np.median([r['seconds'] for r in rows]):>10.1f}{100 * c50:>12.0f}%{100 * c90:>12.0f}%{err:>12.3f}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
