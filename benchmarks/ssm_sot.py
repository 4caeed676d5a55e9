"""Benchmark and size check of the SOT growth model (docs/models.md B.4, B.9).

Run ``python benchmarks/ssm_sot.py [--repeats 5] [--full]`` (or through ``benchmarks/ssm.py``).
Prints:

* the median (and minimum) wall time of ``repeats`` runs, single core, for the calibrated default
  at 18 cycles (target <= 0.2 s) and for a ~10 000-segment tree (default parameters at 21 cycles;
  target <= 0.5 s); with ``--full`` also 30 cycles (target <= 4 s);
* baselines measured in the same run: a fixed numpy workload (each model time is also given as a
  multiple of it, so figures from a loaded machine can be compared) and the original's per-voxel
  Python loop for casting shadows against the batched sum used here (a compiled loop over the
  touched voxels, ``bforest_sot/kernels.py``);
* tree sizes (live segments, height, crown radius, base diameter) over seeds 1-5 beside the
  indicative table of B.4 (no clone noise) and with the default clone noise (table of E).

Timings are noisy on a shared machine; re-run when it is quiet.
"""

from __future__ import annotations

import argparse
import os
import warnings

# single core, as the targets of docs/models.md B.9 (set before numpy loads its BLAS)
for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import numpy as np  # noqa: E402
from _timing import timed  # noqa: E402

# docs/models.md B.4: cycles -> (live segments, height m, crown radius m, base diameter m, time budget s)
SPEC_B4 = {
    8: ("~130", 4.3, 1.4, 0.07, 0.05),
    12: ("~0.6 k", 6.7, 2.5, 0.14, 0.1),
    16: ("~2.4 k", 8.6, 3.6, 0.27, 0.2),
    18: ("4.0-4.6 k", 9.3, 4.0, 0.36, 0.2),
    30: ("~40 k", 12.0, 7.0, 1.1, 4.0),
}
NO_CLONE_NOISE = {"branch_angle_sd": 0.0, "phyllotaxis_sd": 0.0}


def _model():
    warnings.filterwarnings("ignore", category=RuntimeWarning, module="bforest_core.registry")
    from bforest_sot.plugin import SOT

    return SOT()


def sizes(tree) -> tuple[int, float, float, float]:
    """(live segments, height, crown radius, base diameter) by the measurement conventions of docs/models.md (before D)."""
    e = tree.end
    base = tree.start[0]
    return (
        tree.n,
        float(e[:, 2].max() - base[2]),
        float(np.hypot(e[:, 0] - base[0], e[:, 1] - base[1]).max()),
        float(2 * tree.radius[0]),
    )


def machine_baseline(repeats: int) -> float:
    """Median time of a fixed numpy workload (sort + gather + bincount, ~the model's kind of work)."""
    rng = np.random.default_rng(0)
    x = rng.random(400_000)
    idx = rng.integers(0, 300_000, 400_000)

    def work():
        np.sort(x, kind="stable")
        np.bincount(idx, weights=x[idx], minlength=300_000)
        np.exp(x[idx])

    return timed(work, max(repeats, 5))[0]


def shadow_baseline(repeats: int) -> tuple[float, float]:
    """Casting 1 000 segment shadows: the original's per-voxel Python loop vs one batched sum.

    Returns (loop seconds, batched seconds), medians; both give the same field (checked)."""
    from bforest_sot.light import LightField

    rng = np.random.default_rng(1)
    pts = np.column_stack([rng.normal(0, 1.5, 1000), rng.normal(0, 1.5, 1000), rng.uniform(2, 10, 1000)])

    f = LightField(12.0, 0.2, 6, 1.0, 0.5, 2.0)
    n = f.n_vox
    ijk = f.voxel_of(pts)

    def loop():
        log = f.log_e0.reshape(n, n, n)
        for i, j, k in ijk:
            for di, dj, dk, lf in zip(f.di, f.dj, f.dk, f.log_f):
                a, b, c = i + di, j + dj, k + dk
                if 0 <= a < n and 0 <= b < n and c >= 0:
                    log[a, b, c] += lf
        return log.ravel()

    def batched():
        f.cast(pts)
        return f.log_e

    t_loop, _, ref = timed(loop, 1 if repeats < 3 else 3)
    f.rebuild(pts)
    assert np.max(np.abs(ref - f.log_e)) < 1e-9
    t_vec, _, _ = timed(batched, repeats)
    return t_loop, t_vec


def bench_sot(repeats: int = 5, full: bool = False, seeds=(1, 2, 3, 4, 5)) -> dict:
    """Run the SOT benchmark and size table; print them and return the figures."""
    ssm = _model()
    ssm.simulate({"max_iter": 8}, 1)  # warm-up (imports, first allocations)
    base = machine_baseline(repeats)
    print(f"SOT benchmark (single core, median of {repeats} runs; machine baseline {1e3 * base:.1f} ms)")
    t_loop, t_vec = shadow_baseline(repeats)
    print(
        f"  shadow casting, 1 000 segments: per-voxel Python loop {1e3 * t_loop:.0f} ms, "
        f"batched sum {1e3 * t_vec:.2f} ms ({t_loop / t_vec:.0f}x)"
    )
    cases = [
        ("calibrated default, 18 cycles (seed 2)", {"max_iter": 18}, 2, 0.2),
        ("~10 k segments (default, 21 cycles, seed 1)", {"max_iter": 21}, 1, 0.5),
    ]
    if full:
        cases.append(("default, 30 cycles (at the roof, seed 1)", {"max_iter": 30}, 1, 4.0))
    results = {"baseline_s": base, "shadow_loop_s": t_loop, "shadow_batched_s": t_vec, "timings": [], "sizes": []}
    print(f"  {'case':60s} {'segments':>8s} {'median s':>9s} {'min s':>7s} {'target s':>8s} {'x baseline':>10s}")
    import bforest_sot.light as light

    def fresh(params, seed):  # a seed not seen before: the initial light field is computed
        light._INITIAL.clear()
        return ssm.simulate(params, seed)

    for label, params, seed, target in cases:
        # a fit grows every candidate with the same model seeds: their initial fields are cached
        for kind, fn in (("repeated seed", ssm.simulate), ("fresh seed", fresh)):
            med, mn, tree = timed(lambda: fn(params, seed), repeats)
            ok = "ok" if med <= target else "OVER"
            print(
                f"  {label + ', ' + kind:60s} {tree.n:8d} {med:9.3f} {mn:7.3f} {target:8.2f} {med / base:10.1f}  {ok}"
            )
            results["timings"].append(
                {"case": f"{label}, {kind}", "segments": tree.n, "median_s": med, "min_s": mn, "target_s": target}
            )

    print(f"\nSizes over seeds {list(seeds)} (mean; range of segments) vs docs/models.md B.4 (no clone noise):")
    print(
        f"  {'cycles':>6s} {'noise':>6s} {'segments':>13s} {'B.4':>10s} {'height':>7s} {'B.4':>5s} "
        f"{'crown r':>7s} {'B.4':>5s} {'base d':>7s} {'B.4':>5s}"
    )
    cycles = [8, 12, 16, 18] + ([30] if full else [])
    for T in cycles:
        for noise, extra in (("none", NO_CLONE_NOISE), ("clone", {})):
            if noise == "clone" and T != 18:
                continue
            rows = np.array([sizes(ssm.simulate({"max_iter": T, **extra}, s)) for s in seeds])
            spec = SPEC_B4[T]
            seg = f"{int(rows[:, 0].min())}-{int(rows[:, 0].max())}"
            print(
                f"  {T:6d} {noise:>6s} {seg:>13s} {spec[0]:>10s} {rows[:, 1].mean():7.2f} {spec[1]:5.1f} "
                f"{rows[:, 2].mean():7.2f} {spec[2]:5.1f} {rows[:, 3].mean():7.3f} {spec[3]:5.2f}"
            )
            results["sizes"].append(
                {
                    "cycles": T,
                    "noise": noise,
                    "segments": rows[:, 0].tolist(),
                    "height": rows[:, 1].mean(),
                    "crown_radius": rows[:, 2].mean(),
                    "base_diameter": rows[:, 3].mean(),
                }
            )
    return results


def main(argv=None):
    ap = argparse.ArgumentParser(description="SOT growth model benchmark")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--full", action="store_true", help="also the 30-cycle case (slow)")
    args = ap.parse_args(argv)
    bench_sot(args.repeats, args.full)


if __name__ == "__main__":
    main()
