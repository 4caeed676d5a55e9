"""Numeric text tables of cylinders, both ways.

Vectorised parsing with line-precise errors (the text and CSV readers), sniffing of binary
content, and the assembly of a tree's columns into formatted rows (the text and CSV writers).

Parsing is vectorised: the field count of every line comes from byte masks (so a ragged line is
reported by its number), the numbers from one ``np.loadtxt`` call. Writing is one ``%`` formatting
of a repeated row template over the flattened table (no Python loop over cylinders).
"""

from __future__ import annotations

import io
import warnings
from pathlib import Path
from typing import Optional

import numpy as np

from .errors import QSMFormatError

HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"
_SEP_TABLE = bytes.maketrans(b",\r\x0b\x0c", b"    ")


# ------------------------------------------------------------------------------------------
# what a file holds
# ------------------------------------------------------------------------------------------


def mat_kind(head: bytes) -> Optional[str]:
    """Tell the MAT-file version from the first bytes of a file.

    Parameters
    ----------
    head : bytes
        The first bytes of the file (at least 520 to see an HDF5 user block).

    Returns
    -------
    str or None
        ``"v5"``, ``"hdf5"`` (MAT v7.3 or any HDF5 file) or ``None`` for neither.
    """
    if head[:8] == HDF5_MAGIC or head[512:520] == HDF5_MAGIC:
        return "hdf5"
    if len(head) >= 128 and head[126:128] in (b"IM", b"MI"):
        ver = head[124:126]
        return "hdf5" if ver in (b"\x00\x02", b"\x02\x00") else "v5"
    if head.startswith(b"MATLAB 7.3"):
        return "hdf5"
    if head.startswith(b"MATLAB 5.0"):
        return "v5"
    return None


def read_bytes(path: Path) -> bytes:
    """Return the whole content of a file.

    Parameters
    ----------
    path : Path
        The file.

    Returns
    -------
    bytes
        Its content.

    Raises
    ------
    OSError
        If the file cannot be opened or read.
    """
    with open(path, "rb") as fh:
        return fh.read()


def looks_binary(head: bytes) -> Optional[str]:
    """Tell whether the start of a file is binary rather than text.

    Parameters
    ----------
    head : bytes
        The first bytes of the file (up to 4096 are examined for NUL bytes).

    Returns
    -------
    str or None
        A message saying what the content looks like (a MAT-file, binary data), or ``None``
        for text.
    """
    if mat_kind(head) is not None:  # MAT v5, or any HDF5 file (MAT v7.3 is HDF5)
        return "content looks like a MAT-file, not text"
    if b"\x00" in head[:4096]:
        return "content looks like binary data, not text"
    return None


# ------------------------------------------------------------------------------------------
# reading: vectorised table parsing
# ------------------------------------------------------------------------------------------


def split_lines_head(data: bytes, k: int):
    """Split the first ``k`` lines off ``data``.

    Parameters
    ----------
    data : bytes
        The file content.
    k : int
        Number of lines.

    Returns
    -------
    lines : list of str
        Up to ``k`` lines, decoded as Latin-1, without CR/LF.
    offset : int
        Byte offset just after them.
    """
    lines = []
    pos = 0
    for _ in range(k):
        j = data.find(b"\n", pos)
        if j < 0:
            lines.append(data[pos:].decode("latin-1").rstrip("\r"))
            pos = len(data)
            break
        lines.append(data[pos:j].decode("latin-1").rstrip("\r"))
        pos = j + 1
    return lines, pos


def field_counts(body: bytes):
    """Count the fields on every non-blank line of ``body``.

    Fields are separated by whitespace/control bytes and commas.

    Parameters
    ----------
    body : bytes
        The table's lines.

    Returns
    -------
    counts : ndarray of int64
        Number of fields of each non-blank line.
    line_index : ndarray of int64
        0-based index of each of those lines in ``body``.
    """
    arr = np.frombuffer(body, dtype=np.uint8)
    if arr.size == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    sep = (arr <= 32) | (arr == 44)
    starts = ~sep
    starts[1:] &= sep[:-1]
    tok = np.flatnonzero(starts)
    nl = np.flatnonzero(arr == 10)
    counts = np.bincount(np.searchsorted(nl, tok), minlength=nl.size + 1)
    lines = np.flatnonzero(counts)
    return counts[lines], lines


def first_line_fields(body: bytes) -> int:
    """Count the fields on the first non-blank line of ``body`` (0 if the first 64 KiB have none).

    Parameters
    ----------
    body : bytes
        The table's lines.

    Returns
    -------
    int
        Number of whitespace/comma separated fields.
    """
    for line in body[: 1 << 16].split(b"\n"):
        k = len(line.translate(_SEP_TABLE).split())
        if k:
            return k
    return 0


def _ragged(path, body: bytes, first_line: int, k: int, what: str):
    """Error path: report the first line whose field count is not ``k``."""
    counts, lines = field_counts(body)
    bad = np.flatnonzero(counts != k)
    if bad.size:
        i = int(bad[0])
        more = f" (and {bad.size - 1} more lines)" if bad.size > 1 else ""
        raise QSMFormatError(
            path,
            f"line {int(lines[i]) + first_line}: {int(counts[i])} {what}, expected {k}{more}",
            (lines[bad[:10]] + first_line).tolist(),
        )


def parse_table(path, body: bytes, first_line: int, expected: Optional[int], what: str = "fields"):
    """Parse whitespace/comma separated numbers with one ``np.loadtxt`` call.

    The fast path trusts ``np.loadtxt`` (which refuses ragged rows and bad numbers); only when it
    fails are the lines examined, to report the first ragged line or the first field that is
    not a number with its file line.

    Parameters
    ----------
    path : str or path-like
        The file (for messages).
    body : bytes
        The data part of the file.
    first_line : int
        1-based line number of the first line of ``body`` (for messages).
    expected : int or None
        Required fields per line; ``None`` takes the first line's count.
    what : str, optional
        What the fields are called in messages.

    Returns
    -------
    values : (m, k) float64
        The numbers, one row per non-blank line.

    Raises
    ------
    QSMFormatError
        For a table with no cylinders, a ragged line or a field that is not a number (naming
        its file line).
    """
    k = first_line_fields(body) if expected is None else int(expected)
    if k == 0:
        raise QSMFormatError(path, "file contains no cylinders")
    if b"," in body or b"\r" in body or b"\x0b" in body or b"\x0c" in body:
        body = body.translate(_SEP_TABLE)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            values = np.loadtxt(io.BytesIO(body), dtype=np.float64, comments=None, ndmin=2, encoding="latin1")
    except Exception:
        _ragged(path, body, first_line, k, what)
        _locate_bad_token(path, body.decode("latin-1"), first_line)
        raise QSMFormatError(path, "could not read the numbers of the table") from None
    if values.shape[0] == 0:
        raise QSMFormatError(path, "file contains no cylinders")
    if values.shape[1] != k:
        _ragged(path, body, first_line, k, what)
        raise QSMFormatError(path, f"{values.shape[1]} {what} per line, expected {k}")
    return values


def _locate_bad_token(path, text: str, first_line: int) -> None:
    """Error path only: find the first field that is not a number and raise."""
    for j, line in enumerate(text.split("\n")):
        for c, tok in enumerate(line.split()):
            try:
                float(tok)
            except ValueError:
                shown = tok if len(tok) <= 40 else tok[:37] + "..."
                raise QSMFormatError(
                    path, f"line {j + first_line}, field {c + 1}: cannot read {shown!r} as a number", [j + first_line]
                ) from None


# ------------------------------------------------------------------------------------------
# writing: a tree's columns as formatted rows
# ------------------------------------------------------------------------------------------


def format_rows(values: np.ndarray, formats: list[str], sep: str = "\t") -> str:
    """Format the rows of a numeric table.

    Parameters
    ----------
    values : ndarray, shape (n, k)
        The table.
    formats : list of str
        One printf format per column.
    sep : str, optional
        Field separator.

    Returns
    -------
    str
        One LF-terminated line per row (empty for no rows).
    """
    n = values.shape[0]
    if n == 0:
        return ""
    row = sep.join(formats) + "\n"
    return (row * n) % tuple(values.ravel().tolist())


def format_columns(columns, sep: str = "\t") -> str:
    """Assemble the rows of a table from per-cylinder columns (what every table writer writes).

    Parameters
    ----------
    columns : list of (values, format)
        ``values`` of shape (n,) or (n, k) (start points, axes: a k-wide column takes its printf
        ``format`` k times), any numeric dtype (written through float64, exact for ids below
        2**53).
    sep : str
        Field separator.

    Returns
    -------
    str
        One LF-terminated line per cylinder.
    """
    n = np.asarray(columns[0][0]).shape[0]
    if n == 0:  # a scan with no points
        return ""
    blocks, formats = [], []
    for values, fmt in columns:
        v = np.asarray(values, dtype=np.float64).reshape(n, -1)
        blocks.append(v)
        formats += [fmt] * v.shape[1]
    return format_rows(np.hstack(blocks), formats, sep)
