"""Growth with this checkout against another (an older commit): time per tree, the same trees?

    git worktree add /tmp/sot-old <commit>      (and python3 dev.py env there)
    .venv/bin/python benchmarks/sot_versions.py --old /tmp/sot-old [--points 48] [--repeats 3]
        [--seeds 1 2] [--recipe R.toml ...] [--no-timing]

Grows the trees a fit of each recipe grows (``--recipe``, any number; default the SOT pine recipe
``examples/real/pine_sot.toml``; ``bforest init``'s recipes of a broadleaved tree for large trees;
a LIGNUM recipe works too): ``--points`` points of a scrambled Sobol' design over the recipe's
search box (a bound scaled to the tree, ``scaled_by``, by the measure of the recipe's target), each with
every model seed of ``--seeds``, with the recipe's model settings and fixed parameters. A fixed
value that one checkout's model takes as a setting and the other's as a parameter (LIGNUM's
``piece_length`` since issue 76) is given to each as it takes it. Each checkout runs in its own process with its own
``.venv`` (imports and numba's compiled-code cache load are left out of the time: the first
point is grown once before the clock starts), alternately, ``--repeats`` times; the figure is
the median. Prints per recipe the milliseconds per tree of both, their ratio, and whether the
two grow the same trees to the bit (a hash of every cylinder's start, axis, length, radius,
parent and extension, and the status; a failed growth by its partial tree). Exits 1 when a recipe's trees differ.
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


def points(recipe: Path, n: int) -> list[dict]:
    """``n`` Sobol' points over the box of a recipe's ``[ssm]`` section, with its fixed parameters
    (a bound scaled to the tree resolved with the measure of the recipe's target QSM)."""
    from scipy.stats import qmc

    raw = tomllib.loads(recipe.read_text())
    ssm = raw["ssm"]
    free = ssm.get("free", {})
    names = sorted(free)
    scale = [1.0] * len(names)
    if any("scaled_by" in free[k] for k in names):
        import bforest_core as bf
        from bforest_core.metrics import measure_tree

        m = measure_tree(bf.read_qsm(recipe.parent / raw["target"]["qsm"]))
        scale = [getattr(m, free[k]["scaled_by"]) if "scaled_by" in free[k] else 1.0 for k in names]
    lo = [free[k]["lower"] * f for k, f in zip(names, scale)]
    hi = [free[k]["upper"] * f for k, f in zip(names, scale)]
    X = qmc.scale(qmc.Sobol(len(names), scramble=True, rng=1).random(n), lo, hi)
    fixed = ssm.get("fixed", {})
    return [{**fixed, **{k: float(v) for k, v in zip(names, x)}} for x in X]


def child(checkout: str, n: int, recipe: Path, seeds: list[int]) -> None:
    """Grow the trees with the code of ``checkout``; print seconds and hashes as JSON."""
    import numpy as np

    import bforest_core as bf

    assert Path(bf.__file__).resolve().is_relative_to(Path(checkout).resolve()), bf.__file__
    section = tomllib.loads(recipe.read_text())["ssm"]
    settings = {k: v for k, v in section.items() if k not in ("kind", "free", "fixed", "topology")}
    cls = bf.discover().get("ssm", section["kind"])
    # a value one checkout's model takes as a setting and the other's as a fixed parameter
    as_param = {k: v for k, v in settings.items() if k not in cls.Settings.model_fields}
    settings = {k: v for k, v in settings.items() if k not in as_param}
    known = {p.name for p in cls(**settings).parameters}
    moved = {k: v for k, v in section.get("fixed", {}).items() if k not in known and k in cls.Settings.model_fields}
    ssm = cls(**settings, **moved)
    pts = [{**as_param, **{k: v for k, v in p.items() if k not in moved}} for p in points(recipe, n)]

    def grow(p, seed):
        status = "ok"
        try:
            t = ssm.simulate(p, seed)
        except bf.SimulationFailed as exc:  # a failed growth (too many segments) is part of a fit too
            status, t = f"{exc.status} ({exc.message})", exc.tree
        h = hashlib.sha256()
        for a in (t.start, t.axis, t.length, t.radius, t.parent, t.extension) if t is not None else ():
            h.update(np.ascontiguousarray(a).tobytes())
        return f"{status}: {h.hexdigest()}"

    grow(pts[0], seeds[0])  # imports, first allocations, numba's cache
    t0 = time.perf_counter()
    hashes = [grow(p, seed) for p in pts for seed in seeds]
    print(json.dumps({"seconds": time.perf_counter() - t0, "trees": len(hashes), "hashes": hashes}))


def run(checkout: Path, n: int, recipe: Path, seeds: list[int]) -> dict:
    venv = checkout / ".venv" / "bin" / "python"
    args = ["--child", str(checkout), "--points", str(n), "--recipe", str(recipe), "--seeds", *map(str, seeds)]
    out = subprocess.run(
        [str(venv if venv.exists() else sys.executable), __file__, *args], capture_output=True, text=True
    )
    if out.returncode:
        raise SystemExit(f"{checkout}, {recipe.name}: {out.stderr.strip().splitlines()[-1]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--old", type=Path, help="the other checkout (a git worktree of an older commit)")
    ap.add_argument("--points", type=int, default=48)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2], help="model seeds of every point")
    ap.add_argument("--recipe", type=Path, action="append", help="a recipe (its [ssm] section); repeat for more")
    ap.add_argument("--no-timing", action="store_true", help="one run per checkout: only whether the trees agree")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    recipes = [r.resolve() for r in (a.recipe or [RECIPE])]
    if a.child:
        child(a.child, a.points, recipes[0], a.seeds)
        return 0
    if a.old is None or not (a.old / "bforest_core").is_dir():
        raise SystemExit(f"--old {a.old}: not a checkout (git worktree add PATH COMMIT)")
    repeats = 1 if a.no_timing else a.repeats
    differ = 0
    for recipe in recipes:
        new_t, old_t = [], []
        for _ in range(repeats):  # alternately, so a drift of the machine's speed hits both
            new, old = run(ROOT, a.points, recipe, a.seeds), run(a.old.resolve(), a.points, recipe, a.seeds)
            new_t.append(new["seconds"] / new["trees"])
            old_t.append(old["seconds"] / old["trees"])
        same = new["hashes"] == old["hashes"]
        differ += not same
        failed = sum(not h.startswith("ok: ") for h in new["hashes"])
        tn, to = statistics.median(new_t), statistics.median(old_t)
        timing = "" if a.no_timing else f"; {1e3 * tn:.1f} ms per tree here, {1e3 * to:.1f} there ({to / tn:.2f}x)"
        print(
            f"{recipe.name}: {new['trees']} trees ({failed} failed growths), seeds {a.seeds}: "
            f"{'the same to the bit' if same else 'DIFFERENT'}{timing}",
            flush=True,
        )
    print(f"verdict: {'IDENTICAL' if not differ else f'{differ} recipe(s) DIFFERENT'} ({len(recipes)} recipes)")
    return 1 if differ else 0


if __name__ == "__main__":
    sys.exit(main())
