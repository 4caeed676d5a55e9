"""Figures fit for a paper (issue 33, item 4): ``bforest report --format png|svg|pdf --dpi N``
writes every figure in that format, nothing drawn is clipped, and the parameter plot reads at 18
parameters."""

from __future__ import annotations

import re
import shutil
import struct
from pathlib import Path

import numpy as np
import pytest
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

import bforest_core as bf
from bforest_core.pipeline.clones import clones as grow_clones
from bforest_core.report import convergence, write_report
from conftest import toy_config


def png_size(path) -> tuple[int, int]:
    data = Path(path).read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n", f"{path} is not a PNG"
    return struct.unpack(">II", data[16:24])


def _figures(md: str) -> list[str]:
    return re.findall(r"!\[[^\]]*\]\((figures/[^)]+)\)", md)  # the images, not the PDF links


def _final(fname) -> Path:
    """The file a figure saved to ``fname`` ends as: figures are written whole, into
    ``.NAME.tmp/NAME`` and then renamed."""
    f = Path(fname)
    return f.parent.parent / f.name if f.parent.name.endswith(".tmp") else f


@pytest.fixture(scope="module")
def sampler_run(toy_plugin, tmp_path_factory):
    """A toy abc-smc fit with clones and its PNG report, every kind of figure a report draws
    (trees, data sets, convergence, parameters, corner, generations, clones, their metrics and
    distributions), drawn in this process; returns the run and every ``(figure, file, dpi)`` saved."""
    import bforest_core.report.build as build

    base = tmp_path_factory.mktemp("formats")
    p = toy_config(base, optimizer="abc-smc", optimizer_settings="particles = 10\ngenerations = 3", budget=200)
    bf.fit(bf.load_config(p), base / "run", progress=False)
    grow_clones(base / "run", n=4, progress=False)
    saved, real_save, real_cores = [], Figure.savefig, build._cores

    def spy(self, fname, *a, **kw):
        saved.append((self, _final(fname), kw.get("dpi")))
        return real_save(self, fname, *a, **kw)

    Figure.savefig, build._cores = spy, (lambda: 1)
    try:
        write_report(base / "run", strict=True)
    finally:
        Figure.savefig, build._cores = real_save, real_cores
    return base / "run", saved


@pytest.mark.parametrize("fmt", ["svg", "pdf"])
def test_every_figure_is_written_in_the_chosen_format(sampler_run, tmp_path, fmt):
    from bforest_core.cli import main

    sampler_run, _ = sampler_run
    png = _figures((sampler_run / "report.md").read_text())
    stems = sorted(Path(f).stem for f in png)
    assert {
        "trees",
        "convergence",
        "parameters",
        "corner",
        "generations",
        "clones",
        "clone_metrics",
        "distributions",
    } <= set(stems)
    run = tmp_path / "run"
    shutil.copytree(sampler_run, run)
    shutil.rmtree(run / "figures")
    assert main(["report", str(run), "--format", fmt]) == 0
    written = sorted(p.stem for p in (run / "figures").glob(f"*.{fmt}"))
    assert written == stems
    for stem in stems:
        head = (run / "figures" / f"{stem}.{fmt}").read_bytes()[:400]
        assert (b"<svg" in head) if fmt == "svg" else head.startswith(b"%PDF-")
    md = (run / "report.md").read_text()
    html = (run / "report.html").read_text()
    if fmt == "svg":
        assert sorted(Path(f).stem for f in _figures(md)) == stems and all(f.endswith(".svg") for f in _figures(md))
        assert html.count("data:image/svg+xml;base64,") == len(stems)
    else:  # report.md and report.html show the PNG preview and link the PDF
        assert all(f.endswith(".png") for f in _figures(md)) and md.count("([PDF](figures/") == len(stems)
        assert html.count("data:image/png;base64,") == len(stems) and html.count(">PDF</a>") == len(stems)
        assert sorted(p.stem for p in (run / "figures").glob("*.png")) == stems


def test_the_runs_report_keeps_its_format_and_leaves_no_other_figures(sampler_run, tmp_path):
    """Issue 78, item 5: after `bforest report --format svg`, `bforest clones` rewrote the report
    with PNGs and left the SVGs beside them. The run keeps the format and dpi it was last asked for,
    and figures/ holds just the files the report links."""
    import json

    from bforest_core.cli import main

    sampler_run, _ = sampler_run
    run = tmp_path / "run"
    shutil.copytree(sampler_run, run)
    stems = sorted(Path(f).stem for f in _figures((run / "report.md").read_text()))
    assert main(["report", str(run), "--format", "svg", "--dpi", "60"]) == 0
    assert main(["clones", str(run), "-n", "5", "-q"]) == 0  # writes the report again
    assert json.loads((run / "report_options.json").read_text()) == {"format": "svg", "dpi": 60}
    assert sorted(p.name for p in (run / "figures").iterdir()) == sorted(f"{s}.svg" for s in stems)
    assert all(f.endswith(".svg") for f in _figures((run / "report.md").read_text()))
    assert main(["report", str(run), "--format", "png"]) == 0  # the dpi asked for before stays
    assert json.loads((run / "report_options.json").read_text()) == {"format": "png", "dpi": 60}
    assert sorted(p.name for p in (run / "figures").iterdir()) == sorted(f"{s}.png" for s in stems)
    w60, _ = png_size(run / "figures" / "trees.png")
    w130, _ = png_size(sampler_run / "figures" / "trees.png")
    assert w60 / w130 == pytest.approx(60 / 130, rel=0.05)
    shutil.rmtree(run / "clones")  # figures of clones that are gone leave with them
    assert main(["report", str(run)]) == 0
    assert not list((run / "figures").glob("clone*")) and (run / "figures" / "trees.png").exists()


def test_dpi_sets_the_resolution_and_a_bad_value_is_one_line(tmp_path, capsys, monkeypatch):
    from bforest_core.cli import main
    from bforest_core.report.canvas import figure_output

    d = np.r_[0.5, 0.4, 0.3, 0.35, 0.2]
    w130, h130 = png_size(convergence.convergence_figure(d, tmp_path / "a.png"))  # its own 130 dpi
    with figure_output("png", 260):
        w260, h260 = png_size(convergence.convergence_figure(d, tmp_path / "b.png"))
    assert w260 / w130 == pytest.approx(2.0, rel=0.01) and h260 / h130 == pytest.approx(2.0, rel=0.01)
    seen = {}
    monkeypatch.setattr(
        "bforest_core.report.build.write_report", lambda run, **kw: seen.update(kw) or Path(run) / "report.md"
    )
    assert main(["report", str(tmp_path), "--format", "svg", "--dpi", "300"]) == 0
    assert seen == {"format": "svg", "dpi": 300}
    capsys.readouterr()
    assert main(["report", str(tmp_path), "--dpi", "5"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["error: --dpi must be between 20 and 600 (got 5)"]


def test_a_label_beyond_the_bottom_edge_is_saved_not_clipped(tmp_path):
    """An x label below the figure's edge (axes placed by hand, no layout) is in the file: the
    image grows to hold it, and its bottom rows hold the label's dark pixels."""
    import matplotlib.image as mpimg

    from bforest_core.report.canvas import new_figure, save_figure

    fig = new_figure(4.0, 3.0, layout=None)
    ax = fig.add_axes([0.12, 0.03, 0.83, 0.9])
    ax.plot([0, 1], [0, 1])
    ax.set_xlabel("a bottom axis label", fontsize=14)
    p = save_figure(fig, tmp_path / "f.png", dpi=100)
    w, h = png_size(p)
    assert h > 300 + 20  # 3 in at 100 dpi, plus the tick labels and the label below the edge
    img = mpimg.imread(p)[..., :3].mean(axis=2)
    assert img[-int(0.06 * h) :].min() < 0.3  # the label's text is in the bottom rows


def _drawn_box(fig, dpi):
    canvas = FigureCanvasAgg(fig)
    fig.set_dpi(dpi)
    canvas.draw()
    return fig.get_tightbbox(canvas.get_renderer())


def test_no_report_figure_is_clipped(sampler_run, tmp_path, monkeypatch):
    """Every figure of a report, and the worst-lines figure whose long line formulas reach past
    the right edge, is saved as the box of everything drawn on it (plus a 0.05 in pad)."""
    from bforest_core.report import datasets

    _, saved = sampler_run
    saved = list(saved)
    real = Figure.savefig

    def spy(self, fname, *a, **kw):
        saved.append((self, _final(fname), kw.get("dpi")))
        return real(self, fname, *a, **kw)

    monkeypatch.setattr(Figure, "savefig", spy)
    rng = np.random.default_rng(2)  # line formulas of S0,1's columns that reach past the right edge
    ud, um = rng.normal(size=(200, 6)), rng.normal(0.3, 1, size=(150, 6))
    A = rng.normal(size=(32, 6))
    A /= np.linalg.norm(A, axis=1, keepdims=True)
    datasets.worst_lines_figure(
        um,
        ud,
        A,
        ["R", "L", "sin(gamma)", "cos(gamma)", "sin(zeta)", "cos(zeta)"],
        tmp_path / "lines.png",
        k=4,
        normalised=True,
    )
    pngs = [(f, p, dpi) for f, p, dpi in saved if p.suffix == ".png"]
    assert len(pngs) >= 10
    for fig, path, dpi in pngs:
        box = _drawn_box(fig, dpi)
        w, h = png_size(path)
        # the file holds the whole box (whatever lies past the figure's edge included), and not much more
        assert w >= box.width * dpi - 2 and h >= box.height * dpi - 2, (path.name, (w, h), box.bounds)
        tol = 0.1 * dpi  # a redraw's layout may move by a few pixels
        assert abs(w - (box.width + 0.1) * dpi) <= tol and abs(h - (box.height + 0.1) * dpi) <= tol, (
            path.name,
            (w, h),
            box.bounds,
            fig.get_size_inches(),
        )


def test_parameter_plot_reads_at_18_parameters(tmp_path, monkeypatch):
    """The colour bar was as tall as the whole figure (18 panels in 6 rows): it is a bar across
    the top now, one row wide, and the figure stays within a screen's width."""
    figs = []
    real = convergence.save_figure
    monkeypatch.setattr(convergence, "save_figure", lambda fig, path, dpi=130: figs.append(fig) or real(fig, path, dpi))
    rng = np.random.default_rng(0)
    names = [f"param_{i}" for i in range(18)]
    p = convergence.parameter_scatter_figure(
        names, rng.random((300, 18)), rng.random(300), tmp_path / "p.png", best={"param_0": 0.5}
    )
    fig = figs[-1]
    fig.canvas.draw()
    bar = next(ax for ax in fig.axes if ax.get_label() == "<colorbar>")
    panels = [ax for ax in fig.axes if ax.get_visible() and ax is not bar and ax.collections]
    assert len(panels) == 18
    bb = bar.get_position()
    assert bb.height < 0.05 and bb.width > 0.3  # horizontal, thin
    assert bb.y0 > max(ax.get_position().y1 for ax in panels)  # above the panels
    assert png_size(p)[0] <= 1700


def _slender_tree():
    """A 20 m stem of 0.3 m laterals, each with a 0.2 m shoot (orders 0-2): a slender tree's
    figure is narrower than its captions."""
    n = 20
    start = [[0, 0, float(i)] for i in range(n)]
    axis, length, radius = [[0, 0, 1]] * n, [1.0] * n, list(np.linspace(0.2, 0.02, n))
    parent, extension = [-1] + list(range(n - 1)), list(range(1, n)) + [-1]
    for i in range(n):  # a lateral on every stem cylinder, and a shoot on it
        a = 2 * np.pi * i / 5
        d = [np.cos(a), np.sin(a), 0.0]
        k = len(start)
        start += [[0, 0, i + 1.0], [0.3 * d[0], 0.3 * d[1], i + 1.0]]
        axis += [d, [0, 0, 1]]
        length += [0.3, 0.2]
        radius += [0.01, 0.005]
        parent += [i, k]
        extension += [-1, -1]
    return bf.Tree(start, axis, length, radius, parent, extension, topology="source")


@pytest.mark.parametrize("rows", [["target (QSM)", "best fit"], [""]])
def test_the_legend_covers_no_title_of_a_slender_trees_figure(tmp_path, monkeypatch, rows):
    """Issue 78, item 9: in trees.png the order legend, beside the rows, covered the end of the
    first row's caption for a slender tree (the figure is narrower than its captions). No title,
    caption or axis label overlaps the legend, with two rows (the report's) and one (bforest simulate --png)."""
    from bforest_core.report import trees

    figs, real = [], trees.save_figure
    monkeypatch.setattr(trees, "save_figure", lambda fig, path, dpi=130: figs.append(fig) or real(fig, path, dpi))
    tree = _slender_tree()
    trees.tree_comparison_figure(
        dict.fromkeys(rows, tree),
        tmp_path / "t.png",
        title="Target and best-fit tree (line width ∝ radius, colour = branch order)",
    )
    (fig,) = figs
    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    r = canvas.get_renderer()
    (legend,) = fig.legends
    box = legend.get_window_extent(r)
    from matplotlib.text import Text

    skip = set(legend.findobj(Text)) | {t for ax in fig.get_axes() for t in ax.get_xticklabels() + ax.get_yticklabels()}
    texts = [t for t in fig.findobj(Text) if t.get_visible() and t.get_text().strip() and t not in skip]
    assert sum(t.get_text().startswith("side view") for t in texts) == 2 * len(rows)
    over = [t.get_text()[:40] for t in texts if t.get_window_extent(r).overlaps(box)]
    assert not over, f"the legend covers {over}"
