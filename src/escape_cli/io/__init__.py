"""Point-cloud files: read and write PLY, PCD, text (xyz/txt/pts/csv), NumPy, LAS/LAZ and HDF5 clouds.

`read_points` / `read_point_fields` return float64 coordinates with non-finite rows
dropped (and counted in a warning); `write_points` writes atomically and never
replaces an existing file unless asked. The path ``-`` is stdin for readers (the format
is then sniffed from the bytes) and stdout for writers (binary PLY unless a format is
given). Every problem is an `escape_cli.errors` exception with a one-line message that
names the file.

Coordinates are written as float32 unless float32 would round them by more than a small
share of the cloud's size (`coordinate_dtype_for`: far from the origin, e.g. UTM metres);
LAS/LAZ store scaled integers instead (`escape_cli.io.las`).

One module per format does the parsing and serialising on bytes: `ply`, `pcd`,
`text`, `npy` (with `lzf` for compressed PCD), `las` (LAS and LAZ), `h5`; `files` moves
the bytes. The format names are in `escape_cli.formats`.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np

from escape_cli.core.checks import as_points
from escape_cli.errors import FormatError, InputFileError, PointCloudError
from escape_cli.formats import CLOUD_SUFFIXES, FORMAT_LIST, FORMATS
from escape_cli.io.common import Fields, coordinate_dtype_for, storage_dtype
from escape_cli.io.files import check_writable_folder, display_name, is_stdio, read_input_bytes, write_output_bytes
from escape_cli.io.h5 import is_h5, parse_h5, serialize_h5
from escape_cli.io.las import is_las, parse_las, serialize_las, template_layout
from escape_cli.io.npy import is_npy, is_npz, parse_array, parse_npy, serialize_array, serialize_npy, serialize_npz
from escape_cli.io.pcd import is_pcd, parse_pcd, serialize_pcd
from escape_cli.io.ply import is_ply, parse_ply, serialize_ply
from escape_cli.io.text import TEXT_FORMATS, looks_like_text_cloud, parse_text, serialize_text

__all__ = [
    "CLOUD_SUFFIXES",
    "FORMATS",
    "coordinate_dtype_for",
    "check_writable_folder",
    "display_name",
    "format_from_path",
    "input_format",
    "is_cloud_file",
    "is_stdio",
    "output_format",
    "parse_point_fields",
    "read_array",
    "read_point_fields",
    "read_points",
    "sniff_format",
    "write_array",
    "write_points",
]

log = logging.getLogger("escape")

STDOUT_DEFAULT_FORMAT = "ply"
COORDINATE_DTYPES = (np.dtype(np.float32), np.dtype(np.float64))
FIELD_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*\Z")


def format_from_path(path: str | Path) -> str:
    """The format named by a file's extension (case-insensitive).

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    str
        One of `FORMATS`.

    Raises
    ------
    InputFileError
        The extension is missing or not a known format.
    """
    suffix = Path(str(path)).suffix.lower()
    fmt = suffix.lstrip(".")
    if fmt in FORMATS:
        return fmt
    if not suffix:
        raise FormatError(f"cannot tell the format of {path} (no extension); use --format ({FORMAT_LIST})")
    raise FormatError(f"unknown format '{suffix}' for {path}; use --format ({FORMAT_LIST})")


TEXT_HEAD_BYTES = 8192


def is_cloud_file(path: str | Path) -> bool:
    """Whether a file found in a folder is a point cloud to read: a known extension, and for
    the text formats a first row of numbers (a ``LICENSE.txt`` is skipped, not read).

    A file named on the command line is read whatever it is called; this is for folders.
    """
    fmt = Path(path).suffix.lower().lstrip(".")
    if fmt not in FORMATS:
        return False
    if fmt not in TEXT_FORMATS:
        return True
    try:
        with open(path, "rb") as handle:
            head = handle.read(TEXT_HEAD_BYTES)
    except OSError:
        return True  # reading it reports the problem, for that file alone
    return looks_like_text_cloud(head)


def sniff_format(data: bytes) -> str:
    """Guess a cloud's format from its first bytes: ply, pcd, npy, npz, las (LAS or LAZ), h5, else xyz (text)."""
    if is_ply(data):
        return "ply"
    if is_las(data):
        return "las"
    if is_h5(data):
        return "h5"
    if is_npy(data):
        return "npy"
    if is_npz(data):
        return "npz"
    if is_pcd(data):
        return "pcd"
    return "xyz"


def read_points(path: str | Path, fmt: str | None = None) -> np.ndarray:
    """Read a point cloud's coordinates.

    Parameters
    ----------
    path : str or Path
        The file, or ``-`` for stdin.
    fmt : str, optional
        One of `FORMATS`; by default from the extension (sniffed from the bytes for
        stdin).

    Returns
    -------
    points : (N, 3) float64
        Finite points only; N >= 1.

    Raises
    ------
    InputFileError
        Missing, unreadable, corrupt or truncated file, or unknown format.
    PointCloudError
        No points, or no finite points.
    """
    return read_point_fields(path, fmt)[0]


def read_point_fields(path: str | Path, fmt: str | None = None) -> tuple[np.ndarray, Fields]:
    """Read a point cloud's coordinates and its other per-point scalar fields.

    Parameters
    ----------
    path : str or Path
        The file, or ``-`` for stdin.
    fmt : str, optional
        One of `FORMATS`; by default from the extension (sniffed for stdin).

    Returns
    -------
    points : (N, 3) float64
        Finite points only; N >= 1.
    fields : dict of str to (N,) float64
        E.g. ``red``/``green``/``blue``, ``normal_x``, ``curvature``, ``intensity``,
        ``residual``; rows match `points`.

    Raises
    ------
    InputFileError, PointCloudError
        As `read_points`.
    """
    fmt = input_format(path, fmt)  # an unknown extension is reported before the file is read
    return parse_point_fields(read_input_bytes(path), display_name(path), fmt)


def input_format(path: str | Path, fmt: str | None = None) -> str | None:
    """The format `read_points(path, fmt)` will parse: `fmt`, else the extension (None: sniffed, for ``-``).

    Raises
    ------
    InputFileError
        Unknown format or extension.
    """
    if fmt is not None:
        return _checked_format(fmt)
    return None if is_stdio(path) else format_from_path(path)


def parse_point_fields(data: bytes, name: str, fmt: str | None = None) -> tuple[np.ndarray, Fields]:
    """`read_point_fields` on the bytes of a file already read (by a batch engine's reader).

    Parameters
    ----------
    data : bytes
        The whole file.
    name : str
        The name used in messages (the path as given).
    fmt : str, optional
        One of `FORMATS`; None sniffs it from the bytes.

    Returns
    -------
    points : (N, 3) float64
    fields : dict of str to (N,) float64

    Raises
    ------
    InputFileError, PointCloudError
        As `read_points`.
    """
    if not data:
        raise InputFileError(f"{name}: empty file")
    fmt = sniff_format(data) if fmt is None else _checked_format(fmt)
    xyz, fields = _parse(data, name, fmt)
    return _finite_rows(xyz, fields, name)


def write_points(
    path: str | Path,
    points,
    fmt: str | None = None,
    *,
    overwrite: bool = False,
    fields: dict[str, np.ndarray] | None = None,
    binary: bool = True,
    coordinate_dtype=None,
    like: str | Path | None = None,
) -> None:
    """Write a point cloud atomically.

    Parameters
    ----------
    path : str or Path
        The file, or ``-`` for stdout.
    points : (N, 3) array_like
        N >= 1.
    fmt : str, optional
        One of `FORMATS`; by default from the extension (binary PLY for stdout).
    overwrite : bool
        Replace an existing file.
    fields : dict of str to (N,) array_like, optional
        Extra per-point scalars (e.g. ``residual``): float32 properties in PLY/PCD,
        extra columns in text files, arrays in npz and h5, float32 extra-bytes
        dimensions in LAS/LAZ (or the dimension of that name, ``intensity``...); not
        stored in npy.
    binary : bool
        Binary (default) or ascii body for PLY and PCD; ignored by other formats.
    coordinate_dtype : numpy dtype, optional
        float32 or float64 coordinates; by default `coordinate_dtype_for(points)`:
        float32 unless the coordinates need float64. LAS/LAZ ignore it.
    like : str or Path, optional
        A LAS/LAZ file whose scale, offset, point format and CRS records a LAS/LAZ
        output copies (`escape complete` passes its input); ignored for other outputs,
        or when `like` is not a LAS file. Without it LAS/LAZ get `las.layout_for`.

    float32 gives way to float64 for coordinates (and fields) beyond its range, so a file
    never holds an infinity the data did not have.

    Raises
    ------
    OutputExistsError
        `path` exists and `overwrite` is false.
    OutputFileError
        The file cannot be written.
    InputFileError
        Unknown format.
    PointCloudError
        Points not (N, 3) with N >= 1, or a bad field name or length.
    """
    name = display_name(path) if not is_stdio(path) else "<stdout>"
    fmt = output_format(path, fmt)
    points = _checked_points(points, name)
    fields = _checked_fields(fields or {}, len(points), name)
    coordinate_dtype = coordinate_dtype_for(points) if coordinate_dtype is None else np.dtype(coordinate_dtype)
    if coordinate_dtype not in COORDINATE_DTYPES:
        raise ValueError(f"coordinate_dtype must be float32 or float64, not {coordinate_dtype}")
    coordinate_dtype = storage_dtype(points, coordinate_dtype)  # never inf (or 0) where float32 cannot hold them
    if fmt == "ply":
        data = serialize_ply(points, fields, binary=binary, coordinate_dtype=coordinate_dtype)
    elif fmt == "pcd":
        data = serialize_pcd(points, fields, binary=binary, coordinate_dtype=coordinate_dtype)
    elif fmt == "npy":
        data = serialize_npy(points, coordinate_dtype=coordinate_dtype)
    elif fmt == "npz":
        data = serialize_npz(points, fields, coordinate_dtype=coordinate_dtype)
    elif fmt in ("las", "laz"):
        layout = template_layout(like) if like is not None else None
        data = serialize_las(points, fields, compressed=fmt == "laz", layout=layout)
    elif fmt == "h5":
        data = serialize_h5(points, fields, coordinate_dtype=coordinate_dtype)
    else:
        data = serialize_text(points, fields, fmt=fmt, coordinate_dtype=coordinate_dtype)
    write_output_bytes(path, data, overwrite=overwrite)


def output_format(path: str | Path, fmt: str | None = None) -> str:
    """The format `write_points` will use: `fmt`, else binary PLY for ``-``, else the extension.

    Lets a command check its output format before doing any work.

    Raises
    ------
    InputFileError
        Unknown format or extension.
    """
    if fmt is not None:
        return _checked_format(fmt)
    return STDOUT_DEFAULT_FORMAT if is_stdio(path) else format_from_path(path)


def read_array(path: str | Path) -> np.ndarray:
    """Read any numeric array from a ``.npy`` file, or from stdin for ``-``.

    Returns
    -------
    numpy.ndarray
        As stored (no pickles).

    Raises
    ------
    InputFileError
        Missing, unreadable, empty, corrupt or non-numeric.
    """
    return parse_array(read_input_bytes(path), display_name(path))


def write_array(path: str | Path, array, *, overwrite: bool = False) -> None:
    """Write an array as ``.npy`` atomically, or to stdout for ``-``.

    Raises
    ------
    OutputExistsError, OutputFileError
        As `write_points`.
    """
    write_output_bytes(path, serialize_array(np.asarray(array)), overwrite=overwrite)


def _checked_format(fmt: str) -> str:
    normalised = fmt.lower().lstrip(".")
    if normalised not in FORMATS:
        raise FormatError(f"unknown format '{fmt}'; use one of {FORMAT_LIST}")
    return normalised


def _parse(data: bytes, name: str, fmt: str) -> tuple[np.ndarray, Fields]:
    # Casting stored NaN bit patterns (signalling NaNs) to float64 sets numpy's "invalid"
    # flag; the rows are dropped later, so no RuntimeWarning.
    with np.errstate(all="ignore"):
        if fmt == "ply":
            return parse_ply(data, name)
        if fmt == "pcd":
            return parse_pcd(data, name)
        if fmt in ("npy", "npz"):
            return parse_npy(data, name, fmt)
        if fmt in ("las", "laz"):
            return parse_las(data, name)
        if fmt == "h5":
            return parse_h5(data, name)
        return parse_text(data, name, fmt)


def _finite_rows(xyz: np.ndarray, fields: Fields, name: str) -> tuple[np.ndarray, Fields]:
    """Drop rows with a non-finite coordinate; refuse clouds with no finite point."""
    total = len(xyz)
    if total == 0:
        raise PointCloudError(f"{name}: the file holds no points")
    finite = np.isfinite(xyz).all(axis=1)  # (N,)
    kept = int(finite.sum())
    if kept == 0:
        raise PointCloudError(f"{name}: all {total} points have non-finite (NaN/Inf) coordinates")
    if kept < total:
        log.warning("%s: dropped %d of %d points with non-finite coordinates", name, total - kept, total)
        xyz = xyz[finite]
        fields = {key: value[finite] for key, value in fields.items()}
    return np.ascontiguousarray(xyz, dtype=np.float64), fields


def _checked_points(points, name: str) -> np.ndarray:
    return as_points(points, f"cannot write {name}: the cloud", min_points=1)


def _checked_fields(fields: dict, n_points: int, name: str) -> Fields:
    checked: Fields = {}
    for key, values in fields.items():
        if not FIELD_NAME.match(key) or key in ("x", "y", "z"):
            raise PointCloudError(f"cannot write {name}: bad field name '{key}' (letters, digits, '_'; not x/y/z)")
        array = np.asarray(values, dtype=np.float64)
        if array.shape != (n_points,):
            raise PointCloudError(f"cannot write {name}: field '{key}' has shape {array.shape}, expected ({n_points},)")
        checked[key] = array
    return checked
