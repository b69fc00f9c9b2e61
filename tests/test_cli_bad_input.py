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
    return ["anchors", _ply_file(tmp), "--json", "--k", "3"], "--k: must be at least 4, got 3"


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


def case_garbage_npz(tmp):
    (tmp / "g.npz").write_bytes(bytes(range(256)) * 2)
    return ["anchors", tmp / "g.npz", "--json"], "g.npz: not a .npz file (no zip archive signature)"


def case_decode_residuals_to_npy(tmp):
    distances, anchors = _encoded(tmp)
    fields = "ply, pcd, xyz, txt, pts, csv, npz, las, laz, h5"
    return ["decode", distances, "-a", anchors, "-o", tmp / "o.npy", "--residuals"], f"keeps fields ({fields}); npy holds"


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


# --- an output is never an input, --overwrite or not (issue 21, item 1)


def case_anchors_output_is_the_input(tmp):
    src = _ply_file(tmp)
    return ["anchors", src, "-o", src, "--overwrite"], "in.ply is also an input: escape never writes over its inputs"


def case_anchors_output_is_a_symlink_to_the_input(tmp):
    src = _ply_file(tmp)
    (tmp / "link.ply").symlink_to(src)
    return ["anchors", src, "-o", tmp / "link.ply", "--overwrite"], "link.ply is the same file as the input"


def case_anchors_output_is_a_hard_link_to_the_input(tmp):
    src = _ply_file(tmp)
    os.link(src, tmp / "hard.ply")
    return ["anchors", src, "-o", tmp / "hard.ply", "--overwrite"], "hard.ply is the same file as the input"


def case_anchors_output_is_the_input_by_another_path(tmp):
    src = _ply_file(tmp)
    (tmp / "sub").mkdir()
    return ["anchors", src, "-o", tmp / "sub" / ".." / "in.ply", "--overwrite"], "is the same file as the input"


def case_encode_anchors_out_is_the_input(tmp):
    src = _ply_file(tmp)
    return ["encode", src, "-o", tmp / "d.npy", "--anchors-out", src, "--overwrite"], "in.ply is also an input"


def case_encode_both_outputs_the_same_file(tmp):
    return ["encode", _ply_file(tmp), "-o", tmp / "d.npy", "--anchors-out", tmp / "d.npy"], "--output and --anchors-out name the same file"


def case_decode_output_is_the_anchors(tmp):
    distances, anchors = _encoded(tmp)
    return ["decode", distances, "-a", anchors, "-o", anchors, "--overwrite"], "d.anchors.ply is also an input"


def case_decode_output_is_the_distances(tmp):
    distances, anchors = _encoded(tmp)
    return ["decode", distances, "-a", anchors, "-o", distances, "--overwrite"], "d.npy is also an input"


def case_average_checkpoints_output_is_an_input(tmp):
    for name in ("a.pt", "b.pt"):
        (tmp / name).write_bytes(b"not loaded: refused before")
    return ["average-checkpoints", tmp / "a.pt", tmp / "b.pt", "-o", tmp / "a.pt", "--overwrite"], "a.pt is also an input"


def case_export_onnx_output_is_a_symlink_to_the_checkpoint(tmp):
    (tmp / "run.pt").write_bytes(b"not loaded: refused before")
    (tmp / "model.onnx").symlink_to(tmp / "run.pt")
    return ["export-onnx", tmp / "run.pt", "-o", tmp / "model.onnx", "--overwrite"], "model.onnx is the same file as the input"


def case_eval_json_is_the_model_metadata(tmp):
    (tmp / "m.onnx").write_bytes(b"x")
    (tmp / "m.json").write_text('{"k": 8, "input_points": 8, "output_points": 8}')
    return ["eval", "--root", tmp, "--model", tmp / "m.onnx", "--json-out", tmp / "m.json", "--overwrite"], "m.json is also an input"


def case_eval_save_inside_the_dataset(tmp):
    (tmp / "data").mkdir()
    return ["eval", "--root", tmp / "data", "--save", tmp / "data" / "out"], "is inside the input"


def case_train_out_is_the_data(tmp):
    pytest.importorskip("torch")
    (tmp / "data").mkdir()
    return ["train", "--data", tmp / "data", "--out", tmp / "data"], "is the dataset folder"


def case_train_init_is_a_checkpoint_the_run_writes(tmp):
    pytest.importorskip("torch")
    (tmp / "data").mkdir()
    (tmp / "run").mkdir()
    (tmp / "run" / "best.pt").write_bytes(b"weights")
    return ["train", "--data", tmp / "data", "--out", tmp / "run", "--init", tmp / "run" / "best.pt"], "a checkpoint this run would overwrite"


# --- outputs and models checked before any work (item 7)


def case_output_folder_is_a_file(tmp):
    (tmp / "f").write_text("a file")
    return ["anchors", _ply_file(tmp), "-o", tmp / "f" / "a.ply"], "f is not a directory"


def case_eval_save_under_a_file(tmp):
    (tmp / "data").mkdir()
    (tmp / "f").write_text("a file")
    return ["eval", "--root", tmp / "data", "--save", tmp / "f" / "out"], "f is not a directory"


def case_eval_model_is_a_folder(tmp):
    return ["eval", "--root", tmp, "--model", tmp], "is a folder; give the model's .onnx file"


def case_eval_model_metadata_not_json(tmp):
    (tmp / "m.onnx").write_bytes(b"x")
    (tmp / "m.json").write_text("{not json")
    return ["eval", "--root", tmp, "--model", tmp / "m.onnx"], "m.json is corrupt (not JSON"


def case_eval_model_metadata_not_an_object(tmp):
    (tmp / "m.onnx").write_bytes(b"x")
    (tmp / "m.json").write_text("[1, 2]")
    return ["eval", "--root", tmp, "--model", tmp / "m.onnx"], "a JSON object expected, got list"


def case_eval_model_metadata_bad_count(tmp):
    (tmp / "m.onnx").write_bytes(b"x")
    (tmp / "m.json").write_text('{"k": "eight", "input_points": 8, "output_points": 8}')
    return ["eval", "--root", tmp, "--model", tmp / "m.onnx"], "k must be a positive integer, got 'eight'"


def case_eval_model_not_onnx(tmp):
    return ["eval", "--root", tmp, "--model", _ply_file(tmp)], "is not an ONNX model"


def case_export_onnx_checkpoint_is_a_folder(tmp):
    return ["export-onnx", tmp, "-o", tmp / "m.onnx"], "is a folder, not a checkpoint file"


def case_export_onnx_output_folder_under_a_file(tmp):
    (tmp / "run.pt").write_bytes(b"x")
    (tmp / "f").write_text("a file")
    return ["export-onnx", tmp / "run.pt", "-o", tmp / "f" / "m.onnx"], "f is not a directory"


# --- values that must not get through (item 5)


def case_coordinates_near_1e300(tmp):
    (tmp / "big.xyz").write_text("\n".join(f"{1e300 * (i + 1)} {i} {2 * i}" for i in range(40)) + "\n")
    return ["anchors", tmp / "big.xyz", "--json"], "big.xyz: the cloud has values up to 4e+301; at most 1e+150 can be used"


def case_complex_npy(tmp):
    np.save(tmp / "c.npy", _cloud().astype(np.complex128))
    return ["anchors", tmp / "c.npy", "--json"], "c.npy holds complex numbers (complex128)"


def case_complex_distances_for_decode(tmp):
    distances, anchors = _encoded(tmp)
    np.save(tmp / "c.npy", np.load(distances).astype(np.complex64))
    return ["decode", tmp / "c.npy", "-a", anchors, "-o", tmp / "o.ply"], "holds complex numbers"


def case_decode_distances_times_1e300(tmp):
    distances, anchors = _encoded(tmp)
    np.save(tmp / "huge.npy", np.load(distances) * 1e300)
    return ["decode", tmp / "huge.npy", "-a", anchors, "-o", tmp / "o.ply"], "at most 1e+150 can be used"


def case_decode_distances_that_do_not_fit_the_anchors(tmp):
    distances, anchors = _encoded(tmp)
    np.save(tmp / "huge.npy", np.load(distances) * 1e120)
    return ["decode", tmp / "huge.npy", "-a", anchors, "-o", tmp / "o.ply"], "do not fit the anchors of"


def case_decode_negative_distances(tmp):
    distances, anchors = _encoded(tmp)
    values = np.load(distances)
    values[7, 3] = -0.25
    np.save(tmp / "neg.npy", values)
    return ["decode", tmp / "neg.npy", "-a", anchors, "-o", tmp / "o.ply"], "neg.npy: 1 negative distance in 1 of 200 rows"


# --- files other software writes (item 8) and headers that disagree with the body (item 6)


def case_ply_list_length_not_an_integer(tmp):
    (tmp / "l.ply").write_bytes(
        b"ply\nformat ascii 1.0\nelement vertex 1\nproperty list uchar float v\nproperty float x\nproperty float y\n"
        b"property float z\nend_header\n7.94 1 2 3\n"
    )
    return ["anchors", tmp / "l.ply", "--json"], "l.ply: corrupt PLY body (list length '7.94' is not an integer)"


def case_pts_count_line_disagrees(tmp):
    (tmp / "s.pts").write_text("50\n" + "".join(f"{i} {i % 7} {i % 5}\n" for i in range(40)))
    return ["anchors", tmp / "s.pts", "--json"], "s.pts: the first line declares 50 points, but 40 rows follow"


def case_binary_ply_one_byte_longer(tmp):
    path = _ply_file(tmp)
    path.write_bytes(path.read_bytes() + b"x")
    return ["anchors", path, "--json"], "in.ply: 1 byte after the end of the PLY body the header declares (vertex 200)"


def case_ascii_ply_one_line_longer(tmp):
    path = tmp / "a.ply"
    write_points(path, _cloud(), binary=False)
    path.write_bytes(path.read_bytes() + b"1 2 3\n")
    return ["anchors", path, "--json"], "a.ply: 3 values after the end of the PLY body"


def case_binary_pcd_one_byte_longer(tmp):
    path = tmp / "b.pcd"
    write_points(path, _cloud())
    path.write_bytes(path.read_bytes() + b"x")
    return ["anchors", path, "--json"], "b.pcd: 1 byte after the 200 points the header declares"


def case_ascii_pcd_more_values_than_declared(tmp):
    path = tmp / "a.pcd"
    write_points(path, _cloud(), binary=False)
    path.write_bytes(path.read_bytes() + b"1 2 3\n")
    return ["anchors", path, "--json"], "a.pcd: 3 values after the 200 points the header declares"


# --- messages stay one printable line (item 9)


def case_control_bytes_in_a_ply_header_are_escaped(tmp):
    (tmp / "g.ply").write_bytes(b"ply\nformat ascii 1.0\n\x1b[31mred\x07\nend_header\n")
    return ["anchors", tmp / "g.ply", "--json"], "corrupt PLY header at line 3: '\\x1b[31mred\\x07'"


def case_control_bytes_in_a_pcd_header_are_escaped(tmp):
    (tmp / "g.pcd").write_bytes(b"VERSION 0.7\n\x1b]0;title\x07 x\n")
    return ["anchors", tmp / "g.pcd", "--json"], "unexpected line '\\x1b]0;title\\x07 x'"


def case_control_bytes_in_a_text_cloud_are_escaped(tmp):
    (tmp / "g.xyz").write_bytes(b"1 2 \x1b[2J\n")
    return ["anchors", tmp / "g.xyz", "--json"], "'\\x1b[2J' is not a number"


CASES = {name[len("case_") :]: function for name, function in sorted(globals().items()) if name.startswith("case_")}


def _assert_one_line_error(exit_code: int, stderr: str, expected: str) -> None:
    assert exit_code not in (0, 70)
    assert "Traceback" not in stderr
    lines = stderr.splitlines()
    assert len(lines) == 1, stderr
    assert lines[0].startswith("escape: error: "), stderr
    assert expected in lines[0], lines[0]
    assert all(c.isprintable() for c in lines[0]), repr(lines[0])


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
