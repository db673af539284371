"""Numeric tables as text, vectorised: what Python's ``format`` writes, byte for byte, at numpy speed.

A text mesh (OBJ) of a full frame holds ~15 million numbers; formatting them one at a time with
``str.format`` (trimesh's ``array_to_string``) takes ~10 s. :func:`table_text` writes the same bytes
with array operations: every number becomes a row of ASCII digits in a (rows, width) byte matrix
(4-digit chunks from a lookup table), the padding is dropped in one boolean selection.

- integers: ``'{}'.format(n)``;
- floats: ``'{:.Nf}'.format(x)`` — the exact binary value rounded to N decimals, ties to even. The
  scaled value s = |x|·10^N is one float rounding away from the exact product, so it is rounded here
  (floor, then up when its fraction exceeds ½) wherever that fraction is farther from ½ than two units
  in the last place of the column's largest s; the few numbers closer to a tie, beyond 2^52 after
  scaling, or not finite (``nan``, ``inf``) are formatted by Python itself. The sign is the float's sign bit
  (``-0.00000000`` for −0.0 and for negatives that round to zero, as Python writes them).
"""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import torch
from numpy.typing import NDArray

__all__ = ["table_text"]

#: '0000' … '9999', each 4 ASCII bytes read as one uint32 (10000,) (a gather of 4 bytes at once).
_CHUNKS = np.frombuffer("".join(f"{i:04d}" for i in range(10_000)).encode(), dtype=np.uint32)
#: Rows formatted at a time (their byte matrices stay in cache; blocks go to torch's threads).
_CHUNK_ROWS = 1 << 15
#: Below this, |x|·10^N and its floor are exact integers in float64.
_EXACT = float(2**52)


def _digits(n: NDArray[np.integer], width: int, out: NDArray[np.uint8]) -> None:
    """ASCII digits of n ≥ 0 (M,) into ``out`` (M, width), zero-padded on the left; ``width`` ≥ the longest."""
    rest = n.astype(np.uint32) if n.size and int(n.max()) < 2**32 else n.astype(np.uint64)
    at = width
    while at > 0:  # the last 4 digits first
        rest, low = np.divmod(rest, 10_000)
        chunk = _CHUNKS[low].view(np.uint8).reshape(-1, 4)  # (M, 4)
        take = min(4, at)
        out[:, at - take:at] = chunk[:, 4 - take:]
        at -= take


def _length(n: NDArray[np.integer], width: int) -> NDArray[np.int16]:
    """(M,) number of decimal digits of n ≥ 0 (M,) (1 for 0), none longer than ``width``."""
    length = np.ones(n.shape, dtype=np.int16)
    for k in range(1, width):
        length += n >= 10**k
    return length


def _blank_leading(cells: NDArray[np.uint8], length: NDArray[np.int16], negative: NDArray[np.bool_] | None) -> None:
    """Zero the columns of ``cells`` (M, width) left of each row's last ``length`` (M,) digits; a ``-``
    just left of them where ``negative`` (M,)."""
    width = cells.shape[1]
    if width > 1 and int(length.min()) < width:
        cells *= np.arange(width, dtype=np.int16)[None, :] >= (width - length)[:, None]
    if negative is not None and negative.any():
        rows = np.flatnonzero(negative)
        cells[rows, width - 1 - length[rows]] = ord("-")


def _width(length: NDArray[np.int16], negative: NDArray[np.bool_] | None) -> int:
    """Columns the longest of the integers of ``length`` (M,) digits needs, with a sign where ``negative``."""
    if length.size == 0:
        return 1
    if negative is None or not negative.any():
        return int(length.max())
    return max(int(length.max()), int(length[negative].max()) + 1)


def _max_digits(n: NDArray[np.integer]) -> int:
    """Decimal digits of the largest of n ≥ 0 (M,) (1 when empty)."""
    return len(str(int(n.max()))) if n.size else 1


def _integer_cells(values: NDArray[np.int64]) -> NDArray[np.uint8]:
    """(M, width) right-aligned ASCII of integers (M,) (0 = nothing on the left)."""
    negative = values < 0
    magnitude = np.abs(values)
    length = _length(magnitude, _max_digits(magnitude))
    width = _width(length, negative)
    cells = np.empty((values.shape[0], width), dtype=np.uint8)
    _digits(magnitude, width, cells)
    _blank_leading(cells, length, negative)
    return cells


def _float_cells(values: NDArray[np.float64], decimals: int) -> NDArray[np.uint8]:
    """(M, width) right-aligned ASCII of ``'{:.<decimals>f}'`` of floats (M,) (0 = nothing on the left)."""
    scaled = np.abs(values)
    with np.errstate(invalid="ignore", over="ignore"):  # nan, inf, huge: Python's
        scaled *= 10.0**decimals
        whole = np.floor(scaled)
        fraction = scaled - whole  # exact
        up = fraction > 0.5
        fast = scaled < _EXACT
    top = float(scaled.max(where=fast, initial=0.0))
    fraction -= 0.5
    np.abs(fraction, out=fraction)
    slow = ~fast | (fraction <= 2.0 * np.spacing(top))  # too close to a tie to trust s's rounding: Python's
    whole += up
    whole[slow] = 0.0
    integer, frac = np.divmod(whole.astype(np.int64), 10**decimals)
    others = {int(i): f"{float(values[i]):.{decimals}f}".encode() for i in np.flatnonzero(slow)}
    negative = np.signbit(values) & ~slow
    length = _length(integer, _max_digits(integer))
    point = 1 if decimals > 0 else 0
    int_width = _width(length, negative)
    width = max(int_width + point + decimals, max((len(t) for t in others.values()), default=0))
    cells = np.empty((values.shape[0], width), dtype=np.uint8)
    int_width = width - point - decimals
    _digits(integer, int_width, cells[:, :int_width])
    _blank_leading(cells[:, :int_width], length, negative)
    if decimals > 0:
        cells[:, int_width] = ord(".")
        _digits(frac, decimals, cells[:, int_width + 1:])
    for i, text in others.items():
        cells[i] = 0
        cells[i, width - len(text):] = np.frombuffer(text, dtype=np.uint8)
    return cells


def table_text(values: NDArray, *, prefix: bytes = b"", delimiters: bytes | Sequence[bytes] = b" ",
               line_end: bytes = b"\n", decimals: int = 8) -> bytes:
    """The rows of a numeric table as text, each ``prefix v0 d0 v1 d1 … v(C−1) line_end``.

    Integers as ``'{}'``, floats as ``'{:.<decimals>f}'`` — the bytes Python's ``format`` writes for each
    number (module docstring), e.g. the vertex, normal and face lines of an OBJ file.

    Args:
        values: (N, C) integers or floats (a (N,) array is one column).
        prefix: bytes before each row's first number (e.g. ``b"v "``).
        delimiters: bytes between neighbouring numbers of a row: one for all, or C − 1 of them.
        line_end: bytes after each row.
        decimals: digits after the point for floats (0–18).

    Returns:
        The text, N rows (empty for N = 0).

    Example:
        >>> table_text(np.array([[1.5, -0.25]]), prefix=b"v ", decimals=3)
        b'v 1.500 -0.250\\n'
        >>> table_text(np.array([[1, 2], [30, 4]]), prefix=b"f ", delimiters=b"//")
        b'f 1//2\\nf 30//4\\n'
    """
    table = np.asarray(values)
    if table.ndim == 1:
        table = table[:, None]
    if table.ndim != 2:
        raise ValueError(f"values must be a (N, C) table; got shape {table.shape}")
    if table.dtype.kind not in "iuf":
        raise ValueError(f"values must be integers or floats; got dtype {table.dtype}")
    if not 0 <= decimals <= 18:
        raise ValueError(f"decimals must be in 0..18; got {decimals}")
    rows, columns = table.shape
    between = [delimiters] * (columns - 1) if isinstance(delimiters, bytes) else list(delimiters)
    if len(between) != max(columns - 1, 0):
        raise ValueError(f"delimiters: {columns - 1} needed between {columns} columns; got {len(between)}")
    if rows == 0:
        return b""
    parts = [table[r0:r0 + _CHUNK_ROWS] for r0 in range(0, rows, _CHUNK_ROWS)]  # a few MB each: in cache
    separators = [np.frombuffer(d, dtype=np.uint8) for d in (prefix, *between, line_end)]
    workers = min(len(parts), max(1, torch.get_num_threads()))
    if workers == 1:
        return b"".join(_rows_text(part, separators, decimals) for part in parts)
    with ThreadPoolExecutor(workers) as pool:  # numpy lets go of the GIL in its array loops
        return b"".join(pool.map(lambda part: _rows_text(part, separators, decimals), parts))


def _rows_text(table: NDArray, separators: list[NDArray[np.uint8]], decimals: int) -> bytes:
    """:func:`table_text` of a (N, C) table; ``separators``: the prefix, the C − 1 delimiters, the line end."""
    rows, columns = table.shape
    pieces = [separators[0]]
    for c in range(columns):  # one column at a time: (N,) temporaries
        column = np.ascontiguousarray(table[:, c])
        if c and np.array_equal(column, table[:, c - 1]):  # (an OBJ face's "a//a": the same cells twice)
            pieces.append(pieces[-2])
        else:
            pieces.append(_float_cells(column.astype(np.float64), decimals) if table.dtype.kind == "f"
                          else _integer_cells(column.astype(np.int64)))
        pieces.append(separators[c + 1])
    widths = [p.shape[-1] for p in pieces]
    line = np.empty((rows, sum(widths)), dtype=np.uint8)
    at = 0
    for piece, width in zip(pieces, widths):
        line[:, at:at + width] = piece
        at += width
    return line[line != 0].tobytes()
