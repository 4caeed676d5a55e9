"""Where a tree came from, for the file that holds it.

The provenance block every writer records (a comment line in PLY, OBJ and XYZ files, the native
CSV's sidecar, a LAS VLR, ``rundata`` of the TreeQSM ``.mat``), and metadata as plain JSON values
(``io.jsonable``: unknown objects as text, NaN as null).
"""

from __future__ import annotations

import json
from importlib.metadata import PackageNotFoundError
from importlib.metadata import version as _version

from .io import jsonable

try:
    __version__ = _version("bayesforest")
except PackageNotFoundError:  # running from a source tree
    __version__ = "0.0.0+local"


def provenance(tree, **extra) -> dict:
    """Return where a tree came from, for the file that holds it.

    Parameters
    ----------
    tree : Tree
        The tree; its ``metadata`` supplies model, parameters, fixed parameters, seed, role,
        run folder and source file when it has them.
    **extra
        Further entries (e.g. scan settings).

    Returns
    -------
    dict
        The Bayes Forest version and the entries above, as plain JSON values.
    """
    md = tree.metadata
    out = {"software": f"Bayes Forest {__version__}"}
    for k in ("model", "params", "fixed", "seed", "role", "run", "source"):
        if md.get(k) is not None:
            out[k] = jsonable(md[k], loose=True, strict=True)
    out.update(jsonable(extra, loose=True, strict=True))
    return out


def provenance_line(tree, **extra) -> str:
    """Return :func:`provenance` as one line of compact JSON (for PLY, OBJ and XYZ comments).

    Parameters
    ----------
    tree : Tree
        The tree.
    **extra
        Further entries, as for :func:`provenance`.

    Returns
    -------
    str
        ``"provenance "`` followed by the JSON object.
    """
    return "provenance " + json.dumps(provenance(tree, **extra), separators=(",", ":"), allow_nan=False)
