"""Every bad input gives one line `escape: error: ...` on stderr, a non-zero exit, no traceback.

Each case builds its inputs in a temp folder and returns the command line; the check
also makes sure that a failed command leaves no new file behind.
"""

from __future__ import annotations

import os
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from cli_runner import run_escape

from escape_cli.io import write_array, write_points

ESCAPE = Path(sys.executable).with_name("escape")


def _cloud(n: int = 200, seed: int = 0) -> np.ndarray:
    """(n, 3) points on a unit-ish blob, well spread in 3D."""
    return np.random.default_rng(seed).normal(size=(n, 3)) * [0.3, 0.2, 0.1]


def _ply_file(tmp: Path, name: str = "in.ply", points: np.ndarray | None = None) -> Path:
    path = tmp / name
    write_points(path, _cloud() if points is None else points)
    return path


def _truncated(tmp: Path, name: str, **write_options) -> Path:
    path = tmp / name
    write_points(path, _cloud(), **write_options)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) * 2 // 3])
    return path


def _encoded(tmp: Path) -> tuple[Path, Path]:
    """An (N, 8) distance file and its anchors, made with the CLI itself."""
    _ply_file(tmp)
    assert run_escape("encode", tmp / "in.ply", "-o", tmp / "d.npy").exit_code == 0
    return tmp / "d.npy", tmp / "d.anchors.ply"


# Each case: name -> function(tmp) returning (argv, text the message must contain).
def case_missing_file(tmp):
    return ["anchors", tmp / "nope.ply", "-o", tmp / "a.ply"], "nope.ply: no such file"


def case_directory(tmp):
    (tmp / "scans.ply").mkdir()
    return ["anchors", tmp / "scans.ply", "-o", tmp / "a.ply"], "is a directory"


def case_empty_file(tmp):
    (tmp / "empty.pcd").write_bytes(b"")
    return ["encode", tmp / "empty.pcd", "-o", tmp / "d.npy"], "empty.pcd: empty file"


def case_header_only_ply_without_points(tmp):
    (tmp / "h.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\nproperty float z\nend_header\n")
    return ["anchors", tmp / "h.ply", "--json"], "h.ply: the file holds no points"


def case_header_only_ply_with_points_declared(tmp):
    (tmp / "h.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 9\nproperty float x\nproperty float y\nproperty float z\nend_header\n")
    return ["anchors", tmp / "h.ply", "--json"], "h.ply: truncated PLY body"


def case_header_only_pcd(tmp):
    (tmp / "h.pcd").write_bytes(b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 5\nHEIGHT 1\nPOINTS 5\nDATA ascii\n")
    return ["anchors", tmp / "h.pcd", "--json"], "h.pcd: truncated PCD body"


def case_pcd_header_cut_before_data(tmp):
    (tmp / "h.pcd").write_bytes(b"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4")
    return ["anchors", tmp / "h.pcd", "--json"], "no DATA line"


def case_truncated_binary_ply(tmp):
    return ["anchors", _truncated(tmp, "t.ply"), "--json"], "t.ply: truncated PLY body"


def case_truncated_ascii_ply(tmp):
    return ["anchors", _truncated(tmp, "t.ply", binary=False), "--json"], "t.ply: truncated PLY body"


def case_truncated_binary_pcd(tmp):
    return ["anchors", _truncated(tmp, "t.pcd"), "--json"], "t.pcd: truncated PCD body"


def case_truncated_compressed_pcd(tmp):
    raw = np.zeros(3 * 4 * 10, np.uint8).tobytes()
    body = struct.pack("<II", 100, len(raw)) + bytes([0x1F]) + raw[:32]  # 100 bytes announced, 33 present
    header = b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 10\nHEIGHT 1\nPOINTS 10\nDATA binary_compressed\n"
    (tmp / "c.pcd").write_bytes(header + body)
    return ["anchors", tmp / "c.pcd", "--json"], "c.pcd: truncated PCD body"


def case_garbage_bytes_as_ply(tmp):
    (tmp / "g.ply").write_bytes(np.random.default_rng(3).bytes(500))
    return ["anchors", tmp / "g.ply", "--json"], "g.ply: not a PLY file"


def case_garbage_bytes_as_xyz(tmp):
    (tmp / "g.xyz").write_bytes(b"\x00\xff\x13garbage\x01 \x02\n" * 20)
    return ["anchors", tmp / "g.xyz", "--json"], "is not a number"


def case_wrong_column_count(tmp):
    (tmp / "c.xyz").write_text("1 2 3\n4 5 6\n7 8\n")
    return ["anchors", tmp / "c.xyz", "--json"], "c.xyz: line 3 has 2 columns"


def case_two_column_text(tmp):
    (tmp / "c.txt").write_text("1 2\n4 5\n7 8\n")
    return ["anchors", tmp / "c.txt", "--json"], "need at least x y z"


def case_unknown_input_extension(tmp):
    (tmp / "scan.foo").write_text("1 2 3\n")
    return ["anchors", tmp / "scan.foo", "--json"], "unknown format '.foo' for"


def case_unknown_output_extension(tmp):
    return ["anchors", _ply_file(tmp), "-o", tmp / "a.foo"], "unknown format '.foo' for"


def case_unknown_format_option(tmp):
    return ["anchors", _ply_file(tmp), "-o", tmp / "a.ply", "--format", "obj"], "unknown format 'obj'"


def case_nan_inf_only_cloud(tmp):
    (tmp / "n.xyz").write_text("nan nan nan\ninf 1 2\n1 -inf 3\n")
    return ["anchors", tmp / "n.xyz", "--json"], "n.xyz: all 3 points have non-finite"


def case_too_few_points(tmp):
    return ["encode", _ply_file(tmp, points=_cloud(5)), "-o", tmp / "d.npy"], "in.ply:"


def case_fewer_than_four_anchors(tmp):
    return ["anchors", _ply_file(tmp), "--json", "--k", "3"], "the number of anchors) must be at least 4"


def case_all_points_identical(tmp):
    return ["anchors", _ply_file(tmp, points=np.ones((50, 3))), "--json"], "in.ply:"


def case_collinear_points(tmp):
    line = np.linspace(0, 1, 50)[:, None] * [1.0, 2.0, 3.0]
    return ["encode", _ply_file(tmp, points=line), "-o", tmp / "d.npy"], "line"


def case_collinear_anchors_for_decode(tmp):
    distances, _ = _encoded(tmp)
    write_points(tmp / "line.ply", np.linspace(0, 1, 8)[:, None] * [1.0, 1.0, 0.0])
    return ["decode", distances, "-a", tmp / "line.ply", "-o", tmp / "o.ply"], "collinear"


def case_three_coplanar_anchors_for_decode(tmp):
    write_array(tmp / "d3.npy", np.ones((10, 3)))
    write_points(tmp / "tri.ply", np.eye(3))
    return ["decode", tmp / "d3.npy", "-a", tmp / "tri.ply", "-o", tmp / "o.ply"], "at least 4 anchors"


def case_anchors_output_exists(tmp):
    (tmp / "a.ply").write_bytes(b"keep")
    return ["anchors", _ply_file(tmp), "-o", tmp / "a.ply"], "a.ply exists (use --overwrite"


def case_encode_anchors_output_exists(tmp):
    (tmp / "d.anchors.ply").write_bytes(b"keep")
    return ["encode", _ply_file(tmp), "-o", tmp / "d.npy"], "d.anchors.ply exists"


def case_decode_output_exists(tmp):
    distances, anchors = _encoded(tmp)
    (tmp / "o.ply").write_bytes(b"keep")
    return ["decode", distances, "-a", anchors, "-o", tmp / "o.ply"], "o.ply exists"


def case_output_directory_missing(tmp):
    return ["anchors", _ply_file(tmp), "-o", tmp / "no" / "a.ply"], "does not exist"


def case_corrupt_npy_for_decode(tmp):
    _, anchors = _encoded(tmp)
    data = (tmp / "d.npy").read_bytes()
    (tmp / "bad.npy").write_bytes(data[: len(data) // 2])
    return ["decode", tmp / "bad.npy", "-a", anchors, "-o", tmp / "o.ply"], "bad.npy: corrupt or truncated .npy"


def case_garbage_npy_for_decode(tmp):
    _, anchors = _encoded(tmp)
    (tmp / "bad.npy").write_bytes(b"this is no numpy file")
    return ["decode", tmp / "bad.npy", "-a", anchors, "-o", tmp / "o.ply"], "bad.npy: not a .npy file"


def case_missing_npy_for_decode(tmp):
    _, anchors = _encoded(tmp)
    return ["decode", tmp / "none.npy", "-a", anchors, "-o", tmp / "o.ply"], "none.npy: no such file"


def case_one_dimensional_distances(tmp):
    _, anchors = _encoded(tmp)
    write_array(tmp / "v.npy", np.ones(8))
    return ["decode", tmp / "v.npy", "-a", anchors, "-o", tmp / "o.ply"], "must have shape (M, K)"


def case_nan_distances(tmp):
    distances, anchors = _encoded(tmp)
    values = np.load(distances)
    values[3, 2] = np.nan
    write_array(tmp / "nan.npy", values)
    return ["decode", tmp / "nan.npy", "-a", anchors, "-o", tmp / "o.ply"], "NaN or infinite values in "


def case_distances_anchors_k_mismatch(tmp):
    distances, _ = _encoded(tmp)
    write_points(tmp / "six.ply", _cloud(6, seed=9))
    return ["decode", distances, "-a", tmp / "six.ply", "-o", tmp / "o.ply"], "8 distances per point but"


def case_decode_residuals_into_npy(tmp):
    distances, anchors = _encoded(tmp)
    return ["decode", distances, "-a", anchors, "-o", tmp / "o.npy", "--residuals"], "--residuals needs"


def case_encode_stdout_without_anchors_out(tmp):
    return ["encode", _ply_file(tmp), "-o", "-"], "give --anchors-out"


def case_encode_output_not_npy(tmp):
    return ["encode", _ply_file(tmp), "-o", tmp / "d.ply"], "name the output *.npy"


def case_anchors_without_output(tmp):
    return ["anchors", _ply_file(tmp)], "give -o OUT"


def case_empty_stdin(tmp):
    return ["anchors", "-", "--json"], "<stdin>: empty file"


def case_decode_both_from_stdin(tmp):
    return ["decode", "-", "-a", "-", "-o", tmp / "o.ply"], "cannot both come from stdin"


CASES = {name[len("case_") :]: function for name, function in sorted(globals().items()) if name.startswith("case_")}


def _assert_one_line_error(exit_code: int, stderr: str, expected: str) -> None:
    assert exit_code != 0
    assert "Traceback" not in stderr
    lines = stderr.splitlines()
    assert len(lines) == 1, stderr
    assert lines[0].startswith("escape: error: "), stderr
    assert expected in lines[0], lines[0]


@pytest.mark.parametrize("case", CASES.values(), ids=CASES.keys())
def test_bad_input_gives_one_line_error(tmp_path, case):
    argv, expected = case(tmp_path)
    before = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    result = run_escape(*argv)
    _assert_one_line_error(result.exit_code, result.stderr, expected)
    after = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    assert after == before  # nothing written, nothing changed, no temporary left


def test_unreadable_file(tmp_path):
    path = _ply_file(tmp_path)
    path.chmod(0)
    try:
        if os.access(path, os.R_OK):
            pytest.skip("running as a user (root?) whom chmod 000 does not stop from reading")
        result = run_escape("anchors", path, "--json")
        _assert_one_line_error(result.exit_code, result.stderr, "in.ply: permission denied")
    finally:
        path.chmod(0o644)


def test_overwrite_replaces_existing_output(tmp_path):
    (tmp_path / "a.ply").write_bytes(b"old")
    result = run_escape("anchors", _ply_file(tmp_path), "-o", tmp_path / "a.ply", "--overwrite")
    assert result.exit_code == 0, result.stderr
    assert (tmp_path / "a.ply").read_bytes().startswith(b"ply\n")


@pytest.mark.parametrize("case", [case_missing_file, case_garbage_bytes_as_ply, case_anchors_output_exists, case_distances_anchors_k_mismatch])
def test_console_script_one_line_errors(tmp_path, case):
    """The same through the installed `escape` executable (a real process, real exit code)."""
    argv, expected = case(tmp_path)
    done = subprocess.run([str(ESCAPE), *map(str, argv)], capture_output=True, text=True, timeout=120)
    _assert_one_line_error(done.returncode, done.stderr, expected)
    assert done.returncode == 1 and done.stdout == ""
