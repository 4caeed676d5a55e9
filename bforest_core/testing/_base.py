"""Results, the check machinery and the checks every component shares."""

from __future__ import annotations

import json
import pickle
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pydantic

from ..interfaces import INTERFACES, KINDS, ComponentSettings, RecipeDraft, RecipePart, RecipePlan
from ..tree import Tree

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
            return CheckResult(
                self.component,
                self.name,
                False,
                f"raised {type(exc).__name__}: {exc}",
                seconds=time.perf_counter() - t0,
            )
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

    def raise_for_failures(self) -> Report:
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
            return (
                cls,
                None,
                dict(settings or {}),
                f"{cls.__qualname__}(**{dict(settings or {})!r}) raised {type(exc).__name__}: {exc}",
            )
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
        _require(
            a.shape == shape and a.dtype == np.float64,
            f"{what}.{k} has shape {a.shape} and dtype {a.dtype}, expected {shape} float64",
        )
        bad = np.flatnonzero(~np.isfinite(a).reshape(n, -1).all(axis=1))
        _require(bad.size == 0, f"{what}.{k} is not finite at rows {bad[:5].tolist()}")
    for k in ("parent", "extension"):
        a = getattr(tree, k)
        _require(
            a.shape == (n,) and a.dtype == np.int64,
            f"{what}.{k} has shape {a.shape} and dtype {a.dtype}, expected ({n},) int64",
        )
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
    _require(
        bad.size == 0,
        f"{what}: parent is not in [0, row) at rows {bad[:5].tolist()} (one root at row 0, parents before children)",
    )
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
        _require(
            issubclass(cls, INTERFACES[kind]),
            f"{cls.__qualname__} does not subclass bforest_core.{INTERFACES[kind].__name__}",
        )
        name = getattr(cls, "name", None)
        _require(isinstance(name, str) and name != "", "class attribute 'name' is missing or empty")
        _require(
            name.strip() == name and not any(ch.isspace() or ch in "\"'[]=#" for ch in name),
            f'name {name!r} has whitespace or TOML-special characters (it is typed in configs as kind = "...")',
        )
        _require(isinstance(getattr(cls, "summary", ""), str), "summary is not a string")
        _require(
            isinstance(cls.Settings, type) and issubclass(cls.Settings, ComponentSettings),
            "Settings is not a subclass of bforest_core.ComponentSettings",
        )
        _require(
            not getattr(cls, "__abstractmethods__", None),
            f"abstract methods not implemented: {', '.join(sorted(cls.__abstractmethods__))}",
        )

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
            raise _Fail(
                f"an unknown settings key ({UNKNOWN_KEY!r}) was accepted; Settings must forbid extra "
                "keys (subclass bforest_core.ComponentSettings)"
            )

    checks = [Check(label, "class", c_class), Check(label, "settings", c_settings)]
    if kind in RECIPE_WRITERS:
        checks.append(Check(label, "recipe", lambda: _recipe_check(cls, _need(inst, make_error), kind)))
    if registered:

        def c_registered():
            from ..registry import discover

            reg = discover()
            entry = reg.components.get((kind, cls.name))
            _require(
                entry is not None,
                f"not registered: bf.discover() has no {kind} {cls.name!r} "
                f"(known: {', '.join(reg.names(kind)) or 'none'}; plugin load errors: "
                f"{[e.error for e in reg.errors] or 'none'})",
            )
            _require(
                entry.cls is cls,
                f"the registry resolves {kind} {cls.name!r} to {entry.cls.__module__}."
                f"{entry.cls.__qualname__}, not to {cls.__module__}.{cls.__qualname__}",
            )
            if isinstance(registered, str):
                _require(
                    entry.distribution == registered,
                    f"registered by distribution {entry.distribution!r}, expected {registered!r}",
                )
            from ..registry import component

            component(kind, cls.name, **settings)
            return f"from {entry.distribution} {entry.version} (entry point {entry.plugin!r})"

        checks.append(Check(label, "registered", c_registered))
    return checks


#: the kinds whose components may write a part of a recipe (``draft_recipe``, ``bforest init``)
RECIPE_WRITERS = ("ssm", "features", "distance", "optimizer")


def _built(cls, settings: dict, what: str):
    """The component with ``settings`` (its recipe part's), or a failed check naming them."""
    try:
        return cls(**settings)
    except Exception as exc:
        raise _Fail(f"{what} {settings!r} are not valid settings of the component: {exc}") from None


def _recipe_check(cls, inst, kind: str) -> str:
    """``draft_recipe`` on the sample tree: None (no recipes), or a part that bforest init can write."""
    from ..metrics import measure_tree
    from .samples import sample_tree

    measures = measure_tree(sample_tree())
    if kind == "ssm":
        d = inst.draft_recipe(measures)
        if d is None:
            return "writes no recipes"
        _require(isinstance(d, RecipeDraft), f"draft_recipe returned a {type(d).__name__}, not a RecipeDraft")
        _require(0.0 <= d.suits <= 1.0 and isinstance(d.why, str) and d.why, "suits must lie in [0, 1], why be text")
        specs = {p.name for p in inst.parameters}
        named = [k for k, *_ in d.free] + [k for k, *_ in d.fixed]
        _require(not set(named) - specs, f"the draft names unknown parameters {sorted(set(named) - specs)}")
        _require(all(lo < hi for _, lo, hi, _ in d.free), "a free parameter's lower bound is not below its upper")
        _require(not set(d.scaled) - {k for k, *_ in d.free}, "scaled names a parameter that is not free")
        _require(d.seeds >= 1 and d.max_evaluations >= 1, "seeds and max_evaluations must be 1 or more")
        _built(cls, {k: v for k, v, _ in d.settings}, "the draft's settings")
        return f"suits the sample tree {d.suits:.1f}, {len(d.free)} free parameters"
    draft = RecipeDraft(suits=1.0, why="the sample tree", free=[("x", 0.0, 1.0, None)])
    wrote = []
    for term in ("search",) if kind == "optimizer" else ("structure", "size"):
        part = inst.draft_recipe(RecipePlan(term, draft, measures, 1))
        if part is None:
            continue
        _require(isinstance(part, RecipePart), f"draft_recipe returned a {type(part).__name__}, not a RecipePart")
        _require(part.kind == cls.name, f"the {term} part's kind is {part.kind!r}, not the name {cls.name!r}")
        settings = {k: v for k, v, _ in part.settings}
        _built(cls, settings, f"the {term} part's settings")
        _built(cls, {**settings, **part.select}, f"the {term} part's settings with its select")
        _require(part.reach is None or part.reach > 0, f"the {term} part's reach {part.reach!r} is not positive")
        wrote.append(term)
    return f"writes the recipe's {' and '.join(wrote)} part" if wrote else "writes no recipes"


def _priority_check(cls, label) -> Check:
    """``priority`` (``QSMReader``/``QSMWriter``, default 0) is a whole number."""

    def c_priority():
        p = cls.priority
        _require(isinstance(p, int) and not isinstance(p, bool), f"priority is {p!r}, expected an int (default 0)")
        return f"priority {p}"

    return Check(label, "priority", c_priority)


def _need(inst, make_error):
    _require(inst is not None, make_error or "could not be instantiated")
    return inst


def _roundtrip(inst):
    try:
        data = pickle.dumps(inst)
    except Exception as exc:
        raise _Fail(
            f"the instance cannot be pickled ({type(exc).__name__}: {exc}); executors send components "
            "to worker processes, so keep only picklable state (no lambdas, locks, open files)"
        ) from None
    try:
        other = pickle.loads(data)
    except Exception as exc:
        raise _Fail(f"the pickled instance cannot be unpickled ({type(exc).__name__}: {exc})") from None
    _require(type(other) is type(inst), f"unpickled as {type(other).__name__}")
    _require(other.settings == inst.settings, "settings changed through pickling")
    return other
