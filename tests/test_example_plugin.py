"""The example third-party plugin (docs/examples/bforest-example-ssm): discovered through its own
entry point, conformant, a real L-system with known answers, selectable and fittable from TOML."""

from __future__ import annotations

import importlib.metadata as md
import json
from pathlib import Path

import numpy as np
import pytest

import bforest_core as bf
from bforest_core.pipeline.store import RunStore
from bforest_core.testing import check_ssm, check_tree, ssm_checks

EXAMPLE = Path(__file__).resolve().parents[1] / "docs" / "examples" / "bforest-example-ssm"
DIST = "bforest-example-ssm"

try:
    md.distribution(DIST)
except md.PackageNotFoundError:
    pytest.skip(
        f"the example plugin distribution {DIST!r} is not installed (run `python3 dev.py env`, or "
        f".venv/bin/pip install -e {EXAMPLE})",
        allow_module_level=True,
    )


@pytest.fixture(scope="module")
def ssm():
    return bf.component("ssm", "lsystem")


def test_discovered_through_its_entry_point():
    reg = bf.discover()
    entry = reg.components[("ssm", "lsystem")]
    assert entry.distribution == DIST and entry.plugin == "lsystem"
    assert entry.version == md.version(DIST)
    assert entry.cls.__module__ == "bforest_example_ssm.model"
    assert "lsystem" in reg.names("ssm")
    assert not [e for e in reg.errors if e.distribution == DIST]
    # the entry point is declared by the example's own pyproject, not by bayesforest's
    eps = [ep for ep in md.distribution(DIST).entry_points if ep.group == "bforest"]
    assert [(ep.name, ep.value) for ep in eps] == [("lsystem", "bforest_example_ssm.plugin")]


def _conformance_checks():
    reg = bf.discover()
    if ("ssm", "lsystem") not in reg.components:  # installed but not loadable: fail loudly, not at collection
        errors = [e.error for e in reg.errors if e.distribution == DIST]
        return [pytest.param(None, id=f"not registered: {errors}")]
    return ssm_checks(reg.get("ssm", "lsystem"), params={"iterations": 5}, registered=DIST)


@pytest.mark.parametrize("check", _conformance_checks(), ids=str)
def test_conformance(check):
    assert check is not None, f"{DIST} is installed but registers no ssm 'lsystem'"
    check()


def test_conformance_with_default_params_and_a_small_cap():
    rep = check_ssm(bf.component_class("ssm", "lsystem"), settings={"max_segments": 300}, bounds="corners")
    assert rep.ok and "bounds" in rep.passed
    # with 300 internodes at most, the all-upper corner must have failed cleanly
    note = next(r.note for r in rep.results if r.check == "bounds")
    assert "too_many_segments" in note


def test_segment_counts_follow_the_grammar(ssm):
    # deterministic branching (p = 1): apices of order o at step t obey a_o(t+1) = a_o(t) + k a_{o-1}(t);
    # with k = 2, max order 2, 4 steps: 1 + 3 + 9 + 19 = 32 internodes, by order [4, 12, 16]
    p = dict(iterations=4, whorl_size=2, max_order=2, bare_steps=0, lateral_prob=1.0)
    t = ssm.simulate(p, seed=3)
    assert t.n == 32
    assert np.bincount(t.order).tolist() == [4, 12, 16]
    assert t.n_branches == 1 + 6 + 12
    # the growth topology: the apical child continues its axis, so the trunk is one branch of 4
    assert t.branches.n_cyl[0] == 4 and t.metadata["topology"] == "source"
    # no laterals at all: a trunk of `iterations` internodes of internode_length
    t0 = ssm.simulate({"lateral_prob": 0.0, "iterations": 7, "internode_length": 0.3}, seed=1)
    assert t0.n == 7 and t0.n_branches == 1
    np.testing.assert_allclose(t0.length, 0.3)
    # clear bole: no lateral on the first `bare_steps` trunk internodes
    tb = ssm.simulate({"bare_steps": 3, "lateral_prob": 1.0, "iterations": 6}, seed=1)
    trunk = np.flatnonzero(tb.order == 0)
    first_lat = tb.branches.parent_cyl[1:]
    assert first_lat.min() == trunk[3]


def test_turtle_geometry_known_angles(ssm):
    # no noise, no tropism: the trunk stays vertical, each lateral leaves its mother internode at
    # exactly branch_angle and successive trunk laterals are rolled by the divergence angle
    p = dict(
        iterations=6,
        whorl_size=1,
        lateral_prob=1.0,
        angle_sd=0.0,
        tropism=0.0,
        bare_steps=0,
        branch_angle=40.0,
        divergence=137.5,
        max_order=2,
    )
    t = ssm.simulate(p, seed=8)
    trunk = np.flatnonzero(t.order == 0)
    np.testing.assert_allclose(t.axis[trunk], np.tile([0, 0, 1.0], (trunk.size, 1)), atol=1e-12)
    bt = t.branches
    firsts = bt.first[1:]
    ang = np.degrees(np.arccos(np.clip(np.sum(t.axis[firsts] * t.axis[bt.parent_cyl[1:]], axis=1), -1, 1)))
    np.testing.assert_allclose(ang, 40.0, atol=1e-9)
    on_trunk = firsts[bt.order[1:] == 1]
    az = np.degrees(np.arctan2(t.axis[on_trunk, 1], t.axis[on_trunk, 0]))
    np.testing.assert_allclose(np.mod(np.diff(az), 360.0), 137.5, atol=1e-9)
    # internode length decays with order
    for o in range(3):
        np.testing.assert_allclose(t.length[t.order == o], 0.4 * 0.65**o)


def test_pipe_model_radii(ssm):
    p = {"pipe_exponent": 2.0, "tip_radius": 0.005}
    t = ssm.simulate(p, seed=4)
    ptr, idx = t.children()
    nchild = np.diff(ptr)
    tips = nchild == 0
    np.testing.assert_allclose(t.radius[tips], 0.005)
    # r^e of a cylinder = sum of its children's r^e (cross-sectional area is conserved for e = 2)
    inner = np.flatnonzero(~tips)
    sums = np.add.reduceat(t.radius[idx] ** 2, ptr[:-1][inner])
    np.testing.assert_allclose(t.radius[inner] ** 2, sums, rtol=1e-12)
    # so the base area is the number of tips times the tip area
    assert t.radius[0] ** 2 == pytest.approx(tips.sum() * 0.005**2)


def test_tropism_and_noise_shape_the_crown(ssm):
    up = ssm.simulate({"tropism": 0.5, "iterations": 7}, seed=2)
    down = ssm.simulate({"tropism": -0.5, "iterations": 7}, seed=2)
    lat_up, lat_down = up.axis[up.order > 0, 2], down.axis[down.order > 0, 2]
    assert lat_up.mean() > 0.7 > lat_down.mean()
    # the trunk tip is high above the ground: it looks like a tree
    assert up.end[:, 2].max() > 0.8 * 7 * 0.4 and up.max_order == 3


def test_too_many_segments_is_a_simulation_failure():
    small = bf.component("ssm", "lsystem", max_segments=40)
    with pytest.raises(bf.SimulationFailed) as exc:
        small.simulate({"iterations": 8}, seed=1)
    assert exc.value.status == "too_many_segments" and "max_segments = 40" in str(exc.value)
    check_tree(small.simulate({"iterations": 2}, seed=1))


def test_unknown_parameter_named(ssm):
    with pytest.raises(ValueError, match="branch_angel"):
        ssm.simulate({"branch_angel": 30.0}, seed=1)


# ------------------------------------------------------------------------------- TOML + fit
def _stack(request):
    """The features/distance/optimizer sections: the bundled ones when registered, else the toy
    plugin's (installed through the toy_plugin fixture)."""
    reg = bf.discover()
    if (
        "branch-segment" in reg.names("features")
        and "sliced" in reg.names("distance")
        and "ga" in reg.names("optimizer")
    ):
        return (
            '[features]\nkind = "branch-segment"\nsets = ["S0,1", "B1"]\n'
            '[distance]\nkind = "sliced"\n'
            '[optimizer]\nkind = "ga"\npopulation = 8\n'
        ), True
    request.getfixturevalue("toy_plugin")
    return (
        '[features]\nkind = "toy-features"\n[distance]\nkind = "toy-distance"\n'
        '[optimizer]\nkind = "toy-random"\nbatch = 8\n'
    ), False


CONFIG = """
seed = 5
[target.generate]
ssm = "lsystem"
seed = 21
params = {{ iterations = 7, whorl_size = 4, branch_angle = 35.0, length_decay = 0.65 }}
[ssm]
kind = "lsystem"
max_segments = 5000
fixed = {{ iterations = 7, whorl_size = 4 }}
free.branch_angle = {{ lower = 10.0, upper = 90.0 }}
free.length_decay = {{ lower = 0.3, upper = 1.0 }}
{stack}
[executor]
kind = "serial"
[stop]
max_evaluations = 32
[clones]
count = 2
"""


def test_selected_by_kind_in_toml(tmp_path, request):
    stack, _ = _stack(request)
    path = tmp_path / "run.toml"
    path.write_text(CONFIG.format(stack=stack))
    cfg = bf.load_config(path)
    assert cfg.ssm.kind == "lsystem" and cfg.ssm.max_segments == 5000
    assert cfg.ssm.free["branch_angle"].upper == 90.0 and cfg.ssm.fixed == {"iterations": 7, "whorl_size": 4}
    # the plugin's own settings and parameter ranges are validated like a bundled model's
    bad = tmp_path / "bad.toml"
    bad.write_text(CONFIG.format(stack=stack).replace("max_segments = 5000", "max_segment = 5000"))
    with pytest.raises(bf.ConfigError, match=r"ssm\.max_segment: unknown key"):
        bf.load_config(bad)
    bad.write_text(CONFIG.format(stack=stack).replace("upper = 90.0", "upper = 120.0"))
    with pytest.raises(
        bf.ConfigError, match=r"ssm\.free\.branch_angle: bounds \[10\.0, 120\.0\] exceed .*\[10\.0, 90\.0\] deg"
    ):
        bf.load_config(bad)


def test_fit_recovers_generating_parameters(tmp_path, request):
    stack, real = _stack(request)
    path = tmp_path / "run.toml"
    path.write_text(CONFIG.format(stack=stack))
    res = bf.fit(bf.load_config(path), tmp_path / "run", progress=False)
    run = tmp_path / "run"
    evs = RunStore.open(run).evaluations()
    assert res.n_evaluations == len(evs) == 32 and "budget" in res.stop_reason
    assert all(e.status == "ok" for e in evs)
    d = np.array([e.distance for e in evs])
    assert res.distance == d.min() and res.distance < 0.75 * np.median(d)
    best = json.loads((run / "best.json").read_text())
    assert best["params"]["iterations"] == 7 and isinstance(best["params"]["iterations"], int)
    assert (run / "best_tree.txt").exists()
    if real:  # the bundled features + sliced distance + GA pin the branch angle down
        assert abs(res.params["branch_angle"] - 35.0) < 8.0
        assert abs(res.params["length_decay"] - 0.65) < 0.15
