"""An interactive 3-D view of the target beside its clones, for ``report.html``.

The trees go into the page as JSON (cylinder start and end points in mm, radius, branch order)
with a few hundred lines of plain JavaScript that draw them on a 2-D canvas: an orthographic
projection of every cylinder as a line segment as wide as the cylinder (at least a hair), painted
far to near, coloured by branch order as in the figures. Drag (mouse, pen or touch) turns every
tree about its own vertical axis and tilts the view; the trees stand side by side on one scale.
Nothing is loaded from elsewhere (no library, no CDN, no font), so the page works offline from a
copied folder. When it has drawn, the canvas carries ``data-drawn="<segments drawn>"``, and once
the page is laid out its place on it (``data-top``, ``data-left``, CSS pixels).
"""

from __future__ import annotations

import html as _html
import json
from collections.abc import Sequence

import numpy as np

from .canvas import ORDER_COLORS

#: most cylinders drawn per tree (the thinnest beyond it are left out, and the view says so)
MAX_CYLINDERS = 20000


def tree_json(tree, label: str, max_cylinders: int = MAX_CYLINDERS) -> dict:
    """One tree for the viewer: ``label``, ``n`` (cylinders of the tree), and flat integer lists
    in mm relative to the tree's base (the root cylinder's start): ``s`` starts, ``e`` ends
    (x, y, z each), ``r`` radii, and ``o`` branch orders; the thickest ``max_cylinders``."""
    start, end = np.asarray(tree.start, float), np.asarray(tree.end, float)
    radius, order = np.asarray(tree.radius, float), np.asarray(tree.order, int)
    keep = np.arange(tree.n)
    if tree.n > max_cylinders:
        keep = np.sort(np.argsort(-radius, kind="stable")[:max_cylinders])
    base = start[0] if tree.n else np.zeros(3)
    mm = lambda a: np.rint(1000.0 * a).astype(np.int64).ravel().tolist()  # noqa: E731
    return {
        "label": label,
        "n": int(tree.n),
        "s": mm(start[keep] - base),
        "e": mm(end[keep] - base),
        "r": mm(radius[keep]),
        "o": order[keep].tolist(),
    }


def view3d_html(trees: Sequence[tuple[str, object]], element_id: str = "bf-view3d", height: int = 560) -> str:
    """The viewer as one self-contained HTML block (a canvas, its data and its script) for
    ``trees``, a list of ``(label, tree)``: the first is drawn first (the target)."""
    data = {"trees": [tree_json(t, label) for label, t in trees], "colors": list(ORDER_COLORS)}
    # "</" cannot end the script early inside a JSON string
    payload = json.dumps(data, separators=(",", ":")).replace("</", "<\\/")
    eid = _html.escape(element_id)
    return (
        f'<div class="bf-view3d"><canvas id="{eid}" style="width:100%;height:{int(height)}px;'
        'border:1px solid #ddd;touch-action:none;cursor:grab;background:#fff"></canvas>'
        '<div style="font-size:0.9em;color:#555">Drag to turn the trees and tilt the view; double-click '
        "resets it. Colour: branch order; line width: cylinder diameter; one scale for all trees.</div></div>\n"
        f'<script type="application/json" id="{eid}-data">{payload}</script>\n'
        f"<script>\n{_SCRIPT.replace('__ID__', json.dumps(element_id))}\n</script>"
    )


_SCRIPT = r"""
(function () {
  "use strict";
  var id = __ID__;
  var canvas = document.getElementById(id);
  var data = JSON.parse(document.getElementById(id + "-data").textContent);
  var trees = data.trees, colors = data.colors;
  var yaw = 0.6, pitch = 0.15;          // radians: about the vertical axis, and the tilt
  var YAW0 = yaw, PITCH0 = pitch;

  // extent of every tree (m) around its base, for the layout and the common scale
  var slots = [], totalW = 0, maxH = 0, maxZ = 0, minZ = 0;
  trees.forEach(function (t) {
    var rmax = 0.01, zmin = 0, zmax = 0.01;
    for (var k = 0; k < t.s.length; k += 3) {
      [t.s, t.e].forEach(function (a) {
        var x = a[k] / 1000, y = a[k + 1] / 1000, z = a[k + 2] / 1000;
        rmax = Math.max(rmax, Math.sqrt(x * x + y * y));
        zmin = Math.min(zmin, z); zmax = Math.max(zmax, z);
      });
    }
    slots.push({ half: rmax * 1.1, zmin: zmin, zmax: zmax });
    maxZ = Math.max(maxZ, zmax); minZ = Math.min(minZ, zmin);
  });
  maxH = Math.max(maxZ - minZ, 0.01);
  slots.forEach(function (slot) {       // a slender tree still gets room for its label
    slot.half = Math.max(slot.half, 0.2 * maxH);
    totalW += 2 * slot.half;
  });
  var order = [];                       // per tree: segment indices, painted far to near
  trees.forEach(function (t) { order.push(new Array(t.r.length)); });

  function fitHeight() {                 // as tall as the row of trees needs, 300-700 px
    var w = canvas.clientWidth || 800;
    var h = Math.round(Math.min(700, Math.max(300, (w - 56) * maxH / Math.max(totalW, 0.01) + 62)));
    canvas.style.height = h + "px";
  }

  function draw() {
    var dpr = window.devicePixelRatio || 1;
    var cssW = canvas.clientWidth || 800, cssH = canvas.clientHeight || 500;
    if (canvas.width !== Math.round(cssW * dpr) || canvas.height !== Math.round(cssH * dpr)) {
      canvas.width = Math.round(cssW * dpr); canvas.height = Math.round(cssH * dpr);
    }
    var ctx = canvas.getContext("2d");
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    ctx.fillStyle = "#ffffff";
    ctx.fillRect(0, 0, cssW, cssH);
    var pad = 28, labelH = 34;
    var scale = Math.min((cssW - 2 * pad) / Math.max(totalW, 0.01), (cssH - pad - labelH) / maxH);
    var cy = Math.cos(yaw), sy = Math.sin(yaw), cp = Math.cos(pitch), sp = Math.sin(pitch);
    var ground = cssH - labelH - 8 + minZ * scale * cp;  // screen y of z = 0: the trees stand on one line
    var x0 = (cssW - totalW * scale) / 2, drawn = 0;
    ctx.lineCap = "round";
    trees.forEach(function (t, i) {
      var slot = slots[i], cx = x0 + slot.half * scale, n = t.r.length;
      var sx = new Float64Array(2 * n), syy = new Float64Array(2 * n), depth = new Float64Array(n);
      for (var j = 0; j < n; j++) {
        var k = 3 * j;
        for (var end = 0; end < 2; end++) {
          var a = end ? t.e : t.s;
          var x = a[k] / 1000, y = a[k + 1] / 1000, z = a[k + 2] / 1000;
          var xr = cy * x - sy * y, yr = sy * x + cy * y;     // turned about the vertical
          var zs = cp * z - sp * yr, ds = sp * z + cp * yr;   // tilted towards the viewer
          sx[2 * j + end] = cx + xr * scale;
          syy[2 * j + end] = ground - zs * scale;
          if (end) { depth[j] += ds; } else { depth[j] = ds; }
        }
      }
      var idx = order[i];
      for (var m = 0; m < n; m++) { idx[m] = m; }
      idx.sort(function (p, q) { return depth[q] - depth[p]; });  // far (large depth) first
      for (var q = 0; q < n; q++) {
        var s = idx[q];
        ctx.strokeStyle = colors[Math.min(t.o[s], colors.length - 1)];
        ctx.lineWidth = Math.max(0.6, 2 * t.r[s] / 1000 * scale);
        ctx.beginPath();
        ctx.moveTo(sx[2 * s], syy[2 * s]);
        ctx.lineTo(sx[2 * s + 1], syy[2 * s + 1]);
        ctx.stroke();
        drawn++;
      }
      ctx.fillStyle = "#222222";
      ctx.font = "13px sans-serif";
      ctx.textAlign = "center";
      var lines = String(t.label).split("\n");
      if (t.n > n) { lines.push(n + " of " + t.n + " cylinders"); }
      lines.forEach(function (txt, l) { ctx.fillText(txt, cx, cssH - labelH + 12 + 14 * l); });
      x0 += 2 * slot.half * scale;
    });
    // a scale bar of 1 m (or 10 cm for small trees)
    var bar = maxH > 2 ? 1 : 0.1;
    ctx.strokeStyle = "#444444"; ctx.lineWidth = 2; ctx.lineCap = "butt";
    ctx.beginPath(); ctx.moveTo(10, cssH - 8); ctx.lineTo(10 + bar * scale, cssH - 8); ctx.stroke();
    ctx.fillStyle = "#444444"; ctx.font = "11px sans-serif"; ctx.textAlign = "left";
    ctx.fillText(bar === 1 ? "1 m" : "10 cm", 14 + bar * scale, cssH - 4);
    canvas.setAttribute("data-drawn", String(drawn));
  }

  var pending = false;
  function redraw() {
    if (pending) { return; }
    pending = true;
    window.requestAnimationFrame(function () { pending = false; draw(); });
  }
  var dragging = false, lastX = 0, lastY = 0;
  canvas.addEventListener("pointerdown", function (ev) {
    dragging = true; lastX = ev.clientX; lastY = ev.clientY;
    canvas.style.cursor = "grabbing";
    if (canvas.setPointerCapture) { canvas.setPointerCapture(ev.pointerId); }
  });
  canvas.addEventListener("pointermove", function (ev) {
    if (!dragging) { return; }
    yaw += (ev.clientX - lastX) * 0.01;
    pitch = Math.max(-1.5, Math.min(1.5, pitch + (ev.clientY - lastY) * 0.01));
    lastX = ev.clientX; lastY = ev.clientY;
    redraw();
  });
  function stop() { dragging = false; canvas.style.cursor = "grab"; }
  canvas.addEventListener("pointerup", stop);
  canvas.addEventListener("pointercancel", stop);
  canvas.addEventListener("dblclick", function () { yaw = YAW0; pitch = PITCH0; redraw(); });
  window.addEventListener("resize", function () { fitHeight(); redraw(); });
  fitHeight();
  draw();
  window.addEventListener("load", function () {  // where the view is on the laid-out page (for tests)
    var box = canvas.getBoundingClientRect();
    canvas.setAttribute("data-top", String(Math.round(box.top + window.scrollY)));
    canvas.setAttribute("data-left", String(Math.round(box.left + window.scrollX)));
  });
})();
"""
