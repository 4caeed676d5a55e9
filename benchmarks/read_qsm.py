"""Benchmark of the QSM readers (plugins bforest_treeqsm and bforest_formats).

Prints the time to read every sample in ../shared/data/qsm (the largest first) and a synthetic
100 000-cylinder TreeQSM text file (17 columns + header, written to a temp dir with the plugin's
own writer), each against a numpy baseline measured in the same run: ``np.loadtxt`` and
``np.genfromtxt`` of the same text (parsing only, no validation, no Tree). Target: each read
under one second. Timings are best of ``--repeat`` runs (the machine is shared; re-run later
for quieter figures).

Usage::

    python benchmarks/read_qsm.py [--n 100000] [--repeat 3] [--data ../shared/data/qsm]
"""

from __future__ import annotations

import argparse
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

import bforest_core as bf

ROOT = Path(__file__).resolve().parents[1]


def best_of(fn, repeat: int) -> float:
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def synthetic_tree(n: int, seed: int = 0) -> bf.Tree:
    """A random cylinder tree of n cylinders: long extension chains with random laterals."""
    rng = np.random.default_rng(seed)
    parent = np.arange(-1, n - 1, dtype=np.int64)
    lateral = rng.random(n) < 0.15
    lateral[0] = False
    idx = np.flatnonzero(lateral)
    parent[idx] = (rng.random(idx.size) * idx).astype(np.int64)  # any earlier row
    # extension: the first child of every cylinder that continues its chain (row i -> i + 1)
    ext = np.full(n, -1, dtype=np.int64)
    cont = np.flatnonzero(~lateral[1:]) + 1
    ext[parent[cont]] = cont
    axis = rng.normal(size=(n, 3)) + [0, 0, 2.0]
    axis /= np.linalg.norm(axis, axis=1)[:, None]
    length = rng.uniform(0.02, 0.3, n)
    radius = np.exp(rng.uniform(np.log(0.002), np.log(0.3), n))
    start = rng.uniform(-5, 5, (n, 3)) + [0, 0, 10]
    return bf.Tree(start, axis, length, radius, parent, ext)


def compare(label: str, path: Path, repeat: int, skiprows: int, delimiter=None) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        t_read = best_of(lambda: bf.read_qsm(path), repeat)
        tree = bf.read_qsm(path)
    line = f"{label:38s} {tree.n:7d} cyl  read_qsm {t_read * 1e3:8.1f} ms"
    if skiprows is not None:
        t_lt = best_of(lambda: np.loadtxt(path, skiprows=skiprows, delimiter=delimiter, comments=None), repeat)
        t_gf = best_of(lambda: np.genfromtxt(path, skip_header=skiprows, delimiter=delimiter), repeat)
        line += (
            f" | np.loadtxt {t_lt * 1e3:8.1f} ms | np.genfromtxt {t_gf * 1e3:8.1f} ms"
            f" | read_qsm / loadtxt = {t_read / t_lt:4.2f}"
        )
    print(line + ("" if t_read < 1.0 else "   ** over 1 s **"))


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=100_000, help="cylinders of the synthetic text file")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data" / "qsm")
    a = ap.parse_args(argv)

    bf.discover()  # plugin loading is not part of the timings
    print(f"QSM reader benchmark (best of {a.repeat})")
    if a.data.is_dir():
        files = sorted(a.data.iterdir(), key=lambda p: -p.stat().st_size)
        for p in files:
            text = p.suffix in (".txt", ".csv")
            skip = (1 if p.read_bytes()[:1].isalpha() or p.suffix == ".csv" else 0) if text else None
            compare(
                p.name + (" (largest)" if p == files[0] else ""), p, a.repeat, skip, "," if p.suffix == ".csv" else None
            )
    else:
        print(f"(sample folder {a.data} not found: only the synthetic file is timed)")

    with tempfile.TemporaryDirectory() as d:
        tree = synthetic_tree(a.n)
        path = Path(d) / "cylinder_synthetic.txt"
        t_w = best_of(lambda: bf.write_tree(tree, path), 1)
        print(f"synthetic: wrote {a.n} cylinders ({path.stat().st_size / 1e6:.1f} MB, %.9g) in {t_w * 1e3:.0f} ms")
        compare(f"synthetic TreeQSM text ({a.n})", path, a.repeat, 1)
        back = bf.read_qsm(path)
        assert back.equals(tree, atol=1e-6), "synthetic round trip failed"
        csv = Path(d) / "synthetic.csv"
        bf.write_tree(tree, csv)
        compare(f"synthetic native CSV ({a.n})", csv, a.repeat, 1, ",")


if __name__ == "__main__":
    main()
