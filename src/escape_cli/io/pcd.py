"""PCD point clouds (PCL's format): read ascii / binary / binary_compressed, write ascii or binary.

The header gives FIELDS with their SIZE, TYPE (F float, I signed, U unsigned) and
COUNT. ``x``, ``y``, ``z`` become the coordinates; every other field becomes one or
more scalar fields: a field with COUNT c > 1 gives ``name_0`` ... ``name_{c-1}``;
packed colours ``rgb``/``rgba`` are unpacked into ``red``, ``green``, ``blue`` (and
``alpha``); PCL's ``_`` padding fields are dropped.

``binary`` bodies store points one after the other (array of structs);
``binary_compressed`` bodies are LZF-compressed and store each field for all points
in turn (struct of arrays), after two little-endian uint32: compressed and
uncompressed size. ``ascii`` bodies may separate values with blanks or commas.

Field names are matched case-insensitively for the coordinates (PDAL writes ``X Y Z``).
The header must match the body: fewer points than declared is "truncated", more data
than declared (other than padding: line endings, zeros) is refused as well.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from escape_cli.errors import InputFileError
from escape_cli.io.common import (
    PADDING, Fields, counted, format_rows, pack_rows, printable, storage_dtype, tokens_to_float, trailing_data,
)
from escape_cli.io.lzf import LZFError, lzf_decompress

HEADER_KEYWORDS = (
    "VERSION", "FIELDS", "COLUMNS", "SIZE", "TYPE", "COUNT", "WIDTH", "HEIGHT", "VIEWPOINT", "POINTS", "DATA",
)  # fmt: skip
DATA_KINDS = ("ascii", "binary", "binary_compressed")
MAX_HEADER_LINES = 64
VALID_TYPES = {("F", 4), ("F", 8), ("I", 1), ("I", 2), ("I", 4), ("I", 8), ("U", 1), ("U", 2), ("U", 4), ("U", 8)}
PACKED_COLOUR_FIELDS = ("rgb", "rgba")
# One 3-byte LZF back-reference yields at most 264 bytes: no stream expands more than 88x.
LZF_MAX_EXPANSION = 88


@dataclass(frozen=True)
class PcdField:
    """One FIELDS entry with its SIZE, TYPE and COUNT."""

    name: str
    size: int
    type_code: str  # "F", "I" or "U"
    count: int

    @property
    def dtype(self) -> np.dtype:
        """Little-endian numpy dtype of one value."""
        kind = {"F": "f", "I": "i", "U": "u"}[self.type_code]
        return np.dtype(f"<{kind}{self.size}")


@dataclass(frozen=True)
class PcdHeader:
    """The parsed header: fields, number of points, body encoding and offset."""

    fields: list[PcdField]
    points: int
    data_kind: str
    body_offset: int

    @property
    def values_per_point(self) -> int:
        return sum(f.count for f in self.fields)

    @property
    def bytes_per_point(self) -> int:
        return sum(f.size * f.count for f in self.fields)


def is_pcd(data: bytes) -> bool:
    """True when the first non-empty line looks like a PCD header line."""
    first_line = data.lstrip()[:64].split(b"\n", 1)[0].strip()
    return first_line.startswith((b"# .PCD", b"VERSION", b"FIELDS"))


def parse_pcd(data: bytes, name: str) -> tuple[np.ndarray, Fields]:
    """Read the points of a PCD file.

    Parameters
    ----------
    data : bytes
        The whole file.
    name : str
        The file name, for messages.

    Returns
    -------
    xyz : (N, 3) float64
        Coordinates, non-finite rows (organised scans) included.
    fields : dict of str to (N,) float64
        The other fields, one scalar array each (see the module docstring).

    Raises
    ------
    InputFileError
        Corrupt or truncated header or body, or no x/y/z fields.
    """
    header = _parse_header(data, name)
    body = data[header.body_offset :]
    if header.data_kind == "ascii":
        columns = _read_ascii(body, header, name)
    elif header.data_kind == "binary":
        columns = _read_binary(body, header, name)
    else:
        columns = _read_binary_compressed(body, header, name)
    xyz = np.column_stack([columns[axis][:, 0] for axis in ("x", "y", "z")]).astype(np.float64)
    fields: Fields = {}
    for field in header.fields:
        values = columns[field.name]  # (N, count)
        if field.name in ("x", "y", "z") or field.name.split("#")[0] == "_":
            continue  # coordinates, or PCL's padding
        if field.name in PACKED_COLOUR_FIELDS and field.size == 4 and field.count == 1:
            fields.update(_unpack_colour(values[:, 0], field, with_alpha=field.name == "rgba"))
        elif field.count == 1:
            fields[field.name] = values[:, 0].astype(np.float64)
        else:
            for i in range(field.count):
                fields[f"{field.name}_{i}"] = values[:, i].astype(np.float64)
    return xyz, fields


def serialize_pcd(
    points: np.ndarray, fields: Fields, *, binary: bool = True, coordinate_dtype=np.float32
) -> bytes:
    """A PCD v0.7 file: x, y, z then one float32 field per extra field (float64 where float32
    cannot hold it, see `storage_dtype`); unorganised.

    Parameters
    ----------
    points : (N, 3) float64
    fields : dict of str to (N,) float64
    binary : bool
        DATA binary when true, DATA ascii otherwise.
    coordinate_dtype : numpy dtype
        float32 (SIZE 4) or float64 (SIZE 8) coordinates.

    Returns
    -------
    bytes
    """
    dtypes = [np.dtype(coordinate_dtype)] * 3 + [storage_dtype(values) for values in fields.values()]
    names = ["x", "y", "z", *fields]
    count = len(points)
    header = (
        "# .PCD v0.7 - Point Cloud Data file format\n"
        "VERSION 0.7\n"
        f"FIELDS {' '.join(names)}\n"
        f"SIZE {' '.join(str(d.itemsize) for d in dtypes)}\n"
        f"TYPE {' '.join('F' for _ in dtypes)}\n"
        f"COUNT {' '.join('1' for _ in dtypes)}\n"
        f"WIDTH {count}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {count}\n"
        f"DATA {'binary' if binary else 'ascii'}\n"
    ).encode("ascii")
    columns = [points[:, 0], points[:, 1], points[:, 2], *fields.values()]
    if not binary:
        return header + format_rows(columns, dtypes)
    return header + pack_rows(columns, dtypes)


def _parse_header(data: bytes, name: str) -> PcdHeader:
    entries: dict[str, list[str]] = {}
    position = 0
    for _ in range(MAX_HEADER_LINES):
        if position >= len(data):
            break
        newline = data.find(b"\n", position)
        end = len(data) if newline < 0 else newline
        raw_line = data[position:end]
        position = end + 1
        try:
            line = raw_line.decode("ascii").strip()
        except UnicodeDecodeError:
            raise InputFileError(f"{name}: corrupt PCD header (bytes that are not text)") from None
        if not line or line.startswith("#"):
            continue
        keyword, *values = line.split()
        keyword = keyword.upper()
        if keyword not in HEADER_KEYWORDS:
            raise InputFileError(f"{name}: corrupt PCD header: unexpected line '{printable(line)}'")
        entries["FIELDS" if keyword == "COLUMNS" else keyword] = values
        if keyword == "DATA":
            return _header_from_entries(entries, position, name)
    raise InputFileError(f"{name}: truncated or corrupt PCD header (no DATA line)")


def _header_from_entries(entries: dict[str, list[str]], body_offset: int, name: str) -> PcdHeader:
    def numbers(key: str, default: list[int] | None = None) -> list[int]:
        if key not in entries:
            if default is None:
                raise InputFileError(f"{name}: corrupt PCD header (no {key} line)")
            return default
        try:
            return [int(v) for v in entries[key]]
        except ValueError:
            raise InputFileError(f"{name}: corrupt PCD header ({key} {printable(' '.join(entries[key]), 40)})") from None

    def number(key: str, default: int | None = None) -> int:
        values = numbers(key, None if default is None else [default])
        if len(values) != 1 or values[0] < 0:
            raise InputFileError(f"{name}: corrupt PCD header ({key} {printable(' '.join(entries[key]), 40)})")
        return values[0]

    data_kind = entries["DATA"][0].lower() if entries["DATA"] else ""
    if data_kind not in DATA_KINDS:
        raise InputFileError(f"{name}: unsupported PCD DATA '{printable(data_kind, 40)}' (ascii, binary, binary_compressed)")
    names = entries.get("FIELDS")
    if not names:
        raise InputFileError(f"{name}: corrupt PCD header (no FIELDS line)")
    n_fields = len(names)
    default_sizes = [4] * n_fields if data_kind == "ascii" else None
    sizes = numbers("SIZE", default_sizes)
    types = entries.get("TYPE", ["F"] * n_fields if data_kind == "ascii" else None)
    if types is None:
        raise InputFileError(f"{name}: corrupt PCD header (no TYPE line)")
    counts = numbers("COUNT", [1] * n_fields)
    for key, values in (("SIZE", sizes), ("TYPE", types), ("COUNT", counts)):
        if len(values) != n_fields:
            raise InputFileError(f"{name}: corrupt PCD header ({key} has {len(values)} entries, FIELDS has {n_fields})")
    fields = []
    for index, (field_name, size, type_code, count) in enumerate(zip(names, sizes, types, counts)):
        type_code = type_code.upper()
        if (type_code, size) not in VALID_TYPES or count < 1:
            raise InputFileError(
                f"{name}: corrupt PCD header (field {printable(field_name, 40)}: "
                f"TYPE {printable(type_code, 8)} SIZE {size} COUNT {count})"
            )
        # repeated names (PCL pads with several "_" fields) get a suffix to stay apart
        unique_name = field_name if field_name not in names[:index] else f"{field_name}#{index}"
        fields.append(PcdField(unique_name, size, type_code, count))
    fields = _lower_case_coordinates(fields)
    for axis in ("x", "y", "z"):
        if not any(f.name == axis and f.count == 1 for f in fields):
            raise InputFileError(f"{name}: PCD file has no '{axis}' field")
    points = number("POINTS") if "POINTS" in entries else number("WIDTH") * number("HEIGHT", 1)
    return PcdHeader(fields, points, data_kind, body_offset)


def _lower_case_coordinates(fields: list[PcdField]) -> list[PcdField]:
    """Fields ``X``, ``Y``, ``Z`` (any case) become ``x``, ``y``, ``z`` where no lower-case one exists."""
    names = {f.name for f in fields}
    renamed = []
    for field in fields:
        lower = field.name.lower()
        if lower in ("x", "y", "z") and field.name != lower and lower not in names:
            names.add(lower)
            field = PcdField(lower, field.size, field.type_code, field.count)
        renamed.append(field)
    return renamed


def _read_ascii(body: bytes, header: PcdHeader, name: str) -> dict[str, np.ndarray]:
    tokens = body.rstrip(PADDING).replace(b",", b" ").split()
    width = header.values_per_point
    expected = header.points * width
    if len(tokens) < expected:
        raise InputFileError(
            f"{name}: truncated PCD body ({header.points} points declared, {len(tokens) // width} found)"
        )
    if len(tokens) > expected:
        raise InputFileError(
            f"{name}: {counted(len(tokens) - expected, 'value')} after the {header.points} points the header declares "
            f"({width} values each); is its POINTS count wrong?"
        )
    table = tokens_to_float(tokens, name, "point data").reshape(header.points, width)
    columns: dict[str, np.ndarray] = {}
    start = 0
    for field in header.fields:
        values = table[:, start : start + field.count]
        start += field.count
        if field.name in PACKED_COLOUR_FIELDS and field.size == 4:
            # ascii stores the packed bits as a float (TYPE F) or an integer (TYPE U/I)
            values = values.astype(np.float32).view(np.uint32) if field.type_code == "F" else values.astype(np.uint32)
        columns[field.name] = values
    return columns


def _read_binary(body: bytes, header: PcdHeader, name: str) -> dict[str, np.ndarray]:
    row = np.dtype([(f"f{i}", f.dtype, (f.count,)) for i, f in enumerate(header.fields)])
    needed = header.points * row.itemsize
    if len(body) < needed:
        raise InputFileError(
            f"{name}: truncated PCD body ({header.points} points declared, {needed} bytes needed, {len(body)} found)"
        )
    _check_end(body, needed, header, name)
    table = np.frombuffer(body, dtype=row, count=header.points)
    columns: dict[str, np.ndarray] = {}
    for i, field in enumerate(header.fields):
        columns[field.name] = table[f"f{i}"].reshape(header.points, field.count)
    return columns


def _read_binary_compressed(body: bytes, header: PcdHeader, name: str) -> dict[str, np.ndarray]:
    if len(body) < 8:
        raise InputFileError(f"{name}: truncated PCD body (no compressed-size words)")
    compressed_size, uncompressed_size = struct.unpack_from("<II", body, 0)
    needed = header.points * header.bytes_per_point
    if uncompressed_size != needed:
        raise InputFileError(
            f"{name}: corrupt PCD body ({uncompressed_size} uncompressed bytes announced, "
            f"{header.points} points need {needed})"
        )
    if uncompressed_size > LZF_MAX_EXPANSION * compressed_size + 64:
        raise InputFileError(
            f"{name}: corrupt PCD body ({compressed_size} compressed bytes cannot hold {uncompressed_size})"
        )
    if len(body) - 8 < compressed_size:
        raise InputFileError(
            f"{name}: truncated PCD body ({compressed_size} compressed bytes announced, {len(body) - 8} found)"
        )
    _check_end(body, 8 + compressed_size, header, name)
    try:
        raw = lzf_decompress(body[8 : 8 + compressed_size], uncompressed_size) if needed else b""
    except LZFError as err:
        raise InputFileError(f"{name}: corrupt compressed PCD body ({err})") from None
    columns: dict[str, np.ndarray] = {}
    offset = 0
    for field in header.fields:  # struct of arrays: one block per field
        values = np.frombuffer(raw, dtype=field.dtype, count=header.points * field.count, offset=offset)
        offset += values.nbytes
        columns[field.name] = values.reshape(header.points, field.count)
    return columns


def _check_end(body: bytes, end: int, header: PcdHeader, name: str) -> None:
    """Refuse bytes (other than padding: line endings, zeros) after the body the header declares."""
    extra = trailing_data(body, end)
    if extra:
        raise InputFileError(
            f"{name}: {counted(extra, 'byte')} after the {header.points} points the header declares; is its POINTS count wrong?"
        )


def _unpack_colour(packed: np.ndarray, field: PcdField, *, with_alpha: bool) -> Fields:
    """Split packed 0xAARRGGBB colours (stored as float or uint32 bits) into channels."""
    bits = np.ascontiguousarray(packed)
    if bits.dtype != np.uint32:
        bits = bits.astype(field.dtype).view(np.uint32) if field.type_code == "F" else bits.astype(np.uint32)
    channels = {
        "red": (bits >> 16) & 0xFF,
        "green": (bits >> 8) & 0xFF,
        "blue": bits & 0xFF,
    }
    if with_alpha:
        channels["alpha"] = (bits >> 24) & 0xFF
    return {key: value.astype(np.float64) for key, value in channels.items()}
