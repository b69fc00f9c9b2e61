"""The shipped model (package data in src/escape_cli/models/): metadata, size, and completion of every real scan."""

from __future__ import annotations

import json

import numpy as np
import pytest

from conftest import REPO, realdata_clouds, realdata_id

MODEL = REPO / "src" / "escape_cli" / "models" / "escape-small.onnx"

pytestmark = pytest.mark.skipif(not MODEL.exists(), reason=f"no shipped model at {MODEL}")


def test_model_card_and_metadata():
    meta = json.loads(MODEL.with_suffix(".json").read_text())
    assert MODEL.stat().st_size < 50e6
    assert meta["k"] == 8 and meta["input_points"] == 2048
    assert meta["training"]["train_objects"] > 0 and meta["validation"]
    assert (REPO / "models" / "README.md").exists()  # the model card stays beside the curve
    assert meta["frame"]["kind"] == "partial"  # trained in the scan's own frame: units do not matter
    assert meta["frame"]["rows"] > 0 and meta["frame"]["radius"] > 0
    assert meta["output_points"] == 16384


@pytest.mark.parametrize("path", realdata_clouds(), ids=realdata_id)
def test_network_output_is_never_negative_on_real_scans(path, realdata_dir):
    from escape_cli.core.anchors import select_anchors
    from escape_cli.core.encoding import distance_matrix
    from escape_cli.core.normalize import network_input
    from escape_cli.inference import load_model
    from escape_cli.io import read_points

    net = load_model(str(MODEL))
    net_in = network_input(read_points(path), net.input_points, net.frame)
    anchors = select_anchors(net_in.observed, **net.anchors.to_dict())
    assert net.predict(distance_matrix(net_in.rows, anchors.points).astype(np.float32)[None]).min() >= 0.0


def test_network_output_is_never_negative_on_random_inputs():
    from escape_cli.inference import load_model

    net = load_model(str(MODEL))
    rng = np.random.default_rng(0)
    shape = (2, net.input_points, net.k)
    for inputs in (rng.random(shape), rng.random(shape) * 20.0, np.zeros(shape), rng.normal(size=shape) * 3.0):
        assert net.predict(inputs.astype(np.float32)).min() >= 0.0


def test_shipped_model_is_the_default(monkeypatch):
    from escape_cli.inference import default_model_path

    monkeypatch.delenv("ESCAPE_MODEL", raising=False)
    assert default_model_path().resolve() == MODEL.resolve()
    monkeypatch.setenv("ESCAPE_MODEL", "/elsewhere/m.onnx")
    assert str(default_model_path()) == "/elsewhere/m.onnx"


@pytest.mark.parametrize("path", realdata_clouds(), ids=realdata_id)
def test_completes_every_real_scan(path, realdata_dir, tmp_path):
    from cli_runner import run_escape
    from escape_cli.io import read_points

    out = tmp_path / "out.ply"
    res = run_escape("complete", path, "-o", out, "--residuals")
    assert res.exit_code == 0, res.stderr
    points = read_points(out)
    summary = json.loads(res.stderr_lines[-1])
    assert points.shape == (summary["points"], 3) and np.all(np.isfinite(points))
    # 16384 predicted rows; a scan of fewer than 2048 distinct points repeats network rows, whose copies are dropped
    assert len(points) == min(16384, summary["available_points"])
    if len(np.unique(read_points(path), axis=0)) >= 2048:
        assert len(points) == 16384
    assert len(np.unique(points, axis=0)) == len(points), "no repeated points"
    cloud = read_points(path)
    # the output stays in the input's frame and units: same place, comparable size
    extent = np.ptp(cloud, axis=0).max()
    assert np.linalg.norm(points.mean(axis=0) - cloud.mean(axis=0)) < 2 * extent
    assert np.ptp(points, axis=0).max() < 5 * extent


def test_shipped_model_is_equivariant_end_to_end():
    from escape_cli import complete
    from escape_cli.io import read_points
    from escape_cli.core.metrics import chamfer_l1
    from escape_cli.core.rotations import random_rotation

    cloud = read_points(REPO / "examples" / "chair.pcd")
    base = complete(cloud).points
    rng = np.random.default_rng(5)
    for _ in range(3):
        r, t = random_rotation(rng), rng.normal(scale=2.0, size=3)
        moved = complete((cloud @ r.T + t)[rng.permutation(len(cloud))]).points
        assert chamfer_l1(moved, base @ r.T + t) < 1e-4
