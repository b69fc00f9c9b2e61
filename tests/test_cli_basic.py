"""`escape anchors`, `escape encode`, `escape decode`: outputs, stdin/stdout, round trips."""

from __future__ import annotations

import hashlib
import io
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from cli_runner import run_escape

from escape_cli.core.anchors import select_anchors
from escape_cli.core.encoding import distance_matrix
from escape_cli.io import read_point_fields, read_points, write_points
from escape_cli.io.ply import parse_ply

ESCAPE = Path(sys.executable).with_name("escape")


@pytest.fixture
def cloud(rng) -> np.ndarray:
    """(400, 3) float32-exact points on a bumpy ellipsoid cap: curvature varies, not planar."""
    directions = rng.normal(size=(1200, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    directions = directions[directions[:, 2] > -0.3][:400]
    points = directions * np.array([0.4, 0.3, 0.2]) * (1 + 0.05 * np.sin(7 * directions[:, :1]))
    return points.astype(np.float32).astype(np.float64)


@pytest.fixture
def cloud_file(tmp_path, cloud) -> Path:
    path = tmp_path / "in.ply"
    write_points(path, cloud)
    return path


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


# ---------------------------------------------------------------- anchors


@pytest.mark.parametrize("method", ["ball", "fps", "cluster"])
def test_anchors_writes_the_library_anchors(tmp_path, cloud, cloud_file, method):
    out = tmp_path / "a.pcd"
    result = run_escape("anchors", cloud_file, "-o", out, "--method", method, "--k", "6")
    assert result.exit_code == 0, result.stderr
    expected = select_anchors(cloud, k=6, method=method)
    np.testing.assert_array_equal(read_points(out), expected.points)  # float64 file: exact
    assert result.stderr_lines == [f"6 anchors ({method}) chosen on 400 points -> {out}"]


def test_anchors_json_without_output(cloud, cloud_file):
    result = run_escape("anchors", cloud_file, "--json", "--radius", "0.05", "--knn", "12")
    assert result.exit_code == 0, result.stderr
    report = json.loads(result.stdout)
    expected = select_anchors(cloud, radius=0.05, knn=12)
    assert report["indices"] == expected.indices.tolist()
    np.testing.assert_array_equal(report["anchors"], expected.points)
    assert (report["method"], report["k"], report["radius"], report["knn"], report["points"]) == ("ball", 8, 0.05, 12, 400)
    assert report["output"] is None
    np.testing.assert_array_equal(np.asarray(report["anchors"]), cloud[report["indices"]])


def test_anchors_json_and_file(tmp_path, cloud_file):
    out = tmp_path / "a.xyz"
    result = run_escape("anchors", cloud_file, "-o", out, "--json")
    report = json.loads(result.stdout)
    np.testing.assert_array_equal(read_points(out), report["anchors"])
    assert report["output"] == str(out)


def test_anchors_stdin_to_stdout(cloud, cloud_file):
    result = run_escape("-q", "anchors", "-", "-o", "-", stdin=cloud_file.read_bytes())
    assert result.exit_code == 0 and result.stderr == ""
    assert result.stdout.startswith(b"ply\nformat binary_little_endian")
    np.testing.assert_array_equal(parse_ply(result.stdout, "-")[0], select_anchors(cloud).points)


def test_anchors_text_stdin_ascii_stdout(cloud, tmp_path):
    text = "\n".join(" ".join(f"{v:.9g}" for v in row) for row in cloud).encode()
    result = run_escape("anchors", "-", "-o", "-", "--format", "pcd", "--ascii", stdin=text)
    assert result.exit_code == 0, result.stderr
    result.stdout.decode("ascii")
    assert b"DATA ascii" in result.stdout


def test_anchors_input_format_override(tmp_path, cloud):
    path = tmp_path / "scan.data"
    write_points(path, cloud, fmt="pcd")
    result = run_escape("anchors", path, "--input-format", "pcd", "--json")
    assert result.exit_code == 0, result.stderr


# ---------------------------------------------------------------- encode


def test_encode_writes_distances_and_anchors_beside_them(tmp_path, cloud, cloud_file):
    out = tmp_path / "d.npy"
    result = run_escape("encode", cloud_file, "-o", out, "--method", "fps")
    assert result.exit_code == 0, result.stderr
    distances = np.load(out)
    anchors = read_points(tmp_path / "d.anchors.ply")
    assert distances.dtype == np.float64 and distances.shape == (400, 8)
    np.testing.assert_array_equal(anchors, select_anchors(cloud, method="fps").points)
    np.testing.assert_array_equal(distances, distance_matrix(cloud, anchors))
    assert "encoded 400 points with 8 anchors (fps)" in result.stderr


def test_encode_anchors_out_and_stdout(tmp_path, cloud, cloud_file):
    anchors_path = tmp_path / "anchors.pcd"
    result = run_escape("encode", cloud_file, "-o", "-", "--anchors-out", anchors_path)
    assert result.exit_code == 0, result.stderr
    distances = np.load(io.BytesIO(result.stdout))
    np.testing.assert_array_equal(distances, distance_matrix(cloud, read_points(anchors_path)))


# ---------------------------------------------------------------- decode and round trips


def test_encode_decode_round_trip_through_files(tmp_path, cloud, cloud_file):
    before = _sha(cloud_file)
    assert run_escape("encode", cloud_file, "-o", tmp_path / "d.npy").exit_code == 0
    result = run_escape("decode", tmp_path / "d.npy", "--anchors", tmp_path / "d.anchors.ply", "-o", tmp_path / "out.pcd", "--residuals")
    assert result.exit_code == 0, result.stderr
    points, fields = read_point_fields(tmp_path / "out.pcd")
    assert np.abs(points - cloud).max() < 1e-6
    assert list(fields) == ["residual"] and fields["residual"].max() < 1e-6
    assert len(result.stderr_lines) == 1
    assert result.stderr.startswith("decoded 400 points from 8 anchors (batched): residual mean ")
    assert "anchors well spread" in result.stderr
    assert _sha(cloud_file) == before  # inputs untouched


def test_decode_stdin_stdout_and_scipy_solver(tmp_path, cloud, cloud_file):
    encoded = run_escape("encode", cloud_file, "-o", "-", "--anchors-out", tmp_path / "a.ply")
    fast = run_escape("-q", "decode", "-", "-a", tmp_path / "a.ply", "-o", "-", stdin=encoded.stdout)
    assert fast.exit_code == 0 and fast.stderr == ""
    points = parse_ply(fast.stdout, "-")[0]
    assert np.abs(points - cloud).max() < 1e-6
    distances = np.load(io.BytesIO(encoded.stdout))[:40]
    np.save(tmp_path / "few.npy", distances)
    reference = run_escape("decode", tmp_path / "few.npy", "-a", tmp_path / "a.ply", "-o", tmp_path / "r.npy", "--solver", "scipy")
    assert reference.exit_code == 0, reference.stderr
    np.testing.assert_allclose(np.load(tmp_path / "r.npy"), points[:40], atol=1e-6)


def test_decode_near_planar_anchors_are_reported(tmp_path, rng):
    flat = np.column_stack([rng.uniform(-0.5, 0.5, (300, 2)), rng.normal(0, 0.002, 300)])
    write_points(tmp_path / "flat.ply", flat, coordinate_dtype=np.float64)
    assert run_escape("encode", tmp_path / "flat.ply", "-o", tmp_path / "d.npy", "--method", "fps").exit_code == 0
    result = run_escape("decode", tmp_path / "d.npy", "-a", tmp_path / "d.anchors.ply", "-o", tmp_path / "o.ply")
    assert result.exit_code == 0, result.stderr
    assert "near-planar" in result.stderr


def test_shell_pipeline_round_trip(tmp_path, cloud, cloud_file):
    """The documented pipe: encode to stdout, decode from stdin, anchors through a file."""
    command = (
        f"'{ESCAPE}' encode '{cloud_file}' -o - --anchors-out a.ply"
        f" | '{ESCAPE}' decode - --anchors a.ply -o out.ply"
    )
    done = subprocess.run(command, shell=True, cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert np.abs(read_points(tmp_path / "out.ply") - cloud).max() < 1e-6
    assert [line.split()[0] for line in done.stderr.splitlines()] == ["encoded", "decoded"]


def test_console_script_reads_stdin_cloud(cloud_file):
    done = subprocess.run(
        [str(ESCAPE), "anchors", "-", "--json", "--k", "5"], input=cloud_file.read_bytes(), capture_output=True, timeout=120
    )
    assert done.returncode == 0, done.stderr
    assert len(json.loads(done.stdout)["indices"]) == 5


def test_commands_import_no_heavy_libraries_at_module_level():
    code = (
        "import sys; import escape_cli.cli.cmd_anchors, escape_cli.cli.cmd_encode, escape_cli.cli.cmd_decode; "
        "print(sorted(m for m in ('numpy', 'scipy', 'open3d') if m in sys.modules))"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.stdout.strip() == "[]", done.stderr
