"""A stand: every tree of a scanned plot fitted, cloned and put in one table (``bforest stand``).

A terrestrial laser scanning campaign scans plots: a folder of QSMs, or a stem map (a CSV of
``file, x, y``). For each tree the stand writes a recipe (``bforest init``'s, or one recipe for
every tree), fits it, grows its clones and adds a row to ``STAND/stand.csv``. Trees are the unit of
work: each tree's fit, with its evaluations one after another, runs as one task on the stand's
executor (``serial``, ``process`` or ``dask``, on a local cluster or a running scheduler), the
tallest trees first, so that N workers fit N trees at a time. A tree whose file is bad or whose fit
fails gets its one-line reason in the table and the others go on.

Nothing in the table depends on the machine: the recipes stop on their evaluation budgets, each
tree's run is the same whatever executor or worker fits it, and the table holds results only
(fit times are in each run's ``best.json`` and in the stand report). ``--resume`` continues every
unfinished tree from its evaluation log (a killed worker's tree too) and never refits a finished
one; a resumed stand's table equals an uninterrupted one's.

Layout (:class:`~.store.StandFiles` names each file)::

    STAND/stand.toml            the stand's settings and its trees (what --resume continues)
    STAND/stand.csv             one row per tree
    STAND/recipes/NAME.toml     each tree's recipe
    STAND/trees/NAME/           each tree's run folder (bforest report STAND/trees/NAME)
    STAND/synthetic/stand_NNN/  synthetic stands (plot mesh, plot scan, trees.csv)
    STAND/report.md, report.html, figures/
"""

from __future__ import annotations

import csv
import glob
import json
import math
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Optional

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from ..errors import BayesForestError, ConfigError
from ..io import qsm_suffixes, read_qsm
from .rundir import run_lock
from .store import RunFiles, StandFiles, clock_warning, logged_count, slug


class StandError(BayesForestError):
    """A stand cannot be started or continued (its folder, its source, its stem map)."""


#: columns of a stem map: required, then optional (``tree``: the tree's name, default the file's
#: stem; ``z``: the stem base's height, m, default 0; ``model``/``recipe``: per-tree overrides)
STEM_MAP_REQUIRED = ("file", "x", "y")
STEM_MAP_OPTIONAL = ("tree", "z", "model", "recipe")


class StandTree(BaseModel):
    """One tree of a stand: its name, its QSM and where it stands."""

    model_config = ConfigDict(extra="forbid")

    name: str = Field(description="the tree's name in the table and its run folder's")
    file: str = Field(description="the QSM file (absolute path)")
    x: Optional[float] = Field(None, description="stem base, m (from the stem map; none: the QSM's own frame)")
    y: Optional[float] = Field(None, description="stem base, m")
    z: Optional[float] = Field(None, description="stem base height, m")
    model: Optional[str] = Field(None, description="growth model for this tree (default: the stand's)")
    recipe: Optional[str] = Field(None, description="recipe for this tree (default: the stand's)")


class StandSettings(BaseModel):
    """What a stand fits and grows (``STAND/stand.toml``; a stand config's ``[stand]`` table)."""

    model_config = ConfigDict(extra="forbid")

    trees: list[StandTree] = Field(default_factory=list, description="the trees (from the source)")
    recipe: Optional[str] = Field(None, description="one recipe for every tree (default: bforest init's for each)")
    model: Optional[str] = Field(None, description="growth model of init's recipes (default: the one that suits)")
    seed: Optional[int] = Field(None, description="run seed of every tree's fit (default: the recipe's)")
    max_evaluations: Optional[int] = Field(
        None, ge=1, description="every tree's evaluation budget (default: its recipe's; less is a quick look only)"
    )
    clones: int = Field(30, ge=0, le=10000, description="clones grown per tree")
    realisations: int = Field(1, ge=0, le=1000, description="synthetic stands grown from the clones")
    positions: Literal["qsm", "stem-map"] = Field(
        "qsm", description="where the trees stand: the QSMs' own shared frame, or the stem map's x, y"
    )
    mesh: Literal["ply", "obj"] = Field("ply", description="format of each synthetic stand's mesh")
    scan_density: float = Field(
        500.0, gt=0, le=1e5, description="points per m² of bark in each synthetic stand's scan (LAS)"
    )
    executor: dict = Field(default_factory=lambda: {"kind": "process"}, description="where the trees run")


# --------------------------------------------------------------------------- sources
def _stem_rows(path: Path) -> tuple[list[str], list[dict]]:
    try:
        text = path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise StandError(f"{path}: stem map not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise StandError(f"{path}: cannot be read as a CSV stem map ({exc})") from None
    sample = text[:4096]
    try:
        dialect = csv.Sniffer().sniff(sample, delimiters=",;\t") if sample.strip() else csv.excel
    except csv.Error:
        dialect = csv.excel
    reader = csv.DictReader(text.splitlines(), dialect=dialect)
    header = [h.strip().lower() for h in (reader.fieldnames or [])]
    rows = [{(k or "").strip().lower(): (v or "").strip() for k, v in r.items()} for r in reader]
    return header, rows


def read_stem_map(path) -> list[StandTree]:
    """The trees of a stem map: a CSV with columns ``file, x, y`` (m; a file relative to the
    CSV's folder) and optionally ``tree, z, model, recipe``.

    Raises
    ------
    StandError
        One line naming the file, the row (1-based, the header is row 1) and the value: a missing
        column, an unknown file, a tree or file twice, a position that is not a number.
    """
    path = Path(path)
    header, rows = _stem_rows(path)
    missing = [c for c in STEM_MAP_REQUIRED if c not in header]
    if missing:
        raise StandError(
            f"{path}: no column {', '.join(repr(c) for c in missing)} (columns: {', '.join(header) or 'none'}; "
            f"a stem map needs {', '.join(STEM_MAP_REQUIRED)}, optionally {', '.join(STEM_MAP_OPTIONAL)})"
        )
    if not rows:
        raise StandError(f"{path}: the stem map lists no tree")
    trees, seen_name, seen_file = [], {}, {}
    for i, r in enumerate(rows, start=2):
        where = f"{path} row {i}"
        if not r.get("file"):
            raise StandError(f"{where}: the file is empty")
        f = Path(r["file"]).expanduser()
        f = f if f.is_absolute() else (path.parent / f)
        if not f.is_file():
            raise StandError(f"{where}: file '{r['file']}' not found (looked for {f})")
        pos = {}
        for c in ("x", "y", "z"):
            v = r.get(c, "")
            if c == "z" and v == "":
                continue
            try:
                pos[c] = float(v)
            except ValueError:
                pos[c] = math.nan
            if not math.isfinite(pos[c]):
                raise StandError(f"{where}: {c} = {v!r} is not a number (m)")
        key = str(f.resolve())
        if key in seen_file:
            raise StandError(f"{path} rows {seen_file[key]} and {i}: the file '{r['file']}' twice")
        name = slug(r.get("tree") or f.stem)
        if name in seen_name:
            raise StandError(f"{path} rows {seen_name[name]} and {i}: the tree '{name}' twice")
        seen_name[name], seen_file[key] = i, i
        rec = r.get("recipe") or None
        if rec:
            rp = Path(rec).expanduser()
            rp = rp if rp.is_absolute() else path.parent / rp
            if not rp.is_file():
                raise StandError(f"{where}: recipe '{rec}' not found (looked for {rp})")
            rec = str(rp.resolve())
        trees.append(StandTree(name=name, file=key, model=r.get("model") or None, recipe=rec, **pos))
    return trees


def trees_from_source(source) -> list[StandTree]:
    """The trees of a folder of QSMs (every file a reader takes), a glob (``plot/*.mat``) or one
    QSM file, in name order; each named by its file's stem.

    Raises
    ------
    StandError
        When the source names nothing, or two files would give one name.
    """
    text = str(source)
    p = Path(text).expanduser()
    suffixes = set(qsm_suffixes())
    if p.is_dir():
        files = sorted(f for f in p.iterdir() if f.is_file() and f.suffix.lower() in suffixes)
        if not files:
            raise StandError(f"{p}: no QSM file in this folder (looked for {', '.join(sorted(suffixes))})")
    elif glob.has_magic(text):
        files = sorted(Path(f) for f in glob.glob(str(p)) if Path(f).is_file())
        if not files:
            raise StandError(f"{text}: matches no file")
    elif p.is_file():
        files = [p]
    else:
        raise StandError(f"{text}: not found (give a folder of QSMs, a glob such as 'plot/*.mat', or --stem-map)")
    trees, seen = [], {}
    for f in files:
        name = slug(f.stem)
        if name in seen:
            raise StandError(f"{seen[name]} and {f}: two files of one name '{name}'; rename one, or use a stem map")
        seen[name] = f
        trees.append(StandTree(name=name, file=str(f.resolve())))
    return trees


def check_models(settings: StandSettings) -> None:
    """Every model a stand names (its own and its trees') is an installed growth model."""
    from ..config import did_you_mean
    from ..registry import discover

    known = discover().names("ssm")
    for where, m in [("model", settings.model)] + [(f"tree {t.name}: model", t.model) for t in settings.trees]:
        if m is not None and m not in known:
            raise StandError(f"{where}: unknown growth model {m!r} (known: {', '.join(known)}){did_you_mean(m, known)}")


# --------------------------------------------------------------------------- the stand's files
def read_settings(stand_dir) -> StandSettings:
    """The settings of an existing stand (``STAND/stand.toml``)."""
    from ..config import read_toml

    path = StandFiles(stand_dir).settings_path
    try:
        return StandSettings.model_validate(read_toml(path))
    except (OSError, BayesForestError) as exc:
        raise StandError(f"{path}: cannot be read ({exc})") from None
    except ValidationError as exc:
        raise StandError(f"{path}: not a stand's settings ({exc.errors()[0]['msg']})") from None


def write_settings(stand_dir, settings: StandSettings) -> None:
    import tomli_w

    from ..io import jsonable

    text = tomli_w.dumps(jsonable(settings.model_dump(exclude_none=True), strict=True))
    _atomic_text(StandFiles(stand_dir).settings_path, text)


def _atomic_text(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text, encoding="utf-8")
    tmp.replace(path)


# --------------------------------------------------------------------------- one tree (a task)
#: one tree at a time in a process: a fit's serial executor keeps its scoring context in the
#: process (a Dask worker with several threads runs its trees one after another)
_ONE_TREE = threading.Lock()


def _recipe_text(job: dict) -> str:
    """The tree's recipe: the stand's (or the tree's own) with this tree as its target, else
    ``bforest init``'s for the tree."""
    import tomli_w

    from .recipe import write_recipe

    out = Path(job["recipe_path"])
    if job["recipe"] is None:
        write_recipe(job["file"], out, job["model"])
        return out.read_text(encoding="utf-8")
    raw = recipe_for_tree(job["recipe"], job["file"])
    text = f"# {job['name']}: the stand's recipe {job['recipe']} with this tree as its target\n" + tomli_w.dumps(raw)
    _atomic_text(out, text)
    return text


def recipe_for_tree(recipe, qsm) -> dict:
    """A recipe (TOML file) as a config table with the QSM ``qsm`` as its target (its other paths
    made absolute, so the table holds wherever it is written)."""
    from ..config import read_toml

    raw = read_toml(recipe)
    base = Path(recipe).resolve().parent
    target = {k: v for k, v in raw.get("target", {}).items() if k != "generate"}
    if target.get("references"):
        target["references"] = [str((base / r).resolve()) for r in target["references"]]
    raw["target"] = {**target, "qsm": str(qsm)}
    return raw


def check_recipe(recipe, qsm) -> None:
    """A recipe given for every tree is a valid run config with ``qsm`` as its target: checked
    once, before any tree starts (StandError naming the recipe)."""
    from ..config import parse_config

    try:
        parse_config(recipe_for_tree(recipe, qsm), source=str(recipe))
    except BayesForestError as exc:
        raise StandError(f"recipe {exc}") from None


def _tree_config(job: dict):
    """The tree's run config: its recipe, with the stand's run seed and the serial executor (the
    task is the unit of work; results never depend on the executor)."""
    from ..config import parse_config, read_toml

    path = Path(job["recipe_path"])
    if not path.exists():
        _recipe_text(job)
    raw = read_toml(path)
    raw["executor"] = {"kind": "serial"}
    if job["seed"] is not None:
        raw["seed"] = int(job["seed"])
    if job["max_evaluations"] is not None:
        raw.setdefault("stop", {})["max_evaluations"] = int(job["max_evaluations"])
    return parse_config(raw, base_dir=path.resolve().parent, source=str(path))


def _fit_tree(job: dict) -> dict:
    from ..registry import component
    from .clones import clones
    from .fit import fit

    run = Path(job["run_dir"])
    files = RunFiles(run)
    if not files.best_path.exists():
        cfg = _tree_config(job)
        fit(cfg, run, resume=files.evaluations_path.exists(), progress=False)
    if job["clones"]:
        clones(run, n=job["clones"], executor=component("executor", "serial"), progress=False)
    return tree_row(job, run)


def tree_task(job: dict) -> dict:
    """Fit one tree of a stand and grow its clones (in a worker: never raises for the tree's own
    faults, which come back as a failed row with their one-line reason)."""
    with _ONE_TREE:
        try:
            return _fit_tree(job)
        except (BayesForestError, OSError, ValueError) as exc:
            return failed_row(job, _one_line(exc))
        except Exception as exc:  # noqa: BLE001 - a plugin's fault costs this tree only
            return failed_row(job, f"{type(exc).__name__}: {_one_line(exc)}")


def _one_line(exc) -> str:
    text = " ".join(str(exc).split())
    return text if len(text) <= 400 else text[:397] + "..."


# --------------------------------------------------------------------------- the table
#: the tree-level statistics of the table: the tree's value and the clones' mean
TABLE_STATISTICS = ("height", "dbh", "crown_spread", "crown_base_height", "n_branches_o1", "stem_length")
_HEAD = ["tree", "file", "status", "reason", "model", "seed", "x", "y", "z"]
_FIT = ["evaluations", "stop_kind", "timeouts", "distance", "heldout_distance", "clones", "verdict", "warnings"]


def failed_row(job: dict, reason: str) -> dict:
    return {
        "tree": job["name"],
        "file": job["file"],
        "status": "failed",
        "reason": reason,
        **{k: job.get(k) for k in ("x", "y", "z")},
    }


def tree_row(job: dict, run: Path) -> dict:
    """The table's row of a finished tree, from its run folder (results only: no times)."""
    files = RunFiles(run)
    best = files.read_best()
    cfg = json.loads(json.dumps(_config_of(run)))
    row = {
        "tree": job["name"],
        "file": job["file"],
        "status": "ok",
        "reason": clock_warning(best) or "",
        "model": cfg.get("ssm", {}).get("kind", ""),
        "seed": cfg.get("seed"),
        **{k: job.get(k) for k in ("x", "y", "z")},
        "evaluations": best.get("n_evaluations"),
        "stop_kind": best.get("stop_kind", ""),
        "timeouts": (best.get("stop") or {}).get("timeouts", 0),
        "distance": best.get("distance"),
        "heldout_distance": best.get("heldout_distance"),
    }
    summary_path = files.clones_dir() / RunFiles.CLONE_SUMMARY
    if summary_path.exists():
        summary = json.loads(summary_path.read_text(encoding="utf-8"))
        fid = summary.get("fidelity") or {}
        table = {r["statistic"]: r for r in fid.get("table", [])}
        warned = [r["statistic"] for r in fid.get("table", []) if r.get("warn")]
        row.update(
            clones=summary.get("ok", 0),
            verdict="pass" if not warned else "warn",
            warnings=" ".join(warned),
        )
        for k in TABLE_STATISTICS:
            r = table.get(k, {})
            row[k] = r.get("target")
            row[f"{k}_clones"] = r.get("mean")
    free = list(cfg.get("ssm", {}).get("free", {}))
    row["params"] = {k: best["params"][k] for k in free if k in best["params"]}
    return row


def _config_of(run: Path) -> dict:
    from ..config import read_toml

    return read_toml(RunFiles(run).config_path)


def table_columns(rows: list[dict]) -> list[str]:
    stats = [c for k in TABLE_STATISTICS for c in (k, f"{k}_clones")]
    params = sorted({k for r in rows for k in (r.get("params") or {})})
    return _HEAD + _FIT + stats + [f"param:{p}" for p in params]


def write_table(path: Path, rows: list[dict]) -> None:
    """``stand.csv``: one row per tree in the stand's order, numbers as Python writes them (every
    digit, so two tables compare equal exactly when their results do)."""
    cols = table_columns(rows)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(cols)
        for r in rows:
            params = r.get("params") or {}
            w.writerow(
                [
                    _cell(params.get(c[6:]) if c.startswith("param:") else r.get(c))
                    for c in cols  # fmt: skip
                ]
            )
    tmp.replace(path)


def _cell(v) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return repr(v) if math.isfinite(v) else ""
    return str(v)


def read_table(path) -> list[dict]:
    """The rows of a ``stand.csv`` (values as text; ``params`` gathered from the ``param:`` columns)."""
    with open(path, newline="", encoding="utf-8") as fh:
        rows = list(csv.DictReader(fh))
    for r in rows:
        r["params"] = {k[6:]: float(v) for k, v in list(r.items()) if k.startswith("param:") and v != ""}
    return rows


# --------------------------------------------------------------------------- the driver
@dataclass
class StandResult:
    """Outcome of :func:`run_stand`."""

    stand_dir: Path
    rows: list[dict]
    fitted: int  # trees fitted (or continued) by this call
    already: int  # trees that had finished before it
    synthetic: list[Path]

    @property
    def failed(self) -> list[dict]:
        return [r for r in self.rows if r.get("status") != "ok"]


def plan_stand(settings: StandSettings, stand_dir) -> tuple[list[dict], list[dict]]:
    """The tasks of a stand, tallest tree first, and the rows of trees that cannot start (their QSM
    cannot be read: one line each). Reads every QSM once, for its position and its height."""
    files = StandFiles(stand_dir)
    jobs, bad = [], []
    for i, t in enumerate(settings.trees):
        job = {
            "index": i,
            "name": t.name,
            "file": t.file,
            "model": t.model or settings.model,
            "recipe": t.recipe or settings.recipe,
            "recipe_path": str(files.recipe_path(t.name)),
            "run_dir": str(files.run_dir(t.name)),
            "seed": settings.seed,
            "max_evaluations": settings.max_evaluations,
            "clones": settings.clones,
            "x": t.x,
            "y": t.y,
            "z": t.z,
        }
        try:
            tree = read_qsm(t.file)
        except (BayesForestError, OSError, ValueError) as exc:
            bad.append(failed_row(job, _one_line(exc)))
            continue
        base = tree.start[0]
        if settings.positions == "qsm":
            job["x"], job["y"], job["z"] = (float(v) for v in base)
        elif job["z"] is None:
            job["z"] = 0.0
        job["height"] = float(tree.end[:, 2].max() - base[2])
        jobs.append(job)
    jobs.sort(key=lambda j: (-j["height"], j["index"]))
    return jobs, bad


def finished(job: dict) -> bool:
    """Whether a tree's fit and its clones are complete (a resumed stand does not run it)."""
    files = RunFiles(job["run_dir"])
    if not files.best_path.exists():
        return False
    if not job["clones"]:
        return True
    summary = files.clones_dir() / RunFiles.CLONE_SUMMARY
    if not summary.exists():
        return False
    s = json.loads(summary.read_text(encoding="utf-8"))
    return bool(s.get("complete")) and int(s.get("count", 0)) >= int(job["clones"])


def frame_warning(jobs: list[dict]) -> str | None:
    """A line when the QSMs' own coordinates do not look like one plot's frame (stems on one
    spot, or bases kilometres or hundreds of metres of height apart): the synthetic stand then
    needs a stem map."""
    if len(jobs) < 2:
        return None
    xyz = np.array([[j["x"], j["y"], j["z"]] for j in jobs], float)
    d = np.linalg.norm(xyz[:, None, :2] - xyz[None, :, :2], axis=2)
    np.fill_diagonal(d, np.inf)
    close, span, rise = float(d.min()), float(np.ptp(xyz[:, 0]) + np.ptp(xyz[:, 1])), float(np.ptp(xyz[:, 2]))
    if close < 0.1 or span > 1000.0 or rise > 100.0:
        return (
            f"the QSMs do not look like one plot's frame (stems {close:.2f} m apart at the closest, bases "
            f"{rise:.0f} m apart in height): the synthetic stands place them as the files do; give a stem map "
            "(--stem-map) for a plot"
        )
    return None


class _Progress:
    """Trees done of all, and the evaluations the stand's fits have logged (read from their logs
    every few seconds, wherever the workers run: the run folders are the stand's)."""

    def __init__(self, total: int, jobs: list[dict], enabled: bool):
        from .progress import progress_bar

        self.bar = progress_bar(total, "stand", "tree", enabled)
        self.jobs = jobs
        self.enabled = enabled
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._poll, name="bforest-stand-progress", daemon=True)
        if enabled:
            self._thread.start()

    def _poll(self):
        while not self._stop.wait(3.0):
            n = sum(logged_count(RunFiles(j["run_dir"]).evaluations_path) for j in self.jobs)
            self.bar.set_postfix_str(f"evaluations {n}", refresh=True)

    def done(self, row: dict):
        self.bar.update(1)
        if row.get("status") != "ok":
            self.bar.write(f"{row['tree']}: failed: {row.get('reason', '')}")

    def close(self):
        self._stop.set()
        if self.enabled:
            self._thread.join(5)
        self.bar.close()


def _executor(settings: StandSettings):
    from ..registry import component

    spec = dict(settings.executor)
    kind = spec.pop("kind", "process")
    try:
        return component("executor", kind, **spec)
    except BayesForestError as exc:
        raise ConfigError(f"stand executor: {exc}") from None


def check_stand_dir(stand_dir, resume: bool, overwrite: bool) -> bool:
    """Whether ``stand_dir`` holds a stand; StandError when the command cannot use it (a stand
    without --resume or --overwrite, no stand to resume, a folder of other files)."""
    stand_dir = Path(stand_dir)
    holds = StandFiles(stand_dir).settings_path.exists()
    if resume and not holds:
        raise StandError(f"{stand_dir}: holds no stand to resume (no {StandFiles.SETTINGS})")
    if holds and not resume and not overwrite:
        raise StandError(
            f"{stand_dir}: holds a stand already; continue it with --resume, or start anew with --overwrite "
            "(deletes its fits)"
        )
    if not resume and not holds and stand_dir.is_dir() and any(stand_dir.iterdir()):
        raise StandError(f"{stand_dir}: a folder holding other files; choose an empty or new -o")
    if stand_dir.exists() and not stand_dir.is_dir():
        raise StandError(f"{stand_dir}: exists and is not a folder; choose another -o")
    return holds


def run_stand(
    settings: StandSettings,
    stand_dir,
    resume: bool = False,
    overwrite: bool = False,
    progress: bool = True,
    warn=print,
) -> StandResult:
    """Fit every tree of a stand, grow its clones and write the table, the synthetic stands and
    the report (see the module text).

    Parameters
    ----------
    settings : StandSettings
        The trees and how to fit them (with ``resume``: the stand's own, from ``stand.toml``;
        only the executor may differ).
    stand_dir : path
        The stand folder.
    resume : bool
        Continue a stand: trees whose fit and clones are complete are read, not refitted.
    overwrite : bool
        Delete what an earlier stand wrote in the folder first (its runs included).

    Raises
    ------
    StandError
        The folder holds a stand and neither ``resume`` nor ``overwrite`` is given (or holds none
        to resume), or another command uses it.
    """
    stand_dir = Path(stand_dir)
    files = StandFiles(stand_dir)
    holds = check_stand_dir(stand_dir, resume, overwrite)
    if not settings.trees:
        raise StandError("the stand has no trees")
    check_models(settings)
    with run_lock(stand_dir, create=True):
        if overwrite and holds:
            files.clear()
        if resume:
            old = read_settings(stand_dir)
            if old.model_dump(exclude={"executor"}) != settings.model_dump(exclude={"executor"}):
                raise StandError(
                    f"{stand_dir}: the trees or settings differ from the stand's {StandFiles.SETTINGS}; resume with "
                    "the stand's own (bforest stand --resume -o STAND)"
                )
        for d in (files.runs_dir, files.recipes_dir):
            d.mkdir(parents=True, exist_ok=True)
        write_settings(stand_dir, settings)
        jobs, bad = plan_stand(settings, stand_dir)
        order = {t.name: i for i, t in enumerate(settings.trees)}
        rows: dict[str, dict] = {r["tree"]: r for r in bad}
        done = [j for j in jobs if finished(j)]
        for j in done:
            rows[j["name"]] = tree_row(j, Path(j["run_dir"]))
        todo = [j for j in jobs if not finished(j)]
        if settings.positions == "qsm":
            note = frame_warning(jobs)
            if note and settings.realisations:
                warn(f"warning: {note}")

        def table():
            write_table(files.table_path, sorted(rows.values(), key=lambda r: order[r["tree"]]))

        table()
        if todo:
            _run_trees(settings, todo, rows, table, progress)
        synthetic = []
        if settings.realisations:
            from .synthetic import grow_stand

            synthetic = grow_stand(stand_dir, settings, jobs, rows)
        result = StandResult(
            stand_dir, sorted(rows.values(), key=lambda r: order[r["tree"]]), len(todo), len(done), synthetic
        )
        return result


def _run_trees(settings: StandSettings, todo: list[dict], rows: dict, table, progress: bool) -> None:
    ex = _executor(settings)
    ex.on_lost = lambda fn, item, status, message: failed_row(
        item, f"its worker {status} ({message}); continue with --resume"
    )
    bar = _Progress(len(todo), todo, progress)
    left = {j["name"]: j for j in todo}
    try:
        with ex.started(None) as pool:
            for _, row in pool.map_unordered(tree_task, todo):
                rows[row["tree"]] = row
                left.pop(row["tree"], None)
                table()
                bar.done(row)
    except (KeyboardInterrupt, SystemExit):
        raise
    except Exception as exc:  # noqa: BLE001 - the cluster went away (a worker killed too often, ...)
        for name, j in left.items():
            rows[name] = failed_row(j, f"interrupted: {type(exc).__name__}: {_one_line(exc)}; continue with --resume")
        table()
        raise StandError(
            f"the stand stopped ({type(exc).__name__}: {_one_line(exc)}); {len(left)} tree(s) unfinished, every "
            "finished tree and logged evaluation kept: continue with --resume"
        ) from None
    finally:
        bar.close()


# --------------------------------------------------------------------------- stand configs
#: keys of a stand config's ``[stand]`` table beyond :class:`StandSettings`' own: where the trees
#: come from (a folder or glob of QSMs, or a stem map), relative to the config's folder
SOURCE_KEYS = ("qsms", "stem_map")


def settings_from(
    source=None, stem_map=None, base_dir: Path | None = None, executor: dict | None = None, **options
) -> StandSettings:
    """A stand's settings from its source (a folder, glob or file of QSMs) or a stem map, and
    the options of :class:`StandSettings` (``None`` values are left at their defaults).

    Raises
    ------
    StandError
        Neither or both sources, or a source that names no tree (one line each).
    """
    base = Path(base_dir) if base_dir is not None else Path.cwd()

    def at(p):
        q = Path(str(p)).expanduser()
        return q if q.is_absolute() else base / q

    if (source is None) == (stem_map is None):
        raise StandError("give the trees as a folder or glob of QSMs, or as a stem map (--stem-map), not both")
    if stem_map is not None:
        trees, positions = read_stem_map(at(stem_map)), "stem-map"
    else:
        text = str(source)
        trees, positions = (
            trees_from_source(str(at(text)) if not Path(text).expanduser().is_absolute() else text),
            "qsm",
        )
    opts = {k: v for k, v in options.items() if v is not None}
    for k in ("recipe",):
        if k in opts:
            rp = at(opts[k])
            if not rp.is_file():
                raise StandError(f"recipe {opts[k]}: not found (looked for {rp})")
            opts[k] = str(rp.resolve())
    try:
        settings = StandSettings(trees=trees, positions=positions, executor=executor or {"kind": "process"}, **opts)
    except ValidationError as exc:
        e = exc.errors()[0]
        raise StandError(f"stand.{'.'.join(str(x) for x in e['loc'])}: {e['msg']}") from None
    check_models(settings)
    _executor(settings)  # its settings checked now, not after the first tree
    for rec in {t.recipe for t in settings.trees if t.recipe} | ({settings.recipe} if settings.recipe else set()):
        check_recipe(rec, settings.trees[0].file)
    return settings


def load_stand_config(path, stem_map=None, executor: dict | None = None, **options) -> StandSettings:
    """A stand config (TOML): a ``[stand]`` table (``qsms`` or ``stem_map``, relative to the
    config's folder, and the options of :class:`StandSettings`) and an ``[executor]`` table as a
    run's. ``stem_map``, ``executor`` and ``options`` (where not None) replace the config's.

    Raises
    ------
    StandError
        Naming the file and the key (an unknown key, a bad value, a missing source).
    """
    from ..config import did_you_mean, read_toml

    path = Path(path)
    try:
        raw = read_toml(path)
    except (OSError, BayesForestError) as exc:
        raise StandError(f"{path}: {exc}") from None
    unknown = sorted(set(raw) - {"stand", "executor"})
    if unknown or not isinstance(raw.get("stand"), dict):
        raise StandError(
            f"{path}: a stand config holds a [stand] table and an [executor] table"
            + (f" (unknown: {', '.join(unknown)})" if unknown else " (no [stand])")
        )
    stand = dict(raw["stand"])
    allowed = set(SOURCE_KEYS) | (set(StandSettings.model_fields) - {"trees", "positions", "executor"})
    bad = sorted(set(stand) - allowed)
    if bad:
        raise StandError(
            f"{path}: stand.{bad[0]}: unknown key (allowed: {', '.join(sorted(allowed))}){did_you_mean(bad[0], allowed)}"
        )
    source, own_map = stand.pop("qsms", None), stand.pop("stem_map", None)
    here = Path.cwd()
    if stem_map is not None:  # the command line's, relative to where it runs
        source, own_map = None, str((here / Path(stem_map).expanduser()).resolve())
    stand.update({k: v for k, v in options.items() if v is not None})
    try:
        return settings_from(
            source, own_map, base_dir=path.resolve().parent, executor=executor or raw.get("executor"), **stand
        )
    except StandError as exc:
        raise StandError(f"{path}: {exc}") from None
