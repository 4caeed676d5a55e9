"""Synthetic stands: the clones of a stand's trees, each at its tree's place (``bforest stand``).

Realisation ``r`` puts one clone of every fitted tree at that tree's stem base (from the QSMs'
shared frame, or from the stem map): a plot with the real plot's trees where they stand, each a
morphological clone of its tree. No clone stands twice while the realisations are at most the
clones (:func:`~.seeds.realisation_clones`). Each realisation is written as

- ``plot.ply`` (or ``plot.obj``): one cylinder mesh of the plot,
- ``plot.las``: a synthetic laser scan of the plot (points on the bark, ``stand.scan_density``
  per m², the tree of every point in the extra dimension ``tree_id``),
- ``trees.csv``: one row per tree: its place, the clone's file, model, seed and parameters.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np

from ..io import read_qsm, write_plot
from .seeds import realisation_clones
from .store import RunFiles, StandFiles

#: ``trees.csv`` of a realisation
TREE_COLUMNS = ("tree_id", "tree", "x", "y", "z", "clone", "file", "model", "seed", "params")


def _placed(tree, xyz) -> object:
    """``tree`` moved so that its stem base stands at ``xyz``."""
    return tree.translated(np.asarray(xyz, float) - tree.start[0])


def stand_clones(stand_dir, jobs: list[dict], rows: dict) -> list[dict]:
    """The fitted trees of a stand that have clones: name, place, clone rows, model, params."""
    out = []
    for j in jobs:
        row = rows.get(j["name"])
        if not row or row.get("status") != "ok":
            continue
        run = RunFiles(j["run_dir"])
        table = run.clones_dir() / RunFiles.CLONE_TABLE
        if not table.exists():
            continue
        with open(table, newline="", encoding="utf-8") as fh:
            grown = [r for r in csv.DictReader(fh) if r["status"] == "ok" and r["file"]]
        if grown:
            best = run.read_best()
            out.append({**j, "clones": grown, "model": row.get("model", ""), "params": best["params"]})
    return sorted(out, key=lambda t: t["index"])


def grow_stand(stand_dir, settings, jobs: list[dict], rows: dict) -> list[Path]:
    """Write the stand's ``settings.realisations`` synthetic stands (see the module text); a
    realisation already written is kept. Returns their folders."""
    files = StandFiles(stand_dir)
    trees = stand_clones(stand_dir, jobs, rows)
    if not trees:
        return []
    seed = int(settings.seed or 0)
    picks = [realisation_clones(seed, t["index"], len(t["clones"]), settings.realisations) for t in trees]
    out = []
    for r in range(settings.realisations):
        folder = files.realisation_dir(r)
        table = folder / "trees.csv"
        out.append(folder)
        if table.exists():  # written last: the realisation is complete
            continue
        folder.mkdir(parents=True, exist_ok=True)
        chosen = [t["clones"][p[r]] for t, p in zip(trees, picks)]
        placed = []
        for t, c in zip(trees, chosen):
            clone = read_qsm(RunFiles(t["run_dir"]).clones_dir() / c["file"])
            placed.append(_placed(clone, (t["x"], t["y"], t["z"])))
        names = [t["name"] for t in trees]
        write_plot(placed, folder / f"plot.{settings.mesh}", names=names)
        write_plot(placed, folder / "plot.las", names=names, density=settings.scan_density, seed=seed * 1000 + r)
        tmp = table.with_name("trees.csv.tmp")
        with open(tmp, "w", newline="", encoding="utf-8") as fh:
            w = csv.writer(fh)
            w.writerow(TREE_COLUMNS)
            for i, (t, c) in enumerate(zip(trees, chosen)):
                clone_file = RunFiles(t["run_dir"]).clones_dir() / c["file"]
                w.writerow(
                    [
                        i,
                        t["name"],
                        repr(float(t["x"])),
                        repr(float(t["y"])),
                        repr(float(t["z"])),
                        c["index"],
                        str(clone_file.relative_to(Path(stand_dir))),
                        t["model"],
                        c["seed"],
                        json.dumps(t["params"], sort_keys=True),
                    ]
                )
        tmp.replace(table)
    return out


def real_plot(jobs: list[dict]) -> list[tuple[str, object]]:
    """The stand's real trees (their QSMs) at their places: (name, tree) each."""
    out = []
    for j in sorted(jobs, key=lambda j: j["index"]):
        tree = read_qsm(j["file"])
        out.append((j["name"], _placed(tree, (j["x"], j["y"], j["z"]))))
    return out


def realisation_trees(stand_dir, r: int) -> list[tuple[str, object]]:
    """The trees of synthetic stand ``r``, read back from its ``trees.csv``: (name, tree) each."""
    folder = StandFiles(stand_dir).realisation_dir(r)
    with open(folder / "trees.csv", newline="", encoding="utf-8") as fh:
        rows = list(csv.DictReader(fh))
    return [
        (
            row["tree"],
            _placed(read_qsm(Path(stand_dir) / row["file"]), (float(row["x"]), float(row["y"]), float(row["z"]))),
        )
        for row in rows
    ]
