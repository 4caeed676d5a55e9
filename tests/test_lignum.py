"""Tests of the simplified stochastic LIGNUM SSM (docs/models.md part A, sanity properties D).

Deliberately NOT asserted (docs/models.md D warns they are false): monotone taper along branches, trunk
radii never increasing upwards, crown radius <= R_env, the beta_max cap for order >= 2.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.special import ndtr

import bforest_core as bf
from bforest_lignum import model as LM
from bforest_lignum import params as LP
from bforest_lignum.shadow import q_max_of, shadow_brute, shadow_fast, voxel_coords

RNG = np.random.default_rng(12345)


def _ssm(**settings):
    return bf.component("ssm", "lignum", **settings)


@pytest.fixture(scope="module")
def ssm():
    return _ssm()


@pytest.fixture(scope="module")
def synth12():
    """sf_synthetic, T = 12, seed 1: output, per-year traces and on_step views."""
    views, trace = {}, []
    tree = _ssm().simulate({"years": 12}, seed=1, on_step=lambda t, v: views.__setitem__(t, v), trace=trace)
    return tree, trace, views


@pytest.fixture(scope="module")
def real32():
    """sf_real at its own T = 32 (Poisson partial shedding, T_sh = 12), seed 1, with traces."""
    trace = []
    tree = _ssm(preset="sf_real").simulate({}, seed=1, trace=trace)
    return tree, trace


def _arrays(tree):
    return (
        tree.start,
        tree.axis,
        tree.length,
        tree.radius,
        tree.parent,
        tree.extension,
        tree.extras["is_dead"],
        tree.extras["heartwood_radius"],
        tree.extras["foliage_mass"],
    )


def _same(a, b):
    return all(np.array_equal(x, y) for x, y in zip(_arrays(a), _arrays(b)))


def _height_crown(tree):
    e = tree.end
    return e[:, 2].max(), np.hypot(e[:, 0], e[:, 1]).max()


# ---------------------------------------------------------------------------- component, params
def test_component_parameters_and_presets(ssm):
    names = [p.name for p in ssm.parameters]
    for n in (
        "years",
        "radiation",
        "shadow_max",
        "shadow_len",
        "voxel_size",
        "r_env_mean",
        "r_env_sd",
        "lr_mean",
        "lr_sd",
        "q_mean",
        "q_sd",
        "beta_init",
        "beta_incr",
        "beta_max",
        "zeta_sd",
        "gamma_sd",
        "init_rot_angle",
        "whorl_rotation_sd",
        "shed_year",
        "shed_dist",
        "shed_mu",
        "foliage_per_area",
        "root_per_foliage",
        "root_senescence",
        "sapwood_senescence",
        "ss_start",
        "resp_foliage",
        "resp_sapwood",
        "resp_root",
        "heartwood_share",
        "wood_density",
        "photo_eff",
        "fl_threshold",
        "fl_min_buds",
        "min_len",
        "init_len",
        "pipe_coeff",
        "fol_threshold",
        "bud_table",
        "collision",
    ):
        assert n in names
    spec = {p.name: p for p in ssm.parameters}
    assert spec["years"].integer and spec["years"].default == 15
    assert spec["shadow_len"].unit == "m" and spec["shadow_len"].description.startswith("[S_L]")
    assert (spec["lr_mean"].default, spec["lr_sd"].default, spec["q_mean"].default) == (0.009, 0.001, 0.2)
    real = {p.name: p.default for p in _ssm(preset="sf_real").parameters}
    assert (real["shadow_max"], real["shadow_len"], real["years"], real["shed_dist"], real["bud_table"]) == (
        72.4,
        0.87,
        32,
        2,
        1,
    )
    assert {p.name: p.default for p in _ssm(preset="p98").parameters}["voxel_size"] == 0.01
    assert {p.name: p.default for p in _ssm(preset="s08").parameters}["pipe_coeff"] == 0.77
    assert {p.name: p.default for p in _ssm(preset="sf_test16").parameters}["shadow_len"] == 0.4
    for preset in LP.PRESETS:  # every preset's values lie in the plausible ranges
        for p in _ssm(preset=preset).parameters:
            assert p.lower <= p.default <= p.upper, (preset, p.name)
    with pytest.raises(bf.ConfigError, match="preset"):
        _ssm(preset="nope")


@pytest.mark.parametrize(
    "bad, name",
    [
        ({"lr_sd": -0.1}, "lr_sd"),
        ({"voxel_size": 0.0}, "voxel_size"),
        ({"shed_dist": 3}, "shed_dist"),
        ({"zeta_sd": -1}, "zeta_sd"),
        ({"years": 0}, "years"),
        ({"bud_table": "x"}, "bud_table"),
        ({"radiation": float("nan")}, "radiation"),
        ({"no_such_parameter": 1}, "no_such_parameter"),
    ],
)
def test_invalid_parameters_raise_value_error_naming_them(ssm, bad, name):
    with pytest.raises(ValueError, match=name):
        ssm.simulate(bad, seed=1)


def test_resolve_params_overrides_and_categoricals(ssm):
    p = ssm.resolve_params({"years": 7.4, "bud_table": "s08", "collision": True})
    assert p["years"] == 7 and isinstance(p["years"], int)
    assert p["bud_table"] == 1 and p["collision"] == 1 and p["radiation"] == 30.0
    p = ssm.resolve_params({"lr": (0.01, 0.002), "r_env": [1.0, 0.1]})
    assert (p["lr_mean"], p["lr_sd"], p["r_env_mean"], p["r_env_sd"]) == (0.01, 0.002, 1.0, 0.1)
    with pytest.raises(ValueError, match="'q'"):
        ssm.resolve_params({"q": 0.2})


# ---------------------------------------------------------------------------- helpers
def test_truncated_normal_inverse_cdf():
    u = RNG.random(200_000)
    m, s = 0.1, 0.1
    x = LM.tn_inverse_cdf(u, m, s)
    assert np.all(x >= 0) and np.all(np.isfinite(x))
    a = -m / s
    expected = m + s * (np.exp(-a * a / 2) / math.sqrt(2 * math.pi)) / (1 - ndtr(a))
    assert abs(x.mean() - expected) < 3e-3 * expected
    assert np.all(LM.tn_inverse_cdf(u[:10], 0.3, 0.0) == 0.3)
    ext = LM.tn_inverse_cdf(np.array([0.0, 1.0, 1 - 1e-17]), 0.2, 0.03)
    assert np.all(np.isfinite(ext)) and np.all(ext >= 0)
    # monotone in u (one uniform per value)
    xs = LM.tn_inverse_cdf(np.linspace(0.001, 0.999, 50), 0.009, 0.001)
    assert np.all(np.diff(xs) > 0)


def test_lateral_count_tables_and_foliage_survival():
    wf = np.array([0.07, 0.06, 0.031, 0.0102, 0.003, 0.0012, 0.0005, 0.0001])
    assert LM.lateral_count(wf, 0).tolist() == [7, 6, 6, 5, 3, 2, 1, 0]
    wf = np.array([0.006, 0.0045, 0.0031, 0.0025, 0.002, 0.0015, 0.0011, 0.0009])
    assert LM.lateral_count(wf, 1).tolist() == [7, 6, 5, 4, 3, 2, 1, 0]
    assert LM.foliage_survival(np.arange(8)).tolist() == [1, 0.9, 0.7, 0.5, 0.3, 0, 0, 0]


def test_rotation_is_right_handed():
    v = LM.rotate(np.array([[0.0, 0.0, 1.0]]), np.array([0.0, 1.0, 0.0]), math.pi / 2)
    assert np.allclose(v, [[1.0, 0.0, 0.0]])


# ---------------------------------------------------------------------------- shadow (D.7)
def test_q_max_rounding():
    assert q_max_of(0.4, 0.02) == 20
    assert q_max_of(0.55, 0.02) == 28
    assert q_max_of(0.87, 0.02) == 44


@pytest.mark.parametrize("n, spread, q", [(300, 20, 28), (800, 40, 44), (200, 6, 5), (50, 3, 2)])
def test_fast_shadow_equals_brute_force(n, spread, q):
    vox = RNG.integers(-spread, spread, size=(n, 3))
    vox[: n // 10] = vox[n // 10 : 2 * (n // 10)]  # several sources in one voxel
    fast = shadow_fast(vox, 7.3, q)
    brute = shadow_brute(vox, 7.3, q)
    assert np.array_equal(fast, brute)
    assert np.all(fast >= 0) and fast.max() > 0
    some = RNG.random(n) < 0.3  # receivers only at some points (all points cast shadow)
    for method in ("auto", "grid", "pairs", "two_tree", "sat"):
        assert np.array_equal(shadow_fast(vox, 7.3, q, method=method), brute)
        part = shadow_fast(vox, 7.3, q, receivers=some, method=method)
        assert np.array_equal(part[some], brute[some]) and np.all(np.isnan(part[~some]))


def test_fast_shadow_equals_brute_force_on_a_grown_crown(synth12):
    _, _, views = synth12
    v = views[12]
    mid = v.start + 0.5 * v.length[:, None] * v.axis
    vox = voxel_coords(mid, 0.02)
    brute = shadow_brute(vox, 10.0, 28)
    assert np.array_equal(shadow_fast(vox, 10.0, 28), brute)
    fol = v.foliage > 1e-5
    assert 0 < fol.sum() < fol.size
    assert np.array_equal(v.shadow[fol], brute[fol]) and np.all(np.isnan(v.shadow[~fol]))


def test_all_shadow_methods_on_a_grown_crown(synth12, monkeypatch):
    from bforest_lignum import shadow as SH

    _, _, views = synth12
    v = views[10]
    vox = voxel_coords(v.start + 0.5 * v.length[:, None] * v.axis, 0.02)
    fol = v.foliage > 1e-5
    ref = shadow_fast(vox, 10.0, 28, method="pairs")
    assert np.array_equal(shadow_fast(vox, 10.0, 28, receivers=fol, method="two_tree")[fol], ref[fol])
    monkeypatch.setattr(SH, "_SAT_CHUNK_CELLS", 20_000)  # many layer chunks
    assert np.array_equal(SH.shadow_fast(vox, 10.0, 28, method="sat"), ref)
    assert np.array_equal(SH.shadow_fast(vox, 10.0, 28, receivers=fol, method="grid")[fol], ref[fol])
    # the cost model prefers the compiled column scan for this sparse fine-voxel crown, the
    # integral images for a dense block of points in coarse voxels
    assert SH.choose_method(vox - vox.min(0), vox.shape[0], 28) == "grid"
    dense = RNG.integers(0, 12, size=(20_000, 3))
    assert SH.choose_method(dense, dense.shape[0], 10) == "sat"
    # its short cut (the grid at the most pairs there can be against the integral images) makes
    # the full model's choice: crowns sparse and dense, few receivers and all, deep and shallow pyramids
    cut = 0
    for k, (n, box, q) in enumerate(
        [(300, 400, 40), (2_000, 300, 37), (5_000, 200, 60), (20_000, 12, 10), (800, 30, 4)]
    ):
        pts = np.random.default_rng(k).integers(0, box, size=(n, 3))
        for n_rcv in (n // 10, n):
            sat = SH._sat_cost(pts, n_rcv, q)
            assert SH.choose_method(pts, n_rcv, q) == SH._cheapest(pts, n_rcv, q, sat), (n, box, q, n_rcv)
            cut += SH._grid_cost_bound(n, n_rcv, q) <= sat
    assert 0 < cut < 10  # the short cut was taken, and passed over
    with pytest.raises(ValueError, match="method"):
        shadow_fast(vox, 10.0, 28, method="kdtree")


def test_pyramid_geometry_exact_values():
    q = 28
    smax = 10.0
    for dz in (1, 5, 27):
        for dx, dy in ((0, 0), (dz, -dz), (dz, 0)):
            vox = np.array([[0, 0, 0], [dx, dy, dz]])
            assert shadow_fast(vox, smax, q)[0] == pytest.approx(smax * (1 - dz / q), rel=1e-15, abs=0)
            assert shadow_fast(vox, smax, q)[1] == 0.0  # no shade upwards
    outside = [[1, 0, 0], [0, 0, 28], [3, 0, 2], [0, -3, 2], [0, 0, 0]]
    for o in outside:
        assert shadow_fast(np.array([[0, 0, 0], o]), smax, q)[0] == 0.0
    # sources in one voxel add up; the lattice is origin-anchored (floor)
    assert shadow_fast(np.array([[0, 0, 0], [0, 0, 3], [0, 0, 3]]), smax, q)[0] == pytest.approx(
        2 * smax * (1 - 3 / q), rel=1e-15, abs=0
    )
    assert voxel_coords(np.array([[-0.001, 0.019, 0.02]]), 0.02).tolist() == [[-1, 0, 1]]


def test_light_lone_and_bare_segments():
    p = _ssm().resolve_params({})
    S, I, fL, P = LM.light(np.array([[0.0, 0.0, 0.25]]), np.array([0.01]), p)
    assert S[0] == 0 and I[0] == p["radiation"] and fL[0] == 1.0 and P == p["photo_eff"] * p["radiation"]
    mid = np.array([[0.0, 0.0, 0.25], [0.0, 0.0, 0.31]])  # voxel layers 12 and 15
    S, I, fL, P = LM.light(mid, np.array([1e-6, 0.01]), p)  # the lower one is bare (W_f <= 1e-5)
    assert I[0] == 0 and fL[0] == 0 and np.isnan(S[0])  # S is not evaluated at bare receivers
    S, I, fL, P = LM.light(mid, np.array([0.01, 1e-6]), p)  # a bare segment still casts shadow
    assert S[0] == pytest.approx(p["shadow_max"] * (1 - 3 / 28), rel=1e-15) and I[0] == p["radiation"] - S[0]
    assert I[1] == 0 and P == p["photo_eff"] * I[0]


def test_light_ranges_and_production_counts_only_foliage(synth12):
    _, trace, views = synth12
    for v in views.values():
        R = 30.0
        fol = v.foliage > 1e-5
        assert np.all(v.shadow[fol] >= 0) and np.all(np.isnan(v.shadow[~fol]))
        assert np.all((v.light >= 0) & (v.light <= R))
        assert np.all((v.f_L >= 0) & (v.f_L <= 1))
        assert np.all(v.light[v.foliage <= 1e-5] == 0)
        assert math.isclose(v.P, 0.001 * v.light.sum(), rel_tol=1e-12)
    assert views[1].f_L.tolist() == [1.0]  # the lone first segment


# ---------------------------------------------------------------------------- topology, output (D.3)
def test_output_table_invariants(synth12):
    tree, _, _ = synth12
    n = tree.n
    assert tree.parent[0] == -1 and np.sum(tree.parent < 0) == 1
    assert np.all(tree.parent[1:] < np.arange(1, n))
    assert np.all(tree.length > 0) and np.all(tree.radius > 0)
    assert np.all(np.abs(np.linalg.norm(tree.axis, axis=1) - 1) < 1e-9)
    assert np.max(np.abs(tree.end[tree.parent[1:]] - tree.start[1:])) < 1e-9
    ext = tree.extension[tree.extension >= 0]
    assert np.unique(ext).size == ext.size
    lat = tree.extras["is_lateral"]
    assert np.array_equal(tree.order[1:], tree.order[tree.parent[1:]] + lat[1:])
    assert np.all(tree.order[tree.branch == 0] == 0) and tree.order[0] == 0
    assert np.array_equal(np.unique(tree.branch), np.arange(tree.n_branches))
    assert np.array_equal(lat[1:], tree.branch[1:] != tree.branch[tree.parent[1:]])
    md = tree.metadata
    assert md["model"] == "lignum" and md["status"] == "ok" and md["seed"] == 1 and md["years"] == 12
    assert md["preset"] == "sf_synthetic" and md["params"]["q_mean"] == 0.2
    assert md["topology"] == "source" and md["segments_created"] >= n
    for k in ("is_dead", "age", "foliage_mass", "heartwood_radius"):
        assert tree.extras[k].shape == (n,)
    assert np.all(tree.end[:, 2] >= 0)  # D.14 ground


def test_thickest_order_mode():
    t_growth = _ssm().simulate({"years": 9}, seed=4)
    t_thick = _ssm(order_mode="thickest").simulate({"years": 9}, seed=4)
    assert t_thick.topology == "thickest"
    assert np.array_equal(t_growth.radius, t_thick.radius)
    assert np.array_equal(t_thick.extension, t_growth.with_topology("thickest").extension)


# ---------------------------------------------------------------------------- RNG (D.1, D.2)
def test_determinism_and_seeds(ssm):
    a = ssm.simulate({"years": 9}, seed=7)
    b = ssm.simulate({"years": 9}, seed=7)
    c = ssm.simulate({"years": 9}, seed=8)
    assert _same(a, b)
    assert not (a.n == c.n and _same(a, c))


def test_prefix_property(synth12, ssm):
    tree, _, views = synth12
    assert _same(views[12].tree(), tree)
    for t in (1, 5, 8):
        short = ssm.simulate({"years": t}, seed=1)
        assert _same(views[t].tree(), short)


def test_height_grows_with_years(synth12):
    _, _, views = synth12
    h = [views[t].tree().end[:, 2].max() for t in sorted(views)]
    assert np.all(np.diff(h) >= 0) and h[-1] > h[0]


def test_no_randomness_gives_identical_trees(ssm):
    quiet = {
        "years": 8,
        "zeta_sd": 0,
        "gamma_sd": 0,
        "lr_sd": 0,
        "q_sd": 0,
        "r_env_sd": 0,
        "whorl_rotation_sd": 0,
        "shed_dist": 0,
    }
    assert _same(ssm.simulate(quiet, seed=1), ssm.simulate(quiet, seed=99))


# ---------------------------------------------------------------------------- failures (D.5)
def test_negative_balance_failure(ssm):
    with pytest.raises(bf.SimulationFailed) as ei:
        ssm.simulate({"resp_foliage": 1.0, "photo_eff": 1e-4}, seed=1)
    assert ei.value.status == "negative_balance"
    assert isinstance(ei.value.tree, bf.Tree) and ei.value.tree.n == 1
    assert ei.value.tree.metadata["status"] == "negative_balance"


def test_too_many_segments_failure():
    with pytest.raises(bf.SimulationFailed) as ei:
        _ssm(max_live_segments=200).simulate({}, seed=1)
    assert ei.value.status == "too_many_segments"
    assert ei.value.tree.n > 200


def test_no_root_failure():
    ssm = _ssm(max_live_segments=10)
    sim = LM._Simulation(ssm.resolve_params({"years": 2}), 1, ssm.settings)
    sim._init()
    sim.st.deleted[:] = True
    with pytest.raises(LM._Failed) as ei:
        sim.to_tree("ok", 1)
    assert ei.value.status == "no_root"


def test_a_year_without_new_shoots_grows_only_wood(monkeypatch):
    """A year in which no bud makes a shoot (all dormant or killed) allocates nothing to shoots:
    the tree adds no segment and keeps its wood (np.bincount of no shoots is an integer array;
    the allocation used to fail on it with a casting error)."""
    short = _ssm().simulate({"years": 5}, seed=1)
    real = LM._Simulation._buds_to_shoots
    sizes = {}

    def no_shoots_after_year_4(self, live, fL, tr):
        s = real(self, live, fL, tr)
        sizes[len(sizes) + 1] = int(np.count_nonzero(~self.st.deleted))
        if len(sizes) <= 4:
            return s
        keep = np.zeros(s.par.size, dtype=bool)
        return LM._Shoots(s.prod[:0], s.par[keep], s.lat[keep], s.l0[keep], s.r0[keep], s.lr[keep], s.dirs[keep])

    monkeypatch.setattr(LM._Simulation, "_buds_to_shoots", no_shoots_after_year_4)
    tree = _ssm().simulate({"years": 8}, seed=1)
    assert tree.metadata["status"] == "ok"
    assert len(sizes) == 7 and sizes[5] == sizes[6] == sizes[7]
    assert tree.n <= short.n  # no new segment after year 4 (shedding may take some)
    assert tree.radius[0] >= short.radius[0]  # the stem keeps its wood (the pipe model asks no more)


# ---------------------------------------------------------------------------- carbon (D.8)
def test_carbon_balance_and_lambda(synth12):
    _, trace, _ = synth12
    assert len(trace) == 11
    lams = []
    for tr in trace:
        assert not tr.futile
        bal = tr.P - tr.M
        assert tr.lam > 0
        assert abs(tr.G_at_lam) <= 1e-8 * bal
        lams.append(tr.lam)
        d = tr.data
        # kept shoots have L = lambda * l0 exactly and were appended in shoot order
        kept = d["shoot_kept"]
        assert np.array_equal(d["shoot_L"], tr.lam * d["shoot_l0"])
        new = np.arange(d["r_before"].size, d["end_length"].size)
        assert np.array_equal(d["end_length"][new], d["shoot_L"][kept])
    assert lams[-1] > lams[0]  # lambda rises with sf_synthetic (P98)


def test_carbon_spent_equals_balance_from_state_changes(synth12):
    """Independent check: the mass actually added (new foliage, roots, new wood and the real
    radius increments of old segments) equals P - M in years where nothing was discarded."""
    _, trace, _ = synth12
    p = _ssm().resolve_params({})
    checked = 0
    for tr in trace:
        d = tr.data
        if not d["shoot_kept"].all() or d["ground_removed"].size:
            continue
        n_old = d["r_before"].size
        old = np.flatnonzero(d["old_live"])
        new = np.arange(n_old, d["end_radius"].size)
        r_new, L_new = d["end_radius"][new], d["end_length"][new]
        wf0 = p["foliage_per_area"] * 2 * np.pi * r_new * L_new
        wood_new = p["wood_density"] * np.sum(np.pi * r_new**2 * L_new)
        dA = np.pi * d["end_radius"][old] ** 2 - np.pi * d["r_before"][old] ** 2
        wood_old = p["wood_density"] * np.sum(d["end_length"][old] * dA)
        spent = (1 + p["root_per_foliage"]) * wf0.sum() + wood_new + wood_old
        assert spent == pytest.approx(tr.P - tr.M, rel=1e-9)
        checked += 1
    assert checked >= 5


# ---------------------------------------------------------------------------- pipe model (D.9)
def test_pipe_model_areas(synth12):
    _, trace, _ = synth12
    unclamped_total = 0
    for tr in trace:
        d = tr.data
        old = np.flatnonzero(d["old_live"] & ~np.isin(np.arange(d["B"].size), d["ground_removed"]))
        Areq = d["Ah"][old] + tr.lam**2 * d["B"][old] + d["C"][old]
        r, hw = d["end_radius"][old], d["end_hw"][old]
        unc = Areq >= d["A_before"][old]
        sap = np.pi * (r**2 - hw**2)
        target = tr.lam**2 * d["B"][old] + d["C"][old]
        np.testing.assert_allclose(sap[unc], target[unc], rtol=1e-12, atol=0)
        unclamped_total += unc.sum()
    assert unclamped_total > 1000


def test_pipe_sums_against_explicit_paths():
    """B and C of the level pass equal explicit path products over the tree (year 7)."""
    cp, xi, ss = 0.8, 0.6, 0.07  # an unusual pipe coefficient makes the link weights visible
    trace = []
    _ssm().simulate({"years": 8, "pipe_coeff": cp}, seed=1, trace=trace)
    d = trace[6].data
    n_old = d["B"].size
    parent, is_lat, live = d["end_parent"], d["end_is_lat"], d["old_live"]
    B = np.zeros(n_old)
    C = np.zeros(n_old)
    sp, sl, r0 = d["shoot_parent"], d["shoot_lat"], d["shoot_r0"]
    children = np.bincount(parent[1:n_old][live[1:n_old]], minlength=n_old)
    tip = live.copy()
    tip[children > 0] = False
    tip[sp] = False
    As = np.pi * (d["r_before"] ** 2 - d["hw_before"] ** 2)
    for s in range(sp.size):  # walk each new shoot's path to the root
        w = cp if sl[s] else 1.0
        i = sp[s]
        while i >= 0:
            B[i] += w * np.pi * r0[s] ** 2 * (1 - xi)
            w *= cp if is_lat[i] else 1.0
            i = parent[i]
    for t in np.flatnonzero(tip):
        w, i = 1.0, t
        val = (1 - ss) * As[t]  # ss_start = 0 and every old segment has age >= 1
        while i >= 0:
            C[i] += w * val
            w *= cp if is_lat[i] else 1.0
            i = parent[i]
    np.testing.assert_allclose(d["B"][live], B[live], rtol=1e-11)
    np.testing.assert_allclose(d["C"][live], C[live], rtol=1e-11)


def test_radii_and_heartwood_never_decrease(synth12):
    _, _, views = synth12
    prev = None
    for t in sorted(views):
        v = views[t]
        tree = v.tree()
        ids = tree.extras["segment_id"]
        assert np.all(v.heartwood_radius <= v.radius)
        if prev is not None:
            common, i_now, i_prev = np.intersect1d(ids, prev[0], return_indices=True)
            assert np.all(v.radius[i_now] >= prev[1][i_prev])
            assert np.all(v.heartwood_radius[i_now] >= prev[2][i_prev])
        prev = (ids, v.radius, v.heartwood_radius)
    assert views[12].radius[0] == views[12].radius.max()  # trunk base is thickest


def test_trunk_base_thickest_real(real32):
    tree, _ = real32
    assert tree.radius[0] == tree.radius.max()


# ---------------------------------------------------------------------------- angles (D.12)
def test_trunk_exactly_vertical(synth12):
    tree, _, _ = synth12
    trunk = tree.order == 0
    assert trunk.sum() >= 12
    assert np.all(tree.axis[trunk] == np.array([0.0, 0.0, 1.0]))
    assert np.all(tree.start[trunk, :2] == 0)


def test_new_laterals_at_beta_init(synth12):
    _, trace, _ = synth12
    n = 0
    for tr in trace:
        d = tr.data
        lat = d["shoot_lat"]
        ang = np.degrees(LM._angle(d["shoot_dir"][lat], d["shoot_parent_axis"][lat]))
        assert np.all(np.abs(ang - 35.0) < 1e-9)
        n += lat.sum()
    assert n > 500


def test_first_order_inclination_cap(synth12):
    tree, _, views = synth12
    bmax = 95.0
    worst = 0.0
    for v in views.values():
        tr = v.tree()
        o1 = tr.order == 1
        incl = np.degrees(np.arccos(np.clip(tr.axis[o1, 2], -1, 1)))
        assert np.all(incl <= bmax + 1e-9)
        worst = max(worst, incl.max(initial=0))
    assert worst >= bmax - 1e-9  # the cap is reached
    for seed in (2, 3, 4):
        tr = _ssm().simulate({"years": 12}, seed=seed)
        incl = np.degrees(np.arccos(np.clip(tr.axis[tr.order == 1, 2], -1, 1)))
        assert np.all(incl <= bmax + 1e-9) and incl.max() >= bmax - 1e-9


# ---------------------------------------------------------------------------- foliage (D.10)
def test_foliage_table(synth12):
    _, trace, _ = synth12
    for tr in trace:
        d = tr.data
        live = ~d["end_deleted"]
        wf, wf0, age = d["end_wf"][live], d["end_wf0"][live], d["end_age"][live]
        assert np.array_equal(wf, LM.foliage_survival(age) * wf0)
        assert np.all((wf >= 0) & (wf <= wf0))
        assert np.all(wf[age >= 5] == 0)
        assert np.all(wf[age == 1] == 0.9 * wf0[age == 1])


# ---------------------------------------------------------------------------- R_env (D.11)
def test_buds_beyond_r_env_do_not_grow():
    trace = []
    _ssm(preset="sf_test16").simulate({}, seed=2, trace=trace)
    killed = 0
    for tr in trace:
        d = tr.data
        act = d["bud_active"]
        assert np.all(d["bud_hdist"][act] <= d["bud_renv"][act])
        assert np.all(~act[d["bud_killed"]])
        killed += d["bud_killed"].sum()
    assert killed > 20
    renv = np.concatenate([tr.data["bud_renv"] for tr in trace])
    assert renv.std() > 0.1  # a TN draw per bud (sd 0.3)


# ---------------------------------------------------------------------------- shedding (D.13)
def _no_shedding_candidates(d, p):
    live = ~d["end_deleted"]
    parent, is_lat, axis_id = d["end_parent"], d["end_is_lat"], d["end_axis_id"]
    n = live.size
    idx = np.flatnonzero(live)
    nonroot = idx[parent[idx] >= 0]
    has_ext = np.zeros(n, bool)
    has_ext[parent[nonroot[~is_lat[nonroot]]]] = True
    lat_on_axis = np.zeros(n, bool)
    lat_on_axis[axis_id[parent[nonroot[is_lat[nonroot]]]]] = True
    bare_old_tip = (
        live
        & ~has_ext
        & (d["end_order"] >= 1)
        & ~d["end_dead"]
        & (d["end_wf"] < p["fol_threshold"])
        & (d["end_age"] >= p["shed_year"])
    )
    return not np.any(bare_old_tip & ~lat_on_axis[axis_id])


def test_full_shedding_removes_bare_axes(synth12):
    _, trace, _ = synth12
    p = _ssm().resolve_params({})
    shed_events = 0
    for tr in trace:
        assert _no_shedding_candidates(tr.data, p)
        assert not tr.data["end_dead"].any()  # shed_dist 0 leaves no remnants
        shed_events += sum(len(ax) for ax, _, _ in tr.data["shed"])
    assert shed_events > 10


def test_poisson_shedding_leaves_dead_remnants_at_order1_bases(real32):
    tree, trace = real32
    p = _ssm(preset="sf_real").resolve_params({})
    for tr in trace:
        assert _no_shedding_candidates(tr.data, p)
    dead = tree.extras["is_dead"]
    assert dead.sum() > 30
    assert np.all(tree.order[dead] == 1)
    par = tree.parent[dead]
    # a remnant starts at the base of its order-1 axis: its parent is dead on the same axis or
    # a live trunk segment, and nothing live continues it
    same_axis = ~tree.extras["is_lateral"][dead]
    assert np.all(dead[par[same_axis]])
    assert np.all((tree.order[par[~same_axis]] == 0) & ~dead[par[~same_axis]])
    ext = tree.extension[dead]
    assert np.all(dead[ext[ext >= 0]])
    assert np.all(tree.extras["foliage_mass"][dead] == 0)
    # magnitudes of docs/models.md A.10 (sf_real, T = 32): about 10 m, 2.3-2.5 k live, ~14 cm base
    h, _ = _height_crown(tree)
    assert 8.5 < h < 11.5 and 1800 < tree.n < 3200 and 0.11 < 2 * tree.radius[0] < 0.17


# ---------------------------------------------------------------------------- magnitudes (D.4, D.6)
def test_sf_synthetic_magnitudes(synth12):
    tree, _, _ = synth12
    h, crown = _height_crown(tree)
    assert 4.2 < h < 6.2  # docs/models.md D.4: ~5.2 m at T = 12
    assert 1000 < tree.n < 3500
    assert crown > 1.33  # bending swings segments beyond R_env (not asserted the other way)


def test_apical_dominance_trend(ssm):
    """D.6: mean H / crown radius rises with Q (sf_synthetic, T = 15; docs/models.md D.6: 2.4 / 3.6 / 5.7)."""
    ratios, heights, counts = [], [], []
    for q in (0.05, 0.20, 0.35):
        hc = []
        for seed in (1, 2, 3):
            tree = ssm.simulate({"q_mean": q}, seed=seed)
            h, c = _height_crown(tree)
            hc.append((h, c, tree.n))
        hc = np.array(hc)
        ratios.append(np.mean(hc[:, 0] / hc[:, 1]))
        heights.append(hc[:, 0].mean())
        counts.append(hc[:, 2].mean())
    assert ratios[0] < ratios[1] < ratios[2]
    assert heights[0] < heights[1] < heights[2]
    assert counts[0] > counts[1] > counts[2]
    for got, spec in zip(ratios, (2.4, 3.6, 5.7)):  # indicative, +-25 %
        assert abs(got - spec) < 0.25 * spec
    for got, spec in zip(heights, (4.2, 7.3, 11.8)):
        assert abs(got - spec) < 0.25 * spec


def test_collision_option_rejects_shoots(ssm):
    trace = []
    tree = ssm.simulate({"years": 9, "collision": 1}, seed=3, trace=trace)
    rejected = sum(int(tr.data["shoot_collided"].sum()) for tr in trace)
    for tr in trace:
        assert not np.any(tr.data["shoot_kept"] & tr.data["shoot_collided"])
    assert rejected > 0
    assert np.max(np.abs(tree.end[tree.parent[1:]] - tree.start[1:])) < 1e-9


def test_stand_shade_adds_its_shadow_below_the_top():
    p = _ssm().resolve_params({"stand_shade": 4.0})
    mid = np.array([[0.0, 0.0, 0.25], [0.0, 0.0, 3.0], [5.0, 5.0, 6.0]])
    wf = np.full(3, 0.01)
    S0, I0, _, _ = LM.light(mid, wf, {**p, "stand_shade": 0.0}, z_top=6.0)
    S, I, fL, P = LM.light(mid, wf, p, z_top=6.0)
    assert np.allclose(S - S0, 4.0 * np.array([5.75, 3.0, 0.0]), rtol=0, atol=1e-12)
    assert I[0] == max(0.0, p["radiation"] - S[0]) and I[2] == I0[2]
    assert P == pytest.approx(p["photo_eff"] * I.sum(), rel=1e-15)


def test_stand_shade_lifts_the_crown_and_is_off_by_default():
    ssm = _ssm(preset="sf_real")
    base = {"years": 22}
    t0 = ssm.simulate(base, seed=3)
    assert _same(t0, ssm.simulate({**base, "stand_shade": 0.0}, seed=3))
    low = []
    for k in (0.0, 8.0, 16.0):
        t = ssm.simulate({**base, "stand_shade": k}, seed=3)
        alive = ~np.asarray(t.extras["is_dead"], bool)
        h = float(t.end[:, 2].max())
        low.append(float(t.length[alive & (t.order >= 1) & (t.start[:, 2] < 0.4 * h)].sum()))
    assert low[0] > low[1] > low[2]


def test_crown_space_takes_the_light_outside_the_envelope_and_is_off_by_default():
    from bforest_core.envelope import CrownEnvelope

    reach = np.zeros((4, 8))
    reach[:, 2:6] = 3.0  # open towards +x only, from 0.5 m to the top at 3 m
    env = CrownEnvelope(0.1, 0.5, 3.0, np.zeros((5, 2)), reach)
    p = _ssm().resolve_params({"envelope_shade": 1.0})
    # inside; outside towards -x; above the top towards -x (outside) and towards +x (no lid: lit)
    mid = np.array([[1.0, 0.2, 1.0], [-1.0, 0.0, 1.0], [-1.0, 0.0, 4.0], [1.0, 0.0, 4.0]])
    _, I0, _, _ = LM.light(mid, np.full(4, 0.01), p)
    _, I, fL, _ = LM.light(mid, np.full(4, 0.01), p, space=env.light(mid))
    assert I[0] == I0[0] > 0 and I[1] == 0.0 == I[2] and fL[1] == 0.0  # no light, so its buds stay dormant
    assert I[3] == I0[3] > 0
    inside = _ssm(crown_envelope=env.setting())
    base = {"years": 12}
    t0 = _ssm().simulate(base, seed=3)
    assert _same(t0, inside.simulate(base, seed=3))  # the setting alone: the papers' tree, draw for draw
    assert _same(t0, _ssm().simulate({**base, "envelope_shade": 1.0}, seed=3))  # and the parameter alone
    t = inside.simulate({**base, "envelope_shade": 1.0}, seed=3)
    pts0, pts = np.concatenate([t0.start, t0.end]), np.concatenate([t.start, t.end])
    assert (~env.contains(pts0)).mean() > 0.4 and (~env.contains(pts)).mean() < 0.2
    b = t.order > 0
    mid = t.start[b] + 0.5 * t.length[b, None] * t.axis[b]
    assert (mid[:, 0] * t.length[b]).sum() / t.length[b].sum() > 0.4  # the crown on the +x side
    assert t.end[:, 2].max() > 3.0 + 0.1 + 1.0  # no lid: the leader grows above the envelope's top
    assert inside.crown_space({"envelope_shade": 1.0}).reach.shape == (4, 8)
    assert inside.crown_space({}) is None and _ssm().crown_space({"envelope_shade": 1.0}) is None
    with pytest.raises(ValueError, match="envelope_shade"):
        inside.simulate({**base, "envelope_shade": 2.0}, seed=3)


def test_render_pieces_on_a_hand_built_table():
    # a vertical stem segment (1 m) and a lateral (0.35 m along +x) from its end
    start = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    axis = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    length = np.array([1.0, 0.35])
    parent = np.array([-1, 0])
    ext = np.array([-1, -1])
    order = np.array([0, 1])
    for wind in (0.0, 25.0):
        s, a, ln, par, ex, keep = LM.render_pieces(
            start, axis, length, parent, ext, order, 0.1, wind, np.random.default_rng(5)
        )
        assert keep.tolist() == [0] * 10 + [1] * 4  # ceil(1/0.1) and ceil(0.35/0.1)
        assert par.tolist() == [-1] + list(range(9)) + [9, 10, 11, 12]
        assert ex.tolist() == list(range(1, 10)) + [-1, 11, 12, 13, -1]
        end = s + a * ln[:, None]
        assert np.allclose(end[:-1][par[1:]], s[1:][par[1:] >= 0], atol=1e-12)  # pieces chain up
        assert np.allclose(end[9], [0, 0, 1], atol=1e-12) and np.allclose(end[13], [0.35, 0, 1], atol=1e-12)
        assert np.allclose(a[:10], [0, 0, 1]) and np.allclose(ln[:10], 0.1)  # the stem never winds
        turns = np.degrees(np.arccos(np.clip(a[10:] @ [1.0, 0.0, 0.0], -1, 1)))
        if wind == 0:
            assert np.allclose(ln[10:], 0.0875) and np.allclose(turns, 0, atol=1e-6)
        else:
            assert turns.min() > 0.5 and ln[10:].sum() > 0.35


def test_pieces_are_output_only_reproducible_and_off_by_default():
    ssm, pieces = _ssm(preset="sf_real"), _ssm(preset="sf_real", piece_length=0.12)  # a setting: output only
    base = {"years": 16}
    t0 = ssm.simulate(base, seed=3)
    assert _same(t0, ssm.simulate({**base, "wind_sd": 30.0}, seed=3))
    straight = pieces.simulate(base, seed=3)
    wound = pieces.simulate({**base, "wind_sd": 20.0}, seed=3)
    assert _same(wound, pieces.simulate({**base, "wind_sd": 20.0}, seed=3))
    assert not _same(wound, pieces.simulate({**base, "wind_sd": 20.0}, seed=4))
    with pytest.raises(bf.ConfigError, match="piece_length"):
        _ssm(piece_length=-0.1)
    with pytest.raises(ValueError, match="unknown parameter.*piece_length"):
        ssm.simulate({**base, "piece_length": 0.12}, seed=3)
    ends0 = np.round(t0.end, 9)
    for t in (straight, wound):
        assert t.n > 1.5 * t0.n and t.n_branches == t0.n_branches and t.max_order == t0.max_order
        # the growth is unchanged: every segment's end point is the end of its last piece
        got = {tuple(r) for r in np.round(t.end, 9)}
        assert {tuple(r) for r in ends0} <= got
        assert np.isclose(t.end[:, 2].max(), t0.end[:, 2].max(), rtol=0, atol=1e-9)
    assert straight.length.max() <= 0.12 + 1e-12
    assert math.isclose(straight.length.sum(), t0.length.sum(), rel_tol=1e-12)
    assert wound.length.sum() > straight.length.sum()
    assert np.allclose(wound.axis[wound.order == 0], straight.axis[straight.order == 0], rtol=0, atol=1e-12)
    assert not np.allclose(wound.axis[wound.order > 0], straight.axis[straight.order > 0], atol=1e-3)


def test_a_years_weather_is_off_by_default_and_varies_the_leaders_steps():
    """year_sd: 0 gives the tree draw for draw; above 0 each year's production gets a factor of
    mean 1 from a stream of its own (the same factors for a seed, other ones for another), and
    the leader's yearly shoots, the steps between the stem's whorls, vary more."""
    ssm = _ssm(preset="sf_real")
    base = {"years": 20}
    t0 = ssm.simulate(base, seed=3)
    assert _same(t0, ssm.simulate({**base, "year_sd": 0.0}, seed=3))
    f = LM.year_factors(3, 5000, 0.3)
    assert abs(f.mean() - 1.0) < 0.02 and abs(np.log(f).std() - 0.3) < 0.01
    assert np.array_equal(f[:21], LM.year_factors(3, 20, 0.3)) and not np.array_equal(f, LM.year_factors(4, 5000, 0.3))
    assert np.array_equal(LM.year_factors(3, 20, 0.0), np.ones(21))

    def step_cv(tree):
        born = np.asarray(tree.extras["birth_year"])
        stem = (tree.order == 0) & (born >= 3)  # the leader's yearly shoots, past the first years
        steps = np.bincount(born[stem], weights=tree.length[stem])[3:]
        steps = steps[steps > 0]
        return steps.std() / steps.mean()

    calm = [step_cv(ssm.simulate(base, seed=s)) for s in (1, 2, 3)]
    windy = [step_cv(ssm.simulate({**base, "year_sd": 0.4}, seed=s)) for s in (1, 2, 3)]
    assert np.mean(windy) > 1.5 * np.mean(calm), (calm, windy)
    with pytest.raises(ValueError, match="year_sd"):
        ssm.simulate({**base, "year_sd": -0.1}, seed=3)


def test_max_laterals_caps_the_branches_of_a_whorl_and_is_off_at_seven():
    """max_laterals: 7 (the tables' most) gives the tree draw for draw; 3 caps every bud's laterals,
    so no whorl of the stem holds more than 3 first-order branches, and the whorls stay one a year."""
    from bforest_core.metrics import whorls

    ssm = _ssm(preset="sf_real")
    base = {"years": 20}
    t0 = ssm.simulate(base, seed=3)
    assert _same(t0, ssm.simulate({**base, "max_laterals": 7}, seed=3))
    assert max(g.size for g in whorls(t0, min_diameter=0.0)) > 3  # the tables give vigorous buds more
    capped = ssm.simulate({**base, "max_laterals": 3}, seed=3)
    groups = whorls(capped, min_diameter=0.0)
    assert max(g.size for g in groups) == 3 and len(groups) == 19
    with pytest.raises(ValueError, match="max_laterals"):
        ssm.simulate({**base, "max_laterals": 0}, seed=3)
