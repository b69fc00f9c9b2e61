"""Plain-text point clouds (.xyz, .txt, .pts, .csv): one point per line.

Values are separated by whitespace or commas. The first three columns are x, y, z,
unless a line of names says otherwise; extra columns become fields. Blank lines and
lines starting with ``#`` or ``//`` are skipped. A first line holding one integer is
the point count (``.pts`` files): it must match the rows. Column names come from a
first line of names (``x,y,z,intensity``; quoted, any case: PDAL writes
``"X","Y","Z"``) or from the last comment line before the data (``# x y z residual``,
as `serialize_text` writes); named columns x, y, z (any case, any position) are the
coordinates. Otherwise extra columns are ``col3``, ``col4``, ... (``.pts``:
``intensity``, ``red``, ``green``, ``blue``).
"""

from __future__ import annotations

import numpy as np

from escape_cli.errors import InputFileError
from escape_cli.formats import TEXT_FORMATS
from escape_cli.io.common import Fields, format_rows, storage_dtype, tokens_to_float

__all__ = ["TEXT_FORMATS", "looks_like_text_cloud", "parse_text", "serialize_text"]
COMMENT_PREFIXES = (b"#", b"//")
PTS_EXTRA_COLUMNS = {1: ["intensity"], 4: ["intensity", "red", "green", "blue"], 3: ["red", "green", "blue"]}


def parse_text(data: bytes, name: str, fmt: str = "xyz") -> tuple[np.ndarray, Fields]:
    """Read a text point cloud.

    Parameters
    ----------
    data : bytes
        The whole file.
    name : str
        The file name, for messages.
    fmt : str
        One of `TEXT_FORMATS`; only changes the default names of extra columns.

    Returns
    -------
    xyz : (N, 3) float64
        Non-finite rows included.
    fields : dict of str to (N,) float64
        One per extra column.

    Raises
    ------
    InputFileError
        A value that is not a number, fewer than 3 columns, or lines with different
        numbers of columns.
    """
    rows: list[list[bytes]] = []
    line_numbers: list[int] = []
    header_names: list[str] | None = None
    declared: int | None = None  # the .pts point count line
    for line_number, raw_line in enumerate(data.splitlines(), start=1):
        line = raw_line.strip()
        if not line:
            continue
        if line.startswith(COMMENT_PREFIXES):
            if not rows:
                header_names = _names_or_none(line.lstrip(b"#/").replace(b",", b" ").split())
            continue
        tokens = line.replace(b",", b" ").split()
        if not rows:
            if len(tokens) == 1 and tokens[0].isdigit() and declared is None:
                declared = int(tokens[0])
                continue  # point count line (.pts)
            names = _names_or_none(tokens)
            if names is not None:
                header_names = names
                continue
            tokens_to_float(tokens, name, f"line {line_number}")  # fail early on text that is no cloud
        rows.append(tokens)
        line_numbers.append(line_number)
    if not rows:
        if declared:
            raise InputFileError(f"{name}: the first line declares {declared} points, but no rows follow")
        return np.empty((0, 3)), {}
    n_columns = len(rows[0])
    for tokens, line_number in zip(rows, line_numbers):
        if len(tokens) != n_columns:
            raise InputFileError(
                f"{name}: line {line_number} has {len(tokens)} columns, line {line_numbers[0]} has {n_columns}"
            )
    if n_columns < 3:
        raise InputFileError(f"{name}: {n_columns} column{'s' if n_columns > 1 else ''} per line; need at least x y z")
    if declared is not None and declared != len(rows):
        raise InputFileError(f"{name}: the first line declares {declared} points, but {len(rows)} rows follow")
    flat = [token for tokens in rows for token in tokens]
    try:
        table = tokens_to_float(flat, name, "point data").reshape(len(rows), n_columns)
    except InputFileError:
        for tokens, line_number in zip(rows, line_numbers):
            tokens_to_float(tokens, name, f"line {line_number}")  # raises, naming the line
        raise
    named = _named_coordinates(header_names, n_columns)
    if named is not None:
        xyz_columns, extra = named
        fields = {field: table[:, j].copy() for field, j in extra.items()}
        return np.ascontiguousarray(table[:, xyz_columns]), fields
    extra_names = _extra_column_names(header_names, n_columns, fmt)
    fields = {field: table[:, 3 + i].copy() for i, field in enumerate(extra_names)}
    return np.ascontiguousarray(table[:, :3]), fields


def looks_like_text_cloud(head: bytes) -> bool:
    """Whether the first bytes of a file read as the start of a text cloud.

    Its first row of values, after blank lines, comments, a point count and one line of
    names, must hold three or more numbers: a licence or a note saved as ``.txt``
    does not. True when `head` holds no complete row to judge by (the reader decides).
    """
    lines = head.splitlines()
    if len(lines) > 1 and not head.endswith((b"\n", b"\r")):
        lines = lines[:-1]  # cut off by the length of `head`
    names_seen = False
    for line in (raw.strip() for raw in lines):
        if not line or line.startswith(COMMENT_PREFIXES):
            continue
        tokens = line.replace(b",", b" ").split()
        if len(tokens) == 1 and tokens[0].isdigit() and not names_seen:
            continue  # a point count
        if _names_or_none(tokens) is not None:
            if names_seen:
                return False  # words after words: prose
            names_seen = True
            continue
        try:
            [float(token) for token in tokens]
        except ValueError:
            return False
        return len(tokens) >= 3
    return True


def serialize_text(points: np.ndarray, fields: Fields, *, fmt: str = "xyz", coordinate_dtype=np.float32) -> bytes:
    """One point per line; a ``# x y z name...`` line first when there are fields.

    Parameters
    ----------
    points : (N, 3) float64
    fields : dict of str to (N,) float64
        Written as float32 columns after x y z (float64 digits where float32 cannot hold them).
    fmt : str
        ``csv`` separates with commas (and always writes the names line, uncommented);
        ``pts`` starts with the point count; others separate with spaces.
    coordinate_dtype : numpy dtype
        float32 or float64: how many digits the coordinates get.

    Returns
    -------
    bytes
    """
    separator = "," if fmt == "csv" else " "
    names = ["x", "y", "z", *fields]
    lines = b""
    if fmt == "pts":
        lines += f"{len(points)}\n".encode()
    if fmt == "csv":
        lines += (",".join(names) + "\n").encode()
    elif fields:
        lines += ("# " + " ".join(names) + "\n").encode()
    columns = [points[:, 0], points[:, 1], points[:, 2], *fields.values()]
    dtypes = [np.dtype(coordinate_dtype)] * 3 + [storage_dtype(values) for values in fields.values()]
    return lines + format_rows(columns, dtypes, separator)


def _names_or_none(tokens: list[bytes]) -> list[str] | None:
    """Column names when every token is an identifier (not a number; quotes removed), else None."""
    try:
        words = [token.decode("ascii").strip("\"'") for token in tokens]
    except UnicodeDecodeError:
        return None
    if words and all(word.isidentifier() and word.lower() not in ("nan", "inf", "infinity") for word in words):
        return words
    return None


def _named_coordinates(header_names: list[str] | None, n_columns: int) -> tuple[list[int], dict[str, int]] | None:
    """([column of x, y, z], {field: column}) when a names line names x, y and z (any case), else None."""
    if header_names is None or len(header_names) != n_columns:
        return None
    lower = [n.lower() for n in header_names]
    if not all(lower.count(axis) == 1 for axis in "xyz"):
        return None
    xyz_columns = [lower.index(axis) for axis in "xyz"]
    extra = {n: j for j, n in enumerate(header_names) if j not in xyz_columns}
    return xyz_columns, extra


def _extra_column_names(header_names: list[str] | None, n_columns: int, fmt: str) -> list[str]:
    n_extra = n_columns - 3
    if header_names is not None and len(header_names) == n_columns:
        return header_names[3:]
    if fmt == "pts" and n_extra in PTS_EXTRA_COLUMNS:
        return PTS_EXTRA_COLUMNS[n_extra]
    return [f"col{3 + i}" for i in range(n_extra)]
