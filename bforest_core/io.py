"""Files in and out.

``read_qsm`` and ``write_tree`` dispatch to the registered readers and writers; ``jsonable``,
``json_text`` and ``write_json`` are the one way results become JSON (the run folder's files, the
evaluation log's columns, ``--json`` output, a writer's metadata). ``whole_file`` is how a file is
written all or nothing (a full disk leaves the old file or none, never half of one).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
from pathlib import Path
from typing import TYPE_CHECKING

from .errors import PluginError, QSMFormatError
from .registry import component_class, discover
from .samples import resolve as resolve_sample

if TYPE_CHECKING:
    from .tree import Tree


def _readers():
    reg = discover()
    return [reg.get("qsm_reader", n) for n in reg.names("qsm_reader")]


def qsm_suffixes() -> list[str]:
    """Return the file suffixes the installed QSM readers take.

    Returns
    -------
    list of str
        Lower-case suffixes with the dot (``".mat"``, ``".txt"``, ...), sorted.
    """
    return sorted({s for c in _readers() for s in c.suffixes})


def _check_regular_file(path: Path) -> None:
    """Check that a QSM path is a regular file.

    Not missing, a folder, a FIFO (reading one waits for a writer for ever), a device or a loop
    of symbolic links (each named as such).
    """
    import errno
    import os
    import stat

    try:
        mode = os.stat(path).st_mode
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise QSMFormatError(path, "symbolic link loop (the link points back to itself)") from None
        if os.path.islink(path):
            raise QSMFormatError(path, "broken symbolic link (its target does not exist)") from None
        if exc.errno == errno.ENOENT:
            raise QSMFormatError(path, "file not found") from None
        raise QSMFormatError(path, f"cannot be read ({exc.strerror})") from None
    if stat.S_ISDIR(mode):
        raise QSMFormatError(path, "is a folder, not a QSM file")
    if not stat.S_ISREG(mode):
        kind = "a FIFO (named pipe)" if stat.S_ISFIFO(mode) else "a socket" if stat.S_ISSOCK(mode) else "a device"
        raise QSMFormatError(path, f"is {kind}, not a regular file")


def read_qsm(path, reader: str | None = None, **options):
    """Read a QSM file into a :class:`~bforest_core.Tree`.

    Parameters
    ----------
    path : str or Path
        The QSM file, or ``sample:NAME`` for a fetched sample tree (:mod:`bforest_core.samples`).
    reader : str, optional
        A registered reader's name; by default the reader is picked from the file's content
        (the suffix only narrows the candidates).
    **options
        Passed to the reader: ``select`` (reconstruction index, list or ``"all"``),
        ``topology`` (``"source"``, ``"subtree"``, ``"thickest"``), ``fragments``
        (``"drop"``/``"error"``), ``drop_degenerate`` (bool), ...

    Returns
    -------
    Tree
        The tree the file holds.

    Raises
    ------
    QSMFormatError
        Naming the file and the problem.
    PluginError
        If no reader is installed or ``reader`` names none.
    """
    path = resolve_sample(path)
    _check_regular_file(path)
    if reader is not None:
        cls = component_class("qsm_reader", reader)
        return cls().read(path, **options)
    suffix = path.suffix.lower()
    readers = sorted(_readers(), key=lambda c: -c.priority)
    if not readers:
        raise PluginError("no QSM reader plugin is installed (see 'bforest plugins')")
    supported = qsm_suffixes()
    cands = [c for c in readers if suffix in c.suffixes]
    if not cands:
        raise QSMFormatError(path, f"unsupported file type '{path.suffix}' (supported: {', '.join(supported)})")
    with open(path, "rb") as fh:
        head = fh.read(4096)
    if not head:
        raise QSMFormatError(path, "file is empty")
    for cls in cands:
        r = cls()
        if r.sniff(path, head):
            return r.read(path, **options)
    raise QSMFormatError(
        path,
        "content matches no known QSM layout (tried readers: "
        + ", ".join(c.name for c in cands)
        + "); pass reader=... to force one",
    )


def read_tree(path, reader: str | None = None, **options) -> Tree:
    """Read one tree: :func:`read_qsm` for a caller that takes one.

    A ``select`` of several reconstructions gives their first.
    """
    tree = read_qsm(path, reader, **options)
    return tree[0] if isinstance(tree, list) else tree


def writer_for(path, format: str | None = None):
    """Return the writer class for ``path`` (by suffix) or ``format``.

    Lets a caller check an output name before it computes the tree.

    Parameters
    ----------
    path : str or Path
        The output file; its suffix picks the writer (the highest ``priority`` among those
        that take it).
    format : str, optional
        A registered writer's name, which takes precedence over the suffix.

    Returns
    -------
    type
        The writer class.

    Raises
    ------
    QSMFormatError
        If no writer takes the suffix (naming the known suffixes).
    PluginError
        If ``format`` names no registered writer.
    """
    path = Path(path)
    reg = discover()
    if format is not None:
        return reg.get("qsm_writer", format)
    suffix = path.suffix.lower()
    cands = [reg.get("qsm_writer", n) for n in reg.names("qsm_writer")]
    cands = [c for c in cands if suffix in c.suffixes]
    if not cands:
        known = sorted({s for n in reg.names("qsm_writer") for s in reg.get("qsm_writer", n).suffixes})
        raise QSMFormatError(path, f"no writer for '{path.suffix}' (known: {', '.join(known) or 'none'})")
    cands.sort(key=lambda c: -c.priority)
    return cands[0]


def write_tree(tree, path, format: str | None = None, **options) -> Path:
    """Write a tree: TreeQSM text (``.txt``), CSV (``.csv``), PLY/OBJ meshes, ...

    The writer is chosen by :func:`writer_for`; missing parent folders are made.

    Parameters
    ----------
    tree : Tree
        The tree.
    path : str or Path
        The output file.
    format : str, optional
        A registered writer's name (by default the suffix picks it).
    **options
        Passed to the writer.

    Returns
    -------
    Path
        The file written.

    Raises
    ------
    QSMFormatError
        If no writer takes the suffix.
    """
    path = Path(path)
    cls = writer_for(path, format)
    path.parent.mkdir(parents=True, exist_ok=True)
    with whole_file(path) as part:
        cls().write(tree, part, **options)
    return path


@contextlib.contextmanager
def whole_file(path):
    """Write a file all or nothing: yield a path of the same name in a temporary folder beside it.

    When the ``with`` block ends normally every file written into that folder (the file, and a
    writer's side files named after it) replaces its namesake beside ``path`` (a rename each,
    the file itself last); when it raises (a full disk, an interrupted command) the folder is
    removed and ``path`` is left as it was. The folder is ``.NAME.tmp``.

    Parameters
    ----------
    path : str or Path
        The file to write.

    Yields
    ------
    Path
        The path to write to.
    """
    import shutil

    path = Path(path)
    folder = path.with_name(f".{path.name}.tmp")
    shutil.rmtree(folder, ignore_errors=True)  # left by a killed command
    folder.mkdir(parents=True)
    try:
        yield folder / path.name
        for f in sorted(folder.iterdir(), key=lambda f: f.name == path.name):  # the file itself last
            os.replace(f, path.with_name(f.name))
    finally:
        shutil.rmtree(folder, ignore_errors=True)


# ------------------------------------------------------------------------------------ JSON
def write_plot(trees, path, names=None, format: str | None = None, **options) -> Path:
    """Write several trees, each at its own place, to one file (a plot mesh or scan).

    Parameters
    ----------
    trees : list of Tree
        The trees, in the plot's coordinates (m).
    path : str or Path
        The output file; its suffix chooses the writer unless ``format`` names one.
    names : list of str, optional
        The trees' names.
    format : str, optional
        A registered writer's name.
    **options
        The writer's options.

    Returns
    -------
    Path
        The path written.

    Raises
    ------
    QSMFormatError
        The format holds one tree, or the trees are none.
    """
    path = Path(path)
    trees = list(trees)
    if not trees:
        raise QSMFormatError(path, "no trees to write")
    names = [f"tree_{i}" for i in range(len(trees))] if names is None else [str(n) for n in names]
    return writer_for(path, format)().write_plot(trees, path, names=names, **options)


def jsonable(obj, *, loose: bool = False, strict: bool = False):
    """Convert ``obj`` to plain JSON values: dicts, lists, text, numbers, booleans and ``None``.

    Numpy scalars become Python numbers, numpy arrays and tuples lists, paths text; dict keys that
    JSON takes (text, numbers, booleans, ``None``) stay, numpy scalar keys become numbers.

    Parameters
    ----------
    obj : object
        The value (nested dicts, lists and tuples of them).
    loose : bool
        Anything else (a free-form optimiser diagnostic, a writer's metadata) becomes its text;
        without it, ``TypeError`` names its type.
    strict : bool
        NaN and infinities become ``None`` (strict JSON readers reject them); without it they stay
        floats (Python's ``json`` writes them as ``NaN``/``Infinity``).

    Returns
    -------
    object
        The plain value; ``json.dumps`` writes it with no ``default``.

    Raises
    ------
    TypeError
        Without ``loose``, for a value or dict key JSON has no form for.
    """
    if obj is None or isinstance(obj, (bool, str)):
        return obj
    if isinstance(obj, float):  # numpy's float64 too: a float subclass
        return None if strict and not math.isfinite(obj) else obj
    if isinstance(obj, int):
        return obj
    if isinstance(obj, dict):
        return {_json_key(k, loose): jsonable(v, loose=loose, strict=strict) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v, loose=loose, strict=strict) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    import numpy as np

    if isinstance(obj, np.generic):
        return jsonable(obj.item(), loose=loose, strict=strict)
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist(), loose=loose, strict=strict)
    if loose:
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def _json_key(k, loose: bool):
    if k is None or isinstance(k, (str, int, float, bool)):
        return k
    import numpy as np

    if isinstance(k, np.generic):
        return k.item()
    if loose:
        return str(k)
    raise TypeError(f"not a JSON key: {type(k).__name__}")


def json_text(
    obj, *, indent: int | None = 2, sort_keys: bool = False, loose: bool = False, strict: bool = False
) -> str:
    """Return ``obj`` as JSON text (:func:`jsonable` with ``loose`` and ``strict``).

    Parameters
    ----------
    obj : object
        The value.
    indent : int or None, optional
        Indentation; ``None`` gives one line (the evaluation log's columns, with ``sort_keys``).
    sort_keys : bool, optional
        Sort the keys of dicts.
    loose : bool, optional
        Write unknown objects as their text (see :func:`jsonable`).
    strict : bool, optional
        For people and other programs (``--json`` output, a study's summary file): NaN and
        infinities as ``null``. Without it non-finite numbers are written as Python's ``json``
        writes them and read back by it (the run folder's own files).

    Returns
    -------
    str
        The JSON text.
    """
    return json.dumps(
        jsonable(obj, loose=loose, strict=strict), indent=indent, sort_keys=sort_keys, allow_nan=not strict
    )


def write_json(path, obj, **options) -> Path:
    """Write :func:`json_text` of ``obj`` to ``path``, all or nothing.

    The text goes through a temporary file beside it (:func:`whole_file`), so a reader never
    sees half a file.

    Parameters
    ----------
    path : str or Path
        The output file.
    obj : object
        The value.
    **options
        As for :func:`json_text`.

    Returns
    -------
    Path
        The file written.
    """
    path = Path(path)
    with whole_file(path) as part:
        part.write_text(json_text(obj, **options), encoding="utf-8")
    return path
