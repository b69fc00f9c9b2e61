"""PLY point clouds: read ascii / binary little / big endian, write ascii or binary.

Only the ``vertex`` element is read: its ``x``, ``y``, ``z`` properties (any numeric
type) and its other scalar properties as fields. Other elements (faces, edges, ...)
and list properties are skipped, wherever they sit in the file.

The header must match the body: a body shorter than the header declares is
"truncated"; data after the last element (other than padding: line endings, zeros) is refused too, as
it means a wrong count in the header (checked unless elements with list properties
follow the vertices, whose end would take reading every list).
"""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass

import numpy as np

from escape_cli.errors import InputFileError
from escape_cli.io.common import (
    PADDING, Fields, counted, format_rows, pack_rows, printable, storage_dtype, tokens_to_float, trailing_data,
)

MAGIC_LINE = re.compile(rb"ply[ \t]*\r?\n")  # some writers leave blanks after the magic word
# The header is a few hundred bytes; give up looking for end_header after this much.
MAX_HEADER_BYTES = 1 << 20

SCALAR_TYPES = {
    "char": "i1", "int8": "i1",
    "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4",
    "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4",
    "double": "f8", "float64": "f8",
}  # fmt: skip
ENCODINGS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}


@dataclass(frozen=True)
class PlyProperty:
    """One property of an element; `count_type` is set for list properties."""

    name: str
    value_type: str  # numpy type code without byte order, e.g. "f4"
    count_type: str | None = None

    @property
    def is_list(self) -> bool:
        return self.count_type is not None


@dataclass
class PlyElement:
    """An element declaration: its name, how many rows, and their properties."""

    name: str
    count: int
    properties: list[PlyProperty]

    @property
    def has_lists(self) -> bool:
        return any(p.is_list for p in self.properties)

    def row_dtype(self, byte_order: str) -> np.dtype:
        """Structured dtype of one row (only for elements without list properties)."""
        return np.dtype([(f"p{i}", byte_order + p.value_type) for i, p in enumerate(self.properties)])


@dataclass
class PlyHeader:
    """The parsed header: encoding, elements in file order, and where the body starts."""

    encoding: str
    elements: list[PlyElement]
    body_offset: int


def is_ply(data: bytes) -> bool:
    """True when the bytes start like a PLY file: a first line ``ply`` (trailing blanks allowed)."""
    return MAGIC_LINE.match(data) is not None


def parse_ply(data: bytes, name: str) -> tuple[np.ndarray, Fields]:
    """Read the vertices of a PLY file.

    Parameters
    ----------
    data : bytes
        The whole file.
    name : str
        The file name, for messages.

    Returns
    -------
    xyz : (N, 3) float64
        Vertex coordinates, non-finite rows included.
    fields : dict of str to (N,) float64
        The vertex's other scalar properties (``red``, ``nx``, ``quality``, ...).

    Raises
    ------
    InputFileError
        Not a PLY file, a corrupt or truncated header or body, or no x/y/z vertex
        properties.
    """
    header = _parse_header(data, name)
    vertex_index = _vertex_element_index(header, name)
    if header.encoding == "ascii":
        columns = _read_ascii_vertex(data[header.body_offset :], header.elements, vertex_index, name)
    else:
        columns = _read_binary_vertex(data, header, vertex_index, name)
    xyz = np.column_stack([columns.pop(axis) for axis in ("x", "y", "z")]).astype(np.float64)
    return xyz, {key: value.astype(np.float64) for key, value in columns.items()}


def serialize_ply(
    points: np.ndarray, fields: Fields, *, binary: bool = True, coordinate_dtype=np.float32
) -> bytes:
    """A PLY file with one vertex element: x, y, z then one float32 property per field
    (float64 for a field float32 cannot hold, see `storage_dtype`).

    Parameters
    ----------
    points : (N, 3) float64
    fields : dict of str to (N,) float64
    binary : bool
        binary_little_endian when true, ascii otherwise.
    coordinate_dtype : numpy dtype
        float32 ("float" properties) or float64 ("double").

    Returns
    -------
    bytes
    """
    coordinate_dtype = np.dtype(coordinate_dtype)
    field_dtypes = [storage_dtype(values) for values in fields.values()]
    type_names = {np.dtype(np.float32): "float", np.dtype(np.float64): "double"}
    lines = [
        "ply",
        f"format {'binary_little_endian' if binary else 'ascii'} 1.0",
        "comment written by escape",
        f"element vertex {len(points)}",
        *(f"property {type_names[coordinate_dtype]} {axis}" for axis in "xyz"),
        *(f"property {type_names[dtype]} {field}" for field, dtype in zip(fields, field_dtypes)),
        "end_header",
    ]
    header = ("\n".join(lines) + "\n").encode("ascii")
    columns = [points[:, 0], points[:, 1], points[:, 2], *fields.values()]
    dtypes = [coordinate_dtype] * 3 + field_dtypes
    if not binary:
        return header + format_rows(columns, dtypes)
    return header + pack_rows(columns, dtypes)


def _parse_header(data: bytes, name: str) -> PlyHeader:
    if not is_ply(data):
        first = data[: data.find(b"\n")] if b"\n" in data[:64] else data[:20]
        raise InputFileError(f"{name}: not a PLY file (its first line is '{printable(first, 20)}', not 'ply')")
    end = data.find(b"\nend_header", 0, MAX_HEADER_BYTES) + 1  # at the start of a line
    if end == 0:
        raise InputFileError(f"{name}: truncated or corrupt PLY header (no end_header line)")
    newline = data.find(b"\n", end)
    body_offset = len(data) if newline < 0 else newline + 1
    try:
        text = data[:end].decode("ascii")
    except UnicodeDecodeError:
        raise InputFileError(f"{name}: corrupt PLY header (bytes that are not text)") from None
    encoding = None
    elements: list[PlyElement] = []
    for line_number, line in enumerate(text.splitlines()[1:], start=2):
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        keyword = words[0]
        if keyword == "format" and len(words) == 3 and words[1] in ENCODINGS:
            encoding = words[1]
        elif keyword == "element" and len(words) == 3 and words[2].isdigit():
            elements.append(PlyElement(words[1], int(words[2]), []))
        elif keyword == "property" and elements:
            elements[-1].properties.append(_parse_property(words, name, line_number))
        else:
            raise InputFileError(f"{name}: corrupt PLY header at line {line_number}: '{printable(line.strip())}'")
    if encoding is None:
        raise InputFileError(f"{name}: corrupt PLY header (no valid 'format' line)")
    return PlyHeader(encoding, elements, body_offset)


def _parse_property(words: list[str], name: str, line_number: int) -> PlyProperty:
    if len(words) == 3 and words[1] in SCALAR_TYPES:
        return PlyProperty(words[2], SCALAR_TYPES[words[1]])
    if len(words) == 5 and words[1] == "list" and words[2] in SCALAR_TYPES and words[3] in SCALAR_TYPES:
        return PlyProperty(words[4], SCALAR_TYPES[words[3]], SCALAR_TYPES[words[2]])
    raise InputFileError(f"{name}: corrupt PLY header at line {line_number}: bad property '{printable(' '.join(words))}'")


def _vertex_element_index(header: PlyHeader, name: str) -> int:
    for index, element in enumerate(header.elements):
        if element.name == "vertex":
            scalar_names = {p.name for p in element.properties if not p.is_list}
            missing = [axis for axis in "xyz" if axis not in scalar_names]
            if missing:
                raise InputFileError(f"{name}: PLY vertex element has no {'/'.join(missing)} property")
            return index
    raise InputFileError(f"{name}: PLY file has no vertex element")


def _read_ascii_vertex(body: bytes, elements: list[PlyElement], vertex_index: int, name: str) -> Fields:
    """Scalar vertex properties of an ascii body, skipping the elements before it."""
    tokens = body.rstrip(PADDING).split()
    position = 0
    for element in elements[:vertex_index]:
        position = _skip_ascii_element(tokens, position, element, name)
    vertex = elements[vertex_index]
    if not vertex.has_lists:
        width = len(vertex.properties)
        end = position + vertex.count * width
        if end > len(tokens):
            found = max(0, (len(tokens) - position) // max(width, 1))
            raise InputFileError(f"{name}: truncated PLY body ({vertex.count} vertices declared, {found} found)")
        _check_ascii_end(tokens, end, elements, vertex_index, name)
        values = tokens_to_float(tokens[position:end], name, "vertex data").reshape(vertex.count, width)
        return {p.name: values[:, i] for i, p in enumerate(vertex.properties)}
    scalar_positions: list[int] = []  # token index of each row's scalar values, row-major
    for _ in range(vertex.count):
        for prop in vertex.properties:
            if prop.is_list:
                position += 1 + _ascii_list_length(tokens, position, name)
            else:
                scalar_positions.append(position)
                position += 1
    if position > len(tokens):
        raise InputFileError(f"{name}: truncated PLY body (vertex data cut off)")
    _check_ascii_end(tokens, position, elements, vertex_index, name)
    scalars = [p for p in vertex.properties if not p.is_list]
    picked = [tokens[i] for i in scalar_positions]
    values = tokens_to_float(picked, name, "vertex data").reshape(vertex.count, len(scalars))
    return {p.name: values[:, i] for i, p in enumerate(scalars)}


def _check_ascii_end(tokens: list[bytes], position: int, elements: list[PlyElement], vertex_index: int, name: str) -> None:
    """Refuse values after the last element (`position`: the token after the vertices)."""
    later = elements[vertex_index + 1 :]
    if any(element.has_lists for element in later):
        return  # finding the end would take walking every list
    end = position + sum(element.count * len(element.properties) for element in later)
    if end > len(tokens):
        cut = next(e.name for e in later)
        raise InputFileError(f"{name}: truncated PLY body ('{cut}' element cut off)")
    if end < len(tokens):
        raise InputFileError(
            f"{name}: {counted(len(tokens) - end, 'value')} after the end of the PLY body the header declares "
            f"({_declared(elements)}); is a count in the header wrong?"
        )


def _check_binary_end(data: bytes, position: int, header: PlyHeader, vertex_index: int, byte_order: str, name: str) -> None:
    """Refuse bytes (other than padding: line endings, zeros) after the last element (`position`: the byte after the vertices)."""
    later = header.elements[vertex_index + 1 :]
    if any(element.has_lists for element in later):
        return  # finding the end would take walking every list
    end = position + sum(element.count * element.row_dtype(byte_order).itemsize for element in later)
    if end > len(data):
        cut = next(e.name for e in later)
        raise InputFileError(f"{name}: truncated PLY body ('{cut}' element cut off)")
    extra = trailing_data(data, end)
    if extra:
        raise InputFileError(
            f"{name}: {counted(extra, 'byte')} after the end of the PLY body the header declares "
            f"({_declared(header.elements)}); is a count in the header wrong?"
        )


def _declared(elements: list[PlyElement]) -> str:
    return ", ".join(f"{element.name} {element.count}" for element in elements)


def _skip_ascii_element(tokens: list[bytes], position: int, element: PlyElement, name: str) -> int:
    if not element.has_lists:
        position += element.count * len(element.properties)
    else:
        for _ in range(element.count):
            for prop in element.properties:
                position += 1 + (_ascii_list_length(tokens, position, name) if prop.is_list else 0)
    if position > len(tokens):
        raise InputFileError(f"{name}: truncated PLY body ('{element.name}' element cut off)")
    return position


def _ascii_list_length(tokens: list[bytes], position: int, name: str) -> int:
    try:
        length = int(tokens[position])
    except IndexError:
        raise InputFileError(f"{name}: truncated PLY body (list property cut off)") from None
    except ValueError:
        shown = printable(tokens[position], 20)
        raise InputFileError(f"{name}: corrupt PLY body (list length '{shown}' is not an integer)") from None
    if length < 0:
        raise InputFileError(f"{name}: corrupt PLY body (negative list length)")
    return length


def _read_binary_vertex(data: bytes, header: PlyHeader, vertex_index: int, name: str) -> Fields:
    """Scalar vertex properties of a binary body, skipping the elements before it."""
    byte_order = ENCODINGS[header.encoding]
    position = header.body_offset
    for element in header.elements[:vertex_index]:
        position = _skip_binary_element(data, position, element, byte_order, name)
    vertex = header.elements[vertex_index]
    if not vertex.has_lists:
        row = vertex.row_dtype(byte_order)
        needed = vertex.count * row.itemsize
        available = len(data) - position
        if needed > available:
            raise InputFileError(
                f"{name}: truncated PLY body ({vertex.count} vertices declared, "
                f"{needed} bytes needed, {max(available, 0)} found)"
            )
        _check_binary_end(data, position + needed, header, vertex_index, byte_order, name)
        table = np.frombuffer(data, dtype=row, count=vertex.count, offset=position)
        return {p.name: table[f"p{i}"] for i, p in enumerate(vertex.properties)}
    scalars = [p for p in vertex.properties if not p.is_list]
    rows = []
    for _ in range(vertex.count):
        values = []
        for prop in vertex.properties:
            if prop.is_list:
                position = _skip_binary_list(data, position, prop, byte_order, name)
            else:
                values.append(_unpack(data, position, byte_order + prop.value_type, name))
                position += np.dtype(prop.value_type).itemsize
        rows.append(values)
    if position > len(data):
        raise InputFileError(f"{name}: truncated PLY body (vertex data cut off)")
    _check_binary_end(data, position, header, vertex_index, byte_order, name)
    table = np.array(rows, dtype=np.float64).reshape(vertex.count, len(scalars))
    return {p.name: table[:, i] for i, p in enumerate(scalars)}


def _skip_binary_element(data: bytes, position: int, element: PlyElement, byte_order: str, name: str) -> int:
    if not element.has_lists:
        position += element.count * element.row_dtype(byte_order).itemsize
    else:
        for _ in range(element.count):
            for prop in element.properties:
                if prop.is_list:
                    position = _skip_binary_list(data, position, prop, byte_order, name)
                else:
                    position += np.dtype(prop.value_type).itemsize
    if position > len(data):
        raise InputFileError(f"{name}: truncated PLY body ('{element.name}' element cut off)")
    return position


def _skip_binary_list(data: bytes, position: int, prop: PlyProperty, byte_order: str, name: str) -> int:
    length = int(_unpack(data, position, byte_order + prop.count_type, name))
    if length < 0:
        raise InputFileError(f"{name}: corrupt PLY body (negative list length)")
    return position + np.dtype(prop.count_type).itemsize + length * np.dtype(prop.value_type).itemsize


_STRUCT_CODES = {"i1": "b", "u1": "B", "i2": "h", "u2": "H", "i4": "i", "u4": "I", "f4": "f", "f8": "d"}


def _unpack(data: bytes, position: int, numpy_code: str, name: str) -> float:
    try:
        return struct.unpack_from(numpy_code[0] + _STRUCT_CODES[numpy_code[1:]], data, position)[0]
    except struct.error:
        raise InputFileError(f"{name}: truncated PLY body (data cut off)") from None
