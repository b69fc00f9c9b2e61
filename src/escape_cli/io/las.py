"""LAS and LAZ point clouds (the ASPRS LiDAR format and its compressed form), through laspy and lazrs.

A LAS file stores each coordinate as an int32 count of a per-axis scale above an
offset: ``x = X * scale_x + offset_x``. Reading gives float64 coordinates, computed
from those integers, and the point format's other dimensions (``intensity``,
``classification``, ``return_number``, ``gps_time``, ``red``..., and every extra-bytes
dimension) as fields. Writing needs a scale and an offset: those of a template file
(`template_layout`: `escape complete` passes its input, so the observed points of a
LAS scan go back onto the same integer grid, CRS records included), or ones chosen
for the cloud (`layout_for`). LAZ is the same content compressed (lazrs backend).
"""

from __future__ import annotations

import io
import logging
import math
import os
import struct
import sys
import tempfile
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from escape_cli.errors import InputFileError, OutputFileError, PointCloudError
from escape_cli.io.common import Fields

log = logging.getLogger("escape")

LAS_MAGIC = b"LASF"
DEFAULT_POINT_FORMAT = 6  # LAS 1.4: the format extra-bytes dimensions are specified for
DEFAULT_VERSION = "1.4"
SCALE_SHARE = 1e-6
"""Chosen scales are the power of ten at or below this share of the cloud's extent:
1 mm for a 1-2 km tile, 1 micrometre for a car, in whatever units the cloud is in."""
INT32_LIMIT = 2**31 - 1
PROJECTION_USER_ID = "LASF_Projection"  # GeoTIFF keys (34735-34737) and WKT (2111, 2112)
COORDINATE_DIMENSIONS = ("X", "Y", "Z")
MAX_EXTRA_NAME = 32


@dataclass(frozen=True)
class LasLayout:
    """How a LAS file stores its points: scale, offset, point format and CRS records.

    Attributes
    ----------
    scales : (3,) float64
    offsets : (3,) float64
    point_format : int
        LAS point data record format (0-10).
    version : str
        ``"1.2"``, ``"1.4"``...
    projection : tuple of (user_id, record_id, description, data) tuples
        The template's coordinate reference system records, copied as they are.
    wkt : bool
        The global-encoding flag saying the CRS is WKT (LAS 1.4).
    """

    scales: np.ndarray
    offsets: np.ndarray
    point_format: int = DEFAULT_POINT_FORMAT
    version: str = DEFAULT_VERSION
    projection: tuple = field(default=())
    wkt: bool = False

    def fits(self, points: np.ndarray) -> bool:
        """True when every point's integer counts fit in int32 with this scale and offset."""
        counts = np.round((points - self.offsets) / self.scales)  # (N, 3)
        return bool(np.all(np.abs(counts) <= INT32_LIMIT))


def is_las(data: bytes) -> bool:
    """True when the bytes start like a LAS or LAZ file."""
    return data.startswith(LAS_MAGIC)


def parse_las(data: bytes, name: str) -> tuple[np.ndarray, Fields]:
    """Read a LAS or LAZ file.

    Parameters
    ----------
    data : bytes
        The whole file (compressed or not: the header says).
    name : str
        The file name, for messages.

    Returns
    -------
    xyz : (N, 3) float64
        ``X * scale + offset`` per axis.
    fields : dict of str to (N,) float64
        Every other scalar dimension of the point format, extra-bytes ones included.

    Raises
    ------
    InputFileError
        Not a LAS file, a corrupt or truncated one, or LAZ without a decompressor.
    """
    laspy = _laspy()
    if not is_las(data):
        raise InputFileError(f"{name}: not a LAS/LAZ file (it does not start with 'LASF')")
    try:
        check_header_counts(data, name)
        # the sequential decompressor: the parallel one sizes its buffers from chunk-table
        # entries no header check can read (1M points: 0.21 s against 0.14 s on 2 cores)
        with _native_stderr_silenced():  # a panic in lazrs' Rust code prints its own lines
            las = laspy.read(io.BytesIO(data), laz_backend=laspy.LazBackend.Lazrs)
    except (InputFileError, KeyboardInterrupt, SystemExit):
        raise
    except BaseException as err:  # LaspyException, ValueError, struct errors; lazrs panics are BaseExceptions
        raise InputFileError(f"{name}: corrupt or truncated LAS/LAZ file ({_first_line(err)})") from None
    scales = np.asarray(las.header.scales, dtype=np.float64)
    offsets = np.asarray(las.header.offsets, dtype=np.float64)
    counts = np.column_stack([np.asarray(las[axis]) for axis in COORDINATE_DIMENSIONS])  # (N, 3) int32
    xyz = counts.astype(np.float64) * scales + offsets
    fields: Fields = {}
    for dim in las.point_format.dimension_names:
        if dim in COORDINATE_DIMENSIONS:
            continue
        values = np.asarray(las[dim])
        if values.ndim == 1:  # extra-bytes arrays (N, k) are skipped
            fields[dim] = values.astype(np.float64)
    return xyz, fields


def serialize_las(points: np.ndarray, fields: Fields, *, compressed: bool, layout: LasLayout | None = None) -> bytes:
    """A LAS (or LAZ) file of the points and fields.

    Parameters
    ----------
    points : (N, 3) float64
    fields : dict of str to (N,) float64
        A field named like a dimension of the point format (``intensity``,
        ``classification``...) fills that dimension and must fit its type; the others
        become float32 extra-bytes dimensions (``residual``, ``observed``).
    compressed : bool
        LAZ when true.
    layout : LasLayout, optional
        Scale, offset, point format and CRS records; by default `layout_for(points)`.
        A layout whose offset leaves points out of int32 range keeps its scale and gets
        a new offset.

    Returns
    -------
    bytes

    Raises
    ------
    PointCloudError
        A field that does not fit its dimension, or a bad extra-bytes name.
    """
    laspy = _laspy()
    layout = _usable_layout(points, layout)
    header = laspy.LasHeader(point_format=layout.point_format, version=layout.version)
    standard = {dim.name: dim for dim in header.point_format.dimensions}
    extra = [key for key in fields if key not in standard]
    for key in fields:
        if key.upper() in COORDINATE_DIMENSIONS:
            raise PointCloudError(f"a LAS field cannot be named '{key}' (the coordinates)")
        if key in extra and len(key) > MAX_EXTRA_NAME:
            raise PointCloudError(f"LAS extra-dimension names have at most {MAX_EXTRA_NAME} characters: '{key}'")
    if extra:
        header.add_extra_dims([laspy.ExtraBytesParams(name=key, type=np.float32) for key in extra])
    header.scales = layout.scales
    header.offsets = layout.offsets
    for user_id, record_id, description, record_data in layout.projection:
        header.vlrs.append(laspy.VLR(user_id=user_id, record_id=record_id, description=description, record_data=record_data))
    if layout.wkt:
        header.global_encoding.wkt = True
    las = laspy.LasData(header=header, points=laspy.ScaleAwarePointRecord.zeros(len(points), header=header))
    counts = np.round((points - layout.offsets) / layout.scales).astype(np.int32)  # (N, 3)
    for j, axis in enumerate(COORDINATE_DIMENSIONS):
        las[axis] = counts[:, j]
    for key, values in fields.items():
        if key in standard:
            las[key] = _fitted(values, standard[key], key)
        else:
            las[key] = values.astype(np.float32)
    buffer = io.BytesIO()
    try:
        las.write(buffer, do_compress=compressed)
    except Exception as err:  # no LAZ backend, or laspy refusing a value
        raise OutputFileError(f"cannot write LAS/LAZ: {_first_line(err)}") from None
    return buffer.getvalue()


LAZ_MOST_COMPRESSION = 1000
"""The most bytes of point records a LAZ file's byte may stand for (real scans: 5-20; a
constant cloud a few hundred): a header declaring more is refused before anything is
allocated for it."""


LAZ_LARGEST_CHUNK = 64 << 20
"""Bytes of point records one LAZ chunk may hold when the file has fewer points (LAZ
writers use 50,000-point chunks: 1.5-3.5 MB)."""


@contextmanager
def _native_stderr_silenced():
    """Send file descriptor 2 to a temporary file for the block (what native code prints there
    is logged at debug level), so that a decoder's own panic message stays off the terminal."""
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError, AttributeError):
        yield
        return
    with tempfile.TemporaryFile() as capture:
        os.dup2(capture.fileno(), 2)
        try:
            yield
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            capture.seek(0)
            text = capture.read(4096).decode("utf-8", "replace").strip()
            if text:
                log.debug("LAS decoder: %s", " ".join(text.split()))


def check_header_counts(data: bytes, name: str) -> None:
    """Refuse a LAS header whose counts the file cannot hold, before laspy allocates for them.

    The counts are read from the public header layout (LAS 1.0-1.4): VLRs (54-byte
    headers) must fit between the header and the point data, EVLRs (60-byte headers)
    after their start, and the points in what follows the point data offset (for LAZ,
    at most `LAZ_MOST_COMPRESSION` bytes of records per byte of file).

    Raises
    ------
    InputFileError
        A count or offset the file's size contradicts.
    """
    if len(data) < 227:
        raise InputFileError(f"{name}: truncated LAS header ({len(data)} bytes; at least 227 needed)")
    minor = data[25]
    header_size, point_offset, vlr_count = struct.unpack_from("<HII", data, 94)
    point_format, record_length, legacy_count = struct.unpack_from("<BHI", data, 104)
    count = legacy_count
    if minor >= 4 and len(data) >= 255:
        evlr_start, evlr_count, count_64 = struct.unpack_from("<QIQ", data, 235)
        count = count_64 or legacy_count
        if evlr_count and (evlr_start > len(data) or evlr_count * 60 > len(data) - evlr_start):
            raise InputFileError(f"{name}: corrupt LAS header ({evlr_count} extended VLRs declared at byte {evlr_start} "
                                 f"of a {len(data)}-byte file)")
    if not header_size <= point_offset <= len(data):
        raise InputFileError(f"{name}: corrupt LAS header (point data at byte {point_offset}, header of {header_size} "
                             f"bytes, file of {len(data)})")
    if vlr_count * 54 > point_offset - header_size:
        raise InputFileError(f"{name}: corrupt LAS header ({vlr_count} VLRs declared in {point_offset - header_size} bytes)")
    needed, available = count * record_length, len(data) - point_offset
    compressed = bool(point_format & 0xC0)  # LAZ sets bit 7 (or bit 6) of the point format
    if not compressed:
        if needed > available:
            raise InputFileError(f"{name}: truncated LAS file ({count} points of {record_length} bytes declared, "
                                 f"{needed} bytes needed, {available} found)")
        return
    if needed > LAZ_MOST_COMPRESSION * max(available, 1):
        raise InputFileError(f"{name}: corrupt LAZ header ({count} points declared; {available} bytes cannot hold them)")
    _check_chunks(data, name, header_size, vlr_count, point_offset, count, record_length)


def _check_chunks(data: bytes, name: str, header_size: int, vlr_count: int, point_offset: int, count: int,
                  record_length: int) -> None:
    """LAZ: the chunk size (laszip VLR) may not exceed what the points need, nor the chunk
    table declare more chunks than the points fill (lazrs reserves memory for both before
    reading a point)."""
    chunk_size, at = None, header_size
    for _ in range(vlr_count):  # VLR: reserved u16, user id 16 s, record id u16, length u16, description 32 s
        if at + 54 > point_offset:
            raise InputFileError(f"{name}: corrupt LAS header (its VLRs run past the point data)")
        user_id = data[at + 2 : at + 18].rstrip(b"\0")
        record_id, length = struct.unpack_from("<HH", data, at + 18)
        if user_id == b"laszip encoded" and record_id == 22204 and length >= 16 and at + 54 + 16 <= point_offset:
            chunk_size = struct.unpack_from("<I", data, at + 54 + 12)[0]
        at += 54 + length
    if at > point_offset:
        raise InputFileError(f"{name}: corrupt LAS header (its VLRs run past the point data)")
    variable = chunk_size in (None, 0, 0xFFFFFFFF)  # no fixed size: chunks as the table says
    if not variable and chunk_size * record_length > max(LAZ_LARGEST_CHUNK, 2 * count * record_length):
        raise InputFileError(f"{name}: corrupt LAZ header (chunks of {chunk_size} points declared for {count} points)")
    if len(data) < point_offset + 8:
        return  # no chunk table pointer: lazrs reports the truncation
    table = struct.unpack_from("<q", data, point_offset)[0]
    if not point_offset < table <= len(data) - 8:
        return  # no table (-1), or one lazrs cannot reach: it reads the points in order or says what is wrong
    chunks = struct.unpack_from("<I", data, table + 4)[0]
    most = count + 1 if variable else -(-count // chunk_size) + 1
    if chunks > most:
        raise InputFileError(f"{name}: corrupt LAZ chunk table ({chunks} chunks declared for {count} points)")


def layout_for(points: np.ndarray) -> LasLayout:
    """A scale and offset for a cloud that has no template.

    The scale is the power of ten at or below `SCALE_SHARE` of the cloud's extent (its
    bounding box's longest side; of its largest |coordinate|, or 1, for a single
    point), the same on every axis; the offset is the bounding box's centre rounded to
    a multiple of the power of ten at or above the extent.

    Parameters
    ----------
    points : (N, 3) float64

    Returns
    -------
    LasLayout
        Point format 6, LAS 1.4.
    """
    low, high = points.min(axis=0), points.max(axis=0)  # (3,)
    extent = float(np.max(high - low))
    if not extent > 0:
        extent = max(float(np.max(np.abs(points))), 1.0)
    scale = 10.0 ** math.floor(math.log10(extent * SCALE_SHARE))
    step = 10.0 ** math.ceil(math.log10(extent))
    offsets = np.round((low + high) / 2 / step) * step
    return LasLayout(np.full(3, scale), offsets)


def template_layout(path: str | Path) -> LasLayout | None:
    """The layout of an existing LAS/LAZ file (its header only), or None when it is not one.

    Parameters
    ----------
    path : str or Path
        Any file; stdin (``-``) and files that are not LAS give None.

    Returns
    -------
    LasLayout or None
    """
    if str(path) == "-":
        return None
    try:
        with open(path, "rb") as handle:
            if not is_las(handle.read(len(LAS_MAGIC))):
                return None
    except OSError:
        return None
    laspy = _laspy()
    try:
        with laspy.open(str(path)) as reader:
            header = reader.header
    except Exception as err:  # a corrupt template: write with a chosen layout instead
        log.warning("%s: cannot read its LAS header (%s); choosing a scale and offset", path, _first_line(err))
        return None
    records = [*header.vlrs, *(getattr(header, "evlrs", None) or [])]
    projection = tuple(
        (vlr.user_id, vlr.record_id, vlr.description, bytes(vlr.record_data_bytes()))
        for vlr in records
        if vlr.user_id == PROJECTION_USER_ID
    )
    return LasLayout(
        scales=np.asarray(header.scales, dtype=np.float64),
        offsets=np.asarray(header.offsets, dtype=np.float64),
        point_format=int(header.point_format.id),
        version=str(header.version),
        projection=projection,
        wkt=bool(getattr(header.global_encoding, "wkt", False)),
    )


def _usable_layout(points: np.ndarray, layout: LasLayout | None) -> LasLayout:
    if layout is None:
        return layout_for(points)
    if layout.fits(points):
        return layout
    chosen = layout_for(points)
    moved = LasLayout(layout.scales, chosen.offsets, layout.point_format, layout.version, layout.projection, layout.wkt)
    if moved.fits(points):
        log.warning("the template's LAS offset leaves points out of range; keeping its scale with offset %s", moved.offsets)
        return moved
    log.warning("the template's LAS scale leaves points out of range; using scale %g", chosen.scales[0])
    return LasLayout(chosen.scales, chosen.offsets, layout.point_format, layout.version, layout.projection, layout.wkt)


def _fitted(values: np.ndarray, dim, key: str) -> np.ndarray:
    """A field's values as the dimension's type, or PointCloudError when they do not fit it."""
    kind = dim.kind.name  # SignedInteger, UnsignedInteger, FloatingPoint, BitField
    if kind == "FloatingPoint":
        return values
    bits = dim.num_bits
    low, high = (-(2 ** (bits - 1)), 2 ** (bits - 1) - 1) if kind == "SignedInteger" else (0, 2**bits - 1)
    in_range = values.size == 0 or (values.min() >= low and values.max() <= high)
    if not (in_range and np.all(values == np.round(values))):
        raise PointCloudError(f"field '{key}' does not fit the LAS dimension of that name (integers {low}..{high})")
    return values.astype(np.int64)


def _laspy():
    """laspy, a runtime dependency (imported here: `escape --help` does not load it)."""
    import laspy

    return laspy


def _first_line(err: Exception) -> str:
    text = str(err).strip()
    return text.splitlines()[0] if text else type(err).__name__
