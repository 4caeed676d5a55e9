"""Amortised inference: the prior an estimator is trained on, the summaries it reads, its file,
and a tree's posterior from it.

An amortised estimator (:class:`~bforest_core.interfaces.AmortisedEstimator`, e.g. the ``flow``
plugin) learns p(parameters | summaries of a tree) once, from trees grown from a prior
(``bforest train``, :mod:`.train`); a tree's posterior is then one pass (``bforest posterior``).

* **The prior** (:class:`TrainingPrior`) is that of ``bforest init``: for a draw, a reference tree
  of the crown form (the three Ruotsinkylä pines for the shipped pine estimators) is scaled to a
  height drawn uniformly from ``heights`` (its lengths and the measures a recipe's bounds scale by
  scaled, its angles and ratios kept), the model's recipe box for that tree is resolved
  (:func:`~.recipe.recipe_box`: bounds scaled by a measure of the tree, such as LIGNUM's years per
  whorl, resolved; the recipe's fixed values and settings, such as SOT's world cube, taken), and
  the parameters are drawn uniformly in that box. One estimator so serves trees of the form at any height in the range: the height a
  tree's box was scaled for is the first of the summaries it is conditioned on.
* **The summaries** (:class:`Summaries`) carry what the fit's judge sees: the tree-level
  statistics of :func:`~bforest_core.metrics.tree_summary` (sizes, counts, lengths, volumes and
  the vertical profile in logarithms; branching angles in degrees) and a fixed-length description
  of the branch and segment tables of the recipes' structural sets (``S0,1``, ``B1,2``): the
  logarithm of each table's rows and its columns' 10/25/50/75/90 % quantiles.
* **The file** (:func:`write_estimator`, :func:`read_estimator`): one ``.npz`` (no pickles) holding
  a JSON header (the prior, the summary definition, the model and its version, the estimator's
  kind, settings and state, the training record and provenance) and the weights. A file whose
  summary definition or model version differs from the installed code's is refused with one
  line, never read into wrong answers.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..config import SCALE_MEASURES
from ..errors import ConfigError, PluginError
from ..metrics import TreeMeasures, measure_tree, summary_unit, tree_summary
from ..registry import component, component_class, discover
from .recipe import recipe_box, write_recipe

#: what an estimator file says it is
FORMAT = "bayesforest-amortised-estimator"
#: the layout of the file; a reader of another layout refuses it
FORMAT_VERSION = 1
#: the summaries' definition: raise it whenever :meth:`Summaries.vector` computes other values
SUMMARY_VERSION = 1
#: streams of the draws of a training and of a calibration's targets
TRAIN_STREAM, CALIBRATION_STREAM = 0xA3D1, 0x5BC0
#: tree-level statistics of the summaries (:func:`~bforest_core.metrics.tree_summary`)
STATISTICS = (
    "height",
    "dbh",
    "base_diameter",
    "crown_spread",
    "crown_base_height",
    "stem_length",
    *(f"{s}_o{w}" for w in (1, 2, 3) for s in ("n_branches", "length", "angle", "angle_iqr")),
    *(f"volume_o{w}" for w in (0, 1, 2, 3)),
    *(f"profile_{s}_b{k}" for k in range(5) for s in ("n", "len")),
)
#: the recipes' structural sets and the quantiles (%) of their columns
TABLE_SETS = ("S0,1", "B1,2")
QUANTILES = (10, 25, 50, 75, 90)
#: offset of the logarithm of a statistic by unit: a count of 0 or a length near 0 stays finite
LOG_OFFSET = {"count": 1.0, "m": 0.05, "m^3": 1e-4}
#: lengths of :class:`~bforest_core.metrics.TreeMeasures` scaled with the height: those a recipe's
#: bounds may be scaled by (but the thinnest branch, a floor of the scan), and where the crown's
#: centre lies and how long the stem is
SCALED_MEASURES = (*(m for m in SCALE_MEASURES if m != "thinnest_branch"), "crown_offset", "stem_length")
#: heights of the reference trees the prior's overall bounds are taken over
_BOUND_STEPS = 9


# ------------------------------------------------------------------------------ summaries
@dataclass(frozen=True)
class Summaries:
    """The summaries an estimator is conditioned on (see the module text)."""

    statistics: tuple = STATISTICS
    sets: tuple = TABLE_SETS
    quantiles: tuple = QUANTILES
    features: str = "branch-segment"

    def feature_set(self):
        """The feature set of the tables (a registered component)."""
        return component("features", self.features, sets=list(self.sets))

    def labels(self) -> list[str]:
        """One name per value of :meth:`vector`."""
        fs = self.feature_set()
        out = ["size:log_height_m", *(f"stat:{s}" for s in self.statistics)]
        for k in self.sets:
            out.append(f"{k}:log_rows")
            out += [f"{k}:{c}:q{q}" for c in fs.columns(k) for q in self.quantiles]
        return out

    def definition(self) -> dict:
        """What the summaries are, as stored in an estimator's file."""
        return {
            "version": SUMMARY_VERSION,
            "statistics": list(self.statistics),
            "features": {"kind": self.features, "sets": list(self.sets)},
            "quantiles": list(self.quantiles),
            "labels": self.labels(),
        }

    @classmethod
    def from_definition(cls, d: dict) -> Summaries:
        return cls(tuple(d["statistics"]), tuple(d["features"]["sets"]), tuple(d["quantiles"]), d["features"]["kind"])

    def vector(self, tree, size: float, fs=None) -> np.ndarray:
        """The summaries of ``tree`` whose recipe box was scaled for the height ``size`` (m);
        ``fs``: the :meth:`feature_set`, when the caller keeps one."""
        s = tree_summary(tree, min_diameter=0.0)
        out = [math.log(max(float(size), 1e-3))]
        for name in self.statistics:
            v, unit = float(s[name]), summary_unit(name)
            if unit in LOG_OFFSET:
                out.append(math.log(max(v, 0.0) + LOG_OFFSET[unit]))
            else:  # angles (deg); none without branches of that order
                out.append(v if math.isfinite(v) else 0.0)
        fs = self.feature_set() if fs is None else fs
        U = fs.extract(tree)
        for k in self.sets:
            u = np.asarray(U[k], float)
            out.append(math.log1p(u.shape[0]))
            if u.shape[0]:
                out.extend(np.percentile(u, self.quantiles, axis=0).T.reshape(-1))
            else:
                out.extend([0.0] * (u.shape[1] * len(self.quantiles)))
        return np.asarray(out, float)


# ------------------------------------------------------------------------------ the prior
def scaled_measures(m: TreeMeasures, height: float) -> TreeMeasures:
    """``m`` of a tree of the same form ``height`` m tall: its lengths and the measures a recipe's
    bounds scale by (:data:`SCALED_MEASURES`: LIGNUM's whorls too, so its years follow the height)
    scaled; its angles and ratios (and the QSM's thinnest branch, a floor of the scan) kept."""
    f = float(height) / m.height
    new = {k: getattr(m, k) * f for k in SCALED_MEASURES}
    new["stem_path"] = tuple(tuple(c * f for c in q) for q in m.stem_path)
    return dataclasses.replace(m, **new)


def _measures_from(d: dict) -> TreeMeasures:
    d = dict(d)
    d["stem_path"] = tuple(tuple(q) for q in d.get("stem_path", ()))
    return TreeMeasures(**d)


@dataclass
class Draw:
    """One draw of a :class:`TrainingPrior`: the tree it is scaled to and the parameters."""

    index: int
    reference: int
    height: float
    settings: dict
    fixed: dict
    theta: np.ndarray
    seed: int

    def params(self, names, integer) -> dict:
        """The parameters the model grows this draw's tree from (the fixed ones included)."""
        from ..interfaces import parameter_value

        return {**self.fixed, **{n: parameter_value(v, i) for n, v, i in zip(names, self.theta, integer)}}


@dataclass
class TrainingPrior:
    """The prior of a training (see the module text).

    Attributes
    ----------
    model : str
        The growth model.
    references : list of (str, TreeMeasures)
        The reference trees of the crown form, by name.
    heights : (float, float)
        Range of the heights (m) the references are scaled to, drawn uniformly.
    names, lower, upper, integer
        The free parameters and the bounds of every draw's box together.
    """

    model: str
    references: list
    heights: tuple
    names: list
    lower: np.ndarray
    upper: np.ndarray
    integer: np.ndarray

    @classmethod
    def build(cls, model: str, references: list, heights) -> TrainingPrior:
        """The prior of ``model`` over ``references`` (name, measures) scaled to ``heights``;
        ConfigError when the references' recipes fit other parameters (other crown forms)."""
        lo_h, hi_h = (float(h) for h in heights)
        if not 0 < lo_h < hi_h:
            raise ConfigError(f"train.heights: need 0 < lower < upper (got {lo_h}, {hi_h})")
        if not references:
            raise ConfigError("train.references: name at least one reference tree of the crown form")
        names, lo, hi, integer = None, None, None, None
        for name, m in references:
            for h in np.linspace(lo_h, hi_h, _BOUND_STEPS):
                box = recipe_box(model, scaled_measures(m, h))
                if names is None:
                    names, lo, hi, integer = box.names, box.lower.copy(), box.upper.copy(), box.integer
                elif box.names != names:
                    raise ConfigError(
                        f"train.references: {name} at {h:.1f} m gets a {model} recipe of other parameters "
                        f"({', '.join(sorted(set(box.names) ^ set(names)))} differ): the references must share "
                        "a crown form (bforest init says each tree's)"
                    )
                else:
                    lo, hi = np.minimum(lo, box.lower), np.maximum(hi, box.upper)
        lo = np.where(integer, np.ceil(lo), lo)
        hi = np.where(integer, np.floor(hi), hi)
        return cls(model, list(references), (lo_h, hi_h), list(names), lo, hi, np.asarray(integer, bool))

    @property
    def form(self) -> str:
        """``excurrent`` or ``decurrent``: the crown form of the references."""
        return "decurrent" if self.references[0][1].decurrent else "excurrent"

    def draw(self, seed: int, i: int, stream: int = TRAIN_STREAM) -> Draw:
        """Draw ``i`` of the stream ``stream`` of ``seed``: the same whatever else is drawn."""
        from .posterior import uniform_draw

        rng = np.random.default_rng(np.random.SeedSequence([int(seed), int(stream), int(i)]))
        ref = int(rng.integers(len(self.references)))
        height = float(self.heights[0] + (self.heights[1] - self.heights[0]) * rng.random())
        box = recipe_box(self.model, scaled_measures(self.references[ref][1], height))
        order = [box.names.index(n) for n in self.names]
        theta = uniform_draw(rng, box.lower[order], box.upper[order], box.integer[order])
        return Draw(i, ref, height, box.settings, box.fixed, theta, int(rng.integers(1, 2**31 - 1)))

    def to_dict(self) -> dict:
        return {
            "model": self.model,
            "form": self.form,
            "heights": list(self.heights),
            "references": [{"name": n, "measures": dataclasses.asdict(m)} for n, m in self.references],
            "names": list(self.names),
            "lower": self.lower.tolist(),
            "upper": self.upper.tolist(),
            "integer": self.integer.tolist(),
        }

    @classmethod
    def from_dict(cls, d: dict) -> TrainingPrior:
        refs = [(r["name"], _measures_from(r["measures"])) for r in d["references"]]
        return cls(
            d["model"],
            refs,
            tuple(d["heights"]),
            list(d["names"]),
            np.asarray(d["lower"], float),
            np.asarray(d["upper"], float),
            np.asarray(d["integer"], bool),
        )


def reference_trees(paths) -> list:
    """(name, measures) of each reference QSM (a path or ``sample:NAME``)."""
    from ..io import read_tree
    from ..samples import stem

    out = []
    for p in paths:
        tree = read_tree(p)
        try:
            out.append((stem(p), measure_tree(tree)))
        except ValueError as exc:
            raise ConfigError(f"{p}: cannot be a reference tree: {exc}") from None
    return out


def model_version(model: str) -> str:
    """The installed growth model's version (:attr:`~bforest_core.interfaces.SSM.model_version`)."""
    return str(component_class("ssm", model).model_version)


# ------------------------------------------------------------------------------ the file
@dataclass
class TrainedEstimator:
    """An estimator read from its file: the component (trained), its prior and summaries."""

    header: dict
    estimator: object
    prior: TrainingPrior
    summaries: Summaries
    path: Path | None = None

    @property
    def names(self) -> list[str]:
        return self.prior.names

    @property
    def model(self) -> str:
        return self.prior.model

    def label(self) -> str:
        """One line: what the estimator is (its model, form, heights and training size)."""
        t = self.header.get("training", {})
        return (
            f"{self.header['estimator']['kind']} estimator of {self.model} ({self.prior.form} crowns, "
            f"{self.prior.heights[0]:g}-{self.prior.heights[1]:g} m, trained on {t.get('pairs', '?')} trees)"
        )


def estimator_component(kind: str, settings: dict):
    """The amortised estimator ``kind`` with ``settings``; a PluginError of one line saying what
    to install when its libraries are missing, or that none is installed."""
    if kind not in discover().names("amortised"):
        known = ", ".join(discover().names("amortised")) or "none installed"
        raise PluginError(f"no amortised estimator '{kind}' is installed (known: {known})")
    est = component("amortised", kind, **settings)
    problem = est.missing()
    if problem:
        raise PluginError(problem)
    return est


def estimator_header(prior: TrainingPrior, summaries: Summaries, est, training: dict, seed: int) -> dict:
    """The header of an estimator's file (everything but the weights)."""
    import platform

    from ..provenance import __version__

    meta, _ = est.state()
    return {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "model": prior.model,
        "model_version": model_version(prior.model),
        "prior": prior.to_dict(),
        "summary": summaries.definition(),
        "estimator": {"kind": est.name, "settings": est.settings.model_dump(mode="json"), "state": meta},
        "training": training,
        "seed": int(seed),
        "provenance": {
            "software": f"Bayes Forest {__version__}",
            "python": platform.python_version(),
            "numpy": np.__version__,
            "libraries": est.library_versions(),
            "machine": platform.machine(),
            "created": time.strftime("%Y-%m-%dT%H:%M:%S"),
        },
    }


def write_estimator(path, header: dict, est) -> Path:
    """Write the estimator's file (all or nothing: a temporary file renamed into place)."""
    path = Path(path)
    _, blob = est.state()
    text = json.dumps(header, sort_keys=True).encode("utf-8")
    tmp = path.with_name(path.name + ".tmp.npz")
    np.savez_compressed(tmp, header=np.frombuffer(text, dtype=np.uint8), weights=np.frombuffer(blob, dtype=np.uint8))
    tmp.replace(path)
    return path


def _header(path: Path) -> tuple[dict, bytes]:
    import zipfile

    try:
        with np.load(path, allow_pickle=False) as z:
            text, blob = bytes(z["header"]), bytes(z["weights"])
    except FileNotFoundError:
        raise ConfigError(f"{path}: estimator file not found") from None
    except (OSError, ValueError, KeyError, zipfile.BadZipFile):
        raise ConfigError(f"{path}: not an estimator file (bforest train writes them)") from None
    try:
        header = json.loads(text.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError):
        raise ConfigError(f"{path}: not an estimator file (its header is not JSON)") from None
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        raise ConfigError(f"{path}: not an estimator file (bforest train writes them)")
    return header, blob


def read_estimator(path) -> TrainedEstimator:
    """Read an estimator's file, refusing one this code would read into wrong answers.

    Raises
    ------
    ConfigError
        One line: a missing file, another file, another layout, a model not installed or of
        another version, summaries defined otherwise than this code computes them.
    PluginError
        One line: the estimator's kind is not installed, or its libraries are missing (what to
        install).
    """
    path = Path(path)
    header, blob = checked_header(path)
    spec = header["estimator"]
    est = estimator_component(spec["kind"], spec["settings"])
    est.load_state(spec["state"], blob)
    return TrainedEstimator(
        header, est, TrainingPrior.from_dict(header["prior"]), Summaries.from_definition(header["summary"]), path
    )


def checked_header(path) -> tuple[dict, bytes]:
    """The header and weights of an estimator's file, checked as :func:`read_estimator` checks
    them (its layout, model, model version and summaries; not the estimator's libraries)."""
    path = Path(path)
    header, blob = _header(path)
    if header.get("format_version") != FORMAT_VERSION:
        raise ConfigError(
            f"{path}: an estimator file of layout {header.get('format_version')}; this version of Bayes Forest "
            f"reads layout {FORMAT_VERSION}: retrain it (bforest train)"
        )
    model = header["model"]
    if model not in discover().names("ssm"):
        raise ConfigError(f"{path}: trained on the growth model '{model}', which is not installed")
    have = model_version(model)
    if str(header.get("model_version")) != have:
        raise ConfigError(
            f"{path}: trained on {model} version {header.get('model_version')}, the installed {model} is "
            f"version {have} (it grows other trees): retrain it (bforest train)"
        )
    summaries = Summaries.from_definition(header["summary"])
    want = header["summary"]
    try:
        now = summaries.definition()
    except Exception as exc:  # a feature set that no longer takes these sets
        raise ConfigError(f"{path}: its summaries cannot be computed by this version ({exc}): retrain it") from None
    if want.get("version") != SUMMARY_VERSION or want.get("labels") != now["labels"]:
        raise ConfigError(
            f"{path}: its summaries (definition {want.get('version')}, {len(want.get('labels', []))} values) differ "
            f"from this version's (definition {SUMMARY_VERSION}, {len(now['labels'])} values): retrain it "
            "(bforest train)"
        )
    return header, blob


def shipped_estimators() -> dict[str, Path]:
    """The estimator files the installed plugins ship, by growth model."""
    reg = discover()
    out = {}
    for name in reg.names("amortised"):
        if ("amortised", name) in reg.components:
            out.update(reg.get("amortised", name).shipped())
    return out


def estimator_for(model: str | None, path=None) -> Path:
    """The estimator file to use: ``path``, or the one shipped for ``model``."""
    if path is not None:
        return Path(path)
    shipped = shipped_estimators()
    if model not in shipped:
        have = ", ".join(sorted(shipped)) or "none"
        raise ConfigError(
            f"no estimator ships for the model '{model}' (shipped: {have}); train one with bforest train "
            "and give it with --estimator"
        )
    return shipped[model]


# ------------------------------------------------------------------------------ a tree's posterior
def tree_posterior(te: TrainedEstimator, tree, n: int, seed: int, source: str = "the tree") -> dict:
    """``n`` posterior draws of the estimator's parameters for ``tree``.

    Returns
    -------
    dict
        ``names``, ``samples`` (n, p), ``summaries`` (the tree's), ``measures``, ``warnings``
        (lines: a tree outside what the estimator was trained on).
    """
    try:
        m = measure_tree(tree)
    except ValueError as exc:
        raise ConfigError(f"{source}: cannot be inferred: {exc}") from None
    notes = []
    lo, hi = te.prior.heights
    if not lo <= m.height <= hi:
        notes.append(
            f"{source} is {m.height:.1f} m tall; the estimator was trained on trees of {lo:g}-{hi:g} m: its "
            "posterior there is an extrapolation"
        )
    form = "decurrent" if m.decurrent else "excurrent"
    if form != te.prior.form:
        notes.append(
            f"{source} has a {form} crown; the estimator was trained on {te.prior.form} crowns: its posterior "
            "does not describe this tree"
        )
    x = te.summaries.vector(tree, m.height)
    X = te.estimator.sample(x[None, :], int(n), int(seed))[0]
    return {"names": list(te.names), "samples": X, "summaries": x, "measures": m, "warnings": notes}


def warn_lines(lines) -> None:
    """Each line as a warning (the CLI prints ``warning: ...``)."""
    for line in lines:
        warnings.warn(line, stacklevel=2)


def posterior_for(
    qsm,
    out_dir,
    model: str | None = None,
    estimator=None,
    n: int = 2000,
    seed: int = 1,
    clones: int = 0,
    overwrite: bool = False,
    progress: bool = True,
) -> dict:
    """``bforest posterior``: the amortised posterior of the tree in ``qsm``, written to ``out_dir``
    (:class:`~.store.PosteriorFiles`): ``posterior.csv`` (one column per free parameter, and equal
    weights), ``posterior.nc`` (ArviZ), ``posterior.json`` (the tree, the estimator, per parameter
    mean, sd, 5/50/95 % quantiles and 90 % HDI, warnings, seconds) and, with ``clones``, that many
    posterior-predictive clones in ``clones/`` (clone ``i`` grown from draw ``i`` with its own seed,
    in the tree's own recipe box's world: SOT's cube scaled to its height).

    Returns
    -------
    dict
        ``summary`` (what posterior.json holds), ``samples``, ``estimator`` (the
        :class:`TrainedEstimator`), ``files`` and ``seconds``.
    """
    from ..interfaces import Posterior
    from ..io import read_tree, write_json
    from ..samples import stem
    from .posterior import posterior_outputs
    from .rundir import run_lock
    from .store import PosteriorFiles

    t0 = time.monotonic()
    out = Path(out_dir)
    files = PosteriorFiles(out)
    if files.summary_path.exists() and not overwrite:
        raise ConfigError(f"{out}: holds a posterior already; replace it with --overwrite, or choose another -o")
    path = estimator_for(model, estimator)
    te = read_estimator(path)
    if model is not None and model != te.model:
        raise ConfigError(f"{path}: an estimator of {te.model}, not of --model {model}")
    tree = read_tree(qsm)
    res = tree_posterior(te, tree, n, seed, source=str(qsm))
    with run_lock(out):
        if overwrite:
            files.clear()
        X = res["samples"]
        post = Posterior("population", X, np.full(len(X), 1.0 / len(X)), tuple(te.names))
        table = posterior_outputs(
            out,
            post,
            attrs={"estimator": str(path), "ssm": te.model, "tree": str(qsm)},
            seed=seed,
        )
        m = res["measures"]
        rows = grow_clones(te.model, X[:clones], m, files.clones_dir, seed, te.names, progress) if clones else []
        summary = {
            "tree": str(qsm),
            "tree_name": stem(qsm),
            "height_m": m.height,
            "crown_form": "decurrent" if m.decurrent else "excurrent",
            "estimator": {
                "file": str(path),
                "label": te.label(),
                **{k: te.header[k] for k in ("model", "model_version")},
            },
            "draws": int(n),
            "seed": int(seed),
            "names": te.names,
            "prior": {k: [float(a), float(b)] for k, a, b in zip(te.names, te.prior.lower, te.prior.upper)},
            "posterior_summary": table,
            "warnings": res["warnings"],
            "clones": rows,
            "seconds": time.monotonic() - t0,
        }
        write_json(files.summary_path, summary, strict=True)
    return {"summary": summary, "samples": X, "estimator": te, "files": files, "seconds": summary["seconds"]}


def grow_clones(
    model: str, thetas: np.ndarray, measures: TreeMeasures, out_dir: Path, seed: int, names, progress
) -> list:
    """Grow one clone per row of ``thetas`` (posterior draws) in the world of the tree's own
    recipe box (its fixed values and settings); write ``clone_NNN.txt`` and ``clones.csv``."""
    import csv

    from ..errors import SimulationFailed
    from ..interfaces import parameter_value
    from ..io import write_tree
    from ..metrics import classical_metrics
    from .progress import progress_bar
    from .seeds import clone_seeds
    from .store import PosteriorFiles

    box = recipe_box(model, measures)
    ssm = component("ssm", model, **box.settings)
    integer = [ssm.parameter_spec(k).integer for k in names]
    out_dir.mkdir(parents=True, exist_ok=True)
    rows = []
    bar = progress_bar(len(thetas), "clones", "clone", progress)
    try:
        for i, (theta, s) in enumerate(zip(thetas, clone_seeds(seed, len(thetas)))):
            params = {**box.fixed, **{k: parameter_value(v, b) for k, v, b in zip(names, theta, integer)}}
            row = {"index": i, "seed": s, "status": "ok", "file": "", **{k: params[k] for k in names}}
            try:
                tree = ssm.simulate(params, s)
            except SimulationFailed as exc:
                row["status"] = exc.status
            else:
                row["file"] = write_tree(tree, out_dir / f"clone_{i:03d}.txt").name
                metrics = classical_metrics(tree)
                row.update({k: metrics[k] for k in ("height", "dbh", "crown_spread")})
            rows.append(row)
            bar.update(1)
    finally:
        bar.close()
    cols = ["index", "seed", "status", "file", "height", "dbh", "crown_spread", *names]
    with (out_dir / PosteriorFiles.CLONE_TABLE).open("w", newline="", encoding="utf-8") as fh:
        w = csv.DictWriter(fh, fieldnames=cols, extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)
    return rows


# ------------------------------------------------------------------------------ a fit's start
#: ``[start] estimator`` naming the estimator the installed plugins ship for the fit's model
SHIPPED = "shipped"


def start_estimator_path(cfg) -> Path:
    """The file ``[start] estimator`` names (``"shipped"``: the one shipped for ``[ssm] kind``)."""
    return named_estimator(cfg.start.estimator, cfg.ssm.kind)


def named_estimator(name, model: str | None) -> Path:
    """The file an estimator's ``name`` means: a path, or ``"shipped"`` for the one shipped for ``model``."""
    return estimator_for(model) if name == SHIPPED else Path(name)


def start_problems(cfg) -> list[str]:
    """What keeps ``[start] estimator`` from starting this fit (``bforest config check`` and the
    fit's preflight): a file that cannot be read, another model, a free parameter it lacks, an
    estimator whose libraries are missing."""
    if cfg.start.estimator is None:
        return []
    from ..config import section_settings

    try:
        if not component("optimizer", cfg.optimizer.kind, **section_settings(cfg, "optimizer")).takes_start():
            return [
                f"start.estimator: the optimizer '{cfg.optimizer.kind}' with these settings takes no start points "
                "(cma does, as its init_design)"
            ]
        path = start_estimator_path(cfg)
        header, _ = checked_header(path)
        if header["model"] != cfg.ssm.kind:
            return [f"start.estimator: {path} is an estimator of {header['model']}, the fit's model is {cfg.ssm.kind}"]
        lacks = [k for k in cfg.ssm.free if k not in header["prior"]["names"]]
        if lacks:
            return [
                f"start.estimator: {path} has no posterior of the free parameter(s) {', '.join(lacks)} "
                f"(it has {', '.join(header['prior']['names'])})"
            ]
        estimator_component(header["estimator"]["kind"], header["estimator"]["settings"])
    except (ConfigError, PluginError) as exc:
        return [f"start.estimator: {exc}"]
    return []


def start_points(cfg, tree, names, lower, upper) -> np.ndarray:
    """``[start] draws`` points of the estimator's posterior for ``tree`` (seeded by the run seed),
    in the order of ``names``, moved into the fit's box ``[lower, upper]``."""
    te = read_estimator(start_estimator_path(cfg))
    res = tree_posterior(te, tree, int(cfg.start.draws), int(cfg.seed), source=str(cfg.target.qsm or "the target"))
    warn_lines(res["warnings"])
    cols = [te.names.index(k) for k in names]
    return np.clip(res["samples"][:, cols], np.asarray(lower, float), np.asarray(upper, float))


def write_amortised_recipe(qsm, out, estimator, model: str | None = None):
    """``bforest init --amortised``: the recipe of :func:`~.recipe.write_recipe` whose search
    starts from ``estimator``'s posterior for the tree (a file of ``bforest train``, or
    ``"shipped"``: the one shipped for ``model``). The model is the estimator's; a ``model``
    that differs is refused in one line."""
    path = named_estimator(estimator, model)
    header, _ = checked_header(path)
    if model is not None and model != header["model"]:
        raise ConfigError(f"--amortised {estimator}: an estimator of {header['model']}, not of --model {model}")
    start = estimator if estimator == SHIPPED else os.path.relpath(path.resolve(), Path(out).resolve().parent)
    # the estimator learnt the open world's parameters: no crown's space
    return write_recipe(
        qsm, out, header["model"], start=start, how="asked for" if model else "the estimator's", crown_space=False
    )
