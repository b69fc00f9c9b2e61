"""`escape average-checkpoints`: snapshots during training, their weight average, export of the average."""

from __future__ import annotations

import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from escape_cli.errors import EscapeError, OutputExistsError  # noqa: E402
from escape_cli.nn.average import average_checkpoints, average_state_dicts  # noqa: E402
from escape_cli.nn.checkpoint import load_checkpoint_model  # noqa: E402
from escape_cli.nn.train import Trainer, TrainOptions  # noqa: E402
from tests_support import write_tiny_pcn_tree  # noqa: E402


@pytest.fixture(scope="module")
def snapshot_run(tmp_path_factory):
    """A tiny run that keeps a snapshot every step: (run folder, snapshot paths)."""
    root = tmp_path_factory.mktemp("pcn")
    write_tiny_pcn_tree(root)
    out = tmp_path_factory.mktemp("run")
    options = TrainOptions(
        data=str(root), out=str(out), config="tiny", epochs=1, batch=2, warmup_steps=1, gt_points=512,
        coarse_gt_points=128, fold_subset=4, workers=1, xyz_val_samples=2, val_limit=4, max_steps=3, snapshot_every=1,
    )
    Trainer(options).run()
    return out, sorted((out / "snapshots").glob("step*.pt"))


def test_training_keeps_weight_snapshots_without_optimizer_state(snapshot_run):
    out, snaps = snapshot_run
    assert [p.name for p in snaps] == ["step0000001.pt", "step0000002.pt", "step0000003.pt"]
    state = torch.load(snaps[0], map_location="cpu", weights_only=False)
    assert state["step"] == 1 and "optimizer" not in state and "model" in state


def test_average_is_the_elementwise_mean_and_keeps_the_latest_metadata(snapshot_run, tmp_path):
    _, snaps = snapshot_run
    out = tmp_path / "avg.pt"
    state = average_checkpoints(list(reversed(snaps)), out)
    assert state["step"] == 3 and [e["step"] for e in state["averaged_from"]] == [1, 2, 3]
    models = [load_checkpoint_model(p)[0].state_dict() for p in snaps]
    averaged = load_checkpoint_model(out)[0].state_dict()
    for name, value in averaged.items():
        if value.is_floating_point():
            want = sum(m[name].double() for m in models) / 3
            np.testing.assert_allclose(value.double().numpy(), want.numpy(), rtol=1e-6, atol=1e-7)
    assert state["metrics"]["val_xyz_cd_l1_x1000"] > 0  # scored on the run's own val split
    assert "optimizer" not in torch.load(out, map_location="cpu", weights_only=False)


def test_average_of_one_network_with_itself_is_that_network():
    sd = {"w": torch.randn(3, 4), "n": torch.tensor(7)}
    out = average_state_dicts([sd, {k: v.clone() for k, v in sd.items()}])
    assert torch.equal(out["w"], sd["w"]) and int(out["n"]) == 7


def test_average_refuses_mismatched_networks_overwrites_and_single_inputs(snapshot_run, tmp_path):
    _, snaps = snapshot_run
    with pytest.raises(EscapeError, match="different networks"):
        average_state_dicts([{"a": torch.zeros(2)}, {"b": torch.zeros(2)}])
    with pytest.raises(EscapeError, match="at least two"):
        average_checkpoints(snaps[:1], tmp_path / "x.pt")
    (tmp_path / "taken.pt").write_bytes(b"keep")
    with pytest.raises(OutputExistsError):
        average_checkpoints(snaps, tmp_path / "taken.pt")
    assert (tmp_path / "taken.pt").read_bytes() == b"keep"


def test_average_then_export_through_the_cli(snapshot_run, tmp_path):
    from typer.testing import CliRunner

    from escape_cli.cli.main import app

    _, snaps = snapshot_run
    runner = CliRunner()
    res = runner.invoke(app, ["average-checkpoints", *map(str, snaps), "-o", str(tmp_path / "avg.pt"), "--no-validate"])
    assert res.exit_code == 0, res.output
    assert "mean of 3 checkpoints (steps 1-3)" in res.output
    res = runner.invoke(app, ["export-onnx", str(tmp_path / "avg.pt"), "-o", str(tmp_path / "m.onnx")])
    assert res.exit_code == 0, res.output
    meta = json.loads((tmp_path / "m.json").read_text())
    assert [e["step"] for e in meta["training"]["averaged_from"]] == [1, 2, 3]
    assert meta["validation"] == {}  # not validated: no numbers copied from a single snapshot


def test_corrupt_checkpoint_is_a_one_line_error(snapshot_run, tmp_path):
    from cli_runner import run_escape

    _, snaps = snapshot_run
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint")
    res = run_escape("average-checkpoints", str(snaps[0]), str(bad), "-o", str(tmp_path / "avg.pt"))
    assert res.exit_code != 0 and len(res.stderr_lines) == 1, res.stderr
    assert res.stderr.startswith("escape: error: cannot load checkpoint")
    assert not (tmp_path / "avg.pt").exists()
