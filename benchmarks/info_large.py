"""Benchmark of ``bforest info`` on the QSM of a large tree (a plot's QSMs hold 10^5-10^6 cylinders).

Grows a synthetic tree of about ``--n`` cylinders (default 1 000 000): a trunk whose cylinders
each bear a lateral branch, theirs in turn, down to the order that reaches the size (every axis
a chain of cylinders that tapers, bends a little at random and holds a random azimuth and a
branching angle of 35-65 deg, so the crown is a cloud of thin branches, as a QSM's is). The
tree is written as TreeQSM text with the project's own writer, and then, each in a process of
its own (wall time, and the peak resident memory of its processes from ``wait4``):

* baseline: reading the file alone (``bforest_core.read_qsm``), the floor of any command on it;
* ``bforest init`` of the file, another command that reads all of it (6.6 s and 0.7 GB at 1 M in
  the probe of issue 79);
* ``bforest info`` of the file, the command under test (target: <= 30 s and <= 2 GB on 2 cores).

Usage::

    python benchmarks/info_large.py [--n 1000000] [--keep DIR]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import bforest_core as bf


def _rotate(v: np.ndarray, k: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rotate the unit vectors ``v`` about the unit axes ``k`` by ``angle`` (Rodrigues)."""
    c, s = np.cos(angle)[:, None], np.sin(angle)[:, None]
    return v * c + np.cross(k, v) * s + k * (k * v).sum(1, keepdims=True) * (1 - c)


def _normal(v: np.ndarray, rng) -> np.ndarray:
    """A random unit vector perpendicular to each row of ``v``."""
    r = rng.normal(size=v.shape)
    r -= v * (r * v).sum(1, keepdims=True)
    return r / np.linalg.norm(r, axis=1, keepdims=True)


def synthetic_crown(n: int = 1_000_000, seed: int = 0) -> bf.Tree:
    """A branching tree of about ``n`` cylinders (see the module text), built order by order."""
    rng = np.random.default_rng(seed)
    trunk = 120
    # cylinders per axis of each order, scaled so that the orders together hold about n
    per = np.array([trunk, 40, 16, 8, 5, 3], float)
    counts = np.cumprod(per)
    scale = 1.0
    for _ in range(60):
        c = np.cumprod(np.maximum(np.round(per * [1, scale, scale, scale, scale, scale]), 2))
        if c.sum() >= n:
            break
        scale *= 1.1
    per = np.maximum(np.round(per * [1, scale, scale, scale, scale, scale]), 2).astype(int)
    counts = np.cumprod(per)
    orders = int(np.searchsorted(np.cumsum(counts), n) + 1)
    start_rows, axis_rows, length_rows, radius_rows, parent_rows, ext_rows = [], [], [], [], [], []
    # the axes of the current order: base point, direction, parent cylinder, base radius, cylinder length
    base = np.zeros((1, 3))
    direction = np.array([[0.0, 0.0, 1.0]])
    parent = np.array([-1])
    r0, l0 = np.array([0.35]), np.array([0.25])
    offset = 0
    for order in range(min(orders, len(per))):
        m, k = base.shape[0], int(per[order])
        if offset + m * k > n:  # the last order: as many of its axes as reach n
            pick = np.sort(rng.choice(m, min(m, -(-(n - offset) // k)), replace=False))  # spread over the crown
            base, direction, parent, r0, l0 = base[pick], direction[pick], parent[pick], r0[pick], l0[pick]
            m = pick.size
        # every axis a chain of k cylinders: bends of a few degrees, tapering to a third of its base
        d = np.repeat(direction, k, axis=0)
        bend = np.radians(rng.normal(0, 6 if order else 1.5, m * k))
        d = _rotate(d, _normal(d, rng), bend)
        d = d.reshape(m, k, 3)
        length = np.repeat(l0, k).reshape(m, k) * rng.uniform(0.8, 1.2, (m, k))
        steps = d * length[..., None]
        start = base[:, None, :] + np.concatenate([np.zeros((m, 1, 3)), np.cumsum(steps, 1)[:, :-1]], 1)
        radius = r0[:, None] * np.linspace(1.0, 0.3, k)[None, :]
        rows = offset + np.arange(m * k).reshape(m, k)
        par = np.concatenate([parent[:, None], rows[:, :-1]], 1)
        ext = np.concatenate([rows[:, 1:], np.full((m, 1), -1)], 1)
        start_rows.append(start.reshape(-1, 3))
        axis_rows.append(d.reshape(-1, 3))
        length_rows.append(length.reshape(-1))
        radius_rows.append(radius.reshape(-1))
        parent_rows.append(par.reshape(-1))
        ext_rows.append(ext.reshape(-1))
        offset += m * k
        if offset >= n or order + 1 >= len(per):
            break
        # a lateral on every cylinder of this order but the last two of each axis
        bearing = rows[:, :-2].reshape(-1)
        if bearing.size == 0:
            break
        j = bearing - rows[0, 0]
        pd = d.reshape(-1, 3)[j]
        angle = np.radians(rng.uniform(35, 65, bearing.size))
        az = _normal(pd, rng)
        direction = _rotate(pd, az, angle)
        base = start.reshape(-1, 3)[j] + pd * length.reshape(-1)[j, None] * 0.5
        parent = bearing
        r0 = radius.reshape(-1)[j] * 0.6
        l0 = length.reshape(-1)[j] * 0.75
    return bf.Tree(
        np.concatenate(start_rows),
        np.concatenate(axis_rows),
        np.concatenate(length_rows),
        np.concatenate(radius_rows),
        np.concatenate(parent_rows),
        np.concatenate(ext_rows),
    )


def measure(argv: list[str]) -> tuple[float, float, int, str]:
    """Wall time (s), peak resident memory (GB: the largest of the command's processes) and exit
    code of one command in a process of its own, and the tail of its output."""
    with tempfile.TemporaryFile("w+") as out:
        t0 = time.perf_counter()
        proc = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT, text=True)
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
        proc.returncode = os.waitstatus_to_exitcode(status)
        out.seek(0)
        return wall, usage.ru_maxrss / 2**20, proc.returncode, out.read()[-300:]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=1_000_000, help="cylinders of the synthetic tree")
    ap.add_argument("--keep", type=Path, help="write the QSM here (default: a temporary folder)")
    args = ap.parse_args()
    folder = args.keep or Path(tempfile.mkdtemp(prefix="bforest-info-"))
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"synthetic_{args.n}.txt"
    t0 = time.perf_counter()
    # grown and written in a process of its own: a child forked from a process holding the tree
    # would count its memory in the child's peak
    grow = f"import sys; sys.path.insert(0, {str(Path(__file__).parent)!r}); import info_large as b; import bforest_core as bf; t = b.synthetic_crown({args.n}); bf.write_tree(t, {str(path)!r}); print(t.n, t.n_branches, t.max_order)"
    n, branches, order = subprocess.run(
        [sys.executable, "-c", grow], check=True, capture_output=True, text=True
    ).stdout.split()
    print(
        f"synthetic tree: {n} cylinders, {branches} branches, order {order}; grown and written in "
        f"{time.perf_counter() - t0:.1f} s ({path.stat().st_size / 1e6:.0f} MB)",
        flush=True,
    )
    exe = Path(sys.executable).with_name("bforest")
    env_note = f"cores {len(os.sched_getaffinity(0))}, load {os.getloadavg()[0]:.1f}"
    rows = [
        ("baseline: read the file", [sys.executable, "-c", f"import bforest_core as bf; bf.read_qsm({str(path)!r})"]),
        ("bforest init", [str(exe), "init", str(path), "-o", str(folder / "init.toml"), "--overwrite"]),
        ("bforest info", [str(exe), "info", str(path)]),
    ]
    print(f"{'command':<26} {'wall (s)':>9} {'peak RSS (GB)':>14}   ({env_note})")
    failed = 0
    for label, argv in rows:
        wall, peak, code, out = measure(argv)
        print(f"{label:<26} {wall:>9.1f} {peak:>14.2f}" + ("" if code == 0 else f"   exit {code}: {out}"), flush=True)
        failed |= code != 0
    print("target for bforest info: <= 30 s and <= 2 GB on 2 cores")
    return int(failed)


if __name__ == "__main__":
    sys.exit(main())
