"""The repository stands on its own: a user who clones it has only what it holds.

* No tracked file (outside ``.ci/``) cites the external development notes that live beside the
  repository (a ``shared/`` folder with ``spec/`` pages and a design sketch): the project's own
  reference pages are docs/models.md, docs/features-and-distance.md and docs/qsm-formats.md. The
  one sibling folder a file may name is the sample data, ``../shared/data/qsm``, which tests and
  examples read and skip without.
* Every ``docs/<name>.md`` a file names and every relative link of a Markdown page resolves to a
  file of the repository, and a link's ``#anchor`` to a heading of the page it points to (as
  GitHub makes anchors: lower case, punctuation dropped, spaces as hyphens).
"""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
THIS = Path(__file__).resolve()

#: what a standalone repository must not cite (the sample-data folder is the one exception)
EXTERNAL = re.compile(
    r"DESIGN\.md"  # the design sketch
    r"|\bshared/(?!data/qsm\b)"  # shared/spec/..., ../shared/papers, ...
    r"|[\"']shared[\"']\s*/\s*[\"'](?!data[\"']\s*/\s*[\"']qsm[\"'])"
)  # ROOT.parent / "shared" / "spec"

#: a page of the docs named in text: docs/models.md, docs/examples/x/README.md
DOC_PATH = re.compile(r"(?<![\w/.-])docs/[\w./-]*?\.md\b")
#: the target of a Markdown link or image: [text](target)
MD_LINK = re.compile(r"\]\(([^)\s]+)\)")

SKIP_SUFFIXES = {".png", ".jpg", ".jpeg", ".gif", ".mat", ".npz", ".npy", ".parquet", ".sqlite", ".pdf"}


def tracked_files() -> list[Path]:
    """The files of the repository: ``git ls-files`` in a checkout, else a walk of the tree."""
    try:
        out = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True)
        names = [n for n in out.stdout.decode("utf-8", "surrogateescape").split("\0") if n]
    except (OSError, subprocess.CalledProcessError):
        skip = {".git", ".venv", "runs", "demo-run", "__pycache__", ".pytest_cache"}
        names = [
            str(p.relative_to(ROOT))
            for p in ROOT.rglob("*")
            if p.is_file()
            and not skip.intersection(p.relative_to(ROOT).parts)
            and not any(part.endswith(".egg-info") for part in p.parts)
        ]
    return [ROOT / n for n in sorted(names) if not n.startswith(".ci/")]


def text_of(path: Path) -> str | None:
    """The file's text, or None for a binary, missing or unreadable file."""
    if path.suffix.lower() in SKIP_SUFFIXES or not path.is_file():
        return None
    data = path.read_bytes()
    if b"\0" in data[:8192]:
        return None
    return data.decode("utf-8", "replace")


def external_citations(paths: list[Path], root: Path = ROOT) -> list[str]:
    """``file:line: text`` of every line that cites the external notes."""
    found = []
    for p in paths:
        if p.resolve() == THIS:
            continue
        text = text_of(p)
        if text is None:
            continue
        for i, line in enumerate(text.splitlines(), 1):
            if EXTERNAL.search(line):
                found.append(f"{p.relative_to(root)}:{i}: {line.strip()[:160]}")
    return found


def heading_anchors(text: str) -> set[str]:
    """The anchors GitHub gives a Markdown page's headings (code blocks left out): lower case,
    every character but letters, digits, ``_``, ``-`` and spaces dropped, spaces as hyphens; a
    repeated heading gets ``-1``, ``-2``, ..."""
    out, seen, fence = set(), {}, False
    for line in text.splitlines():
        if line.lstrip().startswith("```"):
            fence = not fence
            continue
        m = None if fence else re.match(r"#{1,6}\s+(.*?)\s*#*\s*$", line)
        if m:
            slug = re.sub(r"[^\w\- ]", "", m.group(1).strip().lower()).replace(" ", "-")
            n = seen.get(slug, 0)
            seen[slug] = n + 1
            out.add(slug if n == 0 else f"{slug}-{n}")
    return out


def broken_doc_links(paths: list[Path], root: Path = ROOT) -> list[str]:
    """``file: target`` of every ``docs/....md`` mention and relative Markdown link that does not
    resolve (mentions from the repository root, links from the page's folder), and of every link
    whose ``#anchor`` names no heading of the Markdown page it points to."""
    bad = []
    for p in paths:
        if p.resolve() == THIS or p.suffix not in (".md", ".py", ".toml", ".txt"):
            continue
        text = text_of(p)
        if text is None:
            continue
        for m in DOC_PATH.finditer(text):
            if not (root / m.group(0)).exists():
                bad.append(f"{p.relative_to(root)}: {m.group(0)}")
        if p.suffix == ".md":
            for m in MD_LINK.finditer(text):
                target, _, anchor = m.group(1).partition("#")
                if re.match(r"[a-zA-Z][\w+.-]*:", target):  # a URL
                    continue
                page = p.parent / target if target else p
                if not page.exists():
                    bad.append(f"{p.relative_to(root)}: link ({m.group(1)})")
                elif anchor and page.suffix == ".md" and anchor.lower() not in heading_anchors(text_of(page) or ""):
                    bad.append(f"{p.relative_to(root)}: anchor ({m.group(1)})")
    return bad


def test_no_file_cites_the_external_spec_or_design_notes():
    found = external_citations(tracked_files())
    assert not found, (
        "files cite notes a clone of the repository does not have (cite docs/models.md, "
        "docs/features-and-distance.md or docs/qsm-formats.md instead):\n" + "\n".join(found)
    )


def test_every_docs_page_named_or_linked_exists():
    bad = broken_doc_links(tracked_files())
    assert not bad, "docs pages named or linked that do not exist:\n" + "\n".join(bad)


def test_the_reference_pages_exist_with_their_sections():
    models = (ROOT / "docs" / "models.md").read_text(encoding="utf-8")
    for head in ("## A.", "### A.3 ", "### A.13 ", "## B.", "### B.5 ", "### B.10 ", "## C.", "## D.", "## E."):
        assert head in models, head
    fd = (ROOT / "docs" / "features-and-distance.md").read_text(encoding="utf-8")
    for head in ("## 1.", "### 1.1 ", "## 2.", "## 3.", "## 4.", "### 4.5 ", "## 5.", "## 6.", "## 7."):
        assert head in fd, head
    qf = (ROOT / "docs" / "qsm-formats.md").read_text(encoding="utf-8")
    for head in ("## 0.", "## 5a.", "## 5b.", "## 9.", "## 10.", "## 11."):
        assert head in qf, head


@pytest.mark.parametrize(
    "line, cites",
    [
        ("see shared/spec/ssm-models.md part B", True),
        ("Public names (see ``DESIGN.md``)", True),
        ("the papers in ../shared/papers/", True),
        ('SPEC = ROOT.parent / "shared" / "spec"', True),
        ("samples in ../shared/data/qsm (skipped when absent)", False),
        ('QSM = ROOT.parent / "shared" / "data" / "qsm"', False),
        ("see docs/models.md B.5 step 3", False),
        ("the machine is shared with other jobs", False),
    ],
)
def test_the_checks_can_fail(tmp_path, line, cites):
    f = tmp_path / "planted.py"
    f.write_text(f"# {line}\n", encoding="utf-8")
    assert bool(external_citations([f], tmp_path)) is cites
    page = tmp_path / "page.md"
    page.write_text("[a](missing.md) and docs/nowhere.md and [b](page.md) [c](https://x.org/y.md)\n", encoding="utf-8")
    assert broken_doc_links([page], tmp_path) == ["page.md: docs/nowhere.md", "page.md: link (missing.md)"]


def test_an_anchor_must_name_a_heading(tmp_path):
    page = tmp_path / "page.md"
    page.write_text(
        "# Title\n\n## 4. Real trees: the pine's clones\n\n```\n# not a heading\n```\n## Title\n\n"
        "[a](#4-real-trees-the-pines-clones) [b](page.md#title-1) [c](#not-a-heading) [d](other.md#x)\n",
        encoding="utf-8",
    )
    (tmp_path / "other.md").write_text("# X\n", encoding="utf-8")
    assert broken_doc_links([page], tmp_path) == ["page.md: anchor (#not-a-heading)"]
    (tmp_path / "other.md").write_text("# Y\n", encoding="utf-8")
    assert broken_doc_links([page], tmp_path) == ["page.md: anchor (#not-a-heading)", "page.md: anchor (other.md#x)"]
