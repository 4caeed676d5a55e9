"""Time the L-system model on trees of a few hundred to ~10 000 internodes.

Prints milliseconds per simulated tree and, as the baseline measured in the same run, the time
of building the same ``bforest_core.Tree`` from ready arrays (the part every SSM pays): the
ratio is the cost of the rewriting + turtle + pipe model on top of the core tree.

    python docs/examples/bforest-example-ssm/benchmarks/bench_lsystem.py
"""

import time

import numpy as np

import bforest_core as bf
from bforest_example_ssm.model import LSystemSSM, grow

CASES = [
    {"iterations": 6},
    {"iterations": 8, "whorl_size": 4},
    {"iterations": 8, "whorl_size": 4, "lateral_prob": 1.0, "bare_steps": 0},
    {"iterations": 9, "whorl_size": 4, "lateral_prob": 1.0, "bare_steps": 0},
]


def best_of(fn, repeat=15):
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def main():
    ssm = LSystemSSM(max_segments=100_000)
    print(f"{'internodes':>10} {'simulate ms':>12} {'Tree() ms':>10} {'ratio':>6}  params")
    for params in CASES:
        p = ssm.resolve_params(params)
        tree = ssm.simulate(p, 1)
        t_sim = best_of(lambda: ssm.simulate(p, 1))
        a = grow(p, np.random.default_rng(1), 100_000)
        t_tree = best_of(lambda: bf.Tree(a["start"], a["axis"], a["length"], a["radius"], a["parent"], a["extension"]))
        print(f"{tree.n:>10} {t_sim * 1e3:>12.2f} {t_tree * 1e3:>10.2f} {t_sim / t_tree:>6.1f}  {params}")


if __name__ == "__main__":
    main()
