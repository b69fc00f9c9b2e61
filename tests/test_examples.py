"""examples/: the bundled scans read, and the shell scripts work as written."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import REPO
from escape_cli.io import read_points, write_points
from tests_support import partial_cloud

ESCAPE = str(Path(sys.executable).parent / "escape")
EXAMPLES = sorted((REPO / "examples").glob("*.p[cl][dy]"))


def test_one_example_per_category():
    names = {p.stem for p in EXAMPLES}
    assert names == {"airplane", "cabinet", "car", "chair", "lamp", "sofa", "table", "watercraft"}
    assert {p.suffix for p in EXAMPLES} == {".ply", ".pcd"}
    for path in EXAMPLES:
        assert 200 < len(read_points(path)) < 10000


def test_pipeline_script_completes_a_folder_and_reports_a_bad_file(tmp_path, rng, tiny_model):
    scans = tmp_path / "scans"
    scans.mkdir()
    for name in ("one.ply", "two.pcd"):
        write_points(scans / name, partial_cloud(rng, 400))
    (scans / "bad.ply").write_bytes(b"ply\nbroken")
    env = {**os.environ, "ESCAPE": ESCAPE, "ESCAPE_MODEL": str(tiny_model)}
    run = subprocess.run(["bash", str(REPO / "examples" / "pipeline.sh"), str(scans), str(tmp_path / "out")],
                         env=env, capture_output=True, text=True, timeout=300)
    assert run.returncode != 0
    assert "failed:" in run.stderr and "bad.ply" in run.stderr
    for name in ("one", "two"):  # the tiny model predicts 1024 points; the 256 observed join them
        assert len(read_points(tmp_path / "out" / f"{name}.ply")) == 1024 + 256
    assert not (tmp_path / "out" / "bad.ply").exists()


@pytest.mark.skipif(not (REPO / "src" / "escape_cli" / "models" / "escape-small.onnx").exists(), reason="no shipped model")
@pytest.mark.skipif(shutil.which("bash") is None, reason="needs bash")
def test_demo_script(tmp_path):
    run = subprocess.run(["bash", str(REPO / "examples" / "demo.sh"), str(tmp_path / "demo")],
                         env={**os.environ, "ESCAPE": ESCAPE}, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    assert (tmp_path / "demo" / "completions.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert len(list((tmp_path / "demo").glob("*.ply"))) == 8
