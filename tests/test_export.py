"""ONNX export: parity with torch, metadata, dynamic batch, refusal to overwrite."""

from __future__ import annotations

import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from escape_cli.errors import EscapeError, ModelError, OutputExistsError  # noqa: E402
from escape_cli.inference import CompletionModel  # noqa: E402
from escape_cli.nn.export import export_onnx  # noqa: E402
from escape_cli.nn.parity import sample_input  # noqa: E402
from tests_support import write_tiny_checkpoint  # noqa: E402


def test_export_matches_torch(tmp_path):
    net = write_tiny_checkpoint(tmp_path / "tiny.pt")
    meta = export_onnx(tmp_path / "tiny.pt", tmp_path / "tiny.onnx")
    assert meta["onnx_parity_max_abs"] <= 1e-4
    saved = json.loads((tmp_path / "tiny.json").read_text())
    assert saved["k"] == 8 and saved["input_points"] == 256 and saved["output_points"] == 1024
    model = CompletionModel(tmp_path / "tiny.onnx")
    x = sample_input(net.config, batch=3, seed=5)  # a batch size not used in the export
    with torch.no_grad():
        want = net(torch.from_numpy(x))[0].numpy()
    got = model.predict(x)
    assert got.shape == (3, 1024, 8)
    assert np.abs(got - want).max() <= 1e-4


def test_export_refuses_to_overwrite(tmp_path):
    write_tiny_checkpoint(tmp_path / "tiny.pt")
    export_onnx(tmp_path / "tiny.pt", tmp_path / "tiny.onnx")
    with pytest.raises(OutputExistsError):
        export_onnx(tmp_path / "tiny.pt", tmp_path / "tiny.onnx")
    export_onnx(tmp_path / "tiny.pt", tmp_path / "tiny.onnx", overwrite=True)


def test_corrupt_model_is_detected(tmp_path):
    write_tiny_checkpoint(tmp_path / "tiny.pt")
    export_onnx(tmp_path / "tiny.pt", tmp_path / "tiny.onnx")
    data = bytearray((tmp_path / "tiny.onnx").read_bytes())
    data[len(data) // 2] ^= 0xFF
    (tmp_path / "tiny.onnx").write_bytes(bytes(data))
    with pytest.raises(ModelError, match="corrupt"):
        CompletionModel(tmp_path / "tiny.onnx")


def test_bad_checkpoint_is_a_clear_error(tmp_path):
    (tmp_path / "bad.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(EscapeError, match="cannot load checkpoint"):
        export_onnx(tmp_path / "bad.pt", tmp_path / "bad.onnx")
    assert not (tmp_path / "bad.onnx").exists()
