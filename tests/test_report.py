"""Run report, figures and distance profiles: rendered headlessly from small real runs."""

import json
import shutil
import struct
from pathlib import Path

import numpy as np
import pytest

import bforest_core as bf
from bforest_core.errors import ConfigError
from bforest_core.interfaces import Posterior
from bforest_core.pipeline.clones import clones as grow_clones
from bforest_core.pipeline.profile import profile, profile_values
from bforest_core.pipeline.store import RunStore
from bforest_core.report import canvas, comparison, convergence, datasets, posterior, trees, write_report
from bforest_core.report.datasets import distance_view
from bforest_core.report.run_view import RunView
from conftest import hand_tree, toy_config

SECTIONS = [
    "# Bayes Forest run report",
    "## Target",
    "## Model and method",
    "## Parameters",
    "## Fit result",
    "## Optimiser",
    "## Evaluations and run time",
    "## Clones",
    "## Notes",
]


def png_size(path: Path) -> tuple[int, int]:
    """Width and height from a PNG's IHDR chunk; asserts the file is a PNG."""
    data = Path(path).read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n", f"{path} is not a PNG"
    assert data[12:16] == b"IHDR"
    return struct.unpack(">II", data[16:24])


def assert_png(path: Path, min_w: int = 300, min_h: int = 200) -> None:
    path = Path(path)
    assert path.exists(), f"{path} missing"
    w, h = png_size(path)
    assert min_w <= w <= 6000 and min_h <= h <= 6000, (path.name, w, h)
    assert 5_000 < path.stat().st_size < 5_000_000, (path.name, path.stat().st_size)


def _toy_run(tmp: Path, budget: int = 24, fail_above: float | None = None) -> Path:
    tmp.mkdir(parents=True, exist_ok=True)
    cfg = toy_config(tmp, budget=budget)
    if fail_above is not None:  # the toy SSM fails ("collapsed") above this angle
        cfg.write_text(cfg.read_text().replace('kind = "toy"\n', f'kind = "toy"\nfail_above = {fail_above}\n', 1))
    bf.fit(bf.load_config(cfg), tmp / "run", progress=False)
    return tmp / "run"


@pytest.fixture(scope="module")
def toy_runs(toy_plugin, tmp_path_factory):
    """Two toy fits: one with 4 clones, one without."""
    base = tmp_path_factory.mktemp("report")
    with_clones = _toy_run(base / "a")
    grow_clones(with_clones, n=4, progress=False)
    without = _toy_run(base / "b", fail_above=60.0)
    return with_clones, without


# ---------------------------------------------------------------------------------- report
def test_report_of_a_run_with_clones(toy_runs):
    run, _ = toy_runs
    md = write_report(run, strict=True)
    text = md.read_text()
    pos = [text.find(s) for s in SECTIONS]
    assert all(p >= 0 for p in pos) and pos == sorted(pos), pos
    for name in ("trees", "set_L", "convergence", "parameters", "clones", "clone_metrics"):
        assert_png(run / "figures" / f"{name}.png")
        assert f"](figures/{name}.png)" in text
    best = json.loads((run / "best.json").read_text())
    store = RunStore.open(run)
    n = store.count()
    assert f"{n} evaluations; {n} ok, 0 failed." in text
    # parameters table: free bounds and the best values; the fixed one with its value
    # the target was grown by the toy model with angle 30 and segments 12: the true values beside the best
    assert f"| angle | free | 5 | 80 | {best['params']['angle']:.4g} | 30 | deg |" in text
    assert "| noise | fixed |  |  | 2 |  | deg |" in text
    assert f"| L | 1 | {best['per_set']['L']:.4g} | 12 | 12 |" in text
    assert "4 of 4 clones grown." in text and "No clones yet" not in text
    # html: every figure inline once
    html = (run / "report.html").read_text()
    assert html.count('src="data:image/png;base64,') == text.count("](figures/")
    assert "<table>" in html and "<h2>Clones</h2>" in html


def test_report_of_a_run_without_clones(toy_runs):
    _, run = toy_runs
    text = write_report(run, strict=True).read_text()
    assert all(s in text for s in SECTIONS)
    assert "No clones yet: grow them with `bforest clones" in text
    assert not (run / "figures" / "clones.png").exists()
    assert_png(run / "figures" / "trees.png")
    assert_png(run / "figures" / "convergence.png")
    # failures are counted by status, with an example message
    evs = RunStore.open(run).evaluations()
    n_fail = sum(e.status == "collapsed" for e in evs)
    assert 0 < n_fail < len(evs)
    assert f"{len(evs)} evaluations; {len(evs) - n_fail} ok, {n_fail} failed." in text
    assert (
        f"| collapsed | {n_fail} | {100 * n_fail / len(evs):.1f} % | simulation failed (collapsed): angle too large |"
        in text
    )


def test_report_of_an_unfinished_run_and_text_only(toy_plugin, tmp_path):
    run = _toy_run(tmp_path, budget=16)
    (run / "best.json").unlink()
    text = write_report(run, figures=False, html=False).read_text()
    assert "the fit has not finished; 16 evaluations logged, best distance so far" in text
    assert "no best.json" in text and "figures were not drawn" in text
    assert not (run / "report.html").exists()
    assert not list((run / "figures").glob("*.png"))


def test_report_draws_the_same_figures_in_one_or_two_processes(toy_runs, tmp_path, monkeypatch):
    """On two cores the data-set figures are drawn in a second (spawned) process; the report
    lists the same figures as when one process draws them all, and a second process that fails
    leaves a note and the figures drawn in the first."""
    import re

    from bforest_core.report import build

    run = tmp_path / "run"
    shutil.copytree(toy_runs[0], run)
    figs = lambda text: re.findall(r"\]\((figures/[^)]+\.png)\)", text)  # noqa: E731

    monkeypatch.setattr(build, "_cores", lambda: 1)
    one = figs(write_report(run, strict=True).read_text())
    monkeypatch.setattr(build, "_cores", lambda: 2)
    two_text = write_report(run, strict=True).read_text()
    assert one == figs(two_text) and "figures/set_L.png" in one
    assert "second report process" not in two_text

    class Broken(build._SideProcess):
        def __init__(self, *a, **k):
            super().__init__(*a, **k)
            self.stop()  # it dies before it sends its figures

    monkeypatch.setattr(build, "_SideProcess", Broken)
    (run / "figures" / "set_L.png").unlink()
    text = write_report(run).read_text()
    assert figs(text) == one and "the second report process failed (it ended (exit code -9) before it sent" in text
    assert_png(run / "figures" / "set_L.png")


def test_report_when_the_config_no_longer_validates(toy_runs, tmp_path):
    """A run whose plugin is gone still gets a report from what the run directory holds."""
    run = tmp_path / "run"
    shutil.copytree(toy_runs[1], run)
    cfg = run / "config.toml"
    cfg.write_text(cfg.read_text().replace('kind = "toy-random"', 'kind = "uninstalled-optimizer"'))
    text = write_report(run, strict=True).read_text()
    assert "config.toml does not validate with the installed plugins" in text
    assert "| optimizer | `uninstalled-optimizer` |" in text
    assert_png(run / "figures" / "convergence.png")
    assert_png(run / "figures" / "trees.png")  # from target.txt alone (no model to regrow the best fit)


def test_figures_match_the_fit(toy_runs):
    """The best-fit tree of the figures is the tree the fit scored (same data sets, same D)."""
    run, _ = toy_runs
    v = RunView(run)
    best = json.loads((run / "best.json").read_text())
    assert v.best_tree_source == "" and v.best_tree is not None and v.best_tree_source == "regrown"
    feats, dist = v.worker_parts
    per_set = dist.compute_per_set(v.U_model, v.U_data)
    assert per_set["L"] == pytest.approx(best["per_set"]["L"], abs=1e-12)


# ---------------------------------------------------------------------------------- profile
def test_profile_passes_through_the_best_fit(toy_runs):
    run, _ = toy_runs
    best = json.loads((run / "best.json").read_text())
    res = profile(run, "angle", seeds=3, n=5)
    v = res["values"]
    assert v.size == 6 and best["params"]["angle"] in v  # 5 spread values + the best fit
    assert res["distances"].shape == (6, 3) and (res["status"] == "ok").all()
    i = int(np.flatnonzero(v == best["params"]["angle"])[0])
    # seed 0 is the fit's own model seed: the same distance as the fit at the best point
    assert res["distances"][i, 0] == pytest.approx(best["distance"], abs=1e-12)
    # the toy target was grown at angle 30: the median profile is lowest near it
    med = np.median(res["distances"], axis=1)
    assert abs(v[np.argmin(med)] - 30) < 20 and med[0] > med[i] and med[-1] > med[i]
    assert_png(comparison.write_profile_figure(res))
    rows = res["csv"].read_text().splitlines()
    assert rows[0].startswith("value_deg,seed,distance,status,D[L]") and len(rows) == 1 + 18  # the unit in the header
    assert "<- best fit" in res["table_text"]
    # the report includes the profile figure
    assert "](figures/profile_angle.png)" in write_report(run, figures=False).read_text()


def test_profile_integer_values_and_errors(toy_runs):
    run, _ = toy_runs
    res = profile(run, "segments", values=[4.2, 8, 7.6], seeds=2)
    assert res["values"].tolist() == [4.0, 8.0]
    with pytest.raises(ConfigError, match="not a parameter of SSM 'toy' .*known: angle, segments"):
        profile(run, "nope", seeds=2)
    with pytest.raises(ConfigError, match="outside the model's allowed range"):
        profile(run, "angle", values=[100.0], seeds=2)
    assert profile_values(0, 1, 3).tolist() == [0, 0.5, 1]
    assert profile_values(2, 6, 3, integer=True, include=3.4).tolist() == [2, 3, 4, 6]


# ---------------------------------------------------------------------------------- plotting units
def test_plot_tree_widths_colours_and_depth_order():
    tree = hand_tree()
    fig = canvas.new_figure(4, 4)
    ax = fig.subplots()
    lc = trees.plot_tree(ax, tree, "xz", lw_max=4.0, lw_min=0.5)
    segs = np.asarray(lc.get_segments())
    assert segs.shape == (tree.n, 2, 2)
    _, perm = trees.tree_segments(tree, "xz")
    # far-to-near along the viewing direction (+y points away in the XZ view)
    mid_y = 0.5 * (tree.start[perm, 1] + tree.end[perm, 1])
    assert np.all(np.diff(-mid_y) >= 0)
    # segment k is cylinder perm[k], base at the origin
    assert np.allclose(segs[:, 0, 0], tree.start[perm, 0] - tree.start[0, 0])
    assert np.allclose(segs[:, 1, 1], tree.end[perm, 2] - tree.start[0, 2])
    # widths proportional to radius (thickest = lw_max), floored
    lw = np.asarray(lc.get_linewidths())
    assert np.allclose(lw, np.maximum(0.5, 4.0 * tree.radius[perm] / 0.20))
    cols = lc.get_colors()
    from matplotlib.colors import to_rgba

    assert np.allclose(cols, [to_rgba(canvas.ORDER_COLORS[o]) for o in tree.order[perm]])
    assert ax.get_xlabel() == "x (m)" and ax.get_ylabel() == "z (m)"
    assert trees.radius_linewidths(np.array([0.001, 0.1, 0.2]), 4.0, 0.3).tolist() == [0.3, 2.0, 4.0]
    with pytest.raises(ValueError, match="view must be one of"):
        trees.tree_segments(tree, "zz")


def test_save_tree_figure_and_clones_figure(tmp_path):
    tree = hand_tree()
    assert_png(trees.save_tree_figure(tree, tmp_path / "t.png", title="hand tree"))
    clones = [(f"clone {i}", tree.translated([0.1 * i, 0, 0])) for i in range(3)]
    assert_png(trees.clones_figure(tree, clones, tmp_path / "c.png"))
    vals = {
        "height": np.array([3.0, 3.2, 2.9]),
        "girth": np.array([0.4, 0.41, 0.39]),
        "d_h": np.array([0.0, 0.06, 0.03]),
    }
    assert_png(trees.clone_metrics_figure(vals, tmp_path / "m.png", target={"height": 3.0, "girth": 0.4}))


def test_display_columns_turns_circular_pairs_into_degrees():
    ang = np.array([10.0, -170.0, 90.0])
    tab = np.c_[np.ones(3), np.sin(np.radians(ang)), np.cos(np.radians(ang)), 2 * np.ones(3)]
    out, names = datasets.display_columns(tab, ["R", "sin(gamma)", "cos(gamma)", "L"])
    assert names == ["R", "gamma", "L"]
    assert np.allclose(out[:, 1], ang) and np.allclose(out[:, [0, 2]], tab[:, [0, 3]])


def test_per_line_ks_equals_scipy_with_ties():
    from scipy.stats import ks_2samp

    rng = np.random.default_rng(4)
    um = np.round(rng.normal(size=(60, 3)), 1)
    ud = np.round(rng.normal(0.3, 1.2, size=(45, 3)), 1)
    A = rng.normal(size=(7, 3))
    A /= np.linalg.norm(A, axis=1, keepdims=True)
    A[0] = [1, 0, 0]  # heavy ties on a coordinate axis
    got = datasets.per_line_ks(um, ud, A)
    want = [ks_2samp(um @ a, ud @ a).statistic for a in A]
    assert np.allclose(got, want, atol=1e-12)


def test_column_gaps_rank_columns_by_their_own_ks_with_angles_in_degrees():
    from scipy.stats import ks_2samp

    # data: L uniform on [0, 3], angles 0-90 deg; model: L on [0, 3] shifted by +1.5 (KS 0.5),
    # angles the same (KS 0): L ranks first, then gamma, with its medians in degrees
    x = np.linspace(0.0, 3.0, 101)
    ang = np.linspace(0.0, 90.0, 101)
    rad = np.radians(ang)
    ud = np.c_[x, np.sin(rad), np.cos(rad)]
    um = np.c_[x + 1.5, np.sin(rad), np.cos(rad)]
    rows = datasets.column_gaps(um, ud, ["L", "sin(gamma)", "cos(gamma)"])
    assert [r["column"] for r in rows] == ["L", "gamma"]
    assert rows[0]["ks"] == pytest.approx(ks_2samp(um[:, 0], ud[:, 0]).statistic, abs=1e-12)
    assert rows[0]["ks"] == pytest.approx(0.5, abs=0.01)
    assert rows[0]["median_model"] == pytest.approx(3.0) and rows[0]["median_data"] == pytest.approx(1.5)
    assert rows[1]["ks"] == 0.0 and rows[1]["median_data"] == pytest.approx(45.0)
    # a model without rows of the set: every column at KS 1, its medians None (valid JSON)
    empty = datasets.column_gaps(np.empty((0, 3)), ud, ["L", "sin(gamma)", "cos(gamma)"])
    assert [r["ks"] for r in empty] == [1.0, 1.0] and empty[0]["median_model"] is None


def test_data_set_and_worst_lines_figures(tmp_path):
    rng = np.random.default_rng(1)
    cols = ["R", "L", "sin(gamma)", "cos(gamma)"]
    g = rng.uniform(-np.pi, np.pi, (2, 300))
    ud = np.c_[rng.gamma(2, 0.01, 300), rng.uniform(0, 3, 300), np.sin(g[0]), np.cos(g[0])]
    um = np.c_[rng.gamma(2, 0.012, 300), rng.uniform(0, 2, 300), np.sin(g[1]), np.cos(g[1])]
    assert_png(datasets.set_scatter_figure(ud, um, cols, tmp_path / "s.png", title="S1"), 600, 600)
    A = rng.normal(size=(32, 4))
    A /= np.linalg.norm(A, axis=1, keepdims=True)
    assert_png(datasets.worst_lines_figure(um, ud, A, cols, tmp_path / "l.png", k=3), 900, 200)
    # an empty model table still draws (data only)
    assert_png(datasets.set_scatter_figure(ud, np.empty((0, 4)), cols, tmp_path / "e.png"))


def test_convergence_compare_chain_and_corner_figures(tmp_path):
    d = np.r_[0.5, 0.4, 1.0, 0.3, 0.35, 0.2]
    st = ["ok", "ok", "collapsed", "ok", "ok", "ok"]
    recs = [{"generation": 0, "best": 0.4, "mean": 0.45, "std": 0.05}, {"generation": 1, "best": 0.2, "mean": 0.3}]
    assert_png(convergence.convergence_figure(d, tmp_path / "c.png", statuses=st, records=recs), 900)
    assert comparison._pad_curves([np.array([3.0, 2, 2.5]), np.array([4.0, 1])]).tolist() == [[3, 2, 2], [4, 1, 1]]
    curves = {"ga": [np.linspace(1, 0.2, 50), np.linspace(1, 0.3, 40)], "de": [np.linspace(1, 0.5, 50)]}
    assert_png(comparison.compare_figure(curves, tmp_path / "cmp.png", threshold=0.3))
    rng = np.random.default_rng(0)
    chain = rng.normal(size=(30, 8, 3)) * [1, 2, 0.1] + [0, 5, 1]
    diag = {
        "chain": chain.tolist(),
        "distances": rng.random((30, 8)).tolist(),
        "burn_in": 10,
        "names": ["a", "b", "c"],
        "walkers": 8,
    }
    got = Posterior.from_diagnostics(diag, ["x", "y", "z"])  # the diagnostics name the parameters
    assert got.kind == "chain" and got.chain.shape == (30, 8, 3) and got.distances.shape == (30, 8)
    assert got.burn_in == 10 and got.names == ("a", "b", "c")
    assert np.array_equal(got.samples, chain[10:].reshape(-1, 3)) and got.weights.sum() == pytest.approx(1.0)
    assert Posterior.from_diagnostics({"generations": 3}, ["a"]) is None
    assert_png(posterior.chain_figure(got.chain, got.names, tmp_path / "ch.png", burn_in=10, distances=got.distances))
    assert_png(
        posterior.corner_figure(chain[10:].reshape(-1, 3), ["a", "b", "c"], tmp_path / "co.png", truths=[0, 5, 1]),
        500,
        500,
    )


# ---------------------------------------------------------------------------------- real components
def _have(kind, name):
    try:
        bf.component_class(kind, name)
        return True
    except Exception:
        return False


REAL_TOML = """
seed = 5
[target.generate]
ssm = "sot"
seed = 3
params = {{ max_iter = 8, branch_angle = 50.0 }}
[ssm]
kind = "sot"
fixed = {{ max_iter = 8 }}
free.branch_angle = {{ lower = 30.0, upper = 70.0 }}
free.init_lambda = {{ lower = 0.5, upper = 0.65 }}
[features]
kind = "branch-segment"
sets = ["S0,1", "B1,2"]
[distance]
kind = "sliced"
lines = 32
[optimizer]
kind = "emcee"
walkers = 4
steps = 3
burn_in = 1
[executor]
kind = "serial"
[stop]
max_evaluations = 40
"""


@pytest.mark.skipif(
    not all(
        _have(k, n)
        for k, n in [("ssm", "sot"), ("features", "branch-segment"), ("distance", "sliced"), ("optimizer", "emcee")]
    ),
    reason="needs the sot, branch-segment, sliced and emcee plugins",
)
def test_report_of_a_real_emcee_run(tmp_path):
    cfg_path = tmp_path / "real.toml"
    cfg_path.write_text(REAL_TOML.format())
    run = tmp_path / "run"
    bf.fit(bf.load_config(cfg_path), run, progress=False)
    text = write_report(run, strict=True).read_text()
    for name in ("trees", "set_S0-1", "set_B1-2", "lines_S0-1", "lines_B1-2", "convergence", "chain", "corner"):
        assert_png(run / "figures" / f"{name}.png")
    assert "of which the first 1 are burn-in and dropped" in text and "| branch_angle | 50 |" in text
    # the worst-lines figure uses the fit's own per-line values: their mean is the set's distance
    v = RunView(run)
    best = json.loads((run / "best.json").read_text())
    feats, dist = v.worker_parts
    for name, ud in v.U_data.items():
        um2, ud2, lines, stat, normalised = distance_view(dist, name, v.U_model[name], ud)
        assert stat == "ks" and normalised and lines.shape == (32,)
        assert lines.mean() == pytest.approx(best["per_set"][name], abs=1e-12)
        # ... and equal the KS of the normalised projections the figure draws
        assert np.allclose(datasets.per_line_ks(um2, ud2, dist.directions(ud.shape[1])), lines, atol=1e-9)


def test_wide_figures_stay_readable(tmp_path):
    """Many worst lines or many parameters: at most 1600 px wide, units on the corner axes."""
    rng = np.random.default_rng(0)
    ud, um = rng.normal(size=(200, 4)), rng.normal(0.3, 1, size=(150, 4))
    A = rng.normal(size=(64, 4))
    A /= np.linalg.norm(A, axis=1, keepdims=True)
    p = datasets.worst_lines_figure(um, ud, A, ["a", "b", "c", "d"], tmp_path / "l.png", k=8)
    w, h = png_size(p)
    assert w <= 1600 and h > 600  # the 9 panels wrap into 3 rows
    S = rng.normal(size=(500, 10))
    p = posterior.corner_figure(S, [f"p{i}" for i in range(10)], tmp_path / "c.png", units=["m"] * 10)
    assert png_size(p)[0] <= 1600
