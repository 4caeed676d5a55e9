"""Shared drawing conventions of every figure (matplotlib, headless).

Every ``*_figure`` function of the report draws on a fresh :class:`matplotlib.figure.Figure` (no
pyplot, no global backend switch: it renders with Agg and never needs a display) and writes a PNG
(or SVG or PDF: :func:`figure_output`).
Conventions follow Potapov et al. (GigaScience 2017): the data side (QSM) is blue, the model side
(SSM) red; branch orders have fixed colours; lengths are in metres and angles in degrees.
"""

from __future__ import annotations

from contextlib import contextmanager
from pathlib import Path

from matplotlib.figure import Figure

from ..io import whole_file

#: colours of branch orders 0 (trunk), 1, 2, ...; the last one repeats for higher orders
ORDER_COLORS = ("#5a3a1a", "#1f77b4", "#2ca02c", "#ff7f0e", "#9467bd", "#d62728", "#17becf", "#e377c2", "#8c8c8c")
DATA_COLOR = "#1f5fbf"  # QSM / target (blue, as in the GigaScience figures)
MODEL_COLOR = "#d62728"  # SSM / model (red)
TARGET_LINE = "black"
TRUE_COLOR = "#2ca02c"  # the true parameters of a generated target (green)

#: view name -> (horizontal coordinate, vertical coordinate, coordinate pointing at the viewer,
#: sign). "xz" looks along +y (y points away), "yz" along -x, "xy" down from above.
VIEWS = {"xz": (0, 2, 1, -1.0), "yz": (1, 2, 0, 1.0), "xy": (0, 1, 2, 1.0)}
_AXIS_NAMES = "xyz"
_VIEW_TITLES = {"xz": "side view (XZ)", "yz": "side view (YZ)", "xy": "top view (XY)"}

#: units of the branch-segment feature columns (docs/features-and-distance.md §2)
COLUMN_UNITS = {
    "beta": "deg",
    "alpha": "deg",
    "gamma": "deg",
    "zeta": "deg",
    "L_t": "m",
    "R_f": "m",
    "L_a": "m",
    "R": "m",
    "L": "m",
    "angle": "deg",
    "length": "m",
}
_GREEK = {
    "beta": r"$\beta$",
    "alpha": r"$\alpha$",
    "gamma": r"$\gamma$",
    "zeta": r"$\zeta$",
    "L_t": r"$L_t$",
    "R_f": r"$R_f$",
    "L_a": r"$L_a$",
}


# ---------------------------------------------------------------------------------- figures
def new_figure(width: float, height: float, layout: str | None = "constrained") -> Figure:
    """A new Agg-backed figure (inches)."""
    fig = Figure(figsize=(width, height), layout=layout)
    return fig


#: widest figure in pixels at its dpi: a report is read on a normal screen
MAX_WIDTH_PX = 1600
#: the margin around everything a figure draws in its file
PAD_INCHES = 0.05


def capped_size(width: float, height: float, dpi: int, max_px: int = MAX_WIDTH_PX) -> tuple[float, float]:
    """(width, height) in inches scaled down together so the PNG is at most ``max_px`` wide (its
    saved box, :func:`save_figure`, adds a pad of 0.05 in on each side)."""
    f = min(1.0, (max_px - 2 * PAD_INCHES * dpi) / (width * dpi))
    return width * f, height * f


#: the format every figure is written in, and a resolution that overrides the figures' own:
#: set for a whole report by :func:`figure_output` (``bforest report --format --dpi``)
FORMATS = ("png", "svg", "pdf")
_OUTPUT = {"format": "png", "dpi": None}
#: the resolutions a report may ask for: at 600 dpi the largest figure is about 7 400 px wide and
#: takes a few hundred MB to draw (at 2 400 dpi, gigabytes: the report ran out of memory)
DPI_RANGE = (20, 600)


def check_dpi(dpi: int | None) -> None:
    """ValueError naming ``--dpi`` when ``dpi`` is outside :data:`DPI_RANGE` (None: the figures' own)."""
    if dpi is not None and not DPI_RANGE[0] <= dpi <= DPI_RANGE[1]:
        raise ValueError(f"--dpi must be between {DPI_RANGE[0]} and {DPI_RANGE[1]} (got {dpi})")


@contextmanager
def figure_output(format: str = "png", dpi: int | None = None):
    """Within the block :func:`save_figure` writes ``format`` (png, svg or pdf) at ``dpi``
    (None: each figure's own resolution)."""
    if format not in FORMATS:
        raise ValueError(f"figure format {format!r} is not one of {', '.join(FORMATS)}")
    check_dpi(dpi)
    saved = dict(_OUTPUT)
    _OUTPUT.update(format=format, dpi=dpi)
    try:
        yield
    finally:
        _OUTPUT.clear()
        _OUTPUT.update(saved)


def current_output() -> tuple[str, int | None]:
    """The ``(format, dpi)`` :func:`save_figure` writes now."""
    return _OUTPUT["format"], _OUTPUT["dpi"]


def save_figure(fig: Figure, path, dpi: int = 130) -> Path:
    """Write ``fig`` (creating the folder) in the current output format (PNG unless
    :func:`figure_output` says otherwise; the path's suffix follows it) and return the path.

    The saved area is the box of everything drawn (``bbox_inches="tight"``), so no axis label,
    legend or title placed beyond the figure's edge is clipped. A PDF also gets a PNG preview
    beside it (for report.html, which cannot show a PDF inline)."""
    fmt = _OUTPUT["format"]
    dpi = _OUTPUT["dpi"] or dpi
    path = Path(path).with_suffix("." + fmt)
    path.parent.mkdir(parents=True, exist_ok=True)
    opts = dict(dpi=dpi, facecolor="white", bbox_inches="tight", pad_inches=PAD_INCHES)
    for out, kind in [(path, fmt)] + ([(path.with_suffix(".png"), "png")] if fmt == "pdf" else []):
        with whole_file(out) as part:
            fig.savefig(part, format=kind, **opts)
    return path


def column_label(name: str) -> str:
    """Axis label of a feature column with its unit, e.g. ``"β (deg)"``."""
    unit = COLUMN_UNITS.get(name)
    shown = _GREEK.get(name, name)
    return f"{shown} ({unit})" if unit else shown
