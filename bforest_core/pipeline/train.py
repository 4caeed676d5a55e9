"""``bforest train``: grow trees from a model's prior on the executor, keep each as it finishes,
and train an amortised estimator on them; and the estimator's simulation-based calibration.

A training folder (:class:`~.store.TrainFiles`) holds its resolved config (``train.toml``), every
simulation (``simulations.sqlite``: the draw, its status and the tree's summaries, committed as
each finishes), the trained estimator (``estimator.npz``, :mod:`.amortised`) and what the training
did (``training.json``). Draw ``i`` depends on the run seed and ``i`` only, so a training killed
(kill -9 included) and resumed with ``--resume`` simulates only the draws it had not stored, and
``--resume`` with a larger ``simulations`` extends it. Trees that fail to grow (collapsed, too
many segments, timed out) are stored with their status and left out of the training: the
posterior of a tree that exists is the posterior given that the model grew one.

The calibration (:func:`calibrate_estimator`) draws targets from the estimator's own prior on
another stream, grows and summarises them the same way (stored likewise, so it resumes), and
checks the coverage of the central 50 % and 90 % posterior intervals and the ranks of the truths
as ``bforest calibrate`` does for a sampler (:mod:`.calibrate`).
"""

from __future__ import annotations

import json
import math
import os
import socket
import time
from pathlib import Path
from typing import Any, Optional

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from ..errors import BayesForestError, ConfigError, SimulationFailed, validation_error_text
from .amortised import (
    CALIBRATION_STREAM,
    TRAIN_STREAM,
    Summaries,
    TrainedEstimator,
    TrainingPrior,
    estimator_component,
    estimator_header,
    read_estimator,
    reference_trees,
    write_estimator,
)
from .store import SimulationStore, TrainFiles

#: draws sent to the executor at a time (the store is written as each finishes)
CHUNK = 256
#: posterior draws per target of a calibration (the ranks are among RANK_DRAWS of their quantiles)
CALIBRATION_DRAWS = 1000


class TrainError(BayesForestError):
    """A training folder cannot be used as asked (one line)."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class TrainSection(_Strict):
    """What to train on: the model, the crown form (its reference trees) and the prior's heights."""

    model: str = Field(..., description="the growth model (an installed ssm that writes recipes: sot, lignum)")
    references: list[str] = Field(
        ...,
        min_length=1,
        description="QSMs of the crown form (paths relative to this file, or sample:NAME): each draw scales "
        "one of them to a height and takes bforest init's box for it",
    )
    heights: tuple[float, float] = Field(..., description="heights (m) the references are scaled to, uniformly")
    simulations: int = Field(..., ge=1, description="trees drawn from the prior and grown (failures included)")
    timeout: float = Field(20.0, gt=0, description="seconds one growth may take before it counts as failed")


class TrainConfig(_Strict):
    """A training configuration (``bforest train CONFIG.toml``)."""

    seed: int = Field(1, ge=0, description="seeds every draw and the training")
    train: TrainSection
    estimator: dict[str, Any] = Field(
        default_factory=lambda: {"kind": "flow"}, description="the amortised estimator: kind and settings"
    )
    executor: dict[str, Any] = Field(
        default_factory=lambda: {"kind": "process"}, description="where the trees grow: kind and settings"
    )

    @field_validator("estimator", "executor")
    @classmethod
    def _kind(cls, v):
        if not isinstance(v.get("kind"), str):
            raise ValueError('needs kind = "<plugin name>"')
        return v


def load_train_config(path) -> TrainConfig:
    """Read and check a training configuration (paths relative to its folder)."""
    from ..config import read_toml, resolve_path

    path = Path(path)
    raw = read_toml(path)
    try:
        cfg = TrainConfig.model_validate(raw)
    except ValidationError as exc:
        raise ConfigError(f"{path}: {validation_error_text(exc)}") from None
    cfg.train.references = [resolve_path(r, path.resolve().parent) for r in cfg.train.references]
    _check_parts(cfg, str(path))
    return cfg


def _kind_and_settings(spec: dict) -> tuple[str, dict]:
    """A ``{kind, ...settings}`` table of a training config as (kind, settings)."""
    return spec["kind"], {k: v for k, v in spec.items() if k != "kind"}


def _check_parts(cfg: TrainConfig, source: str) -> None:
    from ..registry import component, discover

    problems = []
    if cfg.train.model not in discover().names("ssm"):
        problems.append(f"train.model: unknown ssm {cfg.train.model!r} (known: {', '.join(discover().names('ssm'))})")
    for section in ("estimator", "executor"):
        kind, settings = _kind_and_settings(getattr(cfg, section))
        try:
            component("amortised" if section == "estimator" else "executor", kind, **settings)
        except BayesForestError as exc:
            problems.append(f"{section}: {exc}")
    if problems:
        raise ConfigError(f"{source}: " + "; ".join(problems))


# ------------------------------------------------------------------------------ the worker side
_MODELS: dict[str, tuple] = {}  # (model, settings) -> (ssm, feature set), per worker process


def simulate_task(item: tuple) -> dict:
    """Grow and summarise one draw in a worker. Never raises: a failure comes back with its status."""
    from ..registry import component
    from .scoring import _MODEL_ERRORS, _simulate_with_timeout, _Timeout

    model, settings, params, seed, timeout, summaries, size = item
    key = json.dumps([model, settings, summaries], sort_keys=True, default=str)
    t0 = time.perf_counter()
    worker = f"{socket.gethostname()}:{os.getpid()}"
    try:
        if key not in _MODELS:
            defn = Summaries(*(tuple(v) if isinstance(v, list) else v for v in summaries))
            _MODELS[key] = (component("ssm", model, **settings), defn, defn.feature_set())
        ssm, defn, fs = _MODELS[key]
        tree = _simulate_with_timeout(ssm, params, seed, timeout)
        x = defn.vector(tree, size, fs)
    except SimulationFailed as exc:
        return dict(status=exc.status, message=str(exc)[:300], seconds=time.perf_counter() - t0, worker=worker)
    except _Timeout:
        return dict(status="timeout", message=f"growth exceeded {timeout} s", seconds=timeout, worker=worker)
    except _MODEL_ERRORS as exc:
        return dict(status="error", message=f"{type(exc).__name__}: {exc}"[:300], seconds=0.0, worker=worker)
    if not np.all(np.isfinite(x)):
        return dict(status="nan_summaries", message="a summary is not finite", seconds=0.0, worker=worker)
    return dict(status="ok", message="", summaries=x.tolist(), seconds=time.perf_counter() - t0, worker=worker)


def _lost(fn, item, status, message):
    """A draw whose worker died or was stopped (the process executor's stand-in result)."""
    return dict(status=status, message=message[:300], seconds=0.0, worker="")


# ------------------------------------------------------------------------------ simulating
def _summaries_spec(s: Summaries) -> list:
    return [list(s.statistics), list(s.sets), list(s.quantiles), s.features]


def simulate(
    prior: TrainingPrior,
    summaries: Summaries,
    store: SimulationStore,
    indices,
    seed: int,
    stream: int,
    timeout: float,
    executor,
    bar=None,
) -> int:
    """Grow and summarise the draws ``indices`` of ``stream`` not yet in ``store`` on
    ``executor``, storing each as it finishes; return how many were grown now."""
    spec = _summaries_spec(summaries)
    todo = sorted(set(int(i) for i in indices) - store.done())
    executor.on_lost = _lost
    executor.time_limit = lambda item: float(item[4]) + max(2.0, float(item[4]))
    n = 0
    with executor.started(None, ()):
        for at in range(0, len(todo), CHUNK):
            draws = [prior.draw(seed, i, stream) for i in todo[at : at + CHUNK]]
            items = [
                (prior.model, d.settings, d.params(prior.names, prior.integer), d.seed, timeout, spec, d.height)
                for d in draws
            ]
            for j, res in executor.map_unordered(simulate_task, items):
                d = draws[j]
                store.add(d.index, d.reference, d.height, items[j][2], d.seed, res)
                n += 1
                if bar is not None:
                    bar.update(1)
    return n


def training_pairs(store: SimulationStore, prior: TrainingPrior, limit: int | None = None):
    """``(theta (n, p), x (n, m), indices)`` of the grown trees (the first ``limit`` draws)."""
    rows = store.grown(limit)
    if not rows:
        return np.zeros((0, len(prior.names))), np.zeros((0, 0)), []
    theta = np.array([[r[2][n] for n in prior.names] for r in rows], float)
    x = np.vstack([r[3] for r in rows])
    return theta, x, [r[0] for r in rows]


# ------------------------------------------------------------------------------ the folder
def _prior_of(cfg: TrainConfig) -> TrainingPrior:
    return TrainingPrior.build(cfg.train.model, reference_trees(cfg.train.references), cfg.train.heights)


def _fingerprint(cfg: TrainConfig, prior: TrainingPrior) -> dict:
    """What the stored simulations depend on (a resumed training must match it)."""
    return {
        "seed": cfg.seed,
        "prior": prior.to_dict(),
        "timeout": cfg.train.timeout,
        "summary": Summaries().definition(),
    }


def _open_folder(out: Path, resume: bool, overwrite: bool, what: str) -> None:
    files = TrainFiles(out)
    held = files.simulations_path.exists() and _held(files) > 0
    if resume and overwrite:
        raise TrainError(f"{what}: --resume and --overwrite exclude each other")
    if resume and not held:
        raise TrainError(f"{out}: holds no simulations to resume (no {TrainFiles.SIMULATIONS})")
    if held and not (resume or overwrite):
        raise TrainError(
            f"{out}: already holds {_held(files)} simulations; continue with --resume, start anew with "
            "--overwrite, or choose another -o"
        )
    if out.exists() and not out.is_dir():
        raise TrainError(f"{out}: exists and is not a folder")
    out.mkdir(parents=True, exist_ok=True)
    if overwrite:
        files.clear()


def _held(files: TrainFiles) -> int:
    with SimulationStore(files.simulations_path) as st:
        return st.count()


def _check_same(store: SimulationStore, fp: dict, out: Path) -> None:
    old = store.get_meta("fingerprint")
    if old is not None and old != json.loads(json.dumps(fp, default=float)):
        raise TrainError(
            f"{out}: its simulations were drawn with another prior, seed, timeout or summaries; start anew "
            "with --overwrite or choose another -o"
        )


def _executor(spec: dict):
    from ..registry import component

    kind, settings = _kind_and_settings(spec)
    return component("executor", kind, **settings)


def train(config_path, out_dir, resume: bool = False, overwrite: bool = False, progress: bool = True) -> dict:
    """Grow ``[train] simulations`` trees from the prior, train the estimator, write its file.

    Returns
    -------
    dict
        The training record (also ``training.json``) with ``estimator`` (the file's path).
    """
    import tomli_w

    from .progress import progress_bar
    from .rundir import run_lock

    cfg = load_train_config(config_path)
    out = Path(out_dir)
    est = estimator_component(*_kind_and_settings(cfg.estimator))
    _open_folder(out, resume, overwrite, "train")
    files = TrainFiles(out)
    with run_lock(out):
        prior = _prior_of(cfg)
        summaries = Summaries()
        fp = _fingerprint(cfg, prior)
        with SimulationStore(files.simulations_path) as store:
            _check_same(store, fp, out)
            store.set_meta("fingerprint", fp)
            files.config_path.write_text(tomli_w.dumps(cfg.model_dump(mode="json")), encoding="utf-8")
            n = cfg.train.simulations
            t0 = time.monotonic()
            before = len(store.done() & set(range(n)))
            bar = progress_bar(n, "train", "tree", progress)
            bar.update(before)
            try:
                ex = _executor(cfg.executor)
                grown = simulate(prior, summaries, store, range(n), cfg.seed, TRAIN_STREAM, cfg.train.timeout, ex, bar)
            finally:
                bar.close()
            sim_wall = time.monotonic() - t0
            theta, x, _ = training_pairs(store, prior, n)
            statuses = store.statuses()
            sim_seconds = store.seconds()
        if len(theta) == 0:
            raise BayesForestError(f"{out}: no draw of the prior grew a tree ({statuses}); nothing to train on")
        t1 = time.monotonic()
        record = est.train(theta, x, prior.lower, prior.upper, prior.integer, cfg.seed)
        train_wall = time.monotonic() - t1
        training = {
            "simulations": n,
            "timeout": cfg.train.timeout,
            "grown_now": grown,
            "stored_before": before,
            "pairs": int(len(theta)),
            "statuses": statuses,
            "simulation_wall_seconds": sim_wall,
            "simulation_worker_seconds": sim_seconds,
            "training_wall_seconds": train_wall,
            "estimator": record,
        }
        header = estimator_header(prior, summaries, est, training, cfg.seed)
        path = write_estimator(files.estimator_path, header, est)
        from ..io import write_json

        write_json(files.record_path, {**training, "estimator_file": str(path)}, strict=True)
    return {**training, "estimator_file": path, "out_dir": out}


# ------------------------------------------------------------------------------ calibration
def calibrate_estimator(
    estimator,
    n: int,
    out_dir,
    executor: Optional[dict] = None,
    seed: int = 1,
    resume: bool = False,
    overwrite: bool = False,
    progress: bool = True,
) -> dict:
    """Simulation-based calibration of an amortised estimator on ``n`` targets drawn from its own
    prior (see the module text); the result has the keys of :func:`.calibrate.calibrate`'s."""
    from ..io import write_json
    from .calibrate import (
        LEVELS,
        RANK_DRAWS,
        _write_csv,
        coverage_table,
        posterior_params,
        rank_bins,
        table_text,
        uniform_band,
    )
    from .progress import progress_bar
    from .rundir import run_lock

    if int(n) < 1:
        raise ConfigError(f"calibrate: -n must be at least 1 (got {n})")
    te: TrainedEstimator = read_estimator(estimator)
    prior, out = te.prior, Path(out_dir)
    _open_folder(out, resume, overwrite, "calibrate")
    files = TrainFiles(out)
    timeout = float(te.header["training"].get("timeout", 20.0))
    fp = {"estimator": str(Path(estimator).resolve()), "seed": int(seed), "prior": prior.to_dict()}
    t0 = time.monotonic()
    with run_lock(out), SimulationStore(files.simulations_path) as store:
        _check_same(store, fp, out)
        store.set_meta("fingerprint", fp)
        ex = _executor(executor or {"kind": "process"})
        bar = progress_bar(int(n), "calibrate", "target", progress)
        try:
            upto, shown = int(n), 0
            while True:  # draws that grow no tree are no targets: draw on until n have grown
                simulate(prior, te.summaries, store, range(upto), seed, CALIBRATION_STREAM, timeout, ex)
                got = store.grown(upto)
                bar.update(min(len(got), int(n)) - shown)
                shown = min(len(got), int(n))
                if len(got) >= int(n) or upto >= 20 * int(n):
                    break
                rate = max(len(got), 1) / upto
                upto += max(8, math.ceil((int(n) - len(got)) / rate * 1.2))
        finally:
            bar.close()
        targets = got[: int(n)]
        statuses = store.statuses()
    if not targets:
        raise BayesForestError(f"calibrate: no draw of the prior grew a tree ({statuses})")
    X = np.vstack([t[3] for t in targets])
    draws = te.estimator.sample(X, CALIBRATION_DRAWS, seed)
    w = np.full(CALIBRATION_DRAWS, 1.0 / CALIBRATION_DRAWS)
    rows = []
    for (idx, _, params, _), S in zip(targets, draws):
        theta = np.array([params[k] for k in te.names], float)
        rows.append(
            {
                "run": f"target_{idx:05d}",
                "status": "ok",
                "truth": dict(zip(te.names, theta.tolist())),
                "params": posterior_params(S, w, te.names, theta, prior.integer, seed, idx),
            }
        )
    table = coverage_table(rows, te.names, prior.lower, prior.upper, prior.integer)
    bins = rank_bins(len(rows))
    from ..registry import component

    ssm = component("ssm", te.model)
    res = {
        "config": str(estimator),
        "optimizer": f"the amortised {te.header['estimator']['kind']} estimator",
        "ssm": te.model,
        "n": int(n),
        "names": list(te.names),
        "units": [ssm.parameter_spec(k).unit or "" for k in te.names],
        "lower": prior.lower.tolist(),
        "upper": prior.upper.tolist(),
        "levels": list(LEVELS),
        "rank_draws": RANK_DRAWS,
        "bins": bins,
        "band": list(uniform_band(len(rows), bins)),
        "table": table,
        "runs": rows,
        "counts": {"targets": len(rows), "draws": sum(statuses.values()), "statuses": statuses},
        "wall_seconds": time.monotonic() - t0,
        "out_dir": out,
    }
    res["table_text"] = table_text(res)
    res["json"] = write_json(files.calibration_path("json"), {k: v for k, v in res.items() if k != "json"}, strict=True)
    res["csv"] = _write_csv(files.calibration_path("csv"), rows, te.names)
    return res
