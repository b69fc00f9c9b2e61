"""The CLI stays light: `--help` imports no numeric library, runtime commands never import torch."""

from __future__ import annotations

import subprocess
import sys

from conftest import REPO


def run_python(code: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, cwd=REPO)


def test_help_imports_no_heavy_library():
    res = run_python(
        "import sys\n"
        "from escape_cli.cli.main import app\n"
        "heavy = [m for m in ('numpy', 'scipy', 'open3d', 'onnxruntime', 'torch') if m in sys.modules]\n"
        "print(heavy)\n"
    )
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == "[]"


def test_runtime_commands_do_not_import_torch(tmp_path, tiny_model):
    scan = REPO / "examples" / "chair.pcd"
    code = f"""
import sys
from escape_cli.cli.main import main
commands = [
    ["anchors", {str(scan)!r}, "-o", {str(tmp_path / 'a.ply')!r}],
    ["encode", {str(scan)!r}, "-o", {str(tmp_path / 'd.npy')!r}],
    ["decode", {str(tmp_path / 'd.npy')!r}, "--anchors", {str(tmp_path / 'd.anchors.ply')!r}, "-o", {str(tmp_path / 'r.ply')!r}],
    ["complete", {str(scan)!r}, "-o", {str(tmp_path / 'c.ply')!r}, "--model", {str(tiny_model)!r}],
]
for argv in commands:
    sys.argv = ["escape", "-q", *argv]
    try:
        main()
    except SystemExit as exit_:
        assert not exit_.code, (argv, exit_.code)
print("torch" in sys.modules)
"""
    res = run_python(code)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == "False"


def test_version_imports_no_numeric_library():
    res = run_python(
        "import sys\n"
        "from escape_cli.cli.main import main\n"
        "sys.argv = ['escape', '--version']\n"
        "try:\n"
        "    main()\n"
        "except SystemExit:\n"
        "    pass\n"
        "print([m for m in ('numpy', 'scipy', 'onnxruntime', 'torch') if m in sys.modules], file=sys.stderr)\n"
    )
    assert res.stdout.startswith("escape "), res.stderr
    assert res.stderr.strip().endswith("[]"), res.stderr


def test_library_completion_imports_no_cli_and_only_what_it_needs(tiny_model):
    scan = REPO / "examples" / "chair.pcd"
    res = run_python(
        "import sys\n"
        "from escape_cli import complete, complete_many\n"
        "from escape_cli.io import read_points\n"
        f"cloud = read_points({str(scan)!r})\n"
        f"complete(cloud, {str(tiny_model)!r}, output_points=500)\n"
        f"complete_many([cloud, cloud], {str(tiny_model)!r}, output_points=500)\n"
        "unwanted = ('typer', 'click', 'rich', 'pydantic', 'torch', 'open3d', 'scipy.optimize', 'scipy.spatial', 'matplotlib')\n"
        "print([m for m in unwanted if m in sys.modules])\n"
    )
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip().splitlines()[-1] == "[]"


def test_complete_command_imports_only_what_it_needs(tmp_path, tiny_model):
    scan = REPO / "examples" / "chair.pcd"
    res = run_python(
        "import sys\n"
        "from escape_cli.cli.main import main\n"
        f"sys.argv = ['escape', '-q', 'complete', {str(scan)!r}, '-o', {str(tmp_path / 'c.ply')!r}, '--model', {str(tiny_model)!r}]\n"
        "try:\n"
        "    main()\n"
        "except SystemExit as exit_:\n"
        "    assert not exit_.code, exit_.code\n"
        "unwanted = ('torch', 'open3d', 'scipy.optimize', 'matplotlib', 'rich')\n"
        "print([m for m in unwanted if m in sys.modules])\n"
    )
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == "[]"
