"""`escape train` on a tiny PCN tree: checkpoints, curve, resume, export."""

from __future__ import annotations

import csv
import json
from dataclasses import replace

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from escape_cli.nn.train import Trainer, TrainOptions  # noqa: E402
from tests_support import write_tiny_pcn_tree  # noqa: E402


@pytest.fixture(scope="module")
def tiny_tree(tmp_path_factory):
    root = tmp_path_factory.mktemp("pcn")
    write_tiny_pcn_tree(root)
    return root


def options(tiny_tree, out, **kw) -> TrainOptions:
    base = dict(
        data=str(tiny_tree), out=str(out), config="tiny", epochs=3, batch=2, warmup_steps=2, gt_points=512,
        coarse_gt_points=128, fold_subset=4, workers=1, xyz_val_samples=2, val_limit=4,
    )
    base.update(kw)
    return TrainOptions(**base)


def test_training_writes_checkpoints_and_curve(tiny_tree, tmp_path):
    trainer = Trainer(options(tiny_tree, tmp_path / "run"))
    metrics = trainer.run()
    assert trainer.step == 3 * trainer.steps_per_epoch
    for name in ("last.pt", "best.pt", "curve.csv", "options.json"):
        assert (tmp_path / "run" / name).exists(), name
    rows = list(csv.DictReader((tmp_path / "run" / "curve.csv").open()))
    assert len(rows) == 3  # one validation per epoch
    assert {"val_dmcd_x1000", "val_xyz_cd_l1_x1000", "train_loss_x1000"} <= set(rows[0])
    assert metrics["val_xyz_cd_l1_x1000"] > 0
    assert trainer.input_radius is None  # the partial frame needs no dataset radius
    assert json.loads((tmp_path / "run" / "options.json").read_text())["frame"] == {"rows": 256, "radius": 0.28}


def test_resume_continues_where_it_stopped(tiny_tree, tmp_path):
    out = tmp_path / "run"
    first = Trainer(options(tiny_tree, out, max_steps=2))
    first.run()
    assert first.step == 2
    resumed = Trainer(options(tiny_tree, out, epochs=4), resume=True)
    assert resumed.step == 2
    resumed.run()
    assert resumed.step == 4 * resumed.steps_per_epoch


def test_train_and_export_through_the_cli(tiny_tree, tmp_path):
    """Through `main()`, as the console script runs: progress and messages on stderr, nothing on stdout."""
    from cli_runner import run_escape

    out = tmp_path / "run"
    res = run_escape("train", "--data", tiny_tree, "--out", out, "--config", "tiny",
                     "--epochs", "1", "--batch", "2", "--workers", "1", "--val-limit", "4")
    assert res.exit_code == 0, res.stderr
    assert res.stdout == b"" and "done: step" in res.stderr
    res = run_escape("-q", "export-onnx", out / "best.pt", "-o", tmp_path / "m.onnx")
    assert res.exit_code == 0, res.stderr
    assert res.stdout == b"" and res.stderr == ""
    res = run_escape("-q", "train", "--data", tiny_tree, "--out", tmp_path / "quiet", "--config", "tiny",
                     "--epochs", "1", "--batch", "2", "--workers", "1", "--val-limit", "4", "--max-steps", "1")
    assert res.exit_code == 0 and res.stdout == b"" and res.stderr == ""  # -q: no progress bar, no summary
    meta = json.loads((tmp_path / "m.json").read_text())
    assert meta["training"]["train_objects"] == 4
    assert meta["frame"] == {"kind": "partial", "rows": 256, "radius": 0.28}
    assert meta["validation"]["val_xyz_cd_l1_x1000"] > 0


def test_init_starts_from_weights_with_a_fresh_schedule_and_xyz_loss(tiny_tree, tmp_path):
    import torch

    first = Trainer(options(tiny_tree, tmp_path / "a", max_steps=2))
    first.run()
    tuned = Trainer(options(tiny_tree, tmp_path / "b", max_steps=2, init=str(tmp_path / "a" / "last.pt"), xyz_weight=1.0))
    assert tuned.step == 0
    for name, value in first.model.state_dict().items():
        assert torch.equal(value, tuned.model.state_dict()[name]), name
    tuned.run()
    assert tuned.step == 2 and (tmp_path / "b" / "best.pt").exists()
    from escape_cli.nn.export import export_onnx

    meta = export_onnx(tmp_path / "b" / "last.pt", tmp_path / "m.onnx")
    assert meta["training"]["xyz_weight"] == 1.0
    assert [run["steps"] for run in meta["training"]["initialised_from"]] == [2]
    assert meta["training"]["total_steps"] == 4


def test_init_refuses_another_preset(tiny_tree, tmp_path):
    from escape_cli.errors import EscapeError

    Trainer(options(tiny_tree, tmp_path / "a", max_steps=1)).run()
    with pytest.raises(EscapeError, match="network"):
        Trainer(options(tiny_tree, tmp_path / "b", config="small", init=str(tmp_path / "a" / "last.pt")))


def test_training_on_two_datasets_joins_their_train_splits(tiny_tree, tmp_path):
    other = tmp_path / "other"
    write_tiny_pcn_tree(other, seed=9, objects=1, views=1)
    one = Trainer(options(tiny_tree, tmp_path / "one"))
    both = Trainer(replace(options(tiny_tree, tmp_path / "both"), extra_data=(str(other),)))
    extra = Trainer(options(other, tmp_path / "extra"))
    assert len(both.train_data) == len(one.train_data) + len(extra.train_data)
    assert len(both.train_data.completes) == len(one.train_data.completes) + len(extra.train_data.completes)
    i = len(one.train_data)  # the first sample of the second dataset keeps its own complete cloud
    np.testing.assert_array_equal(both.train_data.complete_in_frame(i), extra.train_data.complete_in_frame(0))
    assert len(both.val_data) == len(one.val_data)  # validation: the first dataset's val split
    both.opt = replace(both.opt, max_steps=1)
    both.run()
    saved = torch.load(tmp_path / "both" / "last.pt", weights_only=False)
    assert TrainOptions.from_dict(saved["options"]).extra_data == (str(other),)
