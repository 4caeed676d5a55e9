"""Figure of a calibration study (``bforest calibrate``): SBC rank histograms and intervals."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .canvas import DATA_COLOR, MODEL_COLOR, new_figure, save_figure


def calibration_figure(res: dict, path, title: str | None = None, dpi: int = 120) -> Path:
    """One column per parameter. Top: the histogram of the truth's ranks among the posterior
    draws, with the 99 % band of a bin's count under uniform ranks (grey) and its expectation
    (dashed): a calibrated sampler stays inside the band; a U shape means intervals too narrow, a
    hump too wide, a slope a bias. Bottom: each run's central 90 % (thin) and 50 % (thick)
    interval against the truth, in the parameter's unit (blue: the 90 % interval holds the truth,
    red: it misses), with the diagonal.

    ``res`` is the result of :func:`bforest_core.pipeline.calibrate.calibrate` (or its
    ``calibration.json``)."""
    names, units = res["names"], res["units"]
    ok = [r for r in res["runs"] if r["status"] == "ok"]
    bins, draws = int(res["bins"]), int(res["rank_draws"])
    lo_band, hi_band = res["band"]
    p = len(names)
    fig = new_figure(3.6 * p + 0.4, 7.0)
    axes = fig.subplots(2, p, squeeze=False)
    table = {t["parameter"]: t for t in res["table"]}
    n = len(ok)
    for j, name in enumerate(names):
        unit = units[j] if j < len(units) else ""
        label = f"{name} ({unit})" if unit else name
        t = table[name]
        ax = axes[0, j]
        counts = np.asarray(t["rank_counts"], float)
        edges = np.arange(bins + 1) * (draws + 1) / bins
        ax.axhspan(lo_band, hi_band, color="#bbbbbb", alpha=0.5, lw=0, label="99 % band of uniform ranks")
        ax.axhline(n / bins, color="black", ls="--", lw=0.8, label="uniform expectation", zorder=3)
        ax.bar(
            edges[:-1],
            counts,
            width=np.diff(edges),
            align="edge",
            color="#e06666",
            edgecolor="white",
            label="runs",
            zorder=2,
        )
        ax.set_xlim(0, draws + 1)
        ax.set_xlabel(f"rank of the truth among {draws} posterior draws", fontsize="small")
        ax.set_ylabel("number of runs" if j == 0 else "", fontsize="small")
        cov = (
            f"50 %: {100 * t['coverage50']:.0f} %, 90 %: {100 * t['coverage90']:.0f} % covered"
            if t["runs"]
            else "no runs"
        )
        ax.set_title(f"{label}\n{cov}", fontsize="medium")
        if j == 0:
            ax.legend(fontsize="x-small", loc="upper right")
        ax = axes[1, j]
        truth = np.array([r["params"][name]["truth"] for r in ok], float)
        order = np.argsort(truth)
        for k in order:
            q = ok[k]["params"][name]
            inside = q["lo90"] <= q["truth"] <= q["hi90"]
            c = DATA_COLOR if inside else MODEL_COLOR
            ax.plot([q["truth"]] * 2, [q["lo90"], q["hi90"]], color=c, lw=0.8, alpha=0.7)
            ax.plot([q["truth"]] * 2, [q["lo50"], q["hi50"]], color=c, lw=2.4, alpha=0.9)
        lo, hi = res["lower"][j], res["upper"][j]
        ax.plot([lo, hi], [lo, hi], color="black", lw=0.8, ls="--")
        ax.set_xlim(lo, hi)
        ax.set_ylim(lo, hi)
        ax.set_xlabel(f"truth: {label}", fontsize="small")
        ax.set_ylabel(
            f"posterior 50 / 90 % interval ({unit})" if unit else "posterior 50 / 90 % interval", fontsize="small"
        )
        ax.grid(True, lw=0.3, alpha=0.5)
    fig.suptitle(title or f"simulation-based calibration of {res['optimizer']} ({n} runs)")
    return save_figure(fig, path, dpi)


def write_calibration_figure(res: dict) -> Path:
    """``calibration.png`` in the study folder."""
    return calibration_figure(res, Path(res["out_dir"]) / "calibration.png")
