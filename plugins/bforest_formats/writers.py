"""Writers for ``bf.write_tree`` of the formats that are not TreeQSM's (docs/qsm-formats.md §9): the
native CSV + JSON sidecar, PLY and OBJ cylinder meshes.

Tables are assembled by :func:`bforest_core.tables.format_columns` (no Python loop over cylinders).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field

from bforest_core.cylinders import resolve_options
from bforest_core.interfaces import ComponentSettings, QSMWriter
from bforest_core.io import jsonable
from bforest_core.provenance import provenance, provenance_line
from bforest_core.tables import format_columns, format_rows

from .csv_readers import NATIVE_COLUMNS

CSV_FORMAT_VERSION = 1


# ------------------------------------------------------------------------------------------
# native CSV + JSON sidecar
# ------------------------------------------------------------------------------------------


class CSVSettings(ComponentSettings):
    #: write ``<name>.json`` beside the CSV
    sidecar: bool = True


class CSVWriter(QSMWriter):
    """Native CSV (docs/qsm-formats.md §9): named columns, 0-based ids, -1 = none, floats at ``repr``
    precision (``%.17g``), plus 1-D numeric extras as further columns and, for a tree under a
    non-source topology, its ``source_extension``; a JSON sidecar keeps format version, units,
    topology rule, source, model, parameters and seed, and the ``provenance`` the other formats
    write as a comment (with the Bayes Forest version). The CSV itself has no comment line, so
    any CSV reader (pandas, R's ``read.csv``) takes its first line as the header. Read back it
    gives the same tree."""

    name = "bforest-csv"
    summary = "Bayes Forest native cylinder CSV with a JSON sidecar"
    suffixes = (".csv",)
    Settings = CSVSettings
    priority = 10

    def write(self, tree, path, **options) -> Path:
        o = resolve_options(self, options)
        path = Path(path)
        n = tree.n
        ids = [np.arange(n), tree.parent, tree.extension, tree.branch, tree.order, tree.position_in_branch, tree.added]
        geometry = [tree.start, tree.axis, tree.length, tree.radius, tree.end]
        cols = [(c, "%d") for c in ids] + [(c, "%.17g") for c in geometry]
        names = list(NATIVE_COLUMNS)
        src = tree.extras.get("_source_extension")
        if tree.topology != "source" and src is not None and np.shape(src) == (n,):
            cols.append((src, "%d"))
            names.append("source_extension")
        for k, v in tree.extras.items():
            v = np.asarray(v)
            if k.startswith("_") or k in names or v.shape != (n,) or v.dtype.kind not in "iufb":
                continue
            if "," in k or "\n" in k:
                continue
            cols.append((v, "%.17g"))
            names.append(k)
        with open(path, "w", encoding="utf-8", newline="\n") as fh:
            fh.write(",".join(names) + "\n")
            fh.write(format_columns(cols, sep=","))
        if o.sidecar:
            md = dict(tree.metadata)
            side = {
                "format": "bforest-csv",
                "format_version": CSV_FORMAT_VERSION,
                "units": "m",
                "topology": tree.topology,
                "source": md.get("source"),
                "model": md.get("model"),
                "params": md.get("params"),
                "seed": md.get("seed"),
                "provenance": provenance(tree),
                "metadata": jsonable({k: v for k, v in md.items() if k not in ("topology",)}, loose=True, strict=True),
            }
            path.with_suffix(".json").write_text(json.dumps(side, indent=2, allow_nan=False), encoding="utf-8")
        return path


# ------------------------------------------------------------------------------------------
# meshes
# ------------------------------------------------------------------------------------------


class MeshSettings(ComponentSettings):
    #: sides of each prism (>= 3)
    sides: int = Field(default=12, ge=3, le=1024)
    #: close both ends of every cylinder
    caps: bool = True
    #: per-vertex colour
    color_by: Literal["order", "branch", "radius", "none"] = "order"
    #: thinner cylinders are drawn with this radius (m)
    min_radius: float = Field(default=0.0, ge=0.0)
    #: move the tree so that the base (root start point) is at the origin
    translate_to_base: bool = False


def cylinder_mesh(tree, sides: int = 12, caps: bool = True, min_radius: float = 0.0, translate_to_base: bool = False):
    """Triangle mesh of every cylinder as a ``sides``-sided prism (docs/qsm-formats.md §9).

    Frame: u = normalise(a x e) with e the coordinate axis least aligned with a, w = a x u; ring
    vertices s + r(u cos t + w sin t), top ring shifted by l a. Faces are counter-clockwise seen
    from outside.

    Returns
    -------
    vertices : (n * 2k, 3) float64
    faces : (F, 3) int64, F = n * (2k + (2(k - 2) if caps))
    face_cyl : (F,) int64
        Cylinder of every face.
    """
    k = int(sides)
    n = tree.n
    a = np.asarray(tree.axis, dtype=np.float64)
    e = np.eye(3)[np.argmin(np.abs(a), axis=1)]
    u = np.cross(a, e)
    u /= np.linalg.norm(u, axis=1)[:, None]
    w = np.cross(a, u)
    t = 2 * np.pi * np.arange(k) / k
    r = np.maximum(tree.radius, min_radius)
    s = tree.start - (tree.start[0] if translate_to_base else 0.0)
    ring = r[:, None, None] * (u[:, None, :] * np.cos(t)[None, :, None] + w[:, None, :] * np.sin(t)[None, :, None])
    bottom = s[:, None, :] + ring
    top = bottom + (tree.length[:, None] * a)[:, None, :]
    vertices = np.concatenate([bottom, top], axis=1).reshape(-1, 3)
    j = np.arange(k)
    j1 = (j + 1) % k
    side = np.concatenate([np.stack([j, j1, k + j1], axis=1), np.stack([j, k + j1, k + j], axis=1)])
    local = [side]
    if caps and k >= 3:
        m = np.arange(1, k - 1)
        local.append(np.stack([np.full(k - 2, k), k + m, k + m + 1], axis=1))  # top, normal +a
        local.append(np.stack([np.zeros(k - 2, dtype=np.int64), m + 1, m], axis=1))  # bottom, -a
    local = np.concatenate(local).astype(np.int64)
    base = (np.arange(n, dtype=np.int64) * 2 * k)[:, None, None]
    faces = (base + local[None, :, :]).reshape(-1, 3)
    face_cyl = np.repeat(np.arange(n, dtype=np.int64), local.shape[0])
    return vertices, faces, face_cyl


ORDER_PALETTE = np.array(
    [
        [120, 72, 38],
        [214, 140, 45],
        [235, 200, 60],
        [120, 190, 70],
        [40, 150, 110],
        [50, 120, 200],
        [120, 80, 200],
        [200, 70, 160],
        [220, 60, 60],
        [140, 140, 140],
    ],
    dtype=np.uint8,
)


def _hsv_to_rgb(h, s, v):
    i = np.floor(h * 6).astype(np.int64) % 6
    f = h * 6 - np.floor(h * 6)
    p, q, t = v * (1 - s), v * (1 - f * s), v * (1 - (1 - f) * s)
    r = np.choose(i, [v, q, p, p, t, v])
    g = np.choose(i, [t, v, v, q, p, p])
    b = np.choose(i, [p, p, t, v, v, q])
    return np.stack([r, g, b], axis=1)


def cylinder_colors(tree, by: str) -> np.ndarray:
    """(n, 3) uint8 colour of every cylinder: by order (fixed palette), branch (golden-ratio
    hues) or radius (log-scaled ramp from brown to green)."""
    n = tree.n
    if by == "order":
        return ORDER_PALETTE[np.asarray(tree.order) % len(ORDER_PALETTE)]
    if by == "branch":
        h = (np.asarray(tree.branch) * 0.618033988749895) % 1.0
        return (_hsv_to_rgb(h, np.full(n, 0.65), np.full(n, 0.9)) * 255).round().astype(np.uint8)
    if by == "radius":
        lr = np.log(np.asarray(tree.radius))
        span = lr.max() - lr.min()
        x = (lr - lr.min()) / span if span > 0 else np.zeros(n)
        lo, hi = np.array([110, 70, 40.0]), np.array([150, 220, 90.0])
        return (hi[None, :] * (1 - x[:, None]) + lo[None, :] * x[:, None]).round().astype(np.uint8)
    return np.full((n, 3), 200, dtype=np.uint8)


class PLYSettings(MeshSettings):
    #: ASCII instead of binary little-endian
    ascii: bool = False


class PLYWriter(QSMWriter):
    """PLY cylinder mesh (binary little-endian by default, ``ascii=True`` option) with per-vertex
    RGB colours (by order, branch or radius). Coordinates are float32, or float64 when they
    exceed 1e4 m in magnitude (georeferenced trees). A plot (:meth:`write_plot`) is one mesh of
    every tree, each tree's provenance a comment."""

    name = "ply"
    summary = "PLY cylinder mesh (binary LE or ASCII, RGB by order/branch/radius)"
    suffixes = (".ply",)
    Settings = PLYSettings
    priority = 10

    def write(self, tree, path, **options) -> Path:
        o = resolve_options(self, options)
        v, f, _ = cylinder_mesh(tree, o.sides, o.caps, o.min_radius, o.translate_to_base)
        col = np.repeat(cylinder_colors(tree, o.color_by), 2 * o.sides, axis=0)
        return _write_ply(Path(path), o, v, f, col, f"{tree.n} cylinders", [provenance_line(tree)])

    def write_plot(self, trees, path, names=None, **options) -> Path:
        o = resolve_options(self, options)
        names = names or [f"tree_{i}" for i in range(len(trees))]
        meshes = [cylinder_mesh(t, o.sides, o.caps, o.min_radius, False) for t in trees]
        starts = np.cumsum([0] + [m[0].shape[0] for m in meshes])[:-1]
        v = np.concatenate([m[0] for m in meshes])
        f = np.concatenate([m[1] + at for m, at in zip(meshes, starts)])
        col = np.concatenate([np.repeat(cylinder_colors(t, o.color_by), 2 * o.sides, axis=0) for t in trees])
        what = f"plot of {len(trees)} trees, {sum(t.n for t in trees)} cylinders"
        return _write_ply(
            Path(path), o, v, f, col, what, [f"tree {n}: {provenance_line(t)}" for n, t in zip(names, trees)]
        )


def _write_ply(path: Path, o, v, f, col, what: str, notes: list[str]) -> Path:
    """One PLY file of a triangle mesh with per-vertex colours (``o``: the mesh options; ``what``
    and ``notes``: the header's comments)."""
    big = np.abs(v).max() > 1e4 if v.size else False
    ftype = "double" if big else "float"
    header = [
        "ply",
        f"format {'ascii' if o.ascii else 'binary_little_endian'} 1.0",
        f"comment Bayes Forest cylinder mesh: {what}, {o.sides} sides, "
        f"caps {'on' if o.caps else 'off'}, colour by {o.color_by}",
        *(f"comment {n}" for n in notes),
        f"element vertex {v.shape[0]}",
        f"property {ftype} x",
        f"property {ftype} y",
        f"property {ftype} z",
        "property uchar red",
        "property uchar green",
        "property uchar blue",
        f"element face {f.shape[0]}",
        "property list uchar int vertex_indices",
        "end_header",
    ]
    with open(path, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        if o.ascii:
            vt = np.hstack([v, col.astype(np.float64)])
            fh.write(format_rows(vt, ["%.9g"] * 3 + ["%d"] * 3, sep=" ").encode("ascii"))
            ft = np.hstack([np.full((f.shape[0], 1), 3.0), f.astype(np.float64)])
            fh.write(format_rows(ft, ["%d"] * 4, sep=" ").encode("ascii"))
        else:
            fdt = "<f8" if big else "<f4"
            vrec = np.empty(
                v.shape[0], dtype=[("x", fdt), ("y", fdt), ("z", fdt), ("r", "u1"), ("g", "u1"), ("b", "u1")]
            )
            vrec["x"], vrec["y"], vrec["z"] = v[:, 0], v[:, 1], v[:, 2]
            vrec["r"], vrec["g"], vrec["b"] = col[:, 0], col[:, 1], col[:, 2]
            frec = np.empty(f.shape[0], dtype=[("n", "u1"), ("i", "<i4", (3,))])
            frec["n"] = 3
            frec["i"] = f
            fh.write(vrec.tobytes())
            fh.write(frec.tobytes())
    return path


class OBJWriter(QSMWriter):
    """Wavefront OBJ cylinder mesh with one group per branch order (``g order_<w>``); a plot
    (:meth:`write_plot`) has one object per tree (``o <name>``), each with its order groups."""

    name = "obj"
    summary = "Wavefront OBJ cylinder mesh (one group per order)"
    suffixes = (".obj",)
    Settings = MeshSettings
    priority = 10

    def write(self, tree, path, **options) -> Path:
        o = resolve_options(self, options)
        with open(path, "w", encoding="ascii", newline="\n") as fh:
            fh.write(f"# Bayes Forest cylinder mesh: {tree.n} cylinders, {o.sides} sides\n")
            fh.write(f"# {provenance_line(tree)}\n")
            _obj_tree(fh, tree, o, o.translate_to_base, 0)
        return Path(path)

    def write_plot(self, trees, path, names=None, **options) -> Path:
        o = resolve_options(self, options)
        names = names or [f"tree_{i}" for i in range(len(trees))]
        with open(path, "w", encoding="ascii", newline="\n") as fh:
            fh.write(f"# Bayes Forest plot mesh: {len(trees)} trees, {o.sides} sides\n")
            at = 0
            for name, tree in zip(names, trees):
                fh.write(f"# tree {name}: {provenance_line(tree)}\no {name}\n")
                at += _obj_tree(fh, tree, o, False, at)
        return Path(path)


def _obj_tree(fh, tree, o, translate: bool, at: int) -> int:
    """Write one tree's vertices and order groups (vertex numbers after ``at``); returns its vertices."""
    v, f, fc = cylinder_mesh(tree, o.sides, o.caps, o.min_radius, translate)
    order = np.asarray(tree.order)[fc]
    srt = np.argsort(order, kind="stable")
    f, order = f[srt], order[srt]
    fh.write(format_rows(v, ["v %.9g", "%.9g", "%.9g"], sep=" "))
    bounds = np.flatnonzero(np.diff(order)) + 1
    for chunk, w in zip(np.split(f + 1 + at, bounds), order[np.concatenate([[0], bounds])] if f.size else []):
        fh.write(f"g order_{int(w)}\n")
        fh.write(format_rows(chunk.astype(np.float64), ["f %d", "%d", "%d"], sep=" "))
    return v.shape[0]
