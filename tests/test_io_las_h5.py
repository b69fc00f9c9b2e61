"""LAS/LAZ and HDF5 clouds: round trips, the file's scale and offset, extra dimensions, float64 when needed."""

from __future__ import annotations

import re

import io as stdlib_io
import logging
import sys

import numpy as np
import pytest

from escape_cli import io as cloud_io
from escape_cli.errors import InputFileError, MissingDependencyError, PointCloudError
from escape_cli.io.common import coordinate_dtype_for
from escape_cli.io.las import layout_for, template_layout

laspy = pytest.importorskip("laspy")

UTM = np.array([512_345.0, 4_012_345.0, 87.0])  # easting, northing, height in metres


def write_laspy(path, points, *, scale=0.01, offset=(0.0, 0.0, 0.0), point_format=3, version="1.2", extra=True):
    """A LAS/LAZ file written by laspy itself (not by escape), with standard and extra dimensions."""
    header = laspy.LasHeader(point_format=point_format, version=version)
    header.scales = np.full(3, scale)
    header.offsets = np.asarray(offset, dtype=float)
    if extra:
        header.add_extra_dims([
            laspy.ExtraBytesParams(name="reflectance", type=np.float32),
            laspy.ExtraBytesParams(name="normals", type="3f8"),  # an array dimension: skipped on read
        ])
    las = laspy.LasData(header)
    las.x, las.y, las.z = points[:, 0], points[:, 1], points[:, 2]
    las.intensity = np.arange(len(points)) % 65536
    las.classification = np.full(len(points), 2)
    if extra:
        las.reflectance = np.linspace(0, 1, len(points))
    las.write(str(path))
    return laspy.read(str(path))


@pytest.fixture
def utm_scan(rng) -> np.ndarray:
    """(400, 3) float64: a 4 m object at UTM coordinates, on a 1 mm grid."""
    local = rng.uniform(-2, 2, size=(400, 3))
    return np.round(UTM + local, 3)


# ---------------------------------------------------------------- LAS / LAZ


@pytest.mark.parametrize("suffix", ["las", "laz"])
def test_reads_laspy_files_within_the_file_scale(tmp_path, utm_scan, suffix):
    path = tmp_path / f"scan.{suffix}"
    written = write_laspy(path, utm_scan, scale=0.001, offset=(512_000.0, 4_012_000.0, 0.0))
    points, fields = cloud_io.read_point_fields(path)
    assert points.dtype == np.float64 and points.shape == utm_scan.shape
    assert np.abs(points - utm_scan).max() <= 0.0005 + 1e-9  # half the file's scale
    expected = np.column_stack([written.X, written.Y, written.Z]) * 0.001 + [512_000.0, 4_012_000.0, 0.0]
    np.testing.assert_array_equal(points, expected)  # exactly X * scale + offset
    # other dimensions come back as fields; the (N, 3) extra dimension is skipped
    assert fields["classification"].tolist() == [2.0] * len(points)
    np.testing.assert_array_equal(fields["intensity"], np.arange(len(points)))
    np.testing.assert_allclose(fields["reflectance"], np.linspace(0, 1, len(points)), atol=1e-7)
    assert "normals" not in fields and not {"X", "Y", "Z", "x", "y", "z"} & set(fields)
    np.testing.assert_array_equal(cloud_io.read_points(path), points)


@pytest.mark.parametrize("suffix", ["las", "laz"])
def test_round_trip_within_the_chosen_scale(tmp_path, utm_scan, rng, suffix):
    path = tmp_path / f"cloud.{suffix}"
    fields = {"residual": rng.random(len(utm_scan)), "observed": (rng.random(len(utm_scan)) > 0.5).astype(float)}
    cloud_io.write_points(path, utm_scan, fields=fields)
    layout = layout_for(utm_scan)
    assert layout.scales.tolist() == [1e-6] * 3  # a millionth of the 4 m extent, as a power of ten
    back, back_fields = cloud_io.read_point_fields(path)
    assert np.abs(back - utm_scan).max() <= 0.5e-6 + 1e-9
    for key, values in fields.items():
        np.testing.assert_array_equal(back_fields[key], values.astype(np.float32))
    header = laspy.read(str(path)).header
    assert header.point_format.id == 6 and str(header.version) == "1.4"
    compressed = path.read_bytes()[104] & 0x80 != 0  # the point-format byte's compression bit
    assert compressed == (suffix == "laz")


def test_laz_is_compressed_and_sniffed_from_stdin(tmp_path, utm_scan, monkeypatch):
    las, laz = tmp_path / "a.las", tmp_path / "a.laz"
    cloud_io.write_points(las, utm_scan)
    cloud_io.write_points(laz, utm_scan)
    assert laz.stat().st_size < las.stat().st_size
    assert cloud_io.sniff_format(laz.read_bytes()) == "las"
    monkeypatch.setattr(sys, "stdin", stdlib_io.TextIOWrapper(stdlib_io.BytesIO(laz.read_bytes())))
    np.testing.assert_array_equal(cloud_io.read_points("-"), cloud_io.read_points(las))


def test_writing_like_a_template_keeps_its_scale_offset_and_crs(tmp_path, utm_scan, rng):
    template = tmp_path / "scan.laz"
    header = laspy.LasHeader(point_format=3, version="1.2")
    header.scales = np.full(3, 0.001)
    header.offsets = np.array([500_000.0, 4_000_000.0, 0.0])
    header.vlrs.append(laspy.VLR(user_id="LASF_Projection", record_id=2112, record_data=b"PROJCS[\"UTM 32N\"]\x00"))
    las = laspy.LasData(header)
    las.x, las.y, las.z = utm_scan.T
    las.write(str(template))
    observed = cloud_io.read_points(template)
    completed = np.concatenate([observed, UTM + rng.uniform(-2, 2, size=(100, 3))])
    out = tmp_path / "out.las"
    cloud_io.write_points(out, completed, fields={"residual": rng.random(len(completed))}, like=template)
    written = laspy.read(str(out))
    assert written.header.scales.tolist() == [0.001] * 3
    assert written.header.offsets.tolist() == [500_000.0, 4_000_000.0, 0.0]
    assert written.header.point_format.id == 3
    crs = [v for v in written.header.vlrs if v.user_id == "LASF_Projection"]
    assert len(crs) == 1 and crs[0].record_id == 2112 and b"UTM 32N" in crs[0].record_data_bytes()
    back = cloud_io.read_points(out)
    np.testing.assert_array_equal(back[: len(observed)], observed)  # the same integers: bit-identical
    assert np.abs(back - completed).max() <= 0.0005 + 1e-9


def test_template_that_is_not_las_is_ignored(tmp_path, utm_scan):
    ply = tmp_path / "scan.ply"
    cloud_io.write_points(ply, utm_scan)
    assert template_layout(ply) is None and template_layout("-") is None
    cloud_io.write_points(tmp_path / "out.las", utm_scan, like=ply)
    assert laspy.read(str(tmp_path / "out.las")).header.scales.tolist() == [1e-6] * 3


def test_template_offset_out_of_range_keeps_the_scale(tmp_path, utm_scan, caplog):
    template = tmp_path / "origin.las"
    write_laspy(template, np.zeros((3, 3)) + [1.0, 2.0, 3.0], scale=0.001, extra=False)  # offset 0
    out = tmp_path / "out.las"
    with caplog.at_level(logging.WARNING, logger="escape"):
        cloud_io.write_points(out, utm_scan, like=template)  # 4e6 / 0.001 > 2^31
    assert "out of range" in caplog.text
    header = laspy.read(str(out)).header
    assert header.scales.tolist() == [0.001] * 3 and header.offsets[1] != 0
    assert np.abs(cloud_io.read_points(out) - utm_scan).max() <= 0.0005 + 1e-9


def test_fields_named_like_las_dimensions_fill_them(tmp_path, utm_scan):
    path = tmp_path / "c.las"
    n = len(utm_scan)
    cloud_io.write_points(path, utm_scan, fields={"intensity": np.arange(n, dtype=float), "classification": np.full(n, 6.0)})
    las = laspy.read(str(path))
    assert las.intensity.tolist() == list(range(n)) and set(np.asarray(las.classification).tolist()) == {6}
    assert [d.name for d in las.point_format.extra_dimensions] == []
    with pytest.raises(PointCloudError, match="intensity"):
        cloud_io.write_points(tmp_path / "bad.las", utm_scan, fields={"intensity": np.full(n, -1.5)})


@pytest.mark.parametrize("damage", ["truncated", "garbage"])
def test_broken_las_is_one_error(tmp_path, utm_scan, damage):
    path = tmp_path / "b.laz"
    cloud_io.write_points(path, utm_scan)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2] if damage == "truncated" else b"LASF" + b"\x00" * 300)
    with pytest.raises(InputFileError, match=r"^.*b\.laz: corrupt or truncated LAS/LAZ file") as err:
        cloud_io.read_points(path)
    assert "\n" not in str(err.value)


def _hostile(data: bytes, offset: int, fmt: str, value: int) -> bytes:
    import struct

    out = bytearray(data)
    struct.pack_into(fmt, out, offset, value)
    return bytes(out)


@pytest.mark.parametrize(
    ("suffix", "damage", "expected"),
    [
        (".las", "point count 2**36 (LAS 1.4 field)", "truncated LAS file (68719476736 points"),
        (".las", "legacy point count 2**32 - 1", "truncated LAS file (4294967295 points"),
        (".las", "2**32 - 1 VLRs", "4294967295 VLRs declared"),
        (".las", "point data past the end", "corrupt LAS header (point data at byte"),
        (".laz", "point count 2**36 (LAS 1.4 field)", "corrupt LAZ header (68719476736 points declared"),
        (".laz", "2**32 - 1 chunks", "corrupt LAZ chunk table (4294967295 chunks declared"),
        (".laz", "chunks of 2**32 - 2 points", "corrupt LAZ header (chunks of 4294967294 points"),
    ],
)
def test_hostile_las_counts_are_refused_before_anything_is_allocated(tmp_path, utm_scan, suffix, damage, expected):
    """Counts the file cannot hold would make laspy or lazrs reserve gigabytes (or abort): refused from the header."""
    import struct

    path = tmp_path / f"h{suffix}"
    cloud_io.write_points(path, utm_scan)
    data = path.read_bytes()
    header_size, point_offset = struct.unpack_from("<HI", data, 94)
    if damage.startswith("point count"):
        data = _hostile(data, 247, "<Q", 2**36)
    elif damage.startswith("legacy"):
        data = _hostile(_hostile(data, 247, "<Q", 0), 107, "<I", 2**32 - 1)
    elif damage.endswith("VLRs"):
        data = _hostile(data, 100, "<I", 2**32 - 1)
    elif damage == "point data past the end":
        data = _hostile(data, 96, "<I", len(data) + 10)
    elif damage.endswith("chunks"):
        table = struct.unpack_from("<q", data, point_offset)[0]
        data = _hostile(data, table + 4, "<I", 2**32 - 1)
    else:  # the chunk size in the laszip VLR (record data after the VLR's 54-byte header, at +12)
        data = _hostile(data, header_size + 54 + 12, "<I", 2**32 - 2)
    path.write_bytes(data)
    with pytest.raises(InputFileError, match=re.escape(expected)) as err:
        cloud_io.read_points(path)
    assert "\n" not in str(err.value)


# ---------------------------------------------------------------- float64 where the coordinates need it


def test_float32_kept_near_the_origin_float64_far_from_it(rng):
    local = rng.uniform(-0.5, 0.5, size=(100, 3))
    assert coordinate_dtype_for(local) == np.float32
    assert coordinate_dtype_for(local + 30.0) == np.float32  # a car 30 m from a LiDAR
    assert coordinate_dtype_for(local + UTM) == np.float64
    assert coordinate_dtype_for(np.zeros((1, 3))) == np.float32
    assert coordinate_dtype_for(np.array([[5.0, 0.0, 0.0]])) == np.float64  # one point: no extent to compare


@pytest.mark.parametrize(("fmt", "marker"), [("ply", b"property double x"), ("pcd", b"SIZE 8 8 8"), ("xyz", None),
                                             ("npy", None), ("npz", None)])
def test_utm_coordinates_survive_every_writer(tmp_path, utm_scan, fmt, marker):
    path = tmp_path / f"utm.{fmt}"
    cloud_io.write_points(path, utm_scan + 1e-4)  # sub-millimetre detail: float32 would keep 0.25-0.5 m
    if marker:
        assert marker in path.read_bytes()[:400]
    np.testing.assert_array_equal(cloud_io.read_points(path), utm_scan + 1e-4)


def test_small_clouds_are_still_written_as_float32(tmp_path, rng):
    path = tmp_path / "small.ply"
    cloud_io.write_points(path, rng.uniform(-0.5, 0.5, size=(10, 3)))
    assert b"property float x" in path.read_bytes()[:200]


# ---------------------------------------------------------------- HDF5


def test_h5_round_trip_and_the_usual_dataset_names(tmp_path, utm_scan, rng):
    h5py = pytest.importorskip("h5py")
    path = tmp_path / "cloud.h5"
    residual = rng.random(len(utm_scan))
    cloud_io.write_points(path, utm_scan, fields={"residual": residual})
    points, fields = cloud_io.read_point_fields(path)
    np.testing.assert_array_equal(points, utm_scan)  # float64 kept: UTM magnitudes
    np.testing.assert_array_equal(fields["residual"], residual.astype(np.float32))
    assert cloud_io.sniff_format(path.read_bytes()) == "h5"
    pcn = tmp_path / "pcn.h5"  # PCN / Completion3D h5 files: one (2048, 3) dataset named 'data'
    with h5py.File(pcn, "w") as handle:
        handle["data"] = utm_scan[:, :3].astype(np.float32) - UTM.astype(np.float32)
        handle["label"] = np.arange(3)
    assert cloud_io.read_points(pcn).shape == utm_scan.shape


def test_h5_batches_of_clouds_are_refused_with_their_shape(tmp_path):
    h5py = pytest.importorskip("h5py")
    path = tmp_path / "mvp.h5"
    with h5py.File(path, "w") as handle:  # the MVP layout: (B, N, 3) batches
        handle["incomplete_pcds"] = np.zeros((4, 2048, 3), dtype=np.float32)
        handle["labels"] = np.zeros(4)
    with pytest.raises(InputFileError, match=r"incomplete_pcds \(4, 2048, 3\)"):
        cloud_io.read_points(path)


def test_h5_without_h5py_names_the_extra(tmp_path, monkeypatch):
    path = tmp_path / "x.h5"
    path.write_bytes(b"\x89HDF\r\n\x1a\n" + b"\x00" * 100)
    monkeypatch.setitem(sys.modules, "h5py", None)  # as if it were not installed
    with pytest.raises(MissingDependencyError, match=r"reading \.h5 files needs h5py.*pip install 'escape-cli\[h5\]'"):
        cloud_io.read_points(path)
