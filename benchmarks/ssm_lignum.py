"""Benchmark and size check of the simplified stochastic LIGNUM (docs/models.md A.10, A.12).

    .venv/bin/python benchmarks/ssm_lignum.py [--repeats 5] [--sizes] [--markdown] [--log RUN]

Prints (single core):

* the median and minimum wall time over seeds 1-5 of the Silva Fennica synthetic target
  (``sf_synthetic``, T = 15, target <= 0.25 s) and of the real fit (``sf_real``, T = 32, target
  <= 0.2 s; T = 40, target <= 0.5 s), each beside the previous code (the shadow without the
  compiled bucket kernel) and beside the shadow's method chosen by its full cost model every year
  (before the cost model's short cut) in the same run, and whether all grow identical trees;
* baselines measured in the same run: a fixed numpy workload (each model time is also given as a
  multiple of it, so figures from a loaded machine can be compared) and, on the final
  ``sf_synthetic`` crown, the brute-force O(n^2) pyramid sum against the kd-tree kernel used;
* with ``--log RUN``: 60 points of a LIGNUM fit's log (RUN, its run folder) grown with the
  shadow's short cut and with its full cost model in turns, and whether the trees are identical;
* with ``--sizes``: tree sizes over seeds 1-5 (live segments, created, dead, height, crown radius,
  base diameter) beside the indicative table of A.10 and the apical-dominance trend of D.6
  (``--markdown`` prints them as the tables of docs/lignum-sizes.md).

Timings are noisy on a shared machine; re-run when it is quiet.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import warnings
from pathlib import Path

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import numpy as np  # noqa: E402
from _timing import timed  # noqa: E402

_ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(_ROOT / "plugins"))

# docs/models.md A.10: (preset, T) -> (live segments, created, height m, base diameter cm)
SPEC_A10 = {
    ("sf_synthetic", 8): ("~0.66 k", "-", "3.0", "-"),
    ("sf_synthetic", 12): ("~2.4 k", "-", "5.2", "-"),
    ("sf_synthetic", 15): ("3.6-4.5 k", "~4.8 k", "7.0-7.6", "~11"),
    ("sf_synthetic", 20): ("~6.5 k", "-", "10.8", "-"),
    ("sf_real", 15): ("~3.0 k", "~3.0 k", "4.9", "~10.7"),
    ("sf_real", 32): ("2.3-2.5 k (90-100 dead)", "5.8-6.3 k", "9.8-9.9", "13.7-14.4"),
    ("sf_test16", 12): ("1.15-1.19 k", "~1.2 k", "5.0-5.1", "-"),
}
# docs/models.md D.6 (sf_synthetic, T = 15): q_mean -> (H/crown, height, live segments)
SPEC_D6 = {0.05: (2.4, 4.2, "4.5 k"), 0.20: (3.6, 7.3, "-"), 0.35: (5.7, 11.8, "2.5 k")}
SEEDS = (1, 2, 3, 4, 5)


def _ssm(preset: str):
    warnings.filterwarnings("ignore", category=RuntimeWarning, module="bforest_core.registry")
    from bforest_lignum import LignumSSM

    return LignumSSM(preset=preset)


def sizes(tree) -> dict:
    """Sizes by the measurement conventions of docs/models.md (before D) (height and crown radius from segment end points)."""
    e = tree.end
    base = tree.start[0]
    return {
        "live": tree.n,
        "created": tree.metadata["segments_created"],
        "dead": int(tree.extras["is_dead"].sum()),
        "height": float(e[:, 2].max() - base[2]),
        "crown": float(np.hypot(e[:, 0] - base[0], e[:, 1] - base[1]).max()),
        "base_cm": float(200 * tree.radius[0]),
    }


def _numpy_workload():
    rng = np.random.default_rng(0)
    a = rng.random((400_000, 3))
    for _ in range(10):
        k = np.argsort(a[:, 0], kind="stable")
        a = a[k] * 1.0000001
        np.bincount((a[:, 1] * 1000).astype(np.int64), weights=a[:, 2], minlength=1000)
    return a


def _over_seeds(ssm, T: int):
    """Median and minimum wall time of one run per seed of SEEDS, and the trees."""
    ts, trees = [], []
    for seed in SEEDS:
        t, _, tree = timed(lambda: ssm.simulate({"years": T}, seed=seed), 1)
        ts.append(t)
        trees.append(tree)
    return float(np.median(ts)), float(np.min(ts)), trees


@contextlib.contextmanager
def _without_grid():
    """The shadow method choice of the code before the compiled bucket kernel."""
    from bforest_lignum import shadow

    saved = shadow._C_GRID
    shadow._C_GRID = float("inf")
    try:
        yield
    finally:
        shadow._C_GRID = saved


@contextlib.contextmanager
def _full_cost_model():
    """The shadow method chosen by the full cost model every year (before its short cut, 2026-12-07)."""
    from bforest_lignum import shadow

    saved = shadow.choose_method

    def full(rel, n_rcv, q_max):
        return shadow._cheapest(rel, n_rcv, q_max, shadow._sat_cost(rel, n_rcv, q_max))

    shadow.choose_method = full
    try:
        yield
    finally:
        shadow.choose_method = saved


def bench_lignum(repeats: int = 5, full: bool = False) -> dict:
    """Time the two A.12 cases and the same-run baselines; returns the figures."""
    from bforest_lignum.shadow import shadow_brute, shadow_fast, voxel_coords

    base_med, _, _ = timed(_numpy_workload, repeats)
    print(
        f"LIGNUM benchmark (single core; models: median/min over seeds {SEEDS[0]}-{SEEDS[-1]}; "
        f"kernels: median of {repeats} runs)"
    )
    print(f"  baseline numpy workload: {base_med * 1000:.1f} ms")
    out = {"baseline": base_med}
    cases = [("sf_synthetic", 15, 0.25), ("sf_real", 32, 0.2), ("sf_real", 40, 0.5)]
    for preset, T, target in cases:
        ssm = _ssm(preset)
        ssm.simulate({"years": T}, seed=1)  # warm-up (imports, compiled kernel cache)
        med, mn, trees = _over_seeds(ssm, T)
        with _without_grid():  # the previous code: the same choice among the other three methods
            old_med, _, old_trees = _over_seeds(ssm, T)
        with _full_cost_model():  # the method's cost model in full every year
            cm_med, _, cm_trees = _over_seeds(ssm, T)
        same = all(
            np.array_equal(a.start, b.start) and np.array_equal(a.radius, b.radius)
            for other in (old_trees, cm_trees)
            for a, b in zip(trees, other)
        )
        s = sizes(trees[0])
        flag = "ok" if med <= target else "OVER TARGET (machine load?)"
        print(
            f"  {preset:13s} T={T:2d}: median {med:.3f} s, min {mn:.3f} s over seeds {SEEDS[0]}-{SEEDS[-1]} "
            f"(target <= {target} s: {flag}); previous code {old_med:.3f} s ({old_med / med:.1f}x), "
            f"the full cost model every year {cm_med:.3f} s ({cm_med / med:.2f}x), "
            f"identical trees: {same}; {med / base_med:.1f} x baseline; seed 1: {s['live']} live / "
            f"{s['created']} created segments"
        )
        out[f"{preset}_T{T}"] = (med, mn, old_med, cm_med)
    # the hot spot against its brute-force reference, on the final sf_synthetic crown
    views = {}
    _ssm("sf_synthetic").simulate({}, seed=1, on_step=lambda t, v: views.__setitem__(t, v))
    v = views[max(views)]
    vox = voxel_coords(v.start + 0.5 * v.length[:, None] * v.axis, 0.02)
    f_med, _, S1 = timed(lambda: shadow_fast(vox, 10.0, 28), repeats)
    b_med, _, S2 = timed(lambda: shadow_brute(vox, 10.0, 28), max(1, min(repeats, 2)))
    print(
        f"  shadow kernel on {len(vox)} points: auto method {f_med * 1000:.1f} ms vs brute force "
        f"{b_med * 1000:.1f} ms ({b_med / f_med:.0f}x), equal: {bool(np.array_equal(S1, S2))}"
    )
    out["shadow"] = (f_med, b_med)
    return out


def size_table(markdown: bool = False) -> None:
    """Sizes over seeds 1-5 against A.10, and the D.6 apical-dominance trend."""
    rows = []
    for (preset, T), spec in SPEC_A10.items():
        ssm = _ssm(preset)
        ss = [sizes(ssm.simulate({"years": T}, seed=s)) for s in SEEDS]
        rows.append((preset, T, ss, spec))

    def rng_(vals, fmt):
        vals = np.asarray(vals, float)
        return f"{fmt.format(vals.min())}-{fmt.format(vals.max())} (mean {fmt.format(vals.mean())})"

    if markdown:
        print(
            "| preset | T | live segments | dead | created | height m | crown radius m | base Ø cm "
            "| A.10 live | A.10 created | A.10 height | A.10 base Ø |"
        )
        print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for preset, T, ss, spec in rows:
        cells = [
            rng_([s["live"] for s in ss], "{:.0f}"),
            rng_([s["dead"] for s in ss], "{:.0f}"),
            rng_([s["created"] for s in ss], "{:.0f}"),
            rng_([s["height"] for s in ss], "{:.2f}"),
            rng_([s["crown"] for s in ss], "{:.2f}"),
            rng_([s["base_cm"] for s in ss], "{:.1f}"),
        ]
        if markdown:
            print(f"| `{preset}` | {T} | " + " | ".join(cells) + " | " + " | ".join(spec) + " |")
        else:
            print(
                f"{preset:13s} T={T:2d}: live {cells[0]}, dead {cells[1]}, created {cells[2]}, "
                f"height {cells[3]} m, crown {cells[4]} m, base {cells[5]} cm | A.10: live {spec[0]}, "
                f"created {spec[1]}, height {spec[2]} m, base {spec[3]} cm"
            )
    print()
    if markdown:
        print("| q_mean | H / crown radius | height m | live segments | D.6 H/crown | D.6 height | D.6 live |")
        print("|---|---|---|---|---|---|---|")
    ssm = _ssm("sf_synthetic")
    for q, spec in SPEC_D6.items():
        ss = [sizes(ssm.simulate({"q_mean": q}, seed=s)) for s in SEEDS]
        ratio = np.mean([s["height"] / s["crown"] for s in ss])
        h = np.mean([s["height"] for s in ss])
        n = np.mean([s["live"] for s in ss])
        if markdown:
            print(f"| {q:.2f} | {ratio:.2f} | {h:.2f} | {n:.0f} | {spec[0]} | {spec[1]} | {spec[2]} |")
        else:
            print(
                f"q_mean {q:.2f}: H/crown {ratio:.2f}, height {h:.2f} m, live {n:.0f} | D.6: "
                f"{spec[0]}, {spec[1]} m, {spec[2]}"
            )


def bench_log(run: Path, n: int = 60, repeats: int = 5) -> tuple[float, float]:
    """Grow ``n`` points of a LIGNUM fit's log (drawn with seed 0, each with its logged model seed)
    with the shadow's short cut and with its full cost model, in turns; the medians (s)."""
    import json
    import random
    import sqlite3
    import time

    import bforest_core as bf
    from bforest_core.config import build_component

    cfg = bf.load_config(run / "config.toml")
    ssm = build_component(cfg, "ssm")
    with sqlite3.connect(run / "evaluations.sqlite") as con:
        rows = con.execute("SELECT params, seeds FROM evaluations WHERE status = 'ok' ORDER BY idx").fetchall()
    random.seed(0)
    pick = [({**cfg.ssm.fixed, **json.loads(p)}, json.loads(s)[0]) for p, s in random.sample(rows, min(n, len(rows)))]

    def grow():
        t = time.perf_counter()
        trees = [ssm.simulate(p, seed=s) for p, s in pick]
        return time.perf_counter() - t, trees

    grow()  # warm-up
    short, full = [], []
    for _ in range(repeats):
        t, a = grow()
        short.append(t)
        with _full_cost_model():
            t, b = grow()
        full.append(t)
    same = all(np.array_equal(x.start, y.start) and np.array_equal(x.radius, y.radius) for x, y in zip(a, b))
    ratios = np.array(full) / np.array(short)
    print(
        f"  {len(pick)} growths of the log of {run.name}: short cut {np.median(short):.3f} s, the full cost model "
        f"every year {np.median(full):.3f} s (paired ratio median {np.median(ratios):.3f}, "
        f"{ratios.min():.3f}-{ratios.max():.3f}); identical trees: {same}"
    )
    return float(np.median(short)), float(np.median(full))


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--sizes", action="store_true", help="also print sizes over seeds 1-5 (A.10, D.6)")
    ap.add_argument("--markdown", action="store_true", help="sizes as markdown tables only (no timing)")
    ap.add_argument(
        "--log", type=Path, metavar="RUN", help="also grow 60 points of a LIGNUM fit's log (its run folder)"
    )
    args = ap.parse_args(argv)
    if args.markdown:
        size_table(markdown=True)
        return
    bench_lignum(args.repeats)
    if args.log:
        bench_log(args.log, repeats=args.repeats)
    if args.sizes:
        print()
        size_table()


if __name__ == "__main__":
    main()
