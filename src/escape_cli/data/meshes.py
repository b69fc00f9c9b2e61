"""Triangle meshes from OBJ, OFF, STL (ascii and binary) and PLY (faces or tristrips).

`read_mesh(path)` returns plain arrays: (V, 3) float64 vertices and (F, 3) int64
triangles. Polygons are split into fans; PLY ``tristrips`` (with -1 restarts) are
triangulated with alternating winding; degenerate triangles (a repeated vertex) are
dropped. Only geometry is read: normals, texture coordinates, colours and materials
are ignored. Text files may have CRLF line endings and a byte order mark; OBJ
comments and backslash continuations, OFF's ST/C/N variants, and PLY faces of either
byte order, before or after the vertices, beside other properties, with their index
list named ``vertex_indices``, ``vertex_index`` or alone, are read. Errors are
`InputFileError` with the file named.
"""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

from escape_cli.errors import InputFileError

MESH_SUFFIXES = (".obj", ".off", ".stl", ".ply")
"""File endings read as meshes (a PLY without faces is a point cloud)."""
MAX_PLY_HEADER = 1 << 24
"""The most bytes `ply_has_faces` reads looking for a PLY header's end."""


@dataclass(frozen=True)
class Mesh:
    """A triangle mesh.

    Attributes
    ----------
    vertices : (V, 3) float64
    triangles : (F, 3) int64, rows of `vertices`.
    note : str
        How the faces were read ("triangles", "polygons split into fans", "tristrips
        triangulated").
    """

    vertices: np.ndarray
    triangles: np.ndarray
    note: str = "triangles"


def read_mesh(path: str | Path) -> Mesh:
    """Read a triangle mesh; the format comes from the extension.

    Raises
    ------
    InputFileError
        Unreadable file, unknown extension, corrupt content, or no face.
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as err:
        raise InputFileError(f"{path}: cannot read: {err.strerror or err}") from None
    suffix = path.suffix.lower()
    readers = {".obj": _parse_obj, ".off": _parse_off, ".stl": _parse_stl, ".ply": _parse_ply_mesh}
    if suffix not in readers:
        raise InputFileError(f"{path}: not a mesh file (expected {', '.join(MESH_SUFFIXES)})")
    try:
        if suffix == ".ply":  # the PLY parser names the file itself
            vertices, triangles, note = _parse_ply_mesh(data, str(path))
        else:
            vertices, triangles, note = readers[suffix](data)
    except InputFileError as err:
        raise InputFileError(str(err) if suffix == ".ply" else f"{path}: {err}") from None
    except (ValueError, IndexError, struct.error, UnicodeDecodeError) as err:
        raise InputFileError(f"{path}: corrupt {suffix[1:].upper()} file ({err})") from None
    try:
        return _checked(vertices, triangles, note)
    except InputFileError as err:
        raise InputFileError(f"{path}: {err}") from None


def ply_has_faces(path: str | Path) -> bool:
    """True when a PLY file declares a non-empty ``face`` or ``tristrips`` element."""
    from escape_cli.io.ply import _parse_header

    path = Path(path)
    head = b""
    try:
        with path.open("rb") as fh:
            while b"end_header" not in head and len(head) < MAX_PLY_HEADER:  # long headers (comments, obj_info)
                chunk = fh.read(1 << 16)
                if not chunk:
                    break
                head += chunk
    except OSError:
        return False
    if b"end_header" not in head:
        return False
    try:
        header = _parse_header(head, str(path))
    except InputFileError:
        return False
    return any(e.name in ("face", "tristrips") and e.count > 0 for e in header.elements)


def _checked(vertices: np.ndarray, triangles: np.ndarray, note: str) -> Mesh:
    vertices = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    triangles = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    if len(triangles) == 0:
        raise InputFileError("no faces")
    if triangles.min() < 0 or triangles.max() >= len(vertices):
        raise InputFileError(f"a face refers to a vertex that does not exist ({len(vertices)} vertices)")
    distinct = (triangles[:, 0] != triangles[:, 1]) & (triangles[:, 1] != triangles[:, 2]) & (triangles[:, 0] != triangles[:, 2])
    triangles = triangles[distinct]
    if len(triangles) == 0:
        raise InputFileError("every face is degenerate (a repeated vertex)")
    return Mesh(vertices, triangles, note)


def _text(data: bytes) -> str:
    """A text mesh file's characters: UTF-8 (other bytes replaced), a leading byte order mark dropped."""
    return data.decode("utf-8-sig", errors="replace")


def _fans(polygons: list[list[int]]) -> tuple[np.ndarray, bool]:
    """Triangles of polygons split into fans (first vertex shared); whether any had more than 3."""
    out, split = [], False
    for poly in polygons:
        if len(poly) < 3:
            continue
        split |= len(poly) > 3
        for i in range(1, len(poly) - 1):
            out.append((poly[0], poly[i], poly[i + 1]))
    return np.array(out, dtype=np.int64).reshape(-1, 3), split


# --------------------------------------------------------------------------- OBJ


def _obj_lines(text: str) -> Iterator[str]:
    """The statements of an OBJ file: comments (from ``#``) cut, lines ending in a backslash joined to the next."""
    pending = ""
    for line in text.splitlines():
        line = line.split("#", 1)[0]
        stripped = line.rstrip()
        if stripped.endswith("\\"):
            pending += stripped[:-1] + " "
            continue
        yield pending + line
        pending = ""
    if pending:
        yield pending


def _parse_obj(data: bytes) -> tuple[np.ndarray, np.ndarray, str]:
    vertices: list[tuple[float, float, float]] = []
    polygons: list[list[int]] = []
    for line in _obj_lines(_text(data)):
        words = line.split()
        if not words:
            continue
        if words[0] == "v":
            if len(words) < 4:
                raise InputFileError(f"a vertex line has {len(words) - 1} numbers: {line[:60]!r}")
            vertices.append((float(words[1]), float(words[2]), float(words[3])))
        elif words[0] == "f":
            poly = []
            for word in words[1:]:
                index = int(word.split("/")[0])
                poly.append(index - 1 if index > 0 else len(vertices) + index)  # 1-based or relative
            polygons.append(poly)
    if not vertices:
        raise InputFileError("no vertices ('v' lines)")
    triangles, split = _fans(polygons)
    return np.array(vertices), triangles, "polygons split into fans" if split else "triangles"


# --------------------------------------------------------------------------- OFF


_OFF_KEYWORD = re.compile(r"(ST)?C?N?OFF")
"""The OFF keywords read: texture coordinates (ST), colours (C) and normals (N) follow a vertex's x y z."""


def _parse_off(data: bytes) -> tuple[np.ndarray, np.ndarray, str]:
    lines = [ln.split("#")[0].split() for ln in _text(data).splitlines()]
    lines = [words for words in lines if words]
    keyword = lines[0][0].upper() if lines else ""
    kind = keyword.rstrip("0123456789")
    if not _OFF_KEYWORD.fullmatch(kind):
        if "OFF" in keyword:
            raise InputFileError(f"unsupported OFF variant {lines[0][0]!r}")
        raise InputFileError("not an OFF file (no OFF keyword)")
    if len(lines[0]) > 1 and lines[0][1].upper() == "BINARY":
        raise InputFileError("binary OFF is not read; convert it to ascii OFF (e.g. with meshlab or trimesh)")
    counts = lines[0][1:] if len(lines[0]) > 1 else lines[1]
    if keyword != kind:  # "OFF490 518 0": ModelNet's missing line break
        counts = [keyword[len(kind):], *lines[0][1:]]
    first = 1 if len(lines[0]) > 1 or keyword != kind else 2
    n_vertices, n_faces = int(counts[0]), int(counts[1])
    if n_vertices < 0 or n_faces < 0 or first + n_vertices + n_faces > len(lines):
        raise InputFileError(f"truncated: {n_vertices} vertices and {n_faces} faces declared, {len(lines) - first} lines")
    vertices = np.array([words[:3] for words in lines[first : first + n_vertices]], dtype=np.float64)
    polygons = []
    for words in lines[first + n_vertices : first + n_vertices + n_faces]:
        count = int(words[0])
        if count < 0 or len(words) < 1 + count:
            raise InputFileError(f"a face line declares {count} vertices and has {len(words) - 1} numbers")
        polygons.append([int(t) for t in words[1 : 1 + count]])  # colour values after them are ignored
    triangles, split = _fans(polygons)
    return vertices, triangles, "polygons split into fans" if split else "triangles"


# --------------------------------------------------------------------------- STL

_STL_RECORD = np.dtype([("normal", "<f4", 3), ("v", "<f4", (3, 3)), ("attr", "<u2")])


def _parse_stl(data: bytes) -> tuple[np.ndarray, np.ndarray, str]:
    if len(data) >= 84:
        (count,) = struct.unpack_from("<I", data, 80)
        if 84 + 50 * count == len(data):  # binary (its header may start with "solid" too)
            records = np.frombuffer(data, dtype=_STL_RECORD, count=count, offset=84)
            return _soup(records["v"].astype(np.float64))
    text = _text(data)
    if not text.lstrip().lower().startswith("solid"):
        raise InputFileError("neither ascii STL ('solid') nor binary STL (size does not match its triangle count)")
    coords = [line.split()[1:4] for line in text.splitlines() if line.strip().lower().startswith("vertex")]
    if len(coords) % 3:
        raise InputFileError(f"{len(coords)} vertex lines, not a multiple of 3")
    corners = np.array(coords, dtype=np.float64).reshape(-1, 3, 3)
    return _soup(corners)


def _soup(corners: np.ndarray) -> tuple[np.ndarray, np.ndarray, str]:
    """(F, 3, 3) triangle corners -> (3F, 3) vertices and (F, 3) triangles of consecutive rows."""
    return corners.reshape(-1, 3), np.arange(3 * len(corners), dtype=np.int64).reshape(-1, 3), "triangles"


# --------------------------------------------------------------------------- PLY


def _parse_ply_mesh(data: bytes, name: str) -> tuple[np.ndarray, np.ndarray, str]:
    from escape_cli.io.ply import _parse_header, parse_ply

    xyz, _fields = parse_ply(data, name)
    header = _parse_header(data, name)
    try:
        lists = _ply_face_lists(data, header)
    except (ValueError, IndexError, InputFileError) as err:
        raise InputFileError(f"{name}: corrupt PLY faces ({err})") from None
    faces = lists.get("face")
    if "tristrips" in lists and not any(len(row) >= 3 for row in faces or []):  # (an empty face element beside them)
        return xyz, _strip_triangles(lists["tristrips"]), "tristrips triangulated"
    if faces is not None:
        triangles, split = _fans(faces)
        return xyz, triangles, "polygons split into fans" if split else "triangles"
    raise InputFileError(f"{name}: no face or tristrips element")


INDEX_LISTS = ("vertex_indices", "vertex_index")
"""The names of a PLY face's list of vertex indices (the standard's and a common variant)."""


def _index_list(element) -> int | None:
    """Which property of a face or tristrips element holds its vertex indices (None: none of them).

    The list named `INDEX_LISTS`, else the element's only list property (whatever it is called).
    """
    lists = [i for i, prop in enumerate(element.properties) if prop.is_list]
    named = [i for i in lists if element.properties[i].name in INDEX_LISTS]
    if named:
        return named[0]
    return lists[0] if len(lists) == 1 else None


def _strip_triangles(strips: list[list[int]]) -> np.ndarray:
    """Triangles of triangle strips; -1 restarts a strip; every other triangle flipped to keep the winding."""
    out = []
    for strip in strips:
        run: list[int] = []
        for index in strip + [-1]:
            if index < 0:
                for i in range(len(run) - 2):
                    a, b, c = run[i], run[i + 1], run[i + 2]
                    out.append((a, b, c) if i % 2 == 0 else (b, a, c))
                run = []
            else:
                run.append(index)
    return np.array(out, dtype=np.int64).reshape(-1, 3)


def _ply_face_lists(data: bytes, header) -> dict[str, list[list[int]]]:
    """The index lists of the ``face`` and ``tristrips`` elements, walking the body element by element."""
    wanted = ("face", "tristrips")
    out: dict[str, list[list[int]]] = {}
    if header.encoding == "ascii":
        tokens = data[header.body_offset :].split()
        position = 0
        for element in header.elements:
            rows = []
            wanted_list = _index_list(element) if element.name in wanted else None
            for _ in range(element.count):
                row: list[int] = []
                for k, prop in enumerate(element.properties):
                    if prop.is_list:
                        count = int(tokens[position])
                        if count < 0:
                            raise InputFileError(f"a negative list length in the {element.name} element")
                        values = tokens[position + 1 : position + 1 + count]
                        if len(values) < count:
                            raise InputFileError(f"truncated {element.name} element")
                        if k == wanted_list:
                            row = [int(float(v)) for v in values]
                        position += 1 + count
                    else:
                        position += 1
                rows.append(row)
            if element.name in wanted:
                out[element.name] = rows
        return out
    order = "<" if header.encoding == "binary_little_endian" else ">"
    position = header.body_offset
    for element in header.elements:
        if not element.has_lists:
            position += element.row_dtype(order).itemsize * element.count
            continue
        rows, position = _binary_list_rows(data, position, element, order,
                                           _index_list(element) if element.name in wanted else None)
        if element.name in wanted:
            out[element.name] = rows
    return out


def _binary_list_rows(data: bytes, position: int, element, order: str, wanted: int | None) -> tuple[list[list[int]], int]:
    """The list of property `wanted` (None: none) of every row of a binary element with list properties, and the end offset."""
    props = element.properties
    if len(props) == 1 and element.count > 1 and wanted == 0:  # fast path: every row a polygon of one size
        count_dtype, value_dtype = np.dtype(order + props[0].count_type), np.dtype(order + props[0].value_type)
        if position + count_dtype.itemsize <= len(data):
            (first,) = np.frombuffer(data, count_dtype, 1, position)
            if first == int(first) and 0 < first <= 1024:
                row = np.dtype([("n", count_dtype), ("i", value_dtype, int(first))])
                if position + row.itemsize * element.count <= len(data):
                    table = np.frombuffer(data, row, element.count, position)
                    if np.all(table["n"] == first):
                        return table["i"].astype(np.int64).tolist(), position + row.itemsize * element.count
    rows = []
    for _ in range(element.count):
        indices: list[int] = []
        for k, prop in enumerate(props):
            if not prop.is_list:
                position += np.dtype(prop.value_type).itemsize
                continue
            count_dtype, value_dtype = np.dtype(order + prop.count_type), np.dtype(order + prop.value_type)
            (count,) = np.frombuffer(data, count_dtype, 1, position)
            if count < 0:
                raise InputFileError(f"a negative list length in the {element.name} element")
            position += count_dtype.itemsize
            values = np.frombuffer(data, value_dtype, int(count), position)
            position += value_dtype.itemsize * int(count)
            if k == wanted:
                indices = values.astype(np.int64).tolist()
        rows.append(indices)
    return rows, position
