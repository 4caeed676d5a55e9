"""ABC-SMC on problems with a known posterior, its stops, and resume through the fit pipeline."""

import numpy as np
import pytest

import bforest_core as bf
from bforest_core.interfaces import Problem
from bforest_core.metrics import weighted_quantiles
from bforest_optim.abc_smc import AbcSmc
from conftest import fit_killed_after, toy_config


def _problem(simulate_distance, lo, hi, integer=None, budget=200_000, seed=1):
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    pr = Problem(
        names=[f"x{i}" for i in range(lo.size)],
        lower=lo,
        upper=hi,
        integer=np.zeros(lo.size, bool) if integer is None else np.asarray(integer, bool),
        evaluate=None,
        seed=seed,
        max_evaluations=budget,
    )
    calls = []

    def evaluate(X):
        X = np.atleast_2d(X)
        k = min(len(X), pr.remaining())
        out = np.full(len(X), np.inf)
        out[:k] = simulate_distance(X[:k])
        calls.append(X[:k].copy())
        pr.n_evaluations += k
        if pr.remaining() == 0:
            pr.stopped, pr.stop_reason = True, "budget"
        return out

    pr.evaluate = evaluate
    return pr, calls


def gaussian_location(y_obs=2.0, sigma=1.0, seed=0):
    """One draw y ~ N(theta, sigma^2) per simulation, D = |y - y_obs|: under a flat prior the
    exact posterior is N(y_obs, sigma^2); ABC at tolerance eps adds eps^2 / 3 to the variance."""
    rng = np.random.default_rng(seed)
    return lambda X: np.abs(X[:, 0] + sigma * rng.standard_normal(len(X)) - y_obs)


def test_weighted_quantiles_equal_weights_match_numpy_hazen():
    x = np.random.default_rng(1).normal(size=101)
    q = weighted_quantiles(x, np.ones_like(x), [10, 50, 90])
    assert q == pytest.approx(np.percentile(x, [10, 50, 90], method="hazen"))
    # a weight of zero removes a point
    assert weighted_quantiles(np.array([0.0, 1.0, 100.0]), np.array([1.0, 1.0, 0.0]), [50]) == pytest.approx(0.5)
    # ... in the tails too: the same quantiles as without it
    with_zero = weighted_quantiles(np.array([1.0, 2.0, 100.0]), np.array([1.0, 1.0, 0.0]), [5, 50, 95])
    assert with_zero == pytest.approx(weighted_quantiles(np.array([1.0, 2.0]), np.array([1.0, 1.0]), [5, 50, 95]))
    assert with_zero[-1] == pytest.approx(2.0)


@pytest.mark.parametrize("kernel", ["mvn", "local"])
def test_gaussian_location_posterior_mean_and_sd(kernel):
    pr, _ = _problem(gaussian_location(), [-10.0], [10.0])
    res = AbcSmc(particles=400, generations=40, epsilon_target=0.1, min_acceptance=0.005, kernel=kernel).minimize(pr)
    d = res.diagnostics
    assert d["epsilon"][-1] <= 0.1 and "target" in res.stop_reason
    post = d["posterior"]["x0"]
    eps = d["epsilon"][-1]
    sd_exact = np.sqrt(1.0 + eps**2 / 3)
    assert post["mean"] == pytest.approx(2.0, abs=0.1 * sd_exact)
    assert post["std"] == pytest.approx(sd_exact, rel=0.10)
    assert post["p5"] < post["p50"] < post["p95"]
    assert d["particles"].shape == (400, 1) and d["weights"].sum() == pytest.approx(1.0)
    assert all(a > b for a, b in zip(d["epsilon"][1:], d["epsilon"][2:]))  # epsilon falls every generation
    assert np.all(d["distances"] <= eps)


def test_recycled_posterior_is_the_abc_posterior_at_its_lower_tolerance():
    """``posterior = "recycled"``: the proposals of every generation with a distance at most a
    lower tolerance eps', weighted by multiple importance sampling, are the ABC posterior at eps':
    for the Gaussian location N(y_obs, 1 + eps'^2 / 3) (the exact posterior widened by the
    tolerance), narrower than the last population's N(y_obs, 1 + eps_T^2 / 3). The same run (same
    evaluations) gives both; the last population stays in the diagnostics."""
    out = {}
    for post in ("population", "recycled"):
        pr, calls = _problem(gaussian_location(seed=3), [-10.0], [10.0])
        res = AbcSmc(particles=400, generations=40, epsilon_target=1.0, min_acceptance=0.005, posterior=post).minimize(
            pr
        )
        out[post] = (res.diagnostics, np.concatenate(calls))
    pop, rec = out["population"][0], out["recycled"][0]
    assert np.array_equal(out["population"][1], out["recycled"][1])  # the same proposals
    eps_t, eps = rec["epsilon"][-1], rec["epsilon_posterior"]
    assert pop["epsilon_posterior"] == eps_t == pytest.approx(1.0)
    assert eps < 0.7 * eps_t  # the earlier generations hold many proposals closer than eps_T
    w = rec["weights"]
    assert w.sum() == pytest.approx(1.0) and 1.0 / np.sum(w**2) >= 400  # a population's ESS
    assert np.all(rec["distances"] <= eps) and rec["distances"].max() == eps
    sd = np.sqrt(1.0 + eps**2 / 3)
    post = rec["posterior"]["x0"]
    assert post["mean"] == pytest.approx(2.0, abs=0.1 * sd)
    assert post["std"] == pytest.approx(sd, rel=0.10)
    assert post["std"] < pop["posterior"]["x0"]["std"]
    assert np.array_equal(rec["population"]["particles"], pop["particles"])
    assert np.array_equal(rec["population"]["weights"], pop["weights"])


def test_recycled_posterior_at_a_bound_of_the_prior():
    """Near a bound the proposals are truncated (drawn again when outside); the recycled
    posterior is still the ABC posterior at its tolerance, p(theta) ~ Phi(y - theta + eps) -
    Phi(y - theta - eps) on theta >= 0, integrated numerically."""
    from scipy.stats import norm

    pr, _ = _problem(gaussian_location(y_obs=0.3, seed=1), [0.0], [10.0])
    d = (
        AbcSmc(particles=400, generations=40, epsilon_target=1.0, min_acceptance=0.005, posterior="recycled")
        .minimize(pr)
        .diagnostics
    )
    eps = d["epsilon_posterior"]
    t = np.linspace(0.0, 10.0, 200_001)
    p = norm.cdf(0.3 - t + eps) - norm.cdf(0.3 - t - eps)
    mean = (t * p).sum() / p.sum()
    sd = np.sqrt(((t - mean) ** 2 * p).sum() / p.sum())
    assert eps < 0.7
    assert d["posterior"]["x0"]["mean"] == pytest.approx(mean, abs=0.1 * sd)
    assert d["posterior"]["x0"]["std"] == pytest.approx(sd, rel=0.10)


def test_stops_on_min_acceptance_and_budget_keeping_the_last_complete_generation():
    pr, _ = _problem(gaussian_location(), [-10.0], [10.0])
    res = AbcSmc(particles=100, generations=60, min_acceptance=0.2).minimize(pr)
    assert "below min_acceptance" in res.stop_reason
    assert res.diagnostics["acceptance"][-1] >= 0.2
    pr, _ = _problem(gaussian_location(), [-10.0], [10.0], budget=450)
    res = AbcSmc(particles=100).minimize(pr)
    assert pr.n_evaluations == 450 and "budget" in res.stop_reason
    assert "incomplete" in res.diagnostics["note"] and "last complete" in res.diagnostics["note"]
    assert res.diagnostics["particles"].shape == (100, 1)


def test_integer_parameters_are_whole_numbers_and_the_run_is_reproducible():
    def dist(X):
        return np.abs(X[:, 0] - 7) + np.abs(X[:, 1] - 0.3)

    runs = []
    for _ in range(2):
        pr, calls = _problem(dist, [0, 0.0], [20, 1.0], integer=[True, False], budget=3000)
        res = AbcSmc(particles=50, generations=6).minimize(pr)
        X = np.vstack(calls)
        assert np.all(X[:, 0] == np.rint(X[:, 0]))
        runs.append((X, res.diagnostics["particles"]))
    assert np.array_equal(runs[0][0], runs[1][0]) and np.array_equal(runs[0][1], runs[1][1])
    assert runs[0][1][:, 0].tolist().count(7) > 25  # the posterior concentrates on the right integer


def test_abc_smc_in_a_fit_resumes_after_a_kill(toy_plugin, tmp_path, monkeypatch):
    """A fit killed after 30 evaluations and resumed ends exactly where an uninterrupted run ends
    (the logged evaluations are replayed, the same particles proposed and accepted)."""
    from bforest_core.pipeline.store import RunStore

    settings = "particles = 12\ngenerations = 4"
    cfg_path = toy_config(tmp_path, optimizer="abc-smc", optimizer_settings=settings, budget=80)
    full = bf.fit(bf.load_config(cfg_path), tmp_path / "full", progress=False)
    fit_killed_after(bf.load_config(cfg_path), tmp_path / "killed", 30, monkeypatch)
    res = bf.fit(bf.load_config(cfg_path), tmp_path / "killed", resume=True, progress=False)
    ev = lambda run: [(e.params, e.distance) for e in RunStore.open(run).evaluations()]  # noqa: E731
    assert ev(tmp_path / "killed") == ev(tmp_path / "full")
    assert res.params == full.params and res.distance == full.distance


def test_posterior_csv_of_abc_smc_and_emcee_runs(toy_plugin, tmp_path):
    import csv

    for kind, settings in (
        ("abc-smc", "particles = 10\ngenerations = 3"),
        ("emcee", "walkers = 8\nsteps = 6\nburn_in = 2"),
    ):
        run = tmp_path / kind
        p = toy_config(tmp_path, optimizer=kind, optimizer_settings=settings, budget=200)
        res = bf.fit(bf.load_config(p), run, progress=False)
        rows = list(csv.reader((run / "posterior.csv").open()))
        names = res.diagnostics["names"]  # the fitted parameters
        assert rows[0] == [*names, "weight"] and set(names) < set(res.params)
        w = np.array([float(r[-1]) for r in rows[1:]])
        assert w.sum() == pytest.approx(1.0)
        if kind == "abc-smc":
            assert len(rows) - 1 == 10
            X = np.array([[float(v) for v in r[:-1]] for r in rows[1:]])
            assert np.allclose(X, res.diagnostics["particles"]) and np.allclose(w, res.diagnostics["weights"])
        else:
            assert len(rows) - 1 == 8 * (6 - 2) and np.allclose(w, 1 / 32)


def test_inference_data_and_summary_round_trip(toy_plugin, tmp_path):
    import json

    import arviz as az

    for kind, settings in (
        ("abc-smc", "particles = 10\ngenerations = 3"),
        ("emcee", "walkers = 8\nsteps = 6\nburn_in = 2"),
    ):
        run = tmp_path / kind
        res = bf.fit(
            bf.load_config(toy_config(tmp_path, optimizer=kind, optimizer_settings=settings, budget=200)),
            run,
            progress=False,
        )
        names = res.diagnostics["names"]
        idata = az.from_netcdf(str(run / "posterior.nc"))
        table = json.loads((run / "best.json").read_text())["posterior_summary"]
        X = np.loadtxt(run / "posterior.csv", delimiter=",", skiprows=1)
        for j, name in enumerate(names):
            draws = idata.posterior[name].values
            if kind == "emcee":  # walkers x kept steps, the same numbers as the CSV
                assert draws.shape == (8, 4) and np.allclose(np.sort(draws.ravel()), np.sort(X[:, j]))
                assert "r_hat" in table[name]
            else:  # one chain of a resample by weight; the raw weights beside it
                assert draws.shape == (1, 10)
                assert np.all(np.isclose(draws.ravel()[:, None], X[None, :, j], rtol=1e-9).any(axis=1))
                assert np.allclose(idata.sample_stats["weight"].values.ravel(), X[:, -1])
            assert table[name]["p5"] <= table[name]["p50"] <= table[name]["p95"]
            assert table[name]["mean"] == pytest.approx(float(X[:, -1] @ X[:, j]))


def test_posterior_predictive_clones_draw_distinct_parameters(toy_plugin, tmp_path):
    from bforest_core.pipeline.clones import ClonesError, clones

    run = tmp_path / "abc"
    res = bf.fit(
        bf.load_config(
            toy_config(tmp_path, optimizer="abc-smc", optimizer_settings="particles = 10\ngenerations = 3", budget=200)
        ),
        run,
        progress=False,
    )
    s = clones(run, n=6, posterior=True, progress=False)
    names = res.diagnostics["names"]
    drawn = [tuple(r["params"][k] for k in names) for r in s["rows"]]
    assert len(set(drawn)) >= 3 and s["posterior"] is True  # draws, not the best fit six times
    X = np.loadtxt(run / "posterior.csv", delimiter=",", skiprows=1)[:, :-1]
    for d in drawn:  # every draw is a particle of the posterior
        assert np.isclose(X, np.array(d, float), rtol=1e-9).all(axis=1).any()
    assert (run / "clones_posterior" / "clones.csv").exists()
    # the set grows reproducibly: clone i keeps its draw
    again = clones(run, n=8, posterior=True, progress=False)
    assert [tuple(r["params"][k] for k in names) for r in again["rows"][:6]] == drawn
    # a run without a posterior says so
    run2 = tmp_path / "ga"
    bf.fit(bf.load_config(toy_config(tmp_path, optimizer="ga", budget=20)), run2, progress=False)
    with pytest.raises(ClonesError, match="posterior clones need a sampler's run"):
        clones(run2, n=2, posterior=True, progress=False)


def test_noise_target_stops_at_the_distance_a_perfect_model_shows():
    """``epsilon_target = "noise"``: the median distance under fresh seeds at the best particle or
    the weighted mean, whichever is lower.
    For the Gaussian location (D = |theta + z - y_obs|) a perfect model's median distance is
    0.674 sigma; the last generation runs at that epsilon and the posterior is the exact one
    widened by eps^2 / 3."""
    pr, _ = _problem(gaussian_location(), [-10.0], [10.0])
    rng = np.random.default_rng(7)
    measured = []

    def seed_spread(x, k):
        vals = np.abs(x[0] + rng.standard_normal(k) - 2.0)
        measured.append(np.median(vals))
        return vals

    pr.seed_spread = seed_spread
    res = AbcSmc(particles=400, generations=40, epsilon_target="noise", noise_seeds=200, min_acceptance=0.005).minimize(
        pr
    )
    d = res.diagnostics
    targets = [min(a, b) for a, b in zip(measured[::2], measured[1::2])]  # best particle, weighted mean
    assert "noise floor" in res.stop_reason and d["epsilon_target"] == pytest.approx(targets)
    eps = d["epsilon"][-1]
    assert eps == pytest.approx(targets[-2])  # the last generation ran at the target (clamped)
    assert eps == pytest.approx(0.674, rel=0.15)
    assert d["posterior"]["x0"]["std"] == pytest.approx(np.sqrt(1.0 + eps**2 / 3), rel=0.10)
    assert d["posterior"]["x0"]["mean"] == pytest.approx(2.0, abs=0.15)
    # without a way to measure the noise there is no target (the other stops end the run)
    pr, _ = _problem(gaussian_location(), [-10.0], [10.0], budget=3000)
    res = AbcSmc(particles=100, generations=5, epsilon_target="noise").minimize(pr)
    assert res.stop_reason == "5 generations done" and res.diagnostics["epsilon_target"] == [0.0] * 4
    with pytest.raises(Exception, match="epsilon_target"):
        AbcSmc(epsilon_target=-1.0)


@pytest.mark.parametrize("as_inf", [True, False])
def test_failed_simulations_are_never_accepted_whatever_the_penalty(toy_plugin, tmp_path, monkeypatch, as_inf):
    """A failed simulation matches nothing: abc-smc gets ``inf`` for it (``failures_as_inf``), so
    even a penalty below every real distance (as 1.0 is under the sample-size-scaled KS
    statistic) is never accepted; the store still logs the penalty with the status. Without the
    flag (the ``False`` case, the behaviour before it) the failures are accepted as perfect fits."""
    from bforest_core.pipeline.store import RunStore

    monkeypatch.setattr(AbcSmc, "failures_as_inf", as_inf)
    p = toy_config(tmp_path, optimizer="abc-smc", optimizer_settings="particles = 12\ngenerations = 4", budget=300)
    text = p.read_text().replace('kind = "toy"\n', 'kind = "toy"\nfail_above = 50.0\n')
    p.write_text(text + "[objective]\npenalty = 0.0\n")
    run = tmp_path / "run"
    res = bf.fit(bf.load_config(p), run, progress=False)
    failed = [e for e in RunStore.open(run).evaluations() if e.status != "ok"]
    assert failed and all(e.distance == 0.0 and e.params["angle"] > 50.0 for e in failed)
    angle = np.asarray(res.diagnostics["particles"])[:, res.diagnostics["names"].index("angle")]
    if as_inf:
        assert angle.max() <= 50.0 and res.params["angle"] <= 50.0
    else:
        assert angle.max() > 50.0


def _location_with_summaries(seed: int, y_obs: float = 2.0):
    """The Gaussian location (one draw y ~ N(theta, 1), D = |y - y_obs|) with its summary
    statistic: ``summaries`` gives the y each evaluated point drew."""
    rng = np.random.default_rng(seed)
    drawn = {}

    def simulate(X):
        y = X[:, 0] + rng.standard_normal(len(X))
        drawn.update(zip(X[:, 0].tolist(), y.tolist()))
        return np.abs(y - y_obs)

    pr, _ = _problem(simulate, [-10.0], [10.0])
    pr.summaries = lambda X: np.array([[drawn[x]] for x in np.atleast_2d(X)[:, 0].tolist()])
    pr.target_summaries = np.array([y_obs])
    return pr


def test_linear_adjustment_takes_out_the_width_the_tolerance_adds():
    """At a coarse tolerance eps = 2 the ABC posterior of the Gaussian location is
    N(y_obs, 1 + eps^2 / 3) (sd 1.53); regressing theta on the simulated y and moving every
    particle to y_obs (Beaumont et al. 2002) gives back the exact posterior N(y_obs, 1), from the
    same evaluations."""
    out = {}
    for adjust in ("none", "linear"):
        pr = _location_with_summaries(seed=4)
        res = AbcSmc(particles=400, generations=40, epsilon_target=2.0, min_acceptance=0.005, adjust=adjust).minimize(
            pr
        )
        out[adjust] = res.diagnostics
    raw, adj = out["none"], out["linear"]
    assert raw["epsilon"][-1] == pytest.approx(2.0)
    assert raw["posterior"]["x0"]["std"] == pytest.approx(np.sqrt(1 + 4 / 3), rel=0.10)
    assert adj["posterior"]["x0"]["mean"] == pytest.approx(2.0, abs=0.1)
    assert adj["posterior"]["x0"]["std"] == pytest.approx(1.0, rel=0.10)
    assert adj["epsilon"] == raw["epsilon"]  # the same run, only the posterior differs
    a = adj["adjustment"]
    assert a["method"] == "linear" and a["summaries"] == 1 and a["regrown"] >= 400 and a["r2"][0] > 0.3
    assert np.array_equal(adj["unadjusted"]["particles"], raw["particles"])
    assert np.all(adj["distances"] <= 2.0) and adj["weights"].sum() == pytest.approx(1.0)


def test_regression_adjustment_known_linear_model_and_degrees_of_freedom():
    """logit(theta) = 0.3 + s_1 + 0.1 e with s_1 informative and 20 summaries of pure noise, 80
    equally weighted particles: the adjusted particles centre on 0.3 with the residual sd 0.1
    (the residuals of a fit with df degrees of freedom, inflated by sqrt(n / (n - df)), not the
    fit's underestimate); a parameter the summaries do not explain keeps its spread."""
    from bforest_optim.abc_smc import regression_adjust

    rng = np.random.default_rng(7)
    n, lo, hi = 80, np.array([0.0, 0.0]), np.array([1.0, 1.0])
    sds = {"inflated": [], "raw": []}
    for _ in range(40):
        S = rng.standard_normal((n, 21))
        e = rng.standard_normal(n)
        z = np.c_[0.3 + S[:, 0] + 0.1 * e, 0.5 * rng.standard_normal(n)]
        X = 1.0 / (1.0 + np.exp(-z))
        Xa, fit = regression_adjust(X, np.full(n, 1.0 / n), S, np.zeros(21), lo, hi)
        za = np.log(Xa / (1 - Xa))
        assert np.all((Xa > 0) & (Xa < 1))
        assert za[:, 0].mean() == pytest.approx(0.3, abs=0.05)
        assert fit["r2"][0] > 0.95 and 0 < fit["df"][0] < n
        sds["inflated"].append(za[:, 0].std())
        r = za[:, 0] - za[:, 0].mean()
        sds["raw"].append(np.std(r / np.sqrt(n / (n - fit["df"][0]))))
        assert za[:, 1].std() == pytest.approx(z[:, 1].std(), rel=0.35)
    assert np.mean(sds["inflated"]) == pytest.approx(0.1, rel=0.10)
    assert np.mean(sds["raw"]) < 0.92 * 0.1  # without the inflation the spread is too small


def test_adjusted_posterior_in_a_fit_regrows_logged_trees_and_resumes(toy_plugin, tmp_path, monkeypatch):
    """Through the fit: ``Problem.summaries`` regrows each proposal within the last tolerance with
    its logged seeds (toy: log rows = the trunk's segments, exactly; mean angle), the adjusted
    posterior is what posterior.csv holds, narrower than the unadjusted one, and a run killed and
    resumed writes the same posterior."""
    import json

    settings = 'particles = 30\ngenerations = 4\nadjust = "linear"'
    cfg_path = toy_config(tmp_path, optimizer="abc-smc", optimizer_settings=settings, budget=400)
    full = bf.fit(bf.load_config(cfg_path), tmp_path / "full", progress=False)
    d = full.diagnostics
    a = d["adjustment"]
    assert a["summaries"] == 3 and a["regrown"] >= 30 and len(a["r2"]) == 2
    X = np.loadtxt(tmp_path / "full" / "posterior.csv", delimiter=",", skiprows=1)
    assert np.allclose(X[:, :2], d["particles"]) and np.allclose(X[:, 2], d["weights"])
    seg = d["names"].index("segments")
    assert np.all(d["particles"][:, seg] == np.round(d["particles"][:, seg]))
    for j in range(2):
        sd = np.sqrt(d["weights"] @ (d["particles"][:, j] - d["weights"] @ d["particles"][:, j]) ** 2)
        u = d["unadjusted"]
        sd_raw = np.sqrt(u["weights"] @ (u["particles"][:, j] - u["weights"] @ u["particles"][:, j]) ** 2)
        assert sd < sd_raw
    assert json.loads((tmp_path / "full" / "best.json").read_text())["diagnostics"]["adjustment"]["method"] == "linear"
    from bforest_core.report.build import write_report

    text = write_report(tmp_path / "full", figures=False, html=False).read_text()
    assert "regression-adjusted" in text and "regressed on 3 summary statistics" in text
    fit_killed_after(bf.load_config(cfg_path), tmp_path / "killed", 100, monkeypatch)
    bf.fit(bf.load_config(cfg_path), tmp_path / "killed", resume=True, progress=False)
    assert (tmp_path / "killed" / "posterior.csv").read_text() == (tmp_path / "full" / "posterior.csv").read_text()


def test_set_summaries_rows_per_tree_and_column_means():
    """The statistics the adjustment regresses on: per set log(1 + rows per tree), then the
    columns' means; an empty set gives zeros; a target pooled over two trees counts rows per tree."""
    from bforest_core.pipeline.scoring import set_summaries

    U = {"B": np.array([[1.0, 10.0], [3.0, 30.0], [5.0, 20.0], [7.0, 40.0]]), "S": np.empty((0, 3))}
    assert set_summaries(U, ["B", "S"]) == pytest.approx([np.log(5.0), 4.0, 25.0, 0.0, 0.0, 0.0, 0.0])
    assert set_summaries(U, ["S", "B"], trees=2)[4] == pytest.approx(np.log(3.0))


def test_summary_task_counts_a_failing_data_set_as_a_failure_like_evaluate_task(toy_plugin, tmp_path, monkeypatch):
    """A tree whose data sets cannot be extracted is a failed evaluation (status "error") and has
    no summaries (None): regrowing it never crashes the adjustment."""
    from bforest_core.pipeline.target import build_target
    from bforest_core.pipeline.worker import evaluate_task, started_workers, summary_task

    cfg = bf.load_config(toy_config(tmp_path))
    task = ({"angle": 30.0, "segments": 12}, [1, 2])
    with started_workers(cfg, build_target(cfg)):  # serial: the worker is this process
        assert summary_task(task).shape == (3,)  # one set: log rows, two column means
        monkeypatch.setattr(
            type(bf.component("features", "toy-features")),
            "extract",
            lambda self, tree: (_ for _ in ()).throw(ValueError("bad table")),
        )
        assert evaluate_task(task)["status"] == "error"
        assert summary_task(task) is None
