"""``bforest report RUN``: figures and a summary of a run folder.

Writes ``RUN/figures/*.png`` (or ``.svg``, ``.pdf``: ``format``), ``RUN/report.md`` and a
self-contained ``RUN/report.html`` (the figures inline as base64, PDFs as their PNG previews). Everything is read from the run directory (``config.toml``,
``evaluations.sqlite``, ``best.json``, ``target_sets.npz``, ``best_tree.txt``, ``clones/``); what
is missing (an interrupted fit, no clones yet, a distance without projection lines) is skipped
and the report says so. A figure that fails never stops the report (unless ``strict``).

Figures:

* ``trees.png``: target and best fit in XZ, YZ and XY (GigaScience Fig. 2/6);
* ``set_<set>.png``: data (QSM, blue) against model (SSM, red) for every fitted set (Fig. 3);
* ``lines_<set>.png``: ECDFs on the worst-fitting projection lines with the KS gap;
* ``convergence.png``, ``parameters.png``: the optimiser's progress and where it searched;
* ``corner.png``: the posterior's marginals and pairs (every sampler that gives a posterior, with
  the true values of a generated target); ``chain.png``: the trace of a chain (MCMC);
  ``generations.png``: tolerance, acceptance and ESS per generation (a population sampler);
* ``clones.png``, ``clone_metrics.png``: clones beside the target and their metric
  distributions (Fig. 5);
* ``profile_<param>.png``: made by ``bforest profile`` (Fig. 4), included when present.
"""

from __future__ import annotations

import datetime as _dt
import json
import multiprocessing as mp
import os
import signal
import time
from pathlib import Path

from ..errors import quiet_read_repairs
from ..io import whole_file, write_json
from ..processes import available_cores, bind_to_owner
from .attributes import fig_distributions
from .canvas import FORMATS, current_output, figure_output
from .convergence import fig_convergence
from .datasets import fig_sets
from .document import Document, slug
from .posterior import fig_posterior
from .run_view import RunView
from .sections import (
    section_clones,
    section_evaluations,
    section_fit,
    section_model,
    section_optimizer,
    section_parameters,
    section_profiles,
    section_summary,
    section_target,
    stopped_short,
)
from .trees import fig_clones, fig_trees

__all__ = ["write_report", "RunView", "slug"]


# ---------------------------------------------------------------------------------- figures
class _Figures:
    def __init__(self, view: RunView, strict: bool):
        self.v = view
        self.strict = strict
        self.dir = view.store.figures_dir
        self.dir.mkdir(exist_ok=True)
        self.made: dict[str, list[tuple[str, str]]] = {}

    def run(self, section: str, name: str, fn, *args, **kw):
        """Call a figure function; record (relative path, caption) or a note on failure."""
        try:
            res = fn(*args, **kw)
        except Exception as exc:
            if self.strict:
                raise
            self.v.note(f"figure '{name}' failed: {type(exc).__name__}: {exc}")
            return None
        if res:
            for path, caption in res:
                self.made.setdefault(section, []).append((Path(path).relative_to(self.v.path).as_posix(), caption))
        return res


#: (section, name, function) of the report's figures; ``_SIDE`` is drawn in a second process when
#: the machine has two cores or more (a fit's workers are idle by then), so the report takes
#: about half as long: the two groups cost about the same
_SIDE = [("sets", "data sets", fig_sets)]
_MAIN = [
    ("trees", "trees", fig_trees),
    ("convergence", "convergence", fig_convergence),
    ("posterior", "posterior", fig_posterior),
    ("clones", "clones", fig_clones),
    ("clones", "distributions", fig_distributions),
]


def _side_figures(run_dir, strict: bool, output: tuple = ("png", None)):
    """Draw the ``_SIDE`` figures from a fresh view of ``run_dir`` (in the second process, which
    never touches the first one's database connection) in the ``(format, dpi)`` of ``output``.
    Returns (figures made, notes)."""
    quiet_read_repairs()  # the command has reported the target's repairs
    v = RunView(run_dir)
    figs = _Figures(v, strict)
    with figure_output(*output):
        for section, name, fn in _SIDE:
            figs.run(section, name, fn, v)
    v.store.close()
    return figs.made, v.notes


def _side_main(conn, owner: int, run_dir, strict: bool, output: tuple) -> None:
    """The second process's life: the ``_SIDE`` figures, sent back as ``("ok", (made, notes))``
    or ``("error", text)``. It ends with the command however that ends (``bind_to_owner``) and
    leaves Ctrl-C to it (the command stops this process as it unwinds)."""
    bind_to_owner(owner)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        result = ("ok", _side_figures(run_dir, strict, output))
    except Exception as exc:
        result = ("error", f"{type(exc).__name__}: {exc}")
    try:
        conn.send(result)
    except OSError:  # the command has gone: nothing to tell
        pass


class _SideProcess:
    """The report's second process (spawned: a fresh interpreter with this one's ``sys.path``,
    so plugins are found the same way), drawing the ``_SIDE`` figures while this one draws the
    rest. :meth:`stop` ends it whatever it is doing: nothing a report starts outlives it."""

    def __init__(self, run_dir, strict: bool, output: tuple):
        ctx = mp.get_context("spawn")
        self.conn, child = ctx.Pipe(duplex=False)
        self.proc = ctx.Process(
            target=_side_main, args=(child, os.getpid(), run_dir, strict, output), name="bforest-report", daemon=True
        )
        try:
            self.proc.start()
        finally:
            child.close()

    def result(self) -> tuple:
        """(figures made, notes) of the second process; RuntimeError when it failed or died."""
        try:
            kind, payload = self.conn.recv()
        except (EOFError, OSError):
            self.proc.join(5)
            raise RuntimeError(f"it ended (exit code {self.proc.exitcode}) before it sent its figures") from None
        if kind == "error":
            raise RuntimeError(payload)
        return payload

    def stop(self) -> None:
        if self.proc.is_alive():
            self.proc.kill()
        self.proc.join(5)
        self.conn.close()


def _cores() -> int:
    return available_cores()


def _draw_figures(v: RunView, figs: _Figures, strict: bool) -> None:
    side = None
    if _cores() >= 2:
        try:
            side = _SideProcess(v.path, strict, current_output())
        except OSError as exc:  # no second process here: draw everything in this one
            v.note(f"figures drawn in one process ({exc})")
    try:
        for section, name, fn in _MAIN if side else _SIDE + _MAIN:
            figs.run(section, name, fn, v)
        if side:
            try:
                made, notes = side.result()
            except RuntimeError as exc:
                if strict:
                    raise
                v.note(f"the second report process failed ({exc}); its figures were drawn here")
                for section, name, fn in _SIDE:
                    figs.run(section, name, fn, v)
            else:
                for section, items in made.items():
                    figs.made.setdefault(section, []).extend(items)
                for text in notes:
                    v.note(text)
    finally:  # done, failed or stopped by the user: the second process ends with this one
        if side:
            side.stop()


# ---------------------------------------------------------------------------------- entry point
def write_report(
    run_dir,
    figures: bool = True,
    html: bool = True,
    strict: bool = False,
    format: str | None = None,
    dpi: int | None = None,
) -> Path:
    """Write the figures, ``report.md`` and ``report.html`` of a run directory.

    Parameters
    ----------
    run_dir : path
        A run directory (``bforest fit`` output).
    figures : bool
        Draw the figures (False: text only, fast).
    html : bool
        Also write ``report.html`` with the figures inline.
    strict : bool
        Raise when a figure fails instead of noting it in the report.
    format : {"png", "svg", "pdf"}, optional
        Format of every figure (a PDF gets a PNG preview beside it for ``report.html``); None:
        the format of the run's last report (``report_options.json``), else PNG.
    dpi : int, optional
        Resolution of raster figures (and of the raster parts of vector ones); None: the run's
        last report's, else each figure's own (120-130).

    Notes
    -----
    On a machine with two cores or more the data-set figures are drawn in a second, spawned
    process (about 40 % less wall time on a recipe's run: 15 s -> 8-10 s for runs of
    ``examples/real/pine_sot.toml``). As for the process executor, a script that calls this must
    guard its entry point with ``if __name__ == "__main__":``; without it the second process
    cannot start, and its figures are drawn in this one (with a note in the report).

    The format and dpi are kept in ``report_options.json``, so the report that ``bforest clones``
    or a resumed fit writes again keeps them; a figure file of ``figures/`` that the new report
    does not link (another format's, a figure of clones that are gone) is removed.

    Returns
    -------
    Path
        The path of ``report.md``.
    """
    t0 = time.monotonic()
    v = RunView(run_dir)
    output = _output_options(v.store.report_options_path, format, dpi)
    figs = _Figures(v, strict)
    if figures:
        with figure_output(*output):
            _draw_figures(v, figs, strict)
    doc = Document()
    title = f"Bayes Forest run report: {v.path.name}"
    doc.h(1, title)
    section_summary(doc, v)
    section_target(doc, v)
    section_model(doc, v)
    section_parameters(doc, v)
    section_fit(doc, v, figs)
    section_optimizer(doc, v, figs)
    section_evaluations(doc, v)
    section_clones(doc, v, figs)
    section_profiles(doc, v)
    doc.h(2, "Notes")
    from .. import __version__

    notes = list(v.notes)
    if stopped_short(v):
        notes.insert(0, f"WARNING: the sampler stopped short of its target: {stopped_short(v)}")
    if not figures:
        notes.append("figures were not drawn (figures=False)")
    doc.items(notes or ["none"])
    doc.p(
        f"Written {_dt.datetime.now().strftime('%Y-%m-%d %H:%M:%S')} by bforest {__version__} "
        f"in {time.monotonic() - t0:.1f} s."
    )
    md = v.store.report_md_path
    with whole_file(md) as part:  # a full disk leaves the report before, never half of one
        part.write_text(doc.markdown(), encoding="utf-8")
    if html:
        with whole_file(v.store.report_html_path) as part:
            part.write_text(doc.html(v.path, title), encoding="utf-8")
    if figures:
        _remove_unlinked(v, doc.figure_files())
        write_json(v.store.report_options_path, {"format": output[0], "dpi": output[1]})
    v.store.close()
    return md


def _output_options(path: Path, format: str | None, dpi: int | None) -> tuple[str, int | None]:
    """The report's ``(format, dpi)``: those asked for, else the run's last report's, else PNG at
    each figure's own resolution."""
    last = {}
    if path.exists():
        try:
            last = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError):  # a damaged file: the defaults
            last = {}
    fmt = format or last.get("format") or "png"
    if fmt not in FORMATS:
        fmt = "png"
    return fmt, dpi if dpi is not None else last.get("dpi")


def _remove_unlinked(v: RunView, linked: set[str]) -> None:
    """Remove the figure files the report does not link (another format's, a figure of clones
    that are gone): figures/ shows what the report shows."""
    for p in v.store.figures_dir.glob("*"):
        rel = p.relative_to(v.path).as_posix()
        if p.is_file() and p.suffix[1:] in FORMATS and rel not in linked:
            p.unlink()
