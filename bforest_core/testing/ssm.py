"""Conformance checks of a growth model (SSM)."""

from __future__ import annotations

import keyword
import math
import pickle
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np

from ..errors import SimulationFailed
from ..interfaces import ParameterSpec
from ._base import (
    METADATA_KEYS,
    Check,
    Report,
    _common_checks,
    _Fail,
    _instance,
    _label,
    _need,
    _require,
    _roundtrip,
    _run,
    _tree_diff,
    check_tree,
)


class _SSMCase:
    """One model under test: the instance, the parameters and seeds of the runs, and the first
    simulated tree (shared by the checks so the model is grown once)."""

    def __init__(self, ssm, cls, inst, settings, err, params, seeds, hold, bounds):
        self.ssm, self.cls, self.inst, self.settings, self.err = ssm, cls, inst, settings, err
        self.params, self.seeds, self.hold, self.bounds = params, seeds, hold, bounds
        self.cache: dict[str, Any] = {}

    def sim(self, p=None, seed=None, model=None):
        inst, params, seeds, err = self.inst, self.params, self.seeds, self.err
        model = model or _need(inst, err)
        p = params if p is None else p
        seed = seeds[0] if seed is None else seed
        try:
            return model.simulate(dict(p), seed)
        except SimulationFailed as exc:
            raise _Fail(
                f"simulate({p!r}, seed={seed}) raised SimulationFailed ({exc.status}): {exc}; choose "
                "params for which the model succeeds"
            ) from None

    def first_tree(self):
        inst, params, seeds, err, cache = self.inst, self.params, self.seeds, self.err, self.cache
        if "tree" not in cache:
            given = dict(params)
            try:
                cache["tree"] = _need(inst, err).simulate(given, seeds[0])
            except SimulationFailed as exc:
                raise _Fail(
                    f"simulate({params!r}, seed={seeds[0]}) raised SimulationFailed ({exc.status}): {exc}; "
                    "choose params for which the model succeeds"
                ) from None
            cache["mutated"] = given if given != params else None
        return cache["tree"]

    def c_parameters(self):
        inst, err = self.inst, self.err
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
            if not all(
                isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool) and math.isfinite(v)
                for v in vals.values()
            ):
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

    def c_resolve(self):
        inst, err = self.inst, self.err
        m = _need(inst, err)
        specs = m.parameters
        bogus = "bforest_conformance_no_such_parameter"
        try:
            m.resolve_params({bogus: 1.0})
        except ValueError as exc:
            _require(
                bogus in str(exc), f"resolve_params raised ValueError for an unknown name without naming it: {exc}"
            )
        else:
            raise _Fail(f"resolve_params accepted an unknown parameter name ({bogus!r}); it must raise ValueError")
        d = m.resolve_params({})
        _require(
            set(d) == {s.name for s in specs},
            f"resolve_params({{}}) gives names {sorted(d)}, not the parameters {sorted(s.name for s in specs)}",
        )
        for s in specs:
            if s.integer:
                _require(
                    isinstance(d[s.name], (int, np.integer)) and d[s.name] == s.default,
                    f"resolve_params({{}})[{s.name!r}] is {d[s.name]!r}, expected the integer default {s.default}",
                )
            else:
                _require(
                    d[s.name] == s.default,
                    f"resolve_params({{}})[{s.name!r}] is {d[s.name]!r}, expected the default {s.default}",
                )
        ints = [s for s in specs if s.integer and s.upper > s.lower]
        if ints:
            s = ints[0]
            v = m.resolve_params({s.name: s.lower + 0.6})[s.name]
            _require(
                v == s.lower + 1 and isinstance(v, (int, np.integer)),
                f"resolve_params({{{s.name!r}: {s.lower + 0.6}}}) gives {v!r}; integer parameters are rounded",
            )

    def c_unknown(self):
        inst, params, seeds, err = self.inst, self.params, self.seeds, self.err
        bogus = "bforest_conformance_no_such_parameter"
        try:
            _need(inst, err).simulate({**params, bogus: 1.0}, seeds[0])
        except ValueError as exc:
            _require(bogus in str(exc), f"simulate raised ValueError for an unknown parameter without naming it: {exc}")
        except SimulationFailed as exc:
            raise _Fail(
                f"simulate with an unknown parameter raised SimulationFailed ({exc.status}), not ValueError"
            ) from None
        else:
            raise _Fail(
                f"simulate accepted an unknown parameter ({bogus!r}); unknown names must raise ValueError "
                "(use self.resolve_params)"
            )

    def c_simulate(self):
        inst, params, seeds, cache, cls = self.inst, self.params, self.seeds, self.cache, self.cls
        t = self.first_tree()
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
        _require(
            set(md["params"]) <= known | set(params) and set(params) <= set(md["params"]),
            f"metadata['params'] ({sorted(md['params'])}) should hold the resolved parameters",
        )
        for k, v in params.items():
            spec = inst.parameter_spec(k)
            want = int(round(v)) if spec.integer else v
            _require(
                md["params"][k] == want, f"metadata['params'][{k!r}] is {md['params'][k]!r}, the run used {want!r}"
            )
        return f"{t.n} cylinders, max order {t.max_order}"

    def c_determinism(self):
        seeds, cls, settings, ssm = self.seeds, self.cls, self.settings, self.ssm
        t1 = self.first_tree()
        t2 = self.sim()
        d = _tree_diff(t1, t2)
        _require(
            d is None,
            f"the same params and seed {seeds[0]} gave different trees: {d}; draw every random "
            "number from one numpy Generator seeded with `seed`",
        )
        if isinstance(ssm, type):
            fresh = cls(**settings)
            d = _tree_diff(t1, self.sim(model=fresh))
            _require(
                d is None,
                f"a second instance gave a different tree for the same params and seed: {d} "
                "(state leaks between runs?)",
            )
        # interleaving another seed must not change the result (no hidden state)
        self.sim(seed=seeds[1])
        d = _tree_diff(t1, self.sim())
        _require(d is None, f"simulating seed {seeds[1]} in between changed the tree of seed {seeds[0]}: {d}")

    def c_seeds(self):
        seeds = self.seeds
        trees = [self.first_tree()] + [self.sim(seed=s) for s in seeds[1:]]
        same = [s for s, t in zip(seeds[1:], trees[1:]) if _tree_diff(trees[0], t) is None]
        if same:
            raise _Fail(
                f"seeds {seeds[0]} and {same[0]} gave identical trees; the model ignores its seed "
                "(pass stochastic=False for a deterministic model)"
            )

    def c_pickle(self):
        inst, err = self.inst, self.err
        other = _roundtrip(_need(inst, err))
        d = _tree_diff(self.first_tree(), self.sim(model=other))
        _require(d is None, f"the unpickled instance grows a different tree: {d}")
        t = self.first_tree()
        t2 = pickle.loads(pickle.dumps(t))
        d = _tree_diff(t, t2)
        _require(d is None, f"the returned tree does not survive pickling: {d}")

    def c_crown_space(self):
        from ..envelope import CrownEnvelope

        space = _need(self.inst, self.err).crown_space(dict(self.params))
        _require(
            space is None or isinstance(space, CrownEnvelope),
            f"crown_space returned a {type(space).__name__}, not None or a CrownEnvelope",
        )

    def c_bounds(self):
        inst, params, seeds, err, hold, bounds = self.inst, self.params, self.seeds, self.err, self.hold, self.bounds
        m = _need(inst, err)
        specs = [s for s in m.parameters if s.name not in hold]
        cases = [
            ("all at lower bounds", {s.name: s.lower for s in specs}),
            ("all at upper bounds", {s.name: s.upper for s in specs}),
        ]
        if bounds == "each":
            for s in specs:
                if s.upper > s.lower:
                    cases += [
                        (f"{s.name} = {s.lower:g} (lower)", {s.name: s.lower}),
                        (f"{s.name} = {s.upper:g} (upper)", {s.name: s.upper}),
                    ]
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
                _require(
                    t.metadata.get("status") == "ok", f"status {t.metadata.get('status')!r} without SimulationFailed"
                )
            except _Fail as exc:
                errors.append(f"{what}: {exc}")
        shown = "; ".join(errors[:6]) + (f"; ... ({len(errors)} cases)" if len(errors) > 6 else "")
        _require(not errors, f"parameters at their bounds must give a valid tree or raise SimulationFailed: {shown}")
        note = f"{len(cases)} bound settings"
        if failed:
            note += (
                f", {len(failed)} raised SimulationFailed ({'; '.join(failed[:4])}{' ...' if len(failed) > 4 else ''})"
            )
        return note


def ssm_checks(
    ssm,
    params: Mapping[str, float] | None = None,
    seeds: Sequence[int] = (1, 2),
    *,
    settings: Mapping[str, Any] | None = None,
    stochastic: bool = True,
    bounds: str | bool = "each",
    hold: Iterable[str] | None = None,
    registered: bool | str = False,
) -> list[Check]:
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
    case = _SSMCase(ssm, cls, inst, settings, err, params, seeds, hold, bounds)
    checks = _common_checks(cls, inst, settings, label, "ssm", registered, err)
    checks += [
        Check(label, "parameters", case.c_parameters),
        Check(label, "resolve_params", case.c_resolve),
        Check(label, "unknown_params", case.c_unknown),
        Check(label, "simulate", case.c_simulate),
        Check(label, "determinism", case.c_determinism),
    ]
    if stochastic:
        checks.append(Check(label, "seeds", case.c_seeds))
    checks.append(Check(label, "pickle", case.c_pickle))
    checks.append(Check(label, "crown_space", case.c_crown_space))
    if bounds not in ("none", False, None):
        checks.append(Check(label, "bounds", case.c_bounds))
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
