"""Fuzzing the readers and the CLI: damaged files never crash, never exit 70, never lose anything.

Every variant the project reads (PLY ascii and binary, PCD ascii, binary and
binary_compressed, XYZ, NPY, LAS and LAZ) is damaged at random: truncated, bytes flipped or
inserted, header lines edited, dropped or doubled. The parsers must then give a cloud
(finite float64 coordinates, fields of the same length) or raise an `EscapeError` with
a one-line printable message; through the CLI (in-process, `cli_runner.run_escape`)
the exit code is 0, 1 or 2, the input is unchanged and a failed run leaves no file.
Random valid clouds round-trip through every writer and reader.

Sized for CI (well under a minute in all): derandomized, fixed example counts, no deadline.
"""

from __future__ import annotations

import struct

import numpy as np
import pytest

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402
from hypothesis.extra.numpy import arrays  # noqa: E402

from cli_runner import run_escape  # noqa: E402
from escape_cli import io as cloud_io  # noqa: E402
from escape_cli.errors import EscapeError  # noqa: E402
from escape_cli.io.lzf import lzf_decompress  # noqa: E402

PARSER_EXAMPLES = 150
CLI_EXAMPLES = 12
FUZZ = settings(max_examples=PARSER_EXAMPLES, deadline=None, derandomize=True, suppress_health_check=list(HealthCheck))


def _lzf_literals(raw: bytes) -> bytes:
    """LZF stream of literal runs only (a valid, uncompressed encoding: enough for a reader)."""
    out = bytearray()
    for start in range(0, len(raw), 32):
        chunk = raw[start : start + 32]
        out.append(len(chunk) - 1)
        out += chunk
    return bytes(out)


def _compressed_pcd(points: np.ndarray, intensity: np.ndarray) -> bytes:
    raw = b"".join(np.ascontiguousarray(points[:, j], dtype=np.float32).tobytes() for j in range(3))
    raw += intensity.astype(np.float32).tobytes()
    compressed = _lzf_literals(raw)
    assert lzf_decompress(compressed, len(raw)) == raw
    n = len(points)
    header = (
        "# .PCD v0.7\nVERSION 0.7\nFIELDS x y z intensity\nSIZE 4 4 4 4\nTYPE F F F F\nCOUNT 1 1 1 1\n"
        f"WIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA binary_compressed\n"
    ).encode()
    return header + struct.pack("<II", len(compressed), len(raw)) + compressed


def _valid_files() -> dict[str, tuple[str, bytes]]:
    """{variant: (format, bytes)}: one small valid file of every variant that is read."""
    rng = np.random.default_rng(21)
    points = rng.normal(size=(40, 3)) * [0.3, 0.2, 0.1]
    fields = {"intensity": rng.uniform(0, 1, 40)}
    las_fields = {"intensity": np.round(fields["intensity"] * 65535)}  # LAS intensity: 16-bit counts
    files = {
        "ply-binary": ("ply", cloud_io.ply.serialize_ply(points, fields, binary=True)),
        "ply-ascii": ("ply", cloud_io.ply.serialize_ply(points, fields, binary=False)),
        "pcd-binary": ("pcd", cloud_io.pcd.serialize_pcd(points, fields, binary=True)),
        "pcd-ascii": ("pcd", cloud_io.pcd.serialize_pcd(points, fields, binary=False)),
        "pcd-binary_compressed": ("pcd", _compressed_pcd(points, fields["intensity"])),
        "xyz": ("xyz", cloud_io.text.serialize_text(points, fields, fmt="xyz")),
        "npy": ("npy", cloud_io.npy.serialize_npy(points)),
        "las": ("las", cloud_io.las.serialize_las(points, las_fields, compressed=False)),
        "laz": ("laz", cloud_io.las.serialize_las(points, las_fields, compressed=True)),
    }
    for fmt, data in files.values():  # the seeds themselves are valid
        assert cloud_io._parse(data, "seed", fmt)[0].shape == (40, 3)
    return files


VALID = _valid_files()
HEADER_TOKENS = [
    b"0", b"1", b"-1", b"3", b"99999999999", b"18446744073709551617", b"1e400", b"nan", b"-0", b"",
    b"x", b"X", b"y", b"z", b"vertex", b"face", b"list", b"uchar", b"int", b"double", b"char", b"float",
    b"ascii", b"binary", b"binary_compressed", b"binary_big_endian", b"F", b"I", b"U", b"8", b"rgb", b"_",
    b"end_header", b"DATA", b"POINTS", b"\x1b[31m", b"\xff\xfe", b"(1, 2)", b"{'descr': '<c16'}",
]  # fmt: skip


def _header_end(data: bytes) -> int:
    for marker in (b"end_header\n", b"DATA binary_compressed\n", b"DATA binary\n", b"DATA ascii\n"):
        at = data.find(marker)
        if at >= 0:
            return at + len(marker)
    return min(len(data), 128)  # text and npy: the first line(s) act as the header


@st.composite
def damaged(draw):
    """(variant, format, damaged bytes): one or a few random damages of a valid file."""
    variant = draw(st.sampled_from(sorted(VALID)))
    fmt, data = VALID[variant]
    for _ in range(draw(st.integers(1, 3))):
        kind = draw(st.sampled_from(["truncate", "flip", "insert", "header-token", "header-line", "append"]))
        if not data:
            break
        if kind == "truncate":
            data = data[: draw(st.integers(0, len(data) - 1))]
        elif kind == "flip":
            at = draw(st.integers(0, len(data) - 1))
            data = data[:at] + bytes([data[at] ^ draw(st.integers(1, 255))]) + data[at + 1 :]
        elif kind == "insert":
            at = draw(st.integers(0, len(data)))
            data = data[:at] + draw(st.binary(min_size=1, max_size=8)) + data[at:]
        elif kind == "append":
            data = data + draw(st.sampled_from([b"x", b"\n", b"\0" * 7, b"1 2 3\n", b"\xff" * 9]))
        else:  # edit the header: a token, or a whole line dropped or doubled
            end = _header_end(data)
            lines = data[:end].split(b"\n")
            i = draw(st.integers(0, max(0, len(lines) - 2)))
            if kind == "header-token":
                words = lines[i].split(b" ")
                j = draw(st.integers(0, len(words) - 1))
                words[j] = draw(st.sampled_from(HEADER_TOKENS))
                lines[i] = b" ".join(words)
            elif draw(st.booleans()):
                del lines[i]
            else:
                lines.insert(i, lines[i])
            data = b"\n".join(lines) + data[end:]
    return variant, fmt, data


def _check_parse(fmt: str, data: bytes) -> None:
    """A cloud (finite float64, matching fields) or an EscapeError with one printable line."""
    try:
        xyz, fields = cloud_io._parse(data, "fuzzed", fmt)
        xyz, fields = cloud_io._finite_rows(xyz, fields, "fuzzed")
    except EscapeError as err:
        message = str(err)
        assert message.startswith("fuzzed"), message
        assert message.isprintable(), repr(message)
        return
    assert xyz.dtype == np.float64 and xyz.ndim == 2 and xyz.shape[1] == 3 and len(xyz) >= 1
    assert np.isfinite(xyz).all()
    for values in fields.values():
        assert values.shape == (len(xyz),)


@FUZZ
@given(damaged())
def test_damaged_files_parse_or_fail_cleanly(case):
    _, fmt, data = case
    _check_parse(fmt, data)


@FUZZ
@given(variant=st.sampled_from(sorted(VALID)), data=st.data())
def test_every_truncation_fails_cleanly(variant, data):
    fmt, valid = VALID[variant]
    cut = data.draw(st.integers(0, len(valid) - 1))
    _check_parse(fmt, valid[:cut])


@settings(max_examples=60, deadline=None, derandomize=True)
@given(st.binary(min_size=1, max_size=300), st.sampled_from(["ply", "pcd", "xyz", "npy", "las", "laz"]))
def test_garbage_fails_cleanly(garbage, fmt):
    _check_parse(fmt, garbage)


@settings(max_examples=40, deadline=None, derandomize=True)
@given(st.binary(min_size=1, max_size=300))
def test_garbage_npz_names_npz(garbage):
    """A damaged .npz is reported as an .npz (a .npy inside one is still read)."""
    try:
        cloud_io._parse(garbage, "g.npz", "npz")
    except EscapeError as err:
        assert ".npz" in str(err) or ".npy" in str(err) and garbage.startswith(b"\x93NUMPY"), str(err)


@FUZZ
@given(arrays(np.float64, st.tuples(st.integers(1, 30), st.just(3)), elements=st.floats(-1e6, 1e6)),
       st.sampled_from(["xyz", "txt", "pts", "csv"]), st.booleans())
def test_every_text_cloud_written_is_taken_from_a_folder(cloud, fmt, with_fields):
    """`looks_like_text_cloud` (the folder filter) never skips a text cloud escape writes, nor others' headers."""
    from escape_cli.io.text import looks_like_text_cloud

    fields = {"intensity": np.arange(len(cloud), dtype=np.float64)} if with_fields else {}
    data = cloud_io.text.serialize_text(cloud, fields, fmt=fmt)
    assert looks_like_text_cloud(data)
    assert looks_like_text_cloud(data[:64])  # the head of a big file, cut mid-line
    if fmt in ("xyz", "txt"):  # (csv has a names line of its own, pts starts with its count)
        assert looks_like_text_cloud(b'"X","Y","Z"\n' + data)  # PDAL's names line


@pytest.mark.parametrize("text", [
    b"Software License Agreement (BSD License)\n\nCopyright (c) 2009\n",
    b"MIT License\n\nPermission is hereby granted, free of charge\n",
    b"Scans of the lab\nTaken in May\n",
    b"1 2\n3 4\n",
    b"x y z\nhello world again\n",
])
def test_text_that_is_no_cloud_is_not_taken_from_a_folder(text):
    from escape_cli.io.text import looks_like_text_cloud

    assert not looks_like_text_cloud(text)


# ----------------------------------------------------------------------------- through the CLI


def _run_and_check(tmp_path, variant: str, data: bytes, argv_after: list) -> None:
    """Run the CLI on a damaged file; the promises hold whatever the outcome."""
    fmt = VALID[variant][0]
    folder = tmp_path / f"run{abs(hash(data)) % 10**8}"
    folder.mkdir()
    source = folder / f"in.{fmt}"
    source.write_bytes(data)
    output = folder / "out.ply"
    result = run_escape(argv_after[0], source, "-o", output, *argv_after[1:])
    assert result.exit_code in (0, 1, 2), result.stderr
    assert "Traceback" not in result.stderr and "internal error" not in result.stderr, result.stderr
    assert source.read_bytes() == data  # the input is never changed
    leftovers = sorted(p.name for p in folder.iterdir())
    if result.exit_code == 0:
        assert leftovers == sorted([source.name, output.name])
        assert len(cloud_io.read_points(output)) >= 1
    else:
        assert leftovers == [source.name], leftovers  # no partial output, no temporary
        lines = result.stderr_lines
        assert len(lines) == 1 and lines[0].startswith("escape: error: ") and lines[0].isprintable(), result.stderr


@settings(max_examples=CLI_EXAMPLES, deadline=None, derandomize=True, suppress_health_check=list(HealthCheck))
@given(damaged())
def test_cli_anchors_on_damaged_files(tmp_path_factory, case):
    variant, _, data = case
    _run_and_check(tmp_path_factory.mktemp("anchors"), variant, data, ["anchors"])


@settings(max_examples=6, deadline=None, derandomize=True, suppress_health_check=list(HealthCheck))
@given(damaged())
def test_cli_complete_on_damaged_files(tmp_path_factory, tiny_model, case):
    variant, _, data = case
    _run_and_check(tmp_path_factory.mktemp("complete"), variant, data, ["complete", "--model", tiny_model, "--points", "300"])


# ----------------------------------------------------------------------------- round trips

WRITE_VARIANTS = [
    ("ply", True), ("ply", False), ("pcd", True), ("pcd", False),
    ("xyz", True), ("txt", True), ("pts", True), ("csv", True), ("npy", True), ("npz", True),
]  # fmt: skip
KEEPS_FIELDS = {"ply", "pcd", "xyz", "txt", "pts", "csv", "npz"}
coordinates = st.floats(min_value=-1e150, max_value=1e150, allow_nan=False, allow_infinity=False)


@st.composite
def clouds(draw):
    n = draw(st.integers(1, 30))
    points = draw(arrays(np.float64, (n, 3), elements=coordinates))
    residual = draw(arrays(np.float64, (n,), elements=st.floats(-1e300, 1e300, allow_nan=False, allow_infinity=False)))
    return points, {"residual": residual}


@settings(max_examples=40, deadline=None, derandomize=True, suppress_health_check=list(HealthCheck))
@given(cloud=clouds(), variant=st.sampled_from(WRITE_VARIANTS), exact=st.booleans())
def test_valid_clouds_round_trip_through_every_writer_and_reader(tmp_path_factory, cloud, variant, exact):
    points, fields = cloud
    fmt, binary = variant
    path = tmp_path_factory.mktemp("round") / f"c.{fmt}"
    dtype = np.float64 if exact else np.float32
    cloud_io.write_points(path, points, fields=fields, binary=binary, coordinate_dtype=dtype)
    back, back_fields = cloud_io.read_point_fields(path)
    assert back.shape == points.shape and np.isfinite(back).all()
    if exact or cloud_io.common.storage_dtype(points) == np.float64:
        np.testing.assert_array_equal(back, points)
    else:  # float32 in the file: the same float32 values
        np.testing.assert_array_equal(back.astype(np.float32), points.astype(np.float32))
    if fmt in KEEPS_FIELDS:
        got, want = back_fields["residual"], fields["residual"]
        if cloud_io.common.storage_dtype(want) == np.float64:
            np.testing.assert_array_equal(got, want)
        else:
            np.testing.assert_array_equal(got.astype(np.float32), want.astype(np.float32))


@settings(max_examples=20, deadline=None, derandomize=True, suppress_health_check=list(HealthCheck))
@given(cloud=clouds(), compressed=st.booleans())
def test_valid_clouds_round_trip_through_las_within_its_scale(tmp_path_factory, cloud, compressed):
    """LAS stores integers on a grid it chooses for the cloud: back within half a grid step."""
    points, _ = cloud
    points = points / max(1.0, float(np.abs(points).max())) * 1e4  # LAS grids hold about 2**31 steps per axis
    path = tmp_path_factory.mktemp("las") / ("c.laz" if compressed else "c.las")
    cloud_io.write_points(path, points)
    back = cloud_io.read_points(path)
    layout = cloud_io.las.layout_for(points)
    assert back.shape == points.shape
    assert np.all(np.abs(back - points) <= 0.5 * layout.scales + 1e-9 * np.abs(points).max())
