"""Where a tree came from, for the file that holds it: the provenance block every writer records
(a comment line in PLY, OBJ and XYZ files, the native CSV's sidecar, a LAS VLR, ``rundata`` of the
TreeQSM ``.mat``), and metadata as plain JSON values."""

from __future__ import annotations

import json
import math
from importlib.metadata import PackageNotFoundError
from importlib.metadata import version as _version
from pathlib import Path

import numpy as np

try:
    __version__ = _version("bayesforest")
except PackageNotFoundError:  # running from a source tree
    __version__ = "0.0.0+local"


def jsonable(obj, depth: int = 0):
    """Metadata as plain JSON values (numpy scalars/arrays converted, unknown objects as str)."""
    if depth > 8:
        return str(obj)
    if obj is None or isinstance(obj, (bool, int, str)):
        return obj
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else str(obj)
    if isinstance(obj, np.generic):
        return jsonable(obj.item(), depth + 1)
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist(), depth + 1)
    if isinstance(obj, dict):
        return {str(k): jsonable(v, depth + 1) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v, depth + 1) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    return str(obj)


def provenance(tree, **extra) -> dict:
    """Where a tree came from, for the file that holds it: the Bayes Forest version and, when the
    tree's metadata has them, model, parameters, fixed parameters, seed, role, run folder and
    source file (``extra`` adds e.g. scan settings). JSON-ready."""
    md = tree.metadata
    out = {"software": f"Bayes Forest {__version__}"}
    for k in ("model", "params", "fixed", "seed", "role", "run", "source"):
        if md.get(k) is not None:
            out[k] = jsonable(md[k])
    out.update(jsonable(extra))
    return out


def provenance_line(tree, **extra) -> str:
    """:func:`provenance` as one line of compact JSON (for PLY, OBJ and XYZ comments)."""
    return "provenance " + json.dumps(provenance(tree, **extra), separators=(",", ":"), allow_nan=False)
