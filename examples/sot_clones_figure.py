"""Six SOT clones (same parameters, six seeds) in side and top views -> docs/img/sot-clones.png.

Usage::

    python examples/sot_clones_figure.py [--cycles 18] [--out docs/img/sot-clones.png]

Cylinders are drawn as line segments whose width is proportional to their radius (drawn at
true scale where that is visible, with a floor for the finest twigs).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.collections import LineCollection  # noqa: E402

import bforest_core as bf  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def draw(ax, tree, dims, lw_per_m, color_by_radius=True):
    """Draw a tree's cylinders projected on ``dims`` (e.g. (0, 2) for a side view x-z)."""
    a = tree.start[:, dims]
    b = tree.end[:, dims]
    # thick first so twigs stay visible on top
    order = np.argsort(-tree.radius)
    seg = np.stack([a[order], b[order]], axis=1)
    r = tree.radius[order]
    lw = np.maximum(2.0 * r * lw_per_m, 0.25)
    t = np.clip(np.log(r / r.min()) / max(np.log(r.max() / r.min()), 1e-9), 0, 1)
    twig = np.array([0.42, 0.55, 0.22])  # olive green twigs
    wood = np.array([0.36, 0.22, 0.12])  # bark brown
    col = twig[None, :] * (1 - t[:, None]) + wood[None, :] * t[:, None]
    ax.add_collection(LineCollection(seg, linewidths=lw, colors=col, capstyle="round"))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cycles", type=int, default=18)
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4, 5, 6])
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "img" / "sot-clones.png")
    args = ap.parse_args(argv)

    ssm = bf.component("ssm", "sot")
    trees = [ssm.simulate({"max_iter": args.cycles}, seed) for seed in args.seeds]
    n = len(trees)
    ext = max(float(np.abs(t.end[:, :2]).max()) for t in trees) + 0.3
    top = max(float(t.end[:, 2].max()) for t in trees) + 0.3

    fig, axes = plt.subplots(
        2,
        n,
        figsize=(2.6 * n, 2.6 * top / (2 * ext) + 3.4),
        gridspec_kw={"height_ratios": [top / (2 * ext), 1.0]},
        squeeze=False,
    )
    for c, (tree, seed) in enumerate(zip(trees, args.seeds)):
        e = tree.end
        h = e[:, 2].max()
        cr = np.hypot(e[:, 0], e[:, 1]).max()
        side, plan = axes[0, c], axes[1, c]
        side.set_xlim(-ext, ext)
        side.set_ylim(0, top)
        side.set_title(
            f"seed {seed}: {tree.n} cyl., H {h:.1f} m\ncrown r {cr:.1f} m, base d {200 * tree.radius[0]:.0f} cm",
            fontsize=8,
        )
        side.set_xlabel("x (m)", fontsize=8)
        plan.set_xlim(-ext, ext)
        plan.set_ylim(-ext, ext)
        plan.set_xlabel("x (m)", fontsize=8)
        for axx in (side, plan):
            axx.set_aspect("equal")
            axx.tick_params(labelsize=7)
            axx.set_facecolor("#f4f7fb")
        if c == 0:
            side.set_ylabel("z (m)", fontsize=8)
            plan.set_ylabel("y (m)", fontsize=8)
    p = trees[0].metadata["params"]
    fig.suptitle(
        f"SOT clones: calibrated defaults, {args.cycles} cycles, six seeds "
        f"(clone noise: branch angle sd {p['branch_angle_sd']:g}\u00b0, phyllotaxis sd "
        f"{p['phyllotaxis_sd']:g}\u00b0, ran {p['ran']:g}); side views (top) and top views (bottom)",
        fontsize=10,
    )
    fig.tight_layout(rect=(0, 0, 1, 0.96))
    fig.canvas.draw()
    for c, tree in enumerate(trees):
        for axx, dims in ((axes[0, c], (0, 2)), (axes[1, c], (0, 1))):
            px = axx.transData.transform([[0.0, 0.0], [1.0, 0.0]])
            pt_per_m = (px[1, 0] - px[0, 0]) * 72.0 / fig.dpi
            draw(axx, tree, dims, pt_per_m)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=130)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
