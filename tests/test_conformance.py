"""The conformance kit (bforest_core.testing): run on the bundled components and the toy plugin,
and shown to catch deliberately broken components with a message naming component and check."""

from __future__ import annotations

import re
import threading
import warnings
from pathlib import Path

import numpy as np
import pytest
from pydantic import ConfigDict

import bforest_core as bf
from bforest_core import SSM, ComponentSettings, Distance, FeatureSet, Optimizer, OptimizeResult, ParameterSpec, Tree
from bforest_core.testing import (
    ConformanceError,
    check_component,
    check_distance,
    check_feature_set,
    check_optimizer,
    check_ssm,
    check_tree,
    run_all,
    sample_tables,
    sample_tree,
    ssm_checks,
)
from conftest import qsm_path

# ----------------------------------------------------------------------------- every registered component
#: Options that make a registered component's checks fast or give a reader its sample files (own
#: layout, and files of other layouts with the same suffix that it must not claim). A component
#: not named here is checked with the kit's defaults: a new plugin is checked without a test edit
#: (a reader without samples reads the sample tree as the writer of its name writes it).
OPTIONS = {
    ("ssm", "sot"): {"params": {"max_iter": 8}},
    ("ssm", "sot-bud-abort"): {"params": {"max_iter": 8}},  # the example growth form (docs/examples)
    ("ssm", "lignum"): {"params": {"years": 6}},
    ("features", "branch-segment"): {"settings": {"sets": ["S0,1", "B1", "B2"]}},
    ("optimizer", "ga"): {"settings": {"population": 8}},
    ("optimizer", "turbo"): {"settings": {"batch": 6, "candidates": 128, "hyper_every": 20}},
    ("qsm_writer", "bforest-csv"): {"roundtrip": True},
    ("qsm_writer", "treeqsm-text"): {"roundtrip": True},
    ("qsm_writer", "treeqsm-mat"): {"roundtrip": True},
    # a small flow on 1 000 pairs: the kit's known posterior in seconds
    ("amortised", "flow"): {
        "settings": {"layers": 4, "width": 24, "max_epochs": 20, "patience": 8, "batch": 100},
        "pairs": 1000,
    },
}
READER_SAMPLES = {
    "treeqsm-mat": (
        ["itsme_qsm_tree_v230.mat", "itsme_qsms_tree_v230.mat"],
        ["wytham_tf3.mat", "pine_ruotsinkyla_3.mat"],
    ),
    "treeqsm-flat": (["pine_ruotsinkyla_3.mat"], ["wytham_tf3.mat", "itsme_qsm_tree_v230.mat"]),
    "cyldata-mat": (["wytham_tf3.mat"], ["itsme_qsm_tree_v230.mat"]),
    "treeqsm-text": (["itsme_tree_v240_cylinder.txt", "archi_tree1_treeqsm_v23.txt"], []),
    "archi-csv": (["coffeetree_archi.csv"], ["coffeetree_simpleforest.csv"]),
    "simpleforest-csv": (["coffeetree_simpleforest.csv"], ["coffeetree_archi.csv"]),
}
#: further settings of some components, checked besides their defaults
VARIANTS = [
    ("features", "branch-segment", "linear", {"settings": {"sets": ["S1"], "angles": "linear"}}),
    ("distance", "sliced", "wasserstein", {"settings": {"statistic": "wasserstein", "lines": 32, "empty_cost": 3.0}}),
]
#: the test suite's own plugin, installed for the session by the toy_plugin fixture (checked by
#: test_toy_plugin_conforms), so not among the components installed when the tests are collected
TOY = "bforest-toy"
REGISTERED = sorted(k for k, e in bf.discover().components.items() if e.distribution != TOY)


def _options(kind, name, tmp_path, extra=None):
    opts = dict(extra if extra is not None else OPTIONS.get((kind, name), {}))
    if kind == "qsm_writer":
        opts["out_dir"] = tmp_path
    if kind == "qsm_reader" and name in READER_SAMPLES:
        own, foreign = READER_SAMPLES[name]
        opts.update(paths=[qsm_path(p) for p in own], foreign=[qsm_path(p) for p in foreign])
    return opts


@pytest.mark.parametrize("kind,name", REGISTERED, ids=[f"{k}:{n}" for k, n in REGISTERED])
def test_registered_component(kind, name, tmp_path):
    """The kit's checks of every component the registry discovers (bundled and installed plugins)."""
    missing = bf.component(kind, name).missing() if kind == "amortised" else None
    if missing:
        pytest.skip(missing)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # readers warn about repaired rows of the real files
        rep = run_all(kinds=[kind], names=[name], options={(kind, name): _options(kind, name, tmp_path)})[(kind, name)]
    assert not rep.skipped, rep.skipped
    assert rep.ok and "registered" in rep.passed and len(rep.passed) >= 4, str(rep)


@pytest.mark.parametrize("kind,name,tag,extra", VARIANTS, ids=[f"{k}:{n}[{t}]" for k, n, t, _ in VARIANTS])
def test_registered_component_variant(kind, name, tag, extra, tmp_path):
    if (kind, name) not in REGISTERED:
        pytest.skip(f"{kind} '{name}' is not registered")
    run_all(kinds=[kind], names=[name], options={(kind, name): _options(kind, name, tmp_path, extra)})


def test_the_kit_covers_every_registered_component(record_property):
    """Every registered component is a case of test_registered_component (the parametrisation is
    the registry itself) and the kit finds checks for each of them; the count goes to the report."""
    reg = bf.discover()
    installed = sorted(k for k, e in reg.components.items() if e.distribution != TOY)  # not the session's toy
    assert REGISTERED == installed and len(REGISTERED) >= 32
    assert {"bforest-example-ssm"} <= {e.distribution for e in reg.components.values()}, (
        "the example plugin (docs/examples/bforest-example-ssm) is not installed: python3 dev.py env"
    )
    record_property("conformance_components", f"{len(REGISTERED)} of {len(installed)} registered (100 %)")
    print(f"conformance kit: {len(REGISTERED)} of {len(installed)} registered components (100 %)")


def test_readers_are_checked_on_their_writers_output_when_they_have_no_samples():
    reps = run_all(kinds=["qsm_reader"], names=["bforest-csv", "treeqsm-text"])
    assert all(r.ok and "read" in r.passed for r in reps.values()), reps


# ----------------------------------------------------------------------------- toy plugin
def test_toy_plugin_conforms(toy_plugin):
    reports = run_all(
        distribution="bforest-toy",
        options={
            ("ssm", "toy"): {"params": {"segments": 6}},
            ("features", "toy-features"): {"trees": [sample_tree(0), sample_tree(1)]},
        },
    )
    assert sorted(reports) == [
        ("distance", "toy-distance"),
        ("features", "toy-features"),
        ("optimizer", "toy-random"),
        ("ssm", "toy"),
    ]
    assert all(r.ok and "registered" in r.passed for r in reports.values())
    ssm = reports[("ssm", "toy")]
    assert ssm.passed == [
        "class",
        "settings",
        "recipe",
        "registered",
        "parameters",
        "resolve_params",
        "unknown_params",
        "simulate",
        "determinism",
        "seeds",
        "pickle",
        "crown_space",
        "bounds",
    ]
    assert "4 parameters" in str(ssm)


def test_toy_ssm_failing_at_bounds_is_fine_when_it_raises_simulation_failed(toy_plugin):
    # fail_above makes every angle above 60 raise SimulationFailed("collapsed"): allowed
    rep = check_ssm(
        bf.component_class("ssm", "toy"), settings={"fail_above": 60.0}, params={"angle": 30.0}, bounds="each", hold=[]
    )
    note = next(r.note for r in rep.results if r.check == "bounds")
    assert "angle = 90 (upper): collapsed" in note and "all at upper bounds: collapsed" in note


def test_run_all_skips_readers_without_samples_or_writer_and_names_unknown_distribution():
    reps = run_all(kinds=["qsm_reader"], names=["cyldata-mat", "treeqsm-flat"])
    assert len(reps) == 2 and all("needs sample files" in r.skipped for r in reps.values())
    with pytest.raises(ConformanceError, match="'no-such-dist'.*registers no components"):
        run_all(distribution="no-such-dist")


# ----------------------------------------------------------------------------- helpers
def test_sample_tree_is_valid_and_deterministic():
    t = sample_tree(3)
    check_tree(t)
    assert t.max_order == 2 and np.bincount(t.order)[0] == 16
    assert (t.order == 1).sum() > 50 and t.branches.order.tolist().count(1) == 28
    u = sample_tree(3)
    assert all(np.array_equal(getattr(t, k), getattr(u, k)) for k in ("start", "axis", "radius", "parent"))
    assert not np.array_equal(sample_tree(4).axis, t.axis)


def test_check_tree_names_violations():
    t = sample_tree(0)
    object.__setattr__(t, "metadata", ["not", "a", "dict"])
    with pytest.raises(AssertionError, match="metadata is a list"):
        check_tree(t, "x")
    with pytest.raises(AssertionError, match="is a dict, not a bforest_core.Tree"):
        check_tree({}, "x")


# ----------------------------------------------------------------------------- broken components
class GoodSettings(ComponentSettings):
    scale: float = 1.0


class GoodSSM(SSM):
    """A correct little model (positive control): a trunk with one lateral per node."""

    name = "good"
    Settings = GoodSettings

    @property
    def parameters(self):
        return [
            ParameterSpec("angle", 40.0, 10.0, 80.0, unit="deg", description="lateral angle"),
            ParameterSpec("nodes", 5, 2, 12, integer=True, description="trunk cylinders"),
        ]

    def _rng(self, seed):
        return np.random.default_rng(seed)

    def simulate(self, params, seed):
        p = self.resolve_params(params)
        rng = self._rng(seed)
        n = int(p["nodes"])
        a = np.radians(p["angle"] + rng.normal(0, 3, n))
        az = rng.uniform(0, 2 * np.pi, n)
        lat = np.c_[np.sin(a) * np.cos(az), np.sin(a) * np.sin(az), np.cos(a)]
        start = np.r_[np.c_[np.zeros((n, 2)), np.arange(n)], np.c_[np.zeros((n, 2)), np.arange(n) + 1.0]]
        axis = np.r_[np.tile([0, 0, 1.0], (n, 1)), lat]
        parent = np.r_[-1, np.arange(n - 1), np.arange(n)]
        ext = np.r_[np.arange(1, n), -1, np.full(n, -1)]
        return Tree(
            start * self.settings.scale,
            axis,
            np.ones(2 * n),
            np.full(2 * n, 0.05),
            parent,
            ext,
            metadata=self._metadata(p, seed),
        )

    def _metadata(self, p, seed):
        return {"model": self.name, "params": p, "seed": seed, "status": "ok"}


class NoisySSM(GoodSSM):
    name = "noisy"

    def _rng(self, seed):
        return np.random.default_rng()  # forgets the seed


class SeedBlindSSM(GoodSSM):
    name = "seed-blind"

    def _rng(self, seed):
        return np.random.default_rng(0)


class UnpicklableSSM(GoodSSM):
    name = "unpicklable"

    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self._lock = threading.Lock()


class WrongSpaceSSM(GoodSSM):
    name = "wrong-space"

    def crown_space(self, params):
        return {"reach": [[1.0] * 16] * 8}  # the setting, not the envelope


class BadSpecSSM(GoodSSM):
    name = "bad-spec"

    @property
    def parameters(self):
        return [
            ParameterSpec("angle", 95.0, 10.0, 80.0),  # default outside the range
            ParameterSpec("nodes", 5, 2, 12.5, integer=True),  # fractional bound of an integer
            ParameterSpec("nodes", 5, 2, 12, integer=True),  # duplicate
            ParameterSpec("leaf area", 1.0, 0.0, 2.0),
        ]  # not an identifier

    def simulate(self, params, seed):
        return super().simulate({}, seed)


class CrashAtBoundsSSM(GoodSSM):
    name = "crash-at-bounds"

    def simulate(self, params, seed):
        p = self.resolve_params(params)
        if p["angle"] == 10.0:
            raise ZeroDivisionError("division by zero in the light model")
        if p["nodes"] == 12:
            raise bf.SimulationFailed("too_many_segments", "fine: a typed failure")
        return super().simulate(params, seed)


class LaxSettings(GoodSettings):
    model_config = ConfigDict(extra="allow", validate_assignment=True)  # a defect: unknown keys pass


class LaxSettingsSSM(GoodSSM):
    name = "lax-settings"
    Settings = LaxSettings


class LaxParamsSSM(GoodSSM):
    name = "lax-params"

    def resolve_params(self, params):
        known = self.defaults()
        return {**known, **{k: v for k, v in params.items() if k in known}}  # silently drops unknown names


class NoSeedMetadataSSM(GoodSSM):
    name = "no-seed-metadata"

    def _metadata(self, p, seed):
        return {"model": self.name, "params": p, "status": "ok"}


def _fails(component, check, match, **options):
    with pytest.raises(ConformanceError) as exc:
        check_component(component, **options)
    err = exc.value
    assert isinstance(err, AssertionError)
    assert check in err.checks, f"{check} not among the failed checks {err.checks}: {err}"
    problem = dict(err.failures)[check]
    assert re.search(match, problem), problem
    assert err.component.startswith(f"{component.kind} '{component.name}'")
    return err


def test_positive_control_passes_every_check():
    rep = check_ssm(GoodSSM, params={"nodes": 4})
    assert rep.ok and len(rep.results) == 12  # no 'registered' check unless asked
    assert dict((r.check, r.note) for r in rep.results)["recipe"] == "writes no recipes"


def test_nondeterministic_ssm_is_caught():
    err = _fails(NoisySSM, "determinism", r"same params and seed 1 gave different trees: 'axis' differs")
    assert str(err).startswith("ssm 'noisy': ")


def test_seed_blind_ssm_is_caught_unless_declared_deterministic():
    _fails(SeedBlindSSM, "seeds", r"seeds 1 and 2 gave identical trees; the model ignores its seed")
    assert check_ssm(SeedBlindSSM, stochastic=False).ok


def test_a_crown_space_that_is_not_an_envelope_is_caught():
    err = _fails(WrongSpaceSSM, "crown_space", r"crown_space returned a dict, not None or a CrownEnvelope")
    assert err.checks == ["crown_space"]


def test_unpicklable_ssm_is_caught():
    err = _fails(UnpicklableSSM, "pickle", r"cannot be pickled \(TypeError: .*lock")
    assert err.checks == ["pickle"]
    # one check run on its own raises with the component and the check in the message
    check = next(c for c in ssm_checks(UnpicklableSSM) if c.name == "pickle")
    with pytest.raises(
        ConformanceError, match=r"^ssm 'unpicklable': check 'pickle' failed: the instance cannot be pickled"
    ):
        check()


def test_bad_parameter_specs_are_caught():
    err = _fails(BadSpecSSM, "parameters", r"angle: default 95.0 is outside \[10.0, 80.0\]")
    problem = dict(err.failures)["parameters"]
    assert "nodes: integer parameter with non-integer" in problem
    assert "duplicate parameter names: nodes" in problem
    assert "'leaf area' is not a Python identifier" in problem


def test_exception_at_bounds_is_caught_but_simulation_failed_is_allowed():
    err = _fails(CrashAtBoundsSSM, "bounds", r"angle = 10 \(lower\): ZeroDivisionError: division by zero")
    problem = dict(err.failures)["bounds"]
    assert "nodes = 12" not in problem  # SimulationFailed at the upper bound is a legal outcome
    assert err.checks == ["bounds"]
    # parameters given in `params` are held there by the bounds check (cheap settings stay cheap)
    rep = check_ssm(CrashAtBoundsSSM, params={"angle": 30.0})
    assert "nodes = 12 (upper): too_many_segments" in next(r.note for r in rep.results if r.check == "bounds")
    assert check_ssm(CrashAtBoundsSSM, bounds="none").ok


def test_settings_that_accept_unknown_keys_are_caught():
    _fails(LaxSettingsSSM, "settings", r"unknown settings key .* was accepted; Settings must forbid extra keys")


def test_resolve_params_ignoring_unknown_names_is_caught():
    err = _fails(LaxParamsSSM, "resolve_params", r"accepted an unknown parameter name")
    assert "unknown_params" in err.checks


def test_missing_metadata_is_caught():
    _fails(NoSeedMetadataSSM, "simulate", r"tree.metadata lacks seed")


class MutatingSSM(GoodSSM):
    name = "mutating"

    def simulate(self, params, seed):
        params.setdefault("angle", 40.0)  # writes into the caller's mapping
        return super().simulate(params, seed)


def test_simulate_mutating_its_params_is_caught():
    _fails(MutatingSSM, "simulate", r"simulate changed the params mapping it was given \(\{\} -> \{'angle': 40.0\}\)")


def test_kit_rejects_bad_options():
    with pytest.raises(ValueError, match="two different seeds"):
        ssm_checks(GoodSSM, seeds=(1, 1))
    with pytest.raises(ValueError, match="bounds must be"):
        ssm_checks(GoodSSM, bounds="some")


class FlatFeatures(FeatureSet):
    name = "flat"

    @property
    def set_names(self):
        return ["L"]

    def columns(self, set_name):
        return ["length", "radius"]

    def extract(self, tree):
        return {"L": tree.length.astype(np.float32)}  # 1-D float32: two defects


class WideFeatures(FlatFeatures):
    name = "wide"

    def extract(self, tree):
        return {"L": np.c_[tree.length, tree.radius, tree.order.astype(float)]}


def test_broken_feature_sets_are_caught():
    _fails(FlatFeatures, "extract", r"set 'L' has shape \(\d+,\); tables are 2-D")
    _fails(WideFeatures, "extract", r"set 'L' has 3 columns but columns\('L'\) names 2")


class OffsetDistance(Distance):
    name = "offset"

    def compute(self, u_model, u_data):
        return 0.1 + float(np.abs(u_model.mean(0) - u_data.mean(0)).sum()) if len(u_model) else 1.0


class SignedDistance(Distance):
    name = "signed"

    def compute(self, u_model, u_data):
        return float(u_data.mean() - u_model.mean()) if len(u_model) else 0.0


class MiswrittenDistance(Distance):
    """Writes a recipe part with a setting it does not have, under another kind."""

    name = "miswritten"

    def compute(self, u_model, u_data):
        return float(np.abs(u_model.mean(0) - u_data.mean(0)).sum()) if len(u_model) else 1.0

    def draft_recipe(self, plan):
        if plan.term == "structure":
            return bf.RecipePart(self.name, [("lines", 128, None)])
        return bf.RecipePart("sliced", [])


def test_broken_distances_are_caught():
    _fails(MiswrittenDistance, "recipe", r"structure part's settings \{'lines': 128\} are not valid settings")
    assert check_distance(MiswrittenDistance, raise_on_failure=False).failures[0].check == "recipe"
    _fails(OffsetDistance, "identical", r"identical model and data tables give non-zero distances")
    _fails(SignedDistance, "finite", r"distance -?\d.* is not a finite non-negative number")
    U_data, U_model, cols = sample_tables(dims=(3,), shift=2.0)
    assert (
        check_distance(OffsetDistance, (U_data, U_model, cols), raise_on_failure=False).failures[0].check == "identical"
    )


class GreedyOptimizer(Optimizer):
    """Ignores problem.stopped and keeps evaluating."""

    name = "greedy"

    def minimize(self, problem):
        rng = np.random.default_rng(problem.seed)
        for _ in range(20):
            problem.evaluate(problem.lower + (problem.upper - problem.lower) * rng.random((8, problem.dim)))
        return OptimizeResult(x=problem.best_x, fun=problem.best_f, n_evaluations=problem.n_evaluations)


class UnseededOptimizer(GreedyOptimizer):
    name = "unseeded"

    def minimize(self, problem):
        rng = np.random.default_rng()
        while not problem.stopped:
            problem.evaluate(problem.lower + (problem.upper - problem.lower) * rng.random((8, problem.dim)))
        return OptimizeResult(x=problem.best_x, fun=problem.best_f, n_evaluations=problem.n_evaluations)


def test_broken_optimizers_are_caught():
    _fails(GreedyOptimizer, "minimize", r"evaluate was called \d+ times after the problem stopped")
    _fails(UnseededOptimizer, "determinism", r"the same seed and objective gave a different sequence")
    rep = check_optimizer(GreedyOptimizer, raise_on_failure=False)
    assert [f.check for f in rep.failures] == ["minimize"]  # deterministic and picklable, just greedy


class CappedOptimizer(GreedyOptimizer):
    """Stops after its own two rounds and does not lift them for a budget (the default)."""

    name = "capped"

    def expected_evaluations(self, dim):
        return 16

    def minimize(self, problem):
        rng = np.random.default_rng(problem.seed)
        for _ in range(2):
            if problem.stopped:
                break
            problem.evaluate(problem.lower + (problem.upper - problem.lower) * rng.random((8, problem.dim)))
        return OptimizeResult(x=problem.best_x, fun=problem.best_f, n_evaluations=problem.n_evaluations)


class LiftingOptimizer(CappedOptimizer):
    name = "lifting"

    @classmethod
    def budget_settings(cls, settings, budget):
        settings["rounds"] = budget  # writes into the caller's mapping, and a key Settings forbids
        return settings


def test_optimiser_limits_the_budget_cannot_lift_are_caught():
    _fails(CappedOptimizer, "budget", r"with budget_settings for 600 evaluations the optimiser plans only 16")
    err = _fails(LiftingOptimizer, "budget", r"budget_settings\(settings, 600\) gave settings the class rejects")
    assert err.checks == ["budget"]


class BadPriorityWriter(bf.QSMWriter):
    name = "bad-priority"
    suffixes = (".bad",)
    priority = "high"

    def write(self, tree, path, **options):
        Path(path).write_text("x")
        return Path(path)


class MislinedDistance(bf.LineDistance):
    """Per-line values that match no direction."""

    name = "mislined"

    def compute(self, u_model, u_data):
        return float(np.abs(u_model.mean(0) - u_data.mean(0)).sum()) if len(u_model) else 1.0

    def directions(self, d):
        return np.eye(d)

    def line_values(self, u_model, u_data, set_name=None):
        return np.zeros(d + 1) if (d := u_data.shape[1]) else None


def test_declared_capabilities_are_checked(tmp_path):
    _fails(BadPriorityWriter, "priority", r"priority is 'high', expected an int", out_dir=tmp_path)
    _fails(MislinedDistance, "capabilities", r"line_values of set '.*' has shape \(\d+,\), expected \(\d+,\) finite")
    rep = check_distance(OffsetDistance, raise_on_failure=False)  # a plain distance: no lines, no transforms
    assert next(r for r in rep.results if r.check == "capabilities").note == (
        "compares the tables as they are (no projection lines)"
    )

    class Lined(bf.LineDistance):  # a line distance with the defaults: no per-line values of its own
        name = "lined"
        compute, directions = MislinedDistance.compute, MislinedDistance.directions

    rep = check_distance(Lined, raise_on_failure=False)
    assert next(r for r in rep.results if r.check == "capabilities").note == "statistic 'ks'; no per-line values"


def test_feature_check_on_the_hand_tree():
    from conftest import hand_tree

    rep = check_feature_set(WideFeatures, trees=[hand_tree()], raise_on_failure=False)
    assert [f.check for f in rep.failures] == ["extract"]
