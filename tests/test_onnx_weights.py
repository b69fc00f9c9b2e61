"""Recovering torch weights from an exported model, and fine-tuning from an `.onnx`."""

from __future__ import annotations

import json

import pytest

torch = pytest.importorskip("torch")

from escape_cli.errors import ModelError  # noqa: E402
from escape_cli.nn.export import export_onnx  # noqa: E402
from escape_cli.nn.onnx_weights import state_dict_from_onnx  # noqa: E402
from escape_cli.nn.checkpoint import load_checkpoint_model  # noqa: E402
from escape_cli.nn.train import Trainer, TrainOptions  # noqa: E402
from tests_support import with_moving_refiners, write_tiny_checkpoint, write_tiny_pcn_tree  # noqa: E402


@pytest.fixture()
def exported(tmp_path):
    net = write_tiny_checkpoint(tmp_path / "tiny.pt", seed=3)
    export_onnx(tmp_path / "tiny.pt", tmp_path / "tiny.onnx")
    return net, tmp_path / "tiny.onnx"


def test_every_parameter_comes_back_bit_exact(exported):
    net, onnx_path = exported
    recovered = state_dict_from_onnx(onnx_path, net.config)
    original = net.state_dict()
    assert set(recovered) == set(original)
    for name, value in original.items():
        assert torch.equal(recovered[name], value), name


def test_onnx_loads_like_a_checkpoint_with_its_lineage(tmp_path):
    net = write_tiny_checkpoint(tmp_path / "tiny.pt", seed=1)
    state = torch.load(tmp_path / "tiny.pt", weights_only=False)
    state.update(step=7, elapsed=12.5, lineage=[{"checkpoint": "a.pt", "steps": 3, "train_seconds": 1.0}])
    state["options"].update(lr=2e-4, xyz_weight=3.0, recall_weight=2.0)
    torch.save(state, tmp_path / "tiny.pt")
    export_onnx(tmp_path / "tiny.pt", tmp_path / "tiny.onnx")
    model, loaded = load_checkpoint_model(tmp_path / "tiny.onnx")
    assert model.config == net.config and not model.training
    assert loaded["step"] == 7 and loaded["elapsed"] == 12.5
    assert loaded["options"]["lr"] == 2e-4 and loaded["options"]["xyz_weight"] == 3.0
    assert loaded["options"]["recall_weight"] == 2.0
    assert [run["steps"] for run in loaded["lineage"]] == [3]


def test_a_graph_of_another_network_is_refused(exported, tmp_path):
    _, onnx_path = exported
    meta_path = onnx_path.with_suffix(".json")
    meta = json.loads(meta_path.read_text())
    meta["config"]["dim"] = 48  # the metadata no longer matches the graph
    meta["sha256"] = None
    meta_path.write_text(json.dumps(meta))
    with pytest.raises(ModelError, match="shape|configuration"):
        load_checkpoint_model(onnx_path)


def test_a_file_that_is_not_onnx_is_a_clear_error(tmp_path):
    write_tiny_checkpoint(tmp_path / "tiny.pt")
    export_onnx(tmp_path / "tiny.pt", tmp_path / "tiny.onnx")
    (tmp_path / "tiny.onnx").write_bytes(b"not a model at all")
    with pytest.raises(ModelError, match="cannot read"):
        load_checkpoint_model(tmp_path / "tiny.onnx")


def test_training_can_start_from_an_exported_model(tmp_path):
    root = tmp_path / "pcn"
    write_tiny_pcn_tree(root)
    net = write_tiny_checkpoint(tmp_path / "tiny.pt", seed=2)
    export_onnx(tmp_path / "tiny.pt", tmp_path / "tiny.onnx")
    options = TrainOptions(
        data=str(root), out=str(tmp_path / "run"), config="tiny", epochs=1, batch=2, warmup_steps=1,
        gt_points=512, coarse_gt_points=128, fold_subset=4, workers=1, xyz_val_samples=2, val_limit=4,
        max_steps=2, init=str(tmp_path / "tiny.onnx"),
    )
    trainer = Trainer(options)
    for name, value in net.state_dict().items():
        assert torch.equal(trainer.model.state_dict()[name], value), name
    trainer.run()
    meta = export_onnx(tmp_path / "run" / "last.pt", tmp_path / "tuned.onnx")
    assert [run["checkpoint"] for run in meta["training"]["initialised_from"]] == [str(tmp_path / "tiny.onnx")]


def test_a_refined_network_comes_back_from_its_export(tmp_path):
    from escape_cli.nn.config import get_preset
    from escape_cli.nn.model import EscapeNet

    torch.manual_seed(5)
    config = get_preset("tiny-refine")
    net = with_moving_refiners(EscapeNet(config).eval())  # so parity tests the offsets
    write_tiny_checkpoint(tmp_path / "r.pt")
    state = torch.load(tmp_path / "r.pt", weights_only=False)
    torch.save({**state, "model": net.state_dict(), "config": config.to_dict(),
                "options": {**state["options"], "config": "tiny-refine"}}, tmp_path / "r.pt")
    export_onnx(tmp_path / "r.pt", tmp_path / "r.onnx")
    recovered = state_dict_from_onnx(tmp_path / "r.onnx", config)
    for name, value in net.state_dict().items():
        assert torch.equal(recovered[name], value), name
    model, _ = load_checkpoint_model(tmp_path / "r.onnx")  # checks onnxruntime parity
    assert len(model.refine) == 2
    import onnx

    output = onnx.load(str(tmp_path / "r.onnx")).graph.output[0]
    dims = [d.dim_value or d.dim_param for d in output.type.tensor_type.shape.dim]
    assert dims == ["batch", config.output_points, config.anchors]  # static, so metadata checks can see it
