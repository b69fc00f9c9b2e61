"""Helpers shared by the format modules: number parsing and text formatting."""

from __future__ import annotations

import io

import numpy as np

from escape_cli.errors import InputFileError

# A reader returns the coordinates and the other per-point scalar fields:
#   xyz : (N, 3) float64 (non-finite rows still in), fields : name -> (N,) float64.
Fields = dict[str, np.ndarray]

FLOAT32_MAX = float(np.finfo(np.float32).max)
FLOAT32_TINY = float(np.finfo(np.float32).tiny)  # the smallest normal float32


def storage_dtype(values, preferred=np.float32) -> np.dtype:
    """`preferred` (float32 or float64), or float64 where float32 cannot hold `values`.

    float32 overflows to inf beyond 3.4e38, and a cloud whose values all lie below its
    normal range (1.2e-38) would lose its precision or become zeros: a file must never
    hold infinities (or zeros) the data did not have.

    Parameters
    ----------
    values : array_like of float
    preferred : numpy dtype

    Returns
    -------
    numpy dtype
    """
    preferred = np.dtype(preferred)
    if preferred == np.float64:
        return preferred
    magnitudes = np.abs(np.asarray(values, dtype=np.float64))
    magnitudes = magnitudes[np.isfinite(magnitudes)]
    largest = float(magnitudes.max()) if magnitudes.size else 0.0
    if largest > FLOAT32_MAX or 0.0 < largest < FLOAT32_TINY:
        return np.dtype(np.float64)
    return preferred


# Enough significant digits to give back the exact binary value.
SIGNIFICANT_DIGITS = {np.dtype(np.float32): 9, np.dtype(np.float64): 17}

FLOAT32_SHARE = 1e-5
"""Coordinates are written as float64 when float32's spacing at the largest |coordinate|
exceeds this share of the cloud's extent (its bounding box's longest side)."""


def coordinate_dtype_for(points: np.ndarray) -> np.dtype:
    """float32, or float64 where float32 would round the coordinates by too much.

    float32 has 24 significant bits: its spacing at |x| is about 1.2e-7 |x|. A cloud
    about one unit across near the origin loses nothing of note; the same cloud 10^6
    units away (UTM eastings and northings in metres) would be rounded to 0.06-0.5 units.
    The rule: float64 when `numpy.spacing(float32(max |x|))` exceeds `FLOAT32_SHARE`
    (1e-5) of the extent, i.e. from 64-128 extents away from the origin on; a single point
    (or identical points) away from the origin gets float64 too.

    Parameters
    ----------
    points : (N, 3) float64, N >= 1, finite.

    Returns
    -------
    numpy.dtype
        float32 or float64.
    """
    largest = float(np.max(np.abs(points)))
    extent = float(np.max(points.max(axis=0) - points.min(axis=0)))
    spacing = float(np.spacing(np.float32(largest)))
    if largest == 0.0 or spacing <= FLOAT32_SHARE * extent:
        return np.dtype(np.float32)
    return np.dtype(np.float64)


def printable(raw: bytes | str, limit: int = 60) -> str:
    """At most `limit` characters of `raw` for a message: control characters and bytes
    that are not ASCII text escaped (``\\x1b``), so a garbage file cannot garble the terminal."""
    text = raw.decode("ascii", errors="backslashreplace") if isinstance(raw, bytes) else str(raw)
    shown = "".join(c if c.isprintable() and ord(c) < 0x7F else _escaped(c) for c in text[:limit])
    return shown + ("..." if len(text) > limit else "")


def counted(count: int, noun: str) -> str:
    """``1 byte``, ``3 bytes``: a count with its noun."""
    return f"{count} {noun}{'' if count == 1 else 's'}"


PADDING = b" \t\r\n\x00"
"""Bytes a writer may leave after a body: line endings, and zeros (PCL pads binary_compressed files)."""


def _escaped(char: str) -> str:
    code = ord(char)
    return f"\\x{code:02x}" if code < 0x100 else f"\\u{code:04x}"


def trailing_data(data: bytes, end: int) -> int:
    """How many bytes after offset `end` are data rather than padding (0 if only `PADDING`)."""
    rest = data[end:]
    return len(rest) if rest.strip(PADDING) else 0


def tokens_to_float(tokens: list[bytes], name: str, what: str) -> np.ndarray:
    """Convert number tokens to float64, or raise a one-line error naming the bad token.

    Parameters
    ----------
    tokens : list of bytes
        Decimal numbers (``nan``/``inf`` accepted).
    name : str
        The file, for the message.
    what : str
        What the tokens are ("vertex data", "line 3"), for the message.

    Returns
    -------
    (T,) float64
    """
    try:
        return np.array(tokens, dtype=np.bytes_).astype(np.float64)
    except (ValueError, UnicodeDecodeError):
        for token in tokens:
            try:
                float(token)
            except (ValueError, UnicodeDecodeError):
                raise InputFileError(f"{name}: {what}: '{printable(token, 20)}' is not a number") from None
        raise InputFileError(f"{name}: {what}: not numbers") from None


def format_rows(columns: list[np.ndarray], dtypes: list[np.dtype], separator: str = " ") -> bytes:
    """Text rows, one per point, each value with enough digits for its dtype.

    Parameters
    ----------
    columns : list of (N,) arrays
    dtypes : list of numpy dtypes, one per column (float32 or float64).
    separator : str

    Returns
    -------
    bytes
        N lines, each ending in a newline.
    """
    if not columns:
        return b""
    table = np.column_stack([np.asarray(c, dtype=np.float64) for c in columns])
    formats = [f"%.{SIGNIFICANT_DIGITS[np.dtype(d)]}g" for d in dtypes]
    # round float32 columns first: 9 significant digits of the float32 value read back
    # as exactly that float32
    for j, dtype in enumerate(dtypes):
        if np.dtype(dtype) == np.float32:
            table[:, j] = table[:, j].astype(np.float32)
    buffer = io.BytesIO()
    np.savetxt(buffer, table, fmt=formats, delimiter=separator)
    return buffer.getvalue()


def pack_rows(columns: list[np.ndarray], dtypes: list[np.dtype]) -> bytes:
    """Little-endian binary rows, one per point: column j as `dtypes[j]` (PLY and PCD bodies).

    Parameters
    ----------
    columns : list of (N,) arrays
    dtypes : list of numpy dtypes, one per column.

    Returns
    -------
    bytes
        N rows of sum(itemsize) bytes each, no padding.
    """
    row = np.dtype([(f"c{i}", np.dtype(d).newbyteorder("<")) for i, d in enumerate(dtypes)])
    table = np.empty(len(columns[0]) if columns else 0, dtype=row)
    for i, column in enumerate(columns):
        table[f"c{i}"] = column
    return table.tobytes()
