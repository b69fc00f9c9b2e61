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
        las = laspy.read(io.BytesIO(data))
    except Exception as err:  # laspy raises LaspyException, ValueError, struct/lazrs errors on bad bytes
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
