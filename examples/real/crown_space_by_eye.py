"""A fit's tree beside 4 of its clones, top and side view, with the crown envelope's outline at four
heights (cylinders red where the envelope gives them no light) and each one's crown offset and
share of wood outside the envelope.

    .venv/bin/python examples/real/crown_space_by_eye.py RUN OUT.png

RUN is the run folder of a fit whose recipe holds ``[ssm.crown_envelope]`` (``bforest init`` on a
one-sided broadleaved tree), with its clones grown.
"""

import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import bforest_core as bf  # noqa: E402
from bforest_core.envelope import CrownEnvelope  # noqa: E402
from bforest_core.metrics import crown_base_height, crown_offset  # noqa: E402


def ends(t):
    """Start and end of every cylinder, the stem base at the origin."""
    s = t.start - t.start[0]
    return s, s + t.length[:, None] * t.axis


def main(run: Path, out: Path) -> None:
    cfg = bf.load_config(run / "config.toml")
    env = CrownEnvelope.from_setting(cfg.ssm.crown_envelope)
    tree = bf.read_qsm(cfg.target.qsm)
    tree = tree[0] if isinstance(tree, list) else tree
    clones = [bf.read_qsm(p) for p in sorted((run / "clones").glob("clone_*.txt"))[:4]]
    fig, ax = plt.subplots(2, 5, figsize=(25, 10))
    for k, t in enumerate([tree, *clones]):
        s, e = ends(t)
        vol = np.pi * t.radius**2 * t.length
        lit = env.light(0.5 * (s + e)) > 0
        lw = np.clip(t.radius * 40, 0.2, 4)
        for a, (i, j) in ((ax[0, k], (0, 1)), (ax[1, k], (0, 2))):
            for n in np.argsort(-t.radius)[:4000]:
                a.plot([s[n, i], e[n, i]], [s[n, j], e[n, j]], color="k" if lit[n] else "r", lw=lw[n])
            a.set_aspect("equal")
        for z in np.linspace(env.base, env.top, 4):
            o = env.outline(z)
            ax[0, k].plot(o[:, 0], o[:, 1], lw=1, alpha=0.6, label=f"{z:.1f} m")
        off = crown_offset(t)
        ax[0, k].set_title(
            f"{'tree' if k == 0 else 'clone'}: offset {np.hypot(*off):.2f} at {np.degrees(np.arctan2(off[1], off[0])):.0f} deg\n"
            f"wood outside the envelope {vol[~lit].sum() / vol.sum():.1%}, crown base {crown_base_height(t):.1f} m"
        )
    ax[0, 0].legend()
    xlim, ylim = ax[0, 0].get_xlim(), ax[0, 0].get_ylim()
    for a in ax[0]:
        a.set_xlim(*xlim)
        a.set_ylim(*ylim)
    fig.savefig(out, dpi=60)


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]))
