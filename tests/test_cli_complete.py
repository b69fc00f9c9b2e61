"""`escape complete` through the CLI: formats, stdin/stdout, batches, bad files, overwrite."""

from __future__ import annotations

import json

import numpy as np
import pytest

from cli_runner import run_escape
from escape_cli.io import read_point_fields, read_points, write_points
from tests_support import partial_cloud


@pytest.fixture
def scan(tmp_path, rng):
    path = tmp_path / "scan.ply"
    write_points(path, partial_cloud(rng, 700))
    return path


@pytest.mark.parametrize("in_fmt", ["ply", "pcd", "xyz", "npy"])
@pytest.mark.parametrize("out_fmt", ["ply", "pcd", "xyz", "npy"])
def test_round_trips_every_format(tmp_path, rng, tiny_model, in_fmt, out_fmt):
    cloud = partial_cloud(rng, 500)
    src = tmp_path / f"in.{in_fmt}"
    write_points(src, cloud)
    dst = tmp_path / f"out.{out_fmt}"
    res = run_escape("complete", src, "-o", dst, "--model", tiny_model, "--points", "1000")
    assert res.exit_code == 0, res.stderr
    out = read_points(dst)
    assert out.shape == (1000, 3)
    summary = json.loads(res.stderr_lines[-1])
    assert summary["points"] == 1000 and summary["input_points"] == 500


def test_stdin_to_stdout(scan, tiny_model):
    res = run_escape("complete", "-", "-o", "-", "--model", tiny_model, "--points", "512", stdin=scan.read_bytes())
    assert res.exit_code == 0, res.stderr
    assert res.stdout.startswith(b"ply")
    res_pcd = run_escape("complete", "-", "-o", "-", "--format", "pcd", "--model", tiny_model, stdin=scan.read_bytes())
    assert res_pcd.exit_code == 0 and b"FIELDS x y z" in res_pcd.stdout


def test_residuals_and_anchors_out(scan, tmp_path, tiny_model):
    out, anchors = tmp_path / "out.ply", tmp_path / "anchors.ply"
    res = run_escape("complete", scan, "-o", out, "--model", tiny_model, "--residuals", "--anchors-out", anchors)
    assert res.exit_code == 0, res.stderr
    points, fields = read_point_fields(out)
    assert "residual" in fields and "observed" in fields
    assert np.all(fields["residual"] >= 0) and set(np.unique(fields["observed"])) <= {0.0, 1.0}
    assert read_points(anchors).shape == (8, 3)


def test_snap_radius_option(scan, tmp_path, tiny_model):
    outs = {}
    for radius in ("0", "10"):
        out = tmp_path / f"out-{radius}.ply"
        res = run_escape("complete", scan, "-o", out, "--model", tiny_model, "--snap-radius", radius, "--json")
        assert res.exit_code == 0, res.stderr
        outs[radius] = json.loads(res.stdout)["snapped"]
    assert outs["0"] == 0 and outs["10"] > 0
    res = run_escape("complete", scan, "-o", tmp_path / "bad.ply", "--model", tiny_model, "--snap-radius", "-1")
    assert res.exit_code != 0 and not (tmp_path / "bad.ply").exists()


def test_anchor_sets_option(scan, tmp_path, tiny_model):
    one, pooled = tmp_path / "one.ply", tmp_path / "pooled.ply"
    for out, extra in ((one, []), (pooled, ["--anchor-sets", "3"])):
        res = run_escape("complete", scan, "-o", out, "--model", tiny_model, "--points", "1000", "--json", *extra)
        assert res.exit_code == 0, res.stderr
    assert json.loads(res.stdout)["available_points"] > 2 * json.loads(res.stdout)["points"]
    assert read_points(pooled).shape == read_points(one).shape == (1000, 3)
    assert not np.array_equal(read_points(pooled), read_points(one))


def test_batch_with_a_corrupt_file_completes_the_others(tmp_path, rng, tiny_model):
    folder = tmp_path / "scans"
    folder.mkdir()
    for name in ("a.ply", "b.pcd", "c.xyz"):
        write_points(folder / name, partial_cloud(rng, 400))
    (folder / "broken.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 99\n")
    before = {p.name: p.read_bytes() for p in folder.iterdir()}
    res = run_escape("complete", folder, "-o", tmp_path / "out", "--model", tiny_model, "--points", "600")
    assert res.exit_code != 0
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["a.ply", "b.ply", "c.ply"]
    errors = [line for line in res.stderr_lines if line.startswith("escape: error:")]
    assert any("broken.ply" in line for line in errors)
    assert "Traceback" not in res.stderr
    assert {p.name: p.read_bytes() for p in folder.iterdir()} == before, "inputs must never change"


def test_glob_and_workers(tmp_path, rng, tiny_model):
    for name in ("x.ply", "y.ply"):
        write_points(tmp_path / name, partial_cloud(rng, 300))
    res = run_escape("complete", str(tmp_path / "*.ply"), "-o", tmp_path / "out", "--model", tiny_model,
                     "--workers", "2", "--json", "--points", "400")
    assert res.exit_code == 0, res.stderr
    lines = [json.loads(line) for line in res.stdout.decode().splitlines()]
    assert sorted(line["input"].split("/")[-1] for line in lines) == ["x.ply", "y.ply"]


def test_refuses_to_overwrite(scan, tmp_path, tiny_model):
    out = tmp_path / "out.ply"
    out.write_bytes(b"keep me")
    res = run_escape("complete", scan, "-o", out, "--model", tiny_model)
    assert res.exit_code != 0 and "--overwrite" in res.stderr
    assert out.read_bytes() == b"keep me"
    assert run_escape("complete", scan, "-o", out, "--model", tiny_model, "--overwrite").exit_code == 0


@pytest.mark.parametrize(
    "content, message",
    [
        (b"", "empty"),
        (b"0 0 0\n1 1 1\n2 2 2\n", "distinct points"),
        (b"nan nan nan\ninf 0 0\n", "non-finite"),
    ],
)
def test_bad_clouds_give_one_line(tmp_path, tiny_model, content, message):
    src = tmp_path / "bad.xyz"
    src.write_bytes(content)
    res = run_escape("complete", src, "-o", tmp_path / "out.ply", "--model", tiny_model)
    assert res.exit_code != 0
    assert len(res.stderr_lines) == 1 and res.stderr_lines[0].startswith("escape: error:"), res.stderr
    assert message in res.stderr
    assert not (tmp_path / "out.ply").exists()


@pytest.mark.parametrize("scale", [1e-15, 1e-30, 1e-300, 1e-310])
def test_a_tiny_cloud_completes_as_the_same_cloud_at_unit_scale(tmp_path, rng, tiny_model, scale):
    """Any cloud whose points float64 tells apart: 2000 Gaussian points 1e-15 across have 2000 distinct points."""
    cloud = rng.normal(size=(2000, 3))
    np.save(tmp_path / "unit.npy", cloud)
    np.save(tmp_path / "tiny.npy", cloud * scale)
    for name in ("unit", "tiny"):
        res = run_escape("complete", tmp_path / f"{name}.npy", "-o", tmp_path / f"{name}.ply", "--model", tiny_model)
        assert res.exit_code == 0, res.stderr
    unit, tiny = read_points(tmp_path / "unit.ply"), read_points(tmp_path / "tiny.ply")
    np.testing.assert_allclose(tiny / scale, unit, rtol=0, atol=1e-6)  # the unit-scale file holds float32


def test_a_cloud_float64_cannot_tell_apart_names_its_distinct_points(tmp_path, rng, tiny_model):
    np.save(tmp_path / "flat.npy", 1.0 + rng.normal(size=(2000, 3)) * 1e-17)  # every point rounds to (1, 1, 1)
    res = run_escape("complete", tmp_path / "flat.npy", "-o", tmp_path / "o.ply", "--model", tiny_model)
    assert res.exit_code == 1
    assert res.stderr_lines == [f"escape: error: {tmp_path / 'flat.npy'}: the input has 1 distinct points; at least 16 are needed to complete it"]


def test_the_residuals_refusal_lists_the_formats_that_keep_them(scan, tmp_path, tiny_model):
    from escape_cli.formats import FIELD_FORMATS

    res = run_escape("complete", scan, "-o", tmp_path / "o.npy", "--residuals", "--model", tiny_model)
    assert res.exit_code == 1
    listed = res.stderr.split("keeps fields (")[1].split(")")[0].split(", ")
    assert listed == list(FIELD_FORMATS)
    for fmt in listed:  # and each of them does keep them
        if fmt == "h5":
            pytest.importorskip("h5py")
        out = tmp_path / f"o.{fmt}"
        done = run_escape("complete", scan, "-o", out, "--residuals", "--model", tiny_model, "--points", "300")
        assert done.exit_code == 0, (fmt, done.stderr)
        assert "residual" in read_point_fields(out)[1], fmt


def test_corrupt_or_missing_model(scan, tmp_path, tiny_model):
    res = run_escape("complete", scan, "-o", tmp_path / "o.ply", "--model", tmp_path / "none.onnx")
    assert res.exit_code != 0 and len(res.stderr_lines) == 1 and "does not exist" in res.stderr
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"garbage")
    (tmp_path / "bad.json").write_text(json.dumps({"k": 8, "input_points": 256, "output_points": 256}))
    res = run_escape("complete", scan, "-o", tmp_path / "o.ply", "--model", bad)
    assert res.exit_code != 0 and len(res.stderr_lines) == 1 and "model" in res.stderr


def test_utm_laz_scan_keeps_its_observed_points_to_the_millimetre(tmp_path, rng, tiny_model):
    """A LiDAR crop in UTM metres (x ~ 5e5, y ~ 4e6), as LAZ on a 1 mm grid, completed to LAZ and PLY."""
    laspy = pytest.importorskip("laspy")
    utm = np.array([512_345.678, 4_012_345.678, 87.5])
    scan = np.round(utm + 2.0 * partial_cloud(rng, 600), 3)  # a 2 m object
    src = tmp_path / "crop.laz"
    header = laspy.LasHeader(point_format=3, version="1.2")
    header.scales, header.offsets = np.full(3, 0.001), np.array([512_000.0, 4_012_000.0, 0.0])
    las = laspy.LasData(header)
    las.x, las.y, las.z = scan.T
    las.intensity = np.arange(len(scan))
    las.write(str(src))

    out = tmp_path / "done.laz"
    res = run_escape("complete", src, "-o", out, "--model", tiny_model, "--residuals")
    assert res.exit_code == 0, res.stderr
    points, fields = read_point_fields(out)
    observed = points[fields["observed"] == 1.0]
    assert len(observed) > 0
    gap = np.min(np.linalg.norm(observed[:, None] - scan[None], axis=2), axis=1)  # to the nearest input point
    assert gap.max() < 1e-3  # within 1 mm (on the input's own grid: exact)
    assert gap.max() < 1e-9
    written = laspy.read(str(out)).header
    assert written.scales.tolist() == [0.001] * 3 and written.offsets.tolist() == [512_000.0, 4_012_000.0, 0.0]
    predicted = points[fields["observed"] == 0.0]
    assert np.abs(predicted - scan.mean(axis=0)).max() < 50  # in the scan's frame, metres

    ply = tmp_path / "done.ply"  # float64 coordinates where float32 would lose the millimetres
    res = run_escape("complete", src, "-o", ply, "--model", tiny_model, "--residuals")
    assert res.exit_code == 0, res.stderr
    assert b"property double x" in ply.read_bytes()[:300]
    points, fields = read_point_fields(ply)
    observed = points[fields["observed"] == 1.0]
    assert np.min(np.linalg.norm(observed[:, None] - scan[None], axis=2), axis=1).max() < 1e-3


def test_utm_scan_through_the_python_api(rng, tiny_model):
    from escape_cli import complete

    utm = np.array([512_345.678, 4_012_345.678, 87.5])
    scan = utm + 2.0 * partial_cloud(rng, 600)
    result = complete(scan, tiny_model)
    observed = result.points[result.is_observed]
    assert result.points.dtype == np.float64 and len(observed) > 0
    assert np.min(np.linalg.norm(observed[:, None] - scan[None], axis=2), axis=1).max() < 1e-3
