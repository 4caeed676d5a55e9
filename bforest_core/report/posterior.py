"""Figures of a posterior sample, for every sampler that gives one: the corner plot (marginals
and pairs, weighted for a population), the trace of a chain, and a population's tolerance,
acceptance rate and effective sample size per generation. The true parameters are drawn where
the target was grown by the fitted model.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..interfaces import Posterior
from ..pipeline.store import RunFiles
from .canvas import MODEL_COLOR, TRUE_COLOR, capped_size, new_figure, save_figure

if TYPE_CHECKING:  # annotations only: run_view imports this module's neighbours
    from .run_view import RunView


def chain_figure(
    chain: np.ndarray,
    names: Sequence[str],
    path,
    burn_in: int = 0,
    distances: np.ndarray | None = None,
    title: str | None = None,
    dpi: int = 120,
) -> Path:
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
        ax.plot(
            t, np.where(np.isfinite(dd), dd, np.nan), color="#1f77b4", alpha=max(0.05, min(0.5, 8.0 / walkers)), lw=0.6
        )
        ax.set_ylabel("distance D", fontsize="small")
    for ax in axes:
        if burn_in > 0:
            ax.axvspan(0, burn_in, color="#dddddd", alpha=0.6, lw=0)
        ax.grid(True, lw=0.3, alpha=0.4)
    axes[-1].set_xlabel(f"step ({walkers} walkers" + (f", burn-in {burn_in} shaded)" if burn_in else ")"))
    if title:
        fig.suptitle(title)
    return save_figure(fig, path, dpi)


def corner_figure(
    samples: np.ndarray,
    names: Sequence[str],
    path,
    truths: Sequence[float] | None = None,
    bins: int | None = None,
    bounds: Sequence[tuple[float, float]] | None = None,
    smooth: float = 1.0,
    title: str | None = None,
    dpi: int = 120,
    units: Sequence[str] | None = None,
    weights: np.ndarray | None = None,
    true_values: Sequence[float | None] | None = None,
) -> Path:
    """Corner plot of posterior samples ``(n, p)`` (with ``weights``, a weighted population):
    marginal histograms with the 5/50/95 % quantiles on the diagonal (those of ``best.json``),
    2-D histograms (Gaussian-smoothed by ``smooth`` bins) with 39/86 % (1σ/2σ) contours below;
    ``truths`` (the best evaluation) in red, ``true_values`` (the parameters a generated target
    was grown with; None where unknown) in green. ``bins`` defaults to about sqrt(n)/2, between
    8 and 30."""
    from scipy.ndimage import gaussian_filter

    from ..metrics import weighted_quantiles

    S = np.asarray(samples, float)
    W = np.ones(S.shape[0]) if weights is None else np.asarray(weights, float)
    keep = np.isfinite(S).all(1) & np.isfinite(W)
    S, W = S[keep], W[keep]
    n, p = S.shape
    true_values = list(true_values) if true_values is not None else [None] * p
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
        t = true_values[j]
        if t is not None and not lo <= t <= hi:  # the truth stays in view, also outside the posterior's range
            lo, hi = min(lo, t), max(hi, t)
            pad = 0.04 * (hi - lo)
            lo, hi = (lo - pad, hi) if t == lo else (lo, hi + pad)
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
                ax.hist(S[:, j], bins=bins, range=rng[j], weights=W, histtype="step", color="black", lw=1.2)
                if n:
                    q = weighted_quantiles(S[:, j], W / W.sum(), [5, 50, 95])
                    for v, ls in zip(q, (":", "-", ":")):
                        ax.axvline(v, color="#1f77b4", ls=ls, lw=1.0)
                    ax.set_title(
                        f"{names[j]} = {q[1]:.3g}$^{{+{q[2] - q[1]:.2g}}}_{{-{q[1] - q[0]:.2g}}}$", fontsize="small"
                    )
                ax.set_yticks([])
                if truths is not None:
                    ax.axvline(truths[j], color=MODEL_COLOR, lw=1.2)
                if true_values[j] is not None:
                    ax.axvline(true_values[j], color=TRUE_COLOR, lw=1.6, ls="--")
            else:
                H, xe, ye = np.histogram2d(S[:, j], S[:, i], bins=bins, range=[rng[j], rng[i]], weights=W)
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
                if true_values[j] is not None and true_values[i] is not None:
                    ax.plot(true_values[j], true_values[i], "D", color=TRUE_COLOR, mec="black", mew=0.5, ms=5)
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
    from matplotlib.lines import Line2D

    keys = [Line2D([], [], color="#1f77b4", lw=1.0, label="5/50/95 % quantiles")]
    if truths is not None:
        keys.append(Line2D([], [], color=MODEL_COLOR, lw=1.2, label="best evaluation"))
    if any(t is not None for t in true_values):
        keys.append(
            Line2D(
                [],
                [],
                color=TRUE_COLOR,
                lw=1.6,
                ls="--",
                marker="D",
                mec="black",
                mew=0.5,
                label="true value (generated target)",
            )
        )
    if p >= 2:  # in the empty upper-right corner
        key_ax = axes[0, p - 1]
        key_ax.set_visible(True)
        key_ax.axis("off")
        key_ax.legend(handles=keys, loc="upper right", fontsize="small", frameon=False)
    else:
        axes[0, 0].legend(handles=keys, loc="upper right", fontsize="x-small")
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


def generations_figure(
    epsilon: Sequence,
    acceptance: Sequence,
    ess: Sequence,
    path,
    epsilon_target: Sequence | float | None = None,
    particles: int | None = None,
    title: str | None = None,
    dpi: int = 130,
) -> Path:
    """A population sampler's progress per generation: the tolerance ε (log scale, with its
    target where there is one), the acceptance rate and the effective sample size of the
    weights (with the population size). Generation 0 (the prior draws) has no ε."""
    eps = np.array([np.nan if e is None else float(e) for e in epsilon], float)
    eps[~np.isfinite(eps)] = np.nan
    g = np.arange(eps.size)
    fig = new_figure(7.5, 6.4)
    axes = fig.subplots(3, 1, sharex=True)
    ax = axes[0]
    ax.plot(g, eps, "o-", color=MODEL_COLOR, ms=4, label="ε")
    if epsilon_target is not None:
        if np.ndim(epsilon_target) == 0:
            if float(epsilon_target) > 0:
                ax.axhline(float(epsilon_target), color="black", ls="--", lw=1.0, label="ε target")
        else:
            tgt = np.array([np.nan if t is None else float(t) for t in epsilon_target], float)
            # the target measured before generation t (t = 1, 2, ...)
            ax.plot(
                np.arange(1, tgt.size + 1),
                np.where(tgt > 0, tgt, np.nan),
                "s--",
                color="black",
                ms=3,
                lw=1.0,
                label="ε target (noise floor)",
            )
    if np.isfinite(eps).any() and np.nanmin(eps) > 0:
        ax.set_yscale("log")
    ax.set_ylabel("tolerance ε")
    ax.legend(fontsize="small")
    ax = axes[1]
    acc = np.array([np.nan if a is None else float(a) for a in acceptance], float)
    ax.plot(np.arange(acc.size), acc, "o-", color="#1f77b4", ms=4)
    ax.set_ylim(0, 1.05)
    ax.set_ylabel("acceptance rate")
    ax = axes[2]
    es = np.array([np.nan if e is None else float(e) for e in ess], float)
    ax.plot(np.arange(es.size), es, "o-", color="#2ca02c", ms=4, label="ESS")
    if particles:
        ax.axhline(particles, color="grey", ls=":", lw=1.0, label=f"population ({particles})")
        ax.legend(fontsize="small")
    top = np.nanmax(np.r_[es, particles or 0, 1.0])
    ax.set_ylim(0, 1.1 * top)
    ax.set_ylabel("effective sample size")
    ax.set_xlabel("generation")
    ax.xaxis.get_major_locator().set_params(integer=True)
    for ax in axes:
        ax.grid(True, lw=0.3, alpha=0.5)
    if title:
        fig.suptitle(title)
    return save_figure(fig, path, dpi)


# ---------------------------------------------------------------------------------- run report
def _per_generation(diag: dict, key: str):
    """A per-generation list of the diagnostics (``epsilon``, ``acceptance``, ``ess``), or None."""
    val = diag.get(key)
    if isinstance(val, (list, tuple, np.ndarray)) and np.ndim(val) == 1 and len(val) >= 1:
        return list(val)
    return None


def fig_posterior(v: RunView):
    """The posterior figures of a sampler's run: the corner plot for every posterior, the chain's
    trace for a chain, and tolerance, acceptance and ESS per generation for a population."""
    diag = v.store.read_diagnostics()
    post = Posterior.from_diagnostics(diag, v.free_names, (v.best or {}).get("posterior_kind"))
    if post is None:
        return []
    X, w, names, kind = post.samples, post.weights, list(post.names), post.kind
    true = [v.true_params.get(n) for n in names]
    out = []
    if kind == "chain":
        chain, burn = post.chain, post.burn_in
        out.append(
            (
                chain_figure(
                    chain,
                    names,
                    v.store.figures_dir / "chain.png",
                    burn_in=burn,
                    distances=post.distances,
                    title="MCMC chain",
                ),
                f"Trace of every walker per parameter ({chain.shape[1]} walkers, {chain.shape[0]} steps; "
                f"burn-in of {burn} steps shaded)",
            )
        )
        what = f"{X.shape[0]} draws of {int(diag.get('walkers') or 0) or '?'} walkers after burn-in"
    else:
        ess = 1.0 / float(np.sum(w**2))
        what = f"a population of {X.shape[0]} weighted particles, effective sample size {ess:.0f}"
    best = [v.best_params.get(n) for n in names] if v.best_params else None
    best = best if best and all(t is not None for t in best) else None
    bounds = None
    if v.cfg is not None and all(n in v.cfg.ssm.free for n in names):
        bounds = [(v.cfg.ssm.free[n].lower, v.cfg.ssm.free[n].upper) for n in names]
    specs = v.param_specs
    units = [specs[n].unit if n in specs else "" for n in names]
    out.append(
        (
            corner_figure(
                X,
                names,
                v.store.figures_dir / "corner.png",
                truths=best,
                bounds=bounds,
                units=units,
                weights=None if kind == "chain" else w,
                true_values=true if any(t is not None for t in true) else None,
                title=f"Posterior: {what}",
            ),
            f"Posterior marginals (5/50/95 % quantiles, as in {RunFiles.BEST}) and pairwise densities (39 %/86 % "
            "contours)"
            + (", weighted by the particles' weights" if kind != "chain" else "")
            + "; red: the best evaluation"
            + ("; green: the true values the target was grown with" if any(t is not None for t in true) else ""),
        )
    )
    if kind == "population":
        eps, acc, ess = (_per_generation(diag, k) for k in ("epsilon", "acceptance", "ess"))
        if eps is not None and acc is not None and ess is not None and len(eps) == len(acc) == len(ess):
            target = diag.get("epsilon_target")
            if target is None:
                opt = (v.raw_config.get("optimizer") or {}).get("epsilon_target")
                target = opt if isinstance(opt, (int, float)) and not isinstance(opt, bool) else None
            n_pop = (
                len(diag["population"]["particles"])
                if isinstance(diag.get("population"), dict) and diag["population"].get("particles") is not None
                else X.shape[0]
            )
            out.append(
                (
                    generations_figure(
                        eps,
                        acc,
                        ess,
                        v.store.figures_dir / "generations.png",
                        epsilon_target=target,
                        particles=n_pop,
                        title="Population per generation",
                    ),
                    "Tolerance ε (log scale; dashed: its target), acceptance rate and effective sample size "
                    "of the weights per complete generation (generation 0: the prior draws)",
                )
            )
    return out
