"""Run directory and its SQLite evaluation log.

Layout (:class:`RunFiles` names each file; no other module spells these names)::

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
import re
import shutil
import sqlite3
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Self

import numpy as np

from ..errors import BayesForestError
from ..io import json_text, write_json

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
    per_set   TEXT,                 -- JSON {set or term:<name>: distance or null}; null in older runs
    sizes     TEXT,                 -- JSON {statistic: the trees' mean} ([select] sizes); null when not measured
    PRIMARY KEY (scoring, point, seeds)
);
"""


#: why a fit's search stopped (``best.json``'s ``stop_kind``): on its evaluation budget, on the
#: optimiser's own convergence rules, at ``[stop] target_distance``, on the clock (``[stop]
#: wall_time``), or after it ended otherwise with growths stopped by ``[objective] timeout``; the last
#: two make the answer depend on the machine's speed and load (:func:`clock_warning`)
STOP_KINDS = ("budget", "convergence", "target", "wall_time", "timeout")


def stop_fields(search: str, store: RunStore, selection: dict | None = None) -> dict:
    """``best.json``'s ``stop_kind`` and ``stop`` (``{"search": why the search ended, "timeouts":
    growths stopped by the timeout, in the search and among the held-out candidates}``)."""
    timeouts = store.count("timeout") + sum(int(c.get("timeouts", 0)) for c in (selection or {}).get("candidates", []))
    kind = search if search == "wall_time" or not timeouts else "timeout"
    return {"stop_kind": kind, "stop": {"search": search, "timeouts": timeouts}}


def clock_warning(best: dict) -> str | None:
    """One line when a fit's answer depends on the clock (``stop_kind`` ``wall_time`` or
    ``timeout``), saying what happened and what to raise; None for an answer that only the
    evaluation budget and the optimiser decided."""
    kind, stop = best.get("stop_kind"), best.get("stop") or {}
    timeouts = int(stop.get("timeouts", 0))
    if kind == "wall_time":
        return (
            f"the search stopped on its wall time ([stop] wall_time) after {best.get('n_evaluations', '?')} "
            "evaluations, so where it stopped depends on this machine's speed and load: raise wall_time (a safety "
            "net) for an answer that only the evaluation budget decides"
        )
    if kind == "timeout":
        return (
            f"{timeouts} growth(s) ran past [objective] timeout and scored the penalty; which ones depends on this "
            "machine's speed and load: raise timeout (a safety net) for an answer that does not"
        )
    return None


def slug(text: str) -> str:
    """A file-name-safe version of a set or parameter name (``"S0,1"`` -> ``"S0-1"``)."""
    s = re.sub(r"[^A-Za-z0-9_.-]+", "-", str(text)).strip("-")
    return s or "x"


class RunDirError(BayesForestError):
    pass


def _log_error(db: Path, exc: sqlite3.Error, what: str) -> RunDirError:
    """One line for what SQLite says of the database ``db`` (``what`` it is to the user): the
    file and what to do."""
    name = getattr(exc, "sqlite_errorname", "")
    if name == "SQLITE_FULL":
        return RunDirError(
            f"{db}: the disk is full ({exc}); everything stored before is kept: free space "
            "and run the command again (a fit or a training continues with --resume)"
        )
    if name in ("SQLITE_CORRUPT", "SQLITE_NOTADB") or type(exc) is sqlite3.DatabaseError:
        return RunDirError(
            f"{db}: {what} is damaged ({exc}); restore it from a backup (the sqlite3 "
            "shell's .recover may save its rows), or start anew with --overwrite"
        )
    return RunDirError(f"{db}: {exc}")


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


def _column(x) -> str:
    """A JSON column of the evaluation log: one line, keys sorted."""
    return json_text(x, indent=None, sort_keys=True)


class FolderFiles:
    """A folder a command writes, its files named by the subclass (the one place their names are
    spelled); :data:`DERIVED` is what ``--overwrite`` removes (:meth:`clear`)."""

    DERIVED: tuple = ()

    def __init__(self, path):
        self.path = Path(path)

    def clear(self) -> None:
        """Remove everything of :data:`DERIVED` (folders with their content); other files stay."""
        import shutil

        for name in self.DERIVED:
            p = self.path / name
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p)
            else:
                p.unlink(missing_ok=True)


class RunFiles(FolderFiles):
    """The files and folders of a run directory, each by what it holds.

    The one place their names are spelled: every stage reads and writes a run's files through
    these accessors (``RunFiles(run_dir).best_path``), and :class:`RunStore`, which opens the
    evaluation log, has them too. A new file of the run directory is a name here, an accessor
    and an entry of :data:`DERIVED` (what ``--overwrite`` removes).
    """

    CONFIG = "config.toml"
    EVALUATIONS = "evaluations.sqlite"
    BEST = "best.json"
    BEST_TREE = "best_tree.txt"
    TARGET_TREE = "target.txt"
    TARGET_SETS = "target_sets.npz"
    DISTANCE = "distance.json"
    DIRECTIONS = "directions.npz"
    DIAGNOSTICS = "diagnostics.npz"
    POSTERIOR_CSV = "posterior.csv"
    POSTERIOR_NC = "posterior.nc"
    REPORT_MD = "report.md"
    REPORT_HTML = "report.html"
    #: the report's figure format and resolution, kept for the next report of the run
    REPORT_OPTIONS = "report_options.json"
    CLONES = "clones"
    CLONES_POSTERIOR = "clones_posterior"
    #: in a clones folder: its summary and its table
    CLONE_SUMMARY = "summary.json"
    CLONE_TABLE = "clones.csv"
    CLONE_FIDELITY = "fidelity.json"
    FIGURES = "figures"
    EXPORT = "export"
    LOCK = ".bforest.lock"
    #: files and folders a run writes into its directory (globs), all derived from its config
    #: (``heldout.json``: where older runs kept their held-out scores)
    DERIVED = (
        CONFIG,
        EVALUATIONS,
        f"{EVALUATIONS}-wal",
        f"{EVALUATIONS}-shm",
        f"{EVALUATIONS}-journal",
        BEST,
        f"{BEST}.tmp",
        ".*.tmp",  # a file written all or nothing (io.whole_file), left by a killed command
        BEST_TREE,
        TARGET_TREE,
        TARGET_SETS,
        DISTANCE,
        DIRECTIONS,
        DIAGNOSTICS,
        POSTERIOR_CSV,
        POSTERIOR_NC,
        "heldout.json",
        "heldout.json.tmp",
        "profile_*.csv",
        REPORT_MD,
        REPORT_HTML,
        REPORT_OPTIONS,
        CLONES,
        CLONES_POSTERIOR,
        FIGURES,
        EXPORT,
    )

    @property
    def config_path(self) -> Path:
        """The resolved configuration the run was made with."""
        return self.path / self.CONFIG

    @property
    def evaluations_path(self) -> Path:
        """The SQLite log of every evaluation (and the held-out scores)."""
        return self.path / self.EVALUATIONS

    @property
    def best_path(self) -> Path:
        """The fit's answer (written when the fit has finished)."""
        return self.path / self.BEST

    @property
    def best_tree_path(self) -> Path:
        """The answer's tree, regrown with its first model seed."""
        return self.path / self.BEST_TREE

    @property
    def target_tree_path(self) -> Path:
        """A copy of the target tree."""
        return self.path / self.TARGET_TREE

    @property
    def target_sets_path(self) -> Path:
        """The target's data tables."""
        return self.path / self.TARGET_SETS

    @property
    def distance_path(self) -> Path:
        """The distance's frozen data-side transforms."""
        return self.path / self.DISTANCE

    @property
    def directions_path(self) -> Path:
        """The directions a sliced distance projects on."""
        return self.path / self.DIRECTIONS

    @property
    def diagnostics_path(self) -> Path:
        """The optimiser's large diagnostic arrays."""
        return self.path / self.DIAGNOSTICS

    @property
    def posterior_csv_path(self) -> Path:
        """A sampler's posterior sample."""
        return self.path / self.POSTERIOR_CSV

    @property
    def posterior_nc_path(self) -> Path:
        """A sampler's posterior as ArviZ NetCDF."""
        return self.path / self.POSTERIOR_NC

    @property
    def report_md_path(self) -> Path:
        return self.path / self.REPORT_MD

    @property
    def report_html_path(self) -> Path:
        return self.path / self.REPORT_HTML

    @property
    def report_options_path(self) -> Path:
        """The format and dpi ``bforest report`` was last asked for (later reports keep them)."""
        return self.path / self.REPORT_OPTIONS

    @property
    def figures_dir(self) -> Path:
        return self.path / self.FIGURES

    @property
    def export_dir(self) -> Path:
        return self.path / self.EXPORT

    @property
    def lock_path(self) -> Path:
        """The lock a command holds while it works on the run."""
        return self.path / self.LOCK

    def clones_dir(self, posterior: bool = False) -> Path:
        """The clones of the best fit (``posterior``: the posterior-predictive clones)."""
        return self.path / (self.CLONES_POSTERIOR if posterior else self.CLONES)

    def profile_path(self, param_slug: str) -> Path:
        """The table of ``bforest profile`` along one parameter."""
        return self.path / f"profile_{param_slug}.csv"

    def finished(self) -> bool:
        """Whether the fit has finished (it wrote its answer)."""
        return self.best_path.exists()

    def read_best(self) -> dict:
        """The fit's answer (``best.json``); RunDirError when the fit has not finished."""
        if not self.best_path.exists():
            raise RunDirError(f"{self.path}: no {self.BEST} (has the fit finished?)")
        return json.loads(self.best_path.read_text(encoding="utf-8"))


def derived_paths(run_dir) -> list[Path]:
    """The paths of ``run_dir`` that a run wrote (or would write), existing ones only."""
    run_dir = Path(run_dir)
    out = []
    for pattern in RunFiles.DERIVED:
        out.extend(sorted(run_dir.glob(pattern)))
    return out


def is_run_dir(run_dir) -> bool:
    """Whether ``run_dir`` holds a run (its evaluation log), as opposed to a user's folder."""
    return RunFiles(run_dir).evaluations_path.exists()


def foreign_files(run_dir) -> list[str]:
    """Names of files in ``run_dir`` that a run would write but no run wrote there: a folder
    without an evaluation log that holds e.g. the user's own ``config.toml`` (``-o .``)."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir() or is_run_dir(run_dir):
        return []
    found = []
    for p in derived_paths(run_dir):
        if p.is_dir() and not any(p.iterdir()):
            continue  # an empty clones/ or figures/ holds nothing to lose
        found.append(p.name)
    return found


def clear_derived(run_dir) -> None:
    """Remove everything the old run of ``run_dir`` wrote (log, results, clones, report,
    figures, exports); other files are left alone."""
    for p in derived_paths(run_dir):
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
        else:
            p.unlink(missing_ok=True)


def logged_count(path) -> int:
    """Evaluations in the log at ``path`` read without taking part in the run (a stand's progress
    reads the logs its workers write): 0 while the log is missing, locked or being created."""
    path = Path(path)
    if not path.exists():
        return 0
    try:
        con = sqlite3.connect(f"file:{path}?mode=ro", uri=True, timeout=0.2)
        try:
            return int(con.execute("SELECT COUNT(*) FROM evaluations").fetchone()[0])
        finally:
            con.close()
    except sqlite3.Error:
        return 0


class StandFiles(FolderFiles):
    """The files and folders of a stand folder (``bforest stand``; the one place their names are
    spelled). Each tree's run folder is a run directory of its own (:class:`RunFiles`)."""

    SETTINGS = "stand.toml"
    TABLE = "stand.csv"
    RECIPES = "recipes"
    RUNS = "trees"
    SYNTHETIC = "synthetic"
    FIGURES = "figures"
    REPORT_MD = "report.md"
    REPORT_HTML = "report.html"
    LOCK = RunFiles.LOCK
    #: what a stand writes into its folder (``--overwrite`` removes exactly these)
    DERIVED = (
        SETTINGS,
        f"{SETTINGS}.tmp",
        TABLE,
        f"{TABLE}.tmp",
        RECIPES,
        RUNS,
        SYNTHETIC,
        FIGURES,
        REPORT_MD,
        REPORT_HTML,
    )

    @property
    def settings_path(self) -> Path:
        """The stand's settings and its trees."""
        return self.path / self.SETTINGS

    @property
    def table_path(self) -> Path:
        """One row per tree."""
        return self.path / self.TABLE

    @property
    def recipes_dir(self) -> Path:
        return self.path / self.RECIPES

    @property
    def runs_dir(self) -> Path:
        return self.path / self.RUNS

    @property
    def synthetic_dir(self) -> Path:
        return self.path / self.SYNTHETIC

    @property
    def figures_dir(self) -> Path:
        return self.path / self.FIGURES

    @property
    def report_md_path(self) -> Path:
        return self.path / self.REPORT_MD

    @property
    def report_html_path(self) -> Path:
        return self.path / self.REPORT_HTML

    def recipe_path(self, name: str) -> Path:
        """The recipe of the tree ``name``."""
        return self.recipes_dir / f"{name}.toml"

    def run_dir(self, name: str) -> Path:
        """The run folder of the tree ``name``."""
        return self.runs_dir / name

    def realisation_dir(self, r: int) -> Path:
        """The folder of synthetic stand number ``r`` (0-based)."""
        return self.synthetic_dir / f"stand_{r:03d}"


class TrainFiles(FolderFiles):
    """The files of a training folder (``bforest train``) and of an estimator's calibration
    (``bforest calibrate --estimator``): the one place their names are spelled."""

    CONFIG = "train.toml"
    SIMULATIONS = "simulations.sqlite"
    ESTIMATOR = "estimator.npz"
    RECORD = "training.json"
    CALIBRATION_JSON = "calibration.json"
    CALIBRATION_CSV = "calibration.csv"
    CALIBRATION_FIGURE = "calibration.png"
    LOCK = RunFiles.LOCK
    #: what a training or calibration writes (``--overwrite`` removes exactly these)
    DERIVED = (
        CONFIG,
        SIMULATIONS,
        f"{SIMULATIONS}-wal",
        f"{SIMULATIONS}-shm",
        f"{SIMULATIONS}-journal",
        ESTIMATOR,
        f"{ESTIMATOR}.tmp.npz",
        RECORD,
        f"{RECORD}.tmp",
        CALIBRATION_JSON,
        CALIBRATION_CSV,
        CALIBRATION_FIGURE,
    )

    @property
    def config_path(self) -> Path:
        """The resolved training configuration."""
        return self.path / self.CONFIG

    @property
    def simulations_path(self) -> Path:
        """Every simulation of the folder, written as it finishes."""
        return self.path / self.SIMULATIONS

    @property
    def estimator_path(self) -> Path:
        """The trained estimator's file."""
        return self.path / self.ESTIMATOR

    @property
    def record_path(self) -> Path:
        """What the training did (counts, times, losses)."""
        return self.path / self.RECORD

    def calibration_path(self, what: str) -> Path:
        """``json``, ``csv`` or ``png`` of a calibration study."""
        return (
            self.path
            / {"json": self.CALIBRATION_JSON, "csv": self.CALIBRATION_CSV, "png": self.CALIBRATION_FIGURE}[what]
        )


class PosteriorFiles(FolderFiles):
    """The files of a tree's amortised posterior (``bforest posterior -o DIR``): the one place
    their names are spelled (the table and the ArviZ file as a sampler's run names them)."""

    POSTERIOR_CSV = RunFiles.POSTERIOR_CSV
    POSTERIOR_NC = RunFiles.POSTERIOR_NC
    SUMMARY = "posterior.json"
    FIGURES = RunFiles.FIGURES
    CORNER = "posterior_corner.png"
    CLONES = RunFiles.CLONES
    CLONE_TABLE = RunFiles.CLONE_TABLE
    LOCK = RunFiles.LOCK
    #: what ``bforest posterior`` writes (``--overwrite`` removes exactly these)
    DERIVED = (POSTERIOR_CSV, POSTERIOR_NC, SUMMARY, f"{SUMMARY}.tmp", FIGURES, CLONES)

    @property
    def summary_path(self) -> Path:
        """What the posterior is: the tree, the estimator, per parameter its quantiles."""
        return self.path / self.SUMMARY

    @property
    def corner_path(self) -> Path:
        return self.path / self.FIGURES / self.CORNER

    @property
    def clones_dir(self) -> Path:
        return self.path / self.CLONES


class _Database:
    """An SQLite file written by one process, each statement committed on its own (write-ahead
    log), with a ``meta`` table of JSON values. What SQLite says of a damaged file or a full disk
    becomes one :class:`RunDirError` naming the file (:meth:`_sql`)."""

    db_path: Path
    #: what the file is, as an error names it
    what = "the database"

    def _connect(self, path: Path, schema: str | None = None) -> None:
        """Open ``path`` (its ``schema`` made now, or later by :meth:`_make`)."""
        self.db_path = path
        try:
            self._con = sqlite3.connect(path, isolation_level=None, timeout=30)
        except sqlite3.Error as exc:
            raise _log_error(path, exc, self.what) from None
        if schema is not None:
            self._make(schema)

    def _make(self, schema: str) -> None:
        """The tables of ``schema`` (those missing), the connection closed on an error."""
        try:
            self._sql("PRAGMA journal_mode=WAL")
            self._sql("PRAGMA synchronous=NORMAL")
            try:
                self._con.executescript(schema)
            except sqlite3.Error as exc:
                raise _log_error(self.db_path, exc, self.what) from None
        except RunDirError:
            self._con.close()
            raise

    def _sql(self, query: str, args: tuple = ()) -> list[tuple]:
        """The rows of one statement."""
        try:
            return self._con.execute(query, args).fetchall()
        except sqlite3.ProgrammingError:  # this program's mistake (a closed store), not the file's
            raise
        except sqlite3.Error as exc:
            raise _log_error(self.db_path, exc, self.what) from None

    def set_meta(self, key: str, value: Any) -> None:
        self._sql("INSERT OR REPLACE INTO meta VALUES (?, ?)", (key, _column(value)))

    def get_meta(self, key: str, default=None):
        r = self._sql("SELECT value FROM meta WHERE key=?", (key,))
        return default if not r else json.loads(r[0][0])

    def close(self) -> None:
        """Close the connection. Close it when done rather than leave it to the garbage collector:
        the last connection's close checkpoints SQLite's write-ahead log into the file, which must
        not happen at a random later moment (under a later command reading it)."""
        try:
            self._con.close()
        except sqlite3.Error as exc:  # the checkpoint on a full disk
            raise _log_error(self.db_path, exc, self.what) from None

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


SIMULATIONS_SCHEMA = """
CREATE TABLE IF NOT EXISTS simulations (
    idx        INTEGER PRIMARY KEY,  -- draw index of the prior's stream
    reference  INTEGER,              -- the reference tree the draw was scaled from
    height     REAL,                 -- the height (m) it was scaled to
    params     TEXT NOT NULL,        -- JSON {name: value}, the fixed ones included
    seed       INTEGER NOT NULL,     -- model seed
    status     TEXT NOT NULL,        -- ok | <SimulationFailed status> | timeout | error | crashed
    message    TEXT,
    summaries  BLOB,                 -- float64 values of the summaries (NULL for a failure)
    seconds    REAL,
    worker     TEXT,
    finished   REAL                  -- unix time
);
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT);
"""


class SimulationStore(_Database):
    """The simulations of a training folder (SQLite; each row committed as it arrives, so a
    killed training loses nothing that finished and ``--resume`` grows no tree twice)."""

    what = "the training's log of simulations"

    def __init__(self, path):
        self.path = Path(path)
        self._connect(self.path, SIMULATIONS_SCHEMA)

    def add(self, idx: int, reference: int, height: float, params: dict, seed: int, result: dict) -> None:
        s = result.get("summaries")
        blob = None if s is None else np.asarray(s, "<f8").tobytes()
        self._sql(
            "INSERT OR REPLACE INTO simulations VALUES (?,?,?,?,?,?,?,?,?,?,?)",
            (
                int(idx),
                int(reference),
                float(height),
                _column(params),
                int(seed),
                result["status"],
                result.get("message", ""),
                blob,
                float(result.get("seconds", 0.0)),
                result.get("worker", ""),
                time.time(),
            ),
        )

    def done(self) -> set[int]:
        """Indices already simulated."""
        return {r[0] for r in self._sql("SELECT idx FROM simulations")}

    def count(self, status: str | None = None) -> int:
        if status is None:
            return int(self._sql("SELECT COUNT(*) FROM simulations")[0][0])
        return int(self._sql("SELECT COUNT(*) FROM simulations WHERE status=?", (status,))[0][0])

    def statuses(self) -> dict[str, int]:
        return dict(self._sql("SELECT status, COUNT(*) FROM simulations GROUP BY status"))

    def seconds(self) -> float:
        """Summed seconds of the simulations (worker time, not wall time)."""
        return float(self._sql("SELECT COALESCE(SUM(seconds), 0) FROM simulations")[0][0])

    def grown(self, limit: int | None = None) -> list[tuple[int, float, dict, np.ndarray]]:
        """``(idx, height, params, summaries)`` of the grown trees, by index (the first ``limit``
        indices only, when given)."""
        q = "SELECT idx, height, params, summaries FROM simulations WHERE status='ok'"
        args: tuple = ()
        if limit is not None:
            q += " AND idx < ?"
            args = (int(limit),)
        rows = self._sql(q + " ORDER BY idx", args)
        return [(int(i), float(h), json.loads(p), np.frombuffer(b, "<f8")) for i, h, p, b in rows]


class RunStore(RunFiles, _Database):
    """A run directory with its evaluation log."""

    what = "the evaluation log"

    def __init__(self, path: Path, new: bool = False):
        """Open the evaluation log of the run directory ``path`` (``new``: begin one).

        Raises
        ------
        RunDirError
            The log of an existing run is missing, empty, holds no evaluation table or is
            damaged: a resume never starts again from zero over a lost log.
        """
        super().__init__(path)
        db = self.evaluations_path
        if not new and not db.is_file():
            raise RunDirError(
                f"{db}: missing: the run's evaluations are gone; restore the file, or start the run "
                "anew with --overwrite"
            )
        self._connect(db)
        try:
            if not new and not self._sql("SELECT 1 FROM sqlite_master WHERE type='table' AND name='evaluations'"):
                raise RunDirError(
                    f"{db}: holds no evaluation table (an empty or foreign file, not a run's log); "
                    "restore the run's own, or start the run anew with --overwrite"
                )
            self._make(SCHEMA)
            have = {r[1] for r in self._sql("PRAGMA table_info(heldout)")}
            for column in ("per_set", "sizes"):  # a run written before held-out scores kept them
                if column not in have:
                    self._sql(f"ALTER TABLE heldout ADD COLUMN {column} TEXT")
        except RunDirError:
            self._con.close()
            raise

    # ------------------------------------------------------------------ creation
    @classmethod
    def create(cls, path, config_text: str, overwrite: bool = False) -> RunStore:
        """A new run directory holding ``config_text`` as ``config.toml``.

        Refuses a directory that already holds evaluations unless ``overwrite``, which then removes
        everything the old run wrote (clones, report, figures, exports too); refuses a folder
        holding files of a run's names that no run wrote (a user's ``config.toml``).
        """
        path = Path(path)
        files = RunFiles(path)
        db = files.evaluations_path
        foreign = foreign_files(path)
        if foreign:
            raise RunDirError(
                f"{path}: holds {', '.join(foreign)}, not written by a run, which a run would "
                "overwrite; choose another -o (a new or empty folder)"
            )
        if db.exists() and not overwrite and cls.held(path) > 0:
            raise RunDirError(
                f"{path}: already holds a run; continue it with --resume, replace it with "
                "--overwrite, or choose another -o"
            )
        path.mkdir(parents=True, exist_ok=True)
        if db.exists():  # --overwrite, or a run that failed before its first evaluation: nothing of it is kept
            clear_derived(path)
        for sub in (files.clones_dir(), files.figures_dir):
            sub.mkdir(exist_ok=True)
        files.config_path.write_text(config_text, encoding="utf-8")
        store = cls(path, new=True)
        store.set_meta("created", time.time())
        store.set_meta("config", config_text)  # the config the log is begun with: a resume checks against it
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
        files = RunFiles(path)
        if files.finished():
            return "finished"
        if files.evaluations_path.exists() and cls.held(path) > 0:
            return "partial"
        return "new"

    @classmethod
    def open(cls, path) -> RunStore:
        path = Path(path)
        if not RunFiles(path).config_path.exists():
            raise RunDirError(f"{path}: not a run directory (no {RunFiles.CONFIG})")
        return cls(path)

    # ------------------------------------------------------------------ evaluations
    def add(self, ev: Evaluation) -> None:
        self._sql(
            "INSERT INTO evaluations VALUES (?,?,?,?,?,?,?,?,?,?,?)",
            (
                ev.idx,
                _column(ev.params),
                _column(ev.seeds),
                float(ev.distance),
                _column(ev.per_set),
                ev.status,
                ev.message,
                ev.seconds,
                ev.worker,
                _column(ev.n_rows),
                time.time(),
            ),
        )

    def growths(self) -> int:
        """Every tree the run grew: each evaluation's model seeds and each held-out score's."""
        q = "SELECT COALESCE(SUM(json_array_length(seeds)), 0) FROM {}"
        return sum(int(self._sql(q.format(t))[0][0]) for t in ("evaluations", "heldout"))

    def count(self, status: str | None = None) -> int:
        """Logged evaluations (of ``status`` only, when given)."""
        if status is None:
            return self._sql("SELECT COUNT(*) FROM evaluations")[0][0]
        return self._sql("SELECT COUNT(*) FROM evaluations WHERE status = ?", (status,))[0][0]

    def _select(self, tail: str, args: tuple = ()) -> list[Evaluation]:
        """The logged evaluations that the SQL ``tail`` (WHERE / ORDER BY / LIMIT) selects."""
        rows = self._sql(
            "SELECT idx, params, seeds, distance, per_set, status, message, seconds, worker, n_rows "
            f"FROM evaluations {tail}",
            args,
        )
        return [
            Evaluation(
                r[0],
                json.loads(r[1]),
                json.loads(r[2]),
                r[3],
                json.loads(r[4]),
                r[5],
                r[6] or "",
                r[7] or 0.0,
                r[8] or "",
                json.loads(r[9] or "{}"),
            )
            for r in rows
        ]

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
        found = self._select(
            "WHERE idx < ? ORDER BY status != 'ok', distance, idx LIMIT 1", (2**62 if before is None else int(before),)
        )
        return found[0] if found else None

    # ------------------------------------------------------------------ held-out scores
    def heldout_scores(self, scoring: str) -> dict[tuple[str, str], dict]:
        """Every kept held-out score of this scoring: ``(point, seeds)`` (both JSON text) ->
        ``{"distance", "status", "per_set", "sizes"}`` (``per_set`` None when an older run did not
        keep it, ``sizes`` None when the trees were not measured)."""
        rows = self._sql(
            "SELECT point, seeds, distance, status, per_set, sizes FROM heldout WHERE scoring = ?", (scoring,)
        )
        return {
            (r[0], r[1]): {
                "distance": r[2],
                "status": r[3],
                "per_set": None if r[4] is None else json.loads(r[4]),
                "sizes": None if r[5] is None else json.loads(r[5]),
            }
            for r in rows
        }

    def add_heldout(
        self,
        scoring: str,
        point: str,
        seeds: str,
        distance: float,
        status: str,
        per_set: dict | None = None,
        sizes: dict | None = None,
    ) -> None:
        """Keep one held-out score as soon as it is known (a killed scoring loses nothing), with
        its distance per set and per term, and the trees' measured sizes."""
        self._sql(
            "INSERT OR REPLACE INTO heldout (scoring, point, seeds, distance, status, per_set, sizes) "
            "VALUES (?,?,?,?,?,?,?)",
            (
                scoring,
                point,
                seeds,
                float(distance),
                status,
                None if per_set is None else _column(per_set),
                None if sizes is None else _column(sizes),
            ),
        )

    # ------------------------------------------------------------------ optimiser log
    def log(self, record: dict) -> None:
        self._sql("INSERT INTO log (record) VALUES (?)", (_column(record),))

    def log_records(self) -> list[dict]:
        return [json.loads(r[0]) for r in self._sql("SELECT record FROM log ORDER BY seq")]

    def clear_log(self) -> None:
        self._sql("DELETE FROM log")

    # ------------------------------------------------------------------ json files
    def write_json(self, name: str, data) -> Path:
        return write_json(self.path / name, data)

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
            if isinstance(v, np.ndarray) or (
                isinstance(v, (list, tuple)) and v and isinstance(v[0], (list, tuple, np.ndarray))
            ):
                try:
                    arr = np.asarray(v, dtype=float)
                except (TypeError, ValueError):
                    arr = None
            if arr is not None and arr.size > max_inline:
                big[k] = arr
            else:
                small[k] = v
        path = self.diagnostics_path
        if big:
            np.savez_compressed(path, **big)
            small["arrays"] = sorted(big)
        else:
            path.unlink(missing_ok=True)
        return small

    def read_diagnostics(self) -> dict:
        """The optimiser diagnostics of ``best.json`` with the stored arrays put back."""
        import numpy as np

        p = self.best_path
        diag = dict(json.loads(p.read_text(encoding="utf-8")).get("diagnostics") or {}) if p.exists() else {}
        npz = self.diagnostics_path
        if diag.pop("arrays", None) is not None and npz.exists():
            with np.load(npz) as z:
                diag.update({k: z[k] for k in z.files})
        return diag
