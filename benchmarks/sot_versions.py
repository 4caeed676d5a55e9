"""SOT growth with this checkout against another (an older commit): time per tree, same trees?

    git worktree add /tmp/sot-old <commit>
    .venv/bin/python benchmarks/sot_versions.py --old /tmp/sot-old [--points 48] [--repeats 3]

Grows the trees a fit of the pine SOT recipe grows: ``--points`` points of a scrambled Sobol'
design over the recipe's search box (``examples/real/pine_sot.toml``; the internode at 0.8-1.45 x
0.1 m, a pine's branch spacing), model seeds 1 and 2, with the recipe's model settings. Each
checkout runs in its own process (imports and numba's compiled-code cache load are left out of the
time: the first point is grown once before the clock starts), alternately, ``--repeats`` times;
the figure is the median. Prints the milliseconds per tree of both, their ratio, and whether the
two grow the same trees to the bit (a hash of every cylinder's start, axis, length, radius and
parent).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import statistics
import subprocess
import sys
import time
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RECIPE = ROOT / "examples" / "real" / "pine_sot.toml"


def points(n: int) -> list[dict]:
    """``n`` Sobol' points over the recipe's box (whole growth cycles)."""
    from scipy.stats import qmc

    free = tomllib.loads(RECIPE.read_text())["ssm"]["free"]
    names = sorted(free)
    lo = [free[k]["lower"] * (0.1 if k == "node_length" else 1.0) for k in names]
    hi = [free[k]["upper"] * (0.1 if k == "node_length" else 1.0) for k in names]
    X = qmc.scale(qmc.Sobol(len(names), scramble=True, rng=1).random(n), lo, hi)
    return [{k: (round(v) if k == "max_iter" else float(v)) for k, v in zip(names, x)} for x in X]


def child(checkout: str, n: int) -> None:
    """Grow the trees with the code of ``checkout``; print seconds and hashes as JSON."""
    sys.path[:0] = [checkout, str(Path(checkout) / "plugins")]
    import numpy as np
    from bforest_sot.plugin import SOT

    import bforest_sot

    assert Path(bforest_sot.__file__).resolve().is_relative_to(Path(checkout).resolve()), bforest_sot.__file__
    model = tomllib.loads(RECIPE.read_text())["ssm"]
    ssm = SOT(order_mode=model["order_mode"], max_live_segments=model["max_live_segments"])
    pts = [{**p, "span": model["fixed"]["span"]} for p in points(n)]

    def grow(p, seed):
        try:
            t = ssm.simulate(p, seed)
        except Exception as exc:  # a failed growth (too many segments) is part of a fit too
            return type(exc).__name__
        h = hashlib.sha256()
        for a in (t.start, t.axis, t.length, t.radius, t.parent):
            h.update(np.ascontiguousarray(a).tobytes())
        return h.hexdigest()

    grow(pts[0], 1)  # imports, first allocations, numba's cache
    t0 = time.perf_counter()
    hashes = [grow(p, seed) for p in pts for seed in (1, 2)]
    print(json.dumps({"seconds": time.perf_counter() - t0, "trees": len(hashes), "hashes": hashes}))


def run(checkout: Path, n: int) -> dict:
    out = subprocess.run(
        [sys.executable, __file__, "--child", str(checkout), "--points", str(n)],
        capture_output=True,
        text=True,
        check=True,
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--old", type=Path, help="the other checkout (a git worktree of an older commit)")
    ap.add_argument("--points", type=int, default=48)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--child", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.child:
        child(a.child, a.points)
        return
    if a.old is None or not (a.old / "plugins" / "bforest_sot").is_dir():
        raise SystemExit(f"--old {a.old}: not a checkout with plugins/bforest_sot (git worktree add PATH COMMIT)")
    new_t, old_t = [], []
    for _ in range(a.repeats):  # alternately, so a drift of the machine's speed hits both
        new, old = run(ROOT, a.points), run(a.old, a.points)
        new_t.append(new["seconds"] / new["trees"])
        old_t.append(old["seconds"] / old["trees"])
    same = new["hashes"] == old["hashes"]
    failed = sum(len(h) != 64 for h in new["hashes"])
    tn, to = statistics.median(new_t), statistics.median(old_t)
    print(f"SOT, {new['trees']} trees of the pine recipe's box ({failed} failed growths), median of {a.repeats}:")
    print(f"  this checkout {1e3 * tn:.1f} ms per tree, {a.old} {1e3 * to:.1f} ms per tree: {to / tn:.2f}x")
    print(f"  the same trees to the bit: {'yes' if same else 'NO'}")


if __name__ == "__main__":
    main()
