"""The stand report (``bforest stand``): a table per tree, the fitted parameters across trees, the
plot map, and the real plot beside a synthetic stand.

It reads the stand folder (``stand.csv``, ``stand.toml`` and each tree's run folder through
:mod:`bforest_core.pipeline.store`) and writes ``STAND/report.md``, ``STAND/report.html`` and
``STAND/figures/``.
"""

from __future__ import annotations

import datetime as _dt
import math
from pathlib import Path

import numpy as np

from ..pipeline.store import RunFiles, StandFiles, clock_warning
from .canvas import DATA_COLOR, MODEL_COLOR, new_figure, save_figure
from .document import Document, fmt, seconds_text
from .trees import plot_tree


def _num(v):
    try:
        x = float(v)
    except (TypeError, ValueError):
        return None
    return x if math.isfinite(x) else None


def _runs(stand_dir, rows):
    """Each tree's best.json and run config (None for a tree without a finished fit)."""
    from ..config import read_toml

    files = StandFiles(stand_dir)
    out = {}
    for r in rows:
        run = RunFiles(files.run_dir(r["tree"]))
        if r.get("status") == "ok" and run.best_path.exists():
            out[r["tree"]] = (run.read_best(), read_toml(run.config_path))
        else:
            out[r["tree"]] = (None, None)
    return out


def parameters_figure(rows, runs, path) -> Path | None:
    """Every fitted parameter of every tree, as its place in the tree's search box (0 = lower
    bound, 1 = upper), one panel per growth model: where the trees agree and where they part."""
    by_model: dict[str, list] = {}
    for r in rows:
        best, cfg = runs[r["tree"]]
        if best is None:
            continue
        free = cfg.get("ssm", {}).get("free", {})
        pos = {}
        for k, b in free.items():
            lo, hi, v = b.get("lower"), b.get("upper"), best["params"].get(k)
            if v is not None and hi is not None and lo is not None and hi > lo:
                pos[k] = (float(v) - lo) / (hi - lo)
        by_model.setdefault(cfg["ssm"]["kind"], []).append((r["tree"], pos))
    if not by_model:
        return None
    heights = [max(len({k for _, p in trees for k in p}), 1) for trees in by_model.values()]
    fig = new_figure(7.5, 0.28 * sum(heights) + 1.2 * len(heights))
    axes = fig.subplots(len(heights), 1, squeeze=False, gridspec_kw={"height_ratios": heights})[:, 0]
    colors = ["#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22"]
    for ax, (model, trees) in zip(axes, by_model.items()):
        names = sorted({k for _, p in trees for k in p})
        for i, (tree, pos) in enumerate(trees):
            ys = [names.index(k) for k in pos]
            jitter = 0.3 * (i / max(len(trees) - 1, 1) - 0.5)
            ax.scatter(
                list(pos.values()),
                np.array(ys) + jitter,
                s=18,
                color=colors[i % len(colors)],
                label=tree,
                zorder=3,
            )
        ax.set_yticks(range(len(names)), names, fontsize=8)
        ax.set_ylim(len(names) - 0.5, -0.5)
        ax.set_xlim(-0.03, 1.03)
        ax.axvspan(-0.03, 0.05, color="0.9", zorder=0)
        ax.axvspan(0.95, 1.03, color="0.9", zorder=0)
        ax.grid(axis="x", color="0.85", lw=0.5)
        ax.set_title(f"{model}: fitted value within its search box (grey: within 5 % of a bound)", fontsize=9)
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False)
    axes[-1].set_xlabel("place in the search box (0 = lower bound, 1 = upper bound)")
    return save_figure(fig, path)


def _draw_plot(ax, trees, view, r_max, color_by="order"):
    for _, t in trees:
        plot_tree(
            ax, t, view, color_by, origin="data", r_max=r_max, lw_max=2.5, lw_min=0.2, label_axes=False, autoscale=False
        )


def _extent(trees, view):
    from .canvas import VIEWS

    h, v = VIEWS[view][:2]
    pts = np.concatenate([np.vstack([t.start, t.end]) for _, t in trees])
    return pts[:, h].min(), pts[:, h].max(), pts[:, v].min(), pts[:, v].max()


def plot_map_figure(real, path, label: bool = True) -> Path:
    """The plot from above: every tree at its place, its name at its stem base (m)."""
    fig = new_figure(6.5, 6.0)
    ax = fig.subplots()
    r_max = max(float(t.radius.max()) for _, t in real)
    _draw_plot(ax, real, "xy", r_max)
    for name, t in real:
        x, y = t.start[0, :2]
        ax.plot([x], [y], "o", ms=4, color="black", zorder=5)
        if label:
            ax.annotate(name, (x, y), xytext=(4, 4), textcoords="offset points", fontsize=7, zorder=6)
    x0, x1, y0, y1 = _extent(real, "xy")
    pad = 0.05 * max(x1 - x0, y1 - y0, 1.0)
    ax.set_xlim(x0 - pad, x1 + pad)
    ax.set_ylim(y0 - pad, y1 + pad)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(f"plot map: {len(real)} trees from above (line width ∝ radius, colour = branch order)", fontsize=9)
    return save_figure(fig, path)


def real_vs_synthetic_figure(real, synthetic, path, title: str = "synthetic stand") -> Path:
    """The real plot (its QSMs) beside one synthetic stand (a clone of each tree at its place), from
    above and from the side (XZ), all four panels at one scale (m)."""
    fig = new_figure(11.0, 9.5)
    axes = fig.subplots(2, 2, gridspec_kw={"height_ratios": [1.0, 0.8]})
    r_max = max(float(t.radius.max()) for _, t in real + synthetic)
    for view, row in (("xy", 0), ("xz", 1)):
        e = np.array([_extent(real, view), _extent(synthetic, view)])
        x0, x1, y0, y1 = e[:, 0].min(), e[:, 1].max(), e[:, 2].min(), e[:, 3].max()
        pad = 0.04 * max(x1 - x0, y1 - y0, 1.0)
        for col, (trees, name, edge) in enumerate(
            ((real, "real plot (QSMs)", DATA_COLOR), (synthetic, title, MODEL_COLOR))
        ):
            ax = axes[row, col]
            _draw_plot(ax, trees, view, r_max)
            ax.set_xlim(x0 - pad, x1 + pad)
            ax.set_ylim(y0 - pad, y1 + pad)
            ax.set_aspect("equal")
            for s in ax.spines.values():
                s.set_color(edge)
            ax.set_xlabel("x (m)")
            ax.set_ylabel("y (m)" if view == "xy" else "z (m)")
            ax.set_title(f"{name}, {'top view' if view == 'xy' else 'side view (XZ)'}", fontsize=9)
    return save_figure(fig, path)


def _tree_rows(rows, runs):
    out = []
    for r in rows:
        best, _ = runs[r["tree"]]
        if r.get("status") != "ok":
            out.append([r["tree"], "failed", "", "", "", "", "", "", "", "", r.get("reason", "")])
            continue
        h, hc = _num(r.get("height")), _num(r.get("height_clones"))
        d, dc = _num(r.get("dbh")), _num(r.get("dbh_clones"))
        c, cc = _num(r.get("crown_spread")), _num(r.get("crown_spread_clones"))
        out.append(
            [
                r["tree"],
                r.get("model", ""),
                f"{fmt(h, 3)} / {fmt(hc, 3)}",
                f"{fmt(None if d is None else 100 * d, 3)} / {fmt(None if dc is None else 100 * dc, 3)}",
                f"{fmt(c, 3)} / {fmt(cc, 3)}",
                r.get("verdict", "") + (f" ({r['warnings']})" if r.get("warnings") else ""),
                f"{fmt(_num(r.get('distance')))} / {fmt(_num(r.get('heldout_distance')))}",
                r.get("evaluations", ""),
                r.get("stop_kind", ""),
                seconds_text(best.get("seconds") if best else None),
                "",
            ]
        )
    return out


def _parameter_tables(rows, runs):
    """Per growth model: a table of the trees' fitted parameters (rows: trees)."""
    by_model: dict[str, list] = {}
    for r in rows:
        best, cfg = runs[r["tree"]]
        if best is not None:
            free = list(cfg.get("ssm", {}).get("free", {}))
            by_model.setdefault(cfg["ssm"]["kind"], []).append((r["tree"], {k: best["params"].get(k) for k in free}))
    for model, trees in by_model.items():
        names = sorted({k for _, p in trees for k in p})
        yield model, ["tree", *names], [[t, *(fmt(p.get(k), 3) for k in names)] for t, p in trees]


def write_stand_report(stand_dir, figures: bool = True) -> Path:
    """Write ``report.md``, ``report.html`` and the figures of a stand folder; returns report.md."""
    from ..pipeline.stand import read_settings, read_table
    from ..pipeline.synthetic import real_plot, realisation_trees

    stand_dir = Path(stand_dir)
    files = StandFiles(stand_dir)
    settings = read_settings(stand_dir)
    rows = read_table(files.table_path)
    runs = _runs(stand_dir, rows)
    ok = [r for r in rows if r.get("status") == "ok"]
    doc = Document()
    title = f"Bayes Forest stand report: {stand_dir.name}"
    doc.h(1, title)
    passed = sum(r.get("verdict") == "pass" for r in ok)
    doc.p(
        f"**{len(ok)} of {len(rows)}** trees fitted; the clones of **{passed}** meet every fidelity limit "
        f"(height, DBH and crown spread within 20 %, crown base, stem length and branch counts within 30 %). "
        f"{settings.clones} clones per tree; {settings.realisations} synthetic stand(s)."
    )
    problems = [f"{r['tree']}: failed: {r.get('reason', '')}" for r in rows if r.get("status") != "ok"]
    for r in ok:
        best, _ = runs[r["tree"]]
        note = clock_warning(best or {})
        if note:
            problems.append(f"{r['tree']}: WARNING: {note}")
    if problems:
        doc.h(2, "Warnings")
        doc.items(problems)
    doc.h(2, "Trees")
    doc.p(
        "Each tree beside the mean of its clones (tree / clones); the verdict of the clones' fidelity table (pass, or "
        "warn with the statistics beyond their limits); the fit's own best distance and its answer's on held-out model "
        "seeds; evaluations, why the search stopped (`budget`, `convergence`; `wall_time` or `timeout` make the answer "
        "depend on the machine) and the fit's time with its clones' on the worker that ran it. Every tree's run folder "
        f"is `{StandFiles.RUNS}/NAME` (`bforest report {stand_dir.name}/{StandFiles.RUNS}/NAME` draws its own report)."
    )
    doc.table(
        [
            "tree",
            "model",
            "height (m)",
            "DBH (cm)",
            "crown spread (m)",
            "fidelity",
            "distance own / held-out",
            "evaluations",
            "stop",
            "fit time",
            "reason",
        ],
        _tree_rows(rows, runs),
    )
    doc.h(2, "Fitted parameters")
    for model, header, table in _parameter_tables(rows, runs):
        doc.p(f"**{model}** (each tree's answer; its search box in its recipe, `{StandFiles.RECIPES}/NAME.toml`):")
        doc.table(header, table)
    if figures and ok:
        figs = files.figures_dir
        p = parameters_figure(rows, runs, figs / "parameters")
        if p is not None:
            doc.fig(str(p.relative_to(stand_dir)), "each fitted parameter's place in its tree's search box, per model")
        from ..pipeline.stand import plan_stand

        jobs, _ = plan_stand(settings, stand_dir)
        real = real_plot(jobs)
        doc.h(2, "The plot")
        p = plot_map_figure(real, figs / "plot_map")
        doc.fig(str(p.relative_to(stand_dir)), "the plot from above: every tree at its place")
        if settings.realisations and (files.realisation_dir(0) / "trees.csv").exists():
            synth = realisation_trees(stand_dir, 0)
            p = real_vs_synthetic_figure(real, synth, figs / "real_vs_synthetic", "synthetic stand 0")
            doc.fig(
                str(p.relative_to(stand_dir)),
                "the real plot (left) beside synthetic stand 0 (right: a clone of each tree at its place), top and "
                "side view, one scale",
            )
    if settings.realisations:
        doc.h(2, "Synthetic stands")
        doc.p(
            f"`{StandFiles.SYNTHETIC}/stand_NNN/`: `plot.{settings.mesh}` (the plot's cylinder mesh), `plot.las` (a "
            f"synthetic scan of the plot, {settings.scan_density:g} points per m² of bark, the tree of every point in "
            "`tree_id`) and `trees.csv` (each tree's place, clone file, model, seed and parameters)."
        )
    doc.h(2, "Reproduce")
    doc.code(
        f"bforest stand --resume -o {stand_dir.name}    # continues unfinished trees; a finished stand: nothing to do"
    )
    from .. import __version__

    doc.p(f"Written {_dt.datetime.now().strftime('%Y-%m-%d %H:%M:%S')} by bforest {__version__}.")
    md = files.report_md_path
    md.write_text(doc.markdown(), encoding="utf-8")
    files.report_html_path.write_text(doc.html(stand_dir, title), encoding="utf-8")
    return md
