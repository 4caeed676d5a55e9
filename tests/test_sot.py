"""Tests of the SOT growth model plugin (docs/models.md part B; sanity properties D 1-5, 15-21)."""

from __future__ import annotations

import copy
import itertools
import math
from types import SimpleNamespace

import numpy as np
import pytest

import bforest_core as bf
from bforest_sot.forms.shade import GapShade, StandShade
from bforest_sot.light import LightField, shadow_kernel
from bforest_sot.model import BUD, CHILD, STUB, accumulate, allocate, path_any
from bforest_sot.plugin import SOT

NO_NOISE = {"branch_angle_sd": 0.0, "phyllotaxis_sd": 0.0}


@pytest.fixture(scope="module")
def ssm():
    return SOT()


def height(t):
    return float(t.end[:, 2].max() - t.start[0, 2])


def run_recorded(ssm, params, seed, keep_trees=()):
    """Run with on_step; collect per-cycle allocation/shoot records, field checks and trees."""
    rec = {"alloc": {}, "shoots": {}, "trees": {}, "field_err": {}, "heights": {}, "n_live": {}}

    def on_step(c, view):
        if view.alloc is not None:
            rec["alloc"][c] = view.alloc
            rec["shoots"][c] = view.shoots
        t = view.tree()
        rec["heights"][c] = height(t)
        rec["n_live"][c] = view.n_live
        if c in keep_trees:
            rec["trees"][c] = t
            store = view.store
            rec.setdefault("order", {})[c] = store.order[view.live_ids].copy()
            rec.setdefault("growth_lateral", {})[c] = store.is_lateral[view.live_ids].copy()
            rec.setdefault("stubs", {})[c] = {
                k: getattr(store, k)[view.live_ids].copy()
                for k in ("api_state", "lat_state", "api_stub_w", "lat_stub_w", "api_child", "lat_child")
            }
            rec.setdefault("segments", {})[c] = {  # every segment ever made, shed ones too
                k: getattr(store, k)[: store.n].copy() for k in ("start", "h", "length")
            }
        # the incrementally maintained field equals one rebuilt from the living segments
        f2 = copy.copy(view.field)
        f2.rebuild(view.store.start[view.live_ids])
        rec["field_err"][c] = float(np.max(np.abs(f2.log_e - view.field.log_e)))
        e = view.field.voxel_exposure()
        rec.setdefault("field_range", []).append((float(e.min()), float(e.max()), float(e[view.field.roof].max())))

    tree = ssm.simulate(params, seed, on_step=on_step)
    return tree, rec


@pytest.fixture(scope="module")
def default_run(ssm):
    """Calibrated defaults at 14 cycles (fast; drops and branching already active)."""
    return run_recorded(ssm, {"max_iter": 14}, 7, keep_trees=(14,))


# ------------------------------------------------------------------------------ parameters
def test_parameter_table_complete():
    PARAMETERS = SOT().parameters  # the papers' table and the growth forms' parameters
    names = [p.name for p in PARAMETERS]
    expected = {
        "max_iter",
        "alpha0",
        "alpha1",
        "max_grow",
        "drop_thresh",
        "init_width",
        "pipe_exp",
        "nonlinear",
        "reorient",
        "redir_strength",
        "tropism",
        "sample_rad",
        "ran",
        "vert",
        "init_lambda",
        "targ_lambda",
        "delay",
        "transition",
        "depth",
        "spread",
        "shadow_a",
        "shadow_b",
        "branch_angle",
        "phyllotaxis",
        "nonplanar_twist",
        "node_length",
        "voxel_size",
        "span",
        "branch_angle_sd",
        "phyllotaxis_sd",
        "lambda_sd",
        "tropism_sd",
        "stand_shade",
        "heading_sd",
        "leader_death",
        "death_delay",
        "short_shoot",
        "gap_shade",
        "gap_azimuth",
        "stem_death",
        "stem_guide",
        "envelope_shade",
        "side_shade",
        "space_claim",
    }  # stand_shade and the ones after it are additions, off by default
    assert set(names) == expected and len(names) == len(expected)
    by = {p.name: p for p in PARAMETERS}
    # calibrated defaults of B.4 and clone noise of E
    calib = {
        "max_iter": 18,
        "alpha0": 1,
        "alpha1": 1.5,
        "shadow_a": 0.5,
        "shadow_b": 2,
        "max_grow": 3,
        "drop_thresh": 0.2,
        "init_width": 0.02,
        "sample_rad": 0.32,
        "branch_angle_sd": 5,
        "phyllotaxis_sd": 10,
        "lambda_sd": 0,
        "tropism_sd": 0,
        "span": 12,
        "node_length": 0.2,
        "stand_shade": 0,
        "heading_sd": 0,
    }
    for k, v in calib.items():
        assert by[k].default == v, k
    assert {p.name for p in PARAMETERS if p.integer} == {"max_iter", "depth"}
    for p in PARAMETERS:
        assert p.lower <= p.default <= p.upper, p.name
        assert p.group in {"I", "II", "III", "IV", "V", "fixed"}, p.name
        assert p.description
    assert by["branch_angle"].unit == "deg" and by["init_width"].unit == "m"
    assert by["depth"].group == "IV" and by["lambda_sd"].group == "III"
    # group by group (I .. V, fixed): the papers' parameters first, then the growth forms'
    groups = [p.group for p in PARAMETERS]
    assert groups == sorted(groups, key=["I", "II", "III", "IV", "V", "fixed"].index)
    assert names.index("vert") < names.index("stand_shade") < names.index("gap_shade") < names.index("stem_guide")
    assert (
        names.index("tropism_sd") < names.index("heading_sd") < names.index("leader_death") < names.index("short_shoot")
    )


def test_component_registered_and_settings_checked():
    ssm = bf.component("ssm", "sot", order_mode="thickest")
    assert isinstance(ssm, SOT) and ssm.settings.order_mode == "thickest"
    with pytest.raises(Exception, match="order_mode"):
        bf.component("ssm", "sot", order_mode="sideways")
    with pytest.raises(Exception, match="no_such_switch"):
        SOT(no_such_switch=1)


@pytest.mark.parametrize(
    "params, name",
    [
        ({"shadow_b": 1.0}, "shadow_b"),
        ({"shadow_a": 2.5, "shadow_b": 2.0}, "shadow_a"),
        ({"shadow_a": -0.1}, "shadow_a"),
        ({"depth": 1}, "depth"),
        ({"depth": 1.4}, "depth"),  # integer parameters are rounded (SSM contract): 1
        ({"max_iter": "many"}, "max_iter"),
        ({"branch_angle_sd": -1.0}, "branch_angle_sd"),
        ({"lambda_sd": -0.01}, "lambda_sd"),
        ({"ran": 0.7, "vert": 0.4}, "ran"),
        ({"node_length": 0.0}, "node_length"),
        ({"init_width": -0.02}, "init_width"),
        ({"transition": 0.0}, "transition"),
        ({"init_lambda": 1.2}, "init_lambda"),
        ({"alpha1": float("nan")}, "alpha1"),
        ({"gap_shade": -1.0}, "gap_shade"),
        ({"stem_guide": 1.5}, "stem_guide"),
        ({"stem_death": 1.5}, "stem_death"),
        ({"no_such_param": 1.0}, "no_such_param"),
    ],
)
def test_invalid_parameters_raise_value_error_naming_them(ssm, params, name):
    with pytest.raises(ValueError, match=name):
        ssm.simulate(params, 1)


# ------------------------------------------------------------------------------ light field (D15)
def test_shadow_kernel_entries_and_factors():
    di, dj, dk, log_f = shadow_kernel(6, 1.0, 0.5, 2.0)
    assert di.size == 285  # 9 + 25 + 49 + 81 + 121
    assert set(dk.tolist()) == {-1, -2, -3, -4, -5}
    sel = (di == 2) & (dj == -1) & (dk == -3)
    assert np.exp(log_f[sel][0]) == pytest.approx(1 - 0.5 * 2.0 ** -math.sqrt(14), rel=1e-14)
    assert np.all(np.abs(di) <= -dk) and np.all(np.abs(dj) <= -dk)


def test_single_shadow_exact_and_trilinear():
    f = LightField(12.0, 0.2, 6, 1.0, 0.5, 2.0, ran=0.0)
    n = f.n_vox
    p = np.array([[0.05, -0.05, 3.01]])  # voxel (30, 29, 15)
    assert f.voxel_of(p).tolist() == [[30, 29, 15]]
    f.cast(p)
    e = f.voxel_exposure().reshape(n, n, n)
    assert e[30, 29, 15] == 1.0 and e[30, 29, 16] == 1.0  # no self-shading, nothing above
    assert e[30, 29, 14] == pytest.approx(1 - 0.5 / 2.0, rel=1e-14)
    assert e[32, 26, 12] == pytest.approx(1 - 0.5 * 2.0 ** -math.sqrt(9 + 4 + 9), rel=1e-14)
    assert e[30, 29, 9] == 1.0  # layer 6 is beyond depth - 1
    assert e[34, 29, 12] == 1.0  # outside the pyramid (|di| > l)
    # trilinear: at a voxel centre it is the voxel value, half way between two centres the mean
    c = np.array([[30.5 * 0.2 - 6.0, 29.5 * 0.2 - 6.0, 14.5 * 0.2]])
    assert f.exposure(c)[0] == pytest.approx(e[30, 29, 14], rel=1e-12)
    mid = c + [[0.0, 0.0, 0.1]]
    assert f.exposure(mid)[0] == pytest.approx(0.5 * (e[30, 29, 14] + e[30, 29, 15]), rel=1e-12)
    # roof is dark
    assert f.exposure(np.array([[0.0, 0.0, 11.95]]))[0] == 0.0


def test_cast_remove_restores_field_exactly():
    rng = np.random.default_rng(0)
    f = LightField(12.0, 0.2, 6, 1.0, 0.8, 1.5, ran=0.2, uniforms=rng.random(60**3))
    pts = np.column_stack([rng.uniform(-6, 6, 3000), rng.uniform(-6, 6, 3000), rng.uniform(0, 12, 3000)])
    pts[:500, :2] *= 0.05  # a dense column so voxels get many factors
    f.cast(pts)
    e = f.voxel_exposure()
    assert e.min() >= 0.0 and e.max() <= 1.0 and e[f.roof].max() == 0.0
    assert e.min() < 1e-3  # heavily shaded somewhere: the check above is not vacuous
    perm = rng.permutation(3000)
    f.remove(pts[perm[:1200]])
    f.cast(pts[perm[:100]])
    f.remove(pts[perm[:100]])
    f.remove(pts[perm[1200:]])
    assert np.max(np.abs(f.log_e - f.log_e0)) < 1e-9


def test_field_in_run_equals_rebuilt_and_stays_in_range(default_run):
    _, rec = default_run
    assert max(rec["field_err"].values()) < 1e-9
    for lo, hi, roof in rec["field_range"]:
        assert 0.0 <= lo <= hi <= 1.0 and roof == 0.0
    # drops happened, so shadows were removed as well as cast
    assert sum(int(a.dropped.sum()) for a in rec["alloc"].values()) > 0


# ------------------------------------------------------------------------------ passes (D16, D20)
def _hand_structure():
    # 0: apical CHILD -> 1, lateral STUB (w 0.05); 1: apical BUD (0.6), lateral CHILD -> 2;
    # 2: apical BUD (0.2), lateral BUD (0.4); 3 (lateral of nothing, separate check): two stubs
    api_state = np.array([CHILD, BUD, BUD], np.int8)
    lat_state = np.array([STUB, CHILD, BUD], np.int8)
    api_child = np.array([1, -1, -1])
    lat_child = np.array([-1, 2, -1])
    q_api = np.array([0.0, 0.6, 0.2])
    q_lat = np.array([0.0, 0.0, 0.4])
    api_w = np.zeros(3)
    lat_w = np.array([0.05, 0.0, 0.0])
    depth = np.array([0, 1, 2])
    return api_state, lat_state, api_child, lat_child, q_api, q_lat, api_w, lat_w, depth


def test_accumulate_and_allocate_known_answers():
    acc = accumulate(*_hand_structure(), lam=0.6, kappa=1.0, pipe_exp=2.0, init_width=0.02)
    np.testing.assert_allclose(acc["N"], [6, 5, 3])
    np.testing.assert_allclose(acc["Q"], [1.2, 1.2, 0.6])
    np.testing.assert_allclose(acc["D"], [0.72, 0.6, 0.28], rtol=1e-14)
    np.testing.assert_allclose(acc["W"], [0.0004 + 0.0025, 0.0004, 0.0004], rtol=1e-14)
    parent = np.array([-1, 0, 1])
    is_lat = np.array([False, False, True])
    v, rounds = allocate(parent, is_lat, acc["N"], acc["Q"], acc["D"], 0.6, 1.0, v_base=2.0)
    np.testing.assert_allclose(v, [2.0, 2.0, 0.8], rtol=1e-14)
    assert path_any(np.array([False, True, False]), rounds).tolist() == [False, True, True]
    acc2 = accumulate(*_hand_structure(), lam=0.6, kappa=2.0, pipe_exp=2.0, init_width=0.02)
    np.testing.assert_allclose(acc2["D"][1:], [0.6 * 0.36 + 0.4 * 3 * 0.2**2, 0.6 * 0.04 + 0.4 * 0.16], rtol=1e-14)
    # a segment with no BUD or CHILD slot: N = 1, Q = 0, D = 1, stubs keep their width
    acc3 = accumulate(
        np.array([STUB], np.int8),
        np.array([STUB], np.int8),
        np.array([-1]),
        np.array([-1]),
        np.zeros(1),
        np.zeros(1),
        np.array([0.03]),
        np.array([0.04]),
        np.array([0]),
        lam=0.5,
        kappa=1.0,
        pipe_exp=2.0,
        init_width=0.02,
    )
    assert (acc3["N"][0], acc3["Q"][0], acc3["D"][0]) == (1.0, 0.0, 1.0)
    assert acc3["width"][0] == pytest.approx(0.05, rel=1e-14)


def _check_conservation(alloc, kappa):
    v = alloc.v

    def child_v(children, states):
        m = states == CHILD
        return np.where(m, v[np.searchsorted(alloc.ids, np.where(m, children, 0))], 0.0)

    passed = (
        child_v(alloc.api_child, alloc.api_state)
        + child_v(alloc.lat_child, alloc.lat_state)
        + alloc.vA_raw
        + alloc.vL_raw
    )
    has = np.isin(alloc.api_state, [BUD, CHILD]) | np.isin(alloc.lat_state, [BUD, CHILD])
    sel = has & (alloc.D > 0)
    assert sel.sum() > 0
    rel = np.abs(passed[sel] - v[sel]) / np.abs(v[sel])
    assert rel.max() < 1e-12
    return int(sel.sum())


@pytest.mark.parametrize("kappa", [1.0, 1.7])
def test_borchert_honda_conserves_vigor_at_every_branch_point(ssm, kappa, default_run):
    if kappa == 1.0:
        _, rec = default_run
    else:
        _, rec = run_recorded(ssm, {"max_iter": 11, "nonlinear": kappa}, 3)
    checked = 0
    for alloc in rec["alloc"].values():
        checked += _check_conservation(alloc, kappa)
        root = int(np.flatnonzero(alloc.parent < 0)[0])
        assert alloc.v[root] == pytest.approx(1.0 + 1.5 * alloc.Q[root], rel=1e-15)
        assert alloc.v_base == alloc.v[root]
    assert checked > 500


def test_drops_leave_only_supplied_segments(default_run):
    tree, rec = default_run
    n_dropped = 0
    for a in rec["alloc"].values():
        kept = ~a.dropped & (a.parent >= 0)
        assert np.all(a.v[kept] / a.N[kept] > 0.2)
        # every dropped subtree has a dropped top whose own v/N fell to the threshold
        pos = np.searchsorted(a.ids, a.parent[a.dropped])
        top = np.flatnonzero(a.dropped)[~a.dropped[pos]]
        assert np.all(a.v[top] / a.N[top] <= 0.2)
        n_dropped += int(a.dropped.sum())
        assert a.ids[0] == 0 and not a.dropped[0]
    assert n_dropped > 50
    # pruned subtrees leave no segments: the output has no row of a dropped segment
    ids_last = rec["alloc"][14].ids[~rec["alloc"][14].dropped]
    assert tree.n == ids_last.size + int(rec["shoots"][14].built.sum())


# ------------------------------------------------------------------------------ shoots (D17)
def test_metamer_counts_lengths_and_cube(default_run):
    tree, rec = default_run
    total_shoots = 0
    for sh in rec["shoots"].values():
        np.testing.assert_array_equal(sh.planned, np.floor(sh.vigor))
        assert np.all(sh.planned >= 1) and np.all(sh.planned <= 3)
        np.testing.assert_array_equal(sh.built, sh.planned)  # far from the walls here
        assert np.all(sh.metamer_length >= 0.2) and np.all(sh.metamer_length < 0.4)
        np.testing.assert_allclose(sh.metamer_length, sh.vigor / sh.planned * 0.2, rtol=1e-15)
        total_shoots += sh.bearing.size
    assert total_shoots > 300
    L = tree.length[1:]
    assert L.min() >= 0.2 and L.max() < 0.4 and tree.length[0] == 0.2


def test_walls_stop_growth_inside_the_cube(ssm):
    # a 3.2 m cube: the tree hits the roof and the walls; growth stops there, not an error
    span = 3.2
    fewer = []

    def on_step(c, view):
        if view.shoots is not None:
            fewer.append(int((view.shoots.built < view.shoots.planned).sum()))
            assert np.all(view.shoots.built <= view.shoots.planned)

    t = ssm.simulate({"span": span, "max_iter": 16}, 2, on_step=on_step)
    s = t.start
    assert np.all(np.abs(s[:, :2]) <= span / 2 + 1e-12)
    assert np.all((s[:, 2] >= 0) & (s[:, 2] <= span + 1e-12))
    assert sum(fewer) > 0 and height(t) > span - 0.4


# ------------------------------------------------------------------------------ pipe (D18)
def test_pipe_model_exact_after_final_update(default_run):
    tree, rec = default_run
    n_exp = 2.6
    d = 2 * tree.radius
    st = rec["stubs"][14]
    W = np.bincount(tree.parent[1:], weights=d[1:] ** n_exp, minlength=tree.n)
    W += np.where(st["api_state"] == STUB, st["api_stub_w"], 0) ** n_exp
    W += np.where(st["lat_state"] == STUB, st["lat_stub_w"], 0) ** n_exp
    woody = np.bincount(tree.parent[1:], minlength=tree.n) + (st["api_state"] == STUB) + (st["lat_state"] == STUB)
    assert np.any(st["api_state"] == STUB) or np.any(st["lat_state"] == STUB)
    np.testing.assert_allclose(d[woody > 0] ** n_exp, W[woody > 0], rtol=1e-12)
    np.testing.assert_array_equal(d[woody == 0], 0.02)
    # width never decreases from tip to base
    assert np.all(d[tree.parent[1:]] >= d[1:])
    assert d[0] == d.max() and d[0] > 0.1


# ------------------------------------------------------------------------------ angles and frames
def test_branch_angle_phyllotaxis_and_vertical_trunk_without_turning(ssm):
    t = ssm.simulate({"max_iter": 9, "reorient": 0.0, "tropism": 0.0, **NO_NOISE, "branch_angle": 50.0}, 1)
    lat = np.flatnonzero(t.extras["is_lateral"])
    cosang = np.einsum("ij,ij->i", t.axis[lat], t.axis[t.parent[lat]])
    np.testing.assert_allclose(np.degrees(np.arccos(np.clip(cosang, -1, 1))), 50.0, atol=1e-9)
    trunk = t.branch == 0
    np.testing.assert_allclose(t.axis[trunk], np.tile([0, 0, 1.0], (trunk.sum(), 1)), atol=1e-12)
    # laterals on consecutive trunk segments differ by the phyllotaxis angle in azimuth
    lt = lat[trunk[t.parent[lat]]]
    pos = t.position_in_branch[t.parent[lt]]
    az = np.full(trunk.sum(), np.nan)
    az[pos] = np.degrees(np.arctan2(t.axis[lt, 1], t.axis[lt, 0]))
    turn = np.mod(np.diff(az), 360.0)
    turn = turn[np.isfinite(turn)]
    assert turn.size >= 3
    np.testing.assert_allclose(turn, 137.52, atol=1e-7)


def test_tropism_turns_branches_up(ssm):
    base = {"max_iter": 10, "reorient": 0.0, **NO_NOISE}
    lo = ssm.simulate({**base, "tropism": 0.0}, 1)
    hi = ssm.simulate({**base, "tropism": 0.25}, 1)
    mean_up = lambda t: float(t.axis[t.order >= 1, 2].mean())
    assert mean_up(hi) > mean_up(lo) + 0.1


# ------------------------------------------------------------------------------ output contract (D3)
def test_topology_invariants(default_run, ssm):
    tree, rec = default_run
    n = tree.n
    assert tree.parent[0] == -1 and np.count_nonzero(tree.parent < 0) == 1
    assert np.all(tree.parent[1:] < np.arange(1, n))
    assert np.max(np.abs(tree.end[tree.parent[1:]] - tree.start[1:])) < 1e-9
    assert np.max(np.abs(np.linalg.norm(tree.axis, axis=1) - 1)) < 1e-9
    assert tree.length.min() > 0 and tree.radius.min() > 0
    assert np.bincount(tree.extension[tree.extension >= 0], minlength=n).max() <= 1
    assert np.array_equal(np.unique(tree.branch), np.arange(tree.n_branches))
    is_lat = tree.extras["is_lateral"]
    np.testing.assert_array_equal(is_lat, rec["growth_lateral"][14])  # = first metamers of lateral shoots
    same = tree.branch[1:] == tree.branch[tree.parent[1:]]
    np.testing.assert_array_equal(same, ~is_lat[1:])
    np.testing.assert_array_equal(tree.order[1:], tree.order[tree.parent[1:]] + is_lat[1:])
    assert tree.order[0] == 0 and np.all(tree.order[tree.branch == 0] == 0)
    np.testing.assert_array_equal(tree.order, rec["order"][14])  # model's Gravelius order
    md = tree.metadata
    assert md["model"] == "sot" and md["status"] == "ok" and md["seed"] == 7 and md["cycles"] == 14
    assert md["params"]["max_iter"] == 14 and md["params"]["alpha1"] == 1.5
    assert tree.topology == "source" and tree.max_order >= 3
    # thickest mode: the thickest child continues each branch
    thick = SOT(order_mode="thickest").simulate({"max_iter": 14}, 7)
    np.testing.assert_array_equal(thick.start, tree.start)
    assert thick.topology == "thickest"
    ext = thick.extension
    has = np.flatnonzero(ext >= 0)
    r_max = np.zeros(n)
    np.maximum.at(r_max, thick.parent[1:], thick.radius[1:])
    np.testing.assert_array_equal(thick.radius[ext[has]], r_max[has])


# ------------------------------------------------------------------------------ D1, D2, D4
def test_determinism_and_seeds(ssm):
    a = ssm.simulate({"max_iter": 10}, 11)
    b = ssm.simulate({"max_iter": 10}, 11)
    for k in ("start", "axis", "length", "radius", "parent", "extension"):
        assert np.array_equal(getattr(a, k), getattr(b, k)), k
    c = ssm.simulate({"max_iter": 10}, 12)
    assert c.n != a.n or not np.array_equal(c.start, a.start)
    # no randomness at all: every seed gives the same tree
    quiet = {"max_iter": 10, "ran": 0.0, **NO_NOISE}
    q1, q2 = ssm.simulate(quiet, 1), ssm.simulate(quiet, 99)
    assert q1.equals(q2)
    # each noise source alone makes seeds differ
    for extra in (
        {"ran": 0.05},
        {"branch_angle_sd": 5.0},
        {"phyllotaxis_sd": 10.0},
        {"lambda_sd": 0.05},
        {"tropism_sd": 0.05},
    ):
        t1 = ssm.simulate({**quiet, **extra}, 1)
        t2 = ssm.simulate({**quiet, **extra}, 2)
        assert not t1.equals(t2), extra


def test_prefix_property(ssm):
    short = ssm.simulate({"max_iter": 9, "lambda_sd": 0.02, "tropism_sd": 0.02}, 5)
    snaps = {}
    ssm.simulate(
        {"max_iter": 12, "lambda_sd": 0.02, "tropism_sd": 0.02},
        5,
        on_step=lambda c, v: snaps.__setitem__(c, v.tree()) if c == 9 else None,
    )
    assert short.equals(snaps[9])


def test_taller_with_more_cycles(ssm):
    hs = {}
    for seed in (1, 2, 3):
        _, rec = run_recorded(ssm, {"max_iter": 16}, seed)
        h = np.array([rec["heights"][c] for c in range(1, 17)])
        assert np.all(np.diff(h) >= 0)
        hs[seed] = h
    mean = np.mean(list(hs.values()), axis=0)
    # docs/models.md B.4 / D.4: about 4.3 / 6.7 / 8.6 m at 8 / 12 / 16 cycles (+-25 % indicative)
    for c, target in ((8, 4.3), (12, 6.7), (16, 8.6)):
        assert abs(mean[c - 1] - target) < 0.25 * target


def test_apical_control_trend_with_constant_lambda(ssm):
    res = []
    for lam in (0.45, 0.55, 0.65):
        trees = [ssm.simulate({"max_iter": 12, "init_lambda": lam, "targ_lambda": lam}, s) for s in (1, 2)]
        res.append((np.mean([height(t) for t in trees]), np.mean([t.n for t in trees])))
    h, n = np.array(res).T
    assert np.all(np.diff(h) > 0.3)
    assert np.all(np.diff(n) < 0)


def test_clones_differ(ssm):
    def occupancy(t):
        f = np.linspace(0, 1, 5)
        pts = t.start[:, None, :] + f[None, :, None] * (t.length[:, None, None] * t.axis[:, None, :])
        return set(map(tuple, np.floor(pts.reshape(-1, 3) / 0.4).astype(np.int64).tolist()))

    occ = [occupancy(ssm.simulate({}, s)) for s in range(1, 6)]
    jac = [len(a & b) / len(a | b) for a, b in itertools.combinations(occ, 2)]
    assert np.mean(jac) < 0.5


# ------------------------------------------------------------------------------ failures (D5)
def test_too_many_segments_never_overshoots(ssm):
    capped = SOT(max_live_segments=300)
    with pytest.raises(bf.SimulationFailed) as ei:
        capped.simulate({"max_iter": 18}, 1)
    e = ei.value
    assert e.status == "too_many_segments"
    assert isinstance(e.tree, bf.Tree) and 0 < e.tree.n <= 300
    assert e.tree.metadata["status"] == "too_many_segments"
    # widths of the partial tree are updated (pipe model: base is the thickest)
    assert e.tree.radius[0] == e.tree.radius.max() > 0.01


def test_collapse_raises_with_partial_tree(ssm):
    with pytest.raises(bf.SimulationFailed) as ei:
        ssm.simulate({"alpha0": 0.0, "alpha1": 1.0, "shadow_a": 0.8, "shadow_b": 1.5, "max_iter": 12}, 1)
    assert ei.value.status == "collapsed"
    assert ei.value.tree is not None and ei.value.tree.n < 10


def test_sympodial_has_no_apical_continuation(ssm):
    # all vigor of apical buds is lost, so a sympodial tree needs weak apical control
    t = SOT(sympodial=True).simulate({"max_iter": 10, "init_lambda": 0.35, "targ_lambda": 0.35}, 1)
    # every non-root segment is the first metamer of a lateral shoot or continues one within a cycle
    age = t.extras["age"]
    ext_rows = np.flatnonzero(t.extension >= 0)
    assert np.all(age[t.extension[ext_rows]] == age[ext_rows])  # apical children only within a shoot
    assert t.n > 10


# ------------------------------------------------------------------------------ additions: stand shade, winding
def test_stand_shade_exposure_is_beer_lambert_below_the_top():
    f = LightField(12.0, 0.2, 6, 1.0, 0.5, 2.0, ran=0.0)
    stand = StandShade(SimpleNamespace(p={"stand_shade": 0.3}), None)  # the form's factor on the field
    stand.z_top = 5.0
    g = LightField(12.0, 0.2, 6, 1.0, 0.5, 2.0, ran=0.0, filters=[stand.transmission])
    pts = np.array([[0.1, 0.0, 1.0], [0.1, 0.0, 4.5], [0.1, 0.0, 5.0], [0.1, 0.0, 6.0]])
    for fld in (f, g):
        fld.cast(np.array([[0.0, 0.0, 7.0]]))
    e0, e1 = f.exposure(pts), g.exposure(pts)
    assert e1[0] == pytest.approx(e0[0] * math.exp(-0.3 * 4.0), rel=1e-14)
    assert e1[1] == pytest.approx(e0[1] * math.exp(-0.3 * 0.5), rel=1e-14)
    assert e1[2] == e0[2] and e1[3] == e0[3]  # at and above the top: open sky
    # the gradient now points up: light comes from above
    assert (
        g.gradient(np.array([[3.0, 3.0, 2.0]]), 0.32)[0, 2] > 0 == f.gradient(np.array([[3.0, 3.0, 2.0]]), 0.32)[0, 2]
    )


def test_stand_shade_raises_the_crown_and_keeps_trees_without_it(ssm):
    base = {"max_iter": 16}
    t0 = ssm.simulate(base, 1)
    assert _same_tree(t0, ssm.simulate({**base, "stand_shade": 0.0}, 1))
    lows = []
    for k in (0.0, 0.2, 0.5):
        t = ssm.simulate({**base, "stand_shade": k}, 1)
        h = height(t)
        mid = t.start + 0.5 * t.length[:, None] * t.axis
        lows.append(int(np.count_nonzero(mid[:, 2] < 0.5 * h)))  # segments in the lower half
    assert lows[0] > lows[1] > lows[2]


def test_gap_shade_exposure_falls_behind_the_stem_away_from_the_gap():
    f = LightField(12.0, 0.2, 6, 1.0, 0.5, 2.0, ran=0.0)
    gap = GapShade(SimpleNamespace(p={"gap_shade": 0.4, "gap_azimuth": 90.0}), None)  # gap towards +y
    g = LightField(12.0, 0.2, 6, 1.0, 0.5, 2.0, ran=0.0, filters=[gap.transmission])
    pts = np.array([[0.3, 2.0, 3.0], [0.3, 0.0, 3.0], [0.3, -1.0, 3.0], [-2.0, -2.5, 3.0]])
    for fld in (f, g):
        fld.cast(np.array([[0.0, 0.0, 4.0]]))
    e0, e1 = f.exposure(pts), g.exposure(pts)
    assert e1[0] == e0[0] and e1[1] == e0[1]  # on the gap's side of the stem base: open
    assert e1[2] == pytest.approx(e0[2] * math.exp(-0.4 * 1.0), rel=1e-14)
    assert e1[3] == pytest.approx(e0[3] * math.exp(-0.4 * 2.5), rel=1e-14)
    # the gradient points into the gap
    gy = g.gradient(np.array([[0.3, 0.0, 2.0]]), 0.32)[0]
    assert gy[1] > 0 and abs(gy[0]) < 1e-12


def test_gap_shade_grows_the_crown_into_the_gap_and_keeps_trees_without_it(ssm):
    base = {"max_iter": 16}
    t0 = ssm.simulate(base, 1)
    assert _same_tree(t0, ssm.simulate({**base, "gap_shade": 0.0, "gap_azimuth": 60.0}, 1))

    def offset(t):  # length-weighted horizontal centre of the branches, from the stem base
        b = t.order > 0
        mid = t.start[b, :2] + 0.5 * t.length[b, None] * t.axis[b, :2]
        return (mid * t.length[b, None]).sum(0) / t.length[b].sum() - t.start[0, :2]

    c0 = offset(t0)
    for az in (0.0, 90.0, -135.0):
        d = np.array([math.cos(math.radians(az)), math.sin(math.radians(az))])
        t = ssm.simulate({**base, "gap_shade": 1.0, "gap_azimuth": az}, 1)
        c = offset(t)
        assert c @ d > c0 @ d + 0.3, az  # the crown's centre moves at least 0.3 m into the gap
        stem = t.order == 0
        top = t.start[stem][-1, :2] + t.length[stem][-1] * t.axis[stem][-1, :2] - t.start[0, :2]
        assert top @ d > 0.1, az  # and the stem leans towards it


def _half_space(margin: float = 0.2):
    """A crown's space open towards +x only: 3 m of reach in the sectors from -90 to 90 deg, none
    elsewhere, from 1 m to the top at 6 m."""
    from bforest_core.envelope import CrownEnvelope

    reach = np.zeros((4, 8))
    reach[:, 2:6] = 3.0
    return CrownEnvelope(margin, 1.0, 6.0, np.zeros((5, 2)), reach)


def test_crown_space_gives_a_bud_outside_the_envelope_no_light():
    from bforest_sot.forms.envelope import CrownSpace

    env = _half_space()
    run = SimpleNamespace(p={"envelope_shade": 1.0}, settings=SimpleNamespace(crown_envelope=env.setting()))
    form = CrownSpace(run, None)  # before a cycle its stem is the stem base alone
    f = LightField(12.0, 0.2, 6, 1.0, 0.5, 2.0, ran=0.0)
    g = LightField(12.0, 0.2, 6, 1.0, 0.5, 2.0, ran=0.0, filters=[form.transmission])
    for fld in (f, g):
        fld.cast(np.array([[0.0, 0.0, 4.0]]))
    # inside; in the margin beyond the reach (half way); outside towards -x; above the top (no
    # lid: lit as the top band's reach below it)
    pts = np.array([[2.0, 0.5, 3.0], [3.1, 0.0, 3.0], [-1.0, 0.0, 3.0], [2.0, 0.0, 6.5]])
    e0, e1 = f.exposure(pts), g.exposure(pts)
    assert e0.min() > 0.3
    assert e1[0] == e0[0] and e1[1] == pytest.approx(0.5 * e0[1]) and e1[2] == 0.0 and e1[3] == e0[3]
    # half the neighbours' shade: half the light outside
    run.p["envelope_shade"] = 0.5
    assert g.exposure(pts)[2] == pytest.approx(0.5 * e0[2])
    # the light gradient at the envelope's edge points back into it
    assert g.gradient(np.array([[0.1, -0.3, 3.0]]), 0.32)[0][0] > 0


def test_crown_space_grows_the_crown_in_the_envelope_and_keeps_trees_without_it(ssm):
    env = _half_space()
    inside = bf.component("ssm", "sot", crown_envelope=env.setting())
    base = {"max_iter": 14}
    for seed in (1, 2):
        t0 = ssm.simulate(base, seed)
        # off by default: the setting alone, or the parameter alone, is the papers' tree draw for draw
        assert _same_tree(t0, inside.simulate(base, seed))
        assert _same_tree(t0, ssm.simulate({**base, "envelope_shade": 1.0}, seed))
        t = inside.simulate({**base, "envelope_shade": 1.0}, seed)
        pts0, pts = np.concatenate([t0.start, t0.end]), np.concatenate([t.start, t.end])
        # without it most of the crown lies outside the half space; with it nearly none: the shoots
        # of buds that got no light never grew, and a shoot grown out in one cycle was shed
        assert (~env.contains(pts0)).mean() > 0.5 and (~env.contains(pts)).mean() < 0.05
        # the crown's wood lies on the +x side of the stem base
        b = t.order > 0
        mid = t.start[b] + 0.5 * t.length[b, None] * t.axis[b]
        assert (mid[:, 0] * t.length[b]).sum() / t.length[b].sum() > 0.5
        assert _same_tree(t, inside.simulate({**base, "envelope_shade": 1.0}, seed))  # no draws of its own
    with pytest.raises(ValueError, match="envelope_shade"):
        inside.simulate({**base, "envelope_shade": 1.5}, 1)
    # what the report draws: the envelope the trees grew in, none when it shades nothing
    assert np.array_equal(inside.crown_space({"envelope_shade": 1.0}).reach, env.reach)
    assert inside.crown_space({}) is None and ssm.crown_space({"envelope_shade": 1.0}) is None


def _same_tree(a, b):
    return all(np.array_equal(getattr(a, k), getattr(b, k)) for k in ("start", "axis", "length", "radius", "parent"))


def test_heading_noise_winds_axes_and_stays_deterministic(ssm):
    base = {"max_iter": 12, **NO_NOISE}
    smooth = ssm.simulate(base, 1)
    assert _same_tree(smooth, ssm.simulate({**base, "heading_sd": 0.0}, 1))  # no draws without it
    wind = ssm.simulate({**base, "heading_sd": 8.0}, 1)
    assert _same_tree(wind, ssm.simulate({**base, "heading_sd": 8.0}, 1))
    assert not _same_tree(wind, ssm.simulate({**base, "heading_sd": 8.0}, 2))

    def turn(t):  # mean angle (deg) between a cylinder and its parent on the same branch
        child = np.flatnonzero((t.parent >= 0) & (t.branch == t.branch[np.maximum(t.parent, 0)]))
        c = np.einsum("ij,ij->i", t.axis[child], t.axis[t.parent[child]])
        return float(np.degrees(np.arccos(np.clip(c, -1, 1))).mean())

    assert turn(wind) > turn(smooth) + 3.0
    # the stem does not wind: without light-seeking it stays exactly vertical
    straight = ssm.simulate({**base, "heading_sd": 8.0, "reorient": 0.0}, 1)
    assert np.abs(straight.axis[straight.order == 0] - [0.0, 0.0, 1.0]).max() < 1e-9
    assert turn(straight) > 3.0


def test_cached_initial_field_gives_the_same_trees(ssm):
    """A seed seen before takes its initial light field from the cache and skips its uniforms
    (PCG64 advance): the tree is the one grown without the cache, and other seeds, ran or grid
    sizes are not served the wrong field."""
    import bforest_sot.light as light

    for params in ({"max_iter": 10}, {"max_iter": 10, "ran": 0.2}):
        light._INITIAL.clear()
        miss = ssm.simulate(params, 21)
        assert [k[0] for k in light._INITIAL] == [("sot", 21)]
        hit = ssm.simulate(params, 21)
        assert hit.equals(miss)
        # a hit that skipped the wrong number of draws would change every later random choice
        assert not ssm.simulate(params, 22).equals(miss)
    light._INITIAL.clear()
    a = ssm.simulate({"max_iter": 10, "ran": 0.2}, 21)
    b = ssm.simulate({"max_iter": 10, "ran": 0.0}, 21)  # same seed, another initial field
    assert len(light._INITIAL) == 2 and not a.equals(b)
    for seed in range(30, 36):
        ssm.simulate({"max_iter": 2}, seed)
    assert len(light._INITIAL) == light._INITIAL_KEEP


# ------------------------------------------------------------------------------ growth forms (additions)
#: the default tree at 14 cycles, recorded from the model before the growth forms were added
#: (seed: cylinders, branches, total length m, sum of radii m, sum of start heights m, sum of axis x)
DEFAULT_TREES = {
    1: (944, 360, 242.566928, 16.511129, 4472.327294, -79.893762),
    2: (1074, 412, 278.805355, 18.763092, 4833.032427, -33.109388),
}


def _digest(t):
    return (
        t.n,
        t.n_branches,
        round(float(t.length.sum()), 6),
        round(float(t.radius.sum()), 6),
        round(float(t.start[:, 2].sum()), 6),
        round(float(t.axis[:, 0].sum()), 6),
    )


@pytest.mark.parametrize("seed", [1, 2])
def test_growth_forms_off_leave_the_papers_tree_as_it_was(seed):
    # the options at their defaults draw nothing and add no node: the tree recorded before them
    off = {
        "leader_death": 0.0,
        "death_delay": 3.0,
        "short_shoot": 0.0,
        "stem_death": 1.0,
        "stem_guide": 0.0,
        "heading_sd": 0.0,
        "stand_shade": 0.0,
        "gap_shade": 0.0,
        "gap_azimuth": 45.0,
    }
    for ssm_, params in [(SOT(), {}), (SOT(buds_per_node=1, stem_path=[[0, 0, 0], [5, 0, 5]]), off)]:
        assert _digest(ssm_.simulate({"max_iter": 14, **params}, seed)) == DEFAULT_TREES[seed]


#: a tree whose geometry can be checked by hand: no noise, no light-seeking, no tropism
HAND = {
    "max_iter": 3,
    "phyllotaxis": 90.0,
    **NO_NOISE,
    "tropism": 0.0,
    "reorient": 0.0,
    "ran": 0.0,
    "init_lambda": 0.5,
    "targ_lambda": 0.5,
    "alpha0": 3.0,
    "max_grow": 4.0,
    "drop_thresh": 0.05,
    "branch_angle": 65.0,
}


def _nodes(t):
    """{cylinder: its lateral children} for cylinders bearing more than one child."""
    out = {}
    for i in range(t.n):
        kids = np.flatnonzero(t.parent == i)
        lat = [k for k in kids if t.axis[k] @ t.axis[i] < 0.99]
        if len(kids) > 1:
            out[i] = lat
    return out


def test_opposite_buds_grow_pairs_on_opposite_sides_decussate():
    t = SOT(buds_per_node=2).simulate(HAND, 1)
    nodes = _nodes(t)
    assert len(nodes) >= 3
    sides = []
    for i, lat in nodes.items():
        assert len(lat) == 2  # two laterals at every node
        a, b = t.axis[lat[0]], t.axis[lat[1]]
        for x in (a, b):  # each at the branch angle from its (vertical) bearing metamer
            assert math.degrees(math.acos(x @ t.axis[i])) == pytest.approx(65.0, abs=1e-9)
        ha, hb = a[:2] / np.linalg.norm(a[:2]), b[:2] / np.linalg.norm(b[:2])
        assert ha @ hb == pytest.approx(-1.0, abs=1e-9)  # opposite sides
        sides.append((t.start[i, 2], ha))
    sides.sort(key=lambda s: s[0])
    for (_, u), (_, v) in zip(sides, sides[1:]):  # successive pairs cross at 90 deg: decussate
        assert abs(u @ v) == pytest.approx(0.0, abs=1e-9)
    # one bud per node (the default) grows a single lateral per node
    assert all(len(lat) == 1 for lat in _nodes(SOT().simulate(HAND, 1)).values())


def test_whorl_of_three_buds_spreads_them_at_120_degrees():
    t = SOT(buds_per_node=3).simulate({**HAND, "alpha0": 5.0}, 1)
    nodes = _nodes(t)
    # buds whose share of the vigor is below one metamer stay buds; the others are 120 deg apart
    assert all(len(lat) <= 3 for lat in nodes.values()) and any(len(lat) == 3 for lat in nodes.values())
    for lat in nodes.values():
        h = [t.axis[k][:2] / np.linalg.norm(t.axis[k][:2]) for k in lat]
        for u, v in itertools.combinations(h, 2):
            assert u @ v == pytest.approx(-0.5, abs=1e-9)


def test_bud_nodes_keep_the_pipe_model_and_the_axis_share_of_lambda():
    p = {**HAND, "max_iter": 12, "drop_thresh": 0.2}
    t = SOT(buds_per_node=2).simulate(p, 3)
    assert np.isclose(t.length, 0.0).sum() == 0  # bud nodes are folded away
    n = p.get("pipe_exp", 2.6)
    own = (2 * t.radius) ** n
    kids = np.bincount(t.parent[1:], weights=own[1:], minlength=t.n)
    has = np.bincount(t.parent[1:], minlength=t.n) > 0
    # d^n = the children's sum, plus the stubs of shed branches where there are some
    assert np.all(own[has] >= kids[has] * (1 - 1e-12))
    assert np.mean(np.isclose(own[has], kids[has], rtol=1e-9)) > 0.8
    # with lambda = 1 every lateral bud of a node gets nothing, as with one bud per node
    solo = SOT(buds_per_node=2).simulate({**p, "init_lambda": 1.0, "targ_lambda": 1.0}, 3)
    assert solo.n_branches == 1


def test_short_shoots_grow_one_internode_and_never_grow_on():
    p = {**HAND, "max_iter": 8}
    node = SOT().parameter_spec("node_length").default

    def first_order(t):  # cylinders per first-order branch, and the highest order
        br = t.branches
        n = np.bincount(t.branch, minlength=len(br))
        return n[br.order == 1], int(br.order.max())

    for bpn in (1, 2):
        ssm = SOT(buds_per_node=bpn)
        n, top = first_order(ssm.simulate(p, 1))
        assert n.max() > 1 and top >= 2  # without: laterals grow on and branch
        # every lateral shoot a short shoot: one internode of node_length on the stem, nothing more
        t = ssm.simulate({**p, "short_shoot": 1.0}, 1)
        n, top = first_order(t)
        assert top == 1 and n.size > 0 and (n == 1).all()
        lat = t.order == 1
        assert np.allclose(t.length[lat], node), bpn
    # a probability draws per lateral shoot: seeds differ, a seed repeats; some shoots grow on
    a, b = (SOT().simulate({**p, "short_shoot": 0.5}, s) for s in (1, 2))
    assert _same_tree(a, SOT().simulate({**p, "short_shoot": 0.5}, 1)) and not _same_tree(a, b)
    n, _ = first_order(a)
    assert (n == 1).any() and (n > 1).any()
    # at 0 nothing is drawn: the tree without short shoots
    assert _same_tree(SOT().simulate(p, 1), SOT().simulate({**p, "short_shoot": 0.0}, 1))


def test_leader_death_makes_every_shoot_fork_after_its_delay():
    def continued(t):  # ages of straight continuations built in a later cycle than their parent
        c = np.flatnonzero(t.parent >= 0)
        straight = np.einsum("ij,ij->i", t.axis[c], t.axis[t.parent[c]]) > 0.99
        later = t.extras["age"][c] < t.extras["age"][t.parent[c]]
        return t.extras["age"][c[straight & later]]

    p = {**HAND, "max_iter": 8}
    ssm = SOT(buds_per_node=2)
    assert continued(ssm.simulate(p, 1)).size > 0
    # every apical bud dies: no axis goes on past the cycle that built it; the laterals take over
    forked = ssm.simulate({**p, "leader_death": 1.0}, 1)
    assert continued(forked).size == 0
    assert forked.n_branches > 1  # the laterals took over
    # from cycle death_delay + 1 on: continuations only from the cycles before (age = 8 - cycle)
    late = ssm.simulate({**p, "leader_death": 1.0, "death_delay": 4.0}, 1)
    assert continued(late).size > 0 and continued(late).min() >= 8 - 4
    # a probability draws per growing apical bud: seeds differ, a seed repeats
    a, b = (ssm.simulate({**p, "leader_death": 0.3}, s) for s in (1, 2))
    assert _same_tree(a, ssm.simulate({**p, "leader_death": 0.3}, 1)) and not _same_tree(a, b)
    # stem_death 0: the trunk goes on every cycle (a monopodial stem, Scarrone's model), every
    # branch forks; 1 is the tree without the setting, the same draws
    mono = ssm.simulate({**p, "leader_death": 1.0, "stem_death": 0.0}, 1)
    stem = mono.order == 0
    assert continued(mono).size > 0 and set(mono.extras["age"][stem]) == set(range(8))  # one metamer a cycle at least
    c = np.flatnonzero((mono.parent >= 0) & ~stem)
    straight = np.einsum("ij,ij->i", mono.axis[c], mono.axis[mono.parent[c]]) > 0.99
    assert not np.any(straight & (mono.extras["age"][c] < mono.extras["age"][mono.parent[c]]))  # branches fork
    assert height(mono) > height(forked) + 1.0
    assert _same_tree(a, ssm.simulate({**p, "leader_death": 0.3, "stem_death": 1.0}, 1))


@pytest.mark.parametrize("bpn", [1, 2])
def test_stem_guide_grows_the_stem_along_the_measured_path(bpn):
    # the path rises 1.5 m, leans 45 deg towards +x for 1 m and stands up again; with no
    # light-seeking or tropism the stem (the growth topology's order 0) runs on it: each cycle's
    # shoot heads for the path's point one shoot length beyond its arc length, so it cuts the
    # bend's corner by less than a shoot's length and its end sits on the path at its own length
    path = [[0, 0, 0], [0, 0, 1.5], [1, 0, 2.5], [1, 0, 30]]
    arc = np.r_[0.0, 1.5, 1.5 + np.sqrt(2.0), 29.0 + np.sqrt(2.0)]
    along = np.asarray(path, float)
    dense = np.stack([np.interp(np.linspace(0, arc[-1], 5000), arc, along[:, k]) for k in range(3)], 1)
    ssm = SOT(buds_per_node=bpn, stem_path=path)
    p = {**HAND, "max_iter": 12}

    def stem(t):
        c = np.flatnonzero(t.order == 0)
        ends, length = t.end[c], t.length[c].sum()
        on_path = np.array([np.interp(length, arc, along[:, k]) for k in range(3)])
        off = np.min(np.linalg.norm(ends[:, None, :] - dense[None], axis=2), axis=1).max()
        return ends, length, np.linalg.norm(ends[-1] - on_path), off

    ends, length, _, off = stem(ssm.simulate(p, 1))
    assert np.allclose(ends[:, :2], 0.0) and off == pytest.approx(1.0, abs=1e-3)  # the papers' model: straight up
    assert length > 3.5  # the stem goes past the bend
    ends, length2, end_off, off = stem(ssm.simulate({**p, "stem_guide": 1.0}, 1))
    assert length2 == pytest.approx(length, rel=0.05)  # the guide turns the stem; its growth stays
    assert end_off < 0.1 and off < 0.12  # on the path, within 12 cm of it everywhere
    assert ends[-1, 0] == pytest.approx(1.0, abs=0.01) and np.allclose(ends[:, 1], 0.0, atol=1e-9)
    # a share blends the stem's own target with the path's: further from it than the full guide
    assert off < stem(ssm.simulate({**p, "stem_guide": 0.5}, 1))[3] < 0.5
    # 0, or no path, is the tree without the guide, draw for draw; out of range names the parameter
    assert _same_tree(ssm.simulate(p, 1), SOT(buds_per_node=bpn).simulate({**p, "stem_guide": 0.0}, 1))
    assert _same_tree(ssm.simulate(p, 1), SOT(buds_per_node=bpn).simulate({**p, "stem_guide": 1.0}, 1))
    with pytest.raises(ValueError, match="stem_guide"):
        ssm.simulate({**p, "stem_guide": 1.5}, 1)
    # a path that gives no direction is refused when the settings are read, naming the setting
    nan = [[0, 0, 0], [0, 0, float("nan")]]
    for bad, says in (
        ([[0, 0, 0]], "2 distinct"),
        ([[0, 0, 1]] * 3, "2 distinct"),
        (nan, r"1\.2: Input should be a finite number"),
    ):
        with pytest.raises(bf.ConfigError, match=f"stem_path.*{says}"):
            bf.component("ssm", "sot", stem_path=bad)


# ------------------------------------------------------------------------------ compiled loops
# kernels.py replaces numpy loops of the growth cycle; each must give the numpy's bits, or the
# fits' trajectories (and the recorded trees) would change with the speed-up.


def test_frame_kernels_give_numpy_rotations_bit_for_bit():
    from bforest_sot.kernels import advance_frames, turn_geometry
    from bforest_sot.model import _norm, _unit, cross, rotate

    rng = np.random.default_rng(5)
    m = 301
    h = _unit(rng.normal(size=(m, 3)))
    u = _unit(cross(h, rng.normal(size=(m, 3))))
    target = rng.normal(size=(m, 3))
    target[8] = 2.0 * h[8]  # parallel: no turn
    tau = rng.uniform(0.0, 0.5, m)
    act = np.arange(0, m, 2)
    phi = rng.normal(size=act.size)
    for bend in (rng.normal(size=act.size) * 0.3, np.empty(0)):
        # the numpy of model._build_shoots before kernels.py
        ha, ua, ta = h[act], u[act], target[act]
        ax = cross(ha, ta)
        sn = _norm(ax)
        cs = np.einsum("ij,ij->i", ha, ta)
        ti = np.flatnonzero(sn > 1e-12)
        assert ti.size == act.size - 1
        th = tau[act][ti] * np.arctan2(sn[ti], cs[ti])
        ha[ti] = rotate(ha[ti], ax[ti] / sn[ti, None], th)
        ua[ti] = rotate(ua[ti], ax[ti] / sn[ti, None], th)
        ha = _unit(ha)
        if bend.size:
            ha = _unit(rotate(ha, ua, bend))
        ua = rotate(ua, ha, phi)
        ua = _unit(ua - np.einsum("ij,ij->i", ua, ha)[:, None] * ha)
        # the kernels
        h2, u2 = h.copy(), u.copy()
        kax, ksn, kcs = turn_geometry(h2, target, act)
        assert np.array_equal(kax, ax) and np.array_equal(ksn, sn) and np.array_equal(kcs, cs)
        kth = np.zeros(act.size)
        kth[ti] = th
        advance_frames(h2, u2, act, kax, ksn, kth, bend, phi)
        assert np.array_equal(h2[act], ha) and np.array_equal(u2[act], ua)
        rest = np.setdiff1d(np.arange(m), act)
        assert np.array_equal(h2[rest], h[rest]) and np.array_equal(u2[rest], u[rest])


def test_level_sums_and_shadow_sums_give_the_numpy_bits():
    from bforest_core.tree import group_by_level
    from bforest_sot.kernels import add_shadows, sum_levels

    # a random tree of 400 nodes: parent before child, each slot holding at most one child
    rng = np.random.default_rng(8)
    m = 400
    ac, lc = np.full(m, m), np.full(m, m)
    depth = np.zeros(m, np.int64)
    for c in range(1, m):
        while True:
            p = int(rng.integers(0, c))
            slot = ac if rng.random() < 0.5 else lc
            if slot[p] == m:
                slot[p] = c
                depth[c] = depth[p] + 1
                break
    base = rng.normal(size=(m + 1, 3))
    base[m] = 0.0
    base[::7, 2] = -1.0  # widths that fall back to d0n
    order, bounds = group_by_level(depth)
    V = np.zeros((m + 1, 3))
    for j in range(bounds.shape[0] - 2, -1, -1):  # the numpy of model.accumulate before kernels.py
        L = order[bounds[j] : bounds[j + 1]]
        x = base[L] + V[ac[L]] + V[lc[L]]
        x[x[:, 2] <= 0.0, 2] = 0.37
        V[L] = x
    assert np.array_equal(sum_levels(base, ac, lc, order, bounds, 0.37), V)

    # shadows of overlapping voxels: the bincount of light.py before kernels.py
    log = rng.normal(size=5000)
    off = np.array([0, 1, -1, 50, -50, 49, 51, 100, 2])
    wf = -rng.uniform(0.1, 2.0, off.size)
    base_v, cnt = np.unique(rng.integers(200, 4700, 300), return_counts=True)
    flat = (base_v[:, None] + off[None, :]).ravel()
    w = (cnt[:, None] * wf[None, :]).ravel()
    lo, hi = int(base_v[0] + off.min()), int(base_v[-1] + off.max()) + 1
    want = log.copy()
    want[lo:hi] += np.bincount(flat - lo, weights=w, minlength=hi - lo)
    acc = np.zeros(log.size)
    add_shadows(log, acc, base_v, cnt, off, wf)
    assert np.array_equal(log, want) and not acc.any()


def test_growth_forms_that_clash_are_refused():
    """Each form declares parameters and a stream of its own: a name twice or a shared key is refused."""
    from bforest_core.interfaces import ParameterSpec
    from bforest_sot.forms.base import GrowthForm

    class Twice(GrowthForm):
        parameters = (ParameterSpec("leader_death", 0.0, 0.0, 1.0),)

    class KeyA(GrowthForm):
        stream = 0x99

    class KeyB(GrowthForm):
        stream = 0x99

    for extra, says in (((Twice,), r"\['leader_death'\] named twice"), ((KeyA, KeyB), r"\[153\] shared")):
        model = type("Clash", (SOT,), {"name": "clash", "forms": SOT.forms + extra})
        with pytest.raises(ValueError, match=says):
            model().simulate({"max_iter": 2}, 1)


def test_crown_markers_fill_the_crowns_space_and_a_bud_whose_space_is_taken_gets_less_light():
    from bforest_sot.forms.markers import FREE_MARKERS, MARKERS, CrownMarkers

    env = _half_space()
    rng = np.random.default_rng(5)
    store = SimpleNamespace(n=0, start=np.zeros((0, 3)), length=np.zeros(0), h=np.zeros((0, 3)))
    run = SimpleNamespace(
        p={"space_claim": 1.0, "node_length": 0.2}, settings=SimpleNamespace(crown_envelope=env.setting()), s=store
    )
    form = CrownMarkers(run, rng)
    m = form.markers
    # the markers lie in the crown's space, from its base to its top, all of it (the +x half space)
    assert m.shape == (MARKERS, 3) and env.contains(m).all()
    assert m[:, 2].min() >= 1.0 and m[:, 2].max() <= 6.0 and m[:, 0].min() > -0.25 and m[:, 0].max() > 2.9
    # every marker free: full light in the space; below the crown base the form does nothing
    pts = np.array([[1.5, 0.0, 3.0], [1.5, 0.0, 0.5], [-2.0, 0.0, 3.0]])
    assert np.array_equal(form.transmission(pts)[:2], [1.0, 1.0])
    # a point far from any marker (behind the stem, outside the space) has none about it: no light
    assert form.transmission(pts)[2] == 0.0
    # a metamer ending at (1.5, 0, 3) claims the markers within 2 internodes (0.4 m) of its end
    store.n, store.start = 1, np.array([[1.5, 0.0, 2.9]])
    store.length, store.h = np.array([0.1]), np.array([[0.0, 0.0, 1.0]])
    form.begin_cycle(2)
    d_old = np.linalg.norm(m - [1.5, 0.0, 3.0], axis=1)
    d_new = np.linalg.norm(form.free - [1.5, 0.0, 3.0], axis=1)
    assert len(form.free) == (d_old > 0.4).sum() and d_new.min() > 0.4
    # a bud there perceives the markers within 4 internodes (0.8 m): the free ones only, up to FREE_MARKERS
    near = (d_new <= 0.8).sum()
    assert 0 < near and form.transmission(pts[:1])[0] == pytest.approx(min(near, FREE_MARKERS) / FREE_MARKERS)
    # a metamer that claimed every marker within the perception radius leaves the bud in shade
    store.n = 2
    store.start = np.vstack([store.start, [[1.5, -0.1, 3.0]]])
    store.length, store.h = np.array([0.1, 0.1]), np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0]])
    form.claim_r = 0.85  # (a larger claim than the form's: every marker the bud perceives)
    form.begin_cycle(3)
    assert form.transmission(pts[:1])[0] == 0.0
    run.p["space_claim"] = 0.25
    assert form.transmission(pts[:1])[0] == pytest.approx(0.75)  # the share space_claim of its light


def test_crown_markers_grow_trees_of_their_own_and_keep_trees_without_them(ssm):
    env = _half_space()
    inside = bf.component("ssm", "sot", crown_envelope=env.setting())
    base = {"max_iter": 14, "envelope_shade": 1.0}
    for seed in (1, 2):
        t0 = inside.simulate(base, seed)
        # off by default, or without a crown's space: the tree draw for draw
        assert _same_tree(t0, inside.simulate({**base, "space_claim": 0.0}, seed))
        assert _same_tree(ssm.simulate(base, seed), ssm.simulate({**base, "space_claim": 1.0}, seed))
        t = inside.simulate({**base, "space_claim": 1.0}, seed)
        assert not _same_tree(t0, t)
        # its markers come from a stream of their own: the same run seed, the same tree
        assert _same_tree(t, inside.simulate({**base, "space_claim": 1.0}, seed))
    with pytest.raises(ValueError, match="space_claim"):
        inside.simulate({**base, "space_claim": 1.5}, 1)


def test_crown_markers_in_a_space_of_no_volume_take_every_point_above_the_crown_base():
    from bforest_core.envelope import CrownEnvelope
    from bforest_sot.forms.markers import CrownMarkers

    # no reach and no margin about a leaning stem: no point of the box lies in the space
    env = CrownEnvelope(0.0, 1.0, 6.0, np.column_stack([np.linspace(0, 1, 5), np.zeros(5)]), np.zeros((4, 8)))
    run = SimpleNamespace(
        p={"space_claim": 0.5, "node_length": 0.2}, settings=SimpleNamespace(crown_envelope=env.setting())
    )
    form = CrownMarkers(run, np.random.default_rng(1))
    assert len(form.markers) == 0 and form.tree is None
    assert np.array_equal(form.transmission(np.array([[0.5, 0.0, 3.0], [0.0, 0.0, 0.5]])), [0.5, 1.0])


def test_crown_side_shades_the_side_the_crown_does_not_reach_and_not_the_stem():
    from bforest_sot.forms.side import CrownSide

    env = _half_space()  # open towards +x only, margin 0.2 m
    run = SimpleNamespace(
        p={"side_shade": 1.0, "node_length": 0.1}, settings=SimpleNamespace(crown_envelope=env.setting())
    )
    form = CrownSide(run, None)  # before a cycle its stem is the stem base alone: the upright line over it
    # the open side (3 m of reach) in full light, the side it does not reach in none, beside the
    # stem a share of the way (the margin, 0.2 m: w = 0.25 at 0.05 m), and the stem itself lit
    pts = np.array([[2.0, 0.0, 3.0], [-1.0, 0.0, 3.0], [-0.05, 0.0, 3.0], [0.0, 0.0, 3.0], [0.0, 2.0, 3.0]])
    # towards +y, the boundary between the reaching sectors (-90 .. 90 deg) and the others: half
    assert form.transmission(pts) == pytest.approx([1.0, 0.0, 0.75, 1.0, 0.5])
    run.p["side_shade"] = 0.5
    assert form.transmission(pts) == pytest.approx([1.0, 0.5, 0.875, 1.0, 0.75])
    # the light gradient beside the stem points to the open side
    f = LightField(12.0, 0.2, 6, 1.0, 0.5, 2.0, ran=0.0, filters=[form.transmission])
    assert f.gradient(np.array([[0.0, 0.3, 3.0]]), 0.1)[0][0] > 0


def test_crown_side_moves_the_crown_to_its_open_side_and_keeps_trees_without_it(ssm):
    env = _half_space(margin=3.0)  # a space wide enough not to stop the -x side by itself
    inside = bf.component("ssm", "sot", crown_envelope=env.setting())
    base = {"max_iter": 14, "envelope_shade": 1.0}

    def centre_x(t):
        b = t.order > 0
        mid = t.start[b] + 0.5 * t.length[b, None] * t.axis[b]
        return (mid[:, 0] * t.length[b]).sum() / t.length[b].sum()

    for seed in (1, 2):
        t0 = inside.simulate(base, seed)
        # off by default, or without a crown's space: the tree draw for draw
        assert _same_tree(t0, inside.simulate({**base, "side_shade": 0.0}, seed))
        assert _same_tree(ssm.simulate(base, seed), ssm.simulate({**base, "side_shade": 1.0}, seed))
        t = inside.simulate({**base, "side_shade": 1.0}, seed)
        assert centre_x(t) > centre_x(t0) + 0.15  # the crown's wood moves to its open side
        assert _same_tree(t, inside.simulate({**base, "side_shade": 1.0}, seed))  # no draws of its own
    with pytest.raises(ValueError, match="side_shade"):
        inside.simulate({**base, "side_shade": -0.1}, 1)
