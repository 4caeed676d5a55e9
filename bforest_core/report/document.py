"""The report document (Markdown and HTML from one list of blocks) and its number formats."""

from __future__ import annotations

import base64
import html as _html
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..pipeline.store import slug  # noqa: F401  (the run directory names files; the report follows)

if TYPE_CHECKING:  # annotations only: run_view imports this module's neighbours
    from .run_view import RunView


METRIC_ROWS = (
    ("height", "height (m)", "d_h"),
    ("girth", "base diameter (m)", "d_g"),
    ("crown_spread", "crown spread (m)", "d_c"),
    ("dbh", "DBH at 1.3 m (m)", None),
)


def fmt(v, digits: int = 4) -> str:
    if v is None:
        return "–"
    if isinstance(v, bool):
        return str(v)
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        if not np.isfinite(v):
            return "–" if np.isnan(v) else str(v)
        if v != 0 and (abs(v) >= 1e5 or abs(v) < 1e-3):
            return f"{v:.{digits - 1}e}"
        return f"{v:.{digits}g}"
    return str(v)


def seconds_text(s) -> str:
    if s is None or not np.isfinite(s):
        return "–"
    s = float(s)
    if s < 120:
        return f"{s:.1f} s"
    if s < 7200:
        return f"{s / 60:.1f} min"
    return f"{s / 3600:.2f} h"


# ---------------------------------------------------------------------------------- document
_TAG_START = re.compile(r"<(?=[A-Za-z/!?])")
_CODE_SPAN = re.compile(r"(`[^`]+`)")


@dataclass
class Document:
    """A tiny document model rendered to both Markdown and HTML."""

    blocks: list = field(default_factory=list)

    def h(self, level: int, text: str):
        self.blocks.append(("h", level, text))

    def p(self, text: str):
        self.blocks.append(("p", text))

    def items(self, items: list[str]):
        if items:
            self.blocks.append(("list", list(items)))

    def table(self, header: list[str], rows: list[list]):
        self.blocks.append(("table", header, [[fmt(c) if not isinstance(c, str) else c for c in r] for r in rows]))

    def fig(self, rel: str, caption: str):
        self.blocks.append(("fig", rel, caption))

    def figure_files(self) -> set[str]:
        """Every file the figures link (relative to the run folder): a PDF and its PNG preview."""
        out = set()
        for b in self.blocks:
            if b[0] == "fig":
                out.update({b[1], _shown(b[1])[0]})
        return out

    def code(self, text: str):
        self.blocks.append(("code", text))

    def details(self, summary: str, text: str):
        """A block of preformatted ``text`` shown closed under ``summary`` (opened by a click)."""
        self.blocks.append(("details", summary, text))

    def raw_html(self, html: str, markdown: str = ""):
        """A block of HTML for report.html (trusted: written by the report itself) and its
        stand-in in report.md."""
        self.blocks.append(("raw", html, markdown))

    # ----------------------------------------------------------------- markdown
    @staticmethod
    def _md(text) -> str:
        """Text for Markdown with no raw HTML: a ``<`` that would open a tag (``<script>``,
        ``<img``, ``</``, ``<!``) from a file or parameter name is written as ``&lt;``, except in
        a code span (`` `...` ``), whose text Markdown shows as it is (an entity there would
        show as ``&lt;``)."""
        parts = _CODE_SPAN.split(str(text))
        return "".join(p if i % 2 else _TAG_START.sub("&lt;", p) for i, p in enumerate(parts))

    def markdown(self) -> str:
        out = []
        md = self._md
        for b in self.blocks:
            kind = b[0]
            if kind == "h":
                out.append("#" * b[1] + " " + md(b[2]))
            elif kind == "p":
                out.append(md(b[1]))
            elif kind == "list":
                out.append("\n".join(f"- {md(x)}" for x in b[1]))
            elif kind == "table":
                header, rows = b[1], b[2]
                esc = lambda c: md(c).replace("|", "\\|").replace("\n", " ")
                lines = ["| " + " | ".join(esc(c) for c in header) + " |", "|" + "|".join("---" for _ in header) + "|"]
                lines += ["| " + " | ".join(esc(c) for c in r) + " |" for r in rows]
                out.append("\n".join(lines))
            elif kind == "fig":
                shown, pdf = _shown(b[1])
                out.append(f"![{md(b[2])}]({shown})\n\n*{md(b[2])}*" + (f" ([PDF]({b[1]}))" if pdf else ""))
            elif kind == "code":
                out.append("```\n" + b[1] + "\n```")
            elif kind == "details":  # the fence outlasts any run of backticks in the text
                fence = "`" * max(3, 1 + max((len(r) for r in re.findall(r"`+", b[2])), default=0))
                out.append(
                    f"<details><summary>{_html.escape(b[1])}</summary>\n\n{fence}\n{b[2].rstrip()}\n{fence}\n\n</details>"
                )
            elif kind == "raw" and b[2]:
                out.append(md(b[2]))
        return "\n\n".join(out) + "\n"

    # ----------------------------------------------------------------- html
    @staticmethod
    def _inline(text: str) -> str:
        t = _html.escape(text)
        t = re.sub(r"`([^`]+)`", r"<code>\1</code>", t)
        t = re.sub(r"\*\*([^*]+)\*\*", r"<b>\1</b>", t)
        return t

    def html(self, base: Path, title: str, inline_images: bool = True) -> str:
        parts = []
        for b in self.blocks:
            kind = b[0]
            if kind == "h":
                parts.append(f"<h{b[1]}>{self._inline(b[2])}</h{b[1]}>")
            elif kind == "p":
                parts.append(f"<p>{self._inline(b[1])}</p>")
            elif kind == "list":
                parts.append("<ul>" + "".join(f"<li>{self._inline(x)}</li>" for x in b[1]) + "</ul>")
            elif kind == "table":
                head = "".join(f"<th>{self._inline(str(c))}</th>" for c in b[1])
                body = "".join("<tr>" + "".join(f"<td>{self._inline(str(c))}</td>" for c in r) + "</tr>" for r in b[2])
                parts.append(f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>")
            elif kind == "fig":
                shown, pdf = _shown(b[1])
                src = shown
                p = base / shown
                if inline_images and p.exists():
                    mime = "image/svg+xml" if p.suffix == ".svg" else "image/png"
                    src = f"data:{mime};base64," + base64.b64encode(p.read_bytes()).decode("ascii")
                link = f' (<a href="{_html.escape(b[1])}">PDF</a>)' if pdf else ""
                parts.append(
                    f'<figure><img src="{src}" alt="{_html.escape(b[2])}">'
                    f"<figcaption>{self._inline(b[2])}{link}</figcaption></figure>"
                )
            elif kind == "raw":
                parts.append(b[1])
            elif kind == "code":
                parts.append(f"<pre>{_html.escape(b[1])}</pre>")
            elif kind == "details":
                parts.append(
                    f"<details><summary>{self._inline(b[1])}</summary><pre>{_html.escape(b[2])}</pre></details>"
                )
        style = (
            "body{font-family:system-ui,-apple-system,Segoe UI,Helvetica,Arial,sans-serif;max-width:1200px;"
            "margin:2em auto;padding:0 1em;color:#222;line-height:1.45}"
            "table{border-collapse:collapse;margin:0.6em 0}th,td{border:1px solid #ccc;padding:3px 8px;"
            "text-align:left;font-size:0.92em}th{background:#f2f2f2}"
            "img{max-width:100%;border:1px solid #eee}figure{margin:1em 0}"
            "figcaption{font-size:0.9em;color:#555}code,pre{background:#f6f6f6;padding:1px 3px}"
            "h1{border-bottom:2px solid #ddd}h2{border-bottom:1px solid #eee;margin-top:1.6em}"
        )
        return (
            f'<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8"><title>{_html.escape(title)}'
            f"</title><style>{style}</style></head><body>\n" + "\n".join(parts) + "\n</body></html>\n"
        )


def _shown(rel: str) -> tuple[str, bool]:
    """(the figure the report shows, whether it is a PDF's preview): a PDF is shown as the PNG
    written beside it."""
    if rel.endswith(".pdf"):
        return rel[:-4] + ".png", True
    return rel, False


def cfg_kind(v: RunView, section: str) -> str:
    if v.cfg is not None:
        return getattr(v.cfg, section).kind
    return str((v.raw_config.get(section) or {}).get("kind", "?"))
