"""The CLI's promises under hostile conditions: nothing lost, every failure one line, the right exit code.

Outputs never replace an input; outputs, models and limits are checked before any
work; a full disk, a closed pipe, Ctrl-C and a lack of memory each end in one line (or,
for a closed pipe, quietly) with a documented exit code; Python warnings stay out of
the user's terminal; onnxruntime's own logger is silenced.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
import types
import warnings
from pathlib import Path

import numpy as np
import pytest
from cli_runner import run_escape

from escape_cli.io import read_points, write_points
from tests_support import partial_cloud

ESCAPE = Path(sys.executable).with_name("escape")


@pytest.fixture
def scan(tmp_path, rng) -> Path:
    path = tmp_path / "scan.ply"
    write_points(path, partial_cloud(rng, 700))
    return path


def _one_line(result_or_text, expected: str) -> str:
    text = result_or_text if isinstance(result_or_text, str) else result_or_text.stderr
    lines = text.splitlines()
    assert len(lines) == 1 and lines[0].startswith("escape: "), text
    assert expected in lines[0], lines[0]
    return lines[0]


def _files(folder: Path) -> dict:
    return {p: p.read_bytes() for p in folder.rglob("*") if p.is_file()}


# ------------------------------------------------------------------ outputs are never inputs


@pytest.mark.parametrize("link", ["same", "symlink", "hardlink"])
def test_complete_never_writes_over_its_input(scan, tmp_path, tiny_model, link):
    target = {"same": scan, "symlink": tmp_path / "link.ply", "hardlink": tmp_path / "hard.ply"}[link]
    if link == "symlink":
        target.symlink_to(scan)
    elif link == "hardlink":
        os.link(scan, target)
    before = _files(tmp_path)
    result = run_escape("complete", scan, "-o", target, "--overwrite", "--model", tiny_model)
    assert result.exit_code == 1
    _one_line(result, "escape never writes over its inputs, with or without --overwrite")
    assert _files(tmp_path) == before


@pytest.mark.parametrize("command", ["complete", "anchors"])
def test_a_symlinked_output_is_written_through(scan, tmp_path, tiny_model, command):
    """--overwrite of a symlink replaces what it points to, as a shell redirection would; the link stays."""
    (tmp_path / "real.ply").write_text("old\n")
    link = tmp_path / "link.ply"
    link.symlink_to(tmp_path / "real.ply")
    extra = ["--model", tiny_model, "--points", "256"] if command == "complete" else []
    result = run_escape(command, scan, "-o", link, "--overwrite", *extra)
    assert result.exit_code == 0, result.stderr
    assert link.is_symlink() and os.readlink(link) == str(tmp_path / "real.ply")
    assert len(read_points(tmp_path / "real.ply")) == (256 if command == "complete" else 8)


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no named pipes here")
@pytest.mark.parametrize("overwrite", [[], ["--overwrite"]])
def test_a_named_pipe_output_is_written_into_not_replaced(scan, tmp_path, overwrite):
    import stat
    import threading

    fifo = tmp_path / "pipe.ply"
    os.mkfifo(fifo)
    received = []
    reader = threading.Thread(target=lambda: received.append(fifo.read_bytes()), daemon=True)
    reader.start()
    result = run_escape("anchors", scan, "-o", fifo, *overwrite)
    reader.join(timeout=30)
    assert result.exit_code == 0, result.stderr
    assert stat.S_ISFIFO(os.stat(fifo).st_mode)  # still the pipe, not a file put in its place
    assert received and received[0].startswith(b"ply\n") and len(received[0]) > 100


@pytest.mark.skipif(not hasattr(os, "mknod") or os.geteuid() != 0, reason="making device nodes needs root")
@pytest.mark.parametrize("overwrite", [[], ["--overwrite"]])
def test_a_character_device_output_is_written_into_not_replaced(scan, tmp_path, tiny_model, overwrite):
    """`-o /dev/null` discards the output (here a null device made in tmp_path), with or without --overwrite."""
    import stat

    null = tmp_path / "null"
    os.mknod(null, 0o666 | stat.S_IFCHR, os.makedev(1, 3))
    for argv in (["anchors", scan], ["complete", scan, "--model", tiny_model, "--points", "256"]):
        result = run_escape(*argv, "-o", null, "--format", "ply", *overwrite)
        assert result.exit_code == 0, result.stderr
        assert stat.S_ISCHR(os.stat(null).st_mode)


@pytest.mark.skipif(not hasattr(os, "mknod") or os.geteuid() != 0, reason="making device nodes needs root")
def test_a_block_device_output_is_refused(scan, tmp_path):
    import stat

    disk = tmp_path / "disk"
    os.mknod(disk, 0o600 | stat.S_IFBLK, os.makedev(7, 0))
    result = run_escape("anchors", scan, "-o", disk, "--format", "ply", "--overwrite")
    assert result.exit_code == 1
    _one_line(result, "it is a block device, not a file")
    assert stat.S_ISBLK(os.stat(disk).st_mode)


def test_complete_anchors_out_is_never_an_input(scan, tmp_path, tiny_model):
    result = run_escape("complete", scan, "-o", tmp_path / "o.ply", "--anchors-out", scan, "--overwrite", "--model", tiny_model)
    _one_line(result, "scan.ply is also an input")
    assert not (tmp_path / "o.ply").exists()


def test_batch_into_its_own_folder_is_refused_before_any_file(tmp_path, rng, tiny_model):
    folder = tmp_path / "scans"
    folder.mkdir()
    for name in ("a", "b"):
        write_points(folder / f"{name}.ply", partial_cloud(rng, 300))
    before = _files(tmp_path)
    result = run_escape("complete", folder, "-o", folder, "--overwrite", "--model", tiny_model)
    _one_line(result, "is also an input")
    assert _files(tmp_path) == before


def test_writer_guard_refuses_a_file_read_in_the_same_command(tmp_path, rng):
    """The last line of defence: inside guard_inputs no write replaces a file that was read."""
    from escape_cli.errors import OutputFileError
    from escape_cli.io.files import guard_inputs

    path = tmp_path / "a.ply"
    write_points(path, rng.normal(size=(20, 3)))
    before = path.read_bytes()
    with guard_inputs():
        points = read_points(path)
        with pytest.raises(OutputFileError, match="is one of the inputs"):
            write_points(path, points * 2, overwrite=True)
    assert path.read_bytes() == before
    write_points(path, points * 2, overwrite=True)  # a library caller outside the CLI may
    assert path.read_bytes() != before


# ------------------------------------------------------------------ checks before any work


def _forbid(monkeypatch, module: str, name: str) -> None:
    def called(*args, **kwargs):
        raise AssertionError(f"{module}.{name} ran before the output was checked")

    monkeypatch.setattr(f"{module}.{name}", called)


@pytest.mark.parametrize(
    ("argv", "module", "name"),
    [
        (["anchors", "{scan}", "-o", "{tmp}/missing/a.ply"], "escape_cli.core.anchors", "select_anchors"),
        (["encode", "{scan}", "-o", "{tmp}/missing/d.npy"], "escape_cli.core.anchors", "select_anchors"),
        (["encode", "{scan}", "-o", "{tmp}/e.npy", "--anchors-out", "{tmp}/missing/a.ply"], "escape_cli.core.anchors", "select_anchors"),
        (["decode", "{tmp}/d.npy", "-a", "{tmp}/d.anchors.ply", "-o", "{tmp}/missing/o.ply"], "escape_cli.core.reconstruction", "reconstruct"),
        (["render", "{scan}", "-o", "{tmp}/missing/r.png"], "escape_cli.io", "read_point_fields"),
        (["eval", "--root", "{tmp}/data", "--json-out", "{tmp}/missing/r.json"], "escape_cli.inference", "load_model"),
        (["eval", "--root", "{tmp}/data", "--save", "{file}/out"], "escape_cli.inference", "load_model"),
        (["export-onnx", "{file}", "-o", "{tmp}/f/m.onnx"], "escape_cli.nn.export", "export_onnx"),
        (["export-onnx", "{scan}", "-o", "{file}/m.onnx"], "escape_cli.nn.export", "export_onnx"),
    ],
)
def test_unwritable_output_is_reported_before_the_work(scan, tmp_path, monkeypatch, argv, module, name):
    if module.startswith("escape_cli.nn"):
        pytest.importorskip("torch")
    (tmp_path / "f").write_text("a file, not a folder")
    assert run_escape("encode", scan, "-o", tmp_path / "d.npy").exit_code == 0
    _forbid(monkeypatch, module, name)
    filled = [a.format(scan=scan, tmp=tmp_path, file=tmp_path / "f") for a in argv]
    result = run_escape(*filled)
    assert result.exit_code == 1
    _one_line(result, "cannot write")


def test_permission_denied_on_the_output_folder(scan, tmp_path, monkeypatch):
    """As root chmod cannot make a folder unwritable: the check asks os.access, so ask it to say no."""
    import escape_cli.io.files as files

    monkeypatch.setattr(files.os, "access", lambda path, mode: False)
    _forbid(monkeypatch, "escape_cli.core.anchors", "select_anchors")
    result = run_escape("anchors", scan, "-o", tmp_path / "a.ply")
    _one_line(result, f"cannot write {tmp_path / 'a.ply'}: permission denied (directory {tmp_path})")


def test_absurd_points_are_refused_before_reading(tmp_path, tiny_model):
    result = run_escape("complete", tmp_path / "not-even-there.ply", "-o", tmp_path / "o.ply", "--points", "100000000",
                        "--model", tiny_model)
    assert result.exit_code == 2
    _one_line(result, "--points 100000000 is more than tiny.onnx can produce: at most 1280 (1024 predicted and up to 256 observed points)")


def test_default_points_fit_a_small_model(scan, tmp_path, tiny_model):
    result = run_escape("complete", scan, "-o", tmp_path / "o.ply", "--model", tiny_model)
    assert result.exit_code == 0, result.stderr
    assert len(read_points(tmp_path / "o.ply")) <= 1280


@pytest.mark.parametrize("what", ["folder", "not onnx", "not json"])
def test_bad_model_path_is_reported_before_reading(tmp_path, what):
    if what == "folder":
        model = tmp_path
    elif what == "not onnx":
        model = tmp_path / "m.ply"
        model.write_text("ply\n")
    else:
        model = tmp_path / "m.onnx"
        model.write_bytes(b"\x08\x07")
        (tmp_path / "m.json").write_bytes(b"\x00\xff garbage")
    result = run_escape("complete", tmp_path / "not-there.ply", "-o", tmp_path / "o.ply", "--model", model)
    expected = {"folder": "is a folder; give the model's .onnx file", "not onnx": "is not an ONNX model",
                "not json": "m.json is corrupt (not JSON"}[what]  # fmt: skip
    _one_line(result, expected)


@pytest.mark.parametrize("batch", [False, True], ids=["one scan", "a folder"])
@pytest.mark.parametrize("damage", ["garbage, no checksum", "checksum mismatch"])
def test_a_model_onnxruntime_refuses_fails_in_one_line_and_writes_nothing(scan, tmp_path, tiny_model, batch, damage):
    """One scan prepares itself while the session builds: a refused model still ends in one line, nothing written."""
    import json

    model = tmp_path / "model" / "m.onnx"
    model.parent.mkdir()
    meta = json.loads(tiny_model.with_suffix(".json").read_text())
    if damage == "garbage, no checksum":
        meta.pop("sha256", None)
        model.write_bytes(b"\x08\x07 not a protobuf model" * 64)
    else:
        model.write_bytes(tiny_model.read_bytes()[:-100])  # truncated: the checksum in the metadata differs
    model.with_suffix(".json").write_text(json.dumps(meta))
    out = tmp_path / "out"
    out.mkdir()
    if batch:
        (tmp_path / "in").mkdir()
        for name in ("a.ply", "b.ply"):
            (tmp_path / "in" / name).write_bytes(scan.read_bytes())
        result = run_escape("complete", tmp_path / "in", "-o", out, "--model", model)
    else:
        result = run_escape("complete", scan, "-o", out / "o.ply", "--model", model)
    assert result.exit_code == 1
    _one_line(result, "cannot load model" if damage == "garbage, no checksum" else "is corrupt: its checksum does not match")
    assert _files(out) == {}


@pytest.mark.parametrize(
    ("edit", "expected"),
    [
        ({"k": 3}, "k is 3, but the network's input partial_distances is (B, 256, 8)"),
        ({"input_points": 10**12}, "input_points is 1000000000000, but the network's input partial_distances is (B, 256, 8)"),
        ({"output_points": 7}, "output_points is 7, but the network's output distances is (B, 1024, 8)"),
        ({"input_name": "points"}, "input_name is 'points', but the network's inputs are partial_distances"),
        ({"output_name": "points"}, "output_name is 'points', but the network's outputs are distances, coarse"),
        ({"anchors": {"k": 3}}, "anchors.k is 3, but k is 8"),
        ({"anchors": {"method": "bogus"}}, "bad anchor settings: the anchor method must be one of"),
        ({"frame": {"kind": "partial", "rows": 0, "radius": 0.28}}, "bad frame record"),
        ({"frame": "scan"}, "frame must be absolute or a partial-frame record"),
    ],
    ids=["k", "input_points", "output_points", "input_name", "output_name", "anchors.k", "anchors.method", "frame rows", "frame"],
)
@pytest.mark.parametrize("batch", [False, True], ids=["one scan", "a folder"])
def test_metadata_that_disagrees_with_the_network_is_one_line_before_any_scan_is_read(
    scan, tmp_path, tiny_model, monkeypatch, edit, expected, batch
):
    import json

    model = tmp_path / "model" / "m.onnx"
    model.parent.mkdir()
    model.write_bytes(tiny_model.read_bytes())
    meta = json.loads(tiny_model.with_suffix(".json").read_text())
    edit = {key: {**meta[key], **value} if key == "anchors" else value for key, value in edit.items()}
    model.with_suffix(".json").write_text(json.dumps({**meta, **edit}))
    if batch:
        (tmp_path / "scans").mkdir()
        for name in ("a.ply", "b.ply"):
            (tmp_path / "scans" / name).write_bytes(scan.read_bytes())
    _forbid(monkeypatch, "escape_cli.io", "read_point_fields")
    inputs, output = (tmp_path / "scans", tmp_path / "out") if batch else (scan, tmp_path / "out" / "o.ply")
    (tmp_path / "out").mkdir()
    result = run_escape("complete", inputs, "-o", output, "--model", model)
    assert result.exit_code == 1
    _one_line(result, f"model metadata {model.with_suffix('.json')}: {expected}")
    assert _files(tmp_path / "out") == {}


# ------------------------------------------------------------------ the machine fails, not escape


def test_a_read_only_file_system_is_named(scan, tmp_path, monkeypatch):
    """As the folder check asks os.access and statvfs, make them say what a read-only mount says."""
    import escape_cli.io.files as files

    monkeypatch.setattr(files.os, "access", lambda path, mode: False)
    monkeypatch.setattr(files.os, "statvfs", lambda path: types.SimpleNamespace(f_flag=os.ST_RDONLY))
    result = run_escape("anchors", scan, "-o", tmp_path / "a.ply")
    _one_line(result, f"cannot write {tmp_path / 'a.ply'}: {tmp_path} is on a read-only file system")


def test_a_file_the_file_system_refuses_to_create_is_said_why(tmp_path):
    import errno

    from escape_cli.io.files import _why_not_created

    assert _why_not_created(OSError(errno.EROFS, "Read-only file system"), tmp_path) == f"{tmp_path} is on a read-only file system"
    assert _why_not_created(PermissionError(errno.EACCES, "Permission denied"), tmp_path).startswith(f"{tmp_path} takes no new files")
    assert _why_not_created(OSError(errno.ENOSPC, "No space left on device"), tmp_path) == "No space left on device"


@pytest.mark.skipif(not Path("/proc/self").exists(), reason="needs a /proc file system")
@pytest.mark.parametrize("command", ["anchors", "complete"])
def test_an_output_in_proc_says_why_it_cannot_be_written(scan, tiny_model, command):
    extra = ["--model", tiny_model] if command == "complete" else []
    result = run_escape(command, scan, "-o", "/proc/out.ply", *extra)
    assert result.exit_code == 1
    _one_line(result, "/proc takes no new files (a proc file system)")




@pytest.mark.skipif(not Path("/dev/full").exists(), reason="no /dev/full on this system")
@pytest.mark.parametrize("extra", [["-o", "-"], ["--json"]])
def test_full_disk_under_stdout_is_one_line(scan, extra):
    with open("/dev/full", "wb") as full:
        done = subprocess.run([str(ESCAPE), "anchors", str(scan), *extra], stdout=full, stderr=subprocess.PIPE, text=True, timeout=120)
    assert done.returncode == 1
    _one_line(done.stderr, "escape: error: cannot write to stdout: No space left on device")


def test_memory_error_is_one_line(scan, monkeypatch):
    def no_memory(*args, **kwargs):
        raise MemoryError

    monkeypatch.setattr("escape_cli.core.anchors.select_anchors", no_memory)
    result = run_escape("anchors", scan, "--json")
    assert result.exit_code == 1
    _one_line(result, "escape: error: out of memory")


def test_python_warnings_are_debug_lines(scan, monkeypatch):
    import escape_cli.core.anchors as anchors_module

    original = anchors_module.select_anchors

    def noisy(*args, **kwargs):
        warnings.warn("overflow encountered in multiply", RuntimeWarning)
        return original(*args, **kwargs)

    monkeypatch.setattr(anchors_module, "select_anchors", noisy)
    quiet = run_escape("anchors", scan, "--json")
    assert quiet.exit_code == 0 and "overflow" not in quiet.stderr, quiet.stderr
    loud = run_escape("-vv", "anchors", scan, "--json")
    assert loud.exit_code == 0
    assert any(line.startswith("escape: DEBUG: RuntimeWarning: overflow encountered") for line in loud.stderr_lines), loud.stderr


def test_onnxruntime_logger_is_silenced_before_the_session(monkeypatch, tmp_path):
    model = tmp_path / "model.onnx"
    model.write_bytes(b"not checked: no metadata gives a checksum")
    calls = []
    fake = types.SimpleNamespace(
        set_default_logger_severity=lambda level: calls.append(("severity", level)),
        SessionOptions=lambda: types.SimpleNamespace(add_session_config_entry=lambda key, value: None),
        InferenceSession=lambda *args, **kwargs: calls.append(("session", args[0])) or "session",
    )
    monkeypatch.setitem(sys.modules, "onnxruntime", fake)
    from escape_cli.inference import _session

    assert _session(str(model), 0) == "session"
    assert calls == [("severity", 3), ("session", model.read_bytes())]  # the bytes read (and checked) once


# ------------------------------------------------------------------ closed pipes


def _popen(argv, **kwargs) -> subprocess.Popen:
    return subprocess.Popen([str(ESCAPE), *map(str, argv)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, **kwargs)


@pytest.mark.parametrize("argv", [["anchors", "{scan}", "-o", "-"], ["anchors", "{scan}", "--json"], ["--help"], ["complete", "--help"]])
def test_stdout_closed_before_writing_exits_141_quietly(scan, argv):
    """`escape ... | true`: the reader is gone before a byte is written."""
    process = _popen([a.format(scan=scan) for a in argv])
    process.stdout.close()
    err = process.stderr.read()
    assert process.wait(timeout=120) == 141, err
    assert err == b""


def test_stdout_closed_after_ten_bytes_exits_141_quietly(tmp_path, rng):
    """`escape encode big.ply -o - | head -c 10`: more data than a pipe holds, the reader leaves early."""
    write_points(tmp_path / "big.ply", rng.normal(size=(30000, 3)))  # 30000 x 8 float64: 1.9 MB of distances
    process = _popen(["-q", "encode", tmp_path / "big.ply", "-o", "-", "--anchors-out", tmp_path / "a.ply", "--method", "fps"])
    assert len(process.stdout.read(10)) == 10
    process.stdout.close()
    err = process.stderr.read()
    assert process.wait(timeout=300) == 141, err
    assert err == b""


# ------------------------------------------------------------------ Ctrl-C


DRIVER = r"""
import sys, time
import escape_cli.inference as inference

real_predict = inference.CompletionModel.predict

def predict(self, x):
    print("model running", file=sys.stderr, flush=True)
    if sys.argv[1] == "sleep":
        time.sleep(120)
    for _ in range(100000):  # the interrupt arrives while onnxruntime runs
        real_predict(self, x)

inference.CompletionModel.predict = predict
from escape_cli.cli.main import main
sys.argv = ["escape", *sys.argv[2:]]
main()
"""


@pytest.mark.parametrize("how", ["sleep", "onnxruntime"])
def test_ctrl_c_while_the_model_runs(scan, tmp_path, tiny_model, how):
    out = tmp_path / "o.ply"
    process = subprocess.Popen(
        [sys.executable, "-c", DRIVER, how, "complete", str(scan), "-o", str(out), "--model", str(tiny_model)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),  # a background shell may have ignored it
    )  # fmt: skip
    try:
        assert process.stderr.readline() == b"model running\n"
        process.send_signal(signal.SIGINT)
        _, err = process.communicate(timeout=120)
    finally:
        if process.poll() is None:
            process.kill()
    assert process.returncode == 130
    assert err.decode().splitlines() == ["escape: interrupted"]
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == sorted(["scan.ply"])


def test_stdout_write_failures_name_stdout(monkeypatch):
    """An OSError other than a closed pipe on stdout is an OutputFileError naming stdout."""
    import errno

    from escape_cli.errors import OutputFileError
    from escape_cli.io.files import write_output_bytes

    class Full:
        def flush(self):
            pass

        def fileno(self):
            raise OSError(errno.ENOSPC, "No space left on device")

        @property
        def buffer(self):
            raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(sys, "stdout", Full())
    with pytest.raises(OutputFileError, match="cannot write to stdout"):
        write_output_bytes("-", b"data")


# ------------------------------------------------------------------ closed standard streams (GNU tools' way)

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "car.ply"


def _run_closed(argv, closed: tuple[int, ...], **kwargs) -> subprocess.CompletedProcess:
    """`escape ARGV` with the descriptors `closed` shut, as `>&-`, `2>&-` or `<&-` would."""
    def close():
        for fd in closed:
            os.close(fd)

    return subprocess.run([sys.executable, "-m", "escape_cli", *map(str, argv)], capture_output=True,
                          preexec_fn=close, timeout=300, **kwargs)


def test_a_closed_stderr_changes_neither_the_data_nor_the_exit_code(tmp_path, tiny_model):
    argv = ["complete", EXAMPLE, "-o", "-", "--model", tiny_model, "--points", "500"]
    normal, quiet = _run_closed(argv, ()), _run_closed(argv, (2,))
    assert normal.returncode == quiet.returncode == 0, normal.stderr
    assert normal.stderr.decode().startswith('{"input"')  # the summary goes to stderr...
    assert quiet.stdout == normal.stdout and normal.stdout.startswith(b"ply\n")  # ...never into the data
    failed = _run_closed(["complete", tmp_path / "missing.ply", "-o", "-", "--model", tiny_model], (2,))
    assert failed.returncode == 1 and failed.stdout == b""


@pytest.mark.parametrize("argv", [["--version"], ["--help"], ["anchors", "{scan}", "--json"], ["anchors", "{scan}", "-o", "-"]])
@pytest.mark.parametrize("stderr_too", [False, True], ids=["stdout closed", "both closed"])
def test_a_command_that_must_print_to_a_closed_stdout_says_so(scan, argv, stderr_too):
    done = _run_closed([a.format(scan=scan) for a in argv], (1, 2) if stderr_too else (1,))
    assert done.returncode == 1
    assert done.stderr.decode().splitlines() == ([] if stderr_too else ["escape: error: cannot write to stdout: Bad file descriptor"])


def test_a_command_with_nothing_to_print_succeeds_with_stdout_closed(scan, tmp_path, tiny_model):
    out = tmp_path / "o.ply"
    done = _run_closed(["complete", scan, "-o", out, "--model", tiny_model, "--points", "300"], (1,))
    assert done.returncode == 0, done.stderr
    assert done.stderr.decode().startswith('{"input"')
    assert len(read_points(out)) == 300
    assert sorted(p.name for p in tmp_path.iterdir()) == ["o.ply", "scan.ply"]


def test_a_closed_stdin_is_one_line(tmp_path, tiny_model):
    done = _run_closed(["complete", "-", "-o", tmp_path / "o.ply", "--model", tiny_model], (0,))
    assert done.returncode == 1
    assert done.stderr.decode().splitlines() == ["escape: error: <stdin>: cannot read (Bad file descriptor)"]


# ------------------------------------------------------------------ Ctrl-C and SIGTERM at any moment


def _handlers_installed(pid: int) -> bool:
    """Whether process `pid` catches SIGTERM: escape's first instruction has run (Python alone never catches it)."""
    if not Path(f"/proc/{pid}").exists():
        return True  # gone already: nothing to wait for
    return bool(_signal_mask(pid, "SigCgt") >> (signal.SIGTERM - 1) & 1)


def _signal_mask(pid: int, field: str) -> int:
    """The SigBlk / SigIgn / SigCgt mask of process `pid` (0 when it is gone)."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return 0
    return int(next(line for line in status.splitlines() if line.startswith(field + ":")).split()[1], 16)


def _children(pid: int) -> list[int]:
    found = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            found += [int(child) for child in (task / "children").read_text().split()]
        except OSError:
            pass
    return found


def _interrupted_at(argv, delay: float, signum=signal.SIGINT, before=None, group: bool = True) -> subprocess.CompletedProcess:
    """Run `escape ARGV`; `delay` seconds after its entry point's first instruction, call `before(pid)`
    and send `signum` to its process group (as a terminal's Ctrl-C reaches every process of the job,
    workers included)."""
    process = subprocess.Popen(
        [sys.executable, "-m", "escape_cli", *map(str, argv)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        start_new_session=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),  # a background shell may have ignored it
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 5  # (then the signal is sent anyway, and the checks say what went wrong)
        while not _handlers_installed(process.pid) and time.monotonic() < deadline:
            time.sleep(0.001)
        time.sleep(delay)
        if before is not None:
            before(process.pid)
        try:
            (os.killpg if group else os.kill)(process.pid, signum)  # or to the command alone, as `kill PID` sends it
        except ProcessLookupError:
            pass
        out, err = process.communicate(timeout=120)  # returns once every process holding the pipes is gone
    finally:
        if process.poll() is None:
            process.kill()
    return subprocess.CompletedProcess(process.args, process.returncode, out, err)


def _check_interrupted(done, signum, out_folder: Path, points: int) -> bool:
    """The promises of an interrupted run (or of one that finished first); True when it was interrupted."""
    err = done.stderr.decode()
    if done.returncode == 0:
        assert err == "", err
    else:
        assert done.returncode == 128 + signum, err
        assert err == "escape: interrupted\n", err
    leftovers = [p.name for p in out_folder.rglob("*") if p.name.endswith(".tmp")]
    assert not leftovers, leftovers
    for path in out_folder.rglob("*.ply"):  # finished outputs are whole
        assert len(read_points(path)) == points, path
    return done.returncode != 0


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="reads a process's signal handlers from /proc")
def test_an_interrupt_at_any_moment_of_one_scan_is_one_line(tmp_path):
    """From the first instruction of the entry point on: start-up imports, the model's load, the scan, the writing."""
    moments = [(signal.SIGINT, d) for d in (0.0, 0.02, 0.05, 0.1, 0.15, 0.2, 0.3, 0.5)]
    moments += [(signal.SIGTERM, d) for d in (0.0, 0.1, 0.4)]
    interrupted = 0
    for i, (signum, delay) in enumerate(moments):
        out = tmp_path / f"run{i}"
        out.mkdir()
        done = _interrupted_at(["-q", "complete", EXAMPLE, "-o", out / "car.ply", "--points", "4000"], delay, signum)
        interrupted += _check_interrupted(done, signum, out, 4000)
    assert interrupted >= len(moments) - 2  # a cold one-scan run takes longer than these moments


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_while_the_interpreter_tears_down_after_the_command_is_ignored(tmp_path, signum):
    """The interpreter puts back the default actions before tearing its modules down (open3d's take
    long): a signal then must not kill a finished command silently, with no line and no code of ours."""
    script = tmp_path / "late.py"
    script.write_text(
        "import escape_cli.interrupts as interrupts\n"
        "interrupts.install()\n"
        "import os, time\n"
        "class SignalAtTeardown:\n"
        "    def __del__(self):\n"
        f"        os.kill(os.getpid(), {int(signum)})\n"
        "        time.sleep(0.2)\n"
        "late = SignalAtTeardown()\n"
        "print('finished', flush=True)\n"
    )
    done = subprocess.run([sys.executable, str(script)], capture_output=True, timeout=60)
    assert (done.returncode, done.stdout, done.stderr) == (0, b"finished\n", b"")


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="reads a process's signal handlers from /proc")
def test_an_interrupt_in_a_worker_pool_is_one_line_and_leaves_no_worker(tmp_path):
    """Workers never see Ctrl-C (not even while their interpreter starts): the parent stops them,
    removes what they were writing and keeps what they finished."""
    scans = tmp_path / "scans"
    scans.mkdir()
    for i in range(3):
        for example in sorted(EXAMPLE.parent.glob("*.p[lc][yd]")):
            (scans / f"{example.stem}_{i}{example.suffix}").write_bytes(example.read_bytes())
    sigint = 1 << (signal.SIGINT - 1)
    workers_seen = []

    def workers_hold_sigint_back(pid):
        for child in _children(pid):  # the workers and multiprocessing's resource tracker
            assert (_signal_mask(child, "SigBlk") | _signal_mask(child, "SigIgn")) & sigint, f"worker {child} takes Ctrl-C"
            try:
                if b"spawn_main" in Path(f"/proc/{child}/cmdline").read_bytes():
                    workers_seen.append(child)
            except OSError:
                pass

    moments = [(signal.SIGINT, d) for d in (0.3, 0.9, 1.5, 3.0)] + [(signal.SIGTERM, 1.2)]
    interrupted = 0
    for i, (signum, delay) in enumerate(moments):
        out = tmp_path / f"out{i}"
        argv = ["complete", scans, "-o", out, "--workers", "2", "--json", "--points", "2000"]
        done = _interrupted_at(argv, delay, signum, before=workers_hold_sigint_back)
        interrupted += _check_interrupted(done, signum, out, 2000)
    assert interrupted >= len(moments) - 1  # a fast machine may finish the 24 files within the last moment
    assert workers_seen
    assert not [pid for pid in workers_seen if _alive(pid)]  # none left behind (killed and reaped by the parent)


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="reads a process's signal handlers from /proc")
@pytest.mark.parametrize("command", ["from-shapes", "synth"])
def test_an_interrupt_of_a_dataset_command_with_workers_is_one_line(tmp_path, command):
    """Ctrl-C at the terminal (the process group) or SIGTERM to the command alone: the workers are
    killed, nothing half-written stays, and no worker writes on or prints after the one line."""
    from escape_cli.data.pcn import read_pcd

    if command == "from-shapes":
        shapes = tmp_path / "shapes"
        shapes.mkdir()
        rng = np.random.default_rng(0)
        for i in range(80):  # about 8 s on 2 cores
            directions = rng.normal(size=(400, 3))
            np.save(shapes / f"s{i:02d}.npy", directions / np.linalg.norm(directions, axis=1, keepdims=True) * (1, 0.6, 0.4))
        argv = ["-q", "dataset", "from-shapes", shapes, "--views", "4", "--workers", "2", "-o"]
    else:
        pytest.importorskip("open3d")
        argv = ["-q", "dataset", "synth", "--train", "4", "--views", "2", "--workers", "2", "-o"]  # about 8 s
    workers_seen = []

    def note_workers(pid):
        workers_seen.extend(c for c in _children(pid) if b"spawn_main" in _cmdline(c))

    interrupted = 0
    for i, (signum, delay, group) in enumerate([(signal.SIGINT, 2.0, True), (signal.SIGTERM, 3.0, False)]):
        out = tmp_path / f"out{i}"
        done = _interrupted_at([*argv, out], delay, signum, before=note_workers, group=group)
        interrupted += _check_interrupted(done, signum, out, 0)
        written = sorted(out.rglob("*"))
        for path in out.rglob("*.pcd"):  # finished files are whole
            assert len(read_pcd(path)) > 0, path
        time.sleep(0.5)
        assert sorted(out.rglob("*")) == written  # no worker goes on writing after the command has ended
    assert interrupted >= 1
    assert workers_seen and not [pid for pid in workers_seen if _alive(pid)]


@pytest.mark.skipif(not hasattr(os, "openpty"), reason="needs a pseudo-terminal")
def test_an_interrupt_under_a_progress_bar_gives_the_terminal_its_cursor_back(tmp_path):
    """On a terminal the dataset commands draw a bar with the cursor hidden: Ctrl-C shows it again
    and ends the bar's line before the one line."""
    import pty
    import select

    shapes = tmp_path / "shapes"
    shapes.mkdir()
    rng = np.random.default_rng(0)
    for i in range(30):
        np.save(shapes / f"s{i:02d}.npy", rng.normal(size=(400, 3)) * (1, 0.6, 0.4))
    pid, fd = pty.fork()
    if pid == 0:  # the child: escape on the terminal
        os.execv(sys.executable, [sys.executable, "-m", "escape_cli", "dataset", "from-shapes", str(shapes),
                                  "-o", str(tmp_path / "out"), "--views", "2"])
    screen = b""
    deadline = time.monotonic() + 60
    try:
        while b"/30" not in screen and time.monotonic() < deadline:  # the bar is drawn
            if select.select([fd], [], [], 0.1)[0]:
                screen += os.read(fd, 1 << 16)
        os.kill(pid, signal.SIGINT)
        while True:
            try:
                chunk = os.read(fd, 1 << 16)
            except OSError:  # the terminal's other end closed: the command has ended
                break
            if not chunk:
                break
            screen += chunk
    finally:
        _, status = os.waitpid(pid, 0)
        os.close(fd)
    assert os.waitstatus_to_exitcode(status) == 130, screen[-300:]
    hidden = screen.rindex(b"\x1b[?25l")  # the bar hides the cursor...
    assert b"\x1b[?25h" in screen[hidden:], screen[-300:]  # ...and shows it again
    assert screen.endswith(b"\nescape: interrupted\r\n") or screen.endswith(b"\n\x1b[?25hescape: interrupted\r\n"), screen[-300:]
    assert not list((tmp_path / "out").rglob("*.tmp"))


def _cmdline(pid: int) -> bytes:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return b""


def _alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(") ")[1][0] != "Z"
    except (OSError, IndexError):
        return False
