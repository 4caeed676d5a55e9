"""A small third-party-style plugin used by the core tests (installed through a temporary
``.dist-info`` entry point, exactly as a published plugin would be).

ToySSM grows a deterministic-under-seed tree: a vertical trunk of ``segments`` cylinders, each
trunk cylinder bearing one lateral of ``lateral_len`` m at ``angle`` degrees (with noise).
ToyFeatures gives one table per tree: [angle of each lateral to the vertical, lateral length].
ToyDistance is the absolute difference of column means (cheap, exact, known answers).
"""

from __future__ import annotations

import time

import numpy as np
from pydantic import Field

from bforest_core import (
    SSM,
    ComponentSettings,
    Distance,
    FeatureSet,
    Optimizer,
    OptimizeResult,
    ParameterSpec,
    SimulationFailed,
    Tree,
)
from bforest_core.hookspecs import hookimpl


class ToySSMSettings(ComponentSettings):
    sleep: float = Field(0.0, ge=0, description="seconds to sleep per simulation (tests timeouts)")
    fail_above: float = Field(1e9, description="raise SimulationFailed when angle exceeds this")
    gate: str = Field("", description="a file: simulations after the first gate_after of this process wait for it")
    gate_after: int = Field(0, ge=0, description="simulations this process runs before it waits for the gate")


#: simulations this process has run with a gate (tests hold a command at a known point)
_GATED = {"n": 0}


def wait_at_gate(gate: str, after: int) -> None:
    """Block while ``gate`` does not exist once ``after`` simulations of this process have passed
    it: a test holds a command at a known point, whatever the machine's speed, and lets it go on
    by creating the file."""
    import os

    _GATED["n"] += 1
    while _GATED["n"] > after and not os.path.exists(gate):
        time.sleep(0.02)


class ToySSM(SSM):
    name = "toy"
    summary = "toy model for tests"
    Settings = ToySSMSettings

    @property
    def parameters(self):
        return [
            ParameterSpec("angle", 45.0, 0.0, 90.0, unit="deg", description="lateral angle"),
            ParameterSpec("segments", 10, 2, 40, integer=True, description="trunk cylinders"),
            ParameterSpec("lateral_len", 0.5, 0.05, 3.0, unit="m"),
            ParameterSpec("noise", 2.0, 0.0, 20.0, unit="deg"),
        ]

    def simulate(self, params, seed):
        p = self.resolve_params(params)
        if self.settings.sleep:
            time.sleep(self.settings.sleep)
        if self.settings.gate:
            wait_at_gate(self.settings.gate, self.settings.gate_after)
        if p["angle"] > self.settings.fail_above:
            raise SimulationFailed("collapsed", "angle too large")
        rng = np.random.default_rng(seed)
        n = int(p["segments"])
        ang = np.radians(p["angle"] + p["noise"] * rng.standard_normal(n))
        az = rng.uniform(0, 2 * np.pi, n)
        trunk_start = np.c_[np.zeros(n), np.zeros(n), np.arange(n, dtype=float)]
        lat_axis = np.c_[np.sin(ang) * np.cos(az), np.sin(ang) * np.sin(az), np.cos(ang)]
        lat_start = trunk_start + [0, 0, 1.0]
        start = np.r_[trunk_start, lat_start]
        axis = np.r_[np.tile([0, 0, 1.0], (n, 1)), lat_axis]
        length = np.r_[np.ones(n), np.full(n, p["lateral_len"]) * (1 + 0.1 * rng.random(n))]
        radius = np.r_[np.linspace(0.2, 0.05, n), np.full(n, 0.02)]
        parent = np.r_[-1, np.arange(n - 1), np.arange(n)]
        ext = np.r_[np.arange(1, n), -1, np.full(n, -1)]
        return Tree(
            start,
            axis,
            length,
            radius,
            parent,
            ext,
            metadata={"model": "toy", "params": p, "seed": seed, "status": "ok"},
        )


class ToyFeatureSettings(ComponentSettings):
    sets: list[str] = ["L"]
    topology: str = "source"


class ToyFeatures(FeatureSet):
    name = "toy-features"
    Settings = ToyFeatureSettings

    @property
    def set_names(self):
        return list(self.settings.sets)

    def columns(self, set_name):
        return ["angle", "length"]

    def extract(self, tree):
        t = tree.with_topology(self.settings.topology)
        lat = t.order == 1
        ang = np.degrees(np.arccos(np.clip(t.axis[lat, 2], -1, 1)))
        table = np.c_[ang, t.length[lat]]
        return {s: table for s in self.settings.sets}


class ToyDistance(Distance):
    name = "toy-distance"

    def compute(self, u_model, u_data):
        if len(u_model) == 0 or len(u_data) == 0:
            return 1.0
        return float(np.abs(u_model.mean(0) - u_data.mean(0)).sum() / 100.0)


class ToyRandomSettings(ComponentSettings):
    batch: int = Field(8, ge=1)
    batches: int = Field(100, ge=1)


class ToyRandomSearch(Optimizer):
    """Seeded random search in batches (tests the pipeline without the real optimisers)."""

    name = "toy-random"
    Settings = ToyRandomSettings

    def expected_evaluations(self, dim):
        return self.settings.batch * self.settings.batches

    @classmethod
    def budget_settings(cls, settings, budget):
        # a field name the core does not know: only this class lifts it for a comparison
        return {**settings, "batches": -(-int(budget) // settings.get("batch", 8))}

    def minimize(self, problem):
        rng = np.random.default_rng(problem.seed)
        lo, hi = problem.init_box()
        for b in range(self.settings.batches):
            X = lo + (hi - lo) * rng.random((self.settings.batch, problem.dim))
            f = problem.evaluate(X)
            problem.log(
                {
                    "generation": b,
                    "best": float(problem.best_f),
                    "mean": float(np.mean(f[np.isfinite(f)])) if np.isfinite(f).any() else None,
                }
            )
            if problem.stopped:
                break
        return OptimizeResult(
            x=problem.best_x, fun=problem.best_f, n_evaluations=problem.n_evaluations, stop_reason=problem.stop_reason
        )


@hookimpl
def bforest_components():
    return [ToySSM, ToyFeatures, ToyDistance, ToyRandomSearch]
