"""Figures of a posterior sample: MCMC traces and the corner plot.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

from pathlib import Path
from typing import Sequence

import numpy as np

from .canvas import MODEL_COLOR, capped_size, new_figure, save_figure

if TYPE_CHECKING:  # annotations only: run_view imports this module's neighbours
    from .run_view import RunView


def chain_figure(chain: np.ndarray, names: Sequence[str], path, burn_in: int = 0,
                 distances: np.ndarray | None = None, title: str | None = None, dpi: int = 120) -> Path:
    """Trace of every walker of an MCMC chain ``(steps, walkers, parameters)`` per parameter
    (and of each walker's distance, ``(steps, walkers)``), the burn-in shaded."""
    chain = np.asarray(chain, float)
    steps, walkers, p = chain.shape
    rows = p + (1 if distances is not None else 0)
    fig = new_figure(9.0, 1.7 * rows + 0.6)
    axes = fig.subplots(rows, 1, squeeze=False, sharex=True)[:, 0]
    t = np.arange(steps)
    for j in range(p):
        ax = axes[j]
        ax.plot(t, chain[:, :, j], color="black", alpha=max(0.05, min(0.5, 8.0 / walkers)), lw=0.6)
        ax.set_ylabel(names[j] if j < len(names) else f"p{j}", fontsize="small")
    if distances is not None:
        dd = np.asarray(distances, float)
        ax = axes[p]
        ax.plot(t, np.where(np.isfinite(dd), dd, np.nan), color="#1f77b4",
                alpha=max(0.05, min(0.5, 8.0 / walkers)), lw=0.6)
        ax.set_ylabel("distance D", fontsize="small")
    for ax in axes:
        if burn_in > 0:
            ax.axvspan(0, burn_in, color="#dddddd", alpha=0.6, lw=0)
        ax.grid(True, lw=0.3, alpha=0.4)
    axes[-1].set_xlabel(f"step ({walkers} walkers" + (f", burn-in {burn_in} shaded)" if burn_in else ")"))
    if title:
        fig.suptitle(title)
    return save_figure(fig, path, dpi)


def corner_figure(samples: np.ndarray, names: Sequence[str], path, truths: Sequence[float] | None = None,
                  bins: int | None = None, bounds: Sequence[tuple[float, float]] | None = None,
                  smooth: float = 1.0, title: str | None = None, dpi: int = 120,
                  units: Sequence[str] | None = None) -> Path:
    """Corner plot of posterior samples ``(n, p)``: marginal histograms with the 16/50/84 %
    quantiles on the diagonal, 2-D histograms (Gaussian-smoothed by ``smooth`` bins) with
    39/86 % (1σ/2σ) contours below; ``truths`` (e.g. the best fit) in red. ``bins`` defaults
    to about sqrt(n)/2, between 8 and 30."""
    from scipy.ndimage import gaussian_filter
    S = np.asarray(samples, float)
    S = S[np.isfinite(S).all(1)]
    n, p = S.shape
    labels = [f"{nm} ({u})" if u else nm for nm, u in zip(names, list(units or []) + [""] * p)]
    if bins is None:
        bins = int(np.clip(np.sqrt(max(n, 1)) / 2, 8, 30))
    size = 2.3 if p > 2 else 3.0
    fig = new_figure(*capped_size(size * p + 0.5, size * p + 0.5, dpi))
    axes = fig.subplots(p, p, squeeze=False)
    rng = []
    for j in range(p):
        lo, hi = (float(S[:, j].min()), float(S[:, j].max())) if n else (0.0, 1.0)
        if bounds is not None:
            lo, hi = max(lo, bounds[j][0]) if n else bounds[j][0], min(hi, bounds[j][1]) if n else bounds[j][1]
        if hi <= lo:
            lo, hi = lo - 0.5 * max(abs(lo), 1e-3), hi + 0.5 * max(abs(hi), 1e-3)
        rng.append((lo, hi))
    for i in range(p):
        for j in range(p):
            ax = axes[i, j]
            if j > i:
                ax.set_visible(False)
                continue
            if i == j:
                ax.hist(S[:, j], bins=bins, range=rng[j], histtype="step", color="black", lw=1.2)
                if n:
                    q = np.quantile(S[:, j], [0.16, 0.5, 0.84])
                    for v, ls in zip(q, (":", "-", ":")):
                        ax.axvline(v, color="#1f77b4", ls=ls, lw=1.0)
                    ax.set_title(f"{names[j]} = {q[1]:.3g}$^{{+{q[2] - q[1]:.2g}}}_{{-{q[1] - q[0]:.2g}}}$",
                                 fontsize="small")
                ax.set_yticks([])
                if truths is not None:
                    ax.axvline(truths[j], color=MODEL_COLOR, lw=1.2)
            else:
                H, xe, ye = np.histogram2d(S[:, j], S[:, i], bins=bins, range=[rng[j], rng[i]])
                if smooth:
                    H = gaussian_filter(H, smooth, mode="constant")
                ax.pcolormesh(xe, ye, H.T, cmap="Greys", shading="flat", rasterized=True)
                levels = _hpd_levels(H, (0.393, 0.865)) if n >= 50 else None
                if levels is not None:
                    xc, yc = 0.5 * (xe[1:] + xe[:-1]), 0.5 * (ye[1:] + ye[:-1])
                    ax.contour(xc, yc, H.T, levels=levels, colors="#1f77b4", linewidths=0.9)
                if truths is not None:
                    ax.axvline(truths[j], color=MODEL_COLOR, lw=1.0)
                    ax.axhline(truths[i], color=MODEL_COLOR, lw=1.0)
                    ax.plot(truths[j], truths[i], "s", color=MODEL_COLOR, ms=4)
                ax.set_ylim(*rng[i])
            ax.set_xlim(*rng[j])
            ax.tick_params(labelsize="x-small")
            if i == p - 1:
                ax.set_xlabel(labels[j], fontsize="small")
            else:
                ax.set_xticklabels([])
            if j == 0 and i > 0:
                ax.set_ylabel(labels[i], fontsize="small")
            elif i != j:
                ax.set_yticklabels([])
    if title:
        fig.suptitle(title)
    return save_figure(fig, path, dpi)


def _hpd_levels(H: np.ndarray, masses=(0.393, 0.865)):
    """Density thresholds enclosing the given probability masses of a 2-D histogram."""
    flat = np.sort(H.ravel())[::-1]
    total = flat.sum()
    if total <= 0:
        return None
    cum = np.cumsum(flat) / total
    levels = []
    for m in masses:
        k = min(int(np.searchsorted(cum, m)), flat.size - 1)
        levels.append(flat[k])
    levels = np.unique(levels)
    levels = levels[levels > 0]
    return levels if levels.size else None


# ---------------------------------------------------------------------------------- run report
def mcmc_chain(diag: dict, names: list[str]):
    """``(chain (steps, walkers, p), distances (steps, walkers) or None, burn_in, names)`` from an
    MCMC optimiser's diagnostics (the ``emcee`` optimiser stores ``chain``, ``distances``,
    ``burn_in`` and ``names``), or None when they hold no chain."""
    if not isinstance(diag, dict) or diag.get("chain") is None:
        return None
    try:
        chain = np.asarray(diag["chain"], float)
    except (TypeError, ValueError):
        return None
    names = list(diag.get("names") or names)
    if chain.ndim == 2 and chain.shape[1] == len(names):
        chain = chain[:, None, :]
    if chain.ndim != 3 or chain.shape[0] == 0 or chain.shape[1] == 0:
        return None
    if chain.shape[2] != len(names):
        names = [f"p{i}" for i in range(chain.shape[2])]
    dist = diag.get("distances")
    if dist is not None:
        try:
            dist = np.asarray(dist, float)
        except (TypeError, ValueError):
            dist = None
        if dist is not None and dist.shape != chain.shape[:2]:
            dist = None
    burn = diag.get("burn_in")
    burn = int(burn) if burn is not None else chain.shape[0] // 2
    burn = min(max(burn, 0), chain.shape[0] - 1)
    return chain, dist, burn, names


def fig_mcmc(v: "RunView"):
    diag = v.store.read_diagnostics()
    names = v.free_names
    got = mcmc_chain(diag, names)
    if got is None:
        return []
    chain, dist, burn, names = got
    out = [(chain_figure(chain, names, v.path / "figures" / "chain.png", burn_in=burn, distances=dist,
                         title="MCMC chain"),
            f"Trace of every walker per parameter ({chain.shape[1]} walkers, {chain.shape[0]} steps; "
            f"burn-in of {burn} steps shaded)")]
    samples = chain[burn:].reshape(-1, chain.shape[2])
    truths = [v.best_params.get(n) for n in names] if v.best_params else None
    truths = truths if truths and all(t is not None for t in truths) else None
    bounds = None
    if v.cfg is not None and all(n in v.cfg.ssm.free for n in names):
        bounds = [(v.cfg.ssm.free[n].lower, v.cfg.ssm.free[n].upper) for n in names]
    units = None
    if v.cfg is not None:
        try:
            from ..registry import component
            from ..config import ssm_settings
            ssm = component("ssm", v.cfg.ssm.kind, **ssm_settings(v.cfg))
            units = [ssm.parameter_spec(n).unit for n in names]
        except Exception:  # a report of a run whose model is gone still draws, without units
            units = None
    out.append((corner_figure(samples, names, v.path / "figures" / "corner.png", truths=truths, bounds=bounds,
                              units=units,
                              title=f"Posterior ({samples.shape[0]} samples after burn-in)"),
                "Posterior marginals (16/50/84 % quantiles) and pairwise densities (39 %/86 % contours); "
                "red: the best evaluation"))
    return out
