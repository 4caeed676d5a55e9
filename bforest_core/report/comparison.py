"""Figures of studies built on fits: likelihood profiles and optimiser comparisons."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from .canvas import MODEL_COLOR, new_figure, save_figure


# ---------------------------------------------------------------------------------- profiles, comparison
def profile_figure(
    values: np.ndarray,
    distances: np.ndarray,
    path,
    param: str,
    failed: np.ndarray | None = None,
    best_value: float | None = None,
    best_distance: float | None = None,
    unit: str = "",
    title: str | None = None,
    dpi: int = 130,
) -> Path:
    """Distance profile along one parameter (GigaScience Fig. 4): one thin line per seed (a
    realisation of the distance surface), the median over seeds, the interquartile and
    min-max bands, and the best-fit value marked.

    ``distances`` is ``(len(values), seeds)``; ``failed`` (same shape) marks failed
    simulations (their penalty distance is included in the statistics).
    """
    v = np.asarray(values, float)
    D = np.asarray(distances, float).reshape(v.size, -1)
    k = D.shape[1]
    fig = new_figure(7.5, 4.6)
    ax = fig.subplots()
    for j in range(1, k):
        ax.plot(v, D[:, j], color="#888888", lw=0.7, alpha=0.6, label="other seeds" if j == 1 else None)
    ax.plot(v, D[:, 0], color="black", lw=0.9, ls="--", alpha=0.8, label="the fit's own seed")
    med = np.nanmedian(D, axis=1)
    if k > 1:
        ax.fill_between(v, np.nanmin(D, 1), np.nanmax(D, 1), color=MODEL_COLOR, alpha=0.08, lw=0, label="min–max")
        q1, q3 = np.nanquantile(D, [0.25, 0.75], axis=1)
        ax.fill_between(v, q1, q3, color=MODEL_COLOR, alpha=0.2, lw=0, label="interquartile range")
    ax.plot(v, med, color=MODEL_COLOR, lw=2.0, marker="o", ms=4, label=f"median of {k} seeds")
    if failed is not None and np.asarray(failed).any():
        f = np.asarray(failed, bool).reshape(D.shape)
        ii, jj = np.nonzero(f)
        ax.scatter(v[ii], D[ii, jj], marker="x", color="#e6550d", s=25, label="failed simulation", zorder=4)
    if best_value is not None:
        ax.axvline(best_value, color="black", lw=1.0, ls="--")
        ax.annotate(
            f"best fit {best_value:.4g}",
            (best_value, 1.0),
            xycoords=("data", "axes fraction"),
            xytext=(4, -12),
            textcoords="offset points",
            ha="left",
            fontsize="small",
        )
        if best_distance is not None:
            ax.plot(
                [best_value],
                [best_distance],
                marker="v",
                color="black",
                ms=9,
                ls="",
                label=f"best fit (D = {best_distance:.3f})",
            )
    ax.set_xlabel(f"{param} ({unit})" if unit else param)
    ax.set_ylabel("distance D")
    ax.grid(True, lw=0.3, alpha=0.5)
    ax.legend(fontsize="small")
    ax.set_title(title or f"distance profile along {param} (other parameters at the best fit)", fontsize="medium")
    return save_figure(fig, path, dpi)


def _pad_curves(curves: Sequence[np.ndarray]) -> np.ndarray:
    """Best-so-far curves of unequal length as one ``(repeats, n)`` array; a finished run keeps
    its last value (its best does not change after it stops)."""
    curves = [np.minimum.accumulate(np.asarray(c, float).ravel()) for c in curves if np.size(c)]
    if not curves:
        return np.empty((0, 0))
    n = max(c.size for c in curves)
    out = np.empty((len(curves), n))
    for r, c in enumerate(curves):
        out[r, : c.size] = c
        out[r, c.size :] = c[-1]
    return out


def compare_figure(
    curves: Mapping[str, Sequence[np.ndarray]],
    path,
    threshold: float | None = None,
    title: str | None = None,
    dpi: int = 130,
    heldout: Mapping[str, Sequence[tuple[int, float]]] | None = None,
    heldout_threshold: float | None = None,
) -> Path:
    """Optimiser comparison: best-so-far distance against evaluations, median over repeats
    (line) and the interquartile and min-max spread (bands), one colour per optimiser.

    Parameters
    ----------
    curves : dict
        Optimiser name -> list of best-so-far (or raw distance) arrays, one per repeat, indexed by
        evaluation; shorter runs keep their last value.
    threshold : float, optional
        A target distance drawn as a dashed line (for "evaluations to reach").
    heldout : dict, optional
        Optimiser name -> ``(evaluations, median held-out distance)`` points (``bforest compare
        --heldout``), drawn as open markers joined by a dotted line in the optimiser's colour;
        ``heldout_threshold`` as a dotted black line.
    """
    from matplotlib import colormaps

    pal = colormaps["tab10"].colors
    fig = new_figure(12.0, 4.8)
    ax, zoom = fig.subplots(1, 2, gridspec_kw={"width_ratios": [1.2, 1.0]})
    all_pos = True
    lo_all, hi_all, early = np.inf, -np.inf, -np.inf
    for c, (name, runs) in enumerate(curves.items()):
        M = _pad_curves(runs)
        if M.size == 0:
            continue
        col = pal[c % len(pal)]
        x = np.arange(1, M.shape[1] + 1)
        med = np.median(M, axis=0)
        with np.errstate(invalid="ignore"):  # inf (no grown tree yet) beside a distance: no band there
            bands = (
                [(M.min(0), M.max(0), 0.08), (*np.quantile(M, [0.25, 0.75], axis=0), 0.25)] if M.shape[0] > 1 else []
            )
        for a in (ax, zoom):
            for low, high, alpha in bands:
                a.fill_between(x, low, high, color=col, alpha=alpha, lw=0, step="post")
            a.step(x, med, where="post", color=col, lw=2.0, label=f"{name} (median of {M.shape[0]}: {med[-1]:.4g})")
        fin = M[np.isfinite(M)]
        all_pos &= bool(np.all(fin > 0))
        lo_all, hi_all = min(lo_all, fin.min(initial=np.inf)), max(hi_all, fin.max(initial=-np.inf))
        early = max(early, float(med[min(len(med) - 1, len(med) // 5)]))  # where each stands at a fifth
        pts = sorted((heldout or {}).get(name, []))
        if pts:
            hx, hy = np.array(pts, float).T
            ax.plot(
                hx,
                hy,
                color=col,
                ls=":",
                lw=1.2,
                marker="o",
                mfc="white",
                ms=6,
                label=f"{name}, best point held out ({hy[-1]:.4g})",
            )
            hi_all = max(hi_all, float(hy.max()))
    if heldout_threshold is not None:
        ax.axhline(
            heldout_threshold, color="black", ls=":", lw=1.0, label=f"held-out threshold {heldout_threshold:.4g}"
        )
    if threshold is not None:
        for a in (ax, zoom):
            a.axhline(threshold, color="black", ls="--", lw=1.0, label=f"threshold {threshold:.4g}")
        lo_all = min(lo_all, threshold)
    if all_pos and np.isfinite(lo_all) and lo_all > 0 and hi_all / lo_all > 20:
        ax.set_yscale("log")  # best distances spanning decades
    if np.isfinite(lo_all) and np.isfinite(early) and early > lo_all:
        pad = 0.05 * (early - lo_all)
        zoom.set_ylim(lo_all - pad, early + pad)
    for a in (ax, zoom):
        a.set_xlabel("evaluations")
        a.grid(True, which="both", lw=0.3, alpha=0.5)
    ax.set_ylabel("best distance so far")
    zoom.set_title("the end game: from the lowest distance to the medians at a fifth of the budget", fontsize="small")
    ax.legend(fontsize="small", title="optimizer (final median)", title_fontsize="small")
    ax.set_title(title or "optimiser comparison (bands: interquartile and min–max over repeats)", fontsize="medium")
    return save_figure(fig, path, dpi)


def write_profile_figure(res: dict) -> Path:
    """Draw ``figures/profile_<param>.png`` of a :func:`bforest_core.pipeline.profile.profile` result."""
    from ..pipeline.store import RunFiles, slug

    param = res["param"]
    return profile_figure(
        res["values"],
        res["distances"],
        RunFiles(res["run_dir"]).figures_dir / f"profile_{slug(param)}.png",
        param,
        failed=res["failed"],
        best_value=res["best_value"],
        best_distance=res["best_distance"],
        unit=res["unit"],
        title=f"Distance profile along {param} ({len(res['seeds'])} seeds; other parameters at the best fit)",
    )


def write_compare_figure(res: dict) -> Path:
    """Draw ``compare.png`` of a :func:`bforest_core.pipeline.compare.compare` result and link it
    from ``compare.md``."""
    out = Path(res["out_dir"])
    heldout = {}
    for t in res["table"] if res.get("heldout") else []:
        n_end = max(len(c) for c in res["curves"][t["optimizer"]])
        heldout[t["optimizer"]] = [
            (n_end if cp == "final" else min(int(cp), n_end), v) for cp, v in t["heldout"].items()
        ]
    fig = compare_figure(
        res["curves"],
        out / "compare.png",
        threshold=res["threshold"],
        heldout=heldout,
        heldout_threshold=(res.get("heldout") or {}).get("threshold"),
    )
    md = out / "compare.md"
    if md.exists() and "](compare.png)" not in md.read_text():
        md.write_text(md.read_text() + "\n![curves](compare.png)\n")
    return fig
