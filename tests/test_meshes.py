"""Mesh files (escape_cli.data.meshes): OBJ, OFF, STL ascii and binary, PLY faces and tristrips."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from escape_cli.data.meshes import ply_has_faces, read_mesh
from escape_cli.errors import InputFileError

TEST_MESHES = Path(__file__).resolve().parents[2] / "shared" / "shapes" / "test-meshes"

# a unit square (two triangles) and a tetrahedron
QUAD = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=np.float64)
TETRA = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=np.float64)
TETRA_FACES = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])


def _area(mesh) -> float:
    t = mesh.vertices[mesh.triangles]
    return float(0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1).sum())


def test_obj_with_texture_normal_indices_quads_and_relative_indices(tmp_path):
    path = tmp_path / "q.obj"
    path.write_text("# quad\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvn 0 0 1\n"
                    "f 1/1/1 2/1/1 3/1/1 4/1/1\nf -4 -3 -2\n")
    mesh = read_mesh(path)
    assert mesh.vertices.shape == (4, 3) and mesh.triangles.shape == (3, 3)
    assert mesh.note == "polygons split into fans"
    assert _area(mesh) == pytest.approx(1.5)


def test_off_variants(tmp_path):
    body = "".join(f"{x} {y} {z}\n" for x, y, z in TETRA) + "".join(f"3 {a} {b} {c} 255 0 0\n" for a, b, c in TETRA_FACES)
    plain = tmp_path / "t.off"
    plain.write_text(f"OFF\n# comment\n4 4 0\n{body}")
    glued = tmp_path / "g.off"  # ModelNet's files: counts glued to the keyword
    glued.write_text(f"OFF4 4 0\n{body}")
    for path in (plain, glued):
        mesh = read_mesh(path)
        np.testing.assert_array_equal(mesh.triangles, TETRA_FACES)
        assert _area(mesh) == pytest.approx(1.5 + np.sqrt(3) / 2)


def _binary_stl(corners: np.ndarray, header: bytes = b"binary") -> bytes:
    record = np.zeros(len(corners), dtype=[("n", "<f4", 3), ("v", "<f4", (3, 3)), ("a", "<u2")])
    record["v"] = corners
    return header.ljust(80, b" ") + struct.pack("<I", len(corners)) + record.tobytes()


@pytest.mark.parametrize("header", [b"binary", b"solid looks like ascii"])
def test_stl_binary_and_ascii_agree(tmp_path, header):
    corners = TETRA[TETRA_FACES]
    binary = tmp_path / "b.stl"
    binary.write_bytes(_binary_stl(corners, header))
    ascii_path = tmp_path / "a.stl"
    facets = "".join(
        "facet normal 0 0 0\nouter loop\n" + "".join(f"vertex {x} {y} {z}\n" for x, y, z in tri) + "endloop\nendfacet\n"
        for tri in corners
    )
    ascii_path.write_text(f"solid t\n{facets}endsolid t\n")
    a, b = read_mesh(ascii_path), read_mesh(binary)
    np.testing.assert_allclose(a.vertices[a.triangles], b.vertices[b.triangles])
    assert len(b.triangles) == 4


def _ply(encoding: str, faces: list[list[int]], element: str = "face") -> bytes:
    header = (f"ply\nformat {encoding} 1.0\nelement vertex {len(QUAD)}\nproperty float x\nproperty float y\n"
              f"property float z\nelement {element} {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n")
    if encoding == "ascii":
        body = "".join(f"{x} {y} {z}\n" for x, y, z in QUAD) + "".join(f"{len(f)} {' '.join(map(str, f))}\n" for f in faces)
        return header.encode() + body.encode()
    body = QUAD.astype("<f4").tobytes()
    for f in faces:
        body += struct.pack("<B", len(f)) + np.asarray(f, dtype="<i4").tobytes()
    return header.encode() + body


@pytest.mark.parametrize("encoding", ["ascii", "binary_little_endian"])
@pytest.mark.parametrize("faces", [[[0, 1, 2], [0, 2, 3]], [[0, 1, 2, 3]]])
def test_ply_faces(tmp_path, encoding, faces):
    path = tmp_path / "q.ply"
    path.write_bytes(_ply(encoding, faces))
    assert ply_has_faces(path)
    mesh = read_mesh(path)
    assert len(mesh.triangles) == 2 and _area(mesh) == pytest.approx(1.0)


@pytest.mark.parametrize("encoding", ["ascii", "binary_little_endian"])
def test_ply_tristrips_with_restarts(tmp_path, encoding):
    path = tmp_path / "s.ply"
    path.write_bytes(_ply(encoding, [[0, 1, 3, 2, -1, 0, 1, 2]], element="tristrips"))
    mesh = read_mesh(path)
    assert mesh.note == "tristrips triangulated"
    assert len(mesh.triangles) == 3  # 2 from the first strip, 1 from the second
    normals = np.cross(*(mesh.vertices[mesh.triangles[:2, k]] - mesh.vertices[mesh.triangles[:2, 0]] for k in (1, 2)))
    assert np.sign(normals[0, 2]) == np.sign(normals[1, 2])  # alternate triangles flipped: one winding


def test_ply_without_faces_is_a_cloud(tmp_path):
    path = tmp_path / "c.ply"
    path.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n0 0 0\n")
    assert not ply_has_faces(path)


@pytest.mark.parametrize("name, content, message", [
    ("bad.obj", "v 0 0 0\nv 1 0 0\nf 1 2 9\n", "vertex that does not exist"),
    ("none.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\n", "no faces"),
    ("flat.obj", "v 0 0 0\nv 1 0 0\nf 1 1 2\n", "degenerate"),
    ("short.off", "OFF\n4 4 0\n0 0 0\n", "truncated"),
    ("x.off", "COFFEE\n", "OFF"),
    ("g.stl", "not an stl at all", "neither ascii STL"),
    ("h.stl", "solid x\nvertex 0 0 0\n", "multiple of 3"),
    ("z.xyz", "0 0 0\n", "not a mesh file"),
])
def test_bad_meshes_name_the_file(tmp_path, name, content, message):
    path = tmp_path / name
    path.write_text(content)
    with pytest.raises(InputFileError, match=message) as info:
        read_mesh(path)
    assert str(path) in str(info.value)


def test_missing_file(tmp_path):
    with pytest.raises(InputFileError, match="cannot read"):
        read_mesh(tmp_path / "nope.obj")


@pytest.mark.parametrize("name, triangles, note", [
    ("spot.obj", 5856, "triangles"),  # v/vt indices
    ("suzanne.obj", 968, "polygons split into fans"),
    ("igea.ply", 268686, "tristrips triangulated"),
])
def test_third_party_meshes(name, triangles, note):
    path = TEST_MESHES / name
    if not path.is_file():
        pytest.skip(f"test meshes not found at {TEST_MESHES}")
    mesh = read_mesh(path)
    assert len(mesh.triangles) == triangles and mesh.note == note
    assert np.isfinite(mesh.vertices).all() and _area(mesh) > 0


# ------------------------------------------------------------------ files as other software writes them

QUAD_TRIANGLES = [[0, 1, 2], [0, 2, 3]]
OBJ_VERTICES = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\n"


@pytest.mark.parametrize("text", [
    OBJ_VERTICES + "f 1 2 3\nf 1 3 4\n",
    (OBJ_VERTICES + "f 1 2 3\nf 1 3 4\n").replace("\n", "\r\n"),  # CRLF
    "\ufeff" + OBJ_VERTICES + "f 1 2 3\nf 1 3 4\n",  # a byte order mark (it hid the first vertex)
    OBJ_VERTICES + "vn 0 0 1\nf 1//1 2//1 3//1\nf 1//1 3//1 4//1\n",  # v//vn
    OBJ_VERTICES + "f 1 2 3 # a comment\nf 1 3 4#another\n",
    OBJ_VERTICES + "f 1 2 \\\n  3\nf 1 3 4\n",  # a statement continued on the next line
    "f 1 2 3\nf 1 3 4\n" + OBJ_VERTICES,  # faces before vertices (absolute indices)
    "v 0 0 0\nv 1 0 0\nv 1 1 0\nf -3 -2 -1\nv 0 1 0\nf -4 -2 -1\n",  # relative indices count the vertices so far
], ids=["plain", "crlf", "bom", "v//vn", "comments", "continued", "faces-first", "relative"])
def test_obj_as_other_software_writes_it(tmp_path, text):
    path = tmp_path / "q.obj"
    path.write_bytes(text.encode("utf-8"))
    mesh = read_mesh(path)
    np.testing.assert_array_equal(mesh.vertices, QUAD)
    assert mesh.triangles.tolist() == QUAD_TRIANGLES


@pytest.mark.parametrize("keyword, extra", [("OFF", ""), ("NOFF", " 0 0 1"), ("COFF", " 255 0 0 255"),
                                            ("CNOFF", " 0 0 1 1 0 0 1"), ("STOFF", " 0.5 0.5")])
@pytest.mark.parametrize("newline, bom", [("\n", ""), ("\r\n", "\ufeff")], ids=["lf", "crlf-bom"])
def test_off_variants_line_endings_and_vertex_columns(tmp_path, keyword, extra, newline, bom):
    lines = [keyword, "4 2 0", *(f"{x} {y} {z}{extra}" for x, y, z in QUAD), "3 0 1 2", "3 0 2 3 1 0 0"]
    path = tmp_path / "q.off"
    path.write_bytes((bom + newline.join(lines) + newline).encode("utf-8"))
    mesh = read_mesh(path)
    np.testing.assert_array_equal(mesh.vertices, QUAD)
    assert mesh.triangles.tolist() == QUAD_TRIANGLES


def test_binary_off_is_refused_in_words(tmp_path):
    path = tmp_path / "b.off"
    path.write_bytes(b"OFF BINARY\n" + struct.pack(">3i", 3, 1, 0) + struct.pack(">9f", 0, 0, 0, 1, 0, 0, 0, 1, 0)
                     + struct.pack(">5i", 3, 0, 1, 2, 0))
    with pytest.raises(InputFileError, match=f"^{path}: binary OFF is not read"):
        read_mesh(path)


def test_ascii_stl_with_crlf_and_a_byte_order_mark(tmp_path):
    facets = "".join("facet normal 0 0 1\nouter loop\n" + "".join(f"vertex {x} {y} {z}\n" for x, y, z in QUAD[tri])
                     + "endloop\nendfacet\n" for tri in QUAD_TRIANGLES)
    path = tmp_path / "q.stl"
    path.write_bytes(("\ufeffsolid q\n" + facets + "endsolid q\n").replace("\n", "\r\n").encode("utf-8"))
    mesh = read_mesh(path)
    np.testing.assert_array_equal(mesh.vertices[mesh.triangles], QUAD[QUAD_TRIANGLES])


def _ply_file(encoding: str, faces, *, count="uchar", index="int", name="vertex_indices", faces_first=False,
              extra=(), element="face", more="") -> bytes:
    """A PLY of QUAD with a face element of list property `name` (`count`, `index` types) and
    scalar properties `extra` (uchar, after the list), optionally before the vertex element."""
    order = ">" if encoding == "binary_big_endian" else "<"
    codes = {"uchar": "u1", "uint8": "u1", "char": "i1", "ushort": "u2", "int": "i4", "uint": "u4", "uint32": "u4", "float": "f4"}
    vertex = "element vertex 4\nproperty float x\nproperty float y\nproperty float z\n"
    face = (f"element {element} {len(faces)}\nproperty list {count} {index} {name}\n"
            + "".join(f"property uchar {e}\n" for e in extra))
    header = f"ply\nformat {encoding} 1.0\ncomment written by a test\n" + (face + vertex if faces_first else vertex + face)
    header += more + "end_header\n"
    if encoding == "ascii":
        vertices = "".join(f"{x} {y} {z}\n" for x, y, z in QUAD).encode()
        face_rows = "".join(f"{len(f)} {' '.join(map(str, f))}{' 7' * len(extra)}\n" for f in faces).encode()
    else:
        vertices = QUAD.astype(order + "f4").tobytes()
        face_rows = b"".join(np.array(len(f), order + codes[count]).tobytes() + np.asarray(f, order + codes[index]).tobytes()
                             + bytes([7] * len(extra)) for f in faces)
    return header.encode() + (face_rows + vertices if faces_first else vertices + face_rows)


PLY_ENCODINGS = ["ascii", "binary_little_endian", "binary_big_endian"]


@pytest.mark.parametrize("encoding", PLY_ENCODINGS)
@pytest.mark.parametrize("variant", [
    {}, {"faces_first": True}, {"name": "vertex_index"}, {"name": "indices"}, {"extra": ("red", "green", "blue")},
    {"count": "uint8", "index": "uint32"}, {"count": "int", "index": "ushort"}, {"faces_first": True, "extra": ("flags",)},
], ids=["plain", "faces-first", "vertex_index", "other-name", "extra-properties", "uint8-uint32", "int-ushort",
        "faces-first-extra"])
@pytest.mark.parametrize("faces", [QUAD_TRIANGLES, [[0, 1, 2, 3], [0, 1, 2, 3]], [[0, 1, 2], [0, 2, 3, 3]]],
                         ids=["triangles", "quads", "mixed"])
def test_ply_faces_as_other_software_writes_them(tmp_path, encoding, variant, faces):
    path = tmp_path / "q.ply"
    path.write_bytes(_ply_file(encoding, faces, **variant))
    assert ply_has_faces(path)
    mesh = read_mesh(path)
    np.testing.assert_array_equal(mesh.vertices, QUAD)
    expected = [[0, 1, 2], [0, 2, 3]] * (2 if faces[0] == [0, 1, 2, 3] else 1)
    assert mesh.triangles.tolist() == expected  # (the mixed case's [0, 3, 3] is degenerate: dropped)


def test_ply_with_crlf_lines(tmp_path):
    path = tmp_path / "q.ply"
    path.write_bytes(_ply_file("ascii", QUAD_TRIANGLES).replace(b"\n", b"\r\n"))
    assert read_mesh(path).triangles.tolist() == QUAD_TRIANGLES


@pytest.mark.parametrize("encoding", PLY_ENCODINGS)
def test_ply_tristrips_beside_an_empty_face_element(tmp_path, encoding):
    more = "element tristrips 1\nproperty list int int vertex_indices\n"
    data = _ply_file(encoding, [], more=more)
    strip = [0, 1, 3, 2]
    if encoding == "ascii":
        data += f"{len(strip)} {' '.join(map(str, strip))}\n".encode()
    else:
        order = ">" if encoding == "binary_big_endian" else "<"
        data += np.array([len(strip), *strip], order + "i4").tobytes()
    path = tmp_path / "s.ply"
    path.write_bytes(data)
    mesh = read_mesh(path)
    assert mesh.note == "tristrips triangulated" and len(mesh.triangles) == 2
    assert _area(mesh) == pytest.approx(1.0)


@pytest.mark.parametrize("encoding", PLY_ENCODINGS)
def test_a_negative_list_length_is_an_error_naming_the_file(tmp_path, encoding):
    data = _ply_file(encoding, [[0, 1, 2], [0, 2, 3]], count="char")
    if encoding == "ascii":
        data = data.replace(b"\n3 0 2 3\n", b"\n-1 0 2 3\n")
    else:
        data = data.replace(b"\x03" + np.asarray([0, 2, 3], (">" if "big" in encoding else "<") + "i4").tobytes(),
                            b"\xff" + np.asarray([0, 2, 3], (">" if "big" in encoding else "<") + "i4").tobytes())
    path = tmp_path / "n.ply"
    path.write_bytes(data)
    with pytest.raises(InputFileError, match=f"^{path}: corrupt PLY faces \\(a negative list length in the face element\\)"):
        read_mesh(path)


def test_a_long_ply_header_still_has_its_faces_found(tmp_path):
    path = tmp_path / "q.ply"
    path.write_bytes(_ply_file("binary_little_endian", QUAD_TRIANGLES).replace(
        b"comment written by a test\n", b"".join(b"comment %06d\n" % i for i in range(8000))))  # > 64 KiB of header
    assert ply_has_faces(path)
    assert read_mesh(path).triangles.tolist() == QUAD_TRIANGLES
