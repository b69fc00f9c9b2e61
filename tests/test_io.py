"""Tests of escape_cli.io: round trips, every realdata cloud against open3d, edge cases."""

from __future__ import annotations

import io as stdlib_io
import logging
import os
import struct
import sys

import numpy as np
import pytest
from conftest import realdata_clouds, realdata_id

from escape_cli import io as cloud_io
from escape_cli.errors import InputFileError, OutputExistsError, OutputFileError, PointCloudError
from escape_cli.io.lzf import LZFError, lzf_decompress, lzf_decompress_naive

# (format, binary) pairs that write_points can produce
WRITE_VARIANTS = [
    ("ply", True), ("ply", False), ("pcd", True), ("pcd", False),
    ("xyz", True), ("txt", True), ("pts", True), ("csv", True), ("npy", True), ("npz", True),
]  # fmt: skip
FORMATS_KEEPING_FIELDS = {"ply", "pcd", "xyz", "txt", "pts", "csv", "npz"}


@pytest.fixture
def cloud(rng) -> np.ndarray:
    """(50, 3) float64 with a wide range of magnitudes."""
    return rng.normal(size=(50, 3)) * np.array([1e-3, 1.0, 1e3])


# ---------------------------------------------------------------- round trips


@pytest.mark.parametrize(("fmt", "binary"), WRITE_VARIANTS)
def test_round_trip_to_float32_precision(tmp_path, cloud, fmt, binary):
    path = tmp_path / f"cloud.{fmt}"
    cloud_io.write_points(path, cloud, binary=binary)
    back = cloud_io.read_points(path)
    assert back.dtype == np.float64 and back.shape == cloud.shape
    # the same float32 values (ascii bodies give back the 9-digit decimals, kept as float64)
    np.testing.assert_array_equal(back.astype(np.float32), cloud.astype(np.float32))
    if binary and fmt in ("ply", "pcd", "npy", "npz"):  # binary: exactly the float32 values
        np.testing.assert_array_equal(back, cloud.astype(np.float32).astype(np.float64))


@pytest.mark.parametrize(("fmt", "binary"), WRITE_VARIANTS)
def test_round_trip_float64_coordinates_exact(tmp_path, cloud, fmt, binary):
    path = tmp_path / f"cloud.{fmt}"
    cloud_io.write_points(path, cloud, binary=binary, coordinate_dtype=np.float64)
    np.testing.assert_array_equal(cloud_io.read_points(path), cloud)


@pytest.mark.parametrize(("fmt", "binary"), WRITE_VARIANTS)
def test_round_trip_fields(tmp_path, cloud, rng, fmt, binary):
    fields = {"residual": rng.random(len(cloud)), "label_2": np.arange(len(cloud), dtype=float)}
    path = tmp_path / f"cloud.{fmt}"
    cloud_io.write_points(path, cloud, fields=fields, binary=binary)
    back, back_fields = cloud_io.read_point_fields(path)
    np.testing.assert_array_equal(back.astype(np.float32), cloud.astype(np.float32))
    if fmt in FORMATS_KEEPING_FIELDS:
        assert list(back_fields) == list(fields)
        for key, values in fields.items():
            np.testing.assert_array_equal(back_fields[key].astype(np.float32), values.astype(np.float32))
    else:
        assert back_fields == {}


def test_explicit_format_overrides_extension(tmp_path, cloud):
    path = tmp_path / "cloud.dat"
    cloud_io.write_points(path, cloud, fmt="pcd")
    assert path.read_bytes().startswith(b"# .PCD")
    np.testing.assert_array_equal(cloud_io.read_points(path, fmt="PCD"), cloud.astype(np.float32))


def test_format_from_path():
    assert cloud_io.format_from_path("a/b/Scan.PLY") == "ply"
    assert cloud_io.format_from_path("x.anchors.ply") == "ply"
    assert cloud_io.format_from_path("x.xyz") == "xyz"
    with pytest.raises(InputFileError, match=r"unknown format '\.foo' for x\.foo; use --format"):
        cloud_io.format_from_path("x.foo")
    with pytest.raises(InputFileError, match="no extension"):
        cloud_io.format_from_path("cloud")


def test_ascii_ply_and_pcd_are_text(tmp_path, cloud):
    for fmt in ("ply", "pcd"):
        path = tmp_path / f"c.{fmt}"
        cloud_io.write_points(path, cloud, binary=False)
        path.read_bytes().decode("ascii")  # no binary bytes


# ---------------------------------------------------------------- stdin / stdout


class _FakeStdin:
    def __init__(self, data: bytes):
        self.buffer = stdlib_io.BytesIO(data)


@pytest.mark.parametrize(("fmt", "binary"), WRITE_VARIANTS)
def test_stdin_sniffs_format(tmp_path, cloud, monkeypatch, fmt, binary):
    path = tmp_path / f"c.{fmt}"
    cloud_io.write_points(path, cloud, binary=binary)
    monkeypatch.setattr(sys, "stdin", _FakeStdin(path.read_bytes()))
    np.testing.assert_array_equal(cloud_io.read_points("-").astype(np.float32), cloud.astype(np.float32))


def test_stdout_defaults_to_binary_ply(cloud, capsysbinary):
    cloud_io.write_points("-", cloud)
    data = capsysbinary.readouterr().out
    assert data.startswith(b"ply\nformat binary_little_endian 1.0\n")
    np.testing.assert_array_equal(cloud_io.ply.parse_ply(data, "x")[0], cloud.astype(np.float32))


def test_stdout_with_format(cloud, capsysbinary):
    cloud_io.write_points("-", cloud, fmt="xyz")
    lines = capsysbinary.readouterr().out.decode().splitlines()
    assert len(lines) == len(cloud) and len(lines[0].split()) == 3


# ---------------------------------------------------------------- writing safely


def test_no_overwrite_keeps_existing_file(tmp_path, cloud):
    path = tmp_path / "c.ply"
    path.write_bytes(b"precious")
    with pytest.raises(OutputExistsError, match="c.ply exists"):
        cloud_io.write_points(path, cloud)
    assert path.read_bytes() == b"precious"
    cloud_io.write_points(path, cloud, overwrite=True)
    np.testing.assert_array_equal(cloud_io.read_points(path), cloud.astype(np.float32))


def test_write_leaves_no_temporary_files(tmp_path, cloud):
    cloud_io.write_points(tmp_path / "c.pcd", cloud)
    cloud_io.write_points(tmp_path / "c.pcd", cloud, overwrite=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.pcd"]


def test_failed_write_leaves_nothing(tmp_path, cloud, monkeypatch):
    def failing_fsync(fd):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "fsync", failing_fsync)
    with pytest.raises(OutputFileError, match="No space left"):
        cloud_io.write_points(tmp_path / "c.ply", cloud)
    assert list(tmp_path.iterdir()) == []


def test_failed_overwrite_keeps_old_content(tmp_path, cloud, monkeypatch):
    path = tmp_path / "c.xyz"
    path.write_bytes(b"1 2 3\n")
    monkeypatch.setattr(os, "fsync", lambda fd: (_ for _ in ()).throw(OSError(5, "I/O error")))
    with pytest.raises(OutputFileError):
        cloud_io.write_points(path, cloud, overwrite=True)
    assert path.read_bytes() == b"1 2 3\n"
    assert [p.name for p in tmp_path.iterdir()] == ["c.xyz"]


def test_write_errors(tmp_path, cloud):
    with pytest.raises(OutputFileError, match="does not exist"):
        cloud_io.write_points(tmp_path / "missing" / "c.ply", cloud)
    with pytest.raises(OutputFileError, match="is a directory"):
        cloud_io.write_points(tmp_path, cloud, fmt="ply")
    with pytest.raises(InputFileError, match="unknown format '.foo'"):
        cloud_io.write_points(tmp_path / "c.foo", cloud)
    with pytest.raises(PointCloudError, match="no points"):
        cloud_io.write_points(tmp_path / "c.ply", np.empty((0, 3)))
    with pytest.raises(PointCloudError, match=r"shape \(4, 2\)"):
        cloud_io.write_points(tmp_path / "c.ply", np.zeros((4, 2)))
    with pytest.raises(PointCloudError, match="bad field name"):
        cloud_io.write_points(tmp_path / "c.ply", cloud, fields={"two words": np.zeros(len(cloud))})
    with pytest.raises(PointCloudError, match="field 'r' has shape"):
        cloud_io.write_points(tmp_path / "c.ply", cloud, fields={"r": np.zeros(3)})
    assert list(tmp_path.iterdir()) == []


# ---------------------------------------------------------------- PLY details


def _ply(header_lines: list[str], body: bytes) -> bytes:
    return ("\n".join(["ply", *header_lines, "end_header"]) + "\n").encode() + body


def test_ply_big_endian_mixed_types_with_faces_before_vertices():
    points = np.array([[1.5, -2.0, 3.25], [0.0, 1e-3, -7.0], [4.0, 5.0, 6.0]])
    faces = struct.pack(">B3i", 3, 0, 1, 2) + struct.pack(">B4i", 4, 0, 1, 2, 0)
    rows = b"".join(struct.pack(">hdfB", 7 * i, x, y, 200 + i) + struct.pack(">f", z) for i, (x, y, z) in enumerate(points))
    data = _ply(
        ["format binary_big_endian 1.0", "comment faces first", "element face 2",
         "property list uchar int vertex_indices", "element vertex 3", "property short id",
         "property double x", "property float y", "property uchar red", "property float z"],
        faces + rows,
    )  # fmt: skip
    xyz, fields = cloud_io.ply.parse_ply(data, "t.ply")
    np.testing.assert_array_equal(xyz, points.astype(np.float32).astype(np.float64) * [0, 1, 1] + points * [1, 0, 0])
    assert list(fields) == ["id", "red"]
    np.testing.assert_array_equal(fields["red"], [200, 201, 202])


def test_ply_list_property_inside_vertex_binary_and_ascii():
    header = ["element vertex 2", "property float x", "property list uchar int ids", "property float y",
              "property float z", "property float quality", "element face 1", "property list uchar int vertex_indices"]  # fmt: skip
    binary = struct.pack("<fB2ifff", 1, 2, 9, 9, 2, 3, 0.5) + struct.pack("<fBfff", 4, 0, 5, 6, 0.25)
    ascii_body = b"1 2 9 9 2 3 0.5\n4 0 5 6 0.25\n3 0 1 1\n"
    for data in (
        _ply(["format binary_little_endian 1.0", *header], binary + struct.pack("<B3i", 3, 0, 1, 1)),
        _ply(["format ascii 1.0", *header], ascii_body),
    ):
        xyz, fields = cloud_io.ply.parse_ply(data, "t.ply")
        np.testing.assert_array_equal(xyz, [[1, 2, 3], [4, 5, 6]])
        np.testing.assert_array_equal(fields["quality"], [0.5, 0.25])


def test_ply_ascii_faces_before_vertices_and_crlf():
    data = _ply(["format ascii 1.0", "element face 2", "property list uchar int v", "element vertex 2",
                 "property int x", "property int y", "property int z"], b"3 0 1 1\n4 0 1 1 0\n1 2 3\n4 5 6\n")  # fmt: skip
    xyz, _ = cloud_io.ply.parse_ply(data.replace(b"\n", b"\r\n"), "t.ply")
    np.testing.assert_array_equal(xyz, [[1, 2, 3], [4, 5, 6]])


@pytest.mark.parametrize(
    ("data", "message"),
    [
        (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n", "no end_header"),
        (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n0\n", "no y/z property"),
        (b"ply\nformat ascii 1.0\nelement face 1\nproperty list uchar int v\nend_header\n0\n", "no vertex element"),
        (b"ply\nformat zip 1.0\nelement vertex 1\nend_header\n", "corrupt PLY header at line 2"),
        (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty quad x\nend_header\n", "bad property"),
        (b"PK\x03\x04ply", "not a PLY file"),
    ],
)
def test_ply_header_errors(data, message):
    with pytest.raises(InputFileError, match=message):
        cloud_io.ply.parse_ply(data, "t.ply")


# ---------------------------------------------------------------- PCD details


def _pcd(fields, sizes, types, counts, points, kind, body: bytes) -> bytes:
    header = (
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\n"
        f"FIELDS {fields}\nSIZE {sizes}\nTYPE {types}\nCOUNT {counts}\n"
        f"WIDTH {points}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {points}\nDATA {kind}\n"
    )
    return header.encode() + body


def _packed_rgb(red, green, blue) -> float:
    return np.array([(red << 16) | (green << 8) | blue], dtype=np.uint32).view(np.float32)[0]


def test_pcd_binary_with_padding_count_and_packed_rgb():
    rows = b"".join(
        struct.pack("<fff", i, 2 * i, 3 * i) + b"\0" * 4 + struct.pack("<f", _packed_rgb(10, 20 + i, 30))
        + struct.pack("<3h", 1, 2, i) + struct.pack("<d", 0.5 * i)
        for i in range(4)
    )  # fmt: skip
    data = _pcd("x y z _ rgb hist curvature", "4 4 4 4 4 2 8", "F F F U F I F", "1 1 1 1 1 3 1", 4, "binary", rows)
    xyz, fields = cloud_io.pcd.parse_pcd(data, "t.pcd")
    np.testing.assert_array_equal(xyz[:, 1], [0, 2, 4, 6])
    assert list(fields) == ["red", "green", "blue", "hist_0", "hist_1", "hist_2", "curvature"]
    np.testing.assert_array_equal(fields["green"], [20, 21, 22, 23])
    np.testing.assert_array_equal(fields["hist_2"], [0, 1, 2, 3])
    np.testing.assert_array_equal(fields["curvature"], [0, 0.5, 1, 1.5])


def test_pcd_ascii_rgb_as_float_and_rgba_as_integer():
    rgb = _packed_rgb(255, 128, 1)
    data = _pcd("x y z rgb", "4 4 4 4", "F F F F", "1 1 1 1", 1, "ascii", f"1 2 3 {rgb:.9g}\n".encode())
    _, fields = cloud_io.pcd.parse_pcd(data, "t.pcd")
    assert (fields["red"][0], fields["green"][0], fields["blue"][0]) == (255, 128, 1)
    rgba = (7 << 24) | (1 << 16) | (2 << 8) | 3
    data = _pcd("x y z rgba", "4 4 4 4", "F F F U", "1 1 1 1", 1, "ascii", f"1 2 3 {rgba}\n".encode())
    _, fields = cloud_io.pcd.parse_pcd(data, "t.pcd")
    assert [fields[c][0] for c in ("red", "green", "blue", "alpha")] == [1, 2, 3, 7]


def test_pcd_old_version_without_count_and_points():
    data = b"VERSION .5\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 2\nHEIGHT 1\nDATA ascii\n1 2 3\n4 5 6\n"
    np.testing.assert_array_equal(cloud_io.pcd.parse_pcd(data, "t.pcd")[0], [[1, 2, 3], [4, 5, 6]])


def _lzf_compress_for_tests(data: bytes, window: int = 400) -> bytes:
    """Greedy brute-force LZF compressor (slow; tiny inputs only)."""
    out, literals, i = bytearray(), bytearray(), 0

    def flush():
        while literals:
            chunk = literals[:32]
            out.append(len(chunk) - 1)
            out.extend(chunk)
            del literals[:32]

    while i < len(data):
        best_length, best_distance = 0, 0
        for distance in range(1, min(i, window) + 1):
            length = 0
            while i + length < len(data) and length < 264 and data[i - distance + length] == data[i + length]:
                length += 1
            if length > best_length:
                best_length, best_distance = length, distance
        if best_length >= 3:
            flush()
            offset, extra = best_distance - 1, best_length - 2
            if extra < 7:
                out += bytes([(extra << 5) | (offset >> 8), offset & 0xFF])
            else:
                out += bytes([(7 << 5) | (offset >> 8), extra - 7, offset & 0xFF])
            i += best_length
        else:
            literals.append(data[i])
            i += 1
    flush()
    return bytes(out)


def test_lzf_agrees_with_naive_version_on_runs_and_long_references(rng):
    pieces = [bytes(300), rng.integers(0, 255, 70, dtype=np.uint8).tobytes() * 5, b"ab" * 150, rng.bytes(40)]
    data = b"".join(pieces)
    compressed = _lzf_compress_for_tests(data)
    assert len(compressed) < len(data) / 2
    assert lzf_decompress(compressed, len(data)) == data
    assert lzf_decompress_naive(compressed, len(data)) == data
    for bad_size in (len(data) - 1, len(data) + 1):
        with pytest.raises(LZFError):
            lzf_decompress(compressed, bad_size)
    with pytest.raises(LZFError):
        lzf_decompress(compressed[:-1], len(data))
    with pytest.raises(LZFError, match="before the start"):
        lzf_decompress(bytes([0x20, 0x05]), 3)


def test_pcd_binary_compressed_struct_of_arrays(rng):
    points = np.round(rng.normal(size=(30, 3)), 1).astype(np.float32)
    intensity = np.full(30, 7.0, dtype=np.float32)
    raw = b"".join(np.ascontiguousarray(points[:, j]).tobytes() for j in range(3)) + intensity.tobytes()
    compressed = _lzf_compress_for_tests(raw)
    body = struct.pack("<II", len(compressed), len(raw)) + compressed
    data = _pcd("x y z intensity", "4 4 4 4", "F F F F", "1 1 1 1", 30, "binary_compressed", body)
    xyz, fields = cloud_io.pcd.parse_pcd(data, "t.pcd")
    np.testing.assert_array_equal(xyz, points)
    np.testing.assert_array_equal(fields["intensity"], intensity)
    with pytest.raises(InputFileError, match="truncated PCD body"):
        cloud_io.pcd.parse_pcd(data[:-5], "t.pcd")
    huge = data.replace(struct.pack("<I", len(raw)), struct.pack("<I", 10**9)).replace(b"POINTS 30", b"POINTS 62500000")
    with pytest.raises(InputFileError, match="cannot hold"):  # no gigabyte allocation
        cloud_io.pcd.parse_pcd(huge, "t.pcd")
    corrupt = data[: -len(compressed)] + bytes([0x20, 0xFF]) + compressed[2:]
    with pytest.raises(InputFileError, match="corrupt compressed PCD body"):
        cloud_io.pcd.parse_pcd(corrupt, "t.pcd")


def test_organised_pcd_drops_nan_rows_with_a_warning(tmp_path, caplog):
    body = b"1 2 3 0.1\nnan nan nan 0.2\n4 5 6 0.3\n7 nan 8 0.4\n"
    path = tmp_path / "scene.pcd"
    path.write_bytes(b"FIELDS x y z intensity\nSIZE 4 4 4 4\nTYPE F F F F\nWIDTH 2\nHEIGHT 2\nDATA ascii\n" + body)
    with caplog.at_level(logging.WARNING, logger="escape"):
        xyz, fields = cloud_io.read_point_fields(path)
    np.testing.assert_array_equal(xyz, [[1, 2, 3], [4, 5, 6]])
    np.testing.assert_allclose(fields["intensity"], [0.1, 0.3], rtol=1e-6)
    assert "dropped 2 of 4 points" in caplog.text and "scene.pcd" in caplog.text


# ---------------------------------------------------------------- text details


def test_text_comments_count_line_commas_and_names(tmp_path):
    path = tmp_path / "c.pts"
    path.write_text("3\n# a comment\n1 2 3 9 8 7 6\n\n4,5,6,1,2,3,4\n7\t8\t9\t0 0 0 0\n")
    xyz, fields = cloud_io.read_point_fields(path)
    np.testing.assert_array_equal(xyz, [[1, 2, 3], [4, 5, 6], [7, 8, 9]])
    assert list(fields) == ["intensity", "red", "green", "blue"]
    path = tmp_path / "c.csv"
    path.write_text("x,y,z,intensity\n1,2,3,0.5\n4,5,6,0.25\n")
    xyz, fields = cloud_io.read_point_fields(path)
    np.testing.assert_array_equal(fields["intensity"], [0.5, 0.25])
    path = tmp_path / "c.xyz"
    path.write_text("1 2 3 4 5\n")
    assert list(cloud_io.read_point_fields(path)[1]) == ["col3", "col4"]


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("1 2 3\n4 5\n", "line 2 has 2 columns, line 1 has 3"),
        ("1 2\n3 4\n", "2 columns per line; need at least x y z"),
        ("1 2 3\n4 five 6\n", "line 2: 'five' is not a number"),
    ],
)
def test_text_errors(tmp_path, text, message):
    path = tmp_path / "c.xyz"
    path.write_text(text)
    with pytest.raises(InputFileError, match=message):
        cloud_io.read_points(path)


def test_npy_shapes(tmp_path):
    np.save(tmp_path / "wide.npy", np.arange(12.0).reshape(3, 4))
    xyz, fields = cloud_io.read_point_fields(tmp_path / "wide.npy")
    np.testing.assert_array_equal(fields["col3"], [3, 7, 11])
    np.save(tmp_path / "flat.npy", np.arange(3.0))
    with pytest.raises(InputFileError, match=r"shape \(3,\); expected \(N, 3\)"):
        cloud_io.read_points(tmp_path / "flat.npy")
    np.savez(tmp_path / "two.npz", a=np.zeros((2, 3)), b=np.zeros((2, 3)))
    with pytest.raises(InputFileError, match="expected an array named 'points'"):
        cloud_io.read_points(tmp_path / "two.npz")


def test_read_array_round_trip(tmp_path, rng):
    distances = rng.random((20, 8))
    cloud_io.write_array(tmp_path / "d.npy", distances)
    np.testing.assert_array_equal(cloud_io.read_array(tmp_path / "d.npy"), distances)
    with pytest.raises(OutputExistsError):
        cloud_io.write_array(tmp_path / "d.npy", distances)


# ---------------------------------------------------------------- bad inputs (library level)


@pytest.mark.parametrize("fmt", ["ply", "pcd", "xyz", "npy"])
def test_empty_and_missing_files(tmp_path, fmt):
    with pytest.raises(InputFileError, match="no such file"):
        cloud_io.read_points(tmp_path / f"missing.{fmt}")
    (tmp_path / f"empty.{fmt}").write_bytes(b"")
    with pytest.raises(InputFileError, match="empty file"):
        cloud_io.read_points(tmp_path / f"empty.{fmt}")
    (tmp_path / f"dir.{fmt}").mkdir()
    with pytest.raises(InputFileError, match="is a directory"):
        cloud_io.read_points(tmp_path / f"dir.{fmt}")


def test_permission_denied_is_an_input_error(tmp_path, monkeypatch):
    """chmod 000 does not stop root, so simulate the refusal."""
    path = tmp_path / "c.ply"
    path.write_bytes(b"ply\n")

    def refusing_open(*args, **kwargs):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(cloud_io.files, "open", refusing_open, raising=False)
    with pytest.raises(InputFileError, match="c.ply: permission denied"):
        cloud_io.read_points(path)


@pytest.mark.parametrize(("fmt", "binary"), [("ply", True), ("ply", False), ("pcd", True), ("pcd", False), ("npy", True)])
def test_truncated_bodies(tmp_path, cloud, fmt, binary):
    path = tmp_path / f"c.{fmt}"
    cloud_io.write_points(path, cloud, binary=binary)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) - 40])
    with pytest.raises(InputFileError, match="truncated"):
        cloud_io.read_points(path)


@pytest.mark.parametrize(
    ("fmt", "header"),
    [
        ("ply", b"ply\nformat binary_little_endian 1.0\nelement vertex 0\nproperty float x\nproperty float y\n"
                b"property float z\nend_header\n"),
        ("pcd", b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 0\nHEIGHT 1\nPOINTS 0\nDATA binary\n"),
    ],
)  # fmt: skip
def test_header_only_file_with_zero_points(tmp_path, fmt, header):
    path = tmp_path / f"c.{fmt}"
    path.write_bytes(header)
    with pytest.raises(PointCloudError, match="holds no points"):
        cloud_io.read_points(path)


def test_non_finite_only_cloud(tmp_path):
    path = tmp_path / "c.xyz"
    path.write_text("nan nan nan\ninf 1 2\n")
    with pytest.raises(PointCloudError, match="all 2 points have non-finite"):
        cloud_io.read_points(path)


def test_reading_never_modifies_input(tmp_path, cloud):
    path = tmp_path / "c.ply"
    cloud_io.write_points(path, cloud)
    before = (path.read_bytes(), path.stat().st_mtime_ns)
    cloud_io.read_points(path)
    assert (path.read_bytes(), path.stat().st_mtime_ns) == before


# ---------------------------------------------------------------- real scans


@pytest.mark.parametrize(
    "path",
    realdata_clouds(),
    ids=realdata_id,
)
def test_realdata_matches_open3d(realdata_dir, path):
    open3d = pytest.importorskip("open3d")
    o3d_cloud = open3d.io.read_point_cloud(str(path), remove_nan_points=False, remove_infinite_points=False)
    expected = np.asarray(o3d_cloud.points)
    finite = np.isfinite(expected).all(axis=1)
    points, fields = cloud_io.read_point_fields(path)
    assert len(points) == int(finite.sum())
    np.testing.assert_array_equal(points, expected[finite])
    if o3d_cloud.has_colors():
        colours = np.column_stack([fields["red"], fields["green"], fields["blue"]]) / 255.0
        np.testing.assert_allclose(colours, np.asarray(o3d_cloud.colors)[finite], atol=1e-12)
    if o3d_cloud.has_normals():
        normals = np.column_stack([fields["normal_x"], fields["normal_y"], fields["normal_z"]])
        np.testing.assert_array_equal(normals, np.asarray(o3d_cloud.normals)[finite])


def test_realdata_text_files(realdata_dir):
    """KITTI boxes (.txt, 8 corners) read like open3d's xyz reader; licence texts fail cleanly."""
    open3d = pytest.importorskip("open3d")
    boxes = sorted(realdata_dir.glob("kitti_cars/bboxes/*.txt"))
    licences = sorted(realdata_dir.rglob("LICENSE*.txt"))
    if not boxes and not licences:
        pytest.skip("no .txt files in realdata")
    for path in boxes:
        expected = np.asarray(open3d.io.read_point_cloud(str(path), format="xyz").points)
        np.testing.assert_array_equal(cloud_io.read_points(path), expected)
        assert expected.shape == (8, 3)
    for path in licences:
        with pytest.raises(InputFileError, match=f"{path.name}: line .* is not a number"):
            cloud_io.read_points(path)


def test_realdata_compressed_pcd_is_fast(realdata_dir):
    import time

    path = realdata_dir / "pcl_test_scans" / "table_scene_mug_stereo_textured.pcd"
    if not path.exists():
        pytest.skip(f"{path} not found")
    start = time.perf_counter()
    points, fields = cloud_io.read_point_fields(path)
    assert time.perf_counter() - start < 5.0
    assert points.shape == (209280, 3) and {"red", "green", "blue"} <= set(fields)


# ---------------------------------------------------------------- files other software writes
# Small hand-made files of the shapes PDAL, PCL and others write (issue 21, item 8).


def test_pdal_text_with_quoted_upper_case_names():
    data = b'"X","Y","Z","Intensity"\n1.5,2.25,-3.0,10\n4.0,5.0,6.0,20\n'
    xyz, fields = cloud_io.text.parse_text(data, "autzen.txt", "txt")
    np.testing.assert_array_equal(xyz, [[1.5, 2.25, -3.0], [4.0, 5.0, 6.0]])
    np.testing.assert_array_equal(fields["Intensity"], [10, 20])


def test_named_coordinates_in_any_column():
    data = b'"Intensity","Z","X","Y"\n10,3,1,2\n20,6,4,5\n'
    xyz, fields = cloud_io.text.parse_text(data, "t.csv", "csv")
    np.testing.assert_array_equal(xyz, [[1, 2, 3], [4, 5, 6]])
    assert list(fields) == ["Intensity"]


@pytest.mark.parametrize("kind", ["ascii", "binary"])
def test_pcd_with_upper_case_coordinate_fields(kind):
    points = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]], dtype=np.float32)
    if kind == "ascii":
        body = b"1 2 3 7\n4 5 6 8\n"
    else:
        body = b"".join(struct.pack("<ffff", *row, 7.0 + i) for i, row in enumerate(points))
    data = _pcd("X Y Z Intensity", "4 4 4 4", "F F F F", "1 1 1 1", 2, kind, body)
    xyz, fields = cloud_io.pcd.parse_pcd(data, "autzen-utm.pcd")
    np.testing.assert_array_equal(xyz, points)
    np.testing.assert_array_equal(fields["Intensity"], [7, 8])


def test_pcd_ascii_separated_by_commas():
    data = _pcd("x y z", "4 4 4", "F F F", "1 1 1", 2, "ascii", b"1,2,3\n4, 5, 6\n")
    xyz, _ = cloud_io.pcd.parse_pcd(data, "c.pcd")
    np.testing.assert_array_equal(xyz, [[1, 2, 3], [4, 5, 6]])


@pytest.mark.parametrize("magic", [b"ply \n", b"ply\t\r\n", b"ply  \r\n"])
def test_ply_magic_line_with_trailing_blanks(magic):
    data = magic + b"format ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n1 2 3\n"
    assert cloud_io.sniff_format(data) == "ply"
    xyz, _ = cloud_io.ply.parse_ply(data, "t.ply")
    np.testing.assert_array_equal(xyz, [[1, 2, 3]])


def test_not_a_ply_file_says_what_its_first_line_is():
    with pytest.raises(InputFileError, match="its first line is 'plyx', not 'ply'"):
        cloud_io.ply.parse_ply(b"plyx\nformat ascii 1.0\n", "t.ply")


def test_pts_count_line_must_match_the_rows():
    xyz, _ = cloud_io.text.parse_text(b"2\n1 2 3\n4 5 6\n", "s.pts", "pts")
    assert xyz.shape == (2, 3)
    for data, message in ((b"3\n1 2 3\n4 5 6\n", "declares 3 points, but 2 rows follow"),
                          (b"5\n", "declares 5 points, but no rows follow")):  # fmt: skip
        with pytest.raises(InputFileError, match=message):
            cloud_io.text.parse_text(data, "s.pts", "pts")


# ---------------------------------------------------------------- headers that disagree with the body


def _valid_bytes(fmt: str, binary: bool, points: np.ndarray) -> bytes:
    if fmt == "ply":
        return cloud_io.ply.serialize_ply(points, {}, binary=binary)
    return cloud_io.pcd.serialize_pcd(points, {}, binary=binary)


def _compressed_pcd(points: np.ndarray) -> bytes:
    raw = b"".join(np.ascontiguousarray(points[:, j], dtype=np.float32).tobytes() for j in range(3))
    compressed = _lzf_compress_for_tests(raw)
    return _pcd("x y z", "4 4 4", "F F F", "1 1 1", len(points), "binary_compressed",
                struct.pack("<II", len(compressed), len(raw)) + compressed)  # fmt: skip


HEADER_VARIANTS = [("ply", True), ("ply", False), ("pcd", True), ("pcd", False), ("pcd", "compressed")]


@pytest.mark.parametrize(("fmt", "binary"), HEADER_VARIANTS)
def test_padding_after_the_body_is_accepted(fmt, binary):
    points = np.arange(12, dtype=np.float64).reshape(4, 3)
    valid = _compressed_pcd(points) if binary == "compressed" else _valid_bytes(fmt, binary, points)
    parse = cloud_io.ply.parse_ply if fmt == "ply" else cloud_io.pcd.parse_pcd
    for padding in (b"\n", b"\r\n", b"\0" * 3901):  # PCL pads its binary_compressed files with zeros
        np.testing.assert_array_equal(parse(valid + padding, "t")[0], points)


@pytest.mark.parametrize(("fmt", "binary"), HEADER_VARIANTS)
def test_data_after_the_declared_body_is_refused(fmt, binary):
    points = np.arange(12, dtype=np.float64).reshape(4, 3)
    valid = _compressed_pcd(points) if binary == "compressed" else _valid_bytes(fmt, binary, points)
    parse = cloud_io.ply.parse_ply if fmt == "ply" else cloud_io.pcd.parse_pcd
    extra = b"x" if binary else b"9 9 9\n"
    with pytest.raises(InputFileError, match=r"after the (end of the PLY body|4 points) the header declares"):
        parse(valid + extra, "t")


def test_ply_elements_after_the_vertices_count_towards_the_end():
    header = ["format binary_little_endian 1.0", "element vertex 1", "property float x", "property float y",
              "property float z", "element note 2", "property uchar a"]  # fmt: skip
    body = struct.pack("<fff", 1, 2, 3) + b"\x05\x06"
    assert cloud_io.ply.parse_ply(_ply(header, body), "t.ply")[0].tolist() == [[1, 2, 3]]
    with pytest.raises(InputFileError, match=r"1 byte after .*\(vertex 1, note 2\)"):
        cloud_io.ply.parse_ply(_ply(header, body + b"\x07"), "t.ply")
    with pytest.raises(InputFileError, match="'note' element cut off"):
        cloud_io.ply.parse_ply(_ply(header, body[:-1]), "t.ply")


# ---------------------------------------------------------------- values float32 cannot hold


@pytest.mark.parametrize(("fmt", "binary"), WRITE_VARIANTS)
@pytest.mark.parametrize("scale", [1e100, 1e-40])
def test_float32_gives_way_to_float64_where_it_cannot_hold_the_values(tmp_path, rng, fmt, binary, scale):
    points = rng.normal(size=(20, 3)) * scale
    fields = {"residual": rng.uniform(1, 2, size=20) * scale} if fmt in FORMATS_KEEPING_FIELDS else None
    path = tmp_path / f"c.{fmt}"
    cloud_io.write_points(path, points, fields=fields, binary=binary)
    back, back_fields = cloud_io.read_point_fields(path)
    np.testing.assert_array_equal(back, points)  # not inf, not 0: every digit
    if fields:
        np.testing.assert_array_equal(back_fields["residual"], fields["residual"])


def test_float32_stays_where_it_holds_the_values(tmp_path, rng):
    cloud_io.write_points(tmp_path / "c.ply", rng.normal(size=(20, 3)) * 1e30, fields={"r": np.zeros(20)})
    assert b"property float x" in (tmp_path / "c.ply").read_bytes()[:200]
    assert b"property float r" in (tmp_path / "c.ply").read_bytes()[:200]


def test_complex_arrays_are_refused(rng):
    data = cloud_io.npy.serialize_array(rng.normal(size=(5, 3)) + 1j)
    with pytest.raises(InputFileError, match="holds complex numbers"):
        cloud_io.npy.parse_npy(data, "c.npy")
    with pytest.raises(InputFileError, match="holds complex numbers"):
        cloud_io.npy.parse_array(data, "c.npy")


# ---------------------------------------------------------------- robustness


@pytest.mark.parametrize(("fmt", "binary"), WRITE_VARIANTS)
def test_damaged_files_raise_only_escape_errors(fmt, binary):
    """Cut or overwrite bytes anywhere in a valid file: a clean EscapeError or a cloud, never a crash."""
    hypothesis = pytest.importorskip("hypothesis")
    strategies = hypothesis.strategies
    from escape_cli.errors import EscapeError

    points = np.random.default_rng(5).normal(size=(12, 3))
    fields = {"residual": np.linspace(0, 1, 12)} if fmt != "npy" else None
    buffer = {}

    def capture(path, data, *, overwrite=False):
        buffer["data"] = data

    original = cloud_io.write_output_bytes
    cloud_io.write_output_bytes = capture
    try:
        cloud_io.write_points("x", points, fmt, fields=fields, binary=binary)
    finally:
        cloud_io.write_output_bytes = original
    valid = buffer["data"]

    @hypothesis.settings(max_examples=60, deadline=None, derandomize=True)
    @hypothesis.given(
        cut=strategies.integers(0, len(valid)),
        position=strategies.integers(0, len(valid) - 1),
        replacement=strategies.binary(min_size=0, max_size=6),
    )
    def check(cut, position, replacement):
        for damaged in (valid[:cut], valid[:position] + replacement + valid[position + len(replacement) :]):
            try:
                xyz, _ = cloud_io._parse(damaged, "d", fmt)
                cloud_io._finite_rows(xyz, {}, "d")
            except EscapeError as err:
                assert "\n" not in str(err)

    check()
