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
    8 and 30.

    The diagonal panels are axes of their own; the pair panels below them are drawn together on
    one axes spanning the grid (:func:`_pair_panels`), whose data coordinates are the figure's
    fractions: with 19 parameters a grid of 361 axes placed by matplotlib's layout engine took
    7-12 s, more than the posterior it shows; drawn so, about 1.5 s."""
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
    rng = [_panel_range(S[:, j], None if bounds is None else bounds[j], true_values[j]) for j in range(p)]
    size = 2.3 if p > 2 else 3.0
    # room for the outer tick labels and the labels (slanted below many columns, level beside many rows)
    longest = 0.065 * max((len(t) for t in labels), default=1)  # inches at the labels' size
    left, bottom = 0.7 + (longest if p > 6 else 0.2), 0.6 + (0.71 * longest if p > 6 else 0.2)
    width, height = capped_size(size * p + left, size * p + bottom, dpi)
    fig = new_figure(width, height, layout=None)
    grid = fig.add_gridspec(
        p,
        p,
        left=left / width,
        bottom=bottom / height,
        right=1 - 0.1 / width,
        top=1 - (0.45 if title else 0.3) / height,
        wspace=0.1,
        hspace=0.35 if p > 2 else 0.25,
    )
    boxes = [[grid[i, j].get_position(fig) for j in range(p)] for i in range(p)]
    for j in range(p):
        ax = fig.add_subplot(grid[j, j])
        ax.hist(S[:, j], bins=bins, range=rng[j], weights=W, histtype="step", color="black", lw=1.2)
        if n:
            q = weighted_quantiles(S[:, j], W / W.sum(), [5, 50, 95])
            for v, ls in zip(q, (":", "-", ":")):
                ax.axvline(v, color="#1f77b4", ls=ls, lw=1.0)
            ax.set_title(f"{names[j]} = {q[1]:.3g}$^{{+{q[2] - q[1]:.2g}}}_{{-{q[1] - q[0]:.2g}}}$", fontsize="small")
        if truths is not None:
            ax.axvline(truths[j], color=MODEL_COLOR, lw=1.2)
        if true_values[j] is not None:
            ax.axvline(true_values[j], color=TRUE_COLOR, lw=1.6, ls="--")
        ax.set_xlim(*rng[j])
        ax.set_xticks([])  # the outer ticks and labels are drawn with the pairs
        ax.set_yticks([])
    _pair_panels(fig, boxes, S, W, rng, bins, smooth, labels, truths, true_values)
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
        key_ax = fig.add_subplot(grid[0, p - 1])
        key_ax.axis("off")
        key_ax.legend(handles=keys, loc="upper right", fontsize="small", frameon=False)
    else:
        fig.axes[0].legend(handles=keys, loc="upper right", fontsize="x-small")
    if title:
        fig.suptitle(title)
    return save_figure(fig, path, dpi)


def _panel_range(x: np.ndarray, bounds: tuple[float, float] | None, truth: float | None) -> tuple[float, float]:
    """A parameter's axis range: its samples' within the bounds, widened to show the true value."""
    lo, hi = (float(x.min()), float(x.max())) if x.size else (0.0, 1.0)
    if bounds is not None:
        lo, hi = (max(lo, bounds[0]), min(hi, bounds[1])) if x.size else bounds
    if truth is not None and not lo <= truth <= hi:  # the truth stays in view, also outside the posterior's range
        lo, hi = min(lo, truth), max(hi, truth)
        pad = 0.04 * (hi - lo)
        lo, hi = (lo - pad, hi) if truth == lo else (lo, hi + pad)
    if hi <= lo:
        lo, hi = lo - 0.5 * max(abs(lo), 1e-3), hi + 0.5 * max(abs(hi), 1e-3)
    return lo, hi


#: a tick's length as a fraction of the corner figure
TICK = 0.004


def _ticks(p: int):
    from matplotlib.ticker import MaxNLocator

    return MaxNLocator(3 if p > 6 else 5)


def _pair_panels(fig, boxes, S, W, rng, bins, smooth, labels, truths, true_values) -> None:
    """The pair panels (i > j) of a corner plot and the outer row's and column's ticks and labels,
    on one axes over the whole grid whose data coordinates are the figure's fractions,
    ``boxes[i][j]`` each panel's box (:func:`_pair_mesh`); the frames, the best evaluation's and
    the true values' lines and markers."""
    from matplotlib.collections import LineCollection

    p = len(rng)
    x0, y0, x1, y1 = boxes[p - 1][0].x0, boxes[p - 1][0].y0, boxes[0][p - 1].x1, boxes[0][p - 1].y1
    ax = fig.add_axes((x0, y0, x1 - x0, y1 - y0))
    ax.set_gid("pairs")
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.axis("off")
    if p > 1:
        _pair_mesh(ax, boxes, S, W, rng, bins, smooth)

    def fx(j, v):  # a value of parameter j at its place in column j (a figure fraction)
        b = boxes[p - 1][j]
        return b.x0 + (v - rng[j][0]) / (rng[j][1] - rng[j][0]) * b.width

    def fy(i, v):
        b = boxes[i][0]
        return b.y0 + (v - rng[i][0]) / (rng[i][1] - rng[i][0]) * b.height

    frames = []
    pairs = [(i, j) for i in range(1, p) for j in range(i)]
    for i, j in pairs:
        b = boxes[i][j]
        frames.append([(b.x0, b.y0), (b.x1, b.y0), (b.x1, b.y1), (b.x0, b.y1), (b.x0, b.y0)])
    ticks, locator = [], _ticks(p)
    tilt = 45 if p > 6 else 0  # many narrow columns: their labels slanted, the rows' level

    def inside(j):  # parameter j's tick values within its range
        return [v for v in locator.tick_values(*rng[j]) if rng[j][0] <= v <= rng[j][1]]

    def note(text, x, y, dx, dy, size="x-small", **kw):  # a text offset from (x, y) by (dx, dy) points
        ax.annotate(text, (x, y), xytext=(dx, dy), textcoords="offset points", fontsize=size, **kw)

    under = dict(ha="right" if tilt else "center", va="top", rotation=tilt, rotation_mode="anchor")
    for j in range(p):  # below the bottom row
        b = boxes[p - 1][j]
        for v in inside(j):
            ticks.append([(fx(j, v), b.y0), (fx(j, v), b.y0 - TICK)])
            note(f"{v:.3g}", fx(j, v), b.y0, 0, -4, **under)
        note(labels[j], (b.x0 + b.x1) / 2, b.y0, 0, -26, size="small", **under)
    for i in range(1, p):  # left of the first column
        b = boxes[i][0]
        for v in inside(i):
            ticks.append([(b.x0, fy(i, v)), (b.x0 - TICK, fy(i, v))])
            note(f"{v:.3g}", b.x0, fy(i, v), -4, 0, ha="right", va="center")
        note(
            labels[i],
            b.x0,
            (b.y0 + b.y1) / 2,
            -36,
            0,
            ha="right" if tilt else "center",
            va="center" if tilt else "bottom",
            rotation=0 if tilt else 90,
            rotation_mode="anchor",
            size="small",
        )
    ax.add_collection(LineCollection(frames + ticks, colors="black", linewidths=0.8))
    if truths is not None:  # a column's panels share their x, a row's their y
        lines = []
        for i, j in pairs:
            b = boxes[i][j]
            x, y = fx(j, truths[j]), fy(i, truths[i])
            lines += [[(x, b.y0), (x, b.y1)], [(b.x0, y), (b.x1, y)]]
        ax.add_collection(LineCollection(lines, colors=MODEL_COLOR, linewidths=1.0))
        ax.plot(
            [fx(j, truths[j]) for i, j in pairs], [fy(i, truths[i]) for i, j in pairs], "s", color=MODEL_COLOR, ms=4
        )
    known = [(i, j) for i, j in pairs if true_values[i] is not None and true_values[j] is not None]
    if known:
        xs, ys = [fx(j, true_values[j]) for i, j in known], [fy(i, true_values[i]) for i, j in known]
        ax.plot(xs, ys, "D", color=TRUE_COLOR, mec="black", mew=0.5, ms=5, ls="none")


def _pair_mesh(ax, boxes, S, W, rng, bins, smooth) -> None:
    """Every pair panel's 2-D histogram in one mesh (each scaled to its own maximum; the gaps
    between panels masked cells) and one contour of each cell's highest-density mass at 39/86 %."""
    from scipy.ndimage import gaussian_filter

    p = len(rng)
    nb = bins + 1  # a panel's bins and the masked gap after it
    X = np.empty((p - 1) * nb + 1)  # cell edges, shared by a column's panels
    Y = np.empty((p - 1) * nb + 1)
    for j in range(p - 1):  # columns 0 .. p-2 hold pairs; each panel's last edge is the gap's first
        X[j * nb : j * nb + nb] = np.linspace(boxes[p - 1][j].x0, boxes[p - 1][j].x1, nb)
    for k, i in enumerate(range(p - 1, 0, -1)):  # rows p-1 .. 1, from the figure's bottom
        Y[k * nb : k * nb + nb] = np.linspace(boxes[i][0].y0, boxes[i][0].y1, nb)
    X[-1], Y[-1] = X[-2], Y[-2]
    C = np.ma.masked_array(np.zeros(((p - 1) * nb, (p - 1) * nb)), mask=True)  # rows: y from the bottom
    M = C.copy()  # each cell's highest-density mass (the contoured field)
    for k, i in enumerate(range(p - 1, 0, -1)):
        for j in range(i):
            H, _, _ = np.histogram2d(S[:, j], S[:, i], bins=bins, range=[rng[j], rng[i]], weights=W)
            if smooth:
                H = gaussian_filter(H, smooth, mode="constant")
            top = H.max()
            cells = (slice(k * nb, k * nb + bins), slice(j * nb, j * nb + bins))
            C[cells] = H.T / top if top > 0 else H.T
            if top > 0 and S.shape[0] >= 50:
                order = np.argsort(H, axis=None)[::-1]
                mass = np.empty(H.size)
                mass[order] = np.cumsum(H.ravel()[order]) / H.sum()
                M[cells] = mass.reshape(H.shape).T
    ax.pcolormesh(X, Y, C, cmap="Greys", shading="flat", rasterized=True)
    if M.count():
        ax.contour(
            0.5 * (X[1:] + X[:-1]), 0.5 * (Y[1:] + Y[:-1]), M, levels=(0.393, 0.865), colors="#1f77b4", linewidths=0.9
        )


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
