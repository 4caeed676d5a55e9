"""Hostile configs: `config check` passes exactly what `fit` accepts, and nothing it passes runs
away before its first evaluation.

Every setting of a recipe (the kernel's sections and the chosen plugins' settings, defaults
included) is given hostile values: wrong types, NaN and infinities, huge, negative and fractional
numbers, empty strings, unknown keys. For each config, the check (`load_config` and `preflight`,
what `bforest config check` runs) either refuses it with a ConfigError or passes it; a config it
passes must then reach the fit's first evaluation without an error, within 60 s and 2 GB more
memory than the process held before (a child process with a limit on its address space).
"""

from __future__ import annotations

import json
import math
import resource
import sys
import time
import tomllib
from pathlib import Path

import numpy as np
import pytest
import tomli_w

import bforest_core as bf
from conftest import toy_config

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="fork and RLIMIT_AS")

#: the recipe every hostile config is made from: the toy model's target (grown in milliseconds),
#: the real feature set, distance and optimisers, so their settings are fuzzed too
BASE_EXTRA = {
    "features": {"kind": "branch-segment", "sets": ["S0,1"], "topology": "source", "min_rows": 2},
    "distance": {"kind": "sliced", "lines": 16},
    "select": {"top": 2, "sets": 2},
}
OPTIMIZERS = {
    "ga": {"population": 8, "generations": 2},
    "cma": {"population": 6},
    "de": {"popsize": 3, "maxiter": 2},
    "nlopt": {},
    "abc-smc": {"particles": 8, "generations": 2},
    "emcee": {"walkers": 8, "steps": 4, "burn_in": 1},
    "turbo": {"batch": 2},
}
LIMIT_SECONDS, LIMIT_BYTES = 60, 2 << 30
#: the test model's own switches (a sleep per tree, a failure threshold) are not the product's
TOY_SETTINGS = (("ssm", "sleep"), ("ssm", "fail_above"), ("target", "generate", "settings"))


def _base(tmp_path: Path, optimizer: str) -> dict:
    raw = tomllib.loads(toy_config(tmp_path, budget=8).read_text())
    raw.update(json.loads(json.dumps(BASE_EXTRA)))
    raw["optimizer"] = {"kind": optimizer, **OPTIMIZERS[optimizer]}
    cfg = bf.config.parse_config(raw, base_dir=tmp_path)
    return bf.config.config_to_dict(cfg)  # every setting, the plugins' defaults included


def _leaves(table: dict, path=()):
    for k, v in table.items():
        if isinstance(v, dict) and v:
            yield from _leaves(v, (*path, k))
        else:
            yield (*path, k), v


def _hostile(value) -> list:
    if isinstance(value, bool):
        return ["yes", 2]
    if isinstance(value, int):
        return [-1, 0, 10.5, 10**8, 10**12, math.nan, math.inf, "", "12"]
    if isinstance(value, float):
        return [math.nan, math.inf, -math.inf, -1.0, 0.0, 1e8, 1e300, "", True]
    if isinstance(value, str):
        return ["", 1e8, "x" * 300]
    if isinstance(value, list):
        return ["", [], [1e8], [math.nan]]
    return [""]


def _set(raw: dict, path: tuple, value) -> dict:
    out = json.loads(json.dumps(raw))
    node = out
    for k in path[:-1]:
        node = node[k]
    node[path[-1]] = value
    return out


def hostile_configs(tmp_path: Path) -> list[tuple[str, dict]]:
    """(name, config table): every leaf of every optimiser's recipe given each hostile value,
    one unknown key per table, a few hand-picked runaways (in the probe's words)."""
    out = []
    for opt in OPTIMIZERS:
        base = _base(tmp_path, opt)
        for path, value in _leaves(base):
            if any(path[: len(t)] == t for t in TOY_SETTINGS):
                continue
            if path[0] == "optimizer" or opt == "ga":  # the kernel's sections once, each optimiser's own
                out += [(f"{'.'.join(map(str, path))} = {v!r}", _set(base, path, v)) for v in _hostile(value)]
        tables = {p[:-1] for p, _ in _leaves(base)}
        if opt == "ga":
            out += [(f"unknown key in [{'.'.join(t)}]", _set(base, (*t, "bogus_key"), 1)) for t in tables]
    base = _base(tmp_path, "ga")
    out += [
        (
            "integer bounds without a whole number",
            _set(base, ("ssm", "free", "angle"), {"lower": 5.2, "upper": 5.8, "integer": True}),
        ),
        ("process executor of 10**6 workers", _set(base, ("executor",), {"kind": "process", "workers": 10**6})),
        ("all-zero weights", _set(base, ("objective", "weights"), {"S0,1": 0.0})),
        (
            "a term of 10**8 lines",
            _set(
                base,
                ("objective", "terms"),
                [{"name": "t", "features": BASE_EXTRA["features"], "distance": {"kind": "sliced", "lines": 10**8}}],
            ),
        ),
    ]
    return out


class _FirstEvaluation(Exception):
    pass


def _run_all(listing: Path) -> list:
    """In a fresh process with an address-space limit: check each config of ``listing`` (JSON
    ``[[name, path], ...]``) and, when it passes, run its fit to the first evaluation. Returns
    ``[name, outcome, message, seconds]`` per config."""
    import signal
    import warnings

    from bforest_core.errors import ConfigError
    from bforest_core.pipeline import fit as fit_mod
    from bforest_core.pipeline.checks import preflight

    warnings.simplefilter("ignore")
    vm = int(next(ln for ln in open("/proc/self/status") if ln.startswith("VmSize")).split()[1]) * 1024
    resource.setrlimit(resource.RLIMIT_AS, (vm + LIMIT_BYTES, vm + LIMIT_BYTES))

    real = fit_mod.Evaluator.__call__

    def first(self, X):  # the first point is evaluated, then the fit stops
        real(self, np.atleast_2d(X)[:1])
        ev = self.store.evaluations()[0]
        raise _FirstEvaluation(ev.status, ev.message)

    def late(signum, frame):
        raise TimeoutError(f"past {LIMIT_SECONDS} s")

    fit_mod.Evaluator.__call__ = first
    signal.signal(signal.SIGALRM, late)
    results = []
    for name, path in json.loads(listing.read_text()):
        path = Path(path)
        t0 = time.monotonic()
        signal.alarm(LIMIT_SECONDS)
        try:
            try:
                cfg = bf.load_config(path)
                preflight(cfg)
            except ConfigError as exc:
                outcome = ("refused", str(exc)[:300])
            except Exception as exc:  # noqa: BLE001 - the check must not raise anything else
                outcome = ("check raised", f"{type(exc).__name__}: {exc}"[:300])
            else:
                try:
                    fit_mod.fit(bf.load_config(path), path.with_suffix(".run"), progress=False)
                    outcome = ("fit ended before its first evaluation", "")
                except _FirstEvaluation as exc:  # a model's own failure is a status; an "error" is a fault
                    outcome = ("first evaluation failed", exc.args[1]) if exc.args[0] == "error" else ("ran", "")
                except BaseException as exc:  # noqa: BLE001 - MemoryError, TimeoutError, the fit's refusal
                    outcome = ("fit refused", f"{type(exc).__name__}: {exc}"[:300])
        finally:
            signal.alarm(0)
        results.append([name, *outcome, time.monotonic() - t0])
    return results


def test_hostile_configs_config_check_passes_only_what_fit_runs(toy_plugin, tmp_path):
    import os
    import subprocess

    from conftest import TOY_DIR

    cases = hostile_configs(tmp_path)
    assert len(cases) >= 100
    listing = []
    for i, (name, raw) in enumerate(cases):
        path = tmp_path / f"c{i:03d}.toml"
        path.write_text(tomli_w.dumps(raw))
        listing.append([name, str(path)])
    (tmp_path / "cases.json").write_text(json.dumps(listing))
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(toy_plugin), str(TOY_DIR), os.environ.get("PYTHONPATH", "")]),
    }
    r = subprocess.run(
        [sys.executable, __file__, str(tmp_path / "cases.json")], env=env, capture_output=True, text=True, timeout=600
    )
    assert r.returncode == 0, r.stderr[-3000:]
    results = json.loads(r.stdout.strip().splitlines()[-1])
    bad = [x for x in results if x[1] not in ("refused", "ran")]
    assert not bad, "\n".join(f"{n}: {o}: {m} ({s:.1f} s)" for n, o, m, s in bad)
    refused = [x for x in results if x[1] == "refused"]
    assert len(refused) > len(cases) / 2  # most hostile values are refused, each naming its key
    assert all("\n" not in x[2] for x in refused)


if __name__ == "__main__":  # the child of the test above
    print(json.dumps(_run_all(Path(sys.argv[1]))))


def test_more_workers_than_cores_start_as_many_as_there_are_cores_with_a_warning():
    from bforest_core.processes import available_cores

    ex = bf.component("executor", "process", workers=available_cores() + 3)
    assert ex.workers == available_cores()
    with pytest.warns(UserWarning, match=rf"executor.workers = {available_cores() + 3} is more than the"):
        ex.start()
    try:
        assert len(ex._workers) == available_cores()
    finally:
        ex.shutdown()
