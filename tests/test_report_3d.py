"""The interactive 3-D view of report.html (issue 33, item 4): the target beside its clones,
drawn by the page's own script in a real browser (Debian's chromium, headless) from a copied
folder with the network off; the screenshot of the view is not blank and the page logs nothing
to the console. Skipped where chromium is not installed (.ci/run installs it)."""

from __future__ import annotations

import re
import shutil
import subprocess

import numpy as np
import pytest

import bforest_core as bf
from bforest_core.pipeline.clones import clones as grow_clones
from bforest_core.report import write_report
from bforest_core.report.view3d import tree_json, view3d_html
from conftest import hand_tree, toy_config

CHROMIUM = next((shutil.which(n) for n in ("chromium", "chromium-browser") if shutil.which(n)), None)
needs_chromium = pytest.mark.skipif(
    CHROMIUM is None,
    reason="chromium is not installed (Debian: apt-get install "
    "chromium; .ci/run installs it): the 3-D view is not rendered",
)


def _chromium(url: str, *extra: str, height: int = 1000) -> subprocess.CompletedProcess:
    """Headless chromium on ``url`` with every connection refused (no proxy reachable, no name
    resolves): what the page needs must be in it."""
    cmd = [
        CHROMIUM,
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--hide-scrollbars",
        "--no-first-run",
        f"--window-size=1280,{height}",
        "--virtual-time-budget=8000",
        "--enable-logging=stderr",
        "--v=0",
        "--proxy-server=http://127.0.0.1:9",
        "--proxy-bypass-list=<-loopback>",
        "--host-resolver-rules=MAP * ~NOTFOUND",
        *extra,
        url,
    ]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=120)


def _console(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if ":CONSOLE" in line]


def test_tree_json_is_in_mm_from_the_base_and_keeps_the_thickest():
    t = hand_tree()
    d = tree_json(t, "t")
    assert d["n"] == t.n and len(d["s"]) == len(d["e"]) == 3 * t.n and len(d["r"]) == len(d["o"]) == t.n
    assert d["s"][:3] == [0, 0, 0]
    assert np.allclose(np.reshape(d["e"], (-1, 3)), np.rint(1000 * (t.end - t.start[0])))
    assert d["r"] == np.rint(1000 * t.radius).astype(int).tolist() and d["o"] == t.order.tolist()
    few = tree_json(t, "t", max_cylinders=2)
    assert sorted(few["r"], reverse=True) == sorted(np.rint(1000 * np.sort(t.radius)[-2:]).astype(int), reverse=True)
    html = view3d_html([("a</script><b>", t)])
    assert "a<\\/script><b>" in html and "http" not in html  # a label cannot end the script; nothing loaded


@pytest.fixture(scope="module")
def run_with_clones(toy_plugin, tmp_path_factory):
    base = tmp_path_factory.mktemp("view3d")
    bf.fit(bf.load_config(toy_config(base, budget=16)), base / "run", progress=False)
    grow_clones(base / "run", n=4, progress=False)
    write_report(base / "run", figures=False)  # the view does not need the figures (they are tested elsewhere)
    return base / "run"


def test_the_report_holds_the_view_of_the_target_and_its_clones(run_with_clones):
    html = (run_with_clones / "report.html").read_text()
    md = (run_with_clones / "report.md").read_text()
    assert html.count('<canvas id="bf-view3d"') == 1
    labels = re.findall(r'"label":"([^"]*)"', html)
    assert labels == ["target", "clone 0\\nD = " + labels[1].split("D = ")[1], *labels[2:]] and len(labels) == 5
    assert not re.search(r'(src|href)\s*=\s*"(https?:)?//', html)  # nothing from elsewhere
    assert "An interactive 3-D view of target, clone 0, clone 1, clone 2, clone 3" in md


@needs_chromium
def test_the_view_renders_in_headless_chromium_from_a_copied_folder_offline(run_with_clones, tmp_path):
    # the check sees a page's console: a page that logs and throws is caught
    bad = tmp_path / "bad.html"
    bad.write_text('<!DOCTYPE html><html><body><script>throw new Error("bf-boom");</script></body></html>')
    assert any("bf-boom" in line for line in _console(_chromium(bad.as_uri(), "--dump-dom").stderr))

    copied = tmp_path / "copied"  # report.html alone: it needs nothing beside it
    copied.mkdir()
    shutil.copy(run_with_clones / "report.html", copied / "report.html")
    url = (copied / "report.html").as_uri()
    r = _chromium(url, "--dump-dom", height=1000)
    canvas = re.search(r'<canvas id="bf-view3d"[^>]*>', r.stdout)
    assert canvas, r.stderr[-2000:]
    attrs = dict(re.findall(r'([\w-]+)="([^"]*)"', canvas.group(0)))
    total = sum(int(n) for n in re.findall(r'"n":(\d+)', (copied / "report.html").read_text()))
    assert int(attrs["data-drawn"]) == total > 0  # every cylinder of the five trees drawn
    assert _console(r.stderr) == [], _console(r.stderr)
    top, left = int(attrs["data-top"]), int(attrs["data-left"])
    w, h = int(attrs["width"]), int(attrs["height"])  # the canvas in device pixels (= CSS pixels here)
    shot = tmp_path / "shot.png"
    r = _chromium(url, f"--screenshot={shot}", height=top + h + 60)
    assert shot.exists(), r.stderr[-2000:]
    assert _console(r.stderr) == [], _console(r.stderr)
    from PIL import Image

    img = np.asarray(Image.open(shot).convert("RGB"), float)
    view = img[top + 2 : top + h - 2, left + 2 : left + w - 2]
    gray = view.mean(axis=2)
    assert gray.std() > 5.0  # not blank
    ink = np.abs(view - 255).max(axis=2) > 60  # drawn pixels (white is the background)
    coloured = (view.max(axis=2) - view.min(axis=2)) > 60  # branch-order colours, not only text
    assert coloured.mean() > 0.005
    # five trees side by side: five separate groups of columns with coloured pixels
    cols = coloured.any(axis=0)
    groups = np.count_nonzero(np.diff(cols.astype(int)) == 1) + int(cols[0])
    assert groups == 5, groups
    assert ink[-40:].any()  # the labels under the trees
    Image.fromarray(view.astype(np.uint8)).save(tmp_path / "view.png")  # to look at by hand
