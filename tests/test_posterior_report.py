"""The posterior report of a sampler's run (issue 33, item 3): a population worded as a population
and a chain as a chain, best.json's quantiles, the corner plot for every sampler with a
posterior, a population's per-generation figure, the true values of a generated target, the
warning when a sampler stops above its tolerance target or at a cap, and the ArviZ groups."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import bforest_core as bf
from bforest_core.interfaces import Optimizer, Posterior
from bforest_core.pipeline.posterior import prior_draws
from bforest_core.report import canvas
from bforest_core.report import posterior as post_fig
from conftest import toy_config

ROOT = Path(__file__).resolve().parents[1]
RECIPE = ROOT / "examples" / "calibration" / "sot_abc_smc_adjusted.toml"
TRUE = {"init_lambda": 0.5, "branch_angle": 55.0, "alpha1": 1.5}


def _have(kind, name):
    try:
        bf.component_class(kind, name)
        return True
    except Exception:
        return False


def _capture(monkeypatch, module):
    """Keep every Figure ``module`` saves (to read what it drew)."""
    figs = []
    real = module.save_figure

    def keep(fig, path, dpi=130):
        figs.append(fig)
        return real(fig, path, dpi)

    monkeypatch.setattr(module, "save_figure", keep)
    return figs


# ---------------------------------------------------------------------------------- the kind
def test_samplers_declare_their_posterior_kind_and_optimisers_none():
    assert Optimizer.posterior_kind is None
    assert bf.component_class("optimizer", "abc-smc").posterior_kind == "population"
    assert bf.component_class("optimizer", "emcee").posterior_kind == "chain"
    assert bf.component_class("optimizer", "cma").posterior_kind is None
    # a run written before the samplers declared it: the diagnostics' keys tell
    assert Posterior.from_diagnostics({"particles": [[1.0]], "weights": [1.0]}, ["a"]).kind == "population"
    assert Posterior.from_diagnostics({"chain": [[[1.0]]]}, ["a"]).kind == "chain"
    # the sampler's declared kind rules: a population that holds no particles is no posterior
    assert Posterior.from_diagnostics({"chain": [[[1.0]]]}, ["a"], "population") is None
    assert Posterior.from_diagnostics({"generations": 3}, ["a"]) is None
    # a population's weights sum to 1; columns that the names do not match are no posterior
    post = Posterior.from_diagnostics({"particles": [[1.0], [3.0]], "weights": [1.0, 3.0]}, ["a"])
    assert post.weights.tolist() == [0.25, 0.75] and post.draws()["a"].tolist() == [[1.0, 3.0]]
    assert Posterior.from_diagnostics({"particles": [[1.0, 2.0]], "weights": [1.0]}, ["a"]) is None


def test_prior_draws_are_uniform_over_the_box_integers_whole():
    d = prior_draws({"a": (2.0, 4.0, False), "k": (3, 7, True)}, 4000, seed=2)
    a, k = d["a"].ravel(), d["k"].ravel()
    assert d["a"].shape == (1, 4000) and 2.0 <= a.min() and a.max() <= 4.0
    assert a.mean() == pytest.approx(3.0, abs=0.05) and a.std() == pytest.approx(2 / np.sqrt(12), rel=0.05)
    assert set(np.unique(k)) == {3, 4, 5, 6, 7}
    assert np.bincount(k.astype(int))[3:] / 4000 == pytest.approx([0.2] * 5, abs=0.03)


# ---------------------------------------------------------------------------------- figures
def test_weighted_corner_draws_best_json_quantiles_and_the_true_values(tmp_path, monkeypatch):
    """Two particles hold all the weight: the 5/50/95 % lines are their weighted quantiles, not
    those of the unweighted cloud; the true value is drawn on the diagonal and in the pair panel."""
    from bforest_core.metrics import weighted_quantiles

    figs = _capture(monkeypatch, post_fig)
    rng = np.random.default_rng(0)
    X = np.vstack([rng.uniform(0, 10, size=(200, 2)), [[2.0, 8.0], [3.0, 7.0]]])
    w = np.r_[np.full(200, 1e-9), 1.0, 1.0]
    post_fig.corner_figure(X, ["a", "b"], tmp_path / "c.png", weights=w, true_values=[2.5, 11.0])
    fig = figs[-1]
    axes = [ax for ax in fig.axes if ax.get_visible()]
    diag_a = next(ax for ax in axes if ax.get_title().startswith("a = "))
    xs = sorted(round(float(line.get_xdata()[0]), 6) for line in diag_a.lines if line.get_color() == "#1f77b4")
    assert xs == pytest.approx(sorted(weighted_quantiles(X[:, 0], w / w.sum(), [5, 50, 95])), abs=1e-6)
    assert 1.9 < xs[0] and xs[-1] < 3.2  # the unweighted cloud spans 0-10
    greens = [line for ax in axes for line in ax.lines if line.get_color() == canvas.TRUE_COLOR]
    assert any(np.allclose(line.get_xdata(), 2.5) for line in greens)  # marginal of a
    assert any(np.allclose(line.get_xdata(), 11.0) for line in greens)  # marginal of b, outside the cloud
    diag_b = next(ax for ax in axes if ax.get_title().startswith("b = "))
    assert diag_b.get_xlim()[1] > 11.0  # ... and kept in view
    # the pair panel (b against a): the pairs share one axes in figure fractions, so the marker
    # stands at a's place in a's column and b's place in b's row
    pa, pb = diag_a.get_position(), diag_b.get_position()
    (a0, a1), (b0, b1) = diag_a.get_xlim(), diag_b.get_xlim()
    x, y = pa.x0 + (2.5 - a0) / (a1 - a0) * pa.width, pb.y0 + (11.0 - b0) / (b1 - b0) * pb.height
    pairs = next(ax for ax in axes if ax.get_gid() == "pairs")
    assert [(line.get_xdata()[0], line.get_ydata()[0]) for line in pairs.lines if line.get_marker() == "D"] == [
        pytest.approx((x, y), abs=1e-9)
    ]
    assert pa.x0 <= x <= pa.x1 and y > pb.y1 - 0.05 * pb.height  # near the top of the panel, kept in view


def test_generations_figure_draws_epsilon_acceptance_and_ess(tmp_path, monkeypatch):
    figs = _capture(monkeypatch, post_fig)
    post_fig.generations_figure(
        [None, 0.5, 0.3, 0.2],
        [1.0, 0.5, 0.3, 0.1],
        [40.0, 35.0, 30.0, 20.0],
        tmp_path / "g.png",
        epsilon_target=[0.1, 0.12, 0.15],
        particles=40,
    )
    ax_eps, ax_acc, ax_ess = figs[-1].axes[:3]
    eps = ax_eps.lines[0].get_ydata()
    assert np.isnan(eps[0]) and list(eps[1:]) == [0.5, 0.3, 0.2] and ax_eps.get_yscale() == "log"
    assert list(ax_eps.lines[1].get_ydata()) == [0.1, 0.12, 0.15] and list(ax_eps.lines[1].get_xdata()) == [1, 2, 3]
    assert list(ax_acc.lines[0].get_ydata()) == [1.0, 0.5, 0.3, 0.1]
    assert list(ax_ess.lines[0].get_ydata()) == [40.0, 35.0, 30.0, 20.0]
    assert ax_ess.get_xlabel() == "generation"


# ---------------------------------------------------------------------------------- the stop note
def test_abc_smc_says_when_it_stops_above_its_target_and_not_when_it_reaches_it():
    from bforest_optim.abc_smc import AbcSmc
    from test_abc_smc import _problem, gaussian_location

    pr, _ = _problem(gaussian_location(), [-10.0], [10.0])
    res = AbcSmc(particles=50, generations=3, epsilon_target=0.05).minimize(pr)
    eps = res.diagnostics["epsilon"][-1]
    assert eps > 0.05 and res.stop_reason == "3 generations done"
    assert res.diagnostics["stopped_short"].startswith(f"epsilon stopped at {eps:.4g}, above its target 0.05")
    pr, _ = _problem(gaussian_location(), [-10.0], [10.0])
    res = AbcSmc(particles=50, generations=30, epsilon_target=2.0).minimize(pr)
    assert "target" in res.stop_reason and "stopped_short" not in res.diagnostics
    pr, _ = _problem(gaussian_location(), [-10.0], [10.0], budget=220)  # the evaluation cap, no target
    res = AbcSmc(particles=50, generations=30).minimize(pr)
    assert "stopped at a cap" in res.diagnostics["stopped_short"]


def test_emcee_says_when_the_budget_cut_its_chain(toy_plugin, tmp_path):
    p = toy_config(tmp_path, optimizer="emcee", optimizer_settings="walkers = 8\nsteps = 50\nburn_in = 2", budget=40)
    res = bf.fit(bf.load_config(p), tmp_path / "run", progress=False)
    assert res.diagnostics["stopped_short"].startswith(f"stopped after {res.diagnostics['steps']} of 50 steps")
    from bforest_core.report import write_report

    text = write_report(tmp_path / "run", figures=False).read_text()
    assert "WARNING: the sampler stopped short of its target: stopped after" in text
    assert "burn-in" in text and "autocorr. time" in text and "weighted population" not in text


# ---------------------------------------------------------------------------------- the acceptance run
@pytest.mark.slow
@pytest.mark.skipif(
    not all(
        _have(k, n)
        for k, n in [("ssm", "sot"), ("features", "branch-segment"), ("distance", "sliced"), ("optimizer", "abc-smc")]
    ),
    reason="needs the sot, branch-segment, sliced and abc-smc plugins",
)
def test_abc_smc_report_of_the_calibrated_recipe_on_a_generated_target(tmp_path, capsys):
    """The user guide's calibrated recipe (noise-floor target, recycled and adjusted posterior)
    on a tree grown with known parameters, cut to 3 generations of 10 particles: epsilon stops
    above the noise floor, and the fit's output and the report say so; the report words a
    population, gives best.json's quantiles beside the true values, and draws the corner and
    per-generation figures."""
    import arviz as az

    from bforest_core.cli import main

    text = RECIPE.read_text()
    text = text.replace(
        "[ssm]",
        '[target.generate]\nssm = "sot"\nseed = 5\nparams = { max_iter = 10, '
        + ", ".join(f"{k} = {v}" for k, v in TRUE.items())
        + " }\n\n[ssm]",
        1,
    )
    for old, new in (
        ("particles = 40", "particles = 10"),
        ("generations = 20", "generations = 3"),
        ("noise_seeds = 8", "noise_seeds = 4"),
        ("lines = 64", "lines = 16"),
        ('kind = "process"\nworkers = 2', 'kind = "serial"'),
    ):
        assert old in text, old
        text = text.replace(old, new)
    cfg = tmp_path / "calibrated.toml"
    cfg.write_text(text)
    run = tmp_path / "run"
    assert main(["fit", str(cfg), "-o", str(run), "-q"]) == 0
    out = capsys.readouterr().out
    best = json.loads((run / "best.json").read_text())
    diag = best["diagnostics"]
    eps, floor = diag["epsilon"][-1], diag["epsilon_target"][-1]
    assert eps > floor > 0 and best["stop_reason"] == "3 generations done"
    warning = f"epsilon stopped at {eps:.4g}, above its target {floor:.4g}, the distance's noise floor,"
    assert f"WARNING: the sampler stopped short of its target: {warning}" in out
    report = (run / "report.md").read_text()
    assert (
        report.count(f"WARNING: the sampler stopped short of its target: {warning}") == 3
    )  # summary, posterior, notes
    assert "Notes\n\n- none" not in report
    # a population's words, not a chain's
    assert best["posterior_kind"] == "population"
    assert "The posterior is a weighted population of" in report
    assert "burn-in" not in report and "autocorr" not in report and "2.5 %" not in report
    # best.json's quantiles and HDI, beside the true values
    for name, q in best["posterior_summary"].items():
        row = next(line for line in report.splitlines() if line.startswith(f"| {name} | {TRUE[name]:g} | "))
        cells = [c.strip() for c in row.strip("|").split("|")]
        assert cells[4:7] == [f"{q['p5']:.4g}", f"{q['p50']:.4g}", f"{q['p95']:.4g}"], (row, q)
        assert cells[7] == f"{q['hdi90_low']:.4g} – {q['hdi90_high']:.4g}"
        inside = q["hdi90_low"] <= TRUE[name] <= q["hdi90_high"]
        assert cells[8] == ("yes" if inside else "**no**")
    for name in ("corner", "generations"):
        assert (run / "figures" / f"{name}.png").stat().st_size > 10_000
        assert f"](figures/{name}.png)" in report
    assert "green: the true values the target was grown with" in report
    # ArviZ: posterior, prior over the box, the target's data sets, per-particle statistics
    idata = az.from_netcdf(str(run / "posterior.nc"))
    assert {"posterior", "prior", "observed_data", "sample_stats"} <= set(idata.groups())
    n = len(diag["particles"]) if isinstance(diag["particles"], list) else None
    lam = idata.prior["init_lambda"].values
    assert lam.shape == idata.posterior["init_lambda"].values.shape and 0.35 <= lam.min() and lam.max() <= 0.65
    assert set(idata.observed_data.data_vars) == {"S0_1", "B1_2"}
    target_sets = np.load(run / "target_sets.npz")
    assert np.array_equal(idata.observed_data["S0_1"].values, target_sets["S0,1"])
    assert idata.sample_stats["weight"].values.ravel() == pytest.approx(
        np.loadtxt(run / "posterior.csv", delimiter=",", skiprows=1)[:, -1]
    )
    assert idata.attrs["posterior_kind"] == "population" and idata.attrs["optimizer"] == "abc-smc"
    assert n is None or idata.sample_stats["distance"].shape[-1] == n
