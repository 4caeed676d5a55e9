"""How long `bforest posterior` takes for a new tree from a trained estimator file, reading the QSM
included, as a user runs it (a fresh process each time), beside a baseline measured in the same
run: `bforest info` on the same tree (the command's start-up and the reading of the QSM).

    .venv/bin/python benchmarks/amortised_posterior.py [--estimator FILE | --model sot] [--trees PATHS] [--repeats 3]

Per tree it prints the wall time of

* ``cold``: the first call on a machine (an empty JAX compilation cache: JAX compiles the flow's
  sampling once; later processes read it from the cache);
* ``posterior``: later calls (the cache warm), without the corner plot (``--no-figure``);
* ``+ figure``: the same with the corner plot (what a user gets by default);
* ``info``: `bforest info` on the same tree (the baseline).

The times are wall times of the whole command (the interpreter's start included), the median of
``--repeats`` calls; the load average is printed beside them (timings on a machine shared with
other work are marked as such in docs/performance.md). The commands run as on a user's machine,
where Python keeps the compiled bytecode of the modules it imports: a ``PYTHONDONTWRITEBYTECODE``
in the caller's environment (set on some build machines) is left out, since it makes every call
compile the project's modules again (about a second).
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
EXE = str(Path(sys.executable).with_name("bforest"))
DATA = ROOT.parent / "shared" / "data" / "qsm"


def _wall(args: list[str], env: dict | None = None) -> float:
    env = {k: v for k, v in (env or os.environ).items() if k != "PYTHONDONTWRITEBYTECODE"}
    t0 = time.perf_counter()
    r = subprocess.run([EXE, *args], capture_output=True, text=True, env=env)
    if r.returncode != 0:
        raise SystemExit(f"bforest {' '.join(args)} failed:\n{r.stderr[-1500:]}")
    return time.perf_counter() - t0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--estimator", help="a trained estimator file (default: the shipped one of --model)")
    ap.add_argument("--model", default="sot", help="model of the shipped estimator (default sot)")
    ap.add_argument("--trees", nargs="*", help="QSM files (default: the three Ruotsinkyla pines)")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)
    trees = args.trees or [str(DATA / f"pine_ruotsinkyla_{k}.mat") for k in (1, 2, 3)]
    which = ["--estimator", args.estimator] if args.estimator else ["--model", args.model]
    print(f"load average at start: {os.getloadavg()[0]:.2f} ({os.cpu_count()} cores)")
    print(f"{'tree':<28}{'cold':>8}{'posterior':>11}{'+ figure':>10}{'info':>8}   (s, wall, median of {args.repeats})")
    with tempfile.TemporaryDirectory() as tmp:
        for i, tree in enumerate(trees):
            out = Path(tmp) / f"p{i}"
            cold = None
            if i == 0:  # the first call on a machine: JAX compiles into an empty cache
                env = {**os.environ, "BFOREST_JAX_CACHE": str(Path(tmp) / "cache")}
                cold = _wall(["posterior", tree, *which, "-o", str(out), "--no-figure", "-q", "--overwrite"], env)
            warm = [
                _wall(["posterior", tree, *which, "-o", str(out), "--no-figure", "-q", "--overwrite"])
                for _ in range(args.repeats)
            ]
            fig = [_wall(["posterior", tree, *which, "-o", str(out), "-q", "--overwrite"]) for _ in range(args.repeats)]
            info = [_wall(["info", tree]) for _ in range(args.repeats)]
            print(
                f"{Path(tree).stem:<28}{'-' if cold is None else f'{cold:.1f}':>8}{statistics.median(warm):>11.1f}"
                f"{statistics.median(fig):>10.1f}{statistics.median(info):>8.1f}"
            )
    print(f"load average at end: {os.getloadavg()[0]:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
