"""Conformance kit: checks any Bayes Forest component against the contract of its interface.

A plugin author runs it in their own test suite::

    from bforest_core.testing import check_ssm

    def test_my_model_conforms():
        check_ssm(MyModel, params={"years": 5})      # raises ConformanceError on a failure

or, one pytest test per check (failures then show up individually)::

    import pytest
    from bforest_core.testing import ssm_checks

    @pytest.mark.parametrize("check", ssm_checks(MyModel, params={"years": 5}), ids=str)
    def test_my_model(check):
        check()

Every kind has a ``<kind>_checks(...)`` function returning a list of :class:`Check` objects and a
``check_<kind>(...)`` function running them and returning a :class:`Report` (raising a
:class:`ConformanceError` that lists every failed check, unless ``raise_on_failure=False``).
:func:`check_component` picks the right one from the component's ``kind``; :func:`run_all`
checks every registered component (optionally only those of one distribution).

What is checked
---------------
all components
    ``class``: ``kind``/``name``/``Settings`` well formed; ``settings``: the settings round-trip
    (``model_dump`` -> new instance -> equal, also through JSON) and unknown keys are rejected;
    ``pickle``: an instance survives pickling *and still gives the same results* (executors
    ship components to worker processes); ``registered`` (optional): the registry resolves
    ``(kind, name)`` to this class, from the expected distribution.
SSM
    ``parameters`` (unique identifier names, ``lower <= default <= upper``, integer flags with
    whole values), ``resolve_params`` (defaults, integer rounding, unknown names rejected),
    ``simulate`` (a valid :class:`~bforest_core.Tree` with metadata ``model``, ``params``,
    ``seed``, ``status``), ``determinism`` (same params and seed -> bit-identical arrays),
    ``seeds`` (different seeds give different trees; ``stochastic=False`` turns it off),
    ``bounds`` (every parameter at its bounds returns a valid tree or raises
    ``SimulationFailed`` -- never another exception).
features
    ``set_names``/``columns``, ``extract`` (2-D float64 tables with one column per name, no
    inf), ``determinism``, ``pooled``.
distance
    ``identical`` (zero for identical inputs), ``finite`` (finite, non-negative), ``separates``
    (positive for shifted tables), ``determinism``, ``empty`` (an empty model table gives a
    finite value or ``None``).
qsm_reader / qsm_writer / optimizer / executor
    see :func:`reader_checks`, :func:`writer_checks`, :func:`optimizer_checks`,
    :func:`executor_checks`.
"""
from __future__ import annotations

import json
import keyword
import math
import pickle
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Sequence

import numpy as np
import pydantic

from ..errors import SimulationFailed
from ..interfaces import (INTERFACES, KINDS, ComponentSettings, OptimizeResult, ParameterSpec, Problem)
from ..tree import Tree

__all__ = ["ConformanceError", "Check", "CheckResult", "Report", "check_tree", "sample_tree",
           "sample_trees", "sample_tables", "component_checks", "check_component", "ssm_checks",
           "check_ssm", "feature_set_checks", "check_feature_set", "distance_checks", "check_distance",
           "reader_checks", "check_reader", "writer_checks", "check_writer", "optimizer_checks",
           "check_optimizer", "executor_checks", "check_executor", "run_all"]

#: a settings key no component can have
UNKNOWN_KEY = "bforest_conformance_unknown_key"
TREE_ARRAYS = ("start", "axis", "length", "radius", "parent", "extension")
METADATA_KEYS = ("model", "params", "seed", "status")


# ==============================================================================================
# results
# ==============================================================================================

class ConformanceError(AssertionError):
    """A component failed one or more conformance checks.

    Attributes
    ----------
    component : str
        ``"<kind> '<name>'"`` of the component.
    failures : list of (str, str)
        ``(check, problem)`` of every failed check.
    """

    def __init__(self, component: str, failures: Sequence[tuple[str, str]]):
        self.component = component
        self.failures = list(failures)
        if len(self.failures) == 1:
            check, problem = self.failures[0]
            msg = f"{component}: check '{check}' failed: {problem}"
        else:
            lines = "\n".join(f"  - {c}: {p}" for c, p in self.failures)
            msg = f"{component}: {len(self.failures)} checks failed:\n{lines}"
        super().__init__(msg)

    @property
    def checks(self) -> list[str]:
        """Names of the failed checks."""
        return [c for c, _ in self.failures]


class _Fail(AssertionError):
    """A check's own failure (its message is the problem, without the component)."""


def _require(cond: bool, problem: str) -> None:
    if not cond:
        raise _Fail(problem)


@dataclass
class CheckResult:
    """Outcome of one :class:`Check`."""

    component: str
    check: str
    passed: bool
    problem: str = ""
    note: str = ""
    seconds: float = 0.0


@dataclass
class Check:
    """One named conformance check of one component; calling it runs it.

    Raises :class:`ConformanceError` (an ``AssertionError``) naming the component and the check
    when it fails; an unexpected exception inside the component counts as a failure too. The
    string form (``"ssm 'x': determinism"``) makes a readable pytest id.
    """

    component: str
    name: str
    fn: Callable[[], str | None] = field(repr=False)

    @property
    def id(self) -> str:
        return f"{self.component}: {self.name}"

    def __str__(self) -> str:
        return self.id

    def run(self) -> CheckResult:
        """Run without raising; the result says whether it passed."""
        t0 = time.perf_counter()
        try:
            note = self.fn() or ""
        except _Fail as exc:
            return CheckResult(self.component, self.name, False, str(exc), seconds=time.perf_counter() - t0)
        except Exception as exc:  # the component itself broke
            return CheckResult(self.component, self.name, False, f"raised {type(exc).__name__}: {exc}",
                               seconds=time.perf_counter() - t0)
        return CheckResult(self.component, self.name, True, note=note, seconds=time.perf_counter() - t0)

    def __call__(self) -> CheckResult:
        res = self.run()
        if not res.passed:
            raise ConformanceError(self.component, [(self.name, res.problem)])
        return res


@dataclass
class Report:
    """Results of running a list of checks on one component."""

    component: str
    results: list[CheckResult] = field(default_factory=list)
    skipped: str = ""

    @property
    def ok(self) -> bool:
        return all(r.passed for r in self.results)

    @property
    def failures(self) -> list[CheckResult]:
        return [r for r in self.results if not r.passed]

    @property
    def passed(self) -> list[str]:
        return [r.check for r in self.results if r.passed]

    def raise_for_failures(self) -> "Report":
        """Raise :class:`ConformanceError` listing every failed check (else return self)."""
        if self.failures:
            raise ConformanceError(self.component, [(r.check, r.problem) for r in self.failures])
        return self

    def __str__(self) -> str:
        if self.skipped:
            return f"{self.component}: skipped ({self.skipped})"
        lines = [f"{self.component}: {len(self.passed)}/{len(self.results)} checks passed"]
        for r in self.results:
            mark = "ok  " if r.passed else "FAIL"
            text = r.note if r.passed else r.problem
            lines.append(f"  {mark} {r.check}" + (f" -- {text}" if text else ""))
        return "\n".join(lines)


def _run(checks: Sequence[Check], label: str, raise_on_failure: bool) -> Report:
    rep = Report(label, [c.run() for c in checks])
    if raise_on_failure:
        rep.raise_for_failures()
    return rep


# ==============================================================================================
# helpers
# ==============================================================================================

def _instance(obj, kind: str, settings: Mapping[str, Any] | None):
    """``(cls, instance-or-None, settings-dict, error)`` of a class or an instance."""
    if isinstance(obj, type):
        cls = obj
        try:
            inst = cls(**dict(settings or {}))
        except Exception as exc:
            return cls, None, dict(settings or {}), f"{cls.__qualname__}(**{dict(settings or {})!r}) raised " \
                                                    f"{type(exc).__name__}: {exc}"
        return cls, inst, dict(settings or {}), ""
    if settings:
        raise TypeError("give settings only together with a component class, not an instance")
    return type(obj), obj, obj.settings.model_dump(), ""


def _label(cls, kind: str) -> str:
    name = getattr(cls, "name", None)
    return f"{kind} '{name}'" if isinstance(name, str) and name else f"{kind} {cls.__qualname__}"


def _first_diff(a: np.ndarray, b: np.ndarray) -> str:
    if a.shape != b.shape:
        return f"shapes {a.shape} and {b.shape}"
    if a.ndim == 0:
        return f"{a!r} vs {b!r}"
    eq = a == b
    if a.dtype.kind == "f":
        eq |= np.isnan(a) & np.isnan(b)
    neq = np.flatnonzero(~eq.reshape(a.shape[0], -1).all(axis=1))
    if neq.size == 0:
        return "equal"
    r = int(neq[0])
    return f"{neq.size} rows differ, first row {r}: {np.asarray(a[r]).tolist()} vs {np.asarray(b[r]).tolist()}"


def _tree_diff(t1: Tree, t2: Tree) -> str | None:
    """None when the trees have bit-identical arrays, else what differs."""
    if t1.n != t2.n:
        return f"{t1.n} vs {t2.n} cylinders"
    for k in TREE_ARRAYS:
        a, b = getattr(t1, k), getattr(t2, k)
        if not np.array_equal(a, b):
            return f"'{k}' differs ({_first_diff(a, b)})"
    return None


def _tables_diff(u1: Mapping[str, np.ndarray], u2: Mapping[str, np.ndarray]) -> str | None:
    if list(u1) != list(u2):
        return f"sets {list(u1)} vs {list(u2)}"
    for k in u1:
        a, b = np.asarray(u1[k]), np.asarray(u2[k])
        if a.shape != b.shape or not np.array_equal(a, b, equal_nan=True):
            return f"set '{k}' differs ({_first_diff(a, b)})"
    return None


def check_tree(tree, what: str = "tree") -> None:
    """Assert the invariants of a :class:`~bforest_core.Tree` a component returns.

    Parameters
    ----------
    tree : Tree
        The tree to check.
    what : str
        How to name it in messages.

    Raises
    ------
    AssertionError
        Naming the first violated invariant (type, shapes and dtypes, finite values,
        ``radius > 0``, ``length > 0``, unit axes, root at row 0, ``parent < child``, valid
        ``extension``, ``metadata`` a dict).
    """
    _require(isinstance(tree, Tree), f"{what} is a {type(tree).__name__}, not a bforest_core.Tree")
    n = tree.n
    _require(n >= 1, f"{what} has no cylinders")
    for k, shape in (("start", (n, 3)), ("axis", (n, 3)), ("length", (n,)), ("radius", (n,))):
        a = getattr(tree, k)
        _require(a.shape == shape and a.dtype == np.float64, f"{what}.{k} has shape {a.shape} and dtype "
                                                             f"{a.dtype}, expected {shape} float64")
        bad = np.flatnonzero(~np.isfinite(a).reshape(n, -1).all(axis=1))
        _require(bad.size == 0, f"{what}.{k} is not finite at rows {bad[:5].tolist()}")
    for k in ("parent", "extension"):
        a = getattr(tree, k)
        _require(a.shape == (n,) and a.dtype == np.int64, f"{what}.{k} has shape {a.shape} and dtype {a.dtype}, "
                                                          f"expected ({n},) int64")
    for k in ("radius", "length"):
        bad = np.flatnonzero(getattr(tree, k) <= 0)
        _require(bad.size == 0, f"{what}.{k} <= 0 at rows {bad[:5].tolist()}")
    nrm = np.linalg.norm(tree.axis, axis=1)
    bad = np.flatnonzero(np.abs(nrm - 1) > 1e-6)
    _require(bad.size == 0, f"{what}.axis is not unit at rows {bad[:5].tolist()}")
    p = tree.parent
    _require(p[0] == -1, f"{what}: row 0 is not the root (parent[0] = {p[0]})")
    rows = np.arange(1, n)
    bad = rows[(p[1:] < 0) | (p[1:] >= rows)]
    _require(bad.size == 0, f"{what}: parent is not in [0, row) at rows {bad[:5].tolist()} "
                            "(one root at row 0, parents before children)")
    e = tree.extension
    has = np.flatnonzero(e >= 0)
    _require(np.all(e >= -1) and np.all(e < n), f"{what}.extension out of range")
    bad = has[p[e[has]] != has]
    _require(bad.size == 0, f"{what}: the extension of rows {bad[:5].tolist()} is not one of their children")
    _require(isinstance(tree.metadata, dict), f"{what}.metadata is a {type(tree.metadata).__name__}, not a dict")


def _common_checks(cls, inst, settings, label, kind, registered, make_error="") -> list[Check]:
    """``class``, ``settings`` and (optionally) ``registered`` checks of any component."""

    def c_class():
        _require(getattr(cls, "kind", None) in KINDS, f"kind {getattr(cls, 'kind', None)!r} is not one of {KINDS}")
        _require(cls.kind == kind, f"kind is {cls.kind!r}, checked as {kind!r}")
        _require(issubclass(cls, INTERFACES[kind]), f"{cls.__qualname__} does not subclass "
                                                     f"bforest_core.{INTERFACES[kind].__name__}")
        name = getattr(cls, "name", None)
        _require(isinstance(name, str) and name != "", "class attribute 'name' is missing or empty")
        _require(name.strip() == name and not any(ch.isspace() or ch in "\"'[]=#" for ch in name),
                 f"name {name!r} has whitespace or TOML-special characters (it is typed in configs as kind = \"...\")")
        _require(isinstance(getattr(cls, "summary", ""), str), "summary is not a string")
        _require(isinstance(cls.Settings, type) and issubclass(cls.Settings, ComponentSettings),
                 "Settings is not a subclass of bforest_core.ComponentSettings")
        _require(not getattr(cls, "__abstractmethods__", None),
                 f"abstract methods not implemented: {', '.join(sorted(cls.__abstractmethods__))}")

    def c_settings():
        _require(inst is not None, make_error or "could not be instantiated")
        s = inst.settings
        _require(isinstance(s, cls.Settings), f"instance.settings is a {type(s).__name__}, not {cls.Settings.__name__}")
        dumped = s.model_dump()
        again = cls(**dumped).settings
        _require(again == s, f"settings do not round-trip: {dumped!r} -> {again.model_dump()!r}")
        js = json.loads(json.dumps(s.model_dump(mode="json")))
        again = cls(**js).settings
        _require(again == s, f"settings do not round-trip through JSON/TOML: {js!r} -> {again.model_dump()!r}")
        try:
            cls(**{**settings, UNKNOWN_KEY: 1})
        except pydantic.ValidationError as exc:
            _require(UNKNOWN_KEY in str(exc), f"the error for an unknown key does not name it: {exc}")
        else:
            raise _Fail(f"an unknown settings key ({UNKNOWN_KEY!r}) was accepted; Settings must forbid extra "
                        "keys (subclass bforest_core.ComponentSettings)")

    checks = [Check(label, "class", c_class), Check(label, "settings", c_settings)]
    if registered:
        def c_registered():
            from ..registry import discover
            reg = discover()
            entry = reg.components.get((kind, cls.name))
            _require(entry is not None, f"not registered: bf.discover() has no {kind} {cls.name!r} "
                     f"(known: {', '.join(reg.names(kind)) or 'none'}; plugin load errors: "
                     f"{[e.error for e in reg.errors] or 'none'})")
            _require(entry.cls is cls, f"the registry resolves {kind} {cls.name!r} to {entry.cls.__module__}."
                                       f"{entry.cls.__qualname__}, not to {cls.__module__}.{cls.__qualname__}")
            if isinstance(registered, str):
                _require(entry.distribution == registered, f"registered by distribution {entry.distribution!r}, "
                                                           f"expected {registered!r}")
            from ..registry import component
            component(kind, cls.name, **settings)
            return f"from {entry.distribution} {entry.version} (entry point {entry.plugin!r})"
        checks.append(Check(label, "registered", c_registered))
    return checks


def _need(inst, make_error):
    _require(inst is not None, make_error or "could not be instantiated")
    return inst


def _roundtrip(inst):
    try:
        data = pickle.dumps(inst)
    except Exception as exc:
        raise _Fail(f"the instance cannot be pickled ({type(exc).__name__}: {exc}); executors send components "
                    "to worker processes, so keep only picklable state (no lambdas, locks, open files)") from None
    try:
        other = pickle.loads(data)
    except Exception as exc:
        raise _Fail(f"the pickled instance cannot be unpickled ({type(exc).__name__}: {exc})") from None
    _require(type(other) is type(inst), f"unpickled as {type(other).__name__}")
    _require(other.settings == inst.settings, "settings changed through pickling")
    return other


# ==============================================================================================
# sample inputs
# ==============================================================================================

def _branches(parent_rows, starts, dirs, ncyl, clen, rad, offset):
    """Rows of straight branches (vectorised): branch b has ``ncyl[b]`` cylinders of ``clen[b]``."""
    ncyl = np.asarray(ncyl, np.int64)
    bi = np.repeat(np.arange(ncyl.size), ncyl)
    pos = np.arange(bi.size) - np.repeat(np.cumsum(ncyl) - ncyl, ncyl)
    rows = offset + np.arange(bi.size)
    start = starts[bi] + (pos * clen[bi])[:, None] * dirs[bi]
    parent = np.where(pos == 0, parent_rows[bi], rows - 1)
    ext = np.where(pos < ncyl[bi] - 1, rows + 1, -1)
    radius = rad[bi] * (1.0 - 0.4 * pos / ncyl[bi])
    return start, dirs[bi], np.asarray(clen)[bi], radius, parent, ext


def _directions(rng, up, beta_deg, n):
    """Unit vectors at ``beta`` degrees from the rows of ``up``, random azimuth."""
    ref = np.where(np.abs(up[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
    u = np.cross(up, ref)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    w = np.cross(up, u)
    b = np.radians(beta_deg)[:, None]
    az = rng.uniform(0, 2 * np.pi, n)[:, None]
    d = np.cos(b) * up + np.sin(b) * (np.cos(az) * u + np.sin(az) * w)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def sample_tree(seed: int = 0, trunk: int = 16, laterals: int = 2) -> Tree:
    """A small synthetic tree (orders 0-2, a few hundred cylinders) to feed feature sets and
    writers; deterministic in ``seed``.

    Parameters
    ----------
    seed : int
        Seeds the branching angles, lengths and which sub-laterals exist.
    trunk : int
        Trunk cylinders (0.5 m each).
    laterals : int
        First-order branches per trunk node (from the third node up).

    Returns
    -------
    Tree
        With ``source`` topology and metadata ``{"model": "conformance-sample", "seed": seed}``.
    """
    rng = np.random.default_rng(seed)
    parts = [_branches(np.array([-1]), np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]), [trunk],
                       np.array([0.5]), np.array([0.15]), 0)]
    n = trunk
    # first order: `laterals` branches on trunk cylinders 2..trunk-1 (at their start)
    host = np.repeat(np.arange(2, trunk), laterals)
    k = host.size
    up = np.tile([0.0, 0.0, 1.0], (k, 1))
    d1 = _directions(rng, up, rng.uniform(40, 75, k), k)
    nc1 = rng.integers(3, 6, k)
    parts.append(_branches(host, parts[0][0][host], d1, nc1, rng.uniform(0.25, 0.45, k),
                           np.full(k, 0.04), n))
    s1, a1, l1 = parts[1][0], parts[1][1], parts[1][2]
    rows1 = n + np.arange(s1.shape[0])
    n += s1.shape[0]
    # second order: on 70 % of the first-order cylinders, at their end
    sel = rows1[rng.random(rows1.size) < 0.7]
    loc = sel - rows1[0]
    m = sel.size
    d2 = _directions(rng, a1[loc], rng.uniform(30, 70, m), m)
    parts.append(_branches(sel, s1[loc] + l1[loc, None] * a1[loc], d2, rng.integers(1, 4, m),
                           rng.uniform(0.1, 0.25, m), np.full(m, 0.012), n))
    start, axis, length, radius, parent, ext = (np.concatenate(c) for c in zip(*parts))
    return Tree(start, axis, length, radius, parent, ext,
                metadata={"model": "conformance-sample", "seed": seed})


def sample_trees(n: int = 2) -> list[Tree]:
    """``n`` sample trees (seeds 0..n-1) of :func:`sample_tree`."""
    return [sample_tree(s) for s in range(n)]


def sample_tables(dims: Sequence[int] = (2, 4), seed: int = 0, shift: float = 1.0):
    """Data and model tables to feed a distance: ``(U_data, U_model, columns)``.

    Set ``"T{d}"`` has ``d`` columns; the data side is standard normal (200 rows), the model
    side (150 rows) is shifted by ``shift`` in every column.
    """
    rng = np.random.default_rng(seed)
    U_data, U_model, cols = {}, {}, {}
    for d in dims:
        U_data[f"T{d}"] = rng.standard_normal((200, d))
        U_model[f"T{d}"] = rng.standard_normal((150, d)) + shift
        cols[f"T{d}"] = [f"c{i}" for i in range(d)]
    return U_data, U_model, cols


# ==============================================================================================
# SSM
# ==============================================================================================

def ssm_checks(ssm, params: Mapping[str, float] | None = None, seeds: Sequence[int] = (1, 2), *,
               settings: Mapping[str, Any] | None = None, stochastic: bool = True,
               bounds: str | bool = "each", hold: Iterable[str] | None = None,
               registered: bool | str = False) -> list[Check]:
    """The conformance checks of a growth model.

    Parameters
    ----------
    ssm : SSM subclass or instance
        The model (a class is instantiated with ``settings``).
    params : mapping, optional
        Parameter values used for the simulations (small, fast values: e.g. few years);
        missing names take their defaults.
    seeds : sequence of int
        At least two different seeds; the first is used for determinism and pickling.
    settings : mapping, optional
        Component settings (only with a class).
    stochastic : bool
        The model's output depends on the seed: different seeds must give different trees.
    bounds : {"each", "corners", "none"} or bool
        ``"each"``: every parameter at its lower and at its upper bound in turn (the others at
        ``params``/defaults) plus all at once; ``"corners"``: only all-lower and all-upper;
        ``"none"``/``False``: skip. Each run must return a valid tree or raise
        ``SimulationFailed``.
    hold : iterable of str, optional
        Parameters kept at their ``params`` value in the bounds check (default: the names given
        in ``params``, so a cheap setting such as ``years = 5`` is not pushed to its upper
        bound).
    registered : bool or str
        Also check the registry resolves the model's name to this class (a string: and that it
        comes from that distribution).

    Returns
    -------
    list of Check
    """
    cls, inst, settings, err = _instance(ssm, "ssm", settings)
    label = _label(cls, "ssm")
    params = dict(params or {})
    seeds = list(seeds)
    if len(seeds) < 2 or len(set(seeds)) < 2:
        raise ValueError("ssm_checks needs at least two different seeds")
    hold = set(params) if hold is None else set(hold)
    if bounds is True:
        bounds = "each"
    if bounds not in ("each", "corners", "none", False, None):
        raise ValueError(f"bounds must be 'each', 'corners' or 'none' (got {bounds!r})")
    cache: dict[str, Any] = {}

    def sim(p=None, seed=None, model=None):
        model = model or _need(inst, err)
        p = params if p is None else p
        seed = seeds[0] if seed is None else seed
        try:
            return model.simulate(dict(p), seed)
        except SimulationFailed as exc:
            raise _Fail(f"simulate({p!r}, seed={seed}) raised SimulationFailed ({exc.status}): {exc}; choose "
                        "params for which the model succeeds") from None

    def first_tree():
        if "tree" not in cache:
            given = dict(params)
            try:
                cache["tree"] = _need(inst, err).simulate(given, seeds[0])
            except SimulationFailed as exc:
                raise _Fail(f"simulate({params!r}, seed={seeds[0]}) raised SimulationFailed ({exc.status}): {exc}; "
                            "choose params for which the model succeeds") from None
            cache["mutated"] = given if given != params else None
        return cache["tree"]

    def c_parameters():
        m = _need(inst, err)
        specs = m.parameters
        _require(isinstance(specs, (list, tuple)) and len(specs) > 0, "parameters is empty or not a list")
        problems = []
        names = []
        for i, s in enumerate(specs):
            if not isinstance(s, ParameterSpec):
                problems.append(f"item {i} is a {type(s).__name__}, not a ParameterSpec")
                continue
            names.append(s.name)
            if not (isinstance(s.name, str) and s.name.isidentifier() and not keyword.iskeyword(s.name)):
                problems.append(f"name {s.name!r} is not a Python identifier (it is a TOML key and a column name)")
            vals = {"default": s.default, "lower": s.lower, "upper": s.upper}
            if not all(isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool)
                       and math.isfinite(v) for v in vals.values()):
                problems.append(f"{s.name}: default/lower/upper must be finite numbers (got {vals})")
                continue
            if not s.lower <= s.upper:
                problems.append(f"{s.name}: lower {s.lower} is above upper {s.upper}")
            if not s.lower <= s.default <= s.upper:
                problems.append(f"{s.name}: default {s.default} is outside [{s.lower}, {s.upper}]")
            if s.integer and not all(float(v).is_integer() for v in vals.values()):
                problems.append(f"{s.name}: integer parameter with non-integer default/lower/upper {vals}")
            if not isinstance(s.unit, str) or not isinstance(s.description, str):
                problems.append(f"{s.name}: unit and description must be strings")
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            problems.append(f"duplicate parameter names: {', '.join(map(str, dup))}")
        _require(not problems, "; ".join(problems))
        again = [s.name for s in m.parameters]
        _require(again == names, "parameters changes between calls")
        return f"{len(names)} parameters"

    def c_resolve():
        m = _need(inst, err)
        specs = m.parameters
        bogus = "bforest_conformance_no_such_parameter"
        try:
            m.resolve_params({bogus: 1.0})
        except ValueError as exc:
            _require(bogus in str(exc), f"resolve_params raised ValueError for an unknown name without naming it: {exc}")
        else:
            raise _Fail(f"resolve_params accepted an unknown parameter name ({bogus!r}); it must raise ValueError")
        d = m.resolve_params({})
        _require(set(d) == {s.name for s in specs}, f"resolve_params({{}}) gives names {sorted(d)}, "
                                                    f"not the parameters {sorted(s.name for s in specs)}")
        for s in specs:
            if s.integer:
                _require(isinstance(d[s.name], (int, np.integer)) and d[s.name] == s.default,
                         f"resolve_params({{}})[{s.name!r}] is {d[s.name]!r}, expected the integer default {s.default}")
            else:
                _require(d[s.name] == s.default, f"resolve_params({{}})[{s.name!r}] is {d[s.name]!r}, "
                                                 f"expected the default {s.default}")
        ints = [s for s in specs if s.integer and s.upper > s.lower]
        if ints:
            s = ints[0]
            v = m.resolve_params({s.name: s.lower + 0.6})[s.name]
            _require(v == s.lower + 1 and isinstance(v, (int, np.integer)),
                     f"resolve_params({{{s.name!r}: {s.lower + 0.6}}}) gives {v!r}; integer parameters are rounded")

    def c_unknown():
        bogus = "bforest_conformance_no_such_parameter"
        try:
            _need(inst, err).simulate({**params, bogus: 1.0}, seeds[0])
        except ValueError as exc:
            _require(bogus in str(exc), f"simulate raised ValueError for an unknown parameter without naming it: {exc}")
        except SimulationFailed as exc:
            raise _Fail(f"simulate with an unknown parameter raised SimulationFailed ({exc.status}), not ValueError") \
                from None
        else:
            raise _Fail(f"simulate accepted an unknown parameter ({bogus!r}); unknown names must raise ValueError "
                        "(use self.resolve_params)")

    def c_simulate():
        t = first_tree()
        changed = cache.get("mutated")
        if changed is not None:
            raise _Fail(f"simulate changed the params mapping it was given ({params!r} -> {changed!r})")
        check_tree(t, "the simulated tree")
        md = t.metadata
        missing = [k for k in METADATA_KEYS if k not in md]
        _require(not missing, f"tree.metadata lacks {', '.join(missing)} (needs {', '.join(METADATA_KEYS)})")
        _require(md["model"] == cls.name, f"metadata['model'] is {md['model']!r}, expected the name {cls.name!r}")
        _require(md["seed"] == seeds[0], f"metadata['seed'] is {md['seed']!r}, expected {seeds[0]}")
        _require(md["status"] == "ok", f"metadata['status'] is {md['status']!r} for a successful run, expected 'ok'")
        _require(isinstance(md["params"], Mapping), "metadata['params'] is not a mapping")
        known = {s.name for s in inst.parameters}
        _require(set(md["params"]) <= known | set(params) and set(params) <= set(md["params"]),
                 f"metadata['params'] ({sorted(md['params'])}) should hold the resolved parameters")
        for k, v in params.items():
            spec = inst.parameter_spec(k)
            want = int(round(v)) if spec.integer else v
            _require(md["params"][k] == want, f"metadata['params'][{k!r}] is {md['params'][k]!r}, the run used {want!r}")
        return f"{t.n} cylinders, max order {t.max_order}"

    def c_determinism():
        t1 = first_tree()
        t2 = sim()
        d = _tree_diff(t1, t2)
        _require(d is None, f"the same params and seed {seeds[0]} gave different trees: {d}; draw every random "
                            "number from one numpy Generator seeded with `seed`")
        if isinstance(ssm, type):
            fresh = cls(**settings)
            d = _tree_diff(t1, sim(model=fresh))
            _require(d is None, f"a second instance gave a different tree for the same params and seed: {d} "
                                "(state leaks between runs?)")
        # interleaving another seed must not change the result (no hidden state)
        sim(seed=seeds[1])
        d = _tree_diff(t1, sim())
        _require(d is None, f"simulating seed {seeds[1]} in between changed the tree of seed {seeds[0]}: {d}")

    def c_seeds():
        trees = [first_tree()] + [sim(seed=s) for s in seeds[1:]]
        same = [s for s, t in zip(seeds[1:], trees[1:]) if _tree_diff(trees[0], t) is None]
        if same:
            raise _Fail(f"seeds {seeds[0]} and {same[0]} gave identical trees; the model ignores its seed "
                        "(pass stochastic=False for a deterministic model)")

    def c_pickle():
        other = _roundtrip(_need(inst, err))
        d = _tree_diff(first_tree(), sim(model=other))
        _require(d is None, f"the unpickled instance grows a different tree: {d}")
        t = first_tree()
        t2 = pickle.loads(pickle.dumps(t))
        d = _tree_diff(t, t2)
        _require(d is None, f"the returned tree does not survive pickling: {d}")

    def c_bounds():
        m = _need(inst, err)
        specs = [s for s in m.parameters if s.name not in hold]
        cases = [("all at lower bounds", {s.name: s.lower for s in specs}),
                 ("all at upper bounds", {s.name: s.upper for s in specs})]
        if bounds == "each":
            for s in specs:
                if s.upper > s.lower:
                    cases += [(f"{s.name} = {s.lower:g} (lower)", {s.name: s.lower}),
                              (f"{s.name} = {s.upper:g} (upper)", {s.name: s.upper})]
        errors, failed = [], []
        for what, over in cases:
            p = {**params, **over}
            try:
                t = m.simulate(p, seeds[0])
            except SimulationFailed as exc:
                if not (isinstance(exc.status, str) and exc.status):
                    errors.append(f"{what}: SimulationFailed without a status string")
                failed.append(f"{what}: {exc.status}")
                continue
            except Exception as exc:
                errors.append(f"{what}: {type(exc).__name__}: {exc}")
                continue
            try:
                check_tree(t, "tree")
                _require(t.metadata.get("status") == "ok", f"status {t.metadata.get('status')!r} without SimulationFailed")
            except _Fail as exc:
                errors.append(f"{what}: {exc}")
        shown = "; ".join(errors[:6]) + (f"; ... ({len(errors)} cases)" if len(errors) > 6 else "")
        _require(not errors, f"parameters at their bounds must give a valid tree or raise SimulationFailed: {shown}")
        note = f"{len(cases)} bound settings"
        if failed:
            note += f", {len(failed)} raised SimulationFailed ({'; '.join(failed[:4])}{' ...' if len(failed) > 4 else ''})"
        return note

    checks = _common_checks(cls, inst, settings, label, "ssm", registered, err)
    checks += [Check(label, "parameters", c_parameters), Check(label, "resolve_params", c_resolve),
               Check(label, "unknown_params", c_unknown), Check(label, "simulate", c_simulate),
               Check(label, "determinism", c_determinism)]
    if stochastic:
        checks.append(Check(label, "seeds", c_seeds))
    checks.append(Check(label, "pickle", c_pickle))
    if bounds not in ("none", False, None):
        checks.append(Check(label, "bounds", c_bounds))
    return checks


def check_ssm(ssm, params=None, seeds=(1, 2), *, raise_on_failure: bool = True, **options) -> Report:
    """Run :func:`ssm_checks` and return the :class:`Report`.

    Raises
    ------
    ConformanceError
        Listing every failed check (unless ``raise_on_failure=False``).

    Examples
    --------
    >>> from bforest_core.testing import check_ssm
    >>> check_ssm(MyModel, params={"years": 5}, bounds="corners")   # doctest: +SKIP
    """
    checks = ssm_checks(ssm, params, seeds, **options)
    return _run(checks, checks[0].component, raise_on_failure)


# ==============================================================================================
# features
# ==============================================================================================

def feature_set_checks(features, trees: Sequence[Tree] | None = None, *, settings=None,
                       allow_nan: bool = False, registered: bool | str = False) -> list[Check]:
    """The conformance checks of a feature set.

    Parameters
    ----------
    features : FeatureSet subclass or instance
    trees : sequence of Tree, optional
        Data trees for ``prepare`` and ``extract`` (default :func:`sample_trees`).
    settings : mapping, optional
        Component settings (only with a class).
    allow_nan : bool
        Tables may hold NaN (only for a ``nan_policy`` that keeps them); inf is never allowed.
    registered : bool or str
        See :func:`ssm_checks`.
    """
    cls, inst, settings, err = _instance(features, "features", settings)
    label = _label(cls, "features")
    trees = list(trees) if trees is not None else sample_trees()
    cache: dict[str, Any] = {}

    def prepared():
        if "fs" not in cache:
            fs = _need(inst, err)
            fs.prepare(trees)
            cache["fs"] = fs
        return cache["fs"]

    def c_names():
        fs = prepared()
        names = fs.set_names
        _require(isinstance(names, list) and len(names) > 0, f"set_names is {names!r}, expected a non-empty list")
        _require(all(isinstance(n, str) and n for n in names), f"set names must be non-empty strings: {names!r}")
        _require(len(set(names)) == len(names), f"duplicate set names: {names!r}")
        for n in names:
            cols = fs.columns(n)
            _require(isinstance(cols, list) and len(cols) > 0 and all(isinstance(c, str) and c for c in cols),
                     f"columns({n!r}) is {cols!r}, expected a non-empty list of strings")
            _require(len(set(cols)) == len(cols), f"columns({n!r}) has duplicates: {cols!r}")
        return ", ".join(f"{n} ({len(fs.columns(n))} columns)" for n in names)

    def c_extract():
        fs = prepared()
        rows = {}
        for i, t in enumerate(trees):
            U = fs.extract(t)
            _require(isinstance(U, dict), f"extract returned a {type(U).__name__}, not a dict")
            _require(list(U) == list(fs.set_names), f"extract gave sets {list(U)}, set_names is {fs.set_names}")
            for k, a in U.items():
                cols = fs.columns(k)
                _require(isinstance(a, np.ndarray), f"set {k!r} is a {type(a).__name__}, not a numpy array")
                _require(a.ndim == 2, f"set {k!r} has shape {a.shape}; tables are 2-D (rows, columns)")
                _require(a.dtype == np.float64, f"set {k!r} has dtype {a.dtype}, expected float64")
                _require(a.shape[1] == len(cols), f"set {k!r} has {a.shape[1]} columns but columns({k!r}) names "
                                                  f"{len(cols)}: {cols}")
                _require(not np.isinf(a).any(), f"set {k!r} of tree {i} holds inf values")
                if not allow_nan:
                    bad = np.flatnonzero(np.isnan(a).any(axis=1))
                    _require(bad.size == 0, f"set {k!r} of tree {i} holds NaN in rows {bad[:5].tolist()}")
                rows[k] = rows.get(k, 0) + a.shape[0]
        return ", ".join(f"{k}: {v} rows" for k, v in rows.items())

    def c_determinism():
        fs = prepared()
        d = _tables_diff(fs.extract(trees[0]), fs.extract(trees[0]))
        _require(d is None, f"extracting the same tree twice differs: {d}")

    def c_pooled():
        fs = prepared()
        pooled = fs.extract_pooled(trees)
        _require(list(pooled) == list(fs.set_names), f"extract_pooled gave sets {list(pooled)}")
        for k in fs.set_names:
            n = sum(fs.extract(t)[k].shape[0] for t in trees)
            _require(pooled[k].shape[0] == n, f"extract_pooled set {k!r} has {pooled[k].shape[0]} rows, the trees "
                                              f"have {n} together")

    def c_pickle():
        fs = prepared()
        other = _roundtrip(fs)
        d = _tables_diff(fs.extract(trees[0]), other.extract(trees[0]))
        _require(d is None, f"the unpickled (prepared) feature set extracts different tables: {d}")

    return _common_checks(cls, inst, settings, label, "features", registered, err) + [
        Check(label, "set_names", c_names), Check(label, "extract", c_extract),
        Check(label, "determinism", c_determinism), Check(label, "pooled", c_pooled),
        Check(label, "pickle", c_pickle)]


def check_feature_set(features, trees=None, *, raise_on_failure: bool = True, **options) -> Report:
    """Run :func:`feature_set_checks`; raises :class:`ConformanceError` on failures."""
    checks = feature_set_checks(features, trees, **options)
    return _run(checks, checks[0].component, raise_on_failure)


# ==============================================================================================
# distance
# ==============================================================================================

def distance_checks(distance, tables=None, *, settings=None, atol: float = 1e-9, separates: bool = True,
                    empty: bool = True, registered: bool | str = False) -> list[Check]:
    """The conformance checks of a distance.

    Parameters
    ----------
    distance : Distance subclass or instance
    tables : (U_data, U_model, columns), optional
        Named data and model tables (default :func:`sample_tables`: model shifted by 1).
    atol : float
        Tolerance of "zero for identical inputs".
    separates : bool
        The distance of the (different) data and model tables must be positive.
    empty : bool
        Check that an empty model table gives a finite value or ``None`` (never an exception).
    """
    cls, inst, settings, err = _instance(distance, "distance", settings)
    label = _label(cls, "distance")
    U_data, U_model, cols = tables if tables is not None else sample_tables()
    cache: dict[str, Any] = {}

    def prepared():
        if "d" not in cache:
            d = _need(inst, err)
            d.prepare(U_data, cols)
            cache["d"] = d
        return cache["d"]

    def values(d, U):
        per = d.compute_per_set(U, U_data)
        _require(isinstance(per, dict) and set(per) == set(U_data),
                 f"compute_per_set returned {per!r}, expected a dict with the sets {sorted(U_data)}")
        for k, v in per.items():
            _require(v is None or (isinstance(v, (float, int, np.floating)) and math.isfinite(v) and v >= 0),
                     f"set {k!r}: distance {v!r} is not a finite non-negative number")
        return per

    def c_identical():
        d = prepared()
        per = values(d, U_data)
        bad = {k: v for k, v in per.items() if v is None or abs(v) > atol}
        _require(not bad, f"identical model and data tables give non-zero distances {bad} (atol {atol})")
        for k in U_data:
            v = d.compute(U_data[k], U_data[k])
            _require(abs(v) <= atol, f"compute(u, u) of set {k!r} is {v!r}, expected 0")

    def c_finite():
        per = values(prepared(), U_model)
        tot = prepared().combine(per)
        _require(math.isfinite(tot) and tot >= 0, f"combined distance {tot!r} is not finite and non-negative")
        return ", ".join(f"{k}={v:.4g}" for k, v in per.items() if v is not None)

    def c_separates():
        per = values(prepared(), U_model)
        zero = [k for k, v in per.items() if v is None or v <= 0]
        _require(not zero, f"tables shifted by 1 in every column give distance 0 (or None) for sets {zero} "
                           "(pass separates=False if that is intended)")

    def c_determinism():
        d = prepared()
        a, b = values(d, U_model), values(d, U_model)
        _require(a == b, f"the same tables gave different distances: {a} vs {b}")

    def c_empty():
        d = prepared()
        U = {k: np.empty((0, v.shape[1])) for k, v in U_model.items()}
        per = values(d, U)
        return f"empty model tables -> {per}"

    def c_pickle():
        d = prepared()
        other = _roundtrip(d)
        a, b = values(d, U_model), values(other, U_model)
        _require(a == b, f"the unpickled (prepared) distance gives {b}, the original {a}")

    checks = _common_checks(cls, inst, settings, label, "distance", registered, err) + [
        Check(label, "identical", c_identical), Check(label, "finite", c_finite)]
    if separates:
        checks.append(Check(label, "separates", c_separates))
    checks.append(Check(label, "determinism", c_determinism))
    if empty:
        checks.append(Check(label, "empty", c_empty))
    checks.append(Check(label, "pickle", c_pickle))
    return checks


def check_distance(distance, tables=None, *, raise_on_failure: bool = True, **options) -> Report:
    """Run :func:`distance_checks`; raises :class:`ConformanceError` on failures."""
    checks = distance_checks(distance, tables, **options)
    return _run(checks, checks[0].component, raise_on_failure)


# ==============================================================================================
# readers and writers
# ==============================================================================================

def reader_checks(reader, paths: Sequence[str | Path], *, settings=None, foreign: Sequence[str | Path] = (),
                  options: Mapping[str, Any] | None = None, registered: bool | str = False) -> list[Check]:
    """The conformance checks of a QSM reader.

    Parameters
    ----------
    reader : QSMReader subclass or instance
    paths : sequence of path
        Sample files in the reader's layout (each must be recognised and read).
    foreign : sequence of path
        Files in other layouts that ``sniff`` must reject.
    options : mapping, optional
        Keyword options passed to ``read``.
    """
    cls, inst, settings, err = _instance(reader, "qsm_reader", settings)
    label = _label(cls, "qsm_reader")
    paths = [Path(p) for p in paths]
    options = dict(options or {})

    def head(p):
        with open(p, "rb") as f:
            return f.read(4096)

    def trees_of(r, p):
        out = r.read(p, **options)
        lst = out if isinstance(out, (list, tuple)) else [out]
        _require(len(lst) > 0, f"read({p.name}) returned no trees")
        for i, t in enumerate(lst):
            check_tree(t, f"tree {i} of {p.name}")
        return lst

    def c_suffixes():
        s = cls.suffixes
        _require(isinstance(s, tuple) and len(s) > 0, f"suffixes is {s!r}, expected a non-empty tuple")
        _require(all(isinstance(x, str) and x.startswith(".") and x == x.lower() for x in s),
                 f"suffixes must be lower-case strings with the dot: {s!r}")
        bad = [p.name for p in paths if p.suffix.lower() not in s]
        _require(not bad, f"sample files {bad} have suffixes outside {s}")

    def c_sniff():
        r = _need(inst, err)
        for p in paths:
            _require(r.sniff(p, head(p)) is True, f"sniff does not recognise its own sample {p.name}")
        for p in map(Path, foreign):
            _require(not r.sniff(p, head(p)), f"sniff claims the foreign file {p.name}")

    def c_read():
        r = _need(inst, err)
        n = [len(trees_of(r, p)) for p in paths]
        return f"{sum(n)} trees from {len(paths)} files"

    def c_determinism():
        r = _need(inst, err)
        for p in paths:
            a, b = trees_of(r, p), trees_of(r, p)
            for x, y in zip(a, b):
                d = _tree_diff(x, y)
                _require(d is None, f"reading {p.name} twice gave different trees: {d}")

    def c_pickle():
        r = _need(inst, err)
        other = _roundtrip(r)
        for x, y in zip(trees_of(r, paths[0]), trees_of(other, paths[0])):
            d = _tree_diff(x, y)
            _require(d is None, f"the unpickled reader reads {paths[0].name} differently: {d}")

    if not paths:
        raise ValueError("reader_checks needs at least one sample file in `paths`")
    return _common_checks(cls, inst, settings, label, "qsm_reader", registered, err) + [
        Check(label, "suffixes", c_suffixes), Check(label, "sniff", c_sniff), Check(label, "read", c_read),
        Check(label, "determinism", c_determinism), Check(label, "pickle", c_pickle)]


def check_reader(reader, paths, *, raise_on_failure: bool = True, **options) -> Report:
    """Run :func:`reader_checks`; raises :class:`ConformanceError` on failures."""
    checks = reader_checks(reader, paths, **options)
    return _run(checks, checks[0].component, raise_on_failure)


def writer_checks(writer, out_dir: str | Path, tree: Tree | None = None, *, settings=None,
                  roundtrip: bool = False, atol: float = 1e-6, registered: bool | str = False) -> list[Check]:
    """The conformance checks of a QSM writer.

    Parameters
    ----------
    writer : QSMWriter subclass or instance
    out_dir : path
        A writable (temporary) folder.
    tree : Tree, optional
        The tree to write (default :func:`sample_tree`).
    roundtrip : bool
        Read the written file back with :func:`bforest_core.read_qsm` and compare (geometry
        within ``atol``, same parent links).
    """
    cls, inst, settings, err = _instance(writer, "qsm_writer", settings)
    label = _label(cls, "qsm_writer")
    tree = tree if tree is not None else sample_tree()
    out_dir = Path(out_dir)

    def c_write():
        w = _need(inst, err)
        _require(isinstance(cls.suffixes, tuple) and cls.suffixes, f"suffixes is {cls.suffixes!r}")
        path = out_dir / f"conformance_{cls.name}{cls.suffixes[0]}"
        out = w.write(tree, path)
        _require(out is not None and Path(out).exists() and Path(out).stat().st_size > 0,
                 f"write returned {out!r}, which is not a non-empty file")
        if roundtrip:
            from ..io import read_qsm
            back = read_qsm(out)
            back = back[0] if isinstance(back, (list, tuple)) else back
            _require(back.n == tree.n, f"read back {back.n} cylinders of {tree.n}")
            _require(np.array_equal(back.parent, tree.parent), "parent links changed through write + read")
            for k in ("start", "axis", "length", "radius"):
                diff = float(np.max(np.abs(getattr(back, k) - getattr(tree, k))))
                _require(diff <= atol, f"'{k}' changed by up to {diff:g} through write + read (atol {atol})")
        return f"wrote {Path(out).name} ({Path(out).stat().st_size} bytes)"

    def c_pickle():
        _roundtrip(_need(inst, err))

    return _common_checks(cls, inst, settings, label, "qsm_writer", registered, err) + [
        Check(label, "write", c_write), Check(label, "pickle", c_pickle)]


def check_writer(writer, out_dir, tree=None, *, raise_on_failure: bool = True, **options) -> Report:
    """Run :func:`writer_checks`; raises :class:`ConformanceError` on failures."""
    checks = writer_checks(writer, out_dir, tree, **options)
    return _run(checks, checks[0].component, raise_on_failure)


# ==============================================================================================
# optimizer
# ==============================================================================================

class _Harness:
    """A Problem over a shifted quadratic bowl whose ``evaluate`` behaves like the fit's:
    rounds integer parameters, stops at the budget, tracks the best point and later calls."""

    lower = np.array([-2.0, -2.0, 0.0])
    upper = np.array([3.0, 3.0, 10.0])
    integer = np.array([False, False, True])
    optimum = np.array([1.0, -0.5, 4.0])

    def __init__(self, seed: int, budget: int):
        self.points: list[np.ndarray] = []
        self.calls_after_stop = 0
        self.problem = Problem(names=["x", "y", "k"], lower=self.lower.copy(), upper=self.upper.copy(),
                               integer=self.integer.copy(), evaluate=self.evaluate, seed=seed, budget=budget)

    def f(self, x):
        return float(np.sum(((x - self.optimum) / (self.upper - self.lower)) ** 2))

    def evaluate(self, X):
        pr = self.problem
        X = np.atleast_2d(np.asarray(X, dtype=float))
        if X.ndim != 2 or X.shape[1] != pr.dim:
            raise _Fail(f"evaluate was called with an array of shape {X.shape}, expected (k, {pr.dim})")
        if pr.stopped:
            self.calls_after_stop += 1
        X = np.clip(X, pr.lower, pr.upper)
        X[:, pr.integer] = np.round(X[:, pr.integer])
        out = np.full(X.shape[0], np.inf)
        for r, x in enumerate(X):
            if pr.stopped or pr.n_evaluations >= pr.budget:
                pr.stopped, pr.stop_reason = True, f"evaluation budget ({pr.budget}) reached"
                continue
            out[r] = self.f(x)
            self.points.append(x.copy())
            pr.n_evaluations += 1
            if out[r] < pr.best_f:
                pr.best_f, pr.best_x = out[r], x.copy()
        if pr.n_evaluations >= pr.budget:
            pr.stopped, pr.stop_reason = True, f"evaluation budget ({pr.budget}) reached"
        return out


def optimizer_checks(optimizer, *, settings=None, budget: int = 60, seed: int = 3,
                     registered: bool | str = False) -> list[Check]:
    """The conformance checks of an optimiser, on a 3-parameter bowl (one integer parameter).

    ``minimize`` must return an :class:`OptimizeResult` inside the bounds, never exceed the
    evaluation budget, return promptly once the problem has stopped (at most one more
    ``evaluate`` call), find a point better than the median of what it evaluated, and repeat
    exactly the same evaluations for the same seed.
    """
    cls, inst, settings, err = _instance(optimizer, "optimizer", settings)
    label = _label(cls, "optimizer")
    cache: dict[str, Any] = {}

    def run(opt=None):
        h = _Harness(seed, budget)
        res = (opt or _need(inst, err)).minimize(h.problem)
        return h, res

    def first():
        if "run" not in cache:
            cache["run"] = run()
        return cache["run"]

    def c_minimize():
        h, res = first()
        pr = h.problem
        _require(isinstance(res, OptimizeResult), f"minimize returned a {type(res).__name__}, not an OptimizeResult")
        _require(len(h.points) > 0, "minimize evaluated nothing")
        _require(pr.n_evaluations <= budget, f"{pr.n_evaluations} evaluations for a budget of {budget}")
        _require(h.calls_after_stop <= 1, f"evaluate was called {h.calls_after_stop} times after the problem "
                                          "stopped; return once problem.stopped is set")
        x = np.asarray(res.x, float).reshape(-1)
        _require(x.shape == (pr.dim,), f"result.x has shape {x.shape}, expected ({pr.dim},)")
        _require(np.all(x >= pr.lower - 1e-9) and np.all(x <= pr.upper + 1e-9), f"result.x {x} is outside the bounds")
        _require(math.isfinite(res.fun), f"result.fun is {res.fun!r}")
        vals = np.array([h.f(p) for p in h.points])
        _require(res.fun <= np.median(vals) and (res.fun < np.median(vals) or np.ptp(vals) == 0),
                 f"best value {res.fun:.4g} is not below the median {np.median(vals):.4g} of the evaluated points")
        return f"{pr.n_evaluations} evaluations, best {res.fun:.3g} (median {np.median(vals):.3g})"

    def c_determinism():
        h1, r1 = first()
        h2, r2 = run()
        same = len(h1.points) == len(h2.points) and all(np.array_equal(a, b) for a, b in zip(h1.points, h2.points))
        _require(same, "the same seed and objective gave a different sequence of evaluated points (the run "
                       "store replays evaluations on resume, so the search must be deterministic)")

    def c_pickle():
        other = _roundtrip(_need(inst, err))
        h1, _ = first()
        h2, _ = run(other)
        _require(len(h1.points) == len(h2.points) and all(np.array_equal(a, b) for a, b in zip(h1.points, h2.points)),
                 "the unpickled optimiser searches differently")

    return _common_checks(cls, inst, settings, label, "optimizer", registered, err) + [
        Check(label, "minimize", c_minimize), Check(label, "determinism", c_determinism),
        Check(label, "pickle", c_pickle)]


def check_optimizer(optimizer, *, raise_on_failure: bool = True, **options) -> Report:
    """Run :func:`optimizer_checks`; raises :class:`ConformanceError` on failures."""
    checks = optimizer_checks(optimizer, **options)
    return _run(checks, checks[0].component, raise_on_failure)


# ==============================================================================================
# executor
# ==============================================================================================

_WORKER_OFFSET = None


def _conformance_init(offset):
    """Executor initializer used by the executor checks (module level: picklable)."""
    global _WORKER_OFFSET
    _WORKER_OFFSET = offset


def _conformance_task(x):
    if _WORKER_OFFSET is None:
        raise RuntimeError("initializer did not run in this worker")
    return x * x + _WORKER_OFFSET


def executor_checks(executor, *, settings=None, items: int = 12, registered: bool | str = False) -> list[Check]:
    """The conformance checks of an executor: the initializer runs in every worker before any
    task, ``map_unordered`` yields every index exactly once with its result, ``map`` keeps the
    order, and the executor can be started again after ``shutdown``."""
    cls, inst, settings, err = _instance(executor, "executor", settings)
    label = _label(cls, "executor")
    xs = list(range(items))

    def c_map():
        ex = _need(inst, err)
        _require(isinstance(ex.workers, int) and ex.workers >= 1, f"workers is {ex.workers!r}")
        with ex.started(_conformance_init, (7,)):
            got = list(ex.map_unordered(_conformance_task, xs))
            idx = sorted(i for i, _ in got)
            _require(idx == list(range(items)), f"map_unordered yielded indices {idx}, expected each of 0..{items - 1} once")
            bad = [(i, r) for i, r in got if r != xs[i] ** 2 + 7]
            _require(not bad, f"wrong results (index, result): {bad[:3]}")
            ordered = ex.map(_conformance_task, xs)
            _require(ordered == [x * x + 7 for x in xs], f"map returned {ordered}")
        with ex.started(_conformance_init, (1,)):
            again = ex.map(_conformance_task, xs[:3])
            _require(again == [x * x + 1 for x in xs[:3]], f"after a restart with a new initializer argument map "
                                                          f"returned {again}")
        return f"{ex.workers} worker(s)"

    def c_pickle():
        _roundtrip(_need(inst, err))

    return _common_checks(cls, inst, settings, label, "executor", registered, err) + [
        Check(label, "map", c_map), Check(label, "pickle", c_pickle)]


def check_executor(executor, *, raise_on_failure: bool = True, **options) -> Report:
    """Run :func:`executor_checks`; raises :class:`ConformanceError` on failures."""
    checks = executor_checks(executor, **options)
    return _run(checks, checks[0].component, raise_on_failure)


# ==============================================================================================
# dispatch
# ==============================================================================================

_CHECKS = {"ssm": ssm_checks, "features": feature_set_checks, "distance": distance_checks,
           "qsm_reader": reader_checks, "qsm_writer": writer_checks, "optimizer": optimizer_checks,
           "executor": executor_checks}


def component_checks(component, **options) -> list[Check]:
    """The checks of any component (class or instance), chosen by its ``kind``; ``options`` go
    to the kind's ``*_checks`` function (readers need ``paths``, writers ``out_dir``)."""
    cls = component if isinstance(component, type) else type(component)
    kind = getattr(cls, "kind", None)
    if kind not in _CHECKS:
        raise ConformanceError(f"{cls.__qualname__}", [("class", f"kind {kind!r} is not one of {KINDS}")])
    return _CHECKS[kind](component, **options)


def check_component(component, *, raise_on_failure: bool = True, **options) -> Report:
    """Run :func:`component_checks`; raises :class:`ConformanceError` listing the failures.

    Examples
    --------
    >>> import bforest_core as bf
    >>> from bforest_core.testing import check_component
    >>> print(check_component(bf.component_class("executor", "serial")))   # doctest: +SKIP
    executor 'serial': 4/4 checks passed
    ...
    """
    checks = component_checks(component, **options)
    return _run(checks, checks[0].component, raise_on_failure)


def run_all(distribution: str | None = None, kinds: Iterable[str] | None = None,
            names: Iterable[str] | None = None, options: Mapping[tuple[str, str], Mapping[str, Any]] | None = None,
            *, raise_on_failure: bool = True) -> dict[tuple[str, str], Report]:
    """Check every registered component (of one distribution, kinds or names).

    Parameters
    ----------
    distribution : str, optional
        Only components registered by this distribution (e.g. ``"bforest-example-ssm"``).
    kinds, names : iterable of str, optional
        Only these kinds / names.
    options : mapping, optional
        ``{(kind, name): {option: value}}`` passed to the kind's checks (e.g. fast SSM
        ``params``, a reader's sample ``paths``, a writer's ``out_dir``). Readers without
        ``paths`` and writers without ``out_dir`` are skipped (``Report.skipped`` says why).
    raise_on_failure : bool
        Raise one :class:`ConformanceError` listing every failed check of every component.

    Returns
    -------
    dict
        ``(kind, name) -> Report``.
    """
    from ..registry import discover
    reg = discover()
    options = dict(options or {})
    kinds = set(kinds) if kinds is not None else None
    names = set(names) if names is not None else None
    reports: dict[tuple[str, str], Report] = {}
    for (kind, name), entry in sorted(reg.components.items()):
        if distribution is not None and entry.distribution != distribution:
            continue
        if (kinds is not None and kind not in kinds) or (names is not None and name not in names):
            continue
        opts = dict(options.get((kind, name), {}))
        opts.setdefault("registered", entry.distribution)
        label = f"{kind} '{name}'"
        if kind == "qsm_reader" and "paths" not in opts:
            reports[(kind, name)] = Report(label, skipped="needs sample files: options={(kind, name): {'paths': [...]}}")
            continue
        if kind == "qsm_writer" and "out_dir" not in opts:
            reports[(kind, name)] = Report(label, skipped="needs a folder: options={(kind, name): {'out_dir': ...}}")
            continue
        reports[(kind, name)] = _run(component_checks(entry.cls, **opts), label, False)
    if distribution is not None and not reports:
        raise ConformanceError(f"distribution {distribution!r}",
                               [("registered", "registers no components (is it installed? known distributions: "
                                 f"{sorted({e.distribution for e in reg.components.values()})})")])
    if raise_on_failure:
        failures = [(f"{r.component}: {f.check}", f.problem) for r in reports.values() for f in r.failures]
        if failures:
            raise ConformanceError("conformance run", failures)
    return reports
