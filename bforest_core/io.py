"""``read_qsm`` and ``write_tree``: dispatch to the registered readers and writers."""

from __future__ import annotations

from pathlib import Path

from .errors import PluginError, QSMFormatError
from .registry import component_class, discover


def _readers():
    reg = discover()
    return [reg.get("qsm_reader", n) for n in reg.names("qsm_reader")]


def _check_regular_file(path: Path) -> None:
    """A QSM path must be a regular file: not missing, a folder, a FIFO (reading one waits for a
    writer for ever), a device or a loop of symbolic links (each named as such)."""
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
    reader : str, optional
        A registered reader's name; by default the reader is picked from the file's content
        (the suffix only narrows the candidates).
    **options
        Passed to the reader: ``select`` (reconstruction index, list or ``"all"``),
        ``topology`` (``"source"``, ``"subtree"``, ``"thickest"``), ``fragments``
        (``"drop"``/``"error"``), ``drop_degenerate`` (bool), ...

    Raises
    ------
    QSMFormatError
        Naming the file and the problem.
    """
    path = Path(path)
    _check_regular_file(path)
    if reader is not None:
        cls = component_class("qsm_reader", reader)
        return cls().read(path, **options)
    suffix = path.suffix.lower()
    readers = sorted(_readers(), key=lambda c: -c.priority)
    if not readers:
        raise PluginError("no QSM reader plugin is installed (see 'bforest plugins')")
    supported = sorted({s for c in readers for s in c.suffixes})
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


def writer_for(path, format: str | None = None):
    """The writer class for ``path`` (by suffix) or ``format`` (a registered writer's name);
    raises ``QSMFormatError`` naming the known suffixes. Lets a caller check an output name before
    it computes the tree."""
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
    """Write a tree: TreeQSM text (``.txt``), CSV (``.csv``), PLY/OBJ meshes, by suffix or
    ``format`` (a registered writer's name)."""
    path = Path(path)
    cls = writer_for(path, format)
    path.parent.mkdir(parents=True, exist_ok=True)
    return cls().write(tree, path, **options)
