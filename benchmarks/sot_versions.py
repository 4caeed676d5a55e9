"""SOT growth with this checkout against another (an older commit): time per tree, same trees?

    git worktree add /tmp/sot-old <commit>
    .venv/bin/python benchmarks/sot_versions.py --old /tmp/sot-old [--points 48] [--repeats 3] [--recipe R.toml]

Grows the trees a fit of an SOT recipe grows (``--recipe``, default the pine recipe
``examples/real/pine_sot.toml``; ``bforest init``'s recipe of a broadleaved tree for large trees):
``--points`` points of a scrambled Sobol' design over the recipe's search box (a bound scaled to
the tree, ``scaled_by``, is taken for a pine's 0.1 m), model seeds 1 and 2, with the recipe's model
settings and fixed parameters. Each
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
#: what a bound scaled to the tree (``scaled_by``) is taken to scale by: a pine's branch spacing (m)
SCALE = 0.1


def points(recipe: Path, n: int) -> list[dict]:
    """``n`` Sobol' points over the recipe's box (whole growth cycles), with its fixed parameters."""
    from scipy.stats import qmc

    ssm = tomllib.loads(recipe.read_text())["ssm"]
    free = ssm["free"]
    names = sorted(free)
    scale = [SCALE if "scaled_by" in free[k] else 1.0 for k in names]
    lo = [free[k]["lower"] * f for k, f in zip(names, scale)]
    hi = [free[k]["upper"] * f for k, f in zip(names, scale)]
    X = qmc.scale(qmc.Sobol(len(names), scramble=True, rng=1).random(n), lo, hi)
    fixed = ssm.get("fixed", {})
    return [{**fixed, **{k: (round(v) if k == "max_iter" else float(v)) for k, v in zip(names, x)}} for x in X]


def child(checkout: str, n: int, recipe: Path) -> None:
    """Grow the trees with the code of ``checkout``; print seconds and hashes as JSON."""
    sys.path[:0] = [checkout, str(Path(checkout) / "plugins")]
    import numpy as np

    import bforest_sot
    from bforest_sot.plugin import SOT

    assert Path(bforest_sot.__file__).resolve().is_relative_to(Path(checkout).resolve()), bforest_sot.__file__
    settings = {k: v for k, v in tomllib.loads(recipe.read_text())["ssm"].items() if k not in ("kind", "free", "fixed")}
    ssm = SOT(**settings)
    pts = points(recipe, n)

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


def run(checkout: Path, n: int, recipe: Path) -> dict:
    out = subprocess.run(
        [sys.executable, __file__, "--child", str(checkout), "--points", str(n), "--recipe", str(recipe)],
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
    ap.add_argument("--recipe", type=Path, default=RECIPE, help="an SOT recipe (its [ssm] section)")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.child:
        child(a.child, a.points, a.recipe.resolve())
        return
    if a.old is None or not (a.old / "plugins" / "bforest_sot").is_dir():
        raise SystemExit(f"--old {a.old}: not a checkout with plugins/bforest_sot (git worktree add PATH COMMIT)")
    recipe = a.recipe.resolve()
    new_t, old_t = [], []
    for _ in range(a.repeats):  # alternately, so a drift of the machine's speed hits both
        new, old = run(ROOT, a.points, recipe), run(a.old, a.points, recipe)
        new_t.append(new["seconds"] / new["trees"])
        old_t.append(old["seconds"] / old["trees"])
    same = new["hashes"] == old["hashes"]
    failed = sum(len(h) != 64 for h in new["hashes"])
    tn, to = statistics.median(new_t), statistics.median(old_t)
    print(f"SOT, {new['trees']} trees of {a.recipe.name}'s box ({failed} failed growths), median of {a.repeats}:")
    print(f"  this checkout {1e3 * tn:.1f} ms per tree, {a.old} {1e3 * to:.1f} ms per tree: {to / tn:.2f}x")
    print(f"  the same trees to the bit: {'yes' if same else 'NO'}")


if __name__ == "__main__":
    main()
