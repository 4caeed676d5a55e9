"""Run directory and its SQLite evaluation log.

Layout (docs/architecture.md)::

    RUN/config.toml          the resolved configuration
    RUN/evaluations.sqlite   every evaluation, written as soon as it finishes; the held-out
                             scores of candidate points (table ``heldout``), likewise
    RUN/best.json            best parameters, per-set distances, classical metrics
    RUN/target.txt           the target tree (TreeQSM text) when generated or for the report
    RUN/best_tree.txt        the best-fit tree
    RUN/clones/              clone trees and their table
    RUN/figures/             PNG figures
    RUN/report.md            the summary

Only the main process writes; each row is committed on its own, so a killed run loses nothing
that finished. :meth:`RunStore.replay` gives the stored evaluations back in index order, which is
how ``--resume`` continues without repeating work.
"""
from __future__ import annotations

import json
import math
import re
import sqlite3
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..errors import BayesForestError

SCHEMA = """
CREATE TABLE IF NOT EXISTS evaluations (
    idx       INTEGER PRIMARY KEY,  -- evaluation index, 0-based, in the optimiser's order
    params    TEXT NOT NULL,        -- JSON {name: value}
    seeds     TEXT NOT NULL,        -- JSON list of model seeds
    distance  REAL NOT NULL,        -- objective value (penalty for failures)
    per_set   TEXT NOT NULL,        -- JSON {set: distance or null}
    status    TEXT NOT NULL,        -- ok | <SimulationFailed status> | timeout | error
    message   TEXT,
    seconds   REAL,
    worker    TEXT,
    n_rows    TEXT,                 -- JSON {set: model rows}
    finished  REAL                  -- unix time
);
CREATE TABLE IF NOT EXISTS log (
    seq    INTEGER PRIMARY KEY AUTOINCREMENT,
    record TEXT NOT NULL            -- JSON: one optimiser generation/iteration record
);
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT);
CREATE TABLE IF NOT EXISTS heldout (
    scoring   TEXT NOT NULL,        -- fingerprint of what a score depends on (target, model, objective)
    point     TEXT NOT NULL,        -- JSON {name: value}, keys sorted
    seeds     TEXT NOT NULL,        -- JSON list of held-out model seeds
    distance  REAL NOT NULL,
    status    TEXT NOT NULL,
    PRIMARY KEY (scoring, point, seeds)
);
"""



def slug(text: str) -> str:
    """A file-name-safe version of a set or parameter name (``"S0,1"`` -> ``"S0-1"``)."""
    s = re.sub(r"[^A-Za-z0-9_.-]+", "-", str(text)).strip("-")
    return s or "x"


class RunDirError(BayesForestError):
    pass


@dataclass
class Evaluation:
    idx: int
    params: dict[str, float]
    seeds: list[int]
    distance: float
    per_set: dict[str, float | None]
    status: str
    message: str = ""
    seconds: float = 0.0
    worker: str = ""
    n_rows: dict[str, int] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return self.status == "ok"


def _json(x) -> str:
    return json.dumps(x, sort_keys=True, allow_nan=True)


def json_text(obj) -> str:
    """Strict JSON (indented) of results for people and other programs: NaN and infinities as
    null (strict JSON readers reject NaN), numpy scalars as numbers, paths as strings."""
    def clean(x):
        if isinstance(x, dict):
            return {str(k): clean(v) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return [clean(v) for v in x]
        if isinstance(x, Path):
            return str(x)
        if isinstance(x, float) and not math.isfinite(x):
            return None
        if hasattr(x, "item"):  # numpy scalars
            return clean(x.item())
        return x
    return json.dumps(clean(obj), indent=2, allow_nan=False)


class RunStore:
    """A run directory with its evaluation log."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self.db_path = self.path / "evaluations.sqlite"
        self._con = sqlite3.connect(self.db_path, isolation_level=None, timeout=30)
        self._con.execute("PRAGMA journal_mode=WAL")
        self._con.execute("PRAGMA synchronous=NORMAL")
        self._con.executescript(SCHEMA)

    # ------------------------------------------------------------------ creation
    @classmethod
    def create(cls, path, config_text: str, overwrite: bool = False) -> "RunStore":
        """A new run directory holding ``config_text`` as ``config.toml``.

        Refuses a directory that already holds evaluations unless ``overwrite``, which then removes
        everything the old run wrote (clones, report, figures, exports too); refuses a folder
        holding files of a run's names that no run wrote (a user's ``config.toml``).
        """
        from .rundir import clear_derived, foreign_files
        path = Path(path)
        db = path / "evaluations.sqlite"
        foreign = foreign_files(path)
        if foreign:
            raise RunDirError(f"{path}: holds {', '.join(foreign)}, not written by a run, which a run would "
                              "overwrite; choose another -o (a new or empty folder)")
        if db.exists() and not overwrite and cls.held(path) > 0:
            raise RunDirError(f"{path}: already holds a run; continue it with --resume, replace it with "
                              "--overwrite, or choose another -o")
        path.mkdir(parents=True, exist_ok=True)
        if db.exists():  # --overwrite, or a run that failed before its first evaluation: nothing of it is kept
            clear_derived(path)
        for sub in ("clones", "figures"):
            (path / sub).mkdir(exist_ok=True)
        (path / "config.toml").write_text(config_text, encoding="utf-8")
        store = cls(path)
        store.set_meta("created", time.time())
        return store

    @classmethod
    def held(cls, path) -> int:
        """Evaluations in an existing run directory (0: a run that failed before its first)."""
        probe = cls(path)
        try:
            return probe.count()
        finally:
            probe.close()

    @classmethod
    def state(cls, path) -> str:
        """``finished`` (it has its ``best.json``), ``partial`` (evaluations logged, no result:
        stopped or killed) or ``new`` (nothing to keep) for the run directory ``path``."""
        path = Path(path)
        if (path / "best.json").exists():
            return "finished"
        if (path / "evaluations.sqlite").exists() and cls.held(path) > 0:
            return "partial"
        return "new"

    @classmethod
    def open(cls, path) -> "RunStore":
        path = Path(path)
        if not (path / "config.toml").exists():
            raise RunDirError(f"{path}: not a run directory (no config.toml)")
        return cls(path)

    @property
    def config_path(self) -> Path:
        return self.path / "config.toml"

    # ------------------------------------------------------------------ evaluations
    def add(self, ev: Evaluation) -> None:
        self._con.execute(
            "INSERT INTO evaluations VALUES (?,?,?,?,?,?,?,?,?,?,?)",
            (ev.idx, _json(ev.params), _json(ev.seeds), float(ev.distance), _json(ev.per_set), ev.status,
             ev.message, ev.seconds, ev.worker, _json(ev.n_rows), time.time()))

    def count(self) -> int:
        return self._con.execute("SELECT COUNT(*) FROM evaluations").fetchone()[0]

    def _select(self, tail: str, args: tuple = ()) -> list[Evaluation]:
        """The logged evaluations that the SQL ``tail`` (WHERE / ORDER BY / LIMIT) selects."""
        rows = self._con.execute(
            "SELECT idx, params, seeds, distance, per_set, status, message, seconds, worker, n_rows "
            f"FROM evaluations {tail}", args).fetchall()
        return [Evaluation(r[0], json.loads(r[1]), json.loads(r[2]), r[3], json.loads(r[4]), r[5], r[6] or "",
                           r[7] or 0.0, r[8] or "", json.loads(r[9] or "{}")) for r in rows]

    def evaluations(self) -> list[Evaluation]:
        """Every logged evaluation, in order."""
        return self._select("ORDER BY idx")

    def replay(self) -> dict[int, Evaluation]:
        return {e.idx: e for e in self.evaluations()}

    def evaluation(self, idx: int) -> Evaluation:
        """The logged evaluation of index ``idx``."""
        found = self._select("WHERE idx = ?", (int(idx),))
        if not found:
            raise RunDirError(f"{self.path}: no evaluation {idx} in the log")
        return found[0]

    def best(self, before: int | None = None) -> Evaluation | None:
        """The evaluation of lowest distance, a grown tree before any failure (whose distance is
        the config's penalty, which need not exceed every real distance); with ``before``, among
        the evaluations of index below it (the best after that many evaluations)."""
        found = self._select("WHERE idx < ? ORDER BY status != 'ok', distance, idx LIMIT 1",
                                 (2 ** 62 if before is None else int(before),))
        return found[0] if found else None

    # ------------------------------------------------------------------ held-out scores
    def heldout_scores(self, scoring: str) -> dict[tuple[str, str], dict]:
        """Every kept held-out score of this scoring: ``(point, seeds)`` (both JSON text) ->
        ``{"distance", "status"}``."""
        rows = self._con.execute("SELECT point, seeds, distance, status FROM heldout WHERE scoring = ?",
                                 (scoring,)).fetchall()
        return {(r[0], r[1]): {"distance": r[2], "status": r[3]} for r in rows}

    def add_heldout(self, scoring: str, point: str, seeds: str, distance: float, status: str) -> None:
        """Keep one held-out score as soon as it is known (a killed scoring loses nothing)."""
        self._con.execute("INSERT OR REPLACE INTO heldout VALUES (?,?,?,?,?)",
                          (scoring, point, seeds, float(distance), status))

    # ------------------------------------------------------------------ optimiser log
    def log(self, record: dict) -> None:
        self._con.execute("INSERT INTO log (record) VALUES (?)", (_json(record),))

    def log_records(self) -> list[dict]:
        return [json.loads(r[0]) for r in self._con.execute("SELECT record FROM log ORDER BY seq")]

    def clear_log(self) -> None:
        self._con.execute("DELETE FROM log")

    # ------------------------------------------------------------------ meta
    def set_meta(self, key: str, value: Any) -> None:
        self._con.execute("INSERT OR REPLACE INTO meta VALUES (?, ?)", (key, _json(value)))

    def get_meta(self, key: str, default=None):
        r = self._con.execute("SELECT value FROM meta WHERE key=?", (key,)).fetchone()
        return default if r is None else json.loads(r[0])

    # ------------------------------------------------------------------ json files
    def write_json(self, name: str, data) -> Path:
        p = self.path / name
        tmp = p.with_suffix(p.suffix + ".tmp")
        tmp.write_text(json.dumps(data, indent=2, sort_keys=False, default=_default), encoding="utf-8")
        tmp.replace(p)
        return p

    def read_json(self, name: str):
        p = self.path / name
        if not p.exists():
            raise RunDirError(f"{self.path}: no {name} (has the fit finished?)")
        return json.loads(p.read_text(encoding="utf-8"))

    # ------------------------------------------------------------------ optimiser diagnostics
    def write_diagnostics(self, diagnostics: dict, max_inline: int = 64) -> dict:
        """Split optimiser diagnostics: arrays with more than ``max_inline`` values (an MCMC
        chain, a final population) go to ``diagnostics.npz``; the rest is returned for
        ``best.json`` with ``"arrays"`` naming the stored keys."""
        import numpy as np
        small, big = {}, {}
        for k, v in (diagnostics or {}).items():
            arr = None
            if isinstance(v, np.ndarray) or (isinstance(v, (list, tuple)) and v and isinstance(v[0], (list, tuple, np.ndarray))):
                try:
                    arr = np.asarray(v, dtype=float)
                except (TypeError, ValueError):
                    arr = None
            if arr is not None and arr.size > max_inline:
                big[k] = arr
            else:
                small[k] = v
        path = self.path / "diagnostics.npz"
        if big:
            np.savez_compressed(path, **big)
            small["arrays"] = sorted(big)
        else:
            path.unlink(missing_ok=True)
        return small

    def read_diagnostics(self) -> dict:
        """The optimiser diagnostics of ``best.json`` with the stored arrays put back."""
        import numpy as np
        p = self.path / "best.json"
        diag = dict(json.loads(p.read_text(encoding="utf-8")).get("diagnostics") or {}) if p.exists() else {}
        npz = self.path / "diagnostics.npz"
        if diag.pop("arrays", None) is not None and npz.exists():
            with np.load(npz) as z:
                diag.update({k: z[k] for k in z.files})
        return diag

    def close(self) -> None:
        """Close the log's connection. Close it when done rather than leave it to the garbage
        collector: the last connection's close checkpoints SQLite's write-ahead log into
        ``evaluations.sqlite``, which must not happen at a random later moment (under a later
        command reading the run)."""
        self._con.close()

    def __enter__(self) -> "RunStore":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _default(o):
    try:
        import numpy as np
        if isinstance(o, np.generic):
            return o.item()
        if isinstance(o, np.ndarray):
            return o.tolist()
    except ImportError:
        pass
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")
